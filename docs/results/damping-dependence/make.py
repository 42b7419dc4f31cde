#!/usr/bin/env python3
"""Tables and figures of docs/results/damping-dependence.md, from the runs' own files.

  python3 docs/results/damping-dependence/make.py collect runs/damping-small runs/damping-small-B ...
      copies each study's study.json, analysis/deviation.csv and analysis/tables.md, and of every
      finished run summary.json, series.csv.gz and classes.csv.gz, here (STUDY_NAME/...);
  python3 docs/results/damping-dependence/make.py collect-runs NAME RUN_DIR...
      the same for runs of `qsdem run` (NAME/study.json made from their summary.json);
  python3 docs/results/damping-dependence/make.py
      reads those copies and writes tables.md and figures/*.png (gnuplot, pngcairo; the plot's
      data and script are written next to it and removed once it is drawn).

Measures (per run, from series.csv, classes.csv and summary.json of the triaxial test):
  phi: phi_al_deg, the angle from the axial and the mean lateral stress; its peak over the rows,
       and its mean over the rows with e1 in [1 %, 3 %] and in [3 %, 7 %];
  ev at 5 / 10 %, cn at 10 %: linear interpolation of the rows at that e1;
  IMom, UFR: mean_imom, mean_ufr of summary.json (the average over the rows);
  fines: the smallest size class of classes.csv, its fraction in contact (in_contact), share
       of p (p_share), mean speed and spin, each averaged over the rows with e1 in [1 %, 10 %].
Python 3 standard library only; gnuplot draws the PNGs.
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


def copy_run(src, dst):
    """summary.json as it is; series.csv and classes.csv gzipped (mtime 0: the same bytes each time)."""
    os.makedirs(dst)
    shutil.copy(os.path.join(src, "summary.json"), dst)
    for f in ("series.csv", "classes.csv"):
        with open(os.path.join(src, f), "rb") as i, open(os.path.join(dst, f + ".gz"), "wb") as raw:
            with gzip.GzipFile(filename=f, mode="wb", fileobj=raw, mtime=0) as o:
                o.write(i.read())


def collect(study_dirs):
    for sd in study_dirs:
        manifest = json.load(open(os.path.join(sd, "study.json")))
        out = os.path.join(HERE, manifest["name"])
        if os.path.isdir(out):
            shutil.rmtree(out)
        os.makedirs(os.path.join(out, "analysis"))
        shutil.copy(os.path.join(sd, "study.json"), out)
        for f in ("deviation.csv", "tables.md"):
            src = os.path.join(sd, "analysis", f)
            if os.path.exists(src):
                shutil.copy(src, os.path.join(out, "analysis"))
        for run in manifest["runs"]:
            src = os.path.join(sd, run["dir"])
            if not os.path.exists(os.path.join(src, "summary.json")):
                continue
            copy_run(src, os.path.join(out, run["dir"]))


def collect_runs(name, run_dirs):
    """Runs made by `qsdem run` (not a study): a manifest like a study's, from each summary.json."""
    out = os.path.join(HERE, name)
    if os.path.isdir(out):
        shutil.rmtree(out)
    runs = []
    for rd in run_dirs:
        cfg = json.load(open(os.path.join(rd, "summary.json")))["config"]["resolved_si"]
        sample = json.load(open(os.path.join(rd, "summary.json")))["case"]
        test = cfg["protocol"][-1]  # the sheared phase (older summaries also hold "damping" and "triaxial")
        model, xi, rate = test["damping"]["model"], test["damping"]["ratio"], test["control"]["33"]["strain_rate"]
        rid = "%s-seed%d/%s/xi-%.3g%%/rate-%.0e" % (sample, cfg["sample"]["seed"], model, 100 * xi, rate)
        runs.append({"id": rid, "sample": sample, "seed": cfg["sample"]["seed"], "model": model, "xi": xi,
                     "rate": rate, "dir": "runs/" + rid})
        copy_run(rd, os.path.join(out, "runs", rid))
    with open(os.path.join(out, "study.json"), "w") as f:
        json.dump({"name": name, "runs": runs}, f, indent=1)


def read_csv(path):
    with gzip.open(path + ".gz", "rt") as f:
        return list(csv.DictReader(f))


def interp(rows, x, key, xkey="e1"):
    pts = [(float(r[xkey]), float(r[key])) for r in rows]
    for (x0, y0), (x1, y1) in zip(pts, pts[1:]):
        if x0 <= x <= x1 + 1e-9 and x1 > x0:
            return y0 + (y1 - y0) * (min(x, x1) - x0) / (x1 - x0)
    return float("nan")


def mean_over(rows, lo, hi, key):
    v = [float(r[key]) for r in rows if lo <= float(r["e1"]) <= hi]
    return sum(v) / len(v) if v else float("nan")


def load_runs():
    runs = []
    for study in sorted(os.listdir(HERE)):
        mf = os.path.join(HERE, study, "study.json")
        if not os.path.exists(mf):
            continue
        manifest = json.load(open(mf))
        for run in manifest["runs"]:
            d = os.path.join(HERE, study, run["dir"])
            if not os.path.exists(os.path.join(d, "summary.json")):
                runs.append(dict(run, study=study, finished=False))
                continue
            s = json.load(open(os.path.join(d, "summary.json")))
            series = read_csv(os.path.join(d, "series.csv"))
            classes = [r for r in read_csv(os.path.join(d, "classes.csv")) if r["phase"] == "triaxial"]
            fine_r = min(float(r["radius_mm"]) for r in classes)
            fines = [r for r in classes if float(r["radius_mm"]) == fine_r]
            runs.append(dict(
                run, study=study, finished=True, path=d, series=series, fines=fines, fine_radius_mm=fine_r,
                phi_peak=max(float(r["phi_al_deg"]) for r in series),
                phi_1_3=mean_over(series, 0.01, 0.03, "phi_al_deg"),
                phi_3_7=mean_over(series, 0.03, 0.07, "phi_al_deg"),
                ev5=interp(series, 0.05, "ev"), ev10=interp(series, 0.10, "ev"),
                cn10=interp(series, 0.10, "cn"),
                imom=s["mean_imom"], ufr=s["mean_ufr"],
                fine_contact=mean_over(fines, 0.01, 0.10, "in_contact"),
                fine_share=mean_over(fines, 0.01, 0.10, "p_share"),
                fine_speed=mean_over(fines, 0.01, 0.10, "speed_m_s"),
                fine_spin=mean_over(fines, 0.01, 0.10, "spin_1_s")))
    return runs


def label(r):
    if r["model"] == "none":
        return "none"
    return "%s %.3g%s" % (r["model"], 100 * r["xi"] if r["model"] != "local" else r["xi"],
                          " %" if r["model"] != "local" else "")


def table(runs):
    out = ["| study | sample, seed | model | eps' | phi peak | phi 1-3 % | phi 3-7 % | ev 5 % | ev 10 % | cn 10 % "
           "| mean IMom | mean UFR | fines in contact | fines' share of p | fines' speed | fines' spin |",
           "| --- | --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r in runs:
        head = "| %s | %s, %d | %s | %.0e |" % (r["study"], r["sample"], r["seed"], label(r), r["rate"])
        if not r["finished"]:
            out.append(head + " not finished |" + " |" * 11)
            continue
        out.append(head + " %.1f | %.1f | %.1f | %+.2f %% | %+.2f %% | %.2f | %.2f %% | %.3f | %.0f %% | %.1f %% | %.3g mm/s | %.3g 1/s |" % (
            r["phi_peak"], r["phi_1_3"], r["phi_3_7"], 100 * r["ev5"], 100 * r["ev10"], r["cn10"],
            100 * r["imom"], r["ufr"], 100 * r["fine_contact"], 100 * r["fine_share"], 1e3 * r["fine_speed"],
            r["fine_spin"]))
    return "\n".join(out)


def plot(name, title, ylabel, curves, xrange="[0:10]"):
    """curves: (title, [(x, y)], dash[, colour]) each; writes figures/NAME.png and its .dat and .gp."""
    fig = os.path.join(HERE, "figures")
    os.makedirs(fig, exist_ok=True)
    dat = os.path.join(fig, name + ".dat")
    with open(dat, "w") as f:
        for t, pts, *_ in curves:
            f.write("# %s\n" % t)
            for x, y in pts:
                f.write("%.6g %.6g\n" % (x, y))
            f.write("\n\n")
    colours = ["#000000", "#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf",
               "#7f7f7f", "#bcbd22"]
    lines = []
    for k, (t, _, dash, *colour) in enumerate(curves):
        lines.append("'%s.dat' index %d using 1:2 with lines lw 2 dt %d lc rgb '%s' title \"%s\"" % (
            name, k, dash, colour[0] if colour else colours[k % len(colours)], t))
    gp = os.path.join(fig, name + ".gp")
    with open(gp, "w") as f:
        f.write("set terminal pngcairo size 800,520 font ',10'\nset output '%s.png'\n" % name)
        f.write('set title "%s"\nset xlabel "axial strain e1 (%%)"\nset ylabel "%s"\n' % (title, ylabel))
        f.write("set xrange %s\nset key outside right\nset grid\n" % xrange)
        f.write("plot " + ", \\\n     ".join(lines) + "\n")
    subprocess.run(["gnuplot", name + ".gp"], cwd=fig, check=True)
    os.remove(dat)  # remade with the figure; the data are the runs' files
    os.remove(gp)


def curve(r, key, scale=1.0, rows="series"):
    return [(100 * float(x["e1"]), scale * float(x[key])) for x in r[rows]]


def figures(runs):
    shutil.rmtree(os.path.join(HERE, "figures"), ignore_errors=True)
    done = [r for r in runs if r["finished"]]
    groups = {}
    for r in done:
        groups.setdefault((r["study"], r["sample"], r["seed"]), []).append(r)
    for (study, sample, seed), rs in groups.items():
        if study == "damping-seeds":
            continue
        for rate in (1e-6,):  # every model at 1e-6; the other rates in the rate figures
            at = [r for r in rs if r["rate"] == rate]
            if len(at) < 2:
                continue
            tag = "%s_%.0e" % (sample, rate)
            what = "%s, eps' = %.0e" % (sample, rate)
            plot("phi_" + tag, "phi (axial-lateral) vs e1: " + what, "phi (deg)",
                 [(label(r), curve(r, "phi_al_deg"), 1) for r in at])
            plot("ev_" + tag, "volumetric strain vs e1: " + what, "ev (%, dilation +)",
                 [(label(r), curve(r, "ev", 100), 1) for r in at])
            plot("fines_" + tag, "fraction of the smallest class (R = %.4g mm) in contact: %s" % (at[0]["fine_radius_mm"], what),
                 "fraction with >= 1 contact", [(label(r), curve(r, "in_contact", 1, "fines"), 1) for r in at])
    # The rate: none and nd at every rate run on one sample (the studies and the runs from its
    # prepared sample).
    by_sample = {}
    for r in done:
        if r["study"] != "damping-seeds":
            by_sample.setdefault((r["sample"], r["seed"]), []).append(r)
    for (sample, seed), rs in by_sample.items():
        pair = [r for r in rs if r["model"] in ("none", "nd")]
        if len({r["rate"] for r in pair}) > 2:
            pair.sort(key=lambda r: (r["model"], -r["rate"]))
            dash = {1e-5: 3, 1e-6: 2, 1e-7: 1}
            for key, name, yl, sc, rows in (("phi_al_deg", "phi", "phi (deg)", 1, "series"),
                                             ("ev", "ev", "ev (%, dilation +)", 100, "series"),
                                             ("in_contact", "fines", "fraction of the smallest class in contact", 1, "fines")):
                plot("rate_%s_%s" % (name, sample), "%s, none (black) and nd (red); solid 1e-7, dashed 1e-6, dotted 1e-5" % sample, yl,
                     [("%s, %.0e" % (label(r), r["rate"]), curve(r, key, sc, rows), dash.get(r["rate"], 1),
                       "#000000" if r["model"] == "none" else "#d62728") for r in pair])
    # The seeds: none and nd of each seed.
    seeds = sorted((r for r in done if r["study"] == "damping-seeds"), key=lambda r: (r["model"], r["seed"]))
    if seeds:
        for key, name, yl, sc, rows in (("phi_al_deg", "phi", "phi (deg)", 1, "series"),
                                         ("ev", "ev", "ev (%, dilation +)", 100, "series"),
                                         ("in_contact", "fines", "fraction of the smallest class in contact", 1, "fines")):
            plot("seeds_%s" % name, "spheres-A-small, three seeds, eps' = 1e-6", yl,
                 [("%s, seed %d" % (label(r), r["seed"]), curve(r, key, sc, rows), 1 + (r["seed"] - 1)) for r in seeds])


def main():
    if len(sys.argv) > 1 and sys.argv[1] == "collect":
        collect(sys.argv[2:])
        return
    if len(sys.argv) > 2 and sys.argv[1] == "collect-runs":
        collect_runs(sys.argv[2], sys.argv[3:])
        return
    runs = load_runs()
    with open(os.path.join(HERE, "tables.md"), "w") as f:
        f.write("<!-- written by make.py from the files in this directory -->\n\n")
        f.write(table(runs) + "\n")
    figures(runs)


if __name__ == "__main__":
    main()
