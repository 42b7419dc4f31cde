#!/usr/bin/env python3
"""Stepping a case from Python: the compaction, then the triaxial test in chunks of steps, with a
callback that halves the strain rate at every sample point where the unbalanced force ratio (UFR)
exceeds a bound, and the contacts read between the chunks.

    PYTHONPATH=build/python /usr/bin/python3 examples/python/stepping.py [CASE] [UFR bound] [steps per chunk]
"""
import sys

import numpy as np

import qsdem

case = sys.argv[1] if len(sys.argv) > 1 else None  # None: the built-in default case
bound = float(sys.argv[2]) if len(sys.argv) > 2 else 0.02
chunk = int(sys.argv[3]) if len(sys.argv) > 3 else 1000

sim = qsdem.Simulation(case)
sim.run_phase()  # the compaction
m = sim.measures()
print(f"compacted: p = {m['mean_stress'] / 1e3:.1f} kPa, void ratio {m['void_ratio']:.4f}, "
      f"{m['contacts']} contacts")


def slower_when_unbalanced(point):
    ufr, rate = point["measures"]["ufr"], point["controls"]["33"][1]
    if ufr > bound:
        print(f"row {point['row']}: UFR {ufr:.3g} > {bound}: eps' {rate:.4g} -> {rate / 2:.4g}")
        return {"33": rate / 2}


sim.on_sample(slower_when_unbalanced)
while not sim.finished:
    sim.step(chunk)
    c = sim.contacts()
    print(f"step {sim.steps}: {len(c['fn'])} contacts, mean fn {c['fn'].mean():.3g} N, "
          f"s33 {sim.stress[2, 2] / 1e3:.1f} kPa, mean |v| {np.linalg.norm(sim.velocities, axis=1).mean():.3g} m/s")
r = sim.records[-1]
print(f"triaxial: {r['steps']} steps, {r['rows']} rows, peak phi {r['peak_phi_deg']:.2f} deg, "
      f"final e1 {100 * r['final_e1']:.3f} %")
