"""Device selection and image validation shared by all launchers."""
import numpy as np
import pytest

from kernels._device import as_float32_image, available_devices, resolve_device


def test_default_device_is_available():
    assert resolve_device(None) in available_devices()
    assert resolve_device("cpu") == "cpu"


def test_unknown_device_is_rejected():
    with pytest.raises(ValueError, match="device must be"):
        resolve_device("tpu")


def test_cuda_without_gpu_is_a_clear_error():
    if "cuda:0" in available_devices():
        pytest.skip("a CUDA device is present")
    with pytest.raises(ValueError, match="no CUDA device"):
        resolve_device("cuda:0")


@pytest.mark.parametrize(
    "bad, message",
    [
        (np.zeros((8, 8, 3)), "colour image"),
        (np.zeros(8), "2-D array"),
        (np.zeros((0, 5)), "empty"),
        (np.array([[1.0, np.nan], [0.0, 1.0]]), "NaN"),
    ],
)
def test_bad_images_are_rejected(bad, message):
    with pytest.raises(ValueError, match=message):
        as_float32_image(bad)


def test_uint16_image_keeps_grey_levels():
    img = np.array([[0, 65535], [1000, 2]], dtype=np.uint16)
    out = as_float32_image(img)
    assert out.dtype == np.float32 and out[0, 1] == 65535.0


def test_no_cuda_driver_warning_on_a_cpu_machine():
    """Without the NVIDIA driver, Warp's start-up printed "Warp CUDA warning: Could not find or load the
    NVIDIA CUDA driver" on every command; a CPU user who did not ask for CUDA must not see it."""
    import subprocess
    import sys

    from kernels._device import _cuda_driver_present

    if _cuda_driver_present():
        pytest.skip("this machine has the NVIDIA driver: the warning never appears")
    code = ("from kernels._device import resolve_device; "
            "from dic.synth import speckle_pair; from dic._track import track; "
            "r, c = speckle_pair((48, 48), (0.3, 0.1)); print(int(track(r, c, step=8).valid.sum()))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "CUDA" not in run.stderr and int(run.stdout.strip()) > 0
