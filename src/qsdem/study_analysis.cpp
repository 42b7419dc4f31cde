#include "qsdem/study_analysis.hpp"

#include <stdexcept>

namespace qsdem {

nlohmann::json analyze_study(const std::filesystem::path& dir) {
  throw std::runtime_error("analyze_study: not implemented yet (" + dir.string() + ")");
}

}  // namespace qsdem
