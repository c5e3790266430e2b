"""Fixtures: the real fleetmem-server binary of this build, as a child.

FLEETMEM_BIN_DIR names the build's bin folder (default: build/bin of the
checkout). The server is started like tools/process/server.sh does: it is
ready when its --ready-file appears, never after a fixed wait.
"""

import os
import pathlib
import signal
import socket
import subprocess
import time

import pytest

REPO = pathlib.Path(__file__).resolve().parents[3]
BIN_DIR = pathlib.Path(os.environ.get("FLEETMEM_BIN_DIR", REPO / "build" / "bin"))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """fleetmem-server on fixed ports (so that a restart keeps them)."""

    def __init__(self, data_dir: pathlib.Path, *extra: str):
        self.data_dir = data_dir
        self.grpc_port, self.http_port = free_port(), free_port()
        self.address = f"127.0.0.1:{self.grpc_port}"
        self.http = f"http://127.0.0.1:{self.http_port}"
        self.extra = list(extra)
        self.process = None
        self.started = False
        self.log = data_dir.parent / f"{data_dir.name}.log"

    def start(self, timeout: float = 60.0) -> "Server":
        # A port free_port() found may be taken by another test (ctest runs
        # two at once) before the server binds it: a first start that cannot
        # listen tries new ports; a restart keeps its own.
        for attempt in range(5):
            logged = self.log.stat().st_size if self.log.exists() else 0
            if self._launch(timeout):
                self.started = True
                return self
            lost_port = "cannot listen" in self.log.read_text()[logged:]
            if self.started or not lost_port:
                break
            self.grpc_port, self.http_port = free_port(), free_port()
            self.address = f"127.0.0.1:{self.grpc_port}"
            self.http = f"http://127.0.0.1:{self.http_port}"
        raise RuntimeError(f"fleetmem-server not ready; log:\n{self.log.read_text()[-3000:]}")

    def _launch(self, timeout: float) -> bool:
        """Starts the server; True once it is ready, False once it exited or timed out."""
        ready = self.data_dir.parent / f"{self.data_dir.name}.ready"
        ready.unlink(missing_ok=True)
        with open(self.log, "ab") as log:
            self.process = subprocess.Popen(
                [str(BIN_DIR / "fleetmem-server"), "--listen", self.address,
                 "--data-dir", str(self.data_dir), "--http-listen", f"127.0.0.1:{self.http_port}",
                 "--ready-file", str(ready)] + self.extra, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout
        while not ready.exists():
            if self.process.poll() is not None or time.monotonic() > deadline:
                if self.process.poll() is None:
                    self.process.kill()
                self.process.wait()
                return False
            time.sleep(0.02)
        return True

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            assert self.process.wait(timeout=60) == 0, self.log.read_text()[-3000:]
        self.process = None


@pytest.fixture
def server(tmp_path):
    s = Server(tmp_path / "data").start()
    yield s
    s.stop()


@pytest.fixture
def cli():
    """Runs build/bin/fleetmem with arguments; returns its stdout."""
    def run(*args: str) -> str:
        done = subprocess.run([str(BIN_DIR / "fleetmem"), *args], capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        return done.stdout
    return run
