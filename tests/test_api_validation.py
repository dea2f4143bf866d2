"""Every bad input to the Python API raises ValueError with a message naming the problem.

Covers ``Scene(...)``, ``Scene.from_file``, ``Scene.load``, ``Grid.uniform``,
``Grid.nested`` and ``grid.intersect / count / bench``: wrong shapes, wrong
dtypes (strings, complex, objects, booleans), NaN/Inf vertices, out-of-range and
negative face indices, empty meshes, non-triangular faces, missing / directory /
empty / corrupt / truncated mesh files (OBJ, PLY, STL written to tmp_path),
unknown built-in names, bad resolutions, unknown intersectors, levels out of
range, bad subgrid resolutions, mismatched ray arrays, zero directions, NaN rays
and loops < 1; integers past what the kernel holds (threshold 2^32, memory_limit
and loops 2^63, rule_max_axis 2^31, uint64 face indices past 2^63), booleans and
strings where numbers or flags are expected, and huge values (the message stays
short).  Valid inputs of other dtypes (float32 vertices, int32 faces, lists,
Fortran order) are accepted and give the same hits as float64/int64.
"""

from __future__ import annotations

import os
import re
import reprlib

import numpy as np
import pytest

from calibrate._grid import MAX_LEVELS, Grid, Scene, brute_force, empty_grid
from calibrate.scenes import builtin_names, jittered_closed_mesh

#: A closed tetrahedron: 4 vertices (scene units), 4 outward triangles.
TETRA_VERTICES = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
TETRA_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=np.int64)
#: A valid OBJ file: one triangle.
GOOD_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
PLY_HEADER = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
              "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n")
#: Binary STL: 80-byte header, uint32 triangle count, 50 bytes per triangle.
STL_HEADER_BYTES = 80
STL_TRIANGLE_BYTES = 50


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(TETRA_VERTICES, TETRA_FACES, name="tetra")


@pytest.fixture(scope="module")
def grid(scene) -> Grid:
    return Grid.uniform(scene, (2, 2, 2))


def rays_inside(n: int, seed: int):
    """(n, 3) origins inside the tetrahedron and (n, 3) random unit directions."""
    rng = np.random.default_rng(seed)
    o = np.full((n, 3), 0.1) + 0.1 * rng.random((n, 3))
    d = rng.normal(size=(n, 3))
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


# ---------------------------------------------------------------------------------
# Scene(vertices, faces)
# ---------------------------------------------------------------------------------

V, F = TETRA_VERTICES, TETRA_FACES
BAD_MESHES = [
    # (label, vertices, faces, message pattern)
    ("vertices 1-D", V.ravel(), F, r"vertices must have shape \(V, 3\)"),
    ("vertices (V, 2)", V[:, :2], F, r"vertices must have shape \(V, 3\).*\(4, 2\)"),
    ("vertices (V, 4)", np.c_[V, V[:, :1]], F, r"vertices must have shape \(V, 3\)"),
    ("vertices 3-D", V[:, :, None], F, r"vertices must have shape"),
    ("vertices None", None, F, r"vertices must have shape"),
    ("vertices strings", V.astype(str), F, r"vertices must be numbers.*<U"),
    ("vertices letters", np.full((4, 3), "a"), F, r"vertices must be numbers"),
    ("vertices complex", V.astype(complex), F, r"vertices must be numbers.*complex"),
    ("vertices objects", np.array([[None] * 3] * 4), F, r"vertices must be numbers.*object"),
    ("vertices booleans", V.astype(bool), F, r"vertices must be numbers.*bool"),
    ("vertex NaN", np.where(np.arange(12).reshape(4, 3) == 4, np.nan, V), F, r"NaN or Inf.*vertex 1"),
    ("vertex +Inf", np.where(np.arange(12).reshape(4, 3) == 11, np.inf, V), F, r"NaN or Inf.*vertex 3"),
    ("vertex -Inf", np.where(np.arange(12).reshape(4, 3) == 0, -np.inf, V), F, r"NaN or Inf.*vertex 0"),
    ("unused vertex NaN", np.r_[V, [[np.nan, 0, 0]]], F, r"NaN or Inf.*vertex 4"),
    ("face index = V", V, np.r_[F, [[0, 1, 4]]], r"face 4 refers to vertex 4.*only 4 vertices"),
    ("face index >> V", V, np.r_[F, [[0, 1, 10**9]]], r"refers to vertex 1000000000"),
    ("negative face index", V, np.r_[F, [[0, -1, 2]]], r"face 4 has a negative vertex index -1"),
    ("faces (F, 4)", V, np.c_[F, F[:, :1]], r"triangles with 3 vertex indices each, got 4"),
    ("faces (F, 2)", V, F[:, :2], r"triangles with 3 vertex indices each, got 2"),
    ("faces 1-D", V, F.ravel(), r"faces must have shape \(F, 3\)"),
    ("faces 3-D", V, F[:, :, None], r"faces must have shape \(F, 3\)"),
    ("faces (0, 3)", V, np.zeros((0, 3), dtype=np.int64), r"mesh is empty: it has no faces"),
    ("faces []", V, [], r"faces must have shape \(F, 3\)"),
    ("no vertices", np.zeros((0, 3)), F, r"faces but no vertices"),
    ("faces fractional", V, F + 0.5, r"faces must be integer vertex indices.*float"),
    ("faces NaN", V, np.where(F == 3, np.nan, F.astype(float)), r"faces must be integer vertex indices"),
    ("faces strings", V, F.astype(str), r"faces must be integer vertex indices.*<U"),
    ("faces complex", V, F.astype(complex), r"faces must be integer vertex indices.*complex"),
    ("faces booleans", V, F.astype(bool), r"faces must be integer vertex indices.*bool"),
    ("faces beyond int64", V, [[0, 1, 2**70]], r"faces must be integer vertex indices"),
]


@pytest.mark.parametrize("label,vertices,faces,pattern", BAD_MESHES, ids=[m[0] for m in BAD_MESHES])
def test_scene_rejects_bad_mesh(label, vertices, faces, pattern):
    with pytest.raises(ValueError, match=pattern):
        Scene(vertices, faces)


def test_scene_rejects_box_too_wide_for_float64():
    """Coordinates of +-1e308: the box extent overflows to inf; refused, naming the box."""
    with pytest.raises(ValueError, match=r"box"):
        with np.errstate(over="ignore"):
            Scene([[0.0, 0.0, 0.0], [1e308, 0.0, 0.0], [-1e308, 1.0, 0.0]], [[0, 1, 2]])


def test_scene_ragged_vertices_message_names_vertices():
    with pytest.raises(ValueError, match=r"vertices"):
        Scene([[0.0, 0.0, 0.0], [1.0, 0.0], [0.0, 1.0, 0.0]], [[0, 1, 2]])


RANGE_AND_RAGGED_MESHES = [
    # (label, vertices, faces, message pattern): wrapped or unnamed before the check was added
    ("ragged vertices", [[0.0, 0.0, 0.0], [1.0, 0.0], [0.0, 1.0, 0.0]], [[0, 1, 2]],
     r"^vertices must have shape \(V, 3\), got rows of different lengths$"),
    ("ragged faces", V, [[0, 1, 2], [0, 1]], r"^faces must have shape \(F, 3\), got rows of different lengths$"),
    ("uint64 index 2^64 - 1", V, np.array([[0, 1, 2**64 - 1]], dtype=np.uint64),
     r"face 0 refers to vertex 18446744073709551615, but the mesh has only 4 vertices"),
    ("float index 2^63", V, np.array([[0.0, 1.0, 2.0**63]]), r"face 0 refers to vertex 9223372036854775808"),
    ("float index 1e30", V, np.r_[F, [[0, 1, 1e30]]].astype(float), r"face 4 refers to vertex 1000000000000000019884624838656"),
    ("float index -1e30", V, np.r_[F, [[-1e30, 1, 2]]].astype(float), r"face 4 has a negative vertex index -1000000000000000019884624838656"),
]


@pytest.mark.parametrize("label,vertices,faces,pattern", RANGE_AND_RAGGED_MESHES,
                         ids=[m[0] for m in RANGE_AND_RAGGED_MESHES])
def test_scene_ragged_and_huge_indices_are_named(label, vertices, faces, pattern):
    with pytest.raises(ValueError, match=pattern):
        Scene(vertices, faces)


def test_scene_huge_unsigned_face_index_is_named_out_of_range():
    with pytest.raises(ValueError, match=r"refers to vertex"):
        Scene(V, np.array([[0, 1, 2**63 + 5]], dtype=np.uint64))


# ---------------------------------------------------------------------------------
# accepted inputs of other dtypes and layouts
# ---------------------------------------------------------------------------------

ACCEPTED_MESHES = [
    ("float32 vertices", V.astype(np.float32), F),
    ("float16 vertices", V.astype(np.float16), F),
    ("int vertices", V.astype(np.int64), F),
    ("int32 faces", V, F.astype(np.int32)),
    ("uint16 faces", V, F.astype(np.uint16)),
    ("uint64 faces", V, F.astype(np.uint64)),
    ("whole-number float faces", V, F.astype(np.float64)),
    ("lists", V.tolist(), F.tolist()),
    ("tuples", tuple(map(tuple, V)), tuple(map(tuple, F))),
    ("Fortran order", np.asfortranarray(V), np.asfortranarray(F)),
    ("strided views", np.repeat(V, 2, axis=1)[:, ::2], np.repeat(F, 2, axis=1)[:, ::2]),
]


@pytest.mark.parametrize("case", range(len(ACCEPTED_MESHES)), ids=[m[0] for m in ACCEPTED_MESHES])
def test_scene_accepts_other_dtypes(case):
    """Other dtypes are converted to float64/int64 and trace exactly like the converted arrays."""
    label, vertices, faces = ACCEPTED_MESHES[case]
    s = Scene(vertices, faces)
    assert s.vertices.dtype == np.float64 and s.faces.dtype == np.int64
    assert s.vertices.flags.c_contiguous and s.faces.flags.c_contiguous
    ref = Scene(np.asarray(vertices).astype(np.float64), np.asarray(faces).astype(np.int64))
    assert np.array_equal(s.vertices, ref.vertices) and np.array_equal(s.faces, ref.faces)
    o, d = rays_inside(200, 4000 + case)
    t, prim = Grid.uniform(s, (3, 3, 3)).intersect(o, d)
    t_ref, p_ref = brute_force(ref, o, d)
    assert np.array_equal(t, t_ref) and np.array_equal(prim, p_ref)
    assert np.all(prim >= 0), f"{label}: rays from inside the closed tetrahedron must hit it"


def test_rays_accept_other_dtypes(grid):
    """Rays as lists, float32 and integers trace like their float64 conversion, in every entry point."""
    o, d = rays_inside(50, 4100)
    o32, d32 = o.astype(np.float32), d.astype(np.float32)
    t_ref, p_ref = grid.intersect(o32.astype(np.float64), d32.astype(np.float64))
    for oo, dd in ((o32, d32), (o32.tolist(), d32.tolist()), (np.asfortranarray(o32), np.asfortranarray(d32))):
        t, prim = grid.intersect(oo, dd)
        assert np.array_equal(t, t_ref) and np.array_equal(prim, p_ref)
        tc, pc, *_ = grid.count(oo, dd, hits=True)
        assert np.array_equal(tc, t_ref) and np.array_equal(pc, p_ref)
        elapsed_ns, checksum = grid.bench(oo, dd, loops=1)
        assert elapsed_ns >= 0 and np.isfinite(checksum)
    t, prim = grid.intersect([[0, 0, 0]], [[1, 1, 1]])  # integers
    assert t.dtype == np.float64 and prim.dtype == np.int32
    t, prim = grid.intersect(np.zeros((0, 3)), np.zeros((0, 3)))  # no rays is valid
    assert t.shape == (0,) and prim.shape == (0,)


def test_resolution_accepts_whole_numbers_of_any_type(scene):
    for res in [(2, 3, 4), [2, 3, 4], np.array([2, 3, 4]), (2.0, 3.0, 4.0), np.array([2, 3, 4], dtype=np.int32),
                np.array([2, 3, 4], dtype=np.uint64), np.array([2, 3, 4], dtype=np.float32), (np.int8(2), 3.0, np.int64(4))]:
        assert Grid.uniform(scene, res).resolution == (2, 3, 4)
        assert Grid.nested(scene, 2, res).resolution == (2, 3, 4)


# ---------------------------------------------------------------------------------
# Scene.from_file, Scene.load
# ---------------------------------------------------------------------------------

BAD_FILES = [
    # (file name, content, message pattern after the file name)
    ("empty.obj", "", r"the file is empty"),
    ("blank.obj", "\n\n   \n", r"holds no triangles"),
    ("comments.obj", "# nothing here\n", r"holds no triangles"),
    ("vertices_only.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n", r"holds no triangles"),
    ("garbage.obj", "hello world\nthis is not a mesh\n", r"holds no triangles"),
    ("bad_index.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n", r"line 4: face index 7 refers to no vertex"),
    ("nan.obj", "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n", r"NaN or Inf"),
    ("truncated_vertex.obj", "v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n", r"line 2: a vertex needs three coordinates"),
    ("truncated.ply", PLY_HEADER + "0 0 0\n1 0 0\n", r"holds no triangles|cannot read it as a mesh"),
    ("header_only.ply", "ply\nformat ascii 1.0\nelement vertex 3\n", r"cannot read it as a mesh"),
    ("bad_magic.ply", "plx\nformat ascii 1.0\nend_header\n", r"cannot read it as a mesh.*ply"),
    ("truncated_binary.stl",
     b"\0" * STL_HEADER_BYTES + (5).to_bytes(4, "little") + b"\0" * (STL_TRIANGLE_BYTES // 2),
     r"truncated binary STL: its header announces 5 triangles \(334 bytes\), but the file has 109 bytes"),
    ("no_triangles.stl", b"\0" * STL_HEADER_BYTES + (0).to_bytes(4, "little"), r"holds no triangles"),
    ("truncated_ascii.stl", "solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0\n",
     r"holds no triangles|cannot read it as a mesh"),
    ("no_extension", GOOD_OBJ, r"cannot read it as a mesh"),
    ("unknown.xyz", GOOD_OBJ, r"cannot read it as a mesh"),
]


@pytest.mark.parametrize("name,content,pattern", BAD_FILES, ids=[b[0] for b in BAD_FILES])
def test_from_file_rejects_corrupt_files(tmp_path, name, content, pattern):
    path = tmp_path / name
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    with pytest.raises(ValueError, match=re.escape(name) + r".*(" + pattern + ")"):
        Scene.from_file(path)
    with pytest.raises(ValueError, match=re.escape(name)):
        Scene.load(str(path))


def test_from_file_reads_good_files(tmp_path):
    """The same triangle as OBJ, ASCII PLY and ASCII STL loads as one triangle (control)."""
    files = {"t.obj": GOOD_OBJ, "t.ply": PLY_HEADER + "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
             "t.stl": ("solid t\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\n"
                       "endloop\nendfacet\nendsolid t\n")}
    for name, text in files.items():
        (tmp_path / name).write_text(text)
        s = Scene.from_file(tmp_path / name)
        assert s.n_triangles == 1 and s.name == name
        assert np.array_equal(np.sort(s.vertices[s.faces[0]], axis=0),
                              np.sort(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), axis=0))
        assert Scene.load(str(tmp_path / name)).n_triangles == 1


def test_from_file_missing_file_and_directory(tmp_path):
    with pytest.raises(ValueError, match=r"nope\.obj: no such file"):
        Scene.from_file(tmp_path / "nope.obj")
    with pytest.raises(ValueError, match=r"is a directory, not a mesh file"):
        Scene.from_file(tmp_path)
    with pytest.raises(ValueError, match=r"nope\.obj: no such file"):
        Scene.load(str(tmp_path / "nope.obj"))
    with pytest.raises(ValueError, match=r"is a directory"):
        Scene.load(str(tmp_path))


@pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() == 0, reason="root can read a file with mode 000")
def test_from_file_unreadable(tmp_path):
    path = tmp_path / "locked.obj"
    path.write_text(GOOD_OBJ)
    path.chmod(0)
    try:
        with pytest.raises(ValueError, match=r"locked\.obj: not readable"):
            Scene.from_file(path)
    finally:
        path.chmod(0o600)


def test_from_file_none_is_a_value_error():
    with pytest.raises(ValueError, match=r"path|file"):
        Scene.from_file(None)


@pytest.mark.parametrize("path", [None, 123, 1.5, b"mesh.obj", ["mesh.obj"]])
def test_from_file_rejects_a_non_path(path):
    with pytest.raises(ValueError, match=r"^path must be a mesh file's path \(str or os.PathLike\), got "):
        Scene.from_file(path)


def test_from_file_name_too_long_for_the_file_system(tmp_path):
    """A 5000-character name: stat fails with ENAMETOOLONG, which is refused as a ValueError naming the file."""
    with pytest.raises(ValueError, match=r"x{100}\.obj: cannot access it"):
        Scene.from_file(tmp_path / ("x" * 5000 + ".obj"))


@pytest.mark.parametrize("name", ["spherez", "Sphere", "cylinder", "cylinder197", "room2", "none"])
def test_load_unknown_builtin_lists_the_valid_names(name):
    with pytest.raises(ValueError, match=re.escape(repr(name)) + r" is neither a mesh file nor a built-in scene"):
        Scene.load(name)
    with pytest.raises(ValueError, match=r"unknown built-in scene.*" + re.escape(", ".join(builtin_names()))):
        Scene.builtin(name)


def test_load_path_like_name_that_does_not_exist():
    with pytest.raises(ValueError, match=r"sphere\.obj: no such file"):
        Scene.load("sphere.obj")


def test_load_builtin_and_scene_pass_through():
    s = Scene.load("cylinder196")
    assert s.n_triangles == 196 and Scene.load(s) is s


# ---------------------------------------------------------------------------------
# Grid.uniform, Grid.nested
# ---------------------------------------------------------------------------------

BAD_RESOLUTIONS = [
    ((0, 1, 1), r"resolution 0x1x1: every axis needs at least 1 cell"),
    ((2, 0, 2), r"every axis needs at least 1 cell"),
    ((-1, 2, 2), r"resolution -1x2x2: every axis needs at least 1 cell"),
    ((1.5, 2, 2), r"three whole numbers"),
    ((2, 2, 2.0000001), r"three whole numbers"),
    ((2, 2), r"three whole numbers"),
    ((2, 2, 2, 2), r"three whole numbers"),
    (2, r"three whole numbers"),
    ("abc", r"three whole numbers"),
    (None, r"three whole numbers"),
    ((float("nan"), 1, 1), r"three whole numbers"),
    ((float("inf"), 1, 1), r"three whole numbers"),
    ((complex(2, 0), 1, 1), r"three whole numbers"),
    ((2**31, 1, 1), r"an axis exceeds 2\^31 - 1 cells"),
    ((2**40, 1, 1), r"an axis exceeds 2\^31 - 1 cells"),
    ((65536, 65536, 2), r"65536x65536x2 .*overflows the grid's 32-bit cell offsets"),
    ((2**31 - 1,) * 3, r"overflows the grid's 32-bit cell offsets"),
    ((1, 1, 2**31 - 1), r"over the memory limit"),
    ((True, True, True), r"three whole numbers"),
    ((2, 2, np.True_), r"three whole numbers"),
    (np.array([True, True, True]), r"three whole numbers"),
    (("2", "2", "2"), r"three whole numbers"),
    ("222", r"three whole numbers"),
    (np.array(["2", "2", "2"]), r"three whole numbers"),
    ((b"2", 2, 2), r"three whole numbers"),
    ((1e300, 1, 1), r"^resolution 1e\+300x1x1: an axis exceeds 2\^31 - 1 cells$"),
    ((1, 10**300, 1), r"^resolution 1x1e\+300x1: an axis exceeds 2\^31 - 1 cells$"),
    ((1, 1, -1e300), r"^resolution 1x1x-1e\+300: every axis needs at least 1 cell$"),
    ((2**40, 3, 3), r"^resolution 1\.09e\+12x3x3: an axis exceeds"),
]


@pytest.mark.parametrize("resolution,pattern", BAD_RESOLUTIONS, ids=[reprlib.repr(r[0]) for r in BAD_RESOLUTIONS])
def test_uniform_and_nested_reject_bad_resolution(scene, resolution, pattern):
    with pytest.raises(ValueError, match=pattern):
        Grid.uniform(scene, resolution)
    if resolution is not None:  # for Grid.nested, None asks for the rule's top resolution
        with pytest.raises(ValueError, match=pattern):
            Grid.nested(scene, 2, resolution)


BAD_BUILD_OPTIONS = [
    # (label, keyword arguments for Grid.uniform, message pattern)
    ("unknown intersector", dict(intersector="embree"), r"unknown intersector 'embree'; choose one of watertight"),
    ("intersector None", dict(intersector=None), r"unknown intersector None"),
    ("intersector number", dict(intersector=1), r"unknown intersector 1"),
    ("unknown insertion", dict(insertion="sloppy"), r"unknown insertion 'sloppy'; choose one of exact, bounds"),
    ("memory limit 0", dict(memory_limit=0), r"memory_limit \(bytes\) must be a whole number from 1 to 2\^63 - 1, got 0$"),
    ("memory limit < 0", dict(memory_limit=-1), r"memory_limit \(bytes\) must be a whole number from 1"),
    ("memory limit fractional", dict(memory_limit=1.5), r"memory_limit \(bytes\) must be a whole number from 1"),
    ("memory limit too small", dict(memory_limit=64), r"over the memory limit"),
    ("memory limit 2^63", dict(memory_limit=2**63), r"memory_limit \(bytes\) must be a whole number.*got 9223372036854775808$"),
    ("memory limit uint64 2^63", dict(memory_limit=np.uint64(2**63)), r"memory_limit \(bytes\) must be a whole number"),
    ("memory limit True", dict(memory_limit=True), r"memory_limit \(bytes\) must be a whole number.*got True$"),
    ("memory limit np.True_", dict(memory_limit=np.True_), r"memory_limit \(bytes\) must be a whole number"),
    ("memory limit string", dict(memory_limit="1000000"), r"memory_limit \(bytes\) must be a whole number"),
    ("mailbox string", dict(mailbox="no"), r"^mailbox must be True or False, got 'no'$"),
    ("mailbox 1", dict(mailbox=1), r"^mailbox must be True or False, got 1$"),
    ("mailbox None", dict(mailbox=None), r"^mailbox must be True or False, got None$"),
    ("insertion list", dict(insertion=["exact"]), r"unknown insertion \['exact'\]; choose one of exact, bounds"),
    ("threads 0", dict(threads=0), r"^threads must be a whole number from 1 to 64, got 0$"),
    ("threads 65", dict(threads=65), r"^threads must be a whole number from 1 to 64, got 65$"),
    ("threads fractional", dict(threads=1.5), r"^threads must be a whole number from 1 to 64, got 1.5$"),
    ("threads True", dict(threads=True), r"^threads must be a whole number from 1 to 64, got True$"),
    ("threads None", dict(threads=None), r"^threads must be a whole number from 1 to 64, got None$"),
]


@pytest.mark.parametrize("label,kwargs,pattern", BAD_BUILD_OPTIONS, ids=[b[0] for b in BAD_BUILD_OPTIONS])
def test_uniform_rejects_bad_options(scene, label, kwargs, pattern):
    with pytest.raises(ValueError, match=pattern):
        Grid.uniform(scene, (2, 2, 2), **kwargs)
    with pytest.raises(ValueError, match=pattern):
        Grid.nested(scene, 2, (2, 2, 2), **kwargs)


@pytest.mark.parametrize("levels", [1, 2])
def test_build_threads_give_the_same_grid(levels):
    """The build's parts (2 and 3 threads, 40,000 triangles: several parts) join into the
    grid one thread builds: same counts per cell and same first hits (the C tests
    compare the grids byte for byte)."""
    v, f = jittered_closed_mesh(levels, frequency=45)  # 40,500 triangles
    scene = Scene(v, f, name="jittered")
    rng = np.random.default_rng(levels)
    o = rng.normal(size=(3000, 3)) * 3.0
    d = rng.uniform(-0.5, 0.5, size=(3000, 3)) - o
    grids = [Grid.nested(scene, levels, (23, 19, 31), threads=t) for t in (1, 2, 3)]
    first = grids[0]
    t0, p0 = first.intersect(o, d)
    assert np.isfinite(t0).sum() > 1000
    for g in grids[1:]:
        assert g.info == first.info
        np.testing.assert_array_equal(g.top_counts(), first.top_counts())
        t, p = g.intersect(o, d)
        np.testing.assert_array_equal(t, t0)
        np.testing.assert_array_equal(p, p0)


def test_grid_rejects_a_non_scene():
    with pytest.raises(ValueError, match=r"scene must be a calibrate.Scene, got tuple"):
        Grid.uniform((TETRA_VERTICES, TETRA_FACES), (2, 2, 2))
    with pytest.raises(ValueError, match=r"scene must be a calibrate.Scene, got tuple"):
        Grid.nested((TETRA_VERTICES, TETRA_FACES), 2, (2, 2, 2))


@pytest.mark.parametrize("levels", [0, -1, MAX_LEVELS + 1, 100, 1.5, 2.0, "2", None, True, np.True_, 2**64])
def test_nested_rejects_levels_out_of_range(scene, levels):
    with pytest.raises(ValueError, match=rf"levels must be a whole number from 1 to {MAX_LEVELS}"):
        Grid.nested(scene, levels)


def test_nested_accepts_every_level_in_range(scene):
    for levels in range(1, MAX_LEVELS + 1):
        g = Grid.nested(scene, levels, (2, 2, 2), threshold=0)
        assert 1 <= g.info["levels"] <= levels


BAD_NESTED_OPTIONS = [
    ("scale 0", dict(scale=0), r"scale must be a positive number, got 0"),
    ("scale < 0", dict(scale=-8.0), r"scale must be a positive number"),
    ("scale NaN", dict(scale=float("nan")), r"scale must be a positive number"),
    ("scale Inf", dict(scale=float("inf")), r"scale must be a positive number"),
    ("scale string", dict(scale="8"), r"scale must be a positive number"),
    ("threshold < 0", dict(threshold=-1), r"threshold must be a whole number from 0 to 2\^32 - 2, got -1$"),
    ("threshold fractional", dict(threshold=1.5), r"threshold must be a whole number from 0 to 2\^32 - 2"),
    ("exponents too few", dict(exponents=[1.0]), r"exponents needs 2 positive numbers, one per level"),
    ("exponents too many", dict(exponents=[1.0, 1.0, 1.0]), r"exponents needs 2 positive numbers"),
    ("exponents negative", dict(exponents=[1.0, -1.0]), r"exponents needs 2 positive numbers"),
    ("exponents NaN", dict(exponents=[1.0, float("nan")]), r"exponents needs 2 positive numbers"),
    ("rule_max_axis 0", dict(rule_max_axis=0), r"rule_max_axis must be a whole number from 1 to 2\^31 - 1, got 0$"),
    ("rule_max_axis < 0", dict(rule_max_axis=-5), r"rule_max_axis must be a whole number from 1 to 2\^31 - 1"),
    ("rule_max_axis 2^31", dict(rule_max_axis=2**31), r"rule_max_axis must be a whole number.*got 2147483648$"),
    ("rule_max_axis True", dict(rule_max_axis=True), r"rule_max_axis must be a whole number.*got True$"),
    ("rule_max_axis None", dict(rule_max_axis=None), r"rule_max_axis must be a whole number.*got None$"),
    ("threshold 2^32 - 1", dict(threshold=2**32 - 1), r"threshold must be a whole number.*got 4294967295$"),
    ("threshold 2^64", dict(threshold=2**64), r"threshold must be a whole number from 0 to 2\^32 - 2"),
    ("threshold True", dict(threshold=True), r"threshold must be a whole number.*got True$"),
    ("threshold False", dict(threshold=False), r"threshold must be a whole number.*got False$"),
    ("threshold string", dict(threshold="2"), r"threshold must be a whole number.*got '2'$"),
    ("scale True", dict(scale=True), r"scale must be a positive number, got True$"),
    ("scale huge int", dict(scale=10**400), r"scale must be a positive number"),
    ("exponents a string", dict(exponents="ab"), r"exponents needs 2 positive numbers, one per level, got 'ab'$"),
    ("exponents a number", dict(exponents=2.0), r"exponents needs 2 positive numbers, one per level, got 2\.0$"),
    ("exponents digit strings", dict(exponents=["1", "1"]), r"exponents needs 2 positive numbers"),
    ("exponents booleans", dict(exponents=[True, True]), r"exponents needs 2 positive numbers"),
    ("exponents huge int", dict(exponents=[1.0, 10**400]), r"exponents needs 2 positive numbers"),
    ("exponents Inf", dict(exponents=[1.0, float("inf")]), r"exponents needs 2 positive numbers"),
]


@pytest.mark.parametrize("label,kwargs,pattern", BAD_NESTED_OPTIONS, ids=[b[0] for b in BAD_NESTED_OPTIONS])
def test_nested_rejects_bad_options(scene, label, kwargs, pattern):
    with pytest.raises(ValueError, match=pattern):
        Grid.nested(scene, 2, **kwargs)


def test_nested_huge_threshold_does_not_wrap(scene):
    v, f = jittered_closed_mesh(0)
    big = Scene(v, f)
    try:
        g = Grid.nested(big, 2, (6, 6, 6), threshold=2**32)
    except ValueError as exc:
        assert "threshold" in str(exc)
    else:
        assert g.info["levels"] == 1, "no cell holds more than 2^32 references, so none may get a subgrid"


def test_memory_limit_beyond_64_bits_does_not_wrap(scene):
    try:
        g = Grid.uniform(scene, (2, 2, 2), memory_limit=2**64 + 100)
    except ValueError as exc:
        assert "memory_limit" in str(exc), f"refused without naming memory_limit: {exc}"
    else:
        assert g.info["n_triangles"] == 4


@pytest.mark.parametrize("value", [1.5, "a", 2**40])
def test_nested_rule_max_axis_is_validated(scene, value):
    with pytest.raises(ValueError, match=r"rule_max_axis"):
        Grid.nested(scene, 2, rule_max_axis=value)


def test_nested_exponents_strings_named(scene):
    with pytest.raises(ValueError, match=r"exponents"):
        Grid.nested(scene, 2, exponents=["a", "b"])


@pytest.fixture(scope="module")
def dense_scene() -> Scene:
    """1280 triangles: a (6, 6, 6) top level has cells holding more than 2 references."""
    v, f = jittered_closed_mesh(0)
    return Scene(v, f, name="jittered")


def test_nested_extreme_whole_numbers_take_effect(dense_scene):
    """The largest threshold and the smallest rule_max_axis reach the kernel unwrapped.

    Control: threshold 0 subdivides (2 levels).  threshold 2^32 - 2 subdivides no cell, and
    rule_max_axis 1 makes every subgrid 1x1x1, which is not built (1 level); a value wrapped
    or truncated on the way (2^32 - 2 to a small number) would give 2 levels again.
    """
    res = (6, 6, 6)
    assert Grid.nested(dense_scene, 2, res, threshold=0).info["levels"] == 2
    assert Grid.nested(dense_scene, 2, res, threshold=np.uint32(0), rule_max_axis=2**31 - 1).info["levels"] == 2
    assert Grid.nested(dense_scene, 2, res, threshold=2**32 - 2).info["levels"] == 1
    assert Grid.nested(dense_scene, 2, res, threshold=np.int64(2**32 - 2)).info["levels"] == 1
    assert Grid.nested(dense_scene, 2, res, threshold=0, rule_max_axis=1).info["levels"] == 1
    assert Grid.nested(dense_scene, 2, res, threshold=0, rule_max_axis=np.int16(1)).info["levels"] == 1


def test_memory_limit_accepts_the_largest_value_and_numpy_integers(scene):
    for limit in (2**63 - 1, np.uint64(2**63 - 1), np.int64(10**9)):
        g = Grid.uniform(scene, (2, 2, 2), memory_limit=limit)
        assert g.info["n_triangles"] == 4
    with pytest.raises(ValueError, match=r"over the memory limit"):
        Grid.uniform(scene, (2, 2, 2), memory_limit=np.uint64(64))


def test_numpy_flags_and_numbers_act_like_python_ones(dense_scene):
    """np.bool_ flags, numpy numbers for scale and exponents and an exponents array build the same grid."""
    res = (4, 4, 4)
    ref = Grid.nested(dense_scene, 2, res, scale=4.0, exponents=[1.0, 0.5], mailbox=True)
    same = Grid.nested(dense_scene, 2, res, scale=np.float32(4.0), exponents=np.array([1.0, 0.5]), mailbox=np.True_)
    assert same.info == ref.info and same.options["mailbox"] is True
    other = Grid.nested(dense_scene, 2, res, scale=8.0, exponents=[1.0, 0.5])
    assert other.info["n_cells"] != ref.info["n_cells"], "control: the scale must change the subgrids"
    o, d = rays_inside(20, 4300)
    steps_ref, _, _ = ref.count(o, d, hits=np.False_)
    t, prim, steps, _, _ = same.count(o, d, hits=np.True_)
    assert np.array_equal(steps, steps_ref) and t.shape == prim.shape == (20,)


@pytest.mark.parametrize("hits", ["no", 1, None])
def test_count_rejects_a_non_bool_hits(grid, hits):
    with pytest.raises(ValueError, match=r"^hits must be True or False, got "):
        grid.count(O3, D3, hits=hits)


@pytest.mark.parametrize("resolution,value", [((1e300, 1, 1), "1e+300"), ((10**400, 2, 2), "1e+400"),
                                              ((2, 2, -10**1000), "-1e+1000"), (list(range(10**4)), "...")],
                         ids=["1e300", "10**400", "-10**1000", "10**4 entries"])
def test_huge_resolution_message_is_short(scene, resolution, value):
    """A 1e300 axis is printed as 1e+300, not as its 301 digits; a long list is cut."""
    for build in (lambda: Grid.uniform(scene, resolution), lambda: empty_grid([0, 0, 0], [1, 1, 1], resolution)):
        with pytest.raises(ValueError, match=r"resolution") as info:
            build()
        message = str(info.value)
        assert value in message and len(message) < 100 and "\n" not in message, message


@pytest.mark.parametrize("kwargs", [dict(memory_limit=10**400), dict(threshold=-10**400),
                                    dict(rule_max_axis=10**400), dict(levels=10**400), dict(exponents=[10**400] * 2)],
                         ids=["memory_limit", "threshold", "rule_max_axis", "levels", "exponents"])
def test_huge_option_message_is_short(scene, kwargs):
    (name, _), = kwargs.items()
    with pytest.raises(ValueError, match=name) as info:
        Grid.nested(scene, **({"levels": 2} | kwargs))
    assert len(str(info.value)) < 160, str(info.value)


def subgrid_cases():
    ncell = 8  # top level (2, 2, 2)
    ones = np.ones((ncell, 3), dtype=np.int64)
    return [
        ("too few rows", ones[:7], 2, r"shape \(8, 3\), one row per top-level cell, got \(7, 3\)"),
        ("too many rows", np.ones((9, 3), dtype=np.int64), 2, r"shape \(8, 3\).*got \(9, 3\)"),
        ("two columns", ones[:, :2], 2, r"shape \(8, 3\).*got \(8, 2\)"),
        ("flat", ones.ravel(), 2, r"shape \(8, 3\).*got \(24,\)"),
        ("float", ones.astype(float), 2, r"whole numbers of shape \(8, 3\).*float64"),
        ("bool", ones.astype(bool), 2, r"whole numbers of shape \(8, 3\).*bool"),
        ("strings", ones.astype(str), 2, r"whole numbers of shape \(8, 3\)"),
        ("negative", -ones, 2, r"between 0 \(no subgrid\) and 2\^31 - 1"),
        ("huge", np.full((ncell, 3), 2**31, dtype=np.int64), 2, r"between 0 \(no subgrid\) and 2\^31 - 1"),
        ("mixed zero axes", np.r_[[[1, 0, 1]], ones[1:]], 2, r"row 0 mixes zero and non-zero axes"),
        ("ragged", [[1, 1, 1]] * 7 + [[1, 1]], 2, r"^subgrid_resolutions must have shape \(8, 3\), got rows of different lengths$"),
        ("levels 1", ones, 1, r"subgrid_resolutions needs levels >= 2"),
        ("cells overflow", np.full((ncell, 3), 2048, dtype=np.int64), 2, r"overflows the grid's 32-bit cell offsets"),
    ]


@pytest.mark.parametrize("label,sub,levels,pattern", subgrid_cases(), ids=[c[0] for c in subgrid_cases()])
def test_nested_rejects_bad_subgrid_resolutions(scene, label, sub, levels, pattern):
    with pytest.raises(ValueError, match=pattern):
        Grid.nested(scene, levels, (2, 2, 2), subgrid_resolutions=sub)


def subgrid2_cases():
    sub = np.ones((8, 3), dtype=np.int64)  # top (2, 2, 2): eight 1x1x1 subgrids, eight rows
    sub[0] = (2, 1, 1)  # ... and the first two cells: nine rows
    ones = np.ones((9, 3), dtype=np.int64)
    return [
        ("without a depth-1 table", None, ones, 3, r"subgrid_resolutions2 needs subgrid_resolutions and levels >= 3"),
        ("two levels", sub, ones, 2, r"subgrid_resolutions2 needs subgrid_resolutions and levels >= 3"),
        ("a row short", sub, ones[:8], 3, r"shape \(9, 3\), one row per cell of the depth-1 subgrids, got \(8, 3\)"),
        ("a row over", sub, np.ones((10, 3), dtype=np.int64), 3, r"shape \(9, 3\).*got \(10, 3\)"),
        ("float", sub, ones.astype(float), 3, r"whole numbers of shape \(9, 3\).*float64"),
        ("negative", sub, -ones, 3, r"between 0 \(no subgrid\) and 2\^31 - 1"),
        ("mixed zero axes", sub, np.r_[ones[:4], [[0, 2, 2]], ones[5:]], 3, r"row 4 mixes zero and non-zero axes"),
        ("ragged", sub, [[1, 1, 1]] * 8 + [[1, 1]], 3, r"^subgrid_resolutions2 must have shape \(9, 3\), got rows of different lengths$"),
    ]


@pytest.mark.parametrize("label,sub,sub2,levels,pattern", subgrid2_cases(), ids=[c[0] for c in subgrid2_cases()])
def test_nested_rejects_bad_subgrid_resolutions2(scene, label, sub, sub2, levels, pattern):
    with pytest.raises(ValueError, match=pattern):
        Grid.nested(scene, levels, (2, 2, 2), subgrid_resolutions=sub, subgrid_resolutions2=sub2)


def test_nested_builds_both_tables_cell_for_cell(scene):
    sub = np.ones((8, 3), dtype=np.int64)
    sub[0] = (2, 1, 1)
    sub[3] = 0  # a leaf list: no rows for it
    sub2 = np.zeros((8, 3), dtype=np.int64)
    sub2[1] = (2, 2, 3)
    sub2[7] = (1, 4, 1)
    g = Grid.nested(scene, 3, (2, 2, 2), subgrid_resolutions=sub, subgrid_resolutions2=sub2)
    assert g.info["n_nodes"] == 1 + 7 + 2
    assert g.info["n_cells"] == 8 + 8 + 12 + 4
    assert g.info["levels"] == 3


def test_nested_accepts_subgrid_resolutions_as_lists_and_small_ints(scene):
    for sub in ([[2, 1, 3]] * 8, np.full((8, 3), 2, dtype=np.int8), np.zeros((8, 3), dtype=np.int32)):
        g = Grid.nested(scene, 2, (2, 2, 2), subgrid_resolutions=sub)
        assert g.info["levels"] == (1 if np.all(np.asarray(sub) == 0) else 2)


def test_empty_grid_overflow_is_a_value_error():
    with pytest.raises(ValueError, match=r"overflow"):
        empty_grid([0.0, 0.0, 0.0], [1.0, 1.0, 1.0], (65536, 65536, 2))
    with pytest.raises(ValueError, match=r"cannot build the grid: .*65536x65536x2 .*overflows the grid's 32-bit cell offsets"):
        empty_grid([0.0, 0.0, 0.0], [1.0, 1.0, 1.0], (65536, 65536, 2))


@pytest.mark.parametrize("lo,hi,pattern", [
    (["a", 0, 0], [1, 1, 1], r"^box_lo must be numbers \(x, y, z\), got \['a', 0, 0\]$"),
    ([0, 0, 0], [1, 1, None], r"^box_hi must be numbers \(x, y, z\)"),
    ([0, 0, 0], [[1, 1], [1]], r"^box_hi must have shape \(3,\), got rows of different lengths$"),
], ids=["string in box_lo", "None in box_hi", "ragged box_hi"])
def test_empty_grid_names_a_bad_box_corner(lo, hi, pattern):
    with pytest.raises(ValueError, match=pattern):
        empty_grid(lo, hi, (2, 2, 2))


def test_empty_grid_accepts_integer_and_float32_corners():
    a = empty_grid(np.array([0, 0, 0]), np.array([2, 2, 2], dtype=np.float32), (2, 2, 2))
    b = empty_grid([0.0, 0.0, 0.0], [2.0, 2.0, 2.0], (2, 2, 2))
    assert a.info == b.info


@pytest.mark.parametrize("lo,hi,res,pattern", [
    ([1, 1, 1], [0, 0, 0], (2, 2, 2), r"hi > lo on every axis"),
    ([0, 0, 0], [0, 1, 1], (2, 2, 2), r"hi > lo on every axis"),
    ([np.nan, 0, 0], [1, 1, 1], (2, 2, 2), r"finite bounds"),
    ([0, 0], [1, 1], (2, 2, 2), r"box_lo must have shape \(3,\), got \(2,\)"),
    ([0, 0], [1, 1, 1, 1], (2, 2, 2), r"box_lo must have shape \(3,\), got \(2,\)"),
    ([0, 0, 0], [[1, 1, 1]], (2, 2, 2), r"box_hi must have shape \(3,\), got \(1, 3\)"),
    (0, [1, 1, 1], (2, 2, 2), r"box_lo must have shape \(3,\), got \(\)"),
    ([0, 0, 0], [1, 1, 1], (0, 2, 2), r"every axis needs at least 1 cell"),
])
def test_empty_grid_rejects_bad_box_and_resolution(lo, hi, res, pattern):
    with pytest.raises(ValueError, match=pattern):
        empty_grid(lo, hi, res)


# ---------------------------------------------------------------------------------
# grid.intersect, grid.count, grid.bench
# ---------------------------------------------------------------------------------

O3, D3 = rays_inside(3, 4200)


def bad_rays():
    nan_o = O3.copy()
    nan_o[1, 2] = np.nan
    inf_d = D3.copy()
    inf_d[2, 0] = -np.inf
    zero_d = D3.copy()
    zero_d[1] = 0.0
    neg_zero_d = D3.copy()
    neg_zero_d[0] = [-0.0, 0.0, -0.0]
    return [
        ("different lengths", O3, D3[:2], r"origins and directions differ in length: 3 and 2 rays"),
        ("zero direction", O3, zero_d, r"1 rays have a zero direction \(first: ray 1\)"),
        ("-0.0 direction", O3, neg_zero_d, r"1 rays have a zero direction \(first: ray 0\)"),
        ("NaN origin", nan_o, D3, r"origins of 1 rays contain NaN or Inf \(first: ray 1\)"),
        ("NaN direction", O3, np.where(np.isnan(nan_o), np.nan, D3), r"directions of 1 rays contain NaN or Inf"),
        ("Inf direction", O3, inf_d, r"directions of 1 rays contain NaN or Inf \(first: ray 2\)"),
        ("1-D origins", O3[0], D3[0], r"origins must have shape \(n, 3\), got \(3,\)"),
        ("(n, 2) directions", O3, D3[:, :2], r"directions must have shape \(n, 3\), got \(3, 2\)"),
        ("3-D origins", O3[:, None, :], D3, r"origins must have shape \(n, 3\)"),
        ("None", None, None, r"origins must have shape \(n, 3\)"),
        ("string origins", O3.astype(str), D3, r"origins must be numbers"),
        ("complex directions", O3, D3.astype(complex), r"directions must be numbers.*complex"),
        ("object origins", np.array([[None] * 3]), D3[:1], r"origins must be numbers.*object"),
        ("bool directions", O3, D3 > 0, r"directions must be numbers.*bool"),
    ]


@pytest.mark.parametrize("method", ["intersect", "count", "bench", "timed_batch"])
@pytest.mark.parametrize("label,origins,directions,pattern", bad_rays(), ids=[b[0] for b in bad_rays()])
def test_tracing_rejects_bad_rays(grid, scene, method, label, origins, directions, pattern):
    with pytest.raises(ValueError, match=pattern):
        getattr(grid, method)(origins, directions)
    if method == "intersect":
        with pytest.raises(ValueError, match=pattern):
            brute_force(scene, origins, directions)


def test_nested_grid_tracing_rejects_bad_rays(scene):
    g = Grid.nested(scene, 3, (2, 2, 2), threshold=0, mailbox=True)
    with pytest.raises(ValueError, match=r"zero direction"):
        g.count(O3, np.zeros((3, 3)), hits=True)
    with pytest.raises(ValueError, match=r"differ in length"):
        g.intersect(O3, D3[:1])


@pytest.mark.parametrize("loops", [0, -1, 1.5, "2", None, 2.0, True, np.True_, 2**63, 2**64, np.uint64(2**63)])
def test_bench_rejects_bad_loops(grid, loops):
    with pytest.raises(ValueError, match=r"loops must be a whole number from 1 to 2\^63 - 1"):
        grid.bench(O3, D3, loops=loops)
    with pytest.raises(ValueError, match=r"loops must be a whole number from 1 to 2\^63 - 1"):
        grid.timed_batch(O3, D3)(loops)


def test_bench_loops_beyond_int64(grid):
    with pytest.raises(ValueError, match=r"loops"):
        grid.bench(O3, D3, loops=2**63)


def test_bench_accepts_numpy_integer_loops(grid):
    elapsed_ns, checksum = grid.bench(O3, D3, loops=np.int64(2))
    t, prim = grid.intersect(O3, D3)
    one = float(np.sum(np.where(prim >= 0, t + prim, -1.0)))
    assert elapsed_ns >= 0 and checksum == pytest.approx(2 * one, rel=1e-12)


def test_timed_batch_thread_clock_counts_the_same_work(grid):
    """The thread clock times the same loop: same checksum, and a single thread's CPU
    time cannot exceed the wall time around it."""
    import time

    run_wall, run_thread = grid.timed_batch(O3, D3), grid.timed_batch(O3, D3, clock="thread")
    t0 = time.perf_counter_ns()
    elapsed, checksum = run_thread(50_000)
    wall = time.perf_counter_ns() - t0
    assert 0 < elapsed <= wall + 1_000_000  # the thread clock may tick in steps of up to 1 ms
    assert checksum == run_wall(50_000)[1]


@pytest.mark.parametrize("clock", ["cpu", "", None, 1])
def test_timed_batch_rejects_unknown_clock(grid, clock):
    with pytest.raises(ValueError, match=r"clock must be one of wall, thread"):
        grid.timed_batch(O3, D3, clock=clock)


@pytest.mark.parametrize("ragged", ["origins", "directions"])
def test_ragged_rays_are_named(grid, scene, ragged):
    rows = [[0.1, 0.1, 0.1], [0.2, 0.2]]
    o, d = (rows, D3[:2]) if ragged == "origins" else (O3[:2], rows)
    pattern = rf"^{ragged} must have shape \(n, 3\), got rows of different lengths$"
    for trace in (grid.intersect, grid.count, grid.bench, lambda o, d: brute_force(scene, o, d)):
        with pytest.raises(ValueError, match=pattern):
            trace(o, d)


@pytest.mark.parametrize("not_a_scene", [(TETRA_VERTICES, TETRA_FACES), None, "cylinder196"])
def test_brute_force_rejects_a_non_scene(not_a_scene):
    with pytest.raises(ValueError, match=rf"^scene must be a calibrate.Scene, got {type(not_a_scene).__name__}$"):
        brute_force(not_a_scene, O3, D3)


def test_brute_force_rejects_unknown_intersector(scene):
    with pytest.raises(ValueError, match=r"unknown intersector 'fast'"):
        brute_force(scene, O3, D3, "fast")


def test_scene_and_kernel_refuse_a_box_whose_extent_overflows_on_every_axis():
    """+-1.7e308 on all three axes: no axis is thin, so nothing widened the box and noticed the
    overflow; the kernel then divided by an infinite extent and crashed (a fuzzing find)."""
    from calibrate import _kernels

    v = np.array([[-1.7e308] * 3, [1.7e308] * 3, [0.0, 1.7e308, -1.7e308]])
    f = np.array([[0, 1, 2]])
    with pytest.raises(ValueError, match=r"box is too wide for float64: its extent overflows"):
        Scene(v, f)
    with pytest.raises(ValueError, match=r"too wide for double precision"):
        _kernels.build(v, f, (1, 1, 6))
