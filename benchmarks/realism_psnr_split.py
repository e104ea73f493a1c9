#!/usr/bin/env python3
"""Where the default RGB's error against the 1024-spp Cycles reference comes from (issue #15's PSNR gap).

    python benchmarks/realism_psnr_split.py --inputs DIR/patient_000 --views trachea,distal --out NAME

The same 4x4 grid of 32x32 px tiles of 600x600 frames as ``realism_indirect.py --tiles --grid-tiles 4 --tile 32
--ref-textures per_point`` (its cached references are reused: same ``--cache``), and in addition a Cycles
reference of the **direct light alone** on the same tiles (0 bounces, ``--direct-spp`` samples, shadow rays, the
same OSL appearance per shading point).  The ray caster renders the product's frame (8 bounces, K 64) and its
direct term alone (``IndirectConfig(bounces=0)``: no diffuse or glossy inter-reflection).  Everything goes
through the same film at the exposure metered on the product's frame (as realism_indirect.py).  Splits:

* **direct / indirect**: PSNR of the direct terms alone; PSNR of the product with its direct term replaced by
  Cycles' (``ref_direct + (ours - ours_direct)``: the error left is the indirect one) and with its indirect
  term replaced by Cycles' (``ours_direct + (ref - ref_direct)``: the error left is the direct one); the
  ratios sum(ours) / sum(Cycles) of each term;
* **colour channels**: PSNR per channel;
* **exposure**: PSNR after the best single gain on the product's linear radiance (2^(k/200), |k| <= 200);
* **regions**: the 4 centre tiles against the 12 outer ones; pixels by the ray caster's depth (near < 10 mm,
  10-25 mm, far > 25 mm); highlights (the reference's brightest 1 % of the tiles' pixels): each one's share
  of the squared error and its PSNR.

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


def render_rc(sc, bounces: int, rp, threads: int, k: int = 64, glossy: bool = True, **indirect):
    """Linear radiance (exposure 0) and depth (m) of the product's ray caster with ``bounces``, ``k`` rays per vertex."""
    from room_pipeline.render.indirect import IndirectConfig
    from room_pipeline.render.raycast import RaycastConfig, RaycastRenderer

    sc0 = dataclasses.replace(sc, film=dataclasses.replace(sc.film, exposure_ev=0.0, frame_ev=None, vignetting=0.0))
    rc = RaycastRenderer(sc0, RaycastConfig(nthreads=threads, per_pixel_texture=True, shading_stride=rp.shading_stride,
                                            indirect=IndirectConfig(bounces=bounces, rays_per_point=k, glossy=glossy,
                                                                    **{'caustics': rp.indirect_caustics, **indirect}),
                                            direct_shadows=rp.direct_shadows))
    out = rc.render(0, ("rgb", "depth"))
    return out["rgb_linear"], out["depth"]


def reference_glossy_off(sc, normals, name: str, args, spp: int, border) -> tuple[np.ndarray, np.ndarray]:
    """Two cached halves (linear, exposure 0) of a Cycles border render with 8 bounces but no glossy bounce
    (``glossy_bounces = 0``: the wet layer still reflects the tip light itself, not the walls' light)."""
    from realism_indirect import key_of, set_border
    from room_pipeline.render.blender import CyclesRenderer, CyclesSettings

    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    k = key_of(sc, spp, 8, border, "shadows", "unclamped", "per_point", "glossy0")
    halves = []
    for seed in (1000, 1001):
        p = cache / f"{name}_{k}_{seed}.npy"
        if not p.exists():
            st = CyclesSettings(samples=spp // 2, adaptive_threshold=0.0, denoise=False, seed=seed, exposure=0.0,
                                max_bounces=8, threads=args.threads, cast_shadows=True, clamp_indirect=0.0,
                                filter_glossy=0.0, texture="per_point")
            with CyclesRenderer(sc, st, vertex_normals=normals) as r:
                set_border(r, border)
                r._bscene.cycles.glossy_bounces = 0
                img = r.render(0, ("rgb",))["rgb"].astype(np.float32)
            np.save(str(p) + ".tmp.npy", img)
            os.replace(str(p) + ".tmp.npy", p)
        halves.append(np.load(p))
    return halves[0], halves[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--inputs", required=True)
    ap.add_argument("--sequence", default="sequence_000")
    ap.add_argument("--cache", default=str(ROOT / "benchmarks" / ".cache" / "realism_indirect"))
    ap.add_argument("--views", default="trachea,bifurcation,distal")
    ap.add_argument("--poses", default="", help="extra views by pose index, comma-separated (named pose_N)")
    ap.add_argument("--res", type=int, default=600)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--direct-spp", type=int, default=256)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--rays", default="", help="also score the product with these gather rays per vertex (K), "
                    "comma-separated (the default is 64)")
    ap.add_argument("--glossy-off", action="store_true", help="also: both sides without glossy inter-reflection "
                    "(Cycles glossy_bounces 0 at --direct-spp; the ray caster's IndirectConfig(glossy=False))")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=JSON")
    ap.add_argument("--out", default="realism_psnr_split")
    args = ap.parse_args()
    args.ref_bounces, args.tile, args.grid_tiles = 8, 32, 4
    from room_pipeline.paths import PatientPaths

    mesh_path = PatientPaths(Path(args.inputs).parent, Path(args.inputs).name).mesh
    if not mesh_path.exists():
        print(f"realism_psnr_split: no lumen mesh {mesh_path.relative_to(args.inputs)} under {args.inputs}",
              file=sys.stderr)
        sys.exit(2)
    from realism_indirect import (grid_boxes, lumen_normals, metered_ev, one_view, psnr, reference, scene_and_views,
                                  to8)

    scene, graph, views, names, rp = scene_and_views(args)
    for p in (int(x) for x in args.poses.split(",") if x):
        views[f"pose_{p}"] = p
        names.append(f"pose_{p}")
    normals = lumen_normals(scene.mesh)
    film = scene.film
    rows = []
    for n in names:
        i = views[n]
        sc = one_view(scene, i)
        c0 = time.process_time()
        lin, depth = render_rc(sc, 8, rp, args.threads)
        lin0, _ = render_rc(sc, 0, rp, args.threads)
        rc_cpu = time.process_time() - c0
        ev = metered_ev(lin, film)
        boxes = grid_boxes(args.res, args.tile, args.grid_tiles)
        R, RD, O, OD, Z, C, M = [], [], [], [], [], [], []
        for (x0, x1, y0, y1) in boxes:
            a, b, _ = reference(sc, normals, f"{n}_tile{x0}_{y0}", args, 8, args.ref_spp, border=(x0, x1, y0, y1),
                                texture="per_point")
            da, db, _ = reference(sc, normals, f"{n}_tile{x0}_{y0}", args, 0, args.direct_spp,
                                  border=(x0, x1, y0, y1), texture="per_point")
            s = np.s_[y0:y1, x0:x1]
            R.append(0.5 * (a[s] + b[s]))
            RD.append(0.5 * (da[s] + db[s]))
            M.append(float(np.mean((to8(a[s], film, ev) - to8(b[s], film, ev)) ** 2)) / 4)
            O.append(lin[s])
            OD.append(lin0[s])
            Z.append(depth[s])
            cx, cy = (x0 + x1) / 2 / args.res, (y0 + y1) / 2 / args.res
            C.append(np.full(depth[s].shape, max(abs(cx - 0.5), abs(cy - 0.5)) < 0.25))
        R, RD, O, OD, Z, C = (np.concatenate(x, axis=0) for x in (R, RD, O, OD, Z, C))
        ref8 = to8(R, film, ev)
        e2 = (to8(O, film, ev) - ref8) ** 2                       # per pixel and channel
        lum = R @ np.array([0.2126, 0.7152, 0.0722])
        hl = lum >= np.percentile(lum, 99)
        tot = float(e2.sum())

        def region(mask):
            m = e2[mask]
            return {"pixels": int(mask.sum()), "psnr_db": psnr(float(m.mean())) if m.size else None,
                    "error_share": float(m.sum() / tot)}

        gains = [(k, psnr(float(np.mean((to8(O * 2 ** (k / 200), film, ev) - ref8) ** 2)))) for k in range(-200, 201, 2)]
        kbest, pbest = max(gains, key=lambda t: t[1])
        z = np.where(np.isfinite(Z), Z, np.inf)
        row = {"view": n, "pose": i, "exposure_ev": ev, "tiles": len(boxes), "rc_cpu_s": rc_cpu,
               "ref_psnr_db": psnr(float(np.mean(M))),
               "psnr_db": psnr(float(e2.mean())),
               "psnr_channels_db": [psnr(float(e2[..., c].mean())) for c in range(3)],
               "direct_alone_psnr_db": psnr(float(np.mean((to8(OD, film, ev) - to8(RD, film, ev)) ** 2))),
               "cycles_direct_psnr_db": psnr(float(np.mean((to8(RD + (O - OD), film, ev) - ref8) ** 2))),
               "cycles_indirect_psnr_db": psnr(float(np.mean((to8(OD + (R - RD), film, ev) - ref8) ** 2))),
               "direct_ratio": float(OD.sum() / RD.sum()),
               "indirect_ratio": float((O - OD).sum() / max((R - RD).sum(), 1e-30)),
               "indirect_share_ref": float((R - RD).sum() / R.sum()),
               "indirect_ratio_channels": [float((O - OD)[..., c].sum() / max((R - RD)[..., c].sum(), 1e-30))
                                           for c in range(3)],
               "best_gain": 2 ** (kbest / 200), "psnr_best_gain_db": pbest,
               "centre": region(C), "outer": region(~C),
               "near_lt_10mm": region(z < 0.010), "mid_10_25mm": region((z >= 0.010) & (z < 0.025)),
               "far_gt_25mm": region(z >= 0.025), "highlights_top1pct": region(hl),
               "direct_ratio_by_depth": {k: float(OD[m].sum() / max(RD[m].sum(), 1e-30)) for k, m in
                                         (("near", z < 0.010), ("mid", (z >= 0.010) & (z < 0.025)), ("far", z >= 0.025))
                                         if m.any()},
               "indirect_ratio_by_depth": {k: float((O - OD)[m].sum() / max((R - RD)[m].sum(), 1e-30)) for k, m in
                                           (("near", z < 0.010), ("mid", (z >= 0.010) & (z < 0.025)),
                                            ("far", z >= 0.025)) if m.any()}}
        if args.glossy_off:
            lg, _ = render_rc(sc, 8, rp, args.threads, glossy=False)
            G, Gm, P = [], [], []
            for (x0, x1, y0, y1) in boxes:
                a, b = reference_glossy_off(sc, normals, f"{n}_tile{x0}_{y0}", args, args.direct_spp, (x0, x1, y0, y1))
                s = np.s_[y0:y1, x0:x1]
                G.append(0.5 * (a[s] + b[s]))
                Gm.append(float(np.mean((to8(a[s], film, ev) - to8(b[s], film, ev)) ** 2)) / 4)
                P.append(lg[s])
            G, P = np.concatenate(G, axis=0), np.concatenate(P, axis=0)
            row["glossy_off"] = {"psnr_db": psnr(float(np.mean((to8(P, film, ev) - to8(G, film, ev)) ** 2))),
                                 "ref_psnr_db": psnr(float(np.mean(Gm))),
                                 "sum_ratio": float(P.sum() / G.sum()),
                                 "sum_ratio_indirect": float((P - OD).sum() / max((G - RD).sum(), 1e-30)),
                                 "cycles_glossy_share_of_light": float(1 - G.sum() / R.sum()),
                                 "ours_glossy_share_of_light": float(1 - P.sum() / O.sum())}
        for k in (int(x) for x in args.rays.split(",") if x):
            c0 = time.process_time()
            lk, _ = render_rc(sc, 8, rp, args.threads, k)
            P = np.concatenate([lk[y0:y1, x0:x1] for (x0, x1, y0, y1) in boxes], axis=0)
            row.setdefault("psnr_by_rays_per_point", {})[str(k)] = psnr(float(np.mean((to8(P, film, ev) - ref8) ** 2)))
            row.setdefault("cpu_s_by_rays_per_point", {})[str(k)] = time.process_time() - c0
        rows.append(row)
        print(json.dumps(row), flush=True)
    doc = {"args": vars(args), "rows": rows, "load_avg": os.getloadavg()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{args.out}.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    write_md(args.out)


def write_md(out: str) -> None:
    d = json.loads((RESULTS / f"{out}.json").read_text())
    a = d["args"]
    cmd = (f"python benchmarks/realism_psnr_split.py --inputs {a['inputs']} --views {a['views']}"
           + (f" --poses {a['poses']}" if a.get("poses") else "") + (f" --rays {a['rays']}" if a.get("rays") else "") + (" --glossy-off" if a.get("glossy_off") else "") + f" --direct-spp {a['direct_spp']}"
           + "".join(f" --set '{x}'" for x in a.get("set", [])) + f" --out {out}")
    f = lambda x: "" if x is None else f"{x:.2f}"  # noqa: E731
    L = ["# The default RGB's error against 1024-spp Cycles, split (issue #15)", "",
         f"`{cmd}` (module docstring: the 4x4 grid of 32x32 tiles of 600x600 frames, Cycles' direct light alone "
         f"at {a['direct_spp']} spp; load average {d['load_avg'][0]:.1f}).  'ours direct + Cycles indirect' leaves "
         "the direct term's error only, 'Cycles direct + ours indirect' the indirect term's only.", "",
         "| view (pose) | PSNR dB | R / G / B dB | best gain (PSNR dB) | direct alone dB | ours direct + Cycles "
         "indirect dB | Cycles direct + ours indirect dB | sum ratio direct / indirect (R, G, B) | indirect share "
         "of Cycles' light | reference's own PSNR dB |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in d["rows"]:
        ch = " / ".join(f"{x:.2f}" for x in r["psnr_channels_db"])
        ic = ", ".join(f"{x:.3f}" for x in r["indirect_ratio_channels"])
        L.append(f"| {r['view']} ({r['pose']}) | {r['psnr_db']:.2f} | {ch} | {r['best_gain']:.3f} "
                 f"({r['psnr_best_gain_db']:.2f}) | {r['direct_alone_psnr_db']:.2f} | {r['cycles_indirect_psnr_db']:.2f} "
                 f"| {r['cycles_direct_psnr_db']:.2f} | {r['direct_ratio']:.3f} / {r['indirect_ratio']:.3f} ({ic}) | "
                 f"{r['indirect_share_ref']:.2f} | {r['ref_psnr_db']:.1f} |")
    L += ["", "Regions (share of the squared error, PSNR dB of the region; depth from the ray caster):", "",
          "| view | centre 4 tiles | outer 12 tiles | near < 10 mm | 10-25 mm | far > 25 mm | highlights (top 1 %) | "
          "direct ratio near / mid / far | indirect ratio near / mid / far |", "|---|---|---|---|---|---|---|---|---|"]
    for r in d["rows"]:
        cells = [f"{100 * r[k]['error_share']:.0f} % ({f(r[k]['psnr_db'])}; {r[k]['pixels']} px)" for k in
                 ("centre", "outer", "near_lt_10mm", "mid_10_25mm", "far_gt_25mm", "highlights_top1pct")]
        dr = " / ".join(f"{v:.3f}" for v in r["direct_ratio_by_depth"].values())
        ir = " / ".join(f"{v:.3f}" for v in r["indirect_ratio_by_depth"].values())
        L.append(f"| {r['view']} | " + " | ".join(cells) + f" | {dr} | {ir} |")
    for r in d["rows"]:
        g = r.get("glossy_off")
        if g:
            L += ["", f"{r['view']}, glossy inter-reflection off on both sides (Cycles glossy_bounces 0, "
                  f"{a['direct_spp']} spp): PSNR {g['psnr_db']:.2f} dB (reference's own {g['ref_psnr_db']:.1f}), "
                  f"sum ratio {g['sum_ratio']:.3f}, indirect {g['sum_ratio_indirect']:.3f}; the glossy bounces' share "
                  f"of the light: Cycles {g['cycles_glossy_share_of_light']:.3f}, ours {g['ours_glossy_share_of_light']:.3f}"]
        if r.get("psnr_by_rays_per_point"):
            L += ["", f"{r['view']}: PSNR with K gather rays per vertex (the exposure kept): " + ", ".join(
                f"K {k} {v:.2f} dB ({r['cpu_s_by_rays_per_point'][k]:.0f} CPU s with the build)"
                for k, v in r["psnr_by_rays_per_point"].items())]
    L += ["", f"Per view: `benchmarks/results/{out}.json`."]
    (RESULTS / f"{out}.md").write_text("\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
