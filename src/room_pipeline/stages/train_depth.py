"""Stage `train_depth`: the fine-tuning experiment of the paper's Table III, run once for the training patient.

The training patient is ``depth.cnn.checkpoint_patient`` (a phantom patient).
Pretrains the small U-Net of :mod:`room_pipeline.depth.cnn` on generic
synthetic tube scenes ("before"), fine-tunes it on that patient's rendered
sequences minus a held-out tail of each ("after"), and evaluates both,
median-scaled per sequence, on

``phantom_held_out``  the held-out tails (same anatomy, frames never trained on);
``simcol``            the SimCol RGB-D pairs of ``depth.train.simcol_dir`` (external set).

The third set of Table III, ``other_anatomy`` (the other configured patients:
real airway masks or other phantom seeds), is measured by `evaluate_depth` on
those patients' sequences with these two checkpoints (rows ``cnn_pretrained``
and ``cnn``) and gathered by `tables`: DVC then orders every read correctly,
whatever patients a configuration lists.

Writes ``<output_dir>/evaluation/<patient>/depth_finetune.json`` (read by `tables`) and
``<patient>/depth_model/{pretrained.pt, finetuned.pt, training.json,
training_log.csv, train_mean_depth.npy}`` (the last: mean ground-truth depth of the
training frames, metres, for Table II's ``train_mean`` baseline) and ``<patient>/metrics/train_depth.json`` =
``{"datasets": {name: {"available", "reason", "source", "before", "after",
"n_frames"}}, "training": {...provenance, times, losses...}}``.  Without torch
the stage still succeeds: ``depth_model/`` then holds only ``training.json``
and every dataset says why there are no numbers.
"""
from __future__ import annotations

import copy
import dataclasses
import io
import os
import platform
import time
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from ..config.compose import section
from ..depth.cnn import (CNNEstimator, build_model, checkpoint_path, dataset_from_samples, deterministic_torch,
                         n_parameters, require_torch, save_checkpoint, simcol_samples, synthetic_tube_set, timed,
                         train_steps)
from ..depth.estimators import DepthParams, evaluate, sequence_samples
from ..errors import BackendUnavailable, InputError
from ..evaluate.allocator import keep_freed_memory
from ..depth.baselines import TRAIN_MEAN_FILE
from ..io.atomic import write_bytes, write_json, write_text
from .common import StageTimer, _finite, metadata, patient_paths, round_floats, write_metrics

DEFINITION = {
    "before": "U-Net pretrained on generic synthetic tube scenes (random bent, bulging tubes, tissue colours, "
              "exposures, fields of view; the project's fast renderer), never on an airway tree",
    "after": "the same network fine-tuned on the training patient's ROOM phantom sequences (held-out tails excluded)",
    "scaling": "median, once per sequence (median(gt) / median(pred))",
}


def outputs(cfg: DictConfig, patient: str) -> list:
    paths = patient_paths(cfg, patient)
    return [paths.depth_model, paths.depth_finetune, paths.metrics("train_depth")]


def split_indices(n: int, holdout_fraction: float, gap: int, train_stride: int, eval_stride: int
                  ) -> tuple[list[int], list[int]]:
    """(training indices, held-out indices) of an n-frame sequence: the last ``holdout_fraction`` is held out,
    and ``gap`` frames before it are used for neither (neighbouring frames look alike)."""
    n_hold = int(round(n * holdout_fraction))
    start_hold = n - n_hold
    train = list(range(0, max(start_hold - gap, 0), train_stride)) if n_hold else list(range(0, n, train_stride))
    held = list(range(start_hold, n, eval_stride)) if n_hold else []
    return train, held


def _datasets(cfg: DictConfig, patient: str, p: DepthParams, held: list) -> dict:
    """name -> {"samples": list | None, "reason": str | None, "source": str}."""
    tp = p.train
    out: dict = {}
    out["phantom_held_out"] = {
        "samples": held or None, "source": f"{patient}: last {tp.holdout_fraction:.0%} of each sequence, "
                                          f"every {tp.eval_stride}th frame",
        "reason": None if held else "no held-out frames (depth.train.holdout_fraction is 0 or sequences too short)"}
    simcol = Path(tp.simcol_dir) if tp.simcol_dir else None
    if simcol is None:
        out["simcol"] = {"samples": None, "reason": "depth.train.simcol_dir is not set", "source": "SimCol3D"}
    elif not simcol.is_dir():
        out["simcol"] = {"samples": None, "reason": f"SimCol sample folder not found: {simcol}",
                         "source": f"SimCol3D pairs in {simcol}"}
    else:
        sc = simcol_samples(simcol)
        out["simcol"] = {"samples": sc or None, "reason": None if sc else f"no FrameBuffer/Depth pairs in {simcol}",
                         "source": f"SimCol3D synthetic colonoscopy, {len(sc)} RGB-D pairs in {simcol} "
                                   "(depth_cm = value / 255 / 256 * 20)"}
    return out


def train_mean_depth(samples: list, valid_range_m: tuple[float, float], stride: int = 5) -> np.ndarray:
    """Mean ground-truth planar depth image (metres, float32) over every ``stride``-th training frame, valid
    pixels only (NaN where no frame has one): the ``train_mean`` trivial baseline of Table II."""
    lo, hi = valid_range_m
    acc = cnt = None
    for s in samples[::max(1, stride)]:
        gt = np.asarray(s.load_gt(), dtype=np.float64)
        ok = np.isfinite(gt) & (gt >= lo) & (gt <= hi)
        if acc is None:
            acc, cnt = np.zeros(gt.shape), np.zeros(gt.shape)
        if gt.shape != acc.shape:
            continue
        acc += np.where(ok, gt, 0.0)
        cnt += ok
    if acc is None:
        raise InputError("train_mean_depth: no training frames")
    return np.where(cnt > 0, acc / np.maximum(cnt, 1), np.nan).astype(np.float32)


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def _log_csv(pre: list, ft: list) -> str:
    """Training log for DVC plots: global step (pretraining then fine-tuning), phase, phase step, loss."""
    buf = io.StringIO()
    buf.write("step,phase,phase_step,loss\n")
    k = 0
    for phase, losses in (("pretrain", pre), ("finetune", ft)):
        for i, v in enumerate(losses):
            buf.write(f"{k},{phase},{i},{v:.6g}\n")
            k += 1
    return buf.getvalue()


def run(cfg: DictConfig, patient: str) -> dict:
    p = DepthParams.from_dict(section(cfg, "depth"))
    tp, cp = p.train, p.cnn
    paths = patient_paths(cfg, patient)
    model_dir = paths.depth_model
    rng_m = p.valid_range_m
    keep_freed_memory()          # full-frame temporaries: no page-fault churn (evaluate/allocator.py)
    cpu0 = time.process_time()
    with StageTimer() as timer:
        train_samples, held, sources = [], [], []
        for s in cfg.get("sequences") or []:
            all_frames = sequence_samples(paths.sequence(s), p.input, group=f"{patient}/{s}")
            tr, ho = split_indices(len(all_frames), tp.holdout_fraction, tp.holdout_gap_frames, tp.train_stride,
                                   tp.eval_stride)
            train_samples += [all_frames[i] for i in tr]
            held += [all_frames[i] for i in ho]
            sources.append({"sequence": f"{patient}/{s}", "frames": len(all_frames), "train_frames": len(tr),
                            "train_range": [all_frames[tr[0]].name, all_frames[tr[-1]].name] if tr else None,
                            "held_out_frames": len(ho),
                            "held_out_range": [all_frames[ho[0]].name, all_frames[ho[-1]].name] if ho else None})
        if not train_samples:
            raise InputError(f"{patient}: no training frames in sequences {list(cfg.get('sequences') or [])}")
        datasets = _datasets(cfg, patient, p, held)
        # the image-blind train_mean baseline of Table II (evaluate_depth never scores it on this patient)
        write_bytes(model_dir / TRAIN_MEAN_FILE, _npy_bytes(train_mean_depth(train_samples, rng_m)))
        training: dict = {"definition": DEFINITION, "seed": tp.seed, "threads": cp.threads,
                          "params": {"cnn": dataclasses.asdict(cp), "train": dataclasses.asdict(tp)},
                          "input": p.input, "valid_range_mm": [float(x) for x in p.valid_range_mm],
                          "training_sequences": sources, "host": {"machine": platform.machine(),
                                                                 "cpu_count": os.cpu_count()}}
        try:
            torch = require_torch()
        except BackendUnavailable as exc:
            training.update(available=False, reason=str(exc))
            results = {name: {"available": False, "reason": str(exc), "source": d["source"], "before": None,
                              "after": None, "n_frames": 0} for name, d in datasets.items()}
            for which in ("pretrained", "finetuned"):            # no stale weights next to a failed run
                checkpoint_path(cfg.output_dir, patient, which).unlink(missing_ok=True)
            write_json(model_dir / "training.json", _finite(training))
            write_json(paths.depth_finetune,
                       _finite({"datasets": results, "definition": DEFINITION}))
            write_metrics(paths, "train_depth", {"datasets": results, "training": training})
            return {"available": False, "reason": str(exc)}
        size = cp.input_size
        with deterministic_torch(tp.seed, cp.threads):
            syn, t_syn = timed(lambda: synthetic_tube_set(tp.pretrain_scenes, tp.pretrain_views, size, tp.seed, rng_m))
            model = build_model(cp.channels)
            pre_losses, t_pre = timed(lambda: train_steps(model, syn, tp.pretrain_steps, tp.pretrain_learning_rate,
                                                          tp.batch_size, tp.seed, tp.si_lambda))
            ft_data, t_data = timed(lambda: dataset_from_samples(train_samples, size, rng_m))
            finetuned = copy.deepcopy(model)
            ft_losses, t_ft = timed(lambda: train_steps(finetuned, ft_data, tp.finetune_steps,
                                                        tp.finetune_learning_rate, tp.batch_size, tp.seed + 1,
                                                        tp.si_lambda))
        meta = {"patient": patient, "seed": tp.seed, "torch": str(torch.__version__)}
        sha = {which: save_checkpoint(checkpoint_path(cfg.output_dir, patient, which), m, cp.channels, size,
                                      {**meta, "which": which})
               for which, m in (("pretrained", model), ("finetuned", finetuned))}
        info = {"input_size": size, "channels": list(cp.channels)}
        ests = {"before": CNNEstimator("before", model, info, cp.inference_threads),
                "after": CNNEstimator("after", finetuned, info, cp.inference_threads)}
        results: dict = {}
        t_eval = 0.0
        for name, d in datasets.items():
            if d["samples"] is None:
                results[name] = {"available": False, "reason": d["reason"], "source": d["source"], "before": None,
                                 "after": None, "n_frames": 0}
                continue
            rows, dt = timed(lambda: evaluate(ests, d["samples"], rng_m, also_median=False, force_median=True))
            t_eval += dt
            results[name] = {"available": True, "reason": d.get("missing") and "; ".join(d["missing"]),
                             "source": d["source"], "before": rows["before"].summary(),
                             "after": rows["after"].summary(), "n_frames": len(d["samples"]),
                             "groups": sorted({s.group for s in d["samples"]})}
    training.update(
        available=True, reason=None, torch=str(torch.__version__), n_parameters=n_parameters(model),
        pretrain={"frames": len(syn), "source": syn.sources[0], "steps": tp.pretrain_steps,
                  "loss_first": pre_losses[0] if pre_losses else None,
                  "loss_last_10_mean": float(np.mean(pre_losses[-10:])) if pre_losses else None},
        finetune={"frames": len(ft_data), "steps": tp.finetune_steps,
                  "loss_first": ft_losses[0] if ft_losses else None,
                  "loss_last_10_mean": float(np.mean(ft_losses[-10:])) if ft_losses else None},
        checkpoints={w: {"path": os.path.relpath(checkpoint_path(cfg.output_dir, patient, w), cfg.output_dir),
                         "sha256": h}
                     for w, h in sha.items()},
        times_s={"synthetic_data": t_syn, "pretrain": t_pre, "finetune_data": t_data, "finetune": t_ft,
                 "evaluation": t_eval, "total": timer.wall_s, "cpu_total": time.process_time() - cpu0})
    training = round_floats(training, 6)
    # timings go to the metrics only: the data files are the same bytes for the same data and seed
    write_json(model_dir / "training.json",
               _finite({**{k: v for k, v in training.items() if k != "times_s"},
                        "metadata": metadata("train_depth", patient, cfg, ("depth",))}))
    write_text(model_dir / "training_log.csv", _log_csv(pre_losses, ft_losses))
    doc = {"datasets": {k: round_floats(v, 6) if isinstance(v, dict) else v for k, v in results.items()},
           "training": training}
    # the tables' input (no timings: same data and seed -> same bytes)
    write_json(paths.depth_finetune, _finite({"datasets": doc["datasets"],
                                                                       "definition": DEFINITION}))
    write_metrics(paths, "train_depth", doc)
    return {"available": True, "pretrain_s": round(t_pre, 2), "finetune_s": round(t_ft, 2),
            "wall_time_s": round(timer.wall_s, 3),
            **{f"{k}_AbsRel_{w}": round(v[w]["AbsRel"], 4) for k, v in results.items() if v["available"]
               for w in ("before", "after")}}
