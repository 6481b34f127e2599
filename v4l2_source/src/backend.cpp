// V4l2Backend: enumeration and opening by URI (identity from sysfs), USB hot-plug.
#include <fcntl.h>

#include <algorithm>
#include <chrono>
#include <condition_variable>
#include <cstdio>
#include <deque>
#include <filesystem>
#include <mutex>
#include <optional>
#include <thread>

#include "v4l2_internal.hpp"

namespace posecal {

namespace fs = std::filesystem;

std::string UsbHotplugEvent::sysfs_name() const {
  if (ports.empty()) return "";
  std::string s = std::to_string(bus) + "-";
  for (size_t i = 0; i < ports.size(); ++i) {
    if (i) s.push_back('.');
    s.append(std::to_string(ports[i]));
  }
  return s;
}

void V4l2BackendOptions::validate() const {
  if (sysfs_root.empty())
    throw Error(ErrorCode::kInvalidArgument, "V4l2BackendOptions.sysfs_root is empty");
  if (dev_root.empty())
    throw Error(ErrorCode::kInvalidArgument, "V4l2BackendOptions.dev_root is empty");
  if (hotplug_settle_ms < 0 || hotplug_settle_ms > 60000) {
    throw Error(ErrorCode::kInvalidArgument,
                "V4l2BackendOptions.hotplug_settle_ms must be within [0, 60000]");
  }
}

struct V4l2Backend::Impl {
  V4l2BackendOptions options;
  std::shared_ptr<V4l2Io> io;

  std::mutex control_mutex;  // serialises starting and stopping hot-plug
  std::shared_ptr<UsbEventSource> source;
  std::thread worker;
  std::string status;

  std::mutex mutex;  // guards everything below
  std::condition_variable wake;
  std::deque<UsbHotplugEvent> queue;
  bool stopping = false;
  HotplugCallback callback;
  // Cameras announced per USB device ("1-2"), so that a removal can name them after sysfs has
  // forgotten the device.
  std::map<std::string, std::vector<DeviceInfo>> known;

  ~Impl() { stop_hotplug(); }

  // Opens the node and asks VIDIOC_QUERYCAP: false if it cannot be opened; *info is set for a
  // video-capture node only.
  bool probe(const V4l2NodeIdentity& id, std::optional<DeviceInfo>* info) {
    info->reset();
    const int fd = io->open(id.dev_path.c_str(), O_RDWR | O_NONBLOCK);
    if (fd < 0) return false;
    v4l2_capability cap{};
    const int err = v4l2::xioctl(*io, fd, VIDIOC_QUERYCAP, &cap);
    io->close(fd);
    if (!err && v4l2::is_video_capture(v4l2::node_caps(cap)))
      *info = v4l2::make_device_info(id, cap);
    return true;
  }
  std::optional<DeviceInfo> describe(const V4l2NodeIdentity& id) {
    std::optional<DeviceInfo> info;
    probe(id, &info);
    return info;
  }

  V4l2NodeIdentity identify(const std::string& node) const {
    return identify_v4l2_node(options.sysfs_root, options.dev_root, node);
  }

  void start_hotplug(HotplugCallback cb);
  void stop_hotplug();
  void worker_loop();
  void handle(const UsbHotplugEvent& e);
  void notify(const DeviceInfo& info, bool added) {
    HotplugCallback cb;
    {
      std::lock_guard<std::mutex> lock(mutex);
      cb = callback;
    }
    if (cb) cb(info, added);
  }
};

V4l2Backend::V4l2Backend(V4l2BackendOptions options) : impl_(std::make_shared<Impl>()) {
  options.validate();
  impl_->options = std::move(options);
  impl_->io = impl_->options.io ? impl_->options.io : make_system_v4l2_io();
}

V4l2Backend::~V4l2Backend() = default;

std::vector<DeviceInfo> V4l2Backend::enumerate() {
  std::vector<DeviceInfo> out;
  for (const std::string& node :
       list_v4l2_nodes(impl_->options.sysfs_root, impl_->options.dev_root)) {
    if (auto info = impl_->describe(impl_->identify(node))) out.push_back(*info);
  }
  return out;
}

std::unique_ptr<Camera> V4l2Backend::open(const Uri& uri) {
  if (uri.scheme != "v4l2") {
    throw Error(ErrorCode::kInvalidArgument, "V4L2 backend cannot open '" + uri.text + "'");
  }
  if (!uri.query.empty()) {
    throw Error(ErrorCode::kInvalidArgument, uri.text + ": v4l2 URIs take no options");
  }
  const std::string& p = uri.path;
  if (p.empty()) {
    throw Error(ErrorCode::kInvalidArgument,
                uri.text + ": names no camera (v4l2://<stable id> or v4l2:///dev/videoN)");
  }
  const Impl& impl = *impl_;
  V4l2NodeIdentity id;
  if (p[0] == '/') {
    std::string dev = p;
    if (impl.options.dev_root != "/dev" && p.rfind("/dev/", 0) == 0) {
      dev = impl.options.dev_root + p.substr(4);
    }
    // Follow links such as /dev/v4l/by-id/... lexically: the node's name is what sysfs knows.
    fs::path path(dev);
    for (int i = 0; i < 8; ++i) {
      std::error_code ec;
      if (!fs::is_symlink(path, ec)) break;
      const fs::path target = fs::read_symlink(path, ec);
      if (ec) break;
      path = target.is_absolute() ? target : (path.parent_path() / target).lexically_normal();
    }
    id = impl.identify(path.filename().string());
    id.dev_path = path.string();
  } else {
    std::vector<V4l2NodeIdentity> matches;
    std::string present;
    for (const std::string& node :
         list_v4l2_nodes(impl.options.sysfs_root, impl.options.dev_root)) {
      V4l2NodeIdentity candidate = impl.identify(node);
      if (candidate.stable_id.empty()) continue;
      present += (present.empty() ? "" : ", ") + candidate.stable_id;
      if (candidate.stable_id == p) matches.push_back(candidate);
    }
    if (matches.empty()) {
      throw Error(ErrorCode::kNotFound, uri.text + ": no V4L2 camera with this id (present: " +
                                            (present.empty() ? "none" : present) + ")");
    }
    if (matches.size() > 1) {
      std::string nodes;
      for (const auto& m : matches) nodes += (nodes.empty() ? "" : ", ") + m.dev_path;
      throw Error(ErrorCode::kInvalidArgument,
                  uri.text + ": id is ambiguous (identical cameras without serial numbers: " +
                      nodes + "); open one by its node path, v4l2:///dev/videoN");
    }
    id = matches.front();
  }
  return v4l2::open_v4l2_camera(impl.io, id, uri.text);
}

void V4l2Backend::set_hotplug_callback(HotplugCallback cb) {
  if (cb) {
    impl_->start_hotplug(std::move(cb));
  } else {
    impl_->stop_hotplug();
  }
}

std::string V4l2Backend::hotplug_status() const {
  std::lock_guard<std::mutex> lock(impl_->control_mutex);
  return impl_->status;
}

void V4l2Backend::Impl::start_hotplug(HotplugCallback cb) {
  std::lock_guard<std::mutex> control(control_mutex);
  if (source) {
    std::lock_guard<std::mutex> lock(mutex);
    callback = std::move(cb);
    return;
  }
  // Cameras present now, so that their removal can be reported.
  std::map<std::string, std::vector<DeviceInfo>> present;
  for (const std::string& node : list_v4l2_nodes(options.sysfs_root, options.dev_root)) {
    const V4l2NodeIdentity id = identify(node);
    if (!id.usb) continue;
    if (auto info = describe(id)) present[id.usb_device].push_back(*info);
  }
  {
    std::lock_guard<std::mutex> lock(mutex);
    known = std::move(present);
    callback = std::move(cb);
    stopping = false;
    queue.clear();
  }
  worker = std::thread([this] { worker_loop(); });
  std::shared_ptr<UsbEventSource> s =
      options.usb_events ? options.usb_events : make_libusb_event_source();
  std::string why;
  const bool ok = s->start(
      [this](const UsbHotplugEvent& e) {
        std::lock_guard<std::mutex> lock(mutex);
        queue.push_back(e);
        wake.notify_all();
      },
      &why);
  if (!ok) {
    {
      std::lock_guard<std::mutex> lock(mutex);
      stopping = true;
      callback = nullptr;
    }
    wake.notify_all();
    worker.join();
    status = "USB hot-plug unavailable: " + (why.empty() ? std::string("unknown reason") : why) +
             "; cameras plugged in later are found by enumerating again";
    std::fprintf(stderr, "posecal v4l2: %s\n", status.c_str());
    return;
  }
  source = std::move(s);
  status.clear();
}

void V4l2Backend::Impl::stop_hotplug() {
  std::lock_guard<std::mutex> control(control_mutex);
  if (source) source->stop();  // no handler call after this returns
  source.reset();
  {
    std::lock_guard<std::mutex> lock(mutex);
    stopping = true;
    callback = nullptr;
    queue.clear();
  }
  wake.notify_all();
  if (worker.joinable()) {
    // A callback that stops hot-plug from the worker itself cannot join it (documented as not
    // allowed); detach rather than deadlock.
    if (worker.get_id() == std::this_thread::get_id()) {
      worker.detach();
    } else {
      worker.join();
    }
  }
}

void V4l2Backend::Impl::worker_loop() {
  for (;;) {
    UsbHotplugEvent e;
    {
      std::unique_lock<std::mutex> lock(mutex);
      wake.wait(lock, [&] { return stopping || !queue.empty(); });
      if (stopping) return;
      e = queue.front();
      queue.pop_front();
    }
    try {
      handle(e);
    } catch (const std::exception& ex) {
      // A failing callback or file system hiccup must not end hot-plug handling.
      std::fprintf(stderr, "posecal v4l2: hot-plug event for USB device %s: %s\n",
                   e.sysfs_name().c_str(), ex.what());
    }
  }
}

void V4l2Backend::Impl::handle(const UsbHotplugEvent& e) {
  const std::string name = e.sysfs_name();
  if (name.empty()) return;  // root hub
  if (e.kind == UsbHotplugEvent::Kind::kLeft) {
    std::vector<DeviceInfo> gone;
    {
      std::lock_guard<std::mutex> lock(mutex);
      auto it = known.find(name);
      if (it == known.end()) return;
      gone = std::move(it->second);
      known.erase(it);
    }
    for (const DeviceInfo& info : gone) notify(info, false);
    return;
  }
  // Arrived. libusb reports the USB device as soon as it exists; its interfaces, uvcvideo's
  // binding and the /dev node (with udev's permissions) follow within a second or so.
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::milliseconds(options.hotplug_settle_ms);
  std::vector<DeviceInfo> cameras;
  for (;;) {
    const std::vector<std::string> classes = usb_interface_classes(options.sysfs_root, name);
    if (!classes.empty() && std::find(classes.begin(), classes.end(), "0e") == classes.end()) {
      return;  // configured, and no Video interface: not a camera
    }
    const std::vector<std::string> nodes = v4l2_nodes_of_usb_device(options.sysfs_root, name);
    bool all_described = !nodes.empty();
    cameras.clear();
    for (const std::string& node : nodes) {
      std::optional<DeviceInfo> info;
      if (!probe(identify(node), &info)) {
        all_described = false;  // node not created or not yet accessible
        continue;
      }
      if (info) cameras.push_back(*info);
    }
    if (all_described) break;
    std::unique_lock<std::mutex> lock(mutex);
    if (std::chrono::steady_clock::now() >= deadline) break;
    if (wake.wait_for(lock, std::chrono::milliseconds(50), [&] { return stopping; })) return;
  }
  if (cameras.empty()) return;
  {
    std::lock_guard<std::mutex> lock(mutex);
    known[name] = cameras;
  }
  for (const DeviceInfo& info : cameras) notify(info, true);
}

std::shared_ptr<CameraBackend> make_v4l2_backend(const V4l2BackendOptions& options) {
  return std::make_shared<V4l2Backend>(options);
}

}  // namespace posecal
