"""Tutorial: a volume out of mi_tetvr, as a colored surface that Blender, MeshLab and
any glTF viewer open, rendered back by Mitsuba's own path tracer.

1. The volume is a jittered tet grid carrying a few soft colored blobs (per-vertex
   color and opacity), rendered by ``tetvr``.
2. Its surface at an opacity level is extracted by VTK's contour filter on the tets
   (marching tets), colored with the field's colors there, and written as ``.ply``,
   ``.obj`` and ``.glb`` (:mod:`mi_tetvr.mesh.export`; ``mi-tetvr export MESH -o
   OUT.ply`` does the same from the command line, for a mesh file or a fit's folder).
   Without a level, the export takes Otsu's threshold of the vertex opacities.
3. The ``.ply`` is loaded by Mitsuba as an ordinary mesh, its vertex colors read by a
   ``mesh_attribute`` texture, and rendered by the ``path`` integrator under a sky
   and a sun: a surface now, which shades and casts shadows.

``--out`` gets the three files and ``export_surface.png``: the volume | the exported
surface, from the same camera.

Run it with::

    python tutorials/export_surface.py
    python tutorials/export_surface.py --level 0.5 --res 256
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import mitsuba as mi


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cells", type=int, default=24, help="grid cells per axis (default 24)")
    p.add_argument("--level", type=float, help="the surface's opacity (default: Otsu's "
                   "threshold of the vertex opacities)")
    p.add_argument("--res", type=int, default=320, help="image side (default 320)")
    p.add_argument("--spp", type=int, default=64, help="path tracer's samples per pixel")
    p.add_argument("--out", default="out/export_surface")
    p.add_argument("--variant", default="llvm_ad_rgb")
    return p.parse_args(argv)


def volume(cells):
    """``(V, T, color, opacity)``: three soft blobs of three colors on a jittered grid."""
    from mi_tetvr.mesh.generate import grid_mesh
    V, T = grid_mesh(cells, jitter=0.1, seed=3)
    centres = np.array([[-0.35, -0.1, 0.0], [0.35, 0.0, 0.1], [0.0, 0.35, -0.2]])
    colors = np.array([[0.8, 0.25, 0.1], [0.1, 0.45, 0.8], [0.85, 0.75, 0.2]])
    w = np.exp(-((V[:, None, :] - centres[None]) ** 2).sum(-1) / (2 * 0.22 ** 2))
    opacity = 6.0 * w.sum(1)
    color = (w[..., None] * colors[None]).sum(1) / np.maximum(w.sum(1, keepdims=True), 1e-9)
    return V, T, color, opacity


def sensor(res):
    return {"type": "perspective", "fov": 38,
            "to_world": mi.ScalarTransform4f().look_at(origin=[2.2, 1.6, 2.6], target=[0, 0, 0],
                                                       up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": res, "height": res,
                     "rfilter": {"type": "gaussian"}}}


def read_back(path):
    """The exported file as a Mitsuba mesh, read by trimesh: its 8-bit sRGB vertex
    colors as the linear ``vertex_color`` attribute that a ``mesh_attribute`` texture
    reads (Mitsuba's own PLY reader expects colors in [0, 1], not bytes)."""
    import trimesh

    from mi_tetvr.color import srgb_to_linear
    m = trimesh.load(path, process=False)
    mesh = mi.Mesh("surface", len(m.vertices), len(m.faces), props=mi.Properties(),
                   has_vertex_normals=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = np.asarray(m.vertices, np.float32).ravel()
    params["faces"] = np.asarray(m.faces, np.uint32).ravel()
    rgb = srgb_to_linear(np.asarray(m.visual.vertex_colors)[:, :3] / 255.0)
    mesh.add_attribute("vertex_color", 3, [0.0])
    params = mi.traverse(mesh)
    params["vertex_color"] = np.asarray(rgb, np.float32).ravel()
    params.update()
    mesh.set_bsdf(mi.load_dict({"type": "diffuse", "reflectance": {
        "type": "mesh_attribute", "name": "vertex_color"}}))
    return mesh


def main(argv=None):
    a = parse_args(argv)
    mi.set_variant(a.variant)
    import mi_tetvr
    from mi_tetvr.mesh.export import default_level, level_surface, write_surface
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    V, T, color, opacity = volume(a.cells)
    level = default_level(opacity) if a.level is None else a.level
    surface = level_surface(V, T, opacity, level, color)
    files = {s: out / f"surface.{s}" for s in ("ply", "obj", "glb")}
    for f in files.values():
        write_surface(f, surface)
    sky = {"type": "constant", "radiance": {"type": "rgb", "value": 0.35}}
    vol = mi.render(mi.load_dict({
        "type": "scene", "integrator": {"type": "tetvr"}, "sensor": sensor(a.res),
        "volume": mi_tetvr.tetmesh_dict(V, T, color, opacity), "sky": sky}), spp=4)
    surf = mi.render(mi.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 6},
        "sensor": sensor(a.res), "sky": sky,
        "sun": {"type": "directional", "direction": [-0.4, -1.0, -0.3],
                "irradiance": {"type": "rgb", "value": 2.5}},
        "surface": read_back(files["ply"]),
        "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate(
            [0, -0.9, 0]).rotate([1, 0, 0], -90).scale(3.0),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}}}),
        spp=a.spp)
    side = np.concatenate([np.asarray(vol)[..., :3], np.asarray(surf)[..., :3]], 1)
    files["figure"] = out / "export_surface.png"
    mi.util.write_bitmap(str(files["figure"]), side,
                         write_async=False)   # (written when the function returns)
    print(f"surface at opacity {level:.3g}: {len(surface.points):,} vertices, "
          f"{len(surface.faces):,} triangles -> {', '.join(str(f) for f in files.values())}")
    return {"level": level, "surface": surface, "volume_image": np.asarray(vol),
            "surface_image": np.asarray(surf), "files": files}


if __name__ == "__main__":
    main()
