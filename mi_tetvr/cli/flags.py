"""The options the commands share (``-o/--out``, ``--res``, ``--variant``, ``--quiet``,
``--repair`` and ``--cell-to-point``, the viewer's ``--port`` and ``--host``, ...),
and the options generated from a settings dataclass: one per field of
:class:`~mi_tetvr.apps.settings.RenderSettings` (``render``) or of
:class:`~mi_tetvr.recon.config.FitConfig` (``fit``), with the field's type,
choices, metavar and help."""
from __future__ import annotations

import argparse
import dataclasses
import json

from mi_tetvr.apps.settings import OPACITY_SCALE
from mi_tetvr.apps.settings import image_size as _image_size

#: The Mitsuba variants mi_tetvr renders in.
VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")


def argument_type(parse, name):
    """``parse`` (text -> value, ``ValueError`` on bad text) as an argparse type: its
    message is argparse's error (exit status 2)."""
    def typed(text):
        try:
            return parse(text)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
    typed.__name__ = name
    return typed


#: ``WxH`` or ``N`` (N x N) -> (width, height), as an argparse type.
image_size = argument_type(_image_size, "image_size")


# -- the shared options --------------------------------------------------------------------

def out(parser, help, required=True, append=False):
    parser.add_argument("-o", "--out", required=required, action="append" if append else None,
                        help=help)


def variant(parser):
    parser.add_argument("--variant", default="llvm_ad_rgb",
                        help="Mitsuba variant: llvm_ad_rgb (CPU, default) or cuda_ad_rgb (GPU)")


def quiet(parser):
    parser.add_argument("-q", "--quiet", action="store_true",
                        help="no progress bars (in a log file they write a line every few "
                             "seconds)")


def mesh_flags(parser):
    """The flags of the commands that read a mesh file."""
    parser.add_argument("--repair", action="store_true",
                        help="drop folded, flat and duplicate tets of the mesh read (reported)")
    parser.add_argument("--cell-to-point", action="store_true",
                        help="average the mesh's per-cell arrays onto its vertices")


def serve(parser):
    parser.add_argument("--port", type=int, default=8080,
                        help="viewer: the port to serve on (default 8080; the next free one "
                        "when taken)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="viewer: the address to listen on (default 127.0.0.1, this "
                        "machine only; 0.0.0.0: every network)")


def res(parser, default, help="image size in pixels, WxH or N"):
    parser.add_argument("--res", type=image_size, default=default, metavar="WxH",
                        help=f"{help} (default {default[0]}x{default[1]})" if default else help)


def opacity_scale(parser, default=OPACITY_SCALE):
    parser.add_argument("--opacity-scale", type=float, default=default,
                        help="with a transfer function: its opacity per mesh radius times this "
                             f"(per unit length on a grid volume; default {OPACITY_SCALE:g})")


# -- options generated from settings dataclasses -------------------------------------------

def setting_type(f):
    """The Python type a settings field holds (from its annotation)."""
    text = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
    for name, kind in (("bool", bool), ("int", int), ("float", float), ("str", str)):
        if text.split(" | ")[0] == name:
            return kind
    return str


def _typed(f, kind):
    """argparse's ``type`` (the field's ``parse``, else its type) and ``choices`` of a
    settings field."""
    kw = {"type": argument_type(f.metadata.get("parse", kind), kind.__name__)}
    if "choices" in f.metadata:
        kw["choices"] = f.metadata["choices"]
    return kw


def _flag(f):
    return f.metadata.get("flag", "--" + f.name.replace("_", "-"))


def settings_flags(parser, cls):
    """One option per field of the settings dataclass ``cls`` (:class:`RenderSettings`):
    ``--name-with-dashes`` (or the field's ``flag``), the field's default, type (its
    ``parse``), choices, metavar and help; a boolean is a switch (``store_true``).
    :func:`settings_of` makes the parsed options the settings again."""
    for f in dataclasses.fields(cls):
        meta = f.metadata
        kind = setting_type(f)
        kw = dict(dest=f.name, default=f.default, help=meta["help"].replace("%", "%%"))
        if kind is bool:
            kw["action"] = "store_true"
        else:
            kw.update(_typed(f, kind))
            if "metavar" in meta:
                kw["metavar"] = meta["metavar"]
        parser.add_argument(_flag(f), **kw)


def settings_of(cls, a):
    """The settings dataclass ``cls`` of a parsed command line (:func:`settings_flags`)."""
    return cls(**{f.name: getattr(a, f.name) for f in dataclasses.fields(cls)})


def config_flags(parser):
    """One option per :class:`~mi_tetvr.recon.config.FitConfig` field, generated from the
    fields: ``--name-with-dashes`` (or the field's ``flag``), its type, choices and help
    with the default; booleans have ``--no-...``; every option's default is ``None`` (the
    config file's or the field's value stands). Returns {dest: field name}."""
    from mi_tetvr.recon.config import PARTS, FitConfig
    groups = {part: parser.add_argument_group(f"fit settings: {part}, {about} (--config's "
                                              f"'{part}')")
              for part, (about, _) in PARTS.items()}
    dests = {}
    for part, f in FitConfig.settings():
        group = groups[part]
        meta = f.metadata
        default = "chosen by the run" if f.default is None else json.dumps(f.default)
        help = meta["help"] if "default" in meta["help"] else \
            f"{meta['help']} (default: {default})"
        kind = setting_type(f)
        kw = dict(dest=f"cfg_{f.name}", default=None, help=help.replace("%", "%%"))
        if kind is bool:
            kw["action"] = argparse.BooleanOptionalAction
        else:
            kw.update(_typed(f, kind))
            if "choices" not in meta:
                kw["metavar"] = meta.get("metavar", {int: "N", float: "X"}.get(kind, "TEXT"))
        group.add_argument(_flag(f), **kw)
        dests[f"cfg_{f.name}"] = f.name
    return dests
