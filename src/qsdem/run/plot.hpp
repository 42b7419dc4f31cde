// A picture of a run (`qsdem plot DIR`, docs/runs.md): the figures of each of its series files,
// read by column name (docs/physics.md 10.1, 10.3), drawn by gnuplot into DIR/plot/ with one HTML
// page, DIR/plot/index.html.
#pragma once
#include <filesystem>
#include <string>
#include <vector>

namespace qsdem {

struct PlotResult {
  std::filesystem::path page;        // the HTML page
  std::vector<std::string> figures;  // the names of the figures drawn (NAME.png, NAME.svg, ...)
  std::vector<std::string> notes;    // the figures left out, and why (a missing column, no rows)
};

// Draws the figures of the run directory `dir` into `out` (default: dir/plot), which is created
// (never through a link) and whose figures and page of an earlier plot are replaced. The series
// files are those summary.json's phases name, else series.csv and compaction.csv (or their
// .partial, of a run still going). Throws InputError when `dir` holds none of them, naming what is
// missing; std::runtime_error when gnuplot is missing or fails.
PlotResult plot_run(const std::filesystem::path& dir, const std::filesystem::path& out = {});

}  // namespace qsdem
