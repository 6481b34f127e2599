#include "session/session_options.hpp"

#include <cmath>
#include <cstdio>
#include <functional>

#include "common/error.hpp"

namespace posecal {

namespace {

[[noreturn]] void bad(const char* key, const std::string& expected) {
  throw Error(ErrorCode::kInvalidArgument, std::string("'") + key + "' must be " + expected);
}

std::string range_text(double lo, double hi) {
  char buf[64];
  std::snprintf(buf, sizeof buf, "[%g, %g]", lo, hi);
  return buf;
}

template <class T>
const T& value_as(const char* key, const SessionKeyValue& v, const std::string& expected) {
  if (const T* p = std::get_if<T>(&v)) return *p;
  bad(key, expected);
}

std::vector<std::string> split_choices(const char* choices) {
  std::vector<std::string> out;
  std::string c = choices;
  size_t start = 0;
  while (true) {
    const size_t bar = c.find('|', start);
    out.push_back(c.substr(start, bar - start));
    if (bar == std::string::npos) return out;
    start = bar + 1;
  }
}

std::string choices_text(const char* choices) {
  std::string out;
  for (const std::string& c : split_choices(choices)) out += (out.empty() ? "\"" : " or \"") + c + "\"";
  return out;
}

// ---- setters and getters by kind, for the member's type ----

void set_Number(const char* key, double lo, double hi, const char*, double& m, const SessionKeyValue& v) {
  double x = 0;
  if (const long long* i = std::get_if<long long>(&v)) {
    x = static_cast<double>(*i);
  } else {
    x = value_as<double>(key, v, "a number in " + range_text(lo, hi));
  }
  if (!(x >= lo && x <= hi)) bad(key, "a number in " + range_text(lo, hi));
  m = x;
}
SessionKeyValue get_Number(const char*, double m) { return m; }

void set_OptionalNumber(const char* key, double lo, double hi, const char* choices, std::optional<double>& m,
                        const SessionKeyValue& v) {
  if (std::holds_alternative<std::monostate>(v)) {
    m.reset();
    return;
  }
  double x = 0;
  set_Number(key, lo, hi, choices, x, v);
  m = x;
}
SessionKeyValue get_OptionalNumber(const char*, const std::optional<double>& m) {
  return m ? SessionKeyValue(*m) : SessionKeyValue(std::monostate{});
}

void set_Integer(const char* key, double lo, double hi, const char*, int& m, const SessionKeyValue& v) {
  const long long x = value_as<long long>(key, v, "an integer in " + range_text(lo, hi));
  if (!(static_cast<double>(x) >= lo && static_cast<double>(x) <= hi)) bad(key, "an integer in " + range_text(lo, hi));
  m = static_cast<int>(x);
}
SessionKeyValue get_Integer(const char*, int m) { return static_cast<long long>(m); }

void set_Bool(const char* key, double, double, const char*, bool& m, const SessionKeyValue& v) {
  m = value_as<bool>(key, v, "true or false");
}
SessionKeyValue get_Bool(const char*, bool m) { return m; }

// A choice sets the member to the choice's index (an enum, or false/true).
template <class T>
void set_Choice(const char* key, double, double, const char* choices, T& m, const SessionKeyValue& v) {
  const std::string& name = value_as<std::string>(key, v, choices_text(choices));
  const std::vector<std::string> names = split_choices(choices);
  for (size_t i = 0; i < names.size(); ++i) {
    if (names[i] == name) {
      m = static_cast<T>(i);
      return;
    }
  }
  bad(key, choices_text(choices) + ", got \"" + name + "\"");
}
template <class T>
SessionKeyValue get_Choice(const char* choices, T m) {
  return split_choices(choices).at(static_cast<size_t>(m));
}
// "method": a preset over several engine members (EngineOptions::set_method).
void set_Choice(const char* key, double lo, double hi, const char* choices, EngineOptions& m, const SessionKeyValue& v) {
  EngineOptions::Method method = EngineOptions::Method::kPosecal;
  set_Choice(key, lo, hi, choices, method, v);
  m.set_method(method);
}
SessionKeyValue get_Choice(const char* choices, const EngineOptions& m) { return get_Choice(choices, m.method); }

// "lens_model": a model of the lens table (the choices in table order), or "auto" (last).
void set_Choice(const char* key, double lo, double hi, const char* choices,
                EngineOptions::LensModelKey m, const SessionKeyValue& v) {
  const std::string& name = value_as<std::string>(key, v, choices_text(choices));
  m.automatic = name == "auto";
  if (m.automatic) {
    m.model = LensModel::kOpenCV5;  // the first model; the engine moves from it
  } else {
    set_Choice(key, lo, hi, choices, m.model, v);
  }
}
SessionKeyValue get_Choice(const char* choices, EngineOptions::ConstLensModelKey m) {
  return m.automatic ? std::string("auto") : get_Choice(choices, m.model);
}

void set_Text(const char* key, double, double, const char*, BoardSpec& m, const SessionKeyValue& v) {
  m = BoardSpec::parse(value_as<std::string>(key, v, "a string"));
}
SessionKeyValue get_Text(const char*, const BoardSpec& m) { return m.to_string(); }
void set_Text(const char* key, double, double, const char*, std::string& m, const SessionKeyValue& v) {
  m = value_as<std::string>(key, v, "a string");
}
SessionKeyValue get_Text(const char*, const std::string& m) { return m; }

void set_TextList(const char* key, double, double, const char*, std::vector<std::string>& m,
                  const SessionKeyValue& v) {
  m = value_as<std::vector<std::string>>(key, v, "an array of strings");
}
SessionKeyValue get_TextList(const char*, const std::vector<std::string>& m) { return m; }

struct KeyAccess {
  SessionKeyInfo info;
  std::function<void(SessionOptions&, const SessionKeyValue&)> set;
  std::function<SessionKeyValue(const SessionOptions&)> get;
};

#define POSECAL_MEMBER_engine(o, member) (o).engine.member
#define POSECAL_MEMBER_session(o, member) (o).member
#define POSECAL_KEY(scope, key, kind, member, lo, hi, choices, def, alias, doc)                              \
  KeyAccess{{#key, SessionKeyKind::k##kind, lo, hi, choices, def, alias, doc},                               \
            [](SessionOptions& o, const SessionKeyValue& v) {                                                \
              set_##kind(#key, lo, hi, choices, POSECAL_MEMBER_##scope(o, member), v);                       \
            },                                                                                               \
            [](const SessionOptions& o) { return get_##kind(choices, POSECAL_MEMBER_##scope(o, member)); }},

const std::vector<KeyAccess>& table() {
  static const std::vector<KeyAccess> t = {
#include "session/session_keys.def"
  };
  return t;
}
#undef POSECAL_KEY

const KeyAccess& access(const std::string& key) {
  for (const KeyAccess& k : table())
    if (key == k.info.key) return k;
  std::string known;
  for (const KeyAccess& k : table()) known += (known.empty() ? "" : ", ") + std::string(k.info.key);
  throw Error(ErrorCode::kInvalidArgument, "unknown key '" + key + "' (known: " + known + ")");
}

}  // namespace

const std::vector<SessionKeyInfo>& session_keys() {
  static const std::vector<SessionKeyInfo> keys = [] {
    std::vector<SessionKeyInfo> v;
    for (const KeyAccess& k : table()) v.push_back(k.info);
    return v;
  }();
  return keys;
}

const SessionKeyInfo* find_session_key(const std::string& key) {
  for (const SessionKeyInfo& k : session_keys())
    if (key == k.key) return &k;
  return nullptr;
}

void set_session_key(SessionOptions* options, const std::string& key, const SessionKeyValue& value) {
  access(key).set(*options, value);
}

SessionKeyValue get_session_key(const SessionOptions& options, const std::string& key) {
  return access(key).get(options);
}

}  // namespace posecal
