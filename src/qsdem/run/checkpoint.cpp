#include "qsdem/run/checkpoint.hpp"

#include <fcntl.h>
#include <fmt/format.h>
#include <unistd.h>

#include <cstring>
#include <algorithm>
#include <cmath>
#include <limits>
#include <tuple>
#include <type_traits>

#include "qsdem/engine/contact/laws.hpp"
#include "qsdem/run/controller.hpp"
#include "qsdem/run/files.hpp"

namespace qsdem {
namespace {

constexpr char magic[8] = {'Q', 'S', 'D', 'E', 'M', 'C', 'K', 'P'};
constexpr std::size_t header_size = 8 + 4 + 4 + 8 + 8;

// Appends plain values and arrays of them to a byte buffer.
class BinaryWriter {
 public:
  template <class T>
  void pod(const T& v) {
    static_assert(std::is_trivially_copyable_v<T>);
    const auto* b = reinterpret_cast<const char*>(&v);
    out.insert(out.end(), b, b + sizeof(T));
  }
  template <class Scalar, int R, int C>
  void pod(const Eigen::Matrix<Scalar, R, C>& m) {
    for (int k = 0; k < m.size(); ++k) pod(m.data()[k]);
  }
  void pod(const Quat& q) { pod(q.coeffs()); }
  template <class T>
  void vec(const std::vector<T>& v) {
    pod(static_cast<std::uint64_t>(v.size()));
    for (const T& x : v) pod(x);
  }
  // Component arrays as the array of T they hold (one layout in the file).
  template <class T>
  void vec(const ComponentArrays<T>& v) {
    pod(static_cast<std::uint64_t>(v.size()));
    for (std::size_t i = 0; i < v.size(); ++i) pod(v[i]);
  }
  void str(const std::string& s) {
    pod(static_cast<std::uint64_t>(s.size()));
    out.insert(out.end(), s.begin(), s.end());
  }
  // A per-pair array of w doubles per pair: the number of pairs, then the values.
  void pair_values(const std::vector<double>& v, std::size_t w) {
    pod(static_cast<std::uint64_t>(w > 0 ? v.size() / w : 0));
    for (const double x : v) pod(x);
  }
  std::vector<char> out;
};

// Reads what BinaryWriter wrote; any overrun is a damaged file.
class BinaryReader {
 public:
  BinaryReader(const char* data, std::size_t size, std::string file) : p_(data), end_(data + size), file_(std::move(file)) {}
  template <class T>
  void pod(T& v) {
    static_assert(std::is_trivially_copyable_v<T>);
    need(sizeof(T));
    std::memcpy(&v, p_, sizeof(T));
    p_ += sizeof(T);
  }
  template <class Scalar, int R, int C>
  void pod(Eigen::Matrix<Scalar, R, C>& m) {
    for (int k = 0; k < m.size(); ++k) pod(m.data()[k]);
  }
  void pod(Quat& q) { pod(q.coeffs()); }
  // A flag is the byte 0 or 1: any other value, copied into a bool, would be undefined behaviour.
  void pod(bool& v) {
    std::uint8_t b = 0;
    pod(b);
    if (b > 1) damaged(fmt::format("a flag holds {}, not 0 or 1", b));
    v = b == 1;
  }
  template <class T>
  void vec(std::vector<T>& v) {
    std::uint64_t n = 0;
    pod(n);
    if (n > static_cast<std::uint64_t>(end_ - p_) / sizeof(T)) damaged("an array is longer than the file");
    v.resize(n);
    for (T& x : v) pod(x);
  }
  template <class T>
  void vec(ComponentArrays<T>& v) {
    std::vector<T> elements;
    vec(elements);
    v.assign(elements);
  }
  void str(std::string& s) {
    std::uint64_t n = 0;
    pod(n);
    need(n);
    s.assign(p_, n);
    p_ += n;
  }
  void pair_values(std::vector<double>& v, std::size_t w) {
    std::uint64_t n = 0;
    pod(n);
    if (w > 0 && n > static_cast<std::uint64_t>(end_ - p_) / (w * sizeof(double)))
      damaged("an array is longer than the file");
    v.resize(w > 0 ? n * w : 0);
    for (double& x : v) pod(x);
  }
  bool at_end() const { return p_ == end_; }
  [[noreturn]] void damaged(const std::string& why) const {
    throw InputError(fmt::format("checkpoint '{}' is damaged: {}", file_, why));
  }
  [[noreturn]] void refuse(const std::string& why) const {
    throw InputError(fmt::format("checkpoint '{}' {}", file_, why));
  }

 private:
  void need(std::size_t n) const {
    if (static_cast<std::size_t>(end_ - p_) < n) damaged("it ends early");
  }
  const char* p_;
  const char* end_;
  std::string file_;
};

// One function per type, used in both directions so that the two can never disagree.
// The particles' arrays as their registry lists them (particles.hpp).
template <class IO, class P>
void io_particles(IO& io, P& p, std::uint32_t version) {
  for_each_field(p, [&](auto& array, ParticleField field) {
    if (field.saved_since != 0 && version >= field.saved_since) io.vec(array);
  });
}

template <class IO, class M>
void io_measures(IO& io, M& m, std::uint32_t version) {
  io.pod(m.stress);
  io.pod(m.principal);
  io.pod(m.mean_stress);
  io.pod(m.deviator);
  io.pod(m.octahedral);
  io.pod(m.friction_angle_deg);
  if (version >= 7) {
    io.pod(m.friction_angle_al_deg);
    io.pod(m.principal_tilt_deg);
  }
  io.pod(m.ufr);
  io.pod(m.iuf);
  io.pod(m.imom);
  io.pod(m.contacts);
  io.pod(m.coordination);
  io.pod(m.ekin_trans);
  io.pod(m.ekin_rot);
  io.pod(m.volume);
  io.pod(m.solid_volume);
  io.pod(m.void_ratio);
}

// Where a run of the default protocol was, as formats 1 to 6 kept it: its phase (0 compaction, 1
// triaxial, 2 done), the current phase's start, the compaction's end and the triaxial sums.
struct LegacyRun {
  std::int32_t phase = 0;
  bool phase_started = false;
  long phase_steps = 0, rows = 0;
  double v0 = 0;
  Mat3 h0 = Mat3::Identity();
  long compaction_steps = 0;
  double compaction_wall_s = 0;
  Measures compaction_final;
  int sums_rows = 0;
  double ufr = 0, iuf = 0, imom = 0, lateral_error = 0, max_lateral_error = 0;
  double peak_phi_deg = 0, peak_phi_e1 = 0, final_ev = 0, final_e1 = 0, sums_wall_s = 0;
  double wall_s = 0;
  long first_step = 0;
  bool prepare_only = false;
  std::string changes;
};

template <class IO, class R>
void io_legacy_run(IO& io, R& r, std::uint32_t version) {
  io.pod(r.phase);
  io.pod(r.phase_started);
  io.pod(r.phase_steps);
  io.pod(r.rows);
  io.pod(r.v0);
  io.pod(r.h0);
  io.pod(r.compaction_steps);
  io.pod(r.compaction_wall_s);
  io_measures(io, r.compaction_final, version);
  // The triaxial sums (before format 5: a struct's raw bytes, 4 bytes of padding after the row
  // count on LP64, and no wall time).
  io.pod(r.sums_rows);
  if (version < 5) {
    std::uint32_t padding = 0;
    io.pod(padding);
  }
  io.pod(r.ufr);
  io.pod(r.iuf);
  io.pod(r.imom);
  io.pod(r.lateral_error);
  io.pod(r.max_lateral_error);
  io.pod(r.peak_phi_deg);
  io.pod(r.peak_phi_e1);
  io.pod(r.final_ev);
  io.pod(r.final_e1);
  if (version >= 5) io.pod(r.sums_wall_s);
  io.pod(r.wall_s);
  if (version >= 2) io.pod(r.first_step);
  if (version >= 5) {
    io.pod(r.prepare_only);
    io.str(r.changes);
  }
}

// The default protocol's phases 0 (compaction) and 1 (triaxial) to and from the old layout.
RunProgress from_legacy(const LegacyRun& l) {
  RunProgress r;
  r.phase = l.phase;
  r.phase_started = l.phase_started;
  r.phases.resize(2);
  PhaseRecord& c = r.phases[0];
  PhaseRecord& t = r.phases[1];
  c.steps = l.phase == 0 ? l.phase_steps : l.compaction_steps;
  c.wall_s = l.compaction_wall_s;
  c.final = l.compaction_final;
  t.rows = l.sums_rows;
  t.ufr = l.ufr, t.iuf = l.iuf, t.imom = l.imom;
  t.stress_error = l.lateral_error, t.max_stress_error = l.max_lateral_error;
  t.peak_phi_deg = l.peak_phi_deg, t.peak_phi_e1 = l.peak_phi_e1;
  t.final_ev = l.final_ev, t.final_e1 = l.final_e1;
  t.wall_s = l.sums_wall_s;
  if (l.phase < 2) {
    PhaseRecord& now = r.phases[static_cast<std::size_t>(l.phase)];
    now.steps = l.phase_steps;
    now.rows = l.rows;
    now.v0 = l.v0;
    now.h0 = l.h0;
  }
  r.wall_s = l.wall_s;
  r.first_step = l.first_step;
  r.prepare_only = l.prepare_only;
  r.changes = l.changes;
  return r;
}

LegacyRun to_legacy(const RunProgress& r) {
  LegacyRun l;
  l.phase = r.phase;
  l.phase_started = r.phase_started;
  const std::size_t n = r.phases.size();
  if (static_cast<std::size_t>(r.phase) < n) {
    const PhaseRecord& now = r.current();
    l.phase_steps = now.steps;
    l.rows = now.rows;
    l.v0 = now.v0;
    l.h0 = now.h0;
  }
  if (n > 0) {
    l.compaction_steps = r.phases[0].steps;
    l.compaction_wall_s = r.phases[0].wall_s;
    l.compaction_final = r.phases[0].final;
  }
  if (n > 1) {
    const PhaseRecord& t = r.phases[1];
    l.sums_rows = static_cast<int>(t.rows);
    l.ufr = t.ufr, l.iuf = t.iuf, l.imom = t.imom;
    l.lateral_error = t.stress_error, l.max_lateral_error = t.max_stress_error;
    l.peak_phi_deg = t.peak_phi_deg, l.peak_phi_e1 = t.peak_phi_e1;
    l.final_ev = t.final_ev, l.final_e1 = t.final_e1;
    l.sums_wall_s = t.wall_s;
  }
  l.wall_s = r.wall_s;
  l.first_step = r.first_step;
  l.prepare_only = r.prepare_only;
  l.changes = r.changes;
  return l;
}

// Formats 7 to 12: any protocol. Every field on its own (no struct's raw bytes, so no padding).
template <class IO, class P>
void io_record(IO& io, P& p) {
  io.pod(p.h0);
  io.pod(p.v0);
  io.pod(p.steps);
  io.pod(p.rows);
  io.pod(p.wall_s);
  io.pod(p.ufr);
  io.pod(p.iuf);
  io.pod(p.imom);
  io.pod(p.stress_error);
  io.pod(p.max_stress_error);
  io.pod(p.max_shear_stress);
  io.pod(p.peak_phi_deg);
  io.pod(p.peak_phi_e1);
  io.pod(p.final_e1);
  io.pod(p.final_ev);
  io_measures(io, p.final, 7);
}

// A phase record's values in for_each_record_value's order: their names, and which may be
// undefined (NaN by default: a fabric measure without contacts). Made once.
struct RecordSlots {
  std::vector<std::string> names;
  std::vector<char> may_be_undefined;
};
const RecordSlots& record_slots() {
  static const RecordSlots slots = [] {
    RecordSlots s;
    const PhaseRecord blank;
    for_each_record_value(blank, [&](std::string_view name, const auto& v) {
      s.names.emplace_back(name);
      s.may_be_undefined.push_back(std::isnan(static_cast<double>(v)) ? 1 : 0);
    });
    return s;
  }();
  return slots;
}

// Format 13 on: the records by name (for_each_record_value, run_progress.hpp), the names once and
// then each record's values in their order, as doubles (a count is exact below 2^53). A name this
// build does not know is skipped, and a value the file does not hold keeps its default, so a new
// measure or ledger term needs no new format.
void io_records_by_name(BinaryWriter& w, const std::vector<PhaseRecord>& records) {
  const std::vector<std::string>& names = record_slots().names;
  w.pod(static_cast<std::uint64_t>(names.size()));
  for (const std::string& n : names) w.str(n);
  for (const PhaseRecord& r : records)
    for_each_record_value(r, [&](std::string_view, const auto& v) { w.pod(static_cast<double>(v)); });
}

void io_records_by_name(BinaryReader& in, std::vector<PhaseRecord>& records) {
  std::uint64_t count = 0;
  in.pod(count);
  if (count > 100000) in.damaged("a phase record holds more values than a record can");
  std::vector<std::string> names(count);
  for (std::string& n : names) in.str(n);
  // Where each of this build's values is in the file's list (count: not there), found once.
  std::vector<std::size_t> at;
  for (const std::string& n : record_slots().names)
    at.push_back(static_cast<std::size_t>(std::find(names.begin(), names.end(), n) - names.begin()));
  std::vector<double> values(count);
  for (PhaseRecord& r : records) {
    for (double& v : values) in.pod(v);
    std::size_t k = 0;
    for_each_record_value(r, [&](std::string_view name, auto& v) {
      const std::size_t from = at[k++];
      if (from == count) return;
      const double x = values[from];
      if constexpr (std::is_integral_v<std::remove_reference_t<decltype(v)>>) {
        // A count: whole and within the range of the checks that follow (no cast of NaN or 1e300).
        if (!(std::abs(x) <= 1e15) || x != std::floor(x))
          in.damaged(fmt::format("a phase record's {} is {}, not a count", name, x));
        v = static_cast<long>(x);
      } else {
        v = x;
      }
    });
  }
}

template <class IO, class S>
void io_phase_state(IO& io, S& s) {
  io.pod(s.live);
  for (auto& c : s.controls.component) {
    io.pod(c.kind);
    io.pod(c.value);
  }
  io.pod(s.controls.max_strain_rate);
  io.pod(s.controls.rate_factor);
  io.pod(s.segment_step);
  io.pod(s.segment_strain);
  io.pod(s.row_base_step);
  io.pod(s.row_base_rows);
  io.pod(s.last_row_step);
  io.pod(s.stress_side);
  io.vec(s.controller);
}

void io_run(BinaryWriter& w, const RunProgress& r, std::uint32_t version) {
  if (version < 7) {
    LegacyRun l = to_legacy(r);
    io_legacy_run(w, l, version);
    return;
  }
  w.pod(r.phase);
  w.pod(r.phase_started);
  io_phase_state(w, r.state);
  w.pod(static_cast<std::uint64_t>(r.phases.size()));
  if (version >= 13)
    io_records_by_name(w, r.phases);
  else
    for (const PhaseRecord& p : r.phases) io_record(w, p);
  w.pod(r.wall_s);
  w.pod(r.first_step);
  w.pod(r.prepare_only);
  w.str(r.changes);
  if (version >= 8) {  // the controllers' states at their phases' ends
    w.pod(static_cast<std::uint64_t>(r.controller_end.size()));
    for (const auto& c : r.controller_end) w.vec(c);
  }
  if (version >= 9 && version < 13)  // each phase's energy ledger at its start and last row
    for (const PhaseRecord& p : r.phases) w.pod(p.energy_start), w.pod(p.energy_end);
  if (version >= 10) {  // the digests of the run directory's files
    w.pod(r.case_digest.has_value());
    w.pod(r.case_digest.value_or(0));
    w.pod(static_cast<std::uint64_t>(r.files.size()));
    for (const FileDigest& f : r.files) w.str(f.name), w.pod(f.bytes), w.pod(f.hash);
  }
  if (version >= 12) {  // the builds that ran it
    w.pod(static_cast<std::uint64_t>(r.builds.size()));
    for (const std::string& b : r.builds) w.str(b);
  }
}

void io_run(BinaryReader& in, RunProgress& r, std::uint32_t version) {
  if (version < 7) {
    LegacyRun l;
    io_legacy_run(in, l, version);
    if (l.phase < 0 || l.phase > 2) in.damaged(fmt::format("the run's phase is {}, not 0, 1 or 2", l.phase));
    r = from_legacy(l);
    return;
  }
  in.pod(r.phase);
  in.pod(r.phase_started);
  io_phase_state(in, r.state);
  std::uint64_t n = 0;
  in.pod(n);
  if (n > 1000) in.damaged("more phases than a case can hold");
  r.phases.resize(n);
  if (version >= 13)
    io_records_by_name(in, r.phases);
  else
    for (PhaseRecord& p : r.phases) io_record(in, p);
  in.pod(r.wall_s);
  in.pod(r.first_step);
  in.pod(r.prepare_only);
  in.str(r.changes);
  if (version >= 8) {
    std::uint64_t m = 0;
    in.pod(m);
    if (m > n) in.damaged("more controller states than phases");
    r.controller_end.resize(m);
    for (auto& c : r.controller_end) in.vec(c);
  }
  if (version >= 9 && version < 13)
    for (PhaseRecord& p : r.phases) in.pod(p.energy_start), in.pod(p.energy_end);
  if (version >= 10) {
    bool known = false;
    std::uint64_t digest = 0, files = 0;
    in.pod(known);
    in.pod(digest);
    if (known) r.case_digest = digest;
    in.pod(files);
    if (files > 16) in.damaged("more file digests than a run has files");
    r.files.resize(files);
    for (FileDigest& f : r.files) in.str(f.name), in.pod(f.bytes), in.pod(f.hash);
  }
  if (version >= 12) {
    std::uint64_t builds = 0;
    in.pod(builds);
    if (builds > 100000) in.damaged("more builds than a run can have been resumed by");
    r.builds.resize(builds);
    for (std::string& b : r.builds) in.str(b);
  }
}

// The contact history's layout, by its name (contact/law.hpp) from format 6 on; the formats
// before hold Hertz-Mindlin's tangential force.
void io_history_layout(BinaryWriter& w, const PairHistory& h, std::uint32_t version) {
  if (version >= 6) w.str(std::string(h.layout->name));
}
void io_history_layout(BinaryReader& r, PairHistory& h, std::uint32_t version) {
  if (version < 6) {
    h.layout = &HertzMindlin::history;
    return;
  }
  std::string name;
  r.str(name);
  h.layout = name.empty() ? &no_history : find_history_layout(name);
  if (!h.layout)
    r.refuse(fmt::format("holds the contact history \"{}\", which no contact law of this qsdem declares", name));
}

// `version`: the format being read (the writer always writes checkpoint_format_version).
template <class IO, class S>
void io_state(IO& io, S& st, std::uint32_t version = checkpoint_format_version) {
  io_particles(io, st.particles, version);
  io.pod(st.cell.h);
  io.pod(st.cell.L);
  io.vec(st.pairs.i);
  io.vec(st.pairs.j);
  io.vec(st.pairs.image);
  io_history_layout(io, st.pairs.history, version);
  for_each_pair_field(
      [&](const HistoryLayout& layout, PairField field, auto& values) {
        if (field.saved_since != 0 && version >= field.saved_since)
          io.pair_values(values, static_cast<std::size_t>(layout.width));
      },
      st.pairs);
  io.vec(st.neighbor.s_at_build);
  if (version >= 2) {
    io.vec(st.neighbor.surface_path);
    io.pod(st.neighbor.strain_path);
  }
  if (version >= 3) io.pod(st.neighbor.fluctuation_path);
  io.pod(st.neighbor.h_at_build);
  io.pod(st.neighbor.skin);
  io.pod(st.neighbor.max_bound_radius);
  io.pod(st.neighbor.builds);
  io.pod(st.neighbor.distance_checks);
  io.pod(st.neighbor.valid);
  io.pod(st.servo_integral);
  io.pod(st.step);
  io.pod(st.time);
  io.pod(st.stress);
  io.pod(st.affine_stiffness);
  io.pod(st.shear_stiffness);
  io.pod(st.stress_volume);
  io.pod(st.stress_h);
  io.pod(st.timers.seconds);
  if (version >= 9) io.pod(st.energy);
}

// What the state and the run of a checkpoint must be for a run to step them: every count and index
// in range, the arrays of one length, every number finite. A valid checksum proves only that the
// bytes are those written; a faulty build or an edit can still break these, and the neighbour list,
// the force stage or the phase loop would then read out of bounds or compute NaN. The case is not
// known here (check_checkpoint_case checks what depends on it).
class ContentCheck {
 public:
  ContentCheck(const BinaryReader& r) : r_(r) {}
  template <class... A>
  void require(bool ok, fmt::format_string<A...> what, A&&... args) const {
    if (!ok) r_.damaged(fmt::format(what, std::forward<A>(args)...));
  }
  static bool finite(double x) { return std::isfinite(x); }
  template <class Scalar, int R, int C>
  static bool finite(const Eigen::Matrix<Scalar, R, C>& m) {
    return m.allFinite();
  }
  static bool finite(const Quat& q) { return q.coeffs().allFinite(); }
  // Each of `v` finite, else names the first that is not.
  template <class T>
  void all_finite(const T& v, const char* what) const {
    for (std::size_t k = 0; k < v.size(); ++k) require(finite(v[k]), "{} {} is not finite (NaN or infinity)", what, k);
  }
  // A cell matrix: finite with a positive determinant (a volume).
  void cell_matrix(const Mat3& h, const char* what) const {
    require(h.allFinite() && h.determinant() > 0, "{} is not finite with a positive determinant", what);
  }
  void count(long n, const char* what) const {
    require(n >= 0 && n <= max_count, "{} is {}, not from 0 to {}", what, n, max_count);
  }
  // No run takes 10^15 steps (30 years at 10^6 steps per second): larger counts are damage, and
  // products of them with a phase's settings must not overflow.
  static constexpr long max_count = 1'000'000'000'000'000;

 private:
  const BinaryReader& r_;
};

void check_particles(const ContentCheck& c, const Particles& p, std::uint32_t version) {
  const std::size_t n = p.size();
  c.require(n >= 1 && n < std::numeric_limits<std::uint32_t>::max(), "it holds {} particles", n);
  for_each_field(p, [&](const auto& array, ParticleField field) {
    if (field.saved_since != 0 && version >= field.saved_since)
      c.require(array.size() == n, "the particles' {} has {} entries for {} particles", field.name, array.size(), n);
  });
  std::vector<bool> seen(n, false);
  for (std::size_t i = 0; i < n; ++i) {
    c.require(p.id[i] < n && !seen[p.id[i]], "particle {} has id {}: the ids are not 0 to {}, each once", i, p.id[i],
              n - 1);
    seen[p.id[i]] = true;
    const Vec3& a = p.semi_axes[i];
    c.require(p.shape[i] == ShapeKind::sphere || p.shape[i] == ShapeKind::ellipsoid, "particle {} has no shape ({})",
              i, static_cast<int>(p.shape[i]));
    // The bounds of the packing reader (packing-format.md): from 1 nm to 1 km, a >= b >= c.
    c.require(a.allFinite() && a.minCoeff() >= 1e-9 && a.maxCoeff() <= 1e3 && a.x() >= a.y() && a.y() >= a.z(),
              "particle {} has semi-axes ({}, {}, {}) m, not ordered a >= b >= c from 1 nm to 1 km", i, a.x(), a.y(),
              a.z());
    c.require(p.shape[i] == ShapeKind::ellipsoid || a.x() == a.z(), "sphere {} has unequal semi-axes", i);
    c.require(p.bound_radius[i] == a.x(), "particle {} has a bounding radius {} m, not its largest semi-axis {} m", i,
              p.bound_radius[i], a.x());
    const double r = std::cbrt(a.x() * a.y() * a.z());
    c.require(std::abs(p.equiv_radius[i] - r) <= 1e-12 * r, "particle {} has an equal-volume radius {} m, not {} m", i,
              p.equiv_radius[i], r);
    c.require(std::isfinite(p.mass[i]) && p.mass[i] > 0 && p.inertia[i].allFinite() && p.inertia[i].minCoeff() > 0,
              "particle {} has a mass or moment of inertia that is not finite and > 0", i);
    c.require(version < 11 || (std::isfinite(p.inertia_scale[i]) && p.inertia_scale[i] >= 1),
              "particle {} has an inertia scale that is not finite and >= 1", i);
    c.require(std::isfinite(p.damping_translation[i]) && p.damping_translation[i] >= 0,
              "particle {} has a damping factor that is not finite and >= 0", i);
    // Unwrapped fractional centres (SPEC 3): within a million cell lengths, so that wrapping keeps
    // the digits and the integer shifts of the neighbour search do not overflow.
    c.require(p.s[i].allFinite() && p.s[i].cwiseAbs().maxCoeff() <= 1e6,
              "particle {} has its centre not finite or more than 10^6 cell lengths from the cell", i);
    c.require(p.q[i].coeffs().allFinite() && std::abs(p.q[i].norm() - 1) <= 1e-6,
              "particle {} has an orientation that is not a unit quaternion", i);
  }
  c.all_finite(p.v, "the velocity of particle");
  c.all_finite(p.angmom, "the angular momentum of particle");
  c.all_finite(p.omega, "the angular velocity of particle");
  c.all_finite(p.force, "the force on particle");
  c.all_finite(p.torque, "the torque on particle");
}

void check_pairs(const ContentCheck& c, const PairList& q, const Particles& p, std::uint32_t version) {
  const std::size_t np = q.size(), n = p.size();
  c.require(q.j.size() == np && q.image.size() == np, "the pair list's keys have {}, {} and {} entries", np,
            q.j.size(), q.image.size());
  c.require(np < std::numeric_limits<std::uint32_t>::max(), "it holds {} pairs", np);
  for (std::size_t k = 0; k < np; ++k) {
    const std::uint32_t i = q.i[k], j = q.j[k];
    c.require(i < j && j < n, "pair {} joins particles {} and {}: the ends must be i < j < {} (the particles)", k, i,
              j, n);
    // A listed pair is closer than its bounding spheres plus the skin, under half the cell
    // (SPEC 3): its fractional branch is well within a cell length.
    const Vec3 f = p.s[j] - p.s[i] + q.image[k].cast<double>();
    c.require(f.cwiseAbs().maxCoeff() <= 1, "pair {} ({}, {}) has the image ({}, {}, {}): its ends are {} cell lengths "
              "apart", k, i, j, q.image[k].x(), q.image[k].y(), q.image[k].z(), f.cwiseAbs().maxCoeff());
    if (k > 0) {
      const auto key = [&](std::size_t m) {
        return std::tie(q.i[m], q.j[m], q.image[m].x(), q.image[m].y(), q.image[m].z());
      };
      c.require(key(k - 1) < key(k), "pair {} is not after pair {} in the order of the keys (i, j, image)", k, k - 1);
    }
  }
  const auto sized = [&](const std::vector<double>& v, std::size_t width, const char* what) {
    c.require(v.size() == width * np, "the pairs' {} has {} values for {} pairs of {}", what, v.size(), np, width);
    c.all_finite(v, what);
  };
  sized(q.history.values, static_cast<std::size_t>(q.history.layout->width), "contact history");
  sized(q.pw_lambda, 1, "Perram-Wertheim warm start");
  if (version >= 2) sized(q.apart_until, 1, "proven gap");
  if (version >= 9) {
    sized(q.overlap, 1, "overlap");
    for (std::size_t k = 0; k < np; ++k) c.require(q.overlap[k] >= 0, "pair {} has a negative overlap", k);
  }
}

void check_neighbor(const ContentCheck& c, const NeighborState& ns, const Particles& p) {
  const std::size_t n = p.size();
  c.require(ns.s_at_build.size() == n || (!ns.valid && ns.s_at_build.empty()),
            "the neighbour list's reference holds {} positions for {} particles", ns.s_at_build.size(), n);
  c.all_finite(ns.s_at_build, "the neighbour list's reference position");
  c.require(ns.surface_path.empty() || ns.surface_path.size() == n, "the surface paths hold {} values for {} particles",
            ns.surface_path.size(), n);
  c.all_finite(ns.surface_path, "the surface path of particle");
  for (const double x : ns.surface_path) c.require(x >= 0, "a surface path is negative");
  c.cell_matrix(ns.h_at_build, "the cell matrix of the neighbour list's build");
  // fluctuation_path may be infinite: unknown (a checkpoint of format 2 or older, until the next build).
  c.require(!std::isnan(ns.fluctuation_path) && ns.fluctuation_path >= 0 && std::isfinite(ns.strain_path) &&
                ns.strain_path >= 0,
            "the neighbour list's motion bounds are negative or NaN");
  c.require(std::isfinite(ns.skin) && ns.skin >= 0 && (!ns.valid || ns.skin > 0), "the Verlet skin {} m is not > 0",
            ns.skin);
  const double rmax = *std::max_element(p.bound_radius.begin(), p.bound_radius.end());
  c.require(!ns.valid || ns.max_bound_radius == rmax,
            "the neighbour list was built for a largest bounding radius {} m; the particles' is {} m",
            ns.max_bound_radius, rmax);
  c.count(ns.builds, "the number of list builds");
  c.count(ns.distance_checks, "the number of distance checks");
}

void check_record(const ContentCheck& c, const PhaseRecord& r, std::size_t p, bool started, std::uint32_t version) {
  c.count(r.steps, "a phase's step count");
  c.count(r.rows, "a phase's row count");
  c.require(version < 7 || r.rows <= r.steps, "phase {} has {} rows in {} steps (at most a row a step)", p, r.rows,
            r.steps);
  if (started) {
    c.cell_matrix(r.h0, "the cell matrix at the start of a phase");
    // 0: not recorded (a prepared sample of an older format, saved again)
    c.require(std::isfinite(r.v0) && r.v0 >= 0, "phase {} started at a volume {} m^3", p, r.v0);
  }
  // Every number finite; one whose default is undefined (NaN: a fabric measure without contacts)
  // may be undefined.
  const std::vector<char>& may_be_undefined = record_slots().may_be_undefined;
  std::size_t k = 0;
  for_each_record_value(r, [&](std::string_view name, const auto& v) {
    const double x = static_cast<double>(v);
    c.require(std::isfinite(x) || (may_be_undefined[k] && std::isnan(x)), "phase {}'s record holds {} = {}, not a finite number",
              p, name, x);
    ++k;
  });
  c.require(r.wall_s >= 0 && r.final.contacts >= 0, "phase {}'s record holds a negative count or time", p);
}

void check_run(const ContentCheck& c, const RunProgress& r, const State& st, std::uint32_t version) {
  const std::size_t phases = r.phases.size();
  c.require(phases >= 1, "it holds no phase");
  c.require(r.phase >= 0 && static_cast<std::size_t>(r.phase) <= phases && !(r.phase_started && r.phase == static_cast<std::int32_t>(phases)),
            "it stands at phase {} (started: {}) of {}", r.phase, r.phase_started, phases);
  for (std::size_t p = 0; p < phases; ++p) {
    const bool now = static_cast<std::int32_t>(p) == r.phase;
    // Formats 1 to 6 kept the start of the current phase only.
    const bool started = (static_cast<std::int32_t>(p) < r.phase && version >= 7) || (now && r.phase_started);
    check_record(c, r.phases[p], p, started, version);
  }
  c.require(std::isfinite(r.wall_s) && r.wall_s >= 0, "its wall time {} s is not finite and >= 0", r.wall_s);
  c.require(r.first_step >= 0 && r.first_step <= st.step, "its first step {} is not from 0 to the state's step {}",
            r.first_step, st.step);
  for (const auto& saved : r.controller_end) c.all_finite(saved, "a controller's saved value");
  if (!r.phase_started || !r.state.live) return;  // a phase begins with its own controls (run_phase)
  const PhaseState& s = r.state;
  const PhaseRecord& now = r.phases[static_cast<std::size_t>(r.phase)];
  for (const ComponentControl& k : s.controls.component)
    c.require(k.kind >= ControlKind::fixed && k.kind <= ControlKind::constant_volume &&
                  std::isfinite(k.value),
              "the current phase's controls hold an unknown kind or a value that is not finite");
  c.require(std::isfinite(s.controls.max_strain_rate) && s.controls.max_strain_rate >= 0 &&
                std::isfinite(s.controls.rate_factor) && s.controls.rate_factor >= 0,
            "the current phase's cap of the servo's rate is not finite and >= 0");
  for (std::size_t k = 0; k < 3; ++k) {
    c.require(s.segment_step[k] >= 0 && s.segment_step[k] <= now.steps && std::isfinite(s.segment_strain[k]),
              "the current phase's strain segment {} starts at step {} of {}", k, s.segment_step[k], now.steps);
  }
  c.require(s.row_base_step >= 0 && s.row_base_step <= now.steps && s.row_base_rows >= 0 && s.row_base_rows <= now.rows &&
                s.last_row_step >= -1 && s.last_row_step < now.steps,
            "the current phase's rows are counted from step {}, row {}, last at step {}, of {} steps and {} rows",
            s.row_base_step, s.row_base_rows, s.last_row_step, now.steps, now.rows);
  for (const std::int8_t side : s.stress_side)
    c.require(side >= -1 && side <= 1, "the current phase's stress stop has the side {}", side);
  c.all_finite(s.controller, "the current phase's controller's saved value");
}

void check_contents(const Checkpoint& ck, std::uint32_t version, const BinaryReader& r) {
  const ContentCheck c(r);
  const State& st = ck.state;
  check_particles(c, st.particles, version);
  c.cell_matrix(st.cell.h, "the cell matrix");
  c.require(st.cell.L.allFinite(), "the cell's velocity gradient is not finite");
  check_pairs(c, st.pairs, st.particles, version);
  check_neighbor(c, st.neighbor, st.particles);
  c.count(st.step, "the step count");
  c.require(std::isfinite(st.time) && st.time >= 0, "the time {} s is not finite and >= 0", st.time);
  c.require(st.servo_integral.allFinite() && st.stress.allFinite() && st.affine_stiffness.allFinite() &&
                st.shear_stiffness.allFinite(),
            "the stress or the servo's state is not finite");
  c.require(std::isfinite(st.stress_volume) && st.stress_volume > 0, "the stress was evaluated at a volume of {} m^3",
            st.stress_volume);
  c.cell_matrix(st.stress_h, "the cell matrix of the last force evaluation");
  for (const double t : st.timers.seconds) c.require(std::isfinite(t) && t >= 0, "a stage's time is not finite and >= 0");
  for (const EnergyTerm& term : energy_ledger_terms) c.require(std::isfinite(st.energy.*term.field), "the energy ledger is not finite");
  check_run(c, ck.run, st, version);
}

struct Header {
  std::uint32_t version = 0;
  std::uint64_t size = 0, sum = 0;  // of the payload
};

Header parse_header(std::string_view bytes, const std::string& name) {
  if (bytes.size() < header_size || std::memcmp(bytes.data(), magic, 8) != 0)
    throw InputError(fmt::format("'{}' is not a qsdem checkpoint (or is truncated before its header)", name));
  Header h;
  std::memcpy(&h.version, bytes.data() + 8, 4);
  std::memcpy(&h.size, bytes.data() + 16, 8);
  std::memcpy(&h.sum, bytes.data() + 24, 8);
  if (h.version < 1 || h.version > checkpoint_format_version)
    throw InputError(fmt::format("checkpoint '{}' has format version {}; this qsdem reads versions 1 to {}", name,
                                 h.version, checkpoint_format_version));
  return h;
}

// `have` bytes after the header, where it says `size`.
void check_length(std::uint64_t have, std::uint64_t size, const std::string& name) {
  if (have < size)
    throw InputError(fmt::format("checkpoint '{}' is damaged: truncated ({} of {} bytes)", name, have, size));
  if (have > size)
    throw InputError(fmt::format("checkpoint '{}' is damaged: {} bytes after its header, which says {}", name, have,
                                 size));
}

void fsync_dir(const std::filesystem::path& dir) {
  const int fd = ::open(dir.empty() ? "." : dir.c_str(), O_RDONLY | O_DIRECTORY);
  if (fd >= 0) {
    ::fsync(fd);
    ::close(fd);
  }
}

}  // namespace

void save_checkpoint(const std::filesystem::path& path, const std::string& case_text, const std::string& case_source,
                     const State& state, const RunProgress& run, std::uint32_t format) {
  BinaryWriter w;
  w.str(case_text);
  w.str(case_source);
  io_run(w, run, format);
  io_state(w, state, format);
  const std::uint64_t size = w.out.size();
  const std::uint64_t sum = fnv1a64(w.out.data(), w.out.size());

  std::filesystem::path tmp = path;
  tmp += ".tmp";
  const int fd = create_file(tmp);  // a new file, never one reached through a link planted under the name
  const bool has_previous = std::filesystem::exists(path);
  const char* kept = has_previous ? "the previous checkpoint is kept" : "there is no earlier checkpoint";
  if (fd < 0)
    throw RunError(fmt::format("cannot write checkpoint '{}': {}; {}", tmp.string(), std::strerror(errno), kept));
  std::vector<char> head(header_size);
  const std::uint32_t version = format, reserved = 0;
  std::memcpy(head.data(), magic, 8);
  std::memcpy(head.data() + 8, &version, 4);
  std::memcpy(head.data() + 12, &reserved, 4);
  std::memcpy(head.data() + 16, &size, 8);
  std::memcpy(head.data() + 24, &sum, 8);
  auto write_all = [&](const char* p, std::size_t n) {
    while (n > 0) {
      const ssize_t k = ::write(fd, p, n);
      if (k <= 0) return false;
      p += k;
      n -= static_cast<std::size_t>(k);
    }
    return true;
  };
  const bool ok = write_all(head.data(), head.size()) && write_all(w.out.data(), w.out.size()) && ::fsync(fd) == 0;
  const int saved_errno = errno;
  ::close(fd);
  if (!ok) {
    std::filesystem::remove(tmp);
    throw RunError(fmt::format("writing checkpoint '{}' failed: {}; {}", tmp.string(), std::strerror(saved_errno), kept));
  }
  std::filesystem::path prev = path;
  prev += ".prev";
  // The current checkpoint gets a second name, .prev, then the new one replaces it atomically: at
  // every instant `path` names a whole checkpoint (renaming path to .prev first left a window in
  // which a SIGKILL found none). Without hard links (some file systems), rename as before.
  std::error_code ec;
  if (has_previous) {
    std::filesystem::remove(prev, ec);
    std::filesystem::create_hard_link(path, prev, ec);
    if (ec) std::filesystem::rename(path, prev, ec);
  }
  std::filesystem::rename(tmp, path, ec);
  if (ec) throw RunError(fmt::format("renaming '{}' to '{}' failed: {}; {}", tmp.string(), path.string(), ec.message(), kept));
  fsync_dir(path.parent_path());
}

Checkpoint parse_checkpoint(std::string_view bytes, const std::string& name, Seal seal) {
  const Header h = parse_header(bytes, name);
  const std::uint64_t size = seal == Seal::ignore ? bytes.size() - header_size : h.size;
  check_length(bytes.size() - header_size, size, name);
  const char* payload = bytes.data() + header_size;
  if (seal == Seal::verify && fnv1a64(payload, size) != h.sum)
    throw InputError(fmt::format("checkpoint '{}' is damaged: checksum mismatch", name));
  BinaryReader r(payload, size, name);
  Checkpoint c;
  r.str(c.case_text);
  r.str(c.case_source);
  const std::uint32_t version = h.version;
  io_run(r, c.run, version);
  io_state(r, c.state, version);
  if (!r.at_end()) r.damaged("unexpected bytes after the state");
  check_contents(c, version, r);
  // Before format 11 no phase scaled the particles' inertia (SPEC 5.6).
  if (version < 11) c.state.particles.inertia_scale.assign(c.state.particles.size(), 1.0);
  c.state.particles.derive_inverses();
  // The rotation's damping factors are not kept: a phase sets both when it starts (damping/stage.hpp).
  c.state.particles.damping_rotation = c.state.particles.damping_translation;
  set_matrix(c.state.cell, c.state.cell.h);
  const std::size_t np = c.state.pairs.size();
  // Before format 9 the overlaps were not kept (the energy ledger's stiffness work reads them).
  if (version < 9) c.state.pairs.overlap.assign(np, 0.0);
  build_incidence(c.state.pairs, c.state.particles.size());
  if (version < 2) {
    // Format 1 (before apart pairs were skipped): no skip state, so every pair is tested at the
    // first step and the motion bounds start from zero (as after a list build).
    c.state.pairs.apart_until.assign(np, -1.0);
    c.state.neighbor.restart_motion(c.state.particles);
  }
  // Before format 3 a run of spheres did not keep its motion since the list build: unknown, so no
  // apart sphere pair is skipped and the skin test runs in full until the next build.
  if (version < 3) c.state.neighbor.fluctuation_path = std::numeric_limits<double>::infinity();
  // Before format 4 a run with ellipsoids did not sum it (it was kept for spheres only).
  c.state.neighbor.ellipsoids = c.state.particles.has_ellipsoids();  // not stored: the particles tell
  if (version < 4 && c.state.neighbor.ellipsoids)
    c.state.neighbor.fluctuation_path = std::numeric_limits<double>::infinity();
  return c;
}

Checkpoint load_checkpoint(const std::filesystem::path& path) {
  const std::string name = path.string();
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) throw InputError(fmt::format("no checkpoint '{}'", name));
  // Regular files only, read no further than the header's length: a FIFO or a device (/dev/zero)
  // is refused at once.
  std::uint64_t file_size = 0;
  const Header h = parse_header(read_regular_file(path, header_size, &file_size), name);
  check_length(file_size - header_size, h.size, name);
  const std::string bytes = read_regular_file(path, header_size + h.size);
  return parse_checkpoint(bytes, name);
}

void check_checkpoint_case(const Checkpoint& c, const Params& params, const std::string& name) {
  const auto refuse = [&](const std::string& why) {
    throw InputError(fmt::format("checkpoint '{}' does not fit the case it holds ({}): {}", name, c.case_source, why));
  };
  const RunProgress& run = c.run;
  const Protocol& protocol = params.protocol;
  if (run.phases.size() != protocol.size())
    refuse(fmt::format("it holds {} phases, the case has {}", run.phases.size(), protocol.size()));
  // A controller's saved state, restored as the phase loop and the summary restore it.
  const auto restorable = [&](std::size_t p, const std::vector<double>& saved) {
    if (!protocol[p].make_controller || saved.empty()) return;
    try {
      protocol[p].make_controller()->restore(saved);
    } catch (const InputError& e) {
      refuse(fmt::format("the saved state of the controller of phase {}: {}", protocol[p].name, e.what()));
    }
  };
  for (std::size_t p = 0; p < run.controller_end.size(); ++p) restorable(p, run.controller_end[p]);
  if (!run.phase_started || !run.state.live) return;
  const std::size_t p = static_cast<std::size_t>(run.phase);
  const Phase& phase = protocol[p];
  const PhaseControls& now = run.state.controls;
  // A controller changes the control values, never their kinds; without one they are the case's.
  for (std::size_t k = 0; k < now.component.size(); ++k) {
    const ComponentControl &a = now.component[k], &b = phase.controls.component[k];
    if (a.kind != b.kind || (!phase.make_controller && a.value != b.value))
      refuse(fmt::format("phase {} is controlled by other values than its case's ({} of component {})", phase.name,
                         a.kind != b.kind ? "the kind" : "the value", component_names[k]));
  }
  if (!phase.make_controller &&
      (now.max_strain_rate != phase.controls.max_strain_rate || now.rate_factor != phase.controls.rate_factor))
    refuse(fmt::format("phase {} caps the servo's rate otherwise than its case", phase.name));
  restorable(p, run.state.controller);
  // No more rows than the phase's sample points give in its steps (the last step is one too).
  const PhaseRecord& rec = run.phases[p];
  const Cadence& cadence = phase.output.cadence;
  const long most = cadence.kind == Cadence::Kind::points        ? cadence.points
                    : cadence.kind == Cadence::Kind::every_steps ? rec.steps / cadence.every_steps + 1
                                                                 : rec.steps;
  if (rec.rows > most)
    refuse(fmt::format("phase {} has {} rows after {} steps, more than its sample points give ({})", phase.name,
                       rec.rows, rec.steps, most));
}

State prepared_sample(Checkpoint c, const Params& params, const std::string& from, RunProgress& run) {
  const Params prepared = parse_case(c.case_text, c.case_source);
  const auto& a = prepared.material;
  const auto& b = params.material;
  if (a.density != b.density || a.young_modulus != b.young_modulus || a.poisson_ratio != b.poisson_ratio ||
      prepared.step_ratio != params.step_ratio)
    throw InputError(fmt::format(
        "sample.from = '{}': that sample was prepared with density {} kg/m^3, E {} Pa, nu {}, time.step_ratio {}; "
        "this case has {}, {}, {}, {}: they must be equal",
        from, a.density, a.young_modulus, a.poisson_ratio, prepared.step_ratio, b.density, b.young_modulus,
        b.poisson_ratio, params.step_ratio));
  if (c.run.phase != 1 || c.run.phase_started)
    throw InputError(
        fmt::format("sample.from = '{}': {} is not a sample at the end of compaction", from, "sample.qsck"));
  check_checkpoint_case(c, prepared, (std::filesystem::path(from) / "sample.qsck").string());
  run = c.run;
  run.phases.resize(params.protocol.size());  // its first phase's record; the others are this run's
  run.wall_s = 0;
  run.first_step = c.state.step;  // its compaction steps and time are the sample's, not this run's
  run.prepare_only = false;
  run.changes.clear();
  run.builds.clear();          // the sample's builds are in its own summary.json
  run.case_digest.reset();     // its directory's files are not this run's
  run.files.clear();
  c.state.timers = {};
  return std::move(c.state);
}

Checkpoint load_latest_checkpoint(const std::filesystem::path& path, std::string* note) {
  try {
    return load_checkpoint(path);
  } catch (const InputError& newest) {
    std::filesystem::path prev = path;
    prev += ".prev";
    if (!std::filesystem::exists(prev)) throw;
    Checkpoint c = load_checkpoint(prev);  // throws if this one is bad too
    if (note) *note = fmt::format("{}; using the previous checkpoint '{}'", newest.what(), prev.string());
    return c;
  }
}

}  // namespace qsdem
