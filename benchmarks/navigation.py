"""Closed-loop navigation benchmark (issue #19): vision policies vs the centreline oracle.

    python benchmarks/navigation.py --output-dir OUTPUT_DIR [--targets-per-patient N] [--policies depth,oracle,darkest]
                                    [--max-time-s S] [--trace] [--reuse A.json,B.json] [--name NAME] [--report STEM]
                                    [overrides ...]

OUTPUT_DIR holds the patients' anatomy stages' outputs (``room run --patient ID --until medial_axis
output_dir=OUTPUT_DIR``, or a full pipeline run).  For each patient of ``navigate.benchmark.patients``,
``targets_per_patient`` branches of generation ``target_generation`` are drawn (``seed``) among those whose whole
route is at least ``min_route_radius_mm`` wide (another draw: the override ``navigate.benchmark.seed=N``, e.g. to
check a change on targets it was not tuned on); every policy runs one episode per target
(:func:`room_pipeline.navigation.closed_loop.run_episode`, config ``navigate.episode`` / ``navigate.planner`` /
``simulate``).  Reports success (target branch reached), time, tip path length, physics steps in contact, peak
contact force, minimum distance from the scope's surface to the true lumen wall, generation reached, and CPU time
per control step (render + plan + simulate 0.1 s), next to the wall time and the load average (the machine is
shared: CPU time is the figure).  Writes benchmarks/results/NAME.{md,json} (``--name``, default navigation) and
reports/STEM.md (``--report``, default NAME; e.g. ``--merge ... --name navigation_s14 --report navigation``: the
committed table reports/navigation.md from a dated result, leaving benchmarks/results/navigation.md as it was);
``--reuse``: episodes already run in those result files with the same output dir and the same episode / planner /
simulate parameters are taken from them (an episode is deterministic; e.g. another seed's draw shares most targets);
``--trace``: also NAME_trace.md, every wrong-branch episode's fork, failure class and last steps
(:mod:`room_pipeline.navigation.diagnose`; the classified causes so far: benchmarks/results/navigation_failures.md).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from room_pipeline.config.compose import compose, section  # noqa: E402
from room_pipeline.navigation.cli import load_patient, params_from  # noqa: E402
from room_pipeline.navigation import diagnose  # noqa: E402
from room_pipeline.navigation.airways import Airways, draw_targets  # noqa: E402
from room_pipeline.navigation.closed_loop import run_episode  # noqa: E402
from room_pipeline.navigation.params import BenchmarkParams  # noqa: E402

FIELDS = ("success", "outcome", "time_s", "path_length_mm", "contact_steps", "peak_contact_force_n",
          "min_wall_clearance_mm", "generation_reached")


def summarise(rows: list[dict], policy: str) -> dict:
    r = [x for x in rows if x["policy"] == policy]
    if not r:
        return {}
    ok = [x for x in r if x["success"]]
    cpu = np.array([x["cpu_per_step_s"]["total"] for x in r])
    return {"policy": policy, "episodes": len(r), "success_rate": len(ok) / len(r),
            "success_no_contact_over_0_5n": sum(x["success"] and x["peak_contact_force_n"] <= 0.5 for x in r) / len(r),
            "median_time_s_success": float(np.median([x["time_s"] for x in ok])) if ok else None,
            "median_path_length_mm_success": float(np.median([x["path_length_mm"] for x in ok])) if ok else None,
            "peak_contact_force_n_max": max(x["peak_contact_force_n"] for x in r),
            "contact_step_fraction": sum(x["contact_steps"] for x in r) / max(1, sum(x["physics_steps"] for x in r)),
            "min_wall_clearance_mm_min": min(x["min_wall_clearance_mm"] for x in r),
            "mean_generation_reached": float(np.mean([x["generation_reached"] for x in r])),
            "cpu_per_step_s_mean": float(cpu.mean()), "cpu_per_step_s_max_episode": float(cpu.max()),
            "cpu_split_s": {k: float(np.mean([x["cpu_per_step_s"][k] for x in r])) for k in ("render", "plan", "simulate")}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--output-dir", required=True)
    ap.add_argument("--targets-per-patient", type=int)
    ap.add_argument("--policies")
    ap.add_argument("--max-time-s", type=float)
    ap.add_argument("--name", default="navigation")
    ap.add_argument("--report", help="stem of the reports/ copy of the table (default: --name)")
    ap.add_argument("--patients", help="comma-separated subset of navigate.benchmark.patients")
    ap.add_argument("--merge", nargs="+", help="combine these result JSONs (runs over other patients) into --name")
    ap.add_argument("--reuse", help="comma-separated result JSONs of earlier runs: an episode (patient, target, policy) run there "
                    "with the same output dir and the same episode / planner / simulate parameters is taken from it instead "
                    "of re-run (episodes are deterministic; the row keeps reused_from)")
    ap.add_argument("--trace", action="store_true", help="for every wrong-branch episode, the fork, the class of the "
                    "failure and its last steps (navigation/diagnose.py) into benchmarks/results/NAME_trace.md")
    args, overrides = ap.parse_known_args(argv)
    cfg = compose(overrides)
    bench = BenchmarkParams.from_dict(section(cfg, "navigate").get("benchmark"))
    planner, ep, sim = params_from(cfg)
    if args.max_time_s:
        ep = dataclasses.replace(ep, max_time_s=args.max_time_s)
    n_t = args.targets_per_patient or bench.targets_per_patient
    policies = args.policies.split(",") if args.policies else list(bench.policies)
    rows, plan, traces = [], [], []
    if args.merge:
        docs = [json.loads(Path(m).read_text()) for m in args.merge]
        rows = [r for d in docs for r in d["episodes"]]
        plan = list({t["patient"]: t for d in docs for t in d["targets"]}.values())   # one entry a patient
    same = {"output_dir": str(args.output_dir), "episode": dataclasses.asdict(ep), "planner": dataclasses.asdict(planner),
            "simulate": dataclasses.asdict(sim)}
    done = {}
    for f in (args.reuse.split(",") if args.reuse else []):
        d = json.loads(Path(f).read_text())
        if all(json.loads(json.dumps(v)) == d.get(k) for k, v in same.items()):
            for r in d["episodes"]:
                done.setdefault((r["patient"], r["target"], r["policy"]), dict(r, reused_from=f))
    patients = [] if args.merge else (args.patients.split(",") if args.patients else list(bench.patients))
    for pid in patients:
        patient = load_patient(Path(args.output_dir), pid)
        elig, pick = draw_targets(patient.graph, bench.target_generation, bench.min_route_radius_mm, n_t, bench.seed)
        plan.append({"patient": pid, "eligible": elig, "targets": pick})
        for target in pick:
            for pol in policies:
                if (pid, int(target), pol) in done:
                    rows.append(done[(pid, int(target), pol)])
                    print(f"{pid} target {target} {pol}: reused from {rows[-1]['reused_from']}", flush=True)
                    continue
                w0, c0 = time.time(), time.process_time()
                res = run_episode(patient, int(target), dataclasses.replace(ep, policy=pol), planner, sim)
                log = res.pop("log")
                if args.trace and res["outcome"] == "wrong_branch":
                    tr = diagnose.trace(Airways(patient.graph), int(target), log)
                    res["failure"] = None if tr is None else {k: tr[k] for k in tr if k != "steps"}
                    traces.append((res, tr))
                res["wall_s"] = time.time() - w0
                res["cpu_s"] = time.process_time() - c0
                res["load_avg_1min"] = os.getloadavg()[0]
                rows.append(res)
                print(f"{pid} target {target} (gen {res['target_generation']}) {pol:8s}: {res['outcome']:12s} "
                      f"t {res['time_s']:5.1f} s, path {res['path_length_mm']:6.1f} mm, peak force "
                      f"{res['peak_contact_force_n']:.3f} N, min clearance {res['min_wall_clearance_mm']:.2f} mm, "
                      f"gen {res['generation_reached']}, CPU/step {res['cpu_per_step_s']['total'] * 1e3:.0f} ms "
                      f"(wall {res['wall_s']:.0f} s, load {res['load_avg_1min']:.1f})", flush=True)
    summary = [summarise(rows, p) for p in policies]
    doc = {"command": "python benchmarks/navigation.py " + " ".join(argv if argv is not None else sys.argv[1:]),
           "merged_from": [docs_i["command"] for docs_i in docs] if args.merge else None,
           "output_dir": str(args.output_dir), "targets": plan, "episode": dataclasses.asdict(ep),
           "planner": dataclasses.asdict(planner), "simulate": dataclasses.asdict(sim), "summary": summary, "episodes": rows,
           "machine": {"platform": platform.platform(), "cpus": os.cpu_count()},
           "units": {"time": "s", "length": "mm", "force": "N"}}
    res_dir = ROOT / "benchmarks" / "results"
    res_dir.mkdir(parents=True, exist_ok=True)
    (res_dir / f"{args.name}.json").write_text(json.dumps(doc, indent=1) + "\n")
    md = table(doc)
    if args.trace:
        (res_dir / f"{args.name}_trace.md").write_text(trace_table(doc["command"], traces))
    (res_dir / f"{args.name}.md").write_text(md)
    (ROOT / "reports").mkdir(exist_ok=True)
    (ROOT / "reports" / f"{args.report or args.name}.md").write_text(md)
    print(md)
    return 0


def trace_table(command: str, traces: list) -> str:
    """Markdown: per wrong-branch episode, its fork, class and last steps (navigation/diagnose.py)."""
    L = [f"# Wrong-branch traces (`{command}`)", "", "Class: `target_in_wrong_child` (the axis target lay nearer the "
         "wrong child on most of the last 10 steps with a split seen), `late_turn` (nearer the right child, the tip "
         "entered the wrong one anyway), `no_fork_seen` (no split reported while commanded). Sides: distance to the "
         "wrong child's centreline minus to the right child's (mm; > 0 = the right child's side); tip off = tip to "
         "the route's centreline (mm). Uses the graph: diagnostic only, the policy never sees it.", ""]
    for res, tr in traces:
        if tr is None:
            L += [f"## {res['patient']} target {res['target']}: left the route off any fork of it", ""]
            continue
        L += [f"## {res['patient']} target {res['target']}: fork at branch {tr['parent']} (generation "
              f"{tr['generation']} children), right {tr['right']}, wrong {tr['wrong']}, entered at {tr['entry_t']:.1f} s:"
              f" **{tr['class']}**", "", "| t (s) | branch | command | split (mm) | tip side | target side | tip off "
              "| force (N) | openings at the split (u, v, px; pick; held) |", "|---|---|---|---|---|---|---|---|---|"]
        L += [f"| {r['t']:.1f} | {r['branch']} | {r['command']} | {r['split_mm']} | {r['tip_side_mm']} | "
              f"{r['target_side_mm']} | {r['tip_off_mm']} | {r['force_n']} | {_openings(r['openings'])} |" for r in tr["steps"]]
        L.append("")
    return "\n".join(L)


def _openings(o) -> str:
    return "-" if not o else " ".join(f"({u:.0f},{v:.0f},{n})" for u, v, n in o["uv_px"]) + \
        f"; {o['pick']}{'; held' if o['held'] else ''}"


def table(doc: dict) -> str:
    L = [f"# Closed-loop navigation to generation-N targets (navigate.benchmark.target_generation)", "",
         f"`{doc['command']}` (output_dir: the patients' anatomy; targets per patient: "
         + "; ".join(f"{t['patient']}: {t['targets']} of eligible {t['eligible']}" for t in doc["targets"]) + ")",
         "", "Policies: `depth` = rendered ground-truth depth -> point cloud -> planner (the upper bound of any depth "
         "estimator); `darkest` = steer to the darkest image region (naive); `oracle` = the centreline route (true pose "
         "and anatomy). All get the operator's left/right/up/down at each bifurcation of the route.", "",
         "| policy | episodes | success | success with peak force <= 0.5 N | median time (s) | median path (mm) | "
         "peak force max (N) | steps in contact | min wall clearance (mm) | mean generation reached | CPU per step (ms, mean / worst episode) |",
         "|---|---|---|---|---|---|---|---|---|---|---|"]
    for s in doc["summary"]:
        if not s:
            continue
        f = lambda v, p=1: "-" if v is None else f"{v:.{p}f}"  # noqa: E731
        L.append(f"| {s['policy']} | {s['episodes']} | {100 * s['success_rate']:.0f} % | "
                 f"{100 * s['success_no_contact_over_0_5n']:.0f} % | {f(s['median_time_s_success'])} | "
                 f"{f(s['median_path_length_mm_success'])} | {s['peak_contact_force_n_max']:.3f} | "
                 f"{100 * s['contact_step_fraction']:.0f} % | {s['min_wall_clearance_mm_min']:.2f} | "
                 f"{s['mean_generation_reached']:.1f} | {1e3 * s['cpu_per_step_s_mean']:.0f} / "
                 f"{1e3 * s['cpu_per_step_s_max_episode']:.0f} |")
    L += ["", "Per episode:", "", "| patient | target | policy | outcome | time (s) | path (mm) | peak force (N) | "
          "min clearance (mm) | generation | CPU/step (ms) | wall (s) | load |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in doc["episodes"]:
        L.append(f"| {r['patient']} | {r['target']} | {r['policy']} | {r['outcome']} | {r['time_s']:.1f} | "
                 f"{r['path_length_mm']:.1f} | {r['peak_contact_force_n']:.3f} | {r['min_wall_clearance_mm']:.2f} | "
                 f"{r['generation_reached']} | {1e3 * r['cpu_per_step_s']['total']:.0f} | {r['wall_s']:.0f}{' (reused)' if r.get('reused_from') else ''} | "
                 f"{r['load_avg_1min']:.1f} |")
    L += ["", "Min wall clearance: distance from the scope's backbone to the true lumen surface minus the scope "
          "radius, every control step (negative: the soft contact's penetration). CPU per step: "
          "`time.process_time()` of render + plan + 0.1 s of physics, averaged over the episode.", ""]
    return "\n".join(L)


if __name__ == "__main__":
    sys.exit(main())
