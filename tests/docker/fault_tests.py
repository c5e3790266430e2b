#!/usr/bin/env python3
"""Dockerized fault tests of a fleetmem fleet (`make test-docker`).

Builds the images from docker/server.Dockerfile and docker/robot.Dockerfile
on a local bookworm base (tests/docker/base_image.sh: this engine cannot
pull), brings up the compose fleet of docker/compose.yaml (server with auth
and TLS, three robots on the real Nordland summer drive, Prometheus) and
injects the faults of the field while the robots observe and upload:

  server SIGKILL      `docker kill -s KILL` of the server mid-upload, then
                      `docker start` on its volume
  robot offline 120s  `docker network disconnect` of robot-2 for two minutes
                      while it keeps observing, then reconnect
  robot SIGKILL       robot-1 killed and started again on its queue volume
  server upgrade      the server replaced by a new image version on the
                      same volume
  wrong encoder       a robot whose codes come from another encoder
  wrong robot id      a robot configured with another robot's id
  bad config file     a robot whose config file has an unknown option

Every trace is counted by (robot_id, seq): what each robot observed (its
status file: seqs 1..next_seq-1) against what the server stores (REST
ListTraces, every page) and has received (GetStats). Prints the table
(fault, observed, expected, stored, lost, duplicated, recovery time) and
exits 1 if any row loses or duplicates a trace or misses its log message;
exits 77 (skipped) when no Docker engine, docker-compose or debootstrap is
available.

Environment: FLEETMEM_DATA (../shared/data), FLEETMEM_DOCKER_KEEP=1 keeps the
fleet and its volumes after the run, FLEETMEM_DOCKER_OFFLINE_S (120),
FLEETMEM_DOCKER_TABLE (a file the table is also written to, markdown).
"""

import json
import os
import re
import shutil
import socket
import ssl
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.parse
import urllib.request

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
HERE = os.path.join(ROOT, "tests", "docker")
SKIP = 77
BASE_IMAGE = "fleetmem-local/bookworm:base"
PROMETHEUS_IMAGE = "fleetmem-local/prometheus:test"
VERSION, NEXT_VERSION = "0.1.0", "0.1.1"
FLEET = "nordland"
ROBOTS = ["robot-1", "robot-2", "robot-3"]
# Frames per robot and rate: long enough for the two minutes offline.
FRAMES, RATE = 600, 4
OFFLINE_S = float(os.environ.get("FLEETMEM_DOCKER_OFFLINE_S", "120"))
ROBOT_STATUS = "/var/lib/fleetmem-robot/status.json"
# The host's build, which the images take where that is sound (docker_build).
HOST_BIN = os.environ.get("FLEETMEM_HOST_BIN", os.path.join(ROOT, "build", "bin"))


def log(message):
    print(f"[{time.strftime('%H:%M:%S')}] {message}", flush=True)


def run(args, check=True, capture=True, env=None, timeout=None):
    result = subprocess.run(args, check=False, text=True, env=env,
                            timeout=timeout,
                            stdout=subprocess.PIPE if capture else None,
                            stderr=subprocess.STDOUT if capture else None)
    if check and result.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} exited {result.returncode}:\n"
                           f"{result.stdout or ''}")
    return result


def free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def preconditions():
    """Returns why the tests cannot run here, or None."""
    if shutil.which("docker") is None:
        return "no docker client"
    if run(["docker", "info"], check=False).returncode != 0:
        return "no Docker engine answers `docker info`"
    if shutil.which("docker-compose") is None:
        return "no docker-compose (Debian package docker-compose)"
    if shutil.which("debootstrap") is None and run(
            ["docker", "image", "inspect", BASE_IMAGE], check=False).returncode != 0:
        return "no debootstrap to build the local bookworm base image"
    return None


def host_build_unsound():
    """Why the host's build may not go into the images, or None. The images
    are bookworm with Debian's libraries; so is a bookworm host, from the
    same archive (base_image.sh), so its binaries load there as they do
    here (docker_build also checks that with ldd in the image).
    FLEETMEM_DOCKER_FROM_SOURCE=1 builds as a user's registry build does."""
    if os.environ.get("FLEETMEM_DOCKER_FROM_SOURCE") == "1":
        return "FLEETMEM_DOCKER_FROM_SOURCE=1"
    try:
        release = open("/etc/os-release").read()
    except OSError:
        return "no /etc/os-release"
    if "VERSION_CODENAME=bookworm" not in release:
        return "the host is not Debian bookworm"
    if not os.path.isdir(HOST_BIN):
        return f"no host build in {HOST_BIN}"
    return None


def runtime_stage(dockerfile):
    """A Dockerfile's global ARGs and its last stage, with what that stage
    copies from the build stage's /build/bin/ taken from bin/ of the build
    context instead; and the binaries it names."""
    lines = open(dockerfile).read().splitlines()
    froms = [i for i, l in enumerate(lines) if l.startswith("FROM ")]
    head = [l for l in lines[:froms[0]] if l.startswith("ARG ")]
    text = "\n".join(head + lines[froms[-1]:]) + "\n"
    binaries = sorted(set(re.findall(r"/build/bin/([\w.-]+)", text)))
    text = text.replace("--from=build /build/bin/", "bin/").replace("/build/bin/", "bin/")
    return text, binaries


def docker_build(relative, tag, build_args):
    """Builds ROOT/relative as `tag`. Paid once: Docker's layer cache reuses
    every layer whose inputs are unchanged on this machine, and a Dockerfile
    with a build stage (the project compiled in the image, ~10 minutes on 2
    cores) takes the host's build instead where that is sound
    (host_build_unsound): its last stage alone, over the host's stripped
    binaries. The image is then checked to load them (ldd); if it does not,
    it is built from source after all."""
    dockerfile = os.path.join(ROOT, relative)  # ctest runs us elsewhere
    args = [a for k, v in build_args.items() for a in ("--build-arg", f"{k}={v}")]
    unsound = host_build_unsound()
    if " AS build" in open(dockerfile).read() and unsound is None:
        text, binaries = runtime_stage(dockerfile)
        with tempfile.TemporaryDirectory(prefix="fleetmem-context-") as context:
            os.mkdir(os.path.join(context, "bin"))
            for b in binaries:
                run(["strip", "--strip-unneeded", "-o", os.path.join(context, "bin", b),
                     os.path.join(HOST_BIN, b)])
            shutil.copytree(os.path.join(ROOT, "docker"), os.path.join(context, "docker"))
            with open(os.path.join(context, "Dockerfile"), "w") as f:
                f.write(text)
            log(f"docker build {tag}: {relative}'s runtime stage over the host's "
                f"{', '.join(binaries)}")
            run(["docker", "build", "-q", "--force-rm", *args, "-t", tag, context],
                capture=False)
        missing = run(["docker", "run", "--rm", "--entrypoint", "sh", tag, "-c",
                       "ldd /usr/local/bin/* 2>&1 | grep 'not found' || true"]).stdout
        if not missing.strip():
            return
        log(f"the host's binaries do not load in {tag}:\n{missing}building from source")
    else:
        log(f"docker build -f {relative} -t {tag}" +
            (f" (from source: {unsound})" if unsound else ""))
    result = run(["docker", "build", "-q", "--force-rm", "-f", dockerfile, *args,
                  "-t", tag, ROOT], check=False)
    if result.returncode != 0:
        # Again with the output shown: the build log is the diagnosis.
        run(["docker", "build", "--force-rm", "-f", dockerfile, *args, "-t", tag, ROOT],
            capture=False)


def build_images():
    t0 = time.time()
    run([os.path.join(HERE, "base_image.sh"), BASE_IMAGE], capture=False)
    builds = [
        ("docker/server.Dockerfile", f"fleetmem/server:{VERSION}", VERSION),
        ("docker/robot.Dockerfile", f"fleetmem/robot:{VERSION}", VERSION),
        # The "new version": the same Dockerfile with the next version's
        # build argument (label and FLEETMEM_IMAGE_VERSION differ).
        ("docker/server.Dockerfile", f"fleetmem/server:{NEXT_VERSION}", NEXT_VERSION),
        ("tests/docker/prometheus.Dockerfile", PROMETHEUS_IMAGE, VERSION),
    ]
    for relative, tag, version in builds:
        docker_build(relative, tag, {"BASE_IMAGE": BASE_IMAGE, "FLEETMEM_VERSION": version})
    log(f"images built in {time.time() - t0:.0f} s")


class Fleet:
    """The compose fleet of one test run and the probes into it."""

    def __init__(self, workdir):
        self.project = f"fmtest{os.getpid()}"
        self.secrets = os.path.join(workdir, "secrets")
        self.http_port = free_port()
        data = os.environ.get("FLEETMEM_DATA", os.path.join(ROOT, "..", "shared", "data"))
        self.env = dict(os.environ,
                        COMPOSE_PROJECT_NAME=self.project,
                        FLEETMEM_BASE_IMAGE=BASE_IMAGE,
                        FLEETMEM_VERSION=VERSION,
                        FLEETMEM_SECRETS=self.secrets,
                        FLEETMEM_DATA=os.path.abspath(data),
                        FLEETMEM_PROMETHEUS_IMAGE=PROMETHEUS_IMAGE,
                        FLEETMEM_TEST_SERVER_CONFIG=os.path.join(HERE, "server-test.textproto"),
                        FLEETMEM_GRPC_PORT=str(free_port()),
                        FLEETMEM_HTTP_PORT=str(self.http_port),
                        FLEETMEM_PROMETHEUS_PORT=str(free_port()),
                        FLEETMEM_GRAFANA_PORT=str(free_port()),
                        FLEETMEM_ROBOT_FRAMES=str(FRAMES),
                        FLEETMEM_ROBOT2_LAST=str(800 + FRAMES),
                        FLEETMEM_ROBOT3_LAST=str(1600 + FRAMES),
                        FLEETMEM_ROBOT_RATE=str(RATE))
        self.network = f"{self.project}_fleet"
        self.ssl = None
        self.token = None

    def compose(self, *args, check=True):
        return run(["docker-compose", "-f", os.path.join(ROOT, "docker", "compose.yaml"),
                    "-f", os.path.join(HERE, "compose.test.yaml"), *args],
                   check=check, env=self.env)

    def make_secrets(self):
        run([os.path.join(ROOT, "docker", "make-secrets.sh"), self.secrets],
            env=dict(self.env, FLEETMEM_SERVER_IMAGE=f"fleetmem/server:{VERSION}"))
        self.ssl = ssl.create_default_context(cafile=os.path.join(self.secrets, "ca.pem"))
        with open(os.path.join(self.secrets, "ops.token")) as f:
            self.token = f.read().strip()

    def container(self, service):
        out = self.compose("ps", "-q", service).stdout.strip()
        if not out:
            raise RuntimeError(f"no container for {service}")
        return out.splitlines()[-1]

    # --- the server, through its REST port with the admin's token ---------
    def rest(self, path, timeout=5):
        request = urllib.request.Request(
            f"https://127.0.0.1:{self.http_port}{path}",
            headers={"Authorization": f"Bearer {self.token}"})
        with urllib.request.urlopen(request, context=self.ssl, timeout=timeout) as r:
            return json.load(r)

    def received(self):
        """{robot: traces received} from GetStats, or None if unreachable."""
        try:
            stats = self.rest(f"/v1/fleets/{FLEET}/stats")
        except (urllib.error.URLError, OSError, ValueError):
            return None
        # Robots that only read (a refused robot's queries and replay draws)
        # are listed with nothing received: leave them out.
        received = {r["robotId"]: int(r.get("received", 0)) for r in stats.get("robots", [])}
        return {robot: n for robot, n in received.items() if n > 0}

    def wait_applied(self, timeout=120):
        """Waits until the fleet's log is applied through every upload
        acknowledged (robots upload with durable acknowledgement: a robot
        that has finished may have traces still waiting to be applied)."""
        deadline = time.time() + timeout
        while time.time() < deadline:
            try:
                stats = self.rest(f"/v1/fleets/{FLEET}/stats")
            except (urllib.error.URLError, OSError, ValueError):
                stats = None
            if stats is not None and int(stats.get("appliedThrough", 0)) >= int(
                    stats.get("acknowledgedThrough", 0)):
                return
            time.sleep(0.2)
        raise RuntimeError(f"the fleet's log was not applied within {timeout} s")

    def stored(self):
        """[(robot_id, seq)] of every trace ListTraces returns, all pages."""
        keys, token = [], ""
        while True:
            query = urllib.parse.urlencode({"pageSize": 5000, "pageToken": token})
            page = self.rest(f"/v1/fleets/{FLEET}/traces?{query}", timeout=30)
            keys += [(t["robotId"], int(t["seq"])) for t in page.get("traces", [])]
            token = page.get("nextPageToken", "")
            if not token:
                return keys

    def wait_healthy(self, service, timeout=120):
        container = self.container(service)
        deadline = time.time() + timeout
        while time.time() < deadline:
            state = run(["docker", "inspect", "-f", "{{.State.Health.Status}}", container],
                        check=False).stdout.strip()
            if state == "healthy":
                return
            time.sleep(0.5)
        raise RuntimeError(f"{service} not healthy within {timeout} s:\n" +
                           run(["docker", "logs", "--tail", "30", container], check=False).stdout)

    # --- robots -----------------------------------------------------------
    def robot_status(self, service):
        return container_status(self.container(service))

    def observed(self, service):
        status = self.robot_status(service) or {}
        counters = status.get("counters", {})
        return int(counters.get("nextSeq", 1)) - 1, int(counters.get("observations", 0))

    def logs(self, container):
        return run(["docker", "logs", container], check=False).stdout


def container_status(container):
    """A robot container's status file (docker cp works on stopped ones)."""
    result = run(["docker", "cp", f"{container}:{ROBOT_STATUS}", "-"], check=False)
    if result.returncode != 0:
        return None
    # `docker cp ... -` writes a tar stream: the JSON is its one member.
    text = result.stdout
    start, end = text.find("{"), text.rfind("}")
    return json.loads(text[start:end + 1]) if start >= 0 else None


def wait_until(what, predicate, timeout, poll=0.5):
    deadline = time.time() + timeout
    while time.time() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll)
    raise RuntimeError(f"timed out after {timeout:.0f} s waiting for {what}")


def count(keys, robots, observed, received):
    """Row counts for `robots`: observed, expected (= observed), stored,
    lost, duplicated, unexpected (stored but never observed)."""
    rows = [k for k in keys if k[0] in robots]
    unique = set(rows)
    expected = {(r, s) for r in robots for s in range(1, observed.get(r, 0) + 1)}
    lost = len(expected - unique)
    # A key listed twice, or received more often than it is stored.
    duplicated = (len(rows) - len(unique)) + sum(
        max(0, received.get(r, 0) - sum(1 for k in unique if k[0] == r)) for r in robots)
    extra = len(unique - expected)
    return len(expected), len(expected), len(rows), lost, duplicated, extra


def main():
    why = preconditions()
    if why:
        print(f"fault_tests.py: SKIPPED: {why}", flush=True)
        return SKIP
    build_images()
    workdir = tempfile.mkdtemp(prefix="fleetmem-docker-")
    fleet = Fleet(workdir)
    rows, failures = [], []
    try:
        fleet.make_secrets()
        log(f"compose up (project {fleet.project}): server, {', '.join(ROBOTS)}, prometheus")
        fleet.compose("up", "-d", "--no-build", "fleetmem-server", *ROBOTS, "prometheus")
        fleet.wait_healthy("fleetmem-server")
        server = fleet.container("fleetmem-server")
        robots = {r: fleet.container(r) for r in ROBOTS}
        t_start = time.time()
        # The Kubernetes liveness probe (k8s/base): the gRPC health service
        # over TLS through the image's CLI.
        probe = run(["docker", "exec", server, "fleetmem", "--server=127.0.0.1:50051",
                     "--tls-ca=/run/secrets/ca.pem", "--tls-server-name=fleetmem-server",
                     "health"], check=False)
        log(f"gRPC health probe in the server image: {probe.stdout.strip()}")
        if probe.returncode != 0 or probe.stdout.strip() != "SERVING":
            failures.append(f"gRPC health probe: exit {probe.returncode}: {probe.stdout}")

        # 1. Server SIGKILL mid-upload, as soon as every robot has uploaded.
        def uploading(got):
            return got.keys() >= set(ROBOTS) and min(got.values()) >= 10
        wait_until("every robot uploading", lambda: uploading(fleet.received() or {}), 90)
        before = sum(fleet.received().values())
        log(f"fault: docker kill -s KILL server ({before} traces received so far)")
        t_kill = time.time()
        run(["docker", "kill", "-s", "KILL", server])
        time.sleep(3)
        run(["docker", "start", server])
        wait_until("the server answering and receiving again",
                   lambda: sum((fleet.received() or {}).values()) > before,
                   120)
        server_recovery = time.time() - t_kill
        log(f"server back and receiving after {server_recovery:.1f} s")

        # 2. robot-2 offline for OFFLINE_S while it keeps observing; 3. robot-1
        # SIGKILLed and started again meanwhile.
        log(f"fault: docker network disconnect robot-2 for {OFFLINE_S:.0f} s")
        run(["docker", "network", "disconnect", fleet.network, robots["robot-2"]])
        t_offline = time.time()
        _, observations_offline = fleet.observed("robot-2")
        time.sleep(10)
        got = fleet.received() or {}
        log("fault: docker kill -s KILL robot-1")
        t_robot_kill = time.time()
        robot1_before = got.get("robot-1", 0)
        run(["docker", "kill", "-s", "KILL", robots["robot-1"]])
        time.sleep(2)
        run(["docker", "start", robots["robot-1"]])
        wait_until("robot-1 uploading again",
                   lambda: (fleet.received() or {}).get("robot-1", 0) > robot1_before, 120)
        robot_recovery = time.time() - t_robot_kill
        log(f"robot-1 resumed and uploading after {robot_recovery:.1f} s")
        time.sleep(max(0.0, OFFLINE_S - (time.time() - t_offline)))
        _, observations_back = fleet.observed("robot-2")
        run(["docker", "network", "connect", fleet.network, robots["robot-2"]])
        t_reconnect = time.time()
        kept_observing = observations_back - observations_offline
        log(f"robot-2 reconnected; it made {kept_observing} observations offline")
        if kept_observing <= 0:
            failures.append("robot-2 did not keep observing while offline")

        # The backlog: every trace robot-2 had sealed when it came back. The
        # recovery ends when the server has all of it (uploads go in seq
        # order, once each, so "received" is the highest seq stored).
        backlog = int(fleet.robot_status("robot-2")["counters"]["nextSeq"]) - 1
        queued_at_reconnect = backlog - (fleet.received() or {}).get("robot-2", 0)
        wait_until("robot-2's backlog on the server",
                   lambda: (fleet.received() or {}).get("robot-2", 0) >= backlog, 300)
        offline_recovery = time.time() - t_reconnect
        log(f"robot-2's backlog of {queued_at_reconnect} traces was on the server "
            f"{offline_recovery:.1f} s after reconnecting")

        # Every robot finishes its drive and drains (exit 0).
        for name, container in robots.items():
            code = run(["docker", "wait", container], timeout=600).stdout.strip()
            if code != "0":
                failures.append(f"{name} exited {code}:\n{fleet.logs(container)[-2000:]}")
        log(f"robots finished {time.time() - t_start:.0f} s after the start")
        # A robot that exits 3 (its queue did not drain within its
        # --drain-timeout) is started again by its restart policy: count it.
        restarts = {name: int(run(["docker", "inspect", "-f", "{{.RestartCount}}", c]).stdout)
                    for name, c in robots.items()}
        log(f"restarts by the restart policy: {restarts}")
        reopened = fleet.logs(robots["robot-2"]).count("opened a new connection")
        observed = {r: fleet.observed(r)[0] for r in ROBOTS}
        fleet.wait_applied()
        received = fleet.received() or {}
        keys = fleet.stored()
        report_sizing(fleet, server, robots, len(keys))
        check_prometheus(fleet, len(keys), failures)
        rows.append(("server SIGKILL mid-upload, restart on its volume",
                     *count(keys, ROBOTS, observed, received), f"{server_recovery:.1f} s"))
        rows.append((f"robot-2 offline {OFFLINE_S:.0f} s, kept observing "
                     f"({kept_observing} observations, {queued_at_reconnect} queued; "
                     f"uploader reconnected {reopened}x, restarted "
                     f"{restarts['robot-2']}x by its policy)", *count(keys, ["robot-2"], observed, received),
                     f"{offline_recovery:.1f} s"))
        rows.append(("robot-1 SIGKILL, restart on its queue",
                     *count(keys, ["robot-1"], observed, received), f"{robot_recovery:.1f} s"))

        # 4. The server replaced by the next image version on the same volume.
        log(f"fault: server replaced by fleetmem/server:{NEXT_VERSION}")
        t_upgrade = time.time()
        fleet.env["FLEETMEM_VERSION"] = NEXT_VERSION
        fleet.compose("up", "-d", "--no-build", "--no-deps", "fleetmem-server")
        fleet.wait_healthy("fleetmem-server")
        upgrade_recovery = time.time() - t_upgrade
        server = fleet.container("fleetmem-server")
        image = run(["docker", "inspect", "-f", "{{.Config.Image}}", server]).stdout.strip()
        if image != f"fleetmem/server:{NEXT_VERSION}":
            failures.append(f"upgrade: the server runs {image}")
        after_keys = fleet.stored()
        after_received = fleet.received() or {}
        if sorted(after_keys) != sorted(keys) or after_received != received:
            failures.append("upgrade: the state differs from before the upgrade")
        rows.append((f"server upgraded {VERSION} -> {NEXT_VERSION}, same volume",
                     *count(after_keys, ROBOTS, observed, after_received),
                     f"{upgrade_recovery:.1f} s"))

        # 5. Robots that must be refused: nothing of theirs is stored.
        rows += refused_robots(fleet, observed, failures)
    except Exception as error:  # report what happened, then clean up
        failures.append(f"{type(error).__name__}: {error}")
        try:
            for service in ["fleetmem-server", *ROBOTS]:
                print(f"--- last log lines of {service}:\n" +
                      fleet.logs(fleet.container(service))[-3000:])
        except Exception:
            pass
    finally:
        if os.environ.get("FLEETMEM_DOCKER_KEEP") != "1":
            fleet.compose("down", "-v", "--remove-orphans", check=False)
            shutil.rmtree(workdir, ignore_errors=True)
            # Build stages of older sources (untagged, ~3 GB each): keep a
            # day's worth as build cache, drop the rest.
            run(["docker", "image", "prune", "-f", "--filter", "until=24h"], check=False)
        else:
            log(f"kept: project {fleet.project}, secrets in {fleet.secrets}")

    print_table(rows)
    # Rows: (fault, observed, expected, stored, lost, duplicated,
    # unexpected, recovery).
    for row in rows:
        if row[4] != 0 or row[5] != 0 or row[6] != 0:
            failures.append(f"{row[0]}: lost {row[4]}, duplicated {row[5]}, "
                            f"unexpected {row[6]}")
    if failures:
        print("fault_tests.py: FAILED\n  " + "\n  ".join(failures), flush=True)
        return 1
    print("fault_tests.py: every fault: 0 lost, 0 duplicated", flush=True)
    return 0


def check_prometheus(fleet, traces, failures):
    """Prometheus (in the fleet) scrapes the server over TLS: its target is
    up and its traces + pending gauges add up to the stored count."""
    port = fleet.env["FLEETMEM_PROMETHEUS_PORT"]

    def query(expr):
        url = f"http://127.0.0.1:{port}/api/v1/query?" + urllib.parse.urlencode({"query": expr})
        with urllib.request.urlopen(url, timeout=5) as r:
            return json.load(r)["data"]["result"]

    def scraped():
        try:
            up = query('up{job="fleetmem"}')
            gauge = query(f'fleetmem_fleet_traces{{fleet="{FLEET}"}} + '
                          f'fleetmem_fleet_pending_traces{{fleet="{FLEET}"}}')
        except (urllib.error.URLError, OSError, KeyError, ValueError):
            return None
        if up and up[0]["value"][1] == "1" and gauge and \
                int(float(gauge[0]["value"][1])) == traces:
            return gauge[0]["value"][1]
        return None
    try:
        value = wait_until("Prometheus to scrape the stored count", scraped, 60, poll=2)
        log(f"prometheus: target up; it has scraped {value} traces (+ pending)")
    except RuntimeError as error:
        failures.append(f"prometheus: {error}")


def report_sizing(fleet, server, robots, traces):
    """Measured memory and disk of the fleet, for docs/deployment.md."""
    stats = fleet.rest(f"/v1/fleets/{FLEET}/stats")
    memory = run(["docker", "stats", "--no-stream", "--format", "{{.MemUsage}}", server],
                 check=False).stdout.strip().split(" / ")[0]
    disk = run(["docker", "exec", server, "du", "-sb", "/var/lib/fleetmem"],
               check=False).stdout.split()
    disk_bytes = int(disk[0]) if disk and disk[0].isdigit() else 0
    queue = run(["docker", "run", "--rm", "--volumes-from", robots["robot-1"], "--entrypoint",
                 "du", f"fleetmem/robot:{VERSION}", "-sb", "/var/lib/fleetmem-robot"],
                check=False).stdout.split()
    images = ", ".join(
        f"{tag} {int(run(['docker', 'image', 'inspect', '-f', '{{.Size}}', tag]).stdout) / 1e6:.0f} MB"
        for tag in (f"fleetmem/server:{VERSION}", f"fleetmem/robot:{VERSION}"))
    log(f"images: {images}")
    log(f"sizing: {traces} traces of dimension {stats.get('codeDimension')} in "
        f"{stats.get('clusters')} clusters; server memory {memory}; server data dir "
        f"{disk_bytes / 2**20:.1f} MiB ({disk_bytes / max(traces, 1):.0f} B per trace); "
        f"robot-1's data dir (queue drained) {int(queue[0]) / 2**20 if queue and queue[0].isdigit() else 0:.1f} MiB")


def refused_robots(fleet, observed, failures):
    """Robots with a wrong encoder, another robot's id and a bad config file:
    a clear error in the robot's log (and the server's, when the robot got as
    far as the server), nothing stored."""
    server = fleet.container("fleetmem-server")
    image = f"fleetmem/robot:{VERSION}"
    secrets = ["-v", f"{fleet.secrets}/ca.pem:/run/secrets/ca.pem:ro",
               "-v", f"{fleet.secrets}/robot-4.token:/run/secrets/robot-4.token:ro",
               "-v", f"{fleet.env['FLEETMEM_DATA']}/nordland:/recordings:ro"]
    common = ["--fleet=nordland", "--server=fleetmem-server:50051",
              "--tls-ca=/run/secrets/ca.pem", "--tls-server-name=fleetmem-server",
              "--token-file=/run/secrets/robot-4.token",
              "--source=nordland:/recordings/summer", "--first=2300", "--last=2340",
              "--data-dir=/var/lib/fleetmem-robot", "--segment-size=20",
              "--drain-timeout=20"]
    cases = [
        ("robot with a wrong encoder version", "robot-4",
         ["--robot-id=robot-4", "--encoder=hog-64x32-c8-s16"],
         "encoder_version", "encoder_version", None),
        ("robot configured with another robot's id", "robot-1",
         ["--robot-id=robot-1"], "PERMISSION_DENIED", "PERMISSION_DENIED", None),
        ("robot with a bad config file", "robot-4",
         ["--robot-id=robot-4", "--config=/run/bad.toml"], "bad-option", None,
         "upload-batchh = 10\n"),
    ]
    rows = []
    for n, (what, robot_id, flags, robot_says, server_says, config) in enumerate(cases):
        before_keys = fleet.stored()
        before = fleet.received() or {}
        extra = []
        if config is not None:
            path = os.path.join(fleet.secrets, f"bad-{n}.toml")
            with open(path, "w") as f:
                f.write(config)
            os.chmod(path, 0o644)
            extra = ["-v", f"{path}:/run/bad.toml:ro"]
        server_log_before = len(fleet.logs(server))
        log(f"fault: {what}")
        name = f"{fleet.project}-refused-{n}"
        result = run(["docker", "run", "--name", name, "--network", fleet.network,
                      *secrets, *extra, "--entrypoint", "fleetmem-robot", image,
                      *common, *flags], check=False, timeout=300)
        robot_log = result.stdout
        # Traces it queued (not next_seq - 1: a robot starting as robot-1
        # continues robot-1's sequence from the server's max_seq).
        status = container_status(name) or {}
        queued = int(status.get("counters", {}).get("tracesQueued", 0))
        run(["docker", "rm", "-v", name], check=False)
        server_log = fleet.logs(server)[server_log_before:]
        after_keys = fleet.stored()
        after = fleet.received() or {}
        stored = len(after_keys) - len(before_keys)
        changed = sorted(after_keys) != sorted(before_keys) or after != before
        if result.returncode == 0:
            failures.append(f"{what}: the robot exited 0")
        if config is not None:
            robot_says = "upload-batchh"
        if robot_says not in robot_log:
            failures.append(f"{what}: the robot's log lacks {robot_says!r}:\n{robot_log[-1500:]}")
        if server_says is not None and (server_says not in server_log or
                                        "UploadTraces refused" not in server_log):
            failures.append(f"{what}: the server's log lacks the refusal "
                            f"({server_says!r}):\n{server_log[-1500:]}")
        if changed:
            failures.append(f"{what}: the server's traces changed")
        first_error = next((line for line in robot_log.splitlines()
                            if robot_says in line), "")[:90]
        log(f"  robot exit {result.returncode}: {first_error}")
        # Expected: nothing stored; anything that is counts as unexpected.
        rows.append((f"{what} (exit {result.returncode})", queued, 0, stored, 0,
                     0, stored if changed else 0, "-"))
    return rows


def print_table(rows):
    header = ("fault", "observed", "expected", "stored", "lost", "duplicated",
              "unexpected", "recovery")
    lines = ["| " + " | ".join(header) + " |",
             "|" + "|".join(["---"] + ["---:"] * (len(header) - 1)) + "|"]
    for row in rows:
        lines.append("| " + " | ".join(str(cell) for cell in row) + " |")
    table = "\n".join(lines)
    print(table, flush=True)
    path = os.environ.get("FLEETMEM_DOCKER_TABLE")
    if path:
        with open(path, "w") as f:
            f.write(table + "\n")


if __name__ == "__main__":
    sys.exit(main())
