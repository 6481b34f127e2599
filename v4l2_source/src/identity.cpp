// sysfs -> stable identity of video nodes (see v4l2_identity.hpp for the layout it reads).
#include <algorithm>
#include <cctype>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <optional>
#include <set>
#include <sstream>

#include "posecal/v4l2_identity.hpp"

namespace posecal {

namespace fs = std::filesystem;

namespace {

// A sysfs attribute as udev reads it: the file's text without the trailing newline.
std::optional<std::string> read_attr(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return std::nullopt;
  std::stringstream ss;
  ss << in.rdbuf();
  std::string s = ss.str();
  const size_t nul = s.find('\0');
  if (nul != std::string::npos) s.resize(nul);
  while (!s.empty() && (s.back() == '\n' || s.back() == '\r')) s.pop_back();
  return s;
}

std::string attr_or_empty(const fs::path& path) { return read_attr(path).value_or(""); }

// "video12" -> 12; -1 if the name is not video<digits>.
int node_number(const std::string& name) {
  if (name.size() <= 5 || name.compare(0, 5, "video") != 0) return -1;
  int n = 0;
  for (size_t i = 5; i < name.size(); ++i) {
    if (!std::isdigit(static_cast<unsigned char>(name[i])) || n > 100000) return -1;
    n = n * 10 + (name[i] - '0');
  }
  return n;
}

void sort_nodes(std::vector<std::string>* nodes) {
  std::sort(nodes->begin(), nodes->end(), [](const std::string& a, const std::string& b) {
    return node_number(a) < node_number(b);
  });
}

std::optional<fs::path> resolve(const fs::path& p) {
  std::error_code ec;
  fs::path r = fs::canonical(p, ec);
  if (ec) return std::nullopt;
  return r;
}

bool is_space(char c) { return std::isspace(static_cast<unsigned char>(c)) != 0; }

// systemd's udev_replace_whitespace: at most `max_len` bytes, leading/trailing whitespace
// dropped, every inner run of whitespace becomes one '_'.
std::string replace_whitespace(const std::string& in, size_t max_len) {
  std::string s = in.substr(0, max_len);
  while (!s.empty() && is_space(s.back())) s.pop_back();
  size_t i = 0;
  while (i < s.size() && (s[i] == ' ' || s[i] == '\t' || s[i] == '\n' || s[i] == '\r')) ++i;
  std::string out;
  bool in_space = false;
  for (; i < s.size(); ++i) {
    if (is_space(s[i])) {
      in_space = true;
      continue;
    }
    if (in_space) out.push_back('_');
    in_space = false;
    out.push_back(s[i]);
  }
  return out;
}

// Length of the valid multi-byte UTF-8 character at s[i] (2..4), or 0 if there is none.
size_t utf8_char_length(const std::string& s, size_t i) {
  const auto byte = [&](size_t k) { return static_cast<unsigned char>(s[k]); };
  const unsigned char lead = byte(i);
  size_t len = 0;
  uint32_t cp = 0;
  if ((lead & 0xE0) == 0xC0) {
    len = 2;
    cp = lead & 0x1F;
  } else if ((lead & 0xF0) == 0xE0) {
    len = 3;
    cp = lead & 0x0F;
  } else if ((lead & 0xF8) == 0xF0) {
    len = 4;
    cp = lead & 0x07;
  } else {
    return 0;
  }
  if (i + len > s.size()) return 0;
  for (size_t k = 1; k < len; ++k) {
    if ((byte(i + k) & 0xC0) != 0x80) return 0;
    cp = (cp << 6) | (byte(i + k) & 0x3F);
  }
  static constexpr uint32_t kMinForLength[5] = {0, 0, 0x80, 0x800, 0x10000};
  if (cp < kMinForLength[len]) return 0;  // overlong
  if (cp > 0x10FFFF || (cp >= 0xD800 && cp <= 0xDFFF)) return 0;
  if ((cp >= 0xFDD0 && cp <= 0xFDEF) || (cp & 0xFFFE) == 0xFFFE) return 0;  // non-characters
  return len;
}

// systemd's udev_replace_chars with no extra allowed characters.
std::string replace_chars(std::string s) {
  static const std::string kAllowed = "#+-.:=@_";
  size_t i = 0;
  while (i < s.size()) {
    const unsigned char c = static_cast<unsigned char>(s[i]);
    if (std::isalnum(c) && c < 0x80) {
      ++i;
    } else if (kAllowed.find(static_cast<char>(c)) != std::string::npos) {
      ++i;
    } else if (c == '\\' && i + 1 < s.size() && s[i + 1] == 'x') {
      i += 2;  // an already escaped character
    } else if (const size_t len = utf8_char_length(s, i); len > 1) {
      i += len;
    } else {
      s[i] = '_';
      ++i;
    }
  }
  return s;
}

std::optional<fs::path> usb_device_dir(const std::string& sysfs_root,
                                       const std::string& usb_device) {
  if (usb_device.empty() || usb_device.find('/') != std::string::npos) return std::nullopt;
  return resolve(fs::path(sysfs_root) / "bus" / "usb" / "devices" / usb_device);
}

// Interface directories ("1-2:1.0") of a USB device directory.
std::vector<fs::path> usb_interfaces(const fs::path& device_dir) {
  std::vector<fs::path> out;
  const std::string prefix = device_dir.filename().string() + ":";
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(device_dir, ec)) {
    const std::string n = e.path().filename().string();
    if (n.compare(0, prefix.size(), prefix) == 0) out.push_back(e.path());
  }
  std::sort(out.begin(), out.end());
  return out;
}

}  // namespace

std::string udev_usb_serial_id(const std::string& vendor_id, const std::string& product_id,
                               const std::string& manufacturer, const std::string& product,
                               const std::string& serial) {
  const std::string vendor = manufacturer.empty() ? vendor_id : manufacturer;
  const std::string model = product.empty() ? product_id : product;
  std::string id = replace_chars(replace_whitespace(vendor, 63)) + "_" +
                   replace_chars(replace_whitespace(model, 63));
  // usb_id drops serials with characters outside printable ASCII or with commas.
  const bool serial_ok = std::all_of(serial.begin(), serial.end(), [](char ch) {
    const unsigned char c = static_cast<unsigned char>(ch);
    return c >= 0x20 && c <= 0x7F && c != ',';
  });
  if (serial_ok) {
    const std::string s = replace_chars(replace_whitespace(serial, 511));
    if (!s.empty()) id += "_" + s;
  }
  if (id.size() > 255) id.resize(255);
  return id;
}

std::string v4l2_control_name(const std::string& kernel_name) {
  std::string out;
  bool pending_underscore = false;
  for (char ch : kernel_name) {
    const unsigned char c = static_cast<unsigned char>(ch);
    if (c < 0x80 && std::isalnum(c)) {
      if (pending_underscore) out.push_back('_');
      pending_underscore = false;
      out.push_back(static_cast<char>(std::tolower(c)));
    } else if (!out.empty()) {
      pending_underscore = true;
    }
  }
  return out;
}

std::vector<std::string> list_v4l2_nodes(const std::string& sysfs_root,
                                         const std::string& dev_root) {
  std::set<std::string> names;
  std::error_code ec;
  for (const fs::path& dir : {fs::path(sysfs_root) / "class" / "video4linux", fs::path(dev_root)}) {
    for (const auto& e : fs::directory_iterator(dir, ec)) {
      const std::string n = e.path().filename().string();
      if (node_number(n) >= 0) names.insert(n);
    }
    ec.clear();
  }
  std::vector<std::string> out(names.begin(), names.end());
  sort_nodes(&out);
  return out;
}

V4l2NodeIdentity identify_v4l2_node(const std::string& sysfs_root, const std::string& dev_root,
                                    const std::string& node) {
  V4l2NodeIdentity id;
  id.node = node;
  id.dev_path = (fs::path(dev_root) / node).string();
  const fs::path node_dir = fs::path(sysfs_root) / "class" / "video4linux" / node;
  if (!fs::exists(node_dir)) return id;

  if (const auto index = read_attr(node_dir / "index")) {
    try {
      id.index = std::stoi(*index);
    } catch (const std::exception&) {
      id.index = -1;
    }
  }
  id.name = attr_or_empty(node_dir / "name");
  const int index = id.index >= 0 ? id.index : 0;

  const auto parent = resolve(node_dir / "device");
  if (!parent) return id;
  // The first ancestor with idVendor is the USB device (the node hangs off one of its
  // interfaces).
  for (fs::path p = *parent; !p.empty() && p != p.parent_path(); p = p.parent_path()) {
    if (!fs::exists(p / "idVendor")) continue;
    id.usb = true;
    id.usb_device = p.filename().string();
    id.vendor_id = attr_or_empty(p / "idVendor");
    id.product_id = attr_or_empty(p / "idProduct");
    id.manufacturer = attr_or_empty(p / "manufacturer");
    id.product = attr_or_empty(p / "product");
    id.serial = attr_or_empty(p / "serial");
    id.devpath = attr_or_empty(p / "devpath");
    try {
      id.busnum = std::stoi(attr_or_empty(p / "busnum"));
    } catch (const std::exception&) {
      id.busnum = -1;
    }
    id.interface_class = attr_or_empty(*parent / "bInterfaceClass");
    id.stable_id =
        "usb-" +
        udev_usb_serial_id(id.vendor_id, id.product_id, id.manufacturer, id.product, id.serial) +
        "-video-index" + std::to_string(index);
    return id;
  }
  // Not USB: by-path style "<bus>-<device>-video-index<N>".
  const auto subsystem = resolve(*parent / "subsystem");
  if (subsystem) {
    id.stable_id = subsystem->filename().string() + "-" + parent->filename().string() +
                   "-video-index" + std::to_string(index);
  }
  return id;
}

std::vector<std::string> v4l2_nodes_of_usb_device(const std::string& sysfs_root,
                                                  const std::string& usb_device) {
  std::vector<std::string> out;
  const auto dir = usb_device_dir(sysfs_root, usb_device);
  if (!dir) return out;
  for (const fs::path& iface : usb_interfaces(*dir)) {
    std::error_code ec;
    for (const auto& e : fs::directory_iterator(iface / "video4linux", ec)) {
      const std::string n = e.path().filename().string();
      if (node_number(n) >= 0) out.push_back(n);
    }
  }
  sort_nodes(&out);
  return out;
}

std::vector<std::string> usb_interface_classes(const std::string& sysfs_root,
                                               const std::string& usb_device) {
  std::vector<std::string> out;
  const auto dir = usb_device_dir(sysfs_root, usb_device);
  if (!dir) return out;
  for (const fs::path& iface : usb_interfaces(*dir)) {
    out.push_back(attr_or_empty(iface / "bInterfaceClass"));
  }
  return out;
}

}  // namespace posecal
