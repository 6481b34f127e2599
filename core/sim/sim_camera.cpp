#include "sim/sim_camera.hpp"

#include <cmath>

#include "calib/metrics.hpp"
#include "common/error.hpp"
#include "io/model_file.hpp"
#include "lens/reference_models.hpp"
#include "board/views.hpp"

namespace posecal {

std::vector<Observation> render_test_set(SyntheticCamera& camera, int count) {
  std::vector<Observation> out;
  for (const Pose& p : test_set_views(camera.model(), camera.board(), count)) {
    // A test frame must determine its pose: at least half the board (a handful of corners on
    // one row at the border gave PnP nothing to hold on to and a 1150 px "test error").
    const Detection d = camera.board().detect(camera.render(p));
    if (static_cast<int>(d.size()) >= camera.board().num_corners() / 2) out.push_back(Observation::from(d));
  }
  return out;
}

SimEvaluation evaluate_synthetic(const CameraModel& estimate, const CameraModel& truth,
                                 const std::vector<Observation>& test_set) {
  SimEvaluation e;
  const TestError te = test_error(estimate, test_set);
  e.eps_test = te.rms_px;
  e.test_frames = te.frames_used;
  e.eps_gt = ground_truth_error(truth, estimate);
  return e;
}

namespace {

DeviceInfo sim_info(const SimCameraOptions& o) {
  DeviceInfo info;
  info.uri = "sim://?seed=" + std::to_string(o.seed) + "&operator=" +
             (o.op.kind == OperatorKind::kRobot ? "robot" : "person");
  info.backend = "sim";
  info.id = "sim-" + std::to_string(o.seed);
  info.vendor = "posecal";
  info.model = "synthetic camera " + std::to_string(o.truth.width()) + "x" + std::to_string(o.truth.height());
  info.serial = "SIM" + std::to_string(o.seed);
  info.transport = "simulated";
  return info;
}

class SimCameraImpl final : public SimCamera {
 public:
  explicit SimCameraImpl(const SimCameraOptions& o)
      : SimCamera(sim_info(o)),
        options_(o),
        board_(o.board),
        synthetic_(o.truth, board_, o.render),
        operator_(o.truth, board_, o.op, o.seed * 0x9e3779b97f4a7c15ull + 17) {}

  void guide(const GuidanceInfo& g) override { guidance_ = g; }
  bool take_pose_reached() override { return operator_.take_pose_reached(); }

  const CameraModel& truth() const override { return options_.truth; }
  SyntheticCamera& synthetic() override { return synthetic_; }
  const SimulatedOperator& op() const override { return operator_; }
  const SimCameraOptions& sim_options() const override { return options_; }

 protected:
  CameraConfig do_validate(const CameraConfig& r) override {
    if (r.exposure_us || r.gain_db || r.roi) {
      throw Error(ErrorCode::kUnsupported, label() + ": simulated camera has fixed settings");
    }
    if (r.pixel_format && *r.pixel_format != PixelFormat::kMono8) {
      throw Error(ErrorCode::kUnsupported, label() + " delivers Mono8 only");
    }
    return r;
  }
  std::vector<FeatureInfo> do_features() override {
    auto num = [](double v) { return std::to_string(v); };
    const auto I = FeatureType::kInteger, F = FeatureType::kFloat;
    std::vector<FeatureInfo> out;
    out.push_back({"Width", I, std::to_string(options_.truth.width()), true, false, "px", "", "", {}});
    out.push_back({"Height", I, std::to_string(options_.truth.height()), true, false, "px", "", "", {}});
    out.push_back({"NoiseSigma", F, num(options_.render.noise_sigma), true, false, "grey levels", "", "", {}});
    out.push_back({"BlurSigma", F, num(options_.render.blur_sigma_px), true, false, "px", "", "", {}});
    out.push_back({"Operator", FeatureType::kEnumeration, options_.op.kind == OperatorKind::kRobot ? "robot" : "person",
                   true, false, "", "", "", {"person", "robot"}});
    return out;
  }
  std::string do_get_feature(const std::string& name) override {
    for (const auto& f : do_features())
      if (f.name == name) return f.value;
    return SimCamera::do_get_feature(name);
  }
  void do_set_feature(const std::string& name, const std::string& value) override {
    for (const auto& f : do_features())
      if (f.name == name) throw Error(ErrorCode::kInvalidArgument, label() + ": feature '" + name + "' is read-only");
    SimCamera::do_set_feature(name, value);
  }
  std::map<std::string, std::string> do_lock_for_calibration() override {
    return {{"exposure", std::to_string(options_.render.exposure)}, {"focus", "fixed (simulated)"}};
  }
  FrameStatus do_next_frame(int, Frame* frame) override {
    const Pose p = operator_.next_pose(guidance_);
    frame->image = synthetic_.render(p);
    frame->frame_id = frame_id_++;
    frame->timestamp_ns = static_cast<int64_t>(frame->frame_id) * 33'333'333;
    frame->source_format = PixelFormat::kMono8;
    ++stats_.frames_delivered;
    return FrameStatus::kOk;
  }

 private:
  SimCameraOptions options_;
  Board board_;
  SyntheticCamera synthetic_;
  SimulatedOperator operator_;
  GuidanceInfo guidance_;
  uint64_t frame_id_ = 0;
};

class SimBackend final : public CameraBackend {
 public:
  explicit SimBackend(BoardSpec t) : board_(std::move(t)) {}
  std::string scheme() const override { return "sim"; }
  std::vector<DeviceInfo> enumerate() override {
    DeviceInfo d;
    d.uri = "sim://";
    d.backend = "sim";
    d.id = "sim";
    d.vendor = "posecal";
    d.model = "synthetic camera (sampled around the Logitech C525)";
    d.serial = "SIM1";
    d.transport = "simulated";
    return {d};
  }
  std::unique_ptr<Camera> open(const Uri& uri) override { return make_sim_camera(sim_options_from_uri(uri, board_)); }

 private:
  BoardSpec board_;
};

double parse_number(const Uri& uri, const std::string& key, double lo, double hi) {
  const std::string& text = uri.query.at(key);
  size_t used = 0;
  double v = 0;
  try {
    v = std::stod(text, &used);
  } catch (...) {
    used = 0;
  }
  if (used == 0 || used != text.size() || !(v >= lo && v <= hi)) {
    throw Error(ErrorCode::kInvalidArgument, "camera URI '" + uri.text + "': " + key + " must be a number in [" +
                                                 std::to_string(lo) + ", " + std::to_string(hi) + "]");
  }
  return v;
}

}  // namespace

SimCameraOptions sim_options_from_uri(const Uri& uri, const BoardSpec& board) {
  if (!uri.path.empty()) {
    throw Error(ErrorCode::kInvalidArgument, "camera URI '" + uri.text + "': use sim://?key=value options");
  }
  for (const auto& [k, v] : uri.query) {
    if (k != "model" && k != "seed" && k != "operator" && k != "noise" && k != "blur" && k != "renderer") {
      throw Error(ErrorCode::kInvalidArgument, "camera URI '" + uri.text + "': unknown option '" + k +
                                                   "' (model, seed, operator, noise, blur, renderer)");
    }
  }
  SimCameraOptions o;
  o.board = board;
  o.seed = uri.query.count("seed") ? static_cast<uint64_t>(parse_number(uri, "seed", 0, 4e9)) : 1;
  if (uri.query.count("model")) {
    o.truth = read_camera_model(uri.query.at("model"));
  } else {
    o.truth = sample_camera(c525_reference_model(), 0.1, o.seed);
  }
  if (uri.query.count("operator")) {
    // "person" is the default person ("approach"); the other names are operator presets.
    const std::string& k = uri.query.at("operator");
    try {
      o.op = operator_preset(k == "person" ? "approach" : k);
    } catch (const Error&) {
      throw Error(ErrorCode::kInvalidArgument, "camera URI '" + uri.text + "': operator must be person or one of " +
                                                   kOperatorPresetNames);
    }
  }
  if (uri.query.count("renderer")) {
    const std::string& r = uri.query.at("renderer");
    if (r != "raycast" && r != "warp")
      throw Error(ErrorCode::kInvalidArgument, "camera URI '" + uri.text + "': renderer must be raycast or warp");
    o.render.renderer = r == "warp" ? Renderer::kWarp : Renderer::kRayCast;
  }
  o.render.noise_sigma = uri.query.count("noise") ? parse_number(uri, "noise", 0, 50) : 2.0;
  o.render.blur_sigma_px = uri.query.count("blur") ? parse_number(uri, "blur", 0, 10) : 0.8;
  o.render.seed = o.seed;
  return o;
}

std::unique_ptr<Camera> make_sim_camera(const SimCameraOptions& options) {
  return std::make_unique<SimCameraImpl>(options);
}

std::shared_ptr<CameraBackend> make_sim_backend(const BoardSpec& board) { return std::make_shared<SimBackend>(board); }

SimCamera* as_sim_camera(Camera* camera) { return dynamic_cast<SimCamera*>(camera); }

}  // namespace posecal
