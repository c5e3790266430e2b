// The peer of fleetmem-load's benchmarks: a bare gRPC server speaking the
// same fleetmem.v1.MemoryService that parses and discards every upload
// (answering accepted = the traces received) and answers queries and samples
// with empty results. What fleetmem does beyond moving the same bytes over
// gRPC is the difference between the two.
#ifndef FLEETMEM_TOOLS_LOAD_PEER_SERVER_H_
#define FLEETMEM_TOOLS_LOAD_PEER_SERVER_H_

#include <memory>
#include <string>

#include "absl/status/statusor.h"

namespace fleetmem::load {

class PeerServer {
 public:
  // Listens on `listen` (HOST:PORT; port 0 picks a free one).
  static absl::StatusOr<std::unique_ptr<PeerServer>> Start(
      const std::string& listen);
  ~PeerServer();
  // HOST:PORT it listens on.
  const std::string& address() const { return address_; }
  // Blocks until Shutdown (from another thread or a signal handler).
  void Wait();
  void Shutdown();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
  std::string address_;
};

}  // namespace fleetmem::load

#endif  // FLEETMEM_TOOLS_LOAD_PEER_SERVER_H_
