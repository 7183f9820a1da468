"""The sequence engine (dic/sequence/): dic.sequence.track_sequence, reference strategies, resume, streaming outputs,
bounded memory; and ``specula track --reference/--vtk/--figure-every``."""
import os

import numpy as np
import pytest
from click.testing import CliRunner

from dic.sequence import parse_reference, track_sequence
from dic.sequence.reference import compose_params, relative_params, shift_params
from dic.store import read_results
from dic.synth import speckle_pair

SHAPE = (96, 112)
N_FRAMES = 20
# translation increments alternate 0.35 / 0.65 px (opposite interpolation biases), plus a growing stretch
STEPS = np.cumsum([0.0] + [0.35 if j % 2 else 0.65 for j in range(1, N_FRAMES + 1)])


def truth(k):
    return lambda x, y: (STEPS[k] + 0.003 * k * (x - 56), -STEPS[k] + 0.0015 * k * (y - 48))


@pytest.fixture(scope="module")
def sequence():
    ref, _ = speckle_pair(SHAPE, (0, 0), seed=3)
    return ref, [speckle_pair(SHAPE, truth(k), seed=3)[1] for k in range(1, N_FRAMES + 1)]


def _rms_error(frame, k):
    p, v = frame.points, frame.valid
    tu, tv = truth(k)(p[:, 0], p[:, 1])
    return float(np.sqrt(np.mean((frame.u[v] - tu[v]) ** 2 + (frame.v[v] - tv[v]) ** 2)))


def _same_frames(a, b):
    ra, rb = read_results(a), read_results(b)
    assert sorted(ra.frames) == sorted(rb.frames)
    for k in ra.frames:
        fa, fb = ra.frames[k], rb.frames[k]
        for name in ("points", "u", "v", "params", "zncc", "status", "valid", "sigma_u", "sigma_v"):
            assert np.array_equal(getattr(fa, name), getattr(fb, name), equal_nan=True), (k, name)
        for name in fa.strain:
            assert np.array_equal(fa.strain[name], fb.strain[name], equal_nan=True), (k, name)
        assert fa.attrs["reference_index"] == fb.attrs["reference_index"]


@pytest.mark.parametrize("strategy", ["fixed", "incremental", "every:5", "auto"])
def test_every_strategy_follows_the_exact_field(sequence, tmp_path, strategy):
    ref, frames = sequence
    out = tmp_path / "r.h5"
    s = track_sequence(ref, frames, out, reference=strategy, step=8, device="cpu")
    assert [f["index"] for f in s.frames] == list(range(1, N_FRAMES + 1)) and s.skipped == 0
    res = read_results(out)
    refs = [res.frames[k].attrs["reference_index"] for k in range(1, N_FRAMES + 1)]
    expected = {"fixed": [0] * N_FRAMES, "incremental": list(range(N_FRAMES)),
                "every:5": [5 * ((k - 1) // 5) for k in range(1, N_FRAMES + 1)]}
    if strategy in expected:
        assert refs == expected[strategy]
    else:  # auto: some update, never ahead of the frame, never backwards
        assert refs[-1] > 0 and all(0 <= r < k for k, r in enumerate(refs, 1)) and refs == sorted(refs)
    for k in range(1, N_FRAMES + 1):
        f = res.frames[k]
        assert np.array_equal(f.points, res.frames[1].points)  # the same (original) POIs at every step
        assert f.valid.mean() > 0.6 and _rms_error(f, k) < 0.02, (strategy, k, _rms_error(f, k))
    assert res.settings.get("reference", "fixed") == strategy


@pytest.mark.parametrize("strategy", ["incremental", "every:3", "auto"])
def test_resume_after_a_crash_gives_identical_results(sequence, tmp_path, strategy):
    ref, frames = sequence
    frames = frames[:10]
    whole = tmp_path / "whole.h5"
    track_sequence(ref, frames, whole, reference=strategy, step=8, device="cpu")

    def crash(k, field, strain):
        if k == 6:
            raise RuntimeError("killed")

    out = tmp_path / "cut.h5"
    with pytest.raises(RuntimeError, match="killed"):
        track_sequence(ref, frames, out, reference=strategy, step=8, device="cpu", callback=crash)
    assert sorted(read_results(out).frames) == [1, 2, 3, 4, 5, 6]
    s = track_sequence(ref, frames, out, reference=strategy, step=8, device="cpu")
    assert s.skipped == 6 and [f["index"] for f in s.frames] == [7, 8, 9, 10]
    _same_frames(whole, out)


def test_unreadable_frame_in_the_middle_keeps_the_frames_before(sequence, tmp_path):
    ref, frames = sequence

    def source():
        yield from frames[:4]
        raise OSError("the camera stopped")

    out = tmp_path / "r.h5"
    with pytest.raises(ValueError, match=r"frame 5 \(array\): the camera stopped; frames before it are saved in"):
        track_sequence(ref, source(), out, reference="incremental", step=8, device="cpu")
    assert sorted(read_results(out).frames) == [1, 2, 3, 4]
    with pytest.raises(ValueError, match="frame 3 .*all images must have the same size"):
        track_sequence(ref, [frames[0], frames[1], frames[2][:50]], tmp_path / "b.h5", step=8, device="cpu")
    assert sorted(read_results(tmp_path / "b.h5").frames) == [1, 2]
    s = track_sequence(ref, np.stack(frames[:6]), out, reference="incremental", step=8, device="cpu")  # resumes
    assert s.skipped == 4 and len(s.frames) == 2  # a (T, H, W) array is a sequence of frames too


def test_every_n_key_frame_without_a_valid_point_keeps_the_previous_reference(sequence, tmp_path):
    """Issue 24, defect 3: frame 2 (a flash: one flat grey level) has no valid point. With every:2 it is the key
    frame of frames 3 and 4; it cannot serve as their reference, so they stay on the reference of frame 2 (the
    reference image, as incremental and auto fall back), frame 5 moves to frame 4. Before, frame 4 failed with a
    false "cannot resume ...: the image of frame 2 was not given again", and so did every rerun."""
    ref, frames = sequence
    frames = list(frames[:5])
    frames[1] = np.full_like(frames[1], float(np.mean(frames[1])))
    out = tmp_path / "r.h5"
    with pytest.warns(RuntimeWarning, match="only 0 of"):
        s = track_sequence(ref, frames, out, reference="every:2", step=8, device="cpu")
    assert list(s.indices) == [1, 2, 3, 4, 5] and s.skipped == 0
    assert list(s.reference_indices) == [0, 0, 0, 0, 4]
    assert s.n_valid[1] == 0
    res = read_results(out)
    for k in (1, 3, 4, 5):  # the frames around the flash follow the exact field as usual
        f = res.frames[k]
        assert f.valid.mean() > 0.6 and _rms_error(f, k) < 0.02, (k, f.valid.mean(), _rms_error(f, k))
    # a run cut after frame 3 resumes to the same file
    cut = tmp_path / "cut.h5"

    def stop(k, field, strain):
        if k == 3:
            raise RuntimeError("killed")

    with pytest.raises(RuntimeError, match="killed"), pytest.warns(RuntimeWarning):
        track_sequence(ref, frames, cut, reference="every:2", step=8, device="cpu", callback=stop)
    resumed = track_sequence(ref, frames, cut, reference="every:2", step=8, device="cpu")
    assert resumed.skipped == 3 and list(resumed.indices) == [4, 5]
    _same_frames(out, cut)


def test_streaming_vtk_and_figures(sequence, tmp_path):
    import meshio

    ref, frames = sequence
    seen = []

    def spy(k, field, strain):  # the frame's files exist when it is handed over: written as it finishes
        seen.append((k, (tmp_path / "vtk" / f"frame_{k:06d}.vtu").exists()))

    track_sequence(ref, frames[:6], tmp_path / "r.h5", reference="every:2", step=8, device="cpu",
                   vtk_dir=tmp_path / "vtk", figure_dir=tmp_path / "figs", figure_every=2, callback=spy)
    assert seen == [(k, True) for k in range(1, 7)]
    assert sorted(p.name for p in (tmp_path / "figs").iterdir()) == [f"frame_{k:06d}.png" for k in (2, 4, 6)]
    res = read_results(tmp_path / "r.h5")
    first = None
    for k in range(1, 7):
        mesh = meshio.read(tmp_path / "vtk" / f"frame_{k:06d}.vtu")
        first = mesh.points if first is None else first
        assert np.array_equal(mesh.points, first)  # one point set for every step
        u = mesh.point_data["u"]
        invalid = ~res.frames[k].valid
        assert len(u) == len(invalid) and np.array_equal(np.isnan(u), invalid) and invalid.any()


def test_memory_does_not_grow_with_the_sequence(tmp_path):
    """RSS after 200 frames stays within a few MB of RSS after 50 (no per-frame accumulation; the
    first ~40 frames fill HDF5's metadata cache of the growing file, a bounded cost)."""
    ref, cur = speckle_pair((128, 128), (0.4, -0.3), seed=5)
    rss = {}

    def measure(k, field, strain):
        if k in (50, 200):
            with open("/proc/self/statm") as f:
                rss[k] = int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    def frames():
        rng = np.random.default_rng(0)
        for _ in range(200):
            yield cur + rng.normal(0, 0.5, cur.shape).astype(np.float32)

    track_sequence(ref, frames(), tmp_path / "r.h5", step=6, device="cpu", callback=measure)
    assert rss[200] <= rss[50] + 4 * 2**20, (rss[50] / 2**20, rss[200] / 2**20)


def test_bad_arguments(sequence, tmp_path):
    ref, frames = sequence
    cases = [({"reference": "every:0"}, "whole number N >= 1"), ({"reference": "sometimes"}, "'fixed', 'incremental'"),
             ({"reference": 3}, "'fixed', 'incremental'"), ({"figure_every": 0}, "figure_every"),
             ({"auto_valid": 1.5}, "auto_valid"), ({"callback": 3}, "callback must be callable"),
             ({"strain_window": 4}, "odd"), ({"mode": "sometimes"}, "mode must be")]
    for kw, msg in cases:
        with pytest.raises(ValueError, match=msg):
            track_sequence(ref, frames[:2], tmp_path / "r.h5", step=8, device="cpu", **kw)
    with pytest.raises(ValueError, match="frames is empty"):
        track_sequence(ref, [], tmp_path / "r.h5", step=8)
    assert not (tmp_path / "r.h5").exists()
    pts = np.array([[30.0, 30.0], [50.5, 40.0], [70.0, 60.0]])  # given POIs: stored as a digest, and tracked
    track_sequence(ref, frames[:1], tmp_path / "p.h5", points=pts, strain_window=0, device="cpu")
    res = read_results(tmp_path / "p.h5")
    assert res.settings["points"]["shape"] == [3, 2] and np.array_equal(res.frames[1].points, pts)
    with pytest.raises(ValueError, match="matches no files"):  # one path is a folder/pattern/stack/video
        track_sequence(ref, str(tmp_path / "nothing" / "*.tif"), tmp_path / "r.h5", step=8)
    import tifffile

    (tmp_path / "seq").mkdir()
    for k, f in enumerate(frames[:2]):  # float32 TIFFs: the same grey levels as the arrays
        tifffile.imwrite(tmp_path / "seq" / f"f{k + 1}.tif", np.asarray(f, np.float32))
    from_folder = track_sequence(ref, tmp_path / "seq", tmp_path / "folder.h5", step=8, strain_window=0, device="cpu")
    track_sequence(ref, list(frames[:2]), tmp_path / "list.h5", step=8, strain_window=0, device="cpu")
    a, b = read_results(tmp_path / "folder.h5"), read_results(tmp_path / "list.h5")
    assert len(from_folder.frames) == 2 and np.array_equal(a.frames[2].u, b.frames[2].u)
    with pytest.raises(ValueError, match=".h5"):
        track_sequence(ref, frames[:2], tmp_path / "r.txt", step=8)
    assert parse_reference(" Every:4 ").every == 4


def test_composition_is_the_chain_rule():
    """compose_params(d_r, w) = the parameters of X -> d_r(X) + w(X + d_r(X)) at X = 0, by finite differences."""
    rng = np.random.default_rng(1)
    for order in (1, 2):
        k = 6 if order == 1 else 12
        pr, pw = rng.normal(0, 0.05, (1, k)), rng.normal(0, 0.05, (1, k))
        pr[0, 0], pw[0, 0] = 1.3, -0.4

        def warp(p, x, y):
            h = k // 2
            out = []
            for b in (0, h):
                val = p[0, b] + p[0, b + 1] * x + p[0, b + 2] * y
                if order == 2:
                    val = val + 0.5 * p[0, b + 3] * x * x + p[0, b + 4] * x * y + 0.5 * p[0, b + 5] * y * y
                out.append(val)
            return np.array(out)

        d0 = warp(pr, 0, 0)  # w's shape function is centred on the moved point X + d_r(X) (where it is tracked)

        def total(x, y):
            d = warp(pr, x, y)
            return d + warp(pw, x + d[0] - d0[0], y + d[1] - d0[1])

        c = compose_params(pr, pw, order)[0]
        e = 1e-4
        assert np.allclose(total(0, 0), [c[0], c[k // 2]], atol=1e-12)
        gx = (total(e, 0) - total(-e, 0)) / (2 * e)
        gy = (total(0, e) - total(0, -e)) / (2 * e)
        assert np.allclose([gx[0], gy[0], gx[1], gy[1]], [c[1], c[2], c[k // 2 + 1], c[k // 2 + 2]], atol=1e-7)
        if order == 2:
            hxx = (total(e, 0) - 2 * total(0, 0) + total(-e, 0)) / e**2
            hxy = (total(e, e) - total(e, -e) - total(-e, e) + total(-e, -e)) / (4 * e**2)
            assert np.allclose([hxx[0], hxy[0], hxx[1], hxy[1]], [c[3], c[4], c[9], c[10]], atol=1e-5)
        # shift_params: the same warp seen from another point
        s = shift_params(pw, np.array([[0.3, -0.2]]), order)[0]
        assert np.allclose([s[0], s[k // 2]], warp(pw, 0.3, -0.2), atol=1e-12)
        # relative_params inverts the translation and the gradient
        r = relative_params(pr, c[None], order)
        assert np.allclose(r[0, [0, 1, 2, k // 2, k // 2 + 1, k // 2 + 2]], pw[0, [0, 1, 2, k // 2, k // 2 + 1, k // 2 + 2]],
                           atol=1e-12)


def test_cli_reference_and_vtk(sequence, tmp_path):
    from dic.cli import main
    from dic.io import write_image

    ref, frames = sequence
    paths = [str(write_image(tmp_path / f"f{k:02d}.tif", img, bits=8)) for k, img in enumerate([ref, *frames[:4]])]
    out = tmp_path / "r.h5"
    r = CliRunner().invoke(main, ["track", *paths, "-o", str(out), "--step", "8", "--device", "cpu",
                                  "--reference", "incremental", "--vtk", str(tmp_path / "vtk")])
    assert r.exit_code == 0, r.output
    res = read_results(out)
    assert [res.frames[k].attrs["reference_index"] for k in (1, 2, 3, 4)] == [0, 1, 2, 3]
    assert res.settings["reference"] == "incremental" and "frames/s" in r.output and "(reference: frame 3)" in r.output
    assert len(list((tmp_path / "vtk").glob("frame_*.vtu"))) == 4
    r = CliRunner().invoke(main, ["track", *paths, "-o", str(out), "--step", "8", "--reference", "fixed"])
    assert r.exit_code == 1 and "different settings" in r.output and "Traceback" not in r.output
    r = CliRunner().invoke(main, ["track", *paths, "-o", str(out), "--reference", "every:x"])
    assert r.exit_code == 2 and "--reference" in r.output and "whole number" in r.output


@pytest.mark.parametrize("strategy, search", [("fixed", None), ("every:3", "zncc")])
def test_chunks_under_a_memory_budget_give_identical_results(sequence, tmp_path, strategy, search, monkeypatch):
    from dic.sequence import chunks
    from dic.sequence.chunks import bytes_per_poi

    built = []
    real = chunks.ChunkedTracker.track

    def spy(self, current, guess=None):
        built.append(self.n_chunks)
        return real(self, current, guess=guess)

    monkeypatch.setattr(chunks.ChunkedTracker, "track", spy)

    ref, frames = sequence
    kw = dict(reference=strategy, step=8, device="cpu", search=search, search_radius=4, order=2)
    whole = track_sequence(ref, frames[:6], tmp_path / "whole.h5", **kw)
    budget = 37 * bytes_per_poi(2)  # 37 POIs at a time: 4 chunks of the 120
    assert built == []
    chunked = track_sequence(ref, frames[:6], tmp_path / "chunked.h5", max_memory=budget, **kw)
    assert built == [4] * 6  # every frame in 4 chunks
    assert [f["n_valid"] for f in whole.frames] == [f["n_valid"] for f in chunked.frames]
    _same_frames(tmp_path / "whole.h5", tmp_path / "chunked.h5")
    with pytest.raises(ValueError, match="cannot run on POIs in chunks"):
        track_sequence(ref, frames[:2], tmp_path / "rg.h5", step=8, search="rg", max_memory=budget)
    with pytest.raises(ValueError, match="max_memory"):
        track_sequence(ref, frames[:2], tmp_path / "x.h5", step=8, max_memory=0)


def test_cli_max_memory_chunks_with_the_same_results(sequence, tmp_path, monkeypatch):
    from dic.cli import main
    from dic.io import write_image
    from dic.sequence import chunks

    built = []
    real = chunks.ChunkedTracker.track
    monkeypatch.setattr(chunks.ChunkedTracker, "track", lambda self, cur, guess=None: built.append(self.n_chunks) or
                        real(self, cur, guess=guess))

    ref, frames = sequence
    paths = [str(write_image(tmp_path / f"f{k:02d}.tif", img, bits=8)) for k, img in enumerate([ref, *frames[:3]])]
    base = ["track", *paths, "--step", "8", "--device", "cpu", "-q", "--reference", "every:2"]
    assert CliRunner().invoke(main, [*base, "-o", str(tmp_path / "a.h5")]).exit_code == 0
    r = CliRunner().invoke(main, [*base, "-o", str(tmp_path / "b.h5"), "--max-memory", "10K"])  # 15 POIs a chunk
    assert r.exit_code == 0, r.output
    assert built == [-(-120 // (10240 // chunks.bytes_per_poi(1)))] * 3 == [8, 8, 8]  # the 120 POIs in 8 chunks
    _same_frames(tmp_path / "a.h5", tmp_path / "b.h5")
    for bad in ("0", "lots", "-5M"):
        r = CliRunner().invoke(main, [*base, "-o", str(tmp_path / "c.h5"), "--max-memory", bad])
        assert r.exit_code == 2 and "--max-memory" in r.output and "Traceback" not in r.output


def test_points_lost_at_a_reference_update_come_back(sequence, tmp_path):
    """A patch of frame 2 is blanked: its points are invalid in frame 2 and, tracked against it, in frames 3 and 4.
    Frame 4 (every:2) becomes the reference with them placed by interpolating their neighbours; tracked against
    frame 4's intact texture they are valid again, on the exact field (before, they stayed invalid for good).

    Measured against the previous rule on this sequence (20 frames; incremental, every:2, every:5, auto): on the
    points valid under both rules max |d params| = 0 and no status changed; 85 (incremental) and 80 (every:2)
    point-frames more are valid, every:5 and auto unchanged (their references avoid frame 2's patch)."""
    ref, frames = sequence
    frames = [f.copy() for f in frames[:8]]
    yy, xx = np.mgrid[:SHAPE[0], :SHAPE[1]]
    frames[1][(xx - 50) ** 2 + (yy - 46) ** 2 < 9 ** 2] = frames[1].mean()
    out = tmp_path / "r.h5"
    track_sequence(ref, frames, out, reference="every:2", step=8, device="cpu")
    res = read_results(out)
    lost = res.frames[1].valid & ~res.frames[2].valid  # the blanked patch's points
    assert 3 <= lost.sum() <= 10
    for k in (3, 4):
        assert not res.frames[k].valid[lost].any()
    pts = res.frames[1].points
    dist = np.min(np.hypot(*(pts[:, None, :] - pts[lost][None]).transpose(2, 0, 1)), axis=1)
    near = (dist <= 12) & ~lost  # the neighbours their reference position is interpolated from
    for k in (5, 6, 7, 8):
        f = res.frames[k]
        assert f.valid[lost].all(), k
        tu, tv = truth(k)(pts[:, 0], pts[:, 1])
        err = np.hypot(f.u - tu, f.v - tv)
        # as good as their neighbours (which carry the blanked patch's bias of frame 2: up to ~0.25 px) ...
        assert err[lost].max() <= err[near & f.valid].max(), k
        # ... and the points away from the patch are on the exact field
        assert np.sqrt(np.mean(err[f.valid & ~near & ~lost] ** 2)) < 0.02, k
    # counted where the reference position was interpolated (frames 5, 6 against frame 4), not once re-measured
    assert [res.frames[k].attrs["reference_interpolated"] for k in (5, 6, 7, 8)] == [lost.sum()] * 2 + [0, 0]


def test_fill_reference_interpolates_locally_and_says_where():
    from dic.correlation.lagrangian import fill_reference, moved_points

    x, y = np.meshgrid(np.arange(0.0, 100.0, 5.0), np.arange(0.0, 80.0, 5.0))
    pts = np.stack([x.ravel(), y.ravel()], 1)
    params = np.zeros((len(pts), 6))
    params[:, 0] = 0.02 * pts[:, 0] + 1.0  # u = 1 + 0.02 x (affine: linear interpolation exact)
    params[:, 1] = 0.02
    params[:, 3] = -0.01 * pts[:, 1]
    params[:, 5] = -0.01
    valid = np.ones(len(pts), bool)
    small = np.hypot(pts[:, 0] - 30, pts[:, 1] - 30) < 6  # a 3x3 hole: surrounded closely
    wide = np.hypot(pts[:, 0] - 75, pts[:, 1] - 45) < 26  # ~10 points across: wider than 4 spacings
    edge = pts[:, 0] == 0.0  # outside the valid points' hull
    valid[small | wide | edge] = False
    bad = params.copy()
    bad[~valid] = np.nan
    filled, supported = fill_reference(pts, bad, valid)
    assert supported[valid | small].all() and not supported[edge].any()
    centre = np.hypot(pts[:, 0] - 75, pts[:, 1] - 45) < 11  # > 3 spacings from any valid point
    assert centre.sum() == 13 and not supported[centre].any()
    inside = ~valid & ~edge
    assert np.allclose(filled[inside], params[inside], atol=1e-12)  # every parameter interpolated
    assert np.array_equal(filled[valid], bad[valid])
    assert np.all(np.isfinite(filled))
    # the same positions as moved_points (bitwise): the moved reference's POIs do not change
    assert np.array_equal(pts + filled[:, [0, 3]], moved_points(pts, bad[:, 0], bad[:, 3], valid))
    # a radius given in px
    assert not fill_reference(pts, bad, valid, radius=4.0)[1][small].any()
    for kw, msg in (({"valid": valid[:-1]}, "valid must be"), ({"radius": -1.0}, "radius"),
                    ({"params": bad[:, :5]}, "params"), ({"valid": np.zeros(len(pts), bool)}, "no valid point")):
        args = {"points0": pts, "params": bad, "valid": valid, **kw}
        with pytest.raises(ValueError, match=msg):
            fill_reference(**args)


@pytest.mark.parametrize("window, max_points", [(5, 50), (3, 37), (7, 200), (5, 10**6)])
def test_strain_in_bands_is_the_strain(window, max_points, monkeypatch):
    """Strain a band of grid rows at a time (bounded memory on huge grids) equals one call over the grid."""
    from types import SimpleNamespace

    from dic._strain import strain
    from dic.correlation.points import grid
    from dic.sequence.chunks import strain_in_bands

    rng = np.random.default_rng(window)
    pts = grid((200, 160), 4, margin=10)
    keep = ((pts[:, 0] - 80) ** 2 + (pts[:, 1] - 100) ** 2 > 30**2) & (rng.random(len(pts)) > 0.02)  # a hole
    pts = pts[keep][rng.permutation(int(keep.sum()))]  # and in no particular order
    x, y = pts.T
    field = SimpleNamespace(points=pts, u=1e-3 * x + 2e-5 * y**2 + rng.normal(0, 1e-3, len(x)),
                            v=-5e-4 * y + 1e-5 * x * y, valid=rng.random(len(x)) > 0.1)
    whole = strain(field, window=window)
    import sys

    sizes = []
    monkeypatch.setattr(sys.modules["dic._strain"], "strain", lambda f, window, **kw: sizes.append(len(f.points)) or strain(f, window=window, **kw))
    banded = strain_in_bands(field, window, max_points=max_points)
    if max_points < len(x):  # in bands, none of them the whole grid
        assert len(sizes) > 3 and max(sizes) < len(x) / 2, sizes
    else:
        assert sizes == [len(x)]
    for name in whole.COMPONENTS + ("valid", "n_fit", "points", "grid_index"):
        assert np.array_equal(getattr(banded, name), getattr(whole, name), equal_nan=True), name
    assert banded.grid_shape == whole.grid_shape and banded.step == whole.step and banded.window == window
    assert np.count_nonzero(whole.valid) > 0.7 * len(x)
    with pytest.raises(ValueError, match="max_points"):
        strain_in_bands(field, window, max_points=0)


@pytest.mark.parametrize("depth", [0, 1, 2])
def test_write_behind_holds_at_most_depth_plus_one_frames(depth):
    """WriteBehind: at most ``depth`` finished frames wait beside the one being written (0: none waits)."""
    import threading
    import time

    from dic.sequence.chunks import write_depth
    from dic.sequence.pipeline import WriteBehind

    gate = threading.Event()
    running, most, done = [0], [0], []
    lock = threading.Lock()

    def job(k):
        def run():
            gate.wait()
            done.append(k)
            with lock:
                running[0] -= 1
        return run

    wb = WriteBehind(depth=depth)
    submitted = []

    def producer():
        for k in range(6):
            with lock:
                running[0] += 1
                most[0] = max(most[0], running[0])
            wb.submit(job(k))
            submitted.append(k)

    t = threading.Thread(target=producer)
    t.start()
    time.sleep(0.5)  # the writer is stuck on the first job: the producer blocks once depth + 1 are pending
    assert len(submitted) == depth + 1
    gate.set()
    t.join()
    wb.close()
    assert done == list(range(6)) and most[0] <= depth + 2  # + the one the producer holds while it waits
    assert write_depth(40401, 1, 2 << 30) == 2 and write_depth(16_703_569, 1, 2 << 30) == 0


def test_chunks_filter_the_reference_image_once(sequence, tmp_path, monkeypatch):
    """The implausible-warp check's textured fractions are computed once per reference, not per chunk and
    frame (each computation filters the whole reference image: 3.5 GB at 8192 x 8192); same results."""
    from dic.correlation import plausibility
    from dic.sequence.chunks import bytes_per_poi

    calls = []
    real = plausibility.textured_fraction
    monkeypatch.setattr(plausibility, "textured_fraction", lambda *a, **k: calls.append(len(a[1])) or real(*a, **k))
    ref, frames = sequence
    track_sequence(ref, frames[:4], tmp_path / "whole.h5", step=8, device="cpu")
    assert calls == [120]
    calls.clear()
    track_sequence(ref, frames[:4], tmp_path / "chunked.h5", step=8, device="cpu", max_memory=37 * bytes_per_poi(1))
    assert calls == [120]  # all 120 POIs once, for 4 frames of 4 chunks each
    _same_frames(tmp_path / "whole.h5", tmp_path / "chunked.h5")


def test_strain_in_bands_refuses_what_is_not_a_field():
    from dic.sequence.chunks import strain_in_bands

    with pytest.raises(ValueError, match="needs a 2-D field"):
        strain_in_bands(np.zeros((4, 2)), 5)


def test_a_false_match_is_no_anchor_of_a_moved_reference(sequence, tmp_path):
    """A false match (valid, ZNCC fine, a whole pixel off; seen on the evolving-texture benchmark where a subset
    converged to the wrong speckle) in the frame that becomes the reference must not be composed into every later
    frame. Frame 2's result at one point is shifted by 1 px (as a false match would be); every:2 moves the
    reference to frame 2. Before the fix the point kept the 1 px error in frames 3-8 (it anchored the moved
    reference); now the normalised median test finds it, the reference places it by interpolating its
    neighbours, and it is tracked again on the exact field."""
    from dic._track import Tracker

    ref, frames = sequence
    frames = [f.copy() for f in frames[:8]]
    calls = {"n": 0}
    victim = {}

    def make_tracker(image, points):
        tracker = Tracker(image, step=8, device="cpu") if points is None else Tracker(image, points=points, device="cpu")
        track = tracker.track

        def corrupted(current, **kw):
            field = track(current, **kw)
            calls["n"] += 1
            if calls["n"] == 2:  # frame 2, against the reference image
                j = victim.setdefault("j", int(np.flatnonzero(field.valid)[len(field.u) // 2]))
                field.u[j] += 1.0
                field.params[j, 0] += 1.0
            return field

        tracker.track = corrupted
        return tracker

    out = tmp_path / "r.h5"
    track_sequence(ref, frames, out, reference="every:2", make_tracker=make_tracker, points=None, order=1,
                   strain_window=0)
    res = read_results(out)
    j = victim["j"]
    pts = res.frames[1].points
    assert res.frames[2].valid[j]  # the false match itself is reported as it came (a plain tracker)
    for k in range(3, 9):
        f = res.frames[k]
        tu, tv = truth(k)(pts[:, 0], pts[:, 1])
        assert f.valid[j], k
        assert abs(f.u[j] - tu[j]) < 0.05 and abs(f.v[j] - tv[j]) < 0.05, (k, f.u[j] - tu[j])


def test_normalised_median_test_flags_false_matches_not_smooth_fields_or_cracks():
    from dic.correlation.lagrangian import displacement_outliers

    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:30, 0:40] * 5.0
    pts = np.column_stack([x.ravel(), y.ravel()])
    u = 0.3 + 0.01 * pts[:, 0] - 0.004 * pts[:, 1] + rng.normal(0, 0.005, len(pts))
    v = -0.2 + 0.002 * pts[:, 0] + 0.02 * pts[:, 1] + rng.normal(0, 0.005, len(pts))
    valid = np.ones(len(pts), bool)
    assert not displacement_outliers(pts, u, v, valid).any()  # a smooth (linear) field: nothing
    crack = u + np.where(pts[:, 0] > 100, 2.0, 0.0)  # a 2 px opening along x = 100
    assert not displacement_outliers(pts, crack, v, valid).any()  # a real discontinuity is not an outlier
    bad = [37, 410, 777]
    u2, v2 = u.copy(), v.copy()
    u2[bad[0]] += 1.0
    v2[bad[1]] -= 0.5
    u2[bad[2]] += 0.3
    out = displacement_outliers(pts, u2, v2, valid)
    assert set(np.flatnonzero(out)) == set(bad)
    valid[bad[0]] = False  # invalid points are never flagged, and do not count as neighbours
    assert not displacement_outliers(pts, u2, v2, valid)[bad[0]]
    from dic.correlation.lagrangian import _median_rows

    for k in (3, 4, 7, 8):  # the partial-sort median is numpy's, odd and even counts, ties included
        a = np.round(rng.normal(size=(500, k, 2)), 1)
        assert np.array_equal(_median_rows(a), np.median(a, axis=1)), k
    with pytest.raises(ValueError, match="neighbours"):
        displacement_outliers(pts, u, v, valid, neighbours=2)
    with pytest.raises(ValueError, match="threshold"):
        displacement_outliers(pts, u, v, valid, threshold=0)
    with pytest.raises(ValueError, match="points"):
        displacement_outliers(pts[:5], u, v, valid)


def test_tracker_check_outliers_flags_a_false_match(sequence, monkeypatch):
    from dic._track import Tracker
    from kernels.conventions import Status

    ref, frames = sequence
    cur = np.clip(np.round(frames[0]), 0, 255).astype(np.uint8)  # the device-resident frame path
    plain = Tracker(ref, step=8, robust=False, device="cpu")
    checked = Tracker(ref, step=8, robust=False, check_outliers=True, device="cpu")
    assert not plain.check_outliers  # off without robust IC-GN, on with it (True or "adaptive", the default)
    assert Tracker(ref, step=8, robust=True, device="cpu").check_outliers and Tracker(ref, step=8).check_outliers
    j = checked.n_points // 2
    for tr in (plain, checked):
        run = tr.correlator.run_frame

        def corrupt(frame, guess, name="current", run=run):
            r = run(frame, guess, name)
            r["params"][j, 0] += 1.0  # a false match a whole pixel off
            return r

        monkeypatch.setattr(tr.correlator, "run_frame", corrupt)
    fp, fc = plain.track(cur), checked.track(cur)
    assert fp.valid[j] and not fc.valid[j] and fc.status[j] == int(Status.NEIGHBOUR_OUTLIER)
    others = np.arange(len(fc.u)) != j
    assert np.array_equal(fp.valid[others], fc.valid[others])  # nothing else flagged
    with pytest.raises(ValueError, match="check_outliers"):
        Tracker(ref, step=8, check_outliers="yes")


def test_strain_grid_worked_out_once_and_the_strain_unchanged(sequence, tmp_path, monkeypatch):
    """The strain's grid layout is computed once per sequence (not per frame: dic.StrainPlan), and
    each frame's strain in the file is bit for bit dic.strain of that frame's field, also when the
    valid points change from frame to frame (a flat patch in some frames: its POIs are invalid there)."""
    import sys

    from dic._strain import strain

    strain_module = sys.modules["dic._strain"]
    ref, frames = sequence
    frames = [f.copy() for f in frames[:6]]
    frames[1][20:60, 30:70] = 128.0  # invalid POIs in frames 2, 4 and 5
    frames[3][20:60, 30:70] = 128.0
    frames[4][40:90, 10:50] = 128.0
    calls = []
    layout = strain_module.grid_layout
    monkeypatch.setattr(strain_module, "grid_layout", lambda p, **kw: calls.append(len(p)) or layout(p, **kw))
    out = tmp_path / "s.h5"
    track_sequence(ref, frames, out, step=8, device="cpu")
    assert len(calls) == 1  # once for the sequence, not once per frame as well
    res = read_results(out)
    masks = {k: res.frames[k].valid.tobytes() for k in res.frames}
    assert 3 <= len(set(masks.values())) < len(masks)  # the cached fits recomputed, and reused
    for k, f in res.frames.items():
        s = strain(f, window=5)
        assert f.strain["window"] == 5 and tuple(f.strain["step"]) == s.step
        for name in [n for n in f.strain if n not in ("window", "step")]:
            want = np.asarray(getattr(s, name))
            assert f.strain[name].dtype == want.dtype and f.strain[name].tobytes() == want.tobytes(), (k, name)
