"""The live viewer (mi_tetvr.apps.viewer): its cameras against the pinhole
formula, its images against ``mi-tetvr render`` of the view it saved, its
refinement, its share of a fit's time, and the page in a real browser
(Debian's Chromium driven by Selenium)."""
import math
import socket
import time

import numpy as np
import pytest

from tests.helpers import ROOT, start_browser, use_variant

use_variant()

import mitsuba as mi  # noqa: E402

from mi_tetvr.apps.viewer import (LEVELS, FitViewer, MeshShown, Viewer,  # noqa: E402
                                  browser_camera, camera_pose)
from mi_tetvr.mesh.generate import grid_mesh  # noqa: E402
from mi_tetvr.mesh.io import write_tetmesh  # noqa: E402
from mi_tetvr.mesh.tetmesh import TetMesh  # noqa: E402
from mi_tetvr.recon.images import read_image  # noqa: E402
from tests.recon.conftest import CFG, data  # noqa: E402,F401  (the tiny data set)


@pytest.fixture(scope="module")
def mesh_file(tmp_path_factory):
    """A small scalar mesh: a smooth bump on a jittered grid."""
    v, t = grid_mesh(6, jitter=0.15, seed=1)
    bump = np.exp(-np.sum((v - [0.2, -0.1, 0.1]) ** 2, 1) / 0.3)
    path = tmp_path_factory.mktemp("viewer") / "bump.vtu"
    write_tetmesh(path, TetMesh(v, t, point_data={"bump": bump, "x": v[:, 0]}), color=None,
                  opacity=None)
    return path


def start_pose(viewer, aspect=1.5):
    """Viser's pose (position, wxyz, vertical fov) of the viewer's first view."""
    from mi_tetvr.camera import Camera, look_at
    position, target, _ = viewer.start_camera()
    cam = Camera(300, 200, 250.0, 250.0, 150.0, 100.0, look_at(position, target,
                                                               viewer.shown.up))
    p, q, fov, _ = camera_pose(cam)
    return p, q, fov, aspect


def test_browser_camera_follows_the_pinhole_formula():
    """Viser's camera (OpenCV axes: +z forward, +x right, +y down) as a
    Camera: points in front project by u = f x / z + w/2, v = f y / z + h/2
    (f from the vertical field of view); camera_pose inverts it."""
    rng = np.random.default_rng(3)
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    position = rng.normal(size=3)
    fov, aspect = math.radians(35.0), 1.6
    cam = browser_camera(position, q, fov, aspect, 320)
    assert (cam.width, cam.height) == (320, 200)
    from mi_tetvr.apps.viewer import quaternion_matrix
    R = quaternion_matrix(q)
    local = np.array([[0.0, 0.0, 2.0], [0.3, -0.2, 1.5], [-0.5, 0.4, 3.0]])
    world = position + local @ R.T
    u, v = cam.project(world)[0].T
    f = 100.0 / math.tan(fov / 2)
    np.testing.assert_allclose(u, f * local[:, 0] / local[:, 2] + 160.0, atol=1e-6)
    np.testing.assert_allclose(v, f * local[:, 1] / local[:, 2] + 100.0, atol=1e-6)
    p2, q2, fov2, aspect2 = camera_pose(cam)
    np.testing.assert_allclose(p2, position, atol=1e-9)
    assert min(np.abs(q2 - q).max(), np.abs(q2 + q).max()) < 1e-9
    assert fov2 == pytest.approx(fov) and aspect2 == pytest.approx(aspect)


def run_until_idle(viewer, limit=200):
    for _ in range(limit):
        if not viewer.update():
            return
    raise AssertionError("the viewer did not settle")


def test_refines_from_a_quarter_to_full_resolution(mesh_file):
    """While the camera moves the viewer shows a quarter of the resolution;
    when it stops it refines to half and full, then adds passes; a move
    starts over from the quarter."""
    shown = MeshShown(mesh_file, scalar="bump")
    viewer = Viewer(shown, server=False, resolution=256, spp=2)
    pushed = []
    viewer.add_client("a", lambda im, final: pushed.append((im.shape[1], final)),
                      *start_pose(viewer))
    run_until_idle(viewer)
    assert pushed == [(64, False), (128, False), (256, False), (256, True)]
    assert LEVELS == (0.25, 0.5, 1.0)
    c = viewer.clients["a"]
    assert 0 < c.latency["first"] < c.latency["refined"]
    pushed.clear()
    viewer.update()
    viewer.set_camera("a", *start_pose(viewer, aspect=1.2))
    run_until_idle(viewer)
    assert pushed[0] == (64, False) and pushed[-1] == (256, True)


def test_a_saved_view_renders_again_with_render(mesh_file, tmp_path):
    """The viewer's settings changed in place (transfer function, range,
    opacity scale: the shape's texels; mode and isovalue: the integrator) and
    the view saved: ``mi-tetvr render MESH <its flags> --sensor VIEW.xml``
    (the shape loaded afresh from the flags) gives the same image, alpha 0
    where the rays miss the mesh."""
    from mi_tetvr.cli import main
    shown = MeshShown(mesh_file, scalar="bump")
    shown.tf, shown.opacity_scale = "viridis", 4.0
    shown.value_range = (0.2, 0.9)
    assert shown.apply("texels")
    shown.mode, shown.iso, shown.surface_opacity = "volume + isosurface", 0.6, 0.5
    assert shown.apply("integrator")
    viewer = Viewer(shown, server=False, resolution=96, save_dir=tmp_path / "views")
    viewer.add_client("a", lambda im, final: None, *start_pose(viewer))
    saved = viewer.save("a")
    assert "--value-range" in saved["command"] and "--iso" in saved["command"]
    ours = read_image(saved["exr"])
    again = tmp_path / "again.exr"
    args = saved["command"].split()[1:]
    args[args.index("-o") + 1] = str(again)
    main(args)
    theirs = read_image(again)
    assert ours.shape == theirs.shape == (64, 96, 4)
    np.testing.assert_allclose(ours, theirs, atol=2e-5)
    assert theirs[0, 0, 3] == 0.0 and theirs[..., 3].max() > 0.5
    # the in-place texels are those of a load: loading again changes nothing
    camera = browser_camera(*start_pose(viewer), 96)
    before = shown.render(camera)
    assert shown.apply("shape")
    np.testing.assert_array_equal(before, shown.render(camera))


def test_fit_viewer_keeps_to_its_share(data, tmp_path):  # noqa: F811 (the fixture)
    """fit --viewer: between steps the viewer renders the fit from a camera that moves
    after every step, in at most its share of the time (plus one render), and records the
    curve of every step. The time is a simulated clock's (each reading a tick later, the
    fit and the viewer reading the same one), so the share is a count of readings and the
    renders it allows are the same on any machine."""
    from mi_tetvr.recon.pipeline import run
    from tests.recon.test_fit import TickClock
    made, clock = {}, TickClock(1.0)

    def factory(trainer):
        v = FitViewer(trainer, share=0.1, server=False, resolution=64, now=clock)
        pose = start_pose(v)
        v.add_client("a", lambda im, final: made.setdefault("pushed", []).append(final), *pose)
        after = v.after_step

        def moving(trainer, *args):
            v.set_camera("a", *pose)
            return after(trainer, *args)
        v.after_step = moving
        made["viewer"] = v
        return v
    run(data, tmp_path / "fit", CFG.updated(iterations=12), progress=False,
        log=lambda *a: None, viewer=factory, now=clock)
    v = made["viewer"]
    assert v.curve["step"] == list(range(1, 13))
    # every render is one tick (two readings); the fit's readings since the viewer began
    elapsed = clock.t - v.began
    assert 0 < v.rendered == len(made["pushed"]) and v.render_seconds == v.rendered
    assert v.render_seconds <= 0.1 * elapsed + v.last["seconds"], (v.rendered, elapsed)
    # and it takes the share it has: within one render of it
    assert v.render_seconds >= 0.1 * elapsed - 2 * v.last["seconds"] - 1, (v.rendered, elapsed)


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_page_in_a_real_browser(mesh_file):
    """Chromium loads the page; the rendered volume is in its screenshot
    (pixels unlike the empty view's background); dragging on the page orbits
    the camera, which reaches the renderer and changes the picture; typing a
    new maximum of the transfer function's range changes it again."""
    import io

    from PIL import Image
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from mi_tetvr.apps.viewer import PARAVIEW_BACKGROUND
    browser = start_browser()
    shown = MeshShown(mesh_file, scalar="bump")
    viewer = Viewer(shown, port=_free_port(), resolution=256).start()
    try:
        def refined(after=None, limit=90.0):
            end = time.perf_counter() + limit
            while time.perf_counter() < end:
                cs = list(viewer.clients.values())
                if cs and cs[0].level >= len(LEVELS) and cs[0].version != after:
                    time.sleep(1.0)          # the image on its way to the page
                    return cs[0].version
                time.sleep(0.1)
            raise AssertionError("no refined image reached the page")

        def screenshot():
            png = browser.get_screenshot_as_png()
            image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), np.float64)
            return image[160:, :480]         # below the browser's notice, left of the panel

        browser.get(viewer.url)
        version = refined()
        first = screenshot()
        unlike = np.abs(first - PARAVIEW_BACKGROUND).max(-1) > 12
        assert unlike.mean() > 0.02, "the volume is not on the page"
        canvas = browser.find_element(By.TAG_NAME, "canvas")
        ActionChains(browser).move_to_element_with_offset(canvas, -150, 0).click_and_hold() \
            .move_by_offset(80, 10).move_by_offset(80, 10).release().perform()
        version = refined(after=version)
        turned = screenshot()
        assert np.abs(turned - first).mean() > 0.3, "the camera's move changed nothing"
        label = browser.find_element(By.XPATH, "//label[normalize-space(text())='range max']")
        field = browser.find_element(By.ID, label.get_attribute("for"))
        field.click()
        field.send_keys(Keys.CONTROL, "a")
        field.send_keys("0.3", Keys.ENTER)
        refined(after=version)
        assert shown.value_range[1] == pytest.approx(0.3)
        assert np.abs(screenshot() - turned).mean() > 0.3, "the range's change changed nothing"
    finally:
        browser.quit()
        viewer.stop()


def test_the_commands_serve_fits_data_and_meshes(data, mesh_file, tmp_path,  # noqa: F811
                                                 capsys):
    """``fit --viewer`` serves while it fits and records its data set; ``view``
    opens the fit's folder (its data set found from that record), the data
    set and the mesh; a click on a test camera moves the view there and
    scores it as the fit scored it (its metrics.json)."""
    import json

    from mi_tetvr.apps.viewer import FitShown
    from mi_tetvr.cli import fit_dataset, main
    from mi_tetvr.recon.checkpoint import load_checkpoint
    fit = tmp_path / "fit"
    main(["fit", str(data.root), "-o", str(fit), "--viewer", "--port", str(_free_port()),
          "--grid-resolution", "4", "--iterations", "6", "--n-sub", "2", "--no-jitter",
          "--quiet"])
    assert "viewer: http://localhost:" in capsys.readouterr().out
    assert json.loads((fit / "data.json").read_text())["data"] == str(data.root.resolve())
    for path in (fit, data.root, mesh_file, ROOT / "scenes" / "default.xml"):
        main(["view", str(path), "--port", str(_free_port()), "--seconds", "0.5"])
        assert "viewer: http://localhost:" in capsys.readouterr().out
    config, dataset = fit_dataset(fit)
    viewer = Viewer(FitShown(load_checkpoint(fit / "checkpoint.npz", dataset, config)),
                    server=False, resolution=32)
    viewer.add_client("a", lambda im, final: None, *start_pose(viewer))
    view = dataset.test[0]
    viewer.compare("a", view, "test")
    c = viewer.clients["a"]
    np.testing.assert_allclose(c.position, view.camera.center, atol=1e-9)
    saved = json.loads((fit / "metrics.json").read_text())["views"][view.name]
    assert viewer.compared["metrics"]["psnr"] == pytest.approx(saved["psnr"], abs=1e-6)


def test_serve_shows_a_scene_from_python():
    """serve(scene, block=False): a viewer of any loaded scene, rendering from a
    thread of its own until stopped."""
    from mi_tetvr.apps.viewer import serve
    scene = mi.load_file(str(ROOT / "scenes" / "default.xml"))
    viewer = serve(scene, port=_free_port(), block=False, resolution=64)
    try:
        pushed = []
        viewer.add_client("a", lambda im, final: pushed.append(final), *start_pose(viewer))
        end = time.perf_counter() + 60
        while not (pushed and pushed[-1]) and time.perf_counter() < end:
            time.sleep(0.05)
        assert pushed and pushed[-1]
    finally:
        viewer.stop()
