#include "services/http/socket_bytes.h"

#include <linux/sockios.h>
#include <linux/tcp.h>
#include <netinet/in.h>
#include <sys/ioctl.h>
#include <sys/socket.h>

#include <cstddef>

namespace fleetmem::http {

std::optional<uint64_t> BytesReadFrom(int socket) {
  tcp_info info{};
  socklen_t length = sizeof(info);
  if (getsockopt(socket, IPPROTO_TCP, TCP_INFO, &info, &length) != 0 ||
      length < offsetof(tcp_info, tcpi_bytes_received) +
                   sizeof(info.tcpi_bytes_received)) {
    return std::nullopt;
  }
  int unread = 0;
  if (ioctl(socket, SIOCINQ, &unread) != 0 || unread < 0) return std::nullopt;
  const uint64_t received = info.tcpi_bytes_received;
  return received >= static_cast<uint64_t>(unread) ? received - unread : 0;
}

}  // namespace fleetmem::http
