"""fleetmem.Client against the real fleetmem-server binary."""

import threading
import time

import numpy as np
import pytest

import fleetmem
from conftest import BIN_DIR, Server


def codes_of(seed, n, dim=64):
    codes = np.random.default_rng(seed).standard_normal((n, dim)).astype(np.float32)
    return codes / np.linalg.norm(codes, axis=1, keepdims=True)


def test_two_robots_upload_query_sample_and_export(server):
    a, b = codes_of(1, 1200), codes_of(2, 800)
    places_a = np.stack([np.arange(1200) * 10.0, np.zeros(1200)], axis=1)
    with fleetmem.Client(server.address) as fm:
        first = fm.upload("f1", a, places_a, rewards=np.linspace(0.1, 1, 1200), robot_id="robot-a",
                          seqs=np.arange(1200))
        assert (first.accepted, first.duplicates, first.applied) == (1200, 0, True)
        notes = np.random.default_rng(3).integers(0, 256, (800, 24), dtype=np.uint8)
        second = fm.upload("f1", b, np.arange(800) * 10.0, 0.5, robot_id="robot-b", seqs=np.arange(1000, 1800),
                           domain="winter", attachments=notes, ack="durable")
        assert (second.accepted, second.duplicates) == (800, 0) and second.last_sequence > 0
        with pytest.warns(fleetmem.DuplicateUploadWarning):
            again = fm.upload("f1", a[:100], robot_id="robot-a", seqs=np.arange(100))
        assert (again.accepted, again.duplicates) == (0, 100)

        stats = fm.stats("f1")
        while stats.applied_through < second.last_sequence:  # durable: applied a moment later
            stats = fm.stats("f1")
        assert stats.traces + stats.pending_traces == 2000 and stats.code_dimension == 64
        assert sorted(r.robot_id for r in stats.robots) == ["robot-a", "robot-b"]

        for i in (0, 599, 1199):
            match = fm.query_place("f1", a[i], k=3)
            assert len(match) == 3 and match.distances[0] < 1e-3
            assert (match.traces.robot_ids[0], int(match.traces.seqs[0])) == ("robot-a", i)
            np.testing.assert_allclose(match.traces.places[0, :2], places_a[i])
        near = fm.query_place("f1", b[5], k=5, near=(50.0, 0.0), radius_m=25.0)
        assert np.all(np.abs(near.traces.places[:, 0] - 50.0) <= 25.0)

        replay = fm.sample_replay("f1", "robot-a", 64)
        assert replay.codes.shape == (64, 64) and replay.places.shape == (64, 4)
        assert len(set(zip(replay.robot_ids, replay.seqs.tolist()))) == 64
        assert np.all(replay.replay_counts >= 1) and replay.codes.dtype == np.float32

        exported = fm.export("f1", page_size=300)
        assert len(exported) == 2000
        rows = {(r, int(s)): i for i, (r, s) in enumerate(zip(exported.robot_ids, exported.seqs))}
        np.testing.assert_array_equal(exported.codes[[rows[("robot-a", i)] for i in range(1200)]], a)
        np.testing.assert_array_equal(exported.codes[[rows[("robot-b", 1000 + i)] for i in range(800)]], b)
        assert {d for r, d in zip(exported.robot_ids, exported.domains) if r == "robot-b"} == {"winter"}
        assert [exported.attachments[rows[("robot-b", 1000 + i)]] for i in range(800)] == [x.tobytes() for x in notes]


def test_the_cli_export_loads(server, cli, tmp_path):
    codes = codes_of(3, 300)
    with fleetmem.Client(server.address) as fm:
        fm.upload("f2", codes, np.arange(300.0), robot_id="robot-a", seqs=np.arange(300) + 7)
    cli("--server", server.address, "export", "--fleet", "f2", "--out", str(tmp_path / "out"))
    loaded = fleetmem.load_export(tmp_path / "out")
    order = np.argsort(loaded.seqs)
    np.testing.assert_array_equal(loaded.codes[order], codes)
    np.testing.assert_array_equal(loaded.seqs[order], np.arange(300) + 7)
    np.testing.assert_array_equal(loaded.places[order, 0], np.arange(300.0))


def test_an_export_imports_into_a_new_fleet(server):
    codes = codes_of(4, 900)
    with fleetmem.Client(server.address) as fm:
        fm.upload("f3", codes, np.arange(900.0), rewards=np.linspace(0.5, 1, 900), robot_id="robot-a",
                  seqs=np.arange(900))
        exported = fm.export("f3")
        result = fm.import_traces("f3-copy", exported.codes, exported.places, exported.rewards,
                                  robot_ids=exported.robot_ids, seqs=exported.seqs,
                                  domains=exported.domains, chunk=250)
        assert (result.accepted, result.duplicates, result.unindexed_codes) == (len(exported), 0, 0)
        assert result.fleet_traces == len(exported)
        copy = fm.export("f3-copy")
        np.testing.assert_array_equal(copy.codes, exported.codes)
        np.testing.assert_array_equal(copy.rewards, exported.rewards)
        match = fm.query_place("f3-copy", codes[123], k=1)
        assert int(match.traces.seqs[0]) == 123 and match.distances[0] < 1e-3
        with pytest.raises(fleetmem.FleetMemError) as refused:
            fm.import_traces("f3-copy", exported.codes, robot_ids="robot-a", seqs=exported.seqs)
        assert refused.value.code.name == "FAILED_PRECONDITION"
        again = fm.import_traces("f3-copy", exported.codes, robot_ids=exported.robot_ids,
                                 seqs=exported.seqs, resume=True)
        assert (again.accepted, again.duplicates) == (0, len(exported))
        with pytest.raises(ValueError, match="robot_ids"):
            fm.import_traces("f4", codes[:3], robot_ids=["a", "b"], seqs=[1, 2, 3])


def test_errors_carry_the_servers_status(server):
    with fleetmem.Client(server.address, max_attempts=1) as fm:
        with pytest.raises(fleetmem.FleetMemError) as missing:
            fm.stats("no-such-fleet")
        assert missing.value.status == "NOT_FOUND" and "no-such-fleet" in missing.value.message
        fm.upload("f3", codes_of(4, 10), robot_id="r1", seqs=np.arange(10))
        with pytest.raises(fleetmem.FleetMemError) as wrong:
            fm.query_place("f3", np.ones(7))
        assert wrong.value.status == "INVALID_ARGUMENT" and "dimension" in wrong.value.message
        with pytest.raises(fleetmem.FleetMemError) as bad:
            fm.upload("f3", codes_of(5, 3, dim=64) * np.nan, robot_id="r1", seqs=[100, 101, 102])
        assert bad.value.status == "INVALID_ARGUMENT"
        assert fm.stats("f3").traces + fm.stats("f3").pending_traces == 10  # nothing of it stored
        # Issue 32's poisoning batch: finite values whose squared norm
        # overflows float32 are refused, naming the trace.
        poison = np.tile(np.array([3e38, -3e38], np.float32), 32)[None, :]
        with pytest.raises(fleetmem.FleetMemError) as poisoned:
            fm.upload("f3", poison, robot_id="r2", seqs=[1])
        assert poisoned.value.status == "INVALID_ARGUMENT" and "traces[0].code has norm" in poisoned.value.message
        own = codes_of(4, 10)
        assert all(int(fm.query_place("f3", own[i]).traces.seqs[0]) == i for i in range(10))
        with pytest.raises(ValueError, match="places"):
            fm.upload("f3", codes_of(6, 3), np.zeros((2, 3)), robot_id="r1", seqs=[0, 1, 2])
        with pytest.raises(ValueError, match="seqs"):
            fm.upload("f3", codes_of(6, 3), robot_id="r1", seqs=[-1, 0, 1])
        with pytest.raises(ValueError, match="seqs"):
            fm.upload("f3", codes_of(6, 3), robot_id="r1", seqs=[5, 6, 5])  # not distinct


def test_watch_resumes_across_a_server_restart(server):
    with fleetmem.Client(server.address) as fm:
        fm.upload("w", codes_of(7, 300), robot_id="r1", seqs=np.arange(300))
        fm.consolidate("w")
        watch = fm.watch("w", idle_timeout=30)
        events = iter(watch)
        before = [next(events) for _ in range(fm.stats("w").last_event_id)]
        assert [e.id for e in before] == list(range(1, len(before) + 1))

        server.stop()
        server.start()
        fm.upload("w", codes_of(8, 300), robot_id="r2", seqs=np.arange(300))
        fm.consolidate("w")
        last = fm.stats("w").last_event_id
        after = [next(events) for _ in range(last - len(before))]
        assert [e.id for e in after] == list(range(len(before) + 1, last + 1))
        assert {e.robot_id for e in after} == {"r2"}

        closer = threading.Timer(0.5, watch.close)
        closer.start()
        assert list(events) == []  # close() ends the iteration
        closer.join()


def test_tokens_from_files(tmp_path):
    credentials = tmp_path / "credentials.textproto"
    import subprocess
    for name, role in (("robot-7", "robot"), ("ops", "reader")):
        with open(credentials, "a") as out:
            subprocess.run([str(BIN_DIR / "fleetmem-credential"), "--name", name, "--role", role,
                            "--fleet", "f1", "--token-file", str(tmp_path / f"{name}.token")],
                           stdout=out, check=True)
    server = Server(tmp_path / "data", "--auth-file", str(credentials)).start()
    try:
        with fleetmem.Client(server.address, token_file=str(tmp_path / "robot-7.token")) as robot:
            assert robot.upload("f1", codes_of(9, 20), robot_id="robot-7", seqs=np.arange(20)).accepted == 20
            with pytest.raises(fleetmem.FleetMemError) as other:
                robot.upload("f1", codes_of(9, 20), robot_id="robot-8", seqs=np.arange(20))
            assert other.value.status == "PERMISSION_DENIED"
        with fleetmem.Client(server.address, token_file=str(tmp_path / "ops.token")) as reader:
            assert reader.stats("f1").traces + reader.stats("f1").pending_traces == 20
        with fleetmem.Client(server.address, token="ops:wrong", max_attempts=1) as wrong:
            with pytest.raises(fleetmem.FleetMemError) as refused:
                wrong.stats("f1")
            assert refused.value.status == "UNAUTHENTICATED"
    finally:
        server.stop()


def test_every_program_says_its_version():
    import subprocess
    programs = [p for p in ("fleetmem", "fleetmem-server", "fleetmem-robot", "fleetmem-credential",
                            "fleetmem-demo", "fleetmem-eval", "fleetmem-load") if (BIN_DIR / p).exists()]
    assert "fleetmem-server" in programs and "fleetmem" in programs  # (builds without the demo lack it)
    for program in programs:
        done = subprocess.run([str(BIN_DIR / program), "--version"], capture_output=True, text=True)
        assert done.returncode == 0 and done.stdout.startswith(f"{program} {fleetmem.__version__}"), \
            (program, done.stdout, done.stderr)


def test_read_calls_create_no_fleet(server):
    with fleetmem.Client(server.address, max_attempts=1) as fm:
        for call in (lambda: fm.stats("ghost"), lambda: fm.query_place("ghost", np.ones(4)),
                     lambda: fm.clusters("ghost"), lambda: fm.export("ghost")):
            try:
                call()
            except fleetmem.FleetMemError as error:
                assert error.status == "NOT_FOUND", error
        assert list(fm.watch("ghost", idle_timeout=0.3)) == []
        assert [f.fleet_id for f in fm.fleets()] == []


def test_bad_arguments_are_python_errors_and_standing_limits_are_not_retried(tmp_path):
    """Issue 44 (the outside sweep): a non-str id raised UNKNOWN "Exception
    iterating requests!" from deep in gRPC, complex codes lost their
    imaginary part silently, and a standing limit (RESOURCE_EXHAUSTED
    "limit max_fleets ...") was retried max_attempts times."""
    config = tmp_path / "server.textproto"
    config.write_text("limits { max_fleets: 1 }\n")
    server = Server(tmp_path / "data", "--config", str(config)).start()
    try:
        with fleetmem.Client(server.address, max_attempts=4, initial_backoff=0.5) as fm:
            with pytest.raises(TypeError, match="robot_id"):
                fm.upload("f1", codes_of(1, 2), robot_id=7, seqs=[0, 1])
            with pytest.raises(TypeError, match="fleet"):
                fm.upload(b"f1", codes_of(1, 2), robot_id="r1", seqs=[0, 1])
            with pytest.raises(TypeError, match="codes"):
                fm.upload("f1", codes_of(1, 2) * (1 + 1j), robot_id="r1", seqs=[0, 1])
            with pytest.raises(TypeError, match="code"):
                fm.query_place("f1", np.ones(64) * 1j)
            fm.upload("f1", codes_of(1, 2), robot_id="r1", seqs=[0, 1])
            # Issue 48: every array argument's shape is checked before
            # anything is sent (a 2-D code went out flat: "dimension 128").
            code = codes_of(1, 2)[0]
            for bad, match in ((codes_of(1, 2), "query_places"), (np.ones((1, 64)), "1-D"),
                               (np.array([]), "1-D"), (np.full(64, np.nan), "NaN")):
                with pytest.raises(ValueError, match=match):
                    fm.query_place("f1", bad)
            with pytest.raises(ValueError, match="1-D"):
                fm.query_place("f1", {"v1": codes_of(1, 2)})
            with pytest.raises(ValueError, match="near"):
                fm.query_place("f1", code, near=[1.0])
            with pytest.raises(ValueError, match="near"):
                fm.query_places("f1", codes_of(1, 2), near=np.zeros((2, 2)))
            with pytest.raises(ValueError, match="k"):
                fm.query_place("f1", code, k=0)
            with pytest.raises(TypeError, match="k"):
                fm.query_place("f1", code, k=2.5)
            with pytest.raises(ValueError, match="count"):
                fm.sample_replay("f1", "r1", -1)
            with pytest.raises(ValueError, match="codes"):
                fm.query_places("f1", code)
            assert len(fm.query_place("f1", code, k=2, near=(0.0, 0.0), radius_m=1e9)) == 2
            # An upload of which nothing is new says so.
            with pytest.warns(fleetmem.DuplicateUploadWarning, match="nothing was stored"):
                again = fm.upload("f1", codes_of(1, 2), robot_id="r1", seqs=[0, 1])
            assert again.all_duplicates and again.duplicates == 2
            started = time.monotonic()
            with pytest.raises(fleetmem.FleetMemError) as limit:
                fm.upload("f2", codes_of(2, 2), robot_id="r1", seqs=[0, 1])
            assert limit.value.status == "RESOURCE_EXHAUSTED"
            assert "limit max_fleets" in limit.value.message
            # Three retries would have waited at least 0.25 + 0.5 + 1 s.
            assert time.monotonic() - started < 0.5
    finally:
        server.stop()


def test_a_deleted_robot_is_gone_from_every_read_and_rewards_change_the_draw(server, cli):
    a, b = codes_of(11, 300), codes_of(12, 300)
    with fleetmem.Client(server.address) as fm:
        fm.upload("f1", a, np.arange(300) * 5.0, 1.0, robot_id="robot-a", seqs=np.arange(300))
        fm.upload("f1", b, np.arange(300) * 5.0, 1.0, robot_id="robot-b", seqs=np.arange(300),
                  domain="winter")
        with pytest.raises(ValueError):
            fm.delete_traces("f1")  # a selection of nothing deletes everything: refused here
        with pytest.raises(fleetmem.FleetMemError) as refused:
            fm.delete_traces("f1", seq_first=3)  # a seq range without its robot
        assert refused.value.status == "INVALID_ARGUMENT"

        deleted = fm.delete_traces("f1", robot_id="robot-b")
        assert deleted.deleted == 300 and deleted.traces == 300
        assert set(fm.export("f1").robot_ids) == {"robot-a"}
        assert set(fm.sample_replay("f1", "robot-a", 300).robot_ids) == {"robot-a"}
        for i in (0, 150, 299):
            assert fm.query_place("f1", b[i], k=10).traces.robot_ids == ["robot-a"] * 10
        stats = fm.stats("f1")
        assert stats.traces + stats.pending_traces == 300
        with pytest.warns(fleetmem.DuplicateUploadWarning):
            again = fm.upload("f1", b[:50], robot_id="robot-b", seqs=np.arange(50))
        assert (again.accepted, again.duplicates) == (0, 50)
        # The CLI's delete of a seq range, and its get.
        out = cli("--server", server.address, "--json", "delete-traces", "--fleet", "f1",
                  "--robot", "robot-a", "--seq-first", "0", "--seq-last", "9")
        assert '"deleted":"10"' in out.replace(" ", "")
        found, missing = fm.get_traces("f1", "robot-a", [5, 10, 11])
        assert missing == [("robot-a", 5)] and found.seqs.tolist() == [10, 11]
        np.testing.assert_array_equal(found.codes, a[10:12])

        # Rescoring: one held trace outweighs the rest.
        held = fm.export("f1")
        seqs = held.seqs.astype(np.int64)
        rewards = np.where(seqs == 42, 1e6, 0.0)
        rescored = fm.update_rewards("f1", "robot-a", seqs, rewards)
        assert rescored.updated == len(seqs) and not rescored.not_held
        assert int(fm.sample_replay("f1", "robot-a", 1).seqs[0]) == 42
        with pytest.raises(ValueError):
            fm.get_traces("f1", "robot-a", [[1, 2]])


def test_two_fleets_with_their_own_settings(server, cli):
    with fleetmem.Client(server.address) as fm:
        made = fm.create_fleet("laser", code_dimension=16, encoder_version="scan-v1",
                               place_unit="m", max_clusters=4, max_traces_per_cluster=5,
                               forgetting="drop", index="hnsw", hnsw_m=8)
        assert (made.code_dimension, made.max_clusters, made.forgetting) == (
            16, 4, fleetmem.pb.FORGETTING_RULE_DROP)
        assert (made.index, made.hnsw_m) == (fleetmem.pb.INDEX_KIND_HNSW, 8)
        assert made.hnsw_codes == fleetmem.pb.HNSW_CODES_UNSPECIFIED
        floats = fm.create_fleet("floats", code_dimension=16, hnsw_codes="float")
        assert floats.hnsw_codes == fleetmem.pb.HNSW_CODES_FLOAT
        with pytest.raises(ValueError):
            fm.create_fleet("typo2", code_dimension=8, index="flann")
        with pytest.raises(ValueError):
            fm.create_fleet("typo3", code_dimension=8, hnsw_codes="int4")
        with pytest.raises(fleetmem.FleetMemError) as twice:
            fm.create_fleet("laser", code_dimension=16)
        assert twice.value.status == "ALREADY_EXISTS"
        with pytest.raises(fleetmem.FleetMemError) as bad:
            fm.create_fleet("nothing", code_dimension=0)
        assert bad.value.status == "INVALID_ARGUMENT"
        with pytest.raises(TypeError):
            fm.create_fleet("typo", code_dimension=8, max_cluster=3)
        fm.upload("camera", codes_of(21, 600, dim=64), np.arange(600) * 5.0, 1.0,
                  robot_id="cam-1", seqs=np.arange(600))
        fm.upload("laser", codes_of(22, 600, dim=16), np.arange(600) * 5.0, 1.0,
                  robot_id="lidar-1", seqs=np.arange(600), encoder_version="scan-v1")
        laser, camera = fm.get_fleet("laser"), fm.get_fleet("camera")
        assert laser.own_settings and not camera.own_settings
        assert laser.clusters <= 4 and camera.settings.max_clusters == 100
        assert laser.settings.place_unit == "m" and laser.code_dimension == 16
        assert laser.settings.index == fleetmem.pb.INDEX_KIND_HNSW
        assert camera.settings.index == fleetmem.pb.INDEX_KIND_UNSPECIFIED
        with pytest.raises(fleetmem.FleetMemError) as wrong:
            fm.upload("laser", codes_of(23, 5, dim=64), robot_id="cam-1", seqs=np.arange(5))
        assert wrong.value.status == "INVALID_ARGUMENT"

        after = fm.update_fleet("camera", max_clusters=10, replay_decay=0.5,
                                refresh_pair_radius=20, refresh_uniform=True)
        assert (after.max_clusters, after.replay_decay, after.code_dimension) == (10, 0.5, 64)
        assert after.refresh_pair_radius == 20.0 and laser.settings.refresh_pair_radius == 0
        assert fm.get_fleet("camera").own_settings
        fm.upload("camera", codes_of(24, 200, dim=64), np.arange(200) * 5.0, 1.0,
                  robot_id="cam-1", seqs=np.arange(600, 800))
        assert fm.get_fleet("camera").clusters <= 10
        listed = {f.fleet_id: f for f in fm.fleets()}
        assert listed["laser"].settings.max_clusters == 4 and listed["camera"].settings.max_clusters == 10
        out = cli("--server", server.address, "fleet", "--fleet", "laser")
        assert "clusters (K_max)" in out and "drop" in out
        out = cli("--server", server.address, "fleet", "--fleet", "camera")
        assert "uniform, pairs within 20" in out
        with pytest.raises(ValueError):
            fm.update_fleet("camera", refresh_uniform=1)
    server.stop()
    server.start()
    with fleetmem.Client(server.address) as fm:
        assert fm.get_fleet("laser").settings.max_clusters == 4
        assert fm.get_fleet("camera").settings.replay_decay == 0.5


def test_an_alias_moves_queries_to_the_new_encoders_fleet(server, cli):
    """The encoder migration of docs/api.md in small: codes by encoder let a
    query through the alias answer from whichever fleet it names."""
    a, b = codes_of(41, 50, dim=32), codes_of(42, 50, dim=16)
    with fleetmem.Client(server.address) as fm:
        fm.create_fleet("map-v1", code_dimension=32, encoder_version="enc-A")
        fm.create_fleet("map-v2", code_dimension=16, encoder_version="enc-B")
        fm.upload("map-v1", a, robot_id="r1", seqs=np.arange(50), encoder_version="enc-A")
        fm.upload("map-v2", b, robot_id="r1", seqs=np.arange(50), encoder_version="enc-B")
        fm.create_alias("map", "map-v1")
        with pytest.raises(fleetmem.FleetMemError) as taken:
            fm.create_alias("map-v2", "map-v1")
        assert taken.value.status == "ALREADY_EXISTS"
        both = {"enc-A": a[7], "enc-B": b[7]}
        before = fm.query_place("map", both)
        assert (before.fleet_id, before.encoder_version) == ("map-v1", "enc-A")
        assert int(before.traces.seqs[0]) == 7 and before.traces.codes.shape[1] == 32
        assert fm.switch_alias("map", "map-v2") == "map-v1"
        after = fm.query_place("map", both)
        assert (after.fleet_id, after.encoder_version) == ("map-v2", "enc-B")
        assert int(after.traces.seqs[0]) == 7 and after.traces.codes.shape[1] == 16
        assert fm.stats("map").code_dimension == 16
        assert fm.list_aliases() == {"map": "map-v2"}
        assert "map -> map-v2" in cli("--server", server.address, "aliases")
        with pytest.raises(fleetmem.FleetMemError) as named:
            fm.delete_fleet("map-v2")
        assert named.value.status == "FAILED_PRECONDITION"
        assert fm.delete_alias("map") == "map-v2"
        assert fm.list_aliases() == {}
        # The old fleet goes; its id makes a new fleet afterwards.
        assert fm.delete_fleet("map-v1") == 50
        with pytest.raises(fleetmem.FleetMemError) as gone:
            fm.stats("map-v1")
        assert gone.value.status == "NOT_FOUND"
        assert "map-v1" not in [f.fleet_id for f in fm.fleets()]
        fm.upload("map-v1", codes_of(43, 5, dim=8), robot_id="r1", seqs=np.arange(5))
        again = fm.stats("map-v1")
        assert again.code_dimension == 8 and again.traces + again.pending_traces == 5


def test_many_codes_in_one_query(server):
    a = codes_of(31, 400)
    with fleetmem.Client(server.address) as fm:
        fm.upload("f1", a, np.arange(400) * 5.0, 1.0, robot_id="robot-a", seqs=np.arange(400))
        fm.upload("f1", codes_of(32, 50), robot_id="robot-b", seqs=np.arange(50))
        only_b = fm.query_place("f1", a[3], k=5, robot_ids="robot-b")
        assert only_b.traces.robot_ids == ["robot-b"] * 5
        answers = fm.query_places("f1", a[[3, 150, 399]], k=2, robot_ids=["robot-a"])
        assert [int(m.traces.seqs[0]) for m in answers] == [3, 150, 399]
        assert all(len(m) == 2 and m.distances[0] < 1e-3 for m in answers)
        with pytest.raises(ValueError):
            fm.query_places("f1", a[0])  # one code: query_place
        with pytest.raises(fleetmem.FleetMemError) as too_many:
            request = fleetmem.pb.QueryPlaceRequest(fleet_id="f1", k=1)
            request.code.extend(a[0].tolist())
            for _ in range(100):
                request.more_codes.add().code.extend(a[1].tolist())
            fm._unary("QueryPlace", request)
        assert too_many.value.status == "INVALID_ARGUMENT"
        # A filtered replay draws one robot's traces only.
        fm.consolidate("f1")
        drawn = fm.sample_replay("f1", "robot-b", 30, robot_ids="robot-b")
        assert len(drawn.seqs) > 0 and set(drawn.robot_ids) == {"robot-b"}
        everyone = fm.sample_replay("f1", "robot-a", 300)
        assert set(everyone.robot_ids) == {"robot-a", "robot-b"}


def test_replay_dataset_streams_batches_and_keeps_the_rate_limit(server):
    """Issue 48: replay as a stream of batches for a training loop (Reverb's
    dataset), the answer as columns, and SampleToInsertRatio's limit."""
    with fleetmem.Client(server.address) as fm:
        codes = codes_of(48, 300, dim=16)
        fm.upload("replayed", codes, np.arange(300.0), 1.0, robot_id="r1", seqs=np.arange(300),
                  domain="summer")
        fm.consolidate("replayed")
        # Columns and messages carry the same kind of draw.
        columns = fm.sample_replay("replayed", "r1", 50)
        messages = fm.sample_replay("replayed", "r1", 50, columnar=False)
        for drawn in (columns, messages):
            assert drawn.codes.shape == (50, 16) and drawn.codes.dtype == np.float32
            assert drawn.places.shape == (50, 4) and len(set(drawn.seqs.tolist())) == 50
            assert drawn.robot_ids == ["r1"] * 50 and drawn.domains == ["summer"] * 50
            assert (drawn.replay_counts >= 1).all()
            # Each code is the one uploaded under its seq.
            np.testing.assert_allclose(drawn.codes, codes[drawn.seqs.astype(int)], rtol=1e-6)
        dataset = fleetmem.ReplayDataset(fm, "replayed", "r1", batch_size=100, batches=5)
        batches = list(dataset)
        assert [len(b) for b in batches] == [100] * 5 and dataset.sampled == 500
        assert all(len(set(b.seqs.tolist())) == 100 for b in batches)
        # No prefetch: the same, drawn when asked for.
        assert len(list(fleetmem.ReplayDataset(fm, "replayed", "r1", batch_size=10, batches=3,
                                               prefetch=0))) == 3
        # At most one trace drawn per trace received: three batches of 100
        # from 300 received, then the limit holds the fourth.
        limited = fleetmem.ReplayDataset(fm, "replayed", "r1", batch_size=100, samples_per_insert=1.0,
                                         poll_seconds=0.05, max_wait_seconds=0.5)
        got = []
        with pytest.raises(TimeoutError, match="samples_per_insert 1.0"):
            for batch in limited:
                got.append(len(batch))
        assert got == [100, 100, 100] and limited.inserted == 300
        # Not before the fleet holds min_size_to_sample.
        waiting = fleetmem.ReplayDataset(fm, "replayed", "r1", batch_size=10, min_size_to_sample=1000,
                                         poll_seconds=0.05, max_wait_seconds=0.3, prefetch=0)
        with pytest.raises(TimeoutError):
            next(iter(waiting))
        with pytest.raises(ValueError, match="samples_per_insert"):
            fleetmem.ReplayDataset(fm, "replayed", "r1", samples_per_insert=0)
