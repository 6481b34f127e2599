// Aravis camera backend: GenICam cameras (GigE Vision, USB3 Vision) through Aravis 0.8, serving
// URIs of the form
//
//   aravis://<device id | serial number | IPv4 address>[?option=value&...]
//
// e.g. aravis://Basler-21234567, aravis://21234567, aravis://192.168.1.20?packet_size=8000.
// The query options are fields of AravisBackendOptions below, by the same names (packet_size,
// packet_resend=always|never, socket_buffer_size, packet_timeout_us, frame_retention_us,
// packet_socket=0|1, startup_discard_ms, extra_buffers, max_lent_buffers, zero_copy=0|1,
// frame_timeout_ms, idle_probe_interval_ms, probe_timeout_ms, probe_retries, auto_reconnect=0|1,
// reconnect_min_backoff_ms, reconnect_max_backoff_ms); they override the backend's defaults for
// that one camera. docs/aravis.md describes the threads, the frame path, disconnect
// detection and reconnection.
#pragma once

#include <cstdint>
#include <memory>
#include <string>

#include "device/camera.hpp"

namespace posecal {

struct AravisBackendOptions {
  // --- GigE Vision transport (ignored for USB3 Vision) ---
  // GVSP packet size in bytes. 0 keeps Aravis' behaviour (the camera's value, adjusted once if
  // the first frame fails); otherwise the size is forced and never adjusted. 576..16384.
  int packet_size = 0;
  // Ask the camera to resend lost packets (ARV_GV_STREAM_PACKET_RESEND_ALWAYS) or not (NEVER).
  // Either way a frame that is still incomplete is counted in frames_incomplete and dropped.
  bool packet_resend = true;
  // Kernel receive buffer of the stream's UDP socket in bytes; 0 sizes it for four frames. The
  // kernel caps it at net.core.rmem_max (208 KiB on a stock Linux: raise it for GigE cameras).
  // Aravis' own choice (one payload) loses most frames of a 1280x720 camera at 30 Hz with
  // 8000-byte packets over loopback (docs/aravis.md).
  int socket_buffer_size = 0;
  // arv_gv_stream "packet-timeout" (wait before requesting a resend) and "frame-retention"
  // (give up on an incomplete frame), microseconds.
  int packet_timeout_us = 20000;
  int frame_retention_us = 100000;
  // Let Aravis receive GVSP through a memory-mapped packet socket where the process may open one
  // (CAP_NET_RAW, e.g. root); false always uses the ordinary UDP socket.
  bool packet_socket = true;
  // Buffers (complete or not) that arrive within this many milliseconds after a stream
  // (re)starts are discarded (counted in frames_dropped, not frames_incomplete). Aravis attaches
  // its packet filter to a new stream socket only after the socket exists, so packets of other
  // cameras streaming to the same host that arrive in between are queued with the stream's own;
  // when they carry the same GVSP block id as one of its first frames (cameras count block ids
  // from the same start), that frame is assembled from both and still reported complete.
  // Measured with three simulators: 6 of 60 stream starts delivered such a frame, all within the
  // first 100 ms (docs/aravis.md). The default covers frame_retention_us, after which a stale
  // partial frame is given up. 0 disables.
  int startup_discard_ms = 300;

  // --- Buffers ---
  // The stream owns queue_depth + max_lent_buffers + extra_buffers buffers; extra_buffers are
  // the ones being filled from the wire while the others wait in the queue or are lent out.
  int extra_buffers = 3;
  // Mono8/BGR8 frames are handed out without a copy: Frame::hold keeps the Aravis buffer and
  // gives it back to the stream when the last copy of the Frame is destroyed. At most this many
  // buffers are lent at a time; beyond that frames are copied so a consumer that keeps frames
  // can never starve the stream.
  int max_lent_buffers = 2;
  bool zero_copy = true;

  // --- Liveness ---
  // While streaming, a gap of this many milliseconds without any buffer from the camera makes the
  // backend probe it (one GVCP register read, or a register read over USB); a camera that does
  // not answer is declared disconnected. Not streaming, the camera is probed every
  // idle_probe_interval_ms. The probe sends probe_retries reads, each waiting probe_timeout_ms.
  int frame_timeout_ms = 600;
  int idle_probe_interval_ms = 1000;
  int probe_timeout_ms = 150;
  int probe_retries = 3;
  // Reopen a disconnected camera (same serial number) when it answers again, restore its
  // configuration and features and resume streaming if it was streaming. Attempts back off
  // exponentially from reconnect_min_backoff_ms to reconnect_max_backoff_ms.
  bool auto_reconnect = true;
  int reconnect_min_backoff_ms = 200;
  int reconnect_max_backoff_ms = 2000;

  // True if every field is in range; otherwise false with the offending field in *error.
  bool is_valid(std::string* error = nullptr) const;
};

// Transport counters of an open Aravis camera (for diagnostics and tests).
struct AravisTransportStats {
  std::string protocol;        // "GigE Vision", "USB3 Vision"
  std::string device_address;  // IPv4 address of a GigE Vision camera, else ""
  unsigned packet_size = 0;    // current GVSP packet size (GigE Vision, 0 otherwise)
  bool packet_resend = false;  // resend policy of the current stream
  // Aravis' stream statistics, since the current stream was created.
  uint64_t completed_buffers = 0;
  uint64_t failed_buffers = 0;
  uint64_t underruns = 0;
  uint64_t resent_packets = 0;   // GigE Vision only
  uint64_t missing_packets = 0;  // GigE Vision only
  // Frames handed out without a copy / copied (lending off or max_lent_buffers out), since open.
  uint64_t frames_zero_copy = 0;
  uint64_t frames_copied = 0;
  int buffers_lent = 0;  // lent frames still held by the consumer
  uint64_t reconnects = 0;
};

// The cameras the Aravis backend opens implement this extension of Camera.
class AravisCamera : public Camera {
 public:
  // Throws Error(kState) while disconnected.
  virtual AravisTransportStats transport_stats() = 0;

 protected:
  using Camera::Camera;
};

// The backend for the "aravis" scheme. Throws Error(kInvalidArgument) if the options are invalid.
std::shared_ptr<CameraBackend> make_aravis_backend(const AravisBackendOptions& options = {});

}  // namespace posecal
