// A study (SPEC 9): samples x damping models x damping ratios x strain rates (x seeds), each sample
// prepared once, runs executed in parallel processes (and over MPI ranks), resumable. The study
// file and the layout of the study directory are documented in docs/study.md.
#pragma once
#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

namespace qsdem {

// One prepared sample: a case (with its overrides) and a seed, compacted once by `qsdem prepare`.
struct StudySample {
  std::string name;                   // the [[sample]] name
  std::uint64_t seed = 1;             // sample.seed it is prepared with
  std::string dir;                    // relative to the study directory: samples/<name>-seed<S>
  std::filesystem::path case_file;    // absolute
  std::string case_hash;              // FNV-1a 64 of the case file's bytes, 16 hex digits
  std::vector<std::string> sets;      // --set overrides of `qsdem prepare` (seed first)
  std::vector<std::string> run_sets;  // the sample's own overrides, also given to its runs
};

// One triaxial test of a prepared sample.
struct StudyRun {
  std::string id;  // <sample>-seed<S>/<model>/xi-<xi %>/rate-<rate>, also its directory under runs/
  std::size_t sample = 0;  // index into Study::samples
  std::string model;       // none | od | nd
  double xi = 0;           // damping ratio, as a fraction
  double rate = 0;         // dimensionless strain rate eps'
  std::string dir;         // relative to the study directory: runs/<id>
  std::vector<std::string> sets;  // --set overrides of `qsdem run`, except sample.from
  double expected_steps = 0;      // triaxial steps, final_axial_strain / (c_t eps') (for the ETA)
};

struct Study {
  std::string name;
  std::filesystem::path file;  // the study file as given
  std::string text;            // its contents (copied to DIR/study.toml)
  std::vector<StudySample> samples;
  std::vector<StudyRun> runs;
  int parallel_runs = 1;    // processes at once (per MPI rank)
  int threads_per_run = 1;  // --threads of every child
};

// Reads and checks a study file, and every case it names with every override of every run.
// Throws InputError naming the file, line, key, value and what is allowed.
Study load_study(const std::filesystem::path& file);

// The manifest DIR/study.json (the contract with the analysis, docs/study.md); keys in the
// documented order.
nlohmann::ordered_json study_manifest(const Study& study);

struct StudyOptions {
  std::filesystem::path out;
  bool quiet = false;
  int parallel = 0;  // > 0: overrides execution.parallel_runs
};

// Runs (or continues) the study described by `study_file` in options.out, then analyses it.
// Returns the process exit code: 0, 2 (bad input), 3 (failed runs or analysis), 128 + signal.
int run_study(const std::filesystem::path& study_file, const StudyOptions& options);

}  // namespace qsdem
