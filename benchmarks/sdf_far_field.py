#!/usr/bin/env python3
"""Speed / memory / error of the SDF far-field knobs against the exact whole-volume feature transform.

``sdf.far_field_cell_mm: 0`` (reference) runs the feature transform on the whole volume; the default runs it on
the airway's bounding box grown by the band and ``far_field_margin_mm`` and looks the nearest band voxel up on
cells of ``far_field_cell_mm`` beyond.  On a real mask from ../shared/data (default: the AirQuant demo tree,
512x512x130) this prints, per setting, CPU time, the peak of numpy allocations (tracemalloc), the absolute
difference to the reference (mm) in the lumen, within 10 mm of the wall and everywhere, and, on 20,000 seeded
random voxels more than 10 mm from the wall, the overestimate of the true distance to the surface (taken as the
distance to the nearest of all band voxels' closest surface points, a dense sampling of the surface): both
far fields are distances to surface points, so both only overestimate.  Saves
benchmarks/results/sdf_far_field.{json,md}.

    python benchmarks/sdf_far_field.py [--mask PATH]
"""
from __future__ import annotations

import argparse
import json
import os
import time
import tracemalloc
from pathlib import Path

import numpy as np

from room_pipeline.anatomy.sdf import SdfParams, compute_sdf
from room_pipeline.anatomy.segment import validate_mask
from room_pipeline.io.volume import read_volume

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
DEFAULT = ROOT.parent / "shared/data/airway_masks/airquant_demo/github_demo_seg.nii.gz"
SETTINGS = [("reference (whole volume)", {"far_field_cell_mm": 0.0}),
            ("default: margin 10 mm, cells 2 mm", {}),
            ("margin 10 mm, cells 4 mm", {"far_field_cell_mm": 4.0}),
            ("margin 5 mm, cells 2 mm", {"far_field_margin_mm": 5.0}),
            ("margin 0 mm, cells 2 mm", {"far_field_margin_mm": 0.0})]


def _far_truth(mask, n: int = 20_000, seed: int = 0):
    """Distance (m) to the nearest surface sample for n random voxels > 10 mm from every band voxel."""
    from scipy import ndimage
    from scipy.spatial import cKDTree

    from room_pipeline.anatomy import sdf as S
    from room_pipeline.conventions import MM

    p = SdfParams()
    m = np.asarray(mask.data)
    h = mask.spacing / MM
    nb = max(1, int(np.ceil(p.band_mm / float(h.min()))))
    margin = np.full(3, nb + int(np.ceil(3 * p.sigma_voxels)) + 3)
    sub, lo = S._crop_pad(m, margin)
    boundary = ndimage.binary_dilation(sub) ^ ndimage.binary_erosion(sub)
    band = ndimage.binary_dilation(boundary, iterations=nb - 1) if nb > 1 else boundary
    pts = np.argwhere(band)
    feet_mm = (S._smooth_mc_feet(sub, h, p, pts.astype(np.float64)) / h + lo) * h
    kd = cKDTree(feet_mm)
    rng = np.random.default_rng(seed)
    cand = np.stack([rng.integers(0, s, 20 * n) for s in m.shape], axis=1)
    d, _ = kd.query(cand * h)
    far = cand[d > 10.0][:n]
    return kd.query(far * h)[0] * MM, far


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mask", default=str(DEFAULT))
    args = ap.parse_args()
    if not Path(args.mask).exists():
        print(f"skipped: {args.mask} not found")
        return
    mask = validate_mask(read_volume(args.mask))
    mask = mask.with_data(np.asarray(mask.data) > 0)
    truth, sample = _far_truth(mask)
    rows, ref = [], None
    for name, over in SETTINGS:
        tracemalloc.start()
        t0 = time.process_time()
        sdf = np.asarray(compute_sdf(mask, SdfParams(**over)).data)
        cpu = time.process_time() - t0
        peak = tracemalloc.get_traced_memory()[1] / 2 ** 20
        tracemalloc.stop()
        row = {"setting": name, "params": over, "cpu_s": round(cpu, 2), "peak_alloc_mb": round(peak, 1)}
        if ref is None:
            ref = sdf
        else:
            err = np.abs(sdf.astype(np.float64) - ref) * 1e3
            near = np.abs(ref) <= 10e-3
            row.update(max_err_lumen_mm=float(err[ref < 0].max()), max_err_within_10mm_mm=float(err[near].max()),
                       max_err_all_mm=float(err.max()), mean_err_all_mm=float(err.mean()),
                       max_rel_err_beyond_10mm=float((err[~near] / (np.abs(ref[~near]) * 1e3)).max())
                       if (~near).any() else 0.0)
        over_est = np.abs(sdf[tuple(sample.T)].astype(np.float64)) - truth
        row.update(far_overestimate_mean_mm=float(over_est.mean() * 1e3), far_overestimate_max_mm=float(over_est.max() * 1e3),
                   far_overestimate_max_rel=float((over_est / truth).max()))
        rows.append(row)
        print(json.dumps(row), flush=True)
    keys = ["cpu_s", "peak_alloc_mb", "max_err_lumen_mm", "max_err_within_10mm_mm", "max_err_all_mm",
            "mean_err_all_mm", "far_overestimate_mean_mm", "far_overestimate_max_mm", "far_overestimate_max_rel"]
    md = ["| setting | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
    for r in rows:
        md.append(f"| {r['setting']} | " + " | ".join(
            (f"{r[k]:.4g}" if isinstance(r.get(k), float) else str(r.get(k, "-"))) for k in keys) + " |")
    text = "\n".join(md) + f"\n\nmask {Path(args.mask).name}, shape {list(mask.shape)}; load average " \
                           f"{os.getloadavg()[0]:.1f} (CPU time, not wall, is the comparable figure)\n"
    print(text)
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "sdf_far_field.json").write_text(json.dumps({"mask": Path(args.mask).name, "rows": rows,
                                                            "command": "python benchmarks/sdf_far_field.py"},
                                                           indent=2) + "\n")
    (RESULTS / "sdf_far_field.md").write_text("# SDF far-field knobs vs the exact whole-volume transform\n\n"
                                              "`python benchmarks/sdf_far_field.py`\n\n" + text)


if __name__ == "__main__":
    main()
