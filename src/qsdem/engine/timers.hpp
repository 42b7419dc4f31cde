// Wall time per pipeline stage (Cabana-style), printed as a table at the end of every run.
#pragma once
#include <array>
#include <chrono>
#include <string>

namespace qsdem {

// integrate: the kick and the drift's translation (one pass, integrate_velocities); advance: the
// ellipsoids' turn (turn_orientations).
enum class Stage { neighbor, contact_forces, gather, integrate, servo, advance, measures, output, count };

inline constexpr std::array<const char*, static_cast<std::size_t>(Stage::count)> stage_names{
    "neighbor (broad phase)", "contact forces", "gather resultants", "integrate velocities",
    "servo (cell control)", "advance positions", "measures", "output"};

struct StageTimers {
  std::array<double, static_cast<std::size_t>(Stage::count)> seconds{};
  // The force stage's threads (when it runs on several): summed over steps, the mean and the
  // largest time a thread spent on its blocks. mean / max is the stage's load balance.
  double force_thread_mean = 0, force_thread_max = 0;
  double total() const {
    double t = 0;
    for (double s : seconds) t += s;
    return t;
  }
};

class ScopedStage {
 public:
  ScopedStage(StageTimers& t, Stage s) : timers_(t), stage_(s), start_(std::chrono::steady_clock::now()) {}
  ~ScopedStage() {
    timers_.seconds[static_cast<std::size_t>(stage_)] +=
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start_).count();
  }
  ScopedStage(const ScopedStage&) = delete;
  ScopedStage& operator=(const ScopedStage&) = delete;

 private:
  StageTimers& timers_;
  Stage stage_;
  std::chrono::steady_clock::time_point start_;
};

// A plain-text table: stage, seconds, share, microseconds per step.
std::string format_stage_table(const StageTimers& t, long steps);

}  // namespace qsdem
