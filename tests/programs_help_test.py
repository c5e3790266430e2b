#!/usr/bin/env python3
"""Every program in build/bin speaks one command-line style (issue 48).

Before, three help styles (the server's, `fleetmem`'s, CLI11's), CLI11's
help named argv[0] and showed build-tree paths as defaults, lines ran to 283
characters, `fleetmem --help` did not list --version, a missing required
flag exited 106 in two programs and 2 elsewhere, and fleetmem_ann_bench
--version ran the whole benchmark. Now, for each program:
  --help      exit 0, "Usage: NAME ..." (its own name), every line at most
              80 columns, --help and --version listed, no path of the tree;
  --version   exit 0, "NAME VERSION";
  a flag it does not know: exit 2, "NAME: error: ..." and the hint to
              --help on stderr, nothing run.

  programs_help_test.py BUILD_DIR SOURCE_DIR
"""

import pathlib
import subprocess
import sys

build = pathlib.Path(sys.argv[1]).resolve()
source = pathlib.Path(sys.argv[2]).resolve()
programs = sorted(p for p in (build / "bin").iterdir()
                  if p.name.startswith("fleetmem") and p.is_file() and p.stat().st_mode & 0o111)
assert len(programs) >= 5, programs
failures = []


def check(ok, program, what, text=""):
    if not ok:
        failures.append(f"{program}: {what}\n{text}")


for path in programs:
    name = path.name
    run = lambda *args: subprocess.run([str(path), *args], capture_output=True, text=True, timeout=60,
                                       cwd="/")
    shown = run("--help")
    check(shown.returncode == 0, name, f"--help exits {shown.returncode}", shown.stderr)
    check(f"Usage: {name}" in shown.stdout, name, "--help says Usage: NAME", shown.stdout[:400])
    long = [line for line in shown.stdout.splitlines() if len(line) > 80]
    check(not long, name, f"{len(long)} help lines over 80 columns", "\n".join(long[:3]))
    check("--version" in shown.stdout and "--help" in shown.stdout, name, "--help lists --help and --version")
    for tree in (str(source), str(build)):
        check(tree not in shown.stdout, name, f"--help shows a path of the tree ({tree})")
    version = run("--version")
    check(version.returncode == 0 and version.stdout.startswith(f"{name} ") and
          len(version.stdout.splitlines()) == 1, name, "--version prints NAME VERSION",
          version.stdout[:200] + version.stderr[:200])
    bad = run("--no-such-flag")
    check(bad.returncode == 2, name, f"an unknown flag exits {bad.returncode}, not 2", bad.stderr[:300])
    check(bad.stderr.startswith(f"{name}: error: ") and f"{name} --help" in bad.stderr, name,
          "an unknown flag says NAME: error: and points to --help", bad.stderr[:300])

# A missing required flag is a usage error too (it exited 106 in these two).
for name, args in (("fleetmem-credential", []), ("fleetmem-load", ["verify"])):
    path = build / "bin" / name
    if path.exists():
        done = subprocess.run([str(path), *args], capture_output=True, text=True, timeout=60)
        check(done.returncode == 2 and done.stderr.startswith(f"{name}: error: "), name,
              f"a missing required flag exits {done.returncode}", done.stderr[:300])

for failure in failures:
    print("FAIL", failure, file=sys.stderr)
print(f"{len(programs)} programs checked, {len(failures)} failures")
sys.exit(1 if failures else 0)
