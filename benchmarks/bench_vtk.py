"""A peer, side by side: ``tetvr`` against VTK's unstructured-grid ray caster.

VTK's ``vtkUnstructuredGridVolumeRayCastMapper`` with the
``vtkUnstructuredGridLinearRayIntegrator`` (which integrates a transfer
function that is linear between its points exactly along each cell segment)
renders a tet mesh with a scalar field, offscreen; ``tetvr`` renders the same
mesh post-classified with the same transfer function (resampled to
``--tf-resolution`` texels), from the same perspective camera, at the same
size, one ray per pixel centre, no early termination in either.

Per mesh (Blunt Fin's ``Density``, SPX's ``scalars``; ``../shared/data``):
the warm render time of each (median of ``--repeat``), their ratio, the
PSNR between the two images, and, on ``--pixels`` random pixels, each one's
largest error against the float64 reference that classifies after
interpolation (``tests/reference.py``), which tells which of two disagreeing
images is right. VTK writes the integrated color to an 8-bit
framebuffer as it is (no sRGB encoding), so both images are compared as
8-bit values of the linear color over black, which is the scale the peer
has (not the sRGB scale of the reconstruction metrics).

Usage::

    python benchmarks/bench_vtk.py            # 512x512
    python benchmarks/bench_vtk.py --quick    # SPX only, 64x64
"""
from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np

from common import header, make_parser, timed, vtk_offscreen, vtk_ray_cast_volume, write_json

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "tets"
MESHES = {"bluntfin": ("bluntfin/bluntfin_tets.vtu", "Density"),
          "spx": ("spx/spx.vtk", "scalars")}
#: Transfer function control points on the normalised scalar axis: a faint
#: ramp with one peak (color linear RGB, opacity per unit of the mesh's
#: diagonal / OPACITY_PER_DIAGONAL).
COLOR = [(0.0, (0.1, 0.2, 0.6)), (0.3, (0.2, 0.6, 0.9)), (0.5, (1.0, 0.5, 0.1)),
         (1.0, (0.9, 0.9, 0.8))]
OPACITY = [(0.0, 0.0), (0.25, 0.05), (0.35, 1.0), (0.45, 0.05), (1.0, 0.2)]
OPACITY_PER_DIAGONAL = 4.0


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=3, quick="SPX only, 64x64")
    p.add_argument("--res", type=int, default=512, help="image size (default 512)")
    p.add_argument("--meshes", default="bluntfin,spx", help="of bluntfin, spx")
    p.add_argument("--pixels", type=int, default=48,
                   help="pixels checked against the float64 reference (default 48)")
    p.add_argument("--tf-resolution", type=int, default=256,
                   help="tetvr's texels of the transfer function (default 256)")
    a = p.parse_args(argv)
    if a.quick:
        a.res, a.meshes, a.pixels = 64, "spx", 8
    return a


ARGS = parse_args()

import mitsuba as mi  # noqa: E402

mi.set_variant(ARGS.variant)
import mi_tetvr  # noqa: E402,F401


def camera(bounds):
    lo, hi = bounds
    centre, diag = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    return centre + diag * np.array([0.7, -0.9, 0.6]), centre, diag, 35.0


def tf_file(path):
    import json
    path.write_text(json.dumps({"color": [[p, *c] for p, c in COLOR],
                                "opacity": [[p, o] for p, o in OPACITY],
                                "colorspace": "linear"}))
    return path


def render_vtk(path, scalar, vrange, eye, target, fov, res, scale, repeat):
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy
    reader = (vtk.vtkXMLUnstructuredGridReader() if path.suffix == ".vtu"
              else vtk.vtkUnstructuredGridReader())
    reader.SetFileName(str(path))
    reader.Update()
    grid = reader.GetOutput()
    grid.GetPointData().SetActiveScalars(scalar)
    lo, hi = vrange
    ctf = vtk.vtkColorTransferFunction()
    for p, c in COLOR:
        ctf.AddRGBPoint(lo + p * (hi - lo), *c)
    otf = vtk.vtkPiecewiseFunction()
    for p, o in OPACITY:
        otf.AddPoint(lo + p * (hi - lo), o * scale)
    vtk, ren, win = vtk_offscreen(res, eye, target, fov)
    vtk_ray_cast_volume(vtk, ren, grid, ctf, otf)

    def run():
        win.Render()
    first, med, runs, _ = timed(run, repeat)
    grab = vtk.vtkWindowToImageFilter()
    grab.SetInput(win)
    grab.SetInputBufferTypeToRGB()
    grab.ReadFrontBufferOff()
    grab.Update()
    img = vtk_to_numpy(grab.GetOutput().GetPointData().GetScalars()).reshape(res, res, 3)
    return img[::-1].astype(np.float64) / 255.0, med, runs


def render_tetvr(path, scalar, vrange, eye, target, fov, res, scale, tf_path, tf_res, repeat,
                 classification="post"):
    scene = mi.load_dict({
        "type": "scene", "integrator": {"type": "tetvr", "min_transmittance": 0.0},
        "sensor": {"type": "perspective", "fov": fov, "fov_axis": "y",
                   "to_world": mi.ScalarTransform4f().look_at(origin=eye.tolist(),
                                                              target=target.tolist(),
                                                              up=[0, 0, 1]),
                   "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}}},
        "volume": {"type": "tetmesh", "filename": str(path), "transfer_function": str(tf_path),
                   "scalar_attribute": scalar, "value_min": vrange[0], "value_max": vrange[1],
                   "tf_resolution": tf_res, "opacity_scale": scale,
                   "classification": classification}})

    def run():
        img = np.array(mi.render(scene, spp=1))
        return img
    first, med, runs, img = timed(run, repeat)
    return img[..., :3], med, runs


def reference_pixels(mesh, values, vrange, eye, target, fov, res, scale, tf_path, tf_res, n):
    """``n`` random pixel centres and their float64 reference colors."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tests.reference import reference_render_classified
    from mi_tetvr.transfer import read_transfer_function
    sensor = mi.load_dict({"type": "perspective", "fov": fov, "fov_axis": "y",
                           "to_world": mi.ScalarTransform4f().look_at(
                               origin=eye.tolist(), target=target.tolist(), up=[0, 0, 1]),
                           "film": {"type": "hdrfilm", "width": res, "height": res}})
    rng = np.random.default_rng(0)
    py, px = rng.integers(0, res, n), rng.integers(0, res, n)
    ray, _ = sensor.sample_ray(mi.Float(0), mi.Float(0.5),
                               mi.Point2f(mi.Float((px + 0.5) / res), mi.Float((py + 0.5) / res)),
                               mi.Point2f(0.5))
    o, d = np.array(ray.o).T, np.array(ray.d).T
    color, opacity = read_transfer_function(tf_path).texels(tf_res)
    ref, _ = reference_render_classified(mesh.vertices, mesh.tets, values, color,
                                         opacity * scale, vrange, o, d)
    return py, px, ref


def psnr(a, b):
    mse = float(np.mean((np.round(np.clip(a, 0, 1) * 255) / 255 - b) ** 2))
    return 10 * np.log10(1.0 / mse) if mse > 0 else float("inf")


def main(a):
    info = header("VTK comparison benchmark")
    import tempfile
    tf_path = tf_file(Path(tempfile.mkdtemp()) / "tf.json")
    results = []
    print(f"{'mesh':<10}{'tets':>10}{'tetvr [s]':>11}{'VTK [s]':>10}{'VTK / tetvr':>13}"
          f"{'PSNR [dB]':>11}{'tetvr err':>12}{'VTK err':>12}")
    for name in a.meshes.split(","):
        rel, scalar = MESHES[name]
        path = DATA / rel
        if not path.is_file():
            print(f"{name:<10} skipped: {path} not found")
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mesh = mi_tetvr.read_tetmesh(path)
        values = np.asarray(mesh.point_data[scalar]).reshape(-1)
        vrange = (float(values.min()), float(values.max()))
        eye, target, diag, fov = camera(mesh.bounds)
        scale = OPACITY_PER_DIAGONAL / diag
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ours, t_ours, r_ours = render_tetvr(path, scalar, vrange, eye, target, fov, a.res,
                                                scale, tf_path, a.tf_resolution, a.repeat)
        theirs, t_vtk, r_vtk = render_vtk(path, scalar, vrange, eye, target, fov, a.res, scale,
                                          a.repeat)
        q = psnr(ours, theirs)
        py, px, ref = reference_pixels(mesh, values, vrange, eye, target, fov, a.res, scale,
                                       tf_path, a.tf_resolution, a.pixels)
        err_ours = float(np.abs(ours[py, px] - ref).max())
        err_vtk = float(np.abs(theirs[py, px] - ref).max())
        print(f"{name:<10}{len(mesh.tets):>10,}{t_ours:>11.3f}{t_vtk:>10.3f}"
              f"{t_vtk / t_ours:>12.1f}x{q:>11.2f}{err_ours:>12.1e}{err_vtk:>12.1e}")
        modes = {}
        for mode in ("preintegrated", "pre"):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                img, t_mode, _ = render_tetvr(path, scalar, vrange, eye, target, fov, a.res,
                                              scale, tf_path, a.tf_resolution, a.repeat, mode)
            modes[mode] = (t_mode, float(np.abs(img - ours).max()), psnr(img, ours))
        results.append(dict(mesh=name, tets=len(mesh.tets), res=a.res, tetvr_s=t_ours,
                            classifications=modes,
                            tetvr_runs_s=r_ours, vtk_s=t_vtk, vtk_runs_s=r_vtk,
                            vtk_over_tetvr=t_vtk / t_ours, psnr=q, tetvr_max_error=err_ours,
                            vtk_max_error=err_vtk, pixels=a.pixels,
                            mean_tetvr=float(ours.mean()), mean_vtk=float(theirs.mean())))
    print(f"(err: max |RGB - float64 reference| over {a.pixels} random pixels, linear color)")
    print()
    print("tetvr's classifications against its exact post-classification (same camera):")
    print(f"{'mesh':<10}{'classification':<16}{'time [s]':>9}{'/ exact':>9}{'max |diff|':>12}"
          f"{'PSNR [dB]':>11}")
    for r in results:
        for mode, (t, err, q) in r["classifications"].items():
            print(f"{r['mesh']:<10}{mode:<16}{t:>9.3f}{t / r['tetvr_s']:>8.2f}x{err:>12.1e}"
                  f"{q:>11.2f}")
    write_json(a, info, {"meshes": results})
    return 0


if __name__ == "__main__":
    sys.exit(main(ARGS))
