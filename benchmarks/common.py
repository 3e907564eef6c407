"""Shared pieces of the benchmarks: the command line, the header and the JSON
results, timing, the grid scene and the camera.

A benchmark builds its command line with :func:`make_parser` (the common
options ``--variant``, ``--repeat``, ``--quick``, ``--json PATH``) and adds its
own options; a Dr.Jit benchmark sets the Mitsuba variant before it imports
``mi_tetvr`` (this module imports neither at import time). What it prints it
also collects as numbers and hands to :func:`write_json`, which writes, when
``--json PATH`` is given::

    {
      "benchmark": "render",         # the script's name without "bench_"
      "header": {                    # header_info(): what the printed header says
        "title": ..., "date": ...,   # ISO 8601, UTC
        "python": ..., "numpy": ..., "mi_tetvr": ..., "mitsuba": ..., "drjit": ...,
        "variant": ...,              # null for the numpy benchmarks
        "device": ..., "cpu": ..., "cpu_count": ..., "drjit_threads": ...
      },
      "args": {...},                 # the parsed options
      "results": {...}               # the benchmark's printed numbers (seconds, counts, ...)
    }
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path

CAM_ORIGIN = [2.6, 1.8, 3.4]
CAM_FOV = 33.0


# ----------------------------------------------------------------------------
# Command line, header, JSON
# ----------------------------------------------------------------------------

def make_parser(doc, *, variant=True, repeat=3, quick=None):
    """The benchmarks' argument parser with the common options.

    Parameters
    ----------
    doc : str
        The benchmark's module docstring: its first paragraph is the
        description, the rest the epilog of ``--help``.
    variant : bool
        Offer ``--variant`` (default ``llvm_ad_rgb``); False for the numpy
        benchmarks.
    repeat : int or None
        Default of ``--repeat`` (timed runs); None where the benchmark has no
        repeated timing.
    quick : str, optional
        What ``--quick`` (a smoke run) stands for, for ``--help``.

    Returns
    -------
    argparse.ArgumentParser
        Common options: ``--variant``, ``--repeat``, ``--quick`` and
        ``--json PATH``; the benchmark adds its own and applies ``--quick``.
    """
    head, _, rest = doc.strip().partition("\n\n")
    p = argparse.ArgumentParser(description=head, epilog=rest or None,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    if variant:
        p.add_argument("--variant", default="llvm_ad_rgb",
                       help="Mitsuba variant (default llvm_ad_rgb; or cuda_ad_rgb)")
    if repeat is not None:
        p.add_argument("--repeat", type=int, default=repeat,
                       help=f"timed runs (default {repeat})")
    p.add_argument("--quick", action="store_true",
                   help="smoke run" + (f": {quick}" if quick else ""))
    p.add_argument("--json", metavar="PATH",
                   help="also write the header and the results as JSON to PATH")
    return p


def _variant():
    """The Mitsuba variant if one is set (without importing Mitsuba)."""
    mi = sys.modules.get("mitsuba")
    return mi.variant() if mi is not None else None


def _version(dist):
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def _cpu_name():
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _gpu_name():
    try:
        r = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"],
                           capture_output=True, text=True, timeout=10)
        return r.stdout.strip().splitlines()[0] if r.returncode == 0 and r.stdout.strip() else None
    except (OSError, subprocess.SubprocessError):
        return None


def header_info(title):
    """Versions, variant, device and date, as a dict (see the module docstring)."""
    import numpy as np
    variant = _variant()
    cpu = _cpu_name()
    info = {"title": title,
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "python": platform.python_version(), "numpy": np.__version__,
            "mi_tetvr": _version("mi_tetvr"), "mitsuba": _version("mitsuba"),
            "drjit": _version("drjit"), "variant": variant,
            "device": cpu, "cpu": cpu, "cpu_count": os.cpu_count(), "drjit_threads": None}
    if variant is not None:
        import drjit as dr
        info["drjit_threads"] = dr.thread_count()
        if variant.startswith("cuda"):
            info["device"] = _gpu_name() or "CUDA GPU"
    return info


def header(title):
    """Print the header of a Dr.Jit benchmark; returns :func:`header_info`."""
    info = header_info(title)
    print(f"# mi_tetvr {title}  (mitsuba {info['mitsuba']}, drjit {info['drjit']}, "
          f"variant {info['variant']})")
    print(f"# device: {info['device']}, {info['cpu_count']} CPU cores, Dr.Jit thread pool "
          f"size {info['drjit_threads']}; python {info['python']}")
    return info


def _plain(x):
    """JSON form of numpy scalars and arrays, paths."""
    if hasattr(x, "tolist"):
        return x.tolist()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"not JSON serializable: {type(x).__name__}")


def write_json(args, header, results):
    """Write ``{"benchmark", "header", "args", "results"}`` to ``args.json``
    (nothing without ``--json``)."""
    if not getattr(args, "json", None):
        return
    name = Path(sys.argv[0]).stem.removeprefix("bench_")
    out = {"benchmark": name, "header": header, "args": vars(args), "results": results}
    path = Path(args.json)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=2, default=_plain) + "\n")
    print(f"# results written to {path}")


# ----------------------------------------------------------------------------
# Timing
# ----------------------------------------------------------------------------

def sync():
    """Wait for Dr.Jit's queued work when a Mitsuba variant is set (a numpy
    benchmark has none: nothing to wait for)."""
    if _variant() is not None:
        import drjit as dr
        dr.sync_thread()


def timed(fn, repeat, warmup=True):
    """Time ``fn()``.

    With ``warmup`` (Dr.Jit: the first run includes tracing and compilation)
    one run, then ``repeat`` warm runs; without it, ``repeat`` runs, the first
    of which is also reported as the first run.

    Returns
    -------
    (first-run seconds, median seconds of the timed runs, the timed runs, the
    last result)
    """
    sync()
    times = []
    first = None
    out = None
    if warmup:
        t0 = time.perf_counter()
        out = fn()
        sync()
        first = time.perf_counter() - t0
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        sync()
        times.append(time.perf_counter() - t0)
    if first is None:
        first = times[0]
    return first, statistics.median(times), times, out


def add_code_options(p):
    """``--code DIR`` and ``--rounds N``: the benchmark also run with another
    checkout's package, alternating (:func:`alternate`)."""
    p.add_argument("--code", metavar="DIR",
                   help="another checkout of mi_tetvr (e.g. a worktree of the code before a "
                        "change): this script runs with its package too, in turns with this "
                        "checkout's, each in a process of its own")
    p.add_argument("--rounds", type=int, default=2,
                   help="turns of this checkout and --code (default 2)")


def check_code(p, a):
    """Refuse a ``--code`` that is not a checkout of mi_tetvr, or no
    ``--rounds``, in one line."""
    if getattr(a, "code", None) and not (Path(a.code) / "mi_tetvr").is_dir():
        p.error(f"--code {a.code}: not a checkout of mi_tetvr (no mi_tetvr/ in it)")
    if getattr(a, "rounds", 1) < 1:
        p.error(f"--rounds {a.rounds}: give at least 1")


def alternate(script, argv, code, rounds):
    """Run ``script`` with ``argv`` (its own options, without ``--code``) with
    this checkout's package and with ``code``'s, in turn, ``rounds`` times,
    each run in a process of its own and one after the other (never at
    once). Returns per round ``{"this": results, "other": results}`` (the
    ``results`` of each run's JSON)."""
    import tempfile

    from checkout_cli import command
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(rounds):
            row = {}
            for name, prefix in (("this", [sys.executable]), ("other", command(code))):
                path = Path(tmp) / f"{name}_{r}.json"
                cmd = prefix + [str(Path(script).resolve()), *argv, "--json", str(path)]
                run = subprocess.run(cmd, capture_output=True, text=True)
                if run.returncode != 0:
                    raise RuntimeError(f"{' '.join(cmd)} failed:\n{run.stderr[-3000:]}")
                row[name] = json.loads(path.read_text())["results"]
            out.append(row)
    return out


def spread(values):
    """``"median [min-max]"`` of a few ratios or seconds."""
    return (f"{statistics.median(values):.2f} [{min(values):.2f}-{max(values):.2f}]"
            if len(values) > 1 else f"{values[0]:.2f}")


# ----------------------------------------------------------------------------
# Scene (needs a Mitsuba variant)
# ----------------------------------------------------------------------------

def sensor_dict(res):
    """Perspective camera looking at the origin, one pixel-center ray per pixel."""
    import mitsuba as mi
    return {
        "type": "perspective",
        "fov": CAM_FOV,
        "to_world": mi.ScalarTransform4f().look_at(origin=CAM_ORIGIN, target=[0, 0, 0],
                                                   up=[0, 1, 0]),
        "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
        "film": {"type": "hdrfilm", "width": res, "height": res, "pixel_format": "rgb",
                 "rfilter": {"type": "box"}},
    }


def grid_scene(cells, res, jitter=0.15, scale=1.0, shuffle=False, **integrator):
    """The jittered ``cells^3`` grid over [-1, 1]^3 carrying the blob field, in
    a scene with the tetvr integrator (``integrator`` are its properties);
    ``shuffle`` lists vertices and tets in random order (as a mesh file
    may). Returns (scene, vertices, tets, color, opacity)."""
    import mitsuba as mi
    import numpy as np

    import mi_tetvr
    from mi_tetvr.mesh.generate import blob_field, grid_mesh
    v, tets = grid_mesh(cells, jitter=jitter)
    if shuffle:
        rng = np.random.default_rng(0)
        perm = rng.permutation(len(v))
        rank = np.empty_like(perm)
        rank[perm] = np.arange(len(perm))
        v, tets = v[perm], rank[tets][rng.permutation(len(tets))]
    color, opacity = blob_field(v, scale)
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "tetvr", **integrator},
        "sensor": sensor_dict(res),
        "volume": mi_tetvr.tetmesh_dict(v, tets, color, opacity),
    })
    return scene, v, tets, color, opacity


def pixel_rays(sensor, res):
    """One normalized ray through each pixel center (row-major, like the film)."""
    import drjit as dr
    import mitsuba as mi
    idx = dr.arange(mi.UInt32, res * res)
    x = mi.Float(idx % res) + 0.5
    y = mi.Float(idx // res) + 0.5
    ray, _ = sensor.sample_ray(mi.Float(0.0), mi.Float(0.5),
                               mi.Point2f(x / res, y / res), mi.Point2f(0.5))
    ray = mi.Ray3f(ray.o, dr.normalize(ray.d))
    dr.eval(ray)
    return ray


def render_steps(scene, keys, spp=1):
    """``(primal, backward)``: one ``mi.render`` of ``scene`` (evaluated),
    and one ``mi.render`` + ``dr.backward`` of an L2 loss against 0.9 x the
    first image with gradients on the parameters ``keys`` (returns them as
    numpy arrays). The target is rendered here."""
    import drjit as dr
    import mitsuba as mi
    import numpy as np
    params = mi.traverse(scene)
    target = mi.TensorXf(mi.render(scene, spp=spp)) * 0.9
    dr.eval(target)

    def primal():
        img = mi.render(scene, spp=spp)
        dr.eval(img)
        return img

    def backward():
        for k in keys:
            dr.enable_grad(params[k])
        loss = dr.mean(dr.square(mi.render(scene, params, spp=spp) - target), axis=None)
        dr.backward(loss)
        grads = [np.array(dr.grad(params[k])) for k in keys]
        for k in keys:
            dr.disable_grad(params[k])
        return grads
    return primal, backward


def vtk_offscreen(res, eye, target, fov):
    """``(vtk, renderer, window)``: an offscreen VTK window of ``res`` x ``res``
    pixels, black, its camera at ``eye`` looking at ``target`` (z up) with a
    vertical field of view of ``fov`` degrees."""
    import vtk
    ren = vtk.vtkRenderer()
    ren.SetBackground(0, 0, 0)
    win = vtk.vtkRenderWindow()
    win.SetOffScreenRendering(1)
    win.AddRenderer(ren)
    win.SetSize(res, res)
    cam = ren.GetActiveCamera()
    cam.SetPosition(*eye)
    cam.SetFocalPoint(*target)
    cam.SetViewUp(0, 0, 1)
    cam.SetViewAngle(fov)
    return vtk, ren, win


def vtk_ray_cast_volume(vtk, ren, source, color, opacity):
    """Add to ``ren`` the tet mesh ``source`` (a data set, or an algorithm's
    output port) volume-rendered by VTK's ``vtkUnstructuredGridVolumeRayCastMapper``
    with the ``vtkUnstructuredGridLinearRayIntegrator`` (exact for a transfer
    function linear between its points), one ray per pixel, unshaded:
    ``color`` a ``vtkColorTransferFunction``, ``opacity`` a
    ``vtkPiecewiseFunction`` (per unit length)."""
    prop = vtk.vtkVolumeProperty()
    prop.SetColor(color)
    prop.SetScalarOpacity(opacity)
    prop.SetScalarOpacityUnitDistance(1.0)
    prop.SetInterpolationTypeToLinear()
    prop.ShadeOff()
    mapper = vtk.vtkUnstructuredGridVolumeRayCastMapper()
    if isinstance(source, vtk.vtkAlgorithmOutput):
        mapper.SetInputConnection(source)
    else:
        mapper.SetInputData(source)
    mapper.SetRayIntegrator(vtk.vtkUnstructuredGridLinearRayIntegrator())
    mapper.SetImageSampleDistance(1.0)
    mapper.AutoAdjustSampleDistancesOff()
    volume = vtk.vtkVolume()
    volume.SetMapper(mapper)
    volume.SetProperty(prop)
    ren.AddVolume(volume)
    ren.ResetCameraClippingRange()
