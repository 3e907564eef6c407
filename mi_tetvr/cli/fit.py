"""``mi-tetvr fit DATA -o DIR``: reconstruct a tet-mesh volume from a data set. Its
settings are :class:`~mi_tetvr.recon.config.FitConfig`'s fields, one option each
(:func:`~mi_tetvr.cli.flags.config_flags`), over a ``--config`` file; ``--viewer``
shows the fit in the browser while it runs."""
from __future__ import annotations

import json
from pathlib import Path

from mi_tetvr.cli import flags
from mi_tetvr.cli.common import CommandError, forwarding, load_data, set_variant
from mi_tetvr.extras import require

NAME = "fit"
HELP = "reconstruct a tet-mesh volume from a multi-view data set"


def add_arguments(p):
    p.add_argument("data", help="NeRF-style folder (transforms*.json) or COLMAP model folder")
    flags.out(p, "output folder (also the checkpoint a later run resumes)")
    p.add_argument("--config", help="fit settings as JSON or YAML, by part as --print-config "
                   "prints them (or one flat mapping: the settings below, with underscores); "
                   "options given here override it")
    p.add_argument("--print-config", action="store_true",
                   help="print the settings this command would fit with, those of its kind of "
                   "fit by part (JSON: a --config file), and exit")
    p.add_argument("--holdout", type=int, default=8,
                   help="with a train split only: every N-th view is a test view (default 8)")
    p.add_argument("--restart", action="store_true", help="ignore an existing checkpoint")
    p.add_argument("--viewer", action="store_true", help="show the fit in the browser while it "
                   "runs: the mesh from the browser's camera between steps (in at most 10%% of "
                   "the time), the loss curve and the stage")
    flags.serve(p)
    p.add_argument("--view-res", type=int, default=384, metavar="N",
                   help="--viewer: the refined image's longer side (default 384)")
    p.add_argument("--workers", type=int, default=None,
                   help="fit a partitioned mesh (--init MESH.pvtu written by `partition`) on "
                   "Ray workers, each holding its blocks: Adam on the colors and opacities "
                   "(no stages, no refinement)")
    p.add_argument("--address", default=None, help="a running Ray cluster for --workers "
                   "(default: RAY_ADDRESS, else a local one)")
    flags.quiet(p)
    flags.variant(p)
    p.set_defaults(config_dests=flags.config_flags(p))


def fit_config(a):
    """The FitConfig of a ``fit`` command line: the --config file's (or the defaults), with
    the options given on the command line over it."""
    from mi_tetvr.recon.config import FitConfig
    cfg = FitConfig.from_file(a.config) if a.config else FitConfig()
    return cfg.updated(**{name: getattr(a, dest) for dest, name in a.config_dests.items()
                          if getattr(a, dest) is not None})


def run(a):
    cfg = fit_config(a)
    if a.print_config:
        print(json.dumps(cfg.nested(), indent=2))
        return
    require("recon", "mi-tetvr fit", "scipy", "skimage", "PIL", "matplotlib")
    if a.viewer:
        require("viewer", "fit --viewer", "viser")
    if a.workers is not None or a.address is not None:
        require("cluster", "fit --workers", "ray")
    from mi_tetvr.recon.config import INITS
    if a.viewer and cfg.linear_solver:
        raise ValueError(f"--viewer shows the steps of an Adam fit; --model absorption "
                         f"solves with {cfg.linear_solver} (add --solver adam to watch it)")
    if cfg.mesh.init not in INITS and not Path(cfg.mesh.init).is_file():
        raise FileNotFoundError(f"--init {cfg.mesh.init}: no such mesh file (or one of "
                                f"{', '.join(INITS)})")
    if cfg.field.model == "scattering" and (a.workers is not None or a.address is not None):
        raise ValueError("--workers fits colors and opacities over blocks; --model scattering "
                         "runs in one process")
    if cfg.data.lights is not None and not Path(cfg.data.lights).is_file():
        raise FileNotFoundError(f"--lights {cfg.data.lights}: no such Mitsuba scene file")
    set_variant(a.variant)
    if cfg.data.lights is not None:
        # (read before the data and the mesh: a wrong file is one line, at once)
        from mi_tetvr.render.surfaces import lights_scene
        lights_scene(cfg.data.lights)
    if a.workers is not None or a.address is not None:
        return run_blocks(a, cfg)
    from mi_tetvr.recon.outputs import fitted_file
    from mi_tetvr.recon.pipeline import run as run_fit
    data = load_data(a.data, cfg.data.downscale, a.holdout)
    print(f"{a.data}: {len(data.train)} training and {len(data.test)} test views "
          f"({data.train[0].camera.width}x{data.train[0].camera.height})")
    Path(a.out).mkdir(parents=True, exist_ok=True)
    # what `view FIT_DIR` finds the data set by
    (Path(a.out) / "data.json").write_text(json.dumps(
        {"data": str(Path(a.data).resolve()), "holdout": a.holdout}, indent=2))

    def open_viewer(trainer):
        from mi_tetvr.apps.viewer import FitViewer
        v = FitViewer(trainer, port=a.port, host=a.host, resolution=a.view_res,
                      save_dir=Path(a.out) / "views")
        print(f"viewer: {v.url}" + forwarding(a.host, v.port))
        return v
    try:
        metrics = run_fit(data, a.out, cfg, resume=not a.restart, progress=not a.quiet,
                          viewer=open_viewer if a.viewer else None)
    except KeyboardInterrupt:
        raise CommandError("interrupted; progress saved (run the same command to resume)") \
            from None
    m = metrics["mean"]
    from mi_tetvr.recon.fields import field_type
    what = field_type(cfg.field).scored
    print(f"test PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f} ({what}) over "
          f"{len(metrics['views'])} view(s) [{metrics['split']}]; {metrics['tets']:,} tets, "
          f"{metrics['step']:,} steps, {metrics['wall_seconds']:.0f} s -> "
          f"{Path(a.out) / fitted_file(cfg)}")


def run_blocks(a, cfg):
    """``fit --workers N --init MESH.pvtu``: the partitioned mesh's colors and
    opacities fitted on Ray workers (:func:`mi_tetvr.distributed.fit_blocks`)."""
    from mi_tetvr.distributed import PartitionedMesh, fit_blocks
    from mi_tetvr.mesh.partition import blocks_path
    init = Path(cfg.mesh.init)
    if init.suffix.lower() != ".pvtu" or not blocks_path(init).is_file():
        raise ValueError("fit --workers fits a partitioned mesh: --init MESH.pvtu (written "
                         "by `mi-tetvr partition MESH -o MESH.pvtu --blocks N`)")
    if cfg.strategy.stages or cfg.trainer.lr_position or cfg.field.model != "emission" or a.viewer:
        raise ValueError("fit --workers fits colors and opacities in one stage: no --stages, "
                         "--lr-position, --model absorption or --viewer")
    data = load_data(a.data, cfg.data.downscale, a.holdout)
    print(f"{a.data}: {len(data.train)} training and {len(data.test)} test views "
          f"({data.train[0].camera.width}x{data.train[0].camera.height})")
    with PartitionedMesh(init, a.workers, address=a.address) as pm:
        m = fit_blocks(pm, data, a.out, cfg, progress=not a.quiet)
    print(f"test PSNR {m['mean']['psnr']:.2f} dB, SSIM {m['mean']['ssim']:.4f} (sRGB) over "
          f"{len(m['views'])} view(s) [{m['split']}]; {m['tets']:,} tets in {m['blocks']} "
          f"blocks on {m['workers']} workers, {m['step']:,} steps, {m['seconds']:.0f} s -> "
          f"{Path(a.out) / 'mesh.pvtu'}")
