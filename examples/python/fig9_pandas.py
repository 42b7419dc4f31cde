#!/usr/bin/env python3
"""A study read into pandas: the paper's Fig. 9 (IMom at the optimum damping ratio against the strain
rate, and its power law IMom = a eps'^b) from a study directory's analysis/optimum.csv, the fit
redone with numpy, checked against the analysis' own (power_law.csv), and drawn by gnuplot.

    PYTHONPATH=build/python /usr/bin/python3 examples/python/fig9_pandas.py [STUDY_DIR] [OUT.png]

STUDY_DIR defaults to the committed paper-size study, docs/results/paper-full. Needs pandas
(Debian: python3-pandas) and gnuplot.
"""
import pathlib
import subprocess
import sys
import tempfile

import numpy as np
import pandas as pd

root = pathlib.Path(__file__).resolve().parents[2]
study = pathlib.Path(sys.argv[1]) if len(sys.argv) > 1 else root / "docs" / "results" / "paper-full"
out = pathlib.Path(sys.argv[2] if len(sys.argv) > 2 else "fig9.png").resolve()

optimum = pd.read_csv(study / "analysis" / "optimum.csv")
laws = pd.read_csv(study / "analysis" / "power_law.csv").set_index(["sample", "model"])
imom = optimum[(optimum["index"] == "imom") & (optimum["index_at_opt"] > 0)]

plots, data = [], []
for k, ((sample, model), g) in enumerate(imom.groupby(["sample", "model"])):
    g = g.sort_values("rate")
    if len(g) < 2:
        continue
    b, log_a = np.polyfit(np.log10(g["rate"]), np.log10(g["index_at_opt"]), 1)
    law = laws.loc[(sample, model)]
    print(f"{sample} {model}: {len(g)} rates, IMom = {10 ** log_a:.4g} eps'^{b:.4f} "
          f"(the analysis: {law['a']:.4g} eps'^{law['b']:.4f}; the paper: {law['paper_a']} eps'^{law['paper_b']}), "
          f"eps'_QS = {law['eps_qs']:.3g}")
    name = f"{sample} {model}"
    data.append("\n".join(f"{r} {100 * i}" for r, i in zip(g["rate"], g["index_at_opt"])))
    plots.append(f"'$DAT' index {2 * k} with points pt 7 lc {k + 1} title '{name}'")
    rates = np.geomspace(g["rate"].min() / 2, g["rate"].max() * 2, 20)
    data.append("\n".join(f"{r} {100 * 10 ** log_a * r ** b}" for r in rates))
    plots.append(f"'$DAT' index {2 * k + 1} with lines lc {k + 1} notitle")

with tempfile.TemporaryDirectory() as tmp:
    dat = pathlib.Path(tmp) / "fig9.dat"
    dat.write_text("\n\n\n".join(data) + "\n")
    script = (f"set terminal pngcairo size 800,600\nset output '{out}'\nset logscale xy\n"
              "set format x '10^{%L}'\nset format y '%g'\n"
              "set xlabel \"strain rate eps'\"\nset ylabel 'IMom at the optimum (%)'\nset key top left\n"
              "set title 'IMom at the optimum damping ratio (paper Fig. 9)'\n"
              "plot " + ", ".join(plots).replace("$DAT", str(dat)) + "\n")
    subprocess.run(["gnuplot"], input=script, text=True, check=True)
print(f"wrote {out}")
