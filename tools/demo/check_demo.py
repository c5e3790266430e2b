#!/usr/bin/env python3
"""Checks a fleetmem-demo results table (tools/demo/demo_smoke_test.sh).

  check_demo.py RESULTS_MD ROBOTS FRAMES_PER_ROBOT

Every system row scores ROBOTS x FRAMES winter queries (the learned head on
its peers' frames: ROBOTS - 1 times as many): its recalls are counts over them (multiples of 1/queries), recall@1 <= recall@5, WR lies
between what recall@1 and recall@5 allow; the baseline and the learned row
search every summer frame (traces held = queries); the fleet memory row's
recall@1 and WR are the frame-weighted means of the per-robot rows. The
fleet memory, the baseline and the learned rows come each also over
sequences (fleetmem-robot --sequence).
Exits 1 with the failed checks.
"""
import sys


def rows(text, first_header):
    out, on = [], False
    for line in text.splitlines():
        if line.startswith("| %s |" % first_header):
            on = True
            continue
        if on and line.startswith("|---"):
            continue
        if on and line.startswith("|"):
            out.append([c.strip() for c in line.strip().strip("|").split("|")])
        elif on:
            break
    return out


def main():
    path, robots, frames = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    text = open(path).read()
    failures = []

    def check(ok, what):
        if not ok:
            failures.append(what)

    systems = {r[0]: r for r in rows(text, "system")}
    names = list(systems)
    check(any(n.startswith("fleet memory") for n in names), "no fleet memory row")
    check(any(n.startswith("all traces") for n in names), "no baseline row")
    learned = [n for n in names if n.startswith("HOG + metric head learned")]
    check(len(learned) == 4,
          "want the learned head's two rows, each also over sequences: %s" % names)
    sequences = [n for n in names if "sequences of" in n]
    check(len(sequences) == 4,
          "want sequence rows of the fleet memory, the baseline and the two learned: %s"
          % names)
    for name, r in systems.items():
        r1, r5, wr = float(r[1]), float(r[2]), float(r[3])
        # Each robot's head scores every peer's winter frames.
        queries = robots * frames * ((robots - 1) if "peers'" in name else 1)
        for value, label in ((r1, "recall@1"), (r5, "recall@5")):
            # Printed with three decimals: within 0.0005 of k / queries.
            check(abs(value * queries - round(value * queries)) <= 0.0005 * queries + 1e-9,
                  "%s: %s %.3f is not a count over %d queries" % (name, label, value, queries))
        check(0 <= r1 <= r5 <= 1, "%s: recall@1 %.3f > recall@5 %.3f" % (name, r1, r5))
        # WR = 0.5 r1 + 0.1 (r2 + ... + r6) with r1 <= r2 <= ... <= r6 <= 1.
        check(0.9 * r1 - 0.001 <= wr <= 0.5 * r1 + 0.4 * r5 + 0.1 + 0.001,
              "%s: WR %.3f outside what recall@1 %.3f / recall@5 %.3f allow" % (name, wr, r1, r5))
        if not name.startswith("fleet memory"):
            check(r[4] == str(robots * frames), "%s: map of %s frames, want every summer frame (%d)" % (name, r[4], robots * frames))
    per_robot = rows(text, "robot")
    check(len(per_robot) == robots, "want %d robot rows, got %d" % (robots, len(per_robot)))
    memory = next((r for n, r in systems.items() if n.startswith("fleet memory")), None)
    if memory is not None and len(per_robot) == robots:
        r1 = sum(float(r[6]) for r in per_robot) / robots
        wr = sum(float(r[7]) for r in per_robot) / robots
        check(abs(r1 - float(memory[1])) <= 0.002, "fleet memory recall@1 %s != robots' mean %.3f" % (memory[1], r1))
        check(abs(wr - float(memory[3])) <= 0.002, "fleet memory WR %s != robots' mean %.3f" % (memory[3], wr))
    if failures:
        print("check_demo: FAILED\n  " + "\n  ".join(failures))
        print(text)
        return 1
    print("check_demo: %d rows: ok" % len(systems))
    return 0


if __name__ == "__main__":
    sys.exit(main())
