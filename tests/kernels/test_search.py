"""Integer initial-guess kernels: ZNCC window search (vs. NumPy brute force), phase correlation,
Gaussian pyramid reduction (vs. scipy.ndimage)."""
import numpy as np
import pytest
from scipy import ndimage

from kernels.search import phase_correlation, phase_correlation_spectra, phase_spectrum, pyramid, reduce, zncc_search


def texture(shape, seed=0, sigma=1.5):
    rng = np.random.default_rng(seed)
    img = ndimage.gaussian_filter(rng.uniform(0, 1, shape), sigma)
    return 128 + 50 * (img - img.mean()) / img.std()


def shifted_pair(u, v, shape=(100, 110), seed=0):
    """(reference, current) with current(x, y) = reference(x - u, y - v) (integer u, v)."""
    m = 40
    big = texture((shape[0] + 2 * m, shape[1] + 2 * m), seed)
    ref = big[m:m + shape[0], m:m + shape[1]]
    cur = big[m - v:m - v + shape[0], m - u:m - u + shape[1]]
    return ref, cur


def zncc_numpy(ref, cur, cx, cy, du, dv, r):
    a = ref[cy - r:cy + r + 1, cx - r:cx + r + 1].ravel()
    b = cur[cy + dv - r:cy + dv + r + 1, cx + du - r:cx + du + r + 1].ravel()
    a, b = a - a.mean(), b - b.mean()
    return a @ b / np.sqrt((a @ a) * (b @ b))


def test_zncc_search_finds_integer_shift(device):
    ref, cur = shifted_pair(7, -5)
    pts = np.array([[40.0, 50.0], [60.2, 45.7], [70.0, 30.0]])
    uv, cc = zncc_search(ref, cur, pts, radius=10, subset=15, device=device)
    np.testing.assert_array_equal(uv, np.tile([7, -5], (3, 1)))
    assert np.all(cc > 0.9999)


def test_zncc_search_matches_numpy_brute_force(device):
    ref = texture((60, 60), seed=1)
    cur = texture((60, 60), seed=2) * 0.3 + ref * 0.7  # a partly decorrelated image: a non-trivial peak
    cx, cy, r, radius = 30, 28, 7, 6
    uv, cc = zncc_search(ref, cur, [[cx, cy]], radius=radius, subset=2 * r + 1, start=[[1, -2]], device=device)
    best, arg = -2.0, None
    for dv in range(-2 - radius, -2 + radius + 1):
        for du in range(1 - radius, 1 + radius + 1):
            z = zncc_numpy(ref, cur, cx, cy, du, dv, r)
            if z > best:
                best, arg = z, (du, dv)
    assert tuple(uv[0]) == arg
    assert abs(cc[0] - best) < 1e-4  # float32 sums over 225 pixels


def test_zncc_search_out_of_bounds_subset(device):
    ref, cur = shifted_pair(3, 2)
    uv, cc = zncc_search(ref, cur, [[4.0, 50.0], [50.0, 50.0]], radius=4, subset=15, device=device)
    assert np.isnan(cc[0]) and tuple(uv[0]) == (0, 0)
    assert tuple(uv[1]) == (3, 2)


@pytest.mark.parametrize("shift", [(7, -5), (25, -31)])
def test_phase_correlation(shift):
    ref, cur = shifted_pair(*shift, shape=(128, 120), seed=3)
    u, v, peak = phase_correlation(ref, cur)
    assert (u, v) == shift
    assert peak > 0.1  # well above the ~1/sqrt(N) noise level of a mismatch


def test_phase_correlation_from_kept_spectra():
    """A sequence keeps each image's spectrum (its current image is the next state's base): the shifts from kept
    spectra are the known ones, and the same as from the images."""
    ref, cur = shifted_pair(7, -5, shape=(128, 120), seed=3)
    _, nxt = shifted_pair(-4, 9, shape=(128, 120), seed=3)  # the same texture shifted by (-4, 9) from ref
    s_ref, s_cur, s_nxt = phase_spectrum(ref), phase_spectrum(cur), phase_spectrum(nxt)
    assert s_ref.spectrum.shape == (128, 61) and s_ref.shape == (128, 120)
    assert phase_correlation_spectra(s_ref, s_cur)[:2] == (7, -5)
    assert phase_correlation_spectra(s_cur, s_nxt)[:2] == (-11, 14)  # cur -> nxt, the spectrum of cur reused
    assert phase_correlation_spectra(s_cur, s_nxt) == phase_correlation(cur, nxt)
    with pytest.raises(ValueError, match="same shape"):
        phase_correlation_spectra(s_ref, phase_spectrum(ref[:, :-2]))
    with pytest.raises(ValueError, match="PhaseSpectrum"):
        phase_correlation_spectra(s_ref, cur)


def test_phase_spectra_on_several_threads_are_bitwise_one_thread(monkeypatch):
    """The FFTs run on the CPU launch threads (SPECULA_THREADS): whole 1-D transforms per thread, the same bits."""
    ref, cur = shifted_pair(7, -5, shape=(256, 250), seed=3)
    monkeypatch.setenv("SPECULA_THREADS", "1")
    one = phase_spectrum(ref), phase_spectrum(cur)
    shift_one = phase_correlation_spectra(*one)
    monkeypatch.setenv("SPECULA_THREADS", "2")
    two = phase_spectrum(ref), phase_spectrum(cur)
    assert all(np.array_equal(a.spectrum, b.spectrum) for a, b in zip(one, two))
    assert phase_correlation_spectra(*two) == shift_one and shift_one[:2] == (7, -5)


def test_phase_window_is_the_points_box_with_a_margin():
    from scipy.fft import next_fast_len

    from kernels.search import phase_window

    pts = np.array([[532.2, 335.0], [1361.7, 864.4], [900.0, 600.0]])
    rows, cols = phase_window(pts, (1200, 1920), 74)
    for span, lo, hi, size in ((rows, 335.0, 864.4, 1200), (cols, 532.2, 1361.7, 1920)):
        assert span.start <= lo - 74 and span.stop >= hi + 74 + 1 and 0 <= span.start and span.stop <= size
        assert span.stop - span.start == next_fast_len(span.stop - span.start, real=True)  # a fast FFT length
    assert phase_window(pts, (1200, 1920), 74) == phase_window(pts + 3.0, (1200, 1920), 74)  # small moves: same
    assert phase_window(np.array([[10.0, 10.0], [1013.0, 1013.0]]), (1024, 1024), 74) is None  # whole image
    assert phase_window(np.full((3, 2), np.nan), (1024, 1024), 74) is None
    # the shift of a texture measured on its window is the shift measured on the whole image
    ref, cur = shifted_pair(7, -5, shape=(256, 250), seed=3)
    window = phase_window(np.array([[60.0, 70.0], [180.0, 170.0]]), ref.shape, 20)
    assert window is not None
    assert phase_correlation(ref[window], cur[window])[:2] == (7, -5) == phase_correlation(ref, cur)[:2]


def test_reduce_matches_scipy(device):
    img = texture((37, 50), seed=4)
    kern = np.array([1, 4, 6, 4, 1]) / 16.0
    ref = ndimage.convolve1d(ndimage.convolve1d(img, kern, axis=0, mode="mirror"), kern, axis=1, mode="mirror")
    got = reduce(img, device=device)
    assert got.shape == (19, 25)
    assert np.max(np.abs(got - ref[::2, ::2])) < 1e-3  # float32
    levels = pyramid(img, 2, device=device)
    assert [lv.shape for lv in levels] == [(37, 50), (19, 25), (10, 13)]


def test_bad_input(device):
    ref, cur = shifted_pair(1, 1)
    with pytest.raises(ValueError, match="same shape"):
        zncc_search(ref, cur[:-1], [[50, 50]], radius=3, device=device)
    with pytest.raises(ValueError, match="odd"):
        zncc_search(ref, cur, [[50, 50]], radius=3, subset=14, device=device)
    with pytest.raises(ValueError, match="radius"):
        zncc_search(ref, cur, [[50, 50]], radius=-1, device=device)
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        zncc_search(ref, cur, [50, 50], radius=3, device=device)
    with pytest.raises(ValueError, match="same shape"):
        phase_correlation(ref, cur[:, :-2])
    with pytest.raises(ValueError, match="levels"):
        pyramid(ref, -1)
