"""Showing a target's images on a monitor, full screen and unscaled (``specula target show``).

:func:`show_images` opens one borderless window over a whole monitor (Tk, imported on first use) and
shows the images one after the other, each **unscaled**: image pixel (i, j) is monitor pixel (i, j)
(the target frame of docs/targets.md puts its origin at the centre of screen pixel (0, 0)), on black;
an image larger than the monitor is refused (showing part of it would change the target). It steps

* on a key press: Space, Return, Right or Page Down show the next image, Left, BackSpace or Page Up
  the previous one, Escape or q stop;
* or on a timer (``interval`` seconds per image; keys still work);

and after each image is on the screen (``settle`` seconds after it was drawn) it can run a command,
e.g. a camera trigger, with ``{index}`` (0-based) and ``{path}`` replaced; the next step waits for it,
and a command that fails stops the show (a missed capture must not go unnoticed).

The monitor: ``geometry`` ``(width, height, x, y)`` in px of the X screen, or ``screen`` K, the K-th
monitor of ``xrandr --listmonitors`` (X11; without xrandr, monitor 0 is the whole screen).
"""
from __future__ import annotations

import os
import re
import shlex
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["show_images", "list_monitors", "target_images", "ShowResult", "NEXT_KEYS", "PREVIOUS_KEYS", "STOP_KEYS"]

#: Tk key names that show the next image, the previous one, and that stop the show
NEXT_KEYS = ("space", "Return", "Right", "Next")
PREVIOUS_KEYS = ("Left", "BackSpace", "Prior")
STOP_KEYS = ("Escape", "q")

_MONITOR = re.compile(r"^\s*(\d+):\s+\S+\s+(\d+)/\d+x(\d+)/\d+\+(-?\d+)\+(-?\d+)")


@dataclass
class ShowResult:
    """What a show did: ``shown`` the image indices in the order they were shown, ``completed`` True
    when it went past the last image (False: stopped by a key or a failed command), ``reason`` in words."""

    shown: list[int]
    completed: bool
    reason: str


def list_monitors() -> list[tuple[int, int, int, int]]:
    """The monitors of the X display as ``(width, height, x, y)`` px, from ``xrandr --listmonitors``;
    an empty list when xrandr is not there or lists none."""
    try:
        out = subprocess.run(["xrandr", "--listmonitors"], capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    found = {}
    for line in out.splitlines():
        m = _MONITOR.match(line)
        if m:
            k, w, h, x, y = (int(v) for v in m.groups())
            found[k] = (w, h, x, y)
    return [found[k] for k in sorted(found)]


def target_images(folder) -> list[Path]:
    """The images of a target folder in the order to show them: every image file (``kernels.images``
    suffixes) in natural order (``fringes_00.png`` before ``fringes_10.png``)."""
    from kernels.images import IMAGE_SUFFIXES, natural_key

    p = Path(os.fspath(folder))
    if not p.is_dir():
        raise ValueError(f"{p} is not a folder of target images")
    images = sorted((f for f in p.iterdir() if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES),
                    key=lambda f: natural_key(f.name))
    if not images:
        raise ValueError(f"{p} holds no image ({', '.join(sorted(IMAGE_SUFFIXES))}); write one with 'specula target'")
    return images


def _as_rgb8(image, path) -> np.ndarray:
    img = np.asarray(image)
    if img.dtype != np.uint8:
        raise ValueError(f"{path}: {img.dtype} pixels; a target to show must be 8-bit (uint8), as 'specula target' "
                         "writes it")
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    elif img.ndim == 3 and img.shape[2] in (3, 4):
        img = img[:, :, :3]
    else:
        raise ValueError(f"{path}: an image of shape {img.shape} is neither grey nor RGB")
    return np.ascontiguousarray(img)


def _ppm(rgb: np.ndarray) -> bytes:
    h, w = rgb.shape[:2]
    return f"P6 {w} {h} 255\n".encode("ascii") + rgb.tobytes()


def _check_geometry(geometry) -> tuple[int, int, int, int]:
    try:
        w, h, x, y = (int(v) for v in geometry)
    except (TypeError, ValueError):
        raise ValueError(f"geometry must be (width, height, x, y) px, got {geometry!r}") from None
    if w < 1 or h < 1:
        raise ValueError(f"geometry width and height must be at least 1 px, got {geometry!r}")
    return w, h, x, y


def show_images(paths, *, screen: int = 0, geometry=None, interval: float | None = None, after_each: str | None = None,
                settle: float = 0.2, loop: bool = False, on_step=None) -> ShowResult:
    """Show ``paths`` (image files, in order) full screen and unscaled (module docstring).

    Parameters
    ----------
    paths : sequence of image paths (8-bit grey or RGB, each at most the monitor's size)
    screen : int
        The monitor, an index into :func:`list_monitors` (0 without xrandr: the whole X screen).
    geometry : (width, height, x, y), optional
        The monitor's area in px of the X screen; replaces ``screen``.
    interval : float, optional
        Seconds per image (> 0); None: step on key presses only.
    after_each : str, optional
        A command run after each image is on the screen, ``{index}`` and ``{path}`` replaced (split like a
        shell line, run without a shell).
    settle : float
        Seconds between drawing an image and running ``after_each`` (the monitor's response), >= 0.
    loop : bool
        Start again after the last image (stop with Escape or q).
    on_step : callable(index, path), optional
        Called after each image is on the screen (before ``after_each``).
    """
    from kernels.images import read_image

    files = [Path(os.fspath(p)) for p in paths]
    if not files:
        raise ValueError("no image to show")
    if interval is not None and not (isinstance(interval, (int, float)) and np.isfinite(interval) and interval > 0):
        raise ValueError(f"interval must be a positive number of seconds, got {interval!r}")
    if not (isinstance(settle, (int, float)) and np.isfinite(settle) and settle >= 0):
        raise ValueError(f"settle must be a number of seconds >= 0, got {settle!r}")
    if after_each is not None:
        try:
            template = shlex.split(str(after_each))
        except ValueError as exc:
            raise ValueError(f"after_each is not a command line ({exc}): {after_each!r}") from None
        if not template:
            raise ValueError("after_each is empty; give a command or leave it out")
    images = [_as_rgb8(read_image(f), f) for f in files]
    if geometry is None and (isinstance(screen, bool) or not isinstance(screen, (int, np.integer)) or screen < 0):
        raise ValueError(f"screen must be a monitor index >= 0, got {screen!r}")

    try:
        import tkinter as tk
    except ImportError as exc:  # a Python built without Tk
        raise ValueError(f"showing targets needs Tk (tkinter), which this Python lacks: {exc}") from None
    if os.name != "nt" and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        raise ValueError("no display: DISPLAY is not set (run on the desktop whose monitor shows the target)")
    try:
        root = tk.Tk()
    except tk.TclError as exc:
        raise ValueError(f"cannot open the display: {exc}") from None
    try:
        if geometry is not None:
            area = _check_geometry(geometry)
        else:
            monitors = list_monitors() or [(root.winfo_screenwidth(), root.winfo_screenheight(), 0, 0)]
            if screen >= len(monitors):
                raise ValueError(f"there is no monitor {screen}: {len(monitors)} found "
                                 f"({', '.join(f'{k}: {w}x{h}+{x}+{y}' for k, (w, h, x, y) in enumerate(monitors))}); "
                                 "give --screen K or --geometry WxH+X+Y")
            area = monitors[screen]
        w, h, x, y = area
        for f, img in zip(files, images):
            if img.shape[0] > h or img.shape[1] > w:
                raise ValueError(f"{f} is {img.shape[1]}x{img.shape[0]} px, larger than the monitor ({w}x{h}); shown "
                                 "unscaled it would be cut: write the target for this monitor (specula target ... "
                                 f"--screen {w}x{h})")
        return _run(tk, root, files, images, area, interval, after_each, settle, loop, on_step)
    finally:
        try:
            root.destroy()
        except tk.TclError:
            pass


def _run(tk, root, files, images, area, interval, after_each, settle, loop, on_step) -> ShowResult:
    w, h, x, y = area
    root.overrideredirect(True)  # no border, no title bar: the window is the monitor's pixels
    root.geometry(f"{w}x{h}+{x}+{y}")
    root.configure(background="black", cursor="none")
    photos = [tk.PhotoImage(data=_ppm(img), format="PPM") for img in images]
    label = tk.Label(root, borderwidth=0, highlightthickness=0, padx=0, pady=0, background="black")
    label.place(x=0, y=0)  # image pixel (0, 0) on monitor pixel (0, 0)
    state = {"pos": -1, "shown": [], "done": False, "completed": False, "reason": "", "timer": None, "busy": False}

    def finish(completed: bool, reason: str):
        state.update(done=True, completed=completed, reason=reason)
        root.quit()

    def show(pos: int):
        if state["timer"] is not None:
            root.after_cancel(state["timer"])
            state["timer"] = None
        if pos >= len(files):
            if not loop:
                finish(True, f"showed all {len(files)} images")
                return
            pos = 0
        pos = max(pos, 0)
        state["pos"] = pos
        label.configure(image=photos[pos], width=images[pos].shape[1], height=images[pos].shape[0])
        root.update_idletasks()
        root.update()
        state["shown"].append(pos)
        state["busy"] = True
        if settle:
            time.sleep(settle)
        try:
            if on_step is not None:
                on_step(pos, files[pos])
            if after_each is not None:
                cmd = [part.replace("{index}", str(pos)).replace("{path}", str(files[pos]))
                       for part in shlex.split(after_each)]
                try:
                    done = subprocess.run(cmd)
                except OSError as exc:
                    finish(False, f"the command after image {pos} did not start: {exc}")
                    return
                if done.returncode != 0:
                    finish(False, f"the command after image {pos} ({' '.join(cmd)}) failed with exit status "
                                  f"{done.returncode}")
                    return
        finally:
            state["busy"] = False
        if interval is not None and not state["done"]:
            state["timer"] = root.after(int(round(interval * 1000)), lambda: show(state["pos"] + 1))

    def on_key(event):
        if state["done"] or state["busy"]:
            return
        if event.keysym in STOP_KEYS:
            finish(False, f"stopped by a key at image {state['pos']} of {len(files)}")
        elif event.keysym in NEXT_KEYS:
            show(state["pos"] + 1)
        elif event.keysym in PREVIOUS_KEYS:
            show(max(state["pos"] - 1, 0))

    def tick():  # Python runs now and then, so that Ctrl-C in the terminal stops the show
        if not state["done"]:
            root.after(200, tick)

    root.bind("<Key>", on_key)
    root.after(0, lambda: (root.focus_force(), show(0)))
    root.after(200, tick)
    root.mainloop()
    return ShowResult(shown=list(state["shown"]), completed=bool(state["completed"]), reason=str(state["reason"]))
