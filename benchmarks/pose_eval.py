#!/usr/bin/env python3
"""Pose evaluation (stage `evaluate_pose`, Table I) on a rendered default run: accuracy and CPU time of every
method against the trivial baselines, at several frame strides, COLMAP included.

    PYTHONPATH=src python benchmarks/pose_eval.py --data DIR [--quick]

DIR is a rendered run (``data/output`` after ``dvc repro``, or a copy of it; only read here).  Every
``DIR/<patient>/<sequence>`` with ``metadata/render.json`` is evaluated over its whole route exactly as the
stage does (``room_pipeline.evaluate.pose_eval``: same frame loading, downscale, methods, metrics and route
segments; the noisy frames by default), with the knobs of ``conf/evaluate/default.yaml`` except:

* ``frame_stride``: the approximation knob of the stage's time budget.  Every stride tiles the whole
  route (all frames k * stride); the reference is stride 1 (every rendered frame).  ``--quick``: only the
  default stride.
* methods: ``colmap``, ``sift_vo`` and ``orb_vo`` whatever ``evaluate.pose.methods`` says (COLMAP is off by
  default in the stage; this is where its score and cost on the default run are measured); COLMAP only at
  the default stride (``--colmap-strides`` adds others; it costs the most).

Nothing is written into DIR.  Writes benchmarks/results/pose_eval.{json,md} (``--quick``: pose_eval_quick.*):
per sequence, stride and method RRA@5, RTA@5, AUC@30 (% of frame pairs), AUC@30 per route segment,
registration, ATE, CPU seconds (process time: the fair figure on a shared machine) and wall seconds, and
whether the method beats both trivial baselines (as Table I's flag).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from room_pipeline.anatomy.centreline import CentrelineGraph  # noqa: E402
from room_pipeline.catalog import find_sequences  # noqa: E402
from room_pipeline.paths import PatientPaths  # noqa: E402
from room_pipeline.evaluate.allocator import keep_freed_memory  # noqa: E402
from room_pipeline.evaluate.pose_eval import PoseEvalParams, evaluate_methods, load_sequence  # noqa: E402
from room_pipeline.evaluate.route_segments import label_frames  # noqa: E402
from room_pipeline.evaluate.tables import POSE_BETTER, beats  # noqa: E402
from room_pipeline.io.jsondoc import finite as _finite, read_json  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
METHODS = ("colmap", "sift_vo", "orb_vo")
BASELINES = ("identity", "constant_forward")
KEYS = ("RRA@5", "RTA@5", "AUC@30", "registration_rate", "ate_rmse_mm")


def sequences(data: Path) -> list[tuple[str, str]]:
    return [(s.root.parent.name, s.root.name) for s in find_sequences(data) if s.root.parent.parent == data]


def evaluate(data: Path, patient: str, sequence: str, stride: int, methods: tuple, conf: dict) -> dict:
    """One sequence at one stride: {method: record} (+ "_frames", "_load_cpu_s")."""
    p = PoseEvalParams.from_dict({**conf, "frame_stride": stride, "methods": list(methods)})
    seq = data / patient / sequence
    c0 = time.process_time()
    images, K, gt, info = load_sequence(seq, p)
    load_cpu = time.process_time() - c0
    graph = CentrelineGraph.from_dict(read_json(PatientPaths(data, patient).centreline_graph))
    labels, _ = label_frames(gt[:, :3, 3], graph, p.bifurcation_radius_factor)
    out = {}
    for name in p.run_names():
        one = PoseEvalParams.from_dict({**conf, "frame_stride": stride, "methods": [name]})
        c0 = time.process_time()
        res, _ = evaluate_methods(images, K, gt, dataclass_replace_methods(one, name), labels)
        cpu = time.process_time() - c0
        r = res[name]
        r["cpu_s"] = cpu
        out[name] = r
        print(f"{patient}/{sequence} stride {stride} {name}: AUC@30 {r.get('AUC@30', float('nan')):.4f} "
              f"RRA@5 {r.get('RRA@5', float('nan')):.4f} RTA@5 {r.get('RTA@5', float('nan')):.4f} "
              f"CPU {cpu:.1f} s", flush=True)
    return {"frames": info["n_frames"], "load_cpu_s": load_cpu, "methods": out}


def dataclass_replace_methods(p: PoseEvalParams, name: str) -> PoseEvalParams:
    """``p`` running only ``name`` (no baselines when ``name`` is a method, so each is timed alone)."""
    import dataclasses

    class Only(PoseEvalParams):
        def run_names(self) -> list[str]:
            return [name]

    return Only(**{f.name: getattr(p, f.name) for f in dataclasses.fields(p)})


def verdict(rec: dict, base: dict) -> str:
    if not rec.get("available"):
        return "-"
    fails = beats(rec, base, POSE_BETTER)
    return "yes" if not fails else "NO: " + ", ".join(fails)


def pct(v) -> str:
    return "-" if not isinstance(v, (int, float)) or v != v or abs(v) == float("inf") else f"{100 * v:.2f}"


def markdown(res: dict) -> str:
    L = ["# Pose evaluation on the default run: methods against the trivial baselines, by frame stride",
         "", f"`{res['command']}` on {res['machine']}; load average {res['load_start']:.1f} at start, "
         f"{res['load_end']:.1f} at end (CPU time is the fair figure on this shared machine).", "",
         f"Data: `{res['data']}` (renders of commit {res['render_commit']}); frames: {res['images']}; "
         f"downscale {res['downscale']}; default stride {res['default_stride']}.", "",
         "Scores in % of frame pairs over the whole route (all pairs i<j of the evaluated frames); "
         "'beats baselines' as Table I: RRA@5, RTA@5 and AUC@30 all strictly above both identity and "
         "constant_forward on the same frames.", "",
         "| sequence | stride | frames | method | RRA@5 | RTA@5 | AUC@30 | AUC@30 trachea / bifurcations / distal | "
         "registered | ATE (mm) | CPU s | CPU s/frame | beats baselines |",
         "|---|---:|---:|---|---:|---:|---:|---|---:|---:|---:|---:|---|"]
    for run in res["runs"]:
        base = {b: run["methods"][b] for b in BASELINES if b in run["methods"]}
        for name, r in run["methods"].items():
            seg = r.get("segments") or {}
            segs = " / ".join(pct((seg.get(s) or {}).get("AUC@30")) for s in ("trachea", "bifurcations", "distal"))
            ate = r.get("ate_rmse_mm")
            L.append(f"| {run['sequence']} | {run['stride']} | {run['frames']} | {name} | {pct(r.get('RRA@5'))} | "
                     f"{pct(r.get('RTA@5'))} | {pct(r.get('AUC@30'))} | {segs} | {pct(r.get('registration_rate'))} | "
                     f"{'-' if ate is None else f'{ate:.2f}'} | {r['cpu_s']:.1f} | {r['cpu_s'] / run['frames']:.3f} | "
                     f"{'(trivial baseline)' if name in BASELINES else verdict(r, base)} |")
    L += ["", "CPU s: the method alone (frame loading is extra: "
          + ", ".join(f"{run['sequence']} stride {run['stride']}: {run['load_cpu_s']:.1f} s" for run in res["runs"])
          + ")."]
    return "\n".join(L) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "output", help="a rendered run (only read)")
    ap.add_argument("--quick", action="store_true", help="only the default stride")
    ap.add_argument("--strides", default="1,2,3,4,5", help="frame strides for the VO methods and baselines")
    ap.add_argument("--colmap-strides", default="", help="strides COLMAP also runs at besides the default")
    ap.add_argument("--render-commit", help="commit that rendered DATA (default: DATA's git checkout, if any)")
    ap.add_argument("--methods", default=",".join(METHODS), help="comma-separated methods (the trivial baselines "
                                                                 "are always scored)")
    ap.add_argument("--sequences", default="", help="comma-separated patient/sequence keys (default: all)")
    args = ap.parse_args()
    data = args.data.resolve()
    conf = yaml.safe_load((ROOT / "conf" / "evaluate" / "default.yaml").read_text(encoding="utf-8"))["pose"]
    default = int(conf["frame_stride"])
    strides = [default] if args.quick else sorted({int(s) for s in args.strides.split(",") if s} | {default})
    colmap_strides = {default} | {int(s) for s in args.colmap_strides.split(",") if s}
    keys = sequences(data)
    if args.sequences:
        keys = [k for k in keys if "/".join(k) in args.sequences.split(",")]
    if not keys:
        print(f"room: error: {data}: no rendered sequence (<patient>/sequence_*/metadata/render.json)",
              file=sys.stderr)
        return 2
    keep_freed_memory()
    commit = args.render_commit or subprocess.run(["git", "-C", str(data), "rev-parse", "--short", "HEAD"],
                                                  capture_output=True, text=True).stdout.strip() or "unknown"
    res = {"command": "python benchmarks/pose_eval.py " + " ".join(sys.argv[1:]), "data": str(data),
           "render_commit": commit, "machine": f"{platform.machine()}, {os.cpu_count()} CPU cores",
           "load_start": os.getloadavg()[0], "images": conf["images"], "downscale": conf["downscale"],
           "default_stride": default, "runs": []}
    for patient, sequence in keys:
        for stride in strides:
            methods = tuple(m for m in args.methods.split(",") if m and (m != "colmap" or stride in colmap_strides))
            run = evaluate(data, patient, sequence, stride, methods, conf)
            res["runs"].append({"sequence": f"{patient}/{sequence}", "stride": stride, **run})
    res["load_end"] = os.getloadavg()[0]
    try:
        res["code_commit"] = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                                            text=True).stdout.strip()
    except OSError:
        res["code_commit"] = "unknown"
    name = "pose_eval_quick" if args.quick else "pose_eval"
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(_finite(res), indent=2, default=str) + "\n")
    md = markdown(res)
    (RESULTS / f"{name}.md").write_text(md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
