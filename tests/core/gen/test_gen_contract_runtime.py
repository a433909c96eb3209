"""ONNX contract, loader and parity (drop-in models, clear load errors, 1e-4 parity)."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
import torch

from core.errors import ModelLoadError, NumericalError, ShapeError
from core.gen import contract as C
from core.gen.nets import example_inputs
from core.gen.runtime import clear_cache, load_model


def _np(d):
    return {k: v.numpy() for k, v in d.items()}


@pytest.mark.parametrize("key", ["fwd_a", "fwd_b", "inv"])
def test_onnx_parity_with_torch(small_models, key):
    model, path = small_models[key]
    sess = load_model(path, threads=1)
    ex = example_inputs(model.kind, batch=2, frames=model.frames, height=24, width=40, seed=5)
    with torch.no_grad():
        ref = model(**ex).numpy()
    out = sess.run(**_np(ex))["x0"]
    assert out.shape == ref.shape
    assert np.abs(ref).max() > 1e-3  # the random network does something
    assert np.abs(out - ref).max() < 1e-4


def test_two_models_same_contract_drop_in(small_models):
    """Two architectures (different width, depth, window, no temporal mixing) behind one contract:
    the same calling code runs both."""
    outs = []
    for key in ("fwd_a", "fwd_b"):
        sess = load_model(small_models[key][1], kind="forward_denoiser", threads=1)
        ex = _np(example_inputs("forward_denoiser", batch=1, frames=2, height=16, width=24, seed=1))
        y = sess.run(**ex)["x0"]
        assert y.shape == (1, 2, 3, 16, 24) and np.isfinite(y).all()
        outs.append(y)
    assert not np.allclose(outs[0], outs[1])
    assert load_model(small_models["fwd_b"][1]).info.frames == 3


def test_dynamic_size_padding_and_cache(small_models):
    path = small_models["fwd_a"][1]
    clear_cache()
    s1 = load_model(path, threads=1)
    assert load_model(path, threads=1) is s1  # warm session reused
    ex = _np(example_inputs("forward_denoiser", 1, 1, 21, 30, seed=2))  # not multiples of 8
    y = s1.run(**ex)["x0"]
    assert y.shape == (1, 1, 3, 21, 30)


def test_missing_and_corrupt_files_name_the_file(tmp_path):
    missing = tmp_path / "nope.onnx"
    with pytest.raises(ModelLoadError, match="nope.onnx.*not found"):
        load_model(missing)
    bad = tmp_path / "corrupt.onnx"
    bad.write_bytes(b"\x08\x07this is not a protobuf" * 10)
    with pytest.raises(ModelLoadError, match="corrupt.onnx.*not a loadable ONNX"):
        load_model(bad)
    empty = tmp_path / "empty.onnx"
    empty.write_bytes(b"")
    with pytest.raises(ModelLoadError, match="empty.onnx.*empty"):
        load_model(empty)


def test_truncated_file(small_models, tmp_path):
    data = small_models["fwd_a"][1].read_bytes()
    p = tmp_path / "trunc.onnx"
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(ModelLoadError, match="trunc.onnx"):
        load_model(p)


def _rewrite(src, dst, edit):
    m = onnx.load(str(src))
    edit(m)
    onnx.save(m, str(dst))
    return dst


def test_contract_mismatches(small_models, tmp_path):
    src = small_models["fwd_a"][1]
    with pytest.raises(ModelLoadError, match="implements contract 'forward_denoiser', expected 'inverse_gbuffer'"):
        load_model(src, kind="inverse_gbuffer")

    def set_meta(key, value):
        def edit(m):
            for p in m.metadata_props:
                if p.key == key:
                    p.value = value
        return edit

    v2 = _rewrite(src, tmp_path / "v2.onnx", set_meta(C.META_VERSION, "2.0"))
    with pytest.raises(ModelLoadError, match="v2.onnx.*version 2.0 is not compatible"):
        load_model(v2)

    def drop_meta(m):
        keep = [p for p in m.metadata_props if p.key != C.META_CONTRACT]
        del m.metadata_props[:]
        m.metadata_props.extend(keep)

    nometa = _rewrite(src, tmp_path / "nometa.onnx", drop_meta)
    with pytest.raises(ModelLoadError, match="nometa.onnx.*brdf.contract"):
        load_model(nometa)

    def rename_input(m):
        old = m.graph.input[2].name  # "normal"
        m.graph.input[2].name = "normals"
        for node in m.graph.node:
            for i, n in enumerate(node.input):
                if n == old:
                    node.input[i] = "normals"

    renamed = _rewrite(src, tmp_path / "renamed.onnx", rename_input)
    with pytest.raises(ModelLoadError, match=r"renamed.onnx.*input 'normal' missing"):
        load_model(renamed)

    wrong = _toy_forward_model(tmp_path / "wrongenv.onnx", env_w=64)
    with pytest.raises(ModelLoadError, match=r"wrongenv.onnx.*'env_ldr': dimension 4 is 64, contract needs 128"):
        load_model(wrong)


def _toy_forward_model(path, env_w: int = C.ENV_W):
    """A hand-built graph behind the forward contract: x0 = Identity(x_t), other inputs unused."""
    from onnx import TensorProto, helper

    def vi(spec, override=None):
        dims = [d if isinstance(d, int) else d for d in spec.dims]
        if override:
            dims = override(dims)
        return helper.make_tensor_value_info(spec.name, TensorProto.FLOAT, dims)

    con = C.FORWARD_DENOISER
    inputs = [vi(s, (lambda d: d[:-1] + [env_w]) if s.name.startswith("env_") else None) for s in con.inputs]
    out = vi(con.outputs[0])
    g = helper.make_graph([helper.make_node("Identity", ["x_t"], ["x0"])], "toy", inputs, [out])
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    m.ir_version = 8
    helper.set_model_props(m, {C.META_CONTRACT: "forward_denoiser", C.META_VERSION: "1.0", C.META_FRAMES: "1",
                               C.META_SIGMA_DATA: "0.5", C.META_SIGMA_MIN: "0.002", C.META_SIGMA_MAX: "80"})
    onnx.save(m, str(path))
    return path


def test_handmade_model_with_the_contract_drops_in(tmp_path):
    """Any graph with the contract's names/shapes/metadata works, whatever is inside."""
    sess = load_model(_toy_forward_model(tmp_path / "toy.onnx"), kind="forward_denoiser", threads=1)
    ex = _np(example_inputs("forward_denoiser", 1, 2, 13, 17))
    assert np.array_equal(sess.run(**ex)["x0"], ex["x_t"])


def test_bad_inputs_named(small_models):
    sess = load_model(small_models["fwd_a"][1], threads=1)
    ex = _np(example_inputs("forward_denoiser", 1, 1, 16, 16))
    ex["albedo"][0, 0, 0, 3, 3] = np.nan
    with pytest.raises(NumericalError, match="input 'albedo'"):
        sess.run(**ex)
    ex = _np(example_inputs("forward_denoiser", 1, 1, 16, 16))
    ex["depth"] = ex["depth"][..., :8]
    with pytest.raises(ShapeError, match="input 'depth'"):
        sess.run(**ex)
    ex = _np(example_inputs("forward_denoiser", 1, 1, 16, 16))
    del ex["env_dir"]
    with pytest.raises(ShapeError, match="env_dir"):
        sess.run(**ex)


def test_inverse_camera_input_is_optional(small_models, tmp_path):
    """The inverse contract's ``view`` input (1.1) is optional: a file without it loads, and a
    value fed to it is ignored; a file with it matches its torch network and names the input
    when a caller leaves it out."""
    from core.gen.nets import UNetSettings, build_model, export_onnx

    plain_model, plain_path = small_models["inv"]
    plain = load_model(plain_path, threads=1)
    ex = example_inputs("inverse_gbuffer", batch=1, frames=2, height=16, width=24, seed=2)
    assert not plain.info.takes("view")
    without = plain.run(**_np({k: v for k, v in ex.items() if k != "view"}))["x0"]
    assert np.array_equal(plain.run(**_np(ex))["x0"], without)
    torch.manual_seed(3)
    model = build_model("inverse_gbuffer", UNetSettings(base_channels=8, emb_dim=32), frames=2, view=True)
    with torch.no_grad():  # no zero-initialised layers (the head starts at zero)
        for p in model.parameters():
            p.add_(torch.randn(p.shape) * 0.05)
    model.eval()
    sess = load_model(export_onnx(model, tmp_path / "inv_view.onnx"), kind="inverse_gbuffer", threads=1)
    assert sess.info.takes("view") and sess.info.version == (1, 1)
    with torch.no_grad():
        ref = model(**ex).numpy()
    out = sess.run(**_np(ex))["x0"]
    assert np.abs(out - ref).max() < 1e-4
    other = _np(ex)
    other["view"] = -other["view"]
    assert np.abs(sess.run(**other)["x0"] - out).max() > 1e-4  # the camera input is used
    with pytest.raises(ShapeError, match="input 'view' missing"):
        sess.run(**_np({k: v for k, v in ex.items() if k != "view"}))
