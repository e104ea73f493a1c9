#!/usr/bin/env python3
"""Peak RSS and time of the anatomy stages on the largest shared real airway mask.

Runs ``room run --until trajectory`` (each stage in its own process, as DVC does) on a real mask from
``../shared/data`` (default: the ATM'22 tree ATM_001, 512x512x679 at 0.82x0.82x0.5 mm, the largest shared
one) and reads every stage's metrics (wall_time_s, peak_rss_mb) plus the CPU time (user+sys) of the whole
run; prints a table and saves benchmarks/results/anatomy_memory.{json,md}.  Skips (exit 0, message) when the
shared data is absent.

    python benchmarks/anatomy_memory.py [--mask PATH] [--until trajectory]
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from room_pipeline.io.metrics import read_metrics_file
from room_pipeline.paths import PatientPaths

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DEFAULT = ROOT.parent / "shared/data/airway_masks/public_trees/axes_fixed/ATM_001_0000_fixed.nii.gz"
STAGES = ("segment", "sdf", "mesh", "medial_axis", "trajectory")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mask", default=str(DEFAULT))
    ap.add_argument("--until", default="trajectory", choices=STAGES)
    args = ap.parse_args()
    mask = Path(args.mask).resolve()
    if not mask.exists():
        print(f"skipped: {mask} not found (../shared/data absent)")
        return
    stages = STAGES[:STAGES.index(args.until) + 1]
    with tempfile.TemporaryDirectory() as tmp:
        cmd = [sys.executable, "-m", "room_pipeline.cli", "run", "--patient", "bench", "--until", args.until,
               f"output_dir={tmp}", "patients=phantom_single", f"+patients.bench={{kind: mask, input: '{mask}'}}"]
        t0, r0 = time.perf_counter(), resource.getrusage(resource.RUSAGE_CHILDREN)
        subprocess.run(cmd, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        wall = time.perf_counter() - t0
        rows = []
        for st in stages:
            seq = "sequence_000" if st == "trajectory" else ""                      # per-sequence stage
            m = read_metrics_file(PatientPaths(Path(tmp), "bench").stage_metrics(st, seq))   # + its timing file
            rows.append({"stage": st, "wall_s": m.get("wall_time_s"), "peak_rss_mb": m.get("peak_rss_mb")})
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    load = os.getloadavg()[0]
    md = ["| stage | wall s | peak RSS MB |", "|---|---|---|"]
    md += [f"| {r['stage']} | {r['wall_s']} | {r['peak_rss_mb']} |" for r in rows]
    md.append("")
    md.append(f"whole run: wall {wall:.1f} s, CPU (user+sys) {cpu:.1f} s, load average {load:.1f} "
              f"(2-core machine shared with other jobs: wall times are inflated)")
    text = "\n".join(md)
    print(text)
    RESULTS.mkdir(parents=True, exist_ok=True)
    name = "anatomy_memory"
    (RESULTS / f"{name}.json").write_text(json.dumps(
        {"mask": str(mask.relative_to(ROOT.parent)) if mask.is_relative_to(ROOT.parent) else str(mask),
         "rows": rows, "run_wall_s": round(wall, 2), "run_cpu_s": round(cpu, 2), "load_average": round(load, 2),
         "command": " ".join(["python benchmarks/anatomy_memory.py", *sys.argv[1:]])}, indent=2) + "\n")
    (RESULTS / f"{name}.md").write_text(
        f"# Anatomy stages on a real mask ({mask.name})\n\n`python benchmarks/anatomy_memory.py {' '.join(sys.argv[1:])}`; each stage in "
        "its own process; peak RSS of that process.\n\n" + text + "\n")


if __name__ == "__main__":
    main()
