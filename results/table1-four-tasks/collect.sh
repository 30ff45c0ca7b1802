#!/usr/bin/env bash
# Copies the small files of every finished run under runs/every-task/ (summary.json says "finished": true) into
# this folder (<task>/<algo>/seed<k>/), leaving the checkpoints behind; a run already here is left as it is.
# From the repository root:  bash results/table1-four-tasks/collect.sh [runs folder]
# Prints each run it copied; then run verdicts.py and the report (README.md, Status).
set -eu
runs="${1:-runs/every-task}"
here="$(dirname "$0")"
files=(code.jsonl config.yaml diagnostics.csv eval.csv progress.csv resets.csv summary.json triggers.csv)
[[ -d "$runs" ]] || { echo "no runs folder at $runs" >&2; exit 2; }
shopt -s nullglob
for summary in "$runs"/*/*/seed*/summary.json; do
    run="$(dirname "$summary")"
    rel="${run#"$runs"/}"
    grep -q '"finished": true' "$summary" || continue
    [[ -e "$here/$rel/summary.json" ]] && continue
    mkdir -p "$here/$rel"
    for f in "${files[@]}"; do
        [[ -e "$run/$f" ]] && cp "$run/$f" "$here/$rel/"
    done
    echo "copied $rel"
done
