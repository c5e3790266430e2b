"""Protobuf wire encoding of UploadTracesRequest from numpy arrays.

Building one MemoryTrace message per trace in Python costs a Python loop
per trace (and a copy of every code into a repeated field); this module
writes the serialized request with numpy instead, a whole message at a time,
so that uploading from Python runs at the speed of the C++ client
(bench/python_upload_bench.sh). The bytes are an ordinary protobuf encoding
of fleetmem.v1.UploadTracesRequest: every field is tagged and minimal, only
the order of a trace's fields differs from protoc's (the encoding allows any
order); tests/test_wire.py parses them back with the generated classes.

One trace, as written (field numbers of memory.proto's MemoryTrace):
  0x12 LEN                      UploadTracesRequest.traces (2)
    0x0A len robot_id           1   (the same for every trace of a call)
    0x1A len domain             3   (if given)
    0x5A len encoder_version    11  (if given)
    0x22 len code               4   packed float32, little-endian
    0x2A 0x24 Pose              5   x 0x09, y 0x11, z 0x19, yaw 0x21 (float64)
    0x35 reward                 6   float32
    0x3D reward_external        7   (if given)
    0x45 reward_internal        8   (if given)
    0x6A len attachment         13  (if given: the same length for every trace)
    0x10 seq                    2   varint
    0x48 timestamp_ns           9   varint (if given; two's complement)
"""

import numpy as np

_LITTLE = np.dtype("<f4"), np.dtype("<f8")


def varint(value: int) -> bytes:
    """The protobuf varint of a non-negative int below 2**64."""
    out = bytearray()
    while True:
        byte = value & 0x7F
        value >>= 7
        if value:
            out.append(byte | 0x80)
        else:
            out.append(byte)
            return bytes(out)


def _varints(values: np.ndarray):
    """Varints of uint64 `values`: (bytes n x 10, lengths n)."""
    v = values.astype(np.uint64, copy=False)
    shifts = np.arange(10, dtype=np.uint64) * np.uint64(7)
    groups = (v[:, None] >> shifts[None, :]) & np.uint64(0x7F)
    # Length: 1 + the index of the highest non-zero 7-bit group.
    nonzero = groups != 0
    lengths = np.where(nonzero.any(axis=1), 10 - np.argmax(nonzero[:, ::-1], axis=1), 1)
    more = np.arange(10)[None, :] < (lengths[:, None] - 1)
    encoded = groups.astype(np.uint8) | (more.astype(np.uint8) << 7)
    return encoded, lengths


def _string_field(tag: int, text: str) -> bytes:
    data = text.encode("utf-8")
    return bytes([tag]) + varint(len(data)) + data


def encode_request(fleet_id: str, robot_id: str, codes: np.ndarray, places: np.ndarray,
                   rewards: np.ndarray, seqs: np.ndarray, ack: int, domain: str = "",
                   encoder_version: str = "", rewards_external=None, rewards_internal=None,
                   timestamps_ns=None, attachments=None) -> bytes:
    """One serialized UploadTracesRequest of len(codes) traces.

    codes: n x d float32; places: n x 4 float64 (x, y, z, yaw); rewards: n
    float32; seqs: n uint64; the optional arrays have n values;
    attachments: n x k uint8 (k bytes per trace).
    """
    n, dim = codes.shape
    head = _string_field(0x0A, robot_id)
    if domain:
        head += _string_field(0x1A, domain)
    if encoder_version:
        head += _string_field(0x5A, encoder_version)
    head += bytes([0x22]) + varint(4 * dim)
    parts = [np.broadcast_to(np.frombuffer(head, np.uint8), (n, len(head))),
             np.ascontiguousarray(codes, dtype=_LITTLE[0]).view(np.uint8)]
    pose = np.empty((n, 38), np.uint8)
    pose[:, 0], pose[:, 1] = 0x2A, 36
    pose_values = np.ascontiguousarray(places, dtype=_LITTLE[1]).view(np.uint8)
    for i, tag in enumerate((0x09, 0x11, 0x19, 0x21)):
        pose[:, 2 + 9 * i] = tag
        pose[:, 3 + 9 * i:11 + 9 * i] = pose_values[:, 8 * i:8 * i + 8]
    parts.append(pose)
    for tag, values in ((0x35, rewards), (0x3D, rewards_external), (0x45, rewards_internal)):
        if values is None:
            continue
        block = np.empty((n, 5), np.uint8)
        block[:, 0] = tag
        block[:, 1:] = np.ascontiguousarray(values, dtype=_LITTLE[0]).view(np.uint8).reshape(n, 4)
        parts.append(block)
    if attachments is not None and attachments.shape[1] > 0:
        tag = np.frombuffer(bytes([0x6A]) + varint(attachments.shape[1]), np.uint8)
        parts += [np.broadcast_to(tag, (n, len(tag))), np.ascontiguousarray(attachments, np.uint8)]
    fixed = np.concatenate(parts, axis=1) if len(parts) > 1 else parts[0]

    # The variable-length tail: seq (and timestamp) varints, left-aligned in
    # a fixed-width block with a mask of the bytes in use.
    seq_bytes, seq_len = _varints(seqs)
    tails = [np.full((n, 1), 0x10, np.uint8), seq_bytes]
    masks = [np.ones((n, 1), bool), np.arange(10)[None, :] < seq_len[:, None]]
    length = fixed.shape[1] + 1 + seq_len
    if timestamps_ns is not None:
        ts_bytes, ts_len = _varints(np.asarray(timestamps_ns, np.int64).view(np.uint64))
        tails += [np.full((n, 1), 0x48, np.uint8), ts_bytes]
        masks += [np.ones((n, 1), bool), np.arange(10)[None, :] < ts_len[:, None]]
        length = length + 1 + ts_len
    # Each trace's length prefix (a trace is below 2**21 bytes: 3 bytes).
    len_bytes, len_len = _varints(length.astype(np.uint64))
    rows = np.concatenate([np.full((n, 1), 0x12, np.uint8), len_bytes[:, :3], fixed] + tails, axis=1)
    mask = np.concatenate([np.ones((n, 1), bool), np.arange(3)[None, :] < len_len[:, None],
                           np.ones(fixed.shape, bool)] + masks, axis=1)
    if int(len_len.max(initial=1)) > 3:
        raise ValueError("a trace of 2 MiB or more cannot be uploaded")
    request_head = _string_field(0x0A, fleet_id)
    request_tail = bytes([0x18]) + varint(ack) if ack else b""
    return request_head + rows[mask].tobytes() + request_tail
