"""Issue 16 bugs on every device: host results are the caller's (``.numpy()`` was a view of the device buffer on
the CPU, a copy on CUDA), and one rounding rule for POI positions (the integer search rounded half to even, IC-GN
half away from zero)."""
import numpy as np
import pytest
import warp as wp

from dic.synth import speckle_pair
from kernels._device import host_copy, resolve_device
from kernels.conventions import Status, round_half_away
from kernels.icgn import icgn, prepare_current, prepare_reference, prepare_subsets
from kernels.search import useful_radius, zncc_search

SHAPE = (48, 56)


@pytest.fixture(scope="module")
def images():
    ref, cur1 = speckle_pair(SHAPE, (0.4, -0.3), seed=11)
    _, cur2 = speckle_pair(SHAPE, (-1.2, 0.7), seed=11)
    return ref, cur1, cur2


def test_icgn_results_kept_by_the_caller_survive_the_next_frame(images):
    """Frame 1's host results, kept by the caller, must not change when frame 2 reuses the output buffers (on
    the CPU ``IcgnResult.numpy()`` returned views of them, so frame 2 overwrote frame 1's results)."""
    ref, cur1, cur2 = images
    subsets = prepare_subsets(prepare_reference(ref, device="cpu"), [[20.0, 20.0], [30.0, 24.0], [36.0, 28.0]],
                              subset=15)
    first = icgn(subsets, cur1)
    kept = first.numpy()
    snapshot = {k: v.copy() for k, v in kept.items()}
    second = icgn(subsets, prepare_current(cur2, device="cpu"), out=first)  # the next frame, same buffers
    assert second is first
    assert not np.allclose(second.numpy()["params"], snapshot["params"])  # frame 2 did change the buffers
    for name, value in snapshot.items():
        assert np.array_equal(kept[name], value, equal_nan=True), name


def test_host_copy_owns_its_memory():
    device = resolve_device("cpu")
    a = wp.array(np.arange(6, dtype=np.float32), device=device)
    h = host_copy(a)
    assert not np.shares_memory(h, a.numpy())
    a.fill_(7.0)
    assert np.array_equal(h, np.arange(6, dtype=np.float32))


def _wp_round(values: np.ndarray) -> np.ndarray:
    """What the kernels do with a POI coordinate: ``int(wp.round(x))`` on float64 (C ``round``)."""

    @wp.kernel
    def k(x: wp.array(dtype=wp.float64), out: wp.array(dtype=wp.int32)):
        i = wp.tid()
        out[i] = int(wp.round(x[i]))

    xs = wp.array(values, dtype=wp.float64, device="cpu")
    out = wp.empty(values.size, dtype=wp.int32, device="cpu")
    wp.launch(k, dim=values.size, inputs=[xs, out], device="cpu")
    return out.numpy().copy()


def test_round_half_away_is_the_kernels_rounding():
    resolve_device("cpu")
    halves = np.arange(-20, 21) + 0.5
    tricky = np.array([0.49999999999999994, -0.49999999999999994, 2.5 - 2**-51, 1e9 + 0.5, -(2**30) - 0.5,
                       0.0, -0.0, 3.0, -3.0, 10.5, -10.5, 11.5])
    x = np.concatenate([halves, tricky, np.random.default_rng(0).uniform(-1e4, 1e4, 200)])
    assert np.array_equal(round_half_away(x).astype(np.int64), _wp_round(x).astype(np.int64))
    # the rules it replaces disagree with the kernels on these
    assert not np.array_equal(np.rint(halves), _wp_round(halves))
    assert round_half_away(10.5) == 11 and round_half_away(-10.5) == -11 and np.floor(-10.5 + 0.5) == -10


def test_search_and_icgn_centre_a_poi_at_half_a_pixel_alike(images):
    """A POI at x = 42.5 with subset 11 in a 56 px wide image: IC-GN centres it on 43 (half away from zero), its
    subset reaches x = 48 and fits; the search used to centre it on 42 (half to even). At x = 50.5 IC-GN
    centres on 51, whose subset (46..56) leaves the image: OUT_OF_BOUNDS; the search centred on 50 (45..55,
    inside) and reported a match, so the two disagreed on which pixels the POI is."""
    ref, cur1, _ = images
    pts = np.array([[50.5, 24.0], [42.5, 24.5], [10.5, 11.5], [24.0, 36.5]])
    subsets = prepare_subsets(prepare_reference(ref, device="cpu"), pts, subset=11)
    centres = subsets.centres.numpy()
    assert np.array_equal(centres, round_half_away(pts).astype(np.int32))
    st = subsets.status.numpy()
    assert st[0] == Status.OUT_OF_BOUNDS and np.all(st[1:] == Status.CONVERGED)
    best, cc = zncc_search(ref, cur1, pts, subset=11, radius=3, device="cpu")
    assert np.isnan(cc[0])  # the search sees the same subset off the image
    assert np.all(np.isfinite(cc[1:]))
    # the search radius that can matter is computed from the same centres
    assert useful_radius(SHAPE, pts[:1], 11) == 0


def test_host_helpers_refuse_what_they_cannot_read():
    with pytest.raises(ValueError, match="needs a wp.array"):
        host_copy(np.zeros(3))
    with pytest.raises(ValueError, match="real numbers"):
        round_half_away("ten and a half")
