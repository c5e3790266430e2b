// How many bytes the process has read from a TCP socket: the kernel's count
// of bytes received (TCP_INFO's tcpi_bytes_received) less those still unread
// in the receive queue (SIOCINQ). Apart from connection_guard.cc because
// <linux/tcp.h>, which declares that count, clashes with the C library's
// <netinet/tcp.h>, which httplib includes.
#ifndef FLEETMEM_SERVICES_HTTP_SOCKET_BYTES_H_
#define FLEETMEM_SERVICES_HTTP_SOCKET_BYTES_H_

#include <cstdint>
#include <optional>

namespace fleetmem::http {

// nullopt if the socket is not a TCP socket or the kernel does not say.
std::optional<uint64_t> BytesReadFrom(int socket);

}  // namespace fleetmem::http

#endif  // FLEETMEM_SERVICES_HTTP_SOCKET_BYTES_H_
