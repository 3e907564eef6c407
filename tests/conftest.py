"""Fixtures of the test suite and its Mitsuba variant.

The variant comes from the environment variable ``MI_TETVR_VARIANT``
(default ``llvm_ad_rgb``); on a machine with a GPU the whole suite runs on
CUDA with ``MI_TETVR_VARIANT=cuda_ad_rgb python3 -m pytest tests``. It is set
before any test module is imported, and an unusable variant stops the run with
a clear message. Shared helpers live in :mod:`tests.helpers`.
"""
import pytest

from tests.helpers import DATA, VARIANT, use_variant


def pytest_configure(config):
    try:
        use_variant(VARIANT)
    except RuntimeError as e:
        raise pytest.UsageError(str(e)) from None


def pytest_report_header(config):
    return f"mi_tetvr: Mitsuba variant {VARIANT} (MI_TETVR_VARIANT)"


@pytest.fixture
def data_dir():
    if not DATA.is_dir():
        pytest.skip("../shared/data is absent")
    return DATA
