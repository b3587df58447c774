"""Feature matching benchmark: ``cogs.preprocess.sfm.match_descriptors`` per frame pair.

Usage:  python benchmarks/matching.py [--sizes 300,1000,3800,8192] [--repeats R]

Progress goes to stderr; the last stdout line is one JSON object.

Descriptors: SIFT-like uint8 vectors (non-negative, unit length scaled by 512, clipped at
255), the second frame's first half noisy copies of the first frame's, so about half of
them match as in overlapping views. For each size N (features in both frames) it times the
whole call and, apart, the float32 product it starts with (the part no exact matcher can
skip), and reports the minimum over the repeats (the steadiest estimate of the work on a
shared machine) with the matches found. ``overhead`` = whole / product: what finding the two
nearest each way and the tests add to the product.

For scale: COLMAP's default CPU matcher (faiss) took 1.9 s for the 91 pairs of the
basketball clip at 960 px (about 3,800 features a frame), i.e. 21 ms a pair, and is not the
same from run to run (docs/experiments/2026-11-28-feet-seen-end-on.md).
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np


def sift_like(n: int, rng: np.random.Generator, like: np.ndarray | None = None) -> np.ndarray:
    """[n, 128] uint8; with ``like``, its first half perturbed and the rest fresh."""
    d = np.abs(rng.normal(size=(n, 128)))
    if like is not None:
        h = len(like) // 2
        d[:h] = like[:h].astype(np.float64) / 512.0 + 0.02 * np.abs(rng.normal(size=(h, 128)))
    return np.clip(np.round(512 * d / np.linalg.norm(d, axis=1, keepdims=True)), 0, 255).astype(np.uint8)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="300,1000,3800,8192", help="features per frame, comma-separated")
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    from cogs.preprocess.sfm import match_descriptors

    rng = np.random.default_rng(0)
    match_descriptors(sift_like(8, rng), sift_like(8, rng))  # compile (or load the cached kernel)
    rows = []
    for n in (int(s) for s in args.sizes.split(",")):
        d1 = sift_like(n, rng)
        d2 = sift_like(n, rng, like=d1)
        whole, product = [], []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            found = match_descriptors(d1, d2)
            t1 = time.perf_counter()
            d1.astype(np.float32) @ d2.astype(np.float32).T
            t2 = time.perf_counter()
            whole.append(t1 - t0)
            product.append(t2 - t1)
        row = {"features": n, "matches": int(len(found)), "pair_ms": round(1000 * min(whole), 2),
               "product_ms": round(1000 * min(product), 2), "overhead": round(min(whole) / min(product), 2)}
        print(row, file=sys.stderr)
        rows.append(row)
    print(json.dumps({"benchmark": "matching", "repeats": args.repeats, "sizes": rows}))


if __name__ == "__main__":
    main()
