#!/usr/bin/env python3
"""A drained triaxial test from Python: the built-in default case (examples/spheres-A-small.toml),
or the case file given, compacted and sheared; writes DIR/series.csv (and the other files of a run)
and prints the peak friction angle and the mean UFR.

    PYTHONPATH=build/python /usr/bin/python3 examples/python/triaxial.py [DIR] [CASE] [key=value ...]
"""
import sys

import qsdem

out = sys.argv[1] if len(sys.argv) > 1 else "runs/python-default"
case = sys.argv[2] if len(sys.argv) > 2 else None  # None: the built-in default case
sets = sys.argv[3:]  # --set strings, e.g. damping.model=od

summary = qsdem.run(case, out=out, set=sets, progress=True, force=True)
run = qsdem.load(out, pandas=False)  # numpy structured arrays
s = run.series
peak = s["phi_deg"].argmax()
print(f"{len(s)} rows in {out}/series.csv")
print(f"peak friction angle {s['phi_deg'][peak]:.2f} deg at e1 = {100 * s['e1'][peak]:.2f} %")
print(f"mean UFR {s['ufr'].mean():.3g}, final ev {s['ev'][-1]:.4f}, wall {summary['wall_s']:.1f} s")
