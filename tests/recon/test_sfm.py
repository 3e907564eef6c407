"""Structure from motion (mi_tetvr.recon.sfm): camera comparison against known similarity
transforms, pose recovery on real photos against their COLMAP model, triangulation with known
poses against the model's own points, pose recovery on the project's path-traced room photos
against the cameras that rendered them, bad input, video frames and ``mi-tetvr process-data``.

Measured on the 4 ``colmap-maupertuis`` photos (pycolmap 4.2.1, 2 CPU cores): run_sfm at
``max_image_size=1024`` registers 4 of 4 in ~15 s (763 points, 1.01 px), poses within 0.58 deg
(relative rotations 0.50 deg) and 0.18 % of the camera extent of the model, focal length
1890.6 px against its 1847.5 px; triangulate at ``downscale=4`` gives 420 points in ~3 s whose
median distance to the nearest model point is 1.2 % of the scene size (about the spacing of the
model's 1039 points). The tolerances below are a few times these numbers.
"""
import re

import numpy as np
import pytest
from PIL import Image
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from mi_tetvr.recon import sfm
from mi_tetvr.camera import Camera, random_cameras
from mi_tetvr.recon.datasets import View, load_colmap, load_dataset
from tests.helpers import DATA, shared_data

MAUPERTUIS = DATA / "colmap-maupertuis"
REF_FOCAL = 1847.53            # sparse/cameras.txt: SIMPLE_PINHOLE 1919 1079 1847.53 959.5 539.5


def _need_maupertuis():
    shared_data("colmap-maupertuis", "images")
    shared_data("colmap-maupertuis", "sparse")


def _noise_folder(path, n=3, seed=0):
    path.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    for i in range(n):
        Image.fromarray(rng.integers(0, 256, (120, 160, 3), dtype=np.uint8)).save(
            path / f"{i}.png")
    return path


# ---------------------------------------------------------------------------------------------
# align_cameras: known similarity transforms (independent: built here with scipy rotations)
# ---------------------------------------------------------------------------------------------

def _similar_cameras(ref, s, r, t):
    """The cameras ``ref`` expressed in the frame ``x_est = r^T (x_ref - t) / s``."""
    out = []
    for c in ref:
        m = np.eye(4)
        m[:3, :3] = r.T @ c.to_world[:3, :3]
        m[:3, 3] = r.T @ (c.center - t) / s
        out.append(Camera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, m))
    return out


SIM = dict(s=0.37, r=Rotation.from_rotvec([0.4, -1.1, 2.0]).as_matrix(),
           t=np.array([1.0, -2.0, 3.0]))


def test_align_cameras_recovers_a_similarity():
    ref = random_cameras(8, radius=4.0, res=(64, 48), seed=1)
    est = _similar_cameras(ref, **SIM)
    a = sfm.align_cameras(est, ref)
    assert a["scale"] == pytest.approx(SIM["s"], rel=1e-9)
    np.testing.assert_allclose(a["rotation"], SIM["r"], atol=1e-9)
    np.testing.assert_allclose(a["translation"], SIM["t"], atol=1e-9)
    assert a["rotation_error_deg_max"] < 1e-5
    assert a["relative_rotation_error_deg_max"] < 1e-5
    assert a["position_error_max"] < 1e-9
    centers = np.array([c.center for c in ref])
    assert a["scene_size"] == pytest.approx(np.linalg.norm(np.ptp(centers, axis=0)))
    for al, c in zip(a["aligned"], ref):
        np.testing.assert_allclose(al.to_world, c.to_world, atol=1e-9)


def test_align_cameras_measures_a_rotation_perturbation():
    ref = random_cameras(6, radius=3.0, res=(64, 48), seed=2)
    est = _similar_cameras(ref, **SIM)
    angle = 2.5
    turn = Rotation.from_rotvec(np.radians(angle) * np.array([0.6, 0.0, 0.8])).as_matrix()
    est[3].to_world[:3, :3] = est[3].to_world[:3, :3] @ turn        # about its own axis
    a = sfm.align_cameras(est, ref)
    expected = np.zeros(6)
    expected[3] = angle
    np.testing.assert_allclose(a["rotation_errors_deg"], expected, atol=1e-5)
    assert a["rotation_error_deg_max"] == pytest.approx(angle, abs=1e-5)
    assert a["rotation_error_deg_mean"] == pytest.approx(angle / 6, abs=1e-5)
    i, j = np.triu_indices(6, 1)
    np.testing.assert_allclose(a["relative_rotation_errors_deg"],
                               np.where((i == 3) | (j == 3), angle, 0.0), atol=1e-5)
    assert a["position_error_max"] < 1e-9                 # the centers did not move


def test_align_cameras_robust_ignores_an_outlier():
    ref = random_cameras(8, radius=4.0, res=(64, 48), seed=3)
    scene = np.linalg.norm(np.ptp([c.center for c in ref], axis=0))
    shift = np.array([0.3, -0.2, 0.1]) * scene
    moved = [Camera(c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.to_world.copy()) for c in ref]
    moved[0].to_world[:3, 3] += shift
    est = _similar_cameras(moved, **SIM)
    a = sfm.align_cameras(est, ref, robust=True)
    assert a["scale"] == pytest.approx(SIM["s"], rel=1e-6)
    np.testing.assert_allclose(a["position_errors"][1:], 0.0, atol=1e-6)
    assert a["position_errors"][0] == pytest.approx(np.linalg.norm(shift) / scene, rel=1e-6)


def test_align_cameras_bad_input():
    ref = random_cameras(4, res=(32, 24), seed=4)
    with pytest.raises(ValueError, match="4 estimated and 3 reference"):
        sfm.align_cameras(ref, ref[:3])
    with pytest.raises(ValueError, match="at least 3"):
        sfm.align_cameras(ref[:2], ref[:2])


# ---------------------------------------------------------------------------------------------
# run_sfm on real photos against their COLMAP model
# ---------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def maupertuis_sfm(tmp_path_factory):
    _need_maupertuis()
    out = tmp_path_factory.mktemp("maupertuis_sfm")
    logs = []
    summary = sfm.run_sfm(MAUPERTUIS / "images", out, max_image_size=1024, progress=False,
                          log=logs.append)
    return out, summary, logs


def test_run_sfm_recovers_the_model_cameras(maupertuis_sfm):
    out, s, logs = maupertuis_sfm
    print(f"run_sfm: {s['images_registered']}/{s['images_given']} images, {s['points']} "
          f"points, {s['mean_reprojection_error']:.2f} px, {s['seconds']:.1f} s")
    assert s["images_given"] == 4 and s["images_registered"] == 4
    assert s["registered"] == ["00.jpg", "01.jpg", "02.jpg", "03.jpg"]
    assert s["points"] > 200 and s["mean_track_length"] >= 2.0
    assert 0 < s["mean_reprojection_error"] < 2.0
    assert not any("warning" in line for line in logs)
    assert (out / "sparse" / "0").is_dir() and (out / "images" / "00.jpg").is_file()
    # intrinsics: the mapper's focal length against the model's (independent calibration)
    assert s["camera"]["model"] == "SIMPLE_RADIAL"
    assert s["camera"]["params"][0] == pytest.approx(REF_FOCAL, rel=0.06)

    est = load_dataset(out, holdout=None, load_images=False)
    ref = load_colmap(MAUPERTUIS, holdout=None, load_images=False)
    assert [v.name for v in est.views] == [v.name for v in ref.views]
    assert len(est.points) == s["points"]
    check_poses([v.camera for v in est.views], [v.camera for v in ref.views], 2.5, 2.0, 0.01)


def check_poses(estimated, reference, rotation_deg, relative_deg, position):
    """``align_cameras`` of the two, printed, within the given errors (max over cameras)."""
    a = sfm.align_cameras(estimated, reference)
    print(f"poses: rotation max {a['rotation_error_deg_max']:.3f} deg, relative max "
          f"{a['relative_rotation_error_deg_max']:.3f} deg, position max "
          f"{a['position_error_max']:.4f} of {a['scene_size']:.3f}")
    assert a["rotation_error_deg_max"] < rotation_deg
    assert a["relative_rotation_error_deg_max"] < relative_deg
    assert a["position_error_max"] < position


@pytest.fixture(scope="module")
def room_photos(tmp_path_factory):
    """12 path-traced photos of the project's room capture on a 90-degree arc (7.5 degrees
    apart), with its lens distortion, exposure changes and noise; the known cameras."""
    from mi_tetvr.recon.capture import make_room_capture
    from mi_tetvr.recon.datasets import load_nerf
    out = tmp_path_factory.mktemp("room_arc")
    info = make_room_capture(out, views=12, width=320, height=240, spp=8, arc=90.0,
                             progress=False)
    return out, info, load_nerf(out, holdout=None, load_images=False)


def _as_a_phone_stores_them(src, dst, f35):
    """The photos of ``src`` as a phone stores them: every other one turned (EXIF orientations
    6, 8 and 3 in turn, the pixels stored accordingly), one in six at 3/4 of the size, all
    with a 35 mm equivalent focal length ``f35`` in their EXIF data; and a damaged file among
    them."""
    from PIL import Image
    from tests.recon.test_datasets import STORED_FOR_ORIENTATION, _exif
    dst.mkdir()
    for i, path in enumerate(sorted(src.glob("*.png"))):
        o = (1, 6, 1, 8, 1, 3)[i % 6]
        im = Image.open(path).convert("RGB")
        if i % 6 == 4:
            im = im.resize((im.width * 3 // 4, im.height * 3 // 4), Image.LANCZOS)
        upright = np.asarray(im)
        Image.fromarray(np.ascontiguousarray(STORED_FOR_ORIENTATION[o](upright))).save(
            dst / path.name, exif=_exif(o, f35=f35))
    (dst / "frame_broken.png").write_bytes((dst / path.name).read_bytes()[:500])
    return dst


def test_run_sfm_recovers_the_rendered_cameras(room_photos, tmp_path):
    """Photos without poses against the cameras they were rendered from (independent of
    COLMAP), stored as a phone stores them (half of them turned, with EXIF orientations; a
    focal length in the EXIF data about 9 % off; a damaged file). Measured: 12 of 12 registered,
    ~1100 points; rotations within 0.7 deg (relative 0.4 deg), positions within 0.3 % of the
    camera extent, focal length 229.0 px against the true 228.5 px (SIMPLE_RADIAL's k1 -0.09
    stands for the OPENCV lens k1 -0.12, k2 0.03)."""
    import pycolmap
    src, info, ref = room_photos
    f_true = info["width"] / 2 / np.tan(np.radians(info["fov_x_deg"]) / 2)
    diagonal_px = np.hypot(info["width"], info["height"])
    f35 = round(1.1 * f_true * np.hypot(36, 24) / diagonal_px)    # EXIF: whole mm
    f_exif = f35 / np.hypot(36, 24) * diagonal_px                   # about 9 % too long
    photos = _as_a_phone_stores_them(src / "images", tmp_path / "phone", f35=f35)
    logs = []
    s = sfm.run_sfm(photos, tmp_path / "sfm", progress=False, log=logs.append)
    assert s["images_registered"] == s["images_given"] == 12
    assert list(s["unreadable"]) == ["frame_broken.png"]
    assert any("frame_broken.png cannot be read" in line for line in logs)
    assert any("6 of 12 photos turned upright" in line for line in logs)
    assert any("2 sizes (2 of 240x180, 10 of 320x240); one camera for each size" in line
               for line in logs)
    assert s["points"] > 300 and s["mean_reprojection_error"] < 1.5
    # the mapper starts from the EXIF focal length and refines it to the true one
    assert s["focal_prior"] == "exif"
    db = pycolmap.Database.open(tmp_path / "sfm" / "database.db")
    try:
        cams = sorted(db.read_all_cameras(), key=lambda c: c.width)
        assert [(c.width, c.height) for c in cams] == [(240, 180), (320, 240)]
        for c in cams:
            assert c.focal_length == pytest.approx(f_exif * c.width / 320, rel=0.01)
    finally:
        db.close()
    model = pycolmap.Reconstruction(tmp_path / "sfm" / "sparse" / "0")
    for c in model.cameras.values():
        assert c.focal_length == pytest.approx(f_true * c.width / 320, rel=0.02)
    est = load_dataset(tmp_path / "sfm", holdout=None, load_images=False)
    names = {v.name: v.camera for v in ref.views}
    assert sorted(v.name for v in est.views) == sorted(names)
    check_poses([v.camera for v in est.views], [names[v.name] for v in est.views], 2.0, 1.5,
                0.01)


# ---------------------------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------------------------

def test_run_sfm_unregistrable_noise(tmp_path):
    src = _noise_folder(tmp_path / "noise")
    logs = []
    with pytest.raises(ValueError, match=r"registered 0 of 3 images"):
        sfm.run_sfm(src, tmp_path / "out", progress=False, log=logs.append)
    (line,) = [x for x in logs if "not registered" in x]
    assert line.count("no verified match with any other photo") == 3, line


def test_run_sfm_copies_of_one_photo(tmp_path):
    """Three identical pictures: plenty of matches, no parallax, nothing to triangulate."""
    _need_maupertuis()
    src = tmp_path / "copies"
    src.mkdir()
    im = Image.open(MAUPERTUIS / "images" / "00.jpg").resize((480, 270))
    for i in range(3):
        im.save(src / f"{i}.jpg", quality=95)
    logs = []
    with pytest.raises(ValueError, match=r"registered 0 of 3 images"):
        sfm.run_sfm(src, tmp_path / "out", progress=False, log=logs.append)
    (line,) = [x for x in logs if "not registered" in x]
    assert line.count("matched with 2 photo(s)") == 3 and "not placed" in line, line


def test_run_sfm_too_few_images(tmp_path):
    src = _noise_folder(tmp_path / "one", n=1)
    with pytest.raises(ValueError, match=r"at least 2 images.* has 1"):
        sfm.run_sfm(src, tmp_path / "out", progress=False)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"at least 2 images.* has 0"):
        sfm.run_sfm(tmp_path / "empty", tmp_path / "out", progress=False)
    with pytest.raises(FileNotFoundError):
        sfm.run_sfm(tmp_path / "missing", tmp_path / "out", progress=False)
    with pytest.raises(ValueError, match="camera model"):
        sfm.run_sfm(tmp_path / "empty", tmp_path / "out", camera_model="NOPE", progress=False)


# ---------------------------------------------------------------------------------------------
# video frames
# ---------------------------------------------------------------------------------------------

def test_extract_frames_evenly(tmp_path):
    frames = [Image.fromarray(np.full((20, 30, 3), 10 * i, np.uint8)) for i in range(25)]
    frames[0].save(tmp_path / "clip.gif", save_all=True, append_images=frames[1:], duration=40)
    files = sfm.extract_frames(tmp_path / "clip.gif", tmp_path / "frames", max_frames=5,
                               log=lambda *a: None)
    assert [f.name for f in files] == [f"frame_{i:05d}.jpg" for i in range(5)]
    values = [int(np.asarray(Image.open(f))[10, 15, 0]) for f in files]
    np.testing.assert_allclose(values, [0, 60, 120, 180, 240], atol=2)   # frames 0, 6, .. 24


def test_extract_frames_from_an_mp4(tmp_path):
    """An H.264 MP4 (written by the orbit writer, imageio-ffmpeg): frames
    taken evenly, their values kept through the codec."""
    from mi_tetvr.video import write_video
    frames = np.stack([np.full((20, 30, 3), 10 * i, np.uint8) for i in range(25)])
    write_video(tmp_path / "clip.mp4", frames)
    files = sfm.extract_frames(tmp_path / "clip.mp4", tmp_path / "frames", max_frames=5,
                               log=lambda *a: None)
    assert len(files) == 5
    values = [int(np.asarray(Image.open(f))[10, 15, 0]) for f in files]
    np.testing.assert_allclose(values, [0, 60, 120, 180, 240], atol=4)


# ---------------------------------------------------------------------------------------------
# triangulation with known poses against the model's own points
# ---------------------------------------------------------------------------------------------

def test_triangulate_known_poses(tmp_path):
    _need_maupertuis()
    ds = load_colmap(MAUPERTUIS, downscale=4, holdout=None)
    model_points = ds.points
    views = [View(v.name, v.camera, v.image) for v in ds.views]        # no sparse points
    pts, colors, errors, tracks = sfm.triangulate(views, tmp_path, progress=False,
                                                  log=lambda *a: None)
    k = len(pts)
    assert pts.shape == (k, 3) and pts.dtype == np.float64
    assert colors.shape == (k, 3) and colors.dtype == np.uint8
    assert errors.shape == (k,) and tracks.shape == (k,) and tracks.dtype == np.int64
    assert k > 150 and tracks.min() >= 2 and errors.mean() < 1.5
    lo, hi = np.percentile(model_points, [1, 99], axis=0)
    size = np.linalg.norm(hi - lo)
    dist, _ = cKDTree(model_points).query(pts)
    rel = np.median(dist) / size
    print(f"triangulate: {k} points, {errors.mean():.2f} px, median distance to the model's "
          f"points {rel:.4f} of the scene size")
    assert rel < 0.03


def test_triangulate_noise_gives_too_few_points(tmp_path):
    rng = np.random.default_rng(5)
    cams = random_cameras(3, radius=4.0, res=(160, 120), seed=5)
    views = [View(f"n{i}", c, np.concatenate(
        [rng.uniform(0, 1, (120, 160, 3)), np.ones((120, 160, 1))], 2).astype(np.float32))
        for i, c in enumerate(cams)]
    with pytest.raises(ValueError, match=r"gave \d+ points from 3 views"):
        sfm.triangulate(views, tmp_path, progress=False, log=lambda *a: None)
    with pytest.raises(ValueError, match="at least 2"):
        sfm.triangulate(views[:1], tmp_path, progress=False)


# ---------------------------------------------------------------------------------------------
# mi-tetvr process-data
# ---------------------------------------------------------------------------------------------

def test_cli_process_data(tmp_path, capsys):
    _need_maupertuis()
    from mi_tetvr.cli import main
    out = tmp_path / "data"
    main(["process-data", str(MAUPERTUIS / "images"), "--out", str(out), "--max-image-size",
          "800", "--quiet", "--reference", str(MAUPERTUIS)])
    text = capsys.readouterr().out
    assert re.search(r"registered [34] of 4 images, [\d,]+ points, mean reprojection error "
                     r"[\d.]+ px", text), text
    m = re.search(r"\(\d images in common.*rotation error mean ([\d.]+).*position error mean "
                  r"([\d.]+) %", text)
    assert m, text
    assert float(m.group(1)) < 10 and float(m.group(2)) < 5
    assert f"next: mi-tetvr fit {out} --out" in text
    assert len(load_dataset(out, holdout=None, load_images=False).views) >= 3


def test_cli_process_data_errors(tmp_path, capsys):
    from mi_tetvr.cli import main
    src = _noise_folder(tmp_path / "noise")
    with pytest.raises(SystemExit) as e:
        main(["process-data", str(src), "--out", str(tmp_path / "out"), "--quiet"])
    assert str(e.value.code).startswith("mi-tetvr: structure from motion registered 0 of 3")
    with pytest.raises(SystemExit) as e:
        main(["process-data", str(tmp_path / "missing"), "--out", str(tmp_path / "out")])
    assert str(e.value.code).startswith("mi-tetvr: ") and "missing" in str(e.value.code)
