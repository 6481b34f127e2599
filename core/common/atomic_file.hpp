// Files that are either the old version or the new one, never half of either.
//
// Every file posecal writes (calibration results, summaries, boards, grabbed frames) goes
// through write_file_atomic: the bytes go to a temporary file in the same directory, every
// write, the fsync and the close are checked, and the temporary file is renamed over the target
// (then the directory is synced). A failure (ENOSPC, EACCES, EROFS, a directory at the path)
// leaves the previous file untouched and no temporary behind. A symbolic link at the path is
// replaced by the new file, not followed: writing "out.yml" never overwrites what a link there
// points to.
//
// Dependency-free (POSIX and the standard library only), so the command line compiles it in
// beside the C ABI, as it does the percent-encoder.
#pragma once

#include <string>
#include <string_view>

namespace posecal {

// Writes `bytes` to `path` atomically. Returns true on success; otherwise false with *error set
// to a message that names the path, the step and the cause, e.g.
// "cannot write 'out/cal.yml': No space left on device (ENOSPC)".
bool write_file_atomic(const std::string& path, std::string_view bytes, std::string* error);

// Checks, before any work is done, that `path` can later be written by write_file_atomic: its
// directory exists and accepts a new file, and the path is not a directory. Creates and removes
// a probe file. Returns false with *error naming the cause otherwise.
bool check_output_path(const std::string& path, std::string* error);

// "No space left on device (ENOSPC)": strerror with the errno's symbolic name.
std::string errno_text(int err);

}  // namespace posecal
