#!/usr/bin/python3
"""Blending dual-grid study behind docs/blending.md.

Runs build/bin/mpm on generated scenes (one at a time) in a temporary folder, prints the markdown
tables of docs/blending.md and writes docs/img/blending_*.png. Needs python3-matplotlib
(Debian); run from anywhere after a release build:

    /usr/bin/python3 docs/scripts/blending_study.py            # about 4 minutes on 2 cores

Studies: (1) 1D steel bar against a dual-grid wall swept across one grid cell, standard MPM vs
one-way vs mortar, with diagnostics that locate the problematic configurations; (2) 2D block on
an incline; (3) 2D particle and block thrown at a straight wall at 0-90 degrees.
"""
import csv
import json
import math
import os
import random
import subprocess
import sys
import tempfile

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
MPM = os.environ.get("MPM", os.path.join(ROOT, "build", "bin", "mpm"))
IMG = os.path.join(ROOT, "docs", "img")
WORK = None  # temporary folder, set in main

# 1D bar: steel, E = 200 GPa, rho = 7850, L = 1 m, v0 = 1 m/s, h = 1 cm, 2 particles per cell.
E, RHO, L, V0, H = 2.0e11, 7850.0, 1.0, 1.0, 0.01
C = math.sqrt(E / RHO)
T = 2.0 * L / C  # exact contact duration
S0 = RHO * C * V0  # exact wall stress
X0 = 0.2  # grid line the sweep starts from
OFFSETS = [k / 20.0 for k in range(20)]
THICKNESS = [0.5, 1.0, 1.5, 2.0]
KERNELS = [("linear", "flip"), ("linear", "apic"), ("bspline2", "flip"), ("bspline2", "apic")]


def log(*args):
    print(*args, file=sys.stderr, flush=True)


def run(scene):
    """Runs one scene; returns (history rows, None) or (None, the error line)."""
    path = os.path.join(WORK, "scene.json")
    out = os.path.join(WORK, "out")
    with open(path, "w") as f:
        json.dump(scene, f)
    r = subprocess.run([MPM, "run", path, "-o", out, "--overwrite", "-q"], capture_output=True,
                       text=True)
    if r.returncode != 0:
        lines = [x for x in r.stderr.strip().splitlines() if x.strip()]
        return None, lines[-1] if lines else f"exit {r.returncode}"
    with open(os.path.join(out, "history.csv")) as f:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)], None


def fault_kind(err):
    for key in ["inverted", "not finite", "left the grid"]:
        if key in err:
            return key
    return "fault"


# ---------------------------------------------------------------------------------------------
# Study 1: 1D bar
# ---------------------------------------------------------------------------------------------

def bar_scene(offset, method, t=1.0, shape="linear", transfer="flip", update="musl", blend=1.0,
              layers=1, separable=True, cfl=0.5, threshold=None):
    """Bar [xw, xw + 1] moving at -v0 against a wall at xw = X0 + offset h. 'standard' is the
    box wall on the grid line X0 (the grid starts there). The segment body is seeded on the
    grid's sub-cell lattice (h/4 and 3h/4 in every cell), so the first particle sits delta =
    (distance to the next lattice point) in front of the wall: see first_particle_gap()."""
    s = {
        "dimension": 1,
        "grid": {"min": [0.0], "max": [1.5], "spacing": H},
        "shape_function": shape,
        "scheme": {"update": update, "transfer": transfer},
        "materials": [{"name": "steel", "model": "linear_elastic", "density": RHO,
                       "youngs_modulus": E}],
        "bodies": [{"name": "bar", "material": "steel",
                    "shape": {"type": "segment", "min": [X0], "max": [X0 + L]},
                    "particles_per_cell": 2, "velocity": [-V0]}],
        "time": {"end": 1.5 * T, "cfl": cfl},
        "output": {"interval": 1.0, "history_interval": 0},
    }
    if transfer == "flip":
        s["scheme"]["flip_blend"] = blend
    if threshold is not None:
        s["scheme"]["coupling_mass_threshold"] = threshold
    if method == "standard":
        s["grid"]["min"] = [X0]
        s["walls"] = [{"face": "xmin", "condition": "slip", "separable": separable}]
    else:
        xw = X0 + offset * H
        s["bodies"][0]["shape"] = {"type": "segment", "min": [xw], "max": [xw + L]}
        s["walls"] = [{"name": "wall", "surface": {"type": "point", "position": xw, "side": 1},
                       "method": method, "condition": "slip", "separable": separable,
                       "thickness": t * H, "layers": layers}]
    return s


def first_particle_gap(offset):
    """Distance (in h) from the wall to the first particle for a wall at X0 + offset h."""
    return min(q for q in (0.25, 0.75, 1.25) if q >= offset - 1e-12) - offset


def bar_metrics(rows):
    """plateau: reported wall stress / rho c v0, mean over 0.2-0.8 of 2L/c; bar: the same from
    the bar's momentum (the force the bar actually receives); contact: time the reported stress
    is above half of rho c v0, / (2L/c); rebound: final v_cm / v0; de: energy change;
    impulse: reported wall impulse / bar momentum change."""
    key = [k for k in rows[0] if k.startswith("wall_")][0]
    t = [r["time"] for r in rows]
    f = [-r[key] / S0 for r in rows]  # force on the wall (-x) = stress on the bar
    p = [r["momentum_x"] for r in rows]
    on = [ti for ti, fi in zip(t, f) if fi > 0.5]
    num = den = 0.0
    for i in range(1, len(t)):
        if 0.2 * T < t[i] <= 0.8 * T:
            num += f[i] * (t[i] - t[i - 1])
            den += t[i] - t[i - 1]

    def at(x):
        return min(range(len(t)), key=lambda k: abs(t[k] - x))

    i1, i2 = at(0.2 * T), at(0.8 * T)
    impulse = sum(-r[key] * r["dt"] for r in rows)
    dp = p[-1] - p[0]
    return {
        "plateau": num / den,
        "bar": (p[i2] - p[i1]) / (t[i2] - t[i1]) / S0,
        "contact": (on[-1] - on[0]) / T if on else 0.0,
        "rebound": p[-1] / (RHO * L * V0),
        "de": (rows[-1]["total"] - rows[0]["total"]) / rows[0]["total"],
        "impulse": impulse / dp if dp else float("nan"),
        "dp": dp / (RHO * L * V0),
        "wall_impulse": impulse / (RHO * L * V0),
    }


def bar(offset, method, **kw):
    rows, err = run(bar_scene(offset, method, **kw))
    return (bar_metrics(rows), None) if rows else (None, err)


def sweep(method, **kw):
    return [bar(off, method, **kw) for off in OFFSETS]


def summarize(results, key="plateau"):
    ok = [(off, m) for off, (m, _) in zip(OFFSETS, results) if m]
    faults = [e for m, e in results if not m]
    if not ok:
        return None, faults
    err = [(abs(m[key] - 1.0), off) for off, m in ok]
    worst = max(err)
    return {
        "mean": sum(e for e, _ in err) / len(err),
        "max": worst[0],
        "worst": worst[1],
        "bad": sum(1 for e, _ in err if e > 0.05) + len(faults),
        "contact": (min(m["contact"] for _, m in ok), max(m["contact"] for _, m in ok)),
        "rebound": (min(m["rebound"] for _, m in ok), max(m["rebound"] for _, m in ok)),
        "de": (min(m["de"] for _, m in ok), max(m["de"] for _, m in ok)),
        "bar_max": max(abs(m["bar"] - 1.0) for _, m in ok),
    }, faults


def rng_fmt(a, fmt="{:.3f}"):
    return (fmt.format(a[0]) + " .. " + fmt.format(a[1])) if a[0] != a[1] else fmt.format(a[0])


def pct(x):
    """Relative change; past +1000% as the factor E/E0."""
    return f"{100 * x:+.1f}%" if abs(x) < 10 else f"x{1 + x:.2g}"


def study_bar():
    # -- Standard MPM baselines ---------------------------------------------------------------
    print("\n### 1D bar: standard MPM (box wall on a grid line)\n")
    print("| kernel | transfer | plateau / rho c v0 | contact / (2L/c) | rebound / v0 | energy change |")
    print("|---|---|---|---|---|---|")
    standard = {}
    for shape, transfer in KERNELS:
        m, err = bar(0.0, "standard", shape=shape, transfer=transfer)
        standard[(shape, transfer)] = m
        if m:
            print(f"| {shape} | {transfer} | {m['plateau']:.4f} | {m['contact']:.4f} | "
                  f"{m['rebound']:.4f} | {pct(m['de'])} |")
        else:
            print(f"| {shape} | {transfer} | numerical fault ({fault_kind(err)}) | | | |")

    # -- Sweep: one-way and mortar, 20 offsets x 4 thicknesses x 4 kernel/transfer ------------
    log("1D sweep ...")
    data = {}
    for shape, transfer in KERNELS:
        for t in THICKNESS:
            for method in ["mortar", "one-way"]:
                data[(shape, transfer, t, method)] = sweep(method, t=t, shape=shape,
                                                           transfer=transfer)
    print("\n### 1D bar: wall swept across one cell (20 offsets), MUSL\n")
    print("Plateau error = |plateau / rho c v0 - 1| from the stress the wall reports; 'bar-side' "
          "is the same from the bar's momentum. Ranges are over the 20 offsets; 'bad' counts "
          "offsets with a plateau error above 5% or a numerical fault.\n")
    print("| kernel | transfer | t / h | method | plateau error mean / max (worst offset) | "
          "bar-side max | contact / (2L/c) | rebound / v0 | energy change | bad |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for shape, transfer in KERNELS:
        for t in THICKNESS:
            for method in ["mortar", "one-way"]:
                s, faults = summarize(data[(shape, transfer, t, method)])
                if s is None:
                    print(f"| {shape} | {transfer} | {t} | {method} | numerical fault at all 20 "
                          f"offsets ({fault_kind(faults[0])}) | | | | | 20 |")
                    continue
                print(f"| {shape} | {transfer} | {t} | {method} | {s['mean']:.4f} / "
                      f"{s['max']:.4f} ({s['worst']:.2f} h) | {s['bar_max']:.4f} | "
                      f"{rng_fmt(s['contact'])} | {rng_fmt(s['rebound'])} | "
                      f"{pct(s['de'][0])} .. {pct(s['de'][1])} | {s['bad']} |")

    # -- Per-offset plateau, mortar ------------------------------------------------------------
    print("\n### Mortar plateau / rho c v0 at every offset (MUSL)\n")
    print("delta = distance from the wall to the first particle (the body is seeded on the grid's "
          "sub-cell lattice). 'fault' = numerical fault.\n")
    cols = [(s, tr, t) for s, tr in [("linear", "flip"), ("bspline2", "flip"), ("bspline2", "apic")]
            for t in THICKNESS]
    print("| offset / h | delta / h | " + " | ".join(f"{s} {tr} t={t}h" for s, tr, t in cols) + " |")
    print("|---|---|" + "---|" * len(cols))
    for i, off in enumerate(OFFSETS):
        cells = []
        for s, tr, t in cols:
            m, _ = data[(s, tr, t, "mortar")][i]
            cells.append(f"{m['plateau']:.3f}" if m else "fault")
        print(f"| {off:.2f} | {first_particle_gap(off):.2f} | " + " | ".join(cells) + " |")

    # -- Plot: plateau error vs offset --------------------------------------------------------
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5), sharex=True, sharey=True)
    styles = [("linear", "flip", "C0"), ("bspline2", "flip", "C1"), ("bspline2", "apic", "C2")]
    for ax, t in zip(axes.flat, THICKNESS):
        for shape, transfer, colour in styles:
            for method, ls, mk in [("mortar", "-", "o"), ("one-way", "--", "x")]:
                res = data[(shape, transfer, t, method)]
                xs = [o for o, (m, _) in zip(OFFSETS, res) if m]
                key = "plateau" if method == "mortar" else "bar"
                ys = [m[key] - 1.0 for m, _ in res if m]
                label = f"{method} {shape}/{transfer}" + (" (bar-side)" if method == "one-way" else "")
                ax.plot(xs, ys, ls, color=colour, marker=mk, ms=3, lw=1, label=label)
        res = data[("linear", "flip", t, "one-way")]
        ax.plot([o for o, (m, _) in zip(OFFSETS, res) if m],
                [m["plateau"] - 1.0 for m, _ in res if m], ":", color="C3", marker="x", ms=3,
                lw=1, label="one-way linear/flip (reported by the wall)")
        ax.axhspan(-0.05, 0.05, color="0.85", zorder=0)
        ax.axhline(-1.0, color="k", lw=0.6, ls=":")
        ax.set_yscale("symlog", linthresh=0.01)
        ax.set_title(f"boundary cell t = {t} h")
        ax.grid(True, lw=0.3)
    for ax in axes[1]:
        ax.set_xlabel("wall offset from a grid line / h")
    for ax in axes[:, 0]:
        ax.set_ylabel("plateau / (rho c v0) - 1")
    axes[0, 0].legend(fontsize=7, loc="upper right")
    fig.suptitle("1D bar impact, MUSL: plateau error vs wall offset (grey: within 5%; "
                 "-100% = the wall reports no force; symmetric log scale)", fontsize=10)
    fig.tight_layout()
    fig.savefig(os.path.join(IMG, "blending_plateau_offsets.png"), dpi=110)
    plt.close(fig)
    return data, standard


def bar_history(offset, method, **kw):
    rows, err = run(bar_scene(offset, method, **kw))
    if not rows:
        return None
    key = [k for k in rows[0] if k.startswith("wall_")][0]
    t = [r["time"] / T for r in rows]
    f = [-r[key] / S0 for r in rows]
    p = [r["momentum_x"] for r in rows]
    tt = [r["time"] for r in rows]
    # force the bar receives: centred difference of its momentum over +-T/50
    w = T / 50
    g, j0, j1 = [], 0, 0
    for i in range(len(tt)):
        while tt[j0] < tt[i] - w:
            j0 += 1
        while j1 < len(tt) - 1 and tt[j1 + 1] <= tt[i] + w:
            j1 += 1
        g.append((p[j1] - p[j0]) / (tt[j1] - tt[j0]) / S0 if tt[j1] > tt[j0] else 0.0)
    e = [r["total"] / rows[0]["total"] for r in rows]
    return t, f, g, e


def study_bar_diagnostics(data):
    # -- One-way: who receives the impulse -----------------------------------------------------
    print("\n### One-way: reported wall impulse against the bar's momentum change "
          "(offset 0.5 h, linear, FLIP)\n")
    print("Both in units of rho L v0. Exact: 2 (separable wall, full rebound); for a bonded "
          "(non-separable) wall the bar's momentum change over 1.5 (2L/c) is about 1.\n")
    print("| wall | t / h | method | wall impulse | bar momentum change | layer mass / bar mass | "
          "plateau (reported) | plateau (bar-side) | energy change |")
    print("|---|---|---|---|---|---|---|---|---|")
    for sep in [True, False]:
        for t in [0.5, 1.0, 2.0]:
            for method in ["one-way", "mortar"]:
                m, err = bar(0.5, method, t=t, separable=sep)
                if not m:
                    print(f"| {'separable' if sep else 'bonded'} | {t} | {method} | fault | | | | | |")
                    continue
                print(f"| {'separable' if sep else 'bonded'} | {t} | {method} | "
                      f"{m['wall_impulse']:.4f} | {m['dp']:.4f} | {t * H / L:.3f} | "
                      f"{m['plateau']:.4f} | {m['bar']:.4f} | {pct(m['de'])} |")

    # -- Mortar: what the thin-cell failure depends on ----------------------------------------
    log("diagnostics ...")
    print("\n### Mortar: what the problematic configurations depend on (20 offsets each)\n")
    print("| case | kernel | update | transfer | t / h | layers (cell size) | plateau error max "
          "(worst offset) | bad offsets | energy change |")
    print("|---|---|---|---|---|---|---|---|---|")
    cases = [
        ("thin cell, linear", dict(shape="linear", transfer="flip", t=0.5)),
        ("thin cell, linear", dict(shape="linear", transfer="flip", t=0.5, blend=0.0)),
        ("thin cell, linear", dict(shape="linear", transfer="flip", t=0.5, update="usl")),
        ("thin cell, linear", dict(shape="linear", transfer="apic", t=0.5, update="usl")),
        ("B-spline, t = h", dict(shape="bspline2", transfer="flip", t=1.0)),
        ("B-spline, t = h", dict(shape="bspline2", transfer="flip", t=1.0, blend=0.0)),
        ("B-spline, t = h, coupling threshold 0.1",
         dict(shape="bspline2", transfer="flip", t=1.0, threshold=0.1)),
        ("B-spline, t = h, coupling threshold 0.5",
         dict(shape="bspline2", transfer="apic", t=1.0, threshold=0.5)),
        ("B-spline, t = h", dict(shape="bspline2", transfer="flip", t=1.0, update="usl")),
        ("B-spline, t = h", dict(shape="bspline2", transfer="apic", t=1.0, update="usl")),
        ("B-spline, t = h/2", dict(shape="bspline2", transfer="apic", t=0.5, update="usl")),
        ("subdivided layer", dict(shape="linear", transfer="flip", t=1.0, layers=2)),
        ("subdivided layer", dict(shape="linear", transfer="flip", t=2.0, layers=4)),
        ("subdivided layer", dict(shape="linear", transfer="flip", t=2.0, layers=2)),
        ("subdivided layer", dict(shape="bspline2", transfer="flip", t=2.0, layers=2)),
        ("subdivided layer", dict(shape="bspline2", transfer="flip", t=3.0, layers=2)),
    ]
    for name, kw in cases:
        res = sweep("mortar", **kw)
        s, faults = summarize(res)
        tr = kw["transfer"]
        if tr == "flip":
            tr = "PIC" if kw.get("blend", 1.0) == 0.0 else "FLIP"
        else:
            tr = "APIC"
        layers = kw.get("layers", 1)
        cell = f"{layers} ({kw['t'] / layers:g} h)"
        update = kw.get("update", "musl").upper()
        head = f"| {name} | {kw['shape']} | {update} | {tr} | {kw['t']} | {cell} | "
        if s is None:
            print(head + "all fault | 20 | |")
            continue
        fault_note = f" ({len(faults)} faults)" if faults else ""
        print(head +
              f"{s['max']:.4f} ({s['worst']:.2f} h) | {s['bad']}{fault_note} | "
              f"{pct(s['de'][0])} .. {pct(s['de'][1])} |")

    # -- Time step ------------------------------------------------------------------------------
    print("\n### Mortar, linear, FLIP, t = h/2, offset 0.5 h: dependence on the time step\n")
    print("| CFL number | transfer | energy change at 0.3 (2L/c) | plateau / rho c v0 | rebound / v0 "
          "| energy change at the end |")
    print("|---|---|---|---|---|---|")
    energy = {}
    for cfl in [0.5, 0.25, 0.1]:
        for blend in [1.0, 0.0]:
            rows, err = run(bar_scene(0.5, "mortar", t=0.5, cfl=cfl, blend=blend))
            m = bar_metrics(rows)
            i = min(range(len(rows)), key=lambda k: abs(rows[k]["time"] - 0.3 * T))
            e03 = rows[i]["total"] / rows[0]["total"] - 1.0
            if blend == 1.0:
                energy[cfl] = ([r["time"] / T for r in rows],
                               [r["total"] / rows[0]["total"] for r in rows])
            print(f"| {cfl} | {'FLIP' if blend else 'PIC'} | {pct(e03)} | {m['plateau']:.4f} | "
                  f"{m['rebound']:.4f} | {pct(m['de'])} |")

    # -- Plot: histories -------------------------------------------------------------------------
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.4))
    ax = axes[0]
    exact = ([0, 0, 1, 1, 1.5], [0, 1, 1, 0, 0])
    for label, args, kw, colour in [
        ("standard MPM", (0.0, "standard"), {}, "k"),
        ("mortar t = 1.5h, offset 0.5h", (0.5, "mortar"), {"t": 1.5}, "C2"),
        ("mortar t = 0.5h, offset 0.5h", (0.5, "mortar"), {"t": 0.5}, "C3"),
    ]:
        h = bar_history(*args, **kw)
        if h:
            ax.plot(h[0], h[1], color=colour, lw=0.7, label=label + " (per step)")
            if kw.get("t") == 0.5:
                ax.plot(h[0], h[2], color="C1", lw=1.2, label=label + " (-dP/dt of the bar)")
    ax.plot(*exact, "k--", lw=0.8, label="exact")
    ax.set_title("linear, FLIP: wall stress (a problematic thin cell)", fontsize=9)
    ax.set_xlabel("t / (2L/c)")
    ax.set_ylabel("wall stress / (rho c v0)")
    ax.set_ylim(-0.5, 5)
    ax.legend(fontsize=7)
    ax = axes[1]
    h = bar_history(0.5, "one-way", t=1.0)
    ax.plot(h[0], h[1], color="C3", lw=1, label="one-way: stress the wall reports")
    ax.plot(h[0], h[2], color="C1", lw=1, label="one-way: force the bar receives (-dP/dt)")
    h = bar_history(0.5, "one-way", t=1.0, separable=False)
    ax.plot(h[0], h[2], color="C4", lw=1, label="one-way, bonded wall: force on the bar")
    ax.plot(h[0], h[1], color="C5", lw=1, label="one-way, bonded wall: reported")
    ax.plot(*exact, "k--", lw=0.8, label="exact (separable)")
    ax.set_title("one-way, t = h, offset 0.5h (linear, FLIP)", fontsize=9)
    ax.set_xlabel("t / (2L/c)")
    ax.legend(fontsize=7)
    ax = axes[2]
    for cfl, (t, e) in energy.items():
        ax.plot(t, e, lw=1, label=f"mortar t = h/2, MUSL/FLIP, CFL {cfl}")
    h = bar_history(0.5, "mortar", t=0.5, update="usl")
    ax.plot(h[0], h[3], "k", lw=1, label="same, USL/FLIP, CFL 0.5")
    ax.set_title("total energy (linear, offset 0.5h)", fontsize=9)
    ax.set_xlabel("t / (2L/c)")
    ax.set_ylabel("E / E0")
    ax.set_yscale("log")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(IMG, "blending_bar_history.png"), dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------
# Study 2: block on an incline
# ---------------------------------------------------------------------------------------------

def incline_scene(theta, method, mu, shape, transfer, h=0.05, end=0.3):
    th = math.radians(theta)
    d = (math.cos(th), -math.sin(th))  # down the slope
    n = (math.sin(th), math.cos(th))  # out of the slope, into the material
    p0 = (0.15, 1.0 + math.sin(th))
    p1 = (p0[0] + 2.4 * d[0], p0[1] + 2.4 * d[1])
    a, b, s = 0.3, 0.15, 0.45
    c = (p0[0] + s * d[0] + (b / 2 + 1e-6) * n[0], p0[1] + s * d[1] + (b / 2 + 1e-6) * n[1])
    wall = {"name": "incline", "surface": {"type": "polyline", "points": [list(p0), list(p1)]},
            "method": method, "separable": True}
    wall.update({"condition": "friction", "mu": mu} if mu > 0 else {"condition": "slip"})
    scene = {
        "dimension": 2,
        "grid": {"min": [-0.5, -0.5], "max": [3.0, 2.5], "spacing": h},
        "shape_function": shape,
        "scheme": {"update": "musl", "transfer": transfer},
        "gravity": [0.0, -9.81],
        "materials": [{"name": "m", "model": "neo_hookean", "density": 1000.0,
                       "youngs_modulus": 2.0e6, "poisson_ratio": 0.3}],
        "bodies": [{"name": "block", "material": "m",
                    "shape": {"type": "box", "min": [c[0] - a / 2, c[1] - b / 2],
                              "max": [c[0] + a / 2, c[1] + b / 2], "rotation": -theta},
                    "particles_per_cell": 2}],
        "walls": [wall],
        "time": {"end": end, "cfl": 0.4},
        "output": {"interval": 1.0, "history_interval": 0},
    }
    if transfer == "flip":
        scene["scheme"]["flip_blend"] = 1.0
    return scene, d, n, 1000.0 * a * b


def incline(theta, method, mu, shape, transfer):
    scene, d, n, mass = incline_scene(theta, method, mu, shape, transfer)
    rows, err = run(scene)
    if not rows:
        return None
    t = [r["time"] for r in rows]
    v = [(r["momentum_x"] * d[0] + r["momentum_y"] * d[1]) / mass for r in rows]
    disp = sum(0.5 * (v[i] + v[i - 1]) * (t[i] - t[i - 1]) for i in range(1, len(t)))
    th = math.radians(theta)
    acc = 9.81 * (math.sin(th) - mu * math.cos(th)) if math.tan(th) > mu else 0.0
    end = t[-1]
    imp = dur = 0.0
    for i in range(1, len(rows)):
        if t[i] > end / 3:  # after the block has settled on the wall
            fn = -(rows[i]["wall_incline_fx"] * n[0] + rows[i]["wall_incline_fy"] * n[1])
            imp += fn * (t[i] - t[i - 1])
            dur += t[i] - t[i - 1]
    normal = imp / dur / (mass * 9.81 * math.cos(th))
    vn = (rows[-1]["momentum_x"] * n[0] + rows[-1]["momentum_y"] * n[1]) / mass
    return {"disp": disp, "exact": 0.5 * acc * end * end, "normal": normal, "vn": vn}


def study_incline():
    log("incline ...")
    angles = list(range(5, 90, 5))
    combos = [("bspline2", "apic"), ("linear", "flip")]
    res = {}
    for mu in [0.0, 0.3]:
        for shape, transfer in combos:
            for method in ["mortar", "one-way"]:
                for th in angles:
                    res[(mu, shape, method, th)] = incline(th, method, mu, shape, transfer)
    print("\n### 2D block on an incline (t = h, MUSL), displacement after 0.3 s\n")
    print("disp = displacement along the slope / exact 0.5 a t^2, a = g (sin - mu cos) (for mu = 0.3 "
          "below the friction angle 16.7 deg the exact displacement is 0 and the column gives "
          "the displacement in mm). N = time-averaged normal wall force over the last 2/3 of the "
          "run / (m g cos). vn = final velocity normal to the slope (m/s, exact 0).\n")
    for mu in [0.0, 0.3]:
        print(f"\n**mu = {mu}**\n")
        head = []
        for shape, transfer in combos:
            for method in ["mortar", "one-way"]:
                head.append(f"{method} {shape}/{transfer}")
        print("| angle | " + " | ".join(f"{h_} disp / N / vn" for h_ in head) + " |")
        print("|---|" + "---|" * len(head))
        for th in angles:
            cells = []
            for shape, transfer in combos:
                for method in ["mortar", "one-way"]:
                    r = res[(mu, shape, method, th)]
                    if r is None:
                        cells.append("numerical fault")
                    elif r["exact"] > 0:
                        cells.append(f"{r['disp'] / r['exact']:.4f} / {r['normal']:.3f} / "
                                     f"{r['vn']:+.3f}")
                    else:
                        cells.append(f"{1000 * r['disp']:.2f} mm / {r['normal']:.3f} / "
                                     f"{r['vn']:+.3f}")
            print(f"| {th} | " + " | ".join(cells) + " |")
        for shape, transfer in combos:
            ratios = [res[(mu, shape, "mortar", th)]["disp"] / res[(mu, shape, "mortar", th)]["exact"]
                      for th in angles if res[(mu, shape, "mortar", th)]
                      and res[(mu, shape, "mortar", th)]["exact"] > 0]
            normals = [res[(mu, shape, "mortar", th)]["normal"] for th in angles
                       if res[(mu, shape, "mortar", th)]]
            faults = sum(1 for th in angles if res[(mu, shape, "one-way", th)] is None)
            print(f"\nmu = {mu}, {shape}/{transfer}: mortar displacement / exact "
                  f"{min(ratios):.4f} .. {max(ratios):.4f} (spread {max(ratios) - min(ratios):.4f}), "
                  f"normal force / m g cos {min(normals):.3f} .. {max(normals):.3f}; one-way: "
                  f"{faults} of {len(angles)} angles end in a numerical fault.")

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    for mu, ls in [(0.0, "-"), (0.3, "--")]:
        for (shape, transfer), colour in zip(combos, ["C0", "C1"]):
            for method, mk in [("mortar", "o"), ("one-way", "x")]:
                xs, ys, ns = [], [], []
                for th in angles:
                    r = res[(mu, shape, method, th)]
                    if r and r["exact"] > 0:
                        xs.append(th)
                        ys.append(r["disp"] / r["exact"])
                        ns.append(r["normal"])
                lab = f"{method} {shape}/{transfer} mu={mu}"
                col = colour if method == "mortar" else {"C0": "C3", "C1": "C4"}[colour]
                axes[0].plot(xs, ys, ls, marker=mk, color=col, ms=3, lw=1, label=lab)
                if mu == 0.0:
                    axes[1].plot(xs, ns, ls, marker=mk, color=col, ms=3, lw=1, label=lab)
    axes[0].set_ylabel("displacement / exact")
    axes[0].set_ylim(0.0, 2.0)
    axes[1].set_ylabel("mean normal force / (m g cos theta)  (mu = 0)")
    axes[1].set_ylim(0.0, 3.0)
    for ax in axes:
        ax.set_xlabel("incline angle (deg)")
        ax.grid(True, lw=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("Block on an incline, 0.3 s, h = 0.05 m (one-way points missing: numerical fault)",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(os.path.join(IMG, "blending_incline.png"), dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------
# Study 3: thrown at a wall
# ---------------------------------------------------------------------------------------------

def throw_scene(theta, method, kind, rng, h=0.05, vn=1.0, vt=1.0):
    """A single particle (h/2 square, 1 particle) or an elastic block (0.4 x 0.2, nu = 0) 0.05 m
    from a straight slip wall at angle theta, moving at -vn along the normal and vt along it.
    The wall passes through a random point of a cell; the body is offset along it at random."""
    th = math.radians(theta)
    t = (math.cos(th), math.sin(th))
    n = (-math.sin(th), math.cos(th))
    w0 = (rng.uniform(0, h), rng.uniform(0, h))
    along = rng.uniform(-h, h)
    if method == "standard":
        w0, along = (0.0, 0.0), 0.0
    a, b, ppc = (h / 2, h / 2, 1) if kind == "particle" else (0.4, 0.2, 2)
    gap = 0.05
    c = (w0[0] + along * t[0] + (gap + b / 2) * n[0], w0[1] + along * t[1] + (gap + b / 2) * n[1])
    cw = math.sqrt(2.0e6 / 1000.0)
    scene = {
        "dimension": 2,
        "grid": {"min": [-2.0, -2.0], "max": [2.0, 2.0], "spacing": h},
        "shape_function": "bspline2",
        "scheme": {"update": "musl", "transfer": "apic"},
        "materials": [{"name": "m", "model": "neo_hookean", "density": 1000.0,
                       "youngs_modulus": 2.0e6, "poisson_ratio": 0.0}],
        "bodies": [{"name": "b", "material": "m",
                    "shape": {"type": "box", "min": [c[0] - a / 2, c[1] - b / 2],
                              "max": [c[0] + a / 2, c[1] + b / 2], "rotation": theta},
                    "particles_per_cell": ppc,
                    "velocity": [-vn * n[0] + vt * t[0], -vn * n[1] + vt * t[1]]}],
        "time": {"end": gap / vn + 3 * b / cw + 0.02, "cfl": 0.4},
        "output": {"interval": 1.0, "history_interval": 0},
    }
    if method == "standard":
        if theta == 0:
            scene["grid"]["min"] = [-2.0, 0.0]
            scene["walls"] = [{"face": "ymin", "condition": "slip", "separable": True}]
        else:
            scene["grid"]["max"] = [0.0, 2.0]
            scene["walls"] = [{"face": "xmax", "condition": "slip", "separable": True}]
    else:
        pts = [[w0[0] - 1.5 * t[0], w0[1] - 1.5 * t[1]], [w0[0] + 1.5 * t[0], w0[1] + 1.5 * t[1]]]
        scene["walls"] = [{"name": "wall", "surface": {"type": "polyline", "points": pts},
                           "method": method, "condition": "slip", "separable": True}]
    return scene, t, n


def throw(theta, method, kind, rng):
    scene, t, n = throw_scene(theta, method, kind, rng)
    rows, err = run(scene)
    if not rows:
        return None
    p0 = math.hypot(rows[0]["momentum_x"], rows[0]["momentum_y"]) / math.sqrt(2.0)  # mass
    px, py = rows[-1]["momentum_x"], rows[-1]["momentum_y"]
    return {"vn": (px * n[0] + py * n[1]) / p0, "vt": (px * t[0] + py * t[1]) / p0,
            "e": rows[-1]["total"] / rows[0]["total"]}


def study_throw():
    log("throw ...")
    angles = list(range(0, 91, 5))
    rng = random.Random(20100809)
    res = {}
    for kind in ["particle", "block"]:
        for method in ["mortar", "one-way"]:
            for th in angles:
                res[(kind, method, th)] = throw(th, method, kind, rng)
    for th in (0, 90):
        res[("block", "standard", th)] = throw(th, "standard", "block", rng)
        res[("particle", "standard", th)] = throw(th, "standard", "particle", rng)
    print("\n### 2D particle and block thrown at a slip wall (B-spline, APIC, MUSL, t = h)\n")
    print("Approach at 1 m/s normal and 1 m/s tangential. Exact after the impact: tangential "
          "velocity vt = 1 (slip). Single particle: normal velocity vn = 0 (the separable wall "
          "removes the approaching velocity; nothing stores energy). Elastic block (nu = 0): "
          "vn = +1 for a perfectly elastic rebound; E = final / initial total energy.\n")
    print("| angle | particle mortar vn / vt | particle one-way vn / vt | block mortar vn / vt / E | "
          "block one-way vn / vt / E |")
    print("|---|---|---|---|---|")

    def cell(r, energy):
        if r is None:
            return "numerical fault"
        s = f"{r['vn']:+.3f} / {r['vt']:.3f}"
        return s + (f" / {r['e']:.2f}" if energy else "")

    for th in angles:
        print(f"| {th} | {cell(res[('particle', 'mortar', th)], False)} | "
              f"{cell(res[('particle', 'one-way', th)], False)} | "
              f"{cell(res[('block', 'mortar', th)], True)} | "
              f"{cell(res[('block', 'one-way', th)], True)} |")
    for th in (0, 90):
        print(f"| {th}, standard MPM (box wall) | {cell(res[('particle', 'standard', th)], False)} "
              f"| | {cell(res[('block', 'standard', th)], True)} | |")

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    for kind, ax in zip(["particle", "block"], axes):
        for method, colour in [("mortar", "C0"), ("one-way", "C3")]:
            xs = [th for th in angles if res[(kind, method, th)]]
            ax.plot(xs, [res[(kind, method, th)]["vn"] for th in xs], "-o", ms=3, lw=1,
                    color=colour, label=f"{method}: normal velocity after")
            ax.plot(xs, [res[(kind, method, th)]["vt"] for th in xs], "--x", ms=3, lw=1,
                    color=colour, label=f"{method}: tangential velocity after")
        for th in (0, 90):
            r = res[(kind, "standard", th)]
            if r:
                ax.plot([th], [r["vn"]], "ks", ms=5, label="standard MPM (box wall)" if th == 0 else None)
        ax.axhline(1.0, color="k", lw=0.5, ls=":")
        ax.axhline(0.0, color="k", lw=0.5, ls=":")
        ax.set_xlabel("wall angle (deg)")
        ax.set_ylabel("velocity after impact (m/s)")
        ax.set_title("single particle (exact vn = 0, vt = 1)" if kind == "particle"
                     else "elastic block (exact vn = +1, vt = 1)", fontsize=9)
        ax.set_ylim(-1.5, 4)
        ax.grid(True, lw=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(os.path.join(IMG, "blending_throw.png"), dpi=110)
    plt.close(fig)


def main():
    global WORK
    os.makedirs(IMG, exist_ok=True)
    with tempfile.TemporaryDirectory() as work:
        WORK = work
        data, _ = study_bar()
        study_bar_diagnostics(data)
        study_incline()
        study_throw()


if __name__ == "__main__":
    main()
