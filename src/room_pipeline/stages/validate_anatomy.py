"""Stage `validate_anatomy`: accuracy of segment, sdf and mesh against the phantom's exact ground truth.

Each stage is measured twice (the issue's protocol):

* **isolation**: fed the ground-truth input (segment: the phantom CT; sdf: the
  true mask; mesh: the analytic SDF sampled on the grid);
* **end to end**: the outputs the pipeline actually produced from the CT.

``checks`` records each bound of the issue (isolation figures) as true/false.
"""
from __future__ import annotations

import numpy as np
from omegaconf import DictConfig

from ..anatomy.mesh import MeshParams, extract_surface, mesh_topology
from ..anatomy.sdf import SdfParams, compute_sdf
from ..anatomy.tree import AirwayTree
from ..config.compose import section
from ..evaluate.segmentation import segmentation_metrics
from ..evaluate.surface import TreeTruth, mesh_surface_distance, sdf_error
from ..io.mesh import read_obj
from ..io.volume import read_nifti_sdf, read_volume
from .common import StageTimer, patient_paths, read_json, round_floats, write_metrics

#: the SDF accuracy bound is stated "within 3 mm of the wall"
SDF_BAND_M = 3e-3


def outputs(cfg: DictConfig, patient: str) -> list:
    return [patient_paths(cfg, patient).stage_metrics("validate_anatomy")]



def run(cfg: DictConfig, patient: str) -> dict:
    paths = patient_paths(cfg, patient)
    with StageTimer() as timer:
        tree = AirwayTree.from_dict(read_json(paths.gt_tree))
        gt_mask = read_volume(paths.gt_mask)
        gt_mask = gt_mask.with_data(np.asarray(gt_mask.data) > 0)
        voxel = float(gt_mask.spacing.min())
        pred_mask = read_volume(paths.airway_mask)
        pred_mask = pred_mask.with_data(np.asarray(pred_mask.data) > 0)
        seg = segmentation_metrics(pred_mask, gt_mask, tree)
        seg.pop("branch_coverage", None)  # per-capsule detail: too long for a metrics file

        sdf_params = SdfParams.from_dict(section(cfg, "sdf"))
        truth = TreeTruth(tree)             # the tree's exact values, computed once for both comparisons
        sdf_iso = sdf_error(compute_sdf(gt_mask, sdf_params), tree, SDF_BAND_M, truth)
        sdf_e2e = sdf_error(read_nifti_sdf(paths.sdf), tree, SDF_BAND_M, truth)

        mesh_params = MeshParams.from_dict(section(cfg, "mesh"))
        gt_sdf = read_nifti_sdf(paths.gt_sdf)
        mesh_iso_res = extract_surface(gt_sdf, mesh_params)
        mesh_iso = mesh_surface_distance(mesh_iso_res.mesh, tree, voxel, truth)
        mesh_iso["n_faces"] = mesh_iso_res.mesh.n_faces
        mesh_iso["watertight"] = bool(mesh_iso_res.report.get("watertight"))
        product_mesh = read_obj(paths.mesh)
        mesh_e2e = mesh_surface_distance(product_mesh, tree, voxel, truth)
        mesh_e2e["watertight"] = bool(mesh_topology(product_mesh)["watertight"])
    checks = {name: bool(ok) for name, ok in (
        ("segment_dice_ge_0.90", seg["dice"] >= 0.90),
        ("segment_precision_ge_0.95", seg["precision"] >= 0.95),
        ("segment_td_ge_0.85", seg["tree_length_detected"] >= 0.85),
        ("segment_bd_ge_0.80", seg["branches_detected"] >= 0.80),
        ("sdf_isolation_mae_le_0.25_voxel", sdf_iso["mae_vox"] <= 0.25),
        ("mesh_isolation_mean_le_0.15_voxel", mesh_iso["mean_vox"] <= 0.15),
        ("mesh_isolation_p95_le_0.5_voxel", mesh_iso["p95_vox"] <= 0.5),
        ("mesh_watertight", mesh_iso["watertight"] and mesh_e2e["watertight"]),
    )}
    metrics = round_floats({
        "checks": checks,
        "voxel_size_mm": voxel * 1e3,
        "segment": seg,
        "sdf": {"isolation": sdf_iso, "end_to_end": sdf_e2e},
        "mesh": {"isolation": mesh_iso, "end_to_end": mesh_e2e},
        "wall_time_s": timer.wall_s, "peak_rss_mb": timer.peak_rss_mb(),
    })
    write_metrics(paths, "validate_anatomy", metrics)
    return metrics
