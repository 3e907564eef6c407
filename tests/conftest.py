"""Fixtures of the test suite and its Mitsuba variant.

The variant comes from the environment variable ``MI_TETVR_VARIANT``
(default ``llvm_ad_rgb``); on a machine with a GPU the whole suite runs on
CUDA with ``MI_TETVR_VARIANT=cuda_ad_rgb python3 -m pytest tests``. It is set
before any test module is imported, and an unusable variant stops the run with
a clear message. Shared helpers live in :mod:`tests.helpers`.
"""
import gc
import json
import os

import pytest

from tests.helpers import SCENES, VARIANT, shared_data, use_variant


def pytest_configure(config):
    try:
        use_variant(VARIANT)
    except RuntimeError as e:
        raise pytest.UsageError(str(e)) from None
    # the bundled scenes, written where the tests, the tutorials and the README read them
    from mi_tetvr.mesh.scenes import make_scenes
    make_scenes(SCENES)


#: A file to append, per test, the kernels Dr.Jit compiled for it (not found in its memory or
#: disk cache) and their compile time: where a cold run's time goes.
KERNEL_STATS = os.environ.get("MI_TETVR_KERNEL_STATS")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    if not KERNEL_STATS:
        yield
        return
    import drjit as dr
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history()                           # (what came before is not this test's)
    yield
    compiled = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT
                and not k["cache_hit"] and not k["cache_disk"]]
    with open(KERNEL_STATS, "a") as f:
        f.write(json.dumps({"test": item.nodeid, "compiled": len(compiled),
                            "seconds": sum(k["backend_time"] + k["codegen_time"]
                                           for k in compiled) / 1000}) + "\n")


#: The test files that take longest (a cold run's durations, the slowest first). They run
#: first: pytest-xdist hands each worker whole files (``--dist loadfile``), and one of these
#: started last would keep its worker busy long after the other had finished.
FIRST = ("recon/test_sweep.py", "recon/test_sfm.py", "recon/test_tomography_solvers.py",
         "render/test_distributed.py", "recon/test_tomography.py", "test_tutorial.py",
         "recon/test_fit.py", "render/test_overlay.py", "recon/test_unbounded.py",
         "test_docs.py", "recon/test_scattering_fit.py", "render/test_overlap.py",
         "render/test_transport.py", "test_wheel.py", "recon/test_capture.py")


def pytest_collection_modifyitems(session, config, items):
    from tests.helpers import ROOT
    gone = [p for p in FIRST if not (ROOT / "tests" / p).is_file()]
    if gone:
        raise pytest.UsageError(f"tests/conftest.py: FIRST names files that are gone: {gone}")

    def rank(item):
        path = item.nodeid.split("::")[0].removeprefix("tests/")
        return FIRST.index(path) if path in FIRST else len(FIRST)
    items.sort(key=rank)            # (stable: each file's tests, and the others, in order)


def pytest_report_header(config):
    from importlib import metadata
    frameworks = []
    for name in ("torch", "jax"):
        try:
            frameworks.append(f"{name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            frameworks.append(f"{name} not installed (its tests skip)")
    return [f"mi_tetvr: Mitsuba variant {VARIANT} (MI_TETVR_VARIANT)",
            f"mi_tetvr.interop: {', '.join(frameworks)}"]


@pytest.fixture
def data_dir():
    return shared_data()


@pytest.fixture(scope="module", autouse=True)
def collect_after_module():
    """Collect reference cycles after each test module. An error a test
    provokes on purpose keeps, through its traceback, the renderer's frames
    and their Dr.Jit arrays alive until Python's cycle collector runs; a later
    forward-mode pass through a nested Mitsuba integrator (``prb``, whose
    loop isolates its AD traversals) then fails on those arrays' AD edges
    (``ad_traverse(): ... outside of the current dr.isolate_grad() scope``)."""
    yield
    gc.collect()


@pytest.fixture(scope="module")
def tiny_data_path(tmp_path_factory):
    """A tiny data set rendered by the grid ray marcher: 6 training and 2 test
    views of 16x16 pixels of the default volume (its folder)."""
    from mi_tetvr.grid import make_volume
    from mi_tetvr.mesh.scenes import default_volume
    from mi_tetvr.recon.synthetic import make_dataset
    from mi_tetvr.transfer import read_transfer_function
    from tests.helpers import ROOT
    out = tmp_path_factory.mktemp("data")
    tf = read_transfer_function(ROOT / "scenes" / "tf_default.json")
    make_dataset(make_volume(default_volume(16)), tf, views=6, res=16, out_dir=out,
                 test_views=2, fov=30, progress=False)
    return out
