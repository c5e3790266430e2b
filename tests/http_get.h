// Test utility: the body of one GET on a server's HTTP port ("" if it does
// not answer within 5 s). For tests that read /readyz and /metrics beside
// their gRPC calls.
#ifndef FLEETMEM_TESTS_HTTP_GET_H_
#define FLEETMEM_TESTS_HTTP_GET_H_

#include <string>

#include "httplib.h"

namespace fleetmem::testing {

inline std::string HttpGet(const std::string& http_address,
                           const std::string& path) {
  httplib::Client client("http://" + http_address);
  client.set_read_timeout(5, 0);
  httplib::Result got = client.Get(path.c_str());
  return got ? got->body : std::string();
}

}  // namespace fleetmem::testing

#endif  // FLEETMEM_TESTS_HTTP_GET_H_
