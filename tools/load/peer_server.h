// The peers of fleetmem-load's benchmarks: a bare gRPC server speaking the
// same fleetmem.v1.MemoryService that parses and discards every upload
// (answering accepted = the traces received) and answers queries and samples
// with filler of the same size. What fleetmem does beyond moving the same
// bytes over gRPC is the difference between the two.
//
// The durable peer (PeerOptions::durable_file) is the same server that
// appends each upload message to one file and fdatasyncs it before reading
// the next or answering: one message at a time, under one lock for every
// stream, no grouping. It is what acknowledging at a synced append costs
// without group commit, admission or a log of one's own.
#ifndef FLEETMEM_TOOLS_LOAD_PEER_SERVER_H_
#define FLEETMEM_TOOLS_LOAD_PEER_SERVER_H_

#include <memory>
#include <string>

#include "absl/status/statusor.h"

namespace fleetmem::load {

struct PeerOptions {
  // Set: the durable peer, appending every upload message (serialized) to
  // this file, made or truncated at Start, each followed by fdatasync.
  std::string durable_file;
};

class PeerServer {
 public:
  // Listens on `listen` (HOST:PORT; port 0 picks a free one). A durable
  // peer's file that cannot be made is an error.
  static absl::StatusOr<std::unique_ptr<PeerServer>> Start(
      const std::string& listen, PeerOptions options = {});
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
