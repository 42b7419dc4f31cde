// The case file (TOML, docs/config.md) read into plain parameters. Every key is checked:
// unknown keys, wrong types and out-of-range values raise InputError naming file, line, key,
// value and what is allowed.
#pragma once
#include <cstdint>
#include <filesystem>
#include <functional>
#include <map>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json.hpp>

#include "qsdem/engine/types.hpp"
#include "qsdem/run/phase.hpp"

namespace qsdem {

inline constexpr const char* classes_file = "classes.csv";  // docs/physics.md 10.3, output.classes

// One row of the particle-size table (SPEC 9): a shape and how many of it.
struct SizeClass {
  ShapeKind shape = ShapeKind::sphere;
  Vec3 semi_axes = Vec3::Zero();  // a >= b >= c (m); a sphere has a = b = c = R
  long count = 0;
};

// A sieve curve (docs/physics.md 8.6): the sample's sizes are drawn by mass from it.
struct Grading {
  std::vector<double> size;          // d_k, equal-volume diameters (m), increasing
  std::vector<double> passing;       // P_k, mass fraction finer than d_k: 0 at the first point, 1 at the last
  std::vector<double> aspect_ratio;  // a/b in interval k = [d_k, d_k+1]: 1 a sphere, > 1 a prolate spheroid
  bool empty() const { return size.empty(); }
};

struct Params {
  std::string name;
  std::string source;  // file name, or "<built-in default>"

  struct Material {
    double density = 0;        // kg/m^3
    double young_modulus = 0;  // Pa
    double poisson_ratio = 0;
  } material;

  struct Sample {
    std::uint64_t seed = 1;
    double initial_solid_fraction = 0.15;
    long total_particles = 0;  // 0: the table's counts as written; with a grading, its particles
    std::vector<SizeClass> table;
    Grading grading;           // [[sample.grading]], instead of the table
    std::string from;          // a prepared sample (directory of `qsdem prepare`) or a packing
                               // file: an absolute path (parse_case resolves it)
  } sample;

  double step_ratio = 0.32;  // c_t (SPEC 5)

  ContactSettings contact;

  struct Servo {
    double proportional_gain = 0.1;
    double integral_gain = 0.002;
  } servo;

  struct Neighbor {
    double skin_ratio = 0.2;  // Verlet skin as a fraction of the smallest equal-volume radius
  } neighbor;

  struct Checkpoint {
    int every_sample_points = 25;  // also one at the end of compaction and on SIGINT/SIGTERM
    double every_minutes = 10;     // wall clock
  } checkpoint;

  struct Output {
    int vtk_every = 0;  // a VTK snapshot every N sample points (0: never), docs/visualisation.md
    bool classes = true;  // classes.csv, the measures per size class (docs/physics.md 10.3)
    bool energy = false;  // series.csv's energy columns (docs/physics.md 12)
  } output;

  struct Limits {
    double max_overlap = 1.0;        // delta / min(R_i, R_j) that stops the run (BlowUpWatch)
    double max_kinetic_ratio = 1.0;  // Ekin / (p V) that stops the triaxial test as a blow-up
  } limits;

  // The phases of the run: the [[phase]] list, or [compaction] then [triaxial] (with [damping])
  // written into the case as the two phases they stand for (docs/config.md).
  Protocol protocol;
  bool phase_list = false;  // the case gives a [[phase]] list (else the default protocol's tables)

  nlohmann::json as_written;  // the TOML as read, after --set overrides
  std::string case_text;      // the same as TOML text (checkpoints keep it for resume)
};

// Every parameter, defaults included, in SI units (for summary.json).
nlohmann::json to_json(const Params& p);
nlohmann::json to_json(const Phase& phase);

// Reads a case from TOML text. `overrides` are "dotted.key=value" strings (value is TOML, or a
// bare string) applied before validation. A relative sample.from of the text is relative to
// `base_dir` (the case file's directory), one of the overrides to the working directory.
Params parse_case(const std::string& toml_text, const std::string& source,
                  const std::vector<std::string>& overrides = {}, const std::filesystem::path& base_dir = {});
Params load_case(const std::string& path, const std::vector<std::string>& overrides = {});

// Every key the parser reads, dotted, sorted ("material.density", ...; the keys of a
// [[sample.particles]] row as "sample.particles.count", of a [[phase]] as "phase.stop.steps"),
// from the parser itself: docs/config.md documents each of them (tests/test_docs.cpp).
std::vector<std::string> case_keys();

}  // namespace qsdem
