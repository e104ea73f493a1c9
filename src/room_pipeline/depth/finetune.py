"""The depth CNN's fine-tuning experiment (paper Table III): frames, training, evaluation, records.

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

:func:`training_frames` splits each sequence into training frames and a held-out tail
(:func:`split_indices`); :func:`finetune_datasets` names the evaluation sets; :func:`finetune` pretrains,
fine-tunes, saves both checkpoints and evaluates them; :func:`training_record` and
:func:`finish_training_record` are the provenance the stage writes (``training.json``, metrics).
"""
from __future__ import annotations

import copy
import dataclasses
import io
import os
import platform
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..errors import InputError
from .cnn import (CNNEstimator, build_model, dataset_from_samples, deterministic_torch, n_parameters,
                  save_checkpoint, simcol_samples, synthetic_tube_set, timed, train_steps)
from .estimators import DepthParams, evaluate, sequence_samples

DEFINITION = {
    "before": "U-Net pretrained on generic synthetic tube scenes (random bent, bulging tubes, tissue colours, "
              "exposures, fields of view; the project's fast renderer), never on an airway tree",
    "after": "the same network fine-tuned on the training patient's ROOM phantom sequences (held-out tails excluded)",
    "scaling": "median, once per sequence (median(gt) / median(pred))",
}


def split_indices(n: int, holdout_fraction: float, gap: int, train_stride: int, eval_stride: int
                  ) -> tuple[list[int], list[int]]:
    """(training indices, held-out indices) of an n-frame sequence: the last ``holdout_fraction`` is held out,
    and ``gap`` frames before it are used for neither (neighbouring frames look alike)."""
    n_hold = int(round(n * holdout_fraction))
    start_hold = n - n_hold
    train = list(range(0, max(start_hold - gap, 0), train_stride)) if n_hold else list(range(0, n, train_stride))
    held = list(range(start_hold, n, eval_stride)) if n_hold else []
    return train, held


def finetune_datasets(patient: str, p: DepthParams, held: list) -> dict:
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


def npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a, allow_pickle=False)
    return buf.getvalue()


def log_csv(pre: list, ft: list) -> str:
    """Training log for DVC plots: global step (pretraining then fine-tuning), phase, phase step, loss."""
    buf = io.StringIO()
    buf.write("step,phase,phase_step,loss\n")
    k = 0
    for phase, losses in (("pretrain", pre), ("finetune", ft)):
        for i, v in enumerate(losses):
            buf.write(f"{k},{phase},{i},{v:.6g}\n")
            k += 1
    return buf.getvalue()


def training_frames(patient: str, sequences: list[tuple[str, Path]], p: DepthParams) -> tuple[list, list, list]:
    """(training samples, held-out samples, per-sequence provenance) of ``[(name, folder)]`` sequences; no
    training frame at all: InputError."""
    tp = p.train
    train_samples, held, sources = [], [], []
    for s, folder in sequences:
        all_frames = sequence_samples(folder, p.input, group=f"{patient}/{s}")
        tr, ho = split_indices(len(all_frames), tp.holdout_fraction, tp.holdout_gap_frames, tp.train_stride,
                               tp.eval_stride)
        train_samples += [all_frames[i] for i in tr]
        held += [all_frames[i] for i in ho]
        sources.append({"sequence": f"{patient}/{s}", "frames": len(all_frames), "train_frames": len(tr),
                        "train_range": [all_frames[tr[0]].name, all_frames[tr[-1]].name] if tr else None,
                        "held_out_frames": len(ho),
                        "held_out_range": [all_frames[ho[0]].name, all_frames[ho[-1]].name] if ho else None})
    if not train_samples:
        raise InputError(f"{patient}: no training frames in sequences {[s for s, _ in sequences]}")
    return train_samples, held, sources


def training_record(p: DepthParams, sources: list) -> dict:
    """The start of ``training.json``: definition, seed, threads, parameters, input and training sequences."""
    tp, cp = p.train, p.cnn
    return {"definition": DEFINITION, "seed": tp.seed, "threads": cp.threads,
            "params": {"cnn": dataclasses.asdict(cp), "train": dataclasses.asdict(tp)},
            "input": p.input, "valid_range_mm": [float(x) for x in p.valid_range_mm],
            "training_sequences": sources, "host": {"machine": platform.machine(), "cpu_count": os.cpu_count()}}


def unavailable(d: dict, reason: str) -> dict:
    """A dataset's row without numbers, saying why."""
    return {"available": False, "reason": reason, "source": d["source"], "before": None, "after": None,
            "n_frames": 0}


@dataclasses.dataclass
class Finetuned:
    """What :func:`finetune` made: the two networks, per-dataset results, losses, checkpoint sha256, times."""

    model: Any
    finetuned: Any
    syn: Any
    ft_data: Any
    results: dict
    pre_losses: list
    ft_losses: list
    sha: dict
    times_s: dict


def finetune(p: DepthParams, train_samples: list, datasets: dict, checkpoint: Callable[[str], Path],
             meta: dict) -> Finetuned:
    """Pretrain on synthetic tubes, fine-tune on ``train_samples`` (seeded, ``cnn.threads``), save both
    checkpoints at ``checkpoint(which)`` with provenance ``meta``, evaluate both median-scaled on ``datasets``."""
    tp, cp = p.train, p.cnn
    rng_m = p.valid_range_m
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
    sha = {which: save_checkpoint(checkpoint(which), m, cp.channels, size, {**meta, "which": which})
           for which, m in (("pretrained", model), ("finetuned", finetuned))}
    info = {"input_size": size, "channels": list(cp.channels)}
    ests = {"before": CNNEstimator("before", model, info, cp.inference_threads),
            "after": CNNEstimator("after", finetuned, info, cp.inference_threads)}
    results: dict = {}
    t_eval = 0.0
    for name, d in datasets.items():
        if d["samples"] is None:
            results[name] = unavailable(d, d["reason"])
            continue
        rows, dt = timed(lambda: evaluate(ests, d["samples"], rng_m, also_median=False, force_median=True))
        t_eval += dt
        results[name] = {"available": True, "reason": d.get("missing") and "; ".join(d["missing"]),
                         "source": d["source"], "before": rows["before"].summary(),
                         "after": rows["after"].summary(), "n_frames": len(d["samples"]),
                         "groups": sorted({s.group for s in d["samples"]})}
    times = {"synthetic_data": t_syn, "pretrain": t_pre, "finetune_data": t_data, "finetune": t_ft,
             "evaluation": t_eval}
    return Finetuned(model, finetuned, syn, ft_data, results, pre_losses, ft_losses, sha, times)


def finish_training_record(training: dict, ft: Finetuned, p: DepthParams, torch_version: str,
                           checkpoints: dict, total_s: float, cpu_total_s: float) -> dict:
    """``training`` completed after a run: parameters count, losses, checkpoints ({which: {path, sha256}}), times."""
    tp = p.train
    pre, fl = ft.pre_losses, ft.ft_losses
    training.update(
        available=True, reason=None, torch=torch_version, n_parameters=n_parameters(ft.model),
        pretrain={"frames": len(ft.syn), "source": ft.syn.sources[0], "steps": tp.pretrain_steps,
                  "loss_first": pre[0] if pre else None,
                  "loss_last_10_mean": float(np.mean(pre[-10:])) if pre else None},
        finetune={"frames": len(ft.ft_data), "steps": tp.finetune_steps,
                  "loss_first": fl[0] if fl else None,
                  "loss_last_10_mean": float(np.mean(fl[-10:])) if fl else None},
        checkpoints=checkpoints,
        times_s={**ft.times_s, "total": total_s, "cpu_total": cpu_total_s})
    return training
