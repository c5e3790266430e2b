#!/usr/bin/env python3
"""Writes the fuzzers' seed corpora (fuzz_corpus/ beside each harness).

Run from the repository root; the files it writes are committed. Protobuf
messages and PNG files are encoded by hand (no third-party modules).
"""
import os
import struct
import zlib


def varint(n):
    out = bytearray()
    while True:
        b = n & 0x7F
        n >>= 7
        out.append(b | (0x80 if n else 0))
        if not n:
            return bytes(out)


def field(number, wire, payload):
    key = varint((number << 3) | wire)
    if wire == 0:
        return key + varint(payload)
    if wire == 1:
        return key + payload
    if wire == 2:
        return key + varint(len(payload)) + payload
    if wire == 5:
        return key + payload
    raise ValueError(wire)


def string(number, text):
    return field(number, 2, text.encode() if isinstance(text, str) else text)


def pose(x, y):
    return field(1, 1, struct.pack("<d", x)) + field(2, 1, struct.pack("<d", y))


def trace(robot, seq, code, reward=0.5, domain="summer", enc="enc-v1"):
    packed = b"".join(struct.pack("<f", v) for v in code)
    return (string(1, robot) + field(2, 0, seq) + string(3, domain) +
            string(4, packed) + string(5, pose(seq * 5.0, 0.0)) +
            field(6, 5, struct.pack("<f", reward)) + string(11, enc))


def upload(fleet, traces):
    return string(1, fleet) + b"".join(string(2, t) for t in traces)


def png(width, height, colour, pixels):
    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(
            ">I", zlib.crc32(body) & 0xFFFFFFFF)
    channels = 3 if colour else 1
    raw = b"".join(b"\x00" + bytes(pixels[y * width * channels:
                                          (y + 1) * width * channels])
                   for y in range(height))
    header = struct.pack(">IIBBBBB", width, height, 8, 2 if colour else 0, 0,
                         0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) +
            chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


def write(folder, name, data):
    os.makedirs(folder, exist_ok=True)
    with open(os.path.join(folder, name), "wb") as out:
        out.write(data if isinstance(data, bytes) else data.encode())


def main():
    up = "services/transport/fuzz_corpus/upload_message_fuzz"
    code4 = [0.5, -1.0, 2.0, 0.25]
    write(up, "two-traces", upload("f1", [trace("robot-1", 1, code4),
                                          trace("robot-1", 2, code4[::-1])]))
    write(up, "segment", upload("f1", [trace("r", s, [s, 1.0, -s, 0.5],
                                             reward=s / 10.0)
                                       for s in range(1, 9)]))
    write(up, "two-robots", upload("fleet.a", [trace("a", 7, code4),
                                               trace("b", 7, code4, 0.0)]))
    write(up, "empty-fleet", upload("", [trace("r", 1, code4)]))
    write(up, "nan", upload("f", [trace("r", 1, [float("nan"), 1.0])]))

    cfg = "services/server/fuzz_corpus/server_config_fuzz"
    with open("services/server/fleetmem-server.example.textproto") as f:
        write(cfg, "example", f.read())
    write(cfg, "small", 'listen: "127.0.0.1:0" data_dir: "/tmp/x"\n'
          'memory { max_clusters: 5 replay_decay: 0.5 }\n'
          'fleets { fleet_id: "a" memory { clustering: false } }\n')
    write(cfg, "security", 'data_dir: "d" security { auth_file: "c" '
          'tls_cert_file: "s.pem" tls_key_file: "s.key" '
          'tls_client_ca_file: "ca.pem" require_client_certificate: true }\n')
    write(cfg, "limits", 'data_dir: "d" limits { max_fleets: 3 '
          'robot_traces_per_second: 10 max_streams_per_client: 2 }\n'
          'engine { max_events_per_fleet: 100 }\n')

    cred = "services/auth/fuzz_corpus/credentials_fuzz"
    argon = ("$argon2id$v=19$m=65536,t=2,p=1$c2FsdHNhbHRzYWx0c2FsdA$"
             "AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA")
    write(cred, "all-roles",
          'principal { name: "robot-7" role: ROBOT fleets: "f1" '
          'secret_hash: "%s" }\n'
          'principal { name: "r8" role: ROBOT robot_id: "robot-8" '
          'fleets: "f1" certificate_common_name: "robot-8" }\n'
          'principal { name: "dash" role: READER fleets: "*" '
          'certificate_common_name: "dash" }\n'
          'principal { name: "ops" role: ADMIN secret_hash: "%s" }\n'
          % (argon, argon))
    write(cred, "duplicate", 'principal { name: "a" role: ADMIN '
          'certificate_common_name: "x" }\n'
          'principal { name: "a" role: ADMIN certificate_common_name: "y" }\n')

    img = "clients/robot/sensing/fuzz_corpus/image_decode_fuzz"
    write(img, "grey-8x4.png", png(8, 4, False, range(32)))
    write(img, "rgb-16x8.png", png(16, 8, True,
                                   [(i * 7) % 256 for i in range(16 * 8 * 3)]))
    write(img, "one-pixel.png", png(1, 1, False, [128]))

    # CARMEN logs: the message kinds of a real log, and two broken records.
    carmen = "clients/robot/sensing/fuzz_corpus/carmen_log_fuzz"
    write(carmen, "log",
          "# message formats defined: PARAM SYNC ODOM FLASER\n"
          "PARAM robot_use_laser on nohost 0\n"
          "ODOM 0.0 0.0 0.0 0.1 0.0 0.0 70.1 nohost 0.1\n"
          "FLASER 5 1.5 2.25 49.9 50.0 0.0 0.5 -0.25 1.57 0.5 -0.25 1.57 "
          "70.2 nohost 0.2\n"
          "FLASER 3 1 2 3 1.0 1.0 0.0 1.0 1.0 0.0 70.3 nohost 0.3\r\n")
    write(carmen, "nan-range", "FLASER 3 1.0 2.0 nan 0 0 0 0 0 0 1.5 host 0\n")
    write(carmen, "short", "FLASER 180 1.0 2.0\n")

    # SLAM readers: a KITTI and a TUM trajectory, relations, deployments, a
    # scan attachment (3 beams, 180 degrees, 1.5 m, no return, 2 m).
    traj = "clients/robot/slam/fuzz_corpus/trajectory_fuzz"
    write(traj, "kitti", "1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 1 0 1 0 0 0 0 1 0\n"
          "1 0 0 2 0 1 0 0.5 0 0 1 0\n")
    write(traj, "tum", "# t x y z qx qy qz qw\n0.0 0 0 0 0 0 0 1\n"
          "0.1 1 0 0 0 0 0.7071068 0.7071068\n0.2 1 1 0 0 0 1 0\n")
    write(traj, "relations", "90.2 90.7 0.42 -0.0007 0 0 0 0.017\n")
    write(traj, "deployments", "sequence,t_err,r_err\nct>k1,2.5,0.37\n"
          "ct>k1>r1>k2,4.85,1.59\nct>k1>k2,7.48,1.63\n")
    write(traj, "scan", struct.pack("<Hf3H", 3, 3.14159265, 1500, 0, 2000))

    # An index snapshot's memory image (engine/memory_image.h, after its
    # length): a string table, two clusters, one trace with an attachment.
    image = "services/engine/fuzz_corpus/memory_image_fuzz"
    strings = [b"r1", b"summer", b"hog-v1", b"r2"]
    data = struct.pack("<II", 0x314D494D, len(strings))
    data += b"".join(struct.pack("<Q", len(t)) + t for t in strings)
    data += struct.pack("<Q", 2)
    for cluster_id, robot, centroid, members in (
            (4, 0, [0.5, -1.0, 7.0, 2.0], [(0, 1, b""), (0, 2, b"scan"),
                                            (3, 9, b"")]),
            (11, 3, [1.0, 2.0, 3.0, 4.0], [(3, 10, b"")])):
        data += struct.pack("<QII", cluster_id, robot, len(centroid))
        data += struct.pack("<%df" % len(centroid), *centroid)
        data += struct.pack("<I", len(members))
        for member, seq, attachment in members:
            data += struct.pack("<IQII", member, seq, 1, 2)
            data += struct.pack("<dddd", 1.5 * seq, -2.0, 0.0, 0.5)
            data += struct.pack("<fff", 0.75, 0.5, 0.25)
            data += struct.pack("<qI", 1700000000000000000 + seq, seq * 3)
            data += struct.pack("<I", len(attachment)) + attachment
    write(image, "two_clusters.bin", data)


if __name__ == "__main__":
    main()
