// A per-particle field of 3-vectors or quaternions stored as one array per component (structure
// of arrays): for the fields that vector lanes stream contiguously (the drift's turn) and no pair
// loop gathers by particle index (those stay arrays of Vec3: one cache line per gather).
#pragma once
#include <algorithm>
#include <array>
#include <cstddef>
#include <new>
#include <type_traits>
#include <vector>

#include "qsdem/engine/types.hpp"

namespace qsdem {

// The components of a 3-vector (x, y, z) or a quaternion (Eigen's order x, y, z, w).
inline const double* coefficients(const Vec3& x) { return x.data(); }
inline double* coefficients(Vec3& x) { return x.data(); }
inline const double* coefficients(const Quat& x) { return x.coeffs().data(); }
inline double* coefficients(Quat& x) { return x.coeffs().data(); }

// Cache-line aligned allocation: lanes that start at a multiple of 8 elements load whole lines.
template <class T>
struct CacheLineAllocator {
  using value_type = T;
  static constexpr std::align_val_t alignment{64};
  CacheLineAllocator() = default;
  template <class U>
  CacheLineAllocator(const CacheLineAllocator<U>&) noexcept {}
  T* allocate(std::size_t n) { return static_cast<T*>(::operator new(n * sizeof(T), alignment)); }
  void deallocate(T* p, std::size_t) noexcept { ::operator delete(p, alignment); }
  template <class U>
  bool operator==(const CacheLineAllocator<U>&) const noexcept {
    return true;
  }
};

template <class T>
class ComponentArrays {
 public:
  static_assert(std::is_same_v<T, Vec3> || std::is_same_v<T, Quat>);
  static constexpr int width = std::is_same_v<T, Quat> ? 4 : 3;  // components, as `coefficients` orders them
  using Component = std::vector<double, CacheLineAllocator<double>>;
  using Components = std::array<Component, width>;

  std::size_t size() const { return c_[0].size(); }
  void resize(std::size_t n) {
    for (auto& c : c_) c.resize(n, 0.0);
  }

  // By value and const: an assignment to an element does not compile (write with set).
  const T operator[](std::size_t i) const {
    T x;
    for (int k = 0; k < width; ++k) coefficients(x)[k] = c_[k][i];
    return x;
  }
  void set(std::size_t i, const T& x) {
    for (int k = 0; k < width; ++k) c_[k][i] = coefficients(x)[k];
  }
  void fill(const T& x) {
    for (int k = 0; k < width; ++k) std::fill(c_[k].begin(), c_[k].end(), coefficients(x)[k]);
  }

  bool operator==(const ComponentArrays&) const = default;

  double* component(int k) { return c_[k].data(); }
  const double* component(int k) const { return c_[k].data(); }
  Components& components() { return c_; }
  const Components& components() const { return c_; }

  // The elements as one array of T (the checkpoint's byte layout), and back.
  std::vector<T> interleaved() const {
    std::vector<T> out(size());
    for (std::size_t i = 0; i < out.size(); ++i) out[i] = (*this)[i];
    return out;
  }
  void assign(const std::vector<T>& from) {
    resize(from.size());
    for (std::size_t i = 0; i < from.size(); ++i) set(i, from[i]);
  }

 private:
  Components c_;
};

}  // namespace qsdem
