#include "services/core/validation.h"

#include <functional>
#include <limits>
#include <string>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::core {
namespace {

using ::testing::HasSubstr;

constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
constexpr float kInf = std::numeric_limits<float>::infinity();

TEST(ValidateIdTest, AcceptsAllowedCharacters) {
  EXPECT_TRUE(ValidateId("fleet_id", "f1").ok());
  EXPECT_TRUE(ValidateId("fleet_id", "Nordland.summer_2024:robot-7").ok());
  EXPECT_TRUE(ValidateId("fleet_id", std::string(kMaxIdLength, 'a')).ok());
}

struct IdCase {
  std::string id;
  std::vector<std::string> message_parts;
};

TEST(ValidateIdTest, RejectsBadIds) {
  const IdCase cases[] = {
      {"", {"fleet_id", "empty"}},
      {std::string(kMaxIdLength + 1, 'a'), {"fleet_id", "129", "128"}},
      {"ab cd", {"fleet_id", "\"ab cd\"", "' '", "position 2"}},
      {"a/b", {"fleet_id", "'/'", "position 1"}},
      {"robot\n", {"fleet_id", "\\n"}},
      {"caf\xc3\xa9", {"fleet_id", "position 3"}},
  };
  for (const IdCase& c : cases) {
    const absl::Status status = ValidateId("fleet_id", c.id);
    ASSERT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << c.id;
    for (const std::string& part : c.message_parts) {
      EXPECT_THAT(std::string(status.message()), HasSubstr(part)) << c.id;
    }
  }
}

TEST(ValidateCodeTest, ChecksSizeAndFiniteness) {
  EXPECT_TRUE(ValidateCode("code", std::vector<float>{0.0f, -1.0f}).ok());
  EXPECT_THAT(std::string(ValidateCode("code", std::vector<float>{}).message()),
              HasSubstr("code is empty"));
  EXPECT_THAT(
      std::string(ValidateCode("traces[0].code", std::vector<float>{1.0f, kNaN})
                      .message()),
      HasSubstr("traces[0].code[1] is nan"));
  EXPECT_THAT(
      std::string(ValidateCode("c", std::vector<float>{-kInf}).message()),
      HasSubstr("c[0] is -inf"));
  EXPECT_EQ(
      ValidateCode("c", std::vector<float>(kMaxCodeDimension + 1, 0.0f)).code(),
      absl::StatusCode::kInvalidArgument);
}

// Issue 32's query poisoning: finite values whose squared norm overflows
// float32, and values too small for a unit vector.
TEST(ValidateCodeTest, RefusesNormsTheDistanceArithmeticCannotHold) {
  std::vector<float> huge(64);
  for (size_t i = 0; i < huge.size(); ++i) huge[i] = i % 2 ? -3e38f : 3e38f;
  const absl::Status refused = ValidateCode("traces[4].code", huge);
  EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(refused.message()),
              HasSubstr("traces[4].code has norm"));
  EXPECT_THAT(std::string(refused.message()), HasSubstr("[0] = 3e+38"));
  EXPECT_EQ(ValidateCode("c", std::vector<float>(64, 1e-45f)).code(),
            absl::StatusCode::kInvalidArgument);
  // All zeros (a black frame) and everyday norms stay accepted.
  EXPECT_TRUE(ValidateCode("c", std::vector<float>(64, 0.0f)).ok());
  EXPECT_TRUE(ValidateCode("c", std::vector<float>(4096, 1e3f)).ok());
  EXPECT_TRUE(ValidateCode("c", std::vector<float>(8, 1e-6f)).ok());
}

MemoryTrace GoodTrace() {
  MemoryTrace trace;
  trace.robot_id = "robot-1";
  trace.seq = 3;
  trace.domain = "summer";
  trace.code = std::vector<float>(256, 0.5f);
  trace.place = {.x = 1.0, .y = 2.0, .z = 0.0, .yaw = 0.3};
  trace.reward = 0.7f;
  trace.reward_external = 0.4f;
  trace.reward_internal = 0.3f;
  trace.encoder_version = "gpl-v1";
  return trace;
}

struct TraceCase {
  std::string name;
  std::function<void(MemoryTrace&)> mutate;
  std::vector<std::string> message_parts;
};

TEST(ValidateTraceTest, AcceptsGoodTrace) {
  const TraceShape shape{256, "gpl-v1", "f1"};
  EXPECT_TRUE(ValidateTrace("traces[3]", GoodTrace(), shape).ok());
  EXPECT_TRUE(ValidateTrace("traces[3]", GoodTrace(), TraceShape{}).ok());
  MemoryTrace zero_reward = GoodTrace();
  zero_reward.reward = 0.0f;
  EXPECT_TRUE(ValidateTrace("traces[3]", zero_reward, shape).ok());
}

TEST(ValidateTraceTest, AttachmentsUpToTheirLimit) {
  MemoryTrace t = GoodTrace();
  t.attachment.assign(kMaxAttachmentBytes, '\0');
  EXPECT_TRUE(ValidateTrace("traces[3]", t, TraceShape{}).ok());
  t.attachment.push_back('x');
  const absl::Status status = ValidateTrace("traces[3]", t, TraceShape{});
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(status.message()),
              ::testing::HasSubstr("traces[3].attachment has 16385 bytes"));
}

TEST(ValidateTraceTest, RejectsBadTraces) {
  const TraceCase cases[] = {
      {"empty robot id",
       [](MemoryTrace& t) { t.robot_id = ""; },
       {"traces[3].robot_id is empty"}},
      {"bad robot id chars",
       [](MemoryTrace& t) { t.robot_id = "r#1"; },
       {"traces[3].robot_id", "\"r#1\"", "'#'"}},
      {"NaN in code",
       [](MemoryTrace& t) { t.code[17] = kNaN; },
       {"traces[3].code[17] is nan"}},
      {"Inf in code",
       [](MemoryTrace& t) { t.code[0] = kInf; },
       {"traces[3].code[0] is inf"}},
      {"empty code",
       [](MemoryTrace& t) { t.code.clear(); },
       {"traces[3].code is empty"}},
      {"wrong dimension",
       [](MemoryTrace& t) { t.code.resize(128, 0.1f); },
       {"traces[3].code has dimension 128 but fleet \"f1\" uses 256"}},
      {"wrong encoder version",
       [](MemoryTrace& t) { t.encoder_version = "gpl-v2"; },
       {"traces[3].encoder_version is \"gpl-v2\" but fleet \"f1\" uses "
        "\"gpl-v1\""}},
      {"negative reward",
       [](MemoryTrace& t) { t.reward = -0.5f; },
       {"traces[3].reward is -0.5", ">= 0"}},
      {"NaN reward",
       [](MemoryTrace& t) { t.reward = kNaN; },
       {"traces[3].reward is nan"}},
      {"Inf external reward",
       [](MemoryTrace& t) { t.reward_external = kInf; },
       {"traces[3].reward_external is inf"}},
      {"NaN internal reward",
       [](MemoryTrace& t) { t.reward_internal = kNaN; },
       {"traces[3].reward_internal"}},
      {"NaN place",
       [](MemoryTrace& t) { t.place.y = kNaN; },
       {"traces[3].place.y is nan"}},
      {"Inf place",
       [](MemoryTrace& t) { t.place.x = -kInf; },
       {"traces[3].place.x is -inf"}},
      {"Inf yaw",
       [](MemoryTrace& t) { t.place.yaw = kInf; },
       {"traces[3].place.yaw"}},
      // Found by the upload fuzzer: a finite place too large for the
      // single-precision feature-spatial code made k-means index -1.
      {"place beyond any map",
       [](MemoryTrace& t) { t.place.z = 1e300; },
       {"traces[3].place.z is 1e+300; must be within"}},
      {"long domain",
       [](MemoryTrace& t) {
         t.domain = std::string(kMaxDomainLength + 1, 'd');
       },
       {"traces[3].domain", "65 characters", "at most 64"}},
      {"long encoder version",
       [](MemoryTrace& t) {
         t.encoder_version = std::string(kMaxEncoderVersionLength + 1, 'v');
       },
       {"traces[3].encoder_version", "65 characters"}},
  };
  const TraceShape shape{256, "gpl-v1", "f1"};
  for (const TraceCase& c : cases) {
    MemoryTrace trace = GoodTrace();
    c.mutate(trace);
    const absl::Status status = ValidateTrace("traces[3]", trace, shape);
    ASSERT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << c.name;
    for (const std::string& part : c.message_parts) {
      EXPECT_THAT(std::string(status.message()), HasSubstr(part)) << c.name;
    }
  }
}

TEST(ValidateTraceTest, UnfixedShapeAcceptsAnyDimensionAndVersion) {
  MemoryTrace trace = GoodTrace();
  trace.code.resize(64);
  trace.encoder_version = "other";
  EXPECT_TRUE(ValidateTrace("t", trace, TraceShape{}).ok());
  TraceShape dimension_only;
  dimension_only.code_dimension = 256;
  const absl::Status status = ValidateTrace("t", trace, dimension_only);
  EXPECT_THAT(std::string(status.message()),
              HasSubstr("t.code has dimension 64 but the fleet uses 256"));
}

}  // namespace
}  // namespace fleetmem::core
