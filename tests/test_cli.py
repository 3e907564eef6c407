"""The mi-tetvr command line and the bundled scenes."""
import json
import subprocess
import sys

import numpy as np
import pytest

import mitsuba as mi
from conftest import ROOT
from mi_tetvr.generate import grid_mesh
from mi_tetvr.io import write_tetmesh
from mi_tetvr.mesh import TetMesh
from mi_tetvr.scenes import make_scene_meshes

SCENES = ["default", "transfer_function", "nonconvex", "two_meshes", "inside"]


def run(*args):
    return subprocess.run([sys.executable, "-m", "mi_tetvr.cli", *args], capture_output=True,
                          text=True, cwd=ROOT)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    make_scene_meshes()
    return ROOT / "scenes"


@pytest.mark.parametrize("name", SCENES)
def test_render_scene(scenes, tmp_path, name):
    exr, png = tmp_path / f"{name}.exr", tmp_path / f"{name}.png"
    r = run("render", str(scenes / f"{name}.xml"), "-o", str(exr), "-o", str(png),
            "--res", "24x16", "--spp", "1")
    assert r.returncode == 0, r.stderr
    bmp = mi.Bitmap(str(exr))
    assert bmp.pixel_format() == mi.Bitmap.PixelFormat.RGBA
    img = np.array(bmp)
    assert img.shape == (16, 24, 4)
    assert np.all(np.isfinite(img)) and img[..., 3].max() > 0.05  # the volume is visible
    assert np.all((img[..., 3] >= 0) & (img[..., 3] <= 1))
    assert np.array(mi.Bitmap(str(png))).shape == (16, 24, 3)


def test_render_errors(tmp_path):
    r = run("render", "missing.xml", "-o", str(tmp_path / "x.exr"))
    assert r.returncode != 0 and "not found" in r.stderr
    r = run("render", "scenes/default.xml", "-o", str(tmp_path / "x.tif"), "--res", "8x8")
    assert r.returncode != 0 and "unsupported image format" in r.stderr


def test_info(tmp_path):
    v, t = grid_mesh(2)
    p = tmp_path / "g.vtu"
    write_tetmesh(p, TetMesh(v, t))
    r = run("info", str(p), "--json")
    assert r.returncode == 0, r.stderr
    s = json.loads(r.stdout)
    assert s["tets"] == 48 and s["vertices"] == 27 and s["boundary_faces"] == 48
    assert s["volume"] == pytest.approx(8.0)
    r = run("info", str(tmp_path / "none.vtu"))
    assert r.returncode != 0 and "not found" in r.stderr
