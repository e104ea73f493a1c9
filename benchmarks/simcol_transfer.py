"""Why does fine-tuning on ROOM phantom frames make the depth CNN worse on SimCol (Table III)?

    PYTHONPATH=src .venv/bin/python benchmarks/simcol_transfer.py [--data data/output] [--patient patient_000]

Needs the default run's ``train_depth`` outputs (``<data>/<patient>/depth_model/{pretrained,finetuned}.pt``
and ``train_mean_depth.npy``) and the SimCol pairs of ``depth.train.simcol_dir`` (every pair there: the only
external depth pairs in ../shared/data).  On those pairs, median-scaled per set like Table III, it scores

* the CNN before and after fine-tuning, and the image-blind baselines (constant, the phantom's mean training
  depth image, the straight-tube prior);
* how much each CNN's log-depth map follows the SimCol ground truth and how much it follows the phantom's
  mean training depth image (Pearson r over valid pixels, mean over frames): a network that has learned
  the phantom's average layout answers the same layout on a colon;
* the image statistics the network sees (mean sRGB, mean luma) of SimCol and of the training frames.

Writes benchmarks/results/simcol_transfer.{json,md}.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from room_pipeline.config.compose import compose  # noqa: E402
from room_pipeline.depth.baselines import TRAIN_MEAN_FILE, ConstantDepth, TrainMean, TubePrior  # noqa: E402
from room_pipeline.depth.cnn import CNNEstimator, checkpoint_path, simcol_samples  # noqa: E402
from room_pipeline.depth.estimators import DepthParams, Frame, evaluate, sequence_samples  # noqa: E402
from room_pipeline.depth.metrics import fit_to_shape  # noqa: E402
from room_pipeline.paths import PatientPaths  # noqa: E402


def corr(a: np.ndarray, b: np.ndarray, m: np.ndarray) -> float:
    x, y = np.log(a[m]), np.log(b[m])
    if x.size < 10 or x.std() == 0 or y.std() == 0:
        return float("nan")
    return float(np.corrcoef(x, y)[0, 1])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--data", default="data/output")
    ap.add_argument("--patient", default="patient_000")
    args = ap.parse_args()
    cfg = compose()
    p = DepthParams.from_dict(dict(cfg.depth))
    data = Path(args.data)
    samples = simcol_samples(ROOT / p.train.simcol_dir if not Path(p.train.simcol_dir).is_absolute()
                             else p.train.simcol_dir)
    ests = {"cnn_before": CNNEstimator.load("cnn_before", checkpoint_path(data, args.patient, "pretrained"), p.cnn),
            "cnn_after": CNNEstimator.load("cnn_after", checkpoint_path(data, args.patient, "finetuned"), p.cnn),
            "constant": ConstantDepth("constant"), "tube_prior": TubePrior("tube_prior"),
            "train_mean": TrainMean("train_mean", PatientPaths(data, args.patient).depth_model / TRAIN_MEAN_FILE)}
    t0, c0 = time.perf_counter(), time.process_time()
    rows = evaluate(ests, samples, p.valid_range_m, also_median=False, force_median=True)
    scores = {k: {m: r.summary()[m] for m in ("L1_mm", "AbsRel", "RMSE_mm", "delta1")} for k, r in rows.items()}
    lo, hi = p.valid_range_m
    follow = {k: {"r_gt": [], "r_train_mean": []} for k in ("cnn_before", "cnn_after")}
    for s in samples:
        gt, rgb = s.load_gt(), s.load_rgb()
        m = np.isfinite(gt) & (gt >= lo) & (gt <= hi)
        tm = fit_to_shape(ests["train_mean"].predict(Frame(rgb, s.camera)), gt.shape, True)
        m &= np.isfinite(tm) & (tm > 0)
        for k in follow:
            pr = fit_to_shape(ests[k].predict(Frame(rgb, s.camera)), gt.shape, True)
            mm = m & np.isfinite(pr) & (pr > 0)
            follow[k]["r_gt"].append(corr(pr, gt, mm))
            follow[k]["r_train_mean"].append(corr(pr, tm, mm))
    follow = {k: {q: float(np.nanmean(v)) for q, v in d.items()} for k, d in follow.items()}
    train = sequence_samples(data / args.patient / "sequence_000", p.input, stride=20)
    stats = {}
    for name, ss in (("simcol", samples), (f"{args.patient} training frames ({p.input}, every 20th)", train)):
        rgbs = np.stack([s.load_rgb().reshape(-1, 3).mean(0) for s in ss])
        stats[name] = {"mean_srgb": np.round(rgbs.mean(0), 1).tolist(),
                       "mean_luma": round(float((rgbs @ [0.299, 0.587, 0.114]).mean()), 1), "frames": len(ss)}
    out = {"simcol_pairs": len(samples), "scores_median_scaled": scores, "log_depth_correlation": follow,
           "image_stats": stats, "cpu_s": round(time.process_time() - c0, 2),
           "wall_s": round(time.perf_counter() - t0, 2), "data": str(data), "patient": args.patient,
           "units": {"L1_mm, RMSE_mm": "mm", "delta1": "fraction", "r": "Pearson r of log depth, mean over frames"}}
    res = ROOT / "benchmarks" / "results"
    (res / "simcol_transfer.json").write_text(json.dumps(out, indent=2) + "\n")
    md = ["# SimCol transfer of the fine-tuned depth CNN (benchmarks/simcol_transfer.py)", "",
          f"{len(samples)} SimCol RGB-D pairs, median-scaled once over the set (as in Table III).", "",
          "| row | L1 (mm) | AbsRel | RMSE (mm) | delta1 (%) |", "|---|---:|---:|---:|---:|"]
    for k, v in scores.items():
        md.append(f"| {k} | {v['L1_mm']:.2f} | {v['AbsRel']:.3f} | {v['RMSE_mm']:.2f} | {100 * v['delta1']:.1f} |")
    md += ["", "| CNN | r(log pred, log GT) | r(log pred, log phantom mean depth image) |", "|---|---:|---:|"]
    for k, v in follow.items():
        md.append(f"| {k} | {v['r_gt']:.3f} | {v['r_train_mean']:.3f} |")
    md += ["", "| images | mean sRGB | mean luma | frames |", "|---|---|---:|---:|"]
    for k, v in stats.items():
        md.append(f"| {k} | {v['mean_srgb']} | {v['mean_luma']} | {v['frames']} |")
    md += ["", f"CPU {out['cpu_s']} s, wall {out['wall_s']} s."]
    (res / "simcol_transfer.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
