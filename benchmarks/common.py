"""Shared pieces of the benchmarks: the grid scene, the camera, timing.

Import after ``mi.set_variant()``.
"""
from __future__ import annotations

import os
import platform
import statistics
import time

import drjit as dr
import mitsuba as mi

import mi_tetvr
from mi_tetvr.mesh.generate import blob_field, grid_mesh

CAM_ORIGIN = [2.6, 1.8, 3.4]
CAM_FOV = 33.0


def header(title):
    print(f"# mi_tetvr {title}  (mitsuba {mi.__version__}, drjit {dr.__version__}, "
          f"variant {mi.variant()})")
    print(f"# device: {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPU cores, Dr.Jit thread pool size {dr.thread_count()}; "
          f"python {platform.python_version()}")


def sensor_dict(res):
    """Perspective camera looking at the origin, one pixel-centre ray per pixel."""
    return {
        "type": "perspective",
        "fov": CAM_FOV,
        "to_world": mi.ScalarTransform4f().look_at(origin=CAM_ORIGIN, target=[0, 0, 0],
                                                   up=[0, 1, 0]),
        "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
        "film": {"type": "hdrfilm", "width": res, "height": res, "pixel_format": "rgb",
                 "rfilter": {"type": "box"}},
    }


def grid_scene(cells, res, jitter=0.15, scale=1.0, **integrator):
    """The jittered ``cells^3`` grid over [-1, 1]^3 carrying the blob field, in
    a scene with the tetvr integrator (``integrator`` are its properties).
    Returns (scene, vertices, tets, color, opacity)."""
    v, tets = grid_mesh(cells, jitter=jitter)
    color, opacity = blob_field(v, scale)
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "tetvr", **integrator},
        "sensor": sensor_dict(res),
        "volume": mi_tetvr.tetmesh_dict(v, tets, color, opacity),
    })
    return scene, v, tets, color, opacity


def timed(fn, repeat):
    """(first-run seconds incl. compilation, median of ``repeat`` warm runs,
    the warm runs, the last result)."""
    dr.sync_thread()
    t0 = time.perf_counter()
    out = fn()
    dr.sync_thread()
    first = time.perf_counter() - t0
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
    return first, statistics.median(times), times, out
