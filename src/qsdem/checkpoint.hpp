// Checkpoints: the whole State and RunProgress of a run, plus the case, in one binary file
// written atomically (temporary file, fsync, rename; the previous checkpoint is kept as
// `<name>.prev`) with a format version and an FNV-1a 64-bit checksum verified on load.
#pragma once
#include <cstdint>
#include <filesystem>
#include <string>

#include "qsdem/protocol.hpp"
#include "qsdem/state.hpp"

namespace qsdem {

// 2: skip state of apart pairs; 3: the same for runs of spheres only (fluctuation_path); 4: the
// fluctuation_path of runs with ellipsoids too (the skin test's motion bound); 5: the triaxial
// sums field by field with their wall time, the prepare flag and the `resume --set` changes; 6: the
// contact history named by its law's layout; 7: any protocol (phase.hpp): a record per phase, the
// current phase's control values, plan and controller state (formats 1 to 6 are read as the
// default protocol's two phases); 8: a controller's state at its phase's end (summary.json figures);
// 9: the energy ledger (State::energy, and each phase's at its start and last row)
inline constexpr std::uint32_t checkpoint_format_version = 9;

struct Checkpoint {
  std::string case_text;    // the case as TOML, after --set overrides
  std::string case_source;  // where it came from (file name)
  RunProgress run;
  State state;
};

// `format`: an older format version can be written for tests of the reader (a run writes the
// current one).
void save_checkpoint(const std::filesystem::path& path, const std::string& case_text, const std::string& case_source,
                     const State& state, const RunProgress& run,
                     std::uint32_t format = checkpoint_format_version);

// Reads and verifies one checkpoint file; throws InputError saying what is wrong with it
// (missing, truncated, not a checkpoint, other format version, checksum mismatch).
Checkpoint load_checkpoint(const std::filesystem::path& path);

// The newest good checkpoint of `path` or, if that one is damaged, of `path.prev`; `note` says
// which one was used and why. Throws InputError when neither is usable.
Checkpoint load_latest_checkpoint(const std::filesystem::path& path, std::string* note);

std::uint64_t fnv1a64(const void* data, std::size_t size);

}  // namespace qsdem
