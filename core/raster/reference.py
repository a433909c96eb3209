"""Dense PyTorch twin of the rasterizer, for tests only: every Gaussian at every pixel.

Written to be obviously correct rather than fast (memory is ``O(pixels x Gaussians)``): full
matrices (``world_to_cam = inv(cam_to_world)``, ``Sigma = R S S^T R^T``,
``Sigma' = J W Sigma W^T J^T``, ``conic = inv(Sigma' + low_pass I)``), a per-pixel depth order,
and the compositing rules spelled out with cumulative products. It follows the same
conventions and settings as :func:`core.raster.rasterize` and is differentiable by autograd, in
float64 if the inputs are.
"""

from __future__ import annotations

import torch

from core.camera import Camera
from core.raster.settings import RasterSettings


def _rotation(q: torch.Tensor) -> torch.Tensor:
    n = torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    ok = n > 1e-6
    ident = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=q.dtype).expand_as(q)
    q = torch.where(ok, q / torch.where(ok, n, torch.ones_like(n)), ident)
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    r = torch.stack([
        torch.stack([w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        torch.stack([2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)], -1),
        torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z], -1),
    ], -2)
    return r


def reference_rasterize(means, quats, scales, opacities, colors, normals, albedo, roughness, metallic,
                        camera: Camera, background=None, settings: RasterSettings | None = None) -> dict:
    """Same arguments as :func:`core.raster.rasterize` (one :class:`core.camera.Camera`); returns
    a dict of ``[H, W, C]`` tensors (color, opacity, depth, normal, albedo, roughness, metallic,
    transmittance)."""
    cam_to_world, width, height = camera.cam_to_world, camera.width, camera.height
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    s = settings or RasterSettings()
    dt = means.dtype
    n = means.shape[0]
    opac = opacities.reshape(n).clamp(0.0, 1.0)
    rough = roughness.reshape(n, 1)
    metal = metallic.reshape(n, 1)
    bg = torch.zeros(3, dtype=dt) if background is None else background.to(dt)

    w2c = torch.linalg.inv(cam_to_world.to(dt))
    wrot = w2c[:3, :3]
    pc = means @ wrot.T + w2c[:3, 3]
    x, y, z = pc[:, 0], pc[:, 1], pc[:, 2]
    valid = z > s.near
    zs = torch.where(valid, z, torch.ones_like(z))
    mean2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], -1)

    g = 0.5 * (s.guard_band - 1.0)
    lim = ((-g * width - cx) / fx, ((1 + g) * width - cx) / fx, (-g * height - cy) / fy, ((1 + g) * height - cy) / fy)
    tx = torch.clamp(x / zs, lim[0], lim[1]) * zs
    ty = torch.clamp(y / zs, lim[2], lim[3]) * zs
    zero = torch.zeros_like(zs)
    jac = torch.stack([
        torch.stack([fx / zs, zero, -fx * tx / (zs * zs)], -1),
        torch.stack([zero, fy / zs, -fy * ty / (zs * zs)], -1),
    ], -2)  # [N, 2, 3]
    sc = torch.clamp(scales, 0.0, s.max_scale)
    rot = _rotation(quats)
    sigma = rot @ torch.diag_embed(sc * sc) @ rot.transpose(1, 2)
    jw = jac @ wrot
    cov2 = jw @ sigma @ jw.transpose(1, 2) + s.low_pass * torch.eye(2, dtype=dt)
    conic = torch.linalg.inv(cov2)  # [N, 2, 2]

    ys, xs = torch.meshgrid(torch.arange(height, dtype=dt) + 0.5, torch.arange(width, dtype=dt) + 0.5, indexing="ij")
    pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], -1)  # [P, 2]
    d = pix[:, None, :] - mean2d[None, :, :]  # [P, N, 2]
    power = -0.5 * torch.einsum("pni,nij,pnj->pn", d, conic, d)
    alpha = torch.clamp(opac[None, :] * torch.exp(power), max=s.alpha_max)
    alpha = torch.where((alpha >= s.alpha_min) & valid[None, :], alpha, torch.zeros_like(alpha))

    order = torch.argsort(torch.where(valid, z, torch.full_like(z, float("inf"))), stable=True)
    alpha = alpha[:, order]
    feats = torch.cat([colors, z[:, None], normals, albedo, rough, metal], -1)[order]  # [N, 12]
    with torch.no_grad():  # early stop: drop the Gaussian that takes T below transmittance_min
        keep = torch.cumprod(1.0 - alpha, dim=1) >= s.transmittance_min
    alpha = alpha * keep
    trans = torch.cumprod(1.0 - alpha, dim=1)
    t_before = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], dim=1)
    weight = alpha * t_before  # [P, N]
    out = weight @ feats  # [P, 12]
    t_final = trans[:, -1] if n else torch.ones(pix.shape[0], dtype=dt)
    color = out[:, 0:3] + t_final[:, None] * bg
    hw = (height, width)
    return {
        "color": color.reshape(*hw, 3),
        "opacity": weight.sum(1).reshape(*hw, 1),
        "depth": out[:, 3:4].reshape(*hw, 1),
        "normal": out[:, 4:7].reshape(*hw, 3),
        "albedo": out[:, 7:10].reshape(*hw, 3),
        "roughness": out[:, 10:11].reshape(*hw, 1),
        "metallic": out[:, 11:12].reshape(*hw, 1),
        "transmittance": t_final.reshape(*hw),
    }
