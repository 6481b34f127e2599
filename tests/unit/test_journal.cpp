// The session journal: records round-trip exactly, a cut or damaged tail is dropped and said,
// and a session resumed from a journal recomputes the same calibration bit for bit.
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <sstream>

#include "common/error.hpp"
#include "session/journal.hpp"
#include "session/session.hpp"
#include "sim/sim_camera.hpp"

using namespace posecal;
namespace fs = std::filesystem;

namespace {

fs::path fresh(const std::string& name) {
  const fs::path dir = fs::path(testing::TempDir()) / ("posecal_journal_" + name);
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir / "session.journal";
}

KeyframeRecord sample_record(int k) {
  KeyframeRecord r;
  r.state_before = k == 0 ? EngineState::kInitialPose1 : EngineState::kRefining;
  r.state_after = k == 0 ? EngineState::kInitialPose2 : EngineState::kRefining;
  r.target_param = k == 0 ? -1 : 3;
  for (int i = 0; i < 9; ++i) r.estimate_after.push_back(0.1 / 3.0 * (i + 1) * (k + 1) + 1e-17 * i);
  r.converged_after.assign(9, false);
  r.converged_after[2] = true;
  for (int i = 0; i < 6; ++i) {
    r.observation.ids.push_back(i);
    r.observation.image_points.emplace_back(100.0 / 7 * i, 200.0 / 3 + i);
    r.observation.board_points.emplace_back(0.028 * i, 0.028, 0.0);
  }
  return r;
}

void write_three(const fs::path& p) {
  JournalHeader h;
  h.camera_id = "cam-1";
  h.camera_serial = "S1";
  h.config = R"({"max_keyframes":12})";
  auto w = JournalWriter::create(p.string(), h);
  w->append_engine({640, 480}, {{"ExposureTime", "10000"}});
  for (int k = 0; k < 3; ++k) w->append_keyframe(k + 1, sample_record(k), cv::Mat());
}

bool same(const KeyframeRecord& a, const KeyframeRecord& b) {
  return a.estimate_after == b.estimate_after && a.converged_after == b.converged_after &&
         a.observation.ids == b.observation.ids &&
         a.observation.image_points == b.observation.image_points &&
         a.observation.board_points == b.observation.board_points &&
         a.state_before == b.state_before && a.state_after == b.state_after &&
         a.target_param == b.target_param;
}

}  // namespace

TEST(Journal, RecordsRoundTripExactly) {
  const fs::path p = fresh("roundtrip");
  write_three(p);
  const JournalContents j = read_journal(p.string());
  EXPECT_TRUE(j.has_header);
  EXPECT_EQ(j.header.camera_id, "cam-1");
  EXPECT_EQ(j.header.config, R"({"max_keyframes":12})");
  EXPECT_EQ(j.image_size, cv::Size(640, 480));
  EXPECT_EQ(j.locked_settings.at("ExposureTime"), "10000");
  ASSERT_EQ(j.keyframes.size(), 3u);
  for (int k = 0; k < 3; ++k) EXPECT_TRUE(same(j.keyframes[k], sample_record(k))) << k;
  EXPECT_TRUE(j.damage.empty()) << j.damage;
  EXPECT_EQ(j.valid_bytes, fs::file_size(p));
}

// A kill during a write leaves part of a line: the reader drops it and says so; the next
// writer cuts it off before appending, and the journal reads whole again.
TEST(Journal, ACutLastRecordIsDroppedAndTheJournalGoesOn) {
  const fs::path p = fresh("cut");
  write_three(p);
  const auto full = fs::file_size(p);
  fs::resize_file(p, full - 40);
  JournalContents j = read_journal(p.string());
  ASSERT_EQ(j.keyframes.size(), 2u);
  EXPECT_NE(j.damage.find("cut"), std::string::npos) << j.damage;
  {
    auto w = JournalWriter::resume(p.string(), j.valid_bytes);
    w->append_keyframe(3, sample_record(2), cv::Mat());
  }
  j = read_journal(p.string());
  ASSERT_EQ(j.keyframes.size(), 3u);
  EXPECT_TRUE(j.damage.empty()) << j.damage;
  EXPECT_TRUE(same(j.keyframes[2], sample_record(2)));
}

TEST(Journal, ADamagedRecordEndsTheJournalThere) {
  const fs::path p = fresh("crc");
  write_three(p);
  std::string text;
  {
    std::ifstream in(p);
    std::stringstream ss;
    ss << in.rdbuf();
    text = ss.str();
  }
  // Flip one digit inside the second keyframe's record.
  size_t line = 0;
  for (int i = 0; i < 3; ++i) line = text.find('\n', line) + 1;
  const size_t digit = text.find_first_of("123456789", line + 20);
  text[digit] = text[digit] == '1' ? '2' : '1';
  std::ofstream(p) << text;
  const JournalContents j = read_journal(p.string());
  EXPECT_EQ(j.keyframes.size(), 1u);
  EXPECT_NE(j.damage.find("line 4"), std::string::npos) << j.damage;
}

TEST(Journal, AFileThatIsNotAJournalIsRefusedNamingIt) {
  const fs::path p = fresh("other");
  std::ofstream(p) << "%YAML:1.0\ncamera_matrix: []\n";
  try {
    read_journal(p.string());
    FAIL() << "accepted";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
    EXPECT_NE(std::string(e.what()).find(p.string()), std::string::npos) << e.what();
  }
  EXPECT_THROW(read_journal((p.parent_path() / "none").string()), Error);
}

namespace {

std::unique_ptr<CalibrationSession> sim_session(const std::string& uri_text) {
  const Uri uri = Uri::parse(uri_text);
  SimCameraOptions so = sim_options_from_uri(uri, BoardSpec{});
  EngineOptions eo;
  eo.target_timeout_frames = 36;
  return std::make_unique<CalibrationSession>(make_sim_camera(so), eo);
}

}  // namespace

// The core of resume: a session stopped after some keyframes (as by a kill: nothing but the
// journal survives) and a new session on the same journal: the same keyframes, the same
// calibration bit for bit, and it goes on to convergence.
TEST(Journal, AResumedSessionRecomputesTheSameCalibrationAndConverges) {
  const fs::path p = fresh("resume");
  std::vector<double> params_before;
  int keyframes_before = 0;
  {
    auto s = sim_session("sim://?seed=21");
    s->open_journal(p.string(), "{}", false, true);
    for (int f = 0; f < 2000 && !s->finished() && (!s->has_engine() || s->engine().keyframes() < 4);
         ++f) {
      s->step(1000);
    }
    ASSERT_EQ(s->engine().keyframes(), 4);
    params_before = s->engine().result()->model.params();
    keyframes_before = s->engine().keyframes();
  }
  auto s = sim_session("sim://?seed=21");
  s->open_journal(p.string(), "{}", false, true);
  EXPECT_EQ(s->journal_status().resumed_keyframes, keyframes_before);
  s->step(1000);
  ASSERT_TRUE(s->has_engine());
  EXPECT_GE(s->engine().keyframes(), keyframes_before);
  ASSERT_TRUE(s->journal_status().identical.has_value());
  EXPECT_TRUE(*s->journal_status().identical);
  ASSERT_NE(s->engine().result(), nullptr);
  for (int f = 0; f < 2000 && !s->finished(); ++f) s->step(1000);
  EXPECT_TRUE(s->engine().converged()) << s->engine().failure_reason();
  // Every keyframe of both runs is in the journal, the resumed ones once.
  const JournalContents j = read_journal(p.string());
  EXPECT_EQ(static_cast<int>(j.keyframes.size()), s->engine().keyframes());
  EXPECT_EQ(j.end_state, "converged");
  EXPECT_EQ(j.keyframes[keyframes_before - 1].estimate_after, params_before);
}

// lens_model "auto": the bootstrap moves to the fisheye and the journal's keyframes carry its
// eight intrinsics; a resumed session must come back to the same model and calibration.
TEST(Journal, AnAutomaticLensModelResumesWithTheModelItChose) {
  const fs::path p = fresh("resume_auto");
  SimCameraOptions so;
  so.truth = CameraModel(1280, 1024, LensModel::kFisheye,
                         {317.1, 317.8, 641.5, 509.3, 0.008, -0.0012, 0.0002, -0.00001});
  so.seed = 3;
  so.render.seed = 3;
  EngineOptions eo;
  eo.target_timeout_frames = 36;
  eo.auto_lens_model = true;
  std::vector<double> params_before;
  {
    CalibrationSession s(make_sim_camera(so), eo);
    s.open_journal(p.string(), "{}", false, true);
    for (int f = 0; f < 2000 && !s.finished() && (!s.has_engine() || s.engine().keyframes() < 3);
         ++f) {
      s.step(1000);
    }
    ASSERT_EQ(s.engine().keyframes(), 3);
    ASSERT_EQ(s.engine().estimate().lens_model(), LensModel::kFisheye);
    ASSERT_EQ(s.engine().lens_candidates().size(), lens_models().size());
    params_before = s.engine().result()->model.params();
  }
  CalibrationSession s(make_sim_camera(so), eo);
  s.open_journal(p.string(), "{}", false, true);
  EXPECT_EQ(s.journal_status().resumed_keyframes, 3);
  s.step(1000);
  ASSERT_TRUE(s.has_engine());
  ASSERT_TRUE(s.journal_status().identical.has_value());
  EXPECT_TRUE(*s.journal_status().identical);
  EXPECT_EQ(s.engine().estimate().lens_model(), LensModel::kFisheye);
  ASSERT_NE(s.engine().result(), nullptr);
  EXPECT_EQ(s.engine().result()->model.params(), params_before);
}

TEST(Journal, AnotherCamerasJournalIsRefusedUnlessResumeIsOff) {
  const fs::path p = fresh("other_camera");
  {
    auto s = sim_session("sim://?seed=21");
    s->open_journal(p.string(), "{}", false, true);
    for (int f = 0; f < 5; ++f) s->step(1000);
  }
  auto other = sim_session("sim://?seed=22");
  try {
    other->open_journal(p.string(), "{}", false, true);
    FAIL() << "resumed another camera's journal";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
    EXPECT_NE(std::string(e.what()).find("sim-21"), std::string::npos) << e.what();
  }
  auto same_camera = sim_session("sim://?seed=21");
  EXPECT_THROW(same_camera->open_journal(p.string(), R"({"max_keyframes":5})", false, true), Error);
  other->open_journal(p.string(), "{}", false, false);
  EXPECT_NE(other->journal_status().note.find(".old"), std::string::npos);
  EXPECT_EQ(other->journal_status().resumed_keyframes, 0);
  int old_files = 0;
  for (const auto& e : fs::directory_iterator(p.parent_path()))
    old_files += e.path().extension() == ".old";
  EXPECT_EQ(old_files, 1);
}
