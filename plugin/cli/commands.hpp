// The posecal commands, one file each (cmd_<name>.cpp). Each adds its subcommand (with its own
// --help) to the app and returns the function that runs it once the command line is parsed.
#pragma once

#include "cli_common.hpp"

namespace posecal::cli {

Command add_simulate(CLI::App* app);
Command add_calibrate(CLI::App* app);  // --images DIR and --camera URI
Command add_station(CLI::App* app);
Command add_evaluate(CLI::App* app);
Command add_grab(CLI::App* app);
Command add_features(CLI::App* app);
Command add_board(CLI::App* app);
Command add_list(CLI::App* app);
Command add_records(CLI::App* app);  // list, show, resolve, export, import
Command add_report(CLI::App* app);   // the calibration report (HTML, PDF)
Command add_serve(CLI::App* app);    // the station as an HTTP server (station_server.hpp)

// The text of `posecal version` and `posecal --version`.
std::string version_text();

}  // namespace posecal::cli
