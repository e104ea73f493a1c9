#!/usr/bin/env python3
"""Where the default RGB's whole-frame error against the 1024-spp Cycles reference sits (issue #15).

    python benchmarks/cycles_residual.py --views DIR/patient_000:trachea,bifurcation,distal \
        --views DIR/patient_001:trachea,distal --res 200 --out cycles_residual

The references are ``cycles_reference.py``'s (the same cache, keys and scene: the render stage's default,
lens distortion off, the mesh subdivided twice, 1024 spp in two halves, 8 bounces); missing ones are
rendered (``--make-refs`` renders them and stops; ``--partial-refs`` renders nothing and scores against what
the cache holds: both halves, or the first 512-spp half alone, whose own noise then adds to the MSE in
expectation, so the raw PSNR against it is a conservative estimate and PSNR* is not available).  Every image goes through the same film at the view's
metered exposure (as ``cycles_reference.py``).  Per view, the ray caster's default RGB is split:

* **channels**: PSNR per colour channel;
* **regions**: share of the squared error and PSNR of: the centre disc (radius < half the half-width) vs the
  periphery; the ray caster's depth (near < 10 mm, 10-25 mm, far > 25 mm); **silhouette pixels** (a depth
  discontinuity, :func:`room_pipeline.render.antialias.silhouette_pixels`, or a hit next to no hit: the
  pixel footprint straddles two surfaces);
* **pixel filter**: the same ray caster integrated over each pixel's footprint (``S`` x ``S`` sub-pixel
  samples, ``--ss``, weighted with Cycles' pixel filter: separable Blackman-Harris of width
  ``CyclesSettings.filter_width`` = 1.5 px, in linear radiance) — what one ray through each pixel centre
  leaves out; ``RaycastConfig.edge_samples`` (the filter at the silhouette pixels only);
  ``render.shading_stride`` 1; ``render.direct_shadows`` flipped (a shadow ray per pixel for the direct light);
* **light terms** (``--direct``): a Cycles reference of the direct light alone (0 bounces, ``--direct-spp``)
  against the ray caster's direct term alone (0 bounces), and the product with either term swapped for
  Cycles' (the error left is the other term's);
* the best single gain on the product's linear radiance (2^(k/200), |k| <= 200).

CPU s = ``time.process_time``.  Results: benchmarks/results/<out>.{json,md}.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(ROOT / "benchmarks"))
RESULTS = ROOT / "benchmarks" / "results"


def filter_down(hi: np.ndarray, s: int, width: float) -> np.ndarray:
    """(H*s, W*s, C) sub-pixel samples (odd ``s``: sample ``s p + (s-1)/2`` at pixel centre ``p``) -> (H, W, C)
    weighted with the separable pixel filter of ``width`` px."""
    import cv2

    from room_pipeline.render.antialias import blackman_harris

    r = int(np.floor(width / 2 * s))
    taps = blackman_harris(np.arange(-r, r + 1) / s, width)
    taps = (taps / taps.sum()).astype(np.float32)
    out = cv2.sepFilter2D(hi.astype(np.float32), -1, taps, taps, borderType=cv2.BORDER_REFLECT)
    c = (s - 1) // 2
    return out[c::s, c::s]


def scaled_camera(cam, s: int):
    return dataclasses.replace(cam, width=cam.width * s, height=cam.height * s, fx=cam.fx * s, fy=cam.fy * s,
                               cx=(cam.cx + 0.5) * s - 0.5, cy=(cam.cy + 0.5) * s - 0.5)


def rc_linear(sc, cfg) -> tuple[np.ndarray, np.ndarray, float]:
    """(linear radiance at exposure 0, depth m, CPU s of the render) of the ray caster on one-pose scene ``sc``."""
    from room_pipeline.render.raycast import RaycastRenderer

    sc0 = dataclasses.replace(sc, film=dataclasses.replace(sc.film, exposure_ev=0.0, frame_ev=None))
    r = RaycastRenderer(sc0, cfg)
    r.render(0, ("rgb",))
    r._cache.clear()
    c0 = time.process_time()
    out = r.render(0, ("rgb", "depth"))
    return out["rgb_linear"], out["depth"], time.process_time() - c0


def direct_reference(ref_scene, normals, i: int, name: str, args) -> np.ndarray:
    """Cycles' direct light alone (0 bounces, ``--direct-spp``, no denoiser), linear at exposure 0; cached."""
    from cycles_reference import CACHE, cache_key, reference_transport, view_scene
    from room_pipeline.render.blender import CyclesRenderer, CyclesSettings

    tr = reference_transport(args)
    p = CACHE / f"direct_{name}_{i}_{cache_key(ref_scene, i, args.res, args.direct_spp, 0, tr)}.npy"
    if p.exists():
        return np.load(p)
    p.parent.mkdir(parents=True, exist_ok=True)
    st = CyclesSettings(samples=args.direct_spp, adaptive_threshold=0.0, denoise=False, seed=1000, exposure=0.0,
                        max_bounces=0, threads=args.threads, **tr)
    c0 = time.process_time()
    with CyclesRenderer(view_scene(ref_scene, i), st, vertex_normals=normals) as r:
        img = r.render(0, ("rgb",))["rgb"].astype(np.float32)
    print(f"  direct reference {name}: {time.process_time() - c0:.0f} CPU s", flush=True)
    np.save(str(p) + ".tmp.npy", img)
    os.replace(str(p) + ".tmp.npy", p)
    return img


def main() -> None:
    import bpy  # noqa: F401  (bpy before anything that could import pymeshlab)

    import cycles_reference as cr
    from room_pipeline.render.blender import CyclesSettings
    from room_pipeline.render.indirect import IndirectConfig
    from room_pipeline.render.antialias import silhouette_pixels
    from room_pipeline.render.params import raycast_config

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", action="append", help="PATIENT_DIR:view,view (repeatable)")
    ap.add_argument("--sequence", default="sequence_000")
    ap.add_argument("--res", type=int, default=200)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--ref-bounces", type=int, default=8)
    ap.add_argument("--ref-subdivide", type=int, default=2)
    ap.add_argument("--ref-blender-defaults", action="store_true",
                    help="cycles_reference.py's session-10 references (no tip-light shadows, clamp 10, Filter Glossy 1)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--ss", default="3,5", help="odd sub-pixel sample counts per axis for the pixel-filter check")
    ap.add_argument("--edge-samples", default="3", help="RaycastConfig.edge_samples values to score (0 = skip)")
    ap.add_argument("--direct", action="store_true", help="also the direct/indirect split (a Cycles direct render)")
    ap.add_argument("--direct-spp", type=int, default=256)
    ap.add_argument("--set", action="append", default=[], help="render.KEY=VALUE for the ray caster (yaml value)")
    ap.add_argument("--make-refs", action="store_true")
    ap.add_argument("--partial-refs", action="store_true",
                    help="render no reference: score against the cached halves there are (one half: raw PSNR only)")
    ap.add_argument("--out", default="cycles_residual")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (32x32, 8-spp reference, no results file): runs?")
    args = ap.parse_args()
    if args.quick:
        args.res, args.ref_spp, args.ss, args.direct_spp = 32, 8, "3", 4
        args.views = args.views or [str(ROOT / "data" / "output" / "patient_000") + ":bifurcation"]
    if not args.views:
        ap.error("--views PATIENT_DIR:view,... is required")
    import yaml

    over = {}
    for s in args.set:
        k, v = s.split("=", 1)
        over[k] = yaml.safe_load(v)
    rp = cr.render_params(over)
    width = CyclesSettings().filter_width
    rows = []
    for spec in args.views:
        pdir, names = spec.rsplit(":", 1)
        scene, graph = cr.build_scene(Path(pdir), args.sequence, rp, args.res)
        views = cr.pick_views(scene, graph)
        ref_scene, normals = cr.reference_scene(cr.build_scene(Path(pdir), args.sequence, cr.render_params(),
                                                               args.res)[0], args.ref_subdivide)
        for n in names.split(","):
            i = views[n]
            if args.partial_refs:
                key = cr.cache_key(ref_scene, i, args.res, args.ref_spp, args.ref_bounces, cr.reference_transport(args))
                ref_dir = cr.CACHE / f"{n}_{i}_{key}"
            else:
                ref_dir = cr.make_reference(ref_scene, i, n, args, normals)
            if args.make_refs:
                continue
            film = scene.film
            halves = [np.load(p) for p in sorted(ref_dir.glob("half_*.npy"))]
            if not halves:
                print(f"{Path(pdir).name} {n} (pose {i}): no reference half in {ref_dir}: not scored", flush=True)
                continue
            ev = cr.film_ev(scene, i)
            ref_lin = sum(halves) / len(halves)
            ref8 = cr.to8(ref_lin, film, ev).astype(np.float64) / 255
            mse_ref = None                                  # one half: its noise is not known from itself
            if len(halves) == 2:
                a8, b8 = (cr.to8(h, film, ev).astype(np.float64) / 255 for h in halves)
                mse_ref = float(np.mean((a8 - b8) ** 2)) / 4
            star = (lambda m: None) if mse_ref is None else (lambda m: cr.psnr(m - mse_ref))   # noqa: E731
            sc = cr.view_scene(scene, i)
            cfg = raycast_config(rp, args.threads)
            lin, depth, cpu = rc_linear(sc, cfg)

            def err(lin_img):
                return (cr.to8(lin_img, film, ev).astype(np.float64) / 255 - ref8) ** 2

            e = err(lin)
            mse = float(e.mean())
            row = {"patient": Path(pdir).name, "view": n, "pose": i, "exposure_ev": ev, "psnr_db": cr.psnr(mse),
                   "psnr_star_db": star(mse), "ref_own_psnr_db": None if mse_ref is None else cr.psnr(mse_ref),
                   "ref_spp_used": args.ref_spp // 2 * len(halves), "cpu_s": cpu,
                   "channels_db": [cr.psnr(float(e[..., k].mean())) for k in range(3)]}
            h, w = depth.shape
            yy, xx = np.mgrid[0:h, 0:w]
            rr = np.hypot(xx - (w - 1) / 2, yy - (h - 1) / 2) / (w / 2)
            sil = silhouette_pixels(depth, depth > 0, cfg.edge_depth_jump)
            dmm = depth * 1e3
            regions = {"centre": rr < 0.5, "periphery": rr >= 0.5, "near<10mm": (dmm > 0) & (dmm < 10),
                       "10-25mm": (dmm >= 10) & (dmm < 25), "far>25mm": dmm >= 25, "no hit": depth <= 0,
                       "silhouettes": sil, "not silhouettes": ~sil}
            rl = ref8 @ np.array([0.2126, 0.7152, 0.0722])
            regions["highlights (ref top 1 %)"] = rl >= np.percentile(rl, 99)
            es = e.sum(axis=2)
            row["regions"] = {k: {"share": float(es[m].sum() / es.sum()), "frac_px": float(m.mean()),
                                  "psnr_db": cr.psnr(float(e[m].mean())) if m.any() else None}
                              for k, m in regions.items()}
            lum = lambda x: x @ np.array([0.2126, 0.7152, 0.0722])   # noqa: E731
            row["gain_ratio"] = float(lum(lin).sum() / lum(ref_lin).sum())
            best = max((cr.psnr(float(err(lin * 2 ** (k / 200)).mean())), 2 ** (k / 200)) for k in range(-200, 201, 4))
            row["best_gain"] = {"gain": best[1], "psnr_db": best[0]}
            var = {}
            lin1, _, cpu1 = rc_linear(sc, dataclasses.replace(cfg, shading_stride=1))
            var["shading_stride 1"] = (lin1, cpu1)
            lin_s, _, cpu_s_ = rc_linear(sc, dataclasses.replace(cfg, direct_shadows=not cfg.direct_shadows))
            var[f"direct_shadows {not cfg.direct_shadows}"] = (lin_s, cpu_s_)
            for m in (int(x) for x in args.edge_samples.split(",") if x and int(x) > 0):
                if m != cfg.edge_samples:
                    img, _, cpu_m = rc_linear(sc, dataclasses.replace(cfg, edge_samples=m))
                    var[f"edge_samples {m}"] = (img, cpu_m)
            for s in (int(x) for x in args.ss.split(",") if x):
                sch = dataclasses.replace(sc, camera=scaled_camera(sc.camera, s))
                hi, _, cpu_s = rc_linear(sch, cfg)
                var[f"{s}x{s} samples, Blackman-Harris {width} px"] = (filter_down(hi, s, width), cpu_s)
                box = hi.reshape(h, s, w, s, 3).mean(axis=(1, 3))
                var[f"{s}x{s} samples, box 1 px"] = (box, cpu_s)
            row["variants"] = {}
            for k, (img, c) in var.items():
                ev_ = err(img)
                evs = ev_.sum(axis=2)
                row["variants"][k] = {"psnr_db": cr.psnr(float(ev_.mean())), "psnr_star_db": star(float(ev_.mean())),
                                      "cpu_s": c, "silhouettes_psnr_db": cr.psnr(float(ev_[sil].mean())) if sil.any() else None,
                                      "not_silhouettes_psnr_db": cr.psnr(float(ev_[~sil].mean())),
                                      "channels_db": [cr.psnr(float(ev_[..., q].mean())) for q in range(3)]}
            if args.direct:
                ref_d = direct_reference(ref_scene, normals, i, n, args)
                lin_d, _, _ = rc_linear(sc, dataclasses.replace(cfg, indirect=IndirectConfig(bounces=0)))
                rd8 = cr.to8(ref_d, film, ev).astype(np.float64) / 255
                row["direct"] = {
                    "direct_alone_psnr_db": cr.psnr(float(np.mean((cr.to8(lin_d, film, ev) / 255 - rd8) ** 2))),
                    "ours_direct_cycles_indirect_psnr_db": cr.psnr(float(err(lin_d + (ref_lin - ref_d)).mean())),
                    "cycles_direct_ours_indirect_psnr_db": cr.psnr(float(err(ref_d + (lin - lin_d)).mean())),
                    "direct_ratio": float(lum(lin_d).sum() / lum(ref_d).sum()),
                    "indirect_ratio": float(lum(lin - lin_d).sum() / max(lum(ref_lin - ref_d).sum(), 1e-30)),
                    "indirect_share": float(lum(ref_lin - ref_d).sum() / lum(ref_lin).sum()),
                    "indirect_ratio_rgb": [float((lin - lin_d)[..., q].sum() / (ref_lin - ref_d)[..., q].sum())
                                           for q in range(3)]}
            rows.append(row)
            print(json.dumps(row, default=float), flush=True)
    if args.make_refs or args.quick:
        return
    doc = {"args": vars(args), "load_avg_end": os.getloadavg(), "filter_width_px": width, "rows": rows}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{args.out}.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    write_md(doc)


def _db(x) -> str:
    return "-" if x is None else f"{x:.2f}"


def write_md(d: dict) -> None:
    a = d["args"]
    cmd = "python benchmarks/cycles_residual.py " + " ".join(f"--views {v}" for v in a["views"]) + \
        f" --res {a['res']} --ref-spp {a['ref_spp']} --ss {a['ss']}" + (" --direct" if a["direct"] else "") + \
        (" --ref-blender-defaults" if a.get("ref_blender_defaults") else "") + \
        (" --partial-refs" if a.get("partial_refs") else "") + \
        "".join(f" --set {s}" for s in a["set"]) + f" --out {a['out']}"
    L = [f"# The default RGB's whole-frame error against the {a['ref_spp']}-spp Cycles reference, split (issue #15)", "",
         f"`{cmd}` (module docstring; {a['res']}x{a['res']} whole frames; load average {d['load_avg_end'][0]:.1f} at "
         "the end; CPU s = process time under load).", "",
         "| patient / view (pose) | reference spp | PSNR dB | PSNR* dB | R / G / B dB | lum. ratio ours / Cycles | "
         "best gain (PSNR dB) |", "|---|---|---|---|---|---|---|"]
    for r in d["rows"]:
        L.append(f"| {r['patient']} {r['view']} ({r['pose']}) | {r.get('ref_spp_used', a['ref_spp'])} | "
                 f"{r['psnr_db']:.2f} | {_db(r['psnr_star_db'])} | "
                 f"{' / '.join(f'{x:.2f}' for x in r['channels_db'])} | {r['gain_ratio']:.3f} | "
                 f"{r['best_gain']['gain']:.3f} ({r['best_gain']['psnr_db']:.2f}) |")
    if any(r['psnr_star_db'] is None for r in d["rows"]):
        L += ["", "PSNR* '-': one 512-spp half of the reference only (`--partial-refs`): the raw PSNR against it is "
              "conservative (the half's noise adds to the MSE in expectation) and its own noise is not measured."]
    keys = list(d["rows"][0]["regions"]) if d["rows"] else []
    L += ["", "Regions: share of the squared error (fraction of the pixels; PSNR dB of the region).", "",
          "| patient / view | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
    for r in d["rows"]:
        cells = []
        for k in keys:
            g = r["regions"][k]
            ps = "-" if g["psnr_db"] is None else f"{g['psnr_db']:.1f}"
            cells.append(f"{100 * g['share']:.0f} % ({100 * g['frac_px']:.1f} % px; {ps})")
        L.append(f"| {r['patient']} {r['view']} | " + " | ".join(cells) + " |")
    vk = list(d["rows"][0]["variants"]) if d["rows"] else []
    L += ["", "Ray caster variants (PSNR dB whole frame / PSNR* / silhouettes / elsewhere; CPU s of the render at "
          "the sampled resolution):", "", "| patient / view | default (1 ray / pixel centre) | " + " | ".join(vk) + " |",
          "|---|---|" + "---|" * len(vk)]
    for r in d["rows"]:
        sil = r["regions"]["silhouettes"]["psnr_db"]
        nsil = r["regions"]["not silhouettes"]["psnr_db"]
        cells = [f"{r['psnr_db']:.2f} / {_db(r['psnr_star_db'])} / {sil:.1f} / {nsil:.1f} ({r['cpu_s']:.2f} s)"]
        for k in vk:
            v = r["variants"][k]
            cells.append(f"{v['psnr_db']:.2f} / {_db(v['psnr_star_db'])} / {v['silhouettes_psnr_db']:.1f} / "
                         f"{v['not_silhouettes_psnr_db']:.1f} ({v['cpu_s']:.2f} s)")
        L.append(f"| {r['patient']} {r['view']} | " + " | ".join(cells) + " |")
    if d["rows"] and "direct" in d["rows"][0]:
        L += ["", "Light terms (Cycles direct alone: 0 bounces, "
              f"{a['direct_spp']} spp):", "", "| patient / view | direct alone dB | ours direct + Cycles indirect dB | "
              "Cycles direct + ours indirect dB | direct ratio | indirect ratio (R, G, B) | indirect share |",
              "|---|---|---|---|---|---|---|"]
        for r in d["rows"]:
            x = r["direct"]
            L.append(f"| {r['patient']} {r['view']} | {x['direct_alone_psnr_db']:.2f} | "
                     f"{x['ours_direct_cycles_indirect_psnr_db']:.2f} | {x['cycles_direct_ours_indirect_psnr_db']:.2f} | "
                     f"{x['direct_ratio']:.3f} | {x['indirect_ratio']:.3f} ("
                     f"{', '.join(f'{q:.3f}' for q in x['indirect_ratio_rgb'])}) | {x['indirect_share']:.2f} |")
    (RESULTS / f"{d['args']['out']}.md").write_text("\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    if len(sys.argv) == 3 and sys.argv[1] == "--md":        # rewrite a results file's table from its JSON
        write_md(json.loads(Path(sys.argv[2]).read_text()))
    else:
        main()
