#!/usr/bin/env python3
"""The ray caster's precomputed inter-reflection (render/indirect.py) against Cycles path tracing.

    python benchmarks/realism_indirect.py --inputs DIR --cache /tmp/refs --check-direct   # 0 bounces vs Cycles
    python benchmarks/realism_indirect.py --inputs DIR --cache /tmp/refs                  # quality table
    python benchmarks/realism_indirect.py --inputs DIR --cache /tmp/refs --tiles          # 600x600 1024-spp tiles
    python benchmarks/realism_indirect.py --inputs DIR --speed                            # CPU s per 600x600 frame

Inputs: a patient folder written by ``dvc repro`` (``anatomy/lung_model.obj``, ``centreline_graph.json``,
``sequence_000/metadata/simulation.json``); the scene is the render stage's (benchmarks/cycles_reference.py
builds it: default conf/render, lens distortion off, views trachea / bifurcation / distal picked from the
route).

**Same mesh on both sides**: Cycles and the ray caster render the render stage's mesh itself, with the
same area-weighted smooth vertex normals (given to Blender as custom normals).  Two appearances: the
appearance baked at the vertices on both sides (Cycles ``texture='vertex'``, the ray caster with
``per_pixel_texture`` off), so the score measures the light transport only; and the product's default RGB
(the appearance function evaluated per pixel) against Cycles evaluating the same function at every
shading point (``texture='per_point'``: the OSL shader of render/texture_osl.py), the product's own
appearance as the reference.  ``--tiles`` scores both (and the product against the vertex-bake reference,
as before the OSL shader existed).

References: Cycles, no adaptive sampling, no denoiser, ``--ref-bounces`` (8) bounces, shadow rays on (the
physical light; the product's Cycles preset skips them), no sample clamp and no Filter Glossy (Blender's
defaults, a clamp of 10 on bounced samples and Filter Glossy 1.0, bias it; the results before this change were
made with them), two halves of ``--ref-spp / 2`` samples with seeds
1000/1001 averaged in linear radiance; ``MSE_ref = MSE(a, b) / 4`` gives PSNR* (against the noise-free
image).  Every image goes through the same film: the view's exposure metered on the reference itself (the
render stage's rule, :func:`room_pipeline.render.shading.auto_exposure_ev` at its percentile/target), veiling
glare, sRGB, 8 bits.  PSNR of the 8-bit images.  CPU s = ``time.process_time`` of this process (all
threads).  Results: benchmarks/results/realism_indirect*.{md,json}.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
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


def psnr(mse: float) -> float:
    return float(10 * np.log10(1.0 / mse)) if mse > 0 else float("inf")


def lumen_normals(mesh) -> np.ndarray:
    from room_pipeline.render.indirect import vertex_normals_into_lumen

    return vertex_normals_into_lumen(mesh.vertices, mesh.faces)


def one_view(scene, i: int, ev: float | None = None):
    from cycles_reference import view_scene

    sc = view_scene(scene, i)
    if ev is not None:
        sc = dataclasses.replace(sc, film=dataclasses.replace(sc.film, exposure_ev=ev, frame_ev=None))
    return sc


def cycles_linear(sc, normals, spp: int, bounces: int, seed: int, threads: int, shadows: bool = True,
                  denoise: bool = False, border=None, texture: str = "vertex") -> tuple[np.ndarray, float]:
    """Raw linear radiance (exposure 0) of a one-pose scene from Cycles, and its CPU seconds."""
    from room_pipeline.render.blender import CyclesRenderer, CyclesSettings

    st = CyclesSettings(samples=spp, adaptive_threshold=0.0, denoise=denoise, seed=seed, exposure=0.0,
                        max_bounces=bounces, threads=threads, cast_shadows=shadows, clamp_indirect=0.0,
                        filter_glossy=0.0, texture=texture)
    with CyclesRenderer(sc, st, vertex_normals=normals) as r:
        if border is not None:
            set_border(r, border)
        c0 = time.process_time()
        img = r.render(0, ("rgb",))["rgb"].astype(np.float32)
        return img, time.process_time() - c0


def set_border(r, border) -> None:
    """Cycles border render of pixel rows y0:y1, columns x0:x1 (OpenCV rows from the top), not cropped."""
    x0, x1, y0, y1 = border
    rr = r._bscene.render
    w, h = rr.resolution_x, rr.resolution_y
    rr.use_border = True
    rr.use_crop_to_border = False
    rr.border_min_x, rr.border_max_x = x0 / w, x1 / w
    rr.border_min_y, rr.border_max_y = 1 - y1 / h, 1 - y0 / h      # Blender's y is up


def key_of(sc, *parts) -> str:
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(sc.mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(sc.mesh.faces, dtype=np.int64).tobytes())
    h.update(np.round(sc.poses[0], 12).tobytes())
    h.update(repr((sc.material, sc.light, sc.camera, parts)).encode())
    return h.hexdigest()[:16]


def reference(sc, normals, name: str, args, bounces: int, spp: int, border=None,
              texture: str = "vertex") -> tuple[np.ndarray, np.ndarray, dict]:
    """Two cached halves (linear, exposure 0) of a Cycles reference (``texture``: CyclesSettings.texture)."""
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    parts = (spp, bounces, border, "shadows", "unclamped") + (() if texture == "vertex" else (texture,))
    k = key_of(sc, *parts)
    halves, cpu = [], []
    for seed in (1000, 1001):
        p = cache / f"{name}_{k}_{seed}.npy"
        cpu_file = Path(str(p) + ".cpu_s")            # the half's CPU s when it was rendered
        if p.exists():
            halves.append(np.load(p))
            if cpu_file.exists():
                cpu.append(float(cpu_file.read_text()))
            continue
        img, c = cycles_linear(sc, normals, spp // 2, bounces, seed, args.threads, border=border, texture=texture)
        np.save(str(p) + ".tmp.npy", img)
        os.replace(str(p) + ".tmp.npy", p)
        cpu_file.write_text(f"{c!r}\n")
        halves.append(img)
        cpu.append(c)
        print(f"  reference {name} half {seed}: {c:.0f} CPU s", flush=True)
    return halves[0], halves[1], {"spp": spp, "bounces": bounces, "cpu_s_halves": cpu, "texture": texture}


def metered_ev(lin: np.ndarray, film, mask=None) -> float:
    from room_pipeline.render.shading import auto_exposure_ev

    m = np.ones(lin.shape[:2], bool) if mask is None else mask
    return auto_exposure_ev(lin, m & (lin.sum(-1) > 0), film)


def to8(lin, film, ev):
    from room_pipeline.render.shading import apply_response

    return apply_response(np.asarray(lin, np.float32), film, exposure_ev=ev).astype(np.float64) / 255


def raycast_linear(sc, per_pixel: bool, indirect, threads: int, stride: int = 2, rc_cache: dict | None = None,
                   transport_albedo: str = "area_mean", direct_shadows: bool = False):
    """Linear radiance (exposure 0, no vignetting) of the ray caster, its CPU s and build CPU s."""
    from room_pipeline.render.raycast import RaycastConfig, RaycastRenderer

    sc0 = dataclasses.replace(sc, film=dataclasses.replace(sc.film, exposure_ev=0.0, frame_ev=None, vignetting=0.0))
    rc = RaycastRenderer(sc0, RaycastConfig(nthreads=threads, per_pixel_texture=per_pixel, shading_stride=stride,
                                            indirect=indirect, transport_albedo=transport_albedo,
                                            direct_shadows=direct_shadows))
    b0 = time.process_time()
    if indirect.bounces > 0:
        rc.radiosity
    build = time.process_time() - b0
    c0 = time.process_time()
    out = rc.render(0, ("rgb",))
    return out["rgb_linear"], time.process_time() - c0, build


def scene_and_views(args):
    """(scene, graph, views, names, rp): the render stage's scene of ``args.inputs`` / ``args.sequence`` at
    ``args.res`` with the ``--set KEY=JSON`` overrides (``rp``: its render parameters), its named views and the
    ones ``--views`` asks for (bpy imported first: pymeshlab / Open3D must not come before it in a process)."""
    import bpy  # noqa: F401

    from cycles_reference import build_scene, pick_views, render_params

    sets = {k: json.loads(v) for k, v in (x.split("=", 1) for x in args.set)}
    rp = render_params(sets)
    scene, graph = build_scene(Path(args.inputs), args.sequence, rp, args.res)
    scene.vertex_albedo()
    return scene, graph, pick_views(scene, graph), [v for v in args.views.split(",") if v], rp


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--inputs", default=str(ROOT / "data" / "output" / "patient_000"))
    ap.add_argument("--sequence", default="sequence_000")
    ap.add_argument("--cache", default=str(ROOT / "benchmarks" / ".cache" / "realism_indirect"))
    ap.add_argument("--res", type=int, default=200)
    ap.add_argument("--ref-spp", type=int, default=256)
    ap.add_argument("--ref-bounces", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--views", default="trachea,bifurcation,distal")
    ap.add_argument("--check-direct", action="store_true", help="0 bounces: ray caster vs Cycles direct light")
    ap.add_argument("--grid", default="16,64,256", help="rays per point to try")
    ap.add_argument("--out", default="realism_indirect")
    ap.add_argument("--tiles", action="store_true", help="score full-resolution tiles (Cycles border render) of "
                    "--res frames against a --ref-spp reference (the headline: --res 600 --ref-spp 1024)")
    ap.add_argument("--tile", type=int, default=64, help="tile side, px")
    ap.add_argument("--grid-tiles", type=int, default=0, help="with --tiles: an N x N grid of tiles covering "
                    "each frame uniformly (tile centres at (k + 0.5) res / N) instead of the centre and one near-wall "
                    "tile; results realism_indirect_grid.{json,md}")
    ap.add_argument("--ref-textures", default="vertex,per_point",
                    help="with --tiles: the Cycles references to render, comma-separated: 'vertex' (the vertex bake: "
                    "light transport alone) and/or 'per_point' (the appearance function per shading point, OSL)")
    ap.add_argument("--transport-albedo", default="area_mean", choices=("area_mean", "point"),
                    help="with --tiles: the product's inter-reflection albedo (RaycastConfig.transport_albedo)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=JSON",
                    help="a render parameter over conf/render for every scene, e.g. --set 'base_color=[0.7,0.5,0.5]'")
    ap.add_argument("--speed", action="store_true", help="CPU s per frame of the default RGB with and without "
                    "the indirect light, at --res (600 for the headline), each view")
    args = ap.parse_args()
    tex = [t for t in args.ref_textures.split(",") if t]
    if not tex or any(t not in ("vertex", "per_point") for t in tex):
        print(f"realism_indirect: --ref-textures takes vertex and/or per_point, got {args.ref_textures!r}",
              file=sys.stderr)
        sys.exit(2)
    from room_pipeline.render.indirect import IndirectConfig

    scene, graph, views, names, rp = scene_and_views(args)
    normals = lumen_normals(scene.mesh)
    film = scene.film
    rows = []
    if args.speed:
        speed(scene, views, names, args)
        return
    if args.tiles:
        tiles(scene, views, names, normals, args)
        return
    for n in names:
        i = views[n]
        sc = one_view(scene, i)
        bounces = 0 if args.check_direct else args.ref_bounces
        a, b, meta = reference(sc, normals, n, args, bounces, args.ref_spp)
        ref = 0.5 * (a + b)
        ev = metered_ev(ref, film)
        ref8 = to8(ref, film, ev)
        mse_ref = float(np.mean((to8(a, film, ev) - to8(b, film, ev)) ** 2)) / 4
        print(f"{n} (pose {i}) EV {ev:+.3f}: reference's own PSNR {psnr(mse_ref):.1f} dB", flush=True)

        def score(label, lin, cpu, **kw):
            x = to8(lin, film, ev)
            mse = float(np.mean((x - ref8) ** 2))
            ratio = float(np.sum(lin) / max(np.sum(ref), 1e-30))
            row = {"view": n, "pose": i, "method": label, "cpu_s": cpu, "psnr_db": psnr(mse),
                   "psnr_star_db": psnr(mse - mse_ref) if mse > mse_ref else None, "energy_ratio": ratio, **kw}
            rows.append(row)
            print(f"  {label:50s} {cpu:6.2f} CPU s  PSNR {row['psnr_db']:6.2f}  PSNR* "
                  f"{row['psnr_star_db'] or float('nan'):6.2f}  sum ratio {ratio:.4f}", flush=True)

        if args.check_direct:
            lin, cpu, _ = raycast_linear(sc, False, IndirectConfig(bounces=0), args.threads)
            score("ray caster, direct only, vertex albedo (same mesh)", lin, cpu)
            continue
        lin, cpu, _ = raycast_linear(sc, False, IndirectConfig(bounces=0), args.threads)
        score("ray caster, direct only", lin, cpu)
        for k in (int(x) for x in args.grid.split(",")):
            for nb in (args.ref_bounces,):
                cfg = IndirectConfig(bounces=nb, rays_per_point=k)
                lin, cpu, build = raycast_linear(sc, False, cfg, args.threads)
                score(f"ray caster + indirect K {k}, {nb} bounces (vertex albedo)", lin, cpu, build_cpu_s=build,
                      rays_per_point=k, bounces=nb)
        cfg = IndirectConfig(bounces=args.ref_bounces, rays_per_point=64)
        lin, cpu, build = raycast_linear(sc, True, cfg, args.threads, stride=rp.shading_stride)
        score("the product: + indirect K 64, per-pixel appearance", lin, cpu, build_cpu_s=build, rays_per_point=64,
              bounces=args.ref_bounces, per_pixel_texture=True)
    doc = {"args": vars(args), "views": views, "rows": rows, "load_avg": os.getloadavg()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{args.out}.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    write_md(args.out)


def tile_boxes(res: int, t: int) -> list[tuple[int, int, int, int]]:
    """Two tiles (x0, x1, y0, y1) of a res x res frame: the centre (the far lumen) and half-way to the
    upper-left corner (the near wall), fixed, not chosen by looking at images."""
    c = res // 2 - t // 2
    q = res // 4 - t // 2
    return [(c, c + t, c, c + t), (q, q + t, q, q + t)]


def grid_boxes(res: int, t: int, n: int) -> list[tuple[int, int, int, int]]:
    """An n x n grid of t x t tiles (x0, x1, y0, y1) whose centres sit at (k + 0.5) res / n: a uniform sample."""
    cs = [int(round((k + 0.5) * res / n)) - t // 2 for k in range(n)]
    return [(x, x + t, y, y + t) for y in cs for x in cs]


LABEL_VERTEX = "ray caster + indirect, vertex albedo; Cycles: vertex albedo (light transport alone)"
LABEL_PRODUCT = "the product: per-pixel appearance; Cycles: the same function per shading point (OSL)"
LABEL_PRODUCT_VS_BAKE = "the product: per-pixel appearance; Cycles: vertex bake (before the OSL shader)"


def tiles(scene, views, names, normals, args) -> None:
    """PSNR of the ray caster's RGB (K 64, ``--ref-bounces``) on full-resolution tiles against Cycles border
    renders of ``--ref-spp`` samples (two halves): vertex albedo on both sides (light transport alone), and
    the product's per-pixel appearance against Cycles' per-shading-point appearance (and, for comparison,
    against the vertex-bake reference)."""
    from room_pipeline.render.indirect import IndirectConfig

    rp = render_params_default({k: json.loads(v) for k, v in (x.split("=", 1) for x in args.set)})
    ref_textures = [t for t in args.ref_textures.split(",") if t]
    film = scene.film
    rows = []
    for n in names:
        i = views[n]
        sc = one_view(scene, i)
        cfg = IndirectConfig(bounces=args.ref_bounces, rays_per_point=64, caustics=rp.indirect_caustics)
        lin_v, cpu_v, build_v = raycast_linear(sc, False, cfg, args.threads)
        lin_p, cpu_p, build_p = raycast_linear(sc, True, cfg, args.threads, stride=rp.shading_stride,
                                               transport_albedo=args.transport_albedo,
                                               direct_shadows=rp.direct_shadows)
        builds = {LABEL_VERTEX: build_v, LABEL_PRODUCT: build_p, LABEL_PRODUCT_VS_BAKE: build_p}
        ev = metered_ev(lin_p, film)                    # the frame's exposure, metered on the product's frame
        boxes = grid_boxes(args.res, args.tile, args.grid_tiles) if args.grid_tiles else tile_boxes(args.res, args.tile)
        for box in boxes:
            x0, x1, y0, y1 = box
            refs = {}
            for tex in ref_textures:
                a, b, meta = reference(sc, normals, f"{n}_tile{x0}_{y0}", args, args.ref_bounces, args.ref_spp,
                                       border=box, texture=tex)
                a, b = a[y0:y1, x0:x1], b[y0:y1, x0:x1]
                refs[tex] = (to8(0.5 * (a + b), film, ev),
                             float(np.mean((to8(a, film, ev) - to8(b, film, ev)) ** 2)) / 4, meta)
            for label, lin, tex in ((LABEL_VERTEX, lin_v, "vertex"), (LABEL_PRODUCT, lin_p, "per_point"),
                                    (LABEL_PRODUCT_VS_BAKE, lin_p, "vertex")):
                if tex not in refs:
                    continue
                ref8, mse_ref, meta = refs[tex]
                x = to8(lin[y0:y1, x0:x1], film, ev)
                mse = float(np.mean((x - ref8) ** 2))
                rows.append({"view": n, "pose": i, "tile": box, "method": label, "psnr_db": psnr(mse),
                             "psnr_star_db": psnr(mse - mse_ref) if mse > mse_ref else None,
                             "ref_psnr_db": psnr(mse_ref), "exposure_ev": ev, "ref": meta,
                             "mse": mse, "mse_ref": mse_ref, "transport_build_cpu_s": builds[label]})
                print(json.dumps({k: v for k, v in rows[-1].items() if k != "ref"}), flush=True)
    doc = {"args": vars(args), "views": views, "rows": rows, "load_avg": os.getloadavg()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    if args.grid_tiles:
        pooled = []
        for n in names:
            for label in sorted({r["method"] for r in rows}):
                rs = [r for r in rows if r["view"] == n and r["method"] == label]
                mse, mref = float(np.mean([r["mse"] for r in rs])), float(np.mean([r["mse_ref"] for r in rs]))
                pooled.append({"view": n, "pose": views[n], "method": label, "tiles": len(rs),
                               "pixels": len(rs) * args.tile ** 2, "psnr_db": psnr(mse),
                               "psnr_star_db": psnr(mse - mref) if mse > mref else None, "ref_psnr_db": psnr(mref),
                               "worst_tile_psnr_db": min(r["psnr_db"] for r in rs),
                               "transport_build_cpu_s": rs[0].get("transport_build_cpu_s"),
                               "ref_cpu_s": sum(sum(r["ref"]["cpu_s_halves"]) for r in rs)})
        doc["pooled"] = pooled
        (RESULTS / f"{args.out}_grid.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
        write_grid_md(args.out)
        return
    (RESULTS / f"{args.out}_tiles.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    write_md(args.out)


def write_grid_md(out: str = "realism_indirect") -> None:
    d = json.loads((RESULTS / f"{out}_grid.json").read_text())
    a = d["args"]
    n, t, res = a["grid_tiles"], a["tile"], a["res"]
    cover = n * n * t * t / res ** 2
    L = [f"# Ray caster + inter-reflection vs a {a['ref_spp']}-spp Cycles reference: a {n}x{n} grid of tiles over "
         f"whole {res}x{res} frames", "",
         f"`python benchmarks/realism_indirect.py --inputs {a['inputs']} --res {res} --ref-spp {a['ref_spp']} --tiles "
         f"--grid-tiles {n} --tile {t}"
         + (f" --transport-albedo {a['transport_albedo']}" if a.get("transport_albedo", "area_mean") != "area_mean" else "")
         + (f" --out {a['out']}" if a.get("out", "realism_indirect") != "realism_indirect" else "")
         + "".join(f" --set '{x}'" for x in a.get("set", [])) + f"`: in each view, {n * n} tiles of {t}x{t} px whose centres sit on a uniform "
         f"{n}x{n} grid ((k + 0.5) x {res} / {n} px), {100 * cover:.1f} % of the frame's pixels, rendered by Cycles "
         f"(border render of the full {res}x{res} frame: the same camera, same light; {a['ref_bounces']} bounces, "
         "shadow rays, no clamp, no Filter Glossy, two seeds of half the samples each) and compared with the same "
         "pixels of the ray caster's full frame (K 64 rays per vertex, the render stage's config). Same mesh on "
         "both sides; 'vertex albedo' = the appearance baked at the vertices on both sides (the light transport "
         "alone); 'per-pixel appearance' = the product's texture (noise fields every 2nd pixel, bilinear), "
         "against Cycles evaluating the same appearance function at every shading point (an OSL shader, "
         "render/texture_osl.py) or, for comparison, its vertex bake. "
         "Pooled = PSNR of the mean MSE over the tiles; PSNR* removes the reference's own noise (MSE(a, b) / 4). "
         "The product's inter-reflection re-emits with the appearance averaged over each vertex's hat function "
         f"(RaycastConfig.transport_albedo '{a.get('transport_albedo', 'area_mean')}'), the vertex-albedo rows "
         "with the point bake; 'transport "
         "build' = CPU s of building the precomputed transport in this process: the gather matrix is built once per "
         "mesh and shared (the first row), so the other rows show the vertex albedo's cost alone (point bake or area "
         "mean). "
         f"The exposure is metered on the product's full frame. Load average {d['load_avg'][0]:.1f}.", "",
         "| view (pose) | method | tiles (px) | pooled PSNR dB | pooled PSNR* dB | worst tile PSNR dB | reference's own "
         "PSNR dB | reference CPU s | transport build CPU s |", "|---|---|---|---|---|---|---|---|---|"]
    for r in d["pooled"]:
        ps = "" if r["psnr_star_db"] is None else f"{r['psnr_star_db']:.2f}"
        L.append(f"| {r['view']} ({r['pose']}) | {r['method']} | {r['tiles']} ({r['pixels']}) | {r['psnr_db']:.2f} | "
                 f"{ps} | {r['worst_tile_psnr_db']:.2f} | {r['ref_psnr_db']:.1f} | {r['ref_cpu_s']:.0f} | "
                 f"{r.get('transport_build_cpu_s') or float('nan'):.2f} |")
    L += ["", "Per tile: `benchmarks/results/" + out + "_grid.json`."]
    (RESULTS / f"{out}_grid.md").write_text("\n".join(L) + "\n")
    print("\n".join(L))


def speed(scene, views, names, args) -> None:
    """CPU s of the render stage's RGB per frame (cast, normals, per-pixel appearance, shading, indirect, film;
    exposure fixed: the meter's cost is measured separately) at --res, the radiosity built beforehand."""
    from room_pipeline.render.exposure import raw_exposures
    from room_pipeline.render.indirect import IndirectConfig
    from room_pipeline.render.raycast import RaycastConfig, RaycastRenderer
    from room_pipeline.render.params import exposure_params

    rows = []
    grid = [(0, 64)] + [(8, int(k)) for k in args.grid.split(",")]
    for n in names:
        i = views[n]
        sc = one_view(scene, i, 0.0)
        for nb, k in grid:
            rp = render_params_default({k_: json.loads(v) for k_, v in (x.split("=", 1) for x in args.set)})
            cfg = RaycastConfig(nthreads=args.threads, indirect=IndirectConfig(bounces=nb, rays_per_point=k,
                                                                               caustics=rp.indirect_caustics,
                                                                               max_edge_mm=rp.indirect_max_edge_mm),
                                edge_samples=rp.edge_samples, edge_depth_jump=rp.edge_depth_jump)
            rc = RaycastRenderer(sc, cfg)
            b0 = time.process_time()
            if nb:
                rc.radiosity
            build = time.process_time() - b0
            rc.render(0, ("rgb", "depth"))
            cpu, wall = [], []
            for _ in range(3):
                rc._cache.clear()
                rc._rad_frame = None          # the frame's radiosity solve is per-frame work: not reused (before
                #                               session 16 it was, and the rows left out the bounces' cost)
                for key in list(rc.timings):
                    rc.timings[key] = 0.0
                c0, w0 = time.process_time(), time.perf_counter()
                rc.render(0, ("rgb",))
                cpu.append(time.process_time() - c0)
                wall.append(time.perf_counter() - w0)
            m0 = time.process_time()
            raw_exposures(sc, exposure_params(rp), args.threads,
                          IndirectConfig(bounces=nb, rays_per_point=k, caustics=rp.indirect_caustics,
                                         max_edge_mm=rp.indirect_max_edge_mm)
                          if nb else None)
            meter = time.process_time() - m0
            rows.append({"view": n, "bounces": nb, "rays_per_point": k, "cpu_s": float(np.median(cpu)),
                         "wall_s": float(np.median(wall)), "indirect_wall_s": float(rc.timings["indirect"]),
                         "meter_cpu_s_incl_build": meter, "build_cpu_s": build, "res": args.res,
                         "n_vertices": int(sc.mesh.n_vertices),
                         "n_transport_points": int(len(rc.radiosity.vertices)) if nb else 0})
            print(json.dumps(rows[-1]), flush=True)
    doc = {"args": vars(args), "rows": rows, "load_avg": os.getloadavg(), "nproc": os.cpu_count()}
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{args.out}_speed.json").write_text(json.dumps(doc, indent=1) + "\n")
    write_md(args.out)


def render_params_default(sets: dict | None = None):
    from cycles_reference import render_params

    return render_params(sets)



def write_md(out: str = "realism_indirect") -> None:
    out = out.removesuffix("_direct")
    """benchmarks/results/<out>.md from the quality, tiles and speed JSONs that exist."""
    L = ["# Ray caster + precomputed inter-reflection (render/indirect.py) against Cycles path tracing", "",
         "Same mesh on both sides (the render stage's mesh, its area-weighted smooth normals, the appearance baked "
         "at its vertices) unless the row says 'per-pixel appearance' (the product's texture, which Cycles "
         "cannot evaluate per pixel). References: Cycles, no denoiser, no adaptive sampling, 8 bounces, shadow "
         "rays on; PSNR of 8-bit sRGB frames through the same film (veiling glare, the view's metered "
         "exposure); PSNR* removes the reference's own noise (MSE(a, b) / 4 of its two halves). "
         "Patient: the command's --inputs (default: the phantom patient_000), sequence_000; views picked from the route.", ""]
    for q in (RESULTS / f"{out}_direct.json", RESULTS / f"{out}.json"):
        if not q.exists():
            continue
        d = json.loads(q.read_text())
        a = d["args"]
        direct = a.get("check_direct")
        L += [f"## {'Direct light only (0 bounces on both sides)' if direct else 'Whole frames'}, "
              f"{a['res']}x{a['res']}, {a['ref_spp']}-spp reference", "",
              f"`python benchmarks/realism_indirect.py --inputs {a['inputs']} --res {a['res']} --ref-spp "
              f"{a['ref_spp']}{' --check-direct' if direct else ' --grid ' + a['grid']}` (load average "
              f"{d['load_avg'][0]:.1f}; CPU s of the RGB at this resolution, build excluded).", "",
              "| view | method | CPU s | PSNR dB | PSNR* dB | sum(ours)/sum(ref) |", "|---|---|---|---|---|---|"]
        for r in d["rows"]:
            ps = "" if r["psnr_star_db"] is None else f"{r['psnr_star_db']:.2f}"
            L.append(f"| {r['view']} | {r['method']} | {r['cpu_s']:.2f} | {r['psnr_db']:.2f} | {ps} | "
                     f"{r['energy_ratio']:.4f} |")
        L.append("")
    t = RESULTS / f"{out}_tiles.json"
    if t.exists():
        d = json.loads(t.read_text())
        a = d["args"]
        L += [f"## Full-resolution tiles, {a['res']}x{a['res']} frames, {a['ref_spp']}-spp reference", "",
              f"`python benchmarks/realism_indirect.py --inputs {a['inputs']} --res {a['res']} --ref-spp "
              f"{a['ref_spp']} --tiles --tile {a['tile']}`: Cycles border renders of {a['tile']}x{a['tile']} px "
              "tiles (the centre, and half-way to the upper-left corner) of the full frame; the exposure metered "
              f"on the product's full frame (load average {d['load_avg'][0]:.1f}).", "",
              "| view | tile x0,x1,y0,y1 | method | PSNR dB | PSNR* dB | reference's own PSNR dB |",
              "|---|---|---|---|---|---|"]
        for r in d["rows"]:
            ps = "" if r["psnr_star_db"] is None else f"{r['psnr_star_db']:.2f}"
            L.append(f"| {r['view']} | {','.join(str(x) for x in r['tile'])} | {r['method']} | {r['psnr_db']:.2f} | "
                     f"{ps} | {r['ref_psnr_db']:.1f} |")
        L.append("")
    s = RESULTS / f"{out}_speed.json"
    if s.exists():
        d = json.loads(s.read_text())
        a = d["args"]
        L += [f"## Cost per {a['res']}x{a['res']} frame ({a['threads']} threads)", "",
              f"`python benchmarks/realism_indirect.py --inputs {a['inputs']} --res {a['res']} --speed --grid "
              f"{a['grid']}{''.join(' --set ' + x for x in a.get('set') or [])} --out {a.get('out')}`: the render stage's RGB (cast, normals, per-pixel appearance, shading, indirect, film; "
              "median of 3, each with its own radiosity solve; the precomputation excluded and listed) and "
              "the exposure meter's pass of the frame (its own column), load average "
              f"{d['load_avg'][0]:.1f} on {d['nproc']} cores (wall is inflated by the other users).", "",
              "| view | bounces | K rays/vertex | CPU s/frame | wall s/frame | meter CPU s/frame | "
              "precompute CPU s (once per mesh) |",
              "|---|---|---|---|---|---|---|"]
        for r in d["rows"]:
            L.append(f"| {r['view']} | {r['bounces']} | {r['rays_per_point'] if r['bounces'] else '-'} | "
                     f"{r['cpu_s']:.3f} | {r['wall_s']:.3f} | {r['meter_cpu_s_incl_build']:.3f} | "
                     f"{r['build_cpu_s']:.2f} |")
        L.append("")
    (RESULTS / f"{out}.md").write_text("\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    if sys.argv[1:] == ["--md"]:
        write_md()
    else:
        main()
