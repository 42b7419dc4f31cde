#!/bin/bash
# Copies what this page is made from out of a finished study directory of
# studies/critical-state-small.toml: study.json, study.toml, report.html, analysis/ (tables, CSVs,
# analysis.json, figures), every run's summary.json and series.csv, and every sample's summary.json.
#   qsdem study studies/critical-state-small.toml --out runs/critical-state-small
#   bash docs/results/critical-state/collect.sh runs/critical-state-small
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
src=${1:?usage: collect.sh STUDY_DIR}
cd "$src"
rm -rf "$here/analysis" "$here/runs" "$here/samples"
cp study.json study.toml report.html "$here/"
cp -r analysis "$here/"
find runs samples -name summary.json -o -name series.csv | while read -r f; do
  mkdir -p "$here/$(dirname "$f")"
  cp "$f" "$here/$f"
done
