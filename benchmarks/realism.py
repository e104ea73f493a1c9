#!/usr/bin/env python3
"""Realism of the default RGB against real bronchoscope frames; the appearance fit; a lighting sweep.

    python benchmarks/realism.py [--inputs DIR] [--stride 10] [--fit] [--sweep] [--real DIR]
    python benchmarks/realism.py --from-run OUTPUT_DIR      # score a finished default run's frames as they are

Inputs: an output_dir holding ``patient_000/anatomy/{lung_model.obj,centreline_graph.json}`` and
``patient_000/sequence_000/metadata/simulation.json`` (``room run --until simulate output_dir=DIR``).
The needed files are copied into a scratch output_dir (``benchmarks/.cache/realism``), where the
**render and noise stages themselves** run in this process (``stages.render.run`` /
``stages.noise.run``, composed config ``conf/`` + overrides; every ``--stride``-th pose), and the noisy
frames are scored by :mod:`room_pipeline.realism` against the real Ambu aScope 4 frames
(``../shared/data/bronchoscopy_frames/brea_depth``, 60 frames, read in place).

Real frames are split by time: the first half (``fit``) is the only set the fit sees; the second
half (``check``) is held out.  Scores are reported against fit, check and all frames.

``--fit``: fits ``render.base_color`` (chroma) and ``render.auto_exposure_target`` (brightness) to the
*fit* frames together: three fixed-point steps, each rendering the sample and multiplying the base
colour by the ratio of the real to the synthetic mean linear RGB (normalised to unit luminance, so
the exposure keeps the brightness) and the target by the ratio of mean luminances.  Prints the fitted
values (to copy into ``conf/render/default.yaml``); never per frame.

``--sweep``: a lighting sweep (light power, falloff, spot exponent, exposure target) with its
realism statistics.

``--from-run OUTPUT_DIR``: nothing is rendered; every frame of every ``patient_*/sequence_*/rgb_noisy``
(and ``rgb``) folder of a finished run (e.g. the default ``dvc repro``) is scored: clipped / dark
fractions per sequence and over all of them (mean and worst frame), and the realism statistics of the
noisy frames against the real fit / check / all sets (``benchmarks/results/realism_run.{json,md}``).

Results: benchmarks/results/realism.{json,md} (and realism_fit / realism_sweep / realism_clipping / realism_run).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
RESULTS = ROOT / "benchmarks" / "results"
REAL = ROOT.parent / "shared" / "data" / "bronchoscopy_frames" / "brea_depth"
CACHE = ROOT / "benchmarks" / ".cache" / "realism"


def prepare(inputs: Path, mode: str, patient: str = "patient_000", seq: str = "sequence_000") -> Path:
    from room_pipeline.paths import PatientPaths

    out = CACHE / mode            # one scratch output_dir per mode: --fit, --sweep and the score may run at once
    need = [lambda pp: pp.mesh, lambda pp: pp.centreline_graph, lambda pp: pp.seq(seq).simulation]
    for path_of in need:
        src, dst = path_of(PatientPaths(inputs, patient)), path_of(PatientPaths(out, patient))
        if not src.exists():
            sys.exit(f"realism.py: {src} missing: run `room run --until simulate output_dir={inputs}` first")
        if not dst.exists() or dst.stat().st_mtime < src.stat().st_mtime:
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, dst)
    return out


def render(out: Path, overrides: list[str], stride: int, patient="patient_000", seq="sequence_000") -> dict:
    """Render (rgb only) + noise through the stages; returns timing and the noisy frame paths."""
    from room_pipeline.catalog import SequencePaths
    from room_pipeline.config.compose import compose
    from room_pipeline.stages import noise as noise_stage
    from room_pipeline.stages import render as render_stage

    cfg = compose([f"output_dir={out}", f"render.frame_stride={stride}", "render.modalities=[rgb]",
                   "execution.workers=1", *overrides])
    sp = SequencePaths(out / patient / seq)
    for folder in (sp.folder("rgb"), sp.rgb_noisy):
        shutil.rmtree(folder, ignore_errors=True)
    t0, c0 = time.perf_counter(), time.process_time()
    m = render_stage.run(cfg, f"{patient}/{seq}")
    t1, c1 = time.perf_counter(), time.process_time()
    noise_stage.run(cfg, f"{patient}/{seq}")
    meta = json.loads(sp.render_json.read_text())
    evs = meta["renderer"].get("auto_exposure", {}).get("frame_ev")
    return {"frames": m["frames"], "render_wall_s": round(t1 - t0, 2), "render_cpu_s": round(c1 - c0, 2),
            "paths": sorted(sp.rgb_noisy.glob("*.png")), "frame_ev": evs}


def score(paths, real_paths, noise=True) -> dict:
    from room_pipeline import realism as R

    real = R.load(real_paths, 256)
    synth = R.load(paths, 256)
    rs, ss = R.set_stats(real), R.set_stats(synth)
    psd_r = R.residual_psd(R.load(real_paths, 600)) if noise else None
    psd_s = R.residual_psd(R.load(paths, 600)) if noise else None
    c = R.compare(rs, ss, psd_r, psd_s)
    c.update(synth_lab=[round(float(x), 2) for x in ss["lab_mean"]], real_lab=[round(float(x), 2) for x in rs["lab_mean"]],
             clipped_mean=ss["clipped_fraction"], clipped_max=ss["clipped_max"], dark=ss["dark_fraction"])
    return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in c.items()}


def score_sets(paths, sets: dict, noise=True) -> dict:
    """:func:`score` against several real sets, the synthetic frames' statistics computed once."""
    from room_pipeline import realism as R

    ss = R.set_stats(R.load(paths, 256))
    psd_s = R.residual_psd(R.load(paths, 600)) if noise else None
    out = {}
    for k, real_paths in sets.items():
        rs = R.set_stats(R.load(real_paths, 256))
        psd_r = R.residual_psd(R.load(real_paths, 600)) if noise else None
        c = R.compare(rs, ss, psd_r, psd_s)
        c.update(synth_lab=[round(float(x), 2) for x in ss["lab_mean"]],
                 real_lab=[round(float(x), 2) for x in rs["lab_mean"]],
                 clipped_mean=ss["clipped_fraction"], clipped_max=ss["clipped_max"], dark=ss["dark_fraction"])
        out[k] = {kk: (round(v, 4) if isinstance(v, float) else v) for kk, v in c.items()}
    return out


def lab_to_linear(lab) -> np.ndarray:
    import cv2

    L, a, b = (float(x) for x in lab)
    # float Lab (L 0..100, a/b signed) -> sRGB float via OpenCV's float path, then linearise
    f = np.array([[[L, a, b]]], dtype=np.float32)
    rgb = cv2.cvtColor(f, cv2.COLOR_LAB2RGB)[0, 0].astype(np.float64)
    rgb = np.clip(rgb, 1e-4, 1.0)
    return np.where(rgb <= 0.04045, rgb / 12.92, ((rgb + 0.055) / 1.055) ** 2.4)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--inputs", default=str(ROOT / "data" / "output"))
    ap.add_argument("--real", default=str(REAL))
    ap.add_argument("--stride", type=int, default=10)
    ap.add_argument("--fit", action="store_true")
    ap.add_argument("--fit-damping", type=float, default=1.0,
                    help="exponent on each fit step's colour ratio (< 1 damps it: the inter-reflected light makes the "
                         "colour respond more than linearly to the albedo)")
    ap.add_argument("--sweep", action="store_true")
    ap.add_argument("--no-noise-psd", action="store_true")
    ap.add_argument("--clipping", action="store_true",
                    help="only the clipped/dark fractions and mean Lab of every --stride-th frame (noisy RGB)")
    ap.add_argument("--from-run", default=None, metavar="OUTPUT_DIR",
                    help="score the frames of a finished run (every frame of every sequence), render nothing")
    ap.add_argument("overrides", nargs="*")
    a = ap.parse_args()
    from room_pipeline import realism as R

    if a.from_run:
        from_run(Path(a.from_run), R.frame_paths(a.real), a.no_noise_psd)
        return

    out = prepare(Path(a.inputs), "fit" if a.fit else "sweep" if a.sweep else "clipping" if a.clipping else "score")
    real = R.frame_paths(a.real)
    half = len(real) // 2
    sets = {"fit": real[:half], "check": real[half:], "all": real}
    env = {"load_avg_start": os.getloadavg()[0], "cores": os.cpu_count()}
    RESULTS.mkdir(parents=True, exist_ok=True)

    if a.fit:
        from room_pipeline.config.compose import compose
        from room_pipeline.render.shading import LUMINANCE

        cfg = compose(a.overrides)
        base = np.array(cfg.render.base_color, dtype=np.float64)
        target = float(cfg.render.auto_exposure_target)
        real_lab = R.set_stats(R.load(sets["fit"], 256))["lab_mean"]
        steps = []
        for it in range(3):
            ov = [*a.overrides, f"render.base_color=[{','.join(f'{x:.4f}' for x in base)}]",
                  f"render.auto_exposure_target={target:.4f}"]
            r = render(out, ov, a.stride)
            s = score(r["paths"], sets["fit"], noise=False)
            steps.append({"step": it, "base_color": base.round(4).tolist(), "target": round(target, 4), **s})
            print(json.dumps(steps[-1]), flush=True)
            lr, ls = lab_to_linear(real_lab), lab_to_linear(s["synth_lab"])
            ratio = (lr / ls) / (float(LUMINANCE @ lr) / float(LUMINANCE @ ls))
            base = base * ratio ** a.fit_damping
            base = base / max(1.0, base.max() / 0.95)
            target = float(np.clip(target * float(LUMINANCE @ lr) / float(LUMINANCE @ ls), 0.05, 0.95))
        res = {"fit_on": [p.name for p in sets["fit"]], "steps": steps,
               "fitted": {"base_color": base.round(3).tolist(), "auto_exposure_target": round(target, 3)}, "env": env}
        (RESULTS / "realism_fit.json").write_text(json.dumps(res, indent=1))
        md = ["# Appearance fit to the real frames (first half of BREA-Depth, all together)", "",
              f"`python benchmarks/realism.py --fit --fit-damping {a.fit_damping} --stride {a.stride} {' '.join(a.overrides)}` (every {a.stride}th pose of "
              f"patient_000/sequence_000). Each row: the parameters rendered and their scores vs the fit frames.", "",
              "| step | base_color | target | synth Lab | real Lab | dE76 | L* EMD | clipped mean / max |", "|---|---|---|---|---|---|---|---|"]
        for s in steps:
            md.append(f"| {s['step']} | {s['base_color']} | {s['target']} | {s['synth_lab']} | {s['real_lab']} | "
                      f"{s['dE76_mean_colour']:.2f} | {s['L_hist_emd']:.2f} | {s['clipped_mean']:.4f} / {s['clipped_max']:.4f} |")
        md += ["", f"Fitted: `base_color: {res['fitted']['base_color']}`, `auto_exposure_target: "
                   f"{res['fitted']['auto_exposure_target']}`."]
        (RESULTS / "realism_fit.md").write_text("\n".join(md) + "\n")
        print("\n".join(md))
        return

    if a.sweep:
        grid = [("default", []),
                ("power x4", ["render.light_power_w=0.08"]),
                ("isotropic light", ["render.light_spot_exponent=0"]),
                ("spot mu 8", ["render.light_spot_exponent=8"]),
                ("exponential falloff L 10 mm", ["render.light_falloff=exponential", "render.light_falloff_length_mm=10"]),
                ("target 0.25", ["render.auto_exposure_target=0.25"]),
                ("target 0.7", ["render.auto_exposure_target=0.7"]),
                ("fixed exposure (first frame)", ["render.auto_exposure=first_frame"])]
        rows = []
        for name, ov in grid:
            r = render(out, [*a.overrides, *ov], a.stride)
            s = score(r["paths"], sets["all"], noise=False)
            rows.append({"name": name, "overrides": ov, **s})
            print(json.dumps(rows[-1]), flush=True)
        (RESULTS / "realism_sweep.json").write_text(json.dumps({"rows": rows, "env": env}, indent=1))
        md = ["# Lighting sweep (per-frame auto exposure on)", "",
              f"`python benchmarks/realism.py --sweep` (every {a.stride}th pose of patient_000/sequence_000, noisy RGB, "
              "vs all 60 real frames).", "",
              "| setting | overrides | synth Lab | dE76 | L* EMD | radial profile MAD | clipped mean / max | dark |",
              "|---|---|---|---|---|---|---|---|"]
        for s in rows:
            md.append(f"| {s['name']} | `{' '.join(s['overrides'])}` | {s['synth_lab']} | {s['dE76_mean_colour']:.2f} | "
                      f"{s['L_hist_emd']:.2f} | {s['radial_profile_mad']:.2f} | {s['clipped_mean']:.4f} / "
                      f"{s['clipped_max']:.4f} | {s['dark']:.4f} |")
        (RESULTS / "realism_sweep.md").write_text("\n".join(md) + "\n")
        print("\n".join(md))
        return

    if a.clipping:
        c0 = time.process_time()
        r = render(out, a.overrides, a.stride)
        res = {"overrides": a.overrides, "stride": a.stride, "frames": r["frames"],
               "noisy_rgb": R.sequence_metrics(r["paths"]), "cpu_s": round(time.process_time() - c0, 1), "env": env}
        (RESULTS / "realism_clipping.json").write_text(json.dumps(res, indent=1))
        m = res["noisy_rgb"]
        md = ["# Clipped pixels over a whole sequence (noisy RGB, default config)", "",
              f"`python benchmarks/realism.py --clipping --stride {a.stride}`: patient_000/sequence_000, every "
              f"{a.stride}th pose ({r['frames']} frames), full resolution; clipped = a channel >= 250.", "",
              "| frames | clipped mean | clipped worst frame | dark mean | mean Lab |", "|---|---|---|---|---|",
              f"| {r['frames']} | {m['rgb_clipped_fraction_mean']:.5f} | {m['rgb_clipped_fraction_max']:.5f} | "
              f"{m['rgb_dark_fraction_mean']:.5f} | [{m['rgb_L_mean']}, {m['rgb_a_mean']}, {m['rgb_b_mean']}] |"]
        (RESULTS / "realism_clipping.md").write_text("\n".join(md) + "\n")
        print("\n".join(md))
        return

    r = render(out, a.overrides, a.stride)
    res = {"overrides": a.overrides, "stride": a.stride, "frames": r["frames"],
           "render_wall_s_per_frame": round(r["render_wall_s"] / r["frames"], 3),
           "render_cpu_s_per_frame": round(r["render_cpu_s"] / r["frames"], 3),
           "frame_ev_range": [min(r["frame_ev"]), max(r["frame_ev"])] if r["frame_ev"] else None, "env": env}
    for k, ps in sets.items():
        res[k] = score(r["paths"], ps, noise=not a.no_noise_psd)
        print(k, json.dumps(res[k]), flush=True)
    res["env"]["load_avg_end"] = os.getloadavg()[0]
    (RESULTS / "realism.json").write_text(json.dumps(res, indent=1))
    md = ["# Realism of the default RGB (noisy) vs real Ambu aScope 4 frames", "",
          f"`python benchmarks/realism.py {' '.join(a.overrides)}`: patient_000/sequence_000 of the default phantom, "
          f"every {a.stride}th pose ({r['frames']} frames), render + noise stages at the composed default config; "
          f"real: BREA-Depth (60 frames), fit = first 30 (the only ones `--fit` saw), check = last 30 (held out). "
          f"Render: {res['render_cpu_s_per_frame']} CPU s/frame, {res['render_wall_s_per_frame']} wall s/frame "
          f"(RGB only incl. PNG write and the exposure pre-pass; load average {env['load_avg_start']:.1f} -> "
          f"{res['env']['load_avg_end']:.1f} on {env['cores']} cores).", "",
          "| real set | dE76 | L* EMD | clipped mean | clipped max frame | dark | radial profile MAD | gradient hist L1 | noise LSD dB |",
          "|---|---|---|---|---|---|---|---|---|"]
    for k in sets:
        s = res[k]
        md.append(f"| {k} | {s['dE76_mean_colour']:.2f} | {s['L_hist_emd']:.2f} | {s['clipped_mean']:.4f} | "
                  f"{s['clipped_max']:.4f} | {s['dark']:.4f} | {s['radial_profile_mad']:.2f} | "
                  f"{s['gradient_hist_L1']:.3f} | {s.get('noise_lsd_db', float('nan')):.2f} |")
    md += ["", f"Synthetic mean Lab {res['all']['synth_lab']}, real {res['all']['real_lab']}; per-frame exposure range "
               f"{res['frame_ev_range']} EV."]
    (RESULTS / "realism.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


def from_run(run: Path, real: list, no_psd: bool) -> None:
    """Clipping and realism statistics of every frame of a finished run (see the module docstring)."""
    from room_pipeline import realism as R

    c0, env = time.process_time(), {"load_avg_start": os.getloadavg()[0], "cores": os.cpu_count()}
    seqs = sorted(d for d in run.glob("*/sequence_*") if (d / "rgb_noisy").is_dir() or (d / "rgb").is_dir())
    if not seqs:
        sys.exit(f"realism.py: no patient_*/sequence_*/rgb_noisy under {run}")
    rows, noisy_all, clean_all = [], [], []
    for d in seqs:
        for kind in ("rgb_noisy", "rgb"):
            ps = sorted((d / kind).glob("frame_*.png"))
            if not ps:
                continue
            m = R.sequence_metrics(ps)
            rows.append({"sequence": f"{d.parent.name}/{d.name}", "kind": kind, "frames": len(ps), **m})
            (noisy_all if kind == "rgb_noisy" else clean_all).append((ps, m))
            print(json.dumps(rows[-1]), flush=True)

    def pooled(group):
        n = sum(len(ps) for ps, _ in group)
        return {"frames": n,
                "clipped_mean": sum(m["rgb_clipped_fraction_mean"] * len(ps) for ps, m in group) / n,
                "clipped_max": max(m["rgb_clipped_fraction_max"] for _, m in group),
                "dark_mean": sum(m["rgb_dark_fraction_mean"] * len(ps) for ps, m in group) / n} if group else None

    half = len(real) // 2
    sets = {"fit": real[:half], "check": real[half:], "all": real}
    noisy = [p for ps, _ in noisy_all for p in ps]
    res = {"run": str(run), "per_sequence": rows, "noisy_all": pooled(noisy_all), "clean_all": pooled(clean_all),
           "realism": score_sets(noisy, sets, noise=not no_psd) if noisy else {}, "env": env}
    res["cpu_s"] = round(time.process_time() - c0, 1)
    res["env"]["load_avg_end"] = os.getloadavg()[0]
    (RESULTS / "realism_run.json").write_text(json.dumps(res, indent=1, default=str))
    md = ["# Clipping and realism over every frame of a finished run", "",
          f"`python benchmarks/realism.py --from-run {run}`: every frame of every sequence, full resolution, as the "
          "run wrote them (nothing re-rendered); clipped = a channel >= 250, dark = all channels <= 10.", "",
          "| sequence | kind | frames | clipped mean | clipped worst frame | dark mean | mean Lab |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| {r['sequence']} | {r['kind']} | {r['frames']} | {100 * r['rgb_clipped_fraction_mean']:.3f} % | "
                  f"{100 * r['rgb_clipped_fraction_max']:.3f} % | {100 * r['rgb_dark_fraction_mean']:.3f} % | "
                  f"[{r['rgb_L_mean']}, {r['rgb_a_mean']}, {r['rgb_b_mean']}] |")
    for k in ("noisy_all", "clean_all"):
        g = res[k]
        if g:
            md.append(f"| all ({k.split('_')[0]}) | | {g['frames']} | {100 * g['clipped_mean']:.3f} % | "
                      f"{100 * g['clipped_max']:.3f} % | {100 * g['dark_mean']:.3f} % | |")
    if res["realism"]:
        md += ["", "Noisy frames of every sequence against the real BREA-Depth frames (fit = first 30, check = last "
                   "30 held out):", "", "| real set | dE76 | L* EMD | clipped mean | clipped max frame | dark | "
                   "radial profile MAD | gradient hist L1 | noise LSD dB |", "|---|---|---|---|---|---|---|---|---|"]
        for k, s_ in res["realism"].items():
            md.append(f"| {k} | {s_['dE76_mean_colour']:.2f} | {s_['L_hist_emd']:.2f} | {s_['clipped_mean']:.4f} | "
                      f"{s_['clipped_max']:.4f} | {s_['dark']:.4f} | {s_['radial_profile_mad']:.2f} | "
                      f"{s_['gradient_hist_L1']:.3f} | {s_.get('noise_lsd_db', float('nan')):.2f} |")
    md += ["", f"{res['cpu_s']} CPU s; load average {env['load_avg_start']:.1f} -> {env['load_avg_end']:.1f}."]
    (RESULTS / "realism_run.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
