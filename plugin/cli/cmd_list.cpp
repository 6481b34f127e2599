// posecal list: the cameras of every backend.
#include <memory>

#include "commands.hpp"

namespace posecal::cli {

namespace {

int run_list(bool json) {
  Context c;
  const Json cams = Json::parse(
      fetch_json([&](char* b, size_t* s) { return posecal_list_cameras(c.get(), b, s); }));
  if (json) {
    std::printf("%s\n", json_text(cams).c_str());
    return kOk;
  }
  if (cams.empty()) std::printf("no cameras found\n");
  for (const auto& d : cams) {
    std::printf("%-50s %s %s (serial %s, %s)\n", d["uri"].get<std::string>().c_str(),
                d["vendor"].get<std::string>().c_str(), d["model"].get<std::string>().c_str(),
                d["serial"].get<std::string>().c_str(), d["transport"].get<std::string>().c_str());
  }
  return kOk;
}

}  // namespace

Command add_list(CLI::App* app) {
  auto json = std::make_shared<bool>(false);
  CLI::App* cmd = app->add_subcommand("list", "list the cameras of every backend");
  add_json_flag(cmd, json.get(), "print the cameras as one JSON array");
  return [json] { return run_list(*json); };
}

}  // namespace posecal::cli
