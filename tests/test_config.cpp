// The case file (docs/config.md, src/qsdem/run/config.cpp): shipped examples, --set overrides, the
// error messages of bad input (SPEC 1: values carry units, nothing is silently SI or mm), and the
// rescaling of the size table (SPEC 9: the mass fractions of the grading are kept).
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <initializer_list>
#include <iterator>
#include <sstream>
#include <string>
#include <vector>

#include "case_errors.hpp"
#include "qsdem/engine/particles.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/generate.hpp"

using namespace qsdem;
using qsdem_test::error_of;
using qsdem_test::expect_mentions;

namespace {

const std::filesystem::path examples = std::filesystem::path(QSDEM_SOURCE_DIR) / "examples";

// A complete small case; the error tests replace one line (1-based) to know where it is.
const std::vector<std::string> base_lines{
    "name = \"t\"",                   // 1
    "[material]",                     // 2
    "density = \"2650 kg/m^3\"",      // 3
    "young_modulus = \"78 GPa\"",     // 4
    "poisson_ratio = 0.3",            // 5
    "[sample]",                       // 6
    "seed = 3",                       // 7
    "[[sample.particles]]",           // 8
    "shape = \"sphere\"",             // 9
    "diameter = \"2 mm\"",            // 10
    "count = 100",                    // 11
    "[damping]",                      // 12
    "model = \"nd\"",                 // 13
    "ratio = \"0.5 %\"",              // 14
    "[compaction]",                   // 15
    "friction = 0.2",                 // 16
    "stress = \"390 kPa\"",           // 17
    "[triaxial]",                     // 18
    "friction = 0.5",                 // 19
    "confining_stress = \"390 kPa\"", // 20
    "strain_rate = 1e-5",             // 21
};

std::string base_case(int line = 0, const std::string& replacement = "") {
  std::string out;
  for (std::size_t k = 0; k < base_lines.size(); ++k)
    out += (static_cast<int>(k) + 1 == line ? replacement : base_lines[k]) + "\n";
  return out;
}

// Equal-volume sphere diameter of a prolate spheroid (a, b, b): d = 2 (a b^2)^(1/3) (SPEC 2).
double equal_volume_diameter(double a, double b) { return 2 * std::cbrt(a * b * b); }

}  // namespace

// SPEC 9: every shipped example parses; Sample A and B have the paper's material, loading and the
// equal-volume spheres of Tables 1-2 (diameters written to 0.01 mm).
TEST(Config, ShippedExamplesParseWithSiValues) {
  int n = 0;
  for (const auto& entry : std::filesystem::directory_iterator(examples)) {
    if (entry.path().extension() != ".toml") continue;
    ++n;
    EXPECT_NO_THROW(load_case(entry.path().string())) << entry.path();
  }
  EXPECT_GE(n, 3);

  struct Row {
    double a_mm, b_mm;
    long count;
  };
  const std::vector<Row> sample_a{{1.2, 1.0, 7284}, {3.9, 3.0, 498}, {7.0, 5.0, 150}, {10.5, 7.0, 68}};
  const std::vector<Row> sample_b{{6.6, 5.5, 1448}, {7.8, 6.0, 2056}, {9.1, 6.5, 2252}, {10.5, 7.0, 2244}};
  for (const auto& [file, rows, total] :
       {std::tuple{"spheres-A.toml", sample_a, 0L}, std::tuple{"spheres-B.toml", sample_b, 0L},
        std::tuple{"spheres-A-small.toml", sample_a, 1000L}}) {
    SCOPED_TRACE(file);
    const Params p = load_case((examples / file).string());
    EXPECT_DOUBLE_EQ(p.material.density, 2650);
    EXPECT_DOUBLE_EQ(p.material.young_modulus, 7.8e10);  // "78 GPa"
    EXPECT_DOUBLE_EQ(p.material.poisson_ratio, 0.3);
    EXPECT_DOUBLE_EQ(p.step_ratio, 0.32);
    EXPECT_EQ(p.sample.total_particles, total);
    EXPECT_LE(p.sample.initial_solid_fraction, 0.2);  // SPEC 8: loose, solid fraction <= 0.2
    ASSERT_EQ(p.sample.table.size(), rows.size());
    for (std::size_t k = 0; k < rows.size(); ++k) {
      const SizeClass& c = p.sample.table[k];
      EXPECT_EQ(c.shape, ShapeKind::sphere);
      EXPECT_EQ(c.count, rows[k].count);
      EXPECT_DOUBLE_EQ(c.semi_axes.x(), c.semi_axes.z());
      // Rounded to 0.01 mm in the file: within half a digit of the equal-volume diameter.
      EXPECT_NEAR(2 * c.semi_axes.x(), 1e-3 * equal_volume_diameter(rows[k].a_mm, rows[k].b_mm), 0.005e-3) << k;
    }
    ASSERT_EQ(p.protocol.size(), 2u);
    const Phase &compaction = p.protocol[0], &triaxial = p.protocol[1];
    EXPECT_EQ(triaxial.damping.model, "nd");
    EXPECT_DOUBLE_EQ(triaxial.damping.ratio, 0.005);                         // "0.5 %"
    EXPECT_DOUBLE_EQ(compaction.friction, 0.2);                              // mu_0
    EXPECT_DOUBLE_EQ(compaction.controls.component[0].value, 390000);        // "390 kPa"
    EXPECT_DOUBLE_EQ(triaxial.friction, 0.5);
    EXPECT_DOUBLE_EQ(triaxial.controls.component[0].value, 390000);
    EXPECT_DOUBLE_EQ(triaxial.controls.component[2].value, 1e-5);
    EXPECT_DOUBLE_EQ(*triaxial.stop.strain[2], 0.10);                        // "10 %"
    EXPECT_EQ(triaxial.output.cadence.points, 250);
  }
  // The paper's own samples: exactly Tables 1-3 (spheroids a x b = c, counts), full and scaled.
  for (const auto& [file, rows, total] :
       {std::tuple{"paper-A.toml", sample_a, 0L}, std::tuple{"paper-B.toml", sample_b, 0L},
        std::tuple{"paper-A-small.toml", sample_a, 2000L}, std::tuple{"paper-B-small.toml", sample_b, 1000L}}) {
    SCOPED_TRACE(file);
    const Params p = load_case((examples / file).string());
    EXPECT_DOUBLE_EQ(p.material.density, 2650);
    EXPECT_DOUBLE_EQ(p.material.young_modulus, 7.8e10);
    EXPECT_DOUBLE_EQ(p.material.poisson_ratio, 0.3);
    EXPECT_DOUBLE_EQ(p.step_ratio, 0.32);
    EXPECT_EQ(p.sample.total_particles, total);
    ASSERT_EQ(p.sample.table.size(), rows.size());
    for (std::size_t k = 0; k < rows.size(); ++k) {
      const SizeClass& c = p.sample.table[k];
      EXPECT_EQ(c.shape, ShapeKind::ellipsoid);
      EXPECT_EQ(c.count, rows[k].count);
      EXPECT_DOUBLE_EQ(c.semi_axes.x(), 1e-3 * rows[k].a_mm);
      EXPECT_DOUBLE_EQ(c.semi_axes.y(), 1e-3 * rows[k].b_mm);
      EXPECT_DOUBLE_EQ(c.semi_axes.z(), 1e-3 * rows[k].b_mm);
    }
    EXPECT_DOUBLE_EQ(p.protocol[0].friction, 0.2);
    EXPECT_DOUBLE_EQ(p.protocol[1].friction, 0.5);
    EXPECT_DOUBLE_EQ(p.protocol[1].controls.component[1].value, 390000);
  }
  // The spot value of the brief: 2.13 mm is 0.00213 m.
  const Params a = load_case((examples / "spheres-A.toml").string());
  EXPECT_DOUBLE_EQ(2 * a.sample.table[0].semi_axes.x(), 0.00213);
  // SPEC 9: R_min of Sample A is 1.0627 mm (the file rounds the diameter to 2.13 mm).
  EXPECT_NEAR(a.sample.table[0].semi_axes.x(), 1.0627e-3, 0.003e-3);
}

// --set overrides (docs/config.md): the value is TOML, or a bare string as the shell passes it.
TEST(Config, OverridesReplaceValues) {
  const std::string text = base_case();
  const auto test = [&](const std::string& set) { return parse_case(text, "case.toml", {set}).protocol.back(); };
  EXPECT_DOUBLE_EQ(test("damping.ratio=\"0.3 %\"").damping.ratio, 0.003);
  EXPECT_DOUBLE_EQ(test("damping.ratio=0.3 %").damping.ratio, 0.003);
  EXPECT_DOUBLE_EQ(test("damping.ratio=0.003").damping.ratio, 0.003);
  const Params od = parse_case(text, "case.toml", {"damping.model=od"});
  EXPECT_EQ(od.protocol.back().damping.model, "od");
  EXPECT_EQ(od.as_written["damping"]["model"], "od");  // summary.json shows what was run
  EXPECT_FALSE(od.as_written.contains("phase")) << "the case as written, not its phases";
  EXPECT_EQ(to_json(od)["protocol"][1]["damping"]["model"], "od");
  EXPECT_DOUBLE_EQ(test("triaxial.strain_rate=1e-6").controls.component[2].value, 1e-6);
  EXPECT_EQ(parse_case(text, "case.toml", {"sample.particles.0.count=10"}).sample.table[0].count, 10);
  // Several at once, the last one of a key wins.
  const Params p = parse_case(text, "case.toml",
                              {"sample.total_particles=2000", "damping.model=none", "damping.model=od"});
  EXPECT_EQ(p.sample.total_particles, 2000);
  EXPECT_EQ(p.protocol.back().damping.model, "od");
  // An override of a key the file does not set.
  EXPECT_DOUBLE_EQ(
      parse_case(text, "case.toml", {"compaction.stress_tolerance=0.02"}).protocol[0].stop.equilibrium->stress_tolerance,
      0.02);
  // Overrides are validated like the file.
  expect_mentions(error_of(text, {"damping.model=xd"}), {"damping.model", "xd", "\"od\""});
  expect_mentions(error_of(text, {"damping.ratoi=0.1"}), {"unknown key", "damping.ratoi"});
  expect_mentions(error_of(text, {"sample.particles.3.count=10"}), {"sample.particles.3.count", "out of range"});
  // An index beyond any integer is out of range too, not an uncaught std::out_of_range.
  expect_mentions(error_of(text, {"sample.particles.99999999999999999999.count=5"}),
                  {"index 99999999999999999999 is out of range"});
  expect_mentions(error_of(text, {"sample.particles.99999999999999999999=5"}), {"index 99999999999999999999 is out"});
  // A rate that would plan more steps than a run can take (the step count would overflow).
  expect_mentions(error_of(text, {"triaxial.strain_rate=1e-19"}), {"triaxial.strain_rate", "steps", "raise the rate"});
  expect_mentions(error_of(text, {"damping.ratio"}), {"key=value"});
}

// Bad input: InputError naming the file, the line, the key, the value and what is allowed.
TEST(Config, UnknownKeysAreErrors) {
  expect_mentions(error_of(base_case(16, "frction = 0.2")), {"case.toml:16", "unknown key", "compaction.frction"});
  // A misspelt optional key inside [[sample.particles]].
  expect_mentions(error_of(base_case(9, "shap = \"sphere\"")), {"case.toml:9", "unknown key", "sample.particles.0.shap"});
  expect_mentions(error_of(base_case(21, "strain_rate = 1e-5\nstrain = 1")), {"case.toml:22", "triaxial.strain"});
  expect_mentions(error_of(base_case() + "[servo]\ngain = 0.1\n"), {"case.toml:23", "servo.gain"});
}

// A misspelt REQUIRED key: the key is reported missing, and the user's spelling must be named
// too, otherwise the message sends them looking for a key they believe they wrote.
TEST(Config, MisspeltRequiredKeyIsNamed) {
  const std::string msg = error_of(base_case(10, "diamter = \"2 mm\""));
  expect_mentions(msg, {"case.toml", "sample.particles.0.diameter", "required"});
  expect_mentions(msg, {"diamter"});
}

TEST(Config, WrongTypesAreErrors) {
  expect_mentions(error_of(base_case(5, "poisson_ratio = \"0.3\"")),
                  {"case.toml:5", "material.poisson_ratio", "\"0.3\"", "expected a number"});
  expect_mentions(error_of(base_case(11, "count = 1.5")), {"case.toml:11", "sample.particles.0.count", "1.5", "integer"});
  // A dimensional value as a bare number: never silently SI (SPEC 1).
  expect_mentions(error_of(base_case(4, "young_modulus = 78e9")),
                  {"case.toml:4", "material.young_modulus", "unit", "GPa"});
  expect_mentions(error_of(base_case(13, "model = 2")), {"case.toml:13", "damping.model", "string"});
}

TEST(Config, MissingRequiredKeysAreErrors) {
  expect_mentions(error_of(base_case(3, "")), {"case.toml", "material.density", "required"});
  expect_mentions(error_of(base_case(5, "")), {"case.toml", "material.poisson_ratio", "required"});
  expect_mentions(error_of(base_case(11, "")), {"case.toml", "sample.particles.0.count", "required"});
  // No size table at all.
  std::string no_table;
  for (int k = 1; k <= 21; ++k)
    if (k < 8 || k > 11) no_table += base_lines[static_cast<std::size_t>(k - 1)] + "\n";
  expect_mentions(error_of(no_table), {"case.toml", "sample.particles", "required"});
}

TEST(Config, OutOfRangeValuesAreErrors) {
  // Sizes lie from 1 nm to 1 km; moduli must be > 0.
  expect_mentions(error_of(base_case(10, "diameter = \"0 mm\"")),
                  {"case.toml:10", "sample.particles.0.diameter", "0 mm", "from 1 nm to 1 km"});
  expect_mentions(error_of(base_case(10, "diameter = \"-2 mm\"")), {"case.toml:10", "-2 mm", "from 1 nm to 1 km"});
  expect_mentions(error_of(base_case(4, "young_modulus = \"0 GPa\"")), {"case.toml:4", "material.young_modulus", "> 0"});
  expect_mentions(error_of(base_case(3, "density = \"-1 kg/m^3\"")), {"case.toml:3", "material.density", "> 0"});
  // Poisson's ratio of an isotropic solid lies in (-1, 0.5).
  for (const char* v : {"0.5", "0.75", "-1", "-1.5"})
    expect_mentions(error_of(base_case(5, std::string("poisson_ratio = ") + v)),
                    {"case.toml:5", "material.poisson_ratio", v, "(-1, 0.5)"});
  EXPECT_EQ(error_of(base_case(5, "poisson_ratio = 0.49")), "");  // the open bound is allowed up to it
  EXPECT_EQ(error_of(base_case(5, "poisson_ratio = -0.5")), "");
  // Friction and damping ratios must be >= 0.
  expect_mentions(error_of(base_case(19, "friction = -0.1")), {"case.toml:19", "triaxial.friction", "-0.1", ">= 0"});
  expect_mentions(error_of(base_case(16, "friction = -0.2")), {"case.toml:16", "compaction.friction", ">= 0"});
  expect_mentions(error_of(base_case(14, "ratio = \"-0.1 %\"")), {"case.toml:14", "damping.ratio", "-0.1 %", ">= 0"});
  expect_mentions(error_of(base_case(14, "ratio = -0.001")), {"case.toml:14", "damping.ratio", ">= 0"});
  EXPECT_EQ(error_of(base_case(14, "ratio = 0")), "");  // damping ratio 0 is in the paper's sweep
  // eps' > 0.
  expect_mentions(error_of(base_case(21, "strain_rate = 0")), {"case.toml:21", "triaxial.strain_rate", "(0, 0.01)"});
  expect_mentions(error_of(base_case(21, "strain_rate = -1e-5")), {"case.toml:21", "triaxial.strain_rate", "(0, 0.01)"});
}

// The value in a message is the value as the user wrote it: 0.7, not its binary neighbour
// 0.69999999999999996 (which reads like a different number).
TEST(Config, ErrorMessageQuotesValueAsWritten) {
  expect_mentions(error_of(base_case(5, "poisson_ratio = 0.7")), {"'material.poisson_ratio' = 0.7:"});
  expect_mentions(error_of(base_case(21, "strain_rate = 0.3")), {"'triaxial.strain_rate' = 0.3:"});
}

TEST(Config, UnitsAreRequiredAndChecked) {
  expect_mentions(error_of(base_case(17, "stress = \"390\"")),
                  {"case.toml:17", "compaction.stress", "\"390\"", "no unit", "kPa"});
  expect_mentions(error_of(base_case(17, "stress = \"390 kpa\"")),
                  {"case.toml:17", "compaction.stress", "kpa", "unknown", "kPa", "MPa"});
  expect_mentions(error_of(base_case(10, "diameter = \"2 furlongs\"")), {"case.toml:10", "furlongs", "mm"});
  // A length where a stress is expected.
  expect_mentions(error_of(base_case(20, "confining_stress = \"390 mm\"")), {"case.toml:20", "triaxial.confining_stress", "Pa"});
}

TEST(Config, UnknownDampingModelIsAnError) {
  expect_mentions(error_of(base_case(13, "model = \"xd\"")),
                  {"case.toml:13", "damping.model", "\"xd\"", "\"none\"", "\"od\"", "\"nd\""});
}

// damping.acts_on: what the triaxial phase's particle damping acts on (damping/models.hpp), both by default.
TEST(Config, DampingActsOnIsChecked) {
  EXPECT_EQ(parse_case(base_case(), "case.toml").protocol[1].damping.acts_on, DampedMotion::both);
  EXPECT_EQ(parse_case(base_case(13, "acts_on = \"rotation\""), "case.toml").protocol[1].damping.acts_on, DampedMotion::rotation);
  EXPECT_EQ(parse_case(base_case(), "case.toml", {"damping.acts_on=translation"}).protocol[1].damping.acts_on,
            DampedMotion::translation);
  expect_mentions(error_of(base_case(13, "acts_on = \"spin\"")),
                  {"case.toml:13", "damping.acts_on", "\"spin\"", "\"both\"", "\"translation\"", "\"rotation\""});
}

// [contact] (docs/config.md): the law is one that contact/laws.hpp registers, Hertz-Mindlin by
// default; a key that the chosen law does not declare is named with the law and what it takes.
TEST(Config, ContactLawAndItsKeysAreChecked) {
  EXPECT_EQ(parse_case(base_case(), "case.toml").contact.law, "hertz_mindlin");
  EXPECT_TRUE(parse_case(base_case(), "case.toml").contact.values.empty());
  EXPECT_EQ(parse_case(base_case() + "[contact]\nlaw = \"hertz_mindlin\"\n", "case.toml").contact.law, "hertz_mindlin");
  expect_mentions(error_of(base_case() + "[contact]\nlaw = \"hooke\"\n"),
                  {"case.toml:23", "contact.law", "\"hooke\"", "\"hertz_mindlin\""});
  expect_mentions(error_of(base_case() + "[contact]\nrestitution = 0.5\n"),
                  {"case.toml:23", "contact.restitution", "hertz_mindlin", "no keys of its own"});
  expect_mentions(error_of(base_case(), {"contact.law=hooke"}), {"contact.law", "\"hooke\"", "hertz_mindlin"});
}

TEST(Config, TomlSyntaxErrorNamesTheLine) {
  expect_mentions(error_of(base_case(12, "[damping")), {"case.toml:12", "TOML syntax error"});
  expect_mentions(error_of(base_case(16, "friction = ")), {"case.toml:16", "TOML syntax error"});
}

TEST(Config, MissingFileIsAnInputError) {
  try {
    load_case("/nonexistent/dir/case.toml");
    FAIL() << "expected an InputError";
  } catch (const InputError& e) {
    expect_mentions(e.what(), {"/nonexistent/dir/case.toml"});
  }
}

// SPEC 9 / docs: total_particles rescales every count to round(count N / sum count), which keeps
// the count ratios and so the mass fractions of Sample A (10/20/30/40 %).
TEST(Config, ResolveTableKeepsSampleAGrading) {
  const Params p = load_case((examples / "spheres-A.toml").string());
  Params::Sample s = p.sample;
  s.total_particles = 1000;
  const auto table = resolve_table(s);
  ASSERT_EQ(table.size(), 4u);
  // 7284/8: 910.5 -> 911 (half away from zero), 498/8 = 62.25, 150/8 = 18.75, 68/8 = 8.5 -> 9.
  EXPECT_EQ(table[0].count, 911);
  EXPECT_EQ(table[1].count, 62);
  EXPECT_EQ(table[2].count, 19);
  EXPECT_EQ(table[3].count, 9);
  for (std::size_t k = 0; k < 4; ++k) EXPECT_EQ(table[k].semi_axes, p.sample.table[k].semi_axes);

  double total = 0;
  std::vector<double> mass;
  for (const auto& c : table) {
    mass.push_back(static_cast<double>(c.count) * ellipsoid_volume(c.semi_axes));
    total += mass.back();
  }
  // Tolerance 2.5 percentage points: rounding moves a count by at most half a particle, and half
  // of one of the 9 coarsest spheres is 2.3 % of the total mass (the written table itself is
  // within 0.1 point of 10/20/30/40; here: 9.8, 19.4, 29.6, 41.2 %).
  const std::vector<double> target{0.10, 0.20, 0.30, 0.40};
  for (std::size_t k = 0; k < 4; ++k) EXPECT_NEAR(mass[k] / total, target[k], 0.025) << k;

  // The written table itself is used when total_particles is 0.
  s.total_particles = 0;
  EXPECT_EQ(resolve_table(s)[0].count, 7284);
}

// Messages of bad values name the file, line, key and value as written, and what is allowed.
TEST(Config, MessagesOfAbsurdValues) {
  // A number beyond a double's range is said to be so (not "does not start with a number").
  expect_mentions(error_of(base_case(10, "diameter = \"1e400 mm\"")),
                  {"case.toml:10", "sample.particles.0.diameter", "1e400 mm", "out of the range of a double"});
  // A float where a whole number goes is shown as written, with the whole number to write.
  expect_mentions(error_of(base_case(11, "count = 7284.0")),
                  {"case.toml:11", "sample.particles.0.count", "= 7284.0", "without a decimal point: 7284"});
  // Sizes whose masses a double cannot hold are refused (1e-320 m ran into NaN at step 2).
  expect_mentions(error_of(base_case(10, "diameter = \"1e-320 m\"")),
                  {"case.toml:10", "1e-320 m", "from 1 nm to 1 km"});
  expect_mentions(error_of(base_case(10, "diameter = \"2000 m\"")), {"case.toml:10", "2000 m", "from 1 nm to 1 km"});
  EXPECT_EQ(error_of(base_case(10, "diameter = \"0.002 um\"")), "");
}

TEST(Config, ADirectoryIsNoCaseFile) {
  try {
    load_case(examples.string());
    ADD_FAILURE() << "a directory was read as a case";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("is a directory"), std::string::npos) << e.what();
  }
}

// sample.from in a case file is relative to the case file (as the paths of a study file are to
// the study file); on the command line, to the working directory. Kept absolute.
TEST(Config, SampleFromIsRelativeToTheCaseFile) {
  namespace fs = std::filesystem;
  const fs::path dir = fs::temp_directory_path() / ("qsdem_config_from_" + std::to_string(::getpid())) / "cases";
  fs::create_directories(dir);
  std::string with_from = base_case();
  with_from.insert(with_from.find("[[sample.particles]]"), "from = \"packings/a.packing\"\n");
  std::ofstream(dir / "case.toml") << with_from;
  const Params p = load_case((dir / "case.toml").string());
  EXPECT_EQ(p.sample.from, (dir / "packings" / "a.packing").string());
  EXPECT_NE(p.case_text.find((dir / "packings" / "a.packing").string()), std::string::npos)
      << "the checkpoint's case names the same file";
  const Params q = load_case((dir / "case.toml").string(), {"sample.from=other.packing"});
  EXPECT_EQ(q.sample.from, (fs::current_path() / "other.packing").string());
  fs::remove_all(dir.parent_path());
}

// inertia_scaling (docs/config.md, SPEC 5.6): off by default; per phase, as [compaction] and
// [triaxial] keys and in a [[phase]] entry; one of target and factor, the cap in [1, 10^6]; refused
// with a controller that plans its steps with time.step_ratio alone.
TEST(Config, InertiaScalingIsReadPerPhaseAndChecked) {
  const Params off = parse_case(base_case(), "case.toml");
  for (const Phase& ph : off.protocol) EXPECT_FALSE(ph.inertia.on());
  const Params on = parse_case(base_case(), "case.toml",
                               {"triaxial.inertia_scaling.target=coarsest", "compaction.inertia_scaling.factor=2.5",
                                "compaction.inertia_scaling.cap=4"});
  EXPECT_EQ(on.protocol.front().inertia.target, InertiaScaling::Target::factor);
  EXPECT_EQ(on.protocol.front().inertia.factor, 2.5);
  EXPECT_EQ(on.protocol.front().inertia.cap, 4);
  EXPECT_EQ(on.protocol.back().inertia.target, InertiaScaling::Target::coarsest);
  EXPECT_EQ(on.protocol.back().inertia.cap, 100) << "the default cap";

  expect_mentions(error_of(base_case(21, "strain_rate = 1e-5\ninertia_scaling = { target = \"finest\" }")),
                  {"case.toml:22", "triaxial.inertia_scaling.target", "\"finest\"", "\"coarsest\""});
  expect_mentions(error_of(base_case(21, "strain_rate = 1e-5\ninertia_scaling = { factor = 0.5 }")),
                  {"triaxial.inertia_scaling.factor", "0.5", "(1, 1000]"});
  expect_mentions(error_of(base_case(21, "strain_rate = 1e-5\ninertia_scaling = { target = \"coarsest\", cap = 0.5 }")),
                  {"triaxial.inertia_scaling.cap", "0.5", "[1, 10^6]"});
  expect_mentions(error_of(base_case(21, "strain_rate = 1e-5\ninertia_scaling = { target = \"coarsest\", factor = 2 }")),
                  {"triaxial.inertia_scaling.factor", "one of target and factor"});
  expect_mentions(error_of(base_case(21, "strain_rate = 1e-5\ninertia_scaling = { cap = 10 }")),
                  {"triaxial.inertia_scaling", "needs target = \"coarsest\" or factor"});
  expect_mentions(error_of(base_case(21, "strain_rate = 1e-5\ninertia_scaling = \"coarsest\"")),
                  {"triaxial.inertia_scaling", "expected a table"});
  expect_mentions(error_of(base_case(21, "strain_rate = 1e-5\ninertia_scaling = { target = \"coarsest\", gain = 2 }")),
                  {"unknown key", "triaxial.inertia_scaling.gain"});
  expect_mentions(error_of(base_case(21, "strain_rate = 1e-5\ninertia_scaling = { factor = 2 }\n[triaxial.rate_control]\n"
                                         "target = \"3 %\"\nmin_rate = 1e-6\nmax_rate = 1e-3")),
                  {"triaxial.inertia_scaling", "rate_control"});
}

// A [[phase]] entry with inertia_scaling is refused with the cyclic controller, which plans its
// steps with time.step_ratio alone; the same phase with a step budget instead takes it.
TEST(Config, PhaseInertiaScalingIsRefusedWithAStepPlanningController) {
  std::ifstream in(examples / "cyclic-triaxial.toml");
  std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const std::string controller = "controller = { kind = \"cyclic\"";
  ASSERT_NE(text.find(controller), std::string::npos);
  text.insert(text.find(controller), "inertia_scaling = { factor = 2 }\n");
  expect_mentions(error_of(text), {"phase.1.inertia_scaling", "controller \"cyclic\"", "time.step_ratio"});
  const std::size_t at = text.find(controller);
  const Params p = parse_case(text.replace(at, text.find('\n', at) - at, "stop = { steps = 1000 }"), "case.toml");
  EXPECT_EQ(p.protocol.at(1).inertia.target, InertiaScaling::Target::factor);
  EXPECT_EQ(p.protocol.at(1).inertia.factor, 2);
  EXPECT_FALSE(p.protocol.at(0).inertia.on());
}

// A [[phase]] with solver = "fire" (docs/physics.md 5.7): read with its tolerances, its damping
// off; the keys it cannot take are refused by key and reason, and so are FIRE keys in a dynamic phase.
TEST(Config, FireSolverIsReadAndItsPhaseChecked) {
  std::ifstream in(examples / "fire-triaxial.toml");
  const std::string text((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  const Params p = parse_case(text, "case.toml");
  ASSERT_TRUE(p.protocol.at(1).fire.has_value());
  EXPECT_FALSE(p.protocol.at(0).fire.has_value());
  EXPECT_DOUBLE_EQ(p.protocol.at(1).fire->strain_increment, 1e-4);
  EXPECT_DOUBLE_EQ(p.protocol.at(1).fire->ufr, 5e-3);
  EXPECT_EQ(p.protocol.at(1).damping.model, "none");
  expect_mentions(error_of(text, {"phase.1.damping.model=\"nd\""}), {"phase.1.damping.model", "FIRE is the phase's dissipation"});
  expect_mentions(error_of(text, {"phase.1.output.points=10"}), {"phase.1.output.points", "each increment writes one row"});
  expect_mentions(error_of(text, {"output.energy=true"}), {"phase.1.solver", "output.energy"});
  expect_mentions(error_of(text, {"phase.1.solver.strain_increment=\"2 %\""}), {"phase.1.solver.strain_increment", "(0, 1 %]"});
  expect_mentions(error_of(text, {"phase.0.solver.ufr=\"1 %\""}), {"phase.0.solver.ufr", "only with kind = \"fire\""});
}
