#include <mutex>

#include "common/error.hpp"
#include "device/camera.hpp"

namespace posecal {

struct CameraManager::Impl {
  mutable std::mutex mutex;
  std::vector<std::shared_ptr<CameraBackend>> backends;
  CameraBackend::HotplugCallback hotplug;
};

CameraManager::CameraManager() : impl_(std::make_unique<Impl>()) {}
CameraManager::~CameraManager() {
  // Detach hot-plug callbacks before the backends go away.
  for (auto& b : impl_->backends) b->set_hotplug_callback(nullptr);
}

void CameraManager::add_backend(std::shared_ptr<CameraBackend> backend) {
  if (!backend) throw Error(ErrorCode::kInvalidArgument, "add_backend: null backend");
  std::lock_guard<std::mutex> lock(impl_->mutex);
  for (auto& b : impl_->backends) {
    if (b->scheme() == backend->scheme()) {
      b = backend;
      return;
    }
  }
  impl_->backends.push_back(backend);
  if (impl_->hotplug) backend->set_hotplug_callback(impl_->hotplug);
}

std::vector<std::string> CameraManager::schemes() const {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  std::vector<std::string> out;
  for (const auto& b : impl_->backends) out.push_back(b->scheme());
  return out;
}

std::vector<DeviceInfo> CameraManager::list(std::vector<std::string>* errors) {
  std::vector<std::shared_ptr<CameraBackend>> backends;
  {
    std::lock_guard<std::mutex> lock(impl_->mutex);
    backends = impl_->backends;
  }
  std::vector<DeviceInfo> out;
  for (const auto& b : backends) {
    try {
      auto devices = b->enumerate();
      out.insert(out.end(), devices.begin(), devices.end());
    } catch (const std::exception& e) {
      if (errors) errors->push_back(b->scheme() + ": " + e.what());
    }
  }
  return out;
}

std::unique_ptr<Camera> CameraManager::open(const std::string& uri_text) {
  const Uri uri = Uri::parse(uri_text);
  std::shared_ptr<CameraBackend> backend;
  {
    std::lock_guard<std::mutex> lock(impl_->mutex);
    for (const auto& b : impl_->backends) {
      if (b->scheme() == uri.scheme) backend = b;
    }
  }
  if (!backend) {
    std::string known;
    for (const auto& s : schemes()) known += (known.empty() ? "" : ", ") + s;
    throw Error(ErrorCode::kInvalidArgument, "camera URI '" + uri_text + "': unknown scheme '" +
                                                 uri.scheme + "' (known: " + known + ")");
  }
  return backend->open(uri);
}

void CameraManager::set_hotplug_callback(CameraBackend::HotplugCallback cb) {
  std::lock_guard<std::mutex> lock(impl_->mutex);
  impl_->hotplug = cb;
  for (auto& b : impl_->backends) b->set_hotplug_callback(cb);
}

}  // namespace posecal
