"""The built-in procedural phantom patient: a grown bronchial tree rasterised into a CT.

CT model
    Layers mixed with partial-volume coverage ``clip(0.5 - s / h, 0, 1)`` from
    a signed distance ``s`` (``h`` = mean voxel size): outside air, a body
    (elliptic cylinder: subcutaneous fat rim, soft tissue inside, which is also
    the mediastinum around the trachea), the two lungs (parenchyma with
    spatially correlated Gaussian texture), the airway wall (outer surface =
    capsules of radius ``r + t(r)`` with ``t = wall_thickness_ratio * 2r +
    wall_thickness_offset_mm``; the ratio 0.15 is a modelling choice inside the
    commonly quoted normal range of CT wall-thickness / lumen-diameter of about
    0.1-0.2, not a fit to data) and the lumen (air).  The result is blurred by a
    Gaussian PSF (``psf_sigma_voxels``), white Gaussian noise is added and the
    values are rounded to int16 HU in [-1024, 3071].

Ground truth
    ``mask`` = voxel centre inside the lumen union (``sdf < 0``); ``sdf`` comes
    from :meth:`AirwayTree.sdf` (metres, negative in the lumen), evaluated on
    every lumen voxel and on every outside voxel closer than ``sdf_band_mm``
    to the lumen, spatially tiled so that each tile only sees its nearby
    branches (same values as the whole tree).  Farther outside it is clipped
    to ``+sdf_band_mm``.  ``sdf_exact`` is True where the stored value is the
    true signed distance: inside the band and not flagged by the tree's
    junction test; clipped far-field voxels are False.

All functions are pure (no file I/O).  Parameters are millimetres / degrees /
HU in :class:`PhantomParams` (the YAML's units) and metres everywhere else.

Modules: :mod:`.phantom_params` (the config, the wall-thickness rule), :mod:`.phantom_tree` (the lungs
and the tree growth: the tree model); this one rasterises the CT and its ground truth and re-exports
their public names.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np
from scipy import ndimage

from ..conventions import MM
from ..io.volume import Volume
from .phantom_params import PhantomParams, wall_thickness
from .phantom_tree import _half_ellipsoid_sd, _lung_shapes, grow_tree
from .tree import AirwayTree

# the phantom's API, importable from here as before the split
from .phantom_tree import kitaoka_angle, lung_signed_distance, segment_distances  # noqa: F401


@dataclasses.dataclass
class Phantom:
    """A phantom patient: the tree and its CT with exact ground truth on the same grid.

    ``ct`` int16 HU; ``mask`` uint8 (1 = voxel centre in the lumen);
    ``sdf`` float32 metres (negative in the lumen; exact within
    ``sdf_band_mm`` and everywhere inside, clipped to +band beyond);
    ``sdf_exact`` bool (stored sdf equals the true value).
    """

    tree: AirwayTree
    ct: Volume
    mask: Volume
    sdf: Volume
    sdf_exact: Volume


def _coverage(s: np.ndarray, h: float) -> np.ndarray:
    """Fraction of a voxel of width ``h`` inside a surface at signed distance ``s`` (linear ramp)."""
    out = 0.5 - s / np.float32(h)
    np.clip(out, 0.0, 1.0, out=out)
    return out


def _mix(base: np.ndarray, value, frac: np.ndarray) -> None:
    """In place: base <- base + frac * (value - base)."""
    base += frac * (value - base)


def _body_ellipse(params: PhantomParams) -> tuple[np.ndarray, np.ndarray]:
    """Centre (x, y) and semi-axes (metres) of the body's elliptic cross-section."""
    lo = np.full(2, np.inf)
    hi = np.full(2, -np.inf)
    for c, a, _ in _lung_shapes(params):
        lo = np.minimum(lo, c[:2] - a[:2])
        hi = np.maximum(hi, c[:2] + a[:2])
    centre = 0.5 * (lo + hi)
    # an ellipse through the lungs' bounding box corners would be sqrt(2) too big; the
    # lungs are ellipses too, so the box half-sizes plus the chest wall enclose them
    return centre, 0.5 * (hi - lo) + params.chest_wall_mm * MM


def _ellipse_sd(x, y, centre, axes):
    u = (x - centre[0]) / axes[0]
    v = (y - centre[1]) / axes[1]
    g = 2.0 * np.sqrt((u / axes[0]) ** 2 + (v / axes[1]) ** 2)
    return (u * u + v * v - 1.0) / np.maximum(g, 1e-6)


def _grid(tree: AirwayTree, params: PhantomParams, body: bool = True) -> tuple[np.ndarray, tuple[int, int, int]]:
    """Affine (voxel -> world metres, axis-aligned RAS+) and shape of the phantom's field of view.

    The tree's bounding box plus ``margin_mm``, widened in x/y to hold the body
    outline plus ``margin_mm`` of air (``body``; else the field of view lies
    inside the body); the top is lowered by ``crop_top_mm``.
    """
    sp = np.array(params.spacing_mm) * MM
    margin = params.margin_mm * MM
    lo, hi = tree.bounds(margin)
    if body:
        bc, ba = _body_ellipse(params)
        lo[:2] = np.minimum(lo[:2], bc - ba - margin)
        hi[:2] = np.maximum(hi[:2], bc + ba + margin)
    if params.crop_top_mm > 0:
        hi[2] = tree.branch(0).start[2] - params.crop_top_mm * MM
    shape = tuple(int(v) for v in np.floor((hi - lo) / sp).astype(int) + 1)
    affine = np.eye(4)
    affine[:3, :3] = np.diag(sp)
    affine[:3, 3] = lo
    return affine, shape  # type: ignore[return-value]


def _capsule_min_distance(tree: AirwayTree, xs, ys, zs, margin: float, wall: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Min over branches of the capsule signed distances of the lumen and of the wall's outer surface.

    Each branch is evaluated only on the voxel sub-box of its capsule grown by
    ``margin`` (metres); elsewhere the result is ``+inf``.  Outside the lumen
    the lumen value is the exact distance to the union.  float32 arrays.
    """
    shape = (len(xs), len(ys), len(zs))
    d_lumen = np.full(shape, np.inf, dtype=np.float32)
    d_outer = np.full(shape, np.inf, dtype=np.float32)
    axes = (xs, ys, zs)
    sp = np.array([xs[1] - xs[0] if len(xs) > 1 else 1.0, ys[1] - ys[0] if len(ys) > 1 else 1.0,
                   zs[1] - zs[0] if len(zs) > 1 else 1.0])
    origin = np.array([xs[0], ys[0], zs[0]])
    for b, t in zip(tree.branches, wall):
        grow = b.radius + t + margin
        lo = np.ceil((np.minimum(b.start, b.end) - grow - origin) / sp).astype(int)
        hi = np.floor((np.maximum(b.start, b.end) + grow - origin) / sp).astype(int) + 1
        lo = np.maximum(lo, 0)
        hi = np.minimum(hi, shape)
        if np.any(hi <= lo):
            continue
        px = axes[0][lo[0]:hi[0], None, None] - b.start[0]
        py = axes[1][None, lo[1]:hi[1], None] - b.start[1]
        pz = axes[2][None, None, lo[2]:hi[2]] - b.start[2]
        ab = b.end - b.start
        L2 = float(ab @ ab)
        t_ax = (px * ab[0] + py * ab[1] + pz * ab[2]) / L2 if L2 > 0 else np.zeros_like(px * py * pz)
        np.clip(t_ax, 0.0, 1.0, out=t_ax)
        dist = np.sqrt((px - t_ax * ab[0]) ** 2 + (py - t_ax * ab[1]) ** 2 + (pz - t_ax * ab[2]) ** 2)
        sl = (slice(lo[0], hi[0]), slice(lo[1], hi[1]), slice(lo[2], hi[2]))
        np.minimum(d_lumen[sl], dist - b.radius, out=d_lumen[sl])
        np.minimum(d_outer[sl], dist - b.radius - t, out=d_outer[sl])
    return d_lumen, d_outer


def _tree_sdf_tiled(tree: AirwayTree, ijk: np.ndarray, affine: np.ndarray, band: float,
                    tile: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`AirwayTree.sdf` at voxel indices ``ijk`` (N, 3), tile by tile with nearby branches only.

    A branch whose bounding box grown by ``band`` misses a tile is skipped by
    the tree's own band test for every point of that tile and cannot cover a
    foot point within ``band`` of it, so the values equal the whole tree's.
    """
    out = np.empty(len(ijk))
    exact = np.empty(len(ijk), dtype=bool)
    if len(ijk) == 0:
        return out, exact
    keys = ijk // tile
    kid = (keys[:, 0] * (keys[:, 1].max() + 1) + keys[:, 1]) * (keys[:, 2].max() + 1) + keys[:, 2]
    order = np.argsort(kid, kind="stable")
    starts = np.r_[0, np.nonzero(np.diff(kid[order]))[0] + 1, len(order)]
    blo = np.array([np.minimum(b.start, b.end) - b.radius for b in tree.branches]) - band
    bhi = np.array([np.maximum(b.start, b.end) + b.radius for b in tree.branches]) + band
    for s, e in zip(starts[:-1], starts[1:]):
        sel = order[s:e]
        pts = ijk[sel] @ affine[:3, :3].T + affine[:3, 3]
        plo, phi = pts.min(axis=0), pts.max(axis=0)
        near = np.all((blo <= phi) & (bhi >= plo), axis=1)
        sub = AirwayTree([b for b, k in zip(tree.branches, near) if k])
        out[sel], exact[sel] = sub.sdf(pts, band=band)
    return out, exact


def rasterise(tree: AirwayTree, params: PhantomParams, rng: np.random.Generator,
              lungs: Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray] | None = None) -> Phantom:
    """CT (int16 HU) and ground truth of ``tree`` on the phantom's grid; see the module docstring.

    ``lungs``: None for the phantom's own lungs and body (half-ellipsoids in an elliptic body, the field of
    view reaching past the skin); else a function of the grid's axes ``(xs, ys, zs)`` (metres) giving the
    lungs' signed distance (float32, metres, < 0 inside) on the whole grid, and the field of view (the
    tree's bounding box + ``margin_mm``) lies inside the body: soft tissue wherever it is not lung
    (:func:`~room_pipeline.anatomy.reference_tree.hull_lungs`, for measured trees).
    """
    affine, shape = _grid(tree, params, body=lungs is None)
    sp = np.diag(affine)[:3]
    xs, ys, zs = (affine[a, 3] + sp[a] * np.arange(shape[a]) for a in range(3))
    h = float(np.mean(sp))
    band = params.sdf_band_mm * MM
    wall = np.array([wall_thickness(b.radius, params) for b in tree.branches])
    box_margin = max(band, 3 * h * (1 + params.psf_sigma_voxels))

    # ---- airway distances: cheap per-branch boxes, then the exact tree SDF near the surface
    d_lumen, d_outer = _capsule_min_distance(tree, xs, ys, zs, box_margin, wall)
    ijk = np.argwhere(d_lumen < band)
    r_max = max(b.radius for b in tree.branches)
    vals, ex = _tree_sdf_tiled(tree, ijk, affine, max(band, r_max + 2 * h))
    sdf = np.full(shape, band, dtype=np.float32)
    exact = np.zeros(shape, dtype=bool)
    sdf[tuple(ijk.T)] = vals
    exact[tuple(ijk.T)] = ex
    sdf[sdf > band] = band  # outside values beyond the band are clipped ...
    exact &= sdf < band     # ... and are then not exact
    mask = (sdf < 0).astype(np.uint8)
    del ijk, vals, ex

    # ---- tissue layers, outside in
    x32, y32, z32 = (a.astype(np.float32) for a in (xs, ys, zs))
    if lungs is None:
        hu = np.full(shape, params.hu_air, dtype=np.float32)
        bc, ba = _body_ellipse(params)
        s_body = _ellipse_sd(x32[:, None], y32[None, :], bc, ba).astype(np.float32)
        _mix(hu, np.float32(params.hu_fat), _coverage(s_body, h)[:, :, None])
        inner = ba - params.fat_thickness_mm * MM
        s_inner = _ellipse_sd(x32[:, None], y32[None, :], bc, inner).astype(np.float32)
        _mix(hu, np.float32(params.hu_soft_tissue), _coverage(s_inner, h)[:, :, None])

        s_lung = np.full(shape, np.inf, dtype=np.float32)
        for c, a, base in _lung_shapes(params):
            np.minimum(s_lung, _half_ellipsoid_sd(x32[:, None, None], y32[None, :, None], z32[None, None, :],
                                                  c.astype(np.float32), a.astype(np.float32), np.float32(base)),
                       out=s_lung)
    else:
        hu = np.full(shape, params.hu_soft_tissue, dtype=np.float32)
        s_lung = np.asarray(lungs(xs, ys, zs), dtype=np.float32)
        if s_lung.shape != shape:
            raise ValueError(f"lungs gave an array of shape {s_lung.shape}, the grid is {shape}")
    lung = _coverage(s_lung, h)
    del s_lung
    texture = rng.standard_normal(shape, dtype=np.float32)
    corr = params.texture_correlation_mm * MM / sp
    texture = ndimage.gaussian_filter(texture, corr, mode="reflect", truncate=3.0)
    texture *= np.float32(params.texture_sigma_hu / max(float(texture.std()), 1e-12))
    texture += np.float32(params.hu_parenchyma)
    hu += lung * (texture - hu)
    del texture, lung

    _mix(hu, np.float32(params.hu_wall), _coverage(d_outer, h))
    del d_outer
    _mix(hu, np.float32(params.hu_air), _coverage(d_lumen, h))
    del d_lumen

    # ---- scanner: PSF, noise, quantisation
    if params.psf_sigma_voxels > 0:
        hu = ndimage.gaussian_filter(hu, params.psf_sigma_voxels, mode="nearest", truncate=3.0)
    if params.noise_sigma_hu > 0:
        hu += np.float32(params.noise_sigma_hu) * rng.standard_normal(shape, dtype=np.float32)
    np.rint(hu, out=hu)
    np.clip(hu, -1024, 3071, out=hu)
    ct = hu.astype(np.int16)
    del hu
    return Phantom(tree=tree, ct=Volume(ct, affine), mask=Volume(mask, affine.copy()),
                   sdf=Volume(sdf, affine.copy()), sdf_exact=Volume(exact, affine.copy()))


def make_phantom(params: PhantomParams, seed: int) -> Phantom:
    """Grow the tree and rasterise the CT; same ``params`` and ``seed`` give identical arrays."""
    rng = np.random.default_rng(seed)
    tree = grow_tree(params, rng)
    return rasterise(tree, params, rng)
