"""Search and propagation on the device (issue 16): indexed IC-GN, reliability-guided waves on the device,
the pyramid guess's reference work cached across frames.

* Indexed IC-GN (``Correlator.run``) gathers the prepared reference quantities of the POIs asked for
  instead of preparing them again; each POI's result is bitwise what the all-POI launch gives it and what
  a fresh preparation of just those POIs gives it (the route before issue 16).
* The reliability-guided waves run on the device (``waves="device"``, the default): the same waves, sources
  and guesses as the host heap (``waves="host"``), hence bitwise the same results, on a smooth field and on
  a field with a displacement discontinuity, 1st and 2nd order; per frame a bounded number of launches,
  no allocation after the first frame and no copy per wave on the CPU.
* The pyramid guess builds the reference pyramid and its level correlators once per reference.
"""
import collections

import numpy as np
import pytest
import warp as wp

import dic.correlation.engine as engine
import dic.correlation.guesses as guesses
from dic._track import Tracker
from dic.correlation import Correlator, reliability_guided
from dic.correlation.guesses import get_guess, pyramid_guess
from dic.synth import speckle_pair
from kernels.conventions import Status
from kernels.icgn import gather_subsets, icgn, prepare_current, prepare_subsets, subset_buffers
from kernels.propagation import neighbour_lists

SHAPE = (160, 200)


def smooth(x, y):
    return 3.3 + 0.01 * x - 0.004 * y, -2.1 + 0.003 * x + 0.006 * y


def discontinuous(x, y):
    """A 2.5 px jump of v across x = 100.3 (a sliding crack): POIs straddling it fail."""
    return 1.5 + 0.01 * x, -1.1 + 0.006 * y + np.where(x > 100.3, 2.5, 0.0)


@pytest.fixture(scope="module")
def pairs():
    return {name: speckle_pair(SHAPE, f, seed=3) for name, f in (("smooth", smooth), ("crack", discontinuous))}


def _rg(tracker, cur, waves, prepared=None):
    c = tracker.correlator
    base = np.zeros((c.n_points, 6 * tracker.order))
    ctx = tracker._context(cur, base)
    strategy = get_guess("rg")
    pc = prepare_current(cur, device=c.device) if prepared is None else prepared
    return reliability_guided(c, pc, base, lambda i: strategy(ctx, i)[0],
                              zncc_min=tracker.zncc_min, step=tracker.step, waves=waves)


@pytest.mark.parametrize("order", [1, 2])
def test_indexed_icgn_is_bitwise_the_full_launch_and_a_fresh_preparation(device, pairs, order):
    ref, cur = pairs["smooth"]
    c = Correlator(ref, Tracker(ref, step=9, device=device).points, subset=21, order=order, max_iter=30, tol=1e-3,
                   device=device)
    pc = prepare_current(cur, device=device)
    k = 6 * order
    g = np.zeros((c.n_points, k))
    g[:, 0], g[:, k // 2] = 3.0, -2.0
    everything = c.run_all(pc, g)
    idx = np.random.default_rng(1).permutation(c.n_points)[: c.n_points // 3]  # any order, a third of the POIs
    got = c.run(pc, idx, g[idx])
    # the route before issue 16: the POIs' subsets prepared again, IC-GN of just them
    fresh = icgn(prepare_subsets(c.reference, c.points[idx], subset=21, order=order), pc, guess=g[idx]).numpy()
    for name in ("params", "zncc", "iterations", "status"):
        assert np.array_equal(got[name], everything[name][idx], equal_nan=True), name
        assert np.array_equal(got[name], fresh[name], equal_nan=True), name
    assert np.count_nonzero(got["status"] == int(Status.CONVERGED)) > 0.9 * idx.size
    every = c.run(pc, np.arange(c.n_points), g)  # all POIs in order: run on the prepared subsets directly
    assert all(np.array_equal(every[n], everything[n], equal_nan=True) for n in every)
    # a second call reuses the buffers and leaves the first call's host arrays alone
    first = got["params"].copy()
    c.run(pc, idx[::-1].copy(), g[idx[::-1]] + 0.25)
    assert np.array_equal(got["params"], first)


@pytest.mark.parametrize("order", [1, 2])
def test_counted_icgn_is_bitwise_icgn_of_the_counted_rows(device, pairs, order):
    """kernels.rg_device.icgn_counted (launched over all N rows, the count read on the device) gives the first
    counts[ctl[0], 0] rows bitwise what kernels.icgn.icgn gives them and leaves the rows past the count alone."""
    from kernels.icgn import subset_rows
    from kernels.rg_device import icgn_counted

    ref, cur = pairs["crack"]
    c = Correlator(ref, Tracker(ref, step=9, device=device).points, subset=21, order=order, max_iter=30, tol=1e-3,
                   device=device)
    pc = prepare_current(cur, device=device)
    n, k = c.n_points, 6 * order
    idx = np.random.default_rng(2).permutation(n).astype(np.int32)
    m = n // 3
    b = c._buffers()
    gather_subsets(c.subsets, wp.array(idx, dtype=wp.int32, device=device), n, b.subsets)
    g = np.zeros((n, k), np.float32)
    g[:, 0], g[:, k // 2] = 1.5, -1.0
    b.guess.assign(g)
    expected = icgn(subset_rows(b.subsets, m), pc, guess=g[:m], max_iter=30, tol=1e-3).numpy()
    for a in (b.out.params, b.out.zncc):
        a.fill_(-7.0)
    ctl = wp.array(np.array([3, 0], np.int32), dtype=wp.int32, device=device)  # batch 3
    counts = np.zeros((8, 2), np.int32)
    counts[3, 0] = m
    icgn_counted(b.subsets, pc, b.guess, 30, 1e-3, b.out, ctl, wp.array(counts, dtype=wp.int32, device=device))
    got = b.out.numpy()
    for name in ("params", "zncc", "iterations", "status"):
        assert np.array_equal(got[name][:m], expected[name], equal_nan=True), name
    assert np.all(got["params"][m:] == -7.0) and np.all(got["zncc"][m:] == -7.0)
    assert np.count_nonzero(np.isin(expected["status"], (int(Status.CONVERGED), int(Status.MAX_ITERATIONS)))) > m // 2


def test_gathered_subsets_are_the_prepared_rows(device, pairs):
    ref, _ = pairs["smooth"]
    c = Correlator(ref, Tracker(ref, step=20, device=device).points, subset=21, order=2, max_iter=30, tol=1e-3,
                   device=device)
    idx = np.array([5, 0, 17, 3], dtype=np.int32)
    sub = gather_subsets(c.subsets, wp.array(idx, dtype=wp.int32, device=device), 4, subset_buffers(c.subsets),
                         points=c.points[idx])
    for name in ("centres", "deltas", "refdata", "status"):
        assert np.array_equal(getattr(sub, name).numpy(), getattr(c.subsets, name).numpy()[idx]), name
    assert sub.n_points == 4 and np.array_equal(sub.points, c.points[idx])


@pytest.mark.parametrize("field", ["smooth", "crack"])
@pytest.mark.parametrize("order", [1, 2])
def test_device_waves_are_bitwise_the_host_waves(device, pairs, field, order):
    ref, cur = pairs[field]
    t = Tracker(ref, subset=21, step=7, order=order, search="rg", device=device)
    host = _rg(t, cur, "host")
    dev = _rg(t, cur, "device")
    synced = _rg(t, cur, "device-sync")
    for name in ("params", "zncc", "iterations", "status"):
        assert host[name].dtype == dev[name].dtype == synced[name].dtype, name
        assert np.array_equal(host[name], dev[name], equal_nan=True), name
        assert np.array_equal(host[name], synced[name], equal_nan=True), name
    again = _rg(t, cur, "device")  # the device state is reset per frame
    assert all(np.array_equal(dev[n], again[n], equal_nan=True) for n in dev)
    # the CUDA route of the per-wave counts (a 2-int copy into a host buffer), exercised on this device
    t.correlator._rg.counts_host = wp.empty(2, dtype=wp.int32, device="cpu")
    copied = _rg(t, cur, "device-sync")
    t.correlator._rg.counts_host = None if str(device).startswith("cpu") else t.correlator._rg.counts_host
    assert all(np.array_equal(dev[n], copied[n], equal_nan=True) for n in dev)
    # the propagation reached the field (and, across the crack, stopped at it): accuracy vs the exact field
    ok = np.isin(dev["status"], (int(Status.CONVERGED), int(Status.MAX_ITERATIONS))) & (dev["zncc"] >= t.zncc_min)
    u, v = (smooth if field == "smooth" else discontinuous)(t.points[:, 0], t.points[:, 1])
    k = 6 * order
    err = np.hypot(dev["params"][ok, 0] - u[ok], dev["params"][ok, k // 2] - v[ok])
    assert ok.mean() > (0.85 if field == "smooth" else 0.75)
    assert np.median(err) < 0.02
    if field == "crack":  # subsets straddling the jump do not converge to a good ZNCC
        straddle = np.abs(t.points[:, 0] - 100.3) < 10
        assert np.mean(ok[straddle]) < np.mean(ok[~straddle])


@pytest.mark.parametrize("field", ["smooth", "crack"])
@pytest.mark.parametrize("order", [1, 2])
def test_device_loop_graph_and_wave_bound_are_bitwise_the_synced_waves(pairs, field, order, monkeypatch):
    """The frame's device loop (no host round trip per wave): its CUDA branch (the loop captured once as a
    graph with a conditional while node on the pending count, then launched; Warp 1.19 captures on the CPU
    too, one launch per kernel) and the host-driven loop of the same body give bitwise the per-wave-synced
    waves; so does a loop stopped at a small wave bound and finished by the host loop."""
    monkeypatch.setenv("SPECULA_THREADS", "1")  # a capture records the launches of its own thread only
    ref, cur = pairs[field]
    t = Tracker(ref, subset=21, step=7, order=order, search="rg", device="cpu")
    synced = _rg(t, cur, "device-sync")
    runs = {"default": _rg(t, cur, "device")}  # on the CPU: the counts read in place
    monkeypatch.setattr(engine, "_loop_kind", lambda dev: "counted")
    runs["loop"] = _rg(t, cur, "device")  # the device loop's body, driven from the host
    captures = []
    make = wp.ScopedCapture
    monkeypatch.setattr(engine, "_loop_kind", lambda dev: "graph")
    monkeypatch.setattr(wp, "ScopedCapture", lambda *a, **k: (captures.append(1), make(*a, **k))[1])
    pc = prepare_current(cur, device="cpu")  # one current image buffer (as Tracker keeps): one capture
    runs["graph"] = _rg(t, cur, "device", pc)
    runs["graph again"] = _rg(t, cur, "device", pc)  # the captured graph launched again, not captured again
    assert len(captures) == 1 and t.correlator._rg.graph is not None
    runs["graph, another buffer"] = _rg(t, cur, "device")  # another current buffer: captured again
    assert len(captures) == 2
    monkeypatch.setattr(engine, "_loop_kind", lambda dev: "counted")
    for bound in (1, 2, 5):  # stopped after wave `bound`: the host loop finishes the frame
        c = t.correlator
        base = np.zeros((c.n_points, 6 * order))
        ctx = t._context(cur, base)
        strategy = get_guess("rg")
        st = engine._rg_state(c, t.step)
        runs[f"bound {bound}"] = engine._rg_device(
            c, prepare_current(cur, device="cpu"), base, np.flatnonzero(c.ready)[
                np.unique(np.linspace(0, np.flatnonzero(c.ready).size - 1, 9).round().astype(int))],
            lambda i: strategy(ctx, i)[0], t.zncc_min, float(t.step), max_waves=bound)
        assert st.ctl.numpy()[1] == 1  # the bound was reached
    for label, r in runs.items():
        for name in ("params", "zncc", "iterations", "status"):
            assert np.array_equal(synced[name], r[name], equal_nan=True), (label, name)
    assert np.mean(synced["status"] == int(Status.CONVERGED)) > 0.7


def test_device_loop_kind_per_device(monkeypatch):
    """CUDA: the graph where conditional graph nodes exist (CUDA 12.4+), else the per-wave read; the CPU: the
    counts read in place."""
    import types

    cuda, cpu = types.SimpleNamespace(is_cuda=True), types.SimpleNamespace(is_cuda=False)
    assert engine._loop_kind(cpu) == "sync"
    monkeypatch.setattr(wp, "is_conditional_graph_supported", lambda: True)
    assert engine._loop_kind(cuda) == "graph"
    monkeypatch.setattr(wp, "is_conditional_graph_supported", lambda: False)
    assert engine._loop_kind(cuda) == "sync"


def test_device_waves_without_seeds_or_trackable_points(device):
    flat = np.full((60, 60), 100.0, np.float32)  # every subset FLAT_SUBSET: no seed
    t = Tracker(flat, step=10, search="rg", check_warps=False, device=device)
    r = _rg(t, flat, "device")
    assert np.all(r["status"] == int(Status.FLAT_SUBSET)) and np.all(np.isnan(r["zncc"]))
    assert np.all(r["params"] == 0)


class _Counts:
    """Counts wp.launch / wp.copy calls and CPU allocations (Warp's allocator) while active."""

    def __init__(self, monkeypatch):
        import warp._src.context as ctx

        self.n = collections.Counter()
        launch, copy = wp.launch, wp.copy

        def counted_launch(*a, **k):
            self.n["launch"] += 1
            return launch(*a, **k)

        def counted_copy(*a, **k):
            self.n["copy"] += 1
            return copy(*a, **k)

        monkeypatch.setattr(wp, "launch", counted_launch)
        monkeypatch.setattr(wp, "copy", counted_copy)
        for cls in (ctx.CpuDefaultAllocator, ctx.CpuPinnedAllocator):
            def counted_alloc(obj, size, _orig=cls.allocate):
                self.n["alloc"] += 1
                return _orig(obj, size)
            monkeypatch.setattr(cls, "allocate", counted_alloc)


def test_reliability_guided_frame_launches_copies_allocations(monkeypatch):
    """Per reliability-guided frame (256 x 256, step 8, CPU, one launch per kernel): before issue 16 every wave
    prepared its subsets again and copied guesses up and results back (~2 launches, 2 copies, 10 allocations per
    wave); now a wave is 3 launches (bookkeeping, IC-GN of the gathered candidates, scatter of the results) and
    nothing else on the CPU, and a frame after the first allocates only in the image preparation and the seeds'
    ZNCC search (whose reference is uploaded once per reference)."""
    monkeypatch.setenv("SPECULA_THREADS", "1")  # one wp.launch per kernel launch, as on CUDA
    import functools
    import importlib

    import kernels.propagation as prop

    # the waves with their counts read per wave (waves="device-sync"; the default loop: the next test)
    monkeypatch.setattr(importlib.import_module("dic._track"), "reliability_guided",
                        functools.partial(reliability_guided, waves="device-sync"))

    ref, cur = speckle_pair((256, 256), lambda x, y: (2.3 + 0.004 * x, -1.2 + 0.002 * y), seed=4)
    t = Tracker(ref, subset=21, step=8, search="rg", device="cpu")
    t.track(cur)  # first frame: compiles, allocates the reusable buffers
    waves = []
    wave = prop.rg_wave
    monkeypatch.setattr(prop, "rg_wave", lambda *a, **k: (waves.append(a[0]), wave(*a, **k))[1])
    counts = _Counts(monkeypatch)
    f = t.track(cur)
    n = counts.n
    print(f"\nreliability-guided frame: {dict(n)}, {len(waves)} waves")
    assert f.valid.mean() > 0.9 and len(waves) >= 10
    # launches: init + seeds (gather, IC-GN, scatter) + 3 per wave + the seeds' ZNCC search and the image's
    # B-spline preparation (4)
    assert n["launch"] <= 3 * len(waves) + 4 + 4, (dict(n), len(waves))
    # copies: seeds' indices and guesses (2) + the image and the ZNCC search's inputs (4: the reference is
    # uploaded once per reference); none per wave
    assert n["copy"] <= 6, dict(n)
    # allocations: only the image preparation (2) and the seeds' ZNCC search (5); none per wave
    assert n["alloc"] <= 7, dict(n)


def test_reliability_guided_device_loop_has_no_copy_per_wave(monkeypatch):
    """The device loop of ``waves="device"`` on CUDA (here driven from the host): per wave 4 launches
    (bookkeeping, counted IC-GN, counted scatter, the one-thread step that sets the loop condition) and no
    copy: the only copies of a frame are the seeds' and the search's inputs (as with the synced waves) and
    one read of the loop's 2-int control at the end of the frame (the bound check; host memory here); on
    CUDA the waves are one graph launch."""
    monkeypatch.setenv("SPECULA_THREADS", "1")
    import kernels.propagation as prop

    monkeypatch.setattr(engine, "_loop_kind", lambda dev: "counted")  # the CUDA loop, driven from the host
    ref, cur = speckle_pair((256, 256), lambda x, y: (2.3 + 0.004 * x, -1.2 + 0.002 * y), seed=4)
    t = Tracker(ref, subset=21, step=8, search="rg", device="cpu")
    t.track(cur)
    waves = []
    wave = prop.rg_wave_counted
    monkeypatch.setattr(prop, "rg_wave_counted", lambda *a, **k: (waves.append(1), wave(*a, **k))[1])
    synced, synced_wave = [], prop.rg_wave
    monkeypatch.setattr(prop, "rg_wave", lambda *a, **k: synced.append(1))  # must not run
    copies_per_frame = []
    for frames in (1, 2):
        counts = _Counts(monkeypatch)
        for _ in range(frames):
            f = t.track(cur)
        copies_per_frame.append(counts.n["copy"])
        n = counts.n
    print(f"\ndevice loop: {dict(n)} over 2 frames, {len(waves)} waves")
    assert f.valid.mean() > 0.9 and len(waves) >= 30 and not synced
    per_frame = len(waves) // 3
    # launches per frame: init + seeds (gather, start) + 4 per wave + the seeds' search and image preparation (6)
    assert n["launch"] <= 2 * (4 * per_frame + 3 + 6), (dict(n), len(waves))
    # copies: a constant per frame, none per wave (2 frames copy twice what 1 frame copies)
    assert copies_per_frame[1] == 2 * copies_per_frame[0] <= 2 * 6, copies_per_frame
    # the per-wave read of "device-sync" through its CUDA route (a 2-int copy per wave), for contrast
    monkeypatch.setattr(engine, "_loop_kind", lambda dev: "sync")
    monkeypatch.setattr(prop, "rg_wave", synced_wave)
    t.correlator._rg.counts_host = wp.empty(2, dtype=wp.int32, device="cpu")
    counts = _Counts(monkeypatch)
    f = t.track(cur)
    assert f.valid.mean() > 0.9 and counts.n["copy"] >= copies_per_frame[0] + per_frame, (dict(counts.n), per_frame)


def test_pyramid_reference_built_once_per_reference(device, monkeypatch, pairs):
    ref, cur = pairs["smooth"]
    _, cur2 = speckle_pair(SHAPE, (4.2, -3.1), seed=3)
    calls = collections.Counter()
    pyr, prep = guesses.pyramid, engine.prepare_subsets
    monkeypatch.setattr(guesses, "pyramid", lambda img, *a, **k: (calls.update(["pyramid"]), pyr(img, *a, **k))[1])
    monkeypatch.setattr(engine, "prepare_subsets",
                        lambda *a, **k: (calls.update(["prepare_subsets"]), prep(*a, **k))[1])
    t = Tracker(ref, step=12, search="pyramid", search_radius=24, device=device)
    calls.clear()
    f1 = t.track(cur)
    first = dict(calls)
    assert first["pyramid"] == 2 and first["prepare_subsets"] >= 1  # reference + current; the level subsets
    calls.clear()
    f2 = t.track(cur2)
    assert dict(calls) == {"pyramid": 1}  # only the current image's pyramid: nothing of the reference again
    # the cached guesses are bitwise those built from scratch
    for cur_, f in ((cur, f1), (cur2, f2)):
        cached = pyramid_guess(t.reference, cur_, t.points, t.subset, 24, 0.7, device, cache=t.correlator.cache)
        scratch = pyramid_guess(t.reference, cur_, t.points, t.subset, 24, 0.7, device)
        assert np.array_equal(cached, scratch)
        assert f.valid.mean() > 0.9


def test_bad_indexed_inputs_are_refused(device, pairs):
    ref, cur = pairs["smooth"]
    c = Correlator(ref, Tracker(ref, step=20, device=device).points, subset=21, order=1, max_iter=30, tol=1e-3,
                   device=device)
    g = np.zeros((2, 6))
    for idx, msg in (([0, c.n_points], "in \\[0"), ([-1, 0], "in \\[0"), ([1, 1], "distinct"),
                     ([0.5, 1.0], "integer"), ([[0, 1]], "1-D")):
        with pytest.raises(ValueError, match=msg):
            c.run(cur, np.array(idx), g)
    with pytest.raises(ValueError, match="shape"):
        c.run(cur, np.array([0, 1]), np.zeros((3, 6)))
    with pytest.raises(ValueError, match="NaN"):
        c.run(cur, np.array([0, 1]), np.full((2, 6), np.nan))
    assert c.run(cur, np.array([], dtype=int), np.zeros((0, 6)))["params"].shape == (0, 6)
    with pytest.raises(ValueError, match="waves"):
        reliability_guided(c, cur, np.zeros((c.n_points, 6)), lambda i: np.zeros((i.size, 6)), zncc_min=0.8,
                           step=None, waves="gpu")
    with pytest.raises(ValueError, match="base"):
        reliability_guided(c, cur, np.zeros((3, 6)), lambda i: np.zeros((i.size, 6)), zncc_min=0.8, step=None)
    idx = wp.array(np.array([0, 1], np.int32), dtype=wp.int32, device=device)
    with pytest.raises(ValueError, match="count"):
        gather_subsets(c.subsets, idx, 3, subset_buffers(c.subsets))
    with pytest.raises(ValueError, match="int32"):
        gather_subsets(c.subsets, wp.array(np.array([0, 1.0]), dtype=wp.float32, device=device), 1,
                       subset_buffers(c.subsets))
    with pytest.raises(ValueError, match="waves"):
        reliability_guided(c, cur, np.zeros((c.n_points, 6)), lambda i: np.zeros((i.size, 6)), zncc_min=0.8,
                           step=None, waves="graph")
    from kernels.propagation import advance, start_loop
    from kernels.rg_device import icgn_counted

    ctl, cond = wp.zeros(2, dtype=wp.int32, device=device), wp.zeros(1, dtype=wp.int32, device=device)
    counts = wp.zeros((c.n_points + 3, 2), dtype=wp.int32, device=device)
    with pytest.raises(ValueError, match="ctl must have shape"):
        start_loop(wp.zeros(3, dtype=wp.int32, device=device), cond, counts, 1)
    with pytest.raises(ValueError, match="cond must be an int32"):
        start_loop(ctl, wp.zeros(1, dtype=wp.float32, device=device), counts, 1)
    with pytest.raises(ValueError, match="non-negative"):
        start_loop(ctl, cond, counts, -1)
    with pytest.raises(ValueError, match="last must be"):
        advance(ctl, cond, counts, c.n_points + 2)
    b = c._buffers()
    pc = prepare_current(cur, device=device)
    with pytest.raises(ValueError, match="counts must have shape"):
        icgn_counted(b.subsets, pc, b.guess, 30, 1e-3, b.out, ctl, wp.zeros(4, dtype=wp.int32, device=device))
    with pytest.raises(ValueError, match="CurrentImage"):
        icgn_counted(b.subsets, cur, b.guess, 30, 1e-3, b.out, ctl, counts)
    with pytest.raises(ValueError, match="rows"):
        icgn_counted(b.subsets, pc, b.guess[:2], 30, 1e-3, b.out, ctl, counts)
    with pytest.raises(ValueError, match="max_iter"):
        icgn_counted(b.subsets, pc, b.guess, 0, 1e-3, b.out, ctl, counts)
    with pytest.raises(ValueError, match="radius"):
        neighbour_lists(c.points, 0.0)
    with pytest.raises(ValueError, match="points"):
        neighbour_lists(np.zeros((0, 2)), 1.0)


def test_zncc_search_reference_uploaded_once(device, monkeypatch, pairs):
    import kernels.search as search

    ref, cur = pairs["smooth"]
    pts = np.array([[50.0, 60.0], [120.5, 80.0], [150.0, 120.0]])
    plain = search.zncc_search(ref, cur, pts, 6, subset=21, device=device)
    up = search.search_image(ref, device)
    assert up.shape == ref.shape
    once = search.zncc_search(up, cur, pts, 6, subset=21, device=device)
    assert all(np.array_equal(a, b, equal_nan=True) for a, b in zip(plain, once))
    with pytest.raises(ValueError, match="uploaded to"):
        search.zncc_search(search.SearchImage(up.flat, up.shape, "cuda:9"), cur, pts, 6, device=device)
    with pytest.raises(ValueError, match="same shape"):
        search.zncc_search(up, cur[:-1], pts, 6, device=device)
    # tracking with a search uploads the reference once per reference, not per frame
    uploads = []
    validate = search.as_float32_image
    monkeypatch.setattr(search, "as_float32_image", lambda img, name="image": (uploads.append(name),
                                                                              validate(img, name))[1])
    t = Tracker(ref, step=16, search="zncc", search_radius=6, device=device)
    t.track(cur)
    t.track(cur)
    assert uploads.count("reference") == 1 and uploads.count("current") == 2
