"""The oracle Gaussian scene (Gaussians on mesh surfaces) and the shared native build helper."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from core.camera import Camera
from core.conventions import look_at, project_points
from core.errors import ConfigError
from core.synth.oracle import OracleSettings, budget_scale, oracle_gaussians, predicted_count
from core.raster import rasterize_gaussians
from core.synth import geometry as geo
from core.synth.street import Material, Part

MAT = Material("m", (0.5, 0.4, 0.3), 0.6, 0.0)


def _quad_scene():
    part = Part("q", *geo.quad([(-1, 0, 0), (1, 0, 0), (1, 0, 2), (-1, 0, 2)]), MAT)
    c2w = look_at(np.array([0.0, -10.0, 1.0]), np.array([0.0, 0.0, 1.0]))
    return part, c2w


def test_gaussians_lie_on_the_faces_with_face_normals_and_materials():
    box = Part("b", *geo.box((0.0, 0.0, 0.5), (1.0, 2.0, 1.0)), Material("b", (0.2, 0.3, 0.4), 0.25, 1.0))
    g = oracle_gaussians([box], np.array([[0.0, -5.0, 1.0]]), 100.0, OracleSettings(spacing_px=2.0))
    m = g.means.double()
    # every mean is on the box surface (within the edge inset, on one of the 6 planes)
    d = torch.minimum(torch.minimum((m[:, 0].abs() - 0.5).abs(), (m[:, 1].abs() - 1.0).abs()),
                      torch.minimum((m[:, 2] - 0.0).abs(), (m[:, 2] - 1.0).abs()))
    assert float(d.max()) < 1e-5
    n = g.unit_normals().double()
    assert torch.allclose(n.abs().max(-1).values, torch.ones(g.num, dtype=torch.float64), atol=1e-6)
    np.testing.assert_allclose(g.albedo().numpy(), np.tile([0.2, 0.3, 0.4], (g.num, 1)), atol=1e-5)
    np.testing.assert_allclose(g.metallic().numpy(), 1.0, atol=1e-5)
    # flat: the smallest scale is the thickness and lies along the normal
    from core.raster import quat_to_rotmat

    r = quat_to_rotmat(g.rotations().double())
    np.testing.assert_allclose((r[:, :, 2] * n).sum(-1).abs().numpy(), 1.0, atol=1e-5)
    assert float(g.scales()[:, 2].max()) == pytest.approx(OracleSettings().thickness, rel=1e-4)
    assert float(g.opacities().min()) == pytest.approx(0.99, abs=1e-4)


def test_surface_composites_opaque_and_silhouette_on_the_mesh_edge():
    part, c2w = _quad_scene()
    fx, w, h = 200.0, 160, 160
    g = oracle_gaussians([part], c2w[:3, 3][None], fx, OracleSettings(spacing_px=1.5))
    out = rasterize_gaussians(g, Camera.from_intrinsics(torch.tensor(c2w, dtype=torch.float32), fx, fx, w / 2, h / 2, w, h))
    o = out.opacity[..., 0].numpy()
    uv, _ = project_points(np.array([[-1, 0, 0], [1, 0, 2.0]]), c2w, fx, fx, w / 2, h / 2)
    c0, c1 = int(round(uv[0, 0])), int(round(uv[1, 0]))  # true edges at pixel borders 60 and 100
    assert o[65:95, 65:95].min() > 0.99
    row = o[h // 2]
    assert row[c0] > 0.5 and row[c0 - 1] < 0.5 and row[c1 - 1] > 0.5 and row[c1] < 0.5


def test_edge_refine_sharpens_the_silhouette_and_keeps_the_surface_opaque():
    part, c2w = _quad_scene()
    fx, w, h = 200.0, 160, 160
    widths, crossings = {}, {}
    for k in (1, 4):
        g = oracle_gaussians([part], c2w[:3, 3][None], fx, OracleSettings(spacing_px=3.0, edge_refine=k))
        m = g.means.double()
        assert float(m[:, 1].abs().max()) < 1e-6  # on the plane y = 0
        assert float(m[:, 0].abs().max()) < 1.0 and float(m[:, 2].min()) > 0.0 and float(m[:, 2].max()) < 2.0
        out = rasterize_gaussians(g, Camera.from_intrinsics(torch.tensor(c2w, dtype=torch.float32), fx, fx, w / 2, h / 2, w, h))
        o = out.opacity[..., 0].numpy()
        assert o[68:92, 68:92].min() > 0.99
        row = o[h // 2].astype(np.float64)
        uv, _ = project_points(np.array([[-1, 0, 0], [1, 0, 2.0]]), c2w, fx, fx, w / 2, h / 2)
        edge = float(uv[0, 0])  # the mesh edge (a pixel border)
        i = int(np.argmax(row > 0.5))  # first pixel centre (i + 0.5) above 50% opacity
        crossing = i - 0.5 + (0.5 - row[i - 1]) / (row[i] - row[i - 1])  # linear between centres
        crossings[k] = crossing - edge
        widths[k] = int(((row > 0.05) & (row < 0.95)).sum())  # pixels of the opacity ramp
    # the silhouette (50% opacity) is within a pixel of the mesh edge, closer with the fine band;
    # the ramp is narrower (the rasteriser's 0.3 px^2 low-pass still widens sub-pixel Gaussians)
    assert abs(crossings[1]) < 0.75 and abs(crossings[4]) < 0.3, crossings
    assert widths[4] < widths[1], widths


def test_sliver_faces_stay_thin():
    """A window-like box 6 cm deep seen from far (coarse spacing: its side faces are slivers of
    one Gaussian each): no Gaussian reaches more than about ten centimetres beyond the box along
    its thin axis with ``thin_slivers`` (without: isotropic at half its longest edge)."""
    from core.raster import quat_to_rotmat

    win = Part("w", *geo.box((0.0, 0.0, 1.5), (1.2, 0.06, 1.5)), MAT)

    def reach_y(thin):
        g = oracle_gaussians([win], np.array([[0.0, -40.0, 1.5]]), 100.0,
                             OracleSettings(spacing_px=2.0, max_spacing=1.0, thin_slivers=thin))
        r = quat_to_rotmat(g.rotations().double())
        # 3-sigma reach along world y of every Gaussian: |R[1, :] * scale| summed in quadrature
        reach = 3.0 * torch.sqrt(((r[:, 1, :] * g.scales().double()) ** 2).sum(-1))
        return float((g.means.double()[:, 1].abs() + reach).max()), g.num

    thin, n = reach_y(True)
    # half depth 0.03 plus a few centimetres (the long axis of a face split along its diagonal
    # leans 0.06 / 1.5 across it)
    assert thin < 0.15 and n >= 6
    wide, _ = reach_y(False)
    assert wide > 1.0  # isotropic at half the longest edge: 3 x 0.56 m


def test_budget_and_predicted_count():
    part, c2w = _quad_scene()
    cams = c2w[:3, 3][None]
    n = predicted_count([part], cams, 200.0, OracleSettings(spacing_px=3.0))
    assert oracle_gaussians([part], cams, 200.0, OracleSettings(spacing_px=3.0)).num == n
    s = budget_scale([part], cams, 200.0, 300)
    g = oracle_gaussians([part], cams, 200.0, budget=300)
    assert 0.8 * 300 <= g.num <= 300 and s > 1.0


def test_lambert_materials_and_validation():
    lam = Part("l", *geo.quad([(-1, 0, 0), (1, 0, 0), (1, 0, 2), (-1, 0, 2)]),
               Material("l", (0.7, 0.7, 0.7), 0.2, 0.5, "lambert"))
    g = oracle_gaussians([lam], np.array([[0.0, -5.0, 1.0]]), 100.0)
    np.testing.assert_allclose(g.roughness().numpy(), 1.0, atol=1e-5)
    np.testing.assert_allclose(g.metallic().numpy(), 0.0, atol=1e-5)
    for kw, name in ((dict(spacing_px=0.0), "spacing_px"), (dict(opacity=1.5), "opacity"),
                     (dict(max_cells=0), "max_cells"), (dict(edge_inset=-1.0), "edge_inset"),
                     (dict(edge_refine=0), "edge_refine"), (dict(edge_refine=2.5), "edge_refine")):
        with pytest.raises(ConfigError, match=name):
            OracleSettings(**kw)
    with pytest.raises(ConfigError, match="camera_positions"):
        oracle_gaussians([lam], np.zeros((0, 3)), 100.0)
