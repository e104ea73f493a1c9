"""Accuracy of segment, sdf and mesh against the phantom's exact tree (the `validate_anatomy` stage's domain code).

Two halves that share nothing but the tree, so they run side by side on two workers of the executor
(:mod:`room_pipeline.execution`; a single-threaded stage otherwise leaves one of two cores idle):

* :func:`volume_accuracy`: the segmentation against the true mask, and the SDF fed the true mask
  (isolation) and the product's SDF (end to end) against the tree's exact signed distance;
* :func:`mesh_accuracy`: the surface extracted from the analytic SDF sampled on the grid (isolation) and the
  product's mesh (end to end) against the tree's exact surface.

Each half reads its own inputs (file paths in, a metrics dict out: nothing large crosses a process boundary) and
computes the part of :class:`~room_pipeline.evaluate.surface.TreeTruth` it needs (the grid band, or the surface
samples), so the work is the same as in one process and the figures are identical with any backend or worker
count (tests/test_validate_anatomy_parallel.py).  Distances in metres (``*_m``) and voxels (``*_vox``).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

#: the SDF accuracy bound is stated "within 3 mm of the wall"
SDF_BAND_M = 3e-3


@dataclasses.dataclass(frozen=True)
class ValidationInputs:
    """The files one validation reads (paths) and the stage parameters it re-runs (``sdf`` / ``mesh`` sections)."""

    gt_tree: Path
    gt_mask: Path
    gt_sdf: Path
    airway_mask: Path
    sdf: Path
    mesh: Path
    sdf_params: dict
    mesh_params: dict


def _tree(inputs: ValidationInputs):
    from ..anatomy.tree import AirwayTree
    from ..io.jsondoc import read_json

    return AirwayTree.from_dict(read_json(inputs.gt_tree))


def _true_mask(inputs: ValidationInputs):
    from ..io.volume import read_volume

    gt = read_volume(inputs.gt_mask)
    return gt.with_data(np.asarray(gt.data) > 0)


def volume_accuracy(inputs: ValidationInputs) -> dict:
    """``{"segment": ..., "sdf": {"isolation": ..., "end_to_end": ...}}``."""
    from ..anatomy.sdf import SdfParams, compute_sdf
    from ..io.volume import read_nifti_sdf, read_volume
    from .segmentation import segmentation_metrics
    from .surface import TreeTruth, sdf_error

    tree = _tree(inputs)
    gt_mask = _true_mask(inputs)
    pred = read_volume(inputs.airway_mask)
    pred = pred.with_data(np.asarray(pred.data) > 0)
    seg = segmentation_metrics(pred, gt_mask, tree)
    seg.pop("branch_coverage", None)          # per-capsule detail: too long for a metrics file
    truth = TreeTruth(tree)                   # the grid band: computed once for both SDFs
    sdf_iso = sdf_error(compute_sdf(gt_mask, SdfParams.from_dict(inputs.sdf_params)), tree, SDF_BAND_M, truth)
    sdf_e2e = sdf_error(read_nifti_sdf(inputs.sdf), tree, SDF_BAND_M, truth)
    return {"segment": seg, "sdf": {"isolation": sdf_iso, "end_to_end": sdf_e2e}}


def mesh_accuracy(inputs: ValidationInputs) -> dict:
    """``{"voxel_size_m": ..., "mesh": {"isolation": ..., "end_to_end": ...}}`` (voxel: the true mask's finest
    spacing, the unit of the mesh bounds)."""
    from ..anatomy.mesh import MeshParams, extract_surface, mesh_topology
    from ..io.mesh import read_obj
    from ..io.volume import read_nifti_sdf
    from .surface import TreeTruth, mesh_surface_distance

    tree = _tree(inputs)
    voxel = float(_true_mask(inputs).spacing.min())
    truth = TreeTruth(tree)                   # the surface samples: computed once for both meshes
    iso = extract_surface(read_nifti_sdf(inputs.gt_sdf), MeshParams.from_dict(inputs.mesh_params))
    mesh_iso = mesh_surface_distance(iso.mesh, tree, voxel, truth)
    mesh_iso["n_faces"] = iso.mesh.n_faces
    mesh_iso["watertight"] = bool(iso.report.get("watertight"))
    product = read_obj(inputs.mesh)
    mesh_e2e = mesh_surface_distance(product, tree, voxel, truth)
    mesh_e2e["watertight"] = bool(mesh_topology(product)["watertight"])
    return {"voxel_size_m": voxel, "mesh": {"isolation": mesh_iso, "end_to_end": mesh_e2e}}


#: automatic workers: the second worker only for a true mask of at least this many voxels.  A spawned worker costs
#: a few CPU s to start and import the anatomy stack; the default phantom (379 x 221 x 370 voxels at 0.7 mm, 31 M)
#: runs for about a minute (its ``metrics/anatomy_validation.timing.json``), so its halves are worth it, while the
#: test suite's small phantoms are not.
MIN_VOXELS_FOR_TWO_WORKERS = 8_000_000


def workers_for(execution: dict | None, n_voxels: int) -> int:
    """Workers for the two halves: explicit ``execution.workers`` kept (at most 2); ``0`` (automatic): one per
    usable core, at most 2, and 1 below :data:`MIN_VOXELS_FOR_TWO_WORKERS` voxels of the true mask."""
    from ..execution import ExecutionParams

    params = ExecutionParams.from_dict(execution or {})
    if params.workers > 0:
        return min(params.workers, 2)
    if n_voxels < MIN_VOXELS_FOR_TWO_WORKERS:
        return 1
    return min(params.resolved().workers, 2)


def _half(state, job: tuple[str, ValidationInputs]) -> dict:
    name, inputs = job
    return {"volumes": volume_accuracy, "meshes": mesh_accuracy}[name](inputs)


def validate_anatomy(inputs: ValidationInputs, execution: dict | None = None) -> dict:
    """Both halves through the executor of ``execution`` (conf/execution; workers: :func:`workers_for`) and their figures merged, with ``checks``: each bound of the issue (isolation figures) as
    true / false.  ``voxel_size_mm``: the true mask's finest spacing."""
    from ..execution import ExecutionParams, make_executor
    from ..io.volume import read_volume

    n_voxels = int(np.prod(read_volume(inputs.gt_mask).shape))
    params = dataclasses.replace(ExecutionParams.from_dict(execution or {}),
                                 workers=workers_for(execution, n_voxels), chunk_size=1)
    with make_executor(params) as ex:
        vol, mesh = ex.map(_half, [("volumes", inputs), ("meshes", inputs)], desc="validate_anatomy")
    seg, sdf, mesh_iso, mesh_e2e = vol["segment"], vol["sdf"], mesh["mesh"]["isolation"], mesh["mesh"]["end_to_end"]
    checks = {name: bool(ok) for name, ok in (
        ("segment_dice_ge_0.90", seg["dice"] >= 0.90),
        ("segment_precision_ge_0.95", seg["precision"] >= 0.95),
        ("segment_td_ge_0.85", seg["tree_length_detected"] >= 0.85),
        ("segment_bd_ge_0.80", seg["branches_detected"] >= 0.80),
        ("sdf_isolation_mae_le_0.25_voxel", sdf["isolation"]["mae_vox"] <= 0.25),
        ("mesh_isolation_mean_le_0.15_voxel", mesh_iso["mean_vox"] <= 0.15),
        ("mesh_isolation_p95_le_0.5_voxel", mesh_iso["p95_vox"] <= 0.5),
        ("mesh_watertight", mesh_iso["watertight"] and mesh_e2e["watertight"]),
    )}
    return {"checks": checks, "voxel_size_mm": mesh["voxel_size_m"] * 1e3, "segment": seg, "sdf": sdf,
            "mesh": mesh["mesh"]}
