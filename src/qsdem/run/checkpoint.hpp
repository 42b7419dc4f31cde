// Checkpoints: the whole State and RunProgress of a run, plus the case, in one binary file
// written atomically (temporary file, fsync, rename; the previous checkpoint is kept as
// `<name>.prev`) with a format version and an FNV-1a 64-bit checksum verified on load.
#pragma once
#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>

#include "qsdem/engine/state.hpp"
#include "qsdem/run/protocol.hpp"

namespace qsdem {

// 2: skip state of apart pairs; 3: the same for runs of spheres only (fluctuation_path); 4: the
// fluctuation_path of runs with ellipsoids too (the skin test's motion bound); 5: the triaxial
// sums field by field with their wall time, the prepare flag and the `resume --set` changes; 6: the
// contact history named by its law's layout; 7: any protocol (phase.hpp): a record per phase, the
// current phase's control values, plan and controller state (formats 1 to 6 are read as the
// default protocol's two phases); 8: a controller's state at its phase's end (summary.json figures);
// 9: the energy ledger (State::energy, and each phase's at its start and last row); 10: the digests
// of the run directory's case.toml and of the rows counted (RunProgress::case_digest, files); 11: the
// particles' inertia scale; 12: the builds that ran the run (RunProgress::builds); 13: the phases'
// records by name (for_each_record_value), so that a new measure or ledger term needs no new format
inline constexpr std::uint32_t checkpoint_format_version = 13;

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
// (missing, not a regular file, truncated, not a checkpoint, other format version, checksum
// mismatch, contents that do not fit together: check_contents in checkpoint.cpp).
Checkpoint load_checkpoint(const std::filesystem::path& path);

// The bytes of a checkpoint file, read as load_checkpoint reads them; `name` is the file's name in
// messages. Seal::ignore skips the checksum and the payload's length in the header (the contents
// are still checked): only the fuzz target (fuzz/) does, to reach the reader behind the checksum.
enum class Seal { verify, ignore };
Checkpoint parse_checkpoint(std::string_view bytes, const std::string& name, Seal seal = Seal::verify);

// Refuses (InputError naming `name`) a checkpoint that does not fit `params`, the case it holds
// (parse_case of its case_text, with any `resume --set`): its number of phases, the kinds of the
// current phase's controls (and their values when no controller changes them), the controllers'
// saved states, the rows of the current phase against its sample points.
void check_checkpoint_case(const Checkpoint& c, const Params& params, const std::string& name);

// The state of a prepared sample `c` (sample.qsck, read from `from`) for a new run of `params`,
// which continues it from its second phase: `run` is set to start there. Refuses (InputError) a
// sample prepared with another material or time step, or not at the end of its first phase.
State prepared_sample(Checkpoint c, const Params& params, const std::string& from, RunProgress& run);

// The newest good checkpoint of `path` or, if that one is damaged, of `path.prev`; `note` says
// which one was used and why. Throws InputError when neither is usable.
Checkpoint load_latest_checkpoint(const std::filesystem::path& path, std::string* note);

}  // namespace qsdem
