// The fleet: what the passed calibrations of one camera model and lens id say about the next
// unit (issue 15, item 4): the outlier test and the fleet prior.
//
// Given n earlier units' intrinsics x_1..x_n (one run per serial) with sample mean m and sample
// covariance S, a new unit x of the same population is an outlier when
//   d^2 = (x - m)^T S^-1 (x - m)  >  (n + 1) / n * p (n - 1) / (n - p) * F^-1(1 - alpha/2; p, n -
//   p),
// the exact prediction bound for a normal population whose mean and covariance are estimated
// from the n units (Hotelling's T^2 of one new observation), or when one parameter's
// standardised deviation z_i = (x_i - m_i) / sqrt(S_ii) exceeds Student's t prediction bound at
// alpha / (2p) (Bonferroni), which flags a single parameter far off sooner than the joint
// test: a normal unit is flagged with probability at most alpha, whatever n. p counts the
// parameters that vary in the fleet. The parameters responsible are those of largest |z_i|
// (docs/math.md, "Fleet outliers").
//
// The fleet prior (fleet_prior) is the same population as a Gaussian prior on the next unit's
// intrinsics: its mean is where a session starts, its covariance the prior term of the bundle
// adjustment (calib/calibration.hpp, IntrinsicsPrior; docs/math.md, "The fleet prior").
#pragma once

#include <string>
#include <utility>
#include <vector>

#include "calib/calibration.hpp"

namespace posecal {

struct FleetUnit {
  std::string run_id, serial;
  std::vector<double> values;  // by FleetStatistics::names
};

struct FleetStatistics {
  std::vector<std::string> names;  // the parameters that vary in the fleet
  int units = 0;
  std::vector<double> mean;
  std::vector<double> covariance;  // row-major, names.size()^2
};

// The statistics of `units` (values ordered as `names`; a parameter constant over the fleet,
// e.g. a fixed one, is dropped). Error(kDegenerate) naming the counts when there are fewer than
// p + 3 units or the covariance is singular.
FleetStatistics fleet_statistics(const std::vector<std::string>& names,
                                 const std::vector<FleetUnit>& units);

struct FleetPosition {
  int units = 0;
  double distance = 0;   // Mahalanobis distance d
  double threshold = 0;  // d above which the unit is flagged
  // |z| of one parameter (deviations) above which the unit is flagged.
  double parameter_threshold = 0;
  double alpha = 0;  // at most the probability that a normal unit is flagged (by either test)
  bool outlier = false;
  // Every parameter with its standardised deviation z, largest |z| first.
  std::vector<std::pair<std::string, double>> deviations;
};

// Where a unit with intrinsics `values` (ordered as `names`, which must hold every name of
// `fleet`) lies in the fleet. `unit_covariance` (row-major over `names`, or empty): the
// uncertainty of `values`, added to the fleet's covariance, so that a unit measured with fewer
// keyframes than the fleet's units is not flagged for its own noise. The fleet's covariance
// already holds its units' measurement noise, so the sum counts that part twice and the
// false-alarm rate is below alpha (the bound is unchanged): conservative, not exact.
FleetPosition fleet_position(const FleetStatistics& fleet, const std::vector<std::string>& names,
                             const std::vector<double>& values, double alpha,
                             const std::vector<double>& unit_covariance = {});

// The fleet position of a calibration. Calibrated with a prior (options.prior), its estimate is
// pulled towards the fleet, which would hide the very defect the test looks for: the keyframes
// are then solved again without the prior (warm-started from `result`), and that estimate is
// tested with its own covariance added (above); *data_only says so. If the keyframes cannot
// determine the intrinsics without the prior, the prior's estimate is tested and *data_only is
// false.
FleetPosition fleet_position_of(const FleetStatistics& fleet, const CalibrationResult& result,
                                const std::vector<Observation>& keyframes,
                                const CalibrationOptions& options, double alpha, bool* data_only);

// The fleet of `units` (values ordered as intrinsic_names(lens)) as a prior for the next unit:
// the mean of every intrinsic, and the sample covariance of those that vary in the fleet
// (fleet_statistics, whose errors it throws), weighed against corners of noise `noise_px`.
IntrinsicsPrior fleet_prior(LensModel lens, const std::vector<FleetUnit>& units, double noise_px);

// The F distribution's quantile: F^-1(q; d1, d2), for 0 < q < 1.
double f_quantile(double q, double d1, double d2);

}  // namespace posecal
