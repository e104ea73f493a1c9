"""Monocular depth: metrics and their hard cases, physics baseline, registry, external/HF adapters, CNN, stages."""
from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf

from room_pipeline.depth import metrics as dm
from room_pipeline.io.metrics import read_metrics_file, read_with_timings, split_timings
from room_pipeline.depth.estimators import (DepthParams, Estimator, Frame, SequenceInfo, evaluate, sequence_samples,
                                            try_create)
from room_pipeline.depth.physics import (LightModel, PhysicsParams, camera_cos, physics_depth, srgb8_to_linear)
from room_pipeline.errors import BackendUnavailable, ConfigError, InputError
from room_pipeline.io.images import write_exr, write_png8
from room_pipeline.render.camera import CameraIntrinsics
from room_pipeline.render.raycast import RaycastRenderer
from room_pipeline.render.scene import Film, Scene, TipLight, TissueMaterial
from room_pipeline.render.shading import linear_to_srgb8
from tests.conftest import REPO, shared_path
from tests.test_raycast import look, tube

MM = 1e-3
RANGE = (1 * MM, 200 * MM)


# --------------------------------------------------------------------------- fixtures


def render_tube(n: int = 3, size: int = 48, material: TissueMaterial | None = None, wobble: float = 0.1):
    """A few frames inside a tube (the open far end shows nothing): renderer outputs and the renderer."""
    cam = CameraIntrinsics.from_fov(size, size, 85.0, 0.1 * MM, 0.5)
    poses = [look([0.3 * MM * i, 0.0, 2 * MM * i], [0.02 * i, 0.05, 1.0]) for i in range(n)]
    sc = Scene(tube(radius=5 * MM, wobble=wobble), cam, np.array(poses), np.arange(n) * 0.1,
               material=material or TissueMaterial(), light=TipLight(), film=Film())
    r = RaycastRenderer(sc)
    return [r.render(i, ("rgb", "depth", "normals")) for i in range(n)], r


def write_sequence(root, n: int = 3, size: int = 48, blank: bool = False):
    """A rendered sequence in the ROOM layout (rgb, depth, calibration, render.json) under ``root``."""
    outs, r = render_tube(n, size)
    for i, o in enumerate(outs):
        depth = np.zeros_like(o["depth"]) if blank else np.where(o["hit"], o["depth"], 0).astype(np.float32)
        write_png8(root / "rgb" / f"frame_{i:04d}.png", o["rgb"])
        write_exr(root / "depth" / f"frame_{i:04d}.exr", depth, channels=("Y",))
    (root / "calibration").mkdir(parents=True, exist_ok=True)
    (root / "calibration" / "camera_params.json").write_text(json.dumps(r.scene.camera.to_dict()))
    (root / "metadata").mkdir(parents=True, exist_ok=True)
    (root / "metadata" / "render.json").write_text(json.dumps({"renderer": r.metadata()}))
    return outs, r


def depth_cfg(tmp_path, **depth):
    base = OmegaConf.to_container(OmegaConf.load(REPO / "conf" / "depth" / "default.yaml"))
    base["input"] = "rgb"                   # write_sequence renders clean frames only (the default reads rgb_noisy)
    base["frame_stride"] = 1                # the tiny test sequences are scored frame by frame
    base.update(depth)
    return OmegaConf.create({"output_dir": str(tmp_path / "out"), "sequences": ["sequence_000"],
                             "phantoms": {"patient_000": {"seed": 0}},
                             "patients": {"patient_000": {"kind": "ct", "input": "x"}}, "depth": base})


class Constant(Estimator):
    """Returns a fixed map (for the evaluation loop's hard cases)."""

    def __init__(self, value: np.ndarray, scaling: str = "metric", resizes: bool = False) -> None:
        self.name, self.value, self.scaling, self.resizes = "const", value, scaling, resizes

    def predict(self, frame: Frame) -> np.ndarray:
        return self.value


def fake_model(rgb, camera, scale=1.0):
    """A 'module:function' external model: a constant 3 cm plane."""
    assert rgb.dtype == np.uint8 and "fx" in camera
    return np.full(rgb.shape[:2], 30.0 * scale, np.float32)


# --------------------------------------------------------------------------- metrics


def test_metrics_known_values():
    gt = np.full((4, 5), 0.02)
    e = dm.frame_errors(gt, gt * 1.1, RANGE)
    assert e.n_valid == 20 and e.n_gt == 20
    assert e.AbsRel == pytest.approx(0.1) and e.L1_mm == pytest.approx(2.0) and e.RMSE_mm == pytest.approx(2.0)
    assert (e.delta1, e.delta2, e.delta3) == (1.0, 1.0, 1.0)
    e = dm.frame_errors(gt, gt * 2.0, RANGE)                   # ratio 2: > 1.25, > 1.5625, < 1.953? no: 2 > 1.953
    assert (e.delta1, e.delta2, e.delta3) == (0.0, 0.0, 0.0)
    e = dm.frame_errors(gt, gt * 1.5, RANGE)
    assert (e.delta1, e.delta2, e.delta3) == (0.0, 1.0, 1.0)
    perfect = dm.frame_errors(gt, gt, RANGE)
    assert perfect.L1_mm == 0 and perfect.AbsRel == 0 and perfect.delta1 == 1


def test_metrics_no_valid_pixel_is_nan_not_error():
    gt = np.zeros((6, 6), np.float32)                         # renderer's 'no hit' everywhere
    e = dm.frame_errors(gt, np.ones_like(gt), RANGE)
    assert e.n_valid == 0 and e.n_gt == 0 and all(math.isnan(getattr(e, k)) for k in dm.METRIC_KEYS)
    out_of_range = dm.frame_errors(np.full((3, 3), 0.5), np.ones((3, 3)), RANGE)   # 500 mm > 200 mm
    assert out_of_range.n_valid == 0
    agg = dm.aggregate([e, out_of_range])
    assert agg["n_frames"] == 2 and agg["n_frames_valid"] == 0 and math.isnan(agg["AbsRel"])
    assert math.isnan(dm.aggregate([]).get("L1_mm"))


def test_metrics_nan_inf_and_negative_predictions_are_counted_invalid():
    gt = np.full((2, 4), 0.01)
    pred = np.array([[0.01, np.nan, np.inf, -np.inf], [0.011, -0.01, 0.0, 0.01]])
    e = dm.frame_errors(gt, pred, RANGE)
    assert (e.n_valid, e.n_nonfinite, e.n_nonpositive, e.n_gt) == (3, 3, 2, 8)
    assert e.AbsRel == pytest.approx(0.1 / 3)
    assert all(math.isfinite(getattr(e, k)) for k in dm.METRIC_KEYS)
    agg = dm.aggregate([e, e])
    assert agg["n_nonfinite_pixels"] == 6 and agg["n_nonpositive_pixels"] == 4


def test_wrong_sized_prediction_is_a_clear_error():
    gt = np.full((4, 6), 0.02)
    with pytest.raises(InputError, match=r"shape \(6, 4\).*ground truth \(4, 6\)"):
        dm.frame_errors(gt, np.ones((6, 4)), RANGE)
    with pytest.raises(InputError, match="must declare that it resizes"):
        dm.fit_to_shape(np.ones((2, 3)), (4, 6), resizes=False, where="m")
    with pytest.raises(InputError, match=r"\(H, W\)"):
        dm.fit_to_shape(np.ones((2, 3, 1)), (2, 3), resizes=True)
    up = dm.fit_to_shape(np.full((2, 3), 0.5), (4, 6), resizes=True)
    assert up.shape == (4, 6) and np.allclose(up, 0.5)
    holes = np.full((8, 8), 0.5, np.float32)
    holes[0, 0] = np.nan
    r = dm.fit_to_shape(holes, (16, 16), resizes=True)
    assert np.isnan(r[0, 0]) and np.isfinite(r[8:, 8:]).all()         # NaN stays invalid, never averaged in


@settings(max_examples=25, deadline=None)
@given(st.floats(1e-3, 1e3), st.integers(0, 2**31 - 1))
def test_median_scaling_removes_any_global_scale(c, seed):
    rng = np.random.default_rng(seed)
    gts = [rng.uniform(0.005, 0.1, (5, 7)) for _ in range(3)]
    preds = [g * c for g in gts]
    s = dm.median_scale(gts, preds, RANGE)
    assert s == pytest.approx(1 / c, rel=1e-9)
    scaler = dm.MedianScaler(RANGE)
    for g, p in zip(gts, preds):
        scaler.add(g, p)
    assert scaler.scale() == pytest.approx(1 / c, rel=2e-4)        # histogram median: 1e-4 bins in log
    assert dm.frame_errors(gts[0], preds[0], RANGE, scale=s).AbsRel < 1e-9


@settings(max_examples=25, deadline=None)
@given(st.integers(1, 400), st.integers(0, 2**31 - 1))
def test_log_median_matches_numpy(n, seed):
    v = np.exp(np.random.default_rng(seed).normal(-3, 2, n))
    lm = dm.LogMedian()
    lm.add(v[: n // 2])
    lm.add(v[n // 2:])
    exact = np.median(v)
    lo, hi = np.sort(v)[(n - 1) // 2], np.sort(v)[n // 2]
    assert lo * (1 - 2e-4) <= lm.median() <= hi * (1 + 2e-4) or lm.median() == pytest.approx(exact, rel=2e-4)
    assert math.isnan(dm.LogMedian().median())


# --------------------------------------------------------------------------- physics baseline


def test_srgb_decode_inverts_the_renderer_encoding():
    codes = np.arange(256, dtype=np.uint8)
    lin = srgb8_to_linear(codes)
    assert np.array_equal(linear_to_srgb8(lin), codes)
    assert lin[0] == 0 and lin[255] == pytest.approx(1.0)


def test_light_model_from_both_metadata_layouts():
    _, r = render_tube(1, 16)
    meta = json.loads(json.dumps(r.metadata()))
    m = LightModel.from_render_metadata(meta)
    assert m.exposure_ev == r.exposure_ev and m.material == r.scene.material and m.light == r.scene.light
    cycles = {"rgb": {"backend": "blender_cycles", "exposure_ev": 1.5, "settings": {}}, "geometry": meta}
    assert LightModel.from_render_metadata(cycles).exposure_ev == 1.5
    with pytest.raises(InputError, match="light model"):
        LightModel.from_render_metadata({"backend": "x"})


def test_light_model_takes_each_frames_exposure_when_the_run_meters_per_frame():
    """With per-frame automatic exposure the physics baseline must undo each frame's own EV (render.json
    film.frame_ev), not the first frame's: on the default run the exposure drifts by > 5 EV along a sequence."""
    meta = {"material": dataclasses.asdict(TissueMaterial()), "light": dataclasses.asdict(TipLight()),
            "exposure_ev": -0.4, "film": {"frame_ev": [-0.25, -2.5, -5.0]}}
    m = LightModel.from_render_metadata(meta)
    assert [m.at_frame(i).exposure_ev for i in range(3)] == [-0.25, -2.5, -5.0]
    fixed = LightModel.from_render_metadata({k: v for k, v in meta.items() if k != "film"})
    assert fixed.at_frame(2).exposure_ev == -0.4
    with pytest.raises(InputError, match="frame 3 has no exposure"):
        m.at_frame(3)


def test_physics_depth_recovers_metric_depth_with_true_cosines():
    """With the true cosine the inversion is exact up to 8-bit quantisation (unclipped pixels)."""
    outs, r = render_tube(1, 64, wobble=0.0)
    o = outs[0]
    model = LightModel.from_render_metadata(r.metadata())
    cam = r.scene.camera
    rays = cam.pixel_rays()
    cos = -np.einsum("hwi,hwi->hw", o["normals"], rays) / np.linalg.norm(rays, axis=-1)
    from room_pipeline.depth.physics import _log_distance, _rays, brdf_k

    lin = srgb8_to_linear(o["rgb"]) * np.float32(2.0 ** -model.exposure_ev)
    z = np.exp(_log_distance(lin, o["rgb"], brdf_k(np.clip(cos, 0.05, 1), model), 255)) / _rays(cam)[2]
    ok = o["hit"] & (o["rgb"].max(axis=-1) < 255) & (o["rgb"].min(axis=-1) > 20)
    rel = np.abs(z[ok] - o["depth"][ok]) / o["depth"][ok]
    assert ok.sum() > 500 and np.median(rel) < 0.01


def test_physics_iterated_cosine_beats_unit_cosine_on_a_tube():
    outs, r = render_tube(2, 64)
    model = LightModel.from_render_metadata(r.metadata())
    cam = r.scene.camera
    err = {}
    for cos_model in ("unit", "iterate"):
        p = PhysicsParams(cos_model=cos_model, iterations=1)
        preds = [physics_depth(o["rgb"], cam, model, p) for o in outs]
        gts = [np.where(o["hit"], o["depth"], 0) for o in outs]
        assert all(pr.shape == (64, 64) and pr.dtype == np.float32 and np.isfinite(pr).all() for pr in preds)
        err[cos_model] = dm.aggregate([dm.frame_errors(g, pr, RANGE) for g, pr in zip(gts, preds)])["AbsRel"]
    assert err["iterate"] < err["unit"] and err["iterate"] < 0.35
    with pytest.raises(InputError, match="camera is 64x64"):
        physics_depth(outs[0]["rgb"][:32], cam, model)
    with pytest.raises(ConfigError, match="cos_model"):
        PhysicsParams(cos_model="guess")


def test_camera_cos_of_a_fronto_parallel_plane():
    cam = CameraIntrinsics.from_fov(40, 30, 80.0)
    cos = camera_cos(np.full((30, 40), 0.05, np.float32), cam, 1.0)
    rays = cam.pixel_rays()
    expect = 1 / np.linalg.norm(rays, axis=-1)               # normal (0, 0, -1) against each ray
    assert np.allclose(cos[2:-2, 2:-2], expect[2:-2, 2:-2], atol=1e-4)


# --------------------------------------------------------------------------- registry, evaluation loop


def test_default_config_parses_and_bad_names_are_config_errors():
    p = DepthParams.from_dict(OmegaConf.to_container(OmegaConf.load(REPO / "conf" / "depth" / "default.yaml")))
    assert p.valid_range_m == pytest.approx((1e-3, 0.2)) and "physics" in p.methods
    with pytest.raises(ConfigError, match="unknown method 'nope'"):
        DepthParams.from_dict({"methods": ["nope"]})
    with pytest.raises(ConfigError, match="defined twice"):
        DepthParams.from_dict({"hf": {"physics": {"path": "x"}}})
    with pytest.raises(ConfigError, match="valid_range_mm"):
        DepthParams.from_dict({"valid_range_mm": [5, 1]})
    with pytest.raises(ConfigError, match="depth.physics.iterations"):
        DepthParams.from_dict({"physics": {"iterations": "many"}})


def test_unavailable_estimators_give_reasons_not_crashes(tmp_path):
    p = DepthParams.from_dict({"hf": {"dav2": {"path": str(tmp_path / "none"), "hub_id": "org/model"}},
                               "external": {"mine": {"folder": str(tmp_path / "preds/{sequence}")},
                                            "broken": {"callable": "no_such_module_xyz:predict"}},
                               "methods": ["physics", "cnn", "dav2", "mine", "broken"]})
    info = SequenceInfo(camera=CameraIntrinsics.from_fov(8, 8, 80), sequence="s0", output_dir=tmp_path)
    reasons = {m: try_create(m, p, info)[1] for m in p.methods}
    assert "render.json" in reasons["physics"]
    assert "checkpoint" in reasons["cnn"] or "torch" in reasons["cnn"]
    assert str(tmp_path / "none") in reasons["dav2"] and "org/model" in reasons["dav2"]
    assert str(tmp_path / "preds" / "s0") in reasons["mine"]
    assert "no_such_module_xyz" in reasons["broken"]


def test_evaluate_loop_metric_and_median_rows():
    gt = np.full((6, 8), 0.03, np.float32)
    gt[0] = 0                                                   # a no-hit row
    cam = CameraIntrinsics.from_fov(8, 6, 80)
    samples = [dm_sample(gt, cam, i) for i in range(3)]
    rows = evaluate({"half": Constant(np.full((6, 8), 0.015, np.float32))}, samples, RANGE)
    assert set(rows) == {"half", "half_median"}
    assert rows["half"].summary()["AbsRel"] == pytest.approx(0.5)
    med = rows["half_median"].summary()
    assert med["AbsRel"] == pytest.approx(0.0, abs=1e-4) and med["median_scale"]["g"] == pytest.approx(2, rel=1e-4)
    assert med["n_valid_pixels"] == 3 * 5 * 8 and med["n_frames"] == 3
    small = Constant(np.full((3, 4), 0.03, np.float32), resizes=True)
    assert evaluate({"s": small}, samples, RANGE, also_median=False)["s"].summary()["AbsRel"] == pytest.approx(0)
    with pytest.raises(InputError, match=r"s on g/f0.*shape \(3, 4\)"):
        evaluate({"s": Constant(np.ones((3, 4), np.float32))}, samples, RANGE)


def dm_sample(gt, cam, i):
    from room_pipeline.depth.estimators import Sample

    return Sample("g", i, f"f{i}", cam, lambda: np.zeros(gt.shape + (3,), np.uint8), lambda: gt)


# --------------------------------------------------------------------------- external models


def test_external_folder_and_callable(tmp_path):
    seq = tmp_path / "out" / "patient_000" / "sequence_000"
    outs, _ = write_sequence(seq, n=2, size=24)
    pred_dir = tmp_path / "preds" / "sequence_000"
    pred_dir.mkdir(parents=True)
    for i, o in enumerate(outs):                               # the 'model' is the ground truth in mm, in npy
        np.save(pred_dir / f"frame_{i:04d}.npy", np.where(o["hit"], o["depth"] * 1e3, np.nan))
    p = DepthParams.from_dict({"methods": ["gt_mm", "plane"], "also_median": False, "external": {
        "gt_mm": {"folder": str(tmp_path / "preds" / "{sequence}"), "units": "mm", "scaling": "metric"},
        "plane": {"callable": "tests.test_depth:fake_model", "kwargs": {"scale": 1.0}, "units": "mm"}}})
    samples = sequence_samples(seq)
    info = SequenceInfo(camera=samples[0].camera, sequence="sequence_000", patient="patient_000")
    ests = {m: try_create(m, p, info)[0] for m in p.methods}
    rows = evaluate(ests, samples, p.valid_range_m, also_median=False)
    s = rows["gt_mm"].summary()
    assert s["AbsRel"] < 1e-6 and s["n_nonfinite_pixels"] == 0
    assert math.isfinite(rows["plane"].summary()["AbsRel"]) and rows["plane"].scaling == "median"
    np.save(pred_dir / "frame_0001.npy", np.ones((5, 5)))        # wrong size, not declared as resizing
    with pytest.raises(InputError, match=r"shape \(5, 5\)"):
        evaluate({"gt_mm": ests["gt_mm"]}, samples, p.valid_range_m)
    (pred_dir / "frame_0001.npy").unlink()
    with pytest.raises(InputError, match="frame_0001.npy is missing"):
        evaluate({"gt_mm": ests["gt_mm"]}, samples, p.valid_range_m)
    with pytest.raises(ConfigError, match="exactly one"):
        DepthParams.from_dict({"external": {"x": {"folder": "a", "callable": "b:c"}}, "methods": ["x"]})


# --------------------------------------------------------------------------- stage evaluate_depth


def test_evaluate_depth_stage_contract(tmp_path):
    from room_pipeline.stages import evaluate_depth

    seq = tmp_path / "out" / "patient_000" / "sequence_000"
    outs, _ = write_sequence(seq, n=3, size=32)
    pred_dir = tmp_path / "nanpreds"
    pred_dir.mkdir()
    for i, o in enumerate(outs):
        p = np.where(o["hit"], o["depth"], 0).astype(np.float32)
        p[:4] = np.nan                                          # the model fails on the top rows
        np.save(pred_dir / f"frame_{i:04d}.npy", p)
    cfg = depth_cfg(tmp_path, methods=["physics", "nanny", "depth_anything_v2"],
                    external={"nanny": {"folder": str(pred_dir), "scaling": "metric"}},
                    hf={"depth_anything_v2": {"path": str(tmp_path / "no_weights"), "output": "disparity"}})
    m = evaluate_depth.run(cfg, "patient_000/sequence_000")
    assert m["frames"] == 3 and m["methods_unavailable"] == 1
    doc = json.loads((tmp_path / "out" / "evaluation" / "patient_000" / "sequence_000" / "depth.json").read_text())
    assert doc["valid_range_mm"] == [1.0, 200.0] and set(doc["units"]) >= set(dm.METRIC_KEYS)
    rows = doc["methods"]
    assert set(rows) == {"physics", "physics_median", "nanny", "nanny_median", "depth_anything_v2"}
    for name, row in rows.items():
        assert set(row) >= {"available", "reason", "L1_mm", "AbsRel", "RMSE_mm", "delta1", "delta2", "delta3",
                            "n_frames", "scaling"}, name
    assert rows["physics"]["available"] and rows["physics"]["scaling"] == "metric" and rows["physics"]["n_frames"] == 3
    assert rows["physics_median"]["scaling"] == "median" and rows["physics"]["reason"] is None
    dav = rows["depth_anything_v2"]
    assert dav["available"] is False and "no_weights" in dav["reason"] and dav["AbsRel"] is None
    assert rows["nanny"]["n_nonfinite_pixels"] > 0 and rows["nanny"]["AbsRel"] < 1e-6
    csv = (tmp_path / "out" / "evaluation" / "patient_000" / "sequence_000" / "depth_errors.csv").read_text().splitlines()
    assert len(csv) == 4 and csv[0].startswith("frame,physics_L1_mm") and csv[1].startswith("frame_0000,")
    # no timing in the data files: the rows' seconds are in the stage's timing file, read back by read_with_timings
    ev = tmp_path / "out" / "evaluation" / "patient_000" / "sequence_000"
    timing = tmp_path / "out" / "patient_000" / "metrics" / "evaluate_depth_sequence_000.timing.json"
    assert not split_timings(doc)[1] and not any(c.endswith("_seconds") for c in csv[0].split(","))
    tim = json.loads(timing.read_text())
    assert len(tim["methods"]["physics"]["frame_seconds"]) == 3 and tim["cpu_time_s"] >= 0
    merged = read_with_timings(ev / "depth.json", timing)
    assert merged["methods"]["physics"]["seconds_per_frame"] >= 0 and merged["methods"]["physics"]["AbsRel"] is not None
    assert "seconds_per_frame" in merged["methods"]["depth_anything_v2"]
    assert not split_timings(json.loads(timing.with_name("evaluate_depth_sequence_000.json").read_text()))[1]
    assert {str(x) for x in evaluate_depth.outputs(cfg, "patient_000/sequence_000")} == {
        str(tmp_path / "out" / "evaluation" / "patient_000" / "sequence_000" / "depth.json"), str(tmp_path / "out" / "evaluation" / "patient_000" / "sequence_000" / "depth_errors.csv"),
        str(tmp_path / "out" / "patient_000" / "metrics" / "evaluate_depth_sequence_000.json")}


def test_evaluate_depth_outputs_hold_no_timing_and_repeat_byte_for_byte(tmp_path):
    """Two runs with the image-blind baselines: depth.json, depth_errors.csv and the DVC metric are the same
    bytes; the rows' timings are in metrics/evaluate_depth_<seq>.timing.json."""
    from room_pipeline.stages import evaluate_depth

    write_sequence(tmp_path / "out" / "patient_001" / "sequence_000", n=3, size=24)
    cfg = depth_cfg(tmp_path, methods=["constant", "tube_prior"])
    ev = tmp_path / "out" / "evaluation" / "patient_001" / "sequence_000"
    met = tmp_path / "out" / "patient_001" / "metrics"
    files = [ev / "depth.json", ev / "depth_errors.csv", met / "evaluate_depth_sequence_000.json"]
    evaluate_depth.run(cfg, "patient_001/sequence_000")
    first = [f.read_bytes() for f in files]
    evaluate_depth.run(cfg, "patient_001/sequence_000")
    assert [f.read_bytes() for f in files] == first
    for f in files[0], files[2]:
        assert split_timings(json.loads(f.read_text()))[1] == {}, f
    assert json.loads(files[0].read_text())["methods"]["constant"]["available"]
    tim = json.loads((met / "evaluate_depth_sequence_000.timing.json").read_text())
    assert len(tim["methods"]["tube_prior"]["frame_seconds"]) == 3 and tim["wall_time_s"] > 0


def test_evaluate_depth_on_a_sequence_without_valid_pixels(tmp_path):
    from room_pipeline.stages import evaluate_depth

    seq = tmp_path / "out" / "patient_000" / "sequence_000"
    write_sequence(seq, n=2, size=16, blank=True)
    evaluate_depth.run(depth_cfg(tmp_path, methods=["physics"]), "patient_000/sequence_000")
    row = json.loads((tmp_path / "out" / "evaluation" / "patient_000" / "sequence_000" / "depth.json").read_text())["methods"]["physics"]
    assert row["available"] and row["AbsRel"] is None and row["n_frames_valid"] == 0 and row["n_frames"] == 2


def test_optional_dependencies_are_not_imported_by_the_stages():
    code = ("import sys, room_pipeline.stages.evaluate_depth, room_pipeline.stages.train_depth;"
            "print(sorted(m for m in ('torch', 'transformers') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO)
    assert out.stdout.strip() == "[]"


# --------------------------------------------------------------------------- CNN


TINY = {"cnn": {"input_size": 32, "channels": [4, 8], "threads": 1, "checkpoint_patient": "patient_000"},
        "train": {"seed": 3, "batch_size": 2, "pretrain_scenes": 1, "pretrain_views": 2, "pretrain_steps": 2,
                  "finetune_steps": 2, "holdout_fraction": 0.34, "holdout_gap_frames": 0, "eval_stride": 1,
                  "simcol_dir": None}}


def tiny_training(seed: int) -> bytes:
    from room_pipeline.depth import cnn

    with cnn.deterministic_torch(seed, 1):
        data = cnn.synthetic_tube_set(1, 2, 32, seed, RANGE)
        model = cnn.build_model((4, 8))
        losses = cnn.train_steps(model, data, 2, 1e-3, 2, seed, 0.85)
    assert len(losses) == 2 and all(math.isfinite(x) for x in losses)
    return cnn.checkpoint_bytes(model, (4, 8), 32, {"seed": seed})


def test_cnn_training_is_deterministic_to_the_byte():
    pytest.importorskip("torch")
    import hashlib

    a, b, c = tiny_training(5), tiny_training(5), tiny_training(6)
    assert a == b and a != c
    code = "import hashlib, tests.test_depth as t; print(hashlib.sha256(t.tiny_training(5)).hexdigest())"
    other = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=REPO)
    assert other.stdout.strip() == hashlib.sha256(a).hexdigest()         # and in a fresh process


def test_cnn_checkpoint_roundtrip_and_bad_files(tmp_path):
    pytest.importorskip("torch")
    from room_pipeline.depth import cnn

    with cnn.deterministic_torch(0, 1):
        model = cnn.build_model((4, 8))
    path = tmp_path / "m" / "finetuned.pt"
    sha = cnn.save_checkpoint(path, model, (4, 8), 32, {"note": "t"})
    assert len(sha) == 64 and not list(path.parent.glob(".*tmp*"))
    est = cnn.CNNEstimator.load("cnn", path, cnn.CNNParams(input_size=32, channels=(4, 8), threads=1))
    rgb = np.random.default_rng(0).integers(0, 255, (20, 30, 3), dtype=np.uint8)
    pred = est.predict(Frame(rgb, CameraIntrinsics.from_fov(30, 20, 80)))
    assert pred.shape == (32, 32) and np.all(pred > 0) and est.resizes
    assert np.array_equal(pred, cnn.predict_depth(model, rgb, 32))
    with pytest.raises(BackendUnavailable, match="train_depth"):
        cnn.load_checkpoint(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="junk.pt"):
        cnn.load_checkpoint(tmp_path / "junk.pt")


def test_si_loss_ignores_global_scale():
    torch = pytest.importorskip("torch")
    from room_pipeline.depth.cnn import si_log_loss

    gen = torch.Generator().manual_seed(0)
    for _ in range(20):                  # the one-pass form m2 - lam m1^2 failed CI (stop 30) on an unseeded draw
        y = torch.rand(2, 5, 5, generator=gen) * 0.05 + 0.01
        y[0, 0, 0] = 0                                          # invalid target pixel
        pred = torch.log(y.clamp(min=1e-6) * 3.0)
        assert float(si_log_loss(torch, pred, y, 1.0)) < 1e-5
    assert float(si_log_loss(torch, pred, y, 0.0)) == pytest.approx(math.log(3.0), rel=1e-4)


def test_train_depth_stage_contract_and_evaluate_uses_it(tmp_path):
    pytest.importorskip("torch")
    from room_pipeline.stages import evaluate_depth, train_depth

    seq = tmp_path / "out" / "patient_000" / "sequence_000"
    write_sequence(seq, n=4, size=32)
    cfg = depth_cfg(tmp_path, methods=["cnn", "cnn_pretrained"], **TINY)
    m = train_depth.run(cfg, "patient_000")
    assert m["available"]
    doc = read_metrics_file(tmp_path / "out" / "patient_000" / "metrics" / "train_depth.json")   # + timings
    ft = tmp_path / "out" / "evaluation" / "patient_000" / "depth_finetune.json"
    ev = json.loads(ft.read_text())
    # no timing in the tables' input: its rows' seconds are in train_depth.timing.json under the same keys
    assert split_timings(ev)[1] == {} and ev["datasets"] == split_timings(doc["datasets"])[0]
    timing = tmp_path / "out" / "patient_000" / "metrics" / "train_depth.timing.json"
    assert read_with_timings(ft, timing)["datasets"] == doc["datasets"]
    assert doc["datasets"]["phantom_held_out"]["after"]["seconds_per_frame"] >= 0
    ds = doc["datasets"]
    assert set(ds) == {"phantom_held_out", "simcol"}      # other_anatomy: evaluate_depth + tables
    held = ds["phantom_held_out"]
    assert held["available"] and held["n_frames"] == 1 and set(held["before"]) >= set(dm.METRIC_KEYS)
    assert held["after"]["scaling"] == "median"
    assert not ds["simcol"]["available"] and ds["simcol"]["before"] is None
    tr = doc["training"]
    assert tr["finetune"]["frames"] == 3 and tr["pretrain"]["frames"] == 2 and tr["seed"] == 3
    assert set(tr["checkpoints"]) == {"pretrained", "finetuned"} and "before" in tr["definition"]
    model_dir = tmp_path / "out" / "patient_000" / "depth_model"
    assert {p.name for p in model_dir.iterdir()} == {"pretrained.pt", "finetuned.pt", "training.json",
                                                     "training_log.csv", "train_mean_depth.npy"}
    assert np.load(model_dir / "train_mean_depth.npy").shape == (32, 32)
    cfg = depth_cfg(tmp_path, methods=["cnn", "cnn_pretrained", "train_mean", "constant", "tube_prior"], **TINY)
    # the training patient: rows fitted on it are never scored there (no in-sample row)
    evaluate_depth.run(cfg, "patient_000/sequence_000")
    rows = json.loads((tmp_path / "out" / "evaluation" / "patient_000" / "sequence_000" / "depth.json").read_text())["methods"]
    assert not rows["cnn"]["available"] and "in-sample" in rows["cnn"]["reason"] and rows["cnn"]["AbsRel"] is None
    assert not rows["train_mean"]["available"] and rows["cnn_pretrained"]["available"]
    # another patient: every row is scored
    write_sequence(tmp_path / "out" / "patient_001" / "sequence_000", n=2, size=32)
    evaluate_depth.run(cfg, "patient_001/sequence_000")
    rows = json.loads((tmp_path / "out" / "evaluation" / "patient_001" / "sequence_000" / "depth.json").read_text())["methods"]
    assert rows["cnn"]["available"] and rows["cnn_pretrained"]["available"] and rows["cnn"]["scaling"] == "median"
    assert math.isfinite(rows["cnn"]["AbsRel"]) and rows["train_mean"]["available"]
    assert all(not r["oracle"] for r in rows.values())


def test_train_depth_without_torch(tmp_path, monkeypatch):
    pytest.importorskip("torch")
    from room_pipeline.stages import train_depth

    write_sequence(tmp_path / "out" / "patient_000" / "sequence_000", n=3, size=32)
    cfg = depth_cfg(tmp_path, **TINY)

    def no_torch():
        raise BackendUnavailable("torch is not installed (test)")
    monkeypatch.setattr(train_depth, "require_torch", no_torch)
    m = train_depth.run(cfg, "patient_000")
    assert m["available"] is False
    doc = json.loads((tmp_path / "out" / "patient_000" / "metrics" / "train_depth.json").read_text())
    assert all(not d["available"] and "torch" in d["reason"] for d in doc["datasets"].values())


def test_split_indices():
    from room_pipeline.depth.finetune import split_indices

    tr, ho = split_indices(100, 0.2, 10, 1, 5)
    assert tr == list(range(70)) and ho == [80, 85, 90, 95]
    assert split_indices(10, 0.0, 3, 2, 1) == ([0, 2, 4, 6, 8], [])


# --------------------------------------------------------------------------- SimCol (shared data)


def test_simcol_depth_convention_against_the_images():
    """Checks the stated convention (value / 255 / 256 * 20 cm, planar z) on the frames themselves.

    Values are 8-bit depths x 256; 6 mm .. 13 cm is a colon seen from inside; under a tip light the
    brightness falls with depth (depth, not inverse depth), and log radiance against log *range*
    (z |ray|, SimCol's intrinsics) is steeper, nearer the inverse-square -2, than against z itself:
    the values are planar z, as SimCol's own unprojection (depth x K^-1 [u, v, 1]) assumes.
    """
    folder = shared_path("endoscopy_depth", "simcol_sample")
    from room_pipeline.depth.cnn import SIMCOL_CAMERA, SIMCOL_DEPTH_M_PER_UNIT, read_simcol

    pairs = read_simcol(folder)
    assert len(pairs) == 10
    rays = SIMCOL_CAMERA.pixel_rays()
    ray_len = np.linalg.norm(rays, axis=-1)
    for name, rgb, depth in pairs:
        assert rgb.dtype == np.uint8 and rgb.shape == (475, 475, 3) and depth.shape == (475, 475)
        raw = np.rint(depth / SIMCOL_DEPTH_M_PER_UNIT).astype(np.int64)
        assert np.all(raw % 256 == 0)
        assert 0.005 < depth.min() < 0.01 and 0.1 < depth.max() < 0.2
        lin = srgb8_to_linear(rgb) @ np.array([0.2126, 0.7152, 0.0722], np.float32)
        m = (rgb.max(axis=-1) > 10) & (rgb.max(axis=-1) < 250)
        assert np.corrcoef(np.log(lin[m]), np.log(depth[m]))[0, 1] < -0.8, name
        slope_range = np.polyfit(np.log(depth * ray_len)[m], np.log(lin[m]), 1)[0]
        slope_z = np.polyfit(np.log(depth)[m], np.log(lin[m]), 1)[0]
        assert -2.5 < slope_range < slope_z < -0.8, (name, slope_range, slope_z)


# --------------------------------------------------------------------------- Hugging Face adapters


def _tiny_hf_models(root):
    torch = pytest.importorskip("torch")
    tr = pytest.importorskip("transformers")
    torch.manual_seed(0)
    made = {}
    dpt = tr.DPTConfig(hidden_size=32, num_hidden_layers=4, num_attention_heads=2, intermediate_size=64,
                       image_size=64, patch_size=16, backbone_out_indices=(0, 1, 2, 3),
                       neck_hidden_sizes=(8, 16, 32, 32), fusion_hidden_size=16, use_auxiliary_head=False)
    tr.DPTForDepthEstimation(dpt).save_pretrained(root / "dpt")
    tr.DPTImageProcessor(size={"height": 64, "width": 64}, keep_aspect_ratio=False).save_pretrained(root / "dpt")
    made["dpt"] = {"path": str(root / "dpt"), "output": "disparity", "scaling": "median"}
    dino = tr.Dinov2Config(hidden_size=32, num_hidden_layers=4, num_attention_heads=2, intermediate_size=64,
                           image_size=56, patch_size=14, out_indices=[1, 2, 3, 4], reshape_hidden_states=False)
    da = tr.DepthAnythingConfig(backbone_config=dino, reassemble_hidden_size=32, neck_hidden_sizes=(8, 16, 32, 32),
                                fusion_hidden_size=16, head_hidden_size=8)
    tr.DepthAnythingForDepthEstimation(da).save_pretrained(root / "da")
    tr.DPTImageProcessor(size={"height": 56, "width": 56}, keep_aspect_ratio=False,
                         ensure_multiple_of=14).save_pretrained(root / "da")
    made["depth_anything_v2"] = {"path": str(root / "da"), "output": "disparity", "scaling": "median"}
    beit = tr.BeitConfig(hidden_size=32, num_hidden_layers=4, num_attention_heads=2, intermediate_size=64,
                         image_size=64, patch_size=16, out_indices=[1, 2, 3, 4], reshape_hidden_states=False,
                         use_relative_position_bias=True)
    zoe = tr.ZoeDepthConfig(backbone_config=beit, neck_hidden_sizes=(8, 16, 32, 32), fusion_hidden_size=16,
                            bottleneck_features=16, num_attractors=[4, 4, 2, 1], bin_embedding_dim=16,
                            num_relative_features=8, backbone_hidden_size=32, hidden_size=32,
                            bin_configurations=[{"n_bins": 8, "min_depth": 0.001, "max_depth": 1.0, "name": "nyu"}])
    tr.ZoeDepthForDepthEstimation(zoe).save_pretrained(root / "zoe")
    tr.ZoeDepthImageProcessor(size={"height": 64, "width": 64}, keep_aspect_ratio=False,
                              ensure_multiple_of=16).save_pretrained(root / "zoe")
    made["zoedepth"] = {"path": str(root / "zoe"), "output": "depth", "scaling": "metric"}
    return made


def test_hf_adapters_load_tiny_random_models(tmp_path):
    specs = _tiny_hf_models(tmp_path)
    p = DepthParams.from_dict({"methods": list(specs), "hf": specs})
    gt = np.full((40, 48), 0.03, np.float32)
    cam = CameraIntrinsics.from_fov(48, 40, 85)
    rgb = np.random.default_rng(1).integers(0, 255, (40, 48, 3), dtype=np.uint8)
    from room_pipeline.depth.estimators import Sample

    samples = [Sample("g", 0, "f0", cam, lambda: rgb, lambda: gt)]
    info = SequenceInfo(camera=cam)
    ests = {}
    for name in specs:
        est, reason = try_create(name, p, info)
        assert reason is None, reason
        pred = est.predict(Frame(rgb, cam))
        assert pred.shape == (40, 48) and pred.dtype == np.float32
        assert est.describe()["model_type"] in ("dpt", "depth_anything", "zoedepth")
        ests[name] = est
    rows = evaluate(ests, samples, RANGE)
    assert set(rows) == {"dpt", "depth_anything_v2", "zoedepth", "zoedepth_median"}
    for name, row in rows.items():
        s = row.summary()
        assert s["n_valid_pixels"] > 0 and all(math.isfinite(s[k]) for k in dm.METRIC_KEYS), name
