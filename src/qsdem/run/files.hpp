// The files qsdem writes, made safe where others may have left names before it: a shared scratch
// directory or an unpacked archive of results can hold symbolic links named like the files a run
// or a study writes. Every file and directory qsdem writes is opened or created here, never
// through a link (CWE-59); and every text it writes into JSON is UTF-8.
#pragma once
#include <fcntl.h>

#include <cstddef>
#include <filesystem>
#include <optional>
#include <string>
#include <string_view>

#include <nlohmann/json.hpp>

namespace qsdem {

// Creates `path` as a new, empty regular file open for `flags` (O_WRONLY or O_RDWR, and e.g.
// O_APPEND): the file or link the name held is removed first, then the name is created with
// O_CREAT | O_EXCL | O_NOFOLLOW, so a link planted under it is never followed. Returns the
// descriptor (close-on-exec), or -1 with errno set (EISDIR: the name is a directory).
int create_file(const std::filesystem::path& path, int flags = O_WRONLY);

// Opens the regular file `path` for `flags`, creating it when absent and keeping it when present
// (a log appended to, a lock file); a symbolic link under the name is removed and a file created
// instead. -1 with errno set; EINVAL when the name is something else than a regular file (a FIFO,
// a device, a directory).
int open_file(const std::filesystem::path& path, int flags);

// Opens the existing regular file `path` for `flags` (O_RDONLY, O_RDWR), never through a link:
// -1 with errno ELOOP when the name is a symbolic link, EINVAL when it is not a regular file,
// ENOENT when there is none.
int open_regular_file(const std::filesystem::path& path, int flags);

// The reason, for a message, of an errno left by the functions above.
std::string file_error(int err);

// The bytes of the regular file `path`, read by open_regular_file; none when it cannot be (absent,
// a link, a FIFO, unreadable: `err`, when given, receives the errno).
std::optional<std::string> read_regular_file(const std::filesystem::path& path, int* err = nullptr);

// Creates the directory `base / relative` and those between, none of which may be a symbolic link
// or something else than a directory (InputError naming it): what is written below `base` stays
// below it. `base` itself (a user's --out) may be anything that leads to a directory.
void make_directories(const std::filesystem::path& base, const std::filesystem::path& relative);

// The offset of the first byte of `text` that does not belong to valid UTF-8 (an overlong form, a
// surrogate or a code point above U+10FFFF included), or npos when it is all valid.
std::size_t invalid_utf8_at(std::string_view text);

// Refuses (InputError) a name or text that qsdem would write into a JSON file and that is not
// UTF-8, before any work. `what` names it ("--out", "the case file's path"); the message shows the
// text with its bytes outside UTF-8 as \xHH.
void require_utf8(std::string_view text, const std::string& what);

// j.dump(indent), with any bytes that are not UTF-8 in its strings replaced by U+FFFD instead of
// an exception: the last defence for a text that came from outside (a child's log, a checkpoint
// of an older engine), which the checks on input should already have refused.
template <class Json>
std::string json_text(const Json& j, int indent = 2) {
  return j.dump(indent, ' ', false, Json::error_handler_t::replace);
}

}  // namespace qsdem
