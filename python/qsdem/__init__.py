"""qsdem: quasi-static DEM of spheres and ellipsoids in a deformable periodic cell.

Whole runs (run, prepare, resume, study, analyze) call the functions the command line calls and
write the same files; load() reads a run directory; Simulation steps a case from Python and reads
its state. Reference: docs/python.md.
"""
import csv
import json
import math
import os

import numpy as np

from . import _qsdem
from ._qsdem import CaseError, Interrupted, RunError, __version__

__all__ = ["run", "prepare", "resume", "study", "analyze", "plot", "check_case", "load", "Run", "Simulation",
           "CaseError", "RunError", "Interrupted", "default_case", "__version__"]

default_case = _qsdem.default_case_toml  # examples/spheres-A-small.toml, built in


def _case(case):
    """(kind, value) of a case: a file path, TOML text, or None for the built-in default case."""
    if case is None:
        return "default", ""
    if isinstance(case, os.PathLike):
        return "path", os.fspath(case)
    if not isinstance(case, str):
        raise TypeError(f"case must be a TOML file path, TOML text or None (the built-in case), not "
                        f"{type(case).__name__}")
    if os.path.isfile(case) or ("\n" not in case and "=" not in case):
        return "path", case
    return "text", case


def _toml(value, key, nested=False):
    """A Python value as the TOML text of a --set value (a top-level str goes as the CLI's text)."""
    if isinstance(value, np.ndarray):
        value = value.tolist()
    elif isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, (str, os.PathLike)):
        text = os.fspath(value)
        return json.dumps(text) if nested else text
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(v, key, True) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml(v, key, True)}" for k, v in value.items()) + "}"
    raise TypeError(f"set: the value of '{key}' is a {type(value).__name__}; give a number, a bool, a string "
                    f"(\"0.5 %\"), a list or a dict")


def _sets(set, overrides):
    """The --set strings of set= (a dict, or a list of "key=value" strings) and of **overrides
    (keys with "." or "__" between their parts: damping__model="od")."""
    out = []
    if set is None:
        pass
    elif isinstance(set, dict):
        out += [f"{k}={_toml(v, k)}" for k, v in set.items()]
    elif isinstance(set, (list, tuple)):
        for s in set:
            if not isinstance(s, str) or "=" not in s:
                raise TypeError(f"set: {s!r} is not a \"key=value\" string")
            out.append(s)
    else:
        raise TypeError(f"set must be a dict {{key: value}} or a list of \"key=value\" strings, not "
                        f"{type(set).__name__}")
    for k, v in overrides.items():
        key = k.replace("__", ".")
        out.append(f"{key}={_toml(v, key)}")
    return out


def _threads(threads):
    if threads is None:
        return
    if isinstance(threads, bool) or not isinstance(threads, int):
        raise TypeError(f"threads must be a whole number from 0 (all cores) to 256, not {threads!r}")
    _qsdem.set_threads(threads)


def check_case(case=None, *, set=None, **overrides):
    """The case as the run would use it (every parameter in SI units), or CaseError: a dry run."""
    return json.loads(_qsdem.check_case(*_case(case), _sets(set, overrides)))


def run(case=None, out="runs/default", *, set=None, threads=None, progress=False, force=False, **overrides):
    """`qsdem run`: runs the case into `out` and returns its summary (summary.json) as a dict."""
    _threads(threads)
    return json.loads(_qsdem.run(*_case(case), _sets(set, overrides), os.fspath(out), bool(progress), False,
                                 bool(force)))


def prepare(case=None, out="runs/prepared", *, set=None, threads=None, progress=False, force=False, **overrides):
    """`qsdem prepare`: generates and compacts a sample into `out` (sample.from of later runs)."""
    _threads(threads)
    return json.loads(_qsdem.run(*_case(case), _sets(set, overrides), os.fspath(out), bool(progress), True,
                                 bool(force)))


def resume(dir, *, set=None, threads=None, progress=False, **overrides):
    """`qsdem resume`: continues the interrupted run in `dir`; returns its summary."""
    _threads(threads)
    return json.loads(_qsdem.resume(os.fspath(dir), _sets(set, overrides), bool(progress)))


def study(file, out, *, parallel=0, order="", progress=False, executable=None):
    """`qsdem study`: runs (or continues) a study; its runs are child processes of the CLI
    (`executable`, by default the qsdem built with this module). Returns the analysis (dict)."""
    if isinstance(parallel, bool) or not isinstance(parallel, int):
        raise TypeError(f"parallel must be a whole number >= 1 (0: the study file's), not {parallel!r}")
    code = _qsdem.study(os.fspath(file), os.fspath(out), bool(progress), parallel, order or "",
                        os.fspath(executable) if executable else "")
    if code == 2:
        raise CaseError(f"study {os.fspath(file)}: bad input (the message is on stderr)")
    if code >= 128:
        raise Interrupted(f"study {os.fspath(out)} stopped by a signal; run it again to continue")
    if code != 0:
        raise RunError(f"study {os.fspath(out)}: runs or the analysis failed (exit code {code}; see its logs)")
    path = os.path.join(os.fspath(out), "analysis", "analysis.json")
    return json.load(open(path)) if os.path.exists(path) else {}


def plot(dir, out=None):
    """`qsdem plot`: draws the figures of the run directory `dir` (into `out`, by default DIR/plot) and
    its page; returns {"page": path of index.html, "figures": names drawn, "notes": figures left out
    and why}. Needs gnuplot (RunError when it is missing or fails; CaseError when `dir` is no run's)."""
    return _qsdem.plot(os.fspath(dir), os.fspath(out) if out else "")


def analyze(dir):
    """`qsdem analyze`: analyses a study directory again (DIR/analysis/); returns the analysis."""
    return json.loads(_qsdem.analyze(os.fspath(dir)))


def _column(values):
    for kind in (np.int64, np.float64):
        try:
            return np.array(values, dtype=kind)
        except (ValueError, OverflowError):
            pass
    return np.array(values, dtype=str)


def read_csv(path):
    """A CSV file a run writes, as a numpy structured array (int64, float64 or text columns)."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    if not rows:
        raise ValueError(f"'{path}' is empty: no header")
    header, body = rows[0], rows[1:]
    for k, r in enumerate(body):
        if len(r) != len(header):
            raise ValueError(f"'{path}' row {k + 1} has {len(r)} cells, its header {len(header)}")
    columns = [_column([r[c] for r in body]) for c in range(len(header))]
    out = np.empty(len(body), dtype=[(h, c.dtype) for h, c in zip(header, columns)])
    for h, c in zip(header, columns):
        out[h] = c
    return out


def _pandas(pandas):
    """The pandas module when tables are to be DataFrames (pandas=None: when it is importable)."""
    if pandas is False:
        return None
    try:
        import pandas as pd
    except ImportError:
        if pandas:
            raise ImportError("load(dir, pandas=True) needs pandas (Debian: apt-get install python3-pandas)") from None
        return None
    return pd


class Run:
    """A run directory read back: series (series.csv), compaction (compaction.csv), classes
    (classes.csv), tables (every *.csv by file name), summary (summary.json), phases. The tables are
    pandas DataFrames when pandas is importable (pandas=None) or asked for (True), numpy structured
    arrays otherwise (False); arrays holds them as numpy arrays always."""

    def __init__(self, dir, pandas=None):
        self.dir = os.fspath(dir)
        if not os.path.isdir(self.dir):
            raise FileNotFoundError(f"'{self.dir}' is not a run directory")
        summary = os.path.join(self.dir, "summary.json")
        if not os.path.exists(summary):
            raise FileNotFoundError(f"'{self.dir}' holds no summary.json: not a finished run (qsdem.resume it)")
        pd = _pandas(pandas)
        with open(summary) as f:
            self.summary = json.load(f)
        self.arrays = {name: read_csv(os.path.join(self.dir, name))
                       for name in sorted(os.listdir(self.dir)) if name.endswith(".csv")}
        self.tables = {name: pd.DataFrame(a) if pd else a for name, a in self.arrays.items()}
        self.series = self.tables.get("series.csv")
        self.compaction = self.tables.get("compaction.csv")
        self.classes = self.tables.get("classes.csv")
        self.phases = self.summary.get("phases", [])

    def __repr__(self):
        return f"qsdem.Run({self.dir!r}: {', '.join(self.tables)})"


def load(dir, pandas=None):
    """Reads a finished run directory (qsdem.Run); pandas: DataFrames (True), numpy arrays (False),
    DataFrames when pandas is importable (None)."""
    return Run(dir, pandas)


class Simulation:
    """A case stepped from Python, phase by phase, through the phase loop of a run (no files).

    sim = qsdem.Simulation(case, set={...}) or Simulation(sample="runs/prepared") to start from a
    prepared sample (sample.from), or Simulation(checkpoint=FILE) to continue what sim.save(FILE)
    (or a run's checkpoint.qsck) holds. See docs/python.md for the state it exposes."""

    def __init__(self, case=None, *, sample=None, checkpoint=None, set=None, threads=None, progress=False,
                 **overrides):
        sets = _sets(set, overrides)
        _threads(threads)
        if checkpoint is not None:
            if case is not None or sample is not None:
                raise ValueError("Simulation: give a case (and sample), or a checkpoint, not both: the checkpoint "
                                 "holds its case")
            self._sim = _qsdem.Simulation("checkpoint", os.fspath(checkpoint), sets, bool(progress))
            return
        if sample is not None:
            sets.append("sample.from=" + json.dumps(os.fspath(sample)))
        self._sim = _qsdem.Simulation(*_case(case), sets, bool(progress))

    def save(self, path):
        """Writes the state and the place in the phases to a checkpoint file (atomically), which
        Simulation(checkpoint=path) continues with the same bits. Callbacks are not saved."""
        self._sim.save(os.fspath(path))

    def step(self, n=1):
        """Takes n steps of the current phase (fewer when it ends); returns the steps taken."""
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
            raise TypeError(f"step(n): n must be a whole number >= 1, not {n!r}")
        return self._sim.step(int(n))

    def run_phase(self):
        """Runs the current phase to its end; returns the steps taken."""
        return self._sim.run_phase()

    def run(self):
        """Runs every remaining phase; returns the steps taken."""
        steps = 0
        while not self._sim.finished:
            steps += self._sim.run_phase()
        return steps

    def on_sample(self, fn):
        """fn(point) at each sample point of every phase: point holds phase, step, row, measures,
        strain, critical_time and controls; fn returns None or a dict of new control values
        ({"33": 2e-5}, {"11": 200e3}, {"max_strain_rate": ...}), applied from the next step.
        None removes it. Returns fn (usable as a decorator)."""
        if fn is not None and not callable(fn):
            raise TypeError(f"on_sample: {fn!r} is not callable")
        self._sim._set_callback(fn)
        return fn

    def __getattr__(self, name):
        return getattr(self._sim, name)

    def __repr__(self):
        s = self._sim
        where = "finished" if s.finished else f"phase {s.phase} ({s.phases[s.phase]}) step {s.phase_steps}"
        return f"qsdem.Simulation({len(s.ids)} particles, {where})"
