# Test stand-in for prom/prometheus (this machine's engine cannot pull):
# Debian's prometheus package (2.42, the version docker/compose.yaml names)
# on the local bookworm base. Not shipped; docker/compose.yaml uses the
# upstream image unless FLEETMEM_PROMETHEUS_IMAGE says otherwise.
ARG BASE_IMAGE=debian:bookworm-slim
FROM ${BASE_IMAGE}
RUN apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y \
      -qq --no-install-recommends prometheus >/dev/null \
 && rm -rf /var/lib/apt/lists/* \
 && install -d -o prometheus -g prometheus /prometheus
USER prometheus
