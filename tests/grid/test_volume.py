"""Regular-grid volumes: placement, normalisation, trilinear sampling, readers and writers."""
import gzip

import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator

from mi_tetvr.grid import volume as V


# ---------------------------------------------------------------------------- placement
def test_make_volume_placement_and_normalisation():
    v = np.arange(5 * 7 * 9, dtype=np.float64).reshape(5, 7, 9) * 3.0 + 10.0
    vol = V.make_volume(v, spacing=(1.0, 1.0, 2.0))
    assert vol.shape == (9, 7, 5)
    lo, hi = vol.bounds()
    # extents (8, 6, 8) * spacing -> (8, 6, 8), largest 8 -> scaled to 2
    np.testing.assert_allclose(lo, [-1, -0.75, -1])
    np.testing.assert_allclose(hi, [1, 0.75, 1])
    np.testing.assert_allclose(vol.spacing, [0.25, 0.25, 0.5])
    assert vol.values.dtype == np.float32 and vol.values.min() == 0 and vol.values.max() == 1
    assert vol.data_range == (10.0, v.max())
    vol2 = V.make_volume(v, value_range=(10.0, 20.0))
    assert vol2.values.max() == 1.0 and vol2.values[0, 0, 1] == pytest.approx(0.3)
    vol3 = V.make_volume(v.transpose(2, 1, 0), layout="xyz")
    np.testing.assert_array_equal(vol3.values, V.make_volume(v).values)


def scipy_trilinear_case():
    """A random volume, random points in its box and scipy's trilinear values there."""
    rng = np.random.default_rng(2)
    vals = rng.uniform(size=(5, 6, 7))
    vol = V.make_volume(vals, spacing=(1.0, 2.0, 1.5))
    lo, hi = vol.bounds()
    p = rng.uniform(lo, hi, (200, 3))
    nx, ny, nz = vol.shape
    axes = [vol.origin[a] + np.arange(n) * vol.spacing[a] for a, n in enumerate((nx, ny, nz))]
    rgi = RegularGridInterpolator((axes[2], axes[1], axes[0]), vol.values.astype(np.float64))
    return vol, p, rgi(p[:, ::-1])


def test_trilinear_numpy_matches_scipy():
    vol, p, ref = scipy_trilinear_case()
    np.testing.assert_allclose(vol.sample(p), ref, atol=1e-12)
    np.testing.assert_allclose(V.trilinear_numpy(vol.values, vol.world_to_index(p)), ref,
                               atol=1e-12)


# ---------------------------------------------------------------------------- loaders
def test_loaders_round_trip(tmp_path):
    rng = np.random.default_rng(5)
    v = rng.integers(0, 256, size=(3, 4, 5), dtype=np.uint8)          # (nz, ny, nx)
    ref = V.make_volume(v)

    np.save(tmp_path / "v.npy", v)
    a = V.load_volume(tmp_path / "v.npy")
    np.testing.assert_array_equal(a.values, ref.values)
    # not an array of numbers: one message naming the file, never numpy's about pickles
    (tmp_path / "t.npy").write_text("not an array")
    np.save(tmp_path / "o.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    np.save(tmp_path / "s.npy", np.full((2, 2, 2), "a"))
    for name, says in (("t", "not a numpy array file"), ("o", "not a numpy array file"),
                       ("s", "not numbers")):
        with pytest.raises(ValueError, match=says) as e:
            V.load_volume(tmp_path / f"{name}.npy")
        assert f"{name}.npy" in str(e.value) and "pickle" not in str(e.value)

    V.write_cvol(tmp_path / "v.cvol", v, voxel_size=(1.0, 1.0, 2.0))
    raw = (tmp_path / "v.cvol").read_bytes()
    assert len(raw) == 64 + v.size and raw[:4] == b"cvol"
    b = V.load_volume(tmp_path / "v.cvol")
    np.testing.assert_array_equal(b.values, ref.values)
    np.testing.assert_allclose(b.source_spacing, [1, 1, 2])
    np.testing.assert_allclose(b.spacing / b.spacing[0], [1, 1, 2])
    bad = bytearray(raw)
    bad[56] = 1
    (tmp_path / "c.cvol").write_bytes(bytes(bad))
    with pytest.raises(ValueError, match="LZ4"):
        V.load_volume(tmp_path / "c.cvol")

    V.write_mhd(tmp_path / "v.mhd", v.astype(np.int16), spacing=(0.5, 0.5, 1.5))
    c = V.load_volume(tmp_path / "v.mhd")
    np.testing.assert_array_equal(c.values, ref.values)
    np.testing.assert_allclose(c.source_spacing, [0.5, 0.5, 1.5])

    with gzip.open(tmp_path / "thing_5x4x3_uint8.raw.gz", "wb") as f:
        f.write(v.tobytes())
    d = V.load_volume(tmp_path / "thing_5x4x3_uint8.raw.gz")
    np.testing.assert_array_equal(d.values, ref.values)
    (tmp_path / "x.raw").write_bytes(v.astype("<u2").tobytes())
    e = V.load_volume(tmp_path / "x.raw", shape=(5, 4, 3), dtype="uint16", value_range=(0, 255))
    np.testing.assert_allclose(e.values, v / 255.0, atol=1e-7)
    with pytest.raises(ValueError, match="shape"):
        V.load_volume(tmp_path / "x.raw")

    import pyvista as pv
    img = pv.ImageData(dimensions=(5, 4, 3), spacing=(1.0, 2.0, 1.0))
    img.point_data["s"] = v.ravel()                                   # VTK: x fastest
    img.save(tmp_path / "v.vti")
    f = V.load_volume(tmp_path / "v.vti")
    np.testing.assert_array_equal(f.values, ref.values)
    np.testing.assert_allclose(f.source_spacing, [1, 2, 1])


def test_real_volumes_load(data_dir):
    eng = V.load_volume(data_dir / "engine-ct" / "engine_256x256x128_uint8.raw.gz")
    assert eng.shape == (256, 256, 128) and eng.values.shape == (128, 256, 256)
    lo, hi = eng.bounds()
    np.testing.assert_allclose(hi, [1, 1, 127 / 255], atol=1e-9)
    np.testing.assert_allclose(lo, -hi)
    assert eng.values.min() == 0 and eng.values.max() == 1
    c60 = V.load_volume(data_dir / "c60" / "C60Large.cvol")
    assert c60.shape == (128, 128, 128)
    head = V.load_volume(data_dir / "headmr" / "HeadMRVolume.mhd")
    assert head.shape == (48, 62, 42) and np.allclose(head.source_spacing, 4.0)
    assert V.load_volume(data_dir / "headmr" / "HeadMRVolume.mhd").values.std() > 0.05
