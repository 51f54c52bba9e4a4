"""Write meshes the way exporters write them, for tests on inputs torchir did not make.

Each mesh is written as OBJ (``v``/``vt``/``vn`` pools and ``f a/b/c`` corners, as Blender and
most DCC tools export: a loader makes one vertex per distinct corner, so uv seams and hard edges
repeat positions) and as binary-free ASCII PLY (per-vertex attributes, the repeated vertices
explicit, as PLY exporters write them). None of them is welded:

================  ===============================================================================
name              what users meet in it
================  ===============================================================================
``uv_sphere``     a UV sphere: a uv seam down one meridian (its column repeated), each pole one
                  position repeated per segment (its own ``u``), smooth normals
``cube``          Mitsuba's ``cube`` convention: 24 vertices, each face its own four
``flat_blob``     a flat-shaded export: every face its own three vertices (per-face normals)
``open_cylinder`` a tube without caps: two open borders, a uv seam
``holed_sphere``  a welded sphere with a few faces deleted: a hole with an open border
``fin_box``       a welded box with a fin on one edge: a non-manifold edge of three faces
================  ===============================================================================

Run ``python -m torchir.bench.exported_meshes OUT_DIR`` to write ``<name>.obj`` and ``<name>.ply``
for each, or import :func:`write_all`. Positions are in a unit box around the origin.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

__all__ = ["MESHES", "write_all", "write_obj", "write_ply"]


class Corners:
    """A mesh as exporters hold it: pools of positions, uvs and normals, and faces whose corners
    index each pool separately."""

    def __init__(self) -> None:
        self.v: list[tuple[float, float, float]] = []
        self.vt: list[tuple[float, float]] = []
        self.vn: list[tuple[float, float, float]] = []
        self.faces: list[tuple[tuple[int, int | None, int | None], ...]] = []

    def add(self, pool: str, value) -> int:
        getattr(self, pool).append(tuple(float(x) for x in value))
        return len(getattr(self, pool)) - 1


def _unit(p) -> np.ndarray:
    p = np.asarray(p, dtype=np.float64)
    return p / np.linalg.norm(p)


def uv_sphere(segments: int = 16, rings: int = 10, radius: float = 0.5) -> Corners:
    """Blender's UV sphere: ``rings - 1`` latitude circles of ``segments`` positions, one position
    per pole, ``segments + 1`` uv columns (the seam), a pole uv per segment."""
    m = Corners()
    pos = {}
    for i in range(1, rings):
        theta = math.pi * i / rings
        for j in range(segments):
            phi = 2 * math.pi * j / segments
            d = (math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta))
            pos[i, j] = (m.add("v", radius * np.array(d)), m.add("vn", d))
    top = (m.add("v", (0, 0, radius)), m.add("vn", (0, 0, 1)))
    bottom = (m.add("v", (0, 0, -radius)), m.add("vn", (0, 0, -1)))
    uv = {(i, j): m.add("vt", (j / segments, 1 - i / rings)) for i in range(1, rings) for j in range(segments + 1)}
    for j in range(segments):
        jn = (j + 1) % segments
        t_top = m.add("vt", ((j + 0.5) / segments, 1.0))
        t_bottom = m.add("vt", ((j + 0.5) / segments, 0.0))
        m.faces.append(((top[0], t_top, top[1]), (pos[1, j][0], uv[1, j], pos[1, j][1]), (pos[1, jn][0], uv[1, j + 1], pos[1, jn][1])))
        for i in range(1, rings - 1):
            a, b = (pos[i, j], uv[i, j]), (pos[i + 1, j], uv[i + 1, j])
            c, d = (pos[i + 1, jn], uv[i + 1, j + 1]), (pos[i, jn], uv[i, j + 1])
            corner = lambda q: (q[0][0], q[1], q[0][1])  # noqa: E731
            m.faces.append((corner(a), corner(b), corner(c)))
            m.faces.append((corner(a), corner(c), corner(d)))
        last = rings - 1
        m.faces.append(((bottom[0], t_bottom, bottom[1]), (pos[last, jn][0], uv[last, j + 1], pos[last, jn][1]),
                        (pos[last, j][0], uv[last, j], pos[last, j][1])))
    return m


def cube(half: float = 0.4) -> Corners:
    """Mitsuba's ``cube``: each of the six faces its own four corners (24 vertices), face normals."""
    m = Corners()
    for axis in range(3):
        for sign in (-1.0, 1.0):
            n = np.zeros(3)
            n[axis] = sign
            u, v = np.roll(np.eye(3), 1, axis=0)[axis], np.roll(np.eye(3), 2, axis=0)[axis]
            if sign > 0:
                u, v = v, u  # counter-clockwise seen from outside
            normal = m.add("vn", n)
            quad = []
            for du, dv, t in ((-1, -1, (0, 0)), (1, -1, (1, 0)), (1, 1, (1, 1)), (-1, 1, (0, 1))):
                quad.append((m.add("v", half * (n + du * u + dv * v)), m.add("vt", t), normal))
            m.faces += [(quad[0], quad[1], quad[2]), (quad[0], quad[2], quad[3])]
    return m


def flat_blob(segments: int = 12, rings: int = 8, radius: float = 0.45) -> Corners:
    """A lumpy closed sphere exported flat-shaded: every face its own three positions and normal."""
    m = Corners()
    def point(i: int, j: int) -> np.ndarray:
        if i == 0 or i == rings:
            return np.array([0, 0, radius if i == 0 else -radius])
        theta, phi = math.pi * i / rings, 2 * math.pi * (j % segments) / segments
        r = radius * (1 + 0.15 * math.sin(3 * phi) * math.sin(theta))
        return r * np.array([math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)])
    tris = []
    for j in range(segments):
        tris.append((point(0, 0), point(1, j), point(1, j + 1)))
        for i in range(1, rings - 1):
            tris += [(point(i, j), point(i + 1, j), point(i + 1, j + 1)), (point(i, j), point(i + 1, j + 1), point(i, j + 1))]
        tris.append((point(rings, 0), point(rings - 1, j + 1), point(rings - 1, j)))
    for a, b, c in tris:
        n = m.add("vn", _unit(np.cross(b - a, c - a)))
        m.faces.append(tuple((m.add("v", p), None, n) for p in (a, b, c)))
    return m


def open_cylinder(segments: int = 16, radius: float = 0.35, height: float = 0.8) -> Corners:
    """A tube without caps (two open borders) with a uv seam, smooth normals."""
    m = Corners()
    ring = {}
    for k, z in enumerate((-height / 2, height / 2)):
        for j in range(segments):
            phi = 2 * math.pi * j / segments
            ring[k, j] = (m.add("v", (radius * math.cos(phi), radius * math.sin(phi), z)), m.add("vn", (math.cos(phi), math.sin(phi), 0)))
    uv = {(k, j): m.add("vt", (j / segments, k)) for k in range(2) for j in range(segments + 1)}
    for j in range(segments):
        jn = (j + 1) % segments
        c = lambda k, jj, jt: (ring[k, jj][0], uv[k, jt], ring[k, jj][1])  # noqa: E731
        m.faces += [(c(0, j, j), c(0, jn, j + 1), c(1, jn, j + 1)), (c(0, j, j), c(1, jn, j + 1), c(1, j, j))]
    return m


def holed_sphere(segments: int = 14, rings: int = 8, radius: float = 0.45) -> Corners:
    """A welded latitude-longitude sphere (no uvs) with four faces near the equator removed."""
    m = Corners()
    idx = {}
    for i in range(1, rings):
        theta = math.pi * i / rings
        for j in range(segments):
            phi = 2 * math.pi * j / segments
            idx[i, j] = m.add("v", radius * np.array([math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)]))
    top, bottom = m.add("v", (0, 0, radius)), m.add("v", (0, 0, -radius))
    hole = {(rings // 2 - 1, 2), (rings // 2, 2), (rings // 2 - 1, 3), (rings // 2, 3)}  # (band, segment)
    for j in range(segments):
        jn = (j + 1) % segments
        m.faces.append(((top, None, None), (idx[1, j], None, None), (idx[1, jn], None, None)))
        for i in range(1, rings - 1):
            if (i, j) in hole:
                continue
            a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, jn], idx[i, jn]
            m.faces += [((a, None, None), (b, None, None), (c, None, None)), ((a, None, None), (c, None, None), (d, None, None))]
        m.faces.append(((bottom, None, None), (idx[rings - 1, jn], None, None), (idx[rings - 1, j], None, None)))
    return m


def fin_box(half: float = 0.3) -> Corners:
    """A welded box (8 shared corners) with a triangular fin standing on its top front edge: that
    edge has three faces (non-manifold)."""
    m = Corners()
    corners = [m.add("v", half * np.array([x, y, z])) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    box = ((0, 1, 3), (0, 3, 2), (4, 6, 7), (4, 7, 5), (0, 4, 5), (0, 5, 1),
           (2, 3, 7), (2, 7, 6), (0, 2, 6), (0, 6, 4), (1, 5, 7), (1, 7, 3))
    for f in box:
        m.faces.append(tuple((corners[k], None, None) for k in f))
    tip = m.add("v", (0.0, -half - 0.3, half + 0.3))  # above and in front of the edge (x, y=-h, z=+h)
    m.faces.append(((corners[1], None, None), (corners[5], None, None), (tip, None, None)))
    return m


MESHES = {
    "uv_sphere": uv_sphere,
    "cube": cube,
    "flat_blob": flat_blob,
    "open_cylinder": open_cylinder,
    "holed_sphere": holed_sphere,
    "fin_box": fin_box,
}


def write_obj(mesh: Corners, path: Path) -> None:
    """Wavefront OBJ with separate position, uv and normal pools (1-based, ``v/vt/vn`` corners)."""
    lines = ["# written by torchir.bench.exported_meshes (exporter conventions)"]
    lines += [f"v {x:.7g} {y:.7g} {z:.7g}" for x, y, z in mesh.v]
    lines += [f"vt {u:.7g} {v:.7g}" for u, v in mesh.vt]
    lines += [f"vn {x:.7g} {y:.7g} {z:.7g}" for x, y, z in mesh.vn]
    for face in mesh.faces:
        corners = []
        for v, t, n in face:
            if t is None and n is None:
                corners.append(f"{v + 1}")
            elif t is None:
                corners.append(f"{v + 1}//{n + 1}")
            else:
                corners.append(f"{v + 1}/{t + 1}" + (f"/{n + 1}" if n is not None else ""))
        lines.append("f " + " ".join(corners))
    path.write_text("\n".join(lines) + "\n")


def write_ply(mesh: Corners, path: Path) -> None:
    """ASCII PLY with one vertex per distinct corner (position, and normal/uv where the mesh has
    them), as PLY exporters write split vertices."""
    has_t = any(t is not None for f in mesh.faces for _, t, _ in f)
    has_n = any(n is not None for f in mesh.faces for _, _, n in f)
    index: dict[tuple, int] = {}
    rows, faces = [], []
    for face in mesh.faces:
        ids = []
        for corner in face:
            if corner not in index:
                v, t, n = corner
                row = list(mesh.v[v]) + (list(mesh.vn[n]) if has_n else []) + (list(mesh.vt[t]) if has_t else [])
                index[corner] = len(rows)
                rows.append(row)
            ids.append(index[corner])
        faces.append(ids)
    header = ["ply", "format ascii 1.0", f"element vertex {len(rows)}", "property float x", "property float y", "property float z"]
    if has_n:
        header += ["property float nx", "property float ny", "property float nz"]
    if has_t:
        header += ["property float u", "property float v"]
    header += [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    body = [" ".join(f"{x:.7g}" for x in row) for row in rows] + ["3 " + " ".join(map(str, f)) for f in faces]
    path.write_text("\n".join(header + body) + "\n")


def write_all(out_dir: str | Path) -> dict[str, dict[str, Path]]:
    """Write every mesh of :data:`MESHES` as OBJ and PLY into ``out_dir``; ``{name: {"obj": path, "ply": path}}``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = {}
    for name, make in MESHES.items():
        mesh = make()
        written[name] = {"obj": out / f"{name}.obj", "ply": out / f"{name}.ply"}
        write_obj(mesh, written[name]["obj"])
        write_ply(mesh, written[name]["ply"])
    return written


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_dir")
    for name, paths in write_all(parser.parse_args().out_dir).items():
        print(name, paths["obj"], paths["ply"])


if __name__ == "__main__":
    main()
