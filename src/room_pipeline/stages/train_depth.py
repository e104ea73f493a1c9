"""Stage `train_depth`: the fine-tuning experiment of the paper's Table III, run once for the training patient.

The training patient is ``depth.cnn.checkpoint_patient``; the experiment (pretraining, fine-tuning, the held-out
and SimCol evaluations; ``other_anatomy`` comes from `evaluate_depth` via `tables`) is described in
:mod:`room_pipeline.depth.finetune`, which runs it.

Writes ``<output_dir>/evaluation/<patient>/depth_finetune.json`` (read by `tables`; its timings are in
``metrics/train_depth.timing.json``) and
``<patient>/depth_model/{pretrained.pt, finetuned.pt, training.json,
training_log.csv, train_mean_depth.npy}`` (the last: mean ground-truth depth of the
training frames, metres, for Table II's ``train_mean`` baseline) and ``<patient>/metrics/train_depth.json`` =
``{"datasets": {name: {"available", "reason", "source", "before", "after",
"n_frames"}}, "training": {...provenance, times, losses...}}``.  Without torch
the stage still succeeds: ``depth_model/`` then holds only ``training.json``
and every dataset says why there are no numbers.
"""
from __future__ import annotations

import os
import time

from omegaconf import DictConfig

from ..config.compose import section
from ..depth.baselines import TRAIN_MEAN_FILE
from ..depth.cnn import checkpoint_path, require_torch
from ..depth.estimators import DepthParams
from ..depth.finetune import (DEFINITION, finetune, finetune_datasets, finish_training_record, log_csv, npy_bytes,
                              train_mean_depth, training_frames, training_record, unavailable)
from ..errors import BackendUnavailable
from ..evaluate.allocator import keep_freed_memory
from ..io.atomic import write_bytes, write_json, write_text
from .common import StageTimer, _finite, metadata, patient_paths, round_floats, without_timings, write_metrics


def outputs(cfg: DictConfig, patient: str) -> list:
    paths = patient_paths(cfg, patient)
    return [paths.depth_model, paths.depth_finetune, paths.stage_metrics("train_depth")]


def run(cfg: DictConfig, patient: str) -> dict:
    p = DepthParams.from_dict(section(cfg, "depth"))
    paths = patient_paths(cfg, patient)
    model_dir = paths.depth_model
    keep_freed_memory()          # full-frame temporaries: no page-fault churn (evaluate/allocator.py)
    cpu0 = time.process_time()
    with StageTimer() as timer:
        sequences = [(str(s), paths.sequence(s)) for s in cfg.get("sequences") or []]
        train_samples, held, sources = training_frames(patient, sequences, p)
        datasets = finetune_datasets(patient, p, held)
        # the image-blind train_mean baseline of Table II (evaluate_depth never scores it on this patient)
        write_bytes(model_dir / TRAIN_MEAN_FILE, npy_bytes(train_mean_depth(train_samples, p.valid_range_m)))
        training = training_record(p, sources)
        try:
            torch = require_torch()
        except BackendUnavailable as exc:
            training.update(available=False, reason=str(exc))
            results = {name: unavailable(d, str(exc)) for name, d in datasets.items()}
            for which in ("pretrained", "finetuned"):            # no stale weights next to a failed run
                checkpoint_path(cfg.output_dir, patient, which).unlink(missing_ok=True)
            write_json(paths.depth_training, _finite(training))
            write_json(paths.depth_finetune, without_timings({"datasets": results, "definition": DEFINITION})[0])
            write_metrics(paths, "train_depth", {"datasets": results, "training": training})
            return {"available": False, "reason": str(exc)}
        ft = finetune(p, train_samples, datasets, lambda which: checkpoint_path(cfg.output_dir, patient, which),
                      {"patient": patient, "seed": p.train.seed, "torch": str(torch.__version__)})
    checkpoints = {w: {"path": os.path.relpath(checkpoint_path(cfg.output_dir, patient, w), cfg.output_dir),
                       "sha256": h} for w, h in ft.sha.items()}
    training = round_floats(finish_training_record(training, ft, p, str(torch.__version__), checkpoints,
                                                   timer.wall_s, time.process_time() - cpu0), 6)
    # timings go to the metrics only: the data files are the same bytes for the same data and seed
    write_json(paths.depth_training,
               _finite({**{k: v for k, v in training.items() if k != "times_s"},
                        "metadata": metadata("train_depth", patient, cfg, ("depth",))}))
    write_text(paths.depth_training_log, log_csv(ft.pre_losses, ft.ft_losses))
    results = ft.results
    doc = {"datasets": {k: round_floats(v, 6) if isinstance(v, dict) else v for k, v in results.items()},
           "training": training}
    # the tables' input (no timings: same data and seed -> same bytes; they are in train_depth.timing.json under
    # the same "datasets" keys, room_pipeline.io.metrics.read_with_timings)
    write_json(paths.depth_finetune, without_timings({"datasets": doc["datasets"], "definition": DEFINITION})[0])
    write_metrics(paths, "train_depth", doc)
    return {"available": True, "pretrain_s": round(ft.times_s["pretrain"], 2),
            "finetune_s": round(ft.times_s["finetune"], 2), "wall_time_s": round(timer.wall_s, 3),
            **{f"{k}_AbsRel_{w}": round(v[w]["AbsRel"], 4) for k, v in results.items() if v["available"]
               for w in ("before", "after")}}
