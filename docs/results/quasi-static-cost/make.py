#!/usr/bin/env python3
"""The tables of docs/results/quasi-static-cost.md, from committed files.

  python3 docs/results/quasi-static-cost/make.py collect runs/qs-cost [SAMPLE]
      copies each finished run's summary.json and series.csv (and each sample's summary.json and
      compaction.csv) of run.sh's directory to docs/results/quasi-static-cost/runs/ (SAMPLE B-small,
      the default; A and A-small: runs-A/, runs-A-small/, with each run's classes.csv gzipped);
  python3 docs/results/quasi-static-cost/make.py [--check] [SAMPLE]
      reads that copy and the references in ../quasi-static-limit/small-B-seeds/runs/ (A's:
      ../quasi-static-limit/A/runs/, A-small's: ../quasi-static-limit/small/runs/), checks that the
      reference ladder's change is reproduced (convergence.csv), and writes tables.md and cost.csv
      (A's: tables-A.md, cost-A.csv; A-small's likewise); with
      --check it writes nothing and fails unless the committed tables are what it would write.

The error of a method against a reference is docs/analysis.md 11's change between two rungs, with
the method in place of the faster rung (src/qsdem/study/convergence.cpp, `change`, computed the
same way here). Python 3 standard library only.
"""
import csv
import gzip
import io
import json
import math
import os
import shutil
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
PHI_TOL, EV_TOL = 0.5, 0.001  # the certificate's tolerances (analysis.md 11), fixed before the runs
SLACK = 1e-9  # a strain this close to a curve's end is on it (study_analysis.cpp)


def a_design(name, limit, study):
    """Sample A's design (quasi-static-cost.md), at 8000 spheroids or on paper-A-small."""
    return {
        "runs": f"runs-{name}", "limit": os.path.join("..", "quasi-static-limit", limit), "seeds": [1, 2, 3],
        "nd_xi": "xi-0.51%", "nd_text": "nd 0.51 %", "tables": f"tables-{name}.md", "cost": f"cost-{name}.csv",
        "refs": {"S_nd": ("nd", "xi-0.51%", "3.16228e-07", "S_nd (nd 0.51 % at 3.16e-7, not certified)"),
                 "S_c": ("none", "xi-0%", "3.16228e-07", "S_c (undamped at 3.16e-7, not certified)")},
        "nd_rates": ("1e-05", "3.16228e-06", "1e-06", "3.16228e-07"),
        "none_rates": ("1e-05", "3.16228e-06", "1e-06", "3.16228e-07"),
        "paper": "nd-1e-06", "wall_note": f"{study} study (another load of the machine)", "fines": True,
        "new": [(f"{m}-scaled-{r}", f"{t}, inertia scaled, at {float(r):.3g}")
                for r in ("1e-6", "3.16228e-7", "1e-7") for m, t in (("nd", "nd"), ("none", "undamped"))]
               + [("nd-scaled-3.16228e-8", "nd, inertia scaled, at 3.16e-8"),
                  ("fire-0.05%", "FIRE, increments of 0.05 %"),
                  ("fire-0.02%", "FIRE, increments of 0.02 %")],
        # each scaled ladder, fastest rung first (its certificate's changes: reported, not a decision)
        "scaled_ladders": [("nd, inertia scaled", ["nd-scaled-1e-6", "nd-scaled-3.16228e-7", "nd-scaled-1e-7",
                                                   "nd-scaled-3.16228e-8"]),
                           ("undamped, inertia scaled", ["none-scaled-1e-6", "none-scaled-3.16228e-7", "none-scaled-1e-7"])],
        # (scaled run, the unscaled ladder's model, xi directory and rate): decision 1
        "scaled_pairs": [(f"{m}-scaled-{r}", m, xi, lr) for r, lr in (("1e-6", "1e-06"), ("3.16228e-7", "3.16228e-07"))
                         for m, xi in (("nd", "xi-0.51%"), ("none", "xi-0%"))],
    }


# Each sample's study: where its runs and reference ladders are, its seeds, nd's ratio directory,
# its references (name: (model, xi directory, rate, title)), its ladders' rates, its new methods.
SAMPLES = {
    "B-small": {
        "runs": "runs", "limit": os.path.join("..", "quasi-static-limit", "small-B-seeds"), "seeds": [1, 2, 3, 4, 5, 6],
        "nd_xi": "xi-0.4%", "nd_text": "nd 0.40 %", "tables": "tables.md", "cost": "cost.csv",
        "refs": {"L_nd": ("nd", "xi-0.4%", "3.16228e-07", "L_nd (nd 0.40 % at 3.16e-7)"),
                 "L_c": ("none", "xi-0%", "1e-06", "L_c (undamped at 1e-6)")},
        "nd_rates": ("1e-05", "3.16228e-06", "1e-06", "3.16228e-07"), "none_rates": ("1e-05", "3.16228e-06", "1e-06"),
        "paper": "nd-1e-06", "wall_note": "small-B-seeds study (energy ledger on, another load of the machine)",
        "new": [("nd-scaled-1e-06", "nd, inertia scaled, at 1e-6"),
                ("nd-scaled-3.16e-06", "nd, inertia scaled, at 3.16e-6"),
                ("none-scaled-1e-05", "undamped, inertia scaled, at 1e-5"),
                ("nd-control-imom-1%", "nd, rate controller, IMom 1 %"),
                ("nd-control-imom-0.3%", "nd, rate controller, IMom 0.3 %"),
                ("fire-0.1%", "FIRE, increments of 0.1 %"),
                ("fire-0.05%", "FIRE, increments of 0.05 %"),
                ("fire-0.02%", "FIRE, increments of 0.02 %"),
                ("fire-0.05%-scaled", "FIRE 0.05 %, inertia scaled")],
        "scaled_pairs": [],
    },
    "A": a_design("A", "A", "quasi-static-limit/A"),
    "A-small": a_design("A-small", "small", "quasi-static-limit/small"),
}


def collect(src, cfg):
    RUNS = os.path.join(HERE, cfg["runs"])
    if os.path.exists(RUNS):
        shutil.rmtree(RUNS)
    for label in sorted(os.listdir(src)):
        top = os.path.join(src, label)
        if not os.path.isdir(top):
            continue
        for seed_dir in sorted(os.listdir(top)):
            d = os.path.join(top, seed_dir)
            keep = ("summary.json", "compaction.csv") if label == "samples" else ("summary.json", "series.csv")
            if not os.path.exists(os.path.join(d, "summary.json")):
                continue
            os.makedirs(os.path.join(RUNS, label, seed_dir))
            for f in keep:
                if os.path.exists(os.path.join(d, f)):
                    shutil.copy(os.path.join(d, f), os.path.join(RUNS, label, seed_dir, f))
            if cfg.get("fines") and label != "samples" and os.path.exists(os.path.join(d, "classes.csv")):
                with open(os.path.join(d, "classes.csv"), "rb") as fi, \
                        gzip.GzipFile(os.path.join(RUNS, label, seed_dir, "classes.csv.gz"), "wb", mtime=0) as fo:
                    shutil.copyfileobj(fi, fo)


def curve(directory):
    """(e1, phi_deg, ev) of a run's series.csv, sorted by e1 (stable, as sorted_curve)."""
    with open(os.path.join(directory, "series.csv")) as f:
        rows = list(csv.DictReader(f))
    pts = sorted(((float(r["e1"]), float(r["phi_deg"]), float(r["ev"])) for r in rows), key=lambda p: p[0])
    return pts


def interpolate(c, x):
    """Linear interpolation of [(x, y)] at x; NaN outside (with SLACK), as study_analysis.cpp."""
    if not c or x < c[0][0] - SLACK or x > c[-1][0] + SLACK:
        return math.nan
    x = min(max(x, c[0][0]), c[-1][0])
    lo_i, hi_i = 0, len(c)
    while lo_i < hi_i:  # lower_bound
        mid = (lo_i + hi_i) // 2
        if c[mid][0] < x:
            lo_i = mid + 1
        else:
            hi_i = mid
    hi = lo_i
    if hi == 0:
        return c[0][1]
    lo = hi - 1
    if c[hi][0] == x or c[hi][0] == c[lo][0]:
        return c[hi][1]
    return c[lo][1] + (c[hi][1] - c[lo][1]) * (x - c[lo][0]) / (c[hi][0] - c[lo][0])


def change(runs, refs, k, grid):
    """Seed-paired change of measure k (1 phi, 2 ev), runs minus refs: (rms, error, excess)."""
    n = len(runs)
    d = []
    for a, b in zip(runs, refs):
        ca = [(p[0], p[k]) for p in a]
        cb = [(p[0], p[k]) for p in b]
        d.append([interpolate(ca, x) - interpolate(cb, x) for x in grid])
    total = total_error = 0.0
    points = 0
    for j in range(len(grid)):
        col = [d[s][j] for s in range(n)]
        if not all(math.isfinite(v) for v in col):
            continue
        mean = sum(col) / n
        var = sum((v - mean) ** 2 for v in col)
        total += mean * mean
        total_error += var / (n - 1) / n if n > 1 else 0.0
        points += 1
    if points == 0:
        return math.nan, math.nan, math.nan
    return (math.sqrt(total / points), math.sqrt(total_error / points),
            math.sqrt(max(0.0, (total - total_error) / points)))


def mean_se(values):
    n = len(values)
    m = sum(values) / n
    se = math.sqrt(sum((v - m) ** 2 for v in values) / (n - 1) / n) if n > 1 else 0.0
    return m, se


def at(c, x, k):
    return interpolate([(p[0], p[k]) for p in c], x)


def within(phi, ev):
    """The certificate's verdict on a change (phi and ev as `change` returns them): beyond the noise
    and its standard error both within the tolerances."""
    return phi[2] <= PHI_TOL and ev[2] <= EV_TOL and phi[1] <= PHI_TOL and ev[1] <= EV_TOL


def end_difference(runs, refs):
    """ev at the end of the shorter of each seed's two curves, run minus reference: mean, s.e."""
    return mean_se([at(c, min(c[-1][0], r[-1][0]), 2) - at(r, min(c[-1][0], r[-1][0]), 2) for c, r in zip(runs, refs)])


def summary(directory):
    with open(os.path.join(directory, "summary.json")) as f:
        return json.load(f)


def ladder_dir(cfg, seed, model, xi, rate):
    return os.path.join(HERE, cfg["limit"], "runs", f"{cfg['name']}-seed{seed}", model, xi, f"rate-{rate}")


def methods(cfg):
    """(label, description, [run directory per seed]) in the design's order."""
    m = []
    for rate in cfg["nd_rates"]:
        m.append((f"nd-{rate}", f"{cfg['nd_text']} at {float(rate):.3g}",
                  [ladder_dir(cfg, s, "nd", cfg["nd_xi"], rate) for s in cfg["seeds"]]))
    for rate in cfg["none_rates"]:
        m.append((f"none-{rate}", f"undamped at {float(rate):.3g}", [ladder_dir(cfg, s, "none", "xi-0%", rate) for s in cfg["seeds"]]))
    for label, text in cfg["new"]:
        m.append((label, text, [os.path.join(HERE, cfg["runs"], label, f"{cfg['name']}-seed{s}") for s in cfg["seeds"]]))
    return m


def check_reference_certificate(cfg, nd_runs, nd_ref, grid):
    """The nd ladder's change 1e-6 -> 3.16e-7 must equal convergence.csv's (this script's change
    against the engine's)."""
    with open(os.path.join(HERE, cfg["limit"], "analysis", "convergence.csv")) as f:
        row = next(r for r in csv.DictReader(f) if r["model"] == "nd" and r["rate"] == "1e-06")
    phi = change(nd_runs, nd_ref, 1, grid)
    ev = change(nd_runs, nd_ref, 2, grid)
    want = [float(row[k]) for k in ("phi_to_slowest_deg", "phi_to_slowest_error_deg", "phi_to_slowest_excess_deg",
                                    "ev_to_slowest", "ev_to_slowest_error", "ev_to_slowest_excess")]
    got = list(phi) + list(ev)
    for g, w in zip(got, want):
        if abs(g - w) > 1e-8 * max(1.0, abs(w)):
            sys.exit(f"make.py: this change {got} is not convergence.csv's {want}")
    return got


def check_run_start(cfg):
    """check-nd-1e-05: the committed rung run again from this study's samples, byte for byte, and
    (for a rung written before the series got more columns) in every column the rung has: per seed
    (bytes equal, columns equal)."""
    same = []
    for s in cfg["seeds"]:
        a = os.path.join(HERE, cfg["runs"], "check-nd-1e-05", f"{cfg['name']}-seed{s}", "series.csv")
        b = os.path.join(ladder_dir(cfg, s, "nd", cfg["nd_xi"], "1e-05"), "series.csv")
        if os.path.exists(a):
            with open(a) as fa, open(b) as fb:
                ra, rb = list(csv.DictReader(fa)), list(csv.DictReader(fb))
            columns = len(ra) == len(rb) and all(x[k] == y[k] for x, y in zip(ra, rb) for k in y)
            same.append((open(a, "rb").read() == open(b, "rb").read(), columns))
    return same


def fines_in_contact(directory):
    """The share of the smallest size class's particles in contact, averaged over the test's rows at
    e1 1-10 % (classes.csv.gz; quasi-static-limit.md's "fines in contact"); NaN without the file."""
    path = os.path.join(directory, "classes.csv.gz")
    if not os.path.exists(path):
        return math.nan
    with gzip.open(path, "rt") as f:
        rows = [r for r in csv.DictReader(f) if r["phase"] != "compaction"]
    smallest = min(float(r["radius_mm"]) for r in rows)
    shares = [float(r["in_contact"]) for r in rows
              if float(r["radius_mm"]) == smallest and 0.01 <= float(r["e1"]) <= 0.1 + SLACK]
    return sum(shares) / len(shares) if shares else math.nan


def build_name(summary):
    """The build that wrote a run: its version, "(dirty)" when the tree differed from its commit (a
    summary.json older than the `build` record gives its version alone, e.g. 0.1.0+43bfc46-dirty)."""
    if "build" not in summary:
        return summary["version"]
    return summary["build"]["version"] + ("" if summary["build"]["tree_clean"] else " (dirty)")


def fmt(x, digits=2):
    return "—" if not math.isfinite(x) else f"{x:.{digits}f}"


def main(cfg, check=False):
    seeds = cfg["seeds"]
    refs = {k: [curve(ladder_dir(cfg, s, model, xi, rate)) for s in seeds] for k, (model, xi, rate, _) in cfg["refs"].items()}
    nd_ref = next(iter(refs))
    grids = {k: [p[0] for p in v[0]] for k, v in refs.items()}
    checked = check_reference_certificate(cfg, [curve(ladder_dir(cfg, s, "nd", cfg["nd_xi"], "1e-06")) for s in seeds],
                                          [curve(ladder_dir(cfg, s, "nd", cfg["nd_xi"], "3.16228e-07")) for s in seeds],
                                          grids[nd_ref])
    same = check_run_start(cfg)
    rows = []
    for label, text, dirs in methods(cfg):
        if not all(os.path.exists(os.path.join(d, "summary.json")) for d in dirs):
            rows.append({"label": label, "method": text, "finished": sum(os.path.exists(os.path.join(d, "summary.json")) for d in dirs)})
            continue
        curves = [curve(d) for d in dirs]
        sums = [summary(d) for d in dirs]
        steps = [s["steps"] for s in sums]
        walls = [s["wall_s"] for s in sums]
        builds = sorted({build_name(s) for s in sums})
        row = {"label": label, "method": text, "finished": len(dirs), "steps": sum(steps) / len(steps),
               "wall_s": sum(walls) / len(walls), "builds": ", ".join(builds), "dirs": dirs, "curves": curves}
        for name, ref in refs.items():
            phi = change(curves, ref, 1, grids[name])
            ev = change(curves, ref, 2, grids[name])
            row[name] = {"phi": phi, "ev": ev, "ev_end": end_difference(curves, ref), "within": within(phi, ev)}
        peak = mean_se([max(p[1] for p in c) for c in curves])
        row["peak_phi"] = peak
        row["ev_end"] = mean_se([c[-1][2] for c in curves])
        rows.append(row)

    paper = next(r for r in rows if r["label"] == cfg["paper"])["steps"]
    out = ["<!-- written by docs/results/quasi-static-cost/make.py from the committed runs; do not edit -->", ""]
    out.append("Check of this script against the engine: the nd ladder's change 1e-6 → 3.16e-7, "
               f"φ {checked[0]:.4f}° (standard error {checked[1]:.4f}°, beyond the noise {checked[2]:.4f}°), "
               f"εv {100 * checked[3]:.4f} % ({100 * checked[4]:.4f} %, {100 * checked[5]:.4f} %): "
               "convergence.csv's to 1e-8.")
    out.append("")
    out.append("Wall times: one thread a run, two runs at a time. The rows of the committed ladders (nd and undamped "
               f"at constant rate) come from the {cfg['wall_note']}; "
               "compare their steps, not their wall times, with the other rows.")
    out.append("")
    bytes_same, columns_same = sum(b for b, _ in same), sum(c for _, c in same)
    if bytes_same == len(same):
        out.append(f"Start check: `check-nd-1e-05` equals the committed rung byte for byte on {bytes_same} of {len(same)} seeds.")
    else:
        out.append(f"Start check: `check-nd-1e-05` equals the committed rung byte for byte on {bytes_same} of {len(same)} "
                   f"seeds, and in every column the committed rung has (its build wrote fewer) on {columns_same} of {len(same)}.")
    out.append("")
    for name, (_, _, _, title) in cfg["refs"].items():
        out.append(f"### Error against {title}")
        out.append("")
        out.append("| method | force evaluations per run | / paper's method | wall per run (s) | Δφ beyond the noise ± s.e. (°) | Δεv beyond the noise ± s.e. (%) | Δεv at 10 % (%) | within |")
        out.append("| --- | ---: | ---: | ---: | --- | --- | --- | --- |")
        for r in rows:
            if "steps" not in r:
                out.append(f"| {r['method']} | {r['finished']} of {len(seeds)} seeds finished | | | | | | |")
                continue
            e = r[name]
            out.append(f"| {r['method']} | {r['steps']:,.0f} | {paper / r['steps']:.2f}× fewer | {r['wall_s']:.1f} | "
                       f"{fmt(e['phi'][2])} ± {fmt(e['phi'][1])} | {fmt(100 * e['ev'][2], 3)} ± {fmt(100 * e['ev'][1], 3)} | "
                       f"{100 * e['ev_end'][0]:+.2f} ± {100 * e['ev_end'][1]:.2f} | {'**yes**' if e['within'] else 'no'} |")
        out.append("")
    out.append(f"### The nd runs against the constant-rate curve of the same cost ({nd_ref})")
    out.append("")
    out.append("The constant-rate nd ladder's error beyond the noise and its standard error, interpolated linearly in "
               "log(steps) between its rungs at each method's steps, beside the method's own; \"lower\" when the "
               "method's error is below the ladder's by more than the two standard errors together.")
    out.append("")
    out.append("| method | force evaluations | Δφ (°): method, constant rate | Δεv (%): method, constant rate | lower |")
    out.append("| --- | ---: | --- | --- | --- |")
    ladder = sorted((r["steps"], r[nd_ref]["phi"][2], r[nd_ref]["ev"][2], r[nd_ref]["phi"][1], r[nd_ref]["ev"][1])
                    for r in rows if r["label"] in ("nd-1e-05", "nd-3.16228e-06", "nd-1e-06"))

    def on_ladder(steps, k):
        for (s0, *y0), (s1, *y1) in zip(ladder, ladder[1:]):
            if s0 <= steps <= s1:
                t = math.log(steps / s0) / math.log(s1 / s0)
                return y0[k] + t * (y1[k] - y0[k])
        return math.nan

    def lower(e, steps, k):
        own, own_se = e["phi" if k == 0 else "ev"][2], e["phi" if k == 0 else "ev"][1]
        return own + own_se + on_ladder(steps, k + 2) < on_ladder(steps, k)

    for r in rows:
        if r["label"].startswith("nd-") and "steps" in r and r["label"] in dict(cfg["new"]):
            e = r[nd_ref]
            verdict = "—" if not math.isfinite(on_ladder(r["steps"], 0)) else \
                ", ".join(f"{name} {'yes' if lower(e, r['steps'], k) else 'no'}" for k, name in ((0, "φ"), (1, "εv")))
            out.append(f"| {r['method']} | {r['steps']:,.0f} | {fmt(e['phi'][2])} ± {fmt(e['phi'][1])}, "
                       f"{fmt(on_ladder(r['steps'], 0))} ± {fmt(on_ladder(r['steps'], 2))} | "
                       f"{fmt(100 * e['ev'][2], 3)} ± {fmt(100 * e['ev'][1], 3)}, {fmt(100 * on_ladder(r['steps'], 1), 3)} ± "
                       f"{fmt(100 * on_ladder(r['steps'], 3), 3)} | {verdict} |")
    out.append("")
    out.append("### FIRE against itself: the change between increments")
    out.append("")
    out.append("Seed-paired change, the finer increment's run as the reference (its first seed's strains as the grid).")
    out.append("")
    out.append("| increments | Δφ beyond the noise ± s.e. (°) | Δεv beyond the noise ± s.e. (%) |")
    out.append("| --- | --- | --- |")
    fire = {r["label"]: r["curves"] for r in rows if r["label"].startswith("fire-") and "steps" in r}
    for a, b in (("fire-0.1%", "fire-0.05%"), ("fire-0.05%", "fire-0.02%"), ("fire-0.1%", "fire-0.02%")):
        if a in fire and b in fire:
            g = [p[0] for p in fire[b][0]]
            phi, ev = change(fire[a], fire[b], 1, g), change(fire[a], fire[b], 2, g)
            out.append(f"| {a[5:]} → {b[5:]} | {fmt(phi[2])} ± {fmt(phi[1])} | {fmt(100 * ev[2], 3)} ± {fmt(100 * ev[1], 3)} |")
    out.append("")
    if cfg.get("scaled_ladders"):
        out.append("### The inertia-scaled ladders against themselves")
        out.append("")
        out.append("The certificate's change (analysis.md 11) of each scaled rung to the slowest scaled rung of the "
                   "same model, and to the next slower one; \"within\" at the certificate's tolerance (0.5°, 0.1 %, "
                   "resolved) for the change to the next rung.")
        out.append("")
        out.append("| ladder | rung | Δφ to the slowest ± s.e. (°) | Δεv to the slowest ± s.e. (%) | "
                   "Δφ to the next ± s.e. (°) | Δεv to the next ± s.e. (%) | within |")
        out.append("| --- | --- | --- | --- | --- | --- | --- |")
        runs_of = {r["label"]: r for r in rows}
        for title, labels in cfg["scaled_ladders"]:
            done = [x for x in labels if "steps" in runs_of[x]]
            if len(done) < 2:
                out.append(f"| {title} | fewer than two rungs finished | | | | | |")
                continue
            curves = {x: runs_of[x]["curves"] for x in done}
            slow = curves[done[-1]]
            for a, b in zip(done, done[1:]):
                g_slow, g_next = [p[0] for p in slow[0]], [p[0] for p in curves[b][0]]
                to_slow = (change(curves[a], slow, 1, g_slow), change(curves[a], slow, 2, g_slow))
                to_next = (change(curves[a], curves[b], 1, g_next), change(curves[a], curves[b], 2, g_next))
                phi, ev = to_next
                out.append(f"| {title} | {runs_of[a]['method'].split(', at ')[-1]} | "
                           f"{fmt(to_slow[0][2])} ± {fmt(to_slow[0][1])} | {fmt(100 * to_slow[1][2], 3)} ± {fmt(100 * to_slow[1][1], 3)} | "
                           f"{fmt(phi[2])} ± {fmt(phi[1])} | {fmt(100 * ev[2], 3)} ± {fmt(100 * ev[1], 3)} | "
                           f"{'**yes**' if within(phi, ev) else 'no'} |")
        out.append("")
    out.append(f"### Where along the strain the rate acts (nd, against {nd_ref})")
    out.append("")
    out.append(f"The change of the constant-rate nd runs from {nd_ref} over windows of axial strain (the same "
               "computation on the grid points in each window): beyond the noise ± standard error.")
    out.append("")
    windows = [(0, 0.005), (0.005, 0.01), (0.01, 0.02), (0.02, 0.04), (0.04, 0.07), (0.07, 0.1 + SLACK)]
    out.append("| rate | " + " | ".join(f"ε1 {100 * lo:g}-{100 * min(hi, 0.1):g} %: Δφ (°), Δεv (%)" for lo, hi in windows) + " |")
    out.append("| --- |" + " --- |" * len(windows))
    for rate in ("1e-05", "3.16228e-06", "1e-06"):
        runs = [curve(ladder_dir(cfg, s, "nd", cfg["nd_xi"], rate)) for s in seeds]
        cells = []
        for lo, hi in windows:
            g = [x for x in grids[nd_ref] if lo <= x < hi]
            phi, ev = change(runs, refs[nd_ref], 1, g), change(runs, refs[nd_ref], 2, g)
            cells.append(f"{phi[2]:.2f} ± {phi[1]:.2f}, {100 * ev[2]:.3f} ± {100 * ev[1]:.3f}")
        out.append(f"| {float(rate):.3g} | " + " | ".join(cells) + " |")
    out.append("")
    out.append("### The responses")
    out.append("")
    fines = cfg.get("fines", False)
    if fines:
        out.append("Fines in contact: the share of the smallest size class's particles with a contact, "
                   "over the rows at ε1 1-10 % (classes.csv.gz), mean over the seeds.")
        out.append("")
    out.append("| method | peak φ (°) | εv at 10 % (%) |" + (" fines in contact |" if fines else "") + " builds |")
    out.append("| --- | --- | --- |" + (" --- |" if fines else "") + " --- |")
    for r in rows:
        if "steps" in r:
            share = ""
            if fines:
                f = [fines_in_contact(d) for d in r["dirs"]]
                share = f" {100 * sum(f) / len(f):.1f} % |" if all(math.isfinite(x) for x in f) else " — |"
            out.append(f"| {r['method']} | {r['peak_phi'][0]:.2f} ± {r['peak_phi'][1]:.2f} | "
                       f"{100 * r['ev_end'][0]:+.2f} ± {100 * r['ev_end'][1]:.2f} |{share} {r['builds']} |")
    out.append("")
    if cfg["scaled_pairs"]:
        out.append("### Inertia scaling against the unscaled run at the same rate")
        out.append("")
        out.append("Seed-paired change of the scaled run from the unscaled ladder's run of the same model and rate "
                   "(its first seed's strains as the grid): decision 1 of the design.")
        out.append("")
        out.append("| scaled run | force evaluations: scaled, unscaled | Δφ beyond the noise ± s.e. (°) | "
                   "Δεv beyond the noise ± s.e. (%) | Δεv at 10 % (%) | within |")
        out.append("| --- | --- | --- | --- | --- | --- |")
        for label, model, xi, rate in cfg["scaled_pairs"]:
            r = next(x for x in rows if x["label"] == label)
            if "steps" not in r:
                out.append(f"| {r['method']} | {r['finished']} of {len(seeds)} seeds finished | | | | |")
                continue
            runs = r["curves"]
            base_dirs = [ladder_dir(cfg, s, model, xi, rate) for s in seeds]
            base = [curve(d) for d in base_dirs]
            base_steps = sum(summary(d)["steps"] for d in base_dirs) / len(base_dirs)
            g = [p[0] for p in base[0]]
            phi, ev = change(runs, base, 1, g), change(runs, base, 2, g)
            end = end_difference(runs, base)
            out.append(f"| {r['method']} | {r['steps']:,.0f}, {base_steps:,.0f} | {fmt(phi[2])} ± {fmt(phi[1])} | "
                       f"{fmt(100 * ev[2], 3)} ± {fmt(100 * ev[1], 3)} | {100 * end[0]:+.2f} ± {100 * end[1]:.2f} | "
                       f"{'**yes**' if within(phi, ev) else 'no'} |")
        out.append("")
    cost = io.StringIO(newline="")
    w = csv.writer(cost, lineterminator="\n")
    w.writerow(["method", "label", "steps_per_run", "wall_s_per_run", "reference", "phi_rms_deg", "phi_error_deg",
                "phi_excess_deg", "ev_rms", "ev_error", "ev_excess", "ev_end_diff", "ev_end_diff_error", "within"])
    for r in rows:
        if "steps" not in r:
            continue
        for name in refs:
            e = r[name]
            w.writerow([r["method"], r["label"], f"{r['steps']:.1f}", f"{r['wall_s']:.2f}", name]
                       + [f"{v:.6g}" for v in e["phi"] + e["ev"] + e["ev_end"]] + [str(e["within"]).lower()])
    files = {cfg["tables"]: "\n".join(out), cfg["cost"]: cost.getvalue()}
    if check:
        for name, text in files.items():
            with open(os.path.join(HERE, name), newline="") as f:
                if f.read() != text:
                    sys.exit(f"make.py: {name} is not what the committed runs give (run make.py {cfg['name']})")
        print(f"make.py: {', '.join(files)} are what the committed runs give")
        return
    for name, text in files.items():
        with open(os.path.join(HERE, name), "w", newline="") as f:
            f.write(text)
    print(files[cfg["tables"]])


if __name__ == "__main__":
    args = sys.argv[1:]
    collecting = len(args) >= 2 and args[0] == "collect"
    checking = not collecting and args[:1] == ["--check"]
    rest = args[2:] if collecting else args[1:] if checking else args
    name = rest[0] if rest else "B-small"
    if name not in SAMPLES:
        sys.exit(f"make.py: the sample is one of {', '.join(SAMPLES)}, not '{name}'")
    config = dict(SAMPLES[name], name=name)
    if collecting:
        collect(args[1], config)
    else:
        main(config, check=checking)
