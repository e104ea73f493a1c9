"""Closed-loop navigation vs perception quality (issue #19): a sweep over depth estimator x sensor-noise level.

    python benchmarks/navigation_sweep.py --output-dir OUTPUT_DIR [--depth gt,shading_sfs,cnn] [--noise 0,1]
                                          [--patients patient_000] [--targets-per-patient N] [--max-time-s S]
                                          [--name NAME] [--report] [overrides ...]
    python benchmarks/navigation_sweep.py --collect RUN.json [RUN.json ...]     # episodes run elsewhere
    python benchmarks/navigation_sweep.py --collect A.json B.json --name NAME   # merge sweeps (e.g. one a cell)
    python benchmarks/navigation_sweep.py --smoke                                # a straight tube, 1 s episodes

Each cell runs the ``depth`` policy (:func:`room_pipeline.navigation.closed_loop.run_episode`) with
``navigate.depth`` = the estimator (``gt`` = ray-cast ground truth; others run on the loop's rendered RGB,
relative ones median-scaled to gt, :mod:`room_pipeline.navigation.depth_source`) and ``navigate.noise`` = the
noise beta added to that RGB (``gt`` has no image: only noise 0).  Targets: ``targets_per_patient`` branches of
generation ``navigate.benchmark.target_generation`` drawn (``navigate.benchmark.seed``) among the eligible ones,
the same draw as benchmarks/navigation.py.  Per cell: success, outcome counts, peak contact force, min wall
clearance, generation reached, CPU per control step (``time.process_time``: render + estimator + plan + 0.1 s
of physics) and the estimator's own CPU per call.  Writes benchmarks/results/NAME.{md,json} (``--name``, default
``navigation_sweep``) and, with ``--report``, the table to reports/NAME.md too.  ``--collect`` takes episode files
of ``room navigate episode --out`` and this script's own result JSONs (their episodes), so cells run as separate
processes merge into one table.

The same sweep as single runs (a shell loop; ``room navigate episode`` is a tool, not a DVC stage, so
``dvc exp run -S`` does not reach it)::

    for d in gt shading_sfs cnn; do for n in 0 1; do [ $d = gt ] && [ $n != 0 ] && continue
      room navigate episode --output-dir OUT --patient patient_000 --target 22 --out runs/${d}_${n}_22.json \\
        navigate.depth=$d navigate.noise=$n navigate.episode.max_time_s=60; done; done
    python benchmarks/navigation_sweep.py --collect runs/*.json
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

from room_pipeline.config.compose import compose, section  # noqa: E402
from room_pipeline.errors import RoomError  # noqa: E402
from room_pipeline.navigation.params import BenchmarkParams, EpisodeParams  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
KEEP = ("patient", "target", "outcome", "success", "time_s", "path_length_mm", "peak_contact_force_n",
        "min_wall_clearance_mm", "generation_reached", "control_steps", "perception", "cpu_per_step_s",
        "estimator_cpu_per_call_s")


class _Timed:
    """A depth source that also sums its own CPU time (the estimator's cost per control step)."""

    def __init__(self, src) -> None:
        self.src, self.cpu, self.calls = src, 0.0, 0

    def __call__(self, eyes, pose):
        c0 = time.process_time()
        try:
            return self.src(eyes, pose)
        finally:
            self.cpu += time.process_time() - c0
            self.calls += 1


def _episode(patient, target, depth, noise, cfg, output_dir) -> dict:
    import dataclasses

    from room_pipeline.navigation.cli import params_from
    from room_pipeline.navigation.closed_loop import run_episode
    from room_pipeline.navigation.depth_source import NavPerception, loop_camera, make_depth_source

    planner, ep, sim = params_from(cfg)
    ep = dataclasses.replace(ep, policy="depth")
    src = make_depth_source(NavPerception(depth, noise), section(cfg, "depth"), section(cfg, "noise"),
                            loop_camera(ep.image_px, ep.fov_deg), output_dir)
    timed = _Timed(src) if src is not None else None
    try:
        res = run_episode(patient, target, ep, planner, sim, depth_source=timed)
    finally:
        if src is not None:
            src.close()
    res["perception"] = {"depth": depth, "noise": noise}
    res["estimator_cpu_per_call_s"] = timed.cpu / max(1, timed.calls) if timed else None
    return {k: res.get(k) for k in KEEP}


def _smoke_patient():
    """A closed 6 mm straight tube with a two-branch centreline (the tests' tube)."""
    import math

    from room_pipeline.anatomy.centreline import CentrelineGraph, GraphBranch
    from room_pipeline.io.mesh import Mesh
    from room_pipeline.navigation.airways import Patient

    r, n_ring = 0.006, 24
    z = np.arange(0.0, 0.18 + 1e-12, 0.002)
    th = np.linspace(0, 2 * math.pi, n_ring, endpoint=False)
    V = [[r * math.cos(a), r * math.sin(a), zi] for zi in z for a in th] + [[0, 0, 0], [0, 0, z[-1]]]
    F = []
    for i in range(len(z) - 1):
        for j in range(n_ring):
            a, b = i * n_ring + j, i * n_ring + (j + 1) % n_ring
            F += [[a, b, a + n_ring], [b, b + n_ring, a + n_ring]]
    c0, c1 = len(V) - 2, len(V) - 1
    for j in range(n_ring):
        F += [[c0, (j + 1) % n_ring, j], [c1, (len(z) - 1) * n_ring + j, (len(z) - 1) * n_ring + (j + 1) % n_ring]]
    mesh = Mesh(np.array(V, float), np.array(F))
    C = np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1)
    h = len(z) * 6 // 10
    graph = CentrelineGraph([GraphBranch(0, -1, 0, C[:h + 1], np.full(h + 1, r)),
                             GraphBranch(1, 0, 1, C[h:], np.full(len(z) - h, r))])
    return {"tube": (Patient("tube", mesh, mesh, graph), [1])}


def _patients(cfg, output_dir: Path, names: list[str], n_targets: int) -> dict:
    from room_pipeline.navigation.airways import draw_targets
    from room_pipeline.navigation.cli import load_patient

    bench = BenchmarkParams.from_dict(section(cfg, "navigate").get("benchmark"))
    out = {}
    for name in names:
        p = load_patient(output_dir, name)
        out[name] = (p, draw_targets(p.graph, bench.target_generation, bench.min_route_radius_mm, n_targets,
                                     bench.seed)[1])
    return out


def cells(rows: list[dict]) -> list[dict]:
    """One row per (depth, noise): counts, rates and medians over its episodes."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        pc = r.get("perception") or {"depth": "gt", "noise": 0.0}
        groups.setdefault((pc["depth"], float(pc["noise"])), []).append(r)
    out = []
    for (d, n), g in sorted(groups.items()):
        est = [r["estimator_cpu_per_call_s"] for r in g if r.get("estimator_cpu_per_call_s") is not None]
        outcomes: dict[str, int] = {}
        for r in g:
            outcomes[r["outcome"]] = outcomes.get(r["outcome"], 0) + 1
        out.append({"depth": d, "noise": n, "episodes": len(g), "success": sum(bool(r["success"]) for r in g),
                    "outcomes": dict(sorted(outcomes.items())),
                    "peak_force_max_n": max(r["peak_contact_force_n"] for r in g),
                    "min_clearance_mm": min(r["min_wall_clearance_mm"] for r in g),
                    "generation_mean": float(np.mean([r["generation_reached"] for r in g])),
                    "path_mm_median": float(np.median([r["path_length_mm"] for r in g])),
                    "cpu_step_ms_mean": 1e3 * float(np.mean([r["cpu_per_step_s"]["total"] for r in g])),
                    "cpu_step_ms_worst": 1e3 * max(r["cpu_per_step_s"]["total"] for r in g),
                    "estimator_ms_per_call": 1e3 * float(np.mean(est)) if est else None})
    return out


def table(doc: dict) -> str:
    lines = [f"# Closed-loop navigation: depth estimator x sensor noise ({doc['what']})", "",
             f"`{doc['command']}`", ""]
    if doc.get("merged_from"):
        lines += ["Merged from:", ""] + [f"- `{c}`" for c in doc["merged_from"]] + [""]
    lines += [
             "Policy `depth` in every cell; `gt` = ray-cast ground truth (no image, so no noise); other estimators "
             "run on the loop's rendered 64x64 RGB (+ the calibrated sensor noise at beta = noise), relative ones "
             "median-scaled to the ground truth. CPU: `time.process_time()` per control step (render + estimator + "
             "plan + 0.1 s of physics), on a shared machine (load " + ("up to " if doc.get("merged_from") else "")
             + f"{doc['load']:.1f}" + " at the end of the run" + ("s" if doc.get("merged_from") else "") + ").", "",
             "| depth | noise | episodes | success | outcomes | peak force max (N) | min clearance (mm) | "
             "mean generation | median path (mm) | CPU/step ms (mean / worst) | estimator ms/step |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in doc["cells"]:
        est = "-" if c["estimator_ms_per_call"] is None else f"{c['estimator_ms_per_call']:.1f}"
        oc = ", ".join(f"{k} {v}" for k, v in c["outcomes"].items())
        lines.append(f"| {c['depth']} | {c['noise']:g} | {c['episodes']} | {c['success']}/{c['episodes']} | {oc} | "
                     f"{c['peak_force_max_n']:.3f} | {c['min_clearance_mm']:.2f} | {c['generation_mean']:.1f} | "
                     f"{c['path_mm_median']:.1f} | {c['cpu_step_ms_mean']:.0f} / {c['cpu_step_ms_worst']:.0f} | {est} |")
    lines += ["", "Per episode:", "", "| patient | target | depth | noise | outcome | time (s) | peak force (N) | "
              "generation | CPU/step (ms) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in doc["episodes"]:
        pc = r.get("perception") or {}
        lines.append(f"| {r['patient']} | {r['target']} | {pc.get('depth')} | {pc.get('noise')} | {r['outcome']} | "
                     f"{r['time_s']:.1f} | {r['peak_contact_force_n']:.3f} | {r['generation_reached']} | "
                     f"{1e3 * r['cpu_per_step_s']['total']:.0f} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--output-dir")
    ap.add_argument("--patients", help="comma-separated (default navigate.benchmark.patients)")
    ap.add_argument("--targets-per-patient", type=int, default=1)
    ap.add_argument("--depth", default="gt,shading_sfs,cnn")
    ap.add_argument("--noise", default="0,1")
    ap.add_argument("--max-time-s", type=float)
    ap.add_argument("--collect", nargs="+", help="episode JSONs of `room navigate episode --out` to tabulate")
    ap.add_argument("--smoke", action="store_true", help="a straight tube, 1 s episodes, gt and shading_sfs")
    ap.add_argument("--results", default=str(RESULTS))
    ap.add_argument("--name", default="navigation_sweep", help="result files' stem: RESULTS/NAME.{md,json}")
    ap.add_argument("--report", action="store_true", help="also write the table to reports/NAME.md")
    args, overrides = ap.parse_known_args(argv)
    cmd = "python benchmarks/navigation_sweep.py " + " ".join(sys.argv[1:] if argv is None else argv)
    merged: list[dict] = []
    try:
        if args.collect:
            rows = []
            for f in args.collect:
                d = json.loads(Path(f).read_text())
                if isinstance(d.get("episodes"), list):          # a sweep's own result file
                    rows += [{k: r.get(k) for k in KEEP} for r in d["episodes"]]
                    merged.append(d)
                else:                                             # one `room navigate episode --out` file
                    rows.append({k: d.get(k) for k in KEEP})
            what = f"{len(rows)} collected episodes" + "".join(sorted({f"; {m['what']}" for m in merged if m.get("what")}))
        else:
            if args.smoke:
                overrides = overrides + ["navigate.episode.max_time_s=1"]
                args.depth, args.noise = "gt,shading_sfs", "0,1"
            elif args.max_time_s:
                overrides = overrides + [f"navigate.episode.max_time_s={args.max_time_s}"]
            cfg = compose(overrides)
            if args.smoke:
                pats = _smoke_patient()
            else:
                if not args.output_dir:
                    ap.error("--output-dir (the patients' anatomy) or --collect or --smoke required")
                names = args.patients.split(",") if args.patients else list(BenchmarkParams.from_dict(section(cfg, "navigate").get("benchmark")).patients)
                pats = _patients(cfg, Path(args.output_dir), names, args.targets_per_patient)
            rows = []
            for d in args.depth.split(","):
                for n in (float(x) for x in args.noise.split(",")):
                    if d == "gt" and n > 0:
                        continue
                    for name, (p, targets) in pats.items():
                        for t in targets:
                            r = _episode(p, t, d, n, cfg, args.output_dir)
                            print(f"{name} target {t} depth {d} noise {n:g}: {r['outcome']} "
                                  f"({1e3 * r['cpu_per_step_s']['total']:.0f} ms CPU/step)", flush=True)
                            rows.append(r)
            max_t = EpisodeParams.from_dict(section(cfg, "navigate").get("episode")).max_time_s
            what = (f"{'smoke: straight tube' if args.smoke else ', '.join(pats)}; "
                    f"{sum(len(t) for _, t in pats.values())} target(s) per cell, max {max_t:g} s per episode")
    except RoomError as exc:
        print(f"room: error: {exc}", file=sys.stderr)
        return 2
    doc = {"command": cmd, "what": what,
           "load": max([m["load"] for m in merged if "load" in m], default=os.getloadavg()[0]),
           "merged_from": [m.get("command") for m in merged] or None, "cells": cells(rows), "episodes": rows}
    out = Path(args.results)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.name}.json").write_text(json.dumps(doc, indent=1) + "\n")
    (out / f"{args.name}.md").write_text(table(doc))
    if args.report:
        (ROOT / "reports").mkdir(exist_ok=True)
        (ROOT / "reports" / f"{args.name}.md").write_text(table(doc))
    print(table(doc))
    return 0


if __name__ == "__main__":
    sys.exit(main())
