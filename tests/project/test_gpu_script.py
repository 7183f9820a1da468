"""bench/gpu.py, the GPU measurement script, in its CPU smoke mode (``--device cpu --quick``, < 30 s): every
section runs and is saved; the carried CPU reference agrees with this machine's CPU results."""
import json
import subprocess
from pathlib import Path

import pytest

from bench import gpu

ROOT = Path(__file__).resolve().parents[2]


def test_quick_cpu_run_writes_every_section(tmp_path):
    pytest.importorskip("torch")
    result = gpu.main(["--device", "cpu", "--quick", "--out", str(tmp_path)])
    saved = json.loads((tmp_path / "gpu_cpu.json").read_text())
    for name in ("environment", *gpu.SECTIONS):
        assert name in saved and "error" not in saved[name], (name, saved.get(name))
    # every IC-GN output element written (pre-filled with NaN / -1), and two runs bitwise equal
    assert saved["outputs"]["ok"]
    for order in ("order1", "order2"):
        assert saved["outputs"][order]["unwritten_params"] == 0 and saved["outputs"][order]["deterministic"]
    kern = saved["kernel"]
    assert [r["n_points"] for r in kern["fill"]["1"]] == [1000, 4000]
    assert all(r["poi_per_s"] > 0 for o in ("1", "2", "1_tiled", "1_plain", "2_plain") for r in kern["fill"][o])
    # the plain layout variant: the same fill sweep, and the same bits as the rows4 layout
    assert [r["n_points"] for r in kern["fill"]["2_plain"]] == [1000, 4000]
    assert kern["layout"]["bitwise_equal"] == {"1": True, "2": True} and kern["layout"]["default"] == "rows4"
    assert all(len(v) == 2 and all(x > 0 for x in v) for v in kern["layout"]["plain_over_rows4"].values())
    assert set(kern["step"]["2"]) == {"4", "8"}
    assert all(saved["prepare"]["summary"][k] > 0 for k in ("reference_image_s", "subsets_order1_s", "current_image_s",
                                                              "current_image_plain_s"))
    pipe = saved["pipeline"]  # the device-resident loop gives the host loop's results bitwise
    assert pipe["device_loop_bitwise_equal"] and pipe["frame_tracker_device"]["poi_per_s"] > 0
    assert pipe["graph_replay"]["skipped"].startswith("CUDA graphs")
    for method in ("zncc", "fft", "pyramid", "rg"):  # a 7.3 px move that IC-GN alone cannot reach
        assert saved["search"][method]["valid_fraction"] > 0.85
        assert saved["search"][method]["rms_error_px"] < 0.05
    ref = saved["reference"]
    assert ref["tensor_input_bitwise_equal"] and ref["ok"]
    for order in ("order1", "order2"):
        assert ref[order]["status_agreement"] >= 0.999 and ref[order]["max_abs_uv_diff_px"] <= 1e-3
    assert saved["icgn"]["orders"]["1"]["poi_per_s_tracking"] > 0
    seq = saved["sequence"]
    assert seq["tensors"]["poi_per_s"] > 0 and seq["numpy"]["mean_valid_fraction"] > 0.9
    assert saved["tests"]["skipped"] == "--quick"
    assert result["device"] == "cpu"


def test_bad_arguments_are_one_clear_message(tmp_path):
    with pytest.raises(SystemExit, match="unknown section"):
        gpu.main(["--device", "cpu", "--sections", "icgn,magic", "--out", str(tmp_path)])
    with pytest.raises(SystemExit, match="device must be"):
        gpu.main(["--device", "nonsense", "--out", str(tmp_path)])
    p = subprocess.run(["bash", str(ROOT / "bench" / "gpu.sh"), "frobnicate"], capture_output=True, text=True)
    assert p.returncode == 2 and "usage" in p.stderr
    p = subprocess.run(["bash", str(ROOT / "bench" / "gpu.sh"), "run", str(tmp_path)], capture_output=True, text=True)
    assert p.returncode == 2 and "gather the carried parts" in p.stderr


def test_device_fixture_tests_on_cuda_are_marked_cuda():
    """tests/conftest.py marks every ``device``-fixture test that runs on CUDA with ``cuda`` (bench/gpu.sh runs
    ``pytest -m cuda``), and no other."""
    import types

    import conftest

    class Item:
        def __init__(self, params):
            self.callspec = types.SimpleNamespace(params=params) if params is not None else None
            self.markers = []
            self.path = Path("test_x.py")  # not one of conftest.SLOW_FILES

        def add_marker(self, marker):
            self.markers.append(marker.name)

    items = [Item({"device": "cuda:0"}), Item({"device": "cpu"}), Item({"order": 2}), Item(None)]
    conftest.pytest_collection_modifyitems(None, items)
    assert [i.markers for i in items] == [["cuda"], [], [], []]
