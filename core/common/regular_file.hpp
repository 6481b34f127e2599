// Reading a whole input file without blocking and without unbounded memory.
//
// Model files, quality specifications and session journals are read whole before they are
// parsed. A path can name a FIFO (opening it waits for a writer), a device (/dev/zero never
// ends) or a file that grows while it is read; read_regular_file refuses all of these, and checks
// the file's kind and size on the descriptor it reads (fstat), not by name before opening.
#pragma once

#include <cstddef>
#include <string>

#include "common/error.hpp"

namespace posecal {

// The whole of `path`, a regular file of at most `max_bytes` bytes. `what` names the file in
// errors ("camera model file", "quality spec", "journal"):
//  - the path does not exist: Error(if_missing): "<what> '<path>' does not exist" when
//    if_missing is not kIo, else "cannot open <what> '<path>': No such file or directory (ENOENT)";
//  - it cannot be opened, inspected or read: Error(kIo) naming the cause (errno_text);
//  - it is not a regular file, or larger than max_bytes (also when it grows while read):
//    Error(kInvalidArgument) "<what> '<path>': not a regular file" / "...: N bytes; the limit is
//    M bytes".
std::string read_regular_file(const std::string& path, size_t max_bytes, const std::string& what,
                              ErrorCode if_missing = ErrorCode::kIo);

}  // namespace posecal
