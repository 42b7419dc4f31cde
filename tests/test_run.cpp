// A whole run (SPEC 8, 10): determinism (seed, thread count), the result files and the CLI.
#include <fcntl.h>
#include <fmt/format.h>
#include <gtest/gtest.h>
#include <omp.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <nlohmann/json.hpp>
#include <set>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include "qsdem/engine/forces.hpp"
#include "qsdem/engine/measures.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/generate.hpp"
#include "qsdem/run/grading.hpp"
#include "qsdem/run/protocol.hpp"
#include "qsdem/run/run.hpp"
#include "qsdem/version.hpp"
#include "test_support.hpp"

using namespace qsdem;
namespace fs = std::filesystem;

namespace {

// 120 spheres of 2.0 and 2.4 mm, eps' = 1.25e-4 to 1 % axial strain: exactly 250 steps of
// c_t eps' = 4e-5, sampled every 25 steps (10 rows). About 15000 compaction steps, ~1 s.
const std::string tiny_case = qsdem_test::tiny_case("run-tiny");

const std::string spec10_header =
    "step,time_s,e1,ev,s11_Pa,s22_Pa,s33_Pa,p_Pa,q_Pa,phi_deg,void_ratio,cn,ufr,iuf,imom,ekin_J,ekin_trans_J,"
    "ekin_rot_J";

class Threads {  // sets the OpenMP thread count for a scope
 public:
  explicit Threads(int n) : saved_(omp_get_max_threads()) { omp_set_num_threads(n); }
  ~Threads() { omp_set_num_threads(saved_); }
  Threads(const Threads&) = delete;
  Threads& operator=(const Threads&) = delete;

 private:
  int saved_;
};

fs::path fresh_dir(const std::string& name) {
  const fs::path dir = fs::temp_directory_path() / ("qsdem_run_" + name + "_" + std::to_string(::getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

using qsdem_test::slurp;

// Runs the tiny case (with extra overrides) on `threads` threads into a fresh directory.
fs::path run_tiny(const std::string& name, int threads, const std::vector<std::string>& overrides = {}) {
  Threads t(threads);
  const fs::path dir = fresh_dir(name);
  run_case(parse_case(tiny_case, "run-tiny.toml", overrides), {dir, true});
  return dir;
}

std::vector<std::string> split(const std::string& s, char sep) {
  std::vector<std::string> out;
  std::stringstream ss(s);
  for (std::string f; std::getline(ss, f, sep);) out.push_back(f);
  return out;
}

// Runs a shell command; returns its exit code, with stdout and stderr in files of `dir`.
int shell(const std::string& cmd, const fs::path& dir, std::string& out, std::string& err) {
  const fs::path o = dir / "stdout.txt", e = dir / "stderr.txt";
  const int status = std::system((cmd + " > '" + o.string() + "' 2> '" + e.string() + "'").c_str());
  out = slurp(o);
  err = slurp(e);
  return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

// 5000 spheres in a loose cell shrunk affinely from solid fraction 0.2 to 0.35 (pairs closer than
// 17 % of their distance now overlap), with friction and nd damping: several thousand contacts.
std::pair<State, Model> large_packing() {
  const Params params = parse_case(tiny_case, "run-tiny.toml",
                                   {"sample.particles.0.count=2500", "sample.particles.1.count=2500"});
  State start = generate_loose_sample(params);
  set_matrix(start.cell, std::cbrt(0.2 / 0.35) * start.cell.h);
  Model model = triaxial_model(params, start);  // friction 0.5, nd 0.5 %, in a fixed cell:
  model.control = {};
  assign_damping(model, start.particles);
  return {start, model};
}

// Particles whose position, velocity or angular momentum differ by any bit between a and b.
std::size_t particles_differing(const State& a, const State& b) {
  std::size_t differ = 0;
  for (std::size_t i = 0; i < a.particles.size(); ++i)
    if (a.particles.s[i] != b.particles.s[i] || a.particles.v[i] != b.particles.v[i] ||
        a.particles.angmom[i] != b.particles.angmom[i])
      ++differ;
  return differ;
}

const std::string binary = QSDEM_BINARY;

}  // namespace

// The same case and seed give byte-identical results (generation, compaction and shear are all
// deterministic); another seed gives another sample and so another series.
TEST(Run, SameSeedIsByteIdenticalOtherSeedDiffers) {
  const fs::path a = run_tiny("a", 1), b = run_tiny("b", 1), c = run_tiny("c", 1, {"sample.seed=2"});
  const std::string sa = slurp(a / "series.csv"), sb = slurp(b / "series.csv"), sc = slurp(c / "series.csv");
  ASSERT_FALSE(sa.empty());
  EXPECT_EQ(sa, sb);
  EXPECT_NE(sa, sc);
  EXPECT_EQ(slurp(a / "compaction.csv"), slurp(b / "compaction.csv"));
  EXPECT_EQ(slurp(a / "final.packing"), slurp(b / "final.packing"));
  for (const auto& d : {a, b, c}) fs::remove_all(d);
}

// The engine sums in fixed blocks in a fixed order, so the thread count must not change a bit of
// the results.
TEST(Run, ThreadCountDoesNotChangeSeries) {
  const fs::path one = run_tiny("t1", 1), two = run_tiny("t2", 2);
  const std::string s1 = slurp(one / "series.csv");
  ASSERT_FALSE(s1.empty());
  EXPECT_EQ(s1, slurp(two / "series.csv"));
  EXPECT_EQ(slurp(one / "compaction.csv"), slurp(two / "compaction.csv"));
  fs::remove_all(one);
  fs::remove_all(two);
}

// The tiny run is below parallel_threshold (every loop runs serially) and has a single block in
// every blocked sum, so the test above cannot see an order-dependent sum. Here a packing of 5000
// spheres with several thousand contacts (all loops parallel, several blocks of the force and
// measure sums, several thread chunks of the broad phase, contacts grouped by the thread owning
// their j end) is stepped 30 times on 1, 2 and 3 threads: state, stress and measures must agree
// bit for bit.
TEST(Run, ThreadCountDoesNotChangeLargePacking) {
  const auto [start, model] = large_packing();

  auto run = [&](int threads) {
    Threads t(threads);
    State st = start;
    Schedule schedule;  // kept from step to step: the cuts after the first follow the blocks' times
    for (int k = 0; k < 30; ++k) step(model, st, schedule);
    if (threads > 1) {  // and the update region's ranges its owners' times
      EXPECT_EQ(schedule.owner_rate.size(), static_cast<std::size_t>(threads)) << threads << " threads";
    }
    return std::make_pair(st, measure(st));
  };
  const auto [s1, m1] = run(1);
  const auto [s2, m2] = run(2);
  const auto [s3, m3] = run(3);
  EXPECT_EQ(particles_differing(s1, s3), 0u) << "3 threads";
  EXPECT_TRUE(s1.stress == s3.stress);
  ASSERT_GT(s1.pairs.size(), parallel_threshold) << "the force loop must run in parallel";
  ASSERT_GT(s1.particles.size(), parallel_threshold) << "the per-particle loops must run in parallel";
  ASSERT_GT(m1.contacts, 2 * 1024) << "several force blocks with contacts";
  ASSERT_GT(s1.particles.size(), 2 * 2048u) << "several measure blocks";
  EXPECT_EQ(s1.pairs.size(), s2.pairs.size());
  EXPECT_TRUE(s1.stress == s2.stress);
  EXPECT_TRUE(s1.affine_stiffness == s2.affine_stiffness);
  EXPECT_EQ(particles_differing(s1, s2), 0u);
  EXPECT_EQ(m1.ufr, m2.ufr);
  EXPECT_EQ(m1.iuf, m2.iuf);
  EXPECT_EQ(m1.imom, m2.imom);
  EXPECT_EQ(m1.ekin_trans, m2.ekin_trans);
  EXPECT_EQ(m1.ekin_rot, m2.ekin_rot);
  EXPECT_EQ(m1.solid_volume, m2.solid_volume);
}

// The same packing with the energy ledger kept (output.energy, docs/physics.md 12): its sums are
// in block order (force stage) and in fixed blocks of particles (kick; 5000 particles are three),
// so 1 and 2 threads give the same ledger bit for bit; keeping it changes no particle's state.
TEST(Run, ThreadCountDoesNotChangeTheEnergyLedger) {
  const auto [start, plain] = large_packing();
  Model model = plain;
  model.track_energy = true;
  auto run = [&](int threads, const Model& m) {
    Threads t(threads);
    State st = start;
    Schedule schedule;
    for (int k = 0; k < 30; ++k) step(m, st, schedule);
    return st;
  };
  const State s1 = run(1, model), s2 = run(2, model), untracked = run(2, plain);
  const auto bits = [](const EnergyLedger& e) {
    std::vector<double> v;
    for (const EnergyTerm& term : energy_ledger_terms) v.push_back(e.*term.field);
    return v;
  };
  EXPECT_EQ(bits(s1.energy), bits(s2.energy));
  EXPECT_GT(s1.energy.elastic, 0.0);
  EXPECT_GT(s1.energy.kinetic, 0.0);
  EXPECT_GT(s1.energy.damping, 0.0) << "nd damps the packing";
  EXPECT_EQ(particles_differing(s1, untracked), 0u) << "the ledger changes no result";
  EXPECT_TRUE(s1.stress == untracked.stress);
}

// The update region's ranges (assign_owners): once timed, shares of equal expected time, cut on
// multiples of 8 particles, each at least a quarter of an even share; the rates smoothed from
// step to step (record_owner_times), kept through a step that did not time every owner.
TEST(Run, UpdateRangesFollowTheOwnersTimes) {
  PairList pairs;
  pairs.block_first = {0, 100, 200};
  Schedule s;
  s.block_cut = {0, 1, 2};
  assign_owners(s, pairs, 8000, 2, 2);
  EXPECT_EQ(s.owner_first, (std::vector<std::size_t>{0, 100, 8000})) << "untimed: the particles of the blocks";
  EXPECT_EQ(s.contact_owner_first.size(), 2u * 3u);

  s.owner_rate = {1e-9, 3e-9};  // owner 1 takes 3 times as long per particle
  assign_owners(s, pairs, 8000, 2, 2);
  EXPECT_EQ(s.owner_first, (std::vector<std::size_t>{0, 6000, 8000}));
  s.owner_rate = {1e-9, 1e-5};
  assign_owners(s, pairs, 8000, 2, 2);
  EXPECT_EQ(s.owner_first, (std::vector<std::size_t>{0, 7000, 8000})) << "a quarter of an even share at least";
  s.owner_rate = {2e-9, 2e-9, 2e-9};
  assign_owners(s, pairs, 9010, 3, 3);
  EXPECT_EQ(s.owner_first, (std::vector<std::size_t>{0, 3000, 6000, 9010})) << "multiples of 8";
  assign_owners(s, pairs, 8000, 2, 2);
  EXPECT_TRUE(s.owner_rate.empty()) << "rates of another thread count";
  EXPECT_EQ(s.owner_first, (std::vector<std::size_t>{0, 100, 8000}));

  s.owner_first = {0, 6000, 8000};
  s.owner_seconds = {6e-6, 4e-6};
  record_owner_times(s);
  ASSERT_EQ(s.owner_rate.size(), 2u);
  EXPECT_DOUBLE_EQ(s.owner_rate[0], 1e-9) << "the first timed step's rates";
  EXPECT_DOUBLE_EQ(s.owner_rate[1], 2e-9);
  s.owner_seconds = {12e-6, 4e-6};
  record_owner_times(s);
  EXPECT_DOUBLE_EQ(s.owner_rate[0], 0.8 * 1e-9 + 0.2 * 2e-9);
  EXPECT_DOUBLE_EQ(s.owner_rate[1], 2e-9);
  const std::vector<double> kept = s.owner_rate;
  s.owner_seconds = {12e-6, 0};
  record_owner_times(s);
  EXPECT_EQ(s.owner_rate, kept) << "an owner without a time";
}

// A block's contacts grouped by the owner of their j end (group_contacts_by_owner): each group in
// pair order, the four contact arrays moved together; a block whose j ends one owner holds (any
// owner, or none for no contacts) left as it is.
TEST(Run, ContactsGroupByTheOwnerOfTheirJEnd) {
  Schedule s;
  s.owner_first = {0, 10, 20, 30};  // three owners
  PairList pairs;
  const std::vector<std::uint32_t> j = {25, 3, 12, 28, 4, 15, 16, 17, 22};
  const std::size_t n = j.size();
  pairs.contact_j = j;
  pairs.contact_pairs.resize(n);
  pairs.contact_force.resize(n);
  pairs.contact_torque_j.resize(n);
  for (std::uint32_t m = 0; m < n; ++m) {
    pairs.contact_pairs[m] = 100 + m;
    pairs.contact_force[m] = Vec3(m, 0, 0);
    pairs.contact_torque_j[m] = Vec3(0, m, 0);
  }
  s.contact_owner_first.assign(3 * 4, 0);
  group_contacts_by_owner(s, pairs, 0, 0, 5);  // block 0: j 25 3 12 28 4 (owners 2 0 1 2 0)
  group_contacts_by_owner(s, pairs, 1, 5, 3);  // block 1: j 15 16 17, all owner 1
  group_contacts_by_owner(s, pairs, 2, 8, 0);  // block 2: no contacts
  EXPECT_EQ(pairs.contact_j, (std::vector<std::uint32_t>{3, 4, 12, 25, 28, 15, 16, 17, 22}));
  EXPECT_EQ(pairs.contact_pairs, (std::vector<std::uint32_t>{101, 104, 102, 100, 103, 105, 106, 107, 108}));
  for (std::uint32_t m = 0; m < n; ++m) {
    EXPECT_EQ(pairs.contact_force[m].x(), pairs.contact_pairs[m] - 100.0) << "slot " << m;
    EXPECT_EQ(pairs.contact_torque_j[m].y(), pairs.contact_pairs[m] - 100.0) << "slot " << m;
  }
  EXPECT_EQ(s.contact_owner_first, (std::vector<std::uint32_t>{0, 2, 3, 5, 5, 5, 8, 8, 8, 8, 8, 8}));
}

// A block's contacts as the force stage writes them (ForceBlock): those of the block's first
// owner up from its first slot, the others down from its last (reverse pair order).
// close_block_contacts moves the others after the first ones in pair order, grouped by owner,
// and writes the block's row; the two ranges may overlap. owner_end gives the end of a
// particle's owner's range.
TEST(Run, BlockContactsCloseInPairOrderByOwner) {
  Schedule s;
  s.owner_first = {0, 10, 20, 30};  // three owners
  EXPECT_EQ(owner_end(s, 0), 10u);
  EXPECT_EQ(owner_end(s, 9), 10u);
  EXPECT_EQ(owner_end(s, 10), 20u);
  EXPECT_EQ(owner_end(s, 29), 30u);
  Schedule one;
  one.owner_first = {0, 30};
  EXPECT_EQ(owner_end(one, 12), 30u);
  // Block 0: slots [0, 9), particles of owner 1 first: pairs 100-106 with j 12 25 15 22 28 19 21
  // (owners 1 2 1 2 2 1 2): 12 15 19 up from slot 0, 25 22 28 21 down from slot 9.
  // Block 1: slots [9, 12), j 14 16 18 all owner 1: nothing moves. Block 2: slots [12, 17), its
  // first owner 1: j 23 24 (owner 2) down from 17, no contact up: the ranges overlap.
  const std::size_t n = 17;
  PairList pairs;
  pairs.contact_j.assign(n, 999);
  pairs.contact_pairs.assign(n, 999);
  pairs.contact_force.assign(n, Vec3::Constant(-1));
  pairs.contact_torque_j.assign(n, Vec3::Constant(-1));
  const auto put = [&](std::uint32_t slot, std::uint32_t pair, std::uint32_t j) {
    pairs.contact_j[slot] = j, pairs.contact_pairs[slot] = pair;
    pairs.contact_force[slot] = Vec3(pair, 0, 0), pairs.contact_torque_j[slot] = Vec3(0, pair, 0);
  };
  put(0, 100, 12), put(1, 102, 15), put(2, 105, 19);
  put(8, 101, 25), put(7, 103, 22), put(6, 104, 28), put(5, 106, 21);
  put(9, 110, 14), put(10, 111, 16), put(11, 112, 18);
  put(16, 120, 23), put(15, 121, 24);
  s.contact_owner_first.assign(3 * 4, 0);
  std::vector<ForceBlock> blocks(3);
  blocks[0].first_contact = 0, blocks[0].slot_end = 9, blocks[0].contacts = 3, blocks[0].later_contacts = 4;
  blocks[1].first_contact = 9, blocks[1].slot_end = 12, blocks[1].contacts = 3, blocks[1].later_contacts = 0;
  blocks[2].first_contact = 12, blocks[2].slot_end = 17, blocks[2].contacts = 0, blocks[2].later_contacts = 2;
  for (std::size_t b = 0; b < 3; ++b) {
    blocks[b].first_owner_end = 20;
    close_block_contacts(s, pairs, b, blocks[b]);
  }
  EXPECT_EQ(blocks[0].contacts, 7u);
  EXPECT_EQ(blocks[1].contacts, 3u);
  EXPECT_EQ(blocks[2].contacts, 2u);
  const std::vector<std::uint32_t> j_of_block0 = {12, 15, 19, 25, 22, 28, 21};  // owner 1, then owner 2 by pair
  EXPECT_EQ(std::vector<std::uint32_t>(pairs.contact_j.begin(), pairs.contact_j.begin() + 7), j_of_block0);
  EXPECT_EQ(std::vector<std::uint32_t>(pairs.contact_pairs.begin(), pairs.contact_pairs.begin() + 7),
            (std::vector<std::uint32_t>{100, 102, 105, 101, 103, 104, 106}));
  EXPECT_EQ(std::vector<std::uint32_t>(pairs.contact_j.begin() + 9, pairs.contact_j.begin() + 14),
            (std::vector<std::uint32_t>{14, 16, 18, 23, 24}));
  EXPECT_EQ(pairs.contact_pairs[12], 120u);
  EXPECT_EQ(pairs.contact_pairs[13], 121u);
  for (const std::uint32_t m : {0u, 1u, 2u, 3u, 4u, 5u, 6u, 9u, 10u, 11u, 12u, 13u}) {
    EXPECT_EQ(pairs.contact_force[m].x(), pairs.contact_pairs[m]) << "slot " << m;
    EXPECT_EQ(pairs.contact_torque_j[m].y(), pairs.contact_pairs[m]) << "slot " << m;
  }
  // Rows: owner 0 none, owner 1 [0, 3), owner 2 [3, 7); block 1 all owner 1; block 2 all owner 2.
  EXPECT_EQ(s.contact_owner_first, (std::vector<std::uint32_t>{0, 0, 3, 7, 9, 9, 12, 12, 12, 12, 12, 14}));
}

// A thread done with its blocks takes those left at the front of another thread's range
// (run_blocks). Here every step's cut gives all the blocks to thread 1 (the smoothed block times
// are overwritten: the first block seems to cost everything), so thread 0 can only work by taking
// blocks from the front of thread 1's range while thread 1 works from the back.
// The state must stay bit for bit that of one thread, and thread 0 must have taken blocks.
TEST(Run, ThreadsShareTheBlocksTheCutLeftUneven) {
  const auto [start, model] = large_packing();
  constexpr int steps = 20;
  State one = start;
  {
    Threads t(1);
    for (int k = 0; k < steps; ++k) step(model, one);
  }
  State two = start;
  Schedule schedule;
  int uneven = 0;     // steps with that cut (not those that rebuild the list: pair counts cut them)
  double taken = 0;  // seconds thread 0 spent in blocks of thread 1's range
  {
    Threads t(2);
    for (int k = 0; k < steps; ++k) {
      // The step's blocks are those of the last step unless it rebuilds the list.
      const long builds = two.neighbor.builds;
      const bool skew = schedule.timed_build == builds && !schedule.block_weight.empty();
      if (skew) {
        for (double& w : schedule.block_weight) w = 0;
        schedule.block_weight.front() = 1;  // cut: thread 0 starts with no block, thread 1 with all
      }
      step(model, two, schedule);
      if (!skew || two.neighbor.builds != builds) continue;
      ++uneven;
      EXPECT_EQ(schedule.block_cut, (std::vector<std::size_t>{0, 0, two.blocks.size()})) << "step " << k;
      ASSERT_EQ(schedule.thread_busy.size(), 2u);
      taken += schedule.thread_busy[0];
    }
  }
  ASSERT_GT(two.blocks.size(), 4u) << "several blocks to share";
  ASSERT_GE(uneven, 5) << "steps without a list build";
  EXPECT_GT(taken, 0.0) << "thread 0 took no block from thread 1's range in " << uneven << " steps";
  EXPECT_TRUE(one.stress == two.stress);
  EXPECT_EQ(particles_differing(one, two), 0u);
}

// The particle update needs no schedule from the force stage: given one that does not describe the
// last force evaluation (here a fresh one), one thread updates every particle, to the bits of the
// update on the force stage's two owners.
TEST(Run, UpdateWithoutTheForceStagesOwnersIsTheSame) {
  const auto [start, model] = large_packing();
  Threads t(2);
  State forces = start;
  Schedule schedule;
  evaluate_forces(model, forces);  // the list and the contact history of a first step
  compute_contact_forces(model, forces, schedule);
  ASSERT_EQ(schedule.owners(), 2u) << "the force stage's owners: two threads";
  State owned = forces, fresh = forces;
  Schedule none;
  const double v2_owned = update_particles(model, owned, schedule);
  const double v2_fresh = update_particles(model, fresh, none);
  EXPECT_EQ(none.owners(), 1u);
  EXPECT_EQ(v2_owned, v2_fresh);
  EXPECT_EQ(particles_differing(owned, fresh), 0u);
  for (std::size_t i = 0; i < owned.particles.size(); ++i)
    ASSERT_TRUE(owned.particles.force[i] == fresh.particles.force[i]) << "particle " << i;
}

// SPEC 10 files, and their consistency with SPEC 1, 7 and 8.
TEST(Run, SeriesAndSummaryFollowSpec10) {
  const fs::path dir = run_tiny("files", 1);
  const std::string text = slurp(dir / "series.csv");
  const auto lines = split(text, '\n');
  ASSERT_GE(lines.size(), 1u);
  // Exactly the SPEC 10 names, in order; more columns may follow.
  const std::string& header = lines[0];
  ASSERT_EQ(header.substr(0, spec10_header.size()), spec10_header);
  EXPECT_TRUE(header.size() == spec10_header.size() || header[spec10_header.size()] == ',');
  const auto names = split(header, ',');
  auto col = [&](const std::string& name) {
    return static_cast<std::size_t>(std::find(names.begin(), names.end(), name) - names.begin());
  };
  std::vector<std::vector<double>> rows;
  for (std::size_t k = 1; k < lines.size(); ++k) {
    if (lines[k].empty()) continue;
    std::vector<double> r;
    for (const auto& f : split(lines[k], ',')) r.push_back(std::stod(f));
    ASSERT_EQ(r.size(), names.size()) << "row " << k;
    rows.push_back(r);
  }
  ASSERT_EQ(rows.size(), 10u);  // triaxial.sample_points

  const nlohmann::json s = nlohmann::json::parse(slurp(dir / "summary.json"));
  for (const char* key : {"config", "mean_ufr", "mean_iuf", "mean_imom", "peak_phi_deg", "final_ev", "steps",
                          "wall_s", "particle_steps_per_s", "version"})
    EXPECT_TRUE(s.contains(key)) << key;
  EXPECT_EQ(s["version"], QSDEM_VERSION);
  // The resolved configuration shows the values that were run.
  EXPECT_NE(s["config"].dump().find("0.000125"), std::string::npos) << "eps' in the configuration";

  // Hand values: R_min = 1.0 mm, t_c = 2 R_min sqrt(rho/E) (SPEC 5), dt = 0.32 t_c;
  // sample k at step 25 k, axial strain 25 k c_t eps' = 1e-3 k (SPEC 8).
  const double dt = 0.32 * 2 * 1e-3 * std::sqrt(2650 / 78e9);
  // Void ratio e0 at the triaxial reference volume V0, from the first row (SPEC 1: V = V_s (1 + e)).
  const double e0 = (1 + rows[0][col("void_ratio")]) / (1 + rows[0][col("ev")]) - 1;
  // The summary's compaction void ratio is from the compaction's last check, one step before the
  // state the triaxial test starts from (see report): equal to within one step's volume change.
  EXPECT_NEAR(s["void_ratio_after_compaction"].get<double>(), e0, 1e-5);
  double ufr = 0, iuf = 0, imom = 0, peak = 0;
  for (std::size_t k = 0; k < rows.size(); ++k) {
    const auto& r = rows[k];
    SCOPED_TRACE("row " + std::to_string(k + 1));
    EXPECT_EQ(r[col("step")], 25.0 * static_cast<double>(k + 1));
    EXPECT_NEAR(r[col("time_s")], r[col("step")] * dt, 1e-9 * r[col("time_s")]);  // 10 digits printed
    EXPECT_NEAR(r[col("e1")], 1e-3 * static_cast<double>(k + 1), 1e-12);
    // SPEC 1: ev = V/V0 - 1 and V = V_s (1 + e): ev = (1 + e)/(1 + e0) - 1 (8 digits of e printed),
    // with one e0 for all rows.
    EXPECT_NEAR(r[col("ev")], (1 + r[col("void_ratio")]) / (1 + e0) - 1, 1e-7);
    // p = tr(sigma)/3, Ekin = translational + rotational; 10 and 8 printed digits.
    EXPECT_NEAR(r[col("p_Pa")], (r[col("s11_Pa")] + r[col("s22_Pa")] + r[col("s33_Pa")]) / 3, 1e-8 * r[col("p_Pa")]);
    EXPECT_NEAR(r[col("ekin_J")], r[col("ekin_trans_J")] + r[col("ekin_rot_J")], 1e-7 * r[col("ekin_J")]);
    // Cn = 2 n_c / n_p with n_p = 120: Cn * 60 is a whole number of contacts.
    EXPECT_NEAR(r[col("cn")] * 60, std::round(r[col("cn")] * 60), 1e-4);
    // Compression positive (SPEC 1): the axially loaded sample has s33 > 0 and phi > 0.
    EXPECT_GT(r[col("s33_Pa")], 0);
    EXPECT_GT(r[col("phi_deg")], 0);
    ufr += r[col("ufr")] / 10;
    iuf += r[col("iuf")] / 10;
    imom += r[col("imom")] / 10;
    peak = std::max(peak, r[col("phi_deg")]);
  }
  // SPEC 8: indices averaged over all sample points; 8 digits printed per value.
  EXPECT_NEAR(s["mean_ufr"].get<double>(), ufr, 1e-7 * ufr);
  EXPECT_NEAR(s["mean_iuf"].get<double>(), iuf, 1e-7 * iuf);
  EXPECT_NEAR(s["mean_imom"].get<double>(), imom, 1e-7 * imom);
  EXPECT_NEAR(s["peak_phi_deg"].get<double>(), peak, 1e-7 * peak);
  EXPECT_NEAR(s["final_ev"].get<double>(), rows.back()[col("ev")], 1e-9);
  const double steps = s["steps"].get<double>();
  EXPECT_GT(steps, 250);  // compaction + 250 triaxial steps at least
  EXPECT_NEAR(s["particle_steps_per_s"].get<double>(), 120 * steps / s["wall_s"].get<double>(),
              1e-9 * s["particle_steps_per_s"].get<double>());
  fs::remove_all(dir);
}

// The CLI: help texts name every option; a bad case exits with code 2 naming the key; a good one
// writes what run_case writes.
TEST(Run, CommandLine) {
  const fs::path dir = fresh_dir("cli");
  std::string out, err;
  ASSERT_EQ(shell("'" + binary + "' --help", dir, out, err), 0) << err;
  for (const char* word : {"run", "bench", "--help", "--version"}) EXPECT_NE(out.find(word), std::string::npos) << word;
  ASSERT_EQ(shell("'" + binary + "' run --help", dir, out, err), 0) << err;
  for (const char* word : {"case", "-o,--out", "-s,--set", "-t,--threads", "-q,--quiet", "--help"})
    EXPECT_NE(out.find(word), std::string::npos) << word;
  EXPECT_EQ(shell("'" + binary + "' --version", dir, out, err), 0);
  EXPECT_NE(out.find(QSDEM_VERSION), std::string::npos);

  // Bad input: exit code 2 and a message naming the key (and the line).
  {
    std::ofstream bad(dir / "bad.toml");
    bad << std::string(tiny_case) << "[servo]\nproportional_gian = 0.1\n";
  }
  EXPECT_EQ(shell("'" + binary + "' run '" + (dir / "bad.toml").string() + "' -q -o '" + (dir / "o").string() + "'",
                  dir, out, err),
            2);
  EXPECT_NE(err.find("servo.proportional_gian"), std::string::npos) << err;
  EXPECT_NE(err.find("bad.toml:"), std::string::npos) << err;
  EXPECT_EQ(shell("'" + binary + "' run -q -o '" + (dir / "o").string() + "' --set damping.model=xd", dir, out, err), 2);
  EXPECT_NE(err.find("damping.model"), std::string::npos) << err;
  EXPECT_EQ(shell("'" + binary + "' run '" + (dir / "missing.toml").string() + "' -q", dir, out, err), 2);
  EXPECT_NE(err.find("missing.toml"), std::string::npos) << err;
  // A bad command line: exit code 1 and a message naming the option, the value and what is allowed.
  const std::string source = QSDEM_SOURCE_DIR;
  for (const std::string steps : {"0", "-5", "2.5", "many"}) {
    EXPECT_EQ(shell("'" + binary + "' bench '" + source + "/tests/golden/paper-A-small.packing' -c x.toml --steps " +
                        steps,
                    dir, out, err),
              1)
        << steps;
    EXPECT_NE(err.find("--steps: '" + steps + "' is not allowed: give a whole number >= 1"), std::string::npos) << err;
  }
  EXPECT_EQ(shell("'" + binary + "' run -q --threads -1", dir, out, err), 1);
  EXPECT_NE(err.find("--threads: '-1' is not allowed: give a whole number from 0 (all cores) to 256"),
            std::string::npos)
      << err;
  // More threads than that crashed inside the OpenMP runtime.
  EXPECT_EQ(shell("'" + binary + "' run -q --threads 100000", dir, out, err), 1);
  EXPECT_NE(err.find("--threads: '100000' is not allowed: give a whole number from 0 (all cores) to 256"),
            std::string::npos)
      << err;
  EXPECT_EQ(shell("'" + binary + "' run -q --no-such-option", dir, out, err), 1);
  EXPECT_NE(err.find("--no-such-option"), std::string::npos) << err;

  // A good case: exit 0, and the CLI's series.csv is the library's, byte for byte.
  {
    std::ofstream good(dir / "tiny.toml");
    good << tiny_case;
  }
  EXPECT_EQ(shell("'" + binary + "' run '" + (dir / "tiny.toml").string() + "' -q -t 1 -o '" +
                      (dir / "cli-out").string() + "'",
                  dir, out, err),
            0)
      << err;
  const fs::path lib = run_tiny("cli-lib", 1);
  EXPECT_EQ(slurp(dir / "cli-out" / "series.csv"), slurp(lib / "series.csv"));
  fs::remove_all(lib);
  fs::remove_all(dir);
}

// `qsdem bench` (the speed issue): one JSON line with particles, contacts, steps, threads, wall
// seconds, particle-steps per second, peak memory and the state's heap by structure, on the
// compacted paper-A-small packing (2001 spheroids). After the first step most apart pairs are
// skipped, so far fewer pairs than listed reach the narrow phase.
TEST(Run, BenchPrintsOneMachineReadableLine) {
  const fs::path dir = fresh_dir("bench");
  const std::string source = QSDEM_SOURCE_DIR;
  std::string out, err;
  ASSERT_EQ(shell("'" + binary + "' bench '" + source + "/tests/golden/paper-A-small.packing' --case '" + source +
                      "/examples/paper-A-small.toml' --steps 30 --threads 1",
                  dir, out, err),
            0)
      << err;
  std::istringstream lines(out);
  std::string line, last;
  while (std::getline(lines, line))
    if (!line.empty()) last = line;
  const auto b = nlohmann::json::parse(last);
  for (const char* key : {"particles", "ellipsoids", "contacts_start", "contacts_end", "pairs", "steps", "threads", "wall_s",
                          "particle_steps_per_s", "peak_rss_kib", "narrow_tests_per_step", "pw_iterations_per_step", "state_kib",
                          "stages"})
    EXPECT_TRUE(b.contains(key)) << key << " in " << last;
  EXPECT_EQ(b["particles"].get<int>(), 2001);
  EXPECT_EQ(b["ellipsoids"].get<int>(), 2001);
  EXPECT_EQ(b["steps"].get<int>(), 30);
  EXPECT_EQ(b["threads"].get<int>(), 1);
  EXPECT_GT(b["contacts_end"].get<int>(), 1000);  // a compacted packing
  EXPECT_NEAR(b["particle_steps_per_s"].get<double>(), 2001 * 30 / b["wall_s"].get<double>(),
              1e-9 * b["particle_steps_per_s"].get<double>());
  EXPECT_LT(b["narrow_tests_per_step"].get<double>(), 0.8 * b["pairs"].get<double>());
  EXPECT_GE(b["narrow_tests_per_step"].get<double>(), 0.5 * b["contacts_end"].get<double>());
  // Warm-started Perram-Wertheim: every contact takes an iteration, few take a second.
  EXPECT_GE(b["pw_iterations_per_step"].get<double>(), b["contacts_end"].get<double>());
  EXPECT_LT(b["pw_iterations_per_step"].get<double>(), 1.5 * b["narrow_tests_per_step"].get<double>());
  const auto& kib = b["state_kib"];
  EXPECT_NEAR(kib["total"].get<double>(),
              kib["particles"].get<double>() + kib["pair_keys_and_history"].get<double>() +
                  kib["pair_results"].get<double>() + kib["lists"].get<double>() + kib["scratch"].get<double>(),
              1e-9 * kib["total"].get<double>());
  EXPECT_GT(kib["particles"].get<double>() * 1024, 2001 * 200.0);  // ~261 B per spheroid
  EXPECT_GT(b["peak_rss_kib"].get<double>(), kib["total"].get<double>());
  EXPECT_TRUE(b["force_stage_balance"].is_null()) << "one thread: no balance to report";
  // On two threads: the force stage's balance, mean / largest thread time, in (0, 1].
  ASSERT_EQ(shell("'" + binary + "' bench '" + source + "/tests/golden/paper-A-small.packing' --case '" + source +
                      "/examples/paper-A-small.toml' --steps 30 --threads 2",
                  dir, out, err),
            0)
      << err;
  const auto b2 = nlohmann::json::parse(out.substr(out.find('{')));
  EXPECT_EQ(b2["threads"].get<int>(), 2);
  EXPECT_EQ(b2["contacts_end"].get<int>(), b["contacts_end"].get<int>()) << "the same physics on two threads";
  EXPECT_GT(b2["force_stage_balance"].get<double>(), 0.0);
  EXPECT_LE(b2["force_stage_balance"].get<double>(), 1.0);
  fs::remove_all(dir);
}

// The bench's peak memory is its own, also when its parent is big: a harness (bench/compare-liggghts
// is Python) must not see its own peak in ours. Linux keeps getrusage's ru_maxrss across exec, so
// the bench forked and exec'd (as Python's subprocess does) by this test holding 256 MiB reported
// >= 256 MiB; VmHWM starts afresh at exec.
TEST(Run, BenchPeakMemoryIsItsOwnUnderABigParent) {
  const fs::path dir = fresh_dir("bench-peak");
  const std::string source = QSDEM_SOURCE_DIR;
  const std::string packing = source + "/tests/golden/paper-A-small.packing";
  const std::string config = source + "/examples/paper-A-small.toml";
  const fs::path out_path = dir / "bench.json";
  std::vector<char> ballast(256u << 20, 1);  // touched: resident in this process and its fork
  const pid_t child = fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    // (Only async-signal-safe calls between fork and exec.)
    const int fd = open(out_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    if (fd < 0 || dup2(fd, STDOUT_FILENO) < 0) _exit(126);
    const char* argv[] = {binary.c_str(), "bench",  packing.c_str(), "--case", config.c_str(),
                          "--steps",      "2",      "--threads",     "1",      nullptr};
    execv(binary.c_str(), const_cast<char* const*>(argv));
    _exit(127);
  }
  int status = 0;
  ASSERT_EQ(waitpid(child, &status, 0), child);
  ASSERT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << status;
  EXPECT_EQ(ballast[ballast.size() / 2], 1);
  std::ifstream in(out_path);
  std::string out((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const auto b = nlohmann::json::parse(out.substr(out.find('{')));
  const double peak = b["peak_rss_kib"].get<double>(), state = b["state_kib"]["total"].get<double>();
  EXPECT_GT(peak, state);
  EXPECT_LT(peak, 128 * 1024) << "the parent's 256 MiB, not the bench's own peak";
  fs::remove_all(dir);
}

// A run of examples/sieve-curve.toml (300 spheres from a sieve curve, 1 to 4 mm), cut short: its
// opening lines and summary.json give D10 ... Cc of the curve and of the particles drawn, the
// drawn particles are those of the run (their count per interval and their mass fractions), and
// classes.csv has one class per sieve interval (docs/physics.md 8.6, 10.3).
TEST(Run, SieveCurveCase) {
  const fs::path dir = fresh_dir("sieve");
  const std::string example = std::string(QSDEM_SOURCE_DIR) + "/examples/sieve-curve.toml";
  const std::string sets = " --set triaxial.strain_rate=1.25e-4"
                           " --set 'triaxial.final_axial_strain=\"0.2 %\"' --set triaxial.sample_points=4";
  std::string out, err;
  ASSERT_EQ(shell("'" + binary + "' run '" + example + "' -t 1 -o '" + (dir / "o").string() + "'" + sets, dir, out, err), 0)
      << err;
  const Params params = load_case(example);
  const GradingSizes curve = curve_sizes(params.sample.grading);
  EXPECT_NE(err.find(fmt::format("curve: D10 {:.4g} mm", 1e3 * curve.d10)), std::string::npos) << err;
  EXPECT_NE(err.find(fmt::format("Cu {:.3f}, Cc {:.3f}", curve.cu, curve.cc)), std::string::npos) << err;

  const nlohmann::json s = nlohmann::json::parse(slurp(dir / "o" / "summary.json"));
  const nlohmann::json& g = s["derived"]["grading"];
  EXPECT_EQ(s["derived"]["particles"].get<long>(), 300);
  EXPECT_DOUBLE_EQ(g["curve"]["D10_m"].get<double>(), curve.d10);
  EXPECT_DOUBLE_EQ(g["curve"]["Cc"].get<double>(), curve.cc);
  const std::vector<double> d = draw_diameters(params.sample.grading, 300, params.sample.seed);
  EXPECT_DOUBLE_EQ(g["sample"]["D60_m"].get<double>(), sample_sizes(d).d60);
  const std::vector<long> counts = interval_counts(params.sample.grading, 300);
  ASSERT_EQ(g["intervals"].size(), 4u);
  double drawn = 0;
  for (std::size_t k = 0; k < 4; ++k) {
    EXPECT_EQ(g["intervals"][k]["count"].get<long>(), counts[k]);
    drawn += g["intervals"][k]["sampled_mass_fraction"].get<double>();
  }
  EXPECT_NEAR(drawn, 1, 1e-12);
  // classes.csv: 4 classes (every interval holds particles) at each of its sample points.
  std::ifstream classes(dir / "o" / "classes.csv");
  std::set<std::string> radii;
  std::map<double, long> count_of;  // by radius, ascending
  std::string line;
  std::getline(classes, line);
  ASSERT_EQ(split(line, ',')[5], "radius_mm");
  while (std::getline(classes, line)) {
    const std::vector<std::string> f = split(line, ',');
    radii.insert(f[5]);
    count_of[std::stod(f[5])] = std::stol(f[6]);
  }
  EXPECT_EQ(radii.size(), 4u);
  long k = 0;
  for (const auto& [radius, n] : count_of) EXPECT_EQ(n, counts[static_cast<std::size_t>(k++)]) << radius;
  fs::remove_all(dir);
}
