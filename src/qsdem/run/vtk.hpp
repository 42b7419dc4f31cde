// Snapshots for ParaView (docs/visualisation.md): VTK XML UnstructuredGrid (.vtu) files with one
// vertex cell per particle, the cell box as a separate .vtu of 12 lines, and a .pvd collection
// that loads a series of snapshots as a time series.
//
// Particle file, point data (all Float64 unless said):
//   semi_axes (3)         a >= b >= c, body frame (m)
//   orientation (4)       quaternion w x y z, body -> world
//   shape_tensor (9)      R diag(a, b, c) R^T (m), symmetric: Tensor Glyph with a sphere of
//                         radius 1 and scale factor 1 draws the true ellipsoid
//   velocity (3)          fluctuation velocity v (m/s)
//   angular_velocity (3)  world frame (rad/s)
//   force (3), torque (3) contact resultants (N, N m)
//   contacts              Int32, contacts with overlap > 0 of the particle
//   radius                equal-volume radius (abc)^(1/3) (m)
//   id                    UInt32, stable particle id
// Field data: cell_matrix (9, h column-major as VTK orders tensors, i.e. the cell vectors a1,
// a2, a3 in turn, m), TimeValue (s, the name ParaView reads as the time of a file), step
// (Int64), stress (9, Pa, compression positive, from the last force evaluation).
#pragma once
#include <filesystem>
#include <vector>

#include "qsdem/engine/state.hpp"

namespace qsdem {

// binary: inline base64 with a UInt64 byte-count header (VTK's default encoding, ~2x smaller and
// faster to load than ascii, values bit-exact); ascii: shortest round-trip decimal text.
enum class VtkEncoding { binary, ascii };

// Centres are wrapped into the cell (fractional coordinates in [0, 1)). Written atomically.
void write_vtu(const std::filesystem::path& path, const State& state,
               VtkEncoding encoding = VtkEncoding::binary);

// The cell box: its 8 corners h {0,1}^3 and 12 VTK_LINE edges, with the same field data.
void write_cell_vtu(const std::filesystem::path& path, const Cell& cell, double time, long step);

struct PvdEntry {
  double time = 0;              // s
  std::filesystem::path file;   // relative to the .pvd's directory
};

// A ParaView collection: one DataSet per entry, in the order given. Written atomically, so
// rewriting it after each snapshot keeps a readable series during a run.
void write_pvd(const std::filesystem::path& path, const std::vector<PvdEntry>& entries);

}  // namespace qsdem
