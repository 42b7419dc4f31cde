// The packing text format (docs/packing-format.md): the cell and, per particle, centre,
// semi-axes and orientation, in metres. Used to hand a compacted sample to a benchmark or a
// peer code, and to start a run from a given packing.
//
//   # comment
//   format qsdem-packing 1
//   cell h11 h12 h13 h21 h22 h23 h31 h32 h33      (rows of h; columns are the cell vectors)
//   particles N
//   x y z a b c qw qx qy qz                       (N lines)
#pragma once
#include <filesystem>
#include <string>

#include "qsdem/engine/state.hpp"

namespace qsdem {

std::string format_packing(const Particles& p, const Cell& cell);
void write_packing(const std::filesystem::path& path, const Particles& p, const Cell& cell);

// Reads a packing into particles at rest (mass properties from `density`) and its cell.
State read_packing(const std::filesystem::path& path, double density);
// The same from text; `name` is used in error messages.
State parse_packing(std::istream& in, const std::string& name, double density);

}  // namespace qsdem
