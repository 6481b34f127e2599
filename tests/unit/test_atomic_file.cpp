// write_file_atomic: the old file or the new one, never half of either; errors name the cause.
#include <gtest/gtest.h>
#include <signal.h>
#include <sys/resource.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>

#include "common/atomic_file.hpp"

namespace fs = std::filesystem;

namespace {

fs::path fresh_dir(const std::string& name) {
  const fs::path dir = fs::path(testing::TempDir()) / ("posecal_atomic_" + name);
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

std::string read_all(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

void put(const fs::path& p, const std::string& text) { std::ofstream(p, std::ios::binary) << text; }

// Names in `dir` other than `keep`: temporaries left behind.
int strays(const fs::path& dir, const std::set<std::string>& keep) {
  int n = 0;
  for (const auto& e : fs::directory_iterator(dir)) n += !keep.count(e.path().filename().string());
  return n;
}

}  // namespace

TEST(AtomicFile, WritesAndReplacesLeavingNoTemporary) {
  const fs::path dir = fresh_dir("replace");
  const fs::path f = dir / "cal.yml";
  std::string error;
  ASSERT_TRUE(posecal::write_file_atomic(f.string(), "first", &error)) << error;
  EXPECT_EQ(read_all(f), "first");
  ASSERT_TRUE(posecal::write_file_atomic(f.string(), "second, longer", &error)) << error;
  EXPECT_EQ(read_all(f), "second, longer");
  ASSERT_TRUE(posecal::write_file_atomic(f.string(), "", &error)) << error;
  EXPECT_EQ(read_all(f), "");
  EXPECT_EQ(strays(dir, {"cal.yml"}), 0);
}

TEST(AtomicFile, KeepsTheModeOfTheFileItReplaces) {
  const fs::path dir = fresh_dir("mode");
  const fs::path f = dir / "cal.yml";
  put(f, "old");
  ASSERT_EQ(::chmod(f.c_str(), 0640), 0);
  std::string error;
  ASSERT_TRUE(posecal::write_file_atomic(f.string(), "new", &error)) << error;
  struct stat st {};
  ASSERT_EQ(::stat(f.c_str(), &st), 0);
  EXPECT_EQ(st.st_mode & 07777, 0640u);
}

TEST(AtomicFile, ReplacesASymlinkInsteadOfWritingThroughIt) {
  const fs::path dir = fresh_dir("symlink");
  put(dir / "precious.txt", "keep me");
  fs::create_symlink(dir / "precious.txt", dir / "out.yml");
  std::string error;
  ASSERT_TRUE(posecal::write_file_atomic((dir / "out.yml").string(), "result", &error)) << error;
  EXPECT_FALSE(fs::is_symlink(dir / "out.yml"));
  EXPECT_EQ(read_all(dir / "out.yml"), "result");
  EXPECT_EQ(read_all(dir / "precious.txt"), "keep me");
}

TEST(AtomicFile, RefusesADirectoryOrAMissingFolderNamingTheCause) {
  const fs::path dir = fresh_dir("refuse");
  fs::create_directories(dir / "sub");
  std::string error;
  EXPECT_FALSE(posecal::write_file_atomic((dir / "sub").string(), "x", &error));
  EXPECT_NE(error.find("directory"), std::string::npos) << error;
  EXPECT_TRUE(fs::is_directory(dir / "sub"));
  EXPECT_FALSE(posecal::write_file_atomic((dir / "missing" / "x.yml").string(), "x", &error));
  EXPECT_NE(error.find("ENOENT"), std::string::npos) << error;
  EXPECT_NE(error.find("missing"), std::string::npos) << error;
}

// A write that fails half-way (here: the file-size limit, EFBIG, as a full disk gives ENOSPC)
// leaves the previous file exactly as it was and no temporary behind.
TEST(AtomicFile, AFailedWriteKeepsThePreviousFile) {
  const fs::path dir = fresh_dir("efbig");
  const fs::path f = dir / "cal.yml";
  put(f, "previous calibration");
  const pid_t pid = ::fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    ::signal(SIGXFSZ, SIG_IGN);
    const rlimit lim{64, 64};
    ::setrlimit(RLIMIT_FSIZE, &lim);
    std::string error;
    const bool ok = posecal::write_file_atomic(f.string(), std::string(4096, 'x'), &error);
    ::_exit(!ok && error.find("EFBIG") != std::string::npos ? 0 : 1);
  }
  int status = 0;
  ASSERT_EQ(::waitpid(pid, &status, 0), pid);
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 0) << "the write did not fail with EFBIG";
  EXPECT_EQ(read_all(f), "previous calibration");
  EXPECT_EQ(strays(dir, {"cal.yml"}), 0);
}

TEST(AtomicFile, OutputPathIsCheckedBeforeAnyWork) {
  const fs::path dir = fresh_dir("check");
  fs::create_directories(dir / "sub");
  std::string error;
  EXPECT_TRUE(posecal::check_output_path((dir / "new.yml").string(), &error)) << error;
  EXPECT_FALSE(fs::exists(dir / "new.yml"));
  EXPECT_EQ(strays(dir, {"sub"}), 0);
  EXPECT_FALSE(posecal::check_output_path((dir / "sub").string(), &error));
  EXPECT_NE(error.find("directory"), std::string::npos) << error;
  EXPECT_FALSE(posecal::check_output_path((dir / "nope" / "x.yml").string(), &error));
  EXPECT_NE(error.find("nope"), std::string::npos) << error;
  put(dir / "file", "");
  EXPECT_FALSE(posecal::check_output_path((dir / "file" / "x.yml").string(), &error));
  EXPECT_NE(error.find("not a directory"), std::string::npos) << error;
}
