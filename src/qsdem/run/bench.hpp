// `qsdem bench` (docs/benchmarks.md): the stepping of a packing or of a run's state, timed.
#pragma once
#include <filesystem>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

namespace qsdem {

// `qsdem bench`: steps a state `steps` times in a fixed cell, with no output, and returns the
// machine-readable speed record (docs/benchmarks.md). `source` is
//   - a packing file (docs/packing-format.md): particles at rest, no contact history, stepped with
//     the triaxial friction and damping of the case `case_path` (required);
//   - a checkpoint file (*.qsck) or a run directory holding one (DIR/sample.qsck of `qsdem
//     prepare`, else DIR/checkpoint.qsck): the state a run steps, with its velocities and contact
//     history, stepped with the friction and damping of the phase it is in. The case is the
//     checkpoint's own, or `case_path` when given (its material and time.step_ratio must equal it).
// `overrides` are --set strings applied to the case. With `as_spheres`, every ellipsoid is first
// replaced by its equal-volume sphere at the same centre, at rest and without contact history.
// `prefetch_j_ends` sets Model::prefetch_j_ends (unset: the engine's choice).
nlohmann::json bench_packing(const std::filesystem::path& source, const std::string& case_path,
                             const std::vector<std::string>& overrides, long steps, bool as_spheres = false,
                             std::optional<bool> prefetch_j_ends = std::nullopt);

}  // namespace qsdem
