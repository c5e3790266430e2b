"""examples/python/nordland_robot.py runs end to end on the real data."""

import os
import subprocess
import sys

import pytest

from conftest import REPO

DATA = os.environ.get("FLEETMEM_DATA_DIR", str(REPO.parent / "shared" / "data"))


@pytest.mark.skipif(not os.path.isdir(os.path.join(DATA, "nordland")), reason="no Nordland data")
def test_the_python_robot_example(server):
    done = subprocess.run([sys.executable, str(REPO / "examples" / "python" / "nordland_robot.py"),
                           "--server", server.address, "--data-root", DATA, "--steps", "50"],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert any("model v1:" in line for line in lines) and any("model v2:" in line for line in lines), done.stdout
