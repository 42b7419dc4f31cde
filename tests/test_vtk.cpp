// VTK snapshots (vtk.hpp): a hand-built packing in a tilted periodic cell is written, read back
// with a minimal XML parser written here (no VTK needed) and checked against values computed by
// hand: centres wrapped into the cell (SPEC 3), the shape tensor R diag(a,b,c) R^T whose
// eigen-pairs are the semi-axes and the rotated body axes (SPEC 2), the Hertz contact force of
// the one touching pair (SPEC 4) and the per-particle contact counts (SPEC 7).
#include <gtest/gtest.h>
#include <unistd.h>

#include <Eigen/Eigenvalues>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include "qsdem/engine/model.hpp"
#include "qsdem/engine/state.hpp"
#include "qsdem/engine/step.hpp"
#include "qsdem/run/vtk.hpp"

using namespace qsdem;
namespace fs = std::filesystem;

namespace {

constexpr double mm = 1e-3;

// ---- A minimal XML reader: elements, attributes, text; throws on anything malformed. ----

struct Node {
  std::string name;
  std::map<std::string, std::string> attr;
  std::vector<Node> children;
  std::string text;

  const Node& child(const std::string& n) const {
    for (const Node& c : children)
      if (c.name == n) return c;
    throw std::runtime_error("no element <" + n + "> in <" + name + ">");
  }
  const Node& array(const std::string& array_name) const {
    for (const Node& c : children)
      if (c.name == "DataArray" && c.attr.count("Name") && c.attr.at("Name") == array_name) return c;
    throw std::runtime_error("no DataArray '" + array_name + "' in <" + name + ">");
  }
};

std::string unescape(const std::string& s) {
  std::string out;
  for (std::size_t k = 0; k < s.size(); ++k) {
    if (s[k] != '&') {
      out += s[k];
      continue;
    }
    const std::size_t end = s.find(';', k);
    if (end == std::string::npos) throw std::runtime_error("bad entity");
    const std::string e = s.substr(k + 1, end - k - 1);
    static const std::map<std::string, char> entities{{"amp", '&'}, {"lt", '<'}, {"gt", '>'}, {"quot", '"'}, {"apos", '\''}};
    if (!entities.count(e)) throw std::runtime_error("unknown entity &" + e + ";");
    out += entities.at(e);
    k = end;
  }
  return out;
}

class XmlParser {
 public:
  explicit XmlParser(std::string text) : s_(std::move(text)) {}

  Node document() {
    const std::string decl = "<?xml version=\"1.0\"?>";
    if (s_.compare(0, decl.size(), decl) != 0) throw std::runtime_error("missing XML declaration");
    pos_ = decl.size();
    skip_space();
    Node root = element();
    skip_space();
    if (pos_ != s_.size()) throw std::runtime_error("content after the root element");
    return root;
  }

 private:
  std::string s_;
  std::size_t pos_ = 0;

  void skip_space() {
    while (pos_ < s_.size() && std::isspace(static_cast<unsigned char>(s_[pos_]))) ++pos_;
  }
  void expect(char c) {
    if (pos_ >= s_.size() || s_[pos_] != c) throw std::runtime_error(std::string("expected '") + c + "' at " + std::to_string(pos_));
    ++pos_;
  }
  std::string name() {
    const std::size_t start = pos_;
    while (pos_ < s_.size() && (std::isalnum(static_cast<unsigned char>(s_[pos_])) || s_[pos_] == '_')) ++pos_;
    if (pos_ == start) throw std::runtime_error("expected a name at " + std::to_string(pos_));
    return s_.substr(start, pos_ - start);
  }
  Node element() {
    Node n;
    expect('<');
    n.name = name();
    for (;;) {
      skip_space();
      if (pos_ >= s_.size()) throw std::runtime_error("unterminated <" + n.name + ">");
      if (s_[pos_] == '/') {
        ++pos_;
        expect('>');
        return n;  // <name ... />
      }
      if (s_[pos_] == '>') {
        ++pos_;
        break;
      }
      const std::string key = name();
      expect('=');
      expect('"');
      const std::size_t end = s_.find('"', pos_);
      if (end == std::string::npos) throw std::runtime_error("unterminated attribute");
      if (n.attr.count(key)) throw std::runtime_error("duplicate attribute " + key);
      n.attr[key] = unescape(s_.substr(pos_, end - pos_));
      pos_ = end + 1;
    }
    for (;;) {  // content up to the matching end tag
      if (pos_ >= s_.size()) throw std::runtime_error("<" + n.name + "> is never closed");
      if (s_.compare(pos_, 2, "</") == 0) {
        pos_ += 2;
        const std::string closing = name();
        if (closing != n.name) throw std::runtime_error("<" + n.name + "> closed by </" + closing + ">");
        skip_space();
        expect('>');
        return n;
      }
      if (s_[pos_] == '<') {
        n.children.push_back(element());
      } else {
        n.text += s_[pos_++];
      }
    }
  }
};

Node parse_file(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw std::runtime_error("cannot open " + path.string());
  std::stringstream ss;
  ss << in.rdbuf();
  return XmlParser(ss.str()).document();
}

std::string base64_decode(const std::string& text) {
  std::string out;
  std::uint32_t acc = 0;
  int bits = 0;
  for (char c : text) {
    int v;
    if (c >= 'A' && c <= 'Z') v = c - 'A';
    else if (c >= 'a' && c <= 'z') v = c - 'a' + 26;
    else if (c >= '0' && c <= '9') v = c - '0' + 52;
    else if (c == '+') v = 62;
    else if (c == '/') v = 63;
    else if (c == '=' || std::isspace(static_cast<unsigned char>(c))) continue;
    else throw std::runtime_error("bad base64 character");
    acc = acc << 6 | static_cast<std::uint32_t>(v);
    bits += 6;
    if (bits >= 8) {
      bits -= 8;
      out += static_cast<char>((acc >> bits) & 0xff);
    }
  }
  return out;
}

template <class T>
std::vector<double> read_raw(const std::string& bytes, std::size_t count) {
  if (bytes.size() != count * sizeof(T)) throw std::runtime_error("binary size does not match");
  std::vector<double> out(count);
  for (std::size_t k = 0; k < count; ++k) {
    T v;
    std::memcpy(&v, bytes.data() + k * sizeof(T), sizeof(T));
    out[k] = static_cast<double>(v);
  }
  return out;
}

// The values of a DataArray (any type, as doubles), checked against its declared size.
std::vector<double> values(const Node& a, std::size_t tuples) {
  const std::size_t ncomp = a.attr.count("NumberOfComponents") ? std::stoul(a.attr.at("NumberOfComponents")) : 1;
  const std::size_t count = tuples * ncomp;
  const std::string& type = a.attr.at("type");
  if (a.attr.at("format") == "ascii") {
    std::istringstream in(a.text);
    std::vector<double> out;
    std::string tok;
    while (in >> tok) out.push_back(std::stod(tok));
    if (out.size() != count) throw std::runtime_error("ascii array " + a.attr.at("Name") + " has the wrong size");
    return out;
  }
  if (a.attr.at("format") != "binary") throw std::runtime_error("unknown format");
  const std::string bytes = base64_decode(a.text);
  std::uint64_t header = 0;  // header_type="UInt64": byte count of the data that follows
  if (bytes.size() < sizeof header) throw std::runtime_error("binary array too short");
  std::memcpy(&header, bytes.data(), sizeof header);
  const std::string data = bytes.substr(sizeof header);
  if (header != data.size()) throw std::runtime_error("binary header does not match the data");
  if (type == "Float64") return read_raw<double>(data, count);
  if (type == "Int64") return read_raw<std::int64_t>(data, count);
  if (type == "Int32") return read_raw<std::int32_t>(data, count);
  if (type == "UInt32") return read_raw<std::uint32_t>(data, count);
  if (type == "UInt8") return read_raw<std::uint8_t>(data, count);
  throw std::runtime_error("unknown type " + type);
}

fs::path temp_dir(const std::string& name) {
  const fs::path dir = fs::temp_directory_path() / ("qsdem_vtk_" + name + "_" + std::to_string(::getpid()));
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

// ---- The packing: a tilted cell h (columns a1 = (10,0,0), a2 = (1,10,0), a3 = (0,0,10) mm). ----

struct Expected {
  std::vector<Vec3> centre;  // wrapped, Cartesian (m), by hand
};

// Rotation matrix of angle t about unit axis u (Rodrigues), independent of Eigen's quaternion.
Mat3 rodrigues(const Vec3& u, double t) {
  Mat3 k;
  k << 0, -u.z(), u.y(), u.z(), 0, -u.x(), -u.y(), u.x(), 0;
  return Mat3::Identity() + std::sin(t) * k + (1 - std::cos(t)) * k * k;
}

const Vec3 axis2 = Vec3(1, 2, 3).normalized();
constexpr double angle2 = 0.7;
const Vec3 semi2(1.5 * mm, 1.0 * mm, 0.6 * mm);
const Vec3 semi3(1.2 * mm, 0.9 * mm, 0.7 * mm);

// 0, 1: spheres R = 1 mm touching across the x face (overlap 0.3 mm); 4: a sphere 0.1 mm from 1,
// inside the Verlet skin but not touching; 2, 3: ellipsoids far from everything, 2 at a generic
// orientation, 3 turned 120 degrees about (1,1,1) (body x, y, z -> world y, z, x).
State make_state(Model& model) {
  Mat3 h;
  h << 10, 1, 0, 0, 10, 0, 0, 0, 10;
  State st;
  st.cell = make_cell(h * mm);
  Particles& p = st.particles;
  const Quat q2(Eigen::AngleAxisd(angle2, axis2));
  const Quat q3(0.5, 0.5, 0.5, 0.5);  // cos 60 deg, sin 60 deg (1,1,1)/sqrt 3
  p.add(10, ShapeKind::sphere, Vec3::Constant(1 * mm), 2650, Vec3(0.91, 0.2, 0.2), Quat::Identity());
  p.add(11, ShapeKind::sphere, Vec3::Constant(1 * mm), 2650, Vec3(1.08, 0.2, 0.2), Quat::Identity());
  p.add(12, ShapeKind::ellipsoid, semi2, 2650, Vec3(0.5, -0.5, 0.7), q2);
  p.add(13, ShapeKind::ellipsoid, semi3, 2650, Vec3(0.45, 0.75, -1.75), q3);
  p.add(14, ShapeKind::sphere, Vec3::Constant(1 * mm), 2650, Vec3(-0.941, 0.41, 0.2), Quat::Identity());
  p.v[2] = Vec3(0.1, -0.2, 0.3);
  p.omega[3] = Vec3(0, 5, 0);  // about world y = body x: L = I_x omega
  p.angmom.set(3, p.inertia[3].x() * p.omega[3]);

  // Material of SPEC 9 (Model defaults), no damping, fixed cell.
  model.r_min = smallest_equiv_radius(p);
  model.critical_time = critical_time(model.material, model.r_min);
  model.dt = 0.3 * model.critical_time;
  model.skin = 0.2 * mm;
  model.contact_law = make_contact_law(model.material, 0.5);
  return st;
}

Expected expected() {
  // x = h s_wrapped: x1 = 10 s1 + s2, x2 = 10 s2, x3 = 10 s3 (mm).
  return {{Vec3(9.3, 2, 2) * mm, Vec3(1.0, 2, 2) * mm, Vec3(5.5, 5, 7) * mm, Vec3(5.25, 7.5, 2.5) * mm,
           Vec3(1.0, 4.1, 2) * mm}};
}

Vec3 tuple3(const std::vector<double>& v, std::size_t k) { return Vec3(v[3 * k], v[3 * k + 1], v[3 * k + 2]); }

class VtkFormat : public ::testing::TestWithParam<VtkEncoding> {};

}  // namespace

// The particle file of a hand-built packing, in both encodings.
TEST_P(VtkFormat, ParticleFileHoldsThePacking) {
  Model model;
  State st = make_state(model);
  evaluate_forces(model, st);
  st.time = 1.25e-3;
  st.step = 4711;

  // Precondition of the contact-count check: the pair list holds the touching pair and a
  // listed pair that does not touch (1-4, gap 0.1 mm < skin), which must not be counted.
  bool listed_apart = false;
  for (std::size_t k = 0; k < st.pairs.size(); ++k) listed_apart |= st.pairs.overlap[k] <= 0;
  ASSERT_TRUE(listed_apart);

  const fs::path dir = temp_dir(GetParam() == VtkEncoding::ascii ? "ascii" : "binary");
  const fs::path file = dir / "snapshot-0000.vtu";
  write_vtu(file, st, GetParam());
  EXPECT_FALSE(fs::exists(dir / "snapshot-0000.vtu.tmp"));  // renamed into place

  const Node root = parse_file(file);  // throws on unbalanced tags or a missing declaration
  EXPECT_EQ(root.name, "VTKFile");
  EXPECT_EQ(root.attr.at("type"), "UnstructuredGrid");
  EXPECT_EQ(root.attr.at("header_type"), "UInt64");
  EXPECT_EQ(root.attr.at("byte_order"), "LittleEndian");  // x86-64 / arm64
  const Node& grid = root.child("UnstructuredGrid");
  const Node& piece = grid.child("Piece");
  const std::size_t n = 5;
  ASSERT_EQ(std::stoul(piece.attr.at("NumberOfPoints")), n);
  ASSERT_EQ(std::stoul(piece.attr.at("NumberOfCells")), n);

  // One VTK_VERTEX (type 1) per particle.
  const Node& cells = piece.child("Cells");
  const auto conn = values(cells.array("connectivity"), n);
  const auto offs = values(cells.array("offsets"), n);
  const auto types = values(cells.array("types"), n);
  for (std::size_t k = 0; k < n; ++k) {
    EXPECT_EQ(conn[k], static_cast<double>(k));
    EXPECT_EQ(offs[k], static_cast<double>(k + 1));
    EXPECT_EQ(types[k], 1.0);
  }

  // Centres wrapped into the cell (SPEC 3): x = h (s - floor s). Both encodings are exact
  // (shortest round-trip text, raw doubles); 1e-15 m absorbs the rounding of h s (~1e-19 m).
  const auto x = values(piece.child("Points").child("DataArray"), n);
  const Expected e = expected();
  for (std::size_t k = 0; k < n; ++k)
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(x[3 * k + c], e.centre[k][c], 1e-15) << k << c;

  const Node& pd = piece.child("PointData");
  EXPECT_EQ(pd.attr.at("Tensors"), "shape_tensor");  // Tensor Glyph's default input
  const auto ids = values(pd.array("id"), n);
  const auto radius = values(pd.array("radius"), n);
  const auto semi = values(pd.array("semi_axes"), n);
  const auto orient = values(pd.array("orientation"), n);
  const auto tensor = values(pd.array("shape_tensor"), n);
  const auto vel = values(pd.array("velocity"), n);
  const auto omega = values(pd.array("angular_velocity"), n);
  const auto force = values(pd.array("force"), n);
  const auto torque = values(pd.array("torque"), n);
  const auto contacts = values(pd.array("contacts"), n);
  EXPECT_EQ(pd.array("contacts").attr.at("type"), "Int32");

  for (std::size_t k = 0; k < n; ++k) EXPECT_EQ(ids[k], 10.0 + static_cast<double>(k));
  // Equal-volume radius (SPEC 2): (abc)^(1/3); 1e-18 m is round-off of cbrt.
  EXPECT_NEAR(radius[0], 1 * mm, 1e-18);
  EXPECT_NEAR(radius[2], std::cbrt(1.5 * 1.0 * 0.6) * mm, 1e-18);
  EXPECT_NEAR(radius[3], std::cbrt(1.2 * 0.9 * 0.7) * mm, 1e-18);
  for (int c = 0; c < 3; ++c) EXPECT_EQ(semi[3 * 2 + c], semi2[c]);

  // Orientation w x y z of particle 3: 120 deg about (1,1,1) is (1/2, 1/2, 1/2, 1/2).
  for (int c = 0; c < 4; ++c) EXPECT_NEAR(orient[4 * 3 + c], 0.5, 1e-15);

  const auto tensor_of = [&](std::size_t k) {
    Mat3 t;
    for (int a = 0; a < 3; ++a)
      for (int b = 0; b < 3; ++b) t(a, b) = tensor[9 * k + 3 * a + b];
    return t;
  };
  // Shape tensor (SPEC 2 body -> world): round-off of R D R^T is ~1e-16 of a (1e-19 m); 1e-17 m.
  const double tol_t = 1e-17;
  // Particle 3, by hand: T = a e_y e_y^T + b e_z e_z^T + c e_x e_x^T = diag(c, a, b).
  const Mat3 t3 = tensor_of(3);
  const Mat3 t3_expected = Vec3(semi3.z(), semi3.x(), semi3.y()).asDiagonal();
  for (int a = 0; a < 3; ++a)
    for (int b = 0; b < 3; ++b) EXPECT_NEAR(t3(a, b), t3_expected(a, b), tol_t) << a << b;
  // Particle 2 at a generic orientation: symmetric, T (R e_k) = a_k (R e_k) with R from
  // Rodrigues' formula, and its eigenvalues are the semi-axes.
  const Mat3 t2 = tensor_of(2);
  const Mat3 r2 = rodrigues(axis2, angle2);
  EXPECT_EQ((t2 - t2.transpose()).norm(), 0.0);  // written exactly symmetric
  for (int k = 0; k < 3; ++k) {
    const Vec3 axis = r2.col(k);
    EXPECT_NEAR((t2 * axis - semi2[k] * axis).norm(), 0.0, tol_t) << "body axis " << k;
  }
  const Eigen::SelfAdjointEigenSolver<Mat3> eig(t2);
  for (int k = 0; k < 3; ++k) EXPECT_NEAR(eig.eigenvalues()[k], semi2[2 - k], tol_t);  // ascending
  // A sphere's tensor is R I.
  const Mat3 t0 = tensor_of(0);
  EXPECT_NEAR((t0 - 1 * mm * Mat3::Identity()).norm(), 0.0, tol_t);

  // Velocities as set (exact copies).
  EXPECT_EQ(tuple3(vel, 2), Vec3(0.1, -0.2, 0.3));
  EXPECT_EQ(tuple3(omega, 3), Vec3(0, 5, 0));
  EXPECT_EQ(tuple3(vel, 0), Vec3::Zero());

  // Hertz (SPEC 4) on the touching pair: branch 0 -> 1 is h (0.17, 0, 0) = 1.7 mm along x,
  // delta = 0.3 mm, R_e = 0.5 mm, F = 4/3 E* sqrt(R_e) delta^(3/2); at rest, so no tangential
  // force; repulsive: +F x on 1, -F x on 0; the force passes through the centres: no torque.
  const double f = 4.0 / 3.0 * model.material.effective_modulus() * std::sqrt(0.5 * mm) * std::pow(0.3 * mm, 1.5);
  const double tol_f = 1e-12 * f;  // delta is a difference of lengths 7x larger: ~1e-15 relative
  const Vec3 f0 = tuple3(force, 0), f1 = tuple3(force, 1);
  for (int c = 0; c < 3; ++c) {
    EXPECT_NEAR(f0[c], c == 0 ? -f : 0.0, tol_f);
    EXPECT_NEAR(f1[c], c == 0 ? f : 0.0, tol_f);
  }
  for (std::size_t k = 2; k < n; ++k) EXPECT_EQ(tuple3(force, k), Vec3::Zero()) << k;
  for (std::size_t k = 0; k < n; ++k) EXPECT_NEAR(tuple3(torque, k).norm(), 0.0, tol_f * 1 * mm) << k;

  // Contacts with overlap > 0 (SPEC 7): the pair 0-1 only; 1-4 is listed but apart.
  const std::vector<double> expected_contacts{1, 1, 0, 0, 0};
  for (std::size_t k = 0; k < n; ++k) EXPECT_EQ(contacts[k], expected_contacts[k]) << k;

  // Field data: the cell, the time (ParaView's TimeValue) and the step.
  const Node& fd = grid.child("FieldData");
  const auto hm = values(fd.array("cell_matrix"), 1);
  // Column-major (VTK's tensor order): a1 = (10, 0, 0), a2 = (1, 10, 0), a3 = (0, 0, 10) mm.
  const double h_expected[9] = {10 * mm, 0, 0, 1 * mm, 10 * mm, 0, 0, 0, 10 * mm};
  for (int k = 0; k < 9; ++k) EXPECT_EQ(hm[k], h_expected[k]) << k;
  EXPECT_EQ(values(fd.array("TimeValue"), 1)[0], 1.25e-3);
  EXPECT_EQ(values(fd.array("step"), 1)[0], 4711.0);
  // Love-Weber stress of the one contact (SPEC 7): sigma_11 = F l / V, l = 1.7 mm, V = 1000 mm^3.
  const auto sigma = values(fd.array("stress"), 1);
  const double sigma11 = f * 1.7 * mm / (1000 * mm * mm * mm);
  EXPECT_NEAR(sigma[0], sigma11, 1e-12 * sigma11);  // as tol_f
  fs::remove_all(dir);
}

INSTANTIATE_TEST_SUITE_P(Vtk, VtkFormat, ::testing::Values(VtkEncoding::binary, VtkEncoding::ascii),
                         [](const auto& p) { return p.param == VtkEncoding::ascii ? "ascii" : "binary"; });

// The cell box: 8 corners h {0,1}^3 and 12 lines, each an edge along one cell vector (SPEC 3).
TEST(Vtk, CellBoxHasTheTwelveEdgesOfTheCell) {
  Mat3 h;
  h << 10, 1, 0.5, 0, 10, -2, 0, 0, 9;
  h *= mm;
  const fs::path dir = temp_dir("cell");
  write_cell_vtu(dir / "cell.vtu", make_cell(h), 0.5, 7);
  const Node root = parse_file(dir / "cell.vtu");
  const Node& piece = root.child("UnstructuredGrid").child("Piece");
  ASSERT_EQ(piece.attr.at("NumberOfPoints"), "8");
  ASSERT_EQ(piece.attr.at("NumberOfCells"), "12");
  const auto x = values(piece.child("Points").child("DataArray"), 8);
  const auto conn = values(piece.child("Cells").array("connectivity"), 24);
  const auto offs = values(piece.child("Cells").array("offsets"), 12);
  const auto types = values(piece.child("Cells").array("types"), 12);
  // Every corner is h times a vertex of the unit cube, each vertex once.
  std::vector<int> seen(8, 0);
  for (std::size_t k = 0; k < 8; ++k) {
    const Vec3 s = h.inverse() * tuple3(x, k);
    const Vec3 r = s.array().round();
    EXPECT_NEAR((s - r).norm(), 0.0, 1e-12) << k;  // round-off of h^-1 h
    ASSERT_TRUE((r.array() >= 0).all() && (r.array() <= 1).all());
    ++seen[static_cast<std::size_t>(r.x() + 2 * r.y() + 4 * r.z())];
  }
  for (int s : seen) EXPECT_EQ(s, 1);
  // Each line joins corners one cell vector apart; 4 lines per cell vector.
  int per_vector[3] = {0, 0, 0};
  for (std::size_t e = 0; e < 12; ++e) {
    EXPECT_EQ(types[e], 3.0);  // VTK_LINE
    EXPECT_EQ(offs[e], 2.0 * static_cast<double>(e + 1));
    const Vec3 d = tuple3(x, static_cast<std::size_t>(conn[2 * e + 1])) - tuple3(x, static_cast<std::size_t>(conn[2 * e]));
    for (int c = 0; c < 3; ++c)
      if ((d - h.col(c)).norm() < 1e-15 || (d + h.col(c)).norm() < 1e-15) ++per_vector[c];
  }
  for (int c = 0; c < 3; ++c) EXPECT_EQ(per_vector[c], 4) << c;
  fs::remove_all(dir);
}

// The collection lists every snapshot with its time, in order, with XML-escaped names.
TEST(Vtk, PvdListsTheSeries) {
  const fs::path dir = temp_dir("pvd");
  write_pvd(dir / "series.pvd", {{0.0, "snapshot-0000.vtu"}, {2.5e-4, "snapshot-0001.vtu"}, {5e-4, "a&b.vtu"}});
  EXPECT_FALSE(fs::exists(dir / "series.pvd.tmp"));
  const Node root = parse_file(dir / "series.pvd");
  EXPECT_EQ(root.attr.at("type"), "Collection");
  const Node& coll = root.child("Collection");
  ASSERT_EQ(coll.children.size(), 3u);
  const std::vector<std::pair<double, std::string>> expected{{0.0, "snapshot-0000.vtu"}, {2.5e-4, "snapshot-0001.vtu"}, {5e-4, "a&b.vtu"}};
  for (std::size_t k = 0; k < 3; ++k) {
    EXPECT_EQ(coll.children[k].name, "DataSet");
    EXPECT_EQ(std::stod(coll.children[k].attr.at("timestep")), expected[k].first);  // shortest round trip
    EXPECT_EQ(coll.children[k].attr.at("file"), expected[k].second);
  }
  fs::remove_all(dir);
}

// The parser used above rejects what it must (so that passing tests mean well-formed files).
TEST(Vtk, TestParserRejectsMalformedXml) {
  EXPECT_THROW(XmlParser("<?xml version=\"1.0\"?>\n<a><b></a>").document(), std::runtime_error);
  EXPECT_THROW(XmlParser("<a></a>").document(), std::runtime_error);
  EXPECT_THROW(XmlParser("<?xml version=\"1.0\"?>\n<a>").document(), std::runtime_error);
  EXPECT_NO_THROW(XmlParser("<?xml version=\"1.0\"?>\n<a x=\"1\"><b/>t</a>\n").document());
}
