#!/usr/bin/env python3
"""Every shared real airway mask through segment -> sdf -> mesh -> medial_axis -> trajectory.

Runs ``room run --until trajectory`` (each stage in its own process) per mask from ``../shared/data`` with the
default config (Med-MPD patient 1 also with its ``start1.txt`` as the user start pose, and every Med-MPD patient
with its ``target.txt``, a nodule in the parenchyma, as the route's target, from the trachea and from its
``start1.txt``), and records per
mask: ok / the one-line error, branches, the trajectory's frames, start, target and stop (reason, distance from
the target), each stage's peak RSS and wall time.  Saves benchmarks/results/real_masks_chain.{json,md}.  Skips masks that are absent.

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
#: overrides of an ultrathin scope: 3.0 mm outer diameter, the path's lumen test at its radius (1.5 mm)
THIN_SCOPE = ("trajectory.min_lumen_radius_mm=1.5", "trajectory.joint_plan.scope_diameter_mm=3.0",
              "simulate.scope_diameter_mm=3.0")
#: name -> (mask, start pose file or None, target file or None[, overrides]), under ../shared/data/airway_masks
MASKS = {
    "medmpd_1": ("medmpd/patient1/bronchialTree.nii.gz", None, None),
    "medmpd_1_target": ("medmpd/patient1/bronchialTree.nii.gz", None, "medmpd/patient1/target.txt"),
    "medmpd_1_start1": ("medmpd/patient1/bronchialTree.nii.gz", "medmpd/patient1/start1.txt", None),
    "medmpd_1_start1_target": ("medmpd/patient1/bronchialTree.nii.gz", "medmpd/patient1/start1.txt",
                               "medmpd/patient1/target.txt"),
    "medmpd_2": ("medmpd/patient2/bronchialTree.nii.gz", None, None),
    "medmpd_2_target": ("medmpd/patient2/bronchialTree.nii.gz", None, "medmpd/patient2/target.txt"),
    "medmpd_2_start1_target": ("medmpd/patient2/bronchialTree.nii.gz", "medmpd/patient2/start1.txt",
                               "medmpd/patient2/target.txt"),
    "medmpd_3": ("medmpd/patient3/bronchialTree.nii.gz", None, None),
    "medmpd_3_target": ("medmpd/patient3/bronchialTree.nii.gz", None, "medmpd/patient3/target.txt"),
    "medmpd_3_start1_target": ("medmpd/patient3/bronchialTree.nii.gz", "medmpd/patient3/start1.txt",
                               "medmpd/patient3/target.txt"),
    # an ultrathin scope (3.0 mm, as Olympus BF-MP190F), the lumen test at its radius
    "medmpd_2_start1_target_3mm": ("medmpd/patient2/bronchialTree.nii.gz", "medmpd/patient2/start1.txt",
                                   "medmpd/patient2/target.txt", THIN_SCOPE),
    "airquant_demo": ("airquant_demo/github_demo_seg.nii.gz", None, None),
    "ATM_001": ("public_trees/axes_fixed/ATM_001_0000_fixed.nii.gz", None, None),
    "CASE073": ("public_trees/axes_fixed/CASE073_fixed.nii.gz", None, None),
    "CASE091": ("public_trees/axes_fixed/CASE091_fixed.nii.gz", None, None),
}


def run_one(name: str, mask: Path, start: Path | None, target: Path | None = None, overrides=()) -> dict:
    """One ``room run --until trajectory``; ``target``: the route goes to that point (``trajectory.targets=points``,
    the default ``unreachable: nearest``) instead of the default random leaf."""
    row: dict = {"mask": name}
    with tempfile.TemporaryDirectory() as tmp:
        entry = f"{{kind: mask, input: '{mask}'" + (f", start_pose: '{start}'" if start else "") + "}"
        cmd = [sys.executable, "-m", "room_pipeline.cli", "run", "--patient", "real", "--until", "trajectory",
               f"output_dir={tmp}", "patients=phantom_single", f"+patients.real={entry}"]
        if target is not None:
            cmd += ["trajectory.targets=points", f"trajectory.points='{target}'"]
        cmd += list(overrides)
        row["overrides"] = list(overrides)
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
            tgt, st = d["target"], d.get("start", {})
            row["sequences"].append({"frames": len(d["frames"]), "start": st.get("kind"),
                                     "start_offset_mm": st.get("offset_mm"),
                                     "start_distance_mm": st.get("distance_to_centreline_mm"),
                                     "reached": tgt["reached"], "stop_reason": tgt.get("stop_reason"),
                                     "stop_distance_mm": round(1e3 * tgt.get("stop_distance", 0.0), 2),
                                     "target_kind": tgt.get("kind"),
                                     "target_to_centreline_mm": round(1e3 * tgt.get("distance", 0.0), 2),
                                     "note": tgt.get("note", "")})
    return row


def start_pose_sites() -> list[dict]:
    """Where Med-MPD's start poses lie in their masks: distance from the wall (the mask's Euclidean distance
    transform, mm: inside > 0, outside < 0, at the voxel nearest the pose) and the widest inscribed radius
    within 3 mm of the pose (mm), the lumen a scope would have to fit."""
    import numpy as np
    from scipy import ndimage

    from room_pipeline.io.volume import read_volume

    rows = []
    for patient in sorted((DATA / "medmpd").glob("patient*")):
        vol = read_volume(patient / "bronchialTree.nii.gz")
        m = np.asarray(vol.data) > 0
        sp = vol.spacing / 1e-3
        inside = ndimage.distance_transform_edt(m, sampling=sp)
        outside = ndimage.distance_transform_edt(~m, sampling=sp)
        for f in sorted(patient.glob("start*.txt")):
            p = np.loadtxt(f).reshape(4, 4)[:3, 3]
            ijk = np.rint(vol.world_to_index(p[None] * 1e-3)[0]).astype(int)
            r = np.ceil(3.0 / sp).astype(int)
            box = tuple(slice(max(0, ijk[a] - r[a]), ijk[a] + r[a] + 1) for a in range(3))
            rows.append({"pose": f"{patient.name}/{f.name}",
                         "wall_distance_mm": round(float(inside[tuple(ijk)] - outside[tuple(ijk)]), 2),
                         "widest_radius_within_3mm": round(float(inside[box].max()), 2)})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="*")
    ap.add_argument("--merge", action="store_true",
                    help="with --only: replace those rows in the saved results and keep the others (marked with the "
                         "command that made them in the json)")
    args = ap.parse_args()
    rows = []
    for name, (rel, start, target, *extra) in MASKS.items():
        if args.only and name not in args.only:
            continue
        mask = DATA / rel
        if not mask.exists():
            print(f"{name}: skipped ({mask} absent)")
            continue
        row = run_one(name, mask, DATA / start if start else None, DATA / target if target else None,
                      extra[0] if extra else ())
        row["run_by"] = " ".join(["python benchmarks/real_masks_chain.py", *sys.argv[1:]])
        print(json.dumps(row), flush=True)
        rows.append(row)
    if args.merge and (RESULTS / "real_masks_chain.json").is_file():
        new = {r["mask"]: r for r in rows}
        old = {r["mask"]: r for r in json.loads((RESULTS / "real_masks_chain.json").read_text())["rows"]}
        rows = [new.get(name) or old[name] for name in MASKS if name in new or name in old]
    md = ["| mask | exit | branches | sequences (frames, start, target, reached / stop reason and distance from the "
          "target) | peak RSS MB sdf / mesh | error |",
          "|---|---|---|---|---|---|"]
    for r in rows:
        def _seq(s: dict) -> str:
            start = f"{s['start']} {s['start_offset_mm']} mm" + (
                f" (pose {s['start_distance_mm']} mm off the centreline)" if s.get("start_distance_mm") is not None
                else "")
            target = s["target_kind"] + (f" {s['target_to_centreline_mm']} mm from the centreline"
                                         if s["target_kind"] == "point" else "")
            stop = "reached" if s["reached"] else f"{s['stop_reason']} {s['stop_distance_mm']} mm"
            return f"{s['frames']} fr, {start}, {target}, {stop}"
        seqs = "; ".join(_seq(s) for s in r["sequences"])
        name = r["mask"] + (f" ({' '.join(r['overrides'])})" if r.get("overrides") else "") + (
            " (re-run: `--only ... --merge`)" if "--merge" in r.get("run_by", "") else "")
        md.append(f"| {name} | {r['exit']} | {r.get('branches')} | {seqs} | {r.get('sdf_peak_mb')} / "
                  f"{r.get('mesh_peak_mb')} | {r['error']} |")
    sites = start_pose_sites()
    if sites:
        md += ["", "Med-MPD's start poses in their masks (distance from the wall: > 0 inside, < 0 outside; the widest "
               "inscribed radius within 3 mm of the pose):", "",
               "| start pose | from the wall (mm) | widest radius within 3 mm (mm) |", "|---|---|---|"]
        md += [f"| {r['pose']} | {r['wall_distance_mm']} | {r['widest_radius_within_3mm']} |" for r in sites]
    text = "\n".join(md) + f"\n\nload average at the end: {os.getloadavg()[0]:.1f}\n"
    print(text)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "real_masks_chain.json").write_text(json.dumps({"rows": rows, "start_pose_sites": sites, "command":
                                                               "python benchmarks/real_masks_chain.py"}, indent=2) + "\n")
    (RESULTS / "real_masks_chain.md").write_text("# Shared real masks, segment -> trajectory (default config)\n\n"
                                                 "`python benchmarks/real_masks_chain.py`\n\n" + text)


if __name__ == "__main__":
    main()
