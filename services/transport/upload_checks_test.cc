#include "services/transport/upload_checks.h"

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::transport {
namespace {

using ::testing::HasSubstr;

v1::UploadTracesRequest Request(const std::string& fleet,
                                std::initializer_list<const char*> robots) {
  v1::UploadTracesRequest request;
  request.set_fleet_id(fleet);
  uint64_t seq = 1;
  for (const char* robot : robots) {
    v1::MemoryTrace* trace = request.add_traces();
    trace->set_robot_id(robot);
    trace->set_seq(seq++);
    trace->add_code(1.0f);
    trace->set_replay_count(7);  // the server's to set
  }
  return request;
}

auth::Principal Robot(const std::string& robot_id,
                      std::vector<std::string> fleets) {
  return auth::Principal{"robot-" + robot_id, auth::Role::kRobot, robot_id,
                         std::move(fleets)};
}

TEST(UploadChecksTest, AStreamIsBoundToItsFirstMessagesFleet) {
  EXPECT_TRUE(CheckUploadFleet(Request("f1", {"r1"})).ok());
  EXPECT_EQ(CheckUploadFleet(Request("bad fleet", {"r1"})).code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_TRUE(CheckUploadFleet(Request("f1", {"r1"}), "f1").ok());
  const absl::Status other = CheckUploadFleet(Request("f2", {"r1"}), "f1");
  EXPECT_EQ(other.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(other.message(), HasSubstr("same fleet"));
}

TEST(UploadChecksTest, ARobotUploadsOnlyAsItselfToItsFleets) {
  const absl::StatusOr<CheckedUpload> own =
      CheckUploadTraces(Robot("r1", {"f1"}), Request("f1", {"r1", "r1"}));
  ASSERT_TRUE(own.ok()) << own.status();
  ASSERT_EQ(own->traces.size(), 2u);
  EXPECT_EQ(own->traces[0].replay_count, 0u);
  EXPECT_FALSE(own->wait_applied);

  const absl::StatusOr<CheckedUpload> other =
      CheckUploadTraces(Robot("r1", {"f1"}), Request("f1", {"r1", "r2"}));
  EXPECT_EQ(other.status().code(), absl::StatusCode::kPermissionDenied);
  EXPECT_THAT(other.status().message(), HasSubstr("traces[1]"));

  EXPECT_EQ(CheckUploadTraces(Robot("r1", {"f1"}), Request("f2", {"r1"}))
                .status()
                .code(),
            absl::StatusCode::kPermissionDenied);
}

TEST(UploadChecksTest, OneMessageIsCheckedWhole) {
  v1::UploadTracesRequest request = Request("f1", {"r1"});
  request.set_ack(v1::UPLOAD_ACK_APPLIED);
  const absl::StatusOr<CheckedUpload> checked =
      CheckUpload(auth::Principal::Anonymous(), request);
  ASSERT_TRUE(checked.ok()) << checked.status();
  EXPECT_TRUE(checked->wait_applied);
  EXPECT_EQ(CheckUpload(auth::Principal::Anonymous(), Request("", {"r1"}))
                .status()
                .code(),
            absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace fleetmem::transport
