"""The settings of a render of a mesh file or a scene, typed: what
``mi-tetvr render`` takes as options (generated from the fields, as ``fit``'s
from :class:`~mi_tetvr.recon.config.FitConfig`), what the live viewer's
controls set, and what :func:`mi_tetvr.apps.framing.mesh_scene` builds a
scene from.

Each field is written once with its default and help (``setting``, as
FitConfig's). :meth:`RenderSettings.validate` says which options do not
combine, for a mesh file or for an XML scene, as ``ValueError`` with the
message the command line prints.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from mi_tetvr.recon.config import setting

__all__ = ["RenderSettings", "OPACITY_SCALE", "MODES", "DEFAULT_VIEW", "DEFAULT_UP",
           "image_size", "numbers", "refuse"]

#: The default opacity scale (a transfer function's opacity per mesh radius), of every
#: command and of the fit.
OPACITY_SCALE = 1.0
#: ``render MESH``'s modes: volume rendering, the intensity projections, a slice, isosurfaces.
MODES = ("dvr", "max", "min", "mean", "slice", "iso")
#: The framing camera's azimuth and elevation (degrees about the up axis) and up axis.
DEFAULT_VIEW = (45.0, 30.0)
DEFAULT_UP = (0.0, 0.0, 1.0)


# -- the values' parsers: command-line text, or the values themselves from Python ------------

def numbers(k=None, nonzero=False):
    """A parser of ``k`` numbers (any count where ``k`` is None): comma-separated text or a
    sequence (or one number) -> a tuple of floats; ``ValueError`` otherwise, or where
    ``nonzero`` and all are zero."""
    def parse(value):
        try:
            if isinstance(value, str):
                x = tuple(float(v) for v in value.split(","))
            else:
                x = tuple(float(v) for v in np.atleast_1d(np.asarray(value, np.float64)))
        except (TypeError, ValueError):
            x = None
        if x is None or (k is not None and len(x) != k) or not x:
            raise ValueError(f"expected {'' if k is None else f'{k} '}comma-separated "
                             f"numbers, got {value!r}")
        if nonzero and not any(x):
            raise ValueError(f"expected a non-zero vector, got {value!r}")
        return x
    return parse


def image_size(value):
    """``WxH`` or ``N`` (N x N), or ``N`` or ``(width, height)`` -> ``(width, height)``."""
    try:
        if isinstance(value, str):
            parts = tuple(int(x) for x in value.lower().split("x"))
        else:
            parts = tuple(int(x) for x in np.atleast_1d(value))
        if len(parts) == 1:
            parts = parts * 2
        if len(parts) != 2 or min(parts) < 1:
            raise ValueError
    except (TypeError, ValueError):
        raise ValueError(f"must be WxH (e.g. 640x480) or N, got {value!r}") from None
    return parts


def refuse(options, names, why):
    """``ValueError`` naming the options among ``names`` that were given (not None or
    False among ``options``' attributes: settings or a command line's) but do not apply."""
    given = [f"--{n.replace('_', '-')}" for n in names
             if getattr(options, n) not in (None, False)]
    if given:
        raise ValueError(f"{', '.join(given)} {'does' if len(given) == 1 else 'do'} not "
                         f"apply {why}")


@dataclass(frozen=True)
class RenderSettings:
    """How a mesh file (or an XML scene) is rendered: ``mi-tetvr render``'s options
    (``--clip-box`` is ``clip_box``), each field's help in its metadata. Values given
    from Python are read as the command line reads them (``plane="0,0,0,0,0,1"`` or
    ``plane=(0, 0, 0, 0, 0, 1)``); :meth:`validate` checks which of them combine."""
    tf: str | None = setting(
        None, "mesh file: transfer function of its scalar (a file, or a matplotlib colormap's "
        "name; default for --mode max|min|mean: gray)")
    scalar: str | None = setting(
        None, "mesh file: the scalar array: point data, or cell data (volume rendering, "
        "constant in each tet) (default: the only one)")
    mode: str = setting(
        "dvr", "mesh file: volume rendering (dvr, default), the maximum, minimum or mean "
        "intensity projection of its scalar, its scalar on a plane (slice) or its "
        "isosurfaces (iso)", choices=MODES)
    shade: bool = setting(
        False, "mesh file, volume rendering with --tf: light the volume by a headlight at the "
        "scalar's gradient (ParaView's Shade)")
    iso: tuple | None = setting(
        None, "--mode iso: the isovalue(s), in the scalar's units (default: the middle of its "
        "range); with --mode dvr: isosurfaces drawn in the volume", metavar="V[,V...]",
        parse=numbers())
    plane: tuple | None = setting(
        None, "--mode slice: a point of the plane and its normal (default: the mesh's centre, "
        "normal --up); with --mode dvr: a slice drawn in the volume",
        metavar="X,Y,Z,NX,NY,NZ", parse=numbers(6))
    surface_opacity: float | None = setting(
        None, "isosurfaces and slices: their opacity in (0, 1] (default 1); below 1 what lies "
        "behind shows through", metavar="A")
    clip: tuple | None = setting(
        None, "mesh file: cut away what lies beyond the plane through X,Y,Z on the side its "
        "normal points to", metavar="X,Y,Z,NX,NY,NZ", parse=numbers(6))
    clip_box: tuple | None = setting(
        None, "mesh file: cut away what lies outside the box", metavar="X0,Y0,Z0,X1,Y1,Z1",
        parse=numbers(6))
    value_range: tuple | None = setting(
        None, "mesh file with --tf or a projection: the scalar values the transfer function "
        "spans (default: the data's range)", metavar="LO,HI", parse=numbers(2))
    sensor: str | None = setting(
        None, "render from this Mitsuba sensor (e.g. one the viewer saved) instead of the "
        "scene's camera (a mesh file: instead of --view)", metavar="SENSOR.xml")
    view: tuple | None = setting(
        None, "mesh file: camera azimuth and elevation in degrees about --up (default 45,30)",
        metavar="AZ,EL", parse=numbers(2))
    up: tuple | None = setting(
        None, "mesh file: the up axis (default 0,0,1)", metavar="X,Y,Z",
        parse=numbers(3, nonzero=True))
    orbit: int | None = setting(
        None, "mesh file: N frames once around --up from --view, written as the -o FILE.mp4 "
        "video and a contact sheet to the -o images", metavar="N")
    opacity_scale: float = setting(
        OPACITY_SCALE, "with a transfer function: its opacity per mesh radius times this (per "
        f"unit length on a grid volume; default {OPACITY_SCALE:g})")
    spp: int = setting(0, "samples per pixel (default: the scene's)")
    res: tuple | None = setting(
        None, "film size of every sensor, WxH or N (default: the scene's)", metavar="WxH",
        parse=image_size)
    lights: str | None = setting(
        None, "a Mitsuba scene file (.xml) of lights and surroundings: the mesh path traced lit "
        "by them, shadows included: --mode dvr, a scattering medium (tetpath; the transfer "
        "function's colors its albedo, classified at the vertices), with --iso/--plane its "
        "surfaces in it; --mode iso|slice, the surfaces alone (Mitsuba's path); surfaces are "
        "VTK's contour or cut, diffuse in the transfer function's colors", metavar="XML")
    classification: str | None = setting(
        None, "how tetmesh shapes with a transfer function classify their scalar: post (along "
        "each ray, the default) or pre (vertices shaded at load)", choices=("post", "pre"))
    repair: bool = setting(
        False, "drop folded, flat and duplicate tets of the mesh read (reported)")
    cell_to_point: bool = setting(
        False, "average the mesh's per-cell arrays onto its vertices")

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value, parse = getattr(self, f.name), f.metadata.get("parse")
            if value is not None and parse is not None:
                object.__setattr__(self, f.name, parse(value))

    # -- what is not given, as rendered
    @property
    def azimuth_elevation(self):
        """The framing camera's ``(azimuth, elevation)`` in degrees (``view``, else 45, 30)."""
        return self.view or DEFAULT_VIEW

    @property
    def up_axis(self):
        """The up axis (``up``, else z)."""
        return self.up or DEFAULT_UP

    @property
    def classified(self):
        """Whether a mesh file's scalar is classified (by ``--tf``, or a projection's gray)."""
        return bool(self.tf) or self.mode != "dvr"

    @property
    def surface(self):
        """The surfaces drawn: ``"iso"``, ``"slice"`` (``--mode iso|slice``, or in the
        volume with ``--iso``/``--plane``) or None."""
        if self.mode == "dvr":
            return "iso" if self.iso is not None else "slice" if self.plane else None
        return {"iso": "iso", "slice": "slice"}.get(self.mode)

    def validate(self, scene="mesh", series=False):
        """Raise ``ValueError`` where options do not combine, for ``scene`` ``"mesh"`` (a
        mesh file; ``series``: several, one camera) or ``"xml"`` (a Mitsuba XML scene,
        whose shapes, integrator and sensors say what the mesh options say)."""
        if scene not in ("mesh", "xml"):
            raise ValueError(f"scene must be 'mesh' or 'xml', got {scene!r}")
        mesh = scene == "mesh"
        if self.mode not in MODES:
            raise ValueError(f"--mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if self.value_range is not None and not self.value_range[1] > self.value_range[0]:
            raise ValueError(f"--value-range needs LO < HI, got {self.value_range}")
        if self.value_range is not None and mesh and not self.classified:
            raise ValueError("--value-range is the range of a scalar's transfer function: it "
                             "needs --tf (or a projection --mode)")
        if self.lights is not None:
            if not mesh:
                raise ValueError("--lights lights a mesh file; an XML scene has its own emitters")
            if self.mode not in ("dvr", "iso", "slice") or (self.mode == "dvr" and not self.tf):
                raise ValueError("--lights path traces a scalar under a transfer function: "
                                 "--mode dvr with --tf, or --mode iso|slice")
            lit_off = [f for f, on in (("--shade", self.shade), ("--clip", self.clip),
                                       ("--clip-box", self.clip_box),
                                       ("--surface-opacity", self.surface_opacity is not None),
                                       ("--classification", self.classification is not None))
                       if on]
            if lit_off:
                raise ValueError(f"--lights does not combine with {', '.join(lit_off)}")
        if self.sensor is not None:
            given = [f for f, on in (("--orbit", self.orbit is not None),
                                     ("--res", self.res is not None),
                                     ("--view", self.view is not None),
                                     ("--up", self.up is not None), ("a series", series)) if on]
            if given:
                raise ValueError(f"--sensor says where the camera is and its film's size; "
                                 f"{', '.join(given)} cannot be combined with it")
        if self.orbit is not None and (not mesh or series):
            raise ValueError("--orbit circles one mesh file (an XML scene's sensors stay)")
        if self.orbit is not None and self.orbit < 1:
            raise ValueError(f"--orbit needs at least 1 frame, got {self.orbit}")
        if mesh:
            self._validate_mesh()
        else:
            self._validate_xml()

    def _validate_mesh(self):
        refuse(self, ("classification",), "to a mesh (its scalar is post-classified)")
        if not self.classified and (self.scalar or self.shade):
            raise ValueError(f"--{'scalar' if self.scalar else 'shade'} needs --tf")
        if self.shade and self.mode != "dvr":
            raise ValueError("--shade lights volume rendering (--mode dvr)")
        if self.mode == "dvr" and (self.iso is not None or self.plane):
            if self.iso is not None and self.plane:
                raise ValueError("the volume takes one kind of surface: --iso or --plane")
            if not self.tf:
                raise ValueError("--iso or --plane in volume rendering needs --tf (a scalar)")
        elif self.mode != "iso" and self.iso is not None:
            raise ValueError("--iso gives the isovalues of --mode iso (or dvr)")
        elif self.mode != "slice" and self.plane:
            raise ValueError("--plane is the plane of --mode slice (or dvr)")
        if self.surface_opacity is not None and (self.surface is None
                                                 or not 0 < self.surface_opacity <= 1):
            raise ValueError("--surface-opacity is an opacity in (0, 1] of isosurfaces and "
                             "slices")

    def _validate_xml(self):
        given = [f for f, on in (("--view", self.view is not None),
                                 ("--up", self.up is not None)) if on]
        if given:
            raise ValueError(f"{', '.join(given)} {'frames' if len(given) == 1 else 'frame'} "
                             f"a mesh file; an XML scene's sensor says where it looks")
        refuse(self, ("tf", "scalar", "plane", "clip", "clip_box", "iso", "shade",
                      "surface_opacity", "value_range"),
               "to an XML scene (its shapes name their transfer functions, its integrator "
               "its mode and clip)")
        if self.opacity_scale != OPACITY_SCALE:
            raise ValueError("--opacity-scale applies to a mesh file rendered with --tf")
        if self.mode != "dvr":
            raise ValueError("--mode applies to a mesh file (an XML scene names its "
                             "integrator: 'tetproj' with its mode)")
