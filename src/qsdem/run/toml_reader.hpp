// What every reader of a TOML file (a case, a study) shares: where a value was written, and the
// error that names it: file:line (or the --set override), the key, the value and why.
#pragma once
#include <string>

#include <toml++/toml.h>

namespace qsdem {

// A value as the user wrote it: "0.5 %" quoted, 7284.0 as a float, "(a table)", "(an array)".
std::string describe(const toml::node& n);

// Shortest round trip (0.7, not 0.69999999999999996), with ".0" on a whole number.
std::string format_float(double v);

class TomlSource {
 public:
  explicit TomlSource(std::string file) : file_(std::move(file)) {}

  const std::string& file() const { return file_; }
  // "file:line", the override ("--set ...") that wrote n, or the file.
  std::string where(const toml::node* n) const;
  // Throws InputError "where: key 'path' = value: why" (without the value when n is null).
  [[noreturn]] void fail(const std::string& path, const toml::node* n, const std::string& why) const;

 private:
  std::string file_;
};

}  // namespace qsdem
