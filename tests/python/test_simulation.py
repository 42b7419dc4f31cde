"""Stepping from Python: the phase loop of a run, the same bits, the state as numpy arrays."""
import csv

import numpy as np
import pytest

import qsdem
from conftest import TINY


def rows_of(sim):
    """Runs every phase, keeping the measures of each sample point of the triaxial phase."""
    rows = []
    sim.on_sample(lambda point: rows.append(point) if point["phase_name"] == "triaxial" else None)
    sim.run()
    return rows


def test_sample_points_are_the_rows_of_the_cli_run(cli_run):
    sim = qsdem.Simulation(TINY, threads=1)
    rows = rows_of(sim)
    with open(cli_run / "series.csv") as f:
        series = list(csv.DictReader(f))
    # The phase's last row is its end (no callback then: no change could apply): every row before it.
    assert len(rows) == len(series) - 1 == 9
    for point, row in zip(rows, series):
        m = point["measures"]
        assert str(point["step"]) == row["step"]
        assert f"{m['mean_stress']:.10g}" == row["p_Pa"]
        assert f"{m['stress'][2, 2]:.10g}" == row["s33_Pa"]
        assert f"{m['friction_angle_deg']:.8g}" == row["phi_deg"]
        assert f"{m['ufr']:.8g}" == row["ufr"]
        assert f"{m['void_ratio']:.8g}" == row["void_ratio"]
        assert f"{m['fabric_dev']:.8g}" == row["fabric_dev"] and f"{m['z_mech']:.8g}" == row["z_mech"]
    assert sim.finished
    assert sim.records[1]["rows"] == 10


def test_steps_in_chunks_give_the_bits_of_one_phase_run():
    whole = qsdem.Simulation(TINY, threads=1)
    whole.run_phase()
    whole.step(40)
    parts = qsdem.Simulation(TINY, threads=1)
    taken = 0
    while parts.phase == 0:
        taken += parts.step(997)
    assert taken == whole.records[0]["steps"]
    for _ in range(8):
        assert parts.step(5) == 5
    assert parts.steps == whole.steps
    for name in ("positions", "orientations", "velocities", "spins", "forces", "moments", "cell", "stress"):
        assert np.array_equal(getattr(parts, name), getattr(whole, name)), name


def test_state_arrays():
    sim = qsdem.Simulation(TINY, threads=1)
    assert sim.phases == ["compaction", "triaxial"] and sim.phase == 0
    sim.run_phase()
    n = 120
    assert np.array_equal(sim.ids, np.arange(n))
    for name, width in (("positions", 3), ("orientations", 4), ("semi_axes", 3), ("velocities", 3),
                        ("spins", 3), ("forces", 3), ("moments", 3)):
        a = getattr(sim, name)
        assert a.shape == (n, width) and a.dtype == np.float64, name
    assert np.allclose(np.linalg.norm(sim.orientations, axis=1), 1, rtol=0, atol=1e-12)
    radii = sim.semi_axes[:, 0]
    assert np.all(sim.semi_axes == radii[:, None])  # spheres
    assert np.array_equal(np.sort(np.unique(radii)), [1.0e-3, 1.2e-3])
    # A copy: changing it changes nothing in the simulation.
    p = sim.positions
    p[:] = 0
    assert not np.array_equal(sim.positions, p)
    # The fractional positions are in the cell's frame: x = h s.
    s = np.linalg.solve(sim.cell, sim.positions.T).T
    assert np.allclose(sim.positions, s @ sim.cell.T)
    # Compacted isotropically to 390 kPa (compaction.stress; stress_tolerance 1 %).
    m = sim.measures()
    assert m["mean_stress"] == pytest.approx(390e3, rel=0.011)
    assert np.allclose(np.diag(sim.stress), 390e3, rtol=0.011)


def test_contacts_give_the_geometry_of_the_next_force_evaluation():
    """A step evaluates the forces at the positions it starts from: the contacts and positions read
    before a step are the geometry of the forces read after it. With that geometry, the overlap is
    r_i + r_j - |l| (spheres), Coulomb's bound |ft| <= mu fn holds (SPEC 4; mu = compaction.friction
    0.2, in the compaction phase) and the stress is Love-Weber's sum (docs/physics.md 7),
    sigma = sym(sum over contacts of f_j (x) l_ij) / V, compression positive."""
    sim = qsdem.Simulation(TINY, threads=1)
    sim.step(10000)  # within the compaction, contacts formed
    assert sim.phase == 0
    before, x, h, r = sim.contacts(), sim.positions, sim.cell, sim.semi_axes[:, 0]
    sim.step(1)
    after = sim.contacts()
    k = len(after["fn"])
    assert k == sim.measures()["contacts"] > 20
    for name, shape in (("normal", (k, 3)), ("point", (k, 3)), ("force", (k, 3)), ("image", (k, 3)),
                        ("i", (k,)), ("j", (k,)), ("overlap", (k,)), ("fn", (k,)), ("ft", (k,))):
        assert after[name].shape == shape, name
    assert np.all(after["i"] != after["j"]) and np.all(after["overlap"] > 0) and np.all(after["fn"] > 0)
    i, j = after["i"], after["j"]  # ids; the rows of x are in id order and the ids are 0 ... N-1
    l = x[j] + after["image"] @ h.T - x[i]
    d = np.linalg.norm(l, axis=1)
    assert np.allclose(after["overlap"], r[i] + r[j] - d, rtol=0, atol=1e-15)
    n = l / d[:, None]
    f = after["force"]
    fn = np.einsum("ka,ka->k", f, n)
    ft = np.linalg.norm(f - fn[:, None] * n, axis=1)
    assert np.all(ft <= 0.2 * fn * (1 + 1e-9))
    assert np.max(ft / fn) > 0.199  # some contacts slide: the bound is reached
    sum_fl = np.einsum("ka,kb->ab", f, l)
    sigma = (sum_fl + sum_fl.T) / 2 / abs(np.linalg.det(h))
    assert np.allclose(sigma, sim.stress, rtol=0, atol=1e-9 * np.trace(sim.stress) / 3)
    # The geometry read before the step is that of the pairs then in contact: the same normals.
    key = {(a, b, tuple(m)): c for c, (a, b, m) in enumerate(zip(before["i"], before["j"], before["image"]))}
    same = [(key[(a, b, tuple(m))], c) for c, (a, b, m) in enumerate(zip(i, j, after["image"]))
            if (a, b, tuple(m)) in key]
    assert len(same) > 0.9 * k
    for cb, ca in same:
        assert np.allclose(before["normal"][cb], n[ca], rtol=0, atol=1e-12)
        # For spheres the contact point is on the branch, at r_i - overlap / 2 from the centre of i.
        arm = before["point"][cb] - x[i[ca]]
        assert np.allclose(arm, (r[i[ca]] - (r[i[ca]] + r[j[ca]] - d[ca]) / 2) * n[ca], rtol=0, atol=1e-12)


def test_callback_changes_the_strain_rate():
    """Doubling eps' at the first row of the triaxial test. Its axial strain is planned (SPEC 3.4):
    c_t eps' = 0.01 / 250 = 4e-5 per step at first (the phase's end is force evaluation 250). Row 1
    of 10 is at force evaluation round(250 / 10) = 25, after 26 steps (1.04e-3); the remaining
    8.96e-3 at 8e-5 per step take 112 steps more: the phase ends after 26 + 112 + 1 = 139 steps."""
    sim = qsdem.Simulation(TINY, threads=1)
    sim.run_phase()
    seen = []

    def faster(point):
        seen.append(point["controls"]["33"])
        if point["row"] == 1:
            return {"33": 2 * point["controls"]["33"][1]}

    sim.on_sample(faster)
    sim.run_phase()
    assert seen[0] == ("strain_rate", 1.25e-4) and seen[1] == ("strain_rate", 2.5e-4)
    assert sim.records[1]["steps"] == 139
    assert sim.records[1]["final_e1"] == pytest.approx(0.01, abs=1e-9)


def test_a_prepared_sample_starts_at_its_second_phase(tmp_path):
    qsdem.prepare(TINY, out=tmp_path / "prep", threads=1)
    sim = qsdem.Simulation(TINY, sample=tmp_path / "prep", threads=1)
    assert sim.phase == 1
    assert sim.run_phase() == 251  # force evaluations 0 ... 250 (the case's comment: 250 steps of eps')
    assert sim.finished
    with pytest.raises(ValueError, match="every phase"):
        sim.step(1)


def test_callback_changes_friction_from_the_next_step():
    """friction = 0 from row 1 of the triaxial test (its force evaluation 25): Coulomb's bound
    |ft| <= mu fn (SPEC 4) leaves no tangential force from the next force evaluation on."""
    sim = qsdem.Simulation(TINY, threads=1)
    sim.run_phase()
    seen = []

    def frictionless(point):
        seen.append(point["controls"]["friction"])
        if point["row"] == 1:
            return {"friction": 0.0}

    sim.on_sample(frictionless)
    assert sim.step(26) == 26  # the steps of one call, though the loop paused for the change
    before = sim.contacts()  # forces of force evaluation 25, before the change
    assert np.max(before["ft"] / before["fn"]) > 0.1
    x, h = sim.positions, sim.cell  # the geometry of the next force evaluation
    sim.step(1)
    after = sim.contacts()
    l = x[after["j"]] + after["image"] @ h.T - x[after["i"]]
    n = l / np.linalg.norm(l, axis=1)[:, None]  # spheres
    f = after["force"]
    fn = np.einsum("ka,ka->k", f, n)
    assert np.all(fn > 0)
    assert np.all(np.linalg.norm(f - fn[:, None] * n, axis=1) <= 1e-12 * fn)
    sim.run_phase()
    assert seen[0] == 0.5 and all(mu == 0.0 for mu in seen[1:]) and len(seen) == 9


def test_a_change_to_the_same_values_changes_no_bit():
    """A callback that returns the current damping ratio and friction pauses the loop and rebuilds
    the phase's model at every sample point: the bits of a run without it."""
    plain = qsdem.Simulation(TINY, threads=1)
    plain.run()
    same = qsdem.Simulation(TINY, threads=1)
    same.on_sample(lambda point: {"damping_ratio": point["controls"]["damping_ratio"],
                                  "friction": point["controls"]["friction"]})
    same.run()
    for name in ("positions", "velocities", "spins", "forces", "cell", "stress"):
        assert np.array_equal(getattr(same, name), getattr(plain, name)), name
    keys = ("steps", "rows", "peak_phi_deg", "final_e1", "final_ev", "mean_ufr")
    assert [[r[k] for k in keys] for r in same.records] == [[r[k] for k in keys] for r in plain.records]


def test_callback_changes_the_damping_ratio():
    sim = qsdem.Simulation(TINY, threads=1)
    sim.run_phase()
    plain = qsdem.Simulation(TINY, threads=1)
    plain.run_phase()
    ratios = []

    def more_damping(point):
        ratios.append(point["controls"]["damping_ratio"])
        return {"damping_ratio": 0.05}

    sim.on_sample(more_damping)
    sim.step(60)
    plain.step(60)
    assert ratios == [0.005, 0.05]
    assert not np.array_equal(sim.velocities, plain.velocities)
    sim.on_sample(lambda point: {"damping_ratio": -0.1})
    with pytest.raises(ValueError, match="damping_ratio = -0.1"):
        sim.run_phase()


RESUMABLE = r'''
import math, sys
import qsdem
case, checkpoint, mode = sys.argv[1], sys.argv[2], sys.argv[3]  # "fresh", "resume" or the step to stop after
stop_at = int(mode) if mode.isdigit() else -1


def hold(point):  # the callback of examples/python/hold_imom.py, target 1 %
    imom, rate = point["measures"]["imom"], point["controls"]["33"][1]
    return {"33": rate * min(2.0, max(0.5, math.sqrt(0.01 / imom)))} if point["phase_name"] == "triaxial" else None


sim = qsdem.Simulation(checkpoint=checkpoint, threads=1) if mode == "resume" else qsdem.Simulation(case, threads=1)
sim.on_sample(hold)
while not sim.finished:
    sim.step(300)
    sim.save(checkpoint)
    if 0 <= stop_at <= sim.steps:
        print("saved", sim.steps, flush=True)
        import time
        time.sleep(60)  # killed here
sim.save(checkpoint)
'''


def final_state(sim):
    return {name: getattr(sim, name) for name in ("positions", "orientations", "velocities", "spins", "cell", "stress")}


def test_a_callback_run_killed_resumes_from_its_checkpoint_to_the_same_bits(tmp_path):
    """A process steps the tiny case 300 steps at a time with a callback that changes eps' at every sample point
    of the triaxial phase, saving a checkpoint after each chunk; it is SIGKILLed in the triaxial phase. A new
    process continues from the checkpoint with the same callback: its end is bit for bit that of a process that
    was never killed."""
    import os, signal, subprocess, sys
    script = tmp_path / "resumable.py"
    script.write_text(RESUMABLE)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    whole = tmp_path / "whole.qsck"
    subprocess.run([sys.executable, script, TINY, whole, "fresh"], check=True, env=env, capture_output=True)
    sim = qsdem.Simulation(TINY, threads=1)
    sim.run_phase()
    compaction = sim.steps
    killed = tmp_path / "killed.qsck"
    p = subprocess.Popen([sys.executable, script, TINY, killed, str(compaction + 3000)], env=env,
                         stdout=subprocess.PIPE, text=True)
    saved = p.stdout.readline().split()
    p.send_signal(signal.SIGKILL)
    p.wait()
    assert saved[0] == "saved" and int(saved[1]) >= compaction + 3000
    half = qsdem.Simulation(checkpoint=killed)
    assert half.phase == 1 and not half.finished and half.steps == int(saved[1])
    subprocess.run([sys.executable, script, TINY, killed, "resume"], check=True, env=env, capture_output=True)
    a, b = qsdem.Simulation(checkpoint=whole), qsdem.Simulation(checkpoint=killed)
    assert a.finished and b.finished and a.steps == b.steps
    assert a.records[1]["rows"] == b.records[1]["rows"] == 10
    for name, value in final_state(a).items():
        assert np.array_equal(value, final_state(b)[name]), name


def test_save_is_refused_after_a_change_of_friction(tmp_path):
    sim = qsdem.Simulation(TINY, threads=1)
    sim.run_phase()
    sim.on_sample(lambda point: {"friction": 0.3})
    sim.step(2000)
    with pytest.raises(qsdem.RunError, match="friction or the damping ratio of phase 'triaxial'"):
        sim.save(tmp_path / "c.qsck")
    with pytest.raises(ValueError, match="not both"):
        qsdem.Simulation(TINY, checkpoint=tmp_path / "c.qsck")
    with pytest.raises(qsdem.CaseError):
        qsdem.Simulation(checkpoint=tmp_path / "missing.qsck")
