#include "qsdem/engine/cell.hpp"

#include <Eigen/LU>

namespace qsdem {

Vec3 Cell::widths() const {
  const Vec3 a = h.col(0), b = h.col(1), c = h.col(2);
  return Vec3(volume / b.cross(c).norm(), volume / c.cross(a).norm(), volume / a.cross(b).norm());
}

void set_matrix(Cell& cell, const Mat3& h) {
  cell.h = h;
  cell.h_inv = h.inverse();
  cell.volume = h.determinant();
}

Cell make_cell(const Mat3& h) {
  Cell c;
  set_matrix(c, h);
  return c;
}

void deform(Cell& cell, double dt) { set_matrix(cell, (Mat3::Identity() + dt * cell.L) * cell.h); }

}  // namespace qsdem
