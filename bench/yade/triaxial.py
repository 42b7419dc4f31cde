"""Drained triaxial compression in YADE from a compacted scene (bench/yade).

    yade -n -j1 -x bench/yade/triaxial.py COMPACTED.yade.gz RATE ALPHA OUTDIR [contact-point]

As qsdem's triaxial phase (docs/physics.md 8.3): friction 0.5 on every contact (the existing
ones too: utils.setContactFriction), NewtonIntegrator(damping=ALPHA), axis 3 shortened at the
engineering strain rate RATE / t_c (its velGrad -RATE/t_c H0/h33, reset every row), axes 1 and
2 held at 390 kPa by PeriTriaxController (its own servo law; rate capped at 10 x the axial rate,
as triaxial.lateral_rate_factor) to e1 = 10 % in N = round(0.1 / (0.32 RATE)) steps, a row
every N / 250 steps. Writes OUTDIR/series.csv (qsdem's column names where they mean the same)
and OUTDIR/summary.json. With `contact-point` the shear increment takes the relative velocity at
the contact point (Ig2_Sphere_Sphere_ScGeom.avoidGranularRatcheting off; the Mindlin law takes its
shear increment from the geometry functor): qsdem's arms R - delta/2, without YADE's factor
(R1 + R2)/(R1 + R2 - delta) (docs/physics.md 4.7).
"""

import sys
import time

sys.path.insert(0, __import__("os").path.dirname(__import__("os").path.abspath(sys.argv[0])))
import peer  # noqa: E402
from peer import *  # noqa: E402,F401,F403

if len(sys.argv) < 5 or sys.argv[5:] not in ([], ["contact-point"]):
    raise SystemExit("usage: yade -n -j1 -x triaxial.py COMPACTED.yade.gz RATE ALPHA OUTDIR [contact-point]")
scene, rate, alpha, out = sys.argv[1], float(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
contact_point_arms = sys.argv[5:] == ["contact-point"]
os.makedirs(out, exist_ok=True)

O.load(scene)
if abs(O.dt - peer.time_step()) > 1e-12 * O.dt:
    raise SystemExit(f"{scene}: time step {O.dt} is not qsdem's {peer.time_step()}")
utils.setContactFriction(math.atan(peer.TRIAXIAL_FRICTION))
edot = rate / peer.critical_time()  # engineering axial strain rate (1/s)
steps = max(1, round(0.1 / (peer.STEP_RATIO * rate)))
rows_wanted = 250
period = max(1, steps // rows_wanted)
h0 = O.cell.hSize[2, 2]
v0 = O.cell.hSize.determinant()
O.cell.trsf = Matrix3.Identity
S = peer.STRESS
lateral = peer.LATERAL_RATE_FACTOR * edot
# Axis 3 strain-controlled towards a strain it never reaches, so it runs at its cap (the rate).
controller = PeriTriaxController(goal=Vector3(-S, -S, math.log(0.5)), stressMask=3,
                                 maxStrainRate=Vector3(lateral, lateral, edot), relStressTol=1.0,
                                 absStressTol=1e30, maxUnbalanced=-1, globUpdate=1, label="servo")
O.engines = peer.engines(alpha, controller) + [PyRunner(iterPeriod=period, command="row()")]
if contact_point_arms:
    for e in O.engines:
        if isinstance(e, InteractionLoop):
            for f in e.geomDispatcher.functors:
                f.avoidGranularRatcheting = False

series = open(os.path.join(out, "series.csv"), "w")
series.write("step,e1,ev,s11_Pa,s22_Pa,s33_Pa,p_Pa,q_Pa,phi_deg,phi_al_deg,void_ratio,cn,ufr,ekin_J\n")
start_iter = O.iter


def row():
    n = O.iter - start_iter
    m = peer.measures()
    h = O.cell.hSize[2, 2]
    e1 = (h0 - h) / h0
    ev = m["volume_m3"] / v0 - 1
    series.write(f"{n},{e1!r},{ev!r},{m['s11_Pa']!r},{m['s22_Pa']!r},{m['s33_Pa']!r},{m['p_Pa']!r},{m['q_Pa']!r},"
                 f"{m['phi_deg']!r},{m['phi_al_deg']!r},{m['void_ratio']!r},{m['cn']!r},{m['ufr']!r},{m['ekin_J']!r}\n")
    series.flush()
    # the engineering rate: L33 = -edot H0 / h33 (docs/physics.md 3.4), held until the next row
    servo.maxStrainRate = Vector3(lateral, lateral, edot * h0 / h)
    if n >= steps:
        O.pause()


start = time.time()
O.run()
O.wait()
wall = time.time() - start
series.close()
peer.write_json(os.path.join(out, "summary.json"), {
    "scene": scene, "strain_rate": rate, "damping": alpha, "steps": O.iter - start_iter, "wall_s": wall,
    "dt_s": O.dt, "axial_rate_per_s": edot, "row_period": period, "particles": len(O.bodies), "yade": version,
    "arms": "contact point" if contact_point_arms else "radius",
})
print(f"triaxial: {O.iter - start_iter} steps in {wall:.0f} s")
