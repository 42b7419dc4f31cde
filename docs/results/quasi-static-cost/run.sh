#!/usr/bin/env bash
# The runs of docs/results/quasi-static-cost.md: paper-B-small, seeds 1-6, each method on the six
# samples that `qsdem prepare` makes (the samples of quasi-static-limit/small-B-seeds: the same
# compaction.csv, byte for byte). Run from the repository's root:
#   bash docs/results/quasi-static-cost/run.sh [OUT]         (OUT: runs/qs-cost)
# QSDEM names the binary (build/qsdem); JOBS runs at a time (2), one thread each. A finished run
# (its summary.json) is kept, so running it again continues.
set -euo pipefail
OUT=${1:-runs/qs-cost}
QSDEM=${QSDEM:-build/qsdem}
JOBS=${JOBS:-2}
CASE=examples/paper-B-small.toml
FIRE=docs/results/quasi-static-cost/paper-B-small-fire.toml
mkdir -p "$OUT/samples"

for s in 1 2 3 4 5 6; do
  d=$OUT/samples/B-small-seed$s
  [ -f "$d/sample.qsck" ] || nice -n 5 "$QSDEM" prepare $CASE --set sample.seed=$s --out "$d" --threads 1 --quiet --force
done

# method label, case, then its --set overrides. nd is paper-B-small's damping at the paper's
# Table 4 optimum for Sample B (0.40 %), as in the committed ladders.
methods() {
  # a committed rung run again from these samples: its series.csv must equal small-B-seeds' bytes
  echo "check-nd-1e-05|$CASE|damping.model=nd damping.ratio=0.004 triaxial.strain_rate=1e-5 output.energy=true"
  echo "nd-scaled-1e-06|$CASE|damping.model=nd damping.ratio=0.004 triaxial.strain_rate=1e-6 triaxial.inertia_scaling.target=coarsest"
  echo "nd-scaled-3.16e-06|$CASE|damping.model=nd damping.ratio=0.004 triaxial.strain_rate=3.16228e-6 triaxial.inertia_scaling.target=coarsest"
  echo "none-scaled-1e-05|$CASE|damping.model=none triaxial.strain_rate=1e-5 triaxial.inertia_scaling.target=coarsest"
  echo "nd-control-imom-1%|$CASE|damping.model=nd damping.ratio=0.004 triaxial.strain_rate=1e-5 triaxial.rate_control.index=imom triaxial.rate_control.target=0.01 triaxial.rate_control.min_rate=1e-7 triaxial.rate_control.max_rate=3e-5"
  echo "nd-control-imom-0.3%|$CASE|damping.model=nd damping.ratio=0.004 triaxial.strain_rate=1e-5 triaxial.rate_control.index=imom triaxial.rate_control.target=0.003 triaxial.rate_control.min_rate=1e-7 triaxial.rate_control.max_rate=3e-5"
  echo "fire-0.1%|$FIRE|phase.1.solver.strain_increment=0.001"
  echo "fire-0.05%|$FIRE|phase.1.solver.strain_increment=0.0005"
  echo "fire-0.02%|$FIRE|phase.1.solver.strain_increment=0.0002"
  echo "fire-0.05%-scaled|$FIRE|phase.1.solver.strain_increment=0.0005 phase.1.inertia_scaling.target=coarsest"
}

one() {  # label case sets seed
  local dir=$OUT/$1/B-small-seed$4
  [ -f "$dir/summary.json" ] && return 0
  local args=()
  for kv in $3; do args+=(--set "$kv"); done
  nice -n 5 "$QSDEM" run "$2" --set sample.from="$OUT/samples/B-small-seed$4" "${args[@]}" \
    --out "$dir" --threads 1 --quiet --force --no-plot > "$OUT/$1-seed$4.log" 2>&1 || echo "failed: $dir (see $OUT/$1-seed$4.log)"
}
export -f one
export OUT QSDEM

for s in 1 2 3 4 5 6; do
  methods | while IFS='|' read -r label case sets; do echo "$label|$case|$sets|$s"; done
done | xargs -P "$JOBS" -I{} bash -c 'IFS="|" read -r l c v s <<< "{}"; one "$l" "$c" "$v" "$s"'
