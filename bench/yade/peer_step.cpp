// qsdem_peer_step: qsdem's steps on a state taken from another code (bench/yade/step_check.py),
// for a contact-by-contact comparison of the forces and a particle-by-particle one of the kick.
//
//   qsdem_peer_step --case CASE [--set KEY=VALUE ...] --packing FILE --contacts FILE
//                   [--motion FILE] [--velocity-gradient "L11 L12 ... L33"] [--steps N]
//                   [--servo "TARGET_PA CAP_PER_S"] --out DIR
//
// The packing's particles keep their order (ids = lines) and its centres as given; the contacts
// file (bench/yade/peer.py, write_contacts: id1 id2 c1 c2 c3 nx ny nz overlap fn ft) gives the
// tangential history, the stored tangential force on id2, which every listed contact starts with;
// the motion file gives each particle's velocity and angular velocity (total, as YADE keeps them:
// the fluctuation velocity is v - L x, with L the velocity gradient). The cell's velocity gradient
// L is held for every step, or, with --servo, axes 1 and 2 follow qsdem's stress servo (SPEC 3.5)
// towards TARGET with |L_kk| <= CAP, axis 3 and the shear components fixed, the integral starting
// at zero (bench/yade/servo_check.py). It writes, for the last step:
//   DIR/forces.txt   per contact of the force evaluation, its key i j c1 c2 c3 (i < j) and the
//                    force on j split into its normal and tangential parts
//   DIR/motion.txt   per particle, the fluctuation velocity and the angular velocity after the kick
// and with --servo, for every step, DIR/servo.txt: the stresses and affine stiffnesses of its force
// evaluation and the rates L11, L22 the servo chose from them.
#include <fmt/format.h>

#include <cstdio>
#include <fstream>
#include <iostream>
#include <map>
#include <sstream>
#include <string>
#include <tuple>
#include <variant>
#include <vector>

#include "peer_state.hpp"
#include "qsdem/engine/contact/hertz_mindlin.hpp"
#include "qsdem/engine/damping/stage.hpp"
#include "qsdem/engine/forces.hpp"
#include "qsdem/engine/neighbor.hpp"
#include "qsdem/engine/servo.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/packing_io.hpp"
#include "qsdem/run/protocol.hpp"

using namespace qsdem;

namespace {

int run(int argc, char** argv) {
  std::string case_path, packing, contacts_path, motion_path, out_dir, gradient, servo;
  std::vector<std::string> overrides;
  long steps = 1;
  for (int a = 1; a < argc; ++a) {
    const std::string arg = argv[a];
    const auto value = [&]() -> std::string {
      if (a + 1 >= argc) throw InputError(fmt::format("{} needs a value", arg));
      return argv[++a];
    };
    if (arg == "--case") case_path = value();
    else if (arg == "--set") overrides.push_back(value());
    else if (arg == "--packing") packing = value();
    else if (arg == "--contacts") contacts_path = value();
    else if (arg == "--motion") motion_path = value();
    else if (arg == "--velocity-gradient") gradient = value();
    else if (arg == "--steps") steps = std::stol(value());
    else if (arg == "--servo") servo = value();
    else if (arg == "--out") out_dir = value();
    else throw InputError(fmt::format("unknown argument '{}'", arg));
  }
  if (case_path.empty() || packing.empty() || contacts_path.empty() || out_dir.empty())
    throw InputError("usage: qsdem_peer_step --case CASE --packing FILE --contacts FILE --out DIR [--motion FILE] "
                     "[--velocity-gradient \"9 numbers\"] [--steps N] [--servo \"TARGET_PA CAP_PER_S\"] [--set KEY=VALUE]");
  const Params params = load_case(case_path, overrides);
  State st = read_packing(packing, params.material.density);
  Model model = triaxial_model(params, st);
  model.sort_particles = false;  // particle k stays the file's line k (YADE's body id)
  model.skip_apart_pairs = false;
  peer::adopt_yade_state(st, model, gradient, motion_path, contacts_path);
  const Mat3 L = st.cell.L;
  assign_damping(model, st.particles);
  if (!servo.empty()) {
    std::istringstream in(servo);
    double target = 0, cap = 0;
    if (!(in >> target >> cap) || !(target > 0) || !(cap > 0))
      throw InputError(fmt::format("--servo '{}': give the target stress (Pa, > 0) and the rate cap (1/s, > 0)", servo));
    for (ResolvedControl& c : model.control) c = ResolvedControl{};  // fixed
    model.control[0] = model.control[1] = ResolvedControl{ControlKind::stress, target, 0};
    model.servo.max_strain_rate = cap;
    st.servo_integral = Vec3::Zero();
  }
  std::ofstream servo_rows;
  if (!servo.empty()) {
    std::filesystem::create_directories(out_dir);
    servo_rows.open(std::filesystem::path(out_dir) / "servo.txt");
    servo_rows << "# step s11 s22 s33 (Pa, compression positive) C11 C22 (Pa, affine stiffness) L11 L22 (1/s)\n";
  }

  // The last step's contacts at its force evaluation: force on j and the unit normal from i to j.
  std::vector<std::tuple<std::size_t, Vec3, Vec3>> last;
  for (long n = 0; n < steps; ++n) {
    Schedule schedule;
    if (needs_rebuild(st.neighbor, st.particles, st.cell, false))
      build_pairs(st.particles, st.cell, model.skin, st.pairs, st.neighbor);
    compute_contact_forces(model, st, schedule);
    if (n + 1 == steps) {
      const std::vector<Vec3> forces = contact_forces_by_pair(st);
      const PairList& pairs = st.pairs;
      for (std::size_t k = 0; k < pairs.size(); ++k) {
        if (!(pairs.overlap[k] > 0)) continue;
        const Vec3 l = st.cell.h * (st.particles.s[pairs.j[k]] - st.particles.s[pairs.i[k]] +
                                    pairs.image[k].cast<double>());
        last.emplace_back(k, forces[k], l.normalized());
      }
    }
    if (servo.empty()) {
      st.cell.L = L;
    } else {
      servo_update(model, st);
      servo_rows << fmt::format("{} {:.17g} {:.17g} {:.17g} {:.17g} {:.17g} {:.17g} {:.17g}\n", n, st.stress(0, 0),
                                st.stress(1, 1), st.stress(2, 2), st.affine_stiffness[0], st.affine_stiffness[1],
                                st.cell.L(0, 0), st.cell.L(1, 1));
    }
    deform(st.cell, model.dt);
    update_particles(model, st, schedule);
  }

  const std::filesystem::path out(out_dir);
  std::filesystem::create_directories(out);
  {
    std::ofstream f(out / "forces.txt");
    f << "# i j c1 c2 c3 fnx fny fnz ftx fty ftz: qsdem's key (i < j, image c of j) and the force on j (N), "
         "normal and tangential parts\n";
    for (const auto& [k, force, n] : last) {
      const Vec3 fn = force.dot(n) * n, ft = force - fn;
      const Vec3i& c = st.pairs.image[k];
      f << fmt::format("{} {} {} {} {} {:.17g} {:.17g} {:.17g} {:.17g} {:.17g} {:.17g}\n", st.pairs.i[k], st.pairs.j[k],
                       c.x(), c.y(), c.z(), fn.x(), fn.y(), fn.z(), ft.x(), ft.y(), ft.z());
    }
  }
  {
    std::ofstream f(out / "motion.txt");
    f << "# vx vy vz wx wy wz (fluctuation velocity, m/s; angular velocity, 1/s)\n";
    const Particles& p = st.particles;
    for (std::size_t i = 0; i < p.size(); ++i) {
      const Vec3& v = p.v[i];
      f << fmt::format("{:.17g} {:.17g} {:.17g} {:.17g} {:.17g} {:.17g}\n", v.x(), v.y(), v.z(), p.omega[i].x(),
                       p.omega[i].y(), p.omega[i].z());
    }
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  return peer::tool_main("qsdem_peer_step", [&] { return run(argc, argv); });
}
