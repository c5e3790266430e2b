#!/usr/bin/env bash
# Runs the slow tier's tests (ctest label "slow") in the order of
# tools/ci/slow_tests.txt: those marked "always" whatever the time, the
# others only if their cost there fits in what is left of SECONDS_LEFT;
# names those left out. Used by .ci/run after the tiers that always run.
#
#   tools/ci/run_slow_within.sh BUILD_DIR SECONDS_LEFT
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
build=$1
left=$2
deadline=$((SECONDS + left))
ran=() skipped=()
while read -r name warm cold always; do
  case $name in '#'* | '') continue ;; esac
  cost=$warm
  # Image builds are paid once per machine: the cold cost until the base
  # image exists.
  if [ "$cold" != - ] && ! docker image inspect fleetmem-local/bookworm:base \
    >/dev/null 2>&1; then
    cost=$cold
  fi
  now_left=$((deadline - SECONDS))
  if [ "$always" != always ] && [ "$cost" -gt "$now_left" ]; then
    skipped+=("$name (~${cost} s, ${now_left} s left)")
    continue
  fi
  (cd "$build" && ctest --output-on-failure -R "^${name}\$" -L slow)
  ran+=("$name")
done <"$here/slow_tests.txt"
echo "slow tier in CI: ran ${#ran[@]}: ${ran[*]:-none}"
if [ ${#skipped[@]} -gt 0 ]; then
  printf 'slow tier in CI: left out (run make test-slow): %s\n' "${skipped[@]}"
fi
