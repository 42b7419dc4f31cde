// Quantities with units (SPEC 1).
#include <gtest/gtest.h>

#include "qsdem/engine/types.hpp"
#include "qsdem/run/units.hpp"

using namespace qsdem;

TEST(Units, ParsesStressLengthDensityRatio) {
  EXPECT_DOUBLE_EQ(parse_quantity("390 kPa", Dimension::stress), 390e3);
  EXPECT_DOUBLE_EQ(parse_quantity("78 GPa", Dimension::stress), 78e9);
  EXPECT_DOUBLE_EQ(parse_quantity("2.13 mm", Dimension::length), 2.13e-3);
  EXPECT_DOUBLE_EQ(parse_quantity("2650 kg/m^3", Dimension::density), 2650);
  EXPECT_DOUBLE_EQ(parse_quantity("0.5 %", Dimension::ratio), 0.005);
  EXPECT_DOUBLE_EQ(parse_quantity("0.005", Dimension::ratio), 0.005);
}

TEST(Units, RefusesMissingOrWrongUnit) {
  EXPECT_THROW(parse_quantity("390", Dimension::stress), InputError);     // no unit: never silently SI
  EXPECT_THROW(parse_quantity("2.13 mm", Dimension::stress), InputError); // wrong dimension
  EXPECT_THROW(parse_quantity("abc kPa", Dimension::stress), InputError);
  try {
    parse_quantity("3 furlongs", Dimension::length);
    FAIL();
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("mm"), std::string::npos) << "lists the allowed units";
  }
}
