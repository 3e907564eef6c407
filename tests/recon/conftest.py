"""Shared pieces of the reconstruction tests: the tiny data set (``tiny_data_path``
of the suite's conftest: 6 training and 2 test views of 16x16 pixels) loaded, and
the small fit settings that go with it (one compiled set of kernels for every
module)."""
import pytest

from mi_tetvr.recon.config import FitConfig
from mi_tetvr.recon.datasets import load_nerf

CFG = FitConfig(grid_resolution=4, iterations=24, views_per_step=2, lr_color=0.08, lr_opacity=0.3,
                n_sub=2, jitter=False, checkpoint_every=4, log_every=4)


@pytest.fixture(scope="module")
def data(tiny_data_path):
    return load_nerf(tiny_data_path)
