"""The fuzz pass over the calibration importers and the image reader (bench/fuzz_inputs.py), reduced.

Every mutated OpenCV/DICe/VIC-3D/JSON calibration file and PNG/TIFF/BMP image must load as a valid
object or raise ValueError: no other exception, no crash, no invalid value. Run in a subprocess:
the pass limits its address space (a header claiming a huge image must fail to allocate, not
exhaust the machine), and a crash in a native library must fail this test, not the session.
Full mode (9 500 files, by hand): ``python -m bench.fuzz_inputs``.
"""
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_fuzz_pass_reduced(tmp_path):
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, "-W", "ignore", "-m", "bench.fuzz_inputs", "--per-seed", "60", "--seed", "3",
                           "--no-save", "--keep", str(tmp_path / "failures")],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    rows = lines[lines.index(next(s for s in lines if s.startswith("seed file"))) + 1:]
    seeds = [r for r in rows if not r.startswith("total")]
    files, loaded, value_errors, _, failures = (int(v) for v in rows[len(seeds)].split()[1:6])
    assert len(seeds) >= 19 and files == len(seeds) * 60, proc.stdout
    assert failures == 0 and loaded > 0 and value_errors > 0, proc.stdout
    for r in seeds:  # every kind of file both loads and is refused
        assert int(r.split()[2]) > 0 and int(r.split()[3]) > 0, r


def test_fuzz_checks_are_strict():
    """The pass's validity checks refuse what the loaders must never return."""
    import numpy as np
    import pytest

    from bench.fuzz_inputs import _rig, check_camera, check_image, check_rig
    from calibration.camera import Camera

    check_rig(_rig())
    with pytest.raises(AssertionError, match="principal point"):
        check_camera(Camera(K=[[100.0, 0, 500.0], [0, 100.0, 5.0], [0, 0, 1]], size=(100, 100)))
    with pytest.raises(AssertionError, match="size"):
        check_camera(Camera(K=[[100.0, 0, 5.0], [0, 100.0, 5.0], [0, 0, 1]], size=(0, 0)))
    with pytest.raises(AssertionError, match="shape"):
        check_image(np.zeros((2, 2, 3), np.uint8))
