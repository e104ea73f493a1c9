#!/usr/bin/env python3
"""Sensor-noise model: every figure of issue #6 (calibration, synthesis, validation, speed).

Inputs:
  * the real frames ``../shared/data/bronchoscopy_frames/brea_depth`` (60 x 600x600 JPEG, Ambu aScope 4)
    and ``lung_odometry`` (4 x 480x480 JPEG, another dataset) -- read in place, never copied;
  * the shipped profile ``data/noise_profiles/brea_depth_ascope4.npz`` (45 calibration frames of
    BREA-Depth; the 15 held-out frames named in its provenance are used below as unseen frames);
  * clean renders: the 20 frames of ``data/output/patient_000/sequence_001/rgb`` when present,
    else 12 frames rendered here with the fast ray caster in a wobbly tube (``--render``).

Measured:
  1. reproducibility: the calibration command re-run gives the shipped profile's bytes (``--recalibrate``);
  2. synthesised noise vs the profile: radial log-spectral distance (LSD, dB; definition in
     ``room_pipeline.noise.spectrum``) of the mean periodogram of N synthesised 600x600 frames;
  3. round trip: clean renders + noise (beta = 1) -> calibration (bilateral residual spectrum) vs the
     real frames' residual spectrum, and the clean renders' own residual spectrum vs the real one;
     also with a profile calibrated without the filter compensation (ablation) and for beta 0.5 / 2;
  4. unseen real frames (the held-out split; the lung_odometry frames) vs noisy and clean renders;
  5. intensity dependence (residual variance per luma bin, fitted slope, t-test across frames);
  6. speed: ``add_noise`` per 600x600 RGB frame (median of many; wall and CPU time; machine load).

    python benchmarks/noise.py [--speed-runs 200] [--synth-frames 20] [--no-recalibrate] [--speed-only]
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from room_pipeline.io.atomic import write_json, write_text
from room_pipeline.noise.calibrate import CalibrationParams, calibrate_images, read_rgb
from room_pipeline.noise.profile import NoiseProfile
from room_pipeline.noise.spectrum import periodogram, radial_average, radial_lsd
from room_pipeline.noise.synthesize import add_noise, filter_table, synthesize, white_noise

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
SHARED = Path(os.environ.get("ROOM_SHARED_DATA", ROOT.parent / "shared" / "data"))
BREA = SHARED / "bronchoscopy_frames" / "brea_depth"
LUNG = SHARED / "bronchoscopy_frames" / "lung_odometry"
PROFILE = ROOT / "data" / "noise_profiles" / "brea_depth_ascope4.npz"
RENDERS = ROOT / "data" / "output" / "patient_000" / "sequence_001" / "rgb"
#: residual spectra of validation sets: same filter and tiles as the profile, no compensation, no hold-out
MEASURE = CalibrationParams(holdout_every=0, compensate_filter=False)


def load_renders(args) -> tuple[list[np.ndarray], str]:
    files = sorted(RENDERS.glob("frame_*.png")) if RENDERS.is_dir() and not args.render else []
    if files:
        return [read_rgb(f) for f in files], f"{RENDERS.relative_to(ROOT)} ({len(files)} frames, phantom airway)"
    from room_pipeline.io.mesh import Mesh
    from room_pipeline.render.camera import CameraIntrinsics
    from room_pipeline.render.raycast import RaycastRenderer
    from room_pipeline.render.scene import Scene

    mm = 1e-3
    th = np.linspace(0, 2 * np.pi, 96, endpoint=False)
    zs = np.linspace(-5 * mm, 80 * mm, 120)
    r = 6 * mm * (1 + 0.15 * np.sin(3 * th)[None, :] * np.cos(zs / (9 * mm))[:, None])
    v = np.stack([r * np.cos(th)[None], r * np.sin(th)[None], np.broadcast_to(zs[:, None], r.shape)], -1)
    idx = np.arange(len(zs) * len(th)).reshape(len(zs), len(th))
    a, b, c, d = idx[:-1], np.roll(idx, -1, 1)[:-1], idx[1:], np.roll(idx, -1, 1)[1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)])
    poses = []
    for i in range(12):
        T = np.eye(4)
        T[:3, 3] = [0.8 * mm * np.sin(i / 3), 0.5 * mm * np.cos(i / 4), i * 2 * mm]
        poses.append(T)
    scene = Scene(Mesh(v.reshape(-1, 3), faces), CameraIntrinsics.from_fov(600, 600, 85.0), np.array(poses),
                  np.arange(12) * 0.1)
    rr = RaycastRenderer(scene)
    return [rr.render(i, ("rgb",))["rgb"] for i in range(12)], "12 frames rendered here (fast ray caster, tube)"


def residual_psd(images: list[np.ndarray]) -> tuple[np.ndarray, NoiseProfile]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prof = calibrate_images(images, MEASURE)
    return prof.residual_psd, prof


def db(x: np.ndarray) -> list:
    return [round(float(v), 2) for v in 10 * np.log10(x)]


def speed(profile: NoiseProfile, img: np.ndarray, runs: int) -> dict:
    add_noise(img, profile, 1.0, 0)                                    # builds the cached filter table
    load0 = os.getloadavg()
    wall, cpu = [], []
    for i in range(runs):
        t0, c0 = time.perf_counter(), time.process_time()
        add_noise(img, profile, 1.0, i)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    load1 = os.getloadavg()
    rng = np.random.default_rng(0)
    parts = {}
    import cv2
    import scipy.fft as sfft
    table = filter_table(profile, (600, 600))
    white = white_noise(rng, (3, 600, 301, 2)).view(np.complex64)[..., 0]
    mixed = np.ascontiguousarray(np.moveaxis(table[:, 0] * white[0], 0, -1))
    noise = synthesize(profile, (600, 600), rng)
    for name, fn in {"white_noise": lambda: white_noise(rng, (3, 600, 301, 2)),
                     "same_count_generator_standard_normal_f32":
                         lambda: rng.standard_normal((3, 600, 301, 2), dtype=np.float32),
                     "irfft2": lambda: sfft.irfft2(mixed, s=(600, 600), axes=(0, 1)),
                     "synthesize_total": lambda: synthesize(profile, (600, 600), rng),
                     "add_and_quantise": lambda: cv2.add(img, noise, dtype=cv2.CV_8U)}.items():
        ts = []
        for _ in range(max(20, runs // 5)):
            t0 = time.perf_counter()
            fn()
            ts.append(time.perf_counter() - t0)
        parts[name] = round(1e3 * float(np.median(ts)), 3)
    t0 = time.perf_counter()
    fresh = NoiseProfile(profile.spectrum, profile.residual_psd, profile.intensity)
    add_noise(img, fresh, 1.0, 0)
    first = time.perf_counter() - t0
    return {"runs": runs, "median_ms": round(1e3 * float(np.median(wall)), 3),
            "p10_ms": round(1e3 * float(np.percentile(wall, 10)), 3),
            "p90_ms": round(1e3 * float(np.percentile(wall, 90)), 3),
            "min_ms": round(1e3 * float(np.min(wall)), 3),
            "cpu_median_ms": round(1e3 * float(np.median(cpu)), 3),
            "first_call_ms_incl_filter_table": round(1e3 * first, 1),
            "components_median_ms": parts,
            "loadavg_before": [round(x, 2) for x in load0], "loadavg_after": [round(x, 2) for x in load1],
            "target_ms": 20.0}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--speed-runs", type=int, default=200)
    ap.add_argument("--synth-frames", type=int, default=20)
    ap.add_argument("--no-recalibrate", action="store_true", help="skip re-running the calibration command")
    ap.add_argument("--render", action="store_true", help="render clean frames here even if the example exists")
    ap.add_argument("--speed-only", action="store_true",
                    help="re-measure only the speed and update the existing results/noise.{json,md}")
    args = ap.parse_args()
    command = "python " + " ".join([f"benchmarks/{Path(__file__).name}", *sys.argv[1:]])
    if args.speed_only:
        res = json.loads((RESULTS / "noise.json").read_text(encoding="utf-8"))
        img = read_rgb(RENDERS / "frame_0000.png") if (RENDERS / "frame_0000.png").is_file() else None
        res["speed_600x600"] = speed(NoiseProfile.load(PROFILE), img if img is not None and img.shape[:2] == (600, 600)
                                     else np.full((600, 600, 3), 128, np.uint8), args.speed_runs)
        res["speed_600x600"]["command"] = command
        write_json(RESULTS / "noise.json", res)
        write_text(RESULTS / "noise.md", report(res))
        print(report(res))
        return 0
    if not BREA.is_dir():
        print(f"shared frames not found: {BREA}", file=sys.stderr)
        return 1
    res: dict = {"command": command,
                 "machine": {"platform": platform.platform(), "cpus": os.cpu_count(),
                             "loadavg_start": [round(x, 2) for x in os.getloadavg()]}}
    t_start = time.perf_counter()
    profile = NoiseProfile.load(PROFILE)
    prov = profile.provenance
    gain_db = 10 * np.log10(profile.psd / profile.residual_psd)
    res["profile"] = {"path": str(PROFILE.relative_to(ROOT)),
                      "sha256": hashlib.sha256(PROFILE.read_bytes()).hexdigest(),
                      "bytes": PROFILE.stat().st_size, "frames_used": prov["frame_count"],
                      "held_out": len(prov["split"]["held_out"]), "tiles": prov["tiles"],
                      "std_levels": [round(float(v), 4) for v in profile.std],
                      "residual_std_levels": [round(float(v), 4) for v in np.sqrt(profile.residual_psd.mean((1, 2)))],
                      "correlation": np.round(profile.correlation, 4).tolist(),
                      "compensation_mismatch_db": prov["filter_compensation"]["residual_mismatch_db_per_iteration"],
                      "compensation_gain_db_max": round(float(gain_db.max()), 3),
                      "compensation_bound_db": prov["filter_compensation"]["max_db"],
                      "bins_at_bound_fraction": round(float(np.mean(
                          gain_db >= prov["filter_compensation"]["max_db"] - 0.01)), 5)}

    # 1. reproducibility of the shipped profile
    if not args.no_recalibrate:
        with tempfile.TemporaryDirectory() as tmp:
            out = Path(tmp) / "p.npz"
            cmd = [sys.executable, "-m", "room_pipeline.cli", "calibrate-noise", "--frames",
                   os.path.relpath(BREA, ROOT), "--out", str(out)]
            t0 = time.perf_counter()
            subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True)
            res["recalibration"] = {"command": "room calibrate-noise --frames ../shared/data/bronchoscopy_frames/"
                                               "brea_depth --out data/noise_profiles/brea_depth_ascope4.npz",
                                    "wall_s": round(time.perf_counter() - t0, 2),
                                    "same_npz_bytes": out.read_bytes() == PROFILE.read_bytes()}

    # 2. synthesised noise vs the profile
    rng = np.random.default_rng(12345)
    acc = np.zeros((3, 600, 600))
    for _ in range(args.synth_frames):
        acc += periodogram(synthesize(profile, (600, 600), rng))
    acc /= args.synth_frames
    res["synthesis_vs_profile"] = {
        "frames": args.synth_frames, "shape": [600, 600],
        "radial_lsd_db": round(radial_lsd(acc, profile.psd), 4),
        "radial_lsd_db_per_channel": [round(radial_lsd(acc[c], profile.psd[c]), 4) for c in range(3)],
        "target_db": 1.0}
    rng = np.random.default_rng(7)
    for shape in [(480, 480), (1080, 1080)]:
        n = synthesize(profile, shape, rng).reshape(-1, 3)
        res["synthesis_vs_profile"][f"std_ratio_{shape[0]}x{shape[1]}"] = \
            [round(float(v), 4) for v in n.std(0) / profile.std]

    # 3. round trip with the clean renders
    renders, render_src = load_renders(args)
    res["renders"] = render_src
    real_psd = profile.residual_psd
    clean_psd, clean_prof = residual_psd(renders)
    rt = {}
    for beta in (0.5, 1.0, 2.0):
        noisy = [add_noise(im, profile, beta, i) for i, im in enumerate(renders)]
        psd, prof_b = residual_psd(noisy)
        rt[f"beta_{beta:g}"] = {"radial_lsd_vs_real_db": round(radial_lsd(psd, real_psd), 4),
                                "residual_std_levels": [round(float(v), 4) for v in np.sqrt(psd.mean((1, 2)))],
                                "residual_correlation": np.round(prof_b.correlation, 4).tolist()}
        if beta == 1.0:
            noisy_psd, noisy1 = psd, noisy
    comp_off = dataclasses.replace(CalibrationParams(), compensate_filter=False)
    calib_imgs = [read_rgb(BREA / n) for n in prov["frames_used"]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        prof_nocomp = calibrate_images(calib_imgs, comp_off)
    nc_psd, _ = residual_psd([add_noise(im, prof_nocomp, 1.0, i) for i, im in enumerate(renders)])
    res["round_trip"] = {
        "recovered_vs_real_db": rt["beta_1"]["radial_lsd_vs_real_db"],
        "clean_residual_vs_real_db": round(radial_lsd(clean_psd, real_psd), 4),
        "target_db": 1.5, "by_beta": rt,
        "ablation_no_filter_compensation_recovered_vs_real_db": round(radial_lsd(nc_psd, real_psd), 4),
        "real_residual_std_levels": res["profile"]["residual_std_levels"],
        "clean_residual_std_levels": [round(float(v), 4) for v in np.sqrt(clean_psd.mean((1, 2)))]}

    # 4. frames the calibration never saw
    held = [read_rgb(BREA / n) for n in prov["split"]["held_out"]]
    held_psd, held_prof = residual_psd(held)
    unseen = {"brea_depth_held_out": {
        "frames": len(held),
        "vs_noisy_renders_db": round(radial_lsd(held_psd, noisy_psd), 4),
        "vs_clean_renders_db": round(radial_lsd(held_psd, clean_psd), 4),
        "vs_profile_residual_db": round(radial_lsd(held_psd, real_psd), 4),
        "residual_std_levels": [round(float(v), 4) for v in np.sqrt(held_psd.mean((1, 2)))],
        "residual_correlation": np.round(held_prof.correlation, 4).tolist()}}
    if LUNG.is_dir():
        lung = [im for im in (read_rgb(p) for p in sorted(LUNG.iterdir()) if p.is_file()) if im is not None]
        lung_psd, _ = residual_psd(lung)
        unseen["lung_odometry_other_dataset"] = {
            "frames": len(lung), "shape": list(lung[0].shape[:2]),
            "vs_noisy_renders_db": round(radial_lsd(lung_psd, noisy_psd), 4),
            "vs_clean_renders_db": round(radial_lsd(lung_psd, clean_psd), 4),
            "vs_profile_residual_db": round(radial_lsd(lung_psd, real_psd), 4),
            "residual_std_levels": [round(float(v), 4) for v in np.sqrt(lung_psd.mean((1, 2)))]}
    res["unseen_frames"] = unseen
    f, r_real = radial_average(real_psd)
    res["radial_psd_db"] = {"f_cycles_per_px": [round(float(x), 4) for x in f],
                            "real_residual_G": db(r_real[1]),
                            "held_out_residual_G": db(radial_average(held_psd)[1][1]),
                            "noisy_render_residual_G": db(radial_average(noisy_psd)[1][1]),
                            "clean_render_residual_G": db(radial_average(clean_psd)[1][1]),
                            "synthesis_spectrum_G": db(radial_average(profile.psd)[1][1])}
    # JPEG 8x8 block grid: residual power on the fx = k/8 columns vs their neighbours (profile grid 1/64)
    s = profile.residual_psd.mean(0)
    t = profile.tile
    peaks = [float(s[:, k * t // 8].mean() / (0.5 * (s[:, k * t // 8 - 1].mean() + s[:, k * t // 8 + 1].mean())))
             for k in (1, 2, 3, 4)]
    res["jpeg_block_grid_peak_ratio_fx_k_over_8"] = [round(v, 3) for v in peaks]

    # 5. intensity dependence
    it = profile.intensity_test
    held_it = held_prof.intensity_test
    res["intensity_dependence"] = {
        k: it.get(k) for k in ("luma_bin_centres", "pooled_residual_var", "pooled_pixels", "slope_mean", "slope_se",
                               "t", "p_value", "intercept_mean", "luma_p10", "luma_p90", "std_ratio_p90_p10",
                               "significant", "modelled", "decision")}
    res["intensity_dependence"]["held_out_frames"] = {
        k: held_it.get(k) for k in ("slope_mean", "slope_se", "t", "p_value", "std_ratio_p90_p10", "significant")}

    # 6. speed
    res["speed_600x600"] = speed(profile, renders[0] if renders[0].shape[:2] == (600, 600)
                                 else np.full((600, 600, 3), 128, np.uint8), args.speed_runs)
    res["speed_600x600"]["command"] = command
    res["machine"]["loadavg_end"] = [round(x, 2) for x in os.getloadavg()]
    res["wall_s"] = round(time.perf_counter() - t_start, 1)
    write_json(RESULTS / "noise.json", res)
    write_text(RESULTS / "noise.md", report(res))
    print(report(res))
    return 0


def report(r: dict) -> str:
    p, syn, rt, sp = r["profile"], r["synthesis_vs_profile"], r["round_trip"], r["speed_600x600"]

    def j(values) -> str:
        return ", ".join(map(str, values))

    un, it = r["unseen_frames"], r["intensity_dependence"]
    lines = [
        "# Sensor-noise model (issue #6)", "",
        f"Command: `{r['command']}` (run from the project root; {r['wall_s']} s).  Machine: {r['machine']['cpus']} "
        f"CPUs shared with other users, load average {r['machine']['loadavg_start'][0]} at start, "
        f"{r['machine']['loadavg_end'][0]} at end.  Spectral distances are radial log-spectral distances "
        "(RMS of 10 log10 of the ratio over 32 annuli 0 < |f| <= 0.5 cycle/pixel and over R, G, B; "
        "`room_pipeline.noise.spectrum`).  Residual spectra: bilateral residual, Hann-windowed 64x64 tiles, "
        "same settings as the calibration.", "",
        "## Profile", "",
        f"`{p['path']}` ({p['bytes']} bytes, sha256 `{p['sha256'][:16]}...`): {p['frames_used']} BREA-Depth frames "
        f"(every 4th of the 60 held out: {p['held_out']}), {p['tiles']} tiles.  Noise std for synthesis R, G, B = "
        f"{j(p['std_levels'])} levels; bilateral residual std {j(p['residual_std_levels'])}; channel correlation "
        f"R-G {p['correlation'][0][1]}, R-B {p['correlation'][0][2]}, G-B {p['correlation'][1][2]}.  "
        f"Filter-compensation fixed point: residual mismatch {p['compensation_mismatch_db']} dB per iteration.",
    ]
    if "recalibration" in r:
        rc = r["recalibration"]
        lines += ["", f"Re-running `{rc['command']}` ({rc['wall_s']} s) gives the same `.npz` bytes: "
                      f"**{rc['same_npz_bytes']}**."]
    lines += [
        "", "## Synthesis vs profile", "",
        f"Mean periodogram of {syn['frames']} synthesised 600x600 frames vs the profile PSD: "
        f"**{syn['radial_lsd_db']} dB** (target <= {syn['target_db']}); per channel "
        f"{j(syn['radial_lsd_db_per_channel'])} dB.  Resampled to 480x480 and 1080x1080 the "
        f"per-pixel std / profile std is {syn['std_ratio_480x480']} and {syn['std_ratio_1080x1080']}.",
        "", "## Round trip: clean renders + noise -> calibration", "",
        f"Clean renders: {r['renders']}.", "",
        "| spectrum | LSD vs real frames' residual (dB) | residual std R,G,B (levels) |", "|---|---|---|",
        f"| noisy renders, beta = 1 (recovered) | **{rt['recovered_vs_real_db']}** (target <= {rt['target_db']}) | "
        f"{', '.join(map(str, rt['by_beta']['beta_1']['residual_std_levels']))} |",
        f"| clean renders' own residual | **{rt['clean_residual_vs_real_db']}** | "
        f"{', '.join(map(str, rt['clean_residual_std_levels']))} |",
        f"| noisy renders, beta = 0.5 | {rt['by_beta']['beta_0.5']['radial_lsd_vs_real_db']} | "
        f"{', '.join(map(str, rt['by_beta']['beta_0.5']['residual_std_levels']))} |",
        f"| noisy renders, beta = 2 | {rt['by_beta']['beta_2']['radial_lsd_vs_real_db']} | "
        f"{', '.join(map(str, rt['by_beta']['beta_2']['residual_std_levels']))} |",
        f"| noisy renders, profile without filter compensation (ablation) | "
        f"{rt['ablation_no_filter_compensation_recovered_vs_real_db']} | |",
        f"| real frames (calibration split) | 0 | {', '.join(map(str, rt['real_residual_std_levels']))} |",
        "", "## Frames the calibration never saw", "",
        "| real frames | n | vs noisy renders (dB) | vs clean renders (dB) | vs profile residual (dB) | residual std |",
        "|---|---|---|---|---|---|"]
    for name, u in un.items():
        lines.append(f"| {name} | {u['frames']} | **{u['vs_noisy_renders_db']}** | {u['vs_clean_renders_db']} | "
                     f"{u['vs_profile_residual_db']} | {', '.join(map(str, u['residual_std_levels']))} |")
    rp = r["radial_psd_db"]
    lines += ["", "Radially averaged residual PSD, G channel, dB re 1 level^2/(cycle/pixel)^2 (every 4th annulus):", "",
              "| f (cycle/px) | " + " | ".join(str(x) for x in rp["f_cycles_per_px"][::4]) + " |",
              "|---" * (1 + len(rp["f_cycles_per_px"][::4])) + "|"]
    for k in ("real_residual_G", "held_out_residual_G", "noisy_render_residual_G", "clean_render_residual_G",
              "synthesis_spectrum_G"):
        lines.append(f"| {k} | " + " | ".join(str(x) for x in rp[k][::4]) + " |")
    lines += ["", "JPEG 8x8 block grid: residual power on the columns fx = k/8 (k = 1..4) over their neighbours: "
                  f"{r['jpeg_block_grid_peak_ratio_fx_k_over_8']} (1 = no trace of the block grid; the profile "
                  "models the compressed output, so whatever is there it keeps).",
              "", "## Intensity dependence", "",
              "Residual variance (levels^2, mean of R, G, B) per luma bin of the filtered frame, calibration split:",
              "",
              "| luma | " + " | ".join(str(int(x)) for x in it["luma_bin_centres"]) + " |",
              "|---" * (1 + len(it["luma_bin_centres"])) + "|",
              "| variance | " + " | ".join("-" if v is None else str(round(v, 2))
                                          for v in it["pooled_residual_var"]) + " |",
              "| pixels (k) | " + " | ".join(str(round(n / 1000)) for n in it["pooled_pixels"]) + " |", "",
              f"Per-frame fit var = a + b Y: slope b = {it['slope_mean']:.5f} +- {it['slope_se']:.5f} (SE) levels^2 "
              f"per level, t = {it['t']:.1f}, p = {it['p_value']:.2g}; std ratio between luma p10 = "
              f"{it['luma_p10']:.0f} and p90 = {it['luma_p90']:.0f}: {it['std_ratio_p90_p10']:.3f}.  "
              f"Decision: {it['decision']}.  Held-out frames: slope {it['held_out_frames']['slope_mean']:.5f}, "
              f"t = {it['held_out_frames']['t']:.1f}, p = {it['held_out_frames']['p_value']:.2g}, std ratio "
              f"{it['held_out_frames']['std_ratio_p90_p10']:.3f}.  Caveat: brighter areas are the nearer walls, "
              "where tissue texture is sharper; texture finer than the filter also enters the residual.",
              "", "## Notes", "",
              "- The synthesis spectrum is larger than the measured residual (std "
              f"{j(p['std_levels'])} vs {j(p['residual_std_levels'])} levels) because `I - BF(I)` misses most "
              "of the noise below the filter's cut-off; the calibration's filter compensation puts it back "
              "(fixed point, at most 20 dB per frequency) so that the residual of noisy renders matches the real "
              "one.  Without it the round trip is off by "
              f"{rt['ablation_no_filter_compensation_recovered_vs_real_db']} dB.  The lowest annulus "
              f"(f = {rp['f_cycles_per_px'][0]}) stays "
              f"{round(rp['real_residual_G'][0] - rp['noisy_render_residual_G'][0], 1)} dB below the real frames "
              "(G): there the filter passes almost none of the noise, the fixed point converges slowest, the "
              "shading of the calibration frames adds residual power of its own that the renders lack, and the "
              f"correction is bounded (largest gain {p['compensation_gain_db_max']} dB, bound "
              f"{p['compensation_bound_db']} dB, {100 * p['bins_at_bound_fraction']:.2f} % of the bins at it).",
              "- Residual power the filter sees at low frequencies may be tissue texture as well as noise: "
              "the method cannot tell them apart, and renders lack that texture, so the profile lends it to the noise.",
              "- beta = 1 is the best of the betas tried: 0.5 and 2 are several dB further from the real residual.",
              "- The lung_odometry frames (another scope and processing chain, 480x480) are much cleaner "
              f"(residual std {j(un['lung_odometry_other_dataset']['residual_std_levels'])} levels): the BREA-Depth "
              "profile does not describe them; calibrate one profile per camera."
              if "lung_odometry_other_dataset" in un else "",
              "", "## Speed (add_noise, 600x600 RGB, uint8 in/out, intensity model on)", "",
              f"`{sp.get('command', r['command'])}`: median **{sp['median_ms']} ms** per frame over "
              f"{sp['runs']} frames (p10 {sp['p10_ms']}, p90 "
              f"{sp['p90_ms']}, min {sp['min_ms']}; CPU {sp['cpu_median_ms']} ms); target <= {sp['target_ms']} ms.  "
              f"Load average {sp['loadavg_before'][0]} before, {sp['loadavg_after'][0]} after (2 cores shared).  "
              f"First call incl. the filter table: {sp['first_call_ms_incl_filter_table']} ms.  "
              "Components (median ms): "
              + ", ".join(f"{k} {v}" for k, v in sp["components_median_ms"].items()) + ".", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
