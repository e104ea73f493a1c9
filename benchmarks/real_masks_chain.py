#!/usr/bin/env python3
"""Every shared real airway mask through segment -> sdf -> mesh -> medial_axis -> trajectory.

Runs ``room run --until trajectory`` (each stage in its own process) per mask from ``../shared/data`` with the
default config (Med-MPD patients also once with their ``start1.txt`` as the user start pose), and records per
mask: ok / the one-line error, branches, the trajectory's frames, start and stop, each stage's peak RSS and
wall time.  Saves benchmarks/results/real_masks_chain.{json,md}.  Skips masks that are absent.

    python benchmarks/real_masks_chain.py [--only NAME ...]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from room_pipeline.catalog import find_sequences
from room_pipeline.io.metrics import read_metrics_file
from room_pipeline.paths import PatientPaths

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "airway_masks"
RESULTS = ROOT / "benchmarks" / "results"
STAGES = ("segment", "sdf", "mesh", "medial_axis")
MASKS = {
    "medmpd_1": ("medmpd/patient1/bronchialTree.nii.gz", None),
    "medmpd_1_start1": ("medmpd/patient1/bronchialTree.nii.gz", "medmpd/patient1/start1.txt"),
    "medmpd_2": ("medmpd/patient2/bronchialTree.nii.gz", None),
    "medmpd_3": ("medmpd/patient3/bronchialTree.nii.gz", None),
    "airquant_demo": ("airquant_demo/github_demo_seg.nii.gz", None),
    "ATM_001": ("public_trees/axes_fixed/ATM_001_0000_fixed.nii.gz", None),
    "CASE073": ("public_trees/axes_fixed/CASE073_fixed.nii.gz", None),
    "CASE091": ("public_trees/axes_fixed/CASE091_fixed.nii.gz", None),
}


def run_one(name: str, mask: Path, start: Path | None) -> dict:
    row: dict = {"mask": name}
    with tempfile.TemporaryDirectory() as tmp:
        entry = f"{{kind: mask, input: '{mask}'" + (f", start_pose: '{start}'" if start else "") + "}"
        cmd = [sys.executable, "-m", "room_pipeline.cli", "run", "--patient", "real", "--until", "trajectory",
               f"output_dir={tmp}", "patients=phantom_single", f"+patients.real={entry}"]
        p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
        row["exit"] = p.returncode
        errs = [ln for ln in p.stderr.splitlines() if ln.startswith("room: error")]
        row["error"] = " | ".join(errs) if errs else ("" if p.returncode == 0 else p.stderr.strip().splitlines()[-1:])
        pp = PatientPaths(Path(tmp), "real")
        for st in STAGES:
            f = pp.stage_metrics(st)
            if f.exists():
                m = read_metrics_file(f)   # + its timing file
                row[f"{st}_peak_mb"], row[f"{st}_s"] = m.get("peak_rss_mb"), m.get("wall_time_s")
                if st == "medial_axis":
                    row["branches"] = m.get("n_branches")
        trajs = [s.trajectory for s in find_sequences(pp.root, "trajectory")]
        row["sequences"] = []
        for t in trajs:
            d = json.loads(t.read_text())
            row["sequences"].append({"frames": len(d["frames"]), "start": d.get("start", {}).get("kind"),
                                     "start_offset_mm": d.get("start", {}).get("offset_mm"),
                                     "reached": d["target"]["reached"], "stop_reason": d["target"].get("stop_reason"),
                                     "stop_distance_mm": round(1e3 * d["target"].get("stop_distance", 0.0), 2)})
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*")
    args = ap.parse_args()
    rows = []
    for name, (rel, start) in MASKS.items():
        if args.only and name not in args.only:
            continue
        mask = DATA / rel
        if not mask.exists():
            print(f"{name}: skipped ({mask} absent)")
            continue
        row = run_one(name, mask, DATA / start if start else None)
        print(json.dumps(row), flush=True)
        rows.append(row)
    md = ["| mask | exit | branches | sequences (frames, start, reached / stop reason) | peak RSS MB sdf / mesh | error |",
          "|---|---|---|---|---|---|"]
    for r in rows:
        seqs = "; ".join(f"{s['frames']} fr, {s['start']} {s['start_offset_mm']} mm, "
                         f"{'reached' if s['reached'] else s['stop_reason'] + ' ' + str(s['stop_distance_mm']) + ' mm'}"
                         for s in r["sequences"])
        md.append(f"| {r['mask']} | {r['exit']} | {r.get('branches')} | {seqs} | {r.get('sdf_peak_mb')} / "
                  f"{r.get('mesh_peak_mb')} | {r['error']} |")
    text = "\n".join(md) + f"\n\nload average at the end: {os.getloadavg()[0]:.1f}\n"
    print(text)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "real_masks_chain.json").write_text(json.dumps({"rows": rows, "command":
                                                               "python benchmarks/real_masks_chain.py"}, indent=2) + "\n")
    (RESULTS / "real_masks_chain.md").write_text("# Shared real masks, segment -> trajectory (default config)\n\n"
                                                 "`python benchmarks/real_masks_chain.py`\n\n" + text)


if __name__ == "__main__":
    main()
