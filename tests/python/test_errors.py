"""Bad input raises a clear exception (the CLI's message for a case), never a crash."""
import numpy as np
import pytest

import qsdem
from conftest import TINY, cli


def cli_message(*sets):
    """The message `qsdem run --dry-run` prints for the tiny case with these --set strings."""
    args = ["run", TINY, "--dry-run"]
    for s in sets:
        args += ["--set", s]
    p = cli(*args, check=False)
    assert p.returncode == 2, p.stderr
    prefix = "qsdem: input error: "
    assert p.stderr.startswith(prefix), p.stderr
    return p.stderr[len(prefix):].rstrip("\n")


@pytest.mark.parametrize("key, value, text, words", [
    ("damping.modell", "od", "damping.modell=od", ["damping.modell"]),                      # unknown key
    ("triaxial.strain_rate", "fast", "triaxial.strain_rate=fast", ["triaxial.strain_rate", "fast"]),  # wrong type
    ("triaxial.strain_rate", -1e-5, "triaxial.strain_rate=-1e-05", ["triaxial.strain_rate", "-1e-05"]),  # negative
    ("damping.model", "xd", "damping.model=xd", ["damping.model", "xd", "nd", "od"]),      # not among the allowed
])
def test_case_errors_carry_the_cli_message(key, value, text, words):
    with pytest.raises(qsdem.CaseError) as e:
        qsdem.check_case(TINY, set={key: value})
    assert str(e.value) == cli_message(text)
    for w in words:
        assert w in str(e.value)
    assert isinstance(e.value, ValueError)


def test_errors_of_a_run_come_before_the_directory_is_touched(tmp_path):
    with pytest.raises(qsdem.CaseError, match="triaxial.strain_rate"):
        qsdem.run(TINY, out=tmp_path / "x", triaxial__strain_rate=-1.0)
    assert not (tmp_path / "x").exists()
    with pytest.raises(qsdem.CaseError, match="triaxial.strain_rate"):
        qsdem.Simulation(TINY, set={"triaxial.strain_rate": 0})


def test_arrays_of_the_wrong_shape_or_kind():
    # A list where one number goes, a 2-d array where a table of particles goes.
    with pytest.raises(qsdem.CaseError, match="triaxial.strain_rate"):
        qsdem.check_case(TINY, set={"triaxial.strain_rate": np.array([1e-5, 2e-5])})
    with pytest.raises(qsdem.CaseError, match="sample.particles"):
        qsdem.check_case(TINY, set={"sample.particles": np.zeros((2, 2))})
    with pytest.raises(TypeError, match="material.density"):
        qsdem.check_case(TINY, set={"material.density": object()})


def test_case_arguments():
    with pytest.raises(qsdem.CaseError, match="no-such-case.toml"):
        qsdem.check_case("no-such-case.toml")
    with pytest.raises(TypeError, match="case must be"):
        qsdem.check_case(42)
    with pytest.raises(qsdem.CaseError):
        qsdem.check_case("name = \n[[[")  # not TOML
    with pytest.raises(TypeError, match="set must be"):
        qsdem.check_case(TINY, set=3)
    with pytest.raises(TypeError, match="key=value"):
        qsdem.check_case(TINY, set=["damping.model"])
    assert qsdem.check_case(None)["name"] == "spheres-A-small"
    assert qsdem.check_case(TINY, damping__ratio="1 %")["protocol"][1]["damping"]["ratio"] == pytest.approx(0.01)


def test_threads():
    with pytest.raises(qsdem.CaseError, match="threads = -1"):
        qsdem.Simulation(TINY, threads=-1)
    with pytest.raises(TypeError, match="threads"):
        qsdem.run(TINY, out="unused", threads="2")


def test_stepping_errors():
    sim = qsdem.Simulation(TINY, threads=1)
    with pytest.raises(ValueError, match="n = 0"):
        sim.step(0)
    with pytest.raises(TypeError):
        sim.step("10")
    with pytest.raises(TypeError, match="not callable"):
        sim.on_sample(3)
    # Compaction: every component is stress-controlled (the shears to 0 Pa).
    for change, error, text in (({"44": 1.0}, ValueError, "unknown control '44'"),
                                ({"11": -5.0}, ValueError, "stress target 11"),
                                ({"11": "big"}, TypeError, "'11' must be a number"),
                                ({"11": True}, TypeError, "'11' must be a number"),
                                ({"11": float("nan")}, ValueError, "not finite"),
                                ({"max_strain_rate": 0}, ValueError, "max_strain_rate")):
        sim.on_sample(lambda point: change)
        with pytest.raises(error, match=text):
            sim.run_phase()
    sim.on_sample(lambda point: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        sim.run_phase()
    sim.on_sample(lambda point: [1])
    with pytest.raises(TypeError, match="dict"):
        sim.run_phase()
    sim.on_sample(None)
    sim.run_phase()  # the compaction ends: still usable after the errors
    # Triaxial test: the shears are fixed.
    sim.on_sample(lambda point: {"12": 1.0})
    with pytest.raises(ValueError, match="component 12 is fixed"):
        sim.run_phase()
    sim.on_sample(None)
    assert sim.step(5) == 5


STEP_UNTIL_INTERRUPTED = r"""
import sys, qsdem
sim = qsdem.Simulation(sys.argv[1], threads=1, triaxial__strain_rate=1e-9)  # 10^8 triaxial steps
sim.run_phase()
print("ready", flush=True)
try:
    sim.run_phase()
except KeyboardInterrupt:
    print("interrupted at", sim.phase_steps, flush=True)
print("then", sim.step(5), sim.phase_steps, flush=True)
"""


def test_ctrl_c_stops_the_stepping_and_leaves_it_usable():
    import signal
    import subprocess
    import sys
    import time
    p = subprocess.Popen([sys.executable, "-c", STEP_UNTIL_INTERRUPTED, str(TINY)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    assert p.stdout.readline() == "ready\n"
    time.sleep(0.5)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=60)
    assert p.returncode == 0, err
    lines = out.splitlines()
    assert lines[0].startswith("interrupted at ")
    stopped = int(lines[0].split()[-1])
    assert 0 < stopped < 10**8
    assert lines[1] == f"then 5 {stopped + 5}"


RUN_UNTIL_INTERRUPTED = r"""
import sys, qsdem
print("ready", flush=True)
try:
    qsdem.run(sys.argv[1], out=sys.argv[2], threads=1, triaxial__strain_rate=1e-9)
except qsdem.Interrupted as e:
    print("interrupted:", isinstance(e, KeyboardInterrupt), flush=True)
"""


def test_ctrl_c_stops_a_run_with_its_checkpoint(tmp_path):
    import signal
    import subprocess
    import sys
    import time
    out = tmp_path / "run"
    p = subprocess.Popen([sys.executable, "-c", RUN_UNTIL_INTERRUPTED, str(TINY), str(out)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    assert p.stdout.readline() == "ready\n"
    time.sleep(2)
    p.send_signal(signal.SIGINT)
    stdout, err = p.communicate(timeout=60)
    assert p.returncode == 0, err
    assert stdout == "interrupted: True\n"
    assert (out / "checkpoint.qsck").exists() and not (out / "summary.json").exists()
