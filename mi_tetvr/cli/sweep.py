"""``mi-tetvr sweep DATA SWEEP.yaml -o DIR``: fits over a grid of settings with
Ray Tune, each trial a fit with its own budget, their held-out scores in one
table (:mod:`mi_tetvr.recon.sweep`)."""
from __future__ import annotations

from mi_tetvr.cli import flags
from mi_tetvr.extras import require

NAME = "sweep"
HELP = "fits over a grid of settings (Ray Tune), their held-out scores in one table"


def add_arguments(p):
    p.add_argument("data", help="data set folder (as fit takes it)")
    p.add_argument("sweep", help="YAML or JSON: 'base' (settings every trial shares) and "
                   "'grid' (settings, each a list of values: every combination is a trial)")
    flags.out(p, "output folder: trials/<settings>/ (each fit), sweep.csv and sweep.md")
    p.add_argument("--workers", type=int, default=1,
                   help="trials at a time (default 1), each with the cores over the workers")
    p.add_argument("--address", default=None,
                   help="a running Ray cluster (default: RAY_ADDRESS, else a local one)")
    p.add_argument("--holdout", type=int, default=8,
                   help="with a train split only: every N-th view is a test view (default 8)")
    flags.variant(p)


def run(a):
    require("cluster", "mi-tetvr sweep", "ray", "yaml")
    from mi_tetvr.cli.common import set_variant
    from mi_tetvr.recon.sweep import format_table, read_sweep, sweep
    if a.workers < 1:
        raise ValueError(f"--workers must be at least 1, got {a.workers}")
    _, grid = read_sweep(a.sweep)
    set_variant(a.variant)
    rows = sweep(a.data, a.sweep, a.out, a.workers, a.address, a.holdout, a.variant)
    print(format_table(rows, list(grid)))
    print(f"{len(rows)} trials -> {a.out}/sweep.csv, {a.out}/sweep.md")
