"""Published numbers of the ROOM paper's Tables I-III, kept apart from anything this pipeline measures.

Source: S. Esposito et al., "ROOM: A Physics-Based Continuum Robot Simulator
for Photorealistic Medical Datasets Generation", arXiv:2509.13177
(https://arxiv.org/html/2509.13177v2, v1 at https://arxiv.org/html/2509.13177v1).

Status: **no number could be retrieved yet.**  The stored copies of the
paper reachable from this project (searched on 2026-11-21 with ten queries on
the tables' content: "Table I pose estimation RRA RTA AUC COLMAP", "TABLE II
L1 AbsRel RMSE delta1", fine-tuning, method names, ...) only returned the
title, abstract and introduction, never the experiments section; the tables'
captions are unknown too.  Following the rule "never invent a number", every
entry below is therefore empty and the report tables print "n/r" (not
retrieved) in the "paper (published)" columns.  What is known from the issue
text: Table I's RTA is printed as 0.07 while the paper's prose says "0.07%"
(the unit is ambiguous; the method it belongs to is not stated), so it is not
recorded either.

To fill in: add ``{method: {metric: value}}`` under ``rows`` of a table (the
metric names are the ``columns``; values exactly as printed in the paper,
with ``unit`` saying whether the paper prints fractions or %), set
``caption`` and ``retrieved`` and cite the version used in ``source``.
"""
from __future__ import annotations

from typing import Any

SOURCE = "https://arxiv.org/html/2509.13177v2"
CITATION = ("S. Esposito, M. Mattamala, D. Rebain, F. X. Zhang, K. Dhaliwal, M. Khadem, S. Ramamoorthy: "
            "ROOM: A Physics-Based Continuum Robot Simulator for Photorealistic Medical Datasets Generation, "
            "arXiv:2509.13177")

#: table id -> caption (None: not retrieved), metric columns, unit as printed, rows {method: {metric: value}}
TABLES: dict[str, dict[str, Any]] = {
    "table_1_pose": {
        "caption": None,
        "columns": ("RRA@5", "RTA@5", "AUC@30"),
        "unit": None,          # the paper's Table I and its prose disagree on RTA (0.07 vs "0.07%")
        "rows": {},
        "retrieved": False,
    },
    "table_2_depth": {
        "caption": None,
        "columns": ("L1_mm", "AbsRel", "RMSE_mm", "delta1"),
        "unit": None,
        "rows": {},
        "retrieved": False,
    },
    "table_3_finetune": {
        "caption": None,
        "columns": ("L1_mm", "AbsRel", "RMSE_mm", "delta1"),
        "unit": None,
        "rows": {},            # {"<dataset> before": {...}, "<dataset> after": {...}}
        "retrieved": False,
    },
}

NOT_RETRIEVED = "n/r"
NOTE = ("paper (published): numbers of arXiv:2509.13177 Tables I-III; 'n/r' = not retrieved (the stored copies of "
        "the paper available to this project hold no table body; no value is invented)")


def published(table: str, row: str, metric: str) -> float | None:
    """The paper's value, or None when it is not recorded."""
    return TABLES[table]["rows"].get(row, {}).get(metric)
