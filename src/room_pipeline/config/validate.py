"""The whole composed config, checked up front: `room run` and every `room stage` call this before any work.

Each stage's own params dataclass is built from its section (types, ranges, unknown keys: their
``from_dict`` / ``__post_init__`` checks), plus the cross-section rules that no single dataclass sees
(patients, sequences, output_dir).  A bad value ends in one :class:`ConfigError` line naming the key,
before the first stage runs instead of after the stages before it.

The stage modules are imported by name (``importlib``), so this module adds no stage's code to another
stage's DVC dependencies (``scripts/stage_deps.py`` follows import statements only).
"""
from __future__ import annotations

import importlib
from typing import Any, Callable

from omegaconf import DictConfig, OmegaConf

from ..errors import ConfigError, RoomError


def _section(cfg: DictConfig, dotted: str) -> Any:
    node = OmegaConf.select(cfg, dotted, default=None)
    if node is None:
        return None
    return OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else node


def _import(module: str):
    """Import quietly at the file-descriptor level: pybullet prints its build-time banner to stderr on import,
    which would be a second line beside a `room: error:` one."""
    import os
    import sys

    if module in sys.modules:
        return sys.modules[module]
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            return importlib.import_module(module)
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _build(module: str, attr: str, dotted: str, optional: bool = False) -> Callable[[DictConfig], Any]:
    def build(cfg: DictConfig) -> Any:
        d = _section(cfg, dotted)
        if d is None:
            if optional:
                return None
            raise ConfigError(f"config has no section '{dotted}'")
        if not isinstance(d, dict):
            raise ConfigError(f"{dotted} must be a mapping, got {d!r}")
        cls = getattr(_import(module), attr)
        return cls.from_dict(d)
    return build


def _execution(cfg: DictConfig) -> Any:
    mod = importlib.import_module("room_pipeline.execution.executor")
    return mod.ExecutionParams.from_dict(_section(cfg, "execution"))


def _pose(cfg: DictConfig) -> Any:
    mod = importlib.import_module("room_pipeline.evaluate.pose_eval")
    p = mod.PoseEvalParams.from_dict(_section(cfg, "evaluate.pose"))
    return p.method_params()


def _tables(cfg: DictConfig) -> Any:
    mod = importlib.import_module("room_pipeline.evaluate.reports")
    return mod.TablesParams.from_dict(_section(cfg, "evaluate.tables"))


def _noise(cfg: DictConfig) -> Any:
    mod = importlib.import_module("room_pipeline.stages.noise")
    p = mod.NoiseParams.from_dict(_section(cfg, "noise"))
    p.calibration_params()
    return p


#: config section -> builder of the params a stage makes from it (the same call the stage makes)
CHECKS: dict[str, Callable[[DictConfig], Any]] = {
    "phantom": _build("room_pipeline.anatomy.phantom_params", "PhantomParams", "phantom"),
    "segment": _build("room_pipeline.anatomy.segment_params", "SegmentParams", "segment"),
    "sdf": _build("room_pipeline.anatomy.sdf", "SdfParams", "sdf"),
    "mesh": _build("room_pipeline.anatomy.mesh", "MeshParams", "mesh"),
    "medial_axis": _build("room_pipeline.anatomy.medial_axis", "MedialAxisParams", "medial_axis"),
    "trajectory": _build("room_pipeline.planning.trajectory_params", "TrajectoryParams", "trajectory"),
    "simulate": _build("room_pipeline.robot.sim_params", "SimParams", "simulate"),
    "render": _build("room_pipeline.render.params", "RenderParams", "render"),
    "execution": _execution,
    "noise": _noise,
    "evaluate.pose": _pose,
    "evaluate.tables": _tables,
    "depth": _build("room_pipeline.depth.estimators", "DepthParams", "depth"),
}


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def _check_patients(cfg: DictConfig) -> None:
    from .compose import patient_entry, phantom_entry

    patients = cfg.get("patients")
    if not patients:
        raise ConfigError("no patients configured (patients: {})")
    for pid in patients:
        patient_entry(cfg, str(pid))
    phantoms = cfg.get("phantoms") or {}
    for pid in phantoms:
        seed = OmegaConf.select(cfg, f"phantoms.{pid}.seed", default=None)
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise ConfigError(f"phantoms.{pid}.seed must be an integer >= 0, got {seed!r}")
        phantom_entry(cfg, str(pid))
    seqs = cfg.get("sequences")
    if seqs is None or isinstance(seqs, (str, int, float)) or len(seqs) == 0:
        raise ConfigError(f"sequences must be a non-empty list of sequence ids, got {seqs!r}")
    bad = [s for s in seqs if not isinstance(s, str) or not s or "/" in s]
    if bad or len(set(seqs)) != len(seqs):
        raise ConfigError(f"sequences must be distinct ids without '/', got {list(seqs)!r}")
    out = cfg.get("output_dir")
    if not isinstance(out, str) or not out.strip():
        raise ConfigError(f"output_dir must be a folder path, got {out!r}")


def validate_key(cfg: DictConfig, stage: str, key: str, fan: str) -> None:
    """The ``--patient`` of `room stage`: a configured patient (a phantom for phantom stages), and sequence."""
    if fan == "dataset":
        return
    patient, _, sequence = key.partition("/")
    pool = "phantoms" if fan == "phantoms" else "patients"
    known = [str(p) for p in (cfg.get(pool) or {})]
    if patient not in known:
        raise ConfigError(f"unknown patient '{patient}' for stage {stage} ({pool}: {', '.join(sorted(known)) or 'none'})")
    if fan == "sequences":
        seqs = [str(s) for s in (cfg.get("sequences") or [])]
        if sequence not in seqs:
            raise ConfigError(f"stage {stage} takes PATIENT/SEQUENCE with a configured sequence "
                              f"({', '.join(seqs)}), got '{key}'")


def validate_config(cfg: DictConfig) -> None:
    """Raise :class:`ConfigError` (one line, naming the key) at the first invalid value of the composed config."""
    _check_patients(cfg)
    for key, build in CHECKS.items():
        try:
            build(cfg)
        except RoomError as exc:
            raise ConfigError(_first_line(exc)) from None
        except (TypeError, ValueError, AttributeError, KeyError) as exc:
            raise ConfigError(f"{key}: invalid value ({_first_line(exc)})") from None
