#!/usr/bin/env python3
"""Cycles at full resolution against a 1024-sample reference, the fast renderer against the same
reference, and memory over a 500-frame Cycles sequence.

    .venv/bin/python benchmarks/cycles_reference.py [--inputs DIR] [--res 600] [--ref-spp 1024]
                                                      [--views 1] [--mem-frames 500] [--quick]

Inputs: a patient folder with ``anatomy/lung_model.obj`` and ``sequence_000/metadata/trajectory.json``
(default ``data/output/patient_000``, written by ``dvc repro``).

1. Reference: two independent renders of ``ref_spp / 2`` samples each (no adaptive sampling, no
   denoiser, seeds 1000/1001), averaged in linear radiance = one ``ref_spp`` reference.  Half
   the mean squared difference of the two halves estimates the variance of one half, so the
   reference's own noise is ``MSE_ref = MSE(a, b) / 4`` and PSNR* (vs the noise-free image) of a
   candidate is ``10 log10(1 / (MSE - MSE_ref))``.
2. Candidates at the same exposure (fixed, from the fast renderer's automatic rule on the view):
   Cycles presets (samples x OpenImageDenoise) and the fast Open3D renderer's shaded RGB.  PSNR,
   PSNR*, SSIM of the 8-bit sRGB images; seconds per frame (Blender's render call, scene already
   built; the first frame of a renderer includes BVH build and is reported separately).
3. Memory: the default Cycles preset's renderer (RGB only, as the render stage uses it) over
   ``--mem-frames`` frames at ``--res`` with 1 sample (memory does not depend on the sample count):
   RSS / peak RSS after 10, 50, 100, 250, 500 frames.

Results: benchmarks/results/cycles_reference.{json,md}.  No GPU is used (``device`` CPU).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
RESULTS = ROOT / "benchmarks" / "results"


def rss_mib() -> tuple[float, float]:
    """(VmRSS, VmHWM) of this process, MiB."""
    vals = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(("VmRSS:", "VmHWM:")):
            k, v = line.split(":")
            vals[k] = int(v.split()[0]) / 1024
    return vals.get("VmRSS", float("nan")), vals.get("VmHWM", float("nan"))


def psnr(mse: float) -> float:
    return float(10 * np.log10(1.0 / mse)) if mse > 0 else float("inf")


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

    return float(structural_similarity(a, b, channel_axis=-1, data_range=1.0))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--inputs", default=str(ROOT / "data" / "output" / "patient_000"))
    ap.add_argument("--res", type=int, default=600)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--views", type=int, default=1)
    ap.add_argument("--mem-frames", type=int, default=500)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--skip-quality", action="store_true")
    ap.add_argument("--quick", action="store_true", help="tiny sizes: check that the script runs")
    args = ap.parse_args()
    if args.quick:
        args.res, args.ref_spp, args.mem_frames = 64, 16, 12

    # bpy first (pymeshlab is never imported here)
    from room_pipeline.render.blender import CyclesRenderer, CyclesSettings, linear_to_srgb8
    from room_pipeline.io.mesh import read_obj
    from room_pipeline.render.camera import CameraIntrinsics
    from room_pipeline.render.raycast import RaycastRenderer
    from room_pipeline.render.scene import Film, Scene, TissueMaterial
    from room_pipeline.stages.render import RenderParams

    pdir = Path(args.inputs)
    traj_path = pdir / "sequence_000" / "metadata" / "trajectory.json"
    if not traj_path.exists():
        raise SystemExit(f"{traj_path} missing: run `dvc repro` (or pass --inputs)")
    mesh = read_obj(pdir / "anatomy" / "lung_model.obj")
    poses_all = np.array([f["pose"] for f in json.loads(traj_path.read_text())["frames"]])
    rp = RenderParams()   # the product's default material, light and Cycles preset
    material = TissueMaterial(base_color=tuple(rp.base_color), roughness=rp.roughness, specular=rp.specular)
    from room_pipeline.render.scene import TipLight

    light = TipLight(power_w=rp.light_power_w, radius_m=rp.light_radius_mm * 1e-3)
    cam = CameraIntrinsics.from_fov(args.res, args.res, rp.fov_deg, rp.near_mm * 1e-3, rp.far_mm * 1e-3)
    base = dict(threads=args.threads)
    doc: dict = {"machine": {"nproc": os.cpu_count(), "cpu_threads": args.threads, "platform": platform.platform(),
                             "python": platform.python_version(), "load_avg_at_start": os.getloadavg(), "gpu": "none"},
                 "inputs": str(pdir), "args": vars(args),
                 "material": dataclasses.asdict(material), "light": dataclasses.asdict(light)}
    t0 = time.perf_counter()

    def scene(poses, ev=None) -> Scene:
        return Scene(mesh, cam, poses, np.arange(len(poses)) * 0.1, material=material, light=light,
                     film=Film(exposure_ev=ev, auto_target=rp.auto_exposure_target))

    rows = []
    if not args.skip_quality:
        views = [int(round(x)) for x in np.linspace(0.4, 0.7, args.views) * (len(poses_all) - 1)]
        for v in views:
            poses = poses_all[[v]]
            ev = RaycastRenderer(scene(poses)).exposure_ev        # the product's automatic exposure rule
            sc = scene(poses, ev)
            halves = []
            for seed in (1000, 1001):
                st = CyclesSettings(samples=args.ref_spp // 2, adaptive_threshold=0.0, denoise=False, seed=seed,
                                    exposure=ev, **base)
                with CyclesRenderer(sc, st) as r:
                    halves.append(r.render(0, ("rgb",))["rgb"])
                    t_half = r.last_render_s
                print(f"view {v}: reference half ({args.ref_spp // 2} spp, seed {seed}) {t_half:.0f} s", flush=True)
            a8, b8 = (linear_to_srgb8(h).astype(np.float64) / 255 for h in halves)
            ref8 = linear_to_srgb8(0.5 * (halves[0] + halves[1])).astype(np.float64) / 255
            mse_ref = float(np.mean((a8 - b8) ** 2)) / 4
            ref_row = {"view": v, "exposure_ev": ev, "ref_spp": args.ref_spp, "ref_half_time_s": t_half,
                       "ref_psnr_vs_noise_free_db": psnr(mse_ref)}
            print(f"  reference's own PSNR vs noise-free: {ref_row['ref_psnr_vs_noise_free_db']:.1f} dB", flush=True)

            def score(name, img8, seconds, first_s=None, **kw):
                x = img8.astype(np.float64) / 255
                mse = float(np.mean((x - ref8) ** 2))
                row = {"view": v, "method": name, **kw, "time_per_frame_s": seconds, "first_frame_s": first_s,
                       "psnr_db": psnr(mse), "psnr_star_db": psnr(mse - mse_ref) if mse > mse_ref else None,
                       "ssim": ssim(x, ref8)}
                rows.append(row)
                print(f"  {name:34s} {seconds:7.2f} s/frame  PSNR {row['psnr_db']:5.2f} dB  "
                      f"PSNR* {row['psnr_star_db'] or float('nan'):5.2f}  SSIM {row['ssim']:.4f}", flush=True)

            for spp, dn in ((1, True), (2, True), (4, True), (8, True), (16, True), (4, False), (64, False)):
                if args.quick and spp > 4:
                    continue
                st = CyclesSettings(samples=spp, denoise=dn, exposure=ev, **base)
                with CyclesRenderer(scene(poses_all[[v, v + 1]], ev), st) as r:
                    r.render(1, ("rgb",))                      # BVH build + first frame
                    first = r.last_render_s
                    img = r.render(0, ("rgb",))["rgb"]
                    score(f"cycles {spp} spp{' + OIDN' if dn else ''}", linear_to_srgb8(img), r.last_render_s, first,
                          samples=spp, denoise=dn)
            rc = RaycastRenderer(scene(poses_all[[v, v + 1]], ev))
            rc.render(1, ("rgb",))
            ts = time.perf_counter()
            img = rc.render(0, ("rgb",))["rgb"]
            score("fast renderer (Open3D ray cast)", img, time.perf_counter() - ts)
            doc.setdefault("references", []).append(ref_row)
    doc["quality"] = rows

    # ---------------------------------------------------------------- memory over a long sequence
    n = args.mem_frames
    idx = np.arange(n) % len(poses_all)
    mem = {"frames": n, "res": args.res, "settings": "1 spp + OIDN, RGB only (the render stage's Cycles use)",
           "rss_before_mib": rss_mib()[0]}
    st = CyclesSettings(samples=1, denoise=True, **base)
    with CyclesRenderer(scene(poses_all[idx]), st) as r:
        mem["rss_after_build_mib"] = rss_mib()[0]
        tm = time.perf_counter()
        marks = {10, 50, 100, 250, 500, n}
        for i in range(n):
            r.render(i, ("rgb",))
            if i + 1 in marks:
                rss, hwm = rss_mib()
                mem[f"after_{i + 1}"] = {"rss_mib": rss, "peak_mib": hwm}
                print(f"memory after {i + 1} frames: RSS {rss:.1f} MiB, peak {hwm:.1f} MiB", flush=True)
        mem["time_per_frame_s"] = (time.perf_counter() - tm) / n
    doc["memory"] = mem
    doc["total_s"] = time.perf_counter() - t0
    doc["machine"]["load_avg_at_end"] = os.getloadavg()
    if args.quick:
        print(json.dumps(doc, indent=1, default=float)[:2000])
        return
    RESULTS.mkdir(parents=True, exist_ok=True)
    old = {}
    if args.skip_quality and (RESULTS / "cycles_reference.json").exists():
        old = json.loads((RESULTS / "cycles_reference.json").read_text())
        doc["quality"], doc["references"] = old.get("quality", []), old.get("references", [])
    (RESULTS / "cycles_reference.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    write_md(doc)


def write_md(d: dict) -> None:
    m = d["machine"]
    L = ["# Cycles vs a 1024-sample reference at full resolution; memory over a long sequence", "",
         f"`python benchmarks/cycles_reference.py` on {m['nproc']} CPU cores shared with other jobs (load average "
         f"{m['load_avg_at_start'][0]:.1f} at start, {m['load_avg_at_end'][0]:.1f} at end: times are upper bounds); "
         f"no GPU on this machine. Inputs: {d['inputs']}. Material/light: the render stage's defaults.", ""]
    for ref in d.get("references", []):
        L += [f"## View {ref['view']} ({d['args']['res']}x{d['args']['res']}, exposure {ref['exposure_ev']:+.2f} EV)", "",
              f"Reference: {ref['ref_spp']} spp (two {ref['ref_spp'] // 2}-spp halves, {ref['ref_half_time_s']:.0f} s each), "
              f"no adaptive sampling, no denoiser; its own PSNR vs the noise-free image: "
              f"{ref['ref_psnr_vs_noise_free_db']:.1f} dB (PSNRs near that are capped by the reference's noise; "
              "PSNR* removes it).", "",
              "| method | s/frame | first frame s (BVH) | PSNR dB | PSNR* dB | SSIM |", "|---|---|---|---|---|---|"]
        for r in d["quality"]:
            if r["view"] != ref["view"]:
                continue
            ps = "" if r["psnr_star_db"] is None else f"{r['psnr_star_db']:.2f}"
            fs = "" if r["first_frame_s"] is None else f"{r['first_frame_s']:.2f}"
            L.append(f"| {r['method']} | {r['time_per_frame_s']:.2f} | {fs} | {r['psnr_db']:.2f} | {ps} | {r['ssim']:.4f} |")
        L.append("")
    mem = d["memory"]
    L += [f"## Memory over {mem['frames']} frames ({mem['res']}x{mem['res']}, {mem['settings']})", "",
          f"RSS before the renderer {mem['rss_before_mib']:.0f} MiB, after building it {mem['rss_after_build_mib']:.0f} MiB; "
          f"{mem['time_per_frame_s']:.2f} s/frame.", "", "| frames | RSS (MiB) | peak RSS (MiB) |", "|---|---|---|"]
    for k, v in mem.items():
        if k.startswith("after_") and k != "after_build":
            L.append(f"| {k.split('_')[1]} | {v['rss_mib']:.1f} | {v['peak_mib']:.1f} |")
    (RESULTS / "cycles_reference.md").write_text("\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
