// The dashboard's static files (services/http/dashboard/), embedded in the
// binary at build time by cmake/embed_files.cmake: no build step, no CDN,
// nothing downloaded at run time.
#ifndef FLEETMEM_SERVICES_HTTP_DASHBOARD_ASSETS_H_
#define FLEETMEM_SERVICES_HTTP_DASHBOARD_ASSETS_H_

#include <cstddef>
#include <span>

namespace fleetmem::http {

struct EmbeddedFile {
  const char* path;  // URL path, e.g. "/app.js"; "/index.html" serves "/"
  const char* content_type;
  const unsigned char* data;
  size_t size;
};

std::span<const EmbeddedFile> DashboardFiles();

}  // namespace fleetmem::http

#endif  // FLEETMEM_SERVICES_HTTP_DASHBOARD_ASSETS_H_
