"""The device-resident frame path (issue 16): kernels.frames.FrameTracker and icgn_batch give today's results bit
for bit (Tracker.track / icgn with the same propagated guesses), allocate no Warp memory per frame after the
first, and refuse bad frames with a clear ValueError."""
import numpy as np
import pytest
import warp as wp

from dic._track import Tracker
from dic.synth import speckle_pair
from kernels.conventions import Status
from kernels.frames import FrameTracker, icgn_batch, zncc_threshold32
from kernels.icgn import icgn, prepare_current

SHAPE = (72, 88)
N_FRAMES = 5
ZNCC_MIN = 0.8
GOOD = (int(Status.CONVERGED), int(Status.MAX_ITERATIONS))


def _motion(k):
    return lambda x, y: (0.45 * k + 0.004 * k * (x - 44), -0.3 * k + 0.003 * k * (y - 36))


@pytest.fixture(scope="module", params=[8, 16])
def sequence(request):
    bits = request.param
    ref, _ = speckle_pair(SHAPE, (0, 0), seed=7, bits=bits)
    frames = [speckle_pair(SHAPE, _motion(k), seed=7, bits=bits)[1] for k in range(1, N_FRAMES + 1)]
    frames[2] = frames[2].copy()
    frames[2][30:50, 40:70] = np.round(frames[2][30:50, 40:70].mean())  # a flat patch: some POIs fail and keep their guess
    return bits, ref, frames


@pytest.fixture(scope="module")
def points():
    ys, xs = np.mgrid[10:63:6, 10:79:6]
    return np.c_[xs.ravel() + 0.25, ys.ravel() - 0.5].astype(np.float64)


def _tracker(ref, points, order):
    # plain IC-GN (robust=False; the default, "adaptive", refines the subsets whose residuals show outliers):
    # the results of the FrameTracker compared with it
    return Tracker(ref, points=points, subset=17, order=order, check_warps=False, zncc_min=ZNCC_MIN, robust=False,
                   device="cpu")


def _today(tracker, frames):
    """Today's path: Tracker.track per frame, the guess taken from the previous frame where it is valid. Frames
    go as float64, which Tracker.track converts and checks on the host, then ``prepare_current`` + ``icgn``
    (uint8/uint16/float32 arrays now take the device-resident path)."""
    n, k = tracker.n_points, 6 * tracker.order
    g = np.zeros((n, k))
    out = []
    for fr in frames:
        f = tracker.track(fr.astype(np.float64), guess=g, search=None)
        out.append(f)
        valid = np.isin(f.status, GOOD) & (f.zncc >= ZNCC_MIN)
        g = np.where(valid[:, None], f.params, g)
    return out


def _as(frame, dtype):
    return frame.astype(dtype) if dtype != np.float32 else frame.astype(np.float32)


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("kind", ["float32", "int", "packed"])
def test_frame_tracker_equals_todays_path(sequence, points, order, kind):
    bits, ref, frames = sequence
    tracker = _tracker(ref, points, order)
    today = _today(tracker, frames)
    dtype = np.float32 if kind == "float32" else (np.uint8 if bits == 8 else np.uint16)
    ft = FrameTracker(tracker.correlator.subsets, dtype, zncc_min=ZNCC_MIN, packed=kind == "packed")
    statuses = set()
    for f, fr in zip(today, frames):
        r = ft.track(_as(fr, dtype))
        assert r["params"].dtype == np.float32 and r["status"].dtype == np.int32
        assert np.array_equal(r["params"].astype(np.float64), f.params, equal_nan=True)
        assert np.array_equal(r["zncc"].astype(np.float64), f.zncc, equal_nan=True)
        assert np.array_equal(r["iterations"], f.iterations)
        assert np.array_equal(r["status"], f.status)
        statuses.update(np.unique(f.status).tolist())
    assert int(Status.CONVERGED) in statuses and len(statuses) > 1  # the sequence exercises the propagation rule
    assert ft.frames_tracked == N_FRAMES


@pytest.mark.parametrize("order", [1, 2])
def test_tracker_takes_the_device_resident_path_bitwise(sequence, points, order, monkeypatch):
    """Tracker.track of 8/16-bit and float32 arrays without a search runs through Correlator.run_frame (the
    device-resident path) and returns the Field2D of the general path (acceptance, implausible warps, sigma)."""
    import dic.correlation.engine as engine

    bits, ref, frames = sequence
    dtype = np.uint8 if bits == 8 else np.uint16
    general = Tracker(ref, points=points, subset=17, order=order, zncc_min=ZNCC_MIN, device="cpu")
    resident = Tracker(ref, points=points, subset=17, order=order, zncc_min=ZNCC_MIN, device="cpu")
    calls = []
    real = engine.Correlator.run_frame
    monkeypatch.setattr(engine.Correlator, "run_frame", lambda self, *a, **kw: calls.append(1) or real(self, *a, **kw))
    g = None
    for fr in frames[:3]:
        a = general.track(fr.astype(np.float64), guess=g)
        for cur in (_as(fr, dtype), fr.astype(np.float32)):
            b = resident.track(cur, guess=g)
            for name in ("u", "v", "params", "zncc", "iterations", "status", "valid", "sigma_u", "sigma_v"):
                assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=True), name
            assert a.noise_sigma == b.noise_sigma
        g = a
    assert len(calls) == 6
    bad = frames[0].astype(np.float32)
    bad[3, 3] = np.nan
    with pytest.raises(ValueError, match="current contains NaN or infinite values"):
        resident.track(bad)
    with pytest.raises(ValueError, match="shape"):
        resident.track(_as(frames[0], dtype)[1:])


def test_frame_tracker_reads_arrays_tensors_and_strided_frames_alike(sequence, points):
    torch = pytest.importorskip("torch")
    bits, ref, frames = sequence
    tracker = _tracker(ref, points, 1)
    dtype = np.uint8 if bits == 8 else np.uint16
    expected = [FrameTracker(tracker.correlator.subsets, dtype).track(_as(fr, dtype)) for fr in frames[:1]]
    for make in (lambda a: wp.array(a, device="cpu"), lambda a: torch.from_numpy(a.astype(np.int32)).to(
                 torch.uint8 if dtype == np.uint8 else torch.uint16), lambda a: np.asfortranarray(a)):
        ft = FrameTracker(tracker.correlator.subsets, dtype)
        r = ft.track(make(_as(frames[0], dtype)))
        for name in expected[0]:
            assert np.array_equal(r[name], expected[0][name], equal_nan=True), name
    # results on the device, as Warp arrays and as torch tensors (no host copy), equal the host results
    ft = FrameTracker(tracker.correlator.subsets, dtype)
    dev = ft.track_device(_as(frames[0], dtype))
    assert isinstance(dev.params, wp.array)
    assert np.array_equal(dev.params.numpy(), expected[0]["params"], equal_nan=True)
    ft.reset()
    t = ft.track_torch(_as(frames[0], dtype))
    assert isinstance(t["params"], torch.Tensor)
    assert np.array_equal(t["status"].numpy(), expected[0]["status"])


@pytest.mark.parametrize("order", [1, 2])
def test_batched_launch_equals_per_frame_launches(sequence, points, order):
    bits, ref, frames = sequence
    tracker = _tracker(ref, points, order)
    subsets = tracker.correlator.subsets
    n, k = subsets.n_points, 6 * order
    rng = np.random.default_rng(3)
    guesses = np.zeros((len(frames), n, k))
    guesses[:, :, 0] = rng.uniform(0, 2, (len(frames), n))
    currents = [prepare_current(fr, device="cpu") for fr in frames]
    batched = icgn_batch(subsets, currents, guesses)
    shared = icgn_batch(subsets, currents, guesses[1])
    for f, cur in enumerate(currents):
        one = icgn(subsets, cur, guess=guesses[f]).numpy()
        same = icgn(subsets, cur, guess=guesses[1]).numpy()
        for name in one:
            assert np.array_equal(batched[f].numpy()[name], one[name], equal_nan=True), (f, name)
            assert np.array_equal(shared[f].numpy()[name], same[name], equal_nan=True), (f, name)
    # FrameTracker.track_batch: frames of a batch share the propagated guess
    ft = FrameTracker(subsets, np.float32, batch=3)
    first = ft.track_batch(frames[:3])
    for f in range(3):
        one = icgn(subsets, currents[f]).numpy()
        for name in one:
            assert np.array_equal(first[f][name], one[name], equal_nan=True), (f, name)
    g = np.zeros((n, k), np.float32)
    for r in first:  # each POI's last valid result, in order
        valid = np.isin(r["status"], GOOD) & (r["zncc"] >= zncc_threshold32(ZNCC_MIN))
        g = np.where(valid[:, None], r["params"], g)
    assert np.array_equal(ft.guess, g)


@pytest.fixture
def allocations(monkeypatch):
    """Every Warp allocation: ``wp.array`` gets its memory from ``Device.get_allocator`` (warp/_src/types.py,
    ``array._init_new``; CPU, pinned and CUDA alike, custom CUDA allocators included), and views, ``ptr=``
    wrappers, ``wp.from_torch`` and launches never call it."""
    import warp._src.context as ctx

    seen = []
    real = ctx.Device.get_allocator

    def counting(self, pinned=False):
        seen.append((str(self), pinned))
        return real(self, pinned)

    monkeypatch.setattr(ctx.Device, "get_allocator", counting)
    return seen


def test_the_hook_sees_allocations(allocations):
    wp.empty(3, dtype=wp.float32, device="cpu")
    wp.zeros((2, 2), dtype=wp.int32, device="cpu")
    wp.array(np.ones(4, np.float32), device="cpu")
    assert len(allocations) == 3


@pytest.mark.parametrize("packed", [False, True])
def test_no_allocation_per_frame_after_the_first(sequence, points, allocations, packed):
    torch = pytest.importorskip("torch")
    bits, ref, frames = sequence
    dtype = np.uint8 if bits == 8 else np.uint16
    tracker = _tracker(ref, points, 2)
    ft = FrameTracker(tracker.correlator.subsets, dtype, packed=packed, batch=2)
    ints = [_as(fr, dtype) for fr in frames]
    ft.track(ints[0])  # compiles and loads the kernels
    ft.track_batch(ints[:2])
    ft.track_device(ints[0])
    allocations.clear()
    for fr in ints[1:]:
        ft.track(fr)
        ft.track(np.asfortranarray(fr))
    ft.track_batch(ints[1:3])
    ft.track_device(ints[3])
    ft.track_torch(torch.from_numpy(ints[4].astype(np.int32)).to(torch.uint8 if bits == 8 else torch.uint16))
    ft.reset(np.zeros((ft.n_points, 12)))
    assert allocations == []


def test_bad_frames_are_refused(sequence, points):
    bits, ref, frames = sequence
    tracker = _tracker(ref, points, 1)
    subsets = tracker.correlator.subsets
    with pytest.raises(ValueError, match="frame_dtype"):
        FrameTracker(subsets, np.float64)
    with pytest.raises(ValueError, match="batch"):
        FrameTracker(subsets, np.float32, batch=0)
    with pytest.raises(ValueError, match="guess"):
        FrameTracker(subsets, np.float32, guess=np.zeros((3, 6)))
    ft = FrameTracker(subsets, np.float32, zncc_min=ZNCC_MIN, batch=2)
    good = frames[0].astype(np.float32)
    with pytest.raises(ValueError, match="shape"):
        ft.track(good[:-1])
    with pytest.raises(ValueError, match="dtype"):
        ft.track(good.astype(np.float64))
    with pytest.raises(ValueError, match="NumPy array"):
        ft.track(good.tolist())
    with pytest.raises(ValueError, match="1 to 2 frames"):
        ft.track_batch([good] * 3)
    first = ft.track(good)
    before = ft.guess
    for value in (np.nan, np.inf, -np.inf):
        bad = good.copy()
        bad[5, 7] = value
        with pytest.raises(ValueError, match="NaN or infinite"):
            ft.track(bad)
        with pytest.raises(ValueError, match=r"frames\[1\]"):
            ft.track_batch([good, bad])
        assert np.array_equal(ft.guess, before)  # a refused frame passes nothing on
    with pytest.raises(ValueError, match="NaN or infinite"):
        ft.track_device(bad)
    assert np.array_equal(ft.guess, before)
    again = ft.track(good)  # still tracking from the last good frame's result
    expected = icgn(subsets, good, guess=before).numpy()
    for name in again:
        assert np.array_equal(again[name], expected[name], equal_nan=True)
    assert first["params"].shape == again["params"].shape


def test_zncc_threshold_matches_the_host_acceptance():
    for zmin in (0.8, 0.9, 0.95, 1 / 3, -0.25, 0.0, 1.0):
        t = np.float32(zncc_threshold32(zmin))
        zs = np.array([np.nextafter(t, np.float32(-1)), t, np.nextafter(t, np.float32(2))], np.float32)
        assert np.array_equal(zs >= t, zs.astype(np.float64) >= zmin)


def test_prepare_current_reuses_its_buffers(sequence, allocations):
    """Today's path too: ``prepare_current(image, out=previous)`` reuses the coefficient buffer (it was allocated
    per frame) and, on the CPU, reads the float32 image in place (it was copied into a new Warp array)."""
    _, _, frames = sequence
    first = prepare_current(frames[0], device="cpu")
    fresh = prepare_current(frames[1], device="cpu")
    allocations.clear()
    again = prepare_current(frames[1], device="cpu", out=first)
    assert allocations == []
    assert again.coef.ptr == first.coef.ptr and again.rows4.ptr == first.rows4.ptr
    assert np.array_equal(again.rows4.numpy(), fresh.rows4.numpy())


def test_graph_capture_is_cuda_only_and_results_view_the_last_frame(sequence, points):
    """``capture_graph`` (the CUDA-graph replay that bench.gpu times) refuses the CPU with a clear message;
    ``results`` and ``frame_buffer`` are the device views a replay reads and writes."""
    bits, ref, frames = sequence
    subsets = _tracker(ref, points, 1).correlator.subsets
    dtype, wdt = (np.uint8, wp.uint8) if bits == 8 else (np.uint16, wp.uint16)
    ft = FrameTracker(subsets, dtype)
    with pytest.raises(ValueError, match="CUDA graphs need a CUDA device"):
        ft.capture_graph()
    got = ft.track(frames[0].astype(dtype))
    assert ft.frame_buffer.shape == SHAPE and ft.frame_buffer.dtype == wdt
    for name in got:
        assert np.array_equal(getattr(ft.results, name).numpy(), got[name], equal_nan=True)


@pytest.mark.parametrize("order", [1, 2])
def test_both_layouts_give_the_same_bits(sequence, points, order):
    """The "plain" layout (the CPU default: coefficients read in place through a vec4 view with a 4-byte stride, no
    expansion pass) and the row-expanded copy run the same compiled kernels: every result the same bits, batched
    launches and the host-path current of the last frame (FrameTracker.current) included."""
    bits, ref, frames = sequence
    subsets = _tracker(ref, points, order).correlator.subsets
    dtype = np.uint8 if bits == 8 else np.uint16
    plain = FrameTracker(subsets, dtype, zncc_min=ZNCC_MIN, layout="plain", batch=2)
    rows4 = FrameTracker(subsets, dtype, zncc_min=ZNCC_MIN, layout="rows4", batch=2)
    assert FrameTracker(subsets, dtype).layout == "plain"  # the CPU default
    assert plain.layout == "plain" and plain._expanded is None and rows4._expanded is not None
    for fr in frames[:3]:
        a, b = plain.track(_as(fr, dtype)), rows4.track(_as(fr, dtype))
        for key in ("params", "zncc", "iterations", "status"):
            assert np.array_equal(a[key], b[key], equal_nan=True), key
        cur_a, cur_b = plain.current(), rows4.current()
        assert cur_a.layout == "plain" and cur_b.layout == "rows4"
        ia, ib = icgn(subsets, cur_a).numpy(), icgn(subsets, cur_b).numpy()
        for key in ("params", "zncc", "iterations", "status"):
            assert np.array_equal(ia[key], ib[key], equal_nan=True), key
    both = [_as(fr, dtype) for fr in frames[3:5]]
    for ra, rb in zip(plain.track_batch(both), rows4.track_batch(both)):
        for key in ("params", "zncc", "iterations", "status"):
            assert np.array_equal(ra[key], rb[key], equal_nan=True), key
    with pytest.raises(ValueError, match="layout must be one of"):
        FrameTracker(subsets, dtype, layout="expanded")
