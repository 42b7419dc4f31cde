// Fuzz target: a run's checkpoint (checkpoint.qsck) as `qsdem resume` takes it: read, checked against
// the case it holds, and stepped on in its current phase. The seeds are checkpoints of small runs
// (fuzz/corpus/checkpoint).
#include "loaders.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  qsdem_fuzz::with_checkpoint(data, size, [](qsdem::Checkpoint& c) {
    const qsdem::Params params = qsdem::parse_case(c.case_text, c.case_source);
    qsdem::check_checkpoint_case(c, params, "fuzz.qsck");
    qsdem_fuzz::step_a_few(params, c.state, c.run);
  });
  return 0;
}
