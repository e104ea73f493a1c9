"""Issue #19 around the closed loop: the demo in the HTML report, depth estimators in the loop, bad requests.

The dataset is test_report's tiny one (a tube 'airway' simulated by PyBullet and rendered by the ray caster,
48 px); the demo runs on it for real; the closed-loop tube is test_navigation's.
"""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from room_pipeline.errors import ConfigError, InputError
from room_pipeline.navigation.depth_source import EstimatorDepth, NavPerception, make_depth_source, make_estimator
from room_pipeline.report import SECTIONS, ReportOptions, build_report
from room_pipeline.report.navigation import find_demos, read_ply_points
from tests.test_report import PATIENT, RENDERED_SEQ, build_dataset, parse, section

ROOT = Path(__file__).resolve().parents[1]


def room(*args):
    return subprocess.run([sys.executable, "-m", "room_pipeline.cli", *map(str, args)], capture_output=True,
                          text=True, encoding="utf-8")


def one_error_line(r) -> str:
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("room: error: "), r.stderr
    return lines[0]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return build_dataset(tmp_path_factory.mktemp("navdemo"))


@pytest.fixture(scope="module")
def demo(dataset) -> Path:
    """``room navigate demo`` (GT depth) on frames 0 and 6 into <patient>/navigation/<sequence>."""
    out = dataset / PATIENT / "navigation" / RENDERED_SEQ
    r = room("navigate", "demo", dataset / PATIENT / RENDERED_SEQ, "--frames", "0,6", "--stride", "2", "--out", out)
    assert r.returncode == 0, r.stderr[-3000:]
    return out


def test_report_shows_the_demo_image_and_3d_view(dataset, demo):
    doc = json.loads((demo / "navigation_demo.json").read_text())
    planned = [f for f in doc["frames"] if f.get("path_world_m")]
    assert planned, doc["frames"]
    assert all(f["status"] == ("free path" if f["collision_free_against_cloud"] else "no free path") for f in planned)
    assert find_demos(dataset) == [demo / "navigation_demo.json"]
    pts = read_ply_points(demo / f"frame_{planned[0]['frame']:04d}_path.ply")
    assert np.allclose(pts[-len(planned[0]["path_world_m"]):], planned[0]["path_world_m"], atol=1e-6)
    page = build_report(ReportOptions(output_dir=dataset, view_size=(200, 180), use_pyvista=False))
    ids = parse(page).sections
    want = [s for s, _ in SECTIONS]
    want.insert(want.index("view3d") + 1, "navigation")
    assert ids == want
    body = section(page, "navigation")
    # per planned frame: the image with the projected path and the 3-D view, both embedded
    assert len(re.findall(r'<img [^>]*src="data:image/', body)) == 2 * len(planned)
    assert "collision spheres" in body and "true lumen mesh" in body and "not drawn" not in body
    assert "matplotlib 3-D fallback" in body
    assert build_report(ReportOptions(output_dir=dataset, view_size=(200, 180), use_pyvista=False)) == page


def test_report_without_demo_output_has_no_navigation_section(tmp_path):
    (tmp_path / "patient_x" / "anatomy").mkdir(parents=True)
    page = build_report(ReportOptions(output_dir=tmp_path, use_pyvista=False))
    assert parse(page).sections == [s for s, _ in SECTIONS]
    assert 'id="navigation"' not in page


def test_demo_bad_requests_are_one_line_errors(dataset, tmp_path):
    seq = dataset / PATIENT / RENDERED_SEQ
    out = tmp_path / "o"
    assert "unknown depth method 'nosuch'" in one_error_line(room("navigate", "demo", seq, "--depth", "nosuch",
                                                                 "--out", out))
    assert "no frame 999" in one_error_line(room("navigate", "demo", seq, "--frames", "999", "--out", out))
    shutil.copytree(dataset / PATIENT, tmp_path / PATIENT, ignore=shutil.ignore_patterns("navigation"))
    copy = tmp_path / PATIENT / RENDERED_SEQ
    (copy / "depth" / "frame_0003.exr").unlink()
    assert "frame 3 has no depth" in one_error_line(room("navigate", "demo", copy, "--frames", "3", "--out", out))
    assert not out.exists()


def test_episode_bad_requests_are_one_line_errors(dataset):
    base = ["navigate", "episode", "--output-dir", dataset, "--patient", PATIENT]
    assert "target branch 9" in one_error_line(room(*base, "--target", "9"))
    assert "unknown depth method 'nosuch'" in one_error_line(room(*base, "--target", "1", "navigate.depth=nosuch"))
    assert "needs an estimator" in one_error_line(room(*base, "--target", "1", "navigate.noise=1"))
    assert "navigate.noise" in one_error_line(room(*base, "--target", "1", "navigate.depth=constant",
                                                   "navigate.noise=-1"))


def test_perception_defaults_are_conf_values_and_checked():
    conf = yaml.safe_load((ROOT / "conf" / "navigate" / "default.yaml").read_text())
    assert NavPerception.from_navigate(conf) == NavPerception() == NavPerception(conf["depth"], conf["noise"])
    with pytest.raises(ConfigError):
        NavPerception("shading_sfs", -0.5)
    assert make_depth_source(NavPerception(), None, None, None) is None
    with pytest.raises(InputError, match="cannot run here"):
        make_estimator("cnn", None, None, None)          # no output_dir: no trained checkpoint to load


class _Eyes:
    """A camera on a tube (test_navigation's), the closed loop's _Eyes interface."""

    def __init__(self):
        from room_pipeline.navigation.closed_loop import _Eyes as Real
        from room_pipeline.navigation.depth_source import loop_camera
        from room_pipeline.navigation.closed_loop import EpisodeParams
        from tests.test_navigation import tube

        mesh, _ = tube(radius=0.005, straight=0.08)
        self.real = Real(mesh, loop_camera(EpisodeParams().image_px, EpisodeParams().fov_deg), rgb=True)
        self.camera = self.real.camera

    def rgb(self, pose):
        return self.real.rgb(pose)

    def depth(self, pose):
        return self.real.depth(pose)


def test_relative_estimator_is_median_scaled_to_gt_and_noise_is_seeded():
    from room_pipeline.navigation.depth_source import loop_camera
    from room_pipeline.navigation.closed_loop import EpisodeParams
    from tests.test_navigation import pose_at

    eyes = _Eyes()
    cam = loop_camera(EpisodeParams().image_px, EpisodeParams().fov_deg)
    pose = pose_at(0.01)
    gt = eyes.depth(pose)
    src = make_depth_source(NavPerception("tube_prior"), None, None, cam)
    d = src(eyes, pose)
    assert d.shape == gt.shape and src.last_scale is not None
    ok = (d > 0) & (gt > 0)
    assert abs(np.median(d[ok]) - np.median(gt[ok])) < 1e-9
    noisy = [make_depth_source(NavPerception("shading_sfs", 1.0), None, None, cam) for _ in range(2)]
    a, b = (n(eyes, pose) for n in noisy)
    assert np.array_equal(a, b)                       # same seed, same step: same noise
    clean = make_depth_source(NavPerception("shading_sfs", 0.0), None, None, cam)(eyes, pose)
    assert not np.array_equal(a, clean)


def test_closed_loop_plans_on_the_estimator_through_the_hook():
    """A 1 s episode in a straight tube with shading_sfs depth: the hook is called once per control step."""
    from room_pipeline.anatomy.centreline import CentrelineGraph, GraphBranch
    from room_pipeline.navigation.closed_loop import EpisodeParams, Patient, run_episode
    from room_pipeline.navigation.depth_source import loop_camera
    from room_pipeline.navigation.planner import PlannerParams
    from room_pipeline.robot.sim_params import SimParams
    from tests.test_navigation import tube

    mesh, C = tube(radius=0.006, straight=0.18)
    root = GraphBranch(0, -1, 0, C[:111], np.full(111, 0.006))
    child = GraphBranch(1, 0, 1, C[110:], np.full(len(C) - 110, 0.006))
    pat = Patient("tube", mesh, mesh, CentrelineGraph([root, child]))
    ep = EpisodeParams(policy="depth", max_time_s=1.0)
    src = make_depth_source(NavPerception("shading_sfs"), None, None, loop_camera(ep.image_px, ep.fov_deg))
    res = run_episode(pat, 1, ep, PlannerParams(), SimParams(), depth_source=src)
    assert isinstance(src, EstimatorDepth) and src.steps == res["control_steps"] == 10, (src.steps, res["control_steps"])


def test_demo_with_an_estimator_median_scales_it(dataset, tmp_path):
    """`--depth shading_sfs` (image only, relative): the demo plans on its median-scaled prediction."""
    r = room("navigate", "demo", dataset / PATIENT / RENDERED_SEQ, "--frames", "2", "--stride", "2",
             "--depth", "shading_sfs", "--out", tmp_path / "d")
    assert r.returncode == 0, r.stderr[-3000:]
    f = json.loads((tmp_path / "d" / "navigation_demo.json").read_text())["frames"][0]
    assert f["depth_source"] == "shading_sfs" and f["median_scale"] > 0


def test_route_command_points_where_the_sequence_goes():
    """The demo's operator word: the route's position 30 mm on, projected; None straight ahead or behind."""
    from room_pipeline.navigation.demo import route_command
    from room_pipeline.render.camera import CameraIntrinsics

    cam = CameraIntrinsics.from_fov(100, 100, 85.0)
    straight = np.array([[0.0, 0.0, z] for z in np.arange(0, 0.05, 0.001)])
    assert route_command(straight, 0, np.eye(4), cam) is None
    up = straight + np.array([[0.0, -0.4 * z, 0.0] for z in straight[:, 2]])       # the route rises (-y: up)
    cmd = route_command(up, 0, np.eye(4), cam)
    assert cmd is not None and cmd[1] < -0.99
    assert route_command(straight[::-1], 0, np.eye(4), cam) is None                # behind the camera


def test_demo_command_route_is_recorded(dataset, demo):
    f = json.loads((demo / "navigation_demo.json").read_text())["frames"][0]
    assert f["command"] == "route" and "command_uv" in f and f["goal_regions"] >= 1


def test_sweep_collects_episode_files_into_one_table(tmp_path):
    """benchmarks/navigation_sweep.py --collect: `room navigate episode --out` files -> one row per (depth, noise)."""
    base = {"patient": "p", "target": 3, "success": False, "time_s": 5.0, "path_length_mm": 20.0,
            "peak_contact_force_n": 0.1, "min_wall_clearance_mm": 0.5, "generation_reached": 1, "control_steps": 50,
            "cpu_per_step_s": {"total": 0.05}}
    runs = []
    for k, (d, n, oc) in enumerate([("gt", 0.0, "timeout"), ("cnn", 1.0, "wrong_branch"), ("cnn", 1.0, "reached")]):
        f = tmp_path / f"run{k}.json"
        f.write_text(json.dumps(base | {"outcome": oc, "success": oc == "reached", "perception": {"depth": d, "noise": n}}))
        runs.append(f)
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "navigation_sweep.py"), "--collect", *map(str, runs),
                        "--results", str(tmp_path / "res")], capture_output=True, text=True, encoding="utf-8")
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads((tmp_path / "res" / "navigation_sweep.json").read_text())
    cells = {(c["depth"], c["noise"]): c for c in doc["cells"]}
    assert set(cells) == {("gt", 0.0), ("cnn", 1.0)}
    assert cells[("cnn", 1.0)]["success"] == 1 and cells[("cnn", 1.0)]["outcomes"] == {"reached": 1, "wrong_branch": 1}
    assert "| cnn | 1 | 2 | 1/2 |" in (tmp_path / "res" / "navigation_sweep.md").read_text()


def test_sweep_merges_its_own_result_files(tmp_path):
    """--collect also takes the sweep's own result JSONs (one cell a process): their episodes in one table under
    --name, their commands listed; --report copies the table to reports/ (not exercised: it writes the repo)."""
    base = {"patient": "p", "target": 3, "success": True, "outcome": "reached", "time_s": 5.0, "path_length_mm": 20.0,
            "peak_contact_force_n": 0.1, "min_wall_clearance_mm": 0.5, "generation_reached": 4, "control_steps": 50,
            "cpu_per_step_s": {"total": 0.05}, "estimator_cpu_per_call_s": 0.01}
    files = []
    for d in ("gt", "cnn"):
        f = tmp_path / f"sweep_{d}.json"
        f.write_text(json.dumps({"command": f"python benchmarks/navigation_sweep.py --depth {d}", "what": "p; 1 target(s)",
                                 "load": 3.0 if d == "gt" else 5.0,
                                 "episodes": [base | {"perception": {"depth": d, "noise": 0.0}}]}))
        files.append(f)
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "navigation_sweep.py"), "--collect", *map(str, files),
                        "--results", str(tmp_path / "res"), "--name", "merged"], capture_output=True, text=True,
                       encoding="utf-8")
    assert r.returncode == 0, r.stderr[-2000:]
    doc = json.loads((tmp_path / "res" / "merged.json").read_text())
    assert [(c["depth"], c["success"]) for c in doc["cells"]] == [("cnn", 1), ("gt", 1)]
    assert doc["merged_from"] == [f"python benchmarks/navigation_sweep.py --depth {d}" for d in ("gt", "cnn")]
    assert doc["load"] == 5.0 and doc["what"] == "2 collected episodes; p; 1 target(s)"
    md = (tmp_path / "res" / "merged.md").read_text()
    assert "- `python benchmarks/navigation_sweep.py --depth cnn`" in md and "load up to 5.0" in md
