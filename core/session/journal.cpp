#include "session/journal.hpp"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h>

#include <cerrno>
#include <cstdio>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>

#include "common/atomic_file.hpp"
#include "common/clock.hpp"
#include "common/error.hpp"
#include "common/regular_file.hpp"

namespace posecal {

namespace {

using Json = nlohmann::json;

constexpr int kFormat = 1;
constexpr size_t kMaxJournalBytes = size_t{1} << 30;  // 20 keyframes with images are ~15 MB

std::string crc_text(const std::string& text) {
  const uLong crc =
      ::crc32(0L, reinterpret_cast<const Bytef*>(text.data()), static_cast<uInt>(text.size()));
  char buf[9];
  std::snprintf(buf, sizeof buf, "%08lx", crc & 0xffffffffUL);
  return buf;
}

std::string base64(const std::vector<uchar>& bytes) {
  static const char* k = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out;
  out.reserve((bytes.size() + 2) / 3 * 4);
  for (size_t i = 0; i < bytes.size(); i += 3) {
    const uint32_t b = (uint32_t{bytes[i]} << 16) |
                       (i + 1 < bytes.size() ? uint32_t{bytes[i + 1]} << 8 : 0) |
                       (i + 2 < bytes.size() ? uint32_t{bytes[i + 2]} : 0);
    out += k[(b >> 18) & 63];
    out += k[(b >> 12) & 63];
    out += i + 1 < bytes.size() ? k[(b >> 6) & 63] : '=';
    out += i + 2 < bytes.size() ? k[b & 63] : '=';
  }
  return out;
}

Json points_json(const std::vector<cv::Point2d>& pts) {
  Json a = Json::array();
  for (const auto& p : pts) a.push_back(p.x), a.push_back(p.y);
  return a;
}

Json points_json(const std::vector<cv::Point3d>& pts) {
  Json a = Json::array();
  for (const auto& p : pts) a.push_back(p.x), a.push_back(p.y), a.push_back(p.z);
  return a;
}

EngineState state_of(const Json& j, const char* key) {
  EngineState s;
  if (!engine_state_from_name(j.at(key).get<std::string>(), &s)) {
    throw Error(ErrorCode::kInvalidArgument, std::string("unknown state in '") + key + "'");
  }
  return s;
}

KeyframeRecord keyframe_of(const Json& j) {
  KeyframeRecord r;
  r.state_before = state_of(j, "state_before");
  r.state_after = state_of(j, "state_after");
  r.target_param = j.at("target_param").get<int>();
  r.estimate_after = j.at("estimate_after").get<std::vector<double>>();
  r.converged_after = j.at("converged_after").get<std::vector<bool>>();
  r.failure = j.value("failure", "");
  Observation& o = r.observation;
  o.ids = j.at("ids").get<std::vector<int>>();
  const auto ip = j.at("image_points").get<std::vector<double>>();
  const auto bp = j.at("board_points").get<std::vector<double>>();
  if (ip.size() != 2 * o.ids.size() || bp.size() != 3 * o.ids.size()) {
    throw Error(ErrorCode::kInvalidArgument, "keyframe: point counts do not match the ids");
  }
  for (size_t i = 0; i < o.ids.size(); ++i) {
    o.image_points.emplace_back(ip[2 * i], ip[2 * i + 1]);
    o.board_points.emplace_back(bp[3 * i], bp[3 * i + 1], bp[3 * i + 2]);
  }
  return r;
}

// A keyframe record without its image: "type", "index", "time" and the record's fields (the
// doubles written so that they read back bit for bit).
Json keyframe_json_object(int index, const KeyframeRecord& r,
                          const std::string& time = utc_now_iso8601()) {
  return {{"type", "keyframe"},
          {"index", index},
          {"time", time},
          {"state_before", engine_state_name(r.state_before)},
          {"target_param", r.target_param},
          {"state_after", engine_state_name(r.state_after)},
          {"estimate_after", r.estimate_after},
          {"converged_after", r.converged_after},
          {"failure", r.failure},
          {"ids", r.observation.ids},
          {"image_points", points_json(r.observation.image_points)},
          {"board_points", points_json(r.observation.board_points)}};
}

JournalHeader header_of(const Json& j) {
  if (j.at("format").get<int>() != kFormat) {
    throw Error(ErrorCode::kInvalidArgument,
                "journal format " + j.at("format").dump() + " is not 1");
  }
  JournalHeader h;
  const Json& c = j.at("camera");
  h.camera_uri = c.value("uri", "");
  h.camera_id = c.value("id", "");
  h.camera_vendor = c.value("vendor", "");
  h.camera_model = c.value("model", "");
  h.camera_serial = c.value("serial", "");
  h.config = j.at("config").dump();
  h.posecal_version = j.value("posecal", "");
  h.created = j.value("created", "");
  return h;
}

// Applies one record; throws on a record that parses but does not make sense.
void apply_record(const Json& j, JournalContents* out) {
  const std::string type = j.at("type").get<std::string>();
  if (!out->has_header) {
    if (type != "header")
      throw Error(ErrorCode::kInvalidArgument, "the first record is not the header");
    out->header = header_of(j);
    out->has_header = true;
  } else if (type == "engine") {
    out->image_size = cv::Size(j.at("image_width").get<int>(), j.at("image_height").get<int>());
    out->locked_settings = j.value("locked_settings", std::map<std::string, std::string>());
  } else if (type == "keyframe") {
    if (j.at("index").get<size_t>() != out->keyframes.size() + 1) {
      throw Error(ErrorCode::kInvalidArgument,
                  "keyframe " + j.at("index").dump() + " out of order");
    }
    out->keyframes.push_back(keyframe_of(j));
  } else if (type == "end") {
    out->end_state = j.at("state").get<std::string>();
  } else {
    throw Error(ErrorCode::kInvalidArgument, "unknown record type '" + type + "'");
  }
}

std::string read_file(const std::string& path) {
  return read_regular_file(path, kMaxJournalBytes, "journal");
}

}  // namespace

JournalContents read_journal(const std::string& path) {
  const std::string text = read_file(path);
  JournalContents out;
  size_t pos = 0;
  for (int line = 1; pos < text.size(); ++line) {
    const size_t nl = text.find('\n', pos);
    const std::string where = "line " + std::to_string(line);
    if (nl == std::string::npos) {
      out.damage = where + " was cut (" + std::to_string(text.size() - pos) + " bytes): ignored";
      break;
    }
    const std::string rec = text.substr(pos, nl - pos);
    const std::string json = rec.size() > 9 ? rec.substr(9) : std::string();
    if (rec.size() <= 9 || rec[8] != ' ' || crc_text(json) != rec.substr(0, 8)) {
      if (!out.has_header) break;  // a whole first line that is no record: not a journal
      out.damage = where + " is damaged (CRC mismatch): it and what follows are ignored";
      break;
    }
    try {
      apply_record(Json::parse(json), &out);
    } catch (const std::exception& e) {
      throw Error(ErrorCode::kInvalidArgument,
                  "journal '" + path + "', " + where + ": " + e.what());
    }
    pos = nl + 1;
    out.valid_bytes = pos;
  }
  // Not a journal: a first line that is whole but no header record. (A first line cut by a kill
  // while the header was written is damage: the session starts afresh.)
  if (!out.has_header && text.size() > 0 && out.damage.empty()) {
    throw Error(ErrorCode::kInvalidArgument, "'" + path + "' is not a posecal journal");
  }
  return out;
}

std::unique_ptr<JournalWriter> JournalWriter::create(const std::string& path,
                                                     const JournalHeader& h) {
  const int fd =
      ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_APPEND | O_CLOEXEC | O_NOFOLLOW, 0644);
  if (fd < 0)
    throw Error(ErrorCode::kIo, "cannot create journal '" + path + "': " + errno_text(errno));
  std::unique_ptr<JournalWriter> w(new JournalWriter(path, fd));
  Json j = {{"type", "header"},
            {"format", kFormat},
            {"posecal", h.posecal_version},
            {"created", utc_now_iso8601()},
            {"camera",
             {{"uri", h.camera_uri},
              {"id", h.camera_id},
              {"vendor", h.camera_vendor},
              {"model", h.camera_model},
              {"serial", h.camera_serial}}},
            {"config", Json::parse(h.config.empty() ? "{}" : h.config)}};
  w->append(j.dump(-1, ' ', false, Json::error_handler_t::replace));
  return w;
}

std::unique_ptr<JournalWriter> JournalWriter::resume(const std::string& path, size_t valid_bytes) {
  const int fd = ::open(path.c_str(), O_WRONLY | O_APPEND | O_CLOEXEC | O_NOFOLLOW);
  if (fd < 0)
    throw Error(ErrorCode::kIo, "cannot open journal '" + path + "': " + errno_text(errno));
  std::unique_ptr<JournalWriter> w(new JournalWriter(path, fd));
  if (::ftruncate(fd, static_cast<off_t>(valid_bytes)) != 0 || ::fdatasync(fd) != 0) {
    throw Error(ErrorCode::kIo,
                "cannot cut journal '" + path + "' back to its last record: " + errno_text(errno));
  }
  return w;
}

JournalWriter::~JournalWriter() {
  if (fd_ >= 0) ::close(fd_);
}

void JournalWriter::append(const std::string& json_text) {
  const std::string line = crc_text(json_text) + " " + json_text + "\n";
  size_t done = 0;
  while (done < line.size()) {
    const ssize_t n = ::write(fd_, line.data() + done, line.size() - done);
    if (n < 0 && errno == EINTR) continue;
    if (n < 0)
      throw Error(ErrorCode::kIo, "cannot write journal '" + path_ + "': " + errno_text(errno));
    done += static_cast<size_t>(n);
  }
  if (::fdatasync(fd_) != 0) {
    throw Error(ErrorCode::kIo, "cannot flush journal '" + path_ + "': " + errno_text(errno));
  }
}

void JournalWriter::append_engine(cv::Size size, const std::map<std::string, std::string>& locked) {
  const Json j = {{"type", "engine"},
                  {"image_width", size.width},
                  {"image_height", size.height},
                  {"locked_settings", locked}};
  append(j.dump(-1, ' ', false, Json::error_handler_t::replace));
}

std::string keyframe_json(int index, const KeyframeRecord& r, const std::string& time) {
  return keyframe_json_object(index, r, time).dump(-1, ' ', false, Json::error_handler_t::replace);
}

KeyframeRecord keyframe_from_json(const std::string& text) {
  Json j;
  try {
    j = Json::parse(text);
    return keyframe_of(j);
  } catch (const Json::exception& e) {
    throw Error(ErrorCode::kInvalidArgument, std::string("keyframe record: ") + e.what());
  }
}

void JournalWriter::append_keyframe(int index, const KeyframeRecord& r, const cv::Mat& image) {
  Json j = keyframe_json_object(index, r);
  if (!image.empty()) {
    std::vector<uchar> png;
    if (cv::imencode(".png", image, png)) j["image_png"] = base64(png);
  }
  append(j.dump(-1, ' ', false, Json::error_handler_t::replace));
}

void JournalWriter::append_end(const std::string& state) {
  append(Json{{"type", "end"}, {"state", state}, {"time", utc_now_iso8601()}}.dump());
}

}  // namespace posecal
