#!/usr/bin/python3
"""Holds N slow HTTP connections (a header line every 3 s, never finished)
against a fleetmem-server's HTTP port while timing GET /readyz once a second;
prints the slowest probe. Usage: slow_http_clients.py HOST:PORT [N] [PROBES]
(docs/reliability.md, "Hostile clients")."""
import socket
import sys
import threading
import time
import urllib.request


def main():
    host, port = sys.argv[1].rsplit(":", 1)
    count = int(sys.argv[2]) if len(sys.argv) > 2 else 50
    probes = int(sys.argv[3]) if len(sys.argv) > 3 else 14
    slow = []
    for _ in range(count):
        connection = socket.create_connection((host, int(port)))
        connection.sendall(b"GET /readyz HTTP/1.1\r\n")
        slow.append(connection)
    stop = threading.Event()

    def trickle():
        while not stop.is_set():
            for connection in slow:
                try:
                    connection.sendall(b"X-Slow: 1\r\n")
                except OSError:
                    pass  # closed by the server's head deadline
            stop.wait(3)

    thread = threading.Thread(target=trickle)
    thread.start()
    worst = 0.0
    for _ in range(probes):
        start = time.time()
        urllib.request.urlopen(f"http://{host}:{port}/readyz", timeout=5).read()
        worst = max(worst, time.time() - start)
        time.sleep(1)
    stop.set()
    thread.join()
    print(f"{count} slow connections: slowest of {probes} /readyz {worst:.3f} s")


if __name__ == "__main__":
    main()
