"""Movies of result files (``specula animate``, dic/animate.py, dic/plots/animate.py) read back with imageio,
and PLY point clouds of stereo states (dic/export.py ``write_ply``, ``specula export --format ply``) read back with the
small PLY parser below (header + numpy.fromfile), independent of the writer."""
import numpy as np
import pytest
from click.testing import CliRunner

from dic._strain import strain
from dic.cli import main
from dic.field2d import Field2D
from dic.field3d import Field3D, StereoStatus
from dic.store import ResultWriter

NY, NX = 5, 6
N_STATES = 3


def field2d(k):
    """A 2-D frame on a 5 x 6 grid (step 8 px): u = 0.5 k + 0.01 k x (so exx = 0.01 k grows with k), one
    point failed per frame."""
    gy, gx = np.meshgrid(np.arange(NY) * 8.0 + 12, np.arange(NX) * 8.0 + 12, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    n = len(pts)
    u = 0.5 * k + 0.01 * k * pts[:, 0]
    v = -0.2 * k + 0.0 * pts[:, 1]
    params = np.zeros((n, 6))
    params[:, 0], params[:, 3], params[:, 1] = u, v, 0.01 * k
    status = np.zeros(n, np.int32)
    status[k] = 2
    return Field2D(points=pts, u=u, v=v, params=params, zncc=np.full(n, 0.95), iterations=np.full(n, 3, np.int32),
                   status=status, valid=status == 0, subset=15, order=1, step=8, zncc_min=0.8)


def field3d(k, ny=4, nx=5):
    """A stereo state: positions shared by every state (NaN where the reference match failed), W growing
    with k, two points failed in this state."""
    n = ny * nx
    gy, gx = np.meshgrid(np.arange(ny) * 10.0 + 20, np.arange(nx) * 10.0 + 20, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    status = np.zeros(n, np.int8)
    status[2] = StereoStatus.MATCH_FAILED
    if k:
        status[[5 + k, 11 + k]] = StereoStatus.TRACK_LEFT_FAILED
    has_pos = status != StereoStatus.MATCH_FAILED
    ok = status == StereoStatus.OK
    X = np.where(has_pos, 0.5 * pts[:, 0] - 20, np.nan)
    Y = np.where(has_pos, 0.5 * pts[:, 1] - 15, np.nan)
    Z = np.where(has_pos, 1000 + 0.01 * pts[:, 0], np.nan)
    U = np.where(ok, 0.1 * k + 0.001 * pts[:, 0], np.nan)
    V = np.where(ok, -0.05 * k, np.nan)
    W = np.where(ok, 0.02 * k * np.sin(pts[:, 1] / 10) + 0.01 * k, np.nan)
    e = {name: np.where(ok, 1e-4 * k * (j + 1), np.nan) for j, name in enumerate(("exx", "eyy", "exy"))}
    q = {name: np.where(ok, 0.95, np.nan) for name in ("zncc_stereo", "zncc_left", "zncc_right")}
    r = {name: np.where(ok, 0.05, np.nan) for name in ("epipolar_ref_px", "epipolar_px", "reprojection_ref_px",
                                                        "reprojection_px")}
    return Field3D(points=pts, grid_shape=(ny, nx), X=X, Y=Y, Z=Z, U=U, V=V, W=W, **e, **q, **r,
                   normal=np.where(ok[:, None], [0.0, 0.0, -1.0], np.nan), status=status, strain_valid=ok.copy(),
                   index=k, frame_name="left")


@pytest.fixture
def results2d(tmp_path):
    path = tmp_path / "run2d.h5"
    with ResultWriter(path, reference_path="missing_ref.tif", reference_shape=(60, 70),
                      settings={"subset": 15, "step": 8}) as w:
        for k in range(1, N_STATES + 1):
            f = field2d(k)
            w.write_frame(k, f, strain=strain(f, window=3), path=f"cur{k}.tif")
    return path


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
        for k in range(N_STATES):
            w.write_frame(k, field3d(k), path=(f"l{k}.tif", f"r{k}.tif"))
    return path


def run(args):
    return CliRunner().invoke(main, args)


def _movie(path):
    import imageio.v3 as iio

    return list(iio.imiter(path))


# -- movies ------------------------------------------------------------------------------------------------
def test_animate_writes_mp4_and_gif_with_one_frame_per_result_frame(results2d, results3d, tmp_path):
    import imageio.v3 as iio

    r = run(["animate", str(results2d), "--quantity", "exx", "-o", str(tmp_path / "exx.mp4"), "--fps", "4"])
    assert r.exit_code == 0, r.output
    assert "missing_ref.tif not found" in r.output  # the stored reference image is absent: said, not fatal
    frames = _movie(tmp_path / "exx.mp4")
    assert len(frames) == N_STATES
    h, w = frames[0].shape[:2]
    assert h % 16 == 0 and w % 16 == 0 and h >= 200 and w >= 300
    assert all(f.shape == frames[0].shape for f in frames)
    assert iio.immeta(tmp_path / "exx.mp4")["fps"] == pytest.approx(4.0)

    r = run(["animate", str(results3d), "-Q", "W", "-o", str(tmp_path / "w.gif"), "--frames", "1-2", "-q"])
    assert r.exit_code == 0, r.output
    props = iio.improps(tmp_path / "w.gif", index=None)
    assert props.n_images == 2 and props.shape[1] % 16 == 0 and props.shape[2] % 16 == 0
    assert sorted(p.name for p in tmp_path.iterdir() if p.suffix in (".mp4", ".gif")) == ["exx.mp4", "w.gif"]
    assert "animate" in run(["--help"]).output


def test_one_colour_range_for_the_whole_movie(results2d):
    from dic.animate import animation_frames, animation_limits
    from dic.plots._common import LIMIT_PERCENTILES
    from dic.plots.fields import field_figure
    from dic.store import ResultFrames

    # the range: percentiles of every frame's valid u together (u > 0 here: not centred on zero)
    u_all = np.concatenate([field2d(k).u[field2d(k).valid] for k in range(1, N_STATES + 1)])
    lo, hi = np.percentile(u_all, LIMIT_PERCENTILES)
    assert animation_limits(results2d, "u") == pytest.approx((lo, hi), rel=1e-12)
    assert animation_limits(results2d, "u", frames=[1]) == pytest.approx(
        tuple(np.percentile(field2d(1).u[field2d(1).valid], LIMIT_PERCENTILES)), rel=1e-12)

    frames = [rgb for _, rgb in animation_frames(results2d, "u")]
    h, w = frames[0].shape[:2]
    bar = (slice(int(0.15 * h), h), slice(int(0.82 * w), w))  # the colourbar and its tick labels, right of the map
    assert np.array_equal(frames[0][bar], frames[-1][bar])
    assert np.mean(np.any(frames[0][bar] != 255, axis=-1)) > 0.05  # the crop holds the coloured bar (about 10 px of 104), not white paper
    assert not np.array_equal(frames[0][: int(0.9 * h), : int(0.8 * w)], frames[-1][: int(0.9 * h), : int(0.8 * w)])
    # the control: with each frame's own range the same crop differs (the crop does show the scale)
    with ResultFrames(results2d) as src:
        own = []
        for i in (1, N_STATES):
            fig = field_figure(None, src.read(i), components=["u"], title=f"frame {i}", panel_size=5.0, dpi=80)
            fig.canvas.draw()
            own.append(np.asarray(fig.canvas.buffer_rgba())[..., :3])
    assert not np.array_equal(own[0][bar], own[1][bar])


def test_a_signed_range_that_spans_zero_is_symmetric_and_frames_are_read_one_at_a_time(results3d, monkeypatch):
    from dic.animate import animation_frames, animation_limits
    from dic.plots._common import LIMIT_PERCENTILES
    from dic.store import ResultFrames

    w_all = np.concatenate([field3d(k).W[field3d(k).valid] for k in range(N_STATES)])
    p1, p99 = np.percentile(w_all, LIMIT_PERCENTILES)
    assert p1 < 0 < p99
    m = max(abs(p1), abs(p99))
    assert animation_limits(results3d, "W") == pytest.approx((-m, m), rel=1e-12)

    reads = []
    real = ResultFrames.read
    monkeypatch.setattr(ResultFrames, "read", lambda self, i: reads.append(i) or real(self, i))
    stream = animation_frames(results3d, "W", frames=[1, 2])
    assert next(stream)[0] == 1
    assert reads[-3:] == [1, 2, 1]  # the colour range (states 1, 2), then only the first picture so far
    assert [i for i, _ in stream] == [2] and reads[-1] == 2


def test_the_reference_image_is_drawn_beneath_the_maps(results3d, tmp_path):
    from dic.animate import animation_frames
    from dic.io import write_image

    rng = np.random.default_rng(0)
    image = (rng.random((240, 320)) * 255).astype(np.uint8)
    plain = next(animation_frames(results3d, "W"))[1]
    over = next(animation_frames(results3d, "W", image=image))[1]

    def grey_share(rgb):  # pixels of a mid grey (r = g = b, neither black text nor white paper)
        r, g, b = (rgb[..., c].astype(int) for c in range(3))
        return np.mean((r == g) & (g == b) & (r > 30) & (r < 225))

    assert grey_share(over) > 0.3 and grey_share(plain) < 0.05
    # the CLI reads the stored left reference image when it exists (relative to the result file)
    write_image(tmp_path / "l0.tif", image)
    r = run(["animate", str(results3d), "-Q", "Z", "-o", str(tmp_path / "z.gif")])
    assert r.exit_code == 0 and "not found" not in r.output, r.output


def test_bad_inputs_are_refused_with_one_line(results2d, results3d, tmp_path):
    empty = tmp_path / "empty.h5"
    ResultWriter(empty, reference_path="r.tif", reference_shape=(10, 10)).close()
    out = str(tmp_path / "m.mp4")
    cases = [
        (["animate", str(results2d), "-Q", "W", "-o", out], 1, "unknown quantity 'W' for this 2-D result file; "
                                                               "choose from u, v, magnitude, exx, eyy, exy"),
        (["animate", str(results3d), "-Q", "u", "-o", out], 1, "choose from Z, U, V, W, exx, eyy, exy, zncc_stereo"),
        (["animate", str(empty), "-Q", "u", "-o", out], 1, "no finished frame to animate"),
        (["animate", str(results2d), "-Q", "u", "-o", out, "--fps", "0"], 2, "--fps"),
        (["animate", str(results2d), "-Q", "u", "-o", out, "--fps", "-3"], 2, "--fps"),
        (["animate", str(results2d), "-Q", "u", "-o", out, "--fps", "fast"], 2, "--fps"),
        (["animate", str(results2d), "-Q", "u", "-o", out, "--fps", "1000"], 2, "--fps"),
        (["animate", str(results2d), "-Q", "u", "-o", str(tmp_path / "m.avi")], 1, "must end in .mp4 or .gif"),
        (["animate", str(results2d), "-Q", "u", "-o", out, "--frames", "2-9"], 1,
         "no finished frame 4, 5, 6, 7, 8, 9 in the result file; finished: 1, 2, 3"),
        (["animate", str(results2d), "-Q", "u", "-o", out, "--frames", "x"], 2, "--frames"),
        (["animate", str(tmp_path / "nope.h5"), "-Q", "u", "-o", out], 1, "result file not found"),
        (["animate", str(results2d), "-Q", "", "-o", out], 2, "must not be empty"),
    ]
    for args, code, text in cases:
        r = CliRunner().invoke(main, args)
        assert r.exit_code == code, (args, r.output)
        assert text in r.output and "Traceback" not in r.output, (args, r.output)
        assert isinstance(r.exception, SystemExit)
        assert len([ln for ln in r.output.splitlines() if ln.startswith("Error")]) == 1, r.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty.h5", "run2d.h5", "run3d.h5"]  # no movie, no partial


def test_a_failed_movie_leaves_no_file(results2d, tmp_path, monkeypatch):
    import dic.animate as animate

    real = animate.animation_frames

    def fail_after_one(*args, **kwargs):
        stream = real(*args, **kwargs)
        yield next(stream)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(animate, "animation_frames", fail_after_one)
    for name in ("m.mp4", "m.gif"):
        with pytest.raises(OSError, match="No space left"):
            animate.write_animation(results2d, tmp_path / name, quantity="u")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run2d.h5"]


# -- PLY ---------------------------------------------------------------------------------------------------
_PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "<i2", "ushort": "<u2", "int": "<i4", "uint": "<u4",
              "float": "<f4", "double": "<f8"}


def read_ply(path):
    """A PLY file's vertices as a structured array, and its format: a reader written from the PLY spec."""
    with open(path, "rb") as fh:
        assert fh.readline() == b"ply\n"
        fmt, names, types, count = None, [], [], None
        while True:
            words = fh.readline().decode("ascii").split()
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                assert words[1] == "vertex"
                count = int(words[2])
            elif words[0] == "property":
                types.append(_PLY_TYPES[words[1]])
                names.append(words[2])
            elif words[0] == "end_header":
                break
        dtype = np.dtype(list(zip(names, types)))
        if fmt == "binary_little_endian":
            table = np.fromfile(fh, dtype=dtype, count=count)
            assert fh.read() == b""
        else:
            assert fmt == "ascii"
            rows = [line.split() for line in fh.read().decode("ascii").splitlines()]
            table = np.array([tuple(float(v) for v in row) for row in rows], dtype=dtype)
    assert len(table) == count
    return table, fmt


@pytest.mark.parametrize("binary", [True, False])
def test_ply_of_a_state_reads_back(tmp_path, binary):
    from dic.export import write_ply

    f = field3d(2)
    [path] = write_ply(f, tmp_path / "s.ply", binary=binary)
    table, fmt = read_ply(path)
    assert fmt == ("binary_little_endian" if binary else "ascii")
    valid = np.flatnonzero(f.valid)
    assert len(valid) == 20 - 3  # one reference failure, two failures in this state
    assert np.array_equal(table["point"], valid)
    for j, name in enumerate("xyz"):
        assert np.array_equal(table[name], f.xyz[valid, j])
    for j, name in enumerate("UVW"):
        assert np.array_equal(table[name], f.uvw[valid, j])
    assert np.all(table["valid"] == 1)

    [nan_path] = write_ply(f, tmp_path / "n.ply", binary=binary, invalid="nan")
    every, _ = read_ply(nan_path)
    assert np.array_equal(every["point"], np.flatnonzero(np.isfinite(f.Z)))  # all but the reference failure
    assert np.array_equal(every["valid"].astype(bool), f.valid[every["point"]])
    assert np.all(np.isnan(every["W"][every["valid"] == 0])) and np.array_equal(every["z"], f.Z[every["point"]])

    [moved] = write_ply(f, tmp_path / "d.ply", binary=binary, deformed=True)
    table, _ = read_ply(moved)
    assert np.allclose(table["z"], f.Z[valid] + f.W[valid], rtol=0, atol=1e-12)


def test_cli_export_ply_writes_one_cloud_per_state(results2d, results3d, tmp_path):
    r = run(["export", str(results3d), "--format", "ply", "-o", str(tmp_path / "ply")])
    assert r.exit_code == 0, r.output
    assert "wrote 3 PLY point cloud(s), one per state, to" in r.output
    names = sorted(p.name for p in (tmp_path / "ply").iterdir())
    assert names == ["stereo_000000.ply", "stereo_000001.ply", "stereo_000002.ply"]
    table, fmt = read_ply(tmp_path / "ply" / "stereo_000002.ply")
    f = field3d(2)
    assert fmt == "binary_little_endian" and np.array_equal(table["W"], f.W[f.valid])
    r = run(["export", str(results2d), "--format", "ply", "-o", str(tmp_path / "ply2")])
    assert r.exit_code == 1 and "PLY export is for stereo result files" in r.output and "Traceback" not in r.output
    r = run(["export", str(results2d), "--format", "csv", "-o", str(tmp_path / "c"), "--deformed"])
    assert r.exit_code == 2 and "--deformed applies to --format vtk and ply only" in r.output
