// The periodic cell (SPEC 3): matrix h whose columns are the cell vectors, velocity gradient
// L (dh/dt = L h). Positions are fractional s = h^-1 x, so the affine field moves with h and
// particle velocities are fluctuations about it.
#pragma once
#include "qsdem/types.hpp"

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

// Branch vector from particle i to the periodic image `image` of particle j (SPEC 3).
inline Vec3 branch_vector(const Cell& cell, const Vec3& si, const Vec3& sj, const Vec3i& image) {
  return cell.h * (sj - si + image.cast<double>());
}

// Minimum-image integer shift for a fractional difference d = sj - si: the image k with
// d + k in [-1/2, 1/2). Exact for orthorhombic cells and for the broad phase's use.
inline Vec3i minimum_image(const Vec3& d) {
  return Vec3i(static_cast<int>(-std::floor(d.x() + 0.5)), static_cast<int>(-std::floor(d.y() + 0.5)),
               static_cast<int>(-std::floor(d.z() + 0.5)));
}

}  // namespace qsdem
