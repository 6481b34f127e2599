// Identity of V4L2 device nodes, read from sysfs the way udev names them.
//
// /dev/videoN says nothing about which camera it is and changes with plug order. udev's
// 60-persistent-v4l.rules gives each node of a USB camera a stable name,
//   /dev/v4l/by-id/usb-<ID_SERIAL>-video-index<index>
// where ID_SERIAL (systemd's usb_id builtin) is "<manufacturer>_<product>[_<serial>]" of the USB
// device, each falling back to the hex idVendor / idProduct when the device has no such string,
// with whitespace runs replaced by '_' and characters outside [A-Za-z0-9#+-.:=@_] (other than
// valid UTF-8) replaced by '_'. The same name is computed here from sysfs alone, without udev:
//
//   <sysfs>/class/video4linux/videoN          -> ../../devices/.../1-2/1-2:1.0/video4linux/videoN
//   <sysfs>/class/video4linux/videoN/index    the node's index within its device (0: video,
//                                             1: UVC metadata on kernels >= 4.16)
//   <sysfs>/class/video4linux/videoN/device   -> the USB interface (1-2:1.0)
//   <interface>/..                            the USB device (1-2): idVendor, idProduct,
//                                             manufacturer, product, serial, busnum, devpath
//
// Nodes not on USB (platform drivers, vivid, ...) get a by-path style id instead:
// "<bus>-<parent device>-video-index<index>", e.g. "platform-vivid.0-video-index0".
#pragma once

#include <optional>
#include <string>
#include <vector>

namespace posecal {

struct V4l2NodeIdentity {
  std::string node;       // "video0"
  std::string dev_path;   // <dev root>/video0
  int index = -1;         // sysfs "index" attribute, -1 if absent
  std::string name;       // sysfs "name" attribute (the driver's card name)
  std::string stable_id;  // "usb-046d_HD_Webcam_C525_0320EC60-video-index0"; "" if unknown

  bool usb = false;
  std::string usb_device;  // sysfs name of the USB device, "<bus>-<port>[.<port>...]", e.g. "1-2"
  int busnum = -1;
  std::string devpath;       // port path within the bus, "2" or "3.1"
  std::string vendor_id;     // idVendor, 4 hex digits
  std::string product_id;    // idProduct
  std::string manufacturer;  // string descriptors as the kernel shows them ("" if absent)
  std::string product;
  std::string serial;
  std::string interface_class;  // bInterfaceClass of the interface the node hangs off ("0e")
};

// Names of the video nodes ("video0", "video2", ...), numerically sorted: the entries of
// <sysfs_root>/class/video4linux, plus <dev_root>/video* for systems without sysfs (containers).
// Empty, not an error, when neither exists.
std::vector<std::string> list_v4l2_nodes(const std::string& sysfs_root,
                                         const std::string& dev_root);

// Identity of one node from sysfs. Without sysfs information only `node` and `dev_path` are set.
V4l2NodeIdentity identify_v4l2_node(const std::string& sysfs_root, const std::string& dev_root,
                                    const std::string& node);

// The video nodes of the USB device <sysfs_root>/bus/usb/devices/<usb_device> (all interfaces),
// numerically sorted. Empty if the device is unknown or has no video node (yet).
std::vector<std::string> v4l2_nodes_of_usb_device(const std::string& sysfs_root,
                                                  const std::string& usb_device);

// bInterfaceClass of each interface of the USB device ("0e" is Video: a camera once uvcvideo binds
// it). Empty while the kernel has not configured the device yet, or if it is unknown.
std::vector<std::string> usb_interface_classes(const std::string& sysfs_root,
                                               const std::string& usb_device);

// udev's ID_SERIAL for a USB device (systemd usb_id): manufacturer/product fall back to the ids.
std::string udev_usb_serial_id(const std::string& vendor_id, const std::string& product_id,
                               const std::string& manufacturer, const std::string& product,
                               const std::string& serial);

// v4l2-ctl's variable name of a control: lower-case alphanumeric words joined by '_'
// ("Focus, Automatic Continuous" -> "focus_automatic_continuous").
std::string v4l2_control_name(const std::string& kernel_name);

}  // namespace posecal
