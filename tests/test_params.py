"""One way to read config sections: :func:`room_pipeline.config.params.params_from_dict` (issue #14).

Every parameter dataclass of src builds from its section through it (then its ``__post_init__`` checks
ranges); nullable fields (``X | None``) take null; trajectory.json's ``params`` block keeps its bytes.
"""
from __future__ import annotations

import ast
import dataclasses
import json

import pytest
import yaml

from room_pipeline.anatomy.segment_params import SegmentParams
from room_pipeline.config.compose import compose, section
from room_pipeline.config.params import field_kind, params_from_dict
from room_pipeline.errors import ConfigError
from room_pipeline.navigation.depth_source import NAVIGATE_SUBSECTIONS, NavPerception
from room_pipeline.planning.trajectory_params import TrajectoryParams
from room_pipeline.robot.kinematics import ScopeGeometry

from .conftest import REPO

SRC = REPO / "src" / "room_pipeline"

#: ``from_*`` methods of src's dataclasses that read no config section, so do not go through
#: params_from_dict: (module path under src/room_pipeline, class, method) -> why
NOT_CONFIG = {
    ("anatomy/centreline.py", "CentrelineGraph", "from_dict"): "a record: parses centreline.json (arrays)",
    ("anatomy/tree.py", "Branch", "from_dict"): "a record: one branch of an airway-tree JSON file",
    ("anatomy/tree.py", "AirwayTree", "from_dict"): "a record: an airway-tree JSON file",
    ("render/camera.py", "CameraIntrinsics", "from_dict"): "a record: a sequence's camera.json (pinhole + distortion)",
    ("render/camera.py", "CameraIntrinsics", "from_fov"): "a constructor from a field of view, no mapping",
    ("depth/physics.py", "LightModel", "from_render_metadata"): "a record: the light block of render.json",
}


@dataclasses.dataclass
class _Demo:
    ratio: float = 1.0
    count: int = 2
    flag: bool = False
    name: str = "a"
    maybe_float: float | None = -500.0
    maybe_int: int | None = None
    maybe_str: str | None = None
    items: tuple = ()
    anything: object = None


def test_field_kinds_follow_default_then_annotation():
    kinds = {f.name: field_kind(_Demo, f) for f in dataclasses.fields(_Demo)}
    assert kinds == {"ratio": (float, False), "count": (int, False), "flag": (bool, False), "name": (str, False),
                     "maybe_float": (float, True), "maybe_int": (int, True), "maybe_str": (str, True),
                     "items": (None, False), "anything": (None, True)}


def test_optional_fields_take_null_and_their_type_only():
    p = params_from_dict(_Demo, {"maybe_float": None, "maybe_int": None, "maybe_str": None, "anything": None},
                         "demo")
    assert (p.maybe_float, p.maybe_int, p.maybe_str, p.anything) == (None, None, None, None)
    p = params_from_dict(_Demo, {"maybe_float": -400, "maybe_int": 3.0, "maybe_str": "x", "ratio": 2,
                                 "items": [1, 2]}, "demo")
    assert (p.maybe_float, p.maybe_int, p.maybe_str, p.ratio, p.items) == (-400.0, 3, "x", 2.0, (1, 2))
    assert type(p.maybe_float) is float and type(p.maybe_int) is int and type(p.ratio) is float
    for key, bad in (("maybe_int", 2.5), ("maybe_str", 3), ("maybe_float", "1"), ("maybe_float", True),
                     ("ratio", None), ("count", None), ("flag", None), ("name", None), ("ratio", "10"),
                     ("count", float("inf")), ("count", float("nan")), ("flag", 1)):
        with pytest.raises(ConfigError, match=rf"^demo\.{key}: expected ") as err:
            params_from_dict(_Demo, {key: bad}, "demo")
        assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match=r"unknown key 'demo\.nope'"):
        params_from_dict(_Demo, {"nope": 1}, "demo")


def test_no_dataclass_hand_rolls_from_dict():
    """Each ``from_*`` method of a dataclass in src calls params_from_dict, or is a listed non-config reader."""
    found, hand_rolled = set(), []
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC).as_posix()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not isinstance(node, ast.ClassDef) or not any("dataclass" in ast.unparse(d)
                                                             for d in node.decorator_list):
                continue
            for fn in node.body:
                if isinstance(fn, ast.FunctionDef) and fn.name.startswith("from_"):
                    key = (rel, node.name, fn.name)
                    found.add(key)
                    calls = {ast.unparse(c.func).split(".")[-1] for c in ast.walk(fn) if isinstance(c, ast.Call)}
                    if "params_from_dict" not in calls and key not in NOT_CONFIG:
                        hand_rolled.append(f"{rel}: {node.name}.{fn.name}")
    assert not hand_rolled, "read these through params_from_dict (or list them in NOT_CONFIG with why): " + \
        ", ".join(hand_rolled)
    assert set(NOT_CONFIG) <= found, f"stale NOT_CONFIG entries: {sorted(set(NOT_CONFIG) - found)}"


def _old_trajectory_params(d: dict) -> TrajectoryParams:
    """The hand-rolled reader TrajectoryParams.from_dict had until session 10: ``cls(**d)``."""
    return TrajectoryParams(**d)


@pytest.mark.parametrize("overrides", [
    {},
    {"rate_hz": 10, "speed_mm_s": 5, "kappa_max": 40, "max_generation": 4.0, "n": 3.0, "centring_weight": 0.0001},
    {"targets": "points", "points": [[0.0, 0.01, -0.02], [0, 0, 0.5]], "joint_plan": {"enabled": False},
     "max_generation": None, "stop_at_wall": False, "view_jitter_deg": 1},
])
def test_trajectory_params_write_the_same_bytes_as_before(overrides):
    """trajectory.json's ``params`` (``to_dict``) is the same JSON through params_from_dict as through the old
    ``cls(**d)`` (whose ``__post_init__`` converts numbers the same way), for conf's values and for ints given
    to float fields (and floats to int fields)."""
    conf = yaml.safe_load((REPO / "conf" / "trajectory" / "default.yaml").read_text(encoding="utf-8"))
    for base in (conf, section(compose(conf_dir=REPO / "conf"), "trajectory")):
        d = {**base, **overrides}
        new = TrajectoryParams.from_dict(json.loads(json.dumps(d))).to_dict()
        old = _old_trajectory_params(json.loads(json.dumps(d))).to_dict()
        assert json.dumps(new, indent=1, sort_keys=True) == json.dumps(old, indent=1, sort_keys=True)
        assert json.dumps(new) == json.dumps(old)


def test_trajectory_params_reject_wrong_types():
    for key, bad in (("rate_hz", "10"), ("n", 2.5), ("stop_at_wall", 1), ("max_generation", "6"),
                     ("kappa_max", True)):
        with pytest.raises(ConfigError, match=rf"trajectory\.{key}"):
            TrajectoryParams.from_dict({key: bad})
    with pytest.raises(ConfigError, match=r"unknown key 'trajectory\.speed_mm'"):
        TrajectoryParams.from_dict({"speed_mm": 3})


def test_segment_params_nullable_fields_and_checks_in_post_init():
    p = SegmentParams.from_dict({"refine_hu": None, "thin_airway_hu": None, "weights_dir": None})
    assert (p.refine_hu, p.thin_airway_hu, p.weights_dir) == (None, None, None)
    assert SegmentParams.from_dict({"refine_hu": -400}).refine_hu == -400.0
    for key, bad in (("air_hu", None), ("connectivity", None), ("weights_dir", 3), ("refine_hu", "low"),
                     ("connectivity", 6.5)):
        with pytest.raises(ConfigError, match=rf"segment\.{key}: expected"):
            SegmentParams.from_dict({key: bad})
    with pytest.raises(ConfigError, match=r"segment\.leak_factor"):
        SegmentParams(leak_factor=1.0)                # __post_init__ checks a direct construction too


def test_scope_geometry_through_params_from_dict():
    g = ScopeGeometry.from_dict({"l": 0.04, "gamma": 0.002, "q1_max": 0.006})
    assert (g.l, g.gamma, g.q1_max) == (0.04, 0.002, 0.006)
    assert ScopeGeometry.from_dict({"l": 1}).l == 1.0 and type(ScopeGeometry.from_dict({"l": 1}).l) is float
    with pytest.raises(ConfigError, match=r"unknown key 'robot\.lenght'"):
        ScopeGeometry.from_dict({"lenght": 0.05})
    with pytest.raises(ConfigError, match=r"robot\.l: expected float"):
        ScopeGeometry.from_dict({"l": "5cm"})


def test_navigate_section_is_perception_plus_its_subsections():
    conf = yaml.safe_load((REPO / "conf" / "navigate" / "default.yaml").read_text(encoding="utf-8"))
    fields = {f.name for f in dataclasses.fields(NavPerception)}
    assert set(conf) == fields | set(NAVIGATE_SUBSECTIONS)
    assert NavPerception.from_navigate(conf) == NavPerception()
    assert NavPerception.from_navigate({"depth": "shading_sfs", "noise": 1}) == NavPerception("shading_sfs", 1.0)
    with pytest.raises(ConfigError, match=r"unknown key 'navigate\.depht'"):
        NavPerception.from_navigate({"depht": "gt"})
    for key, bad in (("noise", "1"), ("depth", 3), ("noise", -1.0)):
        with pytest.raises(ConfigError, match=rf"navigate\.{key}"):
            NavPerception.from_navigate({key: bad})


def test_navigate_benchmark_and_episode_read_without_the_physics():
    """``room navigate`` / the navigation benchmarks read ``navigate.episode`` and ``navigate.benchmark`` through
    the one reader, from a module that does not import PyBullet (closed_loop re-exports EpisodeParams)."""
    import subprocess
    import sys

    from room_pipeline.navigation import closed_loop
    from room_pipeline.navigation.params import BenchmarkParams, EpisodeParams

    assert closed_loop.EpisodeParams is EpisodeParams
    assert BenchmarkParams.from_dict({"seed": 1, "policies": ["depth"]}) == BenchmarkParams(seed=1, policies=("depth",))
    for key, bad, msg in (("min_route_radius_mm", 0.0, "min_route_radius_mm"), ("policies", ["walk"], "policies"),
                          ("seed", "1", "navigate.benchmark.seed"), ("targets", 3, "navigate.benchmark.targets")):
        with pytest.raises(ConfigError, match=msg):
            BenchmarkParams.from_dict({key: bad})
    code = ("import sys, room_pipeline.navigation.params, room_pipeline.navigation.cli; "
            "print(any(m.startswith('pybullet') for m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, encoding="utf-8", check=True)
    assert out.stdout.strip() == "False"


def _old_segment_params(d: dict) -> SegmentParams:
    """The hand-rolled reader SegmentParams.from_dict had until session 10 (its conversions, then validate)."""
    names = {f.name: f for f in dataclasses.fields(SegmentParams)}
    kw = {}
    for k, v in d.items():
        default = names[k].default
        if v is None:
            kw[k] = None
        elif isinstance(default, bool):
            kw[k] = v
        elif isinstance(default, int):
            kw[k] = int(v)
        elif isinstance(default, float) or k in ("refine_hu", "thin_airway_hu"):
            kw[k] = float(v)
        else:
            kw[k] = str(v)
    return SegmentParams(**kw)


@pytest.mark.parametrize("overrides", [[], ["patients=shared_masks"], ["patients=phantom_cohort"], ["patients=reference_tree"],
                                       ["segment=totalsegmentator"], ["trajectory.stop_at_wall=false"],
                                       ["patients=shared_masks", "render.max_frames=30"]])
def test_every_composed_config_reads_to_the_same_params_as_before(overrides):
    """The pipeline's compositions (the default, the shared real masks, the cohort, TotalSegmentator) give the
    same SegmentParams and TrajectoryParams (and trajectory.json bytes) through params_from_dict as through the
    readers they replace, so every mask's segment and trajectory stages see the same parameters."""
    cfg = compose(overrides, conf_dir=REPO / "conf")
    seg, traj = section(cfg, "segment"), section(cfg, "trajectory")
    assert SegmentParams.from_dict(seg) == _old_segment_params(seg)
    new, old = TrajectoryParams.from_dict(traj), _old_trajectory_params(section(cfg, "trajectory"))
    assert new == old and json.dumps(new.to_dict()) == json.dumps(old.to_dict())


def test_phantom_entry_reads_through_the_one_reader():
    """phantoms.<patient> (the seed the phantom stage and Table III read) goes through params_from_dict: a bad
    value or key is one ConfigError line naming it; a patient that is no phantom is refused."""
    from omegaconf import OmegaConf

    from room_pipeline.config.compose import PhantomEntry, phantom_entry
    from room_pipeline.errors import ConfigError

    cfg = OmegaConf.create({"phantoms": {"a": {"seed": 3}, "b": None, "c": {"seed": "x"}, "d": {"sed": 1}}})
    assert phantom_entry(cfg, "a") == PhantomEntry(seed=3) and phantom_entry(cfg, "b").seed == 0
    for patient, message in (("c", r"phantoms\.c\.seed: expected int"), ("d", r"unknown key 'phantoms\.d\.sed'"),
                             ("e", "not a phantom patient")):
        with pytest.raises(ConfigError, match=message):
            phantom_entry(cfg, patient)
