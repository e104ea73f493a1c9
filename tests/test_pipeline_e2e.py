"""End to end through DVC and `room run`: caching reruns exactly what changed; same config -> same bytes."""
from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent

#: a small phantom so the whole chain runs in seconds (coarse voxels, fewer generations)
SMALL = ["phantom.spacing_mm=[1.2,1.2,1.2]", "phantom.max_generation=5", "sequences=[sequence_000]",
         "trajectory.n=1"]
P = "@patient_000"
ANATOMY = {f"{s}{P}" for s in ("segment", "sdf", "mesh", "validate_anatomy", "medial_axis",
                               "validate_centreline")} | {f"trajectory{P}-sequence_000"}

pytestmark = pytest.mark.slow


def _env():
    env = dict(os.environ)
    env["PATH"] = f"{BIN}{os.pathsep}{env.get('PATH', '')}"
    env.pop("ROOM_CONF_DIR", None)
    return env


def _sh(args, cwd, check=True):
    r = subprocess.run(args, cwd=cwd, capture_output=True, text=True, env=_env())
    if check and r.returncode != 0:
        raise AssertionError(f"{' '.join(map(str, args))} failed ({r.returncode}):\n{r.stdout}\n{r.stderr}")
    return r


@pytest.fixture(scope="module")
def project(tmp_path_factory):
    """A copy of the project's tracked files in a fresh git repo, with a small-phantom params.yaml."""
    dst = tmp_path_factory.mktemp("proj")
    files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO,
                           capture_output=True, text=True, check=True).stdout.split()
    for f in files:
        if (REPO / f).is_file():
            (dst / f).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / f, dst / f)
    _sh(["git", "init", "-q"], dst)
    _sh(["room", "params", *SMALL], dst)
    return dst


def _ran(output: str) -> set[str]:
    return set(re.findall(r"Running stage '([^']+)'", output))


def test_dvc_repro_caches_and_reruns_only_what_changed(project):
    first = _sh(["dvc", "repro"], project).stdout
    assert _ran(first) == ANATOMY | {f"phantom{P}"}
    again = _sh(["dvc", "repro"], project).stdout
    assert _ran(again) == set(), again
    status = _sh(["dvc", "status"], project).stdout
    assert "up to date" in status, status
    m = json.loads(_sh(["dvc", "metrics", "show", "--json"], project).stdout)
    assert m, "dvc metrics show returned nothing"

    # a mesh parameter: only mesh (and the validation that reads the mesh) rerun
    _sh(["room", "params", *SMALL, "mesh.smoothing_iterations=3"], project)
    out = _sh(["dvc", "repro"], project).stdout
    assert _ran(out) == {"mesh@patient_000", "validate_anatomy@patient_000"}, out

    # a segmentation parameter that changes the mask: segment and everything downstream of it
    # (DVC hashes content: a parameter change that leaves the mask byte-identical stops at segment)
    _sh(["room", "params", *SMALL, "mesh.smoothing_iterations=3", "segment.refine_layers=0"], project)
    out = _sh(["dvc", "repro"], project).stdout
    ran = _ran(out)
    assert f"phantom{P}" not in ran
    # the trajectory reruns only if the centreline graph or the SDF actually changed
    assert ANATOMY - {f"trajectory{P}-sequence_000"} <= ran <= ANATOMY, out


def test_room_run_reproduces_dvc_bytes(project):
    """Same config and seed -> byte-identical files, whether made by DVC or by `room run`."""
    _sh(["room", "params", *SMALL], project)
    _sh(["dvc", "repro"], project)
    out = project / "data" / "output"
    snapshot = project / "snapshot"
    shutil.copytree(out, snapshot)
    shutil.rmtree(out)
    _sh(["room", "run", *SMALL], project)
    ref = snapshot / "patient_000"
    files = [p for p in ref.rglob("*") if p.is_file() and "metrics" not in p.parts and p.name != ".gitignore"]
    assert len(files) >= 8
    for p in files:
        rel = p.relative_to(ref)
        assert p.read_bytes() == (out / "patient_000" / rel).read_bytes(), f"{rel} differs"
