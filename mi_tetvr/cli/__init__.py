"""The ``mi-tetvr`` command line.

    mi-tetvr render SCENE.xml|MESH [MESH ...|SERIES.pvd] -o OUT.exr|.png|.mp4 [-o ...]
                    [--res WxH] [--spp N]
                    [--tf TF|COLORMAP] [--mode dvr|max|min|mean|slice|iso] [--view AZ,EL]
                    [--iso V,...] [--plane X,Y,Z,NX,NY,NZ] [--surface-opacity A]
                    [--clip X,Y,Z,NX,NY,NZ] [--clip-box X0,Y0,Z0,X1,Y1,Z1] [--orbit N]
                    [--value-range LO,HI] [--sensor SENSOR.xml] [--workers N] [--address A]
    mi-tetvr info MESH [--json]
    mi-tetvr make-scenes [-o DIR]
    mi-tetvr make-dataset VOLUME|MESH (--tf TF | --xray) -o DIR [--views N] [--res WxH]
    mi-tetvr make-capture -o DIR [--views N] [--res WxH] [--spp S]
    mi-tetvr process-data IMAGES_DIR|VIDEO -o DIR [--reference DATA]
    mi-tetvr process-xray SCAN.h5 -o DIR [--center C|auto] [--hold-out K] [--rings]
    mi-tetvr fit DATA -o DIR [--config FILE] [--print-config] [--time-budget MIN] [--viewer]
                 [...]
    mi-tetvr eval FIT_DIR|MESH DATA [-o METRICS.json] [--images DIR]
    mi-tetvr uncertainty FIT_DIR DATA [--stride S] [--draws K]
    mi-tetvr next-view FIT_DIR DATA --candidates DATA|N [-o RANKING.json]
    mi-tetvr export FIT|MESH -o OUT.ply|.obj|.glb [--level L] [--array NAME] [--points]
    mi-tetvr refine MESH --select ARRAY [--fraction F] -o OUT
    mi-tetvr viewpoint MESH -o DIR [--tf TF] [--res WxH]
    mi-tetvr partition MESH -o OUT.pvtu --blocks N
    mi-tetvr sweep DATA SWEEP.yaml -o DIR [--workers N] [--address A]
    mi-tetvr view MESH|SCENE.xml|DATA|FIT_DIR [--tf TF] [--port P] [--host H] [--res N]

One module per command (``render``, ``info``, ``make_scenes``, ``make_dataset``,
``make_capture``, ``process_data``, ``process_xray``, ``fit``, ``view``, ``evaluate`` for ``eval``,
``uncertainty``, ``next_view`` for ``next-view``, ``export``, ``refine``, ``viewpoint``,
``partition``, ``sweep``), each with its ``NAME``, ``HELP``,
``add_arguments(parser)`` and ``run(args)``; :mod:`~mi_tetvr.cli.flags` holds the shared options
and those generated from settings dataclasses (``render``'s from
:class:`~mi_tetvr.apps.settings.RenderSettings`, ``fit``'s from
:class:`~mi_tetvr.recon.config.FitConfig`), :mod:`~mi_tetvr.cli.common` what the
commands share at run time. A command raises what it cannot do (``ValueError``,
``FileNotFoundError``, :class:`~mi_tetvr.cli.common.CommandError`); :func:`main`
alone ends the process.

Conventions (every command): ``-o/--out`` names what a command writes (a file or a
folder); ``--res WxH`` (or ``N`` for N x N) is an image size in pixels; ``--variant``
picks the Mitsuba variant of the commands that render; ``--quiet`` hides progress bars
(in a log file they are a line every few seconds); ``--repair`` and ``--cell-to-point``
apply to every mesh a command reads; ``--opacity-scale`` is a transfer function's
opacity per mesh radius (default 1). Errors are one line, ``mi-tetvr: ...``, exit
status 2 for bad usage and 1 otherwise; ``MI_TETVR_TRACEBACK=1`` shows the traceback.
A command that needs an optional package says which extra brings it
(``pip install "mi_tetvr[viewer]"``) before it starts.
"""
from __future__ import annotations

import argparse
import os
import sys
import textwrap

from mi_tetvr.apps.settings import OPACITY_SCALE
from mi_tetvr.cli import (evaluate, export, fit, info, make_capture, make_dataset,
                          make_scenes, next_view, partition, process_data, process_xray, refine,
                          render, sweep, uncertainty, view, viewpoint)
from mi_tetvr.cli.common import CommandError, scene_xml
from mi_tetvr.cli.fit import fit_config
from mi_tetvr.cli.flags import (VARIANTS, config_flags, image_size, settings_flags,
                                settings_of)
from mi_tetvr.cli.flags import setting_type as _setting_type
from mi_tetvr.cli.info import mesh_report
from mi_tetvr.cli.make_dataset import TEST_VIEWS
from mi_tetvr.cli.render import series_paths
from mi_tetvr.cli.view import fit_dataset, view_shown
from mi_tetvr.extras import MissingExtra

__all__ = ["main", "build_parser", "command_summary", "COMMANDS", "CommandError", "scene_xml",
           "mesh_report", "fit_config", "fit_dataset", "view_shown", "series_paths",
           "config_flags", "settings_flags", "settings_of", "image_size", "OPACITY_SCALE",
           "TEST_VIEWS", "VARIANTS", "_setting_type"]

#: The commands, in the order ``mi-tetvr --help`` and the README list them.
COMMANDS = (render, info, make_scenes, make_dataset, make_capture, process_data, process_xray,
            fit, view, evaluate, uncertainty, next_view, export, refine, viewpoint, partition,
            sweep)


def build_parser():
    """The ``mi-tetvr`` argument parser: one subparser per command of :data:`COMMANDS`,
    each with its module's options and ``func`` its ``run``."""
    from mi_tetvr import __version__
    p = argparse.ArgumentParser(
        prog="mi-tetvr", description="Differentiable volume rendering of tetrahedral meshes "
        "in Mitsuba 3.", epilog=textwrap.fill(
            "Conventions: " + __doc__.split("Conventions (every command): ")[1].split("\n\n")[0]
            .replace("\n", " ").replace("%", "%%").replace("``", "'"), 88),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--version", action="version", version=f"mi-tetvr {__version__}")
    sub = p.add_subparsers(dest="cmd", required=True, metavar="COMMAND")
    for command in COMMANDS:
        c = sub.add_parser(command.NAME, help=command.HELP)
        command.add_arguments(c)
        c.set_defaults(func=command.run)
    return p


def command_summary():
    """Markdown lines, one per command: its positional arguments and required options,
    with its help. The README's command list is this text (a test keeps them equal);
    every option is in the documentation's command-line reference, generated from the
    same parsers."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    helps = {c.dest: c.help for c in sub._choices_actions}
    lines = []
    for name, p in sub.choices.items():
        words = [f"mi-tetvr {name}"]
        for a in p._actions:
            if not a.option_strings:
                words.append(a.dest.upper().replace("-", "_"))
            elif a.required and not isinstance(a, argparse._HelpAction):
                words.append(f"{a.option_strings[0]} {a.dest.upper()}")
        lines.append(f"- `{' '.join(words)}` — {helps[name]}")
    return "\n".join(lines)


def error_message(e):
    """The line ``mi-tetvr: ...`` says of an exception a command raised (``None``: it
    says nothing more; status 1): one line, also where a message (Mitsuba's) has
    several."""
    if isinstance(e, KeyboardInterrupt):
        return "interrupted"
    # what a command could not do with its input (the library's messages say what is
    # wrong and the way past it)
    text = str(e).strip("'\"") if isinstance(e, KeyError) else str(e)
    if isinstance(e, FileNotFoundError) and e.filename and str(e.filename) not in text:
        text = f"file not found: {e.filename}"
    text = " ".join(line.strip() for line in text.splitlines() if line.strip())
    if isinstance(e, CommandError):
        return text or None
    return text or type(e).__name__


def _one_line_warnings():
    """The project's own warnings (a renamed setting read, ...) as one line each,
    ``mi-tetvr: warning: <message>``; other packages' as Python shows them."""
    import warnings
    from pathlib import Path
    if getattr(warnings.showwarning, "one_line", False):
        return
    default, root = warnings.showwarning, str(Path(__file__).resolve().parents[1])

    def show(message, category, filename, lineno, file=None, line=None):
        if category is UserWarning and str(filename).startswith(root):
            print(f"mi-tetvr: warning: {message}", file=file or sys.stderr)
        else:
            default(message, category, filename, lineno, file, line)
    show.one_line = True
    warnings.showwarning = show


def main(argv=None):
    """Run ``mi-tetvr`` with ``argv`` (default ``sys.argv[1:]``): the one place where the
    command line ends the process on an error, with one line ``mi-tetvr: <message>``
    (status 1; argparse's usage errors: 2). ``MI_TETVR_TRACEBACK=1`` lets the error
    through, with its traceback."""
    a = build_parser().parse_args(argv)
    _one_line_warnings()
    try:
        return a.func(a)
    except (CommandError, KeyboardInterrupt, ValueError, KeyError, OSError,
            RuntimeError, MissingExtra) as e:
        message = error_message(e)
        if message is None:
            sys.exit(1)
        if os.environ.get("MI_TETVR_TRACEBACK"):
            raise
        sys.exit(f"mi-tetvr: {message}")
