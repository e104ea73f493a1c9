"""Stage `phantom`: generate the procedural phantom patient's CT and its exact ground truth (its tree grown,
or a measured tree read from a branch table: ``phantoms.<id>.tree``)."""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from ..anatomy.phantom import PhantomParams, make_phantom, rasterise
from ..anatomy.reference_tree import hull_lungs, read_tree_table
from ..errors import InputError
from ..config.compose import phantom_entry, section
from ..io.atomic import write_json
from ..io.volume import write_nifti
from .common import StageTimer, metadata, patient_paths, write_metrics

#: centreline sampling step as a fraction of the smallest voxel size
CENTRELINE_STEP_VOXELS = 0.25
#: a measured tree's lungs: every point this close to a lobar or deeper branch's axis, mm
LUNG_REACH_MM = 15.0


def outputs(cfg: DictConfig, patient: str) -> list:
    p = patient_paths(cfg, patient)
    return [p.phantom_ct, p.ground_truth]


def _reference_tree(entry) -> tuple:
    """The measured tree of ``entry.tree`` after checking its bytes against ``entry.tree_sha256``."""
    path = Path(entry.tree)
    if not path.is_file():
        raise InputError(f"tree table not found: {path}")
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    if digest != entry.tree_sha256:
        raise InputError(f"{path}: sha256 {digest} differs from the config's tree_sha256 {entry.tree_sha256} "
                         f"(the table changed: set tree_sha256 to its new sha256 to use it)")
    return read_tree_table(path, entry.tree_frame), {"tree": str(path), "tree_frame": entry.tree_frame,
                                                     "tree_sha256": digest}


def run(cfg: DictConfig, patient: str) -> dict:
    entry = phantom_entry(cfg, patient)
    seed = entry.seed
    params = PhantomParams.from_dict(section(cfg, "phantom"))
    paths = patient_paths(cfg, patient)
    source: dict = {"tree": "grown", "lungs": "ellipsoids"}
    with StageTimer() as timer:
        if entry.tree is None:
            ph = make_phantom(params, seed=seed)
        else:
            tree, source = _reference_tree(entry)
            source["lungs"] = f"hull: within {LUNG_REACH_MM} mm of a branch of generation >= 2"
            ph = rasterise(tree, params, np.random.default_rng(seed), lungs=hull_lungs(tree, params, LUNG_REACH_MM))
        step = CENTRELINE_STEP_VOXELS * float(ph.ct.spacing.min())
        cl = ph.tree.centreline(step)
    extra = {} if entry.tree is None else {"source": source}
    meta = metadata("phantom", patient, cfg, ("phantom",), seed=seed,
                    shape=list(ph.ct.shape), spacing_m=ph.ct.spacing.tolist(), affine_m=ph.ct.affine.tolist(),
                    n_branches=len(ph.tree), max_generation=ph.tree.max_generation, **extra)
    write_nifti(paths.phantom_ct, ph.ct, description=f"room phantom CT, HU, seed {seed}")
    write_nifti(paths.gt_mask, ph.mask, description="room phantom airway lumen mask")
    write_nifti(paths.gt_sdf, ph.sdf, description="room phantom analytic SDF, mm, <0 in lumen",
                scale_values_to_mm=True)
    write_nifti(paths.gt_sdf_exact, ph.sdf_exact.with_data(ph.sdf_exact.data.astype(np.uint8)),
                description="1 where the analytic SDF is exact")
    write_json(paths.gt_tree, {**ph.tree.to_dict(), "metadata": meta})
    write_json(paths.gt_centreline, {
        "units": "m", "frame": "RAS+", "step_m": step,
        "points": np.round(cl["points"], 9), "radius": np.round(cl["radius"], 9),
        "branch": cl["branch"], "generation": cl["generation"],
        "arclength": np.round(cl["arclength"], 9)})
    write_json(paths.gt_metadata, meta)
    metrics = {"n_branches": len(ph.tree), "max_generation": ph.tree.max_generation,
               "n_voxels": int(np.prod(ph.ct.shape)), "lumen_volume_ml": float(ph.mask.data.sum() * np.prod(ph.ct.spacing) * 1e6),
               "wall_time_s": round(timer.wall_s, 3), "peak_rss_mb": round(timer.peak_rss_mb(), 1)}
    write_metrics(paths, "phantom", metrics)
    return metrics
