#include "qsdem/output.hpp"

#include <fmt/format.h>
#include <unistd.h>

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
    if (!file_) throw RunError(fmt::format("cannot write '{}'", partial_.string()));
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
    throw RunError(fmt::format("cannot rewrite '{}'", partial_.string()));
}

SeriesWriter::~SeriesWriter() {
  if (file_) std::fclose(file_);
}

void SeriesWriter::write(const std::string& row) {
  if (std::fputs(row.c_str(), file_) < 0 || std::fputc('\n', file_) < 0 || std::fflush(file_) != 0)
    throw RunError(fmt::format("write to '{}' failed (disk full?)", partial_.string()));
}

void SeriesWriter::commit() {
  if (::fsync(fileno(file_)) != 0 || std::fclose(file_) != 0)
    throw RunError(fmt::format("closing '{}' failed", partial_.string()));
  file_ = nullptr;
  std::filesystem::rename(partial_, path_);
}

void write_file_atomic(const std::filesystem::path& path, const std::string& text) {
  std::filesystem::path tmp = path;
  tmp += ".tmp";
  std::FILE* f = std::fopen(tmp.c_str(), "w");
  if (!f) throw RunError(fmt::format("cannot write '{}'", tmp.string()));
  const bool ok = std::fwrite(text.data(), 1, text.size(), f) == text.size() && std::fflush(f) == 0 &&
                  ::fsync(fileno(f)) == 0;
  if (std::fclose(f) != 0 || !ok) throw RunError(fmt::format("write to '{}' failed (disk full?)", tmp.string()));
  std::filesystem::rename(tmp, path);
}

}  // namespace qsdem
