#include "aravis_util.hpp"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <atomic>
#include <cctype>
#include <cerrno>
#include <chrono>
#include <cstdio>

namespace posecal::aravis {

std::mutex& device_list_mutex() {
  static std::mutex mutex;
  return mutex;
}

std::vector<std::string> genicam_pixel_format_names(PixelFormat format) {
  // SFNC/PFNC names first, then the GigE Vision 1.x names older cameras still use.
  switch (format) {
    case PixelFormat::kMono8:
      return {"Mono8"};
    case PixelFormat::kMono16:
      return {"Mono16"};
    case PixelFormat::kRGB8:
      return {"RGB8", "RGB8Packed"};
    case PixelFormat::kBGR8:
      return {"BGR8", "BGR8Packed"};
    case PixelFormat::kBayerRG8:
      return {"BayerRG8"};
    case PixelFormat::kBayerGR8:
      return {"BayerGR8"};
    case PixelFormat::kBayerGB8:
      return {"BayerGB8"};
    case PixelFormat::kBayerBG8:
      return {"BayerBG8"};
    case PixelFormat::kYUYV:
      return {"YUV422_8", "YUV422_YUYV_Packed"};
    case PixelFormat::kMJPEG:
    case PixelFormat::kUnknown:
      break;
  }
  return {};
}

PixelFormat pixel_format_from_genicam(const std::string& name) {
  for (PixelFormat f : {PixelFormat::kMono8, PixelFormat::kMono16, PixelFormat::kRGB8,
                        PixelFormat::kBGR8, PixelFormat::kBayerRG8, PixelFormat::kBayerGR8,
                        PixelFormat::kBayerGB8, PixelFormat::kBayerBG8, PixelFormat::kYUYV}) {
    for (const std::string& n : genicam_pixel_format_names(f)) {
      if (n == name) return f;
    }
  }
  return PixelFormat::kUnknown;
}

PixelFormat pixel_format_from_arv(ArvPixelFormat format) {
  switch (format) {
    case ARV_PIXEL_FORMAT_MONO_8:
      return PixelFormat::kMono8;
    case ARV_PIXEL_FORMAT_MONO_16:
      return PixelFormat::kMono16;
    case ARV_PIXEL_FORMAT_RGB_8_PACKED:
      return PixelFormat::kRGB8;
    case ARV_PIXEL_FORMAT_BGR_8_PACKED:
      return PixelFormat::kBGR8;
    case ARV_PIXEL_FORMAT_BAYER_RG_8:
      return PixelFormat::kBayerRG8;
    case ARV_PIXEL_FORMAT_BAYER_GR_8:
      return PixelFormat::kBayerGR8;
    case ARV_PIXEL_FORMAT_BAYER_GB_8:
      return PixelFormat::kBayerGB8;
    case ARV_PIXEL_FORMAT_BAYER_BG_8:
      return PixelFormat::kBayerBG8;
    case ARV_PIXEL_FORMAT_YUV_422_YUYV_PACKED:
      return PixelFormat::kYUYV;
    default:
      return PixelFormat::kUnknown;
  }
}

bool engine_can_convert(PixelFormat format) { return bytes_per_pixel(format) > 0; }

int bytes_per_pixel(PixelFormat format) {
  switch (format) {
    case PixelFormat::kMono8:
    case PixelFormat::kBayerRG8:
    case PixelFormat::kBayerGR8:
    case PixelFormat::kBayerGB8:
    case PixelFormat::kBayerBG8:
      return 1;
    case PixelFormat::kMono16:
    case PixelFormat::kYUYV:
      return 2;
    case PixelFormat::kRGB8:
    case PixelFormat::kBGR8:
      return 3;
    case PixelFormat::kMJPEG:
    case PixelFormat::kUnknown:
      break;
  }
  return 0;
}

std::string transport_name(const std::string& aravis_protocol) {
  if (aravis_protocol == "GigEVision") return "GigE Vision";
  if (aravis_protocol == "USB3Vision") return "USB3 Vision";
  return aravis_protocol;
}

bool is_ipv4_address(const std::string& text) {
  in_addr addr{};
  return inet_pton(AF_INET, text.c_str(), &addr) == 1;
}

namespace {

constexpr uint16_t kGvcpPort = 3956;
constexpr uint8_t kGvcpKey = 0x42;
constexpr uint8_t kGvcpFlagAckRequired = 0x01;
constexpr uint16_t kGvcpReadRegCmd = 0x0080;
constexpr uint16_t kGvcpReadRegAck = 0x0081;

struct FdCloser {
  int fd;
  ~FdCloser() {
    if (fd >= 0) ::close(fd);
  }
};

}  // namespace

bool gvcp_probe(const std::string& ipv4_address, int timeout_ms, int retries) {
  sockaddr_in to{};
  to.sin_family = AF_INET;
  to.sin_port = htons(kGvcpPort);
  if (inet_pton(AF_INET, ipv4_address.c_str(), &to.sin_addr) != 1) return false;
  const FdCloser sock{::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0)};
  if (sock.fd < 0) return false;
  // Connected, so the kernel filters foreign datagrams and reports ICMP port-unreachable.
  if (::connect(sock.fd, reinterpret_cast<const sockaddr*>(&to), sizeof to) != 0) return false;

  static std::atomic<uint16_t> next_request_id{1};
  using Clock = std::chrono::steady_clock;
  for (int attempt = 0; attempt < retries; ++attempt) {
    uint16_t id = next_request_id.fetch_add(1);
    if (id == 0) id = next_request_id.fetch_add(1);  // 0 is not a valid GVCP request id
    // GigE Vision 2.0 §15.3: key, flags, command, length (bytes after the header), request id;
    // then the register address (the bootstrap Version register, 0x0000).
    const uint8_t command[12] = {kGvcpKey,
                                 kGvcpFlagAckRequired,
                                 static_cast<uint8_t>(kGvcpReadRegCmd >> 8),
                                 static_cast<uint8_t>(kGvcpReadRegCmd & 0xff),
                                 0x00,
                                 0x04,
                                 static_cast<uint8_t>(id >> 8),
                                 static_cast<uint8_t>(id & 0xff),
                                 0,
                                 0,
                                 0,
                                 0};
    if (::send(sock.fd, command, sizeof command, MSG_NOSIGNAL) < 0) {
      if (errno == ECONNREFUSED) return false;
      continue;
    }
    const Clock::time_point deadline = Clock::now() + std::chrono::milliseconds(timeout_ms);
    for (;;) {
      const auto left =
          std::chrono::duration_cast<std::chrono::milliseconds>(deadline - Clock::now()).count();
      if (left <= 0) break;
      pollfd p{sock.fd, POLLIN, 0};
      const int r = ::poll(&p, 1, static_cast<int>(left));
      if (r < 0 && errno == EINTR) continue;
      if (r <= 0) break;
      uint8_t ack[64];
      const ssize_t n = ::recv(sock.fd, ack, sizeof ack, 0);
      if (n < 0) {
        if (errno == ECONNREFUSED) return false;  // nothing listens on the GVCP port
        continue;
      }
      // ACK header: status (2), acknowledge (2), length (2), ack id (2).
      if (n >= 8 && ((ack[2] << 8) | ack[3]) == kGvcpReadRegAck &&
          static_cast<uint16_t>((ack[6] << 8) | ack[7]) == id) {
        return true;
      }
    }
  }
  return false;
}

}  // namespace posecal::aravis
