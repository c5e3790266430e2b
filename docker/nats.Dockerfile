# NATS server with JetStream for fleetmem's distributed mode
# (docs/distributed.md, docker/cluster.compose.yaml): Debian's nats-server.
#
#   docker build -f docker/nats.Dockerfile -t fleetmem/nats:2.9 .
#
# BASE_IMAGE is debian:bookworm-slim; the Docker tests build on a local
# debootstrap of bookworm instead (tests/docker/base_image.sh).
ARG BASE_IMAGE=debian:bookworm-slim
FROM ${BASE_IMAGE}
RUN apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y \
      -qq --no-install-recommends nats-server curl ca-certificates >/dev/null \
 && rm -rf /var/lib/apt/lists/* \
 && useradd --system --uid 10003 --user-group --home-dir /var/lib/nats \
      --shell /usr/sbin/nologin natsd \
 && install -d -o natsd -g natsd -m 0750 /var/lib/nats
COPY docker/cluster/nats.conf /etc/nats/nats.conf
USER natsd
VOLUME /var/lib/nats
# Clients, routes between the servers, monitoring (/healthz).
EXPOSE 4222 6222 8222
HEALTHCHECK --interval=5s --timeout=3s --start-period=20s --retries=3 \
  CMD ["curl", "-fsS", "-o", "/dev/null", "http://127.0.0.1:8222/healthz"]
ENTRYPOINT ["nats-server", "-c", "/etc/nats/nats.conf"]
