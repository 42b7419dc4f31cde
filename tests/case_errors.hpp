// The error messages of case files in the unit tests: the InputError of a parse, and a check that
// it names every fragment.
#pragma once
#include <gtest/gtest.h>

#include <initializer_list>
#include <string>
#include <vector>

#include "qsdem/run/config.hpp"

namespace qsdem_test {

// The message of the InputError that parsing the case `toml` throws ("" if none).
inline std::string error_of(const std::string& toml, const std::vector<std::string>& overrides = {}) {
  try {
    qsdem::parse_case(toml, "case.toml", overrides);
  } catch (const qsdem::InputError& e) {
    return e.what();
  }
  return "";
}

// That `message` is an error's and holds every fragment.
inline void expect_mentions(const std::string& message, std::initializer_list<std::string> fragments) {
  EXPECT_FALSE(message.empty()) << "expected an InputError";
  for (const auto& f : fragments)
    EXPECT_NE(message.find(f), std::string::npos) << "message lacks \"" << f << "\":\n  " << message;
}

}  // namespace qsdem_test
