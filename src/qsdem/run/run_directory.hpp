// A run's directory (docs/runs.md): the names of its files, the checks before a run or a resume
// writes into it and its lock, the files its phases write, and its VTK snapshots.
#pragma once
#include <filesystem>
#include <string>
#include <vector>

#include "qsdem/engine/state.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/output.hpp"
#include "qsdem/run/protocol.hpp"

namespace qsdem {

// File names inside a run directory.
inline constexpr const char* checkpoint_file = "checkpoint.qsck";
inline constexpr const char* prepared_sample_file = "sample.qsck";
inline constexpr const char* run_lock_file = ".run.lock";

// Locks `dir` for this process (DIR/.run.lock): a run, resume or prepare, one at a time.
DirectoryLock lock_run_directory(const std::filesystem::path& dir);

// Refuses what --out cannot be, a directory another qsdem works in (unless `locked_here`: this
// process holds its lock), and one whose results a run would overwrite (unless forced) or that
// holds files of something else than a qsdem run. Writes nothing.
void check_out(const std::filesystem::path& dir, bool force, bool locked_here);

// Removes what a run writes into `dir` (its files, those of the protocol's phases, vtk/ and
// plot/): what --force removes.
void clear_run_files(const std::filesystem::path& dir, const Protocol& protocol);

// Refuses to resume `dir` when its files are not those its checkpoint counts (checkpoints of format
// 10 on): its case.toml is not the one the run wrote, or the rows of a file it appends to begin
// otherwise (another run's checkpoint, case.toml or rows copied in).
void check_run_directory(const std::filesystem::path& dir, const RunProgress& run, const Params& params);

// A name in the directory, whatever it is (a link too, which commit_partial refuses to rename).
bool present(const std::filesystem::path& p);

// The files the phases of a protocol write, each with the phases that write to it, in order.
struct PhaseFile {
  std::string name;
  std::vector<int> phases;
};
std::vector<PhaseFile> phase_files(const Protocol& protocol);
const PhaseFile& file_of(const std::vector<PhaseFile>& files, const Protocol& protocol, int phase);

// The sample points classes.csv holds when a run continues (-1: none begun, the file starts
// anew): those of the phases this run has done and of the current one so far.
long classes_rows_held(const RunProgress& run);

// Snapshot k (0: the prepared sample, k: after the k-th row of the phases after the first) and the
// .pvd of all snapshots on disk, whose time is each snapshot's nominal axial strain for the default
// protocol, else its number (so a resumed run rebuilds it from the files).
void write_snapshot(const std::filesystem::path& dir, const Params& params, const State& st, long k);

// The rows of the phases after the first, up to the current one: the number of a snapshot.
long snapshot_rows(const RunProgress& run);

}  // namespace qsdem
