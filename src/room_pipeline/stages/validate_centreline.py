"""Stage `validate_centreline`: the medial axis against the phantom's exact centreline.

* **isolation**: medial axis of the phantom's analytic SDF (ground-truth input);
* **end to end**: the ``centreline_graph.json`` the pipeline produced from the CT.

The truth is :func:`room_pipeline.anatomy.centreline.from_airway_tree` of the
phantom's capsule tree.  ``checks`` records the issue's bounds (isolation).
"""
from __future__ import annotations

from omegaconf import DictConfig

from ..anatomy.centreline import CentrelineGraph, from_airway_tree
from ..anatomy.medial_axis import MedialAxisParams, extract_medial_axis
from ..anatomy.tree import AirwayTree
from ..config.compose import section
from ..evaluate.centreline import centreline_metrics
from ..io.volume import read_nifti_sdf
from .common import StageTimer, patient_paths, read_json, round_floats, write_metrics


def outputs(cfg: DictConfig, patient: str) -> list:
    return [patient_paths(cfg, patient).stage_metrics("validate_centreline")]



def run(cfg: DictConfig, patient: str) -> dict:
    paths = patient_paths(cfg, patient)
    with StageTimer() as timer:
        tree = AirwayTree.from_dict(read_json(paths.gt_tree))
        gt_sdf = read_nifti_sdf(paths.gt_sdf)
        voxel = float(gt_sdf.spacing.min())
        truth = from_airway_tree(tree, voxel / 4)
        params = MedialAxisParams.from_dict(section(cfg, "medial_axis"))
        iso = centreline_metrics(extract_medial_axis(gt_sdf, params).graph, truth, voxel)
        e2e = centreline_metrics(CentrelineGraph.from_dict(read_json(paths.centreline_graph)), truth, voxel)
    checks = {
        "mean_distance_le_0.5_voxel": iso.get("dist_ext_to_true_mean_vox", float("inf")) <= 0.5,
        "detection_large_ge_0.95": iso.get("detection_rate_large", 0.0) >= 0.95,
        "spurious_le_0.05": iso.get("spurious_fraction", 1.0) <= 0.05,
        "median_bifurcation_error_le_1mm": iso.get("bifurcation_error_median_m", float("inf")) <= 1e-3,
    }
    metrics = round_floats({"checks": checks, "isolation": iso, "end_to_end": e2e,
                      "wall_time_s": timer.wall_s, "peak_rss_mb": timer.peak_rss_mb()})
    write_metrics(paths, "validate_centreline", metrics)
    return metrics
