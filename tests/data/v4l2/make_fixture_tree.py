#!/usr/bin/env python3
"""Writes the sysfs + /dev fixture tree used by tests/v4l2 (two_uvc_cameras/).

The tree is modelled, attribute by attribute and link by link, on what Linux 6.1 shows for:
  * a Logitech HD Webcam C525 (046d:0826, serial 0320EC60, no manufacturer string) on port 2
    of the xHCI root hub: interface 1-2:1.0 carries video0 (index 0, capture) and video1
    (index 1, UVC metadata);
  * a Microsoft LifeCam HD-3000 (045e:0810, no serial) behind a USB 2 hub on port 3, port 1:
    device 1-3.1, video2 and video3;
  * a USB keyboard (1-1, HID only): a USB device that is not a camera;
  * a platform (non-USB) capture node video4 of a made-up "mono-sensor.0" device.
It was not captured from a machine (there is no camera here); the names follow the kernel's
sysfs layout and udev's 60-persistent-v4l.rules / usb_id naming. dev/ holds the by-id and
by-path links udev would create (the device nodes themselves cannot live in git).

Run from this directory to regenerate: python3 make_fixture_tree.py
"""
import os
import shutil

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "two_uvc_cameras")
HCD = "sys/devices/pci0000:00/0000:00:14.0"
USB1 = HCD + "/usb1"


def write(path, text):
    full = os.path.join(ROOT, path)
    os.makedirs(os.path.dirname(full), exist_ok=True)
    with open(full, "w", encoding="utf-8") as f:
        f.write(text)


def attrs(directory, values):
    for name, value in values.items():
        write(f"{directory}/{name}", f"{value}\n")


def link(path, target):
    full = os.path.join(ROOT, path)
    os.makedirs(os.path.dirname(full), exist_ok=True)
    os.symlink(target, full)


def rel(from_dir, to_path):
    """Relative link target from directory `from_dir` to `to_path` (both under ROOT)."""
    return os.path.relpath(os.path.join(ROOT, to_path), os.path.join(ROOT, from_dir))


def usb_device(path, name, busnum, devpath, devnum, vid, pid, product, bcd, dev_class="00",
               manufacturer=None, serial=None, num_interfaces=1, speed="480"):
    d = f"{path}/{name}"
    values = {
        "idVendor": vid, "idProduct": pid, "product": product, "busnum": busnum,
        "devpath": devpath, "devnum": devnum, "speed": speed, "bcdDevice": bcd,
        "bDeviceClass": dev_class, "bDeviceSubClass": "02" if dev_class == "ef" else "00",
        "bDeviceProtocol": "01" if dev_class == "ef" else "00", "bNumConfigurations": "1",
        "bConfigurationValue": "1", "bNumInterfaces": f"{num_interfaces:2d}", "bMaxPacketSize0": "64",
        "maxchild": "0", "version": " 2.00", "removable": "removable", "authorized": "1",
        "uevent": f"MAJOR=189\nMINOR={(int(busnum) - 1) * 128 + int(devnum) - 1}\n"
                  f"DEVNAME=bus/usb/{int(busnum):03d}/{int(devnum):03d}\nDEVTYPE=usb_device\n"
                  f"DRIVER=usb\nPRODUCT={vid.lstrip('0')}/{pid.lstrip('0')}/{bcd.lstrip('0')}\n"
                  f"TYPE={int(dev_class, 16)}/0/0\nBUSNUM={int(busnum):03d}\nDEVNUM={int(devnum):03d}",
    }
    if manufacturer is not None:
        values["manufacturer"] = manufacturer
    if serial is not None:
        values["serial"] = serial
    attrs(d, values)
    link(f"{d}/subsystem", rel(d, "sys/bus/usb"))
    link(f"{d}/driver", rel(d, "sys/bus/usb/drivers/usb"))
    link(f"sys/bus/usb/devices/{name}", rel("sys/bus/usb/devices", d))
    return d


def interface(device_dir, name, number, cls, subcls, driver, label=None):
    d = f"{device_dir}/{name}"
    values = {"bInterfaceNumber": f"{number:02x}", "bAlternateSetting": " 0",
              "bInterfaceClass": cls, "bInterfaceSubClass": subcls, "bInterfaceProtocol": "00",
              "bNumEndpoints": "01", "authorized": "1", "supports_autosuspend": "1"}
    if label:
        values["interface"] = label
    attrs(d, values)
    link(f"{d}/subsystem", rel(d, "sys/bus/usb"))
    link(f"{d}/driver", rel(d, f"sys/bus/usb/drivers/{driver}"))
    link(f"sys/bus/usb/drivers/{driver}/{name}", rel(f"sys/bus/usb/drivers/{driver}", d))
    link(f"sys/bus/usb/devices/{name}", rel("sys/bus/usb/devices", d))
    return d


def video_node(parent_dir, node, minor, index, name):
    d = f"{parent_dir}/video4linux/{node}"
    attrs(d, {"dev": f"81:{minor}", "index": index, "name": name,
              "uevent": f"MAJOR=81\nMINOR={minor}\nDEVNAME={node}"})
    # The kernel spells this link through the parent's parent: device -> ../../../1-2:1.0
    link(f"{d}/device", "../../../" + os.path.basename(parent_dir))
    link(f"{d}/subsystem", rel(d, "sys/class/video4linux"))
    link(f"sys/class/video4linux/{node}", rel("sys/class/video4linux", d))


def main():
    if os.path.exists(ROOT):
        shutil.rmtree(ROOT)
    for driver in ("usb", "uvcvideo", "usbhid", "snd-usb-audio", "hub"):
        write(f"sys/bus/usb/drivers/{driver}/uevent", "")
    write("sys/bus/platform/drivers/mono_sensor/uevent", "")

    root_hub = usb_device(HCD, "usb1", "1", "0", "1", "1d6b", "0002", "xHCI Host Controller", "0601",
                          dev_class="09", manufacturer="Linux 6.1.0-13-amd64 xhci-hcd",
                          serial="0000:00:14.0")
    interface(root_hub, "1-0:1.0", 0, "09", "00", "hub")

    kbd = usb_device(USB1, "1-1", "1", "1", "2", "046d", "c31c", "USB Keyboard", "6400",
                     manufacturer="Logitech", num_interfaces=2, speed="1.5")
    interface(kbd, "1-1:1.0", 0, "03", "01", "usbhid")
    interface(kbd, "1-1:1.1", 1, "03", "00", "usbhid")

    # Logitech C525: no iManufacturer string, so udev's vendor part is the id "046d".
    c525 = usb_device(USB1, "1-2", "1", "2", "3", "046d", "0826", "HD Webcam C525", "0010",
                      dev_class="ef", serial="0320EC60", num_interfaces=4)
    vc = interface(c525, "1-2:1.0", 0, "0e", "01", "uvcvideo")
    interface(c525, "1-2:1.1", 1, "0e", "02", "uvcvideo")
    interface(c525, "1-2:1.2", 2, "01", "01", "snd-usb-audio")
    interface(c525, "1-2:1.3", 3, "01", "02", "snd-usb-audio")
    video_node(vc, "video0", 0, "0", "HD Webcam C525")
    video_node(vc, "video1", 1, "1", "HD Webcam C525")

    hub = usb_device(USB1, "1-3", "1", "3", "4", "05e3", "0608", "USB2.0 Hub", "8536",
                     dev_class="09")
    interface(hub, "1-3:1.0", 0, "09", "00", "hub")
    lifecam = usb_device(hub, "1-3.1", "1", "3.1", "5", "045e", "0810",
                         "Microsoft\u00ae LifeCam HD-3000", "0106", dev_class="ef",
                         manufacturer="Microsoft", num_interfaces=4)
    vc2 = interface(lifecam, "1-3.1:1.0", 0, "0e", "01", "uvcvideo")
    interface(lifecam, "1-3.1:1.1", 1, "0e", "02", "uvcvideo")
    interface(lifecam, "1-3.1:1.2", 2, "01", "01", "snd-usb-audio")
    interface(lifecam, "1-3.1:1.3", 3, "01", "02", "snd-usb-audio")
    video_node(vc2, "video2", 2, "0", "Microsoft\u00ae LifeCam HD-3000")
    video_node(vc2, "video3", 3, "1", "Microsoft\u00ae LifeCam HD-3000")

    plat = "sys/devices/platform/mono-sensor.0"
    attrs(plat, {"modalias": "platform:mono-sensor", "driver_override": "(null)",
                 "uevent": "DRIVER=mono_sensor\nMODALIAS=platform:mono-sensor"})
    link(f"{plat}/subsystem", rel(plat, "sys/bus/platform"))
    link(f"{plat}/driver", rel(plat, "sys/bus/platform/drivers/mono_sensor"))
    link("sys/bus/platform/devices/mono-sensor.0", rel("sys/bus/platform/devices", plat))
    video_node(plat, "video4", 4, "0", "Mono Sensor")

    # What udev's 60-persistent-v4l.rules would have linked.
    for name, node in [("usb-046d_HD_Webcam_C525_0320EC60-video-index0", "video0"),
                       ("usb-046d_HD_Webcam_C525_0320EC60-video-index1", "video1"),
                       ("usb-Microsoft_Microsoft\u00ae_LifeCam_HD-3000-video-index0", "video2"),
                       ("usb-Microsoft_Microsoft\u00ae_LifeCam_HD-3000-video-index1", "video3")]:
        link(f"dev/v4l/by-id/{name}", f"../../{node}")
    for name, node in [("pci-0000:00:14.0-usb-0:2:1.0-video-index0", "video0"),
                       ("pci-0000:00:14.0-usb-0:2:1.0-video-index1", "video1"),
                       ("pci-0000:00:14.0-usb-0:3.1:1.0-video-index0", "video2"),
                       ("pci-0000:00:14.0-usb-0:3.1:1.0-video-index1", "video3"),
                       ("platform-mono-sensor.0-video-index0", "video4")]:
        link(f"dev/v4l/by-path/{name}", f"../../{node}")


if __name__ == "__main__":
    main()
