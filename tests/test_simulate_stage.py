"""The simulate stage's own geometry: opening the airway entrance for the scope."""
from __future__ import annotations

import numpy as np

from room_pipeline.io.mesh import Mesh
from room_pipeline.io.tum import tum_text as tum
from room_pipeline.robot.sequence_sim import open_entrance


def _tube(radius=5e-3, z0=0.0, z1=0.1, n=24, m=20):
    """A closed tube along z (side + two fan caps)."""
    th = 2 * np.pi * np.arange(n) / n
    rings = [np.stack([radius * np.cos(th), radius * np.sin(th), np.full(n, z)], 1) for z in np.linspace(z0, z1, m)]
    v = np.concatenate(rings + [np.array([[0, 0, z0], [0, 0, z1]])])
    f = []
    for k in range(m - 1):
        for i in range(n):
            a, b = k * n + i, k * n + (i + 1) % n
            f += [[a, b, b + n], [a, b + n, a + n]]
    c0, c1 = len(v) - 2, len(v) - 1
    for i in range(n):
        f += [[c0, (i + 1) % n, i], [c1, (m - 1) * n + i, (m - 1) * n + (i + 1) % n]]
    return Mesh(v, np.array(f))


def test_open_entrance_removes_only_the_proximal_cap_region():
    mesh = _tube()
    start = np.array([0.0, 0.0, 0.09])       # first pose 10 mm below the top cap
    tangent = np.array([0.0, 0.0, -1.0])     # looking down the tube
    opened, n = open_entrance(mesh, start, tangent, radius=5e-3)
    c = opened.vertices[opened.faces].mean(axis=1)
    assert n > 0 and opened.n_faces == mesh.n_faces - n
    assert np.all(c[:, 2] <= 0.09 + 1e-12)   # nothing left behind the start plane near the axis
    assert np.isclose(c[:, 2].min(), mesh.vertices[mesh.faces].mean(axis=1)[:, 2].min())  # far cap kept


def test_tum_text_has_unit_quaternions():
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, :3, 3] = np.arange(9).reshape(3, 3) * 1e-3
    lines = [ln for ln in tum(np.array([0.0, 0.1, 0.2]), poses).splitlines() if not ln.startswith("#")]
    q = np.array([[float(x) for x in ln.split()[4:]] for ln in lines])
    assert len(lines) == 3 and np.allclose(np.linalg.norm(q, axis=1), 1.0)


# --------------------------------------------------------------------------- bad input: one line, exit 2 (issue #17)


def _write_inputs(out, frames=None, graph=None, obj=None):
    import json

    from room_pipeline.io.mesh import write_obj
    from room_pipeline.paths import PatientPaths

    paths = PatientPaths(out, "patient_000")
    meta = paths.sequence_metadata("sequence_000")
    meta.mkdir(parents=True, exist_ok=True)
    paths.collision_mesh.parent.mkdir(parents=True, exist_ok=True)
    if frames is None:
        frames = []
        for i in range(20):
            pose = np.eye(4)
            pose[:3, 3] = [0.0, 0.0, 0.06 + 0.001 * i]
            frames.append({"timestamp": 0.1 * i, "pose": pose.tolist(), "arclength": 0.001 * i})
    (meta / "trajectory.json").write_text(json.dumps({"frames": frames}))
    if graph is not False:
        g = graph or {"branches": [{"parent": -1, "mean_radius": 0.005}]}
        paths.centreline_graph.write_text(json.dumps(g))
    if obj is None:
        write_obj(paths.collision_mesh, _tube(z0=-0.02, z1=0.2))
    else:
        paths.collision_mesh.write_text(obj)
    return meta


def _nan_frames():
    frames = []
    for i in range(5):
        pose = np.eye(4)
        pose[:3, 3] = [0.0, 0.0, 0.06 + 0.001 * i]
        frames.append({"timestamp": 0.1 * i, "pose": pose.tolist(), "arclength": 0.001 * i})
    frames[2]["pose"][0][3] = float("nan")
    return frames


def _backwards_frames():
    frames = []
    for i in range(5):
        pose = np.eye(4)
        pose[:3, 3] = [0.0, 0.0, 0.06 + 0.001 * i]
        frames.append({"timestamp": 0.1 * (i % 3), "pose": pose.tolist(), "arclength": 0.001 * i})
    return frames


import pytest  # noqa: E402


@pytest.mark.parametrize("case, words", [
    ("nan_pose", "non-finite"),
    ("backwards_time", "timestamps must increase"),
    ("one_frame", "at least 2 frames"),
    ("no_frames_key", "cannot read"),
    ("no_graph", "cannot read"),
    ("no_root", "no root branch"),
    ("bad_face", "collision mesh"),
])
def test_simulate_bad_input_is_one_line_exit_2_no_outputs(tmp_path, capsys, case, words):
    from room_pipeline import cli

    out = tmp_path / "out"
    kw = {}
    if case == "nan_pose":
        kw["frames"] = _nan_frames()
    elif case == "backwards_time":
        kw["frames"] = _backwards_frames()
    elif case == "one_frame":
        kw["frames"] = [{"timestamp": 0.0, "pose": np.eye(4).tolist(), "arclength": 0.0}]
    elif case == "no_graph":
        kw["graph"] = False
    elif case == "no_root":
        kw["graph"] = {"branches": [{"parent": 0, "mean_radius": 0.005}]}
    elif case == "bad_face":
        kw["obj"] = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n"
    meta = _write_inputs(out, **kw)
    if case == "no_frames_key":
        (meta / "trajectory.json").write_text('{"poses": []}')
    before = {p for p in out.rglob("*") if p.is_file()}
    capsys.readouterr()
    rc = cli.main(["stage", "simulate", "--patient", "patient_000/sequence_000", f"output_dir={out}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and err[0].startswith("room: error:") and words in err[0], err
    assert {p for p in out.rglob("*") if p.is_file()} == before          # nothing written
