// The files a run and a study write (files.hpp; docs/runs.md, docs/study.md): never through a
// symbolic link planted under a name they use, and no text outside UTF-8 in their JSON files. The
// helpers against closed cases and a plain decoder, then real processes in directories whose every
// name is a planted link.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/stat.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <random>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "qsdem/run/config.hpp"
#include "qsdem/run/files.hpp"
#include "qsdem/run/output.hpp"
#include "qsdem/run/run.hpp"
#include "qsdem/run/run_directory.hpp"
#include "test_support.hpp"

using namespace qsdem;
namespace fs = std::filesystem;
using qsdem_test::slurp;

namespace {

const fs::path root = fs::temp_directory_path() / ("qsdem_files_" + std::to_string(::getpid()));
const fs::path source_dir = QSDEM_SOURCE_DIR;

fs::path fresh(const std::string& name) {
  const fs::path d = root / name;
  fs::remove_all(d);
  fs::create_directories(d);
  return d;
}

void write(const fs::path& p, const std::string& text) { std::ofstream(p, std::ios::binary) << text; }

using qsdem_test::Cli;
using qsdem_test::finish;

pid_t spawn(const std::vector<std::string>& args, const fs::path& log) {
  std::vector<std::string> all{QSDEM_BINARY};
  all.insert(all.end(), args.begin(), args.end());
  return qsdem_test::spawn_logged(all, log);
}

Cli cli(const std::vector<std::string>& args, const std::string& log_name) {
  fs::create_directories(root / "logs");
  const fs::path log = root / "logs" / log_name;
  return finish(spawn(args, log), log);
}

// The files under `dir` (not the directories), relative to it.
std::vector<fs::path> files_under(const fs::path& dir) {
  std::vector<fs::path> files;
  for (const auto& e : fs::recursive_directory_iterator(dir))
    if (!e.is_directory()) files.push_back(fs::relative(e.path(), dir));
  std::sort(files.begin(), files.end());
  return files;
}

bool is_regular_not_link(const fs::path& p) { return fs::symlink_status(p).type() == fs::file_type::regular; }

// Symbolic links planted in a directory, each pointing out of it into `outside`: at a file of its
// own (whose bytes must stay as they are) or at a name that must never come to exist.
class Planted {
 public:
  explicit Planted(fs::path outside) : outside_(std::move(outside)) { fs::create_directories(outside_); }
  void to_file(const fs::path& link) {
    const fs::path target = outside_ / ("target-" + std::to_string(targets_.size()));
    const std::string text = "outside file " + std::to_string(targets_.size()) + ", planted as " + link.string() + "\n";
    write(target, text);
    targets_[target] = text;
    plant(target, link);
  }
  void to_nothing(const fs::path& link) {
    const fs::path target = outside_ / ("absent-" + std::to_string(absent_.size()));
    absent_.push_back(target);
    plant(target, link);
  }
  std::size_t size() const { return targets_.size() + absent_.size(); }
  // Every target as planted, and nothing else in `outside`.
  void expect_untouched() const {
    for (const auto& [target, text] : targets_) EXPECT_EQ(slurp(target), text) << target << " was written through a link";
    for (const fs::path& a : absent_) EXPECT_FALSE(fs::exists(fs::symlink_status(a))) << a << " was created through a link";
    EXPECT_EQ(files_under(outside_).size(), targets_.size()) << "files appeared in " << outside_;
  }

 private:
  void plant(const fs::path& target, const fs::path& link) {
    fs::create_directories(link.parent_path());
    fs::remove(link);
    fs::create_symlink(target, link);
  }
  fs::path outside_;
  std::map<fs::path, std::string> targets_;
  std::vector<fs::path> absent_;
};

// Plain UTF-8 decoding: a sequence's length from its lead byte's high bits, continuation bytes
// 10xxxxxx, then the code point refused when overlong, a surrogate or above U+10FFFF.
std::size_t invalid_utf8_plain(const std::string& s) {
  std::size_t i = 0;
  while (i < s.size()) {
    const unsigned c = static_cast<unsigned char>(s[i]);
    std::size_t n;
    std::uint32_t cp;
    if (c < 0x80) n = 1, cp = c;
    else if ((c >> 5) == 0x6) n = 2, cp = c & 0x1F;
    else if ((c >> 4) == 0xE) n = 3, cp = c & 0x0F;
    else if ((c >> 3) == 0x1E) n = 4, cp = c & 0x07;
    else return i;
    if (i + n > s.size()) return i;
    for (std::size_t k = 1; k < n; ++k) {
      const unsigned d = static_cast<unsigned char>(s[i + k]);
      if ((d >> 6) != 0x2) return i;
      cp = (cp << 6) | (d & 0x3F);
    }
    const std::uint32_t least[] = {0, 0, 0x80, 0x800, 0x10000};
    if (cp < least[n] || (cp >= 0xD800 && cp <= 0xDFFF) || cp > 0x10FFFF) return i;
    i += n;
  }
  return std::string::npos;
}

// The tiny case (test_support.hpp) with a checkpoint every 2 sample points and a VTK snapshot
// every 2 rows; `rate`: its eps' (1.25e-4: 250 triaxial steps).
std::string tiny_case(const std::string& rate = "1.25e-4") {
  std::string text = qsdem_test::tiny_case("files");
  const std::string from = "strain_rate = 1.25e-4";
  text.replace(text.find(from), from.size(), "strain_rate = " + rate);
  return text + "[checkpoint]\nevery_sample_points = 2\n[output]\nvtk_every = 2\n";
}

}  // namespace

// The validator against the plain decoder, on every string of one to three bytes and on random
// strings of four to twelve, and on the closed cases of each rule.
TEST(Files, Utf8ValidatorAgreesWithAPlainDecoder) {
  EXPECT_EQ(invalid_utf8_at(""), std::string_view::npos);
  EXPECT_EQ(invalid_utf8_at("plain ASCII, 0.5 %"), std::string_view::npos);
  EXPECT_EQ(invalid_utf8_at("\xC3\xA9 \xE2\x82\xAC \xF0\x9F\x98\x80 \xF4\x8F\xBF\xBF"), std::string_view::npos);
  EXPECT_EQ(invalid_utf8_at("c\xFF.toml"), 1u);
  EXPECT_EQ(invalid_utf8_at("\x80"), 0u) << "a continuation byte alone";
  EXPECT_EQ(invalid_utf8_at("\xC0\xAF"), 0u) << "overlong '/'";
  EXPECT_EQ(invalid_utf8_at("\xE0\x80\xAF"), 0u) << "overlong '/' in three bytes";
  EXPECT_EQ(invalid_utf8_at("\xED\xA0\x80"), 0u) << "a surrogate";
  EXPECT_EQ(invalid_utf8_at("\xF4\x90\x80\x80"), 0u) << "above U+10FFFF";
  EXPECT_EQ(invalid_utf8_at("ab\xE2\x82"), 2u) << "cut short";
  EXPECT_EQ(invalid_utf8_at("\xC3\x28"), 0u) << "a lead byte without its continuation";
  long checked = 0;
  for (unsigned len = 1; len <= 3; ++len)
    for (std::uint32_t v = 0; v < (1u << (8 * len)); ++v) {
      std::string s(len, '\0');
      for (unsigned k = 0; k < len; ++k) s[k] = static_cast<char>((v >> (8 * k)) & 0xFF);
      ASSERT_EQ(invalid_utf8_at(s), invalid_utf8_plain(s)) << "bytes " << std::hex << v << " (" << len << ")";
      ++checked;
    }
  std::mt19937 rng(7);
  for (int trial = 0; trial < 2'000'000; ++trial) {
    std::string s(4 + rng() % 9, '\0');
    // Bytes biased to lead and continuation bytes, where the rules are.
    for (char& c : s) c = static_cast<char>(rng() % 3 == 0 ? rng() % 256 : 0x80 + rng() % 0x78);
    ASSERT_EQ(invalid_utf8_at(s), invalid_utf8_plain(s)) << trial;
    ++checked;
  }
  EXPECT_GT(checked, 16'000'000);
  try {
    require_utf8("runs/c\xFF\xFE.toml", "--out");
    ADD_FAILURE() << "not refused";
  } catch (const InputError& e) {
    EXPECT_NE(std::string(e.what()).find("--out 'runs/c\\xFF\\xFE.toml' is not valid UTF-8"), std::string::npos)
        << e.what();
    EXPECT_EQ(invalid_utf8_at(e.what()), std::string_view::npos) << "the message itself is UTF-8";
  }
}

// json_text, the last defence: where dump() throws type_error.316, the bytes become U+FFFD.
TEST(Files, JsonTextReplacesWhatIsNotUtf8) {
  const nlohmann::json j = {{"source", "c\xFF.toml"}};
  EXPECT_THROW((void)j.dump(), nlohmann::json::type_error);
  EXPECT_EQ(json_text(j, -1), "{\"source\":\"c\xEF\xBF\xBD.toml\"}");
  const nlohmann::ordered_json o = {{"case", "\xC0"}};
  EXPECT_EQ(json_text(o, -1), "{\"case\":\"\xEF\xBF\xBD\"}");
}

// The helpers each writer uses: a link under the name is never followed, a FIFO never blocks.
TEST(Files, NoFileIsOpenedThroughALink) {
  const fs::path d = fresh("helpers");
  Planted planted(d / "outside");
  const fs::path in = d / "in";
  fs::create_directories(in);

  planted.to_file(in / "a.tmp");
  int fd = create_file(in / "a.tmp");
  ASSERT_GE(fd, 0) << std::strerror(errno);
  ASSERT_EQ(::write(fd, "new", 3), 3);
  ::close(fd);
  EXPECT_TRUE(is_regular_not_link(in / "a.tmp"));
  EXPECT_EQ(slurp(in / "a.tmp"), "new");

  planted.to_nothing(in / "b.tmp");
  fd = create_file(in / "b.tmp");
  ASSERT_GE(fd, 0);
  ::close(fd);
  EXPECT_TRUE(is_regular_not_link(in / "b.tmp"));

  fs::create_directories(in / "dir");
  EXPECT_LT(create_file(in / "dir"), 0) << "a directory is not removed";
  EXPECT_TRUE(fs::is_directory(in / "dir"));

  planted.to_file(in / "file.json");
  write_file_atomic(in / "file.json", "{}\n");  // through file.json.tmp, then renamed over the link
  planted.to_file(in / "file.json.tmp");
  write_file_atomic(in / "file.json", "{}\n");
  EXPECT_TRUE(is_regular_not_link(in / "file.json"));
  EXPECT_EQ(slurp(in / "file.json"), "{}\n");

  // Kept in place when it is a regular file (a log), replaced when it is a link (a lock).
  write(in / "run.log", "earlier lines\n");
  fd = open_file(in / "run.log", O_WRONLY | O_APPEND);
  ASSERT_GE(fd, 0);
  ASSERT_EQ(::write(fd, "more\n", 5), 5);
  ::close(fd);
  EXPECT_EQ(slurp(in / "run.log"), "earlier lines\nmore\n");
  planted.to_file(in / ".run.lock");
  fd = open_file(in / ".run.lock", O_RDWR);
  ASSERT_GE(fd, 0);
  ::close(fd);
  EXPECT_TRUE(is_regular_not_link(in / ".run.lock"));

  planted.to_file(in / "series.csv.partial");
  EXPECT_LT(open_regular_file(in / "series.csv.partial", O_RDWR), 0);
  EXPECT_EQ(errno, ELOOP);
  ASSERT_EQ(::mkfifo((in / "fifo").c_str(), 0644), 0);
  EXPECT_LT(open_regular_file(in / "fifo", O_RDONLY), 0) << "refused without blocking";
  EXPECT_EQ(errno, EINVAL);
  EXPECT_FALSE(read_regular_file(in / "fifo"));
  EXPECT_LT(open_file(in / "fifo", O_WRONLY | O_APPEND), 0);
  EXPECT_FALSE(read_regular_file(in / "series.csv.partial"));
  EXPECT_EQ(read_regular_file(in / "run.log").value_or(""), "earlier lines\nmore\n");

  // A directory on the way that is a link: refused, nothing made at its target.
  fs::create_directories(d / "outside-dir");
  fs::create_symlink(d / "outside-dir", in / "runs");
  EXPECT_THROW(make_directories(in, "runs/a/b"), InputError);
  EXPECT_TRUE(fs::is_empty(d / "outside-dir"));
  make_directories(in, "samples/a-seed1");
  EXPECT_TRUE(fs::is_directory(fs::symlink_status(in / "samples/a-seed1")));
  EXPECT_THROW(make_directories(in, "../escape"), InputError);
  planted.expect_untouched();
  fs::remove_all(d);
}

// A path, --out, --set key or value, sample.from or study file that is not UTF-8 is refused at
// once with exit 2, naming it, before anything is computed or written (it used to fail only
// when summary.json was written, after the whole run, exit 3).
TEST(Utf8, NamesAndValuesThatAreNotUtf8AreRefusedBeforeAnyWork) {
  const fs::path d = fresh("utf8");
  write(d / "case.toml", tiny_case());
  write(d / "c\xFF.toml", tiny_case());
  const auto refused = [&](const std::vector<std::string>& args, const std::string& shown, const std::string& log) {
    SCOPED_TRACE(log);
    const Cli c = cli(args, log);
    EXPECT_EQ(c.code, 2) << c.err;
    EXPECT_NE(c.err.find(shown), std::string::npos) << c.err;
    EXPECT_NE(c.err.find("not valid UTF-8"), std::string::npos) << c.err;
  };
  const std::string out = (d / "out").string();
  refused({"run", (d / "c\xFF.toml").string(), "--out", out, "--quiet"}, "c\\xFF.toml", "path");
  refused({"run", (d / "case.toml").string(), "--out", (d / "r\xFF").string(), "--quiet"}, "r\\xFF", "out");
  refused({"run", (d / "case.toml").string(), "--out", out, "--quiet", "--set", "name=c\xFF"}, "name=c\\xFF", "value");
  refused({"run", (d / "case.toml").string(), "--out", out, "--quiet", "--set", "name=\"c\xFF\""}, "c\\xFF", "string");
  refused({"run", (d / "case.toml").string(), "--out", out, "--quiet", "--set", "na\xFFme=1"}, "na\\xFFme", "key");
  refused({"run", (d / "case.toml").string(), "--out", out, "--quiet", "--set", "sample.from=p\xFF"}, "p\\xFF", "from");
  refused({"prepare", (d / "case.toml").string(), "--out", (d / "p\xFF").string(), "--quiet"}, "p\\xFF", "prepare");
  EXPECT_FALSE(fs::exists(out));
  EXPECT_FALSE(fs::exists(d / "r\xFF"));
  // In a case file, the TOML parser refuses it.
  std::string text = tiny_case();
  text.replace(text.find("name = \"files\""), 14, "name = \"fi\xFFles\"");
  write(d / "bad.toml", text);
  const Cli bad = cli({"run", (d / "bad.toml").string(), "--out", out, "--quiet"}, "toml");
  EXPECT_EQ(bad.code, 2) << bad.err;
  EXPECT_NE(bad.err.find("utf-8"), std::string::npos) << bad.err;
  // A study: its directory (the absolute path of a case), its --out, `qsdem analyze`.
  fs::create_directories(d / "s\xFF");
  write(d / "s\xFF" / "case.toml", slurp(source_dir / "examples" / "spheres-A-small.toml"));
  write(d / "s\xFF" / "study.toml",
        "[[sample]]\nname = \"a\"\ncase = \"case.toml\"\n[design]\nmodels = [\"nd\"]\ndamping_ratios = [\"1 %\"]\n"
        "strain_rates = [1e-5]\n");
  refused({"study", (d / "s\xFF" / "study.toml").string(), "--out", out, "--quiet"}, "s\\xFF/case.toml", "study");
  refused({"study", (source_dir / "studies" / "tiny.toml").string(), "--out", (d / "st\xFF").string(), "--quiet"},
          "st\\xFF", "study-out");
  fs::create_directories(d / "a\xFF");
  refused({"analyze", (d / "a\xFF").string()}, "a\\xFF", "analyze");
  EXPECT_FALSE(fs::exists(out));
  EXPECT_FALSE(fs::exists(d / "st\xFF"));
  fs::remove_all(d);
}

// A checkpoint written before these checks, whose case path is not UTF-8, still resumes: its
// summary.json names the path with U+FFFD in place of the bad byte (resume used to fail on it
// every time, after the whole run).
TEST(Utf8, ACheckpointNamingAPathThatIsNotUtf8Resumes) {
  const fs::path d = fresh("legacy");
  RunOptions o;
  o.out = d / "run";
  o.quiet = true;
  // parse_case takes the source as given (load_case is what refuses it): as an older engine did.
  EXPECT_THROW(run_case(parse_case(tiny_case(), "c\xFF.toml", {"limits.max_kinetic_ratio=1e-30"}), o), RunError);
  ASSERT_TRUE(fs::exists(d / "run" / "checkpoint.qsck"));
  o.sets = {"limits.max_kinetic_ratio=1"};
  nlohmann::json s;
  ASSERT_NO_THROW(s = resume_run(d / "run", o));
  EXPECT_EQ(s["config"]["resolved_si"]["source"], "c\xFF.toml") << "the path as the checkpoint holds it";
  const auto written = nlohmann::json::parse(slurp(d / "run" / "summary.json"));
  EXPECT_EQ(written["config"]["resolved_si"]["source"], "c\xEF\xBF\xBD.toml");
  EXPECT_FALSE(fs::exists(d / "run" / "checkpoint.qsck")) << "finished";
  fs::remove_all(d);
}

// A fresh run (--force) in a directory where every name it writes, and the temporary name of
// each, is a link to outside it: nothing outside is written or created, and every result is a
// regular file with the bytes of a run in an empty directory.
TEST(LinkSafety, RunWritesNothingThroughAPlantedLink) {
  const fs::path d = fresh("run");
  write(d / "case.toml", tiny_case());
  const Cli ref = cli({"run", (d / "case.toml").string(), "--out", (d / "ref").string(), "--quiet", "--threads", "1"},
                      "run-ref");
  ASSERT_EQ(ref.code, 0) << ref.err;
  std::vector<fs::path> names = files_under(d / "ref");
  ASSERT_TRUE(std::find(names.begin(), names.end(), "summary.json") != names.end());
  // The names a finished run no longer holds: its checkpoints and the rows before each rename.
  std::vector<fs::path> written = names;
  for (const char* f : {"checkpoint.qsck", "checkpoint.qsck.prev", "series.csv.partial", "compaction.csv.partial",
                        "classes.csv.partial"})
    written.emplace_back(f);
  const fs::path out = d / "out";
  Planted planted(d / "outside");
  for (const fs::path& f : written) {
    if (*f.begin() == "vtk") continue;  // --force removes vtk/ first (its names: the resume test)
    planted.to_file(out / (f.string() + ".tmp"));
    if (f == run_lock_file) planted.to_file(out / f);  // opened in place
    else if (!fs::exists(fs::symlink_status(out / f))) planted.to_nothing(out / f);
  }
  ASSERT_GT(planted.size(), 20u);
  const Cli c = cli({"run", (d / "case.toml").string(), "--out", out.string(), "--quiet", "--threads", "1", "--force"},
                    "run-links");
  ASSERT_EQ(c.code, 0) << c.err;
  planted.expect_untouched();
  for (const fs::path& f : names) EXPECT_TRUE(is_regular_not_link(out / f)) << f;
  for (const char* f : {"series.csv", "compaction.csv", "classes.csv", "final.packing"})
    EXPECT_EQ(slurp(out / f), slurp(d / "ref" / f)) << f;
  fs::remove_all(d);
}

// A resumed run (stopped by SIGTERM in its triaxial test, with rows and VTK snapshots written)
// in a directory where every name it has yet to write, and the temporary name of every file, is a
// link to outside: nothing outside is touched and the results are those of the uninterrupted run.
// A link in place of the series.csv.partial it continues, or of vtk/, is refused, and the file
// outside is left as it was.
TEST(LinkSafety, ResumeWritesNothingThroughAPlantedLink) {
  const fs::path d = fresh("resume");
  write(d / "case.toml", tiny_case("1.25e-6"));  // 25000 triaxial steps, a row every 2500
  const Cli ref = cli({"run", (d / "case.toml").string(), "--out", (d / "ref").string(), "--quiet", "--threads", "1"},
                      "resume-ref");
  ASSERT_EQ(ref.code, 0) << ref.err;
  const std::vector<fs::path> names = files_under(d / "ref");
  ASSERT_TRUE(std::find(names.begin(), names.end(), "vtk/series.pvd") != names.end());

  const fs::path stopped = d / "stopped";
  const pid_t pid = spawn({"run", (d / "case.toml").string(), "--out", stopped.string(), "--quiet", "--threads", "1"},
                          root / "logs" / "resume-stopped");
  ASSERT_GT(pid, 0);
  const auto deadline = std::chrono::steady_clock::now() + std::chrono::minutes(2);
  while (std::chrono::steady_clock::now() < deadline && qsdem_test::lines(stopped / "series.csv.partial") < 4)
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  ::kill(pid, SIGTERM);
  ASSERT_EQ(qsdem_test::wait_exit(pid), 143) << "stopped with a checkpoint after its second row";
  ASSERT_TRUE(fs::exists(stopped / "checkpoint.qsck"));
  ASSERT_TRUE(fs::exists(stopped / "vtk"));

  const fs::path out = d / "out";
  fs::copy(stopped, out, fs::copy_options::recursive);
  Planted planted(d / "outside");
  std::vector<fs::path> written = names;
  for (const char* f : {"checkpoint.qsck", "checkpoint.qsck.prev", "series.csv.partial", "classes.csv.partial"})
    written.emplace_back(f);
  for (const fs::path& f : written) {
    planted.to_file(out / (f.string() + ".tmp"));
    if (f == run_lock_file) planted.to_file(out / f);
    else if (!fs::exists(fs::symlink_status(out / f))) planted.to_nothing(out / f);
  }
  const Cli c = cli({"resume", out.string(), "--quiet", "--threads", "1"}, "resume-links");
  ASSERT_EQ(c.code, 0) << c.err;
  planted.expect_untouched();
  for (const fs::path& f : names) EXPECT_TRUE(is_regular_not_link(out / f)) << f;
  for (const char* f : {"series.csv", "compaction.csv", "classes.csv", "final.packing"})
    EXPECT_EQ(slurp(out / f), slurp(d / "ref" / f)) << f;

  // The file it continues, a link: refused (exit 2), the file outside as it was.
  const fs::path partial = d / "partial";
  fs::copy(stopped, partial, fs::copy_options::recursive);
  fs::create_directories(d / "outside-partial");
  fs::rename(partial / "series.csv.partial", d / "outside-partial" / "rows");
  const std::string rows = slurp(d / "outside-partial" / "rows");
  fs::create_symlink(d / "outside-partial" / "rows", partial / "series.csv.partial");
  const Cli p = cli({"resume", partial.string(), "--quiet", "--threads", "1"}, "resume-partial");
  EXPECT_EQ(p.code, 2) << p.err;
  EXPECT_NE(p.err.find("symbolic link"), std::string::npos) << p.err;
  EXPECT_EQ(slurp(d / "outside-partial" / "rows"), rows);

  // vtk/ a link: the run stops at its next snapshot (exit 3) with its checkpoint; nothing outside.
  const fs::path vtk = d / "vtk-link";
  fs::copy(stopped, vtk, fs::copy_options::recursive);
  fs::remove_all(vtk / "vtk");
  fs::create_directories(d / "outside-vtk");
  fs::create_symlink(d / "outside-vtk", vtk / "vtk");
  const Cli v = cli({"resume", vtk.string(), "--quiet", "--threads", "1"}, "resume-vtk");
  EXPECT_EQ(v.code, 3) << v.err;
  EXPECT_NE(v.err.find("symbolic link"), std::string::npos) << v.err;
  EXPECT_TRUE(fs::is_empty(d / "outside-vtk"));
  EXPECT_TRUE(fs::exists(vtk / "checkpoint.qsck"));
  fs::remove_all(d);
}

// A study in a directory holding its study.toml and, for every file the study writes (its
// manifest, the case copies, the samples' and runs' files and logs, the analysis and its gnuplot
// figures, the report, the locks), a link under the name or its temporary name pointing outside:
// nothing outside is touched, the results are regular files, and the run's series is that of
// the study in an empty directory. A link in place of runs/ stops its runs, not the study.
TEST(LinkSafety, StudyWritesNothingThroughAPlantedLink) {
  const fs::path d = fresh("study");
  write(d / "case.toml", slurp(source_dir / "examples" / "spheres-A-small.toml"));
  write(d / "study.toml",
        "[[sample]]\nname = \"tiny\"\ncase = \"case.toml\"\nset = ['sample.particles=[{shape=\"sphere\", "
        "diameter=\"2.4 mm\", count=60}, {shape=\"sphere\", diameter=\"2.0 mm\", count=60}]', "
        "\"sample.total_particles=0\", \"sample.initial_solid_fraction=0.2\", \"compaction.max_strain_rate=1e-3\"]\n"
        "[design]\nmodels = [\"nd\"]\ndamping_ratios = [\"1 %\"]\nstrain_rates = [5e-5]\n"
        "set = [\"triaxial.final_axial_strain=1 %\", \"triaxial.sample_points=10\"]\n"
        "[execution]\nparallel_runs = 1\n");
  const Cli ref = cli({"study", (d / "study.toml").string(), "--out", (d / "ref").string(), "--quiet"}, "study-ref");
  ASSERT_EQ(ref.code, 0) << ref.err;
  const std::vector<fs::path> names = files_under(d / "ref");
  for (const char* f : {"study.json", "report.html", "analysis/analysis.json"})
    ASSERT_TRUE(std::find(names.begin(), names.end(), f) != names.end()) << f;
  ASSERT_TRUE(std::any_of(names.begin(), names.end(), [](const fs::path& f) { return f.extension() == ".svg"; }));
  ASSERT_TRUE(std::any_of(names.begin(), names.end(), [](const fs::path& f) { return f.filename() == "run.log"; }));

  const fs::path out = d / "out";
  fs::create_directories(out);
  write(out / "study.toml", slurp(d / "study.toml"));  // the study it continues
  Planted planted(d / "outside");
  for (const fs::path& f : names) {
    if (f == "study.toml") continue;
    planted.to_file(out / (f.string() + ".tmp"));
    const std::string name = f.filename().string();
    if (name == "run.log" || name == "prepare.log" || name == ".run.lock" || name == ".study.lock")
      planted.to_file(out / f);  // opened in place
    else
      planted.to_nothing(out / f);
  }
  const Cli c = cli({"study", (d / "study.toml").string(), "--out", out.string(), "--quiet"}, "study-links");
  ASSERT_EQ(c.code, 0) << c.err;
  planted.expect_untouched();
  for (const fs::path& f : names) EXPECT_TRUE(is_regular_not_link(out / f)) << f;
  for (const fs::path& f : names) {
    if (f.filename() == "series.csv") {
      EXPECT_EQ(slurp(out / f), slurp(d / "ref" / f)) << f;
    }
  }

  const fs::path linked = d / "runs-link";
  fs::create_directories(linked);
  write(linked / "study.toml", slurp(d / "study.toml"));
  fs::create_directories(d / "outside-runs");
  fs::create_symlink(d / "outside-runs", linked / "runs");
  const Cli r = cli({"study", (d / "study.toml").string(), "--out", linked.string(), "--quiet"}, "study-runs-link");
  EXPECT_EQ(r.code, 3) << r.err;
  EXPECT_TRUE(fs::is_empty(d / "outside-runs"));
  EXPECT_NE(slurp(linked / "failures.json").find("symbolic link"), std::string::npos);
  fs::remove_all(d);
}
