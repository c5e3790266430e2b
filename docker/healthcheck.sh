#!/bin/sh
# HEALTHCHECK of the fleetmem images.
# Server (default): GET /healthz on the HTTP port, FLEETMEM_HEALTH_URL
#   (default http://127.0.0.1:8080/healthz; use https://... when the server
#   has TLS: the certificate is not verified, this is the local host).
# Robot (FLEETMEM_HEALTH_STATUS_FILE set): the agent rewrites its status file
#   while it runs; healthy while it is younger than FLEETMEM_HEALTH_MAX_AGE
#   seconds (default 60).
set -eu
if [ -n "${FLEETMEM_HEALTH_STATUS_FILE:-}" ]; then
  age=$(($(date +%s) - $(stat -c %Y "$FLEETMEM_HEALTH_STATUS_FILE")))
  [ "$age" -lt "${FLEETMEM_HEALTH_MAX_AGE:-60}" ] || {
    echo "status file is ${age}s old"
    exit 1
  }
  exit 0
fi
exec curl -fsS -k --max-time 2 -o /dev/null \
  "${FLEETMEM_HEALTH_URL:-http://127.0.0.1:8080/healthz}"
