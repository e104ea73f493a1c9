"""Input plausibility: is this volume a chest CT, is this mask a human airway lumen?  Checked before any work.

Every check ends in one :class:`InputError` line naming the file and the problem, or in a repair that the
returned report states (the segment stage writes it to ``ct_metadata.json`` and ``metrics/segment.json``).

Human airway ranges (adult, intrathoracic airway lumen as segmented from CT), with their sources:

* lumen volume ``MIN_VOLUME_ML`` .. ``MAX_VOLUME_ML`` = 2 .. 250 ml.  Upper bound: the whole conducting
  airway, upper airway included, is Fowler's anatomical dead space, ~2.2 ml/kg (~150 ml at 70 kg; Fowler,
  Am J Physiol 1948), so the CT-visible tree of a 110 kg adult stays below ~250 ml.  Lower bound: a trachea
  (>= 10 mm across, Breatnach et al. 1984) cut 25 mm above the carina alone holds ~2 ml.
* trachea calibre (equivalent diameter of its cross-section) ``TRACHEA_DIAMETER_MM`` = 8 .. 30 mm: adult
  coronal diameters 10-25 mm (men 13-25, women 10-21; Breatnach, Abbott & Fraser, AJR 142:903, 1984),
  widened for sabre-sheath and paediatric-sized tracheas; the same bounds as ``segment.trachea_*``.
* largest inscribed radius ``MAX_INSCRIBED_RADIUS_MM`` = 16 mm: the widest lumen is the trachea (or the
  larynx at the top of a mask), at most ~27 mm across (Breatnach et al.).
* bounding box ``MAX_EXTENT_MM`` = 400 mm along each world axis: a thorax is ~300 mm high and wide.
* foreground fraction ``MAX_FOREGROUND_FRACTION`` = 0.5: airway lumen fills a few % of a chest field of
  view (the shared real masks: 0.1-2 %); more than half means background labelled 1 (inverted) or
  an all-ones volume.

* an airway segmented from a chest CT holds at least ``MIN_CT_TREE_VOLUME_ML`` = 8 ml and branches: the scan
  covers the lungs, so the intrathoracic trachea (>= ~60 mm of >= 10 mm lumen, ~4.7 ml) and both main
  bronchi are in it.

These are physiological ranges, not fitted to any sample.  A mask may be broken into pieces: the largest
26-connected piece is kept when it holds at least ``MIN_LARGEST_PIECE_FRACTION`` (0.5) of the lumen
(the repair is stated), otherwise it is an error.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from ..conventions import MM
from ..errors import InputError
from ..io.volume import Volume, check_affine

MIN_VOLUME_ML = 2.0
MAX_VOLUME_ML = 250.0
TRACHEA_DIAMETER_MM = (8.0, 30.0)
MAX_INSCRIBED_RADIUS_MM = 16.0
MAX_EXTENT_MM = 400.0
MAX_FOREGROUND_FRACTION = 0.5
MIN_LARGEST_PIECE_FRACTION = 0.5
#: airway segmented from a chest CT: the scan covers the lungs, so it holds the intrathoracic trachea
#: (>= ~60 mm of >= 10 mm lumen, Breatnach et al.: >= 4.7 ml) and both main bronchi
MIN_CT_TREE_VOLUME_ML = 8.0
#: a probability map / label map has at most this many distinct values before it is taken for an image
_MAX_LABELS = 64
#: non-finite CT voxels repaired (mean of finite neighbours) up to this fraction; more is an error
MAX_NONFINITE_FRACTION = 1e-3
#: a trachea must be a single round blob over this length below the top of the tree (mm)
_TRACHEA_RUN_MM = 15.0


def _where(path) -> str:
    return str(path) if path is not None else "input"


def repair_nonfinite(ct: Volume, path=None) -> tuple[Volume, dict]:
    """Replace NaN/Inf CT voxels by the mean of their finite 26-neighbours (volume median where none).

    Errors when every voxel, or more than ``MAX_NONFINITE_FRACTION`` of them, is non-finite.
    """
    data = np.asarray(ct.data)
    if data.dtype.kind not in "fc":
        return ct, {}
    bad = ~np.isfinite(data)
    n = int(bad.sum())
    if n == 0:
        return ct, {}
    if n == data.size:
        raise InputError(f"{_where(path)}: every voxel is NaN or Inf: no intensities to segment")
    if n > MAX_NONFINITE_FRACTION * data.size:
        raise InputError(f"{_where(path)}: {n} voxels ({100.0 * n / data.size:.2f} %) are NaN or Inf "
                         f"(at most {100 * MAX_NONFINITE_FRACTION:g} % are repaired): a corrupt volume")
    good = np.where(bad, 0.0, data).astype(np.float64)
    k = np.ones((3, 3, 3))
    s = ndi.convolve(good, k, mode="nearest")
    c = ndi.convolve((~bad).astype(np.float64), k, mode="nearest")
    fill = np.where(c > 0, s / np.maximum(c, 1), float(np.median(data[~bad])))
    out = np.array(data, dtype=np.float32 if data.dtype.itemsize <= 4 else np.float64)
    out[bad] = fill[bad]
    rule = (f"{n} non-finite voxels (NaN/Inf) set to the mean of their finite 26-neighbours "
            "(the volume median where none)")
    return ct.with_data(out), {"nonfinite_voxels_repaired": n, "repairs": [rule]}


def check_ct(ct: Volume, path=None) -> tuple[Volume, dict]:
    """A CT in Hounsfield units: affine valid, not a binary mask, air present; non-finite voxels repaired."""
    check_affine(ct.affine, path)
    ct, report = repair_nonfinite(ct, path)
    data = np.asarray(ct.data)
    lo, hi = float(data.min()), float(data.max())
    values = np.unique(data[:: max(1, data.size // 2_000_000)]) if data.size else np.array([])
    if values.size == 1 and lo == hi:
        raise InputError(f"{_where(path)}: every voxel is {lo:g}: a blank image, not a CT")
    if values.size <= 2 and lo >= 0:
        raise InputError(f"{_where(path)}: values {values.tolist()} look like a binary mask, not a CT in HU: "
                         "give it as `kind: mask`")
    if lo > -500.0:
        raise InputError(f"{_where(path)}: intensities {lo:g}..{hi:g} are not Hounsfield units (air is ~-1000 HU, "
                         "nothing here is below -500): apply the scanner's rescale slope/intercept")
    return ct, report


def _mask_values(data: np.ndarray) -> np.ndarray:
    step = max(1, data.size // 4_000_000)
    vals = np.unique(data.ravel()[::step])
    return vals


def binarise_mask(vol: Volume, path=None, label: float | None = None, threshold: float | None = None
                  ) -> tuple[np.ndarray, dict]:
    """The lumen as a boolean array: binary {0, v} as given, ``label`` picks one label, ``threshold`` cuts a map.

    A probability map (non-integer values) without ``mask_threshold``, a label map (more than two values)
    without ``mask_label``, a CT given as a mask and non-finite values are errors.
    """
    where = _where(path)
    data = np.asarray(vol.data)
    if data.dtype.kind not in "biuf":
        raise InputError(f"{where}: voxel type {data.dtype} is not a mask")
    if data.dtype.kind == "f" and not np.isfinite(data).all():
        n = int((~np.isfinite(data)).sum())
        raise InputError(f"{where}: {n} mask voxels are NaN or Inf: a corrupt mask")
    vals = _mask_values(data)
    lo, hi = float(data.min()), float(data.max())
    report: dict = {"mask_values": int(vals.size) if vals.size > 2 else [float(v) for v in vals]}
    if label is not None and threshold is not None:
        raise InputError(f"{where}: give mask_label or mask_threshold, not both")
    if label is not None:
        out = data == label
        if not out.any():
            raise InputError(f"{where}: no voxel has mask_label {label:g} (values {lo:g}..{hi:g})")
        report["mask_rule"] = f"voxels == {label:g} (mask_label)"
        return out, report
    if threshold is not None:
        out = data >= threshold
        report["mask_rule"] = f"voxels >= {threshold:g} (mask_threshold)"
        if not out.any():
            raise InputError(f"{where}: no voxel reaches mask_threshold {threshold:g} (values {lo:g}..{hi:g})")
        return out, report
    if lo < -100.0 and vals.size > 16:
        raise InputError(f"{where}: values {lo:g}..{hi:g} ({'many' if vals.size >= _MAX_LABELS else vals.size} "
                         "distinct) look like a CT in HU, not a mask: give it as `kind: ct`")
    if lo < 0:
        raise InputError(f"{where}: negative mask values ({lo:g}): not a binary mask; name the lumen label with "
                         "mask_label")
    integral = data.dtype.kind in "biu" or bool(np.all(vals == np.round(vals)))
    if not integral:
        raise InputError(f"{where}: non-integer values in {lo:g}..{hi:g} ({vals.size} distinct sampled): a "
                         "probability map; set mask_threshold in the patient entry (e.g. 0.5)")
    nonzero = vals[vals != 0]
    if nonzero.size > 1:
        shown = ", ".join(f"{v:g}" for v in nonzero[:8]) + (", ..." if nonzero.size > 8 else "")
        raise InputError(f"{where}: a label map (labels {shown}), not a binary mask: set mask_label in the "
                         "patient entry to the airway label")
    report["mask_rule"] = "voxels > 0 (binary mask)"
    return data > 0, report


def _section_stats(sl: np.ndarray, px_mm2: float) -> tuple[int, float, float]:
    """(number of 8-connected blobs, equivalent diameter mm and roundness of the largest) of one 2-D slice."""
    lab, n = ndi.label(sl, np.ones((3, 3), bool))
    if n == 0:
        return 0, 0.0, 0.0
    sizes = np.bincount(lab.ravel())[1:]
    k = int(np.argmax(sizes)) + 1
    ii, jj = np.nonzero(lab == k)
    area = float(sizes[k - 1]) * px_mm2
    if ii.size < 3:
        return n, 2.0 * np.sqrt(area / np.pi), 0.0
    cov = np.cov(np.stack([ii, jj]).astype(np.float64))
    ev = np.linalg.eigvalsh(cov)
    rnd = float(np.sqrt(max(ev[0], 0.0) / ev[1])) if ev[1] > 0 else 0.0
    return n, 2.0 * np.sqrt(area / np.pi), rnd


def trachea_run(mask: np.ndarray, spacing_mm: np.ndarray, axis: int, from_end: bool) -> tuple[float, float]:
    """(length in mm, median equivalent diameter in mm) of the tube of single, round (>= 0.5) blobs of
    trachea calibre that starts at one end of ``mask`` along ``axis`` (only slices with 1-3 blobs, largest
    one round and 8-30 mm across, count)."""
    n = mask.shape[axis]
    order = range(n - 1, -1, -1) if from_end else range(n)
    others = [a for a in range(3) if a != axis]
    px = float(spacing_mm[others[0]] * spacing_mm[others[1]])
    length, diam, started, misses = 0.0, [], False, 0
    for i in order:
        sl = np.take(mask, i, axis=axis)
        if not sl.any():
            if started:
                break
            continue
        started = True
        blobs, d, rnd = _section_stats(sl, px)
        if blobs <= 3 and TRACHEA_DIAMETER_MM[0] <= d <= TRACHEA_DIAMETER_MM[1] and rnd >= 0.5:
            length += float(spacing_mm[axis])
            diam.append(d)
            misses = 0
            if length >= 3 * _TRACHEA_RUN_MM:
                break
        else:
            misses += 1
            if misses * spacing_mm[axis] > 5.0:     # larynx or a cut edge at the very top: allow 5 mm
                break
    return length, (float(np.median(diam)) if diam else 0.0)


@dataclasses.dataclass
class MaskCheck:
    mask: Volume
    report: dict


#: a second piece at least this fraction of the largest is a second airway tree, not debris (the fraction of
#: the cut cross-section's separate airways in trachea_root._cut_entry; a lung's bronchial tree holds roughly
#: 40-60 % of the airway volume, airway-model islands a few voxels each)
SECOND_TREE_FRACTION = 0.2


def second_tree_at_top(lab: np.ndarray, sizes: np.ndarray, keep: int, affine: np.ndarray,
                       shape: tuple[int, ...], box: tuple[slice, ...] | None = None) -> str | None:
    """Why the scan holds no trachea, or None: the largest piece ``keep`` and another of at least
    ``SECOND_TREE_FRACTION`` of its voxels both reach the volume's most superior slice (world +z).  That is a
    scan cut below the carina, both main bronchi open at its top; keeping the largest would start the route in
    a main bronchus.  ``lab`` holds the pieces' labels over ``box`` of a volume of ``shape`` (default: all)."""
    ax = int(np.argmax(np.abs(affine[2, :3])))
    top = shape[ax] - 1 if affine[2, ax] > 0 else 0
    start = box[ax].start if box is not None else 0
    if not start <= top < start + lab.shape[ax]:
        return None                                       # no lumen on the top slice
    on_top = np.unique(np.take(lab, top - start, axis=ax))
    big = [int(c) for c in on_top if c and c != keep and sizes[c] >= SECOND_TREE_FRACTION * sizes[keep]]
    if keep not in on_top or not big:
        return None
    return (f"the scan's top slice cuts {1 + len(big)} separate airway trees ({int(sizes[keep])} and "
            f"{int(sizes[big[0]])} voxels): cut below the carina, no trachea to start the route in")


def check_mask(vol: Volume, path=None, label: float | None = None, threshold: float | None = None,
               given: bool = True) -> MaskCheck:
    """Check and binarise an airway lumen mask (given by the user, or ``given=False``: segmented from a CT).

    Returns the largest 26-connected piece as uint8 0/1 and a report of what was measured and repaired.
    """
    where = _where(path)
    check_affine(vol.affine, path)
    if given:
        binary, report = binarise_mask(vol, path, label, threshold)
    else:
        binary, report = np.asarray(vol.data) > 0, {}
    n_fg = int(binary.sum())
    if n_fg == 0:
        raise InputError(f"{where}: the airway mask is empty (no lumen voxel)")
    frac = n_fg / binary.size
    spacing_mm = vol.spacing / MM
    voxel_ml = float(np.prod(spacing_mm)) / 1000.0
    if frac > MAX_FOREGROUND_FRACTION:
        raise InputError(f"{where}: the lumen fills {100 * frac:.1f} % of the volume ({n_fg * voxel_ml:.0f} ml): "
                         "an inverted (background = 1) or all-ones mask, not an airway lumen")
    # components on the lumen's bounding box only (int32 labels of a whole 512x512x700 scan are 0.7 GB)
    box = tuple(slice(int(np.flatnonzero(binary.any(axis=tuple(b for b in range(3) if b != a)))[0]),
                      int(np.flatnonzero(binary.any(axis=tuple(b for b in range(3) if b != a)))[-1]) + 1)
                for a in range(3))
    lab, n = ndi.label(binary[box], np.ones((3, 3, 3), bool))
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    keep = int(np.argmax(sizes))
    kept = int(sizes[keep])
    repairs = list(report.pop("repairs", []))
    cut = second_tree_at_top(lab, sizes, keep, vol.affine, binary.shape, box)
    if cut:
        raise InputError(f"{where}: {cut}")
    if n > 1:
        share = kept / n_fg
        if share < MIN_LARGEST_PIECE_FRACTION:
            raise InputError(f"{where}: the airway tree is broken into {n} pieces; the largest holds only "
                             f"{100 * share:.0f} % of the lumen (at least {100 * MIN_LARGEST_PIECE_FRACTION:.0f} % "
                             "needed to keep it): reconnect the segmentation")
        repairs.append(f"kept the largest of {n} 26-connected pieces ({100 * share:.1f} % of the lumen); "
                       f"dropped {n_fg - kept} voxels in {n - 1} pieces")
    sub_keep = lab == keep
    del lab
    volume_ml = kept * voxel_ml
    idx = np.nonzero(sub_keep)
    off = np.array([b.start for b in box])
    lo = np.array([int(i.min()) for i in idx]) + off
    hi = np.array([int(i.max()) for i in idx]) + 1 + off
    del idx
    out = np.zeros(binary.shape, np.uint8)      # the result, written once (no bool copy of the scan kept)
    out[box] = sub_keep
    del sub_keep
    corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    world = (corners @ vol.affine[:3, :3].T) / MM
    extent = world.max(axis=0) - world.min(axis=0)
    crop = out[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].astype(bool)
    report.update({"components": int(n), "kept_voxels": kept, "dropped_voxels": int(n_fg - kept),
                   "lumen_volume_ml": round(volume_ml, 3), "extent_mm": np.round(extent, 1).tolist()})
    if kept < 50 or volume_ml < MIN_VOLUME_ML:
        raise InputError(f"{where}: the airway lumen holds {kept} voxels ({volume_ml:.3g} ml; a human airway "
                         f"tree holds {MIN_VOLUME_ML:g}-{MAX_VOLUME_ML:g} ml): too small to be an airway tree")
    if volume_ml > MAX_VOLUME_ML:
        raise InputError(f"{where}: the airway lumen holds {volume_ml:.0f} ml (human airway trees hold "
                         f"{MIN_VOLUME_ML:g}-{MAX_VOLUME_ML:g} ml): wrong label, wrong voxel spacing in the header "
                         f"({np.round(spacing_mm, 3).tolist()} mm) or not an airway mask")
    if (extent > MAX_EXTENT_MM).any():
        raise InputError(f"{where}: the airway tree spans {np.round(extent).tolist()} mm (a thorax is < "
                         f"{MAX_EXTENT_MM:g} mm across): the header's voxel spacing "
                         f"{np.round(spacing_mm, 3).tolist()} mm disagrees with the anatomy")
    # largest inscribed radius (EDT inside the lumen, on the bounding box; every 2nd voxel on big boxes)
    step = 2 if crop.size > 40_000_000 else 1
    sub = np.pad(crop[::step, ::step, ::step], 1)
    r_max = float(ndi.distance_transform_edt(sub, sampling=spacing_mm * step).max())
    report["inscribed_radius_max_mm"] = round(r_max, 2)
    if r_max > MAX_INSCRIBED_RADIUS_MM:
        raise InputError(f"{where}: the widest lumen has an inscribed radius of {r_max:.1f} mm (human airways: "
                         f"<= {MAX_INSCRIBED_RADIUS_MM:g} mm): not an airway lumen or wrong voxel spacing")
    # the trachea: a tube of trachea calibre entering from the superior end of the tree
    sup_axis, sup_sign = vol.superior_axis()
    runs = {(a, e): trachea_run(crop, spacing_mm, a, e) for a in range(3) for e in (False, True)}
    header = runs[(sup_axis, sup_sign > 0)]
    best_key = max(runs, key=lambda k: runs[k][0])
    best = runs[best_key]
    report["trachea_length_mm"] = round(header[0], 1)
    report["trachea_diameter_mm"] = round(header[1], 1)
    if header[0] < _TRACHEA_RUN_MM and best[0] >= 2 * _TRACHEA_RUN_MM and best_key[0] != sup_axis:
        raise InputError(
            f"{where}: the trachea ({best[1]:.0f} mm across, {best[0]:.0f}+ mm long) runs along array axis "
            f"{best_key[0]}, but the header puts superior along axis {sup_axis}: the array's axes disagree with "
            "its header (e.g. a (z, x, y) array under an (x, y, z) header); transpose the array to match")
    flipped = runs[(sup_axis, sup_sign < 0)]
    if header[0] < _TRACHEA_RUN_MM and flipped[0] >= 2 * _TRACHEA_RUN_MM and best_key == (sup_axis, sup_sign < 0):
        raise InputError(
            f"{where}: the trachea ({flipped[1]:.0f} mm across) enters from the inferior end of array axis {sup_axis}: "
            "the array is upside down relative to its header; flip that axis (or fix the header's direction)")
    if header[0] < _TRACHEA_RUN_MM and not given:
        raise InputError(f"{where}: the segmented air ({volume_ml:.1f} ml) has no trachea-calibre tube "
                         f"({TRACHEA_DIAMETER_MM[0]:g}-{TRACHEA_DIAMETER_MM[1]:g} mm across, >= {_TRACHEA_RUN_MM:g} mm "
                         "long) at its superior end: not an airway tree (a scan without the trachea?)")
    if not given and volume_ml < MIN_CT_TREE_VOLUME_ML:
        raise InputError(f"{where}: the air found holds {volume_ml:.1f} ml ({' x '.join(f'{e:.0f}' for e in extent)} "
                         f"mm); a chest CT's airway tree holds >= {MIN_CT_TREE_VOLUME_ML:g} ml (the intrathoracic "
                         "trachea alone): an air pocket, not an airway tree (is the chest in the scan?)")
    if not given:      # air segmented from a CT: an airway tree branches (an air pocket does not)
        most = max(ndi.label(np.take(crop, i, axis=sup_axis), np.ones((3, 3), bool))[1]
                   for i in range(crop.shape[sup_axis]))
        if most < 2:
            raise InputError(f"{where}: the air found ({volume_ml:.1f} ml, {' x '.join(f'{e:.0f}' for e in extent)} mm) "
                             "never branches: a single air pocket, not an airway tree (is the chest in the scan?)")
    if header[0] < _TRACHEA_RUN_MM:
        report["warnings"] = [f"no trachea-calibre tube ({TRACHEA_DIAMETER_MM[0]:g}-{TRACHEA_DIAMETER_MM[1]:g} mm) "
                              f"found at the superior end (longest {header[0]:.0f} mm)"]
    report["repairs"] = repairs
    return MaskCheck(Volume(out, vol.affine.copy()), report)
