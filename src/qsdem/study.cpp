#include "qsdem/study.hpp"

#include <stdexcept>

namespace qsdem {

int run_study(const std::filesystem::path& study_file, const StudyOptions&) {
  throw std::runtime_error("run_study: not implemented yet (" + study_file.string() + ")");
}

}  // namespace qsdem
