// What one client may hold of the HTTP port, and the deadlines of a
// request: the options of ConnectionGuard (connection_guard.h), apart from it
// so that users need not see httplib.
#ifndef FLEETMEM_SERVICES_HTTP_CONNECTION_LIMITS_H_
#define FLEETMEM_SERVICES_HTTP_CONNECTION_LIMITS_H_

#include <cstddef>
#include <functional>
#include <optional>
#include <string>
#include <string_view>
#include <utility>

#include "absl/time/time.h"

namespace fleetmem::http {

struct ConnectionLimits {
  // Connections served at once (each holds a thread while open).
  size_t max_connections = 256;
  // Connections one IP address may hold at once.
  size_t max_connections_per_client = 64;
  // From a connection's start (or its previous answer) to the end of the
  // next request's head; the TLS handshake counts.
  absl::Duration head_timeout = absl::Seconds(10);
  // From the end of a request's head to the end of its body.
  absl::Duration body_timeout = absl::Seconds(60);
  // Bytes a connection may send for one request head (request line and
  // headers; the TLS handshake too): httplib bounds each line (8 KiB) but
  // not their number, so a client could send headers for head_timeout at
  // the network's speed. Checked every check_every from the bytes the
  // server has read, so a connection is closed within one read buffer
  // (4 KiB) and one check of going over.
  size_t max_head_bytes = 64 * 1024;
  // How often deadlines are checked.
  absl::Duration check_every = absl::Milliseconds(100);
  // Called with the reason (naming the client's address) for each
  // connection refused or closed by a limit (for a metric or a log; may be
  // empty).
  std::function<void(const std::string& reason)> on_refused;
  // Over a limit, a connection's request line is still read, for up to
  // probe_wait and without a thread of its own (one thread polls them
  // all), and a probe is answered: `probe` gets the path ("/readyz") and
  // returns the status and body, or nullopt for every other path (those
  // get 503). So probes keep their answer whatever slow clients hold (the
  // third outside sweep: /readyz answered 503 to 33 of 60 probes beside
  // 300 slow connections). Empty (and over TLS, whose handshake this does
  // not do): over a limit every connection is refused at once.
  std::function<std::optional<std::pair<int, std::string>>(
      std::string_view path)>
      probe;
  absl::Duration probe_wait = absl::Seconds(1);
};

}  // namespace fleetmem::http

#endif  // FLEETMEM_SERVICES_HTTP_CONNECTION_LIMITS_H_
