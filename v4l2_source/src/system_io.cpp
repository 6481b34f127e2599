// The seam's kernel side: plain forwarding, errno untouched.
#include <fcntl.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/mman.h>
#include <unistd.h>

#include "posecal/v4l2_io.hpp"

namespace posecal {

namespace {

class SystemV4l2Io final : public V4l2Io {
 public:
  int open(const char* path, int flags) override { return ::open(path, flags | O_CLOEXEC); }
  int close(int fd) override { return ::close(fd); }
  int ioctl(int fd, unsigned long request, void* arg) override { return ::ioctl(fd, request, arg); }
  void* mmap(void* addr, size_t length, int prot, int flags, int fd, off_t offset) override {
    return ::mmap(addr, length, prot, flags, fd, offset);
  }
  int munmap(void* addr, size_t length) override { return ::munmap(addr, length); }
  int poll(struct pollfd* fds, nfds_t nfds, int timeout_ms) override {
    return ::poll(fds, nfds, timeout_ms);
  }
  ssize_t read(int fd, void* buf, size_t count) override { return ::read(fd, buf, count); }
};

}  // namespace

std::shared_ptr<V4l2Io> make_system_v4l2_io() { return std::make_shared<SystemV4l2Io>(); }

}  // namespace posecal
