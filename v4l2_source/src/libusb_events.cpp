// libusb hot-plug as a UsbEventSource: one libusb context, one registered callback for every
// device, and an event thread running libusb_handle_events_timeout_completed. The callback only
// copies the device's bus and port path into a UsbHotplugEvent; the backend's own thread does
// the slow part (waiting for uvcvideo's node), so libusb's thread never blocks.
#include <libusb.h>

#include <atomic>
#include <mutex>
#include <thread>

#include "posecal/v4l2_backend.hpp"

namespace posecal {

namespace {

class LibusbEventSource final : public UsbEventSource {
 public:
  ~LibusbEventSource() override { stop(); }

  bool start(Handler handler, std::string* why_not) override {
    std::lock_guard<std::mutex> lock(mutex_);
    if (context_) return true;
    const auto refuse = [&](const std::string& why) {
      if (why_not) *why_not = why;
      return false;
    };
    libusb_context* ctx = nullptr;
    if (const int rc = libusb_init(&ctx); rc != LIBUSB_SUCCESS) {
      return refuse(std::string("libusb_init failed: ") + libusb_strerror(rc));
    }
    if (!libusb_has_capability(LIBUSB_CAP_HAS_HOTPLUG)) {
      libusb_exit(ctx);
      return refuse("this libusb has no hot-plug support (LIBUSB_CAP_HAS_HOTPLUG)");
    }
    handler_ = std::move(handler);
    context_ = ctx;
    const int rc = libusb_hotplug_register_callback(
        ctx,
        static_cast<libusb_hotplug_event>(LIBUSB_HOTPLUG_EVENT_DEVICE_ARRIVED |
                                          LIBUSB_HOTPLUG_EVENT_DEVICE_LEFT),
        static_cast<libusb_hotplug_flag>(0), LIBUSB_HOTPLUG_MATCH_ANY, LIBUSB_HOTPLUG_MATCH_ANY,
        LIBUSB_HOTPLUG_MATCH_ANY, &LibusbEventSource::on_event, this, &handle_);
    if (rc != LIBUSB_SUCCESS) {
      libusb_exit(ctx);
      context_ = nullptr;
      handler_ = nullptr;
      return refuse(std::string("libusb_hotplug_register_callback failed: ") + libusb_strerror(rc));
    }
    running_ = true;
    thread_ = std::thread([this, ctx] {
      while (running_) {
        // Bounded wait so that stop() is noticed even if no event wakes the loop.
        timeval tv{0, 100 * 1000};
        libusb_handle_events_timeout_completed(ctx, &tv, nullptr);
      }
    });
    return true;
  }

  void stop() override {
    std::lock_guard<std::mutex> lock(mutex_);
    if (!context_) return;
    running_ = false;
    // Deregistering wakes the event loop; the loop's 100 ms timeout bounds the join otherwise.
    libusb_hotplug_deregister_callback(context_, handle_);
    if (thread_.joinable()) thread_.join();
    libusb_exit(context_);
    context_ = nullptr;
    handler_ = nullptr;
  }

 private:
  static int LIBUSB_CALL on_event(libusb_context*, libusb_device* device,
                                  libusb_hotplug_event event, void* user) {
    auto* self = static_cast<LibusbEventSource*>(user);
    UsbHotplugEvent e;
    e.kind = event == LIBUSB_HOTPLUG_EVENT_DEVICE_ARRIVED ? UsbHotplugEvent::Kind::kArrived
                                                          : UsbHotplugEvent::Kind::kLeft;
    e.bus = libusb_get_bus_number(device);
    uint8_t ports[8];
    const int n = libusb_get_port_numbers(device, ports, sizeof ports);
    for (int i = 0; i < n; ++i) e.ports.push_back(ports[i]);
    libusb_device_descriptor d{};
    if (libusb_get_device_descriptor(device, &d) == LIBUSB_SUCCESS) {
      e.vendor_id = d.idVendor;
      e.product_id = d.idProduct;
    }
    if (self->handler_) self->handler_(e);
    return 0;  // stay registered
  }

  std::mutex mutex_;
  libusb_context* context_ = nullptr;
  libusb_hotplug_callback_handle handle_ = 0;
  Handler handler_;
  std::atomic<bool> running_{false};
  std::thread thread_;
};

}  // namespace

std::shared_ptr<UsbEventSource> make_libusb_event_source() {
  return std::make_shared<LibusbEventSource>();
}

}  // namespace posecal
