"""Rasterizer benchmark on a CUDA machine: gsplat vs the torch reference on the GPU, with
the numba CPU backend on the same machine's host cores for scale, and their agreement.

Usage:  python benchmarks/rasterizer_cuda.py [--quick] [--repeats R]

Needs a CUDA device and the ``[cuda]`` extra (gsplat); without them it prints a JSON object
saying what is missing and exits 0, so the script is safe anywhere. Its first run, on an
H200: docs/experiments/2026-11-27-first-cuda-run.md. Progress goes to stderr; the last
stdout line is one JSON object.

Scenes are ``cogs.render.scenes.splat_scene`` (as in benchmarks/rasterizer.py: all
Gaussians in the frustum, 3-sigma radii ~2-10 px), at the CPU benchmark's sizes and at two
sizes a GPU user trains at (960x540 with 200k and 1920x1080 with 1M Gaussians). GPU times
are medians of CUDA-synchronised wall-clock repeats after a warm-up; "fwd_bwd" is forward
plus backward with fixed random upstream gradients on colour, alpha and depth down to the
leaf parameters, as in the CPU benchmark.

``gsplat_first_call_s`` is gsplat's first rasterization in this process: the load of its
compiled CUDA extension, or its JIT compilation when no build is cached (minutes).

``parity`` compares gsplat with the torch reference on the GPU at 256x192 / 20k: max abs
difference of colour, alpha, depth (relative to the largest depth) and the relative L2
error of each parameter's gradient. The reference clamps alpha at 0.99 and gsplat at
0.999, so a dense scene with opaque splats differs there by design (docs/rendering.md);
the parity *tests* use a scene that stays clear of the clamp.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import cogs  # noqa: F401  (before torch: torch's OpenMP wait policy as the cogs command has it)
import torch
from rasterizer import Case, times_ms  # the CPU benchmark beside this file: its scenes and timer


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def median_ms(fn, repeats: int, sync) -> tuple[float, float]:
    times = times_ms(fn, repeats, sync)
    return statistics.median(times), min(times)


def parity(case: Case) -> dict:
    outs, grads = {}, {}
    for backend in ("gsplat", "torch"):
        out = case.run(backend, True)
        outs[backend] = out
        grads[backend] = [p.grad.clone() for p in case.params]
    a, b = outs["gsplat"], outs["torch"]
    a_c, a_a, a_d, b_c, b_a, b_d = (x.detach() for x in (a.colors, a.alpha, a.depth, b.colors, b.alpha, b.depth))
    names = ("means", "quats", "scales", "opacities", "colors")
    return {
        "colors_max_abs": float((a_c - b_c).abs().max()),
        "alpha_max_abs": float((a_a - b_a).abs().max()),
        "depth_max_abs_rel": float((a_d - b_d).abs().max() / b_d.abs().max()),
        "pixels_alpha_over_0_99": int((b_a > 0.99).sum()),
        "grad_rel_l2": {n: float((ga - gb).norm() / gb.norm().clamp_min(1e-30))
                        for n, ga, gb in zip(names, grads["gsplat"], grads["torch"])},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="smoke run: small sizes, few repeats")
    ap.add_argument("--repeats", type=int, default=None, help="GPU repeats (default 50, quick 5)")
    ap.add_argument("--no-cpu", action="store_true", help="skip the host CPU backend column")
    args = ap.parse_args()

    result = {"benchmark": "rasterizer_cuda", "torch_version": torch.__version__}
    if not torch.cuda.is_available():
        result["skipped"] = "no CUDA device"
        print(json.dumps(result))
        return
    from cogs.render.gsplat_backend import gsplat_available

    if not gsplat_available():
        result["skipped"] = "gsplat is not installed (pip install -e '.[cuda]')"
        print(json.dumps(result))
        return
    import gsplat
    import numba

    from cogs.render import count_pairs, warmup

    dev = torch.device("cuda")
    props = torch.cuda.get_device_properties(dev)
    result.update({
        "gpu": props.name, "gpu_memory_gib": round(props.total_memory / 2**30, 1),
        "cuda_version": torch.version.cuda, "gsplat_version": gsplat.__version__,
        "host_cpu_count": os.cpu_count(), "numba_threads": numba.get_num_threads(),
    })
    sync = torch.cuda.synchronize
    t0 = time.perf_counter()
    Case(100, 64, 48, dev).run("gsplat", True)
    sync()
    result["gsplat_first_call_s"] = round(time.perf_counter() - t0, 2)
    result["cpu_warmup_s"] = round(warmup(), 2)

    reps = args.repeats or (5 if args.quick else 50)
    sizes = [(128, 128, 5_000), (256, 192, 20_000), (256, 192, 50_000),
             (960, 540, 200_000), (1920, 1080, 1_000_000)]
    if args.quick:
        sizes = [(128, 128, 5_000), (256, 192, 20_000)]
    cases = []
    for width, height, n in sizes:
        case = Case(n, width, height, dev)
        row = {"width": width, "height": height, "n_gaussians": n}
        small = width * height <= 256 * 192
        if small:
            s = case.params
            row["pairs"] = count_pairs(*(t.detach() for t in s[:3]), case.viewmat, case.K,
                                       width, height)
        log(f"{width}x{height} N={n}")
        backends = ["gsplat"] + (["torch"] if small else [])
        for backend in backends:
            case.run(backend, True)  # warm-up
            fwd, _ = median_ms(lambda: case.run(backend, False), reps if backend == "gsplat" else 5, sync)
            fb, fb_min = median_ms(lambda: case.run(backend, True), reps if backend == "gsplat" else 5, sync)
            row[f"{backend}_cuda"] = {"fwd_ms": round(fwd, 3), "fwd_bwd_ms": round(fb, 3),
                                      "fwd_bwd_min_ms": round(fb_min, 3)}
            log(f"  {backend} (cuda): fwd {fwd:.2f} ms, fwd+bwd {fb:.2f} ms")
        if not args.no_cpu and n <= 200_000:
            host = Case(n, width, height, torch.device("cpu"))
            host.run("cpu", True)
            fwd, _ = median_ms(lambda: host.run("cpu", False), 5, lambda: None)
            fb, fb_min = median_ms(lambda: host.run("cpu", True), 5, lambda: None)
            row["cpu_host"] = {"fwd_ms": round(fwd, 2), "fwd_bwd_ms": round(fb, 2),
                               "fwd_bwd_min_ms": round(fb_min, 2)}
            log(f"  cpu (host, {numba.get_num_threads()} threads): fwd {fwd:.1f} ms, fwd+bwd {fb:.1f} ms")
        if (width, height, n) == (256, 192, 20_000):
            row["parity_gsplat_vs_torch"] = parity(case)
        cases.append(row)
        del case
        torch.cuda.empty_cache()
    result["cases"] = cases
    result["max_memory_allocated_gib"] = round(torch.cuda.max_memory_allocated() / 2**30, 2)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
