"""Benchmark of the tile rasterizer (core.raster): forward / backward ms and peak extra memory.

Scene: Gaussians uniformly spread over the image (uniform in pixel coordinates) at depths
2..10 m in front of an OpenCV camera at the origin, random rotations, anisotropic scales chosen
so that on average ``--overlap`` (default 80) Gaussians overlap each pixel (the opacity-aware
footprint ``o * g >= 1/255``), opacities uniform in [0.05, 0.95]. The script prints the measured
per-pixel counts: overlapping (compositing without early stop), evaluated and contributing
(with the default early stop at T < 1e-4).

Timing: forward = one ``rasterize`` call (projection, binning, compositing); backward = one
``loss.backward()`` of a random linear loss over all 13 channels (rasterizer backward plus the
torch autograd of the projection). Medians over ``--runs`` runs after ``--warmup`` runs.
Peak extra memory: each configuration also runs in a fresh subprocess that builds the scene,
warms the kernels up on a tiny scene, resets the kernel's RSS high-water mark (``echo 5 >
/proc/self/clear_refs``), reads the current RSS, runs one forward + backward, and reads the
high-water mark (``VmHWM``): the delta is what a forward + backward adds at peak, including
torch allocations, the kernels' own buffers and the input gradients. (Falls back to the
``ru_maxrss`` delta where clear_refs is unavailable, which can under-report.)

Other processes compete for the two cores on shared machines: the 1-minute load average before
and after each configuration is printed and stored, so a slow run can be told from a slow kernel.

Usage: ``python benchmarks/bench_raster.py [--profile quick|full] [--threads N]``.
Writes ``benchmarks/results/raster.json`` (a JSON list of runs).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import torch  # noqa: E402

from core.camera import Camera  # noqa: E402
from core.raster import RasterSettings, rasterize  # noqa: E402

PROFILES = {
    "quick": [(320, 213, 50_000)],
    "full": [(320, 213, 50_000), (960, 640, 200_000)],
}


def make_scene(width: int, height: int, n: int, overlap: float = 80.0, seed: int = 0,
               dtype=torch.float32):
    """A dense random scene and its camera; returns (tensors list, :class:`core.camera.Camera`)."""
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=torch.float64)

    f = 0.9 * width
    cx, cy = width / 2.0, height / 2.0
    z = 2.0 + 8.0 * rand(n)
    u = rand(n) * (width + 20) - 10
    v = rand(n) * (height + 20) - 10
    means = torch.stack([(u - cx) / f * z, (v - cy) / f * z, z], -1)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    opac = 0.05 + 0.9 * rand(n)
    aniso = torch.exp(0.5 * torch.randn(n, 3, generator=g, dtype=torch.float64))
    # Footprint area (px^2) of a Gaussian with screen sigma s px: pi s^2 * 2 ln(255 o).
    target_area = overlap * width * height / n
    mean_level = float((2.0 * torch.log(255.0 * opac)).mean())
    sigma_px = math.sqrt(max(target_area / (math.pi * mean_level) - 0.3, 0.05))
    geo = torch.exp(torch.log(aniso).mean(-1, keepdim=True))
    scales = (sigma_px * z / f)[:, None] * aniso / geo
    colors, albedo = rand(n, 3), rand(n, 3)
    normals = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    rough, metal = rand(n), rand(n)
    tensors = [t.to(dtype) for t in (means, quats, scales, opac, colors, normals, albedo, rough, metal)]
    cam = Camera.from_intrinsics(torch.eye(4, dtype=dtype), f, f, cx, cy, width, height)
    return tensors, cam


def _forward_backward(tensors, cam, settings, weights=None):
    leaves = [t.detach().clone().requires_grad_() for t in tensors]
    t0 = time.perf_counter()
    out = rasterize(*leaves, cam, settings=settings)
    t1 = time.perf_counter()
    if weights is None:
        weights = torch.rand(out.packed.shape, generator=torch.Generator().manual_seed(1), dtype=out.packed.dtype)
    loss = (out.packed * weights).sum()
    t2 = time.perf_counter()
    loss.backward()
    t3 = time.perf_counter()
    return out, (t1 - t0) * 1e3, (t3 - t2) * 1e3, weights


def measure_memory(width: int, height: int, n: int, threads: int) -> float:
    """Peak extra RSS (MB) of one forward + backward, in a fresh subprocess."""
    code = f"""
import resource, sys, torch
sys.path.insert(0, {str(ROOT)!r})
from benchmarks.bench_raster import make_scene, _forward_backward
from core.raster import RasterSettings
s = RasterSettings(threads={threads})
t, c = make_scene(16, 16, 50)
_forward_backward(t, c, s)
tensors, cam = make_scene({width}, {height}, {n})
leaves = [x.detach().clone().requires_grad_() for x in tensors]
w = torch.rand({height}, {width}, 13)
from core.raster import rasterize
def status(key):
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key):
                return int(line.split()[1])  # kB
try:  # reset the RSS high-water mark (Linux >= 4.0) so earlier peaks (imports) do not hide ours
    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")
    before, key = status("VmRSS:"), "VmHWM:"
except OSError:
    before, key = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, None
out = rasterize(*leaves, cam, settings=s)
(out.packed * w).sum().backward()
after = status(key) if key else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print((after - before) / 1024.0)
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return float(res.stdout.strip().splitlines()[-1])


def machine() -> dict:
    model = "unknown"
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cpu": model, "cores": cores, "python": platform.python_version(), "torch": torch.__version__}


def run(profile: str, threads: int | None, runs: int, warmup: int, overlap: float) -> list[dict]:
    mach = machine()
    settings = RasterSettings(threads=threads)
    print(f"machine: {mach['cpu']}, {mach['cores']} cores | profile: {profile} | threads: {settings.num_threads}")
    results = []
    for width, height, n in PROFILES[profile]:
        tensors, cam = make_scene(width, height, n, overlap=overlap)
        # per-pixel counts
        with torch.no_grad():
            no_stop = rasterize(*tensors, cam, settings=RasterSettings(threads=threads, transmittance_min=0.0,
                                                                        collect_stats=True))
            normal = rasterize(*tensors, cam, settings=RasterSettings(threads=threads, collect_stats=True))
        overl = float(no_stop.stats[..., 1].double().mean())
        evaluated = float(normal.stats[..., 0].double().mean())
        contributed = float(normal.stats[..., 1].double().mean())
        fwd, bwd = [], []
        weights = None
        load_before = os.getloadavg()[0]
        for i in range(warmup + runs):
            _, f_ms, b_ms, weights = _forward_backward(tensors, cam, settings, weights)
            if i >= warmup:
                fwd.append(f_ms)
                bwd.append(b_ms)
        load_after = os.getloadavg()[0]
        peak = measure_memory(width, height, n, settings.num_threads)
        row = {
            "width": width,
            "height": height,
            "gaussians": n,
            "forward_ms": round(statistics.median(fwd), 2),
            "backward_ms": round(statistics.median(bwd), 2),
            "peak_extra_mb": round(peak, 1),
            "forward_ms_min": round(min(fwd), 2),
            "backward_ms_min": round(min(bwd), 2),
            "threads": settings.num_threads,
            "runs": runs,
            "profile": profile,
            "dtype": "float32",
            "overlapping_per_pixel": round(overl, 1),
            "evaluated_per_pixel": round(evaluated, 1),
            "contributed_per_pixel": round(contributed, 1),
            "tile_pairs": normal.num_tile_pairs,
            "visible": normal.num_visible,
            "mean_opacity": round(float(normal.opacity.mean()), 4),
            "load_avg_1min": [round(load_before, 2), round(load_after, 2)],
            "machine": mach,
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        }
        results.append(row)
        print(f"{width}x{height} ({width * height} px), {n} Gaussians: forward {row['forward_ms']:.1f} ms, "
              f"backward {row['backward_ms']:.1f} ms (medians of {runs}; min {row['forward_ms_min']:.1f} / "
              f"{row['backward_ms_min']:.1f}), peak extra {row['peak_extra_mb']:.0f} MB | "
              f"per pixel: overlapping {overl:.1f}, evaluated {evaluated:.1f}, contributed {contributed:.1f} | "
              f"tile pairs {normal.num_tile_pairs}, mean opacity {row['mean_opacity']} | "
              f"load avg {load_before:.2f} -> {load_after:.2f}")
    return results


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", choices=sorted(PROFILES), default="full")
    ap.add_argument("--threads", type=int, default=None)
    ap.add_argument("--runs", type=int, default=9)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--overlap", type=float, default=80.0)
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "raster.json")
    ap.add_argument("--no-write", action="store_true")
    a = ap.parse_args(argv)
    results = run(a.profile, a.threads, a.runs, a.warmup, a.overlap)
    if not a.no_write:
        a.out.parent.mkdir(parents=True, exist_ok=True)
        a.out.write_text(json.dumps(results, indent=2) + "\n")
        print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
