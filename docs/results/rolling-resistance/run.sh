#!/bin/bash
# The default case (spheres-A-small, 1001 spheres) with and without rolling resistance
# (contact.law = "hertz_mindlin_rolling", mu_r = 0.1, the other keys at their defaults): the whole
# case with the law in both phases, and the triaxial test of the first run's compacted packing
# with the law. Writes plain/, rolling/, rolling-from-plain/ here (summary.json, series.csv,
# case.toml kept) and table.md. Usage: bash docs/results/rolling-resistance/run.sh [path/to/qsdem]
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
qsdem=$(realpath "${1:-$here/../../../build/qsdem}")
work=$(mktemp -d)
rolling=(--set contact.law=hertz_mindlin_rolling --set contact.rolling_friction=0.1)
"$qsdem" run -q --no-plot -t 1 -o "$work/plain"
"$qsdem" run -q --no-plot -t 1 -o "$work/rolling" "${rolling[@]}"
"$qsdem" run -q --no-plot -t 1 -o "$work/rolling-from-plain" "${rolling[@]}" \
  --set sample.from="$work/plain/compacted.packing"
for d in plain rolling rolling-from-plain; do
  mkdir -p "$here/$d"
  cp "$work/$d/summary.json" "$work/$d/series.csv" "$work/$d/case.toml" "$here/$d/"
done
rm -rf "$work"
/usr/bin/python3 - "$here" <<'PY' > "$here/table.md"
import json, sys
print("| run | void ratio after compaction | peak φ (°) | at ε1 | final εv | mean UFR | mean IMom | steps |")
print("|---|---|---|---|---|---|---|---|")
for d in ["plain", "rolling", "rolling-from-plain"]:
    s = json.load(open(f"{sys.argv[1]}/{d}/summary.json"))
    print(f"| `{d}` | {s['void_ratio_after_compaction']:.4f} | {s['peak_phi_deg']:.2f} | {100 * s['peak_phi_e1']:.2f} % "
          f"| {100 * s['final_ev']:.2f} % | {s['mean_ufr']:.4f} | {s['mean_imom']:.4f} | {s['steps']} |")
PY
cat "$here/table.md"
