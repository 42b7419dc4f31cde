// Fuzz target: the case-file parser. Any input must give a Params or an InputError, never a crash.
// A first line starting with "--set " is applied as an override, to fuzz that path too.
#include <cstddef>
#include <cstdint>
#include <string>

#include "qsdem/run/config.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  std::string text(reinterpret_cast<const char*>(data), size);
  std::vector<std::string> overrides;
  if (text.rfind("--set ", 0) == 0) {
    const auto nl = text.find('\n');
    overrides.push_back(text.substr(6, nl == std::string::npos ? std::string::npos : nl - 6));
    text = nl == std::string::npos ? std::string() : text.substr(nl + 1);
  }
  try {
    qsdem::parse_case(text, "fuzz.toml", overrides);
  } catch (const qsdem::InputError&) {
  }
  return 0;
}
