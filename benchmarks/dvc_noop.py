#!/usr/bin/env python3
"""Wall and CPU time of a no-op ``dvc repro`` in a finished DVC workspace (issue #14: <= 3 s).

Make a finished workspace first (a short run is enough; the no-op cost depends on the number of stages,
deps and output files, not on the frames' contents), then time ``dvc repro`` there::

    git clone . /tmp/ws && cd /tmp/ws && dvc exp run -S render.max_frames=5
    python benchmarks/dvc_noop.py /tmp/ws --label default --rounds 3

Each round runs ``dvc repro`` in ``WORKSPACE`` and records its wall time and its CPU time (user + sys of
the child processes, ``resource.getrusage(RUSAGE_CHILDREN)``), with the 1-minute load average before it
(wall time on a shared machine is polluted by other work; CPU time is not).  One warm-up run comes first
and is not counted (it fills DVC's state database if the workspace is new to this machine).  A round in
which DVC ran a stage fails the benchmark (exit 2): that is not a no-op.  Rows are merged by ``--label``
into ``benchmarks/results/dvc_noop.{md,json}`` (one row per DAG measured).
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def _fail(msg: str) -> None:
    print(f"room: error: {msg}", file=sys.stderr)
    sys.exit(2)


def _dvc() -> str:
    exe = Path(sys.executable).with_name("dvc")
    return str(exe) if exe.exists() else "dvc"


def repro_once(ws: Path) -> dict:
    """One ``dvc repro`` in ``ws``: wall s, CPU s (children user + sys), load before, DVC's output."""
    load = os.getloadavg()[0]
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run([_dvc(), "repro"], cwd=ws, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    out = proc.stdout + proc.stderr
    if proc.returncode != 0:
        _fail(f"{ws}: dvc repro exited {proc.returncode}: {out.strip().splitlines()[-1:]}")
    if "Running stage" in out:
        ran = [ln for ln in out.splitlines() if ln.startswith("Running stage")]
        _fail(f"{ws}: dvc repro ran {len(ran)} stage(s), not a no-op (first: {ran[0]}); finish the run first")
    return {"wall_s": round(wall, 3), "cpu_s": round(cpu, 3), "load_1min": round(load, 2)}


def dag_size(ws: Path) -> dict:
    """Stages after foreach/matrix expansion (from dvc.lock), code deps and lines of dvc.yaml."""
    lock = yaml.safe_load((ws / "dvc.lock").read_text(encoding="utf-8")) or {}
    stages = lock.get("stages") or {}
    deps = sum(len(s.get("deps") or []) for s in stages.values())
    code = sum(1 for s in stages.values() for d in s.get("deps") or [] if str(d.get("path", "")).startswith("src/"))
    outs = sum(len(s.get("outs") or []) for s in stages.values())
    return {"stages": len(stages), "deps": deps, "code_deps": code, "outs": outs,
            "dvc_yaml_lines": len((ws / "dvc.yaml").read_text(encoding="utf-8").splitlines())}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path, help="a DVC workspace whose pipeline has finished")
    ap.add_argument("--label", required=True, help="the row's name (e.g. default, shared_masks)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--note", default="", help="free text for the row (e.g. which dvc.yaml)")
    args = ap.parse_args(argv)
    ws = args.workspace.resolve()
    if not (ws / "dvc.yaml").is_file() or not (ws / "dvc.lock").is_file():
        _fail(f"{ws}: not a finished DVC workspace (needs dvc.yaml and dvc.lock)")
    if args.rounds < 1:
        _fail(f"--rounds must be >= 1, got {args.rounds}")
    repro_once(ws)                                   # warm-up: not counted
    rounds = [repro_once(ws) for _ in range(args.rounds)]
    fs = subprocess.run(["findmnt", "-n", "-o", "FSTYPE", "-T", str(ws)],
                        capture_output=True, text=True).stdout.strip()
    row = {"label": args.label, "note": args.note, **dag_size(ws), "rounds": rounds,
           "wall_s_median": statistics.median(r["wall_s"] for r in rounds),
           "cpu_s_median": statistics.median(r["cpu_s"] for r in rounds),
           "filesystem": fs, "cpus": os.cpu_count(), "python": platform.python_version(),
           "dvc": subprocess.run([_dvc(), "--version"], capture_output=True, text=True).stdout.strip(),
           "command": f"python benchmarks/dvc_noop.py WORKSPACE --label {args.label} --rounds {args.rounds}"}
    RESULTS.mkdir(parents=True, exist_ok=True)
    jf = RESULTS / "dvc_noop.json"
    rows = {r["label"]: r for r in (json.loads(jf.read_text()) if jf.is_file() else {}).get("rows", [])}
    rows[args.label] = row
    doc = {"description": "no-op `dvc repro` in a finished workspace: wall and CPU (children user+sys) seconds",
           "units": {"wall_s, cpu_s": "s", "load_1min": "1-minute load average before the round"},
           "rows": [rows[k] for k in sorted(rows)]}
    jf.write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")
    lines = ["# No-op `dvc repro`", "", "`python benchmarks/dvc_noop.py WORKSPACE --label L --rounds N` in a finished "
             "workspace (a warm-up run first, not counted). Bound (issue #14): <= 3 s.", "",
             "| DAG | note | stages | code deps | outs | dvc.yaml lines | wall s (median) | CPU s (median) | "
             "load | filesystem |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in doc["rows"]:
        loads = "-".join(f"{x['load_1min']:.1f}" for x in r["rounds"])
        lines.append(f"| {r['label']} | {r['note']} | {r['stages']} | {r['code_deps']} | {r['outs']} | "
                     f"{r['dvc_yaml_lines']} | {r['wall_s_median']:.2f} | {r['cpu_s_median']:.2f} | {loads} | "
                     f"{r['filesystem']} |")
    (RESULTS / "dvc_noop.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
