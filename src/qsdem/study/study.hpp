// A study (SPEC 9): samples x damping models x damping ratios x strain rates (x seeds), each sample
// prepared once, runs executed in parallel processes (and over MPI ranks), resumable; optionally
// in stages, a later stage taking its damping ratios from an earlier stage's optimum. The study
// file and the layout of the study directory are documented in docs/study.md.
#pragma once
#include <cstdint>
#include <filesystem>
#include <functional>
#include <optional>
#include <limits>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "qsdem/study/study_analysis.hpp"

namespace qsdem {

struct Params;

// One prepared sample: a case (with its overrides) and a seed, compacted once by `qsdem prepare`.
struct StudySample {
  std::string name;                   // the [[sample]] name
  std::uint64_t seed = 1;             // sample.seed it is prepared with
  std::string dir;                    // relative to the study directory: samples/<name>-seed<S>
  std::filesystem::path case_file;    // absolute
  std::string case_text;              // its bytes as read when the study was loaded
  std::string case_hash;              // FNV-1a 64 of case_text, 16 hex digits
  std::string from;                   // sample.from as the case resolves it (absolute), or empty
  std::vector<std::string> sets;      // --set overrides of `qsdem prepare` (seed first)
  std::vector<std::string> run_sets;  // the sample's own overrides, also given to its runs
  // The sample axes of [design] (NaN: not varied): design.confining_stresses sets compaction.stress
  // and triaxial.confining_stress, design.compaction_frictions compaction.friction (the density).
  double confining_stress = std::numeric_limits<double>::quiet_NaN();     // Pa
  double compaction_friction = std::numeric_limits<double>::quiet_NaN();
  // What a run sets, by the keys of the case's last phase as the case writes them (PhaseKeys):
  // its damping model and ratio, and each strain-rate component's rate, the run's rate times the
  // component's share of the phase's fastest (the path's proportions kept).
  std::string model_key, ratio_key;
  std::vector<std::pair<std::string, double>> rate_keys;  // key, share
  bool phase_list = false;                                // a [[phase]] case
};

// One entry of the model axis: a damping model's name ("nd"), or a label with case overrides
// ({ label = "nd-t", set = ["damping.model=nd", "damping.acts_on=translation"] }).
struct StudyModel {
  std::string label;              // names the runs' directories and the analysis' groups
  std::vector<std::string> sets;  // the entry's overrides (a name: none; the model key is set from it)
  bool named = true;              // given as a bare model name
};

// The rate controller of a stage's runs ([triaxial.rate_control] of docs/config.md): each run
// starts at its strain rate and the controller drives eps' to hold the index at the target.
struct StudyControl {
  std::string table;   // the override's value, an inline TOML table; empty: constant rate
  std::string index;   // "imom", "ufr" or "iuf"
  double target = std::numeric_limits<double>::quiet_NaN();    // fraction
  double min_rate = std::numeric_limits<double>::quiet_NaN();  // the controller's lower bound
  bool on() const { return !table.empty(); }
};

// One triaxial test of a prepared sample.
struct StudyRun {
  // <sample>-seed<S>/<model>/xi-<xi %>/rate-<rate>[-control-<index>-<target %>%], also its directory
  // under runs/
  std::string id;
  std::size_t sample = 0;  // index into Study::samples
  std::size_t model = 0;   // index into Study::models
  double xi = 0;           // damping ratio, as a fraction
  double rate = 0;         // dimensionless strain rate eps' (a controlled run's start rate)
  StudyControl control;    // the stage's rate controller
  std::size_t stage = 0;   // index into Study::stages: the first stage that lists it
  std::string dir;         // relative to the study directory: runs/<id>
  std::vector<std::string> sets;  // --set overrides of `qsdem run`, except sample.from
  std::string damping_model;      // the case's damping.model with these overrides
  double expected_steps = 0;      // triaxial steps, final_axial_strain / (c_t eps') (for the ETA)
};

// The damping ratios of one (sample, model) that a stage picked from its source's optimum.
struct StudyPick {
  std::string sample, model;   // sample name and model label
  double xi_opt = std::numeric_limits<double>::quiet_NaN();
  std::string method;          // how xi_opt was obtained (StageOptimum::method)
  int runs_used = 0;
  std::vector<double> ratios;  // what the stage runs
};

// A stage of the design: a grid of samples x models x ratios x rates, or a list of runs. Without
// [[stage]] tables the design is one stage. Stages of one level run together; a stage that picks
// its ratios from another is one level after it, and a stage nothing picks from is on the last.
struct StudyStage {
  std::string name;
  std::vector<std::size_t> samples;  // indices of the [[sample]] tables (names)
  std::vector<std::size_t> models;   // indices into Study::models
  std::vector<double> rates;         // with `control`: the start rates
  StudyControl control;              // rate_control = { ... }: one controlled run per combination
  std::vector<double> ratios;        // fixed ratios (empty when picked or listed)
  struct Listed {
    std::size_t model;
    double xi, rate;
  };
  std::vector<Listed> listed;        // a list of runs instead of a grid
  std::size_t from = 0;              // with `pick`: the stage the ratios are picked from
  std::string pick;                  // "" | "optimum" | "optimum+neighbours"
  double at_rate = std::numeric_limits<double>::quiet_NaN();  // optimum at this rate of `from`
  int digits = 2;                    // significant digits of the picked optimum
  int level = 0;
  std::vector<StudyPick> picks;      // recorded picks (study.json)
};

struct Study {
  std::string name;
  std::filesystem::path file;  // the study file as given
  std::string text;            // its contents (copied to DIR/study.toml)
  // The [[sample]] tables in file order, each expanded over the sample axes of [design]
  // (confining stress, compaction friction): "A-p100kPa-cf0" is sample A at 100 kPa, friction 0.
  std::vector<std::string> sample_names;
  std::vector<StudySample> samples;       // one per [[sample]] and seed
  std::vector<StudyModel> models;
  std::vector<StudyStage> stages;
  bool staged = false;                    // [[stage]] tables (else one stage from [design])
  bool has_analysis = false;              // an [analysis] table
  AnalysisSettings analysis;
  std::vector<std::string> design_sets;   // design.set: overrides of every run
  std::vector<StudyRun> runs;             // those known so far (a picking stage adds its own)
  int parallel_runs = 1;    // processes at once (per MPI rank)
  int threads_per_run = 1;  // --threads of every child
  // Runs of a level in order of their expected steps: longest first (the pool ends with short
  // runs: the shortest makespan) or shortest first (the most runs finished soonest).
  bool shortest_first = false;
};

// Reads and checks a study file, and every case it names with every override of every run.
// Throws InputError naming the file, line, key, value and what is allowed.
Study load_study(const std::filesystem::path& file);

// The same, from the text of a study file read as if it were `file` (its relative case paths and
// its default name are `file`'s): the design a study directory's study.toml holds.
Study load_study_text(const std::string& text, const std::filesystem::path& file);

// Why `grown` does not only add runs to `held` (the design a study directory holds, both with
// their recorded picks): a run or sample of `held` that `grown` lacks or defines otherwise (its
// case, its overrides, its stage), another name, analysis or picking rule. Empty when it grows.
std::string growth_refusal(const Study& held, const Study& grown);

// Two study files with the same tables and values (comments and layout aside): a study directory
// made with one continues with the other.
bool same_study_values(const std::string& a, const std::string& b);

// Adds the runs of stage `stage` whose ratios are known (given, listed, or picked so far) and that
// the study does not hold yet. Throws InputError when two stages of given ratios list one run.
void add_stage_runs(Study& study, std::size_t stage);

// The steps of the case's last phase at rate `rate` (fastest_strain_rate, the components'
// proportions kept): its planned strain stop / (c_t eps' share), at least 1 (the ETA's and
// `qsdem converge`'s step budget).
double planned_triaxial_steps(const Params& params, double rate);

// FNV-1a 64 of a file's bytes, 16 hex digits (the hashes of study.json).
std::string file_fnv1a64(const std::filesystem::path& file);

// Adds the picks recorded in a manifest (study.json) that the study does not hold yet, and their
// runs: a continued study uses the ratios its stages picked before. Throws InputError when a
// recorded pick has no ratios.
void adopt_recorded_picks(Study& study, const nlohmann::json& manifest);

// The triaxial steps a run still has to do: `expected` less the step of the last row of its
// series.csv.partial when it holds a checkpoint (it resumes from there), else `expected` (it
// starts afresh). Orders the pool and feeds the ETA.
double steps_left(const std::filesystem::path& run_dir, double expected);

// The manifest DIR/study.json (the contract with the analysis, docs/study.md); keys in the
// documented order.
nlohmann::ordered_json study_manifest(const Study& study);

struct StudyOptions {
  std::filesystem::path out;
  bool quiet = false;
  int parallel = 0;  // > 0: overrides execution.parallel_runs
  std::string order;  // "longest_first" or "shortest_first": overrides execution.order
  std::vector<std::string> stages;  // non-empty: only the runs of these stages run (samples all do)
  std::string again;  // the command that continues it, for the message on SIGINT/SIGTERM
  // The qsdem program the child processes run; empty: this program (/proc/self/exe). The Python
  // module, whose process is the interpreter, names the CLI.
  std::string executable;
};

// Runs (or continues) the study described by `study_file` in options.out, then analyses it.
// Returns the process exit code: 0, 2 (bad input), 3 (failed runs or analysis), 128 + signal.
int run_study(const std::filesystem::path& study_file, const StudyOptions& options);

// The same in rounds, under one MPI start: round k runs (or continues) the stages `next(k)` names
// (an empty list: every stage) and analyses the directory; no list, or a round that does not
// return 0, ends it. Every rank calls `next` after the analysis of the round before, so it decides
// from the files alone. Returns the last round's code.
int run_study_rounds(const std::filesystem::path& study_file, const StudyOptions& options,
                     const std::function<std::optional<std::vector<std::string>>(int round)>& next);

}  // namespace qsdem
