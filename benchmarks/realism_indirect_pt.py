#!/usr/bin/env python3
"""The ray caster's precomputed inter-reflection against a brute-force path tracer of the same transport (issue #15).

    python benchmarks/realism_indirect_pt.py --views DIR/patient_000:bifurcation,trachea \
        --views DIR/patient_001:trachea --max-edge 0,2.0 --out realism_indirect_pt
    python benchmarks/realism_indirect_pt.py --quick          # a tiny run: does it work?

No Cycles: both sides are diffuse transport on the render mesh (the vertex albedo the transport uses,
Lambertian walls as Cycles without reflective caustics, the tip light as a point with its shadow rays and
its cos^mu / falloff profile), so the difference is the discretisation of :class:`~room_pipeline.render.
indirect.Radiosity` alone.  Views as benchmarks/cycles_reference.py picks them.  At every ``--stride``-th
pixel's hit ``x0``: the indirect irradiance (W/m^2, 1..8 bounces) of the radiosity (vertex values
interpolated, as the renderer reads them) and of ``--spp`` cosine-weighted paths from ``x0`` (Open3D rays;
at each path vertex the tip light's irradiance at that exact point, interpolated normal, shadow ray;
throughput times the interpolated albedo; a path ends when it escapes or hits a back face).  Reported:
ratio radiosity / path tracer of the summed irradiance per channel, over all sampled hits and by depth
(< 10, 10-25, > 25 mm), per bounce (1..5), and the share of bounces beyond 8 (the truncation both
Cycles' max_bounces = 8 and the radiosity leave out).  CPU s = ``time.process_time``.
Results: benchmarks/results/<out>.{json,md}.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))
sys.path.insert(0, str(ROOT / "benchmarks"))
RESULTS = ROOT / "benchmarks" / "results"
MAX_BOUNCES = 30


def check_view(sc, cfg, spp: int, stride: int, seed: int = 7) -> dict:
    """Radiosity vs path tracer on the one-pose scene ``sc`` (module docstring)."""
    from room_pipeline.render.indirect import cosine_directions
    from room_pipeline.render.raycast import RaycastRenderer

    rad = RaycastRenderer(sc, cfg).radiosity
    o3d, F = rad._o3d, rad.faces
    vn, alb = rad.normals.astype(np.float64), rad._alb.astype(np.float64)
    pose, light = sc.poses[0], sc.light
    R = pose[:3, :3]
    lp = R @ np.asarray(light.offset_m) + pose[:3, 3] - rad.origin

    def cast(o, d):
        out = rad.rc.cast_rays(o3d.core.Tensor(np.concatenate([o, d], 1).astype(np.float32)), nthreads=cfg.nthreads)
        t = out["t_hit"].numpy()
        hit = np.isfinite(t) & (np.einsum("ij,ij->i", out["primitive_normals"].numpy(), d.astype(np.float32)) > 0)
        return hit, t, out["primitive_ids"].numpy().astype(np.int64), out["primitive_uvs"].numpy().astype(np.float64)

    def interp(vals, prim, uv):
        tri, w0 = F[prim], 1 - uv[:, 0] - uv[:, 1]
        return w0[:, None] * vals[tri[:, 0]] + uv[:, :1] * vals[tri[:, 1]] + uv[:, 1:] * vals[tri[:, 2]]

    def unit(x):
        return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-30)

    c0 = time.process_time()
    ed, cos_l = rad.direct(pose, light)
    per_bounce_rad = [rad.indirect_irradiance(ed, b, cos_l).astype(np.float64) for b in range(1, 6)]
    e8 = rad.indirect_irradiance(ed, 8, cos_l).astype(np.float64)
    cpu_rad = time.process_time() - c0
    rays = sc.camera.pixel_rays()[::stride, ::stride].reshape(-1, 3) @ R.T
    d0 = unit(rays)
    o0 = np.repeat((pose[:3, 3] - rad.origin)[None], len(d0), 0)
    hit0, t0, prim0, uv0 = cast(o0, d0)
    idx = np.flatnonzero(hit0)
    p0 = o0[idx] + t0[idx, None] * d0[idx]
    depth = (p0 - o0[idx]) @ R[:, 2]
    rad8 = interp(e8, prim0[idx], uv0[idx])
    radb = [interp(x, prim0[idx], uv0[idx]) for x in per_bounce_rad]
    c0 = time.process_time()
    n = len(idx)
    acc = np.zeros((n, MAX_BOUNCES + 1, 3))
    P, N = np.repeat(p0, spp, 0), np.repeat(unit(interp(vn, prim0[idx], uv0[idx])), spp, 0)
    T, own, alive = np.ones((n * spp, 3)), np.repeat(np.arange(n), spp), np.arange(n * spp)
    for b in range(1, MAX_BOUNCES + 1):
        d = cosine_directions(N[alive], 1, seed + b).reshape(-1, 3)
        hit, t, prim, uv = cast(P[alive] + rad.config.eps_m * N[alive], d)
        o = P[alive][hit] + rad.config.eps_m * N[alive][hit]
        alive = alive[hit]
        if alive.size == 0:
            break
        P[alive] = o + t[hit, None] * d[hit]
        N[alive] = unit(interp(vn, prim[hit], uv[hit]))
        T[alive] *= interp(alb, prim[hit], uv[hit])
        e = rad.point_irradiance(P[alive] + rad.origin, N[alive], lp + rad.origin, R[:, 2], light)   # world m
        np.add.at(acc, (own[alive], b), T[alive] * e[:, None])
    acc /= spp
    cpu_pt = time.process_time() - c0
    pt8, pt_all = acc[:, 1:9].sum(1), acc[:, 1:].sum(1)
    out = {"hits": int(n), "spp": spp, "cpu_s_radiosity": cpu_rad, "cpu_s_path_tracer": cpu_pt, "regions": {}}
    for name, m in (("all", np.ones(n, bool)), ("near<10mm", depth < 0.010),
                    ("10-25mm", (depth >= 0.010) & (depth < 0.025)), ("far>25mm", depth >= 0.025)):
        if m.any():
            out["regions"][name] = {"frac": float(m.mean()),
                                    "ratio_rgb": (rad8[m].sum(0) / pt8[m].sum(0)).tolist()}
    ptb = acc.sum(0)[1:6]
    out["per_bounce_ratio_rgb"] = [(radb[k].sum(0) - (radb[k - 1].sum(0) if k else 0)) / ptb[k] for k in range(5)]
    out["per_bounce_ratio_rgb"] = [x.tolist() for x in out["per_bounce_ratio_rgb"]]
    out["beyond_8_share_rgb"] = ((pt_all.sum(0) - pt8.sum(0)) / pt_all.sum(0)).tolist()
    return out


def main() -> None:
    import cycles_reference as cr
    from room_pipeline.render.params import raycast_config
    from room_pipeline.render.indirect import IndirectConfig

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", action="append", help="PATIENT_DIR:view,view (repeatable)")
    ap.add_argument("--sequence", default="sequence_000")
    ap.add_argument("--max-edge", default="0,2.0", help="IndirectConfig.max_edge_mm values to compare (mm; "
                    "0: the transport on the render mesh, L > 0: on the mesh refined to edges <= L mm)")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--stride", type=int, default=4, help="every n-th pixel of the 200x200 frame")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default="realism_indirect_pt")
    ap.add_argument("--quick", action="store_true", help="tiny sizes, no results file: does it run?")
    args = ap.parse_args()
    if args.quick:
        args.spp, args.stride = 4, 25
        args.views = args.views or [str(ROOT / "data" / "output" / "patient_000") + ":bifurcation"]
    if not args.views:
        ap.error("--views PATIENT_DIR:view,... is required")
    for spec in args.views:
        if not Path(spec.rsplit(":", 1)[0]).is_dir():
            print(f"realism_indirect_pt: no patient folder {spec.rsplit(':', 1)[0]}", file=sys.stderr)
            sys.exit(2)
    for edge in args.max_edge.split(","):
        try:
            IndirectConfig(max_edge_mm=float(edge))
        except ValueError as e:
            print(f"realism_indirect_pt: bad --max-edge {edge!r}: {e}", file=sys.stderr)
            sys.exit(2)
    rp = cr.render_params()
    rows = []
    for spec in args.views:
        pdir, names = spec.rsplit(":", 1)
        scene, graph = cr.build_scene(Path(pdir), args.sequence, rp, 200)
        views = cr.pick_views(scene, graph)
        for name in names.split(","):
            sc = cr.view_scene(scene, views[name])
            for edge in args.max_edge.split(","):
                cfg = raycast_config(rp, args.threads)
                cfg = dataclasses.replace(cfg, indirect=dataclasses.replace(cfg.indirect, max_edge_mm=float(edge)))
                r = check_view(sc, cfg, args.spp, args.stride)
                r.update({"patient": Path(pdir).name, "view": name, "pose": views[name], "max_edge_mm": float(edge)})
                rows.append(r)
                print(json.dumps(r), flush=True)
    if args.quick:
        return
    RESULTS.mkdir(parents=True, exist_ok=True)
    doc = {"args": vars(args), "load_avg_end": os.getloadavg(), "rows": rows}
    (RESULTS / f"{args.out}.json").write_text(json.dumps(doc, indent=1) + "\n")
    cmd = "python benchmarks/realism_indirect_pt.py " + " ".join(f"--views {v}" for v in args.views) + \
        f" --max-edge {args.max_edge} --spp {args.spp} --stride {args.stride} --out {args.out}"
    f3 = lambda x: " / ".join(f"{v:.3f}" for v in x)   # noqa: E731
    L = ["# Precomputed inter-reflection vs a brute-force path tracer of the same diffuse transport (issue #15)", "",
         f"`{cmd}` (module docstring; 200x200 views, every {args.stride}-th pixel, {args.spp} paths each; load "
         f"average {doc['load_avg_end'][0]:.1f} at the end).  Ratio radiosity / path tracer of the indirect "
         "irradiance (8 bounces), R / G / B.", "",
         "| patient / view (pose) | transport max edge mm | all | near < 10 mm | 10-25 mm | far > 25 mm | per bounce 1 / 2 / 3 (G) | "
         "share beyond 8 bounces (R / G / B) |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cells = [f3(r["regions"][k]["ratio_rgb"]) if k in r["regions"] else "-"
                 for k in ("all", "near<10mm", "10-25mm", "far>25mm")]
        pb = " / ".join(f"{x[1]:.3f}" for x in r["per_bounce_ratio_rgb"][:3])
        L.append(f"| {r['patient']} {r['view']} ({r['pose']}) | {r['max_edge_mm']:g} | " + " | ".join(cells) +
                 f" | {pb} | {f3(r['beyond_8_share_rgb'])} |")
    (RESULTS / f"{args.out}.md").write_text("\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
