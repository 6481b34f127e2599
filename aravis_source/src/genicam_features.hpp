// Generic GenICam feature access by name, through Aravis' node tree (ArvGc). Aravis' node tree is
// not thread-safe: callers hold the camera's device lock. `camera` is the label that names the
// camera in error messages ("camera 'aravis://...'").
#pragma once

#include <arv.h>

#include <optional>
#include <string>
#include <vector>

#include "device/camera.hpp"

namespace posecal::aravis {

// The implemented feature node of that name, or nullptr.
ArvGcFeatureNode* find_feature(ArvDevice* device, const std::string& name);
// The node's type; nullopt for nodes that carry
// no value (categories, ports, enumeration entries).
std::optional<FeatureType> feature_type(ArvGcFeatureNode* node);
FeatureInfo describe_feature(ArvGcFeatureNode* node);

// Every visible value feature: the category tree under "Root" first, then features that no
// category lists, in document order.
std::vector<FeatureInfo> list_features(ArvDevice* device);

// Throws Error(kNotFound) for an unknown feature, Error(kInvalidArgument) for a write-only
// feature or a command, Error(kDevice) if the camera does not answer.
std::string read_feature(ArvDevice* device, const std::string& camera, const std::string& name);

// Checks the value against the feature's type, range, increment and options before writing it.
// Throws Error(kNotFound) for an unknown feature; Error(kInvalidArgument) for a read-only,
// unavailable or locked feature or a bad value (naming both); Error(kDevice) if the camera fails.
// Commands are executed for value "" or "execute".
void write_feature(ArvDevice* device, const std::string& camera, const std::string& name,
                   const std::string& value);

// Enumeration entries currently available ("" entries skipped); empty for other types.
std::vector<std::string> enumeration_options(ArvGcFeatureNode* node);

}  // namespace posecal::aravis
