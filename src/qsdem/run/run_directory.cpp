#include "qsdem/run/run_directory.hpp"

#include <fmt/format.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <utility>

#include "qsdem/run/files.hpp"
#include "qsdem/run/vtk.hpp"

namespace qsdem {

namespace fs = std::filesystem;

namespace {

// The files a run writes into its directory (besides vtk/, plot/ and its phases' files): what --force
// removes.
constexpr const char* run_files[] = {"summary.json",      "series.csv",      "series.csv.partial",
                                     classes_file,        "classes.csv.partial",
                                     "compaction.csv",    "compaction.csv.partial", "compacted.packing",
                                     "final.packing",     checkpoint_file,   "checkpoint.qsck.prev",
                                     prepared_sample_file, "case.toml"};

// What `dir` holds, for the checks before a run writes into it.
enum class DirKind { absent, empty, run_finished, run_unfinished, run_started, foreign };

DirKind classify(const fs::path& dir) {
  std::error_code ec;
  if (!fs::exists(dir, ec)) return DirKind::absent;
  if (fs::exists(dir / "summary.json") && !fs::exists(dir / checkpoint_file)) return DirKind::run_finished;
  if (fs::exists(dir / checkpoint_file) || fs::exists(dir / "checkpoint.qsck.prev")) return DirKind::run_unfinished;
  if (fs::exists(dir / "case.toml")) return DirKind::run_started;  // a run stopped before its first checkpoint
  for (const auto& e : fs::directory_iterator(dir, ec))
    if (e.path().filename() != run_lock_file) return DirKind::foreign;
  return DirKind::empty;
}

}  // namespace

DirectoryLock lock_run_directory(const fs::path& dir) {
  return DirectoryLock(dir, run_lock_file,
                       fmt::format("another qsdem (run, resume or prepare) is working in '{}' (it holds {}): wait "
                                   "for it, stop it, or choose another --out",
                                   dir.string(), (dir / run_lock_file).string()));
}

void check_out(const fs::path& dir, bool force, bool locked_here) {
  if (dir.empty()) throw InputError("--out is empty: give the directory for the results");
  for (const auto& part : fs::absolute(dir))
    if (part.string().size() > 255)
      throw InputError(fmt::format("--out '{}': the name '{}' is longer than 255 bytes", dir.string(), part.string()));
  std::error_code ec;
  if (fs::exists(dir, ec) && !fs::is_directory(dir, ec))
    throw InputError(fmt::format("--out '{}' is a file, not a directory", dir.string()));
  // The nearest existing ancestor must be a directory we may write into.
  fs::path up = fs::absolute(dir).parent_path();
  while (!up.empty() && !fs::exists(up, ec) && up != up.root_path()) up = up.parent_path();
  if (!fs::exists(dir, ec)) {
    if (!fs::is_directory(up, ec))
      throw InputError(fmt::format("cannot create --out '{}': '{}' is not a directory", dir.string(), up.string()));
    if (::access(up.c_str(), W_OK | X_OK) != 0)
      throw InputError(fmt::format("cannot create --out '{}' in '{}': {}", dir.string(), up.string(),
                                   std::strerror(errno)));
  } else if (::access(dir.c_str(), W_OK | X_OK) != 0) {
    throw InputError(fmt::format("cannot write into --out '{}': {}", dir.string(), std::strerror(errno)));
  }
  if (!locked_here && fs::exists(dir / run_lock_file, ec)) {
    const DirectoryLock probe = lock_run_directory(dir);  // refused now if another qsdem holds it
  }
  switch (classify(dir)) {
    case DirKind::run_finished:
      if (!force)
        throw InputError(fmt::format(
            "'{}' holds a finished run (summary.json): choose another --out or add --force", dir.string()));
      break;
    case DirKind::run_unfinished:
      if (!force)
        throw InputError(fmt::format(
            "'{}' holds an unfinished run: continue it with `qsdem resume {}`, or add --force to start over",
            dir.string(), dir.string()));
      break;
    case DirKind::foreign:
      if (!force)
        throw InputError(fmt::format(
            "'{}' is not empty and holds no qsdem run (no case.toml): choose a new or empty --out, or add --force "
            "(which removes only the files a run writes: {})",
            dir.string(), "summary.json, series.csv, compaction.csv, classes.csv, *.packing, *.qsck, case.toml, vtk/, plot/"));
      break;
    default: break;
  }
}

void clear_run_files(const fs::path& dir, const Protocol& protocol) {
  for (const char* f : run_files) fs::remove(dir / f);
  for (const Phase& phase : protocol) {
    fs::remove(dir / phase.output.file);
    fs::remove(dir / (phase.output.file + ".partial"));
  }
  fs::remove_all(dir / "vtk");
  fs::remove_all(dir / "plot");  // the page of the run replaced (`qsdem plot`)
}

void check_run_directory(const fs::path& dir, const RunProgress& run, const Params& params) {
  const std::string checkpoint = (dir / checkpoint_file).string();
  const auto refuse = [&](const std::string& what) {
    throw InputError(fmt::format("cannot resume '{}': {}. Its checkpoint ({}) and its files are of different runs "
                                 "(copied in, or edited): put back the run's own files, or start it anew (`qsdem "
                                 "run CASE --out {} --force`)",
                                 dir.string(), what, checkpoint, dir.string()));
  };
  const auto hash = [](const std::string& bytes) { return fnv1a64(bytes.data(), bytes.size()); };
  if (run.case_digest) {
    const fs::path file = dir / "case.toml";
    if (!fs::exists(file)) refuse(fmt::format("it holds no case.toml, which the checkpoint's run wrote"));
    if (hash(read_regular_file(file, UINT64_MAX)) != *run.case_digest)
      refuse(fmt::format("'{}' is not the case.toml of the run that wrote the checkpoint", file.string()));
  }
  for (const FileDigest& f : run.files) {
    const bool known = f.name == classes_file || std::any_of(params.protocol.begin(), params.protocol.end(),
                                                              [&](const Phase& p) { return p.output.file == f.name; });
    if (!known) refuse(fmt::format("the checkpoint counts rows of '{}', a file no phase of its case writes", f.name));
    // The file is still being written, or renamed at its end (a crash after the rename).
    fs::path file = dir / (f.name + ".partial");
    if (!fs::exists(file)) file = dir / f.name;
    if (!fs::exists(file)) refuse(fmt::format("the checkpoint counts {} bytes of rows of {}, which it does not hold", f.bytes, f.name));
    const std::string bytes = read_regular_file(file, f.bytes);
    if (bytes.size() < f.bytes || hash(bytes) != f.hash)
      refuse(fmt::format("the first {} bytes of '{}' are not the rows the checkpoint counts", f.bytes, file.string()));
  }
}

bool present(const fs::path& p) {
  std::error_code ec;
  return fs::symlink_status(p, ec).type() != fs::file_type::not_found && !ec;
}

std::vector<PhaseFile> phase_files(const Protocol& protocol) {
  std::vector<PhaseFile> files;
  for (std::size_t p = 0; p < protocol.size(); ++p) {
    const std::string& name = protocol[p].output.file;
    auto f = std::find_if(files.begin(), files.end(), [&](const PhaseFile& x) { return x.name == name; });
    if (f == files.end()) f = files.insert(files.end(), {name, {}});
    f->phases.push_back(static_cast<int>(p));
  }
  return files;
}

const PhaseFile& file_of(const std::vector<PhaseFile>& files, const Protocol& protocol, int phase) {
  const std::string& name = protocol[static_cast<std::size_t>(phase)].output.file;
  return *std::find_if(files.begin(), files.end(), [&](const PhaseFile& f) { return f.name == name; });
}

long classes_rows_held(const RunProgress& run) {
  const int first = run.first_step == 0 ? 0 : 1;
  const int p = run.phase;
  if (!(p > first || run.phase_started)) return -1;
  long held = run.phase_started && p < static_cast<int>(run.phases.size()) ? run.phases[static_cast<std::size_t>(p)].rows : 0;
  for (int q = first; q < p; ++q) held += run.phases[static_cast<std::size_t>(q)].rows;
  return held;
}

void write_snapshot(const std::filesystem::path& dir, const Params& params, const State& st, long k) {
  namespace fs = std::filesystem;
  const fs::path vtk = dir / "vtk";
  make_directories(dir, "vtk");
  write_vtu(vtk / fmt::format("snapshot-{:04}.vtu", k), st);
  std::vector<std::pair<long, fs::path>> files;
  for (const auto& e : fs::directory_iterator(vtk)) {
    const std::string name = e.path().filename().string();
    if (name.size() == 17 && name.rfind("snapshot-", 0) == 0 && e.path().extension() == ".vtu")
      files.emplace_back(std::stol(name.substr(9, 4)), e.path().filename());
  }
  std::sort(files.begin(), files.end());
  std::vector<PvdEntry> entries;
  // [triaxial]'s rows by axial strain: sample_points over final_axial_strain (rate_control: every_strain).
  const Phase& test = params.protocol.back();
  const Cadence& cadence = test.output.cadence;
  const double per_row = params.phase_list                          ? 1.0
                         : cadence.kind == Cadence::Kind::every_strain ? cadence.every_strain
                                                                       : *test.stop.strain[2] / static_cast<double>(cadence.points);
  for (const auto& [row, file] : files) entries.push_back({static_cast<double>(row) * per_row, file});
  write_pvd(vtk / "series.pvd", entries);
}

long snapshot_rows(const RunProgress& run) {
  long k = 0;
  for (std::size_t p = 1; p < run.phases.size() && p <= static_cast<std::size_t>(run.phase); ++p) k += run.phases[p].rows;
  return k;
}

}  // namespace qsdem
