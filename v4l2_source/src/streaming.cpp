// V4l2Camera: streaming (REQBUFS, mmap, QBUF/DQBUF, STREAMON/STREAMOFF, poll) or read() I/O.
#include <fcntl.h>
#include <sys/mman.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <numeric>
#include <optional>

#include "common/clock.hpp"

#include "camera_internal.hpp"

namespace posecal::v4l2 {

void V4l2CameraImpl::release_buffers(bool device_alive) {
  if (device_alive && stream_on_) {
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    ioctl(VIDIOC_STREAMOFF, &type);
  }
  stream_on_ = false;
  for (const Mapping& m : buffers_) io_->munmap(m.addr, m.length);
  buffers_.clear();
  if (device_alive && buffers_allocated_) {
    v4l2_requestbuffers req{};
    req.count = 0;
    req.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    req.memory = V4L2_MEMORY_MMAP;
    ioctl(VIDIOC_REQBUFS, &req);
  }
  buffers_allocated_ = false;
  read_buffer_.clear();
  read_buffer_.shrink_to_fit();
}

void V4l2CameraImpl::do_start() {
  last_sequence_.reset();
  if (read_io_) {
    // read() I/O: capture starts with the first read() (or poll()).
    read_buffer_.assign(std::max<size_t>(fmt_.sizeimage, 1), 0);
    read_frames_ = 0;
    return;
  }
  const auto failed = [&](const std::string& what, int err) {
    release_buffers(!is_gone(err));
    fail(what, err);
  };
  v4l2_requestbuffers req{};
  req.count = static_cast<uint32_t>(queue_depth_);
  req.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  req.memory = V4L2_MEMORY_MMAP;
  if (const int err = ioctl(VIDIOC_REQBUFS, &req)) {
    if (err == EBUSY) {
      throw Error(
          ErrorCode::kDevice,
          who() + ": VIDIOC_REQBUFS: device busy (another application is streaming from it)");
    }
    fail("VIDIOC_REQBUFS", err);
  }
  buffers_allocated_ = req.count > 0;
  if (req.count < static_cast<uint32_t>(kMinBuffers)) {
    release_buffers(true);
    throw Error(ErrorCode::kDevice, who() + ": the driver granted only " +
                                        std::to_string(req.count) +
                                        " buffers (out of buffer memory?)");
  }
  buffers_.reserve(req.count);
  for (uint32_t i = 0; i < req.count; ++i) {
    v4l2_buffer b{};
    b.index = i;
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    if (const int err = ioctl(VIDIOC_QUERYBUF, &b)) failed("VIDIOC_QUERYBUF", err);
    void* addr = io_->mmap(nullptr, b.length, PROT_READ | PROT_WRITE, MAP_SHARED, fd_,
                           static_cast<off_t>(b.m.offset));
    if (addr == MAP_FAILED) failed("mmap of buffer " + std::to_string(i), errno);
    buffers_.push_back({addr, b.length});
  }
  for (uint32_t i = 0; i < buffers_.size(); ++i) {
    v4l2_buffer b{};
    b.index = i;
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    if (const int err = ioctl(VIDIOC_QBUF, &b)) failed("VIDIOC_QBUF", err);
  }
  int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  stream_on_ = true;  // so that a failure below is undone with STREAMOFF as well
  if (const int err = ioctl(VIDIOC_STREAMON, &type)) failed("VIDIOC_STREAMON", err);
}

void V4l2CameraImpl::reopen_for_read_io() {
  // A read() capture only stops when the file is closed (and holds the queue until then, so
  // S_FMT would fail with EBUSY): close and open the node again.
  io_->close(fd_);
  fd_ = io_->open(dev_path_.c_str(), O_RDWR | O_NONBLOCK);
  if (fd_ < 0) {
    const int err = errno;
    fd_ = -1;
    disconnect(err, "reopening after read() capture");
    if (err != ENOENT && !is_gone(err)) {
      throw Error(ErrorCode::kDevice,
                  who() + ": cannot reopen " + dev_path_ + ": " + errno_text(err));
    }
  }
}

void V4l2CameraImpl::do_stop() {
  release_buffers(true);
  if (read_io_) reopen_for_read_io();
}

bool V4l2CameraImpl::deliver(const uint8_t* data, size_t bytes, uint64_t frame_id,
                             int64_t timestamp_ns, Frame* frame) {
  const PixelFormat pf = pixel_format_of_fourcc(fmt_.pixelformat);
  cv::Mat image;
  try {
    image = convert_to_engine(pf, data, bytes, static_cast<int>(fmt_.width),
                              static_cast<int>(fmt_.height),
                              pf == PixelFormat::kMJPEG ? 0 : fmt_.bytesperline);
  } catch (const Error& e) {
    if (e.code() != ErrorCode::kInvalidArgument) throw;
    image.release();  // short buffer: an incomplete frame
  }
  if (image.empty()) {
    ++stats_.frames_incomplete;
    return false;
  }
  // The buffer goes back to the driver right after this; Mono8 is only wrapped, so copy it.
  if (image.data == data) image = image.clone();
  frame->image = image;
  frame->frame_id = frame_id;
  frame->timestamp_ns = timestamp_ns;
  frame->source_format = pf;
  frame->hold.reset();
  ++stats_.frames_delivered;
  return true;
}

FrameStatus V4l2CameraImpl::do_next_frame(int timeout_ms, Frame* frame) {
  const auto deadline = Clock::now() + std::chrono::milliseconds(timeout_ms);
  for (;;) {
    const auto left = std::chrono::ceil<std::chrono::milliseconds>(deadline - Clock::now()).count();
    pollfd p{fd_, POLLIN, 0};
    const int r = io_->poll(&p, 1, static_cast<int>(std::max<int64_t>(left, 0)));
    if (r < 0) {
      const int err = errno;
      if (err == EINTR) {
        if (Clock::now() >= deadline) return FrameStatus::kTimeout;
        continue;
      }
      fail("poll", err);
    }
    if (r == 0) {
      if (Clock::now() >= deadline) return FrameStatus::kTimeout;
      continue;
    }
    if (p.revents & POLLNVAL) {
      throw Error(ErrorCode::kInternal, who() + ": poll: descriptor is not open");
    }
    const bool error_reported = (p.revents & (POLLERR | POLLHUP)) != 0;
    const std::optional<FrameStatus> st = read_io_ ? read_frame(error_reported, frame) : dequeue_frame(error_reported, frame);
    if (st) return *st;
    if (Clock::now() >= deadline) return FrameStatus::kTimeout;
  }
}

// read() I/O: one frame, or nullopt to wait on (no data yet, or an incomplete frame).
std::optional<FrameStatus> V4l2CameraImpl::read_frame(bool error_reported, Frame* frame) {
  const ssize_t n = io_->read(fd_, read_buffer_.data(), read_buffer_.size());
  if (n < 0) {
    const int err = errno;
    if (err == EAGAIN || err == EINTR) {
      if (error_reported) {
        throw Error(ErrorCode::kDevice, who() + ": poll reports an error, read() has no data");
      }
      return std::nullopt;
    }
    if (is_gone(err) || err == EIO) {
      disconnect(err, "read");
      return FrameStatus::kDisconnected;
    }
    fail("read", err);
  }
  if (deliver(read_buffer_.data(), static_cast<size_t>(n), read_frames_++, monotonic_ns(),
              frame)) {
    return FrameStatus::kOk;
  }
  return std::nullopt;
}

// Streaming I/O: dequeue a buffer, decode it, queue it again; nullopt to wait on.
std::optional<FrameStatus> V4l2CameraImpl::dequeue_frame(bool error_reported, Frame* frame) {
  v4l2_buffer b{};
  b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  b.memory = V4L2_MEMORY_MMAP;
  if (const int err = ioctl(VIDIOC_DQBUF, &b)) {
    if (err == EAGAIN) {
      if (error_reported) {
        throw Error(ErrorCode::kDevice, who() + ": poll reports an error, no buffer is ready");
      }
      return std::nullopt;
    }
    if (is_gone(err) || err == EIO) {
      disconnect(err, "VIDIOC_DQBUF");
      return FrameStatus::kDisconnected;
    }
    fail("VIDIOC_DQBUF", err);
  }
  if (b.index >= buffers_.size()) {
    throw Error(ErrorCode::kInternal, who() + ": driver returned buffer index " +
                                          std::to_string(b.index) + " of " +
                                          std::to_string(buffers_.size()));
  }
  // Frames the driver had to drop for want of a queued buffer show as sequence gaps.
  if (last_sequence_ && b.sequence > *last_sequence_ + 1) {
    stats_.frames_dropped += b.sequence - *last_sequence_ - 1;
  }
  last_sequence_ = b.sequence;
  bool ok = false;
  if (b.flags & V4L2_BUF_FLAG_ERROR || b.bytesused == 0) {
    ++stats_.frames_incomplete;
  } else {
    const int64_t ts =
        (b.flags & V4L2_BUF_FLAG_TIMESTAMP_MASK) == V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC
            ? static_cast<int64_t>(b.timestamp.tv_sec) * 1000000000LL +
                  static_cast<int64_t>(b.timestamp.tv_usec) * 1000
            : monotonic_ns();
    const size_t bytes = std::min<size_t>(b.bytesused, buffers_[b.index].length);
    ok = deliver(static_cast<const uint8_t*>(buffers_[b.index].addr), bytes, b.sequence, ts,
                 frame);
  }
  // The decoded image is a copy, so the buffer can go straight back to the driver.
  v4l2_buffer q{};
  q.index = b.index;
  q.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  q.memory = V4L2_MEMORY_MMAP;
  if (const int err = ioctl(VIDIOC_QBUF, &q)) {
    if (is_gone(err) || err == EIO) {
      disconnect(err, "VIDIOC_QBUF");
      return ok ? FrameStatus::kOk : FrameStatus::kDisconnected;
    }
    fail("VIDIOC_QBUF", err);
  }
  if (ok) return FrameStatus::kOk;
  return std::nullopt;
}

}  // namespace posecal::v4l2
