// The context behind posecal_context: the camera manager with every enabled backend.
#pragma once

#include <nlohmann/json.hpp>

#include "posecal/camera.hpp"

struct posecal_context {
  explicit posecal_context(const nlohmann::json& options);
  posecal::CameraManager& manager() { return manager_; }

 private:
  posecal::CameraManager manager_;
};
