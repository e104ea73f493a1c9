"""The whole-sequence joint plan (planning/joint_plan.py): CPU time per sequence, departure from the path, and
its approximation knobs (iterations, backbone points) against a tighter reference solve.

    .venv/bin/python benchmarks/simulation_joint_plan.py OUTPUT_DIR [OUTPUT_DIR ...] [--no-knobs]

Each OUTPUT_DIR holds patient folders written by ``room stage trajectory`` (``P/sequence_000/metadata/
trajectory.json`` with ``path_pose`` per frame, and ``P/anatomy/sdf.nii.gz``).  For each sequence the plan is
re-solved from the recorded path poses (the targets: ``trajectory.view_jitter_deg`` is 0 by default, so the
camera targets are the path poses) with the config's ``trajectory.joint_plan`` settings, timed with
``time.process_time`` (user+sys CPU of this process; wall time and the load average are recorded too: the
machine is shared), and checked against the joints the stage wrote (the same config gives the same joints).
Reported: departure of the planned camera from the path (position p50 / p95 / max mm, view p50 / p95 / max
deg), the end (last camera to the path's last point, and how far short of the path's end it stops), the
plan's camera roll change over straight stretches (|q1| < 5 % of q1_max), the largest backbone clearance
deficit, passes and function evaluations.  Knobs (skipped with ``--no-knobs``): ``max_iterations`` and
``body_points`` against a reference solve (``max_iterations`` 2000, ``body_points`` 21): joint and camera
differences, departure, CPU time.
Writes benchmarks/results/simulation_joint_plan.{json,md}.
"""
from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from room_pipeline.catalog import find_sequences  # noqa: E402
from room_pipeline.io.volume import read_nifti_sdf  # noqa: E402
from room_pipeline.paths import PatientPaths  # noqa: E402
from room_pipeline.planning.joint_plan import JointPlanParams, plan_joints  # noqa: E402
from room_pipeline.planning.trajectory import volume_sdf_fn  # noqa: E402
from room_pipeline.robot.kinematics import DEFAULT_GEOMETRY as G  # noqa: E402
from room_pipeline.robot.route import Route  # noqa: E402

REFERENCE = {"max_iterations": 2000, "body_points": 21}
KNOBS = [("max_iterations", 50), ("max_iterations", 100), ("body_points", 6)]


def config_params() -> dict:
    d = yaml.safe_load((ROOT / "conf" / "trajectory" / "default.yaml").read_text())["joint_plan"]
    d = dict(d)
    d.pop("enabled", None)
    return d


def solve(route, tr, fn, over: dict):
    p = JointPlanParams.from_dict(over)
    c0, w0 = time.process_time(), time.perf_counter()
    q, poses, rep = plan_joints(route, tr["targets"], tr["arclength"], tr["timestamps"], fn, G, p)
    return q, poses, rep, time.process_time() - c0, time.perf_counter() - w0


def summary(rep: dict, cpu: float, wall: float) -> dict:
    return {"cpu_s": cpu, "wall_s": wall, "load_average": os.getloadavg()[0],
            "departure_mm": rep["departure_from_path_mm"], "view_departure_deg": rep["view_departure_from_path_deg"],
            "end": {k: v for k, v in rep["end"].items() if k != "description"},
            "straight_roll_change_deg": rep["roll_vs_path_deg"]["straight_stretch_change_max"],
            "body_clearance_deficit_max_mm": rep["body_clearance_deficit_max_mm"],
            "passes": len(rep["passes"]), "function_evaluations": rep["function_evaluations"],
            "final_projection_max": rep["final_projection_max"]}


def main() -> None:
    dirs = [a for a in sys.argv[1:] if not a.startswith("--")]
    knobs = "--no-knobs" not in sys.argv
    base = config_params()
    rows = []
    for d in dirs:
        for sp in find_sequences(d, "trajectory"):
            patient = sp.root.parent
            if sp.root.name != "sequence_000" or patient.parent != Path(d):
                continue
            doc = json.loads(sp.trajectory.read_text())
            fr = doc["frames"]
            if "path_pose" not in fr[0] or "q" not in fr[0]:
                continue
            tr = {"targets": np.array([f["path_pose"] for f in fr]), "arclength": np.array([f["arclength"] for f in fr]),
                  "timestamps": np.array([f["timestamp"] for f in fr]), "q": np.array([f["q"] for f in fr])}
            fn = volume_sdf_fn(read_nifti_sdf(PatientPaths(patient.parent, patient.name).sdf))
            route = Route(tr["targets"][:, :3, 3], tr["arclength"], tr["targets"][:, :3, :3])
            q, poses, rep, cpu, wall = solve(route, tr, fn, base)
            row = {"sequence": f"{patient.name}/sequence_000", "frames": len(fr), "duration_s": float(tr["timestamps"][-1]),
                   "default": summary(rep, cpu, wall),
                   "same_joints_as_stage_max_diff": float(np.abs(q - tr["q"]).max())}
            print(row["sequence"], json.dumps(row["default"]), "same joints:", row["same_joints_as_stage_max_diff"],
                  flush=True)
            if knobs:
                qr, pr, repr_, cr, wr = solve(route, tr, fn, {**base, **REFERENCE})
                row["reference"] = {"params": REFERENCE, **summary(repr_, cr, wr)}
                row["knobs"] = []
                for key, val in [(None, None)] + KNOBS:
                    if key is None:
                        qk, pk, rk, ck, wk = q, poses, rep, cpu, wall
                    else:
                        qk, pk, rk, ck, wk = solve(route, tr, fn, {**base, key: val})
                    dp = np.linalg.norm(pk[:, :3, 3] - pr[:, :3, 3], axis=1) * 1e3
                    dv = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", pk[:, :3, 2], pr[:, :3, 2]), -1, 1)))
                    row["knobs"].append({"knob": "default" if key is None else f"{key}={val}",
                                         "camera_vs_reference_mm_max": float(dp.max()),
                                         "camera_vs_reference_mm_p95": float(np.percentile(dp, 95)),
                                         "view_vs_reference_deg_max": float(dv.max()), **summary(rk, ck, wk)})
                    print("  ", row["knobs"][-1]["knob"], json.dumps(row["knobs"][-1]), flush=True)
            rows.append(row)
    out = {"rows": rows, "params": base, "reference": REFERENCE,
           "command": "python benchmarks/simulation_joint_plan.py " + " ".join(sys.argv[1:])}
    res = ROOT / "benchmarks" / "results"
    res.mkdir(parents=True, exist_ok=True)
    (res / "simulation_joint_plan.json").write_text(json.dumps(out, indent=1) + "\n")
    f2 = lambda s: f"{s['median']:.2f} / {s['p95']:.2f} / {s['max']:.2f}"
    md = ["# The whole-sequence joint plan (benchmarks/simulation_joint_plan.py)", "",
          "One sparse least-squares solve over the sequence (planning/joint_plan.py; the config's "
          "`trajectory.joint_plan`), re-solved from each sequence's recorded path poses.  CPU = time.process_time "
          "(user+sys) of plan_joints; wall time is shared with other jobs (load average shown).  Departure = the "
          "planned camera against the path pose of the same frame.  End: the last camera to the path's last point, "
          "and how far short of the path's end it stops.  Straight roll: the plan's camera roll change over "
          "stretches with |q1| < 5 % of q1_max (issue #17 bound: 1 deg).  Deficit: how far the scope body's backbone "
          "comes closer to the wall than min(scope radius + body_clearance_mm, the path's own clearance).", "",
          f"Command: `{out['command']}`", "",
          "| sequence | frames | CPU s | wall s | load | position p50 / p95 / max mm | view p50 / p95 / max deg | "
          "end mm | short of end mm | straight roll deg | deficit max mm | passes | f evals | same joints as stage |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        s = r["default"]
        md.append(f"| {r['sequence']} | {r['frames']} | {s['cpu_s']:.1f} | {s['wall_s']:.1f} | {s['load_average']:.1f} | "
                  f"{f2(s['departure_mm'])} | {f2(s['view_departure_deg'])} | {s['end']['departure_mm']:.2f} | "
                  f"{s['end']['short_of_path_end_mm']:.2f} | {s['straight_roll_change_deg']:.3f} | "
                  f"{s['body_clearance_deficit_max_mm']:.2f} | {s['passes']} | {s['function_evaluations']} | "
                  f"{r['same_joints_as_stage_max_diff']:.1e} |")
    if knobs and rows:
        md += ["", f"## Knobs: speed vs difference from the reference solve ({json.dumps(REFERENCE)})", "",
               "| sequence | knob | CPU s | camera vs reference max / p95 mm | view vs reference max deg | "
               "position p95 / max mm | end mm | deficit max mm |", "|---|---|---|---|---|---|---|---|"]
        for r in rows:
            ref = r["reference"]
            md.append(f"| {r['sequence']} | reference | {ref['cpu_s']:.1f} | 0 / 0 | 0 | "
                      f"{ref['departure_mm']['p95']:.2f} / {ref['departure_mm']['max']:.2f} | "
                      f"{ref['end']['departure_mm']:.2f} | {ref['body_clearance_deficit_max_mm']:.2f} |")
            for k in r["knobs"]:
                md.append(f"| {r['sequence']} | {k['knob']} | {k['cpu_s']:.1f} | {k['camera_vs_reference_mm_max']:.3f} / "
                          f"{k['camera_vs_reference_mm_p95']:.3f} | {k['view_vs_reference_deg_max']:.2f} | "
                          f"{k['departure_mm']['p95']:.2f} / {k['departure_mm']['max']:.2f} | "
                          f"{k['end']['departure_mm']:.2f} | {k['body_clearance_deficit_max_mm']:.2f} |")
    (res / "simulation_joint_plan.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
