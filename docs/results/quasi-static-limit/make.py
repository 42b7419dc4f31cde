#!/usr/bin/env python3
"""Tables and figures of docs/results/quasi-static-limit.md, from the studies' own files.

  python3 docs/results/quasi-static-limit/make.py collect runs/qs-limit-small [NAME]
      copies the study's study.toml, study.json, analysis/ and report.html (and a `qsdem
      converge` directory's certificate.json and .html, case.toml and cases/), of every prepared sample
      summary.json and compaction.csv, and of every finished run summary.json, series.csv and
      classes.csv.gz, to docs/results/quasi-static-limit/NAME/ (default `small`; `qsdem analyze`
      of that copy gives its analysis again);
  python3 docs/results/quasi-static-limit/make.py [NAME]
      reads the copy and writes tables.md (NAME small) or tables-NAME.md, and
      figures/limit-A-small.png (NAME small) or figures/limit-NAME.png (gnuplot, pngcairo).

Measures: the certificate of each ladder (analysis.json "convergence", docs/analysis.md section
11): per rung the seed mean and standard error of peak phi and of ev at the last strain, the paired
change to the slowest rung (RMS, beyond the noise, standard error), the status. Where the runs kept
the energy ledger (summary.json phases[-1].energy), the shares of the triaxial work dissipated by
sliding, by the contact dashpots and by the particle damping. The fines: the smallest size class of classes.csv, its
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
COPY = os.path.join(HERE, "small")  # set by main()


def gz(src, dst):
    with open(src, "rb") as i, open(dst, "wb") as raw:
        with gzip.GzipFile(filename=os.path.basename(src), mode="wb", fileobj=raw, mtime=0) as o:
            shutil.copyfileobj(i, o)


def collect(study):
    if os.path.exists(COPY):
        shutil.rmtree(COPY)
    os.makedirs(COPY)
    for f in ("study.toml", "study.json", "report.html", "certificate.json", "certificate.html", "case.toml"):
        if os.path.exists(os.path.join(study, f)):
            shutil.copy(os.path.join(study, f), COPY)
    if os.path.isdir(os.path.join(study, "cases")):
        shutil.copytree(os.path.join(study, "cases"), os.path.join(COPY, "cases"))
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
        if os.path.exists(os.path.join(root, "classes.csv")):
            gz(os.path.join(root, "classes.csv"), os.path.join(d, "classes.csv.gz"))
        else:  # a run kept from a committed study (study.md: continuing from what a repository keeps)
            shutil.copy(os.path.join(root, "classes.csv.gz"), d)


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


def tables(a, manifest, name):
    ladders = a["convergence"]
    n_seeds = len(ladders[0]["seeds"])
    out = ["# Tables of docs/results/quasi-static-limit.md",
           "",
           f"Made by `python3 docs/results/quasi-static-limit/make.py {name}` from `{name}/` (the study's files).",
           "",
           "## The certificate of each model (tolerances RMS Δφ 0.5°, RMS Δεv 0.1 %, and the seed scatter)",
           "",
           "Δ: the seed mean of the paired change between the two slowest rungs, RMS over the strain (beyond",
           "its noise in brackets, docs/analysis.md 11), ± its standard error over the seeds. Scatter: the",
           "standard deviation over the seeds at the slowest rung. Peak φ and εv at the end: seed mean ±",
           "standard error at the slowest rung.",
           "",
           "| model | rates run | Δφ two slowest (°) | Δεv two slowest (%) | seed scatter φ (°) / εv (%) | status | peak φ at the slowest (°) | εv at the end at the slowest (%) | steps |",
           "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for l in ladders:
        r = l["rungs"][-2] if len(l["rungs"]) > 1 else None
        pk, ev = scalar(l, "peak_phi_deg"), scalar(l, "ev")

        def change(key, scale):
            if not r:
                return "—"
            c = r[key + "_to_slowest"]
            return f"{fmt(scale * c['rms'], 2)} ({fmt(scale * c['excess'], 2)}) ± {fmt(scale * c['error'], 2)}"

        out.append("| {} | {} | {} | {} | {} / {} | {} | {} ± {} | {} ± {} | {} |".format(
            label(l), ", ".join(f"{x:.3g}" for x in l["rates"]), change("phi", 1), change("ev", 100),
            fmt(l["phi_scatter_deg"], 2), fmt(100 * l["ev_scatter"], 2), l["status"],
            fmt(pk["mean"][-1], 4), fmt(pk["error"][-1], 2), fmt(100 * ev["mean"][-1], 3), fmt(100 * ev["error"][-1], 2),
            fmt(l["steps"], 3)))
    out += ["", "## Peak φ and εv at the end at each rate (seed mean ± standard error)", "",
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
    if not any(l["model"] == "none" for l in ladders):
        return "\n".join(out) + "\n"
    out += ["", "## Against the undamped run of the same seed and rate", "",
            "Per seed, the model's run minus the undamped run on the same sample at the same rate, then the mean",
            f"± its standard error over the {n_seeds} seeds (summary.json: peak_phi_deg, final_ev).", "",
            "| model | " + " | ".join(f"ε' = {x:.3g}: Δ peak φ (°) / Δ εv at the end (%)" for x in rates) + " |",
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
    for model, contact, speed, imom in rows:
        out.append(f"| {model} | {contact:.3f} | {1000 * speed:.3g} | {speed / base:.2f} | {100 * imom:.3g} |")
    # Where the work went: the energy ledger of the triaxial phase, when the runs kept it.
    energy = {}
    for l in ladders:
        k = l["rates"].index(common)
        shares = []
        for i in l["rungs"][k]["runs"]:
            summary = json.load(open(os.path.join(COPY, runs[i]["dir"], "summary.json")))
            e = summary["phases"][-1].get("energy")
            if not e:
                break
            w = e["work_J"]
            shares.append((e["friction_J"] / w, e["contact_damping_J"] / w, e["damping_J"] / w,
                           e["elastic_change_J"] / w, e["kinetic_change_J"] / w))
        if len(shares) == len(l["rungs"][k]["runs"]):
            energy[label(l)] = [sum(s[j] for s in shares) / len(shares) for j in range(5)]
    if energy:
        out += ["", f"## Where the work goes at ε' = {common:.3g}", "",
                "The triaxial phase's energy ledger (summary.json phases[-1].energy, docs/physics.md 12): the work",
                "of the cell, and its shares dissipated by sliding, by the contact dashpots and by the particle",
                "damping, stored as elastic energy and left as kinetic energy, mean over the seeds.", "",
                "| model | sliding | dashpots | particle damping | elastic change | kinetic change |",
                "| --- | --- | --- | --- | --- | --- |"]
        for model, v in energy.items():
            out.append(f"| {model} | " + " | ".join(f"{round(100 * x, 1) + 0.0:.1f} %" for x in v) + " |")
    return "\n".join(out) + "\n"


def plot(a, name):
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
    sample = ladders[0]["sample"]
    png = os.path.join(HERE, "figures", "limit-A-small.png" if name == "small" else f"limit-{name}.png")
    script = f"""set terminal pngcairo size 1400,600 font ',11' noenhanced
set output '{png}'
set multiplot layout 1,2 title '{sample} ({name}/), {len(ladders[0]["seeds"])} seeds: the response as the strain rate falls (seed mean ± standard error)'
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
    global COPY
    collecting = len(sys.argv) in (3, 4) and sys.argv[1] == "collect"
    name = (sys.argv[3] if len(sys.argv) == 4 else "small") if collecting else (sys.argv[1] if len(sys.argv) == 2 else "small")
    COPY = os.path.join(HERE, name)
    if collecting:
        collect(sys.argv[2])
        return
    a = json.load(open(os.path.join(COPY, "analysis", "analysis.json")))
    manifest = json.load(open(os.path.join(COPY, "study.json")))
    with open(os.path.join(HERE, "tables.md" if name == "small" else f"tables-{name}.md"), "w") as o:
        o.write(tables(a, manifest, name))
    plot(a, name)


if __name__ == "__main__":
    main()
