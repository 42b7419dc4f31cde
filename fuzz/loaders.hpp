// What the loaders' fuzz targets share: a checkpoint file's bytes read past their checksum and
// length (Seal::ignore), so that a mutation reaches the reader and its checks, and a few steps of
// whatever they accept, as a run takes them. An input must end in an InputError or a RunError (a
// refusal, a blow-up) or in a state that steps: never in a crash or an AddressSanitizer report.
#pragma once
#include <omp.h>

#include <cstddef>
#include <cstdint>
#include <string_view>

#include "qsdem/engine/neighbor.hpp"
#include "qsdem/run/checkpoint.hpp"
#include "qsdem/run/protocol.hpp"

namespace qsdem_fuzz {

struct Stepped {};  // thrown by the hook: enough steps

// Three steps of the run's current phase (none once every phase is done), writing no rows.
inline void step_a_few(const qsdem::Params& params, qsdem::State& st, qsdem::RunProgress& run) {
  if (static_cast<std::size_t>(run.phase) >= params.protocol.size()) return;
  qsdem::Progress quiet(qsdem::Progress::Mode::quiet);
  int steps = 0;
  try {
    qsdem::run_phase(params, st, run, {}, quiet, [&](bool) {
      if (++steps == 3) throw Stepped{};
    });
  } catch (const Stepped&) {
  }
}

// `run` is called with the checkpoint the input holds; refusals are expected.
template <class Run>
void with_checkpoint(const std::uint8_t* data, std::size_t size, Run&& run) {
  static const bool one_thread = [] {
    omp_set_num_threads(1);
    return true;
  }();
  (void)one_thread;
  try {
    qsdem::Checkpoint c = qsdem::parse_checkpoint({reinterpret_cast<const char*>(data), size}, "fuzz.qsck",
                                                  qsdem::Seal::ignore);
    run(c);
  } catch (const qsdem::InputError&) {
  } catch (const qsdem::RunError&) {
  }
}

}  // namespace qsdem_fuzz
