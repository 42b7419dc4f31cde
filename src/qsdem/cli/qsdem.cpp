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
  bool dry_run = false;
  app.add_flag("--dry-run", dry_run,
               "Check the command line, and the case or study file it names when that file exists (with its --set "
               "overrides), then exit without running anything (exit code 0, 1 or 2)");
  app.fallthrough();  // --dry-run may follow the subcommand

  const CLI::Validator all_cores_or_count = thread_count();
  std::string case_path;
  std::string out_dir;
  std::vector<std::string> overrides;
  int threads = 0;
  bool quiet = false;
  auto* run = app.add_subcommand(
      "run",
      "Generate a loose sample, compact it isotropically and shear it in drained triaxial compression "
      "(SPEC 8). Writes DIR/series.csv (one row per sample point), DIR/summary.json, DIR/compaction.csv and "
      "the compacted and final packings, then prints a summary table and the time spent per stage.");
  run->add_option("case", case_path,
                  "Case file (TOML, see docs/config.md). Without it, the built-in default case "
                  "examples/spheres-A-small.toml is run.");
  run->add_option("--out,-o", out_dir, "Directory for the results (created if needed)")->default_val("runs/default");
  run->add_option("--set,-s", overrides,
                  "Override a case key, e.g. --set damping.ratio=\"0.3 %\" --set triaxial.strain_rate=1e-6 "
                  "--set sample.total_particles=2000 --set damping.model=od (repeatable)");
  run->add_option("--threads,-t", threads, "OpenMP threads (default: all cores)")->check(all_cores_or_count);
  run->add_flag("--quiet,-q", quiet, "No progress line");
  bool force = false;
  run->add_flag("--force,-f", force, "Overwrite a directory that holds a finished or unfinished run");
  bool no_plot = false;
  run->add_flag("--no-plot", no_plot,
                "Do not draw the run's figures at its end (they are drawn into DIR/plot/ when gnuplot is installed; "
                "`qsdem plot DIR` draws them later)");

  auto* prepare = app.add_subcommand(
      "prepare",
      "Generate and compact a sample only (SPEC 8): writes DIR/compacted.packing, DIR/compaction.csv and "
      "DIR/summary.json. The packing can be benchmarked with `qsdem bench`.");
  prepare->add_option("case", case_path, "Case file (TOML). Without it, the built-in default case.");
  prepare->add_option("--out,-o", out_dir, "Directory for the results (created if needed)")->default_val("runs/prepared");
  prepare->add_option("--set,-s", overrides, "Override a case key (as for run)");
  prepare->add_option("--threads,-t", threads, "OpenMP threads (default: all cores)")->check(all_cores_or_count);
  prepare->add_flag("--quiet,-q", quiet, "No progress line");
  prepare->add_flag("--force,-f", force, "Overwrite a directory that holds a finished or unfinished run");

  std::string resume_dir;
  auto* resume = app.add_subcommand(
      "resume",
      "Continue an interrupted run (killed, stopped by SIGINT/SIGTERM, crashed) from the newest good checkpoint "
      "in its directory (DIR/checkpoint.qsck, or DIR/checkpoint.qsck.prev when the newest is damaged). The "
      "resumed series.csv is identical to that of an uninterrupted run.");
  resume->add_option("dir", resume_dir, "Directory of the run")->required();
  resume->add_option("--set,-s", overrides,
                     "Change a case key that does not invalidate the state (limits.max_overlap, "
                     "limits.max_kinetic_ratio, checkpoint.every_sample_points, checkpoint.every_minutes, "
                     "output.vtk_every, compaction.max_steps; time.step_ratio during compaction); recorded in "
                     "summary.json (repeatable)");
  resume->add_option("--threads,-t", threads, "OpenMP threads (default: all cores)")->check(all_cores_or_count);
  resume->add_flag("--quiet,-q", quiet, "No progress line");
  resume->add_flag("--no-plot", no_plot, "Do not draw the run's figures at its end (as for run)");

  std::string plot_dir, plot_out;
  auto* plot = app.add_subcommand(
      "plot",
      "Draw the figures of a run directory (docs/runs.md): for each series file, q/p, phi, ev and the void ratio "
      "against e1, the stress path in p-q, the equilibrium indices UFR, Iuf, IMom and Cn, the fabric columns, the "
      "loops of a cyclic phase, and the size classes of classes.csv; PNG and SVG with their data and gnuplot "
      "scripts, and one page, DIR/plot/index.html. Needs gnuplot.");
  plot->add_option("dir", plot_dir, "Directory of the run (its series.csv, compaction.csv, summary.json)")->required();
  plot->add_option("--out,-o", plot_out, "Directory for the figures and the page (default: DIR/plot)");

  std::string bench_source;
  long steps = 1000;
  auto* bench = app.add_subcommand(
      "bench",
      "Step a state in a fixed cell with no output and print one JSON line (docs/benchmarks.md): particles, "
      "contacts at the first and the last step, steps, threads, wall seconds, particle-steps per second, memory, "
      "time per stage. The state is a packing (at rest, no contact history; the triaxial friction and damping of "
      "--case), or a checkpoint: DIR/sample.qsck of `qsdem prepare`, DIR/checkpoint.qsck of an unfinished run "
      "(velocities and contact history as the run left them; the friction and damping of its phase).");
  bench->add_option("source", bench_source,
                    "A packing file, a checkpoint file (*.qsck), or a run directory (its sample.qsck, else its "
                    "checkpoint.qsck)")
      ->required();
  bench->add_option("--case,-c", case_path,
                    "Case file: material, friction, damping and time step. Required for a packing; for a checkpoint "
                    "it replaces the checkpoint's own case (material and time.step_ratio must be equal)");
  bench->add_option("--steps,-n", steps, "Steps to time (default 1000)")->check(whole_number_at_least(1));
  bench->add_option("--set,-s", overrides, "Override a case key (as for run)");
  bench->add_option("--threads,-t", threads, "OpenMP threads (default: all cores)")->check(all_cores_or_count);
  bool as_spheres = false;
  bench->add_flag("--as-spheres", as_spheres,
                  "Replace every ellipsoid by its equal-volume sphere at the same centre first, at rest and without "
                  "contact history (the sphere path on the same packing)");

  std::string study_file;
  int parallel = 0;
  std::string order;
  auto* study = app.add_subcommand(
      "study",
      "Run a study (SPEC 9, docs/study.md): every sample of the study file prepared once, then sheared with every "
      "damping model, damping ratio and strain rate of its [design] (or of its [[stage]] tables, in order), in "
      "parallel processes (and over the ranks of "
      "`mpirun -np K`). Writes DIR/study.json, DIR/samples/, DIR/runs/, then the analysis (DIR/analysis/). Running it "
      "again on the same DIR continues it: finished runs are kept, interrupted ones resume from their checkpoints.");
  study->add_option("study", study_file, "Study file (TOML, see docs/study.md)")->required();
  study->add_option("--out,-o", out_dir, "Study directory (created if needed)")->required();
  study->add_option("--parallel,-j", parallel,
                    "Child processes at once (per MPI rank); default: execution.parallel_runs of the study file")
      ->check(whole_number_at_least(1));
  study->add_option("--order", order,
                    "Runs of a stage longest_first (the shortest total time) or shortest_first (the most runs "
                    "finished soonest); default: execution.order of the study file")
      ->check(CLI::IsMember({"longest_first", "shortest_first"}));
  study->add_flag("--quiet,-q", quiet, "No progress display");

  std::string analyze_dir;
  auto* analyze = app.add_subcommand(
      "analyze", "Analyse a study directory (written by `qsdem study`) again: DIR/analysis/ (docs/analysis.md).");
  analyze->add_option("dir", analyze_dir, "Study directory")->required();

  qsdem::LadderOptions ladder;
  std::string ladder_case;
  auto* converge = app.add_subcommand(
      "converge",
      "Certify a case's quasi-static response (docs/analysis.md, section 11): the case prepared with several seeds "
      "and sheared at a ladder of falling strain rates, as a study in DIR, rung by rung until the response stops "
      "changing with the rate (converged), the ladder ends or the step budget would be passed (not converged). "
      "Writes DIR/certificate.json and the study's report; exit code 0 when converged, 4 when not. Running it "
      "again on the same DIR continues it.");
  converge->add_option("case", ladder_case, "Case file (TOML). Without it, the built-in default case.");
  converge->add_option("--out,-o", out_dir, "Directory of the ladder (created if needed)")->required();
  converge->add_option("--set,-s", overrides, "Override a case key (as for run)");
  converge->add_option("--seeds", ladder.seeds, "Samples, prepared with sample.seed = 1 .. N")->default_val(3);
  converge->add_option("--start-rate", ladder.start_rate, "The first rung's eps' (default: the case's triaxial.strain_rate)");
  converge->add_option("--factor", ladder.factor, "eps' of a rung over eps' of the next")->default_val(3.16227766016838);
  converge->add_option("--rungs", ladder.rungs, "Rungs at most")->default_val(4);
  converge->add_option("--max-steps", ladder.max_steps,
                       "Step budget: triaxial steps of every run together; a rung that would pass it is not run");
  converge->add_option("--phi-tolerance", ladder.tolerances.phi_rms_deg, "RMS change of phi(e1), degrees")
      ->default_val(0.5);
  converge->add_option("--ev-tolerance", ladder.tolerances.ev_rms, "RMS change of ev(e1), a ratio")->default_val(0.001);
  bool no_scatter = false;
  converge->add_flag("--no-seed-scatter", no_scatter, "A rung's change need not be below the seed scatter");
  converge->add_option("--parallel,-j", parallel, "Child processes at once (default: cores / MPI ranks on the node)")
      ->check(whole_number_at_least(1));
  converge->add_flag("--quiet,-q", quiet, "No progress display");

  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? 0 : 1;  // --help and --version exit 0; a bad command line 1 (CLI11's codes vary)
  }

  try {
    set_threads(threads);
    if (dry_run) {
      namespace fs = std::filesystem;
      std::string checked;
      if (*run || *prepare || *study) qsdem::require_utf8(out_dir, "--out");
      if ((*run || *prepare) && case_path.empty()) {
        qsdem::parse_case(qsdem::default_case_toml, qsdem::default_case_name, overrides);
        checked = "the built-in case";
      } else if ((*run || *prepare || *bench) && fs::is_regular_file(case_path)) {
        qsdem::load_case(case_path, overrides);
        checked = "case " + case_path;
      } else if (*converge) {
        ladder.case_file = ladder_case, ladder.sets = overrides, ladder.tolerances.within_seed_scatter = !no_scatter;
        qsdem::ladder_study_text(ladder);
        checked = ladder_case.empty() ? "the ladder of the built-in case" : "the ladder of case " + ladder_case;
      } else if (*study && fs::is_regular_file(study_file)) {
        qsdem::load_study(study_file);
        checked = "study " + study_file;
      }
      std::cout << "qsdem: dry run: the command line is valid"
                << (checked.empty() ? std::string() : "; " + checked + " is valid") << "\n";
      return 0;
    }
    if (*run || *prepare) {
      const qsdem::Params params =
          case_path.empty() ? qsdem::parse_case(qsdem::default_case_toml, qsdem::default_case_name, overrides)
                            : qsdem::load_case(case_path, overrides);
      if (!quiet)
        std::fprintf(stderr, "qsdem %s: case %s -> %s (%d threads)\n", QSDEM_VERSION, params.source.c_str(),
                     out_dir.c_str(), omp_get_max_threads());
      if (!quiet && params.sample.from.empty() && !params.sample.grading.empty())
        std::fprintf(stderr, "qsdem: %s\n",
                     qsdem::describe_grading(params.sample.grading, params.sample.total_particles, params.sample.seed).c_str());
      const auto summary = qsdem::run_case(params, {out_dir, quiet, bool(*prepare), force});
      std::cout << "\n" << qsdem::format_run_table(summary) << "\nTime per stage:\n"
                << summary["stage_table"].get<std::string>() << "\nResults in " << out_dir
                << (*prepare ? "/ (compacted.packing, summary.json)\n" : "/ (series.csv, summary.json)\n");
      if (!*prepare) draw_page(out_dir, no_plot);
    } else if (*resume) {
      qsdem::RunOptions options;
      options.out = resume_dir;
      options.quiet = quiet;
      options.sets = overrides;
      const auto summary = qsdem::resume_run(resume_dir, options);
      std::cout << "\n" << qsdem::format_run_table(summary) << "\nTime per stage:\n"
                << summary["stage_table"].get<std::string>() << "\nResults in " << resume_dir << "/\n";
      // A resumed `qsdem prepare` (steps_cover: its compaction, physics.md 10.2) has no test to draw.
      const std::string cover = summary.value("steps_cover", "");
      if (cover != "compaction" && cover != "the first phase") draw_page(resume_dir, no_plot);
    } else if (*plot) {
      const qsdem::PlotResult r = qsdem::plot_run(plot_dir, plot_out);
      for (const std::string& n : r.notes) std::cout << "not drawn: " << n << "\n";
      std::cout << r.page.parent_path().string() << ": " << r.figures.size() << " figures; open " << r.page.string()
                << "\n";
    } else if (*study) {
      qsdem::StudyOptions options;
      options.out = out_dir, options.quiet = quiet, options.parallel = parallel, options.order = order;
      return qsdem::run_study(study_file, options);
    } else if (*converge) {
      ladder.case_file = ladder_case, ladder.sets = overrides, ladder.out = out_dir, ladder.parallel = parallel;
      ladder.quiet = quiet, ladder.tolerances.within_seed_scatter = !no_scatter;
      return qsdem::run_ladder(ladder);
    } else if (*analyze) {
      qsdem::analyze_study(analyze_dir);
      std::cout << "Analysis written to " << analyze_dir << "/analysis/\n";
    } else if (*bench) {
      std::cout << qsdem::json_text(qsdem::bench_packing(bench_source, case_path, overrides, steps, as_spheres), -1) << std::endl;
    }
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
  return 0;
}
