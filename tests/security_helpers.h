// Test utilities for identity and TLS: principals made with the real
// fleetmem-credential tool, certificates made with the openssl command, and
// stubs that present a token and/or TLS credentials.
#ifndef FLEETMEM_TESTS_SECURITY_HELPERS_H_
#define FLEETMEM_TESTS_SECURITY_HELPERS_H_

#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "fleetmem/v1/memory.grpc.pb.h"

namespace fleetmem::testing {

// Runs `command` through /bin/sh; INTERNAL with the command and its exit
// status if it fails.
absl::Status RunCommand(const std::string& command);

// Runs build/bin/fleetmem-credential for a new principal, appends its entry
// to `credentials_file` and returns its token ("" for --certificate-cn
// only). `fleets` may be empty (admin).
absl::StatusOr<std::string> AddPrincipal(
    const std::string& dir, const std::string& credentials_file,
    const std::string& name, const std::string& role,
    const std::vector<std::string>& fleets,
    const std::string& certificate_cn = "");

// PEM files under `dir`: ca.pem/ca.key (a CA), server.pem/server.key
// (CN and SAN localhost, IP 127.0.0.1, signed by the CA), client-<cn>.pem/
// .key for each of `client_cns` (signed by the CA), and rogue-ca.pem plus
// rogue-client.pem/.key (a client certificate of another CA, CN robot-8).
absl::Status MakeCertificates(const std::string& dir,
                              const std::vector<std::string>& client_cns);

struct ChannelSecurity {
  // Sent as "authorization: Bearer TOKEN" when not empty.
  std::string token;
  // PEM contents; TLS when ca_pem is set, mutual TLS with cert_pem/key_pem.
  std::string ca_pem;
  std::string cert_pem;
  std::string key_pem;
  // A connection of the stub's own, as another process would have (gRPC
  // shares one between channels with the same arguments; the server
  // rations token checks per connection).
  bool own_connection = false;
};

std::unique_ptr<v1::MemoryService::Stub> MakeSecureStub(
    const std::string& address, const ChannelSecurity& security);

}  // namespace fleetmem::testing

#endif  // FLEETMEM_TESTS_SECURITY_HELPERS_H_
