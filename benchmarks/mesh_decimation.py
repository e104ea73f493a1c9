#!/usr/bin/env python3
"""Mesh decimation: triangle count vs accuracy vs time.

For a synthetic capsule tree (and the default phantom when
``room_pipeline.anatomy.phantom`` is present) the ground-truth SDF is meshed
with ``extract_surface`` at several decimation targets (fraction of faces kept:
1.0 = none, 0.5, 0.25, 0.1, 0.05; error bound disabled so the target is
applied as asked).  Each mesh is compared with the exact tree surface
(``evaluate.surface.mesh_surface_distance``: mean / p95 / max distance in
voxels, mesh -> truth and truth -> mesh) and with the pre-decimation mesh; the
last column says whether the default bound of ``conf/mesh/default.yaml``
would have accepted it.  Prints a table and saves
benchmarks/results/mesh_decimation.{json,md}.

    python benchmarks/mesh_decimation.py [--no-phantom]
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _synthetic import capsule_tree, rasterise  # noqa: E402

from room_pipeline.anatomy.mesh import MeshParams, extract_surface  # noqa: E402
from room_pipeline.evaluate.surface import mesh_surface_distance  # noqa: E402

FRACTIONS = (1.0, 0.5, 0.25, 0.1, 0.05)
RESULTS = ROOT / "benchmarks" / "results"


def cases(with_phantom: bool):
    tree = capsule_tree(generations=5)
    _, sdf = rasterise(tree, 0.7e-3)
    yield "capsule_tree_g5_0.7mm", tree, sdf
    if with_phantom:
        try:
            from room_pipeline.anatomy.phantom import PhantomParams, make_phantom
        except ImportError:
            return
        ph = make_phantom(PhantomParams(), seed=0)
        yield "phantom_seed0", ph.tree, ph.sdf


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--no-phantom", action="store_true")
    args = ap.parse_args()
    default = MeshParams()
    rows = []
    for name, tree, sdf in cases(not args.no_phantom):
        voxel = float(np.exp(np.mean(np.log(sdf.spacing))))
        for frac in FRACTIONS:
            p = dataclasses.replace(default, decimation_fraction=frac, decimation_max_error_mm=1e3,
                                    decimation_p95_error_mm=1e3, decimation_max_retries=0)
            t0 = time.perf_counter()
            res = extract_surface(sdf, p)
            wall = time.perf_counter() - t0
            e = mesh_surface_distance(res.mesh, tree, voxel)
            r = res.report
            accepted = (r["decimation_error_max_m"] <= default.decimation_max_error_mm * 1e-3
                        and r["decimation_error_p95_m"] <= default.decimation_p95_error_mm * 1e-3)
            row = {"case": name, "shape": list(sdf.shape), "voxel_mm": round(voxel * 1e3, 4),
                   "target_fraction": frac, "n_faces": r["n_faces"],
                   "n_faces_before": r["n_faces_before_decimation"],
                   "mean_vox": e["m2t_mean_vox"], "p95_vox": e["m2t_p95_vox"], "max_vox": e["m2t_max_vox"],
                   "t2m_mean_vox": e["t2m_mean_vox"], "t2m_p95_vox": e["t2m_p95_vox"],
                   "hausdorff_vox": e["hausdorff_vox"],
                   "dec_err_max_mm": r["decimation_error_max_m"] * 1e3,
                   "dec_err_p95_mm": r["decimation_error_p95_m"] * 1e3,
                   "watertight": r["watertight"], "manifold": r["manifold"],
                   "extract_wall_s": wall, "accepted_by_default_bound": bool(accepted)}
            rows.append(row)
            print(f"{name:24s} keep {frac:5.2f} faces {row['n_faces']:8d}  mean {row['mean_vox']:.3f} "
                  f"p95 {row['p95_vox']:.3f} max {row['max_vox']:.3f} vox  t2m p95 {row['t2m_p95_vox']:.3f}  "
                  f"dec.err max {row['dec_err_max_mm']:.3f} mm  {wall:6.2f} s  "
                  f"{'ok' if accepted else 'over bound'}", flush=True)
    RESULTS.mkdir(parents=True, exist_ok=True)
    meta = {"benchmark": "mesh_decimation", "default_params": dataclasses.asdict(default),
            "note": "ground-truth SDF in; distances to the exact capsule-union surface; "
                    "extract_wall_s = whole extract_surface (marching cubes, cleaning, smoothing, decimation, "
                    "decimation-error measurement)", "rows": rows}
    (RESULTS / "mesh_decimation.json").write_text(json.dumps(meta, indent=2) + "\n")
    hdr = ("| case | keep | faces | mean (vox) | p95 (vox) | max (vox) | truth->mesh p95 (vox) | "
           "decim. err max / p95 (mm) | watertight | time (s) | default bound |")
    lines = ["# Mesh decimation: faces vs accuracy vs time", "",
             "Ground-truth SDF -> `extract_surface` (Taubin 10, quadric edge collapse, preservetopology). "
             "Distances mesh -> exact tree surface in voxels.", "", hdr, "|" + "---|" * 11]
    for r in rows:
        lines.append(f"| {r['case']} | {r['target_fraction']:.2f} | {r['n_faces']} | {r['mean_vox']:.3f} | "
                     f"{r['p95_vox']:.3f} | {r['max_vox']:.3f} | {r['t2m_p95_vox']:.3f} | "
                     f"{r['dec_err_max_mm']:.3f} / {r['dec_err_p95_mm']:.3f} | {r['watertight']} | "
                     f"{r['extract_wall_s']:.2f} | {'ok' if r['accepted_by_default_bound'] else 'over'} |")
    (RESULTS / "mesh_decimation.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
