// A study (SPEC 9): samples x damping models x damping ratios x strain rates (x seeds), each sample
// prepared once, runs executed in parallel processes (and over MPI ranks), resumable.
#pragma once
#include <filesystem>

namespace qsdem {

struct StudyOptions {
  std::filesystem::path out;
  bool quiet = false;
};

// Runs (or continues) the study described by `study_file` in options.out, then analyses it.
// Returns the process exit code.
int run_study(const std::filesystem::path& study_file, const StudyOptions& options);

}  // namespace qsdem
