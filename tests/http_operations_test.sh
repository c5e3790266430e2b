#!/usr/bin/env bash
# The HTTP port of the real fleetmem-server, end to end, with real tools:
#   rest       every REST route with curl: answers equal to the gRPC ones (the
#              fleetmem CLI), bad JSON, unknown fields, unknown fleets,
#              oversized bodies; export read back with numpy.
#   snapshot   a snapshot taken under upload load; a second server started on
#              it holds every trace acknowledged before the snapshot call.
#   prometheus a real Prometheus scrapes /metrics; its query API returns the
#              fleet's trace count.
#   dashboard  headless Chromium renders the dashboard after a small fleet
#              uploaded; the DOM shows the fleet, its robots, counts and a
#              drawn map; the screenshot is kept as BUILD/test-artifacts/
#              dashboard.png.
# Usage: http_operations_test.sh BUILD_DIR MODE
set -euo pipefail

BUILD=$(cd "$1" && pwd)
MODE=$2
BIN=$BUILD/bin
WORK=$(mktemp -d "${TMPDIR:-/tmp}/fleetmem-http-XXXXXX")
PIDS=()
cleanup() {
  for pid in "${PIDS[@]}"; do kill -9 "$pid" 2>/dev/null || true; done
  if [ -z "${FLEETMEM_KEEP_TEST_DIRS:-}" ]; then rm -rf "$WORK"; fi
}
trap cleanup EXIT
fail() { echo "FAIL: $*" >&2; exit 1; }
check() { # check DESCRIPTION COMMAND...
  local what=$1; shift
  if "$@"; then echo "ok: $what"; else fail "$what"; fi
}

# shellcheck source=../tools/process/server.sh
source "$(dirname "$0")/../tools/process/server.sh"
# serve NAME DATA_DIR [extra flags]: a server with an HTTP port (the
# project's start_server); sets GRPC_ADDR and HTTP_ADDR, and MAIN_ADDR for
# the server named main.
serve() {
  local name=$1 data=$2; shift 2
  start_server "$BUILD" "$data" "$WORK/$name.log" --http-listen 127.0.0.1:0 \
    "$@" || fail "server $name did not start"
  PIDS+=("$SERVER_PID")
  disown "$SERVER_PID"
  GRPC_ADDR=$SERVER_ADDR
  HTTP_ADDR=$SERVER_HTTP_ADDR
  if [ "$name" = main ]; then MAIN_ADDR=$SERVER_ADDR; fi
}

cli() { "$BIN/fleetmem" --server "$GRPC_ADDR" "$@"; }
http_code() { # http_code METHOD PATH [BODY]: prints the status, body to $WORK/body
  curl -s -o "$WORK/body" -w '%{http_code}' -X "$1" \
    -H 'Content-Type: application/json' ${3:+--data-binary "$3"} \
    "http://$HTTP_ADDR$2"
}
# json_equal FILE_A FILE_B: same JSON value.
json_equal() {
  /usr/bin/python3 -c 'import json,sys; a=json.load(open(sys.argv[1])); b=json.load(open(sys.argv[2])); sys.exit(0 if a==b else 1)' "$1" "$2" ||
    { echo "--- $1"; cat "$1"; echo "--- $2"; cat "$2"; return 1; }
}

upload_fleet() { # upload_fleet FLEET ROBOTS PER_ROBOT
  cli gen-traces --robots "$2" --per-robot "$3" --dim 32 --out "$WORK/traces.jsonl" > /dev/null
  cli upload --fleet "$1" --file "$WORK/traces.jsonl" > /dev/null
}

case "$MODE" in
rest)
  # Index snapshots every second, of any fleet: the pause metric is served;
  # retention every second too (fleet beta, below).
  printf 'index_snapshot_interval_seconds: 1\nindex_snapshot_min_codes: 0\nretention_interval_seconds: 1\n' \
    > "$WORK/snapshots.textproto"
  serve main "$WORK/data" --config "$WORK/snapshots.textproto"
  upload_fleet alpha 6 150   # 6 x 20 clusters > K_max = 100: forgetting runs
  cli consolidate --fleet alpha > /dev/null  # clusters and events
  for route in "GET /v1/fleets" "GET /v1/fleets/alpha/stats" \
               "GET /v1/fleets/alpha/clusters"; do
    set -- $route
    check "$route is 200" [ "$(http_code "$1" "$2")" = 200 ]
    cp "$WORK/body" "$WORK/rest.json"
    case "$2" in
      /v1/fleets) cli --json fleets > "$WORK/grpc.json" ;;
      */stats) cli --json stats --fleet alpha > "$WORK/grpc.json" ;;
      */clusters) cli --json clusters --fleet alpha > "$WORK/grpc.json" ;;
    esac
    check "$route equals the gRPC answer" json_equal "$WORK/rest.json" "$WORK/grpc.json"
  done
  check "events after a cursor" [ "$(http_code GET '/v1/fleets/alpha/events?after=2')" = 200 ]
  check "events start at 3" /usr/bin/python3 -c 'import json; e=json.load(open("'"$WORK/body"'"))["events"]; assert e[0]["id"]=="3", e[0]'
  code=$(head -1 "$WORK/traces.jsonl" | /usr/bin/python3 -c 'import json,sys; print(json.dumps({"code": json.load(sys.stdin)["code"], "k": 3}))')
  check "query is 200" [ "$(http_code POST /v1/fleets/alpha/query "$code")" = 200 ]
  cp "$WORK/body" "$WORK/rest.json"
  echo "$code" > "$WORK/code.json"
  cli --json query --fleet alpha --code-file "$WORK/code.json" --k 3 > "$WORK/grpc.json"
  check "query equals the gRPC answer" json_equal "$WORK/rest.json" "$WORK/grpc.json"
  check "sample is 200" [ "$(http_code POST /v1/fleets/alpha/sample '{"robotId":"robot-1","count":4}')" = 200 ]
  check "sample returns 4 traces" /usr/bin/python3 -c 'import json; assert len(json.load(open("'"$WORK/body"'"))["traces"])==4'
  check "consolidate is 200" [ "$(http_code POST /v1/fleets/alpha/consolidate '{}')" = 200 ]
  # A fleet with its own settings, over REST: made, changed, read; its
  # traces fetched by key, re-scored and deleted; its retention run by the
  # server (every second here) through the fleet's log.
  check "create a fleet is 200" [ "$(http_code POST /v1/fleets '{"fleetId":"beta","settings":{"codeDimension":32,"encoderVersion":"v1","maxClusters":5,"maxTracesPerRobot":20}}')" = 200 ]
  check "creating it again is 409" [ "$(http_code POST /v1/fleets '{"fleetId":"beta","settings":{"codeDimension":32}}')" = 409 ]
  cli gen-traces --robots 2 --per-robot 60 --dim 32 --out "$WORK/beta.jsonl" > /dev/null
  cli upload --fleet beta --file "$WORK/beta.jsonl" > /dev/null
  # operations.md's consolidate: a POST with no body at all (no
  # Content-Length, no Content-Type), as `curl -X POST` sends it.
  check "a POST without a body is served" \
    [ "$(curl -s -o "$WORK/body" -w '%{http_code}' -X POST "http://$HTTP_ADDR/v1/fleets/beta/consolidate")" = 200 ]
  check "and answers the consolidation" grep -q '"clusters"' "$WORK/body"
  check "settings update is 200" [ "$(http_code POST /v1/fleets/beta/settings '{"settings":{"maxClusters":4}}')" = 200 ]
  check "get a fleet is 200" [ "$(http_code GET /v1/fleets/beta)" = 200 ]
  check "its settings are its own" /usr/bin/python3 -c 'import json; f=json.load(open("'"$WORK/body"'"))["fleet"]; assert f["ownSettings"] and f["settings"]["maxClusters"]==4, f'
  check "batch get is 200" [ "$(http_code POST '/v1/fleets/beta/traces:batchGet' '{"keys":[{"robotId":"robot-1","seq":"60"},{"robotId":"nobody","seq":"1"}]}')" = 200 ]
  check "batch get finds one and misses one" /usr/bin/python3 -c 'import json; b=json.load(open("'"$WORK/body"'")); assert len(b["traces"])==1 and b["missing"][0]["robotId"]=="nobody", b'
  check "update rewards is 200" [ "$(http_code POST '/v1/fleets/beta/traces:updateRewards' '{"updates":[{"robotId":"robot-1","seq":"60","rewardExternal":3}]}')" = 200 ]
  # A bulk import over REST: two rows of 2-d codes as columns (codes as
  # base64 float32), the last call: applied, its graph built, answered.
  import_body=$(/usr/bin/python3 -c 'import base64,json,struct
codes=base64.b64encode(struct.pack("<4f",1,0,0,1)).decode()
print(json.dumps({"traces":{"count":2,"codeDimension":2,"codes":codes,
  "places":[0,0,0,0,1,0,0,0],"rewards":[1,1],"robotIds":["r","r"],
  "seqs":["1","2"]},"finish":True}))')
  check "an import is 200" [ "$(http_code POST '/v1/fleets/gamma/traces:import' "$import_body")" = 200 ]
  check "and answers what it stored" /usr/bin/python3 -c 'import json; b=json.load(open("'"$WORK/body"'")); assert b["accepted"]=="2" and b["fleetTraces"]=="2", b'
  check "an import into a fleet holding traces is 400" [ "$(http_code POST '/v1/fleets/gamma/traces:import' "$import_body")" = 400 ]
  check "delete traces is 200" [ "$(http_code POST '/v1/fleets/beta/traces:delete' '{"robotId":"robot-2"}')" = 200 ]
  check "a delete of nothing named is 400" [ "$(http_code POST '/v1/fleets/beta/traces:delete' '{}')" = 400 ]
  held_by() { # held_by ROBOT: its traces in fleet beta (0 if none)
    http_code GET /v1/fleets/beta/stats > /dev/null
    /usr/bin/python3 -c 'import json,sys; s=json.load(open(sys.argv[1])); print(sum(int(r.get("traces",0))+int(r.get("pendingTraces",0)) for r in s.get("robots",[]) if r["robotId"]==sys.argv[2]))' "$WORK/body" "$1"
  }
  check "robot-2's traces are gone" [ "$(held_by robot-2)" = 0 ]
  for _ in $(seq 1 100); do
    [ "$(held_by robot-1)" -le 20 ] && break
    sleep 0.1
  done
  check "retention keeps robot-1's newest 20" [ "$(held_by robot-1)" = 20 ]
  # Aliases over REST: made, read through, switched, listed, removed.
  check "create an alias is 200" [ "$(http_code POST /v1/aliases '{"alias":"live","fleetId":"beta"}')" = 200 ]
  check "an alias with a fleet's name is 409" [ "$(http_code POST /v1/aliases '{"alias":"alpha","fleetId":"beta"}')" = 409 ]
  check "stats through the alias are 200" [ "$(http_code GET /v1/fleets/live/stats)" = 200 ]
  check "they are beta's" /usr/bin/python3 -c 'import json; s=json.load(open("'"$WORK/body"'")); assert s["codeDimension"]==32 and any(r["robotId"]=="robot-1" for r in s["robots"]), s'
  check "switch the alias is 200" [ "$(http_code POST /v1/aliases/live/switch '{"fleetId":"alpha"}')" = 200 ]
  check "it names alpha" [ "$(http_code GET /v1/aliases)" = 200 ]
  check "the listing says so" /usr/bin/python3 -c 'import json; a=json.load(open("'"$WORK/body"'"))["aliases"]; assert a==[{"alias":"live","fleetId":"alpha"}], a'
  check "delete the alias is 200" [ "$(http_code POST /v1/aliases/live/delete '{}')" = 200 ]
  check "the alias is gone (404)" [ "$(http_code GET /v1/fleets/live/stats)" = 404 ]
  check "bad JSON is 400" [ "$(http_code POST /v1/fleets/alpha/query '{"code": [1,')" = 400 ]
  check "unknown field is 400 naming it" [ "$(http_code POST /v1/fleets/alpha/query '{"codes": [1]}')" = 400 ]
  grep -q codes "$WORK/body" || fail "the message does not name the field: $(cat "$WORK/body")"
  check "wrong type is 400" [ "$(http_code POST /v1/fleets/alpha/query '{"k": "three"}')" = 400 ]
  check "unknown fleet is 404" [ "$(http_code GET /v1/fleets/nobody/stats)" = 404 ]
  grep -q '"status":"NOT_FOUND"' "$WORK/body" || fail "404 body: $(cat "$WORK/body")"
  /usr/bin/python3 -c 'print("{\"code\": [" + "0.5," * 1200000 + "0.5]}")' > "$WORK/big.json"
  status=$(curl -s -o "$WORK/body" -w '%{http_code}' -X POST -H 'Content-Type: application/json' \
    --data-binary "@$WORK/big.json" "http://$HTTP_ADDR/v1/fleets/alpha/query")
  check "oversized body is 413" [ "$status" = 413 ]
  check "unknown route is 404" [ "$(http_code GET /v1/nothing)" = 404 ]
  check "healthz" [ "$(http_code GET /healthz)" = 200 ]
  check "readyz" [ "$(http_code GET /readyz)" = 200 ]
  for _ in $(seq 1 100); do
    grep -q 'codes saved in' "$WORK/main.log" && break
    sleep 0.1
  done
  check "a periodic index snapshot was written" grep -q 'codes saved in' "$WORK/main.log"
  curl -s "http://$HTTP_ADDR/metrics" > "$WORK/metrics.txt"
  check "metrics has the fleet's traces" grep -q 'fleetmem_fleet_traces{fleet="alpha"}' "$WORK/metrics.txt"
  SOURCE=$(cd "$(dirname "$0")/.." && pwd)
  check "every metric of the Grafana dashboard and docs/operations.md is served" \
    /usr/bin/python3 - "$WORK/metrics.txt" "$SOURCE/docker/grafana/fleetmem-dashboard.json" "$SOURCE/docs/operations.md" <<'EOF'
import re, sys
served = set(re.findall(r"^# TYPE (fleetmem_\w+)", open(sys.argv[1]).read(), re.M))
for path in sys.argv[2:]:
    named = set(re.findall(r"fleetmem_[a-z_]+", open(path).read()))
    named = {re.sub(r"_(bucket|count|sum)$", "", n) for n in named}
    missing = sorted(n for n in named if n not in served)
    assert not missing, (path, missing)
# And the other way: every metric served has its row in operations.md's
# table (issue 48: fleetmem_build_info had none).
documented = set(re.findall(r"^\| `(fleetmem_\w+)`", open(sys.argv[3]).read(), re.M))
undocumented = sorted(served - documented)
assert not undocumented, ("served but not in docs/operations.md", undocumented)
EOF
  cli export --fleet alpha --out "$WORK/export" --page-size 100 > /dev/null
  check "export reads back with numpy" /usr/bin/python3 - "$WORK/export" <<'EOF'
import csv, json, sys
import numpy as np
d = sys.argv[1]
codes, places = np.load(d + "/codes.npy"), np.load(d + "/places.npy")
rows = list(csv.DictReader(open(d + "/metadata.csv")))
N = len(rows)
assert 500 < N <= 900, N  # downsampling keeps at most N_max per cluster
assert codes.shape == (N, 32) and codes.dtype == np.float32, codes.shape
assert places.shape == (N, 4) and places.dtype == np.float64, places.shape
assert len(rows) == N
first = json.loads(open(d + "/../traces.jsonl").readline())
row = next(i for i, r in enumerate(rows) if r["robot_id"] == first["robotId"] and r["seq"] == first["seq"])
assert np.allclose(codes[row], np.array(first["code"], dtype=np.float32)), row
assert abs(places[row][0] - first["pose"]["x"]) < 1e-9
EOF
  ;;

snapshot)
  serve main "$WORK/data"
  cli gen-traces --robots 40 --per-robot 100 --dim 32 --out "$WORK/all.jsonl" > /dev/null
  # One upload per robot, one after another, logging each acknowledgement.
  (
    for r in $(seq 1 40); do
      grep "\"robotId\":\"robot-$r\"" "$WORK/all.jsonl" > "$WORK/r$r.jsonl"
      cli upload --fleet load --file "$WORK/r$r.jsonl" > /dev/null
      echo "robot-$r" >> "$WORK/acked"
    done
  ) &
  uploader=$!
  PIDS+=($uploader)
  until [ "$(wc -l < "$WORK/acked" 2>/dev/null || echo 0)" -ge 10 ]; do sleep 0.1; done
  cp "$WORK/acked" "$WORK/acked-before"   # acknowledged before the call began
  cli snapshot --name under-load > "$WORK/snapshot.out"
  wait "$uploader"
  snap=$(sed -n 's/^restore: fleetmem-server --data-dir NEW_DIR --restore-from //p' "$WORK/snapshot.out")
  check "snapshot directory exists" [ -d "$snap/db" ]
  check "the snapshot says what it is" grep -q 'restore: fleetmem-server' "$snap/SNAPSHOT"
  echo "acknowledged before the snapshot: $(wc -l < "$WORK/acked-before") robots"
  # Issue 48: a server on the snapshot itself turned it into a live store.
  ls -R "$snap" > "$WORK/snapshot-files-before"
  refused=0
  "$BIN/fleetmem-server" --listen 127.0.0.1:0 --data-dir "$snap" > "$WORK/on-snapshot.log" 2>&1 || refused=$?
  check "a server on a snapshot is refused (exit 2)" [ "$refused" = 2 ]
  check "and says how to restore it" grep -q -- '--restore-from' "$WORK/on-snapshot.log"
  ls -R "$snap" > "$WORK/snapshot-files-after"
  check "and leaves the snapshot unchanged" cmp -s "$WORK/snapshot-files-before" "$WORK/snapshot-files-after"
  refused=0
  "$BIN/fleetmem-server" --listen 127.0.0.1:0 --data-dir "$WORK/not-made" \
    --restore-from "$WORK/no-snapshot" > "$WORK/bad-restore.log" 2>&1 || refused=$?
  check "a restore from no snapshot is refused (exit 2)" [ "$refused" = 2 ]
  check "and makes no data dir" [ ! -e "$WORK/not-made" ]
  serve restored "$WORK/restored" --restore-from "$snap"
  check "the snapshot stayed a snapshot" cmp -s "$WORK/snapshot-files-before" <(ls -R "$snap")
  cli --json stats --fleet load > "$WORK/restored.json"
  check "every trace acknowledged before the snapshot is in it" /usr/bin/python3 - "$WORK/restored.json" "$WORK/acked-before" <<'EOF'
import json, sys
stats = json.load(open(sys.argv[1]))
received = {r["robotId"]: int(r["received"]) for r in stats["robots"]}
for robot in open(sys.argv[2]).read().split():
    assert received.get(robot) == 100, (robot, received.get(robot))
print("restored robots:", len(received), "traces:", sum(received.values()))
EOF
  check "the live server kept serving and has all 40 robots" /usr/bin/python3 -c '
import json, subprocess, sys
s = json.loads(subprocess.check_output(sys.argv[1:]))
assert len(s["robots"]) == 40, len(s["robots"])' "$BIN/fleetmem" --server "$MAIN_ADDR" --json stats --fleet load
  GRPC_ADDR=$MAIN_ADDR
  cli snapshot --name under-load > "$WORK/again.out" 2>&1 || true
  check "a taken name is refused" grep -q ALREADY_EXISTS "$WORK/again.out"
  ;;

prometheus)
  command -v prometheus > /dev/null || fail "prometheus is not installed (make deps)"
  serve main "$WORK/data"
  upload_fleet scraped 2 250   # 200 per robot consolidate automatically
  traces=$(cli --json stats --fleet scraped | /usr/bin/python3 -c 'import json,sys; print(json.load(sys.stdin)["traces"])')
  port=$(/usr/bin/python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
  cat > "$WORK/prometheus.yml" <<EOF
global:
  scrape_interval: 1s
scrape_configs:
  - job_name: fleetmem
    static_configs:
      - targets: ["$HTTP_ADDR"]
EOF
  prometheus --config.file="$WORK/prometheus.yml" --storage.tsdb.path="$WORK/tsdb" \
    --web.listen-address="127.0.0.1:$port" > "$WORK/prometheus.log" 2>&1 &
  PIDS+=($!)
  disown $!
  value=""
  for _ in $(seq 1 60); do
    value=$(curl -s "http://127.0.0.1:$port/api/v1/query" \
      --data-urlencode 'query=fleetmem_fleet_traces{fleet="scraped"}' |
      /usr/bin/python3 -c 'import json,sys; r=json.load(sys.stdin)["data"]["result"]; print(r[0]["value"][1] if r else "")' 2>/dev/null || true)
    [ -n "$value" ] && break
    sleep 1
  done
  echo "Prometheus says fleetmem_fleet_traces{fleet=\"scraped\"} = $value; GetStats says $traces"
  check "the fleet has consolidated traces" [ "$traces" -gt 0 ]
  check "Prometheus returns the fleet's trace count" [ "$value" = "$traces" ]
  ;;

dashboard)
  command -v chromium > /dev/null || fail "chromium is not installed (make deps)"
  serve main "$WORK/data"
  upload_fleet dashfleet 3 300
  cli create-alias --alias dashalias --fleet dashfleet > /dev/null
  ARTIFACTS=$BUILD/test-artifacts
  mkdir -p "$ARTIFACTS"
  browse() {
    timeout 120 chromium --headless --no-sandbox --disable-gpu --hide-scrollbars \
      --user-data-dir="$WORK/chromium" --window-size=1400,1000 \
      --virtual-time-budget=8000 "$@" "http://$HTTP_ADDR/" 2> "$WORK/chromium.log"
  }
  browse --dump-dom > "$WORK/dom.html"
  browse --screenshot="$ARTIFACTS/dashboard.png" > /dev/null
  check "the DOM shows the fleet" grep -q 'data-fleet="dashfleet"' "$WORK/dom.html"
  check "the DOM shows its alias" grep -q 'data-aliases="dashalias"' "$WORK/dom.html"
  check "the fleet's deletion waits for its typed id" \
    grep -q 'id="delete-button" type="button" disabled' "$WORK/dom.html"
  for r in 1 2 3; do
    check "the DOM shows robot-$r" grep -q "data-robot=\"robot-$r\"" "$WORK/dom.html"
  done
  traces=$(cli --json stats --fleet dashfleet | /usr/bin/python3 -c 'import json,sys; print("{:,}".format(int(json.load(sys.stdin)["traces"])))')
  check "the DOM shows the trace count ($traces)" grep -q "id=\"stat-traces\" class=\"value\">$traces<" "$WORK/dom.html"
  check "the map drew 900 places" grep -q 'data-points="900"' "$WORK/dom.html"
  check "the map drew clusters" grep -qE 'data-clusters="[1-9][0-9]*"' "$WORK/dom.html"
  check "the screenshot was saved" [ -s "$ARTIFACTS/dashboard.png" ]
  echo "screenshot: $ARTIFACTS/dashboard.png"
  check "the chart has its ticks" grep -q 'data-ticks="15"' "$WORK/dom.html"
  check "the map does not claim metres unless told" grep -q 'data-unit="units"' "$WORK/dom.html"
  check "the map of a 2-D fleet is drawn as a map" grep -q 'data-layout="2-d"' "$WORK/dom.html"
  check "the status says it is live, not connecting" grep -q 'id="status" class="muted">live' "$WORK/dom.html"
  # Each fleet has its own address, which also names the place unit. Its
  # bound is small (K_max 10): the chart draws the memory after each
  # consolidation, never the 30 clusters between its added and merged
  # events.
  cli create-fleet --fleet otherfleet --dim 32 --encoder v1 --max-clusters 10 > /dev/null
  upload_fleet otherfleet 1 100
  cli consolidate --fleet otherfleet > /dev/null
  timeout 120 chromium --headless --no-sandbox --disable-gpu \
    --user-data-dir="$WORK/chromium3" --virtual-time-budget=8000 --dump-dom \
    "http://$HTTP_ADDR/#fleet=otherfleet&unit=route%20index" > "$WORK/dom-link.html" 2> /dev/null
  check "#fleet= selects that fleet" \
    grep -q 'data-fleet="otherfleet" class="active"' "$WORK/dom-link.html"
  check "#unit= labels the map" grep -q 'data-unit="route index"' "$WORK/dom-link.html"
  check "the map drew the other fleet's 100 places" grep -q 'data-points="100"' "$WORK/dom-link.html"
  check "the picker names the fleet shown" grep -q 'id="fleet-current"[^>]*>otherfleet<' "$WORK/dom-link.html"
  check "one robot is not \"1 robots\"" grep -q '1 robot<' "$WORK/dom-link.html"
  check "the chart never passes the bound of 10 clusters" /usr/bin/python3 -c '
import re, sys
peak = int(re.search(r"data-peak-clusters=\"(\d+)\"", open(sys.argv[1]).read()).group(1))
assert 0 < peak <= 10, peak' "$WORK/dom-link.html"
  # A fleet on one line (a route index, y = 0) is folded into rows; with
  # 60 fleets the picker lists 50 and says how to find the rest.
  /usr/bin/python3 - "$WORK/traces.jsonl" "$WORK/route.jsonl" <<'EOF'
import json, sys
with open(sys.argv[2], "w") as out:
    for i, line in enumerate(open(sys.argv[1])):
        trace = json.loads(line)
        trace["pose"] = {"x": float(i * 10)}
        out.write(json.dumps(trace) + "\n")
EOF
  cli upload --fleet route --file "$WORK/route.jsonl" > /dev/null
  for i in $(seq 1 57); do cli create-fleet --fleet "empty-$i" --dim 8 > /dev/null; done
  timeout 120 chromium --headless --no-sandbox --disable-gpu \
    --user-data-dir="$WORK/chromium4" --virtual-time-budget=8000 --dump-dom \
    "http://$HTTP_ADDR/#fleet=route&unit=route%20index" > "$WORK/dom-route.html" 2> /dev/null
  check "a 1-D fleet is folded into rows" grep -q 'data-layout="1-d, [0-9]* rows"' "$WORK/dom-route.html"
  check "the picker lists 50 of 60 fleets" /usr/bin/python3 -c '
import sys
page = open(sys.argv[1]).read()
assert page.count("data-fleet=") == 50, page.count("data-fleet=")
assert "10 more: type to narrow" in page and "60 fleets on this server" in page' "$WORK/dom-route.html"

  # With auth on, the page asks for a reader token; given one, it shows the
  # fleet.
  mkdir -p "$WORK/auth"
  for who in "admin admin" "viewer reader"; do
    set -- $who
    "$BIN/fleetmem-credential" --name "$1" --role "$2" --fleet '*' \
      --token-file "$WORK/auth/$1.token" >> "$WORK/auth/credentials.textproto"
  done
  serve secured "$WORK/data-secured" --auth-file "$WORK/auth/credentials.textproto"
  cli --token-file "$WORK/auth/admin.token" upload --fleet securefleet \
    --file "$WORK/traces.jsonl" > /dev/null
  check "the API refuses the dashboard's calls without a token" \
    [ "$(http_code GET /v1/fleets)" = 401 ]
  browse --dump-dom > "$WORK/dom-locked.html"
  check "without a token the page shows the login form" \
    grep -q '<div id="login">' "$WORK/dom-locked.html"
  check "without a token the page shows no fleet" \
    bash -c "! grep -q 'data-fleet=' '$WORK/dom-locked.html'"
  check "without a token the status asks for credentials" \
    grep -q 'id="status" class="muted">credentials needed' "$WORK/dom-locked.html"
  token=$(cat "$WORK/auth/viewer.token")
  timeout 120 chromium --headless --no-sandbox --disable-gpu \
    --user-data-dir="$WORK/chromium2" --virtual-time-budget=8000 --dump-dom \
    "http://$HTTP_ADDR/#token=$token" > "$WORK/dom-token.html" 2> /dev/null
  check "with a reader token the page shows the fleet" \
    grep -q 'data-fleet="securefleet"' "$WORK/dom-token.html"
  ;;
*)
  fail "unknown mode $MODE"
  ;;
esac
echo "PASS: $MODE"
