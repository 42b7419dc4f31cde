"""Isotropic compaction of a loose cloud to 390 kPa in YADE (bench/yade).

    yade -n -j1 -x bench/yade/compact.py SEED ALPHA OUTDIR [MAX_STEPS]

Sample A's grading (peer.py), friction 0.2, NewtonIntegrator(damping=ALPHA), PeriTriaxController
on the three axes at 390 kPa, its rate capped at compaction.max_strain_rate / t_c as in qsdem
(docs/physics.md 8.2). It stops when every normal stress is within 1 % of the target and YADE's
unbalanced force (mean resultant over mean contact force: qsdem's UFR) is below 1 %, qsdem's
default criteria, and writes to OUTDIR:

    compacted.yade.gz   the YADE scene (the triaxial test continues from it, with its history)
    compacted.packing   the bodies as a qsdem packing (body ids = particle ids, unwrapped centres)
    contacts.txt        the contacts with their history (peer.write_contacts)
    compaction.csv      a row every 1000 steps
    compaction.json     steps, wall time, the final measures
"""

import sys
import time

sys.path.insert(0, __import__("os").path.dirname(__import__("os").path.abspath(sys.argv[0])))
import peer  # noqa: E402
from peer import *  # noqa: E402,F401,F403

if len(sys.argv) < 4:
    raise SystemExit("usage: yade -n -j1 -x compact.py SEED ALPHA OUTDIR [MAX_STEPS]")
seed, alpha, out = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3]
max_steps = int(sys.argv[4]) if len(sys.argv) > 4 else 3000000
os.makedirs(out, exist_ok=True)

side, cloud = peer.loose_cloud(seed)
O.periodic = True
O.cell.hSize = Matrix3(side, 0, 0, 0, side, 0, 0, 0, side)
mat = O.materials.append(peer.material(peer.COMPACTION_FRICTION))
for c, r in cloud:
    O.bodies.append(utils.sphere(Vector3(*c), r, material=mat))
O.dt = peer.time_step()
cap = peer.COMPACTION_MAX_RATE / peer.critical_time()
S = peer.STRESS
done = {"steps": None}


def finished():
    done["steps"] = O.iter
    O.pause()


controller = PeriTriaxController(goal=Vector3(-S, -S, -S), stressMask=7, maxStrainRate=Vector3(cap, cap, cap),
                                 relStressTol=0.01, absStressTol=0.01 * S, maxUnbalanced=0.01,
                                 doneHook="finished()", globUpdate=1, label="servo")
O.engines = peer.engines(alpha, controller) + [PyRunner(iterPeriod=1000, command="row()")]

rows = open(os.path.join(out, "compaction.csv"), "w")
rows.write("step,s11_Pa,s22_Pa,s33_Pa,void_ratio,cn,ufr,ekin_J\n")


def row():
    m = peer.measures()
    rows.write(f"{O.iter},{m['s11_Pa']!r},{m['s22_Pa']!r},{m['s33_Pa']!r},{m['void_ratio']!r},{m['cn']!r},"
               f"{m['ufr']!r},{m['ekin_J']!r}\n")
    rows.flush()
    if O.iter >= max_steps:
        O.pause()


start = time.time()
O.run()
O.wait()
wall = time.time() - start
rows.close()
if done["steps"] is None:
    raise SystemExit(f"compaction did not reach equilibrium within {max_steps} steps")
O.save(os.path.join(out, "compacted.yade.gz"))
peer.write_packing(os.path.join(out, "compacted.packing"))
peer.write_contacts(os.path.join(out, "contacts.txt"))
final = peer.measures()
peer.write_json(os.path.join(out, "compaction.json"), {
    "seed": seed, "damping": alpha, "steps": O.iter, "wall_s": wall, "dt_s": O.dt,
    "critical_time_s": peer.critical_time(), "particles": len(O.bodies), "contacts": peer.contacts(),
    "final": final, "yade": version,
})
print(f"compacted: {O.iter} steps in {wall:.0f} s, void ratio {final['void_ratio']:.4f}, cn {final['cn']:.2f}")
