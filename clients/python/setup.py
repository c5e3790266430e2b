"""Build step of the fleetmem package: generates the gRPC stubs from proto/.

setuptools runs this for `pip install ./clients/python`. The stubs go into
the built package only (never into the source tree), so they are always
those of the checkout's proto:

  fleetmem/v1/memory_pb2.py, memory_pb2_grpc.py   fleetmem.v1 (protoc's own
      import path: the package is named like the proto package)
  fleetmem/_vendor/google/api/{annotations,http}_pb2.py   the HTTP
      annotations memory.proto imports. Debian has no Python package of
      them, so they are generated from golang-github-gogo-googleapis-dev's
      copy and memory_pb2 imports them from here.

Environment: FLEETMEM_PROTO_DIR (default: ../../proto beside this file),
FLEETMEM_GOOGLEAPIS_DIR (default: Debian's gogo googleapis folder), PROTOC
and GRPC_PYTHON_PLUGIN (default: found on PATH).
"""

import os
import pathlib
import re
import shutil
import subprocess
import tempfile

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = pathlib.Path(__file__).resolve().parent
PROTO_DIR = pathlib.Path(os.environ.get("FLEETMEM_PROTO_DIR", HERE.parent.parent / "proto"))
GOOGLEAPIS_DIR = pathlib.Path(
    os.environ.get("FLEETMEM_GOOGLEAPIS_DIR", "/usr/share/gocode/src/github.com/gogo/googleapis"))


def _tool(env, name, package):
    path = os.environ.get(env) or shutil.which(name)
    if not path:
        raise SystemExit(f"fleetmem: {name} not found; install Debian's {package} (make deps does)")
    return path


def generate_stubs(package_root: pathlib.Path) -> None:
    """Writes the generated modules under package_root (the built 'fleetmem')."""
    memory_proto = PROTO_DIR / "fleetmem" / "v1" / "memory.proto"
    annotations = GOOGLEAPIS_DIR / "google" / "api" / "annotations.proto"
    for path, package in ((memory_proto, "a fleetmem checkout (FLEETMEM_PROTO_DIR)"),
                          (annotations, "golang-github-gogo-googleapis-dev")):
        if not path.is_file():
            raise SystemExit(f"fleetmem: {path} not found: {package}")
    protoc = _tool("PROTOC", "protoc", "protobuf-compiler")
    plugin = _tool("GRPC_PYTHON_PLUGIN", "grpc_python_plugin", "protobuf-compiler-grpc")
    with tempfile.TemporaryDirectory() as out:
        subprocess.run([protoc, f"--proto_path={PROTO_DIR}", f"--proto_path={GOOGLEAPIS_DIR}",
                        f"--python_out={out}", f"--grpc_out={out}",
                        f"--plugin=protoc-gen-grpc={plugin}", str(memory_proto)], check=True)
        subprocess.run([protoc, f"--proto_path={GOOGLEAPIS_DIR}", f"--python_out={out}",
                        "google/api/annotations.proto", "google/api/http.proto"],
                       check=True, cwd=GOOGLEAPIS_DIR)
        out = pathlib.Path(out)
        targets = {
            out / "fleetmem/v1/memory_pb2.py": package_root / "v1/memory_pb2.py",
            out / "fleetmem/v1/memory_pb2_grpc.py": package_root / "v1/memory_pb2_grpc.py",
            out / "google/api/annotations_pb2.py": package_root / "_vendor/google/api/annotations_pb2.py",
            out / "google/api/http_pb2.py": package_root / "_vendor/google/api/http_pb2.py",
        }
        for source, target in targets.items():
            text = re.sub(r"^from google\.api import", "from fleetmem._vendor.google.api import",
                          source.read_text(), flags=re.M)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(text)
        for folder in ("v1", "_vendor", "_vendor/google", "_vendor/google/api"):
            init = package_root / folder / "__init__.py"
            if not init.exists():
                init.write_text('"""Generated from proto/ by setup.py; do not edit."""\n')


class BuildPyWithStubs(build_py):
    def run(self):
        super().run()
        generate_stubs(pathlib.Path(self.build_lib) / "fleetmem")


setup(cmdclass={"build_py": BuildPyWithStubs})
