// The context behind posecal_context: the camera manager with every enabled backend. The handle
// holds it by shared_ptr and so does every session opened on it, so cameras never outlive their
// backends whatever order a host destroys things in. Thread-safe: every member may be called
// from several threads.
#pragma once

#include <map>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>
#include <vector>

#include "posecal.h"
#include "device/camera.hpp"
#include "board/board.hpp"

namespace posecal::abi {

class Context {
 public:
  explicit Context(const nlohmann::json& options);

  // Backends this build knows, in listing order.
  static const std::vector<std::string>& known_backends();
  bool enabled(const std::string& scheme) const;
  // Error(kUnsupported) naming the scheme unless its backend is enabled in this context.
  void require_enabled(const std::string& scheme) const;

  // Cameras of every enabled backend; a backend that fails to enumerate is reported in *errors.
  std::vector<posecal::DeviceInfo> list(std::vector<std::string>* errors);
  // Opens a camera by URI. sim:// cameras show `target` (the board the caller will look for).
  std::unique_ptr<posecal::Camera> open(const std::string& uri, const posecal::BoardSpec& target);

  // Buffer protocol of calls that do work once (grab, evaluate, features, list): when the
  // caller's buffer is too small the JSON is kept here, per calling thread and function, and a
  // retry with the same arguments returns it instead of doing the work again.
  bool take_pending(const char* function, const std::string& args, std::string* text);
  void keep_pending(const char* function, const std::string& args, const std::string& text);

 private:
  std::vector<std::string> enabled_;
  posecal::CameraManager manager_;
  std::mutex pending_mutex_;
  struct Pending {
    std::string args;
    std::string text;
  };
  std::map<std::pair<std::thread::id, std::string>, Pending> pending_;
};

// copy_out() that keeps the text in the context for a retry when the buffer is too small.
posecal_status copy_out_kept(Context& ctx, const char* function, const std::string& args,
                             const std::string& text, char* buf, size_t* size);

}  // namespace posecal::abi

// The C handle.
struct posecal_context {
  std::shared_ptr<posecal::abi::Context> impl;
};
