#include "qsdem/checkpoint.hpp"

#include <fcntl.h>
#include <fmt/format.h>
#include <unistd.h>

#include <cstring>
#include <fstream>
#include <iterator>
#include <limits>
#include <type_traits>

#include "qsdem/contact/laws.hpp"
#include "qsdem/files.hpp"

namespace qsdem {
namespace {

constexpr char magic[8] = {'Q', 'S', 'D', 'E', 'M', 'C', 'K', 'P'};
constexpr std::size_t header_size = 8 + 4 + 4 + 8 + 8;

// Appends plain values and arrays of them to a byte buffer.
class Writer {
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

// Reads what Writer wrote; any overrun is a damaged file.
class Reader {
 public:
  Reader(const char* data, std::size_t size, std::string file) : p_(data), end_(data + size), file_(std::move(file)) {}
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
  template <class T>
  void vec(std::vector<T>& v) {
    std::uint64_t n = 0;
    pod(n);
    if (n > static_cast<std::uint64_t>(end_ - p_)) damaged("an array is longer than the file");
    v.resize(n);
    for (T& x : v) pod(x);
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
    if (n > static_cast<std::uint64_t>(end_ - p_)) damaged("an array is longer than the file");
    v.resize(n * w);
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

// Format 7: any protocol. Every field on its own (no struct's raw bytes, so no padding).
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

void io_run(Writer& w, const RunProgress& r, std::uint32_t version) {
  if (version < 7) {
    LegacyRun l = to_legacy(r);
    io_legacy_run(w, l, version);
    return;
  }
  w.pod(r.phase);
  w.pod(r.phase_started);
  io_phase_state(w, r.state);
  w.pod(static_cast<std::uint64_t>(r.phases.size()));
  for (const PhaseRecord& p : r.phases) io_record(w, p);
  w.pod(r.wall_s);
  w.pod(r.first_step);
  w.pod(r.prepare_only);
  w.str(r.changes);
  if (version >= 8) {  // the controllers' states at their phases' ends
    w.pod(static_cast<std::uint64_t>(r.controller_end.size()));
    for (const auto& c : r.controller_end) w.vec(c);
  }
  if (version >= 9)  // each phase's energy ledger at its start and last row
    for (const PhaseRecord& p : r.phases) w.pod(p.energy_start), w.pod(p.energy_end);
}

void io_run(Reader& in, RunProgress& r, std::uint32_t version) {
  if (version < 7) {
    LegacyRun l;
    io_legacy_run(in, l, version);
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
  if (version >= 9)
    for (PhaseRecord& p : r.phases) in.pod(p.energy_start), in.pod(p.energy_end);
}

// The contact history's layout, by its name (contact/law.hpp) from format 6 on; the formats
// before hold Hertz-Mindlin's tangential force.
void io_history_layout(Writer& w, const PairHistory& h, std::uint32_t version) {
  if (version >= 6) w.str(std::string(h.layout->name));
}
void io_history_layout(Reader& r, PairHistory& h, std::uint32_t version) {
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

void fsync_dir(const std::filesystem::path& dir) {
  const int fd = ::open(dir.empty() ? "." : dir.c_str(), O_RDONLY | O_DIRECTORY);
  if (fd >= 0) {
    ::fsync(fd);
    ::close(fd);
  }
}

}  // namespace

std::uint64_t fnv1a64(const void* data, std::size_t size) {
  std::uint64_t h = 14695981039346656037ull;
  const auto* b = static_cast<const unsigned char*>(data);
  for (std::size_t k = 0; k < size; ++k) {
    h ^= b[k];
    h *= 1099511628211ull;
  }
  return h;
}

void save_checkpoint(const std::filesystem::path& path, const std::string& case_text, const std::string& case_source,
                     const State& state, const RunProgress& run, std::uint32_t format) {
  Writer w;
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

Checkpoint load_checkpoint(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw InputError(fmt::format("no checkpoint '{}'", path.string()));
  const std::vector<char> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const std::string name = path.string();
  if (bytes.size() < header_size || std::memcmp(bytes.data(), magic, 8) != 0)
    throw InputError(fmt::format("'{}' is not a qsdem checkpoint (or is truncated before its header)", name));
  std::uint32_t version = 0;
  std::uint64_t size = 0, sum = 0;
  std::memcpy(&version, bytes.data() + 8, 4);
  std::memcpy(&size, bytes.data() + 16, 8);
  std::memcpy(&sum, bytes.data() + 24, 8);
  if (version < 1 || version > checkpoint_format_version)
    throw InputError(fmt::format("checkpoint '{}' has format version {}; this qsdem reads versions 1 to {}", name,
                                 version, checkpoint_format_version));
  if (bytes.size() - header_size != size)
    throw InputError(fmt::format("checkpoint '{}' is damaged: truncated ({} of {} bytes)", name,
                                 bytes.size() - header_size, size));
  const char* payload = bytes.data() + header_size;
  if (fnv1a64(payload, size) != sum)
    throw InputError(fmt::format("checkpoint '{}' is damaged: checksum mismatch", name));
  Reader r(payload, size, name);
  Checkpoint c;
  r.str(c.case_text);
  r.str(c.case_source);
  io_run(r, c.run, version);
  io_state(r, c.state, version);
  c.state.particles.derive_inverses();
  // The rotation's damping factors are not kept: a phase sets both when it starts (damping/stage.hpp).
  c.state.particles.damping_rotation = c.state.particles.damping_translation;
  if (!r.at_end()) r.damaged("unexpected bytes after the state");
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
  if (version < 4 && c.state.particles.has_ellipsoids())
    c.state.neighbor.fluctuation_path = std::numeric_limits<double>::infinity();
  return c;
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
