#!/usr/bin/env python3
"""Blender Cycles backend: samples x denoiser vs time and PSNR/SSIM, shadow rays, memory, realism.

Inputs: a patient folder holding ``anatomy/lung_model.obj`` and
``sequence_000/metadata/trajectory.json`` (``--inputs``).  Without it the
benchmark makes its own through the pipeline, in a subprocess (pymeshlab must
not share the bpy process): ``room run --until trajectory
output_dir=benchmarks/.cache/cycles_quality`` (cached).

Sections (each prints as it goes; results in benchmarks/results/cycles_quality.{json,md}
and a contact sheet cycles_quality_realism.png):

1. quality: for ``--views`` frames of the trajectory at ``--res``, a
   reference of ``--ref-spp`` samples (no adaptive sampling, no denoiser)
   and, for each spp in ``--spp`` with the denoiser off/on (adaptive
   threshold 0.01), the time per frame (Blender's render call incl. scene
   sync/BVH and the EXR write: one render per setting) and PSNR/SSIM of the 8-bit sRGB image vs the
   reference's (same exposure).  The reference's own noise is estimated from
   two independent renders (``ref_psnr_estimate``).
2. timing of presets at ``--timing-res`` (600x600 default).
3. shadow rays on/off for the tip light: PSNR between them vs the
   seed-to-seed noise floor, and the time.
4. memory: VmRSS / VmHWM after N = 10, 50, 100 frames (all passes) at ``--mem-res``.
5. realism: default renders vs the real frames in
   ../shared/data/bronchoscopy_frames/brea_depth/*.jpg (read in place):
   Lab mean/std per channel and the radial brightness (L*) profile; the
   base colour is then tuned toward the real frames (two multiplicative
   steps on the mean linear colour) and the numbers are reported before/after.

    python benchmarks/cycles_quality.py [--inputs DIR] [--res 300] [--ref-spp 256] [--quick]
"""
from __future__ import annotations

import argparse
import dataclasses
import glob
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
CACHE = ROOT / "benchmarks" / ".cache" / "cycles_quality"
REAL = Path(os.environ.get("ROOM_SHARED_DATA", ROOT.parent / "shared" / "data")) / "bronchoscopy_frames" / "brea_depth"


def ensure_inputs(inputs: str | None) -> Path:
    if inputs:
        return Path(inputs)
    from room_pipeline.paths import PatientPaths

    pdir = CACHE / "patient_000"
    if not PatientPaths(CACHE, "patient_000").mesh.exists():
        print(f"making inputs in {CACHE} (room run --until trajectory, subprocess) ...", flush=True)
        room = Path(sys.executable).parent / "room"
        subprocess.run([str(room), "run", "--until", "trajectory", f"output_dir={CACHE}"], check=True, cwd=ROOT)
    return pdir


def rss_kib() -> tuple[int, int]:
    """(VmRSS, VmHWM) of this process in KiB."""
    vals = {}
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(("VmRSS:", "VmHWM:")):
                k, v = line.split(":")
                vals[k] = int(v.split()[0])
    return vals["VmRSS"], vals["VmHWM"]


def srgb(lin: np.ndarray) -> np.ndarray:
    from room_pipeline.render.blender import linear_to_srgb8

    return linear_to_srgb8(lin).astype(np.float64) / 255.0


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a - b) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

    return float(structural_similarity(a, b, channel_axis=-1, data_range=1.0))


def lab_stats(imgs_srgb: list[np.ndarray], mask_dark: bool = False) -> dict:
    """Per-channel mean/std in CIE Lab (cv2, D65; L in [0, 100]) over all pixels of all images."""
    import cv2

    labs = np.concatenate([cv2.cvtColor(im.astype(np.float32), cv2.COLOR_RGB2Lab).reshape(-1, 3) for im in imgs_srgb])
    return {"L_mean": float(labs[:, 0].mean()), "L_std": float(labs[:, 0].std()),
            "a_mean": float(labs[:, 1].mean()), "a_std": float(labs[:, 1].std()),
            "b_mean": float(labs[:, 2].mean()), "b_std": float(labs[:, 2].std())}


def radial_profile(imgs_srgb: list[np.ndarray], bins: int = 10, about_lumen: bool = False) -> list[float]:
    """Mean L* in rings of normalised radius r / (W/2) in [0, 1] (the inscribed circle size).

    Centre: the image centre, or with ``about_lumen`` the lumen centre of each
    image (centroid of the darkest 3 % of pixels after a Gaussian blur of
    W/20), so the fall-off from the lumen outward is compared even when the
    lumen is off-centre.
    """
    import cv2

    out = np.zeros(bins)
    cnt = np.zeros(bins)
    h, w = imgs_srgb[0].shape[:2]
    v, u = np.mgrid[0:h, 0:w]
    for im in imgs_srgb:
        L = cv2.cvtColor(im.astype(np.float32), cv2.COLOR_RGB2Lab)[..., 0]
        cu, cv = (w - 1) / 2, (h - 1) / 2
        if about_lumen:
            Lb = cv2.GaussianBlur(L, (0, 0), w / 20)
            dark = Lb <= np.percentile(Lb, 3)
            cu, cv = u[dark].mean(), v[dark].mean()
        r = np.hypot(u - cu, v - cv) / (min(h, w) / 2)
        ring = (r * bins).astype(int)
        m = ring < bins
        s = np.bincount(ring[m], weights=L[m], minlength=bins)
        n = np.bincount(ring[m], minlength=bins)
        out += np.where(n > 0, s / np.maximum(n, 1), 0.0)
        cnt += n > 0
    return (out / np.maximum(cnt, 1)).tolist()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--inputs", help="patient folder with anatomy/lung_model.obj and sequence_000/metadata/trajectory.json")
    ap.add_argument("--res", type=int, default=300, help="resolution of the quality table (square)")
    ap.add_argument("--ref-spp", type=int, default=256)
    ap.add_argument("--spp", default="4,16,64")
    ap.add_argument("--views", type=int, default=2)
    ap.add_argument("--timing-res", type=int, default=600)
    ap.add_argument("--mem-res", type=int, default=64)
    ap.add_argument("--realism-res", type=int, default=150)
    ap.add_argument("--realism-views", type=int, default=6)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="tiny sizes, to check the script runs")
    args = ap.parse_args()
    if args.quick:
        args.res, args.ref_spp, args.spp, args.views, args.timing_res = 64, 16, "4", 1, 96
        args.realism_res, args.realism_views = 48, 2

    # bpy before anything that might pull pymeshlab (nothing here does; the inputs come from a subprocess)
    from room_pipeline.render.blender import CyclesRenderer, CyclesSettings
    from room_pipeline.io.mesh import read_obj
    from room_pipeline.render.camera import CameraIntrinsics
    from room_pipeline.render.scene import Film, Scene, TissueMaterial
    from room_pipeline.render.shading import auto_exposure_ev

    pdir = ensure_inputs(args.inputs)
    from room_pipeline.paths import PatientPaths

    pp = PatientPaths(pdir.parent, pdir.name)
    mesh = read_obj(pp.mesh)
    traj = json.loads(pp.seq("sequence_000").trajectory.read_text())
    all_poses = np.array([f["pose"] for f in traj["frames"]])
    T = len(all_poses)
    print(f"inputs {pdir}: {mesh.n_faces} faces, {T} poses", flush=True)
    base = dict(threads=args.threads)
    t_start = time.perf_counter()

    def scene_at(res, idx, material=TissueMaterial(), film=Film()):
        cam = CameraIntrinsics.from_fov(res, res, 85.0)
        poses = all_poses[list(idx)]
        return Scene(mesh, cam, poses, np.arange(len(poses)) * 0.1, material=material, film=film)

    def render_rgb(sc, st, i=0, repeat=1):
        with CyclesRenderer(sc, st) as r:
            for _ in range(repeat):
                out = r.render(i, ("rgb",))
            return out["rgb"], r.last_render_s

    res_doc: dict = {"machine": {"cpu_threads": args.threads, "nproc": os.cpu_count(), "platform": platform.platform(),
                                 "load_avg_at_start": os.getloadavg()},
                     "inputs": str(pdir), "args": vars(args)}

    # ---------------------------------------------------------------- 1. quality table
    view_idx = [int(round(x)) for x in np.linspace(0.15, 0.75, args.views) * (T - 1)]
    spps = [int(s) for s in args.spp.split(",")]
    rows = []
    for v in view_idx:
        sc = scene_at(args.res, [v])
        ref_st = CyclesSettings(samples=args.ref_spp, adaptive_threshold=0.0, denoise=False, seed=1000, exposure=0.0, **base)
        ref_lin, ref_t = render_rgb(sc, ref_st)
        ev = auto_exposure_ev(ref_lin, ref_lin.sum(-1) > 0, Film())
        ref = srgb(ref_lin * 2 ** ev)
        print(f"view {v}: reference {args.ref_spp} spp {ref_t:.1f} s, EV {ev:+.2f}", flush=True)
        pair = {}
        for spp in spps:
            for dn in (False, True):
                st = CyclesSettings(samples=spp, denoise=dn, exposure=ev, **base)
                lin, t = render_rgb(sc, st)
                img = srgb(lin)
                rows.append({"view": v, "spp": spp, "denoise": dn, "time_s": t, "psnr_db": psnr(img, ref),
                             "ssim": ssim(img, ref)})
                print(f"  {spp:4d} spp denoise {'on ' if dn else 'off'}  {t:6.2f} s  PSNR {rows[-1]['psnr_db']:5.2f} dB"
                      f"  SSIM {rows[-1]['ssim']:.4f}", flush=True)
                if not dn and spp == spps[-1]:
                    pair["a"] = img
        # reference noise: two independent renders of spps[-1] samples (no adaptive) -> MSE of one ref
        st = CyclesSettings(samples=spps[-1], adaptive_threshold=0.0, denoise=False, seed=1, exposure=ev, **base)
        a = srgb(render_rgb(sc, st)[0])
        b = srgb(render_rgb(sc, dataclasses.replace(st, seed=2))[0])
        mse_one = float(np.mean((a - b) ** 2)) / 2 * spps[-1] / args.ref_spp
        res_doc.setdefault("ref_psnr_estimate_db", {})[str(v)] = 10 * np.log10(1 / mse_one) if mse_one > 0 else None
        print(f"  reference's own PSNR (estimated from two {spps[-1]}-spp renders): "
              f"{res_doc['ref_psnr_estimate_db'][str(v)]:.1f} dB", flush=True)
    res_doc["quality"] = rows

    # ---------------------------------------------------------------- 2. timing at 600x600
    presets = {"4 spp, 1 bounce, OIDN": dict(samples=4, max_bounces=1, denoise=True),
               "4 spp, 3 bounces, OIDN (recommended default)": dict(samples=4, max_bounces=3, denoise=True),
               "16 spp, 3 bounces, OIDN": dict(samples=16, max_bounces=3, denoise=True),
               "16 spp, 3 bounces, no denoiser": dict(samples=16, max_bounces=3, denoise=False)}
    if args.quick:
        presets = dict(list(presets.items())[:1])
    timing = []
    sc = scene_at(args.timing_res, view_idx[:1] + [view_idx[0] + 1])
    for name, kw in presets.items():
        with CyclesRenderer(sc, CyclesSettings(exposure=0.0, **base, **kw)) as r:
            r.render(0, ("rgb",))
            t_first = r.last_render_s
            r.render(1, ("rgb", "depth", "normals", "flow"))
            timing.append({"preset": name, "settings": kw, "res": args.timing_res, "first_frame_s": t_first,
                           "next_frame_s": r.last_render_s})
        print(f"timing {args.timing_res}px {name}: first {t_first:.2f} s, next (all passes) {r.last_render_s:.2f} s",
              flush=True)
    res_doc["timing"] = timing

    # ---------------------------------------------------------------- 3. shadow rays
    sc = scene_at(args.res, view_idx[:1])
    sh, times = {}, {False: [], True: []}
    for rep in range(3):  # alternate on/off, 3 times each: the cores are shared, take the minimum
        for cast in (False, True):
            for seed in ((0, 1) if rep == 0 else (0,)):
                st = CyclesSettings(samples=spps[-1], adaptive_threshold=0.0, denoise=False, cast_shadows=cast,
                                    seed=seed, exposure=0.0, **base)
                lin, t = render_rgb(sc, st)
                sh[(cast, seed)] = (lin, t)
                times[cast].append(t)
    ev = auto_exposure_ev(sh[(False, 0)][0], sh[(False, 0)][0].sum(-1) > 0, Film())
    im = {k: srgb(v[0] * 2 ** ev) for k, v in sh.items()}
    shadow = {"spp": spps[-1], "res": args.res,
              "time_s_off": float(min(times[False])), "time_s_on": float(min(times[True])),
              "times_s_off_all": times[False], "times_s_on_all": times[True],
              "psnr_on_vs_off_same_seed_db": psnr(im[(True, 0)], im[(False, 0)]),
              "psnr_on_vs_off_other_seed_db": psnr(im[(True, 1)], im[(False, 0)]),
              "psnr_noise_floor_off_seed0_vs_seed1_db": psnr(im[(False, 1)], im[(False, 0)]),
              "mean_linear_ratio_on_over_off": float(sh[(True, 0)][0].mean() / sh[(False, 0)][0].mean())}
    res_doc["shadow_rays"] = shadow
    print("shadow rays:", json.dumps(shadow), flush=True)

    # ---------------------------------------------------------------- 4. memory over many frames
    n_max = 100
    sc = scene_at(args.mem_res, range(0, min(T, n_max + 1)))
    with open("/proc/self/clear_refs", "w") as fh:  # reset VmHWM: the peak of this section alone
        fh.write("5")
    mem = {"res": args.mem_res, "spp": 1, "modalities": "rgb, depth, normals, flow", "rss_before_kib": rss_kib()[0]}
    with CyclesRenderer(sc, CyclesSettings(samples=1, denoise=False, exposure=0.0, **base)) as r:
        mem["rss_after_build_kib"] = rss_kib()[0]
        t0 = time.perf_counter()
        for i in range(min(n_max, len(sc.poses))):
            r.render(i)
            if i + 1 in (10, 50, 100):
                rss, hwm = rss_kib()
                mem[f"after_{i + 1}"] = {"rss_kib": rss, "peak_kib": hwm}
                print(f"memory after {i + 1} frames: RSS {rss / 1024:.1f} MiB, peak {hwm / 1024:.1f} MiB", flush=True)
        mem["time_per_frame_s"] = (time.perf_counter() - t0) / min(n_max, len(sc.poses))
    res_doc["memory"] = mem

    # ---------------------------------------------------------------- 5. realism
    import cv2

    real_files = sorted(glob.glob(str(REAL / "*.jpg")))
    realism: dict = {"real_frames": len(real_files), "real_dir": str(REAL)}
    if real_files:
        rr = args.realism_res
        real = [cv2.resize(cv2.imread(f)[..., ::-1], (rr, rr), interpolation=cv2.INTER_AREA).astype(np.float64) / 255
                for f in real_files]
        realism["real"] = {"lab": lab_stats(real), "radial_L": radial_profile(real),
                           "radial_L_lumen": radial_profile(real, about_lumen=True)}
        # the real frames' exposure in the Film's terms: the p95 of linear luminance (auto_target would match it)
        lum = [np.percentile((np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
                              @ np.array([0.2126, 0.7152, 0.0722])), 95) for x in real]
        realism["real"]["p95_linear_luminance_mean"] = float(np.mean(lum))
        real_lin_mean = np.mean([np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).reshape(-1, 3).mean(0)
                                 for x in real], axis=0)
        vidx = [int(round(x)) for x in np.linspace(0.05, 0.95, args.realism_views) * (T - 1)]
        rst = CyclesSettings(samples=16, denoise=True, **base)

        def evaluate(material, film=Film()):
            imgs = []
            for v in vidx:
                sc = scene_at(rr, [v], material=material, film=film)  # automatic exposure per view (a scope's AGC)
                with CyclesRenderer(sc, rst) as r:
                    imgs.append(srgb(r.render(0, ("rgb",))["rgb"]))
            lab = lab_stats(imgs)
            prof = radial_profile(imgs)
            prof_l = radial_profile(imgs, about_lumen=True)
            lin_mean = np.mean([np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).reshape(-1, 3).mean(0)
                                for x in imgs], axis=0)
            d = {"material": dataclasses.asdict(material), "film_auto_target": film.auto_target, "lab": lab, "radial_L": prof, "radial_L_lumen": prof_l,
                 "ab_mean_distance": float(np.hypot(lab["a_mean"] - realism["real"]["lab"]["a_mean"],
                                                    lab["b_mean"] - realism["real"]["lab"]["b_mean"])),
                 "radial_L_lumen_rmse": float(np.sqrt(np.mean((np.array(prof_l) - realism["real"]["radial_L_lumen"]) ** 2))),
                 "lab_mean_distance": float(np.linalg.norm([lab[k] - realism["real"]["lab"][k]
                                                            for k in ("L_mean", "a_mean", "b_mean")])),
                 "radial_L_rmse": float(np.sqrt(np.mean((np.array(prof) - realism["real"]["radial_L"]) ** 2)))}
            return d, imgs, lin_mean

        before, imgs_before, lin_mean = evaluate(TissueMaterial())
        print(f"realism before: Lab dist {before['lab_mean_distance']:.1f}, radial RMSE {before['radial_L_rmse']:.1f}",
              flush=True)
        mat = TissueMaterial()
        steps = [before]
        imgs_steps = [imgs_before]
        imgs_after = imgs_before
        for _ in range(3):
            ratio = (real_lin_mean / np.maximum(lin_mean, 1e-6)) ** 0.7  # damped: bounces amplify the albedo's hue
            bc = np.array(mat.base_color) * ratio / ratio.max() * max(mat.base_color) / max(
                (np.array(mat.base_color) * ratio / ratio.max()).max(), 1e-6)
            mat = dataclasses.replace(mat, base_color=tuple(float(round(c, 3)) for c in np.clip(bc, 0.02, 0.95)))
            d, imgs_after, lin_mean = evaluate(mat)
            steps.append(d)
            imgs_steps.append(imgs_after)
            print(f"realism base_color {mat.base_color}: Lab dist {d['lab_mean_distance']:.1f}, "
                  f"a*b* dist {d['ab_mean_distance']:.1f}, lumen-radial RMSE {d['radial_L_lumen_rmse']:.1f}, "
                  f"radial RMSE {d['radial_L_rmse']:.1f}", flush=True)
        best = min(range(len(steps)), key=lambda i: steps[i]["ab_mean_distance"])  # colour; L is the exposure's
        mat = TissueMaterial(**{**steps[best]["material"],
                                "base_color": tuple(steps[best]["material"]["base_color"]),
                                "subsurface_radius_m": tuple(steps[best]["material"]["subsurface_radius_m"])})
        imgs_after = imgs_steps[best]
        # subsurface variant of the tuned colour
        mat_sss = dataclasses.replace(mat, subsurface_weight=0.3)
        d, imgs_sss, _ = evaluate(mat_sss)
        steps.append(d)
        print(f"realism + subsurface 0.3: Lab dist {d['lab_mean_distance']:.1f}, radial RMSE {d['radial_L_rmse']:.1f}",
              flush=True)
        # exposure matched to the real frames: Film.auto_target = the real frames' p95 linear luminance
        tgt = round(realism["real"]["p95_linear_luminance_mean"], 2)
        d, imgs_exp, _ = evaluate(mat, Film(auto_target=tgt))
        steps.append(d)
        print(f"realism tuned colour + Film.auto_target {tgt}: Lab dist {d['lab_mean_distance']:.1f}, "
              f"a*b* dist {d['ab_mean_distance']:.1f}, lumen-radial RMSE {d['radial_L_lumen_rmse']:.1f}, "
              f"radial RMSE {d['radial_L_rmse']:.1f}", flush=True)
        realism["steps"] = steps
        realism["best_step"] = best
        # contact sheet: real | before | after | after + SSS (4 views)
        k = min(4, len(vidx))
        pick_real = [real[int(i)] for i in np.linspace(0, len(real) - 1, k)]
        rows_img = [np.concatenate(row[:k], 1) for row in (pick_real, imgs_before, imgs_after, imgs_exp)]
        sheet = (np.concatenate(rows_img, 0) * 255).round().astype(np.uint8)
        cv2.imwrite(str(RESULTS / "cycles_quality_realism.png"), sheet[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    res_doc["realism"] = realism
    res_doc["total_s"] = time.perf_counter() - t_start
    res_doc["load_avg_at_end"] = os.getloadavg()

    if not args.quick:
        RESULTS.mkdir(parents=True, exist_ok=True)
        (RESULTS / "cycles_quality.json").write_text(json.dumps(res_doc, indent=2, default=float) + "\n")
        write_md(res_doc)
    print(f"done in {res_doc['total_s']:.0f} s", flush=True)


def write_md(d: dict) -> None:
    a = d["args"]
    L = [f"# Blender Cycles quality / speed (CPU, {a['threads']} threads on a shared {d['machine']['nproc']}-core machine)",
         "",
         f"`python benchmarks/cycles_quality.py --inputs {d['inputs']}`; load average at start "
         f"{d['machine']['load_avg_at_start'][0]:.1f}, at end {d['load_avg_at_end'][0]:.1f} (other jobs share the cores: "
         "times are upper bounds).  Total {:.0f} s.".format(d["total_s"]),
         "",
         f"## Samples x denoiser ({a['res']}x{a['res']}, reference {a['ref_spp']} spp, no adaptive, no denoiser)",
         "",
         "PSNR/SSIM of the 8-bit sRGB image vs the reference's (same exposure); adaptive threshold 0.01; "
         "3 bounces; time = Blender's render call incl. scene sync/BVH (about 0.3 s here) and EXR write, one render per cell.",
         "",
         "PSNR* = the PSNR vs the noise-free image, estimated by removing the reference's own noise "
         "(MSE* = MSE - MSE_ref, MSE_ref from two independent renders; blank where MSE_ref >= MSE).",
         "",
         "| view | spp | denoiser | time/frame (s) | PSNR (dB) | PSNR* (dB) | SSIM |", "|---|---|---|---|---|---|---|"]
    for r in d["quality"]:
        ref_db = d["ref_psnr_estimate_db"].get(str(r["view"]))
        mse = 10 ** (-r["psnr_db"] / 10)
        mse_ref = 10 ** (-ref_db / 10) if ref_db else 0.0
        corr = f"{-10 * np.log10(mse - mse_ref):.1f}" if mse > mse_ref else ""
        L.append(f"| {r['view']} | {r['spp']} | {'OIDN' if r['denoise'] else 'off'} | {r['time_s']:.2f} | "
                 f"{r['psnr_db']:.2f} | {corr} | {r['ssim']:.4f} |")
    L += ["", "Reference's own PSNR vs the noise-free image (estimated from two independent renders): " +
          ", ".join(f"view {k}: {v:.1f} dB" for k, v in d["ref_psnr_estimate_db"].items()) +
          " -- PSNRs above that are capped by the reference's noise.", "",
          f"## Presets at {d['timing'][0]['res']}x{d['timing'][0]['res']}", "",
          "| preset | first frame (s, incl. BVH) | next frame, all passes (s) |", "|---|---|---|"]
    for t in d["timing"]:
        L.append(f"| {t['preset']} | {t['first_frame_s']:.2f} | {t['next_frame_s']:.2f} |")
    s = d["shadow_rays"]
    L += ["", f"## Shadow rays for the tip light ({s['res']}x{s['res']}, {s['spp']} spp, no denoiser)", "",
          "| | value |", "|---|---|",
          f"| time off / on (s, min of {len(s['times_s_off_all'])} alternating renders) | {s['time_s_off']:.2f} / {s['time_s_on']:.2f} |",
          f"| PSNR on vs off, same seed (dB) | {s['psnr_on_vs_off_same_seed_db']:.2f} |",
          f"| PSNR on vs off, other seed (dB) | {s['psnr_on_vs_off_other_seed_db']:.2f} |",
          f"| noise floor: off seed 0 vs seed 1 (dB) | {s['psnr_noise_floor_off_seed0_vs_seed1_db']:.2f} |",
          f"| mean linear radiance on / off | {s['mean_linear_ratio_on_over_off']:.4f} |"]
    m = d["memory"]
    L += ["", f"## Memory over a sequence ({m['res']}x{m['res']}, {m['spp']} spp, {m['modalities']})", "",
          f"RSS before the renderer {m['rss_before_kib'] / 1024:.1f} MiB, after building it "
          f"{m['rss_after_build_kib'] / 1024:.1f} MiB; {m['time_per_frame_s']:.3f} s/frame.", "",
          "| frames | RSS (MiB) | peak RSS (MiB) |", "|---|---|---|"]
    for n in (10, 50, 100):
        if f"after_{n}" in m:
            L.append(f"| {n} | {m[f'after_{n}']['rss_kib'] / 1024:.1f} | {m[f'after_{n}']['peak_kib'] / 1024:.1f} |")
    r = d["realism"]
    if "steps" in r:
        L += ["", f"## Realism vs {r['real_frames']} real frames (BREA-Depth, Ambu aScope 4), "
                  f"{a['realism_views']} views, {a['realism_res']}x{a['realism_res']}, 16 spp + OIDN, auto exposure per view",
              "", "Lab: cv2 (D65), L in [0, 100]; radial profile: mean L* in 10 rings of r / (W/2).", "",
              "| material | L mean/std | a mean/std | b mean/std | Lab-mean distance | a*b*-mean distance | radial L RMSE (image centre) "
              "| radial L RMSE (lumen centre) |",
              "|---|---|---|---|---|---|---|---|"]
        rl = r["real"]["lab"]
        L.append(f"| real frames | {rl['L_mean']:.1f} / {rl['L_std']:.1f} | {rl['a_mean']:.1f} / {rl['a_std']:.1f} | "
                 f"{rl['b_mean']:.1f} / {rl['b_std']:.1f} | 0 | 0 | 0 | 0 |")
        for st in r["steps"]:
            mt = st["material"]
            lab = st["lab"]
            name = f"base {tuple(mt['base_color'])}" + (f", SSS {mt['subsurface_weight']}" if mt["subsurface_weight"] else "")
            if st["film_auto_target"] != 0.8:
                name += f", Film.auto_target {st['film_auto_target']}"
            L.append(f"| {name} | {lab['L_mean']:.1f} / {lab['L_std']:.1f} | {lab['a_mean']:.1f} / {lab['a_std']:.1f} | "
                     f"{lab['b_mean']:.1f} / {lab['b_std']:.1f} | {st['lab_mean_distance']:.1f} | {st['ab_mean_distance']:.1f} | {st['radial_L_rmse']:.1f} "
                     f"| {st['radial_L_lumen_rmse']:.1f} |")
        L += ["", "Radial L* profile (centre -> edge):", "",
              "| | " + " | ".join(f"{(i + 0.5) / 10:.2f}" for i in range(10)) + " |", "|---" * 11 + "|",
              "| real | " + " | ".join(f"{x:.0f}" for x in r["real"]["radial_L"]) + " |"]
        for st in r["steps"]:
            L.append(f"| {tuple(st['material']['base_color'])}{' SSS' if st['material']['subsurface_weight'] else ''}"
                     f"{' target ' + str(st['film_auto_target']) if st['film_auto_target'] != 0.8 else ''} | "
                     + " | ".join(f"{x:.0f}" for x in st["radial_L"]) + " |")
        L += ["", "Radial L* profile about the lumen centre (darkest 3 %, blurred):", "",
              "| | " + " | ".join(f"{(i + 0.5) / 10:.2f}" for i in range(10)) + " |", "|---" * 11 + "|",
              "| real | " + " | ".join(f"{x:.0f}" for x in r["real"]["radial_L_lumen"]) + " |"]
        for st in r["steps"]:
            L.append(f"| {tuple(st['material']['base_color'])}{' SSS' if st['material']['subsurface_weight'] else ''}"
                     f"{' target ' + str(st['film_auto_target']) if st['film_auto_target'] != 0.8 else ''} | "
                     + " | ".join(f"{x:.0f}" for x in st["radial_L_lumen"]) + " |")
        L += ["", f"Real frames: mean over frames of the 95th percentile of linear luminance = "
                  f"{r['real']['p95_linear_luminance_mean']:.3f} (the renders use Film.auto_target = 0.8 at that "
                  "percentile: the exposure, not the material, sets their mean L*).",
              f"Best (smallest a*b*-mean distance: colour; L* follows the exposure): step {r['best_step']}."]
        L += ["", "Contact sheet `cycles_quality_realism.png`: rows = real, default material, tuned colour, "
                  "tuned colour + exposure matched (Film.auto_target)."]
    (RESULTS / "cycles_quality.md").write_text("\n".join(L) + "\n")


if __name__ == "__main__":
    main()
