"""ReplayDataset: the fleet's replay as a stream of batches for a training loop.

Reverb's users sample a replay table as a dataset; this is the same for a
fleet's memory. Each batch is one SampleReplay draw (distinct traces with
weight gamma^n * R, Eq. 18; the draw raises each trace's n, so later batches
favour traces replayed less), asked for as columns (one float32 block of
codes) and decoded into a fleetmem.Traces of numpy arrays. A thread keeps
`prefetch` batches ready, so the next draw's round trip overlaps the
caller's work on the current one. No torch dependency: a plain loop uses it
as is, and so does torch.utils.data.DataLoader (an IterableDataset needs
only __iter__; pass batch_size=None, as the batches are made here).

    dataset = fleetmem.ReplayDataset(fm, "f1", "robot-1", batch_size=256)
    for batch in dataset:            # fleetmem.Traces: codes (256, d), ...
        train_step(batch.codes, batch.places)

Rate limit (Reverb's SampleToInsertRatio), optional: with
samples_per_insert=R a batch is drawn only while the traces this dataset
has drawn stay within R x (the traces the fleet has received) +
error_buffer, and none before the fleet has received min_size_to_sample;
otherwise the dataset waits (polling the fleet's stats every
poll_seconds) until robots upload more. Unlike Reverb it never holds up the
robots' uploads: robots write at the pace they drive.
"""

from __future__ import annotations

import itertools
import queue
import threading
import time
from typing import Iterator, Optional

from fleetmem.client import Client, FleetMemError, Traces, _count, _text


class ReplayDataset:
    """An iterable of fleetmem.Traces batches drawn from a fleet's replay.

    client: a fleetmem.Client; fleet, robot_id: the fleet and the robot
    whose refreshes these are (SampleReplay's robot_id: its rights and its
    replay counter). batch_size: traces per draw (at most the server's
    max_sample_count). batches: how many batches an iteration yields (None:
    until close()). prefetch: batches kept ready by the thread (0: none, each
    drawn when asked for). robot_ids / domains: SampleReplay's filters.
    samples_per_insert, min_size_to_sample, error_buffer, poll_seconds,
    max_wait_seconds: the rate limit (module doc); a wait longer than
    max_wait_seconds raises TimeoutError (None: wait as long as it takes).
    Errors of the server are raised from the iteration as FleetMemError.
    """

    def __init__(self, client: Client, fleet: str, robot_id: str, *, batch_size: int = 256,
                 batches: Optional[int] = None, prefetch: int = 2, robot_ids=None, domains=None,
                 samples_per_insert: Optional[float] = None, min_size_to_sample: int = 1,
                 error_buffer: float = 0.0, poll_seconds: float = 0.5,
                 max_wait_seconds: Optional[float] = None):
        self._client = client
        self._fleet = _text("fleet", fleet)
        self._robot_id = _text("robot_id", robot_id)
        self._batch_size = _count("batch_size", batch_size)
        self._batches = None if batches is None else _count("batches", batches, low=0)
        self._prefetch = _count("prefetch", prefetch, low=0)
        self._filters = dict(robot_ids=robot_ids, domains=domains)
        if samples_per_insert is not None and not samples_per_insert > 0:
            raise ValueError(f"samples_per_insert: want a number > 0, got {samples_per_insert!r}")
        self._ratio = samples_per_insert
        self._min_size = _count("min_size_to_sample", min_size_to_sample, low=0)
        if error_buffer < 0:
            raise ValueError(f"error_buffer: want >= 0, got {error_buffer!r}")
        self._buffer = float(error_buffer)
        self._poll = float(poll_seconds)
        self._max_wait = max_wait_seconds
        self._closed = threading.Event()
        self.sampled = 0      # traces drawn so far by this dataset
        self.inserted = 0     # the fleet's received traces, as last polled
        self.waited_seconds = 0.0  # time spent held by the rate limit

    def close(self) -> None:
        """Ends every iteration (from any thread), after its current draw."""
        self._closed.set()

    def _received(self) -> int:
        stats = self._client.stats(self._fleet)
        return sum(robot.received for robot in stats.robots)

    def _admit(self) -> None:
        """Waits until the rate limit lets the next batch be drawn."""
        if self._ratio is None and self._min_size <= 1:
            return
        started = time.monotonic()
        while not self._closed.is_set():
            try:
                self.inserted = self._received()
            except FleetMemError as error:
                if error.status != "NOT_FOUND":  # a fleet nothing reached yet: 0
                    raise
                self.inserted = 0
            enough = self.inserted >= self._min_size
            within = (self._ratio is None or
                      self.sampled + self._batch_size <= self._ratio * self.inserted + self._buffer)
            if enough and within:
                break
            if self._max_wait is not None and time.monotonic() - started > self._max_wait:
                raise TimeoutError(
                    f"ReplayDataset: rate limit held the next batch for {self._max_wait} s "
                    f"(drawn {self.sampled}, fleet received {self.inserted}, "
                    f"samples_per_insert {self._ratio}, min_size_to_sample {self._min_size})")
            self._closed.wait(self._poll)
        self.waited_seconds += time.monotonic() - started

    def _draw(self) -> Traces:
        self._admit()
        batch = self._client.sample_replay(self._fleet, self._robot_id, self._batch_size,
                                           **self._filters)
        self.sampled += len(batch)
        return batch

    def _count_left(self):
        return itertools.count() if self._batches is None else range(self._batches)

    def __iter__(self) -> Iterator[Traces]:
        if self._prefetch == 0:
            for _ in self._count_left():
                if self._closed.is_set():
                    return
                yield self._draw()
            return
        ready: queue.Queue = queue.Queue(maxsize=self._prefetch)
        stop = threading.Event()
        end = object()

        def fill():
            try:
                for _ in self._count_left():
                    if stop.is_set() or self._closed.is_set():
                        break
                    item = self._draw()
                    while not stop.is_set():
                        try:
                            ready.put(item, timeout=0.1)
                            break
                        except queue.Full:
                            continue
            except BaseException as error:  # raised in the caller's thread
                ready.put(error)
                return
            ready.put(end)

        thread = threading.Thread(target=fill, name="fleetmem-replay", daemon=True)
        thread.start()
        try:
            while True:
                try:
                    item = ready.get(timeout=0.1)
                except queue.Empty:
                    if self._closed.is_set() and not thread.is_alive():
                        return
                    continue
                if item is end:
                    return
                if isinstance(item, BaseException):
                    raise item
                yield item
        finally:
            stop.set()
            thread.join(timeout=5)
