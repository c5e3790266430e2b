#!/usr/bin/env bash
# Installs the fleetmem Python package into a venv on Debian's Python and
# its python3-grpcio/-protobuf/-numpy (--system-site-packages), offline: the
# README's two lines, for the tests, benchmarks and examples.
#   clients/python/install_venv.sh VENV_DIR
# Reinstalls the package each time (it is built from the checkout's proto).
set -euo pipefail
venv=${1:?usage: install_venv.sh VENV_DIR}
here=$(cd "$(dirname "$0")" && pwd)
if [ ! -x "$venv/bin/python" ]; then
  /usr/bin/python3 -m venv --system-site-packages "$venv"
fi
"$venv/bin/pip" install --quiet --no-build-isolation --no-index --no-deps \
  --force-reinstall "$here" >&2
echo "$venv/bin/python"
