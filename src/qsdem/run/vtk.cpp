#include "qsdem/run/vtk.hpp"

#include <fmt/format.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <string>
#include <type_traits>

#include "qsdem/run/output.hpp"

namespace qsdem {

namespace {

template <class T>
constexpr const char* vtk_type_name() {
  if constexpr (std::is_same_v<T, double>) return "Float64";
  else if constexpr (std::is_same_v<T, std::int64_t>) return "Int64";
  else if constexpr (std::is_same_v<T, std::int32_t>) return "Int32";
  else if constexpr (std::is_same_v<T, std::uint32_t>) return "UInt32";
  else if constexpr (std::is_same_v<T, std::uint8_t>) return "UInt8";
}

constexpr const char* byte_order = std::endian::native == std::endian::little ? "LittleEndian" : "BigEndian";

void append_base64(std::string& out, const std::string& bytes) {
  static constexpr char alphabet[] = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  const auto byte = [&](std::size_t k) { return static_cast<std::uint32_t>(static_cast<unsigned char>(bytes[k])); };
  std::size_t k = 0;
  for (; k + 3 <= bytes.size(); k += 3) {
    const std::uint32_t w = byte(k) << 16 | byte(k + 1) << 8 | byte(k + 2);
    for (int s = 18; s >= 0; s -= 6) out += alphabet[(w >> s) & 63];
  }
  const std::size_t rest = bytes.size() - k;
  if (rest > 0) {
    const std::uint32_t w = byte(k) << 16 | (rest == 2 ? byte(k + 1) << 8 : 0u);
    out += alphabet[(w >> 18) & 63];
    out += alphabet[(w >> 12) & 63];
    out += rest == 2 ? alphabet[(w >> 6) & 63] : '=';
    out += '=';
  }
}

// One <DataArray> of `values.size() / ncomp` tuples. Binary: base64 of a UInt64 byte count
// followed by the raw values, encoded together (VTK's uncompressed inline layout).
template <class T>
void data_array(std::string& out, const char* name, int ncomp, const std::vector<T>& values, VtkEncoding enc,
                const std::string& extra = "") {
  out += fmt::format(R"(        <DataArray type="{}" Name="{}" NumberOfComponents="{}"{} format="{}">)",
                     vtk_type_name<T>(), name, ncomp, extra, enc == VtkEncoding::binary ? "binary" : "ascii");
  if (enc == VtkEncoding::binary) {
    const std::uint64_t nbytes = values.size() * sizeof(T);
    std::string bytes(sizeof nbytes + nbytes, '\0');
    std::memcpy(bytes.data(), &nbytes, sizeof nbytes);
    if (nbytes > 0) std::memcpy(bytes.data() + sizeof nbytes, values.data(), nbytes);
    out += "\n          ";
    append_base64(out, bytes);
    out += '\n';
  } else {
    const std::size_t nc = static_cast<std::size_t>(ncomp);
    for (std::size_t k = 0; k < values.size(); ++k) {
      out += k % nc == 0 ? "\n          " : " ";
      if constexpr (std::is_same_v<T, double>) out += fmt::format("{}", values[k]);  // shortest round trip
      else out += fmt::format("{}", static_cast<std::int64_t>(values[k]));
    }
    out += '\n';
  }
  out += "        </DataArray>\n";
}

// Field data is a few numbers: always ascii, exact.
void field_data(std::string& out, const Mat3& h, double time, long step, const Mat3* stress) {
  // VTK's order for a 9-component tensor is column-major (T_ij = component i + 3 j), so that
  // ParaView's Python view of the array is the matrix itself; for h: a1, a2, a3 in turn.
  const auto column_major = [](const Mat3& m) {
    std::string s;
    for (int c = 0; c < 3; ++c)
      for (int r = 0; r < 3; ++r) s += fmt::format("{}{}", r + c == 0 ? "" : " ", m(r, c));
    return s;
  };
  out += "    <FieldData>\n";
  out += fmt::format(R"(      <DataArray type="Float64" Name="cell_matrix" NumberOfComponents="9" NumberOfTuples="1" format="ascii">{}</DataArray>)",
                     column_major(h));
  out += '\n';
  out += fmt::format(R"(      <DataArray type="Float64" Name="TimeValue" NumberOfTuples="1" format="ascii">{}</DataArray>)", time);
  out += '\n';
  out += fmt::format(R"(      <DataArray type="Int64" Name="step" NumberOfTuples="1" format="ascii">{}</DataArray>)", step);
  out += '\n';
  if (stress) {
    out += fmt::format(R"(      <DataArray type="Float64" Name="stress" NumberOfComponents="9" NumberOfTuples="1" format="ascii">{}</DataArray>)",
                       column_major(*stress));
    out += '\n';
  }
  out += "    </FieldData>\n";
}

std::string file_header() {
  return fmt::format("<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"{}\" "
                     "header_type=\"UInt64\">\n  <UnstructuredGrid>\n",
                     byte_order);
}

// Closes <Points>, writes the <Cells> of an UnstructuredGrid piece and closes the file.
void finish_unstructured_grid(std::string& out, const std::vector<std::int64_t>& connectivity,
                              const std::vector<std::int64_t>& offsets, const std::vector<std::uint8_t>& types,
                              VtkEncoding enc) {
  out += "      </Points>\n      <Cells>\n";
  data_array(out, "connectivity", 1, connectivity, enc);
  data_array(out, "offsets", 1, offsets, enc);
  data_array(out, "types", 1, types, enc);
  out += "      </Cells>\n    </Piece>\n  </UnstructuredGrid>\n</VTKFile>\n";
}

template <class V>
std::vector<double> flatten(const std::vector<V>& v) {
  std::vector<double> out;
  out.reserve(v.size() * static_cast<std::size_t>(V::SizeAtCompileTime));
  for (const V& x : v)
    for (Eigen::Index c = 0; c < x.size(); ++c) out.push_back(x[c]);
  return out;
}

std::string xml_attribute(const std::string& s) {
  std::string out;
  for (char ch : s) {
    switch (ch) {
      case '&': out += "&amp;"; break;
      case '<': out += "&lt;"; break;
      case '>': out += "&gt;"; break;
      case '"': out += "&quot;"; break;
      default: out += ch;
    }
  }
  return out;
}

}  // namespace

void write_vtu(const std::filesystem::path& path, const State& state, VtkEncoding enc) {
  const Particles& p = state.particles;
  const std::size_t n = p.size();

  std::vector<Vec3> centre(n);
  std::vector<double> orientation, shape_tensor;
  orientation.reserve(4 * n);
  shape_tensor.reserve(9 * n);
  for (std::size_t k = 0; k < n; ++k) {
    const Vec3 s = p.s[k];
    centre[k] = state.cell.h * (s.array() - s.array().floor()).matrix();  // wrapped into the cell
    const Quat q = p.q[k];
    orientation.insert(orientation.end(), {q.w(), q.x(), q.y(), q.z()});
    const Mat3 r = q.toRotationMatrix();
    const Mat3 rdr = r * p.semi_axes[k].asDiagonal() * r.transpose();
    const Mat3 t = 0.5 * (rdr + rdr.transpose());  // exactly symmetric (no aliasing: new matrix)
    for (int a = 0; a < 3; ++a)
      for (int b = 0; b < 3; ++b) shape_tensor.push_back(t(a, b));
  }

  // Contacts per particle: listed pairs that touch (overlap > 0) at the last force evaluation.
  std::vector<std::int32_t> contacts(n, 0);
  const PairList& pairs = state.pairs;
  const std::size_t np = std::min(pairs.size(), pairs.overlap.size());
  for (std::size_t k = 0; k < np; ++k) {
    if (!(pairs.overlap[k] > 0)) continue;
    ++contacts[pairs.i[k]];
    ++contacts[pairs.j[k]];
  }

  std::vector<std::int64_t> connectivity(n), offsets(n);
  for (std::size_t k = 0; k < n; ++k) {
    connectivity[k] = static_cast<std::int64_t>(k);
    offsets[k] = static_cast<std::int64_t>(k + 1);
  }
  const std::vector<std::uint8_t> types(n, 1);  // VTK_VERTEX

  std::string out = file_header();
  field_data(out, state.cell.h, state.time, state.step, &state.stress);
  out += fmt::format("    <Piece NumberOfPoints=\"{}\" NumberOfCells=\"{}\">\n", n, n);
  out += "      <PointData Scalars=\"radius\" Vectors=\"velocity\" Tensors=\"shape_tensor\">\n";
  data_array(out, "semi_axes", 3, flatten(p.semi_axes), enc);
  data_array(out, "orientation", 4, orientation, enc,
             R"( ComponentName0="w" ComponentName1="x" ComponentName2="y" ComponentName3="z")");
  data_array(out, "shape_tensor", 9, shape_tensor, enc);
  data_array(out, "velocity", 3, flatten(p.v), enc);
  data_array(out, "angular_velocity", 3, flatten(p.omega), enc);
  data_array(out, "force", 3, flatten(p.force), enc);
  data_array(out, "torque", 3, flatten(p.torque), enc);
  data_array(out, "contacts", 1, contacts, enc);
  data_array(out, "radius", 1, p.equiv_radius, enc);
  data_array(out, "id", 1, p.id, enc);
  out += "      </PointData>\n      <Points>\n";
  data_array(out, "centre", 3, flatten(centre), enc);
  finish_unstructured_grid(out, connectivity, offsets, types, enc);
  write_file_atomic(path, out);
}

void write_cell_vtu(const std::filesystem::path& path, const Cell& cell, double time, long step) {
  // Corner c has fractional coordinates (c & 1, c >> 1 & 1, c >> 2 & 1); an edge joins two
  // corners that differ in one bit.
  std::vector<double> corners;
  for (int c = 0; c < 8; ++c) {
    const Vec3 x = cell.h * Vec3(c & 1, c >> 1 & 1, c >> 2 & 1);
    corners.insert(corners.end(), {x.x(), x.y(), x.z()});
  }
  std::vector<std::int64_t> connectivity, offsets;
  for (int c = 0; c < 8; ++c)
    for (int bit = 1; bit < 8; bit <<= 1)
      if (!(c & bit)) {
        connectivity.insert(connectivity.end(), {c, c | bit});
        offsets.push_back(static_cast<std::int64_t>(connectivity.size()));
      }
  const std::vector<std::uint8_t> types(offsets.size(), 3);  // VTK_LINE

  const VtkEncoding enc = VtkEncoding::ascii;  // 8 points: text is as small as binary
  std::string out = file_header();
  field_data(out, cell.h, time, step, nullptr);
  out += fmt::format("    <Piece NumberOfPoints=\"8\" NumberOfCells=\"{}\">\n      <Points>\n", offsets.size());
  data_array(out, "corner", 3, corners, enc);
  finish_unstructured_grid(out, connectivity, offsets, types, enc);
  write_file_atomic(path, out);
}

void write_pvd(const std::filesystem::path& path, const std::vector<PvdEntry>& entries) {
  std::string out = fmt::format("<?xml version=\"1.0\"?>\n<VTKFile type=\"Collection\" version=\"0.1\" byte_order=\"{}\">\n"
                                "  <Collection>\n",
                                byte_order);
  for (const PvdEntry& e : entries)
    out += fmt::format("    <DataSet timestep=\"{}\" group=\"\" part=\"0\" file=\"{}\"/>\n", e.time,
                       xml_attribute(e.file.generic_string()));
  out += "  </Collection>\n</VTKFile>\n";
  write_file_atomic(path, out);
}

}  // namespace qsdem
