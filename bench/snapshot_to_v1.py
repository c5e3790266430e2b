#!/usr/bin/python3
"""Rewrites an index snapshot file of the second format ("FMIDXSN2": a
checksum per chunk) in the first ("FMIDXSN1": one XXH3-64 of everything
after the magic), in place, for bench/snapshot_read_ab.sh: the same stamp,
key and payload (services/storage/snapshot_file.h gives both frames).

    snapshot_to_v1.py FILE
"""
import ctypes
import mmap
import os
import struct
import sys

xxhash = ctypes.CDLL("libxxhash.so.0")
xxhash.XXH3_64bits.restype = ctypes.c_uint64
xxhash.XXH3_64bits.argtypes = [ctypes.c_void_p, ctypes.c_size_t]


def main(path):
    with open(path, "rb") as f:
        data = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_COPY)
    if data[:8] != b"FMIDXSN2":
        sys.exit(f"{path}: not a snapshot of the second format")
    size = len(data)
    (key_size,) = struct.unpack_from("<Q", data, 16)
    chunk_bytes, payload = struct.unpack_from("<QQ", data, size - 24)
    body_end = 24 + key_size + payload  # stamp, key size, key, payload
    address = ctypes.addressof(ctypes.c_char.from_buffer(data, 8))
    digest = xxhash.XXH3_64bits(address, body_end - 8)
    temporary = path + ".v1"
    with open(temporary, "wb") as out:
        out.write(b"FMIDXSN1")
        view = memoryview(data)
        for at in range(8, body_end, 64 << 20):
            out.write(view[at:min(body_end, at + (64 << 20))])
        view.release()
        out.write(struct.pack("<QQ", payload, digest))
    os.replace(temporary, path)
    print(f"{path}: rewritten in the first format ({payload} payload bytes, "
          f"{(payload + chunk_bytes - 1) // chunk_bytes} chunk checksums dropped)")


if __name__ == "__main__":
    main(sys.argv[1])
