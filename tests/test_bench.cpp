// `qsdem bench` (bench.hpp bench_packing): the state it times is the state given, stepped as a
// run steps it (a checkpoint with its velocities and contact history), and its contact counts
// are those of that state.
#include <gtest/gtest.h>

#include <filesystem>

#include "qsdem/engine/measures.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/bench.hpp"
#include "qsdem/run/checkpoint.hpp"
#include "qsdem/run/packing_io.hpp"
#include "qsdem/run/protocol.hpp"
#include "qsdem/run/run_directory.hpp"
#include "test_support.hpp"

using namespace qsdem;
namespace fs = std::filesystem;

namespace {

const fs::path golden_sample = fs::path(QSDEM_SOURCE_DIR) / "tests" / "golden" / "format1-sample";

fs::path scratch(const std::string& name) {
  const fs::path d = fs::temp_directory_path() / ("qsdem-test-bench-" + name);
  fs::remove_all(d);
  fs::create_directories(d);
  return d;
}

// The model bench uses for a state in the triaxial phase: the case's, in a fixed cell.
Model fixed_cell_triaxial(const Params& params, State& st) {
  Model m = triaxial_model(params, st);
  for (auto& c : m.control) c = {};
  assign_damping(m, st.particles);
  return m;
}

long contacts_of_last_evaluation(const State& st) {
  long n = 0;
  for (double d : st.pairs.overlap) n += d > 0;
  return n;
}

// A prepared sample in the current checkpoint format, in motion: the golden 120-spheroid sample
// stepped 40 times (velocities and tangential history non-zero), saved as DIR/sample.qsck.
fs::path moving_sample(const std::string& name) {
  Checkpoint c = load_checkpoint(golden_sample / "sample.qsck");
  const Params params = parse_case(c.case_text, c.case_source);
  const Model m = fixed_cell_triaxial(params, c.state);
  for (int n = 0; n < 40; ++n) step(m, c.state);
  const fs::path dir = scratch(name);
  save_checkpoint(dir / prepared_sample_file, c.case_text, c.case_source, c.state, c.run);
  return dir;
}

}  // namespace

TEST(Bench, StepsACheckpointAsARunDoes) {
  const qsdem_test::SingleThread one;
  const fs::path dir = moving_sample("as-a-run");
  const nlohmann::json b = bench_packing(dir, "", {}, 30);
  EXPECT_EQ(b["source"], "checkpoint");
  EXPECT_EQ(b["phase"], "triaxial");

  // Reference: the restored state stepped 30 times, nothing else (no extra force evaluation,
  // which would add a step's tangential displacement to every contact's history).
  Checkpoint c = load_checkpoint(dir / prepared_sample_file);
  const Params params = parse_case(c.case_text, c.case_source);
  State& st = c.state;
  const Model m = fixed_cell_triaxial(params, st);
  ASSERT_GT(st.particles.v[0].norm() + st.particles.v[1].norm(), 0.0);  // the state moves
  step(m, st);
  const long first = contacts_of_last_evaluation(st);
  for (int n = 1; n < 30; ++n) step(m, st);
  const Measures ref = measure(st);
  ASSERT_GT(first, 50);
  EXPECT_EQ(b["contacts_start"].get<long>(), first);
  EXPECT_EQ(b["contacts_end"].get<long>(), ref.contacts);
  EXPECT_EQ(b["ekin_J"].get<double>(), ref.ekin_trans + ref.ekin_rot);  // same steps, same bits
  EXPECT_EQ(b["steps"].get<long>(), 30);
  EXPECT_EQ(b["particles"].get<long>(), 120);
  EXPECT_EQ(b["ellipsoids"].get<long>(), 120);
  EXPECT_GT(b["particle_steps_per_s"].get<double>(), 0.0);
  // 120 particles are within any cache: not prefetched, unless asked; the same bits either way.
  EXPECT_EQ(b["prefetch_j_ends"]["used"], false);
  EXPECT_EQ(b["prefetch_j_ends"]["engine_choice"], false);
  const nlohmann::json prefetched = bench_packing(dir, "", {}, 30, false, true);
  EXPECT_EQ(prefetched["prefetch_j_ends"]["used"], true);
  EXPECT_EQ(prefetched["prefetch_j_ends"]["engine_choice"], false);
  EXPECT_EQ(prefetched["ekin_J"].get<double>(), ref.ekin_trans + ref.ekin_rot);
}

TEST(Bench, APackingStartsAtRestWithoutHistory) {
  const qsdem_test::SingleThread one;
  const fs::path dir = scratch("packing");
  const Checkpoint c = load_checkpoint(golden_sample / "sample.qsck");
  write_packing(dir / "p.packing", c.state.particles, c.state.cell);
  const fs::path case_file = golden_sample / "case.toml";
  EXPECT_THROW(bench_packing(dir / "p.packing", "", {}, 5), InputError);  // a packing needs its case
  const nlohmann::json b = bench_packing(dir / "p.packing", case_file.string(), {}, 5);
  EXPECT_EQ(b["source"], "packing");
  // Reference: the packing read at rest, its forces evaluated (the list build), stepped.
  const Params params = load_case(case_file.string());
  State st = read_packing(dir / "p.packing", params.material.density);
  const Model m = fixed_cell_triaxial(params, st);
  evaluate_forces(m, st);
  const long at_rest = contacts_of_last_evaluation(st);
  step(m, st);
  EXPECT_EQ(b["contacts_start"].get<long>(), contacts_of_last_evaluation(st));
  EXPECT_EQ(b["contacts_start"].get<long>(), at_rest);  // at rest, the first step sees the packing's contacts
  for (int n = 1; n < 5; ++n) step(m, st);
  EXPECT_EQ(b["ekin_J"].get<double>(), measure(st).ekin_trans + measure(st).ekin_rot);
}

TEST(Bench, RefusesWhatItCannotStep) {
  const fs::path empty = scratch("empty");
  EXPECT_THROW(bench_packing(empty, "", {}, 5), InputError);                  // no checkpoint in DIR
  EXPECT_THROW(bench_packing(empty / "missing.packing", "", {}, 5), InputError);
  // A case whose material differs from the one the checkpoint's contacts were made with.
  const fs::path case_file = golden_sample / "case.toml";
  EXPECT_THROW(bench_packing(golden_sample, case_file.string(), {"material.young_modulus=70 GPa"}, 5), InputError);
  EXPECT_NO_THROW(bench_packing(golden_sample, case_file.string(), {"damping.model=none"}, 2));
}
