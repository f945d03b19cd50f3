#!/usr/bin/env python3
"""Plots what `mpm run` wrote to OUTDIR: the force on each wall over time (forces.png) and a
picture of the particles, coloured by speed, with the walls' surfaces (render.png) at the time of
the largest wall force and at the end.

Usage: scripts/plot_run.py OUTDIR [--wall NAME]   (needs python3-matplotlib, python3-h5py)
"""
import argparse
import csv
import glob
import json
import os
import sys

import h5py
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402


def read_history(path):
    with open(path) as f:
        rows = list(csv.DictReader(f))
    t = np.array([float(r["time"]) for r in rows])
    walls = {}
    for key in rows[0]:
        if key.startswith("wall_") and key[-3:-1] == "_f":
            name = key[5:-3]
            walls.setdefault(name, []).append(np.array([float(r[key]) for r in rows]))
    return t, {k: np.stack(v, axis=1) for k, v in walls.items()}


def plot_forces(out, t, walls):
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for name, f in walls.items():
        magnitude = np.linalg.norm(f, axis=1)
        if magnitude.max() <= 0.0:
            continue
        ax.plot(t, magnitude / 1e3, label=f"{name} |F|")
    ax.set_xlabel("time (s)")
    ax.set_ylabel("force on wall (kN), averaged over each history interval")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(out, "forces.png"), dpi=120)
    plt.close(fig)


def frames(out):
    with h5py.File(os.path.join(out, "particles.h5"), "r") as h5:
        names = sorted(h5["frames"].keys())
        times = [float(h5["frames"][n].attrs["time"]) for n in names]
        return names, np.array(times)


def read_frame(out, name):
    with h5py.File(os.path.join(out, "particles.h5"), "r") as h5:
        g = h5["frames"][name]
        return np.array(g["position"]), np.array(g["velocity"])


def wall_surfaces(out):
    surfaces = []
    for path in sorted(glob.glob(os.path.join(out, "wall_*.h5"))):
        with h5py.File(path, "r") as h5:
            nodes = np.array(h5["layer"]["nodes"])
            facets = np.array(h5["layer"]["wall_facets"])
        if nodes.shape[1] < 3:
            nodes = np.hstack([nodes, np.zeros((nodes.shape[0], 3 - nodes.shape[1]))])
        surfaces.append((os.path.basename(path)[5:-3], nodes, facets))
    return surfaces


def render(out, dimension, picks):
    surfaces = wall_surfaces(out)
    fig = plt.figure(figsize=(6.5 * len(picks), 5.5))
    for k, (label, name) in enumerate(picks):
        x, v = read_frame(out, name)
        speed = np.linalg.norm(v, axis=1)
        if dimension == 3:
            ax = fig.add_subplot(1, len(picks), k + 1, projection="3d")
            for _, nodes, facets in surfaces:
                poly = Poly3DCollection(nodes[facets], facecolor=(0.75, 0.72, 0.66, 0.35),
                                        edgecolor=(0.4, 0.4, 0.4, 0.08), linewidth=0.2)
                ax.add_collection3d(poly)
            sc = ax.scatter(x[:, 0], x[:, 1], x[:, 2], c=speed, s=1.5, cmap="viridis",
                            depthshade=False)
            allpts = np.vstack([x] + [n for _, n, _ in surfaces])
            lo, hi = allpts.min(axis=0), allpts.max(axis=0)
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(lo[1], hi[1])
            ax.set_zlim(lo[2], hi[2])
            ax.set_box_aspect(hi - lo)
            ax.view_init(elev=35, azim=-115)
        else:
            ax = fig.add_subplot(1, len(picks), k + 1)
            for _, nodes, facets in surfaces:
                for f in facets:
                    ax.plot(nodes[f, 0], nodes[f, 1], color="0.3", lw=1)
            sc = ax.scatter(x[:, 0], x[:, 1], c=speed, s=2, cmap="viridis")
            ax.set_aspect("equal")
        ax.set_title(label)
        fig.colorbar(sc, ax=ax, shrink=0.6, label="speed (m/s)")
    fig.tight_layout()
    fig.savefig(os.path.join(out, "render.png"), dpi=110)
    plt.close(fig)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out")
    parser.add_argument("--wall", help="wall whose peak force picks the first picture")
    args = parser.parse_args()
    summary = json.load(open(os.path.join(args.out, "summary.json")))
    t, walls = read_history(os.path.join(args.out, "history.csv"))
    plot_forces(args.out, t, walls)
    names, times = frames(args.out)
    peaks = summary.get("walls", {})
    wall = args.wall or (max(peaks, key=lambda w: peaks[w]["peak_force"]) if peaks else None)
    picks = []
    if wall and peaks[wall]["peak_force"] > 0.0:
        t_peak = peaks[wall]["peak_force_time"]
        i = int(np.argmin(np.abs(times - t_peak)))
        picks.append((f"t = {times[i]:.2f} s (peak force on {wall})", names[i]))
    picks.append((f"t = {times[-1]:.2f} s (end)", names[-1]))
    render(args.out, summary["dimension"], picks)
    print(f"wrote {args.out}/forces.png and {args.out}/render.png")


if __name__ == "__main__":
    sys.exit(main())
