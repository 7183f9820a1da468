"""Post-processing (dic/postprocess.py, dic/plots/postprocess.py, dic/commands/postprocess.py).

Ground truth: hand-computed principal strains; a synthetic 2-D sequence (dic.synth) of 4 frames
with a growing uniform strain, tracked by dic.track; stereo fields built with an exactly affine
displacement (linear interpolation reproduces it exactly).
"""
import math

import numpy as np
import pytest
from click.testing import CliRunner

from dic.cli import main
from dic.postprocess import (
    SCALE_KEY,
    extensometer,
    line_profile,
    load_results,
    point_history,
    principal_strains,
    quantities,
    recompute_strain,
    results_scale,
    window_points,
)
from dic.store import ResultWriter, read_results

# ------------------------------------------------------------------------------------------------
# principal strains, maximum shear, von Mises: hand-computed cases


def test_uniaxial_strain():
    p = principal_strains(0.01, 0.0, 0.0)
    assert (p.e1, p.e2, p.angle, p.max_shear) == (0.01, 0.0, 0.0, 0.005)
    assert p.von_mises == pytest.approx(2 / math.sqrt(3) * 0.01, abs=1e-15)


def test_incompressible_uniaxial_strain_has_von_mises_equal_to_the_axial_strain():
    p = principal_strains(0.02, -0.01, 0.0)
    assert p.von_mises == pytest.approx(0.02, abs=1e-15)
    assert p.max_shear == pytest.approx(0.015, abs=1e-15)


def test_pure_shear():
    g = 0.003  # tensor shear: engineering shear 0.006
    p = principal_strains(0.0, 0.0, g)
    assert p.e1 == pytest.approx(g, abs=1e-16) and p.e2 == pytest.approx(-g, abs=1e-16)
    assert p.angle == pytest.approx(math.pi / 4, abs=1e-15)
    assert p.max_shear == pytest.approx(g, abs=1e-16)
    assert p.von_mises == pytest.approx(2 * g / math.sqrt(3), abs=1e-16)  # gamma / sqrt(3)
    assert principal_strains(0.0, 0.0, -g).angle == pytest.approx(-math.pi / 4, abs=1e-15)


@pytest.mark.parametrize("theta", [0.0, 0.3, -0.7, 1.2, math.pi / 2])
def test_rotated_uniaxial_strain(theta):
    e1, e2 = 0.012, -0.004
    c, s = math.cos(theta), math.sin(theta)
    exx = e1 * c * c + e2 * s * s
    eyy = e1 * s * s + e2 * c * c
    exy = (e1 - e2) * s * c
    p = principal_strains(np.array([exx]), np.array([eyy]), np.array([exy]))
    assert p.e1[0] == pytest.approx(e1, abs=1e-15) and p.e2[0] == pytest.approx(e2, abs=1e-15)
    assert p.max_shear[0] == pytest.approx(0.008, abs=1e-15)
    # the angle is defined modulo pi, in (-pi/2, pi/2]
    want = math.atan2(math.sin(2 * theta), math.cos(2 * theta)) / 2
    assert p.angle[0] == pytest.approx(want, abs=1e-12)
    assert p.von_mises[0] == pytest.approx(2 / math.sqrt(3) * math.sqrt(e1 * e1 + e1 * e2 + e2 * e2), abs=1e-15)


def test_principal_strains_of_objects_and_errors():
    from types import SimpleNamespace

    p = principal_strains({"exx": np.array([0.0, np.nan]), "eyy": np.array([0.0, 0.0]), "exy": np.array([0.001, 0.0])})
    assert p.e1[0] == pytest.approx(0.001) and np.isnan(p.e1[1]) and np.isnan(p.von_mises[1])
    q = principal_strains(SimpleNamespace(exx=0.01, eyy=0.0, exy=0.0))
    assert q.e1 == 0.01
    with pytest.raises(ValueError, match="one shape"):
        principal_strains(np.zeros(3), np.zeros(2), np.zeros(3))
    with pytest.raises(ValueError, match="all three components"):
        principal_strains(np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="has no exy"):
        principal_strains({"exx": 1, "eyy": 2})
    with pytest.raises(ValueError, match="exx, eyy, exy arrays"):
        principal_strains(3.0)


def test_window_points():
    assert window_points(7, 5) == 7
    assert window_points(30, 6, "px") == 5      # span 4 steps = 24 px <= 30
    assert window_points(24, 6, "px") == 5
    assert window_points(23.9, 6, "px") == 3
    assert window_points(12, (6.0, 6.0), "px") == 3
    with pytest.raises(ValueError, match="fewer than 3 grid points"):
        window_points(11, 6, "px")
    with pytest.raises(ValueError, match="equal grid steps"):
        window_points(30, (6.0, 5.0), "px")
    with pytest.raises(ValueError, match="odd"):
        window_points(4, 6)
    with pytest.raises(ValueError, match="unit must be"):
        window_points(5, 6, "mm")
    with pytest.raises(ValueError, match="positive length"):
        window_points(-5, 6, "px")


# ------------------------------------------------------------------------------------------------
# a synthetic 2-D sequence with growing uniform strain

SHAPE = (120, 160)
CX, CY = 80.0, 60.0
STRAINS = (0.0025, 0.005, 0.0075, 0.01)  # exx per frame; eyy = -0.3 exx
NU = 0.3
STEP = 6


def _disp(e):
    return lambda x, y: (e * (x - CX), -NU * e * (y - CY))


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    """A 2-D result file of 4 frames (uniform strain growing to 1 %), tracked from synthetic speckle."""
    from dic._strain import strain
    from dic._track import Tracker
    from dic.synth import deformed_image, speckle_pair

    ref, _, model = speckle_pair(SHAPE, _disp(STRAINS[-1]), seed=5, return_model=True)
    tracker = Tracker(ref, subset=21, step=STEP, device="cpu")
    path = tmp_path_factory.mktemp("post") / "seq.h5"
    with ResultWriter(path, reference_path="ref.tif", reference_shape=ref.shape, settings={"strain_window": 5}) as w:
        for k, e in enumerate(STRAINS):
            cur = deformed_image(model, SHAPE, _disp(e), bits=8, seed=100 + k)
            field = tracker.track(cur)
            w.write_frame(k + 1, field, strain=strain(field, window=5), path=f"cur{k + 1}.tif", attrs={"seconds": 1.0})
    return path


def test_extensometer_matches_the_applied_strain(sequence):
    ext = extensometer(sequence, (40, 60), (120, 60))
    assert ext.unit == "px" and list(ext.frames) == [1, 2, 3, 4] and ext.valid.all()
    assert np.all(ext.length0 == 80.0)
    # u = e (x - 80): the gauge stretches by exactly e; the tracked displacements carry the
    # measurement noise of 8-bit images (~0.01 px at each end over 80 px)
    assert np.max(np.abs(ext.strain - np.array(STRAINS))) < 4e-4
    assert np.allclose(ext.elongation, ext.strain * 80.0)
    assert np.max(np.abs(ext.start_displacement[:, 0] + 40 * np.array(STRAINS))) < 0.03
    # along y the strain is -0.3 e
    ey = extensometer(sequence, (80, 25), (80, 95))
    assert np.max(np.abs(ey.strain + NU * np.array(STRAINS))) < 4e-4
    # a diagonal gauge: length from the exact affine map
    d = extensometer(sequence, (40, 30), (120, 90), frames=[2, 4])
    want = [math.hypot(80 * (1 + e), 60 * (1 - NU * e)) / 100 - 1 for e in (STRAINS[1], STRAINS[3])]
    assert list(d.frames) == [2, 4] and np.max(np.abs(d.strain - want)) < 4e-4


def test_extensometer_outside_the_valid_points_is_nan(sequence):
    ext = extensometer(sequence, (2, 2), (120, 60))  # (2, 2) is outside the grid of points
    assert not ext.valid.any() and np.all(np.isnan(ext.strain)) and np.all(ext.length0 == pytest.approx(math.hypot(118, 58)))


def test_point_history_and_line_profile(sequence):
    e = np.array(STRAINS)
    h = point_history(sequence, (110, 40), "u")
    assert h.unit == "px" and np.max(np.abs(h.values - e * 30)) < 0.03
    hv = point_history(sequence, (110, 40), "v")
    assert np.max(np.abs(hv.values - (-NU * e * -20))) < 0.03
    hx = point_history(sequence, (80, 60), "exx")
    assert hx.unit == "" and np.max(np.abs(hx.values - e)) < 5e-4
    h1 = point_history(sequence, (80, 60), "e1")
    assert np.max(np.abs(h1.values - e)) < 5e-4
    hvm = point_history(sequence, (80, 60), "von_mises")
    want = 2 / math.sqrt(3) * e * math.sqrt(1 - NU + NU * NU)
    assert np.max(np.abs(hvm.values - want)) < 5e-4
    p = line_profile(sequence, (30, 60), (130, 60), "u", frames=[4])
    assert p.values.shape == (1, p.distance.size) and p.distance.size == round(100 / STEP) + 1
    assert p.distance[0] == 0 and p.distance[-1] == pytest.approx(100)
    assert np.max(np.abs(p.values[0] - 0.01 * (p.positions[:, 0] - CX))) < 0.03
    p5 = line_profile(sequence, (30, 60), (130, 60), "exx", samples=5)
    assert p5.values.shape == (4, 5)
    names, table = p5.table()
    assert names == ["frame", "distance_px", "x_px", "y_px", "exx"] and table.shape == (20, 5)
    assert set(quantities(sequence)) >= {"u", "v", "exx", "e1", "e2", "angle", "max_shear", "von_mises"}


def test_scale_gives_mm_and_leaves_strain_unchanged(sequence, tmp_path):
    s = 0.05
    ext_px = extensometer(sequence, (40, 60), (120, 60))
    ext = extensometer(sequence, (40, 60), (120, 60), scale=s)
    assert ext.unit == "mm" and np.allclose(ext.length0, 80 * s) and np.allclose(ext.elongation, ext_px.elongation * s)
    assert np.allclose(ext.strain, ext_px.strain, rtol=0, atol=1e-15)
    # positions in mm are px times the scale
    ext_mm = extensometer(sequence, (2.0, 3.0), (6.0, 3.0), at="mm", scale=s)
    assert np.allclose(ext_mm.strain, ext_px.strain, rtol=0, atol=1e-15)
    h = point_history(sequence, (110, 40), "u", scale=s)
    assert h.unit == "mm" and np.allclose(h.values, point_history(sequence, (110, 40), "u").values * s)
    # a scale stored in the file is used by default
    scaled = recompute_strain(sequence, tmp_path / "scaled.h5", window=5, scale=s)
    res = read_results(scaled)
    assert res.settings[SCALE_KEY] == s and results_scale(res) == s
    assert extensometer(scaled, (40, 60), (120, 60)).unit == "mm"
    with pytest.raises(ValueError, match="positions in mm need a scale"):
        extensometer(sequence, (2, 3), (6, 3), at="mm")
    with pytest.raises(ValueError, match="positive finite number"):
        extensometer(sequence, (40, 60), (120, 60), scale=-1.0)


def test_recompute_strain(sequence, tmp_path):
    from dic._strain import strain

    before = read_results(sequence)
    same = read_results(recompute_strain(sequence, tmp_path / "same.h5", window=5))
    for i, f in before.frames.items():
        g = same.frames[i]
        for key in ("points", "u", "v", "params", "zncc", "iterations", "status", "valid"):
            assert np.array_equal(getattr(f, key), getattr(g, key))
        for key in ("exx", "eyy", "exy", "Exx", "valid"):
            assert np.array_equal(f.strain[key], g.strain[key], equal_nan=True)
        assert g.attrs["seconds"] == 1.0 and g.path == f.path
    assert same.reference == before.reference
    # another window, given in px: 36 px at a 6 px step is 7 grid points
    wide = read_results(recompute_strain(sequence, tmp_path / "wide.h5", window=36, unit="px"))
    assert wide.settings["strain_window"] == 7
    f4 = before.frames[4]
    ref7 = strain(f4, window=7)
    assert np.array_equal(wide.frames[4].strain["exx"], ref7.exx, equal_nan=True)
    assert wide.frames[4].strain["window"] == 7
    # the wider fit averages more noise
    assert np.nanstd(ref7.exx) < np.nanstd(f4.strain["exx"])
    # in place
    copy = tmp_path / "copy.h5"
    copy.write_bytes(sequence.read_bytes())
    assert recompute_strain(copy, window=9) == copy
    back = read_results(copy)
    assert back.settings["strain_window"] == 9 and back.frames[1].strain["window"] == 9
    assert np.array_equal(back.frames[1].u, before.frames[1].u)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temporary file left
    with pytest.raises(ValueError, match="fewer than 3 grid points"):
        recompute_strain(sequence, tmp_path / "x.h5", window=10, unit="px")
    with pytest.raises(ValueError, match="ending in .h5"):
        recompute_strain(sequence, tmp_path / "x.csv", window=5)
    with pytest.raises(ValueError, match="result file not found"):
        recompute_strain(tmp_path / "missing.h5", tmp_path / "y.h5", window=5)
    (tmp_path / "dir.h5").mkdir()
    with pytest.raises(ValueError, match="cannot write .*dir.h5"):
        recompute_strain(sequence, tmp_path / "dir.h5", window=5)
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_errors_name_the_problem(sequence, tmp_path):
    with pytest.raises(ValueError, match="unknown quantity 'w'.*choose one of u, v"):
        point_history(sequence, (80, 60), "w")
    with pytest.raises(ValueError, match=r"no finished frame 7.*available: \[1, 2, 3, 4\]"):
        point_history(sequence, (80, 60), "u", frames=[7])
    with pytest.raises(ValueError, match="finite point"):
        point_history(sequence, (80, np.nan), "u")
    with pytest.raises(ValueError, match="gauge ends coincide"):
        extensometer(sequence, (80, 60), (80, 60))
    with pytest.raises(ValueError, match="at must be"):
        extensometer(sequence, (80, 60), (90, 60), at="in")
    with pytest.raises(ValueError, match="samples must be an integer >= 2"):
        line_profile(sequence, (30, 60), (130, 60), "u", samples=1)
    with pytest.raises(ValueError, match=r"must be a result file \(path\) or what"):
        load_results(42)
    # a frame without strain
    no_strain = tmp_path / "nostrain.h5"
    f = read_results(sequence).frames[1]
    with ResultWriter(no_strain, reference_shape=SHAPE) as w:
        w.write_frame(1, f)
    with pytest.raises(ValueError, match="frame 1 has no strain; recompute it with `specula strain`"):
        point_history(no_strain, (80, 60), "exx")
    assert np.isfinite(point_history(no_strain, (80, 60), "u").values).all()


# ------------------------------------------------------------------------------------------------
# stereo results


def _stereo_field(e, index, ny=9, nx=11):
    """A tilted plane (mm) seen on an image grid, with U = e (X - X0) along the frame's x."""
    from dic.field3d import Field3D

    gy, gx = np.meshgrid(20.0 + 10 * np.arange(ny), 30.0 + 10 * np.arange(nx), indexing="ij")
    x, y = gx.ravel(), gy.ravel()
    n = x.size
    X, Y = 0.2 * (x - 80), 0.2 * (y - 60)
    Z = 500.0 + 0.3 * X - 0.1 * Y
    U, V, W = e * (X - 1.0), np.zeros(n), 0.5 * e * X
    ok = np.ones(n, bool)
    ok[0] = False  # one failed point (a corner)
    nan = lambda a: np.where(ok, a, np.nan)  # noqa: E731
    full = lambda v: np.full(n, float(v))  # noqa: E731
    return Field3D(points=np.column_stack([x, y]), grid_shape=(ny, nx), X=X, Y=Y, Z=Z, U=nan(U), V=nan(V), W=nan(W),
                   exx=full(e), eyy=full(-0.3 * e), exy=full(0.1 * e), normal=np.tile([0.0, 0.0, -1.0], (n, 1)),
                   zncc_stereo=full(0.99), zncc_left=full(0.98), zncc_right=full(0.97), epipolar_ref_px=full(0.01),
                   epipolar_px=full(0.01), reprojection_ref_px=full(0.01), reprojection_px=full(0.01),
                   status=np.where(ok, 0, 3).astype(np.int8), strain_valid=ok.copy(), index=index)


@pytest.fixture
def stereo_file(tmp_path):
    from test_store import fake_match, fake_rig

    path = tmp_path / "stereo.h5"
    with ResultWriter(path, kind="stereo", rig=fake_rig(), reference_path=("l0.tif", "r0.tif"),
                      reference_shape=(240, 320), settings={"step": 10}) as w:
        w.write_match(fake_match(99))
        for k, e in enumerate((0.0, 0.004, 0.008)):
            w.write_frame(k, _stereo_field(e, k), path=(f"l{k}.tif", f"r{k}.tif"))
    return path


def test_stereo_extensometer_and_histories_are_exact_for_affine_fields(stereo_file):
    a, b = (40.0, 50.0), (120.0, 70.0)  # image px of the left reference
    ext = extensometer(stereo_file, a, b)
    assert ext.unit == "mm" and list(ext.frames) == [0, 1, 2] and ext.valid.all()

    def pos(p):  # the plane at an image point (the fields are affine in x, y)
        X, Y = 0.2 * (p[0] - 80), 0.2 * (p[1] - 60)
        return np.array([X, Y, 500.0 + 0.3 * X - 0.1 * Y])

    A, B = pos(a), pos(b)
    L0 = np.linalg.norm(B - A)
    for k, e in enumerate((0.0, 0.004, 0.008)):
        dA = np.array([e * (A[0] - 1), 0, 0.5 * e * A[0]])
        dB = np.array([e * (B[0] - 1), 0, 0.5 * e * B[0]])
        L = np.linalg.norm(B + dB - A - dA)
        assert ext.length0[k] == pytest.approx(L0, abs=1e-9)
        assert ext.strain[k] == pytest.approx(L / L0 - 1, abs=1e-12)
        assert np.allclose(ext.end_displacement[k], dB, atol=1e-12)
    # positions in mm: X, Y of the result's frame
    ext_mm = extensometer(stereo_file, A[:2], B[:2], at="mm")
    assert np.allclose(ext_mm.strain, ext.strain, atol=1e-12)
    h = point_history(stereo_file, (100, 80), "W")
    assert h.unit == "mm" and np.allclose(h.values, 0.5 * np.array([0, 0.004, 0.008]) * 0.2 * 20, atol=1e-12)
    h1 = point_history(stereo_file, (100, 80), "e1")
    want = principal_strains(np.array([0, 0.004, 0.008]), -0.3 * np.array([0, 0.004, 0.008]),
                             0.1 * np.array([0, 0.004, 0.008])).e1
    assert np.allclose(h1.values, want, atol=1e-15)
    p = line_profile(stereo_file, (40, 50), (120, 50), "U", samples=9)
    assert p.unit == "mm" and np.allclose(p.values[2], 0.008 * (0.2 * (p.positions[:, 0] - 80) - 1), atol=1e-12)
    with pytest.raises(ValueError, match="scale applies to 2-D results only"):
        extensometer(stereo_file, a, b, scale=0.1)
    with pytest.raises(ValueError, match="unknown quantity 'u' for stereo results"):
        point_history(stereo_file, a, "u")
    with pytest.raises(ValueError, match="a stereo result file is in mm already"):
        recompute_strain(stereo_file, window=5, scale=0.1)


# ------------------------------------------------------------------------------------------------
# plots


def test_figures(sequence, tmp_path):
    from dic.plots import history_figure, write_extensometer_figure, write_history_figure, write_profile_figure

    ext = extensometer(sequence, (40, 60), (120, 60))
    assert write_extensometer_figure(tmp_path / "ext.png", ext).stat().st_size > 1000
    h = [point_history(sequence, (80, 60), q) for q in ("exx", "eyy")]
    assert write_history_figure(tmp_path / "h.png", h).stat().st_size > 1000
    p = line_profile(sequence, (30, 60), (130, 60), "u")
    assert write_profile_figure(tmp_path / "p.svg", p).stat().st_size > 1000
    with pytest.raises(ValueError, match="expected a dic.postprocess.Extensometer"):
        write_extensometer_figure(tmp_path / "x.png", h[0])
    with pytest.raises(ValueError, match="at least one History"):
        history_figure([])


# ------------------------------------------------------------------------------------------------
# CLI


def _invoke(*args):
    return CliRunner().invoke(main, [str(a) for a in args])


def test_cli_strain(sequence, tmp_path):
    out = tmp_path / "w9.h5"
    r = _invoke("strain", sequence, "--window", 9, "-o", out)
    assert r.exit_code == 0, r.output
    assert "strain window 9 grid points" in r.output and read_results(out).settings["strain_window"] == 9
    r = _invoke("strain", sequence, "--window", 30, "--px", "-o", out, "--scale", 0.05)
    assert r.exit_code == 0, r.output
    res = read_results(out)
    assert res.settings["strain_window"] == 5 and res.settings[SCALE_KEY] == 0.05
    r = _invoke("strain", sequence, "--window", 4, "-o", out)
    assert r.exit_code == 1 and "window must be an odd integer >= 3" in r.output and "Traceback" not in r.output
    r = _invoke("strain", sequence, "--window", 5.5, "-o", out)
    assert r.exit_code == 2 and "odd integer >= 3" in r.output
    r = _invoke("strain", sequence, "--window", "nan", "-o", out)
    assert r.exit_code == 2 and "finite" in r.output and "Traceback" not in r.output
    r = _invoke("strain", tmp_path / "missing.h5", "--window", 5)
    assert r.exit_code == 1 and "result file not found" in r.output


def test_cli_extensometer_history_profile(sequence, tmp_path):
    import csv

    r = _invoke("extensometer", sequence, "--from", "40,60", "--to", "120,60", "--csv", tmp_path / "e.csv",
                "--plot", tmp_path / "e.png")
    assert r.exit_code == 0, r.output
    rows = list(csv.reader(open(tmp_path / "e.csv")))
    assert rows[0][:5] == ["frame", "length0_px", "length_px", "elongation_px", "strain"] and len(rows) == 5
    assert abs(float(rows[4][4]) - 0.01) < 4e-4 and (tmp_path / "e.png").stat().st_size > 1000
    r = _invoke("extensometer", sequence, "--from", "40,60", "--to", "120,60", "--frames", "2-3")
    assert r.exit_code == 0 and len(r.output.strip().splitlines()) == 3  # header + 2 frames on stdout
    r = _invoke("history", sequence, "--point", "110,40", "--quantity", "u", "--scale", "0.05")
    assert r.exit_code == 0 and "u_mm" in r.output
    r = _invoke("profile", sequence, "--from", "30,60", "--to", "130,60", "--quantity", "exx", "--samples", "4",
                "--csv", tmp_path / "p.csv", "--plot", tmp_path / "p.png")
    assert r.exit_code == 0, r.output
    assert len(list(csv.reader(open(tmp_path / "p.csv")))) == 1 + 4 * 4
    # errors: one message, no traceback
    r = _invoke("history", sequence, "--point", "110;40")
    assert r.exit_code == 2 and "expected a point x,y" in r.output
    r = _invoke("history", sequence, "--point", "110,40", "--quantity", "speed")
    assert r.exit_code == 1 and "unknown quantity 'speed'" in r.output and "Traceback" not in r.output
    r = _invoke("history", sequence, "--point", "110,40", "--frames", "a-b")
    assert r.exit_code == 2 and "frame indices" in r.output
    r = _invoke("extensometer", sequence, "--from", "40,60", "--to", "120,60", "--at", "mm")
    assert r.exit_code == 1 and "positions in mm need a scale" in r.output
    r = _invoke("extensometer", sequence, "--from", "40,60", "--to", "120,60", "--plot", tmp_path / "e.csv" / "x.png")
    assert r.exit_code == 1 and "cannot write" in r.output and "Traceback" not in r.output
    r = _invoke("extensometer", sequence, "--from", "40,60", "--to", "120,60", "--plot", tmp_path / "e.xyz")
    assert r.exit_code == 1 and "not supported" in r.output
    r = _invoke("extensometer", sequence, "--from", "1,1", "--to", "2,2")  # no value at an end: an error that says why
    assert r.exit_code == 1 and "gauge start (1, 1) px in any frame: it is outside the grid of points" in r.output


def test_cli_on_stereo_results(stereo_file, tmp_path):
    r = _invoke("history", stereo_file, "--point", "100,80")  # default quantity: U for stereo
    assert r.exit_code == 0, r.output
    assert "U_mm" in r.output and len(r.output.strip().splitlines()) == 4
    r = _invoke("extensometer", stereo_file, "--from", "40,50", "--to", "120,70", "--csv", tmp_path / "e.csv")
    assert r.exit_code == 0, r.output
    assert open(tmp_path / "e.csv").readline().strip().endswith("end_U_mm,end_V_mm,end_W_mm")
    r = _invoke("profile", stereo_file, "--from", "40,50", "--to", "120,50", "--quantity", "von_mises", "-q",
                "--plot", tmp_path / "p.png")
    assert r.exit_code == 0 and r.output == "" and (tmp_path / "p.png").exists()
    # stereo strain is recomputed (issue 25 item 6; tests/dic/test_strain_types.py checks it against a run)
    r = _invoke("strain", stereo_file, "--window", 5, "-o", tmp_path / "s.h5")
    assert r.exit_code == 0 and "state 2: strain at" in r.output and "Green-Lagrange" in r.output
    r = _invoke("history", stereo_file, "--point", "100,80", "--scale", 0.1)
    assert r.exit_code == 1 and "scale applies to 2-D results only" in r.output


def test_cli_track_stores_the_scale(tmp_path):
    from dic.io import write_image
    from dic.synth import speckle_pair

    ref, cur = speckle_pair((64, 80), (0.4, -0.3), seed=2)
    paths = [write_image(tmp_path / n, img, bits=8) for n, img in (("r.tif", ref), ("c.tif", cur))]
    out = tmp_path / "run.h5"
    r = _invoke("track", *paths, "-o", out, "--step", 8, "--scale", 0.02, "--device", "cpu", "-q")
    assert r.exit_code == 0, r.output
    assert read_results(out).settings[SCALE_KEY] == 0.02
    h = point_history(out, (40, 32), "u")
    assert h.unit == "mm" and h.values[0] == pytest.approx(0.4 * 0.02, abs=0.02 * 0.02)
    r = _invoke("track", *paths, "-o", tmp_path / "b.h5", "--scale", "nan", "-q")
    assert r.exit_code == 2 and "scale" in r.output
