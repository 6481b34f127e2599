#include "device/guidance.hpp"

namespace posecal {

const char* target_kind_name(TargetKind kind) {
  switch (kind) {
    case TargetKind::kInitTilted: return "init-tilted";
    case TargetKind::kInitFrontoParallel: return "init-fronto-parallel";
    case TargetKind::kPinhole: return "pinhole";
    case TargetKind::kDistortion: return "distortion";
    case TargetKind::kView: return "view";
  }
  return "unknown";
}

}  // namespace posecal
