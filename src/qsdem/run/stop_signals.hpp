// SIGINT and SIGTERM caught while a StopSignals guard lives: a run checkpoints and stops, a study
// tells its children and waits for them (docs/runs.md). The old handlers come back after.
#pragma once
#include <csignal>

namespace qsdem {

class StopSignals {
 public:
  StopSignals();  // forgets any signal caught before
  ~StopSignals();
  StopSignals(const StopSignals&) = delete;
  StopSignals& operator=(const StopSignals&) = delete;

  // The signal caught since the guard was made (SIGINT or SIGTERM), else 0.
  static int received();

 private:
  struct sigaction old_int_ {}, old_term_ {};
};

const char* signal_name(int sig);  // "SIGINT" or "SIGTERM"

}  // namespace qsdem
