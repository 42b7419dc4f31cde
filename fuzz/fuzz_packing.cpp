// Fuzz target: the packing parser. Any input must give a State or an InputError, never a crash.
#include <cstddef>
#include <cstdint>
#include <sstream>
#include <string>

#include "qsdem/run/packing_io.hpp"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  std::istringstream in(std::string(reinterpret_cast<const char*>(data), size));
  try {
    qsdem::parse_packing(in, "fuzz.packing", 2650);
  } catch (const qsdem::InputError&) {
  }
  return 0;
}
