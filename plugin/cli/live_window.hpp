// The live window of `calibrate --camera` (OpenCV highgui, only where a display answers): the
// camera's last frame with the guidance overlay.
#pragma once

#include <string>
#include <vector>

#include "cli_common.hpp"

namespace posecal::cli {

// True if an X server answers at `display` ("[host]:N[.S]"): a GUI toolkit that cannot open
// its display ends the process (Qt aborts), so the CLI looks before it leaps.
bool x_display_reachable(const std::string& display);

class LiveWindow {
 public:
  // Opens nothing until the first frame; disabled without highgui, without DISPLAY, or when
  // no X server answers there. POSECAL_WINDOW=0 disables it, POSECAL_WINDOW=force skips the
  // display check (e.g. with QT_QPA_PLATFORM=offscreen).
  explicit LiveWindow(bool wanted);
  ~LiveWindow();
  LiveWindow(const LiveWindow&) = delete;
  LiveWindow& operator=(const LiveWindow&) = delete;

  bool enabled() const { return enabled_; }
  // Shows the last frame with the guidance overlay. Returns false when the user closed the
  // window or pressed q/Esc.
  bool show(posecal_session* s, const Json& status);
  // Once the calibration has finished: the result screen (the overlay's verdict, expected error
  // and the keyframes' coverage) stays until a key, the window is closed, a signal, or
  // `seconds`. Nothing if the window was never opened.
  void hold_result(posecal_session* s, double seconds);

 private:
  bool enabled_ = false;
  bool opened_ = false;
  std::vector<unsigned char> pixels_;
};

}  // namespace posecal::cli
