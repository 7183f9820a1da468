"""``specula target show`` under Xvfb (calibration/display.py): the screen holds the target image pixel for pixel, and
the show steps on a timer and on key presses, running a command after each image. The screen is captured by that
command itself (``xwd -root``, the way a camera trigger would be run) and read by the small XWD reader below.

Skips when Xvfb, xdotool, xwd or Tk is missing (Debian: xvfb, xdotool, x11-apps; .ci/run installs them as root).
"""
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from dic.cli import main

TOOLS = {name: shutil.which(name) for name in ("Xvfb", "xdotool", "xwd")}
try:
    import tkinter  # noqa: F401
    HAS_TK = True
except ImportError:
    HAS_TK = False
MISSING = [name for name, path in TOOLS.items() if path is None] + ([] if HAS_TK else ["tkinter"])
pytestmark = pytest.mark.skipif(bool(MISSING), reason=f"needs {', '.join(MISSING)} (Debian: apt-get install xvfb xdotool "
                                "x11-apps; .ci/run installs them when it runs as root)")

SCREEN = (320, 240)


def read_xwd(path) -> np.ndarray:
    """An XWD screen dump (ZPixmap, 32 bits per pixel, as ``xwd`` writes a 24-bit screen) as (H, W, 3) uint8."""
    data = Path(path).read_bytes()
    hdr = np.frombuffer(data[:100], dtype=">u4")
    header_size, version, pixmap_format, _, width, height = (int(v) for v in hdr[:6])
    byte_order, bits_per_pixel, bytes_per_line = int(hdr[7]), int(hdr[11]), int(hdr[12])
    masks = [int(v) for v in hdr[14:17]]
    assert (version, pixmap_format, bits_per_pixel) == (7, 2, 32), "an XWD file of another layout"
    start = header_size + 12 * int(hdr[19])  # the colour map entries follow the header
    raw = np.frombuffer(data[start:start + height * bytes_per_line], dtype="<u4" if byte_order == 0 else ">u4")
    raw = raw.reshape(height, bytes_per_line // 4)[:, :width]
    return np.stack([((raw & m) >> ((m & -m).bit_length() - 1)).astype(np.uint8) for m in masks], axis=-1)


@pytest.fixture(scope="module")
def display():
    """A fresh Xvfb screen of SCREEN px at 24 bits; the environment to run on it."""
    number = next(n for n in range(90, 200) if not os.path.exists(f"/tmp/.X{n}-lock")
                  and not os.path.exists(f"/tmp/.X11-unix/X{n}"))
    server = subprocess.Popen([TOOLS["Xvfb"], f":{number}", "-screen", "0", f"{SCREEN[0]}x{SCREEN[1]}x24", "-nolisten",
                               "tcp"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    env = dict(os.environ, DISPLAY=f":{number}")
    try:
        for _ in range(100):
            if subprocess.run([TOOLS["xdotool"], "getdisplaygeometry"], env=env, capture_output=True).returncode == 0:
                break
            time.sleep(0.1)
        else:
            pytest.fail("Xvfb did not start")
        yield env
    finally:
        server.terminate()
        server.wait(timeout=10)


@pytest.fixture(scope="module")
def fringes(tmp_path_factory):
    """A real phase target for the screen: 3 fringe images (grey, 8-bit) and its JSON."""
    import imageio.v3 as iio

    out = tmp_path_factory.mktemp("fringes")
    r = CliRunner().invoke(main, ["target", "fringes", "--screen", f"{SCREEN[0]}x{SCREEN[1]}", "--grid", "4x2",
                                  "--pitch", "60", "--steps", "3", "-o", str(out)])
    assert r.exit_code == 0, r.output
    images = [np.asarray(iio.imread(out / f"fringes_{k:02d}.png")) for k in range(3)]
    assert all(img.shape == (SCREEN[1], SCREEN[0]) and img.dtype == np.uint8 for img in images)
    assert not np.array_equal(images[0], images[1])  # the steps differ: a shot can tell them apart
    return out, images


def show(args, env, **kwargs):
    cmd = [sys.executable, "-m", "dic.cli", "target", "show", *[str(a) for a in args]]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kwargs)


def wait_for(path: Path, seconds: float = 20.0) -> bool:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if path.exists() and path.stat().st_size > 0:
            time.sleep(0.1)  # xwd writes it whole before it exits; the show waits for the command
            return True
        time.sleep(0.05)
    return False


def test_timer_shows_each_image_unscaled_pixel_for_pixel(display, fringes, tmp_path):
    folder, images = fringes
    proc = show([folder, "--interval", "0.3", "--settle", "0.1", "--after-each",
                 f"{TOOLS['xwd']} -root -silent -out {tmp_path}/shot_{{index}}.xwd"], display)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    assert "showed all 3 images" in out
    for k, image in enumerate(images):
        shot = read_xwd(tmp_path / f"shot_{k}.xwd")
        assert shot.shape == (SCREEN[1], SCREEN[0], 3)
        for c in range(3):  # grey on every channel, every pixel of the screen
            assert np.array_equal(shot[..., c], image), (k, c)


def test_keys_step_forward_and_stop(display, fringes, tmp_path):
    folder, images = fringes
    proc = show([folder, "--settle", "0.1", "--after-each", f"{TOOLS['xwd']} -root -silent -out {tmp_path}/shot_{{index}}.xwd"],
                display)
    try:
        assert wait_for(tmp_path / "shot_0.xwd"), "the first image was not shown"
        assert np.array_equal(read_xwd(tmp_path / "shot_0.xwd")[..., 0], images[0])
        time.sleep(1.0)
        assert not (tmp_path / "shot_1.xwd").exists()  # without an interval nothing steps by itself
        subprocess.run([TOOLS["xdotool"], "key", "space"], env=display, check=True)
        assert wait_for(tmp_path / "shot_1.xwd"), "Space did not step"
        assert np.array_equal(read_xwd(tmp_path / "shot_1.xwd")[..., 0], images[1])
        subprocess.run([TOOLS["xdotool"], "key", "Escape"], env=display, check=True)
        out, _ = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, out
    assert "stopped by a key at image 1 of 3" in out
    assert not (tmp_path / "shot_2.xwd").exists()


def test_refusals(display, fringes, tmp_path):
    import imageio.v3 as iio

    folder, _ = fringes
    big = tmp_path / "big"
    big.mkdir()
    iio.imwrite(big / "wide.png", np.zeros((10, SCREEN[0] + 1), np.uint8))
    proc = show([big], display)
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 1 and "larger than the monitor (320x240)" in out and "--screen 320x240" in out
    proc = show([folder, "--screen", "3"], display)
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 1 and "there is no monitor 3" in out
    proc = show([folder, "--interval", "0.1", "--after-each", "false"], display)
    out, _ = proc.communicate(timeout=30)
    assert proc.returncode == 1 and "failed with exit status 1" in out
    r = CliRunner().invoke(main, ["target", "show", str(folder), "--geometry", "320x240"])
    assert r.exit_code == 2 and "WxH+X+Y" in r.output
    r = CliRunner().invoke(main, ["target", "show", str(tmp_path / "none")])
    assert r.exit_code == 1 and "not a folder of target images" in r.output


def test_geometry_places_the_image_unscaled_at_the_monitor_origin(display, tmp_path):
    """A 'monitor' of 200 x 150 px at (50, 40) of the screen: a 100 x 80 random image lands on its top-left
    pixels unscaled, the rest of the monitor black; ``{path}`` names the image shown."""
    import imageio.v3 as iio

    folder = tmp_path / "small"
    folder.mkdir()
    image = np.random.default_rng(3).integers(1, 256, size=(80, 100), dtype=np.uint8)  # no black pixel
    iio.imwrite(folder / "pattern.png", image)
    proc = show([folder, "--geometry", "200x150+50+40", "--interval", "0.2", "--settle", "0.1", "--after-each",
                 f"{TOOLS['xwd']} -root -silent -out {{path}}.xwd"], display)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    shot = read_xwd(folder / "pattern.png.xwd")
    assert np.array_equal(shot[40:120, 50:150, 0], image) and np.array_equal(shot[40:120, 50:150, 2], image)
    assert not shot[40:190, 150:250].any() and not shot[120:190, 50:150].any()  # the monitor beyond the image: black
