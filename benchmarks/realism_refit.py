#!/usr/bin/env python3
"""Refit the appearance with the inter-reflection on: colour, exposure target, veiling glare and noise
amplitude together, on 45 real frames; score on the real frames the fit never saw.

    python benchmarks/realism_refit.py [--inputs OUTPUT_DIR] [--stride 20] [--glare 0,0.05,0.12]
                                       [--beta 0.8,1.0,1.2] [overrides ...]
    python benchmarks/realism_refit.py --check [--stride 20] [overrides ...]   # score the composed config only

Real frames (read in place, never copied): the 60 BREA-Depth Ambu aScope 4 frames sorted by name, split as
the noise profile's calibration splits them (``noise.calibration.holdout_every: 4``, ``holdout_offset: 3``):
**fit** = the 45 with index % 4 != 3 (the only frames the fit sees; also the frames the noise profile was
measured on), **held out** = the 15 with index % 4 == 3 plus the 4 Lung-Odometry frames (another scope,
480x480; the judges resize them), 19 frames.

Synthetic sample: every ``--stride``-th pose of both default sequences (patient_000 and patient_001,
sequence_000), rendered (RGB only) and noised **by the render and noise stages themselves** at the composed
config (``conf/`` + overrides, ``render.indirect_bounces`` as composed: pass ``render.indirect_bounces=8`` to
fit with the inter-reflection when the default is 0).

Fit (few parameters, all frames together, never per frame): for each veiling glare ``g`` of ``--glare``:
``--steps`` renders of the damped fixed point of ``render.base_color`` (chroma: ratio of the real to the synthetic mean
linear RGB at unit luminance, exponent 0.5) and ``render.auto_exposure_target`` (ratio of mean luminances)
against the fit frames; then, on that last render, the noise stage for each ``noise.beta`` of ``--beta``.
Every (g, beta) is scored against the fit frames by the shared judges (``../shared/tools/realism_check.py``,
``../shared/tools/noise_psd_check.py``, run as they are) and the one with the smallest worst margin
``max(dE76 / 6, L* EMD / 6, LSD / 1.5)`` on the **fit** frames is chosen; only then is it scored on the held-out
frames (both are written).  Synthetic frames, real split lists and logs live under ``--scratch``
(default ``/tmp/room_realism_refit``); a rerun reuses the rows a previous run left there for the same glare
and betas (``--fresh`` re-renders).

Results: benchmarks/results/realism_refit.{json,md} (``--out``; ``--check``: realism_refit_check.{json,md}).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(ROOT / "benchmarks"))
RESULTS = ROOT / "benchmarks" / "results"
SHARED = ROOT.parent / "shared"
BREA = SHARED / "data" / "bronchoscopy_frames" / "brea_depth"
ODO = SHARED / "data" / "bronchoscopy_frames" / "lung_odometry"
TOOLS = SHARED / "tools"
SEQS = [("patient_000", "sequence_000"), ("patient_001", "sequence_000")]
BOUNDS = {"dE76": 6.0, "L_emd": 6.0, "lsd_db": 1.5}


def real_split(scratch: Path) -> dict[str, Path]:
    """Symlink folders of the fit / held-out real frames (the judges take folders)."""
    brea = sorted(p for p in BREA.iterdir() if p.suffix.lower() in (".jpg", ".png"))
    odo = sorted(p for p in ODO.iterdir() if p.suffix.lower() in (".jpg", ".png")) if ODO.is_dir() else []
    if len(brea) < 60:
        sys.exit(f"realism_refit.py: expected the 60 BREA-Depth frames in {BREA}, found {len(brea)}")
    sets = {"fit": [p for i, p in enumerate(brea) if i % 4 != 3],
            "heldout": [p for i, p in enumerate(brea) if i % 4 == 3] + odo,
            "heldout_brea": [p for i, p in enumerate(brea) if i % 4 == 3]}
    out = {}
    for k, ps in sets.items():
        d = scratch / "real" / k
        shutil.rmtree(d, ignore_errors=True)
        d.mkdir(parents=True)
        for p in ps:
            (d / f"{p.parent.name}_{p.name}").symlink_to(p)
        out[k] = d
    return out


def judge(real: Path, synth: Path) -> dict:
    """The shared tools, run as they are, on two folders."""
    py = sys.executable
    r = subprocess.run([py, str(TOOLS / "realism_check.py"), str(real), str(synth), "--n", "1000",
                        "--json", str(synth.parent / f"rc_{real.name}.json")], capture_output=True, text=True)
    if r.returncode:
        sys.exit(f"realism_check failed: {r.stderr[-2000:]}")
    rc = json.loads((synth.parent / f"rc_{real.name}.json").read_text())
    n = subprocess.run([py, str(TOOLS / "noise_psd_check.py"), str(real), str(synth)], capture_output=True, text=True)
    if n.returncode:
        sys.exit(f"noise_psd_check failed: {n.stderr[-2000:]}")
    lsd = float(re.search(r"mean ([0-9.]+)", n.stdout).group(1))
    return {"realism_check": rc, "lsd_db": lsd, "noise_stdout": n.stdout.strip()}


def summary(j: dict) -> dict:
    rc = j["realism_check"]
    pick = lambda *ks: next(rc[k] for k in ks if k in rc)  # noqa: E731
    return {"dE76": pick("dE76_mean_colour", "dE76"), "L_emd": pick("L_hist_emd", "L_emd", "L_histogram_emd"),
            "lsd_db": j["lsd_db"]}


def collect(outs: list[Path], dst: Path, kind: str = "rgb_noisy") -> tuple[Path, list[Path]]:
    shutil.rmtree(dst, ignore_errors=True)
    dst.mkdir(parents=True)
    paths = []
    for out in outs:
        for (pat, seq) in SEQS:
            for p in sorted((out / pat / seq / kind).glob("frame_*.png")):
                q = dst / f"{pat}_{p.name}"
                q.symlink_to(p)
                paths.append(p)
    return dst, paths


def render_both(outs: dict, overrides: list[str], stride: int) -> dict:
    import realism as RB

    res = {"frames": 0, "render_cpu_s": 0.0, "render_wall_s": 0.0, "paths": []}
    for (pat, seq) in SEQS:
        r = RB.render(outs[pat], overrides, stride, pat, seq)
        res["frames"] += r["frames"]
        res["render_cpu_s"] += r["render_cpu_s"]
        res["render_wall_s"] += r["render_wall_s"]
        res["paths"] += r["paths"]
    return res


def noise_only(outs: dict, overrides: list[str], stride: int) -> None:
    from room_pipeline.config.compose import compose
    from room_pipeline.stages import noise as noise_stage

    for (pat, seq) in SEQS:
        cfg = compose([f"output_dir={outs[pat]}", f"render.frame_stride={stride}", "render.modalities=[rgb]",
                       "execution.workers=1", *overrides])
        shutil.rmtree(outs[pat] / pat / seq / "rgb_noisy", ignore_errors=True)
        noise_stage.run(cfg, f"{pat}/{seq}")


def prepare_all(inputs: Path, scratch: Path) -> dict:
    """Copy the anatomy + simulation of both sequences (never the frames) into the scratch output_dir."""
    from room_pipeline.paths import PatientPaths

    out = scratch / "synth_out"
    outs = {}
    for (pat, seq) in SEQS:
        for path_of in (lambda pp: pp.mesh, lambda pp: pp.centreline_graph, lambda pp: pp.seq(seq).simulation):
            src, dst = path_of(PatientPaths(inputs, pat)), path_of(PatientPaths(out, pat))
            if not src.exists():
                sys.exit(f"realism_refit.py: {src} missing: run `room run --until simulate output_dir={inputs}` first")
            if not dst.exists() or dst.stat().st_mtime < src.stat().st_mtime:
                dst.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(src, dst)
        outs[pat] = out
    return outs


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--inputs", default=str(ROOT / "data" / "output"))
    ap.add_argument("--scratch", default="/tmp/room_realism_refit")
    ap.add_argument("--stride", type=int, default=20)
    ap.add_argument("--glare", default="0,0.05,0.12")
    ap.add_argument("--beta", default="0.8,1.0,1.2")
    ap.add_argument("--steps", type=int, default=3)
    ap.add_argument("--fresh", action="store_true", help="re-render every glare (default: reuse the rows a previous "
                    "run left in --scratch for the same glare and betas)")
    ap.add_argument("--heldout-all", action="store_true", help="score every grid point on the held-out frames too "
                    "(default: the chosen one only; the held-out scores never enter the choice)")
    ap.add_argument("--from-run", default=None, metavar="OUTPUT_DIR",
                    help="render nothing: judge every rgb_noisy frame of OUTPUT_DIR/patient_*/sequence_* (a full default "
                         "run) against the fit and held-out frames, with per-frame clipping (realism_refit_run.{json,md})")
    ap.add_argument("--out", default="realism_refit", help="the fit's result files: benchmarks/results/OUT.{json,md}")
    ap.add_argument("--tag", default="", help="--from-run: write realism_refit_run_TAG.{json,md}")
    ap.add_argument("--no-ours", action="store_true", help="--from-run: the shared judges only (skip `room realism`)")
    ap.add_argument("--check", action="store_true", help="score the composed config (+ overrides) only, no fit")
    ap.add_argument("overrides", nargs="*")
    a = ap.parse_args()
    import realism as RB
    from room_pipeline import realism as R
    from room_pipeline.config.compose import compose
    from room_pipeline.render.shading import LUMINANCE

    scratch = Path(a.scratch)
    scratch.mkdir(parents=True, exist_ok=True)
    real = real_split(scratch)
    if a.from_run:
        from_run(Path(a.from_run), scratch, real, a.tag, not a.no_ours)
        return
    outs = prepare_all(Path(a.inputs), scratch)
    env = {"load_avg_start": os.getloadavg()[0], "cores": os.cpu_count()}
    c_start = time.process_time()
    RESULTS.mkdir(parents=True, exist_ok=True)

    if a.check:
        cfg = compose(a.overrides)
        r = render_both(outs, a.overrides, a.stride)
        synth, _ = collect(list(set(outs.values())), scratch / "synth_check")
        res = {"overrides": a.overrides, "stride": a.stride, "frames": r["frames"],
               "render_cpu_s_per_frame": round(r["render_cpu_s"] / r["frames"], 3),
               "appearance": {"base_color": list(cfg.render.base_color), "target": cfg.render.auto_exposure_target,
                              "glare": cfg.render.veiling_glare, "beta": cfg.noise.beta,
                              "indirect_bounces": cfg.render.indirect_bounces},
               "clipping": R.sequence_metrics(r["paths"])}
        for k in ("fit", "heldout", "heldout_brea"):
            j = judge(real[k], synth)
            res[k] = {**summary(j), "clipped": j["realism_check"].get("synth", {}).get("clipped_fraction"), "raw": j}
            print(k, json.dumps(res[k]["raw"]["realism_check"]), res[k]["lsd_db"], flush=True)
        res["env"] = {**env, "load_avg_end": os.getloadavg()[0], "cpu_s": round(time.process_time() - c_start, 1)}
        (RESULTS / "realism_refit_check.json").write_text(json.dumps(res, indent=1, default=str))
        md = ["# Realism of the composed config against the fit and held-out real frames", "",
              f"`python benchmarks/realism_refit.py --check --stride {a.stride} {' '.join(a.overrides)}`: every "
              f"{a.stride}th pose of both default sequences ({r['frames']} frames), render + noise stages; judged by "
              "`../shared/tools/realism_check.py` and `noise_psd_check.py`. Fit = the 45 BREA-Depth frames with "
              "index % 4 != 3; held out = the other 15 + the 4 Lung-Odometry frames.", "",
              f"Appearance: {res['appearance']}; render {res['render_cpu_s_per_frame']} CPU s/frame (RGB only).", "",
              "| real set | frames | dE76 | L* EMD | noise LSD dB |", "|---|---|---|---|---|"]
        for k in ("fit", "heldout", "heldout_brea"):
            s = res[k]
            md.append(f"| {k} | {len(list(real[k].iterdir()))} | {s['dE76']:.2f} | {s['L_emd']:.2f} | {s['lsd_db']:.2f} |")
        c = res["clipping"]
        md += ["", f"Clipped (a channel >= 250), noisy RGB of the sample: mean {100 * c['rgb_clipped_fraction_mean']:.3f} %, "
                   f"worst frame {100 * c['rgb_clipped_fraction_max']:.3f} %; dark mean {100 * c['rgb_dark_fraction_mean']:.3f} %.",
               f"Load average {env['load_avg_start']:.1f} -> {res['env']['load_avg_end']:.1f}; {res['env']['cpu_s']} CPU s."]
        (RESULTS / "realism_refit_check.md").write_text("\n".join(md) + "\n")
        print("\n".join(md))
        return

    cfg = compose(a.overrides)
    fit_paths = sorted(real["fit"].iterdir())
    real_lab = R.set_stats(R.load(fit_paths, 256))["lab_mean"]
    base0 = np.array(cfg.render.base_color, dtype=np.float64)
    target0 = float(cfg.render.auto_exposure_target)
    rows = []
    betas = [float(x) for x in a.beta.split(",")]
    for g in [float(x) for x in a.glare.split(",")]:
        done = [scratch / f"row_g{g}_b{b}.json" for b in betas]
        if all(q.exists() for q in done) and not a.fresh:     # resume: this glare's rows were scored before
            rows += [json.loads(q.read_text()) for q in done]
            print(f"glare {g}: rows reused from {scratch}", flush=True)
            continue
        base, target, steps = base0.copy(), target0, []
        for it in range(a.steps):
            ov = [*a.overrides, f"render.veiling_glare={g}", f"render.base_color=[{','.join(f'{x:.4f}' for x in base)}]",
                  f"render.auto_exposure_target={target:.4f}"]
            r = render_both(outs, ov, a.stride)
            s = R.set_stats(R.load(r["paths"], 256))
            steps.append({"step": it, "base_color": base.round(4).tolist(), "target": round(target, 4),
                          "synth_lab": [round(float(x), 2) for x in s["lab_mean"]],
                          "cpu_s_per_frame": round(r["render_cpu_s"] / r["frames"], 3)})
            print(json.dumps({"glare": g, **steps[-1]}), flush=True)
            if it == a.steps - 1:
                break
            lr, ls = RB.lab_to_linear(real_lab), RB.lab_to_linear(s["lab_mean"])
            ratio = (lr / ls) / (float(LUMINANCE @ lr) / float(LUMINANCE @ ls))
            base = base * ratio ** 0.5
            base = base / max(1.0, base.max() / 0.95)
            target = float(np.clip(target * (float(LUMINANCE @ lr) / float(LUMINANCE @ ls)) ** 0.8, 0.05, 0.95))
        for b in betas:
            noise_only(outs, [*ov, f"noise.beta={b}"], a.stride)
            synth, paths = collect(list(set(outs.values())), scratch / f"synth_g{g}_b{b}")
            # keep this point's frames: copy the links' targets (the next render overwrites them)
            keep = scratch / f"frames_g{g}_b{b}"
            shutil.rmtree(keep, ignore_errors=True)
            keep.mkdir(parents=True)
            for p in synth.iterdir():
                q = keep / p.name
                shutil.copy2(p.resolve(), q)
            shutil.rmtree(synth)
            j = judge(real["fit"], keep)
            clip = R.sequence_metrics(sorted(keep.glob("*.png")))
            row = {"glare": g, "beta": b, "base_color": base.round(3).tolist(), "target": round(target, 3),
                   "steps": steps, "fit": summary(j), "clipped_mean": clip["rgb_clipped_fraction_mean"],
                   "clipped_max": clip["rgb_clipped_fraction_max"], "frames_dir": str(keep)}
            row["fit_margin"] = max(row["fit"][k] / BOUNDS[k] for k in BOUNDS)
            rows.append(row)
            (scratch / f"row_g{g}_b{b}.json").write_text(json.dumps(row, indent=1))
            print(json.dumps({k: v for k, v in row.items() if k != "steps"}), flush=True)
    best = min(rows, key=lambda r: r["fit_margin"])
    # held-out scores: the chosen point (and --heldout-all: every point); the choice above saw only the fit frames
    for r in rows if a.heldout_all else [best]:
        keep = Path(r["frames_dir"])
        r["heldout"] = summary(judge(real["heldout"], keep))
        r["heldout_brea"] = summary(judge(real["heldout_brea"], keep))
    res = {"overrides": a.overrides, "stride": a.stride, "fit_frames": [p.name for p in fit_paths],
           "heldout_frames": [p.name for p in sorted(real["heldout"].iterdir())], "rows": rows,
           "chosen": {k: best[k] for k in ("glare", "beta", "base_color", "target")},
           "env": {**env, "load_avg_end": os.getloadavg()[0], "cpu_s": round(time.process_time() - c_start, 1)}}
    (RESULTS / f"{a.out}.json").write_text(json.dumps(res, indent=1, default=str))
    md = ["# Appearance refit with the composed renderer: colour, exposure target, veiling glare, noise amplitude", "",
          f"`python benchmarks/realism_refit.py --inputs {a.inputs} --steps {a.steps} --stride {a.stride} --glare {a.glare} "
          f"--beta {a.beta}{'' if a.out == 'realism_refit' else ' --out ' + a.out} "
          f"{' '.join(a.overrides)}`: every {a.stride}th pose of both default sequences, render + noise stages. "
          "Fit = the 45 BREA-Depth frames with index % 4 != 3 (what the noise profile was measured on too); held out = "
          "the other 15 + the 4 Lung-Odometry frames (19). Judges: `../shared/tools/realism_check.py`, "
          "`../shared/tools/noise_psd_check.py`. Each glare: " + str(a.steps) + " renders of the damped fixed point of base "
          "colour and exposure target on the fit frames (the last one is scored). Chosen by the smallest worst margin max(dE76/6, L* EMD/6, LSD/1.5) **on the fit "
          "frames**; the held-out columns (the chosen point only, unless `--heldout-all`) were not used for the choice.", "",
          "| glare | beta | base_color | target | fit dE76 | fit L* EMD | fit LSD dB | held-out dE76 | held-out L* EMD | "
          "held-out LSD dB | held-out BREA only dE76 / EMD / LSD | clipped mean / worst |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        f = r["fit"]
        mark = " **(chosen)**" if r is best else ""
        if "heldout" in r:
            h, hb = r["heldout"], r["heldout_brea"]
            held = (f"{h['dE76']:.2f} | {h['L_emd']:.2f} | {h['lsd_db']:.2f} | "
                    f"{hb['dE76']:.2f} / {hb['L_emd']:.2f} / {hb['lsd_db']:.2f}")
        else:
            held = "- | - | - | -"
        md.append(f"| {r['glare']}{mark} | {r['beta']} | {r['base_color']} | {r['target']} | {f['dE76']:.2f} | "
                  f"{f['L_emd']:.2f} | {f['lsd_db']:.2f} | {held} | "
                  f"{100 * r['clipped_mean']:.3f} % / {100 * r['clipped_max']:.3f} % |")
    md += ["", f"Load average {env['load_avg_start']:.1f} -> {res['env']['load_avg_end']:.1f}; {res['env']['cpu_s']} CPU s "
               "in this process (the judges run in subprocesses)."]
    (RESULTS / f"{a.out}.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


def from_run(run: Path, scratch: Path, real: dict, tag: str = "", ours: bool = True) -> None:
    """Every noisy frame of a finished run, judged by the shared tools and by ``room realism``
    (:func:`room_pipeline.realism.evaluate` on every frame, ``ours``); clipping per sequence and frame.
    Results: ``realism_refit_run{_tag}.{json,md}``."""
    from room_pipeline import realism as R

    env = {"load_avg_start": os.getloadavg()[0], "cores": os.cpu_count()}
    c0 = time.process_time()
    seqs = sorted(d for d in run.glob("patient_*/sequence_*") if (d / "rgb_noisy").is_dir())
    if not seqs:
        sys.exit(f"realism_refit.py: no patient_*/sequence_*/rgb_noisy under {run}")
    dst = scratch / "run_frames"
    shutil.rmtree(dst, ignore_errors=True)
    dst.mkdir(parents=True)
    per_seq = []
    for d in seqs:
        ps = sorted((d / "rgb_noisy").glob("frame_*.png"))
        m = R.sequence_metrics(ps)
        per_seq.append({"sequence": f"{d.parent.name}/{d.name}", "frames": len(ps), **m})
        for p in ps:
            (dst / f"{d.parent.name}_{d.name}_{p.name}").symlink_to(p.resolve())
    n = sum(r["frames"] for r in per_seq)
    res = {"run": str(run), "per_sequence": per_seq, "frames": n,
           "clipped_mean": sum(r["rgb_clipped_fraction_mean"] * r["frames"] for r in per_seq) / n,
           "clipped_max": max(r["rgb_clipped_fraction_max"] for r in per_seq)}
    for k in ("fit", "heldout", "heldout_brea"):
        j = judge(real[k], dst)
        res[k] = {**summary(j), "raw": j}
        print(k, res[k]["dE76"], res[k]["L_emd"], res[k]["lsd_db"], flush=True)
    all_paths = sorted(dst.iterdir())
    for k in (("fit", "heldout") if ours else ()):
        o = R.evaluate(real[k], n=None, synth_paths=all_paths)
        res[f"ours_{k}"] = {"dE76": o["real_vs_synth"]["dE76_mean_colour"], "L_emd": o["real_vs_synth"]["L_hist_emd"],
                            "lsd_db": o["real_vs_synth"]["noise_lsd_db"],
                            "clipped_mean": o["synth"]["clipped_fraction_all_frames"],
                            "clipped_max": o["synth"]["clipped_max_all_frames"], "raw": o}
        print("room realism", k, res[f"ours_{k}"]["dE76"], res[f"ours_{k}"]["L_emd"], res[f"ours_{k}"]["lsd_db"],
              flush=True)
    res["env"] = {**env, "load_avg_end": os.getloadavg()[0], "cpu_s": round(time.process_time() - c0, 1)}
    name = "realism_refit_run" + (f"_{tag}" if tag else "")
    (RESULTS / f"{name}.json").write_text(json.dumps(res, indent=1, default=str))
    cmd = f"python benchmarks/realism_refit.py --from-run {run}" + (f" --tag {tag}" if tag else "")
    md = ["# Every noisy frame of a finished run against the fit and held-out real frames", "",
          f"`{cmd}`: {n} frames ({', '.join(r['sequence'] for r in per_seq)}), "
          "as the run wrote them; judged by `../shared/tools/realism_check.py` (all frames, 256 px) and "
          "`noise_psd_check.py`; clipped = a channel >= 250 (the shared tool's rule) at full resolution.", "",
          "| sequence | frames | clipped mean | clipped worst frame | dark mean |", "|---|---|---|---|---|"]
    for r in per_seq:
        md.append(f"| {r['sequence']} | {r['frames']} | {100 * r['rgb_clipped_fraction_mean']:.3f} % | "
                  f"{100 * r['rgb_clipped_fraction_max']:.3f} % | {100 * r['rgb_dark_fraction_mean']:.3f} % |")
    md += [f"| all | {n} | {100 * res['clipped_mean']:.3f} % | {100 * res['clipped_max']:.3f} % | |", "",
           "| real set | frames | dE76 | L* EMD | noise LSD dB |", "|---|---|---|---|---|"]
    for k in ("fit", "heldout", "heldout_brea"):
        md.append(f"| {k} | {len(list(real[k].iterdir()))} | {res[k]['dE76']:.2f} | {res[k]['L_emd']:.2f} | "
                  f"{res[k]['lsd_db']:.2f} |")
    if ours:
        md += ["", "The project's own judge (`room realism`, `room_pipeline.realism.evaluate`, every frame, 256 px; noise "
               "spectrum at 600 px; clipped over every frame at 256 px):", "",
               "| real set | dE76 | L* EMD | noise LSD dB | clipped mean / worst frame | real vs real (halves) dE76 / EMD / LSD |",
               "|---|---|---|---|---|---|"]
        for k in ("fit", "heldout"):
            o = res[f"ours_{k}"]
            rr = o["raw"].get("real_vs_real", {})
            md.append(f"| {k} | {o['dE76']:.2f} | {o['L_emd']:.2f} | {o['lsd_db']:.2f} | {100 * o['clipped_mean']:.3f} % / "
                      f"{100 * o['clipped_max']:.3f} % | {rr.get('dE76_mean_colour', float('nan')):.2f} / "
                      f"{rr.get('L_hist_emd', float('nan')):.2f} / {rr.get('noise_lsd_db', float('nan')):.2f} |")
    md += ["", f"Load average {env['load_avg_start']:.1f} -> {res['env']['load_avg_end']:.1f}; "
           f"{res['env']['cpu_s']} CPU s in this process (the shared tools run in subprocesses)."]
    (RESULTS / f"{name}.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
