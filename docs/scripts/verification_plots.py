#!/usr/bin/python3
"""Convergence plots and observed orders from `mpm verify --convergence --json FILE`.

    build/bin/mpm verify --convergence --case incline_block_2d --case rolling_cylinder_2d \\
        --case self_weight_column_2d --case bar_impact_1d --case axial_vibration_1d \\
        --json docs/verification_convergence.json
    /usr/bin/python3 docs/scripts/verification_plots.py docs/verification_convergence.json

`verification_plots.py summary docs/verification.json` prints the pass counts per case and method
of a plain `mpm verify --json` run instead.

Prints a Markdown table of the observed order per case, measure and method (least-squares slope
of log error against log h over the resolutions that finished) and writes
docs/img/verification_<case>.png. Needs python3-matplotlib (Debian).
"""
import json
import math
import os
import sys
from collections import defaultdict

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
IMG = os.path.join(ROOT, "docs", "img")
STYLE = {"grid": "k-o", "sdf": "C1-s", "one-way": "C3-x", "mortar": "C0-o", "enhanced": "C2-^"}


def slope(points):
    """Least-squares slope of log(error) against log(h) (h = 1 / K)."""
    pts = [(math.log(1.0 / k), math.log(e)) for k, e in points if e > 0 and math.isfinite(e)]
    if len(pts) < 2:
        return None
    mx = sum(x for x, _ in pts) / len(pts)
    my = sum(y for _, y in pts) / len(pts)
    sxx = sum((x - mx) ** 2 for x, _ in pts)
    return sum((x - mx) * (y - my) for x, y in pts) / sxx if sxx > 0 else None


def summary(path):
    """Pass counts per case and method, and the worst value against its tolerance."""
    checks = json.load(open(path))
    methods = ["grid", "sdf", "one-way", "mortar", "enhanced"]
    cells = defaultdict(list)
    for c in checks:
        cells[(c["case"], c["method"])].append(c)
    cases = sorted({c["case"] for c in checks})
    print("| case | " + " | ".join(methods) + " |")
    print("|---|" + "---|" * len(methods))
    for case in cases:
        row = []
        for m in methods:
            cs = cells.get((case, m))
            if not cs:
                row.append("n/a")
                continue
            ok = sum(1 for c in cs if c["pass"])
            faults = sum(1 for c in cs if c["note"])
            worst = max(cs, key=lambda c: c["value"] / c["tolerance"] if c["tolerance"] else 0)
            text = f"{ok}/{len(cs)}"
            if faults:
                text += " (fault)"
            else:
                text += f", worst {worst['value']:.2g}"
            row.append(text)
        print(f"| {case} | " + " | ".join(row) + " |")


def main(paths):
    checks = [c for path in paths for c in json.load(open(path))]
    series = defaultdict(list)  # (case, measure, method) -> [(K, value)]
    for c in checks:
        if c["note"]:
            continue  # a numerical fault: no error value to plot
        series[(c["case"], c["measure"], c["method"])].append((c["resolution"], c["value"]))
    print("| case | measure | method | error at K = 1, 2, 4 | observed order |")
    print("|---|---|---|---|---|")
    for (case, measure, method), pts in sorted(series.items()):
        pts.sort()
        order = slope(pts)
        errors = ", ".join(f"{e:.2e}" for _, e in pts)
        print(f"| {case} | {measure} | {method} | {errors} | "
              f"{'-' if order is None else f'{order:.2f}'} |")
    os.makedirs(IMG, exist_ok=True)
    cases = sorted({c for c, _, _ in series})
    for case in cases:
        measures = sorted({m for c, m, _ in series if c == case})
        cols = min(3, len(measures))
        rows = (len(measures) + cols - 1) // cols
        fig, axes = plt.subplots(rows, cols, figsize=(5 * cols, 3.6 * rows), squeeze=False)
        for ax, measure in zip(axes.flat, measures):
            for (c, m, method), pts in sorted(series.items()):
                if c != case or m != measure:
                    continue
                ks = [k for k, _ in pts]
                ax.loglog([1.0 / k for k in ks], [max(e, 1e-8) for _, e in pts],
                          STYLE.get(method, "-o"), label=method, ms=4)
            ax.set_title(measure, fontsize=8)
            ax.set_xlabel("h / h0")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
        for ax in list(axes.flat)[len(measures):]:
            ax.axis("off")
        fig.suptitle(case)
        fig.tight_layout()
        fig.savefig(os.path.join(IMG, f"verification_{case}.png"), dpi=100)
        plt.close(fig)


if __name__ == "__main__":
    if len(sys.argv) > 2 and sys.argv[1] == "summary":
        summary(sys.argv[2])
    else:
        main(sys.argv[1:] or [os.path.join(ROOT, "docs", "verification_convergence.json")])
