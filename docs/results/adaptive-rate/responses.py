#!/usr/bin/env python3
"""The response of runs side by side (docs/results/adaptive-rate.md): for each run directory, the
mean friction angle over 1-3 % and 3-7 % axial strain (rows in the range, averaged by strain:
trapezoids), ev at 5 and 10 % and the coordination number at 10 % (linear interpolation in e1),
the mean IMom, the steps and the wall time (from summary.json). Reads series.csv by header name (docs/physics.md 10.1)
and summary.json.

    python3 responses.py RUNDIR...
"""
import csv
import json
import sys


def series(run):
    with open(f"{run}/series.csv") as f:
        rows = list(csv.DictReader(f))
    return {k: [float(r[k]) for r in rows] for k in ("e1", "ev", "phi_deg", "cn", "imom")}


def at(x, y, x0):
    # The last row of a run whose rows are equal strain increments may end 1e-7 short of the
    # final strain (rounding): it stands for it.
    if 0 <= x0 - x[-1] < 1e-6:
        return y[-1]
    for i in range(1, len(x)):
        if x[i - 1] <= x0 <= x[i]:
            t = (x0 - x[i - 1]) / (x[i] - x[i - 1])
            return y[i - 1] + t * (y[i] - y[i - 1])
    return float("nan")


def mean_over(x, y, lo, hi):
    # Trapezoids on the rows within [lo, hi], with the ends interpolated.
    pts = [(lo, at(x, y, lo))] + [(a, b) for a, b in zip(x, y) if lo < a < hi] + [(hi, at(x, y, hi))]
    area = sum((pts[i][0] - pts[i - 1][0]) * (pts[i][1] + pts[i - 1][1]) / 2 for i in range(1, len(pts)))
    return area / (hi - lo)


print("| run | phi 1-3 % (deg) | phi 3-7 % (deg) | ev at 5 % (%) | ev at 10 % (%) | Cn at 10 % | mean IMom (%) | steps | wall (s) |")
print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
for run in sys.argv[1:]:
    s = series(run)
    summary = json.load(open(f"{run}/summary.json"))
    e1 = s["e1"]
    print(f"| {run} | {mean_over(e1, s['phi_deg'], 0.01, 0.03):.2f} | {mean_over(e1, s['phi_deg'], 0.03, 0.07):.2f} "
          f"| {100 * at(e1, s['ev'], 0.05):.3f} | {100 * at(e1, s['ev'], 0.10):.3f} | {at(e1, s['cn'], 0.10):.3f} "
          f"| {100 * summary['mean_imom']:.3f} | {summary['steps']} | {summary['wall_s']:.0f} |")
