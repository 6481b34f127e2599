// The corner detector's systematic error against tilt and blur, on both renderers
// (docs/benchmarks.md, "The corner detector's bias").
//
//   build/bin/detector_bias [--tilts 0,20,40,55,65] [--blurs 0.5,0.8,1.5] [--noise 2] [--draws 6]
//                           [--board charuco:9x6:0.028:0.0182:DICT_4X4_50 | chessboard:9x6:0.028]
//                           [--camera c525|wide|...] [--seed N] [--off-axis 0,30,45]
//
// Per (renderer, blur, off-axis angle, tilt): 4 poses of the board (default: the default ChArUco
// board; about half the C525's width, tilt about 4 different in-plane axes) near the optical
// axis, or with --off-axis A > 0 8 poses with the board's centre A degrees off the axis at 8
// azimuths (tilted about the azimuth's tangent), each rendered `draws` times with independent
// noise. The camera is a family of bench_pose_selection (camera_families.hpp), with --seed N > 0
// the one that benchmark samples for seed N. Per corner detected in every draw: its bias is the
// mean error against the true projection over the draws, its noise the spread about that mean.
// Printed: corners, RMS, median and largest bias, RMS noise. A bias well above the noise is what a
// covariance (which assumes independent noise) cannot predict; a largest bias far above the median
// is a corner pulled off.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <sstream>
#include <string>
#include <vector>

#include "board/views.hpp"
#include "camera_families.hpp"
#include "lens/reference_models.hpp"
#include "sim/operator.hpp"
#include "sim/synthetic.hpp"

using namespace posecal;

namespace {

std::vector<double> numbers(const std::string& text) {
  std::vector<double> out;
  std::stringstream ss(text);
  std::string item;
  while (std::getline(ss, item, ',')) out.push_back(std::stod(item));
  return out;
}

struct BiasFigures {
  int corners = 0;
  double bias_rms = 0, noise_rms = 0;
  double bias_median = 0, bias_max = 0;  // per-corner |bias|: a few wrong corners show as max >> median
};

BiasFigures measure(const CameraModel& cam, const Board& board, Renderer renderer, double blur,
                    double off_axis_deg, double tilt_deg, double noise, int draws) {
  double bias_ss = 0, noise_ss = 0;
  std::vector<double> bias_norms;
  BiasFigures f;
  const int poses = off_axis_deg > 0 ? 8 : 4;
  for (int pose = 0; pose < poses; ++pose) {
    RenderOptions ro;
    ro.renderer = renderer;
    ro.noise_sigma = noise;
    ro.blur_sigma_px = blur;
    ro.seed = 100 + pose;
    SyntheticCamera sc(cam, board, ro);
    const double azimuth = pose * M_PI / 4, off = std::tan(off_axis_deg * M_PI / 180) * 0.45;
    const Pose p =
        off_axis_deg > 0
            ? board_pose_at(board,
                            Eigen::Vector3d(off * std::cos(azimuth), off * std::sin(azimuth), 0.45),
                            azimuth + M_PI / 2, tilt_deg * M_PI / 180, 0.1)
            : board_pose_at(board, Eigen::Vector3d(0.02 * (pose - 1.5), 0.01 * (pose % 2), 0.45),
                            pose * 0.8, tilt_deg * M_PI / 180, 0.1 * pose);
    const std::vector<cv::Point2d> truth = sc.true_corners(p);
    std::map<int, cv::Point2d> sum;
    std::map<int, double> sq;
    std::map<int, int> seen;
    for (int k = 0; k < draws; ++k) {
      const Detection d = board.detect(sc.render(p));
      for (size_t i = 0; i < d.size(); ++i) {
        const cv::Point2d e = d.image_points[i] - truth[d.ids[i]];
        sum[d.ids[i]] += e;
        sq[d.ids[i]] += e.dot(e);
        ++seen[d.ids[i]];
      }
    }
    for (const auto& [id, s] : sum) {
      if (seen[id] < draws) continue;  // seen in every draw only
      const cv::Point2d m = s / draws;
      bias_ss += m.dot(m);
      bias_norms.push_back(std::sqrt(m.dot(m)));
      noise_ss += std::max(0.0, sq[id] / draws - m.dot(m));
      ++f.corners;
    }
  }
  if (f.corners > 0) {
    f.bias_rms = std::sqrt(bias_ss / f.corners);
    f.noise_rms = std::sqrt(noise_ss / f.corners);
    std::sort(bias_norms.begin(), bias_norms.end());
    f.bias_median = bias_norms[bias_norms.size() / 2];
    f.bias_max = bias_norms.back();
  }
  return f;
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<double> tilts = {0, 20, 40, 55, 65}, blurs = {0.5, 0.8, 1.5}, off_axis = {0};
  double noise = 2;
  int draws = 6, seed = 0;
  std::string camera = "c525";
  BoardSpec spec;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (i + 1 >= argc) {
      std::fprintf(stderr, "%s needs a value\n", a.c_str());
      return 1;
    }
    const std::string v = argv[++i];
    if (a == "--tilts") tilts = numbers(v);
    else if (a == "--blurs") blurs = numbers(v);
    else if (a == "--noise") noise = std::stod(v);
    else if (a == "--draws") draws = std::max(2, std::stoi(v));
    else if (a == "--camera")
      camera = v;
    else if (a == "--seed")
      seed = std::stoi(v);
    else if (a == "--off-axis")
      off_axis = numbers(v);
    else if (a == "--board")
      spec = BoardSpec::parse(v);
    else {
      std::fprintf(stderr, "unknown option %s\n", a.c_str());
      return 1;
    }
  }
  const Board board(spec);
  const CameraModel reference = reference_camera(camera);
  const CameraModel cam =
      seed > 0 ? sample_camera(reference, 0.1, static_cast<uint64_t>(seed)) : reference;
  std::printf(
      "| renderer | blur [px] | off-axis [deg] | tilt [deg] | corners | bias RMS [px] | bias "
      "median [px] | bias max [px] | noise RMS [px] |\n"
      "|---|---|---|---|---|---|---|---|---|\n");
  for (const Renderer r : {Renderer::kRayCast, Renderer::kWarp})
    for (const double blur : blurs)
      for (const double off : off_axis)
        for (const double tilt : tilts) {
          const BiasFigures f = measure(cam, board, r, blur, off, tilt, noise, draws);
          std::printf("| %s | %.1f | %.0f | %.0f | %d | %.4f | %.4f | %.4f | %.4f |\n",
                      r == Renderer::kWarp ? "warp" : "raycast", blur, off, tilt, f.corners,
                      f.bias_rms, f.bias_median, f.bias_max, f.noise_rms);
          std::fflush(stdout);
        }
  return 0;
}
