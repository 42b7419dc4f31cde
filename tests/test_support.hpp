// Helpers the process-level tests share: read a file whole, start the CLI with its output in
// files, wait for it. Header-only, tests only.
#pragma once
#include <fcntl.h>
#include <spawn.h>
#include <sys/wait.h>
#include <omp.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

namespace qsdem_test {

inline std::string slurp(const std::filesystem::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
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
