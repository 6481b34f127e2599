// Generic view candidates (EngineOptions::view_candidates): many random whole-board views scored
// by the covariance of the intrinsics they would leave, screened cheaply so that a few hundred of
// them cost well under a millisecond; only a shortlist is predicted exactly.
// docs/pose-selection.md, "Generic view candidates".
#pragma once

#include <cstdint>
#include <vector>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "lens/camera_model.hpp"
#include "select/pose_rules.hpp"
#include "board/board.hpp"
#include "board/views.hpp"

namespace posecal {

// Predicted covariance of the free intrinsics after one more view: (information + frame_info)^-1,
// with Sigma_p = I as in frame_information(); its diagonal and, if a projection Gram matrix G is
// given, trace(G Sigma), the expected squared projection error (projection_gram()).
struct CovariancePrediction {
  double projection = 0;     // 0 without a Gram matrix
  // Of the free intrinsics, in their order (no heap allocation: one per screened view).
  Eigen::Matrix<double, Eigen::Dynamic, 1, 0, kMaxIntrinsics, 1> variance;
};
CovariancePrediction predict_covariance(const Eigen::MatrixXd& information, const Eigen::MatrixXd& gram,
                                        const Eigen::MatrixXd& frame_info);

struct ViewCandidateOptions {
  int count = 300;        // views used at most
  double margin_px = 0;   // border margin of the visibility checks
  int shortlist = 16;     // views predicted exactly per shortlist() call
};

// A candidate view: the board's pose in the camera frame, its rotation as a matrix.
struct ViewPose {
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  Eigen::Vector3d t = Eigen::Vector3d::Zero();
};

class ViewCandidates {
 public:
  // Takes up to options.count of `views` (drawn earlier, e.g. with ViewSampler under an earlier
  // estimate) whose outline is in view under `estimate` (board_outline_in_view) and screens each
  // on corner_quadrature()'s 3x3 points. `information` and `gram` as for predict_covariance();
  // `fixed` selects the free intrinsics. Throws Error(kInvalidArgument) for inconsistent sizes.
  ViewCandidates(const CameraModel& estimate, const Board& board, const std::vector<bool>& fixed,
                 const Eigen::MatrixXd& information, const Eigen::MatrixXd& gram, const std::vector<ViewPose>& views,
                 const ViewCandidateOptions& options);

  // Number of views in view and screened.
  size_t size() const { return views_.size(); }

  struct Exact {
    const TargetPose* target = nullptr;
    CovariancePrediction prediction;
  };
  // The shortlist: the options.shortlist best views by screened projection error (rank_by < 0)
  // or by the screened variance of the free intrinsic at position rank_by, together with (if
  // also_by >= 0) the best by the screened variance of the free intrinsic at also_by; each
  // checked densely (board_fully_visible) and predicted exactly on every corner, once (cached
  // across calls). Views that fail the dense check are left out.
  std::vector<Exact> shortlist(int rank_by, int also_by = -1);

 private:
  struct View {
    Eigen::Matrix3d R;
    Eigen::Vector3d t;
    TargetPose target;  // filled when shortlisted
    CovariancePrediction screened;
    bool exact_done = false;
    bool visible = false;
    CovariancePrediction exact;
  };
  std::vector<size_t> best(int rank_by) const;
  CovariancePrediction predict(const Eigen::Matrix3d& R, const Eigen::Vector3d& t, const std::vector<cv::Point3d>& points,
                               const std::vector<double>* weights) const;
  // predict() for a lens model with N intrinsics.
  template <int N>
  CovariancePrediction predict_fixed(const Eigen::Matrix3d& R, const Eigen::Vector3d& t,
                                     const std::vector<cv::Point3d>& points, const std::vector<double>* weights) const;

  CameraModel estimate_;
  Board board_;
  std::vector<bool> fixed_;
  std::vector<int> free_;  // indices of the free intrinsics
  Eigen::MatrixXd information_, gram_;
  ViewCandidateOptions options_;
  std::vector<View> views_;
};

}  // namespace posecal
