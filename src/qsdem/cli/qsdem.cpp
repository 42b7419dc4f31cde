// qsdem command line: run a case, prepare a sample, resume, plot, study, analyse, benchmark.
#include <CLI/CLI.hpp>
#include <fmt/format.h>
#include <omp.h>

#include <algorithm>
#include <charconv>
#include <cstring>
#include <iterator>
#include <cstdio>
#include <filesystem>
#include <iostream>

#include "qsdem/default_case.hpp"
#include "qsdem/run/bench.hpp"
#include "qsdem/run/config.hpp"
#include "qsdem/run/figures.hpp"
#include "qsdem/run/files.hpp"
#include "qsdem/run/grading.hpp"
#include "qsdem/run/plot.hpp"
#include "qsdem/run/run.hpp"
#include "qsdem/run/summary.hpp"
#include "qsdem/study/converge.hpp"
#include "qsdem/study/study.hpp"
#include "qsdem/study/study_analysis.hpp"
#include "qsdem/version.hpp"

namespace {

// exit codes: 0 ok, 1 usage, 2 bad input, 3 run failed (blow-up, no equilibrium, I/O),
// 128 + signal when stopped by SIGINT/SIGTERM after a checkpoint
int report(const char* kind, const std::exception& e, int code) {
  std::fprintf(stderr, "qsdem: %s: %s\n", kind, e.what());
  return code;
}

void set_threads(int threads) {
  if (threads > 0) omp_set_num_threads(threads);
}

// A whole number >= lo, refused with a message that says so (CLI11's PositiveNumber and
// NonNegativeNumber print their range up to 1.8e308).
CLI::Validator whole_number_at_least(long lo, const std::string& meaning = "") {
  return CLI::Validator(
      [lo, meaning](std::string& text) -> std::string {
        long value = 0;
        const char* const end = text.data() + text.size();
        const auto [stop, ec] = std::from_chars(text.data(), end, value);
        if (ec == std::errc() && stop == end && value >= lo) return {};
        return fmt::format("'{}' is not allowed: give a whole number >= {}{}", text, lo, meaning);
      },
      fmt::format("INT>={}", lo));
}

// Threads of --threads: 0 (all cores) to max_threads. More only exhausts the address space
// (each OpenMP thread reserves a stack) and crashed inside the OpenMP runtime.
constexpr long max_threads = 256;

CLI::Validator thread_count() {
  return CLI::Validator(
      [](std::string& text) -> std::string {
        long value = 0;
        const char* const end = text.data() + text.size();
        const auto [stop, ec] = std::from_chars(text.data(), end, value);
        if (ec == std::errc() && stop == end && value >= 0 && value <= max_threads) return {};
        return fmt::format("'{}' is not allowed: give a whole number from 0 (all cores) to {}", text, max_threads);
      },
      fmt::format("INT in [0, {}]", max_threads));
}

constexpr const char* subcommands[] = {"run", "prepare", "resume", "plot", "bench", "study", "analyze", "converge"};

// The page of a run that has just ended (`qsdem plot DIR`), when gnuplot is there: a run never
// fails for want of its figures, it says how to draw them later.
void draw_page(const std::string& dir, bool no_plot) {
  const std::string later = fmt::format("qsdem plot {}", dir);
  if (no_plot) {
    std::cout << "Figures: " << later << "\n";
    return;
  }
  if (!qsdem::gnuplot_available()) {
    std::cout << "Figures: not drawn (gnuplot is not installed: apt-get install gnuplot-nox); then " << later << "\n";
    return;
  }
  try {
    const qsdem::PlotResult r = qsdem::plot_run(dir);
    std::cout << "Figures in " << r.page.string() << "\n";
  } catch (const std::exception& e) {
    std::fprintf(stderr, "qsdem: the figures were not drawn: %s\n", e.what());
    std::cout << "Figures: not drawn; " << later << " tries again\n";
  }
}

// What the command line gave: one field per option, shared by the subcommands that take it.
struct CommandLine {
  bool dry_run = false;
  std::string case_path, out_dir;
  std::vector<std::string> overrides;
  int threads = 0;
  bool quiet = false, force = false, no_plot = false;
  std::string resume_dir, plot_dir, plot_out;
  std::string bench_source;
  long steps = 1000;
  bool as_spheres = false;
  std::string prefetch = "auto";
  std::string study_file;
  int parallel = 0;
  std::string order;
  std::string analyze_dir;
  qsdem::LadderOptions ladder;
  std::string ladder_case;
  bool no_scatter = false;
  CLI::App *run = nullptr, *prepare = nullptr, *resume = nullptr, *plot = nullptr, *bench = nullptr,
           *study = nullptr, *analyze = nullptr, *converge = nullptr;
};

// `run` and `prepare`: a case, run or compacted only.
void add_run(CLI::App& app, CommandLine& c, const CLI::Validator& cores) {
  c.run = app.add_subcommand(
      "run",
      "Generate a loose sample, compact it isotropically and shear it in drained triaxial compression "
      "(SPEC 8). Writes DIR/series.csv (one row per sample point), DIR/summary.json, DIR/compaction.csv and "
      "the compacted and final packings, then prints a summary table and the time spent per stage.");
  c.run->add_option("case", c.case_path,
                    "Case file (TOML, see docs/config.md). Without it, the built-in default case "
                    "examples/spheres-A-small.toml is run.");
  c.run->add_option("--out,-o", c.out_dir, "Directory for the results (created if needed)")->default_val("runs/default");
  c.run->add_option("--set,-s", c.overrides,
                    "Override a case key, e.g. --set damping.ratio=\"0.3 %\" --set triaxial.strain_rate=1e-6 "
                    "--set sample.total_particles=2000 --set damping.model=od (repeatable)");
  c.run->add_option("--threads,-t", c.threads, "OpenMP threads (default: all cores)")->check(cores);
  c.run->add_flag("--quiet,-q", c.quiet, "No progress line");
  c.run->add_flag("--force,-f", c.force, "Overwrite a directory that holds a finished or unfinished run");
  c.run->add_flag("--no-plot", c.no_plot,
                  "Do not draw the run's figures at its end (they are drawn into DIR/plot/ when gnuplot is installed; "
                  "`qsdem plot DIR` draws them later)");

  c.prepare = app.add_subcommand(
      "prepare",
      "Generate and compact a sample only (SPEC 8): writes DIR/compacted.packing, DIR/compaction.csv and "
      "DIR/summary.json. The packing can be benchmarked with `qsdem bench`.");
  c.prepare->add_option("case", c.case_path, "Case file (TOML). Without it, the built-in default case.");
  c.prepare->add_option("--out,-o", c.out_dir, "Directory for the results (created if needed)")->default_val("runs/prepared");
  c.prepare->add_option("--set,-s", c.overrides, "Override a case key (as for run)");
  c.prepare->add_option("--threads,-t", c.threads, "OpenMP threads (default: all cores)")->check(cores);
  c.prepare->add_flag("--quiet,-q", c.quiet, "No progress line");
  c.prepare->add_flag("--force,-f", c.force, "Overwrite a directory that holds a finished or unfinished run");
}

// `resume` and `plot`: a run directory continued, or drawn.
void add_resume(CLI::App& app, CommandLine& c, const CLI::Validator& cores) {
  c.resume = app.add_subcommand(
      "resume",
      "Continue an interrupted run (killed, stopped by SIGINT/SIGTERM, crashed) from the newest good checkpoint "
      "in its directory (DIR/checkpoint.qsck, or DIR/checkpoint.qsck.prev when the newest is damaged). The "
      "resumed series.csv is identical to that of an uninterrupted run.");
  c.resume->add_option("dir", c.resume_dir, "Directory of the run")->required();
  c.resume->add_option("--set,-s", c.overrides,
                       "Change a case key that does not invalidate the state (limits.max_overlap, "
                       "limits.max_kinetic_ratio, checkpoint.every_sample_points, checkpoint.every_minutes, "
                       "output.vtk_every, compaction.max_steps; time.step_ratio during compaction); recorded in "
                       "summary.json (repeatable)");
  c.resume->add_option("--threads,-t", c.threads, "OpenMP threads (default: all cores)")->check(cores);
  c.resume->add_flag("--quiet,-q", c.quiet, "No progress line");
  c.resume->add_flag("--no-plot", c.no_plot, "Do not draw the run's figures at its end (as for run)");

  c.plot = app.add_subcommand(
      "plot",
      "Draw the figures of a run directory (docs/runs.md): for each series file, q/p, phi, ev and the void ratio "
      "against e1, the stress path in p-q, the equilibrium indices UFR, Iuf, IMom and Cn, the fabric columns, the "
      "loops of a cyclic phase, and the size classes of classes.csv; PNG and SVG with their data and gnuplot "
      "scripts, and one page, DIR/plot/index.html. Needs gnuplot.");
  c.plot->add_option("dir", c.plot_dir, "Directory of the run (its series.csv, compaction.csv, summary.json)")->required();
  c.plot->add_option("--out,-o", c.plot_out, "Directory for the figures and the page (default: DIR/plot)");
}

// `bench`: the stepping of a packing or a checkpoint, timed.
void add_bench(CLI::App& app, CommandLine& c, const CLI::Validator& cores) {
  c.bench = app.add_subcommand(
      "bench",
      "Step a state in a fixed cell with no output and print one JSON line (docs/benchmarks.md): particles, "
      "contacts at the first and the last step, steps, threads, wall seconds, particle-steps per second, memory, "
      "time per stage. The state is a packing (at rest, no contact history; the triaxial friction and damping of "
      "--case), or a checkpoint: DIR/sample.qsck of `qsdem prepare`, DIR/checkpoint.qsck of an unfinished run "
      "(velocities and contact history as the run left them; the friction and damping of its phase).");
  c.bench->add_option("source", c.bench_source,
                      "A packing file, a checkpoint file (*.qsck), or a run directory (its sample.qsck, else its "
                      "checkpoint.qsck)")
        ->required();
  c.bench->add_option("--case,-c", c.case_path,
                      "Case file: material, friction, damping and time step. Required for a packing; for a checkpoint "
                      "it replaces the checkpoint's own case (material and time.step_ratio must be equal)");
  c.bench->add_option("--steps,-n", c.steps, "Steps to time (default 1000)")->check(whole_number_at_least(1));
  c.bench->add_option("--set,-s", c.overrides, "Override a case key (as for run)");
  c.bench->add_option("--threads,-t", c.threads, "OpenMP threads (default: all cores)")->check(cores);
  c.bench->add_flag("--as-spheres", c.as_spheres,
                    "Replace every ellipsoid by its equal-volume sphere at the same centre first, at rest and without "
                    "contact history (the sphere path on the same packing)");
  c.bench->add_option("--prefetch", c.prefetch,
                      "Whether the pair loops fetch the j ends' data ahead: auto (when the particles' arrays take "
                      "more than half the last-level cache), on or off; the results are the same bits")
      ->check(CLI::IsMember({"auto", "on", "off"}));
}

// `study`, `analyze` and `converge`: studies, their analysis, and a case's certificate.
void add_study(CLI::App& app, CommandLine& c) {
  c.study = app.add_subcommand(
      "study",
      "Run a study (SPEC 9, docs/study.md): every sample of the study file prepared once, then sheared with every "
      "damping model, damping ratio and strain rate of its [design] (or of its [[stage]] tables, in order), in "
      "parallel processes (and over the ranks of "
      "`mpirun -np K`). Writes DIR/study.json, DIR/samples/, DIR/runs/, then the analysis (DIR/analysis/). Running it "
      "again on the same DIR continues it: finished runs are kept, interrupted ones resume from their checkpoints.");
  c.study->add_option("study", c.study_file, "Study file (TOML, see docs/study.md)")->required();
  c.study->add_option("--out,-o", c.out_dir, "Study directory (created if needed)")->required();
  c.study->add_option("--parallel,-j", c.parallel,
                      "Child processes at once (per MPI rank); default: execution.parallel_runs of the study file")
        ->check(whole_number_at_least(1));
  c.study->add_option("--order", c.order,
                      "Runs of a stage longest_first (the shortest total time) or shortest_first (the most runs "
                      "finished soonest); default: execution.order of the study file")
        ->check(CLI::IsMember({"longest_first", "shortest_first"}));
  c.study->add_flag("--quiet,-q", c.quiet, "No progress display");

  c.analyze = app.add_subcommand(
      "analyze", "Analyse a study directory (written by `qsdem study`) again: DIR/analysis/ (docs/analysis.md).");
  c.analyze->add_option("dir", c.analyze_dir, "Study directory")->required();

  c.converge = app.add_subcommand(
      "converge",
      "Certify a case's quasi-static response (docs/analysis.md, section 11): the case prepared with several seeds "
      "and sheared at a ladder of falling strain rates, as a study in DIR, rung by rung until the response stops "
      "changing with the rate (converged), the ladder ends or the step budget would be passed (not converged). "
      "Writes DIR/certificate.json and the study's report; exit code 0 when converged, 4 when not. Running it "
      "again on the same DIR continues it.");
  c.converge->add_option("case", c.ladder_case, "Case file (TOML). Without it, the built-in default case.");
  c.converge->add_option("--out,-o", c.out_dir, "Directory of the ladder (created if needed)")->required();
  c.converge->add_option("--set,-s", c.overrides, "Override a case key (as for run)");
  c.converge->add_option("--seeds", c.ladder.seeds, "Samples, prepared with sample.seed = 1 .. N")->default_val(3);
  c.converge->add_option("--start-rate", c.ladder.start_rate, "The first rung's eps' (default: the case's triaxial.strain_rate)");
  c.converge->add_option("--factor", c.ladder.factor, "eps' of a rung over eps' of the next")->default_val(3.16227766016838);
  c.converge->add_option("--rungs", c.ladder.rungs, "Rungs at most")->default_val(4);
  c.converge->add_option("--max-steps", c.ladder.max_steps,
                         "Step budget: triaxial steps of every run together; a rung that would pass it is not run");
  c.converge->add_option("--phi-tolerance", c.ladder.tolerances.phi_rms_deg, "RMS change of phi(e1), degrees")
        ->default_val(0.5);
  c.converge->add_option("--ev-tolerance", c.ladder.tolerances.ev_rms, "RMS change of ev(e1), a ratio")->default_val(0.001);
  c.converge->add_option("--ev-end-tolerance", c.ladder.tolerances.ev_end,
                         "Change of ev at the end (the last strain every curve reaches), a ratio (default: not judged)");
  c.converge->add_flag("--no-seed-scatter", c.no_scatter, "A rung's change need not be below the seed scatter");
  c.converge->add_option("--parallel,-j", c.parallel, "Child processes at once (default: cores / MPI ranks on the node)")
        ->check(whole_number_at_least(1));
  c.converge->add_flag("--quiet,-q", c.quiet, "No progress display");
}

// --dry-run: the command line and the file it names checked, nothing run.
int check_only(CommandLine& c) {
  namespace fs = std::filesystem;
  std::string checked;
  if (*c.run || *c.prepare || *c.study) qsdem::require_utf8(c.out_dir, "--out");
  if ((*c.run || *c.prepare) && c.case_path.empty()) {
    qsdem::parse_case(qsdem::default_case_toml, qsdem::default_case_name, c.overrides);
    checked = "the built-in case";
  } else if ((*c.run || *c.prepare || *c.bench) && fs::is_regular_file(c.case_path)) {
    qsdem::load_case(c.case_path, c.overrides);
    checked = "case " + c.case_path;
  } else if (*c.converge) {
    c.ladder.case_file = c.ladder_case, c.ladder.sets = c.overrides, c.ladder.tolerances.within_seed_scatter = !c.no_scatter;
    qsdem::ladder_study_text(c.ladder);
    checked = c.ladder_case.empty() ? "the ladder of the built-in case" : "the ladder of case " + c.ladder_case;
  } else if (*c.study && fs::is_regular_file(c.study_file)) {
    qsdem::load_study(c.study_file);
    checked = "study " + c.study_file;
  }
  std::cout << "qsdem: dry run: the command line is valid"
            << (checked.empty() ? std::string() : "; " + checked + " is valid") << "\n";
  return 0;
}

// The subcommand given; its exit code.
int execute(CommandLine& c) {
  if (*c.run || *c.prepare) {
    const qsdem::Params params =
        c.case_path.empty() ? qsdem::parse_case(qsdem::default_case_toml, qsdem::default_case_name, c.overrides)
                          : qsdem::load_case(c.case_path, c.overrides);
    if (!c.quiet)
      std::fprintf(stderr, "qsdem %s: case %s -> %s (%d threads)\n", QSDEM_VERSION, params.source.c_str(),
                   c.out_dir.c_str(), omp_get_max_threads());
    if (!c.quiet && params.sample.from.empty() && !params.sample.grading.empty())
      std::fprintf(stderr, "qsdem: %s\n",
                   qsdem::describe_grading(params.sample.grading, params.sample.total_particles, params.sample.seed).c_str());
    const auto summary = qsdem::run_case(params, {c.out_dir, c.quiet, bool(*c.prepare), c.force});
    std::cout << "\n" << qsdem::format_run_table(summary) << "\nTime per stage:\n"
              << summary["stage_table"].get<std::string>() << "\nResults in " << c.out_dir
              << (*c.prepare ? "/ (compacted.packing, summary.json)\n" : "/ (series.csv, summary.json)\n");
    if (!*c.prepare) draw_page(c.out_dir, c.no_plot);
  } else if (*c.resume) {
    qsdem::RunOptions options;
    options.out = c.resume_dir;
    options.quiet = c.quiet;
    options.sets = c.overrides;
    const auto summary = qsdem::resume_run(c.resume_dir, options);
    std::cout << "\n" << qsdem::format_run_table(summary) << "\nTime per stage:\n"
              << summary["stage_table"].get<std::string>() << "\nResults in " << c.resume_dir << "/\n";
    // A resumed `qsdem prepare` (steps_cover: its compaction, physics.md 10.2) has no test to draw.
    const std::string cover = summary.value("steps_cover", "");
    if (cover != "compaction" && cover != "the first phase") draw_page(c.resume_dir, c.no_plot);
  } else if (*c.plot) {
    const qsdem::PlotResult r = qsdem::plot_run(c.plot_dir, c.plot_out);
    for (const std::string& n : r.notes) std::cout << "not drawn: " << n << "\n";
    std::cout << r.page.parent_path().string() << ": " << r.figures.size() << " figures; open " << r.page.string()
              << "\n";
  } else if (*c.study) {
    qsdem::StudyOptions options;
    options.out = c.out_dir, options.quiet = c.quiet, options.parallel = c.parallel, options.order = c.order;
    return qsdem::run_study(c.study_file, options);
  } else if (*c.converge) {
    c.ladder.case_file = c.ladder_case, c.ladder.sets = c.overrides, c.ladder.out = c.out_dir, c.ladder.parallel = c.parallel;
    c.ladder.quiet = c.quiet, c.ladder.tolerances.within_seed_scatter = !c.no_scatter;
    return qsdem::run_ladder(c.ladder);
  } else if (*c.analyze) {
    qsdem::analyze_study(c.analyze_dir);
    std::cout << "Analysis written to " << c.analyze_dir << "/analysis/\n";
  } else if (*c.bench) {
    std::cout << qsdem::json_text(qsdem::bench_packing(c.bench_source, c.case_path, c.overrides, c.steps, c.as_spheres,
                                                                   c.prefetch == "auto" ? std::nullopt
                                                                                        : std::optional<bool>(c.prefetch == "on")), -1) << std::endl;
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  // CLI11 answers an unknown subcommand with "A subcommand is required": name it instead.
  if (argc > 1 && argv[1][0] != '-' &&
      std::none_of(std::begin(subcommands), std::end(subcommands), [&](const char* c) { return std::strcmp(c, argv[1]) == 0; })) {
    std::fprintf(stderr, "qsdem: unknown subcommand '%s' (allowed: run, prepare, resume, plot, bench, study, analyze, converge; see "
                         "qsdem --help)\n", argv[1]);
    return 1;
  }

  CLI::App app{
      "qsdem: quasi-static DEM of spheres and ellipsoids in a deformable periodic cell.\n"
      "Drained triaxial tests with size-dependent (nd) or global mass (od) damping, and the equilibrium\n"
      "indices UFR, Iuf and IMom of Yousefi (2018). Cases are TOML files (docs/config.md)."};
  app.require_subcommand(1);
  app.set_version_flag("--version", QSDEM_VERSION);
  CommandLine c;
  app.add_flag("--dry-run", c.dry_run,
               "Check the command line, and the case or study file it names when that file exists (with its --set "
               "overrides), then exit without running anything (exit code 0, 1 or 2)");
  app.fallthrough();  // --dry-run may follow the subcommand

  const CLI::Validator cores = thread_count();
  add_run(app, c, cores);
  add_resume(app, c, cores);
  add_bench(app, c, cores);
  add_study(app, c);

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? 0 : 1;  // --help and --version exit 0; a bad command line 1 (CLI11's codes vary)
  }

  try {
    set_threads(c.threads);
    return c.dry_run ? check_only(c) : execute(c);
  } catch (const qsdem::Interrupted& e) {
    std::fprintf(stderr, "\nqsdem: %s\n", e.what());
    return 128 + e.signal;
  } catch (const qsdem::InputError& e) {
    return report("input error", e, 2);
  } catch (const qsdem::RunError& e) {
    return report("run stopped", e, 3);
  } catch (const std::exception& e) {
    return report("error", e, 3);
  }
}
