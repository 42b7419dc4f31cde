"""YADE's stress servo (PeriTriaxController) against qsdem's (docs/physics.md 3.5) on the same
state: the lateral rates each chooses for the same stress error, and the stress each then reaches,
step by step (bench/yade, issue of the slow-rate peer check).

    yade -n -j1 -x bench/yade/servo_check.py SCENE.yade.gz QSDEM_PEER_STEP CASE OUTDIR
         [--alpha A] [--friction MU] [--warmup N] [--steps K] [--errors E1,E2,...] [--rate EPS]

SCENE: a scene of compact.py. YADE runs WARMUP steps (default 200) in a fixed cell with friction
MU and local damping A, so that every contact has its tangential history; the state is written
(as step_check.py does) and both codes start from it. For each relative error E (default
0.01,-0.01,0.1) the target of axes 1 and 2 is set to sigma_t = mean(s11, s22) / (1 - E) of the
first force evaluation, axis 3 is held, and each code runs K steps (default 400) on its own
servo: YADE's PeriTriaxController as bench/yade/triaxial.py sets it up (globUpdate 1, its default
growDamping), qsdem's PI law through QSDEM_PEER_STEP --servo. Both rates are capped at
LATERAL_RATE_FACTOR * EPS / t_c (EPS default 1e-7, the slow rate of the peer check; 0: no cap).
Writes OUTDIR/servo_check.json (per error: the first step's rates, the fraction of the error the
affine response would remove in one step, the steps to halve the error's size (RMS over the two
axes), each axis's largest overshoot, the RMS error over all steps and over the second half) and
OUTDIR/servo-E.csv (per step, each axis's relative error in each code).
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
options = {"--alpha": 0.1, "--friction": 0.5, "--warmup": 200, "--steps": 400, "--errors": "0.01,-0.01,0.1",
           "--rate": 1e-7}
rest = args[4:]
while rest:
    key = rest.pop(0)
    if key not in options or not rest:
        raise SystemExit(f"unknown option or missing value: {key}")
    options[key] = type(options[key])(rest.pop(0))
alpha, mu, warmup, steps, rate = (options[k] for k in ("--alpha", "--friction", "--warmup", "--steps", "--rate"))
errors = [float(x) for x in options["--errors"].split(",")]
os.makedirs(out, exist_ok=True)
cap = peer.LATERAL_RATE_FACTOR * rate / peer.critical_time() if rate > 0 else 1e3  # 1/s

O.load(scene)
utils.setContactFriction(math.atan(mu))
O.engines = [e for e in O.engines if not isinstance(e, (PeriTriaxController, PyRunner))]
newton = [e for e in O.engines if isinstance(e, NewtonIntegrator)][0]
newton.damping = alpha
O.cell.velGrad = Matrix3.Zero
O.run(warmup, True)
before = os.path.join(out, "before")
peer.write_state(before)
saved = os.path.join(out, "before.yade.gz")
O.save(saved)

rows = []


def record_stress():
    s = peer.stress()  # this step's forces on this step's positions: what the controller reads
    rows.append([s[0][0], s[1][1]])


def record_rate():
    rows[-1] += [O.cell.velGrad[0, 0], O.cell.velGrad[1, 1]]


def yade_run(target, k):
    """K steps of YADE's servo from the saved state: per step s11, s22 and the rates L11, L22."""
    O.load(saved)
    O.cell.trsf = Matrix3.Identity  # axis 3 strain-controlled at its start: held
    rows.clear()
    ctrl = PeriTriaxController(goal=Vector3(-target, -target, 0), stressMask=3,
                               maxStrainRate=Vector3(cap, cap, cap), relStressTol=1.0, absStressTol=1e30,
                               maxUnbalanced=-1, globUpdate=1, label="servo")
    integrator = [e for e in O.engines if isinstance(e, NewtonIntegrator)]
    engines = [e for e in O.engines if not isinstance(e, NewtonIntegrator)]
    O.engines = engines + [PyRunner(iterPeriod=1, command="record_stress()"), ctrl,
                           PyRunner(iterPeriod=1, command="record_rate()")] + integrator
    O.run(k, True)
    return [list(r) for r in rows], ctrl.growDamping, list(ctrl.stiff)


def qsdem_run(target, k, d):
    cmd = peer.peer_step_command(tool, case, alpha, mu, before, "0 0 0 0 0 0 0 0 0", k, d,
                                 "--servo", f"{target!r} {cap!r}")
    done = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    if done.returncode != 0:
        raise SystemExit(f"qsdem_peer_step failed ({done.returncode}): {' '.join(cmd)}\n{done.stdout}")
    table = [[float(x) for x in l.split()] for l in open(os.path.join(d, "servo.txt")) if not l.startswith("#")]
    return [[r[1], r[2], r[6], r[7]] for r in table], [r[4] for r in table[:1]] + [r[5] for r in table[:1]], cmd


# The stress of the first force evaluation (both codes read the same forces there: step_check.py).
first, _, _ = yade_run(1.0, 1)
mean0 = 0.5 * (first[0][0] + first[0][1])


def rel_error(r, target):
    return [(target - r[0]) / target, (target - r[1]) / target]


def halving(size):
    """The first step at which the error's size (RMS over the two axes) is half its first value."""
    for n, x in enumerate(size):
        if x <= 0.5 * size[0]:
            return n
    return None


def overshoot(errs):
    """How far one axis's error goes past zero, to the side opposite its first error."""
    side = 1.0 if errs[0] > 0 else -1.0
    return max(0.0, max(-side * x for x in errs))


report = {"scene": scene, "alpha": alpha, "friction": mu, "warmup": warmup, "steps": steps, "rate": rate,
          "cap_per_s": cap, "dt_s": O.dt, "cases": []}
for e in errors:
    target = mean0 / (1 - e)
    y, grow, ystiff = yade_run(target, steps)
    q, qstiff, cmd = qsdem_run(target, steps, os.path.join(out, f"qsdem-{e!r}"))
    case_rows = []  # step, then the relative error of axes 1 and 2 in YADE, then in qsdem
    for n in range(min(len(y), len(q))):
        case_rows.append([n] + rel_error(y[n], target) + rel_error(q[n], target))
    with open(os.path.join(out, f"servo-{e!r}.csv"), "w") as f:
        f.write("step,error_11_yade,error_22_yade,error_11_qsdem,error_22_qsdem\n")
        for r in case_rows:
            f.write(",".join(repr(x) for x in r) + "\n")
    size = {"yade": [math.hypot(r[1], r[2]) / math.sqrt(2) for r in case_rows],
            "qsdem": [math.hypot(r[3], r[4]) / math.sqrt(2) for r in case_rows]}
    ey0, eq0 = rel_error(y[0], target), rel_error(q[0], target)
    # The fraction of the error that the affine response (qsdem's C_kk, the same contacts in both)
    # would remove with each code's first rate: -L dt C / (sigma_t - sigma).
    removed = {code: [-r[2 + k] * O.dt * qstiff[k] / (target - r[k]) for k in range(2)] for code, r in
               (("yade", y[0]), ("qsdem", q[0]))}
    report["cases"].append({
        "error": e, "target_Pa": target,
        "first_stress_Pa": {"yade": y[0][:2], "qsdem": q[0][:2]},
        "first_error": {"yade": ey0, "qsdem": eq0},
        "first_rate_per_s": {"yade": y[0][2:4], "qsdem": q[0][2:4]},
        "affine_stiffness_Pa": qstiff, "yade_stiff_N_per_m": ystiff, "yade_grow_damping": grow,
        "affine_fraction_removed_first_step": removed,
        "steps_to_half_error": {code: halving(v) for code, v in size.items()},
        "largest_overshoot": {code: [overshoot([r[c + k] for r in case_rows]) for k in range(2)]
                              for code, c in (("yade", 1), ("qsdem", 3))},
        "error_at_end": {"yade": case_rows[-1][1:3], "qsdem": case_rows[-1][3:5]},
        "rms_error": {code: math.sqrt(sum(x * x for x in v) / len(v)) for code, v in size.items()},
        "rms_error_second_half": {code: math.sqrt(sum(x * x for x in v[len(v) // 2:]) / (len(v) - len(v) // 2))
                                  for code, v in size.items()},
        "qsdem_command": cmd,
    })
peer.write_json(os.path.join(out, "servo_check.json"), report)
for c in report["cases"]:
    print(f"error {c['error']}: first rates yade {c['first_rate_per_s']['yade']} qsdem {c['first_rate_per_s']['qsdem']}; "
          f"affine fraction removed yade {c['affine_fraction_removed_first_step']['yade']} "
          f"qsdem {c['affine_fraction_removed_first_step']['qsdem']}; half in {c['steps_to_half_error']}; "
          f"overshoot {c['largest_overshoot']}; end {c['error_at_end']}")
