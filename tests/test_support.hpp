// Helpers the process-level tests share: read a file whole or as CSV, start the CLI with its output
// in files, wait for it. Header-only, tests only.
#pragma once
#include <fcntl.h>
#include <gtest/gtest.h>
#include <spawn.h>
#include <sys/wait.h>
#include <omp.h>
#include <unistd.h>

#include <chrono>
#include <csignal>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

namespace qsdem_test {

// The small cases of the process-level tests, as TOML text that a test extends with its own tables.
// Their material, that of the examples.
inline const std::string small_case_material = R"([material]
density = "2650 kg/m^3"
young_modulus = "78 GPa"
poisson_ratio = 0.3
)";

// 200 spheres of 2 and 2.4 mm (150 + 50), seed 3: the name, material and sample tables.
inline std::string sample_200(const std::string& name) {
  return "name = \"" + name + "\"\n" + small_case_material + R"([sample]
seed = 3
[[sample.particles]]
diameter = "2 mm"
count = 150
[[sample.particles]]
diameter = "2.4 mm"
count = 50
)";
}

// 120 spheres of 2.0 and 2.4 mm (60 + 60), seed 1, nd 0.5 %, eps' = 1.25e-4 to 1 % axial strain:
// exactly 250 steps of c_t eps' = 4e-5, sampled every 25 steps (10 rows); about 15000 compaction
// steps, ~1 s.
inline std::string tiny_case(const std::string& name) {
  return "name = \"" + name + "\"\n" + small_case_material + R"([sample]
seed = 1
initial_solid_fraction = 0.2
[[sample.particles]]
diameter = "2.4 mm"
count = 60
[[sample.particles]]
diameter = "2.0 mm"
count = 60
[damping]
model = "nd"
ratio = "0.5 %"
[compaction]
max_strain_rate = 1e-3
[triaxial]
strain_rate = 1.25e-4
final_axial_strain = "1 %"
sample_points = 10
)";
}

inline std::string slurp(const std::filesystem::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

// The lines of a file (a CSV file's rows and its header).
inline long lines(const std::filesystem::path& p) {
  std::ifstream in(p);
  long n = 0;
  for (std::string l; std::getline(in, l);) ++n;
  return n;
}

// A CSV file as a run writes it: the header and the rows, cells as text (a `phase` column is text).
struct Csv {
  std::vector<std::string> header;
  std::vector<std::vector<std::string>> rows;
  // Whether the header has column `name` (columns may be appended: never test a position).
  bool has(const std::string& name) const {
    for (const auto& h : header)
      if (h == name) return true;
    return false;
  }
  // The index of column `name`; a test failure (and 0) when there is none.
  std::size_t col(const std::string& name) const {
    for (std::size_t k = 0; k < header.size(); ++k)
      if (header[k] == name) return k;
    ADD_FAILURE() << "no column " << name;
    return 0;
  }
  double at(std::size_t row, const std::string& name) const { return std::stod(rows.at(row).at(col(name))); }
  std::vector<double> column(const std::string& name) const {
    const std::size_t c = col(name);
    std::vector<double> v;
    for (const auto& r : rows) v.push_back(std::stod(r.at(c)));
    return v;
  }
};

inline Csv read_csv(const std::filesystem::path& p) {
  const auto split = [](const std::string& l) {
    std::vector<std::string> cells;
    std::stringstream s(l);
    for (std::string cell; std::getline(s, cell, ',');) cells.push_back(cell);
    return cells;
  };
  Csv t;
  std::istringstream in(slurp(p));
  std::string line;
  if (std::getline(in, line)) t.header = split(line);
  while (std::getline(in, line)) t.rows.push_back(split(line));
  return t;
}

// Starts `args` (args[0] looked up in PATH unless it holds a '/') with stdout and stderr in
// LOG.out and LOG.err. Returns the pid, or -1 when it could not be started.
inline pid_t spawn_logged(std::vector<std::string> args, const std::filesystem::path& log) {
  std::vector<char*> argv;
  for (auto& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  posix_spawn_file_actions_t fa;
  posix_spawn_file_actions_init(&fa);
  posix_spawn_file_actions_addopen(&fa, 1, (log.string() + ".out").c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  posix_spawn_file_actions_addopen(&fa, 2, (log.string() + ".err").c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  pid_t pid = -1;
  const int rc = posix_spawnp(&pid, args[0].c_str(), &fa, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&fa);
  return rc == 0 ? pid : -1;
}

// Exit code of a child; 128 + signal when a signal ended it, -1 when it cannot be waited for.
inline int wait_exit(pid_t pid) {
  int status = 0;
  if (pid <= 0 || ::waitpid(pid, &status, 0) != pid) return -1;
  if (WIFEXITED(status)) return WEXITSTATUS(status);
  if (WIFSIGNALED(status)) return 128 + WTERMSIG(status);
  return -1;
}

// A command's exit code and what it printed (spawn_logged's files next to `log`).
struct Cli {
  int code = -1;
  std::string out, err;
};

inline Cli finish(pid_t pid, const std::filesystem::path& log) {
  Cli c;
  c.code = wait_exit(pid);
  c.out = slurp(log.string() + ".out");
  c.err = slurp(log.string() + ".err");
  return c;
}

// wait_exit with a deadline: a child still running after `seconds` is killed (SIGKILL) and -2 is
// returned, so that a hang fails a test instead of stopping the suite.
inline int wait_exit_within(pid_t pid, double seconds) {
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
  while (pid > 0 && std::chrono::steady_clock::now() < deadline) {
    int status = 0;
    const pid_t r = ::waitpid(pid, &status, WNOHANG);
    if (r == pid) return WIFEXITED(status) ? WEXITSTATUS(status) : WIFSIGNALED(status) ? 128 + WTERMSIG(status) : -1;
    if (r < 0) return -1;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  if (pid > 0) {
    ::kill(pid, SIGKILL);
    ::waitpid(pid, nullptr, 0);
  }
  return -2;
}

// One thread for the scope. Tests of 1-5 particles: OpenMP fork/join per stage costs far more
// than the work and, on a loaded 2-core machine, a second thread waiting for a time slice can
// make 10^4 steps take tens of seconds. Physics does not depend on the thread count
// (deterministic block sums); the previous setting is restored.
struct SingleThread {
  int previous = omp_get_max_threads();
  SingleThread() { omp_set_num_threads(1); }
  ~SingleThread() { omp_set_num_threads(previous); }
  SingleThread(const SingleThread&) = delete;
  SingleThread& operator=(const SingleThread&) = delete;
};

}  // namespace qsdem_test
