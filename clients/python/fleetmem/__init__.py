"""fleetmem: the shared lifelong place memory of a robot fleet, from Python.

    import numpy as np, fleetmem
    with fleetmem.Client("127.0.0.1:50051") as fm:
        fm.upload("f1", codes, places, rewards, robot_id="robot-1", seqs=np.arange(len(codes)))
        matches = fm.query_place("f1", codes[0], k=5)
        replay = fm.sample_replay("f1", "robot-1", 64)   # fleetmem.Traces (arrays)
        for batch in fleetmem.ReplayDataset(fm, "f1", "robot-1", batch_size=256, batches=10):
            ...                                          # a training loop's batches

docs/python.md has the API and the example robot.
"""

import csv as _csv
import pathlib as _pathlib

import numpy as _np

from fleetmem.client import (Client, DuplicateUploadWarning, FleetMemError, ImportResult, Matches,
                             Traces, UploadResult, Watch)
from fleetmem.replay import ReplayDataset
from fleetmem.v1 import memory_pb2 as pb

__all__ = ["Client", "DuplicateUploadWarning", "FleetMemError", "ImportResult", "ReplayDataset", "Matches", "Traces", "UploadResult", "Watch", "load_export", "pb"]
__version__ = "0.1.0"


def load_export(directory) -> Traces:
    """Traces from the files `fleetmem export --out DIR` writes (codes.npy,
    places.npy, metadata.csv)."""
    directory = _pathlib.Path(directory)
    codes = _np.load(directory / "codes.npy")
    places = _np.load(directory / "places.npy")
    with open(directory / "metadata.csv", newline="", encoding="utf-8") as f:
        rows = list(_csv.DictReader(f))
    if not len(rows) == len(codes) == len(places):
        raise ValueError(f"{directory}: {len(codes)} codes, {len(places)} places, {len(rows)} metadata rows")
    column = lambda name, dtype: _np.array([r[name] for r in rows], dtype=dtype)  # noqa: E731
    return Traces(codes=codes.astype(_np.float32, copy=False), places=places,
                  rewards=column("reward", _np.float32), seqs=column("seq", _np.uint64),
                  cluster_ids=column("cluster_id", _np.uint64),
                  replay_counts=column("replay_count", _np.uint32),
                  timestamps_ns=column("timestamp_ns", _np.int64),
                  robot_ids=[r["robot_id"] for r in rows], domains=[r["domain"] for r in rows])
