#!/usr/bin/env python3
"""Writes the small meshes that ship in data/meshes/ (deterministic; rerun to regenerate).

hillside.obj            synthetic terrain from a height function: a 60 m x 24 m slope that
                        steepens, then flattens into a run-out, with a shallow channel along x
barrier_wall.stl        closed box wall (binary STL) across the run-out, standing on the terrain
source_volume.ply       closed debris source volume (ASCII PLY) resting on the upper slope
hillside_barrier.obj    the hillside and the barrier as one surface (parts terrain, barrier)
chute_half_cylinder.obj open half-cylinder chute, radius 0.5 m, 4 m long, inclined 30 degrees
tilted_plane.obj        2 m x 1 m plane inclined 25 degrees about y
Units are metres; normals (counter-clockwise) point to the material side: up for terrain and
chute, out of the closed bodies.
"""
import math
import struct


def terrain_height(x, y):
    # Slope profile: 40% grade at the top easing into a flat run-out below x = 45 m, a shallow
    # channel centred at y = 12 m, and gentle undulation so nothing is grid-aligned.
    run_out = 45.0
    s = min(max(x / run_out, 0.0), 1.0)
    profile = 18.0 * (1.0 - s) ** 2
    channel = -1.2 * math.exp(-((y - 12.0) / 4.0) ** 2) * (1.0 - 0.5 * s)
    bumps = 0.15 * math.sin(0.7 * x + 0.3 * y) * math.cos(0.4 * y)
    return profile + channel + bumps


def write_obj(path, vertices, faces, name, header=""):
    with open(path, "w") as f:
        f.write("# " + header + "\n" if header else "")
        f.write(f"o {name}\n")
        for v in vertices:
            f.write("v %.6f %.6f %.6f\n" % v)
        for a, b, c in faces:
            f.write(f"f {a + 1} {b + 1} {c + 1}\n")


def grid_surface(nu, nv, point):
    vertices = [point(i / nu, j / nv) for j in range(nv + 1) for i in range(nu + 1)]
    faces = []
    for j in range(nv):
        for i in range(nu):
            a = j * (nu + 1) + i
            b, c, d = a + 1, a + nu + 1, a + nu + 2
            faces += [(a, b, d), (a, d, c)]
    return vertices, faces


def box(lo, hi):
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = [(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0),
         (x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)]
    f = [(0, 2, 1), (0, 3, 2), (4, 5, 6), (4, 6, 7), (0, 1, 5), (0, 5, 4),
         (1, 2, 6), (1, 6, 5), (2, 3, 7), (2, 7, 6), (3, 0, 4), (3, 4, 7)]
    return v, f


def normal(v, f):
    a, b, c = (v[i] for i in f)
    u = [b[k] - a[k] for k in range(3)]
    w = [c[k] - a[k] for k in range(3)]
    n = (u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0])
    length = math.sqrt(sum(x * x for x in n)) or 1.0
    return tuple(x / length for x in n)


def write_binary_stl(path, vertices, faces, name):
    with open(path, "wb") as f:
        f.write(name.encode().ljust(80, b" ")[:80])
        f.write(struct.pack("<I", len(faces)))
        for face in faces:
            f.write(struct.pack("<3f", *normal(vertices, face)))
            for i in face:
                f.write(struct.pack("<3f", *vertices[i]))
            f.write(struct.pack("<H", 0))


def write_ply(path, vertices, faces):
    with open(path, "w") as f:
        f.write("ply\nformat ascii 1.0\n")
        f.write(f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n")
        f.write(f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
        for v in vertices:
            f.write("%.6f %.6f %.6f\n" % v)
        for a, b, c in faces:
            f.write(f"3 {a} {b} {c}\n")


def main():
    # Terrain: 160 x 60 quads = 19,200 triangles over [0, 60] x [0, 24].
    v, f = grid_surface(160, 60, lambda u, w: (60.0 * u, 24.0 * w, terrain_height(60.0 * u, 24.0 * w)))
    write_obj("hillside.obj", v, f, "hillside", "synthetic hillside, generate_meshes.py")

    # Barrier: 0.6 m thick, 3.5 m high, 16 m wide, founded 0.5 m into the run-out at x = 50 m.
    base = min(terrain_height(50.0, y) for y in [4.0 + 0.5 * k for k in range(33)]) - 0.5
    v, f = box((50.0, 4.0, base), (50.6, 20.0, base + 3.5 + 0.5))
    write_binary_stl("barrier_wall.stl", v, f, "barrier_wall")

    # Source volume: a 6 m x 8 m block whose base follows the slope 0.3 m above the terrain
    # at its four corners, 2.5 m thick; a closed hexahedron (12 triangles).
    x0, x1, y0, y1 = 4.0, 10.0, 8.0, 16.0
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    bottom = [(x, y, terrain_height(x, y) + 0.3) for x, y in corners]
    top = [(x, y, z + 2.5) for x, y, z in bottom]
    v = bottom + top
    f = [(0, 2, 1), (0, 3, 2), (4, 5, 6), (4, 6, 7), (0, 1, 5), (0, 5, 4),
         (1, 2, 6), (1, 6, 5), (2, 3, 7), (2, 7, 6), (3, 0, 4), (3, 4, 7)]
    write_ply("source_volume.ply", v, f)

    # Half-cylinder chute: axis along the incline (30 degrees, descending in +x), trough down,
    # normals pointing into the trough (up, towards the material).
    r, length, theta = 0.5, 4.0, math.radians(30.0)
    def chute(u, w):
        phi = math.pi * (1.0 + w)  # pi..2pi: the lower half
        s = length * u
        lx, ly, lz = s, r * math.cos(phi), r * math.sin(phi)
        return (lx * math.cos(theta) + lz * math.sin(theta), ly,
                -lx * math.sin(theta) + lz * math.cos(theta) + 2.5)
    v, f = grid_surface(40, 24, chute)  # (u along the axis, w around it): normals face the axis
    write_obj("chute_half_cylinder.obj", v, f, "chute")

    # Tilted plane, 25 degrees about y, normals up.
    t = math.radians(25.0)
    v, f = grid_surface(10, 5, lambda u, w: (2.0 * u * math.cos(t), 1.0 * w, -2.0 * u * math.sin(t) + 1.0))
    write_obj("tilted_plane.obj", v, f, "plane")

    hillside_with_barrier()


def oriented(v, tri, outward):
    """tri wound so that its normal points along `outward` (a 3-vector)."""
    n = normal(v, tri)
    return tri if sum(n[k] * outward[k] for k in range(3)) > 0.0 else (tri[0], tri[2], tri[1])


def hillside_with_barrier():
    """hillside_barrier.obj: the hillside and the barrier as one open surface (parts `terrain`
    and `barrier`): the terrain with the barrier's footprint cut out, and the barrier's upslope,
    downslope and end faces and top standing on it. One surface, so that material at the foot of
    the wall meets both in the same boundary layer (two separate walls overlap there)."""
    x0, x1, y0, y1 = 50.0, 50.6, 4.0, 20.0
    base = min(terrain_height(50.0, y) for y in [4.0 + 0.5 * k for k in range(33)]) - 0.5
    top = base + 4.0
    xs = sorted({round(60.0 * i / 160, 6) for i in range(161)
                 if not (x0 - 0.1 < 60.0 * i / 160 < x1 + 0.1)} | {x0, x1})
    ys = [round(24.0 * j / 60, 6) for j in range(61)]
    assert y0 in ys and y1 in ys
    nx, ny = len(xs), len(ys)
    v = [(x, y, terrain_height(x, y)) for y in ys for x in xs]
    ground = lambda i, j: j * nx + i
    inside = lambda x, y: x0 <= x <= x1 and y0 <= y <= y1
    top_index = {}
    for j, y in enumerate(ys):
        for i, x in enumerate(xs):
            if inside(x, y):
                top_index[(i, j)] = len(v)
                v.append((x, y, top))
    terrain, barrier = [], []
    for j in range(ny - 1):
        for i in range(nx - 1):
            cx, cy = 0.5 * (xs[i] + xs[i + 1]), 0.5 * (ys[j] + ys[j + 1])
            if inside(cx, cy):
                a, b = top_index[(i, j)], top_index[(i + 1, j)]
                c, d = top_index[(i, j + 1)], top_index[(i + 1, j + 1)]
                barrier += [(a, b, d), (a, d, c)]
            else:
                a, b = ground(i, j), ground(i + 1, j)
                c, d = ground(i, j + 1), ground(i + 1, j + 1)
                terrain += [(a, b, d), (a, d, c)]
    # Vertical faces along the footprint's border, wound outwards.
    def wall(p, q, outward):
        gp, gq, tp, tq = ground(*p), ground(*q), top_index[p], top_index[q]
        barrier.append(oriented(v, (gp, gq, tq), outward))
        barrier.append(oriented(v, (gp, tq, tp), outward))
    i0, i1 = xs.index(x0), xs.index(x1)
    j0, j1 = ys.index(y0), ys.index(y1)
    for j in range(j0, j1):
        wall((i0, j), (i0, j + 1), (-1.0, 0.0, 0.0))
        wall((i1, j), (i1, j + 1), (1.0, 0.0, 0.0))
    for i in range(i0, i1):
        wall((i, j0), (i + 1, j0), (0.0, -1.0, 0.0))
        wall((i, j1), (i + 1, j1), (0.0, 1.0, 0.0))
    with open("hillside_barrier.obj", "w") as f:
        f.write("# hillside and barrier as one surface, generate_meshes.py\n")
        for p in v:
            f.write("v %.6f %.6f %.6f\n" % p)
        for name, faces in (("terrain", terrain), ("barrier", barrier)):
            f.write(f"o {name}\n")
            for a, b, c in faces:
                f.write(f"f {a + 1} {b + 1} {c + 1}\n")


if __name__ == "__main__":
    main()
