"""A Wavefront OBJ reader for triangle meshes: vertices and faces, nothing else.

trimesh's OBJ loader skips ``v`` lines whose fields are separated by TABs and
resolves relative (negative) face indices against the wrong vertex count, which
silently moves vertices (the Cornell box comes out 1.15 wide instead of 2.02).
This reader follows the format as written: any white space separates fields;
a face index is 1-based, or negative for "counted back from the last vertex
defined so far"; ``v/vt/vn`` forms keep the vertex index; polygons are split
into a fan of triangles. Every other statement (normals, texture coordinates,
groups, materials) is ignored.
"""

from __future__ import annotations

import numpy as np


def read_obj(text: str, source: str = "OBJ") -> tuple[np.ndarray, np.ndarray]:
    """Parse OBJ text; returns (vertices (V, 3) float64, faces (F, 3) int64).

    Raises ValueError naming the line for a malformed vertex or face, or an
    index that refers to no vertex.
    """
    verts: list[tuple[float, float, float]] = []
    faces: list[tuple[int, int, int]] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        fields = raw.split("#", 1)[0].split()
        if not fields:
            continue
        key = fields[0]
        if key == "v":
            if len(fields) < 4:
                raise ValueError(f"{source} line {number}: a vertex needs three coordinates")
            try:
                verts.append((float(fields[1]), float(fields[2]), float(fields[3])))
            except ValueError:
                raise ValueError(f"{source} line {number}: cannot read vertex coordinates {fields[1:4]}") from None
        elif key == "f":
            if len(fields) < 4:
                raise ValueError(f"{source} line {number}: a face needs at least three vertices")
            idx = []
            for token in fields[1:]:
                try:
                    i = int(token.split("/", 1)[0])
                except ValueError:
                    raise ValueError(f"{source} line {number}: cannot read face index {token!r}") from None
                if i < 0:
                    i = len(verts) + i  # relative: -1 is the last vertex so far
                elif i > 0:
                    i -= 1
                else:
                    raise ValueError(f"{source} line {number}: face index 0 (OBJ indices start at 1)")
                if not 0 <= i < len(verts):
                    raise ValueError(f"{source} line {number}: face index {token} refers to no vertex "
                                     f"({len(verts)} defined so far)")
                idx.append(i)
            for k in range(1, len(idx) - 1):
                faces.append((idx[0], idx[k], idx[k + 1]))
    return (np.array(verts, dtype=np.float64).reshape(-1, 3),
            np.array(faces, dtype=np.int64).reshape(-1, 3))
