"""The trachea's root on the medial skeleton: where the route enters the airway tree.

Helpers of :func:`room_pipeline.anatomy.medial_axis.extract_medial_axis` (step 3 of its method), kept
apart because they are one job -- reading the top of the skeleton -- with their own measured thresholds:

- a scan cut just above the carina (the skeleton divides at the cut into two downward arms): the arms
  (:func:`_root_arms`), their headings (:func:`_arm_headings`), where they part (:func:`_arms_split`) and
  the middle of the cut cross-section (:func:`_cut_entry`);
- a flattened trachea (its medial set a sheet): the top cross-section's centre (:func:`_top_centre`), the
  lumen's cross-section aspect ratio (:func:`_cross_section_aspect`, threshold :data:`FLAT_ASPECT`), whether
  the lumen divides into the main bronchi within a few radii below (a carinal flare, not a flattened trachea:
  :func:`_divides_below`, :data:`FLARE_DEPTH_RADII`), the
  sheet test (:func:`_sheet_like`, :data:`SHEET_RATIO`), the sheet (:func:`_trachea_sheet`) and the one
  trunk across it (:func:`_sheet_trunk`);
- a twig at the first bifurcation whose lumen never leaves the tree's (:func:`_twig_inside_lumen`).

Units: metres (the SDF's world frame), radii as ``-sdf``; ``field`` is the medial axis's interpolated SDF.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from scipy import ndimage
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from ..errors import InputError
from .sdf_field import SdfField as _Field

def _root_arms(root: int, in_skel: np.ndarray, parent: np.ndarray, dist: np.ndarray, pts: np.ndarray,
               rad: np.ndarray, wide_radius: float) -> dict[int, tuple[float, float, float]]:
    """For each skeleton child of ``root`` (an arm: the subtree through it), metres: the longest path from the
    root through it; the longest such path whose points from the root on all have radius >= ``wide_radius``;
    the largest distance of its points from the longest arm (inf for that arm)."""
    nodes = np.flatnonzero(in_skel)
    nodes = nodes[np.argsort(dist[nodes], kind="stable")]        # parents before children
    arc = np.zeros(len(pts))
    arm = np.full(len(pts), -1, dtype=np.int64)
    wide = np.zeros(len(pts), dtype=bool)
    wide[root] = True
    out: dict[int, list[float]] = {}
    for n in nodes:
        p = int(parent[n])
        if p < 0:
            continue
        arc[n] = arc[p] + float(np.linalg.norm(pts[n] - pts[p]))
        arm[n] = n if p == root else arm[p]
        wide[n] = wide[p] and rad[n] >= wide_radius
        o = out.setdefault(int(arm[n]), [0.0, 0.0])
        o[0] = max(o[0], float(arc[n]))
        if wide[n]:
            o[1] = max(o[1], float(arc[n]))
    if not out:
        return {}
    longest = max(out, key=lambda k: out[k][0])
    kd = cKDTree(pts[arm == longest])
    res = {}
    for k, (length, wide_len) in out.items():
        far = np.inf if k == longest else float(kd.query(pts[arm == k])[0].max())
        res[k] = (length, wide_len, far)
    return res


def _top_centre(root: int, trachea: np.ndarray, pts: np.ndarray, r_max: float
                ) -> tuple[int, np.ndarray, np.ndarray, float]:
    """The middle of the trachea's top cross-section, the trachea's axis there, and how its medial points
    spread below the top.

    The top slab is the trachea points within ``r_max`` below ``root``'s height.  Their horizontal position is
    fitted as a straight line in height (a leaning trachea's axis); the middle is the slab point nearest that
    line at ``root``'s height and the axis is the line's downward direction.  Below the top slab (``r_max`` to
    ``2.5 r_max`` down: a closed end's medial cone lies within ``r_max`` of it), the trachea points and their
    largest distance from the line are returned: about a voxel on a round trachea, whose medial set is its
    axis; about the half-width less the edge radius on a flattened one, whose medial set is a sheet."""
    top = pts[root, 2]
    band = trachea[pts[trachea, 2] >= top - r_max]
    q = pts[band]
    A = np.stack([np.ones(len(q)), q[:, 2] - top], axis=1)
    coef = np.linalg.lstsq(A, q[:, :2], rcond=None)[0] if len(q) >= 2 else np.array([q[0, :2], [0.0, 0.0]])
    c = np.array([coef[0, 0], coef[0, 1], top])
    down = -np.array([coef[1, 0], coef[1, 1], 1.0])
    z = pts[trachea, 2]
    below = trachea[(z < top - r_max) & (z >= top - 2.5 * r_max)]
    qb = pts[below]
    line = np.stack([np.ones(len(qb)), qb[:, 2] - top], axis=1) @ coef
    spread = float(np.linalg.norm(qb[:, :2] - line, axis=1).max()) if len(qb) else 0.0
    return int(band[np.argmin(np.linalg.norm(q - c, axis=1))]), down / np.linalg.norm(down), below, spread


#: a root candidate with two wide arms is a bifurcation at a cut entry when both arms descend at least this
#: much below the horizontal (over their first 3 root radii): 56 deg at the synthetic carina, 31 deg with the
#: trachea leaning 25 deg, 7 deg for the top of an arch (tests/test_medial_axis.py)
ENTRY_ARM_DESCENT_DEG = 20.0
SPLIT_FACTOR = 1.0


def _arm_headings(root: int, arms: list[int], in_skel: np.ndarray, parent: np.ndarray, dist: np.ndarray,
                  pts: np.ndarray, reach: float) -> list[np.ndarray]:
    """Unit direction from ``root`` to the farthest point (straight-line distance <= ``reach``) of each arm
    (the skeleton subtree through each child ``arms[k]`` of the root)."""
    nodes = np.flatnonzero(in_skel)
    nodes = nodes[np.argsort(dist[nodes], kind="stable")]
    arm = np.full(len(pts), -1, dtype=np.int64)
    for a in arms:
        arm[a] = a
    for n in nodes:
        p = int(parent[n])
        if p >= 0 and arm[n] < 0 and arm[p] >= 0:
            arm[n] = arm[p]
    out = []
    for a in arms:
        q = pts[arm == a] - pts[root]
        d = np.linalg.norm(q, axis=1)
        ok = d <= reach
        v = q[ok][np.argmax(d[ok])] if ok.any() else q[np.argmin(d)]
        out.append(v / max(float(np.linalg.norm(v)), 1e-12))
    return out


def _arms_split(root: int, arms: list[int], in_skel: np.ndarray, parent: np.ndarray, dist: np.ndarray,
                pts: np.ndarray, field: _Field) -> tuple[int, int, np.ndarray]:
    """Where two arms of ``root`` part: along each arm's longest path from the root, at equal arc lengths,
    the two points still share one lumen ball while the lumen depth at their midpoint is at least half their
    distance; the first arc length where that fails is the split.  Returns each path's first node at or past
    it and the bifurcation: of the midpoints from the root down to the split (the common trunk's centre line),
    the lowest one whose lumen radius is within a voxel (the mask's resolution) of the largest: the centre of
    the largest ball inscribed in the junction, which touches the trachea and both bronchi, where a full
    tree's skeleton joins its two main bronchi (its shortest paths favour wide points); the split itself lies
    lower, down the carinal ridge, by up to a bronchus radius (AirQuant cut 10 mm above: 12.5 mm).  A trunk
    of one width (radii within a voxel) ends at its most distal such point.  Else the midpoint at the split,
    when a straight way from that centre to either split node leaves the lumen."""
    paths = []
    for a in arms:
        sub = np.zeros(len(pts), dtype=bool)
        sub[a] = True
        nodes = np.flatnonzero(in_skel)
        for n in nodes[np.argsort(dist[nodes], kind="stable")]:
            if parent[n] >= 0 and sub[parent[n]]:
                sub[n] = True
        far = int(np.flatnonzero(sub)[np.argmax(dist[sub])])
        chain = [far]
        while chain[-1] != a:
            chain.append(int(parent[chain[-1]]))
        chain = [root] + chain[::-1]
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts[chain], axis=0), axis=1))])
        paths.append((np.array(chain), arc))
    (ca, sa), (cb, sb) = paths
    voxel = float(np.exp(np.mean(np.log(np.linalg.norm(field.A, axis=0)))))
    step = 0.25 * voxel
    s = np.arange(0.0, min(sa[-1], sb[-1]), step)
    pa = np.stack([np.interp(s, sa, pts[ca, k]) for k in range(3)], axis=1)
    pb = np.stack([np.interp(s, sb, pts[cb, k]) for k in range(3)], axis=1)
    mid = 0.5 * (pa + pb)
    depth = -field.sample(field.to_index(mid))[:, 0]
    bad = np.flatnonzero(depth < SPLIT_FACTOR * np.linalg.norm(pa - pb, axis=1))
    k = int(bad[0]) if len(bad) else len(s) - 1
    k = max(k - 1, 0)
    a_k = int(ca[min(np.searchsorted(sa, s[k]) + 0, len(ca) - 1)])
    b_k = int(cb[min(np.searchsorted(sb, s[k]) + 0, len(cb) - 1)])
    a_k = a_k if a_k != root else int(ca[1])
    b_k = b_k if b_k != root else int(cb[1])
    r_mid = field.radius(field.to_index(mid[:k + 1]))
    centre = mid[int(np.flatnonzero(r_mid >= r_mid.max() - voxel)[-1])]
    t = np.linspace(0.0, 1.0, 9)[:, None]
    for n in (a_k, b_k):
        if not np.all(field.sample(field.to_index(centre + t * (pts[n] - centre)))[:, 0] < 0):
            return a_k, b_k, mid[k]
    return a_k, b_k, centre


def _cut_entry(root: int, pts: np.ndarray, rad: np.ndarray, field: _Field, voxel: float) -> np.ndarray | None:
    """The middle of the lumen's top cross-section above a root candidate when that top is a cut (the scan
    stops there: the lumen runs into the volume's border), else None.

    The lumen voxels within 3 candidate radii of it sideways and above it are taken; their top slab (one
    voxel thick) is the cross-section.  It is a cut when at least half its voxels lie on the volume's border
    and its area is at least half the candidate's disc (a closed end's top is a small cap; a segmentation
    that stops with a flat top inside the volume is not read as a cut).  Raises :class:`InputError` when the cut holds no trachea: the
    cross-section is split into separate airways or its middle lies outside the lumen (cut at or below the
    carina), or the straight way from it down to the candidate leaves the lumen.
    """
    c, r = pts[root], float(rad[root])
    R = 3.0 * r
    shape = field.shape
    corners = np.array([[c[0] + sx * R, c[1] + sy * R, z] for sx in (-1, 1) for sy in (-1, 1)
                        for z in (c[2] - voxel, c[2] + 1e3)])   # up to the grid's top
    ij = field.to_index(corners)
    lo = np.clip(np.floor(ij.min(axis=0)).astype(int), 0, shape - 1)
    hi = np.clip(np.ceil(ij.max(axis=0)).astype(int) + 1, 1, shape)
    sdf = field.vals[:, 0].reshape(tuple(shape))
    blk = sdf[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    idx = np.argwhere(blk < 0)
    if len(idx) == 0:
        return None
    w = field.to_world((idx + lo).astype(np.float64))
    sel = (np.hypot(w[:, 0] - c[0], w[:, 1] - c[1]) <= R) & (w[:, 2] >= c[2] - 0.5 * voxel)
    if not sel.any():
        return None
    w, idx = w[sel], idx[sel]
    top = w[:, 2] >= w[:, 2].max() - 0.5 * voxel
    cell = float(abs(np.linalg.det(field.A))) / voxel      # voxel volume / thickness: one voxel's area
    area = float(top.sum()) * cell
    gi = idx[top] + lo
    on_border = np.mean(np.any((gi == 0) | (gi == shape - 1), axis=1))
    if area < 0.5 * np.pi * r * r or on_border < 0.5:
        return None                                      # a closed end (or no border there): no cut
    q = w[top]
    where = ", ".join(f"{v / 1e-3:.1f}" for v in q.mean(axis=0))
    # pieces of the cross-section (voxels joined within 1.5 voxels)
    ncomp, lab = csgraph.connected_components(cKDTree(q).sparse_distance_matrix(cKDTree(q), 1.5 * voxel),
                                              directed=False)
    sizes = np.bincount(lab)
    if ncomp > 1 and np.sort(sizes)[-2] >= 0.2 * sizes.max():
        raise InputError(f"medial axis: no trachea-like root: the scan's top cross-section at ({where}) mm holds "
                         f"{int(np.sum(sizes >= 0.2 * sizes.max()))} separate airways (cut at or below the carina)")
    e = q[lab == int(np.argmax(sizes))].mean(axis=0)
    if not field.sample(field.to_index(e[None]))[0, 0] < 0:
        raise InputError(f"medial axis: no trachea-like root: the middle of the scan's top cross-section "
                         f"({where}) mm lies outside the lumen (cut at or below the carina)")
    return e


def _section(field: _Field, centre: np.ndarray, a: np.ndarray, r_max: float, h: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The lumen's cross-section through ``centre`` normal to the unit vector ``a``: the plane's in-plane
    coordinates S, T (metres, a grid of step ``h`` over a 6 ``r_max`` square) and whether each lies in the
    lumen (sdf < 0)."""
    u = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(a, u)
    g = np.arange(-3.0 * r_max, 3.0 * r_max + 0.5 * h, h)
    S, T = np.meshgrid(g, g, indexing="ij")
    P = centre + S.reshape(-1, 1) * u + T.reshape(-1, 1) * v
    return S, T, (field.sample(field.to_index(P))[:, 0] < 0).reshape(S.shape)


#: a flattened top cross-section is a carinal flare, not a flattened trachea, when the lumen divides into two
#: airways (main bronchi) within this many trachea radii (``r_max``) below the top (``_divides_below``).
#: Measured (reports' ``trachea_divides_below_mm`` / ``_radii``, printed by ``pytest -s -m slow
#: tests/test_medial_axis.py -k "real_mask_cut and patient1"`` and ``pytest -s tests/test_medial_axis.py -k
#: "flare or flattened_tracheas_cut_end"``): Med-MPD 1 cut 10 / 5 / 2 mm above its carina divides 30.9 / 24.8 /
#: 21.7 mm = 4.5 / 4.0 / 3.5 radii below the top (the flattened-trachea rule fired on all three); the synthetic
#: flattened tracheas (24 x 10 and 20 x 12 mm, upright and leaning 20 deg, 45 mm above the carina) 53.8-56.5 mm
#: = 9.0-11.25 radii; a synthetic flare cut 15 / 9 mm above the carina 3.25 / 2.25.  The threshold is the
#: geometric mean of 4.5 and 9.0 (1.4 x from either).  A flattened trachea cut less than about 6 radii above its
#: ridge is read as a round one (the cut-entry rules).
FLARE_DEPTH_RADII = 6.4


def _divides_below(field: _Field, top: np.ndarray, axis: np.ndarray, r_max: float, voxel: float,
                   max_radii: float = 2.0 * FLARE_DEPTH_RADII) -> float | None:
    """How far (metres) below ``top`` along ``axis`` (the trachea's downward axis) the lumen first divides
    into two airways, searched down to ``max_radii`` ``r_max`` (twice the flare bound, so that the report
    shows the margin) in steps of ``r_max`` / 4; None when it does not.  Each cross-section normal to ``axis``
    (``_section``, half-voxel grid) is labelled; it divides when its two largest lumen regions each have at
    least a quarter of the trachea's disc (pi ``r_max``^2 / 4: a bronchus at least half the trachea's radius;
    voxel debris and sections of small side branches are smaller).  A carinal flare (the cross-section
    widening along the line of the main bronchi just above the carina) divides within a few radii; a
    flattened trachea runs on over many."""
    a = axis / np.linalg.norm(axis)
    h = 0.5 * voxel
    for depth in np.arange(0.5, max_radii + 1e-9, 0.25):
        _, _, inside = _section(field, top + depth * r_max * a, a, r_max, h)
        lab, n = ndimage.label(inside)
        if n < 2:
            continue
        area = np.sort(np.bincount(lab.ravel())[1:])[::-1] * h * h
        if area[1] >= 0.25 * np.pi * r_max * r_max:
            return float(depth * r_max)
    return None


def _cross_section_aspect(field: _Field, top: np.ndarray, axis: np.ndarray, r_max: float, voxel: float
                          ) -> float:
    """The trachea lumen's cross-section aspect ratio (long / short axis, 1 for a circle): the median over
    three cross-sections normal to ``axis`` at 0.5, 1.0 and 1.5 ``r_max`` below ``top`` (the trachea's
    most superior wide medial point: below the cut or the closed end, above a carina just below the cut).  Each is the SDF sampled on a half-voxel grid of the plane
    (6 ``r_max`` square), the connected lumen region at the axis (else the largest), and the square root of
    its second moments' eigenvalue ratio (for an ellipse exactly its axis ratio).  A section whose region
    fills less than 0.9 of its convex hull (two lobes: a trachea cut just above the carina, sectioned in its
    bifurcation) is skipped; with none left the ratio is 1 (no switch)."""
    a = axis / np.linalg.norm(axis)
    h = 0.5 * voxel
    out = []
    for depth in (0.5, 1.0, 1.5):
        S, T, inside = _section(field, top + depth * r_max * a, a, r_max, h)
        g = S[:, 0]
        lab, n = ndimage.label(inside)
        if n == 0:
            continue
        k = lab[len(g) // 2, len(g) // 2]
        if k == 0:
            k = int(np.argmax(np.bincount(lab.ravel())[1:])) + 1
        sel = lab == k
        if sel.sum() < 8:
            continue
        q = np.stack([S[sel], T[sel]], axis=1)
        from scipy.spatial import ConvexHull
        if sel.sum() * h * h < 0.9 * ConvexHull(q).volume:
            continue                  # not convex (two lobes: the section reaches the carina's bifurcation)
        ev = np.linalg.eigvalsh(np.cov(q.T))
        out.append(float(np.sqrt(ev[1] / max(ev[0], 1e-30))))
    return float(np.median(out)) if out else 1.0


#: cross-section aspect ratio (long / short axis) above which a trachea is flattened (its medial set a sheet),
#: measured by ``python benchmarks/anatomy_trachea_aspect.py`` (benchmarks/results/anatomy_trachea_aspect.md):
#: the seven shared real tracheas 1.10-1.39 (CASE091's, narrowing up to the cut, 1.388), synthetic round and
#: 16x14 mm ones <= 1.146; synthetic 20x12 mm >= 1.565 (leaning 20 deg), 24x10 mm >= 2.27.  The threshold is
#: their geometric mean: 6 % from either side.  The sheet-fraction condition (> 0.5) is the second guard
#: (CASE091 0.30, flat ones >= 0.95).  The old measure (medial spread / radius > 0.75) did not separate them
#: (AirQuant 1.00, 20x12 mm 0.96).
FLAT_ASPECT = 1.47


#: second / first eigenvalue of the local medial points' covariance above which they form a sheet
SHEET_RATIO = 0.25


def _sheet_like(i: np.ndarray, kd: cKDTree, pts: np.ndarray, rad: np.ndarray, voxel: float) -> np.ndarray:
    """Whether the medial set is locally two-dimensional at points ``i``: the cluster points within the point's
    own radius (at least 2 voxels; at least 6 of them) spread in a second direction, the second eigenvalue of
    their covariance > 0.25 x the first (a disc gives 1, the half-disc at a sheet's edge 0.28, the scattered
    points along a tube's axis ~0.02)."""
    out = np.zeros(len(i), dtype=bool)
    for k, (n, nb) in enumerate(zip(i, kd.query_ball_point(pts[i], np.maximum(rad[i], 2.0 * voxel)))):
        if len(nb) < 6:
            continue
        q = pts[nb] - pts[nb].mean(axis=0)
        ev = np.linalg.eigvalsh(q.T @ q / len(nb))
        out[k] = ev[1] > SHEET_RATIO * ev[2]
    return out


def _trachea_sheet(root: int, G, pts: np.ndarray, rad: np.ndarray, voxel: float,
                   params: Any) -> np.ndarray:   # params: medial_axis.MedialAxisParams
    """The medial sheet of a flattened trachea: the points where the medial set is locally two-dimensional
    (:func:`_sheet_like`), connected to ``root`` through such points, and the points within TEASAR's
    invalidation distance of them."""
    kd = cKDTree(pts)
    sheet = np.zeros(len(pts), dtype=bool)
    seen = np.zeros(len(pts), dtype=bool)
    front = np.array([root])
    seen[root] = True
    G = G.tocsr()
    while len(front):
        ok = front[_sheet_like(front, kd, pts, rad, voxel)]
        sheet[ok] = True
        nxt = np.unique(np.concatenate([G.indices[G.indptr[i]:G.indptr[i + 1]] for i in ok])) if len(ok) else []
        nxt = np.asarray(nxt, dtype=np.int64)
        front = nxt[~seen[nxt]]
        seen[front] = True
    out = sheet.copy()
    idx = np.flatnonzero(sheet)
    for lst in kd.query_ball_point(pts[idx], params.invalidation_scale * rad[idx]
                                   + params.invalidation_voxels * voxel):
        out[lst] = True
    return np.flatnonzero(out)


def _sheet_trunk(root: int, on_sheet: np.ndarray, pts: np.ndarray, rad: np.ndarray, axis: np.ndarray,
                 voxel: float) -> np.ndarray:
    """The trunk across a flattened trachea's medial sheet: from ``root`` down, steps of half the root's radius
    (>= a voxel), each to the sheet point nearest the centroid of the sheet points in the next cross-section
    (a slab one step thick across the current direction, within the top's half-width of the path); the
    direction follows the centroids.  Ends where a cross-section holds fewer than 3 sheet points or the path
    would turn by more than 45 degrees in one step (the carina)."""
    h = max(0.5 * float(rad[root]), voxel)
    idx = np.flatnonzero(on_sheet)
    if len(idx) == 0:
        return np.array([root], dtype=np.int64)
    q = pts[idx]
    c = pts[root].copy()
    d = axis.copy()
    top = q[np.abs((q - c) @ d) <= 2.0 * h]
    half = float(np.linalg.norm((top - c) - np.outer((top - c) @ d, d), axis=1).max()) + voxel if len(top) else 0.0
    trunk = [root]
    for _ in range(int(np.ceil(10.0 * np.ptp(q, axis=0).max() / h)) + 1):
        g = c + h * d
        off = q - g
        ax = off @ d
        lat = np.linalg.norm(off - np.outer(ax, d), axis=1)
        sel = (np.abs(ax) <= 0.5 * h) & (lat <= half)
        if sel.sum() < 3:
            break
        m = q[sel].mean(axis=0)
        step = m - c
        if not np.linalg.norm(step) > 0.25 * h or step @ d < 0.7 * np.linalg.norm(step):
            break                                   # stalled, or turning (> 45 deg): the carina
        d = step / np.linalg.norm(step)
        c = m
        n = int(idx[np.argmin(np.linalg.norm(q - m, axis=1))])
        if n not in trunk:
            trunk.append(n)
    return np.array(trunk, dtype=np.int64)


#: a twig's straight ways to the rest of the tree count as inside the lumen when they leave it by less than this
#: many voxels: a binary mask places its wall only to the voxel (a staircase of voxel faces, half a voxel either
#: side of the wall it samples).  CASE073 as stored: its trachea's twig's ways leave by 0.30 voxel (0.20 mm)
TWIG_EXIT_VOXELS = 0.5


def _twig_measure(twig: np.ndarray, twig_rad: np.ndarray, r_junction: float, others: np.ndarray, field: _Field,
                  voxel: float, width_only: bool = False) -> tuple[float, float]:
    """A branch (or subtree) hanging off the trachea, measured on its skeleton points (metres, (N, 3), radii
    ``twig_rad``, without the junction) that lie at least one voxel inside the wall (radius >= ``voxel``): the
    points nearer the wall are not resolved by the mask (a twig's last points run into the staircase of voxel
    faces, 0.2-0.3 mm inside it at 0.66-0.8 mm voxels on CASE073 / CASE091, and their straight ways cut its
    steps).  Returns their median radius over the junction's ``r_junction`` (its width) and, in voxels, the
    largest sdf on the straight segments from each of them to the nearest of ``others`` (metres, (M, 3); sampled
    every ``voxel`` / 4): how far the ways out of its lumen into the rest of the tree's leave the lumen (< 0:
    never; not measured, inf, with ``width_only``).  (nan, inf) when no point is that deep."""
    deep = twig_rad >= voxel
    if not deep.any() or len(others) == 0:
        return float("nan"), float("inf")
    width = float(np.median(twig_rad[deep])) / r_junction
    if width_only:
        return width, float("inf")
    q = twig[deep]
    _, j = cKDTree(others).query(q)
    d = float(np.linalg.norm(others[j] - q, axis=1).max())
    t = np.linspace(0.0, 1.0, max(2, int(np.ceil(d / (0.25 * voxel)))) + 1)[:, None, None]
    seg = (q[None] + t * (others[j] - q)[None]).reshape(-1, 3)
    return width, float(field.sample(field.to_index(seg))[:, 0].max()) / voxel


def _twig_inside_lumen(twig: np.ndarray, twig_rad: np.ndarray, r_junction: float, others: np.ndarray,
                       field: _Field, voxel: float) -> bool:
    """True when a branch hanging off the trachea is part of the trachea's medial set, to the mask's resolution
    (:func:`_twig_measure`): as wide as the trachea's medial line (median radius >= half the junction's; a real
    side branch, e.g. a tracheal bronchus, is narrower) and its lumen never leaves the lumen around the other
    branches: from each of its points the straight way to the nearest point of another branch's skeleton stays
    within ``TWIG_EXIT_VOXELS`` of the lumen.  A real branch is parted from its siblings by a wall (a carinal
    ridge) that such a way crosses."""
    if not _twig_measure(twig, twig_rad, r_junction, others, field, voxel, width_only=True)[0] >= 0.5:
        return False
    return bool(_twig_measure(twig, twig_rad, r_junction, others, field, voxel)[1] < TWIG_EXIT_VOXELS)


#: a twig of the root that ends without dividing, beside the one child that divides on (the trachea's
#: continuation), is a line of the trachea's own medial set when the lumen's cross-section at its end is wider than
#: the trachea: the connected lumen region around its last resolved points, in the plane normal to the twig,
#: reaches farther than the junction's radius from them (``_twig_end_width`` > 1).  A side branch of the trachea
#: (a tracheal bronchus) is a tube narrower than the trachea once it has left the trachea's wall, so the
#: cross-section at its end is its own disc.  Measured (session 17; the region is looked for within 1.5 junction
#: radii, so 2.12 is the most it reads): synthetic tracheal bronchi 15 x 3, 25 x 3, 25 x 4.5 mm 0.41 / 0.38 /
#: 0.58 (their own radius, 0.33-0.57 of the junction's); the twigs at which the roots ended 48-101 mm above the
#: carina: CASE091 as stored 2.12 (width 0.40 of the junction, its ways never leave the lumen), CASE091 at 0.5 mm
#: 2.12 then 1.63, CASE073 at 0.5 mm 1.93 (its ways leave the lumen by 0.68 voxel) then 2.13 / 1.93 / 1.84 /
#: 2.12, Med-MPD 2 at 0.5 mm 2.11 (width 0.09); a synthetic crease (a 3.5 mm channel fused along an 8 mm
#: trachea, width 0.45) 1.54 / 1.76.  Width and the ways' exit did not separate those twigs from the 15 x 3 mm
#: bronchus (0.33, -1.40 voxel).  The bound is the trachea's own radius: no branch of it is wider.
TWIG_END_OPEN = 1.0
TWIG_END_POINTS = 3


def _twig_end_width(twig: np.ndarray, twig_rad: np.ndarray, junction: np.ndarray, r_junction: float,
                    field: _Field, voxel: float) -> float:
    """How wide the lumen is around the end of a twig of the root (its skeleton points ``twig``, metres, (N, 3),
    in order from the junction ``junction`` out, radii ``twig_rad``): for each of its last ``TWIG_END_POINTS``
    points that lie at least a voxel inside the wall (radius >= ``voxel``: resolved by the mask) and outside the
    junction's ball (farther than ``r_junction`` from it), the lumen's cross-section normal to the twig there
    (``_section``, half-voxel grid over +-1.5 ``r_junction``) is labelled and the greatest distance from the point
    of the region it lies in is taken, over ``r_junction``; the median.  About the twig's own radius over the
    junction's for a tube of its own (a side branch), > 1 for a line of the trachea's own medial set (its
    cross-section is the trachea's lumen).  nan when no point qualifies."""
    far = np.flatnonzero((twig_rad >= voxel) & (np.linalg.norm(twig - junction, axis=1) > r_junction))
    out = []
    h = 0.5 * voxel
    for i in far[-TWIG_END_POINTS:]:
        a = twig[min(i + 2, len(twig) - 1)] - twig[max(i - 2, 0)]
        n = float(np.linalg.norm(a))
        if n == 0.0:
            continue
        S, T, inside = _section(field, twig[i], a / n, 0.5 * r_junction, h)
        lab, _ = ndimage.label(inside)
        d2 = S * S + T * T
        k = lab.flat[int(np.argmin(d2))]          # the region at the point (at least a voxel inside the wall)
        if k == 0:
            continue
        out.append(float(np.sqrt(d2[lab == k].max())) / r_junction)
    return float(np.median(out)) if out else float("nan")
