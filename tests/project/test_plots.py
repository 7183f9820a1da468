"""The plotting package dic.plots: the only place that imports Matplotlib, its shared helpers, and the
figures not covered by the CLI tests (test_cli_track, test_cli_calibrate, test_export draw the others)."""
import ast
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dic.plots._common import new_figure, padded_limits, percentile_limits, save_figure

ROOT = Path(__file__).resolve().parents[2]
#: files outside dic/plots allowed to import Matplotlib (the research code in repro/ is not scanned)
ALLOWED: set[str] = set()


def _imports_matplotlib(path: Path) -> list[int]:
    """Line numbers of every ``import matplotlib...`` / ``from matplotlib... import`` (also inside functions)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import) and any(a.name.split(".")[0] == "matplotlib" for a in node.names):
            lines.append(node.lineno)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] == "matplotlib":
            lines.append(node.lineno)
    return lines


def test_no_module_outside_dic_plots_imports_matplotlib():
    offenders = []
    for package in ("kernels", "calibration", "dic"):
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            if rel.startswith("dic/plots/") or rel in ALLOWED:
                continue
            offenders += [f"{rel}:{n}" for n in _imports_matplotlib(path)]
    assert not offenders, "Matplotlib imported outside dic/plots (plot through dic.plots instead): " + ", ".join(offenders)
    # the scan does see the imports it should
    assert _imports_matplotlib(ROOT / "dic/plots/_common.py")


def test_importing_dic_plots_imports_no_matplotlib():
    code = ("import sys, dic, dic.plots; assert callable(dic.plots.field_figure); "
            "print(sorted(m for m in ('matplotlib', 'calibration.pipeline', 'dic.lab') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_colour_limits():
    v = np.r_[np.linspace(-2.0, 1.0, 1001), np.nan, 50.0]
    lo, hi = percentile_limits(v)
    assert lo == pytest.approx(np.percentile(v[np.isfinite(v)], 1)) and hi == pytest.approx(np.percentile(v[np.isfinite(v)], 99))
    slo, shi = percentile_limits(v, symmetric=True)
    assert slo == -shi == pytest.approx(-abs(lo))
    assert percentile_limits([np.nan, np.inf]) is None
    assert percentile_limits(np.full(5, 3.0)) == (3.0, 3.0 + 1e-12)
    # padded: a uniform map gets a ±1 % range about its value; none finite: (-1, 1)
    assert padded_limits(np.full(10, 2.0)) == pytest.approx((1.98, 2.02))
    assert padded_limits([np.nan]) == (-1.0, 1.0)
    assert padded_limits(v) == (lo, hi)


def test_save_figure(tmp_path):
    fig = new_figure((2, 1.5))
    fig.subplots().plot([0, 1], [1, 0])
    p = save_figure(fig, tmp_path / "a" / "b.png", dpi=50)
    assert p.read_bytes()[:4] == b"\x89PNG"
    with pytest.raises(ValueError, match="figsize"):
        new_figure((0, 1))
    with pytest.raises(ValueError, match="dpi"):
        save_figure(fig, tmp_path / "c.png", dpi=0)


def _field2d(grid=True):
    from types import SimpleNamespace

    gy, gx = np.meshgrid(np.arange(5) * 8.0 + 10, np.arange(6) * 8.0 + 10, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    if not grid:
        pts = pts + np.random.default_rng(0).uniform(-2, 2, pts.shape)
    u = 0.01 * pts[:, 0]
    valid = np.ones(len(pts), bool)
    valid[3] = False
    return SimpleNamespace(points=pts, u=u, v=np.full(len(pts), 0.25), valid=valid)


@pytest.mark.parametrize("grid", [True, False])
def test_field_figure(tmp_path, grid):
    from dic.plots import field_figure, write_field_figure

    ref = np.random.default_rng(1).uniform(0, 255, (64, 72))
    fig = field_figure(ref, _field2d(grid), components=["u", "v", "magnitude"], title="t")
    titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
    assert titles == ["displacement u (px)", "displacement v (px)", "displacement magnitude |d| (px)"]
    p = write_field_figure(tmp_path / "f.png", ref, _field2d(grid), dpi=40)
    assert p.stat().st_size > 1000
    with pytest.raises(ValueError, match="unknown component"):
        field_figure(ref, _field2d(), components=["w"])
    with pytest.raises(ValueError, match="needs a strain field"):
        field_figure(ref, _field2d(), components=["exx"])
    with pytest.raises(ValueError, match="2-D grey image"):
        field_figure(np.zeros((4, 4, 3)), _field2d())
    with pytest.raises(ValueError, match="Field2D"):
        field_figure(ref, object())


def test_package_level_figure_names():
    import dic
    from dic.plots import fields

    assert dic.write_figures is fields.write_figures


def test_plot_layout(tmp_path):
    from dic.lab.paper import paper_rig
    from dic.plots import plot_layout

    rig = paper_rig(scale=0.25)
    fig = plot_layout(rig, tmp_path / "layout.png")
    assert (tmp_path / "layout.png").stat().st_size > 5000
    assert [ax.get_title() for ax in fig.axes] == ["top view", "top view, around the cameras", "side view"]
    with pytest.raises(ValueError, match="dic.lab.Scene"):
        plot_layout("scene.json")
    with pytest.raises(ValueError, match="near"):
        plot_layout(rig, near=0)


def test_calibration_figures_check_their_input(tmp_path):
    from dic.plots.calibration import (
        write_check_figures,
        write_intrinsics_figures,
        write_mirror_figures,
        write_rig_figures,
    )

    for fn in (write_intrinsics_figures, write_mirror_figures, write_rig_figures):
        with pytest.raises(ValueError, match="calibration.pipeline"):
            fn(object(), tmp_path)
    with pytest.raises(ValueError, match="empty"):
        write_check_figures([], tmp_path)
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="not a folder"):
        write_check_figures([(None, None)], tmp_path / "file")


def test_rig_residual_figure_left_out_with_a_warning(tmp_path, monkeypatch):
    """When the residuals recomputed for stereo_residuals.png do not reproduce the adjustment's RMS, the figure
    is left out with a FigureSkipped warning (the CLI prints it as a note) instead of drawing wrong residuals."""
    from types import SimpleNamespace

    from calibration.pipeline import RigCalibration
    from dic.plots import calibration as cal

    r = np.full((4, 2), 0.1)  # RMS 0.1414 px, the adjustment says 0.2
    monkeypatch.setattr(cal, "_joint_residuals", lambda rc: {"left": [("a", r, r)], "right": [("b", r, r)]})
    rc = RigCalibration(rig=None, per_camera=None, joint=SimpleNamespace(rms_groups={"left_mirrored": 0.2}),
                        far_views=[], check_views=[], checks=[], left=SimpleNamespace(names=["a"]),
                        right=SimpleNamespace(names=["b"]))
    with pytest.warns(cal.FigureSkipped, match="no stereo_residuals.png"):
        assert cal.write_rig_figures(rc, tmp_path) == []
    assert not (tmp_path / "stereo_residuals.png").exists()


def _capture_figures(monkeypatch):
    """Keep every figure dic.plots.calibration saves (it is still written), to read its artists back."""
    import dic.plots.calibration as cal

    figures = []

    def keep(fig, path, *, dpi):
        figures.append(fig)
        return save_figure(fig, path, dpi=dpi)

    monkeypatch.setattr(cal, "save_figure", keep)
    return figures


def test_view_rms_bars_per_camera_with_the_limit(tmp_path, monkeypatch):
    from dic.plots.calibration import view_rms_bars

    figures = _capture_figures(monkeypatch)
    per_camera = {"left": [("tilt1", 0.012), ("tilt2", 0.015), ("far", 0.020)],
                  "right": [("tilt1", 0.011), ("tilt2", 0.013)]}
    path = view_rms_bars(per_camera, tmp_path / "bars.png", limits={"left": 0.045, "right": None})
    assert path.stat().st_size > 1000
    [fig] = figures
    left, right = fig.axes[:2]
    assert [round(p.get_height(), 9) for p in left.patches] == [0.012, 0.015, 0.020]
    assert [t.get_text() for t in left.get_xticklabels()] == ["tilt1", "tilt2", "far"]
    red = [ln for ln in left.get_lines() if "rejection limit" in ln.get_label()]
    assert len(red) == 1 and red[0].get_ydata()[0] == pytest.approx(0.045)
    median = [ln for ln in left.get_lines() if ln.get_label().startswith("median")]
    assert median[0].get_ydata()[0] == pytest.approx(0.015)
    assert not [ln for ln in right.get_lines() if "rejection limit" in ln.get_label()]  # no limit given
    assert len(right.patches) == 2
    with pytest.raises(ValueError, match="non-empty dict"):
        view_rms_bars({}, tmp_path / "x.png")
