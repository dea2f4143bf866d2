"""Fuzz target (atheris): mesh ingestion and grid building.

An input is a mode byte, two bytes choosing the grids and rays, and a payload.
The mode picks the path through the product:

- bytes written to a file ending in .obj, .stl, .ply or .off and read by
  ``Scene.from_file`` (gridcal's OBJ reader, trimesh for the rest);
- vertex and face arrays of arbitrary numbers (NaN, Inf, huge, negative and
  out-of-range indices, any shape) given to ``Scene``;

then, for a scene that loads, its statistics (the compiled pass), a uniform and a
nested grid of a resolution from the input, and a few rays from the input traced
through them and by brute force.

A ``ValueError`` (``calibrate._io.UserError`` is one) with a one-line message is
the answer to bad input; any other exception, an empty or multi-line message, or
a process crash is a finding.  Run for a bounded time:

    python tests/fuzz/fuzz_mesh.py NEW_DIR tests/fuzz/corpus -max_total_time=15

(libFuzzer adds inputs it finds to the first directory: give it a scratch one.)
tests/test_fuzz.py does that in CI.  The seeds in tests/fuzz/corpus are a
tetrahedron in each format (and a byte string for the arrays), each behind its
mode and parameter bytes; ``regression_*`` are inputs that fuzzing found to fail
before their fixes (a NaN face probability for a box of 1e200 in
:func:`calibrate.rays.isotropic`, rays beyond float64's range, a segfault in
the kernel's build for a box whose extent overflowed, and one for a subgrid
narrower than an ulp of its position, whose cells have zero width).
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import atheris

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

with atheris.instrument_imports(include=["calibrate", "models"]):
    import numpy as np

    from calibrate import Grid, Scene, brute_force
    from calibrate.rays import isotropic

SUFFIXES = (".obj", ".stl", ".ply", ".off")
#: Modes: one per suffix, then arrays.
ARRAY_MODE = len(SUFFIXES)
#: Bounds that keep one input fast and small.
MAX_FILE_BYTES = 1 << 16
MAX_ARRAY_VALUES = 3 * 64
MAX_AXIS = 16
RAYS = 8
#: Bytes after the mode byte that choose the grids and rays.
HEADER_BYTES = 2
MEMORY_LIMIT_BYTES = 1 << 24
WORKDIR = Path(tempfile.mkdtemp(prefix="gridcal-fuzz-"))


class Finding(AssertionError):
    """A bad input answered by something other than a one-line ValueError."""


def expect_clean(exc: ValueError) -> None:
    text = str(exc)
    if not text or "\n" in text:
        raise Finding(f"ValueError without a one-line message: {text!r}") from exc


def scene_from_file(payload: bytes, suffix: str):
    path = WORKDIR / f"input{suffix}"
    path.write_bytes(payload[:MAX_FILE_BYTES])
    return Scene.from_file(path)


def scene_from_arrays(payload: bytes):
    fdp = atheris.FuzzedDataProvider(payload)
    n_v = fdp.ConsumeIntInRange(0, MAX_ARRAY_VALUES)
    width = fdp.PickValueInList([3, 3, 3, 2, 4])
    vertices = np.array([fdp.ConsumeFloat() for _ in range(n_v)], dtype=np.float64)
    vertices = vertices[: (n_v // width) * width].reshape(-1, width)
    n_f = fdp.ConsumeIntInRange(0, MAX_ARRAY_VALUES)
    fwidth = fdp.PickValueInList([3, 3, 3, 2, 4])
    faces = np.array([fdp.ConsumeIntInRange(-4, max(3, len(vertices) + 2)) for _ in range(n_f)], dtype=np.int64)
    faces = faces[: (n_f // fwidth) * fwidth].reshape(-1, fwidth)
    return Scene(vertices, faces)


def exercise(scene: Scene, params: bytes) -> None:
    """Statistics, a uniform and a nested grid, and rays through them against brute force."""
    try:
        scene.stats  # noqa: B018 -- the compiled statistics pass
    except ValueError as exc:  # zero extent, out of double range
        expect_clean(exc)
    p = params.ljust(HEADER_BYTES, b"\0")
    res = (1 + p[0] % MAX_AXIS, 1 + (p[0] >> 4) % MAX_AXIS, 1 + p[1] % MAX_AXIS)
    intersector = ("watertight", "moller-trumbore")[(p[1] >> 4) & 1]
    grids = []
    for build in (lambda: Grid.uniform(scene, res, intersector, mailbox=bool(p[1] & 0x20),
                                       memory_limit=MEMORY_LIMIT_BYTES),
                  lambda: Grid.nested(scene, levels=2 + ((p[1] >> 6) & 1), threshold=(p[1] >> 7) * 3,
                                      intersector=intersector, memory_limit=MEMORY_LIMIT_BYTES)):
        try:
            grids.append(build())
        except ValueError as exc:  # over the memory limit
            expect_clean(exc)
    try:
        o, d = isotropic(scene.box_lo, scene.box_hi, RAYS, seed=p[0])
    except ValueError as exc:  # a box at the edge of float64's range
        expect_clean(exc)
        return
    d[0] = (1.0, 0.0, -0.0)  # and one ray along an axis, with a signed zero
    t_ref, _ = brute_force(scene, o, d, intersector)
    for grid in grids:
        t, _ = grid.intersect(o, d)
        if not np.all(t >= t_ref * (1.0 - 1e-9)):
            raise Finding(f"a grid hit before brute force's first hit: {grid}")
        steps, tests, subgrids = grid.count(o, d)
        if tests.max(initial=0) > grid.info["n_refs"]:
            raise Finding(f"more tests than references: {grid}")


def TestOneInput(data: bytes) -> None:
    """data[0] picks the path (a file suffix or arrays), data[1:3] the grids, the rest is the payload."""
    if not data:
        return
    mode = data[0] % (ARRAY_MODE + 1)
    params, payload = data[1:HEADER_BYTES + 1], data[HEADER_BYTES + 1:]
    try:
        scene = scene_from_arrays(payload) if mode == ARRAY_MODE else scene_from_file(payload, SUFFIXES[mode])
    except ValueError as exc:
        expect_clean(exc)
        return
    exercise(scene, params)


def main() -> None:
    atheris.Setup(sys.argv, TestOneInput)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
