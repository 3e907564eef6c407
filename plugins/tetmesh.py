"""The ``tetmesh`` shape: a tetrahedral mesh with per-vertex color and opacity.

.. pluginparameters::

 * - filename
   - |string|
   - Mesh file in any volume format meshio reads (.vtu, .vtk, .msh, .mesh, ...);
     VTK reads the VTK formats meshio cannot.
 * - vertices, tets, color, opacity, scalar, cell_scalar
   - |tensor|
   - Alternatively the arrays themselves: (n, 3) positions, (m, 4) indices,
     (n, 3) linear RGB and (n,) extinction, or an (n,) scalar or an (m,)
     cell scalar (one value per tet) for a ``transfer_function`` (see
     :func:`mi_tetvr.tetmesh_dict`).
 * - color_attribute
   - |string|
   - Point-data array holding the color. (Default: ``color``)
 * - opacity_attribute
   - |string|
   - Point-data array holding the opacity. (Default: ``opacity``)
 * - scalar_attribute
   - |string|
   - Scalar array to classify with ``transfer_function``: point data, or
     (``post`` classification) cell data, rendered as it is, constant in
     each tet. (Default: the only scalar point array, else the only scalar
     cell array).
 * - transfer_function
   - |string|
   - DiffTetVR XML or project JSON transfer function; when given, color and
     opacity come from the scalar field. (Default: none)
 * - value_min, value_max
   - |float|
   - Scalar range mapped to [0, 1] by the transfer function. (Default: the
     field's range)
 * - opacity_scale
   - |float|
   - Multiplies the transfer function's opacity. (Default: 1)
 * - classification
   - |string|
   - With a transfer function: ``post`` classifies the interpolated scalar
     along every ray (exact between the transfer function's texels; its
     scalar and texels are differentiable), ``preintegrated`` does the same
     by Weiler et al.'s pre-integrated table (faster, approximate, no
     derivatives), ``pre`` shades the vertices at load and interpolates the
     colors. (Default: ``post``)
 * - tf_color, tf_opacity
   - |tensor|
   - Instead of a ``transfer_function`` file (array input): the texels
     themselves, (R, 3) linear RGB and (R,) extinction at the centres
     ``(k + 0.5) / R`` of the normalised scalar axis. (Default: none)
 * - model
   - |string|
   - ``emission`` (emission and absorption) or ``absorption`` (X-ray
     attenuation: the opacity is the attenuation per unit length, nothing is
     emitted, ``alpha`` is one minus the transmittance). (Default: ``emission``)
 * - shade
   - |bool|
   - With ``post`` classification: light the volume by a headlight, as
     ParaView's *Shade* (:class:`~mi_tetvr.render.optical.Shaded`): the
     color times ``ambient + diffuse |n.d|`` plus ``specular |n.d|^specular_power``,
     ``n`` the scalar's gradient in each tet. (Default: false)
 * - ambient, diffuse, specular, specular_power
   - |float|
   - The lighting's coefficients. (Default: 0.1, 0.7, 0.2, 10, VTK's)
 * - tf_resolution
   - |int|
   - Texels the transfer function is resampled to over
     ``[value_min, value_max]`` for post-classification (linear between
     texel centres, constant outside). (Default: 256)
 * - cell_to_point
   - |bool|
   - Average per-cell arrays onto the vertices, so that a cell array can be
     the ``scalar_attribute`` or color. (Default: false)
 * - repair
   - |bool|
   - Drop folded, flat and duplicate tets (a warning says which and what it
     did to the boundary) instead of refusing the mesh. (Default: false)
 * - albedo
   - |float|, |color|, |tensor| or |string|
   - Makes the mesh a participating medium that scatters light
     (:class:`~mi_tetvr.render.optical.Scattering`, rendered by the
     ``tetpath`` integrator): its single-scattering albedo, constant, or
     (n,) / (n, 3) per vertex, linear RGB in [0, 1], or ``color``: the
     mesh's color is its albedo (its color array, or a transfer function's
     colors, classified at the vertices: ``classification`` ``pre``). The
     opacity is the extinction. (Default: none: emission and absorption only)
 * - albedo_attribute
   - |string|
   - Instead of ``albedo``: the point-data array (n,) or (n, 3) holding it.
 * - emission, emission_attribute
   - |float|, |color|, |tensor| or |string|
   - With an albedo: the medium's emission per unit extinction (as the
     color of an emission-absorption mesh), constant, per vertex or a
     point-data array. (Default: 0)
 * - phase
   - |phase|
   - With an albedo: the phase function, a Mitsuba phase plugin as a child
     (``isotropic``, ``hg``, ``rayleigh``, ...); its parameters are in
     ``mi.traverse`` under ``<id>.phase.``. (Default: ``isotropic``)
 * - to_world
   - |transform|
   - Applied to the vertex positions at load. Opacity stays per unit length
     of world space. (Default: identity)

Missing color defaults to white (1, 1, 1), missing opacity to 1 per unit length.
``scalar_attribute``, ``value_min``/``value_max`` and ``opacity_scale``
without a ``transfer_function``, or one of ``value_min``/``value_max``
without the other, are errors.

The shape keeps its topology only as the walk's 32-bit index buffers (32
bytes per tet); ``shape.oriented_tets()`` reads its tets back, positively
oriented (e.g. for the quality regularizer).

Differentiable parameters (``mi.traverse``): ``vertex_positions`` (3n),
``vertex_color`` (3n) and ``vertex_opacity`` (n); scattering (an
``albedo``): ``vertex_emission`` (3n) and ``vertex_albedo`` (3n) instead of
``vertex_color``, and the phase function's (``phase.g``, ...); post-classified:
``vertex_positions``, ``vertex_scalar`` (n), ``tf_color`` (3R, linear RGB)
and ``tf_opacity`` (R, extinction per unit length); with cell data,
``cell_scalar`` (m, in the mesh's tet order) instead of ``vertex_scalar``.
After changing them,
``params.update()`` rebuilds the boundary's BVH; the topology stays.

.. code-block:: python

    'volume': {
        'type': 'tetmesh',
        'filename': 'scenes/meshes/blob.vtu',
    }

A mesh whose topology was built already (a ``TetMesh``, a fit's mesh) is
handed to the shape in Python, not through the scene's properties:
:func:`mi_tetvr.tetmesh_shape` builds the shape object (``TetMeshShape(props,
topology=...)``), which goes into the ``mi.load_dict`` scene as it is, under
the id its parameters are named by:

.. code-block:: python

    'volume': mi_tetvr.tetmesh_shape(mesh),          # a TetMesh: its topology
    'volume': mi_tetvr.tetmesh_shape(mi_tetvr.tetmesh_dict(v, t), topology=topo),
"""
from __future__ import annotations

import mitsuba as mi
import numpy as np

from mi_tetvr.mesh import TetMesh, read_tetmesh
from mi_tetvr.mesh.io import choose_scalar
from mi_tetvr.mesh.topology import longest_edges
from mi_tetvr.render.buffers import drjit_index_arrays, owned, shape_index_arrays
from mi_tetvr.render.optical import (Absorption, CellClassified, EmissionAbsorption,
                                     PostClassified, PreIntegrated, Scattering, Shaded)
from mi_tetvr.transfer import TransferFunction, read_transfer_function

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


def scalar_range(scalar, name, props):
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


def check_array_scalars(entry):
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


def mesh_from_properties(props, topology=None) -> TetMesh:
    """The numpy mesh described by a ``tetmesh`` property set; ``topology``
    (:class:`~mi_tetvr.mesh.Topology`, optional) is that of its arrays
    ``vertices`` and ``tets``, built before: kept, not built again."""
    if "filename" in props:
        if topology is not None:
            raise ValueError("tetmesh: a topology is handed with the tensors 'vertices' and "
                             "'tets', not with a 'filename'")
        fs = mi.file_resolver()
        path = str(fs.resolve(props["filename"]))
        given = _given_range(props)
        repairs = dict(cell_to_point=bool(props.get("cell_to_point", False)),
                       repair=bool(props.get("repair", False)))
        if _classification(props) in ("post", "preintegrated"):
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
                       topology=topology)
        tf = _transfer_function(props)
        if tf is not None and _classification(props) == "pre":
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


def _transfer_function(props):
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


def _classification(props):
    """``pre``, ``post`` or ``preintegrated`` with a transfer function, else None."""
    if _transfer_function(props) is None:
        return None
    mode = str(props.get("classification", "post")).lower()
    if mode not in CLASSIFICATIONS:
        raise ValueError(f"tetmesh: classification must be one of {CLASSIFICATIONS}, got "
                         f"{mode!r}")
    return mode


def post_classification(props, mesh):
    """``(optical model, scalar (n,), value_range, tf_color (R, 3), tf_opacity
    (R,))`` of a post-classified ``tetmesh``, or None when it is not one."""
    tf, mode = _transfer_function(props), _classification(props)
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


def scattering(props, mesh):
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
        if _classification(props) not in (None, "pre"):
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


class TetMeshShape(mi.Mesh):
    __doc__ = __doc__
    #: The optical model that integrates this shape's vertex attributes.
    optical_model = EmissionAbsorption

    def __init__(self, props, topology=None):
        mesh = mesh_from_properties(props, topology)
        post = post_classification(props, mesh)
        model = str(props.get("model", "emission")).lower()
        if model not in MODELS:
            raise ValueError(f"tetmesh: model must be one of {tuple(MODELS)}, got {model!r}")
        if model != "emission":
            if post is not None or _transfer_function(props) is not None:
                raise ValueError(f"tetmesh: model '{model}' takes a per-vertex opacity, not a "
                                 f"transfer function")
        scatter = scattering(props, mesh)
        if scatter is not None and (model != "emission" or post is not None):
            raise ValueError("tetmesh: an albedo makes a scattering medium of a per-vertex "
                             "opacity (extinction): it takes no 'model', and a transfer "
                             "function only classified at the vertices (classification 'pre')")
        topo = mesh.topology
        super().__init__("tetmesh", len(mesh.vertices), len(topo.boundary_faces),
                         props, False, False)
        if self.is_emitter():
            raise ValueError("tetmesh: a tet volume cannot be an area emitter; it emits through "
                             "its colors (color, or a transfer function): remove its 'area' "
                             "emitter")
        self.optical_model = MODELS[model]
        params = mi.traverse(self)
        params["vertex_positions"] = owned(mi.Float, mesh.vertices.astype(np.float32).ravel())
        params["faces"] = owned(mi.UInt32, topo.boundary_faces.astype(np.uint32).ravel())
        #: The phase function of a scattering mesh (else None).
        self.phase = None
        if scatter is not None:
            self.optical_model = Scattering
            albedo, emission, self.phase = scatter
            values = {"vertex_emission": emission, "vertex_opacity": mesh.opacity,
                      "vertex_albedo": albedo}
        elif post is None:
            values = self.optical_model.vertex_values(mesh)
        else:
            self.optical_model, scalar, self.value_range, color, opacity = post
            #: The longest chord of any tet (the pre-integrated table's range).
            self.longest_edge = float(longest_edges(mesh.vertices, mesh.tets).max())
            self.tf_resolution = len(opacity)
            self.tf_color = owned(mi.Float, np.asarray(color, np.float32).ravel())
            self.tf_opacity = owned(mi.Float, np.asarray(opacity, np.float32))
            values = {"vertex_scalar": scalar}
            #: ``shade``'s coefficients (ambient, diffuse, specular, power).
            self.lighting = tuple(float(props.get(k, v)) for k, v in
                                  zip(LIGHTING, LIGHTING_DEFAULTS))
            if min(self.lighting) < 0.0:
                raise ValueError(f"tetmesh: the lighting's coefficients must be >= 0, got "
                                 f"{dict(zip(LIGHTING, self.lighting))}")
            if self.optical_model is CellClassified:
                #: The scalar per tet, in the mesh's order (cell data).
                self.cell_scalar = owned(mi.Float, np.asarray(scalar, np.float32))
        for name, channels in self.optical_model.vertex_attributes:
            self.add_attribute(name, channels,
                               owned(mi.Float, np.asarray(values[name], np.float32).ravel()))
        params.update()
        arrays = shape_index_arrays(topo, mesh.vertices)
        #: Index buffers of the walk (Dr.Jit, local indices; see
        #: mi_tetvr.render.buffers): all the shape keeps of its topology
        self.tet_buffers = drjit_index_arrays(arrays)
        #: The mesh's index of each tet the walk stores, where it reorders
        #: them (cell data is read through it), else None.
        self.cell_order = owned(mi.UInt32, arrays["order"]) if (
            "order" in arrays and self.optical_model is CellClassified) else None
        self.tet_count = topo.n_tets

    def set_mesh(self, params, vertices, tets, values, topology=None):
        """Give the shape another mesh in place: new vertices, tets and
        per-vertex values (``{attribute name: array}``, the names of
        ``optical_model.vertex_attributes``), written into ``params`` (the
        scene's ``mi.traverse``, whose ``update()`` then rebuilds the
        scene's BVH; the caller calls it). The shape object stays, and with
        it every object id that Mitsuba's kernels hold as constants: a
        refined mesh renders with the kernels compiled already (a new shape
        in a new scene compiles them again, seconds on a CPU)."""
        from mi_tetvr.mesh.topology import build_topology
        if self.optical_model is CellClassified or issubclass(self.optical_model,
                                                               PostClassified):
            raise ValueError("tetmesh: set_mesh replaces per-vertex colors, opacities or "
                             "albedos; a transfer function's mesh is built anew")
        vertices = np.asarray(vertices, np.float64)
        topo = build_topology(vertices, tets) if topology is None else topology
        prefix = f"{self.id()}."
        params[prefix + "vertex_positions"] = owned(mi.Float,
                                                    vertices.astype(np.float32).ravel())
        params[prefix + "faces"] = owned(mi.UInt32,
                                         topo.boundary_faces.astype(np.uint32).ravel())
        for name, channels in self.optical_model.vertex_attributes:
            a = np.asarray(values[name], np.float32).reshape(-1)
            if a.size != channels * len(vertices):
                raise ValueError(f"tetmesh: {name} needs {channels} value(s) per vertex for "
                                 f"{len(vertices)} vertices, got {a.size}")
            params[prefix + name] = owned(mi.Float, a)
        self.tet_buffers = drjit_index_arrays(shape_index_arrays(topo, vertices))
        self.tet_count = topo.n_tets

    def oriented_tets(self) -> np.ndarray:
        """(m, 4) int64: the shape's tets, positively oriented, in the walk's
        order (read from its index buffer), e.g. for
        :class:`~mi_tetvr.recon.regularizer.QualityRegularizer`."""
        return np.asarray(self.tet_buffers["tets"], np.int64).reshape(-1, 4)

    def traverse(self, callback):
        super().traverse(callback)
        if issubclass(self.optical_model, PostClassified):
            callback.put("tf_color", self.tf_color, mi.ParamFlags.Differentiable)
            callback.put("tf_opacity", self.tf_opacity, mi.ParamFlags.Differentiable)
        if self.optical_model is CellClassified:
            callback.put("cell_scalar", self.cell_scalar, mi.ParamFlags.Differentiable)
        if getattr(self, "phase", None) is not None:
            callback.put("phase", self.phase, mi.ParamFlags.Differentiable)

    def model_buffers(self):
        """The differentiable buffers of the optical model besides the
        vertex attributes (the transfer function's texels, the cell scalar)."""
        out = ([self.tf_color, self.tf_opacity]
               if issubclass(self.optical_model, PostClassified) else [])
        return out + ([self.cell_scalar] if self.optical_model is CellClassified else [])

    def to_string(self):
        return (f"TetMeshShape[vertices={self.vertex_count()}, tets={self.tet_count}, "
                f"boundary_faces={self.face_count()}]")


def shape_properties(entry) -> mi.Properties:
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


def build_shape(entry, topology=None) -> TetMeshShape:
    """A ``tetmesh`` shape built in Python from its dict entry (or its
    ``mi.Properties``) and, optionally, the topology of its arrays (kept, not
    built again; with ``to_world`` the moved mesh builds its own).

    Errors are the plugin's own exceptions (``ValueError``,
    :class:`~mi_tetvr.mesh.MeshError`), not Mitsuba's parser's: a property
    that the shape does not read is one, as ``mi.load_dict`` refuses it."""
    props = entry if isinstance(entry, mi.Properties) else shape_properties(entry)
    shape = TetMeshShape(props, topology=topology)
    unread = props.unqueried()
    if unread:
        raise ValueError(f"tetmesh: unknown propert{'y' if len(unread) == 1 else 'ies'} "
                         f"{', '.join(map(repr, sorted(unread)))}")
    return shape


mi.register_shape("tetmesh", lambda props: TetMeshShape(props))
