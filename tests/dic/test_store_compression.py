"""The compression setting of the results store (dic.store.layout.Compression; ``compression=``,
``--compression``): parsing, what is written, resume across settings, files of earlier versions."""
import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from test_store import SETTINGS, STEREO_KW, fake_field, fake_field3d, fake_match, fake_rig

from dic._strain import strain
from dic.store import ResultReader, ResultWriter, read_results
from dic.store.layout import DEFAULT_COMPRESSION, LEGACY_COMPRESSION, Compression, parse_compression

KW = dict(reference_path="r.tif", reference_shape=(10, 10), reference_sha256="abc", settings=SETTINGS)


def big_field(seed, n_side=40):
    """A field large enough to be compressed (1600 POIs): a grid, smooth u, v, noisy zncc."""
    f = fake_field(seed, n_side=n_side)
    x, y = f.points.T
    f.u = 0.3 + 1e-3 * x  # smooth: compresses
    f.v = -0.2 + 5e-4 * y
    return f


def long_result_file(path, n_frames, n_side=40):
    """A 2-D result file of ``n_frames`` frames of ``big_field`` points (u drifting by 0.01 px per frame, strain
    window 3): what the lazy-reading and export-memory tests read back."""
    with ResultWriter(path, **KW) as w:
        for k in range(1, n_frames + 1):
            f = big_field(k, n_side=n_side)
            f.u = f.u + 0.01 * k
            w.write_frame(k, f, strain=strain(f, window=3))
    return path


def _filters(path, index=1):
    """{dataset: its HDF5 filter (None: stored as it is)} of frame ``index``."""
    out = {}
    with h5py.File(path, "r") as h:
        g = h["frames"][f"{index:06d}"]
        g.visititems(lambda name, obj: out.__setitem__(name, obj.compression) if isinstance(obj, h5py.Dataset) else None)
        return out, h.attrs.get("compression")


def test_parse_compression():
    assert parse_compression(None) == DEFAULT_COMPRESSION
    assert parse_compression("none") == Compression(None) and parse_compression("NONE").text == "none"
    assert parse_compression("lzf") == Compression("lzf")
    assert parse_compression("gzip") == Compression("gzip", 4) == LEGACY_COMPRESSION
    assert parse_compression("gzip:1").text == "gzip:1" and parse_compression("gzip:9").level == 9
    assert parse_compression("") == Compression(None)  # an empty option value
    for bad in ("gzip:10", "gzip:-1", "gzip:x", "zstd", "lz4", 4):
        with pytest.raises(ValueError, match="compression"):
            parse_compression(bad)


@pytest.mark.parametrize("setting, expected", [("none", None), ("lzf", "lzf"), ("gzip:1", "gzip"), (None, None)])
def test_setting_is_recorded_and_applied_where_it_pays(tmp_path, setting, expected):
    out = tmp_path / "a.h5"
    f = big_field(1)
    s = strain(f, window=3)
    with ResultWriter(out, compression=setting, **KW) as w:
        assert w.compression == parse_compression(setting)
        w.write_frame(1, f, strain=s)
    filters, attr = _filters(out)
    assert attr == parse_compression(setting).text
    # the grid, the smooth displacements, the statuses and flags compress; uniform random noise does not
    for name in ("points", "u", "v", "status", "valid", "strain/valid"):
        assert filters[name] == expected, name
    assert filters["params"] is None and filters["zncc"] is None  # random values: stored as they are
    back = read_results(out).frames[1]  # readers need nothing: the filters are in the file
    for key in ("points", "u", "v", "params", "zncc", "iterations", "valid"):
        assert np.array_equal(getattr(back, key), getattr(f, key))
    assert np.array_equal(back.strain["exx"], s.exx, equal_nan=True)
    with ResultReader(out) as r:
        assert r.compression == parse_compression(setting)


def test_resume_keeps_the_files_own_setting(tmp_path):
    out = tmp_path / "a.h5"
    with ResultWriter(out, compression="gzip:4", **KW) as w:
        w.write_frame(1, big_field(1))
    with ResultWriter(out, compression="none", **KW) as w:  # appended frames keep the file's setting
        assert w.compression == Compression("gzip", 4)
        w.write_frame(2, big_field(2))
    filters, attr = _filters(out, 2)
    assert attr == "gzip:4" and filters["points"] == "gzip" and filters["u"] == "gzip"
    with ResultWriter(out, compression="lzf", mode="overwrite", **KW) as w:  # a new run takes the new one
        assert w.compression == Compression("lzf")
        w.write_frame(1, big_field(1))
    assert _filters(out)[0]["points"] == "lzf"


def test_files_without_the_attribute_are_gzip4(tmp_path):
    """Files written before the setting existed (no ``compression`` attribute) resume as gzip level 4."""
    out = tmp_path / "old.h5"
    with ResultWriter(out, compression="gzip:4", **KW) as w:
        w.write_frame(1, big_field(1))
    with h5py.File(out, "a") as h:
        del h.attrs["compression"]
    with ResultReader(out) as r:
        assert r.compression == LEGACY_COMPRESSION
    with ResultWriter(out, **KW) as w:
        assert w.compression == LEGACY_COMPRESSION
        w.write_frame(2, big_field(2))
    filters, attr = _filters(out, 2)
    assert attr is None and filters["points"] == "gzip"
    assert sorted(read_results(out).frames) == [1, 2]


def test_stereo_files_take_the_setting(tmp_path):
    out = tmp_path / "s.h5"
    with ResultWriter(out, rig=fake_rig(), compression="none", **STEREO_KW) as w:
        w.write_match(fake_match(300))
        w.write_frame(0, fake_field3d(0, 0, ny=20, nx=20))
    with h5py.File(out, "r") as h:
        assert h.attrs["compression"] == "none"
        assert all(h["frames/000000"][k].compression is None for k in h["frames/000000"])
    with ResultWriter(out, rig=fake_rig(), compression="gzip:1", mode="overwrite", **STEREO_KW) as w:
        w.write_match(fake_match(300))
        w.write_frame(0, fake_field3d(0, 0, ny=20, nx=20))
    with h5py.File(out, "r") as h:
        assert h.attrs["compression"] == "gzip:1" and h["frames/000000/points"].compression == "gzip"
        assert h["reference/match/status"].compression == "gzip"


def test_bad_setting_is_refused_before_the_file_is_made(tmp_path):
    with pytest.raises(ValueError, match="gzip level must be an integer from 0 to 9"):
        ResultWriter(tmp_path / "a.h5", compression="gzip:12", **KW)
    assert not (tmp_path / "a.h5").exists()


def test_sequence_and_cli_option(tmp_path):
    from dic.cli import main
    from dic.io import write_image
    from dic.sequence import track_sequence
    from dic.synth import speckle_pair

    ref, cur = speckle_pair((64, 72), (0.4, -0.3), seed=2)
    track_sequence(ref, [cur], tmp_path / "a.h5", step=6, compression="gzip:2", strain_window=3)
    filters, attr = _filters(tmp_path / "a.h5")
    assert attr == "gzip:2" and filters["points"] == "gzip"
    with pytest.raises(ValueError, match="compression must be"):
        track_sequence(ref, [cur], tmp_path / "b.h5", step=6, compression="zip")
    paths = [str(write_image(tmp_path / f"f{k}.tif", img, bits=8)) for k, img in enumerate([ref, cur])]
    base = ["track", *paths, "--step", "6", "--strain-window", "3", "--device", "cpu", "-q"]
    r = CliRunner().invoke(main, [*base, "-o", str(tmp_path / "c.h5"), "--compression", "none"])
    assert r.exit_code == 0, r.output
    assert _filters(tmp_path / "c.h5") == ({k: None for k in _filters(tmp_path / "c.h5")[0]}, "none")
    r = CliRunner().invoke(main, [*base, "-o", str(tmp_path / "d.h5"), "--compression", "gzip:11"])
    assert r.exit_code == 2 and "--compression" in r.output and "0 to 9" in r.output


def test_iter_frames_holds_one_frame_at_a_time(tmp_path):
    """ResultReader.iter_frames reads each frame when it is reached: memory stays flat over the file's
    length (read_results, by contrast, holds every frame)."""
    import tracemalloc

    out = tmp_path / "long.h5"
    f = big_field(1, n_side=60)  # 3600 POIs
    one = sum(np.asarray(getattr(f, k)).nbytes for k in ("points", "u", "v", "params", "zncc", "iterations", "valid"))
    with ResultWriter(out, **KW) as w:
        for k in range(1, 41):
            w.write_frame(k, f)
    with ResultReader(out) as r:
        tracemalloc.start()
        seen = [(i, float(fr.u[0])) for i, fr in r.iter_frames()]
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert [i for i, _ in seen] == list(range(1, 41)) and all(u == f.u[0] for _, u in seen)
        assert [i for i, _ in r.iter_frames([3, 1])] == [3, 1]
        with pytest.raises(ValueError, match="no finished frame 99"):
            list(r.iter_frames([99]))
    assert peak < 4 * one  # about one frame (plus the reads' buffers), not 40
    tracemalloc.start()
    held = read_results(out)
    _, peak_all = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert len(held.frames) == 40 and peak_all > 30 * one  # the whole-file reader, for comparison
