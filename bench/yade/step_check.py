"""One YADE step against one qsdem step on the same state and history (bench/yade, SPEC
4.7, 5, 6.2): contact by contact, the normal and tangential force; particle by particle, the
velocity and angular velocity after the damped kick.

    yade -n -j1 -x bench/yade/step_check.py SCENE.yade.gz QSDEM_PEER_STEP CASE OUTDIR
         [--alpha A] [--friction MU] [--rate EPS] [--warmup N] [--steps K]

SCENE: a scene of compact.py (or of a triaxial run). The controller is removed and the cell is
given a constant velocity gradient: axis 3 shortened at EPS / t_c (0: a fixed cell), axes 1 and
2 stretched at half that rate. YADE runs WARMUP steps (default 200) so that every velocity
carries the field's part and every contact has its history; then the state is written (packing,
contacts with their stored shear force, velocities), both codes take K steps from it (default 1)
and their forces at the K-th force evaluation and velocities after the K-th kick are compared.
QSDEM_PEER_STEP is the tool built from bench/yade/peer_step.cpp (build/bench/qsdem_peer_step).
Writes OUTDIR/step_check.json and prints a summary.
"""

import subprocess
import sys

sys.path.insert(0, __import__("os").path.dirname(__import__("os").path.abspath(sys.argv[0])))
import peer  # noqa: E402
from peer import *  # noqa: E402,F401,F403

args = sys.argv[1:]
if len(args) < 4:
    raise SystemExit(__doc__)
scene, tool, case, out = args[:4]
options = {"--alpha": 0.1, "--friction": 0.5, "--rate": 0.0, "--warmup": 200, "--steps": 1}
rest = args[4:]
while rest:
    key = rest.pop(0)
    if key not in options or not rest:
        raise SystemExit(f"unknown option or missing value: {key}")
    options[key] = type(options[key])(rest.pop(0))
alpha, mu, rate, warmup, steps = (options[k] for k in ("--alpha", "--friction", "--rate", "--warmup", "--steps"))
os.makedirs(out, exist_ok=True)

O.load(scene)
utils.setContactFriction(math.atan(mu))
O.engines = [e for e in O.engines if not isinstance(e, (PeriTriaxController, PyRunner))]
newton = [e for e in O.engines if isinstance(e, NewtonIntegrator)][0]
newton.damping = alpha
edot = rate / peer.critical_time()
L = Matrix3(0.5 * edot, 0, 0, 0, 0.5 * edot, 0, 0, 0, -edot)
O.cell.velGrad = L
O.run(warmup, True)


before = os.path.join(out, "before")
peer.write_state(before)
O.run(steps, True)
# YADE after the K steps: the contacts of the K-th force evaluation, the velocities after its kick.
yade_forces = {}
for i in O.interactions:
    if not i.isReal:
        continue
    c = i.cellDist
    fn, ft = i.phys.normalForce, i.phys.shearForce
    if i.id1 < i.id2:
        key, sign = (i.id1, i.id2, c[0], c[1], c[2]), 1.0
    else:
        key, sign = (i.id2, i.id1, -c[0], -c[1], -c[2]), -1.0
    yade_forces[key] = ([sign * fn[k] for k in range(3)], [sign * ft[k] for k in range(3)])
g = O.cell.velGrad
# The kick of SPEC 6.2 on YADE's own resultants of the step and the velocities it started from
# (in the fluctuation frame), against the velocities YADE's NewtonIntegrator made of them.
before_motion = [[float(x) for x in l.split()] for l in open(os.path.join(before, "motion.txt"))]
before_pos = [[float(x) for x in l.split()[:3]]
              for l in [l for l in open(os.path.join(before, "packing")) if not l.startswith("#")][3:]]
kick_dv, kick_dw, kick_v, kick_w = 0.0, 0.0, 0.0, 0.0


def sgn(x):
    return (x > 0) - (x < 0)


for b, mv, xp in zip(O.bodies, before_motion, before_pos):
    m, inertia = b.state.mass, b.state.inertia[0]
    f, t = O.forces.f(b.id), O.forces.t(b.id)
    v0 = [mv[k] - sum(g[k, c] * xp[c] for c in range(3)) for k in range(3)]
    w0 = mv[3:]
    a = [f[k] / m for k in range(3)]
    aw = [t[k] / inertia for k in range(3)]
    v1 = [v0[k] + O.dt * a[k] * (1 - alpha * sgn(a[k]) * sgn(v0[k] + 0.5 * O.dt * a[k])) for k in range(3)]
    w1 = [w0[k] + O.dt * aw[k] * (1 - alpha * sgn(aw[k]) * sgn(w0[k] + 0.5 * O.dt * aw[k])) for k in range(3)]
    x, v, w = b.state.pos, b.state.vel, b.state.angVel
    fluct = v - g * x
    kick_dv = max(kick_dv, math.sqrt(sum((fluct[k] - v1[k]) ** 2 for k in range(3))))
    kick_dw = max(kick_dw, math.sqrt(sum((w[k] - w1[k]) ** 2 for k in range(3))))
    kick_v = max(kick_v, math.sqrt(sum(x * x for x in v1)))
    kick_w = max(kick_w, math.sqrt(sum(x * x for x in w1)))
yade_motion = []
for b in O.bodies:
    x, v, w = b.state.pos, b.state.vel, b.state.angVel
    fluct = v - g * x  # the fluctuation velocity (Cell.bodyFluctuationVel)
    yade_motion.append(([fluct[k] for k in range(3)], [w[k] for k in range(3)]))

qsdem_out = os.path.join(out, "qsdem")
cmd = peer.peer_step_command(tool, case, alpha, mu, before, peer.velocity_gradient(), steps, qsdem_out)
done = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
if done.returncode != 0:
    raise SystemExit(f"qsdem_peer_step failed ({done.returncode}): {' '.join(cmd)}\n{done.stdout}")
qsdem_forces = {}
for line in open(os.path.join(qsdem_out, "forces.txt")):
    if line.startswith("#"):
        continue
    w = line.split()
    qsdem_forces[tuple(int(x) for x in w[:5])] = ([float(x) for x in w[5:8]], [float(x) for x in w[8:11]])
qsdem_motion = []
for line in open(os.path.join(qsdem_out, "motion.txt")):
    if line.startswith("#"):
        continue
    w = [float(x) for x in line.split()]
    qsdem_motion.append((w[:3], w[3:]))


def norm(a):
    return math.sqrt(sum(x * x for x in a))


def diff(a, b):
    return norm([x - y for x, y in zip(a, b)])


common = sorted(set(yade_forces) & set(qsdem_forces))
mean_fn = sum(norm(yade_forces[k][0]) for k in common) / max(1, len(common))
mean_ft = sum(norm(yade_forces[k][1]) for k in common) / max(1, len(common))
dn = [diff(yade_forces[k][0], qsdem_forces[k][0]) for k in common]
dt_ = [diff(yade_forces[k][1], qsdem_forces[k][1]) for k in common]
rel_n = [d / norm(yade_forces[k][0]) for d, k in zip(dn, common) if norm(yade_forces[k][0]) > 0]
rel_t = [d / norm(yade_forces[k][1]) for d, k in zip(dt_, common) if norm(yade_forces[k][1]) > 1e-6 * mean_ft]
vmean = sum(norm(v) for v, _ in yade_motion) / len(yade_motion)
wmean = sum(norm(w) for _, w in yade_motion) / len(yade_motion)
dv = [diff(a[0], b[0]) for a, b in zip(yade_motion, qsdem_motion)]
dw = [diff(a[1], b[1]) for a, b in zip(yade_motion, qsdem_motion)]


def rms(xs):
    return math.sqrt(sum(x * x for x in xs) / max(1, len(xs)))


def read_before():
    """The state the step started from, as written by peer.write_state."""
    lines = [l.split() for l in open(os.path.join(before, "packing")) if not l.startswith("#")]
    h = [float(x) for x in lines[1][1:10]]
    body = [[float(x) for x in w] for w in lines[3:]]
    motion = [[float(x) for x in l.split()] for l in open(os.path.join(before, "motion.txt"))]
    stored = {}
    for l in open(os.path.join(before, "contacts.txt")):
        if l.startswith("#"):
            continue
        w = l.split()
        stored[(int(w[0]), int(w[1]), int(w[2]), int(w[3]), int(w[4]))] = ([float(x) for x in w[5:8]],
                                                                         [float(x) for x in w[12:15]])
    return h, body, motion, stored


def cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def axpy(a, x, y):
    return [a * xi + yi for xi, yi in zip(x, y)]


def shear_update(f0, n0, n1, w1, w2, v1, v2, r1, r2, overlap, shift_vel, ks, cap, twist, ratchet, turn):
    """The new tangential force on id2 of one contact by YADE's rule (turn='yade': the stored force
    turned by n0 x n1 to first order, and about n1 by the mean spin if `twist`; the relative
    velocity with the centre-to-surface arms R and the factor (R1 + R2)/(R1 + R2 - delta) on the
    translation if `ratchet`) or by qsdem's (turn='qsdem': projected into the new plane and scaled
    back to its length; arms R - delta/2, no factor). `cap`: mu |F_n|."""
    dt = O.dt
    f = list(f0)
    if turn == "yade":
        f = axpy(-1.0, cross(f, cross(n0, n1)), f)
    else:
        m0 = norm(f)
        f = axpy(-dot(f, n1), n1, f)
        m1 = norm(f)
        if m0 > 0 and m1 > 0:
            f = [x * m0 / m1 for x in f]
    if twist:
        f = axpy(-1.0, cross(f, [0.5 * dt * dot(n1, [a + b for a, b in zip(w1, w2)]) * x for x in n1]), f)
    if ratchet:
        a = (r1 + r2) / (r1 + r2 - overlap)
        arm1, arm2 = r1, r2
    else:
        a = 1.0
        arm1, arm2 = r1 - 0.5 * overlap, r2 - 0.5 * overlap
    rel = [a * (v2[k] - v1[k] + shift_vel[k]) for k in range(3)]
    rel = axpy(1.0, cross(w2, [-arm2 * x for x in n1]), rel)
    rel = axpy(-1.0, cross(w1, [arm1 * x for x in n1]), rel)
    rel = axpy(-dot(rel, n1), n1, rel)
    f = axpy(-ks * dt, rel, f)
    m = norm(f)
    if m > cap:
        f = [x * cap / m for x in f]
    return f


# The tangential update by hand, YADE's rule and qsdem's and each difference alone: which term
# makes the difference of the codes' tangential forces.
replica = {}
if steps == 1:
    h, body, motion, stored = read_before()
    hm = [[h[3 * a + b] for b in range(3)] for a in range(3)]
    gm = [[float(g[a, b]) for b in range(3)] for a in range(3)]
    mat = O.materials[0]
    E = mat.young / (2 * (1 - mat.poisson ** 2))
    G = mat.young / (2 * (1 + mat.poisson))
    variants = {"yade": ("yade", True, True), "yade_no_twist": ("yade", False, True),
                "yade_qsdem_arms": ("yade", True, False), "qsdem": ("qsdem", False, False),
                "qsdem_with_twist": ("qsdem", True, False)}
    sums = {name: [0.0, 0.0] for name in variants}  # squared difference to YADE's and to qsdem's result
    count = 0
    for key in common:
        if key not in stored and (key[1], key[0], -key[2], -key[3], -key[4]) not in stored:
            continue  # a new contact: no stored force
        i1, i2 = key[0], key[1]
        if key in stored:
            n0, f0 = stored[key]
        else:
            n0, f0 = stored[(key[1], key[0], -key[2], -key[3], -key[4])]
            n0, f0 = [-x for x in n0], [-x for x in f0]
        fn_y, ft_y = yade_forces[key]
        fn_mag = norm(fn_y)
        if fn_mag == 0:
            continue
        n1 = [x / fn_mag for x in fn_y]
        r1, r2 = body[i1][3], body[i2][3]
        x1, x2 = body[i1][:3], body[i2][:3]
        shift = [sum(hm[a][b] * key[2 + b] for b in range(3)) for a in range(3)]
        branch = [x2[k] + shift[k] - x1[k] for k in range(3)]
        overlap = r1 + r2 - norm(branch)
        re = r1 * r2 / (r1 + r2)
        ks = 2 * math.sqrt(4 * re) * G / (2 - mat.poisson) * math.sqrt(overlap)
        shift_vel = [sum(gm[a][b] * shift[b] for b in range(3)) for a in range(3)]
        v1, w1 = motion[i1][:3], motion[i1][3:]
        v2, w2 = motion[i2][:3], motion[i2][3:]
        cap = math.tan(math.atan(mu)) * fn_mag
        count += 1
        for name, (turn, twist, ratchet) in variants.items():
            f = shear_update(f0, n0, n1, w1, w2, v1, v2, r1, r2, overlap, shift_vel, ks, cap, twist, ratchet, turn)
            sums[name][0] += diff(f, ft_y) ** 2
            sums[name][1] += diff(f, qsdem_forces[key][1]) ** 2
    replica = {name: {"rms_diff_to_yade_N": math.sqrt(s[0] / max(1, count)),
                      "rms_diff_to_qsdem_N": math.sqrt(s[1] / max(1, count))} for name, s in sums.items()}
    replica["contacts"] = count

report = {
    "scene": scene, "alpha": alpha, "friction": mu, "rate": rate, "warmup": warmup, "steps": steps,
    "velocity_gradient": peer.velocity_gradient(),
    "contacts_yade": len(yade_forces), "contacts_qsdem": len(qsdem_forces), "contacts_common": len(common),
    "mean_normal_force_N": mean_fn, "mean_tangential_force_N": mean_ft,
    "normal_force_diff_max_rel": max(rel_n) if rel_n else None, "normal_force_diff_rms_N": rms(dn),
    "tangential_force_diff_max_rel": max(rel_t) if rel_t else None, "tangential_force_diff_rms_N": rms(dt_),
    "tangential_force_diff_max_N": max(dt_) if dt_ else None,
    "mean_speed_m_s": vmean, "velocity_diff_rms_m_s": rms(dv), "velocity_diff_max_m_s": max(dv),
    "mean_spin_1_s": wmean, "spin_diff_rms_1_s": rms(dw), "spin_diff_max_1_s": max(dw),
    "tangential_update_by_hand": replica,
    "kick_by_hand": {"max_velocity_diff_m_s": kick_dv, "max_velocity_m_s": kick_v,
                     "max_spin_diff_1_s": kick_dw, "max_spin_1_s": kick_w},
    "qsdem_command": cmd,
}
peer.write_json(os.path.join(out, "step_check.json"), report)
for k, v in report.items():
    if k != "qsdem_command":
        print(f"{k}: {v}")
