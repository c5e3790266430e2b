#include "services/cluster/nats_status.h"

#include <xxhash.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "services/core/absl_view.h"

namespace fleetmem::cluster {

bool Unreachable(natsStatus status) {
  return status == NATS_TIMEOUT || status == NATS_NO_SERVER ||
         status == NATS_NO_RESPONDERS || status == NATS_CONNECTION_CLOSED ||
         status == NATS_CONNECTION_DISCONNECTED ||
         status == NATS_STALE_CONNECTION || status == NATS_NOT_YET_CONNECTED;
}

std::string Hash(std::string_view fleet_id) {
  return absl::StrFormat("%016x",
                         XXH3_64bits(fleet_id.data(), fleet_id.size()));
}

absl::Status FromNats(natsStatus status, int code, std::string_view what) {
  std::string text = absl::StrCat(V(what), ": ", natsStatus_GetText(status));
  const char* detail = nats_GetLastError(nullptr);
  if (detail != nullptr && *detail != '\0') {
    absl::StrAppend(&text, " (", detail, ")");
  }
  if (code != 0) absl::StrAppend(&text, " [JetStream error ", code, "]");
  if (status == NATS_TIMEOUT) return absl::DeadlineExceededError(text);
  if (Unreachable(status)) return absl::UnavailableError(text);
  if (status == NATS_NOT_FOUND) return absl::NotFoundError(text);
  return absl::InternalError(text);
}

}  // namespace fleetmem::cluster
