"""A measured bronchial tree read from a table, placed in the phantom's frame, with lungs that hold it.

A *reference-tree patient* is a phantom whose tree is not grown but read from a file: a centreline table
of straight branches, one row per branch, as published with morphometric airway models (e.g. Schmidt A,
Zidowitz S, Kriete A, et al., "A digital reference model of the human bronchial tree", Comput Med Imaging
Graph 28:203-211, 2004, as tabulated in Nick2858/Branch-Builder ``Demo/TreeData.csv``).  The phantom's CT
model (:func:`~room_pipeline.anatomy.phantom.rasterise`) turns it into a CT with exact ground truth, so
every stage is measured on human airway geometry and not only on the grown trees.

Table (CSV with a header row; other columns are ignored): ``radius`` (lumen radius, mm), ``x1, y1, z1``
(branch start, mm), ``x2, y2, z2`` (branch end, mm).  A branch's parent is the branch whose end point is
its start point (within :data:`JOIN_TOL_MM`); exactly one branch, the trachea, has none.  Generations and
ids are recomputed (trachea 0, +1 per bifurcation; ids in depth-first order), so a table numbered in
another way reads the same.

``frame`` names the table's axes: ``RAS`` (+x toward the patient's right, +y anterior, +z superior: the
project's world frame, :mod:`room_pipeline.conventions`) or ``LPS`` (DICOM's: +x left, +y posterior; x and
y are negated on reading).  The Schmidt table is LPS: its three-lobed (right) main-bronchus subtree lies
toward -x of the carina and its trachea runs toward +y (posterior) on the way down.  The tree is then
translated so that the carina (the trachea's end) is the world origin, as the grown phantom's is.

All lengths in the returned :class:`~room_pipeline.anatomy.tree.AirwayTree` are metres.
"""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..conventions import MM
from ..errors import InputError
from .phantom_params import PhantomParams
from .tree import AirwayTree, Branch

#: a branch's start point joins its parent's end point when they are this close, mm
JOIN_TOL_MM = 1e-3
#: the lungs' distance is computed on every LUNG_STRIDE-th voxel and interpolated (hull_lungs)
LUNG_STRIDE = 2
#: tables of this many branches at most (a whole human tree to the terminal bronchioles has ~60,000)
MAX_BRANCHES = 100_000
FRAMES = ("RAS", "LPS")
_COLUMNS = ("radius", "x1", "y1", "z1", "x2", "y2", "z2")


def read_tree_table(path: str | Path, frame: str = "RAS") -> AirwayTree:
    """The tree of a branch table (see the module docstring), metres, world RAS+, carina at the origin.

    Raises :class:`InputError` (one line naming the file) for a missing or unreadable file, a missing
    column, a value that is not a finite number, a radius <= 0, a branch of zero length, more or fewer than
    one root, a branch whose start joins several ends, or a loop.
    """
    path = Path(path)
    if frame not in FRAMES:
        raise InputError(f"{path}: tree frame must be one of {', '.join(FRAMES)}, got {frame!r}")
    if not path.is_file():
        raise InputError(f"tree table not found: {path}")
    try:
        with path.open(newline="") as fh:
            reader = csv.DictReader(fh)
            header = [h.strip() for h in (reader.fieldnames or [])]
            missing = [c for c in _COLUMNS if c not in header]
            if missing:
                raise InputError(f"{path}: tree table lacks column(s) {', '.join(missing)} "
                                 f"(needs {', '.join(_COLUMNS)}; has {', '.join(header) or 'no header'})")
            rows = []
            for line, row in enumerate(reader, start=2):
                row = {(k or "").strip(): v for k, v in row.items()}
                try:
                    rows.append([float(row[c]) for c in _COLUMNS])
                except (TypeError, ValueError):
                    raise InputError(f"{path}:{line}: not a number in {', '.join(_COLUMNS)}") from None
                if len(rows) > MAX_BRANCHES:
                    raise InputError(f"{path}: more than {MAX_BRANCHES} branches")
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise InputError(f"{path}: cannot read the tree table ({type(exc).__name__}: {exc})") from None
    if not rows:
        raise InputError(f"{path}: tree table has no branches")
    a = np.asarray(rows, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        bad = int(np.nonzero(~np.all(np.isfinite(a), axis=1))[0][0]) + 2
        raise InputError(f"{path}:{bad}: non-finite value")
    radius, p1, p2 = a[:, 0], a[:, 1:4], a[:, 4:7]
    if np.any(radius <= 0):
        raise InputError(f"{path}:{int(np.argmax(radius <= 0)) + 2}: radius must be > 0 mm, got "
                         f"{radius[radius <= 0][0]!r}")
    length = np.linalg.norm(p2 - p1, axis=1)
    if np.any(length <= JOIN_TOL_MM):
        raise InputError(f"{path}:{int(np.argmax(length <= JOIN_TOL_MM)) + 2}: branch of zero length")
    if frame == "LPS":
        p1 = p1 * [-1.0, -1.0, 1.0]
        p2 = p2 * [-1.0, -1.0, 1.0]

    # parent = the branch whose end point is this one's start
    ends = cKDTree(p2)
    hits = ends.query_ball_point(p1, r=JOIN_TOL_MM)
    parent = np.full(len(a), -1, dtype=np.int64)
    for i, h in enumerate(hits):
        h = [j for j in h if j != i]
        if len(h) > 1:
            raise InputError(f"{path}:{i + 2}: branch starts where {len(h)} branches end (rows "
                             f"{', '.join(str(j + 2) for j in h[:4])}): not a tree")
        if h:
            parent[i] = h[0]
    roots = np.nonzero(parent < 0)[0]
    if len(roots) != 1:
        raise InputError(f"{path}: a tree table needs exactly one root branch (a start that is no branch's end), "
                         f"found {len(roots)}" + (f" (rows {', '.join(str(r + 2) for r in roots[:5])})"
                                                   if len(roots) else ""))
    children: dict[int, list[int]] = {}
    for i, p in enumerate(parent):
        if p >= 0:
            children.setdefault(int(p), []).append(i)
    order, gen, new_parent = [], {}, {}
    stack = [(int(roots[0]), -1, 0)]
    seen = np.zeros(len(a), dtype=bool)
    while stack:
        i, par, g = stack.pop()
        if seen[i]:
            raise InputError(f"{path}:{i + 2}: branches form a loop")
        seen[i] = True
        new_id = len(order)
        order.append(i)
        gen[i], new_parent[i] = g, par
        for c in sorted(children.get(i, []), reverse=True):
            stack.append((c, new_id, g + 1))
    if not seen.all():
        raise InputError(f"{path}: {int((~seen).sum())} branches are not connected to the root (a loop)")
    carina = p2[roots[0]]
    branches = [Branch(k, new_parent[i], gen[i], (p1[i] - carina) * MM, (p2[i] - carina) * MM, radius[i] * MM)
                for k, i in enumerate(order)]
    return AirwayTree(branches)


def tree_sample_points(tree: AirwayTree, min_generation: int = 2, step: float = 2e-3) -> np.ndarray:
    """Points every ``step`` metres along the axes of branches of generation >= ``min_generation`` (N, 3)."""
    pts = [b.start + t[:, None] * (b.end - b.start)
           for b in tree.branches if b.generation >= min_generation
           for t in [np.linspace(0.0, 1.0, max(2, int(np.ceil(b.length / step)) + 1))]]
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def hull_lungs(tree: AirwayTree, params: PhantomParams, reach_mm: float = 15.0, min_generation: int = 2):
    """The lungs of a measured tree: every point within ``reach_mm`` of a branch axis of generation >=
    ``min_generation``, outside the mediastinum (``|x| < mediastinum_half_width_mm``).

    The phantom's own lungs are half-ellipsoids sized for the grown tree; a measured tree does not fit in
    them (the Schmidt tree reaches 178 mm below its carina, the default lungs 120 mm) and ellipsoids cannot
    hold a hilum.  A lung is where the bronchial tree is: its lobar and deeper branches fill it to within
    a few centimetres (the Schmidt table ends at generation 17, radius 0.28 mm, so its axes lie everywhere
    in the lung).  Returns a function of the grid's axes ``(xs, ys, zs)`` (metres) for
    :func:`~room_pipeline.anatomy.phantom.rasterise`: the signed distance (float32, metres, < 0 inside),
    the Euclidean distance (``scipy.ndimage``'s EDT) to the axis points, on every :data:`LUNG_STRIDE`-th voxel
    and trilinear in between (the axis points snap to that coarser grid, an eighth of the full grid's
    memory): within 1.6 mm of the full-resolution transform near the lung's edge
    (``tests/test_reference_tree.py::test_hull_lungs_on_the_coarse_grid_stay_near_the_full_resolution_transform``,
    on a small tree at 0.7 mm).  The edge lies ``reach_mm`` from the nearest airway axis, so no airway voxel's
    tissue changes.
    """
    reach = reach_mm * MM
    half_width = params.mediastinum_half_width_mm * MM

    def lungs(xs: np.ndarray, ys: np.ndarray, zs: np.ndarray) -> np.ndarray:
        shape = (len(xs), len(ys), len(zs))
        # the distance on every LUNG_STRIDE-th voxel, then trilinear in between (a lung's edge lies
        # reach_mm from the airways: its exact place within a coarse voxel changes no airway voxel)
        cx, cy, cz = xs[::LUNG_STRIDE], ys[::LUNG_STRIDE], zs[::LUNG_STRIDE]
        cshape = (len(cx), len(cy), len(cz))
        origin = np.array([cx[0], cy[0], cz[0]])
        sp = np.array([(a[1] - a[0]) if len(a) > 1 else 1.0 for a in (xs, ys, zs)]) * LUNG_STRIDE
        pts = tree_sample_points(tree, min_generation=min_generation, step=0.25 * float(sp.min()))
        seed = np.ones(cshape, dtype=bool)
        if len(pts):
            ijk = np.rint((pts - origin) / sp).astype(np.int64)
            ijk = ijk[np.all((ijk >= 0) & (ijk < cshape), axis=1)]
            seed[tuple(ijk.T)] = False
        if seed.all():
            return np.full(shape, np.inf, dtype=np.float32)
        coarse = ndimage.distance_transform_edt(seed, sampling=sp).astype(np.float32)
        del seed
        d = ndimage.affine_transform(coarse, np.full(3, 1.0 / LUNG_STRIDE), output_shape=shape, order=1,
                                     mode="nearest", output=np.float32)
        del coarse
        d -= np.float32(reach)
        np.maximum(d, (half_width - np.abs(xs)).astype(np.float32)[:, None, None], out=d)
        return d

    return lungs
