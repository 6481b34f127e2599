// The "aravis" CameraBackend: discovery, URI resolution and opening. The camera itself is in
// aravis_camera.cpp.
#include "posecal/aravis_backend.hpp"

#include <cerrno>
#include <cstdlib>

#include "aravis_camera.hpp"
#include "aravis_util.hpp"
#include "common/error.hpp"

namespace posecal {

bool AravisBackendOptions::is_valid(std::string* error) const {
  auto fail = [&](const std::string& message) {
    if (error != nullptr) *error = message;
    return false;
  };
  auto in = [](int v, int lo, int hi) { return v >= lo && v <= hi; };
  if (packet_size != 0 && !in(packet_size, 576, 16384)) {
    return fail("packet_size must be 0 (camera default) or 576..16384 bytes, not " +
                std::to_string(packet_size));
  }
  if (!in(socket_buffer_size, 0, 1 << 30))
    return fail("socket_buffer_size must be 0 (auto) or a positive number of bytes");
  if (!in(packet_timeout_us, 1000, 10000000))
    return fail("packet_timeout_us must be 1000..10000000");
  if (!in(frame_retention_us, 1000, 10000000))
    return fail("frame_retention_us must be 1000..10000000");
  if (!in(startup_discard_ms, 0, 10000)) return fail("startup_discard_ms must be 0..10000");
  if (!in(extra_buffers, 1, 64)) return fail("extra_buffers must be 1..64");
  if (!in(max_lent_buffers, 0, 64)) return fail("max_lent_buffers must be 0..64");
  if (!in(frame_timeout_ms, 50, 60000)) return fail("frame_timeout_ms must be 50..60000");
  if (!in(idle_probe_interval_ms, 100, 60000))
    return fail("idle_probe_interval_ms must be 100..60000");
  if (!in(probe_timeout_ms, 10, 5000)) return fail("probe_timeout_ms must be 10..5000");
  if (!in(probe_retries, 1, 10)) return fail("probe_retries must be 1..10");
  if (!in(reconnect_min_backoff_ms, 10, 60000))
    return fail("reconnect_min_backoff_ms must be 10..60000");
  if (!in(reconnect_max_backoff_ms, reconnect_min_backoff_ms, 600000)) {
    return fail("reconnect_max_backoff_ms must be reconnect_min_backoff_ms..600000");
  }
  return true;
}

namespace aravis {
namespace {

AravisBackendOptions options_for(AravisBackendOptions o, const Uri& uri) {
  const std::string where = "camera URI '" + uri.text + "'";
  for (const auto& [key, value] : uri.query) {
    auto bad = [&](const char* expected) {
      return Error(ErrorCode::kInvalidArgument,
                   where + ": option " + key + "=" + value + " is not " + expected);
    };
    auto as_int = [&](int* field) {
      errno = 0;
      char* end = nullptr;
      const long v = std::strtol(value.c_str(), &end, 10);
      if (value.empty() || errno != 0 || *end != '\0' || v < -(1L << 31) || v > (1L << 31) - 1) {
        throw bad("an integer");
      }
      *field = static_cast<int>(v);
    };
    auto as_bool = [&](bool* field) {
      if (value == "1" || value == "true") {
        *field = true;
      } else if (value == "0" || value == "false") {
        *field = false;
      } else {
        throw bad("0/1/true/false");
      }
    };
    if (key == "packet_size") {
      as_int(&o.packet_size);
    } else if (key == "packet_resend") {
      if (value == "always") {
        o.packet_resend = true;
      } else if (value == "never") {
        o.packet_resend = false;
      } else {
        as_bool(&o.packet_resend);
      }
    } else if (key == "socket_buffer_size") {
      as_int(&o.socket_buffer_size);
    } else if (key == "packet_timeout_us") {
      as_int(&o.packet_timeout_us);
    } else if (key == "frame_retention_us") {
      as_int(&o.frame_retention_us);
    } else if (key == "packet_socket") {
      as_bool(&o.packet_socket);
    } else if (key == "startup_discard_ms") {
      as_int(&o.startup_discard_ms);
    } else if (key == "extra_buffers") {
      as_int(&o.extra_buffers);
    } else if (key == "max_lent_buffers") {
      as_int(&o.max_lent_buffers);
    } else if (key == "zero_copy") {
      as_bool(&o.zero_copy);
    } else if (key == "frame_timeout_ms") {
      as_int(&o.frame_timeout_ms);
    } else if (key == "probe_timeout_ms") {
      as_int(&o.probe_timeout_ms);
    } else if (key == "probe_retries") {
      as_int(&o.probe_retries);
    } else if (key == "idle_probe_interval_ms") {
      as_int(&o.idle_probe_interval_ms);
    } else if (key == "auto_reconnect") {
      as_bool(&o.auto_reconnect);
    } else if (key == "reconnect_min_backoff_ms") {
      as_int(&o.reconnect_min_backoff_ms);
    } else if (key == "reconnect_max_backoff_ms") {
      as_int(&o.reconnect_max_backoff_ms);
    } else {
      throw Error(ErrorCode::kInvalidArgument,
                  where + ": unknown option '" + key +
                      "' (known: packet_size, packet_resend, socket_buffer_size, "
                      "packet_timeout_us, frame_retention_us, packet_socket, startup_discard_ms, "
                      "extra_buffers, "
                      "max_lent_buffers, "
                      "zero_copy, frame_timeout_ms, idle_probe_interval_ms, probe_timeout_ms, "
                      "probe_retries, auto_reconnect, reconnect_min_backoff_ms, "
                      "reconnect_max_backoff_ms)");
    }
  }
  std::string why;
  if (!o.is_valid(&why)) throw Error(ErrorCode::kInvalidArgument, where + ": " + why);
  return o;
}

struct ListedDevice {
  std::string id, vendor, model, serial, physical_id, address, protocol;
};

// Caller holds device_list_mutex(). Blocks for Aravis' discovery timeout (one second for GigE).
std::vector<ListedDevice> discover() {
  auto text = [](const char* s) { return s != nullptr ? std::string(s) : std::string(); };
  arv_update_device_list();
  std::vector<ListedDevice> out;
  const unsigned n = arv_get_n_devices();
  for (unsigned i = 0; i < n; ++i) {
    out.push_back(ListedDevice{text(arv_get_device_id(i)), text(arv_get_device_vendor(i)),
                               text(arv_get_device_model(i)), text(arv_get_device_serial_nbr(i)),
                               text(arv_get_device_physical_id(i)), text(arv_get_device_address(i)),
                               text(arv_get_device_protocol(i))});
  }
  return out;
}

DeviceInfo info_of(const ListedDevice& d) {
  DeviceInfo info;
  info.uri = "aravis://" + uri_escape(d.id);
  info.backend = "aravis";
  info.id = d.id;
  info.vendor = d.vendor;
  info.model = d.model;
  info.serial = d.serial;
  info.transport = transport_name(d.protocol);
  return info;
}

class AravisBackend final : public CameraBackend {
 public:
  explicit AravisBackend(const AravisBackendOptions& options) : options_(options) {}

  std::string scheme() const override { return "aravis"; }

  std::vector<DeviceInfo> enumerate() override {
    std::lock_guard<std::mutex> lock(device_list_mutex());
    std::vector<DeviceInfo> out;
    for (const ListedDevice& d : discover()) out.push_back(info_of(d));
    return out;
  }

  std::unique_ptr<Camera> open(const Uri& uri) override;

 private:
  const AravisBackendOptions options_;
};

std::unique_ptr<Camera> AravisBackend::open(const Uri& uri) {
  if (uri.scheme != "aravis") {
    throw Error(ErrorCode::kInvalidArgument, "camera URI '" + uri.text +
                                                 "': the Aravis backend serves aravis://, not " +
                                                 uri.scheme + "://");
  }
  const std::string& path = uri.path;
  if (path.empty()) {
    throw Error(ErrorCode::kInvalidArgument,
                "camera URI '" + uri.text +
                    "' names no camera (expected aravis://<device id | serial number | IPv4>)");
  }
  const AravisBackendOptions options = options_for(options_, uri);

  DeviceInfo info;
  Locator locator;
  std::string target;  // what arv_camera_new() gets
  if (is_ipv4_address(path)) {
    // Straight to the address (no discovery, so routed subnets work too); the probe keeps a
    // missing camera from costing Aravis' 2.5 s connection timeout.
    if (!gvcp_probe(path, options.probe_timeout_ms, options.probe_retries)) {
      throw Error(ErrorCode::kNotFound,
                  "camera '" + uri.text + "' not found: no GigE Vision camera answers at " + path);
    }
    info.uri = "aravis://" + path;
    locator.gige = true;
    locator.address = path;
    target = path;
  } else {
    std::lock_guard<std::mutex> lock(device_list_mutex());
    const std::vector<ListedDevice> devices = discover();
    const ListedDevice* found = nullptr;
    for (const ListedDevice& d : devices) {
      if (d.id == path) found = &d;
    }
    if (found == nullptr) {
      std::vector<const ListedDevice*> matches;
      for (const ListedDevice& d : devices) {
        if (d.serial == path || (!d.physical_id.empty() && d.physical_id == path))
          matches.push_back(&d);
      }
      if (matches.size() > 1) {
        std::string ids;
        for (const ListedDevice* d : matches) ids += (ids.empty() ? "" : ", ") + d->id;
        throw Error(ErrorCode::kInvalidArgument, "camera URI '" + uri.text + "': '" + path +
                                                     "' matches several cameras (" + ids +
                                                     "); use the device id");
      }
      if (!matches.empty()) found = matches.front();
    }
    if (found == nullptr) {
      std::string present;
      for (const ListedDevice& d : devices) present += (present.empty() ? "" : ", ") + d.id;
      throw Error(ErrorCode::kNotFound,
                  "camera '" + uri.text + "' not found (Aravis sees " +
                      (present.empty() ? std::string("no cameras") : present) + ")");
    }
    info = info_of(*found);
    locator.device_id = found->id;
    locator.serial = found->serial;
    locator.gige = found->protocol == "GigEVision";
    locator.address = locator.gige ? found->address : "";
    // By address a GigE camera opens without a second discovery round.
    target = locator.gige && !locator.address.empty() ? locator.address : found->id;
  }

  GPtr<ArvCamera> camera;
  {
    std::lock_guard<std::mutex> lock(device_list_mutex());
    GErr err;
    camera.reset(arv_camera_new(target.c_str(), err.out()));
    if (!camera) {
      throw Error(ErrorCode::kDevice,
                  "camera '" + uri.text + "' could not be opened: " + err.message());
    }
  }
  ArvCamera* cam = camera.get();
  auto read = [&](const char* (*getter)(ArvCamera*, GError**)) {
    GErr err;
    const char* s = getter(cam, err.out());
    return !err && s != nullptr ? std::string(s) : std::string();
  };
  const std::string serial = read(arv_camera_get_device_serial_number);
  if (!locator.serial.empty() && serial != locator.serial) {
    throw Error(ErrorCode::kNotFound, "camera '" + uri.text + "' not found: the camera at " +
                                          target + " now reports serial '" + serial + "'");
  }
  locator.serial = serial;
  if (info.vendor.empty()) info.vendor = read(arv_camera_get_vendor_name);
  if (info.model.empty()) info.model = read(arv_camera_get_model_name);
  info.serial = serial;
  if (info.id.empty()) info.id = info.vendor + "-" + info.model + "-" + serial;  // Aravis' form
  if (locator.device_id.empty()) locator.device_id = info.id;
  info.backend = "aravis";
  info.transport = arv_camera_is_gv_device(cam)   ? "GigE Vision"
                   : arv_camera_is_uv_device(cam) ? "USB3 Vision"
                                                  : info.transport;
  return std::make_unique<AravisCameraImpl>(std::move(camera), std::move(info), std::move(locator),
                                            options);
}

}  // namespace
}  // namespace aravis

std::shared_ptr<CameraBackend> make_aravis_backend(const AravisBackendOptions& options) {
  std::string why;
  if (!options.is_valid(&why)) {
    throw Error(ErrorCode::kInvalidArgument, "Aravis backend options: " + why);
  }
  return std::make_shared<aravis::AravisBackend>(options);
}

}  // namespace posecal
