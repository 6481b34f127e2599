// Offline calibration from a folder (calib/offline.hpp): images grouped by size and camera, the
// group chosen, the others listed with the reason, progress per image (issue 17 item 4).
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>

#include "board/board.hpp"
#include "board/views.hpp"
#include "calib/offline.hpp"
#include "common/error.hpp"
#include "lens/reference_models.hpp"
#include "sim/synthetic.hpp"

using namespace posecal;
namespace fs = std::filesystem;

namespace {

fs::path fresh_dir(const std::string& name) {
  const fs::path dir = fs::path(testing::TempDir()) / name;
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

void blank(const fs::path& path, int w, int h) {
  ASSERT_TRUE(cv::imwrite(path.string(), cv::Mat(h, w, CV_8U, cv::Scalar(128))));
}

std::string describe(const std::vector<ImageGroup>& groups) {
  std::string s;
  for (const ImageGroup& g : groups) s += g.name + ":" + std::to_string(g.files.size()) + " ";
  return s;
}

}  // namespace

// The frame number is the name's last run of digits; what is left names the camera where two
// images share it; a name of its own goes with the one camera of its size.
TEST(GroupImages, ByCameraNameAndSize) {
  const fs::path dir = fresh_dir("posecal_group_images");
  for (const char* n : {"left01.png", "left02.png", "right01.png", "right02.png", "0001_top.png",
                        "0002_top.png"})
    blank(dir / n, 64, 48);
  for (const char* n : {"cam0_0001.png", "cam0_0002.png", "odd.png"}) blank(dir / n, 80, 60);
  blank(dir / "x.png", 100, 100);
  std::ofstream(dir / "notes.txt") << "not an image";
  std::vector<ImageVerdict> unreadable;
  const auto groups = group_images(list_files_sorted(dir.string()), &unreadable);
  EXPECT_EQ(describe(groups), "top@64x48:2 cam0@80x60:3 left@64x48:2 right@64x48:2 100x100:1 ");
  ASSERT_EQ(unreadable.size(), 1u);
  EXPECT_EQ(unreadable[0].file, "notes.txt");
  EXPECT_EQ(groups[1].camera, "cam0");
  EXPECT_EQ(fs::path(groups[1].files[2]).filename(), "odd.png");  // the one camera of 80x60
  EXPECT_EQ(groups[4].camera, "");

  // With two cameras of its size, a name of its own is a group of its own.
  blank(dir / "z.png", 64, 48);
  unreadable.clear();
  const auto more = group_images(list_files_sorted(dir.string()), &unreadable);
  EXPECT_EQ(describe(more),
            "top@64x48:2 cam0@80x60:3 left@64x48:2 right@64x48:2 100x100:1 64x48:1 ");
}

// Before, the first image by name decided the size and every image of another size was rejected
// "for size" behind the message "no image ... shows the target". Now such a folder is refused
// naming its groups, and camera_group calibrates one of them.
TEST(CalibrateImages, MixedFolderIsRefusedNamingItsGroupsAndOneGroupCalibrates) {
  const fs::path dir = fresh_dir("posecal_offline_mixed");
  const CameraModel cam = c525_reference_model();
  const Board board;
  SyntheticCamera sc(cam, board);
  int n = 0;
  for (const Pose& p : random_board_views(11, 6, cam, board)) {
    char name[32];
    std::snprintf(name, sizeof name, "view%02d.png", ++n);
    ASSERT_TRUE(cv::imwrite((dir / name).string(), sc.render(p)));
  }
  blank(dir / "aaa.png", 640, 480);  // first by name, another size
  try {
    calibrate_images(dir.string(), board.spec());
    ADD_FAILURE() << "a folder of two groups was calibrated";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
    const std::string what = e.what();
    EXPECT_NE(what.find("'640x480' (1 image)"), std::string::npos) << what;
    EXPECT_NE(what.find("'view@1280x720' (6 images)"), std::string::npos) << what;
    EXPECT_NE(what.find("--camera-group"), std::string::npos) << what;
  }

  OfflineOptions o;
  o.camera_group = "view";
  std::vector<ImageProgress> seen;
  o.progress = [&](const ImageProgress& p) { seen.push_back(p); };
  const OfflineCalibration cal = calibrate_images(dir.string(), board.spec(), o);
  EXPECT_EQ(cal.group, "view@1280x720");
  EXPECT_EQ(cal.used.size(), 6u);
  ASSERT_EQ(cal.rejected.size(), 1u);
  EXPECT_EQ(cal.rejected[0].file, "aaa.png");
  EXPECT_NE(cal.rejected[0].reason.find("in group '640x480'"), std::string::npos);
  EXPECT_LT(cal.result.rms_px, 0.5);
  ASSERT_EQ(seen.size(), 6u);
  for (size_t i = 0; i < seen.size(); ++i) {
    EXPECT_EQ(seen[i].index, i + 1);
    EXPECT_EQ(seen[i].total, 6u);
    EXPECT_TRUE(seen[i].used) << seen[i].file << ": " << seen[i].reason;
    EXPECT_GT(seen[i].corners, 6);
  }

  // The other group by its size; a name that matches nothing lists the groups.
  o.camera_group = "640x480";
  EXPECT_THROW(calibrate_images(dir.string(), board.spec(), o), Error);  // blank: no target
  o.camera_group = "right";
  try {
    calibrate_images(dir.string(), board.spec(), o);
    ADD_FAILURE() << "an unknown group was accepted";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
    EXPECT_NE(std::string(e.what()).find("'right' is none of"), std::string::npos) << e.what();
  }
}
