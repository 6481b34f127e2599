// posecal command line. Built on the C ABI only (posecal.h), so every command also exercises
// the interface that factory software uses.
//
// Exit codes: 0 success, 1 usage error, 2 failure, 3 finished but not converged, 130 / 143
// stopped by SIGINT / SIGTERM after saving what was calibrated (plugin/cli/interrupt.hpp).
#include <cstring>
#include <map>

#include "commands.hpp"
#include "interrupt.hpp"

namespace posecal::cli {

std::string version_text() {
  return "posecal " + std::string(posecal_version()) + " (ABI " +
         std::to_string(posecal_abi_version()) + ")";
}

namespace {

std::string footer() {
  return "'posecal <command> --help' lists a command's options.\n\n" + target_spec_help() +
         "\n"
         "URI:  sim://?seed=N&operator=person|robot&model=FILE, images://DIR, external,\n"
         "      aravis://ID, v4l2://STABLE_ID, v4l2:///dev/videoN\n"
         "exit codes: 0 ok, 1 usage, 2 failure, 3 finished but not converged,\n"
         "      130 / 143 interrupted by SIGINT / SIGTERM (what was calibrated is saved)";
}

using Commands = std::map<std::string, Command>;

Commands add_commands(CLI::App* app) {
  Commands commands;
  commands["calibrate"] = add_calibrate(app);
  commands["station"] = add_station(app);
  commands["evaluate"] = add_evaluate(app);
  commands["grab"] = add_grab(app);
  commands["features"] = add_features(app);
  commands["simulate"] = add_simulate(app);
  commands["board"] = add_board(app);
  commands["list"] = add_list(app);
  commands["records"] = add_records(app);
  commands["report"] = add_report(app);
  commands["serve"] = add_serve(app);
  app->add_subcommand("version", "print the version and the ABI version");
  commands["version"] = [] {
    std::printf("%s\n", version_text().c_str());
    return static_cast<int>(kOk);
  };
  return commands;
}

void configure(CLI::App* app) {
  app->description("posecal: camera calibration with efficient pose selection");
  app->set_help_flag("-h,--help", "print this help and exit");
  app->set_version_flag("--version", version_text, "print the version and exit");
  app->require_subcommand(1);
  // An option given twice takes its last value, as with the parser before CLI11 (set before
  // the subcommands are added: they copy these defaults).
  app->option_defaults()->multi_option_policy(CLI::MultiOptionPolicy::TakeLast);
  app->get_formatter()->column_width(36);
}

int usage_error(const std::string& cmd, const std::string& message) {
  std::fprintf(stderr, "posecal%s%s: %s (see posecal --help)\n", cmd.empty() ? "" : " ",
               cmd.c_str(), message.c_str());
  return kUsage;
}

// Runs the parsed command; errors become their message and exit code.
int run_command(const std::string& cmd, const Command& command) {
  if (posecal_abi_version() != POSECAL_ABI_VERSION) {
    std::fprintf(stderr, "posecal: library ABI %u does not match this program's %u\n",
                 posecal_abi_version(), POSECAL_ABI_VERSION);
    return kFailure;
  }
  try {
    return command();
  } catch (const UsageError& e) {
    return usage_error(cmd, e.message);
  } catch (const Failure& f) {
    std::fprintf(stderr, "posecal %s: %s [%s]\n", cmd.c_str(), f.message.c_str(),
                 posecal_status_name(f.status));
    return kFailure;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "posecal %s: %s\n", cmd.c_str(), e.what());
    return kFailure;
  }
}

int run(int argc, char** argv) {
  CLI::App app{"", "posecal"};
  Commands commands;
  try {
    configure(&app);
    commands = add_commands(&app);
  } catch (const CLI::ConstructionError& e) {
    // E.g. a key added to the session-key table whose flag a command already has.
    std::fprintf(stderr, "posecal: the command line cannot be built: %s\n", e.what());
    return kFailure;
  }
  app.footer(footer());  // after the commands: a subcommand would inherit it
  if (argc < 2) {
    std::fputs(app.help().c_str(), stderr);
    return kUsage;
  }
  if (!std::strcmp(argv[1], "help")) {
    std::fputs(app.help().c_str(), stdout);
    return kOk;
  }
  // The command's name for messages ("" for an option before any command).
  const std::string cmd = argv[1][0] == '-' ? "" : argv[1];
  if (!cmd.empty() && !commands.count(cmd)) {
    return usage_error(cmd, "unknown command '" + cmd + "'");
  }
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    // --help and --version are "errors" with exit code 0; CLI11 prints them to stdout.
    if (e.get_exit_code() == static_cast<int>(CLI::ExitCodes::Success)) {
      app.exit(e);
      return kOk;
    }
    return usage_error(cmd, e.what());
  }
  const std::string name = app.get_subcommands().front()->get_name();
  return run_command(name, commands.at(name));
}

}  // namespace

}  // namespace posecal::cli

int main(int argc, char** argv) {
  posecal::cli::install_interrupt_handlers();
  const int code = posecal::cli::run(argc, argv);
  // Output lost to a full disk or a closed pipe is a failure, whatever the command did.
  return posecal::cli::close_stdout() ? code : posecal::cli::kFailure;
}
