// Closed-loop calibration through the Aravis backend: the engine guides a simulated operator,
// whose board Aravis' GigE Vision simulator renders and sends over GVCP/GVSP on loopback; the
// session receives it through make_aravis_backend(), opened by serial number
// (guided_loop.hpp explains the lockstep coupling). Person and robot must converge to a result
// within 5 sigma of the truth, with every frame the engine used bit-identical to what the
// simulator sent; the robot run must reproduce sim:// with the same seed frame for frame; a
// camera that vanishes mid-session must be reported within 2 s and the session must go on to
// convergence when it returns. Every wait has a deadline.
#include <gtest/gtest.h>

#include <chrono>
#include <cstdio>
#include <thread>

#include "guided_aravis.hpp"
#include "posecal/aravis_backend.hpp"
#include "calib/metrics.hpp"
#include "session/session.hpp"

using namespace posecal;
using namespace posecal::testing;
using Clock = std::chrono::steady_clock;

namespace {

constexpr const char* kLoopback = "127.0.0.1";
// The simulator's frame rate. Lockstep makes a step last at least one frame period after the
// engine has finished the previous one, so a fast camera keeps the tests short.
constexpr double kFps = 60;
constexpr double kSessionLimitS = 45;  // a session that has not converged by then fails

double ms_since(Clock::time_point t0) {
  return std::chrono::duration<double, std::milli>(Clock::now() - t0).count();
}

// Every intrinsic within 5 sigma (std_scaled) of the truth, as core's closed-loop tests demand.
void expect_honest(const CalibrationEngine& e, const CameraModel& truth, const char* who) {
  ASSERT_NE(e.result(), nullptr) << who;
  const CalibrationResult& r = *e.result();
  for (int i = 0; i < truth.num_params(); ++i) {
    EXPECT_LT(std::abs(r.model.params()[i] - truth.params()[i]), 5 * r.std_scaled[i] + 1e-12)
        << who << " " << truth.param_names()[i] << ": estimate " << r.model.params()[i]
        << ", truth " << truth.params()[i] << ", sigma " << r.std_scaled[i];
  }
}

// Every frame the engine used came through the stream intact and exactly once.
void expect_clean_stream(const GuidedCamera& cam, const CalibrationSession& s,
                         const GuidedScene& scene, const FakeGvCamera& fake) {
  const GuidedCameraStats g = cam.guided_stats();
  EXPECT_EQ(g.delivered, s.frames_processed());
  EXPECT_EQ(g.exact, g.delivered) << cam.first_problem();
  EXPECT_EQ(g.corrupt, 0u) << cam.first_problem();
  EXPECT_EQ(g.unknown, 0u) << cam.first_problem();
  EXPECT_EQ(g.step_gaps, 0u);
  EXPECT_EQ(fake.source_rejects(), 0u);
  // The operator took one step per processed frame (plus at most the one after the last).
  const GuidedSceneStats st = scene.stats();
  EXPECT_GE(st.steps, g.delivered);
  EXPECT_LE(st.steps, g.delivered + 1);
}

struct Rig {
  std::shared_ptr<GuidedScene> scene;
  std::unique_ptr<FakeGvCamera> fake;
  CameraManager manager;

  Rig(const GuidedSceneOptions& options, const std::string& serial) {
    scene = std::make_shared<GuidedScene>(options, mono8_encoder());
    fake = std::make_unique<FakeGvCamera>(serial, kLoopback, guided_source(scene));
    manager.add_backend(make_aravis_backend());
  }
  // Opens the simulator by serial number (one discovery round) and wraps it for the session.
  std::unique_ptr<GuidedCamera> open() {
    std::unique_ptr<Camera> cam = manager.open("aravis://" + fake->serial());
    cam->configure(guided_config(*scene, kFps));
    return std::make_unique<GuidedCamera>(std::move(cam), scene,
                                          mono8_decoder(scene->truth().size()));
  }
};

void print_run(const char* who, const CalibrationSession& s, const GuidedScene& scene,
               const GuidedCamera& cam, double wall_ms) {
  const CalibrationEngine& e = *s.engine_ptr();
  const GuidedSceneStats st = scene.stats();
  const CameraStats cs = cam.stats();
  std::printf(
      "%s: %s, %d keyframes, %llu frames, eps_gt %.3f px, %.1f s; camera sent %llu frames "
      "(%llu repeats while the engine worked), %llu exact, %llu incomplete dropped\n",
      who, engine_state_name(e.state()), e.keyframes(),
      static_cast<unsigned long long>(s.frames_processed()),
      e.result() ? ground_truth_error(scene.truth(), e.result()->model) : -1.0, wall_ms / 1000,
      static_cast<unsigned long long>(st.frames), static_cast<unsigned long long>(st.repeats),
      static_cast<unsigned long long>(cam.guided_stats().exact),
      static_cast<unsigned long long>(cs.frames_incomplete));
}

// Steps the session until it finishes or the limit passes; fails on a disconnect.
void run_to_end(CalibrationSession& s, double limit_s) {
  const auto t0 = Clock::now();
  while (!s.finished() && ms_since(t0) < limit_s * 1000) {
    const StepStatus st = s.step(2000);
    ASSERT_NE(st, StepStatus::kDisconnected) << "the simulator vanished";
    ASSERT_NE(st, StepStatus::kEndOfStream);
  }
}

// The same session on sim:// (core's renderer and operator, no transport).
struct SimRun {
  EngineState state;
  int keyframes;
  uint64_t frames;
  std::vector<double> params;
};
SimRun run_sim(const GuidedSceneOptions& o) {
  CalibrationSession s(make_sim_camera(o.as_sim()), engine_options_for(o));
  for (int f = 0; f < 1500 && !s.finished(); ++f) s.step(1000);
  const CalibrationEngine& e = s.engine();
  return {e.state(), e.keyframes(), s.frames_processed(),
          e.result() ? e.result()->model.params() : std::vector<double>{}};
}

void closed_loop(OperatorKind kind, uint64_t seed, bool compare_with_sim) {
  const char* who = kind == OperatorKind::kRobot ? "robot" : "person";
  const GuidedSceneOptions options = c525_scene(seed, kind);
  Rig rig(options, kind == OperatorKind::kRobot ? "PCAL-ROBOT" : "PCAL-PERSON");
  ASSERT_TRUE(rig.fake->start()) << "the Aravis simulator could not listen on " << kLoopback
                                 << ":3956 (another simulator running?)";
  auto guided = rig.open();
  GuidedCamera* cam = guided.get();
  EXPECT_EQ(cam->info().serial, rig.fake->serial());
  CalibrationSession s(std::move(guided), engine_options_for(options));
  const auto t0 = Clock::now();
  ASSERT_NO_FATAL_FAILURE(run_to_end(s, kSessionLimitS));
  const double wall_ms = ms_since(t0);
  ASSERT_TRUE(s.has_engine());
  const CalibrationEngine& e = s.engine();
  print_run(who, s, *rig.scene, *cam, wall_ms);
  EXPECT_TRUE(e.converged()) << who << ": " << engine_state_name(e.state()) << " "
                             << e.failure_reason();
  EXPECT_FALSE(s.locked_settings().empty()) << "the session locks the camera's settings";
  expect_honest(e, options.truth, who);
  expect_clean_stream(*cam, s, *rig.scene, *rig.fake);
  EXPECT_EQ(cam->stats().disconnects, 0u);

  if (compare_with_sim) {
    // Lockstep makes the transport invisible to the loop: same frames, same keyframes, same
    // result as sim:// (a frame counted twice or skipped would change all three).
    const SimRun sim = run_sim(options);
    std::printf("%s on sim://: %s, %d keyframes, %llu frames\n", who, engine_state_name(sim.state),
                sim.keyframes, static_cast<unsigned long long>(sim.frames));
    EXPECT_EQ(sim.frames, s.frames_processed());
    EXPECT_EQ(sim.keyframes, e.keyframes());
    ASSERT_EQ(sim.params.size(), e.result()->model.params().size());
    for (size_t i = 0; i < sim.params.size(); ++i) {
      EXPECT_EQ(sim.params[i], e.result()->model.params()[i]) << options.truth.param_names()[i];
    }
  }
}

}  // namespace

TEST(AravisClosedLoop, PersonConvergesThroughGigEVision) {
  closed_loop(OperatorKind::kPerson, 2, false);
}

TEST(AravisClosedLoop, RobotConvergesAndReproducesSimFrameForFrame) {
  closed_loop(OperatorKind::kRobot, 4, true);
}

TEST(AravisClosedLoop, CameraVanishesMidSessionAndSessionResumes) {
  const GuidedSceneOptions options = c525_scene(3, OperatorKind::kPerson);
  Rig rig(options, "PCAL-GONE");
  ASSERT_TRUE(rig.fake->start());
  auto guided = rig.open();
  GuidedCamera* cam = guided.get();
  CalibrationSession s(std::move(guided), engine_options_for(options));
  std::vector<std::string> session_events;
  s.set_event_callback([&](const SessionEvent& ev) {
    if (ev.kind != SessionEvent::Kind::kEngine) session_events.push_back(ev.message);
  });

  // Until two keyframes: the engine has calibrated once and refines.
  auto t0 = Clock::now();
  while ((!s.has_engine() || s.engine().keyframes() < 2) && ms_since(t0) < 30000) {
    ASSERT_NE(s.step(2000), StepStatus::kDisconnected);
  }
  ASSERT_TRUE(s.has_engine());
  ASSERT_GE(s.engine().keyframes(), 2) << "no two keyframes within 30 s";
  ASSERT_FALSE(s.finished());
  const int keyframes_at_stop = s.engine().keyframes();
  const uint64_t frames_at_stop = s.frames_processed();

  // The camera vanishes (its simulator stops answering and sending).
  const auto t_stop = Clock::now();
  rig.fake->stop();
  StepStatus st = StepStatus::kFrame;
  while (ms_since(t_stop) < 5000) {
    st = s.step(100);
    if (st == StepStatus::kDisconnected) break;
  }
  const double detect_ms = ms_since(t_stop);
  ASSERT_EQ(st, StepStatus::kDisconnected) << "no disconnect within 5 s";
  // Frames already on their way when it vanished are still processed; nothing is lost.
  const int keyframes = s.engine().keyframes();
  const EngineState state = s.engine().state();
  const uint64_t frames = s.frames_processed();
  std::printf(
      "session reported the disconnect %.0f ms after the camera vanished (%d keyframes, "
      "state %s, %llu frames in flight processed)\n",
      detect_ms, keyframes, engine_state_name(state),
      static_cast<unsigned long long>(frames - frames_at_stop));
  EXPECT_LE(detect_ms, 2000);
  EXPECT_GE(keyframes, keyframes_at_stop);
  EXPECT_LE(frames - frames_at_stop, 4u)
      << "more than the backend's queue after the camera vanished";
  EXPECT_TRUE(s.disconnected());
  ASSERT_EQ(session_events.size(), 1u);
  EXPECT_NE(session_events[0].find("disconnected; keyframes kept"), std::string::npos);
  // While it is away: step() returns at once, the engine keeps its keyframes and its state.
  for (int i = 0; i < 5; ++i) {
    const auto t = Clock::now();
    EXPECT_EQ(s.step(1000), StepStatus::kDisconnected);
    EXPECT_LT(ms_since(t), 100);
  }
  EXPECT_EQ(s.engine().keyframes(), keyframes);
  EXPECT_EQ(s.engine().keyframe_observations().size(), static_cast<size_t>(keyframes));
  EXPECT_EQ(s.engine().state(), state);
  EXPECT_NE(s.engine().state(), EngineState::kFailed);
  EXPECT_EQ(s.frames_processed(), frames);

  // It comes back (a fresh simulator with the same serial on the same address); the backend
  // reconnects by itself and the session goes on.
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  ASSERT_TRUE(rig.fake->start());
  const auto t_back = Clock::now();
  while (ms_since(t_back) < 20000) {
    st = s.step(200);
    if (st == StepStatus::kFrame || st == StepStatus::kFinished) break;
    if (st == StepStatus::kDisconnected) std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  ASSERT_EQ(st, StepStatus::kFrame) << "no frame within 20 s of the camera's return";
  std::printf("frames again %.0f ms after the camera came back\n", ms_since(t_back));
  EXPECT_FALSE(s.disconnected());
  ASSERT_EQ(session_events.size(), 2u);
  EXPECT_NE(session_events[1].find("is back"), std::string::npos);
  EXPECT_GE(s.engine().keyframes(), keyframes);

  t0 = Clock::now();
  ASSERT_NO_FATAL_FAILURE(run_to_end(s, kSessionLimitS));
  print_run("person with a disconnect", s, *rig.scene, *cam, ms_since(t0));
  const CalibrationEngine& e = s.engine();
  EXPECT_TRUE(e.converged()) << engine_state_name(e.state()) << " " << e.failure_reason();
  EXPECT_GT(e.keyframes(), keyframes);
  expect_honest(e, options.truth, "person with a disconnect");
  expect_clean_stream(*cam, s, *rig.scene, *rig.fake);
  EXPECT_EQ(cam->stats().disconnects, 1u);
  EXPECT_EQ(dynamic_cast<AravisCamera&>(cam->inner()).transport_stats().reconnects, 1u);
}
