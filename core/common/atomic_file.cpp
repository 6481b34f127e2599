#include "common/atomic_file.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <fstream>

namespace posecal {

namespace {

std::string parent_dir(const std::string& path) {
  const size_t slash = path.find_last_of('/');
  if (slash == std::string::npos) return ".";
  if (slash == 0) return "/";
  return path.substr(0, slash);
}

std::string base_name(const std::string& path) {
  const size_t slash = path.find_last_of('/');
  return slash == std::string::npos ? path : path.substr(slash + 1);
}

// The process's umask without changing it (umask(2) sets as it reads, which races with other
// threads): /proc/self/status has it since Linux 4.7.
mode_t current_umask() {
  std::ifstream status("/proc/self/status");
  std::string line;
  while (std::getline(status, line)) {
    if (line.rfind("Umask:", 0) == 0)
      return static_cast<mode_t>(std::stoul(line.substr(6), nullptr, 8));
  }
  return 022;
}

// The mode the new file gets: the old file's if a regular file is being replaced, else what
// open(O_CREAT, 0666) would give.
mode_t new_file_mode(const std::string& path) {
  struct stat st {};
  if (::lstat(path.c_str(), &st) == 0 && S_ISREG(st.st_mode)) return st.st_mode & 07777;
  return 0666 & ~current_umask();
}

bool fail(std::string* error, const std::string& path, const std::string& step, int err) {
  if (error) *error = "cannot write '" + path + "': " + step + errno_text(err);
  return false;
}

bool write_all(int fd, std::string_view bytes, int* err) {
  size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t n = ::write(fd, bytes.data() + done, bytes.size() - done);
    if (n < 0) {
      if (errno == EINTR) continue;
      *err = errno;
      return false;
    }
    done += static_cast<size_t>(n);
  }
  return true;
}

// Fills the temporary file and closes it; false with *err and *step on the first failure.
bool fill_temporary(int fd, std::string_view bytes, mode_t mode, int* err, const char** step) {
  bool ok = true;
  if (::fchmod(fd, mode) != 0) {
    *err = errno, *step = "setting its mode: ", ok = false;
  } else if (!write_all(fd, bytes, err)) {
    *step = "", ok = false;
  } else if (::fsync(fd) != 0) {
    *err = errno, *step = "flushing it to disk: ", ok = false;
  }
  if (::close(fd) != 0 && ok) {  // NFS and some FUSE file systems report write errors here
    *err = errno, *step = "", ok = false;
  }
  return ok;
}

bool is_directory(const std::string& path) {
  struct stat st {};
  return ::stat(path.c_str(), &st) == 0 && S_ISDIR(st.st_mode);
}

}  // namespace

std::string errno_text(int err) {
  char buf[256];
  const char* text = ::strerror_r(err, buf, sizeof buf);  // the GNU variant returns the text
  const char* name = ::strerrorname_np(err);
  return std::string(text) + (name ? " (" + std::string(name) + ")" : std::string());
}

bool write_file_atomic(const std::string& path, std::string_view bytes, std::string* error) {
  if (path.empty() || path.back() == '/') return fail(error, path, "it is a directory: ", EISDIR);
  if (is_directory(path)) return fail(error, path, "it is a directory: ", EISDIR);
  const std::string dir = parent_dir(path);
  std::string tmp = dir + "/." + base_name(path) + ".tmp-XXXXXX";
  const mode_t mode = new_file_mode(path);
  const int fd = ::mkostemp(tmp.data(), O_CLOEXEC);
  if (fd < 0) return fail(error, path, "creating a file in '" + dir + "': ", errno);
  int err = 0;
  const char* step = "";
  if (!fill_temporary(fd, bytes, mode, &err, &step)) {
    ::unlink(tmp.c_str());
    return fail(error, path, step, err);
  }
  // rename() replaces a symbolic link at `path` itself; its target is left alone.
  if (::rename(tmp.c_str(), path.c_str()) != 0) {
    err = errno;
    ::unlink(tmp.c_str());
    return fail(error, path, "", err);
  }
  // The rename is durable once the directory is: without this a power cut can bring back the
  // old name (or none).
  const int dfd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dfd >= 0) {
    const int rc = ::fsync(dfd);
    err = errno;
    ::close(dfd);
    // EINVAL: the file system cannot sync directories (the data is already on disk).
    if (rc != 0 && err != EINVAL) return fail(error, path, "syncing its directory: ", err);
  }
  return true;
}

bool check_output_path(const std::string& path, std::string* error) {
  auto bad = [&](const std::string& why) {
    if (error) *error = "cannot write '" + path + "': " + why;
    return false;
  };
  if (path.empty()) return bad("the path is empty");
  if (path.back() == '/' || is_directory(path)) return bad("it is a directory");
  const std::string dir = parent_dir(path);
  struct stat st {};
  if (::stat(dir.c_str(), &st) != 0) return bad("directory '" + dir + "': " + errno_text(errno));
  if (!S_ISDIR(st.st_mode)) return bad("'" + dir + "' is not a directory");
  std::string probe = dir + "/." + base_name(path) + ".probe-XXXXXX";
  const int fd = ::mkostemp(probe.data(), O_CLOEXEC);
  if (fd < 0) return bad("cannot create a file in '" + dir + "': " + errno_text(errno));
  ::close(fd);
  ::unlink(probe.c_str());
  return true;
}

}  // namespace posecal
