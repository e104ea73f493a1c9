#!/usr/bin/env python3
"""SDF from a binary mask: error vs time of plain EDT, half-voxel EDT and the sub-voxel method.

The true mask (voxel centre inside <=> exact SDF < 0) goes in; the error is
measured against the exact SDF at voxel centres within 3 mm of the wall
(exact values only): MAE / p95 / max in voxels.  Cases: a synthetic capsule
tree at 0.7 mm isotropic and at anisotropic spacing, and the default phantom
(its stored exact SDF) when ``room_pipeline.anatomy.phantom`` is present.
Prints a table and saves benchmarks/results/sdf_methods.{json,md}.

    python benchmarks/sdf_methods.py [--no-phantom]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _synthetic import capsule_tree, rasterise  # noqa: E402

from room_pipeline.anatomy.sdf import SdfParams, compute_sdf  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
BAND = 3e-3
METHODS = {
    "edt (voxel centres)": SdfParams(method="edt"),
    "edt - half voxel": SdfParams(method="edt_halfvoxel"),
    "smooth_mc, no curvature corr.": SdfParams(curvature_correction=False),
    "smooth_mc sigma 0.5": SdfParams(sigma_voxels=0.5),
    "smooth_mc (default)": SdfParams(),
}


def errors(est: np.ndarray, true: np.ndarray, exact: np.ndarray, voxel: float) -> dict:
    sel = exact & (np.abs(true) <= BAND)
    e = np.abs(est[sel].astype(np.float64) - true[sel]) / voxel
    return {"n": int(sel.sum()), "mae_vox": float(e.mean()), "p95_vox": float(np.percentile(e, 95)),
            "max_vox": float(e.max()),
            "bias_vox": float((est[sel].astype(np.float64) - true[sel]).mean() / voxel),
            "sign_mismatch_in_mask": float(np.mean((est[sel] < 0) != (true[sel] < 0)))}


def cases(with_phantom: bool):
    tree = capsule_tree(generations=5)
    for name, sp in (("capsule_tree_0.7mm", 0.7e-3), ("capsule_tree_0.6x0.7x1.2mm", (0.6e-3, 0.7e-3, 1.2e-3))):
        mask, sdf = rasterise(tree, sp)
        yield name, mask, sdf.data, np.ones(sdf.shape, bool)
    if with_phantom:
        try:
            from room_pipeline.anatomy.phantom import PhantomParams, make_phantom
        except ImportError:
            return
        ph = make_phantom(PhantomParams(), seed=0)
        yield "phantom_seed0", ph.mask, ph.sdf.data, ph.sdf_exact.data.astype(bool)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-phantom", action="store_true")
    args = ap.parse_args()
    rows = []
    for name, mask, true, exact in cases(not args.no_phantom):
        voxel = float(np.exp(np.mean(np.log(mask.spacing))))
        compute_sdf(mask, SdfParams())  # warm-up (imports)
        for label, p in METHODS.items():
            t0 = time.perf_counter()
            est = compute_sdf(mask, p)
            wall = time.perf_counter() - t0
            row = {"case": name, "shape": list(mask.shape), "lumen_voxels": int((mask.data > 0).sum()),
                   "method": label, "wall_s": wall, **errors(est.data, true, exact, voxel)}
            rows.append(row)
            print(f"{name:28s} {label:32s} MAE {row['mae_vox']:.3f} p95 {row['p95_vox']:.3f} "
                  f"max {row['max_vox']:.3f} bias {row['bias_vox']:+.3f} vox  {wall:6.2f} s", flush=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "sdf_methods.json").write_text(json.dumps({"benchmark": "sdf_methods", "band_m": BAND,
                                                         "rows": rows}, indent=2) + "\n")
    lines = ["# SDF from a binary mask: error vs time", "",
             f"True mask in; error against the exact SDF at voxel centres within {BAND * 1e3:.0f} mm of the wall.",
             "", "| case | shape | method | MAE (vox) | p95 (vox) | max (vox) | bias (vox) | time (s) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['case']} | {'x'.join(map(str, r['shape']))} | {r['method']} | {r['mae_vox']:.3f} | "
                     f"{r['p95_vox']:.3f} | {r['max_vox']:.3f} | {r['bias_vox']:+.3f} | {r['wall_s']:.2f} |")
    (RESULTS / "sdf_methods.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
