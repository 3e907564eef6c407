"""How ``mi-tetvr render MESH`` and the live viewer make the scene of a mesh
file: the framing (the box, the bounding sphere and the scalar's range of one
mesh or a series), the shape, the integrator of a render mode and the camera,
from a :class:`~mi_tetvr.apps.settings.RenderSettings` (``render``'s options,
or the viewer's controls). Options that do not combine raise ``ValueError``
(:meth:`RenderSettings.validate`; the command line prints them as one line)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from mi_tetvr.apps.lit import lit_scene


#: ``render MESH``'s image size (pixels) and horizontal field of view (degrees).
MESH_RES = (512, 512)
MESH_FOV = 40.0


def mesh_extent(settings, mesh, path):
    """``(lo, hi, scalar name, (min, max))`` of a mesh for :func:`mesh_framing`
    (the scalar only where the :class:`RenderSettings` classify it: ``--tf`` or
    a projection)."""
    from mi_tetvr.mesh.io import choose_scalar
    if not settings.classified:
        return mesh.bounds[0], mesh.bounds[1], None, None
    mode = settings.mode
    try:
        name = choose_scalar(mesh.point_data, settings.scalar, str(path), mesh.cell_data,
                             cells=mode == "dvr")
    except ValueError as e:
        raise ValueError(f"{e}" + ("" if mode == "dvr" else
                                   f" (--mode {mode} shows point data)")) from None
    values = np.asarray(mesh.point_data.get(name, mesh.cell_data.get(name)), np.float64)
    return mesh.bounds[0], mesh.bounds[1], name, (float(values.min()), float(values.max()))


def mesh_framing(extents):
    """What ``render MESH`` keeps fixed over one mesh or a time series, from
    their :func:`mesh_extent`: the union of their boxes and its bounding
    sphere (the camera) and the range of their scalar (the transfer
    function's)."""
    from mi_tetvr.mesh.topology import bounding_radius
    lo = np.min([e[0] for e in extents], 0)
    hi = np.max([e[1] for e in extents], 0)
    name, value_range = extents[0][2], None
    if name is not None:
        value_range = (min(e[3][0] for e in extents), max(e[3][1] for e in extents))
        if not value_range[1] > value_range[0]:
            raise ValueError(f"the scalar '{name}' is constant ({value_range[0]:g})")
    return {"lo": lo, "hi": hi, "radius": bounding_radius(np.stack([lo, hi])),
            "scalar": name, "value_range": value_range}


def mesh_scene(settings, mesh, framing):
    """The scene ``render MESH`` renders with the :class:`RenderSettings`
    ``settings``: the mesh (a ``TetMesh``; its color and opacity, or its scalar
    through ``--tf`` over the framing's range), ``tetvr`` or ``tetproj``
    (``--mode``), and a camera at ``--view`` (azimuth, elevation in degrees
    about ``--up``) at the :func:`~mi_tetvr.camera.framing_distance` of the
    framing's bounding sphere (:func:`mesh_framing`). Raises ``ValueError``
    where the settings do not combine for a mesh file."""
    import mi_tetvr
    s = settings
    s.validate("mesh")
    if s.lights is not None:
        return lit_scene(s, mesh, framing, framed_scene(s, framing), shape_props(s, framing))
    props = shape_props(s, framing)
    if "transfer_function" in props:
        name = props.pop("scalar_attribute")
        # a point array, or a cell array (dvr: constant in each tet)
        values = ({"scalar": mesh.point_data[name]} if name in mesh.point_data
                  else {"cell_scalar": mesh.cell_data[name]})
        shape = mi_tetvr.tetmesh_shape(
            mi_tetvr.tetmesh_dict(mesh.vertices, mesh.tets, **values, **props),
            topology=mesh.topology)
    else:
        shape = mi_tetvr.tetmesh_shape(mesh)
    return {**framed_scene(s, framing), "volume": shape}


def shape_props(settings, framing):
    """The ``tetmesh`` properties of a mesh under the :class:`RenderSettings`
    ``settings`` (``scalar_attribute``, ``transfer_function`` over the
    framing's range, ``opacity_scale`` per framing radius, ``shade``), none
    for a mesh shown by its colors."""
    s = settings
    tf = s.tf or ("gray" if s.mode != "dvr" else None)
    if not tf:
        return {}
    # a file, or a matplotlib colormap's name
    lo_v, hi_v = s.value_range or framing["value_range"]
    return {"scalar_attribute": framing["scalar"],
            "transfer_function": str(Path(tf).resolve()) if Path(tf).exists() else tf,
            "value_min": lo_v, "value_max": hi_v,
            "opacity_scale": s.opacity_scale / framing["radius"],
            **({"shade": True} if s.shade else {})}


def framed_scene(settings, framing):
    """:func:`mesh_scene` without its mesh: the integrator of the render mode
    and the camera on the framing."""
    from mi_tetvr.camera import framing_distance, orbit_to_world
    s = settings
    lo, hi, radius = framing["lo"], framing["hi"], framing["radius"]
    width, height = s.res or MESH_RES
    distance = framing_distance(radius, MESH_FOV, (width, height))
    azimuth, elevation = s.azimuth_elevation
    to_world = orbit_to_world(azimuth, elevation, distance, (lo + hi) / 2, s.up_axis)
    integrator = {"type": "tetvr"} if s.mode == "dvr" else {"type": "tetproj", "mode": s.mode}
    # The surfaces: tetproj's own (--mode iso|slice), or drawn in the volume
    # (--mode dvr with --iso or --plane: tetvr's overlay).
    surface = s.surface
    props = {}
    if surface == "iso":
        props["iso"] = ",".join(repr(float(v)) for v in s.iso) if s.iso \
            else str(sum(framing["value_range"]) / 2)
    elif surface == "slice":
        plane = s.plane or (*((lo + hi) / 2), *s.up_axis)
        props.update(origin=list(plane[:3]), normal=list(plane[3:]))
    if s.surface_opacity is not None:
        props["opacity"] = s.surface_opacity
    if s.mode == "dvr" and surface is not None:
        integrator["overlay"] = {"type": "tetproj", "mode": surface, **props}
    else:
        integrator.update(props)
    if s.clip:
        integrator.update(clip_origin=list(s.clip[:3]), clip_normal=list(s.clip[3:]))
    if s.clip_box:
        integrator.update(clip_min=list(s.clip_box[:3]), clip_max=list(s.clip_box[3:]))
    return {"type": "scene", "integrator": integrator,
            "sensor": {"type": "perspective", "fov": MESH_FOV,
                       "to_world": mi_scalar_transform(to_world),
                       "sampler": {"type": "stratified", "sample_count": s.spp or 1,
                                   "jitter": False},
                       "film": {"type": "hdrfilm", "width": width, "height": height,
                                "pixel_format": "rgba", "rfilter": {"type": "box"}}}}


def mi_scalar_transform(transform):
    """A Mitsuba (vectorized) transform of one camera as a ``ScalarTransform4f``."""
    import mitsuba as mi
    return mi.ScalarTransform4f(np.array(transform.matrix, np.float64).reshape(4, 4))


def render_rgba(image):
    """The (h, w, 4) RGBA of a render on an ``rgba`` film: where the integrator
    adds an ``alpha`` channel (``tetvr``: R, G, B, the film's alpha, alpha),
    that is the coverage; the film's own is 1 wherever ``tetvr`` sampled."""
    image = np.asarray(image)
    if image.shape[-1] == 5:
        return np.concatenate([image[..., :3], image[..., 4:5]], -1)
    return image
