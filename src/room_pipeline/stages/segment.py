"""Stage `segment`: CT -> airway lumen mask (or check a given mask), plus ``ct_metadata.json``.

Both inputs are checked for plausibility before any work (:mod:`room_pipeline.anatomy.plausibility`):
a bad input ends in one error line naming the file; a repair (non-finite CT voxels, dropped pieces of a
mask) is stated in ``ct_metadata.json`` (``plausibility``) and ``metrics/segment.json`` (``repairs``).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from ..anatomy.plausibility import check_ct, check_mask
from ..anatomy.segment import SegmentParams, segment_airways
from ..config.compose import patient_entry, section
from ..errors import InputError
from ..io.atomic import write_json
from ..io.volume import read_volume, write_nifti
from ..io.hashing import sha256_file
from .common import StageTimer, metadata, patient_paths, write_metrics


def outputs(cfg: DictConfig, patient: str) -> list:
    p = patient_paths(cfg, patient)
    return [p.airway_mask, p.ct_metadata]


def source_path(path: str, output_dir: str) -> str:
    """The input path as written in the metadata: relative to output_dir (``${output_dir}/...``) when inside it,
    so the same data in another output_dir gives the same bytes."""
    p, root = Path(os.path.abspath(path)), Path(os.path.abspath(output_dir))
    try:
        return "${output_dir}/" + p.relative_to(root).as_posix()
    except ValueError:
        return str(path)


def run(cfg: DictConfig, patient: str) -> dict:
    entry = patient_entry(cfg, patient)
    params = SegmentParams.from_dict(section(cfg, "segment"))
    paths = patient_paths(cfg, patient)
    src = str(entry["input"])
    with StageTimer() as timer:
        vol = read_volume(src)
        source = {"kind": entry["kind"], "path": source_path(src, cfg.output_dir), "sha256": sha256_file(src),
                  **vol.info}
        if entry["kind"] == "ct":
            vol, ct_report = check_ct(vol, src)
            try:
                res = segment_airways(vol, params)
            except InputError as exc:                   # name the file the reason is about
                raise InputError(f"{src}: {exc}") from None
            checked = check_mask(res.mask, f"{src} (segmented airway)", given=False)
            report = dict(res.report, seed_voxel=list(map(int, res.seed)), threshold_hu=float(res.threshold_hu))
            data = np.asarray(vol.data, dtype=np.float64)
            intensity = {"hu_min": float(data.min()), "hu_max": float(data.max()), "hu_mean": float(data.mean())}
            plaus = dict(checked.report, repairs=ct_report.get("repairs", []) + checked.report["repairs"])
        else:
            checked = check_mask(vol, src, entry.get("mask_label"), entry.get("mask_threshold"))
            report, intensity, plaus = {"method": "given mask (segmentation skipped)"}, {}, checked.report
        mask = checked.mask
    n = int(mask.data.sum())
    voxel_ml = float(np.prod(mask.spacing)) * 1e6
    meta = metadata("segment", patient, cfg, ("segment",), source=source,
                    shape=list(vol.shape), spacing_m=vol.spacing.tolist(), affine_m=vol.affine.tolist(),
                    intensity=intensity, segmentation=report, plausibility=plaus)
    write_nifti(paths.airway_mask, mask.with_data(mask.data.astype(np.uint8)),
                description="room airway lumen mask, 1 = lumen")
    write_json(paths.ct_metadata, meta)
    metrics = {"lumen_voxels": n, "lumen_volume_ml": round(n * voxel_ml, 4), "repairs": len(plaus["repairs"]),
               "wall_time_s": round(timer.wall_s, 3), "peak_rss_mb": round(timer.peak_rss_mb(), 1)}
    write_metrics(paths, "segment", metrics)
    return metrics
