#!/usr/bin/env python3
"""Centreline extraction: our grassfire medial axis vs scikit-image skeletonisation vs kimimaro TEASAR.

Inputs per phantom seed (default phantom, 0.7 mm):
    isolation: the phantom's ground-truth SDF (``phantom.sdf``);
    chained:   ``compute_sdf(phantom.mask)`` (what the pipeline really sees).
Every method is scored with :func:`room_pipeline.evaluate.centreline.centreline_metrics`
against ``from_airway_tree(phantom.tree)``.  The baselines' skeleton points
(radius = -sdf of the same input) go through the same graph builder as ours
(:func:`centreline_from_points`: linking, TEASAR tree, pruning, smoothing,
resampling), so the table compares the centreline *points*; the baselines'
skeleton time and builder time are reported separately.

kimimaro is optional (extra ``bench``: ``.venv/bin/pip install -c constraints.txt -e ".[bench]"``;
it changes no pinned package), or install it outside the
project venv and point PYTHONPATH at it, e.g.
``pip install --target /tmp/kimi_site kimimaro osteoid==0.6.0`` then
``PYTHONPATH=/tmp/kimi_site python benchmarks/medial_axis.py``.

Also: speed vs error of ours against the number of surface samples (seed 0),
and, when ../shared/data is present, the AirQuant demo mask against its PTK
reference skeleton (distances both ways) and the Med-MPD masks (timings, counts).
Saves benchmarks/results/medial_axis.{json,md}.

    python benchmarks/medial_axis.py [--seeds 0 1 2] [--no-baselines] [--no-real]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
SHARED = Path(os.environ.get("ROOM_SHARED_DATA", ROOT.parent / "shared" / "data"))

from room_pipeline.anatomy.centreline import from_airway_tree  # noqa: E402
from room_pipeline.anatomy.medial_axis import (MedialAxisParams, centreline_from_points,  # noqa: E402
                                               crop_to_interior, extract_medial_axis)
from room_pipeline.anatomy.sdf import SdfParams, compute_sdf  # noqa: E402
from room_pipeline.evaluate.centreline import centreline_metrics  # noqa: E402
from room_pipeline.io.volume import Volume, read_volume  # noqa: E402

KEYS = ("dist_ext_to_true_mean_vox", "dist_true_to_ext_mean_vox", "detection_rate_large", "detection_rate",
        "spurious_fraction", "bifurcation_error_median_m", "n_extracted_branches", "n_true_branches")


def _sample_sdf(sdf: Volume, pts_world: np.ndarray) -> np.ndarray:
    from scipy import ndimage
    return ndimage.map_coordinates(sdf.data.astype(np.float32), sdf.world_to_index(pts_world).T, order=1,
                                   mode="nearest")


def skimage_points(mask: Volume) -> tuple[np.ndarray, float]:
    from skimage.morphology import skeletonize

    crop = crop_to_interior(mask, 2)
    t = time.perf_counter()
    sk = skeletonize(crop.data > 0)
    dt = time.perf_counter() - t
    return crop.index_to_world(np.argwhere(sk).astype(float)), dt


def kimimaro_points(mask: Volume) -> tuple[np.ndarray, float]:
    import kimimaro

    crop = crop_to_interior(mask, 2)
    sp_mm = crop.spacing * 1e3
    t = time.perf_counter()
    skels = kimimaro.skeletonize((crop.data > 0).astype(np.uint8),
                                 teasar_params={"scale": 1.5, "const": 1.0, "pdrf_scale": 100000, "pdrf_exponent": 4,
                                                "soma_detection_threshold": 1e9, "soma_acceptance_threshold": 1e9,
                                                "soma_invalidation_scale": 1.0, "soma_invalidation_const": 0.0},
                                 anisotropy=tuple(float(x) for x in sp_mm), dust_threshold=0, fix_branching=True,
                                 progress=False, parallel=1)
    dt = time.perf_counter() - t
    v = np.concatenate([s.vertices for s in skels.values()]) / sp_mm
    return crop.index_to_world(v), dt


def run_ours(sdf: Volume, truth, voxel: float, params: MedialAxisParams) -> dict:
    t = time.perf_counter()
    res = extract_medial_axis(sdf, params)
    dt = time.perf_counter() - t
    m = centreline_metrics(res.graph, truth, voxel)
    return {"time_s": dt, "report": res.report, "metrics": m}


def run_points(name: str, pts: np.ndarray, t_skel: float, sdf: Volume, truth, voxel: float) -> dict:
    r = -_sample_sdf(sdf, pts)
    keep = r > 0
    t = time.perf_counter()
    graph, rep = centreline_from_points(pts[keep], r[keep], sdf, MedialAxisParams())
    dt = time.perf_counter() - t
    return {"time_s": t_skel + dt, "skeleton_s": t_skel, "builder_s": dt, "n_points": int(keep.sum()),
            "report": rep, "metrics": centreline_metrics(graph, truth, voxel)}


def airquant(params: MedialAxisParams) -> dict | None:
    mp = SHARED / "airway_masks" / "airquant_demo" / "github_demo_seg.nii.gz"
    sk = SHARED / "airway_masks" / "airquant_demo" / "github_demo_seg_PTKskel.nii.gz"
    if not (mp.exists() and sk.exists()):
        return None
    from scipy.spatial import cKDTree

    mask = read_volume(mp)
    crop = crop_to_interior(mask, 6)
    t = time.perf_counter()
    sdf = compute_sdf(crop, SdfParams())
    t_sdf = time.perf_counter() - t
    t = time.perf_counter()
    res = extract_medial_axis(sdf, params)
    t_ma = time.perf_counter() - t
    ref = read_volume(sk)
    ref_pts = ref.index_to_world(np.argwhere(ref.data > 0).astype(float))
    from room_pipeline.evaluate.centreline import densify
    P, _, _, _ = densify(res.graph, 0.1e-3)
    d_ours, _ = cKDTree(ref_pts).query(P)
    d_ref, _ = cKDTree(P).query(ref_pts)

    def st(d):
        return {"mean_mm": float(d.mean() * 1e3), "median_mm": float(np.median(d) * 1e3),
                "p95_mm": float(np.percentile(d, 95) * 1e3)}

    return {"shape": list(mask.shape), "spacing_mm": (mask.spacing * 1e3).round(3).tolist(),
            "sdf_s": t_sdf, "medial_axis_s": t_ma, "n_branches": len(res.graph.branches),
            "max_generation": max(b.generation for b in res.graph.branches),
            "ours_to_reference": st(d_ours), "reference_to_ours": st(d_ref),
            "n_reference_voxels": int(len(ref_pts)), "report": res.report}


def medmpd(params: MedialAxisParams) -> dict:
    out = {}
    for p in (1, 2, 3):
        f = SHARED / "airway_masks" / "medmpd" / f"patient{p}" / "bronchialTree.nii.gz"
        if not f.exists():
            continue
        mask = read_volume(f)
        crop = crop_to_interior(mask, 6)
        t = time.perf_counter()
        sdf = compute_sdf(crop, SdfParams())
        t_sdf = time.perf_counter() - t
        t = time.perf_counter()
        res = extract_medial_axis(sdf, params)
        out[f"patient{p}"] = {"shape": list(mask.shape), "crop_shape": list(crop.shape),
                              "spacing_mm": (mask.spacing * 1e3).round(3).tolist(), "sdf_s": t_sdf,
                              "medial_axis_s": time.perf_counter() - t, "n_branches": len(res.graph.branches),
                              "max_generation": max(b.generation for b in res.graph.branches),
                              "dropped_components": res.report["dropped_components"],
                              "loops_broken": res.report["loops_broken"]}
        print(f"medmpd patient{p}: {out[f'patient{p}']}", flush=True)
    return out


def fmt_row(name, inp, r):
    m = r["metrics"]
    return (f"| {name} | {inp} | {r['time_s']:.1f} | {m['dist_ext_to_true_mean_vox']:.3f} | "
            f"{m['dist_true_to_ext_mean_vox']:.3f} | {m['detection_rate_large']:.3f} | {m['detection_rate']:.3f} | "
            f"{m['spurious_fraction']:.3f} | {m['bifurcation_error_median_m'] * 1e3:.2f} | "
            f"{m['n_extracted_branches']}/{m['n_true_branches']} |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--no-baselines", action="store_true")
    ap.add_argument("--no-real", action="store_true")
    args = ap.parse_args()
    from room_pipeline.anatomy.phantom import PhantomParams, make_phantom

    params = MedialAxisParams()
    try:
        import kimimaro  # noqa: F401
        import osteoid  # noqa: F401
        from importlib.metadata import version
        kimi = {"kimimaro": version("kimimaro"), "osteoid": version("osteoid")}
    except Exception as exc:  # optional baseline
        kimi = None
        print(f"kimimaro unavailable ({exc}); skipping that baseline", flush=True)
    results: dict = {"params": params.__dict__, "kimimaro_versions": kimi, "phantom": {}, "samples_sweep": {}}
    rows = []
    for seed in args.seeds:
        ph = make_phantom(PhantomParams(), seed)
        voxel = float(np.exp(np.mean(np.log(ph.sdf.spacing))))
        truth = from_airway_tree(ph.tree, 0.5 * voxel)
        t = time.perf_counter()
        chained = compute_sdf(ph.mask, SdfParams())
        t_sdf = time.perf_counter() - t
        inputs = {"isolation": ph.sdf, "chained": chained}
        res_seed = {"compute_sdf_s": t_sdf}
        pts_cache = {}
        if not args.no_baselines:
            pts_cache["skimage"] = skimage_points(ph.mask)
            if kimi:
                pts_cache["kimimaro"] = kimimaro_points(ph.mask)
        for inp, sdf in inputs.items():
            r = run_ours(sdf, truth, voxel, params)
            res_seed[f"ours/{inp}"] = r
            rows.append(fmt_row(f"ours (seed {seed})", inp, r))
            print(rows[-1], flush=True)
            for name, (pts, tsk) in pts_cache.items():
                rb = run_points(name, pts, tsk, sdf, truth, voxel)
                res_seed[f"{name}/{inp}"] = rb
                rows.append(fmt_row(f"{name} (seed {seed})", inp, rb))
                print(rows[-1], flush=True)
            if seed == args.seeds[0]:
                sweep = []
                for n in (10000, 25000, 50000, 100000, 150000, 0):
                    p = MedialAxisParams.from_dict({"n_surface_samples": n})
                    rs = run_ours(sdf, truth, voxel, p)
                    m = rs["metrics"]
                    sweep.append({"n_surface_samples": rs["report"]["n_surface_samples"], "time_s": rs["time_s"],
                                  **{k: m[k] for k in KEYS}})
                    print(inp, sweep[-1], flush=True)
                results["samples_sweep"][inp] = sweep
        results["phantom"][str(seed)] = res_seed
    if not args.no_real:
        results["airquant"] = airquant(params)
        print("airquant", results["airquant"], flush=True)
        results["medmpd"] = medmpd(params)

    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "medial_axis.json").write_text(json.dumps(results, indent=1, default=float))
    md = ["# Medial axis / centreline extraction", "",
          "Default phantom (0.7 mm). *isolation* = ground-truth SDF in, *chained* = compute_sdf(mask).",
          "Distances in voxels (mean, length-weighted); detection = true branches covered within half a radius "
          "(>= 1 voxel) over >= 80% of their length (large = radius >= 2 voxels); spurious = extracted branches "
          "< 50% on a true centreline; bifurcation error = median distance true junction -> nearest extracted "
          "junction. Baselines' skeleton points go through our graph builder; time = skeleton + builder.", "",
          "| method | input | time s | ext->true vox | true->ext vox | detection (r>=2 vox) | detection (all) | "
          "spurious | bif. err. median mm | branches ext/true |",
          "|---|---|---|---|---|---|---|---|---|---|", *rows, ""]
    if kimi:
        md += [f"kimimaro {kimi['kimimaro']}, osteoid {kimi['osteoid']} (installed outside the project venv).", ""]
    for inp, sweep in results["samples_sweep"].items():
        md += [f"## Ours: speed vs error against surface samples (seed {args.seeds[0]}, {inp})", "",
               "| surface samples | time s | ext->true vox | true->ext vox | detection (r>=2 vox) | spurious | "
               "bif. err. median mm | branches |", "|---|---|---|---|---|---|---|---|"]
        for s in sweep:
            md.append(f"| {s['n_surface_samples']} | {s['time_s']:.1f} | {s['dist_ext_to_true_mean_vox']:.3f} | "
                      f"{s['dist_true_to_ext_mean_vox']:.3f} | {s['detection_rate_large']:.3f} | "
                      f"{s['spurious_fraction']:.3f} | {s['bifurcation_error_median_m'] * 1e3:.2f} | "
                      f"{s['n_extracted_branches']}/{s['n_true_branches']} |")
        md.append("")
    aq = results.get("airquant")
    if aq:
        md += ["## AirQuant demo mask vs its PTK reference skeleton", "",
               f"shape {aq['shape']}, spacing {aq['spacing_mm']} mm; compute_sdf {aq['sdf_s']:.1f} s, "
               f"medial axis {aq['medial_axis_s']:.1f} s, {aq['n_branches']} branches, max generation "
               f"{aq['max_generation']}.", "",
               "| direction | mean mm | median mm | p95 mm |", "|---|---|---|---|"]
        for k in ("ours_to_reference", "reference_to_ours"):
            md.append(f"| {k.replace('_', ' ')} | {aq[k]['mean_mm']:.2f} | {aq[k]['median_mm']:.2f} | "
                      f"{aq[k]['p95_mm']:.2f} |")
        md.append("")
    if results.get("medmpd"):
        md += ["## Med-MPD masks (no reference centreline)", "",
               "| patient | crop shape | spacing mm | compute_sdf s | medial axis s | branches | max gen | "
               "dropped comps | loops broken |", "|---|---|---|---|---|---|---|---|---|"]
        for k, v in results["medmpd"].items():
            md.append(f"| {k} | {v['crop_shape']} | {v['spacing_mm']} | {v['sdf_s']:.1f} | {v['medial_axis_s']:.1f} "
                      f"| {v['n_branches']} | {v['max_generation']} | {v['dropped_components']} | "
                      f"{v['loops_broken']} |")
    (RESULTS / "medial_axis.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    sys.exit(main())
