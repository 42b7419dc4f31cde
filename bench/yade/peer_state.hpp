// Readers of a state written by bench/yade (peer.py): the contacts with their tangential history and
// the particles' motion, for qsdem_peer_step and qsdem_peer_sample.
#pragma once
#include <fmt/format.h>

#include <cstdint>
#include <exception>
#include <fstream>
#include <iostream>
#include <map>
#include <sstream>
#include <string>
#include <tuple>
#include <vector>

#include "qsdem/engine/cell.hpp"
#include "qsdem/engine/contact/hertz_mindlin.hpp"
#include "qsdem/engine/model.hpp"
#include "qsdem/engine/neighbor.hpp"
#include "qsdem/engine/particles.hpp"
#include "qsdem/engine/state.hpp"
#include "qsdem/run/config.hpp"

namespace peer {
using namespace qsdem;

struct Contact {
  std::uint32_t id1, id2;
  Vec3i cell_dist;
  Vec3 shear;  // stored tangential force on id2 (N)
};

inline std::vector<Contact> read_contacts(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw InputError(fmt::format("cannot read contacts file '{}'", path));
  std::vector<Contact> out;
  std::string line;
  int lineno = 0;
  while (std::getline(in, line)) {
    ++lineno;
    if (line.empty() || line[0] == '#') continue;
    std::istringstream s(line);
    Contact c;
    double n[3], overlap, fn[3];
    if (!(s >> c.id1 >> c.id2 >> c.cell_dist.x() >> c.cell_dist.y() >> c.cell_dist.z() >> n[0] >> n[1] >> n[2] >>
          overlap >> fn[0] >> fn[1] >> fn[2] >> c.shear.x() >> c.shear.y() >> c.shear.z()))
      throw InputError(fmt::format("{}:{}: expected id1 id2 c1 c2 c3 nx ny nz overlap fnx fny fnz ftx fty ftz", path,
                                   lineno));
    out.push_back(c);
  }
  return out;
}

inline void read_motion(const std::string& path, Particles& p, const Mat3& L, const Cell& cell) {
  std::ifstream in(path);
  if (!in) throw InputError(fmt::format("cannot read motion file '{}'", path));
  std::string line;
  std::size_t i = 0;
  int lineno = 0;
  while (std::getline(in, line)) {
    ++lineno;
    if (line.empty() || line[0] == '#') continue;
    if (i >= p.size()) throw InputError(fmt::format("{}:{}: more lines than particles ({})", path, lineno, p.size()));
    std::istringstream s(line);
    Vec3 v, w;
    if (!(s >> v.x() >> v.y() >> v.z() >> w.x() >> w.y() >> w.z()))
      throw InputError(fmt::format("{}:{}: expected vx vy vz wx wy wz", path, lineno));
    const Vec3 x = cell.h * p.s[i];
    p.v[i] = v - L * x;  // the fluctuation velocity (SPEC 3.2)
    p.omega[i] = w;
    p.angmom.set(i, w.cwiseProduct(p.inertia[i]));  // spheres: L = I w
    ++i;
  }
  if (i != p.size()) throw InputError(fmt::format("{}: {} lines for {} particles", path, i, p.size()));
}

inline Mat3 parse_matrix(const std::string& text) {
  std::istringstream s(text);
  Mat3 m;
  for (int a = 0; a < 3; ++a)
    for (int b = 0; b < 3; ++b)
      if (!(s >> m(a, b))) throw InputError("--velocity-gradient: expected 9 numbers, row by row");
  return m;
}

using Key = std::tuple<std::uint32_t, std::uint32_t, int, int, int>;

inline std::map<Key, std::size_t> pair_index(const PairList& pairs) {
  std::map<Key, std::size_t> index;
  for (std::size_t k = 0; k < pairs.size(); ++k)
    index[{pairs.i[k], pairs.j[k], pairs.image[k].x(), pairs.image[k].y(), pairs.image[k].z()}] = k;
  return index;
}

// The key of the YADE contact in qsdem's list (i < j) and the sign of the force on id2 in terms of
// the force on j.
inline std::pair<Key, double> key_of(std::uint32_t id1, std::uint32_t id2, const Vec3i& c) {
  if (id1 < id2) return {{id1, id2, c.x(), c.y(), c.z()}, 1.0};
  return {{id2, id1, -c.x(), -c.y(), -c.z()}, -1.0};
}

// Gives every listed pair that is one of YADE's contacts its stored tangential force (the history of
// HertzMindlin, adopted by the caller); throws RunError when a contact is not in the list.
inline void adopt_contacts(PairList& pairs, const std::vector<Contact>& contacts) {
  const auto index = pair_index(pairs);
  long missing = 0;
  for (const Contact& c : contacts) {
    const auto [key, sign] = key_of(c.id1, c.id2, c.cell_dist);
    const auto found = index.find(key);
    if (found == index.end()) {
      ++missing;
      continue;
    }
    const auto h = pairs.history.of(found->second);
    for (int m = 0; m < 3; ++m) h[static_cast<std::size_t>(m)] = sign * c.shear[m];
  }
  if (missing) throw RunError(fmt::format("{} of the {} contacts are not in qsdem's pair list", missing, contacts.size()));
}

// YADE's state on a packing read in YADE's body order: the cell's velocity gradient (9 numbers row
// by row, or none: 0), the particles' motion when `motion_path` is given, a fresh pair list and every
// contact's stored tangential force. Returns the number of YADE's contacts. The model's law must be
// HertzMindlin, the law of that history.
inline std::size_t adopt_yade_state(State& st, const Model& model, const std::string& gradient,
                                    const std::string& motion_path, const std::string& contacts_path) {
  if (!std::holds_alternative<HertzMindlin>(contact_law_of(model)))
    throw InputError(fmt::format("contact.law must be {} (the law of the contacts file's history)", HertzMindlin::name));
  st.cell.L = gradient.empty() ? Mat3::Zero() : parse_matrix(gradient);
  if (!motion_path.empty()) read_motion(motion_path, st.particles, st.cell.L, st.cell);
  build_pairs(st.particles, st.cell, model.skin, st.pairs, st.neighbor);
  adopt_history(st.pairs, HertzMindlin::history);
  const std::vector<Contact> contacts = read_contacts(contacts_path);
  adopt_contacts(st.pairs, contacts);
  return contacts.size();
}

// A peer tool's main: its run, with input errors as exit code 2 and any other as 3, named `tool`.
template <class Run>
int tool_main(const char* tool, Run&& run) {
  try {
    return run();
  } catch (const InputError& e) {
    std::cerr << tool << ": " << e.what() << "\n";
    return 2;
  } catch (const std::exception& e) {
    std::cerr << tool << ": " << e.what() << "\n";
    return 3;
  }
}

}  // namespace peer
