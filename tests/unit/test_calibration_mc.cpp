// Monte-Carlo check that the reported covariance is honest (mrcal's
// test-projection-uncertainty.py in spirit): over many seeded repetitions the normalised errors
// (est - true) / sigma must have unit standard deviation.
#include <gtest/gtest.h>

#include "calib/calibration.hpp"
#include "calib/metrics.hpp"
#include "sim/synthetic.hpp"
#include "board/views.hpp"
#include "lens/reference_models.hpp"

using namespace posecal;

TEST(CalibrationMonteCarlo, CovarianceIsHonest) {
  const CameraModel truth = c525_reference_model();
  const Board target;
  constexpr int kReps = 50;
  const int idx[3] = {0, 2, 4};  // fx, cx, k1
  std::vector<double> z[3];
  RenderOptions ro;
  ro.noise_sigma = 2.0;
  ro.blur_sigma_px = 0.8;
  SyntheticCamera sc(truth, target, ro);
  int within3 = 0, total = 0;
  for (int rep = 0; rep < kReps; ++rep) {
    ro.seed = 1000 + rep;
    sc.set_options(ro);
    std::vector<Observation> frames;
    for (const Pose& p : random_board_views(5000 + rep, 20, truth, target)) {
      const Detection d = target.detect(sc.render(p));
      if (d.size() >= 6) frames.push_back(Observation::from(d));
    }
    ASSERT_GE(frames.size(), 18u);
    const CalibrationResult r = calibrate(frames, truth.size());
    for (int k = 0; k < 3; ++k) {
      const int i = idx[k];
      z[k].push_back((r.model.params()[i] - truth.params()[i]) / r.std_scaled[i]);
    }
    for (int i = 0; i < 9; ++i) {
      ++total;
      if (std::abs(r.model.params()[i] - truth.params()[i]) < 3 * r.std_scaled[i]) ++within3;
    }
  }
  const char* names[3] = {"fx", "cx", "k1"};
  for (int k = 0; k < 3; ++k) {
    double mean = 0, var = 0;
    for (double v : z[k]) mean += v;
    mean /= z[k].size();
    for (double v : z[k]) var += (v - mean) * (v - mean);
    const double sd = std::sqrt(var / (z[k].size() - 1));
    std::printf("%s: normalised error mean %+.3f, std %.3f over %d repetitions\n", names[k], mean,
                sd, kReps);
    EXPECT_GE(sd, 0.75) << names[k];
    EXPECT_LE(sd, 1.33) << names[k];
  }
  std::printf("within 3 sigma: %d of %d parameter estimates\n", within3, total);
  EXPECT_GE(within3, total * 97 / 100);
}
