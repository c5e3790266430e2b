# fleetmem-server image (docs/deployment.md).
#
#   docker build -f docker/server.Dockerfile -t fleetmem/server:0.1.0 .
#   docker run -v fleetmem-data:/var/lib/fleetmem -p 50051:50051 -p 8080:8080 \
#     -v ./server.textproto:/etc/fleetmem/server.textproto:ro fleetmem/server:0.1.0
#
# Build context: the project root. BASE_IMAGE is debian:bookworm-slim; the
# Docker tests build on a local debootstrap of bookworm instead
# (tests/docker/base_image.sh) because their engine cannot pull.
ARG BASE_IMAGE=debian:bookworm-slim

# Build stage: the toolchain and -dev packages (the same first lines as
# robot.Dockerfile, so the two images share this stage's layers).
FROM ${BASE_IMAGE} AS build
RUN apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y \
      -qq --no-install-recommends cmake ninja-build g++ pkg-config \
      libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev protobuf-compiler \
      libabsl-dev librocksdb-dev libflann-dev liblz4-dev libeigen3-dev \
      libopencv-dev libsodium-dev libcli11-dev libbz2-dev libtorch-dev \
      libcpp-httplib-dev prometheus-cpp-dev golang-github-gogo-googleapis-dev \
      libssl-dev libceres-dev libhnswlib-dev libxxhash-dev libnats-dev \
      >/dev/null \
 && rm -rf /var/lib/apt/lists/*
WORKDIR /src
COPY CMakeLists.txt ./
COPY cmake cmake
COPY proto proto
COPY services services
COPY clients clients
COPY tools tools
# -O2 as in the measured RelWithDebInfo build, without its debug info: the
# binaries are stripped, so -g would only cost compile time.
RUN cmake -S . -B /build -G Ninja -DCMAKE_BUILD_TYPE=Release \
      -DCMAKE_CXX_FLAGS_RELEASE="-O2 -DNDEBUG" \
      -DFLEETMEM_BUILD_TESTS=OFF -DFLEETMEM_BUILD_BENCH=OFF \
      -DFLEETMEM_BUILD_DEMO=OFF >/dev/null \
 && cmake --build /build --target fleetmem-server fleetmem fleetmem-credential \
      fleetmem-robot \
 && strip --strip-unneeded /build/bin/*

# Runtime stage: the server, the CLI and fleetmem-credential with only the
# shared libraries they load.
FROM ${BASE_IMAGE}
RUN apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y \
      -qq --no-install-recommends ca-certificates curl libgrpc++1.51 \
      libprotobuf32 libabsl20220623 libsodium23 libprometheus-cpp-core1.0 \
      libcpp-httplib0.11 libssl3 libbz2-1.0 liblz4-1 libsnappy1v5 libzstd1 libxxhash0 \
      libnats3.4 \
      >/dev/null \
 && rm -rf /var/lib/apt/lists/* \
 && useradd --system --uid 10001 --user-group --home-dir /var/lib/fleetmem \
      --shell /usr/sbin/nologin fleetmem \
 && install -d -o fleetmem -g fleetmem -m 0750 /var/lib/fleetmem \
 && install -d -m 0755 /etc/fleetmem
COPY --from=build /build/bin/fleetmem-server /build/bin/fleetmem \
     /build/bin/fleetmem-credential /usr/local/bin/
COPY docker/server.textproto /etc/fleetmem/server.textproto
COPY docker/healthcheck.sh /usr/local/bin/fleetmem-healthcheck
USER fleetmem
VOLUME /var/lib/fleetmem
# gRPC and HTTP (REST, /metrics, /healthz, /readyz, dashboard).
EXPOSE 50051 8080
# /healthz on the HTTP port (https when the config turns TLS on; see
# docker/healthcheck.sh).
HEALTHCHECK --interval=10s --timeout=3s --start-period=30s --retries=3 \
  CMD ["fleetmem-healthcheck"]
# glibc's malloc asks for transparent huge pages for its larger blocks
# (where the host's THP mode is `madvise`, Debian's default, or `always`):
# fewer page faults while a start builds its memory, the graph and the
# maps; a restart of 1,000,000 traces opened its port 0.69-0.81x as late
# for 1-2 MiB more resident (docs/performance.md, tenth round of issue 49).
ENV GLIBC_TUNABLES=glibc.malloc.hugetlb=1
ENTRYPOINT ["fleetmem-server"]
CMD ["--config", "/etc/fleetmem/server.textproto"]
ARG FLEETMEM_VERSION=0.1.0
LABEL org.opencontainers.image.title="fleetmem-server" \
      org.opencontainers.image.version="${FLEETMEM_VERSION}" \
      org.opencontainers.image.source="https://github.com/fleetmem/fleetmem"
ENV FLEETMEM_IMAGE_VERSION=${FLEETMEM_VERSION}
