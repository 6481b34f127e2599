// Internal to v4l2_source: helpers shared by the backend and the camera.
#pragma once

#include <linux/videodev2.h>

#include <memory>
#include <string>

#include "posecal/v4l2_backend.hpp"
#include "posecal/v4l2_identity.hpp"
#include "posecal/v4l2_io.hpp"

namespace posecal::v4l2 {

// ioctl through the seam, retried on EINTR. Returns 0 or the errno value.
int xioctl(V4l2Io& io, int fd, unsigned long request, void* arg);

std::string errno_text(int err);
// The device is gone: every later call fails the same way.
inline bool is_gone(int err) { return err == ENODEV || err == ENXIO; }

// The capabilities of this node (device_caps where the driver reports them).
uint32_t node_caps(const v4l2_capability& cap);
bool is_video_capture(uint32_t caps);
// "video capture, streaming, read/write" for messages.
std::string caps_text(uint32_t caps);
std::string fixed_string(const void* bytes, size_t size);  // NUL-terminated or full-size char array

// Text of a fourcc ("MJPG"); big-endian variants get "-BE".
std::string fourcc_text(uint32_t fourcc);
PixelFormat pixel_format_of_fourcc(uint32_t fourcc);

// What the backend tells about a node: identity from sysfs, names from VIDIOC_QUERYCAP.
DeviceInfo make_device_info(const V4l2NodeIdentity& id, const v4l2_capability& cap);

// Opens `identity.dev_path` as a V4l2Camera (throws as V4l2Backend::open documents).
std::unique_ptr<V4l2Camera> open_v4l2_camera(std::shared_ptr<V4l2Io> io,
                                             const V4l2NodeIdentity& identity,
                                             const std::string& uri_text);

}  // namespace posecal::v4l2
