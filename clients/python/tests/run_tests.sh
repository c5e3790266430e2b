#!/usr/bin/env bash
# ctest's fleetmem_python_client_test: installs the package into
# BUILD/python-venv (clients/python/install_venv.sh: the README's lines) and
# runs its pytest suite against BUILD/bin/fleetmem-server.
set -euo pipefail
build=${1:?usage: run_tests.sh BUILD_DIR}
here=$(cd "$(dirname "$0")" && pwd)
python=$("$here/../install_venv.sh" "$build/python-venv")
cd "$here"
FLEETMEM_BIN_DIR="$build/bin" exec "$python" -m pytest -q -p no:cacheprovider \
  --basetemp="$build/python-tests" .
