// `qsdem converge` (docs/analysis.md section 11): a case's ladder of rates run as a study, rung by
// rung, until its certificate says converged, the ladder ends or the step budget would be passed.
#include "qsdem/study/converge.hpp"

#include <fmt/format.h>
#include <toml++/toml.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <optional>
#include <sstream>
#include <thread>
#include <vector>

#include "qsdem/default_case.hpp"
#include "qsdem/engine/types.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/files.hpp"
#include "qsdem/run/output.hpp"
#include "qsdem/study/converge_page.hpp"
#include "qsdem/study/study.hpp"

namespace qsdem {
namespace fs = std::filesystem;
namespace {

constexpr const char* sample_name = "case";

Params ladder_case(const LadderOptions& o) {
  return o.case_file.empty() ? parse_case(default_case_toml, default_case_name, o.sets)
                             : load_case(o.case_file.string(), o.sets);
}

void check_options(const LadderOptions& o) {
  const auto bad = [](const char* option, const std::string& value, const char* allowed) {
    throw InputError(fmt::format("{} = {}: {}", option, value, allowed));
  };
  if (o.seeds < 1 || o.seeds > 100) bad("--seeds", std::to_string(o.seeds), "allowed: an integer in [1, 100]");
  if (!(o.factor > 1) || !std::isfinite(o.factor)) bad("--factor", fmt::format("{:g}", o.factor), "allowed: a number > 1");
  if (o.rungs < 2 || o.rungs > 30) bad("--rungs", std::to_string(o.rungs), "allowed: an integer in [2, 30]");
  if (!std::isnan(o.start_rate) && (!(o.start_rate > 0) || !std::isfinite(o.start_rate)))
    bad("--start-rate", fmt::format("{:g}", o.start_rate), "allowed: a number > 0");
  if (!(o.max_steps > 0)) bad("--max-steps", fmt::format("{:g}", o.max_steps), "allowed: a number > 0");
  if (!(o.tolerances.phi_rms_deg > 0) || !std::isfinite(o.tolerances.phi_rms_deg))
    bad("--phi-tolerance", fmt::format("{:g}", o.tolerances.phi_rms_deg), "allowed: degrees > 0");
  if (!(o.tolerances.ev_rms > 0) || !std::isfinite(o.tolerances.ev_rms))
    bad("--ev-tolerance", fmt::format("{:g}", o.tolerances.ev_rms), "allowed: a ratio > 0");
  if (!std::isnan(o.tolerances.ev_end) && (!(o.tolerances.ev_end > 0) || !std::isfinite(o.tolerances.ev_end)))
    bad("--ev-end-tolerance", fmt::format("{:g}", o.tolerances.ev_end), "allowed: a ratio > 0");
}

// The rates of the ladder, fastest first, to 6 significant digits (the run ids' precision).
std::vector<double> ladder_rates(const LadderOptions& o, const Params& p) {
  const double start = std::isnan(o.start_rate) ? fastest_strain_rate(p.protocol.back()) : o.start_rate;
  std::vector<double> rates;
  for (int k = 0; k < o.rungs; ++k) rates.push_back(std::stod(fmt::format("{:.6g}", start / std::pow(o.factor, k))));
  return rates;
}

std::string rung_name(std::size_t k) { return fmt::format("rung-{}", k + 1); }

bool rank_zero() {
  for (const char* v : {"OMPI_COMM_WORLD_RANK", "PMIX_RANK"})
    if (const char* r = std::getenv(v)) return std::string(r) == "0";
  return true;
}

// DIR/analysis/analysis.json, or null.
nlohmann::json analysis_of(const fs::path& out) {
  const std::optional<std::string> text = read_regular_file(out / "analysis" / "analysis.json");
  if (!text) return nullptr;
  nlohmann::json a = nlohmann::json::parse(*text, nullptr, false);
  return a.is_discarded() ? nullptr : a;
}

// The ladder of the case in an analysis, or null.
nlohmann::json ladder_in(const nlohmann::json& a) {
  if (!a.is_object() || !a.contains("convergence")) return nullptr;
  for (const auto& l : a["convergence"])
    if (l.value("sample", "") == sample_name) return l;
  return nullptr;
}

// The ladder figures the analysis drew (PNG names under DIR/analysis/figures/).
std::vector<std::string> ladder_figures(const nlohmann::json& a) {
  std::vector<std::string> figures;
  if (a.is_object() && a.contains("figures"))
    for (const auto& f : a["figures"])
      if (f.value("drawn", false) && f.value("name", "").rfind("ladder_", 0) == 0)
        figures.push_back(f["name"].get<std::string>() + ".png");
  return figures;
}

// Creates DIR with the ladder's study.toml (and the built-in case), or checks that DIR holds this
// very ladder.
void setup(const LadderOptions& o, const std::string& text) {
  const fs::path copy = o.out / "study.toml";
  if (fs::exists(copy)) {
    const std::optional<std::string> held = read_regular_file(copy);
    if (!held || !same_study_values(*held, text))
      throw InputError(fmt::format(
          "'{}' holds another ladder or study: its study.toml differs from the one these options give. Continue it "
          "with the case, --set and options it was started with, or choose another --out",
          o.out.string()));
  } else if (fs::exists(o.out) && !fs::is_empty(o.out)) {
    throw InputError(
        fmt::format("'{}' is not empty and holds no study.toml: choose a new or empty --out directory", o.out.string()));
  }
  if (!rank_zero()) {  // rank 0 writes; the others wait for its study.toml
    for (int k = 0; k < 600 && !fs::exists(copy); ++k) std::this_thread::sleep_for(std::chrono::milliseconds(100));
    return;
  }
  fs::create_directories(o.out);
  if (o.case_file.empty() && !fs::exists(o.out / "case.toml")) write_file_atomic(o.out / "case.toml", default_case_toml);
  if (!fs::exists(copy)) write_file_atomic(copy, text);
}

}  // namespace

std::string ladder_study_text(const LadderOptions& o) {
  check_options(o);
  const Params p = ladder_case(o);
  if (!(fastest_strain_rate(p.protocol.back()) > 0))
    throw InputError(fmt::format("{}: the last phase ('{}') has no strain_rate component: the ladder varies that "
                                 "phase's rate",
                                 p.source, p.protocol.back().name));
  const std::string model = p.protocol.back().damping.model;
  const double xi = model == "none" ? 0.0 : p.protocol.back().damping.ratio;
  toml::table study;
  study.insert("name", "converge");
  toml::array sets;
  for (const auto& s : o.sets) sets.push_back(s);
  toml::table sample{{"name", sample_name},
                     {"case", o.case_file.empty() ? std::string("case.toml") : fs::absolute(o.case_file).string()}};
  if (!sets.empty()) sample.insert("set", sets);
  study.insert("sample", toml::array{sample});
  toml::array seeds;
  for (int s = 1; s <= o.seeds; ++s) seeds.push_back(s);
  study.insert("design", toml::table{{"seeds", seeds}, {"models", toml::array{model}}});
  toml::array stages;
  const std::vector<double> rates = ladder_rates(o, p);
  for (std::size_t k = 0; k < rates.size(); ++k)
    stages.push_back(toml::table{{"name", rung_name(k)},
                                 {"models", toml::array{model}},
                                 {"damping_ratios", toml::array{xi}},
                                 {"strain_rates", toml::array{rates[k]}}});
  study.insert("stage", stages);
  toml::table convergence{{"phi_tolerance_deg", o.tolerances.phi_rms_deg},
                          {"ev_tolerance", o.tolerances.ev_rms},
                          {"within_seed_scatter", o.tolerances.within_seed_scatter}};
  if (std::isfinite(o.tolerances.ev_end)) convergence.insert("ev_end_tolerance", o.tolerances.ev_end);
  study.insert("analysis", toml::table{{"convergence", convergence}});
  std::ostringstream text;
  text << "# The ladder of `qsdem converge` (docs/analysis.md section 11), written by the command.\n" << study << "\n";
  return text.str();
}

int run_ladder(const LadderOptions& o) {
  std::string text;
  Params p;
  try {
    text = ladder_study_text(o);
    p = ladder_case(o);
  } catch (const InputError& e) {
    std::fprintf(stderr, "qsdem: input error: %s\n", e.what());
    return 2;
  }
  const std::vector<double> rates = ladder_rates(o, p);
  const double first_two = o.seeds * (planned_triaxial_steps(p, rates[0]) + planned_triaxial_steps(p, rates[1]));
  if (first_two > o.max_steps) {
    std::fprintf(stderr, "qsdem: input error: --max-steps = %g: the first two rungs alone take %.0f steps (a "
                         "certificate needs two); allowed: at least that\n", o.max_steps, first_two);
    return 2;
  }
  try {
    setup(o, text);
  } catch (const InputError& e) {
    std::fprintf(stderr, "qsdem: input error: %s\n", e.what());
    return 2;
  }

  std::string stopped_by = "not started";
  double next_steps = 0;  // planned steps of the rung the budget left out
  const auto stages_to = [&](std::size_t n) {
    std::vector<std::string> s;
    for (std::size_t k = 0; k < n; ++k) s.push_back(rung_name(k));
    return s;
  };
  const auto next = [&](int round) -> std::optional<std::vector<std::string>> {
    if (round == 0) return stages_to(2);
    const nlohmann::json l = ladder_in(analysis_of(o.out));
    const std::size_t done = l.is_object() ? l["rates"].size() : 0;
    if (!l.is_object() || done < std::size_t(round) + 1) return stopped_by = "failed runs", std::nullopt;
    if (l["status"] == "converged") return stopped_by = "converged", std::nullopt;
    if (done >= rates.size()) return stopped_by = "the last rung", std::nullopt;
    next_steps = o.seeds * planned_triaxial_steps(p, rates[done]);
    if (l["steps"].get<double>() + next_steps > o.max_steps) return stopped_by = "the step budget", std::nullopt;
    return stages_to(done + 1);
  };
  StudyOptions so;
  so.out = o.out;
  so.quiet = o.quiet;
  so.parallel = o.parallel;
  so.again = fmt::format("qsdem converge {}--out {} (with the same options)",
                         o.case_file.empty() ? "" : o.case_file.string() + " ", o.out.string());
  const int code = run_study_rounds(o.out / "study.toml", so, next);
  if (code != 0 || !rank_zero()) return code;

  const nlohmann::json a = analysis_of(o.out);
  const nlohmann::json l = ladder_in(a);
  if (!l.is_object()) {
    std::fprintf(stderr, "qsdem: the analysis of '%s' holds no ladder\n", o.out.string().c_str());
    return 3;
  }
  const bool converged = l["status"] == "converged";
  nlohmann::ordered_json c;
  c["case"] = p.source;
  c["sets"] = o.sets;
  c["status"] = l["status"];
  c["reason"] = converged || stopped_by == "the last rung"
                    ? l["reason"].get<std::string>()
                    : fmt::format("{}; the ladder stopped at {} ({} more steps would pass --max-steps = {:g})",
                                  l["reason"].get<std::string>(), stopped_by, next_steps, o.max_steps);
  c["stopped_by"] = stopped_by;
  c["certified_rate"] = l["certified_rate"];
  c["rates_planned"] = rates;
  c["rates_run"] = l["rates"];
  c["steps"] = l["steps"];
  c["wall_s"] = l["wall_s"];
  c["ladder"] = l;
  c["report"] = "report.html";
  c["page"] = "certificate.html";
  write_file_atomic(o.out / "certificate.json", c.dump(2) + "\n");
  write_file_atomic(o.out / "certificate.html", certificate_html(c, ladder_figures(a)));

  std::string limits;
  for (const auto& s : l["scalars"])
    if ((s["name"] == "peak_phi_deg" || s["name"] == "ev") && s["limit"].is_number())
      limits += fmt::format("\n  {} as eps' -> 0: {:.4g} +- {:.2g}{}", s["name"].get<std::string>(),
                            s["limit"].get<double>(), s["band"].is_number() ? s["band"].get<double>() : NAN,
                            s["extrapolated"].get<bool>() ? " (extrapolated)" : "");
  std::printf("\ncertificate: %s%s\n  %s\n  %zu rungs of %d seeds, %.4g steps, %.4g s of runs%s\nIn %s/ "
              "(certificate.html, certificate.json, report.html, analysis/convergence.csv)\n",
              l["status"].get<std::string>().c_str(),
              converged ? fmt::format(" at eps' = {:g}", l["certified_rate"].get<double>()).c_str() : "",
              c["reason"].get<std::string>().c_str(), l["rates"].size(), o.seeds, l["steps"].get<double>(),
              l["wall_s"].get<double>(), limits.c_str(), o.out.string().c_str());
  return converged ? 0 : 4;
}

}  // namespace qsdem
