#!/usr/bin/env python3
"""Real airway trees, perturbed as trees held back would differ (issue #18): does the anatomy chain still
find the trachea and plan a route?

Every shared real mask (Med-MPD 1-3, AirQuant, ATM_001, CASE073, CASE091 in ``../shared/data``) is perturbed:

* ``original``: as stored (the reference: its root branch is the true trachea, its end the true carina);
* ``crop_30mm`` / ``crop_10mm`` / ``crop_3mm``: the scan cut 30, 10, 3 mm above the carina (the array's
  superior slices removed);
* ``mirror``: left and right swapped (the array flipped along its world-x axis, header kept);
* ``spacing_0.5`` / ``spacing_0.8`` / ``spacing_1.0``: resampled to that isotropic spacing (mm; trilinear on
  the 0/1 mask, threshold 0.5, over the airway's bounding box + 5 mm);
* ``islands_30``: 30 seeded balls of 1-2.5 mm radius added outside the tree (airway-model debris);
* ``border_clip``: the volume clipped 15 % into the airway's extent on the patient's left (-x) side, so
  the left lung's peripheral branches run into the volume's border.

Each case is written as a NIfTI mask and run as a new user would: ``room run --until trajectory`` with the
mask as the patient's input (segment -> sdf -> mesh -> medial_axis -> trajectory, each stage in its own
process, default config); ``--render-cases`` also run simulate + render (10 frames, 192x192) on some.  The
table gives: where the root was found (its start's distance from the reference trachea's centreline, its
end's from the reference carina -- the original's first bifurcation at which both children divide on, see
``reference`` -- both mapped through the perturbation), the route's length and the deepest
generation it reaches, and for a failure the stage and its one-line message.  Results are cached per case
under ``--work`` so an interrupted run resumes.  Saves benchmarks/results/real_tree_robustness.{md,json}.

    python benchmarks/real_tree_robustness.py [--masks medmpd_1 ...] [--cases original crop_3mm ...]
        [--render-cases original crop_3mm] [--render-masks medmpd_1] [--work DIR] [--cached-only]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from room_pipeline.io.volume import Volume, read_volume, write_nifti
from room_pipeline.paths import PatientPaths

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _synthetic import REAL_MASKS  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
SHARED = ROOT.parent / "shared" / "data" / "airway_masks"
REAL = REAL_MASKS
CASES = ["original", "crop_30mm", "crop_10mm", "crop_3mm", "mirror", "spacing_0.5", "spacing_0.8", "spacing_1.0",
         "islands_30", "border_clip"]
MM = 1e-3


# --------------------------------------------------------------------------- perturbations
def _axis_of(vol: Volume, world_axis: int) -> tuple[int, float]:
    A = vol.affine[:3, :3]
    ax = int(np.argmax(np.abs(A[world_axis])))
    return ax, float(np.sign(A[world_axis, ax]))


def _sub(vol: Volume, lo, hi) -> Volume:
    lo, hi = np.asarray(lo, int), np.asarray(hi, int)
    aff = vol.affine.copy()
    aff[:3, 3] = vol.index_to_world(lo[None].astype(float))[0]
    return Volume(np.ascontiguousarray(vol.data[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]), aff)


def crop_above(vol: Volume, z: float) -> Volume:
    """Keep the slices whose world z is <= ``z`` (the scan cut there)."""
    ax, _ = _axis_of(vol, 2)
    idx = np.zeros((vol.shape[ax], 3))
    idx[:, ax] = np.arange(vol.shape[ax])
    keep = np.flatnonzero(vol.index_to_world(idx)[:, 2] <= z)
    lo, hi = np.zeros(3, int), np.array(vol.shape)
    lo[ax], hi[ax] = keep[0], keep[-1] + 1
    return _sub(vol, lo, hi)


def mirror(vol: Volume) -> tuple[Volume, callable]:
    """Flip the array along its world-x axis, header kept; returns the volume and the world map old -> new."""
    ax, _ = _axis_of(vol, 0)
    n = vol.shape[ax]

    def fmap(p):
        ijk = vol.world_to_index(np.atleast_2d(p))
        ijk[:, ax] = n - 1 - ijk[:, ax]
        return vol.index_to_world(ijk)
    return Volume(np.ascontiguousarray(np.flip(vol.data, axis=ax)), vol.affine.copy()), fmap


def resample(vol: Volume, spacing_mm: float) -> Volume:
    """Isotropic ``spacing_mm`` over the lumen's bounding box + 5 mm (trilinear on 0/1, threshold 0.5)."""
    m = np.asarray(vol.data) > 0
    nz = np.argwhere(m)
    pad = np.ceil(5 * MM / vol.spacing).astype(int)
    lo = np.maximum(nz.min(axis=0) - pad, 0)
    hi = np.minimum(nz.max(axis=0) + pad + 1, vol.shape)
    sub = _sub(vol.with_data(m.astype(np.uint8)), lo, hi)
    zoom = sub.spacing / (spacing_mm * MM)
    shape = np.maximum(np.round(np.array(sub.shape) * zoom).astype(int), 2)
    # new voxel centres on the same extent: index i_new -> old index i_new / zoom (corner-aligned scale)
    scale = (np.array(sub.shape) - 1) / np.maximum(shape - 1, 1)
    out = np.zeros(tuple(shape), dtype=np.uint8)
    src = np.asarray(sub.data, dtype=np.float32)
    for k0 in range(0, shape[2], 32):                        # in slabs: bounded memory
        ks = np.arange(k0, min(k0 + 32, shape[2]))
        I, J, K = np.meshgrid(np.arange(shape[0]) * scale[0], np.arange(shape[1]) * scale[1], ks * scale[2],
                              indexing="ij")
        out[:, :, ks] = ndimage.map_coordinates(src, [I, J, K], order=1, mode="nearest") >= 0.5
    aff = sub.affine.copy()
    aff[:3, :3] = sub.affine[:3, :3] * scale[None, :]
    return Volume(out, aff)


def islands(vol: Volume, n: int = 30, seed: int = 0) -> Volume:
    """``n`` seeded balls of 1-2.5 mm radius, each >= 5 mm from the tree and from each other."""
    d = (np.asarray(vol.data) > 0).astype(np.uint8)
    rng = np.random.default_rng(seed)
    far = ndimage.distance_transform_edt(d == 0, sampling=vol.spacing / MM) > 5.0
    nz = np.argwhere(d)
    lo, hi = nz.min(axis=0), nz.max(axis=0)
    placed, tries = 0, 0
    while placed < n and tries < 100000:
        tries += 1
        c = np.array([rng.integers(max(lo[a], 4), min(hi[a], vol.shape[a] - 5) + 1) for a in range(3)])
        if not far[tuple(c)]:
            continue
        r_mm = rng.uniform(1.0, 2.5)
        rv = np.ceil(r_mm / (vol.spacing / MM)).astype(int)
        sl = tuple(slice(max(c[a] - rv[a], 0), min(c[a] + rv[a] + 1, vol.shape[a])) for a in range(3))
        g = np.meshgrid(*[(np.arange(s.start, s.stop) - c[a]) * vol.spacing[a] / MM for a, s in enumerate(sl)],
                        indexing="ij")
        ball = sum(x * x for x in g) <= r_mm * r_mm
        d[sl][ball] = 1
        ex = tuple(slice(max(c[a] - rv[a] - int(np.ceil(5 / (vol.spacing[a] / MM))), 0),
                         c[a] + rv[a] + int(np.ceil(5 / (vol.spacing[a] / MM))) + 1) for a in range(3))
        far[ex] = False
        placed += 1
    return vol.with_data(d)


def border_clip(vol: Volume, fraction: float = 0.15) -> Volume:
    """Remove the part of the volume beyond ``fraction`` of the airway's x-extent on its -x side."""
    ax, sgn = _axis_of(vol, 0)
    nz = np.flatnonzero((np.asarray(vol.data) > 0).any(axis=tuple(b for b in range(3) if b != ax)))
    lo, hi = np.zeros(3, int), np.array(vol.shape)
    cut = int(round(fraction * (nz[-1] - nz[0])))
    if sgn > 0:
        lo[ax] = nz[0] + cut
    else:
        hi[ax] = nz[-1] + 1 - cut
    return _sub(vol, lo, hi)


# --------------------------------------------------------------------------- running
def run_case(mask_path: Path, out: Path, until: str, extra: list[str]) -> tuple[int, str, float, float]:
    cmd = [sys.executable, "-m", "room_pipeline.cli", "run", "--patient", "bench", "--until", until,
           f"output_dir={out}", "patients=phantom_single", f"+patients.bench={{kind: mask, input: '{mask_path}'}}",
           *extra]
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return r.returncode, r.stdout + r.stderr, time.perf_counter() - t0, cpu


def _polyline_dist(p: np.ndarray, line: np.ndarray) -> float:
    seg_a, seg_b = line[:-1], line[1:]
    d = seg_b - seg_a
    t = np.clip(np.einsum("ij,ij->i", p - seg_a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-30), 0, 1)
    return float(np.min(np.linalg.norm(seg_a + t[:, None] * d - p, axis=1)))


def summarise(out: Path, rc: int, log: str, ref: dict | None, fmap) -> dict:
    pp = PatientPaths(out, "bench")
    stages = ["segment", "sdf", "mesh", "medial_axis", "trajectory", "simulate", "render"]
    done = [s for s in stages if pp.stage_metrics(s, "sequence_000" if s in ("trajectory", "simulate", "render")
                                                  else "").is_file()]
    row: dict = {"exit": rc, "stages_done": done}
    if rc != 0:
        err = [ln for ln in log.splitlines() if ln.startswith("room: error")]
        row["failed_stage"] = next((s for s in stages if s not in done), "?")
        row["message"] = (err[-1] if err else log.strip().splitlines()[-1] if log.strip() else "")[:400]
    gpath = pp.centreline_graph
    if gpath.is_file():
        g = json.loads(gpath.read_text())
        br = {b["id"]: b for b in g["branches"]}
        root = next(b for b in g["branches"] if b["parent"] == -1)
        start, end = np.array(root["points"][0]), np.array(root["points"][-1])
        row.update(n_branches=len(br), max_generation=max(b["generation"] for b in br.values()),
                   root_start_mm=np.round(start / MM, 1).tolist(), root_length_mm=round(root["length"] / MM, 1))
        try:
            rep = g["metadata"]["report"]       # the medial-axis stage's root report
        except KeyError:
            rep = {}
        for k in ("root_entry_bifurcation", "root_reselected", "root_centred", "trachea_aspect_ratio"):
            if k in rep:
                row[k] = rep[k]
        if ref is not None:
            tr = fmap(np.array(ref["trachea"]))
            row["root_start_to_true_trachea_mm"] = round(_polyline_dist(start, tr) / MM, 1)
            row["root_end_to_true_carina_mm"] = round(float(np.linalg.norm(end - fmap(np.array(ref["carina"]))[0])) / MM, 1)
    tpath = pp.seq("sequence_000").trajectory
    if tpath.is_file() and gpath.is_file():
        t = json.loads(tpath.read_text())
        row["route_length_mm"] = round(t["summary"]["length_m"] / MM, 1)
        rb = t["summary"].get("route_branches", [])
        row["route_generation"] = max((br[b]["generation"] for b in rb if b in br), default=None)
        row["stop_reason"] = t.get("target", {}).get("stop_reason")
    rpath = pp.stage_metrics("render", "sequence_000")
    if rpath.is_file():
        m = json.loads(rpath.read_text())
        row["render"] = {k: m[k] for k in m if k in ("frames", "hit_fraction", "frames_rendered")} or True
    spath = pp.stage_metrics("simulate", "sequence_000")
    if spath.is_file():
        m = json.loads(spath.read_text())
        row["simulate"] = {k: m[k] for k in m if not isinstance(m[k], (dict, list))}
    return row


def reference(out: Path) -> dict:
    """The original mask's trachea (polyline, metres) and carina (its end) from its centreline graph.

    The carina is the first bifurcation at which both children divide on (the main bronchi each lead a
    subtree): walking down from the root, a bifurcation where one child ends without dividing and the other
    divides is passed (the trachea continues down the dividing one).  CASE091's graph roots 3.1 mm below its
    top, then two terminal twigs (10.0 mm, radius 5.9 -> 1.6 mm; 9.6 mm) within 10 mm of the scan's top cut,
    where its lumen is one oblique tube in every slice, then a 78 mm trunk (median radius 7.0 mm) that divides
    into two subtrees: that end is the carina (the mask resampled to 1 mm roots down to within 5.6 mm of it)."""
    g = json.loads(PatientPaths(out, "bench").centreline_graph.read_text())
    br = {b["id"]: b for b in g["branches"]}
    kids: dict = {}
    for b in g["branches"]:
        kids.setdefault(b["parent"], []).append(b["id"])
    cur = next(b["id"] for b in g["branches"] if b["parent"] == -1)
    trachea = list(br[cur]["points"])
    walked = 0
    while True:
        ch = kids.get(cur, [])
        dividing = [c for c in ch if kids.get(c)]
        if len(ch) < 2 or len(dividing) != 1:
            break
        cur = dividing[0]
        trachea += br[cur]["points"][1:]
        walked += 1
    return {"trachea": trachea, "carina": trachea[-1], "passed_bifurcations": walked}


def perturb_map(name: str, case: str, vol: Volume):
    """The world map original -> perturbed of ``case`` (only mirroring moves the anatomy)."""
    return mirror(vol)[1] if case == "mirror" else (lambda p: np.atleast_2d(p))


def perturb(name: str, case: str, vol: Volume, ref: dict | None):
    ident = (lambda p: np.atleast_2d(p))
    if case == "original":
        return vol, ident
    if case.startswith("crop_"):
        h = float(case[5:-2])
        return crop_above(vol, ref["carina"][2] + h * MM), ident
    if case == "mirror":
        return mirror(vol)
    if case.startswith("spacing_"):
        return resample(vol, float(case[8:])), ident
    if case == "islands_30":
        return islands(vol, 30, seed=0), ident
    if case == "border_clip":
        return border_clip(vol), ident
    raise SystemExit(f"room: error: unknown case {case!r} (choose from {', '.join(CASES)})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--masks", nargs="+", default=list(REAL), choices=list(REAL))
    ap.add_argument("--cases", nargs="+", default=CASES, choices=CASES)
    ap.add_argument("--render-cases", nargs="*", default=["original", "crop_3mm", "islands_30"], choices=CASES)
    ap.add_argument("--render-masks", nargs="*", default=["medmpd_1", "case091"], choices=list(REAL))
    ap.add_argument("--work", default=str(Path(os.environ.get("TMPDIR", "/tmp")) / "room_real_tree_robustness"))
    ap.add_argument("--cached-only", action="store_true",
                    help="run nothing: write the tables from the cases already cached under --work (a partial run)")
    ap.add_argument("--previous", default=None,
                    help="with --cached-only: a results JSON of an earlier run whose rows stand, marked '(prev)', for "
                         "the cases not cached here (those not re-run)")
    args = ap.parse_args()
    prev = {}
    if args.previous:
        prev = {(r["mask"], r["case"]): r for r in json.loads(Path(args.previous).read_text())["rows"]
                if not r.get("not_run")}
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.masks:
        path = SHARED / REAL[name]
        if not path.exists():
            print(f"skipped {name}: {path} not found (../shared/data absent)")
            continue
        vol = read_volume(path)
        ref = None
        cases = ["original"] + [c for c in args.cases if c != "original"]
        for case in cases:
            cache = work / f"{name}__{case}.json"
            cdir = work / f"{name}__{case}"
            if cache.is_file():
                row = json.loads(cache.read_text())
                if (cdir / "out").is_dir():              # re-read the outputs (the table's columns may have grown)
                    row.update(summarise(cdir / "out", row["exit"], (cdir / "room_run.log").read_text(), ref,
                                         perturb_map(name, case, vol)))
            elif args.cached_only:
                if prev and case == "original":       # nothing of this mask re-run: all its rows from --previous
                    rows += [{**prev[(name, c)], "previous": True} if (name, c) in prev else
                             {"mask": name, "case": c, "not_run": True} for c in cases]
                    break
                rows.append({**prev[(name, case)], "previous": True} if (name, case) in prev else
                            {"mask": name, "case": case, "not_run": True})
                if case == "original":
                    break
                continue
            else:
                render = case in args.render_cases and name in args.render_masks
                pv, fmap = perturb(name, case, vol, ref)
                cdir.mkdir(exist_ok=True)
                mpath = cdir / "mask.nii.gz"
                write_nifti(mpath, pv, description=f"{name} {case} (benchmarks/real_tree_robustness.py)")
                extra = ["render.max_frames=10", "render.width=192", "render.height=192"] if render else []
                rc, log, wall, cpu = run_case(mpath, cdir / "out", "render" if render else "trajectory", extra)
                (cdir / "room_run.log").write_text(log)
                row = {"mask": name, "case": case, "shape": list(pv.shape),
                       "spacing_mm": np.round(pv.spacing / MM, 3).tolist(), "rendered": render,
                       "wall_s": round(wall, 1), "cpu_s": round(cpu, 1), **summarise(cdir / "out", rc, log, ref, fmap)}
                if case == "original" and rc == 0:
                    row["reference"] = reference(cdir / "out")
                cache.write_text(json.dumps(row) + "\n")
            if case == "original" and row.get("exit") == 0 and (cdir / "out").is_dir():
                row["reference"] = reference(cdir / "out")       # (the rule below may be newer than the cache)
                row["reference_passed_bifurcations"] = row["reference"]["passed_bifurcations"]
                # the pipeline's own root on the uncut mask against the reference carina: > 0 when the graph's
                # first bifurcation is a terminal twig above the carina (CASE091, CASE073)
                g0 = json.loads(PatientPaths(cdir / "out", "bench").centreline_graph.read_text())
                end0 = np.array(next(b for b in g0["branches"] if b["parent"] == -1)["points"][-1])
                row["root_end_to_true_carina_mm"] = round(float(np.linalg.norm(
                    end0 - np.array(row["reference"]["carina"]))) / MM, 1)
            if case == "original":
                ref = row.get("reference")
                if ref is None:
                    print(f"{name}: the original mask failed; its perturbations are skipped")
                    rows.append(row)
                    break
            rows.append(row)
            print({k: v for k, v in row.items() if k != "reference"}, flush=True)
    write_tables(rows, args)


def write_tables(rows: list[dict], args) -> None:
    lines = ["# Real trees, perturbed: the anatomy chain on trees it was not tuned on (issue #18)", "",
             "`python benchmarks/real_tree_robustness.py " + " ".join(sys.argv[1:]) + f"` on {platform.node()}, "
             f"load average at the end {os.getloadavg()[0]:.1f}.  Each case: `room run --until trajectory` "
             "(default config) on the perturbed mask; rendered cases also simulate + render 10 frames.  "
             "start->trachea: the root's first point's distance from the original mask's trachea centreline; "
             "end->carina: the root's last point (first bifurcation) from the original's carina (its first "
             "bifurcation at which both children divide on; passing a terminal twig beside a dividing sibling: "
             "`reference()`); on an original row, its own root's end from that carina (0.0: the graph's first bifurcation "
             "is the carina; more: it stops at a terminal twig above it).", "",
             "| mask | case | shape | spacing mm | exit | root start->trachea mm | root end->carina mm | root mm | "
             "entry bif. | route mm | route gen. | tree gen. | failed stage: message | CPU s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if r.get("not_run"):
            lines.append(f"| {r['mask']} | {r['case']} | not run |  |  |  |  |  |  |  |  |  |  |  |")
            continue
        fail = f"{r.get('failed_stage')}: {r.get('message', '')}" if r["exit"] else (
            "rendered " + str(r.get("render")) if r.get("rendered") else "")
        lines.append(f"| {r['mask']} | {r['case']}{' (prev)' if r.get('previous') else ''} | "
                     f"{'x'.join(map(str, r['shape']))} | "
                     f"{'/'.join(f'{v:g}' for v in r['spacing_mm'])} | {r['exit']} | "
                     f"{r.get('root_start_to_true_trachea_mm', '')} | {r.get('root_end_to_true_carina_mm', '')} | "
                     f"{r.get('root_length_mm', '')} | {r.get('root_entry_bifurcation', '')} | "
                     f"{r.get('route_length_mm', '')} | {r.get('route_generation', '')} | {r.get('max_generation', '')} | "
                     f"{fail.replace('|', '/')} | {r['cpu_s']} |")
    ran = [r for r in rows if not r.get("not_run")]
    n_fail = sum(1 for r in ran if r["exit"])
    n_prev = sum(1 for r in ran if r.get("previous"))
    lines += ["", f"{len(ran)} cases, {n_fail} failed" + (f"; {len(rows) - len(ran)} not run" if len(ran) < len(rows)
                                                         else "")
              + (f"; {n_prev} rows '(prev)' from {args.previous} (not re-run here)." if n_prev else ".")]
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "real_tree_robustness.md").write_text("\n".join(lines) + "\n")
    (RESULTS / "real_tree_robustness.json").write_text(json.dumps(
        {"command": "python benchmarks/real_tree_robustness.py " + " ".join(sys.argv[1:]),
         "rows": [{k: v for k, v in r.items() if k != "reference"} for r in rows]}, indent=1) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
