#!/usr/bin/env python3
"""A callback that holds the moment index IMom near a target by changing the strain rate, as the
rate controller of the case keys does (docs/physics.md 8.5) but written in a few lines of Python:
at each sample point of the triaxial phase eps' is multiplied by sqrt(target / IMom), at most by 2
and at least by 1/2 (IMom grows about as eps', docs/results/adaptive-rate.md).

    PYTHONPATH=build/python /usr/bin/python3 examples/python/hold_imom.py [CASE] [target] [key=value ...]
"""
import math
import sys

import qsdem

case = sys.argv[1] if len(sys.argv) > 1 else None  # None: the built-in default case
target = float(sys.argv[2]) if len(sys.argv) > 2 else 0.01
sim = qsdem.Simulation(case, set=sys.argv[3:])
sim.run_phase()  # the compaction
indices = []


def hold(point):
    imom, rate = point["measures"]["imom"], point["controls"]["33"][1]
    indices.append(imom)
    factor = min(2.0, max(0.5, math.sqrt(target / imom))) if imom > 0 else 2.0
    print(f"row {point['row']}: IMom {100 * imom:.3f} %, eps' {rate:.4g} -> {rate * factor:.4g}")
    return {"33": rate * factor}


sim.on_sample(hold)
sim.run_phase()
r = sim.records[-1]
late = indices[len(indices) // 2:]
print(f"triaxial: {r['steps']} steps, {r['rows']} rows, final e1 {100 * r['final_e1']:.3f} %, mean IMom over the "
      f"second half {100 * sum(late) / len(late):.3f} % (target {100 * target:g} %)")
