// posecal command line. Built on the C ABI only (posecal.h), so every command also exercises
// the interface that factory software uses.
#include <algorithm>
#include <cstdio>
#include <cstring>
#include <functional>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "posecal.h"

namespace {

using Json = nlohmann::json;

struct UsageError {
  std::string message;
};

// Parsed "--key value" / "--flag" arguments after the command name.
class Args {
 public:
  Args(int argc, char** argv, int first, const std::vector<std::string>& flags,
       const std::vector<std::string>& options) {
    for (int i = first; i < argc; ++i) {
      const std::string a = argv[i];
      if (a.rfind("--", 0) != 0) throw UsageError{"unexpected argument '" + a + "'"};
      const std::string key = a.substr(2);
      if (std::find(flags.begin(), flags.end(), key) != flags.end()) {
        flags_[key] = true;
      } else if (std::find(options.begin(), options.end(), key) != options.end()) {
        if (i + 1 >= argc) throw UsageError{"option '" + a + "' needs a value"};
        values_[key] = argv[++i];
      } else {
        throw UsageError{"unknown option '" + a + "'"};
      }
    }
  }
  bool flag(const std::string& k) const { return flags_.count(k) > 0; }
  bool has(const std::string& k) const { return values_.count(k) > 0; }
  std::string get(const std::string& k, const std::string& def = "") const {
    auto it = values_.find(k);
    return it == values_.end() ? def : it->second;
  }
  std::string need(const std::string& k) const {
    if (!has(k)) throw UsageError{"missing --" + k};
    return get(k);
  }
  double number(const std::string& k, double def) const {
    if (!has(k)) return def;
    try {
      size_t used = 0;
      const double v = std::stod(get(k), &used);
      if (used != get(k).size()) throw 0;
      return v;
    } catch (...) {
      throw UsageError{"--" + k + " expects a number, got '" + get(k) + "'"};
    }
  }

 private:
  std::map<std::string, bool> flags_;
  std::map<std::string, std::string> values_;
};

// A failed ABI call: the status and the library's message.
struct Failure {
  posecal_status status;
  std::string message;
};

void check(posecal_status s) {
  if (s != POSECAL_OK) throw Failure{s, posecal_last_error()};
}

// Calls a JSON-returning ABI function with the size-query protocol.
std::string fetch_json(const std::function<posecal_status(char*, size_t*)>& call) {
  size_t size = 0;
  posecal_status s = call(nullptr, &size);
  if (s != POSECAL_E_BUFFER_TOO_SMALL) check(s);
  std::string buf(size, '\0');
  check(call(buf.data(), &size));
  buf.resize(size - 1);
  return buf;
}

struct Context {
  posecal_context* ctx = nullptr;
  Context() { check(posecal_context_create(nullptr, &ctx)); }
  ~Context() { posecal_context_destroy(ctx); }
};

void print_usage() {
  std::fputs(
      "usage: posecal <command> [options]\n"
      "\n"
      "commands:\n"
      "  calibrate --images DIR [--target SPEC] [--out FILE] [--json]\n"
      "            [--fix-principal-point] [--fix-aspect-ratio] [--zero-tangential]\n"
      "      calibrate from a folder of images (name order); FILE is .yml/.yaml/.json\n"
      "  board --out FILE [--target SPEC] [--dpi N] [--margin M]\n"
      "      write the printable target at exact scale (.pdf vector, .png at DPI)\n"
      "  list [--json]\n"
      "      list the cameras of every backend\n"
      "  version\n"
      "\n"
      "SPEC: charuco:COLSxROWS:SQUARE_M:MARKER_M:DICT (default "
      "charuco:9x6:0.028:0.0182:DICT_4X4_50)\n"
      "      chessboard:COLSxROWS:SQUARE_M (inner corners), e.g. chessboard:9x6:0.025\n",
      stderr);
}

int cmd_calibrate(const Args& args) {
  if (!args.has("images")) throw UsageError{"calibrate needs --images DIR (live cameras: not yet)"};
  Context c;
  Json opts = Json::object();
  if (args.flag("fix-principal-point")) opts["fix_principal_point"] = true;
  if (args.flag("fix-aspect-ratio")) opts["fix_aspect_ratio"] = true;
  if (args.flag("zero-tangential")) opts["zero_tangential"] = true;
  const std::string target = args.get("target");
  posecal_calibration* cal = nullptr;
  check(posecal_calibrate_images(c.ctx, args.get("images").c_str(),
                                 target.empty() ? nullptr : target.c_str(), opts.dump().c_str(),
                                 &cal));
  struct Guard {
    posecal_calibration* p;
    ~Guard() { posecal_calibration_destroy(p); }
  } guard{cal};
  if (args.has("out")) check(posecal_calibration_save(cal, args.get("out").c_str()));
  const Json j = Json::parse(
      fetch_json([&](char* b, size_t* s) { return posecal_calibration_json(cal, b, s); }));
  if (args.flag("json")) {
    std::printf("%s\n", j.dump().c_str());
    return 0;
  }
  std::printf("calibrated from %zu image(s), %zu rejected; RMS %.4f px\n", j["used"].size(),
              j["rejected"].size(), j["rms"].is_number() ? j["rms"].get<double>() : -1.0);
  for (const auto& name : j["covariance_order"]) {
    const std::string n = name.get<std::string>();
    std::printf("  %-3s = %14.6f  +- %.6f\n", n.c_str(), j[n].get<double>(),
                j["std"][n].is_number() ? j["std"][n].get<double>() : -1.0);
  }
  for (const auto& r : j["rejected"]) {
    std::printf("  rejected %s: %s\n", r["file"].get<std::string>().c_str(),
                r["reason"].get<std::string>().c_str());
  }
  if (args.has("out")) std::printf("written %s\n", args.get("out").c_str());
  return 0;
}

int cmd_board(const Args& args) {
  const std::string target = args.get("target");
  check(posecal_write_target(target.empty() ? nullptr : target.c_str(), args.need("out").c_str(),
                             args.number("dpi", 300), args.number("margin", 0.01)));
  std::printf("written %s\n", args.get("out").c_str());
  return 0;
}

int cmd_list(const Args& args) {
  Context c;
  const Json cams = Json::parse(
      fetch_json([&](char* b, size_t* s) { return posecal_list_cameras(c.ctx, b, s); }));
  if (args.flag("json")) {
    std::printf("%s\n", cams.dump().c_str());
    return 0;
  }
  if (cams.empty()) std::printf("no cameras found\n");
  for (const auto& d : cams) {
    std::printf("%-50s %s %s (serial %s, %s)\n", d["uri"].get<std::string>().c_str(),
                d["vendor"].get<std::string>().c_str(), d["model"].get<std::string>().c_str(),
                d["serial"].get<std::string>().c_str(), d["transport"].get<std::string>().c_str());
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 2 || !std::strcmp(argv[1], "--help") || !std::strcmp(argv[1], "-h") ||
      !std::strcmp(argv[1], "help")) {
    print_usage();
    return argc < 2 ? 1 : 0;
  }
  if (posecal_abi_version() != POSECAL_ABI_VERSION) {
    std::fprintf(stderr, "posecal: library ABI %u does not match this program's %u\n",
                 posecal_abi_version(), POSECAL_ABI_VERSION);
    return 2;
  }
  const std::string cmd = argv[1];
  try {
    if (cmd == "calibrate") {
      return cmd_calibrate(Args(
          argc, argv, 2, {"json", "fix-principal-point", "fix-aspect-ratio", "zero-tangential"},
          {"images", "target", "out", "camera"}));
    }
    if (cmd == "board")
      return cmd_board(Args(argc, argv, 2, {}, {"out", "target", "dpi", "margin"}));
    if (cmd == "list") return cmd_list(Args(argc, argv, 2, {"json"}, {}));
    if (cmd == "version") {
      std::printf("posecal %s (ABI %u)\n", posecal_version(), posecal_abi_version());
      return 0;
    }
    throw UsageError{"unknown command '" + cmd + "'"};
  } catch (const UsageError& e) {
    std::fprintf(stderr, "posecal %s: %s (see posecal --help)\n", cmd.c_str(), e.message.c_str());
    return 1;
  } catch (const Failure& f) {
    std::fprintf(stderr, "posecal %s: %s [%s]\n", cmd.c_str(), f.message.c_str(),
                 posecal_status_name(f.status));
    return 2;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "posecal %s: %s\n", cmd.c_str(), e.what());
    return 2;
  }
}
