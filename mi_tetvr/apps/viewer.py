"""A live viewer in the browser: meshes, scenes, data sets and fits, rendered
by mi_tetvr from the browser's camera while they render and train.

`viser <https://viser.studio>`_ serves the page (its built client works
offline) and sends every camera move back here; each image is rendered by
Mitsuba with the project's integrators in the thread that calls
:meth:`Viewer.update` (Dr.Jit's arrays are used by one thread: the viewer's
callbacks only record what changed). While the camera moves the viewer
renders at a quarter of the chosen resolution; when it stops it refines to
half and full resolution and then adds passes up to the chosen samples per
pixel (progressive refinement).

What is shown is a :class:`Shown`:

:class:`MeshShown`
    A tet mesh file, with the controls of ``mi-tetvr render MESH`` (the
    array shown, the transfer function's preset, value range and opacity
    scale, the render mode, isovalue, slice, shading); its scene is built by
    the command's own :func:`mi_tetvr.apps.framing.mesh_scene`, so that a saved view is
    rendered again by ``mi-tetvr render MESH ... --sensor VIEW.xml``.
:class:`SceneShown`
    A Mitsuba scene (an XML file, or any scene from Python): its own
    integrator, an opacity scale on its tet meshes.
:class:`FitShown`
    A fit (a :class:`~mi_tetvr.recon.trainer.Trainer`: a fit's folder, or the
    fit running, ``fit --viewer``) with its data set's cameras.
:class:`DataShown`
    A data set's cameras and images (nothing to render).

The cameras of a data set are drawn as frusta with their images; a click
moves the camera to one and shows the render beside the target with its PSNR
and SSIM (scored as the fit scores itself, :meth:`Trainer.evaluate`).

:func:`serve` shows a scene from Python (a script or a notebook).
"""
from __future__ import annotations

import dataclasses
import math
import threading
import time
from pathlib import Path

import numpy as np

from mi_tetvr.extras import needs

#: Refinement: the fractions of the resolution rendered one after the other
#: once the camera stops (the first also while it moves).
LEVELS = (0.25, 0.5, 1.0)
#: Long sides of the refined image offered (pixels).
RESOLUTIONS = (256, 512, 768, 1024)
#: The transfer-function presets offered besides the mesh's own (matplotlib's).
PRESETS = ("coolwarm", "viridis", "plasma", "inferno", "magma", "cividis", "turbo", "gray")
#: Render modes of a scalar mesh: the names shown, and ``render``'s flags for them.
MODES = {"volume": ("dvr", None), "volume + isosurface": ("dvr", "iso"),
         "volume + slice": ("dvr", "slice"), "isosurface": ("iso", "iso"),
         "slice": ("slice", "slice"), "maximum": ("max", None), "minimum": ("min", None),
         "mean": ("mean", None)}
#: ParaView's default background (sRGB, 0-255).
PARAVIEW_BACKGROUND = (82, 87, 110)
#: Vertical field of view (degrees) the browser's camera starts with.
START_FOV = 40.0
#: ``fit --viewer``: the most of the fit's time the viewer renders in.
FIT_SHARE = 0.1


# -- cameras -------------------------------------------------------------------------------

def browser_camera(position, wxyz, fov, aspect, long_side):
    """A :class:`~mi_tetvr.camera.Camera` of the browser's view: viser's camera
    (OpenCV axes: +z forward, +y down; ``wxyz`` its rotation to the world,
    ``fov`` vertical in radians, ``aspect`` width / height) at ``long_side``
    pixels along the longer image side."""
    from mi_tetvr.camera import Camera
    if aspect >= 1.0:
        width, height = int(long_side), max(1, round(long_side / aspect))
    else:
        width, height = max(1, round(long_side * aspect)), int(long_side)
    c2w = np.eye(4)
    c2w[:3, :3] = quaternion_matrix(wxyz)
    c2w[:3, 3] = np.asarray(position, np.float64)
    f = 0.5 * height / math.tan(0.5 * float(fov))
    return Camera.from_opencv(c2w, width, height, f, f, width / 2, height / 2)


def quaternion_matrix(wxyz):
    """The rotation matrix of a unit quaternion ``(w, x, y, z)``."""
    w, x, y, z = np.asarray(wxyz, np.float64) / np.linalg.norm(wxyz)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_quaternion(r):
    """The unit quaternion ``(w, x, y, z)`` of a rotation matrix."""
    with needs("viewer", "the live viewer"):
        from scipy.spatial.transform import Rotation
    x, y, z, w = Rotation.from_matrix(np.asarray(r, np.float64)).as_quat()
    return np.array([w, x, y, z])


def camera_pose(camera):
    """``(position, wxyz, vertical fov in radians, aspect)`` of a pinhole
    :class:`~mi_tetvr.camera.Camera` for viser (its inverse of :func:`browser_camera`)."""
    c2w = camera.c2w_opencv
    fov = 2.0 * math.atan(0.5 * camera.height / camera.fy)
    return c2w[:3, 3].copy(), matrix_quaternion(c2w[:3, :3]), fov, camera.width / camera.height


def srgb8(rgba, background):
    """8-bit sRGB of a premultiplied linear RGBA image over a linear RGB
    background: the picture the metrics compare (``display_rgb``), rounded."""
    from mi_tetvr.recon.metrics import display_rgb
    return np.round(255.0 * display_rgb(rgba, background)).astype(np.uint8)


def sensor_xml(camera, spp=1):
    """A Mitsuba ``perspective`` sensor of a :class:`~mi_tetvr.camera.Camera`
    as XML (``mi.load_string`` loads it; ``mi-tetvr render --sensor`` renders
    with it): its pose, field of view, principal point and film."""
    m = camera.to_world
    matrix = " ".join(f"{v:.9g}" for v in m.ravel())
    return (f'<sensor type="perspective" version="3.0.0">\n'
            f'    <string name="fov_axis" value="x"/>\n'
            f'    <float name="fov" value="{camera.fov_x:.9g}"/>\n'
            f'    <float name="principal_point_offset_x" '
            f'value="{0.5 - camera.cx / camera.width:.9g}"/>\n'
            f'    <float name="principal_point_offset_y" '
            f'value="{0.5 - camera.cy / camera.height:.9g}"/>\n'
            f'    <transform name="to_world"><matrix value="{matrix}"/></transform>\n'
            f'    <sampler type="stratified"><integer name="sample_count" value="{int(spp)}"/>'
            f'<boolean name="jitter" value="false"/></sampler>\n'
            f'    <film type="hdrfilm"><integer name="width" value="{camera.width}"/>'
            f'<integer name="height" value="{camera.height}"/>'
            f'<string name="pixel_format" value="rgba"/><rfilter type="box"/></film>\n'
            f'</sensor>\n')


def _render(frames, camera, integrator=None, spp=1, seed=0):
    """A frame of :class:`~mi_tetvr.apps.frames.Frames` (no gradients) as a
    numpy RGBA array."""
    from mi_tetvr.apps.framing import render_rgba
    image = render_rgba(np.array(frames.render(camera, integrator, spp, seed)))
    if image.shape[-1] == 3:
        image = np.concatenate([image, np.ones(image.shape[:2] + (1,), image.dtype)], -1)
    return image


# -- what is shown ------------------------------------------------------------------------------

class Shown:
    """What a :class:`Viewer` shows: a scene to render (or none), where it is
    (``centre``, ``radius``, ``up``), its controls and its cameras.

    Subclasses set ``scene`` and may override :meth:`integrator`,
    :meth:`controls`, :meth:`compare` and :meth:`command`."""
    scene = None
    #: The data set whose cameras are drawn, or None.
    dataset = None
    #: Whether frames replay recorded kernels (:mod:`~mi_tetvr.apps.frames`):
    #: for scenes that change only through :meth:`controls` (which
    #: :meth:`forget` the recordings).
    freeze = True
    _frames = None

    def __init__(self, centre, radius, up=(0.0, 0.0, 1.0)):
        self.centre = np.asarray(centre, np.float64)
        self.radius = float(radius)
        self.up = np.asarray(up, np.float64)
        self.message = ""
        from mi_tetvr.color import srgb_to_linear
        #: The background the images are composited over (linear RGB).
        self.background = tuple(srgb_to_linear(np.asarray(PARAVIEW_BACKGROUND) / 255.0))

    def integrator(self):
        """The integrator to render with (None: the scene's)."""
        return None

    def render(self, camera, spp=1, seed=0):
        """(h, w, 4) premultiplied linear RGBA of the scene from ``camera``, or None."""
        if self.scene is None:
            return None
        if self._frames is None or self._frames.scene is not self.scene:
            from mi_tetvr.apps.frames import Frames
            self._frames = Frames(self.scene, self.freeze)
        return _render(self._frames, camera, self.integrator(), spp, seed)

    def forget(self):
        """Forget the recorded frames (something else than the camera changed)."""
        if self._frames is not None:
            self._frames.clear()

    def controls(self, gui, later):
        """Add this kind's controls to ``gui``. Their callbacks run in viser's
        threads: they hand what they do to ``later(fn)``, which runs ``fn()``
        in the viewer's thread and then renders every view again."""

    def compare(self, view):
        """``(render, metrics)`` of a data set's view, or None (nothing to compare)."""
        return None

    def command(self, sensor_path, image_path):
        """The ``mi-tetvr render`` command line that renders the view saved as
        ``sensor_path`` again (a string), or None."""
        return None


def _scene_of(scene):
    """A scene's centre, radius (half its box diagonal) from its bounding box."""
    box = scene.bbox()
    lo, hi = np.array(box.min, np.float64), np.array(box.max, np.float64)
    return (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-6)


class SceneShown(Shown):
    """A loaded Mitsuba scene, rendered with its own integrator; an opacity
    scale multiplies the opacity of its tet meshes (their ``tf_opacity`` or
    ``vertex_opacity``)."""

    def __init__(self, scene, path=None, up=(0.0, 0.0, 1.0)):
        import mitsuba as mi
        super().__init__(*_scene_of(scene), up)
        self.scene, self.path = scene, path
        self.params = mi.traverse(scene)
        self.opacities = {k: mi.Float(self.params[k]) for k in self.params.keys()
                          if k.endswith(("tf_opacity", "vertex_opacity"))}
        self.scale = 1.0

    def controls(self, gui, later):
        if not self.opacities:
            return
        with gui.add_folder("Volume"):
            s = gui.add_slider("log10 opacity scale", min=-2.0, max=2.0, step=0.05,
                               initial_value=0.0)

        @s.on_update
        def _(_):
            value = 10.0 ** s.value
            later(lambda: self.set_opacity_scale(value))
        self.handles = dict(opacity_scale=s)

    def set_opacity_scale(self, scale):
        self.forget()
        self.scale = float(scale)
        for k, v in self.opacities.items():
            self.params[k] = v * self.scale
        self.params.update()

    def command(self, sensor_path, image_path):
        if self.path is None or self.scale != 1.0:
            return None
        return f"mi-tetvr render {self.path} --sensor {sensor_path} -o {image_path}"


class MeshShown(Shown):
    """A tet mesh file with ``render MESH``'s settings as controls. The
    settings are ``render``'s flags (:attr:`flags`); the scene is
    :func:`mi_tetvr.apps.framing.mesh_scene`'s for them. The transfer function's
    preset, range and opacity scale change the shape's texels in place (as
    the shape computes them at load); the array shown and shading load the
    shape again (its topology built once); the mode changes the integrator."""

    def __init__(self, path, tf=None, scalar=None, repair=False, cell_to_point=False,
                 up=(0.0, 0.0, 1.0)):
        import warnings

        import mi_tetvr
        from mi_tetvr.mesh.topology import bounding_radius
        self.path = Path(path)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self.mesh = mi_tetvr.read_tetmesh(path, repair=repair, cell_to_point=cell_to_point)
            self.mesh.topology      # built once (a folded mesh is refused here), kept by the mesh
        lo, hi = self.mesh.bounds
        super().__init__((lo + hi) / 2, bounding_radius(np.stack([lo, hi])), up)
        self.repair, self.cell_to_point = repair, cell_to_point
        scalars = [k for k, v in self.mesh.point_data.items() if np.ndim(v) == 1]
        self.cell_scalars = [k for k, v in self.mesh.cell_data.items() if np.ndim(v) == 1
                             and k not in scalars]
        self.scalars = scalars + self.cell_scalars
        has_colors = any(k in self.mesh.point_data for k in ("color", "opacity")) \
            or not self.scalars
        #: What is shown: "" (the color and opacity arrays) or a scalar's name.
        self.array = ""
        if scalar is not None and scalar not in self.scalars:
            raise ValueError(f"{path} has no scalar array {scalar!r} (its scalar arrays: "
                             f"{', '.join(self.scalars) or 'none'})")
        if tf and not self.scalars:
            raise ValueError(f"{path} has no scalar array for a transfer function")
        if not has_colors or tf or scalar:
            # the one asked for, else the first (the page offers the others)
            self.array = scalar or self.scalars[0]
        self.tf = tf or PRESETS[0]
        self.presets = ((tf,) if tf and tf not in PRESETS else ()) + PRESETS
        self.mode, self.opacity_scale, self.shade = "volume", 1.0, False
        self.iso = self.value_range = None
        self.surface_opacity = 1.0
        self.slice_axis, self.slice_at = "z", 0.5
        self._integrator = None
        self._reset_range()
        self.load()

    # -- the settings as render's flags
    def _reset_range(self):
        if self.array:
            values = np.asarray(self.mesh.point_data.get(self.array,
                                                        self.mesh.cell_data.get(self.array)))
            self.data_range = (float(values.min()), float(values.max()))
            if not self.data_range[1] > self.data_range[0]:
                self.data_range = (self.data_range[0], self.data_range[0] + 1.0)
            self.value_range = self.data_range
            self.iso = sum(self.data_range) / 2

    def settings(self):
        """The :class:`~mi_tetvr.apps.settings.RenderSettings` of the current controls
        (``render``'s options)."""
        from mi_tetvr.apps.settings import RenderSettings
        mode, surface = MODES[self.mode] if self.array else ("dvr", None)
        plane = None
        if surface == "slice":
            lo, hi = self.mesh.bounds
            k = "xyz".index(self.slice_axis)
            origin = (lo + hi) / 2
            origin[k] = lo[k] + self.slice_at * (hi[k] - lo[k])
            plane = (*origin.tolist(), *np.eye(3)[k].tolist())
        tf = None
        if self.array:
            tf = str(Path(self.tf).resolve()) if Path(self.tf).exists() else self.tf
        return RenderSettings(
            tf=tf, scalar=self.array or None, mode=mode,
            shade=bool(self.shade and self.array and mode == "dvr"),
            iso=(float(self.iso),) if surface == "iso" else None, plane=plane,
            surface_opacity=self.surface_opacity if surface and self.surface_opacity < 1
            else None,
            value_range=tuple(self.value_range) if self.array else None,
            opacity_scale=self.opacity_scale if self.array else 1.0,
            repair=self.repair, cell_to_point=self.cell_to_point, clip=None, clip_box=None,
            res=None, spp=1, view=(45.0, 30.0), up=tuple(float(v) for v in self.up))

    def flags(self):
        """The ``render`` flags of the current settings (after the mesh's path)."""
        a = self.settings()
        out = [f"--{k.replace('_', '-')}" for k in ("repair", "cell_to_point", "shade")
               if getattr(a, k)]
        if a.scalar:
            out += ["--tf", a.tf, "--scalar", a.scalar, "--mode", a.mode,
                    "--value-range", ",".join(repr(float(v)) for v in a.value_range),
                    "--opacity-scale", repr(float(a.opacity_scale))]
        for name, value in (("iso", a.iso), ("plane", a.plane),
                            ("surface-opacity", a.surface_opacity)):
            if value is not None:
                out += [f"--{name}", value if isinstance(value, str) else
                        ",".join(repr(float(v)) for v in np.atleast_1d(value))]
        return out

    def _scene_dict(self):
        from mi_tetvr.apps.framing import mesh_extent, mesh_framing, mesh_scene
        a = self.settings()
        return mesh_scene(a, self.mesh, mesh_framing([mesh_extent(a, self.mesh, self.path)]))

    def load(self):
        """Load the shape (and the integrator) for the current settings."""
        import mitsuba as mi
        try:
            # (the shape is built with the mesh's topology, built once; a refusal is a
            # ValueError)
            d = self._scene_dict()
        except ValueError as e:          # a combination render refuses: say so, keep the last
            self.message = str(e)
            return False
        d.pop("sensor")
        self._integrator = mi.load_dict(d.pop("integrator"))
        self.scene = mi.load_dict(d)
        self.params = mi.traverse(self.scene)
        self.loaded = self.flags()
        self.message = ""
        return True

    def integrator(self):
        return self._integrator

    def retexel(self):
        """The shape's transfer-function texels and value range for the current
        preset, range and opacity scale (what a load with them computes)."""
        import mitsuba as mi

        from mi_tetvr.transfer import read_transfer_function
        shape = self.scene.shapes()[0]
        if not self.array or "volume.tf_color" not in self.params:
            return self.load()
        try:
            tf = read_transfer_function(self.tf)
        except ValueError as e:
            self.message = str(e)
            return False
        color, opacity = tf.texels(shape.tf_resolution)
        self.params["volume.tf_color"] = mi.Float(np.asarray(color, np.float32).ravel())
        self.params["volume.tf_opacity"] = mi.Float(
            np.asarray(opacity * (self.opacity_scale / self.radius), np.float32))
        shape.value_range = tuple(float(v) for v in self.value_range)
        self.params.update()
        self.message = ""
        return True

    def apply(self, what):
        """Bring the scene to the settings after a change of ``what``: "texels"
        (preset, range, opacity scale), "integrator" (mode, isovalue, slice)
        or "shape" (array, shading)."""
        import mitsuba as mi
        self.forget()
        if what == "shape" or (what == "texels" and not self.array):
            return self.load()
        if what == "texels":
            return self.retexel()
        try:
            d = self._scene_dict()
        except ValueError as e:
            self.message = str(e)
            return False
        self._integrator = mi.load_dict(d["integrator"])
        self.message = ""
        return True

    def controls(self, gui, later):
        def on(handle, what, set_value):
            @handle.on_update
            def _(_):
                value = handle.value

                def run():
                    set_value(value)
                    self.apply(what)
                    show()
                later(run)

        with gui.add_folder("Volume"):
            arrays = ["color, opacity"] * (not self.array or "color" in self.mesh.point_data
                                           or "opacity" in self.mesh.point_data) + self.scalars
            array = gui.add_dropdown("array", arrays, initial_value=self.array or arrays[0])
            preset = gui.add_dropdown("transfer function", self.presets,
                                      initial_value=self.tf)
            lo = gui.add_number("range min", initial_value=self.value_range[0]
                                if self.array else 0.0)
            hi = gui.add_number("range max", initial_value=self.value_range[1]
                                if self.array else 1.0)
            reset = gui.add_button("reset range")
            scale = gui.add_slider("log10 opacity scale", min=-2.0, max=2.0, step=0.05,
                                   initial_value=0.0)
            shade = gui.add_checkbox("shade", initial_value=False)
            mode = gui.add_dropdown("mode", tuple(MODES), initial_value=self.mode)
            span = self.value_range or (0.0, 1.0)
            iso = gui.add_slider("isovalue", min=span[0], max=span[1],
                                 step=(span[1] - span[0]) / 200, initial_value=self.iso or 0.0)
            axis = gui.add_dropdown("slice normal", ("x", "y", "z"), initial_value="z")
            at = gui.add_slider("slice position", min=0.0, max=1.0, step=0.01,
                                initial_value=0.5)
            surface = gui.add_slider("surface opacity", min=0.05, max=1.0, step=0.05,
                                     initial_value=1.0)
            note = gui.add_markdown("")

        def show():
            scalar = bool(self.array)
            surface_kind = MODES[self.mode][1] if scalar else None
            for h in (preset, lo, hi, reset, shade, mode):
                h.visible = scalar
            iso.visible = surface_kind == "iso"
            axis.visible = at.visible = surface_kind == "slice"
            surface.visible = surface_kind is not None
            note.content = f"*{self.message}*" if self.message else ""

        def set_array(v):
            self.array = "" if v == "color, opacity" else v
            self._reset_range()
            if self.array:
                lo.value, hi.value = self.value_range
                iso.min, iso.max = self.value_range
                iso.step = (self.value_range[1] - self.value_range[0]) / 200
                iso.value = self.iso
            if self.array in self.cell_scalars and self.mode != "volume":
                self.mode = mode.value = "volume"

        def set_range(which, v):
            r = list(self.value_range)
            r[which] = float(v)
            if r[1] > r[0]:
                self.value_range = tuple(r)
            else:
                self.message = "the range's max must exceed its min"

        on(array, "shape", set_array)
        on(preset, "texels", lambda v: setattr(self, "tf", v))
        on(lo, "texels", lambda v: set_range(0, v))
        on(hi, "texels", lambda v: set_range(1, v))
        on(scale, "texels", lambda v: setattr(self, "opacity_scale", 10.0 ** v))
        on(shade, "shape", lambda v: setattr(self, "shade", bool(v)))
        on(mode, "integrator", lambda v: setattr(self, "mode", v))
        on(iso, "integrator", lambda v: setattr(self, "iso", float(v)))
        on(axis, "integrator", lambda v: setattr(self, "slice_axis", v))
        on(at, "integrator", lambda v: setattr(self, "slice_at", float(v)))
        on(surface, "integrator", lambda v: setattr(self, "surface_opacity", float(v)))

        @reset.on_click
        def _(_):
            def run():
                self.value_range = self.data_range
                self.apply("texels")
                lo.value, hi.value = self.data_range
            later(run)

        show()
        #: The controls by name (tests and scripts set them as the page does).
        self.handles = dict(array=array, preset=preset, range_min=lo, range_max=hi,
                            opacity_scale=scale, shade=shade, mode=mode, iso=iso,
                            slice_normal=axis, slice_position=at, surface_opacity=surface)

    def command(self, sensor_path, image_path):
        import shlex
        return shlex.join(["mi-tetvr", "render", str(self.path), *self.loaded_flags(),
                           "--sensor", str(sensor_path), "-o", str(image_path)])

    def loaded_flags(self):
        """The flags of what is on screen (the last settings that loaded)."""
        return self.flags() if not self.message else self.loaded


class FitShown(Shown):
    """A fit: its :class:`~mi_tetvr.recon.trainer.Trainer`'s scene and its data
    set's cameras, shown as fitted (no controls of its own: while it runs,
    the fit owns its parameters)."""
    #: (the fit changes the scene between frames)
    freeze = False

    def __init__(self, trainer, up=None):
        views = trainer.dataset.train + trainer.dataset.test
        centre, radius = _scene_of(trainer.scene)
        if up is None:
            up = _cameras_up([v.camera for v in views])
        super().__init__(centre, radius, up)
        self.set_trainer(trainer)

    def set_trainer(self, trainer):
        """Show ``trainer`` (a fit's next stage)."""
        self.trainer, self.scene, self.dataset = trainer, trainer.scene, trainer.dataset
        bg = trainer.field.shown(trainer.background)
        self.background = tuple(np.zeros(3) if bg is None or isinstance(bg, str) else bg)

    def compare(self, view):
        metrics = self.trainer.evaluate([view])["views"][view.name]
        return self.trainer.render_view(view), metrics


class DataShown(Shown):
    """A data set's cameras and images; nothing is rendered."""

    def __init__(self, dataset):
        cams = [v.camera for v in dataset.views]
        centres = np.array([c.center for c in cams])
        centre = dataset.bounds().mean(0) if hasattr(dataset, "bounds") else centres.mean(0)
        super().__init__(centre, float(np.linalg.norm(centres - centre, axis=1).max()),
                         _cameras_up(cams))
        self.dataset = dataset
        self.message = "a data set alone has nothing to render: its cameras and images are shown"

    def compare(self, view):
        return None, None


def _cameras_up(cameras):
    """The world's up for a set of cameras: the mean of their up vectors (Mitsuba's
    +y of each camera), rounded to an axis when close to one."""
    up = np.mean([c.to_world[:3, 1] for c in cameras], 0)
    up = up / max(np.linalg.norm(up), 1e-12)
    k = int(np.argmax(np.abs(up)))
    return np.sign(up[k]) * np.eye(3)[k] if abs(up[k]) > 0.9 else up


# -- the viewer ------------------------------------------------------------------------------------

@dataclasses.dataclass
class ClientState:
    """What the viewer keeps of one browser: its camera (viser's pose and
    image aspect), what changed (``version``), how far the current view is
    refined (``level``: an index into :data:`LEVELS`, then the passes of
    full resolution) and the sum of the passes."""
    push: object                       # push(image uint8, final): show an image
    position: np.ndarray = None
    wxyz: np.ndarray = None
    fov: float = math.radians(START_FOV)
    aspect: float = 1.0
    version: int = 0
    level: int = 0
    accumulated: np.ndarray = None
    moved: float = 0.0                 # the viewer's clock at the last change
    latency: dict = dataclasses.field(default_factory=dict)


class Viewer:
    """A web viewer of a :class:`Shown` (see the module's docstring).

    Parameters
    ----------
    shown : Shown
    port : int
        The port to serve on (the next free one when taken: :attr:`port`).
    host : str
        The address to listen on: ``127.0.0.1`` (this machine; from another
        machine through ``ssh -L``) or ``0.0.0.0`` (every network).
    resolution : int
        The refined image's longer side in pixels.
    spp : int
        Passes (samples per pixel) the refined image accumulates.
    save_dir : path
        Where the *save* button writes images and cameras.
    server : bool
        False: no web server (benchmarks drive :meth:`add_client` themselves).
    now : callable
        The clock (seconds) render times and a fit's share are kept by (tests pass a
        simulated one).
    """

    def __init__(self, shown, port=8080, host="127.0.0.1", resolution=512, spp=1,
                 save_dir="views", server=True, now=time.perf_counter):
        self.shown, self.now = shown, now
        self.resolution, self.spp = int(resolution), int(spp)
        self.background = shown.background
        self.save_dir = Path(save_dir)
        self.clients = {}
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._jobs = []                    # (kind, client id, payload) for the render thread
        self._stop = threading.Event()
        self.rendered = 0                  # images rendered (all levels)
        self._cost = {}                    # seconds of the last render of each size
        self.render_seconds = 0.0
        self.server = None
        if server:
            with needs("viewer", "the live viewer"):
                import viser
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
            self.server.scene.set_up_direction(tuple(float(v) for v in shown.up))
            self._build_gui()
            self._draw_cameras()
            self.server.on_client_connect(self._connect)
            self.server.on_client_disconnect(self._disconnect)
        self.host = host

    # -- address
    @property
    def port(self):
        return self.server.get_port() if self.server else None

    @property
    def url(self):
        host = "localhost" if self.host in ("127.0.0.1", "0.0.0.0", "localhost") else self.host
        return f"http://{host}:{self.port}"

    # -- clients
    def start_camera(self):
        """``(position, look_at, vertical fov)`` of the first view: a data set's first
        test camera (else its first), looking at the scene's centre; else
        ``render MESH``'s (azimuth 45, elevation 30 degrees about ``up``), the
        whole scene in the field of view."""
        from mi_tetvr.camera import framing_distance, orbit_to_world
        s = self.shown
        data = s.dataset
        if data is not None and (data.test or data.train):
            view = (data.test or data.train)[0]
            if view.camera.pixel_size is None:
                if view.name in getattr(self, "frusta", {}):
                    self.frusta[view.name].visible = False     # it would hide the view
                return view.camera.center, s.centre, camera_pose(view.camera)[2]
        distance = framing_distance(s.radius, START_FOV)
        m = np.array(orbit_to_world(45.0, 30.0, distance, s.centre.tolist(), s.up.tolist()).matrix,
                     np.float64).reshape(4, 4)
        return m[:3, 3], s.centre, math.radians(START_FOV)

    def add_client(self, key, push, position, wxyz, fov, aspect):
        """Track a view (a browser's, or a program's): ``push(image, final)``
        shows its images."""
        with self._lock:
            self.clients[key] = ClientState(push=push)
        self.set_camera(key, position, wxyz, fov, aspect)

    def set_camera(self, key, position, wxyz, fov, aspect):
        """A view's camera moved: render it again from the first level."""
        with self._lock:
            c = self.clients.get(key)
            if c is None:
                return
            c.position, c.wxyz = np.asarray(position, float), np.asarray(wxyz, float)
            c.fov, c.aspect = float(fov), float(aspect)
            c.version += 1
            c.level, c.accumulated, c.moved = 0, None, self.now()
            c.latency = {}
        self._wake.set()

    def changed(self):
        """The scene or a setting changed: every view renders again."""
        with self._lock:
            for c in self.clients.values():
                c.version += 1
                c.level, c.accumulated, c.moved = 0, None, self.now()
                c.latency = {}
        self._wake.set()

    def later(self, fn):
        """Run ``fn()`` in the viewer's thread (the one that renders), then render
        every view again."""
        with self._lock:
            self._jobs.append(("call", None, fn))
        self._wake.set()

    def _connect(self, client):
        position, target, fov = self.start_camera()

        def push(image, final):
            client.scene.set_background_image(image, format="png" if final else "jpeg",
                                              jpeg_quality=None if final else 90)
        cam = client.camera
        with client.atomic():
            cam.fov = fov
            cam.up_direction = tuple(float(v) for v in self.shown.up)
            cam.position = tuple(float(v) for v in position)
            cam.look_at = tuple(float(v) for v in target)
        self.add_client(client.client_id, push, cam.position, cam.wxyz, cam.fov, cam.aspect)

        @cam.on_update
        def _(cam):
            self.set_camera(client.client_id, cam.position, cam.wxyz, cam.fov, cam.aspect)

    def _disconnect(self, client):
        with self._lock:
            self.clients.pop(client.client_id, None)

    # -- rendering
    def _next(self):
        """The view to render next and at what level (the least refined first)."""
        best = None
        for key, c in self.clients.items():
            if c.position is None or c.level >= len(LEVELS) - 1 + self.spp:
                continue
            if best is None or c.level < best[1].level:
                best = (key, c)
        return best

    def update(self, budget=None):
        """Do the viewer's next piece of work (a job, or one image of one view) in
        this thread; returns whether there was any. ``budget``: skip rendering
        when it would start after this many seconds of viewer time (see
        :class:`FitViewer`)."""
        with self._lock:
            job = self._jobs.pop(0) if self._jobs else None
            nxt = None if job else self._next()
            if nxt is not None:
                key, c = nxt
                version, level = c.version, c.level
                pose = (c.position, c.wxyz, c.fov, c.aspect)
        if job is not None:
            self._run_job(*job)
            return True
        if nxt is None or self.shown.scene is None:
            return False
        full = level >= len(LEVELS) - 1
        side = max(32, round(self.resolution * LEVELS[min(level, len(LEVELS) - 1)]))
        if budget is not None and budget <= self._cost.get(side, 0.0):
            return False                       # (what this size took last time)
        t0 = self.now()
        camera = browser_camera(*pose, side)
        try:
            image = self.shown.render(camera, spp=1, seed=max(level - len(LEVELS) + 1, 0))
        except Exception as e:                 # say it on the page; keep serving
            self.shown.message = f"cannot render: {_last_line(e)}"
            with self._lock:
                c.level = len(LEVELS) - 1 + self.spp
            self._status()
            return True
        dt = self.now() - t0
        self._cost[side] = dt
        self.render_seconds += dt
        self.rendered += 1
        with self._lock:
            if c.version != version:           # moved meanwhile: this image is stale
                return True
            if full and c.accumulated is not None and c.accumulated.shape == image.shape:
                passes = level - len(LEVELS) + 2
                c.accumulated = c.accumulated + (image - c.accumulated) / passes
            else:
                c.accumulated = image
            c.level = level + 1
            final = c.level >= len(LEVELS) - 1 + self.spp
            shown = c.accumulated
            now = self.now()
            c.latency.setdefault("first", now - c.moved)
            if final:
                c.latency["refined"] = now - c.moved
        c.push(srgb8(shown, self.background), final)
        self.last = dict(seconds=dt, size=(camera.width, camera.height), level=level)
        self._status()
        return True

    def run(self, seconds=None):
        """Serve in this thread until Ctrl-C (or :meth:`stop`, or ``seconds``)."""
        end = None if seconds is None else self.now() + seconds
        while not self._stop.is_set() and (end is None or self.now() < end):
            if not self.update():
                self._wake.wait(0.05)
                self._wake.clear()

    def start(self):
        """Serve from a thread of its own (returns at once; :meth:`stop` ends it).
        The scene must not be changed elsewhere meanwhile."""
        self._thread = threading.Thread(target=self.run, daemon=True)
        self._thread.start()
        return self

    def stop(self):
        self._stop.set()
        self._wake.set()
        t = getattr(self, "_thread", None)
        if t is not None and t is not threading.current_thread():
            t.join(timeout=10)
        if self.server is not None:
            self.server.stop()

    # -- page
    def _build_gui(self):
        gui = self.server.gui
        gui.configure_theme(control_width="large")
        self.shown.controls(gui, self.later)
        with gui.add_folder("View"):
            sizes = sorted(set(RESOLUTIONS) | {self.resolution})
            res = gui.add_dropdown("resolution", tuple(str(r) for r in sizes),
                                   initial_value=str(self.resolution))
            spp = gui.add_slider("samples per pixel", min=1, max=16, step=1,
                                 initial_value=self.spp)
            bg = gui.add_rgb("background", initial_value=tuple(
                int(v) for v in srgb8(np.zeros((1, 1, 4)), self.background)[0, 0]))
            save = gui.add_button("save image and camera")
            self._status_md = gui.add_markdown("")

        @res.on_update
        def _(_):
            self.resolution = int(res.value)
            self.changed()

        @spp.on_update
        def _(_):
            self.spp = int(spp.value)
            self.changed()

        @bg.on_update
        def _(_):
            from mi_tetvr.color import srgb_to_linear
            self.background = tuple(srgb_to_linear(np.asarray(bg.value) / 255.0))
            self.changed()

        @save.on_click
        def _(event):
            with self._lock:
                self._jobs.append(("save", event.client.client_id, None))
            self._wake.set()
        self.handles = dict(resolution=res, spp=spp, background=bg, save=save)

    def _status(self):
        if self.server is None:
            return
        last = getattr(self, "last", None)
        text = []
        if last:
            w, h = last["size"]
            text.append(f"{w}x{h} in {1000 * last['seconds']:.0f} ms")
        if self.shown.message:
            text.append(f"*{self.shown.message}*")
        self._status_md.content = "  \n".join(text)

    def _draw_cameras(self):
        """The data set's cameras as frusta with their images (train blue, test
        orange); a click moves the view to one and compares."""
        data = self.shown.dataset
        if data is None:
            return
        views = [("train", v) for v in data.train] + [("test", v) for v in data.test]
        centres = np.array([v.camera.center for _, v in views])
        scale = 0.025 * float(np.linalg.norm(centres.max(0) - centres.min(0))
                              or self.shown.radius)
        with self.server.gui.add_folder("Compare"):
            self._compare_md = self.server.gui.add_markdown(
                "click a camera: its view, the render beside the image, PSNR")
            self._compare_img = self.server.gui.add_image(np.zeros((8, 16, 3), np.uint8),
                                                          format="png", visible=False)
        self.frusta = {}
        for k, (split, view) in enumerate(views):
            if view.camera.pixel_size is not None:
                continue                  # parallel beams have no frustum
            position, wxyz, fov, aspect = camera_pose(view.camera)
            thumb = _thumbnail(srgb8(np.asarray(view.image, np.float64), self.background))
            f = self.server.scene.add_camera_frustum(
                f"/cameras/{split}/{k:04d}", fov=fov, aspect=aspect, scale=scale,
                image=thumb, format="jpeg", wxyz=wxyz, position=position,
                thickness=1.5, thickness_units="screen",
                color=(40, 90, 220) if split == "train" else (240, 140, 20))

            def click(event, view=view, split=split):
                with self._lock:
                    self._jobs.append(("compare", event.client.client_id, (view, split)))
                self._wake.set()
            f.on_click(click)
            self.frusta[view.name] = f

    def _run_job(self, kind, key, payload):
        if kind == "call":
            payload()
            self.shown.forget()
            self.changed()
            self._status()
        elif kind == "save":
            self.save(key)
        elif kind == "compare":
            self.compare(key, *payload)

    def compare(self, key, view, split):
        """Move view ``key`` to a data set's camera and show the render beside its
        image with the metrics."""
        position, wxyz, fov, _ = camera_pose(view.camera)
        client = self.server.get_clients().get(key) if self.server else None
        if client is not None:
            with client.atomic():
                client.camera.wxyz = tuple(wxyz)
                client.camera.position = tuple(position)
                client.camera.fov = fov
            # the camera's own frustum would hide the view: shown again when another
            # camera is clicked
            for name, f in self.frusta.items():
                f.visible = name != view.name
        render, metrics = self.shown.compare(view)
        target = srgb8(np.asarray(view.image, np.float64), self.background)
        if render is not None:
            pair = np.concatenate([srgb8(render, self.background),
                                   np.full((target.shape[0], 4, 3), 255, np.uint8), target], 1)
            text = (f"**{view.name}** ({split}): render | image  \n"
                    f"PSNR {metrics['psnr']:.2f} dB, SSIM {metrics['ssim']:.4f}")
        else:
            pair, metrics = target, None
            text = f"**{view.name}** ({split})"
        self.compared = dict(view=view.name, split=split, metrics=metrics)
        if self.server is not None:
            self._compare_md.content = text
            self._compare_img.image = pair
            self._compare_img.visible = True
        with self._lock:
            aspect = self.clients[key].aspect if key in self.clients else 1.0
        self.set_camera(key, position, wxyz, fov, aspect)     # the window keeps its shape

    def save(self, key):
        """Write the view of ``key`` at full resolution: ``view_NNN.png`` (sRGB over
        the background), ``view_NNN.exr`` (linear RGBA), ``view_NNN.xml`` (its
        camera as a Mitsuba sensor) and the command that renders it again."""
        import mitsuba as mi
        with self._lock:
            c = self.clients.get(key)
            if c is None or c.position is None:
                return None
            pose = (c.position, c.wxyz, c.fov, c.aspect)
        camera = browser_camera(*pose, self.resolution)
        image = self.shown.render(camera, spp=self.spp)
        if image is None:
            return None
        self.save_dir.mkdir(parents=True, exist_ok=True)
        k = 1 + len(list(self.save_dir.glob("view_*.xml")))
        stem = self.save_dir / f"view_{k:03d}"
        with needs("viewer", "the live viewer"):
            from PIL import Image
        Image.fromarray(srgb8(image, self.background)).save(f"{stem}.png")
        mi.Bitmap(np.ascontiguousarray(image, np.float32),
                  mi.Bitmap.PixelFormat.RGBA).write(f"{stem}.exr")
        Path(f"{stem}.xml").write_text(sensor_xml(camera, self.spp))
        command = self.shown.command(f"{stem}.xml", f"{stem}.exr")
        self.saved = dict(png=f"{stem}.png", exr=f"{stem}.exr", xml=f"{stem}.xml",
                          command=command)
        print(f"saved {stem}.png, {stem}.exr and the camera {stem}.xml"
              + (f"; render it again: {command}" if command else ""))
        if self.server is not None:
            self._status_md.content = (f"saved `{stem}.png`, `.exr`, camera `{stem}.xml`"
                                       + (f"  \n`{command}`" if command else ""))
        return self.saved


def _thumbnail(image, side=96):
    """An 8-bit image shrunk to at most ``side`` pixels along its longer side."""
    with needs("viewer", "the live viewer"):
        from PIL import Image
    im = Image.fromarray(image)
    im.thumbnail((side, side))
    return np.asarray(im)


def _last_line(e):
    text = [line for line in str(e).splitlines() if line.strip()]
    return text[-1] if text else type(e).__name__


class FitViewer(Viewer):
    """The viewer of a fit while it runs (``fit --viewer``): between optimizer
    steps it renders the current mesh from the browser's camera, in at most
    ``share`` of the fit's time (it skips a step's turn when its renders so
    far exceed that share of the time since the fit began), and shows the
    stage, the loss and the training PSNR's curve."""

    def __init__(self, trainer, share=FIT_SHARE, **kwargs):
        self.share = float(share)
        super().__init__(FitShown(trainer), **kwargs)
        self.began = self.now()
        self.curve = {"step": [], "loss": [], "psnr": []}
        self._plotted = 0.0
        if self.server is not None:
            with needs("viewer", "the live viewer"):
                import viser.uplot as uplot
            with self.server.gui.add_folder("Fit", order=-1):
                self._stage_md = self.server.gui.add_markdown("starting")
                self._plot = self.server.gui.add_uplot(
                    data=(np.zeros(1), np.zeros(1)),
                    series=(uplot.Series(label="step"),
                            uplot.Series(label="training PSNR (dB)", stroke="#3060d0",
                                         width=2)),
                    scales={"x": uplot.Scale(time=False, auto=True),
                            "y": uplot.Scale(auto=True)},
                    legend=uplot.Legend(show=True), aspect=1.6)

    def set_trainer(self, trainer):
        """The fit's next stage."""
        self.shown.set_trainer(trainer)
        self.changed()

    def after_step(self, trainer, loss, psnr, stage_text):
        """Called by the fit after each step: record it, and render if the
        viewer is within its share of the fit's time."""
        step = trainer.state.step
        self.curve["step"].append(step)
        self.curve["loss"].append(float(loss))
        self.curve["psnr"].append(float(psnr))
        now = self.now()
        if self.server is not None and now - self._plotted > 1.0:
            self._plotted = now
            self._plot.data = (np.asarray(self.curve["step"], np.float64),
                               np.asarray(self.curve["psnr"], np.float64))
            self._stage_md.content = (f"{stage_text}  \nstep {step:,}, loss {loss:.4g}, "
                                      f"training PSNR {psnr:.2f} dB")
        budget = self.share * (now - self.began) - self.render_seconds
        while self.update(budget=budget):
            budget = self.share * (self.now() - self.began) - self.render_seconds
            if budget <= 0.0:
                break


def serve(scene, port=8080, host="127.0.0.1", resolution=512, block=True, **kwargs):
    """Show a Mitsuba scene (``mi.load_file``/``mi.load_dict``: tet meshes, and
    anything else Mitsuba renders) in the browser, rendered with its
    integrator from the browser's camera. ``block``: serve until Ctrl-C; else
    serve from a thread and return the :class:`Viewer` (its ``stop()`` ends
    it; do not change the scene meanwhile). Prints the address to open."""
    viewer = Viewer(SceneShown(scene), port=port, host=host, resolution=resolution, **kwargs)
    print(f"viewer: {viewer.url}")
    if not block:
        return viewer.start()
    try:
        viewer.run()
    except KeyboardInterrupt:
        pass
    finally:
        viewer.stop()
    return viewer
