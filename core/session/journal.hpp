// The session journal: every keyframe on disk the moment it is captured, so that a kill, a
// power cut or a watchdog loses at most the frame in flight, and a session opened again with
// the same journal goes on where the other stopped (session key "journal", docs/c-api.md).
//
// Format (version 1): UTF-8 text, one record per line, each line
//     <CRC-32 of the JSON text, 8 lower-case hex digits> <space> <one JSON object> '\n'
// appended with one write and made durable with fdatasync before the call returns. Records, by
// "type":
//   header    first: "format" 1, "posecal" version, "created" (UTC), "camera" {uri, id, vendor,
//             model, serial}, "config" (the session config without the journal's own keys)
//   engine    at the first frame: "image_width", "image_height", "locked_settings" {name: value}
//   keyframe  per keyframe the engine kept: "index" (1-based), "time" (UTC), "state_before",
//             "target_param", "state_after", "estimate_after" (the intrinsics after it, exact
//             doubles), "converged_after", "failure", "ids", "image_points" [x, y, ...],
//             "board_points" [x, y, z, ...], and "image_png" (base64 PNG) with journal_images
//   end       when the session finished: "state" (converged, failed, interrupted), "time"
// The reader accepts a journal whose last line was cut (or whose CRC does not match) by
// ignoring everything from that record on, and says so; a later writer cuts the file back to
// the last complete record before appending. This is the record a traceable calibration
// database (issue 15) stores in its final form.
#pragma once

#include <map>
#include <memory>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "select/engine.hpp"

namespace posecal {

struct JournalHeader {
  std::string camera_uri, camera_id, camera_vendor, camera_model, camera_serial;
  std::string config;  // the session config as canonical JSON text (journal keys removed)
  std::string posecal_version;
  std::string created;  // UTC, ISO 8601
};

struct JournalContents {
  JournalHeader header;
  bool has_header = false;
  cv::Size image_size;  // 0x0 before the engine record
  std::map<std::string, std::string> locked_settings;
  std::vector<KeyframeRecord> keyframes;
  std::string end_state;   // "" if the session had not finished
  size_t valid_bytes = 0;  // the file up to the end of the last complete record
  std::string damage;      // "" or what was dropped (a cut or corrupt record) and where
};

// Reads a journal. Throws Error(kIo) if it cannot be read, Error(kInvalidArgument) naming the
// file if it is not a posecal journal (no valid header line) or a record does not parse.
// A damaged tail is not an error: valid_bytes and damage say what was kept.
JournalContents read_journal(const std::string& path);

// One keyframe as the journal's JSON record (without the image), and back: the record a
// traceable calibration record (core/records) stores per keyframe. keyframe_from_json throws
// Error(kInvalidArgument) naming what is wrong. `time` is the keyframe's (UTC, ISO 8601).
std::string keyframe_json(int index, const KeyframeRecord& record, const std::string& time);
KeyframeRecord keyframe_from_json(const std::string& text);

// Appends records to a journal; every append is durable (fdatasync) when it returns and throws
// Error(kIo) naming the file and the cause (e.g. ENOSPC) if it is not.
class JournalWriter {
 public:
  // A new journal at `path` (an existing file there is replaced).
  static std::unique_ptr<JournalWriter> create(const std::string& path,
                                               const JournalHeader& header);
  // Continues `path` after read_journal: the file is cut back to `valid_bytes` first.
  static std::unique_ptr<JournalWriter> resume(const std::string& path, size_t valid_bytes);
  ~JournalWriter();
  JournalWriter(const JournalWriter&) = delete;
  JournalWriter& operator=(const JournalWriter&) = delete;

  void append_engine(cv::Size image_size,
                     const std::map<std::string, std::string>& locked_settings);
  // `index` 1-based; `image` empty unless the journal keeps images.
  void append_keyframe(int index, const KeyframeRecord& record, const cv::Mat& image);
  void append_end(const std::string& state);
  const std::string& path() const { return path_; }

 private:
  JournalWriter(std::string path, int fd) : path_(std::move(path)), fd_(fd) {}
  void append(const std::string& json_text);
  std::string path_;
  int fd_ = -1;
};

}  // namespace posecal
