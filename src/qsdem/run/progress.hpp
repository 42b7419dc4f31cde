// Progress of a long run on stderr: on a terminal one line updated in place, otherwise a plain
// line every few percent; silent when quiet.
#pragma once
#include <chrono>
#include <string>

namespace qsdem {

class Progress {
 public:
  enum class Mode { quiet, terminal, plain };
  explicit Progress(Mode mode) : mode_(mode) {}
  static Mode detect(bool quiet);  // terminal if stderr is a tty

  // Starts a phase of `total` steps. total <= 0: no known end (no percent, no ETA).
  void begin(const std::string& phase, double total);
  // done: steps taken in the phase so far; fields: what to show after percent, rate and ETA.
  void update(double done, const std::string& fields);
  void end(const std::string& closing);

 private:
  Mode mode_;
  std::string phase_;
  double total_ = 0;
  double last_plain_percent_ = -1;
  std::chrono::steady_clock::time_point start_, last_print_;
  std::size_t last_width_ = 0;
};

std::string format_duration(double seconds);

}  // namespace qsdem
