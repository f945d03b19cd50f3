#!/usr/bin/env python3
"""Plots and reads the CSV of `mpm bench`.

bench_plot.py accuracy CSV PNG [--table MD]
    Error against wall time (log-log), one panel per series, one line per wall method (labels:
    the refinement factor K); points on the Pareto front (no other run is both faster and more
    accurate) ringed. Prints, per series, which methods are on the front and by how much: at
    the most accurate front point, the time each other method needs for that error and the
    error each reaches in that time (both from its own runs: the best of those within the
    budget, no interpolation).
bench_plot.py stability CSV PNG
    Closest approach and penetration (throws), energy growth per run, largest stable CFL per
    method and shape function, creep and drift of the long runs.
"""
import argparse
import csv
import math
from collections import defaultdict

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

METHODS = ["grid", "sdf", "one-way", "mortar", "enhanced"]
COLOURS = {"grid": "#444444", "sdf": "#1f77b4", "one-way": "#ff7f0e", "mortar": "#2ca02c",
           "enhanced": "#d62728"}


def number(x):
    try:
        return float(x)
    except ValueError:
        return math.nan


def read(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def pareto(points):
    """Indices of the points no other point beats in both time and error."""
    front = []
    for i, (t, e, *_rest) in enumerate(points):
        dominated = any((t2 <= t and e2 <= e) and (t2 < t or e2 < e)
                        for j, (t2, e2, *_r) in enumerate(points) if j != i)
        if not dominated:
            front.append(i)
    return front


def best_time_for(points, error):
    """Least time among a method's runs that reach `error` or better (None if none does)."""
    times = [t for t, e in points if e <= error]
    return min(times) if times else None


def best_error_within(points, seconds):
    """Least error among a method's runs that take at most `seconds` (None if none does)."""
    errors = [e for t, e in points if t <= seconds]
    return min(errors) if errors else None


def accuracy(args):
    rows = read(args.csv)
    series = defaultdict(lambda: defaultdict(list))
    for r in rows:
        e, t = number(r["error"]), number(r["seconds"])
        if math.isfinite(e) and math.isfinite(t) and e > 0:
            series[r["series"]][r["method"]].append((t, e, int(r["resolution"])))
    names = list(series)
    cols = min(3, len(names))
    rows_n = math.ceil(len(names) / cols)
    fig, axes = plt.subplots(rows_n, cols, figsize=(5.2 * cols, 4.2 * rows_n), squeeze=False)
    lines = []
    for ax, name in zip(axes.flat, names):
        methods = series[name]
        every = [(t, e, m, k) for m, pts in methods.items() for t, e, k in pts]
        front = [every[i] for i in pareto(every)]
        for m in METHODS:
            if m not in methods:
                continue
            pts = sorted(methods[m], key=lambda p: p[2])
            ax.loglog([p[0] for p in pts], [p[1] for p in pts], "o-", color=COLOURS[m], label=m,
                      ms=4)
            for t, e, k in pts:
                ax.annotate(f"{k}", (t, e), textcoords="offset points", xytext=(3, 3),
                            fontsize=7, color=COLOURS[m])
        ax.loglog([p[0] for p in front], [p[1] for p in front], "o", mfc="none", mec="black",
                  ms=10, label="Pareto front")
        ax.set_title(name)
        ax.set_xlabel("wall time [s]")
        ax.set_ylabel("error")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)

        counts = defaultdict(int)
        for _t, _e, m, _k in front:
            counts[m] += 1
        lines.append(f"### {name}\n")
        lines.append("Pareto front: " + ", ".join(
            f"{m} ({n} of {len(methods[m])} runs)" for m, n in sorted(
                counts.items(), key=lambda x: -x[1])) + "\n")
        # The reference: the front's most accurate point.
        t0, e0, m0, k0 = min(front, key=lambda p: p[1])
        lines.append(f"Most accurate front point: {m0} K = {k0}, error {e0:.3g} in {t0:.3g} s.\n")
        lines.append("| method | best error (K, s) | time for error <= {:.3g} | ratio | "
                     "error within {:.3g} s | ratio |".format(e0, t0))
        lines.append("|---|---|---|---|---|---|")
        for m in METHODS:
            if m not in methods:
                continue
            pts = [(t, e) for t, e, _k in methods[m]]
            bt, be, bk = min(methods[m], key=lambda p: p[1])
            t_need = best_time_for(pts, e0)
            e_got = best_error_within(pts, t0)
            lines.append("| {} | {:.3g} (K = {}, {:.3g} s) | {} | {} | {} | {} |".format(
                m, be, bk, bt,
                f"{t_need:.3g} s" if t_need is not None else "not reached",
                f"{t_need / t0:.3g}" if t_need is not None else "-",
                f"{e_got:.3g}" if e_got is not None else "no run that fast",
                f"{e_got / e0:.3g}" if e_got is not None else "-"))
        lines.append("")
    for ax in list(axes.flat)[len(names):]:
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(args.png, dpi=110)
    text = "\n".join(lines)
    print(text)
    if args.table:
        with open(args.table, "w") as f:
            f.write(text + "\n")


def stability(args):
    rows = read(args.csv)
    fig, axes = plt.subplots(2, 2, figsize=(12, 8.5))
    throws = [r for r in rows if r["part"] == "throws"]
    ax = axes[0][0]
    for m in METHODS:
        sel = [r for r in throws if r["method"] == m]
        if not sel:
            continue
        closest = [number(r["closest_h"]) for r in sel]
        ax.hist(closest, bins=30, histtype="step", color=COLOURS[m], label=f"{m} ({len(sel)})")
    ax.axvline(0.0, color="black", lw=0.8)
    ax.set_xlabel("closest particle centre to the wall over the run [h]")
    ax.set_ylabel("runs")
    ax.set_title("throws: closest approach (2 particles per cell: half-width 0.25 h)")
    ax.legend(fontsize=8)

    ax = axes[0][1]
    for i, m in enumerate(METHODS):
        sel = [r for r in rows if r["method"] == m and r["part"] in ("throws", "crossing")]
        if not sel:
            continue
        growth = [max(number(r["energy_growth"]), 1e-16) for r in sel]
        ax.semilogy([i + 0.15 * (j % 5 - 2) / 2 for j in range(len(sel))], growth, ".",
                    color=COLOURS[m], alpha=0.6)
    ax.axhline(0.01, color="black", ls="--", lw=0.8, label="limit 1%")
    ax.set_xticks(range(len(METHODS)), METHODS)
    ax.set_ylabel("energy growth / energy scale")
    ax.set_title("throws and crossing: energy growth per run (1e-16 = none)")
    ax.legend(fontsize=8)

    ax = axes[1][0]
    cfl = [r for r in rows if r["part"] == "cfl"]
    shapes = sorted({r["kernel"] for r in cfl})
    methods = [m for m in METHODS if any(r["method"] == m for r in cfl)]
    table = []
    for m in methods:
        row = []
        for s in shapes:
            runs = sorted((number(r["cfl"]), r["failed"] == "1") for r in cfl
                          if r["method"] == m and r["kernel"] == s)
            largest = 0.0
            for c, failed in runs:
                if failed:
                    break
                largest = c
            row.append(largest)
        table.append(row)
    if table:
        im = ax.imshow(table, cmap="viridis", vmin=0, vmax=1)
        for i in range(len(methods)):
            for j in range(len(shapes)):
                ax.text(j, i, f"{table[i][j]:.1f}", ha="center", va="center", color="white")
        ax.set_xticks(range(len(shapes)), shapes, rotation=15)
        ax.set_yticks(range(len(methods)), methods)
        fig.colorbar(im, ax=ax)
    ax.set_title("largest stable CFL number (every smaller one passes too)")
    ax.set_xlabel("shape function / transfer")

    ax = axes[1][1]
    long_runs = [r for r in rows if r["part"] == "long"]
    x = range(len(long_runs))
    ax.bar([i - 0.2 for i in x], [number(r["creep_h"]) for r in long_runs], 0.4,
           label="creep [h]")
    ax.bar([i + 0.2 for i in x], [abs(number(r["energy_drift"])) for r in long_runs], 0.4,
           label="|energy drift| / (m g height)")
    ax.set_yscale("log")
    ax.set_xticks(list(x), [r["method"] for r in long_runs])
    steps = long_runs[0]["steps"] if long_runs else "?"
    ax.set_title(f"resting block on a 20 degree incline, mu 0.5, {steps} steps")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.png, dpi=110)


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("kind", choices=["accuracy", "stability"])
    p.add_argument("csv")
    p.add_argument("png")
    p.add_argument("--table", help="accuracy: also write the Pareto tables (markdown) here")
    args = p.parse_args()
    accuracy(args) if args.kind == "accuracy" else stability(args)


if __name__ == "__main__":
    main()
