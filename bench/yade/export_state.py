"""The state of a saved YADE scene as qsdem reads it (bench/yade).

    yade -n -j1 -x bench/yade/export_state.py SCENE.yade.gz OUTDIR

Writes OUTDIR/packing (bodies in id order, centres in the cell (I + dt L) hSize that YADE's next
force evaluation sees), OUTDIR/motion.txt (velocity and angular velocity per body, as YADE keeps them) and
OUTDIR/velocity_gradient.txt (the cell's L, row by row). bench/compare-yade --start yade-state
makes a qsdem prepared sample of them and of the contacts.txt that compact.py wrote with the scene
(build/bench/qsdem_peer_sample): a loaded scene has no overlaps until its next step.
"""

import sys

sys.path.insert(0, __import__("os").path.dirname(__import__("os").path.abspath(sys.argv[0])))
import peer  # noqa: E402
from peer import *  # noqa: E402,F401,F403

if len(sys.argv) != 3:
    raise SystemExit("usage: yade -n -j1 -x export_state.py SCENE.yade.gz OUTDIR")
scene, out = sys.argv[1], sys.argv[2]
os.makedirs(out, exist_ok=True)
O.load(scene)
hs, L = O.cell.hSize, O.cell.velGrad
h = hs + O.dt * L * hs
with open(os.path.join(out, "packing"), "w") as f:
    f.write("# written by bench/yade/export_state.py: a YADE periodic packing; lengths in metres\n")
    f.write("format qsdem-packing 1\n")
    f.write("cell " + " ".join(repr(float(h[i, j])) for i in range(3) for j in range(3)) + "\n")
    f.write(f"particles {len(O.bodies)}\n")
    for b in O.bodies:
        x, r = b.state.pos, b.shape.radius
        f.write(f"{x[0]!r} {x[1]!r} {x[2]!r} {r!r} {r!r} {r!r} 1 0 0 0\n")
with open(os.path.join(out, "motion.txt"), "w") as f:
    for b in O.bodies:
        v, w = b.state.vel, b.state.angVel
        f.write(f"{v[0]!r} {v[1]!r} {v[2]!r} {w[0]!r} {w[1]!r} {w[2]!r}\n")
with open(os.path.join(out, "velocity_gradient.txt"), "w") as f:
    f.write(" ".join(repr(float(L[i, j])) for i in range(3) for j in range(3)) + "\n")
print(f"export_state: {len(O.bodies)} bodies")
