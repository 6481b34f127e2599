#include "sim/simulation.hpp"

#include <cmath>
#include <opencv2/calib3d.hpp>

#include "common/error.hpp"
#include "calib/metrics.hpp"
#include "board/views.hpp"
#include "io/model_file.hpp"
#include "lens/reference_models.hpp"

namespace posecal {

namespace {
constexpr double kPi = 3.14159265358979323846;

Eigen::Matrix3d small_rotation(double ax, double ay, double az) {
  return (Eigen::AngleAxisd(az, Eigen::Vector3d::UnitZ()) * Eigen::AngleAxisd(ay, Eigen::Vector3d::UnitY()) *
          Eigen::AngleAxisd(ax, Eigen::Vector3d::UnitX()))
      .toRotationMatrix();
}

Eigen::Vector3d board_centre(const Board& t) {
  const cv::Size2d bs = t.board_size_m();
  return {bs.width / 2, bs.height / 2, 0};
}
}  // namespace

bool OperatorOptions::is_valid(std::string* error) const {
  auto fail = [&](const std::string& w) {
    if (error) *error = w;
    return false;
  };
  if (!(rotation_error_deg >= 0 && rotation_error_deg < 45)) return fail("rotation error must be in [0, 45) deg");
  if (!(translation_error_fraction >= 0 && translation_error_fraction < 0.5)) return fail("translation error in [0, 0.5)");
  if (move_frames < 1 || move_frames > 100) return fail("move_frames must be in [1, 100]");
  if (hold_frames < 2 || hold_frames > 100) return fail("hold_frames must be in [2, 100]");
  if (!(jitter_px >= 0 && jitter_px < 1.5)) return fail("jitter must be in [0, 1.5) px");
  if (max_tries < 1 || max_tries > 1000) return fail("max_tries must be in [1, 1000]");
  return true;
}

SimulatedOperator::SimulatedOperator(const CameraModel& truth, const Board& board,
                                     const OperatorOptions& options, uint64_t seed)
    : truth_(truth), board_(board), opt_(options), rng_(seed) {
  std::string why;
  if (!options.is_valid(&why)) throw Error(ErrorCode::kInvalidArgument, "operator options: " + why);
}

Pose SimulatedOperator::perturb(const Pose& p) {
  std::normal_distribution<double> N(0.0, 1.0);
  const double sr = opt_.rotation_error_deg * kPi / 180.0;
  const Eigen::Vector3d c = p.apply(board_centre(board_));
  const Eigen::Matrix3d R = small_rotation(sr * N(rng_), sr * N(rng_), sr * N(rng_)) * p.R();
  // Translation error: N(0, 2% of the distance) per axis. For fields of view narrower than the
  // C525's (width / f = 1.2) the lateral part shrinks with the view, so the error stays the same
  // in the image: nobody misaligns an overlay by a fifth of a telephoto's view
  // (docs/pose-selection.md).
  const double st = opt_.translation_error_fraction * c.norm();
  const double fov = std::min(1.0, truth_.width() / truth_.fx() / 1.2);
  const Eigen::Vector3d c2 = c + Eigen::Vector3d(st * fov * N(rng_), st * fov * N(rng_), st * N(rng_));
  return Pose::from_rotation(R, c2 - R * board_centre(board_));
}

Pose SimulatedOperator::bootstrap_goal() {
  // A person first shows the board roughly fronto-parallel near the centre (paper §3.4).
  std::normal_distribution<double> N(0.0, 1.0);
  std::uniform_real_distribution<double> U(-1.0, 1.0);
  const double frac = 0.5 + 0.1 * U(rng_);
  const double depth = truth_.fx() * board_.board_size_m().width / (frac * truth_.width());
  const Eigen::Vector2d px(truth_.cx() + 0.1 * truth_.width() * U(rng_), truth_.cy() + 0.1 * truth_.height() * U(rng_));
  Eigen::Vector2d xn;
  if (!truth_.unproject(px, &xn)) xn.setZero();
  // Roughly fronto-parallel at first; each further attempt follows the guidance "tilt the board"
  // a little more (10 degrees more per attempt, up to 50), about a random in-plane axis.
  const double tilt = std::min(50.0, 10.0 * (1 + tries_)) * kPi / 180.0 * std::abs(N(rng_));
  const double axis = kPi * U(rng_);
  const Eigen::Matrix3d R = Eigen::AngleAxisd(tilt, Eigen::Vector3d(std::cos(axis), std::sin(axis), 0)).toRotationMatrix() *
                            small_rotation(0, 0, 5.0 * kPi / 180.0 * N(rng_));
  const Eigen::Vector3d c(xn.x() * depth, xn.y() * depth, depth);
  return Pose::from_rotation(R, c - R * board_centre(board_));
}

Pose SimulatedOperator::attempt_goal(const GuidanceInfo& g) {
  if (!g.has_target) return bootstrap_goal();
  if (g.robot) return perturb(g.T_cam_board_target);
  // A person makes the board's image match the overlay, which is drawn with the engine's
  // current (imperfect) intrinsics: the pose that the TRUE camera sees as the overlay.
  std::vector<cv::Point3d> pts = board_.corners();
  for (const auto& o : board_.outline()) pts.push_back(o);
  const auto overlay = project_points(g.estimate, g.T_cam_board_target, pts);
  Pose aligned = g.T_cam_board_target;
  std::vector<cv::Point3d> obj;
  std::vector<cv::Point2d> img;
  for (size_t i = 0; i < pts.size(); ++i) {
    if (std::isfinite(overlay[i].x)) {
      obj.push_back(pts[i]);
      img.push_back(overlay[i]);
    }
  }
  if (obj.size() >= 6) {
    cv::Mat rvec = (cv::Mat_<double>(3, 1) << aligned.r.x(), aligned.r.y(), aligned.r.z());
    cv::Mat tvec = (cv::Mat_<double>(3, 1) << aligned.t.x(), aligned.t.y(), aligned.t.z());
    try {
      if (cv::solvePnP(obj, img, cv::Mat(truth_.camera_matrix()), truth_.distortion_coefficients(), rvec, tvec, true)) {
        Pose p;
        p.r << rvec.at<double>(0), rvec.at<double>(1), rvec.at<double>(2);
        p.t << tvec.at<double>(0), tvec.at<double>(1), tvec.at<double>(2);
        if (p.is_finite() && p.t.z() > 0) aligned = p;
      }
    } catch (const cv::Exception&) {
    }
  }
  return perturb(aligned);
}

Pose SimulatedOperator::next_pose(const GuidanceInfo& g) {
  const int cycle = opt_.move_frames + opt_.hold_frames;
  auto start_attempt = [&]() {
    from_ = have_current_ ? current_ : attempt_goal(g);
    goal_ = attempt_goal(g);
    phase_frame_ = 0;
    in_attempt_ = true;
    ++stats_[kind_].attempts;
  };
  if (!g.finished) {
    if (g.target_serial != serial_) {
      if (in_attempt_ && g.keyframes > keyframes_seen_) ++stats_[kind_].reached;
      serial_ = g.target_serial;
      kind_ = g.has_target ? target_kind_name(g.target_kind) : "bootstrap";
      tries_ = 0;
      gave_up_ = false;
      start_attempt();
    } else if (phase_frame_ >= cycle && !gave_up_) {
      // While bootstrapping the engine keeps asking; a person keeps trying.
      if (++tries_ < opt_.max_tries || !g.has_target) {
        start_attempt();
      } else {
        gave_up_ = true;
      }
    }
  } else if (in_attempt_ && g.keyframes > keyframes_seen_) {
    ++stats_[kind_].reached;
    in_attempt_ = false;
  }
  keyframes_seen_ = g.keyframes;

  Pose p;
  if (phase_frame_ < opt_.move_frames && in_attempt_) {
    // Moving: interpolate rotation (slerp) and translation towards the goal.
    const double a = (phase_frame_ + 1.0) / opt_.move_frames;
    const Eigen::Quaterniond q0(from_.R()), q1(goal_.R());
    const Eigen::Vector3d c0 = from_.apply(board_centre(board_)), c1 = goal_.apply(board_centre(board_));
    const Eigen::Matrix3d R = q0.slerp(a, q1).toRotationMatrix();
    p = Pose::from_rotation(R, (1 - a) * c0 + a * c1 - R * board_centre(board_));
  } else {
    // Holding: sub-pixel tremor.
    std::normal_distribution<double> N(0.0, 1.0);
    const double depth = std::max(0.05, goal_.apply(board_centre(board_)).z());
    const double s = opt_.jitter_px * depth / truth_.fx();
    p = goal_;
    p.t += Eigen::Vector3d(s * N(rng_), s * N(rng_), 0.0);
    if (phase_frame_ == opt_.move_frames && g.robot && g.has_target) reached_signal_ = true;
  }
  ++phase_frame_;
  current_ = p;
  have_current_ = true;
  return p;
}

bool SimulatedOperator::take_pose_reached() {
  const bool r = reached_signal_;
  reached_signal_ = false;
  return r;
}

CameraModel sample_camera(const CameraModel& reference, double rel_std, uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> N(0.0, 1.0);
  for (int attempt = 0; attempt < 1000; ++attempt) {
    std::vector<double> p = reference.params();
    for (double& v : p) v += rel_std * v * N(rng);
    CameraModel m(reference.width(), reference.height(), reference.lens_model(), p);
    if (!m.is_valid()) continue;
    // The lens model must be one-to-one over the whole image.
    const cv::Mat dm = m.distortion_map(std::max(8, reference.width() / 64));
    bool ok = true;
    for (auto it = dm.begin<float>(); it != dm.end<float>() && ok; ++it) ok = std::isfinite(*it);
    if (ok) return m;
  }
  throw Error(ErrorCode::kInternal, "could not sample a valid camera around the reference");
}

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
    if (k != "model" && k != "seed" && k != "operator" && k != "noise" && k != "blur") {
      throw Error(ErrorCode::kInvalidArgument, "camera URI '" + uri.text + "': unknown option '" + k +
                                                   "' (model, seed, operator, noise, blur)");
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
    const std::string& k = uri.query.at("operator");
    if (k == "person") {
      o.op.kind = OperatorKind::kPerson;
    } else if (k == "robot") {
      o.op.kind = OperatorKind::kRobot;
    } else {
      throw Error(ErrorCode::kInvalidArgument, "camera URI '" + uri.text + "': operator must be person or robot");
    }
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
