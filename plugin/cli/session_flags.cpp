#include "session_flags.hpp"

#include <algorithm>

namespace posecal::cli {

namespace {

enum class KeyKind { kNumber, kInteger, kOptionalNumber, kBool, kChoice, kText, kTextList };

struct KeyInfo {
  const char* key;
  KeyKind kind;
  double lo, hi;        // Number, Integer, OptionalNumber: inclusive range
  const char* choices;  // Choice: '|'-separated
  const char* default_text;
  const char* alias;  // "" none; "!name": a flag that sets a Bool key to false
  const char* doc;
};

// The library's table of session keys, expanded here rather than linked: the CLI speaks only
// the C ABI, and session_keys.def is a pure X-macro file without includes, so this one file of
// core is safe to read (found through the ${PROJECT_SOURCE_DIR}/core include directory the CLI
// has for common/percent_encoding.hpp). `scope` and `member` are the library's business.
constexpr KeyInfo kKeys[] = {
#define POSECAL_KEY(scope, key, kind, member, lo, hi, choices, def, cli_alias, doc) \
  {#key, KeyKind::k##kind, lo, hi, choices, def, cli_alias, doc},
#include "session/session_keys.def"
#undef POSECAL_KEY
};

std::string flag_name(const std::string& key) {
  std::string name = key;
  std::replace(name.begin(), name.end(), '_', '-');
  return "--" + name;
}

std::vector<std::string> split_choices(const std::string& text) {
  std::vector<std::string> out;
  size_t start = 0;
  while (start <= text.size()) {
    const size_t bar = std::min(text.find('|', start), text.size());
    out.push_back(text.substr(start, bar - start));
    start = bar + 1;
  }
  return out;
}

// A comma-separated list with no empty item (e.g. "k2,,k3" is a mistake, not two names).
std::string check_list(const std::string& text) {
  for (size_t start = 0; start <= text.size();) {
    const size_t comma = std::min(text.find(',', start), text.size());
    if (comma == start) return "empty parameter name in '" + text + "'";
    start = comma + 1;
  }
  return "";
}

Json list_value(const std::string& text) {
  Json names = Json::array();
  for (size_t start = 0; start <= text.size();) {
    const size_t comma = std::min(text.find(',', start), text.size());
    names.push_back(text.substr(start, comma - start));
    start = comma + 1;
  }
  return names;
}

std::string help_text(const KeyInfo& k) {
  const std::string def = k.default_text[0] ? k.default_text : "none";
  return std::string(k.doc) + " (default: " + def + ")";
}

}  // namespace

// One key's flag and the variable CLI11 parses it into.
struct SessionFlags::Flag {
  const KeyInfo* key = nullptr;
  CLI::Option* option = nullptr;
  CLI::Option* negation = nullptr;  // the "!name" alias
  double number = 0;
  long long integer = 0;
  bool on = false;
  bool negated = false;
  std::string text;

  void add_to(CLI::App* cmd);
  void add_negation(CLI::App* cmd);
  Json value() const;
};

void SessionFlags::Flag::add_to(CLI::App* cmd) {
  const KeyInfo& k = *key;
  std::string names = flag_name(k.key);
  const bool negating_alias = k.alias[0] == '!';
  if (k.alias[0] && !negating_alias) names += ",--" + std::string(k.alias);
  const std::string doc = help_text(k);
  switch (k.kind) {
    case KeyKind::kNumber:
    case KeyKind::kOptionalNumber:  // unset unless given
      option = cmd->add_option(names, number, doc)->check(in_range(k.lo, k.hi));
      break;
    case KeyKind::kInteger:
      option = cmd->add_option(names, integer, doc)->check(in_range(k.lo, k.hi));
      break;
    case KeyKind::kBool:  // --lock-settings, --lock-settings=false
      option = cmd->add_flag(names, on, doc);
      break;
    case KeyKind::kChoice:
      option = cmd->add_option(names, text, doc)->check(CLI::IsMember(split_choices(k.choices)));
      break;
    case KeyKind::kText:
      option = cmd->add_option(names, text, doc);
      break;
    case KeyKind::kTextList:
      option = cmd->add_option(names, text, doc)
                   ->check(CLI::Validator(check_list, ""))
                   ->type_name("A,B,...");
      break;
  }
  option->group("session config");
  if (negating_alias) add_negation(cmd);
}

void SessionFlags::Flag::add_negation(CLI::App* cmd) {
  const std::string name = key->alias + 1;
  negation = cmd->add_flag("--" + name, negated, "the same as " + flag_name(key->key) + "=false");
  negation->group("session config");
  negation->excludes(option);
}

Json SessionFlags::Flag::value() const {
  if (negation && negation->count() > 0) return !negated;
  switch (key->kind) {
    case KeyKind::kNumber:
    case KeyKind::kOptionalNumber:
      return number;
    case KeyKind::kInteger:
      return integer;
    case KeyKind::kBool:
      return on;
    case KeyKind::kChoice:
    case KeyKind::kText:
      return text;
    case KeyKind::kTextList:
      return list_value(text);
  }
  return nullptr;
}

SessionFlags::SessionFlags(CLI::App* cmd) {
  for (const KeyInfo& k : kKeys) {
    flags_.push_back(std::make_unique<Flag>());
    flags_.back()->key = &k;
    flags_.back()->add_to(cmd);
  }
}

SessionFlags::~SessionFlags() = default;

Json SessionFlags::config() const {
  Json cfg = Json::object();
  for (const auto& f : flags_) {
    const bool given = f->option->count() > 0 || (f->negation && f->negation->count() > 0);
    if (given) cfg[f->key->key] = f->value();
  }
  return cfg;
}

}  // namespace posecal::cli
