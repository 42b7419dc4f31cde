#include "qsdem/run/output.hpp"

#include <fcntl.h>
#include <fmt/format.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <iterator>

#include "qsdem/engine/types.hpp"
#include "qsdem/run/files.hpp"

namespace qsdem {

std::vector<std::string> split_fields(const std::string& line) {
  std::vector<std::string> fields;
  for (std::size_t at = 0;;) {
    const std::size_t comma = line.find(',', at);
    fields.push_back(line.substr(at, comma == std::string::npos ? std::string::npos : comma - at));
    if (comma == std::string::npos) return fields;
    at = comma + 1;
  }
}

namespace {

// The columns, in order: SPEC 10's (10.1), then phi_al_deg and tilt_deg (SPEC 7), then the fabric
// (SPEC 7.1): a name, the row's value and its significant digits (10 for the strains and
// stresses, 8 for the rest; 0: an integer). The header and the rows are made from this one list.
struct Column {
  const char* name;
  double (*value)(const SeriesRow& r);
  int digits;
};

constexpr Column base_columns[] = {
    {"step", [](const SeriesRow& r) { return static_cast<double>(r.step); }, 0},
    {"time_s", [](const SeriesRow& r) { return r.time; }, 10},
    {"e1", [](const SeriesRow& r) { return r.e1; }, 10},
    {"ev", [](const SeriesRow& r) { return r.ev; }, 10},
    {"s11_Pa", [](const SeriesRow& r) { return r.m.stress(0, 0); }, 10},
    {"s22_Pa", [](const SeriesRow& r) { return r.m.stress(1, 1); }, 10},
    {"s33_Pa", [](const SeriesRow& r) { return r.m.stress(2, 2); }, 10},
    {"p_Pa", [](const SeriesRow& r) { return r.m.mean_stress; }, 10},
    {"q_Pa", [](const SeriesRow& r) { return r.m.deviator; }, 10},
    {"phi_deg", [](const SeriesRow& r) { return r.m.friction_angle_deg; }, 8},
    {"void_ratio", [](const SeriesRow& r) { return r.m.void_ratio; }, 8},
    {"cn", [](const SeriesRow& r) { return r.m.coordination; }, 8},
    {"ufr", [](const SeriesRow& r) { return r.m.ufr; }, 8},
    {"iuf", [](const SeriesRow& r) { return r.m.iuf; }, 8},
    {"imom", [](const SeriesRow& r) { return r.m.imom; }, 8},
    {"ekin_J", [](const SeriesRow& r) { return r.m.ekin_trans + r.m.ekin_rot; }, 8},
    {"ekin_trans_J", [](const SeriesRow& r) { return r.m.ekin_trans; }, 8},
    {"ekin_rot_J", [](const SeriesRow& r) { return r.m.ekin_rot; }, 8},
    {"phi_al_deg", [](const SeriesRow& r) { return r.m.friction_angle_al_deg; }, 8},
    {"tilt_deg", [](const SeriesRow& r) { return r.m.principal_tilt_deg; }, 8},
    {"fabric_11", [](const SeriesRow& r) { return r.m.fabric(0, 0); }, 8},
    {"fabric_22", [](const SeriesRow& r) { return r.m.fabric(1, 1); }, 8},
    {"fabric_33", [](const SeriesRow& r) { return r.m.fabric(2, 2); }, 8},
    {"fabric_dev", [](const SeriesRow& r) { return r.m.fabric_dev; }, 8},
    {"fabric_1", [](const SeriesRow& r) { return r.m.fabric_major; }, 8},
    {"fabric_tilt_deg", [](const SeriesRow& r) { return r.m.fabric_tilt_deg; }, 8},
    {"fabric_strong_33", [](const SeriesRow& r) { return r.m.fabric_strong_33; }, 8},
    {"fabric_strong_dev", [](const SeriesRow& r) { return r.m.fabric_strong_dev; }, 8},
    {"fabric_weak_33", [](const SeriesRow& r) { return r.m.fabric_weak_33; }, 8},
    {"fabric_weak_dev", [](const SeriesRow& r) { return r.m.fabric_weak_dev; }, 8},
    {"strong_fraction", [](const SeriesRow& r) { return r.m.strong_fraction; }, 8},
    {"fabric_force_33", [](const SeriesRow& r) { return r.m.fabric_force_33; }, 8},
    {"fabric_force_dev", [](const SeriesRow& r) { return r.m.fabric_force_dev; }, 8},
    {"orient_33", [](const SeriesRow& r) { return r.m.orient_33; }, 8},
    {"orient_dev", [](const SeriesRow& r) { return r.m.orient_dev; }, 8},
    {"z_mech", [](const SeriesRow& r) { return r.m.z_mech; }, 8},
};

}  // namespace

std::string series_header(const SeriesColumns& columns) {
  std::string h;
  for (const Column& c : base_columns) {
    if (!h.empty()) h += ',';
    h += c.name;
  }
  if (columns.shear) h += ",s12_Pa,s13_Pa,s23_Pa,g12,g13,g23";
  if (columns.dp) h += ",dp_Pa";
  if (columns.strain_rate) h += ",strain_rate";
  if (columns.relaxation) h += ",iterations,relaxed";
  if (columns.energy) h += ",work_J,friction_J,contact_damping_J,damping_J,stiffness_change_J,elastic_J";
  return columns.phase ? h + ",phase" : h;
}

std::string series_row(const SeriesRow& r, const SeriesColumns& columns) {
  fmt::memory_buffer out;
  for (const Column& c : base_columns) {
    if (out.size() > 0) out.push_back(',');
    if (c.digits == 0)
      fmt::format_to(std::back_inserter(out), "{}", static_cast<long>(c.value(r)));  // exact below 2^53
    else
      fmt::format_to(std::back_inserter(out), "{:.{}g}", c.value(r), c.digits);
  }
  if (columns.shear) {
    const Mat3& s = r.m.stress;
    const auto& g = r.shear_strain;
    fmt::format_to(std::back_inserter(out), ",{:.10g},{:.10g},{:.10g},{:.10g},{:.10g},{:.10g}", s(0, 1), s(0, 2), s(1, 2),
                   g[0], g[1], g[2]);
  }
  if (columns.dp) fmt::format_to(std::back_inserter(out), ",{:.10g}", r.dp);
  if (columns.strain_rate) {
    out.push_back(',');
    if (r.strain_rate) fmt::format_to(std::back_inserter(out), "{:.10g}", *r.strain_rate);
  }
  if (columns.relaxation) {
    out.push_back(',');
    if (r.relaxation) fmt::format_to(std::back_inserter(out), "{},{}", r.relaxation->iterations, r.relaxation->converged ? 1 : 0);
    else out.push_back(',');
  }
  if (columns.energy) {
    const EnergyLedger& e = r.energy;
    fmt::format_to(std::back_inserter(out), ",{:.12g},{:.12g},{:.12g},{:.12g},{:.12g},{:.12g}", e.boundary_work,
                   e.friction, e.contact_damping, e.damping, e.stiffness_change, e.elastic);
  }
  if (columns.phase) fmt::format_to(std::back_inserter(out), ",{}", r.phase ? *r.phase : std::string());
  return fmt::to_string(out);
}

nlohmann::json energy_change(const EnergyLedger& start, const EnergyLedger& end) {
  const double work = end.boundary_work - start.boundary_work, friction = end.friction - start.friction;
  const double contact_damping = end.contact_damping - start.contact_damping, damping = end.damping - start.damping;
  const double stiffness = end.stiffness_change - start.stiffness_change;
  const double elastic = end.elastic - start.elastic, kinetic = end.kinetic - start.kinetic;
  const double balance = work + stiffness - (friction + contact_damping + damping + elastic + kinetic);
  return {{"work_J", work},
          {"friction_J", friction},
          {"contact_damping_J", contact_damping},
          {"damping_J", damping},
          {"stiffness_change_J", stiffness},
          {"elastic_change_J", elastic},
          {"kinetic_change_J", kinetic},
          {"balance_error_J", balance}};
}

std::string classes_header() {
  return "step,time_s,e1,ev,phase,radius_mm,count,contacts_per_particle,in_contact,in_contact_2,p_share,speed_m_s,"
         "spin_1_s";
}

std::string classes_rows(const SeriesRow& r, const std::vector<ClassMeasures>& classes) {
  fmt::memory_buffer out;
  for (const ClassMeasures& c : classes) {
    if (out.size() > 0) out.push_back('\n');
    fmt::format_to(std::back_inserter(out), "{},{:.10g},{:.10g},{:.10g},{},{:.8g},{},{:.8g},{:.8g},{:.8g},{:.8g},{:.8g},{:.8g}",
                   r.step, r.time, r.e1, r.ev, r.phase ? *r.phase : std::string(), 1e3 * c.radius, c.count,
                   c.contacts, c.in_contact, c.in_contact_2, c.stress_share, c.speed, c.spin);
  }
  return fmt::to_string(out);
}

std::uint64_t fnv1a64(const void* data, std::size_t size, std::uint64_t h) {
  const auto* b = static_cast<const unsigned char*>(data);
  for (std::size_t k = 0; k < size; ++k) {
    h ^= b[k];
    h *= 1099511628211ull;
  }
  return h;
}

std::string read_regular_file(const std::filesystem::path& path, std::uint64_t max_bytes, std::uint64_t* size) {
  // O_NONBLOCK: opening a FIFO does not wait for a writer (it is then refused as not a regular file).
  const int fd = ::open(path.c_str(), O_RDONLY | O_NONBLOCK | O_CLOEXEC);
  if (fd < 0) throw InputError(fmt::format("cannot read '{}': {}", path.string(), std::strerror(errno)));
  struct stat st {};
  if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
    ::close(fd);
    throw InputError(fmt::format("'{}' is not a regular file (a FIFO, a device or a directory): it cannot be read "
                                 "as one",
                                 path.string()));
  }
  const std::uint64_t file_size = static_cast<std::uint64_t>(st.st_size);
  if (size) *size = file_size;
  std::string bytes(static_cast<std::size_t>(std::min(max_bytes, file_size)), '\0');
  std::size_t got = 0;
  while (got < bytes.size()) {
    const ssize_t n = ::read(fd, bytes.data() + got, bytes.size() - got);
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) {
      const int err = errno;
      ::close(fd);
      throw InputError(fmt::format("cannot read '{}': {}", path.string(), std::strerror(err)));
    }
    if (n == 0) break;  // shorter than it was
    got += static_cast<std::size_t>(n);
  }
  ::close(fd);
  bytes.resize(got);
  return bytes;
}

SeriesWriter::SeriesWriter(std::filesystem::path path, long keep_rows, const SeriesColumns& columns)
    : SeriesWriter(std::move(path), keep_rows, CsvHeader{series_header(columns)}) {}

SeriesWriter::SeriesWriter(std::filesystem::path path, long keep_rows, const CsvHeader& header)
    : path_(std::move(path)) {
  partial_ = path_;
  partial_ += ".partial";
  digest_.name = path_.filename().string();
  if (keep_rows < 0) {
    const int fd = create_file(partial_);
    if (fd >= 0) file_ = ::fdopen(fd, "w");
    if (!file_) {
      const int err = errno;
      if (fd >= 0) ::close(fd);
      throw RunError(fmt::format("cannot write '{}': {}", partial_.string(), file_error(err)));
    }
    write(header.text);
    return;
  }
  // The rows a resumed run keeps: the file is cut after them in place (never rewritten through a
  // link planted under its name, which is refused).
  const int fd = open_regular_file(partial_, O_RDWR);
  if (fd < 0 && errno != ENOENT)
    throw InputError(fmt::format("cannot resume: '{}': {}", partial_.string(), file_error(errno)));
  long lines = 0;
  off_t kept = 0, size = 0;
  bool ends_in_newline = true;
  std::string text;  // the bytes read, of which the first `kept` stay
  if (fd >= 0) {
    char buf[1 << 16];
    for (ssize_t n; lines < keep_rows + 1 && (n = ::read(fd, buf, sizeof buf)) > 0;) {
      for (ssize_t k = 0; k < n && lines < keep_rows + 1; ++k)
        if (buf[k] == '\n') ++lines, kept = size + k + 1;
      text.append(buf, static_cast<std::size_t>(n));
      size += n;
      ends_in_newline = buf[n - 1] == '\n';
    }
    // A last kept line without its newline (the end of the file) is kept whole.
    if (lines == keep_rows && !ends_in_newline && kept < size) ++lines, kept = size;
  }
  if (lines < keep_rows + 1) {
    if (fd >= 0) ::close(fd);
    throw InputError(fmt::format("cannot resume: '{}' holds {} rows, the checkpoint expects {}", partial_.string(),
                                 std::max(0L, lines - 1), keep_rows));
  }
  const bool add_newline = kept == size && !ends_in_newline;
  text.resize(static_cast<std::size_t>(kept));
  if (add_newline) text += '\n';
  try {
    keep_columns(text.substr(0, text.find('\n')), header.text);
  } catch (...) {
    ::close(fd);
    throw;
  }
  if (::ftruncate(fd, kept) != 0 || ::lseek(fd, 0, SEEK_END) < 0 || !(file_ = ::fdopen(fd, "w")) ||
      (add_newline && std::fputc('\n', file_) == EOF) || std::fflush(file_) != 0) {
    const int err = errno;
    if (file_) std::fclose(file_), file_ = nullptr;
    else ::close(fd);
    throw RunError(fmt::format("cannot rewrite '{}': {}", partial_.string(), std::strerror(err)));
  }
  digest_.bytes = text.size();
  digest_.hash = fnv1a64(text.data(), text.size());
}

void SeriesWriter::keep_columns(const std::string& file_header, const std::string& header) {
  if (file_header == header) return;
  const std::vector<std::string> have = split_fields(file_header), names = split_fields(header);
  for (const std::string& name : have) {
    const auto at = std::find(names.begin(), names.end(), name);
    if (at == names.end())
      throw InputError(fmt::format("cannot resume: '{}' has the column '{}', which this qsdem does not write (it "
                                   "was begun by another version): finish the run with the qsdem that began it",
                                   partial_.string(), name));
    projection_.push_back(static_cast<std::size_t>(at - names.begin()));
  }
  for (const std::string& name : names)
    if (std::find(have.begin(), have.end(), name) == have.end()) omitted_ += (omitted_.empty() ? "" : ",") + name;
}

SeriesWriter::~SeriesWriter() {
  if (file_) std::fclose(file_);
}

void SeriesWriter::write(const std::string& row) {
  if (projection_.empty()) return put(row + '\n');
  std::string out;  // each line of the row with the file's columns only
  for (std::size_t at = 0; at <= row.size();) {
    const std::size_t end = std::min(row.find('\n', at), row.size());
    const std::vector<std::string> fields = split_fields(row.substr(at, end - at));
    for (std::size_t k = 0; k < projection_.size(); ++k) (out += k > 0 ? "," : "") += fields.at(projection_[k]);
    out += '\n';
    at = end + 1;
  }
  put(out);
}

void SeriesWriter::put(const std::string& text) {
  if (std::fputs(text.c_str(), file_) < 0 || std::fflush(file_) != 0)
    throw RunError(fmt::format("write to '{}' failed: {}", partial_.string(), std::strerror(errno)));
  digest_.bytes += text.size();
  digest_.hash = fnv1a64(text.data(), text.size(), digest_.hash);
}

void SeriesWriter::sync() {
  if (std::fflush(file_) != 0 || ::fsync(fileno(file_)) != 0)
    throw RunError(fmt::format("writing '{}' to disk failed: {}", partial_.string(), std::strerror(errno)));
}

void SeriesWriter::commit() {
  sync();
  const int closed = std::fclose(file_);
  file_ = nullptr;
  if (closed != 0) throw RunError(fmt::format("closing '{}' failed: {}", partial_.string(), std::strerror(errno)));
  commit_partial(path_);
}

void commit_partial(const std::filesystem::path& path) {
  std::filesystem::path partial = path;
  partial += ".partial";
  std::error_code ec;
  // What is renamed into a result is a file of the run's, never a link planted under its name.
  if (!std::filesystem::is_regular_file(std::filesystem::symlink_status(partial, ec)))
    throw InputError(fmt::format("cannot rename '{}' to '{}': {}", partial.string(), path.string(),
                                 file_error(std::filesystem::is_symlink(std::filesystem::symlink_status(partial, ec))
                                                ? ELOOP
                                                : EINVAL)));
  std::filesystem::rename(partial, path, ec);
  if (ec) throw RunError(fmt::format("renaming '{}' to '{}' failed: {}", partial.string(), path.string(), ec.message()));
}

void write_file_atomic(const std::filesystem::path& path, const std::string& text) {
  std::filesystem::path tmp = path;
  tmp += ".tmp";
  const int fd = create_file(tmp);
  if (fd < 0) throw RunError(fmt::format("cannot write '{}': {}", tmp.string(), file_error(errno)));
  bool ok = true;
  for (std::size_t done = 0; ok && done < text.size();) {
    const ssize_t n = ::write(fd, text.data() + done, text.size() - done);
    if (n < 0 && errno == EINTR) continue;
    ok = n > 0;
    if (ok) done += static_cast<std::size_t>(n);
  }
  ok = ok && ::fsync(fd) == 0;
  int err = errno;
  if (::close(fd) != 0 && ok) ok = false, err = errno;
  if (!ok) {
    std::filesystem::remove(tmp);
    throw RunError(fmt::format("write to '{}' failed: {}", tmp.string(), std::strerror(err)));
  }
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  if (ec) throw RunError(fmt::format("renaming '{}' to '{}' failed: {}", tmp.string(), path.string(), ec.message()));
}

DirectoryLock::DirectoryLock(const std::filesystem::path& dir, const char* name, const std::string& held_message) {
  const std::filesystem::path file = dir / name;
  fd_ = open_file(file, O_RDWR);  // a link planted under the name is replaced, not followed
  if (fd_ < 0) throw InputError(fmt::format("cannot create the lock file '{}': {}", file.string(), file_error(errno)));
  if (::flock(fd_, LOCK_EX | LOCK_NB) != 0) {
    ::close(fd_);
    throw InputError(held_message);
  }
}

DirectoryLock::~DirectoryLock() {
  if (fd_ >= 0) ::close(fd_);  // releases the lock; the file stays (removing it would race a waiting locker)
}

}  // namespace qsdem
