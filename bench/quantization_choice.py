#!/usr/bin/python3
"""int8 scalar quantization of place codes: one scale per code or one per
dimension (issue 49: "per-dimension or per-vector scale, chosen by
measurement").

The codes are bench/import_bench.sh's (256-d, a 16-d gaussian latent through
a fixed random map, noise 0.05, unit length), N of them and 500 queries from
the same source. For each scheme the script ranks every code by its squared
distance after quantization (code and query quantized alike, as the graph
compares two nodes) and reports recall@10 of that ranking's top 10 and top
40 (what rescoring with the floats then sees: k x rescore_oversample 4)
against the exact top 10, and the mean relative error of the squared
distance to the 10 exact neighbours.

  per_code       s = max |x_i| / 127 for each code (core::HnswGraph's)
  per_dimension  s_d = max over the codes of |x_d| / 127, fixed from the
                 first 10,000 codes (a graph must fix it before it holds
                 them all; codes outside clip)

  bench/quantization_choice.py [N] > quantization.csv
"""
import sys

import numpy as np


def codes_like_import_bench(n, seed):
    rng = np.random.default_rng(seed)
    basis = np.random.default_rng(7).standard_normal((16, 256))
    codes = rng.standard_normal((n, 16)) @ basis
    codes += 0.05 * np.sqrt((codes ** 2).mean()) * rng.standard_normal((n, 256))
    codes /= np.linalg.norm(codes, axis=1, keepdims=True)
    return codes.astype(np.float32)


def quantize_per_code(x):
    step = np.abs(x).max(axis=1, keepdims=True) / 127.0
    step[step == 0] = 1.0
    return np.clip(np.rint(x / step), -127, 127) * step


def quantize_per_dimension(x, step):
    return np.clip(np.rint(x / step), -127, 127) * step


def squared_distances(queries, codes):
    return ((queries ** 2).sum(1)[:, None] + (codes ** 2).sum(1)[None, :]
            - 2.0 * queries @ codes.T)


def main():
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 100_000
    codes = codes_like_import_bench(n, 11)
    queries = codes_like_import_bench(500, 13)
    exact = squared_distances(queries.astype(np.float64),
                              codes.astype(np.float64))
    truth = np.argsort(exact, axis=1)[:, :10]
    step = np.abs(codes[:10_000]).max(axis=0) / 127.0
    schemes = {
        "per_code": (quantize_per_code(codes), quantize_per_code(queries)),
        "per_dimension": (quantize_per_dimension(codes, step),
                          quantize_per_dimension(queries, step)),
    }
    print("scheme,codes,recall10_top10,recall10_top40,distance_rel_error")
    for name, (qc, qq) in schemes.items():
        approx = squared_distances(qq.astype(np.float64), qc.astype(np.float64))
        order = np.argsort(approx, axis=1)
        hits10 = np.mean([len(set(truth[i]) & set(order[i, :10])) / 10
                          for i in range(len(queries))])
        hits40 = np.mean([len(set(truth[i]) & set(order[i, :40])) / 10
                          for i in range(len(queries))])
        rows = np.arange(len(queries))[:, None]
        error = np.mean(np.abs(approx[rows, truth] - exact[rows, truth])
                        / exact[rows, truth])
        print(f"{name},{n},{hits10:.4f},{hits40:.4f},{error:.5f}")


if __name__ == "__main__":
    main()
