#!/usr/bin/env python3
"""Tables and figures of docs/results/quasi-static-limit.md, from the study's own files.

  python3 docs/results/quasi-static-limit/make.py collect runs/qs-limit-small
      copies the study's study.toml, study.json, analysis/ and report.html, of every prepared
      sample summary.json and compaction.csv, and of every finished run summary.json, series.csv
      and classes.csv.gz, to docs/results/quasi-static-limit/small/ (`qsdem analyze` of that copy
      gives its analysis again);
  python3 docs/results/quasi-static-limit/make.py
      reads the copy and writes tables.md and figures/*.png (gnuplot, pngcairo).

Measures: the certificate of each ladder (analysis.json "convergence", docs/analysis.md section
11): per rung the seed mean and standard error of peak phi and of ev at the last strain, the paired
RMS change to the slowest rung, the status. The fines: the smallest size class of classes.csv, its
fraction in contact (in_contact) and mean speed, averaged over the rows with e1 in [1 %, 10 %],
then over the seeds. Python 3 standard library only; gnuplot draws the PNGs.
"""
import csv
import gzip
import json
import math
import os
import shutil
import subprocess
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
COPY = os.path.join(HERE, "small")


def gz(src, dst):
    with open(src, "rb") as i, open(dst, "wb") as raw:
        with gzip.GzipFile(filename=os.path.basename(src), mode="wb", fileobj=raw, mtime=0) as o:
            shutil.copyfileobj(i, o)


def collect(study):
    if os.path.exists(COPY):
        shutil.rmtree(COPY)
    os.makedirs(COPY)
    for f in ("study.toml", "study.json", "report.html"):
        shutil.copy(os.path.join(study, f), COPY)
    shutil.copytree(os.path.join(study, "analysis"), os.path.join(COPY, "analysis"))
    for s in sorted(os.listdir(os.path.join(study, "samples"))):
        d = os.path.join(COPY, "samples", s)
        os.makedirs(d)
        for f in ("summary.json", "compaction.csv"):
            shutil.copy(os.path.join(study, "samples", s, f), d)
    for root, _, files in os.walk(os.path.join(study, "runs")):
        if "summary.json" not in files or "checkpoint.qsck" in files:
            continue
        d = os.path.join(COPY, os.path.relpath(root, study))
        os.makedirs(d)
        for f in ("summary.json", "series.csv"):
            shutil.copy(os.path.join(root, f), d)
        gz(os.path.join(root, "classes.csv"), os.path.join(d, "classes.csv.gz"))


def fines(run_dir):
    """Fraction of the smallest class in contact, and its mean speed (m/s), over e1 in [1 %, 10 %]."""
    rows = list(csv.DictReader(gzip.open(os.path.join(run_dir, "classes.csv.gz"), "rt")))
    rows = [r for r in rows if r["phase"] == "triaxial" and 0.01 <= float(r["e1"]) <= 0.10]
    smallest = min(float(r["radius_mm"]) for r in rows)
    rows = [r for r in rows if float(r["radius_mm"]) == smallest]
    n = len(rows)
    return sum(float(r["in_contact"]) for r in rows) / n, sum(float(r["speed_m_s"]) for r in rows) / n


def label(l):
    m, xi = l["model"], l["xi"]
    if m == "local":
        return f"local {xi:g}"
    if m in ("od", "nd", "stiffness"):
        return f"{m} {100 * xi:g} %"
    return m


def fmt(v, d=3):
    return "—" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{d}g}"


def scalar(l, name):
    return next(s for s in l["scalars"] if s["name"] == name)


def tables(a, manifest):
    ladders = a["convergence"]
    out = ["# Tables of docs/results/quasi-static-limit.md",
           "",
           "Made by `python3 docs/results/quasi-static-limit/make.py` from `small/` (the study's files).",
           "",
           "## The certificate of each model (tolerances RMS Δφ 0.5°, RMS Δεv 0.1 %, and the seed scatter)",
           "",
           "Δ: the seed mean of the paired change between the two slowest rungs, RMS over the strain, ± its",
           "standard error over the seeds. Scatter: the standard deviation over the seeds at the slowest rung.",
           "Peak φ and εv at 10 %: seed mean ± standard error at the slowest rung.",
           "",
           "| model | rates run | Δφ two slowest (°) | Δεv two slowest (%) | seed scatter φ (°) / εv (%) | status | peak φ at the slowest (°) | εv at 10 % at the slowest (%) | steps |",
           "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for l in ladders:
        r = l["rungs"][-2] if len(l["rungs"]) > 1 else None
        pk, ev = scalar(l, "peak_phi_deg"), scalar(l, "ev")
        out.append("| {} | {} | {} ± {} | {} ± {} | {} / {} | {} | {} ± {} | {} ± {} | {} |".format(
            label(l), ", ".join(f"{x:.3g}" for x in l["rates"]),
            fmt(r["phi_to_next"]["rms"], 2) if r else "—", fmt(r["phi_to_next"]["error"], 2) if r else "—",
            fmt(100 * r["ev_to_next"]["rms"], 2) if r else "—", fmt(100 * r["ev_to_next"]["error"], 2) if r else "—",
            fmt(l["phi_scatter_deg"], 2), fmt(100 * l["ev_scatter"], 2), l["status"],
            fmt(pk["mean"][-1], 4), fmt(pk["error"][-1], 2), fmt(100 * ev["mean"][-1], 3), fmt(100 * ev["error"][-1], 2),
            fmt(l["steps"], 3)))
    out += ["", "## Peak φ and εv at 10 % at each rate (seed mean ± standard error)", "",
            "| model | " + " | ".join(f"ε' = {x:.3g}" for x in ladders[0]["rates"]) + " |",
            "| --- |" + " --- |" * len(ladders[0]["rates"])]
    rates = sorted({x for l in ladders for x in l["rates"]}, reverse=True)
    out[-2] = "| model | " + " | ".join(f"ε' = {x:.3g}" for x in rates) + " |"
    out[-1] = "| --- |" + " --- |" * len(rates)
    for l in ladders:
        pk, ev = scalar(l, "peak_phi_deg"), scalar(l, "ev")
        cells = []
        for x in rates:
            if x in l["rates"]:
                k = l["rates"].index(x)
                cells.append(f"{pk['mean'][k]:.2f} ± {pk['error'][k]:.2f}° / {100 * ev['mean'][k]:.2f} ± {100 * ev['error'][k]:.2f} %")
            else:
                cells.append("—")
        out.append(f"| {label(l)} | " + " | ".join(cells) + " |")
    # Paired by seed against the undamped run of the same sample and rate.
    runs = {r["id"]: r for r in a["runs"]}
    by = {(r["model"], r["xi"], r["rate"], r["seed"]): r for r in a["runs"] if r["finished"]}
    out += ["", "## Against the undamped run of the same seed and rate", "",
            "Per seed, the model's run minus the undamped run on the same sample at the same rate, then the mean",
            "± its standard error over the three seeds (summary.json: peak_phi_deg, final_ev).", "",
            "| model | " + " | ".join(f"ε' = {x:.3g}: Δ peak φ (°) / Δ εv at 10 % (%)" for x in rates) + " |",
            "| --- |" + " --- |" * len(rates)]

    def mean_se(v):
        m = sum(v) / len(v)
        return m, math.sqrt(sum((x - m) ** 2 for x in v) / (len(v) - 1) / len(v)) if len(v) > 1 else float("nan")

    for l in ladders:
        if l["model"] == "none":
            continue
        cells = []
        for x in rates:
            pairs = [(by.get((l["model"], l["xi"], x, s)), by.get(("none", 0.0, x, s))) for s in l["seeds"]]
            if x not in l["rates"] or not all(p and q for p, q in pairs):
                cells.append("—")
                continue
            dp = mean_se([p["peak_phi_deg"] - q["peak_phi_deg"] for p, q in pairs])
            de = mean_se([100 * (p["final_ev"] - q["final_ev"]) for p, q in pairs])
            cells.append(f"{dp[0]:+.2f} ± {dp[1]:.2f} / {de[0]:+.2f} ± {de[1]:.2f}")
        out.append(f"| {label(l)} | " + " | ".join(cells) + " |")
    # The fines at 1e-6, the slowest rate every model ran.
    common = min(set.intersection(*[set(l["rates"]) for l in ladders]))
    out += ["", f"## The fines at ε' = {common:.3g} (the slowest rate of every model)", "",
            "The smallest size class (classes.csv), rows with e1 in [1 %, 10 %], mean over the seeds: the fraction",
            "of its particles in contact and their mean speed, and the run's mean IMom (summary.json).",
            "",
            "| model | fines in contact | fines' mean speed (mm/s) | speed / undamped | mean IMom (%) |",
            "| --- | --- | --- | --- | --- |"]
    base = None
    rows = []
    for l in ladders:
        k = l["rates"].index(common)
        ids = l["rungs"][k]["runs"]
        f = [fines(os.path.join(COPY, runs[i]["dir"])) for i in ids]
        contact = sum(x[0] for x in f) / len(f)
        speed = sum(x[1] for x in f) / len(f)
        imom = sum(runs[i]["mean_imom"] for i in ids) / len(ids)
        if l["model"] == "none":
            base = speed
        rows.append((label(l), contact, speed, imom))
    for name, contact, speed, imom in rows:
        out.append(f"| {name} | {contact:.3f} | {1000 * speed:.3g} | {speed / base:.2f} | {100 * imom:.3g} |")
    return "\n".join(out) + "\n"


def plot(a):
    os.makedirs(os.path.join(HERE, "figures"), exist_ok=True)
    ladders = a["convergence"]
    dat = os.path.join(HERE, "figures", "limit.dat")
    with open(dat, "w") as o:
        for l in ladders:
            pk, ev = scalar(l, "peak_phi_deg"), scalar(l, "ev")
            o.write(f"# {label(l)}\n")
            for k, x in enumerate(l["rates"]):
                o.write(f"{x} {pk['mean'][k]} {pk['error'][k]} {100 * ev['mean'][k]} {100 * ev['error'][k]}\n")
            o.write("\n\n")
    n = len(ladders)
    titles = [label(l) for l in ladders]
    png = os.path.join(HERE, "figures", "limit-A-small.png")
    script = f"""set terminal pngcairo size 1400,600 font ',11' noenhanced
set output '{png}'
set multiplot layout 1,2 title 'paper-A-small, 3 seeds: the response as the strain rate falls (seed mean ± standard error)'
set logscale x
set xrange [*:*] reverse
set xlabel "strain rate ε'"
set format x '%.0e'
set key top right
set ylabel 'peak φ (°)'
plot for [i=0:{n - 1}] '{dat}' index i using 1:2:3 with yerrorlines title word("{' '.join(t.replace(' ', '_') for t in titles)}", i+1)
unset key
set ylabel 'εv at the end (%)'
plot for [i=0:{n - 1}] '{dat}' index i using 1:4:5 with yerrorlines title word("{' '.join(t.replace(' ', '_') for t in titles)}", i+1)
unset multiplot
"""
    subprocess.run(["gnuplot"], input=script, text=True, check=True)
    os.remove(dat)


def main():
    if len(sys.argv) == 3 and sys.argv[1] == "collect":
        collect(sys.argv[2])
        return
    a = json.load(open(os.path.join(COPY, "analysis", "analysis.json")))
    manifest = json.load(open(os.path.join(COPY, "study.json")))
    with open(os.path.join(HERE, "tables.md"), "w") as o:
        o.write(tables(a, manifest))
    plot(a)


if __name__ == "__main__":
    main()
