// Figures drawn by gnuplot, and the HTML that shows them: the machinery of the study's report
// (docs/analysis.md) and of a run's page (`qsdem plot`, docs/runs.md). A figure is data (panels of
// curves); render_figure writes NAME.dat and NAME.gp and runs gnuplot on them (NAME.svg, NAME.png).
#pragma once
#include <cstddef>
#include <filesystem>
#include <string>
#include <vector>

namespace qsdem {

struct Curve {
  std::string title;  // empty: no key entry
  std::vector<double> x, y;
  std::string style;  // gnuplot `with ...` clause
};

struct Panel {
  std::string title, xlabel, ylabel;
  bool logx = false, logy = false;
  std::vector<Curve> curves;
  std::string extra = "";  // more gnuplot commands before `plot` (ranges)
};

struct Figure {
  std::string name, title, caption;
  std::vector<Panel> panels;  // 1, or 2 per row
};

// The gnuplot line colour of the i-th curve of a panel ("lc 1", "lc 2", ...).
std::string lc(std::size_t i);

// Whether `gnuplot` can be run (found on PATH).
bool gnuplot_available();

// Writes NAME.dat and NAME.gp into figdir and runs gnuplot there (.svg and .png); `source` names the
// section of docs/physics.md the figure shows, in the script's first line ("SPEC 9"). Points a log
// axis cannot show (NaN, zero) are dropped first. Returns false (and nothing is drawn) when the
// figure has no usable point; throws std::runtime_error with gnuplot's log when it fails.
bool render_figure(const std::filesystem::path& figdir, Figure& f, const std::string& source);

std::string html_escape(const std::string& s);

// The start of an HTML page up to and including its <body> tag, with the page's style and a script
// that counts the images that really decoded (data-images-loaded / data-images-total on <body>,
// read by the headless-browser tests).
std::string html_head(const std::string& title);

// A drawn figure as HTML: its PNG, caption and links to its SVG, data and script, all under `prefix`
// ("analysis/figures/", or "" for figures next to the page).
std::string figure_html(const Figure& f, const std::string& prefix);

}  // namespace qsdem
