"""The reconstruction suite (benchmarks/fit_suite.py), shrunk: the project's own
volume, 6 views of 24x24, an 18-second budget (--budget 0.3)."""
import importlib.util
import json

import numpy as np
import pytest

from tests.helpers import ROOT, VARIANT


def test_fit_suite_quick(tmp_path):
    spec = importlib.util.spec_from_file_location("fit_suite", ROOT / "benchmarks" / "fit_suite.py")
    suite = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(suite)
    res = suite.main(["--quick", "--out", str(tmp_path), "--variant", VARIANT,
                      "--json", str(tmp_path / "suite.json")])["default"]
    assert (tmp_path / "suite.json").is_file() and (tmp_path / "default_fit" / "mesh.vtu").is_file()
    assert np.isfinite(res["psnr"]) and 0 < res["ssim"] <= 1 and res["steps"] >= 5
    # (the budget's use is tested in tests/recon/test_fit.py, without the
    # calibration that takes much of a 6-second budget)
    assert 0 < res["optimization_seconds"] <= res["budget_seconds"]
    # the no-fitting grid has about the fit's vertex count
    nofit = res["no_fitting"]
    assert abs(nofit["vertices"] - res["vertices"]) < 0.25 * res["vertices"]
    assert np.isfinite(nofit["psnr"])
    # the suite scores the mesh file the fit wrote: as the fit scored itself (its
    # metrics.json, from the trainer's own arrays), so the file holds what was fitted
    fit = tmp_path / "default_fit"
    own = json.loads((fit / "metrics.json").read_text())["mean"]
    assert res["psnr"] == pytest.approx(own["psnr"], abs=0.01)
    assert res["ssim"] == pytest.approx(own["ssim"], abs=1e-3)
    # and the fit learned: its training loss fell, the last tenth of the steps against
    # the first 20 steps (a fixed window: the steps the budget allows depend on the
    # machine, and the loss levels off after about 100 of them; a first tenth of 670 steps
    # had mostly levelled off too). Measured 0.0060 against 0.0225 at 505 to 680 steps.
    loss = np.array(json.loads(str(np.load(fit / "checkpoint.npz")["history"]))["loss"])
    assert len(loss) >= 40, len(loss)
    k = len(loss) // 10
    assert loss[-k:].mean() < 0.5 * loss[:20].mean(), (loss[:20].mean(), loss[-k:].mean())
