"""Bad input, table by table: every row names what is given and the error it must get (issue 15).

Images (NaN, inf, complex, masked, 3-D, colour, tiny, bool, object, empty), options (max_iter,
search radius, subset, step, strain window, zncc_min, order, roi, tol) for the library
(``dic.track``, ``dic.stereo``) and the CLI (``specula track``): the exception type and a fragment
of its message, or the exit status and a fragment of the CLI's one-line message (never a traceback).
"""
import time
import warnings

import numpy as np
import pytest
from click.testing import CliRunner

from calibration.camera import Camera
from calibration.stereo import StereoRig
from dic._track import Tracker, track
from dic.cli import main
from dic.io import write_image
from dic.synth import speckle_pair

H, W = 48, 56


@pytest.fixture(scope="module")
def pair():
    return speckle_pair((H, W), (0.5, 0.3), seed=1)


def _with(image, fn):
    img = np.array(image, dtype=np.float64)
    fn(img)
    return img


def _nan(img):
    img[3, 4] = np.nan


def _inf(img):
    img[3, 4] = np.inf


def _masked(ref):
    mask = np.zeros(ref.shape, bool)
    mask[:5, :5] = True
    return np.ma.masked_array(ref, mask=mask)


# id, make(ref) -> bad image, expected exception (None: accepted), message fragment
IMAGE_CASES = [
    ("nan", lambda ref: _with(ref, _nan), ValueError, "NaN or infinite"),
    ("inf", lambda ref: _with(ref, _inf), ValueError, "NaN or infinite"),
    ("complex", lambda ref: ref.astype(np.complex64) + 1j, ValueError, "is complex"),
    ("complex-zero-imaginary", lambda ref: ref.astype(np.complex128), ValueError, "is complex"),
    ("masked", _masked, ValueError, "roi="),
    ("3-D", lambda ref: np.stack([ref, ref], axis=-1), ValueError, "must be a 2-D array"),
    ("colour", lambda ref: np.dstack([ref] * 3), ValueError, "colour image"),
    ("1-D", lambda ref: ref.ravel(), ValueError, "must be a 2-D array"),
    ("tiny", lambda ref: ref[:3, :3], ValueError, "at least 4x4"),
    ("object", lambda ref: ref.astype(object), ValueError, "must be numeric"),
    ("string", lambda ref: np.full(ref.shape, "a"), ValueError, "must be numeric"),
    ("empty", lambda ref: np.zeros((0, 0)), ValueError, "is empty"),
    ("empty-rows", lambda ref: np.zeros((0, W)), ValueError, "is empty"),
    ("none", lambda ref: None, ValueError, "must be a 2-D array"),
    # accepted: bool images are grey levels 0/1; a masked array with nothing masked is its data
    ("bool", lambda ref: ref > np.median(ref), None, ""),
    ("masked-nothing", lambda ref: np.ma.masked_array(ref, mask=np.zeros(ref.shape, bool)), None, ""),
]


@pytest.mark.parametrize("make, error, fragment", [c[1:] for c in IMAGE_CASES], ids=[c[0] for c in IMAGE_CASES])
@pytest.mark.parametrize("which", ["reference", "current"])
def test_library_images(pair, which, make, error, fragment):
    ref, cur = pair
    bad = make(ref if which == "reference" else cur)
    args = (bad, cur) if which == "reference" else (ref, bad)
    if error is None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            field = track(*args, subset=11, step=8, device="cpu")
        assert field.n_points > 0
        return
    with pytest.raises(error, match=fragment):
        track(*args, subset=11, step=8, device="cpu")


def test_masked_array_message_says_how(pair):
    ref, cur = pair
    with pytest.raises(ValueError) as info:
        Tracker(_masked(ref), device="cpu")
    msg = str(info.value)
    assert "25 masked pixel(s)" in msg and "the mask would be ignored" in msg and "roi=~image.mask" in msg


def test_masked_array_as_roi_works(pair):
    """What the message advises: the mask as an ROI (True = measure) and the data as the image."""
    ref, cur = pair
    m = _masked(ref)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        field = track(m.filled(0), cur, roi=~m.mask, subset=11, step=8, device="cpu")
    assert field.n_points > 0
    r = 11 // 2
    x, y = field.points.T
    assert not np.any((x - r < 5) & (y - r < 5) & (x < 5) & (y < 5))


# id, Tracker keyword arguments, message fragment (all ValueError)
OPTION_CASES = [
    ("max_iter=0", {"max_iter": 0}, r"max_iter must be an integer in \[1, 10000\]"),
    ("max_iter=3e9 (int32 wrap)", {"max_iter": 3_000_000_000}, r"max_iter must be an integer in \[1, 10000\]"),
    ("max_iter=10001", {"max_iter": 10001}, r"max_iter must be an integer in \[1, 10000\]"),
    ("max_iter=2.5", {"max_iter": 2.5}, "max_iter must be"),
    ("max_iter=True", {"max_iter": True}, "max_iter must be"),
    ("search_radius=-1", {"search_radius": -1}, "search_radius must be a non-negative integer"),
    ("search_radius=1.5", {"search_radius": 1.5}, "search_radius must be a non-negative integer"),
    ("search=bogus", {"search": "bogus"}, "search must be None or one of"),
    ("search=epipolar", {"search": "epipolar"}, "search must be None or one of"),
    ("subset=20", {"subset": 20}, "subset must be an odd integer"),
    ("subset=1", {"subset": 1}, "subset must be an odd integer"),
    ("subset=9.0", {"subset": 9.5}, "subset must be an odd integer"),
    ("subset > image", {"subset": 101}, "no POI"),
    ("step=0", {"step": 0}, "step must be a positive integer"),
    ("step=-3", {"step": -3}, "step must be a positive integer"),
    ("step=2.5", {"step": 2.5}, "step must be a positive integer"),
    ("zncc_min=2", {"zncc_min": 2}, r"zncc_min must be in \[-1.0, 1.0\]"),
    ("zncc_min=nan", {"zncc_min": float("nan")}, r"zncc_min must be in \[-1.0, 1.0\]"),
    ("zncc_min=str", {"zncc_min": "0.9"}, "zncc_min must be a number"),
    ("order=3", {"order": 3}, "order must be 1"),
    ("order='1'", {"order": "1"}, "order must be 1"),
    ("tol=0", {"tol": 0}, "tol must be a positive finite number"),
    ("tol=nan", {"tol": float("nan")}, "tol must be a positive finite number"),
    ("roi=empty box", {"roi": (40, 40, 10, 10)}, "is empty"),
    ("roi=mask of another shape", {"roi": np.ones((3, 3), bool)}, "roi mask must have the image shape"),
    ("roi=all False", {"roi": np.zeros((H, W), bool)}, "no POI left"),
    ("roi=missing mask file", {"roi": "x"}, "roi mask file: image file not found"),
    ("points and roi", {"points": [[20.0, 20.0]], "roi": (0, 0, 10, 10)}, "either points or roi"),
    ("points=empty", {"points": np.zeros((0, 2))}, "points is empty"),
    ("points=nan", {"points": [[np.nan, 1.0]]}, "NaN"),
    ("flat_std=-1", {"flat_std": -1}, "flat_std must be"),
]


@pytest.mark.parametrize("kwargs, fragment", [c[1:] for c in OPTION_CASES], ids=[c[0] for c in OPTION_CASES])
def test_library_options(pair, kwargs, fragment):
    ref, _ = pair
    kwargs = {"subset": 11, **kwargs}
    with pytest.raises(ValueError, match=fragment):
        Tracker(ref, device="cpu", **kwargs)


def test_icgn_max_iter_bounded(pair):
    from kernels.icgn import MAX_ITER, icgn, prepare_reference, prepare_subsets

    ref, cur = pair
    subsets = prepare_subsets(prepare_reference(ref, device="cpu"), [[20.0, 20.0]], subset=11)
    for bad in (0, MAX_ITER + 1, 3_000_000_000, 2**31, -1):
        with pytest.raises(ValueError, match=rf"max_iter must be an integer in \[1, {MAX_ITER}\]"):
            icgn(subsets, cur, max_iter=bad)
    res = icgn(subsets, cur, max_iter=MAX_ITER)
    assert res.status.numpy()[0] == 0  # converges, as with the default limit


# -- search radius: clamped to what the image allows ------------------------------------------------


def test_huge_search_radius_is_clamped_to_the_image():
    from kernels.search import useful_radius, zncc_search

    ref, cur = speckle_pair((64, 72), (7.6, -5.2), seed=5)
    pts = np.array([[20.0, 20.0], [36, 30], [50, 40], [3, 3]])
    most = useful_radius(ref.shape, pts, 11)
    assert 0 < most <= max(ref.shape)
    expected = zncc_search(ref, cur, pts, most, subset=11, device="cpu")
    assert expected[0][:3].tolist() == [[8, -5]] * 3
    for radius in (most + 1, 1000, 2**31, 10**30):
        t0 = time.perf_counter()
        uv, cc = zncc_search(ref, cur, pts, radius, subset=11, device="cpu")
        assert time.perf_counter() - t0 < 5.0
        assert np.array_equal(uv, expected[0]) and np.array_equal(cc, expected[1], equal_nan=True)
    with pytest.raises(ValueError, match="start must lie within"):
        zncc_search(ref, cur, pts, 2**31, subset=11, start=np.full((4, 2), 1e12), device="cpu")


@pytest.mark.parametrize("method", ["zncc", "pyramid", "rg"])
def test_tracker_huge_search_radius_is_fast_and_the_same(method):
    ref, cur = speckle_pair((64, 72), (7.6, -5.2), seed=5)
    largest_useful = int(np.ceil(np.hypot(*ref.shape)))
    fields = []
    for radius in (largest_useful, 2**30, 2**31, 10**400):
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            fields.append(Tracker(ref, subset=11, step=8, search=method, search_radius=radius, device="cpu").track(cur))
        assert time.perf_counter() - t0 < 10.0
    a = fields[0]
    for b in fields[1:]:
        assert np.array_equal(a.params, b.params, equal_nan=True) and np.array_equal(a.status, b.status)
    assert np.count_nonzero(a.valid) > 0.6 * a.n_points  # the border POIs move off the image


def test_pyramid_levels_bounded():
    from kernels.search import pyramid

    img = np.random.default_rng(0).random((20, 30))
    assert len(pyramid(img, 3, device="cpu")) == 4
    with pytest.raises(ValueError, match="levels must be <= 4 for a 30x20 px image"):
        pyramid(img, 10**9, device="cpu")


# -- strain window vs the grid --------------------------------------------------------------------


def test_strain_window_larger_than_the_grid(pair):
    from dic._strain import check_strain_window, strain

    ref, cur = pair
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        field = track(ref, cur, subset=11, step=4, device="cpu")
    from dic._strain import grid_layout

    ny, nx = grid_layout(field.points)[1]
    assert strain(field, window=5).valid.any()
    with pytest.raises(ValueError, match="no strain could be computed; use a window of at most"):
        strain(field, window=999)
    with pytest.raises(ValueError, match="window must be an odd integer"):
        strain(field, window=4)
    with pytest.raises(ValueError, match=r"min_points must be in \[3, 25\]"):
        strain(field, window=5, min_points=26)
    assert check_strain_window(5, (10, 10)) == (5, 9)
    assert check_strain_window(19, (10, 10)) == (19, 100)
    with pytest.raises(ValueError, match="use a window of at most 19"):
        check_strain_window(21, (10, 10))
    assert check_strain_window(5, (1, 40)) == (5, 9)  # no window fits one row: not the window's fault
    assert check_strain_window(5, (2, 40)) == (5, 9)
    with pytest.raises(ValueError, match="use a window of at most 5"):
        check_strain_window(7, (2, 40))
    with pytest.raises(ValueError, match="window must be an odd integer"):
        check_strain_window(10**9, (10, 10))
    assert (ny, nx) == (10, 12)


def test_stereo_strain_window_vs_grid():
    from dic.field3d import check_grid_window, grid_neighbours, surface_strain_grid

    assert check_grid_window(99, (50, 50)) == 99
    with pytest.raises(ValueError, match="use a window of at most 99"):
        check_grid_window(101, (50, 50))
    with pytest.raises(ValueError, match="larger than the 3 x 4 grid"):
        grid_neighbours((3, 4), 999)
    X = np.zeros((12, 3))
    with pytest.raises(ValueError, match="larger than the 3 x 4 grid"):
        surface_strain_grid(X, X, np.ones(12, bool), (3, 4), 999)


# -- stereo (validation happens before any correlation: cheap) ------------------------------------


@pytest.fixture(scope="module")
def stereo_setup(tmp_path_factory):
    h, w = 120, 160
    K = np.array([[400.0, 0, w / 2 - 0.5], [0, 400.0, h / 2 - 0.5], [0, 0, 1]])
    rig = StereoRig(Camera(K, np.zeros(5), (w, h), "left"), Camera(K, np.zeros(5), (w, h), "right"),
                    np.eye(3), [-100.0, 0.0, 0.0])
    left, _ = speckle_pair((h, w), None, seed=2)
    right, _ = speckle_pair((h, w), None, seed=3)
    path = tmp_path_factory.mktemp("rig") / "rig.json"
    rig.save(path)
    return rig, left, right, path


# id, keyword arguments of StereoCorrelation (rig/left/right replaced when given), fragment
STEREO_CASES = [
    ("max_iter=3e9", {"max_iter": 3_000_000_000}, r"max_iter must be an integer in \[1, 10000\]"),
    ("max_iter=0", {"max_iter": 0}, r"max_iter must be an integer in \[1, 10000\]"),
    ("strain_window=999", {"strain_window": 999}, "larger than the"),
    ("strain_window=4", {"strain_window": 4}, "strain window must be an odd integer"),
    ("zncc_min=2", {"zncc_min": 2}, "zncc_min must be in"),
    ("subset=20", {"subset": 20}, "subset must be an odd integer"),
    ("order=3", {"order": 3}, "order must be 1"),
    ("epipolar_tol_px=0", {"epipolar_tol_px": 0}, "epipolar_tol_px"),
    ("rig=123", {"rig": 123}, "rig must be a calibration.stereo.StereoRig or the path of a rig file"),
    ("rig=missing path", {"rig": "no/such/rig.json"}, "does not exist"),
    ("rig=unknown suffix", {"rig": "rig.txt"}, "does not exist|unknown format"),
    ("left complex", {"left": "complex"}, "is complex"),
    ("left masked", {"left": "masked"}, "roi="),
    ("left nan", {"left": "nan"}, "NaN"),
]


@pytest.mark.parametrize("kwargs, fragment", [c[1:] for c in STEREO_CASES], ids=[c[0] for c in STEREO_CASES])
def test_stereo_options(stereo_setup, kwargs, fragment):
    from dic._stereo import StereoCorrelation

    rig, left, right, _ = stereo_setup
    kwargs = dict(kwargs)
    rig = kwargs.pop("rig", rig)
    bad = kwargs.pop("left", None)
    if bad == "complex":
        left = left.astype(np.complex64)
    elif bad == "masked":
        left = _masked(left)
    elif bad == "nan":
        left = _with(left, _nan)
    with pytest.raises(ValueError, match=fragment):
        StereoCorrelation(rig, left, right, step=20, device="cpu", **kwargs)


def test_stereo_rig_given_as_a_path(stereo_setup, tmp_path):
    """A path is read (Specula JSON; OpenCV YAML) before the other checks: max_iter=0 is what fails."""
    from calibration.formats import save_opencv
    from dic._stereo import StereoCorrelation, stereo
    from dic.sequence import stereo_sequence

    rig, left, right, path = stereo_setup
    yml = tmp_path / "rig.yml"
    save_opencv(yml, rig)
    for p in (path, str(path), yml):
        with pytest.raises(ValueError, match="max_iter"):
            StereoCorrelation(p, left, right, step=20, max_iter=0, device="cpu")
        with pytest.raises(ValueError, match="max_iter"):
            stereo(p, left, right, step=20, max_iter=0, device="cpu")
        with pytest.raises(ValueError, match="max_iter"):
            stereo_sequence(p, [(left, right)], tmp_path / "out.h5", step=20, max_iter=0, mode="overwrite")


def test_as_rig(stereo_setup, tmp_path):
    from calibration import as_rig, load_rig
    from calibration.formats import save_dice_xml, save_opencv

    rig, _, _, path = stereo_setup
    assert as_rig(rig) is rig
    for p, save in ((tmp_path / "r.yml", save_opencv), (tmp_path / "r.xml", save_opencv),
                    (tmp_path / "dice.xml", save_dice_xml)):
        save(p, rig)
        back = load_rig(p)
        assert np.allclose(back.left.K, rig.left.K) and np.allclose(back.t_right_left, rig.t_right_left)
    assert np.allclose(as_rig(path).R_right_left, rig.R_right_left)
    save_opencv(tmp_path / "cam.yml", rig.left)
    with pytest.raises(ValueError, match="holds one camera"):
        load_rig(tmp_path / "cam.yml")
    (tmp_path / "r.txt").write_text("x")
    with pytest.raises(ValueError, match="is not a calibration file Specula reads"):
        load_rig(tmp_path / "r.txt")
    (tmp_path / "bad.xml").write_text("<a><b>")
    with pytest.raises(ValueError, match="not well-formed XML"):
        load_rig(tmp_path / "bad.xml")
    with pytest.raises(ValueError, match="is not a file"):
        load_rig(tmp_path)
    with pytest.raises(ValueError, match="rig must be"):
        as_rig(None)


# -- the CLI: one clear message, exit status 1 or 2, no traceback ----------------------------------


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    d = tmp_path_factory.mktemp("imgs")
    ref, cur = speckle_pair((64, 72), (0.5, -0.3), seed=11)
    paths = [write_image(d / "ref.tif", ref, bits=8), write_image(d / "cur.tif", cur, bits=8)]
    import tifffile

    tifffile.imwrite(d / "complex.tif", ref.astype(np.complex64))
    (d / "blocker").write_text("a file, not a folder")
    return d, [str(p) for p in paths]


# id, extra arguments after "track REF CUR -o OUT", exit status, message fragment
CLI_CASES = [
    ("--max-iter 3000000000", ["--max-iter", "3000000000"], 2, "1<=x<=10000"),
    ("--max-iter 0", ["--max-iter", "0"], 2, "1<=x<=10000"),
    ("--max-iter abc", ["--max-iter", "abc"], 2, "is not a valid integer"),
    ("--search 0", ["--search", "0"], 2, "--search"),
    ("--search 2**31", ["--search", str(2**31)], 2, "--search"),
    ("--search-method bogus", ["--search", "5", "--search-method", "bogus"], 2, "--search-method"),
    ("--subset 20", ["--subset", "20"], 2, "odd"),
    ("--subset 1001", ["--subset", "1001"], 1, "no POI"),
    ("--step 0", ["--step", "0"], 2, "--step"),
    ("--strain-window 999", ["--strain-window", "999"], 2, "no strain could be computed"),
    ("--strain-window 4", ["--strain-window", "4"], 2, "odd"),
    ("--order 3", ["--order", "3"], 2, "--order"),
    ("--tol 0", ["--tol", "0"], 2, "--tol"),
    # the run record checks what click lets through: a usage error naming the option, as for --tol 0
    ("--tol nan", ["--tol", "nan"], 2, "Invalid value for --tol: tol must be a positive finite number"),
    ("--device bogus", ["--device", "bogus"], 1, "bogus"),
]


def _clean(result, code: int, fragment: str):
    assert result.exit_code == code, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), repr(result.exception)
    assert "Traceback" not in result.output
    assert fragment in result.output, result.output


@pytest.mark.parametrize("extra, code, fragment", [c[1:] for c in CLI_CASES], ids=[c[0] for c in CLI_CASES])
def test_cli_options(images, tmp_path, extra, code, fragment):
    _, (ref, cur) = images
    r = CliRunner().invoke(main, ["track", ref, cur, "-o", str(tmp_path / "o.h5"), "-q", *extra])
    _clean(r, code, fragment)


def test_cli_max_iter_bound_is_the_library_one():
    from dic.commands.track import track as cmd
    from kernels.icgn import MAX_ITER

    opt = next(p for p in cmd.params if p.name == "max_iter")
    assert opt.type.max == MAX_ITER


def test_cli_images_and_paths(images, tmp_path):
    d, (ref, cur) = images
    runner = CliRunner()
    cases = [
        ([ref, str(d / "complex.tif")], 1, "unsupported pixel type complex"),
        ([str(d / "missing.tif"), cur], 1, "image file not found"),
        ([ref, cur, "-o", str(d / "blocker" / "out.h5")], 1, "blocker"),
    ]
    for args, code, fragment in cases:
        if "-o" not in args:
            args = [*args, "-o", str(tmp_path / "o.h5")]
        _clean(runner.invoke(main, ["track", *args, "-q"]), code, fragment)


def test_cli_stereo_rig_files(images, stereo_setup, tmp_path):
    """``specula stereo --rig`` reads any rig format; a camera file or an unknown suffix is one clear error."""
    from calibration.formats import save_opencv

    d, (ref, cur) = images
    rig = stereo_setup[0]
    save_opencv(tmp_path / "cam.yml", rig.left)
    (tmp_path / "rig.txt").write_text("R T")
    runner = CliRunner()
    for rig_file, fragment in ((tmp_path / "cam.yml", "holds one camera"), (tmp_path / "rig.txt", "is not a calibration file Specula reads"),
                               (tmp_path / "none.json", "does not exist")):
        r = runner.invoke(main, ["stereo", "--rig", str(rig_file), ref, cur, "-o", str(tmp_path / "s.h5"), "-q"])
        _clean(r, 1, fragment)
    save_opencv(tmp_path / "rig.yml", rig)  # read, then refused for the image size (64x72 images, 160x120 rig)
    r = runner.invoke(main, ["stereo", "--rig", str(tmp_path / "rig.yml"), ref, cur, "-o", str(tmp_path / "s.h5"), "-q"])
    _clean(r, 1, "calibrated for 160x120 px images")


def test_cli_huge_search_is_clamped_and_quick(images, tmp_path):
    _, (ref, cur) = images
    t0 = time.perf_counter()
    r = CliRunner().invoke(main, ["track", ref, cur, "-o", str(tmp_path / "o.h5"), "--subset", "11", "--step", "8",
                                  "--search", "1073741824", "--search-method", "zncc", "--device", "cpu"])
    assert r.exit_code == 0, r.output
    assert time.perf_counter() - t0 < 30.0
    n_valid, n = (int(v) for v in r.output.split("frame 1: ")[1].split(" valid")[0].split("/"))
    assert n_valid > 0.8 * n


def test_cli_user_errors_become_one_message_and_bugs_keep_their_traceback(images, tmp_path, monkeypatch):
    import dic.commands.track as cmd

    _, (ref, cur) = images
    runner = CliRunner()
    args = ["track", ref, cur, "-o", str(tmp_path / "o.h5"), "-q"]
    for exc, fragment in ((ValueError("a bad value"), "Error: a bad value"),
                          (PermissionError(13, "Permission denied", "/x/y.h5"), "Error: /x/y.h5: Permission denied"),
                          (OSError(28, "No space left on device"), "Error: No space left on device")):
        def boom(*a, exc=exc, **k):
            raise exc

        monkeypatch.setattr(cmd, "_make_tracker", boom)
        _clean(runner.invoke(main, args), 1, fragment)

    def bug(*a, **k):
        raise KeyError("genuine bug")

    monkeypatch.setattr(cmd, "_make_tracker", bug)
    r = runner.invoke(main, args)
    assert isinstance(r.exception, KeyError)
