"""Transfer-function gradients: many rays write into few texels. One
``mi.render`` + ``dr.backward`` with gradients on ``tf_color`` and
``tf_opacity`` of a post-classified mesh, against one primal render, for each
scatter strategy of the texel reads' reverse-mode derivative
(``dr.ReduceMode``), measured in the same run; every strategy's gradient is
checked against the first's.

Mesh: Blunt Fin's ``Density`` (187k tets, ``../shared/data``); with
``--quick`` or without the data, a jittered 16^3 grid with a smooth scalar.

Usage::

    python benchmarks/bench_tf_gradients.py            # Blunt Fin, 256x256
    python benchmarks/bench_tf_gradients.py --quick    # 16^3 grid, 32x32
"""
from __future__ import annotations

import json
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

from common import header, make_parser, render_steps, timed, write_json

MESH = Path(__file__).resolve().parents[2] / "shared" / "data" / "tets" / "bluntfin" / \
    "bluntfin_tets.vtu"
MODES = ("Auto", "Direct", "Local", "Expand")


def parse_args(argv=None):
    p = make_parser(__doc__, repeat=3, quick="16^3 grid, 32x32")
    p.add_argument("--res", type=int, default=256, help="image size (default 256)")
    p.add_argument("--resolution", type=int, default=256, help="tf_resolution (default 256)")
    a = p.parse_args(argv)
    if a.quick:
        a.res = 32
    return a


ARGS = parse_args()

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402

mi.set_variant(ARGS.variant)
import mi_tetvr  # noqa: E402
from mi_tetvr.render import optical  # noqa: E402

KEYS = ("volume.tf_color", "volume.tf_opacity")


def scene_of(a, tf_path):
    if MESH.is_file() and not a.quick:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            mesh = mi_tetvr.read_tetmesh(MESH)
        def shape(tf):
            return {"type": "tetmesh", "filename": str(MESH), "scalar_attribute": "Density",
                    **tf}
        name, bounds = "Blunt Fin", mesh.bounds
    else:
        from mi_tetvr.mesh.generate import grid_mesh
        V, T = grid_mesh(16, jitter=0.1)
        def shape(tf):
            return mi_tetvr.tetmesh_dict(V, T, scalar=np.sin(2 * V[:, 0]) * np.cos(2 * V[:, 1]),
                                         **tf)
        name, bounds = "16^3 grid", np.array([V.min(0), V.max(0)])
    lo, hi = bounds
    centre, diag = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    shape = shape({"transfer_function": str(tf_path), "tf_resolution": a.resolution,
                   "opacity_scale": 4.0 / diag})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return name, mi.load_dict({
            "type": "scene", "integrator": {"type": "tetvr"},
            "sensor": {"type": "perspective", "fov": 35,
                       "to_world": mi.ScalarTransform4f().look_at(
                           origin=(centre + diag * np.array([0.7, -0.9, 0.6])).tolist(),
                           target=centre.tolist(), up=[0, 0, 1]),
                       "sampler": {"type": "stratified", "sample_count": 1, "jitter": False},
                       "film": {"type": "hdrfilm", "width": a.res, "height": a.res}},
            "volume": shape})


def main(a):
    info = header("transfer-function gradient benchmark")
    tf_path = Path(tempfile.mkdtemp()) / "tf.json"
    tf_path.write_text(json.dumps({
        "color": [[0.0, 0.1, 0.2, 0.6], [0.3, 0.2, 0.6, 0.9], [0.5, 1.0, 0.5, 0.1],
                  [1.0, 0.9, 0.9, 0.8]],
        "opacity": [[0.0, 0.0], [0.25, 0.05], [0.35, 1.0], [0.45, 0.05], [1.0, 0.2]]}))
    name, scene = scene_of(a, tf_path)
    primal, backward = render_steps(scene, KEYS)
    _, p_med, p_runs, _ = timed(primal, a.repeat)
    print(f"{name}, {a.res}x{a.res}, {a.resolution} texels: primal render {p_med:.3f} s")
    rows, reference = [], None
    for mode in MODES:
        optical.TEXEL_REDUCE = getattr(dr.ReduceMode, mode)
        _, med, runs, grads = timed(backward, a.repeat)
        reference = grads if reference is None else reference
        err = max(float(np.abs(g - r).max() / (np.abs(r).max() + 1e-30))
                  for g, r in zip(grads, reference))
        rows.append(dict(mode=mode, median_s=med, runs_s=runs, over_primal=med / p_med,
                         gradient_difference=err))
        print(f"  reduce {mode:<7} render + backward {med:.3f} s ({med / p_med:.2f}x), "
              f"gradient vs {MODES[0]}: {err:.1e} relative")
    optical.TEXEL_REDUCE = dr.ReduceMode.Auto
    write_json(a, info, {"mesh": name, "res": a.res, "primal_s": p_med, "primal_runs_s": p_runs,
                         "modes": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main(ARGS))
