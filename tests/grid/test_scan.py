"""Measured scans in (``mi-tetvr process-xray``): a Data Exchange HDF5 file made
here from a phantom's exact line integrals (:func:`line_integrals`, the
trilinear field) with a known rotation centre, counts, flat and dark fields;
and the bad files a user meets."""
import json

import numpy as np
import pytest

from mi_tetvr.cli import main as cli
from mi_tetvr.grid.scan import (find_center, held_out_split, scan_cameras, scan_grid,
                                transmittance, read_data_exchange)
from mi_tetvr.grid.volume import Volume
from mi_tetvr.grid.xray import line_integrals

h5py = pytest.importorskip("h5py")

W, H, N, CENTER, PIXEL = 48, 2, 60, 26.0, 0.05
DARK, FLAT = 100.0, 5000.0


def phantom_slices(shape_xyz, origin):
    """Two ellipses of different densities in each z slice (z, y, x)."""
    nx, ny, nz = shape_xyz
    x = origin[0] + np.arange(nx) * PIXEL
    y = origin[1] + np.arange(ny) * PIXEL
    yy, xx = np.meshgrid(y, x, indexing="ij")
    v = 0.6 * (((xx - 0.15) / 0.55) ** 2 + ((yy + 0.1) / 0.4) ** 2 <= 1)
    v += 0.4 * (((xx + 0.3) / 0.2) ** 2 + ((yy - 0.25) / 0.3) ** 2 <= 1)
    return np.repeat(v[None], nz, 0)


def make_scan(path, theta=None, flats=True, darks=True, units="degrees", center=CENTER,
              angles=N, rows=H):
    """Counts of a phantom scanned about the z axis with the axis on column
    ``center``; returns the true transmittance and the phantom's Volume."""
    shape, origin = scan_grid(W, rows, PIXEL, center)
    vol = Volume(phantom_slices(shape, origin).astype(np.float32), np.full(3, PIXEL), origin)
    deg = np.arange(angles) * 180.0 / angles
    cams = scan_cameras(deg, W, rows, PIXEL, center)
    t = np.stack([np.exp(-2.0 * line_integrals(vol, *c.rays())).reshape(rows, W)
                  for c in cams])
    with h5py.File(path, "w") as f:
        f["exchange/data"] = (DARK + FLAT * t).astype(np.float32)
        if flats:
            f["exchange/data_white"] = np.full((3, rows, W), DARK + FLAT, np.float32)
        if darks:
            f["exchange/data_dark"] = np.full((2, rows, W), DARK, np.float32)
        th = deg if theta is None else theta
        f["exchange/theta"] = th
        if units:
            f["exchange/theta"].attrs["units"] = units
    return t, vol


def test_process_xray_corrects_centres_and_holds_out(tmp_path, capsys):
    """Flat/dark correction gives back the transmittance exactly, Vo's method
    finds the shifted rotation centre within a quarter pixel, every 8th angle
    is held out, and the written cameras put column ``center`` on the axis;
    FBP of the written training views on the recorded grid recovers the
    phantom (the geometry, cameras and grid agree)."""
    from mi_tetvr.grid.slices import reconstruct_slices
    from mi_tetvr.recon.datasets import load_dataset
    t, vol = make_scan(tmp_path / "scan.h5")
    scan = read_data_exchange(tmp_path / "scan.h5")
    np.testing.assert_allclose(transmittance(scan), t, rtol=1e-5, atol=1e-6)
    b = -np.log(transmittance(scan))
    assert abs(find_center(b, scan.angles) - CENTER) <= 0.25
    cli(["process-xray", str(tmp_path / "scan.h5"), "-o", str(tmp_path / "d"), "--flux",
         "none", "--pixel-size", str(PIXEL)])
    info = json.loads((tmp_path / "d" / "xray_info.json").read_text())
    assert abs(info["center"] - CENTER) <= 0.25
    assert len(info["angles_test_deg"]) == N // 8 and \
        len(info["angles_train_deg"]) == N - N // 8
    data = load_dataset(tmp_path / "d")
    assert data.xray_flux is None
    # the held-out images are the scan's own angles' transmittance
    test_idx = held_out_split(N, 8)[1]
    for v, i in zip(data.test, test_idx):
        np.testing.assert_allclose(1.0 - v.image[..., 3], t[i], atol=2e-6)
    # FBP on the recorded grid (exact centre given: 26) against the phantom
    cli(["process-xray", str(tmp_path / "scan.h5"), "-o", str(tmp_path / "e"), "--flux",
         "none", "--pixel-size", str(PIXEL), "--center", str(CENTER)])
    data = load_dataset(tmp_path / "e")
    fbp = reconstruct_slices(vol, data.train, 2.0, "fbp")
    truth = vol.values.astype(np.float64)
    err = np.sqrt(np.mean((np.clip(fbp, 0, 1) - truth) ** 2))
    mirrored = np.sqrt(np.mean((np.clip(fbp[:, :, ::-1], 0, 1) - truth) ** 2))
    assert err < 0.12 and mirrored > 2 * err, (err, mirrored)
    assert "rotation centre at column 26.00" in capsys.readouterr().out


def test_recentring_a_whole_pixel_shift_is_exact(tmp_path):
    """The same projections with the axis on another column (the detector
    shifted by 3 pixels: the counts moved 3 columns, air coming in) give the
    same FBP on the same grid."""
    from mi_tetvr.grid.slices import reconstruct_slices
    from mi_tetvr.recon.datasets import load_dataset
    make_scan(tmp_path / "a.h5")
    with h5py.File(tmp_path / "a.h5") as f, h5py.File(tmp_path / "b.h5", "w") as g:
        for key in ("data_white", "data_dark", "theta"):
            f.copy(f[f"exchange/{key}"], g.require_group("exchange"), key)
        shifted = np.full(f["exchange/data"].shape, DARK + FLAT, np.float32)
        shifted[..., :-3] = f["exchange/data"][..., 3:]
        g["exchange/data"] = shifted
    shape, origin = scan_grid(W, H, PIXEL, CENTER)
    grid = Volume(np.zeros((H, shape[1], shape[0]), np.float32), np.full(3, PIXEL), origin)
    out = []
    for name, c in (("a", CENTER), ("b", CENTER - 3.0)):
        cli(["process-xray", str(tmp_path / f"{name}.h5"), "-o", str(tmp_path / name),
             "--center", str(c), "--flux", "none", "--pixel-size", str(PIXEL),
             "--hold-out", "0"])
        out.append(reconstruct_slices(grid, load_dataset(tmp_path / name).train, 2.0, "fbp"))
    # the first 3 columns, lost by the shift, lie outside the phantom
    np.testing.assert_allclose(out[0], out[1], atol=1e-5 * np.abs(out[0]).max())


def test_angles_in_radians_are_detected(tmp_path):
    make_scan(tmp_path / "r.h5", theta=np.radians(np.arange(N) * 180.0 / N), units=None)
    scan = read_data_exchange(tmp_path / "r.h5")
    np.testing.assert_allclose(scan.angles, np.arange(N) * 180.0 / N, atol=1e-9)
    assert any("radians" in n for n in scan.notes)
    make_scan(tmp_path / "d.h5", units=None)
    scan = read_data_exchange(tmp_path / "d.h5")
    assert scan.angles[-1] == pytest.approx(177.0) and any("degrees" in n for n in scan.notes)


@pytest.mark.parametrize("case, message", [
    ("no flats", "no flat fields"),
    ("angle count", "holds 59 angles for 60 projections"),
    ("not hdf5", "is not an HDF5 file"),
    ("no angles", "has no angles"),
])
def test_bad_scans_are_one_line_errors(tmp_path, capsys, case, message):
    path = tmp_path / "s.h5"
    if case == "no flats":
        make_scan(path, flats=False)
    elif case == "angle count":
        make_scan(path, theta=np.arange(N - 1) * 3.0)
    elif case == "not hdf5":
        path.write_text("not a scan")
    else:
        make_scan(path)
        with h5py.File(path, "a") as f:
            del f["exchange/theta"]
    with pytest.raises(SystemExit) as e:
        cli(["process-xray", str(path), "-o", str(tmp_path / "out")])
    assert message in str(e.value) and str(e.value).startswith("mi-tetvr: ")
    assert "\n" not in str(e.value)


def test_missing_darks_and_given_angles_are_said(tmp_path, capsys):
    make_scan(tmp_path / "s.h5", darks=False)
    with h5py.File(tmp_path / "s.h5", "a") as f:
        del f["exchange/theta"]
    cli(["process-xray", str(tmp_path / "s.h5"), "-o", str(tmp_path / "o"), "--angles", "0,177",
         "--center", "26", "--hold-out", "0"])
    out = capsys.readouterr().out
    assert "no dark fields" in out and "angles 0 to 177 degrees as given" in out


def test_one_row_scan_fits_as_many_unknowns_as_its_slice(tmp_path):
    """A detector with one row: the tets' slab has two vertex layers that no
    ray tells apart, so the fit ties them (one unknown per sample of the
    slice, as the grid it is compared with has); the slab's layers come out
    equal and the slice recovers the phantom better than FBP does."""
    from mi_tetvr.grid.slices import reconstruct_slices
    from mi_tetvr.mesh.io import read_tetmesh
    from mi_tetvr.mesh.sample import sample_field
    from mi_tetvr.recon.config import FitConfig
    from mi_tetvr.recon.datasets import load_dataset
    from mi_tetvr.recon.pipeline import run
    _, vol = make_scan(tmp_path / "s.h5", rows=1, angles=30)
    cli(["process-xray", str(tmp_path / "s.h5"), "-o", str(tmp_path / "d"), "--center",
         str(CENTER), "--pixel-size", str(PIXEL), "--flux", "none", "-q"])
    data = load_dataset(tmp_path / "d")
    m = run(data, tmp_path / "fit", FitConfig(model="absorption", passes=8, validation=0,
                                              basis="linear"),
            progress=False, log=lambda *a: None)
    nx, ny, nz = vol.shape
    assert nz == 1 and m["unknowns"] == nx * ny
    mesh = read_tetmesh(tmp_path / "fit" / "attenuation.vtu", opacity="attenuation")
    assert len(mesh.vertices) == 2 * nx * ny
    z = mesh.vertices[:, 2]
    lo, hi = np.argsort(z)[:nx * ny], np.argsort(z)[nx * ny:]
    a = mesh.opacity[lo][np.lexsort(mesh.vertices[lo, :2].T)]
    b = mesh.opacity[hi][np.lexsort(mesh.vertices[hi, :2].T)]
    np.testing.assert_array_equal(a, b)
    truth = vol.values.astype(np.float64)
    tets = sample_field(mesh.vertices, mesh.tets, mesh.opacity / 2.0,
                        vol.sample_points()).reshape(truth.shape)
    fbp = reconstruct_slices(vol, data.train, 2.0, "fbp")
    rms = lambda v: np.sqrt(np.mean((np.clip(v, 0, 1) - truth) ** 2))  # noqa: E731
    assert rms(tets) < rms(fbp), (rms(tets), rms(fbp))
    # the trilinear basis (the default) ties them alike: the walked tets' three layers
    # are one slice
    m = run(data, tmp_path / "tri", FitConfig(model="absorption", passes=8, validation=0),
            progress=False, log=lambda *a: None)
    assert m["unknowns"] == nx * ny and m["solver"]["basis"] == "trilinear"
    mesh = read_tetmesh(tmp_path / "tri" / "attenuation.vtu", opacity="attenuation")
    layers = np.round(mesh.vertices[:, 2], 9)
    assert len(np.unique(layers)) == 3 and len(mesh.vertices) == 3 * (2 * nx - 1) * (2 * ny - 1)
    slices = [mesh.opacity[layers == z][np.lexsort(mesh.vertices[layers == z, :2].T)]
              for z in np.unique(layers)]
    np.testing.assert_allclose(slices[0], slices[1], atol=1e-6)
    np.testing.assert_allclose(slices[0], slices[2], atol=1e-6)
    tri = sample_field(mesh.vertices, mesh.tets, mesh.opacity / 2.0,
                       vol.sample_points()).reshape(truth.shape)
    assert rms(tri) < rms(fbp), (rms(tri), rms(fbp))
