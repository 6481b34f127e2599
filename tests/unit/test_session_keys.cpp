// The one table of session keys (core/session/session_keys.def) against everything that states
// them again: the options' own defaults and validation, and the key lists of posecal.h,
// docs/c-api.md and the Python binding.
#include <gtest/gtest.h>

#include <fstream>
#include <limits>
#include <sstream>
#include <string>

#include "common/error.hpp"
#include "session/session_options.hpp"

namespace posecal {
namespace {

std::string read_text(const std::string& relative) {
  std::ifstream in(std::string(POSECAL_SOURCE_DIR) + "/" + relative);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

// The key's default, parsed from its text as the table writes it.
SessionKeyValue default_value(const SessionKeyInfo& k) {
  const std::string text = k.default_text;
  switch (k.kind) {
    case SessionKeyKind::kNumber: return std::stod(text);
    case SessionKeyKind::kOptionalNumber:
      return text.empty() ? SessionKeyValue(std::monostate{}) : SessionKeyValue(std::stod(text));
    case SessionKeyKind::kInteger: return std::stoll(text);
    case SessionKeyKind::kBool: return text == "true";
    case SessionKeyKind::kChoice:
    case SessionKeyKind::kText: return text;
    case SessionKeyKind::kTextList: return std::vector<std::string>{};
  }
  return text;
}

TEST(SessionKeys, DefaultsAreTheOptionsDefaults) {
  const SessionOptions defaults;
  std::string why;
  ASSERT_TRUE(defaults.is_valid(&why)) << why;
  for (const SessionKeyInfo& k : session_keys()) {
    EXPECT_TRUE(get_session_key(defaults, k.key) == default_value(k)) << k.key << ": the table's default '"
                                                                       << k.default_text << "' is not the struct's";
  }
}

TEST(SessionKeys, RangesAreTheValidationsRanges) {
  // Each numeric key's range endpoints are valid options, and just outside them the options are
  // not (the ABI and the engine cannot disagree, as max_tilt_deg 89 once did).
  for (const SessionKeyInfo& k : session_keys()) {
    if (k.kind != SessionKeyKind::kNumber && k.kind != SessionKeyKind::kInteger &&
        k.kind != SessionKeyKind::kOptionalNumber) {
      continue;
    }
    const bool integer = k.kind == SessionKeyKind::kInteger;
    for (const double v : {k.lo, k.hi}) {
      SessionOptions o;
      integer ? set_session_key(&o, k.key, static_cast<long long>(v)) : set_session_key(&o, k.key, v);
      std::string why;
      EXPECT_TRUE(o.is_valid(&why)) << k.key << " = " << v << ": " << why;
    }
    const double step = integer ? 1.0 : std::max(1e-9, 1e-6 * (k.hi - k.lo));
    for (const double v : {k.lo - step, k.hi + step}) {
      SessionOptions o;
      try {
        integer ? set_session_key(&o, k.key, static_cast<long long>(v)) : set_session_key(&o, k.key, v);
        ADD_FAILURE() << k.key << " = " << v << " was accepted";
      } catch (const Error& e) {
        EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
        EXPECT_NE(std::string(e.what()).find(k.key), std::string::npos) << e.what();
      }
    }
  }
}

// Set directly (as a C++ host of the engine would), out-of-range members fail EngineOptions'
// validation too, naming the key: the table's ranges are the engine's.
#define POSECAL_OUT_OF_RANGE_Number(key, member, lo, hi, step)                      \
  for (const double v : {(lo) - (step), (hi) + (step)}) {                            \
    EngineOptions o;                                                                 \
    o.member = static_cast<decltype(o.member)>(v);                                   \
    std::string why;                                                                 \
    EXPECT_FALSE(o.is_valid(&why)) << #key " = " << v;                               \
    EXPECT_NE(why.find(#key), std::string::npos) << why;                             \
  }
#define POSECAL_OUT_OF_RANGE_Integer(key, member, lo, hi, step) POSECAL_OUT_OF_RANGE_Number(key, member, lo, hi, 1)
#define POSECAL_OUT_OF_RANGE_OptionalNumber(key, member, lo, hi, step) POSECAL_OUT_OF_RANGE_Number(key, member, lo, hi, step)
#define POSECAL_OUT_OF_RANGE_Bool(...)
#define POSECAL_OUT_OF_RANGE_Choice(...)
#define POSECAL_OUT_OF_RANGE_Text(...)
#define POSECAL_OUT_OF_RANGE_TextList(...)
#define POSECAL_OUT_OF_RANGE_engine(kind, key, member, lo, hi) \
  POSECAL_OUT_OF_RANGE_##kind(key, member, lo, hi, std::max(1e-9, 1e-6 * ((hi) - (lo))))
#define POSECAL_OUT_OF_RANGE_session(...)

TEST(SessionKeys, EngineValidationUsesTheTablesRanges) {
#define POSECAL_KEY(scope, key, kind, member, lo, hi, choices, def, alias, doc) \
  POSECAL_OUT_OF_RANGE_##scope(kind, key, member, lo, hi)
#include "session/session_keys.def"
#undef POSECAL_KEY
}

TEST(SessionKeys, ValuesOfTheWrongKindAreRefusedNamingTheKey) {
  SessionOptions o;
  for (const SessionKeyInfo& k : session_keys()) {
    const SessionKeyValue wrong = k.kind == SessionKeyKind::kBool ? SessionKeyValue(std::string("yes"))
                                                                  : SessionKeyValue(true);
    try {
      set_session_key(&o, k.key, wrong);
      ADD_FAILURE() << k.key << " accepted a value of the wrong kind";
    } catch (const Error& e) {
      EXPECT_NE(std::string(e.what()).find(k.key), std::string::npos) << e.what();
    }
  }
  EXPECT_THROW(set_session_key(&o, "no_such_key", 1.0), Error);
  EXPECT_THROW(set_session_key(&o, "convergence_measure", std::string("median")), Error);
  EXPECT_THROW(set_session_key(&o, "target", std::string("charuco:1x1")), Error);
}

TEST(SessionKeys, AccuracyIsAPositiveFiniteNumberOrUnset) {
  SessionOptions o;
  EXPECT_FALSE(o.engine.accuracy_px.has_value());
  set_session_key(&o, "accuracy_px", 0.25);
  ASSERT_TRUE(o.engine.accuracy_px.has_value());
  EXPECT_DOUBLE_EQ(*o.engine.accuracy_px, 0.25);
  EXPECT_TRUE(get_session_key(o, "accuracy_px") == SessionKeyValue(0.25));
  set_session_key(&o, "accuracy_px", 1LL);  // an integer is a number
  EXPECT_DOUBLE_EQ(*o.engine.accuracy_px, 1.0);
  set_session_key(&o, "accuracy_px", std::monostate{});
  EXPECT_FALSE(o.engine.accuracy_px.has_value());
  for (const double bad : {0.0, -0.5, std::numeric_limits<double>::quiet_NaN(),
                           std::numeric_limits<double>::infinity()}) {
    try {
      set_session_key(&o, "accuracy_px", bad);
      ADD_FAILURE() << "accuracy_px " << bad << " accepted";
    } catch (const Error& e) {
      EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
      EXPECT_NE(std::string(e.what()).find("accuracy_px"), std::string::npos) << e.what();
    }
    EngineOptions direct;
    direct.accuracy_px = bad;
    std::string why;
    EXPECT_FALSE(direct.is_valid(&why)) << bad;
    EXPECT_NE(why.find("accuracy_px"), std::string::npos) << why;
  }
  // A key that is not optional cannot be unset.
  EXPECT_THROW(set_session_key(&o, "max_keyframes", std::monostate{}), Error);
}

TEST(SessionKeys, ChoicesRoundTrip) {
  SessionOptions o;
  set_session_key(&o, "operator", std::string("robot"));
  EXPECT_TRUE(o.engine.robot);
  set_session_key(&o, "convergence_measure", std::string("std"));
  EXPECT_EQ(o.engine.convergence_measure, EngineOptions::ConvergenceMeasure::kStd);
  EXPECT_TRUE(get_session_key(o, "convergence_measure") == SessionKeyValue(std::string("std")));
  set_session_key(&o, "fixed", std::vector<std::string>{"k2", "k3"});
  EXPECT_EQ(o.engine.calibration.fixed, (std::vector<std::string>{"k2", "k3"}));
}

// "lens_model"'s choices are the lens-model table, in its order (the member is the LensModel
// enum, set to the choice's index), then "auto" (EngineOptions::auto_lens_model).
TEST(SessionKeys, LensModelChoicesAreTheLensTable) {
  std::string table;
  for (const LensModel m : lens_models()) {
    if (!table.empty()) table += '|';
    table += lens_model_name(m);
  }
  bool found = false;
  for (const SessionKeyInfo& k : session_keys()) {
    if (std::string(k.key) != "lens_model") continue;
    found = true;
    EXPECT_EQ(std::string(k.choices), table + "|auto");
  }
  EXPECT_TRUE(found);
  SessionOptions o;
  set_session_key(&o, "lens_model", std::string("opencv14"));
  EXPECT_EQ(o.engine.calibration.lens_model, LensModel::kOpenCV14);
  EXPECT_FALSE(o.engine.auto_lens_model);
  EXPECT_THROW(set_session_key(&o, "lens_model", std::string("fisheye9")), Error);
  set_session_key(&o, "lens_model", std::string("auto"));
  EXPECT_TRUE(o.engine.auto_lens_model);
  EXPECT_EQ(o.engine.calibration.lens_model, LensModel::kOpenCV5);  // where it starts
  EXPECT_TRUE(get_session_key(o, "lens_model") == SessionKeyValue(std::string("auto")));
  set_session_key(&o, "lens_model", std::string("fisheye"));
  EXPECT_FALSE(o.engine.auto_lens_model);
  EXPECT_TRUE(get_session_key(o, "lens_model") == SessionKeyValue(std::string("fisheye")));
  // A prior is of one lens model: auto cannot move away from it.
  EngineOptions eo;
  eo.auto_lens_model = true;
  eo.calibration.prior = IntrinsicsPrior{};
  std::string why;
  EXPECT_FALSE(eo.is_valid(&why));
  EXPECT_NE(why.find("prior"), std::string::npos) << why;
}

TEST(SessionKeys, EveryKeyIsDocumentedWhereHostsLook) {
  const std::string header = read_text("plugin/include/posecal.h");
  const std::string c_api = read_text("docs/c-api.md");
  const std::string python = read_text("plugin/python/posecal/__init__.py");
  ASSERT_FALSE(header.empty() || c_api.empty() || python.empty());
  for (const SessionKeyInfo& k : session_keys()) {
    EXPECT_NE(header.find(std::string("\"") + k.key + "\""), std::string::npos) << k.key << " not in posecal.h";
    EXPECT_NE(c_api.find(std::string("`") + k.key + "`"), std::string::npos) << k.key << " not in docs/c-api.md";
    EXPECT_NE(python.find(k.key), std::string::npos) << k.key << " not in the Python binding's docstring";
  }
}

// "method" is a preset applied before every other key (it is the table's first), so keys given
// with it override it; accuracy_px cannot go with a method that stops on the ratio test.
TEST(SessionKeys, MethodIsAPresetTheOtherKeysOverride) {
  ASSERT_STREQ(session_keys().front().key, "method");
  SessionOptions o;
  set_session_key(&o, "method", std::string("paper"));
  EXPECT_EQ(o.engine.method, EngineOptions::Method::kPaper);
  EXPECT_EQ(o.engine.pose_candidates, 1);
  EXPECT_FALSE(o.engine.prospective_convergence);
  EXPECT_EQ(o.engine.convergence_measure, EngineOptions::ConvergenceMeasure::kVariance);
  EXPECT_EQ(o.engine.view_candidates, 0);
  EXPECT_EQ(o.engine.posegen.pinhole_fill, 0.6);
  EXPECT_EQ(std::get<std::string>(get_session_key(o, "method")), "paper");
  set_session_key(&o, "pose_candidates", 3LL);  // a later key overrides the preset
  EXPECT_EQ(o.engine.pose_candidates, 3);
  set_session_key(&o, "method", std::string("reference-std"));
  EXPECT_EQ(o.engine.convergence_measure, EngineOptions::ConvergenceMeasure::kStd);
  EXPECT_EQ(o.engine.pose_candidates, 1);
  std::string why;
  EXPECT_TRUE(o.is_valid(&why)) << why;
  set_session_key(&o, "accuracy_px", 0.3);
  EXPECT_FALSE(o.is_valid(&why));
  EXPECT_NE(why.find("accuracy_px"), std::string::npos) << why;
  EXPECT_NE(why.find("reference-std"), std::string::npos) << why;
  // Back to posecal's engine: every preset member at its default, accuracy_px allowed.
  set_session_key(&o, "method", std::string("posecal"));
  const EngineOptions d;
  EXPECT_EQ(o.engine.pose_candidates, d.pose_candidates);
  EXPECT_EQ(o.engine.prospective_convergence, d.prospective_convergence);
  EXPECT_EQ(o.engine.convergence_measure, d.convergence_measure);
  EXPECT_EQ(o.engine.view_candidates, d.view_candidates);
  EXPECT_EQ(o.engine.posegen.pinhole_fill, d.posegen.pinhole_fill);
  EXPECT_TRUE(o.is_valid(&why)) << why;
  EXPECT_THROW(set_session_key(&o, "method", std::string("magic")), Error);
}

}  // namespace
}  // namespace posecal
