#!/usr/bin/python3
"""Validation of the debris materials against experiments (docs/validation.md).

Runs build/bin/mpm on generated 2D (plane strain) scenes in a temporary folder, prints the
markdown tables of docs/validation.md, writes docs/validation.json and docs/img/validation_*.png.
Needs python3-matplotlib and python3-h5py (Debian). From anywhere, after a release build:

    /usr/bin/python3 docs/scripts/validation_study.py [collapse] [collapse-study] [collapse-depth]
                                                      [dambreak] [impact]

(1) Granular column collapse (Drucker-Prager, phi = 30 deg, on a rough floor with a smooth back
    wall) for aspect ratios a = H0/L0 from 0.5 to 6: normalised run-out (L_inf - L0)/L0 against
    Lube et al. (2005), 1.2 a for a < 1.8 and 1.9 a^(2/3) for a > 2.8.
(2) Dam break (weakly compressible water, square column of side a): surge front against Martin &
    Moyce (1952) over T = t sqrt(2 g / a) up to 3.
(3) Impact of a granular stream on a wall (box-face wall): alpha and k implied by
    F = alpha rho v^2 d w + 0.5 k rho g H^2 w.
"""
import csv
import json
import math
import os
import subprocess
import sys
import tempfile

import h5py
import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
MPM = os.environ.get("MPM", os.path.join(ROOT, "build", "bin", "mpm"))
IMG = os.path.join(ROOT, "docs", "img")
G = 9.81


def run(scene, name, work):
    path = os.path.join(work, name + ".json")
    with open(path, "w") as f:
        json.dump(scene, f)
    out = os.path.join(work, name)
    r = subprocess.run([MPM, "run", path, "-o", out, "--overwrite", "-q"], capture_output=True,
                       text=True)
    if r.returncode != 0:
        print(f"{name}: exit {r.returncode}: {r.stderr.strip()}", file=sys.stderr)
    with open(os.path.join(out, "summary.json")) as f:
        summary = json.load(f)
    return out, summary


def frames(out):
    with h5py.File(os.path.join(out, "particles.h5"), "r") as h5:
        for name in sorted(h5["frames"].keys()):
            g = h5["frames"][name]
            yield float(g.attrs["time"]), np.array(g["position"]), np.array(g["volume"])


def front(x, h):
    """Front of a deposit: the furthest particle that still has material within 2h behind it
    (a lone particle thrown ahead is not the front)."""
    order = np.argsort(x)
    xs = x[order]
    for i in range(len(xs) - 1, 0, -1):
        if np.count_nonzero(xs[max(0, i - 20):i] > xs[i] - 2.0 * h) >= 3:
            return xs[i]
    return xs[-1]


def scene_2d(name, grid_max, h, material, body, walls, end, interval, history, cfl=0.5):
    """A plane-strain scene on [0, grid_max] with quadratic B-splines, MUSL, APIC, gravity."""
    return {
        "name": name,
        "dimension": 2,
        "grid": {"min": [0.0, 0.0], "max": grid_max, "spacing": h},
        "shape_function": "bspline2",
        "scheme": {"update": "musl", "transfer": "apic"},
        "gravity": [0.0, -G],
        "materials": [material],
        "bodies": [dict(body, material=material["name"], particles_per_cell=2)],
        "walls": walls,
        "time": {"end": end, "cfl": cfl},
        "output": {"interval": interval, "history_interval": history},
    }


def granular(name, rho, E):
    """Drucker-Prager, nu 0.3, phi 30 degrees, no dilatancy, no cohesion."""
    return {"name": name, "model": "drucker_prager", "density": rho, "youngs_modulus": E,
            "poisson_ratio": 0.3, "friction_angle": 30.0, "dilatancy_angle": 0.0,
            "cohesion": 0.0}


def box_wall(face, mu=0.0):
    wall = {"face": face, "condition": "friction" if mu > 0 else "slip", "separable": True}
    if mu > 0:
        wall["mu"] = mu
    return wall


# --- (1) granular column collapse --------------------------------------------------------------

RATIOS = [0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0]
L0 = 0.1  # column width (m)


def lube(a):
    if a < 1.8:
        return 1.2 * a
    if a > 2.8:
        return 1.9 * a ** (2.0 / 3.0)
    return None  # transition: Lube et al. give no fit between 1.8 and 2.8


def collapse_scene(a, h):
    H0 = a * L0
    reach = L0 * (1.0 + 2.5 * max(1.2 * a, 1.9 * a ** (2.0 / 3.0)))
    return scene_2d(
        f"collapse_a{a}", [h * math.ceil(reach / h), h * math.ceil(1.1 * H0 / h + 4)], h,
        granular("sand", 1600.0, 2.0e6),
        {"name": "column", "shape": {"type": "box", "min": [0.0, 0.0], "max": [L0, H0]}},
        [box_wall("xmin"), box_wall("ymin", 0.5)], 4.0 * math.sqrt(H0 / G) + 0.3, 0.05, 0.01)


def collapse(work):
    h = L0 / 16
    rows = []
    for a in RATIOS:
        out, summary = run(collapse_scene(a, h), f"collapse_{a}", work)
        history = list(frames(out))
        t, x, vol = history[-1]
        L_inf = front(x[:, 0], h)
        run_out = (L_inf - L0) / L0
        ref = lube(a)
        rows.append({"a": a, "runout": run_out, "lube": ref,
                     "error": None if ref is None else run_out / ref - 1.0,
                     "height": float(x[:, 1].max()) / (a * L0), "seconds":
                         summary["wall_clock_seconds"], "status": summary["status"]})
        print(f"a = {a}: (L-L0)/L0 = {run_out:.3f}, Lube {ref}, {summary['status']}",
              file=sys.stderr)
    print("| a = H0/L0 | (L_inf - L0)/L0, MPM | Lube et al. (2005) | error | final height / H0 |")
    print("|---|---|---|---|---|")
    for r in rows:
        ref = "transition (no fit)" if r["lube"] is None else f"{r['lube']:.3f}"
        err = "" if r["error"] is None else f"{100 * r['error']:+.1f}%"
        print(f"| {r['a']} | {r['runout']:.3f} | {ref} | {err} | {r['height']:.3f} |")
    a_fit = np.linspace(0.3, 7.0, 200)
    fig, ax = plt.subplots(figsize=(6, 4.2))
    ax.plot(a_fit[a_fit < 1.8], 1.2 * a_fit[a_fit < 1.8], "k-", label="Lube et al.: 1.2 a")
    ax.plot(a_fit[a_fit > 2.8], 1.9 * a_fit[a_fit > 2.8] ** (2 / 3), "k--",
            label="Lube et al.: 1.9 a^(2/3)")
    ax.plot([r["a"] for r in rows], [r["runout"] for r in rows], "o", label="MPM (DP, phi 30)")
    ax.set_xlabel("aspect ratio a = H0 / L0")
    ax.set_ylabel("(L_inf - L0) / L0")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(IMG, "validation_collapse.png"), dpi=120)
    plt.close(fig)
    return rows


# What moves the collapse: spacing and model, at a = 1 and a = 3 (`collapse-study`, ~6 min).
DAVIS_PHI = math.degrees(math.asin(math.tan(math.radians(30.0))))  # sin(phi) = tan 30


def mu_i_glass_beads(name):
    """mu(I) with the glass beads of Jop, Forterre & Pouliquen (2006)."""
    return {"name": name, "model": "mu_i", "density": 1600.0, "youngs_modulus": 2.0e6,
            "poisson_ratio": 0.3, "mu_s": math.tan(math.radians(20.9)),
            "mu_2": math.tan(math.radians(32.76)), "I_0": 0.279, "grain_diameter": 5e-4,
            "grain_density": 2500.0}


def collapse_study(work):
    models = [("Drucker-Prager, phi 30", granular("sand", 1600.0, 2.0e6)),
              (f"Drucker-Prager, phi {DAVIS_PHI:.1f} (sin phi = tan 30)",
               dict(granular("sand", 1600.0, 2.0e6), friction_angle=DAVIS_PHI)),
              ("mu(I), glass beads of Jop et al.", mu_i_glass_beads("sand"))]
    rows = []
    for a, cells in [(1.0, 8), (1.0, 16), (1.0, 32), (3.0, 8), (3.0, 16)]:
        h = L0 / cells
        for label, material in models:
            scene = collapse_scene(a, h)
            scene["materials"] = [material]
            out, summary = run(scene, f"study_{a}_{cells}_{len(rows)}", work)
            t, x, vol = list(frames(out))[-1]
            run_out = (front(x[:, 0], h) - L0) / L0
            rows.append({"a": a, "cells": cells, "model": label, "runout": run_out,
                         "centroid": summary["flow"]["centroid_travel"] / L0,
                         "height": float(x[:, 1].max()) / (a * L0), "lube": lube(a),
                         "status": summary["status"]})
            print(f"a = {a}, L0/h = {cells}, {label}: {run_out:.3f}", file=sys.stderr)
    print("| a | L0 / h | model | (L_inf - L0)/L0 | Lube et al. | centroid travel / L0 | "
          "final height / H0 |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['a']:g} | {r['cells']} | {r['model']} | {r['runout']:.3f} | "
              f"{r['lube']:.2f} | {r['centroid']:.3f} | {r['height']:.3f} |")
    return rows


# The front at a deposit depth (`collapse-depth`, ~3 min): the particle front above grows by
# about 0.4 L0 per halving of h at a = 1 while the bulk converges; the front where the deposit is
# at least delta deep converges once delta is resolved. Same measure as summary.json's
# flow.runout_at_depth (run.cpp, deposit_depth()): the placement volume (first frame) of the
# particles within 2 h horizontally, over the segment's length 4 h.
DEPTHS = [0.002, 0.005, 0.01, 0.02]


def deposit_depth(x, v0, radius):
    order = np.argsort(x)
    xs = x[order]
    cumulative = np.concatenate([[0.0], np.cumsum(v0[order])])
    lo = np.searchsorted(xs, xs - radius, "left")
    hi = np.searchsorted(xs, xs + radius, "right")
    depth = np.empty_like(x)
    depth[order] = (cumulative[hi] - cumulative[lo]) / (2.0 * radius)
    return depth


def collapse_depth(work):
    rows = []
    for a, cells in [(1.0, 8), (1.0, 16), (1.0, 32), (1.0, 64), (3.0, 8), (3.0, 16), (3.0, 32)]:
        h = L0 / cells
        out, summary = run(collapse_scene(a, h), f"depth_{a}_{cells}", work)
        history = list(frames(out))
        x, v0 = history[-1][1][:, 0], history[0][2]
        depth = deposit_depth(x, v0, 2.0 * h)
        fronts = [float((x[depth >= d].max() - L0) / L0) for d in DEPTHS]
        rows.append({"a": a, "cells": cells, "particle_front": (front(x, h) - L0) / L0,
                     "depth_fronts": fronts, "lube": lube(a),
                     "centroid": summary["flow"]["centroid_travel"] / L0,
                     "status": summary["status"]})
        print(f"a = {a}, L0/h = {cells}: {rows[-1]['particle_front']:.3f}, "
              + ", ".join(f"{f:.3f}" for f in fronts), file=sys.stderr)
    heads = " | ".join(f"depth >= {1000 * d:g} mm" for d in DEPTHS)
    print(f"| a | L0 / h | particle front | {heads} | Lube et al. | centroid travel / L0 |")
    print("|---|---|---|" + "---|" * len(DEPTHS) + "---|---|")
    for r in rows:
        cells = " | ".join(f"{f:.3f}" for f in r["depth_fronts"])
        print(f"| {r['a']:g} | {r['cells']} | {r['particle_front']:.3f} | {cells} | "
              f"{r['lube']:.2f} | {r['centroid']:.3f} |")
    return rows


# --- (2) dam break ------------------------------------------------------------------------------

def dambreak(work):
    a, h = 0.2, 0.2 / 32
    water = {"name": "water", "model": "newtonian_fluid", "density": 1000.0,
             "speed_of_sound": 25.0, "viscosity": 1.0e-3}
    scene = scene_2d(
        "dambreak", [1.2, 0.3], h, water,
        {"name": "column", "shape": {"type": "box", "min": [0.0, 0.0], "max": [a, a]}},
        [box_wall(f) for f in ("xmin", "ymin", "xmax")], 3.2 / math.sqrt(2 * G / a),
        0.1 / math.sqrt(2 * G / a), 0.01, cfl=0.4)
    out, summary = run(scene, "dambreak", work)
    scale = math.sqrt(2 * G / a)
    T, Z = [], []
    for t, x, vol in frames(out):
        T.append(t * scale)
        Z.append(front(x[:, 0], h) / a)
    # Martin & Moyce (1952), square column (n^2 = 2), read from their figure: Z = x/a against
    # T = t sqrt(2g/a).
    mm_T = [0.41, 0.84, 1.19, 1.43, 1.63, 1.83, 1.98, 2.20, 2.32, 2.51, 2.65, 2.83, 2.98]
    mm_Z = [1.11, 1.22, 1.44, 1.67, 1.89, 2.11, 2.33, 2.56, 2.78, 3.00, 3.22, 3.44, 3.67]
    model = np.interp(mm_T, T, Z)
    print("\n| T = t sqrt(2g/a) | front x/a, Martin & Moyce | MPM | error |")
    print("|---|---|---|---|")
    rows = []
    for tt, zz, mm in zip(mm_T, mm_Z, model):
        rows.append({"T": tt, "experiment": zz, "mpm": float(mm), "error": float(mm / zz - 1)})
        print(f"| {tt:.2f} | {zz:.2f} | {mm:.2f} | {100 * (mm / zz - 1):+.1f}% |")
    fig, ax = plt.subplots(figsize=(6, 4.2))
    ax.plot(mm_T, mm_Z, "ks", label="Martin & Moyce (1952)")
    ax.plot(T, Z, "-", label="MPM (Tait water, c0 = 25 m/s)")
    ax.set_xlim(0, 3.2)
    ax.set_xlabel("T = t sqrt(2 g / a)")
    ax.set_ylabel("front position x / a")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(os.path.join(IMG, "validation_dambreak.png"), dpi=120)
    plt.close(fig)
    return {"rows": rows, "seconds": summary["wall_clock_seconds"], "status": summary["status"]}


# --- (3) impact on a wall ----------------------------------------------------------------------

GAP, MU_FLOOR = 0.05, 0.4  # stream starts GAP from the wall on a floor with friction MU_FLOOR


def impact_scene(v0, depth, length, h, wall_x):
    # Floor and wall on box faces (slip): the horizontal force on the xmax face is the wall's.
    return scene_2d(
        f"impact_v{v0}", [wall_x, 2.5], h, granular("debris", 1800.0, 5.0e6),
        {"name": "flow", "velocity": [v0, 0.0],
         "shape": {"type": "box", "min": [wall_x - GAP - length, 0.0],
                   "max": [wall_x - GAP, depth]}},
        [box_wall("ymin", MU_FLOOR), box_wall("xmin"), box_wall("xmax"), box_wall("ymax")],
        2.5, 0.05, 0.005)


def impact(work):
    """A granular stream of depth d sliding at v0 on a rough floor (mu 0.4) runs into a vertical
    wall GAP ahead: it meets the wall at v = sqrt(v0^2 - 2 mu g GAP) (a block sliding under
    Coulomb friction). Peak force (5 ms average) and the final static force per metre of width
    give alpha = F_peak / (rho v^2 d) and k = F_static / (0.5 rho g H^2), H the deposit height
    at the wall."""
    depth, length, h, wall_x, rho = 0.1, 1.5, 0.0125, 2.1, 1800.0
    rows = []
    for v0 in [1.5, 2.0, 3.0, 4.0]:
        out, summary = run(impact_scene(v0, depth, length, h, wall_x), f"impact_{v0}", work)
        with open(os.path.join(out, "history.csv")) as f:
            hist = list(csv.DictReader(f))
        t = np.array([float(r["time"]) for r in hist])
        fx = np.array([float(r["wall_xmax_fx"]) for r in hist])
        peak = float(fx.max())
        # The surge: from first contact for as long as the stream takes to arrive (length / v).
        v = math.sqrt(v0 ** 2 - 2.0 * MU_FLOOR * G * GAP)
        start = t[np.argmax(fx > 0.01 * peak)]
        surge = float(np.mean(fx[(t >= start) & (t < start + length / v)]))
        static = float(np.mean(fx[t > t[-1] - 0.3]))
        _, x, _ = list(frames(out))[-1]
        near = x[:, 0] > wall_x - 4 * h
        H = float(x[near, 1].max()) + 0.5 * h / 2 if np.any(near) else float("nan")
        fr = v / math.sqrt(G * depth)
        rows.append({"v0": v0, "v": v, "froude": fr, "peak": peak, "static": static, "H": H,
                     "surge": surge, "alpha_surge": surge / (rho * v ** 2 * depth),
                     "alpha": peak / (rho * v ** 2 * depth),
                     "k": static / (0.5 * rho * G * H ** 2), "status": summary["status"]})
        print(f"v0 {v0}: peak {peak:.1f} N/m, static {static:.1f} N/m, H {H:.3f}, "
              f"{summary['status']}", file=sys.stderr)
    print("\n| v0 (m/s) | v at the wall | Froude | peak F, 5 ms (N/m) | alpha (peak) | mean F over "
          "the surge (N/m) | alpha (surge) | static F (N/m) | deposit H (m) | k | run |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['v0']} | {r['v']:.2f} | {r['froude']:.2f} | {r['peak']:.0f} | "
              f"{r['alpha']:.1f} | {r['surge']:.0f} | {r['alpha_surge']:.2f} | "
              f"{r['static']:.0f} | {r['H']:.3f} | {r['k']:.2f} | {r['status']} |")
    return rows


def main():
    which = sys.argv[1:] or ["collapse", "dambreak", "impact"]
    results = {}
    path = os.path.join(ROOT, "docs", "validation.json")
    if os.path.exists(path):
        with open(path) as f:
            results = json.load(f)
    with tempfile.TemporaryDirectory() as work:
        if "collapse" in which:
            results["collapse"] = collapse(work)
        if "collapse-study" in which:
            results["collapse_study"] = collapse_study(work)
        if "collapse-depth" in which:
            results["collapse_depth"] = collapse_depth(work)
        if "dambreak" in which:
            results["dambreak"] = dambreak(work)
        if "impact" in which:
            results["impact"] = impact(work)
    with open(path, "w") as f:
        json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
