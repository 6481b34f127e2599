// posecal records list|show|resolve|export|import: the calibration records a session or station
// kept with --records (posecal.h, "Records"), and journals recorded afterwards.
#include <filesystem>
#include <memory>

#include "commands.hpp"

namespace posecal::cli {

namespace {

struct RecordsOptions {
  std::string db, run_id, out_dir, format, journal, station_id, operator_id, lens_id;
  bool json = false;
  CLI::App *list = nullptr, *show = nullptr, *resolve = nullptr, *exporter = nullptr,
           *importer = nullptr;
};

std::string text_or(const Json& j, const char* key, const char* none = "-") {
  return j.contains(key) && j[key].is_string() && !j[key].get<std::string>().empty()
             ? j[key].get<std::string>()
             : none;
}

int run_list(const RecordsOptions& o) {
  const Json runs = Json::parse(
      fetch_json([&](char* b, size_t* s) { return posecal_records_list(o.db.c_str(), b, s); }));
  if (o.json) {
    std::printf("%s\n", json_text(runs).c_str());
    return kOk;
  }
  if (runs.empty()) std::printf("no runs in %s\n", o.db.c_str());
  for (const Json& r : runs) {
    const Json& e = r["expected_error_px"];
    std::printf("%s  %s  %-11s %-4s %2d keyframes  %s  %s (serial %s)  station %s\n",
                r["run_id"].get<std::string>().c_str(), r["started"].get<std::string>().c_str(),
                r["state"].get<std::string>().c_str(), text_or(r, "verdict").c_str(),
                r["keyframes"].get<int>(),
                e.is_number() ? (std::to_string(e.get<double>()).substr(0, 5) + " px").c_str()
                              : "  -     ",
                text_or(r["camera"], "id").c_str(), text_or(r["camera"], "serial").c_str(),
                text_or(r, "station_id").c_str());
  }
  return kOk;
}

Json show_json(const RecordsOptions& o) {
  return Json::parse(fetch_json([&](char* b, size_t* s) {
    return posecal_records_show(o.db.c_str(), o.run_id.c_str(), b, s);
  }));
}

int run_show(const RecordsOptions& o) {
  const Json r = show_json(o);
  if (o.json) {
    std::printf("%s\n", json_text(r).c_str());
    return kOk;
  }
  std::printf("run %s: %s, started %s, finished %s\n", r["run_id"].get<std::string>().c_str(),
              r["state"].get<std::string>().c_str(), r["started"].get<std::string>().c_str(),
              text_or(r, "finished").c_str());
  std::printf("  camera %s (%s %s, serial %s), lens %s, station %s, operator %s\n",
              text_or(r["camera"], "uri").c_str(), text_or(r["camera"], "vendor").c_str(),
              text_or(r["camera"], "model").c_str(), text_or(r["camera"], "serial").c_str(),
              text_or(r, "lens_id").c_str(), text_or(r, "station_id").c_str(),
              text_or(r, "operator_id").c_str());
  std::printf("  posecal %s (ABI %s), %dx%d\n", r["posecal_version"].get<std::string>().c_str(),
              r["abi_version"].get<std::string>().c_str(), r["image_width"].get<int>(),
              r["image_height"].get<int>());
  if (r["verdict"].is_string()) std::printf("  verdict %s\n", r["verdict"].get<std::string>().c_str());
  if (r["expected_error_px"].is_number())
    std::printf("  expected error %.3f px\n", r["expected_error_px"].get<double>());
  for (const Json& k : r["keyframes"]) {
    std::printf("  keyframe %2d  %s  %3d corners  %s -> %s\n", k["index"].get<int>(),
                k["time"].get<std::string>().c_str(), k["corners"].get<int>(),
                k["state_before"].get<std::string>().c_str(),
                k["state_after"].get<std::string>().c_str());
  }
  return kOk;
}

int run_resolve(const RecordsOptions& o) {
  const Json r = Json::parse(fetch_json([&](char* b, size_t* s) {
    return posecal_records_resolve(o.db.c_str(), o.run_id.c_str(), b, s);
  }));
  const bool same = r["identical"].get<bool>();
  if (o.json) {
    std::printf("%s\n", json_text(r).c_str());
  } else {
    std::printf("run %s re-solved from %d keyframes: %s\n", r["run_id"].get<std::string>().c_str(),
                r["keyframes"].get<int>(),
                same ? "identical to the stored calibration, bit for bit"
                     : "DIFFERS from the stored calibration");
    for (const auto& [name, v] : r["recomputed"].items()) {
      const Json stored = r["stored"].is_object() ? r["stored"].value(name, Json()) : Json();
      std::printf("  %-3s %.17g%s\n", name.c_str(), v.get<double>(),
                  stored.is_number() && stored.get<double>() != v.get<double>()
                      ? ("  (stored " + json_text(stored) + ")").c_str()
                      : "");
    }
  }
  return same ? kOk : kFailure;
}

int run_export(const RecordsOptions& o) {
  const Json r = show_json(o);
  std::error_code ec;
  std::filesystem::create_directories(o.out_dir, ec);
  if (ec || !std::filesystem::is_directory(o.out_dir)) {
    throw Failure{POSECAL_E_IO, "cannot create directory '" + o.out_dir + "'" +
                                    (ec ? ": " + ec.message() : std::string())};
  }
  std::string id = text_or(r["camera"], "id", "camera");
  for (char& c : id)
    if (c == '/' || c == '\0') c = '_';
  const std::string model = o.out_dir + "/" + id + result_extensions(o.format).front();
  const std::string record = o.out_dir + "/" + r["run_id"].get<std::string>() + ".json";
  check_output_file(model, result_extensions(o.format));
  check(posecal_records_export(o.db.c_str(), o.run_id.c_str(), model.c_str(), format_arg(o.format)));
  write_text_file(record, json_text(r, 2) + "\n");
  std::printf("written %s\nwritten %s\n", model.c_str(), record.c_str());
  return kOk;
}

int run_import(const RecordsOptions& o) {
  Json options = Json::object();
  if (!o.run_id.empty()) options["run_id"] = o.run_id;
  if (!o.station_id.empty()) options["station_id"] = o.station_id;
  if (!o.operator_id.empty()) options["operator_id"] = o.operator_id;
  if (!o.lens_id.empty()) options["lens_id"] = o.lens_id;
  const std::string text = options.dump();
  const Json r = Json::parse(fetch_json([&](char* b, size_t* s) {
    return posecal_records_import(o.db.c_str(), o.journal.c_str(), text.c_str(), b, s);
  }));
  if (o.json) {
    std::printf("%s\n", json_text(r).c_str());
  } else {
    std::printf("recorded %s as run %s (%d keyframes, %s) in %s\n", o.journal.c_str(),
                r["run_id"].get<std::string>().c_str(), r["keyframes"].get<int>(),
                r["state"].get<std::string>().c_str(), o.db.c_str());
    if (r["journal_note"].is_string())
      std::printf("  journal: %s\n", r["journal_note"].get<std::string>().c_str());
  }
  return kOk;
}

}  // namespace

Command add_records(CLI::App* app) {
  auto o = std::make_shared<RecordsOptions>();
  CLI::App* cmd = app->add_subcommand(
      "records", "the calibration records kept with --records (a station keeps DIR/records.sqlite)");
  cmd->require_subcommand(1);
  auto db = [&](CLI::App* sub) {
    sub->add_option("--db", o->db, "the record store (a SQLite file)")
        ->type_name("PATH")
        ->required()
        ->check(non_empty());
  };
  auto run_id = [&](CLI::App* sub) {
    sub->add_option("run_id", o->run_id, "the run (its id, or a unique prefix of it)")
        ->required()
        ->check(non_empty());
  };
  o->list = cmd->add_subcommand("list", "the runs, newest first");
  db(o->list);
  add_json_flag(o->list, &o->json, "print the runs as one JSON array");
  o->show = cmd->add_subcommand("show", "one run: identity, result, keyframes");
  run_id(o->show);
  db(o->show);
  add_json_flag(o->show, &o->json, "print the run as one JSON object");
  o->resolve = cmd->add_subcommand(
      "resolve", "re-solve a run from its stored detections; exit 2 if it differs from the stored result");
  run_id(o->resolve);
  db(o->resolve);
  add_json_flag(o->resolve, &o->json, "print the comparison as one JSON object");
  o->exporter = cmd->add_subcommand(
      "export", "write a run's calibration (re-solved) and its record as JSON into a directory");
  run_id(o->exporter);
  db(o->exporter);
  o->exporter->add_option("--out-dir", o->out_dir, "where: DIR/<camera id>.<ext>, DIR/<run id>.json")
      ->type_name("DIR")
      ->required()
      ->check(non_empty());
  add_format_option(o->exporter, &o->format);
  o->importer = cmd->add_subcommand(
      "import", "record a session's journal as a run (a run whose store was away when it ran)");
  o->importer->add_option("journal", o->journal, "the journal (--journal, or a station's DIR/journal/)")
      ->required()
      ->check(non_empty());
  db(o->importer);
  o->importer->add_option("--run-id", o->run_id, "the run id (default: a new UUID)");
  o->importer->add_option("--station-id", o->station_id, "recorded with the run");
  o->importer->add_option("--operator-id", o->operator_id, "recorded with the run");
  o->importer->add_option("--lens-id", o->lens_id, "recorded with the run");
  add_json_flag(o->importer, &o->json, "print the new run as one JSON object");
  return [o] {
    if (o->importer->parsed()) return run_import(*o);
    if (o->list->parsed()) return run_list(*o);
    if (o->show->parsed()) return run_show(*o);
    if (o->resolve->parsed()) return run_resolve(*o);
    return run_export(*o);
  };
}

}  // namespace posecal::cli
