#!/usr/bin/env bash
# Makes the credentials and certificates of the compose fleet
# (docker/compose.yaml) in DIR (default docker/secrets, git-ignored):
#   ca.pem, ca.key               a private CA (keep ca.key off the servers)
#   server.pem, server.key       the server's certificate for the names
#                                fleetmem-server, server, localhost, 127.0.0.1
#   credentials.textproto        the server's --auth-file: principals ops
#                                and replicas (ADMIN; replicas is what the
#                                replicas of docker/cluster.compose.yaml
#                                forward calls with), grafana (READER) and
#                                robot-1..N (ROBOT, fleet FLEET), Argon2id
#                                hashes only
#   ops.token, replicas.token, grafana.token, robot-K.token
#                                the clients' tokens NAME:SECRET
# Tokens come from fleetmem-credential: $FLEETMEM_CREDENTIAL if set (e.g.
# build/bin/fleetmem-credential), else the one in the server image
# ($FLEETMEM_SERVER_IMAGE, default fleetmem/server:0.1.0, run with docker).
# Existing files are kept: remove DIR to start over.
#
#   docker/make-secrets.sh [DIR]
# Environment: FLEETMEM_FLEET (nordland), FLEETMEM_ROBOTS (4),
#   FLEETMEM_CERT_DAYS (365).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
dir=${1:-$here/secrets}
fleet=${FLEETMEM_FLEET:-nordland}
robots=${FLEETMEM_ROBOTS:-4}
days=${FLEETMEM_CERT_DAYS:-365}
image=${FLEETMEM_SERVER_IMAGE:-fleetmem/server:0.1.0}
mkdir -p "$dir"
chmod 0700 "$dir"
dir=$(cd "$dir" && pwd)

if [ ! -f "$dir/server.pem" ]; then
  openssl req -x509 -newkey rsa:2048 -nodes -days "$days" -subj "/CN=fleetmem-ca" \
    -keyout "$dir/ca.key" -out "$dir/ca.pem" 2>/dev/null
  openssl req -newkey rsa:2048 -nodes -subj "/CN=fleetmem-server" \
    -keyout "$dir/server.key" -out "$dir/server.csr" 2>/dev/null
  printf 'subjectAltName=DNS:fleetmem-server,DNS:server,DNS:localhost,IP:127.0.0.1\n' \
    >"$dir/server.ext"
  openssl x509 -req -in "$dir/server.csr" -CA "$dir/ca.pem" -CAkey "$dir/ca.key" \
    -CAcreateserial -days "$days" -extfile "$dir/server.ext" \
    -out "$dir/server.pem" 2>/dev/null
  rm -f "$dir/server.csr" "$dir/server.ext" "$dir/ca.srl"
  echo "make-secrets.sh: CA and server certificate in $dir"
fi

# credential NAME ROLE [FLAGS...]: appends NAME's principal, writes NAME.token.
credential() {
  local name=$1 role=$2
  shift 2
  if [ -n "${FLEETMEM_CREDENTIAL:-}" ]; then
    "$FLEETMEM_CREDENTIAL" --name "$name" --role "$role" "$@" \
      --token-file "$dir/$name.token"
  else
    docker run --rm --user "$(id -u):$(id -g)" -v "$dir:/out" \
      --entrypoint fleetmem-credential "$image" --name "$name" --role "$role" \
      "$@" --token-file "/out/$name.token"
  fi
}
if [ ! -f "$dir/credentials.textproto" ]; then
  {
    credential ops admin
    credential replicas admin
    credential grafana reader --fleet '*'
    for k in $(seq 1 "$robots"); do
      credential "robot-$k" robot --fleet "$fleet"
    done
  } >"$dir/credentials.new"
  mv "$dir/credentials.new" "$dir/credentials.textproto"
  echo "make-secrets.sh: principals ops, grafana, robot-1..$robots in $dir/credentials.textproto"
fi
# Bind-mounted secrets keep their host mode: the images' users (uids 10001
# and 10002) must read them. DIR itself stays 0700.
chmod 0644 "$dir"/*.pem "$dir"/*.token "$dir/credentials.textproto"
chmod 0644 "$dir/server.key"
chmod 0600 "$dir/ca.key"
