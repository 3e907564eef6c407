"""Shared pieces of the reconstruction tests: the tiny data set (``tiny_data_path``
of the suite's conftest: 6 training and 2 test views of 16x16 pixels) loaded, and
the small fit settings that go with it (one compiled set of kernels for every
module)."""
import numpy as np
import pytest

from mi_tetvr.grid import make_volume
from mi_tetvr.recon.config import FitConfig
from mi_tetvr.recon.datasets import load_nerf
from mi_tetvr.recon.synthetic import make_xray_dataset

CFG = FitConfig(grid_resolution=4, iterations=24, views_per_step=2, lr_color=0.08, lr_opacity=0.3,
                n_sub=2, jitter=False, checkpoint_every=4, log_every=4)


@pytest.fixture(scope="module")
def data(tiny_data_path):
    return load_nerf(tiny_data_path)


def blob_volume(n=9):
    """A Gaussian blob of attenuation on an ``n``-cubed grid over [-1, 1]^3."""
    g = np.linspace(-1, 1, n)
    z, y, x = np.meshgrid(g, g, g, indexing="ij")
    return make_volume(np.exp(-3 * ((x - 0.2) ** 2 + y ** 2 + (z + 0.1) ** 2)))


@pytest.fixture(scope="module")
def blob_data(tmp_path_factory):
    """16 X-ray views (and 4 held out) of :func:`blob_volume`: the volume, what
    ``make_xray_dataset`` returned, and the data set."""
    out = tmp_path_factory.mktemp("blob")
    vol = blob_volume()
    made = make_xray_dataset(vol, out, views=16, test_views=4, progress=False)
    return vol, made, load_nerf(out)
