"""``mi-tetvr make-dataset VOLUME -o DIR``: a NeRF-style data set of a scalar grid volume
(the grid ray marcher) or of a scalar tet mesh (``tetvr``; with ``--lights``, a scattering
medium path traced by ``tetpath`` under known lights) through a transfer function, or X-ray
projections of a grid volume (``--xray``)."""
from __future__ import annotations

from pathlib import Path

from mi_tetvr.apps.settings import OPACITY_SCALE
from mi_tetvr.cli import flags
from mi_tetvr.cli.common import is_mesh_file, refuse, set_variant
from mi_tetvr.extras import require

NAME = "make-dataset"
HELP = ("render a scalar volume or tet mesh into a NeRF-style data set, or project a volume "
        "into X-ray images")

#: The default of ``--test-views`` (the held-out views of every data set maker).
TEST_VIEWS = 8


def add_arguments(p):
    p.add_argument("volume", help="scalar grid (.npy, .cvol, .mhd, .vti, raw .gz) or scalar "
                   "tet mesh (.vtu, .vtk, .msh, .mesh)")
    flags.out(p, "data set folder")
    p.add_argument("--tf", help="transfer function (.json: the project's or a ParaView colormap; "
                   "DiffTetVR .xml; or a matplotlib colormap's name)")
    p.add_argument("--scalar", help="the tet mesh's scalar point array (default: the only one)")
    p.add_argument("--views", type=int, default=64, help="training views (default 64)")
    p.add_argument("--test-views", type=int, default=TEST_VIEWS,
                   help=f"held-out views (default {TEST_VIEWS})")
    flags.res(p, None, "image size, WxH or N (default 256; X-ray: one pixel per voxel)")
    p.add_argument("--value-range", help="lo,hi of the values the transfer function spans "
                   "(default: the data's range)")
    flags.opacity_scale(p)
    p.add_argument("--radius", type=float, help="grid volume: camera distance from the centre "
                   "of its [-1, 1]^3 box (default 4); X-ray cone beam: source distance "
                   "(default 3)")
    p.add_argument("--fov", type=float, help="horizontal field of view in degrees (default: "
                   "frames the grid's box; 40 around a tet mesh and for a cone beam)")
    p.add_argument("--seed", type=int, help="seed of the random held-out cameras (default 0)")
    p.add_argument("--xray", action="store_true", help="X-ray transmittance images (.npy) of "
                   "the grid volume's attenuation: exact line integrals of its trilinear field")
    p.add_argument("--beam", choices=("parallel", "cone"), help="X-ray: parallel beam "
                   "(orthographic, over 180 degrees; default) or cone beam (perspective, "
                   "over 360)")
    p.add_argument("--arc", type=float, help="X-ray: the degrees the training angles span "
                   "(default 180 for a parallel beam, 360 for a cone beam; less: a "
                   "limited-angle scan)")
    p.add_argument("--attenuation", type=float, help="X-ray: attenuation per unit length of a "
                   "normalised value 1 (default: from --max-depth)")
    p.add_argument("--max-depth", type=float, help="X-ray: the largest optical depth of a "
                   "training ray (default 2.5)")
    p.add_argument("--flux", type=float, help="X-ray: photons per pixel of the unattenuated "
                   "beam: the training projections are Poisson counts (the fit weights its "
                   "rays by them); default: noise-free")
    p.add_argument("--detail", type=int, help="X-ray: integrate the volume's cubic B-spline "
                   "K times finer than its samples, a field no reconstruction on them models "
                   "exactly (default 1: its trilinear field)")
    p.add_argument("--lights", metavar="XML", help="tet mesh: a Mitsuba scene file of known "
                   "lighting (emitters, surfaces around): the mesh is a scattering medium "
                   "(the transfer function's colors its albedo, its opacity the extinction, "
                   "classified at the vertices), path traced by tetpath under those lights "
                   "(for fit --model scattering --lights XML)")
    p.add_argument("--spp", type=int, help="--lights: samples per pixel (default 256)")
    flags.mesh_flags(p)
    flags.quiet(p)
    flags.variant(p)


def check(a, is_mesh, path):
    """``ValueError`` for the options that do not apply to the input (X-ray projections,
    a grid volume, a tet mesh)."""
    if a.xray:
        refuse(a, ("tf", "scalar", "res", "seed"), "to X-ray projections (one pixel per "
               "voxel; the angles are even, not random)")
        if a.opacity_scale != OPACITY_SCALE:
            raise ValueError("--opacity-scale does not apply to X-ray projections "
                             "(--attenuation or --max-depth set the attenuation)")
        if is_mesh:
            raise ValueError(f"--xray projects a grid volume, not the tet mesh {path}")
        if (a.beam or "parallel") == "parallel":
            refuse(a, ("fov", "radius"), "to a parallel beam (--beam cone has them)")
    else:
        refuse(a, ("beam", "arc", "attenuation", "max_depth", "flux", "detail"),
               "without --xray")
        if a.tf is None:
            raise ValueError("make-dataset needs --tf (or --xray for X-ray projections)")
        if is_mesh:
            refuse(a, ("radius",), "to a tet mesh (the cameras frame its bounding sphere "
                   "in --fov)")
            if a.lights is None:
                refuse(a, ("spp",), "without --lights (the emission-absorption images are "
                       "exact through pixel centres)")
        else:
            refuse(a, ("scalar", "repair", "cell_to_point", "lights", "spp"),
                   "to a grid volume")
    if a.xray:
        refuse(a, ("lights", "spp"), "to X-ray projections")


def run(a):
    from mi_tetvr.recon.config import _numbers
    path = Path(a.volume)
    if not path.exists():
        raise FileNotFoundError(f"file not found: {path}")
    vr = None if a.value_range is None else _numbers(2)(a.value_range)
    is_mesh = is_mesh_file(path)
    check(a, is_mesh, path)
    if not (a.xray or is_mesh):
        require("recon", "make-dataset of a grid volume (its PNG images)", "PIL")
    set_variant(a.variant)
    seed = 0 if a.seed is None else a.seed
    if a.xray:
        return xray(a, path, vr, seed)
    from mi_tetvr.grid import load_volume
    from mi_tetvr.recon.synthetic import make_dataset
    from mi_tetvr.transfer import read_transfer_function
    res = a.res or (256, 256)
    if is_mesh:
        from mi_tetvr.recon.synthetic import make_mesh_dataset
        info = make_mesh_dataset(path, a.tf, a.out, views=a.views, test_views=a.test_views,
                                 res=res, scalar=a.scalar, opacity_scale=a.opacity_scale,
                                 fov=40.0 if a.fov is None else a.fov, seed=seed,
                                 value_range=vr, repair=a.repair,
                                 cell_to_point=a.cell_to_point, progress=not a.quiet,
                                 lights=a.lights, spp=a.spp or 256)
        lit = f" lit by {a.lights}" if a.lights else ""
        print(f"wrote {a.views} training and {a.test_views} test views at {res[0]}x{res[1]} "
              f"of '{info['scalar']}'{lit} to {a.out}")
        return
    volume = load_volume(path, value_range=vr)
    tf = read_transfer_function(a.tf)
    make_dataset(volume, tf, views=a.views, res=res, out_dir=a.out, test_views=a.test_views,
                 seed=seed, radius=4.0 if a.radius is None else a.radius, fov=a.fov,
                 opacity_scale=a.opacity_scale, progress=not a.quiet)
    print(f"wrote {a.views} training and {a.test_views} test views at {res[0]}x{res[1]} to "
          f"{a.out}")


def xray(a, path, vr, seed):
    """``make-dataset --xray``: parallel- or cone-beam projections of a grid volume."""
    from mi_tetvr.grid import load_volume
    from mi_tetvr.grid.xray import MAX_DEPTH
    from mi_tetvr.recon.synthetic import make_xray_dataset
    beam = a.beam or "parallel"
    geometry = {} if beam == "parallel" else {
        "distance": 3.0 if a.radius is None else a.radius,
        "fov": 40.0 if a.fov is None else a.fov}
    if a.flux is not None and not a.flux > 0:
        raise ValueError(f"--flux must be > 0 photons, got {a.flux:g}")
    if a.detail is not None and a.detail < 1:
        raise ValueError(f"--detail must be a positive integer, got {a.detail}")
    info = make_xray_dataset(load_volume(path, value_range=vr), a.out, views=a.views,
                             test_views=a.test_views, beam=beam, scale=a.attenuation,
                             max_depth=MAX_DEPTH if a.max_depth is None else a.max_depth,
                             flux=a.flux, seed=seed, detail=a.detail or 1,
                             progress=not a.quiet, arc=a.arc, **geometry)["info"]
    if "resampled_from" in info:
        print(f"the volume's spacings differ ({info['resampled_from']['spacing']}): "
              f"resampled to {info['volume']['shape_xyz']} samples of its x spacing for "
              f"the parallel beam's square pixels on the z samples")
    print(f"wrote {a.views} training and {a.test_views} test {beam}-beam projections "
          f"over {info['arc_deg']:g} degrees "
          f"(attenuation {info['attenuation_scale']:.4g} per unit, largest optical depth "
          f"{info['max_depth']:.2f}; noise: {info['noise']}) to {a.out}")
