"""``specula report`` / ``dic.write_report``: one self-contained HTML run report (dic/report.py), checked in the file
and in a real browser (headless Chromium: no console message, and a screenshot that shows the map of the frame
named by ``#frame=K``, pixel for pixel). The browser tests skip when Chromium is not installed (.ci/run installs it).
"""
import base64
import re
import shutil
import subprocess

import numpy as np
import pytest
from click.testing import CliRunner

from dic._strain import strain
from dic.cli import main
from dic.field2d import Field2D
from dic.field3d import Field3D, StereoStatus
from dic.io import write_image
from dic.store import ResultWriter

NY, NX, STEP, X0 = 5, 6, 8, 12  # a 5 x 6 grid of points at 12 + 8 i px
H, W = 60, 70  # the reference image
FRAMES = (1, 2, 3)


def field2d(k):
    """u = 0.5 k + 0.01 k x (exx = 0.01 k), v = -0.2 k; point k (row 0) failed in frame k."""
    gy, gx = np.meshgrid(np.arange(NY) * STEP + X0, np.arange(NX) * STEP + X0, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()]).astype(np.float64)
    n = len(pts)
    u = 0.5 * k + 0.01 * k * pts[:, 0]
    v = np.full(n, -0.2 * k)
    params = np.zeros((n, 6))
    params[:, 0], params[:, 3], params[:, 1] = u, v, 0.01 * k
    status = np.zeros(n, np.int32)
    status[k] = 2
    return Field2D(points=pts, u=u, v=v, params=params, zncc=np.linspace(0.9, 0.99, n),
                   iterations=np.full(n, 3 + k, np.int32), status=status, valid=status == 0, subset=15, order=1,
                   step=STEP, zncc_min=0.8)


@pytest.fixture
def reference_image(tmp_path):
    """A horizontal ramp 0..255 (uint8), saved where the result file records it."""
    img = np.tile(np.rint(np.linspace(0, 255, W)), (H, 1)).astype(np.uint8)
    path = tmp_path / "ref.png"
    write_image(path, img)
    return path, img


@pytest.fixture
def results2d(tmp_path, reference_image):
    path = tmp_path / "run2d.h5"
    with ResultWriter(path, reference_path=str(reference_image[0]), reference_shape=(H, W),
                      settings={"subset": 15, "step": STEP}) as w:
        for k in FRAMES:
            f = field2d(k)
            w.write_frame(k, f, strain=strain(f, window=3), path=f"cur{k}.tif", attrs={"seconds": 0.25 * k})
    return path


def field3d(k, ny=4, nx=5):
    """A stereo state: points 0, 1 outside the region (NOT_COMPUTED), point 2 unmatched, two more failed from
    state 1 on; W = 0.01 k + 0.001 x."""
    n = ny * nx
    gy, gx = np.meshgrid(np.arange(ny) * 10.0 + 20, np.arange(nx) * 10.0 + 20, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    status = np.zeros(n, np.int8)
    status[[0, 1]] = StereoStatus.NOT_COMPUTED
    status[2] = StereoStatus.MATCH_FAILED
    if k:
        status[[5 + k, 11 + k]] = StereoStatus.TRACK_LEFT_FAILED
    has_pos = (status != StereoStatus.MATCH_FAILED) & (status != StereoStatus.NOT_COMPUTED)
    ok = status == StereoStatus.OK
    X = np.where(has_pos, 0.5 * pts[:, 0] - 20, np.nan)
    Y = np.where(has_pos, 0.5 * pts[:, 1] - 15, np.nan)
    Z = np.where(has_pos, 1000 + 0.01 * pts[:, 0], np.nan)
    U = np.where(ok, 0.1 * k, np.nan)
    V = np.where(ok, -0.05 * k, np.nan)
    Wd = np.where(ok, 0.01 * k + 0.001 * pts[:, 0], np.nan)
    e = {name: np.where(ok, 1e-4 * k * (j + 1), np.nan) for j, name in enumerate(("exx", "eyy", "exy"))}
    q = {name: np.where(ok, 0.95, np.nan) for name in ("zncc_stereo", "zncc_left", "zncc_right")}
    r = {name: np.where(ok, 0.05, np.nan) for name in ("epipolar_ref_px", "epipolar_px", "reprojection_ref_px",
                                                        "reprojection_px")}
    return Field3D(points=pts, grid_shape=(ny, nx), X=X, Y=Y, Z=Z, U=U, V=V, W=Wd, **e, **q, **r,
                   normal=np.where(ok[:, None], [0.0, 0.0, -1.0], np.nan), status=status, strain_valid=ok.copy(),
                   index=k, frame_name="left")


@pytest.fixture
def results3d(tmp_path):
    from calibration.camera import Camera
    from calibration.stereo import StereoRig

    K = np.array([[1641.0, 0, 160], [0, 1641.0, 120], [0, 0, 1]])
    rig = StereoRig(Camera(K=K, size=(320, 240), name="left"), Camera(K=K, size=(320, 240), name="right"),
                    np.eye(3), np.array([-300.0, 0.0, 0.0]))
    path = tmp_path / "run3d.h5"
    with ResultWriter(path, kind="stereo", rig=rig, reference_path=("l0.tif", "r0.tif"), reference_shape=(240, 320),
                      settings={"step": 10, "subset": 21}) as w:
        for k in range(3):
            w.write_frame(k, field3d(k), path=(f"l{k}.tif", f"r{k}.tif"))
    return path


def run(args):
    return CliRunner().invoke(main, [str(a) for a in args])


def embedded_maps(text: str) -> dict[int, np.ndarray]:
    """frame -> the map picture embedded in the report, decoded (H, W, 3) uint8."""
    import imageio.v3 as iio

    out = {}
    for frame, data in re.findall(r"<img[^>]*data-frame='(\d+)'[^>]*src='data:image/png;base64,([^']+)'", text):
        out[int(frame)] = np.asarray(iio.imread(base64.b64decode(data)))[..., :3]
    return out


def table_after(text: str, heading_id: str) -> list[list[str]]:
    """The cells of the first table after the heading ``heading_id``."""
    section = text[text.index(f"id='{heading_id}'"):]
    table = section[section.index("<table>"):section.index("</table>")]
    return [re.findall(r"<t[dh]>(.*?)</t[dh]>", row) for row in re.findall(r"<tr>(.*?)</tr>", table)]


# -- the file ----------------------------------------------------------------------------------------------
def test_report_is_self_contained_with_settings_quality_maps_histories_and_extensometers(results2d, tmp_path):
    out = tmp_path / "report.html"
    r = run(["report", results2d, "-o", out, "-Q", "u", "--history", "28,28", "--extensometer", "20,36,44,36"])
    assert r.exit_code == 0, r.output
    text = out.read_text(encoding="utf-8")
    # self-contained: every picture inline, no address of another file or host
    assert not re.search(r"(src|href)\s*=\s*['\"](?!data:|#)", text)
    assert "http://" not in text and "https://" not in text
    maps = embedded_maps(text)
    assert sorted(maps) == list(FRAMES)
    # settings as stored
    assert ["step", str(STEP)] in table_after(text, "settings") and ["subset", "15"] in table_after(text, "settings")
    # quality per frame: 29 of the 30 points valid in every frame, the iterations and seconds as written
    quality = table_after(text, "quality")
    assert quality[0][:3] == ["frame", "valid points", "region points"]
    for k, row in zip(FRAMES, quality[1:]):
        cells = dict(zip(quality[0], row))
        assert (cells["frame"], cells["valid points"], cells["region points"]) == (str(k), "29", "30")
        assert float(cells["mean IC-GN iterations"]) == 3 + k
        assert float(cells["seconds per frame"]) == 0.25 * k
    # u at the grid point (28, 28): 0.5 k + 0.01 k 28, exactly
    hist = table_after(text, "history")
    assert [float(row[1]) for row in hist[1:]] == pytest.approx([0.5 * k + 0.28 * k for k in FRAMES], rel=1e-12)
    # a gauge along x in a field with exx = 0.01 k: engineering strain 0.01 k
    ext = table_after(text, "extensometers")
    col = ext[0].index("strain")
    assert [float(row[col]) for row in ext[1:]] == pytest.approx([0.01 * k for k in FRAMES], rel=1e-9)


def test_map_pixels_are_the_colour_map_of_the_values_over_the_grey_reference(results2d, reference_image, tmp_path):
    import matplotlib

    from dic.plots._common import LIMIT_PERCENTILES

    out = tmp_path / "u.html"
    assert run(["report", results2d, "-o", out, "-Q", "u", "--no-image"]).exit_code == 0
    maps = embedded_maps(out.read_text(encoding="utf-8"))
    u_all = np.concatenate([field2d(k).u[field2d(k).valid] for k in FRAMES])
    lo, hi = np.percentile(u_all, LIMIT_PERCENTILES)  # u > 0 everywhere: one-signed, viridis over its own range
    viridis = matplotlib.colormaps["viridis"]
    s = 640 // W  # the 70 px image enlarged 9 times
    assert maps[1].shape == (H * s, W * s, 3)
    for k in FRAMES:
        f = field2d(k)
        for (x, y), u, ok in zip(f.points, f.u, f.valid):
            pixel = maps[k][int(y) * s + s // 2, int(x) * s + s // 2]
            if ok:
                assert tuple(pixel) == tuple(viridis(np.clip((u - lo) / (hi - lo), 0, 1), bytes=True)[:3]), (k, x, y)
            else:
                assert tuple(pixel) == (235, 235, 235)  # the failed point: paper, no colour
    # with the reference image: the colours at 80 % over the ramp, stretched over its 1st-99th percentiles and
    # rounded to 8 grey levels (the backdrop of every map; blocks of 1 px here: 3 map px per block at 9x)
    out = tmp_path / "u_img.html"
    assert run(["report", results2d, "-o", out, "-Q", "u", "-q"]).exit_code == 0
    maps = embedded_maps(out.read_text(encoding="utf-8"))
    img = reference_image[1].astype(np.float64)
    glo, ghi = np.percentile(img, (1, 99))

    def grey(x, y):
        return np.round(np.clip((img[y, x] - glo) / (ghi - glo), 0, 1) * 7) / 7 * 255

    f = field2d(1)
    for x, y in [(2, 2), (66, 57), (35, 3)]:  # outside the grid of points: the grey image only
        assert tuple(maps[1][y * s + s // 2, x * s + s // 2]) == (round(grey(x, y)),) * 3
    for x, y in [(28, 28), (52, 44)]:
        u = f.u[(f.points[:, 0] == x) & (f.points[:, 1] == y)][0]
        colour = np.asarray(viridis(np.clip((u - lo) / (hi - lo), 0, 1), bytes=True)[:3], np.float64)
        assert np.array_equal(maps[1][y * s + s // 2, x * s + s // 2], np.rint(0.8 * colour + 0.2 * grey(x, y)))


def test_frames_above_the_limit_are_decimated_evenly():
    from dic.report import report_frames

    assert report_frames(range(11), 4) == [0, 3, 7, 10]  # positions 0, 3.33, 6.67, 10 rounded
    assert report_frames([5, 1, 3], 40) == [1, 3, 5]
    picked = report_frames(range(1000), 40)
    assert len(picked) == 40 and picked[0] == 0 and picked[-1] == 999
    assert set(np.diff(picked)) <= {25, 26}  # 999 / 39 = 25.6 apart
    with pytest.raises(ValueError, match="max_frames"):
        report_frames(range(3), 0)


def test_report_decimation_on_the_cli_and_input_errors(results2d, tmp_path):
    out = tmp_path / "two.html"
    r = run(["report", results2d, "-o", out, "--max-frames", "2", "-q"])
    assert r.exit_code == 0, r.output
    text = out.read_text(encoding="utf-8")
    assert sorted(embedded_maps(text)) == [1, 3] and "2 of 3 frames shown" in text
    r = run(["report", results2d, "-o", out, "-Q", "W"])
    assert r.exit_code == 1 and "unknown quantity 'W'" in r.output and "magnitude" in r.output
    r = run(["report", results2d, "-o", tmp_path / "r.txt"])
    assert r.exit_code == 1 and "must end in .html" in r.output
    r = run(["report", results2d, "-o", out, "--extensometer", "1,2,3"])
    assert r.exit_code == 2 and "x1,y1,x2,y2" in r.output
    r = run(["report", tmp_path / "none.h5", "-o", out])
    assert r.exit_code == 1 and "not found" in r.output


def test_stereo_report_quality_over_the_region_and_shape(results3d, tmp_path):
    import dic
    from dic.report import frame_quality
    from dic.store import ResultReader

    with ResultReader(results3d) as reader:
        q = [frame_quality(reader, k) for k in range(3)]
    # 18 points in the region (2 NOT_COMPUTED); 1 unmatched; 2 more failed from state 1
    assert [(d["valid_points"], d["region_points"]) for d in q] == [(17, 18), (15, 18), (15, 18)]
    assert [d["valid_fraction"] for d in q] == [17 / 18, 15 / 18, 15 / 18]
    assert all(d["zncc_median"] == 0.95 and d["reprojection_median_px"] == 0.05 for d in q)
    out = dic.write_report(results3d, tmp_path / "stereo.html", history=[(60, 50)])
    text = out.read_text(encoding="utf-8")
    assert "id='shape'" in text and sorted(embedded_maps(text)) == [0, 1, 2]
    hist = table_after(text, "history")  # W at a grid point (60, 50) valid in every state: 0.01 k + 0.06
    assert [float(row[1]) for row in hist[1:]] == pytest.approx([0.06, 0.07, 0.08], rel=1e-9)


# -- in a real browser ---------------------------------------------------------------------------------------
CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)
needs_chromium = pytest.mark.skipif(CHROMIUM is None, reason="headless Chromium is not installed (Debian: apt-get "
                                    "install chromium; .ci/run installs it when it runs as root)")


def chromium(url: str, profile, *, screenshot=None, size=(1000, 1400)) -> tuple[str, list[str]]:
    """Load ``url`` in headless Chromium: (the DOM after the page's scripts ran; the console messages, one line
    each), and a screenshot of the window when ``screenshot`` names a PNG. The flags keep Chromium off the network."""
    args = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            f"--user-data-dir={profile}", "--enable-logging=stderr", "--v=0", "--force-device-scale-factor=1",
            "--force-color-profile=srgb", "--hide-scrollbars", f"--window-size={size[0]},{size[1]}"]
    args += ["--dump-dom"] + ([f"--screenshot={screenshot}"] if screenshot else [])
    done = subprocess.run(args + [url], capture_output=True, text=True, timeout=60)
    console = [line for line in done.stderr.splitlines() if ":CONSOLE" in line]
    return done.stdout, console


@needs_chromium
def test_console_messages_are_caught(tmp_path):
    """The control of the browser tests: a page that logs an error and throws is seen as such."""
    page = tmp_path / "bad.html"
    page.write_text("<html><body><script>console.error('broken'); notDefined();</script></body></html>")
    _, console = chromium(page.as_uri(), tmp_path / "profile")
    assert any("broken" in line for line in console) and any("notDefined" in line for line in console)


@needs_chromium
def test_browser_shows_the_map_of_the_frame_in_the_address(results2d, results3d, tmp_path):
    import imageio.v3 as iio

    out = tmp_path / "report.html"
    assert run(["report", results2d, "-o", out, "-Q", "u", "--history", "28,28", "-q"]).exit_code == 0
    maps = embedded_maps(out.read_text(encoding="utf-8"))
    url = out.as_uri() + "#frame=2"
    shot = tmp_path / "shot.png"
    dom, console = chromium(url, tmp_path / "profile1", screenshot=shot)
    assert console == []  # no error, no message at all
    body = re.search(r"<body([^>]*)>", dom).group(1)
    assert "data-report-ready=\"1\"" in body and "data-shown-frame=\"2\"" in body
    x, y, w, h = (int(v) for v in re.search(r'data-map-rect="([\d,]+)"', body).group(1).split(","))
    assert (h, w) == maps[2].shape[:2]
    pixels = np.asarray(iio.imread(shot))[..., :3]
    shown = pixels[y:y + h, x:x + w]
    assert np.array_equal(shown, maps[2])  # the embedded picture of frame 2, pixel for pixel
    assert not np.array_equal(shown, maps[3]) and not np.array_equal(shown, maps[1])  # not another frame's

    dom, console = chromium(out.as_uri() + "#frame=7", tmp_path / "profile4")  # a frame the report does not hold
    assert console == [] and 'data-shown-frame="3"' in dom and "frame 7 is not in this report" in dom

    out3 = tmp_path / "stereo.html"
    assert run(["report", results3d, "-o", out3, "-q"]).exit_code == 0
    dom, console = chromium(out3.as_uri(), tmp_path / "profile3")
    assert console == [] and "data-shown-frame=\"2\"" in dom  # no #frame: the last state
