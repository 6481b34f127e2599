// posecal board: the printable target at exact scale.
#include <memory>

#include "commands.hpp"

namespace posecal::cli {

namespace {

struct BoardOptions {
  std::string out, target, paper = "board";
  double dpi = 300, margin = 0.01;
};

int run_board(const BoardOptions& o) {
  const Json options{{"paper", o.paper}, {"dpi", o.dpi}, {"margin_m", o.margin}};
  check(posecal_write_target_ex(o.target.empty() ? nullptr : o.target.c_str(), o.out.c_str(),
                                json_text(options).c_str()));
  std::printf("written %s\n", o.out.c_str());
  return kOk;
}

}  // namespace

Command add_board(CLI::App* app) {
  auto o = std::make_shared<BoardOptions>();
  CLI::App* cmd = app->add_subcommand(
      "board",
      "write the printable target at exact scale (.pdf vector with a 100 mm ruler, .png at DPI)");
  cmd->footer(target_spec_help());
  cmd->add_option("--out", o->out, "the file (.pdf or .png)")
      ->type_name("FILE")
      ->required()
      ->check(non_empty());
  cmd->add_option("--target", o->target,
                  "the board, SPEC (below; default: charuco:9x6:0.028:0.0182:DICT_4X4_50)")
      ->type_name("SPEC");
  cmd->add_option("--paper", o->paper,
                  "a PDF on the board's own page (default) or on a4, a3 or letter sheets, tiled "
                  "when the board is larger")
      ->type_name("board|a4|a3|letter")
      ->check(CLI::IsMember({"board", "a4", "a3", "letter"}, CLI::ignore_case));
  cmd->add_option("--dpi", o->dpi, "resolution of a .png (default: 300)");
  cmd->add_option("--margin", o->margin,
                  "white margin around the board, or the sheet's unprinted edge, metres "
                  "(default: 0.01)");
  return [o] { return run_board(*o); };
}

}  // namespace posecal::cli
