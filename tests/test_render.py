"""`calibrate render`: image sizes, hits against brute force, heatmaps against Grid.count, bad input."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from calibrate import Grid, Scene, brute_force
from calibrate.cli import main
from calibrate.render import (BACKGROUND_RGB, COLORBAR_STRIP_PIXELS, SHADE_FLOOR, camera_rays, face_normals,
                              render, write_image)

W, H = 40, 30


def _png_size(path):
    import matplotlib.image as mpimg

    img = mpimg.imread(path)
    return img.shape[1], img.shape[0], img


@pytest.fixture(scope="module")
def cylinder():
    return Scene.builtin("cylinder196")


@pytest.mark.parametrize("name,resolution,view", [("cylinder196", (3, 3, 14), None),
                                                  ("cylinder1996", (9, 9, 40), (0.0, 0.0, -1.0)),
                                                  ("room", (12, 10, 4), None), ("room", (12, 10, 4), (1.0, 0.2, 0.1))])
def test_shaded_hit_mask_is_brute_force(tmp_path, name, resolution, view):
    scene = Scene.builtin(name)
    result = render(scene, width=W, height=H, resolution=resolution, view=view)
    o, d = camera_rays(scene, W, H, view)
    t_ref, prim_ref = brute_force(scene, o, d)
    hit_ref = (prim_ref >= 0).reshape(H, W)
    assert hit_ref.any() and (~hit_ref).any(), "the default view should show the scene and some background"
    np.testing.assert_array_equal(result["hit"], hit_ref)
    # the written picture itself: background colour exactly where brute force misses
    out = tmp_path / "shaded.png"
    write_image(result, out)
    w, h, img = _png_size(out)
    assert (w, h) == (W, H)
    rgb = img[..., :3]
    background = np.all(np.abs(rgb - np.array(BACKGROUND_RGB)) < 1.5 / 255, axis=-1)
    np.testing.assert_array_equal(~background, hit_ref)
    # hits are grey |n.d|: equal channels, brighter where the hit triangle faces the ray
    grey = rgb[hit_ref]
    assert np.all(np.abs(grey[:, 0] - grey[:, 1]) < 1.5 / 255)
    nd = np.abs(np.einsum("ij,ij->i", face_normals(scene)[prim_ref[prim_ref >= 0]], d[prim_ref >= 0]))
    np.testing.assert_allclose(grey[:, 0], SHADE_FLOOR + (1.0 - SHADE_FLOOR) * nd, atol=1.0 / 255)


@pytest.mark.parametrize("kind", ["steps", "tests", "subgrids"])
def test_heatmap_values_are_grid_count(cylinder, kind):
    grid = Grid.nested(cylinder, levels=2, resolution=(2, 2, 6))
    result = render(cylinder, width=W, height=H, grid=grid)
    o, d = camera_rays(cylinder, W, H)
    steps, tests, subgrids = grid.count(o, d)
    expected = dict(steps=steps, tests=tests, subgrids=subgrids)[kind]
    np.testing.assert_array_equal(result[kind].reshape(-1), expected)
    assert int(result[kind].sum()) == int(expected.sum())
    assert expected.sum() > 0


def test_heatmap_png_size_and_json(tmp_path, cylinder, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "heat.png"
    code = main(["render", "cylinder196", "--out", str(out), "--heatmap", "tests", "--resolution", "3", "3", "14",
                 "--width", str(W), "--height", str(H), "--json"])
    assert code == 0
    info = json.loads(capsys.readouterr().out)
    w, h, _ = _png_size(out)
    assert (w, h) == (W + COLORBAR_STRIP_PIXELS, H)
    assert info["image"] == str(out)
    assert info["resolution"] == [3, 3, 14]
    grid = Grid.uniform(cylinder, (3, 3, 14))
    steps, tests, _ = grid.count(*camera_rays(cylinder, W, H))
    assert info["steps_per_ray"] == dict(mean=pytest.approx(steps.mean()), max=int(steps.max()))
    assert info["tests_per_ray"] == dict(mean=pytest.approx(tests.mean()), max=int(tests.max()))


def test_recommended_grid_is_predicts(tmp_path, cylinder, capsys):
    from calibrate.predict import predict

    out = tmp_path / "r.png"
    assert main(["render", "cylinder196", "--ratio", "1.5", "--levels", "1", "--out", str(out), "--width", "16",
                 "--height", "12", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["resolution"] == predict(cylinder, ratio=1.5, levels="1")["levels"][0]["resolution"]
    assert _png_size(out)[:2] == (16, 12)


@pytest.mark.parametrize("args,needle", [
    (["--out", "{tmp}"], "is a directory"),
    (["--out", "{tmp}/missing/x.png"], "does not exist"),
    (["--out", "{tmp}/x.jpg"], "PNG"),
    (["--width", "0"], "--width"),
    (["--height", "100000"], "--height"),
    (["--resolution", "0", "3", "3"], "at least 1 cell"),
    (["--scene", "nosuchscene"], "neither a mesh file nor a built-in scene"),
    (["--heatmap", "cells"], "invalid choice"),
    (["--view", "0", "0", "0"], "--view must be a finite non-zero"),
])
def test_bad_input_is_one_line_and_no_file(tmp_path, capsys, args, needle):
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    scene = args[1] if args[0] == "--scene" else "cylinder196"
    args = args[2:] if args[0] == "--scene" else args
    argv = ["render", scene, "--ratio", "1", "--width", "8", "--height", "6"] + args
    if "--out" not in args:
        argv += ["--out", str(tmp_path / "x.png")]
    before = set(os.listdir(tmp_path))
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("calibrate: error:") and needle in err[0], err
    assert set(os.listdir(tmp_path)) == before


def test_read_only_directory(tmp_path, capsys, monkeypatch):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    if hasattr(os, "geteuid") and os.geteuid() == 0:  # root writes anyway: refuse as the OS would for a user
        import calibrate._io as io_mod

        def refuse(*args, **kwargs):
            raise PermissionError(13, "Permission denied")

        monkeypatch.setattr(io_mod.tempfile, "mkstemp", refuse)
    try:
        assert main(["render", "cylinder196", "--ratio", "1", "--width", "8", "--height", "6",
                     "--out", str(ro / "x.png")]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "not writable" in err[0]
        assert os.listdir(ro) == []
    finally:
        ro.chmod(0o700)


def test_no_calibration_is_a_user_error(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["render", "cylinder196", "--out", str(tmp_path / "x.png")]) == 2
    assert "no calibration" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()
