"""Why a closed-loop episode went into a wrong branch: a trace of its last control steps before the wrong fork.

Diagnostic only (benchmarks/navigation.py ``--trace``): it reads the episode's per-step log (``tip_mm`` /
``target_mm`` world, ``axis_split_mm``, ``command``; :mod:`.closed_loop`) and the centreline graph, which the
policy never sees.  The fork is the route branch whose child the tip left the route into: ``parent`` (on the
route), ``right`` (the route's child), ``wrong`` (the branch the tip ended in, or the sibling on its way).  Per
step, the tip's and the target's side of the fork: ``tip_side_mm`` / ``target_side_mm`` = distance to the wrong
child's centreline minus distance to the right child's (> 0: nearer the right child), and ``tip_off_mm``, the
tip's offset from the route's centreline.

Classes (:func:`classify`):
    ``no_fork_seen``: the axis reported no split at all in the steps before the wrong entry while the command was
    given; ``target_in_wrong_child``: over the last ``window`` steps with a split seen, the target lay nearer the
    wrong child on most steps (the axis chose the wrong opening); ``late_turn``: the target lay nearer the right
    child on most of them, the tip did not follow (it entered the wrong one anyway).

Units: mm in the output (the log's), world frame.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .airways import Airways


def fork_of(airways: Airways, target: int, log: list[dict]) -> tuple[int, int, int] | None:
    """(parent, right child, wrong child) of the fork where the episode left the route; None if it never did."""
    route = airways.route(target)
    off = [s["branch"] for s in log if s["branch"] not in route]
    if not off:
        return None
    b = airways.graph.branch(off[-1])
    chain = [b]
    while chain[-1].parent not in route and chain[-1].parent >= 0:
        chain.append(airways.graph.branch(chain[-1].parent))
    wrong = chain[-1]
    parent = wrong.parent
    if parent < 0 or parent not in route or route.index(parent) + 1 >= len(route):
        return None
    return parent, route[route.index(parent) + 1], wrong.id


def trace(airways: Airways, target: int, log: list[dict], window: int = 30) -> dict | None:
    """The fork and per-step sides over the last ``window`` steps before the tip first entered the wrong child
    (see the module docstring); None when the episode never left the route."""
    fk = fork_of(airways, target, log)
    if fk is None:
        return None
    parent, right, wrong = fk
    sub = {wrong} | {b.id for b in airways.graph.branches if _under(airways, b.id, wrong)}
    first = next((i for i, s in enumerate(log) if s["branch"] in sub), len(log))
    trees = {k: cKDTree(airways.graph.branch(k).points) for k in (right, wrong)}
    route_tree = cKDTree(airways.route_polyline(target)[0])
    rows = []
    for s in log[max(0, first - window):first + 5]:
        tip, tgt = np.array(s["tip_mm"]) * 1e-3, np.array(s["target_mm"]) * 1e-3
        side = lambda p: (trees[wrong].query(p)[0] - trees[right].query(p)[0]) * 1e3  # noqa: E731
        rows.append({"t": s["t"], "branch": s["branch"], "command": s["command"],
                     "split_mm": s.get("axis_split_mm"), "tip_side_mm": round(side(tip), 2),
                     "target_side_mm": round(side(tgt), 2), "tip_off_mm": round(route_tree.query(tip)[0] * 1e3, 2),
                     "force_n": s.get("force_n"), "openings": s.get("axis_openings")})
    return {"parent": parent, "right": right, "wrong": wrong,
            "generation": airways.graph.branch(wrong).generation, "entry_t": log[min(first, len(log) - 1)]["t"],
            "steps": rows, "class": classify(rows[:max(0, len(rows) - 5)] if len(rows) > 5 else rows)}


def classify(rows: list[dict]) -> str:
    """``no_fork_seen`` | ``target_in_wrong_child`` | ``late_turn`` over the steps before the wrong entry."""
    seen = [r for r in rows if r["split_mm"] is not None and r["command"]]
    if not seen:
        return "no_fork_seen"
    wrong_side = sum(r["target_side_mm"] < 0 for r in seen[-10:])
    return "target_in_wrong_child" if wrong_side > len(seen[-10:]) / 2 else "late_turn"


def _under(airways: Airways, b: int, top: int) -> bool:
    """Whether branch ``b`` descends from ``top``."""
    while b >= 0:
        if b == top:
            return True
        b = airways.graph.branch(b).parent
    return False
