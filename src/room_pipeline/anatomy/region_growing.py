"""Airway segmentation by adaptive-threshold region growing from a trachea seed: steps 1-5 of
:mod:`~room_pipeline.anatomy.segment` (denoise, seed, threshold sweep with leak detection, boundary
refinement, cleanup).  HU and millimetres in :class:`~room_pipeline.anatomy.segment_params.SegmentParams`,
voxel indices (i, j, k) on the CT grid."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import ndimage as ndi

from ..conventions import MM
from ..errors import InputError
from ..io.volume import Volume
from .segment_params import SegmentParams, SegmentResult


#: minimum fill ratio area / (pi/4 * major * minor) of a trachea cross-section (1 for an ellipse)
_MIN_FILL = 0.75
#: above this HU a voxel counts as body tissue (left-right centre estimate)
_TISSUE_HU = -500.0


def _spacing_mm(ct: Volume) -> np.ndarray:
    return np.asarray(ct.spacing, dtype=np.float64) / MM


def _structure(connectivity: int) -> np.ndarray:
    return ndi.generate_binary_structure(3, 1 if connectivity == 6 else 3)


def _denoise(ct: Volume, p: SegmentParams) -> np.ndarray:
    """CT intensities (HU) as float32, denoised as configured."""
    data = np.asarray(ct.data, dtype=np.float32)
    if not np.isfinite(data).all():
        data = np.nan_to_num(data, nan=0.0, posinf=3000.0, neginf=-1024.0)
    if p.denoise == "gaussian" and p.smoothing_sigma_mm > 0:
        sigma = p.smoothing_sigma_mm / _spacing_mm(ct)
        return ndi.gaussian_filter(data, sigma, mode="nearest", truncate=3.0)
    if p.denoise == "median":
        return ndi.median_filter(data, size=3, mode="nearest")
    return data


def _check_air(smoothed: np.ndarray, p: SegmentParams) -> None:
    n_air = int(np.count_nonzero(smoothed < p.air_hu))
    if n_air == 0:
        raise InputError(f"no air (< {p.air_hu:g} HU) in the volume: not a chest CT, or not in HU")
    if n_air >= 0.99 * smoothed.size:
        raise InputError(f"the volume is all air (< {p.air_hu:g} HU): no body to segment")


def _bbox(mask: np.ndarray, margin: int, shape: tuple[int, ...]) -> tuple[slice, ...]:
    idx = [np.nonzero(mask.any(axis=tuple(a for a in range(3) if a != ax)))[0] for ax in range(3)]
    return tuple(slice(max(0, int(i[0]) - margin), min(n, int(i[-1]) + 1 + margin))
                 for i, n in zip(idx, shape))


def _seed_component(binary: np.ndarray, seed: tuple[int, int, int], structure: np.ndarray) -> np.ndarray | None:
    """Connected component of ``binary`` containing ``seed`` (None if the seed is not set)."""
    if not binary[seed]:
        return None
    lab, _ = ndi.label(binary, structure)
    return lab == lab[seed]


# ------------------------------------------------------------------ trachea seed
def find_trachea_seed(ct: Volume, params: SegmentParams | None = None) -> tuple[int, int, int]:
    """Voxel (i, j, k) inside the trachea lumen, found in the superior-most slices.

    Scans slices perpendicular to :meth:`Volume.superior_axis` from the top
    down (at most ``seed_search_depth_mm``) for 2-D air components
    (< ``air_hu`` after denoising) that do not touch the in-plane border (outside
    air), whose equivalent diameter is in the trachea range, that are round
    and within ``trachea_max_offset_mm`` of the body's left-right centre, and
    that persist for ``seed_track_mm`` downwards.  The topmost such track wins;
    the seed is the deepest point (2-D distance transform maximum) of its
    middle cross-section.  A trachea cut by the top face of the volume is found
    like any other.  Raises :class:`InputError` when nothing qualifies.
    """
    p = params or SegmentParams()
    smoothed = _denoise(ct, p)
    _check_air(smoothed, p)
    return _find_seed(smoothed, ct, p)


def _find_seed(S: np.ndarray, ct: Volume, p: SegmentParams) -> tuple[int, int, int]:
    ax, sgn = ct.superior_axis()
    sp = _spacing_mm(ct)
    inplane = [a for a in range(3) if a != ax]
    n = S.shape[ax]
    depth = int(min(n, max(1, math.ceil(p.seed_search_depth_mm / sp[ax]))))
    top_idx = np.arange(n - 1, n - 1 - depth, -1) if sgn > 0 else np.arange(depth)
    slab = np.moveaxis(np.take(S, top_idx, axis=ax), ax, 0)  # (depth, A, B), top slice first

    def to_index(s: int, a: float, b: float) -> np.ndarray:
        ijk = np.zeros(3)
        ijk[ax], ijk[inplane[0]], ijk[inplane[1]] = top_idx[s], a, b
        return ijk

    def fail(why: str) -> InputError:
        return InputError(f"no trachea found in the top {depth * sp[ax]:.0f} mm: {why} "
                          f"(air < {p.air_hu:g} HU, {p.trachea_min_diameter_mm:g}-{p.trachea_max_diameter_mm:g} mm wide, "
                          f"within {p.trachea_max_offset_mm:g} mm of the left-right centre)")

    struct = np.zeros((3, 3, 3), dtype=bool)
    struct[1] = ndi.generate_binary_structure(2, 1)  # 2-D labelling of every slice in one call
    lab, nlab = ndi.label(slab < p.air_hu, struct)
    if nlab == 0:
        raise fail("no air component")
    border = np.unique(np.concatenate([lab[:, 0, :].ravel(), lab[:, -1, :].ravel(),
                                       lab[:, :, 0].ravel(), lab[:, :, -1].ravel()]))
    pix_mm2 = sp[inplane[0]] * sp[inplane[1]]
    area = np.bincount(lab.ravel(), minlength=nlab + 1) * pix_mm2
    ok = (area >= math.pi / 4 * p.trachea_min_diameter_mm ** 2) & (area <= math.pi / 4 * p.trachea_max_diameter_mm ** 2)
    ok[0] = False
    ok[border] = False
    labels = np.nonzero(ok)[0]
    if len(labels) == 0:
        raise fail("no enclosed air region of trachea size")

    # left-right centre: world x of the body tissue centroid in the slab (volume centre if no tissue)
    tissue = slab > _TISSUE_HU
    tot = int(np.count_nonzero(tissue))
    if tot:
        ma = float((tissue.sum(axis=(0, 2)) * np.arange(slab.shape[1])).sum() / tot)
        mb = float((tissue.sum(axis=(0, 1)) * np.arange(slab.shape[2])).sum() / tot)
    else:
        ma, mb = (slab.shape[1] - 1) / 2, (slab.shape[2] - 1) / 2
    centre_x = float(ct.index_to_world(to_index(depth // 2, ma, mb)[None])[0, 0])

    objs = ndi.find_objects(lab)
    cands: dict[int, list[dict]] = {}
    for lb in labels:
        sl = objs[lb - 1]
        a_idx, b_idx = np.nonzero(lab[sl][0] == lb)
        a_mm = (a_idx + sl[1].start) * sp[inplane[0]]
        b_mm = (b_idx + sl[2].start) * sp[inplane[1]]
        ev = np.linalg.eigvalsh(np.cov(np.stack([a_mm, b_mm])))
        major, minor = 4 * math.sqrt(max(ev[1], 1e-12)), 4 * math.sqrt(max(ev[0], 1e-12))
        if minor / major < p.trachea_min_roundness or area[lb] / (math.pi / 4 * major * minor) < _MIN_FILL:
            continue
        s = sl[0].start
        ca, cb = float(a_idx.mean() + sl[1].start), float(b_idx.mean() + sl[2].start)
        x = float(ct.index_to_world(to_index(s, ca, cb)[None])[0, 0])
        if abs(x - centre_x) / MM > p.trachea_max_offset_mm:
            continue
        cands.setdefault(s, []).append({"label": int(lb), "s": s, "c": np.array([ca * sp[inplane[0]], cb * sp[inplane[1]]]),
                                        "d": math.sqrt(area[lb] / (math.pi / 4)), "off": abs(x - centre_x)})
    n_track = int(min(max(0, round(p.seed_track_mm / sp[ax])), depth - 1))
    for s in sorted(cands):
        for c0 in sorted(cands[s], key=lambda c: c["off"]):
            chain, cur = [c0], c0
            for t in range(1, n_track + 1):
                nxt = [c for c in cands.get(s + t, [])
                       if np.linalg.norm(c["c"] - cur["c"]) < cur["d"] / 2 and 2 / 3 < c["d"] / cur["d"] < 1.5]
                if not nxt:
                    break
                cur = min(nxt, key=lambda c: np.linalg.norm(c["c"] - cur["c"]))
                chain.append(cur)
            if len(chain) < n_track + 1:
                continue
            mid = chain[len(chain) // 2]
            sl = objs[mid["label"] - 1]
            region = np.pad(lab[sl][0] == mid["label"], 1)
            edt = ndi.distance_transform_edt(region, sampling=(sp[inplane[0]], sp[inplane[1]]))
            a, b = np.unravel_index(int(np.argmax(edt)), edt.shape)
            ijk = to_index(mid["s"], a - 1 + sl[1].start, b - 1 + sl[2].start)
            return tuple(int(round(v)) for v in ijk)  # type: ignore[return-value]
    raise fail("no round air region of trachea size persists over "
               f"{p.seed_track_mm:g} mm")


# ------------------------------------------------------------------ region growing
def _region_grow(S: np.ndarray, seed: tuple[int, int, int], p: SegmentParams, voxel_ml: float
                 ) -> tuple[np.ndarray, float, dict]:
    """Adaptive-threshold region growing; returns (mask, safe threshold HU, diagnostics)."""
    struct = _structure(p.connectivity)
    min_vox = p.min_volume_ml / voxel_ml
    max_vox = p.max_volume_ml / voxel_ml
    history: list[list[float]] = []

    def leaks(prev: int, v: int) -> bool:
        return v > max_vox or (prev >= min_vox and v > p.leak_factor * prev)

    safe_t, safe_v, safe = None, 0, None
    leak_t = None
    for t in np.arange(p.threshold_start_hu, p.threshold_max_hu + 1e-6, p.threshold_step_hu):
        comp = _seed_component(S < t, seed, struct)
        v = 0 if comp is None else int(np.count_nonzero(comp))
        history.append([float(t), v])
        if v == 0:
            continue
        if leaks(safe_v, v):
            leak_t = float(t)
            break
        safe_t, safe_v, safe = float(t), v, comp
    if leak_t is not None and safe_t is not None and p.threshold_fine_step_hu < p.threshold_step_hu:
        for t in np.arange(safe_t + p.threshold_fine_step_hu, leak_t - 1e-6, p.threshold_fine_step_hu):
            comp = _seed_component(S < t, seed, struct)
            v = 0 if comp is None else int(np.count_nonzero(comp))
            history.append([float(t), v])
            if leaks(safe_v, v):
                leak_t = float(t)
                break
            safe_t, safe_v, safe = float(t), v, comp
    if safe is None:
        if leak_t is not None:
            raise InputError(f"airway segmentation leaked at the first threshold reaching the seed ({leak_t:g} HU): "
                             f"lower segment.threshold_start_hu or raise segment.max_volume_ml")
        raise InputError(f"airway segmentation is empty: the trachea seed {seed} is not below "
                         f"segment.threshold_max_hu={p.threshold_max_hu:g} HU")
    history.sort(key=lambda h: h[0])
    return safe, float(safe_t), {"threshold_history": history, "leak_detected": leak_t is not None,
                                 "leak_threshold_hu": leak_t}


def _refine_boundary(mask: np.ndarray, S: np.ndarray, refine_hu: float) -> np.ndarray:
    """One layer of voxels below ``refine_hu`` next to ``mask`` whose outward neighbour is not darker.

    A voxel v is added when, along some axis direction d, v - d is in the mask
    and S(v + d) >= S(v): HU rises (or stays) away from the lumen, as on a
    lumen boundary.  A wall voxel between two lumens is a local maximum and
    is never added, so adjacent airways are not bridged.
    """
    cand = ~mask & (S < refine_hu)
    add = np.zeros_like(mask)
    for ax in range(3):
        n = mask.shape[ax]
        if n < 2:
            continue

        def sl(a: int, b: int) -> tuple[slice, ...]:
            s = [slice(None)] * 3
            s[ax] = slice(a, b)
            return tuple(s)
        # d = +1: inner neighbour v-1 in mask, outer v+1 not darker (border: treated as not darker)
        inner = np.zeros_like(mask)
        inner[sl(1, n)] = mask[sl(0, n - 1)]
        outer = np.ones_like(mask)
        outer[sl(0, n - 1)] = S[sl(1, n)] >= S[sl(0, n - 1)]
        add |= cand & inner & outer
        # d = -1
        inner = np.zeros_like(mask)
        inner[sl(0, n - 1)] = mask[sl(1, n)]
        outer = np.ones_like(mask)
        outer[sl(1, n)] = S[sl(0, n - 1)] >= S[sl(1, n)]
        add |= cand & inner & outer
    return add


def _segment_region_growing(ct: Volume, p: SegmentParams) -> SegmentResult:
    S = _denoise(ct, p)
    _check_air(S, p)
    seed = _find_seed(S, ct, p)
    sp = _spacing_mm(ct)
    voxel_ml = float(np.prod(sp)) / 1000.0
    struct = _structure(p.connectivity)

    # work inside the bounding box of everything the sweep could ever reach
    reach = _seed_component(S < p.threshold_max_hu, seed, struct)
    if reach is None:
        raise InputError(f"airway segmentation is empty: the trachea seed {seed} is not below "
                         f"segment.threshold_max_hu={p.threshold_max_hu:g} HU")
    box = _bbox(reach, 1, S.shape)
    del reach
    Sb = S[box]
    seed_b = tuple(int(s - b.start) for s, b in zip(seed, box))
    mask, t_safe, rep = _region_grow(Sb, seed_b, p, voxel_ml)
    n_grown = int(np.count_nonzero(mask))

    n_refined = 0
    if p.refine_hu is not None and p.refine_layers > 0:
        for _ in range(p.refine_layers):
            add = _refine_boundary(mask, Sb, p.refine_hu)
            k = int(np.count_nonzero(add))
            if k == 0:
                break
            mask |= add
            n_refined += k
    n_thin, thin_leak = 0, False
    if p.thin_airway_hu is not None:
        raw = np.asarray(ct.data[box])
        comp = _seed_component(mask | (raw < p.thin_airway_hu), seed_b, _structure(6))
        extra = int(np.count_nonzero(comp)) - int(np.count_nonzero(mask))
        if extra > (p.leak_factor - 1.0) * n_grown:
            thin_leak = True  # raw air percolates (noise/emphysema): ignore it
        else:
            mask, n_thin = comp, extra
    n_holes = 0
    if p.fill_holes:
        inner = _bbox(mask, 1, mask.shape)
        filled = ndi.binary_fill_holes(mask[inner])
        n_holes = int(np.count_nonzero(filled)) - int(np.count_nonzero(mask[inner]))
        mask[inner] = filled
    mask = _seed_component(mask, seed_b, _structure(6))
    assert mask is not None  # the seed is always in the grown region

    out = np.zeros(S.shape, dtype=np.uint8)
    out[box] = mask
    _check_tubular(out, ct, seed)
    n = int(np.count_nonzero(out))
    report = {
        "method": "region_growing",
        "seed": [int(s) for s in seed],
        "seed_world_m": [float(v) for v in ct.index_to_world(np.array(seed)[None])[0]],
        "threshold_hu": t_safe,
        **rep,
        "voxels": n,
        "voxels_grown": n_grown,
        "voxels_refined": n_refined,
        "voxels_thin_airway": n_thin,
        "thin_airway_leak": thin_leak,
        "voxels_holes_filled": n_holes,
        "volume_m3": n * float(np.prod(ct.spacing)),
        "volume_ml": n * voxel_ml,
        "params": dataclasses.asdict(p),
    }
    return SegmentResult(Volume(out, ct.affine.copy()), seed, t_safe, report)


#: a segmented airway closed above (not cut by the top of the scan) must be at least this tall (mm): a whole
#: airway tree from the larynx is >= 100 mm; a closed gas pocket (stomach, bowel, oesophagus) of trachea width is not
_MIN_CLOSED_AIRWAY_HEIGHT_MM = 40.0


def _check_tubular(out: np.ndarray, ct: Volume, seed) -> None:
    """InputError when the grown region is a closed air pocket rather than a trachea and its tree."""
    ax, sgn = ct.superior_axis()
    sp = _spacing_mm(ct)
    along = np.nonzero(out.any(axis=tuple(a for a in range(3) if a != ax)))[0]
    n = out.shape[ax]
    gap = (n - 1 - along[-1]) if sgn > 0 else along[0]  # slices between the region's top and the scan's top
    height = (along[-1] - along[0] + 1) * sp[ax]
    if gap > 1 and height < _MIN_CLOSED_AIRWAY_HEIGHT_MM:
        w = ", ".join(f"{v / MM:.0f}" for v in ct.index_to_world(np.array(seed, dtype=float)[None])[0])
        raise InputError(f"no airway tree: the trachea-like air region at ({w}) mm is closed above, "
                         f"{gap * sp[ax]:.0f} mm below the top of the scan, and only {height:.0f} mm tall "
                         f"(< {_MIN_CLOSED_AIRWAY_HEIGHT_MM:g} mm): a gas pocket, not a trachea; the scan does "
                         "not show the airways")
