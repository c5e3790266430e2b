"""The numpy encoder writes what the generated classes write."""

import numpy as np
import pytest

from fleetmem import _wire, pb


def message_built(fleet, robot, codes, places, rewards, seqs, ack, domain, version, ext, ts, att):
    request = pb.UploadTracesRequest(fleet_id=fleet, ack=ack)
    for i in range(len(codes)):
        t = request.traces.add(robot_id=robot, seq=int(seqs[i]), domain=domain, encoder_version=version,
                               reward=float(rewards[i]))
        t.code.extend(codes[i].tolist())
        t.pose.x, t.pose.y, t.pose.z, t.pose.yaw = places[i]
        if ext is not None:
            t.reward_external = float(ext[i])
        if ts is not None:
            t.timestamp_ns = int(ts[i])
        if att is not None:
            t.attachment = att[i].tobytes()
    return request


@pytest.mark.parametrize("dim", [1, 3, 31, 256, 4096])
@pytest.mark.parametrize("optional", [False, True])
def test_encoding_parses_to_the_same_request(dim, optional):
    rng = np.random.default_rng(dim)
    n = 40
    codes = rng.standard_normal((n, dim)).astype(np.float32)
    places = rng.standard_normal((n, 4)) * 1e4
    rewards = rng.random(n).astype(np.float32)
    # Every varint length, the largest values and zero.
    seqs = np.array([0, 1, 2**64 - 1] + [2 ** (7 * k) for k in range(1, 10)]
                    + rng.integers(0, 2**63, n - 12, dtype=np.uint64).tolist(), np.uint64)
    ext = rng.random(n).astype(np.float32) if optional else None
    ts = rng.integers(-2**63, 2**63 - 1, n, dtype=np.int64) if optional else None
    att = rng.integers(0, 256, (n, 200), dtype=np.uint8) if optional else None
    domain, version = ("winter", "gpl-v3") if optional else ("", "")
    encoded = _wire.encode_request("fleet-ü", "robot-7", codes, places, rewards, seqs, 2 if optional else 0,
                                   domain, version, ext, None, ts, att)
    want = message_built("fleet-ü", "robot-7", codes, places, rewards, seqs, 2 if optional else 0,
                         domain, version, ext, ts, att)
    assert pb.UploadTracesRequest.FromString(encoded) == want
    # No bigger than protoc's own encoding but for the zero-valued fields
    # protoc leaves out (a zero seq, pose field or reward is written here).
    zeros = sum(2 * (t.seq == 0) + 5 * (t.reward == 0)
                + sum(9 for v in (t.pose.x, t.pose.y, t.pose.z, t.pose.yaw) if v == 0) for t in want.traces)
    assert want.ByteSize() <= len(encoded) <= want.ByteSize() + zeros + len(want.traces)


def test_varint_matches_protobuf():
    for value in (1, 127, 128, 300, 2**32, 2**64 - 1):
        m = pb.MemoryTrace(seq=value)
        assert m.SerializeToString() == b"\x10" + _wire.varint(value)
