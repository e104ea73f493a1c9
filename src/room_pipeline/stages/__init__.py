"""One thin module per DVC stage: read inputs and params, call domain code, write outputs and metrics.

Stage modules are imported lazily by name, so the CLI never loads a heavy
backend (pymeshlab, bpy, pybullet) that the requested stage does not use.
"""
from __future__ import annotations

import importlib
from types import ModuleType

#: pipeline order; `room run` executes these in turn
STAGES = ("phantom", "segment", "sdf", "mesh", "validate_anatomy")

#: stages that only exist for patients with ground truth (phantoms)
PHANTOM_ONLY = ("phantom", "validate_anatomy")


def load(name: str) -> ModuleType:
    """Import ``room_pipeline.stages.<name>``."""
    if name not in STAGES:
        from ..errors import ConfigError

        raise ConfigError(f"unknown stage '{name}' (stages: {', '.join(STAGES)})")
    return importlib.import_module(f"{__name__}.{name}")
