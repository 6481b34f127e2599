// The emulator itself, driven with raw system calls: it must honour the V4L2 specification's
// rules, or the backend tests prove nothing. Each test names the rule it checks.
#include <fcntl.h>
#include <sys/mman.h>

#include <cstring>

#include "rig.hpp"

namespace posecal::test {
namespace {

class EmulatorSpec : public ::testing::Test {
 protected:
  void SetUp() override {
    emu.add_node(path, emu::c525_video_node(), "1-2");
    emu.add_node(meta, emu::c525_metadata_node(), "1-2");
    fd = emu.open(path.c_str(), O_RDWR | O_NONBLOCK);
    ASSERT_GE(fd, 0);
  }
  void TearDown() override {
    if (fd >= 0) emu.close(fd);
    for (auto& [addr, len] : maps) emu.munmap(addr, len);
    EXPECT_EQ(emu.open_fds(), 0);
    EXPECT_EQ(emu.live_mappings(), 0);
  }
  int ioctl_errno(int fd_, unsigned long req, void* arg) {
    return emu.ioctl(fd_, req, arg) == 0 ? 0 : errno;
  }
  void set_format(uint32_t fourcc, uint32_t w, uint32_t h) {
    v4l2_format f{};
    f.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    f.fmt.pix = {w, h, fourcc, V4L2_FIELD_ANY, 0, 0, 0, 0, 0, {}, 0, 0};
    ASSERT_EQ(ioctl_errno(fd, VIDIOC_S_FMT, &f), 0);
  }
  uint32_t request_buffers(uint32_t count, int on_fd = -1) {
    v4l2_requestbuffers req{};
    req.count = count;
    req.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    req.memory = V4L2_MEMORY_MMAP;
    EXPECT_EQ(ioctl_errno(on_fd < 0 ? fd : on_fd, VIDIOC_REQBUFS, &req), 0);
    return req.count;
  }
  v4l2_buffer buffer(uint32_t index) {
    v4l2_buffer b{};
    b.index = index;
    b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    b.memory = V4L2_MEMORY_MMAP;
    return b;
  }
  void* map(uint32_t index) {
    v4l2_buffer b = buffer(index);
    EXPECT_EQ(ioctl_errno(fd, VIDIOC_QUERYBUF, &b), 0);
    void* p = emu.mmap(nullptr, b.length, PROT_READ | PROT_WRITE, MAP_SHARED, fd, b.m.offset);
    EXPECT_NE(p, MAP_FAILED);
    if (p != MAP_FAILED) maps.emplace_back(p, b.length);
    return p;
  }
  int stream(unsigned long req) {
    int type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
    return ioctl_errno(fd, req, &type);
  }

  emu::UvcEmulator emu;
  std::string path = "/emu/video0";
  std::string meta = "/emu/video1";
  int fd = -1;
  std::vector<std::pair<void*, size_t>> maps;
};

TEST_F(EmulatorSpec, QuerycapReportsPerNodeDeviceCaps) {
  v4l2_capability cap{};
  ASSERT_EQ(ioctl_errno(fd, VIDIOC_QUERYCAP, &cap), 0);
  EXPECT_STREQ(reinterpret_cast<const char*>(cap.driver), "uvcvideo");
  EXPECT_TRUE(cap.capabilities & V4L2_CAP_DEVICE_CAPS);
  EXPECT_TRUE(cap.device_caps & V4L2_CAP_VIDEO_CAPTURE);
  const int mfd = emu.open(meta.c_str(), O_RDWR);
  ASSERT_GE(mfd, 0);
  ASSERT_EQ(ioctl_errno(mfd, VIDIOC_QUERYCAP, &cap), 0);
  // The device as a whole captures video; this node only metadata.
  EXPECT_TRUE(cap.capabilities & V4L2_CAP_VIDEO_CAPTURE);
  EXPECT_FALSE(cap.device_caps & V4L2_CAP_VIDEO_CAPTURE);
  EXPECT_TRUE(cap.device_caps & V4L2_CAP_META_CAPTURE);
  v4l2_fmtdesc d{};
  d.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  EXPECT_EQ(ioctl_errno(mfd, VIDIOC_ENUM_FMT, &d), EINVAL);
  emu.close(mfd);
}

TEST_F(EmulatorSpec, SetFormatAdjustsToNearestSizeAndFirstFormat) {
  v4l2_format f{};
  f.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  f.fmt.pix.pixelformat = V4L2_PIX_FMT_MJPEG;
  f.fmt.pix.width = 1000;
  f.fmt.pix.height = 700;
  ASSERT_EQ(ioctl_errno(fd, VIDIOC_S_FMT, &f), 0);
  EXPECT_EQ(f.fmt.pix.width, 960u);
  EXPECT_EQ(f.fmt.pix.height, 720u);
  EXPECT_EQ(emu.frame_rate(path), 30.0);  // S_FMT resets the interval to the fastest
  f.fmt.pix.pixelformat = v4l2_fourcc('B', 'A', '8', '1');  // not offered
  ASSERT_EQ(ioctl_errno(fd, VIDIOC_TRY_FMT, &f), 0);
  EXPECT_EQ(f.fmt.pix.pixelformat, V4L2_PIX_FMT_YUYV);
  EXPECT_EQ(emu.format(path).pixelformat, V4L2_PIX_FMT_MJPEG);  // TRY_FMT changed nothing
}

TEST_F(EmulatorSpec, QueueRules) {
  set_format(V4L2_PIX_FMT_MJPEG, 640, 480);
  v4l2_buffer b = buffer(0);
  // STREAMON without buffers: EINVAL.
  EXPECT_EQ(stream(VIDIOC_STREAMON), EINVAL);
  ASSERT_EQ(request_buffers(3), 3u);
  // Buffers exist: S_FMT is EBUSY.
  v4l2_format f{};
  f.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
  f.fmt.pix.pixelformat = V4L2_PIX_FMT_YUYV;
  EXPECT_EQ(ioctl_errno(fd, VIDIOC_S_FMT, &f), EBUSY);
  // Another file handle cannot touch the queue.
  const int other = emu.open(path.c_str(), O_RDWR | O_NONBLOCK);
  v4l2_requestbuffers req{3, V4L2_BUF_TYPE_VIDEO_CAPTURE, V4L2_MEMORY_MMAP, 0, 0, {}};
  EXPECT_EQ(ioctl_errno(other, VIDIOC_REQBUFS, &req), EBUSY);
  emu.close(other);
  // QBUF of a queued buffer: EINVAL.
  EXPECT_EQ(ioctl_errno(fd, VIDIOC_QBUF, &b), 0);
  b = buffer(0);
  EXPECT_EQ(ioctl_errno(fd, VIDIOC_QBUF, &b), EINVAL);
  b = buffer(7);
  EXPECT_EQ(ioctl_errno(fd, VIDIOC_QBUF, &b), EINVAL);
  // DQBUF before STREAMON: EINVAL.
  b = buffer(0);
  EXPECT_EQ(ioctl_errno(fd, VIDIOC_DQBUF, &b), EINVAL);
  // poll before STREAMON: POLLERR.
  pollfd p{fd, POLLIN, 0};
  EXPECT_EQ(emu.poll(&p, 1, 0), 1);
  EXPECT_TRUE(p.revents & POLLERR);
  ASSERT_EQ(stream(VIDIOC_STREAMON), 0);
  // REQBUFS while streaming: EBUSY.
  req.count = 2;
  EXPECT_EQ(ioctl_errno(fd, VIDIOC_REQBUFS, &req), EBUSY);
  // Non-blocking DQBUF right away: EAGAIN (the first frame is 33 ms away).
  b = buffer(0);
  EXPECT_EQ(ioctl_errno(fd, VIDIOC_DQBUF, &b), EAGAIN);
  // poll waits for the frame.
  const auto t0 = std::chrono::steady_clock::now();
  p = {fd, POLLIN, 0};
  EXPECT_EQ(emu.poll(&p, 1, 1000), 1);
  EXPECT_TRUE(p.revents & POLLIN);
  EXPECT_LT(elapsed_ms(t0), 200);
  b = buffer(0);
  ASSERT_EQ(ioctl_errno(fd, VIDIOC_DQBUF, &b), 0);
  EXPECT_EQ(b.index, 0u);
  EXPECT_EQ(b.sequence, 0u);
  EXPECT_GT(b.bytesused, 1000u);
  EXPECT_EQ(b.flags & V4L2_BUF_FLAG_TIMESTAMP_MASK, V4L2_BUF_FLAG_TIMESTAMP_MONOTONIC);
  // STREAMOFF hands every buffer back: they can all be queued again.
  ASSERT_EQ(stream(VIDIOC_STREAMOFF), 0);
  for (uint32_t i = 0; i < 3; ++i) {
    b = buffer(i);
    EXPECT_EQ(ioctl_errno(fd, VIDIOC_QBUF, &b), 0) << i;
  }
  ASSERT_EQ(stream(VIDIOC_STREAMOFF), 0);
  EXPECT_EQ(request_buffers(0), 0u);
}

TEST_F(EmulatorSpec, FramesWithoutQueuedBuffersAreDropped) {
  set_format(V4L2_PIX_FMT_MJPEG, 320, 240);
  ASSERT_EQ(request_buffers(2), 2u);
  for (uint32_t i = 0; i < 2; ++i) {
    v4l2_buffer b = buffer(i);
    ASSERT_EQ(ioctl_errno(fd, VIDIOC_QBUF, &b), 0);
  }
  ASSERT_EQ(stream(VIDIOC_STREAMON), 0);
  std::this_thread::sleep_for(std::chrono::milliseconds(250));  // ~7 frames, 2 buffers
  v4l2_buffer a = buffer(0), b = buffer(0), c = buffer(0);
  ASSERT_EQ(ioctl_errno(fd, VIDIOC_DQBUF, &a), 0);
  ASSERT_EQ(ioctl_errno(fd, VIDIOC_DQBUF, &b), 0);
  EXPECT_EQ(ioctl_errno(fd, VIDIOC_DQBUF, &c), EAGAIN);
  EXPECT_EQ(a.sequence, 0u);
  EXPECT_EQ(b.sequence, 1u);
  ASSERT_EQ(ioctl_errno(fd, VIDIOC_QBUF, &a), 0);
  pollfd p{fd, POLLIN, 0};
  ASSERT_EQ(emu.poll(&p, 1, 1000), 1);
  a = buffer(0);
  ASSERT_EQ(ioctl_errno(fd, VIDIOC_DQBUF, &a), 0);
  EXPECT_GE(a.sequence, 7u);  // the frames in between found no buffer
  stream(VIDIOC_STREAMOFF);
  request_buffers(0);
}

TEST_F(EmulatorSpec, UnplugFailsEveryCallButKeepsMappedMemory) {
  set_format(V4L2_PIX_FMT_YUYV, 640, 480);
  ASSERT_EQ(request_buffers(2), 2u);
  auto* p0 = static_cast<volatile uint8_t*>(map(0));
  ASSERT_NE(p0, nullptr);
  emu.unplug("1-2");
  v4l2_capability cap{};
  EXPECT_EQ(ioctl_errno(fd, VIDIOC_QUERYCAP, &cap), ENODEV);
  v4l2_buffer b = buffer(1);
  EXPECT_EQ(emu.mmap(nullptr, 4096, PROT_READ, MAP_SHARED, fd, 0), MAP_FAILED);
  EXPECT_EQ(errno, ENODEV);
  pollfd p{fd, POLLIN, 0};
  EXPECT_EQ(emu.poll(&p, 1, 100), 1);
  EXPECT_EQ(p.revents & (POLLERR | POLLHUP), POLLERR | POLLHUP);
  char byte;
  EXPECT_EQ(emu.read(fd, &byte, 1), -1);
  EXPECT_EQ(errno, ENODEV);
  EXPECT_EQ(emu.open(path.c_str(), O_RDWR), -1);
  EXPECT_EQ(errno, ENOENT);
  p0[0] = 1;  // the mapping stays valid until munmap, as with vb2
  EXPECT_EQ(p0[0], 1);
  EXPECT_EQ(ioctl_errno(fd, VIDIOC_QUERYBUF, &b), ENODEV);
  EXPECT_EQ(emu.close(fd), 0);
  fd = -1;
}

TEST_F(EmulatorSpec, ControlsRangesMenusAndAutomaticModes) {
  // Enumeration with NEXT_CTRL lists the classes and every control once, in id order.
  std::vector<std::string> names;
  v4l2_query_ext_ctrl q{};
  q.id = V4L2_CTRL_FLAG_NEXT_CTRL | V4L2_CTRL_FLAG_NEXT_COMPOUND;
  uint32_t last = 0;
  while (ioctl_errno(fd, VIDIOC_QUERY_EXT_CTRL, &q) == 0) {
    EXPECT_GT(q.id, last);
    last = q.id;
    names.push_back(q.name);
    q.id |= V4L2_CTRL_FLAG_NEXT_CTRL | V4L2_CTRL_FLAG_NEXT_COMPOUND;
  }
  ASSERT_GE(names.size(), 18u);
  EXPECT_EQ(names.front(), "User Controls");
  EXPECT_NE(std::find(names.begin(), names.end(), "Camera Controls"), names.end());
  // Menu items: 0 and 2 are skipped.
  v4l2_querymenu m{};
  m.id = V4L2_CID_EXPOSURE_AUTO;
  m.index = 2;
  EXPECT_EQ(ioctl_errno(fd, VIDIOC_QUERYMENU, &m), EINVAL);
  m.index = 1;
  ASSERT_EQ(ioctl_errno(fd, VIDIOC_QUERYMENU, &m), 0);
  EXPECT_STREQ(reinterpret_cast<const char*>(m.name), "Manual Mode");
  v4l2_control c{V4L2_CID_EXPOSURE_AUTO, 2};
  EXPECT_EQ(ioctl_errno(fd, VIDIOC_S_CTRL, &c), EINVAL);
  c.value = 9;
  EXPECT_EQ(ioctl_errno(fd, VIDIOC_S_CTRL, &c), ERANGE);
  // Integers are clamped and rounded to the step.
  c = {V4L2_CID_BRIGHTNESS, 300};
  ASSERT_EQ(ioctl_errno(fd, VIDIOC_S_CTRL, &c), 0);
  EXPECT_EQ(emu.control(path, V4L2_CID_BRIGHTNESS), 255);
  // Inactive while automatic: writes refused, reads give the automatic value.
  c = {V4L2_CID_FOCUS_ABSOLUTE, 100};
  EXPECT_EQ(ioctl_errno(fd, VIDIOC_S_CTRL, &c), EACCES);
  c = {V4L2_CID_FOCUS_ABSOLUTE, 0};
  ASSERT_EQ(ioctl_errno(fd, VIDIOC_G_CTRL, &c), 0);
  EXPECT_EQ(c.value, 35);
  c = {V4L2_CID_FOCUS_AUTO, 0};
  ASSERT_EQ(ioctl_errno(fd, VIDIOC_S_CTRL, &c), 0);
  c = {V4L2_CID_FOCUS_ABSOLUTE, 52};
  ASSERT_EQ(ioctl_errno(fd, VIDIOC_S_CTRL, &c), 0);
  EXPECT_EQ(emu.control(path, V4L2_CID_FOCUS_ABSOLUTE), 50);
}

}  // namespace
}  // namespace posecal::test
