"""A grid volume rendered into a NeRF-convention data set."""
import json

import numpy as np
import pytest
from PIL import Image

from mi_tetvr.color import srgb_to_linear
from mi_tetvr.grid import volume as V
from mi_tetvr.recon.synthetic import make_dataset
from mi_tetvr.transfer import TransferFunction


def test_make_dataset(tmp_path):
    rng = np.random.default_rng(6)
    vol = V.make_volume(rng.uniform(size=(6, 7, 8)))
    tf = TransferFunction([0, 1], [[0.9, 0.2, 0.1], [0.1, 0.4, 1.0]], [0, 1], [0.2, 4.0])
    res = make_dataset(vol, tf, views=3, res=(16, 12), out_dir=tmp_path / "ds", test_views=2,
                       radius=3.0, seed=1, step=0.5, progress=False)
    out = tmp_path / "ds"
    for name in ("transforms_train.json", "transforms_test.json", "volume_info.json"):
        assert (out / name).is_file()
    info = json.loads((out / "volume_info.json").read_text())
    assert info["step_voxels"] == 0.5 and info["cameras"]["n_test"] == 2
    for split, n in (("train", 3), ("test", 2)):
        meta = json.loads((out / f"transforms_{split}.json").read_text())
        assert meta["w"] == 16 and meta["h"] == 12 and len(meta["frames"]) == n
        assert meta["fl_x"] == pytest.approx(8 / np.tan(meta["camera_angle_x"] / 2))
        imgs = res[split]
        assert imgs.shape == (n, 12, 16, 4) and imgs[..., 3].max() > 0.2
        for i, fr in enumerate(meta["frames"]):
            view = res[f"cameras_{split}"][i]
            assert view.name == f"r_{i}"
            np.testing.assert_array_equal(view.image, imgs[i])
            m = np.array(fr["transform_matrix"])
            np.testing.assert_allclose(m, view.camera.to_world @ np.diag([-1, 1, -1, 1]),
                                       atol=1e-12)
            # OpenGL: the camera looks along its -z axis, towards the origin
            fwd = -m[:3, 2]
            np.testing.assert_allclose(fwd, -m[:3, 3] / np.linalg.norm(m[:3, 3]), atol=1e-9)
            path = out / fr["file_path"]
            png = np.asarray(Image.open(path if path.suffix else path.with_suffix(".png")))
            assert png.shape == (12, 16, 4) and png.dtype == np.uint8
            a = png[..., 3] / 255.0
            rgb = srgb_to_linear(png[..., :3] / 255.0) * a[..., None]
            np.testing.assert_allclose(a, imgs[i, ..., 3], atol=0.5 / 255 + 1e-6)
            np.testing.assert_allclose(rgb, imgs[i, ..., :3], atol=0.01)
