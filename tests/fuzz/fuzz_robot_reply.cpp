// libFuzzer target: the robot stdio protocol's input side (plugin/cli/robot_protocol.cpp): the
// controller's bytes split into lines by LineReader (poll + read on a descriptor, here a memfd
// holding the input) and each line parsed by parse_reply ('reached', 'skip', 'abort', or a JSON
// object).
//
// Besides "no crash, no sanitizer report": LineReader returns every byte of the input but the
// '\n' separators and a '\r' before them, and ends with kEof, never a timeout, on a file.
#include <sys/mman.h>
#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>

#include "robot_protocol.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  const int fd = ::memfd_create("posecal_fuzz_robot", MFD_CLOEXEC);
  if (fd < 0) std::abort();
  size_t written = 0;
  while (written < size) {
    const ssize_t n = ::write(fd, data + written, size - written);
    if (n <= 0) std::abort();
    written += static_cast<size_t>(n);
  }
  if (::lseek(fd, 0, SEEK_SET) != 0) std::abort();

  posecal::cli::LineReader reader(fd);
  size_t bytes = 0;
  int lines = 0;
  while (true) {
    std::string line;
    const auto r = reader.next(&line, 1000);
    if (r == posecal::cli::LineReader::Result::kTimeout) std::abort();
    if (r == posecal::cli::LineReader::Result::kEof) break;
    if (line.find('\n') != std::string::npos) std::abort();
    bytes += line.size();
    ++lines;
    (void)posecal::cli::parse_reply(line);
  }
  ::close(fd);
  // Every byte is in a line except one '\n' per line and at most one '\r' before each.
  if (bytes > size || bytes + 2 * static_cast<size_t>(lines) < size) std::abort();
  return 0;
}
