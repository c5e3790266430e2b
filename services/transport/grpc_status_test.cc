#include "services/transport/grpc_status.h"

#include <chrono>

#include "gtest/gtest.h"

namespace fleetmem::transport {
namespace {

using std::chrono::seconds;
using std::chrono::system_clock;

TEST(ToGrpcStatusTest, KeepsCodeAndMessage) {
  struct Case {
    absl::Status in;
    grpc::StatusCode want;
  };
  const Case cases[] = {
      {absl::InvalidArgumentError("traces[3].code: NaN"),
       grpc::StatusCode::INVALID_ARGUMENT},
      {absl::NotFoundError("fleet f"), grpc::StatusCode::NOT_FOUND},
      {absl::DeadlineExceededError("late"),
       grpc::StatusCode::DEADLINE_EXCEEDED},
      {absl::ResourceExhaustedError("big"),
       grpc::StatusCode::RESOURCE_EXHAUSTED},
      {absl::UnavailableError("bye"), grpc::StatusCode::UNAVAILABLE},
      {absl::InternalError("disk"), grpc::StatusCode::INTERNAL},
      {absl::FailedPreconditionError("encoder"),
       grpc::StatusCode::FAILED_PRECONDITION},
      {absl::AlreadyExistsError("x"), grpc::StatusCode::ALREADY_EXISTS},
      {absl::PermissionDeniedError("x"), grpc::StatusCode::PERMISSION_DENIED},
      {absl::UnauthenticatedError("x"), grpc::StatusCode::UNAUTHENTICATED},
      {absl::AbortedError("x"), grpc::StatusCode::ABORTED},
      {absl::OutOfRangeError("x"), grpc::StatusCode::OUT_OF_RANGE},
      {absl::UnimplementedError("x"), grpc::StatusCode::UNIMPLEMENTED},
      {absl::DataLossError("x"), grpc::StatusCode::DATA_LOSS},
      {absl::CancelledError("x"), grpc::StatusCode::CANCELLED},
      {absl::UnknownError("x"), grpc::StatusCode::UNKNOWN},
  };
  for (const Case& c : cases) {
    grpc::Status got = ToGrpcStatus(c.in);
    EXPECT_EQ(got.error_code(), c.want) << c.in;
    EXPECT_EQ(got.error_message(), c.in.message()) << c.in;
  }
}

TEST(ToGrpcStatusTest, OkIsOk) {
  grpc::Status got = ToGrpcStatus(absl::OkStatus());
  EXPECT_TRUE(got.ok());
  EXPECT_EQ(got.error_message(), "");
}

TEST(ToGrpcStatusTest, UnknownCodeBecomesUnknown) {
  grpc::Status got =
      ToGrpcStatus(absl::Status(static_cast<absl::StatusCode>(99), "odd"));
  EXPECT_EQ(got.error_code(), grpc::StatusCode::UNKNOWN);
  EXPECT_EQ(got.error_message(), "odd");
}

TEST(CannedStatusTest, Codes) {
  EXPECT_EQ(ServerBusyStatus().error_code(),
            grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_NE(ServerBusyStatus().error_message().find("server busy"),
            std::string::npos);
  EXPECT_EQ(ShuttingDownStatus().error_code(), grpc::StatusCode::UNAVAILABLE);
  EXPECT_EQ(DeadlineExceededStatus().error_code(),
            grpc::StatusCode::DEADLINE_EXCEEDED);
}

TEST(CallLivenessTest, Table) {
  const system_clock::time_point now = system_clock::now();
  struct Case {
    system_clock::time_point deadline;
    bool cancelled;
    grpc::StatusCode want;
  };
  const Case cases[] = {
      {now + seconds(5), false, grpc::StatusCode::OK},
      {system_clock::time_point::max(), false, grpc::StatusCode::OK},
      {now + seconds(5), true, grpc::StatusCode::CANCELLED},
      {now, false, grpc::StatusCode::DEADLINE_EXCEEDED},
      {now - seconds(1), false, grpc::StatusCode::DEADLINE_EXCEEDED},
      // A passed deadline wins over cancellation (gRPC cancels such calls).
      {now - seconds(1), true, grpc::StatusCode::DEADLINE_EXCEEDED},
  };
  for (const Case& c : cases) {
    EXPECT_EQ(CallLiveness(c.deadline, c.cancelled, now).error_code(), c.want)
        << "cancelled=" << c.cancelled;
  }
}

}  // namespace
}  // namespace fleetmem::transport
