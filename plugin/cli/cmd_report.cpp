// posecal report: the calibration report of a recorded run (RUN_ID --db PATH) or of a result
// file (--result FILE) as self-contained HTML, and a PDF (posecal.h, posecal_records_report).
#include <memory>

#include "commands.hpp"

namespace posecal::cli {

namespace {

struct ReportOptions {
  std::string run_id, db, result, out, pdf;
  bool json = false;
};

int run_report(const ReportOptions& o) {
  if (o.run_id.empty() == o.result.empty()) {
    throw UsageError{"give a run id (with --db) or --result FILE, not both"};
  }
  if (!o.run_id.empty() && o.db.empty()) throw UsageError{"a run id needs --db PATH"};
  if (!o.result.empty() && !o.db.empty()) throw UsageError{"--result FILE takes no --db"};
  check_output_file(o.out, {".html", ".htm"});
  if (!o.pdf.empty()) check_output_file(o.pdf, {".pdf"});
  const Json r = Json::parse(fetch_json([&](char* b, size_t* s) {
    return posecal_records_report(o.run_id.empty() ? nullptr : o.db.c_str(),
                                  o.run_id.empty() ? nullptr : o.run_id.c_str(),
                                  o.result.empty() ? nullptr : o.result.c_str(), o.out.c_str(),
                                  o.pdf.empty() ? nullptr : o.pdf.c_str(), b, s);
  }));
  if (o.json) {
    std::printf("%s\n", json_text(r).c_str());
    return kOk;
  }
  std::string plots;
  for (const Json& p : r["plots"]) plots += (plots.empty() ? "" : ", ") + p.get<std::string>();
  std::printf("written %s (%s)\n", o.out.c_str(), plots.c_str());
  if (r["pdf"].is_string())
    std::printf("written %s (%d pages)\n", o.pdf.c_str(), r["pages"].get<int>());
  for (const Json& n : r["notes"]) std::printf("  note: %s\n", n.get<std::string>().c_str());
  return kOk;
}

}  // namespace

Command add_report(CLI::App* app) {
  auto o = std::make_shared<ReportOptions>();
  CLI::App* cmd = app->add_subcommand(
      "report",
      "the calibration report of a recorded run or a result file: HTML with the figures "
      "embedded (coverage, residuals, distortion, expected error, sigma per keyframe, verdict "
      "and fleet position), and a PDF");
  cmd->add_option("run_id", o->run_id, "the run (its id, or a unique prefix of it)");
  cmd->add_option("--db", o->db, "the record store of the run (a SQLite file)")->type_name("PATH");
  cmd->add_option("--result", o->result,
                  "a calibration result file instead of a run: the distortion and expected-error "
                  "figures only")
      ->type_name("FILE")
      ->check(non_empty());
  cmd->add_option("--out", o->out, "the HTML report (.html), written atomically")
      ->type_name("FILE")
      ->required()
      ->check(non_empty());
  cmd->add_option("--pdf", o->pdf, "also a PDF: a title page and one page per figure")
      ->type_name("FILE")
      ->check(non_empty());
  add_json_flag(cmd, &o->json, "print what was written as one JSON object");
  return [o] { return run_report(*o); };
}

}  // namespace posecal::cli
