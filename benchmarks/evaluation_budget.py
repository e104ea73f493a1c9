"""Time of the default run's evaluation stages (target: <= 5 min together on the project's 2-core machine).

    PYTHONPATH=src PATH=.venv/bin:$PATH python benchmarks/evaluation_budget.py

Runs, one after the other, exactly what `dvc repro` runs for the default configuration after `noise`:
``room stage train_depth``, ``evaluate_pose`` and ``evaluate_depth`` for every patient x sequence of
params.yaml, then ``tables``; measures each command's wall time and CPU time (user + sys of the child
processes, the fair figure while the machine is shared) and the load average.  The data must already be
rendered (``dvc repro noise``).  Writes benchmarks/results/evaluation_budget.{json,md}; the stages write
their usual outputs (the same bytes as `dvc repro` would).
"""
from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
TARGET_S = 300.0


def run(cmd: list[str]) -> dict:
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr[-2000:]}")
    return {"command": " ".join(cmd), "wall_s": round(wall, 2),
            "cpu_s": round((r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime), 2)}


def main() -> None:
    params = yaml.safe_load((ROOT / "params.yaml").read_text(encoding="utf-8"))
    patients, sequences = sorted(params["patients"]), list(params["sequences"])
    trainer = params["depth"]["cnn"]["checkpoint_patient"]
    base = ["room", "stage"]
    tail = ["--params", "params.yaml", "--quiet"]
    cmds = [base + ["train_depth", "--patient", trainer] + tail]
    for pat in patients:
        for seq in sequences:
            cmds.append(base + ["evaluate_pose", "--patient", f"{pat}/{seq}"] + tail)
            cmds.append(base + ["evaluate_depth", "--patient", f"{pat}/{seq}"] + tail)
    cmds.append(base + ["tables", "--patient", "all"] + tail)
    load0 = os.getloadavg()
    runs = [run(c) for c in cmds]
    load1 = os.getloadavg()
    total = {"wall_s": round(sum(r["wall_s"] for r in runs), 2), "cpu_s": round(sum(r["cpu_s"] for r in runs), 2)}
    out = {"runs": runs, "total": total, "target_s": TARGET_S, "load_average_before": load0,
           "load_average_after": load1, "cpu_count": os.cpu_count(),
           "pose": {k: params["evaluate"]["pose"][k] for k in ("frame_stride", "max_frames", "downscale", "methods")},
           "depth": {k: params["depth"][k] for k in ("frame_stride", "max_frames", "input", "methods")}}
    res = ROOT / "benchmarks" / "results"
    (res / "evaluation_budget.json").write_text(json.dumps(out, indent=2) + "\n")
    md = ["# Evaluation stages of the default run (benchmarks/evaluation_budget.py)", "",
          f"Target: <= {TARGET_S:.0f} s together. Load average before {load0[0]:.1f}, after {load1[0]:.1f} on "
          f"{os.cpu_count()} CPUs (wall time is inflated by other users' jobs; CPU time is the fair figure).", "",
          "| command | wall s | CPU s |", "|---|---:|---:|"]
    md += [f"| `{r['command']}` | {r['wall_s']} | {r['cpu_s']} |" for r in runs]
    md += [f"| **total** | **{total['wall_s']}** | **{total['cpu_s']}** |", "",
           f"CPU within target: {'yes' if total['cpu_s'] <= TARGET_S else 'no'}; "
           f"wall within target: {'yes' if total['wall_s'] <= TARGET_S else 'no'}."]
    (res / "evaluation_budget.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
