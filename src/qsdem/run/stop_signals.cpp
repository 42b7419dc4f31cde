#include "qsdem/run/stop_signals.hpp"

namespace qsdem {
namespace {
volatile std::sig_atomic_t caught = 0;
extern "C" void on_stop_signal(int sig) { caught = sig; }
}  // namespace

StopSignals::StopSignals() {
  caught = 0;
  struct sigaction sa {};
  sa.sa_handler = on_stop_signal;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGINT, &sa, &old_int_);
  sigaction(SIGTERM, &sa, &old_term_);
}

StopSignals::~StopSignals() {
  sigaction(SIGINT, &old_int_, nullptr);
  sigaction(SIGTERM, &old_term_, nullptr);
}

int StopSignals::received() { return caught; }

const char* signal_name(int sig) { return sig == SIGINT ? "SIGINT" : "SIGTERM"; }

}  // namespace qsdem
