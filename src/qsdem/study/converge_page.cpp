#include "qsdem/study/converge_page.hpp"

#include <fmt/format.h>

#include <cmath>
#include <string>
#include <vector>

#include "qsdem/run/figures.hpp"
#include "qsdem/study/study_analysis_data.hpp"
#include "qsdem/version.hpp"

namespace qsdem {
namespace {

using ojson = nlohmann::ordered_json;
using analysis::sig;

double number(const ojson& v) { return v.is_number() ? v.get<double>() : std::nan(""); }

// A change between two rungs as the certificate judges it (docs/analysis.md 11): beyond the noise
// ± its standard error, and the plain RMS.
std::string change(const ojson& c, double scale) {
  return fmt::format("{} ± {} (RMS {})", sig(scale * number(c["excess"]), 2), sig(scale * number(c["error"]), 2),
                     sig(scale * number(c["rms"]), 2));
}

}  // namespace

std::string certificate_html(const ojson& c, const std::vector<std::string>& figures) {
  const ojson& l = c["ladder"];
  const ojson& tol = l["tolerances"];
  const bool judge_end = tol.contains("ev_end_tolerance") && tol["ev_end_tolerance"].is_number();
  std::string h = html_head("qsdem certificate");
  h += "<h1>Quasi-static certificate</h1>\n";
  h += "<p>Case: <code>" + html_escape(c["case"].get<std::string>()) + "</code>";
  for (const auto& s : c["sets"]) h += ", <code>--set " + html_escape(s.get<std::string>()) + "</code>";
  h += fmt::format(". {} seeds, {} of {} planned rungs run.</p>\n", l["seeds"].size(), c["rates_run"].size(),
                   c["rates_planned"].size());
  const std::string status = c["status"].get<std::string>();
  h += "<h2>" + html_escape(status) +
       (c["certified_rate"].is_number() ? fmt::format(" at ε′ = {}", sig(number(c["certified_rate"]))) : "") +
       "</h2>\n<p>" + html_escape(c["reason"].get<std::string>()) + ".</p>\n";
  h += fmt::format(
      "<p class=\"note\">Tolerances: RMS Δφ ≤ {}°, RMS Δεv ≤ {} %{}, each beyond the noise of the seed mean and with a "
      "standard error as small{}. Seed scatter at the slowest rung: {}° in φ, {} % in εv. The ladder stopped at: {}. "
      "The rules: docs/analysis.md, section 11.</p>\n",
      sig(number(tol["phi_tolerance_deg"])), sig(100 * number(tol["ev_tolerance"])),
      judge_end ? fmt::format(", Δεv at the end ≤ {} %", sig(100 * number(tol["ev_end_tolerance"]))) : std::string(),
      tol["within_seed_scatter"].get<bool>() ? ", and no larger than the seed scatter" : "",
      sig(number(l["phi_scatter_deg"]), 2), sig(100 * number(l["ev_scatter"]), 2),
      html_escape(c["stopped_by"].get<std::string>()));

  // Rungs: the change to the slowest, the scalars, the cost.
  const ojson* peak = nullptr;
  const ojson* ev = nullptr;
  for (const ojson& s : l["scalars"]) {
    if (s["name"] == "peak_phi_deg") peak = &s;
    if (s["name"] == "ev") ev = &s;
  }
  analysis::Table rungs{"The rungs",
                        "Δ: the seed mean of (curve at the rung − curve at the slowest rung) of the same seed, over "
                        "the strain: beyond its noise ± its standard error (the plain RMS in brackets). Peak φ and "
                        "εv: seed mean ± standard error.",
                        {"ε′", "Δφ to the slowest (°)", "Δεv to the slowest (%)", "within", "resolved", "peak φ (°)",
                         "εv at the end (%)", "steps", "run time (s)"},
                        {}};
  if (judge_end) rungs.head.insert(rungs.head.begin() + 3, "Δεv at the end to the slowest (%)");
  for (std::size_t k = 0; k < l["rungs"].size(); ++k) {
    const ojson& r = l["rungs"][k];
    const bool last = k + 1 == l["rungs"].size();
    const auto at = [&](const ojson* s, double scale) {
      return s ? fmt::format("{} ± {}", sig(scale * number((*s)["mean"][k]), 4), sig(scale * number((*s)["error"][k]), 2))
               : std::string("—");
    };
    rungs.rows.push_back({sig(number(r["rate"])), last ? "0 (the slowest)" : change(r["phi_to_slowest"], 1),
                          last ? "0" : change(r["ev_to_slowest"], 100), r["within"].get<bool>() ? "yes" : "no",
                          r.value("resolved", true) ? "yes" : "no", at(peak, 1), at(ev, 100),
                          sig(number(r["steps"]), 4), sig(number(r["wall_s"]), 4)});
    if (judge_end) rungs.rows.back().insert(rungs.rows.back().begin() + 3, last ? "0" : change(r["ev_end_to_slowest"], 100));
  }
  h += analysis::to_html(rungs);

  analysis::Table limits{"The response as ε′ → 0",
                         fmt::format("Limit resolved by the seeds: {}. Cost of the certificate: {} steps, {} s of runs.",
                                     l["limit_resolved"].get<bool>() ? "yes" : "no", sig(number(c["steps"]), 4),
                                     sig(number(c["wall_s"]), 4)),
                         {"measure", "limit", "band", "how"},
                         {}};
  for (const ojson& s : l["scalars"])
    limits.rows.push_back({s["name"].get<std::string>(), sig(number(s["limit"]), 4), sig(number(s["band"]), 2),
                           s["extrapolated"].get<bool>() ? "Aitken's extrapolation of the last three rungs"
                                                         : "the slowest rung"});
  h += analysis::to_html(limits);

  for (const std::string& f : figures)
    h += "<figure><img src=\"analysis/figures/" + html_escape(f) + "\" alt=\"" + html_escape(f) +
         "\"><figcaption>The response curves at each rate (analysis/figures/" + html_escape(f) +
         ").</figcaption></figure>\n";
  h += "<p>Files: <a href=\"certificate.json\">certificate.json</a>, <a href=\"report.html\">the study's report</a>, "
       "<a href=\"analysis/convergence.csv\">analysis/convergence.csv</a>.</p>\n";
  h += "<p class=\"note\">Generated by qsdem " QSDEM_VERSION " (qsdem converge).</p>\n</body>\n</html>\n";
  return h;
}

}  // namespace qsdem
