#!/usr/bin/env python3
"""Bytes the recorded scope backbone adds to ``simulation.json`` (issue #14: the report draws the recorded scope).

For every simulated sequence under DIR (a dataset root ``<output_dir>``, a patient folder or a sequence folder):
the bytes of ``metadata/simulation.json`` as the simulate stage wrote it, the bytes of the same document
without ``frames[].backbone`` (serialised exactly as the stage serialises, ``io.atomic.write_json``'s format),
the backbone points per frame, and the sequence folder's total bytes (to put the increase in proportion)::

    room run --until simulate output_dir=/tmp/room_sim           # the default phantom's default sequence
    python benchmarks/simulation_record_bytes.py /tmp/room_sim

Writes ``benchmarks/results/simulation_record_bytes.{md,json}``.  Bad input: one line on stderr, exit 2.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from room_pipeline.catalog import SequencePaths, find_sequences

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def dumps(doc) -> bytes:
    """The stage's serialisation (room_pipeline.io.atomic.write_json)."""
    return (json.dumps(doc, indent=2, sort_keys=True, allow_nan=False) + "\n").encode("utf-8")


def folder_bytes(d: Path) -> int:
    return sum(f.stat().st_size for f in d.rglob("*") if f.is_file())


def measure(sp: SequencePaths) -> dict:
    raw = sp.simulation.read_bytes()
    doc = json.loads(raw)
    frames = doc.get("frames") or []
    points = [len(f["backbone"]) for f in frames if "backbone" in f]
    without = {**doc, "frames": [{k: v for k, v in f.items() if k != "backbone"} for f in frames]}
    seq = sp.root
    return {"sequence": f"{seq.parent.name}/{seq.name}", "frames": len(frames), "bytes": len(raw),
            "bytes_without_backbone": len(dumps(without)), "reserialised_identical": dumps(doc) == raw,
            "backbone_points_min": min(points) if points else 0, "backbone_points_max": max(points) if points else 0,
            "backbone_points_mean": round(sum(points) / len(points), 2) if points else 0.0,
            "sequence_folder_bytes": folder_bytes(seq)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", help="a dataset root, patient folder or sequence folder with metadata/simulation.json")
    args = ap.parse_args()
    root = Path(args.data)
    if not root.is_dir():
        print(f"room: error: {root}: not a folder", file=sys.stderr)
        sys.exit(2)
    found = find_sequences(root, "simulation")
    if not found:
        print(f"room: error: {root}: no <sequence>/metadata/simulation.json below it (run `room run --until "
              "simulate` first)", file=sys.stderr)
        sys.exit(2)
    rows = [measure(f) for f in found]
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "simulation_record_bytes.json").write_text(json.dumps({"rows": rows}, indent=2) + "\n")
    md = ["# simulation.json with and without the recorded scope backbone", "",
          f"`python benchmarks/simulation_record_bytes.py {args.data}` (bytes of the files' contents).", "",
          "| sequence | frames | simulation.json bytes | without backbone | added | added per frame | backbone points "
          "per frame (min / mean / max) | sequence folder bytes | added / folder |",
          "|---|---:|---:|---:|---:|---:|---|---:|---:|"]
    for r in rows:
        added = r["bytes"] - r["bytes_without_backbone"]
        md.append(f"| {r['sequence']} | {r['frames']} | {r['bytes']} | {r['bytes_without_backbone']} | {added} | "
                  f"{added / max(r['frames'], 1):.0f} | {r['backbone_points_min']} / {r['backbone_points_mean']} / "
                  f"{r['backbone_points_max']} | {r['sequence_folder_bytes']} | "
                  f"{100.0 * added / max(r['sequence_folder_bytes'], 1):.3f} % |")
    md += ["", "The sequence folder of a simulated-only run holds no frames; a rendered default sequence is "
           "about 0.7 GB (README, benchmarks/results/sequence_bytes.md)."]
    (RESULTS / "simulation_record_bytes.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
