"""What a ``tetmesh`` shape's properties say, read and checked: its numpy mesh, its
optical model and per-vertex values, its transfer function, a scattering medium's
albedo, emission and phase function. The ``tetmesh`` plugin
(:mod:`mi_tetvr.plugins.tetmesh`) builds its buffers from these; the checks that
need neither a file nor a mesh (:func:`check_array_scalars`) also serve
:func:`mi_tetvr.tetmesh_dict` before Mitsuba builds anything.

A topology built before (a ``TetMesh``'s, a fit's) reaches the shape through
:func:`hand_topology`: Mitsuba's properties hold no Python objects, so the shape
is given a key (its string property ``topology``) under which it takes it.
"""
from __future__ import annotations

import itertools
import threading
from typing import Any

import mitsuba as mi
import numpy as np

from mi_tetvr.mesh import TetMesh, Topology, read_tetmesh
from mi_tetvr.mesh.io import choose_scalar
from mi_tetvr.render.optical import (Absorption, CellClassified, EmissionAbsorption,
                                     PostClassified, PreIntegrated, Shaded)
from mi_tetvr.transfer import TransferFunction, read_transfer_function

__all__ = ["CLASSIFICATIONS", "LIGHTING", "LIGHTING_DEFAULTS", "MODELS", "scalar_range",
           "check_array_scalars", "mesh_from_properties", "transfer_function",
           "classification", "post_classification", "scattering", "spherical_harmonics",
           "shape_properties",
           "hand_topology", "drop_topology"]

CLASSIFICATIONS = ("post", "pre", "preintegrated")
#: The ``shade`` lighting's coefficients and their defaults (VTK's volume property's).
LIGHTING = ("ambient", "diffuse", "specular", "specular_power")
LIGHTING_DEFAULTS = (0.1, 0.7, 0.2, 10.0)
MODELS = {"emission": EmissionAbsorption, "absorption": Absorption}


def _tensor(props, key):
    return np.array(props[key]) if key in props else None


def _given_range(props):
    """``(value_min, value_max)`` as given, or None where neither is."""
    vmin, vmax = props.get("value_min", None), props.get("value_max", None)
    if (vmin is None) != (vmax is None):
        raise ValueError("tetmesh: give both value_min and value_max (or neither: the "
                         "scalar field's range)")
    return None if vmin is None else (float(vmin), float(vmax))


def _array_scalars(props):
    """Refuse scalar tensors that do not combine: a ``scalar`` and a
    ``cell_scalar``, or either without a transfer function."""
    scalar, cells = "scalar" in props, "cell_scalar" in props
    if scalar and cells:
        raise ValueError("tetmesh: give a 'scalar' (per vertex) or a 'cell_scalar' (per "
                         "tet), not both")
    has_tf = any(k in props for k in ("transfer_function", "tf_color", "tf_opacity"))
    if (scalar or cells) and not has_tf:
        raise ValueError("tetmesh: a 'scalar' or 'cell_scalar' needs a transfer_function "
                         "(or the tensors tf_color and tf_opacity) to map it")


def scalar_range(scalar: np.ndarray, name: str,
                 props: mi.Properties | dict[str, Any]) -> tuple[float, float]:
    """``(lo, hi)``, the scalar range a transfer function maps to [0, 1]:
    ``value_min`` and ``value_max``, else the range of ``scalar`` (the array
    ``name``); ValueError where it is empty or the scalar is not finite."""
    if not np.all(np.isfinite(scalar)):
        raise ValueError(f"tetmesh: scalar array '{name}' has non-finite values")
    given = _given_range(props)
    lo, hi = given or (float(np.min(scalar)), float(np.max(scalar)))
    if not hi > lo:
        raise ValueError(f"tetmesh: the scalar range must have value_min < value_max, got "
                         f"[{lo}, {hi}]" + ("" if given else
                                             f" (array '{name}' is constant: give a range)"))
    return lo, hi


def check_array_scalars(entry: dict[str, Any]) -> None:
    """The shape's checks of a dict entry's scalar tensors that need neither
    the mesh nor a file, with the shape's messages (ValueError): for
    :func:`mi_tetvr.tetmesh_dict`, which makes them before Mitsuba builds the
    shape (whose parser would pass them on wrapped in its own error)."""
    _array_scalars(entry)
    values = _tensor(entry, "scalar")
    values = _tensor(entry, "cell_scalar") if values is None else values
    mode = str(entry.get("classification", "post")).lower()
    if values is not None and mode in ("post", "preintegrated"):
        scalar_range(np.asarray(values, np.float64).reshape(-1), "scalar", entry)


def mesh_from_properties(props: mi.Properties) -> TetMesh:
    """The numpy mesh described by a ``tetmesh`` property set; a topology handed
    for its arrays ``vertices`` and ``tets`` (:func:`hand_topology`) is kept, not
    built again."""
    topology = _take_topology(props)
    if "filename" in props:
        if topology is not None:
            raise ValueError("tetmesh: a topology is handed with the tensors 'vertices' and "
                             "'tets', not with a 'filename'")
        fs = mi.file_resolver()
        path = str(fs.resolve(props["filename"]))
        given = _given_range(props)
        repairs = dict(cell_to_point=bool(props.get("cell_to_point", False)),
                       repair=bool(props.get("repair", False)))
        if classification(props) in ("post", "preintegrated"):
            # (the scalar is read by post_classification)
            mesh = read_tetmesh(path, color=None, opacity=None, **repairs)
        else:
            mesh = read_tetmesh(
                path,
                color=props.get("color_attribute", "color"),
                opacity=props.get("opacity_attribute", "opacity"),
                scalar=props.get("scalar_attribute", None),
                transfer_function=(str(fs.resolve(props["transfer_function"]))
                                   if "transfer_function" in props else None),
                value_range=given,
                opacity_scale=float(props.get("opacity_scale", 1.0)), **repairs)
    elif "vertices" in props and "tets" in props:
        opacity = _tensor(props, "opacity")
        scalar, cells = _tensor(props, "scalar"), _tensor(props, "cell_scalar")
        _array_scalars(props)
        mesh = TetMesh(_tensor(props, "vertices"), _tensor(props, "tets"),
                       _tensor(props, "color"),
                       None if opacity is None else opacity.reshape(-1),
                       None if scalar is None else {"scalar": scalar.reshape(-1)},
                       None if cells is None else {"scalar": cells.reshape(-1)},
                       topology=topology, duplicates=False)   # the shape builds the topology
        tf = transfer_function(props)
        if tf is not None and classification(props) == "pre":
            if scalar is None:
                raise ValueError("tetmesh: classification 'pre' shades the vertices: it needs "
                                 "the tensor 'scalar' (per vertex)")
            mesh.color, mesh.opacity = tf.shade(
                scalar.reshape(-1), _given_range(props), float(props.get("opacity_scale", 1.0)))
    else:
        raise ValueError("tetmesh: give either 'filename' or the tensors 'vertices' and 'tets'")
    if "to_world" in props:
        mesh = mesh.transformed(np.array(props["to_world"].matrix, dtype=np.float64))
    return mesh


def transfer_function(props: mi.Properties) -> TransferFunction | None:
    """The shape's :class:`~mi_tetvr.transfer.TransferFunction`: from the
    ``transfer_function`` file, or from the texel tensors ``tf_color`` (R, 3)
    and ``tf_opacity`` (R,); None without either."""
    has_file, has_texels = "transfer_function" in props, ("tf_color" in props or
                                                         "tf_opacity" in props)
    if has_file and has_texels:
        raise ValueError("tetmesh: give a transfer_function file or the tensors tf_color and "
                         "tf_opacity, not both")
    if has_file:
        return read_transfer_function(str(mi.file_resolver().resolve(props["transfer_function"])))
    if not has_texels:
        return None
    if "tf_color" not in props or "tf_opacity" not in props:
        raise ValueError("tetmesh: give both tensors tf_color (R, 3) and tf_opacity (R,)")
    color, opacity = _tensor(props, "tf_color"), _tensor(props, "tf_opacity").reshape(-1)
    if color.size != 3 * opacity.size:
        raise ValueError(f"tetmesh: tf_color must be ({opacity.size}, 3) for {opacity.size} "
                         f"opacity texels, got {color.shape}")
    return TransferFunction.from_texels(color.reshape(-1, 3), opacity)


def classification(props: mi.Properties) -> str | None:
    """``pre``, ``post`` or ``preintegrated`` with a transfer function, else None."""
    if transfer_function(props) is None:
        return None
    mode = str(props.get("classification", "post")).lower()
    if mode not in CLASSIFICATIONS:
        raise ValueError(f"tetmesh: classification must be one of {CLASSIFICATIONS}, got "
                         f"{mode!r}")
    return mode


def post_classification(props: mi.Properties, mesh: TetMesh
                        ) -> tuple[type[PostClassified], np.ndarray, tuple[float, float],
                                   np.ndarray, np.ndarray] | None:
    """``(optical model, scalar (n,), value_range, tf_color (R, 3), tf_opacity
    (R,))`` of a post-classified ``tetmesh``, or None when it is not one."""
    tf, mode = transfer_function(props), classification(props)
    if tf is None or mode == "pre":
        for key in ("shade",) + LIGHTING:
            if key in props:
                raise ValueError(f"tetmesh: '{key}' lights a transfer function's colors "
                                 f"classified 'post'")
    if tf is None:
        for key in ("classification", "tf_resolution"):
            if key in props:
                raise ValueError(f"tetmesh: '{key}' needs a transfer_function")
        return None
    resolution = int(props.get("tf_resolution", 256 if "transfer_function" in props
                                         else len(tf.opacities)))
    if resolution < 2:
        raise ValueError(f"tetmesh: tf_resolution must be >= 2, got {resolution}")
    if mode == "pre":
        return None
    fs = mi.file_resolver()
    path = str(fs.resolve(props["filename"])) if "filename" in props else "tetmesh"
    name = choose_scalar(mesh.point_data, props.get("scalar_attribute", None), path,
                         mesh.cell_data, cells=True)
    per_tet = name not in mesh.point_data
    if per_tet and mode == "preintegrated":
        raise ValueError(f"tetmesh: '{name}' is cell data, constant in each tet: its "
                         f"segments are integrated exactly, with no table: use "
                         f"classification 'post'")
    data, count = (mesh.cell_data, len(mesh.tets)) if per_tet else (mesh.point_data,
                                                                    len(mesh.vertices))
    scalar = np.asarray(data[name], np.float64).reshape(count)
    lo, hi = scalar_range(scalar, name, props)
    color, opacity = tf.texels(resolution)
    model = (CellClassified if per_tet else
             PreIntegrated if mode == "preintegrated" else PostClassified)
    if bool(props.get("shade", False)):
        if model is not PostClassified:
            raise ValueError("tetmesh: shade lights a scalar per vertex classified 'post' "
                             f"(by its gradient in each tet); this one is "
                             f"{'cell data' if per_tet else mode}")
        model = Shaded
    return model, scalar, (lo, hi), color, opacity * float(props.get("opacity_scale", 1.0))


def _per_vertex(props, key, attribute, mesh, default: float):
    """(n, 3) float64 values of a scattering property: constant (a float or
    a color), a tensor (n,) or (n, 3), or the point-data array named by the
    property ``attribute``; ``default`` where none is given."""
    n = len(mesh.vertices)
    if key in props and attribute in props:
        raise ValueError(f"tetmesh: give '{key}' or '{attribute}', not both")
    if attribute in props:
        name = str(props[attribute])
        if name not in mesh.point_data:
            raise ValueError(f"tetmesh: no point-data array '{name}' for {key} (point arrays: "
                             f"{sorted(mesh.point_data)})")
        values = np.asarray(mesh.point_data[name], np.float64)
    elif key in props:
        kind = props.type(key)
        if kind == mi.Properties.Type.Float:
            values = np.full(n, float(props[key]))
        elif kind == mi.Properties.Type.Color:
            c = props[key]
            values = np.tile(np.array([c[0], c[1], c[2]], np.float64), (n, 1))
        else:
            values = np.asarray(np.array(props[key]), np.float64)
    else:
        return np.full((n, 3), float(default))
    if values.size == n:
        values = np.repeat(values.reshape(n, 1), 3, axis=1)
    if values.size != 3 * n:
        raise ValueError(f"tetmesh: {key} must be one value, a color, or (n,) or (n, 3) per "
                         f"vertex for n = {n} vertices, got {values.size} values")
    values = values.reshape(n, 3)
    if not np.all(np.isfinite(values)) or values.min() < 0.0:
        raise ValueError(f"tetmesh: {key} must be finite and >= 0")
    return values


def scattering(props: mi.Properties,
               mesh: TetMesh) -> tuple[np.ndarray, np.ndarray, mi.PhaseFunction] | None:
    """``(albedo (n, 3), emission (n, 3), phase)`` of a scattering ``tetmesh``
    (one with an ``albedo``), or None; the scattering properties without an
    albedo are errors."""
    # (objects only: reading a property marks it as read, and Mitsuba refuses
    # the properties nothing read)
    phases = [k for k in props.keys() if props.type(k) == mi.Properties.Type.Object
              and isinstance(props.get(k, None), mi.PhaseFunction)]
    has = "albedo" in props or "albedo_attribute" in props
    if not has:
        for key in ("emission", "emission_attribute", *phases):
            if key in props:
                raise ValueError(f"tetmesh: '{key}' belongs to a scattering medium: give the "
                                 f"mesh an 'albedo'")
        return None
    if len(phases) > 1:
        raise ValueError(f"tetmesh: one phase function, got {len(phases)}")
    if "albedo" in props and props.type("albedo") == mi.Properties.Type.String:
        if props["albedo"] != "color" or "albedo_attribute" in props:
            raise ValueError(f"tetmesh: albedo is a number, a color, a tensor or 'color' (the "
                             f"mesh's color), got {props['albedo']!r}")
        if classification(props) not in (None, "pre"):
            raise ValueError("tetmesh: a transfer function's colors are an albedo when they "
                             "are classified at the vertices: give classification 'pre'")
        albedo = np.clip(np.asarray(mesh.color, np.float64), 0.0, 1.0)
    else:
        albedo = _per_vertex(props, "albedo", "albedo_attribute", mesh, 0.0)
    if albedo.max() > 1.0:
        raise ValueError(f"tetmesh: the albedo must lie in [0, 1], got up to {albedo.max():g}")
    emission = _per_vertex(props, "emission", "emission_attribute", mesh, 0.0)
    phase = props[phases[0]] if phases else mi.load_dict({"type": "isotropic"})
    return albedo, emission, phase




def spherical_harmonics(props: mi.Properties, mesh: TetMesh) -> tuple[type, np.ndarray] | None:
    """``(model, coefficients (n, 3 K))`` of a view-dependent ``tetmesh``: the
    tensor ``sh`` ((n, K, 3) or (n, 3 K), K = 1, 4, 9 or 16 RGB triples per vertex,
    degree by degree) or the mesh file's point array ``sh`` (as a fit writes it);
    else None."""
    from mi_tetvr.render.optical import view_dependent
    n = len(mesh.vertices)
    if "sh" in props:
        sh = np.asarray(props["sh"], np.float64)
    elif mesh.point_data and "sh" in mesh.point_data:
        sh = np.asarray(mesh.point_data["sh"], np.float64)
    else:
        return None
    if sh.size % (3 * max(n, 1)) or len(sh) != n:
        raise ValueError(f"tetmesh: 'sh' needs (n, K, 3) or (n, 3 K) coefficients for the "
                         f"{n} vertices, got shape {sh.shape}")
    K = sh.size // (3 * n)
    degree = int(round(np.sqrt(K))) - 1
    if (degree + 1) ** 2 != K or not 0 <= degree <= 3:
        raise ValueError(f"tetmesh: 'sh' holds {K} RGB triples per vertex; spherical "
                         f"harmonics up to degree 0 to 3 have 1, 4, 9 or 16")
    if not np.all(np.isfinite(sh)):
        raise ValueError("tetmesh: 'sh' has non-finite coefficients")
    return view_dependent(degree), sh.reshape(n, 3 * K)


def shape_properties(entry: dict[str, Any]) -> mi.Properties:
    """The ``mi.Properties`` of a ``tetmesh`` dict entry (as
    :func:`mi_tetvr.tetmesh_dict` makes): its values as they are, nested
    dicts (an ``emitter``, a ``bsdf``) loaded as objects."""
    kind = entry.get("type", "tetmesh")
    if kind != "tetmesh":
        raise ValueError(f"tetmesh: the entry is a {kind!r}, not a 'tetmesh'")
    props = mi.Properties("tetmesh")
    for key, value in entry.items():
        if key == "type":
            continue
        if key == "id":
            props.set_id(str(value))
            continue
        props[key] = mi.load_dict(value) if isinstance(value, dict) else value
    return props


# -- a topology built before, handed to the shape ------------------------------------------
_handed = {}
_keys = itertools.count()
_lock = threading.Lock()


def hand_topology(topology: Topology) -> str:
    """Keep ``topology`` for the ``tetmesh`` shape about to be built; the key to give
    it as its ``topology`` property (taken once, by that shape)."""
    with _lock:
        key = f"mi_tetvr.topology.{next(_keys)}"
        _handed[key] = topology
    return key


def drop_topology(key: str) -> None:
    """Forget a topology handed and not taken (the shape was never built)."""
    with _lock:
        _handed.pop(key, None)


def _take_topology(props):
    """The topology handed under the shape's ``topology`` property, or None."""
    if "topology" not in props:
        return None
    with _lock:
        topology = _handed.pop(str(props["topology"]), None)
    if topology is None:
        raise ValueError("tetmesh: 'topology' is a key that mi_tetvr.tetmesh_shape gives the "
                         "shape it builds, not a property of a scene: remove it")
    return topology
