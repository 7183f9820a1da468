"""Dask 2-D runs carry the region's pixel mask and the declared cracks to a moved reference, and check composed
frames on the reference subsets' kept pixels, as one process does (issue 26, items 1, 2 and 4 with ``client=`` and
``reference="every:2"``): on the hole and crack sequences of tests/dic/test_moved_masks.py (exact truth) a run on a
Dask LocalCluster (``processes=False``: the workers are threads of this process) gives the file of a single-process
run with ``guess="none"`` bit for bit, and the exact-truth bounds of the single-process tests hold there too.
What travels to the workers (:class:`dic.sequence.distributed.CarriedMasks`) is checked to pickle small and to give
back the same tracker keywords."""
import pickle

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

import test_moved_masks  # noqa: E402 - the scenes and their exact-truth figures
from test_moved_masks import CH, CX, HOLE_SHAPE, _crack_figures, _hole_figures  # noqa: E402

from dic import Crack  # noqa: E402
from dic.sequence import track2d, track_sequence  # noqa: E402
from dic.sequence.distributed import CarriedMasks  # noqa: E402
from dic.store import read_results  # noqa: E402

pytestmark = pytest.mark.dask
hole_sequence = test_moved_masks.hole_sequence  # the fixtures
crack_sequence = test_moved_masks.crack_sequence


@pytest.fixture(scope="module")
def client():
    with distributed.LocalCluster(n_workers=2, processes=False, threads_per_worker=1, dashboard_address=None) as cluster, \
            distributed.Client(cluster, set_as_default=False) as c:
        yield c


def _same_files(a, b, frames):
    """Every frame's fields, status, attributes (reference, composed mismatches) and the settings equal."""
    ra, rb = read_results(a), read_results(b)
    assert sorted(ra.frames) == sorted(rb.frames) == frames
    for k in frames:
        fa, fb = ra.frames[k], rb.frames[k]
        for name in ("points", "u", "v", "params", "zncc", "status", "valid", "sigma_u", "sigma_v"):
            assert np.array_equal(getattr(fa, name), getattr(fb, name), equal_nan=True), (k, name)
        for name in ("reference_index", "composed_mismatch", "reference_interpolated"):
            assert fa.attrs.get(name) == fb.attrs.get(name), (k, name)
    assert ra.settings == rb.settings


def test_dask_masks_a_moved_reference_around_a_moving_hole_as_one_process(hole_sequence, client, tmp_path):
    """every:2, the region given as a mask (subset 21, step 4, "zncc" start): the Dask file is the single-process
    file (guess="none") bit for bit, frames 3 and 4 (against frame 2, its subsets masked by the carried hole) meet
    the bounds of issue 26 (edge RMS <= 2 x interior, >= 80 % of the 100 edge points kept), and no composed point
    fails the check (it compares the kept pixels: a whole-subset check fails correct edge points,
    tests/dic/test_moved_masks.py). Measured on Dask: edge / interior RMS 1.32 and 1.61, 100 % kept, no mismatch;
    before (no carry on Dask, the whole-subset check) 12.1 and 11.1 x, 83 % and 73 % kept (17 and 27 points
    failed the check): the bounds and the equality with one process fail there."""
    ref, frames, region = hole_sequence
    kw = dict(roi=region, step=4, subset=21, search="zncc", search_radius=4, reference="every:2", device="cpu",
              strain_window=0)
    d = track_sequence(ref, frames, tmp_path / "d.h5", client=client, **kw)
    one = track_sequence(ref, frames, tmp_path / "one.h5", guess="none", **kw)
    _same_files(tmp_path / "d.h5", tmp_path / "one.h5", [1, 2, 3, 4])
    assert d.n_mismatch.tolist() == one.n_mismatch.tolist() == [0, 0, 0, 0]
    got = _hole_figures(tmp_path / "d.h5", region)
    for k in (3, 4):
        index, interior, edge, kept, n_edge, f = got[k]
        assert index == 2 and n_edge == 100 and f.attrs["composed_mismatch"] == 0
        assert edge <= 2.0 * interior and kept >= 0.80, got[k][:5]


def test_dask_cuts_a_moved_reference_where_the_crack_has_moved_as_one_process(crack_sequence, client, tmp_path):
    """every:2, the crack declared at x = 100.5 (reference px): the Dask file is the single-process file
    (guess="none") bit for bit, and after the update (frames 3 and 4, against frame 2, where the crack is 4 px to
    the right) the bounds of the single-process test hold: the 240 points within one subset of the crack valid,
    within 0.025 px, RMS within 0.008 px; the opening within 0.01 px of 0.375 / 0.5 px at every station, sliding
    within 0.01 px. Measured on Dask: at most 0.0152 / 0.0179 px off (RMS 0.0051 / 0.0058), the opening at most
    0.0013 / 0.0088 px off; before (no carry on Dask) at most 0.061 / 0.114 px off, the opening 0.023 / 0.040 px
    off. A run of frames 1-3 on one process resumed on Dask (the moved reference rebuilt from frame 2 read back,
    its crack carried again in the client) gives frame 4 bit for bit as well."""
    ref, frames = crack_sequence
    kw = dict(cracks=Crack([[CX, -20.0], [CX, CH + 20.0]]), step=4, subset=21, search="zncc", search_radius=4,
              reference="every:2", device="cpu", strain_window=0)
    d = track_sequence(ref, frames, tmp_path / "d.h5", client=client, **kw)
    one = track_sequence(ref, frames, tmp_path / "one.h5", guess="none", **kw)
    _same_files(tmp_path / "d.h5", tmp_path / "one.h5", [1, 2, 3, 4])
    assert d.n_mismatch.tolist() == one.n_mismatch.tolist()
    resumed = tmp_path / "resumed.h5"
    track_sequence(ref, frames[:3], resumed, guess="none", **kw)
    s = track_sequence(ref, frames, resumed, client=client, **kw)
    assert s.skipped == 3 and [f["index"] for f in s.frames] == [4]
    _same_files(resumed, tmp_path / "one.h5", [1, 2, 3, 4])
    got = _crack_figures(tmp_path / "d.h5")
    for k in (3, 4):
        g = got[k]
        assert g.field.reference_index == 2 and g.near.sum() == 240
        assert g.field.valid[g.near].all()
        assert np.max(g.err[g.near]) < 0.025 and np.sqrt(np.mean(g.err[g.near] ** 2)) < 0.008
        assert np.all(np.isfinite(g.opening_error)) and np.max(np.abs(g.opening_error)) < 0.01
        assert np.max(np.abs(g.sliding)) < 0.01


def test_what_is_shipped_to_the_workers_pickles_small_and_gives_the_same_keywords(hole_sequence, tmp_path):
    """Frame 2 of the hole run as a moved reference with a crack too: the pickled :class:`CarriedMasks` holds the
    carried region packed 8 px a byte (HOLE_SHAPE: 200 x 320 px -> 8000 bytes) and the cracks' callable as two
    (N, 2) float64 arrays (the moved points, whole and sub-pixel) and the carried polyline: under 1000 bytes more
    than those (about 56 kB here, N = 1481; the float32 frame that goes with it is 256 kB); unpickled, its keywords
    are the ones a single-process run gives the tracker (the region bit for bit, the blocked pixels the same)."""
    ref, frames, region = hole_sequence
    crack = Crack([[60.5, -10.0], [60.5, 210.0]])
    opts = dict(roi=region, step=6, subset=21, search="zncc", search_radius=4, device="cpu", cracks=crack)
    track_sequence(ref, frames[:2], tmp_path / "f.h5", strain_window=0, **opts)
    state = read_results(tmp_path / "f.h5").frames[2]
    points0 = np.asarray(state.points, np.float64)
    moved = track2d._moved(points0, state, 2, None, 1).moved
    carried = track2d._carry_for(opts, ref.shape)(moved)
    assert set(carried) == {"pixel_region", "blocked_pixels", "cracks"}
    shipped = CarriedMasks(carried)
    assert shipped.nbytes == HOLE_SHAPE[0] * HOLE_SHAPE[1] // 8
    for dumps in (pickle.dumps, __import__("cloudpickle").dumps):  # plain pickle: no closure travels
        blob = dumps(shipped)
        assert len(blob) < shipped.nbytes + 2 * moved.points.nbytes + 1000, len(blob)
        back = pickle.loads(blob).keywords()
        assert set(back) == set(carried) and back["cracks"] is None
        assert back["pixel_region"].dtype == bool and np.array_equal(back["pixel_region"], carried["pixel_region"])
        assert not back["pixel_region"].all() and back["pixel_region"].any()
        want = carried["blocked_pixels"](moved.points, 21)
        assert want.any() and np.array_equal(back["blocked_pixels"](moved.points, 21), want)
        some = moved.points[::7] + 0.5  # points not among the moved ones: seen from where they are
        assert np.array_equal(back["blocked_pixels"](some, 21), carried["blocked_pixels"](some, 21))


def test_specula_track_on_dask_carries_the_crack_as_one_process(crack_sequence, client, tmp_path):
    """``specula track --scheduler ADDRESS --reference every:2 --crack ...`` (the command line's own tracker factory,
    which takes ``carried``; the region and cracks described by its run record): the file is the command line's
    library's single-process run with ``guess="none"`` and the same options bit for bit (fields, statuses, the
    composed-check counts), and the points near the crack after the update are measured within the bound of the
    library test."""
    from click.testing import CliRunner

    from dic.cli import main
    from dic.io import write_image

    ref, frames = crack_sequence
    write_image(tmp_path / "ref.tif", ref.astype(np.uint8))
    paths = []
    for k, f in enumerate(frames, 1):
        paths.append(str(tmp_path / f"f{k}.tif"))
        write_image(paths[-1], f.astype(np.uint8))
    runner = CliRunner()

    def track(out, *extra):
        args = ["track", str(tmp_path / "ref.tif"), *paths, "-o", str(out), "--step", "4", "-q", "--device", "cpu",
                "--reference", "every:2", "--search-method", "zncc", "--search", "4", "--crack",
                f"{CX},-20,{CX},{CH + 20}", *extra]
        res = runner.invoke(main, args)
        assert res.exit_code == 0, res.output

    track(tmp_path / "d.h5", "--scheduler", client.scheduler.address)
    track_sequence(str(tmp_path / "ref.tif"), paths, tmp_path / "one.h5", reference="every:2", guess="none", step=4,
                   subset=21, order=1, search="zncc", search_radius=4, device="cpu",
                   cracks=Crack([[CX, -20.0], [CX, CH + 20.0]]))
    ra, rb = read_results(tmp_path / "d.h5"), read_results(tmp_path / "one.h5")
    for k in range(1, 5):
        fa, fb = ra.frames[k], rb.frames[k]
        for name in ("u", "v", "params", "zncc", "status", "valid"):
            assert np.array_equal(getattr(fa, name), getattr(fb, name), equal_nan=True), (k, name)
        assert fa.attrs.get("composed_mismatch") == fb.attrs.get("composed_mismatch"), k
    g = _crack_figures(tmp_path / "d.h5")[4]
    assert g.field.reference_index == 2 and g.field.valid[g.near].all() and np.max(g.err[g.near]) < 0.025
