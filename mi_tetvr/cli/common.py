"""What the commands share at run time: the Mitsuba variant, reading meshes and data
sets, loading and rendering scenes, writing renders, and :class:`CommandError`.

A command says what it cannot do by raising: ``ValueError`` (input or options that do
not combine), ``FileNotFoundError``, or :class:`CommandError` (a message written as it
is, e.g. the plugin's own error); :func:`mi_tetvr.cli.main` prints it as one line,
``mi-tetvr: <message>``, and exits with status 1.
"""
from __future__ import annotations

import contextlib

from pathlib import Path

import numpy as np

from mi_tetvr.apps.framing import render_rgba
from mi_tetvr.apps.settings import refuse
from mi_tetvr.cli.flags import VARIANTS

__all__ = ["CommandError", "refuse", "set_variant", "write_render", "srgb8", "scene_xml",
           "load_xml", "plugin_error", "load_scene", "render_image", "read_mesh",
           "is_image_data", "is_mesh_file", "load_data", "forwarding", "IMAGE_SUFFIXES",
           "MESH_SUFFIXES"]

IMAGE_SUFFIXES = (".exr", ".png", ".jpg", ".jpeg")
MESH_SUFFIXES = (".vtu", ".msh", ".mesh", ".vtk", ".pvtu")


class CommandError(Exception):
    """What a command could not do, with the message ``mi-tetvr: ...`` prints as it is;
    without a message the command ends with status 1 and prints nothing more (``info
    --json`` has printed its report)."""


def set_variant(name):
    """``mi.set_variant(name)`` with mi_tetvr's plugins registered; the ``mitsuba`` module."""
    import mitsuba as mi
    if name not in mi.variants():
        raise CommandError(
            f"Mitsuba variant '{name}' is not available here (available: "
            f"{', '.join(v for v in mi.variants() if '_ad_' in v and v.endswith('_rgb'))}"
            f"; mi_tetvr renders with {' or '.join(VARIANTS)})")
    try:
        mi.set_variant(name)
        import mi_tetvr
        mi_tetvr.register()
    except Exception as e:  # unavailable on this machine, or not a variant mi_tetvr renders in
        raise CommandError(f"cannot use Mitsuba variant '{name}': {e}") from None
    return mi


def srgb8(rgb):
    """Linear RGB (h, w, 3) as 8-bit sRGB, by Mitsuba's conversion."""
    import mitsuba as mi
    bmp = mi.Bitmap(np.ascontiguousarray(rgb, dtype=np.float32), mi.Bitmap.PixelFormat.RGB)
    return np.array(bmp.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8,
                                srgb_gamma=True), copy=True)


def write_render(path, rgb, alpha=None):
    """Write a render: linear RGB (h, w, 3) [+ alpha (h, w)] as EXR (linear,
    R G B [A], premultiplied) or PNG/JPG (RGB over black, 8-bit sRGB through
    Mitsuba's conversion, no alpha).

    Data-set images go through :func:`mi_tetvr.recon.images.write_image`
    instead, whose PNGs keep alpha (straight) so that they read back as the
    same premultiplied RGBA; a render's PNG is a picture to look at.
    """
    import mitsuba as mi
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise ValueError(f"unsupported image format '{suffix}' (use .exr or .png)")
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".exr":
        data = rgb if alpha is None else np.concatenate([rgb, alpha[..., None]], -1)
        bmp = mi.Bitmap(np.ascontiguousarray(data, dtype=np.float32),
                        mi.Bitmap.PixelFormat.RGB if alpha is None else mi.Bitmap.PixelFormat.RGBA)
        bmp.write(str(path))
    else:
        mi.Bitmap(srgb8(rgb), mi.Bitmap.PixelFormat.RGB).write(str(path))


def scene_xml(path, res=None, shape_props=None, classification=None):
    """A Mitsuba XML scene as text, with every sensor's film set to ``res``
    ``(width, height)`` (a film is added where a sensor has none),
    ``shape_props`` (name -> boolean) set on every ``tetmesh`` shape and
    ``classification`` on every ``tetmesh`` with a transfer function."""
    import xml.etree.ElementTree as ET
    root = ET.parse(path).getroot()

    def put(parent, tag, name, value):
        for el in parent.findall(tag):
            if el.get("name") == name:
                el.set("value", value)
                return
        ET.SubElement(parent, tag, name=name, value=value)

    if res is not None:
        sensors = root.iter("sensor")
        for sensor in sensors:
            film = sensor.find("film")
            if film is None:
                film = ET.SubElement(sensor, "film", type="hdrfilm")
            put(film, "integer", "width", str(res[0]))
            put(film, "integer", "height", str(res[1]))
    for shape in root.iter("shape"):
        if shape.get("type") == "tetmesh":
            for name, value in (shape_props or {}).items():
                put(shape, "boolean", name, "true" if value else "false")
            has_tf = any(el.get("name") == "transfer_function" for el in shape)
            if classification and has_tf:
                put(shape, "string", "classification", classification)
    return ET.tostring(root, encoding="unicode")


def load_xml(mi, path, res=None, shape_props=None, classification=None):
    """An XML scene file loaded (:func:`scene_xml`'s text, its folder on the file
    resolver's path), or :class:`CommandError` naming the plugin's error."""
    import mi_tetvr
    try:
        text = scene_xml(path, res, shape_props, classification)
        mi.file_resolver().prepend(str(Path(path).resolve().parent))
        return mi_tetvr.load_string(text)
    except Exception as e:
        raise CommandError(f"cannot load {path}: {plugin_error(e)}") from None


def plugin_error(e):
    """The one line of an error raised while Mitsuba built a scene: a plugin's own
    exception (:func:`mi_tetvr.plugin_error`; :func:`mi_tetvr.load_dict` raises it
    as it is) as ``Class: message``, else the error's text."""
    import mi_tetvr
    err = mi_tetvr.plugin_error(e)
    if err is e and (isinstance(e, RuntimeError) or not _from_plugin(e)):
        return str(e)
    return f"{type(err).__name__}: {err}"


def _from_plugin(e):
    """Whether ``e`` is a plugin's own exception, raised again by :func:`mi_tetvr.load_dict`
    (:func:`mi_tetvr.plugin_error` names the plugin in its ``mi_tetvr_plugin``)."""
    return hasattr(e, "mi_tetvr_plugin")


def load_scene(mi, scene_dict, path):
    """``mi.load_dict``, or :class:`CommandError` naming the plugin's error."""
    import mi_tetvr
    try:
        return mi_tetvr.load_dict(scene_dict)
    except Exception as e:
        raise CommandError(f"cannot load {path}: {plugin_error(e)}") from None


@contextlib.contextmanager
def render_errors(path):
    """A render's error as :class:`CommandError` naming the innermost one (Dr.Jit
    wraps the integrator's)."""
    try:
        yield
    except Exception as e:
        while (e.__cause__ or e.__context__) is not None:
            e = e.__cause__ or e.__context__
        raise CommandError(f"cannot render {path}: {plugin_error(e)}") from None


def render_image(mi, scene, path, **kwargs):
    """``mi.render`` as an array (:func:`render_rgba`), or :class:`CommandError`
    (:func:`render_errors`)."""
    with render_errors(path):
        return render_rgba(np.array(mi.render(scene, **kwargs)))


def read_mesh(options, path):
    """A mesh file: its color and opacity (defaults where absent) and point arrays,
    ``options``' ``repair`` and ``cell_to_point`` applied, and its topology, built
    here, before any plugin sees the mesh; what is wrong with it as
    :class:`CommandError`."""
    import warnings

    import mi_tetvr
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            mesh = mi_tetvr.read_tetmesh(path, repair=options.repair,
                                         cell_to_point=options.cell_to_point)
            mesh.topology        # (a folded or flat mesh is refused here)
            return mesh
        except (ValueError, FileNotFoundError, KeyError) as e:
            raise CommandError(str(e)) from None


def is_image_data(path):
    """Whether a legacy .vtk file holds image data (a grid volume), not a mesh."""
    if path.suffix.lower() != ".vtk":
        return False
    with open(path, "rb") as f:
        head = f.read(1024)
    return b"STRUCTURED_POINTS" in head or b"IMAGE_DATA" in head


def is_mesh_file(path):
    """Whether ``path`` names a tet mesh file (by its suffix; a .vtk by its content)."""
    path = Path(path)
    return path.suffix.lower() in MESH_SUFFIXES and not is_image_data(path)


def load_data(path, downscale, holdout):
    """A data set with training views (``ValueError`` when it has none)."""
    from mi_tetvr.recon.datasets import load_dataset
    data = load_dataset(path, downscale=downscale or 1, holdout=holdout)
    if not data.train:
        raise ValueError(f"{path}: the data set has no training views (its frames list is "
                         f"empty, or none of its image files was found)")
    return data


def forwarding(host, port):
    """How to open a viewer served on this machine from another one."""
    if host not in ("127.0.0.1", "localhost"):
        return ""
    return (f" (from another machine: ssh -N -L {port}:localhost:{port} USER@THIS_HOST, "
            f"then open http://localhost:{port})")
