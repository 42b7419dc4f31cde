// The study file (docs/study.md): read and checked into a Study, with every case and override
// of every run; the runs of each stage; the manifest study.json.
#include "qsdem/study/study.hpp"

#include <fmt/format.h>
#include <sched.h>

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <functional>
#include <limits>
#include <optional>
#include <set>
#include <sstream>
#include <thread>
#include <utility>

#define TOML_EXCEPTIONS 1
#include <toml++/toml.h>

#include "qsdem/engine/types.hpp"
#include "qsdem/run/checkpoint.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/files.hpp"
#include "qsdem/run/toml_reader.hpp"
#include "qsdem/run/units.hpp"

namespace qsdem {
namespace {

namespace fs = std::filesystem;

// ---------------------------------------------------------------------------------------------
// The study file (docs/study.md). Errors name file:line, the key, the value and what is allowed,
// in the format of config.cpp.

class StudyReader : public TomlSource {
 public:
  explicit StudyReader(std::string file) : TomlSource(std::move(file)) {}

  // Every key of `t` must be one of `known` (a typo never passes silently).
  void only(const toml::table& t, const std::string& prefix, std::initializer_list<const char*> known) const {
    for (const auto& [k, v] : t) {
      const std::string key(k.str());
      if (std::find_if(known.begin(), known.end(), [&](const char* x) { return key == x; }) != known.end()) continue;
      std::string list;
      for (const char* x : known) list += (list.empty() ? "" : ", ") + std::string(x);
      throw InputError(fmt::format("{}: unknown key '{}{}' (allowed here: {}; see docs/study.md)", where(&v), prefix,
                                   key, list));
    }
  }

  const toml::table* table(const toml::table& t, const std::string& key, const std::string& path) const {
    const toml::node* n = t.get(key);
    if (!n) return nullptr;
    if (!n->is_table()) fail(path, n, "expected a table ([" + path + "])");
    return n->as_table();
  }

  std::string text(const toml::table& t, const std::string& key, const std::string& path,
                    std::optional<std::string> def) const {
    const toml::node* n = t.get(key);
    if (!n) {
      if (def) return *def;
      fail(path, nullptr, "is required but missing");
    }
    if (!n->is_string()) fail(path, n, "expected a string");
    return *n->value<std::string>();
  }

  long integer(const toml::table& t, const std::string& key, const std::string& path, long def, long lo,
               long hi) const {
    const toml::node* n = t.get(key);
    if (!n) return def;
    if (!n->is_integer()) fail(path, n, "expected an integer");
    const long v = static_cast<long>(*n->value<std::int64_t>());
    if (v < lo || v > hi) fail(path, n, fmt::format("out of range: must be in [{}, {}]", lo, hi));
    return v;
  }

  // A non-empty array (or, when optional and absent, nullptr).
  const toml::array* array(const toml::table& t, const std::string& key, const std::string& path,
                           bool required) const {
    const toml::node* n = t.get(key);
    if (!n) {
      if (required) fail(path, nullptr, "is required but missing");
      return nullptr;
    }
    const toml::array* a = n->as_array();
    if (!a) fail(path, n, "expected an array, e.g. " + path.substr(path.rfind('.') + 1) + " = [...]");
    if (a->empty() && required) fail(path, n, "expected at least one entry");
    return a;
  }

  // --set overrides: strings "dotted.key=value"; keys the study itself sets are refused.
  std::vector<std::string> sets(const toml::table& t, const std::string& path,
                                const std::set<std::string>& reserved) const {
    std::vector<std::string> out;
    const toml::array* a = array(t, "set", path, false);
    if (!a) return out;
    for (std::size_t i = 0; i < a->size(); ++i) {
      const toml::node* e = a->get(i);
      const std::string key = fmt::format("{}.{}", path, i);
      if (!e->is_string()) fail(key, e, "expected a string \"dotted.key=value\", e.g. \"triaxial.sample_points=100\"");
      const std::string s = *e->value<std::string>();
      const auto eq = s.find('=');
      if (eq == std::string::npos || eq == 0)
        fail(key, e, "expected \"dotted.key=value\", e.g. \"triaxial.sample_points=100\" (docs/config.md)");
      if (reserved.count(s.substr(0, eq)))
        fail(key, e, fmt::format("'{}' is set by the study itself ([design] or sample seeds); remove it here",
                                 s.substr(0, eq)));
      out.push_back(s);
    }
    return out;
  }

};

std::string fnv1a64_hex(const std::string& bytes) { return fmt::format("{:016x}", fnv1a64(bytes.data(), bytes.size())); }

std::string slurp(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  if (!in) throw InputError(fmt::format("cannot open study file '{}'", p.string()));
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

constexpr std::size_t max_sample_name = 200;  // + "-seed" + 20 digits < 255 bytes

bool valid_name(const std::string& s) {
  return !s.empty() && s[0] != '.' && s.find_first_not_of("ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz"
                                                          "0123456789._+-") == std::string::npos;
}

// Directory-name forms of a damping ratio (in %) and a strain rate: "{:g}" is deterministic.
std::string xi_label(double xi) { return fmt::format("xi-{:g}%", xi * 100); }
std::string rate_label(double rate) { return fmt::format("rate-{:g}", rate); }
// A controlled run's rate label: its start rate, the index and the target, so that it never names
// the directory of a constant-rate run.
std::string run_rate_label(double rate, const StudyControl& c) {
  if (!c.on()) return rate_label(rate);
  return fmt::format("{}-control-{}-{:g}%", rate_label(rate), c.index, c.target * 100);
}

// A value for --set that reads back as exactly this double (shortest round trip).
std::string exact(double v) { return fmt::format("{}", v); }

// A quantity: a string with its unit ("0.5 %", "100 kPa"), read by the case files' unit parser, or
// a number in SI units; `expected` says what when it is neither.
double read_quantity(const StudyReader& r, const toml::node* e, const std::string& key, Dimension dim,
                     const char* expected) {
  if (e->is_string()) {
    try {
      return parse_quantity(*e->value<std::string>(), dim);
    } catch (const InputError& err) {
      r.fail(key, e, err.what());
    }
  }
  if (!(e->is_floating_point() || e->is_integer())) r.fail(key, e, expected);
  return *e->value<double>();
}

// A damping ratio: "0.5 %" or a fraction, >= 0.
double read_ratio(const StudyReader& r, const toml::node* e, const std::string& key) {
  const double xi = read_quantity(r, e, key, Dimension::ratio, "expected a ratio: \"0.5 %\" or a fraction such as 0.005");
  if (!std::isfinite(xi) || xi < 0) r.fail(key, e, "out of range: must be >= 0");
  return xi;
}

// A dimensionless strain rate eps' = (de1/dt) t_c.
double read_rate(const StudyReader& r, const toml::node* e, const std::string& key) {
  if (!(e->is_floating_point() || e->is_integer()))
    r.fail(key, e, "expected a number (dimensionless eps' = (de1/dt) t_c), e.g. 1e-5");
  const double rate = *e->value<double>();
  if (!std::isfinite(rate) || rate <= 0 || rate >= 0.01) r.fail(key, e, "out of range: must be in (0, 0.01)");
  return rate;
}

std::vector<double> read_ratios(const StudyReader& r, const toml::array& a, const std::string& path) {
  std::vector<double> ratios;
  for (std::size_t i = 0; i < a.size(); ++i) {
    const std::string key = fmt::format("{}.{}", path, i);
    const double xi = read_ratio(r, a.get(i), key);
    for (double x : ratios)
      if (xi_label(x) == xi_label(xi))
        r.fail(key, a.get(i), fmt::format("same damping ratio as another entry ({})", xi_label(xi)));
    ratios.push_back(xi);
  }
  return ratios;
}

std::vector<double> read_rates(const StudyReader& r, const toml::array& a, const std::string& path) {
  std::vector<double> rates;
  for (std::size_t i = 0; i < a.size(); ++i) {
    const std::string key = fmt::format("{}.{}", path, i);
    const double rate = read_rate(r, a.get(i), key);
    for (double x : rates)
      if (rate_label(x) == rate_label(rate)) r.fail(key, a.get(i), "listed twice");
    rates.push_back(rate);
  }
  return rates;
}

// A name that names directories: letters, digits, '.', '_', '+', '-'.
void check_name(const StudyReader& r, const std::string& key, const toml::node* n, const std::string& name) {
  if (!valid_name(name))
    r.fail(key, n, "allowed: letters, digits, '.', '_', '+', '-'; not starting with '.' (it names directories)");
  if (name.size() > max_sample_name)
    r.fail(key, n,
           fmt::format("{} characters: at most {} (it names directories, and a file name has at most 255 bytes)",
                       name.size(), max_sample_name));
}

// The keys `qsdem study` sets on every run itself.
const std::set<std::string> run_keys{"sample.from", "damping.model", "damping.ratio", "triaxial.strain_rate",
                                     "triaxial.rate_control"};

// design.models: a model name, or { label = "...", set = [...] } (docs/study.md).
std::vector<StudyModel> read_models(const StudyReader& r, const toml::table& design) {
  std::vector<StudyModel> models;
  const toml::array* a = r.array(design, "models", "design.models", true);
  for (std::size_t i = 0; i < a->size(); ++i) {
    const toml::node* e = a->get(i);
    const std::string key = fmt::format("design.models.{}", i);
    StudyModel m;
    if (e->is_string()) {
      m.label = *e->value<std::string>();
      check_name(r, key, e, m.label);
    } else if (const toml::table* t = e->as_table()) {
      r.only(*t, key + ".", {"label", "set"});
      m.label = r.text(*t, "label", key + ".label", std::nullopt);
      check_name(r, key + ".label", t->get("label"), m.label);
      m.sets = r.sets(*t, key + ".set", {"sample.from", "damping.ratio", "triaxial.strain_rate", "triaxial.rate_control"});
      m.named = false;
    } else {
      r.fail(key, e,
             "expected a damping model's name (\"nd\") or a table { label = \"nd-t\", set = [\"damping.model=nd\", "
             "...] }");
    }
    for (const StudyModel& o : models)
      if (o.label == m.label) r.fail(key, e, "listed twice (a label names the runs' directories)");
    models.push_back(std::move(m));
  }
  return models;
}

std::vector<std::uint64_t> read_seeds(const StudyReader& r, const toml::table& design) {
  std::vector<std::uint64_t> seeds;
  const toml::array* a = r.array(design, "seeds", "design.seeds", false);
  if (!a) return seeds;
  if (a->empty()) r.fail("design.seeds", design.get("seeds"), "expected at least one seed (or leave the key out)");
  for (std::size_t i = 0; i < a->size(); ++i) {
    const toml::node* e = a->get(i);
    const std::string key = fmt::format("design.seeds.{}", i);
    if (!e->is_integer() || *e->value<std::int64_t>() < 0) r.fail(key, e, "expected an integer >= 0 (sample.seed)");
    const auto seed = static_cast<std::uint64_t>(*e->value<std::int64_t>());
    if (std::find(seeds.begin(), seeds.end(), seed) != seeds.end()) r.fail(key, e, "listed twice");
    seeds.push_back(seed);
  }
  return seeds;
}

void read_execution(const StudyReader& r, const toml::table& root, Study& s) {
  long threads = 1, parallel = 0;
  if (const toml::table* ex = r.table(root, "execution", "execution")) {
    r.only(*ex, "execution.", {"parallel_runs", "threads_per_run", "order"});
    threads = r.integer(*ex, "threads_per_run", "execution.threads_per_run", 1, 1, 1024);
    const std::string order = r.text(*ex, "order", "execution.order", std::string("longest_first"));
    if (order != "longest_first" && order != "shortest_first")
      r.fail("execution.order", ex->get("order"), "allowed values: \"longest_first\", \"shortest_first\"");
    s.shortest_first = order == "shortest_first";
    parallel = r.integer(*ex, "parallel_runs", "execution.parallel_runs", 0, 1, 4096);
  }
  s.threads_per_run = static_cast<int>(threads);
  if (parallel == 0) {  // the cores of this node, shared by the MPI ranks on it
    cpu_set_t cpus;
    const long cores = sched_getaffinity(0, sizeof cpus, &cpus) == 0 ? CPU_COUNT(&cpus)
                                                                    : long(std::thread::hardware_concurrency());
    const char* local = std::getenv("OMPI_COMM_WORLD_LOCAL_SIZE");
    const long ranks = local ? std::max(1L, std::atol(local)) : 1;
    parallel = std::max(1L, cores / (threads * ranks));
  }
  s.parallel_runs = static_cast<int>(parallel);
}

// A sample axis of [design]: a list of distinct values, each named by a directory-safe label.
struct SampleAxis {
  std::vector<double> values;  // empty: the axis is not varied
  std::vector<std::string> labels;
};

// A sample axis of [design] (`name`): each value read by `value` (which checks its range), labelled
// by `label`; two values of one label are refused.
SampleAxis read_axis(const StudyReader& r, const toml::table& design, const std::string& name,
                     const std::function<double(const toml::node*, const std::string&)>& value,
                     const std::function<std::string(double)>& label, const char* what) {
  SampleAxis axis;
  const std::string path = "design." + name;
  const toml::array* a = r.array(design, name, path, false);
  if (!a) return axis;
  if (a->empty()) r.fail(path, design.get(name), fmt::format("expected at least one {} (or leave the key out)", what));
  for (std::size_t i = 0; i < a->size(); ++i) {
    const toml::node* e = a->get(i);
    const std::string key = fmt::format("{}.{}", path, i);
    const double v = value(e, key);
    const std::string l = label(v);
    if (std::find(axis.labels.begin(), axis.labels.end(), l) != axis.labels.end())
      r.fail(key, e, fmt::format("listed twice (it names the samples '-{}')", l));
    axis.values.push_back(v);
    axis.labels.push_back(l);
  }
  return axis;
}

// design.confining_stresses: stresses ("100 kPa" or Pa), > 0; labelled "p<kPa>kPa".
SampleAxis read_confining_stresses(const StudyReader& r, const toml::table& design) {
  const auto stress = [&](const toml::node* e, const std::string& key) {
    const double v = read_quantity(r, e, key, Dimension::stress, "expected a stress: \"100 kPa\" or a number in Pa");
    if (!std::isfinite(v) || v <= 0) r.fail(key, e, "out of range: must be > 0");
    return v;
  };
  return read_axis(r, design, "confining_stresses", stress, [](double v) { return fmt::format("p{:g}kPa", v / 1e3); },
                   "stress");
}

// design.compaction_frictions: compaction.friction values, >= 0; labelled "cf<mu>".
SampleAxis read_compaction_frictions(const StudyReader& r, const toml::table& design) {
  const auto friction = [&](const toml::node* e, const std::string& key) {
    if (!(e->is_floating_point() || e->is_integer())) r.fail(key, e, "expected a number >= 0 (compaction.friction)");
    const double v = *e->value<double>();
    if (!std::isfinite(v) || v < 0) r.fail(key, e, "out of range: must be >= 0");
    return v;
  };
  return read_axis(r, design, "compaction_frictions", friction, [](double v) { return fmt::format("cf{:g}", v); },
                   "friction coefficient");
}

// The keys no override may set: the study's own (run_keys) and those of the varied sample axes.
std::set<std::string> axis_keys(const SampleAxis& stresses, const SampleAxis& frictions) {
  std::set<std::string> keys = run_keys;
  if (!stresses.values.empty()) keys.insert({"compaction.stress", "triaxial.confining_stress"});
  if (!frictions.values.empty()) keys.insert("compaction.friction");
  return keys;
}

// The keys a run of the sample sets, from its case's last phase (StudySample::model_key, ...).
void run_keys_of(const Params& base, StudySample& smp) {
  const Phase& test = base.protocol.back();
  smp.model_key = test.keys.damping_model;
  smp.ratio_key = test.keys.damping_ratio;
  smp.phase_list = base.phase_list;
  const double fastest = fastest_strain_rate(test);
  for (std::size_t c = 0; c < test.keys.strain_rates.size(); ++c)
    if (!test.keys.strain_rates[c].empty())
      smp.rate_keys.emplace_back(test.keys.strain_rates[c], test.controls.component[c].value / fastest);
  if (smp.rate_keys.empty())
    throw InputError(fmt::format("sample '{}': the last phase of its case ('{}') has no strain_rate component: a "
                                 "study varies that phase's rate",
                                 smp.name, test.name));
}

// [[sample]]: one StudySample per table, value of each sample axis and seed, each case checked
// with its overrides.
void read_samples(const StudyReader& r, const toml::table& root, const std::vector<std::uint64_t>& seeds,
                  const SampleAxis& stresses, const SampleAxis& frictions, Study& s) {
  const toml::node* sn = root.get("sample");
  if (!sn) r.fail("sample", nullptr, "is required but missing: one [[sample]] table per sample (name, case)");
  const toml::array* sample_arr = sn->as_array();
  if (!sample_arr || sample_arr->empty() || !sample_arr->is_array_of_tables())
    r.fail("sample", sn, "expected [[sample]] tables (name, case)");
  for (std::size_t i = 0; i < sample_arr->size(); ++i) {
    const toml::table& t = *sample_arr->get(i)->as_table();
    const std::string p = fmt::format("sample.{}.", i);
    r.only(t, p, {"name", "case", "set"});
    const std::string table_name = r.text(t, "name", p + "name", std::nullopt);
    check_name(r, p + "name", t.get("name"), table_name);
    const std::string case_text = r.text(t, "case", p + "case", std::nullopt);
    fs::path case_file = case_text;
    if (case_file.is_relative()) case_file = s.file.parent_path() / case_file;  // relative to the study file
    case_file = fs::weakly_canonical(fs::absolute(case_file));
    require_utf8(case_file.string(), fmt::format("{}: key '{}case': the path", r.where(t.get("case")), p));
    if (!fs::is_regular_file(case_file))
      r.fail(p + "case", t.get("case"), fmt::format("no such case file ('{}'; a relative path is relative to the study file)",
                                                    case_file.string()));
    std::set<std::string> reserved = axis_keys(stresses, frictions);
    if (!seeds.empty()) reserved.insert("sample.seed");
    const std::vector<std::string> own = r.sets(t, p + "set", reserved);
    const std::string text = slurp(case_file);  // what the children run (case_copy), hashed once

    // The sample axes' values: one pass with NaN for an axis that is not varied.
    const auto or_none = [](const std::vector<double>& v) {
      return v.empty() ? std::vector{std::numeric_limits<double>::quiet_NaN()} : v;
    };
    const std::vector<double> stress_values = or_none(stresses.values), friction_values = or_none(frictions.values);
    for (std::size_t a = 0; a < stress_values.size(); ++a)
      for (std::size_t b = 0; b < friction_values.size(); ++b) {
        std::string sample_name = table_name;
        std::vector<std::string> axis_sets;
        if (std::isfinite(stress_values[a])) {
          sample_name += "-" + stresses.labels[a];
          axis_sets.push_back(fmt::format("compaction.stress=\"{} Pa\"", exact(stress_values[a])));
          axis_sets.push_back(fmt::format("triaxial.confining_stress=\"{} Pa\"", exact(stress_values[a])));
        }
        if (std::isfinite(friction_values[b])) {
          sample_name += "-" + frictions.labels[b];
          axis_sets.push_back("compaction.friction=" + exact(friction_values[b]));
        }
        check_name(r, p + "name", t.get("name"), sample_name);
        if (std::find(s.sample_names.begin(), s.sample_names.end(), sample_name) != s.sample_names.end())
          r.fail(p + "name", t.get("name"), fmt::format("two samples have the name '{}'", sample_name));
        s.sample_names.push_back(sample_name);
        std::vector<std::string> sample_sets = own;
        sample_sets.insert(sample_sets.end(), axis_sets.begin(), axis_sets.end());

        // Check the case with the sample's overrides now, not after hours of other runs.
        const auto check = [&](const std::vector<std::string>& sets, const std::string& what) {
          try {
            return load_case(case_file.string(), sets);
          } catch (const InputError& e) {
            throw InputError(fmt::format("{}: sample '{}'{}: {}", r.file(), sample_name, what, e.what()));
          }
        };
        const Params base = check(sample_sets, "");
        const std::vector<std::uint64_t> sample_seeds = seeds.empty() ? std::vector{base.sample.seed} : seeds;
        for (const std::uint64_t seed : sample_seeds) {
          StudySample smp;
          smp.name = sample_name;
          smp.seed = seed;
          smp.dir = fmt::format("samples/{}-seed{}", sample_name, seed);
          smp.case_file = case_file;
          smp.case_text = text;
          smp.case_hash = fnv1a64_hex(text);
          smp.confining_stress = stress_values[a];
          smp.compaction_friction = friction_values[b];
          if (!seeds.empty()) smp.sets.push_back(fmt::format("sample.seed={}", seed));
          smp.sets.insert(smp.sets.end(), sample_sets.begin(), sample_sets.end());
          smp.run_sets = sample_sets;
          smp.from = check(smp.sets, fmt::format(" seed {}", seed)).sample.from;
          run_keys_of(base, smp);
          s.samples.push_back(smp);
        }
      }
  }
}

// Every model entry goes through the case parser with each sample's case: an unknown model or a
// bad override is reported with the parser's own message, at the entry's line.
void check_models(const StudyReader& r, const toml::table& design, const Study& s) {
  const toml::array* a = design.get("models")->as_array();
  for (std::size_t i = 0; i < s.models.size(); ++i)
    for (const StudySample& smp : s.samples) {
      std::vector<std::string> sets = smp.run_sets;
      if (s.models[i].named) sets.push_back(smp.model_key + "=" + s.models[i].label);
      sets.insert(sets.end(), s.models[i].sets.begin(), s.models[i].sets.end());
      try {
        load_case(smp.case_file.string(), sets);
      } catch (const InputError& e) {
        r.fail(fmt::format("design.models.{}", i), a->get(i),
               fmt::format("the case of sample '{}' refuses it: {}", smp.name, e.what()));
      }
    }
}

std::size_t index_of(const std::vector<std::string>& v, const std::string& x) {
  return static_cast<std::size_t>(std::find(v.begin(), v.end(), x) - v.begin());
}

std::vector<std::string> model_labels(const Study& s) {
  std::vector<std::string> v;
  for (const StudyModel& m : s.models) v.push_back(m.label);
  return v;
}

// An optional array of names, each one of `allowed`; absent: all of them.
std::vector<std::size_t> read_subset(const StudyReader& r, const toml::table& t, const std::string& key,
                                     const std::string& path, const std::vector<std::string>& allowed,
                                     const std::string& what) {
  std::vector<std::size_t> out;
  const toml::array* a = r.array(t, key, path, false);
  if (!a) {
    for (std::size_t k = 0; k < allowed.size(); ++k) out.push_back(k);
    return out;
  }
  if (a->empty()) r.fail(path, t.get(key), "expected at least one entry (or leave the key out: all of them)");
  std::string list;
  for (const auto& x : allowed) list += (list.empty() ? "\"" : ", \"") + x + "\"";
  for (std::size_t i = 0; i < a->size(); ++i) {
    const toml::node* e = a->get(i);
    const std::string k = fmt::format("{}.{}", path, i);
    const auto v = e->value<std::string>();
    const std::size_t at = v ? index_of(allowed, *v) : allowed.size();
    if (!e->is_string() || at == allowed.size()) r.fail(k, e, fmt::format("expected one of the {}: {}", what, list));
    if (std::find(out.begin(), out.end(), at) != out.end()) r.fail(k, e, "listed twice");
    out.push_back(at);
  }
  return out;
}

// damping_ratios = { from = "sweep", pick = "optimum", at_rate = 1e-6, digits = 2 }
void read_pick(const StudyReader& r, const toml::table& t, const std::string& path, const std::vector<StudyStage>& before,
               StudyStage& st) {
  r.only(t, path + ".", {"from", "pick", "at_rate", "digits"});
  const std::string from = r.text(t, "from", path + ".from", std::nullopt);
  std::size_t k = 0;
  while (k < before.size() && before[k].name != from) ++k;
  if (k == before.size()) {
    std::string names;
    for (const StudyStage& b : before) names += (names.empty() ? "\"" : ", \"") + b.name + "\"";
    r.fail(path + ".from", t.get("from"),
           "no stage of that name before this one: a stage picks its ratios from an earlier stage (" +
               (names.empty() ? std::string("there is none") : "earlier: " + names) + ")");
  }
  st.from = k;
  st.pick = r.text(t, "pick", path + ".pick", std::string("optimum"));
  if (st.pick != "optimum" && st.pick != "optimum+neighbours")
    r.fail(path + ".pick", t.get("pick"), "allowed values: \"optimum\", \"optimum+neighbours\"");
  st.digits = static_cast<int>(r.integer(t, "digits", path + ".digits", 2, 1, 6));
  if (const toml::node* n = t.get("at_rate")) {
    st.at_rate = read_rate(r, n, path + ".at_rate");
    const StudyStage& src = before[k];
    std::vector<double> rates = src.rates;
    for (const auto& l : src.listed) rates.push_back(l.rate);
    if (std::none_of(rates.begin(), rates.end(), [&](double x) { return rate_label(x) == rate_label(st.at_rate); }))
      r.fail(path + ".at_rate", n, fmt::format("stage '{}' has no run at this rate", src.name));
  }
  // Every (sample, model) of this stage needs an optimum from the source.
  const StudyStage& src = before[k];
  for (std::size_t smp : st.samples)
    if (std::find(src.samples.begin(), src.samples.end(), smp) == src.samples.end())
      r.fail(path + ".from", t.get("from"), fmt::format("stage '{}' does not run every sample of this stage", src.name));
  for (std::size_t m : st.models) {
    const bool has = std::find(src.models.begin(), src.models.end(), m) != src.models.end() ||
                     std::any_of(src.listed.begin(), src.listed.end(), [&](const auto& l) { return l.model == m; });
    if (!has) r.fail(path + ".from", t.get("from"), fmt::format("stage '{}' does not run every model of this stage", src.name));
  }
  st.level = before[k].level + 1;
}

// runs = [{ model = "od", ratio = "0.25 %", rate = 4e-8 }, ...]
void read_listed(const StudyReader& r, const toml::array& a, const std::string& path, const Study& s, StudyStage& st) {
  if (a.empty()) r.fail(path, nullptr, "expected at least one run");
  for (std::size_t i = 0; i < a.size(); ++i) {
    const std::string key = fmt::format("{}.{}", path, i);
    const toml::table* t = a.get(i)->as_table();
    if (!t) r.fail(key, a.get(i), "expected a table { model = \"od\", ratio = \"0.25 %\", rate = 4e-8 }");
    r.only(*t, key + ".", {"model", "ratio", "rate"});
    const std::string model = r.text(*t, "model", key + ".model", std::nullopt);
    const std::vector<std::string> labels = model_labels(s);
    const std::size_t m = index_of(labels, model);
    if (m == labels.size()) r.fail(key + ".model", t->get("model"), "not a model of design.models");
    if (!t->get("ratio")) r.fail(key + ".ratio", nullptr, "is required but missing");
    if (!t->get("rate")) r.fail(key + ".rate", nullptr, "is required but missing");
    const StudyStage::Listed l{m, read_ratio(r, t->get("ratio"), key + ".ratio"), read_rate(r, t->get("rate"), key + ".rate")};
    for (const auto& o : st.listed)
      if (o.model == l.model && xi_label(o.xi) == xi_label(l.xi) && rate_label(o.rate) == rate_label(l.rate))
        r.fail(key, a.get(i), "listed twice");
    st.listed.push_back(l);
    if (std::find(st.models.begin(), st.models.end(), m) == st.models.end()) st.models.push_back(m);
  }
}

// A TOML value written back as TOML, for an inline table on the command line; "" for a value that
// is not a string, number or boolean.
std::string toml_text(const toml::node& n) {
  if (n.is_string()) {
    std::string out = "\"";
    for (const char c : *n.value<std::string>()) {
      if (c == '"' || c == '\\') out += '\\';
      out += c;
    }
    return out + '"';
  }
  if (n.is_integer()) return fmt::format("{}", *n.value<std::int64_t>());
  if (n.is_floating_point()) {
    const double v = *n.value<double>();
    if (!std::isfinite(v)) return "";
    std::string out = fmt::format("{}", v);  // shortest round trip
    if (out.find_first_of(".e") == std::string::npos) out += ".0";
    return out;
  }
  if (n.is_boolean()) return *n.value<bool>() ? "true" : "false";
  return "";
}

// rate_control = { index = "imom", target = "0.1 %", min_rate = 1e-8, max_rate = 1e-5, ... }: the keys of
// [triaxial.rate_control] (docs/config.md), checked by the case parser with every sample's case
// and every start rate of the stage, and reported at this key.
StudyControl read_control(const StudyReader& r, const toml::node* n, const std::string& path, const Study& s,
                          const std::vector<std::size_t>& samples, const std::vector<double>& rates) {
  StudyControl c;
  if (!n) return c;
  const toml::table* t = n->as_table();
  if (!t)
    r.fail(path, n, "expected a table of [triaxial.rate_control] keys, e.g. { index = \"imom\", target = \"0.1 %\", "
                    "min_rate = 1e-8, max_rate = 1e-5 } (docs/config.md)");
  for (const auto& [k, v] : *t) {
    const std::string text = toml_text(v);
    if (text.empty())
      r.fail(path + "." + std::string(k.str()), &v, "expected a string or a number (a key of [triaxial.rate_control])");
    c.table += (c.table.empty() ? "{ " : ", ") + std::string(k.str()) + " = " + text;
  }
  c.table += c.table.empty() ? "{}" : " }";
  for (const StudySample& smp : s.samples)
    for (const double rate : rates) {
      if (std::find(samples.begin(), samples.end(), index_of(s.sample_names, smp.name)) == samples.end()) continue;
      std::vector<std::string> sets = smp.run_sets;
      sets.insert(sets.end(), s.design_sets.begin(), s.design_sets.end());
      sets.push_back("triaxial.strain_rate=" + exact(rate));
      sets.push_back("triaxial.rate_control=" + c.table);
      try {
        load_case(smp.case_file.string(), sets);
      } catch (const InputError& e) {
        r.fail(path, n, fmt::format("the case of sample '{}' refuses it at the start rate {}: {}", smp.name, exact(rate),
                                    e.what()));
      }
    }
  // Valid now (the parser accepted it): the fields that name the runs and the ETA.
  c.index = t->get("index") ? t->get("index")->value_or(std::string("imom")) : std::string("imom");
  const toml::node* target = t->get("target");
  c.target = target->is_string() ? parse_quantity(target->value_or(std::string()), Dimension::ratio)
                                 : target->value_or(0.0);
  c.min_rate = t->get("min_rate")->value_or(0.0);
  return c;
}

// The level of each stage: a stage that others pick from runs as early as its own source allows
// (level 0 without one), every other stage on the last level. The independent stages then share
// the pool with the slow picked ones, and no picked stage waits for a long independent run.
void schedule_levels(std::vector<StudyStage>& stages) {
  int last = 0;
  for (const StudyStage& st : stages) last = std::max(last, st.level);
  for (std::size_t k = 0; k < stages.size(); ++k)
    if (std::none_of(stages.begin(), stages.end(), [&](const StudyStage& s) { return !s.pick.empty() && s.from == k; }))
      stages[k].level = last;
}

// [[stage]] tables; without them, one stage made of [design]'s ratios and rates.
void read_stages(const StudyReader& r, const toml::table& root, const toml::table& design, Study& s) {
  std::vector<std::size_t> all_samples, all_models;
  for (std::size_t k = 0; k < s.sample_names.size(); ++k) all_samples.push_back(k);
  for (std::size_t k = 0; k < s.models.size(); ++k) all_models.push_back(k);
  const toml::node* sn = root.get("stage");
  if (!sn) {
    StudyStage st;
    st.name = "design";
    st.samples = all_samples;
    st.models = all_models;
    st.ratios = read_ratios(r, *r.array(design, "damping_ratios", "design.damping_ratios", true), "design.damping_ratios");
    st.rates = read_rates(r, *r.array(design, "strain_rates", "design.strain_rates", true), "design.strain_rates");
    st.control = read_control(r, design.get("rate_control"), "design.rate_control", s, st.samples, st.rates);
    s.stages.push_back(std::move(st));
    return;
  }
  s.staged = true;
  for (const char* key : {"damping_ratios", "strain_rates", "rate_control"})
    if (design.get(key))
      r.fail(std::string("design.") + key, design.get(key),
             "with [[stage]] tables, each stage gives its own damping_ratios, strain_rates and rate_control (or runs)");
  const toml::array* arr = sn->as_array();
  if (!arr || arr->empty() || !arr->is_array_of_tables())
    r.fail("stage", sn, "expected [[stage]] tables (name, damping_ratios, strain_rates)");
  const std::vector<std::string> labels = model_labels(s);
  for (std::size_t i = 0; i < arr->size(); ++i) {
    const toml::table& t = *arr->get(i)->as_table();
    const std::string p = fmt::format("stage.{}", i);
    r.only(t, p + ".", {"name", "samples", "models", "damping_ratios", "strain_rates", "runs", "rate_control"});
    StudyStage st;
    st.name = r.text(t, "name", p + ".name", std::nullopt);
    check_name(r, p + ".name", t.get("name"), st.name);
    for (const StudyStage& o : s.stages)
      if (o.name == st.name) r.fail(p + ".name", t.get("name"), "two stages have this name");
    st.samples = read_subset(r, t, "samples", p + ".samples", s.sample_names, "[[sample]] names");
    if (const toml::array* runs = r.array(t, "runs", p + ".runs", false)) {
      for (const char* key : {"models", "damping_ratios", "strain_rates"})
        if (t.get(key))
          r.fail(p + "." + key, t.get(key), "a stage gives either runs = [...] or a grid (models, damping_ratios, "
                                            "strain_rates), not both");
      read_listed(r, *runs, p + ".runs", s, st);
    } else {
      st.models = read_subset(r, t, "models", p + ".models", labels, "labels of design.models");
      st.rates = read_rates(r, *r.array(t, "strain_rates", p + ".strain_rates", true), p + ".strain_rates");
      const toml::node* dr = t.get("damping_ratios");
      if (!dr) r.fail(p + ".damping_ratios", nullptr, "is required but missing: a list, or { from = \"<stage>\", pick = \"optimum\" }");
      if (const toml::table* pick = dr->as_table()) {
        read_pick(r, *pick, p + ".damping_ratios", s.stages, st);
      } else {
        const toml::array* a = r.array(t, "damping_ratios", p + ".damping_ratios", true);
        st.ratios = read_ratios(r, *a, p + ".damping_ratios");
      }
    }
    std::vector<double> starts = st.rates;
    for (const auto& l : st.listed) starts.push_back(l.rate);
    st.control = read_control(r, t.get("rate_control"), p + ".rate_control", s, st.samples, starts);
    s.stages.push_back(std::move(st));
  }
  schedule_levels(s.stages);
}

// [analysis]: the baseline of the improvement, the quasi-static target, the reference run and the
// tolerances of the damping dependence (docs/analysis.md).
void read_analysis(const StudyReader& r, const toml::table& root, Study& s) {
  AnalysisSettings& a = s.analysis;
  const std::vector<std::string> labels = model_labels(s);
  a.baseline = labels.front();
  const toml::table* t = r.table(root, "analysis", "analysis");
  if (!t) return;
  s.has_analysis = true;
  r.only(*t, "analysis.",
         {"baseline", "imom_target", "reference", "phi_tolerance_deg", "ev_tolerance", "cn_tolerance", "convergence",
          "critical_state"});
  a.baseline = r.text(*t, "baseline", "analysis.baseline", labels.front());
  if (index_of(labels, a.baseline) == labels.size())
    r.fail("analysis.baseline", t->get("baseline"), "not a model of design.models");
  if (const toml::node* n = t->get("imom_target")) {
    a.imom_target = read_ratio(r, n, "analysis.imom_target");
    if (!(a.imom_target > 0 && a.imom_target < 1)) r.fail("analysis.imom_target", n, "out of range: must be in (0, 100 %)");
  }
  // A tolerance > 0 of `table` (whose keys' paths begin with `prefix`), a number or, with `ratio`, a ratio.
  const auto positive = [&](const toml::table& table, const char* prefix, const char* key, bool ratio, double& out) {
    const toml::node* n = table.get(key);
    if (!n) return;
    const std::string path = std::string(prefix) + key;
    if (ratio) {
      out = read_ratio(r, n, path);
    } else {
      if (!(n->is_floating_point() || n->is_integer())) r.fail(path, n, "expected a number");
      out = *n->value<double>();
    }
    if (!std::isfinite(out) || out <= 0) r.fail(path, n, "out of range: must be > 0");
  };
  positive(*t, "analysis.", "phi_tolerance_deg", false, a.phi_tolerance_deg);
  positive(*t, "analysis.", "ev_tolerance", true, a.ev_tolerance);
  positive(*t, "analysis.", "cn_tolerance", false, a.cn_tolerance);
  if (const toml::node* c = t->get("convergence")) {
    const toml::table* ct = c->as_table();
    if (!ct)
      r.fail("analysis.convergence", c,
             "expected a table { phi_tolerance_deg = ..., ev_tolerance = ..., within_seed_scatter = ..., "
             "ev_end_tolerance = ... }");
    r.only(*ct, "analysis.convergence.", {"phi_tolerance_deg", "ev_tolerance", "within_seed_scatter", "ev_end_tolerance"});
    ConvergenceTolerances& tol = a.convergence;
    positive(*ct, "analysis.convergence.", "phi_tolerance_deg", false, tol.phi_rms_deg);
    positive(*ct, "analysis.convergence.", "ev_tolerance", true, tol.ev_rms);
    if (const toml::node* n = ct->get("within_seed_scatter")) {
      if (!n->is_boolean()) r.fail("analysis.convergence.within_seed_scatter", n, "expected true or false");
      tol.within_seed_scatter = *n->value<bool>();
    }
    positive(*ct, "analysis.convergence.", "ev_end_tolerance", true, tol.ev_end);
  }
  if (const toml::node* c = t->get("critical_state")) {
    const toml::table* ct = c->as_table();
    if (!ct) r.fail("analysis.critical_state", c, "expected a table { from = \"30 %\", ev_slope = 0.05, stress_ratio_slope = 0.5 }");
    r.only(*ct, "analysis.critical_state.", {"from", "ev_slope", "stress_ratio_slope"});
    CriticalStateSettings& cs = a.critical_state;
    cs.on = true;
    if (const toml::node* n = ct->get("from")) {
      cs.from = read_ratio(r, n, "analysis.critical_state.from");
      if (!(cs.from > 0 && cs.from < 0.5)) r.fail("analysis.critical_state.from", n, "out of range: must be in (0, 50 %) of axial strain");
    }
    for (auto [key, out] : {std::pair{"ev_slope", &cs.ev_slope}, std::pair{"stress_ratio_slope", &cs.stress_ratio_slope}}) {
      const toml::node* n = ct->get(key);
      if (!n) continue;
      const std::string path = std::string("analysis.critical_state.") + key;
      if (!(n->is_floating_point() || n->is_integer())) r.fail(path, n, "expected a number");
      *out = *n->value<double>();
      if (!std::isfinite(*out) || *out <= 0) r.fail(path, n, "out of range: must be > 0");
    }
  }
  const toml::node* ref = t->get("reference");
  if (!ref) return;
  a.has_reference = true;
  if (ref->is_string()) {
    if (*ref->value<std::string>() != "least-damped")
      r.fail("analysis.reference", ref, "expected \"least-damped\" or a table { model = \"none\", ratio = ..., rate = ... }");
    return;
  }
  const toml::table* sel = ref->as_table();
  if (!sel) r.fail("analysis.reference", ref, "expected \"least-damped\" or a table { model = \"none\", ratio = ..., rate = ... }");
  r.only(*sel, "analysis.reference.", {"model", "ratio", "rate"});
  if (sel->get("model")) {
    a.reference_model = r.text(*sel, "model", "analysis.reference.model", std::nullopt);
    if (index_of(labels, a.reference_model) == labels.size())
      r.fail("analysis.reference.model", sel->get("model"), "not a model of design.models");
  }
  if (const toml::node* n = sel->get("ratio")) a.reference_ratio = read_ratio(r, n, "analysis.reference.ratio");
  if (const toml::node* n = sel->get("rate")) a.reference_rate = read_rate(r, n, "analysis.reference.rate");
}

// The run of (sample, model, xi, rate) in a stage, with the stage's controller; false when a run
// of that id exists already (a controller of the same index and target but other keys is refused).
bool add_run(Study& s, std::size_t stage, std::size_t sample, std::size_t model, double xi, double rate) {
  const StudySample& smp = s.samples[sample];
  const StudyModel& m = s.models[model];
  const StudyControl& control = s.stages[stage].control;
  StudyRun run;
  run.id = fmt::format("{}-seed{}/{}/{}/{}", smp.name, smp.seed, m.label, xi_label(xi), run_rate_label(rate, control));
  const auto same = std::find_if(s.runs.begin(), s.runs.end(), [&](const StudyRun& o) { return o.id == run.id; });
  if (same != s.runs.end()) {
    if (same->control.table != control.table)
      throw InputError(fmt::format("{}: stage '{}': the run '{}' of stage '{}' has another rate_control ({} against "
                                   "{}): a run id holds the index and target only; give the controllers other targets "
                                   "or start rates",
                                   s.file.string(), s.stages[stage].name, run.id, s.stages[same->stage].name,
                                   same->control.table, control.table));
    return false;
  }
  run.sample = sample;
  run.model = model;
  run.xi = xi;
  run.rate = rate;
  run.control = control;
  run.stage = stage;
  run.dir = "runs/" + run.id;
  run.sets = smp.run_sets;
  // A named model's damping model first (the order of the commands before labelled entries), a
  // labelled entry's overrides last: they win over design.set, but may not set the ratio or rate.
  if (m.named) run.sets.push_back(smp.model_key + "=" + m.label);
  run.sets.push_back(smp.ratio_key + "=" + exact(xi));
  for (const auto& [key, share] : smp.rate_keys) run.sets.push_back(key + "=" + exact(rate * share));
  if (control.on()) {
    if (smp.phase_list)
      throw InputError(fmt::format("{}: run '{}': rate_control drives [triaxial]'s axial rate, and sample '{}' is a "
                                   "[[phase]] case: give its last phase a controller = {{ kind = \"rate\", ... }} "
                                   "instead (docs/config.md)",
                                   s.file.string(), run.id, smp.name));
    run.sets.push_back("triaxial.rate_control=" + control.table);
  }
  for (const std::vector<std::string>* given : {&std::as_const(s.design_sets), &m.sets})
    for (const std::string& set : *given) {
      const std::string key = set.substr(0, set.find('='));
      bool own = key == smp.ratio_key || (m.named && key == smp.model_key);
      for (const auto& rk : smp.rate_keys) own = own || key == rk.first;
      if (own)
        throw InputError(fmt::format("{}: run '{}': the override '{}' sets a key the study sets on every run (the "
                                     "model, its ratio and the strain rate of the case's last phase)",
                                     s.file.string(), run.id, set));
    }
  run.sets.insert(run.sets.end(), s.design_sets.begin(), s.design_sets.end());
  if (!m.named) run.sets.insert(run.sets.end(), m.sets.begin(), m.sets.end());
  Params params;
  try {
    params = load_case(smp.case_file.string(), run.sets);
  } catch (const InputError& e) {
    throw InputError(fmt::format("{}: run '{}': {}", s.file.string(), run.id, e.what()));
  }
  run.damping_model = params.protocol.back().damping.model;
  // A controlled run's rate is unknown in advance: the ETA takes the geometric mean of its start
  // rate and its lower bound.
  const double eta_rate = control.on() ? std::sqrt(rate * control.min_rate) : fastest_strain_rate(params.protocol.back());
  run.expected_steps = planned_triaxial_steps(params, eta_rate);
  s.runs.push_back(std::move(run));
  return true;
}

}  // namespace

double planned_triaxial_steps(const Params& params, double rate) {
  // The last phase's planned strain stop, its component at `rate` times its share of the fastest.
  const Phase& test = params.protocol.back();
  for (int c = 0; c < component_count; ++c)
    if (planned_strain(test, c)) {
      const auto k = static_cast<std::size_t>(c);
      const double share = std::abs(test.controls.component[k].value) / fastest_strain_rate(test);
      return std::max(1.0, std::round(std::abs(*test.stop.strain[k]) / (params.step_ratio * rate * share)));
    }
  return std::max(1.0, static_cast<double>(test.stop.steps));  // a phase of given steps; else unknown: 1
}

namespace {

bool stage_has_sample(const StudyStage& st, const StudySample& smp, const Study& s) {
  return std::find(st.samples.begin(), st.samples.end(), index_of(s.sample_names, smp.name)) != st.samples.end();
}


// A picking stage's runs are unknown until its source has run: check now that its rates suit every
// case (e.g. triaxial.sample_points), with the source's first ratio standing in for the pick.
void check_picking_stage(Study& s, std::size_t k) {
  const StudyStage& st = s.stages[k];
  const StudyStage& src = s.stages[st.from];
  const double xi = !src.ratios.empty() ? src.ratios.front() : !src.listed.empty() ? src.listed.front().xi : 0.005;
  Study probe;
  probe.file = s.file;
  probe.samples = s.samples;
  probe.models = s.models;
  probe.design_sets = s.design_sets;
  probe.stages = s.stages;
  for (std::size_t i = 0; i < s.samples.size(); ++i) {
    if (!stage_has_sample(st, s.samples[i], s)) continue;
    for (std::size_t m : st.models)
      for (double rate : st.rates) {
        try {
          add_run(probe, k, i, m, xi, rate);
        } catch (const InputError& e) {
          throw InputError(fmt::format("stage '{}' (checked with the ratio {} % until it is picked): {}", st.name,
                                       xi * 100, e.what()));
        }
      }
  }
}

// The reference of [analysis] must be able to match a run of every sample.
void check_reference(const StudyReader& r, const toml::table& root, const Study& s) {
  const AnalysisSettings& a = s.analysis;
  if (!a.has_reference) return;
  const bool picking = std::any_of(s.stages.begin(), s.stages.end(), [](const StudyStage& st) { return !st.pick.empty(); });
  for (const std::string& name : s.sample_names) {
    const bool found = std::any_of(s.runs.begin(), s.runs.end(), [&](const StudyRun& run) {
      if (s.samples[run.sample].name != name) return false;
      if (!a.reference_model.empty() && s.models[run.model].label != a.reference_model) return false;
      if (std::isfinite(a.reference_ratio) && xi_label(run.xi) != xi_label(a.reference_ratio)) return false;
      return !std::isfinite(a.reference_rate) || rate_label(run.rate) == rate_label(a.reference_rate);
    });
    if (!found && !picking)
      r.fail("analysis.reference", root["analysis"]["reference"].node(),
             fmt::format("matches no run of sample '{}' in the design", name));
  }
}

}  // namespace

std::string file_fnv1a64(const fs::path& file) { return fnv1a64_hex(slurp(file)); }

// The runs of a stage whose ratios are known: listed, fixed, or picked (those recorded so far).
// Runs listed by an earlier stage stay there; two stages of fixed ratios listing one run are refused.
void add_stage_runs(Study& s, std::size_t k) {
  const StudyStage& st = s.stages[k];
  for (std::size_t i = 0; i < s.samples.size(); ++i) {
    if (!stage_has_sample(st, s.samples[i], s)) continue;
    const auto add = [&](std::size_t model, double xi, double rate) {
      if (!add_run(s, k, i, model, xi, rate) && st.pick.empty()) {
        const auto other = std::find_if(s.runs.begin(), s.runs.end(), [&](const StudyRun& o) {
          return o.sample == i && o.model == model && xi_label(o.xi) == xi_label(xi) &&
                 run_rate_label(o.rate, o.control) == run_rate_label(rate, st.control);
        });
        throw InputError(fmt::format("{}: stage '{}' lists the run '{}' of stage '{}' again: list each run once",
                                     s.file.string(), st.name, other->id, s.stages[other->stage].name));
      }
    };
    if (!st.listed.empty()) {
      for (const auto& l : st.listed) add(l.model, l.xi, l.rate);
      continue;
    }
    for (std::size_t m : st.models) {
      std::vector<double> ratios = st.ratios;
      if (!st.pick.empty()) {
        ratios.clear();
        for (const StudyPick& p : st.picks)
          if (p.sample == s.samples[i].name && p.model == s.models[m].label) ratios = p.ratios;
      }
      for (double xi : ratios)
        for (double rate : st.rates) add(m, xi, rate);
    }
  }
}

bool same_study_values(const std::string& a, const std::string& b) {
  try {
    return toml::parse(a) == toml::parse(b);
  } catch (const toml::parse_error&) {
    return false;
  }
}

Study load_study(const fs::path& file) { return load_study_text(slurp(file), file); }

Study load_study_text(const std::string& text, const fs::path& file) {
  Study s;
  s.file = file;
  s.text = text;
  const std::string name = file.string();
  const StudyReader r(name);
  toml::table root;
  try {
    root = toml::parse(s.text, name);
  } catch (const toml::parse_error& e) {
    throw InputError(fmt::format("{}:{}: TOML syntax error: {}", name, e.source().begin.line, e.description()));
  }
  r.only(root, "", {"name", "sample", "design", "stage", "analysis", "execution"});
  s.name = r.text(root, "name", "name", file.stem().string());
  if (s.name.empty()) r.fail("name", root.get("name"), "must not be empty");

  const toml::table* design = r.table(root, "design", "design");
  if (!design)
    r.fail("design", nullptr, "is required but missing: a [design] table with models, damping_ratios, strain_rates");
  r.only(*design, "design.", {"models", "damping_ratios", "strain_rates", "rate_control", "seeds",
                              "confining_stresses", "compaction_frictions", "set"});
  s.models = read_models(r, *design);
  const std::vector<std::uint64_t> seeds = read_seeds(r, *design);
  const SampleAxis stresses = read_confining_stresses(r, *design), frictions = read_compaction_frictions(r, *design);
  s.design_sets = r.sets(*design, "design.set", axis_keys(stresses, frictions));
  read_execution(r, root, s);
  read_samples(r, root, seeds, stresses, frictions, s);
  check_models(r, *design, s);
  read_stages(r, root, *design, s);
  read_analysis(r, root, s);
  for (std::size_t k = 0; k < s.stages.size(); ++k) {
    if (s.stages[k].pick.empty()) add_stage_runs(s, k);
    else check_picking_stage(s, k);
  }
  check_reference(r, root, s);
  return s;
}

void adopt_recorded_picks(Study& s, const nlohmann::json& manifest) {
  if (!manifest.is_object() || !manifest.contains("stages") || !manifest["stages"].is_array()) return;
  for (const auto& rec : manifest["stages"]) {
    const std::string name = rec.value("name", std::string());
    const auto st = std::find_if(s.stages.begin(), s.stages.end(), [&](const StudyStage& x) { return x.name == name; });
    if (st == s.stages.end() || st->pick.empty() || !rec.contains("picks") || !rec["picks"].is_array()) continue;
    for (const auto& p : rec["picks"]) {
      StudyPick pick;
      pick.sample = p.value("sample", std::string());
      pick.model = p.value("model", std::string());
      if (std::any_of(st->picks.begin(), st->picks.end(),
                      [&](const StudyPick& o) { return o.sample == pick.sample && o.model == pick.model; }))
        continue;  // adopted before
      pick.xi_opt = p.contains("xi_opt") && p["xi_opt"].is_number() ? p["xi_opt"].get<double>() : pick.xi_opt;
      pick.method = p.value("method", std::string());
      pick.runs_used = p.value("runs_used", 0);
      if (p.contains("ratios") && p["ratios"].is_array())
        for (const auto& x : p["ratios"])
          if (x.is_number() && x.get<double>() >= 0) pick.ratios.push_back(x.get<double>());
      if (pick.ratios.empty()) throw InputError(fmt::format("study.json: stage '{}': a recorded pick without ratios", name));
      st->picks.push_back(std::move(pick));
    }
    add_stage_runs(s, static_cast<std::size_t>(st - s.stages.begin()));
  }
}

namespace {

// The keys that two lists of overrides set otherwise, as "--set KEY was 'X' and is now 'Y'".
std::string override_change(const std::vector<std::string>& then, const std::vector<std::string>& now) {
  const auto key_of = [](const std::string& set) { return set.substr(0, set.find('=')); };
  const auto value_of = [&](const std::vector<std::string>& sets, const std::string& key) {
    std::string v = "not set";
    for (const std::string& set : sets)  // the last one wins, as on the command line
      if (key_of(set) == key) v = "'" + set.substr(std::min(set.size(), key.size() + 1)) + "'";
    return v;
  };
  std::vector<std::string> keys, changes;
  for (const auto* sets : {&then, &now})
    for (const std::string& set : *sets) {
      const std::string key = key_of(set), a = value_of(then, key), b = value_of(now, key);
      if (a == b || std::find(keys.begin(), keys.end(), key) != keys.end()) continue;
      keys.push_back(key);
      changes.push_back(fmt::format("--set {} was {} and is now {}", key, a, b));
    }
  if (changes.empty()) return "its overrides are given in another order";
  std::string out;
  for (const std::string& c : changes) out += (out.empty() ? "" : ", ") + c;
  return out;
}

// The first value where two resolved cases differ, "PATH was A and is now B"; empty: none.
std::string json_change(const nlohmann::json& a, const nlohmann::json& b, const std::string& path) {
  if (a == b) return "";
  const auto at = [&](const std::string& p) { return path.empty() ? p : path + "." + p; };
  if (a.is_object() && b.is_object()) {
    for (const auto* side : {&a, &b})
      for (const auto& item : side->items()) {
        const std::string& key = item.key();
        const std::string c = json_change(a.contains(key) ? a.at(key) : nlohmann::json(),
                                          b.contains(key) ? b.at(key) : nlohmann::json(), at(key));
        if (!c.empty()) return c;
      }
  }
  if (a.is_array() && b.is_array() && a.size() == b.size())
    for (std::size_t k = 0; k < a.size(); ++k)
      if (const std::string c = json_change(a[k], b[k], at(std::to_string(k))); !c.empty()) return c;
  return fmt::format("{} was {} and is now {}", path, a.dump(), b.dump());
}

// How the case of a sample differs with two lists of overrides: empty when both give the same
// case to the bit (summary.json's resolved_si: an override that sets the value the key had is no
// change, e.g. design.seeds = [1] for a case of seed 1); else the overrides that differ and the
// first resolved value that does.
std::string case_change(const StudySample& smp, const std::vector<std::string>& then,
                        const std::vector<std::string>& now) {
  if (then == now) return "";
  const auto resolved = [&](const std::vector<std::string>& sets) {
    nlohmann::json j = to_json(load_case(smp.case_file.string(), sets));
    j.erase("source");  // the case file's path: its bytes are compared by their hash
    return j;
  };
  const std::string c = json_change(resolved(then), resolved(now), "");
  return c.empty() ? "" : fmt::format("{} (so {})", override_change(then, now), c);
}

std::string pick_text(const Study& s, const StudyStage& st) {
  return fmt::format("'{}' of stage '{}' at {}, {} digits", st.pick, s.stages[st.from].name,
                     std::isfinite(st.at_rate) ? "rate " + exact(st.at_rate) : "every rate", st.digits);
}

}  // namespace

std::string growth_refusal(const Study& held, const Study& grown) {
  if (held.name != grown.name) return fmt::format("its name was '{}' and is now '{}'", held.name, grown.name);
  // The analysis' settings are the decision the study was designed with: growing keeps them.
  if (const std::string c = json_change(to_json(held.analysis), to_json(grown.analysis), "analysis"); !c.empty())
    return "its " + c;
  for (const StudyStage& st : held.stages) {
    if (st.pick.empty()) continue;
    const auto g = std::find_if(grown.stages.begin(), grown.stages.end(),
                                [&](const StudyStage& x) { return x.name == st.name; });
    const std::string now = g == grown.stages.end() ? "there is no such stage"
                            : g->pick.empty()       ? "it lists its ratios"
                                                    : "it picks " + pick_text(grown, *g);
    if (g == grown.stages.end() || g->pick.empty() || pick_text(held, st) != pick_text(grown, *g))
      return fmt::format("stage '{}' picked its ratios as {}, and now {}: its recorded picks would not be its own",
                         st.name, pick_text(held, st), now);
  }
  for (const StudySample& smp : held.samples) {
    const std::string id = fs::path(smp.dir).filename().string();
    const auto g = std::find_if(grown.samples.begin(), grown.samples.end(),
                                [&](const StudySample& x) { return x.dir == smp.dir; });
    if (g == grown.samples.end()) return fmt::format("the sample '{}' is not in it", id);
    if (g->case_hash != smp.case_hash)
      return fmt::format("the sample '{}' was prepared from '{}' (FNV-1a {}) and is now from '{}' ({})", id,
                         smp.case_file.string(), smp.case_hash, g->case_file.string(), g->case_hash);
    if (const std::string c = case_change(smp, smp.sets, g->sets); !c.empty())
      return fmt::format("the sample '{}' is prepared otherwise: {}", id, c);
    if (g->from != smp.from)
      return fmt::format("the sample '{}' is prepared otherwise: its sample.from was '{}' and is now '{}'", id,
                         smp.from, g->from);
  }
  for (const StudyRun& run : held.runs) {
    const auto g = std::find_if(grown.runs.begin(), grown.runs.end(), [&](const StudyRun& x) { return x.id == run.id; });
    if (g == grown.runs.end()) return fmt::format("the run '{}' is not in it", run.id);
    // A stage's runs make its optimum (the picks of later stages) and its part of the report.
    if (held.stages[run.stage].name != grown.stages[g->stage].name)
      return fmt::format("the run '{}' was of stage '{}' and is now of stage '{}'", run.id,
                         held.stages[run.stage].name, grown.stages[g->stage].name);
    if (const std::string c = case_change(held.samples[run.sample], run.sets, g->sets); !c.empty())
      return fmt::format("the run '{}' changes: {}", run.id, c);
  }
  return "";
}

namespace {
nlohmann::ordered_json control_json(const StudyControl& c) {
  return {{"index", c.index}, {"target", c.target}, {"set", "triaxial.rate_control=" + c.table}};
}
}  // namespace

nlohmann::ordered_json study_manifest(const Study& study) {
  using ojson = nlohmann::ordered_json;
  ojson m;
  m["name"] = study.name;
  m["study_file"] = "study.toml";
  // Written only for the features that need them: a design of the earlier kind keeps its
  // study.json byte for byte.
  if (study.has_analysis || study.staged) m["analysis"] = to_json(study.analysis);
  if (study.staged) {
    m["stages"] = ojson::array();
    for (const StudyStage& st : study.stages) {
      ojson j;
      j["name"] = st.name;
      j["samples"] = ojson::array();
      for (std::size_t k : st.samples) j["samples"].push_back(study.sample_names[k]);
      j["models"] = ojson::array();
      for (std::size_t k : st.models) j["models"].push_back(study.models[k].label);
      if (!st.listed.empty()) {
        j["runs"] = ojson::array();
        for (const auto& l : st.listed)
          j["runs"].push_back({{"model", study.models[l.model].label}, {"xi", l.xi}, {"rate", l.rate}});
      } else {
        j["strain_rates"] = st.rates;
        if (st.pick.empty()) j["damping_ratios"] = st.ratios;
      }
      if (st.control.on()) j["rate_control"] = control_json(st.control);
      if (!st.pick.empty()) {
        j["from"] = study.stages[st.from].name;
        j["pick"] = st.pick;
        j["at_rate"] = std::isfinite(st.at_rate) ? ojson(st.at_rate) : ojson(nullptr);
        j["digits"] = st.digits;
        j["picks"] = ojson::array();
        for (const StudyPick& p : st.picks)
          j["picks"].push_back({{"sample", p.sample},
                                {"model", p.model},
                                {"xi_opt", p.xi_opt},
                                {"method", p.method},
                                {"runs_used", p.runs_used},
                                {"ratios", p.ratios}});
      }
      m["stages"].push_back(j);
    }
  }
  m["samples"] = ojson::array();
  for (const auto& smp : study.samples) {
    ojson j = {{"name", smp.name},
               {"seed", smp.seed},
               {"dir", smp.dir},
               {"case", smp.case_file.string()},
               {"case_fnv1a64", smp.case_hash}};
    if (std::isfinite(smp.confining_stress)) j["confining_stress_Pa"] = smp.confining_stress;
    if (std::isfinite(smp.compaction_friction)) j["compaction_friction"] = smp.compaction_friction;
    m["samples"].push_back(j);
  }
  m["runs"] = ojson::array();
  for (const auto& run : study.runs) {
    const StudySample& smp = study.samples[run.sample];
    const StudyModel& model = study.models[run.model];
    ojson j = {{"id", run.id},         {"sample", smp.name}, {"seed", smp.seed}, {"model", model.label},
               {"xi", run.xi},         {"rate", run.rate},   {"dir", run.dir}};
    if (study.staged) j["stage"] = study.stages[run.stage].name;
    if (run.control.on()) j["rate_control"] = control_json(run.control);
    if (!model.named) {
      j["damping_model"] = run.damping_model;
      j["set"] = model.sets;
    }
    m["runs"].push_back(j);
  }
  return m;
}

}  // namespace qsdem
