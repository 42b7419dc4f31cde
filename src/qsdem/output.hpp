// Result files (SPEC 10). Files appear complete or not at all: each is written to a temporary
// name and renamed into place.
#pragma once
#include <array>
#include <cstdio>
#include <filesystem>
#include <optional>
#include <string>

#include "qsdem/measures.hpp"

namespace qsdem {

// One row of series.csv / compaction.csv: the step and time of the row's clock and the strains
// of its file's reference are given by the caller (they depend on the phase).
struct SeriesRow {
  long step = 0;
  double time = 0;
  double e1 = 0, ev = 0;
  const Measures& m;
  const std::string* phase = nullptr;  // the phase's name, when the file has a phase column
  const double* dp = nullptr;  // p - p0 of the row's phase, when the file has a dp_Pa column
  // The shear strains gamma_12, gamma_13, gamma_23 of the file's reference, when the file has the
  // shear columns (s12_Pa, s13_Pa, s23_Pa, g12, g13, g23).
  const std::array<double, 3>* shear_strain = nullptr;
  // The file has a strain_rate column (a phase writing to it has a rate controller); the row's
  // eps' there, or none (an empty field) for a phase without one.
  bool rate_column = false;
  std::optional<double> strain_rate;
};

// The header: SPEC 10's columns, then those added after them, then the shear columns, `dp_Pa`,
// `strain_rate` and `phase` when asked for.
std::string series_header(bool phase_column, bool dp_column = false, bool shear_columns = false,
                          bool rate_column = false);
std::string series_row(const SeriesRow& row);

// Writes to `path.partial`, flushed after every row; commit() renames it to `path`.
// With keep_rows >= 0 it continues an existing `path.partial` after its first keep_rows rows
// (a resumed run: rows written after the checkpoint are dropped and written again).
class SeriesWriter {
 public:
  explicit SeriesWriter(std::filesystem::path path, long keep_rows = -1, bool phase_column = false,
                        bool dp_column = false, bool shear_columns = false, bool rate_column = false);
  ~SeriesWriter();
  SeriesWriter(const SeriesWriter&) = delete;
  SeriesWriter& operator=(const SeriesWriter&) = delete;
  void write(const std::string& row);
  void sync();    // the rows written so far are on disk (fsync): before each checkpoint
  void commit();  // sync, close and rename to `path`

 private:
  std::filesystem::path path_, partial_;
  std::FILE* file_ = nullptr;
};

// Renames `path.partial`, complete and synced, to `path` (a phase that ended before a crash).
void commit_partial(const std::filesystem::path& path);

// Writes text to path atomically (temporary file, fsync, rename).
void write_file_atomic(const std::filesystem::path& path, const std::string& text);

// An exclusive lock (flock) on the file DIR/name, held while the object lives and released by the
// system when the process ends, however it ends. Throws InputError(`held_message`) when another
// process holds it.
class DirectoryLock {
 public:
  DirectoryLock(const std::filesystem::path& dir, const char* name, const std::string& held_message);
  ~DirectoryLock();
  DirectoryLock(const DirectoryLock&) = delete;
  DirectoryLock& operator=(const DirectoryLock&) = delete;

 private:
  int fd_ = -1;
};

}  // namespace qsdem
