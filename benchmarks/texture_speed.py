#!/usr/bin/env python3
"""CPU cost of the per-pixel texture's two inner kernels, each against the form it replaced (same bytes).

    python benchmarks/texture_speed.py [--repeats 20]

* ``gradient_noise`` (render/texture.py) on the 300 x 300 points of one 600x600 frame's noise grid (the default
  ``shading_stride`` 2): the corner gradients from three contiguous per-key tables (``_corner_tables``) against the
  textbook form that gathers (N, 3) gradient rows per corner (the module before session 17; the same arithmetic,
  so the same bytes: checked here and in tests/test_texture.py).
* ``upsample_bilinear`` (render/raycast.py), the four noise fields from 300 x 300 to 600 x 600, against
  ``scipy.ndimage.map_coordinates(order=1, mode='nearest')`` per field at the hit pixels (what the ray caster called
  before; same bytes, checked here and in tests/test_raycast.py).

CPU seconds per call (``time.process_time``, median of ``--repeats``; single-threaded numpy), so other users' load
counts only through shared caches.  A frame calls ``gradient_noise`` 8 times (3 + 2 mottle octaves, 2 vessel, 1
region) and ``upsample_bilinear`` once.  Results: benchmarks/results/texture_speed.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
RESULTS = ROOT / "benchmarks" / "results"


def gradient_noise_rows(p: np.ndarray, key) -> np.ndarray:
    """The textbook form: each corner's gradient gathered as (N, 3) rows, its columns read strided."""
    from room_pipeline.render import texture as T

    p = np.asarray(p, dtype=np.float64)
    perm = T._perm_table(int(key))
    i0 = np.floor(p)
    f = (p - i0).astype(np.float32)
    ii = i0.astype(np.int64) & 255
    w = f * f * f * (f * (f * np.float32(6.0) - np.float32(15.0)) + np.float32(10.0))
    out = np.zeros(len(p), dtype=np.float32)
    X, Y, Z = [ii[:, 0], ii[:, 0] + 1], [ii[:, 1], ii[:, 1] + 1], [ii[:, 2], ii[:, 2] + 1]
    fx, fy, fz = [f[:, 0], f[:, 0] - 1], [f[:, 1], f[:, 1] - 1], [f[:, 2], f[:, 2] - 1]
    wx, wy, wz = [1 - w[:, 0], w[:, 0]], [1 - w[:, 1], w[:, 1]], [1 - w[:, 2], w[:, 2]]
    for dx in (0, 1):
        px = perm[X[dx]]
        for dy in (0, 1):
            pxy = perm[px + Y[dy]]
            wxy = wx[dx] * wy[dy]
            for dz in (0, 1):
                g = T._GRAD32[T._GRAD_OF[perm[pxy + Z[dz]]]]
                out += (wxy * wz[dz]) * (g[:, 0] * fx[dx] + g[:, 1] * fy[dy] + g[:, 2] * fz[dz])
    return out.astype(np.float64)


def timed(fn, repeats: int) -> float:
    fn()                                                     # warm caches and lazy tables
    t = []
    for _ in range(repeats):
        c0 = time.process_time()
        fn()
        t.append(time.process_time() - c0)
    return float(np.median(t))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--out", default="texture_speed")
    args = ap.parse_args()
    from scipy.ndimage import map_coordinates

    from room_pipeline.render.raycast import upsample_bilinear
    from room_pipeline.render.texture import _layer_key, gradient_noise

    rng = np.random.default_rng(0)
    pts = rng.uniform(-300.0, 300.0, (300 * 300, 3))            # mm / feature size: lattice units of one layer
    key = _layer_key(0, 3)
    same_noise = gradient_noise(pts, key).tobytes() == gradient_noise_rows(pts, key).tobytes()
    coarse = rng.standard_normal((300, 300, 4)).astype(np.float32)
    hit = rng.random((600, 600)) > 0.05
    yy, xx = np.nonzero(hit)
    coords = np.stack([yy / 2, xx / 2]).astype(np.float32)

    def mapc():
        return np.stack([map_coordinates(coarse[..., j], coords, order=1, mode="nearest") for j in range(4)], axis=1)

    def ups():
        return upsample_bilinear(coarse, 600, 600, 2)[hit]

    same_up = mapc().tobytes() == ups().tobytes()
    rows = [
        {"kernel": "gradient_noise (90,000 points)", "before": "(N, 3) gradient rows",
         "before_cpu_s": timed(lambda: gradient_noise_rows(pts, key), args.repeats),
         "after": "three per-key tables", "after_cpu_s": timed(lambda: gradient_noise(pts, key), args.repeats),
         "same_bytes": same_noise, "calls_per_frame": 8},
        {"kernel": "noise fields 300x300 -> 600x600 (4 fields, 95 % hits)", "before": "map_coordinates order 1",
         "before_cpu_s": timed(mapc, args.repeats), "after": "upsample_bilinear",
         "after_cpu_s": timed(ups, args.repeats), "same_bytes": same_up, "calls_per_frame": 1},
    ]
    for r in rows:
        r["speedup"] = r["before_cpu_s"] / r["after_cpu_s"]
        print(json.dumps(r), flush=True)
    saved = sum((r["before_cpu_s"] - r["after_cpu_s"]) * r["calls_per_frame"] for r in rows)
    doc = {"args": vars(args), "rows": rows, "saved_cpu_s_per_frame": saved, "load_avg": os.getloadavg(),
           "nproc": os.cpu_count()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{args.out}.json").write_text(json.dumps(doc, indent=1) + "\n")
    md = ["# Per-pixel texture kernels: CPU s per call, before / after (same bytes)", "",
          f"`python benchmarks/texture_speed.py --repeats {args.repeats}`; median of the repeats, "
          f"load average {doc['load_avg'][0]:.1f} on {doc['nproc']} cores.", "",
          "| kernel | before | CPU s | after | CPU s | speed-up | same bytes | calls per frame |",
          "|---|---|---|---|---|---|---|---|"]
    md += [f"| {r['kernel']} | {r['before']} | {r['before_cpu_s']:.4f} | {r['after']} | {r['after_cpu_s']:.4f} | "
           f"{r['speedup']:.2f}x | {r['same_bytes']} | {r['calls_per_frame']} |" for r in rows]
    md += ["", f"Saved per 600x600 frame at the default `shading_stride` 2: **{saved:.3f} CPU s**."]
    (RESULTS / f"{args.out}.md").write_text("\n".join(md) + "\n")
    print(f"saved per frame: {saved:.3f} CPU s")
    if not (same_noise and same_up):
        sys.exit(1)


if __name__ == "__main__":
    main()
