"""The OBJ reader: the format as written, and the real meshes load with their documented sizes."""

from __future__ import annotations

import numpy as np
import pytest

from calibrate import Scene
from calibrate._obj import read_obj

from conftest import shared_mesh


def test_tabs_relative_indices_slashes_and_polygons():
    text = ("# a quad and a triangle\r\n"
            "v\t0 0 0\r\nv 1\t0 0\nv 1 1 0   \nv 0 1 0\n"
            "f -4 -3 -2 -1\n"           # relative indices, a quad -> two triangles
            "vt 0 0\nvn 0 0 1\n"
            "v 0 0 1\n"
            "f 1/1/1 2//1 5\n")         # v/vt/vn and v//vn forms
    v, f = read_obj(text)
    assert v.shape == (5, 3) and np.array_equal(v[1], [1, 0, 0])
    assert f.tolist() == [[0, 1, 2], [0, 2, 3], [0, 1, 4]]


@pytest.mark.parametrize("text,needle", [
    ("v 0 0\n", "three coordinates"),
    ("v 0 x 0\n", "cannot read vertex"),
    ("v 0 0 0\nv 1 0 0\nf 1 2\n", "at least three"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", "refers to no vertex"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "start at 1"),
    ("v 0 0 0\nf -2 -1 -3\n", "refers to no vertex"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 a 2\n", "cannot read face index"),
])
def test_malformed_lines_are_named(text, needle):
    with pytest.raises(ValueError, match=needle) as err:
        read_obj(text, "mesh.obj")
    assert "line" in str(err.value)


# (file, triangles, box extents) from ../shared/meshes/README.md
DOCUMENTED = [
    ("cornell_box_36.obj", 36, (2.02, 1.99, 2.03)),
    ("spot_6k.obj", 5856, (0.94, 1.69, 1.72)),
    ("utah_teapot_6k.obj", 6320, (6.43, 3.15, 4.0)),
    ("stanford_bunny_69k.obj", 69451, (0.156, 0.154, 0.121)),
    ("armadillo_86k.obj", 86482, (0.84, 1.0, 0.76)),
    ("sponza_dabrovic_66k.obj", 66454, (34.8, 16.6, 15.6)),
    ("cad_fandisk_13k.obj", 12946, (4.8, 5.2, 2.7)),
    ("cad_chair_soup_13k.obj", 12756, (0.53, 0.66, 0.53)),
    ("fertility_9k.off", 9000, (199, 144, 73)),
    ("cad_round_cylinder_1k.stl", 1120, (5.1, 5.1, 61)),
    ("cad_tray_bottom_4k.stl", 4520, (356, 3.2, 356)),
]


@pytest.mark.parametrize("name,n,box", DOCUMENTED)
def test_real_meshes_load_with_their_documented_size(name, n, box):
    scene = Scene.from_file(shared_mesh(name))
    assert scene.n_triangles == n
    ext = scene.box_hi - scene.box_lo
    assert np.allclose(ext, box, rtol=0.02, atol=0.006), (name, ext)
