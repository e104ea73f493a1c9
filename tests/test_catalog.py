"""The dataset catalogue (room_pipeline.catalog) and the typed pose records (room_pipeline.io.records)."""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from room_pipeline import catalog
from room_pipeline.errors import ConfigError, InputError
from room_pipeline.io.records import POSE_KEY, pose_track, pose_track_from_doc
from room_pipeline.io.tum import parse_tum, tum_text
from room_pipeline.paths import PatientPaths

SRC = Path(__file__).resolve().parents[1] / "src" / "room_pipeline"


def test_split_key_and_paths(tmp_path):
    assert catalog.split_key("p/sequence_000") == ("p", "sequence_000")
    assert catalog.split_key("p/a/b") == ("p", "a/b")
    with pytest.raises(ConfigError, match="PATIENT/SEQUENCE"):
        catalog.split_key("p")
    pp = PatientPaths(tmp_path, "p")
    s = pp.seq("sequence_000")
    assert s.render_json == tmp_path / "p" / "sequence_000" / "metadata" / "render.json"
    assert s.camera == tmp_path / "p" / "sequence_000" / "calibration" / "camera_params.json"
    assert s.folder("normals").name == "surface_normals" and s.rgb_noisy.name == "rgb_noisy"
    assert s.frame("depth", 7, ".exr").name == "frame_0007.exr"
    assert pp.eval("sequence_000").pose == tmp_path / "evaluation" / "p" / "sequence_000" / "pose.json"
    assert pp.sequence_metadata("sequence_000") == s.metadata
    with pytest.raises(ConfigError, match="unknown modality"):
        s.folder("thermal")
    assert not s.is_rendered()


def test_layout_names_are_spelled_only_in_the_catalogue():
    """Every file and folder name the catalogue owns appears as a string literal in no other module."""
    names = {v for k, v in vars(catalog).items() if k.isupper() and isinstance(v, str) and "." in v}
    # folder names that are not also a modality's name or a config key (rgb_noisy is the modality's name:
    # the literal is checked below; relative_depth names both; point_clouds is also render.storage's key)
    names |= {v for k, v in catalog.FOLDERS.items() if v != k and v != "point_clouds"} | {"depth_model"}
    found = []
    for p in SRC.rglob("*.py"):
        if p.name == "catalog.py":
            continue
        text = p.read_text(encoding="utf-8")
        code = re.sub(r'""".*?"""', "", text, flags=re.S)          # docstrings may name the files
        for n in names:
            if f'"{n}"' in code or f"'{n}'" in code:
                found.append(f"{p.relative_to(SRC)}: {n}")
        if '"rgb_noisy"' in code:
            found.append(f"{p.relative_to(SRC)}: rgb_noisy")
    assert not found, sorted(found)


def _doc(key, n=3, arc=True):
    return {"frames": [{"timestamp": 0.1 * i, key: np.eye(4).tolist(), **({"arclength": 0.01 * i} if arc else {})}
                       for i in range(n)]}


@pytest.mark.parametrize("name", sorted(POSE_KEY))
def test_pose_track_reads_each_pose_file(tmp_path, name):
    p = tmp_path / name
    p.write_text(json.dumps(_doc(POSE_KEY[name])))
    t = pose_track(p)
    assert len(t) == 3 and t.poses.shape == (3, 4, 4) and np.allclose(t.timestamps, [0.0, 0.1, 0.2])
    assert t.positions.shape == (3, 3) and t.arclength is not None


def test_pose_track_hard_cases(tmp_path):
    empty = pose_track_from_doc({"frames": []}, "pose")
    assert len(empty) == 0 and empty.poses.shape == (0, 4, 4) and empty.arclength is None
    assert pose_track_from_doc(_doc("pose", arc=False), "pose").arclength is None
    with pytest.raises(InputError, match="tip_pose"):
        pose_track_from_doc(_doc("pose"), "tip_pose", "simulation.json")
    bad = {"frames": [{"timestamp": 0.0, "pose": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}]}
    with pytest.raises(InputError, match="expected 4x4"):
        pose_track_from_doc(bad, "pose")
    with pytest.raises(InputError, match="not a pose file"):
        pose_track(tmp_path / "noise.json")
    (tmp_path / "render.json").write_text("{not json")
    with pytest.raises(InputError, match="cannot read"):
        pose_track(tmp_path / "render.json")


def test_tum_round_trip_and_empty():
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    poses = np.tile(np.eye(4), (4, 1, 1))
    poses[:, :3, :3] = Rotation.random(4, random_state=1).as_matrix()
    poses[:, :3, 3] = rng.normal(size=(4, 3))
    ts, back = parse_tum(tum_text(np.arange(4) * 0.1, poses))
    assert np.allclose(back, poses, atol=1e-8) and np.allclose(ts, np.arange(4) * 0.1)
    ts, back = parse_tum("# only a comment\n")
    assert ts.shape == (0,) and back.shape == (0, 4, 4)
    with pytest.raises(InputError, match="8 numbers"):
        parse_tum("0 1 2 3\n")


def test_sequence_record_hashes_what_it_names(tmp_path):
    """sequence_index/<sequence>.<stage>.json: sha256 per named output (null when not written), the same bytes
    for the same frames."""
    from room_pipeline.stages.common import write_sequence_record

    pp = PatientPaths(tmp_path, "p")
    s = pp.seq("sequence_000")
    s.folder("rgb").mkdir(parents=True)
    s.frame("rgb", 0, ".png").write_bytes(b"frame")
    files = {"rgb": s.folder("rgb"), "depth": s.folder("depth")}
    write_sequence_record(pp, "sequence_000", "render", files)
    rec = pp.sequence_record("sequence_000", "render")
    assert rec == tmp_path / "p" / "sequence_index" / "sequence_000.render.json"
    doc = json.loads(rec.read_text())
    assert doc["depth"] is None and len(doc["rgb"]) == 64
    first = rec.read_bytes()
    write_sequence_record(pp, "sequence_000", "render", files)
    assert rec.read_bytes() == first
    s.frame("rgb", 0, ".png").write_bytes(b"other")
    write_sequence_record(pp, "sequence_000", "render", files)
    assert json.loads(rec.read_text())["rgb"] != doc["rgb"]


def test_find_sequences_below_a_root_a_patient_or_a_sequence(tmp_path):
    """catalog.find_sequences: the sequences whose record file exists, from a dataset root, a patient folder or
    the sequence folder itself, sorted; an unknown record name is a ConfigError."""
    pp = PatientPaths(tmp_path, "p")
    done, planned = pp.seq("sequence_000"), pp.seq("sequence_001")
    for s in (done, planned):
        s.metadata.mkdir(parents=True)
        s.trajectory.write_text("{}")
    done.render_json.write_text("{}")
    assert catalog.find_sequences(tmp_path) == [done]
    assert catalog.find_sequences(tmp_path, "trajectory") == [done, planned]
    assert catalog.find_sequences(pp.root, "trajectory") == [done, planned]
    assert catalog.find_sequences(done.root) == [done] and catalog.find_sequences(tmp_path / "absent") == []
    with pytest.raises(ConfigError, match="unknown sequence record"):
        catalog.find_sequences(tmp_path, "frames")
