"""Whole runs from Python give the CLI's files, bit for bit; load() reads them back."""
import json
import shutil
import pathlib

import numpy as np
import pytest

import qsdem
from conftest import TINY, cli

SAME_FILES = ["series.csv", "compaction.csv", "classes.csv", "compacted.packing", "final.packing", "case.toml"]


def test_run_writes_the_cli_files_bit_for_bit(cli_run, py_run):
    out, _ = py_run
    for name in SAME_FILES:
        assert (out / name).read_bytes() == (cli_run / name).read_bytes(), name


def test_summary_is_the_cli_summary_but_for_times(cli_run, py_run):
    out, returned = py_run
    mine = json.loads((out / "summary.json").read_text())
    theirs = json.loads((cli_run / "summary.json").read_text())
    assert returned == mine
    for key in ("steps", "void_ratio_after_compaction", "peak_phi_deg", "final_ev", "mean_ufr", "config", "derived"):
        assert mine[key] == theirs[key], key


def test_load_round_trip(py_run):
    out, summary = py_run
    r = qsdem.load(out, pandas=False)
    assert r.summary == summary
    assert len(r.series) == summary["triaxial"]["rows"] == 10
    lines = (out / "series.csv").read_text().splitlines()
    header = lines[0].split(",")
    assert list(r.series.dtype.names) == header
    assert r.series["step"].dtype == np.int64
    for k, line in enumerate(lines[1:]):
        for name, cell in zip(header, line.split(",")):
            value = int(cell) if name == "step" else float(cell)
            assert r.series[name][k] == value or (np.isnan(value) and np.isnan(r.series[name][k])), (name, k)
    assert abs(r.series["e1"][-1] - 0.01) < 1e-9  # final_axial_strain, reached at a planned step
    assert len(r.compaction) > 0 and r.classes is not None
    assert [p["name"] for p in r.phases] == ["compaction", "triaxial"]
    assert set(r.tables) == {"series.csv", "compaction.csv", "classes.csv"}


def test_load_gives_dataframes_when_pandas_is_there(py_run):
    out, _ = py_run
    try:
        import pandas
    except ImportError:
        with pytest.raises(ImportError, match="needs pandas"):
            qsdem.load(out, pandas=True)
        assert isinstance(qsdem.load(out).series, np.ndarray)
        return
    r = qsdem.load(out)
    assert isinstance(r.series, pandas.DataFrame)
    assert list(r.series.columns) == list(r.arrays["series.csv"].dtype.names)
    assert np.array_equal(r.series["phi_deg"].to_numpy(), r.arrays["series.csv"]["phi_deg"])


def test_load_refuses_what_is_not_a_finished_run(tmp_path):
    with pytest.raises(FileNotFoundError, match="summary.json"):
        qsdem.load(tmp_path)
    with pytest.raises(FileNotFoundError, match="not a run directory"):
        qsdem.load(tmp_path / "none")


def test_case_as_toml_text_gives_the_same_run(tmp_path, cli_run):
    qsdem.run(TINY.read_text(), out=tmp_path / "text", threads=1)
    assert (tmp_path / "text" / "series.csv").read_bytes() == (cli_run / "series.csv").read_bytes()


def test_prepare_then_run_and_resume_match_the_cli(tmp_path):
    sets = {"triaxial.final_axial_strain": "0.5 %"}
    qsdem.prepare(TINY, out=tmp_path / "prep", threads=1)
    cli("prepare", TINY, "--out", tmp_path / "prep-cli", "--quiet", "--threads", "1")
    assert (tmp_path / "prep" / "compacted.packing").read_bytes() == \
        (tmp_path / "prep-cli" / "compacted.packing").read_bytes()
    s = qsdem.run(TINY, out=tmp_path / "shear", set={**sets, "sample.from": str(tmp_path / "prep")}, threads=1)
    cli("run", TINY, "--out", tmp_path / "shear-cli", "--quiet", "--threads", "1",
        "--set", "triaxial.final_axial_strain=0.5 %", "--set", f"sample.from={tmp_path / 'prep-cli'}")
    assert (tmp_path / "shear" / "series.csv").read_bytes() == (tmp_path / "shear-cli" / "series.csv").read_bytes()
    assert s["steps_cover"] == "triaxial of a prepared sample"
    # A finished run has nothing to resume: the CLI's message, as CaseError.
    with pytest.raises(qsdem.CaseError, match="holds a finished run"):
        qsdem.resume(tmp_path / "shear")


def test_study_and_analyze(tmp_path):
    """studies/tiny.toml: 8 runs of 120 spheres, child processes of the CLI."""
    study = pathlib.Path(__file__).resolve().parents[2] / "studies" / "tiny.toml"
    out = tmp_path / "study"
    analysis = qsdem.study(study, out)
    assert analysis == json.loads((out / "analysis" / "analysis.json").read_text())
    assert len(list((out / "runs").rglob("summary.json"))) == 8
    again = qsdem.analyze(out)
    assert again == json.loads((out / "analysis" / "analysis.json").read_text())
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "bad"\n[design]\nmodels = ["xd"]\n')
    with pytest.raises(qsdem.CaseError):
        qsdem.study(bad, tmp_path / "bad-study")


@pytest.mark.skipif(shutil.which("gnuplot") is None, reason="gnuplot absent")
def test_plot_draws_the_figures_the_cli_draws(tmp_path, cli_run, py_run):
    out, _ = py_run
    drawn = qsdem.plot(out, tmp_path / "plot")
    assert pathlib.Path(drawn["page"]) == tmp_path / "plot" / "index.html"
    assert pathlib.Path(drawn["page"]).read_text().count("<img ") == len(drawn["figures"])
    cli_figures = sorted(p.stem for p in (cli_run / "plot").glob("*.png"))
    assert sorted(drawn["figures"]) == cli_figures
    for name in drawn["figures"]:
        assert (tmp_path / "plot" / (name + ".png")).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(qsdem.CaseError, match="is not a run directory"):
        qsdem.plot(tmp_path / "plot")
