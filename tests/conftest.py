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


#: test files whose tests are all marked ``slow``: left out of ``make test-fast`` (``-m "not slow and not
#: dask"``), run by ``make test``. Chosen from measured durations (a full run with ``--durations=0`` on 2
#: cores, 2026-12-03): together about 80 % of the suite's time - compilation for sm_90, the calibration
#: CLI on rendered views, stereo DIC on the virtual lab, long sequences and exports, the walkthrough.
SLOW_FILES = frozenset({
    "test_flat_exports.py", "test_cli_calibrate.py", "test_kernel_resources.py", "test_stereo_dic.py", "test_aot.py",
    "test_sequence.py", "test_walkthrough.py", "test_stereo_sequence.py", "test_calibration_lab.py",
    "test_features.py", "test_lab_render.py", "test_experiments.py", "test_rig_uncertainty.py",
    # sequences with moved references and evolving textures (issue 26): 15-35 s each
    "test_moved_masks.py", "test_stereo_moved_masks.py", "test_verify_evolving.py", "test_stereo_cracks.py",
    # a six-state stereo sequence twice (the constant-velocity start): ~10 s
    "test_stereo_motion_prediction.py",
})


def pytest_collection_modifyitems(config, items):
    """Every test run on a CUDA device through the ``device`` fixture is marked ``cuda`` too, so that
    ``pytest -m cuda`` (bench/gpu.sh) runs all of them and only them; every test of ``SLOW_FILES`` is
    marked ``slow``."""
    for item in items:
        if item.path.name in SLOW_FILES:
            item.add_marker(pytest.mark.slow)
        callspec = getattr(item, "callspec", None)
        if callspec is not None and str(callspec.params.get("device", "")).startswith("cuda"):
            item.add_marker(pytest.mark.cuda)
