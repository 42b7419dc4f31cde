// A picture of a run (plot.hpp): figures of its series files and classes.csv, found by column name
// (docs/physics.md 10.1, 10.3), drawn by gnuplot (figures.hpp), and one HTML page.
#include "qsdem/run/plot.hpp"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <optional>
#include <sstream>
#include <stdexcept>
#include <string_view>

#include <fmt/format.h>
#include <nlohmann/json.hpp>

#include "qsdem/engine/types.hpp"
#include "qsdem/run/figures.hpp"
#include "qsdem/run/files.hpp"
#include "qsdem/run/output.hpp"
#include "qsdem/version.hpp"

namespace qsdem {

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

constexpr double nan = std::numeric_limits<double>::quiet_NaN();

// Points per curve at most: a cyclic phase writes a row per step (12000 rows for 5 cycles of the
// example), which would make figures of megabytes and show nothing more.
constexpr std::size_t max_points = 4000;

// A CSV file of a run by header name: columns may be added (physics.md 10.1), order is not assumed.
struct Csv {
  std::vector<std::string> names;
  std::vector<std::vector<double>> cols;  // NaN where a cell is empty or text
  std::vector<std::string> phase;         // the `phase` column's text per row (empty without one)
  std::size_t rows = 0;

  const std::vector<double>* col(std::string_view name) const {
    for (std::size_t k = 0; k < names.size(); ++k)
      if (names[k] == name) return &cols[k];
    return nullptr;
  }
  void derive(const std::string& name, std::vector<double> v) { names.push_back(name), cols.push_back(std::move(v)); }
};

// The rows of a file; a row shorter than the header (the last of a file still being written) is
// left out. Derived columns: q/p, and the deviator q_axial = s33 - (s11 + s22)/2 of the cyclic
// controller's bounds (docs/loading-paths.md), both when their columns are there.
Csv read_csv(const fs::path& p) {
  int err = 0;
  const std::optional<std::string> text = read_regular_file(p, &err);
  if (!text) throw InputError(fmt::format("cannot read '{}': {}", p.string(), file_error(err)));
  std::istringstream in(*text);
  std::string line;
  Csv c;
  if (!std::getline(in, line)) return c;
  c.names = split_fields(line);
  c.cols.resize(c.names.size());
  const auto phase_at = std::find(c.names.begin(), c.names.end(), "phase");
  while (std::getline(in, line)) {
    const std::vector<std::string> cells = split_fields(line);
    if (cells.size() < c.names.size()) continue;
    for (std::size_t k = 0; k < c.names.size(); ++k) {
      char* end = nullptr;
      const double v = std::strtod(cells[k].c_str(), &end);
      c.cols[k].push_back(end != cells[k].c_str() && *end == '\0' ? v : nan);
    }
    if (phase_at != c.names.end()) c.phase.push_back(cells[static_cast<std::size_t>(phase_at - c.names.begin())]);
    ++c.rows;
  }
  const auto* q = c.col("q_Pa");
  const auto* p_ = c.col("p_Pa");
  const auto *s11 = c.col("s11_Pa"), *s22 = c.col("s22_Pa"), *s33 = c.col("s33_Pa");
  std::vector<double> ratio, q_axial;
  for (std::size_t i = 0; i < c.rows; ++i) {
    if (q && p_) ratio.push_back((*q)[i] / (*p_)[i]);
    if (s11 && s22 && s33) q_axial.push_back((*s33)[i] - 0.5 * ((*s11)[i] + (*s22)[i]));
  }
  if (q && p_) c.derive("q/p", std::move(ratio));
  if (s11 && s22 && s33) c.derive("q_axial", std::move(q_axial));
  return c;
}

// The rows of one phase (or one size class of a phase) of a file.
struct Segment {
  std::string name;
  std::vector<std::size_t> rows;
};

// Consecutive rows of the same phase; the whole file as `name` without a phase column.
std::vector<Segment> phase_segments(const Csv& c, const std::string& name) {
  std::vector<Segment> s;
  for (std::size_t i = 0; i < c.rows; ++i) {
    const std::string& ph = c.phase.empty() ? name : c.phase[i];
    if (s.empty() || s.back().name != ph) s.push_back({ph, {}});
    s.back().rows.push_back(i);
  }
  return s;
}

// The horizontal axis of a figure: a column, its scale and label.
struct XAxis {
  std::string column;
  double scale;
  std::string label;
};

const XAxis axial_strain{"e1", 100, "axial strain ε1 (%)"};
const XAxis time_axis{"time_s", 1, "time t (s)"};

// e1 when it only grows (or only falls) over `rows`, else the time: a cyclic or an unloading phase
// turns back in e1, and a quantity against it would be drawn over itself.
XAxis progress_axis(const Csv& c, const std::vector<std::size_t>& rows) {
  const std::vector<double>* e1 = c.col("e1");
  if (!e1) return time_axis;
  double lo = INFINITY, hi = -INFINITY;
  for (std::size_t i : rows) lo = std::min(lo, (*e1)[i]), hi = std::max(hi, (*e1)[i]);
  const double tol = 1e-6 * std::max(std::abs(lo), std::abs(hi));
  bool up = false, down = false;
  for (std::size_t k = 1; k < rows.size(); ++k) {
    const double d = (*e1)[rows[k]] - (*e1)[rows[k - 1]];
    up = up || d > tol, down = down || d < -tol;
  }
  return up && down ? time_axis : axial_strain;
}

std::vector<std::size_t> all_rows(const Csv& c) {
  std::vector<std::size_t> r(c.rows);
  for (std::size_t i = 0; i < c.rows; ++i) r[i] = i;
  return r;
}

// Column `y` (times `ys`) against the axis over the rows of `s`, every k-th row and the last when
// there are more than max_points.
Curve curve(const Csv& c, const XAxis& x, const std::string& y, double ys, const Segment& s, std::string title,
            std::string style) {
  Curve k{std::move(title), {}, {}, std::move(style)};
  const std::vector<double>*vx = c.col(x.column), *vy = c.col(y);
  if (!vx || !vy || s.rows.empty()) return k;
  const std::size_t stride = (s.rows.size() + max_points - 1) / max_points;
  for (std::size_t j = 0; j < s.rows.size(); j += stride) {
    const std::size_t i = s.rows[std::min(j, s.rows.size() - 1)];
    k.x.push_back(x.scale * (*vx)[i]), k.y.push_back(ys * (*vy)[i]);
  }
  if ((s.rows.size() - 1) % stride) {
    const std::size_t i = s.rows.back();
    k.x.push_back(x.scale * (*vx)[i]), k.y.push_back(ys * (*vy)[i]);
  }
  return k;
}

// One quantity of a panel: a column, its scale and its key entry.
struct Quantity {
  std::string column;
  double scale;
  std::string key;
};

// A panel of one or more quantities against `x`, a curve per segment. One quantity: a colour per
// segment (a key entry each when there are several); several: a colour per quantity. A column
// that is missing is named in `missing`; a panel none of whose columns exists is not added.
void add_panel(Figure& f, const Csv& c, const std::vector<Segment>& segs, const XAxis& x, const std::string& title,
               const std::string& ylabel, bool logy, const std::vector<Quantity>& qs, std::vector<std::string>& missing) {
  if (!c.col(x.column)) {
    missing.push_back(fmt::format("{}: no column {}", title, x.column));
    return;
  }
  Panel p{title, x.label, ylabel, false, logy, {}};
  // A strain or a time starts at the frame's left edge, without the margin a point would get.
  if (x.column == "e1" || x.column == "time_s") p.extra = "set offsets 0, 0, graph 0.06, graph 0.06\n";
  bool any = false;
  for (std::size_t k = 0; k < qs.size(); ++k) {
    if (!c.col(qs[k].column)) {
      missing.push_back(fmt::format("{}: no column {}", qs.size() > 1 ? qs[k].key : title, qs[k].column));
      continue;
    }
    any = true;
    for (std::size_t s = 0; s < segs.size(); ++s) {
      const bool many = qs.size() > 1;
      const std::string key = many ? (s == 0 ? qs[k].key : "") : (segs.size() > 1 ? segs[s].name : "");
      p.curves.push_back(curve(c, x, qs[k].column, qs[k].scale, segs[s], key, "lines lw 1.5 " + lc(many ? k : s)));
    }
  }
  if (any) f.panels.push_back(std::move(p));
}

// A series file of the run: its name, the phases that wrote to it, and what was read of it.
struct SeriesFile {
  std::string name;                   // series.csv
  std::vector<std::string> phases;    // in order
  std::vector<std::string> cyclic;    // those with a cyclic controller (summary.json)
  fs::path path;                      // the file read (NAME, or NAME.partial)
  Csv csv;
  std::vector<Segment> segments;
};

// File-name-safe tag of a file or phase name.
std::string tag(const std::string& s) {
  std::string r;
  for (char ch : s) r += (std::isalnum(static_cast<unsigned char>(ch)) || ch == '-' || ch == '_') ? ch : '_';
  return r.empty() ? "_" : r;
}

std::string stem(const std::string& file) { return file.substr(0, file.rfind('.')); }

std::string label_of(const SeriesFile& f) {
  std::string phases;
  for (const std::string& p : f.phases) phases += (phases.empty() ? "" : ", ") + p;
  return phases.empty() ? f.name : f.name + " (" + phases + ")";
}

// q/p, phi, ev and the void ratio against e1: the drained triaxial test's response (SPEC 8).
Figure stress_strain_figure(const SeriesFile& f, std::vector<std::string>& missing) {
  Figure fig{tag(stem(f.name)) + "_stress_strain", label_of(f) + ": stress ratio, friction angle and volumetric strain",
             "The stress ratio q/p (q = √(3 J2)), the mobilised friction angle φ = asin((σ1 − σ3)/(σ1 + σ3)), the "
             "volumetric strain εv = V/V0 − 1 (dilation positive) and the void ratio against the axial strain ε1 "
             "(compression positive), from the start of the file (docs/physics.md 10.1).",
             {}};
  const Csv& c = f.csv;
  add_panel(fig, c, f.segments, axial_strain, "q/p", "stress ratio q/p", false, {{"q/p", 1, "q/p"}}, missing);
  add_panel(fig, c, f.segments, axial_strain, "φ", "mobilised friction angle φ (°)", false, {{"phi_deg", 1, "φ"}},
            missing);
  add_panel(fig, c, f.segments, axial_strain, "εv", "volumetric strain εv (%), dilation > 0", false, {{"ev", 100, "εv"}},
            missing);
  add_panel(fig, c, f.segments, axial_strain, "void ratio", "void ratio e", false, {{"void_ratio", 1, "e"}}, missing);
  return fig;
}

Figure stress_path_figure(const SeriesFile& f, std::vector<std::string>& missing) {
  Figure fig{tag(stem(f.name)) + "_stress_path", label_of(f) + ": stress path",
             "The deviator q = √(3 J2) against the mean stress p (kPa); the open circle marks the first row.", {}};
  const XAxis p_axis{"p_Pa", 1e-3, "mean stress p (kPa)"};
  add_panel(fig, f.csv, f.segments, p_axis, fig.title, "deviator q (kPa)", false, {{"q_Pa", 1e-3, "q"}}, missing);
  if (!fig.panels.empty() && !f.segments.empty()) {
    Segment first{"start", {f.segments.front().rows.front()}};
    fig.panels.front().curves.push_back(curve(f.csv, p_axis, "q_Pa", 1e-3, first, "", "points pt 6 ps 2 lc rgb '#000000'"));
    fig.panels.front().extra = "set key bottom right\n";
  }
  return fig;
}

Figure equilibrium_figure(const SeriesFile& f, std::vector<std::string>& missing) {
  const XAxis x = progress_axis(f.csv, all_rows(f.csv));
  Figure fig{tag(stem(f.name)) + "_equilibrium", label_of(f) + ": equilibrium indices and coordination number",
             fmt::format("The unbalanced force ratio UFR, the unbalanced force index Iuf and the moment index IMom "
                         "(paper Eqs. 3, 2, 4; log scale, zeros not drawn) and the coordination number Cn = 2 nc/np "
                         "against {} (docs/physics.md 10.1).",
                         x.column == "e1" ? "the axial strain" : "the time (the axial strain turns back in this file)"),
             {}};
  add_panel(fig, f.csv, f.segments, x, "equilibrium indices", "index (%)", true,
            {{"ufr", 100, "UFR"}, {"iuf", 100, "Iuf"}, {"imom", 100, "IMom"}}, missing);
  add_panel(fig, f.csv, f.segments, x, "coordination number", "coordination number Cn", false, {{"cn", 1, "Cn"}},
            missing);
  return fig;
}

// The fabric of SPEC 7.1 (docs/physics.md 7.1) against e1 (or the time): the principal values
// along x3 of the contact-normal fabric and of its strong, weak and force-weighted versions, their
// deviatoric invariants with the orientation fabric's, and the mechanical coordination number.
// None for a file without the fabric columns.
std::optional<Figure> fabric_figure(const SeriesFile& f, std::vector<std::string>& missing) {
  if (!f.csv.col("fabric_33")) return std::nullopt;
  const XAxis x = progress_axis(f.csv, all_rows(f.csv));
  Figure fig{tag(stem(f.name)) + "_fabric", label_of(f) + ": fabric",
             "The contact-normal fabric φ = ⟨n n⟩ (Satake, Oda): its components along the axes and, along x3, "
             "those of the strong and the weak networks (normal force above or below the mean, Radjai et al. "
             "1998) and of the force-weighted fabric; the deviatoric invariants √(3/2 φ′:φ′) of each and of the "
             "orientation fabric of the major axes (spheroids only); the mechanical coordination number Z_m "
             "(rattlers out, Thornton 2000). Against " +
                 std::string(x.column == "e1" ? "the axial strain" : "the time") + " (docs/physics.md 7.1).",
             {}};
  add_panel(fig, f.csv, f.segments, x, "fabric components", "φ_ii", false,
            {{"fabric_11", 1, "φ11"}, {"fabric_22", 1, "φ22"}, {"fabric_33", 1, "φ33"},
             {"fabric_strong_33", 1, "φ33 strong"}, {"fabric_weak_33", 1, "φ33 weak"},
             {"fabric_force_33", 1, "φ33 force-weighted"}},
            missing);
  std::vector<Quantity> deviators{{"fabric_dev", 1, "contact normals"}, {"fabric_strong_dev", 1, "strong"},
                                  {"fabric_weak_dev", 1, "weak"}, {"fabric_force_dev", 1, "force-weighted"}};
  if (const std::vector<double>* o = f.csv.col("orient_dev"); o && std::any_of(o->begin(), o->end(), [](double v) {
        return std::isfinite(v);
      }))
    deviators.push_back({"orient_dev", 1, "particle orientation"});
  add_panel(fig, f.csv, f.segments, x, "fabric anisotropy", "deviatoric invariant", false, deviators, missing);
  add_panel(fig, f.csv, f.segments, x, "mechanical coordination", "Z_m", false, {{"z_mech", 1, "Z_m"}}, missing);
  return fig;
}

// The loops of a cyclic phase: q_axial against e1, a colour per cycle. A cycle runs from a top
// corner (where e1 turns from rising to falling) to the next (docs/loading-paths.md); the rows
// before the first are the loading to it.
Figure loops_figure(const SeriesFile& f, const std::string& phase, std::vector<std::string>& missing) {
  Figure fig{tag(stem(f.name)) + "_loops_" + tag(phase), label_of(f) + ": loops of phase " + phase,
             "The deviator q = σ33 − (σ11 + σ22)/2 (the cyclic controller's bounds) against the axial strain ε1 of the "
             "phase's rows, a colour per cycle; a cycle runs from a top corner to the next (docs/loading-paths.md).",
             {}};
  const std::vector<double>* e1 = f.csv.col("e1");
  std::vector<Segment> cycles;
  for (const Segment& s : f.segments) {
    if (s.name != phase || !e1) continue;
    cycles.push_back({"loading", {}});
    for (std::size_t k = 0; k < s.rows.size(); ++k) {
      cycles.back().rows.push_back(s.rows[k]);
      const bool top = k > 0 && k + 1 < s.rows.size() && (*e1)[s.rows[k]] > (*e1)[s.rows[k - 1]] &&
                       (*e1)[s.rows[k + 1]] < (*e1)[s.rows[k]];
      if (top) cycles.push_back({fmt::format("cycle {}", cycles.size()), {s.rows[k]}});
    }
  }
  add_panel(fig, f.csv, cycles, axial_strain, fig.title, "q = σ33 − (σ11 + σ22)/2 (kPa)", false,
            {{"q_axial", 1e-3, "q"}}, missing);
  return fig;
}

// The size classes of one phase of classes.csv (physics.md 10.3): each class's share of p and its
// contacts per particle against e1 (or the time), a colour per class.
Figure classes_figure(const Csv& c, const std::string& phase, std::vector<std::string>& missing) {
  Figure fig{"classes_" + tag(phase), "classes.csv (" + phase + "): the load carried by each size class",
             "Each size class's share of the mean stress p (the shares sum to 1) and its mean contacts per particle "
             "(docs/physics.md 10.3), a colour per class of equal-volume radius R.",
             {}};
  std::vector<Segment> classes;
  std::vector<double> radii;
  std::vector<std::size_t> rows;
  const std::vector<double>* radius = c.col("radius_mm");
  for (std::size_t i = 0; i < c.rows && radius; ++i) {
    if (c.phase.empty() || c.phase[i] != phase) continue;
    rows.push_back(i);
    const double r = (*radius)[i];
    const auto at = std::find(radii.begin(), radii.end(), r);
    if (at == radii.end()) radii.push_back(r), classes.push_back({fmt::format("R = {:.4g} mm", r), {}});
    classes[static_cast<std::size_t>(std::find(radii.begin(), radii.end(), r) - radii.begin())].rows.push_back(i);
  }
  if (!radius) missing.push_back("classes.csv: no column radius_mm");
  const XAxis x = classes.empty() ? axial_strain : progress_axis(c, classes.front().rows);
  add_panel(fig, c, classes, x, "share of p", "share of the mean stress p_share", false, {{"p_share", 1, "p"}}, missing);
  add_panel(fig, c, classes, x, "contacts per particle", "contacts per particle", false,
            {{"contacts_per_particle", 1, "contacts"}}, missing);
  if (x.column != "e1") fig.caption += " Against the time: the axial strain turns back in this phase.";
  return fig;
}

// The series files of the run: those summary.json's phases name, in order, with their phases;
// without a summary, series.csv and compaction.csv. A file that is not complete is read from its
// .partial (a run still going or stopped).
std::vector<SeriesFile> series_files(const fs::path& dir, const json& summary, std::vector<std::string>& notes) {
  std::vector<SeriesFile> files;
  const auto entry = [&](const std::string& name) -> SeriesFile& {
    for (SeriesFile& f : files)
      if (f.name == name) return f;
    return files.emplace_back(SeriesFile{name, {}, {}, {}, {}, {}});
  };
  if (summary.contains("phases") && summary["phases"].is_array() && !summary["phases"].empty()) {
    for (const json& p : summary["phases"]) {
      if (!p.contains("file") || !p["file"].is_string()) continue;
      SeriesFile& f = entry(p["file"].get<std::string>());
      const std::string name = p.value("name", stem(f.name));
      f.phases.push_back(name);
      if (p.contains("controller") && p["controller"].contains("cycles")) f.cyclic.push_back(name);
    }
  } else {
    entry("compaction.csv").phases = {"compaction"};
    entry("series.csv").phases = {"triaxial"};
  }
  std::vector<SeriesFile> found;
  for (SeriesFile& f : files) {
    for (const std::string& name : {f.name, f.name + ".partial"})
      if (fs::is_regular_file(dir / name)) {
        f.path = dir / name;
        break;
      }
    if (f.path.empty()) {
      notes.push_back(f.name + ": not in the directory");
      continue;
    }
    if (f.path.extension() == ".partial") notes.push_back(f.name + ": read from " + f.path.filename().string() + " (not finished)");
    f.csv = read_csv(f.path);
    f.segments = phase_segments(f.csv, f.phases.size() == 1 ? f.phases.front() : stem(f.name));
    if (f.csv.rows == 0) notes.push_back(f.name + ": no rows");
    else found.push_back(std::move(f));
  }
  return found;
}

// The figures of one series file, each with what it left out.
std::vector<Figure> file_figures(const SeriesFile& f, std::vector<std::string>& missing) {
  std::vector<Figure> figs;
  figs.push_back(stress_strain_figure(f, missing));
  figs.push_back(stress_path_figure(f, missing));
  figs.push_back(equilibrium_figure(f, missing));
  if (auto fab = fabric_figure(f, missing)) figs.push_back(std::move(*fab));
  for (const std::string& phase : f.cyclic) figs.push_back(loops_figure(f, phase, missing));
  return figs;
}

// A number of summary.json for the page: `digits` significant digits of scale * j[key], a dash
// when there is none.
std::string cell(const json& j, const char* key, double scale = 1, int digits = 4) {
  if (!j.is_object() || !j.contains(key) || !j[key].is_number()) return "—";
  const double v = scale * j[key].get<double>();
  return std::isfinite(v) ? fmt::format("{:.{}g}", v, digits) : "—";
}

std::string html_table(const std::vector<std::string>& head, const std::vector<std::vector<std::string>>& rows) {
  std::string h = "<table>\n<thead><tr>";
  for (const std::string& c : head) h += "<th>" + html_escape(c) + "</th>";
  h += "</tr></thead>\n<tbody>\n";
  for (const auto& r : rows) {
    h += "<tr>";
    for (const std::string& c : r) h += "<td>" + html_escape(c) + "</td>";
    h += "</tr>\n";
  }
  return h + "</tbody></table>\n";
}

// The phases of summary.json (physics.md 10.2), one row each.
std::string phases_table(const json& summary) {
  std::vector<std::vector<std::string>> rows;
  for (const json& p : summary["phases"])
    rows.push_back({p.value("name", ""), p.value("file", ""), cell(p, "rows", 1, 9), cell(p, "steps", 1, 9),
                    cell(p, "peak_phi_deg"), cell(p, "peak_phi_e1", 100), cell(p, "final_e1", 100),
                    cell(p, "final_ev", 100), cell(p, "mean_ufr", 100), cell(p, "mean_iuf", 100),
                    cell(p, "mean_imom", 100), cell(p, "wall_s", 1, 3)});
  return html_table({"phase", "file", "rows", "steps", "peak φ (°)", "at ε1 (%)", "final ε1 (%)", "final εv (%)",
                     "mean UFR (%)", "mean Iuf (%)", "mean IMom (%)", "wall (s)"},
                    rows);
}

// The cycles of a cyclic phase's record (summary.json phases[k].controller.cycles).
std::string cycles_table(const json& summary, const std::string& phase) {
  std::vector<std::vector<std::string>> rows;
  for (const json& p : summary["phases"])
    if (p.value("name", "") == phase && p.contains("controller") && p["controller"].contains("cycles"))
      for (const json& c : p["controller"]["cycles"])
        rows.push_back({cell(c, "cycle"), cell(c, "q_max_Pa", 1e-3), cell(c, "q_min_Pa", 1e-3),
                        cell(c, "secant_modulus_Pa", 1e-6), cell(c, "damping_ratio", 100), cell(c, "e1", 100),
                        cell(c, "ev", 100)});
  if (rows.empty()) return "";
  return "<h3>Cycles of phase " + html_escape(phase) + " (summary.json)</h3>\n" +
         html_table({"cycle", "q max (kPa)", "q min (kPa)", "secant modulus (MPa)", "damping ratio D (%)",
                     "ε1 at its end (%)", "εv at its end (%)"},
                    rows);
}

// What the page says of the run: its case, size, version and files.
std::string run_facts(const fs::path& dir, const json& summary, const std::string& data) {
  std::string h = "<p>Run directory: " + html_escape(fs::absolute(dir).lexically_normal().string()) + ". ";
  if (summary.is_object() && !summary.empty()) {
    if (summary.contains("derived")) h += "Particles: " + cell(summary["derived"], "particles", 1, 9) + ". ";
    h += "Written by qsdem " + html_escape(summary.value("version", "?")) + " in " + cell(summary, "wall_s", 1, 3) +
         " s.";
  } else {
    h += "No summary.json: the run has not finished (or is not a run of qsdem).";
  }
  h += "</p>\n<p>Data: ";
  bool first = true;
  for (const char* f : {"series.csv", "compaction.csv", "classes.csv", "summary.json", "case.toml"})
    if (fs::is_regular_file(dir / f)) {
      h += std::string(first ? "" : ", ") + "<a href=\"" + html_escape(data + f) + "\">" + f + "</a>";
      first = false;
    }
  return h + ".</p>\n";
}

}  // namespace

PlotResult plot_run(const fs::path& dir, const fs::path& out_arg) {
  if (!fs::is_directory(dir))
    throw InputError(fmt::format("'{}' is not a directory: qsdem plot draws the directory of a run (qsdem run --out DIR)",
                                 dir.string()));
  std::vector<std::string> notes;
  json summary = json::object();
  if (const auto text = read_regular_file(dir / "summary.json")) {
    try {
      summary = json::parse(*text);
    } catch (const json::exception&) {
      notes.push_back("summary.json: not valid JSON; its phases are not known");
      summary = json::object();
    }
  }
  std::vector<SeriesFile> files = series_files(dir, summary, notes);
  if (files.empty()) {
    std::string names;
    for (const std::string& n : notes) names += (names.empty() ? "" : "; ") + n;
    throw InputError(fmt::format("'{}' is not a run directory: it holds no series file to draw ({}{}); qsdem plot draws "
                                 "the directory of a run (qsdem run --out DIR)",
                                 dir.string(), names, summary.empty() ? "; no summary.json" : ""));
  }
  if (!gnuplot_available())
    throw std::runtime_error("gnuplot is needed for the figures but could not be run; install the Debian package "
                             "gnuplot-nox (apt-get install gnuplot-nox)");
  const fs::path out = out_arg.empty() ? dir / "plot" : out_arg;
  if (out_arg.empty()) make_directories(dir, "plot");
  else fs::create_directories(out);
  const std::string data = (fs::relative(fs::absolute(dir), fs::absolute(out)) / "").generic_string();

  PlotResult result{out / "index.html", {}, {}};
  const std::string title = "qsdem run " + summary.value("case", dir.filename().string());
  std::string body, contents;
  const auto draw = [&](Figure& f) {
    if (render_figure(out, f, "SPEC 10")) {
      body += figure_html(f, "");
      result.figures.push_back(f.name);
    } else {
      notes.push_back(f.title + ": no data to draw");
    }
  };
  for (SeriesFile& f : files) {
    const std::string id = tag(stem(f.name));
    body += "<h2 id=\"" + id + "\">" + html_escape(label_of(f)) + "</h2>\n";
    contents += "<li><a href=\"#" + id + "\">" + html_escape(label_of(f)) + "</a></li>\n";
    std::vector<std::string> missing;
    for (Figure& fig : file_figures(f, missing)) draw(fig);
    for (const std::string& phase : f.cyclic) body += cycles_table(summary, phase);
    for (const std::string& m : missing) notes.push_back(f.name + ": " + m);
  }
  for (const std::string name : {"classes.csv", "classes.csv.partial"}) {
    if (!fs::is_regular_file(dir / name)) continue;
    const Csv c = read_csv(dir / name);
    std::vector<std::string> phases, missing;
    for (const std::string& p : c.phase)
      if (std::find(phases.begin(), phases.end(), p) == phases.end()) phases.push_back(p);
    if (!phases.empty()) {
      body += "<h2 id=\"classes\">" + name + ": the size classes</h2>\n";
      contents += "<li><a href=\"#classes\">" + name + "</a></li>\n";
    }
    for (const std::string& p : phases) {
      Figure fig = classes_figure(c, p, missing);
      draw(fig);
    }
    for (const std::string& m : missing) notes.push_back(m);
    break;
  }
  std::string h = html_head(title) + "<h1>" + html_escape(title) + "</h1>\n" + run_facts(dir, summary, data);
  if (summary.contains("phases") && summary["phases"].is_array() && !summary["phases"].empty())
    h += "<h2>Phases</h2>\n" + phases_table(summary);
  h += "<ul>\n" + contents + (notes.empty() ? "" : "<li><a href=\"#notes\">not drawn</a></li>\n") + "</ul>\n" + body;
  if (!notes.empty()) {
    h += "<h2 id=\"notes\">Not drawn</h2>\n<ul class=\"note\">\n";
    for (const std::string& n : notes) h += "<li>" + html_escape(n) + "</li>\n";
    h += "</ul>\n";
  }
  h += "<p class=\"note\">Generated by qsdem " QSDEM_VERSION " (qsdem plot); columns: docs/physics.md 10.1, 10.3. "
       "Each figure's data (.dat) and gnuplot script (.gp) are next to it.</p>\n</body>\n</html>\n";
  write_file_atomic(result.page, h);
  result.notes = notes;
  return result;
}

}  // namespace qsdem
