"""The anatomy stages on a measured human tree, per generation, against the grown phantom.

A reference-tree patient (``conf/patients/reference_tree.yaml``: the Schmidt et al. 2004 digital reference
tree, 3597 branches, generations 0-17, read by :mod:`room_pipeline.anatomy.reference_tree` and rasterised
by the phantom's CT model with exact ground truth) goes through ``room run ... --until validate_centreline``;
the validation stages' metrics are tabulated per generation: the tree's median lumen radius, how many of
its branches the segmentation reaches (ATM'22 BD / TD, ``anatomy_validation.json``; also by lumen radius), and
how many the medial axis finds, fed the segmentation (end to end) and fed the true mask (isolation,
``centreline_validation.json``).  A grown phantom (``--phantom``, default ``patient_001`` of the default
config) runs the same way beside it; other finished runs are tabulated with ``--runs LABEL=PATIENT_DIR``.

    python benchmarks/reference_tree.py [--work /tmp/reftree] [--phantom patient_001] [--runs LABEL=PATIENT_DIR ...]
    python benchmarks/reference_tree.py --cached-only --work /tmp/reftree ...   # tabulate a finished run

Writes ``benchmarks/results/reference_tree.{md,json}`` (``--name`` to change).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from room_pipeline.paths import PatientPaths

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "results"


def _run(patient: str, patients: str, work: Path, overrides: list[str]) -> float:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "room_pipeline.cli", "run", "--patient", patient, "--until",
                    "validate_centreline", f"patients={patients}", f"output_dir={work}", *overrides],
                   cwd=REPO, check=True, env=env)
    return time.perf_counter() - t0


def _table(output_dir: Path, patient: str) -> dict:
    paths = PatientPaths(output_dir, patient)
    a = json.loads(paths.stage_metrics("validate_anatomy").read_text())
    c = json.loads(paths.stage_metrics("validate_centreline").read_text())
    tree = json.loads(paths.gt_tree.read_text())["branches"]
    seg = a["segment"]
    rows = []
    for g in sorted({b["generation"] for b in tree}):
        r = [b["radius"] * 1e3 for b in tree if b["generation"] == g]
        pg = seg["per_generation"].get(str(g), {})
        e = c["end_to_end"]["detection_by_generation"].get(str(g), {})
        i = c["isolation"]["detection_by_generation"].get(str(g), {})
        rows.append({"generation": g, "n": len(r), "radius_median_mm": round(float(np.median(r)), 2),
                     "segment_bd": pg.get("branches_detected"), "segment_td": pg.get("tree_length_detected"),
                     "centreline_e2e": e.get("rate"), "centreline_isolation": i.get("rate")})
    by_radius = [{"radius_mm": k, "n": v["n_branches"], "segment_bd": v["branches_detected"],
                  "segment_td": v["tree_length_detected"]}
                 for k, v in seg.get("per_radius_mm", {}).items()]
    timing = {}
    for stage in ("phantom", "segment", "sdf", "mesh", "medial_axis", "validate_anatomy", "validate_centreline"):
        f = paths.stage_timings(stage)
        if f.is_file():
            t = json.loads(f.read_text())
            timing[stage] = {k: t.get(k) for k in ("wall_time_s", "peak_rss_mb")}
    head = {k: seg[k] for k in ("dice", "precision", "recall", "tree_length_detected", "branches_detected",
                                "n_branches", "n_branches_detected")}
    head.update({"centreline_" + k: c["end_to_end"][k] for k in ("detection_rate_large", "dist_ext_to_true_mean_vox",
                                                                 "spurious_fraction", "bifurcation_error_median_m",
                                                                 "bifurcation_error_detected_median_m")})
    head.update({"centreline_isolation_detection_rate_large": c["isolation"]["detection_rate_large"],
                 "checks_failed": sorted(k for k, v in {**a["checks"], **c["checks"]}.items() if not v)})
    return {"headline": head, "generations": rows, "radii": by_radius, "timing": timing}


def _fmt(v) -> str:
    return "-" if v is None else (f"{v:.3f}" if isinstance(v, float) else str(v))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--patient", default="schmidt2004")
    ap.add_argument("--work", type=Path, default=Path("/tmp/reftree"))
    ap.add_argument("--cached-only", action="store_true", help="tabulate a finished run in --work")
    ap.add_argument("--phantom", default="patient_001",
                    help="a grown phantom of conf/patients/phantom.yaml run the same way beside it ('' = none)")
    ap.add_argument("--runs", nargs="*", default=[], help="LABEL=PATIENT_DIR of other finished runs to tabulate")
    ap.add_argument("--name", default="reference_tree")
    ap.add_argument("overrides", nargs="*", help="Hydra overrides for the run")
    args = ap.parse_args()

    wall = None if args.cached_only else _run(args.patient, "reference_tree", args.work, args.overrides)
    tables = {args.patient: _table(args.work, args.patient)}
    if args.phantom:
        if not args.cached_only:
            _run(args.phantom, "phantom", args.work, args.overrides)
        tables[f"grown phantom {args.phantom}"] = _table(args.work, args.phantom)
    for spec in args.runs:
        label, _, d = spec.partition("=")
        tables[label] = _table(Path(d).parent, Path(d).name)

    lines = [f"# Anatomy stages on a measured human tree (`{args.patient}`) per generation", "",
             f"`python benchmarks/reference_tree.py {' '.join(sys.argv[1:])}`" + (f"; room run wall {wall:.0f} s" if wall else ""),
             f"load average at the end: {os.getloadavg()[0]:.1f}", ""]
    lines += ["| run | Dice | precision | recall | TD | BD | branches detected | centreline detection r >= 2 vox (e2e / isolation) | "
              "centreline mean dist (vox) | spurious | median bifurcation error (mm): every true one / the found ones | "
              "failed checks |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for label, t in tables.items():
        h = t["headline"]
        lines.append(f"| {label} | {h['dice']:.3f} | {h['precision']:.3f} | {h['recall']:.3f} | "
                     f"{h['tree_length_detected']:.3f} | {h['branches_detected']:.3f} | "
                     f"{h['n_branches_detected']}/{h['n_branches']} | {h['centreline_detection_rate_large']:.3f} / "
                     f"{h['centreline_isolation_detection_rate_large']:.3f} | {h['centreline_dist_ext_to_true_mean_vox']:.3f} | "
                     f"{h['centreline_spurious_fraction']:.3f} | {h['centreline_bifurcation_error_median_m'] * 1e3:.2f} / "
                     f"{h['centreline_bifurcation_error_detected_median_m'] * 1e3:.2f} | "
                     f"{', '.join(h['checks_failed']) or 'none'} |")
    for label, t in tables.items():
        lines += ["", f"## {label}: per generation", "",
                  "| generation | branches | median radius (mm) | segment BD | segment TD | centreline e2e | centreline isolation |",
                  "|---|---|---|---|---|---|---|"]
        for r in t["generations"]:
            lines.append(f"| {r['generation']} | {r['n']} | {r['radius_median_mm']:.2f} | {_fmt(r['segment_bd'])} | "
                         f"{_fmt(r['segment_td'])} | {_fmt(r['centreline_e2e'])} | {_fmt(r['centreline_isolation'])} |")
        if t["radii"]:
            lines += ["", f"## {label}: by lumen radius (a branch's median)", "",
                      "| radius (mm) | branches | segment BD | segment TD |", "|---|---|---|---|"]
            lines += [f"| {r['radius_mm']} | {r['n']} | {r['segment_bd']:.3f} | {r['segment_td']:.3f} |"
                      for r in t["radii"]]
        lines += ["", "Stage wall time / peak RSS: " + ", ".join(
            f"{k} {v['wall_time_s']:.0f} s / {v['peak_rss_mb']:.0f} MB" for k, v in t["timing"].items()
            if v.get("wall_time_s") is not None and v.get("peak_rss_mb") is not None)]
    text = "\n".join(lines) + "\n"
    print(text)
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / f"{args.name}.md").write_text(text)
    (OUT / f"{args.name}.json").write_text(json.dumps(tables, indent=1) + "\n")


if __name__ == "__main__":
    main()
