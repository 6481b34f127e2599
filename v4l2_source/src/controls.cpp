// V4l2Camera: controls as features (QUERY_EXT_CTRL / QUERYCTRL, QUERYMENU, G/S_EXT_CTRLS or
// G/S_CTRL) and the calibration lock.
#include <fcntl.h>
#include <sys/mman.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <numeric>
#include <optional>
#include <charconv>

#include "camera_internal.hpp"

namespace posecal::v4l2 {

namespace {

bool parse_int64(const std::string& s, int64_t* v) {
  const char* b = s.data();
  const char* e = s.data() + s.size();
  if (b != e && *b == '+') ++b;
  const auto r = std::from_chars(b, e, *v);
  return r.ec == std::errc() && r.ptr == e && b != e;
}

FeatureType control_feature_type(uint32_t type) {
  switch (type) {
    case V4L2_CTRL_TYPE_BOOLEAN:
      return FeatureType::kBoolean;
    case V4L2_CTRL_TYPE_MENU:
    case V4L2_CTRL_TYPE_INTEGER_MENU:
      return FeatureType::kEnumeration;
    case V4L2_CTRL_TYPE_BUTTON:
      return FeatureType::kCommand;
    case V4L2_CTRL_TYPE_STRING:
      return FeatureType::kString;
    default:  // integer, 64-bit integer, bitmask; other types are not listed
      return FeatureType::kInteger;
  }
}

const char* control_unit(uint32_t id) {
  switch (id) {
    case V4L2_CID_EXPOSURE_ABSOLUTE:
      return "100 us";
    case V4L2_CID_WHITE_BALANCE_TEMPERATURE:
      return "K";
    case V4L2_CID_PAN_ABSOLUTE:
    case V4L2_CID_TILT_ABSOLUTE:
      return "arcsec";
    default:
      return "";
  }
}

}  // namespace

bool V4l2CameraImpl::query_control(uint32_t id_and_flags, Control* out, int* err) {
  if (query_ext_ctrl_) {
    v4l2_query_ext_ctrl q{};
    q.id = id_and_flags;
    *err = ioctl(VIDIOC_QUERY_EXT_CTRL, &q);
    if (*err == ENOTTY) {
      query_ext_ctrl_ = false;
    } else if (*err) {
      return false;
    } else {
      out->id = q.id;
      out->type = q.type;
      out->label = fixed_string(q.name, sizeof(q.name));
      out->minimum = q.minimum;
      out->maximum = q.maximum;
      out->step = q.step;
      out->default_value = q.default_value;
      out->flags = q.flags;
      return true;
    }
  }
  v4l2_queryctrl q{};
  // QUERYCTRL knows no compound controls; NEXT_COMPOUND would make old drivers fail.
  q.id = id_and_flags & ~V4L2_CTRL_FLAG_NEXT_COMPOUND;
  *err = ioctl(VIDIOC_QUERYCTRL, &q);
  if (*err) return false;
  out->id = q.id;
  out->type = q.type;
  out->label = fixed_string(q.name, sizeof(q.name));
  out->minimum = q.minimum;
  out->maximum = q.maximum;
  out->step = static_cast<uint64_t>(std::max(q.step, 0));
  out->default_value = q.default_value;
  out->flags = q.flags;
  return true;
}

void V4l2CameraImpl::enumerate_controls() {
  controls_.clear();
  uint32_t id = 0;
  for (int n = 0; n < kMaxEnumerations; ++n) {
    Control c;
    int err = 0;
    if (!query_control(id | V4L2_CTRL_FLAG_NEXT_CTRL | V4L2_CTRL_FLAG_NEXT_COMPOUND, &c, &err)) {
      if (err == EINVAL || err == ENOTTY) break;
      fail("VIDIOC_QUERY_EXT_CTRL", err);
    }
    if (c.id <= id) break;  // a driver that ignores NEXT_CTRL would loop forever
    id = c.id;
    if (c.type == V4L2_CTRL_TYPE_CTRL_CLASS || (c.flags & V4L2_CTRL_FLAG_DISABLED) ||
        c.type >= V4L2_CTRL_COMPOUND_TYPES) {
      continue;
    }
    if (c.type == V4L2_CTRL_TYPE_MENU || c.type == V4L2_CTRL_TYPE_INTEGER_MENU) {
      for (int64_t i = std::max<int64_t>(c.minimum, 0); i <= c.maximum && i - c.minimum < 256;
           ++i) {
        v4l2_querymenu m{};
        m.id = c.id;
        m.index = static_cast<uint32_t>(i);
        if (const int e = ioctl(VIDIOC_QUERYMENU, &m)) {
          if (e == EINVAL) continue;  // an index the driver skips (menu_skip_mask)
          fail("VIDIOC_QUERYMENU", e);
        }
        c.menu.emplace_back(i, c.type == V4L2_CTRL_TYPE_MENU ? fixed_string(m.name, sizeof(m.name))
                                                             : std::to_string(m.value));
      }
    }
    std::string name = v4l2_control_name(c.label);
    if (name.empty()) name = "control_" + std::to_string(c.id);
    std::string unique = name;
    for (int k = 2; find_control(unique); ++k) unique = name + "_" + std::to_string(k);
    c.name = unique;
    controls_.push_back(std::move(c));
  }
}

void V4l2CameraImpl::refresh_flags(Control* c) {
  Control fresh;
  int err = 0;
  if (query_control(c->id, &fresh, &err)) {
    c->flags = fresh.flags;
  } else if (is_gone(err)) {
    fail("VIDIOC_QUERY_EXT_CTRL", err);
  }
}

Control* V4l2CameraImpl::find_control(const std::string& name) {
  for (auto& c : controls_) {
    if (c.name == name) return &c;
  }
  return nullptr;
}

Control* V4l2CameraImpl::find_control(uint32_t id) {
  for (auto& c : controls_) {
    if (c.id == id) return &c;
  }
  return nullptr;
}

int64_t V4l2CameraImpl::control_value(const Control& c) {
  if (ext_ctrls_) {
    v4l2_ext_control ec{};
    ec.id = c.id;
    v4l2_ext_controls cs{};
    cs.which = V4L2_CTRL_ID2WHICH(c.id);  // the control's class: accepted by every kernel
    cs.count = 1;
    cs.controls = &ec;
    const int err = ioctl(VIDIOC_G_EXT_CTRLS, &cs);
    if (err == 0) return c.type == V4L2_CTRL_TYPE_INTEGER64 ? ec.value64 : ec.value;
    if (err != ENOTTY) fail("VIDIOC_G_EXT_CTRLS(" + c.name + ")", err);
    ext_ctrls_ = false;
  }
  if (c.type == V4L2_CTRL_TYPE_INTEGER64) {
    throw Error(ErrorCode::kUnsupported, who() + ": 64-bit control '" + c.name +
                                             "' needs extended controls, which the driver lacks");
  }
  v4l2_control ctl{};
  ctl.id = c.id;
  if (const int err = ioctl(VIDIOC_G_CTRL, &ctl)) fail("VIDIOC_G_CTRL(" + c.name + ")", err);
  return ctl.value;
}

std::string V4l2CameraImpl::control_text(const Control& c) {
  if (c.type == V4L2_CTRL_TYPE_STRING) {
    std::vector<char> buf(static_cast<size_t>(std::max<int64_t>(c.maximum, 0)) + 1, '\0');
    v4l2_ext_control ec{};
    ec.id = c.id;
    ec.size = static_cast<uint32_t>(buf.size());
    ec.string = buf.data();
    v4l2_ext_controls cs{};
    cs.which = V4L2_CTRL_ID2WHICH(c.id);
    cs.count = 1;
    cs.controls = &ec;
    if (const int err = ioctl(VIDIOC_G_EXT_CTRLS, &cs))
      fail("VIDIOC_G_EXT_CTRLS(" + c.name + ")", err);
    return fixed_string(buf.data(), buf.size());
  }
  return std::to_string(control_value(c));
}

int64_t V4l2CameraImpl::parse_control_value(const Control& c, const std::string& text) {
  const auto invalid = [&](const std::string& why) {
    return Error(ErrorCode::kInvalidArgument, who() + ": control '" + c.name + "': " + why);
  };
  int64_t v = 0;
  switch (c.type) {
    case V4L2_CTRL_TYPE_BOOLEAN: {
      if (text == "1" || text == "true" || text == "on" || text == "yes") return 1;
      if (text == "0" || text == "false" || text == "off" || text == "no") return 0;
      throw invalid("'" + text + "' is not a boolean (0/1, true/false, on/off)");
    }
    case V4L2_CTRL_TYPE_MENU:
    case V4L2_CTRL_TYPE_INTEGER_MENU: {
      bool numeric = parse_int64(text, &v);
      if (!numeric) {
        for (const auto& [index, item] : c.menu) {
          if (item == text || v4l2_control_name(item) == v4l2_control_name(text)) {
            v = index;
            numeric = true;
          }
        }
      }
      std::string items;
      for (const auto& [index, item] : c.menu) {
        items += (items.empty() ? "" : ", ") + std::to_string(index) + ": " + item;
      }
      if (!numeric) throw invalid("'" + text + "' is not one of its items (" + items + ")");
      const bool valid =
          std::any_of(c.menu.begin(), c.menu.end(), [&](const auto& m) { return m.first == v; });
      if (!valid) {
        throw invalid("value " + std::to_string(v) + " is out of range (items: " + items + ")");
      }
      return v;
    }
    case V4L2_CTRL_TYPE_BUTTON:
      return 1;
    default: {
      if (!parse_int64(text, &v)) throw invalid("'" + text + "' is not an integer");
      if (v < c.minimum || v > c.maximum) {
        throw invalid("value " + std::to_string(v) + " is out of range [" +
                      std::to_string(c.minimum) + ", " + std::to_string(c.maximum) + "]");
      }
      return v;
    }
  }
}

void V4l2CameraImpl::write_control(Control& c, int64_t value, const std::string& text) {
  if (c.flags & V4L2_CTRL_FLAG_READ_ONLY) {
    throw Error(ErrorCode::kInvalidArgument, who() + ": control '" + c.name + "' is read-only");
  }
  int err = ENOTTY;
  if (ext_ctrls_ || c.type == V4L2_CTRL_TYPE_STRING) {
    v4l2_ext_control ec{};
    ec.id = c.id;
    std::string s = text;
    if (c.type == V4L2_CTRL_TYPE_STRING) {
      if (static_cast<int64_t>(s.size()) < c.minimum ||
          static_cast<int64_t>(s.size()) > c.maximum) {
        throw Error(ErrorCode::kInvalidArgument,
                    who() + ": control '" + c.name + "': length " + std::to_string(s.size()) +
                        " is out of range [" + std::to_string(c.minimum) + ", " +
                        std::to_string(c.maximum) + "]");
      }
      ec.size = static_cast<uint32_t>(s.size() + 1);
      ec.string = s.data();
    } else if (c.type == V4L2_CTRL_TYPE_INTEGER64) {
      ec.value64 = value;
    } else {
      ec.value = static_cast<int32_t>(value);
    }
    v4l2_ext_controls cs{};
    cs.which = V4L2_CTRL_ID2WHICH(c.id);
    cs.count = 1;
    cs.controls = &ec;
    err = ioctl(VIDIOC_S_EXT_CTRLS, &cs);
    if (err == ENOTTY && c.type != V4L2_CTRL_TYPE_STRING) ext_ctrls_ = false;
  }
  if (err == ENOTTY && !ext_ctrls_ && c.type != V4L2_CTRL_TYPE_STRING &&
      c.type != V4L2_CTRL_TYPE_INTEGER64) {
    v4l2_control ctl{};
    ctl.id = c.id;
    ctl.value = static_cast<int32_t>(value);
    err = ioctl(VIDIOC_S_CTRL, &ctl);
  }
  if (err == 0) return;
  if (is_gone(err)) fail("set control '" + c.name + "'", err);
  if (err == EACCES) {
    refresh_flags(&c);
    throw Error(ErrorCode::kInvalidArgument,
                who() + ": control '" + c.name + "' cannot be written now" +
                    ((c.flags & V4L2_CTRL_FLAG_INACTIVE)
                         ? " (inactive: its automatic mode is on, e.g. auto_exposure or "
                           "focus_automatic_continuous)"
                         : " (" + errno_text(err) + ")"));
  }
  if (err == ERANGE || err == EINVAL) {
    throw Error(ErrorCode::kInvalidArgument, who() + ": control '" + c.name + "' rejects value " +
                                                 text + " (" + errno_text(err) + ")");
  }
  throw Error(ErrorCode::kDevice,
              who() + ": setting control '" + c.name + "' failed: " + errno_text(err));
}

std::vector<FeatureInfo> V4l2CameraImpl::do_features() {
  std::vector<FeatureInfo> out;
  for (auto& c : controls_) {
    refresh_flags(&c);
    FeatureInfo f;
    f.name = c.name;
    f.type = control_feature_type(c.type);
    f.readable = c.type != V4L2_CTRL_TYPE_BUTTON && !(c.flags & V4L2_CTRL_FLAG_WRITE_ONLY);
    f.writable = !(c.flags & (V4L2_CTRL_FLAG_READ_ONLY | V4L2_CTRL_FLAG_INACTIVE));
    f.unit = control_unit(c.id);
    if (f.readable) f.value = control_text(c);
    if (c.type == V4L2_CTRL_TYPE_INTEGER || c.type == V4L2_CTRL_TYPE_INTEGER64 ||
        c.type == V4L2_CTRL_TYPE_BOOLEAN || c.type == V4L2_CTRL_TYPE_BITMASK) {
      f.min = std::to_string(c.minimum);
      f.max = std::to_string(c.maximum);
    }
    for (const auto& [index, item] : c.menu)
      f.options.push_back(std::to_string(index) + ": " + item);
    out.push_back(std::move(f));
  }
  return out;
}

std::string V4l2CameraImpl::do_get_feature(const std::string& name) {
  Control* c = find_control(name);
  if (!c) throw Error(ErrorCode::kNotFound, who() + ": no control '" + name + "'");
  if (c->type == V4L2_CTRL_TYPE_BUTTON || (c->flags & V4L2_CTRL_FLAG_WRITE_ONLY)) {
    throw Error(ErrorCode::kInvalidArgument, who() + ": control '" + name + "' is write-only");
  }
  return control_text(*c);
}

void V4l2CameraImpl::do_set_feature(const std::string& name, const std::string& value) {
  Control* c = find_control(name);
  if (!c) throw Error(ErrorCode::kNotFound, who() + ": no control '" + name + "'");
  const int64_t v = c->type == V4L2_CTRL_TYPE_STRING ? 0 : parse_control_value(*c, value);
  write_control(*c, v, c->type == V4L2_CTRL_TYPE_STRING ? value : std::to_string(v));
}

std::map<std::string, std::string> V4l2CameraImpl::do_lock_for_calibration() {
  std::map<std::string, std::string> locked;
  // 1. Automatic modes off. Exposure priority ("dynamic framerate") lets the camera lengthen
  //    the exposure at the cost of frame rate, so it goes too. Looked up by control id, not by
  //    name, because kernels renamed them (focus_auto -> focus_automatic_continuous).
  if (Control* c = find_control(V4L2_CID_FOCUS_AUTO)) {
    write_control(*c, 0, "0");
    locked.insert_or_assign(c->name, std::string("0"));
  }
  if (Control* c = find_control(V4L2_CID_EXPOSURE_AUTO)) {
    const bool has_manual = std::any_of(c->menu.begin(), c->menu.end(), [](const auto& m) {
      return m.first == V4L2_EXPOSURE_MANUAL;
    });
    if (!has_manual) {
      throw Error(ErrorCode::kUnsupported,
                  who() + ": auto_exposure has no manual mode, exposure cannot be locked");
    }
    write_control(*c, V4L2_EXPOSURE_MANUAL, "1");
    locked[c->name] = std::to_string(V4L2_EXPOSURE_MANUAL);
  }
  for (uint32_t id : {V4L2_CID_EXPOSURE_AUTO_PRIORITY, V4L2_CID_AUTOGAIN}) {
    if (Control* c = find_control(id); c && !(c->flags & V4L2_CTRL_FLAG_READ_ONLY)) {
      write_control(*c, 0, "0");
      locked.insert_or_assign(c->name, std::string("0"));
    }
  }
  // 2. Fix the values the automatics left behind, now that the controls are active.
  for (uint32_t id :
       {V4L2_CID_FOCUS_ABSOLUTE, V4L2_CID_EXPOSURE_ABSOLUTE, V4L2_CID_EXPOSURE, V4L2_CID_GAIN}) {
    Control* c = find_control(id);
    if (!c || (c->flags & V4L2_CTRL_FLAG_READ_ONLY)) continue;
    const int64_t v = control_value(*c);
    write_control(*c, v, std::to_string(v));
    locked[c->name] = std::to_string(control_value(*c));
  }
  return locked;
}

}  // namespace posecal::v4l2
