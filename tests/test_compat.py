"""The Mitsuba releases mi_tetvr runs on: the range is the package's requirement
(its metadata), and importing mi_tetvr beside a Mitsuba outside it fails with one
line naming both (tried with a stub ``mitsuba`` module of another release)."""
import os
import subprocess
import sys

import pytest

import mi_tetvr
from mi_tetvr.compat import check_mitsuba, supported_mitsuba
from tests.helpers import ROOT


def test_the_range_is_the_requirement():
    import tomllib
    wanted = [r for r in tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
              ["dependencies"] if r.startswith("mitsuba")]
    supported = supported_mitsuba()
    if supported is None:
        pytest.skip("mi_tetvr runs from a source tree that is not installed")
    assert wanted == [f"mitsuba{supported}"]
    check_mitsuba()                                   # the Mitsuba the suite runs on
    for inside in ("3.9.1", "3.9.7"):
        check_mitsuba(inside, "~=3.9.1")
    for outside in ("3.5.0", "3.9.0", "3.10.0", "4.0.0", "unknown"):
        with pytest.raises(ImportError, match=rf"runs on Mitsuba ~=3\.9\.1, and the "
                                              rf"installed Mitsuba is {outside}"):
            check_mitsuba(outside, "~=3.9.1")


def test_import_beside_another_release_is_one_line(tmp_path):
    supported = supported_mitsuba()
    if supported is None:
        pytest.skip("mi_tetvr runs from a source tree that is not installed")
    stub = tmp_path / "mitsuba"
    stub.mkdir()
    (stub / "__init__.py").write_text('__version__ = "3.5.0"\n')
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    r = subprocess.run([sys.executable, "-c", "import mi_tetvr"], capture_output=True,
                       text=True, env=env, cwd=tmp_path)
    assert r.returncode != 0
    assert r.stderr.strip().splitlines()[-1] == (
        f"ImportError: mi_tetvr {mi_tetvr.__version__} runs on Mitsuba {supported}, and the "
        f"installed Mitsuba is 3.5.0: pip install \"mitsuba{supported}\"")
