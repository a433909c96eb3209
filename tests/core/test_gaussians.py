"""core.gaussians.Gaussians: activations, inverse activations, manipulation, files, validation."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent / "raster"))  # the rasterizer tests' scenes
from raster_scenes import camera, random_scene  # noqa: E402

from core.camera import Camera  # noqa: E402
from core.errors import FormatError, NumericalError, ShapeError  # noqa: E402
from core.gaussians import FORMAT_VERSION, Gaussians  # noqa: E402


def _make(n=7, seed=0, dtype=torch.float64):
    return Gaussians.from_activated(*[t.to(dtype) for t in random_scene(n, seed)])


def test_roundtrip_activations():
    scene = random_scene(20, 1)
    g = Gaussians.from_activated(*scene)
    a = g.activated()
    torch.testing.assert_close(a["means"], scene[0])
    torch.testing.assert_close(a["quats"], torch.nn.functional.normalize(scene[1], dim=-1))
    torch.testing.assert_close(a["scales"], scene[2])
    torch.testing.assert_close(a["opacities"][:, 0], scene[3])
    torch.testing.assert_close(a["colors"], scene[4])
    torch.testing.assert_close(a["normals"], scene[5])
    torch.testing.assert_close(a["albedo"], scene[6])
    torch.testing.assert_close(a["roughness"][:, 0], scene[7])
    torch.testing.assert_close(a["metallic"], scene[8])
    assert g.num == 20 and len(g) == 20


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_inverse_activation_clamps_extremes(dtype):
    n = 4
    ones, zeros = torch.ones(n, dtype=dtype), torch.zeros(n, dtype=dtype)
    g = Gaussians.from_activated(torch.zeros(n, 3, dtype=dtype), torch.zeros(n, 4, dtype=dtype),
                                 torch.zeros(n, 3, dtype=dtype), torch.tensor([0.0, 1.0, 0.0, 1.0], dtype=dtype),
                                 torch.zeros(n, 3, dtype=dtype), torch.zeros(n, 3, dtype=dtype),
                                 torch.ones(n, 3, dtype=dtype), ones, zeros)
    for t in g.parameters():
        assert torch.isfinite(t).all()
    a = g.activated()
    assert torch.equal(a["quats"], torch.tensor([[1.0, 0, 0, 0]] * n, dtype=dtype))  # zero quaternion
    assert torch.isfinite(a["scales"]).all() and float(a["scales"].max()) < 1e-6
    assert float(a["opacities"][1]) > 0.999 and float(a["opacities"][0]) < 1e-3
    assert float(a["normals"].abs().max()) == 0.0  # zero normal stays zero, no NaN


def test_activation_gradients_finite_for_degenerate_parameters():
    g = _make(5)
    g.quats = torch.zeros(5, 4, dtype=torch.float64)
    g.log_scales = torch.tensor([[1e3, -1e3, 0.0]] * 5, dtype=torch.float64)
    g.normals = torch.zeros(5, 3, dtype=torch.float64)
    g.opacity_logits = torch.tensor([[1e4], [-1e4], [0.0], [50.0], [-50.0]], dtype=torch.float64)
    g.requires_grad_()
    a = g.activated(cam_center=torch.tensor([0.5, -2.0, 1.0], dtype=torch.float64))  # uses view_dep too
    loss = sum(v.sum() for v in a.values())
    grads = torch.autograd.grad(loss, g.parameters())
    assert all(torch.isfinite(x).all() for x in grads)
    assert torch.isfinite(a["scales"]).all()


def test_to_cat_index_select():
    g = _make(6)
    h = g.to(torch.float32)
    assert h.dtype == torch.float32 and h.num == 6
    c = Gaussians.cat([g, _make(3, 1)])
    assert c.num == 9
    torch.testing.assert_close(c.means[6:], _make(3, 1).means)
    mask = torch.tensor([True, False, True, False, False, True])
    assert g.index(mask).num == 3
    assert g.select(torch.tensor([5, 0])).means[0].tolist() == g.means[5].tolist()
    assert g[1:3].num == 2
    assert g.index([0, 1]).num == 2
    with pytest.raises(ShapeError, match="idx"):
        g.index(torch.tensor([True, False]))
    with pytest.raises(ShapeError, match="items"):
        Gaussians.cat([g, h])
    with pytest.raises(ShapeError, match="items"):
        Gaussians.cat([])
    assert Gaussians.empty().num == 0


def test_save_load_roundtrip(tmp_path):
    g = _make(11, 2, torch.float32)
    path = tmp_path / "g.pt"
    g.save(path)
    payload = torch.load(path, weights_only=True)
    assert payload["format"] == "brdfusion.gaussians" and payload["version"] == FORMAT_VERSION
    assert payload["num"] == 11
    h = Gaussians.load(path)
    for k, v in g.tensors().items():
        assert torch.equal(v, getattr(h, k)), k
        assert getattr(h, k).dtype == torch.float32


def test_load_rejects_bad_files(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a torch file")
    with pytest.raises(FormatError):
        Gaussians.load(bad)
    g = _make(3)
    p = tmp_path / "g.pt"
    g.save(p)
    payload = torch.load(p, weights_only=True)
    payload["version"] = FORMAT_VERSION + 1
    torch.save(payload, p)
    with pytest.raises(FormatError, match="version"):
        Gaussians.load(p)
    payload["version"] = FORMAT_VERSION
    del payload["albedo_logits"]
    torch.save(payload, p)
    with pytest.raises(FormatError, match="albedo_logits"):
        Gaussians.load(p)
    payload["albedo_logits"] = torch.zeros(2, 3, dtype=torch.float64)
    torch.save(payload, p)
    with pytest.raises(FormatError, match="albedo_logits"):
        Gaussians.load(p)


@pytest.mark.parametrize("field,value,err", [
    ("means", torch.zeros(3, 2), ShapeError),
    ("quats", torch.zeros(3, 3), ShapeError),
    ("log_scales", torch.zeros(4, 3), ShapeError),
    ("opacity_logits", torch.zeros(3, 1, dtype=torch.float32), ShapeError),
    ("normals", torch.zeros(3, 3, dtype=torch.int64), ShapeError),
    ("albedo_logits", torch.full((3, 3), math.nan), NumericalError),
    ("metallic_logits", torch.full((3, 1), math.inf), NumericalError),
])
def test_validation_names_the_field(field, value, err):
    kw = _make(3).tensors()
    if value.is_floating_point() and value.dtype != torch.float32:
        value = value.to(torch.float64)
    elif value.dtype == torch.float32 and field != "opacity_logits":
        value = value.to(torch.float64)
    kw[field] = value
    with pytest.raises(err, match=field):
        Gaussians(**kw)


def test_render_through_container_gives_parameter_gradients():
    from core.raster import rasterize_gaussians

    g = _make(30, 4).requires_grad_()
    out = rasterize_gaussians(g, Camera.from_intrinsics(*camera(24, 18)))
    loss = sum(v.sum() for v in out.as_dict().values())
    grads = torch.autograd.grad(loss, g.parameters())
    for name, gr in zip(g.tensors(), grads):
        assert torch.isfinite(gr).all(), name
        assert float(gr.abs().sum()) > 0, name


def test_geometry_detached_renders_the_same_and_moves_only_the_attributes():
    from core.raster import rasterize_gaussians

    g = _make(30, 4).requires_grad_()
    cam = Camera.from_intrinsics(*camera(24, 18))
    full, attr = rasterize_gaussians(g, cam), rasterize_gaussians(g.geometry_detached(), cam)
    for k, v in full.as_dict().items():
        torch.testing.assert_close(attr.as_dict()[k], v, msg=k)  # same values
    loss = attr.albedo.sum() + attr.normal.sum() + attr.roughness.sum() + attr.metallic.sum()
    grads = dict(zip(g.tensors(), torch.autograd.grad(loss, g.parameters(), allow_unused=True)))
    for k in Gaussians.GEOMETRY_FIELDS:
        assert grads[k] is None or float(grads[k].abs().sum()) == 0.0, k
    for k in ("albedo_logits", "normals", "roughness_logits", "metallic_logits"):
        assert grads[k] is not None and float(grads[k].abs().sum()) > 0, k
    # the same loss on the attached render moves the geometry too
    loss_full = full.albedo.sum() + full.normal.sum()
    g_means = torch.autograd.grad(loss_full, g.means)[0]
    assert float(g_means.abs().sum()) > 0
