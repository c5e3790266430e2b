#!/usr/bin/env python3
"""Dockerized fault tests of distributed mode (`make test-cluster`).

Builds fleetmem/server (docker/server.Dockerfile) and fleetmem/nats
(docker/nats.Dockerfile) on the local bookworm base
(tests/docker/base_image.sh: this engine cannot pull), brings up
docker/cluster.compose.yaml without its robots (three NATS servers
clustered, three replicas, auth and TLS from docker/make-secrets.sh) and
loads it from this host with fleetmem-load: FLEETS fleets, one robot each,
each fleet uploading through one replica's published port (batches of 20,
100 traces/s), retrying a failed batch until it is acknowledged. The faults,
one after another, under that load:

  replica SIGKILL      `docker kill` of the replica that owns fleet-0
  NATS server SIGKILL  `docker kill` of nats-1 (two of three stay: quorum)
  replica partitioned  `docker network disconnect` of the replica that owns
                       fleet-1 for PARTITION_S seconds, then reconnected

After each fault: the seconds until every fleet answers GetStats through a
replica that is still up (forwarded to its owner) and, for a lost replica,
until another replica owns the fleet it owned. The next fault comes once
the cluster has recovered from the last: every NATS server answers its
/healthz (JetStream current: a restarted server has caught up) and every
fleet is served. Faults that overlap (a replica cut while a NATS server is
still catching up, whose JetStream requests then time out) are a double
fault, not what the bounds are for. A recovery past its bound prints every
replica's log from the fault on. At the end, each fleet's
robot: what fleetmem-load acknowledged against what the fleet received
(GetStats: received and max_seq): lost = acknowledged seqs not received,
duplicated = received more often than distinct seqs (received > max_seq).
Prints the table and exits 1 on a lost or duplicated trace or a recovery
slower than 10 s (a replica) / 30 s (NATS); exits 77 (skipped) without a
Docker engine, docker-compose or debootstrap.

Environment: FLEETMEM_CLUSTER_KEEP=1 keeps the cluster and its volumes,
FLEETMEM_CLUSTER_PARTITION_S (20), FLEETMEM_CLUSTER_FLEETS (3).
"""

import json
import os
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import fault_tests as common  # noqa: E402  (shared helpers of the fleet test)

ROOT, HERE, SKIP = common.ROOT, common.HERE, common.SKIP
BASE_IMAGE, VERSION = common.BASE_IMAGE, common.VERSION
BUILD = os.path.join(ROOT, "build", "bin")
FLEETS = int(os.environ.get("FLEETMEM_CLUSTER_FLEETS", "3"))
PARTITION_S = float(os.environ.get("FLEETMEM_CLUSTER_PARTITION_S", "20"))
PROJECT = f"fmcluster{os.getpid()}"
GRPC_PORTS = [50051, 50052, 50053]  # docker/cluster.compose.yaml
log, run, wait_until = common.log, common.run, common.wait_until


def build_images():
    t0 = time.time()
    run([os.path.join(HERE, "base_image.sh"), BASE_IMAGE], capture=False)
    for relative, tag in [("docker/server.Dockerfile", f"fleetmem/server:{VERSION}"),
                          ("docker/nats.Dockerfile", "fleetmem/nats:2.9")]:
        common.docker_build(relative, tag, {"BASE_IMAGE": BASE_IMAGE,
                                            "FLEETMEM_VERSION": VERSION})
    log(f"images built in {time.time() - t0:.0f} s")


class Cluster:
    def __init__(self, secrets):
        self.secrets = secrets
        self.env = dict(os.environ, FLEETMEM_SECRETS=secrets,
                        FLEETMEM_BASE_IMAGE=BASE_IMAGE, FLEETMEM_VERSION=VERSION,
                        COMPOSE_PROJECT_NAME=PROJECT)
        self.compose = ["docker-compose", "-f",
                        os.path.join(ROOT, "docker", "cluster.compose.yaml")]

    def up(self, *services):
        run(self.compose + ["up", "-d", "--no-build", *services], env=self.env,
            capture=False)

    def down(self):
        run(self.compose + ["down", "-v", "--remove-orphans"], env=self.env,
            check=False)

    def container(self, service):
        return f"{PROJECT}_{service}_1"

    def cli(self, port, *args, timeout_ms=2000):
        return run([os.path.join(BUILD, "fleetmem"), "--server", f"127.0.0.1:{port}",
                    "--deadline-ms", str(timeout_ms), "--json",
                    "--token-file", os.path.join(self.secrets, "ops.token"),
                    "--tls-ca", os.path.join(self.secrets, "ca.pem"), *args],
                   check=False)

    def stats(self, port, fleet):
        result = self.cli(port, "stats", "--fleet", fleet)
        if result.returncode != 0:
            return None
        try:
            return json.loads(result.stdout.strip().splitlines()[-1])
        except (ValueError, IndexError):
            return None

    def owners(self, port):
        result = self.cli(port, "fleets")
        owners = {}
        for line in result.stdout.splitlines():
            try:
                fleet = json.loads(line)
            except ValueError:
                continue
            for summary in fleet.get("fleets", [fleet]):
                if "fleetId" in summary:
                    owners[summary["fleetId"]] = summary.get("replica", "")
        return owners


def nats_current(cluster):
    """True when every NATS server answers /healthz: JetStream enabled and
    current (its streams caught up, leaders elected)."""
    return all(run(["docker", "exec", cluster.container(f"nats-{n}"), "curl",
                    "-fsS", "-o", "/dev/null", "http://127.0.0.1:8222/healthz"],
                   check=False).returncode == 0 for n in range(3))


def settle(cluster):
    """Waits until the cluster has recovered from the last fault."""
    t0 = time.time()
    wait_until("every NATS server current", lambda: nats_current(cluster), 120)
    until_served(cluster, GRPC_PORTS, 120)
    log(f"settled in {time.time() - t0:.1f} s")


def replica_logs(cluster, since):
    """Every replica's log from `since` (epoch seconds) on."""
    text = []
    for n in range(3):
        name = cluster.container(f"fleetmem-{n}")
        out = run(["docker", "logs", "--since", f"{since:.0f}", name],
                  check=False).stdout or ""
        text.append(f"--- fleetmem-{n} since the fault\n{out}")
    return "\n".join(text)


def owner_of(cluster, fleet):
    """The service name of the replica that owns `fleet` (waits for one)."""
    owner = wait_until(f"an owner of {fleet}", lambda: cluster.owners(
        GRPC_PORTS[0]).get(fleet, ""), 60, poll=0.2)
    return owner.split(":")[0]


def until_served(cluster, ports, timeout, moved=None, start=None):
    """Seconds from `start` until every fleet answers GetStats through one of
    `ports`; with `moved` (a fleet and its lost owner), also until another
    replica owns that fleet."""
    start = start or time.time()
    def all_served():
        if moved is not None:
            fleet, lost = moved
            owner = cluster.owners(ports[0]).get(fleet, "")
            if owner == "" or owner.split(":")[0] == lost:
                return False
        return all(any(cluster.stats(p, f"fleet-{f}") for p in ports)
                   for f in range(FLEETS))
    wait_until("every fleet served", all_served, timeout, poll=0.2)
    return time.time() - start


def main():
    why = common.preconditions()
    if why:
        print(f"cluster fault tests: SKIPPED: {why}")
        return SKIP
    for binary in ("fleetmem", "fleetmem-load", "fleetmem-credential"):
        if not os.access(os.path.join(BUILD, binary), os.X_OK):
            print(f"cluster fault tests: build/bin/{binary} is missing (make build)")
            return 1
    build_images()
    secrets = tempfile.mkdtemp(prefix="fleetmem-cluster-secrets-")
    run([os.path.join(ROOT, "docker", "make-secrets.sh"), secrets],
        env=dict(os.environ, FLEETMEM_CREDENTIAL=os.path.join(BUILD, "fleetmem-credential")))
    cluster = Cluster(secrets)
    try:
        return exercise(cluster, secrets)
    finally:
        if os.environ.get("FLEETMEM_CLUSTER_KEEP") != "1":
            cluster.down()


def exercise(cluster, secrets):
    rows, failures, loads = [], [], []
    work = tempfile.mkdtemp(prefix="fleetmem-cluster-load-")
    try:
        cluster.up("nats-0", "nats-1", "nats-2", "fleetmem-0", "fleetmem-1", "fleetmem-2")
        wait_until("the replicas answer", lambda: all(
            cluster.cli(p, "health").returncode == 0 for p in GRPC_PORTS), 180)
        for f in range(FLEETS):
            loads.append(subprocess.Popen(
                [os.path.join(BUILD, "fleetmem-load"), "upload",
                 "--server", f"127.0.0.1:{GRPC_PORTS[f % 3]}", "--fleet", f"fleet-{f}",
                 "--dimension", "64", "--robots", "1", "--batch", "20", "--rate", "100",
                 "--seconds", "100000", "--ack-log", os.path.join(work, f"fleet-{f}.acks"),
                 "--token-file", os.path.join(secrets, "ops.token"),
                 "--tls-ca", os.path.join(secrets, "ca.pem")],
                stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT))
        until_served(cluster, GRPC_PORTS, 120)
        time.sleep(5)

        def port_of(address):
            return GRPC_PORTS[int(address.split(":")[0].rsplit("-", 1)[1])]

        victim = owner_of(cluster, "fleet-0")
        log(f"fault 1: docker kill {victim} (owns fleet-0)")
        killed_at = time.time()
        run(["docker", "kill", cluster.container(victim)])
        live = [p for p in GRPC_PORTS if p != port_of(victim)]
        rows.append(("replica SIGKILL", until_served(
            cluster, live, 60, moved=("fleet-0", victim), start=killed_at),
            10.0, killed_at))
        cluster.up(victim)
        time.sleep(5)
        settle(cluster)

        log("fault 2: docker kill nats-1")
        nats_killed_at = time.time()
        run(["docker", "kill", cluster.container("nats-1")])
        rows.append(("NATS server SIGKILL", until_served(cluster, GRPC_PORTS, 90),
                     30.0, nats_killed_at))
        cluster.up("nats-1")
        time.sleep(5)
        settle(cluster)

        cut = owner_of(cluster, "fleet-1")
        network = f"{PROJECT}_cluster"
        log(f"fault 3: {cut} (owns fleet-1) partitioned for {PARTITION_S:.0f} s")
        cut_at = time.time()
        run(["docker", "network", "disconnect", network, cluster.container(cut)])
        live = [p for p in GRPC_PORTS if p != port_of(cut)]
        rows.append(("replica partitioned", until_served(
            cluster, live, 60, moved=("fleet-1", cut), start=cut_at), 10.0,
            cut_at))
        time.sleep(max(0.0, PARTITION_S - rows[-1][1]))
        run(["docker", "network", "connect", network, cluster.container(cut)])
        time.sleep(5)
    finally:
        for load in loads:
            load.terminate()
        for load in loads:
            load.wait(timeout=30)

    # Every acknowledged trace received once by its fleet.
    table = []
    for f in range(FLEETS):
        acknowledged = 0
        with open(os.path.join(work, f"fleet-{f}.acks")) as acks:
            for line in acks:
                _, first, last = line.split()
                acknowledged = max(acknowledged, int(last))
        def settled():
            stats = cluster.stats(GRPC_PORTS[0], f"fleet-{f}")
            robots = (stats or {}).get("robots", [])
            if not robots:
                return None
            received = int(robots[0].get("received", 0))
            max_seq = int(robots[0].get("maxSeq", 0))
            return (received, max_seq) if received >= acknowledged else None
        try:
            received, max_seq = wait_until(f"fleet-{f} materialised", settled, 120)
        except RuntimeError as error:
            failures.append(str(error))
            received, max_seq = 0, 0
        lost = max(0, acknowledged - min(received, max_seq))
        duplicated = max(0, received - max_seq)
        table.append((f"fleet-{f}", acknowledged, received, lost, duplicated))
        if lost or duplicated:
            failures.append(f"fleet-{f}: {lost} lost, {duplicated} duplicated")

    print("\n| fault | served again after | bound |\n|---|---|---|")
    late = []
    for name, seconds, bound, at in rows:
        print(f"| {name} | {seconds:.1f} s | {bound:.0f} s |")
        if seconds > bound:
            failures.append(f"{name}: {seconds:.1f} s, more than {bound:.0f} s")
            late.append(at)
    print("\n| fleet | acknowledged | received | lost | duplicated |\n|---|---|---|---|---|")
    for row in table:
        print("| " + " | ".join(str(x) for x in row) + " |")
    if failures:
        if late:
            print(replica_logs(cluster, min(late) - 1))
        print("FAILED:\n  " + "\n  ".join(failures))
        return 1
    print("cluster fault tests: 0 lost, 0 duplicated")
    return 0


if __name__ == "__main__":
    sys.exit(main())
