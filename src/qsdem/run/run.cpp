#include "qsdem/run/run.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <optional>

#include "qsdem/engine/measures.hpp"
#include "qsdem/engine/neighbor.hpp"
#include "qsdem/run/checkpoint.hpp"
#include "qsdem/run/files.hpp"
#include "qsdem/run/generate.hpp"
#include "qsdem/run/grading.hpp"
#include "qsdem/run/output.hpp"
#include "qsdem/run/packing_io.hpp"
#include "qsdem/run/protocol.hpp"
#include "qsdem/run/run_directory.hpp"
#include "qsdem/run/stop_signals.hpp"
#include "qsdem/run/summary.hpp"

namespace qsdem {
namespace {

namespace fs = std::filesystem;

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
    const nlohmann::json s = run_summary(params_, st_, run_, wall_before_ + process_s(), note);
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
    // A run of a prepared sample did not run its first phase: those rows are in the sample's directory.
    const auto ran_here = [&](int q) { return q > 0 || run_.first_step == 0; };
    long held = 0;
    bool begun = run_.phase_started;
    for (int q : file.phases)
      if (ran_here(q) && (q < p || (q == p && run_.phase_started)))
        held += run_.phases[static_cast<std::size_t>(q)].rows, begun = begun || q < p;
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

  const Params& params_;
  State& st_;
  RunProgress& run_;
  const RunOptions& options_;
  const fs::path dir_;
  const std::vector<PhaseFile> files_;
  Progress progress_;
  const double wall_before_;

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
  clear_run_files(dir, params.protocol);
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

}  // namespace qsdem
