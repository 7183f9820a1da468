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
