// The one system-call seam of the V4L2 backend.
//
// Everything the backend does to a video device goes through V4l2Io: open/close of the node,
// ioctl, mmap/munmap of the driver's buffers, poll and read. The methods have the kernel's
// semantics exactly: they return -1 (MAP_FAILED for mmap) and set errno on failure. The system
// implementation forwards to libc; tests substitute a userspace emulator of a UVC camera
// (tests/v4l2/uvc_emulator.hpp), so the code above the seam is the code that runs on a camera.
//
// Not behind the seam: sysfs and /dev are read with ordinary file calls (their roots are
// injectable, see V4l2BackendOptions), and USB hot-plug has its own seam (UsbEventSource).
#pragma once

#include <poll.h>
#include <sys/types.h>

#include <cstddef>
#include <memory>

namespace posecal {

class V4l2Io {
 public:
  virtual ~V4l2Io() = default;
  virtual int open(const char* path, int flags) = 0;
  virtual int close(int fd) = 0;
  virtual int ioctl(int fd, unsigned long request, void* arg) = 0;
  virtual void* mmap(void* addr, size_t length, int prot, int flags, int fd, off_t offset) = 0;
  virtual int munmap(void* addr, size_t length) = 0;
  virtual int poll(struct pollfd* fds, nfds_t nfds, int timeout_ms) = 0;
  virtual ssize_t read(int fd, void* buf, size_t count) = 0;
};

// Forwards to the kernel (::open, ::ioctl, ...). Stateless; one instance may be shared.
std::shared_ptr<V4l2Io> make_system_v4l2_io();

}  // namespace posecal
