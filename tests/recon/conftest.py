"""Shared pieces of the reconstruction tests: a tiny data set rendered by the
grid ray marcher (6 training and 2 test views of 16x16 pixels) and the small
fit settings that go with it (one compiled set of kernels for every module)."""
import pytest

from mi_tetvr.grid import make_volume
from mi_tetvr.recon.synthetic import make_dataset
from mi_tetvr.mesh.scenes import default_volume
from mi_tetvr.recon.config import FitConfig
from mi_tetvr.recon.datasets import load_nerf
from mi_tetvr.transfer import read_transfer_function
from tests.helpers import ROOT

CFG = FitConfig(grid_resolution=4, iterations=24, views_per_step=2, lr_color=0.08, lr_opacity=0.3,
                n_sub=2, jitter=False, checkpoint_every=4, log_every=4)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    out = tmp_path_factory.mktemp("data")
    tf = read_transfer_function(ROOT / "scenes" / "tf_default.json")
    make_dataset(make_volume(default_volume(16)), tf, views=6, res=16, out_dir=out,
                 test_views=2, fov=30, progress=False)
    return load_nerf(out)
