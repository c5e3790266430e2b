// Distributed mode: a replica's calls to another replica's MemoryService,
// for the fleets that replica owns (docs/distributed.md). Any unary method,
// by name, with the request and response messages the caller has; the call
// carries kForwardedHeader so that the receiver never forwards it again.
#ifndef FLEETMEM_SERVICES_TRANSPORT_PEER_FORWARDER_H_
#define FLEETMEM_SERVICES_TRANSPORT_PEER_FORWARDER_H_

#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/container/flat_hash_map.h"
#include "absl/status/status.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "google/protobuf/message.h"
#include "grpcpp/channel.h"

namespace fleetmem::transport {

struct PeerOptions {
  // The bearer token ("NAME:SECRET") replicas present to each other: a
  // principal of the shared credentials file with the admin role. Empty
  // when auth is off.
  std::string token;
  // PEM CA bundle the peers' server certificates are checked against; TLS
  // to peers when set.
  std::string ca_pem;
  // The name the peers' certificates are checked for instead of the host of
  // their address (one certificate for every replica); empty: the host.
  std::string tls_server_name;
  // Deadline of one forwarded call, when its caller gave none sooner.
  absl::Duration timeout = absl::Seconds(10);
};

// One call of a fan-out (PeerForwarder::ForwardEach): where to, and where
// its answer goes.
struct PeerCall {
  std::string address;
  google::protobuf::Message* response = nullptr;
};

// Thread-safe; one channel per peer, kept.
class PeerForwarder {
 public:
  explicit PeerForwarder(PeerOptions options);

  // Calls fleetmem.v1.MemoryService/`method` at `address` (HOST:PORT),
  // answered by `deadline` (the caller's) or options.timeout from now,
  // whichever comes first: a peer that does not answer (partitioned, its
  // connection silently gone) holds the call no longer than its caller
  // waits. The peer's status as it answered it; UNAVAILABLE or
  // DEADLINE_EXCEEDED naming the peer when it could not answer.
  absl::Status Forward(const std::string& address, std::string_view method,
                       const google::protobuf::Message& request,
                       google::protobuf::Message* response,
                       absl::Time deadline = absl::InfiniteFuture());
  // Forward to every call's address at once, each under the same deadline;
  // returns when all have answered or timed out, one status per call, in
  // order.
  std::vector<absl::Status> ForwardEach(
      std::span<const PeerCall> calls, std::string_view method,
      const google::protobuf::Message& request, absl::Time deadline);

 private:
  std::shared_ptr<grpc::Channel> ChannelTo(const std::string& address);

  const PeerOptions options_;
  absl::Mutex mu_;
  absl::flat_hash_map<std::string, std::shared_ptr<grpc::Channel>> channels_
      ABSL_GUARDED_BY(mu_);
};

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_PEER_FORWARDER_H_
