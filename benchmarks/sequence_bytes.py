#!/usr/bin/env python3
"""Bytes of a rendered sequence on disk, per folder and per frame (the dataset-size figure of issue #21).

Render the default sequence of the default phantom patient into a scratch folder, add its noisy frames,
then measure it::

    room run --until simulate output_dir=/tmp/room_size
    room stage render --patient patient_000/sequence_000 output_dir=/tmp/room_size
    room stage noise --patient patient_000/sequence_000 output_dir=/tmp/room_size
    python benchmarks/sequence_bytes.py /tmp/room_size/patient_000/sequence_000

Writes ``benchmarks/results/sequence_bytes.{md,json}`` (sizes in bytes of the files' contents, as ``du -sb``).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from room_pipeline.catalog import SequencePaths

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence", help="a rendered sequence folder (<output_dir>/<patient>/<sequence>)")
    args = ap.parse_args()
    seq = Path(args.sequence)
    meta = SequencePaths(seq).render_json
    if not meta.is_file():
        print(f"room: error: {seq}: not a rendered sequence (no metadata/render.json)", file=sys.stderr)
        sys.exit(2)
    render = json.loads(meta.read_text())
    n = len(render["frames"])
    folders = {}
    for d in sorted(p for p in seq.iterdir() if p.is_dir()):
        files = [f for f in d.rglob("*") if f.is_file()]
        folders[d.name] = {"files": len(files), "bytes": sum(f.stat().st_size for f in files)}
    total = sum(v["bytes"] for v in folders.values())
    res = {"sequence": str(seq), "frames": n, "modalities": render.get("modalities"),
           "storage": (render.get("storage") or {}).get("params"), "folders": folders, "total_bytes": total,
           "bytes_per_frame": total / n, "command": "python benchmarks/sequence_bytes.py " + " ".join(sys.argv[1:])}
    lines = ["# Bytes of a rendered sequence", "", f"`{res['command']}`: {n} frames, modalities "
             f"{', '.join(res['modalities'] or [])} (+ the noise stage's rgb_noisy when present).", "",
             "| folder | files | MB | bytes/frame |", "|---|---|---|---|"]
    for k, v in sorted(folders.items(), key=lambda kv: -kv[1]["bytes"]):
        lines.append(f"| {k} | {v['files']} | {v['bytes'] / 1e6:.1f} | {v['bytes'] / n:,.0f} |")
    lines.append(f"| **total** | {sum(v['files'] for v in folders.values())} | **{total / 1e6:.1f}** | "
                 f"{total / n:,.0f} |")
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "sequence_bytes.json").write_text(json.dumps(res, indent=2, sort_keys=True) + "\n")
    (RESULTS / "sequence_bytes.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
