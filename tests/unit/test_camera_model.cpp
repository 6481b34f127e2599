#include <gtest/gtest.h>

#include <Eigen/LU>
#include <algorithm>
#include <cstdio>
#include <fstream>
#include <opencv2/calib3d.hpp>
#include <random>

#include "common/error.hpp"
#include "io/model_file.hpp"
#include "lens/camera_model.hpp"
#include "lens/reference_models.hpp"

using namespace posecal;

namespace {

const std::string kData = std::string(POSECAL_SOURCE_DIR) + "/data/";

// One strongly distorted sample of each lens model of the table (lens_models.hpp): the
// projection, derivative, unprojection, distortion-map and file tests below run on each, and
// EveryLensModelHasASample fails until a new model adds its sample here.
std::vector<CameraModel> sample_models() {
  // A wide-angle rational lens in the form OpenCV's calibrations take (numerator and denominator
  // both large, barrel overall), then with thin prism and a tilted sensor (tau about 0.5 degrees).
  const std::vector<double> rational{0.8, -0.1, 0.001, -0.002, 0.02, 1.1, 0.05, 0.01};
  const std::vector<double> prism{0.002, -0.001, 0.0015, 0.0005};
  const std::vector<double> tilt{0.009, -0.007};
  auto model = [](LensModel lens, std::vector<std::vector<double>> parts) {
    std::vector<double> p{1000, 1010, 650, 350};
    for (const auto& part : parts) p.insert(p.end(), part.begin(), part.end());
    return CameraModel(1280, 720, lens, p);
  };
  return {
      CameraModel::opencv5(1280, 720, 1000, 1010, 650, 350, {-0.25, 0.12, 0.001, -0.002, -0.02}),
      model(LensModel::kOpenCV8, {rational}), model(LensModel::kOpenCV12, {rational, prism}),
      model(LensModel::kOpenCV14, {rational, prism, tilt}),
      // A fisheye whose image corners see 103 degrees from the axis.
      CameraModel(1280, 720, LensModel::kFisheye,
                  {405, 400, 642, 358, 0.02, -0.006, 0.001, -0.0002})};
}

bool is_fisheye(const CameraModel& m) { return m.lens_model() == LensModel::kFisheye; }

// OpenCV's own projection of the model: cv::fisheye's for the fisheye, else cv::projectPoints.
std::vector<cv::Point2d> opencv_project(const CameraModel& m, const std::vector<cv::Point3d>& pts) {
  std::vector<cv::Point2d> out;
  const cv::Vec3d zero(0, 0, 0);
  if (is_fisheye(m)) {
    cv::fisheye::projectPoints(pts, out, zero, zero, cv::Mat(m.camera_matrix()),
                               m.distortion_coefficients());
  } else {
    cv::projectPoints(pts, zero, zero, cv::Mat(m.camera_matrix()), m.distortion_coefficients(),
                      out);
  }
  return out;
}

// OpenCV's own unprojection to the plane Z = 1, iterated to convergence.
std::vector<cv::Point2d> opencv_undistort(const CameraModel& m,
                                          const std::vector<cv::Point2d>& px) {
  std::vector<cv::Point2d> out;
  const cv::TermCriteria done(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 200, 1e-14);
  if (is_fisheye(m)) {
    cv::fisheye::undistortPoints(px, out, cv::Mat(m.camera_matrix()), m.distortion_coefficients(),
                                 cv::noArray(), cv::noArray(), done);
  } else {
    cv::undistortPoints(px, out, cv::Mat(m.camera_matrix()), m.distortion_coefficients(),
                        cv::noArray(), cv::noArray(), done);
  }
  return out;
}

CameraModel strong_model() { return sample_models().front(); }

}  // namespace

TEST(CameraModel, EveryLensModelHasASample) {
  std::vector<LensModel> sampled;
  for (const CameraModel& m : sample_models()) sampled.push_back(m.lens_model());
  for (LensModel model : lens_models()) {
    EXPECT_NE(std::find(sampled.begin(), sampled.end(), model), sampled.end())
        << lens_model_name(model) << " has no sample in sample_models()";
  }
}

TEST(CameraModel, ProjectionMatchesOpenCV) {
  std::vector<CameraModel> models = sample_models();
  models.push_back(c525_reference_model());
  for (const CameraModel& m : models) {
    SCOPED_TRACE(lens_model_name(m.lens_model()));
    std::mt19937_64 rng(3);
    std::uniform_real_distribution<double> U(-0.5, 0.5);
    std::vector<cv::Point3d> pts;
    for (int i = 0; i < 200; ++i) pts.emplace_back(U(rng), U(rng) * 0.6, 1.0 + U(rng));
    const std::vector<cv::Point2d> ref = opencv_project(m, pts);
    for (size_t i = 0; i < pts.size(); ++i) {
      Eigen::Vector2d uv;
      ASSERT_TRUE(m.project(Eigen::Vector3d(pts[i].x, pts[i].y, pts[i].z), &uv));
      EXPECT_NEAR(uv.x(), ref[i].x, 1e-9);
      EXPECT_NEAR(uv.y(), ref[i].y, 1e-9);
    }
  }
}

namespace {

void expect_jacobians_match_finite_differences(const CameraModel& m) {
  const Eigen::Vector3d p(0.21, -0.13, 0.9);
  Eigen::Vector2d uv;
  Eigen::Matrix<double, 2, 3> Jp;
  Eigen::Matrix<double, 2, Eigen::Dynamic> Jc;
  ASSERT_TRUE(m.project(p, &uv, &Jp, &Jc));
  ASSERT_EQ(Jc.cols(), m.num_params());
  const double h = 1e-6;
  for (int k = 0; k < 3; ++k) {
    Eigen::Vector3d a = p, b = p;
    a[k] += h;
    b[k] -= h;
    Eigen::Vector2d ua, ub;
    m.project(a, &ua);
    m.project(b, &ub);
    const Eigen::Vector2d fd = (ua - ub) / (2 * h);
    EXPECT_NEAR(fd.x(), Jp(0, k), 1e-5 * (1 + std::abs(fd.x())));
    EXPECT_NEAR(fd.y(), Jp(1, k), 1e-5 * (1 + std::abs(fd.y())));
  }
  for (int k = 0; k < m.num_params(); ++k) {
    CameraModel a = m, b = m;
    a.params()[k] += h;
    b.params()[k] -= h;
    Eigen::Vector2d ua, ub;
    a.project(p, &ua);
    b.project(p, &ub);
    const Eigen::Vector2d fd = (ua - ub) / (2 * h);
    EXPECT_NEAR(fd.x(), Jc(0, k), 1e-5 * (1 + std::abs(fd.x())));
    EXPECT_NEAR(fd.y(), Jc(1, k), 1e-5 * (1 + std::abs(fd.y())));
  }
}

}  // namespace

TEST(CameraModel, JacobiansMatchFiniteDifferences) {
  for (const CameraModel& m : sample_models()) {
    SCOPED_TRACE(lens_model_name(m.lens_model()));
    expect_jacobians_match_finite_differences(m);
  }
}

// The hand-written derivatives every model supplies (M::project_jacobians, used by the
// information maths of pose selection) against central differences of the projection, at points
// all over the image.
TEST(CameraModel, ModelDerivativesMatchFiniteDifferences) {
  for (const CameraModel& m : sample_models()) {
    SCOPED_TRACE(lens_model_name(m.lens_model()));
    const int n = m.num_params();
    std::vector<Eigen::Vector3d> points{
        Eigen::Vector3d(0.21, -0.13, 0.9), Eigen::Vector3d(-0.55, 0.3, 1.0),
        Eigen::Vector3d(0.6, 0.33, 0.95), Eigen::Vector3d(0.0, 0.0, 2.0)};
    if (is_fisheye(m)) {
      // Beyond 90 degrees from the axis, at 90, and within the series near the axis.
      points.emplace_back(0.9, 0.2, -0.15);
      points.emplace_back(-0.3, 0.7, 0.0);
      points.emplace_back(1e-10, -2e-10, 1.5);
    }
    for (const Eigen::Vector3d& p : points) {
      double u, v;
      Eigen::Matrix<double, 2, 3> Jc;
      Eigen::Matrix<double, 2, Eigen::Dynamic> Ji(2, n);
      with_lens_model(m.lens_model(), [&](auto lm) {
        decltype(lm)::project_jacobians(m.params().data(), p, &u, &v, &Jc, Ji.data());
      });
      Eigen::Vector2d uv;
      ASSERT_TRUE(m.project(p, &uv));
      EXPECT_NEAR(u, uv.x(), 1e-9);
      EXPECT_NEAR(v, uv.y(), 1e-9);
      const double h = 1e-6;
      for (int k = 0; k < 3; ++k) {
        Eigen::Vector3d a = p, b = p;
        a[k] += h, b[k] -= h;
        Eigen::Vector2d ua, ub;
        m.project(a, &ua), m.project(b, &ub);
        const Eigen::Vector2d fd = (ua - ub) / (2 * h);
        EXPECT_NEAR(fd.x(), Jc(0, k), 1e-5 * (1 + std::abs(fd.x()))) << "d/dp " << k;
        EXPECT_NEAR(fd.y(), Jc(1, k), 1e-5 * (1 + std::abs(fd.y()))) << "d/dp " << k;
      }
      for (int k = 0; k < n; ++k) {
        CameraModel a = m, b = m;
        a.params()[k] += h, b.params()[k] -= h;
        Eigen::Vector2d ua, ub;
        a.project(p, &ua), b.project(p, &ub);
        const Eigen::Vector2d fd = (ua - ub) / (2 * h);
        EXPECT_NEAR(fd.x(), Ji(0, k), 1e-5 * (1 + std::abs(fd.x()))) << m.param_names()[k];
        EXPECT_NEAR(fd.y(), Ji(1, k), 1e-5 * (1 + std::abs(fd.y()))) << m.param_names()[k];
      }
    }
  }
}

TEST(CameraModel, UnprojectInvertsProjectAndAgreesWithOpenCV) {
  for (const CameraModel& m : sample_models()) {
    SCOPED_TRACE(lens_model_name(m.lens_model()));
    std::vector<cv::Point2d> px;
    for (int v = 0; v < m.height(); v += 37)
      for (int u = 0; u < m.width(); u += 41) px.emplace_back(u, v);
    px.emplace_back(0, 0), px.emplace_back(m.width() - 1, m.height() - 1);
    const std::vector<cv::Point2d> cvn = opencv_undistort(m, px);
    int beyond_90 = 0;
    for (size_t i = 0; i < px.size(); ++i) {
      // The unit ray, over the whole image (a fisheye's corners look more than 90 degrees aside).
      Eigen::Vector3d ray;
      Eigen::Vector2d xn, back;
      ASSERT_TRUE(m.unproject_ray(Eigen::Vector2d(px[i].x, px[i].y), &ray)) << px[i];
      EXPECT_NEAR(ray.norm(), 1.0, 1e-12);
      ASSERT_TRUE(m.project(ray, &back)) << px[i];
      EXPECT_NEAR(back.x(), px[i].x, 1e-7);
      EXPECT_NEAR(back.y(), px[i].y, 1e-7);
      if (ray.z() <= 1e-6) {
        ++beyond_90;
        EXPECT_FALSE(m.unproject(Eigen::Vector2d(px[i].x, px[i].y), &xn)) << px[i];
        continue;
      }
      ASSERT_TRUE(m.unproject(Eigen::Vector2d(px[i].x, px[i].y), &xn)) << px[i];
      EXPECT_NEAR(xn.x(), ray.x() / ray.z(), 1e-9 * (1 + xn.norm()));
      ASSERT_TRUE(m.project(Eigen::Vector3d(xn.x(), xn.y(), 1), &back));
      EXPECT_NEAR(back.x(), px[i].x, 1e-7);
      EXPECT_NEAR(back.y(), px[i].y, 1e-7);
      // OpenCV's projection takes the ray back to the pixel.
      const cv::Point2d cv_back = opencv_project(m, {cv::Point3d(xn.x(), xn.y(), 1)})[0];
      EXPECT_NEAR(cv_back.x, px[i].x, 1e-7);
      EXPECT_NEAR(cv_back.y, px[i].y, 1e-7);
      // cv::fisheye::undistortPoints stops short of the ray as it nears 90 degrees (1.8 degrees
      // off at 89.7): compared below 75 degrees only.
      if (is_fisheye(m) && xn.norm() > std::tan(75 * M_PI / 180)) continue;
      EXPECT_NEAR(xn.x(), cvn[i].x, 1e-6);
      EXPECT_NEAR(xn.y(), cvn[i].y, 1e-6);
    }
    if (is_fisheye(m)) {
      EXPECT_GT(beyond_90, 10);
    }
  }
}

// The fisheye beyond 90 degrees: a 185-degree lens on 1280x1024 sees points behind the camera
// plane; where its polynomial folds (theta_d stops increasing) it projects and unprojects
// nothing.
TEST(CameraModel, FisheyeSeesBeyondNinetyDegreesAndNothingBeyondItsFold) {
  const double f = 512 / (92.5 * M_PI / 180);  // 92.5 degrees at the short side's edge
  const CameraModel wide(1280, 1024, LensModel::kFisheye, {f, f, 639.5, 511.5, 0, 0, 0, 0});
  EXPECT_NEAR(wide.max_ray_angle(), M_PI, 1e-12);
  const double th = 92 * M_PI / 180;
  Eigen::Vector2d uv;
  ASSERT_TRUE(wide.project(Eigen::Vector3d(std::sin(th), 0, std::cos(th)), &uv));
  EXPECT_NEAR(uv.x(), 639.5 + f * th, 1e-9);
  EXPECT_NEAR(uv.y(), 511.5, 1e-9);
  Eigen::Vector3d ray;
  ASSERT_TRUE(wide.unproject_ray(Eigen::Vector2d(639.5, 511.5 - f * th), &ray));
  EXPECT_NEAR(ray.y(), -std::sin(th), 1e-12);
  EXPECT_NEAR(ray.z(), std::cos(th), 1e-12);
  Eigen::Vector2d xn;
  EXPECT_FALSE(wide.unproject(Eigen::Vector2d(639.5, 511.5 - f * th), &xn));
  EXPECT_FALSE(wide.project(Eigen::Vector3d(0, 0, -1), &uv));  // straight behind
  EXPECT_FALSE(wide.project(Eigen::Vector3d(0, 0, 0), &uv));
  // k1 = -0.3: theta_d' = 1 - 0.9 theta^2 vanishes at 1.054 rad.
  const CameraModel folds(1280, 1024, LensModel::kFisheye, {f, f, 639.5, 511.5, -0.3, 0, 0, 0});
  const double fold = 1 / std::sqrt(0.9);
  EXPECT_LE(folds.max_ray_angle(), fold);
  EXPECT_GT(folds.max_ray_angle(), fold - 0.01);
  EXPECT_TRUE(folds.project(Eigen::Vector3d(std::tan(fold - 0.02), 0, 1), &uv));
  EXPECT_FALSE(folds.project(Eigen::Vector3d(std::tan(fold + 0.02), 0, 1), &uv));
  const double rim = fold * (1 - 0.3 * fold * fold);  // the largest theta_d
  EXPECT_TRUE(folds.unproject_ray(Eigen::Vector2d(639.5 + f * rim * 0.99, 511.5), &ray));
  EXPECT_FALSE(folds.unproject_ray(Eigen::Vector2d(639.5 + f * rim * 1.01, 511.5), &ray));
  EXPECT_FALSE(folds.unproject(Eigen::Vector2d(639.5 + f * rim * 1.01, 511.5), &xn));
}

TEST(CameraModel, UnprojectRejectsPixelsWithoutPreimage) {
  // k1 = -0.6 alone folds over at r = 1/sqrt(1.8) = 0.745 (max distorted radius 0.497): pixels
  // beyond that radius have no preimage.
  const CameraModel m =
      CameraModel::opencv5(1000, 1000, 500, 500, 499.5, 499.5, {-0.6, 0, 0, 0, 0});
  Eigen::Vector2d xn;
  EXPECT_TRUE(m.unproject(Eigen::Vector2d(499.5 + 0.4 * 500, 499.5), &xn));
  EXPECT_FALSE(m.unproject(Eigen::Vector2d(499.5 + 0.6 * 500, 499.5), &xn));
  const cv::Mat dm = m.distortion_map(50);
  EXPECT_TRUE(std::isnan(dm.at<float>(0, 0)));  // the corner has no preimage
  EXPECT_FALSE(std::isnan(dm.at<float>(10, 10)));
}

// fold_free_radius() is a bound: inside it the distortion's Jacobian (central differences of
// project()) stays positive definite, in every direction; and unproject() with it gives the
// same results as without it, and the warm-started distortion map the same as unproject() per
// cell wherever that finds a preimage, also for models that fold inside the image.
TEST(CameraModel, FoldFreeRadiusIsABoundAndChangesNoResult) {
  const std::vector<CameraModel> models = {
      c525_reference_model(),
      strong_model(),
      CameraModel::opencv5(1000, 1000, 500, 500, 499.5, 499.5,
                           {-0.6, 0, 0, 0, 0}),  // folds at r 0.745
      CameraModel::opencv5(1280, 720, 600, 600, 640, 360,
                           {0.3, -0.9, 0.02, -0.03, 0.4}),  // folds, tangential
      CameraModel::opencv5(640, 480, 500, 500, 320, 240, {0, 0, 0, 0, 0}),
  };
  for (size_t mi = 0; mi < models.size(); ++mi) {
    const CameraModel& m = models[mi];
    const double r_free = m.fold_free_radius();
    EXPECT_GE(r_free, 0.0);
    // Positive definite Jacobian of the normalised distortion inside r_free.
    auto distort = [&](double x, double y) {
      Eigen::Vector2d uv;
      EXPECT_TRUE(m.project(Eigen::Vector3d(x, y, 1.0), &uv));
      return Eigen::Vector2d((uv.x() - m.cx()) / m.fx(), (uv.y() - m.cy()) / m.fy());
    };
    for (int a = 0; a < 64; ++a) {
      for (double f : {0.2, 0.5, 0.8, 0.99}) {
        const double r = f * std::min(r_free, 3.0), th = 2 * M_PI * a / 64;
        const double x = r * std::cos(th), y = r * std::sin(th), h = 1e-6;
        Eigen::Matrix2d J;
        J.col(0) = (distort(x + h, y) - distort(x - h, y)) / (2 * h);
        J.col(1) = (distort(x, y + h) - distort(x, y - h)) / (2 * h);
        const Eigen::Matrix2d S = 0.5 * (J + J.transpose());
        EXPECT_GT(S.determinant(), 0.0) << "model " << mi << " r " << r;
        EXPECT_GT(S.trace(), 0.0) << "model " << mi << " r " << r;
      }
    }
    // The same unprojections with and without the shortcut, over the whole image.
    int inside = 0, folded = 0;
    for (int v = 0; v < m.height(); v += 23) {
      for (int u = 0; u < m.width(); u += 23) {
        Eigen::Vector2d a, b;
        const bool ok_a = m.unproject(Eigen::Vector2d(u, v), &a);
        const bool ok_b = m.unproject(Eigen::Vector2d(u, v), &b, r_free);
        ASSERT_EQ(ok_a, ok_b) << "model " << mi << " pixel " << u << "," << v;
        if (ok_a) {
          EXPECT_EQ(a, b);
          inside += a.norm() < r_free;
        } else {
          ++folded;
        }
      }
    }
    if (mi == 0) {
      EXPECT_GT(inside, 0);  // the shortcut is taken for the C525
    }
    if (mi == 2) {
      EXPECT_GT(folded, 0);  // and this model has pixels without preimage
    }
    // The warm-started distortion map against unproject() per cell.
    const int step = 20;
    const cv::Mat dm = m.distortion_map(step);
    for (int i = 0; i < dm.rows; ++i) {
      for (int j = 0; j < dm.cols; ++j) {
        Eigen::Vector2d xn;
        const Eigen::Vector2d px(j * step, i * step);
        const bool ok = m.unproject(px, &xn);
        const float d = dm.at<float>(i, j);
        // Where Newton from the pinhole ray fails (near a fold) the warm start may still find
        // the preimage; where it succeeds, the map has the same value.
        if (!ok) continue;
        ASSERT_FALSE(std::isnan(d)) << "model " << mi << " cell " << i << "," << j;
        const double ex = m.fx() * (xn.x() - (px.x() - m.cx()) / m.fx()),
                     ey = m.fy() * (xn.y() - (px.y() - m.cy()) / m.fy());
        EXPECT_NEAR(d, std::sqrt(ex * ex + ey * ey), 1e-3 + 1e-5 * d);
      }
    }
  }
}

TEST(CameraModel, DistortionMap) {
  const CameraModel none = CameraModel::opencv5(640, 480, 500, 500, 320, 240, {0, 0, 0, 0, 0});
  const cv::Mat z = none.distortion_map(10);
  double mx = 0;
  cv::minMaxLoc(z, nullptr, &mx);
  EXPECT_LT(mx, 1e-3);
  const CameraModel m = strong_model();
  const cv::Mat d = m.distortion_map(8);
  EXPECT_EQ(d.cols, (1280 + 7) / 8);
  EXPECT_EQ(d.rows, (720 + 7) / 8);
  // Barrel distortion grows towards the corners.
  EXPECT_GT(d.at<float>(0, 0), 10 * d.at<float>(d.rows / 2, d.cols / 2) + 1.0);
}

TEST(CameraModel, ReadsTheC525ReferenceFile) {
  const CameraModel m = read_camera_model(kData + "c525_reference.yml");
  const CameraModel ref = c525_reference_model();
  EXPECT_EQ(m.width(), 1280);
  EXPECT_EQ(m.height(), 720);
  for (int i = 0; i < 9; ++i) EXPECT_DOUBLE_EQ(m.params()[i], ref.params()[i]);
}

TEST(CameraModel, WriteReadRoundTripYamlAndJson) {
  for (const CameraModel& m : sample_models()) {
    for (const std::string ext : {".yml", ".json"}) {
      const std::string path = testing::TempDir() + "/posecal_model" + ext;
      CalibrationFileExtras extras;
      extras.nr_of_frames = 9;
      extras.avg_reprojection_error = 0.25;
      extras.param_std = std::vector<double>(m.num_params(), 0.5);
      write_camera_model(path, m, extras);
      const CameraModel r = read_camera_model(path);
      ASSERT_EQ(r.lens_model(), m.lens_model()) << ext;
      for (int i = 0; i < m.num_params(); ++i)
        EXPECT_DOUBLE_EQ(r.params()[i], m.params()[i]) << ext;
      cv::FileStorage fs(path, cv::FileStorage::READ);
      EXPECT_EQ(static_cast<int>(fs["nr_of_frames"]), 9);
      EXPECT_DOUBLE_EQ(static_cast<double>(fs["avg_reprojection_error"]), 0.25);
      std::remove(path.c_str());
    }
  }
}

TEST(CameraModel, BadFilesGiveClearErrors) {
  auto expect_error = [](const std::string& path, ErrorCode code, const std::string& needle) {
    try {
      read_camera_model(path);
      FAIL() << "no error for " << path;
    } catch (const Error& e) {
      EXPECT_EQ(e.code(), code) << e.what();
      EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
    }
  };
  expect_error("/nonexistent/model.yml", ErrorCode::kIo, "cannot open");
  const std::string dir = testing::TempDir();
  {
    std::ofstream(dir + "/garbage.yml") << "%YAML:1.0\n---\nfoo: [1, 2\n";
    expect_error(dir + "/garbage.yml", ErrorCode::kInvalidArgument, "garbage.yml");
  }
  {
    std::ofstream(dir + "/missing.yml") << "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\n";
    expect_error(dir + "/missing.yml", ErrorCode::kInvalidArgument, "camera_matrix");
  }
  {
    std::ofstream(dir + "/nan.yml")
        << "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n"
           "   rows: 3\n   cols: 3\n   dt: d\n   data: [ .Nan, 0., 320., 0., 500., 240., 0., 0., "
           "1. ]\n"
           "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: 5\n   dt: d\n"
           "   data: [ 0., 0., 0., 0., 0. ]\n";
    expect_error(dir + "/nan.yml", ErrorCode::kInvalidArgument, "not finite");
  }
  // A coefficient count that names no model, a model name the coefficients contradict, and
  // OpenCV's fisheye calibration read as a pinhole one.
  const std::string head =
      "%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: !!opencv-matrix\n"
      "   rows: 3\n   cols: 3\n   dt: d\n   data: [ 500., 0., 320., 0., 500., 240., 0., 0., 1. ]\n";
  auto dist = [](int n) {
    std::string d =
        "distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: " + std::to_string(n) +
        "\n   dt: d\n   data: [ 0.1";
    for (int i = 1; i < n; ++i) d += ", 0.";
    return d + " ]\n";
  };
  std::ofstream(dir + "/six.yml") << head << dist(6);
  expect_error(dir + "/six.yml", ErrorCode::kInvalidArgument, "4, 5, 8, 12 or 14 entries, got 6");
  std::ofstream(dir + "/named.yml") << head << "distortion_model: opencv8\n" << dist(5);
  expect_error(dir + "/named.yml", ErrorCode::kInvalidArgument,
               "'distortion_model' opencv8 does not match the distortion_coefficients (5 "
               "coefficients: opencv5)");
  std::ofstream(dir + "/unknown.yml") << head << "distortion_model: fisheye9\n" << dist(5);
  expect_error(dir + "/unknown.yml", ErrorCode::kInvalidArgument,
               "'fisheye9' is not one of: opencv5, opencv8");
  // A fisheye file: by name or by OpenCV's sample's fisheye_model: 1, with cv::fisheye's 4
  // coefficients; with another count, or named a pinhole model as well, it is refused.
  std::ofstream(dir + "/fisheye.yml") << head << "fisheye_model: 1\n" << dist(4);
  EXPECT_EQ(read_camera_model(dir + "/fisheye.yml").lens_model(), LensModel::kFisheye);
  std::ofstream(dir + "/fisheye5.yml") << head << "distortion_model: fisheye\n" << dist(5);
  expect_error(dir + "/fisheye5.yml", ErrorCode::kInvalidArgument,
               "a fisheye model has 4 distortion coefficients (k1..k4), got 5");
  std::ofstream(dir + "/fisheye_pinhole.yml")
      << head << "distortion_model: fisheye\nlens_model: opencv5\n"
      << dist(4) << "posecal_file_end: 1\n";
  expect_error(dir + "/fisheye_pinhole.yml", ErrorCode::kInvalidArgument,
               "'lens_model' opencv5 does not match the distortion_coefficients (4 coefficients: "
               "fisheye)");
  std::ofstream(dir + "/fourteen.yml") << head << dist(14);
  EXPECT_EQ(read_camera_model(dir + "/fourteen.yml").lens_model(), LensModel::kOpenCV14);
  EXPECT_THROW(CameraModel(640, 480, LensModel::kOpenCV5, {1, 2, 3}), Error);
}
