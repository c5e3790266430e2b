#!/usr/bin/python3
"""Opens and closes a REST watch CYCLES times against a fleetmem-server's
HTTP port (each: connect, GET /v1/fleets/FLEET/watch, read the answer's
head, close), waiting WAIT seconds every fourth cycle (a browser's
EventSource reconnects after a second); prints how many were refused
(429) for a watch slot. The fleet must exist. Usage:
watch_cycles.py HOST:PORT FLEET [CYCLES] [WAIT] (docs/reliability.md, "Third
round", item 7)."""
import socket
import sys
import time


def main():
    host, port = sys.argv[1].rsplit(":", 1)
    fleet = sys.argv[2]
    cycles = int(sys.argv[3]) if len(sys.argv) > 3 else 200
    wait = float(sys.argv[4]) if len(sys.argv) > 4 else 0.1
    served = refused = 0
    for cycle in range(cycles):
        with socket.create_connection((host, int(port)), timeout=5) as connection:
            connection.sendall(f"GET /v1/fleets/{fleet}/watch HTTP/1.1\r\n"
                               f"Host: {host}\r\n\r\n".encode())
            head = b""
            while b"\r\n\r\n" not in head:
                piece = connection.recv(4096)
                if not piece:
                    break
                head += piece
        served += head.startswith(b"HTTP/1.1 200")
        refused += head.startswith(b"HTTP/1.1 429")
        if cycle % 4 == 3:
            time.sleep(wait)
    print(f"{cycles} watch connect/close cycles: {served} served, {refused} refused (429)")


if __name__ == "__main__":
    main()
