#include "services/auth/access_policy.h"

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::auth {
namespace {

using ::testing::HasSubstr;

Principal Robot7() { return {"robot-7", Role::kRobot, "robot-7", {"f1"}}; }
Principal Reader() { return {"grafana", Role::kReader, "", {"f1"}}; }
Principal Admin() { return {"ops", Role::kAdmin, "", {}}; }

struct Case {
  Principal principal;
  Action action;
  std::string fleet;
  std::string robot;
  bool allowed;
};

TEST(AccessPolicyTest, RolesAndFleets) {
  const Case cases[] = {
      {Robot7(), Action::kUpload, "f1", "", true},
      {Robot7(), Action::kQuery, "f1", "", true},
      {Robot7(), Action::kWatch, "f1", "", true},
      {Robot7(), Action::kStats, "f1", "", true},
      {Robot7(), Action::kSample, "f1", "robot-7", true},
      {Robot7(), Action::kSample, "f1", "robot-8", false},
      {Robot7(), Action::kConsolidate, "f1", "", false},
      {Robot7(), Action::kQuery, "f2", "", false},
      {Robot7(), Action::kUpload, "f2", "", false},
      {Reader(), Action::kQuery, "f1", "", true},
      {Reader(), Action::kStats, "f1", "", true},
      {Reader(), Action::kWatch, "f1", "", true},
      {Reader(), Action::kUpload, "f1", "", false},
      {Reader(), Action::kSample, "f1", "grafana", false},
      {Reader(), Action::kConsolidate, "f1", "", false},
      {Reader(), Action::kStats, "f2", "", false},
      {Admin(), Action::kConsolidate, "any", "", true},
      {Admin(), Action::kSample, "any", "robot-3", true},
      {Admin(), Action::kUpload, "f9", "", true},
      {Principal::Anonymous(), Action::kConsolidate, "f1", "", true},
  };
  for (const Case& c : cases) {
    const absl::Status status =
        Authorize(c.principal, c.action, c.fleet, c.robot);
    EXPECT_EQ(status.ok(), c.allowed)
        << c.principal.name << " " << ActionName(c.action) << " " << c.fleet
        << ": " << status;
    if (!c.allowed) {
      EXPECT_EQ(status.code(), absl::StatusCode::kPermissionDenied);
      EXPECT_THAT(status.message(), HasSubstr(c.principal.name));
    }
  }
}

TEST(AccessPolicyTest, WildcardFleet) {
  Principal reader{"dash", Role::kReader, "", {"*"}};
  EXPECT_TRUE(Authorize(reader, Action::kStats, "anything").ok());
}

TEST(AccessPolicyTest, UploadOnlyAsItself) {
  EXPECT_TRUE(AuthorizeUploadAs(Robot7(), "robot-7").ok());
  const absl::Status other = AuthorizeUploadAs(Robot7(), "robot-8");
  EXPECT_EQ(other.code(), absl::StatusCode::kPermissionDenied);
  EXPECT_THAT(other.message(), HasSubstr("robot-8"));
  EXPECT_TRUE(AuthorizeUploadAs(Admin(), "robot-8").ok());
  EXPECT_FALSE(AuthorizeUploadAs(Reader(), "grafana").ok());
}

}  // namespace
}  // namespace fleetmem::auth
