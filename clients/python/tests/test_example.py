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


@pytest.mark.skipif(not os.path.isdir(os.path.join(DATA, "nordland")), reason="no Nordland data")
def test_the_example_runs_again_without_measuring_old_codes(server):
    """Issue 48: a second run into the same fleets uploaded only duplicates
    and reported model v2 against the first run's codes. Now a named fleet
    that exists stops the run (exit 2, nothing uploaded), --replace starts
    it afresh, and the default makes new fleets each run."""
    def run(*extra):
        return subprocess.run([sys.executable, str(REPO / "examples" / "python" / "nordland_robot.py"),
                               "--server", server.address, "--data-root", DATA, "--stride", "40",
                               "--steps", "5", "--replay", "50", *extra],
                              capture_output=True, text=True, timeout=120)
    first = run("--fleet", "again")
    assert first.returncode == 0, first.stderr
    second = run("--fleet", "again")
    assert second.returncode == 2, second.stdout
    assert "again-v1, again-v2 exist already" in second.stderr
    replaced = run("--fleet", "again", "--replace")
    assert replaced.returncode == 0, replaced.stderr
    assert "deleted fleet again-v1" in replaced.stdout
    assert run().returncode == 0
