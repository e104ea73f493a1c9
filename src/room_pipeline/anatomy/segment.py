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

Modules: :mod:`.segment_params` (the config and the result record), :mod:`.region_growing` (steps 1-5);
this one runs TotalSegmentator, dispatches (:func:`segment_airways`), checks user masks
(:func:`validate_mask`) and re-exports the public names of the other two.
"""
from __future__ import annotations

import dataclasses
import importlib.util
import logging
import os
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from ..conventions import MM
from ..errors import BackendUnavailable, InputError
from ..io.volume import Volume
from .plausibility import second_tree_at_top
from .region_growing import _segment_region_growing, _spacing_mm, _structure
from .segment_params import TS_AIRWAY_NAME, TS_DATASET, TS_TASK, SegmentParams, SegmentResult

# the segmentation's API, importable from here as before the split
from .region_growing import find_trachea_seed  # noqa: F401
from .segment_params import DENOISE, METHODS  # noqa: F401


log = logging.getLogger(__name__)


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
    given).  Raises :class:`InputError` if the mask is empty, or when the scan's top cuts two airway trees
    (:func:`~room_pipeline.anatomy.plausibility.second_tree_at_top`: a scan cut below the carina).
    """
    data = np.asarray(mask.data)
    binary = np.nan_to_num(data.astype(np.float64, copy=False), nan=0.0) > 0 if data.dtype.kind == "f" else data > 0
    if not binary.any():
        raise InputError("airway mask is empty (no voxel > 0)")
    lab, n = ndi.label(binary, _structure(26))
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    keep = int(np.argmax(sizes))
    cut = second_tree_at_top(lab, sizes, keep, mask.affine, lab.shape)
    if cut:
        raise InputError(f"airway mask: {cut}")
    out = (lab == keep).astype(np.uint8)
    dropped = int(sizes.sum() - sizes[keep])
    if n > 1:
        log.warning("airway mask: kept the largest of %d components (%d voxels), dropped %d voxels",
                    n, int(sizes[keep]), dropped)
    if report is not None:
        report.update({"components": int(n), "dropped_components": int(n - 1),
                       "dropped_voxels": dropped, "kept_voxels": int(sizes[keep])})
    return Volume(out, mask.affine.copy())
