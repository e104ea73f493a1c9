#!/usr/bin/env python3
"""The default RGB and Cycles presets against a Cycles reference (1024 samples by default), on the render stage's own scene.

    python benchmarks/cycles_reference.py --inputs data/output/patient_000 --make-refs   # the references (slow)
    python benchmarks/cycles_reference.py --inputs data/output/patient_000             # the table
    python benchmarks/cycles_reference.py --quick                                      # tiny sizes: runs?

Inputs: a patient folder written by ``dvc repro`` / ``room run --until simulate`` (``anatomy/lung_model.obj``,
``anatomy/centreline_graph.json``, ``sequence_000/metadata/simulation.json``).  The scene is built exactly
as the render stage builds it (:mod:`room_pipeline.stages.render`: mesh, airway coordinates and mucosa
texture, tip light with its offset and cos^mu profile, film) from the default ``conf/render``; the lens
distortion is off here (Cycles renders a pinhole image; the distortion is a geometric resampling shared
by every renderer).

Views (chosen from the route, not by looking at images): ``trachea`` (the middle of the sequence's
generation-0 poses), ``bifurcation`` (the generation-0 pose closest to 10 mm before the carina, facing
it) and ``distal`` (90 % along the sequence).

1. Reference (``--make-refs``; cached under ``benchmarks/.cache/cycles_reference/``, keyed by mesh and
   pose, so it is reusable): two independent renders of ``ref_spp / 2`` samples each (no adaptive
   sampling, no denoiser, seeds 1000/1001, ``--ref-bounces`` bounces; unbiased light transport: shadow rays
   for the tip light, bounced samples not clamped, no Filter Glossy, as realism_indirect.py's references;
   ``--ref-blender-defaults``: session 10's, with Blender's clamp of 10, Filter Glossy 1 and the product
   preset's light without shadows), averaged in linear radiance.  The
   reference's own noise: ``MSE_ref = MSE(a, b) / 4`` of the 8-bit outputs; PSNR* of a candidate =
   ``10 log10(1 / (MSE - MSE_ref))`` estimates its PSNR against the noise-free image.
2. Every candidate's linear radiance goes through the same film (the view's automatic exposure as the
   render stage's per-frame gain control meters it, veiling glare, sRGB response, 8 bits): PSNR / PSNR* /
   SSIM of the 8-bit images.  Candidates: the ray caster (the default RGB: per-pixel appearance; and with
   the appearance read at the vertices), Cycles evaluating the appearance function per shading point
   (CyclesSettings' default ``texture='per_point'``, an OSL shader; the reference too) at 1/2/4/16 spp
   with and without OpenImageDenoise, bounces 1/2/4, and at half resolution upscaled.
3. Cost: CPU seconds of this process per frame (``time.process_time``, all threads: what the frame costs
   on a shared machine) and wall seconds, the scene already built.

Results: benchmarks/results/cycles_reference.{json,md}.  No GPU is used.
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
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
CACHE = ROOT / "benchmarks" / ".cache" / "cycles_reference"


def psnr(mse: float) -> float:
    return float(10 * np.log10(1.0 / mse)) if mse > 0 else float("inf")


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

    return float(structural_similarity(a, b, channel_axis=-1, data_range=1.0))


def render_params(overrides: dict | None = None):
    """The render stage's parameters from the default conf/render (+ overrides), lens distortion off."""
    from room_pipeline.config.compose import compose, section
    from room_pipeline.render.params import RenderParams

    d = dict(section(compose(), "render"))
    d["distortion"] = [0.0] * 5
    d.update(overrides or {})
    return RenderParams.from_dict(d)


def build_scene(pdir: Path, sequence: str, rp, res: int):
    """(scene, graph, timestamps): the render stage's scene of ``sequence`` at ``res`` x ``res``."""
    from room_pipeline.anatomy.centreline import CentrelineGraph
    from room_pipeline.io.mesh import read_obj
    from room_pipeline.render.scene import Scene
    from room_pipeline.render.texture import airway_coordinates
    from room_pipeline.render.params import camera_of, scene_parts
    from room_pipeline.render.sequence import face_labels, load_poses

    from room_pipeline.paths import PatientPaths

    pp = PatientPaths(pdir.parent, pdir.name)
    mesh = read_obj(pp.mesh)
    graph = CentrelineGraph.from_dict(json.loads(pp.centreline_graph.read_text()))
    ts, poses = load_poses(pp.sequence_metadata(sequence), rp.poses)
    rp = dataclasses.replace(rp, width=res, height=res)
    cam = camera_of(rp)
    material, light, film = scene_parts(rp)
    labels, _ = face_labels(mesh, graph)
    airway = airway_coordinates(mesh.vertices, graph) if material.texture.enabled else None
    return Scene(mesh, cam, poses, ts, material=material, light=light, film=film, face_labels=labels,
                 vertex_airway=airway), graph


def vertex_normals(mesh) -> np.ndarray:
    """Area-weighted unit vertex normals (air -> tissue), as the ray caster's smooth shading computes them."""
    v, f = mesh.vertices, mesh.faces
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    vn = np.zeros_like(v)
    for k in range(3):
        np.add.at(vn, f[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def subdivide(mesh, airway: np.ndarray | None, levels: int):
    """Linear (midpoint) subdivision, ``levels`` times: the same surface with 4^levels faces.

    Returns (mesh, airway, vertex normals into the lumen): new vertices get the mean of their edge's
    ends' airway coordinates and normals, i.e. what the ray caster interpolates at that point of the
    parent triangle (normals renormalised), so a texture baked at the new vertices approximates the
    per-pixel appearance function, on the parent's smooth normals.
    """
    from room_pipeline.io.mesh import Mesh

    v, f = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
    n = vertex_normals(mesh)
    a = None if airway is None else np.asarray(airway, np.float64)
    for _ in range(levels):
        e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        es = np.sort(e, axis=1)
        uniq, inv = np.unique(es, axis=0, return_inverse=True)
        inv = inv.reshape(-1)
        mid = len(v) + np.arange(len(uniq))
        v = np.concatenate([v, 0.5 * (v[uniq[:, 0]] + v[uniq[:, 1]])])
        n = np.concatenate([n, 0.5 * (n[uniq[:, 0]] + n[uniq[:, 1]])])
        if a is not None:
            a = np.concatenate([a, 0.5 * (a[uniq[:, 0]] + a[uniq[:, 1]])])
        nf = len(f)
        m01, m12, m20 = mid[inv[:nf]], mid[inv[nf:2 * nf]], mid[inv[2 * nf:]]
        f = np.concatenate([np.stack([f[:, 0], m01, m20], 1), np.stack([m01, f[:, 1], m12], 1),
                            np.stack([m20, m12, f[:, 2]], 1), np.stack([m01, m12, m20], 1)])
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return Mesh(v, f), (None if a is None else a.astype(np.float32)), -n


def pick_views(scene, graph) -> dict[str, int]:
    """trachea / bifurcation / distal pose indices from the route (see the module docstring)."""
    from scipy.spatial import cKDTree

    pts, _, bid = graph.all_points()
    gen = np.array([graph.branch(int(b)).generation for b in bid])
    pos = scene.poses[:, :3, 3]
    _, idx = cKDTree(pts).query(pos)
    g = gen[idx]
    g0 = np.nonzero(g == 0)[0]
    carina = graph.root.points[-1]
    d = np.linalg.norm(pos[g0] - carina, axis=1)
    return {"trachea": int(g0[len(g0) // 2]), "bifurcation": int(g0[np.argmin(np.abs(d - 0.010))]),
            "distal": int(round(0.9 * (len(scene.poses) - 1)))}


def view_scene(scene, i: int):
    """A one-pose scene (pose ``i``) with the film's per-frame exposure metered on it."""
    from room_pipeline.render.scene import Scene

    sc = Scene(scene.mesh, scene.camera, scene.poses[[i]], scene.timestamps[[i]], material=scene.material,
               light=scene.light, film=scene.film, face_labels=scene.face_labels, vertex_airway=scene.vertex_airway)
    sc._albedo_cache = scene._albedo_cache
    return sc


#: the reference's light transport: shadow rays for the tip light, no clamp of bounced samples, no Filter Glossy
#: (the unbiased path-traced image, as realism_indirect.py's references); Blender's defaults (no shadows from the
#: point light as the product's preset, indirect samples clamped at 10, Filter Glossy 1.0) were session 10's
UNBIASED = {"cast_shadows": True, "clamp_indirect": 0.0, "filter_glossy": 0.0}
BLENDER_DEFAULTS = {"cast_shadows": False, "clamp_indirect": 10.0, "filter_glossy": 1.0}


def reference_transport(args) -> dict:
    return dict(BLENDER_DEFAULTS if getattr(args, "ref_blender_defaults", False) else UNBIASED)


def cache_key(scene, i: int, res: int, spp: int, bounces: int, transport: dict | None = None) -> str:
    h = hashlib.sha1()
    h.update(np.ascontiguousarray(scene.mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(scene.mesh.faces, dtype=np.int64).tobytes())
    h.update(np.round(scene.poses[i], 12).tobytes())
    from room_pipeline.render.blender import CyclesSettings

    # the texture mode only when not the vertex bake, so references made before the OSL shader keep their keys
    tex = CyclesSettings().texture
    h.update(repr((scene.material, scene.light, res, spp, bounces) + (() if tex == "vertex" else (tex,))).encode())
    if transport is not None and transport != BLENDER_DEFAULTS:     # session 10's references keep their keys
        h.update(repr(sorted(transport.items())).encode())
    return h.hexdigest()[:16]


def make_reference(scene, i: int, name: str, args, normals: np.ndarray | None = None) -> Path:
    from room_pipeline.render.blender import CyclesRenderer, CyclesSettings

    transport = reference_transport(args)
    key = cache_key(scene, i, args.res, args.ref_spp, args.ref_bounces, transport)
    out = CACHE / f"{name}_{i}_{key}"
    if (out / "meta.json").exists():
        print(f"{name} (pose {i}): cached reference {out}", flush=True)
        return out
    out.mkdir(parents=True, exist_ok=True)
    sc = view_scene(scene, i)
    halves, times = [], []
    for seed in (1000, 1001):
        p = out / f"half_{seed}.npy"
        if p.exists():
            halves.append(np.load(p))
            continue
        st = CyclesSettings(samples=args.ref_spp // 2, adaptive_threshold=0.0, denoise=False, seed=seed,
                            exposure=0.0, max_bounces=args.ref_bounces, threads=args.threads, **transport)
        with CyclesRenderer(sc, st, vertex_normals=normals) as r:
            c0 = time.process_time()
            img = r.render(0, ("rgb",))["rgb"].astype(np.float32)
            times.append({"seed": seed, "wall_s": r.last_render_s, "cpu_s": time.process_time() - c0})
        tmp = out / f".half_{seed}.npy"
        np.save(tmp, img)
        os.replace(tmp, p)
        halves.append(img)
        print(f"{name} (pose {i}): reference half seed {seed}: {times[-1]['wall_s']:.0f} s wall, "
              f"{times[-1]['cpu_s']:.0f} s CPU", flush=True)
    meta = {"view": name, "pose_index": i, "pose": scene.poses[i].tolist(), "res": args.res, "spp": args.ref_spp,
            "bounces": args.ref_bounces, "subdivision_levels": args.ref_subdivide, "transport": transport,
            "mesh_faces": int(scene.mesh.n_faces), "halves": times, "linear": "raw linear radiance (exposure 0)",
            "load_avg": os.getloadavg()}
    (out / "meta.json").write_text(json.dumps(meta, indent=1))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--inputs", default=str(ROOT / "data" / "output" / "patient_000"))
    ap.add_argument("--sequence", default="sequence_000")
    ap.add_argument("--res", type=int, default=600)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--ref-bounces", type=int, default=8)
    ap.add_argument("--ref-blender-defaults", action="store_true",
                    help="session 10's reference: no shadow rays from the tip light, bounced samples clamped at 10, "
                         "Filter Glossy 1.0 (default: the unbiased reference, shadows on, no clamp, no glossy filter)")
    ap.add_argument("--ref-subdivide", type=int, default=2,
                    help="linear subdivisions of the mesh for the reference (appearance baked at 4^n x the vertices)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--views", default="trachea,bifurcation,distal")
    ap.add_argument("--candidates", default="all", help="'all' or 'raycast' (the ray caster's rows only)")
    ap.add_argument("--full-grid", action="store_true", help="also 2 spp, no-denoiser 1/16 spp, 2/4 bounces, ...")
    ap.add_argument("--fit-interreflection", action="store_true",
                    help="fit render.interreflection (F, window) of the ray caster against Cycles on fit views that "
                         "are not scored views (150x150, 64 spp + OIDN, reference mesh and bounces)")
    ap.add_argument("--fit-res", type=int, default=150)
    ap.add_argument("--speed", action="store_true",
                    help="CPU s per 600x600 frame of the ray caster's RGB with and without the fitted inter-reflection")
    ap.add_argument("--merge", action="store_true", help="keep the other views of the existing results file")
    ap.add_argument("--make-refs", action="store_true", help="render (or find cached) references and stop")
    ap.add_argument("--quick", action="store_true", help="tiny sizes: check that the script runs")
    args = ap.parse_args()
    if args.quick:
        args.res, args.ref_spp = 48, 8
    import bpy  # noqa: F401  (bpy before anything that could import pymeshlab)

    pdir = Path(args.inputs)
    rp = render_params()
    scene, graph = build_scene(pdir, args.sequence, rp, args.res)
    views = pick_views(scene, graph)
    names = [v for v in args.views.split(",") if v]
    print("views:", {n: views[n] for n in names}, flush=True)
    if args.fit_interreflection:
        fit_interreflection(pdir, args, views)
        return
    if args.speed:
        speed(scene, views, names, args)
        return
    ref_scene, normals = reference_scene(scene, args.ref_subdivide)
    refs = {n: make_reference(ref_scene, views[n], n, args, normals) for n in names}
    if args.make_refs:
        return
    score_all(scene, views, names, refs, rp, args, (ref_scene, normals))


def reference_scene(scene, levels: int):
    """The scene on the mesh subdivided ``levels`` times (same surface, texture baked at 4^levels x the
    vertices, the parent's smooth normals); ``levels`` 0: the scene itself."""
    from room_pipeline.render.scene import Scene

    if levels <= 0:
        return scene, None
    mesh, airway, normals = subdivide(scene.mesh, scene.vertex_airway, levels)
    t0 = time.process_time()
    sc = Scene(mesh, scene.camera, scene.poses, scene.timestamps, material=scene.material, light=scene.light,
               film=scene.film, vertex_airway=airway)
    sc.vertex_albedo()
    print(f"reference mesh: {mesh.n_faces} faces ({levels} subdivisions), texture baked in "
          f"{time.process_time() - t0:.1f} CPU s", flush=True)
    return sc, normals


def fit_views(n_poses: int, scored: dict) -> list[int]:
    """Poses at 15 %, 50 % and 75 % of the sequence, moved off any scored view by >= 20 poses."""
    out = []
    for f in (0.15, 0.5, 0.75):
        i = int(round(f * (n_poses - 1)))
        while any(abs(i - v) < 20 for v in scored.values()):
            i += 5
        out.append(min(i, n_poses - 1))
    return out


def fit_interreflection(pdir: Path, args, scored: dict) -> None:
    """Grid search of (F, window) for the ray caster against Cycles on the fit views (module docstring)."""
    from room_pipeline.render.blender import CyclesRenderer, CyclesSettings
    from room_pipeline.render.raycast import RaycastConfig, RaycastRenderer
    from room_pipeline.render.scene import Scene

    rp = render_params()
    scene, _ = build_scene(pdir, args.sequence, rp, args.fit_res)
    idx = fit_views(len(scene.poses), scored)
    print("fit views:", idx, "(scored views:", scored, ")", flush=True)
    ref_scene, normals = reference_scene(scene, args.ref_subdivide)
    fsc = Scene(ref_scene.mesh, ref_scene.camera, ref_scene.poses[idx], ref_scene.timestamps[idx],
                material=ref_scene.material, light=ref_scene.light, film=ref_scene.film,
                vertex_airway=ref_scene.vertex_airway)
    fsc._albedo_cache = ref_scene._albedo_cache
    st = CyclesSettings(samples=64, denoise=True, exposure=0.0, max_bounces=args.ref_bounces, threads=args.threads)
    cyc = []
    c0 = time.process_time()
    with CyclesRenderer(fsc, st, vertex_normals=normals) as r:
        for k in range(len(idx)):
            cyc.append(r.render(k, ("rgb",))["rgb"].astype(np.float32))
    print(f"Cycles fit views: {time.process_time() - c0:.0f} CPU s", flush=True)
    rows = []
    for F in (0.0, 0.35, 0.5, 0.6, 0.65, 0.7, 0.75, 0.8):
        for win in ((6.0,) if F == 0 else (6.0, 12.0, 24.0)):
            sc_f = dataclasses.replace(scene, material=dataclasses.replace(
                scene.material, interreflection=F, interreflection_window_m=win * 1e-3))
            ps = []
            for k, i in enumerate(idx):
                ev = film_ev(sc_f, i)
                one = view_scene(sc_f, i)
                one = dataclasses.replace(one, film=dataclasses.replace(one.film, exposure_ev=ev, frame_ev=None))
                out = RaycastRenderer(one, RaycastConfig(nthreads=args.threads)).render(0, ("rgb",))
                ref8 = to8(cyc[k], sc_f.film, ev).astype(np.float64) / 255
                ps.append(psnr(float(np.mean((out["rgb"].astype(np.float64) / 255 - ref8) ** 2))))
            rows.append({"interreflection": F, "window_mm": win, "psnr_db": ps, "mean_psnr_db": float(np.mean(ps))})
            print(f"  F {F:.2f} window {win:4.1f} mm: PSNR {' '.join(f'{x:.2f}' for x in ps)}  mean "
                  f"{rows[-1]['mean_psnr_db']:.2f}", flush=True)
    best = max(rows, key=lambda r: r["mean_psnr_db"])
    doc = {"fit_views": idx, "scored_views": scored, "res": args.fit_res, "cycles": "64 spp + OIDN, "
           f"{args.ref_bounces} bounces, the reference's subdivided mesh", "rows": rows, "best": best,
           "load_avg": os.getloadavg()}
    if args.quick:
        print(json.dumps(best))
        return
    (RESULTS / "interreflection_fit.json").write_text(json.dumps(doc, indent=1) + "\n")
    L = ["# The ray caster's inter-reflection term fitted against Cycles (fit views only)", "",
         f"`python benchmarks/cycles_reference.py --fit-interreflection --inputs {args.inputs}`: poses {idx} of "
         f"{args.sequence} (never the scored views {scored}), {args.fit_res}x{args.fit_res}; Cycles 64 spp + OIDN, "
         f"{args.ref_bounces} bounces on the reference's subdivided mesh; ray caster = the default RGB with "
         "render.interreflection F and window; both through the same film (each F's own metered exposure).", "",
         "| F | window mm | PSNR per view dB | mean dB |", "|---|---|---|---|"]
    for r in rows:
        L.append(f"| {r['interreflection']} | {r['window_mm']} | {' / '.join(f'{x:.2f}' for x in r['psnr_db'])} | "
                 f"{r['mean_psnr_db']:.2f} |")
    L += ["", f"Best: F {best['interreflection']}, window {best['window_mm']} mm ({best['mean_psnr_db']:.2f} dB)."]
    (RESULTS / "interreflection_fit.md").write_text("\n".join(L) + "\n")
    print("\n".join(L))


def speed(scene, views, names, args) -> None:
    """CPU / wall seconds of the ray caster's RGB (cast included, exposure fixed) per frame, F 0 vs fitted."""
    from room_pipeline.render.raycast import RaycastConfig, RaycastRenderer

    b = json.loads((RESULTS / "interreflection_fit.json").read_text())["best"]
    rows = []
    for n in names:
        i = views[n]
        for F, win in ((0.0, 6.0), (b["interreflection"], b["window_mm"])):
            mat = dataclasses.replace(scene.material, interreflection=F, interreflection_window_m=win * 1e-3)
            sc = dataclasses.replace(view_scene(scene, i), material=mat)
            sc = dataclasses.replace(sc, film=dataclasses.replace(sc.film, exposure_ev=0.0, frame_ev=None))
            rc = RaycastRenderer(sc, RaycastConfig(nthreads=args.threads))
            rc.render(0, ("rgb",))
            cpu, wall = [], []
            for _ in range(3):
                rc._cache.clear()
                c0, w0 = time.process_time(), time.perf_counter()
                rc.render(0, ("rgb",))
                cpu.append(time.process_time() - c0)
                wall.append(time.perf_counter() - w0)
            rows.append({"view": n, "interreflection": F, "window_mm": win, "cpu_s": float(np.median(cpu)),
                         "wall_s": float(np.median(wall))})
            print(json.dumps(rows[-1]), flush=True)
    doc = {"res": args.res, "threads": args.threads, "rows": rows, "load_avg": os.getloadavg()}
    (RESULTS / "interreflection_speed.json").write_text(json.dumps(doc, indent=1) + "\n")
    L = ["# The ray caster's RGB with and without the inter-reflection term: cost per frame", "",
         f"`python benchmarks/cycles_reference.py --speed --inputs {args.inputs}`: {args.res}x{args.res}, cast + "
         f"normals + per-pixel appearance + shading + film (exposure fixed; the meter pre-pass is extra), "
         f"{args.threads} threads, median of 3; load average {doc['load_avg'][0]:.1f} (wall is inflated by it).", "",
         "| view | F | window mm | CPU s/frame | wall s/frame |", "|---|---|---|---|---|"]
    for r in rows:
        L.append(f"| {r['view']} | {r['interreflection']} | {r['window_mm']} | {r['cpu_s']:.3f} | {r['wall_s']:.3f} |")
    (RESULTS / "interreflection_speed.md").write_text("\n".join(L) + "\n")
    print("\n".join(L))


def film_ev(scene, i: int) -> float:
    """The render stage's per-frame automatic exposure of pose ``i`` metered on that frame alone (EV)."""
    from room_pipeline.render.exposure import raw_exposures, smooth_exposures
    from room_pipeline.render.params import indirect_config

    p = exposure_params_default()
    sc = view_scene(scene, i)
    raw, lim = raw_exposures(sc, p, indirect=indirect_config(render_params()))   # the meter sees the bounces too
    return float(smooth_exposures(raw, sc.timestamps, p, lim)[0])


def exposure_params_default():
    from room_pipeline.render.params import exposure_params

    return exposure_params(render_params())


def to8(lin: np.ndarray, film, ev: float) -> np.ndarray:
    from room_pipeline.render.shading import apply_response

    return apply_response(np.asarray(lin, np.float32), film, exposure_ev=ev)


def score_all(scene, views, names, refs, rp, args, ref_scene_normals) -> None:
    import cv2

    from room_pipeline.render.blender import CyclesRenderer, CyclesSettings
    from room_pipeline.render.params import raycast_config
    from room_pipeline.render.raycast import RaycastRenderer

    doc = {"machine": {"nproc": os.cpu_count(), "cpu_threads": args.threads, "platform": platform.platform(),
                       "python": platform.python_version(), "load_avg_at_start": os.getloadavg(), "gpu": "none"},
           "inputs": str(args.inputs), "sequence": args.sequence, "args": vars(args), "views": views,
           "render_params": {k: v for k, v in dataclasses.asdict(rp).items() if k not in ("storage",)}}
    rows, references = [], []
    film = scene.film
    for n in names:
        i = views[n]
        meta = json.loads((refs[n] / "meta.json").read_text())
        a, b_half = (np.load(p) for p in sorted(refs[n].glob("half_*.npy")))
        ev = film_ev(scene, i)
        a8, b8 = (to8(h, film, ev).astype(np.float64) / 255 for h in (a, b_half))
        ref8 = to8(0.5 * (a + b_half), film, ev).astype(np.float64) / 255
        mse_ref = float(np.mean((a8 - b8) ** 2)) / 4
        references.append({"view": n, "pose_index": i, "exposure_ev": ev, "ref": meta,
                           "ref_psnr_vs_noise_free_db": psnr(mse_ref)})
        print(f"{n} (pose {i}, EV {ev:+.3f}): reference's own PSNR {psnr(mse_ref):.1f} dB", flush=True)

        def score(method, img8, cpu_s, wall_s, **kw):
            x = img8.astype(np.float64) / 255
            mse = float(np.mean((x - ref8) ** 2))
            row = {"view": n, "method": method, **kw, "cpu_s": cpu_s, "wall_s": wall_s, "psnr_db": psnr(mse),
                   "psnr_star_db": psnr(mse - mse_ref) if mse > mse_ref else None, "ssim": ssim(x, ref8)}
            rows.append(row)
            print(f"  {method:44s} {cpu_s:7.2f} CPU s {wall_s:7.2f} wall s  PSNR {row['psnr_db']:5.2f}  "
                  f"PSNR* {row['psnr_star_db'] or float('nan'):5.2f}  SSIM {row['ssim']:.4f}", flush=True)
            return row

        sc = view_scene(scene, i)
        sc2 = dataclasses.replace(sc, film=dataclasses.replace(film, exposure_ev=ev, frame_ev=None))
        variants = [(True, None, f"ray caster (default RGB: per-pixel appearance, {rp.indirect_bounces} bounces "
                                  f"precomputed)"),
                    (False, None, "ray caster, appearance at the vertices")]
        fit = RESULTS / "interreflection_fit.json"
        if fit.exists() and rp.indirect_bounces == 0:   # the old fitted window term, only without the bounces
            b = json.loads(fit.read_text())["best"]
            if b["interreflection"] != sc.material.interreflection:
                variants.append((True, b, f"ray caster + fitted interreflection F {b['interreflection']}, "
                                          f"window {b['window_mm']} mm"))
        for per_pixel, b, label in variants:
            scv = sc2
            if b is not None:        # its own metered exposure; the reference goes through the same film at that EV
                mat = dataclasses.replace(sc.material, interreflection=b["interreflection"],
                                          interreflection_window_m=b["window_mm"] * 1e-3)
                ev_b = film_ev(dataclasses.replace(scene, material=mat), i)
                scv = dataclasses.replace(sc2, material=mat, film=dataclasses.replace(sc2.film, exposure_ev=ev_b))
            rc = RaycastRenderer(scv, dataclasses.replace(raycast_config(rp, args.threads), per_pixel_texture=per_pixel))
            rc.render(0, ("rgb",))   # warm: the BVH, the precomputed transport and its albedo (once per mesh)
            rc._cache.clear()
            c0, w0 = time.process_time(), time.perf_counter()
            out = rc.render(0, ("rgb",))
            cpu, wall = time.process_time() - c0, time.perf_counter() - w0
            if b is None:
                score(label, out["rgb"], cpu, wall, renderer="raycast", per_pixel_texture=per_pixel)
            else:                    # scored against the reference at this variant's own exposure
                saved = ref8
                ref8 = to8(0.5 * (a + b_half), film, ev_b).astype(np.float64) / 255
                score(label, out["rgb"], cpu, wall, renderer="raycast", per_pixel_texture=True,
                      interreflection=b, exposure_ev=ev_b)
                ref8 = saved
        # (spp, OIDN, bounces, resolution scale, mesh): "product" = the render stage's Cycles scene (appearance
        # baked at the mesh's vertices), "subdivided" = the reference's mesh (isolates sampling from texture)
        grid = [(1, True, 3, 1.0, "product"), (4, True, 3, 1.0, "product"), (16, True, 3, 1.0, "product"),
                (4, False, 3, 1.0, "product"), (4, True, 1, 1.0, "product"), (4, True, 8, 1.0, "product"),
                (4, True, 3, 0.5, "product"), (16, True, 8, 1.0, "subdivided")]
        if args.full_grid:
            grid += [(2, True, 3, 1.0, "product"), (1, False, 3, 1.0, "product"), (16, False, 3, 1.0, "product"),
                     (4, True, 2, 1.0, "product"), (4, True, 4, 1.0, "product"), (16, True, 3, 0.5, "product"),
                     (4, True, 3, 1.0, "subdivided")]
        if args.quick:
            grid = grid[:2] + grid[-1:]
        if args.candidates == "raycast":
            grid = []
        ref_scene, ref_normals = ref_scene_normals
        for spp, dn, bounces, scale, which in grid:
            if which == "subdivided" and ref_normals is None:
                continue
            res = int(round(args.res * scale))
            scs = sc if which == "product" else view_scene(ref_scene, i)
            normals = None if which == "product" else ref_normals
            if scale != 1.0:
                cam = dataclasses.replace(scs.camera, width=res, height=res, fx=sc.camera.fx * scale,
                                          fy=sc.camera.fy * scale, cx=(sc.camera.cx + 0.5) * scale - 0.5,
                                          cy=(sc.camera.cy + 0.5) * scale - 0.5)
                scs = dataclasses.replace(scs, camera=cam)
            st = CyclesSettings(samples=spp, denoise=dn, exposure=0.0, max_bounces=bounces, threads=args.threads)
            with CyclesRenderer(scs, st, vertex_normals=normals) as r:
                r.render(0, ("rgb",))                       # BVH build, scene sync
                c0, w0 = time.process_time(), time.perf_counter()
                lin = r.render(0, ("rgb",))["rgb"]
                if scale != 1.0:
                    lin = cv2.resize(lin, (args.res, args.res), interpolation=cv2.INTER_LINEAR)
                cpu, wall = time.process_time() - c0, time.perf_counter() - w0
            name = f"cycles {spp} spp{' + OIDN' if dn else ''}, {bounces} bounces" + \
                   (f", {res}x{res} upscaled" if scale != 1.0 else "") + \
                   (", reference's subdivided mesh" if which != "product" else "")
            score(name, to8(lin, film, ev), cpu, wall, renderer="cycles", samples=spp, denoise=dn,
                  bounces=bounces, render_res=res, mesh=which)
    doc["references"] = references
    doc["quality"] = rows
    doc["machine"]["load_avg_at_end"] = os.getloadavg()
    if args.quick:
        print(json.dumps(doc, indent=1, default=float)[:1500])
        return
    RESULTS.mkdir(parents=True, exist_ok=True)
    old = RESULTS / "cycles_reference.json"
    if args.merge and old.exists():          # keep the other views of an earlier run (same inputs and settings)
        prev = json.loads(old.read_text())
        if prev.get("args", {}).get("res") == args.res and prev.get("inputs") == doc["inputs"]:
            doc["references"] = [r for r in prev.get("references", []) if r["view"] not in names] + doc["references"]
            doc["quality"] = [r for r in prev.get("quality", []) if r["view"] not in names] + doc["quality"]
            doc["machine"]["load_avg_at_start"] = prev["machine"]["load_avg_at_start"]
    (RESULTS / "cycles_reference.json").write_text(json.dumps(doc, indent=1, default=float) + "\n")
    write_md(doc)


def _light_text(rp: dict) -> str:
    """The tip light as the run's render parameters had it (offset in mm, angular profile, falloff)."""
    off = rp.get("light_offset_mm")
    mu = rp.get("light_spot_exponent")
    where = f"{float(np.linalg.norm(off)):.1f} mm off axis" if off is not None else "offset not recorded"
    shape = ("isotropic" if mu == 0 else f"cos^{mu:g}") if mu is not None else "profile not recorded"
    extra = ""
    if rp.get("indirect_caustics") is not None:
        extra = f", inter-reflection {'with' if rp['indirect_caustics'] else 'without'} the wet layer at bounced walls"
    return f"tip light {where}, {shape}, {rp.get('light_falloff', 'inverse_square')} falloff{extra}"


def _transport_text(t: dict) -> str:
    return (f"tip-light shadows {'on' if t['cast_shadows'] else 'off'}, indirect clamp "
            f"{t['clamp_indirect'] or 'off'}, Filter Glossy {t['filter_glossy']}")


def write_md(d: dict) -> None:
    m = d["machine"]
    a = d["args"]
    L = [f"# The default RGB and Cycles against a {a['ref_spp']}-sample Cycles reference (render stage's scene)", "",
         f"`python benchmarks/cycles_reference.py --inputs {d['inputs']} --views {a['views']} --res {a['res']} "
         f"--ref-spp {a['ref_spp']}"
         + (" --ref-blender-defaults" if a.get("ref_blender_defaults") else "")
         + (f" --candidates {a['candidates']}" if a.get("candidates", "all") != "all" else "")
         + f"` on {m['nproc']} CPU cores shared with "
         f"other jobs (load average {m['load_avg_at_start'][0]:.1f} at start, {m['load_avg_at_end'][0]:.1f} at end; "
         f"{m['cpu_threads']} threads); no GPU.  Scene: the render stage's default (the ray caster with its "
         "precomputed inter-reflection and the appearance function per pixel; Cycles evaluating the same function "
         f"per shading point, OSL; {_light_text(d.get('render_params') or {})}; the view's automatic exposure metered as "
         "the render stage meters it, veiling glare, sRGB, 8 bits for every method).  The reference renders the "
         f"mesh subdivided {a['ref_subdivide']} times (the parent's smooth normals).  CPU s = process CPU time per "
         "frame (all threads), scene and precomputed transport built.", ""]
    for ref in d["references"]:
        r = ref["ref"]
        half = r["halves"][0] if r["halves"] else {}
        L += [f"## {ref['view']} (pose {ref['pose_index']}, {r['res']}x{r['res']}, exposure {ref['exposure_ev']:+.2f} EV)",
              "", f"Reference: {r['spp']} spp (two halves, no adaptive sampling, no denoiser), {r['bounces']} bounces"
              + (f", {_transport_text(r['transport'])}" if r.get("transport") else "")
              + (f"; {half.get('cpu_s', float('nan')):.0f} CPU s per half" if half else "")
              + f"; its own PSNR vs the noise-free image {ref['ref_psnr_vs_noise_free_db']:.1f} dB (PSNR* removes it).",
              "", "| method | CPU s/frame | wall s/frame | PSNR dB | PSNR* dB | SSIM |", "|---|---|---|---|---|---|"]
        for q in d["quality"]:
            if q["view"] != ref["view"]:
                continue
            ps = "" if q["psnr_star_db"] is None else f"{q['psnr_star_db']:.2f}"
            L.append(f"| {q['method']} | {q['cpu_s']:.2f} | {q['wall_s']:.2f} | {q['psnr_db']:.2f} | {ps} | {q['ssim']:.4f} |")
        L.append("")
    (RESULTS / "cycles_reference.md").write_text("\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
