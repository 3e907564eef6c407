"""The render modes against what VTK offers for each, on the same mesh and
image: ``tetproj``'s isosurface against ``vtkContourFilter`` + rendering its
triangles, its slice against ``vtkCutter`` + rendering the cut, ``tetvr``
clipped against ``vtkClipDataSet`` + VTK's unstructured-grid ray caster, and
every mode against ``tetvr``'s plain volume rendering of the same mesh.

VTK's times are the filter (once, what a change of isovalue or plane costs)
and a warm render (offscreen, on this machine's OpenGL, software where there
is no GPU); the project's are a warm ``mi.render`` (median of ``--repeat``),
which redoes everything each frame. VTK has no intensity projection for
unstructured grids on the CPU (ParaView resamples to an image first), so the
projections are timed against volume rendering only.

Usage::

    python benchmarks/bench_modes.py                # Blunt Fin's Density, 512x512
    python benchmarks/bench_modes.py --quick        # SPX, 64x64
"""
from __future__ import annotations

import sys
import time
import warnings
from pathlib import Path

import numpy as np

from common import (header, make_parser, timed, vtk_offscreen, vtk_ray_cast_volume,
                    write_json)

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "tets"
MESHES = {"bluntfin": ("bluntfin/bluntfin_tets.vtu", "Density"),
          "spx": ("spx/spx.vtk", "scalars")}


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=3, quick="SPX, 64x64")
    p.add_argument("--res", type=int, default=512, help="image size (default 512)")
    p.add_argument("--mesh", choices=tuple(MESHES), default="bluntfin")
    a = p.parse_args(argv)
    if a.quick:
        a.res, a.mesh = 64, "spx"
    return a


ARGS = parse_args()

import mitsuba as mi  # noqa: E402

mi.set_variant(ARGS.variant)
import mi_tetvr  # noqa: E402,F401


def view(lo, hi):
    centre, diag = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    return centre + diag * np.array([0.7, -0.9, 0.6]), centre, 35.0


def ours(path, scalar, integrator, eye, target, fov, res, repeat):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = mi.load_dict({
            "type": "scene", "integrator": integrator,
            "sensor": {"type": "perspective", "fov": fov, "fov_axis": "y",
                       "to_world": mi.ScalarTransform4f().look_at(
                           origin=eye.tolist(), target=target.tolist(), up=[0, 0, 1]),
                       "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
                       "film": {"type": "hdrfilm", "width": res, "height": res,
                                "rfilter": {"type": "box"}}},
            "volume": {"type": "tetmesh", "filename": str(path), "transfer_function": "viridis",
                       "scalar_attribute": scalar}})
    _, med, runs, _ = timed(lambda: np.array(mi.render(scene, spp=1)), repeat)
    return med, runs


def vtk_surface(grid, make_filter, res, eye, target, fov, repeat):
    """(filter seconds, warm render seconds, runs) of a filter's polygons."""
    vtk, ren, win = vtk_offscreen(res, eye, target, fov)
    t0 = time.perf_counter()
    f = make_filter(vtk)
    f.SetInputData(grid)
    f.Update()
    filtered = time.perf_counter() - t0
    mapper = vtk.vtkPolyDataMapper()
    mapper.SetInputConnection(f.GetOutputPort())
    actor = vtk.vtkActor()
    actor.SetMapper(mapper)
    ren.AddActor(actor)
    ren.ResetCameraClippingRange()
    _, med, runs, _ = timed(win.Render, repeat)
    return filtered, med, runs


def vtk_clipped_volume(grid, origin, normal, res, eye, target, fov, repeat):
    vtk, ren, win = vtk_offscreen(res, eye, target, fov)
    t0 = time.perf_counter()
    clip = vtk.vtkClipDataSet()
    clip.SetInputData(grid)
    clip.SetClipFunction(_plane(vtk, origin, normal))
    clip.InsideOutOn()
    tri = vtk.vtkDataSetTriangleFilter()
    tri.SetInputConnection(clip.GetOutputPort())
    tri.Update()
    filtered = time.perf_counter() - t0
    lo, hi = grid.GetPointData().GetScalars().GetRange()
    ctf = vtk.vtkColorTransferFunction()
    ctf.AddRGBPoint(lo, 0.1, 0.2, 0.6)
    ctf.AddRGBPoint(hi, 0.9, 0.9, 0.3)
    otf = vtk.vtkPiecewiseFunction()
    otf.AddPoint(lo, 0.0)
    otf.AddPoint(hi, 1.0)
    vtk_ray_cast_volume(vtk, ren, tri.GetOutputPort(), ctf, otf)
    _, med, runs, _ = timed(win.Render, repeat)
    return filtered, med, runs


def main(a):
    info = header("render modes benchmark")
    import pyvista as pv
    rel, scalar = MESHES[a.mesh]
    path = DATA / rel
    if not path.is_file():
        print(f"skipped: {path} not found")
        write_json(a, info, {"skipped": str(path)})
        return 0
    grid = pv.read(path)
    grid.set_active_scalars(scalar)
    values = np.asarray(grid.point_data[scalar])
    lo, hi = np.asarray(grid.bounds).reshape(3, 2).T
    eye, target, fov = view(lo, hi)
    iso = float(np.median(values))
    centre = ((lo + hi) / 2).tolist()
    normal = [0.0, 0.0, 1.0]
    print(f"{a.mesh}: {grid.n_cells:,} tets, '{scalar}', {a.res}x{a.res}; isovalue {iso:.4g} "
          f"(the median), plane through the centre, normal +z")
    rows = []
    dvr, dvr_runs = ours(path, scalar, {"type": "tetvr"}, eye, target, fov, a.res, a.repeat)
    rows.append(dict(mode="volume rendering (tetvr)", ours_s=dvr, ours_runs=dvr_runs,
                     note="(VTK's ray caster: bench_vtk.py)"))
    for mode, extra in (("max", {}), ("mean", {}), ("slice", {"origin": centre, "normal": normal}),
                        ("iso", {"iso": str(iso)})):
        s, runs = ours(path, scalar, {"type": "tetproj", "mode": mode, **extra}, eye, target,
                       fov, a.res, a.repeat)
        row = dict(mode=f"{mode} (tetproj)", ours_s=s, ours_runs=runs,
                   note="(none for unstructured grids on the CPU)")
        if mode == "iso":
            f, r, rr = vtk_surface(grid, lambda vtk: _contour(vtk, scalar, iso), a.res, eye,
                                   target, fov, a.repeat)
            row.update(vtk="vtkContourFilter + render", vtk_filter_s=f, vtk_render_s=r)
        elif mode == "slice":
            f, r, rr = vtk_surface(grid, lambda vtk: _cutter(vtk, centre, normal), a.res, eye,
                                   target, fov, a.repeat)
            row.update(vtk="vtkCutter + render", vtk_filter_s=f, vtk_render_s=r)
        rows.append(row)
    for name, opacity in (("volume + isosurface", 1.0), ("volume + iso, opacity 0.5", 0.5)):
        overlay = {"type": "tetproj", "mode": "iso", "iso": str(iso), "opacity": opacity}
        s, runs = ours(path, scalar, {"type": "tetvr", "overlay": overlay}, eye, target, fov,
                       a.res, a.repeat)
        rows.append(dict(mode=name, ours_s=s, ours_runs=runs,
                         note="(tetvr with a tetproj overlay)"))
    s, runs = ours(path, scalar, {"type": "tetvr", "clip_origin": centre, "clip_normal": normal},
                   eye, target, fov, a.res, a.repeat)
    f, r, rr = vtk_clipped_volume(grid, centre, normal, a.res, eye, target, fov, a.repeat)
    rows.append(dict(mode="clipped volume (tetvr)", ours_s=s, ours_runs=runs,
                     vtk="vtkClipDataSet + unstructured ray caster", vtk_filter_s=f,
                     vtk_render_s=r))
    print(f"{'mode':<28}{'ours [s]':>10}{'/ DVR':>8}{'VTK filter [s]':>16}{'VTK render [s]':>16}"
          f"  VTK")
    for row in rows:
        v = (f"{row['vtk_filter_s']:>16.3f}{row['vtk_render_s']:>16.3f}  {row['vtk']}"
             if "vtk" in row else f"{'-':>16}{'-':>16}  {row['note']}")
        print(f"{row['mode']:<28}{row['ours_s']:>10.3f}{row['ours_s'] / dvr:>7.2f}x{v}")
    write_json(a, info, {"mesh": a.mesh, "res": a.res, "iso": iso, "rows": rows})
    return 0


def _contour(vtk, scalar, value):
    f = vtk.vtkContourFilter()
    f.SetInputArrayToProcess(0, 0, 0, 0, scalar)
    f.SetValue(0, value)
    return f


def _plane(vtk, origin, normal):
    plane = vtk.vtkPlane()
    plane.SetOrigin(*origin)
    plane.SetNormal(*normal)
    return plane


def _cutter(vtk, origin, normal):
    f = vtk.vtkCutter()
    f.SetCutFunction(_plane(vtk, origin, normal))
    return f


if __name__ == "__main__":
    sys.exit(main(ARGS))
