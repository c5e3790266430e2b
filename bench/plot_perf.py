#!/usr/bin/python3
"""Plots of docs/performance.md from the committed benchmark outputs.

    bench/plot_perf.py docs/perf

Reads memory_scale.json and ann.json (Google Benchmark JSON) and
server_scale.csv from the directory, writes *.dat tables (in a temporary directory) and draws the
log-log plots with gnuplot (PNG) into the same directory.
"""
import csv
import json
import os
import shutil
import subprocess
import sys
import tempfile


def load(path):
    with open(path) as f:
        return json.load(f)["benchmarks"]


def series(benchmarks, prefix):
    """(size, ms) of the runs named prefix/<size>, by size."""
    points = []
    for b in benchmarks:
        name = b["name"]
        if not name.startswith(prefix + "/"):
            continue
        size = int(name[len(prefix) + 1:].split("/")[0])
        ms = b["real_time"] * {"ms": 1, "us": 1e-3, "ns": 1e-6}[b["time_unit"]]
        points.append((size, ms))
    return sorted(points)


# The gnuplot data files are intermediates: they go to a temporary
# directory, only the plots to the output directory.
DAT_DIR = tempfile.mkdtemp(prefix="fleetmem-plot-")


def write(name, points):
    with open(os.path.join(DAT_DIR, name), "w") as f:
        for x, y in points:
            f.write(f"{x} {y}\n")


def plot(out_dir, name, title, ylabel, curves):
    if not curves:
        return
    lines = [
        "set terminal png size 800,500",
        f"set output '{os.path.join(out_dir, name)}.png'",
        f"set title '{title}'",
        "set logscale xy",
        "set xlabel 'traces in the memory'",
        f"set ylabel '{ylabel}'",
        "set key top left",
        "set grid",
    ]
    parts = []
    for data, label in curves:
        parts.append(f"'{os.path.join(DAT_DIR, data)}' using 1:2 "
                     f"with linespoints title '{label}'")
    lines.append("plot " + ", ".join(parts))
    subprocess.run(["gnuplot"], input="\n".join(lines), text=True, check=True)


def main():
    out = sys.argv[1] if len(sys.argv) > 1 else "docs/perf"
    scale = load(os.path.join(out, "memory_scale.json"))
    for prefix, file in [
        ("BM_Consolidate", None), ("BM_SampleReplay", "sample.dat"),
        ("BM_SampleReplayScan", "sample_scan.dat"), ("BM_Stats", "stats.dat"),
        ("BM_StatsScan", "stats_scan.dat")]:
        if file:
            write(file, series(scale, prefix))
    by_mode = {0: [], 1: []}
    for b in scale:
        if b["name"].startswith("BM_Consolidate/"):
            _, size, exact = b["name"].split("/")[:3]
            by_mode[int(exact)].append((int(size), b["real_time"]))
    write("consolidate_hnsw.dat", sorted(by_mode[0]))
    write("consolidate_exact.dat", sorted(by_mode[1]))
    plot(out, "consolidate", "P4: consolidation + forgetting of a 200-trace "
         "segment into a full memory", "ms per segment",
         [("consolidate_hnsw.dat", "closest pair via HNSW over centroids"),
          ("consolidate_exact.dat", "peer: exact scans (previous)")])
    plot(out, "sample_stats", "P5 SampleReplay of 1,000 and per-robot/domain "
         "statistics", "ms per call",
         [("sample.dat", "SampleReplay: sum tree"),
          ("sample_scan.dat", "peer: SampleReplay by scan (previous)"),
          ("stats.dat", "statistics: kept counts"),
          ("stats_scan.dat", "peer: statistics by walking every trace")])

    ann_path = os.path.join(out, "ann.json")
    ann = load(ann_path) if os.path.exists(ann_path) else []
    kinds = {0: "fleetmem exact", 2: "fleetmem HNSW (ef 128)",
             3: "hnswlib direct", 4: "faiss HNSW", 5: "faiss flat",
             6: "peer: exact with Eigen's scan (previous)",
             7: "exact, streaming scan at every size"}
    curves = []
    for kind, label in kinds.items():
        points = []
        for b in ann:
            parts = b["name"].split("/")
            if (parts[0] == "BM_Query" and int(parts[1]) == kind and
                    b.get("ef_search", 128) == 128):
                points.append((int(parts[2]), b["p50_ms"]))
        if points:
            write(f"query_{kind}.dat", sorted(points))
            curves.append((f"query_{kind}.dat", label))
    plot(out, "query", "Place query (k = 10, 256-d), median latency",
         "ms per query", curves)

    server = os.path.join(out, "server_scale.csv")
    if os.path.exists(server):
        fill, calls = [], {"query": [], "sample": [], "stats": []}
        with open(server) as f:
            for row in csv.DictReader(f):
                if not row["size"].isdigit():
                    continue
                size = int(row["size"])
                fill.append((size, float(row["fill_traces_per_s"])))
                calls["query"].append((size, float(row["query_p50_ms"])))
                calls["sample"].append((size, float(row["sample_p50_ms"])))
                calls["stats"].append((size, float(row["stats_p50_ms"])))
        write("fill.dat", fill)
        for name, points in calls.items():
            write(f"server_{name}.dat", points)
        plot(out, "server", "The real server as one fleet fills (gRPC, "
             "loopback), median latency", "ms per call",
             [("server_query.dat", "QueryPlace k=10"),
              ("server_sample.dat", "SampleReplay of 1,000"),
              ("server_stats.dat", "GetStats")])
        plot(out, "fill", "Upload throughput while one fleet fills "
             "(4 streams, batches of 200)", "traces/s",
             [("fill.dat", "fleetmem")])


def fmt_ms(ms):
    if ms >= 1000:
        return f"{ms / 1000:.2f} s"
    return f"{ms * 1000:.1f} µs" if ms < 0.1 else f"{ms:.3g} ms"


def tables(out):
    """Prints the markdown tables of docs/performance.md."""
    scale = {b["name"]: b for b in load(os.path.join(out, "memory_scale.json"))}
    print("| traces | consolidate + forget (HNSW pair) | peer: exact scans "
          "| SampleReplay 1,000 | peer: scan | stats | peer: walk |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    for n in (5000, 100000, 1000000):
        def t(name):
            b = scale.get(name)
            return fmt_ms(b["real_time"]) if b else "—"
        print(f"| {n:,} | {t(f'BM_Consolidate/{n}/0')} | "
              f"{t(f'BM_Consolidate/{n}/1')} | {t(f'BM_SampleReplay/{n}')} | "
              f"{t(f'BM_SampleReplayScan/{n}')} | {t(f'BM_Stats/{n}')} | "
              f"{t(f'BM_StatsScan/{n}')} |")
    print()
    print("| traces | Restore of every cluster (a restart's static-memory share) |")
    print("|---:|---:|")
    for n in (100000, 1000000):
        b = scale.get(f"BM_Restore/{n}/iterations:1")
        print(f"| {n:,} | {fmt_ms(b['real_time']) if b else '—'} |")
    print()
    names = {0: "fleetmem exact", 1: "fleetmem tiered (auto)",
             2: "fleetmem HNSW", 3: "hnswlib direct", 4: "faiss HNSW",
             5: "faiss flat", 6: "fleetmem exact, Eigen's scan (previous)",
             7: "fleetmem exact, streaming scan at every size"}
    ann = []
    path = os.path.join(out, "ann.json")
    if os.path.exists(path):
        ann = load(path)
    print("| size | index | ef_search | recall@10 | p50 | p99 | QPS "
          "| of copy bandwidth |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|")
    for b in ann:
        parts = b["name"].split("/")
        if parts[0] != "BM_Query":
            continue
        kind, size = int(parts[1]), int(parts[2])
        ef = "—" if kind in (0, 5, 6, 7) or (kind == 1 and size < 20000) else \
            str(int(b.get("ef_search", 128)))
        bw = f"{b['bw_fraction']:.2f}" if "bw_fraction" in b else ""
        print(f"| {size:,} | {names[kind]} | {ef} | {b['recall@10']:.3f} | "
              f"{fmt_ms(b['p50_ms'])} | {fmt_ms(b['p99_ms'])} | "
              f"{b['qps']:.0f} | {bw} |")
    print()
    load_csv = os.path.join(out, "load.csv")
    if os.path.exists(load_csv):
        print("| streams | target | traces/s | upload p50 | p99 | p99.9 "
              "| query p50 | query p99 | ratio to peer |")
        print("|---:|---|---:|---:|---:|---:|---:|---:|---:|")
        with open(load_csv) as f:
            for r in csv.DictReader(f):
                print(f"| {r['streams']} | {r['target']} | "
                      f"{float(r['uploads_per_s']):,.0f} | "
                      f"{float(r['upload_p50_ms']):.2f} ms | "
                      f"{float(r['upload_p99_ms']):.2f} ms | "
                      f"{float(r['upload_p999_ms']):.2f} ms | "
                      f"{float(r['query_p50_ms']):.2f} ms | "
                      f"{float(r['query_p99_ms']):.2f} ms | "
                      f"{float(r['ratio_to_peer']):.3f} |")
    print()
    server = os.path.join(out, "server_scale.csv")
    if os.path.exists(server):
        with open(server) as f:
            rows = list(csv.reader(f))
        print("| " + " | ".join(rows[0]) + " |")
        print("|" + "---:|" * len(rows[0]))
        for row in rows[1:]:
            print("| " + " | ".join(row) + " |")


if __name__ == "__main__":
    try:
        main()
    finally:
        shutil.rmtree(DAT_DIR, ignore_errors=True)
    tables(sys.argv[1] if len(sys.argv) > 1 else "docs/perf")
