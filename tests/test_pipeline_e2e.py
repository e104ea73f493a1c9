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

from room_pipeline.io.metrics import split_timings
from room_pipeline.stages import FAN_OUT, STAGES

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent

#: a small phantom so the whole chain runs in seconds (coarse voxels, fewer generations)
SMALL = ["patients=phantom_single", "phantom.spacing_mm=[1.2,1.2,1.2]", "phantom.max_generation=5", "sequences=[sequence_000]",
         "trajectory.n=1", "render.width=64", "render.height=48", "render.max_frames=4",
         "render.modalities=[rgb,depth,relative_depth,normals,flow,segmentation,point_cloud]",
         # depth stages: the built-in estimators only, a tiny U-Net trained for two steps, no external data set
         "depth.methods=[physics,cnn,cnn_pretrained]", "depth.cnn.input_size=32", "depth.cnn.channels=[4,8]",
         "depth.train.batch_size=2", "depth.train.pretrain_scenes=1", "depth.train.pretrain_views=2",
         "depth.train.pretrain_steps=2", "depth.train.finetune_steps=2", "depth.train.holdout_fraction=0.34",
         "depth.train.holdout_gap_frames=0", "depth.train.eval_stride=1", "depth.train.simcol_dir=null"]
P = "@patient_000"
ANATOMY = {f"{s}{P}" for s in ("segment", "sdf", "mesh", "validate_anatomy", "medial_axis",
                               "validate_centreline")} | {f"{s}{P}-sequence_000" for s in ("trajectory", "simulate",
                                                                                             "render")}

#: outputs outside metrics/ that hold wall times, so two runs differ there (none: timings go to metrics/)
TIMED: set = set()


def _dvc_name(stage: str) -> str:
    fan = FAN_OUT[stage]
    return stage if fan in ("dataset", "training") else f"{stage}{P}-sequence_000" if fan == "sequences" else f"{stage}{P}"


#: the stages after render (sensor noise, evaluations, tables): they all read what it renders
DOWNSTREAM = {_dvc_name(s) for s in STAGES[STAGES.index("render") + 1:]}

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
        if f.startswith("data/output/") or f == "dvc.lock":   # generated outputs of a local run stay behind
            continue
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
    assert _ran(first) == ANATOMY | DOWNSTREAM | {f"phantom{P}"}
    again = _sh(["dvc", "repro"], project).stdout
    assert _ran(again) == set(), again
    status = _sh(["dvc", "status"], project).stdout
    assert "up to date" in status, status
    m = json.loads(_sh(["dvc", "metrics", "show", "--json"], project).stdout)
    assert m, "dvc metrics show returned nothing"
    # the DVC metrics hold no timing (they sit in metrics/<stage>.timing.json, uncached outs), so a
    # `dvc exp show --only-changed` compares accuracy only
    shown = {}

    def files(node):
        for k, v in (node.items() if isinstance(node, dict) else ()):
            if k.endswith(".json") and isinstance(v, dict) and isinstance(v.get("data"), dict):
                shown[k] = v["data"]
            else:
                files(v)
    files(m)
    per_stage = {k: v for k, v in shown.items() if "/metrics/" in k}
    assert per_stage and all(split_timings(v)[1] == {} for v in per_stage.values()), per_stage
    timing_files = sorted((project / "data" / "output").rglob("*.timing.json"))
    assert len(timing_files) == len(per_stage)
    assert all("wall_time_s" in json.loads(f.read_text()) for f in timing_files if "train_depth" not in f.name)
    # nor do the evaluation files (pose.json, depth.json, depth_finetune.json, the per-frame CSVs): no metrics or
    # evaluation file of the run holds a timing key or a time column
    data = project / "data" / "output"
    for f in [*data.rglob("metrics/*.json"), *(data / "evaluation").rglob("*.json")]:
        if not f.name.endswith(".timing.json"):
            assert split_timings(json.loads(f.read_text()))[1] == {}, f
    for f in (data / "evaluation").rglob("*.csv"):
        assert not [c for c in f.read_text().splitlines()[0].split(",") if "second" in c or "time" in c], f

    # a render parameter: exactly render and what is downstream of it (noise, evaluations, tables)
    _sh(["room", "params", *SMALL, "render.base_color=[0.7,0.5,0.54]"], project)   # changes every RGB byte
    out = _sh(["dvc", "repro"], project).stdout
    assert _ran(out) == {f"render{P}-sequence_000"} | DOWNSTREAM, out

    # a mesh parameter: only mesh and what reads the mesh (validation, simulation, rendering) rerun
    _sh(["room", "params", *SMALL, "mesh.smoothing_iterations=3"], project)
    out = _sh(["dvc", "repro"], project).stdout
    assert _ran(out) == {f"mesh{P}", f"validate_anatomy{P}", f"simulate{P}-sequence_000",
                         f"render{P}-sequence_000"} | DOWNSTREAM, out

    # a segmentation parameter that changes the mask: segment and everything downstream of it
    # (DVC hashes content: a parameter change that leaves the mask byte-identical stops at segment)
    _sh(["room", "params", *SMALL, "mesh.smoothing_iterations=3", "segment.refine_layers=0"], project)
    out = _sh(["dvc", "repro"], project).stdout
    ran = _ran(out)
    assert f"phantom{P}" not in ran
    # per-sequence stages rerun only if the centreline graph, SDF or mesh actually changed
    assert {s for s in ANATOMY if "sequence" not in s} <= ran <= ANATOMY | DOWNSTREAM, out


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
    files = [p for p in ref.rglob("*") if p.is_file() and "metrics" not in p.parts and p.name != ".gitignore"
             and p.relative_to(ref).as_posix() not in TIMED]
    assert len(files) >= 8
    for p in files:
        rel = p.relative_to(ref)
        assert p.read_bytes() == (out / "patient_000" / rel).read_bytes(), f"{rel} differs"
    # `room run` ends with <output_dir>/manifest.json: intact, and the same files and config as what DVC made
    # (metrics hold wall times, run_config.yaml is room run's own, .gitignore files are DVC's)
    from omegaconf import OmegaConf

    from room_pipeline.execution import build_manifest, compare_manifests, read_manifest, verify_manifest

    assert verify_manifest(out) == []
    made = read_manifest(out)
    assert made["extra"]["room_run"]["patient"] == "patient_000"
    assert any(f["path"] == "patient_000/run_config.yaml" for f in made["files"])
    by_dvc = build_manifest(snapshot, OmegaConf.to_container(OmegaConf.load(project / "params.yaml"), resolve=True))
    # evaluation/ holds no timing (the methods' seconds are in metrics/*.timing.json): compared byte for byte
    ignore = ("*/metrics/*", "*/run_config.yaml", "*.gitignore", *(f"patient_000/{t}" for t in TIMED))
    diffs = compare_manifests(by_dvc, made, ignore_files=ignore)
    assert diffs == [], "\n".join(diffs)


def test_room_run_multirun_sweeps_into_two_datasets(project):
    """`room run -m`: one run per sweep point (here two output folders), each with its manifest, same bytes."""
    from room_pipeline.execution import compare_manifests, read_manifest, verify_manifest

    r = _sh(["room", "run", "-m", "--until", "phantom", *SMALL, "output_dir=data/mr0,data/mr1",
             "hydra.sweep.dir=multirun/e2e"], project)
    assert "Launching 2 jobs locally" in r.stdout + r.stderr
    a, b = project / "data" / "mr0", project / "data" / "mr1"
    assert verify_manifest(a) == [] and verify_manifest(b) == []
    ma, mb = read_manifest(a), read_manifest(b)
    assert ma["config"]["output_dir"] == "data/mr0" and (a / "patient_000" / "input" / "ct.nii.gz").is_file()
    where = ("execution", "output_dir", "patients.patient_000.input")      # the input path follows output_dir
    assert compare_manifests(ma, mb, ignore_config=where, ignore_files=("*/metrics/*", "*/run_config.yaml")) == []
    assert (project / "multirun" / "e2e" / "1" / ".hydra" / "overrides.yaml").is_file()


def test_rendered_files_are_read_by_standard_tools(project):
    """EXR (depth, normals, flow) by OpenImageIO and OpenCV, PNG by OpenCV, PLY (`room export -f ply`) by Open3D."""
    import numpy as np

    _sh(["room", "params", *SMALL], project)
    _sh(["dvc", "repro"], project)
    seq = project / "data" / "output" / "patient_000" / "sequence_000"
    os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")
    import cv2
    import open3d as o3d
    import OpenImageIO as oiio

    from room_pipeline.dataset import SequenceReader

    cal = json.loads((seq / "calibration" / "camera_params.json").read_text())
    assert (cal["width"], cal["height"]) == (64, 48)
    for i in range(4):
        name = f"frame_{i:04d}"
        rgb = cv2.imread(str(seq / "rgb" / f"{name}.png"))
        assert rgb.shape == (48, 64, 3)
        depth = oiio.ImageInput.open(str(seq / "depth" / f"{name}.exr")).read_image()[..., 0]
        assert depth.shape == (48, 64) and np.all(np.isfinite(depth)) and depth.max() > 0
        assert np.array_equal(cv2.imread(str(seq / "depth" / f"{name}.exr"), cv2.IMREAD_UNCHANGED), depth)
        n = oiio.ImageInput.open(str(seq / "surface_normals" / f"{name}.exr")).read_image()
        hit = depth > 0
        assert np.allclose(np.linalg.norm(n[hit], axis=1), 1.0, atol=3 ** 0.5 * 2.0 ** -12)   # half floats
        # flow: half-float EXR, R, G = u, v (render.storage; .flo and PLY files: tests/test_storage.py)
        flow = oiio.ImageInput.open(str(seq / "optical_flow" / f"{name}.exr")).read_image()
        assert flow.shape == (48, 64, 2) and np.all(np.isfinite(flow))
        assert np.array_equal(cv2.imread(str(seq / "optical_flow" / f"{name}.exr"), cv2.IMREAD_UNCHANGED)[..., 2],
                              flow[..., 0])
        # point clouds on demand (point_clouds/point_clouds.json), materialised by `room export -f ply`
        pc = SequenceReader(seq, ["point_cloud"]).frame(i)
        assert len(pc["point_cloud"]) == int(hit.sum()) and "point_cloud_normals" in pc
        seg = cv2.imread(str(seq / "segmentation" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        assert seg.dtype == np.uint16 and np.array_equal(seg > 0, hit)
    legend = json.loads((seq / "segmentation" / "legend.json").read_text())
    assert legend["labels"]
    _sh(["room", "export", "-f", "ply", str(seq), str(project / "pc")], project)
    pc = o3d.io.read_point_cloud(str(project / "pc" / "points" / "frame_0000.ply"))
    assert len(pc.points) > 0 and pc.has_normals() and pc.has_colors()


def test_render_stage_with_cycles_rgb(project):
    """backend=cycles: RGB from Blender Cycles, geometric modalities unchanged from the ray caster."""
    import numpy as np

    _sh(["room", "params", *SMALL], project)
    _sh(["dvc", "repro"], project)
    seq = project / "data" / "output" / "patient_000" / "sequence_000"
    before = {p.name: p.read_bytes() for p in (seq / "depth").iterdir()}
    rgb_before = (seq / "rgb" / "frame_0000.png").read_bytes()
    _sh(["room", "stage", "render", "--patient", "patient_000/sequence_000", "--params", "params.yaml",
         "render.backend=cycles"], project)
    assert {p.name: p.read_bytes() for p in (seq / "depth").iterdir()} == before
    import cv2
    rgb = cv2.imread(str(seq / "rgb" / "frame_0000.png"))
    assert rgb.shape == (48, 64, 3) and rgb.std() > 1.0
    assert (seq / "rgb" / "frame_0000.png").read_bytes() != rgb_before
    meta = json.loads((seq / "metadata" / "render.json").read_text())
    assert meta["renderer"]["rgb"]["backend"] == "blender_cycles"
