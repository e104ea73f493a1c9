"""Stage `segment`: CT -> airway lumen mask (or validate a given mask), plus ``ct_metadata.json``."""
from __future__ import annotations

import numpy as np
from omegaconf import DictConfig

from ..anatomy.segment import SegmentParams, segment_airways, validate_mask
from ..config.compose import patient_entry, section
from ..io.atomic import write_json
from ..io.volume import read_volume, write_nifti
from .common import StageTimer, file_sha256, metadata, patient_paths, write_metrics


def outputs(cfg: DictConfig, patient: str) -> list:
    p = patient_paths(cfg, patient)
    return [p.airway_mask, p.ct_metadata]


def run(cfg: DictConfig, patient: str) -> dict:
    entry = patient_entry(cfg, patient)
    params = SegmentParams.from_dict(section(cfg, "segment"))
    paths = patient_paths(cfg, patient)
    with StageTimer() as timer:
        vol = read_volume(entry["input"])
        source = {"kind": entry["kind"], "path": str(entry["input"]), "sha256": file_sha256(entry["input"])}
        if entry["kind"] == "ct":
            res = segment_airways(vol, params)
            mask, report = res.mask, dict(res.report, seed_voxel=list(map(int, res.seed)),
                                           threshold_hu=float(res.threshold_hu))
            data = np.asarray(vol.data, dtype=np.float64)
            intensity = {"hu_min": float(data.min()), "hu_max": float(data.max()),
                         "hu_mean": float(data.mean())}
        else:
            mask = validate_mask(vol)
            report, intensity = {"method": "given mask (segmentation skipped)"}, {}
    n = int(mask.data.sum())
    voxel_ml = float(np.prod(mask.spacing)) * 1e6
    meta = metadata("segment", patient, cfg, ("segment",), source=source,
                    shape=list(vol.shape), spacing_m=vol.spacing.tolist(), affine_m=vol.affine.tolist(),
                    intensity=intensity, segmentation=report)
    write_nifti(paths.airway_mask, mask.with_data(mask.data.astype(np.uint8)),
                description="room airway lumen mask, 1 = lumen")
    write_json(paths.ct_metadata, meta)
    metrics = {"lumen_voxels": n, "lumen_volume_ml": round(n * voxel_ml, 4),
               "wall_time_s": round(timer.wall_s, 3), "peak_rss_mb": round(timer.peak_rss_mb(), 1)}
    write_metrics(paths, "segment", metrics)
    return metrics
