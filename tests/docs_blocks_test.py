#!/usr/bin/env python3
"""README.md's blocks run as written (issue 48: a doc can no longer drift),
and the self-contained Python blocks of docs/python.md and docs/api.md.

The tour (a server, the CLI, REST, a snapshot, an export), the Python block
(a venv, pip install of clients/python, upload, query, replay) and the
secured example (docker/make-secrets.sh, a server with credentials and TLS,
a robot's upload, an admin's stats) are taken from README.md and run by
bash -euo pipefail, each command as the README has it, with three things
changed so that the test runs beside others: /tmp/ is a temporary
directory of the test's own, the ports are free ones, and build/ is the
build under test. Background servers are stopped at the end.

  docs_blocks_test.py BUILD_DIR SOURCE_DIR
"""

import os
import pathlib
import re
import socket
import subprocess
import sys
import tempfile

build = pathlib.Path(sys.argv[1]).resolve()
source = pathlib.Path(sys.argv[2]).resolve()
readme = (source / "README.md").read_text()
blocks = re.findall(r"```sh\n(.*?)```", readme, re.S)


def block_with(marker):
    found = [b for b in blocks if marker in b]
    assert len(found) == 1, (marker, len(found))
    return found[0]


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


work = pathlib.Path(tempfile.mkdtemp(prefix="fleetmem-docs-"))
ports = {"50051": free_port(), "8080": free_port(), "50061": free_port()}


def as_here(text):
    text = text.replace("/tmp/", f"{work}/").replace("build/bin/", f"{build}/bin/")
    text = text.replace(".venv", f"{work}/venv")
    for port, free in ports.items():
        text = re.sub(rf"(?<=:){port}\b", str(free), text)
    return text


def run(name, script):
    path = work / f"{name}.sh"
    path.write_text("set -euo pipefail\ntrap 'kill $(jobs -p) 2>/dev/null || true' EXIT\n" + script)
    done = subprocess.run(["bash", str(path)], cwd=source, capture_output=True, text=True,
                          timeout=600,
                          env=dict(os.environ, FLEETMEM_SERVER=f"127.0.0.1:{ports['50051']}"))
    print(f"---- {name}: exit {done.returncode}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}")
    return done


# docs/python.md's first Python block and docs/api.md's encoder migration,
# against the tour's server, with the venv the README's block made.
docs = {name: (source / "docs" / name).read_text() for name in ("python.md", "api.md")}
python_blocks = [re.findall(r"```python\n(.*?)```", docs["python.md"], re.S)[0],
                 next(b for b in re.findall(r"```python\n(.*?)```", docs["api.md"], re.S)
                      if "switch_alias" in b)]
more = "".join(f".venv/bin/python - <<'PY'\n{block}PY\n" for block in python_blocks)
tour = run("tour-and-python",
           as_here(block_with("fleetmem gen-traces --robots 2") + block_with("pip install") + more))
assert tour.returncode == 0, "the tour or the Python block failed"
assert "consolidated traces" in tour.stdout and "(64, 256)" in tour.stdout, tour.stdout[-2000:]
assert tour.stdout.count("(256, 256)") == 4, "ReplayDataset's four batches"
assert (work / "fm" / "snapshots" / "backup-1" / "SNAPSHOT").exists()
assert (work / "f1" / "codes.npy").exists()

secured = run("secured", as_here(block_with("make-secrets.sh /tmp/fm-secrets")))
assert secured.returncode == 0, "the secured example failed"
assert re.search(r"accepted\s+300", secured.stdout), secured.stdout
assert re.search(r"traces\s+\d+", secured.stdout), secured.stdout
print("README blocks ran as written")
subprocess.run(["rm", "-rf", str(work)])
