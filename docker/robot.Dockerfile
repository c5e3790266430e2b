# fleetmem-robot image: one robot of a fleet (docs/robot.md,
# docs/deployment.md).
#
#   docker build -f docker/robot.Dockerfile -t fleetmem/robot:0.1.0 .
#   docker run -v robot-1:/var/lib/fleetmem-robot \
#     -v /data/nordland/summer:/recordings:ro fleetmem/robot:0.1.0 \
#     --server fleetmem-server:50051 --fleet nordland --robot-id robot-1 \
#     --source nordland:/recordings
#
# Build context: the project root. BASE_IMAGE is debian:bookworm-slim; the
# Docker tests build on a local debootstrap of bookworm instead
# (tests/docker/base_image.sh) because their engine cannot pull.
ARG BASE_IMAGE=debian:bookworm-slim

# Build stage: the toolchain and -dev packages (the same first lines as
# server.Dockerfile, so the two images share this stage's layers).
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

# Runtime stage: the agent with only the shared libraries it loads.
FROM ${BASE_IMAGE}
RUN apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y \
      -qq --no-install-recommends ca-certificates libgrpc++1.51 \
      libprotobuf32 libabsl20220623 libopencv-core406 libopencv-imgproc406 \
      libopencv-imgcodecs406 libopencv-objdetect406 libopencv-calib3d406 \
      libopencv-video406 libtorch1.13 libbz2-1.0 \
      liblz4-1 libsnappy1v5 libzstd1 libxxhash0 libgoogle-glog0v6 libcholmod3 \
      libcxsparse3 libatlas3-base >/dev/null \
 && rm -rf /var/lib/apt/lists/* \
 && useradd --system --uid 10002 --user-group \
      --home-dir /var/lib/fleetmem-robot --shell /usr/sbin/nologin robot \
 && install -d -o robot -g robot -m 0750 /var/lib/fleetmem-robot \
 && install -d -m 0755 /etc/fleetmem
COPY --from=build /build/bin/fleetmem-robot /usr/local/bin/
COPY docker/robot.toml /etc/fleetmem/robot.toml
COPY docker/healthcheck.sh /usr/local/bin/fleetmem-healthcheck
USER robot
# The upload queue, source position, seq counter and watch cursor: keep it
# across restarts or the robot starts over as a new one.
VOLUME /var/lib/fleetmem-robot
ENV FLEETMEM_HEALTH_STATUS_FILE=/var/lib/fleetmem-robot/status.json
# Healthy while the agent keeps rewriting its status file.
HEALTHCHECK --interval=15s --timeout=3s --start-period=60s --retries=3 \
  CMD ["fleetmem-healthcheck"]
ENTRYPOINT ["fleetmem-robot", "--config", "/etc/fleetmem/robot.toml"]
ARG FLEETMEM_VERSION=0.1.0
LABEL org.opencontainers.image.title="fleetmem-robot" \
      org.opencontainers.image.version="${FLEETMEM_VERSION}" \
      org.opencontainers.image.source="https://github.com/fleetmem/fleetmem"
ENV FLEETMEM_IMAGE_VERSION=${FLEETMEM_VERSION}
