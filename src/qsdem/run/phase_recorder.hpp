// A phase's recorder: writes its rows (its file, classes.csv), keeps the per-row statistics of its
// record (SPEC 8.4), tells its progress, and records its end.
#pragma once
#include <optional>
#include <string>
#include <vector>

#include "qsdem/engine/measures.hpp"
#include "qsdem/engine/state.hpp"
#include "qsdem/run/output.hpp"
#include "qsdem/run/phase.hpp"
#include "qsdem/run/progress.hpp"
#include "qsdem/run/run_progress.hpp"

namespace qsdem {

// Where a phase's rows go: the writer of its file (none: rows are counted, not written), the
// phase whose starting cell the file's strains are measured from, and the file's optional columns
// (those asked for by any phase writing to it: holds_volume, shears, a rate controller).
struct RowSink {
  SeriesWriter* writer = nullptr;
  int reference_phase = 0;
  SeriesColumns columns;
  // classes.csv (docs/physics.md 10.3) and the sample's size classes (size_classes), when it is written.
  SeriesWriter* classes = nullptr;
  const std::vector<double>* size_classes = nullptr;
};

// Where a row is in its phase: its force evaluation n, the phase's step, the mean stress p0 at the
// phase's start and the axial strain e1 of the file's reference.
struct RowPlace {
  long n;
  double dt, p0, e1;
};

// Writes the row of the state's last force evaluation to the phase's file (and classes.csv) and
// adds it to the phase's record (SPEC 8.4).
void record_row(const Phase& phase, State& st, RunProgress& run, const RowSink& sink, const Measures& m,
                const RowPlace& at, std::optional<double> strain_rate, std::optional<Relaxation> relaxation);

// The phase's end in the run's records (its controller's last saved state) and its closing line.
void end_phase(RunProgress& run, const Phase& phase, Progress& progress);

// The progress line at a measured step of a phase that ends in equilibrium (`steps`: taken so far;
// `error`: the stress error), of a loading phase (`strain_rate`: the eps' of a rate-controlled
// component), and after an increment of a FIRE phase.
std::string equilibrium_line(long steps, const Measures& m, double error);
std::string loading_line(const Measures& m, double e1, std::optional<double> strain_rate);
std::string increment_line(const Measures& m, double e1, long iterations, bool relaxed);

}  // namespace qsdem
