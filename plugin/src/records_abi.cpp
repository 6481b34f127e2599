// The C ABI of calibration records (posecal.h, "Records"): list the runs of a store, show one,
// re-solve one from its stored detections, export its calibration as a model file.
#include <nlohmann/json.hpp>

#include "abi_common.hpp"
#include "common/clock.hpp"
#include "json_report.hpp"
#include "posecal.h"
#include "records/record_store.hpp"
#include "records_resolve.hpp"
#include "select/engine.hpp"
#include "session/journal.hpp"
#include "session_config.hpp"

using namespace posecal;
using Json = nlohmann::json;
using abi::guarded;
using abi::require;
using abi::resolve;
using abi::Resolved;

namespace {

Json parsed_or_text(const std::string& text) {
  if (text.empty()) return nullptr;
  Json j = Json::parse(text, nullptr, false);
  return j.is_discarded() ? Json(text) : j;
}

Json summary_json(const RunSummary& s) {
  const RunIdentity& id = s.identity;
  return {{"run_id", id.run_id},
          {"station_id", id.station_id},
          {"operator_id", id.operator_id},
          {"lens_id", id.lens_id},
          {"camera",
           {{"uri", id.camera_uri},
            {"id", id.camera_id},
            {"vendor", id.camera_vendor},
            {"model", id.camera_model},
            {"serial", id.camera_serial},
            {"transport", id.camera_device_version}}},
          {"posecal_version", id.posecal_version},
          {"abi_version", id.abi_version},
          {"started", id.started},
          {"finished", s.finished.empty() ? Json(nullptr) : Json(s.finished)},
          {"state", s.state},
          {"verdict", s.verdict.empty() ? Json(nullptr) : Json(s.verdict)},
          {"expected_error_px", s.expected_error_px ? Json(*s.expected_error_px) : Json(nullptr)},
          {"keyframes", s.keyframes},
          {"note", s.note.empty() ? Json(nullptr) : Json(s.note)}};
}

RunRecord get_run(const char* location, const char* run_id) {
  require(location, "location");
  require(run_id, "run_id");
  return RecordStore::open(location)->get_run(run_id);
}

}  // namespace

extern "C" {

POSECAL_API posecal_status posecal_records_list(const char* location, char* buf,
                                                size_t* size) noexcept {
  return guarded(__func__, [&] {
    require(location, "location");
    require(size, "size");
    Json runs = Json::array();
    for (const RunSummary& s : RecordStore::open(location)->list_runs())
      runs.push_back(summary_json(s));
    return abi::copy_out(abi::to_text(runs), buf, size);
  });
}

POSECAL_API posecal_status posecal_records_show(const char* location, const char* run_id,
                                                char* buf, size_t* size) noexcept {
  return guarded(__func__, [&] {
    require(size, "size");
    const RunRecord r = get_run(location, run_id);
    Json j = summary_json(r.summary);
    j["config"] = parsed_or_text(r.summary.identity.config);
    j["image_width"] = r.image_width;
    j["image_height"] = r.image_height;
    j["locked_settings"] = r.locked_settings;
    j["result"] = parsed_or_text(r.result);
    Json kfs = Json::array();
    for (const StoredKeyframe& k : r.keyframes) {
      const KeyframeRecord rec = keyframe_from_json(k.record);
      kfs.push_back({{"index", k.index},
                     {"time", k.time},
                     {"corners", rec.observation.ids.size()},
                     {"state_before", engine_state_name(rec.state_before)},
                     {"state_after", engine_state_name(rec.state_after)},
                     {"image_png_bytes", k.image_png.size()}});
    }
    j["keyframes"] = kfs;
    return abi::copy_out(abi::to_text(j), buf, size);
  });
}

POSECAL_API posecal_status posecal_records_resolve(const char* location, const char* run_id,
                                                   char* buf, size_t* size) noexcept {
  return guarded(__func__, [&] {
    require(size, "size");
    const RunRecord r = get_run(location, run_id);
    const Resolved solved = resolve(r);
    const CalibrationResult& result = *solved.engine->result();
    const std::vector<std::string>& names = result.model.param_names();
    Json recomputed = Json::object(), stored = Json::object();
    const Json stored_result = parsed_or_text(r.result);
    bool identical_to_result = stored_result.is_object();
    for (int i = 0; i < result.model.num_params(); ++i) {
      const double v = result.model.params()[i];
      recomputed[names[i]] = v;
      if (stored_result.is_object() && stored_result.contains(names[i]) &&
          stored_result[names[i]].is_number()) {
        const double s = stored_result[names[i]].get<double>();
        stored[names[i]] = s;
        identical_to_result = identical_to_result && s == v;  // bit for bit
      } else {
        identical_to_result = false;
      }
    }
    const Json j = {
        {"run_id", r.summary.identity.run_id},
        {"keyframes", r.keyframes.size()},
        {"recorded_by", r.summary.identity.posecal_version},
        {"resolved_by", POSECAL_VERSION_STRING},
        {"identical", solved.identical_to_last_keyframe && identical_to_result},
        {"identical_to_last_keyframe", solved.identical_to_last_keyframe},
        {"identical_to_result", identical_to_result},
        {"recomputed", recomputed},
        {"stored", stored_result.is_object() ? stored : Json(nullptr)}};
    return abi::copy_out(abi::to_text(j), buf, size);
  });
}

POSECAL_API posecal_status posecal_records_export(const char* location, const char* run_id,
                                                  const char* path,
                                                  const char* format) noexcept {
  return guarded(__func__, [&] {
    require(path, "path");
    const RunRecord r = get_run(location, run_id);
    const Resolved solved = resolve(r);
    CalibrationFileExtras extras;
    extras.strings = {{"camera_uri", r.summary.identity.camera_uri},
                      {"camera_id", r.summary.identity.camera_id},
                      {"target", solved.engine->options().board.to_string()}};
    extras.converged = r.summary.state == "converged";
    extras.interrupted = r.summary.state == "interrupted";
    abi::save_calibration(path, *solved.engine->result(), format, extras);
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_records_import(const char* location, const char* journal_path,
                                                  const char* options_json, char* buf,
                                                  size_t* size) noexcept {
  return guarded(__func__, [&] {
    require(location, "location");
    require(journal_path, "journal_path");
    require(size, "size");
    const char* what = "records import options";
    const Json o = abi::parse_options(options_json,
                                      {"run_id", "station_id", "operator_id", "lens_id"}, what);
    const JournalContents journal = read_journal(journal_path);
    if (journal.image_size.width <= 0) {
      throw Error(ErrorCode::kState, std::string("journal '") + journal_path +
                                         "' holds no frame: there is nothing to record");
    }
    RunIdentity id;
    id.run_id = abi::get_string(o, "run_id", "", what);
    if (id.run_id.empty()) id.run_id = new_run_id();
    id.station_id = abi::get_string(o, "station_id", "", what);
    id.operator_id = abi::get_string(o, "operator_id", "", what);
    id.lens_id = abi::get_string(o, "lens_id", "", what);
    const JournalHeader& h = journal.header;
    id.camera_uri = h.camera_uri;
    id.camera_id = h.camera_id;
    id.camera_vendor = h.camera_vendor;
    id.camera_model = h.camera_model;
    id.camera_serial = h.camera_serial;
    id.posecal_version = h.posecal_version;
    id.abi_version = std::to_string(POSECAL_ABI_VERSION);
    id.config = h.config;
    id.started = h.created;
    // The result: the calibration recomputed from the journal's keyframes, as a resume does.
    std::string result_text;
    std::optional<double> expected;
    if (journal.keyframes.size() >= 2) {
      RunRecord as_record;
      as_record.summary.identity = id;
      as_record.image_width = journal.image_size.width;
      as_record.image_height = journal.image_size.height;
      for (size_t i = 0; i < journal.keyframes.size(); ++i) {
        StoredKeyframe k;
        k.index = static_cast<int>(i) + 1;
        k.record = keyframe_json(k.index, journal.keyframes[i], utc_now_iso8601());
        as_record.keyframes.push_back(k);
      }
      const Resolved solved = resolve(as_record);
      Json result = abi::calibration_json(*solved.engine->result());
      result["state"] = engine_state_name(solved.engine->state());
      result["converged"] = solved.engine->converged();
      result["keyframes"] = journal.keyframes.size();
      result["run_id"] = id.run_id;
      result["imported_from"] = journal_path;
      if (result.contains("expected_error_px") && result["expected_error_px"].is_number())
        expected = result["expected_error_px"].get<double>();
      result_text = abi::to_text(result);
    }
    // A journal without its end record: the session stopped before it finished (killed, or
    // still running elsewhere).
    const std::string state = journal.end_state.empty() ? "interrupted" : journal.end_state;
    auto store = RecordStore::open(location);
    store->begin_run(id);
    store->set_engine(id.run_id, journal.image_size, journal.locked_settings);
    for (size_t i = 0; i < journal.keyframes.size(); ++i)
      store->add_keyframe(
          id.run_id, stored_keyframe(static_cast<int>(i) + 1, journal.keyframes[i], cv::Mat()));
    store->finish_run(id.run_id, state, result_text, "", expected);
    const Json j = {{"run_id", id.run_id},
                    {"keyframes", journal.keyframes.size()},
                    {"state", state},
                    {"journal_note", journal.damage.empty() ? Json(nullptr) : Json(journal.damage)}};
    return abi::copy_out(abi::to_text(j), buf, size);
  });
}

}  // extern "C"
