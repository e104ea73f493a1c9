"""Sensor-noise calibration and synthesis: spectra, round trip, hard cases, determinism, the stage and the CLI."""
from __future__ import annotations

import dataclasses
import hashlib
import json
import warnings

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf

from room_pipeline.cli import main as cli_main
from room_pipeline.errors import ConfigError, InputError
from room_pipeline.io.hashing import sha256_file
from room_pipeline.io.images import read_png, write_png8
from room_pipeline.noise import CalibrationParams, NoiseProfile, add_noise, calibrate_folder, calibrate_images
from room_pipeline.noise.calibrate import split_frames
from room_pipeline.noise.spectrum import periodogram, radial_average, radial_lsd, resample_spectrum
from room_pipeline.noise.synthesize import synthesize
from room_pipeline.stages import noise as stage
from tests.conftest import REPO, shared_path

T = 32
FAST = CalibrationParams(tile=T, tile_step=16, mask_margin_px=5, holdout_every=0, compensation_frames=4,
                         compensation_iterations=3, intensity_min_pixels=200)


# --------------------------------------------------------------------------- fixtures


def camera_spectrum(tile: int = T, sigma=(2.0, 2.4, 1.8), rho: float = 0.7) -> np.ndarray:
    """A (3, 3, T, T) cross-spectral matrix: correlated band-limited part + independent high-pass part."""
    fy, fx = np.meshgrid(np.fft.fftfreq(tile), np.fft.fftfreq(tile), indexing="ij")
    r2 = fy ** 2 + fx ** 2
    low = np.exp(-r2 / (2 * 0.12 ** 2)) * (1 + 0.5 * np.cos(2 * np.pi * fx * 4))   # anisotropic, like JPEG
    high = 0.2 + r2 / 0.25
    low, high = low / low.mean(), high / high.mean()
    a = np.sqrt(rho) * np.asarray(sigma)
    spec = low[None, None] * np.outer(a, a)[:, :, None, None]
    for c, s in enumerate(sigma):
        spec[c, c] += (1 - rho) * s ** 2 * high
    return spec.astype(np.complex128)


def camera_profile(tile: int = T) -> NoiseProfile:
    spec = camera_spectrum(tile)
    psd = np.stack([spec[i, i].real for i in range(3)])
    return NoiseProfile(spec, psd, provenance={"source": "test camera"})


def clean_scene(h: int, w: int, seed: int) -> np.ndarray:
    """A smooth lumen-like uint8 RGB image: radial shading, soft folds, no texture, no noise."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    cy, cx = h * rng.uniform(0.35, 0.65), w * rng.uniform(0.35, 0.65)
    r = np.hypot(y - cy, x - cx) / max(h, w)
    shade = np.clip(0.25 + 1.6 * r, 0, 1) * (1 + 0.08 * np.sin(x / rng.uniform(9, 15) + y / 23))
    base = np.array([0.85, 0.55, 0.55]) * rng.uniform(0.8, 1.0)
    return np.clip(200 * shade[..., None] * base, 0, 255).round().astype(np.uint8)


def camera_frames(n: int, shape=(128, 128), seed: int = 0) -> list[np.ndarray]:
    prof = camera_profile()
    return [add_noise(clean_scene(*shape, seed + i), prof, 1.0, seed + 100 + i) for i in range(n)]


# --------------------------------------------------------------------------- spectra and synthesis


def test_synthesised_psd_matches_profile_within_1db():
    prof = camera_profile()
    rng = np.random.default_rng(0)
    acc = np.zeros((3, 256, 256))
    for _ in range(6):
        acc += periodogram(synthesize(prof, (256, 256), rng))
    lsd = radial_lsd(acc / 6, prof.psd, bins=T // 2)
    assert lsd <= 1.0, lsd
    # and per 2-D bin (on the profile grid) it is unbiased: the mean log ratio is small
    f_prof, r_prof = radial_average(prof.psd, T // 2)
    f_syn, r_syn = radial_average(acc / 6, T // 2)
    assert np.allclose(f_prof, f_syn)
    assert abs(np.nanmean(10 * np.log10(r_syn / r_prof))) < 0.3


def test_synthesised_channel_correlation_and_variance():
    prof = camera_profile()
    n = synthesize(prof, (384, 384), np.random.default_rng(1)).reshape(-1, 3).astype(np.float64)
    np.testing.assert_allclose(n.std(0), prof.std, rtol=0.03)
    np.testing.assert_allclose(np.corrcoef(n.T), prof.correlation, atol=0.03)
    assert abs(n.mean()) < 0.05


@pytest.mark.parametrize("shape", [(96, 160), (600, 600), (480, 480), (75, 64), (64, 75), (33, 47)])
def test_resampling_to_other_resolutions_keeps_per_pixel_variance(shape):
    prof = camera_profile()
    rng = np.random.default_rng(2)
    reps = max(1, int(np.ceil(300_000 / (shape[0] * shape[1]))))
    n = np.concatenate([synthesize(prof, shape, rng).reshape(-1, 3) for _ in range(reps)])
    np.testing.assert_allclose(n.var(0), prof.std ** 2, rtol=0.05)


@settings(max_examples=25, deadline=None)
@given(h=st.integers(4, 70), w=st.integers(4, 70), seed=st.integers(0, 2 ** 16))
def test_resample_spectrum_keeps_variance_and_hermitian_symmetry(h, w, seed):
    spec = camera_spectrum(16)
    spec = spec * np.random.default_rng(seed).uniform(0.5, 2.0)
    out = resample_spectrum(spec, (h, w))
    for c in range(3):
        assert np.isclose(out[c, c].real.mean(), spec[c, c].real.mean(), rtol=1e-9)
    # S(-f) = conj(S(f)) on the new grid
    flip = out[..., (-np.arange(h)) % h, :][..., (-np.arange(w)) % w]
    np.testing.assert_allclose(flip, np.conj(out), atol=1e-9)
    # the rfft half of the grid is the same data
    np.testing.assert_allclose(resample_spectrum(spec, (h, w), rfft=True), out[..., : w // 2 + 1])


def test_add_noise_is_deterministic_per_seed():
    prof = camera_profile()
    img = clean_scene(90, 120, 0)
    a = add_noise(img, prof, 1.0, 7)
    assert a.dtype == np.uint8 and a.shape == img.shape
    assert a.tobytes() == add_noise(img, prof, 1.0, 7).tobytes()
    assert a.tobytes() != add_noise(img, prof, 1.0, 8).tobytes()
    assert add_noise(img, prof, 0.0, 7).tobytes() == img.tobytes()
    # beta scales the added noise (before clipping: this image has no clipped pixels)
    d1 = a.astype(float) - img
    d2 = add_noise(img, prof, 2.0, 7).astype(float) - img
    assert 1.8 < d2.std() / d1.std() < 2.2


def test_stage_frame_seeds_differ_per_frame_and_sequence():
    prof = camera_profile()
    img = clean_scene(64, 64, 1)
    s = [stage.frame_seed(0, "sequence_000", i) for i in (0, 1)] + [stage.frame_seed(0, "sequence_001", 0)]
    outs = [add_noise(img, prof, 1.0, ss).tobytes() for ss in s]
    assert len(set(outs)) == 3
    assert add_noise(img, prof, 1.0, stage.frame_seed(0, "sequence_000", 0)).tobytes() == outs[0]
    # stable across processes: a fixed value, not Python's salted hash()
    assert stage.sequence_hash("sequence_000") == int.from_bytes(
        hashlib.sha256(b"sequence_000").digest()[:4], "little")


def test_black_and_saturated_frames_are_clipped_not_wrapped():
    prof = camera_profile()
    black = np.zeros((64, 64, 3), np.uint8)
    white = np.full((64, 64, 3), 255, np.uint8)
    nb, nw = add_noise(black, prof, 3.0, 0), add_noise(white, prof, 3.0, 0)
    assert nb.max() < 60 and nb.mean() > 0                 # one-sided: clipped at 0
    assert nw.min() > 195 and nw.mean() < 255
    with pytest.raises(InputError):
        add_noise(black.astype(np.float32), prof, 1.0, 0)
    with pytest.raises(InputError):
        add_noise(black, prof, -1.0, 0)


# --------------------------------------------------------------------------- calibration


def test_round_trip_calibrate_synthesize_recalibrate_within_1_5db():
    """Synthetic 'real' frames -> profile -> noise on other clean frames -> recalibrated residual PSD."""
    real = camera_frames(8, seed=0)
    prof = calibrate_images(real, FAST)
    clean = [clean_scene(128, 128, 50 + i) for i in range(8)]
    noisy = [add_noise(c, prof, 1.0, 200 + i) for i, c in enumerate(clean)]
    p0 = dataclasses.replace(FAST, compensate_filter=False)
    recovered = calibrate_images(noisy, p0)
    clean_only = calibrate_images(clean, p0)
    d_rec = radial_lsd(recovered.residual_psd, prof.residual_psd, bins=T // 2)
    d_clean = radial_lsd(clean_only.residual_psd, prof.residual_psd, bins=T // 2)
    assert d_rec <= 1.5, d_rec
    assert d_clean > 6.0, d_clean
    # filter compensation: the synthesis spectrum is closer to the camera's true noise than the raw residual
    truth = camera_profile().psd
    assert radial_lsd(prof.psd, truth, bins=T // 2) < radial_lsd(prof.residual_psd, truth, bins=T // 2)
    np.testing.assert_allclose(prof.correlation, camera_profile().correlation, atol=0.15)


def test_one_frame_and_mixed_sizes():
    one = calibrate_images(camera_frames(1), FAST)
    assert one.provenance["frame_count"] == 1
    assert one.intensity is None and "not tested" in one.intensity_test["decision"]
    frames = camera_frames(1, (128, 128)) + camera_frames(1, (96, 160), seed=3) + camera_frames(1, (200, 72), seed=5)
    prof = calibrate_images(frames, FAST)
    assert prof.tile == T and prof.provenance["frame_count"] == 3
    assert set(prof.provenance["frame_shapes"]) == {"128x128", "160x96", "72x200"}
    assert np.all(np.isfinite(prof.spectrum))


def test_all_black_saturated_and_tiny_frames_are_skipped_or_rejected():
    black = np.zeros((128, 128, 3), np.uint8)
    white = np.full((128, 128, 3), 255, np.uint8)
    tiny = camera_frames(1, (20, 20))[0]
    with warnings.catch_warnings(record=True) as caught, pytest.raises(InputError, match="none of the 3 frame"):
        warnings.simplefilter("always")
        calibrate_images([black, white, tiny], FAST)
    assert [str(w.message).split(":")[1].split("(")[0].strip() for w in caught] == \
        ["frame_0000", "frame_0001", "frame_0002"]
    with pytest.warns(UserWarning, match="frame_0000.*no 32x32 tile"):
        prof = calibrate_images([black] + camera_frames(2), FAST)
    assert prof.provenance["frame_count"] == 2
    with pytest.raises(InputError):
        calibrate_images([], FAST)


def test_valid_mask_excludes_highlights_and_dark_corners():
    img = camera_frames(1, (160, 160))[0].copy()
    img[:40, :40] = 0                         # black corner
    img[100:120, 100:130] = 255               # specular highlight
    from room_pipeline.noise.calibrate import valid_mask
    m = valid_mask(img, FAST)
    assert not m[:40 + FAST.mask_margin_px, :40 + FAST.mask_margin_px].any()
    assert not m[100 - FAST.mask_margin_px:120 + FAST.mask_margin_px, 100:130].any()
    assert m[60:90, 60:90].all()
    # a frame with those regions gives the same residual level as without (within estimation noise)
    clean_prof = calibrate_images(camera_frames(1, (160, 160)), dataclasses.replace(FAST, compensate_filter=False))
    masked_prof = calibrate_images([img], dataclasses.replace(FAST, compensate_filter=False))
    np.testing.assert_allclose(masked_prof.std, clean_prof.std, rtol=0.15)


def test_intensity_dependence_detected_only_when_present():
    rng = np.random.default_rng(3)
    indep, dep = [], []
    for i in range(6):
        c = clean_scene(128, 128, 10 + i).astype(np.float64)
        y = c @ [0.299, 0.587, 0.114]
        indep.append(np.clip(np.rint(c + rng.normal(0, 2.0, c.shape)), 0, 255).astype(np.uint8))
        sd = np.sqrt(0.5 + 0.06 * y)[..., None]            # Poisson-Gaussian: var = a + b * Y
        dep.append(np.clip(np.rint(c + rng.normal(0, 1, c.shape) * sd), 0, 255).astype(np.uint8))
    p = dataclasses.replace(FAST, compensate_filter=False)
    a = calibrate_images(indep, p)
    b = calibrate_images(dep, p)
    assert a.intensity is None and not a.intensity_test["modelled"]
    assert b.intensity is not None and b.intensity_test["significant"] and b.intensity_test["slope_mean"] > 0
    g = b.intensity.gain_at(np.array([40.0, 160.0]))
    assert g[1] / g[0] > 1.4                                 # sqrt((0.5 + 0.06*160) / (0.5 + 0.06*40)) = 1.87


def test_folder_with_non_image_file_and_empty_folder(tmp_path):
    for i, f in enumerate(camera_frames(3)):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), f[..., ::-1])
    (tmp_path / "gt.csv").write_text("x,y\n1,2\n")
    with pytest.warns(UserWarning, match="gt.csv"):
        prof = calibrate_folder(tmp_path, FAST)
    assert prof.provenance["frames_used"] == ["f0.png", "f1.png", "f2.png"]
    assert prof.provenance["source_folder"] == str(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no readable images"):
        calibrate_folder(empty, FAST)
    (empty / "notes.txt").write_text("no images here")
    with pytest.warns(UserWarning, match="notes.txt"), pytest.raises(InputError, match="no readable images"):
        calibrate_folder(empty, FAST)
    with pytest.raises(InputError, match="not found"):
        calibrate_folder(tmp_path / "missing", FAST)


def test_holdout_split_is_recorded(tmp_path):
    for i, f in enumerate(camera_frames(5)):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), f[..., ::-1])
    prof = calibrate_folder(tmp_path, dataclasses.replace(FAST, holdout_every=4, holdout_offset=3))
    assert prof.provenance["split"]["held_out"] == ["f3.png"]
    assert "f3.png" not in prof.provenance["frames_used"]
    assert split_frames(1, 4, 3) == ([0], [])
    assert split_frames(8, 4, 3) == ([0, 1, 2, 4, 5, 6], [3, 7])


def test_profile_save_load_roundtrip_is_small_and_deterministic(tmp_path):
    prof = calibrate_images(camera_frames(2), FAST)
    npz, meta = prof.save(tmp_path / "p.npz")
    again = NoiseProfile.load(npz)
    np.testing.assert_allclose(again.spectrum, prof.spectrum, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(again.std, prof.std, rtol=1e-6)
    assert again.provenance["frame_count"] == 2
    doc = json.loads(meta.read_text())
    assert doc["format"] == "room-noise-profile/1" and doc["npz"]["file"] == "p.npz"
    first = npz.read_bytes()
    prof.save(tmp_path / "p.npz")
    assert npz.read_bytes() == first
    assert len(first) < 1_000_000
    with pytest.raises(InputError, match="not found"):
        NoiseProfile.load(tmp_path / "nope.npz")
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    (tmp_path / "bad.json").write_text(meta.read_text())
    with pytest.raises(InputError):
        NoiseProfile.load(tmp_path / "bad.npz")


# --------------------------------------------------------------------------- config, stage, CLI


def test_config_file_matches_params():
    doc = OmegaConf.to_container(OmegaConf.load(REPO / "conf" / "noise" / "default.yaml"))
    p = stage.NoiseParams.from_dict(doc)
    assert dataclasses.replace(p, calibration=None) == stage.NoiseParams()
    assert p.calibration_params() == CalibrationParams()
    with pytest.raises(ConfigError, match="noise.bogus"):
        stage.NoiseParams.from_dict({"bogus": 1})
    with pytest.raises(ConfigError, match="beta"):
        stage.NoiseParams.from_dict({"beta": -0.5})
    with pytest.raises(ConfigError, match="noise.calibration.tilee"):
        stage.NoiseParams.from_dict({"calibration": {"tilee": 3}})
    with pytest.raises(ConfigError):
        CalibrationParams(tile=33)


def _stage_cfg(tmp_path, profile_path, **noise):
    return OmegaConf.create({"output_dir": str(tmp_path / "out"),
                             "noise": {"profile": str(profile_path), "beta": 1.0, "seed": 0, **noise}})


def test_stage_writes_noisy_rgb_keeps_clean_and_is_reproducible(tmp_path):
    profile_path, _ = camera_profile().save(tmp_path / "cam.npz")
    seq = tmp_path / "out" / "p0" / "sequence_000"
    for i in range(3):
        write_png8(seq / "rgb" / f"frame_{i:04d}.png", clean_scene(72, 96, i))
    clean_bytes = [(seq / "rgb" / f"frame_{i:04d}.png").read_bytes() for i in range(3)]
    cfg = _stage_cfg(tmp_path, profile_path)
    m = stage.run(cfg, "p0/sequence_000")
    assert m["frames"] == 3 and 1.0 < m["added_std_levels_mean"] < 4.0
    record = tmp_path / "out" / "p0" / "sequence_index" / "sequence_000.noise.json"     # train_depth's DVC dep
    assert stage.outputs(cfg, "p0/sequence_000") == [seq / "rgb_noisy", seq / "metadata" / "noise.json", record]
    assert json.loads(record.read_text()) == {"rgb_noisy": sha256_file(seq / "rgb_noisy")}
    assert [(seq / "rgb" / f"frame_{i:04d}.png").read_bytes() for i in range(3)] == clean_bytes
    noisy = [(seq / "rgb_noisy" / f"frame_{i:04d}.png").read_bytes() for i in range(3)]
    assert len(set(noisy)) == 3
    doc = json.loads((seq / "metadata" / "noise.json").read_text())
    assert doc["beta"] == 1.0 and len(doc["frames"]) == 3
    assert doc["frames"][1]["seed_entropy"][2] == 1
    assert doc["profile"]["sha256"] == hashlib.sha256(profile_path.read_bytes()).hexdigest()
    stage.run(cfg, "p0/sequence_000")
    assert [(seq / "rgb_noisy" / f"frame_{i:04d}.png").read_bytes() for i in range(3)] == noisy
    stage.run(_stage_cfg(tmp_path, profile_path, beta=0.0), "p0/sequence_000")
    for i in range(3):
        assert np.array_equal(read_png(seq / "rgb_noisy" / f"frame_{i:04d}.png"),
                              read_png(seq / "rgb" / f"frame_{i:04d}.png"))


def test_stage_same_bytes_with_one_and_two_workers(tmp_path):
    """The frames are shared among the execution workers (noise/sequence.py): the noisy PNGs and noise.json are
    the same bytes with the serial backend and with two spawned workers."""
    profile_path, _ = camera_profile().save(tmp_path / "cam.npz")
    seq = tmp_path / "out" / "p0" / "sequence_000"
    for i in range(5):
        write_png8(seq / "rgb" / f"frame_{i:04d}.png", clean_scene(48, 64, i))
    got = {}
    for name, execution in (("serial", {"backend": "serial"}),
                            ("local2", {"backend": "local", "workers": 2, "chunk_size": 1})):
        cfg = _stage_cfg(tmp_path, profile_path)
        cfg.execution = execution
        m = stage.run(cfg, "p0/sequence_000")
        got[name] = ([(seq / "rgb_noisy" / f"frame_{i:04d}.png").read_bytes() for i in range(5)],
                     (seq / "metadata" / "noise.json").read_bytes(),
                     {k: v for k, v in m.items() if not k.endswith("_s") and "ms" not in k and "rss" not in k})
    assert got["serial"] == got["local2"]


def test_stage_bad_frame_from_a_worker_is_one_input_error(tmp_path):
    profile_path, _ = camera_profile().save(tmp_path / "cam.npz")
    seq = tmp_path / "out" / "p0" / "sequence_000"
    write_png8(seq / "rgb" / "frame_0000.png", clean_scene(40, 40, 0))
    write_png8(seq / "rgb" / "frame_0001.png", np.zeros((40, 40), np.uint8))      # grey, not RGB
    cfg = _stage_cfg(tmp_path, profile_path)
    cfg.execution = {"backend": "local", "workers": 2, "chunk_size": 1}
    with pytest.raises(InputError, match="frame_0001.png: expected an 8-bit RGB render"):
        stage.run(cfg, "p0/sequence_000")


def test_stage_errors(tmp_path):
    profile_path, _ = camera_profile().save(tmp_path / "cam.npz")
    with pytest.raises(InputError, match="no rendered frames"):
        stage.run(_stage_cfg(tmp_path, profile_path), "p0/sequence_000")
    write_png8(tmp_path / "out" / "p0" / "sequence_000" / "rgb" / "frame_0000.png", clean_scene(40, 40, 0))
    with pytest.raises(InputError, match="noise profile not found"):
        stage.run(_stage_cfg(tmp_path, tmp_path / "none.npz"), "p0/sequence_000")
    with pytest.raises(ConfigError):
        stage.run(_stage_cfg(tmp_path, profile_path), "p0")


def test_cli_calibrate_noise(tmp_path, capsys, monkeypatch):
    frames = tmp_path / "frames"
    frames.mkdir()
    for i, f in enumerate(camera_frames(3)):
        cv2.imwrite(str(frames / f"{i}.jpg"), f[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
    (frames / "readme.txt").write_text("x")
    monkeypatch.chdir(REPO)
    out = tmp_path / "prof" / "cam.npz"
    rc = cli_main(["calibrate-noise", "--frames", str(frames), "--out", str(out), "tile=32", "tile_step=16",
                   "noise.calibration.compensation_frames=2", "holdout_every=0"])
    err = capsys.readouterr()
    assert rc == 0, err
    assert "room: warning:" in err.err and "readme.txt" in err.err
    doc = json.loads(out.with_suffix(".json").read_text())
    assert doc["provenance"]["frame_count"] == 3
    assert "tile=32" in doc["provenance"]["command"]
    assert doc["provenance"]["calibration_params"]["tile"] == 32
    empty = tmp_path / "empty"
    empty.mkdir()
    assert cli_main(["calibrate-noise", "--frames", str(empty), "--out", str(out)]) == 2
    assert "room: error: noise calibration: no readable images" in capsys.readouterr().err
    assert cli_main(["calibrate-noise", "--frames", str(frames), "--out", str(out), "tile=33"]) == 2


# --------------------------------------------------------------------------- the shared real frames


@pytest.mark.shared
def test_shipped_profile_comes_from_the_shared_brea_depth_frames():
    folder = shared_path("bronchoscopy_frames", "brea_depth")
    prof = NoiseProfile.load(REPO / "data" / "noise_profiles" / "brea_depth_ascope4.npz")
    prov = prof.provenance
    hashes = prov["frame_sha256"]
    assert len(hashes) == prov["frame_count"] == 45 and len(prov["split"]["held_out"]) == 15
    for name in list(hashes)[:5]:
        assert hashlib.sha256((folder / name).read_bytes()).hexdigest() == hashes[name]
    assert not set(prov["split"]["held_out"]) & set(hashes)
    assert (REPO / "data" / "noise_profiles" / "brea_depth_ascope4.npz").stat().st_size < 1_000_000
    assert np.all((prof.std > 1) & (prof.std < 10))


@pytest.mark.shared
def test_held_out_real_frames_match_the_shipped_profile():
    folder = shared_path("bronchoscopy_frames", "brea_depth")
    prof = NoiseProfile.load(REPO / "data" / "noise_profiles" / "brea_depth_ascope4.npz")
    held = prof.provenance["split"]["held_out"][::3]
    from room_pipeline.noise.calibrate import read_rgb
    p = CalibrationParams(holdout_every=0, compensate_filter=False)
    measured = calibrate_images([read_rgb(folder / n) for n in held], p)
    assert radial_lsd(measured.residual_psd, prof.residual_psd) < 1.0


@pytest.mark.shared
def test_lung_odometry_frames_480px_with_highlights_and_a_csv():
    folder = shared_path("bronchoscopy_frames", "lung_odometry")
    p = CalibrationParams(holdout_every=0, compensation_frames=2, compensation_iterations=1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        prof = calibrate_folder(folder, p)
    assert any("gt.csv" in str(w.message) for w in caught)
    assert prof.provenance["frame_count"] == 4 and prof.provenance["frame_shapes"] == ["480x480"]
    assert prof.provenance["valid_fraction_mean"] < 0.95          # saturated highlights excluded
    noisy = add_noise(clean_scene(480, 480, 0), prof, 1.0, 0)
    assert noisy.shape == (480, 480, 3)
