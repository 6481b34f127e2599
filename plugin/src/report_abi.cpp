// posecal_records_report (posecal.h, "Records"): the calibration report of a recorded run, or of
// a calibration result file, as self-contained HTML (every figure a PNG in a data: URI) and
// optionally a PDF. The figures are core/report/plots.hpp; this file gathers their data: the
// run re-solved from its keyframes, the residuals, σ after each prefix of the keyframes, and the
// other units of the same camera model and lens in the store.
#include <cmath>
#include <cstdio>
#include <nlohmann/json.hpp>
#include <optional>
#include <set>

#include "abi_common.hpp"
#include "calib/expected_error.hpp"
#include "common/atomic_file.hpp"
#include "io/model_file.hpp"
#include "io/result_file.hpp"
#include "posecal.h"
#include "records/record_store.hpp"
#include "records_resolve.hpp"
#include "report/plots.hpp"
#include "session/journal.hpp"

using namespace posecal;
using Json = nlohmann::json;
using abi::guarded;
using abi::require;

namespace {

struct Report {
  std::string title;
  std::vector<std::pair<std::string, std::string>> header;  // the summary table, in order
  std::vector<Figure> figures;
  std::vector<std::string> notes;  // what is not shown, and why
};

std::string text_of(const Json& j, const char* key) {
  return j.is_object() && j.contains(key) && j[key].is_string() ? j[key].get<std::string>() : "";
}

std::string or_dash(const std::string& s) { return s.empty() ? "-" : s; }

// The run's fleet outlier test as one line (the result's "fleet", records/fleet.hpp); "" if the
// run had none (no records when it ran, or a result from before the test existed).
std::string fleet_position_text(const Json& result) {
  if (!result.is_object() || !result.contains("fleet") || !result["fleet"].is_object()) return "";
  const Json& f = result["fleet"];
  const auto num = [&](const char* k) {
    return f.contains(k) && f[k].is_number() ? f[k].get<double>() : std::nan("");
  };
  if (!f.contains("outlier") || !f["outlier"].is_boolean()) {
    return "no fleet test: " + (f.contains("note") && f["note"].is_string()
                                    ? f["note"].get<std::string>()
                                    : std::string("no note"));
  }
  char buf[200];
  std::snprintf(buf, sizeof buf,
                "Mahalanobis distance %.2f, bound %.2f; one parameter's |z| bound %.2f (%d units, "
                "alpha %g)",
                num("distance"), num("threshold"), num("parameter_threshold"),
                static_cast<int>(num("units")), num("probability"));
  std::string out =
      std::string(f["outlier"].get<bool>() ? "OUTLIER: " : "within the fleet: ") + buf;
  if (f.contains("deviations") && f["deviations"].is_array() && !f["deviations"].empty()) {
    out += "; largest deviations";
    int shown = 0;
    for (const Json& d : f["deviations"]) {
      if (shown++ == 3 || !d.is_object() || !d.contains("z") || !d["z"].is_number()) break;
      std::snprintf(buf, sizeof buf, " %s z %+.1f", d.value("param", "?").c_str(),
                    d["z"].get<double>());
      out += buf;
    }
  }
  return out;
}

std::string number_text(double v, const char* format = "%.4f") {
  char buf[64];
  std::snprintf(buf, sizeof buf, format, v);
  return buf;
}

// The expected-error map on a grid of about 64 columns with square cells.
Figure expected_error_of(const CalibrationResult& result) {
  const int cols = 64;
  const int rows = std::max(2, static_cast<int>(std::lround(cols * double(result.model.height()) /
                                                            result.model.width())));
  const cv::Mat map = expected_error_map(result, cols, rows);
  return expected_error_figure(result.model.size(), map, expected_error(result).rms_px);
}

// σ (at the measured noise) of each intrinsic from the first k keyframes, k = 2..N, solved as
// the engine solved them (engine.cpp, recalibrate): the first cold, each next one warm-started
// from the previous one. A prefix without a solution is a gap (NaN).
Figure sigma_of(const std::vector<KeyframeRecord>& keyframes, cv::Size size,
                const CalibrationOptions& options, const std::vector<std::string>& names) {
  std::vector<int> counts;
  std::vector<std::vector<double>> sigma;
  std::optional<CalibrationResult> previous;
  std::vector<Observation> prefix;
  for (size_t k = 0; k < keyframes.size(); ++k) {
    prefix.push_back(keyframes[k].observation);
    if (prefix.size() < 2) continue;
    counts.push_back(static_cast<int>(prefix.size()));
    try {
      CalibrationResult now;
      if (previous) {
        const WarmStart ws{previous->model, previous->poses};
        now = calibrate(prefix, size, options, &ws);
      } else {
        now = calibrate(prefix, size, options);
      }
      std::vector<double> s = now.std_scaled;
      for (size_t p = 0; p < s.size(); ++p)
        if (p < now.fixed.size() && now.fixed[p]) s[p] = std::nan("");
      sigma.push_back(s);
      previous = now;
    } catch (const Error&) {
      sigma.push_back(std::vector<double>(names.size(), std::nan("")));
    }
  }
  return sigma_figure(names, counts, sigma);
}

// The intrinsics of a result JSON by name; empty if it lacks one.
std::vector<double> intrinsics_of(const Json& result, const std::vector<std::string>& names) {
  std::vector<double> v;
  if (!result.is_object()) return {};
  for (const std::string& n : names) {
    if (!result.contains(n) || !result[n].is_number()) return {};
    v.push_back(result[n].get<double>());
  }
  return v;
}

Report report_of_run(const std::string& location, const std::string& run_id) {
  auto store = RecordStore::open(location);
  const RunRecord r = store->get_run(run_id);
  const RunIdentity& id = r.summary.identity;
  if (r.keyframes.size() < 2) {
    throw Error(ErrorCode::kState, "run " + id.run_id + " has " +
                                       std::to_string(r.keyframes.size()) +
                                       " keyframes: a report needs a calibration, from two");
  }
  const abi::Resolved solved = abi::resolve(r);
  const CalibrationResult& result = *solved.engine->result();
  const CameraModel& model = result.model;
  const cv::Size size(r.image_width, r.image_height);
  std::vector<KeyframeRecord> keyframes;
  for (const StoredKeyframe& k : r.keyframes) keyframes.push_back(keyframe_from_json(k.record));
  if (result.poses.size() != keyframes.size()) {
    throw Error(ErrorCode::kInternal, "run " + id.run_id + ": the calibration has " +
                                          std::to_string(result.poses.size()) + " poses for " +
                                          std::to_string(keyframes.size()) + " keyframes");
  }
  std::vector<KeyframeCorners> corners;
  for (size_t i = 0; i < keyframes.size(); ++i) {
    const Observation& o = keyframes[i].observation;
    KeyframeCorners k;
    k.index = r.keyframes[i].index;
    k.observed = o.image_points;
    for (const cv::Point3d& b : o.board_points) {
      Eigen::Vector2d uv;
      if (!model.project(result.poses[i].apply({b.x, b.y, b.z}), &uv))
        uv = {std::nan(""), std::nan("")};
      k.reprojected.emplace_back(uv.x(), uv.y());
    }
    corners.push_back(std::move(k));
  }

  const Json stored = Json::parse(r.result.empty() ? "null" : r.result, nullptr, false);
  FleetStrips fleet;
  fleet.verdict = r.summary.verdict.empty() ? text_of(stored, "verdict") : r.summary.verdict;
  if (stored.is_object() && stored.contains("verdict_reasons") &&
      stored["verdict_reasons"].is_array()) {
    for (const Json& reason : stored["verdict_reasons"])
      if (reason.is_string()) fleet.reasons.push_back(reason.get<std::string>());
  }
  fleet.group = "camera model " + (id.camera_model.empty() ? "(none)" : id.camera_model) +
                ", lens id " + (id.lens_id.empty() ? "(none)" : id.lens_id);
  fleet.names = model.param_names();
  fleet.unit = model.params();
  // The other units: the passed runs of the same camera model and lens id (the fleet of
  // records/fleet.hpp, read without their frames) with a calibration of the same lens model,
  // one per camera serial (its newest run) where the serial is known, so a unit calibrated
  // twice counts once.
  std::set<std::string> serials_seen;
  if (!id.camera_serial.empty()) serials_seen.insert(id.camera_serial);
  for (const RecordStore::FleetRun& o : store->fleet_runs(id.camera_model, id.lens_id)) {
    if (o.run_id == id.run_id) continue;
    if (!o.serial.empty() && !serials_seen.insert(o.serial).second) continue;
    const std::vector<double> v = intrinsics_of(Json::parse(o.result, nullptr, false), fleet.names);
    if (!v.empty()) fleet.others.push_back(v);
  }
  fleet.position = fleet_position_text(stored);

  Report rep;
  rep.title = "posecal calibration report: " + or_dash(id.camera_id);
  const std::string exp = stored.is_object() && stored.contains("expected_error_px") &&
                                  stored["expected_error_px"].is_number()
                              ? number_text(stored["expected_error_px"].get<double>()) + " px"
                              : "-";
  std::string reasons;
  for (const std::string& s : fleet.reasons) reasons += (reasons.empty() ? "" : "; ") + s;
  rep.header = {
      {"run id", id.run_id},
      {"camera", or_dash(id.camera_id) + " (" + or_dash(id.camera_vendor) + " " +
                     or_dash(id.camera_model) + ", serial " + or_dash(id.camera_serial) + ")"},
      {"camera URI", or_dash(id.camera_uri)},
      {"lens id", or_dash(id.lens_id)},
      {"station / operator", or_dash(id.station_id) + " / " + or_dash(id.operator_id)},
      {"started / finished", or_dash(id.started) + " / " + or_dash(r.summary.finished)},
      {"posecal version", or_dash(id.posecal_version) + " (ABI " + or_dash(id.abi_version) +
                              "); report by " + POSECAL_VERSION_STRING},
      {"state", or_dash(r.summary.state)},
      {"verdict", fleet.verdict.empty() ? "- (no quality specification)" : fleet.verdict},
      {"verdict reasons", or_dash(reasons)},
      {"fleet position", or_dash(fleet.position)},
      {"expected_error_px", exp},
      {"keyframes", std::to_string(r.keyframes.size())},
      {"image", std::to_string(r.image_width) + " x " + std::to_string(r.image_height) + " px"},
      {"lens model", lens_model_name(model.lens_model())},
      {"residual RMS", number_text(result.rms_px) + " px"},
  };
  if (!solved.identical_to_last_keyframe) {
    rep.notes.push_back(
        "the re-solved calibration differs from the one the run recorded after "
        "its last keyframe (another posecal version?): the figures show the "
        "re-solved one");
  }
  rep.figures.push_back(coverage_figure(size, corners));
  rep.figures.push_back(residual_figure(size, corners));
  rep.figures.push_back(distortion_figure(model));
  rep.figures.push_back(expected_error_of(result));
  rep.figures.push_back(
      sigma_of(keyframes, size, solved.engine->options().calibration, fleet.names));
  rep.figures.push_back(fleet_figure(fleet));
  return rep;
}

Report report_of_file(const std::string& path) {
  const ModelFile file = read_model_file(path);
  const CameraModel& model = file.model;
  Report rep;
  rep.title = "posecal calibration report: " + path;
  rep.header = {
      {"result file", path},
      {"format", model_format_name(file.format)},
      {"image", std::to_string(model.width()) + " x " + std::to_string(model.height()) + " px"},
      {"lens model", lens_model_name(model.lens_model())}};
  for (const auto& [key, value] : file.extras.strings) rep.header.push_back({key, value});
  if (file.extras.expected_error_px >= 0)
    rep.header.push_back({"expected_error_px", number_text(file.extras.expected_error_px) + " px"});
  if (file.extras.nr_of_frames >= 0)
    rep.header.push_back({"keyframes", std::to_string(file.extras.nr_of_frames)});
  rep.figures.push_back(distortion_figure(model));
  if (const std::optional<CalibrationResult> result = result_figures_of(file)) {
    rep.figures.push_back(expected_error_of(*result));
  } else {
    rep.notes.push_back(std::string("no expected-error map: the file holds no covariance of the "
                                    "intrinsics (posecal's OpenCV files do; the ") +
                        model_format_name(file.format) + " format here does not)");
  }
  rep.notes.push_back(
      "coverage, residuals, sigma after each keyframe and the fleet position "
      "need a recorded run (posecal report RUN_ID --db ...)");
  return rep;
}

std::string escape(const std::string& s) {
  std::string out;
  for (char c : s) {
    switch (c) {
      case '&':
        out += "&amp;";
        break;
      case '<':
        out += "&lt;";
        break;
      case '>':
        out += "&gt;";
        break;
      case '"':
        out += "&quot;";
        break;
      default:
        out += c;
    }
  }
  return out;
}

// Self-contained HTML: no file or network reference; each figure a PNG data URI. The script
// counts, once the page has loaded, the images the browser decoded (naturalWidth > 0) into
// <body data-plots-decoded>, so a headless browser's DOM dump proves every figure displays.
std::string html_of(const Report& rep, const std::vector<std::string>& pngs) {
  std::string h =
      "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>" +
      escape(rep.title) +
      "</title>\n<style>\n"
      "body { font-family: 'DejaVu Sans', sans-serif; margin: 24px; color: #111; }\n"
      "table { border-collapse: collapse; margin-bottom: 16px; }\n"
      "th, td { text-align: left; padding: 3px 12px 3px 0; vertical-align: top; }\n"
      "th { color: #444; font-weight: normal; }\n"
      "img { max-width: 100%; height: auto; border: 1px solid #ccc; }\n"
      ".pass { color: #1a8c33; font-weight: bold; } .fail { color: #cc1a1a; font-weight: bold; }\n"
      "</style>\n</head>\n<body data-plots=\"" +
      std::to_string(pngs.size()) + "\" data-plots-decoded=\"\">\n<h1>" + escape(rep.title) +
      "</h1>\n<table id=\"summary\">\n";
  for (const auto& [k, v] : rep.header) {
    const char* cls = k == "verdict" && v == "pass"   ? " class=\"pass\""
                      : k == "verdict" && v == "fail" ? " class=\"fail\""
                                                      : "";
    h += "<tr><th>" + escape(k) + "</th><td" + cls + ">" + escape(v) + "</td></tr>\n";
  }
  h += "</table>\n";
  if (!rep.notes.empty()) {
    h += "<ul id=\"notes\">\n";
    for (const std::string& n : rep.notes) h += "<li>" + escape(n) + "</li>\n";
    h += "</ul>\n";
  }
  for (size_t i = 0; i < rep.figures.size(); ++i) {
    const Figure& f = rep.figures[i];
    h += "<section>\n<h2>" + escape(f.title) + "</h2>\n<img id=\"plot-" + f.id + "\" alt=\"" +
         escape(f.title) + "\" width=\"" + std::to_string(kFigureWidth) + "\" height=\"" +
         std::to_string(kFigureHeight) + "\" src=\"data:image/png;base64," +
         base64_encode(pngs[i]) + "\">\n</section>\n";
  }
  h += "<script>\n"
       "window.addEventListener('load', function () {\n"
       "  var n = 0;\n"
       "  for (var i = 0; i < document.images.length; ++i)\n"
       "    if (document.images[i].complete && document.images[i].naturalWidth > 0) ++n;\n"
       "  document.body.setAttribute('data-plots-decoded', String(n));\n"
       "});\n"
       "</script>\n</body>\n</html>\n";
  return h;
}

void write_or_throw(const std::string& path, const std::string& bytes) {
  std::string error;
  if (!write_file_atomic(path, bytes, &error)) throw Error(ErrorCode::kIo, error);
}

}  // namespace

extern "C" {

POSECAL_API posecal_status posecal_records_report(const char* location, const char* run_id,
                                                  const char* result_path, const char* html_path,
                                                  const char* pdf_path, char* buf,
                                                  size_t* size) noexcept {
  return guarded(__func__, [&] {
    require(html_path, "html_path");
    const bool has_run = location && *location && run_id && *run_id;
    const bool has_file = result_path && *result_path;
    if (has_run == has_file) {
      throw Error(ErrorCode::kInvalidArgument,
                  "give either a store and a run id or a result file, not both or neither");
    }
    if (!*html_path) throw Error(ErrorCode::kInvalidArgument, "html_path is empty");
    const bool with_pdf = pdf_path && *pdf_path;
    // Before any work: the outputs can be written.
    std::string error;
    if (!check_output_path(html_path, &error)) throw Error(ErrorCode::kIo, error);
    if (with_pdf && !check_output_path(pdf_path, &error)) throw Error(ErrorCode::kIo, error);

    const Report rep = has_run ? report_of_run(location, run_id) : report_of_file(result_path);
    std::vector<std::string> pngs;
    Json plots = Json::array();
    for (const Figure& f : rep.figures) {
      pngs.push_back(figure_png(f));
      plots.push_back(f.id);
    }
    const std::string html = html_of(rep, pngs);
    std::string pdf;
    if (with_pdf) {
      std::vector<std::string> lines;
      for (const auto& [k, v] : rep.header) lines.push_back(k + ": " + v);
      for (const std::string& n : rep.notes) lines.push_back("note: " + n);
      pdf = report_pdf(rep.title, lines, rep.figures);
    }
    // Everything is rendered: now the files, each atomically.
    write_or_throw(html_path, html);
    if (with_pdf) write_or_throw(pdf_path, pdf);
    const Json j = {{"html", html_path},
                    {"pdf", with_pdf ? Json(pdf_path) : Json(nullptr)},
                    {"plots", plots},
                    {"pages", with_pdf ? Json(rep.figures.size() + 1) : Json(nullptr)},
                    {"notes", rep.notes}};
    if (!size) return POSECAL_OK;  // the caller wants the files only
    return abi::copy_out(abi::to_text(j), buf, size);
  });
}

}  // extern "C"
