#include "qsdem/run/packing_io.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <charconv>
#include <fstream>
#include <numeric>
#include <sstream>

#include "qsdem/run/output.hpp"

namespace qsdem {

std::string format_packing(const Particles& p, const Cell& cell) {
  std::string out = "# qsdem packing: lengths in metres; cell rows h11 h12 h13 h21 ...; columns of h are the cell vectors\n";
  out += "format qsdem-packing 1\ncell";
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) out += fmt::format(" {:.17g}", cell.h(r, c));
  out += fmt::format("\nparticles {}\n", p.size());
  // In id order, not the engine's spatial order: line k is particle id k in every packing of a
  // run, and of the packing it was read from (ids are the input's line numbers).
  std::vector<std::size_t> by_id(p.size());
  std::iota(by_id.begin(), by_id.end(), std::size_t{0});
  std::sort(by_id.begin(), by_id.end(), [&](std::size_t a, std::size_t b) { return p.id[a] < p.id[b]; });
  for (const std::size_t i : by_id) {
    const Vec3 sw = p.s[i] - p.s[i].array().floor().matrix();  // wrapped into the cell
    const Vec3 x = cell.h * sw;
    const Vec3& a = p.semi_axes[i];
    const Quat q = p.q[i];
    out += fmt::format("{:.17g} {:.17g} {:.17g} {:.17g} {:.17g} {:.17g} {:.17g} {:.17g} {:.17g} {:.17g}\n",
                       x.x(), x.y(), x.z(), a.x(), a.y(), a.z(), q.w(), q.x(), q.y(), q.z());
  }
  return out;
}

void write_packing(const std::filesystem::path& path, const Particles& p, const Cell& cell) {
  write_file_atomic(path, format_packing(p, cell));
}

State read_packing(const std::filesystem::path& path, double density) {
  std::ifstream in(path);
  if (!in) throw InputError(fmt::format("cannot open packing '{}'", path.string()));
  return parse_packing(in, path.string(), density);
}

State parse_packing(std::istream& in, const std::string& name, double density) {
  State st;
  std::string line;
  long lineno = 0;
  long expected = -1;
  bool have_format = false, have_cell = false;
  auto fail = [&](const std::string& why) {
    throw InputError(fmt::format("{}:{}: {}", name, lineno, why));
  };
  while (std::getline(in, line)) {
    ++lineno;
    const auto first = line.find_first_not_of(" \t\r");
    if (first == std::string::npos || line[first] == '#') continue;
    std::istringstream ls(line);
    if (!have_format) {
      std::string w, format_name;
      int version = 0;
      if (!(ls >> w >> format_name >> version) || w != "format" || format_name != "qsdem-packing")
        fail("expected 'format qsdem-packing 1' as the first line");
      if (version != 1) fail(fmt::format("format version {} is not supported (this qsdem reads 1)", version));
      have_format = true;
    } else if (!have_cell) {
      std::string w;
      Mat3 h;
      ls >> w;
      if (w != "cell") fail("expected 'cell' followed by 9 numbers");
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
          if (!(ls >> h(r, c))) fail("expected 'cell' followed by 9 numbers");
      if (!h.allFinite() || !(h.determinant() > 0)) fail("the cell matrix must have a positive determinant");
      st.cell = make_cell(h);
      have_cell = true;
    } else if (expected < 0) {
      std::string w, count, extra;
      if (!(ls >> w >> count) || w != "particles" || (ls >> extra)) fail("expected 'particles N' with N >= 1");
      const auto [end, ec] = std::from_chars(count.data(), count.data() + count.size(), expected);
      if (ec != std::errc() || end != count.data() + count.size() || expected < 1)
        fail(fmt::format("'particles {}': N must be a whole number >= 1", count));
    } else {
      Vec3 x, a;
      double qw, qx, qy, qz;
      if (!(ls >> x.x() >> x.y() >> x.z() >> a.x() >> a.y() >> a.z() >> qw >> qx >> qy >> qz))
        fail("expected 10 numbers: x y z a b c qw qx qy qz");
      if (std::string extra; ls >> extra) fail("more than 10 columns: expected x y z a b c qw qx qy qz");
      if (!(a.minCoeff() > 0)) fail("semi-axes must be > 0");
      if (!(a.minCoeff() >= 1e-9 && a.maxCoeff() <= 1e3)) fail("semi-axes must be from 1 nm to 1 km (metres)");
      if (!(a.x() >= a.y() && a.y() >= a.z())) fail("semi-axes must be ordered a >= b >= c");
      const Quat q(qw, qx, qy, qz);
      if (!(q.norm() > 0.5)) fail("the orientation quaternion must be (close to) unit");
      // Within a few cells of the origin: far outside, wrapping would lose the centre's digits.
      const Vec3 s = st.cell.h_inv * x;
      if (!(s.cwiseAbs().maxCoeff() <= 1e3))
        fail(fmt::format("centre ({:.6g}, {:.6g}, {:.6g}) lies more than 1000 cell lengths from the cell", x.x(), x.y(),
                         x.z()));
      const ShapeKind kind = (a.x() == a.z()) ? ShapeKind::sphere : ShapeKind::ellipsoid;
      st.particles.add(static_cast<std::uint32_t>(st.particles.size()), kind, a, density, s, q);
    }
  }
  if (!have_format || !have_cell || expected < 0) fail("incomplete header (format, cell, particles)");
  if (static_cast<long>(st.particles.size()) != expected)
    fail(fmt::format("expected {} particles, read {}", expected, st.particles.size()));
  return st;
}

}  // namespace qsdem
