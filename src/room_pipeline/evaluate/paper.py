"""Published numbers of the ROOM paper's Tables I-III, kept apart from anything this pipeline measures.

Source: S. Esposito et al., "ROOM: A Physics-Based Continuum Robot Simulator
for Photorealistic Medical Datasets Generation", arXiv:2509.13177
(https://arxiv.org/html/2509.13177v2).  The values were transcribed from the
paper's tables as quoted in the project's issue #16; they are kept as the
strings printed there (``"0.440"`` stays ``0.440``, no unit conversion) and the
report tables show them verbatim, in columns headed "paper (published)".

* Table I (pose; RRA@5 / RTA@5 / AUC@30, mean over five sequences).  The paper
  prints these numbers without a % sign in the table; its prose says "0.07%"
  for COLMAP's RTA, so the RTA column's unit is ambiguous: shown as printed.
* Table II (depth; L1 mm / AbsRel / RMSE mm / delta1 %).  DAV2 (Rel.) is
  scale-aligned per sequence by the ground-truth median, like our ``median`` rows.
* Table III (fine-tuning; the external phantom dataset of Visentini-Scarzanella
  et al. 2017, ten image-depth pairs, original -> fine-tuned).  That dataset is
  not available to this project, so these rows have no measured counterpart.

None of the paper's methods except COLMAP is run under the same name here (our
``orb_vo`` is two-frame ORB visual odometry, not ORB-SLAM3), so only ``colmap``
is put next to a published row (:data:`ALIASES`); the others are listed as
"paper only" rows.
"""
from __future__ import annotations

from typing import Any

SOURCE = "https://arxiv.org/html/2509.13177v2"
CITATION = ("S. Esposito, M. Mattamala, D. Rebain, F. X. Zhang, K. Dhaliwal, M. Khadem, S. Ramamoorthy: "
            "ROOM: A Physics-Based Continuum Robot Simulator for Photorealistic Medical Datasets Generation, "
            "arXiv:2509.13177")


def _row(columns: tuple, values: str) -> dict[str, str]:
    parts = [v.strip() for v in values.split("/")]
    if len(parts) != len(columns):
        raise ValueError(f"{values!r}: expected {len(columns)} values")
    return dict(zip(columns, parts))


POSE_COLS = ("RRA@5", "RTA@5", "AUC@30")
DEPTH_COLS = ("L1_mm", "AbsRel", "RMSE_mm", "delta1")

#: table id -> caption, metric columns, unit as printed, rows {paper method: {metric: value as printed}}
TABLES: dict[str, dict[str, Any]] = {
    "table_1_pose": {
        "caption": "Pose estimation on ROOM sequences (RRA@5 / RTA@5 / AUC@30, mean over five sequences)",
        "columns": POSE_COLS,
        "unit": "as printed (no % sign; RTA unit ambiguous, the prose says 0.07%)",
        "rows": {
            "COLMAP": _row(POSE_COLS, "41.00 / 0.07 / 16.91"),
            "ORB-SLAM3": _row(POSE_COLS, "71.67 / 0.17 / 42.74"),
            "DUSt3R": _row(POSE_COLS, "63.00 / 0.21 / 54.90"),
            "VGGT": _row(POSE_COLS, "79.00 / 0.25 / 69.09"),
        },
        "retrieved": True,
    },
    "table_2_depth": {
        "caption": "Monocular depth on ROOM sequences (L1 mm / AbsRel / RMSE mm / delta1 %)",
        "columns": DEPTH_COLS,
        "unit": "L1, RMSE mm; AbsRel ratio; delta1 %",
        "rows": {
            "Metric3DV2": _row(DEPTH_COLS, "9.5 / 0.440 / 14.5 / 27.5"),
            "DAV2 (Metric)": _row(DEPTH_COLS, "9.7 / 0.459 / 14.7 / 28.5"),
            "DAV2 (Rel., GT-median scaled per sequence)": _row(DEPTH_COLS, "11.3 / 0.486 / 17.9 / 28.2"),
            "EndoDAC": _row(DEPTH_COLS, "9.4 / 0.432 / 14.4 / 29.6"),
            "UniDepth": _row(DEPTH_COLS, "10.6 / 0.476 / 16.6 / 27.1"),
            "EndoOmni": _row(DEPTH_COLS, "9.2 / 0.428 / 14.2 / 30.2"),
            "BREA-Depth": _row(DEPTH_COLS, "9.1 / 0.421 / 14.1 / 30.8"),
        },
        "retrieved": True,
    },
    "table_3_finetune": {
        "caption": ("Fine-tuning on ROOM data, tested on the external phantom dataset of Visentini-Scarzanella "
                    "et al. 2017 (ten image-depth pairs); original -> fine-tuned"),
        "columns": DEPTH_COLS,
        "unit": "L1, RMSE mm; AbsRel ratio; delta1 %",
        "rows": {
            "UniDepth original": _row(DEPTH_COLS, "8.0 / 0.545 / 10.0 / 19.77"),
            "UniDepth fine-tuned": _row(DEPTH_COLS, "4.0 / 0.277 / 6.0 / 59.87"),
            "DAV2 original": _row(DEPTH_COLS, "20.0 / 0.382 / 24.0 / 42.15"),
            "DAV2 fine-tuned": _row(DEPTH_COLS, "15.0 / 0.291 / 20.0 / 55.42"),
            "BREA-D original": _row(DEPTH_COLS, "14.0 / 0.197 / 19.0 / 65.39"),
            "BREA-D fine-tuned": _row(DEPTH_COLS, "13.0 / 0.192 / 18.0 / 67.70"),
        },
        "retrieved": True,
    },
}

#: our row name -> the paper's row of the same method (only where it is the same method)
ALIASES: dict[str, dict[str, str]] = {"table_1_pose": {"colmap": "COLMAP"}}

NOT_RETRIEVED = "n/r"
NOTE = ("paper (published): arXiv:2509.13177 Tables I-III, values exactly as printed there (not converted); "
        "'paper only' rows are methods or data not run here; 'n/r' = the paper has no such row")


def published(table: str, row: str, metric: str) -> str | None:
    """The paper's value as printed (a string), or None when the paper has no such row or metric."""
    name = ALIASES.get(table, {}).get(row, row)
    return TABLES[table]["rows"].get(name, {}).get(metric)


def paper_only_rows(table: str) -> list[str]:
    """The paper's rows that no measured row of ours stands next to."""
    mapped = set(ALIASES.get(table, {}).values())
    return [r for r in TABLES[table]["rows"] if r not in mapped]
