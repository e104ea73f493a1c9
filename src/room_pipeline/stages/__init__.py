"""One thin module per DVC stage: read inputs and params, call domain code, write outputs and metrics.

Stage modules are imported lazily by name, so the CLI never loads a heavy
backend (pymeshlab, bpy, pybullet) that the requested stage does not use.
"""
from __future__ import annotations

import importlib
from types import ModuleType

#: pipeline order; `room run` executes these in turn
STAGES = ("phantom", "segment", "sdf", "mesh", "validate_anatomy", "medial_axis", "validate_centreline",
          "trajectory", "simulate", "render", "noise", "train_depth", "evaluate_depth", "evaluate_pose", "tables")

#: how each stage fans out: over phantom patients, all patients, patients x sequences, once for the
#: whole dataset (key "all"), or once for the depth CNN's training patient (``depth.cnn.checkpoint_patient``)
FAN_OUT = {"phantom": "phantoms", "segment": "patients", "sdf": "patients", "mesh": "patients",
           "validate_anatomy": "phantoms", "medial_axis": "patients", "validate_centreline": "phantoms",
           "trajectory": "sequences", "simulate": "sequences", "render": "sequences", "noise": "sequences",
           "train_depth": "training", "evaluate_depth": "sequences", "evaluate_pose": "sequences",
           "tables": "dataset"}


def load(name: str) -> ModuleType:
    """Import ``room_pipeline.stages.<name>``."""
    if name not in STAGES:
        from ..errors import ConfigError

        raise ConfigError(f"unknown stage '{name}' (stages: {', '.join(STAGES)})")
    return importlib.import_module(f"{__name__}.{name}")
