// libFuzzer target: host frames through posecal_session_feed on an "external" session (the
// pixel-format conversion, board detection and the engine's first steps on arbitrary pixels),
// then posecal_session_last_frame and posecal_session_render_overlay on host images of two formats.
//
// Input: byte 0-1 width-1, 2-3 height-1 (each taken modulo 256: frames up to 256x256; byte 1
// odd: a chessboard session, chessboard:9x6:0.025, whose detector is OpenCV's sector search,
// else the default ChArUco board), byte 4 the pixel format (mod 3), byte 5 extra stride bytes
// (mod 8), byte 6 the number of frames fed (1..4, all the same size); the rest are the pixels,
// repeated to fill the frame. Fails on a
// crash, a sanitizer report, or a call that does not succeed on a frame the engine accepts.
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <vector>

#include "posecal.h"

namespace {

posecal_context* external_context() {
  static posecal_context* const ctx = [] {
    posecal_context* c = nullptr;
    if (posecal_context_create("{\"backends\": [\"external\"]}", &c) != POSECAL_OK) std::abort();
    return c;
  }();
  return ctx;
}

int bytes_per_pixel(int format) { return format == POSECAL_PIXEL_MONO8 ? 1 : 3; }

posecal_image image_of(std::vector<uint8_t>* pixels, int w, int h, int format, int extra) {
  posecal_image im{};
  im.struct_size = sizeof(posecal_image);
  im.width = w;
  im.height = h;
  im.stride_bytes = w * bytes_per_pixel(format) + extra;
  im.format = format;
  pixels->assign(static_cast<size_t>(im.stride_bytes) * static_cast<size_t>(h), 0);
  im.data = pixels->data();
  return im;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  if (size < 7) return 0;
  const int w = 1 + ((data[0] | data[1] << 8) % 256);
  const int h = 1 + ((data[2] | data[3] << 8) % 256);
  const int format = data[4] % 3;
  const int extra = data[5] % 8;
  const int frames = 1 + data[6] % 4;
  const uint8_t* px = data + 7;
  const size_t npx = size - 7;

  std::vector<uint8_t> pixels;
  posecal_image im = image_of(&pixels, w, h, format, extra);
  if (npx > 0) {
    for (size_t i = 0; i < pixels.size(); ++i) pixels[i] = px[i % npx];
  }

  posecal_session* s = nullptr;
  const bool chessboard = data[1] % 2 == 1;
  const char* config = chessboard ? "{\"view_candidates\": 0, \"target\": \"chessboard:9x6:0.025\"}"
                                  : "{\"view_candidates\": 0}";
  if (posecal_session_open(external_context(), "external", config, &s) != POSECAL_OK) {
    std::abort();
  }
  // The engine needs at least 16x16 pixels (core/select/engine.cpp; posecal.h promises 1..65535
  // per side, which is reported): a smaller frame must be refused as an invalid argument, with
  // nothing processed. Any other frame of 16..256 pixels per side in a valid format is valid:
  // only a finished session (after a calibration, impossible within 4 frames) may refuse it.
  const bool too_small = w < 16 || h < 16;
  for (int i = 0; i < frames; ++i) {
    const posecal_status st = posecal_session_feed(s, &im);
    if (st != (too_small ? POSECAL_E_INVALID_ARGUMENT : POSECAL_OK)) std::abort();
  }
  if (too_small) {
    posecal_session_close(s);
    return 0;
  }
  // The last frame and the overlay, into a host image of the camera's size in the frame's
  // format and in one other format (a conversion).
  std::vector<uint8_t> out;
  for (int f : {format, (format + 1 + data[5] / 8 % 2) % 3}) {
    posecal_image o = image_of(&out, w, h, f, extra);
    if (posecal_session_last_frame(s, &o) != POSECAL_OK) std::abort();
    if (posecal_session_render_overlay(s, &o) != POSECAL_OK) std::abort();
  }
  std::vector<char> buf(1 << 16);
  size_t n = buf.size();
  if (posecal_session_status(s, buf.data(), &n) != POSECAL_OK) std::abort();
  posecal_session_close(s);
  return 0;
}
