"""Strain types by name (issue 25): Green-Lagrange, small and Euler-Almansi from the same gradient fit,
in 2-D (dic.strain) and stereo (dic.field3d surface strain), against exact truth; the type stored in result
files and recomputed with ``specula strain`` (2-D and stereo files), equal to a run made with that window
and type.

Truth: a homogeneous deformation gradient F (a 10 % stretch, where the three types differ by about 5 % of
the strain) applied to grid points; E = (FᵀF − I)/2, e = (I − F⁻ᵀF⁻¹)/2, ε = (H + Hᵀ)/2 with H = F − I,
each computed here with numpy.linalg from F. A plane fit reproduces an affine field exactly, so only
float64 rounding remains: bound 1e-12.
"""
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner

from dic._strain import STRAIN_TYPES, check_strain_type, stored_strain_type, strain, strain_from_gradient
from dic.field3d import SurfaceStrainPlan, grid_neighbours, surface_strain, surface_strain_grid
from dic.postprocess import recompute_strain
from dic.store import read_results, read_stereo

DATA = Path(__file__).parents[1] / "data" / "settings_v1"
IMG = {k: str(DATA / f"{k}.png") for k in ("ref", "f1", "f2", "L0", "R0", "L1", "R1", "L2", "R2")}
RIG = str(DATA / "rig.json")

#: a 10 % stretch along x, -4 % along y, shear and a 7 degree rotation
_TH = np.deg2rad(7.0)
F_2D = np.array([[np.cos(_TH), -np.sin(_TH)], [np.sin(_TH), np.cos(_TH)]]) @ np.array([[1.10, 0.03], [0.0, 0.96]])


def truths(F):
    """(E Green-Lagrange, e Euler-Almansi, eps small) of a 2x2 deformation gradient, from their definitions."""
    I = np.eye(2)
    H = F - I
    Finv = np.linalg.inv(F)
    return {"green-lagrange": 0.5 * (F.T @ F - I), "euler-almansi": 0.5 * (I - Finv.T @ Finv),
            "small": 0.5 * (H + H.T)}


def _grid(nx=15, ny=12, step=4.0):
    xs, ys = np.meshgrid(10.0 + step * np.arange(nx), 20.0 + step * np.arange(ny))
    return np.stack([xs.ravel(), ys.ravel()], 1)


def test_the_three_types_differ_at_a_10_percent_stretch():
    t = truths(F_2D)
    for a, b in (("green-lagrange", "small"), ("small", "euler-almansi"), ("green-lagrange", "euler-almansi")):
        assert abs(t[a][0, 0] - t[b][0, 0]) > 3e-3  # well above any bound below: the tests tell them apart


@pytest.mark.parametrize("strain_type", list(STRAIN_TYPES))
def test_2d_strain_types_are_exact_for_a_homogeneous_deformation(strain_type):
    pts = _grid()
    c = pts.mean(0)
    d = (pts - c) @ (F_2D - np.eye(2)).T + np.array([3.0, -1.5])  # u = (F - I)(X - c) + translation
    field = SimpleNamespace(points=pts, u=d[:, 0], v=d[:, 1], valid=np.ones(len(pts), bool))
    s = strain(field, window=5, strain_type=strain_type)
    want = truths(F_2D)[strain_type]
    assert s.valid.all() and s.strain_type == strain_type
    assert np.max(np.abs(s.exx - want[0, 0])) < 1e-12
    assert np.max(np.abs(s.eyy - want[1, 1])) < 1e-12
    assert np.max(np.abs(s.exy - want[0, 1])) < 1e-12
    # Exx... stay Green-Lagrange whatever the type
    E = truths(F_2D)["green-lagrange"]
    assert np.max(np.abs(np.stack([s.Exx - E[0, 0], s.Eyy - E[1, 1], s.Exy - E[0, 1]]))) < 1e-12


def test_default_type_is_green_lagrange_and_names_are_checked():
    pts = _grid(6, 5)
    field = SimpleNamespace(points=pts, u=0.1 * pts[:, 0], v=0.0 * pts[:, 1], valid=None)
    s = strain(field, window=3)
    assert s.strain_type == "green-lagrange" and np.allclose(s.exx, 0.1 + 0.5 * 0.01, rtol=0, atol=1e-13)
    assert check_strain_type("Green_Lagrange") == "green-lagrange" and check_strain_type("EULER-ALMANSI")
    for bad in ("engineering", None, 3):
        with pytest.raises(ValueError, match="strain_type must be one of green-lagrange, small, euler-almansi"):
            strain(field, window=3, strain_type=bad)
    # a folded gradient (det F <= 0) has no Euler-Almansi strain
    assert np.isnan(strain_from_gradient(-1.5, 0.0, 0.0, 0.0, "euler-almansi")[0])


def _tilted_plane(nx=13, ny=11, step=2.0):
    """Points of the plane Z = 400 + 0.4 X - 0.2 Y mm (left camera frame) on an nx x ny grid, and the
    tangent basis the surface strain uses there: e1 = x axis projected onto the plane, e2 = n x e1 towards +y,
    n towards the camera at the origin."""
    xs, ys = np.meshgrid(step * (np.arange(nx) - nx // 2), step * (np.arange(ny) - ny // 2))
    X = np.stack([xs.ravel(), ys.ravel(), 400.0 + 0.4 * xs.ravel() - 0.2 * ys.ravel()], 1)
    n = np.array([0.4, -0.2, -1.0])
    n /= np.linalg.norm(n)  # towards the camera (-z)
    e1 = np.array([1.0, 0, 0]) - n[0] * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    e2 = e2 if e2[1] >= 0 else -e2
    return X, (ny, nx), n, e1, e2


def _rotation(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    th = np.deg2rad(deg)
    return np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K


@pytest.mark.parametrize("strain_type", list(STRAIN_TYPES))
def test_stereo_surface_strain_types_are_exact_for_an_in_plane_deformation(strain_type):
    """A tilted plane stretched in its own plane by F (in the tangent basis e1, e2): the surface strain of
    each type is the 2-D one of F, by the grid plan and by the neighbour-list form alike."""
    X, shape, n, e1, e2 = _tilted_plane()
    P = np.stack([e1, e2], 1)  # (3, 2)
    A = np.eye(3) + P @ (F_2D - np.eye(2)) @ P.T  # maps the plane onto itself
    c = X.mean(0)
    U = (X - c) @ (A - np.eye(3)).T + np.array([0.2, -0.1, 0.3])
    valid = np.ones(len(X), bool)
    want = truths(F_2D)[strain_type]
    for out in (surface_strain_grid(X, U, valid, shape, 5, strain_type=strain_type),
                surface_strain(X, U, valid, grid_neighbours(shape, 5), strain_type=strain_type)):
        assert out["strain_valid"].all()
        assert np.max(np.abs(out["exx"] - want[0, 0])) < 1e-12
        assert np.max(np.abs(out["eyy"] - want[1, 1])) < 1e-12
        assert np.max(np.abs(out["exy"] - want[0, 1])) < 1e-12
        assert np.max(np.abs(out["normal"] - n)) < 1e-12


def test_stereo_strain_after_an_out_of_plane_rotation():
    """The same stretch followed by a 20 degree rotation that tilts the surface: Green-Lagrange is unchanged
    (exact for rigid motions), Euler-Almansi keeps its principal values 1/2 (1 - 1/lambda^2) (lambda^2 the
    eigenvalues of FᵀF), the small strain does not (it is not objective)."""
    X, shape, n, e1, e2 = _tilted_plane()
    P = np.stack([e1, e2], 1)
    A = _rotation([1.0, 2.0, 0.5], 20.0) @ (np.eye(3) + P @ (F_2D - np.eye(2)) @ P.T)
    U = (X - X.mean(0)) @ (A - np.eye(3)).T
    valid = np.ones(len(X), bool)
    t = truths(F_2D)
    plan = {k: SurfaceStrainPlan(X, shape, 5, strain_type=k) for k in STRAIN_TYPES}
    gl = plan["green-lagrange"](U, valid)
    E = t["green-lagrange"]
    assert np.max(np.abs(np.stack([gl["exx"] - E[0, 0], gl["eyy"] - E[1, 1], gl["exy"] - E[0, 1]]))) < 1e-12
    ea = plan["euler-almansi"](U, valid)
    lam2 = np.linalg.eigvalsh(F_2D.T @ F_2D)
    principal = 0.5 * (1.0 - 1.0 / lam2)
    assert np.max(np.abs(ea["exx"] + ea["eyy"] - principal.sum())) < 1e-12
    assert np.max(np.abs(ea["exx"] * ea["eyy"] - ea["exy"] ** 2 - np.prod(principal))) < 1e-12
    small = plan["small"](U, valid)
    assert np.min(np.abs(small["exx"] - t["small"][0, 0])) > 1e-3


def _cli(*args):
    from dic.cli import main

    return CliRunner().invoke(main, [str(a) for a in args])


def _same(a, b):
    return np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)


def test_2d_recomputed_strain_equals_a_run_with_that_window_and_type(tmp_path):
    from dic.sequence import track_sequence

    kw = dict(step=8, search="zncc", search_radius=4, roi=(8, 8, 90, 70), device="cpu")
    frames = [IMG["f1"], IMG["f2"]]
    w5 = tmp_path / "w5.h5"
    track_sequence(IMG["ref"], frames, w5, strain_window=5, **kw)
    w3 = tmp_path / "w3.h5"
    track_sequence(IMG["ref"], frames, w3, strain_window=3, strain_type="euler-almansi", **kw)
    assert read_results(w5).settings["strain_type"] == "green-lagrange"
    assert read_results(w3).settings["strain_type"] == "euler-almansi"
    r = _cli("strain", w5, "--window", 3, "--strain-type", "euler-almansi", "-o", tmp_path / "re.h5")
    assert r.exit_code == 0, r.output
    assert "Euler-Almansi exx mean" in r.output and "window 3 grid points, Euler-Almansi strain" in r.output
    got, run = read_results(tmp_path / "re.h5"), read_results(w3)
    assert got.settings == run.settings  # the same record: a resume of either with the other's options works
    for i in (1, 2):
        for key in ("dudx", "dudy", "dvdx", "dvdy", "exx", "eyy", "exy", "Exx", "Eyy", "Exy", "valid"):
            assert _same(got.frames[i].strain[key], run.frames[i].strain[key]), key
        assert got.frames[i].attrs["strain_type"] == "euler-almansi"
    # the type in every label: xarray column attributes, the DataFrame, figure titles and colour bars
    ds = got.to_xarray()
    assert ds["exx"].attrs["long_name"] == "Euler-Almansi strain xx" and ds.attrs["strain_type"] == "euler-almansi"
    assert ds["Exx"].attrs["long_name"] == "Green-Lagrange strain xx"
    assert got.to_dataframe().attrs["strain_type"] == "euler-almansi"
    # ... the CSV files' CSVW description and the MATLAB file's long names and info
    import json

    import scipy.io

    from dic.export import csv_metadata_path, write_csv, write_mat

    csvs = write_csv(tmp_path / "re.h5", tmp_path / "csv")
    meta = json.loads(csv_metadata_path(tmp_path / "csv", "frame").read_text())
    assert [t["url"] for t in meta["tables"]] == [p.name for p in csvs]
    cols = {c["name"]: c for c in meta["tableSchema"]["columns"]}
    header = csvs[0].read_text().splitlines()[0].split(",")
    assert list(cols) == header  # every column of the files, in their order
    assert cols["exx"]["dc:description"] == "Euler-Almansi strain xx" and cols["u"]["schema:unitText"] == "px"
    assert cols["Exx"]["dc:description"] == "Green-Lagrange strain xx"
    assert "Euler-Almansi strains (euler-almansi)" in meta["dc:description"]
    mat = scipy.io.loadmat(write_mat(tmp_path / "re.h5", tmp_path / "re.mat"), simplify_cells=True)
    assert mat["long_names"]["exx"] == "Euler-Almansi strain xx" and mat["info"]["strain_type"] == "euler-almansi"
    from dic.io import read_image
    from dic.plots.fields import field_figure

    fig = field_figure(read_image(IMG["ref"]), got.frames[2], got.frames[2].strain)
    texts = [ax.get_title() for ax in fig.axes] + [t.get_text() for ax in fig.axes for t in ax.texts
                                                   if t.get_gid() == "colourbar-label"]
    assert "Euler-Almansi strain exx (1)" in texts and "exx, Euler-Almansi" in texts
    from dic.plots.postprocess import history_figure
    from dic.postprocess import point_history

    h = point_history(tmp_path / "re.h5", (50, 40), "von_mises")
    assert h.strain_type == "euler-almansi" and point_history(w5, (50, 40), "u").strain_type is None
    assert point_history(w5, (50, 40), "Exx").strain_type == "green-lagrange"
    assert history_figure(h).axes[0].get_ylabel() == "von_mises (Euler-Almansi)"
    # without --strain-type the file's type is kept
    r = _cli("strain", tmp_path / "re.h5", "--window", 5, "-q")
    assert r.exit_code == 0 and read_results(tmp_path / "re.h5").settings["strain_type"] == "euler-almansi"


def test_stereo_recomputed_strain_equals_a_run_with_that_window(tmp_path):
    from dic.sequence import stereo_sequence

    pairs = [(IMG[f"L{k}"], IMG[f"R{k}"]) for k in range(3)]
    w3 = tmp_path / "w3.h5"
    stereo_sequence(RIG, pairs, w3, step=20, strain_window=3, device="cpu")
    w5 = tmp_path / "w5.h5"
    stereo_sequence(RIG, pairs, w5, step=20, strain_window=5, strain_type="small", device="cpu")
    r = _cli("strain", w3, "--window", 5, "--strain-type", "small", "-o", tmp_path / "re.h5")
    assert r.exit_code == 0, r.output
    assert "state 2: strain at" in r.output and "small (engineering) strain" in r.output
    got, run = read_stereo(tmp_path / "re.h5"), read_stereo(w5)
    assert got.settings == run.settings and got.indices == run.indices == [0, 1, 2]
    assert np.count_nonzero(run.fields[2].strain_valid) > 0
    for i in run.indices:
        a, b = got.fields[i], run.fields[i]
        for key in ("exx", "eyy", "exy", "normal", "strain_valid", "X", "U", "W", "status"):
            assert _same(getattr(a, key), getattr(b, key)), (i, key)
        assert a.strain_type == b.strain_type == "small"
    assert got.match is not None and _same(got.match.points_right, run.match.points_right)
    ds = got.to_xarray()
    assert ds["eyy"].attrs["long_name"] == "small (engineering) strain yy" and got.fields[2].to_dataframe().attrs[
        "strain_type"] == "small"
    from dic.plots.fields import field3d_figure

    fig = field3d_figure(got.fields[2], "exx")
    assert "small (engineering) strain exx" in fig.axes[0].get_title()
    import json

    import scipy.io

    from dic.export import csv_metadata_path, write_csv, write_mat

    write_csv(tmp_path / "re.h5", tmp_path / "csv")
    meta = json.loads(csv_metadata_path(tmp_path / "csv", "stereo").read_text())
    cols = {c["name"]: c for c in meta["tableSchema"]["columns"]}
    assert cols["exx"]["dc:description"] == "small (engineering) strain xx" and cols["W"]["schema:unitText"] == "mm"
    mat = scipy.io.loadmat(write_mat(tmp_path / "re.h5", tmp_path / "re.mat"), simplify_cells=True)
    assert mat["long_names"]["eyy"] == "small (engineering) strain yy" and mat["info"]["strain_type"] == "small"
    # the library function names its keywords; the command its options
    with pytest.raises(ValueError, match="strain window 99 .* at most"):
        recompute_strain(w3, tmp_path / "x.h5", window=99)
    r = _cli("strain", w3, "--window", 99, "-o", tmp_path / "x.h5")
    assert r.exit_code == 1 and "--window 99" in r.output and "strain_window" not in r.output
    r = _cli("strain", w3, "--window", 5, "--scale", 0.1, "-o", tmp_path / "x.h5")
    assert r.exit_code == 1 and "scale" in r.output and "recompute_strain" not in r.output
    assert not (tmp_path / "x.h5").exists()


def test_stereo_recomputed_strain_of_a_run_given_points(tmp_path):
    """A stereo run given its points (no grid: the window² nearest points within window spacings): the
    recomputed strain equals a run made with that window, bit for bit."""
    from dic.sequence import stereo_sequence

    pairs = [(IMG[f"L{k}"], IMG[f"R{k}"]) for k in range(3)]
    grid = tmp_path / "grid.h5"
    stereo_sequence(RIG, pairs[:1], grid, step=20, device="cpu")
    points = read_stereo(grid).fields[0].points[1:-2]  # the grid less three points: scattered points
    runs = {}
    for window in (3, 5):
        runs[window] = tmp_path / f"p{window}.h5"
        stereo_sequence(RIG, pairs, runs[window], points=points, strain_window=window, device="cpu")
    assert read_stereo(runs[3]).fields[0].grid_shape is None
    got = read_stereo(recompute_strain(runs[3], tmp_path / "re.h5", window=5))
    run = read_stereo(runs[5])
    assert got.settings == run.settings and np.count_nonzero(run.fields[2].strain_valid) > 0
    for i in run.indices:
        for key in ("exx", "eyy", "exy", "normal", "strain_valid"):
            assert _same(getattr(got.fields[i], key), getattr(run.fields[i], key)), (i, key)


def test_files_before_strain_types_read_as_their_old_type():
    assert stored_strain_type("dic2d", {"strain_window": 5}) == "small"
    assert stored_strain_type("stereo", {"step": 10}) == "green-lagrange"
    assert stored_strain_type("dic2d", {"strain_type": "euler-almansi"}) == "euler-almansi"
    frame = SimpleNamespace(attrs={"strain_type": "green-lagrange"}, strain={"exx": np.zeros(3)})
    assert stored_strain_type("dic2d", {}, frame) == "green-lagrange"


def test_2d_strain_types_from_a_synthetic_image_pair():
    """Rendered speckle (dic.synth, 200 x 160 px, 8-bit, no added noise) deformed by a homogeneous F with a
    10 % stretch, tracked (subset 31, step 8, pyramid search) and strained (window 5): each type within
    5e-4 of its exact value at every valid point (measured: at most 1.9e-4), while the types differ from
    each other by more than 3e-3 -- the image pair tells them apart."""
    from dic._track import Tracker
    from dic.synth import speckle_pair

    F = np.array([[1.10, 0.03], [0.0, 0.96]])
    H = F - np.eye(2)
    centre = np.array([100.0, 80.0])

    def displacement(x, y):
        dx, dy = x - centre[0], y - centre[1]
        return H[0, 0] * dx + H[0, 1] * dy, H[1, 0] * dx + H[1, 1] * dy

    ref, cur = speckle_pair((160, 200), displacement, seed=3)
    field = Tracker(ref, subset=31, step=8, search="pyramid", search_radius=16, device="cpu").track(cur)
    assert field.valid.mean() > 0.8
    t = truths(F)
    for kind, want in t.items():
        s = strain(field, window=5, strain_type=kind)
        ok = s.valid
        got = np.stack([s.exx[ok], s.eyy[ok], s.exy[ok]])
        assert ok.sum() > 250
        assert np.max(np.abs(got - np.array([want[0, 0], want[1, 1], want[0, 1]])[:, None])) < 5e-4
        for other in t:
            if other != kind:
                assert abs(np.median(s.exx[ok]) - t[other][0, 0]) > 3e-3


def test_an_old_file_recomputed_keeps_its_type_and_still_reads_as_a_run_record(tmp_path):
    """A 2-D file of Specula 8d9f975 (the command line's schema-1 settings, small strain): `specula strain`
    keeps the small strain unless asked, records strain_type, and the file's record still reads (resume)."""
    import shutil

    from dic.sequence.options import TrackOptions

    old = tmp_path / "old.h5"
    shutil.copy(DATA / "track_cli_v1.h5", old)
    stored = read_results(old)
    assert "strain_type" not in stored.settings
    r = _cli("strain", old, "--window", 3, "-q")
    assert r.exit_code == 0, r.output
    back = read_results(old)
    assert back.settings["strain_type"] == "small"
    assert TrackOptions.from_settings(back.settings).strain_type == "small"
    f = back.frames[1]
    assert np.array_equal(f.strain["exx"], f.strain["dudx"], equal_nan=True)  # small: exx = du/dx
