// The periodic cell (SPEC 3): matrix h whose columns are the cell vectors, velocity gradient
// L (dh/dt = L h). Positions are fractional s = h^-1 x, so the affine field moves with h and
// particle velocities are fluctuations about it.
#pragma once
#include "qsdem/engine/types.hpp"

namespace qsdem {

struct Cell {
  Mat3 h = Mat3::Identity();
  Mat3 h_inv = Mat3::Identity();
  Mat3 L = Mat3::Zero();  // velocity gradient (1/s) applied over the current step
  double volume = 1.0;

  // Perpendicular widths V / |a_j x a_k| of the three cell faces (m).
  Vec3 widths() const;
  Vec3 to_cartesian(const Vec3& s) const { return h * s; }
};

Cell make_cell(const Mat3& h);
void set_matrix(Cell& cell, const Mat3& h);

// Advances the cell over one step with the current velocity gradient: h <- (I + dt L) h.
void deform(Cell& cell, double dt);

// The cell matrix by its entries: x = h s component by component, for branch_vector below and for
// the pair loop's vector lanes (forces.cpp). Sums in a fixed order (rows 1, 2 left to right, row 3
// right to left), the same in scalar and vector code.
struct CellMap {
  double h00, h01, h02, h10, h11, h12, h20, h21, h22;
  explicit CellMap(const Mat3& h)
      : h00(h(0, 0)), h01(h(0, 1)), h02(h(0, 2)), h10(h(1, 0)), h11(h(1, 1)), h12(h(1, 2)), h20(h(2, 0)),
        h21(h(2, 1)), h22(h(2, 2)) {}
  [[gnu::always_inline]] void apply(double sx, double sy, double sz, double& x, double& y, double& z) const {
    x = (h00 * sx + h01 * sy) + h02 * sz, y = (h10 * sx + h11 * sy) + h12 * sz, z = h20 * sx + (h21 * sy + h22 * sz);
  }
};

// Branch vector from particle i to the periodic image `image` of particle j (SPEC 3):
// l = h (s_j - s_i + image).
inline Vec3 branch_vector(const Cell& cell, const Vec3& si, const Vec3& sj, const Vec3i& image) {
  const Vec3 f = sj - si + image.cast<double>();
  Vec3 l;
  CellMap(cell.h).apply(f.x(), f.y(), f.z(), l.x(), l.y(), l.z());
  return l;
}

// Minimum-image integer shift for a fractional difference d = sj - si: the image k with
// d + k in [-1/2, 1/2). Exact for orthorhombic cells and for the broad phase's use.
inline Vec3i minimum_image(const Vec3& d) {
  return Vec3i(static_cast<int>(-std::floor(d.x() + 0.5)), static_cast<int>(-std::floor(d.y() + 0.5)),
               static_cast<int>(-std::floor(d.z() + 0.5)));
}

}  // namespace qsdem
