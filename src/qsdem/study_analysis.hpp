// Analysis of a study (SPEC 9): optimum damping ratio, power law of the moment index against the
// strain rate, quasi-static rate, tables, figures (gnuplot) and an HTML report.
#pragma once
#include <filesystem>

#include <nlohmann/json.hpp>

namespace qsdem {

// Reads DIR/study.json (the manifest written by `qsdem study`) and every finished run's
// summary.json and series.csv; writes DIR/analysis/ (tables, figures) and DIR/report.html.
// Returns the analysis as JSON (also written to DIR/analysis/analysis.json).
nlohmann::json analyze_study(const std::filesystem::path& dir);

}  // namespace qsdem
