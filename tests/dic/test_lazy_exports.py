"""Exports of long result files read one frame at a time (issue 13: memory flat over the file's length)."""
import tracemalloc

import numpy as np
from test_store_compression import long_result_file

from dic.export import export_results, write_vtk_series
from dic.store import read_results


def test_vtk_series_of_a_file_is_the_same_read_lazily(tmp_path):
    out = long_result_file(tmp_path / "a.h5", 5)
    lazy = export_results(out, "vtk", tmp_path / "lazy")
    eager = write_vtk_series(read_results(out), tmp_path / "eager")
    assert sorted(p.name for p in lazy) == sorted(p.name for p in eager.parent.iterdir())
    for p in lazy:
        assert p.read_bytes() == (tmp_path / "eager" / p.name).read_bytes(), p.name


def test_vtk_series_of_a_long_file_holds_one_frame_at_a_time(tmp_path):
    out = long_result_file(tmp_path / "long.h5", 40, n_side=60)
    one = read_results(out).frames[1]
    frame_bytes = sum(np.asarray(getattr(one, k)).nbytes for k in ("points", "u", "v", "params", "zncc", "iterations",
                                                                    "status", "valid"))
    frame_bytes += sum(np.asarray(v).nbytes for v in one.strain.values() if isinstance(v, np.ndarray))
    tracemalloc.start()
    write_vtk_series(out, tmp_path / "vtk")
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert len(list((tmp_path / "vtk").glob("*.vtu"))) == 40
    assert peak < 10 * frame_bytes, (peak, frame_bytes)  # a few frames' worth (meshio's copies), not 40
