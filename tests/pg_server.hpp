// A real PostgreSQL server for the tests of PostgreSQL records (Debian's `postgresql` package):
// initdb in a temporary directory, pg_ctl on 127.0.0.1 and a free port, stopped and removed at
// the end. initdb refuses root: as root (CI), the server runs as the `postgres` user the package
// creates. fsync is off: these tests prove the SQL, not the server's durability. A reaper process
// stops the server and removes the directory when the test process ends in any way, a crash or
// a kill -9 included (the server is a daemon of its own and would otherwise keep running).
#pragma once

#include <fcntl.h>
#include <gtest/gtest.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>

namespace posecal::testing_pg {

// The newest installed server's binaries (/usr/lib/postgresql/<version>/bin), or "".
inline std::string pg_bin_dir() {
  namespace fs = std::filesystem;
  std::string best;
  int best_version = -1;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator("/usr/lib/postgresql", ec)) {
    const int v = std::atoi(e.path().filename().c_str());
    if (v > best_version && fs::exists(e.path() / "bin" / "initdb")) {
      best_version = v;
      best = (e.path() / "bin").string();
    }
  }
  return best;
}

// 127.0.0.1:port (0: any free port).
inline sockaddr_in loopback(int port) {
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_port = htons(static_cast<uint16_t>(port));
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  return a;
}

// Whether a server accepts connections on 127.0.0.1:port.
inline bool accepting(int port) {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  sockaddr_in a = loopback(port);
  const bool ok = ::connect(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0;
  ::close(fd);
  return ok;
}

inline int free_port() {
  const int fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
  sockaddr_in a = loopback(0);
  socklen_t len = sizeof a;
  int port = 0;
  if (::bind(fd, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0 &&
      ::getsockname(fd, reinterpret_cast<sockaddr*>(&a), &len) == 0) {
    port = ntohs(a.sin_port);
  }
  ::close(fd);
  return port;
}

class PgServer {
 public:
  PgServer() {
    namespace fs = std::filesystem;
    bin_ = pg_bin_dir();
    if (bin_.empty()) {
      error_ =
          "no PostgreSQL server installed (/usr/lib/postgresql/*/bin/initdb); install "
          "Debian's postgresql package (.ci/test-packages)";
      return;
    }
    dir_ = (fs::path(::testing::TempDir()) / ("posecal_pg_" + std::to_string(::getpid()))).string();
    fs::remove_all(dir_);
    fs::create_directories(dir_);
    as_user_ = ::geteuid() == 0 ? "runuser -u postgres -- " : "";
    if (::geteuid() == 0 && std::system(("chown postgres " + dir_).c_str()) != 0) {
      error_ = "cannot give " + dir_ + " to the postgres user";
      return;
    }
    start_reaper();
    if (!run(bin_ + "/initdb -D " + data() + " -A trust -U posecal -E UTF8 --no-locale " +
             "--no-sync > " + dir_ + "/initdb.log 2>&1")) {
      error_ = "initdb failed: " + read(dir_ + "/initdb.log");
      return;
    }
    for (int attempt = 0; attempt < 5 && !running_; ++attempt) {
      port_ = free_port();
      running_ = start();
    }
    if (!running_) error_ = "pg_ctl start failed: " + read(dir_ + "/server.log");
  }
  ~PgServer() {
    if (reaper_ > 0) {
      ::close(reaper_pipe_);  // the reaper stops the server and removes the directory
      int status = 0;
      while (::waitpid(reaper_, &status, 0) < 0 && errno == EINTR) {
      }
      return;
    }
    stop();
    if (!dir_.empty()) {
      std::error_code ec;
      std::filesystem::remove_all(dir_, ec);
    }
  }
  PgServer(const PgServer&) = delete;
  PgServer& operator=(const PgServer&) = delete;

  // Why the server is not running ("" if it is).
  const std::string& error() const { return error_; }
  int port() const { return port_; }
  const std::string& directory() const { return dir_; }

  std::string url(const std::string& database) const {
    return "postgresql://posecal@127.0.0.1:" + std::to_string(port_) + "/" + database;
  }
  // A new, empty database; its URL.
  std::string create_database(const std::string& name) const {
    const std::string psql = bin_ + "/psql -X -q -h 127.0.0.1 -p " + std::to_string(port_) +
                             " -U posecal -d postgres -c ";
    const int rc1 =
        std::system((psql + "'DROP DATABASE IF EXISTS \"" + name + "\"' > /dev/null 2>&1").c_str());
    const int rc2 =
        std::system((psql + "'CREATE DATABASE \"" + name + "\"' > /dev/null 2>&1").c_str());
    (void)rc1;
    EXPECT_EQ(rc2, 0) << "CREATE DATABASE " << name;
    return url(name);
  }
  // SQL through psql (for set-ups the store itself would refuse to make); true on success.
  bool psql(const std::string& database, const std::string& sql) const {
    const std::string file = dir_ + "/statement.sql";
    std::ofstream(file) << sql << ";\n";
    return std::system((bin_ + "/psql -X -q -v ON_ERROR_STOP=1 -h 127.0.0.1 -p " +
                        std::to_string(port_) + " -U posecal -d " + database + " -f " + file +
                        " > /dev/null 2>&1")
                           .c_str()) == 0;
  }

  // Stops the server at once (as a crash or a pulled cable would: no clean shutdown).
  void stop() {
    if (!running_) return;
    run(bin_ + "/pg_ctl -D " + data() + " -m immediate -w -t 30 stop > /dev/null 2>&1");
    running_ = false;
  }
  // Starts it again on the same port.
  bool start() {
    running_ = run(bin_ + "/pg_ctl -D " + data() + " -l " + dir_ + "/server.log -w -t 30 -o '-p " +
                   std::to_string(port_) + " -k " + dir_ +
                   " -c listen_addresses=127.0.0.1 -c fsync=off' start > /dev/null 2>&1");
    return running_;
  }

 private:
  // A child in a session of its own (a kill of the test's process group does not reach it) that
  // waits for the end of a pipe whose only writer is this process (close-on-exec, so neither
  // the shells of run() nor the server inherit it), then stops the server and removes the
  // directory. The command is made before fork(): the child only reads, and execs a shell.
  void start_reaper() {
    const std::string command = as_user_ + bin_ + "/pg_ctl -D " + data() +
                                " -m immediate -w -t 30 stop > /dev/null 2>&1; rm -rf " + dir_;
    int fds[2];
    if (::pipe2(fds, O_CLOEXEC) != 0) return;
    reaper_ = ::fork();
    if (reaper_ == 0) {
      // Nothing of the test's but the pipe's end: an inherited socket or file would stay open
      // for as long as the test runs.
      if (fds[0] > 3) ::close_range(3, static_cast<unsigned>(fds[0]) - 1, 0);
      ::close_range(static_cast<unsigned>(fds[0]) + 1, ~0U, 0);
      ::setsid();
      char c;
      while (::read(fds[0], &c, 1) != 0 && errno == EINTR) {
      }
      ::execl("/bin/sh", "sh", "-c", command.c_str(), static_cast<char*>(nullptr));
      ::_exit(127);
    }
    ::close(fds[0]);
    if (reaper_ < 0) {
      ::close(fds[1]);
      return;
    }
    reaper_pipe_ = fds[1];
  }
  std::string data() const { return dir_ + "/data"; }
  bool run(const std::string& command) const {
    return std::system((as_user_ + command).c_str()) == 0;
  }
  static std::string read(const std::string& path) {
    std::ifstream in(path);
    std::stringstream s;
    s << in.rdbuf();
    return s.str();
  }

  std::string bin_, dir_, as_user_, error_;
  int port_ = 0;
  bool running_ = false;
  pid_t reaper_ = -1;
  int reaper_pipe_ = -1;
};

}  // namespace posecal::testing_pg
