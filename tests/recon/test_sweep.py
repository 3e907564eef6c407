"""``mi-tetvr sweep``: a grid of fit settings run as Ray Tune trials, each a
whole fit; its table is each trial's own held-out scores (read back from the
trial's ``metrics.json``) with the settings it was fitted with."""
from __future__ import annotations

import csv
import json

import pytest

from mi_tetvr.recon.config import FitConfig

pytest.importorskip("ray")


def test_sweep_table_is_each_trials_fit(tiny_data_path, tmp_path):
    from mi_tetvr.cli import main
    spec = tmp_path / "sweep.yaml"
    spec.write_text("base:\n  grid_resolution: 4\n  iterations: 12\n  views_per_step: 2\n"
                    "  n_sub: 2\n  jitter: false\n  checkpoint_every: 4\n  log_every: 4\n"
                    "grid:\n  lr_color: [0.02, 0.08]\n  lr_opacity: [0.3]\n")
    out = tmp_path / "sweep"
    main(["sweep", str(tiny_data_path), str(spec), "-o", str(out), "--workers", "2"])
    rows = list(csv.DictReader(open(out / "sweep.csv")))
    assert sorted(float(r["lr_color"]) for r in rows) == [0.02, 0.08]
    assert float(rows[0]["psnr"]) >= float(rows[1]["psnr"])            # best first
    for r in rows:
        cfg = FitConfig.from_file(tmp_path / "sweep" / "trials" / r["dir"].split("/trials/")[1]
                                  / "config.json")
        metrics = json.loads((out / "trials" / r["dir"].split("/trials/")[1]
                              / "metrics.json").read_text())
        assert cfg.trainer.lr_color == float(r["lr_color"]) and cfg.trainer.iterations == 12
        assert metrics["mean"]["psnr"] == pytest.approx(float(r["psnr"]), abs=1e-9)
        assert int(r["steps"]) == metrics["step"] == 12
    assert "held-out PSNR" in (out / "sweep.md").read_text()


def test_bad_sweeps_are_refused_before_any_trial(tmp_path):
    from mi_tetvr.recon.sweep import read_sweep
    bad = tmp_path / "bad.yaml"
    for text, match in (("grid: {}\n", "a 'grid' of settings"),
                        ("grid:\n  lr_colour: [1]\n", "unknown fit settings"),
                        ("grid:\n  lr_color: []\n", "has no values"),
                        ("grid:\n  lr_color: [1]\nbases: {}\n", "unknown keys")):
        bad.write_text(text)
        with pytest.raises(ValueError, match=match):
            read_sweep(bad)
