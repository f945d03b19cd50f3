#!/usr/bin/env python3
"""Writes the small meshes that ship in data/meshes/ (deterministic; rerun to regenerate).

hillside.obj            synthetic terrain from a height function: a 60 m x 24 m slope that
                        steepens, then flattens into a run-out, with a shallow channel along x
barrier_wall.stl        closed box wall (binary STL) across the run-out, standing on the terrain
source_volume.ply       closed debris source volume (ASCII PLY) resting on the upper slope
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


if __name__ == "__main__":
    main()
