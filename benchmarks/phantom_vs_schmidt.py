"""Phantom tree vs a measured human bronchial tree (Schmidt et al. 2004), per generation.

Compares the default :func:`room_pipeline.anatomy.phantom.grow_tree` (several
seeds pooled) with the reference tree of Schmidt A, Zidowitz S, Kriete A,
et al., "A digital reference model of the human bronchial tree", Comput Med
Imaging Graph 28:203-211 (2004), read from ``../shared/data`` (never copied
into the repository): branch count, radius, length, length/diameter and
branching angle (parent-child axis angle) per generation (trachea = 0).
Also times one default ``make_phantom`` (wall time, peak RSS).

Writes ``benchmarks/results/phantom_vs_schmidt.{json,md}``.

    .venv/bin/python benchmarks/phantom_vs_schmidt.py [--seeds 10] [--no-volume]
"""
from __future__ import annotations

import argparse
import csv
import json
import resource
import sys
import time
from pathlib import Path

import numpy as np

from room_pipeline.anatomy.phantom import PhantomParams, grow_tree, make_phantom

REPO = Path(__file__).resolve().parents[1]
SCHMIDT_CSV = Path(__file__).resolve().parents[2] / "shared" / "data" / "airway_trees" / "schmidt2004" / "TreeData.csv"
OUT = REPO / "benchmarks" / "results"
MAX_GEN = 12


def _branch_table_phantom(seeds: int) -> dict[str, np.ndarray]:
    """Pooled per-branch arrays (mm, deg) over ``seeds`` default trees."""
    g, r, L, ang, tree_id = [], [], [], [], []
    for seed in range(seeds):
        tree = grow_tree(PhantomParams(), np.random.default_rng(seed))
        for b in tree.branches:
            g.append(b.generation)
            r.append(b.radius * 1e3)
            L.append(b.length * 1e3)
            if b.parent >= 0:
                c = float(np.clip(tree.branch(b.parent).direction @ b.direction, -1, 1))
                ang.append(np.degrees(np.arccos(c)))
            else:
                ang.append(np.nan)
            tree_id.append(seed)
    return {"generation": np.array(g), "radius": np.array(r), "length": np.array(L),
            "angle": np.array(ang), "tree": np.array(tree_id)}


def _branch_table_schmidt(path: Path) -> dict[str, np.ndarray]:
    """Per-branch arrays (mm, deg) of the Schmidt tree; parents found by shared end points."""
    with path.open() as fh:
        rows = list(csv.DictReader(fh))
    g = np.array([int(r["generation"]) for r in rows])
    rad = np.array([float(r["radius"]) for r in rows])
    p1 = np.array([[float(r[k]) for k in ("x1", "y1", "z1")] for r in rows])
    p2 = np.array([[float(r[k]) for k in ("x2", "y2", "z2")] for r in rows])
    d = p2 - p1
    L = np.linalg.norm(d, axis=1)
    u = d / np.maximum(L, 1e-12)[:, None]
    ends = {}
    for i in range(len(rows)):
        ends.setdefault((g[i], tuple(np.round(p2[i], 3))), i)
    ang = np.full(len(rows), np.nan)
    for i in range(len(rows)):
        j = ends.get((g[i] - 1, tuple(np.round(p1[i], 3))))
        if j is not None:
            ang[i] = np.degrees(np.arccos(np.clip(u[i] @ u[j], -1, 1)))
    return {"generation": g, "radius": rad, "length": L, "angle": ang, "tree": np.zeros(len(rows), int)}


def _per_generation(t: dict[str, np.ndarray], n_trees: int) -> list[dict]:
    out = []
    for gen in range(MAX_GEN + 1):
        m = t["generation"] == gen
        if not m.any():
            out.append({"generation": gen, "n_per_tree": 0.0})
            continue
        ld = t["length"][m] / (2 * t["radius"][m])
        a = t["angle"][m][np.isfinite(t["angle"][m])]
        out.append({"generation": gen, "n_per_tree": float(m.sum() / n_trees),
                    "radius_mm_mean": float(t["radius"][m].mean()), "radius_mm_sd": float(t["radius"][m].std()),
                    "length_mm_mean": float(t["length"][m].mean()), "length_mm_sd": float(t["length"][m].std()),
                    "l_over_d_mean": float(ld.mean()),
                    "angle_deg_mean": float(a.mean()) if len(a) else None})
    return out


def _fmt(v, f="{:.2f}"):
    return "-" if v is None else f.format(v)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10, help="phantom trees pooled (seeds 0..N-1)")
    ap.add_argument("--no-volume", action="store_true", help="skip timing the default make_phantom")
    args = ap.parse_args(argv)
    if not SCHMIDT_CSV.is_file():
        print(f"SKIP: Schmidt 2004 reference tree not found at {SCHMIDT_CSV} (../shared/data is not available)")
        return 0

    ph_rows = _per_generation(_branch_table_phantom(args.seeds), args.seeds)
    sc_rows = _per_generation(_branch_table_schmidt(SCHMIDT_CSV), 1)
    result = {"reference": "Schmidt et al. 2004, Comput Med Imaging Graph 28:203-211 (TreeData.csv, ../shared)",
              "phantom": f"grow_tree(PhantomParams() defaults), seeds 0..{args.seeds - 1} pooled",
              "units": {"radius": "mm", "length": "mm", "angle": "deg (parent-child axis angle)"},
              "per_generation": [{"generation": p["generation"], "phantom": p, "schmidt": s}
                                 for p, s in zip(ph_rows, sc_rows)]}

    if not args.no_volume:
        t0 = time.perf_counter()
        ph = make_phantom(PhantomParams(), seed=0)
        wall = time.perf_counter() - t0
        peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB
        result["default_make_phantom"] = {
            "shape": list(ph.ct.shape), "voxels": int(np.prod(ph.ct.shape)), "branches": len(ph.tree),
            "max_generation": ph.tree.max_generation, "wall_time_s": round(wall, 2),
            "peak_rss_mb_process": round(peak_mb, 1), "lumen_voxels": int(ph.mask.data.sum())}

    head = ("| gen | n phantom/tree | n Schmidt | r phantom mm | r Schmidt mm | r ratio | L phantom mm | L Schmidt mm "
            "| L/D phantom | L/D Schmidt | angle phantom deg | angle Schmidt deg |")
    lines = [head, "|" + "---|" * 12]
    for p, s in zip(ph_rows, sc_rows):
        ratio = (p["radius_mm_mean"] / s["radius_mm_mean"]) if p.get("radius_mm_mean") and s.get("radius_mm_mean") else None
        lines.append(
            f"| {p['generation']} | {p['n_per_tree']:.1f} | {s['n_per_tree']:.0f} "
            f"| {_fmt(p.get('radius_mm_mean'))} ± {_fmt(p.get('radius_mm_sd'))} "
            f"| {_fmt(s.get('radius_mm_mean'))} ± {_fmt(s.get('radius_mm_sd'))} | {_fmt(ratio)} "
            f"| {_fmt(p.get('length_mm_mean'), '{:.1f}')} ± {_fmt(p.get('length_mm_sd'), '{:.1f}')} "
            f"| {_fmt(s.get('length_mm_mean'), '{:.1f}')} ± {_fmt(s.get('length_mm_sd'), '{:.1f}')} "
            f"| {_fmt(p.get('l_over_d_mean'))} | {_fmt(s.get('l_over_d_mean'))} "
            f"| {_fmt(p.get('angle_deg_mean'), '{:.1f}')} | {_fmt(s.get('angle_deg_mean'), '{:.1f}')} |")
    table = "\n".join(lines)
    md = ["# Phantom tree vs Schmidt et al. 2004 (per generation, trachea = 0)", "",
          f"Phantom: {result['phantom']}. Reference: {result['reference']}.",
          "Radius and length mean ± SD in mm; angle = angle between parent and child axes.", "", table, ""]
    if "default_make_phantom" in result:
        d = result["default_make_phantom"]
        md += [f"Default `make_phantom` (seed 0): shape {tuple(d['shape'])} = {d['voxels'] / 1e6:.1f} M voxels, "
               f"{d['branches']} branches, max generation {d['max_generation']}, {d['wall_time_s']} s, "
               f"peak RSS {d['peak_rss_mb_process']:.0f} MB (whole process).", ""]
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "phantom_vs_schmidt.json").write_text(json.dumps(result, indent=2) + "\n")
    (OUT / "phantom_vs_schmidt.md").write_text("\n".join(md))
    print("\n".join(md))
    print(f"wrote {OUT / 'phantom_vs_schmidt.json'} and .md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
