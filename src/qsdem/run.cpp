#include "qsdem/run.hpp"

#include "qsdem/controller.hpp"

#include <fmt/format.h>
#include <omp.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <optional>
#include <sstream>

#include "qsdem/checkpoint.hpp"
#include "qsdem/files.hpp"
#include "qsdem/generate.hpp"
#include "qsdem/grading.hpp"
#include "qsdem/measures.hpp"
#include "qsdem/neighbor.hpp"
#include "qsdem/output.hpp"
#include "qsdem/packing_io.hpp"
#include "qsdem/protocol.hpp"
#include "qsdem/step.hpp"
#include "qsdem/stop_signals.hpp"
#include "qsdem/version.hpp"
#include "qsdem/vtk.hpp"

namespace qsdem {
namespace {

nlohmann::json stage_json(const StageTimers& t, long steps) {
  nlohmann::json j = nlohmann::json::object();
  for (std::size_t k = 0; k < t.seconds.size(); ++k)
    j[stage_names[k]] = {{"seconds", t.seconds[k]},
                         {"us_per_step", steps > 0 ? 1e6 * t.seconds[k] / static_cast<double>(steps) : 0.0}};
  return j;
}

// Peak resident set of this process (KiB): VmHWM of /proc/self/status, which starts afresh at
// exec. getrusage's ru_maxrss does not: Linux carries the larger peak of the process image before
// exec over, so when launched by a bigger parent it reported the parent's. getrusage only where /proc is not readable.
long peak_rss_kib() {
  if (std::FILE* f = std::fopen("/proc/self/status", "r")) {
    char line[256];
    long kib = -1;
    while (std::fgets(line, sizeof line, f))
      if (std::sscanf(line, "VmHWM: %ld kB", &kib) == 1) break;
    std::fclose(f);
    if (kib >= 0) return kib;
  }
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return u.ru_maxrss;
}

nlohmann::json measures_json(const Measures& m) {
  return {{"p_Pa", m.mean_stress},  {"q_Pa", m.deviator},       {"s11_Pa", m.stress(0, 0)},
          {"s22_Pa", m.stress(1, 1)}, {"s33_Pa", m.stress(2, 2)}, {"void_ratio", m.void_ratio},
          {"ufr", m.ufr},           {"iuf", m.iuf},             {"imom", m.imom},
          {"cn", m.coordination},   {"contacts", m.contacts},  {"ekin_J", m.ekin_trans + m.ekin_rot}};
}

nlohmann::json size_table_json(const Params& params) {
  nlohmann::json counts = nlohmann::json::array();
  const auto table = resolve_table(params.sample);
  double solid = 0;
  for (const auto& c : table) solid += static_cast<double>(c.count) * ellipsoid_volume(c.semi_axes);
  for (const auto& c : table)
    counts.push_back({{"shape", to_string(c.shape)},
                      {"semi_axes_m", {c.semi_axes.x(), c.semi_axes.y(), c.semi_axes.z()}},
                      {"count", c.count},
                      {"mass_fraction", static_cast<double>(c.count) * ellipsoid_volume(c.semi_axes) / solid}});
  return counts;
}

namespace fs = std::filesystem;

// The files a run writes into its directory (besides vtk/, plot/ and its phases' files): what --force
// removes.
constexpr const char* run_files[] = {"summary.json",      "series.csv",      "series.csv.partial",
                                     classes_file,        "classes.csv.partial",
                                     "compaction.csv",    "compaction.csv.partial", "compacted.packing",
                                     "final.packing",     checkpoint_file,   "checkpoint.qsck.prev",
                                     prepared_sample_file, "case.toml"};

// The files the phases of a protocol write, each with the phases that write to it, in order.
struct PhaseFile {
  std::string name;
  std::vector<int> phases;
};

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

// A name in the directory, whatever it is (a link too, which commit_partial refuses to rename).
bool present(const fs::path& p) {
  std::error_code ec;
  return fs::symlink_status(p, ec).type() != fs::file_type::not_found && !ec;
}

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

// The sample points classes.csv holds when a run continues (-1: none begun, the file starts
// anew): those of the phases this run has done and of the current one so far.
long classes_rows_held(const RunProgress& run) {
  const int first = run.first_step == 0 ? 0 : 1;
  const int p = run.phase;
  if (!(p > first || run.phase_started)) return -1;
  long held = run.phase_started && p < static_cast<int>(run.phases.size()) ? run.phases[static_cast<std::size_t>(p)].rows : 0;
  for (int q = first; q < p; ++q) held += run.phases[static_cast<std::size_t>(q)].rows;
  return held;
}

// Locks `dir` for this process (DIR/.run.lock): a run, resume or prepare, one at a time.
DirectoryLock lock_run_directory(const fs::path& dir) {
  return DirectoryLock(dir, run_lock_file,
                       fmt::format("another qsdem (run, resume or prepare) is working in '{}' (it holds {}): wait "
                                   "for it, stop it, or choose another --out",
                                   dir.string(), (dir / run_lock_file).string()));
}

// Refuses what --out cannot be, a directory another qsdem works in (unless `locked_here`: this
// process holds its lock), and one whose results a run would overwrite (unless forced) or that
// holds files of something else than a qsdem run. Writes nothing.
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

// The name of phase p of the protocol (the last one's once all are done), for messages.
const std::string& phase_name(const Params& params, std::int32_t p) {
  return params.protocol[std::min(static_cast<std::size_t>(p), params.protocol.size() - 1)].name;
}

// Snapshot k (0: the prepared sample, k: after the k-th row of the phases after the first) and the
// .pvd of all snapshots on disk, whose time is each snapshot's nominal axial strain for the default
// protocol, else its number (so a resumed run rebuilds it from the files).
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
  const double per_row =
      params.phase_list ? 1.0 : params.triaxial.final_axial_strain / params.triaxial.sample_points;
  for (const auto& [row, file] : files) entries.push_back({static_cast<double>(row) * per_row, file});
  write_pvd(vtk / "series.pvd", entries);
}

// The rows of the phases after the first, up to the current one: the number of a snapshot.
long snapshot_rows(const RunProgress& run) {
  long k = 0;
  for (std::size_t p = 1; p < run.phases.size() && p <= static_cast<std::size_t>(run.phase); ++p) k += run.phases[p].rows;
  return k;
}

// The common target (Pa) of the three normal components of a phase that holds them all at one
// stress, else none. "Equal" allows for unit conversion's rounding ("400 kPa" and "0.4 MPa").
std::optional<double> isotropic_target(const Phase& phase) {
  const auto& c = phase.controls.component;
  for (std::size_t k = 0; k < 3; ++k)
    if (c[k].kind != ComponentControl::Kind::stress || std::abs(c[k].value - c[0].value) > 1e-9 * std::abs(c[0].value))
      return std::nullopt;
  return c[0].value;
}

// Phase p as an isotropic branch (docs/loading-paths.md): a phase after the first with an isotropic
// target, from the end of the phase before to its own end; null for any other phase. Compression
// positive: volume_strain = -(V_end - V_start)/V_start, the secant bulk modulus dp/volume_strain;
// a branch back to the start stress (within 1 %) of the isotropic branch before it also gives the
// volume strain the pair of branches leaves (the hysteresis of a load-unload cycle).
nlohmann::json isotropic_branch(const Protocol& protocol, const std::vector<PhaseRecord>& records, std::size_t p) {
  const std::optional<double> target = isotropic_target(protocol[p]);
  if (p == 0 || !target) return nullptr;
  const Measures &start = records[p - 1].final, &end = records[p].final;
  const double volume_strain = -(end.volume - start.volume) / start.volume;
  nlohmann::json j = {{"p_start_Pa", start.mean_stress}, {"p_end_Pa", end.mean_stress}, {"volume_strain", volume_strain}};
  if (volume_strain != 0) j["bulk_modulus_Pa"] = (end.mean_stress - start.mean_stress) / volume_strain;
  if (p >= 2 && isotropic_target(protocol[p - 1])) {
    const Measures& before = records[p - 2].final;  // the start of the branch before
    if (std::abs(*target - before.mean_stress) <= 0.01 * before.mean_stress)
      j["residual_volume_strain"] = -(end.volume / before.volume - 1);
  }
  return j;
}

// The figures of phase p, which has ended; `records`: those of the protocol's phases; with
// `energy`, the change of the energy ledger over the phase (docs/physics.md 12).
nlohmann::json phase_figures(const Protocol& protocol, const std::vector<PhaseRecord>& records, std::size_t p,
                             bool energy) {
  const Phase& phase = protocol[p];
  const PhaseRecord& r = records[p];
  const double rows = static_cast<double>(std::max(1L, r.rows));
  int normal_targets = 0;
  for (int c = 0; c < 3; ++c)
    normal_targets += phase.controls.component[static_cast<std::size_t>(c)].kind == ComponentControl::Kind::stress;
  nlohmann::json j = {{"name", phase.name},
                      {"file", phase.output.file},
                      {"steps", r.steps},
                      {"rows", r.rows},
                      {"wall_s", r.wall_s},
                      {"mean_ufr", r.ufr / rows},
                      {"mean_iuf", r.iuf / rows},
                      {"mean_imom", r.imom / rows},
                      {"peak_phi_deg", r.peak_phi_deg},
                      {"peak_phi_e1", r.peak_phi_e1},
                      {"final_e1", r.final_e1},
                      {"final_ev", r.final_ev},
                      {"max_stress_error", r.max_stress_error},
                      {"mean_stress_error", normal_targets > 0 ? r.stress_error / (normal_targets * rows) : 0.0},
                      {"max_shear_stress", r.max_shear_stress},
                      {"final", measures_json(r.final)}};
  if (nlohmann::json iso = isotropic_branch(protocol, records, p); !iso.is_null()) j["isotropic"] = iso;
  if (energy) j["energy"] = energy_change(r.energy_start, r.energy_end);
  return j;
}

// `controller`: the phase's controller's state at its end (RunProgress::controller_end), or none;
// `energy`: the run keeps the energy ledger (output.energy).
nlohmann::json phase_json(const Protocol& protocol, const std::vector<PhaseRecord>& records, std::size_t p,
                          const std::vector<double>* controller, bool energy) {
  const Phase& phase = protocol[p];
  nlohmann::json j = phase_figures(protocol, records, p, energy);
  if (phase.make_controller && controller && !controller->empty()) {
    const std::unique_ptr<Controller> c = phase.make_controller();
    c->restore(*controller);
    if (nlohmann::json f = c->figures(); !f.empty()) j["controller"] = f;
  }
  return j;
}

// Everything after the sample exists: the phases from wherever `run` stands, checkpoints, results.
// The end of each phase is ordered so that a crash at any instant leaves a directory that
// `resume` finishes: the phase's rows are synced, a checkpoint of the phase's end is saved, and
// only then are the results renamed and written (again, by a resume, when a crash cut that short).
class Execution {
 public:
  Execution(const Params& params, State& st, RunProgress& run, const RunOptions& options)
      : params_(params),
        st_(st),
        run_(run),
        options_(options),
        dir_(options.out),
        files_(phase_files(params.protocol)),
        progress_(Progress::detect(options.quiet)),
        wall_before_(run.wall_s) {
    run_.phases.resize(params_.protocol.size());
    const std::string self = build_record().dump();
    if (run_.builds.empty() || run_.builds.back() != self) run_.builds.push_back(self);
  }

  nlohmann::json operator()(const std::string& note) {
    const int count = static_cast<int>(params_.protocol.size());
    const int last = run_.prepare_only ? std::min(1, count) : count;  // prepare: the first phase only
    bool just_ended = false;  // the previous phase ended in this process (else its end is redone)
    while (run_.phase < last) {
      if (run_.phase > 0 && !run_.phase_started && !just_ended) finish_phase(run_.phase - 1, nullptr, nullptr);
      run_current_phase();
      just_ended = true;
    }
    if (!just_ended && run_.phase > 0) finish_phase(run_.phase - 1, nullptr, nullptr);  // stopped while writing them
    const nlohmann::json s = summary(note);
    write_file_atomic(dir_ / "summary.json", json_text(s) + "\n");
    done("summary.json written");
    // A finished run needs no checkpoint: the older first, so that a checkpoint.qsck present means
    // "not finished".
    fs::remove(dir_ / "checkpoint.qsck.prev");
    done("checkpoint.qsck.prev removed");
    fs::remove(dir_ / checkpoint_file);
    done("checkpoint.qsck removed");
    return s;
  }

 private:
  double process_s() const {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0_).count();
  }
  void done(const std::string& what) const {
    if (options_.after_write) options_.after_write(what);
  }
  void save(const fs::path& file) {
    run_.wall_s = wall_before_ + process_s();
    ScopedStage t(st_.timers, Stage::output);
    if (rows_) rows_->sync();
    if (classes_rows_) classes_rows_->sync();
    if (rows_) {  // what the checkpoint counts of the files it appends to (resume checks them)
      run_.files = {rows_->digest()};
      if (classes_rows_) run_.files.push_back(classes_rows_->digest());
    }
    save_checkpoint(file, params_.case_text, params_.source, st_, run_);
    last_save_ = std::chrono::steady_clock::now();
  }

  // After every step: stop on a signal, checkpoint every N sample points or M minutes, snapshots.
  void on_step(bool sample_point) {
    if (StopSignals::received() != 0) {
      const int sig = StopSignals::received();
      save(dir_ / checkpoint_file);
      throw Interrupted(fmt::format("stopped by {} after {} step {}; checkpoint written: continue with `qsdem resume {}`",
                                    signal_name(sig), phase_name(params_, run_.phase), run_.current().steps - 1,
                                    dir_.string()),
                        sig);
    }
    const auto& c = params_.checkpoint;
    const long rows = run_.current().rows;
    const bool by_points = sample_point && c.every_sample_points > 0 && rows % c.every_sample_points == 0;
    const bool by_time =
        c.every_minutes > 0 &&
        std::chrono::duration<double>(std::chrono::steady_clock::now() - last_save_).count() > 60 * c.every_minutes;
    if (by_points || by_time) save(dir_ / checkpoint_file);
    const int vtk = params_.output.vtk_every;
    if (sample_point && vtk > 0 && run_.phase > 0 && snapshot_rows(run_) % vtk == 0)
      write_snapshot(dir_, params_, st_, snapshot_rows(run_));
  }

  // The current phase, with its file open, to its end and the checkpoint of its end.
  void run_current_phase() {
    const int p = run_.phase;
    const Phase& phase = params_.protocol[static_cast<std::size_t>(p)];
    const PhaseFile& file = file_of(files_, params_.protocol, p);
    // The rows its file holds: those of the phases before that write to it, and this one's so far.
    long held = 0;
    for (int q : file.phases)
      if (q < p || (q == p && run_.phase_started)) held += run_.phases[static_cast<std::size_t>(q)].rows;
    const bool begun = file.phases.front() < p || run_.phase_started;
    SeriesColumns columns;
    columns.phase = file.phases.size() > 1;
    columns.energy = params_.output.energy;
    for (int q : file.phases) {
      const Phase& writer_phase = params_.protocol[static_cast<std::size_t>(q)];
      columns.dp = columns.dp || holds_volume(writer_phase);
      columns.shear = columns.shear || shears(writer_phase);
      columns.strain_rate = columns.strain_rate || writer_phase.rate_component >= 0;
      columns.relaxation = columns.relaxation || writer_phase.fire.has_value();
    }
    SeriesWriter writer(dir_ / phase.output.file, begun ? held : -1, columns);
    rows_ = &writer;
    std::optional<SeriesWriter> classes;
    if (params_.output.classes) open_classes(classes);
    classes_rows_ = classes ? &*classes : nullptr;
    note_kept_columns(writer);
    if (classes) note_kept_columns(*classes);
    try {
      run_phase(params_, st_, run_, {&writer, file.phases.front(), columns, classes_rows_, &size_classes_}, progress_,
                [this](bool sample_point) { on_step(sample_point); });
    } catch (const InputError& e) {
      // A phase stopped by what only the run could find (the cell shrank below the size rule of
      // SPEC 3) is a failed run, not a bad case: its checkpoints stay.
      throw RunError(fmt::format("{} stopped after {} step {}: {}", phase.name, phase.name, run_.current().steps - 1,
                                 e.what()));
    }
    ++run_.phase;
    run_.phase_started = false;
    run_.state = {};
    writer.sync();
    done(phase.output.file + ".partial synced");
    if (classes) classes->sync();
    save(dir_ / checkpoint_file);
    done("checkpoint at the end of " + phase.name + " written");
    rows_ = nullptr;
    classes_rows_ = nullptr;
    finish_phase(p, &writer, classes ? &*classes : nullptr);
  }

  // classes.csv, one file over the phases this directory runs (a run of a prepared sample starts
  // after the first): continued after the rows of the phases before and this one's so far.
  void open_classes(std::optional<SeriesWriter>& classes) const {
    const long held = classes_rows_held(run_);
    const long lines = held * static_cast<long>(size_classes_.size());
    classes.emplace(dir_ / classes_file, held > 0 ? lines : -1, CsvHeader{classes_header()});
  }

  // A file begun by another version of qsdem keeps its columns (SeriesWriter): said, and recorded
  // among the resume changes (summary.json).
  void note_kept_columns(const SeriesWriter& w) {
    if (w.omitted().empty()) return;
    const std::string change = fmt::format("{} keeps the columns it was begun with, without {}", w.digest().name,
                                           w.omitted());
    std::fprintf(stderr, "qsdem: %s (it was begun by another version of qsdem)\n", change.c_str());
    if (run_.changes.find(change) != std::string::npos) return;
    run_.changes += fmt::format("from {} step {}: {}\n", phase_name(params_, run_.phase), run_.current().steps, change);
  }

  int last_phase() const {
    const int count = static_cast<int>(params_.protocol.size());
    return (run_.prepare_only ? std::min(1, count) : count) - 1;
  }

  // What follows the end of phase p: its file renamed when no later phase writes to it; after the
  // first phase the prepared sample (compacted.packing, sample.qsck, snapshot 0), after the last
  // the final packing. `writer`: its open file, or none when a resume redoes an end a crash cut short.
  void finish_phase(int p, SeriesWriter* writer, SeriesWriter* classes) {
    const PhaseFile& file = file_of(files_, params_.protocol, p);
    if (file.phases.back() == p) {
      if (writer) writer->commit();
      else if (present(dir_ / (file.name + ".partial"))) commit_partial(dir_ / file.name);
      done(file.name + " renamed");
    }
    if (p == last_phase() && params_.output.classes) {
      if (classes) classes->commit();
      else if (present(dir_ / "classes.csv.partial")) commit_partial(dir_ / classes_file);
      done("classes.csv renamed");
    }
    if (p == 0 && run_.first_step == 0) {  // a run of a prepared sample did not run its first phase
      write_packing(dir_ / "compacted.packing", st_.particles, st_.cell);
      done("compacted.packing written");
      save(dir_ / prepared_sample_file);
      // Written again by a resume that redoes this end: the sample needs no previous one.
      fs::remove(dir_ / (std::string(prepared_sample_file) + ".prev"));
      done("sample.qsck written");
      if (params_.output.vtk_every > 0) {
        write_snapshot(dir_, params_, st_, 0);
        done("vtk snapshot 0 written");
      }
    }
    if (p + 1 == static_cast<int>(params_.protocol.size())) {
      write_packing(dir_ / "final.packing", st_.particles, st_.cell);
      done("final.packing written");
      const long k = snapshot_rows(run_);
      if (params_.output.vtk_every > 0 && p > 0 && k % params_.output.vtk_every == 0) {
        write_snapshot(dir_, params_, st_, k);
        done("last vtk snapshot written");
      }
    }
  }

  nlohmann::json summary(const std::string& note) const {
    const double wall = wall_before_ + process_s();
    const double r_min = smallest_equiv_radius(st_.particles);
    const double t_c =
        critical_time({params_.material.density, params_.material.young_modulus, params_.material.poisson_ratio}, r_min);
    const long own_steps = st_.step - run_.first_step;  // steps this run took (not a prepared sample's)
    const double particle_steps = static_cast<double>(own_steps) * static_cast<double>(st_.particles.size());
    nlohmann::json s;
    s["version"] = QSDEM_VERSION;
    s["build"] = build_record();
    s["builds"] = nlohmann::json::array();
    for (const std::string& b : run_.builds) s["builds"].push_back(nlohmann::json::parse(b));
    s["case"] = params_.name;
    s["config"] = {{"resolved_si", to_json(params_)}, {"as_written", params_.as_written}};
    s["derived"] = {{"particles", st_.particles.size()},
                    {"size_table", params_.sample.from.empty() && params_.sample.grading.empty() ? size_table_json(params_)
                                                                                               : nlohmann::json()},
                    {"sample_from", params_.sample.from},
                    {"r_min_m", r_min},
                    {"critical_time_s", t_c},
                    {"dt_s", params_.step_ratio * t_c},
                    {"threads", omp_get_max_threads()}};
    if (params_.sample.from.empty() && !params_.sample.grading.empty())
      s["derived"]["grading"] = grading_json(params_.sample.grading, params_.sample.total_particles, params_.sample.seed);
    if (!params_.phase_list)
      s["derived"]["triaxial_strain_rate_per_s"] = params_.triaxial.strain_rate / t_c;
    if (!note.empty()) s["note"] = note;
    if (!run_.changes.empty()) {
      nlohmann::json changes = nlohmann::json::array();
      std::istringstream lines(run_.changes);
      for (std::string line; std::getline(lines, line);) changes.push_back(line);
      s["resume_changes"] = changes;
    }
    nlohmann::json phases = nlohmann::json::array();
    for (std::size_t p = 0; p < params_.protocol.size() && p < static_cast<std::size_t>(run_.phase); ++p)
      phases.push_back(phase_json(params_.protocol, run_.phases, p, controller_end(p), params_.output.energy));
    s["phases"] = phases;
    // The first phase as the sample's compaction; the last, when it is another, as the test.
    const PhaseRecord& first = run_.phases.front();
    s["compaction"] = {{"steps", first.steps}, {"wall_s", first.wall_s}, {"final", measures_json(first.final)}};
    s["void_ratio_after_compaction"] = first.final.void_ratio;
    if (!run_.prepare_only && run_.phases.size() > 1) {
      const nlohmann::json last =
          phase_json(params_.protocol, run_.phases, run_.phases.size() - 1, controller_end(run_.phases.size() - 1),
                     params_.output.energy);
      s["triaxial"] = {{"steps", last["steps"]},
                       {"rows", last["rows"]},
                       {"wall_s", last["wall_s"]},
                       {"final_e1", last["final_e1"]},
                       {"max_lateral_stress_error", last["max_stress_error"]},
                       {"mean_lateral_stress_error", last["mean_stress_error"]},
                       {"max_shear_stress", last["max_shear_stress"]}};
      if (last.contains("controller")) s["triaxial"]["controller"] = last["controller"];
      for (const char* key : {"mean_ufr", "mean_iuf", "mean_imom", "peak_phi_deg", "peak_phi_e1", "final_ev"})
        s[key] = last[key];
    }
    s["steps"] = own_steps;
    if (!params_.phase_list)
      s["steps_cover"] = run_.first_step == 0 ? (run_.prepare_only ? "compaction" : "compaction + triaxial")
                                              : "triaxial of a prepared sample";
    else
      s["steps_cover"] = run_.first_step == 0 ? (run_.prepare_only ? "the first phase" : "every phase")
                                              : "the phases after the first, of a prepared sample";
    s["wall_s"] = wall;
    s["particle_steps_per_s"] = particle_steps / std::max(wall, 1e-9);
    s["neighbor_builds"] = st_.neighbor.builds;
    s["peak_rss_kib"] = peak_rss_kib();
    s["stages"] = stage_json(st_.timers, own_steps);
    s["stage_table"] = format_stage_table(st_.timers, own_steps);
    return s;
  }

  const Params& params_;
  State& st_;
  RunProgress& run_;
  const RunOptions& options_;
  const fs::path dir_;
  const std::vector<PhaseFile> files_;
  Progress progress_;
  const double wall_before_;

  const std::vector<double>* controller_end(std::size_t p) const {
    return p < run_.controller_end.size() ? &run_.controller_end[p] : nullptr;
  }
  const std::chrono::steady_clock::time_point t0_ = std::chrono::steady_clock::now();
  std::chrono::steady_clock::time_point last_save_ = std::chrono::steady_clock::now();
  SeriesWriter* rows_ = nullptr;  // the phase's file: on disk before each checkpoint counts its rows
  SeriesWriter* classes_rows_ = nullptr;  // classes.csv, the same
  const std::vector<double> size_classes_ = params_.sample.from.empty() && !params_.sample.grading.empty()
                                                ? grading_classes(params_.sample.grading, st_.particles)
                                                : size_classes(st_.particles);
};

nlohmann::json execute(const Params& params, State& st, RunProgress& run, const RunOptions& options,
                       const std::string& note) {
  return Execution(params, st, run, options)(note);
}

// The sample named by sample.from: a prepared sample (directory of `qsdem prepare`, or of a run
// that compacted, which skips compaction) or a packing file (which is compacted).
State load_sample(const Params& params, RunProgress& run) {
  const fs::path from = params.sample.from;
  if (fs::is_directory(from)) {
    if (!fs::exists(from / prepared_sample_file))
      throw InputError(fmt::format("sample.from = '{}': that directory holds no prepared sample ({})", from.string(),
                                   prepared_sample_file));
    return prepared_sample(load_checkpoint(from / prepared_sample_file), params, from.string(), run);
  }
  if (!fs::is_regular_file(from))
    throw InputError(fmt::format("sample.from = '{}': no such prepared sample directory or packing file",
                                 from.string()));
  return read_packing(from, params.material.density);
}

// The sample of a new run, refused (InputError) when it cannot run: too big for the memory, its
// largest particle not smaller than half the cell (SPEC 3), named by a bad sample.from.
State make_sample(const Params& params, RunProgress& run) {
  State st;
  if (params.sample.from.empty()) {
    st = generate_loose_sample(params, [] { return StopSignals::received() != 0; });
    if (const int sig = StopSignals::received(); sig != 0)
      throw Interrupted(
          fmt::format("stopped by {} while generating the sample; nothing was written", signal_name(sig)), sig);
  } else {
    st = load_sample(params, run);
  }
  const Model m = compaction_model(params, st);
  try {
    check_cell_size(st.particles, st.cell, m.skin);
  } catch (const InputError& e) {
    throw InputError(params.sample.from.empty() ? fmt::format("{}: the generated sample: {}", params.source, e.what())
                                                : fmt::format("sample.from = '{}': {}", params.sample.from, e.what()));
  }
  return st;
}

// Refuses to resume `dir` when its files are not those its checkpoint counts (checkpoints of format
// 10 on): its case.toml is not the one the run wrote, or the rows of a file it appends to begin
// otherwise (another run's checkpoint, case.toml or rows copied in).
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

}  // namespace

State new_sample(const Params& params, RunProgress& run) { return make_sample(params, run); }

nlohmann::json run_case(const Params& params, const RunOptions& options) {
  const fs::path dir = options.out;
  require_utf8(dir.string(), "--out");
  const StopSignals signals;
  check_out(dir, options.force, false);
  std::error_code ec;
  if (!params.sample.from.empty() && fs::equivalent(params.sample.from, dir, ec))
    throw InputError(fmt::format("sample.from = '{}' is the --out directory: a run cannot replace the sample it "
                                 "shears; choose another --out",
                                 params.sample.from));
  // Every input error is found before the directory is touched.
  RunProgress run;
  State st = make_sample(params, run);
  run.prepare_only = options.prepare_only;
  fs::create_directories(dir, ec);
  if (ec) throw InputError(fmt::format("cannot create --out '{}': {}", dir.string(), ec.message()));
  const DirectoryLock lock = lock_run_directory(dir);
  check_out(dir, options.force, true);  // again under the lock: another process may have written since
  for (const char* f : run_files) fs::remove(dir / f);
  for (const Phase& phase : params.protocol) {
    fs::remove(dir / phase.output.file);
    fs::remove(dir / (phase.output.file + ".partial"));
  }
  fs::remove_all(dir / "vtk");
  fs::remove_all(dir / "plot");  // the page of the run replaced (`qsdem plot`)
  write_file_atomic(dir / "case.toml", params.case_text);
  run.case_digest = fnv1a64(params.case_text.data(), params.case_text.size());
  return execute(params, st, run, options, "");
}

nlohmann::json resume_run(const fs::path& dir, const RunOptions& options) {
  if (!fs::is_directory(dir)) throw InputError(fmt::format("'{}' is not a run directory", dir.string()));
  require_utf8(dir.string(), "the run directory");
  const StopSignals signals;
  const DirectoryLock lock = lock_run_directory(dir);
  if (fs::exists(dir / "summary.json") && !fs::exists(dir / checkpoint_file))
    throw InputError(fmt::format("'{}' holds a finished run: nothing to resume", dir.string()));
  std::string note;
  Checkpoint c = load_latest_checkpoint(dir / checkpoint_file, &note);
  if (!note.empty()) std::fprintf(stderr, "qsdem: %s\n", note.c_str());
  for (const std::string& set : options.sets) {
    const std::string key = set.substr(0, set.find('='));
    if (std::find(resume_keys.begin(), resume_keys.end(), key) == resume_keys.end()) {
      std::string allowed;
      for (const auto& k : resume_keys) allowed += (allowed.empty() ? "" : ", ") + k;
      throw InputError(fmt::format("resume --set '{}': '{}' cannot change in a run under way (the checkpoint's state "
                                   "depends on it); allowed: {}",
                                   set, key, allowed));
    }
    if (key == "time.step_ratio" && c.run.phase != 0)
      throw InputError(fmt::format("resume --set '{}': the phases after the first take their rows and end at fixed "
                                   "step numbers, so time.step_ratio can change only during compaction (the first "
                                   "phase); shear the run's compacted sample anew (sample.from = '{}')",
                                   set, fs::absolute(dir).string()));
  }
  Params params = parse_case(c.case_text, c.case_source, options.sets);
  check_checkpoint_case(c, params, (dir / checkpoint_file).string());
  check_run_directory(dir, c.run, params);
  const auto record_change = [&](const std::string& change) {  // a line of summary.json's resume_changes
    c.run.changes += fmt::format("from {} step {}: {}\n", phase_name(params, c.run.phase),
                                 c.run.phase < static_cast<std::int32_t>(c.run.phases.size()) ? c.run.current().steps : 0,
                                 change);
  };
  // A run begun by an engine without classes.csv (rows written, no classes.csv.partial) continues
  // without it rather than with a file that lacks its first rows.
  if (params.output.classes && classes_rows_held(c.run) > 0 && !present(dir / "classes.csv.partial") &&
      !present(dir / classes_file)) {
    params.output.classes = false;
    const std::string change = "output.classes=false (begun without classes.csv)";
    if (c.run.changes.find(change) == std::string::npos) record_change(change);
    std::fprintf(stderr, "qsdem: '%s' holds no classes.csv.partial although the run has begun: it was begun "
                         "without classes.csv and continues without it\n",
                 dir.string().c_str());
  }
  for (const std::string& set : options.sets) {
    if (set.rfind("time.step_ratio=", 0) == 0 && planned_end(params.protocol.front(), params.step_ratio) >= 0)
      throw InputError(fmt::format("resume --set '{}': the first phase ends at a fixed step number, so "
                                   "time.step_ratio cannot change in it; start the run anew",
                                   set));
    record_change(set);
  }
  RunOptions o = options;
  o.out = dir;
  return execute(params, c.state, c.run, o, note);
}


std::string format_run_table(const nlohmann::json& s) {
  std::string out;
  auto row = [&](const std::string& name, const std::string& value) {
    out += fmt::format("| {:<38} | {:>14} |\n", name, value);
  };
  row("quantity", "value");
  out += fmt::format("|{:-<40}|{:->16}|\n", "", "");
  row("particles", fmt::format("{}", s["derived"]["particles"].get<long>()));
  row("void ratio after compaction", fmt::format("{:.4f}", s["void_ratio_after_compaction"].get<double>()));
  if (s.contains("triaxial")) {
    row("peak friction angle (deg)", fmt::format("{:.2f}", s["peak_phi_deg"].get<double>()));
    row("mean UFR", fmt::format("{:.4g}", s["mean_ufr"].get<double>()));
    row("mean IMom", fmt::format("{:.4g}", s["mean_imom"].get<double>()));
    row("max lateral stress error", fmt::format("{:.3g} %", 100 * s["triaxial"]["max_lateral_stress_error"].get<double>()));
  }
  row("steps (" + s["steps_cover"].get<std::string>() + ")", fmt::format("{}", s["steps"].get<long>()));
  row("wall time (s)", fmt::format("{:.1f}", s["wall_s"].get<double>()));
  row("particle-steps per second", fmt::format("{:.4g}", s["particle_steps_per_s"].get<double>()));
  return out;
}

namespace {

template <class T>
double kib(const std::vector<T>& v) {
  return static_cast<double>(v.capacity() * sizeof(T)) / 1024;
}

// Heap held by the state's arrays (KiB), by structure: what `peak_rss_kib` is made of besides
// the binary, its libraries and transient build buffers.
nlohmann::json memory_kib(const State& st, const Schedule& schedule) {
  const Particles& p = st.particles;
  const PairList& q = st.pairs;
  double particles = 0;
  for_each_field(p, [&](const auto& array, ParticleField) { particles += kib(array); });
  double history = kib(q.i) + kib(q.j) + kib(q.image);
  for_each_pair_field([&](const HistoryLayout&, PairField, const std::vector<double>& values) { history += kib(values); },
                      q);
  const double results = kib(q.contact_force) + kib(q.contact_torque_j) + kib(q.contact_pairs) + kib(q.contact_j);
  const double lists = kib(q.first_i) + kib(q.block_first) +
                       kib(st.neighbor.s_at_build) + kib(st.neighbor.surface_path);
  const Schedule& s = schedule;
  const double scratch = kib(st.blocks) + kib(st.shapes) + kib(s.block_seconds) + kib(s.block_weight) +
                         kib(s.block_cut) + kib(s.block_claimed) + kib(s.thread_busy) + kib(s.owner_first) +
                         kib(s.contact_owner_first);
  return {{"particles", particles},
          {"pair_keys_and_history", history},
          {"pair_results", results},
          {"lists", lists},
          {"scratch", scratch},
          {"total", particles + history + results + lists + scratch}};
}

}  // namespace

namespace {

// What `qsdem bench` steps: the state, the case, and which phase's friction and damping apply.
struct BenchInput {
  State state;
  Params params;
  std::string source;  // "packing" or "checkpoint"
  std::string phase;   // "compaction" or "triaxial"
  std::filesystem::path file;
};

BenchInput bench_input(const std::filesystem::path& source, const std::string& case_path,
                       const std::vector<std::string>& overrides) {
  namespace fs = std::filesystem;
  fs::path file = source;
  if (fs::is_directory(source)) {
    file = source / prepared_sample_file;
    if (!fs::exists(file)) file = source / checkpoint_file;
    if (!fs::exists(file))
      throw InputError(fmt::format("'{}' holds neither {} (a prepared sample) nor {} (an unfinished run)",
                                   source.string(), prepared_sample_file, checkpoint_file));
  } else if (!fs::is_regular_file(source)) {
    throw InputError(fmt::format("'{}': no such packing file, checkpoint or run directory", source.string()));
  }
  BenchInput in;
  in.file = file;
  if (file.extension() != ".qsck") {
    if (case_path.empty())
      throw InputError(fmt::format("'{}' is a packing: give the case it is stepped with (--case)", file.string()));
    in.params = load_case(case_path, overrides);
    in.state = read_packing(file, in.params.material.density);
    in.source = "packing";
    in.phase = in.params.protocol.back().name;
    return in;
  }
  Checkpoint c = load_checkpoint(file);
  const Params own = parse_case(c.case_text, c.case_source, case_path.empty() ? overrides : std::vector<std::string>{});
  check_checkpoint_case(c, own, file.string());
  in.params = case_path.empty() ? own : load_case(case_path, overrides);
  const auto& a = own.material;
  const auto& b = in.params.material;
  // The masses and contacts of the state were made with the checkpoint's material and time step.
  if (a.density != b.density || a.young_modulus != b.young_modulus || a.poisson_ratio != b.poisson_ratio ||
      own.step_ratio != in.params.step_ratio)
    throw InputError(fmt::format("'{}' was made with density {} kg/m^3, E {} Pa, nu {}, time.step_ratio {}; the case "
                                 "has {}, {}, {}, {}: they must be equal",
                                 file.string(), a.density, a.young_modulus, a.poisson_ratio, own.step_ratio, b.density,
                                 b.young_modulus, b.poisson_ratio, in.params.step_ratio));
  in.state = std::move(c.state);
  in.source = "checkpoint";
  in.phase = phase_name(in.params, c.run.phase);
  return in;
}

long contact_count(const State& st) {
  long n = 0;
  for (const ForceBlock& b : st.blocks) n += b.contacts;
  return n;
}

}  // namespace

nlohmann::json bench_packing(const std::filesystem::path& source, const std::string& case_path,
                             const std::vector<std::string>& overrides, long steps, bool as_spheres) {
  BenchInput in = bench_input(source, case_path, overrides);
  State& st = in.state;
  const Params& params = in.params;
  if (as_spheres) {
    State spheres;
    spheres.cell = st.cell;
    const Particles& p = st.particles;
    for (std::size_t i = 0; i < p.size(); ++i)
      spheres.particles.add(p.id[i], ShapeKind::sphere, Vec3::Constant(p.equiv_radius[i]), params.material.density,
                            p.s[i], Quat::Identity());
    st = std::move(spheres);
    in.source = "packing";
  }
  long ellipsoids = 0;
  for (ShapeKind k : st.particles.shape) ellipsoids += k == ShapeKind::ellipsoid;
  // The phase's friction and damping in a fixed cell: a peer code runs the same physics on the
  // same packing in a fixed periodic box.
  const Phase& phase = *std::find_if(params.protocol.begin(), params.protocol.end(),
                                     [&](const Phase& p) { return p.name == in.phase; });
  Model model = phase_model(params, phase, phase.controls, st.particles, st.cell.h);
  for (auto& c : model.control) c = {};
  for (auto& c : model.shear_control) c = {};
  assign_damping(model, st.particles);
  // A packing's first list build is set-up, not stepping (LIGGGHTS' loop time leaves its own
  // out); at rest it changes no history. A checkpoint's list and history are stepped as they are.
  if (in.source == "packing") evaluate_forces(model, st);
  st.timers = {};
  const long builds_before = st.neighbor.builds;
  long narrow_tests = 0, pw_iterations = 0, contacts_start = 0;
  double wall = 0;
  Schedule schedule;
  for (long n = 0; n < steps; ++n) {
    const auto t0 = std::chrono::steady_clock::now();
    step(model, st, schedule);
    wall += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    if (n == 0) contacts_start = contact_count(st);  // at the first step's force evaluation
    narrow_tests += st.narrow_tests;
    pw_iterations += st.pw_iterations;
  }
  const Measures m = measure(st);
  const double np = static_cast<double>(st.particles.size());
  return {{"source", in.source},
          {"file", in.file.string()},
          {"phase", in.phase},
          {"particles", st.particles.size()},
          {"ellipsoids", ellipsoids},
          {"contacts_start", contacts_start},
          {"contacts_end", m.contacts},
          {"pairs", st.pairs.size()},
          {"narrow_tests_per_step", static_cast<double>(narrow_tests) / static_cast<double>(std::max(1L, steps))},
          {"pw_iterations_per_step", static_cast<double>(pw_iterations) / static_cast<double>(std::max(1L, steps))},
          {"ekin_J", m.ekin_trans + m.ekin_rot},
          {"ekin_trans_J", m.ekin_trans},
          {"steps", steps},
          {"threads", omp_get_max_threads()},
          {"wall_s", wall},
          {"particle_steps_per_s", np * static_cast<double>(steps) / wall},
          // mean / largest thread time in the force stage (1: balanced; null on one thread)
          {"force_stage_balance", st.timers.force_thread_max > 0
                                      ? nlohmann::json(st.timers.force_thread_mean / st.timers.force_thread_max)
                                      : nlohmann::json(nullptr)},
          {"peak_rss_kib", peak_rss_kib()},
          {"state_kib", memory_kib(st, schedule)},
          {"dt_s", model.dt},
          {"density_kg_m3", model.material.density},
          {"young_modulus_Pa", model.material.young_modulus},
          {"poisson_ratio", model.material.poisson_ratio},
          {"friction", phase.friction},
          {"damping_model", phase.damping.model},
          {"damping_ratio", phase.damping.ratio},
          {"neighbor_builds", st.neighbor.builds - builds_before},
          {"stages", stage_json(st.timers, steps)}};
}

nlohmann::json build_record() {
  const std::string commit = QSDEM_COMMIT;
  const int clean = QSDEM_TREE_CLEAN;
  return {{"version", QSDEM_VERSION},
          {"commit", commit.empty() ? nlohmann::json() : nlohmann::json(commit)},
          {"tree_clean", clean < 0 ? nlohmann::json() : nlohmann::json(clean == 1)}};
}

}  // namespace qsdem
