#!/usr/bin/env python3
"""Trajectory planning speed and quality on the default phantom tree.

For every leaf up to generation 4 of the default phantom (seed 0; graph from
the exact capsule tree sampled every 1 mm) a trajectory is planned with the
exact SDF (:meth:`AirwayTree.sdf`) and, with ``--volume``, with the phantom's
rasterised SDF volume through trilinear interpolation.  ``unreachable:
nearest`` so every target gives a path; unreached targets are listed.
Prints time per path, max curvature vs kappa_max and min clearance (absolute
and minus the required margin), and saves benchmarks/results/trajectory.{json,md}.

    python benchmarks/trajectory.py [--volume] [--max-generation 4]
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from room_pipeline.anatomy.centreline import from_airway_tree
from room_pipeline.anatomy.phantom import PhantomParams, grow_tree
from room_pipeline.planning.trajectory import TrajectoryParams, as_sdf_fn, plan_path, select_targets

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def run(name: str, graph, sdf, params: TrajectoryParams) -> list[dict]:
    fn = as_sdf_fn(sdf)
    rows = []
    for bid in select_targets(graph, params):
        t0 = time.perf_counter()
        tr = plan_path(graph, bid, fn, params)
        dt = time.perf_counter() - t0
        s = tr.summary()
        rows.append({"sdf": name, "target_branch": int(bid), "generation": int(graph.branch(bid).generation),
                     "time_s": dt, "frames": s["frames"], "length_mm": s["length_m"] * 1e3,
                     "duration_s": s["duration_s"], "max_curvature_per_m": s["max_curvature_per_m"],
                     "kappa_max_per_m": s["kappa_max_per_m"], "min_clearance_mm": s["min_clearance_m"] * 1e3,
                     "min_clearance_minus_margin_mm": s["min_clearance_minus_margin_m"] * 1e3,
                     "reached": tr.target.reached, "note": tr.target.note})
        r = rows[-1]
        print(f"{name:7s} branch {bid:4d} gen {r['generation']}  {dt:5.2f} s  {r['frames']:4d} frames  "
              f"L {r['length_mm']:6.1f} mm  kappa {r['max_curvature_per_m']:5.1f}/{r['kappa_max_per_m']:.1f} 1/m  "
              f"clear {r['min_clearance_mm']:5.2f} mm (margin +{r['min_clearance_minus_margin_mm']:.3f})"
              f"{'' if r['reached'] else '  NOT REACHED: ' + r['note']}", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--volume", action="store_true", help="also plan with the rasterised phantom SDF (slow to build)")
    ap.add_argument("--max-generation", type=int, default=4)
    args = ap.parse_args()
    pp = PhantomParams()
    tree = grow_tree(pp, np.random.default_rng(0))
    graph = from_airway_tree(tree, 1e-3)
    params = TrajectoryParams(targets="leaves", max_generation=args.max_generation, unreachable="nearest",
                              start_offset_mm=0.0, min_lumen_radius_mm=0.0)
    rows = run("exact", graph, tree, params)
    if args.volume:
        from room_pipeline.anatomy.phantom import make_phantom
        t0 = time.perf_counter()
        ph = make_phantom(pp, seed=0)
        print(f"phantom rasterised in {time.perf_counter() - t0:.1f} s", flush=True)
        rows += run("volume", graph, ph.sdf, params)
    summary = {}
    for name in sorted({r["sdf"] for r in rows}):
        sel = [r for r in rows if r["sdf"] == name]
        t = np.array([r["time_s"] for r in sel])
        summary[name] = {"paths": len(sel), "reached": int(sum(r["reached"] for r in sel)),
                         "time_per_path_mean_s": float(t.mean()), "time_per_path_max_s": float(t.max()),
                         "max_curvature_per_m": float(max(r["max_curvature_per_m"] for r in sel)),
                         "kappa_max_per_m": float(sel[0]["kappa_max_per_m"]),
                         "min_clearance_mm": float(min(r["min_clearance_mm"] for r in sel)),
                         "min_clearance_minus_margin_mm": float(min(r["min_clearance_minus_margin_mm"] for r in sel))}
        s = summary[name]
        print(f"{name}: {s['paths']} paths ({s['reached']} reached), {s['time_per_path_mean_s']:.2f} s/path "
              f"(max {s['time_per_path_max_s']:.2f}), max curvature {s['max_curvature_per_m']:.1f} <= "
              f"{s['kappa_max_per_m']:.2f} 1/m, min clearance {s['min_clearance_mm']:.2f} mm "
              f"(min clearance - margin {s['min_clearance_minus_margin_mm']:+.3f} mm)")
    env = {"python": platform.python_version(), "machine": platform.machine(), "cpus_note": "2 shared cores"}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "trajectory.json").write_text(json.dumps({"params": params.to_dict(), "phantom_seed": 0,
                                                         "graph_step_m": 1e-3, "env": env, "summary": summary,
                                                         "paths": rows}, indent=1) + "\n")
    md = ["# Trajectory planning on the default phantom (seed 0)", "",
          f"Leaves up to generation {args.max_generation}; graph from the exact capsule tree (1 mm step); "
          "`unreachable: nearest`.  Curvature is that of the final C2 spline (checked every 0.1 mm and at "
          "every pose); clearance = -SDF at every pose.", "",
          "| SDF | paths | reached | time/path mean (s) | max (s) | max curvature (1/m) | kappa_max (1/m) | "
          "min clearance (mm) | min clearance - margin (mm) |", "|---|---|---|---|---|---|---|---|---|"]
    for name, s in summary.items():
        md.append(f"| {name} | {s['paths']} | {s['reached']} | {s['time_per_path_mean_s']:.2f} | "
                  f"{s['time_per_path_max_s']:.2f} | {s['max_curvature_per_m']:.1f} | {s['kappa_max_per_m']:.2f} | "
                  f"{s['min_clearance_mm']:.2f} | {s['min_clearance_minus_margin_mm']:+.3f} |")
    md += ["", "| SDF | branch | gen | time (s) | frames | length (mm) | max curvature (1/m) | min clearance (mm) | "
           "reached |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['sdf']} | {r['target_branch']} | {r['generation']} | {r['time_s']:.2f} | {r['frames']} | "
                  f"{r['length_mm']:.1f} | {r['max_curvature_per_m']:.1f} | {r['min_clearance_mm']:.2f} | "
                  f"{'yes' if r['reached'] else 'no: ' + r['note']} |")
    (RESULTS / "trajectory.md").write_text("\n".join(md) + "\n")


if __name__ == "__main__":
    main()
