// The user documentation against the code, where a machine can check it:
//  - every key of docs/config.md is a key the parser reads, and every key it reads is documented;
//  - the annotated example of docs/config.md is the default case with every key written out;
//  - every qsdem command line quoted in README.md and the docs is accepted by `qsdem --dry-run`;
//  - every relative link of the Markdown files points to a file that exists;
//  - every CSV file of the repository (the results' series.csv, compaction.csv, classes.csv and
//    analysis tables) has as many fields in each row as in its header.
#include <gtest/gtest.h>

#include <sys/wait.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <optional>
#include <regex>
#include <set>
#include <sstream>
#include <string>
#include <string_view>
#include <vector>

#include "qsdem/engine/contact/laws.hpp"
#include "qsdem/run/config.hpp"

namespace fs = std::filesystem;

namespace {

const fs::path source_dir = QSDEM_SOURCE_DIR;

std::string read_text(const fs::path& path) {
  std::ifstream in(path);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

std::vector<std::string> lines_of(const std::string& text) {
  std::vector<std::string> lines;
  std::stringstream ss(text);
  for (std::string line; std::getline(ss, line);) lines.push_back(line);
  return lines;
}

// The user-facing Markdown files: README.md and those of docs/, tests/, bench/.
std::vector<fs::path> markdown_files() {
  std::vector<fs::path> files{source_dir / "README.md"};
  for (const char* dir : {"docs", "tests", "bench"})
    for (const auto& e : fs::recursive_directory_iterator(source_dir / dir))
      if (e.is_regular_file() && e.path().extension() == ".md") files.push_back(e.path());
  return files;
}

// The keys of docs/config.md: the first cell, in backticks, of the rows of its tables headed
// "| key | ...". A row under a "[[table]]" heading names a key of that table's rows
// ("count" -> "sample.particles.count").
std::set<std::string> documented_keys() {
  std::set<std::string> keys;
  bool in_key_table = false;
  std::string prefix;
  const std::regex row(R"(^\|\s*`([A-Za-z0-9_.]+)`\s*\|)");
  const std::regex array_heading(R"(\[\[([A-Za-z0-9_.]+)\]\])");
  for (const std::string& line : lines_of(read_text(source_dir / "docs/config.md"))) {
    std::smatch m;
    if (line.rfind("#", 0) == 0) prefix = std::regex_search(line, m, array_heading) ? m[1].str() + "." : "";
    if (line.rfind("| key |", 0) == 0) in_key_table = true;
    if (line.rfind("|", 0) != 0) in_key_table = false;
    if (in_key_table && std::regex_search(line, m, row)) {
      const std::string key = m[1];
      keys.insert(key.find('.') == std::string::npos ? prefix + key : key);
    }
  }
  return keys;
}

// The first ```toml block after the heading `heading` of a Markdown file.
std::string toml_block_after(const fs::path& file, const std::string& heading) {
  std::string block;
  bool after = false, inside = false;
  for (const std::string& line : lines_of(read_text(file))) {
    if (line == heading) after = true;
    if (!after) continue;
    if (inside && line.rfind("```", 0) == 0) return block;
    if (inside) block += line + "\n";
    if (line == "```toml") inside = true;
  }
  return block;
}

// Shell words of a command line as sh would pass them (quotes removed), up to a comment or an
// operator (| ; & < >). Enough for the command lines of the docs.
std::vector<std::string> shell_words(const std::string& text) {
  std::vector<std::string> words;
  std::string word;
  bool in_word = false;
  for (std::size_t k = 0; k < text.size(); ++k) {
    const char c = text[k];
    if (c == '\'' || c == '"') {
      const std::size_t end = text.find(c, k + 1);
      if (end == std::string::npos) return {};  // unbalanced: not a command line
      word += text.substr(k + 1, end - k - 1);
      in_word = true;
      k = end;
    } else if (c == '\\' && k + 1 < text.size()) {
      word += text[++k];
      in_word = true;
    } else if (c == ' ' || c == '\t') {
      if (in_word) words.push_back(word);
      word.clear();
      in_word = false;
    } else if (!in_word && (c == '#' || c == '|' || c == ';' || c == '&' || c == '<' || c == '>')) {
      break;
    } else {
      word += c;
      in_word = true;
    }
  }
  if (in_word) words.push_back(word);
  return words;
}

struct QuotedCommand {
  std::string where;                // file:line
  std::vector<std::string> args;    // after the program name
};

// The arguments of a command line that runs qsdem (`qsdem ...`, `build/qsdem ...`, optionally
// after `mpirun -np K`), or nothing. A synopsis, with [optional] words, is not a command line.
std::optional<std::vector<std::string>> qsdem_arguments(const std::string& text) {
  std::vector<std::string> w = shell_words(text);
  std::size_t k = 0;
  if (w.size() >= 3 && w[0] == "mpirun" && w[1] == "-np") k = 3;
  if (k >= w.size() || (w[k] != "qsdem" && w[k] != "build/qsdem")) return std::nullopt;
  for (const std::string& word : w)
    if (word[0] == '[') return std::nullopt;
  return std::vector<std::string>(w.begin() + static_cast<std::ptrdiff_t>(k) + 1, w.end());
}

// The qsdem command lines of a Markdown file: the lines of its sh / bash / console code blocks
// that run qsdem (with their continuation lines), and the inline code spans that do. A span names
// a subcommand or an option rather than a command line when it has only two words ("`qsdem
// bench`") or ends with an option ("`qsdem run --set`").
std::vector<QuotedCommand> quoted_commands(const fs::path& file) {
  std::vector<QuotedCommand> out;
  const std::vector<std::string> lines = lines_of(read_text(file));
  const std::string name = fs::relative(file, source_dir).string();
  bool in_block = false, shell_block = false;
  const std::regex span("`([^`]+)`");
  for (std::size_t n = 0; n < lines.size(); ++n) {
    const std::string& line = lines[n];
    const std::string where = name + ":" + std::to_string(n + 1);
    if (line.find("```") != std::string::npos && line.find_first_not_of(" ") == line.find("```")) {
      const std::string lang = line.substr(line.find("```") + 3);
      shell_block = !in_block && (lang == "sh" || lang == "bash" || lang == "console" || lang == "shell");
      in_block = !in_block;
      continue;
    }
    if (in_block) {
      if (!shell_block) continue;
      std::string text = line;
      while (!text.empty() && text.back() == '\\' && n + 1 < lines.size()) text = text.substr(0, text.size() - 1) + lines[++n];
      const std::size_t first = text.find_first_not_of(" $");
      if (first == std::string::npos) continue;
      if (auto args = qsdem_arguments(text.substr(first))) out.push_back({where, *args});
      continue;
    }
    for (std::sregex_iterator it(line.begin(), line.end(), span), end; it != end; ++it) {
      const std::string text = (*it)[1].str();
      const auto args = qsdem_arguments(text);
      if (args && args->size() >= 2 && args->back()[0] != '-')
        out.push_back({where, *args});
    }
  }
  return out;
}

std::string quote_for_shell(const std::string& s) {
  std::string q = "'";
  for (char c : s) q += c == '\'' ? std::string("'\\''") : std::string(1, c);
  return q + "'";
}

// Runs a shell command; returns its exit status and output.
std::pair<int, std::string> run_shell(const std::string& command) {
  std::string output;
  std::FILE* pipe = popen((command + " 2>&1").c_str(), "r");
  if (!pipe) return {-1, "popen failed"};
  char buffer[512];
  while (std::fgets(buffer, sizeof buffer, pipe)) output += buffer;
  const int status = pclose(pipe);
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, output};
}

}  // namespace

TEST(Docs, EveryCaseKeyIsDocumentedAndEveryDocumentedKeyIsRead) {
  const std::vector<std::string> parser = qsdem::case_keys();
  const std::set<std::string> parsed(parser.begin(), parser.end());
  const std::set<std::string> documented = documented_keys();
  ASSERT_GT(parsed.size(), 40u);  // the accessor sees the whole parser
  for (const std::string& k : parsed) EXPECT_TRUE(documented.count(k)) << "not in docs/config.md: " << k;
  for (const std::string& k : documented) EXPECT_TRUE(parsed.count(k)) << "docs/config.md documents an unknown key: " << k;
}

TEST(Docs, AnnotatedExampleIsTheDefaultCaseWithEveryKeyWritten) {
  const std::string example = toml_block_after(source_dir / "docs/config.md", "## Complete annotated example");
  ASSERT_FALSE(example.empty());
  const qsdem::Params annotated = qsdem::parse_case(example, "docs/config.md (annotated example)");
  const qsdem::Params plain = qsdem::load_case((source_dir / "examples/spheres-A-small.toml").string());
  nlohmann::json a = qsdem::to_json(annotated), b = qsdem::to_json(plain);
  a.erase("source"), b.erase("source");
  EXPECT_EQ(a, b) << "the annotated example does not run the same case as examples/spheres-A-small.toml";
  // Every key is written, but those of the other shapes' rows (its rows are spheres) and of the
  // other contact laws.
  std::set<std::string> not_taken{"sample.particles.major_semi_axis", "sample.particles.minor_semi_axis",
                                  "sample.particles.semi_axes"};
  for (std::string_view law : qsdem::contact_law_names())
    if (law != annotated.contact.law)
      for (const qsdem::LawKey& key : qsdem::contact_law_keys(law)) not_taken.insert("contact." + std::string(key.name));
  for (const qsdem::LawKey& key : qsdem::contact_law_keys(annotated.contact.law))
    not_taken.erase("contact." + std::string(key.name));
  for (const std::string& key : qsdem::case_keys()) {
    if (not_taken.count(key)) continue;
    if (key.rfind("phase.", 0) == 0) continue;  // a [[phase]] list replaces [compaction] and [triaxial]
    if (key.rfind("triaxial.rate_control.", 0) == 0) continue;  // an optional table: writing it changes the case
    if (key.find(".inertia_scaling.") != std::string::npos) continue;  // the same (and target, factor exclude each other)
    if (key.rfind("sample.grading", 0) == 0) continue;  // a sieve curve replaces the size table
    std::string pointer = "/" + key;
    for (char& c : pointer) c = c == '.' ? '/' : c;
    if (key.rfind("sample.particles.", 0) == 0) pointer.insert(std::string("/sample/particles").size(), "/0");
    EXPECT_TRUE(annotated.as_written.contains(nlohmann::json::json_pointer(pointer)))
        << "the annotated example of docs/config.md leaves out " << key;
  }
}

TEST(Docs, EveryQuotedCommandLineIsAccepted) {
  std::size_t checked = 0;
  for (const fs::path& file : markdown_files()) {
    for (const QuotedCommand& c : quoted_commands(file)) {
      std::string command = "cd " + quote_for_shell(source_dir.string()) + " && " + quote_for_shell(QSDEM_BINARY) +
                            " --dry-run";
      for (const std::string& a : c.args) {
        command += ' ';
        command += quote_for_shell(a);
        // A case or study file of the repository it names must exist (the dry run reads the case
        // when it exists and is silent about one that does not).
        const std::string path = a.substr(a.find('=') == std::string::npos ? 0 : a.find('=') + 1);
        const bool toml = path.size() > 5 && path.compare(path.size() - 5, 5, ".toml") == 0;
        if (toml && (path.rfind("examples/", 0) == 0 || path.rfind("studies/", 0) == 0)) {
          EXPECT_TRUE(fs::exists(source_dir / path)) << c.where << ": no file " << path;
        }
      }
      const auto [status, output] = run_shell(command);
      EXPECT_EQ(status, 0) << c.where << ": `qsdem " << [&] {
        std::string s;
        for (const std::string& a : c.args) s += (s.empty() ? "" : " ") + a;
        return s;
      }() << "` is refused:\n" << output;
      ++checked;
    }
  }
  EXPECT_GE(checked, 30u);  // the docs quote many; finding none would check nothing
}

TEST(Docs, EveryRelativeLinkPointsToAFile) {
  const std::regex link(R"(\]\(([^)\s]+)\))");
  std::size_t checked = 0;
  for (const fs::path& file : markdown_files()) {
    bool in_block = false;
    int n = 0;
    for (const std::string& line : lines_of(read_text(file))) {
      ++n;
      if (line.rfind("```", 0) == 0) in_block = !in_block;
      if (in_block) continue;
      for (std::sregex_iterator it(line.begin(), line.end(), link), end; it != end; ++it) {
        std::string target = (*it)[1];
        if (target.find("://") != std::string::npos || target.rfind("mailto:", 0) == 0 || target[0] == '#') continue;
        target = target.substr(0, target.find('#'));
        EXPECT_TRUE(fs::exists(file.parent_path() / target))
            << fs::relative(file, source_dir).string() << ":" << n << ": link to a missing file: " << target;
        ++checked;
      }
    }
  }
  EXPECT_GE(checked, 10u);
}

// The README's layout table names the units of each layer's folder (src/qsdem/engine/, run/,
// study/, cli/) as they are: each name in backticks is a source file (`name.hpp`, `name.cpp` or
// `name.hpp.in`) or a folder (`name/`) of that layer, every source unit is named, and src/qsdem/
// holds the layers' folders only.
TEST(Docs, LayoutTableNamesTheLibrarysUnits) {
  const std::vector<std::string> layers = {"engine", "run", "study", "cli"};
  const std::vector<std::string> readme = lines_of(read_text(source_dir / "README.md"));
  for (const std::string& layer : layers) {
    const std::string head = "| `src/qsdem/" + layer + "/` |";
    std::string row;
    for (const std::string& line : readme)
      if (line.rfind(head, 0) == 0) row = line.substr(head.size());
    ASSERT_FALSE(row.empty()) << "README.md has no layout row for src/qsdem/" << layer << "/";
    const fs::path dir = source_dir / "src/qsdem" / layer;
    std::set<std::string> named;
    const std::regex name(R"(`([a-z_]+/?)`)");
    for (std::sregex_iterator it(row.begin(), row.end(), name), end; it != end; ++it) {
      const std::string n = (*it)[1];
      if (n == "qsdem_" + layer) continue;  // the layer's library
      named.insert(n);
      const bool exists = n.back() == '/' ? fs::is_directory(dir / n)
                                          : fs::exists(dir / (n + ".hpp")) || fs::exists(dir / (n + ".cpp"));
      EXPECT_TRUE(exists) << "README.md names src/qsdem/" << layer << "/" << n << ", which does not exist";
    }
    std::set<std::string> units;
    for (const auto& e : fs::directory_iterator(dir)) {
      const std::string n = e.path().filename().string();
      units.insert(e.is_directory() ? n + "/" : n.substr(0, n.find('.')));
    }
    units.erase("default_case");  // generated from the annotated example at build time
    for (const std::string& n : units)
      EXPECT_TRUE(named.count(n)) << "README.md's layout table does not name src/qsdem/" << layer << "/" << n;
  }
  for (const auto& e : fs::directory_iterator(source_dir / "src/qsdem"))
    EXPECT_TRUE(e.is_directory() && std::count(layers.begin(), layers.end(), e.path().filename().string()))
        << "src/qsdem/ holds a file or folder that is not a layer's: " << e.path().filename().string();
}

// The [[phase]] list of docs/config.md that writes the default protocol as phases reads as the
// protocol the parser makes of [compaction] and [triaxial].
TEST(Docs, DefaultProtocolWrittenAsPhasesIsTheDefaultProtocol) {
  const std::string phases = toml_block_after(source_dir / "docs/config.md", "### `[[phase]]`: a protocol as a list of phases (SPEC 8)");
  ASSERT_FALSE(phases.empty());
  const std::string text = read_text(source_dir / "examples/spheres-A-small.toml");
  // The example without its protocol tables ([compaction], [triaxial], [damping]), with the phases.
  std::string head;
  bool skip = false;
  for (const std::string& line : lines_of(text)) {
    if (line.rfind("[", 0) == 0) skip = line == "[compaction]" || line == "[triaxial]" || line == "[damping]";
    if (!skip) head += line + "\n";
  }
  const qsdem::Params listed = qsdem::parse_case(head + phases, "docs/config.md (phases)");
  const qsdem::Params plain = qsdem::parse_case(text, "examples/spheres-A-small.toml");
  ASSERT_TRUE(listed.phase_list);
  ASSERT_EQ(listed.protocol.size(), plain.protocol.size());
  for (std::size_t k = 0; k < plain.protocol.size(); ++k)
    EXPECT_EQ(qsdem::to_json(listed.protocol[k]), qsdem::to_json(plain.protocol[k])) << "phase " << k;
}

namespace {

// The fields of each record of a CSV text (RFC 4180: a quoted field may hold commas, doubled
// quotes and line breaks; a CR before the LF is not part of the field), with the line each begins on.
struct CsvRecord {
  std::size_t line = 0, fields = 0;
};
std::vector<CsvRecord> csv_records(const std::string& text) {
  std::vector<CsvRecord> records;
  std::size_t line = 1;
  bool quoted = false, at_start = true;
  CsvRecord r{1, 1};
  for (std::size_t k = 0; k < text.size(); ++k) {
    const char c = text[k];
    if (c == '\n') ++line;
    if (quoted) {
      if (c == '"' && k + 1 < text.size() && text[k + 1] == '"')
        ++k;
      else if (c == '"')
        quoted = false;
    } else if (c == '"') {
      quoted = true;
    } else if (c == ',') {
      ++r.fields;
    } else if (c == '\n') {
      records.push_back(r);
      r = {line, 1};
      at_start = true;
      continue;
    }
    if (c != '\r') at_start = false;
  }
  if (!at_start) records.push_back(r);  // a last record without its line break
  return records;
}

}  // namespace

// A strict CSV reader maps a row's fields to the header's names: a row wider than its header (a run
// resumed by a build that wrote more columns) shifts or drops values without a word. Every CSV file
// of the source tree (build trees and hidden directories aside) is rectangular.
TEST(Docs, EveryCsvFileOfTheRepositoryIsRectangular) {
  std::size_t files = 0;
  for (auto it = fs::recursive_directory_iterator(source_dir); it != fs::recursive_directory_iterator(); ++it) {
    const fs::path& p = it->path();
    if (it->is_directory() && (p.filename().string().front() == '.' || fs::exists(p / "CMakeCache.txt"))) {
      it.disable_recursion_pending();
      continue;
    }
    if (!it->is_regular_file() || p.extension() != ".csv") continue;
    ++files;
    const std::vector<CsvRecord> records = csv_records(read_text(p));
    ASSERT_FALSE(records.empty()) << fs::relative(p, source_dir).string() << " is empty";
    std::size_t wrong = 0;
    for (const CsvRecord& r : records)
      if (r.fields != records[0].fields && wrong++ == 0)
        ADD_FAILURE() << fs::relative(p, source_dir).string() << ":" << r.line << ": " << r.fields
                      << " fields under a header of " << records[0].fields;
    EXPECT_EQ(wrong, 0u) << fs::relative(p, source_dir).string() << ": rows not as wide as the header";
  }
  EXPECT_GE(files, 100u) << "the results' CSV files were not found";
}

// The reader counts as a strict one does: quoted commas and line breaks are inside a field.
TEST(Docs, CsvRecordsAreCountedAsAStrictReaderCounts) {
  const std::vector<CsvRecord> r = csv_records("a,b,c\r\n1,\"x, \"\"y\"\"\n z\",3\n4,5\n");
  ASSERT_EQ(r.size(), 3u);
  EXPECT_EQ(r[0].fields, 3u);
  EXPECT_EQ(r[1].fields, 3u);
  EXPECT_EQ(r[2].line, 4u);
  EXPECT_EQ(r[2].fields, 2u);
}
