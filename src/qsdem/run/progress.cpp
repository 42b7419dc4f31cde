#include "qsdem/run/progress.hpp"

#include <fmt/format.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>

namespace qsdem {

std::string format_duration(double s) {
  if (!std::isfinite(s) || s < 0) return "?";
  const long t = std::lround(s);
  if (t < 60) return fmt::format("{}s", t);
  if (t < 3600) return fmt::format("{}m{:02}s", t / 60, t % 60);
  if (t < 86400) return fmt::format("{}h{:02}m", t / 3600, (t % 3600) / 60);
  return fmt::format("{}d{:02}h", t / 86400, (t % 86400) / 3600);
}

Progress::Mode Progress::detect(bool quiet) {
  if (quiet) return Mode::quiet;
  return ::isatty(STDERR_FILENO) ? Mode::terminal : Mode::plain;
}

void Progress::begin(const std::string& phase, double total) {
  phase_ = phase;
  total_ = total;
  last_plain_percent_ = -1;
  start_ = last_print_ = std::chrono::steady_clock::now();
  last_width_ = 0;
}

void Progress::update(double done, const std::string& fields) {
  if (mode_ == Mode::quiet) return;
  const auto now = std::chrono::steady_clock::now();
  const double elapsed = std::chrono::duration<double>(now - start_).count();
  std::string line;
  if (total_ > 0) {
    const double frac = std::clamp(done / total_, 0.0, 1.0);
    const double eta = frac > 0 ? elapsed * (1 - frac) / frac : NAN;
    if (mode_ == Mode::plain) {
      // A line every 5 %, so that logs stay short.
      const double pct = std::floor(frac * 20) * 5;
      if (pct <= last_plain_percent_) return;
      last_plain_percent_ = pct;
    }
    line = fmt::format("{} {:5.1f}% | {:.0f} steps/s | {} elapsed | ETA {} | {}", phase_, 100 * frac,
                       elapsed > 0 ? done / elapsed : 0.0, format_duration(elapsed), format_duration(eta), fields);
  } else {
    if (mode_ == Mode::plain && std::chrono::duration<double>(now - last_print_).count() < 30) return;
    line = fmt::format("{} | {:.0f} steps/s | {} elapsed | {}", phase_, elapsed > 0 ? done / elapsed : 0.0,
                       format_duration(elapsed), fields);
  }
  if (mode_ == Mode::terminal) {
    if (std::chrono::duration<double>(now - last_print_).count() < 0.2) return;
    const std::size_t width = line.size();
    if (width < last_width_) line += std::string(last_width_ - width, ' ');
    last_width_ = width;
    std::fprintf(stderr, "\r%s", line.c_str());
  } else {
    std::fprintf(stderr, "%s\n", line.c_str());
  }
  std::fflush(stderr);
  last_print_ = now;
}

void Progress::end(const std::string& closing) {
  if (mode_ == Mode::quiet) return;
  if (mode_ == Mode::terminal)
    std::fprintf(stderr, "\r%-*s\n", static_cast<int>(last_width_), closing.c_str());
  else
    std::fprintf(stderr, "%s\n", closing.c_str());
  std::fflush(stderr);
}

}  // namespace qsdem
