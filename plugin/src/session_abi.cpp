// posecal_session_*: one camera feeding one pose-selection engine, behind the C ABI.
//
// Session states as the ABI sees them (docs/c-api.md draws them):
//   open --first frame--> running (engine states waiting_for_board .. refining)
//        --converged/failed--> finished (step/feed/pose_reached/skip: POSECAL_E_STATE)
// and, orthogonally, "inside the event callback", where only status, target_pose and result
// may be called on the session.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <ctime>
#include <memory>
#include <opencv2/imgproc.hpp>
#include <set>

#include "abi_common.hpp"
#include "common/clock.hpp"
#include "context.hpp"
#include "evaluation.hpp"
#include "json_report.hpp"
#include "lens/lens_models.hpp"
#include "posecal.h"
#include "quality_gate.hpp"
#include "records/fleet.hpp"
#include "records/record_store.hpp"
#include "records/record_writer.hpp"
#include "records/sql.hpp"
#include "records_resolve.hpp"
#include "session/session.hpp"
#include "session_config.hpp"
#include "sim/sim_camera.hpp"

using namespace posecal;
using posecal::abi::guarded;
using posecal::abi::require;
using Json = nlohmann::json;

struct posecal_session {
  // Declared first, destroyed last: the camera's backend lives in the context.
  std::shared_ptr<abi::Context> context;
  std::unique_ptr<CalibrationSession> session;
  DeviceInfo camera;
  bool external = false;
  bool in_callback = false;
  // Set by posecal_session_interrupt (any thread): no further frame is processed.
  std::atomic<bool> interrupted{false};
  posecal_event_fn fn = nullptr;
  void* user_data = nullptr;
  std::string started, finished;
  // Wall time from the open to the finish (the quality gate's max_seconds).
  std::chrono::steady_clock::time_point opened = std::chrono::steady_clock::now();
  std::optional<double> finished_seconds;
  // The "spec" key's quality specification, if any: the result's verdict.
  std::optional<abi::QualitySpec> spec;
  // The "records" key's store (core/records) and this run's id. A store that cannot be opened or
  // written does not stop the calibration: the writer keeps the parts it could not write (and
  // spools them at the finish, with "records_spool"); records_note says what happened.
  std::unique_ptr<RecordWriter> records;
  std::string records_location, run_id;
  // The fleet position of the finished result (records/fleet.hpp), computed once.
  std::string records_url, lens_id;
  double fleet_alpha = 0.001;
  std::optional<Json> fleet;
  // "prior": "fleet": the prior's figures, or why it was not used (apply_fleet_prior).
  Json prior_info;
  bool record_finished = false;
  // sim:// only: the fixed test set, rendered once, and the evaluation of the last result.
  std::vector<Observation> test_set;
  int evaluated_keyframes = -1;
  Json evaluation;
};

namespace {

const char* kConfig = "session config";


// Calls not allowed from the session's own event callback (the engine is mid-frame there).
void check_not_in_callback(const posecal_session* s, const char* call) {
  if (s->in_callback) {
    throw Error(ErrorCode::kState, std::string(call) +
                                       " may not be called from the session's event callback "
                                       "(only status, target_pose and result may)");
  }
}

// Frames are processed only until the calibration finishes or the host interrupts it.
void check_running(const posecal_session* s) {
  if (s->session->finished()) throw Error(ErrorCode::kState, "the calibration has finished");
  if (s->interrupted) throw Error(ErrorCode::kState, "the calibration was interrupted");
}

void mark_finished(posecal_session* s) {
  s->finished = utc_now_iso8601();
  s->finished_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - s->opened).count();
}

// Interrupted before it finished by itself; the finish time is the first look after that.
bool was_interrupted(posecal_session* s) {
  if (!s->interrupted || s->session->finished()) return false;
  if (s->finished.empty()) mark_finished(s);
  return true;
}

// The record's part of status and result: the store, the run id, what went wrong.
void records_json(const posecal_session* s, Json* j) {
  (*j)["records"] = s->records_location.empty() ? Json(nullptr) : Json(s->records_location);
  (*j)["run_id"] = s->run_id.empty() ? Json(nullptr) : Json(s->run_id);
  const std::string note = s->records ? s->records->note() : std::string();
  (*j)["records_note"] = note.empty() ? Json(nullptr) : Json(note);
}

// The journal's part of status and result: where it is, what a resume restored.
void journal_json(const CalibrationSession& cs, Json* j) {
  const CalibrationSession::JournalStatus& js = cs.journal_status();
  (*j)["journal"] = js.path.empty() ? Json(nullptr) : Json(js.path);
  (*j)["resumed_keyframes"] = js.resumed_keyframes;
  (*j)["journal_note"] = js.note.empty() ? Json(nullptr) : Json(js.note);
  (*j)["resume_identical"] = js.identical ? Json(*js.identical) : Json(nullptr);
}

Json event_json(const SessionEvent& e, std::string* kind) {
  Json j;
  if (e.kind == SessionEvent::Kind::kEngine && e.engine) {
    const EngineEvent& ev = *e.engine;
    *kind = engine_event_name(ev.kind);
    j["keyframes"] = ev.keyframes;
    if (ev.kind == EngineEvent::Kind::kStateChanged) {
      j["from"] = engine_state_name(ev.from);
      j["to"] = engine_state_name(ev.to);
    }
    if (!ev.parameter.empty()) j["parameter"] = ev.parameter;
    j["message"] = ev.message;
  } else {
    *kind = e.kind == SessionEvent::Kind::kCameraDisconnected  ? "camera_disconnected"
            : e.kind == SessionEvent::Kind::kCameraReconnected ? "camera_reconnected"
                                                               : "error";
    j["message"] = e.message;
  }
  return j;
}

// A host image must have `size` (named `whose` in the error).
void require_size(const cv::Mat& image, cv::Size size, const char* whose) {
  if (image.size() == size) return;
  throw Error(ErrorCode::kInvalidArgument,
              "image: " + std::to_string(image.cols) + "x" + std::to_string(image.rows) +
                  " given, " + whose + " is " + std::to_string(size.width) + "x" +
                  std::to_string(size.height));
}

int channels_of(int32_t format) {
  switch (format) {
    case POSECAL_PIXEL_MONO8:
      return 1;
    case POSECAL_PIXEL_BGR8:
      return 3;
    case POSECAL_PIXEL_RGB8:
      return 3;
    default:
      throw Error(ErrorCode::kInvalidArgument, "image: unknown pixel format " +
                                                   std::to_string(format) +
                                                   " (POSECAL_PIXEL_MONO8, _BGR8 or _RGB8)");
  }
}

// Wraps a host image without copying, after checking every field.
cv::Mat wrap_image(const posecal_image* img) {
  require(img, "image");
  if (img->struct_size < sizeof(posecal_image)) {
    throw Error(
        ErrorCode::kInvalidArgument,
        "image: struct_size " + std::to_string(img->struct_size) +
            " is smaller than sizeof(posecal_image) = " + std::to_string(sizeof(posecal_image)));
  }
  if (img->width <= 0 || img->height <= 0 || img->width > 65535 || img->height > 65535) {
    throw Error(ErrorCode::kInvalidArgument, "image: width and height must be in 1..65535, got " +
                                                 std::to_string(img->width) + "x" +
                                                 std::to_string(img->height));
  }
  const int channels = channels_of(img->format);
  if (img->stride_bytes < img->width * channels) {
    throw Error(
        ErrorCode::kInvalidArgument,
        "image: stride_bytes " + std::to_string(img->stride_bytes) +
            " is smaller than width x bytes per pixel = " + std::to_string(img->width * channels));
  }
  require(img->data, "image->data");
  return cv::Mat(img->height, img->width, channels == 1 ? CV_8UC1 : CV_8UC3, img->data,
                 static_cast<size_t>(img->stride_bytes));
}

// Converts between the engine's 8-bit grey / BGR and a host format.
void convert_into(const cv::Mat& src, cv::Mat& dst, int32_t dst_format) {
  const bool src_grey = src.channels() == 1;
  switch (dst_format) {
    case POSECAL_PIXEL_MONO8:
      if (src_grey)
        src.copyTo(dst);
      else
        cv::cvtColor(src, dst, cv::COLOR_BGR2GRAY);
      return;
    case POSECAL_PIXEL_BGR8:
      if (src_grey)
        cv::cvtColor(src, dst, cv::COLOR_GRAY2BGR);
      else
        src.copyTo(dst);
      return;
    case POSECAL_PIXEL_RGB8:
      cv::cvtColor(src, dst, src_grey ? cv::COLOR_GRAY2RGB : cv::COLOR_BGR2RGB);
      return;
  }
}

void deliver(posecal_session* s, const SessionEvent& e) {
  if (!s->fn) return;
  std::string kind;
  Json payload = event_json(e, &kind);
  payload["frames"] = s->session->frames_processed();
  const std::string text = abi::to_text(payload);
  s->in_callback = true;
  try {
    s->fn(s->user_data, kind.c_str(), text.c_str());
  } catch (...) {
    // A C callback cannot throw; a C++ host's exception must not unwind through the engine.
  }
  s->in_callback = false;
}

void note_finished(posecal_session* s) {
  if (s->session->finished() && s->finished.empty()) mark_finished(s);
}

void finish_record(posecal_session* s, const std::string& state);

// The record's state when the session finished by itself: converged or failed.
void note_finished_record(posecal_session* s) {
  if (!s->records || s->record_finished || !s->session->finished()) return;
  const CalibrationEngine* eng = s->session->engine_ptr();
  finish_record(s, eng ? engine_state_name(eng->state()) : "failed");
}

Json status_json(posecal_session* s) {
  Json j;
  const CalibrationSession& cs = *s->session;
  const CalibrationEngine* eng = cs.engine_ptr();
  j["camera"] = abi::device_json(s->camera);
  j["frames"] = cs.frames_processed();
  j["camera_connected"] = !cs.disconnected();
  j["interrupted"] = was_interrupted(s);
  j["finished"] = cs.finished() || j["interrupted"].get<bool>();
  journal_json(cs, &j);
  records_json(s, &j);
  if (!eng) {
    j["state"] = cs.no_frame_failure().empty() ? "waiting_for_board" : "failed";
    if (!cs.no_frame_failure().empty()) j["failure"] = cs.no_frame_failure();
    j["converged"] = false;
    j["keyframes"] = 0;
    j["target_parameter"] = nullptr;
    j["guidance"] = cs.no_frame_failure().empty() ? "waiting for the first frame" : cs.no_frame_failure();
    j["jaccard"] = nullptr;
    j["still"] = false;
    j["motion_px"] = nullptr;
    j["board_visible"] = false;
    j["corners"] = 0;
    j["corners_required"] = 0;
    j["pose_reached"] = false;
    j["captured"] = false;
    j["has_target"] = false;
    j["image_width"] = nullptr;
    j["image_height"] = nullptr;
    j["parameters"] = Json::object();
    j["expected_error_px"] = nullptr;
    j["expected_error_p90_px"] = nullptr;
    j["board_search"] = {{"tracked", 0}, {"fallback", 0}, {"whole", 0}};
    return j;
  }
  const FrameReport& r = eng->last_report();
  j["state"] = engine_state_name(eng->state());
  j["converged"] = eng->converged();
  j["keyframes"] = eng->keyframes();
  j["target_parameter"] = r.target_parameter.empty() ? Json(nullptr) : Json(r.target_parameter);
  j["guidance"] = r.guidance;
  j["jaccard"] = r.jaccard >= 0 ? abi::number(r.jaccard) : Json(nullptr);
  j["still"] = r.still;
  j["motion_px"] = r.motion_px >= 0 ? abi::number(r.motion_px) : Json(nullptr);
  j["board_visible"] = r.board_visible;
  j["corners"] = r.corners;
  j["corners_required"] = r.corners_required;
  j["pose_reached"] = r.pose_reached;
  j["captured"] = r.captured;
  j["has_target"] = eng->target().has_value();
  j["image_width"] = eng->estimate().width();
  j["image_height"] = eng->estimate().height();
  if (eng->state() == EngineState::kFailed) j["failure"] = eng->failure_reason();
  const ExpectedError* expected = eng->expected_error();
  j["expected_error_px"] = expected ? abi::number(expected->rms_px) : Json(nullptr);
  j["expected_error_p90_px"] = expected ? abi::number(expected->p90_px) : Json(nullptr);
  Json params = Json::object();
  for (const auto& p : eng->parameters()) {
    params[p.name] = {{"value", abi::number(p.value)},
                      {"std", p.std >= 0 ? abi::number(p.std) : Json(nullptr)},
                      {"converged", p.converged}};
  }
  j["parameters"] = params;
  const BoardTracker::Counts& search = eng->board_search_counts();
  j["board_search"] = {
      {"tracked", search.tracked}, {"fallback", search.fallback}, {"whole", search.whole}};
  return j;
}

const CalibrationResult& require_result(posecal_session* s) {
  const CalibrationEngine* eng = s->session->engine_ptr();
  if (!eng || !eng->result()) {
    throw Error(ErrorCode::kState, "no calibration yet: it needs two keyframes (" +
                                       std::to_string(eng ? eng->keyframes() : 0) + " captured)");
  }
  return *eng->result();
}

// The passed units of camera model `model` and lens id `lens_id` in the store at `url` with a
// calibration of lens model `lens` (one per serial, the newest; run `except` left out), their
// intrinsics in intrinsic_names(lens) order; *results (if given): each unit's stored result.
std::vector<FleetUnit> fleet_units(const std::string& url, const std::string& model,
                                   const std::string& lens_id, LensModel lens,
                                   const std::string& except, std::vector<Json>* results) {
  const std::vector<std::string>& names = intrinsic_names(lens);
  std::vector<FleetUnit> units;
  std::set<std::string> serials;
  for (const RecordStore::FleetRun& run : RecordStore::open(url)->fleet_runs(model, lens_id)) {
    if (run.run_id == except || !serials.insert(run.serial).second) continue;
    Json res = Json::parse(run.result, nullptr, false);
    if (!res.is_object() || res.value("model", "") != lens_model_name(lens)) continue;
    FleetUnit u{run.run_id, run.serial, {}};
    for (const std::string& n : names) {
      if (!res.contains(n) || !res[n].is_number()) break;
      u.values.push_back(res[n].get<double>());
    }
    if (u.values.size() != names.size()) continue;
    units.push_back(std::move(u));
    if (results) results->push_back(std::move(res));
  }
  return units;
}

// Where the result lies among the passed units of the same camera model and lens id in the
// session's record store (records/fleet.hpp): {"units", "distance", "threshold",
// "parameter_threshold", "probability", "outlier", "deviations": [{"param", "z"}, ...] largest
// first, "note"}. Too few units or a store that cannot be read give "outlier": null and the note.
Json fleet_json(posecal_session* s, const CalibrationResult& r) {
  Json j = {{"units", 0}, {"outlier", nullptr}, {"probability", s->fleet_alpha}};
  try {
    const std::vector<std::string>& names = r.model.param_names();
    const std::vector<FleetUnit> units = fleet_units(s->records_url, s->camera.model, s->lens_id,
                                                     r.model.lens_model(), s->run_id, nullptr);
    j["units"] = units.size();
    const FleetStatistics fleet = fleet_statistics(names, units);
    const CalibrationEngine& eng = s->session->engine();
    bool data_only = false;
    const FleetPosition pos =
        fleet_position_of(fleet, r, eng.keyframe_observations(), eng.options().calibration,
                          s->fleet_alpha, &data_only);
    // With the prior, the keyframes' own estimate (without it) is what was tested.
    j["tested"] = eng.options().calibration.prior
                      ? (data_only ? "keyframes without the prior" : "estimate with the prior")
                      : "estimate";
    j["distance"] = abi::number(pos.distance);
    j["threshold"] = abi::number(pos.threshold);
    j["parameter_threshold"] = abi::number(pos.parameter_threshold);
    j["outlier"] = pos.outlier;
    Json dev = Json::array();
    for (const auto& [name, z] : pos.deviations)
      dev.push_back({{"param", name}, {"z", abi::number(z)}});
    j["deviations"] = dev;
    j["note"] = nullptr;
  } catch (const std::exception& e) {
    j["note"] = e.what();
  }
  return j;
}

double median_of(std::vector<double> v) {
  if (v.empty()) return NAN;
  std::sort(v.begin(), v.end());
  const size_t h = v.size() / 2;
  return v.size() % 2 ? v[h] : 0.5 * (v[h - 1] + v[h]);
}

// "prior": "fleet" (session key prior): the passed units of the camera's model and lens id in
// the records as the engine's prior (records/fleet.hpp, fleet_prior), weighed against their
// median residual sigma; unless the config sets accuracy_px, the stop is their median expected
// error (90th percentile), i.e. what a unit calibrated without the prior reached. The units must
// share one image size (the engine refuses a camera of another) and vary in every parameter the
// session leaves free; otherwise, or with too few units (p + 3) or a store that cannot be read,
// the session runs without the prior and *info's note says why.
void apply_fleet_prior(const SessionOptions& so, const Json& config, const DeviceInfo& camera,
                       EngineOptions* eo, Json* info) {
  *info = {{"source", "fleet"},
           {"used", false},
           {"units", 0},
           {"accuracy_px", nullptr},
           {"note", nullptr}};
  if (so.records.empty()) {
    throw Error(ErrorCode::kInvalidArgument,
                "session config 'prior': \"fleet\" needs 'records' (the store of the fleet)");
  }
  try {
    std::vector<Json> results;
    std::vector<FleetUnit> units = fleet_units(so.records, camera.model, so.lens_id,
                                               eo->calibration.lens_model, so.run_id, &results);
    std::vector<double> sigma, p90;
    for (const Json& r : results) {
      if (r.contains("residual_sigma") && r["residual_sigma"].is_number())
        sigma.push_back(r["residual_sigma"].get<double>());
      if (r.contains("expected_error_p90_px") && r["expected_error_p90_px"].is_number())
        p90.push_back(r["expected_error_p90_px"].get<double>());
    }
    (*info)["units"] = units.size();
    CalibrationOptions co = eo->calibration;
    co.prior = fleet_prior(co.lens_model, units, median_of(sigma));
    std::string why;
    if (!co.is_valid(&why)) throw Error(ErrorCode::kDegenerate, "fleet prior: " + why);
    const cv::Size size(results.front().value("image_width", 0),
                        results.front().value("image_height", 0));
    for (const Json& r : results) {
      if (r.value("image_width", 0) != size.width || r.value("image_height", 0) != size.height)
        throw Error(ErrorCode::kDegenerate, "fleet prior: the units' images differ in size");
    }
    co.prior->image_size = size;
    prior_result(size, co);  // throws if a free parameter of the session does not vary in the fleet
    eo->calibration = co;
    if (!config.contains("accuracy_px") || config["accuracy_px"].is_null()) {
      if (!(median_of(p90) > 0))
        throw Error(ErrorCode::kDegenerate, "fleet prior: the units have no expected error");
      eo->accuracy_px = median_of(p90);
    }
    info->update(abi::prior_json(*co.prior, intrinsic_names(co.lens_model)));
    (*info)["used"] = true;
    (*info)["accuracy_px"] = *eo->accuracy_px;
  } catch (const Error& e) {
    (*info)["note"] = std::string(e.what()) + "; calibrating without the prior";
  }
}

// The result JSON (posecal_session_result; the record's result): Error(kState) before a
// calibration exists.
Json result_json(posecal_session* session) {
  const CalibrationResult& r = require_result(session);
  CalibrationEngine& eng = session->session->engine();
  Json j = abi::calibration_json(r);
  j["state"] = engine_state_name(eng.state());
  j["converged"] = eng.converged();
  j["interrupted"] = was_interrupted(session);
  journal_json(*session->session, &j);
  if (eng.state() == EngineState::kFailed) j["failure"] = eng.failure_reason();
  j["keyframes"] = eng.keyframes();
  j["frames_processed"] = session->session->frames_processed();
  j["target"] = eng.options().board.to_string();
  j["camera"] = abi::device_json(session->camera);
  j["locked_settings"] = session->session->locked_settings();
  j["started"] = session->started;
  j["finished"] = session->finished.empty() ? Json(nullptr) : Json(session->finished);
  const double seconds = session->finished_seconds.value_or(
      std::chrono::duration<double>(std::chrono::steady_clock::now() - session->opened).count());
  j["seconds"] = abi::number(seconds);
  Json conv = Json::object();
  for (const auto& p : eng.parameters()) conv[p.name] = p.converged;
  j["parameter_converged"] = conv;
  if (!eng.lens_candidates().empty()) j["lens_model_choice"] = abi::lens_choice_json(eng);
  if (SimCamera* sim = as_sim_camera(&session->session->camera())) {
    if (session->test_set.empty()) session->test_set = abi::sim_test_set(sim->sim_options());
    if (session->evaluated_keyframes != eng.keyframes()) {
      session->evaluation = abi::evaluation_json(r.model, session->test_set, &sim->truth());
      session->evaluated_keyframes = eng.keyframes();
    }
    j.update(session->evaluation);
    Json truth;
    for (int i = 0; i < sim->truth().num_params(); ++i) {
      truth[sim->truth().param_names()[i]] = sim->truth().params()[i];
    }
    j["ground_truth"] = truth;
    Json att = Json::object();
    for (const auto& [kind, a] : sim->op().attempts())
      att[kind] = {{"attempts", a.attempts}, {"reached", a.reached}};
    j["operator_attempts"] = att;
  }
  if (session->spec) j.update(abi::quality_verdict(*session->spec, j, eng.keyframes(), seconds));
  records_json(session, &j);
  if (!session->prior_info.is_null()) j["prior"] = session->prior_info;
  if (!session->records_url.empty() && (session->session->finished() || session->interrupted)) {
    if (!session->fleet) session->fleet = fleet_json(session, r);
    j["fleet"] = *session->fleet;
  }
  return j;
}

// Completes the run's record once: its state, the result JSON (empty before a calibration
// exists), the verdict and the expected error.
void finish_record(posecal_session* s, const std::string& state) {
  if (!s->records || s->record_finished) return;
  s->record_finished = true;
  Json j = Json::object();
  try {
    j = result_json(s);
  } catch (const Error&) {
    // No calibration yet (fewer than two keyframes): the record keeps the state alone.
  }
  std::optional<double> expected;
  if (j.contains("expected_error_px") && j["expected_error_px"].is_number())
    expected = j["expected_error_px"].get<double>();
  const std::string verdict = j.contains("verdict") && j["verdict"].is_string() ? j["verdict"].get<std::string>() : "";
  const std::string text = j.empty() ? std::string() : abi::to_text(j);
  s->records->finish(state, text, verdict, expected);
}

}  // namespace

namespace {

void save_session(posecal_session* session, const char* path, const char* format,
                  const char* function) {
  require(session, "session");
  require(path, "path");
  check_not_in_callback(session, function);
  const CalibrationResult& r = require_result(session);
  const CalibrationEngine& eng = session->session->engine();
  CalibrationFileExtras extras;
  extras.strings = {{"camera_uri", session->camera.uri},
                    {"camera_id", session->camera.id},
                    {"target", eng.options().board.to_string()}};
  extras.converged = eng.converged();
  extras.interrupted = was_interrupted(session);
  abi::save_calibration(path, r, format, extras);
}

}  // namespace

namespace {

// The "records" key: opens the store and begins the run's record; every keyframe is added as
// the engine keeps it (one transaction each). A store that cannot be opened does not stop the
// calibration: the session goes on unrecorded and says why (records_note).
void open_record(posecal_session* s, const SessionOptions& o, const Json& config) {
  s->records_location = sql::redact_url(o.records);
  s->records_url = o.records;
  s->lens_id = o.lens_id;
  s->fleet_alpha = o.fleet_outlier_probability;
  s->run_id = o.run_id.empty() ? new_run_id() : o.run_id;
  RunIdentity id;
  id.run_id = s->run_id;
  id.station_id = o.station_id;
  id.operator_id = o.operator_id;
  id.lens_id = o.lens_id;
  id.camera_uri = s->camera.uri;
  id.camera_id = s->camera.id;
  id.camera_vendor = s->camera.vendor;
  id.camera_model = s->camera.model;
  id.camera_serial = s->camera.serial;
  id.camera_device_version = s->camera.transport;
  id.posecal_version = POSECAL_VERSION_STRING;
  id.abi_version = std::to_string(POSECAL_ABI_VERSION);
  id.config = abi::to_text(config);
  id.started = utc_now_iso8601();
  s->records = std::make_unique<RecordWriter>(o.records, id, o.records_spool);
  CalibrationSession::KeyframeObserver observer;
  observer.on_engine = [s](cv::Size size, const std::map<std::string, std::string>& locked) {
    s->records->set_engine(size, locked);
  };
  observer.on_keyframe = [s](int index, const KeyframeRecord& k, const cv::Mat& image) {
    s->records->add_keyframe(stored_keyframe(index, k, image));
  };
  s->session->set_keyframe_observer(std::move(observer));
}

}  // namespace

extern "C" {

POSECAL_API posecal_status posecal_session_open(posecal_context* ctx, const char* camera_uri,
                                                const char* config_json,
                                                posecal_session** out) noexcept {
  return guarded(__func__, [&] {
    require(out, "out");
    *out = nullptr;
    require(ctx, "ctx");
    require(camera_uri, "camera_uri");
    const Json c = abi::parse_options(config_json, abi::session_config_keys(), kConfig);
    const SessionOptions so_config = abi::session_options_from_json(c);
    EngineOptions eo = so_config.engine;
    const bool lock = so_config.lock_settings;
    const Uri uri = Uri::parse(camera_uri);
    ctx->impl->require_enabled(uri.scheme);
    auto s = std::make_unique<posecal_session>();
    s->context = ctx->impl;
    std::unique_ptr<Camera> camera;
    if (uri.scheme == "sim") {
      // The simulated board must be the session's target (the board spec), and the simulated operator follows
      // the session's operator kind, so the camera is built here.
      SimCameraOptions so = sim_options_from_uri(uri, eo.board);
      const bool uri_has_op = uri.query.count("operator") > 0;
      const bool uri_robot = uri_has_op && uri.query.at("operator") == "robot";
      if (c.contains("operator") && uri_has_op && uri_robot != eo.robot) {
        throw Error(ErrorCode::kInvalidArgument,
                    "session config 'operator' contradicts the sim:// URI's operator");
      }
      eo.robot = eo.robot || uri_robot;
      so.op.kind = eo.robot ? OperatorKind::kRobot : OperatorKind::kPerson;
      if (!c.contains("target_timeout_frames")) {
        // The simulated person gives up after max_tries attempts; then move on.
        eo.target_timeout_frames = (so.op.move_frames + so.op.hold_frames) * so.op.max_tries + 1;
      }
      camera = make_sim_camera(so);
    } else {
      camera = ctx->impl->open(camera_uri, eo.board);
    }
    if (!so_config.spec.empty()) {
      // Read before the camera streams: a malformed specification costs no calibration.
      std::vector<std::string> names;
      for (LensModel m : lens_models())
        for (const std::string& n : intrinsic_names(m))
          if (std::find(names.begin(), names.end(), n) == names.end()) names.push_back(n);
      s->spec = abi::read_quality_spec(so_config.spec, names);
    }
    s->external = uri.scheme == "external";
    s->camera = camera->info();
    if (so_config.fleet_prior) apply_fleet_prior(so_config, c, s->camera, &eo, &s->prior_info);
    s->session = std::make_unique<CalibrationSession>(std::move(camera), eo, lock);
    if (!so_config.journal.empty()) {
      // The config a journal is resumed with must be the one it was recorded with, but for
      // the journal's own keys.
      Json recorded = c;
      for (const char* k :
           {"journal", "journal_images", "resume", "spec", "records", "records_spool",
            "fleet_outlier_probability", "run_id", "station_id", "operator_id", "lens_id"})
        recorded.erase(k);
      s->session->open_journal(so_config.journal, abi::to_text(recorded), so_config.journal_images,
                               so_config.resume);
    }
    if (!so_config.records.empty()) open_record(s.get(), so_config, c);
    posecal_session* raw = s.get();
    s->session->set_event_callback([raw](const SessionEvent& e) { deliver(raw, e); });
    s->started = utc_now_iso8601();
    *out = s.release();
    return POSECAL_OK;
  });
}

POSECAL_API void posecal_session_close(posecal_session* session) noexcept {
  abi::guarded_void(__func__, [&] {
    if (session && session->in_callback) {
      throw Error(ErrorCode::kState,
                  "called from the session's event callback: the session was not closed");
    }
    if (session && session->records && !session->record_finished) {
      // Closed before it finished by itself: interrupted by the host, or given up.
      finish_record(session, session->interrupted ? "interrupted" : "closed");
    }
    delete session;
  });
}

POSECAL_API posecal_status posecal_session_step(posecal_session* session, int timeout_ms) noexcept {
  return guarded(__func__, [&] {
    require(session, "session");
    check_not_in_callback(session, "posecal_session_step");
    if (session->external) {
      throw Error(ErrorCode::kState,
                  "session on 'external' has no camera to step: use posecal_session_feed");
    }
    if (timeout_ms < 0 || timeout_ms > 600000) {
      throw Error(ErrorCode::kInvalidArgument,
                  "timeout_ms must be in [0, 600000], got " + std::to_string(timeout_ms));
    }
    check_running(session);
    const StepStatus st = session->session->step(timeout_ms);
    note_finished(session);
    note_finished_record(session);
    switch (st) {
      case StepStatus::kFrame:
        return POSECAL_OK;
      case StepStatus::kTimeout:
        throw Error(ErrorCode::kTimeout, "no frame from '" + session->camera.uri + "' within " +
                                             std::to_string(timeout_ms) + " ms");
      case StepStatus::kDisconnected:
        throw Error(ErrorCode::kDevice,
                    "camera '" + session->camera.uri + "' is disconnected (keyframes kept)");
      case StepStatus::kEndOfStream:
        throw Error(ErrorCode::kNotFound,
                    "camera '" + session->camera.uri + "' has no more frames");
      case StepStatus::kFinished:
        throw Error(ErrorCode::kState, "the calibration has finished");
    }
    return POSECAL_E_INTERNAL;
  });
}

POSECAL_API posecal_status posecal_session_feed(posecal_session* session,
                                                const posecal_image* image) noexcept {
  return guarded(__func__, [&] {
    require(session, "session");
    check_not_in_callback(session, "posecal_session_feed");
    const cv::Mat m = wrap_image(image);
    check_running(session);
    // CalibrationSession::feed keeps its own copy (for last_frame): the host's pixels are not
    // referenced beyond this call.
    if (image->format == POSECAL_PIXEL_RGB8) {
      cv::Mat bgr;
      cv::cvtColor(m, bgr, cv::COLOR_RGB2BGR);
      session->session->feed(bgr);
    } else {
      session->session->feed(m);
    }
    note_finished(session);
    note_finished_record(session);
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_session_status(posecal_session* session, char* buf,
                                                  size_t* size) noexcept {
  return guarded(__func__, [&] {
    require(session, "session");
    require(size, "size");
    return abi::copy_out(abi::to_text(status_json(session)), buf, size);
  });
}

POSECAL_API posecal_status posecal_session_target_pose(posecal_session* session, double rvec[3],
                                                       double tvec[3]) noexcept {
  return guarded(__func__, [&] {
    require(session, "session");
    require(rvec, "rvec");
    require(tvec, "tvec");
    const CalibrationEngine* eng = session->session->engine_ptr();
    if (!eng || !eng->target()) {
      throw Error(ErrorCode::kState,
                  eng ? std::string("no board while ") + engine_state_name(eng->state())
                      : "no board before the first frame");
    }
    const Pose& p = eng->target()->T_cam_board;
    for (int i = 0; i < 3; ++i) {
      rvec[i] = p.r[i];
      tvec[i] = p.t[i];
    }
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_session_pose_reached(posecal_session* session) noexcept {
  return guarded(__func__, [&] {
    require(session, "session");
    check_not_in_callback(session, "posecal_session_pose_reached");
    if (!session->session->options().robot) {
      throw Error(ErrorCode::kState,
                  "pose_reached is for sessions opened with \"operator\": \"robot\"");
    }
    session->session->engine().report_pose_reached();
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_session_skip_target(posecal_session* session) noexcept {
  return guarded(__func__, [&] {
    require(session, "session");
    check_not_in_callback(session, "posecal_session_skip_target");
    session->session->engine().skip_target();
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_session_last_frame(posecal_session* session,
                                                      posecal_image* out) noexcept {
  return guarded(__func__, [&] {
    require(session, "session");
    check_not_in_callback(session, "posecal_session_last_frame");
    cv::Mat dst = wrap_image(out);
    // The core session keeps the last frame (a copy, or a camera buffer it holds alive).
    const cv::Mat& last = session->session->last_frame();
    if (last.empty()) throw Error(ErrorCode::kState, "no frame processed yet");
    require_size(dst, last.size(), "the frame");
    cv::Mat converted;
    convert_into(last, converted, out->format);
    converted.copyTo(dst);  // dst wraps the host's buffer: copyTo keeps its stride
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_session_expected_error_map(posecal_session* session, float* out,
                                                              int width, int height,
                                                              size_t row_stride_bytes) noexcept {
  return guarded(__func__, [&] {
    require(session, "session");
    require(out, "out");
    check_not_in_callback(session, "posecal_session_expected_error_map");
    if (width < 2 || height < 2 || width > 16384 || height > 16384) {
      throw Error(ErrorCode::kInvalidArgument, "width and height must be in [2, 16384], got " +
                                                   std::to_string(width) + "x" + std::to_string(height));
    }
    const size_t row_bytes = static_cast<size_t>(width) * sizeof(float);
    if (row_stride_bytes == 0) row_stride_bytes = row_bytes;
    if (row_stride_bytes < row_bytes || row_stride_bytes % sizeof(float) != 0) {
      throw Error(ErrorCode::kInvalidArgument,
                  "row_stride_bytes must be 0 or a multiple of 4 of at least " + std::to_string(row_bytes));
    }
    const cv::Mat map = expected_error_map(require_result(session), width, height);
    cv::Mat dst(height, width, CV_32F, out, row_stride_bytes);
    map.copyTo(dst);  // dst wraps the host's buffer: copyTo keeps its stride
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_session_render_overlay(posecal_session* session,
                                                          posecal_image* inout) noexcept {
  return guarded(__func__, [&] {
    require(session, "session");
    check_not_in_callback(session, "posecal_session_render_overlay");
    cv::Mat m = wrap_image(inout);
    const CalibrationEngine& eng = session->session->engine();
    require_size(m, eng.estimate().size(), "the camera's");
    if (inout->format == POSECAL_PIXEL_RGB8) {
      cv::Mat bgr;
      cv::cvtColor(m, bgr, cv::COLOR_RGB2BGR);
      eng.draw_overlay(bgr);
      cv::cvtColor(bgr, m, cv::COLOR_BGR2RGB);
    } else {
      eng.draw_overlay(m);
    }
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_session_result(posecal_session* session, char* buf,
                                                  size_t* size) noexcept {
  return guarded(__func__, [&] {
    require(session, "session");
    require(size, "size");
    return abi::copy_out(abi::to_text(result_json(session)), buf, size);
  });
}


POSECAL_API posecal_status posecal_session_save(posecal_session* session,
                                                const char* path) noexcept {
  return guarded(__func__, [&] {
    save_session(session, path, nullptr, "posecal_session_save");
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_session_save_as(posecal_session* session, const char* path,
                                                   const char* format) noexcept {
  return guarded(__func__, [&] {
    save_session(session, path, format, "posecal_session_save_as");
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_session_interrupt(posecal_session* session) noexcept {
  return guarded(__func__, [&] {
    require(session, "session");
    // Only the flag: another thread may be inside posecal_session_step. A calibration that
    // finished before keeps its outcome (was_interrupted).
    session->interrupted = true;
    return POSECAL_OK;
  });
}

POSECAL_API posecal_status posecal_session_set_callback(posecal_session* session,
                                                        posecal_event_fn fn,
                                                        void* user_data) noexcept {
  return guarded(__func__, [&] {
    require(session, "session");
    check_not_in_callback(session, "posecal_session_set_callback");
    session->fn = fn;
    session->user_data = user_data;
    return POSECAL_OK;
  });
}

}  // extern "C"
