// Result files (SPEC 10). Files appear complete or not at all: each is written to a temporary
// name and renamed into place.
#pragma once
#include <array>
#include <cstdio>
#include <filesystem>
#include <optional>
#include <string>
#include <nlohmann/json.hpp>
#include <vector>

#include "qsdem/measures.hpp"

namespace qsdem {

// One row of series.csv / compaction.csv: the step and time of the row's clock and the strains
// of its file's reference are given by the caller (they depend on the phase).
struct SeriesRow {
  long step = 0;
  double time = 0;
  double e1 = 0, ev = 0;
  const Measures& m;
  const std::string* phase = nullptr;  // the phase's name (phase)
  double dp = 0;        // p - p0 of the row's phase (dp_Pa)
  // The shear strains gamma_12, gamma_13, gamma_23 of the file's reference (g12, g13, g23).
  std::array<double, 3> shear_strain{};
  // The eps' of the row's phase, none (an empty field) for a phase without a rate controller.
  std::optional<double> strain_rate;
  EnergyLedger energy{};  // the run's energy (energy columns)
};

// The columns a series file has after SPEC 10's and `phi_al_deg,tilt_deg`, in this order; a file
// has one when a phase writing to it asks for it.
struct SeriesColumns {
  bool shear = false;        // s12_Pa,s13_Pa,s23_Pa,g12,g13,g23: a phase with a shear strain rate
  bool dp = false;           // dp_Pa: a phase that holds the volume
  bool strain_rate = false;  // strain_rate: a phase with a rate controller
  bool phase = false;        // phase: several phases write to the file
  bool energy = false;       // work_J,friction_J,contact_damping_J,damping_J,stiffness_change_J,elastic_J
};

std::string series_header(const SeriesColumns& columns = {});
std::string series_row(const SeriesRow& row, const SeriesColumns& columns = {});

// classes.csv (docs/physics.md 10.3): one row per size class at each sample point of every phase; the step,
// time and strains as in the row of the phase's own file.
std::string classes_header();
std::string classes_rows(const SeriesRow& row, const std::vector<ClassMeasures>& classes);

// The energy of a stretch of a run from the ledgers at its ends (docs/physics.md 12), as summary.json
// gives it for a phase and a cycle: the cell's work, each dissipation, the law's stiffness change,
// the changes of the stored and kinetic energies, and what the balance work + stiffness change =
// dissipated + stored + kinetic misses.
nlohmann::json energy_change(const EnergyLedger& start, const EnergyLedger& end);

// The header line of a file that is not series.csv's (SeriesWriter's second constructor).
struct CsvHeader {
  std::string text;
};

// Writes to `path.partial`, flushed after every row; commit() renames it to `path`.
// With keep_rows >= 0 it continues an existing `path.partial` after its first keep_rows rows
// (a resumed run: rows written after the checkpoint are dropped and written again).
class SeriesWriter {
 public:
  explicit SeriesWriter(std::filesystem::path path, long keep_rows = -1, const SeriesColumns& columns = {});
  SeriesWriter(std::filesystem::path path, long keep_rows, const CsvHeader& header);
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
