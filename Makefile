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
  libsodium-dev libcli11-dev libbz2-dev openssl clang-14 libclang-rt-14-dev \
  libtorch-dev gnuplot-nox \
  libcpp-httplib-dev prometheus-cpp-dev golang-github-gogo-googleapis-dev \
  libssl-dev curl python3 python3-numpy prometheus chromium \
  python3-venv python3-pip python3-setuptools python3-wheel python3-grpcio \
  python3-protobuf python3-pytest python3-pil \
  debootstrap docker-compose libceres-dev libhnswlib-dev libfaiss-dev \
  libxxhash-dev nats-server libnats-dev python3-hnswlib

# ccache serves a fresh clone in another folder too: paths under the
# checkout are hashed relative to it, and the working directory is not
# hashed (debug info may then name the first clone's folder). A cache big
# enough for the three builds (normal, ASan, fuzz) of a few revisions.
export CCACHE_BASEDIR ?= $(CURDIR)
export CCACHE_NOHASHDIR ?= 1
export CCACHE_MAXSIZE ?= 20G

empty :=
space := $(empty) $(empty)
SUDO := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: all deps configure configure-asan build test test-slow test-asan test-tsan test-docker test-k8s test-cluster \
  fuzz soak crash robot-crash demo bench perf perf-scale format clean

SANITIZER_FLAGS_tsan := -fsanitize=thread -fno-omit-frame-pointer
# The sanitizer and fuzzer builds' optimisation and debug level (in place
# of RelWithDebInfo's -O2 -g): -O1, as the sanitizers' and libFuzzer's
# documentation advise, and line tables only (-g1; clang's
# -gline-tables-only), which is all a report's file:line needs. It compiles
# in half the time (memory_engine.cc under ASan: 26 s, against 54 s at
# -O2 -g), and the ASan build is most of CI's sanitizer stage.
SANITIZER_OPT := -O1 -g1 -DNDEBUG
# The tests that run under ThreadSanitizer: the pure core, the engine on the
# in-memory store and the in-memory store (GTEST_FILTER leaves out the
# RocksDB cases: Debian's RocksDB is not instrumented and its lock-free
# memtable reads as races; docs/reliability.md says what else cannot run).
# IndexSnapshotTest is single-threaded (nothing for TSan to order) and its
# graph churn, run after another such test, makes TSan report hnswlib's
# per-node lock-order cycle (the one tools/tsan/suppressions.txt explains)
# without stacks, which no suppression can match.
TSAN_TESTS := fleetmem_core_test fleetmem_engine_test fleetmem_storage_test

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

# RelWithDebInfo's optimisation, -O2 (the benchmarks and evaluations
# measure these binaries), with line tables only (-g1) instead of full debug
# info (-g): a report's file:line is all the tests and sanitizers need, and
# it compiles in about three quarters of the time (docs/testing.md). For
# a debugger's locals: make BUILD_TYPE=Debug, or RELEASE_FLAGS="-O2 -g".
RELEASE_FLAGS ?= -O2 -g1 -DNDEBUG
configure: deps
	@cmake -S . -B $(BUILD_DIR) -G Ninja -DCMAKE_BUILD_TYPE=$(BUILD_TYPE) \
	  -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="$(RELEASE_FLAGS)" >/dev/null

build: configure
	@cmake --build $(BUILD_DIR) -j $(JOBS)

# The tiers (docs/testing.md has what each protects and its times).
# `make test`: unit tests beside the code, integration tests against the
# real server binary, and a smoke run of every command and evaluation on a
# few inputs, checked against numbers computed independently: every test
# but the label "slow". About 10 minutes after the build on 2 cores.
test: build
	@cd $(BUILD_DIR) && ctest --output-on-failure -j $(JOBS) -LE slow $(CTEST_ARGS)

# `make test-slow`: the evaluations on the real data with their figures'
# claims, the Docker fleet and its faults, distributed mode in containers,
# the Kubernetes manifests (label "slow"; each holds both cores).
test-slow: build
	@cd $(BUILD_DIR) && ctest --output-on-failure -j $(JOBS) -L slow $(CTEST_ARGS)

# One instrumented build (build-asan/, clang) serves `make test-asan` and
# `make fuzz`: every file is compiled once with AddressSanitizer, UBSan and
# libFuzzer's coverage hooks (-fsanitize=fuzzer-no-link; in a test binary the
# sanitizer runtime's own no-op hooks take them), the tests' own files at
# -O0 (FLEETMEM_TEST_OPT), the libraries at SANITIZER_OPT. Two builds (gcc
# ASan for the tests, clang for the fuzzers) compiled most of the server
# twice: 8 of CI's minutes (docs/testing.md). Benchmarks and the demo are
# not built: no test runs them.
SANITIZE_FLAGS := -fsanitize=fuzzer-no-link,address,undefined \
  -fno-sanitize-recover=undefined -fno-omit-frame-pointer
configure-asan: deps
	@cmake -S . -B build-asan -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
	  -DCMAKE_C_COMPILER=clang-14 -DCMAKE_CXX_COMPILER=clang++-14 \
	  -DCMAKE_CXX_FLAGS="$(SANITIZE_FLAGS)" \
	  -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="$(SANITIZER_OPT)" \
	  -DCMAKE_EXE_LINKER_FLAGS="-fsanitize=address,undefined" \
	  -DFLEETMEM_BUILD_FUZZ=ON -DFLEETMEM_BUILD_BENCH=OFF \
	  -DFLEETMEM_BUILD_DEMO=OFF -DFLEETMEM_TEST_OPT=-O0 >/dev/null

# `make test`'s tests under AddressSanitizer + UndefinedBehaviorSanitizer
# (the integration tests run the instrumented server), but the evaluations'
# smoke runs (label "eval": compute jobs in an uninstrumented libtorch;
# their code paths run in the GPL, VO and robot tests here). Builds the
# fuzzers too, so that `make fuzz` after it only runs them.
test-asan: configure-asan
	@cmake --build build-asan -j $(JOBS)
	@cd build-asan && ASAN_OPTIONS=detect_leaks=1:abort_on_error=1 \
	  UBSAN_OPTIONS=print_stacktrace=1:halt_on_error=1 \
	  ctest --output-on-failure -j $(JOBS) -LE 'slow|eval' $(CTEST_ARGS)

# The containers (tests/docker/fault_tests.py, also in `make test-slow`):
# builds the images from docker/*.Dockerfile on a local debootstrap of
# bookworm (over the host's build where that is sound), runs the compose
# fleet and every fault, prints the table (docs/deployment.md).
test-docker: build
	@tests/docker/fault_tests.py

# Distributed mode in containers (docker/cluster.compose.yaml): a replica
# killed, a NATS server killed, a replica partitioned, under load from this
# host; prints the recovery times and 0 lost, 0 duplicated
# (tests/docker/cluster_fault_tests.py; docs/distributed.md; also in
# `make test-slow`).
test-cluster: build
	@tests/docker/cluster_fault_tests.py

# The Kubernetes manifests (k8s/) against the real API types (Go, k8s.io/api;
# also in `make test-slow`).
test-k8s:
	@k8s/validate/run.sh

# Core, engine and storage tests under ThreadSanitizer (build-tsan/).
test-tsan: deps
	@cmake -S . -B build-tsan -G Ninja -DCMAKE_BUILD_TYPE=RelWithDebInfo \
	  -DCMAKE_CXX_FLAGS="$(SANITIZER_FLAGS_tsan)" \
	  -DCMAKE_CXX_FLAGS_RELWITHDEBINFO="$(SANITIZER_OPT)" \
	  -DCMAKE_EXE_LINKER_FLAGS="$(SANITIZER_FLAGS_tsan)" \
	  -DFLEETMEM_BUILD_BENCH=OFF -DFLEETMEM_BUILD_DEMO=OFF \
	  -DFLEETMEM_TSAN_ABSL_ANNOTATIONS=ON >/dev/null
	@cmake --build build-tsan -j $(JOBS) --target $(TSAN_TESTS)
	@cd build-tsan && TSAN_OPTIONS="halt_on_error=1 suppressions=$(CURDIR)/tools/tsan/suppressions.txt" \
	  GTEST_FILTER='-RocksDb*:*/RocksDb:Kill/*:IndexSnapshotTest.*' \
	  ctest --output-on-failure -j $(JOBS) -R '^($(subst $(space),|,$(TSAN_TESTS)))$$' $(CTEST_ARGS)

# The libFuzzer harnesses (the instrumented build of test-asan, which
# compiles them), FUZZ_SECONDS each from their seed corpora in the tree.
FUZZ_SECONDS ?= 20
fuzz: configure-asan
	@cmake --build build-asan -j $(JOBS) --target fleetmem_fuzzers
	@tools/fuzz/run_fuzzers.sh build-asan $(FUZZ_SECONDS)

# 20 SIGKILLs of the server under concurrent uploads; every acknowledged
# trace is checked after each restart (docs/reliability.md).
CRASH_TRIALS ?= 20
crash: build
	@tools/load/crash_trials.sh $(BUILD_DIR) $(CRASH_TRIALS)

# Robot crash trials: a camera and a laser robot on the real data while the
# server and the robots are SIGKILLed at random moments (10 trials x 4 kills).
ROBOT_CRASH_TRIALS ?= 10
robot-crash: build
	@tools/load/robot_crash_trials.sh $(BUILD_DIR) $(ROBOT_CRASH_TRIALS)

# The server at half its measured peak load for SOAK_SECONDS (one hour by
# default; e.g. make soak SOAK_SECONDS=300 SOAK_INTERVAL=15).
SOAK_SECONDS ?= 3600
SOAK_INTERVAL ?= 60
soak: build
	@tools/load/soak.sh $(BUILD_DIR) $(SOAK_SECONDS) $(SOAK_INTERVAL) $(BUILD_DIR)/soak.csv

# Starts the server on an embedded RocksDB under .demo/ and runs a
# three-robot fleet on the real Nordland data; ends with a results table.
demo: build
	@tools/demo/run_demo.sh $(BUILD_DIR)

# Benchmarks with their peers measured in the same run (docs/*-benchmark.md).
bench: build
	@$(BUILD_DIR)/bin/fleetmem_index_bench --benchmark_min_time=0.2
	@$(BUILD_DIR)/bin/fleetmem_forgetting_bench --benchmark_min_time=0.2

# docs/performance.md: every figure and plot, into docs/perf/ (about 75 min
# on the 2-core reference machine; run nothing else meanwhile).
PERF_DIR ?= docs/perf
PERF_SIZES ?= 5000 20000 100000 200000 1000000
perf: build
	@mkdir -p $(PERF_DIR)
	$(BUILD_DIR)/bin/fleetmem_memory_scale_bench --benchmark_min_time=0.5 \
	  --benchmark_out=$(PERF_DIR)/memory_scale.json --benchmark_out_format=json
	$(BUILD_DIR)/bin/fleetmem_ann_bench --benchmark_min_time=1 \
	  --benchmark_out=$(PERF_DIR)/ann.json --benchmark_out_format=json
	$(BUILD_DIR)/bin/fleetmem_ann_bench --benchmark_min_time=1 \
	  --benchmark_filter='BM_Query/(0|5|6)/(20000|50000|1000000)/0|BM_Query/0/(2000|5000|10000)/0' \
	  --benchmark_out=$(PERF_DIR)/ann_exact.json --benchmark_out_format=json
	bench/load_bench.sh $(BUILD_DIR) $(PERF_DIR)/load.csv $(PERF_DIR)/query.csv \
	  >$(PERF_DIR)/load.txt && cat $(PERF_DIR)/load.txt
	bench/server_scale.sh $(BUILD_DIR) $(PERF_DIR)/server_scale.csv $(PERF_SIZES)
	bench/restart_bench.sh $(BUILD_DIR) 1000000 >$(PERF_DIR)/restart.txt && \
	  cat $(PERF_DIR)/restart.txt
	bench/ack_streams_bench.sh $(BUILD_DIR) $(PERF_DIR)/ack_streams.csv 1 8 64
	bench/import_bench.sh $(BUILD_DIR) $(PERF_DIR)/import.csv 100000
	bench/scale_fleet.sh $(BUILD_DIR) 1000000 $(PERF_DIR)/scale_fleet_1m.csv
	$(BUILD_DIR)/bin/fleetmem_graph_bench --size 100000 \
	  --kinds hnswlib,float,int8,int8-file --out $(PERF_DIR)/graph.csv
	/usr/bin/python3 bench/quantization_choice.py 100000 \
	  >$(PERF_DIR)/quantization_choice.csv
	$(BUILD_DIR)/bin/fleetmem_row_read_bench --benchmark_min_time=2 \
	  --benchmark_out=$(PERF_DIR)/row_read.json --benchmark_out_format=json
	bench/plot_perf.py $(PERF_DIR)

# Issue 49's fleet of ten million traces (bench/scale_fleet.sh: about 50 GB
# of free disk and an hour on the 2-core machine; `make perf` runs it at
# 1,000,000).
SCALE_TRACES ?= 10000000
perf-scale: build
	@mkdir -p $(PERF_DIR)
	bench/scale_fleet.sh $(BUILD_DIR) $(SCALE_TRACES) \
	  $(PERF_DIR)/scale_fleet_$(SCALE_TRACES).csv

CLANG_FORMAT ?= $(shell command -v clang-format || command -v clang-format-14)
format:
	@git ls-files '*.h' '*.cc' | xargs $(CLANG_FORMAT) -i

clean:
	rm -rf $(BUILD_DIR) build-asan build-tsan .demo
