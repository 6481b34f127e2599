// libFuzzer target: the quality specification (plugin/src/quality_gate.cpp), then the verdict of
// a fixed result against every specification it accepts. Fails on a crash, a sanitizer report,
// an error that is not Error(kInvalidArgument), or a verdict other than "pass" / "fail".
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <string>

#include "common/error.hpp"
#include "quality_gate.hpp"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static const std::vector<std::string> names = {"fx", "fy", "cx", "cy", "k1",
                                                 "k2", "p1", "p2", "k3"};
  static const nlohmann::json result = {
      {"converged", true}, {"interrupted", false}, {"expected_error_px", 0.21},
      {"eps_res", 0.3},    {"fx", 1000.0},         {"fy", 1001.0},
      {"cx", 640.0},       {"cy", 360.0},          {"k1", 0.05},
      {"k2", nullptr}};  // a parameter without a figure
  const std::string text(reinterpret_cast<const char*>(data), size);
  posecal::abi::QualitySpec spec;
  try {
    spec = posecal::abi::parse_quality_spec(text, "fuzz.json", names);
  } catch (const posecal::Error& e) {
    if (e.code() != posecal::ErrorCode::kInvalidArgument) std::abort();
    return 0;
  }
  const nlohmann::json v = posecal::abi::quality_verdict(spec, result, 7, 12.5);
  const std::string verdict = v.at("verdict").get<std::string>();
  if (verdict != "pass" && verdict != "fail") std::abort();
  if ((verdict == "pass") != v.at("verdict_reasons").empty()) std::abort();
  return 0;
}
