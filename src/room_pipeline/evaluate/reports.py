"""The report tables of a dataset (paper Tables I-III): parameters, inputs gathered from the evaluation files.

:func:`read_pose_files` and :func:`read_depth_files` read the per-sequence ``pose.json`` / ``depth.json``
and the per-patient ``depth_finetune.json`` that exist (a missing file gives a "not run" row, never an
error), each with the timings its stage keeps in ``metrics/<stage>.timing.json`` merged back (the tables'
time columns; :func:`room_pipeline.io.metrics.read_with_timings`); :func:`other_anatomy_records` builds Table III's ``other_anatomy`` rows from the `evaluate_depth`
records of the patients other than ``depth.cnn.checkpoint_patient`` (or those of
``depth.train.eval_patients``): ``cnn_pretrained`` is "before", ``cnn`` (the checkpoint fine-tuned on the
training patient) is "after", both median-scaled per sequence like the other Table III sets; mean over each
patient's sequences, then over patients.  :func:`build_tables` makes the tables
(:mod:`room_pipeline.evaluate.tables`) and :func:`report_files` the text of every file of ``reports/``
(same inputs -> same bytes: no time stamps).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Mapping

from ..catalog import SPEED_ACCURACY_CSV, TABLES_METRICS_JSON
from ..config.compose import phantom_entry
from ..config.params import params_from_dict
from ..depth.cnn import CNNParams, TrainParams
from ..errors import ConfigError, InputError
from ..io.jsondoc import finite, round_floats
from ..io.metrics import read_with_timings
from ..paths import PatientPaths
from . import paper
from .tables import FINETUNE_COLUMNS, depth_table, finetune_table, mean_records, pose_table, speed_accuracy_csv


TABLES = ("table_1_pose", "table_2_depth", "table_3_finetune")


@dataclasses.dataclass(frozen=True)
class TablesParams:
    """Keys of ``evaluate.tables`` in ``conf/evaluate/default.yaml``."""

    output_dir: str = "reports"
    digits: int = 2

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None) -> "TablesParams":
        p = params_from_dict(cls, d, "evaluate.tables")
        if not 0 <= p.digits <= 6 or not p.output_dir:
            raise ConfigError("evaluate.tables: 0 <= digits <= 6 and a non-empty output_dir required")
        return p


def _read(path: Path, timing_file: Path) -> Any:
    """An evaluation file with its stage's timings (``timing_file``, when present) merged back."""
    try:
        return read_with_timings(path, timing_file)
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"{path} or {timing_file}: not readable JSON ({exc})") from None


def eval_patients(cfg: Mapping[str, Any], patient: str, chosen) -> list[tuple[str, str]]:
    """[(patient, description)] of the other-anatomy set: ``chosen`` (``depth.train.eval_patients``) or, when
    null, the configured patients built from real airway masks, else every other configured patient."""
    patients = dict(cfg.get("patients") or {})
    phantoms = dict(cfg.get("phantoms") or {})

    def describe(q: str) -> str:
        if q in phantoms:
            return f"phantom seed {phantom_entry(cfg, q).seed}"
        kind = (patients.get(q) or {}).get("kind", "?")
        return "real airway mask (shared data)" if kind == "mask" else f"patient of kind {kind}"

    if chosen is not None:
        return [(str(q), describe(str(q))) for q in chosen if str(q) != patient]
    others = [q for q in patients if q != patient]
    masks = [q for q in others if (patients.get(q) or {}).get("kind") == "mask"]
    return [(q, describe(q)) for q in (masks or others)]


def other_anatomy_records(cfg: Mapping[str, Any], depth_by_patient: Mapping[str, list[dict]]) -> list[dict]:
    """Fine-tuning records (``{"datasets": {"other_anatomy": ...}}``, one per other patient) built from the
    `evaluate_depth` docs of the patients other than the training patient (module docstring)."""
    dep = cfg.get("depth") or {}
    train_patient = params_from_dict(CNNParams, dep.get("cnn"), "depth.cnn").checkpoint_patient
    chosen = TrainParams.from_dict(dep.get("train")).eval_patients
    others = eval_patients(cfg, train_patient, None if chosen is None else list(chosen))
    keys = [k for k, _, _ in FINETUNE_COLUMNS]
    if not others:
        return [{"datasets": {"other_anatomy": {
            "available": False, "source": "none", "before": None, "after": None,
            "reason": f"no other patient configured besides the training patient {train_patient} (add a second "
                      "phantom seed or patients built from real airway masks)"}}}]
    out, missing = [], []
    for q, desc in others:
        docs = depth_by_patient.get(q) or []
        phases = {}
        for phase, method in (("before", "cnn_pretrained"), ("after", "cnn")):
            recs = [(d.get("methods") or {}).get(method) or {} for d in docs]
            recs = [r for r in recs if r.get("available")]
            if recs:
                phases[phase] = {**mean_records(recs, keys), "n_frames": sum(int(r.get("n_frames") or 0) for r in recs),
                                 "sequences": len(recs)}
        if len(phases) == 2:
            out.append({"datasets": {"other_anatomy": {
                "available": True, "reason": None, "source": f"{q} ({desc}): evaluate_depth rows cnn_pretrained "
                                                           "(before) and cnn (after)", **phases}}})
        else:
            missing.append(f"{q}: no evaluate_depth record with cnn and cnn_pretrained")
    if not out:
        return [{"datasets": {"other_anatomy": {"available": False, "source": ", ".join(q for q, _ in others),
                                                "before": None, "after": None, "reason": "; ".join(missing)}}}]
    return out


def read_depth_files(output_dir: Path, patients: list[str], sequences: list[str]
                     ) -> tuple[dict[str, list[dict]], list[dict]]:
    """The depth stages' records: ({patient: its per-sequence ``evaluation/depth.json`` docs}, per-patient
    ``depth_finetune.json`` docs).

    The one place that knows the other stages' file layout and format (adjust here if it changes):
    ``depth.json`` = {"methods": {name: {"available", "reason", "L1_mm", "AbsRel", "RMSE_mm", "delta1", ...,
    "n_frames", "seconds_per_frame"}}, "units": {...}}; ``depth_finetune.json`` = {"datasets": {name:
    {"before": {metrics}, "after": {metrics}}}}.  ``delta1`` is taken as a fraction unless ``units.delta1``
    mentions %, in which case it is converted to a fraction here.  The fine-tuning record is
    ``<output_dir>/evaluation/<patient>/depth_finetune.json`` (written by `train_depth`, with per-dataset
    ``available`` / ``reason``).
    """
    depth: dict[str, list[dict]] = {}
    finetune = []
    for pat in patients:
        paths = PatientPaths(output_dir, pat)
        for seq in sequences:
            f = paths.eval(seq).depth
            if f.is_file():
                doc = _read(f, paths.stage_timings("evaluate_depth", seq))
                if "%" in str((doc.get("units") or {}).get("delta1", "")):
                    for rec in (doc.get("methods") or {}).values():
                        for k in ("delta1", "delta2", "delta3"):
                            if isinstance(rec.get(k), (int, float)):
                                rec[k] = rec[k] / 100.0
                depth.setdefault(pat, []).append(doc)
        f = paths.depth_finetune      # written by train_depth
        if f.is_file():
            finetune.append(_read(f, paths.stage_timings("train_depth")))
    return depth, finetune


def read_pose_files(output_dir: Path, patients: list[str], sequences: list[str]) -> list[dict]:
    """Per-sequence ``evaluation/pose.json`` docs that exist."""
    docs = []
    for pat in patients:
        for seq in sequences:
            paths = PatientPaths(output_dir, pat)
            f = paths.eval(seq).pose
            if f.is_file():
                docs.append(_read(f, paths.stage_timings("evaluate_pose", seq)))
    return docs


def build_tables(pose_docs: list[dict], depth_docs: list[dict], finetune_docs: list[dict], digits: int,
                 pose_order: tuple = ()) -> dict:
    """{table name: Table}."""
    return {"table_1_pose": pose_table(pose_docs, digits, pose_order),
            "table_2_depth": depth_table(depth_docs, digits),
            "table_3_finetune": finetune_table(finetune_docs, digits)}


def report_files(tables: dict, counts: dict) -> dict[str, str | dict]:
    """{file name in ``reports/``: its text, or for ``metrics.json`` its JSON document}: each table as
    Markdown, LaTeX and CSV, ``pose_speed_accuracy.csv`` and ``metrics.json`` (the tables' numbers)."""
    files: dict[str, str | dict] = {}
    for name, t in tables.items():
        files[f"{name}.md"] = t.to_markdown()
        files[f"{name}.tex"] = t.to_latex()
        files[f"{name}.csv"] = t.to_csv()
    files[SPEED_ACCURACY_CSV] = speed_accuracy_csv(tables["table_1_pose"])
    files[TABLES_METRICS_JSON] = finite(round_floats({
        **{name: t.numbers for name, t in tables.items()}, "inputs": counts,
        "units": {"RRA@5, RTA@5, AUC@30, registration_rate, delta1": "fractions in [0, 1]",
                  "ate_rmse_mm, L1_mm, RMSE_mm": "mm", "seconds_per_frame": "s"},
        "paper": {"source": paper.SOURCE, "retrieved": {k: v["retrieved"] for k, v in paper.TABLES.items()}}}, 6))
    return files
