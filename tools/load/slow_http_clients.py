#!/usr/bin/python3
"""Holds N slow HTTP connections (a header line every 3 s, never finished;
one the server closes is opened again)
from ADDRESSES loopback addresses (127.0.0.1, .2, ...) against a
fleetmem-server's HTTP port while timing GET /readyz once a second; prints
how many probes were answered 200 within 1 s and the slowest. Usage:
slow_http_clients.py HOST:PORT [N] [PROBES] [ADDRESSES]
(docs/reliability.md, "Hostile clients" and "Third round": 300 slow
connections from 5 addresses, past the 256-connection limit)."""
import socket
import sys
import threading
import time
import urllib.request


def main():
    host, port = sys.argv[1].rsplit(":", 1)
    count = int(sys.argv[2]) if len(sys.argv) > 2 else 50
    probes = int(sys.argv[3]) if len(sys.argv) > 3 else 14
    addresses = int(sys.argv[4]) if len(sys.argv) > 4 else 1
    slow = []
    for i in range(count):
        connection = socket.create_connection(
            (host, int(port)), source_address=(f"127.0.0.{i % addresses + 1}", 0))
        connection.sendall(b"GET /readyz HTTP/1.1\r\n")
        slow.append(connection)
    stop = threading.Event()

    def trickle():
        while not stop.is_set():
            for i, connection in enumerate(slow):
                try:
                    connection.sendall(b"X-Slow: 1\r\n")
                except OSError:  # closed by the server's head deadline: again
                    try:
                        slow[i] = socket.create_connection(
                            (host, int(port)), source_address=(f"127.0.0.{i % addresses + 1}", 0))
                        slow[i].sendall(b"GET /readyz HTTP/1.1\r\n")
                    except OSError:
                        pass
            stop.wait(3)

    thread = threading.Thread(target=trickle)
    thread.start()
    worst = 0.0
    answered = 0
    for _ in range(probes):
        start = time.time()
        try:
            with urllib.request.urlopen(f"http://{host}:{port}/readyz", timeout=5) as answer:
                ok = answer.status == 200 and answer.read().startswith(b"ready")
        except OSError:  # urllib's HTTPError (a 503) included
            ok = False
        took = time.time() - start
        worst = max(worst, took)
        answered += 1 if ok and took <= 1.0 else 0
        time.sleep(1)
    stop.set()
    thread.join()
    print(f"{count} slow connections from {addresses} address(es): {answered} of {probes} "
          f"/readyz answered 200 within 1 s; slowest {worst:.3f} s")


if __name__ == "__main__":
    main()
