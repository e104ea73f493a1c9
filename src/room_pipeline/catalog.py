"""The dataset catalogue: the one owner of every file and folder name inside a sequence.

Patient-level files (``anatomy/``, ``ground_truth/``, ``metrics/``, ``evaluation/``)
are named in :mod:`room_pipeline.paths`, which builds on this module; everything
inside ``<output_dir>/<patient>/<sequence>/`` and ``<output_dir>/evaluation/<patient>/<sequence>/``
is named here, once, and every stage, the dataset reader, the exports, the report
and the benchmarks read the names from here::

    <sequence>/
        rgb/ depth/ relative_depth/ surface_normals/ optical_flow/ point_clouds/ segmentation/   (render)
        rgb_noisy/                                                                             (noise)
        calibration/camera_params.json                                                         (render)
        point_clouds/point_clouds.json                                                         (render)
        segmentation/legend.json                                                               (render)
        metadata/trajectory.json  timestamps.json  trajectory_tum.txt                          (trajectory)
        metadata/robot_config.json  simulation.json  simulated_tum.txt                         (simulate)
        metadata/render.json                                                                   (render)
        metadata/noise.json                                                                    (noise)
    evaluation/<patient>/<sequence>/
        pose.json  pose_errors.csv                                                             (evaluate_pose)
        depth.json depth_errors.csv                                                            (evaluate_depth)
    evaluation/<patient>/depth_finetune.json  and  <patient>/depth_model/                       (train_depth)

This module imports nothing from the package (it is the lowest layer beside
:mod:`room_pipeline.errors`), so any module may use it without pulling a stage,
the planner or a backend into its DVC dependencies.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

from .errors import ConfigError

#: modality -> folder of the render stage (the ROOM layout)
RENDER_FOLDERS: dict[str, str] = {
    "rgb": "rgb", "depth": "depth", "relative_depth": "relative_depth", "normals": "surface_normals",
    "flow": "optical_flow", "point_cloud": "point_clouds", "segmentation": "segmentation"}
#: the noise stage's frames (modality and folder share the name)
RGB_NOISY = "rgb_noisy"
#: modality -> folder inside a sequence: the render stage's plus the noise stage's
FOLDERS: dict[str, str] = {**RENDER_FOLDERS, RGB_NOISY: RGB_NOISY}
#: the modalities a reader can load, in the dataset's order
MODALITIES: tuple[str, ...] = ("rgb", RGB_NOISY, "depth", "relative_depth", "normals", "flow", "segmentation",
                               "point_cloud")
#: the two RGB sources (clean render, noisy sensor)
RGB_SOURCES: tuple[str, ...] = ("rgb", RGB_NOISY)

METADATA = "metadata"
CALIBRATION = "calibration"
CAMERA_JSON = "camera_params.json"
LEGEND_JSON = "legend.json"
#: inside ``point_clouds/``: how the point clouds are stored (PLY files, or built on demand from depth)
POINT_CLOUD_JSON = "point_clouds.json"
TRAJECTORY_JSON = "trajectory.json"
TIMESTAMPS_JSON = "timestamps.json"
TRAJECTORY_TUM = "trajectory_tum.txt"
ROBOT_CONFIG_JSON = "robot_config.json"
SIMULATION_JSON = "simulation.json"
SIMULATED_TUM = "simulated_tum.txt"
RENDER_JSON = "render.json"
NOISE_JSON = "noise.json"
POSE_JSON = "pose.json"
POSE_ERRORS_CSV = "pose_errors.csv"
DEPTH_JSON = "depth.json"
DEPTH_ERRORS_CSV = "depth_errors.csv"
#: the per-frame error tables (DVC plots)
PER_FRAME_CSVS: tuple[str, ...] = (POSE_ERRORS_CSV, DEPTH_ERRORS_CSV)
EVALUATION = "evaluation"
DEPTH_FINETUNE_JSON = "depth_finetune.json"
DEPTH_MODEL = "depth_model"
#: ``<output_dir>/manifest.json``: every file of a `room run` with its sha256 (room_pipeline.execution.manifest)
MANIFEST_NAME = "manifest.json"
#: inside ``depth_model/``: the training record and the per-epoch losses (train_depth)
TRAINING_JSON = "training.json"
TRAINING_LOG_CSV = "training_log.csv"
#: inside the tables' folder (``evaluate.tables.output_dir``): beside the tables, the time-vs-accuracy table and
#: the tables' numbers (the dataset's DVC metrics file)
SPEED_ACCURACY_CSV = "pose_speed_accuracy.csv"
TABLES_METRICS_JSON = "metrics.json"


def frame_name(index: int, ext: str, prefix: str = "frame") -> str:
    """``frame_NNNN<ext>``: a frame's file name inside a modality folder (``ext`` with its dot)."""
    return f"{prefix}_{int(index):04d}{ext}"


def split_key(key: str) -> tuple[str, str]:
    """DVC matrix key ``<patient>/<sequence>`` -> (patient, sequence)."""
    if "/" not in key:
        raise ConfigError(f"a sequence stage needs --patient PATIENT/SEQUENCE, got '{key}'")
    patient, sequence = key.split("/", 1)
    return patient, sequence


@dataclasses.dataclass(frozen=True)
class SequencePaths:
    """Every path inside one sequence folder ``root`` (``<output_dir>/<patient>/<sequence>``)."""

    root: Path

    def __post_init__(self):
        object.__setattr__(self, "root", Path(self.root))

    def folder(self, modality: str) -> Path:
        """The folder of a modality (a key of :data:`FOLDERS`)."""
        try:
            return self.root / FOLDERS[modality]
        except KeyError:
            raise ConfigError(f"unknown modality {modality!r} (known: {sorted(FOLDERS)})") from None

    def frame(self, modality: str, index: int, ext: str) -> Path:
        return self.folder(modality) / frame_name(index, ext)

    def render_folders(self) -> list[Path]:
        return [self.root / f for f in RENDER_FOLDERS.values()]

    @property
    def rgb_noisy(self) -> Path:
        return self.root / RGB_NOISY

    @property
    def metadata(self) -> Path:
        return self.root / METADATA

    @property
    def calibration(self) -> Path:
        return self.root / CALIBRATION

    @property
    def camera(self) -> Path:
        return self.calibration / CAMERA_JSON

    @property
    def legend(self) -> Path:
        return self.folder("segmentation") / LEGEND_JSON

    @property
    def point_cloud_json(self) -> Path:
        return self.folder("point_cloud") / POINT_CLOUD_JSON

    @property
    def trajectory(self) -> Path:
        return self.metadata / TRAJECTORY_JSON

    @property
    def timestamps(self) -> Path:
        return self.metadata / TIMESTAMPS_JSON

    @property
    def trajectory_tum(self) -> Path:
        return self.metadata / TRAJECTORY_TUM

    @property
    def robot_config(self) -> Path:
        return self.metadata / ROBOT_CONFIG_JSON

    @property
    def simulation(self) -> Path:
        return self.metadata / SIMULATION_JSON

    @property
    def simulated_tum(self) -> Path:
        return self.metadata / SIMULATED_TUM

    @property
    def render_json(self) -> Path:
        return self.metadata / RENDER_JSON

    @property
    def noise_json(self) -> Path:
        return self.metadata / NOISE_JSON

    def is_rendered(self) -> bool:
        return self.render_json.is_file()


@dataclasses.dataclass(frozen=True)
class EvaluationPaths:
    """The benchmark results of one sequence, ``<output_dir>/evaluation/<patient>/<sequence>/``."""

    root: Path

    def __post_init__(self):
        object.__setattr__(self, "root", Path(self.root))

    @property
    def pose(self) -> Path:
        return self.root / POSE_JSON

    @property
    def pose_errors(self) -> Path:
        return self.root / POSE_ERRORS_CSV

    @property
    def depth(self) -> Path:
        return self.root / DEPTH_JSON

    @property
    def depth_errors(self) -> Path:
        return self.root / DEPTH_ERRORS_CSV


def evaluation_root(output_dir: str | Path) -> Path:
    """``<output_dir>/evaluation``: one folder for every dataset's benchmark results."""
    return Path(output_dir) / EVALUATION


def sequence_paths(output_dir: str | Path, patient: str, sequence: str) -> SequencePaths:
    return SequencePaths(Path(output_dir) / patient / sequence)


def evaluation_paths(output_dir: str | Path, patient: str, sequence: str) -> EvaluationPaths:
    return EvaluationPaths(evaluation_root(output_dir) / patient / sequence)


def find_sequences(root: str | Path, record: str = "render_json") -> list[SequencePaths]:
    """The sequences below ``root`` whose ``record`` file exists, sorted by path.

    ``root``: a dataset root (``<patient>/<sequence>`` below it), a patient folder (``<sequence>``) or a
    sequence folder itself.  ``record``: a :class:`SequencePaths` file property, e.g. ``render_json`` (a
    rendered sequence), ``trajectory`` (planned) or ``simulation`` (simulated).
    """
    root = Path(root)
    if not isinstance(getattr(SequencePaths, record, None), property):
        raise ConfigError(f"unknown sequence record {record!r}")
    candidates = [root, *root.glob("*"), *root.glob("*/*")]
    return sorted((s for s in map(SequencePaths, candidates) if getattr(s, record).is_file()),
                  key=lambda s: s.root)
