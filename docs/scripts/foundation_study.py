#!/usr/bin/python3
"""Standard-MPM verification study behind docs/foundation.md.

Runs build/bin/mpm on variants of the shipped 1D scenes and the 3D drop, writes PNG plots to
docs/img/ and prints the markdown tables. Needs python3-matplotlib (Debian); run from the
repository root after a release build:  /usr/bin/python3 docs/scripts/foundation_study.py
"""
import csv
import json
import math
import os
import subprocess
import tempfile

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
MPM = os.path.join(ROOT, "build", "bin", "mpm")
IMG = os.path.join(ROOT, "docs", "img")
SHAPES = ["linear", "gimp", "bspline2"]


def run(scene, work):
    path = os.path.join(work, "scene.json")
    out = os.path.join(work, "out")
    with open(path, "w") as f:
        json.dump(scene, f)
    subprocess.run([MPM, "run", path, "-o", out, "--overwrite", "-q"], check=True,
                   stderr=subprocess.DEVNULL)
    with open(os.path.join(out, "history.csv")) as f:
        rows = [{k: float(v) for k, v in r.items()} for r in csv.DictReader(f)]
    with open(os.path.join(out, "summary.json")) as f:
        return rows, json.load(f)


def load(name):
    with open(os.path.join(ROOT, "data", "scenes", name)) as f:
        return json.load(f)


def vibration(work):
    base = load("bar_vibration_1d.json")
    L, v0, c = 25.0, 0.1, 10.0
    beta = math.pi / (2 * L)
    omega, amp = beta * c, v0 / (beta * L)
    print("\n| shape | h | ppc | transfer | max error of v_cm / amplitude over 4 periods | period error |")
    print("|---|---|---|---|---|---|")
    fig, ax = plt.subplots(figsize=(8, 4))
    for shape in SHAPES:
        for h in [1.0, 0.5]:
            for ppc in [1, 2]:
                for transfer in ["flip", "apic"]:
                    s = json.loads(json.dumps(base))
                    s["shape_function"], s["grid"]["spacing"] = shape, h
                    s["bodies"][0]["particles_per_cell"] = ppc
                    s["scheme"] = {"update": "musl", "transfer": transfer}
                    if transfer == "flip":
                        s["scheme"]["flip_blend"] = 1.0
                    s["output"]["history_interval"] = 0.02
                    try:
                        rows, _ = run(s, work)
                    except subprocess.CalledProcessError:
                        print(f"| {shape} | {h} | {ppc} | {transfer} | numerical fault | |")
                        continue
                    t = [r["time"] for r in rows]
                    v = [r["momentum_x"] / L / amp for r in rows]
                    err = max(abs(vi - math.cos(omega * ti)) for ti, vi in zip(t, v))
                    zero = [t[i - 1] + (t[i] - t[i - 1]) * v[i - 1] / (v[i - 1] - v[i])
                            for i in range(1, len(v)) if (v[i - 1] > 0) != (v[i] > 0)]
                    period = 2 * (zero[-1] - zero[0]) / (len(zero) - 1)
                    print(f"| {shape} | {h} | {ppc} | {transfer} | {err:.4f} | "
                          f"{(period - 10.0) / 10.0:+.4%} |")
                    if h == 0.5 and ppc == 1 and transfer == "flip":
                        ax.plot(t, v, label=f"{shape}")
    tt = [0.02 * k for k in range(2001)]
    ax.plot(tt, [math.cos(omega * x) for x in tt], "k--", lw=1, label="exact")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("v_cm / (v0 / beta L)")
    ax.set_title("Axial vibration, fixed-free bar, MUSL/FLIP, h = L/50, 1 particle per cell")
    ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(IMG, "vibration_1d.png"), dpi=110)


def impact(work):
    base = load("bar_impact_1d.json")
    c = math.sqrt(2e11 / 7850)
    sigma0, T = 7850 * c, 2.0 / c
    print("\n| shape | transfer | plateau / rho c v0 | contact time / (2L/c) | rebound / v0 | energy change |")
    print("|---|---|---|---|---|---|")
    fig, ax = plt.subplots(figsize=(8, 4))
    for shape in SHAPES:
        for transfer in ["flip", "apic"]:
            s = json.loads(json.dumps(base))
            s["shape_function"] = shape
            s["scheme"] = {"update": "musl", "transfer": transfer}
            if transfer == "flip":
                s["scheme"]["flip_blend"] = 1.0
            rows, _ = run(s, work)
            t = [r["time"] for r in rows]
            f = [-r["wall_xmin_fx"] / sigma0 for r in rows]  # force on the wall, -x
            on = [ti for ti, fi in zip(t, f) if fi > 0.5]
            mid = [fi for ti, fi in zip(t, f) if 0.2 * T < ti < 0.8 * T]
            rebound = rows[-1]["momentum_x"] / 7850.0
            de = (rows[-1]["total"] - rows[0]["total"]) / rows[0]["total"]
            print(f"| {shape} | {transfer} | {sum(mid) / len(mid):.4f} | "
                  f"{(on[-1] - on[0]) / T:.4f} | {rebound:.4f} | {de:+.4%} |")
            if transfer == "flip":
                ax.plot([x / T for x in t], f, label=shape)
    ax.plot([0, 0, 1, 1, 1.5], [0, 1, 1, 0, 0], "k--", lw=1, label="exact")
    ax.set_xlabel("t / (2L/c)")
    ax.set_ylabel("wall stress / (rho c v0)")
    ax.set_title("Steel bar against a rigid wall on a grid line (MUSL/FLIP, h = L/100)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(IMG, "bar_impact_1d.png"), dpi=110)


def drop(work):
    s = load("block_drop_3d.json")
    rows, summary = run(s, work)
    t = [r["time"] for r in rows]
    fig, ax = plt.subplots(figsize=(8, 4))
    for key in ["kinetic", "strain", "gravity", "total"]:
        ax.plot(t, [r[key] for r in rows], label=key)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("energy (J)")
    ax.set_title("Neo-Hookean block dropped on a frictional floor (3D, MUSL/APIC, B-spline)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(IMG, "block_drop_3d.png"), dpi=110)
    e0 = rows[0]["total"]
    print(f"\n3D drop: {summary['particles']} particles, {summary['steps']} steps, "
          f"{summary['wall_clock_seconds']:.2f} s; total energy at t = 0.2 s: "
          f"{min(rows, key=lambda r: abs(r['time'] - 0.2))['total'] / e0 - 1:+.2e} relative")


if __name__ == "__main__":
    os.makedirs(IMG, exist_ok=True)
    with tempfile.TemporaryDirectory() as work:
        vibration(work)
        impact(work)
        drop(work)
