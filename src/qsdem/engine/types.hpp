// Basic numeric types shared by every module.
#pragma once
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <functional>
#include <map>
#include <stdexcept>
#include <string>
#include <string_view>

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

enum class ShapeKind : std::uint8_t { sphere = 0, ellipsoid = 1 };
inline const char* to_string(ShapeKind k) { return k == ShapeKind::sphere ? "sphere" : "ellipsoid"; }
// What the particle damping acts on (damping/models.hpp).
enum class DampedMotion : std::uint8_t { both, translation, rotation };
inline const char* to_string(DampedMotion m) {
  switch (m) {
    case DampedMotion::both: return "both";
    case DampedMotion::translation: return "translation";
    case DampedMotion::rotation: return "rotation";
  }
  return "?";
}

// Per-particle inertia (density) scaling of a phase (SPEC 5.6): each particle's mass and moments
// are multiplied by mu_i = min(cap, (R* / R_i)^2) so that its critical step 2 R_i sqrt(mu_i rho / E)
// reaches 2 R* sqrt(rho / E), with R* = R_max (coarsest) or factor R_min (factor).
struct InertiaScaling {
  enum class Target : std::uint8_t { none, coarsest, factor } target = Target::none;
  double factor = 1;  // Target::factor: the target step over the unscaled t_c (> 1)
  double cap = 100;   // the largest mu_i (>= 1)
  bool on() const { return target != Target::none; }
};

// The [contact] table: the contact law (contact/laws.hpp) and the values of its own keys.
struct ContactSettings {
  std::string law = "hertz_mindlin";
  std::map<std::string, double, std::less<>> values;  // the law's keys that the case gives

  bool has(std::string_view key) const { return values.find(key) != values.end(); }
  double value(std::string_view key) const { return values.find(key)->second; }
};

// Loops shorter than this run on one thread: below it, the cost of waking the OpenMP team
// exceeds the work.
inline constexpr std::size_t parallel_threshold = 4096;

}  // namespace qsdem
