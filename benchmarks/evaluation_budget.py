"""Time of the default run's evaluation stages (target: <= 5 min together on the project's 2-core machine).

    PYTHONPATH=src PATH=.venv/bin:$PATH python benchmarks/evaluation_budget.py [--output-dir DIR]

Runs, one after the other, exactly what `dvc repro` runs for the default configuration after `noise`:
``room stage train_depth``, ``evaluate_pose`` and ``evaluate_depth`` for every patient x sequence of
params.yaml, then ``tables``; measures each command's wall time and CPU time (user + sys of the child
processes, the fair figure while the machine is shared; user and system apart) and the load average.
The data must already be rendered (``dvc repro noise``), in params.yaml's output_dir or in ``--output-dir``
(e.g. a copy of a default run: ``cp -al data/output /scratch/output``).  Writes
benchmarks/results/evaluation_budget.{json,md}; the stages write their usual outputs (the same bytes as
`dvc repro` would), ``tables`` into reports/.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
TARGET_S = 300.0


def run(cmd: list[str]) -> dict:
    """Run one stage; its own CPU time from ``wait4`` (exact also when other stages run beside it)."""
    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as err:
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err)
        _, status, ru = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            err.seek(0)
            sys.exit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{err.read().decode(errors='replace')[-2000:]}")
    user, system = ru.ru_utime, ru.ru_stime
    return {"command": " ".join(cmd), "wall_s": round(wall, 2), "cpu_s": round(user + system, 2),
            "user_s": round(user, 2), "sys_s": round(system, 2), "load_average_after": os.getloadavg()[0]}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--output-dir", type=Path, help="the rendered run to evaluate (default: params.yaml's)")
    ap.add_argument("--jobs", type=int, default=1, help="stages run at once where the DAG allows (as dvc repro's "
                                                        "order: evaluate_depth after train_depth, tables last); "
                                                        "CPU time is per stage either way")
    args = ap.parse_args()
    params = yaml.safe_load((ROOT / "params.yaml").read_text(encoding="utf-8"))
    patients, sequences = sorted(params["patients"]), list(params["sequences"])
    trainer = params["depth"]["cnn"]["checkpoint_patient"]
    base = ["room", "stage"]
    tail = ["--params", "params.yaml", "--quiet"]
    if args.output_dir:
        tail.append(f"output_dir={args.output_dir.resolve()}")
    train = base + ["train_depth", "--patient", trainer] + tail
    poses = [base + ["evaluate_pose", "--patient", f"{pat}/{seq}"] + tail for pat in patients for seq in sequences]
    depths = [base + ["evaluate_depth", "--patient", f"{pat}/{seq}"] + tail for pat in patients for seq in sequences]
    tables = base + ["tables", "--patient", "all"] + tail
    load0 = os.getloadavg()
    t0 = time.perf_counter()
    if args.jobs <= 1:
        runs = [run(c) for c in [train] + [c for pd in zip(poses, depths) for c in pd] + [tables]]
    else:
        with ThreadPoolExecutor(args.jobs) as pool:
            pose_f = [pool.submit(run, c) for c in poses]
            train_r = run(train)                    # evaluate_depth reads its checkpoints and train_mean image
            depth_f = [pool.submit(run, c) for c in depths]
            runs = [train_r] + [f.result() for f in pose_f] + [f.result() for f in depth_f]
        runs.append(run(tables))
    elapsed = time.perf_counter() - t0
    load1 = os.getloadavg()
    total = {k: round(sum(r[k] for r in runs), 2) for k in ("wall_s", "cpu_s", "user_s", "sys_s")}
    total["elapsed_s"] = round(elapsed, 2)
    out = {"command": "python benchmarks/evaluation_budget.py" + (" --output-dir DIR" if args.output_dir else "")
           + (f" --jobs {args.jobs}" if args.jobs > 1 else ""), "jobs": args.jobs,
           "output_dir": str(args.output_dir or params.get("output_dir")), "runs": runs, "total": total, "target_s": TARGET_S, "load_average_before": load0,
           "load_average_after": load1, "cpu_count": os.cpu_count(),
           "pose": {k: params["evaluate"]["pose"][k] for k in ("frame_stride", "max_frames", "downscale", "methods")},
           "depth": {k: params["depth"][k] for k in ("frame_stride", "max_frames", "input", "methods")}}
    res = ROOT / "benchmarks" / "results"
    (res / "evaluation_budget.json").write_text(json.dumps(out, indent=2) + "\n")
    md = ["# Evaluation stages of the default run (benchmarks/evaluation_budget.py)", "",
          f"Target: <= {TARGET_S:.0f} s together. Load average before {load0[0]:.1f}, after {load1[0]:.1f} on "
          f"{os.cpu_count()} CPUs (wall time is inflated by other users' jobs; CPU time is the fair figure).", "",
          f"Data (DIR): `{out['output_dir']}`.", "",
          f"Pose: frame_stride {out['pose']['frame_stride']}, downscale {out['pose']['downscale']}, methods "
          f"{out['pose']['methods']}; depth: frame_stride {out['depth']['frame_stride']}, input {out['depth']['input']}.",
          "", "| command | wall s | CPU s | user s | sys s | load after |", "|---|---:|---:|---:|---:|---:|"]
    md += [f"| `{r['command'].replace(str(args.output_dir.resolve()) if args.output_dir else '@@', 'DIR')}` | "
           f"{r['wall_s']} | {r['cpu_s']} | {r['user_s']} | {r['sys_s']} | {r['load_average_after']:.1f} |"
           for r in runs]
    md += [f"| **total** | **{total['wall_s']}** | **{total['cpu_s']}** | {total['user_s']} | {total['sys_s']} | |",
           "",
           f"`{out['command']}`: {args.jobs} stage(s) at once; {total['elapsed_s']} s from first start to last end. "
           f"CPU within target: {'yes' if total['cpu_s'] <= TARGET_S else 'no'}; "
           f"summed wall within target: {'yes' if total['wall_s'] <= TARGET_S else 'no'}."]
    (res / "evaluation_budget.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
