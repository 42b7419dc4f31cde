#!/usr/bin/env python3
"""The table of damping-dependence.md section 7 from run directories (series.csv or series.csv.gz,
summary.json), with make.py's measures:

    python3 docs/results/damping-dependence/spheres-A-8000/table.py RUN_DIR...
"""
import csv
import gzip
import json
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from make import interp, mean_over  # noqa: E402


def series(d):
    p = os.path.join(d, "series.csv")
    with (open(p) if os.path.exists(p) else gzip.open(p + ".gz", "rt")) as f:
        return list(csv.DictReader(f))


print("| model | φ peak | φ 1-3 % | φ 3-7 % | εv 5 % | εv 10 % | Cn 10 % | mean IMom | mean UFR |")
print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
for d in sys.argv[1:]:
    rows, s = series(d), json.load(open(os.path.join(d, "summary.json")))
    print(f"| {os.path.basename(os.path.normpath(d))} | {max(float(r['phi_al_deg']) for r in rows):.1f}° "
          f"| {mean_over(rows, 0.01, 0.03, 'phi_al_deg'):.1f}° | {mean_over(rows, 0.03, 0.07, 'phi_al_deg'):.1f}° "
          f"| {100 * interp(rows, 0.05, 'ev'):+.2f} % | {100 * interp(rows, 0.10, 'ev'):+.2f} % "
          f"| {interp(rows, 0.10, 'cn'):.2f} | {100 * s['mean_imom']:.2f} % | {100 * s['mean_ufr']:.2f} % |")

# The smallest size class (classes.csv, where the run has one): make.py's "fines" measures.
fines = []
for d in sys.argv[1:]:
    p = os.path.join(d, "classes.csv")
    if not (os.path.exists(p) or os.path.exists(p + ".gz")):
        continue
    with (open(p) if os.path.exists(p) else gzip.open(p + ".gz", "rt")) as f:
        rows = [r for r in csv.DictReader(f) if r["phase"] == "triaxial"]
    r_min = min(float(r["radius_mm"]) for r in rows)
    rows = [r for r in rows if float(r["radius_mm"]) == r_min]
    fines.append(f"| {os.path.basename(os.path.normpath(d))} | {100 * mean_over(rows, 0.01, 0.10, 'in_contact'):.0f} % "
                 f"| {100 * mean_over(rows, 0.01, 0.10, 'p_share'):.1f} % | {1e3 * mean_over(rows, 0.01, 0.10, 'speed_m_s'):.0f} mm/s "
                 f"| {mean_over(rows, 0.01, 0.10, 'spin_1_s'):.0f} 1/s |")
if fines:
    print("\n| model | fines in contact | fines' share of p | fines' speed | fines' spin |")
    print("| --- | ---: | ---: | ---: | ---: |")
    print("\n".join(fines))
