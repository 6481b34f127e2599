// The "aravis" CameraBackend: discovery, URI resolution and opening. The camera itself is in
// aravis_camera.cpp.
#include "posecal/aravis_backend.hpp"

#include <cerrno>
#include <cstdlib>

#include "aravis_camera.hpp"
#include "common/percent_encoding.hpp"
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

// The options a camera URI's query may set (aravis://ID?packet_size=8000&...), by name.
struct UriOption {
  const char* key;
  int AravisBackendOptions::*int_field;    // or
  bool AravisBackendOptions::*bool_field;
};
using O = AravisBackendOptions;
constexpr UriOption kUriOptions[] = {
    {"packet_size", &O::packet_size, nullptr},
    {"packet_resend", nullptr, &O::packet_resend},  // also "always" / "never"
    {"socket_buffer_size", &O::socket_buffer_size, nullptr},
    {"packet_timeout_us", &O::packet_timeout_us, nullptr},
    {"frame_retention_us", &O::frame_retention_us, nullptr},
    {"packet_socket", nullptr, &O::packet_socket},
    {"startup_discard_ms", &O::startup_discard_ms, nullptr},
    {"extra_buffers", &O::extra_buffers, nullptr},
    {"max_lent_buffers", &O::max_lent_buffers, nullptr},
    {"zero_copy", nullptr, &O::zero_copy},
    {"frame_timeout_ms", &O::frame_timeout_ms, nullptr},
    {"idle_probe_interval_ms", &O::idle_probe_interval_ms, nullptr},
    {"probe_timeout_ms", &O::probe_timeout_ms, nullptr},
    {"probe_retries", &O::probe_retries, nullptr},
    {"auto_reconnect", nullptr, &O::auto_reconnect},
    {"reconnect_min_backoff_ms", &O::reconnect_min_backoff_ms, nullptr},
    {"reconnect_max_backoff_ms", &O::reconnect_max_backoff_ms, nullptr},
};

// Sets one URI option; false if `value` is not of the option's kind.
bool set_uri_option(const UriOption& opt, const std::string& value, AravisBackendOptions* o) {
  if (opt.int_field) {
    errno = 0;
    char* end = nullptr;
    const long v = std::strtol(value.c_str(), &end, 10);
    if (value.empty() || errno != 0 || *end != '\0' || v < -(1L << 31) || v > (1L << 31) - 1) return false;
    o->*opt.int_field = static_cast<int>(v);
    return true;
  }
  if (value == "1" || value == "true" || (opt.bool_field == &O::packet_resend && value == "always")) {
    o->*opt.bool_field = true;
  } else if (value == "0" || value == "false" || (opt.bool_field == &O::packet_resend && value == "never")) {
    o->*opt.bool_field = false;
  } else {
    return false;
  }
  return true;
}

AravisBackendOptions options_for(AravisBackendOptions o, const Uri& uri) {
  const std::string where = "camera URI '" + uri.text + "'";
  for (const auto& [key, value] : uri.query) {
    const UriOption* opt = nullptr;
    for (const UriOption& u : kUriOptions)
      if (key == u.key) opt = &u;
    if (opt == nullptr) {
      std::string known;
      for (const UriOption& u : kUriOptions) known += (known.empty() ? "" : ", ") + std::string(u.key);
      throw Error(ErrorCode::kInvalidArgument, where + ": unknown option '" + key + "' (known: " + known + ")");
    }
    if (!set_uri_option(*opt, value, &o)) {
      throw Error(ErrorCode::kInvalidArgument, where + ": option " + key + "=" + value + " is not " +
                                                   (opt->int_field ? "an integer" : "0/1/true/false"));
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
  info.uri = "aravis://" + percent_encode(d.id);
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

// Where to open a camera: what arv_camera_new() gets, and what is known of the camera so far.
struct Found {
  DeviceInfo info;
  Locator locator;
  std::string target;
};

// By IPv4 address: straight to it (no discovery, so routed subnets work too); the probe keeps a
// missing camera from costing Aravis' 2.5 s connection timeout.
Found find_by_address(const Uri& uri, const std::string& path, const AravisBackendOptions& options) {
  Found f;
  DeviceInfo& info = f.info;
  Locator& locator = f.locator;
  std::string& target = f.target;
  if (!gvcp_probe(path, options.probe_timeout_ms, options.probe_retries)) {
    throw Error(ErrorCode::kNotFound,
                "camera '" + uri.text + "' not found: no GigE Vision camera answers at " + path);
  }
  info.uri = "aravis://" + path;
  locator.gige = true;
  locator.address = path;
  target = path;
  return f;
}

// By device id, serial number or physical id, through Aravis' discovery.
Found find_by_discovery(const Uri& uri, const std::string& path) {
  Found f;
  DeviceInfo& info = f.info;
  Locator& locator = f.locator;
  std::string& target = f.target;
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
  return f;
}

GPtr<ArvCamera> connect(const Uri& uri, const std::string& target) {
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
  return camera;
}

// The identity the camera reports itself, checked against what discovery said.
void complete_identity(ArvCamera* cam, const Uri& uri, const std::string& target, DeviceInfo* info_out,
                       Locator* locator_out) {
  DeviceInfo& info = *info_out;
  Locator& locator = *locator_out;
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
}

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
  Found f = is_ipv4_address(path) ? find_by_address(uri, path, options) : find_by_discovery(uri, path);
  GPtr<ArvCamera> camera = connect(uri, f.target);
  complete_identity(camera.get(), uri, f.target, &f.info, &f.locator);
  return std::make_unique<AravisCameraImpl>(std::move(camera), std::move(f.info), std::move(f.locator),
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
