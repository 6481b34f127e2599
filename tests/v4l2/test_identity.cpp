// sysfs -> stable id, against the fixture tree (tests/data/v4l2/two_uvc_cameras).
#include <filesystem>

#include "posecal/v4l2_identity.hpp"
#include "rig.hpp"

namespace posecal::test {
namespace {

namespace fs = std::filesystem;

TEST(V4l2Identity, ListsNodesNumerically) {
  const auto nodes = list_v4l2_nodes(fixture_root() + "/sys", fixture_root() + "/dev");
  EXPECT_EQ(nodes, (std::vector<std::string>{"video0", "video1", "video2", "video3", "video4"}));
  EXPECT_TRUE(list_v4l2_nodes("/nonexistent/sys", "/nonexistent/dev").empty());
}

TEST(V4l2Identity, C525OnRootHubPort) {
  const auto id = identify_v4l2_node(fixture_root() + "/sys", "/dev", "video0");
  EXPECT_EQ(id.dev_path, "/dev/video0");
  EXPECT_EQ(id.index, 0);
  EXPECT_EQ(id.name, "HD Webcam C525");
  EXPECT_TRUE(id.usb);
  EXPECT_EQ(id.usb_device, "1-2");
  EXPECT_EQ(id.busnum, 1);
  EXPECT_EQ(id.devpath, "2");
  EXPECT_EQ(id.vendor_id, "046d");
  EXPECT_EQ(id.product_id, "0826");
  EXPECT_EQ(id.manufacturer, "");  // the C525 has no manufacturer string
  EXPECT_EQ(id.product, "HD Webcam C525");
  EXPECT_EQ(id.serial, "0320EC60");
  EXPECT_EQ(id.interface_class, "0e");
  EXPECT_EQ(id.stable_id, kC525Id);
  EXPECT_EQ(identify_v4l2_node(fixture_root() + "/sys", "/dev", "video1").stable_id, kC525MetaId);
}

TEST(V4l2Identity, LifeCamBehindHubWithoutSerial) {
  const auto id = identify_v4l2_node(fixture_root() + "/sys", "/dev", "video2");
  EXPECT_EQ(id.usb_device, "1-3.1");
  EXPECT_EQ(id.devpath, "3.1");
  EXPECT_EQ(id.manufacturer, "Microsoft");
  EXPECT_EQ(id.serial, "");
  EXPECT_EQ(id.stable_id, kLifeCamId);
}

TEST(V4l2Identity, PlatformNodeGetsByPathStyleId) {
  const auto id = identify_v4l2_node(fixture_root() + "/sys", "/dev", "video4");
  EXPECT_FALSE(id.usb);
  EXPECT_EQ(id.name, "Mono Sensor");
  EXPECT_EQ(id.stable_id, kMonoId);
  // A node sysfs does not know keeps only its path.
  const auto unknown = identify_v4l2_node(fixture_root() + "/sys", "/dev", "video9");
  EXPECT_EQ(unknown.stable_id, "");
  EXPECT_EQ(unknown.dev_path, "/dev/video9");
}

// udev's links in dev/v4l/by-id and by-path name the node they point at: the computed ids must
// be exactly these names.
TEST(V4l2Identity, MatchesUdevLinkNames) {
  int checked = 0;
  for (const char* dir : {"/dev/v4l/by-id", "/dev/v4l/by-path"}) {
    for (const auto& e : fs::directory_iterator(fixture_root() + dir)) {
      const std::string node = fs::read_symlink(e.path()).filename().string();
      const auto id = identify_v4l2_node(fixture_root() + "/sys", "/dev", node);
      const std::string name = e.path().filename().string();
      if (std::string(dir) == "/dev/v4l/by-id" || !id.usb) {
        EXPECT_EQ(id.stable_id, name) << node;
        ++checked;
      }
    }
  }
  EXPECT_EQ(checked, 5);
}

TEST(V4l2Identity, NodesAndInterfacesOfUsbDevices) {
  const std::string sys = fixture_root() + "/sys";
  EXPECT_EQ(v4l2_nodes_of_usb_device(sys, "1-2"), (std::vector<std::string>{"video0", "video1"}));
  EXPECT_EQ(v4l2_nodes_of_usb_device(sys, "1-3.1"), (std::vector<std::string>{"video2", "video3"}));
  EXPECT_TRUE(v4l2_nodes_of_usb_device(sys, "1-1").empty());
  EXPECT_TRUE(v4l2_nodes_of_usb_device(sys, "1-9").empty());
  EXPECT_TRUE(v4l2_nodes_of_usb_device(sys, "../1-2").empty());
  EXPECT_EQ(usb_interface_classes(sys, "1-1"), (std::vector<std::string>{"03", "03"}));
  EXPECT_EQ(usb_interface_classes(sys, "1-2"), (std::vector<std::string>{"0e", "0e", "01", "01"}));
}

TEST(V4l2Identity, UdevSerialIdRules) {
  // Ids replace missing strings; whitespace runs collapse to one '_' and ends are trimmed.
  EXPECT_EQ(udev_usb_serial_id("046d", "0826", "", "HD Webcam C525", "0320EC60"),
            "046d_HD_Webcam_C525_0320EC60");
  EXPECT_EQ(udev_usb_serial_id("1234", "5678", "  Acme   Corp ", "Cam\tPro 3000", " SN 01 "),
            "Acme_Corp_Cam_Pro_3000_SN_01");
  EXPECT_EQ(udev_usb_serial_id("1234", "5678", "", "", ""), "1234_5678");
  // Characters outside [A-Za-z0-9#+-.:=@_] become '_', valid UTF-8 stays, broken UTF-8 does not.
  EXPECT_EQ(udev_usb_serial_id("1", "2", "A/B (c)", "X\xC2\xAEY", ""), "A_B__c__X\xC2\xAEY");
  EXPECT_EQ(udev_usb_serial_id("1", "2", "V", "P\xC2", ""), "V_P_");
  // Serials with commas or non-ASCII bytes are dropped entirely.
  EXPECT_EQ(udev_usb_serial_id("1", "2", "V", "P", "12,34"), "V_P");
  EXPECT_EQ(udev_usb_serial_id("1", "2", "V", "P", "12\xC3\xA9"), "V_P");
}

TEST(V4l2Identity, ControlNamesLikeV4l2Ctl) {
  EXPECT_EQ(v4l2_control_name("Focus, Automatic Continuous"), "focus_automatic_continuous");
  EXPECT_EQ(v4l2_control_name("Auto Exposure"), "auto_exposure");
  EXPECT_EQ(v4l2_control_name("Focus, Absolute"), "focus_absolute");
  EXPECT_EQ(v4l2_control_name("Exposure Time, Absolute"), "exposure_time_absolute");
  EXPECT_EQ(v4l2_control_name("White Balance Temperature, Auto"), "white_balance_temperature_auto");
  EXPECT_EQ(v4l2_control_name("  -- LED1 Mode --"), "led1_mode");
  EXPECT_EQ(v4l2_control_name(""), "");
}

TEST(V4l2Identity, UsbEventSysfsName) {
  UsbHotplugEvent e;
  e.bus = 1;
  e.ports = {3, 1};
  EXPECT_EQ(e.sysfs_name(), "1-3.1");
  e.ports = {2};
  EXPECT_EQ(e.sysfs_name(), "1-2");
  e.ports.clear();
  EXPECT_EQ(e.sysfs_name(), "");  // a root hub
}

}  // namespace
}  // namespace posecal::test
