"""Shared fixtures: the tiny case (120 spheres, ~1 s) run once by the CLI and once by the module."""
import os
import pathlib
import subprocess

import pytest

import qsdem

HERE = pathlib.Path(__file__).resolve().parent
TINY = HERE / "tiny.toml"
CLI = os.environ.get("QSDEM_CLI", qsdem._qsdem.cli)


def cli(*args, check=True):
    """Runs the qsdem CLI; returns the completed process (text)."""
    p = subprocess.run([CLI, *map(str, args)], capture_output=True, text=True)
    if check and p.returncode != 0:
        raise AssertionError(f"qsdem {' '.join(map(str, args))} exited {p.returncode}: {p.stderr}")
    return p


@pytest.fixture(scope="session")
def cli_run(tmp_path_factory):
    """The tiny case run by `qsdem run` (one thread)."""
    out = tmp_path_factory.mktemp("cli") / "run"
    cli("run", TINY, "--out", out, "--quiet", "--threads", "1")
    return out


@pytest.fixture(scope="session")
def py_run(tmp_path_factory):
    """The tiny case run by qsdem.run (one thread); (directory, returned summary)."""
    out = tmp_path_factory.mktemp("py") / "run"
    summary = qsdem.run(TINY, out=out, threads=1)
    return out, summary
