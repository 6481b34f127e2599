// Internal helpers of the Aravis backend: GLib ownership, Aravis' process-wide device list,
// pixel-format names and the GVCP liveness probe. Not part of the public interface.
#pragma once

#include <arv.h>

#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "device/camera.hpp"

namespace posecal::aravis {

struct GObjectUnref {
  void operator()(void* object) const {
    if (object != nullptr) g_object_unref(object);
  }
};
// Owns one reference to a GObject (ArvCamera, ArvStream, ...).
template <typename T>
using GPtr = std::unique_ptr<T, GObjectUnref>;

// Owns the GError an Aravis call may set: `call(..., err.out())`, then test `err`.
class GErr {
 public:
  GErr() = default;
  ~GErr() { reset(); }
  GErr(const GErr&) = delete;
  GErr& operator=(const GErr&) = delete;

  GError** out() {
    reset();
    return &error_;
  }
  explicit operator bool() const { return error_ != nullptr; }
  std::string message() const { return error_ != nullptr ? error_->message : ""; }
  // Errors of the GenICam layer (out of range, read-only, unknown entry) versus transport errors
  // (timeouts, a vanished device).
  bool is_genicam_error() const {
    return error_ != nullptr && error_->domain == arv_gc_error_quark();
  }
  void reset() {
    if (error_ != nullptr) g_error_free(error_);
    error_ = nullptr;
  }

 private:
  GError* error_ = nullptr;
};

// Aravis keeps one process-wide device list (arv_update_device_list, arv_get_device_*,
// arv_open_device) and does not lock it; every use in this backend holds this mutex.
std::mutex& device_list_mutex();

// GenICam PixelFormat entry names for an engine format, most common first (empty if none).
std::vector<std::string> genicam_pixel_format_names(PixelFormat format);
// Engine format of a GenICam entry name or an Aravis pixel-format code (kUnknown if none).
PixelFormat pixel_format_from_genicam(const std::string& name);
PixelFormat pixel_format_from_arv(ArvPixelFormat format);
// True if convert_to_engine() accepts frames of this format from a camera.
bool engine_can_convert(PixelFormat format);
// Bytes per pixel of the packed formats convert_to_engine() reads (0 for MJPEG/unknown).
int bytes_per_pixel(PixelFormat format);

// "GigEVision" -> "GigE Vision", "USB3Vision" -> "USB3 Vision".
std::string transport_name(const std::string& aravis_protocol);
// True for a dotted-quad IPv4 address.
bool is_ipv4_address(const std::string& text);
// Percent-encodes what Uri::parse would otherwise misread (space, '?', '%', '#', ...).


// Liveness probe of a GigE Vision camera: a GVCP READREG of the bootstrap Version register
// (0x0000) sent from a fresh UDP socket `retries` times, each waiting `timeout_ms` for the ACK.
// Any acknowledge (even an error status such as ACCESS_DENIED) proves the camera is there; an
// ICMP "port unreachable" ends the probe at once. Aravis' own GVCP transactions cannot be used:
// their timeout is fixed at 5 x 500 ms, too slow to report a disconnect within two seconds.
bool gvcp_probe(const std::string& ipv4_address, int timeout_ms, int retries);

}  // namespace posecal::aravis
