#include "services/auth/authenticator.h"

#include <string>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/auth/secret.h"

namespace fleetmem::auth {
namespace {

using ::testing::HasSubstr;

std::string Hash(const std::string& secret) {
  absl::StatusOr<std::string> hash = HashSecret(secret);
  EXPECT_TRUE(hash.ok()) << hash.status();
  return *hash;
}

TEST(SecretTest, HashVerifies) {
  absl::StatusOr<std::string> secret = NewSecret();
  ASSERT_TRUE(secret.ok());
  EXPECT_EQ(secret->size(), 64u);
  const std::string hash = Hash(*secret);
  EXPECT_TRUE(CheckSecretHash(hash).ok());
  EXPECT_TRUE(VerifySecret(hash, *secret));
  EXPECT_FALSE(VerifySecret(hash, "wrong"));
  EXPECT_FALSE(VerifySecret("garbage", *secret));
  EXPECT_NE(*NewSecret(), *secret);
}

TEST(ParseCredentialsTest, AcceptsAFile) {
  const std::string text = absl::StrCat(
      "principal { name: \"robot-7\" role: ROBOT fleets: \"f1\" secret_hash: "
      "\"",
      Hash("s"),
      "\" }\n"
      "principal { name: \"r8\" role: ROBOT robot_id: \"robot-8\" fleets: "
      "\"f1\" certificate_common_name: \"robot-8.fleet\" }\n"
      "principal { name: \"ops\" role: ADMIN certificate_common_name: \"ops\" "
      "}\n");
  absl::StatusOr<std::vector<CredentialEntry>> entries = ParseCredentials(text);
  ASSERT_TRUE(entries.ok()) << entries.status();
  ASSERT_EQ(entries->size(), 3u);
  EXPECT_EQ((*entries)[0].principal.robot_id, "robot-7");
  EXPECT_EQ((*entries)[1].principal.robot_id, "robot-8");
  EXPECT_EQ((*entries)[2].principal.role, Role::kAdmin);
}

TEST(ParseCredentialsTest, RejectsBadEntries) {
  const struct {
    std::string text;
    std::string message;
  } cases[] = {
      {"principal { name: \"a\" role: ROBOT fleets: \"f\" }", "needs"},
      {"principal { name: \"a\" fleets: \"f\" certificate_common_name: \"a\" }",
       "role"},
      {"principal { name: \"a b\" role: READER fleets: \"f\" "
       "certificate_common_name: \"a\" }",
       "name"},
      {"principal { name: \"a\" role: READER certificate_common_name: \"a\" }",
       "fleets"},
      {"principal { name: \"a\" role: READER fleets: \"f\" secret_hash: "
       "\"plain\" }",
       "Argon2id"},
      {"principal { name: \"a\" role: ADMIN certificate_common_name: \"x\" }\n"
       "principal { name: \"a\" role: ADMIN certificate_common_name: \"y\" }",
       "earlier"},
      {"principal { name: \"a\" role: ADMIN certificate_common_name: \"x\" }\n"
       "principal { name: \"b\" role: ADMIN certificate_common_name: \"x\" }",
       "certificate_common_name"},
      {"principal { name: \"a\" role: READER robot_id: \"r\" fleets: \"f\" "
       "certificate_common_name: \"x\" }",
       "robot_id"},
      {"principal { nme: \"a\" }", "line 1"},
  };
  for (const auto& c : cases) {
    absl::StatusOr<std::vector<CredentialEntry>> entries =
        ParseCredentials(c.text);
    ASSERT_FALSE(entries.ok()) << c.text;
    EXPECT_EQ(entries.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(entries.status().message(), HasSubstr(c.message)) << c.text;
  }
}

class AuthenticatorTest : public ::testing::Test {
 protected:
  std::vector<CredentialEntry> Entries(const std::string& secret) {
    absl::StatusOr<std::vector<CredentialEntry>> entries = ParseCredentials(
        absl::StrCat("principal { name: \"robot-7\" role: ROBOT fleets: \"f1\" "
                     "secret_hash: \"",
                     Hash(secret),
                     "\" }\n"
                     "principal { name: \"r8\" role: ROBOT fleets: \"f1\" "
                     "certificate_common_name: \"robot-8\" }\n"));
    EXPECT_TRUE(entries.ok()) << entries.status();
    return *entries;
  }
};

TEST_F(AuthenticatorTest, TokenAndCertificate) {
  Authenticator authenticator(Entries("secret1"));
  absl::StatusOr<Principal> robot =
      authenticator.Authenticate({MakeToken("robot-7", "secret1"), {}});
  ASSERT_TRUE(robot.ok()) << robot.status();
  EXPECT_EQ(robot->robot_id, "robot-7");
  // Cached the second time: same answer.
  EXPECT_TRUE(authenticator.Authenticate({"robot-7:secret1", {}}).ok());

  absl::StatusOr<Principal> by_cert =
      authenticator.Authenticate({{}, "robot-8"});
  ASSERT_TRUE(by_cert.ok());
  EXPECT_EQ(by_cert->name, "r8");

  for (const PresentedCredentials& bad : {
           PresentedCredentials{"robot-7:wrong", {}},
           PresentedCredentials{"robot-7:wrong", {}},  // cached failure
           PresentedCredentials{"nobody:secret1", {}},
           PresentedCredentials{"no-colon", {}},
           PresentedCredentials{"r8:anything", {}},  // certificate only
           PresentedCredentials{{}, "robot-9"},
           PresentedCredentials{},
       }) {
    EXPECT_EQ(authenticator.Authenticate(bad).status().code(),
              absl::StatusCode::kUnauthenticated);
  }
}

TEST_F(AuthenticatorTest, ReplaceRevokesCachedTokens) {
  Authenticator authenticator(Entries("old"));
  ASSERT_TRUE(authenticator.Authenticate({"robot-7:old", {}}).ok());
  authenticator.Replace(Entries("new"));
  EXPECT_FALSE(authenticator.Authenticate({"robot-7:old", {}}).ok());
  EXPECT_TRUE(authenticator.Authenticate({"robot-7:new", {}}).ok());
}

}  // namespace
}  // namespace fleetmem::auth
