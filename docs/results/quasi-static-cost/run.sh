#!/usr/bin/env bash
# The runs of docs/results/quasi-static-cost.md, on one sample:
#   B-small: paper-B-small, seeds 1-6 (the samples of quasi-static-limit/small-B-seeds: the same
#            compaction.csv, byte for byte);
#   A:       paper-A (8000 spheroids), seeds 1-3 (the samples of quasi-static-limit/A);
#   A-small: paper-A-small (2001 spheroids), seeds 1-3 (the samples of quasi-static-limit/small:
#            the same compaction.csv in every column that file has).
# Each method runs on the samples that `qsdem prepare` makes of the sample's case. Run from the
# repository's root:
#   bash docs/results/quasi-static-cost/run.sh [OUT] [SAMPLE]     (OUT: runs/qs-cost; SAMPLE: B-small, A or A-small)
# QSDEM names the binary (build/qsdem); JOBS runs at a time (2), one thread each; SAMPLES a
# directory of prepared samples to use instead (SAMPLES/<sample>-seed<s>). A finished run (its
# summary.json) is kept, so running it again continues.
set -euo pipefail
OUT=${1:-runs/qs-cost}
SAMPLE=${2:-B-small}
QSDEM=${QSDEM:-build/qsdem}
JOBS=${JOBS:-2}
FIRE=docs/results/quasi-static-cost/paper-B-small-fire.toml  # its particles come from sample.from

# method label, case, then its --set overrides. nd is at the paper's Table 4 optimum of the sample
# (B 0.40 %, A 0.51 %), as in the committed ladders.
case $SAMPLE in
B-small)
  CASE=examples/paper-B-small.toml SEEDS="1 2 3 4 5 6"
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
  } ;;
A | A-small)
  CASE=examples/paper-$SAMPLE.toml SEEDS="1 2 3"
  methods() {
    # a committed rung run again from these samples: its series.csv must equal quasi-static-limit/A's
    # (small's: in every column that file has)
    echo "check-nd-1e-05|$CASE|damping.model=nd damping.ratio=0.0051 triaxial.strain_rate=1e-5"
    for r in 1e-6 3.16228e-7 1e-7; do
      echo "nd-scaled-$r|$CASE|damping.model=nd damping.ratio=0.0051 triaxial.strain_rate=$r triaxial.inertia_scaling.target=coarsest"
      echo "none-scaled-$r|$CASE|damping.model=none triaxial.strain_rate=$r triaxial.inertia_scaling.target=coarsest"
    done
    echo "fire-0.05%|$FIRE|name=paper-$SAMPLE-fire phase.1.solver.strain_increment=0.0005"
    echo "fire-0.02%|$FIRE|name=paper-$SAMPLE-fire phase.1.solver.strain_increment=0.0002"
    echo "nd-scaled-3.16228e-8|$CASE|damping.model=nd damping.ratio=0.0051 triaxial.strain_rate=3.16228e-8 triaxial.inertia_scaling.target=coarsest"
  } ;;
*) echo "run.sh: SAMPLE is B-small, A or A-small, not '$SAMPLE'" >&2; exit 2 ;;
esac
mkdir -p "$OUT/samples"

for s in $SEEDS; do
  d=${SAMPLES:-$OUT/samples}/$SAMPLE-seed$s
  [ -f "$d/sample.qsck" ] || nice -n 5 "$QSDEM" prepare $CASE --set sample.seed=$s --out "$d" --threads 1 --quiet --force
done

one() {  # label case sets seed
  local dir=$OUT/$1/$SAMPLE-seed$4
  [ -f "$dir/summary.json" ] && return 0
  local args=()
  for kv in $3; do args+=(--set "$kv"); done
  nice -n 5 "$QSDEM" run "$2" --set sample.from="${SAMPLES:-$OUT/samples}/$SAMPLE-seed$4" "${args[@]}" \
    --out "$dir" --threads 1 --quiet --force --no-plot > "$OUT/$1-$SAMPLE-seed$4.log" 2>&1 || echo "failed: $dir (see $OUT/$1-$SAMPLE-seed$4.log)"
}
export -f one
export OUT QSDEM SAMPLE SAMPLES

# each method on every seed before the next method: the cheap ones finish first
methods | while IFS='|' read -r label case sets; do
  for s in $SEEDS; do echo "$label|$case|$sets|$s"; done
done | xargs -P "$JOBS" -I{} bash -c 'IFS="|" read -r l c v s <<< "{}"; one "$l" "$c" "$v" "$s"'
