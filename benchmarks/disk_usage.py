#!/usr/bin/env python3
"""Bytes on disk of a finished DVC run (dataset + DVC cache) against the dataset's size (issue #14: <= 1.1x).

After ``dvc repro`` (or ``dvc exp run``) in ``WORKSPACE``::

    python benchmarks/disk_usage.py WORKSPACE --label default

* **dataset size**: the bytes of the files under ``<output_dir>`` (``du -sb``: contents, each hard-linked
  file once); ``output_dir`` is read from ``WORKSPACE/params.yaml``.
* **on disk**: ``du -sB1 -c <output_dir> .dvc/cache`` (allocated blocks; ``du`` counts a file hard-linked
  into the cache once), the same figure computed here from ``st_blocks`` over distinct inodes, and each
  part alone.
* how many output files are single-link (a copy beside its cache object, or an uncached out such as the
  metrics and timing files) and their bytes.

DVC links outputs into its cache when ``.dvc/config`` has ``cache.type = hardlink,...`` (see
``tests/test_dvc_cache.py``); the ratio depends on the filesystem (block size, reflink support), which is
recorded.  Rows are merged by ``--label`` into ``benchmarks/results/disk_usage.{md,json}``.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def _fail(msg: str) -> None:
    print(f"room: error: {msg}", file=sys.stderr)
    sys.exit(2)


def _du(*args: str) -> int:
    out = subprocess.run(["du", *args], capture_output=True, text=True, check=True).stdout.splitlines()
    return int(out[-1].split()[0])


def walk(paths: list[Path]) -> dict:
    """Distinct inodes under ``paths``: allocated bytes, content bytes, single-link files."""
    seen: set[tuple[int, int]] = set()
    alloc = content = single = single_bytes = files = 0
    for base in paths:
        for dirpath, _, names in os.walk(base):
            for n in names:
                st = os.lstat(os.path.join(dirpath, n))
                key = (st.st_dev, st.st_ino)
                if key in seen:
                    continue
                seen.add(key)
                files += 1
                alloc += st.st_blocks * 512
                content += st.st_size
                if st.st_nlink == 1 and base == paths[0]:
                    single += 1
                    single_bytes += st.st_size
    return {"files": files, "allocated_bytes": alloc, "content_bytes": content,
            "single_link_output_files": single, "single_link_output_bytes": single_bytes}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workspace", type=Path, help="a DVC workspace whose pipeline has finished")
    ap.add_argument("--label", required=True)
    args = ap.parse_args(argv)
    ws = args.workspace.resolve()
    params = ws / "params.yaml"
    cache = ws / ".dvc" / "cache"
    if not params.is_file() or not cache.is_dir():
        _fail(f"{ws}: not a DVC workspace with a cache (needs params.yaml and .dvc/cache)")
    out_dir = ws / str((yaml.safe_load(params.read_text(encoding="utf-8")) or {}).get("output_dir", "data/output"))
    if not out_dir.is_dir():
        _fail(f"{out_dir}: output_dir not found (run the pipeline first)")
    dataset = _du("-sb", str(out_dir))
    on_disk = _du("-sB1", "-c", str(out_dir), str(cache))
    parts = {"output_dir_alone": _du("-sB1", str(out_dir)), "cache_alone": _du("-sB1", str(cache))}
    inodes = walk([out_dir, cache])
    cache_types = subprocess.run(["git", "config", "-f", str(ws / ".dvc" / "config"), "cache.type"],
                                 capture_output=True, text=True).stdout.strip()
    fs = subprocess.run(["findmnt", "-n", "-o", "FSTYPE", "-T", str(ws)],
                        capture_output=True, text=True).stdout.strip()
    row = {"label": args.label, "dataset_bytes": dataset, "on_disk_bytes": on_disk,
           "ratio": round(on_disk / dataset, 4) if dataset else None, **parts, **inodes,
           "cache_type": cache_types, "filesystem": fs,
           "command": f"python benchmarks/disk_usage.py WORKSPACE --label {args.label}"}
    RESULTS.mkdir(parents=True, exist_ok=True)
    jf = RESULTS / "disk_usage.json"
    rows = {r["label"]: r for r in (json.loads(jf.read_text()) if jf.is_file() else {}).get("rows", [])}
    rows[args.label] = row
    doc = {"description": "bytes on disk of <output_dir> + .dvc/cache (du, hard links once) vs the dataset's "
                          "content bytes (du -sb <output_dir>)", "units": {"*_bytes": "bytes"},
           "rows": [rows[k] for k in sorted(rows)]}
    jf.write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n")
    lines = ["# Bytes on disk vs the dataset", "", "`python benchmarks/disk_usage.py WORKSPACE --label L` after a "
             "finished run. Bound (issue #14): on disk <= 1.1x the dataset.", "",
             "| run | dataset MB (du -sb) | output_dir MB (du) | cache MB alone | together MB (du -c) | ratio | "
             "single-link outputs (files, MB) | cache.type | filesystem |", "|---|---|---|---|---|---|---|---|---|"]
    for r in doc["rows"]:
        lines.append(f"| {r['label']} | {r['dataset_bytes'] / 1e6:.1f} | {r['output_dir_alone'] / 1e6:.1f} | "
                     f"{r['cache_alone'] / 1e6:.1f} | {r['on_disk_bytes'] / 1e6:.1f} | **{r['ratio']:.3f}** | "
                     f"{r['single_link_output_files']}, {r['single_link_output_bytes'] / 1e6:.1f} | "
                     f"{r['cache_type']} | {r['filesystem']} |")
    (RESULTS / "disk_usage.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
