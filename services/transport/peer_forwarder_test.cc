// PeerForwarder against a replica that accepts connections and never
// answers (a partitioned peer whose connection looks open): a forwarded
// call ends at its caller's deadline, not at the forwarder's own limit.
#include "services/transport/peer_forwarder.h"

#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "fleetmem/v1/memory.pb.h"
#include "gtest/gtest.h"

namespace fleetmem::transport {
namespace {

// A TCP port on 127.0.0.1 that completes handshakes (the kernel's backlog)
// and never reads or writes a byte.
class SilentPeer {
 public:
  SilentPeer() {
    fd_ = socket(AF_INET, SOCK_STREAM, 0);
    sockaddr_in address{};
    address.sin_family = AF_INET;
    address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    address.sin_port = 0;
    socklen_t size = sizeof(address);
    if (fd_ < 0 ||
        bind(fd_, reinterpret_cast<sockaddr*>(&address), size) != 0 ||
        listen(fd_, 16) != 0 ||
        getsockname(fd_, reinterpret_cast<sockaddr*>(&address), &size) != 0) {
      return;
    }
    address_ = absl::StrCat("127.0.0.1:", ntohs(address.sin_port));
  }
  ~SilentPeer() {
    if (fd_ >= 0) close(fd_);
  }
  const std::string& address() const { return address_; }

 private:
  int fd_ = -1;
  std::string address_;
};

TEST(PeerForwarderTest, ACallToASilentPeerEndsAtItsCallersDeadline) {
  SilentPeer first, second;
  ASSERT_FALSE(first.address().empty());
  ASSERT_FALSE(second.address().empty());
  PeerOptions options;
  options.timeout = absl::Minutes(10);  // the caller's deadline comes first
  PeerForwarder forwarder(options);

  v1::ListFleetsResponse one, two;
  const std::vector<PeerCall> calls = {{first.address(), &one},
                                       {second.address(), &two}};
  const absl::Time started = absl::Now();
  const std::vector<absl::Status> statuses =
      forwarder.ForwardEach(calls, "ListFleets", v1::ListFleetsRequest(),
                            started + absl::Milliseconds(300));
  ASSERT_EQ(statuses.size(), 2u);
  for (size_t i = 0; i < statuses.size(); ++i) {
    EXPECT_EQ(statuses[i].code(), absl::StatusCode::kDeadlineExceeded)
        << statuses[i];
    EXPECT_NE(statuses[i].message().find(calls[i].address), std::string::npos)
        << statuses[i];
  }
  // Not a speed check: only that the forwarder's own ten-minute limit was
  // not what ended the calls.
  EXPECT_LT(absl::Now() - started, absl::Minutes(5));

  v1::GetStatsRequest request;
  request.set_fleet_id("f");
  v1::GetStatsResponse response;
  EXPECT_EQ(forwarder
                .Forward(first.address(), "GetStats", request, &response,
                         absl::Now() + absl::Milliseconds(100))
                .code(),
            absl::StatusCode::kDeadlineExceeded);
}

}  // namespace
}  // namespace fleetmem::transport
