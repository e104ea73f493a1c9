"""Airway lumen segmentation of a chest CT (the ``segment`` stage's domain code).

Default method ``region_growing`` needs no trained weights:

1. denoise (Gaussian, sigma in mm; or 3x3x3 median; or none);
2. find a trachea seed in the superior-most slices (:func:`find_trachea_seed`);
3. adaptive-threshold region growing (Mori et al. 1996 style): raise the HU
   threshold step by step, take the connected component of the seed each
   time, and stop at the first step where the volume jumps by more than
   ``leak_factor`` (an explosion into lung parenchyma); the last safe step is
   kept, then refined with a finer step inside the last interval;
4. local refinement: one boundary layer of partial-volume voxels below
   ``refine_hu`` whose outward neighbour is not darker (so a one-voxel wall
   between two airways is never added), and voxels of one-voxel-wide airways
   connected through raw-CT air (``thin_airway_hu``), both leak-guarded;
5. cleanup: fill enclosed holes and keep the component connected to the seed.
   No opening (thin airways survive) and no dilation/closing (branches one
   voxel apart are not bridged).

Method ``totalsegmentator`` runs TotalSegmentator's ``lung_vessels`` model (class
``lung_trachea_bronchia``) from locally provided weights: the nnU-Net v2 results folder is read and run by
:mod:`room_pipeline.anatomy.nnunet` (plans, checkpoint, ``PlainConvUNet``, sliding window).

Units: HU for intensities, millimetres for the lengths in :class:`SegmentParams`
(as in the YAML), metres for geometry in memory (:mod:`room_pipeline.conventions`).
"""
from __future__ import annotations

import dataclasses
import importlib.util
import logging
import math
import os
from pathlib import Path
from typing import Any, Mapping

import numpy as np
from scipy import ndimage as ndi

from ..conventions import MM
from ..errors import BackendUnavailable, ConfigError, InputError
from ..io.volume import Volume

log = logging.getLogger(__name__)

METHODS = ("region_growing", "totalsegmentator")
DENOISE = ("gaussian", "median", "none")
#: TotalSegmentator task, its weights folder and the airway class label in its multilabel output
TS_TASK = "lung_vessels"
TS_DATASET = "Dataset258_lung_vessels_248subj"
TS_AIRWAY_NAME = "lung_trachea_bronchia"  # its label is read from the model's dataset.json (2 in Dataset258)
#: minimum fill ratio area / (pi/4 * major * minor) of a trachea cross-section (1 for an ellipse)
_MIN_FILL = 0.75
#: above this HU a voxel counts as body tissue (left-right centre estimate)
_TISSUE_HU = -500.0


@dataclasses.dataclass
class SegmentParams:
    """Knobs of :func:`segment_airways`; field names are the keys of ``conf/segment/<method>.yaml``.

    HU values are Hounsfield units, ``*_mm`` lengths millimetres, ``*_ml`` volumes millilitres.
    """

    method: str = "region_growing"
    #: HU below which a voxel is air (trachea search, input checks)
    air_hu: float = -900.0
    #: denoising before growing: gaussian | median (3x3x3) | none
    denoise: str = "gaussian"
    #: Gaussian sigma (mm), per axis converted to voxels
    smoothing_sigma_mm: float = 0.5
    #: depth below the top of the volume searched for the trachea (mm)
    seed_search_depth_mm: float = 80.0
    #: a trachea candidate must persist this far downwards (mm)
    seed_track_mm: float = 5.0
    #: accepted equivalent diameter of the trachea cross-section (mm)
    trachea_min_diameter_mm: float = 8.0
    trachea_max_diameter_mm: float = 30.0
    #: minimum minor/major axis ratio of the trachea cross-section
    trachea_min_roundness: float = 0.5
    #: maximum left-right distance of the trachea from the body centre (mm)
    trachea_max_offset_mm: float = 40.0
    #: adaptive threshold sweep (HU): start, coarse step, fine step, upper limit
    threshold_start_hu: float = -950.0
    threshold_step_hu: float = 20.0
    threshold_fine_step_hu: float = 5.0
    threshold_max_hu: float = -500.0
    #: a step whose volume exceeds leak_factor x the previous one is a leak
    leak_factor: float = 1.5
    #: leak checks start once the region holds this much (ml)
    min_volume_ml: float = 0.2
    #: any region larger than this is a leak (ml)
    max_volume_ml: float = 600.0
    #: region-growing connectivity: 6 (faces) or 26 (faces, edges, corners)
    connectivity: int = 6
    #: boundary refinement: add partial-volume voxels below this HU (null: off)
    refine_hu: float | None = -500.0
    #: number of refinement layers (each at most one voxel)
    refine_layers: int = 1
    #: one-voxel airways: also follow raw-CT voxels below this HU (null: off)
    thin_airway_hu: float | None = -950.0
    #: fill cavities enclosed by the lumen mask
    fill_holes: bool = True
    #: TotalSegmentator only: folder with its weights (else env TOTALSEG_HOME_DIR)
    weights_dir: str | None = None
    #: TotalSegmentator only: 'cpu', 'gpu' or 'gpu:N'
    device: str = "cpu"

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "SegmentParams":
        """Build from a config mapping; unknown keys or invalid values raise :class:`ConfigError`."""
        d = dict(d or {})
        names = {f.name: f for f in dataclasses.fields(cls)}
        for k in d:
            if k not in names:
                raise ConfigError(f"segment: unknown key '{k}' (known: {', '.join(names)})")
        kw: dict[str, Any] = {}
        for k, v in d.items():
            default = names[k].default
            try:
                if v is None:
                    if k not in ("refine_hu", "thin_airway_hu", "weights_dir"):
                        raise ValueError("null not allowed")
                    kw[k] = None
                elif isinstance(default, bool):
                    if not isinstance(v, bool):
                        raise ValueError("expected true/false")
                    kw[k] = v
                elif isinstance(default, int):
                    if isinstance(v, bool) or float(v) != int(v):
                        raise ValueError("expected an integer")
                    kw[k] = int(v)
                elif isinstance(default, float) or k in ("refine_hu", "thin_airway_hu"):
                    if isinstance(v, bool):
                        raise ValueError("expected a number")
                    kw[k] = float(v)
                else:
                    kw[k] = str(v)
            except (TypeError, ValueError) as exc:
                raise ConfigError(f"segment.{k}: invalid value {v!r} ({exc})") from None
        p = cls(**kw)
        p.validate()
        return p

    def validate(self) -> None:
        """Raise :class:`ConfigError` on an inconsistent value."""
        def bad(key: str, why: str) -> ConfigError:
            return ConfigError(f"segment.{key}={getattr(self, key)!r}: {why}")
        if self.method not in METHODS:
            raise bad("method", f"must be one of {', '.join(METHODS)}")
        if self.denoise not in DENOISE:
            raise bad("denoise", f"must be one of {', '.join(DENOISE)}")
        if self.connectivity not in (6, 26):
            raise bad("connectivity", "must be 6 or 26")
        for k in ("threshold_step_hu", "threshold_fine_step_hu", "trachea_min_diameter_mm",
                  "seed_search_depth_mm", "max_volume_ml"):
            if not getattr(self, k) > 0:
                raise bad(k, "must be > 0")
        for k in ("smoothing_sigma_mm", "seed_track_mm", "min_volume_ml", "refine_layers",
                  "trachea_max_offset_mm"):
            if getattr(self, k) < 0:
                raise bad(k, "must be >= 0")
        if self.trachea_max_diameter_mm < self.trachea_min_diameter_mm:
            raise bad("trachea_max_diameter_mm", "must be >= trachea_min_diameter_mm")
        if not 0 < self.trachea_min_roundness <= 1:
            raise bad("trachea_min_roundness", "must be in (0, 1]")
        if self.threshold_max_hu < self.threshold_start_hu:
            raise bad("threshold_max_hu", "must be >= threshold_start_hu")
        if not self.leak_factor > 1:
            raise bad("leak_factor", "must be > 1")


@dataclasses.dataclass
class SegmentResult:
    """Output of :func:`segment_airways`.

    Attributes:
        mask: uint8 0/1 airway lumen on the CT grid.
        seed: trachea seed voxel (i, j, k).
        threshold_hu: the last safe region-growing threshold (HU; NaN for TotalSegmentator).
        report: JSON-serialisable diagnostics.
    """

    mask: Volume
    seed: tuple[int, int, int]
    threshold_hu: float
    report: dict


# ------------------------------------------------------------------ helpers
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


# ------------------------------------------------------------------ TotalSegmentator
def _ts_weights(params: SegmentParams) -> tuple[str, Path]:
    """(env var to set, folder) locating the local ``lung_vessels`` weights, or raise BackendUnavailable."""
    where = params.weights_dir or os.environ.get("TOTALSEG_HOME_DIR")
    if not where:
        raise BackendUnavailable(
            f"TotalSegmentator weights location not set: set segment.weights_dir (or env TOTALSEG_HOME_DIR) "
            f"to a folder holding nnunet/results/{TS_DATASET} (copy it from a machine with internet; "
            f"weights cannot be downloaded here), or use segment.method=region_growing")
    root = Path(where).expanduser()
    if (root / "nnunet" / "results" / TS_DATASET).is_dir():
        return "TOTALSEG_HOME_DIR", root
    if (root / TS_DATASET).is_dir():  # pointed at the results folder itself
        return "TOTALSEG_WEIGHTS_PATH", root
    raise BackendUnavailable(
        f"TotalSegmentator '{TS_TASK}' weights not found: expected {root / 'nnunet' / 'results' / TS_DATASET} "
        f"(get them with `totalseg_download_weights -t {TS_TASK}` on a machine with internet and copy "
        f"the folder there; weights cannot be downloaded here), or use segment.method=region_growing")


def _segment_totalsegmentator(ct: Volume, p: SegmentParams) -> SegmentResult:
    missing = [m for m in ("torch", "dynamic_network_architectures") if importlib.util.find_spec(m) is None]
    if missing:
        raise BackendUnavailable(
            "segment.method=totalsegmentator runs TotalSegmentator's nnU-Net v2 model, which needs "
            f"{' and '.join(missing)}, not installed: pip install 'room-pipeline[totalseg]' "
            "(dynamic-network-architectures with --no-deps beside the local CPU torch) plus its weights, "
            "or use segment.method=region_growing")
    _, folder = _ts_weights(p)
    from . import nnunet

    dataset = folder / "nnunet" / "results" / TS_DATASET if (folder / "nnunet").is_dir() else folder / TS_DATASET
    model = nnunet.load_model(nnunet.find_model_folder(dataset, "3d_fullres"), fold=0, device=p.device)
    airway = model.label(TS_AIRWAY_NAME)
    affine_mm = ct.affine.copy()
    affine_mm[:3, :] /= MM
    try:
        labels = nnunet.predict_volume(model, np.asarray(ct.data, dtype=np.float32), affine_mm)
    except RuntimeError as exc:  # torch: out of memory, device errors
        msg = str(exc).splitlines()[0] if str(exc) else ""
        raise BackendUnavailable(f"TotalSegmentator model {model.folder} failed: {type(exc).__name__}: {msg}") from None
    if labels.shape != ct.shape:
        raise BackendUnavailable(f"TotalSegmentator returned shape {labels.shape}, expected {ct.shape}")
    mask_rep: dict = {}
    if not (labels == airway).any():
        raise InputError(f"TotalSegmentator model {model.folder.name} found no '{TS_AIRWAY_NAME}' voxel in the CT")
    mask = validate_mask(Volume((labels == airway).astype(np.uint8), ct.affine.copy()), report=mask_rep)
    m = mask.data.astype(bool)
    ax, sgn = ct.superior_axis()
    prof = np.nonzero(m.any(axis=tuple(a for a in range(3) if a != ax)))[0]
    top = int(prof[-1] if sgn > 0 else prof[0])
    sl = [slice(None)] * 3
    sl[ax] = top
    plane = m[tuple(sl)]
    edt = ndi.distance_transform_edt(plane)
    ij = list(np.unravel_index(int(np.argmax(edt)), plane.shape))
    ij.insert(ax, top)
    seed = tuple(int(v) for v in ij)
    n = int(np.count_nonzero(m))
    report = {"method": "totalsegmentator", "task": TS_TASK, "model_folder": str(model.folder),
              "airway_label": airway, "seed": list(seed), "threshold_hu": None,
              "voxels": n, "volume_m3": n * float(np.prod(ct.spacing)),
              "volume_ml": n * float(np.prod(_spacing_mm(ct))) / 1000.0, **mask_rep,
              "params": dataclasses.asdict(p)}
    return SegmentResult(mask, seed, float("nan"), report)  # type: ignore[arg-type]


# ------------------------------------------------------------------ public entry points
def segment_airways(ct: Volume, params: SegmentParams | None = None) -> SegmentResult:
    """Segment the airway lumen of ``ct`` (HU) with ``params.method``.

    Raises :class:`InputError` for a volume without air, an all-air volume,
    no trachea found or an empty result; :class:`BackendUnavailable` when the
    TotalSegmentator package or its weights are missing.
    """
    p = params or SegmentParams()
    p.validate()
    if p.method == "totalsegmentator":
        return _segment_totalsegmentator(ct, p)
    return _segment_region_growing(ct, p)


def validate_mask(mask: Volume, report: dict | None = None) -> Volume:
    """A user-supplied airway mask as uint8 0/1: voxels > 0, largest 26-connected component.

    Dropped components are logged (and counted in ``report`` when a dict is
    given).  Raises :class:`InputError` if the mask is empty.
    """
    data = np.asarray(mask.data)
    binary = np.nan_to_num(data.astype(np.float64, copy=False), nan=0.0) > 0 if data.dtype.kind == "f" else data > 0
    if not binary.any():
        raise InputError("airway mask is empty (no voxel > 0)")
    lab, n = ndi.label(binary, _structure(26))
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    keep = int(np.argmax(sizes))
    out = (lab == keep).astype(np.uint8)
    dropped = int(sizes.sum() - sizes[keep])
    if n > 1:
        log.warning("airway mask: kept the largest of %d components (%d voxels), dropped %d voxels",
                    n, int(sizes[keep]), dropped)
    if report is not None:
        report.update({"components": int(n), "dropped_components": int(n - 1),
                       "dropped_voxels": dropped, "kept_voxels": int(sizes[keep])})
    return Volume(out, mask.affine.copy())
