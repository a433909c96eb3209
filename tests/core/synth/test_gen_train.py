"""Training scaffolding: bundle -> tensors, held-out split, a few steps that reduce the loss,
resume from the checkpoint, ONNX export + model card that the runtime loads."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from core.errors import ConfigError, ShapeError
from core.gen.contract import GBUFFER_SLICES
from core.gen.nets import UNetSettings, build_model
from core.gen.runtime import load_model
from core.synth.gen_data import ClipDataset, DataSettings, load_clips, split_bundles
from core.synth.gen_train import TrainSettings, edm_loss, train_model

REPO = Path(__file__).resolve().parents[3]
SCENE = REPO / "data" / "scenes" / "default"
TINY_NET = UNetSettings(base_channels=8, emb_dim=32, env_channels=8)

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def clips():
    return load_clips(SCENE, DataSettings(max_frames_per_clip=3), kinds=("forward", "inverse"))


def test_clips_and_dataset(clips):
    assert len(clips) == 2 and len(clips[0]) == 3
    f = clips[0][0]
    assert f["target_ldr"].shape == (3, 160, 240) and f["gbuffer"].shape == (9, 160, 240)
    assert f["env_ldr"].shape == (3, 64, 128) and -1 <= f["input_ldr"].min() and f["input_ldr"].max() <= 1
    n = f["gbuffer"][GBUFFER_SLICES["normal"]]
    nonsky = f["sky"][0] < 0.5
    assert np.allclose(np.linalg.norm(n, axis=0)[nonsky], 1, atol=2e-2)
    ds = ClipDataset(clips, "forward_denoiser", frames=2, crop=32, flip=True)
    b = ds.sample(3, np.random.default_rng(0))
    assert b["x0"].shape == (3, 2, 3, 32, 32) and b["env_dir"].shape == (3, 2, 3, 64, 128)
    inv = ClipDataset(clips, "inverse_gbuffer", frames=1, crop=16).sample(2, np.random.default_rng(1))
    assert inv["x0"].shape == (2, 1, 9, 16, 16) and inv["rgb"].shape == (2, 1, 3, 16, 16)
    with pytest.raises(ConfigError, match="crop"):
        ClipDataset(clips, "forward_denoiser", crop=30)


def test_split_by_seed(tmp_path):
    train, held = split_bundles([SCENE], held_out_seeds=(0,))
    assert held == [SCENE] and train == []
    train, held = split_bundles([SCENE], held_out_seeds=(5,))
    assert train == [SCENE] and held == []


def test_training_reduces_loss_resumes_and_exports(clips, tmp_path):
    s = TrainSettings(batch=2, crop=32, frames=1, lr=2e-3, warmup=5, threads=1, unet=TINY_NET,
                      checkpoint_every=10, ema_decay=0.9)
    out = tmp_path / "fwd"
    r = train_model("forward_denoiser", [SCENE], out, 50, settings=s, clips=clips)
    assert r.steps == 50 and len(r.losses) == 50 and np.all(np.isfinite(r.losses))
    assert np.mean(r.losses[-10:]) < 0.6 * np.mean(r.losses[:10]), (r.losses[:10], r.losses[-10:])
    r2 = train_model("forward_denoiser", [SCENE], out, 55, settings=s, clips=clips)
    assert r2.steps == 55 and len(r2.losses) == 55 and r2.losses[:50] == r.losses  # resumed, not restarted
    sess = load_model(r2.onnx_path, kind="forward_denoiser", threads=1)
    assert sess.info.frames == 1
    card = json.loads(r2.card_path.read_text())
    assert card["contract"] == "forward_denoiser" and card["version"] == "1.0"
    assert card["training"]["steps"] == 55 and card["file"]["sha256"]
    assert [i["name"] for i in card["inputs"]][:2] == ["x_t", "sigma"]
    other = TrainSettings(batch=2, crop=32, threads=1, unet=UNetSettings(base_channels=12))
    with pytest.raises(ConfigError, match="checkpoint of a different model"):
        train_model("forward_denoiser", [SCENE], out, 60, settings=other, clips=clips)


def test_inverse_training_steps(clips, tmp_path):
    s = TrainSettings(batch=2, crop=16, frames=2, lr=2e-3, warmup=2, threads=1, unet=TINY_NET)
    r = train_model("inverse_gbuffer", [SCENE], tmp_path / "inv", 30, settings=s, clips=clips)
    assert np.mean(r.losses[-8:]) < np.mean(r.losses[:8])
    assert load_model(r.onnx_path, kind="inverse_gbuffer", threads=1).info.frames == 2


def test_fine_tuning_starts_from_the_exported_weights(tmp_path):
    """load_onnx_weights (TrainSettings.init_from) copies an exported model's weights back into a
    fresh network of the same shape, and names the file and weight when the network differs."""
    import torch

    from core.errors import ModelLoadError
    from core.gen.nets import build_model, export_onnx
    from core.synth.gen_train import load_onnx_weights

    torch.manual_seed(1)
    src = build_model("inverse_gbuffer", TINY_NET)
    with torch.no_grad():  # a trained network: no zero-initialised layers (the exporter merges equal tensors)
        for p in src.parameters():
            p.normal_(0.0, 0.1)
    path = export_onnx(src, tmp_path / "m.onnx")
    torch.manual_seed(2)
    dst = build_model("inverse_gbuffer", TINY_NET)
    assert any(not torch.equal(a, b) for a, b in zip(src.state_dict().values(), dst.state_dict().values()))
    load_onnx_weights(dst, path)
    for k, v in src.state_dict().items():
        assert torch.equal(dst.state_dict()[k], v), k
    wider = build_model("inverse_gbuffer", UNetSettings(base_channels=12, emb_dim=32, env_channels=8))
    with pytest.raises(ModelLoadError, match=r"m\.onnx: weight '.*' has shape"):
        load_onnx_weights(wider, path)
    (tmp_path / "bad.onnx").write_bytes(b"not a model")
    with pytest.raises(ModelLoadError, match=r"bad\.onnx: cannot read"):
        load_onnx_weights(dst, tmp_path / "bad.onnx")


def test_grown_network_starts_as_the_file_model(tmp_path):
    """load_onnx_weights(grow=True): a network with more residual blocks per level and extra
    bottleneck blocks takes the file's weights and computes exactly the file's model (its new
    blocks are the identity); without grow, or with another missing weight, it is an error."""
    from core.errors import ModelLoadError
    from core.gen.nets import export_onnx
    from core.synth.gen_train import load_onnx_weights, onnx_unet_depth

    torch.manual_seed(1)
    src = build_model("inverse_gbuffer", TINY_NET, view=True).eval()
    with torch.no_grad():
        for p in src.parameters():
            p.normal_(0.0, 0.1)
    path = export_onnx(src, tmp_path / "m.onnx")
    grown = build_model("inverse_gbuffer", UNetSettings(base_channels=8, emb_dim=32, env_channels=8, blocks=2,
                                                        mid_blocks=2), view=True).eval()
    assert sum(p.numel() for p in grown.parameters()) > sum(p.numel() for p in src.parameters())
    with pytest.raises(ModelLoadError, match=r"m\.onnx: no weight 'net\.(enc|dec|mid_extra)\."):
        load_onnx_weights(grown, path)
    load_onnx_weights(grown, path, grow=True)
    g = torch.Generator().manual_seed(3)
    x, rgb, view = (torch.randn(2, 1, c, 16, 24, generator=g) for c in (9, 3, 6))
    sigma = torch.tensor([0.3, 5.0])
    with torch.no_grad():
        a, b = src(x, sigma, rgb, view), grown(x, sigma, rgb, view)
    assert torch.allclose(a, b, atol=1e-5), float((a - b).abs().max())
    # the other way round: the file's extra blocks are never silently dropped by a smaller network
    big = export_onnx(grown, tmp_path / "big.onnx")
    assert onnx_unet_depth(path) == (1, 0) and onnx_unet_depth(big) == (2, 2)  # the depth to build for each file
    with pytest.raises(ModelLoadError, match=r"big\.onnx: the network has no place for .*'net\.(enc|dec|mid_extra)\."):
        load_onnx_weights(build_model("inverse_gbuffer", TINY_NET, view=True), big)
    # the grown blocks train: a step moves the output away from the file model's
    grown.train()
    opt = torch.optim.SGD(grown.parameters(), lr=0.1)
    grown(x, sigma, rgb, view).square().mean().backward()
    opt.step()
    with torch.no_grad():
        assert not torch.allclose(grown.eval()(x, sigma, rgb, view), a, atol=1e-4)
    # a missing weight outside a whole new residual block, or a changed shape, stays an error
    other = build_model("inverse_gbuffer", UNetSettings(base_channels=8, emb_dim=32, env_channels=8, mid_blocks=1),
                        view=True)
    other.net.extra = torch.nn.Linear(4, 4)
    with pytest.raises(ModelLoadError, match=r"m\.onnx: no weight 'net\.extra\.weight'"):
        load_onnx_weights(other, path, grow=True)
    del other.net.extra
    other.net.head = torch.nn.Conv2d(8, 40, 3, padding=1)
    with pytest.raises(ModelLoadError, match=r"m\.onnx: weight 'net\.head\.weight' has shape"):
        load_onnx_weights(other, path, grow=True)


def test_generate_defaults_to_one_step_posterior_mean():
    """The inverse model's default sampler is one Euler step from sigma_max: the output is the
    denoiser's own x0 estimate at sigma_max (one evaluation)."""
    import torch

    from core.gen.edm import GENERATE_SAMPLER, generate

    calls = []

    def den(x, sigma, cond):
        calls.append(float(sigma.reshape(-1)[0]))
        return torch.full_like(x, 0.25)

    y = generate(den, (2, 9, 8, 8), {"rgb": torch.zeros(2, 3, 8, 8)})
    assert GENERATE_SAMPLER.steps == 1 and calls == [GENERATE_SAMPLER.sigma_max]
    assert torch.allclose(y, torch.full_like(y, 0.25), atol=1e-4)  # x - sigma (x - D) / sigma, x ~ 80 N(0, 1)


def _random_export(path, seed: int):
    """An F = 1 inverse network with random weights (as a trained one: no zero-initialised layers,
    which the exporter would merge) in eval mode, and its ONNX export at ``path``."""
    import torch

    from core.gen.nets import export_onnx

    torch.manual_seed(seed)
    src = build_model("inverse_gbuffer", TINY_NET)
    with torch.no_grad():
        for p in src.parameters():
            p.normal_(0.0, 0.1)
    return src.eval(), export_onnx(src.eval(), path)


def test_camera_input_starts_from_a_model_without_it(clips, tmp_path):
    """TrainSettings.view: a network with the camera input initialised from a file without it
    (zero stem weights for the new channels) computes exactly what the file computed, whatever
    the camera; it then trains, and its export declares the optional input."""
    import torch

    from core.gen.nets import example_inputs
    from core.synth.gen_train import load_onnx_weights

    src, path = _random_export(tmp_path / "plain.onnx", seed=3)
    dst = build_model("inverse_gbuffer", TINY_NET, view=True)
    load_onnx_weights(dst, path)
    ex = example_inputs("inverse_gbuffer", batch=2, frames=1, height=16, width=24, seed=4)
    with torch.no_grad():
        ref = src(ex["x_t"], ex["sigma"], ex["rgb"])
        out = dst.eval()(ex["x_t"], ex["sigma"], ex["rgb"], ex["view"])
        out2 = dst(ex["x_t"], ex["sigma"], ex["rgb"], -ex["view"])
    assert ref.abs().max() > 1e-3 and torch.allclose(out, ref, atol=1e-6) and torch.allclose(out2, ref, atol=1e-6)
    s = TrainSettings(batch=2, crop=16, frames=1, lr=2e-3, warmup=2, threads=1, unet=TINY_NET, view=True,
                      init_from=str(path))
    r = train_model("inverse_gbuffer", [SCENE], tmp_path / "inv_view", 20, settings=s, clips=clips)
    assert np.all(np.isfinite(r.losses))
    sess = load_model(r.onnx_path, kind="inverse_gbuffer", threads=1)
    assert sess.info.takes("view") and not load_model(path, threads=1).info.takes("view")
    card = json.loads(r.card_path.read_text())
    assert card["network"]["view"] is True
    with pytest.raises(ConfigError, match="view: only the inverse"):
        train_model("forward_denoiser", [SCENE], tmp_path / "fwd_view", 2, settings=s, clips=clips)


def test_window_model_starts_from_a_single_frame_model(clips, tmp_path):
    """TrainSettings.frames > 1 from an F = 1 file (the paper's sliding window, fine-tuned from the
    shipped single-frame model): the weights load unchanged; on a window of identical frames the
    bottleneck mean is each frame's own feature, so it computes exactly what the file computed,
    and on distinct frames the frames see each other; it trains, and its export declares F."""
    import torch

    from core.gen.nets import example_inputs
    from core.synth.gen_train import load_onnx_weights

    src, path = _random_export(tmp_path / "single.onnx", seed=5)
    dst = build_model("inverse_gbuffer", TINY_NET, frames=3).eval()
    load_onnx_weights(dst, path)
    ex = example_inputs("inverse_gbuffer", batch=1, frames=1, height=16, width=24, seed=6)
    same = {k: ex[k].expand(1, 3, *ex[k].shape[2:]).contiguous() for k in ("x_t", "rgb")}
    with torch.no_grad():
        ref = src(ex["x_t"], ex["sigma"], ex["rgb"])
        out = dst(same["x_t"], ex["sigma"], same["rgb"])
        other = same["rgb"].clone()
        other[:, 1:] = torch.flip(other[:, 1:], dims=[-1])
        mixed = dst(same["x_t"], ex["sigma"], other)
    assert ref.abs().max() > 1e-3
    for t in range(3):
        assert torch.allclose(out[:, t], ref[:, 0], atol=1e-5), t
    assert (mixed[:, 0] - ref[:, 0]).abs().max() > 1e-4  # frame 0 is unchanged, its window is not
    s = TrainSettings(batch=2, crop=16, frames=3, lr=2e-3, warmup=2, threads=1, unet=TINY_NET, init_from=str(path))
    r = train_model("inverse_gbuffer", [SCENE], tmp_path / "inv_f3", 10, settings=s, clips=clips)
    assert np.all(np.isfinite(r.losses))
    assert load_model(r.onnx_path, kind="inverse_gbuffer", threads=1).info.frames == 3
    assert json.loads(r.card_path.read_text())["network"]["frames"] == 3


def test_dataset_camera_input_follows_the_flip(clips):
    """The camera input of a mirrored crop is the mirrored camera's: the x components of the ray
    and of the up direction change sign with the image."""
    ds = ClipDataset(clips, "inverse_gbuffer", frames=1, crop=16, view=True)
    win = clips[0][:1]
    plain, flipped = ds._items(win, 40, 100, False), ds._items(win, 40, 100, True)
    v, fv = plain["view"][0], flipped["view"][0]
    assert v.shape == (6, 16, 16) and np.allclose(np.linalg.norm(v[:3], axis=0), 1, atol=1e-5)
    assert np.allclose(fv[0], -v[0][:, ::-1]) and np.allclose(fv[1:3], v[1:3][:, :, ::-1])
    assert np.allclose(fv[3], -v[3]) and np.allclose(fv[4:], v[4:])
    assert np.allclose(flipped["x0"][0, 5], -plain["x0"][0, 5][:, ::-1])  # normal x, as before
    with pytest.raises(ConfigError, match="view"):
        ClipDataset([[{k: f[k] for k in f if k != "view"} for f in c] for c in clips], "inverse_gbuffer", view=True)


def _material_clip(h=32, w=64, frames=2):
    """A clip whose frames are road-like (roughness 0.9, dielectric) except a metal-glossy block
    (roughness 0.1, metallic 1) in the right eighth of the frame, and sky in the top row."""
    out = []
    for _ in range(frames):
        g = np.zeros((9, h, w), np.float32)
        g[3], g[4] = 0.9 * 2 - 1, -1.0
        g[3, :, -w // 8:], g[4, :, -w // 8:] = 0.1 * 2 - 1, 1.0
        sky = np.zeros((1, h, w), np.float32)
        sky[0, 0] = 1
        out.append({"gbuffer": g, "rgb": np.zeros((3, h, w), np.float32), "sky": sky})
    return [out]


def test_rarity_table_weighs_rare_materials_up():
    from core.synth.gen_data import RARITY_BINS, material_bins, rarity_table

    clip = _material_clip()
    table = rarity_table(clip, stride=1)
    assert table.shape == (RARITY_BINS,)
    b = material_bins(clip[0][0]["gbuffer"])
    road, metal = b[5, 0], b[5, -1]
    assert (road, metal) == (8, 1)  # roughness bin 4 (0.9) x 2 + dielectric; bin 0 x 2 + metal
    f_metal = 1 / 8
    w_road, w_metal = 1 / np.sqrt(1 - f_metal), 1 / np.sqrt(f_metal)
    norm = (1 - f_metal) * w_road + f_metal * w_metal
    assert table[road] == pytest.approx(w_road / norm) and table[metal] == pytest.approx(w_metal / norm)
    assert np.count_nonzero(table) == 2  # bins no pixel falls in weigh nothing
    with pytest.raises(ShapeError, match="gbuffer"):
        material_bins(np.zeros((8, 4, 4)))


def test_rare_crops_draw_more_rare_material():
    clip = _material_clip()

    def metal_share(fraction):
        ds = ClipDataset(clip, "inverse_gbuffer", crop=8, flip=False, rare_fraction=fraction)
        x0 = ds.sample(400, np.random.default_rng(3))["x0"].numpy()
        return float((x0[:, :, 4] > 0).mean())

    uniform, rare = metal_share(0.0), metal_share(1.0)
    assert 0.05 < uniform < 0.2  # about the block's share of the crop positions
    assert rare > 2 * uniform
    with pytest.raises(ConfigError, match="rare_fraction"):
        ClipDataset(clip, "inverse_gbuffer", rare_fraction=1.5)
    with pytest.raises(ConfigError, match="rare_fraction"):
        ClipDataset(load_clips(SCENE, DataSettings(max_frames_per_clip=2), kinds=("forward",)), "forward_denoiser",
                    rare_fraction=0.5)
    with pytest.raises(ConfigError, match="rare_candidates"):
        ClipDataset(clip, "inverse_gbuffer", rare_fraction=0.5, rare_candidates=1)


def test_rare_crop_training_records_its_table(clips, tmp_path):
    s = TrainSettings(batch=2, crop=16, frames=1, lr=2e-3, warmup=2, threads=1, unet=TINY_NET, rare_fraction=0.5)
    r = train_model("inverse_gbuffer", [SCENE], tmp_path / "inv", 4, settings=s, clips=clips)
    card = json.loads(Path(r.card_path).read_text())["training"]
    assert card["rare_fraction"] == 0.5 and len(card["rarity_table"]) == 10 and max(card["rarity_table"]) > 1
    with pytest.raises(ConfigError, match="rare_fraction"):
        TrainSettings(rare_fraction=-0.1)


def test_rare_loss_weights_follow_the_material_and_spare_the_sky():
    clip = _material_clip()
    ds = ClipDataset(clip, "inverse_gbuffer", crop=32, flip=False, rare_loss_max=3.0)
    b = ds.sample(8, np.random.default_rng(0))
    w, x0, sky = b["pixel_weight"].numpy(), b["x0"].numpy(), b["sky"].numpy()
    assert w.shape == (8, 1, 1, 32, 32)
    metal = (x0[:, :, 4:5] > 0) & (sky < 0.5)
    road = (x0[:, :, 4:5] < 0) & (sky < 0.5)
    assert np.allclose(w[sky > 0.5], 1.0)
    assert np.allclose(w[metal], min(3.0, ds.rarity.max())) and np.allclose(w[road], max(1 / 3.0, ds.rarity[8]))
    assert w[metal].min() > w[road].max()
    with pytest.raises(ConfigError, match="rare_loss_max"):
        TrainSettings(rare_loss_max=0.5)
    s = TrainSettings(batch=2, crop=16, frames=1, lr=2e-3, warmup=2, threads=1, unet=TINY_NET, rare_loss_max=3.0)
    model = build_model("inverse_gbuffer", TINY_NET, s.sigma_data, 1)
    batch = ds.sample(2, np.random.default_rng(1))
    plain = {k: v for k, v in batch.items() if k != "pixel_weight"}
    l_w = edm_loss(model, batch, s, torch.Generator().manual_seed(0))
    l_p = edm_loss(model, plain, s, torch.Generator().manual_seed(0))
    assert torch.isfinite(l_w) and not torch.isclose(l_w, l_p)
