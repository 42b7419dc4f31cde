#!/usr/bin/env python3
"""A loading path the case keys do not have, driven from Python: drained compression along a
straight stress path of slope dq/dp' = S from the isotropic state (p'0). sigma_33 is loaded at the
case's strain rate; at each sample point a callback sets the lateral stress targets to the sigma_3
that puts the current sigma_1 on the path:

    p' - p'0 = q / S,  q = sigma_1 - sigma_3,  p' = (sigma_1 + 2 sigma_3) / 3

with sigma_1 = sigma_33 and sigma_3 the mean of sigma_11 and sigma_22 (the axes the servo holds; a
small sample's shear stresses make its principal stresses differ a little from them):
    =>  sigma_3 = ((3 - S) sigma_1 + 3 S p'0) / (2 S + 3)

S = 3 is the conventional drained test (sigma_3 = p'0), S < 3 raises the lateral stress with the
axial one. The targets follow sigma_1 one sample interval late, so a row is off the path by what
sigma_1 gained since the last one. Prints p', q, q/p' and the distance from the path
(p' - p'0 - q/S) / p'0 at each sample point.

    PYTHONPATH=build/python /usr/bin/python3 examples/python/stress_path.py [CASE] [S] [key=value ...]
"""
import sys

import numpy as np

import qsdem

case = sys.argv[1] if len(sys.argv) > 1 else None  # None: the built-in default case
slope = float(sys.argv[2]) if len(sys.argv) > 2 else 1.5
overrides = sys.argv[3:]  # e.g. triaxial.sample_points=50

sim = qsdem.Simulation(case, set=overrides)
sim.run_phase()  # the isotropic compaction
p0 = sim.measures()["mean_stress"]
print(f"compacted: p'0 = {p0 / 1e3:.1f} kPa; stress path dq/dp' = {slope:g}")
off = []


def on_the_path(point):
    s = point["measures"]["stress"]
    s1, s3 = s[2][2], (s[0][0] + s[1][1]) / 2
    p, q = (s1 + 2 * s3) / 3, s1 - s3
    off.append((p - p0 - q / slope) / p0)
    print(f"row {point['row']}: e1 {100 * point['strain'][2]:.3f} %, p' {p / 1e3:.1f} kPa, q {q / 1e3:.1f} kPa, "
          f"q/p' {q / p:.3f}, off the path {100 * off[-1]:+.2f} % of p'0")
    target = ((3 - slope) * s1 + 3 * slope * p0) / (2 * slope + 3)
    return {"11": target, "22": target}


sim.on_sample(on_the_path)
sim.run_phase()  # the triaxial phase, its lateral targets set from here
late = np.abs(off[len(off) // 2:])
print(f"path: {len(off)} points; over the second half at most {100 * late.max():.2f} % of p'0 off the path")
