"""mi_tetvr: differentiable volume rendering of tetrahedral meshes in Mitsuba 3.

Usage::

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")   # or "cuda_ad_rgb"
    import mi_tetvr                 # registers the tetmesh shape and the tetvr,
                                    # tetproj and tetpath integrators

The plugins are registered with the variant set when ``mi_tetvr`` is imported,
and again by themselves whenever :func:`mitsuba.set_variant` switches to another
autodiff RGB variant (``llvm_ad_rgb``, ``cuda_ad_rgb``); :func:`register` does it
by hand.

Sub-packages (see the documentation's *Architecture*):

* :mod:`mi_tetvr.mesh` -- tet meshes in numpy: topology, files, generators,
  refinement, initial meshes (no Mitsuba variant needed);
* :mod:`mi_tetvr.render` -- the Dr.Jit renderer: the tet walk, optical models,
  the adjoint (needs a variant);
* :mod:`mi_tetvr.plugins` -- the Mitsuba plugins and their registration;
* :mod:`mi_tetvr.grid` -- regular-grid volumes and the grid ray marcher;
* :mod:`mi_tetvr.recon` -- cameras, data sets, the training loop behind
  ``mi-tetvr fit``, metrics (the ``recon`` extra);
* :mod:`mi_tetvr.transfer` -- transfer functions and their files;
  :mod:`mi_tetvr.color` -- the sRGB curve;
* :mod:`mi_tetvr.extras` -- the optional packages and the extra that brings each.

In a scene dict, :func:`tetmesh_dict` is a ``tetmesh`` entry made from arrays;
:func:`tetmesh_shape` is the shape itself, built now from a ``TetMesh`` (or from
an entry and the topology of its arrays, built once and handed on).

A plugin that refuses its input raises ``ValueError`` (or :class:`MeshError`);
Mitsuba's parser passes it on as a ``RuntimeError`` holding the plugin's
traceback as text. :func:`load_dict`, :func:`load_file` and :func:`load_string`
are Mitsuba's, raising the plugin's own exception instead (:func:`plugin_error`).
"""
from __future__ import annotations

import contextlib

__version__ = "0.9.0"

# The Mitsuba release first: outside the supported range, one line says so.
from .compat import check_mitsuba  # noqa: E402

check_mitsuba()

from .mesh import MeshError, TetMesh, Topology, build_topology, quality, read_tetmesh, write_tetmesh  # noqa: E402,E501
from .plugins import register  # noqa: E402
from .transfer import TransferFunction, read_transfer_function  # noqa: E402

__all__ = ["__version__", "register", "tetmesh_dict", "tetmesh_shape", "load_dict",
           "load_file", "load_string", "plugin_error", "read_tetmesh", "write_tetmesh",
           "MeshError", "TetMesh", "Topology", "build_topology", "quality", "TransferFunction",
           "read_transfer_function"]


def tetmesh_dict(vertices, tets, color=None, opacity=None, scalar=None, cell_scalar=None,
                 **props):
    """A ``mi.load_dict`` entry for a ``tetmesh`` built from arrays.

    Parameters
    ----------
    vertices : (n, 3) float
    tets : (m, 4) int
    color : (n, 3) float, optional
    opacity : (n,) float, optional
    scalar : (n,) float, optional
        A scalar field for a ``transfer_function`` property.
    cell_scalar : (m,) float, optional
        Or a scalar per tet (cell data, constant in each tet).
    **props
        Other plugin properties (e.g. ``to_world``, ``transfer_function``,
        ``albedo``); numpy arrays become tensors.

    Raises
    ------
    ValueError
        Where the shape would refuse the scalar (two of them, none to map it,
        a constant one without ``value_min`` and ``value_max``), with the
        shape's message: here, before Mitsuba's parser would wrap it.
    """
    import mitsuba as mi
    import numpy as np
    register()
    d = {"type": "tetmesh",
         "vertices": mi.TensorXf(np.asarray(vertices, dtype=np.float32)),
         "tets": mi.TensorXi(np.asarray(tets, dtype=np.int32))}
    if color is not None:
        d["color"] = mi.TensorXf(np.asarray(color, dtype=np.float32))
    if opacity is not None:
        d["opacity"] = mi.TensorXf(np.asarray(opacity, dtype=np.float32))
    if scalar is not None:
        d["scalar"] = mi.TensorXf(np.asarray(scalar, dtype=np.float32))
    if cell_scalar is not None:
        d["cell_scalar"] = mi.TensorXf(np.asarray(cell_scalar, dtype=np.float32))
    # (other per-vertex arrays, e.g. a scattering mesh's albedo and emission)
    d.update({k: mi.TensorXf(np.asarray(v, dtype=np.float32)) if isinstance(v, np.ndarray) else v
              for k, v in props.items()})
    if scalar is not None or cell_scalar is not None:
        from .render.properties import check_array_scalars
        check_array_scalars(d)
    return d


def tetmesh_shape(source, topology=None, **props):
    """The ``tetmesh`` shape itself, built now, for a scene dict: ``mi.load_dict``
    takes the object as it is, and the key it is under becomes its id (the prefix of
    its ``mi.traverse`` names, ``volume.vertex_color`` under ``"volume"``).

    Parameters
    ----------
    source : TetMesh or dict
        A mesh (its vertices, tets, color and opacity, and its topology, built by
        the mesh once and kept with it), or a ``tetmesh`` dict entry with the
        tensors ``vertices`` and ``tets`` (:func:`tetmesh_dict`'s).
    topology : Topology, optional
        :func:`build_topology` of those vertices and tets (any order of each
        tet's corners), when the caller has it: the shape does not build it
        again. Default: a ``TetMesh``'s own; for a dict, built by the shape.
    **props
        Other properties of the shape (``transfer_function``, ``scalar``, ...).

    Raises
    ------
    ValueError
        As the plugin does (:class:`MeshError` for a mesh it refuses), with
        its own message (:func:`load_dict`).
    """
    register()
    from .render.properties import drop_topology, hand_topology
    if isinstance(source, TetMesh):
        entry = tetmesh_dict(source.vertices, source.tets, source.color, source.opacity,
                             **props)
        topology = source.topology if topology is None else topology
    else:
        entry = {"type": "tetmesh", **source, **props}
    if topology is not None:
        if "filename" in entry:
            raise ValueError("tetmesh: a topology is handed with the tensors 'vertices' and "
                             "'tets', not with a 'filename'")
        entry["topology"] = key = hand_topology(topology)
    try:
        return load_dict(entry)
    finally:
        if topology is not None:
            drop_topology(key)


def plugin_error(exc, since=0):
    """The exception a plugin raised while Mitsuba built a scene, for the
    ``RuntimeError`` Mitsuba's parser raised for it.

    Each plugin's constructor keeps what it raises
    (:func:`mi_tetvr.plugins.raised_in`); Mitsuba's parser passes on only its
    text. The exception returned is the plugin's own (its class and message, no
    traceback): of a plugin that built another, the innermost one. Its
    attribute ``mi_tetvr_plugin`` names the plugin; where Python allows (3.11),
    a note says which plugin raised it, building what.

    Parameters
    ----------
    exc : BaseException
        What ``mi.load_dict``, ``mi.load_file`` or ``mi.load_string`` raised.
    since : int, optional
        Only what plugins raised after :func:`mi_tetvr.plugins.mark` returned
        this.

    Returns
    -------
    BaseException
        The plugin's exception, or ``exc`` itself when it does not come from a
        plugin's constructor (Mitsuba's own errors, an unknown plugin type, ...).
    """
    from .plugins import raised_in
    if not isinstance(exc, RuntimeError):
        return exc
    found = raised_in(exc, since)
    if found is None:
        return exc
    err, plugin, where = found
    err.mi_tetvr_plugin = plugin
    if hasattr(err, "add_note"):
        built = f'"{where}"' if where else "an object without an id"
        err.add_note(f'(raised by the "{plugin}" plugin while Mitsuba built {built})')
    return err


@contextlib.contextmanager
def _plugin_errors():
    """Raise a plugin's own exception (:func:`plugin_error`) where Mitsuba's
    parser wraps it in a ``RuntimeError``; others pass unchanged."""
    from .plugins import mark
    since = mark()
    try:
        yield
    except RuntimeError as e:
        err = plugin_error(e, since)
        if err is e:
            raise
        raise err from None      # (Mitsuba's whole text stays as its __context__)


def load_dict(scene, **kwargs):
    """``mi.load_dict``, a plugin's refusal raised as the plugin raised it
    (:func:`plugin_error`)."""
    import mitsuba as mi
    with _plugin_errors():
        return mi.load_dict(scene, **kwargs)


def load_file(path, **kwargs):
    """``mi.load_file`` (an XML scene), a plugin's refusal raised as the plugin
    raised it (:func:`plugin_error`)."""
    import mitsuba as mi
    with _plugin_errors():
        return mi.load_file(str(path), **kwargs)


def load_string(xml, **kwargs):
    """``mi.load_string`` (an XML scene in a string), a plugin's refusal raised
    as the plugin raised it (:func:`plugin_error`)."""
    import mitsuba as mi
    with _plugin_errors():
        return mi.load_string(xml, **kwargs)


def _auto_register():
    """Register the plugins with the variant set now, and with every autodiff RGB
    variant Mitsuba switches to later."""
    import mitsuba as mi
    from .plugins import on_variant_change
    mi.detail.add_variant_callback(on_variant_change)
    if mi.variant() is not None:
        register()


_auto_register()
