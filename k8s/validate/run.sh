#!/usr/bin/env bash
# Runs the manifest validation (manifests_test.go): `make test-k8s` and the
# ctest fleetmem_k8s_manifests_test. Needs Go >= 1.26 (k8s.io/api v0.37) and
# the Go module proxy for the first download; exits 77 (skipped) without a
# Go that new.
set -euo pipefail
cd "$(dirname "$0")"
export PATH="$PATH:/usr/local/go/bin"
if ! command -v go >/dev/null; then
  echo "k8s/validate: SKIPPED: no Go toolchain (go >= 1.26 needed)"
  exit 77
fi
version=$(go env GOVERSION | sed 's/^go//')
if [ "$(printf '%s\n1.26\n' "$version" | sort -V | head -1)" != 1.26 ]; then
  echo "k8s/validate: SKIPPED: go $version is older than 1.26"
  exit 77
fi
exec env GOTOOLCHAIN=local go test -count=1 -v ./...
