"""Every example of examples/python runs (on the tiny case, with one thread) and does what it says."""
import os
import pathlib
import subprocess
import sys

from conftest import TINY, cli

EXAMPLES = pathlib.Path(__file__).resolve().parents[2] / "examples" / "python"
TESTED = {"triaxial.py", "stepping.py", "stress_path.py", "hold_imom.py", "fig9_pandas.py"}


def run_example(name, *args):
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    p = subprocess.run([sys.executable, EXAMPLES / name, *map(str, args)], capture_output=True, text=True, env=env)
    assert p.returncode == 0, p.stderr
    return p.stdout


def test_every_example_is_tested():
    assert {p.name for p in EXAMPLES.glob("*.py")} == TESTED


def test_triaxial_writes_the_cli_series(tmp_path, cli_run):
    out = run_example("triaxial.py", tmp_path / "ex", TINY)
    assert "10 rows" in out
    assert (tmp_path / "ex" / "series.csv").read_bytes() == (cli_run / "series.csv").read_bytes()


def test_triaxial_passes_its_overrides(tmp_path):
    run_example("triaxial.py", tmp_path / "ex", TINY, "triaxial.sample_points=5", "damping.model=od")
    lines = (tmp_path / "ex" / "series.csv").read_text().splitlines()
    assert len(lines) == 1 + 5
    assert "model = 'od'" in (tmp_path / "ex" / "case.toml").read_text()


def test_stepping_slows_the_loading_when_unbalanced():
    """A UFR bound of 0 is exceeded at every sample point: each of the 9 rows before the last halves
    eps', and the test still ends at its planned axial strain, 1 %."""
    out = run_example("stepping.py", TINY, 0, 500).splitlines()
    assert out[0].startswith("compacted: p = 39")  # 390 kPa (compaction.stress)
    halvings = [line for line in out if line.startswith("row ")]
    assert len(halvings) == 9
    rate = 1.25e-4
    for line in halvings:
        before, after = (float(v) for v in line.rsplit("eps' ", 1)[1].split(" -> "))
        assert before == float(f"{rate:.4g}") and after == float(f"{rate / 2:.4g}")
        rate /= 2
    assert any(line.startswith("step ") for line in out)
    assert out[-1].startswith("triaxial: ") and "10 rows" in out[-1] and "final e1 1.000 %" in out[-1]


def test_stress_path_follows_its_slope():
    """dq/dp' = 1.5 from 390 kPa: the conventional test (sigma_3 held) would be -q/(3 p'0) off this path, about
    -30 % of p'0 at q = 350 kPa; the callback keeps every row of the second half within 6 % (the lag of one sample
    interval), with q above 0.5 p'0 on some row."""
    out = run_example("stress_path.py", TINY, 1.5, "triaxial.strain_rate=1e-5", "triaxial.sample_points=20").splitlines()
    assert out[0].startswith("compacted: p'0 = 39")
    rows = [line for line in out if line.startswith("row ")]
    assert len(rows) == 19
    q = [float(line.split(" q ")[1].split(" kPa")[0]) for line in rows]
    assert max(q) > 0.5 * 390
    assert out[-1].startswith("path: 19 points")
    assert float(out[-1].split("at most ")[1].split(" %")[0]) < 6


def test_hold_imom_holds_the_index_by_the_rate():
    """Target IMom 1 %: the rate falls from the case's 1.25e-4 and the mean IMom of the second half lies within a
    factor 1.5 of the target; the test still ends at its planned axial strain."""
    out = run_example("hold_imom.py", TINY, 0.01, "triaxial.sample_points=40").splitlines()
    rows = [line for line in out if line.startswith("row ")]
    assert len(rows) == 39
    last_rate = float(rows[-1].rsplit("-> ", 1)[1])
    assert last_rate < 1.25e-4 / 4
    assert out[-1].startswith("triaxial: ") and "final e1 1.000 %" in out[-1]
    mean = float(out[-1].split("second half ")[1].split(" %")[0])
    assert 1 / 1.5 < mean < 1.5


def test_fig9_from_pandas_is_the_analysis_fit(tmp_path):
    """On the committed paper-size study: each (sample, model) fitted again with numpy gives the analysis' a and b
    to the printed digits, and the figure is drawn."""
    out = run_example("fig9_pandas.py", EXAMPLES.parents[1] / "docs" / "results" / "paper-full", tmp_path / "f.png")
    fits = [line for line in out.splitlines() if "eps'^" in line]
    assert {line.split(":")[0] for line in fits} == {"A nd", "A od", "B nd", "B od"}
    for line in fits:
        ours, theirs = line.split("IMom = ")[1].split(" (the analysis: ")
        assert ours == theirs.split(";")[0], line
    assert (tmp_path / "f.png").stat().st_size > 10000


def test_triaxial_of_the_default_case_writes_the_cli_series(tmp_path):
    """The built-in default case (examples/spheres-A-small.toml, about 25 s a run on two cores)."""
    cli("run", "--out", tmp_path / "cli", "--quiet")
    env = {**os.environ}
    env.pop("OMP_NUM_THREADS", None)  # all cores, as the CLI (no result depends on it)
    p = subprocess.run([sys.executable, EXAMPLES / "triaxial.py", tmp_path / "py"], capture_output=True, text=True,
                       env=env)
    assert p.returncode == 0, p.stderr
    assert "250 rows" in p.stdout
    assert (tmp_path / "py" / "series.csv").read_bytes() == (tmp_path / "cli" / "series.csv").read_bytes()
