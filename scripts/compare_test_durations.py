#!/usr/bin/env python3
"""Is the suite slower at one commit than at another?  Per-test durations of two pytest JUnit XML files.

    python scripts/compare_test_durations.py A.xml[,A2.xml...] B.xml[,B2.xml...] [--min-s 0.05] [--cpu] [--by-file N]

Make the two files on one machine at similar load, each from a fresh clone of its commit, e.g.
``CI=true pytest -m "not slow" --junitxml=A.xml`` at the older commit and ``--junitxml=B.xml`` at the newer,
best run twice in the order A B B A so a change of load shows as disagreement between the pairs.  Only the
tests present (same node id) and passed in both files are compared, so tests added or removed between the
commits do not count as speed.  Printed: the number of common tests, their summed seconds in A and B and
the ratio B / A, the median of the per-test ratios (over tests of at least ``--min-s`` seconds in A), and
the ten tests that slowed most.  Durations are pytest's wall times (setup + call + teardown of each test,
as JUnit records them), not CPU times: a loaded machine inflates both runs.  With ``--cpu`` the per-test
CPU seconds that ``scripts/pytest_cpu_times.py`` records (run pytest with ``-p pytest_cpu_times`` and
``scripts`` on ``PYTHONPATH``) are compared instead: much less sensitive to a shared machine.  Several files per
side (comma-separated): each test's smallest time over them (repeated runs; the minimum is the least disturbed).
``--by-file N``: the N test files whose summed time grew most.  ``--write-ids FILE``: the common tests' pytest
node ids, one a line (``tests/test_x.py::test_y[p]``; ``--root``, default ``.``, is the checkout whose files name
them), so both commits can be re-run on exactly those tests: ``pytest -p pytest_cpu_times @FILE``.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import xml.etree.ElementTree as ET
from pathlib import Path


def durations(path: Path, cpu: bool = False) -> dict[str, float]:
    """node id (``classname::name``) -> seconds of each passed test case in a JUnit XML file (wall, or the
    ``cpu_s`` property with ``cpu``)."""
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        print(f"room: error: {path}: not a readable JUnit XML file ({exc})", file=sys.stderr)
        raise SystemExit(2) from None
    out = {}
    for case in root.iter("testcase"):
        if any(case.find(tag) is not None for tag in ("failure", "error", "skipped")):
            continue
        if cpu:
            prop = case.find("properties/property[@name='cpu_s']")
            if prop is None:
                print(f"room: error: {path}: test case {case.get('name')} has no cpu_s property (run pytest with "
                      "-p pytest_cpu_times)", file=sys.stderr)
                raise SystemExit(2)
            seconds = float(prop.get("value"))
        else:
            seconds = float(case.get("time") or 0.0)
        out[f"{case.get('classname', '')}::{case.get('name', '')}"] = seconds
    return out


def durations_min(paths: str, cpu: bool = False) -> dict[str, float]:
    """Comma-separated JUnit files -> each test's smallest time over the files it passed in all of."""
    runs = [durations(Path(p), cpu) for p in paths.split(",") if p]
    common = set.intersection(*(set(r) for r in runs)) if runs else set()
    return {t: min(r[t] for r in runs) for t in common}


def node_id(test: str, root: Path) -> str | None:
    """JUnit ``classname::name`` (``tests.test_x.TestC::test_y[p]``) -> pytest node id
    (``tests/test_x.py::TestC::test_y[p]``), the module found as a file under ``root``; None when none is."""
    classname, _, name = test.partition("::")
    parts = classname.split(".")
    for k in range(len(parts), 0, -1):
        if (root / Path(*parts[:k])).with_suffix(".py").is_file():
            return "::".join(["/".join(parts[:k]) + ".py", *parts[k:], name])
    return None


def compare(a: dict[str, float], b: dict[str, float], min_s: float) -> dict:
    common = sorted(set(a) & set(b))
    sum_a, sum_b = sum(a[t] for t in common), sum(b[t] for t in common)
    ratios = [b[t] / a[t] for t in common if a[t] >= min_s]
    slowed = sorted(common, key=lambda t: b[t] - a[t], reverse=True)[:10]
    return {"common": len(common), "only_a": len(set(a) - set(b)), "only_b": len(set(b) - set(a)),
            "sum_a_s": sum_a, "sum_b_s": sum_b, "ratio": sum_b / sum_a if sum_a else float("nan"),
            "median_ratio": statistics.median(ratios) if ratios else float("nan"), "n_ratios": len(ratios),
            "slowed": [(t, a[t], b[t]) for t in slowed]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("a", help="JUnit XML of the older commit (comma-separated: repeated runs, minimum taken)")
    ap.add_argument("b", help="JUnit XML of the newer commit (likewise)")
    ap.add_argument("--min-s", type=float, default=0.05, help="tests shorter than this in A leave the median out")
    ap.add_argument("--cpu", action="store_true", help="compare the cpu_s property (pytest_cpu_times) instead")
    ap.add_argument("--by-file", type=int, default=0, metavar="N", help="also the N files that grew most")
    ap.add_argument("--write-ids", type=Path, metavar="FILE", help="write the common tests' pytest node ids here")
    ap.add_argument("--root", type=Path, default=Path("."), help="checkout the node ids' files are found in")
    args = ap.parse_args(argv)
    da, db = durations_min(args.a, args.cpu), durations_min(args.b, args.cpu)
    r = compare(da, db, args.min_s)
    if not r["common"]:
        print(f"room: error: {args.a} and {args.b} have no passed test in common", file=sys.stderr)
        return 2
    print(f"tests passed in both: {r['common']} (only in A: {r['only_a']}, only in B: {r['only_b']})")
    print(f"summed seconds: A {r['sum_a_s']:.1f}, B {r['sum_b_s']:.1f}, B / A {r['ratio']:.3f}")
    print(f"median per-test B / A over {r['n_ratios']} tests of >= {args.min_s} s in A: {r['median_ratio']:.3f}")
    print("slowed most (test, A s, B s):")
    for t, sa, sb in r["slowed"]:
        print(f"  {t}  {sa:.2f}  {sb:.2f}")
    if args.write_ids:
        common = sorted(set(da) & set(db))
        ids = [node_id(t, args.root) for t in common]
        if None in ids:
            print(f"room: error: no test file under {args.root} for {common[ids.index(None)]}", file=sys.stderr)
            return 2
        args.write_ids.write_text("".join(f"{i}\n" for i in ids), encoding="utf-8")
        print(f"wrote {len(ids)} node ids to {args.write_ids}")
    if args.by_file:
        files: dict[str, list] = {}
        for t in set(da) & set(db):
            f = files.setdefault(t.split("::")[0], [0, 0.0, 0.0])
            f[0] += 1
            f[1] += da[t]
            f[2] += db[t]
        print("files that grew most (file, tests, A s, B s):")
        for f, (n, sa, sb) in sorted(files.items(), key=lambda kv: kv[1][1] - kv[1][2])[:args.by_file]:
            print(f"  {f}  {n}  {sa:.1f}  {sb:.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
