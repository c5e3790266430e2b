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

// Issue 32: a second principal acting as robot-7 uploaded robot-7's seqs
// first, and the real robot-7's came back as duplicates.
TEST(ParseCredentialsTest, ARobotIdBelongsToOnePrincipal) {
  const std::string hash = Hash("s");
  auto robot = [&](const std::string& name, const std::string& robot_id,
                   const std::string& fleet) {
    return absl::StrCat(
        "principal { name: \"", name, "\" role: ROBOT robot_id: \"", robot_id,
        "\" fleets: \"", fleet, "\" secret_hash: \"", hash, "\" }\n");
  };
  absl::StatusOr<std::vector<CredentialEntry>> twins = ParseCredentials(
      robot("robot-7", "robot-7", "f1") + robot("twin", "robot-7", "*"));
  ASSERT_FALSE(twins.ok());
  EXPECT_THAT(twins.status().message(), HasSubstr("robot id \"robot-7\""));
  EXPECT_THAT(twins.status().message(), HasSubstr("twin"));
  // The same id in fleets that do not meet is two robots.
  EXPECT_TRUE(ParseCredentials(robot("robot-7", "robot-7", "f1") +
                               robot("other-7", "robot-7", "f2"))
                  .ok());
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

// Issue 32: wrong secrets for a known name each cost an Argon2id check
// (0.1 s, 64 MiB); eight clients took the p50 of real calls to 952 ms. Now
// a name gets `check_burst_per_name` checks, then its rate; over it a new
// token is answered UNAVAILABLE at once, and other names are not held up.
TEST_F(AuthenticatorTest, FailedChecksAreBoundedPerNameAndInAll) {
  absl::Time now = absl::UnixEpoch();
  AuthenticatorOptions options;
  options.checks_per_second_per_name = 1;
  options.check_burst_per_name = 2;
  options.checks_per_second = 100;
  options.check_burst = 3;
  options.now = [&now] { return now; };
  std::vector<CredentialEntry> entries = Entries("secret1");
  entries.push_back(entries[0]);
  entries.back().principal.name = "robot-8";
  entries.back().principal.robot_id = "robot-8";
  entries.back().secret_hash = Hash("secret8");
  Authenticator authenticator(entries, options);

  EXPECT_TRUE(absl::IsUnauthenticated(
      authenticator.Authenticate({"robot-7:wrong-1", {}}).status()));
  EXPECT_TRUE(absl::IsUnauthenticated(
      authenticator.Authenticate({"robot-7:wrong-2", {}}).status()));
  const absl::Status spent =
      authenticator.Authenticate({"robot-7:wrong-3", {}}).status();
  EXPECT_TRUE(absl::IsUnavailable(spent)) << spent;
  EXPECT_THAT(spent.message(), HasSubstr("robot-7"));
  // Even the right secret waits for robot-7's rate; a refused token that was
  // checked stays refused without a check; robot-8 is checked (the last of
  // the server's burst of 3).
  EXPECT_TRUE(absl::IsUnavailable(
      authenticator.Authenticate({"robot-7:secret1", {}}).status()));
  EXPECT_TRUE(absl::IsUnauthenticated(
      authenticator.Authenticate({"robot-7:wrong-1", {}}).status()));
  EXPECT_TRUE(authenticator.Authenticate({"robot-8:secret8", {}}).ok());
  // Unknown names cost no check and are refused as wrong.
  EXPECT_TRUE(absl::IsUnauthenticated(
      authenticator.Authenticate({"nobody:x", {}}).status()));
  // The server's burst is spent; a second later both rates allow one more.
  now += absl::Seconds(1);
  EXPECT_TRUE(authenticator.Authenticate({"robot-7:secret1", {}}).ok());
  EXPECT_TRUE(absl::IsUnavailable(
      authenticator.Authenticate({"robot-7:wrong-4", {}}).status()));
  // The checked tokens answer from the cache, whatever the rates.
  for (int i = 0; i < 10; ++i) {
    EXPECT_TRUE(authenticator.Authenticate({"robot-7:secret1", {}}).ok());
    EXPECT_TRUE(authenticator.Authenticate({"robot-8:secret8", {}}).ok());
  }
}

// 4,100 junk tokens once emptied the whole cache, so every robot's next call
// cost a check. Valid tokens are now cached apart from refused ones.
TEST_F(AuthenticatorTest, JunkTokensDoNotEvictValidOnes) {
  AuthenticatorOptions options;
  options.check_burst_per_name = 1;  // one check, never another
  options.checks_per_second_per_name = 0;
  Authenticator authenticator(Entries("secret1"), options);
  ASSERT_TRUE(authenticator.Authenticate({"robot-7:secret1", {}}).ok());
  for (int i = 0; i < 10000; ++i) {
    ASSERT_FALSE(
        authenticator.Authenticate({absl::StrCat("junk-", i, ":x"), {}}).ok());
  }
  EXPECT_TRUE(authenticator.Authenticate({"robot-7:secret1", {}}).ok());
}

TEST_F(AuthenticatorTest, ReplaceKeepsTheChecksOfUnchangedPrincipals) {
  AuthenticatorOptions options;
  options.check_burst_per_name = 1;
  options.checks_per_second_per_name = 0;
  const std::vector<CredentialEntry> entries = Entries("secret1");
  Authenticator authenticator(entries, options);
  ASSERT_TRUE(authenticator.Authenticate({"robot-7:secret1", {}}).ok());
  authenticator.Replace(entries);  // a SIGHUP with the same file
  EXPECT_TRUE(authenticator.Authenticate({"robot-7:secret1", {}}).ok());
  std::vector<CredentialEntry> narrower = entries;
  narrower[0].principal.fleets = {"f2"};
  authenticator.Replace(narrower);  // rights changed: checked again
  EXPECT_TRUE(absl::IsUnavailable(
      authenticator.Authenticate({"robot-7:secret1", {}}).status()));
}

}  // namespace
}  // namespace fleetmem::auth
