// Fuzz target: a prepared sample (sample.qsck) as a run with `sample.from` takes it: read, taken on
// by the case it was prepared with (prepared_sample), held to the cell's size rule as a new run's
// sample is (SPEC 3), and sheared for a few steps. The seeds are samples of small runs
// (fuzz/corpus/sample).
#include "loaders.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  qsdem_fuzz::with_checkpoint(data, size, [](qsdem::Checkpoint& c) {
    const qsdem::Params params = qsdem::parse_case(c.case_text, c.case_source);
    qsdem::RunProgress run;
    qsdem::State st = qsdem::prepared_sample(std::move(c), params, "fuzz", run);
    qsdem::check_cell_size(st.particles, st.cell, qsdem::compaction_model(params, st).skin);
    qsdem_fuzz::step_a_few(params, st, run);
  });
  return 0;
}
