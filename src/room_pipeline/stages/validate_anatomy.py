"""Stage `validate_anatomy`: accuracy of segment, sdf and mesh against the phantom's exact ground truth.

Each stage is measured twice (the issue's protocol):

* **isolation**: fed the ground-truth input (segment: the phantom CT; sdf: the
  true mask; mesh: the analytic SDF sampled on the grid);
* **end to end**: the outputs the pipeline actually produced from the CT.

``checks`` records each bound of the issue (isolation figures) as true/false.  The volume and mesh halves run
side by side on the executor's workers (:mod:`room_pipeline.evaluate.anatomy_validation`).
"""
from __future__ import annotations

from omegaconf import DictConfig

from ..config.compose import section
from ..evaluate.anatomy_validation import ValidationInputs, validate_anatomy
from .common import StageTimer, patient_paths, round_floats, write_metrics


def outputs(cfg: DictConfig, patient: str) -> list:
    return [patient_paths(cfg, patient).stage_metrics("validate_anatomy")]


def run(cfg: DictConfig, patient: str) -> dict:
    paths = patient_paths(cfg, patient)
    inputs = ValidationInputs(gt_tree=paths.gt_tree, gt_mask=paths.gt_mask, gt_sdf=paths.gt_sdf,
                              airway_mask=paths.airway_mask, sdf=paths.sdf, mesh=paths.mesh,
                              sdf_params=section(cfg, "sdf"), mesh_params=section(cfg, "mesh"))
    with StageTimer() as timer:
        metrics = validate_anatomy(inputs, section(cfg, "execution"))
    metrics = round_floats({**metrics, "wall_time_s": timer.wall_s, "peak_rss_mb": timer.peak_rss_mb()})
    write_metrics(paths, "validate_anatomy", metrics)
    return metrics
