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
peer.write_packing(os.path.join(out, "packing"), peer.next_cell())
peer.write_motion(os.path.join(out, "motion.txt"))
with open(os.path.join(out, "velocity_gradient.txt"), "w") as f:
    f.write(peer.velocity_gradient() + "\n")
print(f"export_state: {len(O.bodies)} bodies")
