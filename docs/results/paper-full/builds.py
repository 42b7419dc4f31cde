#!/usr/bin/env python3
"""Which build made each committed run and prepared sample of docs/results.

    python3 docs/results/paper-full/builds.py

Reads every summary.json under docs/results (a run directory, or a prepared sample's) and writes
docs/results/paper-full/measures/builds.csv, one row per directory:

  study      the directory under docs/results (paper-full, damping-dependence, ...)
  path       the directory, relative to docs/results
  kind       run (a triaxial test), sample (a compaction that runs start from) or analysis (an
             analysis/ directory: its analysis.json's study.qsdem_version, the build of `qsdem
             analyze`; a version without "+commit" names no commit)
  build      summary.json's "version": the build that wrote the summary, i.e. finished the run
  commit     the commit in that version string (or the full hash of summary.json's "build" record,
             which newer builds write with "tree_clean")
  dirty      true when the version ends in -dirty (or "tree_clean" is false): the build's tree had uncommitted changes, so
             the engine's source at that build is not recoverable from git alone
  resumed_at_step, resume_changes
             summary.json's "resume_changes" (a run continued from a checkpoint records the step
             and what changed); the build that began such a run is not recorded in any file
  threads, steps, wall_s
             summary.json's derived.threads (one value per run, not per segment), steps, wall_s

and docs/results/paper-full/measures/builds.md, the count of directories per (study, kind,
build). Python 3 standard library only.
"""
import csv
import collections
import json
import os
import re

HERE = os.path.dirname(os.path.abspath(__file__))
RESULTS = os.path.dirname(HERE)
OUT = os.path.join(HERE, "measures")
VERSION = re.compile(r"^\d+\.\d+\.\d+\+([0-9a-f]{7,40})(-dirty)?$")
RESUME = re.compile(r"from \w+ step (\d+)")


def rows():
    out = []
    for top, dirs, files in os.walk(RESULTS):
        dirs.sort()
        if "analysis.json" in files and os.path.basename(top) == "analysis":
            with open(os.path.join(top, "analysis.json")) as f:
                version = json.load(f).get("study", {}).get("qsdem_version", "")
            m = VERSION.match(version)
            rel = os.path.relpath(top, RESULTS)
            out.append({"study": rel.split(os.sep)[0], "path": rel.replace(os.sep, "/"), "kind": "analysis",
                        "build": version, "commit": m.group(1) if m else "",
                        "dirty": ("true" if m.group(2) else "false") if m else "",
                        "resumed_at_step": "", "resume_changes": "", "threads": "", "steps": "", "wall_s": ""})
        if "summary.json" not in files:
            continue
        with open(os.path.join(top, "summary.json")) as f:
            s = json.load(f)
        version = s.get("version", "")
        m = VERSION.match(version)
        commit = m.group(1) if m else ""
        dirty = ("true" if m.group(2) else "false") if m else ""
        record = s.get("build")  # newer summaries: {version, commit (full hash), tree_clean}
        if isinstance(record, dict):
            version = record.get("version") or version
            commit = record.get("commit") or commit
            if record.get("tree_clean") is not None:
                dirty = "false" if record["tree_clean"] else "true"
        changes = s.get("resume_changes") or []
        steps_at = sorted({int(x) for c in changes for x in RESUME.findall(c)})
        rel = os.path.relpath(top, RESULTS)
        out.append({
            "study": rel.split(os.sep)[0],
            "path": rel.replace(os.sep, "/"),
            "kind": "sample" if s.get("steps_cover") == "compaction" else "run",
            "build": version,
            "commit": commit,
            "dirty": dirty,
            "resumed_at_step": " ".join(str(x) for x in steps_at),
            "resume_changes": "; ".join(changes),
            "threads": s.get("derived", {}).get("threads", ""),
            "steps": s.get("steps", ""),
            "wall_s": f"{s['wall_s']:.1f}" if "wall_s" in s else "",
        })
    out.sort(key=lambda r: r["path"])
    return out


def main():
    os.makedirs(OUT, exist_ok=True)
    table = rows()
    fields = list(table[0].keys())
    with open(os.path.join(OUT, "builds.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, lineterminator="\n")
        w.writeheader()
        w.writerows(table)
    count = collections.Counter((r["study"], r["kind"], r["build"]) for r in table)
    resumed = collections.Counter((r["study"], r["kind"], r["build"]) for r in table if r["resume_changes"])
    lines = ["| study | kind | build | dirty | directories | of them resumed |",
             "| --- | --- | --- | --- | ---: | ---: |"]
    for (study, kind, build), n in sorted(count.items()):
        dirty = "yes" if build.endswith("-dirty") else "no" if VERSION.match(build) else "not recorded"
        lines.append(f"| {study} | {kind} | `{build}` | {dirty} | {n} | {resumed[(study, kind, build)]} |")
    lines.append("")
    for study in sorted({r["study"] for r in table}):
        runs = [r for r in table if r["study"] == study and r["kind"] == "run"]
        dirty = sum(r["dirty"] == "true" for r in runs)
        if not runs:
            lines.append(f"- {study}: no run directories committed")
            continue
        lines.append(f"- {study}: {len(runs)} runs, {dirty} of them by a build from a modified (-dirty) tree")
    with open(os.path.join(OUT, "builds.md"), "w") as f:
        f.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
