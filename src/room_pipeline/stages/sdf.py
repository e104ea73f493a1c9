"""Stage `sdf`: airway mask -> signed distance field (``sdf.nii.gz`` in mm, negative inside)."""
from __future__ import annotations

import numpy as np
from omegaconf import DictConfig

from ..anatomy.sdf import SdfParams, compute_sdf
from ..config.compose import section
from ..io.atomic import write_json
from ..io.volume import read_volume, write_nifti
from .common import StageTimer, metadata, patient_paths, write_metrics


def outputs(cfg: DictConfig, patient: str) -> list:
    p = patient_paths(cfg, patient)
    return [p.sdf, p.sdf_metadata]


def run(cfg: DictConfig, patient: str) -> dict:
    params = SdfParams.from_dict(section(cfg, "sdf"))
    paths = patient_paths(cfg, patient)
    with StageTimer() as timer:
        mask = read_volume(paths.airway_mask)
        mask = mask.with_data(np.asarray(mask.data) > 0)  # drop the file's dtype copy: memory
        sdf = compute_sdf(mask, params)
    inside = np.asarray(mask.data)
    s = np.asarray(sdf.data)
    # sign agreement with the mask at voxel centres (sub-voxel surfaces may flip boundary voxels)
    agree = float(np.mean((s[inside] < 0))) if inside.any() else 0.0
    meta = metadata("sdf", patient, cfg, ("sdf",), shape=list(sdf.shape), spacing_m=sdf.spacing.tolist(),
                    value_unit_in_file="mm", min_m=float(s.min()), max_m=float(s.max()))
    write_nifti(paths.sdf, sdf, description="room SDF, mm, <0 inside airway lumen", scale_values_to_mm=True)
    write_json(paths.sdf_metadata, meta)
    metrics = {"max_inscribed_radius_mm": round(float(-s.min()) * 1e3, 4),
               "lumen_voxels_negative_fraction": round(agree, 6),
               "wall_time_s": round(timer.wall_s, 3), "peak_rss_mb": round(timer.peak_rss_mb(), 1)}
    write_metrics(paths, "sdf", metrics)
    return metrics
