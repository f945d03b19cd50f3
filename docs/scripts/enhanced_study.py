#!/usr/bin/python3
"""Enhanced velocity field against Blending (mortar): the studies of docs/enhanced.md.

Runs build/bin/mpm (set MPM=... for another binary) on scenes written to a temporary folder and
prints the Markdown tables of docs/enhanced.md; draws docs/img/enhanced_*.png. Reuses the scene
builders and measures of blending_study.py, so the two write-ups measure the same things.
Deterministic: a second run prints the same tables.
"""
import copy
import os
import random
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import blending_study as bs  # noqa: E402

METHODS = ["mortar", "enhanced"]


def bar_with(offset, method, scheme=None, **kw):
    """bs.bar() with extra scheme keys."""
    scene = bs.bar_scene(offset, method, **kw)
    if scheme:
        scene = copy.deepcopy(scene)
        scene["scheme"].update(scheme)
    rows, err = bs.run(scene)
    return (bs.bar_metrics(rows), None) if rows else (None, err)


def row(label, results):
    s, faults = bs.summarize(results)
    if s is None:
        return f"| {label} | all {len(faults)} offsets fault | | | | |"
    return (f"| {label} | {s['mean']:.4f} / {s['max']:.4f} ({s['worst']:.2f} h) | "
            f"{bs.rng_fmt(s['contact'])} | {bs.rng_fmt(s['rebound'])} | "
            f"{bs.pct(s['de'][0])} .. {bs.pct(s['de'][1])} | {s['bad']} |")


def study_bar():
    bs.log("bar sweep ...")
    print("\n### 1D bar: every kernel, transfer, layer thickness and offset\n")
    print("Plateau error = |plateau / rho c v0 - 1| over the 20 offsets (mean / max, worst "
          "offset); 'bad' counts offsets over 5% or with a numerical fault. MUSL, separable "
          "slip wall, bar seeded on the grid's sub-cell lattice (not flush at most offsets).\n")
    print("| kernel | transfer | t / h | method | plateau error mean / max | contact / (2L/c) "
          "| rebound / v0 | energy change | bad |")
    print("|---|---|---|---|---|---|---|---|---|")
    data = {}
    for shape, transfer in bs.KERNELS:
        for t in bs.THICKNESS:
            for method in METHODS:
                res = [bs.bar(o, method, t=t, shape=shape, transfer=transfer) for o in bs.OFFSETS]
                data[(shape, transfer, t, method)] = res
                print(row(f"{shape} | {transfer} | {t} | {method}", res),
                      flush=True)
    return data


def study_dependence():
    bs.log("dependence ...")
    print("\n### Enhanced: what dropping dependent enhancement nodes does\n")
    print("Linear kernel, t = h, 20 offsets. 'default' drops covered Gamma nodes and nodes with "
          "K_SS / m_S < 0.01; 'keep covered' sets `drop_covered_enhancement: false`; "
          "`dependence_tolerance: 1` drops every enhancement node (the wall then acts through "
          "its Gamma multipliers on the standard grid alone).\n")
    print("| transfer | variant | plateau error mean / max | contact / (2L/c) | rebound / v0 "
          "| energy change | bad |")
    print("|---|---|---|---|---|---|---|")
    variants = [("default", {}), ("keep covered", {"drop_covered_enhancement": False}),
                ("keep covered, tolerance 0.5",
                 {"drop_covered_enhancement": False, "dependence_tolerance": 0.5}),
                ("tolerance 1 (no enhancement)", {"dependence_tolerance": 1.0})]
    out = {}
    for transfer in ["flip", "apic"]:
        for name, scheme in variants:
            res = [bar_with(o, "enhanced", scheme, t=1.0, shape="linear", transfer=transfer)
                   for o in bs.OFFSETS]
            out[(transfer, name)] = res
            print(row(f"{transfer} | {name}", res), flush=True)
    return out


def study_incline():
    bs.log("incline ...")
    angles = list(range(5, 90, 10))
    print("\n### 2D block on an incline, mortar and enhanced (t = h, MUSL, B-spline / APIC)\n")
    print("disp = displacement along the slope / exact 0.5 a t^2 (mu = 0.3 below the friction "
          "angle: displacement in mm, exact 0); N = mean normal wall force over the last 2/3 "
          "/ (m g cos); vn = final normal velocity (m/s).\n")
    res = {}
    for mu in [0.0, 0.3]:
        print(f"\n**mu = {mu}**\n")
        print("| angle | mortar disp / N / vn | enhanced disp / N / vn |")
        print("|---|---|---|")
        for th in angles:
            cells = []
            for method in METHODS:
                r = bs.incline(th, method, mu, "bspline2", "apic")
                res[(mu, method, th)] = r
                if r is None:
                    cells.append("numerical fault")
                elif r["exact"] > 0:
                    cells.append(f"{r['disp'] / r['exact']:.4f} / {r['normal']:.3f} / "
                                 f"{r['vn']:+.3f}")
                else:
                    cells.append(f"{1000 * r['disp']:.2f} mm / {r['normal']:.3f} / "
                                 f"{r['vn']:+.3f}")
            print(f"| {th} | {cells[0]} | {cells[1]} |", flush=True)
        for method in METHODS:
            ratios = [res[(mu, method, th)]["disp"] / res[(mu, method, th)]["exact"]
                      for th in angles if res[(mu, method, th)] and res[(mu, method, th)]["exact"]
                      > 0 and th >= 25]
            normal = [res[(mu, method, th)]["normal"] for th in angles if res[(mu, method, th)]]
            print(f"\n{method}, mu = {mu}: disp / exact {min(ratios):.4f} .. {max(ratios):.4f} "
                  f"(angles >= 25), N / (m g cos) {min(normal):.3f} .. {max(normal):.3f}")
    return res


def study_throw():
    bs.log("throw ...")
    angles = list(range(0, 91, 5))
    res = {}
    for k, kind in enumerate(["particle", "block"]):
        for th in angles:
            for method in METHODS:
                # The same random wall placement for both methods.
                rng = random.Random(20100809 + 1000 * k + th)
                res[(kind, method, th)] = bs.throw(th, method, kind, rng)
    print("\n### 2D particle and block thrown at a slip wall (B-spline, APIC, MUSL, t = h)\n")
    print("As in docs/blending.md: 1 m/s normal and 1 m/s tangential approach, the wall through "
          "a random point of a cell (the same placement for both methods). Exact after the "
          "impact: vt = 1; single particle vn = 0; elastic block vn = +1, E = 1.\n")
    print("| angle | particle mortar vn / vt | particle enhanced vn / vt | block mortar vn / vt / E "
          "| block enhanced vn / vt / E |")
    print("|---|---|---|---|---|")

    def cell(r, energy):
        if r is None:
            return "numerical fault"
        return f"{r['vn']:+.3f} / {r['vt']:.3f}" + (f" / {r['e']:.2f}" if energy else "")

    for th in angles:
        print(f"| {th} | {cell(res[('particle', 'mortar', th)], False)} | "
              f"{cell(res[('particle', 'enhanced', th)], False)} | "
              f"{cell(res[('block', 'mortar', th)], True)} | "
              f"{cell(res[('block', 'enhanced', th)], True)} |", flush=True)
    for kind in ["particle", "block"]:
        for method in METHODS:
            rs = [res[(kind, method, th)] for th in angles if res[(kind, method, th)]]
            vn = [r["vn"] for r in rs]
            vt = [r["vt"] for r in rs]
            print(f"\n{kind} {method}: vn {min(vn):+.3f} .. {max(vn):+.3f}, vt {min(vt):.3f} .. "
                  f"{max(vt):.3f}, {len(angles) - len(rs)} faults")
    return res


def plot(bar_data):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 4, figsize=(16, 3.6), sharey=True)
    for ax, (shape, transfer) in zip(axes, bs.KERNELS):
        for method, style in [("mortar", "o-"), ("enhanced", "s-")]:
            res = bar_data[(shape, transfer, 1.0, method)]
            xs = [o for o, (m, _) in zip(bs.OFFSETS, res) if m]
            ys = [abs(m["plateau"] - 1.0) + 1e-5 for m, _ in res if m]
            ax.semilogy(xs, ys, style, label=method, ms=4)
        ax.set_title(f"{shape} / {transfer}, t = h")
        ax.set_xlabel("wall offset / h")
        ax.grid(True, alpha=0.3)
    axes[0].set_ylabel("|plateau / rho c v0 - 1| (+1e-5)")
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(os.path.join(bs.IMG, "enhanced_plateau_offsets.png"), dpi=110)


def main():
    os.makedirs(bs.IMG, exist_ok=True)
    with tempfile.TemporaryDirectory() as work:
        bs.WORK = work
        data = study_bar()
        study_dependence()
        study_incline()
        study_throw()
        plot(data)


if __name__ == "__main__":
    main()
