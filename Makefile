# fleetmem — thin wrapper over CMake. `make demo` and `make test` work on a
# fresh Debian bookworm machine: both install what is missing first.
BUILD_DIR ?= build
BUILD_TYPE ?= RelWithDebInfo
JOBS ?= $(shell nproc)
CTEST_ARGS ?=

# Debian packages the build, tests and demo need.
DEB_PACKAGES := cmake ninja-build ccache g++ pkg-config git \
  libgrpc++-dev protobuf-compiler-grpc libprotobuf-dev protobuf-compiler \
  libabsl-dev librocksdb-dev libflann-dev liblz4-dev libeigen3-dev \
  libopencv-dev libgtest-dev libgmock-dev libbenchmark-dev \
  libsodium-dev libcli11-dev openssl

SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: all deps configure build test demo bench format clean

all: build

# Installs the Debian packages that are missing (idempotent: a no-op when all
# are present).
deps:
	@missing=""; for p in $(DEB_PACKAGES); do \
	  dpkg-query -W -f='$${Status}' $$p 2>/dev/null | grep -q "ok installed" || missing="$$missing $$p"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "deps: installing$$missing"; \
	  $(SUDO) apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $(SUDO) apt-get install -y -qq --no-install-recommends $$missing; \
	else echo "deps: all Debian packages present"; fi

configure: deps
	@cmake -S . -B $(BUILD_DIR) -G Ninja -DCMAKE_BUILD_TYPE=$(BUILD_TYPE) >/dev/null

build: configure
	@cmake --build $(BUILD_DIR) -j $(JOBS)

# Every test: unit tests beside the code and the integration tests that start
# the real server binary.
test: build
	@cd $(BUILD_DIR) && ctest --output-on-failure -j $(JOBS) $(CTEST_ARGS)

# Starts the server on an embedded RocksDB under .demo/ and runs a
# three-robot fleet on the real Nordland data; ends with a results table.
demo: build
	@tools/demo/run_demo.sh $(BUILD_DIR)

# Benchmarks with their peers measured in the same run (docs/*-benchmark.md).
bench: build
	@$(BUILD_DIR)/bin/fleetmem_index_bench --benchmark_min_time=0.2
	@$(BUILD_DIR)/bin/fleetmem_forgetting_bench --benchmark_min_time=0.2

format:
	@git ls-files '*.h' '*.cc' | xargs clang-format -i

clean:
	rm -rf $(BUILD_DIR) .demo
