#include "records/fleet.hpp"

#include <Eigen/Cholesky>
#include <Eigen/Core>
#include <algorithm>
#include <cmath>
#include <limits>

#include "common/error.hpp"

namespace posecal {

namespace {

// The continued fraction of the incomplete beta function (modified Lentz's method).
double beta_fraction(double a, double b, double x) {
  constexpr double kTiny = 1e-300, kEps = 1e-15;
  double c = 1, d = 1 - (a + b) * x / (a + 1);
  if (std::abs(d) < kTiny) d = kTiny;
  d = 1 / d;
  double f = d;
  for (int m = 1; m <= 500; ++m) {
    // The even step, then the odd step.
    const double even = m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m));
    d = 1 + even * d;
    c = 1 + even / c;
    if (std::abs(d) < kTiny) d = kTiny;
    if (std::abs(c) < kTiny) c = kTiny;
    d = 1 / d;
    f *= d * c;
    const double odd = -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1));
    d = 1 + odd * d;
    c = 1 + odd / c;
    if (std::abs(d) < kTiny) d = kTiny;
    if (std::abs(c) < kTiny) c = kTiny;
    d = 1 / d;
    const double step = d * c;
    f *= step;
    if (std::abs(step - 1) < kEps) break;
  }
  return f;
}

// The regularised incomplete beta function I_x(a, b).
double incomplete_beta(double a, double b, double x) {
  if (x <= 0) return 0;
  if (x >= 1) return 1;
  const double front = std::exp(std::lgamma(a + b) - std::lgamma(a) - std::lgamma(b) +
                                a * std::log(x) + b * std::log1p(-x));
  // The fraction converges fast on this side of the mean; the symmetry covers the other.
  if (x < (a + 1) / (a + b + 2)) return front * beta_fraction(a, b, x) / a;
  return 1 - front * beta_fraction(b, a, 1 - x) / b;
}

double f_cdf(double f, double d1, double d2) {
  return f <= 0 ? 0 : incomplete_beta(d1 / 2, d2 / 2, d1 * f / (d1 * f + d2));
}

}  // namespace

double f_quantile(double q, double d1, double d2) {
  if (!(q > 0 && q < 1) || !(d1 > 0) || !(d2 > 0)) {
    throw Error(ErrorCode::kInvalidArgument, "F quantile: q must lie in (0, 1) and d1, d2 > 0");
  }
  double lo = 0, hi = 1;
  while (f_cdf(hi, d1, d2) < q) hi *= 2;
  for (int i = 0; i < 200 && hi - lo > 1e-12 * hi; ++i) {
    const double mid = 0.5 * (lo + hi);
    (f_cdf(mid, d1, d2) < q ? lo : hi) = mid;
  }
  return 0.5 * (lo + hi);
}

FleetStatistics fleet_statistics(const std::vector<std::string>& names,
                                 const std::vector<FleetUnit>& units) {
  const size_t n = units.size(), all = names.size();
  for (const FleetUnit& u : units) {
    if (u.values.size() != all)
      throw Error(ErrorCode::kInvalidArgument, "fleet: unit " + u.run_id + " has other parameters");
  }
  std::vector<double> mean(all, 0.0);
  for (const FleetUnit& u : units)
    for (size_t i = 0; i < all; ++i) mean[i] += u.values[i] / static_cast<double>(n);
  // Parameters constant over the fleet (fixed ones) carry no information: dropped.
  std::vector<size_t> varying;
  for (size_t i = 0; i < all; ++i) {
    bool varies = false;
    for (const FleetUnit& u : units) varies = varies || u.values[i] != units[0].values[i];
    if (varies) varying.push_back(i);
  }
  // With fewer than two units nothing can be seen to vary: every parameter counts.
  const size_t p = n >= 2 ? varying.size() : all;
  if (n < p + 3) {
    throw Error(ErrorCode::kDegenerate,
                "fleet: " + std::to_string(n) + " units for " + std::to_string(p) +
                    " parameters; the outlier test needs at least " + std::to_string(p + 3));
  }
  FleetStatistics f;
  f.units = static_cast<int>(n);
  f.covariance.assign(p * p, 0.0);
  for (size_t a = 0; a < p; ++a) {
    f.names.push_back(names[varying[a]]);
    f.mean.push_back(mean[varying[a]]);
  }
  for (const FleetUnit& u : units) {
    for (size_t a = 0; a < p; ++a) {
      for (size_t b = 0; b < p; ++b) {
        f.covariance[a * p + b] += (u.values[varying[a]] - mean[varying[a]]) *
                                   (u.values[varying[b]] - mean[varying[b]]) /
                                   static_cast<double>(n - 1);
      }
    }
  }
  Eigen::Map<const Eigen::MatrixXd> s(f.covariance.data(), static_cast<Eigen::Index>(p),
                                      static_cast<Eigen::Index>(p));
  if (Eigen::LLT<Eigen::MatrixXd>(s).info() != Eigen::Success) {
    throw Error(ErrorCode::kDegenerate, "fleet: the units' covariance is singular");
  }
  return f;
}

FleetPosition fleet_position(const FleetStatistics& fleet, const std::vector<std::string>& names,
                             const std::vector<double>& values, double alpha,
                             const std::vector<double>& unit_covariance) {
  if (!(alpha > 0 && alpha < 1))
    throw Error(ErrorCode::kInvalidArgument, "fleet: the outlier probability must lie in (0, 1)");
  const auto p = static_cast<Eigen::Index>(fleet.names.size());
  Eigen::VectorXd dx(p);
  for (Eigen::Index a = 0; a < p; ++a) {
    const auto it = std::find(names.begin(), names.end(), fleet.names[static_cast<size_t>(a)]);
    if (it == names.end() || values.size() != names.size()) {
      throw Error(ErrorCode::kInvalidArgument,
                  "fleet: the unit has no parameter " + fleet.names[static_cast<size_t>(a)]);
    }
    dx[a] = values[static_cast<size_t>(it - names.begin())] - fleet.mean[static_cast<size_t>(a)];
  }
  std::vector<Eigen::Index> at(static_cast<size_t>(p));  // position in `names`
  for (Eigen::Index a = 0; a < p; ++a)
    at[static_cast<size_t>(a)] =
        std::find(names.begin(), names.end(), fleet.names[static_cast<size_t>(a)]) - names.begin();
  Eigen::MatrixXd s = Eigen::Map<const Eigen::MatrixXd>(fleet.covariance.data(), p, p);
  if (!unit_covariance.empty()) {
    const auto n_all = static_cast<Eigen::Index>(names.size());
    if (static_cast<Eigen::Index>(unit_covariance.size()) != n_all * n_all)
      throw Error(ErrorCode::kInvalidArgument,
                  "fleet: the unit's covariance does not fit its parameters");
    for (Eigen::Index a = 0; a < p; ++a)
      for (Eigen::Index b = 0; b < p; ++b)
        s(a, b) += unit_covariance[static_cast<size_t>(at[static_cast<size_t>(a)] * n_all +
                                                       at[static_cast<size_t>(b)])];
  }
  // Two tests, alpha / 2 each, so that a normal unit is flagged with probability at most alpha
  // (the union bound): the joint one (Hotelling's T^2 prediction bound), which sees a unit off
  // in several parameters at once, and one per parameter (Student's t prediction bound with
  // n - 1 degrees of freedom, Bonferroni over the p parameters), which sees a single parameter
  // far off sooner: 4.8 standard deviations instead of the joint test's 8.5 for 30 units and
  // nine parameters at alpha 0.001 (docs/math.md, "Fleet outliers").
  const double d2 = dx.dot(Eigen::LLT<Eigen::MatrixXd>(s).solve(dx));
  const double n = fleet.units, dp = static_cast<double>(p);
  const double half = alpha / 2;
  const double bound = (n + 1) / n * dp * (n - 1) / (n - dp) * f_quantile(1 - half, dp, n - dp);
  // t^2 with n - 1 degrees of freedom is F(1, n - 1); two-sided at half / p.
  const double z_bound = std::sqrt((n + 1) / n * f_quantile(1 - half / dp, 1, n - 1));
  FleetPosition out;
  out.units = fleet.units;
  out.distance = std::sqrt(std::max(0.0, d2));
  out.threshold = std::sqrt(bound);
  out.parameter_threshold = z_bound;
  out.alpha = alpha;
  out.outlier = !(d2 <= bound);  // a NaN is flagged, never passed
  for (Eigen::Index a = 0; a < p; ++a) {
    const double z = dx[a] / std::sqrt(s(a, a));
    out.deviations.emplace_back(fleet.names[static_cast<size_t>(a)], z);
    if (!(std::abs(z) <= z_bound)) out.outlier = true;
  }
  std::stable_sort(out.deviations.begin(), out.deviations.end(), [](const auto& x, const auto& y) {
    return std::abs(x.second) > std::abs(y.second);
  });
  return out;
}

FleetPosition fleet_position_of(const FleetStatistics& fleet, const CalibrationResult& result,
                                const std::vector<Observation>& keyframes,
                                const CalibrationOptions& options, double alpha, bool* data_only) {
  const std::vector<std::string>& names = result.model.param_names();
  *data_only = false;
  if (options.prior) {
    CalibrationOptions plain = options;
    plain.prior.reset();
    const WarmStart ws{result.model, result.poses};
    try {
      const CalibrationResult d = calibrate(keyframes, result.model.size(), plain, &ws);
      const auto n = static_cast<Eigen::Index>(names.size());
      const Eigen::MatrixXd c = d.covariance_scaled().topLeftCorner(n, n);
      std::vector<double> cov(static_cast<size_t>(n * n));
      for (Eigen::Index a = 0; a < n; ++a)
        for (Eigen::Index b = 0; b < n; ++b) cov[static_cast<size_t>(a * n + b)] = c(a, b);
      *data_only = true;
      return fleet_position(fleet, names, d.model.params(), alpha, cov);
    } catch (const Error&) {
      // The keyframes alone do not determine the intrinsics: test the estimate with the prior.
    }
  }
  return fleet_position(fleet, names, result.model.params(), alpha);
}

IntrinsicsPrior fleet_prior(LensModel lens, const std::vector<FleetUnit>& units, double noise_px) {
  const std::vector<std::string>& names = intrinsic_names(lens);
  const FleetStatistics f = fleet_statistics(names, units);
  IntrinsicsPrior prior;
  prior.mean.assign(names.size(), 0.0);
  for (const FleetUnit& u : units)
    for (size_t i = 0; i < names.size(); ++i)
      prior.mean[i] += u.values[i] / static_cast<double>(units.size());
  prior.names = f.names;
  const auto p = static_cast<Eigen::Index>(f.names.size());
  prior.covariance = Eigen::Map<const Eigen::MatrixXd>(f.covariance.data(), p, p);
  prior.noise_px = noise_px;
  return prior;
}

}  // namespace posecal
