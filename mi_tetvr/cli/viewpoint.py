"""``mi-tetvr viewpoint MESH -o DIR``: the camera position of highest opacity entropy
(DiffDVR's best viewpoint, :mod:`mi_tetvr.apps.viewpoint`), by gradient ascent on the
sphere, with the entropy over the sphere plotted."""
from __future__ import annotations

import json
import time
from pathlib import Path

from mi_tetvr.apps.settings import OPACITY_SCALE
from mi_tetvr.cli import flags
from mi_tetvr.cli.common import CommandError, plugin_error, read_mesh, set_variant, write_render
from mi_tetvr.extras import require

NAME = "viewpoint"
HELP = ("the camera position of highest opacity entropy (DiffDVR's best viewpoint), by "
        "gradient ascent on the sphere")

#: The search camera's horizontal field of view (degrees).
FOV = 40.0


def add_arguments(p):
    p.add_argument("mesh", help="tet mesh file")
    flags.out(p, "folder for viewpoint.json, view.png and viewpoint.png (the entropy over the "
                 "sphere, the ascent paths)")
    p.add_argument("--tf", help="transfer function (post-classifies the scalar): a file, or a "
                   "matplotlib colormap's name")
    p.add_argument("--scalar", help="the scalar point array (default: the only one)")
    flags.opacity_scale(p)
    flags.res(p, (128, 128))
    p.add_argument("--starts", type=int, default=8, help="ascent starts (default 8)")
    p.add_argument("--iterations", type=int, default=20, help="steps per start (default 20)")
    p.add_argument("--samples", type=int, default=256,
                   help="Fibonacci-sphere views for comparison (default 256)")
    flags.mesh_flags(p)
    flags.quiet(p)
    flags.variant(p)


def run(a):
    import warnings

    require("vis", "mi-tetvr viewpoint", "matplotlib")
    set_variant(a.variant)
    from mi_tetvr.apps.viewpoint import (ViewpointSearch, best_viewpoint, default_starts,
                                         orbit_scene, plot_viewpoints)
    from mi_tetvr.mesh.topology import bounding_radius
    from mi_tetvr.progress import progress_bar as tqdm
    path = Path(a.mesh)
    if not path.exists():
        raise FileNotFoundError(f"mesh file not found: {path}")
    mesh = read_mesh(a, path)
    lo, hi = mesh.bounds
    radius = bounding_radius(mesh.vertices)
    shape = {"type": "tetmesh", "filename": str(path.resolve()), "repair": a.repair,
             "cell_to_point": a.cell_to_point}
    if a.tf:
        # a file, or a matplotlib colormap's name
        shape["transfer_function"] = str(Path(a.tf).resolve()) if Path(a.tf).exists() else a.tf
        if a.scalar:
            shape["scalar_attribute"] = a.scalar
        shape["opacity_scale"] = a.opacity_scale / radius
    elif a.scalar:
        raise ValueError("--scalar needs --tf")
    elif a.opacity_scale != OPACITY_SCALE:
        raise ValueError("--opacity-scale scales a transfer function's opacity: it needs --tf")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            scene, centre, distance = orbit_scene(shape, (lo, hi), a.res, FOV)
    except Exception as e:
        raise CommandError(f"cannot load {path}: {plugin_error(e)}") from None
    search = ViewpointSearch(scene, centre.tolist(), distance, up=(0.0, 0.0, 1.0))
    starts = default_starts(a.starts)
    t0 = time.time()
    with tqdm(total=a.samples + len(starts), desc="viewpoint", disable=a.quiet) as bar:
        result = best_viewpoint(search, starts, a.iterations, a.samples, bar.update)
    result["seconds"] = time.time() - t0
    result.update(mesh=str(path), distance=distance, target=centre.tolist(), fov=FOV,
                  resolution=list(a.res), iterations=a.iterations)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "viewpoint.json").write_text(json.dumps(result, indent=1) + "\n")
    image = search.image(result["longitude"], result["latitude"])
    write_render(str(out / "view.png"), image[..., :3], image[..., 3])
    plot_viewpoints(result, out / "viewpoint.png")
    b = result["best_sampled"]
    print(f"{path}: longitude {result['longitude']:.1f}, latitude {result['latitude']:.1f} deg, "
          f"opacity entropy {result['entropy']:.4f} ({100 * result['ratio_to_best_sampled']:.1f} % "
          f"of the best of {b['samples']} sampled views, {b['entropy']:.4f}); "
          f"{result['seconds']:.0f} s -> {out}")
