"""validate_anatomy's two halves (volumes, meshes) on two workers give the figures of one process."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from room_pipeline.evaluate.anatomy_validation import ValidationInputs, validate_anatomy, workers_for
from room_pipeline.paths import PatientPaths

BIN = Path(sys.executable).parent
#: a small phantom (coarse voxels, few generations): segment -> mesh in seconds
SMALL = ["patients=phantom_single", "phantom.spacing_mm=[1.5,1.5,1.5]", "phantom.max_generation=3",
         "sequences=[sequence_000]"]


@pytest.fixture(scope="module")
def small_patient(tmp_path_factory) -> PatientPaths:
    out = tmp_path_factory.mktemp("va")
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    r = subprocess.run([str(BIN / "room"), "run", "--until", "mesh", f"output_dir={out}", *SMALL],
                       capture_output=True, text=True, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    return PatientPaths(out, "patient_000")


def test_two_workers_give_the_serial_figures(small_patient):
    from room_pipeline.config.compose import compose

    p = small_patient
    cfg = compose(SMALL)
    inputs = ValidationInputs(gt_tree=p.gt_tree, gt_mask=p.gt_mask, gt_sdf=p.gt_sdf, airway_mask=p.airway_mask,
                              sdf=p.sdf, mesh=p.mesh, sdf_params=dict(cfg["sdf"]), mesh_params=dict(cfg["mesh"]))
    serial = validate_anatomy(inputs, {"backend": "serial"})
    local = validate_anatomy(inputs, {"backend": "local", "workers": 2})
    assert local == serial
    assert set(serial) == {"checks", "voxel_size_mm", "segment", "sdf", "mesh"}
    assert serial["checks"]["mesh_watertight"] and serial["sdf"]["isolation"]["n"] > 0


def test_automatic_workers_only_for_a_grid_worth_a_process():
    """``workers: 0`` spawns the second worker only for a grid whose halves take longer than a worker's start;
    explicit workers are kept (at most two halves)."""
    assert workers_for({"workers": 0}, n_voxels=1_000) == 1
    assert workers_for({"workers": 0}, n_voxels=10**9) == min(2, max(1, len(os.sched_getaffinity(0))))
    assert workers_for({"workers": 1}, n_voxels=10**9) == 1
    assert workers_for({"workers": 5}, n_voxels=1_000) == 2
