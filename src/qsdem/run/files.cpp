#include "qsdem/run/files.hpp"

#include <fmt/format.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>

#include "qsdem/engine/types.hpp"

namespace qsdem {

namespace fs = std::filesystem;

namespace {

// A regular file's descriptor made blocking again (O_NONBLOCK only kept a FIFO from blocking the
// open); any other kind of file is closed and refused with EINVAL.
int keep_if_regular(int fd) {
  if (fd < 0) return fd;
  struct stat st {};
  if (::fstat(fd, &st) != 0 || !S_ISREG(st.st_mode)) {
    ::close(fd);
    errno = EINVAL;
    return -1;
  }
  const int fl = ::fcntl(fd, F_GETFL);
  if (fl >= 0) ::fcntl(fd, F_SETFL, fl & ~O_NONBLOCK);
  return fd;
}

// A name that something else keeps re-creating between our unlink and our open is given up after
// this many attempts.
constexpr int attempts = 8;

}  // namespace

int create_file(const fs::path& path, int flags) {
  for (int k = 0; k < attempts; ++k) {
    if (::unlink(path.c_str()) != 0 && errno != ENOENT) return -1;
    const int fd = ::open(path.c_str(), flags | O_CREAT | O_EXCL | O_NOFOLLOW | O_CLOEXEC, 0644);
    if (fd >= 0 || errno != EEXIST) return fd;
  }
  return -1;
}

int open_file(const fs::path& path, int flags) {
  for (int k = 0; k < attempts; ++k) {
    const int fd = ::open(path.c_str(), flags | O_CREAT | O_NOFOLLOW | O_NONBLOCK | O_CLOEXEC, 0644);
    if (fd < 0 && errno == ELOOP) {
      if (::unlink(path.c_str()) != 0 && errno != ENOENT) return -1;
      continue;
    }
    return keep_if_regular(fd);
  }
  errno = ELOOP;
  return -1;
}

int open_regular_file(const fs::path& path, int flags) {
  return keep_if_regular(::open(path.c_str(), flags | O_NOFOLLOW | O_NONBLOCK | O_CLOEXEC));
}

std::string file_error(int err) {
  if (err == ELOOP) return "it is a symbolic link, and qsdem reads and writes no file through one";
  if (err == EINVAL) return "it is not a regular file";
  return std::strerror(err);
}

std::optional<std::string> read_regular_file(const fs::path& path, int* err) {
  const int fd = open_regular_file(path, O_RDONLY);
  if (fd < 0) {
    if (err) *err = errno;
    return std::nullopt;
  }
  std::string text;
  char buf[1 << 16];
  for (;;) {
    const ssize_t n = ::read(fd, buf, sizeof buf);
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) {
      if (err) *err = errno;
      ::close(fd);
      return std::nullopt;
    }
    if (n == 0) break;
    text.append(buf, static_cast<std::size_t>(n));
  }
  ::close(fd);
  return text;
}

void make_directories(const fs::path& base, const fs::path& relative) {
  int fd = ::open(base.empty() ? "." : base.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0) throw InputError(fmt::format("cannot open the directory '{}': {}", base.string(), std::strerror(errno)));
  fs::path at = base;
  for (const fs::path& part : relative.lexically_normal()) {
    if (part.empty() || part == ".") continue;
    at /= part;
    if (part == "..") {
      ::close(fd);
      throw InputError(fmt::format("'{}' leads out of '{}'", at.string(), base.string()));
    }
    if (::mkdirat(fd, part.c_str(), 0755) != 0 && errno != EEXIST) {
      const int err = errno;
      ::close(fd);
      throw InputError(fmt::format("cannot create the directory '{}': {}", at.string(), std::strerror(err)));
    }
    const int next = ::openat(fd, part.c_str(), O_RDONLY | O_DIRECTORY | O_NOFOLLOW | O_CLOEXEC);
    const int err = errno;
    ::close(fd);
    if (next < 0)
      throw InputError(fmt::format("cannot write into '{}': {}", at.string(),
                                   err == ELOOP || err == ENOTDIR
                                       ? "it is a symbolic link or not a directory, and qsdem writes nothing through "
                                         "a link: replace it by a directory"
                                       : std::strerror(err)));
    fd = next;
  }
  ::close(fd);
}

std::size_t invalid_utf8_at(std::string_view text) {
  const auto* b = reinterpret_cast<const unsigned char*>(text.data());
  const std::size_t size = text.size();
  std::size_t i = 0;
  while (i < size) {
    const unsigned c = b[i];
    if (c < 0x80) {
      ++i;
      continue;
    }
    // The continuation bytes a lead byte takes, and the range of the first (Unicode 15, Table 3-7).
    std::size_t n = 0;
    unsigned lo = 0x80, hi = 0xBF;
    if (c >= 0xC2 && c <= 0xDF) n = 1;
    else if (c == 0xE0) n = 2, lo = 0xA0;
    else if ((c >= 0xE1 && c <= 0xEC) || c == 0xEE || c == 0xEF) n = 2;
    else if (c == 0xED) n = 2, hi = 0x9F;
    else if (c == 0xF0) n = 3, lo = 0x90;
    else if (c >= 0xF1 && c <= 0xF3) n = 3;
    else if (c == 0xF4) n = 3, hi = 0x8F;
    else return i;
    for (std::size_t k = 1; k <= n; ++k) {
      if (i + k >= size) return i;
      const unsigned d = b[i + k];
      if (d < (k == 1 ? lo : 0x80u) || d > (k == 1 ? hi : 0xBFu)) return i;
    }
    i += n + 1;
  }
  return std::string_view::npos;
}

void require_utf8(std::string_view text, const std::string& what) {
  std::size_t bad = invalid_utf8_at(text);
  if (bad == std::string_view::npos) return;
  const std::size_t first = bad;
  std::string shown;
  std::size_t from = 0;
  while (bad != std::string_view::npos) {
    shown.append(text.substr(from, bad - from));
    shown += fmt::format("\\x{:02X}", static_cast<unsigned char>(text[bad]));
    from = bad + 1;
    const std::size_t next = invalid_utf8_at(text.substr(from));
    bad = next == std::string_view::npos ? next : from + next;
  }
  shown.append(text.substr(from));
  throw InputError(fmt::format("{} '{}' is not valid UTF-8 (byte {} is 0x{:02X}): qsdem writes it into JSON files "
                               "(summary.json, study.json), which hold UTF-8 only; rename it, or write it in UTF-8",
                               what, shown, first, static_cast<unsigned char>(text[first])));
}

}  // namespace qsdem
