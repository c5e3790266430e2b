#!/usr/bin/env python3
"""Lists the functions of the tree's C++ sources longer than a bound.

    tools/ci/long_functions.py [--max 80] [--under services clients tools]

A function is counted from its first line (at column 0) to the closing
brace at column 0 that ends it, so a definition indented inside a class
is not seen (class bodies here are short). Tests, fuzzers and benchmarks
are left out. A function whose comment above says "Long (" gives its reason
and is marked so. Prints one line per function, longest first, then the
count without a reason (docs/architecture.md, "Code shape")."""
import argparse
import pathlib
import re
import subprocess
import sys

SKIP = ("_test.cc", "_fuzz.cc", "_bench.cc")


def functions(path):
    lines = path.read_text(errors="ignore").split("\n")
    i = 0
    while i < len(lines):
        line = lines[i]
        stripped = line.rstrip()
        starts = (line and not line[0].isspace() and line[0] not in "#}/"
                  and not line.startswith(("namespace", "using"))
                  and "(" in line and not stripped.endswith(("}", ";")))
        if starts:
            j = i
            while (j < len(lines) and j < i + 8
                   and not lines[j].rstrip().endswith(("{", ";"))):
                j += 1
            if j < len(lines) and lines[j].rstrip().endswith("{"):
                k = j + 1
                while k < len(lines) and lines[k] != "}":
                    k += 1
                name = re.search(r"([A-Za-z_:~]+)\(", line)
                above = "\n".join(lines[max(0, i - 8):i])
                yield (k - i + 1, i + 1, name.group(1) if name else line[:40],
                       "Long (" in above)
                i = k
        i += 1


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--max", type=int, default=80)
    parser.add_argument("--under", nargs="*",
                        default=["services", "clients", "tools", "proto"])
    args = parser.parse_args()
    root = pathlib.Path(__file__).resolve().parents[2]
    files = subprocess.run(["git", "ls-files", "*.cc"], cwd=root, text=True,
                           capture_output=True, check=True).stdout.split()
    found = []
    for name in files:
        if not name.startswith(tuple(d + "/" for d in args.under)):
            continue
        if name.endswith(SKIP) or "/testing/" in name:
            continue
        for length, line, function, reason in functions(root / name):
            if length > args.max:
                found.append((length, f"{name}:{line}", function, reason))
    for length, where, function, reason in sorted(found, reverse=True):
        print(length, where, function, "(reason given)" if reason else "")
    sizes = sorted(
        len((root / name).read_text(errors="ignore").split("\n")) - 1
        for name in subprocess.run(
            ["git", "ls-files", "*.cc", "*.h"], cwd=root, text=True,
            capture_output=True, check=True).stdout.split()
        if name.startswith(tuple(d + "/" for d in args.under)))
    if sizes:
        print(f"median source file: {sizes[(len(sizes) - 1) // 2]} lines "
              f"of {len(sizes)} files")
    unexplained = sum(1 for f in found if not f[3])
    print(f"{len(found)} functions over {args.max} lines, "
          f"{unexplained} without a reason")
    return 0


if __name__ == "__main__":
    sys.exit(main())
