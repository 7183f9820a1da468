"""Shared fixtures: every kernel test runs on every available Warp device."""
import numpy as np
import pytest

from kernels import available_devices


def pytest_generate_tests(metafunc):
    if "device" in metafunc.fixturenames:
        metafunc.parametrize("device", available_devices())


@pytest.fixture
def rng():
    """A seeded generator so that every test is reproducible."""
    return np.random.default_rng(12345)


def pytest_collection_modifyitems(config, items):
    """Every test run on a CUDA device through the ``device`` fixture is marked ``cuda`` too, so that
    ``pytest -m cuda`` (bench/gpu.sh) runs all of them and only them."""
    for item in items:
        callspec = getattr(item, "callspec", None)
        if callspec is not None and str(callspec.params.get("device", "")).startswith("cuda"):
            item.add_marker(pytest.mark.cuda)
