"""The output layout (the ROOM paper's): patient-level files; names inside a sequence live in
:mod:`room_pipeline.catalog`.

``<output_dir>/<patient>/``
    ``input/ct.nii.gz``                 phantom CT (phantom patients only)
    ``ground_truth/``                   phantom ground truth (mask, analytic SDF, tree, centreline)
    ``anatomy/ct_metadata.json``        source, grid, affine, HU statistics, segmentation report
    ``anatomy/airway_mask.nii.gz``      airway lumen mask (uint8, 1 = lumen)
    ``anatomy/sdf.nii.gz``              signed distance, mm, negative inside the lumen
    ``anatomy/lung_model.obj``          watertight lumen surface, metres
    ``anatomy/medial_axis.ply``         medial points with radius, polyline edges
    ``anatomy/centreline_graph.json``   navigation tree (branches, parents, generations, radii)
    ``sequence_YYY/metadata/``          trajectory.json, timestamps.json, trajectory_tum.txt
    ``sequence_index/<sequence>.{render,noise}.json``  sha256 of the frames the depth CNN trains on (DVC dep)
    ``metrics/<stage>.json``            per-stage DVC metrics (accuracy)
    ``metrics/<stage>.timing.json``     its timings (wall/CPU time, throughput, peak RSS; uncached DVC out)
``<output_dir>/evaluation/<patient>/<sequence>/``  pose / depth benchmark results (read by `tables`)
    ``sequence_YYY/...``                rendered sequences (later stages)
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

from .catalog import (DEPTH_FINETUNE_JSON, DEPTH_MODEL, EVALUATION, TRAINING_JSON, TRAINING_LOG_CSV, EvaluationPaths,
                      SequencePaths)

#: stages whose metrics file is not named after the stage (``metrics/<name>.json``)
METRICS_NAMES = {"validate_anatomy": "anatomy_validation", "validate_centreline": "centreline_validation"}


@dataclasses.dataclass(frozen=True)
class PatientPaths:
    output_dir: Path
    patient: str

    @property
    def root(self) -> Path:
        return Path(self.output_dir) / self.patient

    # phantom stage
    @property
    def input_dir(self) -> Path:
        return self.root / "input"

    @property
    def phantom_ct(self) -> Path:
        return self.input_dir / "ct.nii.gz"

    @property
    def ground_truth(self) -> Path:
        return self.root / "ground_truth"

    @property
    def gt_mask(self) -> Path:
        return self.ground_truth / "airway_mask.nii.gz"

    @property
    def gt_sdf(self) -> Path:
        return self.ground_truth / "sdf.nii.gz"

    @property
    def gt_sdf_exact(self) -> Path:
        return self.ground_truth / "sdf_exact.nii.gz"

    @property
    def gt_tree(self) -> Path:
        return self.ground_truth / "tree.json"

    @property
    def gt_centreline(self) -> Path:
        return self.ground_truth / "centreline.json"

    @property
    def gt_metadata(self) -> Path:
        return self.ground_truth / "phantom_metadata.json"

    # anatomy stages
    @property
    def anatomy(self) -> Path:
        return self.root / "anatomy"

    @property
    def ct_metadata(self) -> Path:
        return self.anatomy / "ct_metadata.json"

    @property
    def airway_mask(self) -> Path:
        return self.anatomy / "airway_mask.nii.gz"

    @property
    def sdf(self) -> Path:
        return self.anatomy / "sdf.nii.gz"

    @property
    def sdf_metadata(self) -> Path:
        return self.anatomy / "sdf_metadata.json"

    @property
    def mesh(self) -> Path:
        return self.anatomy / "lung_model.obj"

    @property
    def collision_mesh(self) -> Path:
        return self.anatomy / "collision_model.obj"

    @property
    def mesh_metadata(self) -> Path:
        return self.anatomy / "mesh_metadata.json"

    @property
    def volume_mesh(self) -> Path:
        """``anatomy/volume_mesh/``: the optional tetrahedral mesh and its ``info.json`` (mesh stage)."""
        return self.anatomy / "volume_mesh"

    @property
    def tet_mesh(self) -> Path:
        """``anatomy/volume_mesh/lung_model_tet.npz`` (vertices in metres, tetrahedra), when made."""
        return self.volume_mesh / "lung_model_tet.npz"

    @property
    def volume_mesh_info(self) -> Path:
        """``anatomy/volume_mesh/info.json``: whether the volume mesh was made, and why not."""
        return self.volume_mesh / "info.json"

    @property
    def medial_axis_ply(self) -> Path:
        return self.anatomy / "medial_axis.ply"

    @property
    def centreline_graph(self) -> Path:
        return self.anatomy / "centreline_graph.json"

    # sequences
    def sequence(self, sequence: str) -> Path:
        return self.root / sequence

    def seq(self, sequence: str) -> SequencePaths:
        """Every path inside the sequence folder (:mod:`room_pipeline.catalog`)."""
        return SequencePaths(self.sequence(sequence))

    def sequence_metadata(self, sequence: str) -> Path:
        return self.seq(sequence).metadata

    # evaluation (one folder per dataset: the tables stage depends on it as a whole)
    @property
    def evaluation_root(self) -> Path:
        """``<output_dir>/evaluation/<patient>/``."""
        return Path(self.output_dir) / EVALUATION / self.patient

    def evaluation(self, sequence: str) -> Path:
        """``<output_dir>/evaluation/<patient>/<sequence>/``: pose.json, depth.json, per-frame CSVs."""
        return self.evaluation_root / sequence

    def eval(self, sequence: str) -> EvaluationPaths:
        """The named result files of :meth:`evaluation` (:mod:`room_pipeline.catalog`)."""
        return EvaluationPaths(self.evaluation(sequence))

    @property
    def depth_finetune(self) -> Path:
        """``<output_dir>/evaluation/<patient>/depth_finetune.json`` (train_depth, read by tables)."""
        return self.evaluation_root / DEPTH_FINETUNE_JSON

    @property
    def depth_model(self) -> Path:
        """``<patient>/depth_model/``: the fine-tuned depth network's checkpoints (train_depth)."""
        return self.root / DEPTH_MODEL

    @property
    def depth_training(self) -> Path:
        """``<patient>/depth_model/training.json``: the fine-tuning's provenance record (train_depth)."""
        return self.depth_model / TRAINING_JSON

    @property
    def depth_training_log(self) -> Path:
        """``<patient>/depth_model/training_log.csv``: per-epoch losses (train_depth)."""
        return self.depth_model / TRAINING_LOG_CSV

    @property
    def sequence_index(self) -> Path:
        """``<patient>/sequence_index/``: one record per rendered sequence and stage (:meth:`sequence_record`);
        train_depth's DVC dep, which stays right whatever ``sequences`` is (scripts/write_dvc_yaml.py)."""
        return self.root / "sequence_index"

    def sequence_record(self, sequence: str, stage: str) -> Path:
        """``sequence_index/<sequence>.<stage>.json``: the sha256 of the sequence outputs of ``stage`` (render,
        noise) that the depth stages read."""
        return self.sequence_index / f"{sequence}.{stage}.json"

    @property
    def metrics_dir(self) -> Path:
        return self.root / "metrics"

    def metrics(self, stage: str) -> Path:
        return self.metrics_dir / f"{stage}.json"

    def stage_metrics(self, stage: str, sequence: str = "") -> Path:
        """The DVC metrics file of pipeline stage ``stage`` (for ``sequence`` when it fans out over sequences):
        ``metrics/<stage>[_<sequence>].json``, or the stage's own name in :data:`METRICS_NAMES`."""
        name = METRICS_NAMES.get(stage, stage)
        return self.metrics(f"{name}_{sequence}" if sequence else name)

    def stage_timings(self, stage: str, sequence: str = "") -> Path:
        """The timing file beside :meth:`stage_metrics` (``metrics/<stage>[_<sequence>].timing.json``, see
        :mod:`room_pipeline.io.metrics`)."""
        return self.stage_metrics(stage, sequence).with_suffix(".timing.json")
