"""Shared pieces of the YADE scripts of bench/yade (run inside `yade -n -x`).

The peer test: a periodic drained triaxial test of about 1000 spheres of
Sample A's grading (equal-volume spheres, examples/spheres-A-small.toml), Hertz-Mindlin
(Law2_ScGeom_MindlinPhys_Mindlin, no contact damping), Cundall's local damping
(NewtonIntegrator.damping), PeriTriaxController, the time step and loading rate of qsdem
(docs/physics.md 5.1, 8.3). Everything in SI units.
"""

import json
import math
import os
import random

from yade import *  # noqa: F401,F403  (O, engines, Vector3, Matrix3: the YADE namespace)
from yade import utils

# Material and grading of examples/spheres-A-small.toml (paper Table 1, scaled to 1000
# particles as qsdem scales it: round(count * 1000 / 8000)).
DENSITY = 2650.0
YOUNG = 78e9
POISSON = 0.3
GRADING = [(2.13e-3, 7284), (6.55e-3, 498), (11.19e-3, 150), (16.03e-3, 68)]  # diameter, count
TOTAL = 1000
STEP_RATIO = 0.32
STRESS = 390e3
COMPACTION_FRICTION = 0.2
TRIAXIAL_FRICTION = 0.5
INITIAL_SOLID_FRACTION = 0.15
COMPACTION_MAX_RATE = 2e-5  # per t_c, as compaction.max_strain_rate
LATERAL_RATE_FACTOR = 10.0  # as triaxial.lateral_rate_factor


def counts():
    written = sum(c for _, c in GRADING)
    # std::lround: halves away from zero
    return [(d, max(1, int(math.floor(c * TOTAL / written + 0.5)))) for d, c in GRADING]


def radii():
    out = []
    for d, c in sorted(counts(), reverse=True):  # largest first, as qsdem generates
        out += [d / 2] * c
    return out


def r_min():
    return min(d for d, _ in GRADING) / 2


def critical_time():
    return 2 * r_min() * math.sqrt(DENSITY / YOUNG)  # t_c, docs/physics.md 5.1


def time_step():
    return STEP_RATIO * critical_time()


def loose_cloud(seed):
    """Random non-overlapping centres in a cubic periodic cell at INITIAL_SOLID_FRACTION, largest
    first (as qsdem's generator; not the same random numbers)."""
    rs = radii()
    vs = sum(4.0 / 3.0 * math.pi * r ** 3 for r in rs)
    side = (vs / INITIAL_SOLID_FRACTION) ** (1.0 / 3.0)
    rng = random.Random(seed)
    placed = []
    for r in rs:
        for _ in range(100000):
            c = [rng.random() * side for _ in range(3)]
            ok = True
            for (q, rq) in placed:
                d2 = 0.0
                for k in range(3):
                    dk = c[k] - q[k]
                    dk -= side * round(dk / side)
                    d2 += dk * dk
                if d2 < (r + rq) ** 2:
                    ok = False
                    break
            if ok:
                placed.append((c, r))
                break
        else:
            raise RuntimeError(f"cannot place a sphere of radius {r} in the loose cell")
    return side, placed


def material(friction):
    return FrictMat(young=YOUNG, poisson=POISSON, density=DENSITY, frictionAngle=math.atan(friction),
                    label="grains")


def engines(damping, controller):
    return [
        ForceResetter(),
        InsertionSortCollider([Bo1_Sphere_Aabb()]),
        InteractionLoop([Ig2_Sphere_Sphere_ScGeom()], [Ip2_FrictMat_FrictMat_MindlinPhys()],
                        [Law2_ScGeom_MindlinPhys_Mindlin()]),
        controller,
        NewtonIntegrator(damping=damping, label="newton"),
    ]


def stress():
    """Love-Weber stress, compression positive (YADE's getStress is tension positive)."""
    s = utils.getStress()
    return [[-s[a, b] for b in range(3)] for a in range(3)]


def contacts():
    return sum(1 for i in O.interactions if i.isReal)


def measures():
    """One row: the stresses, p, q, phi (principal and axial-lateral), void ratio, Cn, UFR, E_kin."""
    s = stress()
    ev = sorted(symmetric_eigenvalues(s), reverse=True)
    s1, s2, s3 = ev
    p = (s1 + s2 + s3) / 3
    q = math.sqrt(((s1 - s2) ** 2 + (s2 - s3) ** 2 + (s3 - s1) ** 2) / 2)
    sl = 0.5 * (s[0][0] + s[1][1])
    phi = asin_deg(s1 - s3, s1 + s3)
    phi_al = asin_deg(s[2][2] - sl, s[2][2] + sl)
    vol = O.cell.hSize.determinant()
    vs = sum(4.0 / 3.0 * math.pi * b.shape.radius ** 3 for b in O.bodies)
    return {"s11_Pa": s[0][0], "s22_Pa": s[1][1], "s33_Pa": s[2][2], "p_Pa": p, "q_Pa": q, "phi_deg": phi,
            "phi_al_deg": phi_al, "void_ratio": (vol - vs) / vs, "cn": 2.0 * contacts() / len(O.bodies),
            "ufr": utils.unbalancedForce(), "ekin_J": utils.kineticEnergy(), "volume_m3": vol}


def asin_deg(num, den):
    """asin(num / den) in degrees, 0 when den <= 0 (as qsdem, docs/physics.md 7)."""
    return math.degrees(math.asin(max(-1.0, min(1.0, num / den)))) if den > 0 else 0.0


def symmetric_eigenvalues(s):
    """Eigenvalues of a symmetric 3x3 matrix (Jacobi rotations; no numpy needed)."""
    a = [row[:] for row in s]
    for _ in range(50):
        off = sum(a[i][j] ** 2 for i in range(3) for j in range(3) if i != j)
        if off < 1e-30 * max(1.0, sum(a[i][i] ** 2 for i in range(3))):
            break
        for p in range(3):
            for q in range(p + 1, 3):
                if abs(a[p][q]) < 1e-300:
                    continue
                theta = 0.5 * math.atan2(2 * a[p][q], a[q][q] - a[p][p])
                c, sn = math.cos(theta), math.sin(theta)
                for k in range(3):
                    akp, akq = a[k][p], a[k][q]
                    a[k][p], a[k][q] = c * akp - sn * akq, sn * akp + c * akq
                for k in range(3):
                    apk, aqk = a[p][k], a[q][k]
                    a[p][k], a[q][k] = c * apk - sn * aqk, sn * apk + c * aqk
    return [a[0][0], a[1][1], a[2][2]]


def next_cell():
    """The cell (I + dt L) hSize that YADE's next force evaluation sees: YADE moves the cell at the
    start of a step, the positions with the kick after it."""
    hs = O.cell.hSize
    return hs + O.dt * O.cell.velGrad * hs


def velocity_gradient():
    """The cell's velocity gradient L, 9 numbers row by row (--velocity-gradient of the peer tools)."""
    g = O.cell.velGrad
    return " ".join(repr(float(g[a, b])) for a in range(3) for b in range(3))


def write_packing(path, cell=None):
    """The bodies as a qsdem packing (docs/packing-format.md), in body-id order, centres as YADE has
    them (unwrapped: the image keys of write_contacts refer to them), in the cell matrix `cell`
    (default: hSize)."""
    hs = O.cell.hSize if cell is None else cell
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        f.write("# written by bench/yade: a YADE periodic packing; lengths in metres; centres unwrapped\n")
        f.write("format qsdem-packing 1\n")
        f.write("cell " + " ".join(repr(float(hs[i, j])) for i in range(3) for j in range(3)) + "\n")
        f.write(f"particles {len(O.bodies)}\n")
        for b in O.bodies:
            x, r = b.state.pos, b.shape.radius
            f.write(f"{x[0]!r} {x[1]!r} {x[2]!r} {r!r} {r!r} {r!r} 1 0 0 0\n")
    os.replace(tmp, path)


def write_motion(path):
    """Per body in id order: velocity and angular velocity as YADE keeps them (total, with the mean
    field: qsdem_peer_step and qsdem_peer_sample take the fluctuation v - L x)."""
    with open(path, "w") as f:
        for b in O.bodies:
            v, w = b.state.vel, b.state.angVel
            f.write(f"{v[0]!r} {v[1]!r} {v[2]!r} {w[0]!r} {w[1]!r} {w[2]!r}\n")


def write_contacts(path):
    """The contacts with their history: per real interaction, id1 id2, the image of id2 (cellDist),
    the normal, the overlap, the normal force and the shear force on id2 (N, MindlinPhys.shearForce:
    the force on id1 is -(normalForce + shearForce))."""
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        f.write("# id1 id2 c1 c2 c3 nx ny nz overlap fnx fny fnz ftx fty ftz\n")
        for i in O.interactions:
            if not i.isReal:
                continue
            c, n, fn, ft = i.cellDist, i.geom.normal, i.phys.normalForce, i.phys.shearForce
            f.write(f"{i.id1} {i.id2} {c[0]} {c[1]} {c[2]} {n[0]!r} {n[1]!r} {n[2]!r} "
                    f"{i.geom.penetrationDepth!r} {fn[0]!r} {fn[1]!r} {fn[2]!r} {ft[0]!r} {ft[1]!r} {ft[2]!r}\n")
    os.replace(tmp, path)


def write_state(d):
    """The state before a step, for qsdem_peer_step: positions with the cell they belong to (YADE
    integrates the cell at the start of the next step, so the positions are those of
    (I + dt L) hSize), contacts and velocities, in directory d."""
    os.makedirs(d, exist_ok=True)
    write_packing(os.path.join(d, "packing"), next_cell())
    write_contacts(os.path.join(d, "contacts.txt"))
    write_motion(os.path.join(d, "motion.txt"))


def peer_step_command(tool, case, alpha, mu, state, gradient, steps, out, *extra):
    """qsdem_peer_step (`tool`) on the state write_state put in `state`: local damping alpha and
    friction mu on CASE, the velocity gradient `gradient` (9 numbers), `steps` steps, into `out`."""
    return [tool, "--case", case, "--set", "damping.model=local", "--set", f"damping.ratio={alpha!r}",
            "--set", f"triaxial.friction={mu!r}", "--packing", os.path.join(state, "packing"),
            "--contacts", os.path.join(state, "contacts.txt"), "--motion", os.path.join(state, "motion.txt"),
            "--velocity-gradient", gradient, "--steps", str(steps), *extra, "--out", out]


def write_json(path, obj):
    tmp = path + ".tmp"
    with open(tmp, "w") as f:
        json.dump(obj, f, indent=2)
        f.write("\n")
    os.replace(tmp, path)
