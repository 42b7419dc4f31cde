// `qsdem study` (docs/study.md): the study directory set up and checked, the samples prepared and
// the runs made by child processes (and over MPI ranks), level by level of the stages, then the
// analysis.
#include "qsdem/study/study.hpp"

#include <fcntl.h>
#include <fmt/format.h>
#include <mpi.h>
#include <sys/file.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <map>
#include <optional>
#include <sstream>

#include "qsdem/engine/types.hpp"
#include "qsdem/run/files.hpp"
#include "qsdem/run/output.hpp"
#include "qsdem/run/progress.hpp"
#include "qsdem/run/run_directory.hpp"
#include "qsdem/run/stop_signals.hpp"
#include "qsdem/run/summary.hpp"
#include "qsdem/study/study_analysis.hpp"

extern char** environ;

namespace qsdem {
namespace {

namespace fs = std::filesystem;

// The bytes of a file of the study directory (never read through a link).
std::string read_bytes(const fs::path& p) {
  int err = 0;
  std::optional<std::string> text = read_regular_file(p, &err);
  if (!text) throw std::runtime_error(fmt::format("cannot read {}: {}", p.string(), file_error(err)));
  return std::move(*text);
}

// ---------------------------------------------------------------------------------------------
// Child processes: `qsdem prepare`, `qsdem run`, `qsdem resume`, one per sample or run.

// How children are started: this binary (or StudyOptions::executable), and the environment
// without the MPI launcher's variables (a child is a plain process, not an MPI rank).
struct Launcher {
  std::string exe;
  std::vector<std::string> env;
};

Launcher make_launcher(const std::string& executable) {
  Launcher l;
  std::error_code ec;
  l.exe = executable.empty() ? fs::read_symlink("/proc/self/exe", ec).string() : executable;
  if (ec) throw RunError("cannot find this program's path (/proc/self/exe): " + ec.message());
  for (char** e = environ; *e; ++e) {
    const std::string_view v(*e);
    if (v.rfind("OMPI_", 0) == 0 || v.rfind("PMIX_", 0) == 0) continue;
    l.env.emplace_back(v);
  }
  return l;
}

// Starts `exe args` with stdout and stderr appended to `log`, stdin from /dev/null, in its own
// process group (a terminal's Ctrl-C reaches the study only, which forwards it once), and with
// SIGTERM on the study's death (no orphan keeps writing into the study directory).
pid_t spawn_child(const Launcher& l, const std::vector<std::string>& args, const fs::path& log) {
  std::vector<std::string> all{l.exe};
  all.insert(all.end(), args.begin(), args.end());
  std::vector<char*> argv, envp;
  for (auto& a : all) argv.push_back(a.data());
  argv.push_back(nullptr);
  for (const auto& e : l.env) envp.push_back(const_cast<char*>(e.c_str()));
  envp.push_back(nullptr);

  const int fd = open_file(log, O_WRONLY | O_APPEND);
  if (fd < 0) throw RunError(fmt::format("cannot open log '{}': {}", log.string(), file_error(errno)));
  const int null_fd = ::open("/dev/null", O_RDONLY | O_CLOEXEC);
  std::string header = "=== qsdem";
  for (const auto& a : args) header += " '" + a + "'";
  header += "\n";
  if (::write(fd, header.data(), header.size()) < 0) { /* the log header is a courtesy */ }

  // Block the stop signals across fork: the child must not run the study's handler (a forwarded
  // signal would be lost); it resets them to the default before exec.
  sigset_t block, old;
  sigemptyset(&block);
  sigaddset(&block, SIGINT);
  sigaddset(&block, SIGTERM);
  sigprocmask(SIG_BLOCK, &block, &old);
  const pid_t parent = ::getpid();
  const pid_t pid = ::fork();
  if (pid == 0) {  // only async-signal-safe calls until exec
    ::signal(SIGINT, SIG_DFL);
    ::signal(SIGTERM, SIG_DFL);
    ::prctl(PR_SET_PDEATHSIG, SIGTERM);
    if (::getppid() != parent) ::_exit(143);
    ::setpgid(0, 0);
    if (null_fd >= 0) ::dup2(null_fd, 0);
    ::dup2(fd, 1);
    ::dup2(fd, 2);
    ::close_range(3, ~0U, 0);  // sockets of an MPI rank are not the child's business
    sigprocmask(SIG_UNBLOCK, &block, nullptr);
    ::execve(argv[0], argv.data(), envp.data());
    ::_exit(127);
  }
  const int err = errno;
  sigprocmask(SIG_SETMASK, &old, nullptr);
  ::close(fd);
  if (null_fd >= 0) ::close(null_fd);
  if (pid < 0) throw RunError(fmt::format("cannot start a child process: {}", std::strerror(err)));
  return pid;
}

// The last lines of a log, for the failure report.
std::string log_tail(const fs::path& log, std::size_t lines) {
  std::istringstream in(read_regular_file(log).value_or(""));
  std::vector<std::string> all;
  for (std::string l; std::getline(in, l);)
    if (!l.empty() && l.rfind("===", 0) != 0) all.push_back(l);
  std::string out;
  for (std::size_t k = all.size() > lines ? all.size() - lines : 0; k < all.size(); ++k)
    out += (out.empty() ? "" : "\n") + all[k];
  return out;
}

// One child's work: prepare a sample or shear it.
struct Job {
  enum class Kind { prepare, run } kind = Kind::run;
  std::string id;       // the sample dir name or the run id
  std::string rel_dir;  // relative to the study directory
  fs::path study_dir;   // absolute
  fs::path dir;         // absolute: study_dir / rel_dir
  fs::path needs;       // runs: the prepared sample they shear
  std::vector<std::string> fresh;  // arguments of a fresh start
  int threads = 1;
  double expected_steps = 0;  // runs: triaxial steps left (order, ETA)
  std::size_t group = 0;      // runs of one sample share a time per step
};

fs::path log_of(const Job& j) { return j.dir / (j.kind == Job::Kind::prepare ? "prepare.log" : "run.log"); }

// A result is a regular file: a link planted under its name does not make a job finished.
bool regular(const fs::path& p) {
  std::error_code ec;
  return fs::is_regular_file(fs::symlink_status(p, ec));
}

bool finished(const Job& j) {
  if (j.kind == Job::Kind::prepare) return regular(j.dir / prepared_sample_file) && regular(j.dir / "summary.json");
  return regular(j.dir / "summary.json") && !fs::exists(j.dir / checkpoint_file);
}

// A run directory that `qsdem resume` continues (its newest or its previous checkpoint).
bool holds_checkpoint(const fs::path& dir) {
  return fs::exists(dir / checkpoint_file) || fs::exists(dir / "checkpoint.qsck.prev");
}

// The copy of a sample's case file that its children run (study_dir/cases/<sample>.toml), written
// from the bytes the study was loaded with: an edit of the case file during the study reaches none
// of its runs (the next start refuses it, check_recorded).
fs::path case_copy(const fs::path& study_dir, const StudySample& smp) { return study_dir / "cases" / (smp.name + ".toml"); }

void write_case_copies(const Study& study, const fs::path& out) {
  make_directories(out, "cases");
  for (const StudySample& smp : study.samples) {
    const fs::path copy = case_copy(out, smp);
    if (read_regular_file(copy) != smp.case_text) write_file_atomic(copy, smp.case_text);
  }
}

// A run with a checkpoint resumes from it; anything else starts afresh (--force clears what an
// unfinished start left). An interrupted `prepare` restarts (a prepared sample of checkpoint format
// 4 or older would be sheared by `resume`).
std::vector<std::string> command(const Job& j) {
  if (j.kind == Job::Kind::run && holds_checkpoint(j.dir))
    return {"resume", j.dir.string(), "--threads", std::to_string(j.threads), "--quiet", "--no-plot"};
  return j.fresh;
}

}  // namespace

double steps_left(const fs::path& run_dir, double expected) {
  if (!holds_checkpoint(run_dir)) return expected;
  std::istringstream in(read_regular_file(run_dir / "series.csv.partial").value_or(""));
  std::string line, last;
  std::getline(in, line);  // the header
  while (std::getline(in, line))
    if (!line.empty()) last = line;
  if (last.empty()) return expected;
  try {
    const double done = std::stod(last.substr(0, last.find(',')));  // the `step` column
    return std::clamp(expected - done, 1.0, expected);
  } catch (const std::exception&) {
    return expected;
  }
}

namespace {

// Wall seconds per triaxial step of a finished run (for the ETA).
std::optional<std::pair<double, double>> run_cost(const fs::path& dir) {
  try {
    const auto s = nlohmann::json::parse(read_bytes(dir / "summary.json"));
    const auto& t = s.at("triaxial");
    return std::make_pair(t.at("wall_s").get<double>(), t.at("steps").get<double>());
  } catch (const std::exception&) {
    return std::nullopt;
  }
}

std::string plural(std::size_t n, const std::string& one, const std::string& many = "") {
  return fmt::format("{} {}", n, n == 1 ? one : many.empty() ? one + "s" : many);
}

// The study's one progress display on stderr: a line redrawn in place on a terminal, a plain
// line whenever the counts change otherwise.
class StudyProgress {
 public:
  StudyProgress(bool quiet, std::string prefix) : quiet_(quiet), tty_(::isatty(2) != 0), prefix_(std::move(prefix)) {}
  ~StudyProgress() { end_line(); }
  StudyProgress(const StudyProgress&) = delete;
  StudyProgress& operator=(const StudyProgress&) = delete;

  void show(const std::string& counts, const std::string& eta) {
    if (quiet_) return;
    const auto now = std::chrono::steady_clock::now();
    if (tty_) {
      if (counts == last_ && now - drawn_at_ < std::chrono::seconds(1)) return;
      std::fprintf(stderr, "\r%s%s%s\033[K", prefix_.c_str(), counts.c_str(), eta.c_str());
      open_line_ = true;
    } else {
      if (counts == last_) return;
      std::fprintf(stderr, "%s%s%s\n", prefix_.c_str(), counts.c_str(), eta.c_str());
    }
    std::fflush(stderr);
    last_ = counts;
    drawn_at_ = now;
  }
  void end_line() {
    if (open_line_) std::fputc('\n', stderr);
    open_line_ = false;
  }
  // A message between progress lines (printed even when quiet: failures, warnings).
  void message(const std::string& text) {
    end_line();
    std::fprintf(stderr, "%s%s\n", prefix_.c_str(), text.c_str());
    last_.clear();
  }
  // Information between progress lines (not when quiet).
  void note(const std::string& text) {
    if (!quiet_) message(text);
  }

 private:
  bool quiet_, tty_;
  std::string prefix_, last_;
  bool open_line_ = false;
  std::chrono::steady_clock::time_point drawn_at_{};
};

struct PoolResult {
  int signal = 0;  // the stop signal, when the study was interrupted
  nlohmann::json failures = nlohmann::json::array();
};

// Runs `jobs` with at most `parallel` children at once; finished jobs are skipped. Stops
// launching on SIGINT/SIGTERM, forwards the signal to the running children and waits for them.
class Pool {
 public:
  Pool(const std::vector<Job>& jobs, std::string what, int parallel, const Launcher& launcher, StudyProgress& progress)
      : jobs_(jobs), what_(std::move(what)), parallel_(std::size_t(parallel)), launcher_(launcher),
        progress_(progress), done_before_(jobs.size(), 0) {}

  PoolResult run() {
    for (std::size_t k = 0; k < jobs_.size(); ++k)
      if (finished(jobs_[k])) {
        done_before_[k] = 1;
        ++done_;
        record_cost(jobs_[k]);
      }
    for (;;) {
      if (StopSignals::received() != 0 && !forwarded_) {
        for (const auto& r : running_) ::kill(r.pid, StopSignals::received());
        forwarded_ = true;
      }
      launch();
      if (running_.empty() && (StopSignals::received() != 0 || (next_ == jobs_.size() && again_.empty()))) break;
      show();
      ::usleep(100'000);  // a signal cuts the nap short
      reap();
    }
    show();
    progress_.end_line();
    result_.signal = StopSignals::received();
    return result_;
  }

 private:
  using clock = std::chrono::steady_clock;
  struct Running {
    std::size_t job;
    pid_t pid;
    clock::time_point start;
  };
  // Children killed by a signal the study did not send (the OOM killer, a kill by hand) are
  // continued from their checkpoints, at most this many times each: an incomplete sweep would
  // make the next stage's pick.
  static constexpr int max_restarts = 3;

  // Starts jobs (those to continue first) while there is room and no stop signal.
  void launch() {
    while (StopSignals::received() == 0 && running_.size() < parallel_ && (!again_.empty() || next_ < jobs_.size())) {
      std::size_t k = 0;
      if (!again_.empty()) {
        k = again_.front();
        again_.erase(again_.begin());
      } else {
        k = next_++;
        if (done_before_[k]) continue;
      }
      const Job& j = jobs_[k];
      if (!j.needs.empty() && !fs::exists(j.needs / prepared_sample_file)) {
        fail(j, fmt::format("its sample {} was not prepared", j.needs.filename().string()), -1);
        continue;
      }
      try {
        make_directories(j.study_dir, j.rel_dir);
        running_.push_back({k, spawn_child(launcher_, command(j), log_of(j)), clock::now()});
      } catch (const std::exception& e) {
        fail(j, e.what(), -1);
      }
    }
  }

  // Collects the children that ended: done, stopped as asked, continued, or failed.
  void reap() {
    for (std::size_t r = 0; r < running_.size();) {
      int status = 0;
      if (::waitpid(running_[r].pid, &status, WNOHANG) != running_[r].pid) {
        ++r;
        continue;
      }
      const std::size_t k = running_[r].job;
      const Job& j = jobs_[k];
      running_.erase(running_.begin() + std::ptrdiff_t(r));
      const int code = WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
      const bool by_signal = WIFSIGNALED(status) || code == 130 || code == 143;  // killed, or stopped at a checkpoint
      if (code == 0 && finished(j)) {
        ++done_;
        record_cost(j);
      } else if (StopSignals::received() != 0 && (code == 130 || code == 143)) {
        // interrupted as asked: its checkpoint continues it next time
      } else if (StopSignals::received() == 0 && by_signal && restarts_[k] < max_restarts) {
        ++restarts_[k];
        again_.push_back(k);
        progress_.message(fmt::format("{} {} was stopped by signal {} (not by the study): continued from its {} ({} of {})",
                                      j.kind == Job::Kind::prepare ? "sample" : "run", j.id,
                                      WIFSIGNALED(status) ? WTERMSIG(status) : code - 128,
                                      j.kind == Job::Kind::run && holds_checkpoint(j.dir) ? "checkpoint" : "start",
                                      restarts_[k], max_restarts));
      } else {
        fail(j, log_tail(log_of(j), 3), code);
      }
    }
  }

  void record_cost(const Job& j) {
    if (j.kind != Job::Kind::run) return;
    if (const auto c = run_cost(j.dir)) {
      cost_[j.group].first += c->first;
      cost_[j.group].second += c->second;
    }
  }

  void fail(const Job& j, const std::string& why, int code) {
    nlohmann::json f = {{"id", j.id}, {"dir", j.rel_dir}, {"log", j.rel_dir + "/" + log_of(j).filename().string()},
                        {"exit_code", code}, {"message", why}};
    result_.failures.push_back(f);
    progress_.message(fmt::format("{} {} failed ({}): {}", j.kind == Job::Kind::prepare ? "sample" : "run", j.id,
                                  code >= 0 ? fmt::format("exit code {}", code) : "not started", why));
  }

  // Seconds left: remaining steps at each sample's measured time per step, over the processes.
  std::string eta() const {
    double all_wall = 0, all_steps = 0;
    for (const auto& [g, c] : cost_) all_wall += c.first, all_steps += c.second;
    if (all_steps <= 0) return "";
    const auto per_step = [&](std::size_t g) {
      const auto it = cost_.find(g);
      return it != cost_.end() && it->second.second > 0 ? it->second.first / it->second.second : all_wall / all_steps;
    };
    double left = 0;
    std::size_t waiting = 0;
    for (std::size_t k = next_; k < jobs_.size(); ++k)
      if (!done_before_[k]) left += jobs_[k].expected_steps * per_step(jobs_[k].group), ++waiting;
    const auto now = clock::now();
    for (const auto& r : running_) {
      const double elapsed = std::chrono::duration<double>(now - r.start).count();
      left += std::max(0.0, jobs_[r.job].expected_steps * per_step(jobs_[r.job].group) - elapsed);
    }
    const double width = double(std::min<std::size_t>(parallel_, running_.size() + waiting));
    return fmt::format(", ETA {}", format_duration(left / std::max(1.0, width)));
  }

  void show() {
    const double elapsed = std::chrono::duration<double>(clock::now() - t0_).count();
    std::string counts = fmt::format("{} {}/{} done, {} running", what_, done_, jobs_.size(), running_.size());
    if (!result_.failures.empty()) counts += fmt::format(", {} failed", result_.failures.size());
    const bool runs = !jobs_.empty() && jobs_.front().kind == Job::Kind::run;
    progress_.show(counts, fmt::format(", {} elapsed", format_duration(elapsed)) + (runs ? eta() : ""));
  }

  const std::vector<Job>& jobs_;
  const std::string what_;
  const std::size_t parallel_;
  const Launcher& launcher_;
  StudyProgress& progress_;
  PoolResult result_;
  std::vector<Running> running_;
  std::map<std::size_t, std::pair<double, double>> cost_;  // group -> (wall s, steps) of finished runs
  std::size_t next_ = 0, done_ = 0;
  bool forwarded_ = false;
  std::vector<std::size_t> again_;  // jobs to continue (stopped by a signal the study did not send)
  std::map<std::size_t, int> restarts_;
  const clock::time_point t0_ = clock::now();
  std::vector<char> done_before_;  // finished before this pool: counted, timed, skipped
};

PoolResult run_pool(const std::vector<Job>& jobs, const std::string& what, int parallel, const Launcher& launcher,
                    StudyProgress& progress) {
  return Pool(jobs, what, parallel, launcher, progress).run();
}

// ---------------------------------------------------------------------------------------------
// MPI: only `qsdem study` under mpirun; ranks share the samples, then the runs, by index % size.

struct Mpi {
  bool active = false;
  int rank = 0;
  int size = 1;
};

Mpi mpi_start() {
  Mpi m;
  // mpirun sets OMPI_COMM_WORLD_SIZE; srun --mpi=pmix sets PMIX_RANK.
  if (!std::getenv("OMPI_COMM_WORLD_SIZE") && !std::getenv("PMIX_RANK")) return m;
  MPI_Init(nullptr, nullptr);
  MPI_Comm_rank(MPI_COMM_WORLD, &m.rank);
  MPI_Comm_size(MPI_COMM_WORLD, &m.size);
  m.active = true;
  return m;
}

// A barrier that sleeps instead of spinning (MPI_Barrier would take a core from the other ranks'
// children) and gives up on SIGINT/SIGTERM. Returns false when interrupted.
bool mpi_wait_all(const Mpi& m) {
  if (!m.active) return true;
  MPI_Request req;
  MPI_Ibarrier(MPI_COMM_WORLD, &req);
  for (;;) {
    int flag = 0;
    MPI_Test(&req, &flag, MPI_STATUS_IGNORE);
    if (flag) return true;
    if (StopSignals::received() != 0) return false;
    ::usleep(20'000);
  }
}

int mpi_bcast(const Mpi& m, int value) {
  if (m.active) MPI_Bcast(&value, 1, MPI_INT, 0, MPI_COMM_WORLD);
  return value;
}

// Rank 0 receives the failures of every rank.
nlohmann::json mpi_gather_failures(const Mpi& m, const nlohmann::json& mine) {
  if (!m.active) return mine;
  const std::string text = json_text(mine, -1);
  int len = static_cast<int>(text.size());
  std::vector<int> lens(std::size_t(m.size)), offsets(std::size_t(m.size));
  MPI_Gather(&len, 1, MPI_INT, lens.data(), 1, MPI_INT, 0, MPI_COMM_WORLD);
  std::string all;
  if (m.rank == 0) {
    int total = 0;
    for (int r = 0; r < m.size; ++r) offsets[std::size_t(r)] = total, total += lens[std::size_t(r)];
    all.resize(std::size_t(total));
  }
  MPI_Gatherv(text.data(), len, MPI_CHAR, all.data(), lens.data(), offsets.data(), MPI_CHAR, 0, MPI_COMM_WORLD);
  nlohmann::json out = nlohmann::json::array();
  if (m.rank == 0)
    for (int r = 0; r < m.size; ++r)
      for (const auto& f : nlohmann::json::parse(all.substr(std::size_t(offsets[std::size_t(r)]), std::size_t(lens[std::size_t(r)]))))
        out.push_back(f);
  return out;
}

// ---------------------------------------------------------------------------------------------

constexpr const char* lock_file = ".study.lock";

// The recorded manifest of DIR (study.json), or null.
nlohmann::json recorded_manifest(const fs::path& out) {
  try {
    return nlohmann::json::parse(read_bytes(out / "study.json"));
  } catch (const std::exception&) {
    return nullptr;
  }
}

// Refuses to continue a study whose case files or prepared samples changed since they were
// recorded in study.json: its runs would mix two cases in one analysis. A sample that is gone with
// its directory's prepared sample (a study kept without its samples) passes: it is prepared again,
// and this check, run again after the preparation, compares the new packing with the recorded one.
void check_recorded(const Study& study, const fs::path& out, const nlohmann::json& recorded) {
  if (!recorded.is_object() || !recorded.contains("samples")) return;
  for (const auto& old : recorded["samples"]) {
    const auto dir = old.value("dir", std::string());
    const auto it = std::find_if(study.samples.begin(), study.samples.end(), [&](const StudySample& s) { return s.dir == dir; });
    if (it == study.samples.end()) continue;
    if (old.contains("case_fnv1a64") && old["case_fnv1a64"] != it->case_hash)
      throw InputError(fmt::format(
          "the case file '{}' of sample '{}' changed since this study recorded it in '{}' (FNV-1a {} then, {} now): "
          "its runs would mix two cases. Restore the file, or start the changed study in another --out",
          it->case_file.string(), it->name, (out / "study.json").string(), old["case_fnv1a64"].get<std::string>(),
          it->case_hash));
    if (old.contains("compacted_fnv1a64") && fs::exists(out / dir / prepared_sample_file)) {
      const fs::path file = out / dir / "compacted.packing";
      const std::string now = fs::exists(file) ? file_fnv1a64(file) : "none (the file is gone)";
      if (now != old["compacted_fnv1a64"])
        throw InputError(fmt::format(
            "the prepared sample '{}' changed since this study recorded it in '{}' (FNV-1a {} then, {} now): the "
            "runs sheared so far used the other one. Start the study anew in another --out",
            file.string(), (out / "study.json").string(), old["compacted_fnv1a64"].get<std::string>(), now));
    }
  }
}

// The manifest with the recorded hashes of the prepared samples kept, and the builds that have
// worked on the study (build_record), this one last when it is new.
nlohmann::ordered_json manifest_keeping(const Study& study, const nlohmann::json& recorded) {
  nlohmann::ordered_json m = study_manifest(study);
  m["builds"] = nlohmann::ordered_json::array();
  const auto ordered = [](const nlohmann::json& j) { return nlohmann::ordered_json::parse(j.dump()); };
  if (recorded.is_object() && recorded.contains("builds") && recorded["builds"].is_array())
    for (const auto& b : recorded["builds"]) m["builds"].push_back(ordered(b));
  const nlohmann::ordered_json self = ordered(build_record());
  if (std::find(m["builds"].begin(), m["builds"].end(), self) == m["builds"].end()) m["builds"].push_back(self);
  if (recorded.is_object() && recorded.contains("samples"))
    for (auto& smp : m["samples"])
      for (const auto& old : recorded["samples"])
        if (old.value("dir", std::string()) == smp["dir"] && old.contains("compacted_fnv1a64"))
          smp["compacted_fnv1a64"] = old["compacted_fnv1a64"];
  return m;
}

// Creates DIR with study.toml and study.json, or checks that DIR holds this very study, or one
// the study file only adds runs to (growth_refusal), with the same case files and prepared
// samples. Takes the lock on DIR first (two studies started at once: the second is told so) and
// holds it, in `lock`, for the life of the study: two studies in one directory would run the same
// runs twice at once.
void setup_directory(Study& study, const fs::path& out, std::optional<DirectoryLock>& lock) {
  std::error_code ec;
  fs::create_directories(out, ec);
  if (ec) throw InputError(fmt::format("cannot create the study directory '{}': {}", out.string(), ec.message()));
  const bool had_lock_file = fs::exists(out / lock_file);
  lock.emplace(out, lock_file,
               fmt::format("another `qsdem study` is working in '{}' (it holds {}): wait for it or stop it",
                           out.string(), (out / lock_file).string()));
  const fs::path copy = out / "study.toml";
  const bool empty = std::all_of(fs::directory_iterator(out), fs::directory_iterator(),
                                 [](const fs::directory_entry& e) { return e.path().filename() == lock_file; });
  const auto refuse = [&](const std::string& why) {
    if (!had_lock_file) fs::remove(out / lock_file, ec);  // leave a foreign directory as it was
    lock.reset();
    throw InputError(why);
  };
  const bool has_copy = fs::exists(copy);
  const std::string copied = has_copy ? read_bytes(copy) : std::string();
  const nlohmann::json recorded = recorded_manifest(out);
  // Other values may only add runs (a study grows): every run DIR holds stays defined as it was.
  std::optional<Study> held;
  if (has_copy && !same_study_values(copied, study.text)) {
    std::string why;
    try {
      held = load_study_text(copied, study.file);
      adopt_recorded_picks(*held, recorded);
      adopt_recorded_picks(study, recorded);
      why = growth_refusal(*held, study);
    } catch (const InputError& e) {
      why = fmt::format("the study it holds cannot be read beside it: {}", e.what());
    }
    if (!why.empty())
      refuse(fmt::format(
          "'{}' holds another study: '{}' does not only add runs to it: {}. Continue a study with a file that keeps "
          "its name, [analysis], samples and runs as they are and adds others (comments, layout and [execution] may "
          "change), or choose another --out",
          out.string(), study.file.string(), why));
  } else if (!has_copy && !empty) {
    refuse(fmt::format("'{}' is not empty and holds no study.toml: choose a new or empty --out directory", out.string()));
  }
  check_recorded(study, out, recorded);
  adopt_recorded_picks(study, recorded);
  if (held) {
    const std::string samples = study.samples.size() > held->samples.size()
                                    ? plural(study.samples.size() - held->samples.size(), "sample") + " and "
                                    : "";
    fmt::print(stderr, "qsdem: the study in '{}' grows by {}{} ({} kept): its study.toml and study.json now hold the "
                       "design of '{}'\n",
               out.string(), samples, plural(study.runs.size() - held->runs.size(), "run"), held->runs.size(),
               study.file.string());
  }
  if (!has_copy || copied != study.text) write_file_atomic(copy, study.text);  // new, or new comments
  write_case_copies(study, out);
  write_file_atomic(out / "study.json", json_text(manifest_keeping(study, recorded)) + "\n");
}

// Records the FNV-1a of every prepared sample's compacted.packing not yet recorded in study.json
// (and checks the others again: a sample prepared anew meanwhile, with other settings, is
// refused). The packing, not sample.qsck: the engine writes it bit-identically for the same
// sample, while a checkpoint holds wall times.
void record_samples(const Study& study, const fs::path& out) {
  const nlohmann::json recorded = recorded_manifest(out);
  check_recorded(study, out, recorded);
  nlohmann::ordered_json m = manifest_keeping(study, recorded);
  for (auto& smp : m["samples"]) {
    const fs::path dir = out / smp["dir"].get<std::string>();
    const fs::path file = dir / "compacted.packing";
    if (!smp.contains("compacted_fnv1a64") && fs::exists(dir / prepared_sample_file) && fs::exists(dir / "summary.json"))
      smp["compacted_fnv1a64"] = file_fnv1a64(file);
  }
  write_file_atomic(out / "study.json", json_text(m) + "\n");
}

std::vector<Job> sample_jobs(const Study& study, const fs::path& out) {
  std::vector<Job> jobs;
  for (std::size_t k = 0; k < study.samples.size(); ++k) {
    const StudySample& smp = study.samples[k];
    Job j;
    j.kind = Job::Kind::prepare;
    j.id = fs::path(smp.dir).filename().string();
    j.rel_dir = smp.dir;
    j.study_dir = out;
    j.dir = out / smp.dir;
    j.threads = study.threads_per_run;
    j.fresh = {"prepare", case_copy(out, smp).string()};
    for (const auto& s : smp.sets) j.fresh.insert(j.fresh.end(), {"--set", s});
    // A relative sample.from of the case file is relative to the file, not to its copy.
    if (!smp.from.empty()) j.fresh.insert(j.fresh.end(), {"--set", "sample.from=" + smp.from});
    j.fresh.insert(j.fresh.end(), {"--out", j.dir.string(), "--threads", std::to_string(j.threads), "--quiet", "--force"});
    j.group = k;
    jobs.push_back(std::move(j));
  }
  return jobs;
}

// The runs of the stages of one level.
std::vector<Job> run_jobs(const Study& study, const fs::path& out, int level, const std::vector<std::string>& only) {
  std::vector<Job> jobs;
  for (const StudyRun& run : study.runs) {
    if (study.stages[run.stage].level != level) continue;
    if (!only.empty() && std::find(only.begin(), only.end(), study.stages[run.stage].name) == only.end()) continue;
    const StudySample& smp = study.samples[run.sample];
    Job j;
    j.id = run.id;
    j.rel_dir = run.dir;
    j.study_dir = out;
    j.dir = out / run.dir;
    j.needs = out / smp.dir;
    j.threads = study.threads_per_run;
    j.fresh = {"run", case_copy(out, smp).string(), "--set", "sample.from=" + j.needs.string()};
    for (const auto& s : run.sets) j.fresh.insert(j.fresh.end(), {"--set", s});
    // The study's report draws its runs; a page per run would cost each of them a second or two.
    j.fresh.insert(j.fresh.end(),
                   {"--out", j.dir.string(), "--threads", std::to_string(j.threads), "--quiet", "--force", "--no-plot"});
    j.expected_steps = steps_left(j.dir, run.expected_steps);
    j.group = run.sample;
    jobs.push_back(std::move(j));
  }
  return jobs;
}

// This rank's share (index % size), longest first so that the last runs of the pool are short, or
// shortest first (Study::shortest_first).
std::vector<Job> share(std::vector<Job> jobs, const Mpi& m, bool shortest_first = false) {
  std::vector<Job> mine;
  for (std::size_t k = 0; k < jobs.size(); ++k)
    if (int(k % std::size_t(m.size)) == m.rank) mine.push_back(std::move(jobs[k]));
  std::stable_sort(mine.begin(), mine.end(), [shortest_first](const Job& a, const Job& b) {
    return shortest_first ? a.expected_steps < b.expected_steps : a.expected_steps > b.expected_steps;
  });
  return mine;
}

int interrupted(const Mpi& m, int sig, const StudyOptions& options, const std::string& study_file) {
  const std::string again = !options.again.empty()
                                ? options.again
                                : fmt::format("qsdem study {} --out {}", study_file, options.out.string());
  std::fprintf(stderr, "qsdem: study stopped by %s; the running children wrote checkpoints. `%s` "
                       "again continues it (finished runs are kept)\n",
               sig == SIGINT ? "SIGINT" : "SIGTERM", again.c_str());
  // No MPI_Finalize: the other ranks may be busy; mpirun ends them when this rank exits.
  (void)m;
  return 128 + sig;
}

std::string ratios_text(const std::vector<double>& v) {
  std::string s;
  for (double x : v) s += fmt::format("{}{:g} %", s.empty() ? "" : ", ", 100 * x);
  return s.empty() ? "none" : s;
}

// Picks the damping ratios of the stages of `level` from their source stages, which have run:
// records the picks in study.json and adds their runs. A (sample, model) picked before keeps its
// ratios (its runs may exist); a source optimum that now gives others is reported, and flagged by
// the analysis. Returns the failures: the (sample, model) pairs without an optimum to pick.
nlohmann::json pick_level(Study& study, const fs::path& out, int level, StudyProgress& progress) {
  nlohmann::json failures = nlohmann::json::array();
  for (std::size_t k = 0; k < study.stages.size(); ++k) {
    StudyStage& st = study.stages[k];
    if (st.level != level || st.pick.empty()) continue;
    const std::string source = study.stages[st.from].name;
    const std::vector<StageOptimum> optima = stage_optima(out, study_manifest(study), source, st.at_rate);
    for (std::size_t smp : st.samples)
      for (std::size_t m : st.models) {
        const std::string& sample = study.sample_names[smp];
        const std::string& model = study.models[m].label;
        const auto o = std::find_if(optima.begin(), optima.end(),
                                    [&](const StageOptimum& x) { return x.sample == sample && x.model == model; });
        const std::vector<double> ratios = o != optima.end() ? pick_ratios(*o, st.pick, st.digits) : std::vector<double>{};
        const auto rec = std::find_if(st.picks.begin(), st.picks.end(),
                                      [&](const StudyPick& p) { return p.sample == sample && p.model == model; });
        if (rec != st.picks.end()) {
          if (ratios != rec->ratios)
            progress.message(fmt::format(
                "stage {}: the optimum of stage {} for {} {} now gives {} (picked before: {}); the stage keeps the "
                "ratios its runs were made with, and the report flags the change",
                st.name, source, sample, model, ratios_text(ratios), ratios_text(rec->ratios)));
        } else if (ratios.empty()) {
          const std::string why = fmt::format("no optimum of stage {} for {} {}: none of its runs finished", source,
                                              sample, model);
          failures.push_back({{"id", fmt::format("stage {}: {} {}", st.name, sample, model)},
                              {"dir", ""}, {"log", ""}, {"exit_code", -1}, {"message", why}});
          progress.message(fmt::format("stage {}: {} {} not started: {}", st.name, sample, model, why));
        } else {
          st.picks.push_back({sample, model, o->xi_opt, o->method, o->runs_used, ratios});
          progress.note(fmt::format("stage {}: {} {}: {} of stage {} ({}: ξopt = {:.4g} %)", st.name, sample, model,
                                       ratios_text(ratios), source, o->method, 100 * o->xi_opt));
        }
      }
    add_stage_runs(study, k);
  }
  write_file_atomic(out / "study.json", json_text(manifest_keeping(study, recorded_manifest(out))) + "\n");
  return failures;
}

int max_level(const Study& study) {
  int level = 0;
  for (const StudyStage& st : study.stages) level = std::max(level, st.level);
  return level;
}

std::string level_label(const Study& study, int level) {
  if (!study.staged) return "runs";
  std::string names;
  for (const StudyStage& st : study.stages)
    if (st.level == level) names += (names.empty() ? "" : ", ") + st.name;
  return "runs of stage " + names + ":";
}

// Writes failures.json (or removes an old one) and analyses the directory. Returns 0 or 3.
int finish_study(const Study& study, const fs::path& out, nlohmann::json failures, bool quiet) {
  int code = 0;
  std::sort(failures.begin(), failures.end(),
            [](const auto& a, const auto& b) { return a["id"].template get<std::string>() < b["id"].template get<std::string>(); });
  const fs::path failures_file = out / "failures.json";
  if (failures.empty()) {
    fs::remove(failures_file);
  } else {
    write_file_atomic(failures_file, json_text(failures) + "\n");
    std::fprintf(stderr, "qsdem: %zu of %zu samples and runs failed (listed in %s, logs in their directories); "
                         "the analysis uses the runs that finished\n",
                 failures.size(), study.samples.size() + study.runs.size(), failures_file.string().c_str());
    code = 3;
  }
  try {
    analyze_study(out);
    if (!quiet) std::fprintf(stderr, "qsdem: analysis written to %s/analysis/\n", out.string().c_str());
  } catch (const std::exception& e) {
    std::fprintf(stderr, "qsdem: analysis failed: %s\n", e.what());
    code = 3;
  }
  if (!quiet)
    std::printf("study %s: %zu runs, %zu failed; results in %s\n", study.name.c_str(), study.runs.size(),
                failures.size(), out.string().c_str());
  return code;
}

int study_main(const fs::path& study_file, const StudyOptions& options, const Mpi& mpi) {
  Study study;
  const fs::path out = fs::absolute(options.out);
  try {
    require_utf8(out.string(), "--out");  // analysis.json names it
    study = load_study(study_file);
  } catch (const InputError& e) {
    if (mpi.rank == 0) std::fprintf(stderr, "qsdem: input error: %s\n", e.what());
    return 2;
  }
  if (options.parallel > 0) study.parallel_runs = options.parallel;
  if (!options.order.empty()) study.shortest_first = options.order == "shortest_first";

  // Rank 0 sets the directory up; the others wait for its verdict, then read the picks it kept.
  int status = 0;
  std::optional<DirectoryLock> lock;  // rank 0's, for the life of the study
  const auto on_rank0 = [&](const auto& work) {
    if (mpi.rank == 0) {
      try {
        work();
      } catch (const InputError& e) {
        std::fprintf(stderr, "qsdem: input error: %s\n", e.what());
        status = 2;
      } catch (const std::exception& e) {
        std::fprintf(stderr, "qsdem: error: %s\n", e.what());
        status = 3;
      }
    }
    status = mpi_bcast(mpi, status);
    if (status == 0 && mpi.rank != 0) adopt_recorded_picks(study, recorded_manifest(out));
    return status;
  };
  if (on_rank0([&] { setup_directory(study, out, lock); }) != 0) return status;

  const StopSignals signals;
  const Launcher launcher = make_launcher(options.executable);
  StudyProgress progress(options.quiet, mpi.active ? fmt::format("[rank {}/{}] ", mpi.rank, mpi.size) : "");
  if (!options.quiet && mpi.rank == 0)
    std::fprintf(stderr, "qsdem study %s: %s, %s%s, %s x %s%s -> %s\n", study.name.c_str(),
                 plural(study.samples.size(), "sample").c_str(), plural(study.runs.size(), "run").c_str(),
                 study.staged ? fmt::format(" in {} (a stage that picks its ratios adds its runs when it starts)",
                                            plural(study.stages.size(), "stage")).c_str()
                              : "",
                 plural(std::size_t(study.parallel_runs), "process", "processes").c_str(),
                 plural(std::size_t(study.threads_per_run), "thread").c_str(),
                 mpi.active ? fmt::format(" on each of {} MPI ranks", mpi.size).c_str() : "", out.string().c_str());

  nlohmann::json failures = nlohmann::json::array();
  PoolResult r = run_pool(share(sample_jobs(study, out), mpi), "samples", study.parallel_runs, launcher, progress);
  failures.insert(failures.end(), r.failures.begin(), r.failures.end());
  if (r.signal != 0) return interrupted(mpi, r.signal, options, study_file.string());
  if (!mpi_wait_all(mpi)) return interrupted(mpi, StopSignals::received(), options, study_file.string());
  if (on_rank0([&] { record_samples(study, out); }) != 0) return status;

  // The stages, level by level: a stage that picks its ratios starts when its source has run and
  // the study directory has been analysed.
  for (int level = 0; level <= max_level(study); ++level) {
    if (level > 0) {
      nlohmann::json picked;
      const auto pick = [&] {
        try {
          analyze_study(out);
        } catch (const std::exception& e) {
          progress.message(fmt::format("the analysis before the next stage failed (the stage goes on): {}", e.what()));
        }
        picked = pick_level(study, out, level, progress);
      };
      if (on_rank0(pick) != 0) return status;
      failures.insert(failures.end(), picked.begin(), picked.end());
    }
    r = run_pool(share(run_jobs(study, out, level, options.stages), mpi, study.shortest_first), level_label(study, level), study.parallel_runs, launcher,
                 progress);
    failures.insert(failures.end(), r.failures.begin(), r.failures.end());
    if (r.signal != 0) return interrupted(mpi, r.signal, options, study_file.string());
    if (!mpi_wait_all(mpi)) return interrupted(mpi, StopSignals::received(), options, study_file.string());
  }

  failures = mpi_gather_failures(mpi, failures);
  const int code = mpi.rank == 0 ? finish_study(study, out, failures, options.quiet) : 0;
  return std::max(code, mpi_bcast(mpi, code));
}

}  // namespace

int run_study(const fs::path& study_file, const StudyOptions& options) {
  return run_study_rounds(study_file, options, [&](int round) {
    return round == 0 ? std::optional(options.stages) : std::nullopt;
  });
}

int run_study_rounds(const fs::path& study_file, const StudyOptions& options,
                     const std::function<std::optional<std::vector<std::string>>(int round)>& next) {
  const Mpi mpi = mpi_start();
  int code = 0;
  for (int round = 0;; ++round) {
    const std::optional<std::vector<std::string>> stages = next(round);
    if (!stages) break;
    StudyOptions o = options;
    o.stages = *stages;
    code = study_main(study_file, o, mpi);
    if (code != 0) break;
  }
  if (mpi.active && code < 128) MPI_Finalize();
  return code;
}

}  // namespace qsdem
