// Basic numeric types shared by every module.
#pragma once
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <stdexcept>
#include <string>

namespace qsdem {

using Vec3 = Eigen::Vector3d;
using Mat3 = Eigen::Matrix3d;
using Quat = Eigen::Quaterniond;
using Vec3i = Eigen::Matrix<std::int32_t, 3, 1>;

// Any error a user can fix (bad input, impossible request). The CLI prints what() and exits 2.
struct InputError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// A run that cannot continue (blow-up, no equilibrium within the step limit). The CLI exits 3.
struct RunError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

inline constexpr double pi = 3.14159265358979323846;

// Loops shorter than this run on one thread: below it, the cost of waking the OpenMP team
// exceeds the work.
inline constexpr std::size_t parallel_threshold = 4096;

}  // namespace qsdem
