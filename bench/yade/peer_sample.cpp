// qsdem_peer_sample: a prepared sample (sample.qsck) holding the state YADE compacted, with its
// contact history and velocities, so that `qsdem run --set sample.from=OUT` shears exactly what
// YADE shears (bench/compare-yade --start yade-state). Without it qsdem compacts YADE's packing again
// and starts from no tangential history.
//
//   qsdem_peer_sample --prepared DIR --packing FILE --contacts FILE --motion FILE
//                     [--velocity-gradient "L11 L12 ... L33"] --out DIR
//
// --prepared: a sample qsdem prepared from the same packing (`qsdem prepare CASE --set
// sample.from=FILE`), whose case, run record, step count and energy ledger are kept; its particles,
// cell, pair list and contact history are replaced by YADE's (packing, contacts and motion files of
// bench/yade/peer.py, YADE's body ids in order). The stress and stiffnesses of its last force
// evaluation are kept until the first step evaluates the forces again.
#include <fmt/format.h>

#include <filesystem>
#include <iostream>
#include <string>

#include "peer_state.hpp"
#include "qsdem/run/checkpoint.hpp"
#include "qsdem/run/packing_io.hpp"
#include "qsdem/run/phase_model.hpp"
#include "qsdem/run/run_directory.hpp"

using namespace qsdem;

namespace {

int run(int argc, char** argv) {
  std::string prepared, packing, contacts_path, motion_path, gradient, out_dir;
  for (int a = 1; a < argc; ++a) {
    const std::string arg = argv[a];
    const auto value = [&]() -> std::string {
      if (a + 1 >= argc) throw InputError(fmt::format("{} needs a value", arg));
      return argv[++a];
    };
    if (arg == "--prepared") prepared = value();
    else if (arg == "--packing") packing = value();
    else if (arg == "--contacts") contacts_path = value();
    else if (arg == "--motion") motion_path = value();
    else if (arg == "--velocity-gradient") gradient = value();
    else if (arg == "--out") out_dir = value();
    else throw InputError(fmt::format("unknown argument '{}'", arg));
  }
  if (prepared.empty() || packing.empty() || contacts_path.empty() || motion_path.empty() || out_dir.empty())
    throw InputError("usage: qsdem_peer_sample --prepared DIR --packing FILE --contacts FILE --motion FILE --out DIR "
                     "[--velocity-gradient \"9 numbers\"]");
  const std::filesystem::path from = std::filesystem::path(prepared) / prepared_sample_file;
  Checkpoint c = load_checkpoint(from);
  const Params params = parse_case(c.case_text, c.case_source);

  State yade = read_packing(packing, params.material.density);
  if (yade.particles.size() != c.state.particles.size())
    throw InputError(fmt::format("{} has {} particles, the prepared sample {}", packing, yade.particles.size(),
                                 c.state.particles.size()));
  const std::size_t contacts = peer::adopt_yade_state(yade, triaxial_model(params, yade), gradient, motion_path,
                                                      contacts_path);

  State& st = c.state;
  st.particles = std::move(yade.particles);
  st.cell = yade.cell;
  st.pairs = std::move(yade.pairs);
  st.neighbor = std::move(yade.neighbor);
  st.contacts_build = -1;  // the contact arrays are of no list until the first force evaluation
  const std::filesystem::path out(out_dir);
  std::filesystem::create_directories(out);
  save_checkpoint(out / prepared_sample_file, c.case_text, c.case_source, st, c.run);
  load_checkpoint(out / prepared_sample_file);  // refuses what does not fit together
  std::cout << fmt::format("{}: {} particles, {} listed pairs, {} contacts with YADE's history\n",
                           (out / prepared_sample_file).string(), st.particles.size(), st.pairs.size(), contacts);
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  return peer::tool_main("qsdem_peer_sample", [&] { return run(argc, argv); });
}
