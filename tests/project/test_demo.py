"""Smoke test of ``python -m repro.demo`` (what ``make demo`` runs) on a reduced image size."""
import json

import numpy as np

from dic.store import read_results
from repro import demo


def test_demo_runs_end_to_end(tmp_path):
    out = tmp_path / "demo"
    assert demo.main(["--out", str(out), "--size", "160", "--step", "6", "--only", "2d"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    for name in summary["files"]:
        assert (out / name).stat().st_size > 0, name
    e = summary["errors"]
    assert e["valid_points"] > 0.9 * e["points"]
    # 8-bit, 1 grey level of noise, 21 px subsets: the noise floor is about
    # sqrt(2) * 1 / (21 * 30 grey/px) = 0.002 px (1st order; 2nd order ~1.5x more); 0.015 px RMS
    # leaves room for the sinusoidal field's curvature and still catches any convention error
    # (a sign or half-pixel slip would give >= 0.5 px)
    assert e["u_rms_error_px"] < 0.015 and e["v_rms_error_px"] < 0.015
    # strain: the largest true strain is 3.8e-2; a 7-point plane fit over 36 px of a 192 px
    # sinusoid plus noise differentiation stays well below 5e-3
    assert max(e["exx_rms_error"], e["eyy_rms_error"], e["exy_rms_error"]) < 5e-3
    res = read_results(out / "results.h5")
    frame = res.frames[1]
    assert frame.strain is not None and np.isfinite(frame.u[frame.valid]).all()
    assert "RMS error" in (out / "summary.md").read_text()
