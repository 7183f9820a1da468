"""The install path the README gives: a wheel of the three packages that works outside the clone.

`make dist` builds the wheel; here it is built the same way, installed with pip into a folder of its
own, and imported from a working directory outside the repository with that folder first on the path,
so that nothing of the clone (repro/, bench/, the editable install) can stand in for a missing file.
"""
import os
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _run(args, **kw):
    return subprocess.run(args, capture_output=True, text=True, timeout=600, **kw)


def test_wheel_installs_and_runs_outside_the_clone(tmp_path):
    wheel_dir = tmp_path / "dist"
    r = _run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation",
              "-w", str(wheel_dir), str(ROOT)])
    assert r.returncode == 0, r.stderr
    wheels = list(wheel_dir.glob("specula_dic-*.whl"))
    assert len(wheels) == 1
    names = zipfile.ZipFile(wheels[0]).namelist()
    tops = {n.split("/")[0] for n in names}
    # the three layers and nothing of the research code or the tests
    assert {"kernels", "calibration", "dic"} <= tops
    assert not tops & {"repro", "bench", "tests"}
    entry = [n for n in names if n.endswith("entry_points.txt")]
    assert entry and "specula = dic.cli:main" in zipfile.ZipFile(wheels[0]).read(entry[0]).decode()

    site = tmp_path / "site"
    r = _run([sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(site), str(wheels[0])])
    assert r.returncode == 0, r.stderr
    env = {**os.environ, "PYTHONPATH": str(site)}
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    code = ("import dic, kernels, calibration, numpy as np;"
            "print(dic.__file__);"
            "ref, cur = dic.synth.speckle_pair((96, 96), displacement=(0.4, -0.25), seed=1);"
            "f = dic.track(ref, cur, step=16, subset=21);"
            "print(float(np.mean(f.u[f.valid])), float(np.mean(f.v[f.valid])))")
    r = _run([sys.executable, "-c", code], cwd=outside, env=env)
    assert r.returncode == 0, r.stderr
    first, second = r.stdout.strip().splitlines()[-2:]
    assert Path(first).resolve().is_relative_to(site.resolve())
    u, v = map(float, second.split())
    assert abs(u - 0.4) < 0.01 and abs(v + 0.25) < 0.01
    r = _run([sys.executable, "-m", "dic.cli", "--help"], cwd=outside, env=env)
    assert r.returncode == 0 and "track" in r.stdout, r.stderr
