"""The stereo tracks on the device frame path, the correlate() hooks they use, and the reference match's progress.

* ``correlate(first=...)``: a first pass handed in (IC-GN over every POI, e.g. ``Correlator.run_frame``)
  gives bitwise the result of ``correlate`` running that pass itself (indexed IC-GN from the same guesses).
* ``correlate(max_fruitless_rounds=...)`` stops asking a fallback that accepts nothing.
* ``StereoCorrelation(progress=...)``: the reference match reports its stages; a tqdm bar on request.
* ``StereoCorrelation.measure``: the frame trackers are built once per reference and frame dtype; each image is
  phase-correlated from its spectrum computed once; 8-bit and
  float32 frames give the same bits.
"""
import numpy as np
import pytest

from dic.correlation.engine import SOURCE_PREVIOUS, Correlator, correlate
from dic.correlation.points import grid_points
from dic.synth import speckle_pair
from kernels.icgn import n_params, prepare_current

FIELDS = ("params", "zncc", "iterations", "icgn_status", "accepted", "source", "extra_failed", "implausible")


@pytest.fixture(scope="module")
def pair():
    # 1.5 px shift plus a 1 % stretch: most POIs converge from zero, a few need the neighbours' help
    ref, cur = speckle_pair((200, 240), lambda x, y: (1.5 + 0.01 * (x - 120), -0.7 + 0 * y), seed=11, bits=8)
    assert np.array_equal(cur, np.round(cur)) and cur.max() <= 255  # 8-bit grey levels, held as float32
    return ref, cur.astype(np.uint8)


def _correlator(ref, order=2):
    pts = grid_points(ref.shape, 8, 21, None)[0]
    return Correlator(ref.astype(np.float32), pts, subset=21, order=order, max_iter=50, tol=1e-3, device="cpu")


@pytest.mark.parametrize("order", [1, 2])
def test_first_pass_from_the_frame_path_is_bitwise_the_indexed_pass(pair, order):
    ref, cur = pair
    corr = _correlator(ref, order)
    n, k = corr.n_points, n_params(order)
    guess = np.zeros((n, k))
    has = np.ones(n, dtype=bool)
    has[::7] = False  # POIs without a guess: left to the propagation in both runs
    eligible = np.ones(n, dtype=bool)
    eligible[::5] = False
    kw = dict(eligible=eligible, zncc_min=0.8, radius=12.5, check_warps=True)
    host = correlate(corr, prepare_current(cur.astype(np.float32), device="cpu"), guess, has, SOURCE_PREVIOUS, **kw)
    first = corr.run_frame(cur, guess)  # uint8 frame, converted in the prefilter
    dev = correlate(corr, corr.frame_current(cur.dtype), guess, has, SOURCE_PREVIOUS, first=first, **kw)
    for name in FIELDS:
        a, b = getattr(host, name), getattr(dev, name)
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), name
    assert np.count_nonzero(host.accepted) > 0.8 * np.count_nonzero(eligible & corr.ready)
    with pytest.raises(ValueError, match="first must hold the results of all"):
        correlate(corr, corr.frame_current(cur.dtype), guess, has, SOURCE_PREVIOUS,
                  first={key: v[:-1] for key, v in first.items()}, **kw)


def test_fruitless_fallback_rounds_stop_early(pair):
    ref, _ = pair
    corr = _correlator(ref, 1)
    n, k = corr.n_points, n_params(1)
    rng = np.random.default_rng(0)
    noise = rng.uniform(0, 255, ref.shape).astype(np.float32)  # nothing in it matches the reference
    calls = []

    def fallback(idx):
        calls.append(idx.size)
        return np.zeros((idx.size, k)), np.ones(idx.size, dtype=bool)

    kw = dict(eligible=np.ones(n, dtype=bool), zncc_min=0.8, radius=12.5, fallback=fallback, max_seeds=8,
              second_opinion=False)
    cur = prepare_current(noise, device="cpu")
    none = correlate(corr, cur, np.zeros((n, k)), np.zeros(n, dtype=bool), SOURCE_PREVIOUS, **kw)
    rounds_all = len(calls)
    calls.clear()
    one = correlate(corr, cur, np.zeros((n, k)), np.zeros(n, dtype=bool), SOURCE_PREVIOUS, max_fruitless_rounds=1,
                    **kw)
    assert rounds_all == 9 and len(calls) == 1  # max_fallback_rounds + 1 rounds, against one
    assert not np.any(none.accepted) and not np.any(one.accepted)


def test_fallback_that_succeeds_is_not_stopped(pair):
    """A round that accepts something resets the count: the rounds go on as long as they help."""
    ref, cur = pair
    corr = _correlator(ref, 1)
    n, k = corr.n_points, n_params(1)
    calls = []

    def fallback(idx):
        calls.append(idx.size)
        g = np.zeros((idx.size, k))
        g[:, 0], g[:, 3] = 1.5, -0.7
        return g, np.ones(idx.size, dtype=bool)

    res = correlate(corr, prepare_current(cur.astype(np.float32), device="cpu"), np.zeros((n, k)),
                    np.zeros(n, dtype=bool), SOURCE_PREVIOUS, eligible=np.ones(n, dtype=bool), zncc_min=0.8,
                    radius=12.5, fallback=fallback, max_seeds=4, max_fruitless_rounds=1)
    assert len(calls) >= 1
    assert np.count_nonzero(res.accepted) > 0.8 * np.count_nonzero(corr.ready)


def test_correlate_reports_its_stages(pair):
    ref, cur = pair
    corr = _correlator(ref, 1)
    n, k = corr.n_points, n_params(1)
    seen = []
    correlate(corr, prepare_current(cur.astype(np.float32), device="cpu"), np.zeros((n, k)), np.ones(n, dtype=bool),
              SOURCE_PREVIOUS, eligible=np.ones(n, dtype=bool), zncc_min=0.8, radius=12.5,
              report=lambda stage, acc, settled: seen.append((stage, acc, settled)))
    stages = [s for s, _, _ in seen]
    assert stages[0] == "first pass" and stages[-1] == "done"
    eligible = int(np.count_nonzero(corr.ready))
    assert seen[-1][2] == eligible and 0 < seen[-1][1] <= eligible
    assert all(a <= s <= eligible for _, a, s in seen)


def test_frames_limited_to_some_pois_give_their_results_bit_for_bit_and_skip_the_others(pair):
    """Correlator.limit_frames: the active POIs' first pass is bitwise the unrestricted one; the others come back
    NOT_COMPUTED after no iteration; the same POIs again keep the tracker (its buffers), all POIs lift the limit."""
    from kernels.conventions import Status

    ref, cur = pair
    corr = _correlator(ref, 2)
    n, k = corr.n_points, n_params(2)
    guess = np.zeros((n, k))
    full = corr.run_frame(cur, guess)
    active = np.zeros(n, dtype=bool)
    active[::3] = True
    corr.limit_frames(active)
    part = corr.run_frame(cur, guess)
    ran = active & corr.ready
    assert np.count_nonzero(ran) > 0.25 * n
    for name in ("params", "zncc", "iterations", "status"):
        a, b = full[name][ran], part[name][ran]
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), name
    skipped = ~active & corr.ready
    assert np.all(part["status"][skipped] == int(Status.NOT_COMPUTED)) and not part["iterations"][skipped].any()
    assert np.all(full["iterations"][skipped] > 0)  # they cost iterations when not skipped
    assert np.array_equal(corr.ready, corr.reference_status == int(Status.CONVERGED))  # reference subsets untouched
    tracker = corr._frames[cur.dtype]
    corr.limit_frames(active.copy())
    corr.run_frame(cur, guess)
    assert corr._frames[cur.dtype] is tracker  # the same POIs: the tracker (and its buffers) kept
    corr.limit_frames(np.ones(n, dtype=bool))
    again = corr.run_frame(cur, guess)
    for name in ("params", "zncc", "iterations", "status"):
        assert np.array_equal(full[name], again[name], equal_nan=full[name].dtype.kind == "f"), name
    with pytest.raises(ValueError, match="active must be"):
        corr.limit_frames(active[:-1])


@pytest.fixture(scope="module")
def lab():
    """Two 320x240 views of a speckled plane (as tests/dic/test_stereo_dic.py, 4 samples per pixel), moved 1 mm."""
    from dataclasses import replace

    from dic.lab import Displacement, LabCamera, Scene, SpecklePlane, render, stereo_rig
    from dic.synth import make_speckle

    cams = [LabCamera.from_lens(name=name, size=(320, 240), focal_length_mm=12.0, f_number=float("inf"),
                                focus_distance_mm=1000.0, position=(x, 0.0, 0.0), look_at_point=(0.0, 0.0, 1000.0),
                                exposure_dn=200.0, bit_depth=8)
            for name, x in (("left", -150.0), ("right", 150.0))]
    speckle = make_speckle(region=(-5, -5, 305, 255), radius=1.2, density=0.5, bits=None, seed=3)
    plane = SpecklePlane.facing(center=(0.0, 0.0, 1000.0), normal=(0.0, 0.0, -1.0), size=(300.0, 250.0),
                                speckle=speckle)
    t_local = plane.R_world_surface.T @ np.array([1.0, -0.5, 2.0])
    moved = replace(plane, displacement=Displacement(np.broadcast_to(t_local, (2, 2, 3)).copy(), (0.0, 0.0),
                                                     (300.0, 250.0)))
    states = [tuple(render(Scene(cameras=cams, planes=[p]), i, samples=4, seed=10 * k + i) for i in range(2))
              for k, p in enumerate((plane, moved))]
    left, right = cams
    return stereo_rig(left, right), states


def test_reference_match_reports_progress(lab):
    from dic._stereo import StereoCorrelation

    rig, states = lab
    seen = []
    sc = StereoCorrelation(rig, *states[0], step=10, device="cpu",
                           progress=lambda stage, done, total: seen.append((stage, done, total)))
    stages = [s for s, _, _ in seen]
    assert stages[0] == "features" and stages[1].startswith("features (") and "first pass" in stages
    assert stages[-1] == "done"
    total = seen[0][2]
    assert total == np.count_nonzero(sc.in_roi & sc.left.ready) and seen[-1][1] == total
    assert all(0 <= d <= t == total for _, d, t in seen)
    assert [d for _, d, _ in seen] == sorted(d for _, d, _ in seen)  # never goes back
    quiet = StereoCorrelation(rig, *states[0], step=10, device="cpu", match=sc.match)
    assert np.array_equal(quiet.reference.status, sc.reference.status)
    with pytest.raises(ValueError, match="progress must be None, a bool or a callable"):
        StereoCorrelation(rig, *states[0], step=10, device="cpu", progress="yes")


def test_reference_match_progress_bar(lab, capsys):
    from dic._stereo import StereoCorrelation

    rig, states = lab
    StereoCorrelation(rig, *states[0], step=20, device="cpu", progress=True)
    err = capsys.readouterr().err
    assert "stereo match" in err and "POI" in err


def test_tracks_reuse_their_frame_buffers_and_8_bit_frames_equal_float(lab):
    from dic._stereo import StereoCorrelation

    rig, states = lab
    (l0, r0), (l1, r1) = states
    assert l1.dtype == np.uint8
    a = StereoCorrelation(rig, l0, r0, step=10, device="cpu")
    fa = a.measure(l1, r1, index=1)
    trackers = (dict(a.left._frames), dict(a.right._frames))
    assert list(trackers[0]) == [np.dtype(np.uint8)] and list(trackers[1]) == [np.dtype(np.uint8)]
    fa2 = a.measure(l1, r1, index=2, use_previous=False)
    assert a.left._frames == trackers[0] and a.right._frames == trackers[1]  # the same trackers: no new buffers
    b = StereoCorrelation(rig, l0, r0, step=10, device="cpu", match=a.match)
    fb = b.measure(l1.astype(np.float32), r1.astype(np.float32), index=1)
    assert list(b.left._frames) == [np.dtype(np.float32)]
    for name in ("U", "V", "W", "exx", "zncc_left", "zncc_right", "status"):
        x, y = getattr(fa, name), getattr(fb, name)
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), name
    assert np.count_nonzero(fa.valid) > 0.8 * np.count_nonzero(a.match.valid)
    assert np.count_nonzero(fa2.valid) > 0.8 * np.count_nonzero(a.match.valid)  # from zero guess: same trackers


def test_each_image_is_transformed_once_for_the_global_shift(lab, monkeypatch):
    """The global shift of a state's guess correlates each camera's previous image with its current one: the
    previous image's spectrum is the one kept from the state before, so a state transforms two images, not four,
    and the fields are bitwise those of transforming every image every time."""
    import dic._stereo as stereo_module
    from kernels.search import phase_spectrum

    rig, states = lab
    (l0, r0), (l1, r1) = states
    transformed = []

    def counting(image):
        transformed.append(image.shape)
        return phase_spectrum(image)

    monkeypatch.setattr(stereo_module, "phase_spectrum", counting)
    # every state's start from the global shift (with the constant-velocity start, state 2 would first try twice
    # state 1's motion, and a camera whose prediction holds measures no shift)
    kept = stereo_module.StereoCorrelation(rig, l0, r0, step=10, device="cpu", motion_prediction="none")
    kept_fields = [kept.measure(l1, r1, index=1)]
    assert len(transformed) == 4  # the reference pair (the first state's base) and the current pair
    kept_fields.append(kept.measure(l0, r0, index=2))  # back to the reference position: a shift from state 1
    assert len(transformed) == 6  # only the new pair: state 1's images were kept
    monkeypatch.setattr(stereo_module._SpectrumMemo, "__call__", lambda self, image: phase_spectrum(image))
    every = stereo_module.StereoCorrelation(rig, l0, r0, step=10, device="cpu", match=kept.match,
                                            motion_prediction="none")
    every_fields = [every.measure(l1, r1, index=1), every.measure(l0, r0, index=2)]
    for a, b in zip(kept_fields, every_fields):
        for name in ("U", "V", "W", "exx", "zncc_left", "zncc_right", "status"):
            x, y = getattr(a, name), getattr(b, name)
            assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), name
        assert np.count_nonzero(a.valid) > 0.8 * np.count_nonzero(kept.match.valid)
