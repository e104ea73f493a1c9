"""Where a finished default run's time went: every stage's wall time (and CPU time where the stage records it), from
the run's own ``metrics/*.timing.json``, beside the whole command's figures from ``/usr/bin/time -v``.

    git clone . X && cd X && env -u PYTHONPATH /usr/bin/time -v ./dev.sh pipeline > pipe.log 2>&1
    python benchmarks/pipeline_timing.py X/data/output --time-log X/pipe.log --name pipeline_timing_s18

Issue #15 bounds the whole fresh-clone command (the install included) at 20 min on 2 cores.  The stages' walls
do not add up to the command's: the rest is the install, each ``room stage`` process's start-up and imports, DVC
hashing the outputs, and the stages that write no wall time (train_depth, tables).  ``render`` records its CPU
time with its workers' (``cpu_seconds_per_frame``: every modality, the exposure meter and the writes of a frame).
Writes benchmarks/results/<name>.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from room_pipeline.io.metrics import TIMING_SUFFIX  # noqa: E402
from room_pipeline.paths import PatientPaths  # noqa: E402


def stage_rows(output_dir: Path) -> list[dict]:
    """One row per timing file of every patient: stage (file stem), patient, wall / CPU s, CPU s per frame, peak RSS
    (MiB, the stage process's own)."""
    rows = []
    for patient in sorted(d.name for d in output_dir.iterdir() if d.is_dir()):
        folder = PatientPaths(output_dir, patient).metrics("x").parent       # the catalogue's metrics folder
        for f in sorted(folder.glob(f"*{TIMING_SUFFIX}")) if folder.is_dir() else []:
            d = json.loads(f.read_text())
            if d.get("wall_time_s") is None:
                continue
            rows.append({"stage": f.name[:-len(TIMING_SUFFIX)], "patient": patient,
                         "wall_s": float(d["wall_time_s"]), "cpu_s": d.get("cpu_time_s"),
                         "cpu_s_per_frame": d.get("cpu_seconds_per_frame"), "peak_rss_mb": d.get("peak_rss_mb")})
    return rows


def time_log(path: Path) -> dict:
    """Wall (s), user / system CPU (s), peak RSS (MiB) and exit status from a ``/usr/bin/time -v`` log."""
    text = path.read_text(errors="replace")

    def grab(label: str) -> str | None:
        m = re.search(rf"^\s*{re.escape(label)}:\s*(.+)$", text, re.M)
        return m.group(1).strip() if m else None

    wall = grab("Elapsed (wall clock) time (h:mm:ss or m:ss)")
    secs = None
    if wall:
        parts = [float(x) for x in wall.split(":")]
        secs = sum(v * 60 ** k for k, v in enumerate(reversed(parts)))
    rss = grab("Maximum resident set size (kbytes)")
    return {"wall_s": secs, "user_s": float(grab("User time (seconds)") or "nan"),
            "system_s": float(grab("System time (seconds)") or "nan"),
            "peak_rss_mb": float(rss) / 1024.0 if rss else None, "exit_status": grab("Exit status")}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("output_dir", help="the run's output_dir (data/output of the clone)")
    ap.add_argument("--time-log", default=None, help="the /usr/bin/time -v log of the whole command")
    ap.add_argument("--name", default="pipeline_timing")
    ap.add_argument("--note", default="", help="a line on the run (commit, machine, load) for the table's header")
    args = ap.parse_args()
    rows = stage_rows(Path(args.output_dir))
    if not rows:
        print(f"{args.output_dir}: no metrics/*.timing.json with a wall time (run the pipeline first)", file=sys.stderr)
        return 2
    whole = time_log(Path(args.time_log)) if args.time_log else None
    total = sum(r["wall_s"] for r in rows)
    lines = [f"# Where the default run's time went ({args.name})", "",
             f"`python benchmarks/pipeline_timing.py {args.output_dir}"
             + (f" --time-log {args.time_log}" if args.time_log else "") + f" --name {args.name}`. {args.note}", ""]
    if whole:
        lines += [f"Whole command (`/usr/bin/time -v`): **{whole['wall_s'] / 60:.1f} min wall**, "
                  f"{whole['user_s']:.0f} s user + {whole['system_s']:.0f} s system CPU, peak RSS "
                  f"{whole['peak_rss_mb']:.0f} MiB, exit status {whole['exit_status']}.", ""]
    lines += [f"Stages' own walls sum to {total:.0f} s ({total / 60:.1f} min).", ""]
    peaks: dict[str, dict] = {}
    for r in rows:
        stage = r["stage"].split("_sequence_")[0]
        if r["peak_rss_mb"] is not None and r["peak_rss_mb"] > peaks.get(stage, {}).get("peak_rss_mb", -1):
            peaks[stage] = r
    if peaks:
        lines += ["Largest peak RSS of each stage over the patients: " + ", ".join(
            f"{k} {v['peak_rss_mb']:.0f} MiB ({v['patient']})"
            for k, v in sorted(peaks.items(), key=lambda kv: -kv[1]["peak_rss_mb"])) + ".", ""]
    lines += ["| stage | patient | wall s | CPU s | CPU s / frame | peak RSS MiB |", "|---|---|---|---|---|---|"]
    for r in sorted(rows, key=lambda r: -r["wall_s"]):
        cpu = f"{r['cpu_s']:.1f}" if r["cpu_s"] is not None else ""
        cpf = f"{r['cpu_s_per_frame']:.3f}" if r["cpu_s_per_frame"] is not None else ""
        rss = f"{r['peak_rss_mb']:.0f}" if r["peak_rss_mb"] is not None else ""
        lines.append(f"| {r['stage']} | {r['patient']} | {r['wall_s']:.1f} | {cpu} | {cpf} | {rss} |")
    md = "\n".join(lines) + "\n"
    out = ROOT / "benchmarks" / "results"
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.name}.json").write_text(json.dumps({"whole": whole, "stages": rows, "stage_wall_sum_s": total},
                                                      indent=1) + "\n")
    (out / f"{args.name}.md").write_text(md)
    print(md)                                          # after the files: a closed pipe loses no result
    return 0


if __name__ == "__main__":
    sys.exit(main())
