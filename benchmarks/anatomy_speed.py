#!/usr/bin/env python3
"""Per-stage wall time and peak memory of the anatomy chain at several phantom volume sizes.

Runs ``room run`` (each stage in its own process, exactly as DVC does) on the
phantom with the (isotropic) voxel size chosen so that the volume holds about
N^3 voxels, for N in --sizes (default 128 256 384), plus the default phantom.
The field of view is the phantom's (body outline + tree + margin), so only the
voxel size changes.  Reads each stage's metrics (wall_time_s, peak_rss_mb), fits the
growth exponent t ~ voxels^a per stage, prints a table and saves
benchmarks/results/anatomy_speed.{json,md}.

    python benchmarks/anatomy_speed.py [--sizes 128 256 384] [--seed 0]
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from room_pipeline.io.metrics import read_metrics_file
from room_pipeline.paths import PatientPaths

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
CHAIN = ("segment", "sdf", "mesh")          # the anatomy chain proper
ALL = ("phantom",) + CHAIN


def run_case(out: Path, overrides: list[str]) -> dict:
    cmd = [sys.executable, "-m", "room_pipeline.cli", "run", "--until", "mesh", f"output_dir={out}", *overrides]
    t0 = time.perf_counter()
    subprocess.run(cmd, cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    pp = PatientPaths(out, "patient_000")
    meta = json.loads(pp.gt_metadata.read_text())
    row = {"shape": meta["shape"], "voxels": int(np.prod(meta["shape"])),
           "spacing_mm": [round(s * 1e3, 4) for s in meta["spacing_m"]], "total_wall_s_incl_startup": round(wall, 2)}
    for st in ALL:
        m = read_metrics_file(pp.stage_metrics(st))   # + its timing file
        row[f"{st}_s"] = m["wall_time_s"]
        row[f"{st}_peak_mb"] = m["peak_rss_mb"]
    row["chain_s"] = round(sum(row[f"{st}_s"] for st in CHAIN), 3)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 384])
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    RESULTS.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        seed = [f"phantoms.patient_000.seed={args.seed}"]
        default = run_case(Path(tmp) / "default", seed)
        default["case"] = "default"
        fov_mm = np.array(default["shape"]) * np.array(default["spacing_mm"])
        for n in args.sizes:
            s = float((np.prod(fov_mm) / n ** 3) ** (1 / 3))
            r = run_case(Path(tmp) / f"n{n}", seed + [f"phantom.spacing_mm=[{s:.4f},{s:.4f},{s:.4f}]"])
            r["case"] = f"~{n}^3 voxels"
            rows.append(r)
        rows.append(default)
    rows.sort(key=lambda r: r["voxels"])
    v = np.log([r["voxels"] for r in rows])
    exps = {st: float(np.polyfit(v, np.log([max(r[f"{st}_s"], 1e-3) for r in rows]), 1)[0]) for st in ALL}
    exps["chain"] = float(np.polyfit(v, np.log([r["chain_s"] for r in rows]), 1)[0])
    hdr = ["case", "shape", "voxels", "spacing_mm"] + [f"{st}_s" for st in ALL] + ["chain_s"] + \
          [f"{st}_peak_mb" for st in ALL]
    md = ["| " + " | ".join(hdr) + " |", "|" + "---|" * len(hdr)]
    for r in rows:
        md.append("| " + " | ".join(str(r[h]) for h in hdr) + " |")
    md.append("")
    md.append("Growth exponent a in t ~ voxels^a: " + ", ".join(f"{k} {val:.2f}" for k, val in exps.items()))
    text = "\n".join(md)
    print(text)
    (RESULTS / "anatomy_speed.json").write_text(json.dumps({"rows": rows, "growth_exponent": exps,
                                                            "command": "python benchmarks/anatomy_speed.py"},
                                                           indent=2) + "\n")
    (RESULTS / "anatomy_speed.md").write_text(
        "# Anatomy chain speed (phantom)\n\n`python benchmarks/anatomy_speed.py` on a 2-core machine; "
        "chain = segment + sdf + mesh; times in s, memory = peak RSS of each stage process in MB.\n\n"
        + text + "\n")


if __name__ == "__main__":
    main()
