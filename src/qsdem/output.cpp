#include "qsdem/output.hpp"

#include <fcntl.h>
#include <fmt/format.h>
#include <sys/file.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <fstream>

#include "qsdem/types.hpp"

namespace qsdem {

std::string series_row(long step, double time, double e1, double ev, const Measures& m) {
  return fmt::format("{},{:.10g},{:.10g},{:.10g},{:.10g},{:.10g},{:.10g},{:.10g},{:.10g},{:.8g},{:.8g},{:.8g},"
                     "{:.8g},{:.8g},{:.8g},{:.8g},{:.8g},{:.8g}",
                     step, time, e1, ev, m.stress(0, 0), m.stress(1, 1), m.stress(2, 2), m.mean_stress,
                     m.deviator, m.friction_angle_deg, m.void_ratio, m.coordination, m.ufr, m.iuf, m.imom,
                     m.ekin_trans + m.ekin_rot, m.ekin_trans, m.ekin_rot);
}

SeriesWriter::SeriesWriter(std::filesystem::path path, long keep_rows) : path_(std::move(path)) {
  partial_ = path_;
  partial_ += ".partial";
  if (keep_rows < 0) {
    file_ = std::fopen(partial_.c_str(), "w");
    if (!file_) throw RunError(fmt::format("cannot write '{}': {}", partial_.string(), std::strerror(errno)));
    write(series_header);
    return;
  }
  std::ifstream in(partial_);
  std::string kept, line;
  long lines = 0;
  while (lines < keep_rows + 1 && std::getline(in, line)) {
    kept += line + '\n';
    ++lines;
  }
  if (lines < keep_rows + 1)
    throw InputError(fmt::format("cannot resume: '{}' holds {} rows, the checkpoint expects {}", partial_.string(),
                                 std::max(0L, lines - 1), keep_rows));
  in.close();
  file_ = std::fopen(partial_.c_str(), "w");
  if (!file_ || std::fputs(kept.c_str(), file_) < 0 || std::fflush(file_) != 0)
    throw RunError(fmt::format("cannot rewrite '{}': {}", partial_.string(), std::strerror(errno)));
}

SeriesWriter::~SeriesWriter() {
  if (file_) std::fclose(file_);
}

void SeriesWriter::write(const std::string& row) {
  if (std::fputs(row.c_str(), file_) < 0 || std::fputc('\n', file_) < 0 || std::fflush(file_) != 0)
    throw RunError(fmt::format("write to '{}' failed: {}", partial_.string(), std::strerror(errno)));
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
  std::filesystem::rename(partial, path, ec);
  if (ec) throw RunError(fmt::format("renaming '{}' to '{}' failed: {}", partial.string(), path.string(), ec.message()));
}

void write_file_atomic(const std::filesystem::path& path, const std::string& text) {
  std::filesystem::path tmp = path;
  tmp += ".tmp";
  std::FILE* f = std::fopen(tmp.c_str(), "w");
  if (!f) throw RunError(fmt::format("cannot write '{}': {}", tmp.string(), std::strerror(errno)));
  bool ok = std::fwrite(text.data(), 1, text.size(), f) == text.size() && std::fflush(f) == 0 &&
            ::fsync(fileno(f)) == 0;
  int err = errno;
  if (std::fclose(f) != 0 && ok) ok = false, err = errno;
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
  fd_ = ::open(file.c_str(), O_RDWR | O_CREAT | O_CLOEXEC, 0644);
  if (fd_ < 0) throw InputError(fmt::format("cannot create the lock file '{}': {}", file.string(), std::strerror(errno)));
  if (::flock(fd_, LOCK_EX | LOCK_NB) != 0) {
    ::close(fd_);
    throw InputError(held_message);
  }
}

DirectoryLock::~DirectoryLock() {
  if (fd_ >= 0) ::close(fd_);  // releases the lock; the file stays (removing it would race a waiting locker)
}

}  // namespace qsdem
