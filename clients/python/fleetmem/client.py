"""fleetmem.Client: the fleet's shared place memory from Python.

Every call of a Client is safe to repeat and is retried, like the C++
client's (clients/cpp/fleetmem_client.h), on UNAVAILABLE, DEADLINE_EXCEEDED
and RESOURCE_EXHAUSTED (but for a standing limit of the server's, whose
message names "limit max_...": a retry meets it again) with exponential
backoff: before attempt n + 1 it
waits a uniformly random time in [b/2, b], b = min(initial_backoff *
2**(n-1), max_backoff). Uploads are idempotent by (robot_id, seq), a
repeated consolidate finds less pending, and sample_replay carries one
request id over its attempts, so the server counts the replay once.
Errors are raised as FleetMemError with the server's status and message.
"""

from __future__ import annotations

import dataclasses
import os
import random
import threading
import time
import uuid
import warnings
from typing import Iterator, Optional, Sequence

import grpc
import numpy as np

from fleetmem import _wire
from fleetmem.v1 import memory_pb2 as pb
from fleetmem.v1 import memory_pb2_grpc as pb_grpc

_RETRYABLE = (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED,
              grpc.StatusCode.RESOURCE_EXHAUSTED)
_UPLOAD_METHOD = "/fleetmem.v1.MemoryService/UploadTraces"
_ACKS = {"durable": pb.UPLOAD_ACK_DURABLE, "applied": pb.UPLOAD_ACK_APPLIED}


def _retryable(code, message: str) -> bool:
    """Transient failures; a standing limit (max_fleets, max_code_dimension,
    max_traces_per_fleet: docs/api.md) is not, though RESOURCE_EXHAUSTED."""
    if code == grpc.StatusCode.RESOURCE_EXHAUSTED and "limit max_" in message:
        return False
    return code in _RETRYABLE


def _text(name: str, value) -> str:
    """`value` if it is a str; TypeError naming the argument otherwise (an id
    of another type failed deep in gRPC's request iterator)."""
    if not isinstance(value, str):
        raise TypeError(f"{name}: want a str, got {type(value).__name__} {value!r}")
    return value


def _real(name: str, values) -> np.ndarray:
    """`values` as an array of real numbers; TypeError for complex (numpy
    drops the imaginary part when casting) or non-numeric values."""
    array = np.asarray(values)
    if array.dtype.kind not in "biuf":
        raise TypeError(f"{name}: want real numbers, got {array.dtype}")
    return array


class FleetMemError(Exception):
    """A call failed: `code` (grpc.StatusCode), `status` (its name, e.g.
    "NOT_FOUND") and `message` (the server's, which says what was and was
    not done; docs/api.md)."""

    def __init__(self, code: grpc.StatusCode, message: str, method: str = ""):
        self.code = code
        self.status = code.name
        self.message = message
        self.method = method
        super().__init__(f"{method}: {code.name}: {message}" if method else f"{code.name}: {message}")


@dataclasses.dataclass
class UploadResult:
    """What the server answered an upload (UploadTracesResponse).

    accepted + duplicates == the traces given; after a retry, duplicates may
    count traces an earlier failed attempt of the same call stored."""
    accepted: int
    duplicates: int
    consolidations: int
    last_sequence: int
    applied: bool

    @property
    def all_duplicates(self) -> bool:
        """True if the server held every trace already (nothing stored): the
        same (robot_id, seq) keys as an earlier upload, e.g. a script run a
        second time into the same fleet. upload() also warns then."""
        return self.accepted == 0 and self.duplicates > 0


@dataclasses.dataclass(frozen=True)
class ImportResult:
    """What a bulk import did (the calls' ImportTracesResponse summed):
    rows stored and rows the fleet held already; after the last call, the
    traces the fleet holds, its codes still outside the place graph (0
    unless the build failed) and the seconds the graph's build took."""
    accepted: int
    duplicates: int
    fleet_traces: int
    unindexed_codes: int
    index_seconds: float


class DuplicateUploadWarning(UserWarning):
    """An upload of which the server stored nothing: it held every
    (robot_id, seq) already. Filter it (warnings.simplefilter) where
    repeating uploads is intended."""


@dataclasses.dataclass
class Traces:
    """Memory traces as arrays, row i one trace (sample_replay, export).

    codes: n x d float32; places: n x 4 float64 (x, y, z, yaw, in the
    fleet's place unit); rewards: n float32; seqs, cluster_ids: n uint64
    (cluster 0: pending); replay_counts: n uint32; timestamps_ns: n int64;
    robot_ids, domains: lists of n str; attachments: list of n bytes."""
    codes: np.ndarray
    places: np.ndarray
    rewards: np.ndarray
    seqs: np.ndarray
    cluster_ids: np.ndarray
    replay_counts: np.ndarray
    timestamps_ns: np.ndarray
    robot_ids: list
    domains: list
    attachments: list = dataclasses.field(default_factory=list)

    def __len__(self) -> int:
        return len(self.seqs)


@dataclasses.dataclass
class Matches:
    """query_place's answer, nearest first: `distances` (n float32, between
    L2-normalised codes, 0..2) beside the matched traces."""
    distances: np.ndarray
    traces: Traces
    # The fleet that answered (an alias's at the time of the call) and its
    # encoder version.
    fleet_id: str = ""
    encoder_version: str = ""

    def __len__(self) -> int:
        return len(self.distances)


def traces_from_messages(messages: Sequence[pb.MemoryTrace], dim: int = 0) -> Traces:
    """Traces (arrays) from MemoryTrace messages."""
    n = len(messages)
    dim = dim or (len(messages[0].code) if n else 0)
    codes = np.empty((n, dim), np.float32)
    places = np.empty((n, 4), np.float64)
    for i, m in enumerate(messages):
        codes[i] = m.code
        places[i] = (m.pose.x, m.pose.y, m.pose.z, m.pose.yaw)
    return Traces(
        codes=codes, places=places,
        rewards=np.fromiter((m.reward for m in messages), np.float32, n),
        seqs=np.fromiter((m.seq for m in messages), np.uint64, n),
        cluster_ids=np.fromiter((m.cluster_id for m in messages), np.uint64, n),
        replay_counts=np.fromiter((m.replay_count for m in messages), np.uint32, n),
        timestamps_ns=np.fromiter((m.timestamp_ns for m in messages), np.int64, n),
        robot_ids=[m.robot_id for m in messages], domains=[m.domain for m in messages],
        attachments=[m.attachment for m in messages])


def _code(name: str, values) -> np.ndarray:
    """One code: a 1-D array of finite real numbers, as float32. ValueError
    before anything is sent for another shape (a 2-D array would be sent
    flat and answered "dimension ..." by the server: several codes are
    query_places's) or for NaN / infinity."""
    array = _real(name, values)
    if array.ndim != 1 or array.shape[0] == 0:
        hint = " (several codes: query_places)" if array.ndim == 2 else ""
        raise ValueError(f"{name}: want one code, a 1-D array of d numbers, got shape {array.shape}{hint}")
    array = array.astype(np.float32)
    if not np.isfinite(array).all():
        raise ValueError(f"{name}: holds NaN or infinity")
    return array


def _near(near) -> tuple:
    """(x, y, z) from 2 or 3 real numbers; ValueError otherwise."""
    array = _real("near", near).astype(np.float64)
    if array.shape not in ((2,), (3,)) or not np.isfinite(array).all():
        raise ValueError(f"near: want 2 or 3 finite numbers (x, y[, z]), got shape {array.shape}")
    return tuple(float(v) for v in array) + (0.0,) * (3 - len(array))


def _count(name: str, value, low: int = 1) -> int:
    """An int >= low (numpy integers too); TypeError / ValueError otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name}: want an int, got {type(value).__name__} {value!r}")
    if value < low:
        raise ValueError(f"{name}: want at least {low}, got {value}")
    return int(value)


def traces_from_columns(columns: pb.TraceColumns) -> Traces:
    """Traces (arrays) from a TraceColumns message: the codes straight from
    their float32 block, the other fields from packed arrays."""
    n, dim = columns.count, columns.code_dimension
    codes = np.frombuffer(columns.codes, "<f4")
    if codes.size != n * dim:
        raise ValueError(f"columns: {codes.size} code values for {n} x {dim}")
    return Traces(
        codes=codes.reshape(n, dim).astype(np.float32, copy=False),
        places=np.array(columns.places, np.float64).reshape(n, 4),
        rewards=np.array(columns.rewards, np.float32),
        seqs=np.array(columns.seqs, np.uint64),
        cluster_ids=np.array(columns.cluster_ids, np.uint64),
        replay_counts=np.array(columns.replay_counts, np.uint32),
        timestamps_ns=np.array(columns.timestamps_ns, np.int64),
        robot_ids=list(columns.robot_ids), domains=list(columns.domains),
        attachments=list(columns.attachments) or [b""] * n)


def _places_array(places, n: int) -> np.ndarray:
    """n x 4 (x, y, z, yaw) from None, n, n x 2, n x 3 or n x 4."""
    out = np.zeros((n, 4), np.float64)
    if places is None:
        return out
    p = _real("places", places).astype(np.float64)
    if p.ndim == 1:
        p = p[:, None]
    if p.ndim != 2 or p.shape[0] != n or not 1 <= p.shape[1] <= 4:
        raise ValueError(f"places: want {n} rows of 1 to 4 numbers (x, y, z, yaw), got shape {np.shape(places)}")
    out[:, :p.shape[1]] = p
    return out


def _per_trace(name: str, values, n: int, dtype, default=None) -> Optional[np.ndarray]:
    if values is None:
        return None if default is None else np.full(n, default, dtype)
    a = _real(name, values).astype(dtype)
    if a.ndim == 0:
        return np.full(n, a, dtype)
    if a.shape != (n,):
        raise ValueError(f"{name}: want {n} values, got shape {a.shape}")
    return a


class Watch:
    """Iterator over a fleet's memory events (MemoryEvent messages), resumed
    after a broken stream or a server restart from the last event delivered,
    so none is missed or repeated. `last_event_id` is the cursor; close()
    (from any thread) ends the iteration."""

    def __init__(self, client: "Client", fleet: str, after_event: int, idle_timeout: Optional[float]):
        self._client = client
        self._fleet = fleet
        self.last_event_id = after_event
        self._idle_timeout = idle_timeout
        self._closed = threading.Event()
        self._call = None
        self._lock = threading.Lock()

    def close(self) -> None:
        self._closed.set()
        with self._lock:
            if self._call is not None:
                self._call.cancel()

    def __iter__(self) -> Iterator[pb.MemoryEvent]:
        client = self._client
        failures = 0
        idle_since = time.monotonic()
        while not self._closed.is_set():
            # One stream per attempt, with a deadline so that an idle fleet
            # re-opens it (and idle_timeout is checked) now and then.
            window = client.timeout
            if self._idle_timeout is not None:
                window = max(0.05, min(window, self._idle_timeout - (time.monotonic() - idle_since)))
            request = pb.WatchMemoryRequest(fleet_id=self._fleet, after_event=self.last_event_id)
            with self._lock:
                if self._closed.is_set():
                    return
                self._call = client._stub.WatchMemory(request, timeout=window, metadata=client._metadata,
                                                      wait_for_ready=True)
            try:
                for event in self._call:
                    if event.id <= self.last_event_id:
                        continue
                    self.last_event_id = event.id
                    failures = 0
                    idle_since = time.monotonic()
                    yield event
                    if self._closed.is_set():
                        return
                failures += 1  # the server ended the stream (shutting down)
                code, message = grpc.StatusCode.UNAVAILABLE, "the server ended the watch"
            except grpc.RpcError as error:
                code, message = error.code(), error.details() or ""
                if self._closed.is_set():
                    return
                if code == grpc.StatusCode.DEADLINE_EXCEEDED:
                    failures = 0  # the window ended: reopen from the cursor
                elif _retryable(code, message) or code == grpc.StatusCode.CANCELLED:
                    # (not by close(): a server shutting down cancels streams)
                    failures += 1
                else:
                    raise FleetMemError(code, message, "WatchMemory") from None
            finally:
                with self._lock:
                    self._call = None
            if self._idle_timeout is not None and time.monotonic() - idle_since >= self._idle_timeout:
                return
            if failures >= client.max_attempts:
                raise FleetMemError(code, message, "WatchMemory")
            if failures:
                self._closed.wait(client._backoff(failures))


class Client:
    """A connection to fleetmem-server (gRPC). Thread-safe; close() or use
    as a context manager.

    address: "host:port". Credentials: `token` ("NAME:SECRET") or
    `token_file` (the file fleetmem-credential wrote); neither: the
    FLEETMEM_TOKEN_FILE or FLEETMEM_TOKEN environment variable, else none.
    TLS: tls=True (system roots) or ca_file (the server's CA, PEM); cert_file
    and key_file for mutual TLS; server_name overrides the name expected in
    the server's certificate. timeout: seconds per attempt of a call
    (uploads: upload_timeout). batch_size: traces per upload message (the
    server takes up to 1,000 by default)."""

    def __init__(self, address: str = "127.0.0.1:50051", *, token: Optional[str] = None,
                 token_file: Optional[str] = None, tls: bool = False, ca_file: Optional[str] = None,
                 cert_file: Optional[str] = None, key_file: Optional[str] = None,
                 server_name: Optional[str] = None, timeout: float = 10.0,
                 upload_timeout: float = 120.0, max_attempts: int = 5,
                 initial_backoff: float = 0.1, max_backoff: float = 5.0, batch_size: int = 500):
        self.timeout = timeout
        self.upload_timeout = upload_timeout
        self.max_attempts = max(1, max_attempts)
        self.initial_backoff = initial_backoff
        self.max_backoff = max_backoff
        self.batch_size = max(1, batch_size)
        token = token or self._token_from(token_file)
        self._metadata = (("authorization", f"Bearer {token}"),) if token else ()
        options = [("grpc.max_receive_message_length", 64 << 20),
                   ("grpc.keepalive_time_ms", 20000), ("grpc.keepalive_timeout_ms", 10000)]
        if server_name:
            options.append(("grpc.ssl_target_name_override", server_name))
        if tls or ca_file or cert_file:
            if bool(cert_file) != bool(key_file):
                raise ValueError("cert_file and key_file go together (mutual TLS)")
            read = lambda path: open(path, "rb").read() if path else None  # noqa: E731
            credentials = grpc.ssl_channel_credentials(read(ca_file), read(key_file), read(cert_file))
            self._channel = grpc.secure_channel(address, credentials, options)
        else:
            self._channel = grpc.insecure_channel(address, options)
        self._stub = pb_grpc.MemoryServiceStub(self._channel)
        self._upload = self._channel.stream_unary(
            _UPLOAD_METHOD, request_serializer=None,
            response_deserializer=pb.UploadTracesResponse.FromString)

    @staticmethod
    def _token_from(token_file: Optional[str]) -> Optional[str]:
        path = token_file or os.environ.get("FLEETMEM_TOKEN_FILE")
        if path:
            with open(path, encoding="utf-8") as f:
                token = f.read().strip()
            if not token:
                raise ValueError(f"token file {path} is empty")
            return token
        return os.environ.get("FLEETMEM_TOKEN") or None

    def close(self) -> None:
        self._channel.close()

    def __enter__(self) -> "Client":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _backoff(self, failures: int) -> float:
        nominal = min(self.initial_backoff * 2 ** (failures - 1), self.max_backoff)
        return random.uniform(nominal / 2, nominal)

    def _call(self, name: str, call, *, retry: bool = True, timeout: Optional[float] = None):
        attempts = self.max_attempts if retry else 1
        for attempt in range(1, attempts + 1):
            try:
                return call(timeout or self.timeout)
            except grpc.RpcError as error:
                code = error.code()
                if not _retryable(code, error.details() or "") or attempt == attempts:
                    raise FleetMemError(code, error.details() or "", name) from None
            time.sleep(self._backoff(attempt))
        raise AssertionError("unreachable")

    def _unary(self, name: str, request, **kwargs):
        method = getattr(self._stub, name)
        return self._call(name, lambda t: method(request, timeout=t, metadata=self._metadata), **kwargs)

    # ---- writes -------------------------------------------------------
    def upload(self, fleet: str, codes, places=None, rewards=None, *, robot_id: str, seqs,
               domain: str = "", encoder_version: str = "", timestamps_ns=None,
               rewards_external=None, rewards_internal=None, attachments=None,
               ack: str = "applied") -> UploadResult:
        """Uploads n traces of one robot in one stream of batch_size-trace
        messages; a retry repeats the stream (idempotent by (robot_id, seq)).

        codes: n x d; places: None, n, n x 2, n x 3 or n x 4 (x, y, z, yaw);
        rewards: n or a scalar (default 1.0); seqs: n distinct per-robot
        sequence numbers, required: (robot_id, seq) is a trace's identity,
        and one already received is counted as a duplicate and not stored
        again (what makes a retry safe), so each new trace needs a new seq
        (e.g. a counter the robot keeps); timestamps_ns, rewards_external, rewards_internal: n or None.
        ack: "applied" (the default: the answer comes once the traces are
        consolidated and searchable) or "durable" (once they are on the
        server's disk: faster; searchable a moment later)."""
        fleet, robot_id = _text("fleet", fleet), _text("robot_id", robot_id)
        domain, encoder_version = _text("domain", domain), _text("encoder_version", encoder_version)
        codes = _real("codes", codes)
        if codes.ndim != 2:
            raise ValueError(f"codes: want an n x d array, got shape {codes.shape}")
        n = codes.shape[0]
        if ack not in _ACKS:
            raise ValueError(f"ack: want one of {sorted(_ACKS)}, got {ack!r}")
        if n == 0:
            return UploadResult(0, 0, 0, 0, False)
        seqs = np.asarray(seqs)
        if seqs.shape != (n,) or seqs.dtype.kind not in "iu" or (seqs.dtype.kind == "i" and (seqs < 0).any()):
            raise ValueError(f"seqs: want {n} non-negative integers, got {seqs.dtype} of shape {seqs.shape}")
        if len(np.unique(seqs)) != n:
            raise ValueError("seqs: the same seq twice in one upload (each trace needs its own)")
        places = _places_array(places, n)
        rewards = _per_trace("rewards", rewards, n, np.float32, default=1.0)
        extras = dict(
            rewards_external=_per_trace("rewards_external", rewards_external, n, np.float32),
            rewards_internal=_per_trace("rewards_internal", rewards_internal, n, np.float32),
            timestamps_ns=_per_trace("timestamps_ns", timestamps_ns, n, np.int64))
        if attachments is not None:
            attachments = np.ascontiguousarray(attachments)
            if attachments.ndim != 2 or attachments.shape[0] != n:
                raise ValueError(f"attachments: want {n} rows, got shape {attachments.shape}")
            attachments = attachments.view(np.uint8).reshape(n, -1)
        extras["attachments"] = attachments
        codes = np.ascontiguousarray(codes, np.float32)
        step = self.batch_size

        def messages():
            for start in range(0, n, step):
                end = min(n, start + step)
                yield _wire.encode_request(
                    fleet, robot_id, codes[start:end], places[start:end], rewards[start:end],
                    seqs[start:end], _ACKS[ack], domain, encoder_version,
                    **{k: (None if v is None else v[start:end]) for k, v in extras.items()})

        answer = self._call("UploadTraces", lambda t: self._upload(messages(), timeout=t, metadata=self._metadata),
                            timeout=self.upload_timeout)
        result = UploadResult(answer.accepted, answer.duplicates, answer.consolidations,
                              answer.last_sequence, answer.applied)
        if result.all_duplicates:
            warnings.warn(
                f"upload to fleet {fleet!r}: all {result.duplicates} traces of robot {robot_id!r} "
                "were held already (the same seqs as an earlier upload): nothing was stored",
                DuplicateUploadWarning, stacklevel=2)
        return result

    def import_traces(self, fleet: str, codes, places=None, rewards=None, *, robot_ids, seqs,
                      domains=None, encoder_versions=None, timestamps_ns=None,
                      rewards_external=None, rewards_internal=None, chunk: Optional[int] = None,
                      resume: bool = False, finish_timeout: float = 24 * 3600.0) -> ImportResult:
        """Bulk import (admin): n rows into a fleet that holds no trace yet, a
        chunk of rows per ImportTraces call, the fleet's place graph built
        once, by the last call (docs/api.md). A fleet that holds traces is
        refused (FleetMemError FAILED_PRECONDITION) unless resume=True (an
        import that stopped: the rows it holds count as duplicates).

        codes: n x d; places, rewards as upload's; robot_ids: one id for
        every row or n of them; seqs: n non-negative integers ((robot_id,
        seq) is a row's identity); domains, encoder_versions: a string or n
        of them; timestamps_ns, rewards_external, rewards_internal: n or
        None. chunk: rows per call (default: 8 MiB of codes, at most
        10,000). finish_timeout: the last call's, which waits for the
        graph (minutes at millions of rows)."""
        fleet = _text("fleet", fleet)
        codes = _real("codes", codes)
        if codes.ndim != 2 or codes.shape[1] == 0:
            raise ValueError(f"codes: want an n x d array, got shape {codes.shape}")
        n, dim = codes.shape
        codes = np.ascontiguousarray(codes, "<f4")
        if not np.isfinite(codes).all():
            raise ValueError("codes: hold NaN or infinity")
        seqs = np.asarray(seqs)
        if seqs.shape != (n,) or seqs.dtype.kind not in "iu" or (seqs.dtype.kind == "i" and (seqs < 0).any()):
            raise ValueError(f"seqs: want {n} non-negative integers, got {seqs.dtype} of shape {seqs.shape}")

        def texts(name, values, default=None):
            if values is None:
                return None if default is None else [default] * n
            if isinstance(values, str):
                return [_text(name, values)] * n
            values = [_text(name, v) for v in values]
            if len(values) != n:
                raise ValueError(f"{name}: want one string or {n}, got {len(values)}")
            return values

        robot_ids = texts("robot_ids", robot_ids)
        if robot_ids is None:
            raise ValueError("robot_ids: required (one id, or one per row)")
        domains, encoders = texts("domains", domains), texts("encoder_versions", encoder_versions)
        places = _places_array(places, n)
        rewards = _per_trace("rewards", rewards, n, np.float32, default=1.0)
        extras = {"rewards_external": _per_trace("rewards_external", rewards_external, n, np.float32),
                  "rewards_internal": _per_trace("rewards_internal", rewards_internal, n, np.float32),
                  "timestamps_ns": _per_trace("timestamps_ns", timestamps_ns, n, np.int64)}
        step = _count("chunk", chunk) if chunk is not None else max(1, min(10_000, (8 << 20) // (4 * dim)))
        totals = [0, 0]
        answer = pb.ImportTracesResponse()
        for start in range(0, max(n, 1), step):
            end = min(n, start + step)
            request = pb.ImportTracesRequest(fleet_id=fleet, finish=end >= n, resume=resume)
            columns = request.traces
            columns.count, columns.code_dimension = end - start, dim
            columns.codes = codes[start:end].tobytes()
            columns.places.extend(places[start:end].ravel().tolist())
            columns.rewards.extend(rewards[start:end].tolist())
            columns.robot_ids.extend(robot_ids[start:end])
            columns.seqs.extend(int(v) for v in seqs[start:end])
            if domains is not None:
                columns.domains.extend(domains[start:end])
            if encoders is not None:
                columns.encoder_versions.extend(encoders[start:end])
            for name, values in extras.items():
                if values is not None:
                    getattr(columns, name).extend(values[start:end].tolist())
            answer = self._unary("ImportTraces", request,
                                 timeout=finish_timeout if request.finish else None)
            totals[0] += answer.accepted
            totals[1] += answer.duplicates
        return ImportResult(totals[0], totals[1], answer.fleet_traces, answer.unindexed_codes,
                            answer.index_seconds)

    def consolidate(self, fleet: str) -> pb.ConsolidateResponse:
        """Consolidates every robot's pending traces now (Algorithm 1 + 2)."""
        return self._unary("Consolidate", pb.ConsolidateRequest(fleet_id=fleet))

    # ---- fleets -------------------------------------------------------
    _SETTINGS = ("clusters_per_segment", "max_traces_per_cluster", "max_clusters",
                 "replay_decay", "max_age_seconds", "max_traces_per_robot",
                 "refresh_pair_radius", "refresh_uniform")

    @classmethod
    def _settings(cls, forgetting: Optional[str], given: dict) -> pb.FleetSettings:
        settings = pb.FleetSettings()
        for name, value in given.items():
            if name not in cls._SETTINGS:
                raise TypeError(f"unknown setting {name!r}; one of {', '.join(cls._SETTINGS)}")
            if value is None:
                continue
            if name in ("replay_decay", "refresh_pair_radius"):
                setattr(settings, name, float(value))
            elif name == "refresh_uniform":
                if not isinstance(value, bool):
                    raise ValueError(f"refresh_uniform: want True or False, got {value!r}")
                settings.refresh_uniform = value
            elif not isinstance(value, (int, np.integer)) or value < 0:
                raise ValueError(f"{name}: want a non-negative integer, got {value!r}")
            else:
                setattr(settings, name, int(value))
        if forgetting is not None:
            if forgetting not in ("merge", "drop"):
                raise ValueError(f"forgetting: want 'merge' or 'drop', got {forgetting!r}")
            settings.forgetting = (pb.FORGETTING_RULE_MERGE if forgetting == "merge"
                                   else pb.FORGETTING_RULE_DROP)
        return settings

    def create_fleet(self, fleet: str, *, code_dimension: int, encoder_version: str = "",
                     place_unit: str = "", forgetting: Optional[str] = None,
                     index: Optional[str] = None, hnsw_m: int = 0, hnsw_ef_search: int = 0,
                     hnsw_codes: Optional[str] = None, **settings) -> pb.FleetSettings:
        """Admin: makes `fleet` with its own settings (keyword arguments
        clusters_per_segment, max_traces_per_cluster, max_clusters,
        replay_decay, max_age_seconds, max_traces_per_robot,
        refresh_pair_radius (above 0: the pair-keeping refresh),
        refresh_uniform (weight 1 instead of gamma^n R); forgetting
        'merge' or 'drop'; index 'exact', 'hnsw' or 'auto' with HNSW's
        hnsw_m and hnsw_ef_search, and hnsw_codes 'int8' or 'float' (what
        the graph walks on), fixed at creation; the server's for those
        not given). Returns every setting as made. ALREADY_EXISTS if the
        fleet exists. Not retried."""
        request = pb.CreateFleetRequest(fleet_id=_text("fleet", fleet))
        request.settings.CopyFrom(self._settings(forgetting, settings))
        request.settings.code_dimension = int(code_dimension)
        request.settings.encoder_version = encoder_version
        request.settings.place_unit = place_unit
        if index is not None:
            kinds = {"exact": pb.INDEX_KIND_EXACT, "hnsw": pb.INDEX_KIND_HNSW,
                     "auto": pb.INDEX_KIND_AUTO}
            if index not in kinds:
                raise ValueError(f"index: want 'exact', 'hnsw' or 'auto', got {index!r}")
            request.settings.index = kinds[index]
        request.settings.hnsw_m = int(hnsw_m)
        request.settings.hnsw_ef_search = int(hnsw_ef_search)
        if hnsw_codes is not None:
            codes = {"int8": pb.HNSW_CODES_INT8, "float": pb.HNSW_CODES_FLOAT}
            if hnsw_codes not in codes:
                raise ValueError(f"hnsw_codes: want 'int8' or 'float', got {hnsw_codes!r}")
            request.settings.hnsw_codes = codes[hnsw_codes]
        return self._unary("CreateFleet", request, retry=False).settings

    def get_fleet(self, fleet: str) -> pb.FleetSummary:
        """The fleet's counts and settings (FleetSummary: settings,
        own_settings, traces, clusters, ...)."""
        return self._unary("GetFleet", pb.GetFleetRequest(fleet_id=_text("fleet", fleet))).fleet

    def update_fleet(self, fleet: str, *, forgetting: Optional[str] = None,
                     **settings) -> pb.FleetSettings:
        """Admin: changes the settings given (those of create_fleet but the
        dimension, encoder and place unit); a smaller max_clusters or
        max_traces_per_cluster applies at the next consolidation. Returns
        every setting after the change."""
        request = pb.UpdateFleetRequest(fleet_id=_text("fleet", fleet))
        request.settings.CopyFrom(self._settings(forgetting, settings))
        return self._unary("UpdateFleet", request).settings

    def delete_fleet(self, fleet: str) -> int:
        """Admin: removes `fleet` and everything it holds (after every upload
        acknowledged before it); returns the traces it held. Refused while an
        alias names it. Not retried."""
        return self._unary("DeleteFleet", pb.DeleteFleetRequest(fleet_id=_text("fleet", fleet)),
                           retry=False).traces_deleted

    # ---- aliases ------------------------------------------------------
    def create_alias(self, alias: str, fleet: str) -> None:
        """Admin: makes `alias` a name of `fleet` in every call (it may not
        be a fleet's id; `fleet` must be a fleet). Not retried."""
        self._unary("CreateAlias", pb.CreateAliasRequest(alias=_text("alias", alias),
                                                         fleet_id=_text("fleet", fleet)),
                    retry=False)

    def switch_alias(self, alias: str, fleet: str) -> str:
        """Admin: points `alias` at `fleet` in one step; returns the fleet it
        named before. Calls that start after the answer use the new fleet."""
        return self._unary("SwitchAlias", pb.SwitchAliasRequest(
            alias=_text("alias", alias), fleet_id=_text("fleet", fleet))).previous_fleet_id

    def delete_alias(self, alias: str) -> str:
        """Admin: removes `alias` (its fleet stays); returns the fleet it
        named. Not retried."""
        return self._unary("DeleteAlias", pb.DeleteAliasRequest(alias=_text("alias", alias)),
                           retry=False).previous_fleet_id

    def list_aliases(self) -> dict:
        """{alias: fleet id} of the fleets the caller may see."""
        return {a.alias: a.fleet_id for a in self._unary("ListAliases", pb.ListAliasesRequest()).aliases}

    def delete_traces(self, fleet: str, *, robot_id: str = "", domain: str = "",
                      seq_first: Optional[int] = None, seq_last: Optional[int] = None,
                      time_from_ns: Optional[int] = None,
                      time_to_ns: Optional[int] = None) -> pb.DeleteTracesResponse:
        """Deletes every trace matching all the criteria given (at least
        one): a robot's, a domain's, a seq range of a robot (inclusive), an
        observation-time range [from, to). Applied after every upload
        acknowledged before it, in one step; deleted traces are never
        returned again and re-uploads of them count as duplicates. A robot's
        credentials delete only its own traces (robot_id naming itself)."""
        if not (robot_id or domain or seq_first is not None or seq_last is not None
                or time_from_ns is not None or time_to_ns is not None):
            raise ValueError("delete_traces: give robot_id, domain, a seq range or a time range")
        request = pb.DeleteTracesRequest(fleet_id=_text("fleet", fleet),
                                         robot_id=_text("robot_id", robot_id) if robot_id else "",
                                         domain=domain)
        for name, value in (("seq_first", seq_first), ("seq_last", seq_last),
                            ("time_from_ns", time_from_ns), ("time_to_ns", time_to_ns)):
            if value is not None:
                if not isinstance(value, (int, np.integer)) or value < 0:
                    raise ValueError(f"{name}: want a non-negative integer, got {value!r}")
                setattr(request, name, int(value))
        return self._unary("DeleteTraces", request)

    def update_rewards(self, fleet: str, robot_ids, seqs, rewards_external,
                       rewards_internal=0.0) -> pb.UpdateRewardsResponse:
        """Re-scores held traces (Reverb's mutate_priorities): trace i is
        (robot_ids[i] or robot_ids if a str, seqs[i]) and gets R_ex, R_in
        (arrays of n, or one number each); R = R_ex + R_in must be finite and
        >= 0. The next sample_replay draws with the new R. The answer's
        not_held lists the keys the fleet does not hold."""
        seq_array = np.asarray(seqs)
        if seq_array.ndim != 1 or not np.issubdtype(seq_array.dtype, np.integer):
            raise ValueError(f"seqs: want a 1-D integer array, got {seq_array.dtype} of shape {seq_array.shape}")
        n = len(seq_array)
        robots = [robot_ids] * n if isinstance(robot_ids, str) else list(robot_ids)
        if len(robots) != n:
            raise ValueError(f"robot_ids: want {n}, got {len(robots)}")
        external = _per_trace("rewards_external", rewards_external, n, np.float32)
        internal = _per_trace("rewards_internal", rewards_internal, n, np.float32)
        request = pb.UpdateRewardsRequest(fleet_id=_text("fleet", fleet))
        for robot, seq, r_ex, r_in in zip(robots, seq_array.tolist(), external.tolist(),
                                          internal.tolist()):
            request.updates.add(robot_id=_text("robot_id", robot), seq=seq,
                                reward_external=r_ex, reward_internal=r_in)
        return self._unary("UpdateRewards", request)

    def get_traces(self, fleet: str, robot_ids, seqs):
        """The traces with keys (robot_ids[i] or robot_ids if a str, seqs[i]),
        with their codes, in the order named: (Traces, missing), missing a
        list of the (robot_id, seq) keys the fleet does not hold."""
        seq_array = np.asarray(seqs)
        if seq_array.ndim != 1 or not np.issubdtype(seq_array.dtype, np.integer):
            raise ValueError(f"seqs: want a 1-D integer array, got {seq_array.dtype} of shape {seq_array.shape}")
        robots = [robot_ids] * len(seq_array) if isinstance(robot_ids, str) else list(robot_ids)
        if len(robots) != len(seq_array):
            raise ValueError(f"robot_ids: want {len(seq_array)}, got {len(robots)}")
        request = pb.GetTracesRequest(fleet_id=_text("fleet", fleet))
        for robot, seq in zip(robots, seq_array.tolist()):
            request.keys.add(robot_id=_text("robot_id", robot), seq=seq)
        answer = self._unary("GetTraces", request)
        return (traces_from_messages(answer.traces),
                [(key.robot_id, key.seq) for key in answer.missing])

    # ---- reads --------------------------------------------------------
    @staticmethod
    def _read_filter(robot_ids, domains) -> pb.ReadFilter:
        read_filter = pb.ReadFilter()
        if robot_ids is not None:
            read_filter.robot_ids.extend(
                [robot_ids] if isinstance(robot_ids, str) else list(robot_ids))
        if domains is not None:
            read_filter.domains.extend([domains] if isinstance(domains, str) else list(domains))
        return read_filter

    def query_place(self, fleet: str, code, k: int = 1, near=None, radius_m: float = 0.0, *,
                    robot_ids=None, domains=None) -> Matches:
        """The k traces nearest to `code` (d values), nearest first; with
        `near` (x, y[, z]) and radius_m > 0 only those within radius_m; with
        robot_ids / domains (a str or several) only those robots' or
        domains' traces. `code` may be a dict {encoder_version: code} (an
        encoder migration): the server searches with the one of the fleet's
        encoder, so a query through an alias never mixes encoders; the
        answer's encoder_version says which."""
        request = pb.QueryPlaceRequest(fleet_id=_text("fleet", fleet), k=_count("k", k),
                                       radius_m=float(_real("radius_m", radius_m)))
        request.filter.CopyFrom(self._read_filter(robot_ids, domains))
        dims = {}
        if isinstance(code, dict):
            if not code:
                raise ValueError("code: an empty dict (want {encoder_version: code})")
            for version, one in code.items():
                values = _code(f"code[{version!r}]", one)
                dims[_text("encoder_version", version)] = len(values)
                request.codes_by_encoder.add(encoder_version=version).code.extend(values.tolist())
        else:
            request.code.extend(_code("code", code).tolist())
        if near is not None:
            request.near.x, request.near.y, request.near.z = _near(near)
        answer = self._unary("QueryPlace", request)
        matches = answer.matches
        dim = dims.get(answer.encoder_version, len(request.code))
        return Matches(np.fromiter((m.distance for m in matches), np.float32, len(matches)),
                       traces_from_messages([m.trace for m in matches], dim),
                       answer.fleet_id, answer.encoder_version)

    def query_places(self, fleet: str, codes, k: int = 1, near=None,
                     radius_m: float = 0.0, *, robot_ids=None, domains=None) -> list:
        """query_place of each row of `codes` (n x d, n <= 100) in one call
        and one read of the fleet: a list of n Matches, in order (a robot's
        last frames for a sequence search)."""
        array = _real("codes", codes).astype(np.float32)
        if array.ndim != 2 or not 1 <= array.shape[0] <= 100 or array.shape[1] == 0:
            raise ValueError(f"codes: want 1 to 100 rows of one code each, got shape {array.shape}")
        if not np.isfinite(array).all():
            raise ValueError("codes: hold NaN or infinity")
        request = pb.QueryPlaceRequest(fleet_id=_text("fleet", fleet), k=_count("k", k),
                                       radius_m=float(_real("radius_m", radius_m)))
        request.filter.CopyFrom(self._read_filter(robot_ids, domains))
        request.code.extend(array[0].tolist())
        for row in array[1:]:
            request.more_codes.add().code.extend(row.tolist())
        if near is not None:
            request.near.x, request.near.y, request.near.z = _near(near)
        answer = self._unary("QueryPlace", request)
        dim = array.shape[1]
        return [Matches(np.fromiter((m.distance for m in matches), np.float32, len(matches)),
                        traces_from_messages([m.trace for m in matches], dim))
                for matches in [answer.matches] + [more.matches for more in answer.more_matches]]

    def sample_replay(self, fleet: str, robot_id: str, count: int, *,
                      robot_ids=None, domains=None, columnar: bool = True) -> Traces:
        """`count` distinct traces drawn with weight gamma^n * R (Eq. 18) to
        refresh robot_id's dynamic memory; replay_counts shows n after this
        draw. With robot_ids / domains (a str or several) only those robots'
        or domains' traces are drawn. A retry carries the same request id:
        counted once. The answer comes as columns (SampleReplayRequest.
        columnar: one float32 block of codes, no message per trace); with
        columnar=False, or from a server without columns, as messages."""
        request = pb.SampleReplayRequest(fleet_id=_text("fleet", fleet),
                                         robot_id=_text("robot_id", robot_id),
                                         count=_count("count", count), request_id=uuid.uuid4().hex,
                                         columnar=bool(columnar))
        request.filter.CopyFrom(self._read_filter(robot_ids, domains))
        answer = self._unary("SampleReplay", request)
        if answer.HasField("columns"):
            return traces_from_columns(answer.columns)
        return traces_from_messages(answer.traces)

    def stats(self, fleet: str) -> pb.GetStatsResponse:
        """The fleet's counts (GetStatsResponse: traces, clusters, robots, ...)."""
        return self._unary("GetStats", pb.GetStatsRequest(fleet_id=fleet))

    def fleets(self) -> list:
        """The fleets the caller may see (FleetSummary messages)."""
        return list(self._unary("ListFleets", pb.ListFleetsRequest()).fleets)

    def clusters(self, fleet: str, include_places: bool = False) -> pb.ListClustersResponse:
        return self._unary("ListClusters", pb.ListClustersRequest(fleet_id=fleet, include_places=include_places))

    def export(self, fleet: str, page_size: int = 1000) -> Traces:
        """Every trace of the fleet with its code (static memory and
        pending, by robot and seq), read page by page."""
        messages, token = [], ""
        while True:
            page = self._unary("ListTraces", pb.ListTracesRequest(
                fleet_id=fleet, page_size=page_size, page_token=token))
            messages.extend(page.traces)
            token = page.next_page_token
            if not token:
                return traces_from_messages(messages)

    def watch(self, fleet: str, after_event: int = 0, *, idle_timeout: Optional[float] = None) -> Watch:
        """The fleet's memory events after `after_event` (0: from the oldest
        kept), then live ones; reconnects across broken streams and server
        restarts. Iteration ends after idle_timeout seconds without an event
        (None: never; break or close() to stop)."""
        return Watch(self, fleet, after_event, idle_timeout)

    def snapshot(self, name: str) -> pb.CreateSnapshotResponse:
        """Admin: a consistent copy of the store under the snapshot root.
        Not retried (a retry would find the name taken)."""
        return self._unary("CreateSnapshot", pb.CreateSnapshotRequest(name=name), retry=False)
