"""Bad input across the command line and the API: one clear line, status 2, nothing written.

Each row of :data:`CASES` is one kind of mistake: a command line (run in-process
through ``calibrate.cli.main``, some also through the installed console script)
or an API call, and a fragment its message must contain.  A command line must
exit with status 2, print exactly one line on stderr starting
``calibrate: error:``, nothing on stdout and no traceback; an API call must raise
``ValueError`` with a one-line message.  Every row runs in a fresh directory of
fixture files (meshes, calibration files, an existing output file, a read-only
directory); afterwards every file there is byte-identical, with the same
permissions, and nothing was added (no partial output, no temporary file).

Errors must come before any expensive work: while a row runs, building the
measuring suites, fitting, drawing plots and tracing rays in the kernels raise
:class:`ReachedExpensiveWork`, so a destination checked only after measuring
(or rendering) fails its row.

``python tests/test_bad_input.py --write-docs`` writes docs/bad-input.md from
this table with the messages the rows actually produce;
:func:`test_docs_are_current` checks the file matches.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import io
import json
import math
import os
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable
from unittest import mock

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script (--write-docs) from anywhere
    sys.path.insert(0, str(REPO))

from calibrate import Grid, Scene, calfile  # noqa: E402
from calibrate import _grid as _grid_module  # noqa: E402
from calibrate.cli import build_parser, main  # noqa: E402

#: The sample columns of a four-constant calibration (no memory term).
FOUR_CONSTANT_COLUMNS = ["t_setup_ns", "t_step_ns", "t_int_ns", "t_sub_ns", "extra_scatter"]

DOCS = REPO / "docs" / "bad-input.md"
ERROR_PREFIX = "calibrate: error: "
EXIT_USER_ERROR = 2
IS_ROOT = hasattr(os, "geteuid") and os.geteuid() == 0

# ---------------------------------------------------------------------------------------
# fixture files: every row runs in a fresh directory holding all of them
# ---------------------------------------------------------------------------------------

TETRA_V = [(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)]
TETRA_F = [(0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)]
#: Content of the existing output files; a failed write must leave exactly this.
EXISTING = b"existing content that a failed write must leave alone\n"


def _obj(vertices, faces) -> bytes:
    lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in vertices] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    return ("\n".join(lines) + "\n").encode()


def _binary_stl(vertices, faces) -> bytes:
    out = bytearray(b"gridcal test".ljust(80, b" ") + len(faces).to_bytes(4, "little"))
    for f in faces:
        out += np.zeros(3, "<f4").tobytes() + np.asarray([vertices[i] for i in f], "<f4").tobytes() + b"\0\0"
    return bytes(out)


def _binary_ply(vertices, faces) -> bytes:
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(vertices)}\nproperty float x\n"
            f"property float y\nproperty float z\nelement face {len(faces)}\n"
            "property list uchar int vertex_indices\nend_header\n").encode()
    body = np.asarray(vertices, "<f4").tobytes()
    for f in faces:
        body += bytes([3]) + np.asarray(f, "<i4").tobytes()
    return head + body


def _calibration() -> dict:
    """A valid calibration (planted constants; a few in-context records so a re-fit could start)."""
    planted = {"t_setup_ns": 40.0, "t_step_ns": 3.0, "t_int_ns": 7.5, "t_sub_ns": 15.0}
    consts = {k: dict(median=v, ci68=[0.9 * v, 1.1 * v], ci95=[0.8 * v, 1.2 * v]) for k, v in planted.items()}
    r = planted["t_int_ns"] / planted["t_step_ns"]
    consts["ratio"] = dict(median=r, ci68=[0.9 * r, 1.1 * r], ci95=[0.8 * r, 1.2 * r])
    row = [planted["t_setup_ns"], planted["t_step_ns"], planted["t_int_ns"], planted["t_sub_ns"], 0.1]
    meas = [dict(kind="in_context", scene="sphere", resolution=[m, m, m], intersector="watertight", rays=1024,
                 steps=1024 * m, tests=1024 * 3 * m, subgrids=0, values_ns=[1024 * (40 + 3 * m + 22.5 * m)] * 3)
            for m in (4, 8, 16, 32)]
    return calfile.validate(dict(schema_version=calfile.SCHEMA_VERSION, fingerprint=dict(cpu_model="Test CPU"),
                                 constants=consts, samples=dict(columns=FOUR_CONSTANT_COLUMNS,
                                                                values=[row, row]),
                                 diagnostics=dict(converged=True), measurements=meas, meta={}))


@functools.lru_cache(maxsize=1)
def fixture_files() -> dict[str, bytes]:
    good = json.dumps(_calibration(), indent=1).encode()
    future = _calibration()
    future["schema_version"] = calfile.SCHEMA_VERSION + 1
    return {
        "tetra.obj": _obj(TETRA_V, TETRA_F),
        "empty.obj": b"",
        "binary.obj": bytes(range(128, 256)) * 4,
        "bad_vertex.obj": b"v 0 0 0\nv 1 zero 0\nv 0 1 0\nf 1 2 3\n",
        "cut_vertex.obj": _obj(TETRA_V[:3], [(0, 1, 2)]) + b"v 0 0\n",
        "nan.obj": _obj([(0.0, 0.0, 0.0), (math.nan, 0.0, 0.0), (0.0, 1.0, 0.0)], [(0, 1, 2)]),
        "inf.obj": _obj([(0.0, 0.0, 0.0), (1.0, 0.0, 0.0), (0.0, math.inf, 0.0)], [(0, 1, 2)]),
        "out_of_range.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n",
        "zero_index.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n",
        "negative_index.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf -1 -2 -9\n",
        "points.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\n",
        "segment.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2\n",
        "point.obj": _obj([(2.0, 2.0, 2.0)] * 3, [(0, 1, 2)]),
        "tiny.obj": _obj([(x * 1e-200, y * 1e-200, z * 1e-200) for x, y, z in TETRA_V], TETRA_F),
        "huge.obj": _obj([(x * 1e200, y * 1e200, z * 1e200) for x, y, z in TETRA_V], TETRA_F),
        "cut_binary.stl": _binary_stl(TETRA_V, TETRA_F)[:84 + 50 + 20],
        "cut_ascii.stl": b"solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0",
        "cut_binary.ply": _binary_ply(TETRA_V, TETRA_F)[:-9],
        "not_a.ply": b"plx\nformat ascii 1.0\nend_header\n",
        "good.json": good,
        "future.json": json.dumps(future, indent=1).encode(),
        "truncated.json": good[: len(good) // 2],
        "empty.json": b"",
        "binary.json": bytes(range(128, 256)),
        "unconverged.json": json.dumps({**_calibration(), "diagnostics": {"converged": False}}).encode(),
        # a fit per ray set whose camera entry lost its posterior samples
        "bad_by_rays.json": json.dumps({**_calibration(), "by_rays": {"camera": {
            k: v for k, v in _calibration().items() if k in ("constants", "diagnostics")}}}).encode(),
        # a measurement entering more occupied cells than it stepped through
        "bad_visits.json": json.dumps({**_calibration(), "measurements": [
            dict(m, visits=m["steps"] + 1) if i == 2 else m
            for i, m in enumerate(_calibration()["measurements"])]}).encode(),
        # existing outputs a failed write must leave alone
        "out.json": EXISTING,
        "locked.json": EXISTING,  # made read-only
        "locked.h": EXISTING,  # made read-only
        "locked.png": EXISTING,  # made read-only
        "fig-residuals.png": EXISTING,  # made read-only: the second of show --plot's three files
        "ro/keep.txt": EXISTING,  # ro/ is made read-only
        "adir/keep.txt": EXISTING,
    }


READ_ONLY_FILES = ("locked.json", "locked.h", "locked.png", "fig-residuals.png")
READ_ONLY_DIR = "ro"


def make_workdir(root: Path) -> Path:
    for name, data in fixture_files().items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    for name in READ_ONLY_FILES:
        (root / name).chmod(0o444)
    (root / READ_ONLY_DIR).chmod(0o555)
    return root


def snapshot(root: Path) -> dict:
    """Every file and directory under root: relative path -> (content or None, permission bits)."""
    out = {}
    for path in sorted(root.rglob("*")):
        st = path.lstat()
        out[str(path.relative_to(root))] = (None if path.is_dir() else path.read_bytes(), st.st_mode & 0o7777)
    return out


# ---------------------------------------------------------------------------------------
# the table
# ---------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Case:
    """One kind of bad input.

    section : heading in docs/bad-input.md.
    kind : what is wrong, in words.
    expect : a fragment the message must contain.
    argv : a command line (without ``calibrate``), run in the fixture directory; or
    call : an API call ``call(workdir)``, shown as ``how`` in the docs.
    console : also run through the console script in a subprocess.
    """

    section: str
    kind: str
    expect: str
    argv: tuple = ()
    call: Callable | None = None
    how: str = ""
    console: bool = False

    @property
    def verb(self) -> str:
        return "API" if self.call is not None else self.argv[0]

    @property
    def shown(self) -> str:
        return self.how if self.call is not None else "calibrate " + " ".join(self.argv)

    @property
    def id(self) -> str:
        return f"{self.verb}: {self.kind}"


def cli(section, kind, argv: str, expect, console=False) -> Case:
    return Case(section, kind, expect, argv=tuple(argv.split()), console=console)


def api(section, kind, how, call, expect) -> Case:
    return Case(section, kind, expect, call=call, how=how)


def _tetra() -> Scene:
    return Scene(TETRA_V, TETRA_F)


def _grid() -> Grid:
    return Grid.uniform(_tetra(), (2, 2, 2))


def _rays(n=2):
    return np.zeros((n, 3)), np.tile([1.0, 1.0, 1.0], (n, 1))


MESH, SCENE, ARRAYS, GRID, OPTIONS, CALFILE, OUTPUT, RENDER = (
    "Mesh files", "Scenes", "Meshes and rays as arrays (API)", "Grids (API)", "Options: budgets, ratios, seeds, "
    "choices", "Calibration files", "Output files", "Rendering and the talk's claims")
BENCH = "Benchmarks and the tradeoff study"

CASES: list[Case] = [
    # -- mesh files ----------------------------------------------------------------------------
    cli(MESH, "mesh file missing", "predict missing.obj --ratio 1", "missing.obj: no such file", console=True),
    cli(MESH, "mesh path is a directory", "predict adir --ratio 1", "adir: is a directory"),
    cli(MESH, "mesh file empty (0 bytes)", "predict empty.obj --ratio 1", "the file is empty"),
    cli(MESH, "OBJ file of binary garbage", "predict binary.obj --ratio 1", "not a text OBJ file"),
    cli(MESH, "corrupt OBJ vertex", "predict bad_vertex.obj --ratio 1", "line 2: cannot read vertex coordinates"),
    cli(MESH, "truncated OBJ (last vertex cut short)", "predict cut_vertex.obj --ratio 1",
        "line 5: a vertex needs three coordinates"),
    cli(MESH, "truncated binary STL", "predict cut_binary.stl --ratio 1", "truncated binary STL", console=True),
    cli(MESH, "truncated ASCII STL", "predict cut_ascii.stl --ratio 1", "holds no triangles"),
    cli(MESH, "truncated binary PLY", "predict cut_binary.ply --ratio 1", "is it corrupt or truncated?"),
    cli(MESH, "corrupt PLY (no magic number)", "predict not_a.ply --ratio 1", "cannot read it as a mesh"),
    cli(MESH, "NaN vertex in a file", "predict nan.obj --ratio 1", "NaN or Inf coordinates", console=True),
    cli(MESH, "Inf vertex in a file", "predict inf.obj --ratio 1", "NaN or Inf coordinates"),
    cli(MESH, "face index out of range", "predict out_of_range.obj --ratio 1", "face index 7 refers to no vertex"),
    cli(MESH, "face index 0 (OBJ counts from 1)", "predict zero_index.obj --ratio 1", "face index 0"),
    cli(MESH, "negative (relative) face index before the first vertex", "predict negative_index.obj --ratio 1",
        "face index -9 refers to no vertex"),
    cli(MESH, "empty mesh (vertices, no faces)", "predict points.obj --ratio 1", "holds no triangles"),
    cli(MESH, "non-triangular face (two vertices)", "predict segment.obj --ratio 1",
        "a face needs at least three vertices"),
    api(MESH, "mesh file missing", 'Scene.from_file("missing.ply")', lambda d: Scene.from_file("missing.ply"),
        "missing.ply: no such file"),
    api(MESH, "truncated binary STL", 'Scene.from_file("cut_binary.stl")',
        lambda d: Scene.from_file("cut_binary.stl"), "its header announces 4 triangles"),
    # -- scenes --------------------------------------------------------------------------------
    cli(SCENE, "zero-extent scene (every vertex at one point)", "predict point.obj --ratio 1", "zero extent"),
    cli(SCENE, "scene too small for double precision", "predict tiny.obj --ratio 1", "too small for its statistics"),
    cli(SCENE, "scene too large for double precision", "predict huge.obj --ratio 1", "too large for its statistics"),
    cli(SCENE, "unknown built-in scene", "predict spehre --ratio 1", "neither a mesh file nor a built-in scene"),
    api(SCENE, "zero-extent scene's statistics", "Scene(three copies of one vertex, [[0, 1, 2]]).stats",
        lambda d: Scene([[1.0, 2.0, 3.0]] * 3, [[0, 1, 2]]).stats, "zero extent"),
    # -- arrays --------------------------------------------------------------------------------
    api(ARRAYS, "NaN vertex", "Scene(vertices with a NaN, faces)",
        lambda d: Scene([[0, 0, 0], [math.nan, 0, 0], [0, 1, 0]], [[0, 1, 2]]), "NaN or Inf coordinates"),
    api(ARRAYS, "Inf vertex", "Scene(vertices with an Inf, faces)",
        lambda d: Scene([[0, 0, 0], [1, 0, 0], [0, -math.inf, 0]], [[0, 1, 2]]), "NaN or Inf coordinates"),
    api(ARRAYS, "negative face index", "Scene(vertices, [[0, 1, -2]])",
        lambda d: Scene(TETRA_V, [[0, 1, -2]]), "negative vertex index -2"),
    api(ARRAYS, "face index out of range", "Scene(4 vertices, [[0, 1, 4]])",
        lambda d: Scene(TETRA_V, [[0, 1, 4]]), "refers to vertex 4, but the mesh has only 4 vertices"),
    api(ARRAYS, "empty mesh", "Scene(vertices, np.zeros((0, 3), int))",
        lambda d: Scene(TETRA_V, np.zeros((0, 3), int)), "the mesh is empty"),
    api(ARRAYS, "non-triangular faces (quads)", "Scene(vertices, [[0, 1, 2, 3]])",
        lambda d: Scene(TETRA_V, [[0, 1, 2, 3]]), "faces must be triangles"),
    api(ARRAYS, "vertices of the wrong shape", "Scene(np.zeros((4, 2)), faces)",
        lambda d: Scene(np.zeros((4, 2)), TETRA_F), "vertices must have shape (V, 3)"),
    api(ARRAYS, "coordinates wider apart than float64 holds", "Scene(vertices from -1.7e308 to 1.7e308 on every axis, "
        "faces)", lambda d: Scene([[-1.7e308] * 3, [1.7e308] * 3, [0.0, 1.7e308, -1.7e308]], [[0, 1, 2]]),
        "box is too wide for float64"),
    api(ARRAYS, "ray origin NaN", "grid.intersect(origins with a NaN, directions)",
        lambda d: _grid().intersect(np.array([[math.nan, 0, 0]]), np.array([[1.0, 0, 0]])), "contain NaN or Inf"),
    api(ARRAYS, "zero ray direction", "grid.count(origins, [[0, 0, 0]])",
        lambda d: _grid().count(np.zeros((1, 3)), np.zeros((1, 3))), "zero direction"),
    # -- grids ---------------------------------------------------------------------------------
    api(GRID, "zero resolution", "Grid.uniform(scene, (0, 4, 4))",
        lambda d: Grid.uniform(_tetra(), (0, 4, 4)), "every axis needs at least 1 cell"),
    api(GRID, "negative resolution", "Grid.uniform(scene, (4, -4, 4))",
        lambda d: Grid.uniform(_tetra(), (4, -4, 4)), "every axis needs at least 1 cell"),
    api(GRID, "fractional resolution", "Grid.uniform(scene, (4.5, 4, 4))",
        lambda d: Grid.uniform(_tetra(), (4.5, 4, 4)), "three whole numbers"),
    api(GRID, "absurd resolution (2^42 cells)", "Grid.uniform(scene, (16384, 16384, 16384))",
        lambda d: Grid.uniform(_tetra(), (16384, 16384, 16384)), "overflows the grid's 32-bit cell offsets"),
    api(GRID, "absurd resolution (1e300 cells on an axis)", "Grid.uniform(scene, (1e300, 1, 1))",
        lambda d: Grid.uniform(_tetra(), (1e300, 1, 1)), "an axis exceeds 2^31 - 1 cells"),
    api(GRID, "grid over the memory limit", "Grid.uniform(scene, (64, 64, 64), memory_limit=1000)",
        lambda d: Grid.uniform(_tetra(), (64, 64, 64), memory_limit=1000), "over the memory limit"),
    api(GRID, "no build threads", "Grid.uniform(scene, (4, 4, 4), threads=0)",
        lambda d: Grid.uniform(_tetra(), (4, 4, 4), threads=0), "threads must be a whole number from 1 to 64"),
    api(GRID, "zero levels", "Grid.nested(scene, levels=0)",
        lambda d: Grid.nested(_tetra(), levels=0), "levels must be a whole number from 1"),
    # -- options -------------------------------------------------------------------------------
    cli(OPTIONS, "zero budget", "run --budget 0", "must be a positive number", console=True),
    cli(OPTIONS, "negative budget", "run --budget -5", "must be a positive number"),
    cli(OPTIONS, "NaN budget", "run --budget nan", "must be a positive number"),
    cli(OPTIONS, "budget too short to measure and fit", "run --budget 0.5", "is too short"),
    cli(OPTIONS, "zero target width", "run --target-rel-width 0", "must be a positive number"),
    cli(OPTIONS, "negative seed", "run --seed -1", "the seed must be from 0"),
    cli(OPTIONS, "unknown intersector", "run --intersector fastest", "invalid choice"),
    cli(OPTIONS, "resume with nothing to resume", "run --resume --out out.json", "no interrupted run to resume"),
    cli(OPTIONS, "seed that is not a number", "fit good.json --seed abc", "the seed must be a whole number"),
    cli(OPTIONS, "cache size in an unknown unit", "fit good.json --cache 16XB", "the size's unit must be one of"),
    cli(OPTIONS, "cache size of zero", "run --cache 0", "the size must be from 64 bytes"),
    cli(OPTIONS, "cache size for a file whose records carry no grid sizes", "fit good.json --cache 16MiB",
        "cannot be counted against another cache"),
    cli(OPTIONS, "zero ratio", "predict --ratio 0", "must be a positive number"),
    cli(OPTIONS, "negative ratio", "predict tetra.obj --ratio -1", "must be a positive number"),
    cli(OPTIONS, "infinite ratio", "export --ratio inf", "must be a positive number"),
    cli(OPTIONS, "ratio and calibration together", "export --ratio 1 --calibration good.json", "not allowed with"),
    cli(OPTIONS, "unknown fidelity", "predict --ratio 1 --fidelity exact", "invalid choice"),
    cli(OPTIONS, "unknown level count", "predict --ratio 1 --levels 9", "invalid choice"),
    cli(OPTIONS, "unknown ray set", "export --ratio 1 --rays sideways", "invalid choice"),
    cli(OPTIONS, "unknown option", "scenes --colour", "unrecognized arguments: --colour"),
    cli(OPTIONS, "unknown verb", "calibrated", "invalid choice"),
    # -- calibration files ---------------------------------------------------------------------
    cli(CALFILE, "calibration from a future schema", "predict --calibration future.json",
        "is newer than this gridcal understands", console=True),
    cli(CALFILE, "truncated calibration", "predict --calibration truncated.json",
        "the file may be truncated or corrupted"),
    cli(CALFILE, "no calibration at all", "predict tetra.obj", "no calibration: ./calibration.json does not exist"),
    cli(CALFILE, "calibration file missing", "fit missing.json", "no such calibration file"),
    cli(CALFILE, "calibration from a future schema", "fit future.json", "is newer than this gridcal understands"),
    cli(CALFILE, "truncated calibration", "fit truncated.json", "the file may be truncated or corrupted"),
    cli(CALFILE, "truncated calibration", "show truncated.json", "the file may be truncated or corrupted",
        console=True),
    cli(CALFILE, "empty calibration (0 bytes)", "show empty.json", "not valid JSON at line 1 column 1"),
    cli(CALFILE, "calibration of binary garbage", "show binary.json", "not UTF-8 text"),
    cli(CALFILE, "calibration whose posterior did not converge", "show unconverged.json",
        "the posterior did not converge"),
    cli(CALFILE, "calibration path is a directory", "show adir", "is a directory, not a calibration file"),
    cli(CALFILE, "more occupied cells entered than cells stepped", "fit bad_visits.json",
        "measurements[2].visits: 16385 occupied cells entered but only 16384 cells stepped"),
    cli(CALFILE, "a ray set's fit without posterior samples", "predict --calibration bad_by_rays.json --rays camera",
        "by_rays.camera: missing key 'samples'"),
    cli(CALFILE, "calibration from a future schema", "export --calibration future.json",
        "is newer than this gridcal understands"),
    cli(CALFILE, "truncated calibration", "export --calibration truncated.json",
        "the file may be truncated or corrupted"),
    api(CALFILE, "calibration from a future schema", 'calfile.load("future.json")',
        lambda d: calfile.load("future.json"), "is newer than this gridcal understands"),
    # -- output files --------------------------------------------------------------------------
    cli(OUTPUT, "output is a directory", "run --out adir", "adir: it is a directory"),
    cli(OUTPUT, "output file is read-only", "run --out locked.json", "the file is read-only"),
    cli(OUTPUT, "output directory is read-only", "run --out ro/cal.json", "directory ro is not writable"),
    cli(OUTPUT, "output directory missing", "run --out nowhere/cal.json", "directory nowhere does not exist"),
    cli(OUTPUT, "output file is read-only", "fit good.json --out locked.json", "the file is read-only"),
    cli(OUTPUT, "output is a directory", "fit good.json --out adir", "adir: it is a directory"),
    cli(OUTPUT, "output directory is read-only", "show good.json --plot ro/fig", "directory ro is not writable"),
    cli(OUTPUT, "second plot file is read-only", "show good.json --plot fig", "fig-residuals.png: the file is "
        "read-only"),
    cli(OUTPUT, "output is a directory", "export --ratio 1 --header adir", "adir: it is a directory",
        console=True),
    cli(OUTPUT, "output file is read-only", "export --ratio 1 --header locked.h", "the file is read-only"),
    cli(OUTPUT, "output directory is read-only", "export --ratio 1 --header ro/grid.h",
        "directory ro is not writable"),
    cli(OUTPUT, "output directory missing", "export --ratio 1 --header nowhere/grid.h",
        "directory nowhere does not exist"),
    cli(OUTPUT, "output's directory is a file", "export --ratio 1 --header out.json/grid.h",
        "out.json is not a directory"),
    cli(OUTPUT, "output is a directory", "render --ratio 1 --out adir", "adir: it is a directory"),
    cli(OUTPUT, "output file is read-only", "render --ratio 1 --out locked.png", "the file is read-only"),
    cli(OUTPUT, "output directory is read-only", "render --ratio 1 --out ro/image.png",
        "directory ro is not writable"),
    cli(OUTPUT, "image name without .png", "render --ratio 1 --out image.jpg", "the image is a PNG"),
    # -- the verbs of rendering and of the talk's claims ----------------------------------------
    cli(RENDER, "NaN vertex in a file", "render nan.obj --ratio 1", "NaN or Inf coordinates"),
    cli(RENDER, "zero resolution", "render --resolution 0 4 4", "every axis needs at least 1 cell"),
    cli(RENDER, "absurd resolution", "render --resolution 100000 100000 100000",
        "overflows the grid's 32-bit cell offsets"),
    cli(RENDER, "zero image width", "render --ratio 1 --width 0", "must be a whole number of pixels"),
    cli(RENDER, "absurd image height", "render --ratio 1 --height 100000", "must be a whole number of pixels"),
    cli(RENDER, "zero view direction", "render --ratio 1 --view 0 0 0", "finite non-zero 3-vector"),
    cli(RENDER, "NaN view direction", "render --ratio 1 --view nan 0 1", "finite non-zero 3-vector"),
    cli(RENDER, "calibration from a future schema", "render --calibration future.json",
        "is newer than this gridcal understands"),
    cli(RENDER, "zero ratio", "paper --ratio 0", "must be a positive number"),
    cli(RENDER, "truncated calibration", "paper --calibration truncated.json", "the file may be truncated or corrupted"),
    cli(RENDER, "no calibration at all", "paper", "no calibration: ./calibration.json does not exist"),
    # -- benchmarks and the tradeoff study ------------------------------------------------------
    cli(BENCH, "unknown built-in scene", "bench spehre", "neither a mesh file nor a built-in scene"),
    cli(BENCH, "mesh file missing", "bench missing.obj", "missing.obj: no such file", console=True),
    cli(BENCH, "corrupt OBJ vertex", "bench bad_vertex.obj", "line 2: cannot read vertex coordinates"),
    cli(BENCH, "mesh file missing (scaling series)", "bench --scale --max-triangles 20 missing.obj",
        "missing.obj: no such file"),
    cli(BENCH, "truncated binary STL (scaling series)", "bench --scale --max-triangles 20 cut_binary.stl",
        "truncated binary STL"),
    cli(BENCH, "zero batch", "bench --batch 0", "--batch must be at least 1"),
    cli(BENCH, "negative repeats", "bench --repeats -2", "--repeats must be at least 1"),
    cli(BENCH, "NaN batch", "bench --batch nan", "invalid int value: 'nan'"),
    cli(BENCH, "unknown ray set", "bench --rays camera,sideways", "unknown ray set 'sideways'"),
    cli(BENCH, "no ray set", "bench --rays ,", "--rays names no ray set"),
    cli(BENCH, "unknown clock", "bench --clock sundial", "invalid choice"),
    cli(BENCH, "zero ratio", "bench --ratio 0", "must be a positive number"),
    cli(BENCH, "ratio and calibration together", "bench --ratio 1 --calibration good.json", "not allowed with"),
    cli(BENCH, "truncated calibration", "bench --calibration truncated.json", "the file may be truncated or corrupted"),
    cli(BENCH, "calibration from a future schema", "bench --calibration future.json",
        "is newer than this gridcal understands"),
    cli(BENCH, "zero largest sphere", "bench --scale --max-triangles 0", "must be a positive number"),
    cli(BENCH, "NaN largest sphere", "bench --scale --max-triangles nan", "must be a positive number"),
    cli(BENCH, "fractional largest sphere", "bench --scale --max-triangles 2000.5", "must be a whole number"),
    cli(BENCH, "largest sphere below the smallest mesh", "bench --scale --max-triangles 10", "a whole number >= 20"),
    cli(BENCH, "absurd largest sphere", "bench --scale --max-triangles 1e12", "must be at most 2,147,483,647"),
    cli(BENCH, "unknown built-in scene", "tradeoff spehre", "neither a mesh file nor a built-in scene"),
    cli(BENCH, "mesh file missing", "tradeoff missing.obj", "missing.obj: no such file"),
    cli(BENCH, "NaN vertex in a file", "tradeoff nan.obj", "NaN or Inf coordinates"),
    cli(BENCH, "one scene twice", "tradeoff tetra.obj tetra.obj", "scenes must have different names"),
    cli(BENCH, "zero budget", "tradeoff --budget 0", "must be a positive number", console=True),
    cli(BENCH, "negative budget", "tradeoff --quick --budget -5", "must be a positive number"),
    cli(BENCH, "NaN budget", "tradeoff --budget nan", "must be a positive number"),
    cli(BENCH, "infinite budget", "tradeoff --budget inf", "must be a positive number"),
    cli(BENCH, "budget too short for a calibration run", "tradeoff --quick --budget 1", "is too short"),
    cli(BENCH, "negative seed", "tradeoff --seed -1", "the seed must be from 0"),
    cli(BENCH, "seed that is not a number", "tradeoff --seed abc", "the seed must be a whole number"),
    cli(BENCH, "unknown option", "tradeoff --intersector fastest", "unrecognized arguments: --intersector"),
    cli(BENCH, "plot is a directory", "tradeoff --quick --plot adir", "adir: it is a directory"),
    cli(BENCH, "plot directory missing", "tradeoff --quick --plot nowhere/fig.png", "directory nowhere does not exist"),
    cli(BENCH, "plot's directory is a file", "tradeoff --quick --plot out.json/fig.png", "out.json is not a directory"),
    cli(BENCH, "plot file is read-only", "tradeoff --quick --plot locked.png", "the file is read-only"),
    cli(BENCH, "plot directory is read-only", "tradeoff --quick --plot ro/fig.png", "directory ro is not writable"),
    cli(BENCH, "plot name without .png", "tradeoff --quick --plot fig.svg", "the plot is a PNG"),
    cli(BENCH, "unknown built-in scene", "compare --ratio 1 spehre", "neither a mesh file nor a built-in scene"),
    cli(BENCH, "mesh file missing", "compare --ratio 1 missing.obj", "missing.obj: no such file", console=True),
    cli(BENCH, "mesh file empty (0 bytes)", "compare --ratio 1 empty.obj", "the file is empty"),
    cli(BENCH, "a bad scene after a good one", "compare --ratio 1 sphere not_a.ply", "cannot read it as a mesh"),
    cli(BENCH, "no calibration at all", "compare sphere", "no calibration: ./calibration.json does not exist"),
    cli(BENCH, "truncated calibration", "compare --calibration truncated.json", "the file may be truncated or corrupted"),
    cli(BENCH, "zero ratio", "compare --ratio 0", "must be a positive number"),
    cli(BENCH, "too few sweep points", "compare --ratio 1 --points 2", "--points must be from 3 to 64"),
    cli(BENCH, "sweep points not a number", "compare --ratio 1 --points many", "--points must be a whole number"),
    cli(BENCH, "zero ray count", "compare --ratio 1 --ray-count 0", "--ray-count must be at least 1"),
    cli(BENCH, "NaN ray count", "compare --ratio 1 --ray-count nan", "--ray-count must be a whole number"),
    cli(BENCH, "absurd ray count", "compare --ratio 1 --ray-count 100000000000", "--ray-count must be at most"),
    cli(BENCH, "negative rounds", "compare --ratio 1 --rounds -1", "--rounds must be at least 1"),
    cli(BENCH, "zero builds", "compare --ratio 1 --builds 0", "--builds must be at least 1"),
    cli(BENCH, "zero shortest value", "compare --ratio 1 --min-time 0", "must be a positive number"),
    cli(BENCH, "NaN shortest value", "compare --ratio 1 --min-time nan", "must be a positive number"),
    cli(BENCH, "unknown level count", "compare --ratio 1 --levels 3", "invalid choice"),
    cli(BENCH, "unknown ray set", "compare --ratio 1 --rays laser", "invalid choice"),
    cli(BENCH, "unknown fidelity", "compare --ratio 1 --fidelity exact", "invalid choice"),
    cli(BENCH, "plot is a directory", "compare --ratio 1 --plot adir", "adir: it is a directory"),
    cli(BENCH, "plot directory missing", "compare --ratio 1 --plot nowhere/fig.png", "directory nowhere does not exist"),
    cli(BENCH, "plot's directory is a file", "compare --ratio 1 --plot out.json/fig.png", "out.json is not a directory"),
    cli(BENCH, "plot file is read-only", "compare --ratio 1 --plot locked.png", "the file is read-only"),
    cli(BENCH, "plot directory is read-only", "compare --ratio 1 --plot ro/fig.png", "directory ro is not writable"),
    cli(BENCH, "plot name without .png", "compare --ratio 1 --plot fig.svg", "the plot is a PNG"),
]


# ---------------------------------------------------------------------------------------
# running a row
# ---------------------------------------------------------------------------------------

class ReachedExpensiveWork(Exception):
    """Raised when a failing row reaches measuring, fitting or plotting before its error."""


def _refuse(what: str):
    def refuse(*args, **kwargs):
        raise ReachedExpensiveWork(f"{what} started before the bad input was reported")

    return refuse


@contextlib.contextmanager
def row_environment(workdir: Path):
    """cwd = workdir; expensive work refused; as root, the read-only directory enforced.

    Root passes every permission check, so for root the directory ``ro`` is made
    read-only the way the kernel reports it to anyone else: creating a file in it
    fails with EACCES.
    """
    real_mkstemp = tempfile.mkstemp
    ro = (workdir / READ_ONLY_DIR).resolve()

    def mkstemp(*args, dir=None, **kwargs):
        if dir is not None and Path(dir).resolve() == ro:
            raise PermissionError(13, "Permission denied", str(dir))
        return real_mkstemp(*args, dir=dir, **kwargs)

    old = os.getcwd()
    os.chdir(workdir)
    try:
        with contextlib.ExitStack() as stack:
            stack.enter_context(mock.patch("calibrate.suites.isolated_configs", _refuse("measuring")))
            stack.enter_context(mock.patch("calibrate.suites.context_configs", _refuse("measuring")))
            stack.enter_context(mock.patch("calibrate.fit.fit", _refuse("fitting")))
            stack.enter_context(mock.patch("calibrate.plots.corner", _refuse("plotting")))
            stack.enter_context(mock.patch("calibrate.plots.residuals", _refuse("plotting")))
            stack.enter_context(mock.patch("calibrate.plots.isolated", _refuse("plotting")))
            for name in ("intersect", "count", "bench"):  # tracing rays (after the API's own checks)
                stack.enter_context(mock.patch.object(_grid_module._kernels, name, _refuse("tracing")))
            if IS_ROOT:
                stack.enter_context(mock.patch.object(tempfile, "mkstemp", mkstemp))
            yield
    finally:
        os.chdir(old)


@contextlib.contextmanager
def fresh_workdir():
    with tempfile.TemporaryDirectory(prefix="gridcal-bad-input-") as tmp:
        root = make_workdir(Path(tmp))
        try:
            yield root
        finally:
            (root / READ_ONLY_DIR).chmod(0o755)


@dataclass
class Outcome:
    code: int | None  # exit status (command line) or None (API)
    stdout: str
    stderr: str
    message: str  # the one line a user sees
    before: dict
    after: dict


def run_case(case: Case) -> Outcome:
    """Run one row in a fresh fixture directory; the API's exception becomes the message."""
    with fresh_workdir() as root:
        before = snapshot(root)
        out, err = io.StringIO(), io.StringIO()
        code = None
        with row_environment(root):
            if case.call is None:
                with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                    code = main(list(case.argv))
                message = err.getvalue().rstrip("\n")
            else:
                try:
                    case.call(root)
                except ValueError as exc:
                    message = f"{type(exc).__name__}: {exc}"
                else:
                    message = "(no error raised)"
        return Outcome(code, out.getvalue(), err.getvalue(), message, before, snapshot(root))


def console_command() -> list[str]:
    """The installed console script beside this Python, else ``python -m calibrate.cli``."""
    script = Path(sys.executable).with_name("calibrate")
    return [str(script)] if script.exists() else [sys.executable, "-m", "calibrate.cli"]


def run_console(case: Case) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO)] + [p for p in [os.environ.get("PYTHONPATH")] if p]))
    with fresh_workdir() as root:
        before = snapshot(root)
        proc = subprocess.run(console_command() + list(case.argv), cwd=root, env=env, capture_output=True,
                              text=True, timeout=120)
        proc.unchanged = snapshot(root) == before
    return proc


# ---------------------------------------------------------------------------------------
# docs
# ---------------------------------------------------------------------------------------

DOCS_HEAD = """# Bad input

Every mistake in what a user gives gridcal gets one clear line and changes nothing.
On the command line that line is `calibrate: error: ...` on stderr, the exit
status is 2, stdout stays empty and no traceback is printed; the Python API
raises `ValueError` (`calibrate._io.UserError` is one) with the same message.
Inputs and destinations are checked before anything is measured, fitted or
drawn, and files are written atomically, so a failure leaves no partial or
temporary file behind and an existing output file keeps its content.

The table below is every kind of bad input the test suite tries
(`tests/test_bad_input.py`), with the message each one gives today. It is
generated from the tests (`python tests/test_bad_input.py --write-docs`), and
a test fails when it is out of date. Paths are relative to the directory the
command ran in.
"""


DOCS_TAIL = """
## Beyond the table

The kernels meet random and degenerate input in two more ways, both in CI:

- property tests (`tests/test_properties.py`, hypothesis, derandomized): random
  meshes with zero-area, duplicate and lattice-aligned triangles at scales from
  1e-20 to 1e20, and rays along axes, along cell faces and aimed at vertices.
  The first hit through uniform and nested grids equals brute force's and never
  comes before it; building either succeeds or refuses the resolution with a
  one-line `ValueError`; per-ray counts stay within what the visited cells allow.
  One stated exception: Moller-Trumbore on a sliver triangle can report a hit
  outside the triangle's bounding box (its barycentrics are rounding noise), which
  brute force keeps and a grid may not see; the watertight intersector has none.
- a fuzz target (`tests/fuzz/fuzz_mesh.py`, atheris) that feeds arbitrary bytes to
  the OBJ, STL, PLY and OFF readers and arbitrary arrays to `Scene`, then builds
  grids and traces rays through what loads. `tests/test_fuzz.py` runs it for 15 s
  from the seed corpus in `tests/fuzz/corpus`; for a longer search:

      python tests/fuzz/fuzz_mesh.py NEW_INPUTS_DIR tests/fuzz/corpus -dict=tests/fuzz/mesh.dict -max_total_time=600
"""


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def docs_text() -> str:
    lines = [DOCS_HEAD.rstrip("\n")]
    section = None
    for case in CASES:
        if case.section != section:
            section = case.section
            lines += ["", f"## {section}", "", "| kind | input | message |", "|---|---|---|"]
        msg = run_case(case).message
        lines.append(f"| {_cell(case.kind)} | `{_cell(case.shown)}` | {_cell(msg)} |")
    return "\n".join(lines) + "\n" + DOCS_TAIL


# ---------------------------------------------------------------------------------------
# tests
# ---------------------------------------------------------------------------------------

try:
    import pytest
except ImportError:  # the docs generator runs without pytest
    pytest = None

if pytest is not None:

    @pytest.mark.parametrize("case", CASES, ids=[f"{i}-{c.id}" for i, c in enumerate(CASES)])
    def test_bad_input_gives_one_line_and_writes_nothing(case):
        got = run_case(case)
        if case.call is None:
            assert got.code == EXIT_USER_ERROR, f"exit status {got.code}; stderr: {got.stderr!r}"
            assert got.stdout == "", f"stdout must stay empty on an error, got {got.stdout!r}"
            assert got.stderr.startswith(ERROR_PREFIX), got.stderr
            assert got.stderr.count("\n") == 1 and got.stderr.endswith("\n"), f"not one line: {got.stderr!r}"
        else:
            assert got.message.startswith("ValueError: ") or got.message.startswith("UserError: "), got.message
            assert "\n" not in got.message, got.message
        assert "Traceback" not in got.stderr + got.message
        assert case.expect in got.message, f"expected {case.expect!r} in {got.message!r}"
        changed = sorted(k for k in set(got.before) | set(got.after) if got.before.get(k) != got.after.get(k))
        assert not changed, f"files added, changed or removed: {changed}"

    CONSOLE_CASES = [c for c in CASES if c.console]

    @pytest.mark.parametrize("case", CONSOLE_CASES, ids=[c.id for c in CONSOLE_CASES])
    def test_console_script_gives_one_line(case):
        proc = run_console(case)
        assert proc.returncode == EXIT_USER_ERROR, proc.stderr
        assert proc.stdout == ""
        assert proc.stderr.startswith(ERROR_PREFIX) and proc.stderr.count("\n") == 1, proc.stderr
        assert case.expect in proc.stderr and "Traceback" not in proc.stderr
        assert proc.unchanged, "the console script changed the directory's files"

    def registered_verbs() -> list[str]:
        for action in build_parser()._actions:
            if isinstance(action, argparse._SubParsersAction):
                return sorted(action.choices)
        raise AssertionError("the parser has no verbs")

    def test_every_verb_has_a_row():
        verbs = registered_verbs()
        assert {"run", "fit", "show", "scenes", "predict", "export"} <= set(verbs)
        missing = sorted(set(verbs) - {c.verb for c in CASES})
        assert not missing, f"verbs without a bad-input row in tests/test_bad_input.py: {missing}"

    def test_the_table_covers_the_issue():
        """At least 20 kinds, across the command line and the API."""
        kinds = {c.kind for c in CASES}
        assert len(kinds) >= 20
        assert any(c.call is None for c in CASES) and any(c.call is not None for c in CASES)

    def test_a_guard_catches_late_errors(tmp_path):
        """The rows' guard is live: work reached before an error fails the row."""
        with fresh_workdir() as root, row_environment(root):
            with pytest.raises(ReachedExpensiveWork):
                main(["fit", "good.json", "--out", "fresh.json", "--quiet"])

    def test_read_only_directory_is_enforced(tmp_path):
        """The fixture's read-only directory refuses a new file (really, or as a non-root user sees it)."""
        with fresh_workdir() as root, row_environment(root):
            with pytest.raises(PermissionError):
                fd, name = tempfile.mkstemp(dir=root / READ_ONLY_DIR)
                os.close(fd)
                os.unlink(name)

    def test_reader_log_records_stay_off_stderr(monkeypatch, capsys, caplog):
        """A mesh reader's log warnings do not add lines to a one-line error.

        Without logging configured (the command line), Python prints a warning record
        on stderr; under pytest the record would go to caplog instead, so both are checked.
        """
        import logging

        import trimesh

        def noisy_load(*args, **kwargs):
            logging.getLogger("trimesh").warning("PLY failed to populate: vertex")
            raise ValueError("PLY is unexpected length!")

        monkeypatch.setattr(trimesh, "load", noisy_load)
        with fresh_workdir() as root, row_environment(root):
            assert main(["predict", "cut_binary.ply", "--ratio", "1"]) == EXIT_USER_ERROR
        err = capsys.readouterr().err
        assert err.startswith(ERROR_PREFIX) and err.count("\n") == 1, err
        assert "failed to populate" not in err
        assert not [r for r in caplog.records if r.name.startswith("trimesh")], caplog.records

    def test_progress_is_drawn_only_on_a_terminal(monkeypatch):
        """A log file or a pipe gets no progress bar: stderr keeps warnings and errors only."""
        from calibrate import cli as cli_module

        err = io.StringIO()
        monkeypatch.setattr(sys, "stderr", err)
        with cli_module._Progress(True, "measuring") as bar:
            bar(1, 2, "label")
            bar.status("stage")
        assert not bar.enabled and err.getvalue() == ""
        err.isatty = lambda: True
        assert cli_module._Progress(True, "measuring").enabled

    def test_docs_are_current():
        assert DOCS.exists(), "docs/bad-input.md is missing: python tests/test_bad_input.py --write-docs"
        assert DOCS.read_text() == docs_text(), (
            "docs/bad-input.md is out of date: python tests/test_bad_input.py --write-docs")


if __name__ == "__main__":
    if sys.argv[1:] != ["--write-docs"]:
        sys.exit("usage: python tests/test_bad_input.py --write-docs")
    DOCS.write_text(docs_text())
    print(f"wrote {DOCS.relative_to(REPO)} ({len(CASES)} rows)")
