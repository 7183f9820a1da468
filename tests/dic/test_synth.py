"""Boolean-model speckle (kernels/speckle.py, dic/synth.py) against independent NumPy evaluations."""
import math

import numpy as np
import pytest
from scipy import integrate
from scipy.special import ndtr

from dic import synth
from kernels.speckle import build_speckle_model, speckle_coverage_points

# ---------------------------------------------------------------------------------------------
# independent NumPy references (brute force over all disks, no cell grid, float64)


def numpy_coverage(centres, radii, pts, width=0.0):
    """Binary (width=0) or anti-aliased coverage by brute force."""
    d = np.hypot(pts[:, None, 0] - centres[None, :, 0], pts[:, None, 1] - centres[None, :, 1]) - radii[None]
    sd = d.min(axis=1)  # signed distance to the union's boundary (exact outside)
    if width == 0:
        return (sd <= 0).astype(float)
    return np.clip(0.5 - sd / width, 0.0, 1.0)


def numpy_kernel_weights(samples, blur):
    """Weights of the pixel-box x Gaussian kernel over sub-cells, by numerical quadrature (scipy)."""
    h = 1.0 / samples
    reach = math.ceil(4 * blur * samples)
    offsets = -0.5 + (np.arange(samples + 2 * reach) - reach + 0.5) * h

    def density(t):  # box [-1/2, 1/2] convolved with N(0, blur^2)
        return ndtr((t + 0.5) / blur) - ndtr((t - 0.5) / blur)

    w = np.array([integrate.quad(density, o - h / 2, o + h / 2, epsabs=1e-13)[0] for o in offsets])
    return offsets, w / w.sum()


def numpy_pixel(model, x, y, mapping=None):
    """Grey level of the pixel centred at (x, y): sub-cell quadrature of the anti-aliased coverage
    at the material points ``mapping(qx, qy)`` (identity when None)."""
    offsets, w = numpy_kernel_weights(model.samples, model.blur)
    qx, qy = np.meshgrid(x + offsets, y + offsets)
    if mapping is not None:
        qx, qy = mapping(qx, qy)
    pts = np.stack([qx.ravel(), qy.ravel()], axis=1)
    near = np.hypot(model.centres[:, 0] - x, model.centres[:, 1] - y) < model.radii + 4 * model.blur + 10
    cov = numpy_coverage(model.centres[near], model.radii[near], pts, width=1.0 / model.samples)
    cov = cov.reshape(qx.shape)
    return model.background + model.contrast * float(w @ cov @ w)


# ---------------------------------------------------------------------------------------------
# kernels.speckle


def test_coverage_matches_bruteforce(device, rng):
    centres = rng.uniform(0, 60, size=(300, 2))
    radii = rng.uniform(0.5, 3.0, size=300)
    model = build_speckle_model(centres, radii, device=device)
    pts = rng.uniform(-5, 65, size=(5000, 2))
    got = speckle_coverage_points(model, pts)
    # binary coverage: exact except for points within float32 rounding (~1e-5) of a boundary
    ref = numpy_coverage(centres, radii, pts)
    d_edge = np.abs(np.hypot(pts[:, None, 0] - centres[:, 0], pts[:, None, 1] - centres[:, 1]) - radii).min(1)
    clear = d_edge > 1e-4
    assert np.array_equal(got[clear], ref[clear])
    assert 0.2 < ref.mean() < 0.9  # the check saw both covered and uncovered points
    # anti-aliased coverage: a continuous function of position, float32 error ~1e-5 / width
    got_aa = speckle_coverage_points(model, pts, width=0.3)
    assert np.max(np.abs(got_aa - numpy_coverage(centres, radii, pts, width=0.3))) < 1e-3
    # a small cell size (many cells per disk) must not change the answer
    fine_cells = build_speckle_model(centres, radii, cell_size=0.7, device=device)
    assert np.array_equal(speckle_coverage_points(fine_cells, pts)[clear], ref[clear])


def test_build_model_rejects_bad_input():
    with pytest.raises(ValueError, match=r"centres must have shape \(M, 2\)"):
        build_speckle_model(np.zeros((3, 3)), np.ones(3), device="cpu")
    with pytest.raises(ValueError, match="radii must be > 0"):
        build_speckle_model(np.zeros((2, 2)), np.array([1.0, 0.0]), device="cpu")


# ---------------------------------------------------------------------------------------------
# the Boolean model


@pytest.mark.parametrize("density,spread", [(0.3, 0.0), (0.5, 0.2), (0.7, 0.4)])
def test_coverage_fraction_matches_poisson_model(density, spread):
    """Covered fraction = 1 - exp(-lambda pi E[r^2]) = the requested density."""
    model = synth.make_speckle(region=(0, 0, 1024, 1024), radius=2.0, density=density, radius_spread=spread, seed=7)
    rng = np.random.default_rng(0)
    pts = rng.uniform(8, 1016, size=(200_000, 2))
    measured = model.coverage(pts[:, 0], pts[:, 1]).mean()
    # std of the estimate: Boolean-model fluctuation over 1e6 px² (correlation area ~ pi (2r)^2 / 2
    # = 25 px², so sqrt(p(1-p) 25 / 1e6) <= 0.0025) plus binomial sampling sqrt(0.25 / 2e5) = 0.0011;
    # 0.015 is > 5 sigma
    assert abs(measured - density) < 0.015
    # radii follow the requested distribution (mean radius within 1 % for ~5e4 disks)
    assert abs(model.radii.mean() - 2.0) < 0.02
    assert abs(model.radii.std() / 2.0 - spread) < 0.01


def test_same_seed_same_disks_in_overlapping_regions():
    a = synth.make_speckle(region=(0, 0, 100, 80), seed=5)
    b = synth.make_speckle(region=(-50, 20, 300, 200), seed=5)
    c = synth.make_speckle(region=(0, 0, 100, 80), seed=6)

    def inside(m):  # disks whose centres lie well inside the overlap (0..100, 20..80)
        sel = (m.centres[:, 0] > 5) & (m.centres[:, 0] < 95) & (m.centres[:, 1] > 25) & (m.centres[:, 1] < 75)
        order = np.lexsort(m.centres[sel].T)
        return m.centres[sel][order], m.radii[sel][order]

    ca, ra = inside(a)
    cb, rb = inside(b)
    assert ca.shape[0] > 50 and np.array_equal(ca, cb) and np.array_equal(ra, rb)
    assert not np.array_equal(inside(c)[0][:10], ca[:10])


# (0.8, 0.9) overflows the 16 candidate disks per block; samples=3 takes the scalar column filter
@pytest.mark.parametrize("radius,density,samples", [(2.0, 0.5, 4), (0.8, 0.9, 4), (2.0, 0.5, 3)])
def test_rendered_pixels_match_numpy_quadrature(radius, density, samples):
    """The separable renderer equals a direct NumPy sum of the same quadrature, pixel by pixel."""
    # 57 columns: not a multiple of the 4 columns the filters compute at once
    model = synth.make_speckle((40, 57), radius=radius, density=density, samples=samples, bits=None, seed=2)
    image = synth.render(model, (40, 57))
    for y, x in [(0, 0), (5, 17), (20, 31), (39, 56), (33, 2)]:
        # float32 rendering of positions (< 64 px, ulp 4e-6 px) and weights: << 0.01 grey levels
        assert abs(image[y, x] - numpy_pixel(model, x, y)) < 0.01
    # evaluate() (direct per-point kernel) gives the same pixels
    yy, xx = np.mgrid[0:40, 0:57]
    assert np.max(np.abs(model.evaluate(xx, yy) - image)) < 0.01


def test_rendering_approximates_the_continuous_model():
    """Against the continuous model (binary disks, exact pixel x Gaussian kernel, 48 x 48 samples
    per pixel): the 4 x 4 sub-cell quadrature's error measured here is 0.41 grey levels RMS for a
    178.5 grey-level contrast (it falls as 1/samples²); bound 0.6 RMS and 1.5 max."""
    model = synth.make_speckle((64, 64), bits=None, seed=3)
    rng = np.random.default_rng(1)
    pts = rng.uniform(5, 58, size=(30, 2))
    sf, blur = 48, model.blur
    reach = math.ceil(4 * blur * sf)
    t = -0.5 + (np.arange(sf + 2 * reach) - reach + 0.5) / sf
    k = ndtr((t + 0.5) / blur) - ndtr((t - 0.5) / blur)
    k /= k.sum()
    errors = []
    for x, y in pts:
        qx, qy = np.meshgrid(x + t, y + t)
        pts_f = np.stack([qx.ravel(), qy.ravel()], axis=1)
        near = np.hypot(model.centres[:, 0] - x, model.centres[:, 1] - y) < model.radii + 4 * blur + 2
        cov = numpy_coverage(model.centres[near], model.radii[near], pts_f).reshape(qx.shape)
        exact = model.background + model.contrast * float(k @ cov @ k)
        errors.append(model.evaluate(x, y) - exact)
    errors = np.array(errors)
    assert np.sqrt(np.mean(errors**2)) < 0.6
    assert np.max(np.abs(errors)) < 1.5


def test_rigid_shift_is_the_model_at_shifted_coordinates():
    """No interpolation: the current image at x is the reference model evaluated at x - (u, v)."""
    u, v = 0.37, -0.81
    ref, cur, model = synth.speckle_pair((48, 64), (u, v), bits=None, seed=4, return_model=True)
    yy, xx = np.mgrid[0:48, 0:64]
    assert np.max(np.abs(model.evaluate(xx - u, yy - v) - cur)) < 0.01  # float32 rounding only
    assert np.max(np.abs(model.evaluate(xx, yy) - ref)) < 0.01
    for y, x in [(3, 4), (24, 40), (47, 63)]:
        assert abs(cur[y, x] - numpy_pixel(model, x - u, y - v)) < 0.01
    # integer shifts are exact copies of the reference image (shift-covariant quadrature)
    ref2, cur2 = synth.speckle_pair((48, 64), (3.0, -2.0), bits=None, seed=4)
    assert np.max(np.abs(cur2[:-2, 3:] - ref2[2:, :-3])) < 0.01  # cur(x, y) = ref(x - 3, y + 2)


def test_affine_and_sinusoidal_fields_map_material_points():
    """Deformed images show the model at X with x = X + u(X): compare with NumPy on a few pixels."""
    A = np.array([[0.02, -0.01], [0.015, -0.03]])
    a = np.array([1.3, -0.6])

    def affine(x, y):
        return a[0] + A[0, 0] * x + A[0, 1] * y, a[1] + A[1, 0] * x + A[1, 1] * y

    inv = np.linalg.inv(np.eye(2) + A)

    def affine_inverse(qx, qy):  # X = (I + A)^-1 (x - a), exact
        dx, dy = qx - a[0], qy - a[1]
        return inv[0, 0] * dx + inv[0, 1] * dy, inv[1, 0] * dx + inv[1, 1] * dy

    _, cur, model = synth.speckle_pair((40, 48), affine, bits=None, seed=8, return_model=True)
    for y, x in [(0, 0), (10, 30), (39, 47), (25, 5)]:
        # Keys interpolation reproduces affine fields exactly; float32 only
        assert abs(cur[y, x] - numpy_pixel(model, x, y, affine_inverse)) < 0.01

    def sine(x, y):
        return 5.0 * np.sin(2 * np.pi * y / 32.0), 0.5 * np.cos(2 * np.pi * x / 40.0)

    def sine_inverse(qx, qy):
        return synth.inverse_displacement(sine, qx, qy, tol=1e-12)

    _, cur, model = synth.speckle_pair((40, 48), sine, bits=None, seed=9, return_model=True)
    errs = [cur[y, x] - numpy_pixel(model, x, y, sine_inverse) for y, x in [(3, 3), (12, 20), (30, 44), (39, 10)]]
    # the inverse field is Keys-interpolated from the pixel grid: error ~ h^3 u''' / 10 with
    # u''' = 5 (2 pi / 32)^3 = 0.038 -> ~4e-3 px; times the largest image gradient (~100 grey/px
    # for a 178.5 contrast and 0.7 px blur) -> < 0.5 grey levels
    assert np.max(np.abs(errs)) < 0.5


def test_inverse_displacement_solves_forward_map():
    rng = np.random.default_rng(3)
    x, y = rng.uniform(0, 100, (2, 500))

    def f(x, y):
        return 3.0 * np.sin(x / 20.0) + 0.1 * y, -2.0 + 0.002 * x * y

    X, Y = synth.inverse_displacement(f, x, y)
    u, v = f(X, Y)
    assert np.max(np.abs(X + u - x)) < 1e-8 and np.max(np.abs(Y + v - y)) < 1e-8


def test_determinism_by_seed():
    f = lambda x, y: (0.01 * x, 0.3 + 0 * y)  # noqa: E731
    a = synth.speckle_pair((32, 40), f, noise_sigma=2.0, seed=11)
    b = synth.speckle_pair((32, 40), f, noise_sigma=2.0, seed=11)
    c = synth.speckle_pair((32, 40), f, noise_sigma=2.0, seed=12)
    assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])
    # speckle_image draws the same pattern and reference noise as speckle_pair for one seed
    assert np.array_equal(synth.speckle_image((32, 40), noise_sigma=2.0, seed=11), a[0])


def test_gaussian_noise_has_the_requested_std():
    shape = (256, 256)
    model = synth.make_speckle(shape, bits=None, seed=1)
    clean = synth.render(model, shape)
    noisy = synth.deformed_image(model, shape, None, noise_sigma=2.0, bits=None, seed=3)
    n = clean.size
    # sample std of n = 65536 normal draws: relative standard error 1 / sqrt(2 n) = 0.28 %; 5 sigma
    assert abs(np.std(noisy - clean) / 2.0 - 1.0) < 5 / math.sqrt(2 * n)
    assert abs(np.mean(noisy - clean)) < 5 * 2.0 / math.sqrt(n)
    # 8-bit: rounding adds a uniform error of variance 1/12
    q = synth.deformed_image(model, shape, None, noise_sigma=2.0, bits=8, seed=3)
    assert np.all(q == np.round(q)) and q.min() >= 0 and q.max() <= 255
    assert abs(np.std(q - clean) / math.sqrt(4.0 + 1 / 12) - 1.0) < 5 / math.sqrt(2 * n)


def test_poisson_noise_variance_follows_the_signal():
    shape = (128, 128)
    model = synth.make_speckle(shape, bits=16, seed=1)
    clean = synth.render(model, shape)
    full_well = 5000.0
    noisy = synth.add_noise(clean, poisson=True, full_well=full_well, bits=16, seed=2)
    # shot noise: variance (grey²) = I * full_scale / full_well (plus 1/12 from rounding to 16 bits);
    # check the normalised residual
    z = (noisy - clean) / np.sqrt(clean * 65535.0 / full_well + 1 / 12)
    n = z.size
    assert abs(np.std(z) - 1.0) < 5 / math.sqrt(2 * n)
    assert abs(np.mean(z)) < 5 / math.sqrt(n)


def test_bad_input_is_rejected():
    with pytest.raises(ValueError, match=r"density .* must be in \(0, 1\)"):
        synth.make_speckle((10, 10), density=1.2)
    with pytest.raises(ValueError, match="exactly one of shape"):
        synth.make_speckle()
    with pytest.raises(ValueError, match="bits must be 8, 16 or None"):
        synth.speckle_image((10, 10), bits=12)
    with pytest.raises(ValueError, match="did not converge"):
        synth.speckle_pair((16, 16), lambda x, y: (-2.0 * x, 0 * y))  # folds: gradient -2
    with pytest.raises(ValueError, match="only covers"):
        m = synth.make_speckle((16, 16))
        synth.deformed_image(m, (16, 16), (40.0, 0.0))
    with pytest.raises(ValueError, match="must return a pair"):
        synth.speckle_pair((16, 16), lambda x, y: x)
    with pytest.raises(ValueError, match="NaN"):
        synth.speckle_pair((16, 16), lambda x, y: (x * np.nan, y))
    with pytest.raises(ValueError, match="displacement must be None"):
        synth.speckle_pair((16, 16), "left")


# ---------------------------------------------------------------------------------------------
# specimen_on_background


def test_specimen_on_background_moves_the_specimen_only():
    shape = (96, 96)
    band = np.array([[-10.0, 30.0], [110.0, 36.0], [110.0, 70.0], [-10.0, 64.0]])

    def disp(x, y):
        return 1.5 + 0.01 * (x - 48), -1.0 + 0.005 * (y - 48)

    ref, cur, fraction = synth.specimen_on_background(shape, disp, specimen=band, background_level=12.0, seed=5)
    ref_s, cur_s = synth.speckle_pair(shape, disp, seed=5)
    assert ref.dtype == np.float32 and ref.shape == shape and fraction.shape == shape
    assert np.all((fraction >= 0) & (fraction <= 1))
    # well inside the specimen: exactly the speckle images of speckle_pair (same disks and noise)
    from scipy.ndimage import binary_erosion
    inner = binary_erosion(fraction >= 1.0, iterations=5)
    assert inner.sum() > 1000
    np.testing.assert_array_equal(ref[inner], ref_s[inner])
    np.testing.assert_array_equal(cur[inner], cur_s[inner])
    # far from it: the featureless background, in both images (it does not move)
    outer = binary_erosion(fraction <= 0.0, iterations=5)
    assert outer.sum() > 1000
    assert np.all(ref[outer] == 12.0) and np.all(cur[outer] == 12.0)
    # the edge is anti-aliased: fractions between 0 and 1 along it
    assert np.any((fraction > 0.2) & (fraction < 0.8))


def test_specimen_on_background_polygon_and_callable_agree():
    shape = (48, 64)
    square = np.array([[10.0, 8.0], [50.0, 8.0], [50.0, 40.0], [10.0, 40.0]])

    def inside(x, y):
        return (x >= 10) & (x <= 50) & (y >= 8) & (y <= 40)

    a = synth.specimen_on_background(shape, (0.4, -0.3), specimen=square, noise_sigma=1.0, seed=2)
    b = synth.specimen_on_background(shape, (0.4, -0.3), specimen=inside, noise_sigma=1.0, seed=2)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert a[2][24, 30] == 1.0 and a[2][2, 2] == 0.0


def test_specimen_on_background_rejects_bad_input():
    with pytest.raises(ValueError, match="specimen"):
        synth.specimen_on_background((32, 32), specimen=[[0, 0], [10, 10]])
    with pytest.raises(ValueError, match="specimen"):
        synth.specimen_on_background((32, 32), specimen=lambda x, y: np.ones(3, bool))
    with pytest.raises(ValueError, match="background_level"):
        synth.specimen_on_background((32, 32), specimen=lambda x, y: x > 10, background_level=float("nan"))
    with pytest.raises(ValueError, match="shape"):
        synth.specimen_on_background((0, 32), specimen=lambda x, y: x > 10)


# ---------------------------------------------------------------------------------------------
# evolving_sequence: long sequences with a growing stretch and an evolving texture


def _track_errors(seq, j, k, *, guess=False):
    """Track frame j -> k with plain IC-GN; per-POI |error| against the exact displacement, and the tracker.
    (robust=False: these tests show what a texture change does to plain IC-GN; the default, adaptive robust
    IC-GN, removes most of it, tests/kernels/test_icgn_robust.py.)"""
    from dic._track import Tracker

    tracker = Tracker(seq[j], step=5, subset=21, robust=False)
    truth = seq.displacement(tracker.points, k, since=j)
    field = tracker.track(seq[k], guess=truth if guess else None)
    err = np.hypot(field.u - truth[:, 0], field.v - truth[:, 1])
    return err, field.valid, tracker


@pytest.mark.parametrize("fade", [0.0, 0.05])
def test_evolving_sequence_frame0_is_the_plain_speckle_image(fade):
    kw = dict(radius=2.5, density=0.45, noise_sigma=1.5, seed=21)
    seq = synth.evolving_sequence((70, 90), 6, stretch_final=0.3, translation_final=(-4.0, 3.0),
                                  fade_fraction=fade, **kw)
    np.testing.assert_array_equal(seq[0], synth.speckle_image((70, 90), **kw))
    if fade == 0:  # nothing fades: every frame shows the same disks
        assert np.all(seq.alive(5)) and seq.pattern.radii.size == np.count_nonzero(seq.alive(0))


def test_evolving_sequence_ground_truth_by_tracking_consecutive_frames():
    # no fading: 30 % stretch over 11 frames (3 % per frame) plus a translation; errors < 0.02 px everywhere
    seq = synth.evolving_sequence((120, 150), 11, stretch_final=0.30, transverse_final=-0.09,
                                  translation_final=(2.5, -1.5), fade_fraction=0.0, seed=4)
    for j in (0, 5, 9):
        err, valid, _ = _track_errors(seq, j, j + 1)
        assert valid.mean() > 0.8
        assert err[valid].max() < 0.02, (j, err[valid].max())
    # Lagrangian truth relative to frame 0 (30 % at the last frame): the POIs that stay in view
    err, valid, tracker = _track_errors(seq, 0, 10, guess=True)  # up to 18 px: start IC-GN at the truth
    inside = np.all(np.abs(seq.to_frame(tracker.points, 10) - np.array(seq.centre)) < np.array([75 - 14, 60 - 14]), axis=1)
    assert valid[inside].all() and err[inside].max() < 0.02


def test_evolving_sequence_fading_changes_exactly_the_dead_and_born_speckles():
    seq = synth.evolving_sequence((160, 200), 11, stretch_final=0.30, fade_fraction=0.01, seed=8)
    # the requested fraction is replaced every frame and the count of speckles stays the same
    n0 = np.count_nonzero(seq.alive(0))
    assert seq.n_changed_per_frame == round(0.01 * n0)
    for k in range(1, 11):
        alive, before = seq.alive(k), seq.alive(k - 1)
        assert np.count_nonzero(alive) == n0
        assert seq.changed_fraction(k) == pytest.approx(0.01, abs=0.5 / n0)
        assert np.count_nonzero(alive & ~before) == np.count_nonzero(before & ~alive) == seq.n_changed_per_frame
    # the new disks cover the pattern's region uniformly
    new = seq.born > 0
    x0, y0, x1, y1 = seq.pattern.region
    c = seq.pattern.centres[new]
    assert np.all((c >= (x0, y0)) & (c <= (x1, y1)))
    # tracking j -> j+1: subsets that hold no changed speckle still match the exact displacement
    j = 4
    err, valid, tracker = _track_errors(seq, j, j + 1)
    changed = seq.alive(j) ^ seq.alive(j + 1)
    where = seq.to_frame(seq.pattern.centres[changed], j)  # changed disks as seen in frame j
    reach = 10 + seq.pattern.radii.max() * 1.3 + 4 * seq.pattern.blur + 1
    d = np.abs(tracker.points[:, None, :] - where[None, :, :]).max(axis=2).min(axis=1)
    clean = valid & (d > reach)
    assert clean.sum() > 30
    assert err[clean].max() < 0.02, err[clean].max()
    # and the texture change is what the correlation sees: those near a changed speckle err more
    touched = valid & (d < 10)
    assert np.median(err[touched]) > 5 * np.median(err[clean])


def test_evolving_sequence_static_images_differ_only_at_changed_speckles():
    seq = synth.evolving_sequence((80, 80), 4, stretch_final=0.0, fade_fraction=0.05, seed=2)
    diff = np.abs(seq.render(2) - seq.render(1))
    changed = seq.alive(1) ^ seq.alive(2)
    yy, xx = np.mgrid[0:80, 0:80]
    near = np.zeros((80, 80), bool)
    for (cx, cy), r in zip(seq.pattern.centres[changed], seq.pattern.radii[changed]):
        near |= np.hypot(xx - cx, yy - cy) < r + 4 * seq.pattern.blur + 1
    assert diff[~near].max() < 1e-3
    assert diff[near].max() > 50  # whole speckles appear or vanish


def test_evolving_sequence_is_deterministic_and_lazy():
    a = synth.evolving_sequence((48, 64), 5, fade_fraction=0.1, noise_sigma=2.0, seed=5)
    b = synth.evolving_sequence((48, 64), 5, fade_fraction=0.1, noise_sigma=2.0, seed=5)
    frames = list(a)
    assert len(frames) == len(a) == 5 and frames[0].dtype == np.float32 and frames[0].shape == (48, 64)
    for k in (4, 1, 3):  # any order, same images
        np.testing.assert_array_equal(b[k], frames[k])
    np.testing.assert_array_equal(b[-1], frames[4])
    c = synth.evolving_sequence((48, 64), 5, fade_fraction=0.1, noise_sigma=2.0, seed=6)
    assert not np.array_equal(c[2], frames[2])
    assert not np.array_equal(frames[1], frames[2])
    # frames are rendered on demand: nothing but the current frame's disks is kept
    assert a._frame_model[0] == 4


def test_evolving_sequence_rejects_bad_input():
    with pytest.raises(ValueError, match="n_frames"):
        synth.evolving_sequence((32, 32), 0)
    with pytest.raises(ValueError, match=r"fade_fraction .* must be in \[0, 1\)"):
        synth.evolving_sequence((32, 32), 5, fade_fraction=1.0)
    with pytest.raises(ValueError, match="fade_fraction"):
        synth.evolving_sequence((32, 32), 5, fade_fraction=float("nan"))
    with pytest.raises(ValueError, match="stretch_final must be > -0.5"):
        synth.evolving_sequence((32, 32), 5, stretch_final=-0.7)
    with pytest.raises(ValueError, match="translation_final"):
        synth.evolving_sequence((32, 32), 5, translation_final=(1.0,))
    with pytest.raises(ValueError, match="shape"):
        synth.evolving_sequence((0, 32), 5)
    with pytest.raises(ValueError, match="noise_sigma"):
        synth.evolving_sequence((32, 32), 5, noise_sigma=-1.0)
    with pytest.raises(ValueError, match="seed"):
        synth.evolving_sequence((32, 32), 5, seed=-3)
    seq = synth.evolving_sequence((32, 32), 5)
    with pytest.raises(IndexError, match="out of range"):
        seq[5]
    with pytest.raises(ValueError, match="out of range"):
        seq.alive(-6)
    with pytest.raises(ValueError, match="frame index must be an integer"):
        seq.frame(1.5)
    with pytest.raises(ValueError, match="points"):
        seq.displacement(np.zeros((3, 3)), 1)
