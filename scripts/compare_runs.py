#!/usr/bin/env python3
"""Byte-identity of two pipeline runs: every output file with its sha256 and size, then the differences.

    python scripts/compare_runs.py list RUN [--out MANIFEST.json]
    python scripts/compare_runs.py compare RUN_A RUN_B [--name NAME] [--label-a A] [--label-b B]
    python scripts/compare_runs.py frames SEQ_A SEQ_B [--name NAME] [--label-a A] [--label-b B]

``frames`` (the cheaper check of a change to how frames are written): SEQ_B is one sequence folder re-rendered
(``room stage render``, e.g. with ``render.max_frames=N``) and every frame file of its render folders is
classified as below against the same path in the sequence folder SEQ_A of a finished run; SEQ_A's other frames
are not compared.

``RUN`` is the folder a run was made from: its ``data/output`` (the dataset, ``output_dir``) and
``reports/`` (the tables stage's ``evaluate.tables.output_dir``) are listed, every regular file with its
relative path, sha256 and size (:func:`room_pipeline.io.hashing.sha256_file`).  Left out of the
listing: the run records ``data/output/manifest.json`` and ``manifest.*.json`` beside them (they hold the
config, library versions and platform; their ``files`` and ``config`` are compared apart, with
:func:`room_pipeline.execution.manifest.compare_manifests`).

``compare`` lists both runs and sorts every path into

* identical: same sha256 and size;
* timing only: the bytes differ, but parsed they differ only in fields that are wall or CPU times: the
  ``metrics/*.timing.json`` files (the stages' timing files, :mod:`room_pipeline.io.metrics`), JSON leaves
  under a key of :data:`room_pipeline.io.metrics.TIMING_KEYS` or named ``seconds`` / ``cpu_seconds``
  (a pose method's time) or ``cpu_time_s``, CSV / Markdown / LaTeX table cells whose column header names a time
  (``s/frame``, ``seconds``, ``time``);
* encoding only: an OpenEXR file (scanline, ZIPS / ZIP / PXR24 chunks, as :mod:`room_pipeline.io.exr`
  writes them) whose header and every chunk's inflated bytes (the stored pixels) are the same, while some
  chunk's deflate stream differs: the same image, deflated to other bytes (ISA-L's deflate does not promise
  the same stream for the same input: measured, ``benchmarks/results/default_run_identity_s10.md``);
* different: anything else (a real behaviour change), and files present in one run only.

It writes ``benchmarks/results/NAME.{md,json}`` (default NAME ``run_identity``) and exits 1 when any file
is different.  Timings cannot be byte-identical between two runs, so they are the only exception.
"""
from __future__ import annotations

import argparse
import csv
import io
import json
import re
import struct
import sys
import zlib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from room_pipeline.execution.manifest import compare_manifests  # noqa: E402
from room_pipeline.io.hashing import sha256_file  # noqa: E402
from room_pipeline.io.atomic import write_json, write_text  # noqa: E402
from room_pipeline.io.metrics import TIMING_KEYS, TIMING_SUFFIX  # noqa: E402

#: the folders of a run that hold its outputs
PARTS = ("data/output", "reports")
#: run records (config, versions, platform), compared apart
RECORDS = re.compile(r"^data/output/manifest(\.[^/]*)?\.json$|^manifest\.[^/]*\.json$")
#: JSON keys holding a time (a pose method's wall and CPU seconds, the evaluation stages' cpu_time_s): TIMING_KEYS
#: lists them now (the evaluation files and DVC metrics no longer hold them); kept for runs made before that
EXTRA_TIMING_KEYS = frozenset({"seconds", "cpu_seconds", "cpu_time_s"})
#: a table column holding a time
TIME_COLUMN = re.compile(r"s/frame|seconds|\btime\b|_s$", re.I)


#: OpenEXR compression ids whose chunks are zlib streams -> scanlines per chunk (ZIPS, ZIP, PXR24)
EXR_DEFLATE = {2: 1, 3: 16, 5: 16}


def exr_chunks(path: Path) -> tuple[dict, list[bytes]] | None:
    """(header attributes name -> (type, bytes), each chunk's y and inflated bytes) of a single-part scanline
    OpenEXR with deflated chunks; None for any other file.  A chunk that does not inflate is kept as stored
    (a chunk not smaller deflated is stored raw), so the same pixels stored raw in one file and deflated in
    the other count as different (the check errs towards "different")."""
    b = path.read_bytes()
    if len(b) < 8 or struct.unpack_from("<i", b, 0)[0] != 20000630 or b[5] & 0x1A:   # tiled, deep, multipart
        return None
    i, attrs = 8, {}
    try:
        while b[i] != 0:
            j = b.index(0, i); name = b[i:j].decode(); i = j + 1
            j = b.index(0, i); kind = b[i:j].decode(); i = j + 1
            (n,) = struct.unpack_from("<i", b, i); i += 4
            attrs[name] = (kind, b[i:i + n]); i += n
        i += 1
        comp = attrs["compression"][1][0]
        if comp not in EXR_DEFLATE:
            return None
        y0, y1 = struct.unpack("<4i", attrs["dataWindow"][1])[1::2]
        n = (y1 - y0 + EXR_DEFLATE[comp]) // EXR_DEFLATE[comp]
        chunks = []
        for off in struct.unpack_from(f"<{n}Q", b, i):
            y, size = struct.unpack_from("<ii", b, off)
            data = b[off + 8:off + 8 + size]
            try:
                data = zlib.decompress(data)
            except zlib.error:
                pass
            chunks.append(struct.pack("<i", y) + data)
    except (KeyError, IndexError, ValueError, struct.error, UnicodeDecodeError):
        return None
    return attrs, chunks


def _exr_same_pixels(a: Path, b: Path) -> list[str] | None:
    """The chunks whose deflate streams differ when the two EXR files hold the same header and pixels,
    else None."""
    ea, eb = exr_chunks(a), exr_chunks(b)
    if ea is None or eb is None or ea[0] != eb[0] or ea[1] != eb[1]:
        return None
    return ["same header and inflated pixel data; the deflate stream of some chunk differs"]


def list_run(run: Path) -> list[dict]:
    """Every output file of the run folder ``run`` (sorted by path): path, sha256, size."""
    out = []
    for part in PARTS:
        base = run / part
        if not base.is_dir():
            continue
        for p in sorted(base.rglob("*")):
            rel = p.relative_to(run).as_posix()
            if p.is_file() and not p.is_symlink() and not RECORDS.match(rel):
                out.append({"path": rel, "sha256": sha256_file(p), "size": p.stat().st_size})
    return sorted(out, key=lambda f: f["path"])


def _json_leaves(obj, prefix=()):
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _json_leaves(v, prefix + (str(k),))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _json_leaves(v, prefix + (i,))
    else:
        yield prefix, obj


def _is_timing_path(path: tuple) -> bool:
    return any(isinstance(k, str) and (k in TIMING_KEYS or k in EXTRA_TIMING_KEYS) for k in path)


def _json_diff(a: str, b: str) -> tuple[list[str], list[str]]:
    """(differing timing leaves, differing other leaves) of two JSON texts."""
    la, lb = dict(_json_leaves(json.loads(a))), dict(_json_leaves(json.loads(b)))
    timing, other = [], []
    for k in sorted(set(la) | set(lb), key=lambda t: tuple(map(str, t))):
        if la.get(k, ...) != lb.get(k, ...):
            (timing if _is_timing_path(k) else other).append(".".join(map(str, k)))
    return timing, other


def _rows(text: str, kind: str) -> list[list[str]]:
    if kind == "csv":
        return list(csv.reader(io.StringIO(text)))
    if kind == "md":
        return [[c.strip() for c in line.strip().strip("|").split("|")] if line.startswith("|") else [line]
                for line in text.splitlines()]
    # LaTeX tabular rows: "a & b & c \\"
    return [[c.strip() for c in line.rstrip().removesuffix("\\\\").split(" & ")] if " & " in line else [line]
            for line in text.splitlines()]


def _table_diff(a: str, b: str, kind: str) -> tuple[list[str], list[str]]:
    """(differing cells in time columns, other differing cells or lines) of two table files."""
    ra, rb = _rows(a, kind), _rows(b, kind)
    if len(ra) != len(rb):
        return [], [f"{len(ra)} vs {len(rb)} rows"]
    timing, other, header = [], [], None
    for i, (x, y) in enumerate(zip(ra, rb)):
        if len(x) > 1 and (header is None or len(x) != len(header)):
            header = x                       # the first row of a table (or of a new table) names its columns
        if x == y:
            continue
        if len(x) != len(y) or header is None or len(x) != len(header):
            other.append(f"line {i + 1}")
            continue
        for j, (u, v) in enumerate(zip(x, y)):
            if u != v:
                (timing if TIME_COLUMN.search(header[j]) else other).append(f"line {i + 1} column '{header[j]}'")
    return timing, other


def classify(run_a: Path, run_b: Path, rel: str) -> tuple[str, list[str]]:
    """'timing', 'encoding' or 'different' for a file whose bytes differ, with the differing fields."""
    if rel.endswith(TIMING_SUFFIX):
        return "timing", ["(a stage timing file)"]
    a = (run_a / rel).read_text(encoding="utf-8", errors="replace")
    b = (run_b / rel).read_text(encoding="utf-8", errors="replace")
    suffix = Path(rel).suffix
    if suffix == ".exr":
        same = _exr_same_pixels(run_a / rel, run_b / rel)
        return ("encoding", same) if same else ("different", ["EXR pixels or header differ, or not a deflated "
                                                              "scanline EXR"])
    try:
        if suffix == ".json":
            timing, other = _json_diff(a, b)
        elif suffix in (".csv", ".md", ".tex"):
            timing, other = _table_diff(a, b, suffix[1:])
        else:
            return "different", ["binary or unparsed file"]
    except (ValueError, json.JSONDecodeError) as exc:
        return "different", [f"not parseable ({exc})"]
    return ("different", other) if other or not timing else ("timing", timing)


def compare(run_a: Path, run_b: Path) -> dict:
    fa = {f["path"]: f for f in list_run(run_a)}
    fb = {f["path"]: f for f in list_run(run_b)}
    identical, timing, encoding, different = [], {}, {}, {}
    for p in sorted(set(fa) | set(fb)):
        if p not in fb or p not in fa:
            different[p] = [f"only in {'the first' if p in fa else 'the second'} run"]
        elif (fa[p]["sha256"], fa[p]["size"]) == (fb[p]["sha256"], fb[p]["size"]):
            identical.append(p)
        else:
            kind, fields = classify(run_a, run_b, p)
            {"timing": timing, "encoding": encoding}.get(kind, different)[p] = fields
    same = set(identical)
    records = {}
    for m in sorted(run_a.glob("manifest.*.json")):
        other = run_b / m.name
        if other.is_file():
            records[m.name] = compare_manifests(json.loads(m.read_text()), json.loads(other.read_text()))
    return {"files": len(set(fa) | set(fb)), "identical": len(identical), "timing_only": timing,
            "encoding_only": encoding, "different": different, "bytes_a": sum(f["size"] for f in fa.values()),
            "bytes_b": sum(f["size"] for f in fb.values()), "run_records": records,
            # the first run's manifest ("sha256 size path" a line) and the second run's entries that differ
            "manifest_a": [f"{f['sha256']} {f['size']} {f['path']}" for f in fa.values()],
            "manifest_b_differing": [f"{f['sha256']} {f['size']} {f['path']}" for p, f in fb.items()
                                     if p not in same]}


def compare_frames(seq_a: Path, seq_b: Path) -> dict:
    """:func:`compare` for the frame files of SEQ_B's render folders against the same paths in SEQ_A."""
    from room_pipeline.catalog import SequencePaths

    rels = sorted(str(f.relative_to(seq_b)) for d in SequencePaths(seq_b).render_folders() if d.is_dir()
                  for f in d.rglob("*") if f.is_file())
    identical, encoding, different = [], {}, {}
    for rel in rels:
        a, b = seq_a / rel, seq_b / rel
        if not a.is_file():
            different[rel] = ["only in the second run"]
        elif sha256_file(a) == sha256_file(b):
            identical.append(rel)
        else:
            kind, fields = classify(seq_a, seq_b, rel)
            (encoding if kind == "encoding" else different)[rel] = fields
    return {"files": len(rels), "identical": len(identical), "timing_only": {}, "encoding_only": encoding,
            "different": different, "bytes_a": sum((seq_a / r).stat().st_size for r in rels if (seq_a / r).is_file()),
            "bytes_b": sum((seq_b / r).stat().st_size for r in rels), "run_records": {}}


def report_md(res: dict, label_a: str, label_b: str, command: str) -> str:
    n_t, n_d = len(res["timing_only"]), len(res["different"])
    L = [f"# Byte-identity of two runs: {label_a} vs {label_b}", "", f"Command: `{command}`", "",
         f"- files: {res['files']} ({res['bytes_a']} bytes in the first run, {res['bytes_b']} in the second)",
         f"- byte-identical: **{res['identical']}**",
         f"- differing only in timing fields (wall / CPU seconds): {n_t}",
         f"- EXR files with the same header and pixels, deflated to other bytes: {len(res.get('encoding_only', {}))}",
         f"- different otherwise, or in one run only: **{n_d}**", "",
         "Result: " + (("**identical** apart from the timings" + (" and the EXR deflate streams" if
                                                                   res.get("encoding_only") else "")
                       + " listed below") if not n_d else "**NOT identical**"),
         ""]
    if res["run_records"]:
        L += ["## Run records (`manifest.*.json`: files and config; versions and platform not compared)", ""]
        for name, diffs in res["run_records"].items():
            L.append(f"- {name}: " + ("files and config agree" if not diffs else f"{len(diffs)} differences: "
                                      + "; ".join(diffs[:10])))
        L.append("")
    if res["timing_only"]:
        L += ["## Files differing only in timing fields", "", "| file | differing fields |", "|---|---|"]
        for p, fields in res["timing_only"].items():
            shown = ", ".join(f"`{f}`" for f in fields[:6]) + (f" (+{len(fields) - 6} more)" if len(fields) > 6 else "")
            L.append(f"| {p} | {shown} |")
        L.append("")
    if res.get("encoding_only"):
        L += ["## EXR files with the same header and pixels, deflated to other bytes", "",
              "| file | what differs |", "|---|---|"]
        for p, fields in res["encoding_only"].items():
            L.append(f"| {p} | {'; '.join(fields)} |")
        L.append("")
    if res["different"]:
        L += ["## Different files", "", "| file | what differs |", "|---|---|"]
        for p, fields in res["different"].items():
            L.append(f"| {p} | {'; '.join(fields[:6])} |")
        L.append("")
    return "\n".join(L)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    ls = sub.add_parser("list", help="every output file of a run with its sha256 and size")
    ls.add_argument("run", type=Path)
    ls.add_argument("--out", type=Path)
    cp = sub.add_parser("compare", help="compare the outputs of two runs")
    cp.add_argument("run_a", type=Path)
    cp.add_argument("run_b", type=Path)
    cp.add_argument("--name", default="run_identity")
    cp.add_argument("--label-a", default="A")
    cp.add_argument("--label-b", default="B")
    fr = sub.add_parser("frames", help="compare a re-rendered sequence's frame files with a finished run's")
    fr.add_argument("run_a", type=Path, help="the finished run's sequence folder")
    fr.add_argument("run_b", type=Path, help="the re-rendered sequence folder")
    fr.add_argument("--name", default="frames_identity")
    fr.add_argument("--label-a", default="A")
    fr.add_argument("--label-b", default="B")
    args = ap.parse_args(argv)
    if args.cmd == "list":
        files = list_run(args.run)
        if args.out:
            write_json(args.out, {"run": str(args.run), "files": files})
        else:
            for f in files:
                print(f"{f['sha256']}  {f['size']:>10}  {f['path']}")
        return 0
    if args.cmd == "frames":
        from room_pipeline.catalog import SequencePaths

        for r in (args.run_a, args.run_b):
            if not SequencePaths(r).is_rendered():
                print(f"room: error: {r}: not a rendered sequence folder", file=sys.stderr)
                return 2
        res = compare_frames(args.run_a, args.run_b)
    else:
        for r in (args.run_a, args.run_b):
            if not (r / PARTS[0]).is_dir():
                print(f"room: error: {r}: no {PARTS[0]} folder (not a run folder)", file=sys.stderr)
                return 2
        res = compare(args.run_a, args.run_b)
    command = f"python scripts/compare_runs.py {args.cmd} {args.run_a} {args.run_b} --name {args.name} " \
              f"--label-a {args.label_a} --label-b {args.label_b}"
    md = report_md(res, args.label_a, args.label_b, command)
    out = ROOT / "benchmarks" / "results"
    write_text(out / f"{args.name}.md", md + "\n")
    write_json(out / f"{args.name}.json", {**res, "command": command, "label_a": args.label_a,
                                           "label_b": args.label_b})
    print(md)
    return 1 if res["different"] else 0


if __name__ == "__main__":
    sys.exit(main())
