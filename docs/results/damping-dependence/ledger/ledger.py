"""Where the cell's work goes in a triaxial test: the energy ledger's columns of series.csv
(output.energy, docs/physics.md 12) from its first row to the rows nearest e1 = 2 %, 5 % and 10 %,
as shares of the work. Usage: ledger.py RUN_DIR..."""
import csv
import sys

TERMS = ("friction_J", "contact_damping_J", "damping_J", "elastic_J")


def shares(run, target):
    rows = list(csv.DictReader(open(run + "/series.csv")))
    first = rows[0]
    row = min(rows, key=lambda r: abs(float(r["e1"]) - target))
    delta = lambda k: float(row[k]) - float(first[k])
    work = delta("work_J")
    parts = {k: delta(k) for k in TERMS}
    error = work + delta("stiffness_change_J") - sum(parts.values()) - delta("ekin_J")
    return float(row["e1"]), work, parts, error


print("| run | e1 | W (J) | sliding | particle damping | dashpots | stored | balance error |")
print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
for run in sys.argv[1:]:
    for target in (0.02, 0.05, 0.10):
        e1, w, p, err = shares(run, target)
        print(f"| {run.rstrip('/').split('/')[-1]} | {100 * e1:.0f} % | {w:.3g} | {p['friction_J'] / w:.1%} | "
              f"{p['damping_J'] / w:.1%} | {p['contact_damping_J'] / w:.1%} | {p['elastic_J'] / w:.1%} | {err / w:.1e} |")
