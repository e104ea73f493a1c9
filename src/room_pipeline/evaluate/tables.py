"""The report tables (the ROOM paper's Tables I-III) from per-sequence evaluation records: pure functions.

Inputs are the parsed evaluation files (see :mod:`room_pipeline.evaluate.reports`
for where they live):

* pose records  -- ``evaluation/pose.json`` per sequence:
  ``{"methods": {name: {"available", "reason", "RRA@5", "RTA@5", "AUC@30",
  "registration_rate", "ate_rmse_mm", "seconds_per_frame", ...}}}``;
* depth records -- ``evaluation/depth.json`` per sequence (written by the depth
  stages): ``{"methods": {name: {"available", "reason", "L1_mm", "AbsRel",
  "RMSE_mm", "delta1", ..., "n_frames", "seconds_per_frame"}}, "units": {...}}``;
* fine-tuning records -- ``metrics/depth_finetune.json`` (or ``train_depth.json``) per patient:
  ``{"datasets": {name: {["available", "reason",] "before": {metrics} | null, "after": {metrics} | null}}}``.

Each table is the mean over the sequences (or patients) where a method ran,
with that count in its own column, the wall time per frame next to the
accuracy (speed against error), a status column saying why a row is empty
(unavailable + reason, not run), and the paper's published values in
separate columns headed "paper (published)" (:mod:`room_pipeline.evaluate.paper`).
Shares (RRA, RTA, AUC, registration, delta1) are stored as fractions and
printed as %, with the unit in the header.

:class:`Table` renders to Markdown, LaTeX and CSV deterministically: fixed
decimals, rows in a fixed order, no time stamps.
"""
from __future__ import annotations

import csv
import dataclasses
import io
import math
from typing import Any, Iterable, Mapping, Sequence

from . import paper

DASH = "-"

#: (key in the records, header, kind): kind "pct" = fraction printed as %, "num" = plain, "time" = seconds
POSE_COLUMNS = (("RRA@5", "RRA@5 (%)", "pct"), ("RTA@5", "RTA@5 (%)", "pct"), ("AUC@30", "AUC@30 (%)", "pct"),
                ("seg:trachea:AUC@30", "AUC@30 trachea (%)", "pct"),
                ("seg:bifurcations:AUC@30", "AUC@30 bifurcations (%)", "pct"),
                ("seg:distal:AUC@30", "AUC@30 distal (%)", "pct"),
                ("registration_rate", "Registered (%)", "pct"), ("ate_rmse_mm", "ATE (mm)", "num"),
                ("seconds_per_frame", "Time (s/frame)", "time"), ("cpu_seconds_per_frame", "CPU (s/frame)", "time"))
#: the scores a method must beat its trivial baselines on: key -> +1 (higher is better) / -1 (lower is better)
POSE_BETTER = {"RRA@5": 1, "RTA@5": 1, "AUC@30": 1}
DEPTH_BETTER = {"AbsRel": -1, "delta1": 1}
POSE_BASELINES = ("identity", "constant_forward")
DEPTH_BASELINES = ("constant", "train_mean", "tube_prior")
DEPTH_COLUMNS = (("L1_mm", "L1 (mm)", "num"), ("AbsRel", "AbsRel", "num"), ("RMSE_mm", "RMSE (mm)", "num"),
                 ("delta1", "delta1 (%)", "pct"), ("seconds_per_frame", "Time (s/frame)", "time"))
FINETUNE_COLUMNS = DEPTH_COLUMNS[:4]
#: why fine-tuning on airway frames can move SimCol either way (measured by benchmarks/simcol_transfer.py on the
#: checkpoints of df75c85's default run; the figures of the current run are the table's own simcol rows)
SIMCOL_WHY = ("Fine-tuning teaches the network part of the phantom airway's average depth layout, which colon views "
              "do not share: on df75c85's checkpoints (benchmarks/simcol_transfer.py) the Pearson r of its log depth "
              "with the phantom's mean training depth image rose from 0.67 to 0.76 on the SimCol frames while its r "
              "with the SimCol ground truth stayed 0.957 -> 0.954; how much that costs on SimCol changes with the "
              "renders it was fine-tuned on.")


def simcol_note(numbers: Mapping[str, Any]) -> str:
    """One sentence on what fine-tuning did to SimCol in *this* table (its simcol rows), then why it can hurt."""
    sc = numbers.get("simcol") or {}
    b, a = sc.get("before") or {}, sc.get("after") or {}
    if not (b.get("patients") and a.get("patients")):
        return "SimCol was not scored in this run. " + SIMCOL_WHY
    parts = []
    for k, label, unit, scale in (("L1_mm", "L1", " mm", 1.0), ("AbsRel", "AbsRel", "", 1.0),
                                  ("RMSE_mm", "RMSE", " mm", 1.0), ("delta1", "delta1", " %", 100.0)):
        if b.get(k) is not None and a.get(k) is not None:
            parts.append(f"{label} {scale * b[k]:.3g} -> {scale * a[k]:.3g}{unit}")
    better = sum((a.get(k) is not None and b.get(k) is not None and (a[k] - b[k]) * sign > 0)
                 for k, sign in (("L1_mm", -1), ("AbsRel", -1), ("RMSE_mm", -1), ("delta1", 1)))
    verdict = {4: "better on every score", 0: "worse on every score"}.get(better, f"better on {better} of 4 scores")
    return f"SimCol after fine-tuning, this run: {', '.join(parts)} ({verdict}). " + SIMCOL_WHY


#: why COLMAP is not in the default evaluate.pose.methods (measured by benchmarks/pose_eval.py)
COLMAP_NOTE = ("COLMAP (careful setup: denoise + CLAHE, SIFT threshold chosen by verified matches, sequential "
               "matching, bundle adjustment) is off by default: on the default run it scores below the "
               "constant_forward baseline on the same frames while costing more CPU time than both VO methods "
               "together, so it would spend the evaluation time budget on a row that says nothing; scores and CPU "
               "seconds: benchmarks/results/pose_eval_quick.md (python benchmarks/pose_eval.py --data DIR --quick).")


@dataclasses.dataclass
class Table:
    """A rendered table: header, string cells, notes under it, and the numbers behind it (for metrics.json)."""

    name: str
    title: str
    header: list[str]
    rows: list[list[str]]
    notes: list[str]
    numbers: dict
    text_columns: int = 1          # the first this many columns and the last (status) are text, the rest numbers

    def align(self) -> list[str]:
        n = len(self.header)
        return ["l" if k < self.text_columns or k == n - 1 else "r" for k in range(n)]

    def to_markdown(self) -> str:
        out = [f"### {self.title}", "", "| " + " | ".join(self.header) + " |",
               "|" + "|".join("---" if a == "l" else "---:" for a in self.align()) + "|"]
        out += ["| " + " | ".join(c.replace("|", "/") for c in row) + " |" for row in self.rows]
        out += [""] + [f"- {n}" for n in self.notes]
        return "\n".join(out) + "\n"

    def to_latex(self) -> str:
        cols = "".join(self.align())
        out = ["% generated by room-pipeline (stage `tables`); do not edit by hand",
               "\\begin{table}[t]", "\\centering", "\\footnotesize",
               f"\\caption{{{latex_escape(self.title)}}}", f"\\label{{tab:room_{self.name}}}",
               f"\\begin{{tabular}}{{{cols}}}", "\\hline",
               " & ".join(latex_escape(h) for h in self.header) + " \\\\", "\\hline"]
        out += [" & ".join(latex_escape(c) for c in row) + " \\\\" for row in self.rows]
        out += ["\\hline", "\\end{tabular}"]
        out += [f"\\par\\smallskip{{\\scriptsize {latex_escape(n)}}}" for n in self.notes]
        out += ["\\end{table}"]
        return "\n".join(out) + "\n"

    def to_csv(self) -> str:
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(self.header)
        w.writerows(self.rows)
        return buf.getvalue()


_LATEX = {"\\": "\\textbackslash{}", "&": "\\&", "%": "\\%", "$": "\\$", "#": "\\#", "_": "\\_", "{": "\\{",
          "}": "\\}", "~": "\\textasciitilde{}", "^": "\\textasciicircum{}"}


def latex_escape(text: str) -> str:
    return "".join(_LATEX.get(ch, ch) for ch in str(text))


def _finite(v: Any) -> float | None:
    if v is None or isinstance(v, bool):
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def fmt(v: Any, kind: str, digits: int) -> str:
    """A cell: fraction -> % (``pct``), plain number (``num``), seconds with 3 decimals (``time``); '-' if undefined."""
    f = _finite(v)
    if f is None:
        return DASH
    if kind == "pct":
        return f"{100.0 * f:.{digits}f}"
    if kind == "time":
        return f"{f:.3f}"
    return f"{f:.{digits}f}"


def fmt_paper(v: Any, digits: int) -> str:
    """A published value exactly as printed in the paper (a string, no unit conversion), or 'n/r'."""
    if isinstance(v, str):
        return v
    f = _finite(v)
    return paper.NOT_RETRIEVED if f is None else f"{f:.{max(digits, 2)}f}"


def flatten_segments(rec: Mapping[str, Any]) -> dict:
    """A pose record with its per-segment scores lifted to ``seg:<segment>:<metric>`` keys."""
    out = dict(rec)
    for seg, m in (rec.get("segments") or {}).items():
        for k, v in (m or {}).items():
            out[f"seg:{seg}:{k}"] = v
    return out


def beats(mean: Mapping[str, Any], base: Mapping[str, Mapping[str, Any]], better: Mapping[str, int]) -> list[str]:
    """The '<metric> (<baseline>)' where ``mean`` does not strictly beat a trivial baseline (empty: beats all)."""
    fails = []
    for b, bm in base.items():
        for k, sign in better.items():
            v, w = _finite(mean.get(k)), _finite(bm.get(k))
            if w is None:
                continue
            if v is None or sign * (v - w) <= 0:
                fails.append(f"{k} ({b})")
    return fails


def mean_records(records: Iterable[Mapping[str, Any]], keys: Sequence[str]) -> dict:
    """Per key, the mean of the finite values over the records (None when there is none)."""
    recs = list(records)
    out = {}
    for k in keys:
        vals = [f for f in (_finite(r.get(k)) for r in recs) if f is not None]
        out[k] = sum(vals) / len(vals) if vals else None
    return out


def aggregate_methods(docs: Sequence[Mapping[str, Any]], keys: Sequence[str], order: Sequence[str] = ()) -> dict:
    """{method: {"available": n sequences with results, "total": n records, "reasons": [...], "mean": {...}}}.

    ``docs`` are per-sequence ``{"methods": {name: record}}``; methods are ordered as in ``order``, then sorted.
    """
    names: list[str] = [m for m in order]
    for d in docs:
        for m in sorted((d.get("methods") or {})):
            if m not in names:
                names.append(m)
    agg = {}
    for m in names:
        recs = [d["methods"][m] for d in docs if m in (d.get("methods") or {})]
        if not recs:
            continue
        ok = [r for r in recs if r.get("available", True)]
        reasons = sorted({str(r.get("reason")) for r in recs if not r.get("available", True) and r.get("reason")})
        not_run = sum(1 for r in recs if r.get("run", True) is False)
        agg[m] = {"available": len(ok), "total": len(recs), "reasons": reasons, "mean": mean_records(ok, keys),
                  "not_run": not_run}
    return agg


def _status(a: Mapping[str, Any]) -> str:
    if a["available"] == a["total"]:
        return "ok"
    why = "; ".join(a["reasons"]) or "no reason given"
    if a.get("not_run") == a["total"]:                   # configured off (e.g. colmap by default), not broken
        return f"not run: {why}"
    if a["available"] == 0:
        return f"unavailable: {why}"
    return f"ran on {a['available']}/{a['total']}; elsewhere unavailable: {why}"


def _baselines_on_same_sequences(docs: Sequence[Mapping[str, Any]], method: str, keys: Sequence[str],
                                 baselines: Sequence[str]) -> dict:
    """The trivial baselines' means over exactly the sequences where ``method`` has results.

    A method that runs on fewer sequences than the baselines (e.g. the fine-tuned CNN, never scored on the
    patient it trained on) is compared with the baselines on its own sequences, not on all of them.
    """
    own = [d for d in docs if (d.get("methods") or {}).get(method, {}).get("available", True)
           and method in (d.get("methods") or {})]
    agg = aggregate_methods(own, keys)
    return {b: agg[b]["mean"] for b in baselines if b in agg and agg[b]["available"]}


def _method_table(name: str, title: str, docs: Sequence[Mapping[str, Any]], columns, paper_cols: Sequence[str],
                  digits: int, order: Sequence[str], unit_label: str, missing: str,
                  baselines: Sequence[str] = (), better: Mapping[str, int] | None = None,
                  labels: Mapping[str, str] | None = None) -> Table:
    """One row per method (mean over sequences); rows in ``baselines`` are labelled trivial baselines and every
    other available row says in "Beats baselines" whether it strictly beats all of them on ``better``."""
    keys = [k for k, _, _ in columns] + [k for k in (better or {}) if k not in [c[0] for c in columns]]
    header = (["Method"] + [h for _, h, _ in columns] + [unit_label]
              + [f"paper (published) {c}" for c in paper_cols] + ["Beats trivial baselines", "Status"])
    rows, numbers = [], {}
    agg = aggregate_methods(docs, keys, order)
    base = {b: agg[b]["mean"] for b in baselines if b in agg and agg[b]["available"]}
    for m, a in agg.items():
        cells = [fmt(a["mean"][k], kind, digits) if a["available"] else DASH for k, _, kind in columns]
        if m in baselines:
            verdict = "(trivial baseline)"
        elif not a["available"] or not base or not better:
            verdict = DASH
        else:
            fails = beats(a["mean"], _baselines_on_same_sequences(docs, m, keys, baselines), better)
            verdict = "yes" if not fails else "NO: not better on " + ", ".join(fails)
        label = (labels or {}).get(m, m)
        rows.append([label] + cells + [str(a["available"])]
                    + [fmt_paper(paper.published(name, m, c), digits) for c in paper_cols] + [verdict, _status(a)])
        numbers[m] = {**{k: _finite(a["mean"][k]) for k in keys}, unit_label.lower(): a["available"],
                      "available": a["available"] > 0, "trivial_baseline": m in baselines,
                      "beats_trivial_baselines": (None if m in baselines or not base or not a["available"]
                                                  else verdict == "yes")}
    for m in paper.paper_only_rows(name):
        rows.append([f"{m} (paper)"] + [DASH] * len(columns) + ["0"]
                    + [fmt_paper(paper.TABLES[name]["rows"][m].get(c), digits) for c in paper_cols]
                    + [DASH, "not run here (paper only)"])
    if not agg:
        rows.insert(0, ["(none)"] + [DASH] * len(columns) + ["0"] + [paper.NOT_RETRIEVED] * len(paper_cols)
                    + [DASH, f"not run: {missing}"])
    return Table(name, title, header, rows, [], numbers)


def pose_table(docs: Sequence[Mapping[str, Any]], digits: int = 2, order: Sequence[str] = (),
               missing: str = "no evaluation/pose.json found") -> Table:
    """Table I: method x RRA@5, RTA@5, AUC@30 (+ registration, ATE, time), mean over sequences."""
    docs = [{**d, "methods": {m: flatten_segments(r) for m, r in (d.get("methods") or {}).items()}} for d in docs]
    t = _method_table("table_1_pose", "Table I: multi-view pose estimation on ROOM sequences", docs, POSE_COLUMNS,
                      paper.TABLES["table_1_pose"]["columns"], digits, order, "Sequences", missing,
                      POSE_BASELINES, POSE_BETTER)
    strides = sorted({int(d["input"]["frame_stride"]) for d in docs
                      if isinstance((d.get("input") or {}).get("frame_stride"), int)})
    every = (f"every {'/'.join(map(str, strides))}th rendered frame (evaluate.pose.frame_stride; frames 0, k, 2k, ... "
             "tile the whole route)" if strides else "every frame after evaluate.pose.frame_stride")
    t.notes = [f"Mean over the sequences where the method ran ({len(docs)} evaluated), each scored over its whole "
               f"route ({every}, bifurcations and bends included). "
               "Over all frame pairs i<j: "
               "RRA@5 / RTA@5 = % of pairs with relative-rotation / relative-translation-direction error under "
               "5 deg (translation sign folded, min(a, 180-a)); AUC@30 = mean over 1..30 deg thresholds of the % "
               "of pairs whose larger error is under the threshold; pairs with an unregistered frame count as "
               "failures. Units: % of pairs (pose.json stores fractions in [0, 1]).",
               "Per segment (AUC@30 trachea / bifurcations / distal): pairs with both frames in the same segment "
               "(bifurcation region = camera within 2 parent lumen radii of a branch point; evaluate/route_segments.py); "
               "pose.json has RRA/RTA/AUC for every segment and every bifurcation region.",
               "identity and constant_forward are image-blind trivial baselines (identity: no motion; constant "
               "forward: identity rotation, constant step along the first optical axis). 'Beats trivial baselines' "
               "says whether a method's RRA@5, RTA@5 and AUC@30 all strictly exceed both baselines' (the baselines "
               "averaged over the same sequences as the method); NO marks a row whose score the trivial answer matches.",
               "Registered = % of frames with a pose; ATE = RMS camera-centre error after Sim(3) alignment of the "
               "registered frames, mm; Time = wall time per input frame on the machine that ran the stage (polluted "
               "when the machine is shared), CPU = process CPU time per frame.",
               "DUSt3R and VGGT are not run: their code and weights cannot be installed on this project's machines "
               "(no network), so no adapter could be run or checked; their rows are the paper's only.",
               "The paper's Table I and its text disagree on the unit of RTA (0.07 vs \"0.07%\"); published "
               "values are shown exactly as printed, without conversion.",
               paper.NOTE]
    not_run = [m for m in aggregate_methods(docs, ()).values() if m.get("not_run") and m["not_run"] == m["total"]]
    if not_run:
        t.notes.insert(-1, "'not run' rows: registered methods left out of evaluate.pose.methods; the status gives "
                           "the override that runs them. " + COLMAP_NOTE)
    return t


def depth_table(docs: Sequence[Mapping[str, Any]], digits: int = 2, order: Sequence[str] = (),
                missing: str = "no evaluation/depth.json found (depth evaluation not run)") -> Table:
    """Table II: method x L1, AbsRel, RMSE, delta1 (+ time), mean over sequences."""
    labels = {}
    for d in docs:
        for m, r in (d.get("methods") or {}).items():
            if r.get("oracle"):
                labels[m] = f"{m} (ORACLE: reads the renderer's light model)"
    t = _method_table("table_2_depth", "Table II: monocular depth estimation on ROOM sequences", docs,
                      DEPTH_COLUMNS, paper.TABLES["table_2_depth"]["columns"], digits, order, "Sequences", missing,
                      DEPTH_BASELINES, DEPTH_BETTER, labels)
    t.notes = [f"Mean over the sequences where the method ran ({len(docs)} evaluated); only frames the method never "
               "trained on: rows trained on a sequence's patient (cnn, train_mean on the training patient) are not "
               "scored there (status says so). L1 and RMSE in mm, AbsRel a ratio, delta1 = % of pixels with "
               "max(d/d*, d*/d) < 1.25; Time = wall time per frame. Input images as in depth.input (default: noisy RGB).",
               "constant, train_mean (mean ground-truth depth image of the training patient's frames) and tube_prior "
               "(depth ~ 1/(image radius) of a straight tube seen along its axis) are image-blind trivial baselines, "
               "median-scaled like every relative row; 'Beats trivial baselines' requires a lower AbsRel and a higher "
               "delta1 than all of them, the baselines averaged over the same sequences as the row (cnn and train_mean "
               "are scored only on patients they were not fitted on).",
               "ORACLE rows read the renderer's light power, material albedo and exposure from metadata/render.json: "
               "information no real endoscope image carries; shading_sfs is the weight-free baseline that does not.",
               paper.NOTE]
    return t


def finetune_table(docs: Sequence[Mapping[str, Any]], digits: int = 2,
                   missing: str = "no metrics/depth_finetune.json found (fine-tuning not run)",
                   extra_notes: Sequence[str] | None = None) -> Table:
    """Table III: dataset x (before, after fine-tuning) x L1, AbsRel, RMSE, delta1, mean over patients."""
    name = "table_3_finetune"
    keys = [k for k, _, _ in FINETUNE_COLUMNS]
    pcols = paper.TABLES[name]["columns"]
    header = (["Dataset", "Model"] + [h for _, h, _ in FINETUNE_COLUMNS] + ["Patients"]
              + [f"paper (published) {c}" for c in pcols] + ["Status"])
    datasets = sorted({ds for d in docs for ds in (d.get("datasets") or {})})
    rows, numbers = [], {}
    for ds in datasets:
        numbers[ds] = {}
        entries = [d["datasets"][ds] for d in docs if isinstance((d.get("datasets") or {}).get(ds), Mapping)]
        reasons = sorted({str(e.get("reason")) for e in entries if e.get("available") is False and e.get("reason")})
        for phase in ("before", "after"):
            recs = [e[phase] for e in entries if e.get("available", True) and isinstance(e.get(phase), Mapping)]
            ok = [r for r in recs if r.get("available", True)]
            mean = mean_records(ok, keys)
            label = f"{ds} {phase}"
            status = "ok" if ok else ("unavailable: " + "; ".join(reasons) if reasons else "not run")
            if ok and reasons:
                status = f"ran for {len(ok)}/{len(entries)}; elsewhere unavailable: " + "; ".join(reasons)
            rows.append([ds, f"{phase} fine-tuning"] + [fmt(mean[k], kind, digits) for k, _, kind in FINETUNE_COLUMNS]
                        + [str(len(ok))] + [fmt_paper(paper.published(name, label, c), digits) for c in pcols]
                        + [status])
            numbers[ds][phase] = {**{k: _finite(mean[k]) for k in keys}, "patients": len(ok)}
    if not rows:
        rows.append(["(none)", DASH] + [DASH] * len(FINETUNE_COLUMNS) + ["0"] + [paper.NOT_RETRIEVED] * len(pcols)
                    + [f"not run: {missing}"])
    for m in paper.paper_only_rows(name):
        rows.append(["Visentini-Scarzanella 2017 phantom (paper)", m] + [DASH] * len(FINETUNE_COLUMNS) + ["0"]
                    + [fmt_paper(paper.TABLES[name]["rows"][m].get(c), digits) for c in pcols]
                    + ["not run here (paper only)"])
    notes = ["Each row: mean over the patients in its Patients column (phantom_held_out, simcol: the training "
             "patient's train_depth record; other_anatomy: evaluate_depth of its two checkpoints on each other "
             "patient, rows cnn_pretrained and cnn); all median-scaled per sequence; units as in Table II; "
             "inputs as depth.input (default noisy RGB; SimCol frames are used as published).",
             "Data the generator did not make: simcol = every RGB-D pair in ../shared/data (10 SimCol3D "
             "colonoscopy frames, the only external depth pairs available offline); the paper's external set "
             "(Visentini-Scarzanella 2017 phantom) is not available here, so its rows are the paper's only.",
             simcol_note(numbers), *(extra_notes or []),
             paper.NOTE]
    return Table(name, "Table III: monocular depth before and after fine-tuning on ROOM data", header, rows, notes,
                 numbers, text_columns=2)


def speed_accuracy_csv(table: Table) -> str:
    """Method, time per frame and the accuracy scores (numbers only) of Table I, for a DVC scatter plot."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["method", "seconds_per_frame", "RRA_5_pct", "RTA_5_pct", "AUC_30_pct"])
    for m, n in table.numbers.items():
        if not n.get("available") or n.get("seconds_per_frame") is None:
            continue
        w.writerow([m, f"{n['seconds_per_frame']:.6f}"]
                   + [f"{100.0 * n[k]:.4f}" if n.get(k) is not None else "" for k in ("RRA@5", "RTA@5", "AUC@30")])
    return buf.getvalue()
