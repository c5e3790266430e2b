#!/usr/bin/env bash
# Builds the local stand-in for debian:bookworm-slim that the Docker tests
# build the Dockerfiles on (this machine's engine cannot pull images):
# debootstrap of bookworm (minbase) from the Debian archive apt already uses
# here, imported as IMAGE. The host's apt settings (its archive and its
# Acquire options) are copied in, so apt inside the image reaches the same
# archive. Does nothing when IMAGE exists.
#
#   tests/docker/base_image.sh [IMAGE]       (default fleetmem-local/bookworm:base)
# Environment: FLEETMEM_DEBIAN_MIRROR (default: the host's first bookworm URI).
set -euo pipefail
image=${1:-fleetmem-local/bookworm:base}
if docker image inspect "$image" >/dev/null 2>&1; then
  echo "base_image.sh: $image exists"
  exit 0
fi
command -v debootstrap >/dev/null || {
  echo "base_image.sh: debootstrap is missing (apt-get install debootstrap)" >&2
  exit 1
}
mirror=${FLEETMEM_DEBIAN_MIRROR:-$(
  grep -rhoE '(URIs:|deb) +https?://[^ ]+/debian( |$)' /etc/apt/sources.list \
    /etc/apt/sources.list.d/ 2>/dev/null | head -1 | awk '{print $2}' || true)}
mirror=${mirror:-http://deb.debian.org/debian}
root=$(mktemp -d "${TMPDIR:-/tmp}/fleetmem-bookworm-XXXXXX")
trap 'rm -rf "$root"' EXIT
echo "base_image.sh: debootstrap bookworm from $mirror (a few minutes)"
debootstrap --variant=minbase bookworm "$root" "$mirror" >"$root.log" 2>&1 || {
  tail -20 "$root.log" >&2
  exit 1
}
rm -f "$root.log"
cp /etc/apt/apt.conf.d/99* "$root/etc/apt/apt.conf.d/" 2>/dev/null || true
printf 'deb %s bookworm main\ndeb %s bookworm-updates main\n' "$mirror" \
  "$mirror" >"$root/etc/apt/sources.list"
rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/*
tar -C "$root" -c . | docker import - "$image" >/dev/null
echo "base_image.sh: imported $image"
