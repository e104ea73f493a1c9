#!/bin/bash
# Byte identity of two commits on the small-phantom config of tests/test_pipeline_e2e.py (SMALL):
#   scripts/compare_small_runs.sh REV_A REV_B SCRATCH [NAME]
# Each commit is exported (git archive) to SCRATCH/tree_{a,b} and run by `room run` into the SAME output_dir
# (SCRATCH/out: absolute paths land in run_config.yaml and depth.json), the first run moved aside to
# SCRATCH/out_a; then scripts/compare_runs.py (of the current checkout) compares them and writes
# benchmarks/results/NAME.{md,json} (default NAME: run_identity).  About 3-6 min wall a run on 2 shared cores.
set -euo pipefail
[ $# -ge 3 ] || { echo "usage: $0 REV_A REV_B SCRATCH [NAME]" >&2; exit 2; }
A=$1; B=$2; S=$(realpath -m "$3"); NAME=${4:-run_identity}
REPO=$(git rev-parse --show-toplevel); PY=${PYTHON:-python}
SMALL=$("$PY" -c "import sys; sys.path.insert(0, '$REPO'); from tests.test_pipeline_e2e import SMALL; print(' '.join(SMALL))")
rm -rf "$S/tree_a" "$S/tree_b" "$S/out" "$S/out_a" "$S/run_a" "$S/run_b"
for side in a b; do
  rev=$A; [ $side = b ] && rev=$B
  mkdir -p "$S/tree_$side" && git -C "$REPO" archive "$rev" | tar -x -C "$S/tree_$side"
  (cd "$S/tree_$side" && PYTHONPATH="$S/tree_$side/src" nice -n 10 "$PY" -m room_pipeline.cli run $SMALL output_dir="$S/out")
  [ $side = a ] && mv "$S/out" "$S/out_a"
done
mkdir -p "$S/run_a/data" "$S/run_b/data"
ln -sfn "$S/out_a" "$S/run_a/data/output"; ln -sfn "$S/tree_a/reports" "$S/run_a/reports"
ln -sfn "$S/out" "$S/run_b/data/output"; ln -sfn "$S/tree_b/reports" "$S/run_b/reports"
PYTHONPATH="$REPO/src" "$PY" "$REPO/scripts/compare_runs.py" compare "$S/run_a" "$S/run_b" --name "$NAME" \
  --label-a "$A" --label-b "$B"
