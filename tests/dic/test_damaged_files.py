"""Issue 24, defects 7 and 15: checksums in result files, and damaged or foreign result files refused with
one line at every reader (the library's readers, resume, strain, export; the CLI), with a repair path."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from click.testing import CliRunner
from test_store import SETTINGS, STEREO_KW, fake_field, fake_field3d, fake_match, fake_rig
from test_store_robust import ENV

from dic.cli import main
from dic.store import ResultFrames, ResultReader, ResultWriter, read_results, read_stereo, repair_results
from dic.store.layout import Compression

KW2 = dict(reference_path="r.tif", reference_shape=(200, 200), reference_sha256="abc", settings=SETTINGS)
N_SIDE = 30  # 900 points: a frame's params (21.6 KB) span several 4 KB blocks


def _build(path: Path, kind: str, compression=None) -> Path:
    """A whole result file of frames 1, 2, 3 (default: uncompressed, with checksums)."""
    if kind == "stereo":
        with ResultWriter(path, rig=fake_rig(), compression=compression, **STEREO_KW) as w:
            w.write_match(fake_match(35))
            for k in (1, 2, 3):
                w.write_frame(k, fake_field3d(k, k), path=(f"l{k}.tif", f"r{k}.tif"))
    else:
        with ResultWriter(path, compression=compression, **KW2) as w:
            for k in (1, 2, 3):
                w.write_frame(k, fake_field(k, n_side=N_SIDE), path=f"c{k}.tif")
    return path


def _data_offset(path: Path, dataset: str) -> tuple[int, int]:
    """(byte offset, size) in the file of the first chunk of ``dataset``'s data."""
    with h5py.File(path, "r") as h5:
        info = h5[dataset].id.get_chunk_info(0)
        return int(info.byte_offset), int(info.size)


def _patch_bytes(path: Path, offset: int, data: bytes) -> None:
    with open(path, "r+b") as fh:
        fh.seek(offset)
        fh.write(data)


def flip_bit(path: Path, kind: str) -> None:
    name = "u" if kind == "dic2d" else "U"
    offset, size = _data_offset(path, f"frames/000002/{name}")
    with open(path, "rb") as fh:
        fh.seek(offset + size // 2)
        byte = fh.read(1)[0]
    _patch_bytes(path, offset + size // 2, bytes([byte ^ 0x40]))  # one bit of one value's exponent


def zero_block(path: Path, kind: str) -> None:
    name = "params" if kind == "dic2d" else "params_left"
    offset, size = _data_offset(path, f"frames/000002/{name}")
    block = min(4096, size - 8)
    _patch_bytes(path, offset + 8, bytes(block))


def drop_index(path: Path, kind: str) -> None:
    with h5py.File(path, "a") as h5:
        del h5["frames/000002"].attrs["index"]


def drop_u(path: Path, kind: str) -> None:
    with h5py.File(path, "a") as h5:
        del h5["frames/000002/" + ("u" if kind == "dic2d" else "U")]


def frames_as_dataset(path: Path, kind: str) -> None:
    with h5py.File(path, "a") as h5:
        del h5["frames"]
        h5["frames"] = np.arange(3)


def header_only(path: Path, kind: str) -> None:
    with h5py.File(path, "a") as h5:
        for name in list(h5.keys()):
            del h5[name]


def no_settings(path: Path, kind: str) -> None:
    with h5py.File(path, "a") as h5:
        del h5["settings"]


def reference_as_dataset(path: Path, kind: str) -> None:
    with h5py.File(path, "a") as h5:
        del h5["reference"]
        h5["reference"] = np.zeros((2, 2))


#: damage -> what the one line says
DAMAGES = {
    flip_bit: r"is damaged: (frame|state) 2 fails its checksum in dataset '[uU]'",
    zero_block: r"is damaged: (frame|state) 2 fails its checksum in dataset 'params(_left)?'",
    drop_index: r"is damaged: (frame|state) '000002' has no 'index' attribute",
    drop_u: r"is damaged: (frame|state) 2 has no '[uU]' dataset",
    frames_as_dataset: r"is damaged or not a Specula result file: '/frames' is a dataset, not a group",
    header_only: r"is damaged or not a Specula result file: it has no '/reference' group",
    no_settings: r"is damaged or not a Specula result file: it has no '/settings' group",
    reference_as_dataset: r"is damaged or not a Specula result file: '/reference' is a dataset, not a group",
}
#: damage of one frame (the others stay readable and the repair drops it) vs damage of the header
FRAME_DAMAGES = (flip_bit, zero_block, drop_index, drop_u)


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    folder = tmp_path_factory.mktemp("whole")
    return {kind: _build(folder / f"{kind}.h5", kind) for kind in ("dic2d", "stereo")}


def _damaged(whole, tmp_path, kind, damage) -> Path:
    path = tmp_path / f"{damage.__name__}.h5"
    shutil.copyfile(whole[kind], path)
    damage(path, kind)
    return path


def _read_everything(path: Path, kind: str) -> None:
    """What every reader does: the whole file, one frame at a time, and the resume of a run."""
    with ResultFrames(path) as frames:
        for _ in frames:
            pass


def _resume(path: Path, kind: str) -> None:
    """What a resumed run reads: the finished frames and the states it starts from."""
    if kind == "stereo":
        w = ResultWriter(path, rig=fake_rig(), **STEREO_KW)
    else:
        w = ResultWriter(path, **KW2)
    with w:
        for k in w.done_frames():
            w.read_frame(k)


@pytest.mark.parametrize("kind", ["dic2d", "stereo"])
@pytest.mark.parametrize("damage", list(DAMAGES), ids=lambda d: d.__name__)
def test_damaged_file_is_refused_with_one_line_at_every_reader(whole, tmp_path, kind, damage):
    """Before: a flipped bit exported u = 7.2e307 on a row marked valid (exit 0); the other damages ended
    in KeyError/TypeError tracebacks (export, resume, strain)."""
    from dic.export import export_results

    path = _damaged(whole, tmp_path, kind, damage)
    pattern = DAMAGES[damage]
    readers = [("read", lambda: (read_stereo if kind == "stereo" else read_results)(path)),
               ("frames", lambda: _read_everything(path, kind)),
               ("resume", lambda: _resume(path, kind)),
               ("export", lambda: export_results(path, "csv", tmp_path / "csv"))]
    if kind == "dic2d":
        from dic.postprocess import point_history, recompute_strain

        readers.append(("strain", lambda: recompute_strain(path, tmp_path / "s.h5", window=3)))
        if damage is not zero_block:  # a history of u reads u only (dic.postprocess): damaged params are not read
            readers.append(("history", lambda: point_history(path, (40.0, 50.0), "u")))
    for what, read in readers:
        with pytest.raises(ValueError, match=pattern) as info:
            read()
        assert str(path) in str(info.value) and "\n" not in str(info.value), what
    verbs = [["export", str(path), "-f", "csv", "-o", str(tmp_path / "csv")]]
    if kind == "dic2d":
        verbs.append(["strain", str(path), "--window", "3", "-o", str(tmp_path / "s.h5")])
    for args in verbs:
        res = CliRunner().invoke(main, args)
        assert res.exit_code == 1, (args, res.output)
        lines = res.output.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("Error:") and "Traceback" not in res.output, res.output
    assert not (tmp_path / "s.h5").exists()


def test_a_flipped_bit_is_refused_by_the_cli_in_a_process_of_its_own(whole, tmp_path):
    path = _damaged(whole, tmp_path, "dic2d", flip_bit)
    proc = subprocess.run([sys.executable, "-m", "dic.cli", "export", str(path), "-f", "csv", "-o",
                           str(tmp_path / "csv")], capture_output=True, text=True, env=ENV, timeout=300)
    assert proc.returncode == 1 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().startswith("Error:") and len(proc.stderr.strip().splitlines()) == 1
    assert "frame 2 fails its checksum in dataset 'u'" in proc.stderr and "specula repair" in proc.stderr


@pytest.mark.parametrize("kind", ["dic2d", "stereo"])
@pytest.mark.parametrize("damage", FRAME_DAMAGES, ids=lambda d: d.__name__)
def test_repair_drops_the_damaged_frame_and_keeps_the_others(whole, tmp_path, kind, damage):
    path = _damaged(whole, tmp_path, kind, damage)
    dropped = repair_results(path)
    assert [label for label, _ in dropped] == [2]
    with ResultReader(path) as r:
        assert r.done_frames() == [1, 3]
        good = ResultReader(whole[kind])
        for k in (1, 3):
            a, b = good.read_frame(k), r.read_frame(k)
            for name in (("u", "v", "params") if kind == "dic2d" else ("U", "X", "status")):
                assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True)
        good.close()
    assert repair_results(path) == []  # whole now
    res = CliRunner().invoke(main, ["repair", str(path)])
    assert res.exit_code == 0 and "nothing to repair" in res.output


@pytest.mark.parametrize("damage", [d for d in DAMAGES if d not in FRAME_DAMAGES], ids=lambda d: d.__name__)
def test_a_damaged_header_cannot_be_repaired_and_says_so(whole, tmp_path, damage):
    path = _damaged(whole, tmp_path, "dic2d", damage)
    res = CliRunner().invoke(main, ["repair", str(path)])
    assert res.exit_code == 1 and res.output.startswith("Error:") and "restore it from a copy" in res.output


def test_repaired_run_resumes_and_recomputes_the_dropped_frame(tmp_path):
    from dic.sequence import track_sequence
    from dic.synth import speckle_pair

    ref, _ = speckle_pair((64, 72), (0, 0), seed=3)
    frames = [speckle_pair((64, 72), (0.4 * k, -0.3 * k), seed=3)[1] for k in range(1, 4)]
    out = tmp_path / "r.h5"
    track_sequence(ref, frames, out, step=8, strain_window=3, device="cpu")
    original = tmp_path / "original.h5"
    shutil.copyfile(out, original)
    flip_bit(out, "dic2d")
    with pytest.raises(ValueError, match="frame 2 fails its checksum"):
        read_results(out)
    res = CliRunner().invoke(main, ["repair", str(out)])
    assert res.exit_code == 0 and "dropped frame 2: fails its checksum in dataset 'u'" in res.output
    s = track_sequence(ref, frames, out, step=8, strain_window=3, device="cpu")
    assert s.skipped == 2  # frames 1 and 3 kept, frame 2 recomputed
    a, b = read_results(original), read_results(out)
    assert sorted(b.frames) == [1, 2, 3]
    for k in (1, 2, 3):
        for name in ("u", "v", "params", "zncc", "status", "valid"):
            assert np.array_equal(getattr(a.frames[k], name), getattr(b.frames[k], name), equal_nan=True), (k, name)


def test_every_dataset_carries_a_checksum_by_default(whole):
    for kind, path in whole.items():
        with h5py.File(path, "r") as h5:
            assert h5.attrs["checksum"] == "fletcher32"
            seen = []

            def visit(name, obj):
                if isinstance(obj, h5py.Dataset) and obj.size and obj.ndim:
                    seen.append(name)
                    assert obj.fletcher32, (kind, name)
            h5.visititems(visit)
            assert len(seen) > 20


def test_files_without_checksums_still_read_and_resume(tmp_path):
    """Files of earlier versions (no fletcher32, no ``checksum`` attribute) read; frames appended get checksums."""
    path = tmp_path / "old.h5"
    with ResultWriter(path, compression=Compression(None, checksum=False), **KW2) as w:
        for k in (1, 2):
            w.write_frame(k, fake_field(k, n_side=N_SIDE), path=f"c{k}.tif")
    with h5py.File(path, "a") as h5:
        del h5.attrs["checksum"]
        assert not h5["frames/000001/u"].fletcher32
    with ResultWriter(path, **KW2) as w:  # resumes
        assert w.done_frames() == [1, 2] and w.compression.checksum
        w.write_frame(3, fake_field(3, n_side=N_SIDE), path="c3.tif")
    back = read_results(path)
    assert sorted(back.frames) == [1, 2, 3]
    for k in (1, 2, 3):
        assert np.array_equal(back.frames[k].u, fake_field(k, n_side=N_SIDE).u)
    with h5py.File(path, "r") as h5:
        assert not h5["frames/000002/u"].fletcher32 and h5["frames/000003/u"].fletcher32
    assert repair_results(path) == []
