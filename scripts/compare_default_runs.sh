#!/bin/bash
# Byte identity of the DEFAULT pipeline (`./dev.sh pipeline`: dvc repro of dvc.yaml) at REV against a finished
# default run RUN_A (a fresh clone of another commit, e.g. the lead's run of main):
#   scripts/compare_default_runs.sh RUN_A LABEL_A REV SCRATCH [NAME]
# REV of this repository is cloned to SCRATCH/run (the conf's ../shared paths resolve through the link
# SCRATCH/shared -> this checkout's ../shared), installed (./dev.sh setup: a fresh .venv from the pinned
# wheels, as a fresh clone does) and run (/usr/bin/time -v ./dev.sh pipeline, log SCRATCH/pipeline.log);
# then scripts/compare_runs.py (of the current checkout) compares RUN_A with SCRATCH/run (every file of
# data/output and reports/ by sha256; timing fields aside, each named in the table) and writes
# benchmarks/results/NAME.{md,json} (default NAME: default_run_identity).  Exit 1 when a file differs.
# PYTHON (default: the clone's .venv/bin/python) runs the comparison.
# About 15-30 min wall on 2 shared cores (the whole default DAG), plus ~2 min of install.
set -euo pipefail
[ $# -ge 4 ] || { echo "usage: $0 RUN_A LABEL_A REV SCRATCH [NAME]" >&2; exit 2; }
A=$(realpath -m "$1"); LA=$2; REV=$3; S=$(realpath -m "$4"); NAME=${5:-default_run_identity}
REPO=$(git rev-parse --show-toplevel); PY=${PYTHON:-$S/run/.venv/bin/python}
[ -d "$A/data/output" ] || { echo "room: error: $A: no data/output (not a finished run)" >&2; exit 2; }
SHA=$(git -C "$REPO" rev-parse -q --verify "$REV^{commit}" 2>/dev/null) || { echo "room: error: unknown revision $REV" >&2; exit 2; }
mkdir -p "$S"
[ -e "$S/shared" ] || ln -s "$(realpath "$REPO/../shared")" "$S/shared"
if [ ! -d "$S/run/.git" ]; then
  git clone -q --no-checkout "$REPO" "$S/run"
  git -C "$S/run" checkout -q --detach "$SHA"
fi
[ "$(git -C "$S/run" rev-parse HEAD)" = "$SHA" ] || { echo "room: error: $S/run is not at $SHA" >&2; exit 2; }
(cd "$S/run" && ./dev.sh setup && /usr/bin/time -v nice -n 10 ./dev.sh pipeline) > "$S/pipeline.log" 2>&1
PYTHONPATH="$REPO/src" "$PY" "$REPO/scripts/compare_runs.py" compare "$A" "$S/run" --name "$NAME" \
  --label-a "$LA" --label-b "${SHA:0:7}"
