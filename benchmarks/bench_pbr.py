"""Benchmark of the PBR pass (paper Sec. 3.2, Eq. 2-3): runtime against error, agreement with Mitsuba, frame and
clip times, and what each skip buys.

Scene (``full``): the synthetic street of ``core.synth`` (profile ``benchmark``: 320x213, seed 0,
street 60 m) as an oracle Gaussian scene graph (:func:`core.synth.oracle.street_scene_graph`:
~50k thin flat Gaussians on the mesh surfaces with the ground-truth materials, spaced for the
24 cameras of the train path; the two moving cars are rigid nodes), lit by ``data/hdri/city.exr``
(real HDRI with a 3.5e4 sun). ``--quick``: 96x64, ~8k Gaussians, a reduced sweep (smoke test).

Measurements (medians of ``--runs`` runs; wall-clock seconds; the 1-minute load average before
and after every measurement is stored, since other jobs share the 2 cores):
- ``runtime_vs_error``: rays per pixel x {env, mis}: ms per frame (G-buffers + PBR; the
  environment tables and the static BVH are built once per renderer, as for a clip) and the error
  of the LDR frame against a converged render of the same frame (4096 rays per pixel, MIS;
  computed once and cached under ``benchmarks/.cache/``): PSNR and mean FLIP (LDR).
- ``frame_64_s``: one frame at 64 rays per pixel with the default settings (MIS, no adaptive
  sampling, no visibility cache), median.
- ``clip_24_s``: 24 frames from a static camera (the path's first camera held still) while the
  cars drive, 64 rays per pixel, MIS, with the static BVH built once and the cross-frame
  visibility cache: total wall time including setup, median of ``--runs`` runs (seeds 0, 1, ...).
  The same clip along the moving camera path is in ``machine.details.clip_camera_path_s``.
- ``skips``: time with and without each skip (median) and the PSNR of each against the converged
  frame (mean over the runs, which use seeds 0, 1, ...; ``within_noise``: the difference of the
  means is at most twice its standard error, or 0.02 dB):
  ``sky`` (no shading for sky pixels), ``light_culling`` (street lights and headlights culled by
  range/cone/horizon; the converged reference adds the lights' deterministic term),
  ``static_nodes`` (static BVH built once vs rebuilt every frame; 8 frames), ``visibility_reuse``
  (the cross-frame cache; 24-frame clips from the static camera and along the path, PSNR on
  the last frame), ``adaptive`` (adaptive sampling).
- ``agreement``: the oracle scene (thin Gaussians 0.5 px apart, 4x finer along face edges)
  rendered by this pass (MIS, 8x8 sub-pixels x 16 rays, box-averaged like Mitsuba's pixel filter)
  vs Mitsuba 3's direct illumination (``path``, ``max_depth = 2``, 4096 spp) of the same meshes,
  camera and HDRI with every part shaded by the paper's BRDF (``core.synth.mitsuba_paper``), for
  city.exr and sunset.exr. Details: interior/edge pixels, FLIP, the same frame against Mitsuba's
  ``principled`` BSDF (the dataset's material model), and the pass on Mitsuba's exact G-buffers.

Usage: ``python benchmarks/bench_pbr.py [--quick] [--runs N] [--threads N] [--skip-agreement | --agreement-only]``
(each keeps the other part from the existing output file).
Writes ``benchmarks/results/pbr.json`` and ``benchmarks/results/pbr_runtime_vs_error.png``
(``--quick`` writes ``pbr_quick.json`` / ``pbr_quick_runtime_vs_error.png`` unless ``--out``).
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import platform
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from core.pbr import EnvironmentMap  # noqa: E402
from core.pbr.lights import PointLight, SpotLight  # noqa: E402
from core.synth.oracle import OracleSettings, street_oracle, street_scene_graph  # noqa: E402
from core.pbr.render import ClipRenderer, PBRSettings, render_pbr, tonemap  # noqa: E402
from core.synth.config import profile  # noqa: E402
from core.synth.generate import load_envmap  # noqa: E402

CACHE = ROOT / "benchmarks" / ".cache"
#: Version of the estimator the cached converged references were computed with.
ESTIMATOR_VERSION = 1
RESULTS = ROOT / "benchmarks" / "results"


def load() -> float:
    return round(os.getloadavg()[0], 2)


def machine(threads: int) -> dict:
    model = "unknown"
    try:
        for line in open("/proc/cpuinfo", encoding="utf-8"):
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": model, "cores": os.cpu_count(), "threads": threads, "python": platform.python_version(),
            "torch": torch.__version__, "date": datetime.datetime.now().isoformat(timespec="seconds")}


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float(-10.0 * np.log10(max(mse, 1e-12)))


def flip(ref_ldr: np.ndarray, test_ldr: np.ndarray) -> float:
    import flip_evaluator

    _, mean, _ = flip_evaluator.evaluate(np.ascontiguousarray(ref_ldr, np.float32),
                                         np.ascontiguousarray(test_ldr, np.float32), "LDR", applyMagma=False)
    return float(mean)


def within_noise(p_with: list, p_without: list, floor_db: float = 0.02) -> bool:
    """Whether two sets of PSNRs (independent seeds) differ by no more than their noise: the
    difference of the means is at most twice its standard error (sample deviations of both sets),
    or at most ``floor_db`` (0.02 dB: the spread of one frame's PSNR over seeds at 64 rays on this
    scene is about 0.01 dB, and a single deterministic pair has no deviation to estimate)."""
    d = abs(statistics.fmean(p_with) - statistics.fmean(p_without))
    se2 = sum(statistics.variance(p) / len(p) for p in (p_with, p_without) if len(p) > 1)
    return bool(d <= max(floor_db, 2.0 * se2 ** 0.5))


def ldr(hdr) -> np.ndarray:
    h = hdr if isinstance(hdr, torch.Tensor) else torch.from_numpy(np.asarray(hdr))
    return tonemap(h.float(), 1.0, 2.2).numpy()


class Bench:
    def __init__(self, quick: bool, runs: int, threads: int):
        self.quick = quick
        self.runs = runs
        self.threads = threads
        if quick:
            self.cfg = profile("benchmark", width=96, height=64, street_length_m=60)
            self.budget = 8000
            self.ref_rays = 256
            self.rays = [4, 16, 64]
            self.clip_frames = 4
        else:
            self.cfg = profile("benchmark", street_length_m=60)
            self.budget = 50_000
            self.ref_rays = 4096
            self.rays = [4, 8, 16, 32, 64, 128, 256]
            self.clip_frames = 24
        t = time.perf_counter()
        self.graph, self.cams, self.street = street_scene_graph(
            self.cfg, tuple(range(self.cfg.num_frames)), settings=OracleSettings(max_spacing=1.0), budget=self.budget)
        self.env = EnvironmentMap(load_envmap("city"))
        self.n_gaussians = self.graph.compose(0.0).num
        print(f"scene: {self.cfg.width}x{self.cfg.height}, {self.n_gaussians} Gaussians "
              f"({len(self.graph.nodes)} moving nodes), city.exr, built in {time.perf_counter() - t:.1f} s")

    def settings(self, **kw) -> PBRSettings:
        base = dict(rays_per_pixel=64, sampling="mis", threads=self.threads)
        base.update(kw)
        return PBRSettings(**base)

    def lights(self):
        """Street lights on the poles (point, range 12 m) and headlights on the moving cars."""
        out = []
        for p in self.street.static_parts:
            if p.name.startswith("pole"):
                v = np.asarray(p.vertices)
                top = v[v[:, 2] > 5.8]  # the lamp arm; the light hangs under its far end
                far = top[np.argmax(np.abs(top[:, 1] - v[:, 1].mean()))]
                out.append(PointLight(tuple(far - np.array([0, 0, 0.1])), color=(1.0, 0.85, 0.6), intensity=60.0,
                                      range=12.0, name=p.name))
        for n in self.graph.nodes:
            for side in (-0.6, 0.6):
                out.append(SpotLight((2.25, side, -0.1), direction=(1.0, 0.0, -0.08), inner_deg=12, outer_deg=30,
                                     intensity=400.0, range=40.0, node=n.name, name=f"{n.name}_head"))
        return out

    # -- references --------------------------------------------------------------------------
    def key(self, what: str) -> str:
        """Cache key of a reference: the scene (oracle placement and map sources, configuration)
        and ESTIMATOR_VERSION (bump it when the kernel's estimator changes; speed-only kernel
        changes keep the converged references valid)."""
        h = hashlib.sha256()
        for f in ("core/synth/oracle.py", "core/pbr/envmap.py"):
            h.update((ROOT / f).read_bytes())
        h.update(repr((self.cfg, self.budget, self.ref_rays, what, ESTIMATOR_VERSION)).encode())
        return h.hexdigest()[:16]

    def reference(self, frame: int, camera: int | None = None) -> np.ndarray:
        """Converged HDR frame (ref_rays rays per pixel, MIS) at time ``frame`` seen from camera
        ``camera`` of the path (default: the frame's own camera), cached."""
        CACHE.mkdir(parents=True, exist_ok=True)
        cam = frame if camera is None else camera
        tag = f"frame{frame}" if cam == frame else f"frame{frame}_cam{cam}"
        path = CACHE / f"pbr_ref_{self.key(tag)}.npy"
        if path.exists():
            return np.load(path)
        t = time.perf_counter()
        r = ClipRenderer(self.graph, self.env, self.settings(rays_per_pixel=self.ref_rays, seed=999))
        img = r.render(self.cams[cam], time_s=frame * self.cfg.frame_dt, frame_index=frame).hdr.numpy()
        np.save(path, img)
        print(f"  reference frame {frame} (camera {cam}): {self.ref_rays} rays/pixel in {time.perf_counter() - t:.0f} s "
              f"(load {load()}) -> {path.name}")
        return img

    def light_term(self, frame: int) -> np.ndarray:
        """The lights' deterministic contribution O L_lights (HDR) at a frame (black environment)."""
        black = EnvironmentMap.constant(0.0, 8, 16)
        r = ClipRenderer(self.graph, black, self.settings(rays_per_pixel=1, sampling="env"), lights=self.lights())
        return r.render(self.cams[frame], time_s=frame * self.cfg.frame_dt, frame_index=frame).hdr.numpy()

    # -- measurements ------------------------------------------------------------------------
    def time_frame(self, settings: PBRSettings, frame: int = 0, lights=(), static_reuse: bool = True, runs=None):
        """Median time of ``runs`` renders of one frame, run k with seed ``settings.seed + k`` (so
        the runs also sample the estimator's noise); returns (median s, last result, info with
        the per-run times and results)."""
        r = ClipRenderer(self.graph, self.env, settings, lights=list(lights), static_reuse=static_reuse)
        times, loads, results = [], [], []
        for k in range(runs or self.runs):
            if r.context.cache is not None:
                r.context.cache.clear()
            r.settings = replace(settings, seed=settings.seed + k)
            loads.append(load())
            t = time.perf_counter()
            results.append(r.render(self.cams[frame], time_s=frame * self.cfg.frame_dt, frame_index=frame))
            times.append(time.perf_counter() - t)
        return statistics.median(times), results[-1], {"times": [round(x, 3) for x in times], "load": loads,
                                                       "setup_s": round(r.setup_seconds, 3), "results": results}

    def time_clip(self, settings: PBRSettings, frames: int, static_reuse: bool = True, camera: int | None = None):
        """Render ``frames`` frames of the clip (cars moving) from scratch (renderer, static BVH
        and cache included): along the camera path, or from the path's camera ``camera`` held
        still (a static camera)."""
        loads = [load()]
        t = time.perf_counter()
        r = ClipRenderer(self.graph, self.env, settings, static_reuse=static_reuse)
        outs = []
        for f in range(frames):
            outs.append(r.render(self.cams[f if camera is None else camera], time_s=f * self.cfg.frame_dt,
                                 frame_index=f))
        total = time.perf_counter() - t
        loads.append(load())
        hits = sum(o.counters.get("cache_hits", 0) for o in outs)
        look = sum(o.counters.get("cache_lookups", 0) for o in outs)
        return total, outs, {"load": loads, "cache_hit_rate": round(hits / look, 3) if look else None,
                             "per_frame_s": [round(o.timings["total"], 3) for o in outs]}

    def seeded_clips(self, settings: PBRSettings, frames: int, camera: int | None, ref_ldr: np.ndarray):
        """``self.runs`` clips, run k with seed ``settings.seed + k``: (median s, PSNRs of the last
        frame against ``ref_ldr``, info of the median run)."""
        runs = [self.time_clip(replace(settings, seed=settings.seed + k), frames, camera=camera)
                for k in range(self.runs)]
        med = statistics.median(r[0] for r in runs)
        info = min(runs, key=lambda r: abs(r[0] - med))[2]
        info["totals_s"] = [round(r[0], 2) for r in runs]
        return med, [psnr(ldr(r[1][-1].hdr), ref_ldr) for r in runs], info

    def runtime_vs_error(self, ref_ldr):
        rows = []
        for sampling in ("env", "mis"):
            for rays in self.rays:
                s = self.settings(rays_per_pixel=rays, sampling=sampling)
                med, res, info = self.time_frame(s)
                out = ldr(res.hdr)
                row = {"rays": rays, "sampling": sampling, "ms_per_frame": round(1000 * med, 1),
                       "psnr": round(psnr(out, ref_ldr), 2), "flip": round(flip(ref_ldr, out), 4)}
                rows.append(row)
                print(f"  {sampling:3s} {rays:4d} rays: {row['ms_per_frame']:8.1f} ms  PSNR {row['psnr']:6.2f} dB  "
                      f"FLIP {row['flip']:.4f}   (runs {info['times']}, load {info['load']})")
        return rows

    def skips(self, ref0, ref_last, frame_last, ref_static_last):
        """Each skip with and without, ``self.runs`` runs each with seeds 0, 1, ...: median time,
        mean PSNR, and whether the PSNR difference is within the seeds' noise (:func:`within_noise`)."""
        out = []
        ref = ldr(ref0)
        for name, kw_with, kw_without in (("sky", {}, {"skip_sky": False}),
                                          ("shadow_roulette", {}, {"roulette": 0.0}),
                                          ("adaptive", {"adaptive": True}, {})):
            t1, _, i1 = self.time_frame(self.settings(**kw_with))
            t0, _, i0 = self.time_frame(self.settings(**kw_without))
            out.append(self._skip(name, t1, t0, [psnr(ldr(r.hdr), ref) for r in i1.pop("results")],
                                  [psnr(ldr(r.hdr), ref) for r in i0.pop("results")], i1, i0))
        # lights culled per pixel (reference: converged environment + the lights' exact term)
        lights = self.lights()
        ref_l = ldr(ref0 + self.light_term(0))
        t1, _, i1 = self.time_frame(self.settings(cull_lights=True), lights=lights)
        t0, _, i0 = self.time_frame(self.settings(cull_lights=False), lights=lights)
        out.append(self._skip(f"light_culling ({len(lights)} lights)", t1, t0,
                              [psnr(ldr(r.hdr), ref_l) for r in i1.pop("results")],
                              [psnr(ldr(r.hdr), ref_l) for r in i0.pop("results")], i1, i0))
        # static nodes: 8 frames, static BVH once vs everything every frame (same seed: the
        # BVH does not change the estimate, so the images must match)
        nf = min(8, self.clip_frames)
        t1, o1, i1 = self.time_clip(self.settings(), nf, static_reuse=True)
        t0, o0, i0 = self.time_clip(self.settings(), nf, static_reuse=False)
        out.append(self._skip(f"static_nodes ({nf} frames)", t1, t0, [psnr(ldr(o1[0].hdr), ref)],
                              [psnr(ldr(o0[0].hdr), ref)], i1, i0))
        # visibility reuse across the frames of a clip: static camera (the clip_24_s clip) and
        # the moving camera path, PSNR of the last frame
        for what, camera, r_last in (("static camera", 0, ref_static_last), ("camera path", None, ref_last)):
            t1, p1, i1 = self.seeded_clips(self.settings(reuse_visibility=True), self.clip_frames, camera, ldr(r_last))
            t0, p0, i0 = self.seeded_clips(self.settings(), self.clip_frames, camera, ldr(r_last))
            out.append(self._skip(f"visibility_reuse ({self.clip_frames} frames, {what}; PSNR of frame {frame_last})",
                                  t1, t0, p1, p0, i1, i0))
        return out

    @staticmethod
    def _skip(name, t1, t0, p1: list, p0: list, i1, i0):
        m1, m0 = statistics.fmean(p1), statistics.fmean(p0)
        row = {"name": name, "s_with": round(t1, 3), "s_without": round(t0, 3), "psnr_with": round(m1, 2),
               "psnr_without": round(m0, 2), "psnr_runs_with": [round(x, 3) for x in p1],
               "psnr_runs_without": [round(x, 3) for x in p0], "within_noise": within_noise(p1, p0)}
        print(f"  skip {name}: {row['s_with']:.3f} s with, {row['s_without']:.3f} s without; PSNR "
              f"{m1:.3f} / {m0:.3f} dB (runs {row['psnr_runs_with']} / {row['psnr_runs_without']}; within noise: "
              f"{row['within_noise']})   (with {i1}, without {i0})")
        return row

    # -- agreement ---------------------------------------------------------------------------
    def agreement(self, hdri: str, *, spacing_px=0.5, edge_refine=4, ss=8, rays=16, spp=4096,
                  exact_gbuffers=False, principled_spp=0):
        """This pass on the dense oracle street vs Mitsuba's direct illumination (LDR PSNR).

        The reference is Mitsuba 3 (``llvm_ad_rgb``, ``path`` with ``max_depth = 2``, ``spp``
        samples, box pixel filter) with every part shaded by the paper's BRDF, the model this pass
        implements (:mod:`core.synth.mitsuba_paper`). ``principled_spp`` > 0 also compares the
        same render with Mitsuba's own ``principled`` BSDF (the dataset's ground truth; scalar
        variant, that many samples): the material-model gap on top. Our frame is rendered at
        ``ss`` x ``ss`` sub-pixels with ``rays`` rays each and box-averaged (Mitsuba's pixel
        filter). ``exact_gbuffers``: shade Mitsuba's own G-buffers (sampled at the sub-pixel
        centres) instead of the rasterised oracle (isolates the Gaussian approximation)."""
        from core.synth.mitsuba_backend import render_beauty, render_gbuffers
        from core.synth.mitsuba_paper import render_direct_paper

        cfg = profile("benchmark", width=self.cfg.width, height=self.cfg.height, street_length_m=90)
        if self.quick:
            spacing_px, rays, spp, ss = max(spacing_px, 1.5), min(rays, 16), min(spp, 64), min(ss, 2)
            principled_spp = min(principled_spp, 16)
        g, cams, parts = street_oracle(cfg, (0,), settings=OracleSettings(spacing_px=spacing_px, max_spacing=0.25,
                                                                          edge_refine=edge_refine))
        cam = cams[0]
        envnp = load_envmap(hdri)
        env = EnvironmentMap(envnp)
        CACHE.mkdir(parents=True, exist_ok=True)

        def reference(kind: str, n: int) -> np.ndarray:
            mpath = CACHE / f"mitsuba_{hdri}_{kind}_{cfg.width}x{cfg.height}_{n}.npy"
            if mpath.exists():
                return np.load(mpath)
            t = time.perf_counter()
            if kind == "paper":
                ref_ = render_direct_paper(parts, envnp, cam, spp=n, seed=7)
            else:
                ref_ = render_beauty(parts, envnp, cam, spp=n, max_depth=2, seed=7)
            np.save(mpath, ref_)
            print(f"    mitsuba {hdri} ({kind}) {n} spp: {time.perf_counter() - t:.0f} s")
            return ref_

        ref = reference("paper", spp)
        cs = cam.scaled(ss)
        s = PBRSettings(rays_per_pixel=rays, sampling="mis", threads=self.threads)
        t = time.perf_counter()
        if exact_gbuffers:
            from core.pbr.visibility import GaussianTracer

            gt = render_gbuffers(parts, cs)
            hit = (~gt["sky"])[..., None].astype(np.float32)
            gb = {"opacity": torch.from_numpy(hit), "depth": torch.from_numpy(gt["depth"] * hit),
                  "normal": torch.from_numpy(gt["normal"]), "albedo": torch.from_numpy(gt["albedo"]),
                  "roughness": torch.from_numpy(gt["roughness"]), "metallic": torch.from_numpy(gt["metallic"])}
            res = render_pbr(gb, cs, env, settings=s, tracers=[GaussianTracer.from_gaussians(g, s.trace)])
        else:
            res = ClipRenderer(g, env, s).render(cs)
        ours = res.hdr.reshape(cam.height, ss, cam.width, ss, 3).mean((1, 3)).numpy()
        el = time.perf_counter() - t
        # interior (5x5 neighbourhood on one surface in Mitsuba's G-buffers) vs edge pixels
        key_path = CACHE / f"mitsuba_gbuf_{cfg.width}x{cfg.height}.npz"
        if key_path.exists():
            gk = dict(np.load(key_path))
        else:
            gk = render_gbuffers(parts, pcam)
            np.savez(key_path, **gk)
        key = np.concatenate([gk["albedo"], gk["normal"], gk["sky"][..., None]], -1)
        same = np.ones(key.shape[:2], bool)
        for dy in range(-2, 3):
            for dx in range(-2, 3):
                same &= np.abs(np.roll(key, (dy, dx), (0, 1)) - key).max(-1) < 1e-4

        def compare(r):
            a, b = ldr(ours), ldr(r)
            return {"psnr": round(psnr(a, b), 2), "interior": round(psnr(a[same], b[same]), 2),
                    "edges": round(psnr(a[~same], b[~same]), 2),
                    "flip": round(flip(b, a), 4),
                    "ratio_interior": round(float(ours[same].mean() / max(r[same].mean(), 1e-12)), 4)}

        out = compare(ref)
        out.update({"edge_fraction": round(float((~same).mean()), 3), "gaussians": g.num, "seconds": round(el, 1),
                    "supersampling": ss, "rays_per_subpixel": rays, "mitsuba_spp": spp, "spacing_px": spacing_px,
                    "edge_refine": edge_refine, "exact_gbuffers": exact_gbuffers})
        if principled_spp:
            out["vs_principled"] = dict(compare(reference("principled", principled_spp)), mitsuba_spp=principled_spp)
        return out


def plot(rows, path: Path, title: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for sampling, mk in (("env", "o-"), ("mis", "s-")):
        r = [x for x in rows if x["sampling"] == sampling]
        t = [x["ms_per_frame"] / 1000 for x in r]
        axes[0].plot(t, [x["psnr"] for x in r], mk, label=sampling)
        axes[1].plot(t, [x["flip"] for x in r], mk, label=sampling)
        for x, tt in zip(r, t):
            axes[0].annotate(str(x["rays"]), (tt, x["psnr"]), fontsize=7)
    from matplotlib.ticker import FixedLocator, NullFormatter, ScalarFormatter

    t_all = [x["ms_per_frame"] / 1000 for x in rows]
    ticks = [v for v in (0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50) if min(t_all) / 1.5 <= v <= max(t_all) * 1.5]
    for ax, lab in ((axes[0], "PSNR (dB, LDR) vs converged"), (axes[1], "mean FLIP (LDR) vs converged")):
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(FixedLocator(ticks))
        ax.xaxis.set_major_formatter(ScalarFormatter())
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("seconds per frame")
        ax.set_ylabel(lab)
        ax.grid(True, alpha=0.3)
        ax.legend()
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def run_agreement(b: "Bench"):
    """The Mitsuba comparison: (agreement rows, details)."""
    agreement, details = [], {}
    print("agreement with Mitsuba (direct illumination, the paper's BRDF in Mitsuba, LDR PSNR):")
    for hdri in ("city", "sunset"):
        r = b.agreement(hdri, principled_spp=1024 if hdri == "city" else 0)
        agreement.append({"hdri": f"{hdri}.exr", "psnr": r["psnr"]})
        details[f"agreement_{hdri}"] = r
        print(f"  {hdri}: {r}")
    print("agreement diagnostics:")
    for name, kw in (("exact_gbuffers_city", dict(exact_gbuffers=True, ss=4)),):
        r = b.agreement("city", **kw)
        details[f"agreement_{name}"] = r
        print(f"  {name}: {r}")
    return agreement, details


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small smoke-test configuration")
    ap.add_argument("--runs", type=int, default=None, help="runs per timing (median); default 3 (quick: 1)")
    ap.add_argument("--threads", type=int, default=0, help="kernel threads (0 = every core)")
    ap.add_argument("--skip-agreement", action="store_true",
                    help="do not run the Mitsuba comparison (keep the one already in the output file)")
    ap.add_argument("--agreement-only", action="store_true",
                    help="run only the Mitsuba comparison (keep the timings already in the output file)")
    ap.add_argument("--out", type=Path, default=None, help="JSON path (default benchmarks/results/pbr[_quick].json)")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)  # torch's OpenMP threads would compete with the kernels' std::threads
    from core.pbr.visibility import default_threads

    threads = args.threads or default_threads()
    runs = args.runs or (1 if args.quick else 3)
    b = Bench(args.quick, runs, threads)
    info = machine(threads)
    info.update({"profile": "quick" if args.quick else "full", "resolution": [b.cfg.width, b.cfg.height],
                 "gaussians": b.n_gaussians, "hdri": "city.exr", "runs": runs, "reference_rays": b.ref_rays,
                 "load_start": load()})
    print(f"machine: {info['cpu']}, {info['cores']} cores, threads {threads}, profile {info['profile']}, "
          f"load {info['load_start']}")
    t_all = time.perf_counter()
    out = args.out or RESULTS / ("pbr_quick.json" if args.quick else "pbr.json")
    prev = json.loads(out.read_text()) if out.exists() else None
    if args.agreement_only:
        if prev is None:
            ap.error(f"--agreement-only: no earlier results in {out} to keep the timings of")
        agreement, details = run_agreement(b)
        prev["agreement"] = agreement
        pd = prev["machine"].setdefault("details", {})
        pd.update(details)
        pd["agreement_run"] = {"date": datetime.datetime.now().isoformat(timespec="seconds"),
                               "load_start": info["load_start"], "load_end": load(),
                               "total_s": round(time.perf_counter() - t_all, 1)}
        out.write_text(json.dumps(prev, indent=2) + "\n")
        print(f"wrote {out} (agreement only; timings kept from {prev['machine'].get('date')})")
        return 0
    ref0 = b.reference(0)
    last = b.clip_frames - 1
    ref_last = b.reference(last)
    ref_static_last = b.reference(last, camera=0)
    ref0_ldr = ldr(ref0)
    print("runtime vs error:")
    rows = b.runtime_vs_error(ref0_ldr)
    print("frame at 64 rays per pixel (default settings):")
    f64, res64, i64 = b.time_frame(b.settings(), runs=max(runs, 5 if not args.quick else 1))
    print(f"  frame_64_s = {f64:.3f} s median (runs {i64['times']}, load {i64['load']}, setup {i64['setup_s']} s); "
          f"PSNR {psnr(ldr(res64.hdr), ref0_ldr):.2f} dB; timings {res64.timings}")
    clips = {}
    for what, camera, r_last in (("static camera", 0, ref_static_last), ("camera path", None, ref_last)):
        print(f"clip of {b.clip_frames} frames, {what}, cars moving (64 rays, MIS, static BVH once, visibility cache):")
        c, p, ic = b.seeded_clips(b.settings(reuse_visibility=True), b.clip_frames, camera, ldr(r_last))
        ic["psnr_last"] = [round(x, 3) for x in p]
        clips[what] = (c, ic)
        print(f"  {c:.2f} s median of {ic['totals_s']} (load {ic['load']}, cache hit rate {ic['cache_hit_rate']}, per frame "
              f"{ic['per_frame_s']}); PSNR of frame {last}: {ic['psnr_last']} dB")
    c24, ic = clips["static camera"]
    print(f"  clip_24_s (static camera) = {c24:.2f} s; camera path {clips['camera path'][0]:.2f} s")
    print("skips:")
    skips = b.skips(ref0, ref_last, last, ref_static_last)
    i64.pop("results", None)
    details = {"frame_64": i64, "clip": ic, "clip_camera_path": clips["camera path"][1],
               "clip_camera_path_s": round(clips["camera path"][0], 2)}
    if not args.skip_agreement:
        agreement, d = run_agreement(b)
        details.update(d)
    else:  # keep the comparison of the earlier run (it does not depend on the timings)
        agreement = prev.get("agreement", []) if prev else []
        if prev:
            details.update({k: v for k, v in prev["machine"].get("details", {}).items() if k.startswith("agreement")})
    info["load_end"] = load()
    info["total_s"] = round(time.perf_counter() - t_all, 1)
    info["details"] = details
    result = {"runtime_vs_error": rows, "agreement": agreement, "frame_64_s": round(f64, 3),
              "clip_24_s": round(c24, 2), "skips": skips, "machine": info}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    png = out.with_name(out.stem + "_runtime_vs_error.png")
    plot(rows, png, f"PBR pass, {b.cfg.width}x{b.cfg.height}, {b.n_gaussians} Gaussians, city.exr, "
                    f"{threads} threads, {info['cpu']}")
    print(f"wrote {out} and {png} in {info['total_s']} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
