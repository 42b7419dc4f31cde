// Result files (SPEC 10). Files appear complete or not at all: each is written to a temporary
// name and renamed into place.
#pragma once
#include <array>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <optional>
#include <string>
#include <nlohmann/json.hpp>
#include <vector>

#include "qsdem/engine/measures.hpp"

namespace qsdem {

// One row of series.csv / compaction.csv: the step and time of the row's clock and the strains
// of its file's reference are given by the caller (they depend on the phase).
// A FIRE increment's relaxation (docs/physics.md 5.7): its force evaluations, and whether it
// reached the solver's tolerances within max_iterations.
struct Relaxation {
  long iterations = 0;
  bool converged = false;
};

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
  std::optional<Relaxation> relaxation{};  // a FIRE phase's row (iterations, relaxed)
};

// The columns a series file has after SPEC 10's and `phi_al_deg,tilt_deg`, in this order; a file
// has one when a phase writing to it asks for it.
struct SeriesColumns {
  bool shear = false;        // s12_Pa,s13_Pa,s23_Pa,g12,g13,g23: a phase with a shear strain rate
  bool dp = false;           // dp_Pa: a phase that holds the volume
  bool strain_rate = false;  // strain_rate: a phase with a rate controller
  bool phase = false;        // phase: several phases write to the file
  bool relaxation = false;   // iterations,relaxed: a phase with solver = "fire"
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

// FNV-1a, 64 bits, over `size` bytes, continued from the hash `h` of the bytes before: the
// checkpoints' checksum and the digests of the files a run appends to.
inline constexpr std::uint64_t fnv1a64_basis = 14695981039346656037ull;
std::uint64_t fnv1a64(const void* data, std::size_t size, std::uint64_t h = fnv1a64_basis);

// The first `bytes` bytes of a file in the run directory, by their hash: what a checkpoint counts of
// a file the run appends rows to (its header and the rows so far).
struct FileDigest {
  std::string name;
  std::uint64_t bytes = 0;
  std::uint64_t hash = fnv1a64_basis;
};

// The first `max_bytes` bytes (all, when it is shorter) of the regular file `path`; `size`: its
// size. Anything else (a FIFO, a device, a directory) is refused, never waited for or read without
// end: InputError naming the file, as when it cannot be opened.
std::string read_regular_file(const std::filesystem::path& path, std::uint64_t max_bytes,
                              std::uint64_t* size = nullptr);

// The fields of a CSV line the engine wrote (no quoting: no field holds a comma), empty ones kept.
std::vector<std::string> split_fields(const std::string& line);

// The header line of a file that is not series.csv's (SeriesWriter's second constructor).
struct CsvHeader {
  std::string text;
};

// Writes to `path.partial`, flushed after every row; commit() renames it to `path`.
// With keep_rows >= 0 it continues an existing `path.partial` after its first keep_rows rows
// (a resumed run: rows written after the checkpoint are dropped and written again). A file begun
// by another engine version, whose header is not this one's, keeps its columns: each row is
// written with those only (omitted() names the others); a column this engine does not write is
// refused (InputError).
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
  // Everything written to the file so far, header included (what a checkpoint counts of it).
  const FileDigest& digest() const { return digest_; }
  // The columns of this engine's header that a file begun with other columns does not get ("" when
  // it has them all, in this order).
  const std::string& omitted() const { return omitted_; }

 private:
  void put(const std::string& text);  // writes, flushes and adds to the digest
  void keep_columns(const std::string& file_header, const std::string& header);
  std::filesystem::path path_, partial_;
  std::FILE* file_ = nullptr;
  FileDigest digest_;
  std::vector<std::size_t> projection_;  // the file's columns, by index in this engine's rows (empty: all)
  std::string omitted_;
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
