"""bench/sequence.py (issue 13's sequence benchmarks) in its quick mode, and its engine adapter.

Full mode, by hand: ``python -m bench.sequence`` (docs in bench/README.md).
"""
import json
import os
import subprocess
import sys

import numpy as np


def test_quick_mode_runs_and_writes_every_figure(tmp_path):
    out = tmp_path / "sequence.json"
    proc = subprocess.run([sys.executable, "-W", "ignore", "-m", "bench.sequence", "--quick", "--out", str(out),
                           "--modes", "fixed,incremental,every:3,auto"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    res = json.loads(out.read_text())
    assert res["quick"] and res["parameters"]["image_size"] == [128, 128]
    t = res["throughput"]
    assert t["frames"] == t["frames_stored"] == 6 and t["n_points"] > 100
    assert t["sequence_pois_per_s"] > 0 and t["track_only_pois_per_s"] > 0
    assert np.isclose(t["ratio"], t["sequence_pois_per_s"] / t["track_only_pois_per_s"])
    assert t["valid_fraction_min"] > 0.85  # the border row of POIs leaves the image with the shift
    m = res["memory"]
    assert [r["frames"] for r in m["runs"]] == [6, 12]
    assert all(r["peak_rss_mb"] > 10 for r in m["runs"])
    assert np.isclose(m["peak_ratio"], m["runs"][1]["peak_rss_mb"] / m["runs"][0]["peak_rss_mb"])
    ev = res["evolving"]
    assert ev["frames"] == 8 and ev["speckles_replaced_per_frame"] >= 1
    assert set(ev["modes"]) == {"fixed", "incremental", "every:3", "auto"}
    fixed = ev["modes"]["fixed"]
    assert [f["frame"] for f in fixed["per_frame"]] == list(range(1, 8))
    # the fixed reference over 30 % stretch on a small image: everything valid, errors of a few 0.01 px
    assert fixed["final_valid_fraction"] > 0.95 and fixed["final_rms_error_px"] < 0.2
    assert all("invalid_by_status" in f and "reference_interpolated" in f for f in fixed["per_frame"])
    # the error binned by the speckles changed in each subset since frame 0 (exact, from the disk pool)
    by = fixed["error_by_changed_speckles"]
    assert set(by) == {"1", "7"}
    for k, bins in by.items():
        assert sum(b["n_points"] for b in bins.values()) == fixed["n_points"], k
    assert by["1"]["0"]["n_valid"] > 0 and by["1"]["0"]["rms_error_px"] < 0.02  # an unchanged subset: noise only
    for mode, r in ev["modes"].items():  # each mode ran, or says why not
        assert "per_frame" in r or r.get("skipped") or r.get("failed"), mode
    if res["engine"] == "fallback":
        assert "skipped" in ev["modes"]["auto"]


def test_engine_adapter_passes_the_reference_mode(monkeypatch):
    import dic.sequence
    from bench import sequence as bench_sequence

    calls = []

    def track_sequence(reference_image, frames, out, *, reference="fixed", mode="resume", progress=False, **opts):
        calls.append((reference_image, list(frames), out, reference, mode, progress, opts))

    monkeypatch.setattr(dic.sequence, "track_sequence", track_sequence, raising=False)
    name, run = bench_sequence.engine()
    assert name == "dic.sequence.track_sequence"
    run("ref.png", ["a.png"], "out.h5", "every:5", subset=21)
    assert calls == [("ref.png", ["a.png"], "out.h5", "every:5", "overwrite", False, {"subset": 21})]
    assert bench_sequence.engine(force_fallback=True)[0] == "fallback"
    assert bench_sequence.supports("fallback", "fixed") and not bench_sequence.supports("fallback", "auto")


def test_evolving_frames_are_reused_from_a_kept_folder(tmp_path):
    from bench.sequence import evolving_frames

    _, paths = evolving_frames(tmp_path, 48, 3, 0.3, 0.01, 1.0, "cpu")
    stamps = [os.stat(p).st_mtime_ns for p in paths]
    os.utime(paths[1], ns=(1, 1))  # a marker: a rendered-again frame would get a new time
    seq, again = evolving_frames(tmp_path, 48, 3, 0.3, 0.01, 1.0, "cpu")
    assert again == paths and os.stat(paths[1]).st_mtime_ns == 1 and len(seq) == 3
    _, other = evolving_frames(tmp_path, 48, 3, 0.3, 0.02, 1.0, "cpu")  # another fade: rendered again
    assert other == paths and os.stat(paths[1]).st_mtime_ns != 1 and os.stat(paths[0]).st_mtime_ns >= stamps[0]
