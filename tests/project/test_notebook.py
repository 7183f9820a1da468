"""Notebook use: short reprs of fields, matches and result files; .plot() methods returning Figures with
signed quantities on a diverging map centred on zero and, on request, one colour range over a sequence."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parents[1] / "dic"))  # the fixtures' module, whatever ran before
from test_export_formats import field2d, field3d, results2d, results3d  # noqa: E402, F401 (fixtures)

from dic._strain import strain
from dic.plots.fields import DIVERGING_CMAP, SEQUENTIAL_CMAP, field3d_figure, field_figure, sequence_limits
from dic.store import read_results, read_stereo

ROOT = Path(__file__).resolve().parents[2]


def _short(text: str, max_len: int = 320):
    assert "\n" not in text and len(text) <= max_len and "array(" not in text, text
    return text


def _match(n=40):
    from dic._stereo import StereoMatch

    status = np.zeros(n, np.int8)
    status[:3] = 3
    return StereoMatch(points_left=np.zeros((n, 2)), points_right=np.zeros((n, 2)), params=np.zeros((n, 12)),
                       zncc=np.ones(n), iterations=np.ones(n, np.int32), icgn_status=np.zeros(n, np.int32),
                       epipolar_px=np.zeros(n), guess_source=np.zeros(n, np.int8), status=status, n_features=11)


def test_reprs_are_short(results2d, results3d):  # noqa: F811
    f = field2d(1)
    text = _short(repr(f))
    assert text.startswith("<Field2D: 30 points, 28 valid (93.3 %)") and "step 8 px" in text
    text = _short(repr(field3d(2)))
    assert "state 2, 20 points on a 4 x 5 grid, 17 OK" in text and "plane frame" in text
    assert _short(repr(_match())) == ("<StereoMatch: 40 points, 37 OK (92.5 %), 11 feature matches, order 2; "
                                      "not OK: MATCH_FAILED 3>")
    res = read_results(results2d)
    text = _short(repr(res))
    assert "2-D DIC, frames 3 (1..3), 30 points" in text and "valid 93.3 % per frame" in text
    assert "reference ref.tif (70 x 60 px)" in text and "subset 15" in text
    assert _short(repr(res.frames[2])).startswith("<FrameResult: frame 2, 30 points, 28 valid")
    text = _short(repr(read_stereo(results3d)))
    assert text.startswith("<StereoResults: states 3 (0..2), 20 points on a 4 x 5 grid, plane frame (mm)")
    assert "OK 85.0-95.0 % per state" in text and "images 320 x 240 px" in text
    # the print() of a notebook cell
    out = subprocess.run([sys.executable, "-c", f"from dic.store import read_results; print(read_results({str(res.path)!r}))"],
                         cwd=ROOT, capture_output=True, text=True, check=True).stdout
    assert out.count("\n") == 1


def _images(fig):
    return [im for ax in fig.axes for im in ax.images if im.get_gid() == "map"]


def test_signed_components_spanning_zero_on_a_diverging_map_centred_on_zero():
    """2-D figures used a sequential map (viridis) with limits that were not centred on zero; then every
    signed map was centred on zero, flattening offset fields (issue 25): now only a range that spans zero is."""
    f = field2d(2)  # u > 0, v < 0 everywhere, exx = 0.002 uniform; exy = 0 (spans zero once padded)
    s = strain(f, window=3)
    f.u = f.u - np.median(f.u[f.valid])  # u now spans zero
    fig = field_figure(None, f, s, components=["u", "v", "exx", "exy", "magnitude"])
    ims = _images(fig)
    assert len(ims) == 5
    for im in (ims[0], ims[3]):
        lo, hi = im.get_clim()
        assert im.get_cmap().name == DIVERGING_CMAP and lo == -hi and hi > 0
    for im in (ims[1], ims[2], ims[4]):  # one-signed: sequential over its own range, not centred on zero
        lo, hi = im.get_clim()
        assert im.get_cmap().name == SEQUENTIAL_CMAP and (hi < 0 or lo > 0)
    # a user's map applies to all
    assert {im.get_cmap().name for im in _images(field_figure(None, f, cmap="magma"))} == {"magma"}


def test_fixed_colour_range_over_a_sequence(results2d):  # noqa: F811
    """Each frame's figure rescaled its colours; limits= (or vmin=/vmax=) now fix them."""
    res = read_results(results2d)
    figs = [res.plot(k, limits="sequence") for k in res.indices]
    clims = [[im.get_clim() for im in _images(fig)] for fig in figs]
    assert clims[0] == clims[1] == clims[2] and len(clims[0]) == 5
    frames = [res.frames[k] for k in res.indices]
    lim = sequence_limits(frames, ["u", "exx"])
    all_u = np.concatenate([fr.u[fr.valid] for fr in frames])
    # u > 0 in every frame: one sequential range over every frame's values (1st-99th percentiles)
    assert lim["u"] == pytest.approx(tuple(np.percentile(all_u, (1, 99))))
    assert clims[0][0] == pytest.approx(lim["u"])
    # per frame (the default) the ranges differ, since u grows from frame to frame
    per_frame = [_images(res.plot(k))[0].get_clim() for k in res.indices]
    assert per_frame[0] != per_frame[2]
    f = field2d(1)
    assert _images(f.plot(vmin=-2, vmax=3))[0].get_clim() == (-2, 3)
    assert _images(f.plot(limits={"v": (0, 1)}))[1].get_clim() == (0, 1)
    with pytest.raises(ValueError, match="vmin < vmax"):
        f.plot(vmin=3, vmax=1)
    with pytest.raises(ValueError, match=r"limits\['u'\] must be a \(vmin, vmax\) pair"):
        f.plot(limits={"u": 5})
    with pytest.raises(ValueError, match="limits must be 'frame', 'sequence'"):
        res.plot(1, limits="global")
    with pytest.raises(ValueError, match="no frame 7"):
        res.plot(7)


def test_plot_methods_return_figures(results2d, results3d):  # noqa: F811
    from matplotlib.figure import Figure

    ref = np.random.default_rng(0).uniform(0, 255, (60, 70))
    f = field2d(1)
    assert isinstance(f.plot(ref, strain(f, window=3)), Figure)
    res = read_results(results2d)
    fig = res.frames[3].plot(ref)
    assert isinstance(fig, Figure) and fig._suptitle.get_text() == "frame 3: cur3.tif"
    assert isinstance(res.plot(), Figure)
    f3 = field3d(2)
    fig = f3.plot("W")
    im = _images(fig)[0]
    assert im.get_cmap().name == DIVERGING_CMAP and im.get_clim()[0] == -im.get_clim()[1]
    assert _images(f3.plot("Z", ref, vmin=1000, vmax=1001))[0].get_clim() == (1000, 1001)
    assert isinstance(f3.plot("status"), Figure)
    st = read_stereo(results3d)
    seq = [_images(st.plot(k, "U", limits="sequence"))[0].get_clim() for k in (1, 2)]
    assert seq[0] == seq[1]
    assert _images(st.plot(2, "W", limits=(-1, 1)))[0].get_clim() == (-1, 1)
    with pytest.raises(ValueError, match="unknown figure quantity"):
        field3d_figure(f3, "T")
    with pytest.raises(ValueError, match="no state 9"):
        st.plot(9)
