#!/usr/bin/env python3
"""Why the medial-axis stage found (or did not find) its root: the stage's report, also when it stops with an error.

    python scripts/diagnose_root.py PATIENT_DIR/anatomy/sdf.nii.gz

Runs :func:`room_pipeline.anatomy.medial_axis.extract_medial_axis` with the default ``MedialAxisParams`` on a lumen
SDF written by the sdf stage (``room run --until sdf``).  On success it prints the report (root point, re-rooting,
twigs dropped, ...).  When the extraction stops with an ``InputError`` (e.g. ``no trachea-like root``) the report is
lost with the stage; this diagnostic replaces the module's ``InputError`` by a subclass that, when raised, reads the
raising frame's ``rep`` (the report so far) and the candidate points (``top_root``, ``root``, ``imax``, ``centre``:
position in mm, inscribed radius in mm) and the first branches of the tree built so far, then prints them.  A
debugging aid only (it inspects the raising frame's locals); nothing it prints is used by the pipeline.
"""
from __future__ import annotations

import sys

import numpy as np

import room_pipeline.anatomy.medial_axis as ma
from room_pipeline.errors import InputError
from room_pipeline.io.volume import read_nifti_sdf


class _Captured(InputError):
    def __init__(self, msg: str):
        loc = sys._getframe(1).f_locals
        print("error:", msg)
        _show(loc.get("rep") or {}, loc)
        super().__init__(msg)


def _show(rep: dict, loc: dict) -> None:
    print("report:", {k: v for k, v in rep.items() if k != "timings"})
    pts, rad = loc.get("pts"), loc.get("rad")
    if pts is None or rad is None:
        return
    for name in ("top_root", "root", "imax", "centre"):
        if name in loc and isinstance(loc[name], (int, np.integer)) and 0 <= loc[name] < len(pts):
            i = int(loc[name])
            print(f"{name}: {np.round(pts[i] / 1e-3, 1).tolist()} mm, radius {rad[i] / 1e-3:.2f} mm")
    tr = loc.get("trachea")
    if tr is not None and len(tr):
        print(f"trachea medial points: {len(tr)}, z {pts[tr, 2].min() / 1e-3:.1f} .. {pts[tr, 2].max() / 1e-3:.1f} mm")
    for bid, b in list((loc.get("branches") or {}).items())[:8]:
        print(f"branch {bid}: {len(b['nodes'])} nodes, parent {b['parent']}, children {b['children']}")


def main(argv: list[str]) -> int:
    if len(argv) != 1:
        print("usage: diagnose_root.py SDF.nii.gz", file=sys.stderr)
        return 2
    ma.InputError = _Captured
    try:
        res = ma.extract_medial_axis(read_nifti_sdf(argv[0]), ma.MedialAxisParams())
    except InputError:
        return 1
    _show(res.report, {})
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
