#!/usr/bin/env python3
"""The flattened-trachea switch of the medial axis, measured (issue #18): cross-section aspect ratio vs the
old medial-spread measure, on synthetic tracheas and every shared real mask.

For each case the mask goes mask -> (largest component, crop) -> SDF -> ``extract_medial_axis`` at the
default parameters and the report's trachea fields are tabulated:

* ``trachea_aspect_ratio``: long / short axis of the lumen's cross-section normal to the trachea's axis
  (median of three sections below the top; ``anatomy/medial_axis.py::_cross_section_aspect``), the switch
  (``FLAT_ASPECT``);
* ``spread / r``: the old measure (the top medial points' spread over the top radius; it switched at 0.75);
* the sheet fraction (the second condition) and whether the root was centred (the switch's outcome).

Synthetic tracheas (``_synthetic_tree``: a trachea of the given elliptic cross-section running out of the
volume's top, main bronchi of 4.5 mm radius): round (radius 6 and 8 mm), 16x14, 20x12 and 24x10 mm, upright
and leaning 20 deg, at 0.7 mm voxels.  Real: Med-MPD 1-3, AirQuant, ATM_001, CASE073, CASE091 from
``../shared/data`` (skipped when absent).  Prints a table; saves benchmarks/results/anatomy_trachea_aspect.{md,json}.

    python benchmarks/anatomy_trachea_aspect.py [--quick]     # --quick: synthetic upright cases only
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from room_pipeline.anatomy.medial_axis import FLAT_ASPECT, MedialAxisParams, crop_to_interior, extract_medial_axis
from room_pipeline.anatomy.sdf import SdfParams, compute_sdf
from room_pipeline.io.volume import Volume, read_volume

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _synthetic import REAL_MASKS, flat_trachea_mask  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
SHARED = ROOT.parent / "shared" / "data" / "airway_masks"
REAL = REAL_MASKS
MM = 1e-3


def _synthetic_tree(half_x: float, half_y: float, tilt_deg: float = 0.0) -> Volume:
    """:func:`_synthetic.flat_trachea_mask` (the tests' flattened trachea) on a y extent of +-12 mm."""
    return flat_trachea_mask(half_x, half_y, tilt_deg, y_extent=12.0)


SYNTH = {"round r6": (6.0, 6.0), "round r8": (8.0, 8.0), "16x14": (8.0, 7.0), "20x12": (10.0, 6.0),
         "24x10": (12.0, 5.0)}


def measure(name: str, kind: str, mask: Volume) -> dict:
    from room_pipeline.anatomy.segment import validate_mask

    t0 = time.process_time()
    m = validate_mask(mask)
    sdf = compute_sdf(crop_to_interior(m, 6), SdfParams())
    rep = extract_medial_axis(sdf, MedialAxisParams()).report
    r_top = rep.get("trachea_top_radius_mm") or rep["root_radius_mm"]
    return {"case": name, "kind": kind, "aspect": rep["trachea_aspect_ratio"],
            "spread_over_r": round(rep["trachea_top_spread_mm"] / r_top, 3) if r_top else None,
            "sheet_fraction": rep["trachea_top_sheet_fraction"], "root_centred": rep["root_centred"],
            "cpu_s": round(time.process_time() - t0, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="synthetic upright cases only (smoke)")
    args = ap.parse_args()
    rows = []
    for name, (hx, hy) in SYNTH.items():
        for tilt in ((0.0,) if args.quick else (0.0, 20.0)):
            label = name + (f" tilted {tilt:g} deg" if tilt else "")
            rows.append(measure(label, "synthetic", _synthetic_tree(hx, hy, tilt)))
            print(rows[-1], flush=True)
    if not args.quick:
        for name, rel in REAL.items():
            p = SHARED / rel
            if not p.exists():
                print(f"skipped {name}: {p} not found")
                continue
            rows.append(measure(name, "shared real", read_volume(p)))
            print(rows[-1], flush=True)
    flat = [r["aspect"] for r in rows if r["case"].startswith(("20x12", "24x10"))]
    roundish = [r["aspect"] for r in rows if not r["case"].startswith(("20x12", "24x10"))]
    summary = {"threshold": FLAT_ASPECT, "max_not_flat": max(roundish), "min_flat": min(flat) if flat else None}
    lines = ["# Flattened-trachea switch: cross-section aspect ratio (issue #18)", "",
             "`python benchmarks/anatomy_trachea_aspect.py" + (" --quick" if args.quick else "") + "`, "
             f"{platform.node()}.  Switch: aspect > {FLAT_ASPECT} (and the sheet fraction > 0.5).  Largest aspect "
             f"of the round, 16x14 mm and shared real tracheas: **{summary['max_not_flat']:.3f}**; smallest of the "
             f"20x12 / 24x10 mm ones: **{summary['min_flat'] if summary['min_flat'] is None else round(summary['min_flat'], 3)}**.  "
             "The old switch compared the medial spread / radius to 0.75.", "",
             "| case | kind | aspect (long/short) | old: spread / r | sheet fraction | root centred | CPU s |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['case']} | {r['kind']} | {r['aspect']:.3f} | {r['spread_over_r']} | {r['sheet_fraction']} "
                     f"| {r['root_centred']} | {r['cpu_s']} |")
    RESULTS.mkdir(parents=True, exist_ok=True)
    stem = "anatomy_trachea_aspect" + ("_quick" if args.quick else "")
    (RESULTS / f"{stem}.md").write_text("\n".join(lines) + "\n")
    (RESULTS / f"{stem}.json").write_text(json.dumps({"summary": summary, "rows": rows}, indent=1) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
