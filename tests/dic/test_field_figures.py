"""Field maps worth looking at (issue 25, item 8): the colour map follows the sign of the range, colourbars
are as tall as their panels, every panel says what it shows and in which unit, and the figure of a
1 MP frame stays under 500 KB. (Their time is measured in bench/figures.py, not here.)"""
from types import SimpleNamespace

import numpy as np
import pytest

from dic._strain import strain
from dic.field3d import Field3D, StereoStatus
from dic.plots.fields import (
    DIVERGING_CMAP,
    SEQUENTIAL_CMAP,
    field3d_figure,
    field_figure,
    write_field_figure,
    write_figures,
)


def _grid_field(shape, step, u_fn, v_fn, invalid_every=97):
    """A Field2D-like result on a grid of ``step`` px over an image of ``shape`` (H, W); u, v (px) of x, y."""
    H, W = shape
    gy, gx = np.meshgrid(np.arange(10, H - 10, step, dtype=float), np.arange(10, W - 10, step, dtype=float),
                         indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    valid = np.ones(len(pts), bool)
    valid[::invalid_every] = False
    return SimpleNamespace(points=pts, u=u_fn(pts[:, 0], pts[:, 1]), v=v_fn(pts[:, 0], pts[:, 1]), valid=valid)


def _field3d(shape=(60, 80), step=4, W=None, U=None):
    H, Wd = shape
    gy, gx = np.meshgrid(np.arange(8, H - 8, step, dtype=float), np.arange(8, Wd - 8, step, dtype=float), indexing="ij")
    ny, nx = gy.shape
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    n = len(pts)
    x, y = pts[:, 0] / Wd, pts[:, 1] / H
    status = np.zeros(n, np.int8)
    status[::53] = StereoStatus.MATCH_FAILED
    ok = status == 0
    rng = np.random.default_rng(3)

    def nan(a):
        return np.where(ok, a, np.nan)

    W = 0.011 + 0.011 * x * y if W is None else W(x, y)
    U = 0.02 * (x - 0.5) if U is None else U(x, y)
    e = {k: nan(rng.normal(scale=1e-3, size=n)) for k in ("exx", "eyy", "exy")}
    return Field3D(points=pts, grid_shape=(ny, nx), X=nan(pts[:, 0] * 0.1), Y=nan(pts[:, 1] * 0.1), Z=nan(500 + x),
                   U=nan(U), V=nan(-0.03 + 0.01 * y), W=nan(W), **e, normal=np.where(ok[:, None], [0.0, 0.0, -1.0], np.nan),
                   zncc_stereo=nan(rng.uniform(0.9, 1, n)), zncc_left=np.ones(n), zncc_right=np.ones(n),
                   epipolar_ref_px=np.zeros(n), epipolar_px=np.zeros(n), reprojection_ref_px=np.zeros(n),
                   reprojection_px=np.zeros(n), status=status, strain_valid=ok.copy(), index=1)


def _field_image(ax):
    """The colour-mapped (non-grey) image of a map panel."""
    ims = [im for im in ax.images if im.get_gid() == "map"]
    assert len(ims) == 1
    return ims[0]


def test_one_signed_range_on_a_sequential_map_spanning_zero_on_a_centred_diverging_map():
    """v from -12 to -5 px was drawn on a diverging map centred on zero: one shade of blue (issue 25)."""
    f = _grid_field((120, 160), 5, lambda x, y: 0.02 * (x - 80.0), lambda x, y: -12.0 + 7.0 * y / 120.0)
    fig = field_figure(None, f, components=["u", "v"])
    u_im, v_im = (_field_image(ax) for ax in fig.axes)
    lo, hi = u_im.get_clim()  # u spans zero: diverging, symmetric
    assert u_im.get_cmap().name == DIVERGING_CMAP and lo == -hi and hi > 0
    lo, hi = v_im.get_clim()  # v one-signed: sequential over the values' own range (1st-99th percentiles)
    v = f.v[f.valid]
    assert v_im.get_cmap().name == SEQUENTIAL_CMAP
    assert (lo, hi) == pytest.approx(tuple(np.percentile(v, (1, 99))))
    assert -12.0 < lo < -11.0 and -6.0 < hi < -5.0  # the map spans the field, not +-12 px
    # stereo: W from 0.011 to 0.022 mm is one-signed; U spans zero
    f3 = _field3d()
    w = _field_image(field3d_figure(f3, "W").axes[0])
    assert w.get_cmap().name == SEQUENTIAL_CMAP and 0.011 <= w.get_clim()[0] < w.get_clim()[1] <= 0.022
    u = _field_image(field3d_figure(f3, "U").axes[0])
    assert u.get_cmap().name == DIVERGING_CMAP and u.get_clim()[0] == -u.get_clim()[1]
    # fixed limits choose the map the same way
    fixed = _field_image(field_figure(None, f, components=["v"], limits={"v": (-3.0, 2.0)}).axes[0])
    assert fixed.get_cmap().name == DIVERGING_CMAP and fixed.get_clim() == (-3.0, 2.0)


@pytest.mark.parametrize("shape", [(60, 120), (120, 60)])
def test_colourbars_as_tall_as_their_panels_and_no_empty_band(shape):
    """Colourbars were 0.85 of a subplot cell, taller than the image panel, in a tall figure (issue 25)."""
    ref = np.random.default_rng(0).uniform(0, 255, shape)
    f = _grid_field(shape, 6, lambda x, y: 0.01 * x, lambda x, y: -0.02 * y)
    figs = [field_figure(ref, f, strain(f, window=3), title="frame 1"), field3d_figure(_field3d(shape), "W", ref)]
    for fig in figs:
        fig.canvas.draw()  # positions after any aspect adjustment
        panels = fig.axes  # one Axes per panel, its colourbar drawn beside it in the same Axes
        assert len(panels) >= 1
        fig_h = fig.get_figheight()
        for ax in panels:
            [bar] = [im for im in ax.images if im.get_gid() == "colourbar"]
            p, c = ax.get_window_extent(), bar.get_window_extent()
            assert c.y0 == pytest.approx(p.y0, abs=1e-6) and c.height == pytest.approx(p.height, abs=1e-6)
            assert c.x0 > p.x1  # beside the panel
            # the panel keeps the image's aspect ratio (square pixels)
            x0, x1 = ax.get_xlim()
            y1, y0 = ax.get_ylim()
            pos = ax.get_position(original=False)
            w_in, h_in = pos.width * fig.get_figwidth(), pos.height * fig_h
            assert h_in / w_in == pytest.approx((y1 - y0) / (x1 - x0), rel=1e-6)
        # no empty band: the lowest panel within 0.7 in of the bottom, the highest within 0.9 in of the top
        assert min(ax.get_position().y0 for ax in panels) * fig_h < 0.7
        assert (1 - max(ax.get_position().y1 for ax in panels)) * fig_h < 0.9


def test_every_panel_has_axis_labels_a_title_with_unit_and_the_reference_beneath():
    ref = np.random.default_rng(0).uniform(0, 255, (80, 100))
    f = _grid_field((80, 100), 5, lambda x, y: 0.01 * x, lambda x, y: -3 - 0.02 * y)
    fig = field_figure(ref, f, strain(f, window=3), components=["u", "v", "magnitude", "exx", "Eyy"])
    units = {"u": "(px)", "v": "(px)", "magnitude": "(px)", "exx": "(1)", "Eyy": "(1)"}
    assert len(fig.axes) == len(units)
    for ax, name in zip(fig.axes, units):
        assert ax.get_xlabel() == "x (px)" and ax.get_ylabel() == "y (px)"
        title = ax.get_title()
        assert units[name] in title and ("displacement" in title or "strain" in title), title
        assert ax.images[0].get_gid() == "backdrop"  # the reference image beneath the map
        assert _field_image(ax).get_alpha() == pytest.approx(0.75)
    f3 = _field3d((80, 100))
    for q, unit in (("W", "(mm)"), ("Z", "(mm)"), ("exx", "(1)")):
        [ax] = field3d_figure(f3, q, ref).axes
        [bar_label] = [t.get_text() for t in ax.texts if t.get_gid() == "colourbar-label"]
        assert "(px)" in ax.get_xlabel() and "(px)" in ax.get_ylabel()
        assert unit in ax.get_title() and unit in bar_label
        assert ax.images[0].get_gid() == "backdrop"


def _speckle(size, seed=0):
    from scipy.ndimage import gaussian_filter

    g = gaussian_filter(np.random.default_rng(seed).standard_normal((size, size)), 1.4)
    return np.round(30 + 190 * gaussian_filter((g > 0).astype(float), 0.7)).astype(np.uint8)


def test_a_1_mp_frame_figure_is_under_500_kb(tmp_path):
    """The 5-panel figure of a 1024 x 1024 frame (grid step 5, 41 616 points) was a 2.1 MB PNG (issue 25)."""
    ref = _speckle(1024)
    f = _grid_field((1024, 1024), 5, lambda x, y: 1 + 2 * x / 1024, lambda x, y: -12 + 7 * y / 1024)
    assert len(f.points) > 40_000
    p = write_field_figure(tmp_path / "frame.png", ref, f, strain(f, window=5), title="frame 1")
    assert p.read_bytes()[:4] == b"\x89PNG"
    assert p.stat().st_size <= 500_000
    paths = write_figures(_field3d((1024, 1024), step=5), ref, tmp_path / "stereo", quantities=["W", "exx", "status"])
    assert max(q.stat().st_size for q in paths) <= 500_000


def test_frozen_ticks_are_matplotlibs_own():
    """A saved map's ticks are drawn as plain marks and texts (freeze_ticks): the same positions and labels
    as Matplotlib's live ticks, and the axis labels stay beyond them."""
    from dic.plots._common import freeze_ticks

    ref = np.random.default_rng(0).uniform(0, 255, (90, 140))
    f = _grid_field((90, 140), 6, lambda x, y: 0.01 * x, lambda x, y: -2 - 0.02 * y)
    fig = field_figure(ref, f, components=["u", "v"])
    fig.canvas.draw()
    live = []  # the labels Matplotlib draws: those of the ticks inside the view
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            lo, hi = sorted(axis.get_view_interval())
            live += [t.get_text() for v, t in zip(axis.get_majorticklocs(), axis.get_majorticklabels())
                     if lo - 1e-9 * (hi - lo) <= v <= hi + 1e-9 * (hi - lo) and t.get_text()]
    freeze_ticks(fig)
    fig.canvas.draw()
    frozen = [t.get_text() for ax in fig.axes for t in ax.texts if t.get_gid() == "tick-label"]
    assert len(live) > 10 and sorted(frozen) == sorted(live)
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        assert not ax.xaxis.get_majorticklocs().size and not ax.yaxis.get_majorticklocs().size
        label = ax.yaxis.label if ax.yaxis.label.get_text() else None
        if label is None or not ax.texts:
            continue
        tick_boxes = [t.get_window_extent(renderer) for t in ax.texts if t.get_gid() == "tick-label"]
        lab_box = label.get_window_extent(renderer)
        assert not any(lab_box.overlaps(b) for b in tick_boxes)  # the axis label clears the tick labels


def test_colourbar_ticks_are_round_values_at_their_colours():
    """The colourbar drawn in the panel (no colourbar Axes): its tick labels are MaxNLocator's round values
    inside the colour range, formatted without an offset, each at the height where the bar has its colour."""
    f = _grid_field((60, 80), 4, lambda x, y: 1000.0 + 0.5 * x, lambda x, y: -2 - 0.02 * y)
    fig = field_figure(None, f, components=["u"])
    [ax] = fig.axes
    im = _field_image(ax)
    [bar] = [i for i in ax.images if i.get_gid() == "colourbar"]
    lo, hi = im.get_clim()
    labels = [t for t in ax.texts if t.get_gid() == "colourbar-tick-label"]
    values = [float(t.get_text().replace("\u2212", "-")) for t in labels]
    # no offset ("+1e3" with labels 0, 10, ...): the labels are the values themselves
    assert 990.0 < lo < hi < 1050.0 and len(values) >= 3 and all(lo <= v <= hi for v in values)
    steps = np.diff(values)
    assert np.allclose(steps, steps[0]) and steps[0] > 0
    grad = bar.get_array()
    for t, v in zip(labels, values):
        y = t.get_position()[1]  # axes fraction along the bar
        assert grad[int(min(y * len(grad), len(grad) - 1)), 0] == pytest.approx(v, abs=(hi - lo) / len(grad) + 1e-12)
    [label] = [t.get_text() for t in ax.texts if t.get_gid() == "colourbar-label"]
    assert label == "u (px)"


def test_saved_tick_labels_drawn_by_pillow_where_matplotlib_draws_them(tmp_path):
    """save_map_png draws the plain tick labels with Pillow (fast): the PNG matches Matplotlib's own drawing of
    the same figure (ticks frozen as Text artists) everywhere but inside the labels, and every label has ink
    inside Matplotlib's box of it."""
    from PIL import Image

    from dic.plots._common import freeze_ticks, save_map_png

    ref = np.random.default_rng(0).uniform(0, 255, (90, 140))
    f = _grid_field((90, 140), 6, lambda x, y: 0.01 * x, lambda x, y: -2 - 0.02 * y)
    fast = np.asarray(Image.open(save_map_png(field_figure(ref, f, components=["u", "v"], dpi=100),
                                              tmp_path / "fast.png", dpi=100)).convert("L"), dtype=float)
    fig = field_figure(ref, f, components=["u", "v"], dpi=100)  # the same figure, drawn by Matplotlib alone
    freeze_ticks(fig)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    slow = np.asarray(Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3]).convert("L"), dtype=float)
    assert fast.shape == slow.shape
    height = fast.shape[0]
    labels = [t for ax in fig.axes for t in ax.texts if t.get_gid() in ("tick-label", "colourbar-tick-label")]
    assert len(labels) > 15 and {t.get_gid() for t in labels} == {"tick-label", "colourbar-tick-label"}
    outside = np.ones(fast.shape, bool)
    for t in labels:
        b = t.get_window_extent(renderer)
        r0, r1 = int(height - b.y1) - 2, int(np.ceil(height - b.y0)) + 2
        c0, c1 = int(b.x0) - 2, int(np.ceil(b.x1)) + 2
        outside[max(r0, 0):r1, max(c0, 0):c1] = False
        assert fast[r0 + 2:r1 - 2, c0 + 2:c1 - 2].min() < 100, t.get_text()  # Pillow's ink inside Matplotlib's box
    assert np.abs(fast - slow)[outside].max() < 1.0  # nothing else differs


def test_stereo_maps_cut_at_a_declared_crack_and_draw_it(tmp_path):
    """Stereo maps take the run's cracks (left reference px) as the 2-D maps do: the grid cells a crack enters
    are not drawn and the crack is drawn; a crack stored as vertex lists (the file's form) draws the same."""
    f3 = _field3d((60, 80), step=4)  # nodes x = 8, 12, ..., 68; cells 4 px wide centred on them
    crack = [[30.0, -5.0], [30.0, 70.0]]  # inside the cells of the node column x = 28 (26..30) and x = 32 (30..34)
    [ax] = field3d_figure(f3, "W", cracks=[crack]).axes
    grid = np.ma.filled(_field_image(ax).get_array().astype(float), np.nan)
    xs = np.arange(8, 72, 4.0)
    cut_cols = np.flatnonzero(np.abs(xs - 30.0) <= 2.0)
    assert cut_cols.tolist() == [5, 6] and np.isnan(grid[:, cut_cols]).all()
    others = np.setdiff1d(np.arange(len(xs)), cut_cols)
    assert np.isfinite(grid[:, others]).mean() > 0.9  # only the match failures besides the cut
    [line] = [ln for ln in ax.lines if ln.get_gid() == "crack"]
    assert np.array_equal(line.get_xdata(), [30.0, 30.0])
    plain = field3d_figure(f3, "W").axes[0]
    assert not [ln for ln in plain.lines if ln.get_gid() == "crack"]
    assert np.isfinite(np.ma.filled(_field_image(plain).get_array().astype(float), np.nan)[:, cut_cols]).any()
    paths = write_figures(f3, np.full((60, 80), 128.0), tmp_path, quantities=["W"], cracks=[crack])
    assert paths[0].stat().st_size > 1000
