#include "common/regular_file.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>

#include "common/atomic_file.hpp"  // errno_text

namespace posecal {

std::string read_regular_file(const std::string& path, size_t max_bytes, const std::string& what,
                              ErrorCode if_missing) {
  const std::string named = what + " '" + path + "'";
  // O_NONBLOCK: opening a FIFO without a writer would otherwise wait for one.
  const int fd = ::open(path.c_str(), O_RDONLY | O_NONBLOCK | O_CLOEXEC | O_NOCTTY);
  if (fd < 0) {
    const int err = errno;
    if (err == ENOENT && if_missing != ErrorCode::kIo)
      throw Error(if_missing, named + " does not exist");
    throw Error(ErrorCode::kIo, "cannot open " + named + ": " + errno_text(err));
  }
  struct Closer {
    int fd;
    ~Closer() { ::close(fd); }
  } closer{fd};
  struct stat st {};
  if (::fstat(fd, &st) != 0)
    throw Error(ErrorCode::kIo, "cannot inspect " + named + ": " + errno_text(errno));
  if (!S_ISREG(st.st_mode)) throw Error(ErrorCode::kInvalidArgument, named + ": not a regular file");
  const std::string limit = "the limit is " + std::to_string(max_bytes) + " bytes";
  if (static_cast<unsigned long long>(st.st_size) > max_bytes) {
    throw Error(ErrorCode::kInvalidArgument,
                named + ": " + std::to_string(st.st_size) + " bytes; " + limit);
  }
  std::string text;
  text.reserve(static_cast<size_t>(st.st_size));
  char buf[65536];
  while (true) {
    const ssize_t n = ::read(fd, buf, sizeof buf);
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) throw Error(ErrorCode::kIo, "cannot read " + named + ": " + errno_text(errno));
    if (n == 0) break;
    if (text.size() + static_cast<size_t>(n) > max_bytes)
      throw Error(ErrorCode::kInvalidArgument, named + ": it grew while read; " + limit);
    text.append(buf, static_cast<size_t>(n));
  }
  return text;
}

}  // namespace posecal
