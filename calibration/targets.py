"""Calibration targets shown on a monitor (or printed): coded phase-fringe dot grids, dense
absolute-phase fringes, checkerboards and symmetric circle grids.

Target frame (all targets, docs/targets.md): origin at the **centre of screen pixel (0, 0)** (the
top-left pixel), x to the right along the screen rows, y down the columns, z into the screen
(right-handed); millimetres. A screen pixel ``(col, row) = (x_px, y_px)`` sits at
``(x_px * pixel_pitch, y_px * pixel_pitch, 0)`` mm. Screen positions in this module are in
(continuous) screen pixels with the same pixel-centre convention as camera images
(docs/conventions.md).

Phase target (the paper behind Specula: "Stereo-camera calibration for large-scale DIC
measurements with active phase targets and planar mirrors", Optics Express 27(6), 9040, 2019,
doi:10.1364/OE.27.009040, Section 2 and Fig. 3): the screen shows ``N`` phase-shifted images

    I_k(x, y) = B + A sin(Phi(x, y) + 2 pi k / N),   Phi = 2 pi r / period + 2 pi code[j, i] / levels

with ``r`` the distance to the nearest dot centre (the centre of the grid cell (i, j) the point
lies in) and ``period`` the fringe period (default: one period per cell, ``period = pitch``, as in
the paper). The wrapped phase of a code-0 cell jumps at ``r = period / 2``, which draws the paper's
"dots" of diameter ``period``. Beyond the paper, each cell carries a phase offset
``2 pi code / levels`` (``levels = 4``) from a pseudo-random code in which every window of
``code_window`` cells differs from every other placement of the same window on the grid, rotated
or mirrored, in at least two cells: ids are unambiguous under any rotation, in mirrored
(left-handed) views and in partial views that show one such window.

Dense mode: two orthogonal sets of N-step linear fringes ``Phi = 2 pi (s - s_c) / P_l`` (s = x or
y in screen px, ``s_c`` the screen centre) at several periods ``P_l`` from fine to coarse; the
coarsest exceeds the screen extent, so its phase is absolute, and temporal (hierarchical
multi-frequency) unwrapping carries it to the finest period. Every camera pixel that sees the
screen gets its screen coordinate (Schmalz, Forster, Angelopoulou, "Camera calibration: active
versus passive targets", Optical Engineering 50(11), 2011, doi:10.1117/1.3643726).

:func:`render_view` renders what a pinhole camera sees of any target here, evaluating the target's
analytic pattern at the exact screen point of each (supersampled) camera pixel, then Gaussian
blur, noise and quantisation — synthetic images with exact ground truth for tests and planning.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from kernels._atomic import atomic_output
from kernels.checks import positive_float, positive_int

#: the default monitor: a 27-inch 1920 x 1080 panel, 0.311 mm pixels (the paper's; dic.lab.paper uses these)
MONITOR_RESOLUTION_PX = (1920, 1080)
MONITOR_PIXEL_PITCH_MM = 0.311

__all__ = [
    "MONITOR_RESOLUTION_PX", "MONITOR_PIXEL_PITCH_MM",
    "PhaseTarget",
    "CheckerboardTarget",
    "CircleGridTarget",
    "DenseLevel",
    "make_cell_code",
    "render_view",
    "load_target",
    "TARGET_SCHEMA",
    "TARGET_SCHEMA_VERSION",
]

TARGET_SCHEMA = "specula.target"
TARGET_SCHEMA_VERSION = 1

TARGET_FRAME = (
    "origin at the centre of screen pixel (0, 0) (top-left); x right along screen rows, y down, "
    "z into the screen (right-handed); millimetres; screen pixel (x_px, y_px) -> (x_px, y_px, 0) * pixel_pitch"
)


# ------------------------------------------------------------------------------------------------
# validation helpers
# ------------------------------------------------------------------------------------------------
#: the largest screen side accepted, px (twice an 8K monitor's 7680 px): a target image holds screen-sized arrays
MAX_SCREEN_SIDE = 16384
#: the most phase shifts of a fringe target (each one is a screen image to show and capture)
MAX_PHASE_STEPS = 64


def _pair(value, name: str, *, integer: bool, minimum: float, maximum: float | None = None,
          why: str = "") -> tuple:
    if isinstance(value, str):
        parts = value.lower().replace(",", "x").split("x")
        try:
            value = tuple(float(p) for p in parts)
        except ValueError:
            raise ValueError(f"{name} must be two numbers like '1920x1080', got {value!r}") from None
    try:
        a, b = value
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair (x, y), got {value!r}") from None
    out = []
    for v in (a, b):
        if not isinstance(v, (int, float, np.integer, np.floating)) or isinstance(v, bool) or not math.isfinite(v):
            raise ValueError(f"{name} must hold two finite numbers, got {value!r}")
        if integer and float(v) != int(v):
            raise ValueError(f"{name} must hold two integers, got {value!r}")
        if v < minimum:
            raise ValueError(f"{name} values must be >= {minimum}, got {value!r}")
        if maximum is not None and v > maximum:
            raise ValueError(f"{name} values must be at most {maximum}{why}, got {value!r}")
        out.append(int(v) if integer else float(v))
    return tuple(out)


def _screen(value) -> tuple[int, int]:
    """``(width, height)`` of a screen in px, each 1 .. MAX_SCREEN_SIDE."""
    return _pair(value, "screen", integer=True, minimum=1, maximum=MAX_SCREEN_SIDE,
                 why=" px per side (twice an 8K monitor)")


def _grey(value, name: str) -> float:
    if not isinstance(value, (int, float, np.integer, np.floating)) or not math.isfinite(value) or not 0 <= value <= 255:
        raise ValueError(f"{name} must be a grey level in [0, 255], got {value!r}")
    return float(value)


def _screen_xy(x, y):
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"x and y must have the same shape, got {x.shape} and {y.shape}")
    return x, y


# ------------------------------------------------------------------------------------------------
# the cell code
# ------------------------------------------------------------------------------------------------
def _dihedral_views(block: np.ndarray) -> list[np.ndarray]:
    """The 8 rotations/reflections of a 2-D array."""
    out = []
    for b in (block, block.T):
        for k in range(4):
            out.append(np.rot90(b, k))
    return out


def _placement_indices(grid: tuple[int, int], h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat cell indices of every window of shape (h, w) read from an (ny, nx) grid in any of the
    8 orientations: (M, h*w) int, and a bool (M,) marking windows read in the target's own
    orientation."""
    nx, ny = grid
    cells = np.arange(nx * ny).reshape(ny, nx)
    blocks, ident = [], []
    for hh, ww in {(h, w), (w, h)}:
        for j in range(ny - hh + 1):
            for i in range(nx - ww + 1):
                sub = cells[j:j + hh, i:i + ww]
                for t, view in enumerate(_dihedral_views(sub)):
                    if view.shape == (h, w):
                        blocks.append(view.ravel())
                        ident.append((hh, ww) == (h, w) and t == 0)
    return np.array(blocks, dtype=np.int64).reshape(-1, h * w), np.array(ident, dtype=bool)


def _code_conflicts(code: np.ndarray, placements, min_distance: int) -> int:
    """Number of (window, other placement) pairs closer than ``min_distance`` (Hamming)."""
    flat = code.ravel()
    total = 0
    for idx, ident in placements:
        if idx.size == 0:
            continue
        blocks = flat[idx]
        rows = np.flatnonzero(ident)
        d = (blocks[rows][:, None, :] != blocks[None, :, :]).sum(axis=2)
        d[np.arange(rows.size), rows] = 10 ** 6  # a window against its own true placement
        total += int((d < min_distance).sum())
    return total


def _windows_for(grid: tuple[int, int], window: tuple[int, int]) -> list[tuple[int, int]]:
    """Window shapes (h, w) to check for ``window = (a, b)`` cells on a grid (nx, ny)."""
    nx, ny = grid
    a, b = window
    shapes = [(h, w) for h, w in {(a, b), (b, a)} if h <= ny and w <= nx]
    return shapes or [(ny, nx)]  # a grid smaller than the window: the whole grid is the window


def _search_code(grid: tuple[int, int], levels: int, window: tuple[int, int], seed: int, iterations: int):
    nx, ny = grid
    rng = np.random.default_rng(seed)
    placements = [_placement_indices(grid, h, w) for h, w in _windows_for(grid, window)]
    # expected number of near-collisions of a random code; a local search does not repair
    # hundreds of them, so go straight to a larger window
    n_cells = window[0] * window[1]
    p_close = (1 + n_cells * (levels - 1)) / float(levels) ** n_cells
    expected = sum(int(ident.sum()) * len(idx) for idx, ident in placements) * p_close
    if expected > 30:
        return None
    code = rng.integers(0, levels, size=(ny, nx))
    cost = _code_conflicts(code, placements, 2)
    for _ in range(iterations):
        if cost == 0:
            return code
        j, i = rng.integers(0, ny), rng.integers(0, nx)
        old = code[j, i]
        code[j, i] = (old + rng.integers(1, levels)) % levels
        new = _code_conflicts(code, placements, 2)
        if new <= cost:
            cost = new
        else:
            code[j, i] = old
    return code if cost == 0 else None


_CODE_CACHE: dict = {}


def make_cell_code(grid, levels: int = 4, window=None, seed: int = 2019) -> tuple[np.ndarray, tuple[int, int]]:
    """Search a cell code for a dot grid: an (ny, nx) int array of symbols in ``[0, levels)``.

    Every window of ``window = (a, b)`` cells (either orientation) differs from every other
    placement of the same cells on the grid, in any of the 8 rotations/reflections, in at least
    two symbols (one misread symbol is detected, never mistaken). ``window=None`` tries (2, 3),
    (3, 3), (3, 4), (4, 4), (4, 5) and returns the first that a seeded local search solves.
    Returns ``(code, window)``; deterministic for a given ``seed`` (the code is also stored in the
    target's JSON file).
    """
    nx, ny = _pair(grid, "grid", integer=True, minimum=2)
    levels = positive_int(levels, "levels", minimum=2)
    candidates = [tuple(window)] if window is not None else [(2, 3), (3, 3), (3, 4), (4, 4), (4, 5)]
    for win in candidates:
        key = (nx, ny, int(levels), int(win[0]), int(win[1]), int(seed))
        if key not in _CODE_CACHE:
            _CODE_CACHE[key] = _search_code((nx, ny), int(levels), (int(win[0]), int(win[1])), int(seed), 3000)
        code = _CODE_CACHE[key]
        if code is not None:
            return code.copy(), (int(win[0]), int(win[1]))
    raise ValueError(
        f"no {levels}-level code with windows {candidates} found for a {nx}x{ny} grid; "
        "pass code=False (no orientation code) or another window"
    )


# ------------------------------------------------------------------------------------------------
# base class: anything displayed on a screen of known pixel pitch
# ------------------------------------------------------------------------------------------------
class _ScreenTarget:
    screen: tuple[int, int]
    pixel_pitch: float

    @property
    def n_images(self) -> int:  # pragma: no cover - overridden
        raise NotImplementedError

    def intensity(self, x, y, index: int = 0) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError

    def intensities(self, x, y, indices) -> list[np.ndarray]:
        """Emitted grey levels of several images at the same screen points (list of arrays)."""
        return [self.intensity(x, y, k) for k in indices]

    def screen_to_target(self, xy_px) -> np.ndarray:
        """Screen pixels (N, 2) -> target-frame points (N, 3) mm (z = 0)."""
        xy = np.asarray(xy_px, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ValueError(f"xy_px must have shape (N, 2), got {xy.shape}")
        return np.concatenate([xy * self.pixel_pitch, np.zeros((len(xy), 1))], axis=1)

    def target_to_screen(self, points_mm) -> np.ndarray:
        """Target-frame points (N, 3) or (N, 2) mm -> screen pixels (N, 2)."""
        p = np.asarray(points_mm, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] not in (2, 3):
            raise ValueError(f"points_mm must have shape (N, 2) or (N, 3), got {p.shape}")
        return p[:, :2] / self.pixel_pitch

    @property
    def size_mm(self) -> tuple[float, float]:
        """Physical size (width, height) of the screen area in mm."""
        return self.screen[0] * self.pixel_pitch, self.screen[1] * self.pixel_pitch

    def _pixel_grid(self):
        w, h = self.screen
        return np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))

    def save_images(self, directory, prefix: str = "target") -> list[str]:
        """Write the images to display as 8-bit PNGs ``{prefix}_{index:02d}.png``; returns paths."""
        import imageio.v3 as iio

        os.makedirs(directory, exist_ok=True)
        paths = []
        for k, img in enumerate(self.images()):
            path = os.path.join(directory, f"{prefix}_{k:02d}.png")
            with atomic_output(path, mkdir=False) as tmp:
                iio.imwrite(tmp, img)
            paths.append(path)
        return paths

    def save_json(self, path) -> None:
        """Write the target description (parameters, code, object points) as JSON."""
        with atomic_output(path, mkdir=False) as tmp, open(tmp, "w", encoding="utf-8") as fh:
            json.dump(self.to_dict(), fh, indent=1)


# ------------------------------------------------------------------------------------------------
# phase target
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DenseLevel:
    """One set of N phase-shifted linear fringes in the dense sequence.

    ``axis`` 0: fringes vary along screen x (vertical lines), 1: along y. ``period`` in screen px.
    ``first`` is the index of its first image in :meth:`PhaseTarget.dense_images`.
    """

    axis: int
    period: float
    first: int


class PhaseTarget(_ScreenTarget):
    """Coded grid of circular phase-fringe dots on a monitor, plus the dense linear-fringe mode.

    Parameters
    ----------
    screen : (width, height)
        Monitor resolution in pixels (``"1920x1080"`` accepted).
    pixel_pitch : float
        Monitor pixel pitch in mm (0.311 for the paper's 27-inch 1920x1080 monitor).
    grid : (nx, ny)
        Dots along x and y (>= 2 each). Dot ids are ``j * nx + i`` (i along x, j along y, from
        the top-left dot).
    pitch : float
        Dot spacing (cell size) in screen px (x and y).
    steps : int
        Phase steps N >= 3 (shifts ``2 pi k / N``).
    period : float, optional
        Fringe period in screen px; default ``pitch`` (one period per cell, as in the paper). The
        wrapped phase draws dots of diameter ``period``. The paper's Section 3 target (4 x 2 dots of
        300 px diameter at 450 px pitch) is ``grid=(4, 2), pitch=450, period=300``.
    centre : (x, y), optional
        Screen position (px) of the grid centre; default the screen centre.
    guard : float, optional
        The fringes of the outer cells extend this far (screen px) beyond the grid's outer cell
        borders (kept on the screen); the rest of the screen shows the uniform background ``B``.
        A guard band keeps the blurred edge of the fringe area away from the outer dots. Default:
        ``pitch / 2`` clipped to the screen; ``guard=0`` gives the paper's layout.
    code : True, False or (ny, nx) int array
        Orientation/identity code: cell (i, j) gets the phase offset ``2 pi code[j, i] / levels``.
        ``True`` searches one (:func:`make_cell_code`); ``False`` shows the paper's plain target
        (ids then rely on a fully visible grid and a known handedness).
    levels : int
        Number of code symbols (phase offsets), default 4.
    background, amplitude : float
        ``B`` and ``A`` in grey levels (displayed values stay in [0, 255]).
    gamma : float
        Display gamma to pre-compensate in :meth:`images` (1 = none): the 8-bit value sent to the
        monitor is ``255 ((B + A sin) / 255) ** (1 / gamma)``, so that a monitor with this gamma
        emits the sinusoid. :meth:`intensity` always returns the emitted (linear) sinusoid.
    dense_periods : ((P_x ...), (P_y ...)), optional
        Fringe periods (screen px) of the dense mode per axis, fine to coarse. Default: from
        ``dense_fine_period`` up to 1.05 x the screen extent, ratio <= ``dense_max_ratio``.
    """

    def __init__(
        self,
        screen=(1920, 1080),
        pixel_pitch: float = MONITOR_PIXEL_PITCH_MM,
        grid=(6, 3),
        pitch: float = 300,
        steps: int = 4,
        *,
        period: float | None = None,
        centre=None,
        guard: float | None = None,
        code=True,
        levels: int = 4,
        background: float = 127.5,
        amplitude: float = 127.0,
        gamma: float = 1.0,
        dense_periods=None,
        dense_fine_period: float = 40.0,
        dense_max_ratio: float = 5.0,
    ):
        self.screen = _screen(screen)
        self.pixel_pitch = positive_float(pixel_pitch, "pixel_pitch")
        self.grid = _pair(grid, "grid", integer=True, minimum=2)
        self.pitch = positive_float(pitch, "pitch")
        self.steps = positive_int(steps, "steps (number of phase shifts)", minimum=3)
        if self.steps > MAX_PHASE_STEPS:
            raise ValueError(f"steps (number of phase shifts) must be at most {MAX_PHASE_STEPS} (each is an image to show "
                             f"and capture), got {steps!r}")
        self.period = self.pitch if period is None else positive_float(period, "period")
        w, h = self.screen
        self.centre = ((w - 1) / 2.0, (h - 1) / 2.0) if centre is None else _pair(centre, "centre", integer=False, minimum=-np.inf)
        self.background = _grey(background, "background")
        self.amplitude = positive_float(amplitude, "amplitude")
        if self.background - self.amplitude < -1e-9 or self.background + self.amplitude > 255 + 1e-9:
            raise ValueError(
                f"background +- amplitude must stay within [0, 255], got B={self.background}, A={self.amplitude}"
            )
        self.gamma = positive_float(gamma, "gamma")
        nx, ny = self.grid
        half = (np.array(self.grid) - 1) / 2.0
        self._first = np.array(self.centre) - half * self.pitch  # screen px of dot (0, 0)
        lo = self._first - self.pitch / 2
        hi = self._first + (np.array(self.grid) - 1) * self.pitch + self.pitch / 2
        if np.any(lo < -0.5 - 1e-9) or hi[0] > w - 0.5 + 1e-9 or hi[1] > h - 0.5 + 1e-9:
            raise ValueError(
                f"the {nx}x{ny} grid of {self.pitch:g} px cells centred at {self.centre} spans x {lo[0]:.1f}..{hi[0]:.1f}, "
                f"y {lo[1]:.1f}..{hi[1]:.1f} px, outside the {w}x{h} screen; reduce pitch or grid"
            )
        if guard is None:
            room = min(lo[0] + 0.5, lo[1] + 0.5, w - 0.5 - hi[0], h - 0.5 - hi[1])
            guard = max(0.0, min(self.pitch / 2, room))
        elif not isinstance(guard, (int, float, np.integer, np.floating)) or not math.isfinite(guard) or guard < 0:
            raise ValueError(f"guard must be a finite number of screen px >= 0, got {guard!r}")
        self.guard = float(min(guard, self.pitch / 2))
        self._lit_lo = np.maximum(lo - self.guard, -0.5)
        self._lit_hi = np.minimum(hi + self.guard, np.array([w - 0.5, h - 0.5]))
        self.levels = positive_int(levels, "levels", minimum=2)
        if code is True:
            self.code, self.code_window = make_cell_code(self.grid, self.levels)
        elif code is False or code is None:
            self.code, self.code_window = np.zeros((ny, nx), dtype=np.int64), None
        else:
            arr = np.asarray(code)
            if arr.shape != (ny, nx) or not np.issubdtype(arr.dtype, np.integer) or arr.min() < 0 or arr.max() >= self.levels:
                raise ValueError(
                    f"code must be an ({ny}, {nx}) integer array with symbols in [0, {self.levels}), "
                    f"got shape {arr.shape}, dtype {arr.dtype}"
                )
            self.code, self.code_window = arr.astype(np.int64), (2, 3)
        self.dense_levels = self._dense_levels(dense_periods, positive_float(dense_fine_period, "dense_fine_period"),
                                               positive_float(dense_max_ratio, "dense_max_ratio"))

    # -- orientation code -----------------------------------------------------------------------
    @property
    def coded(self) -> bool:
        """True when the target carries an orientation code."""
        return self.code_window is not None

    @property
    def dot_codes(self) -> np.ndarray:
        """(n_dots,) int: code symbol of each dot, in id order."""
        return self.code.ravel().copy()

    @property
    def code_offsets(self) -> np.ndarray:
        """(ny, nx) float64: the phase offset ``2 pi code / levels`` (rad) of each cell."""
        return 2 * np.pi * self.code / self.levels

    # -- geometry -------------------------------------------------------------------------------
    @property
    def n_dots(self) -> int:
        return self.grid[0] * self.grid[1]

    @property
    def ids(self) -> np.ndarray:
        """Dot ids (n_dots,) int: ``j * nx + i``."""
        return np.arange(self.n_dots)

    @property
    def dot_indices(self) -> np.ndarray:
        """(n_dots, 2) int: the (i, j) cell of each id."""
        nx = self.grid[0]
        return np.stack([self.ids % nx, self.ids // nx], axis=1)

    @property
    def dot_centres_px(self) -> np.ndarray:
        """(n_dots, 2) float64: screen pixel position (x, y) of each dot centre, in id order."""
        return self._first + self.dot_indices * self.pitch

    @property
    def object_points(self) -> np.ndarray:
        """(n_dots, 3) float64: dot centres in the target frame (mm, z = 0), in id order."""
        return self.screen_to_target(self.dot_centres_px)

    @property
    def spacing_mm(self) -> float:
        """Dot spacing in mm (``pitch * pixel_pitch``; 450 px x 0.311 = 139.95 mm in the paper)."""
        return self.pitch * self.pixel_pitch

    def cell_of(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Cell indices (i, j) whose dot centre is nearest to screen points (x, y) (clipped)."""
        x, y = _screen_xy(x, y)
        i = np.clip(np.rint((x - self._first[0]) / self.pitch), 0, self.grid[0] - 1).astype(np.int64)
        j = np.clip(np.rint((y - self._first[1]) / self.pitch), 0, self.grid[1] - 1).astype(np.int64)
        return i, j

    def lit(self, x, y) -> np.ndarray:
        """Boolean: the screen point shows fringes (inside the grid plus guard band)."""
        x, y = _screen_xy(x, y)
        return (x >= self._lit_lo[0]) & (x <= self._lit_hi[0]) & (y >= self._lit_lo[1]) & (y <= self._lit_hi[1])

    def phase(self, x, y) -> np.ndarray:
        """Displayed (unwrapped) phase Phi (rad) at screen points (x, y) px; NaN where not lit."""
        x, y = _screen_xy(x, y)
        i, j = self.cell_of(x, y)
        cx = self._first[0] + i * self.pitch
        cy = self._first[1] + j * self.pitch
        r = np.hypot(x - cx, y - cy)
        phi = 2 * np.pi * r / self.period + self.code_offsets[j, i]
        return np.where(self.lit(x, y), phi, np.nan)

    def phase_gradient(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Gradient of the displayed phase (rad per screen px) at screen points (x, y): ``2 pi /
        period`` along the direction from the cell's dot centre (the code is constant per cell)."""
        x, y = _screen_xy(x, y)
        i, j = self.cell_of(x, y)
        dx = x - (self._first[0] + i * self.pitch)
        dy = y - (self._first[1] + j * self.pitch)
        r = np.maximum(np.hypot(dx, dy), 1e-12)
        k = 2 * np.pi / self.period
        return k * dx / r, k * dy / r

    @property
    def phase_shifts(self) -> np.ndarray:
        """(steps,) float64 phase shifts ``2 pi k / N`` (rad) of the dot images."""
        return 2 * np.pi * np.arange(self.steps) / self.steps

    # -- images ---------------------------------------------------------------------------------
    @property
    def n_images(self) -> int:
        return self.steps

    def intensity(self, x, y, index: int = 0) -> np.ndarray:
        """Emitted grey level ``B + A sin(Phi + 2 pi k / N)`` of dot image ``index`` at screen points
        (continuous, unquantised; ``B`` where the screen shows no fringes)."""
        if not 0 <= int(index) < self.steps:
            raise ValueError(f"image index must be in [0, {self.steps}), got {index}")
        phi = self.phase(x, y)
        val = self.background + self.amplitude * np.sin(phi + self.phase_shifts[int(index)])
        return np.where(np.isnan(phi), self.background, val)

    def intensities(self, x, y, indices) -> list[np.ndarray]:
        phi = self.phase(x, y)
        lit = ~np.isnan(phi)
        phi = np.where(lit, phi, 0.0)
        out = []
        for k in indices:
            if not 0 <= int(k) < self.steps:
                raise ValueError(f"image index must be in [0, {self.steps}), got {k}")
            val = self.background + self.amplitude * np.sin(phi + self.phase_shifts[int(k)])
            out.append(np.where(lit, val, self.background))
        return out

    def _to_display(self, emitted: np.ndarray) -> np.ndarray:
        v = np.clip(emitted, 0, 255)
        if self.gamma != 1.0:
            v = 255.0 * (v / 255.0) ** (1.0 / self.gamma)
        return np.clip(np.rint(v), 0, 255).astype(np.uint8)

    def images(self) -> np.ndarray:
        """The N dot images to display, (steps, H, W) uint8 (gamma pre-compensated)."""
        x, y = self._pixel_grid()
        return np.stack([self._to_display(self.intensity(x, y, k)) for k in range(self.steps)])

    # -- dense mode -----------------------------------------------------------------------------
    def _dense_levels(self, periods, fine: float, max_ratio: float) -> list[DenseLevel]:
        if max_ratio <= 1:
            raise ValueError(f"dense_max_ratio must be > 1, got {max_ratio}")
        out: list[DenseLevel] = []
        first = 0
        for axis in (0, 1):
            extent = float(self.screen[axis])
            if periods is None:
                coarse = 1.05 * extent
                if fine >= coarse:
                    seq = [coarse]
                else:
                    n = int(math.ceil(math.log(coarse / fine) / math.log(max_ratio))) + 1
                    ratio = (coarse / fine) ** (1.0 / (n - 1))
                    seq = [fine * ratio ** k for k in range(n)]
            else:
                try:
                    seq = [float(p) for p in periods[axis]]
                except (TypeError, IndexError, ValueError):
                    raise ValueError(f"dense_periods must be ((P_x, ...), (P_y, ...)) in screen px, got {periods!r}") from None
                if not seq or any(not math.isfinite(p) or p <= 0 for p in seq) or any(b <= a for a, b in zip(seq, seq[1:])):
                    raise ValueError(f"dense periods along axis {axis} must be positive and increasing (fine to coarse), got {seq}")
                if seq[-1] <= extent:
                    raise ValueError(
                        f"the coarsest dense period along axis {axis} ({seq[-1]:g} px) must exceed the screen extent "
                        f"({extent:g} px) so that its phase is absolute"
                    )
                ratios = [b / a for a, b in zip(seq, seq[1:])]
                if ratios and max(ratios) > 20:
                    raise ValueError(f"dense period ratios {ratios} are too large for reliable unwrapping (<= 20)")
            for p in seq:
                out.append(DenseLevel(axis, float(p), first))
                first += self.steps
        return out

    @property
    def n_dense_images(self) -> int:
        return len(self.dense_levels) * self.steps

    def dense_phase(self, x, y, level: int) -> np.ndarray:
        """Displayed phase of dense level ``level`` at screen points (rad, unwrapped)."""
        x, y = _screen_xy(x, y)
        lv = self.dense_levels[level]
        s = x if lv.axis == 0 else y
        return 2 * np.pi * (s - self.centre[lv.axis]) / lv.period

    def dense_intensity(self, x, y, index: int) -> np.ndarray:
        """Emitted grey level of dense image ``index`` (level ``index // steps``, step ``index % steps``)."""
        if not 0 <= int(index) < self.n_dense_images:
            raise ValueError(f"dense image index must be in [0, {self.n_dense_images}), got {index}")
        level, k = divmod(int(index), self.steps)
        x, y = _screen_xy(x, y)
        on = (x >= -0.5) & (x <= self.screen[0] - 0.5) & (y >= -0.5) & (y <= self.screen[1] - 0.5)
        val = self.background + self.amplitude * np.sin(self.dense_phase(x, y, level) + self.phase_shifts[k])
        return np.where(on, val, self.background)

    def dense_images(self) -> np.ndarray:
        """All dense-mode images to display, (n_dense_images, H, W) uint8, in :attr:`dense_levels` order."""
        x, y = self._pixel_grid()
        return np.stack([self._to_display(self.dense_intensity(x, y, k)) for k in range(self.n_dense_images)])

    def dense_view(self):
        """A view of this target whose ``intensity``/``n_images`` are the dense sequence (for :func:`render_view`)."""
        return _DenseView(self)

    # -- files ----------------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        return {
            "schema": TARGET_SCHEMA,
            "schema_version": TARGET_SCHEMA_VERSION,
            "type": "phase",
            "target_frame": TARGET_FRAME,
            "units": {"screen": "px", "pixel_pitch": "mm/px", "pitch": "screen px", "period": "screen px",
                      "object_points": "mm", "phase": "rad"},
            "screen": list(self.screen),
            "pixel_pitch": self.pixel_pitch,
            "grid": list(self.grid),
            "pitch": self.pitch,
            "steps": self.steps,
            "period": self.period,
            "centre": list(self.centre),
            "guard": self.guard,
            "levels": self.levels,
            "code": self.code.tolist() if self.coded else None,
            "code_window": list(self.code_window) if self.coded else None,
            "background": self.background,
            "amplitude": self.amplitude,
            "gamma": self.gamma,
            "formula": "I_k = B + A sin(2 pi r / period + 2 pi code[j, i] / levels + 2 pi k / steps), "
                       "r = distance to the dot centre of the cell (i, j) the point lies in",
            "dense_periods": [[lv.period for lv in self.dense_levels if lv.axis == a] for a in (0, 1)],
            "dense_formula": "I = B + A sin(2 pi (s - centre[axis]) / period + 2 pi k / steps), s = x (axis 0) or y (axis 1) in screen px",
            "ids": self.ids.tolist(),
            "object_points": self.object_points.tolist(),
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "PhaseTarget":
        _check_schema(data, "phase")
        code = data.get("code")
        target = cls(
            data["screen"], data["pixel_pitch"], data["grid"], data["pitch"], data["steps"],
            period=data["period"], centre=data["centre"], guard=data["guard"],
            code=False if code is None else np.asarray(code, dtype=np.int64), levels=data["levels"],
            background=data["background"], amplitude=data["amplitude"], gamma=data["gamma"],
            dense_periods=data.get("dense_periods"),
        )
        if code is not None and data.get("code_window"):
            target.code_window = tuple(int(v) for v in data["code_window"])
        return target

    def __repr__(self) -> str:
        return (f"PhaseTarget(screen={self.screen}, pixel_pitch={self.pixel_pitch}, grid={self.grid}, pitch={self.pitch:g}, "
                f"steps={self.steps}, period={self.period:g}, coded={self.coded})")


class _DenseView(_ScreenTarget):
    """Adapter exposing a phase target's dense sequence through the generic image interface."""

    def __init__(self, target: PhaseTarget):
        self.target = target
        self.screen = target.screen
        self.pixel_pitch = target.pixel_pitch

    @property
    def n_images(self) -> int:
        return self.target.n_dense_images

    def intensity(self, x, y, index: int = 0):
        return self.target.dense_intensity(x, y, index)

    def images(self):
        return self.target.dense_images()


# ------------------------------------------------------------------------------------------------
# conventional targets
# ------------------------------------------------------------------------------------------------
def _box_supersample(fn, x, y, n: int = 3) -> np.ndarray:
    """Mean of ``fn`` over an n x n grid of sub-samples of each (unit) screen pixel."""
    acc = np.zeros(np.broadcast(x, y).shape)
    for a in range(n):
        for b in range(n):
            acc += fn(x + (a + 0.5) / n - 0.5, y + (b + 0.5) / n - 0.5)
    return acc / (n * n)


class CheckerboardTarget(_ScreenTarget):
    """Checkerboard with ``corners = (nx, ny)`` inner corners (``nx + 1`` by ``ny + 1`` squares).

    ``square`` is the square size in screen px; with ``pixel_pitch`` the size of one screen px in
    mm. For a printed board use e.g. ``square=40, pixel_pitch=1.0`` (units of 1 mm) and
    ``screen=None`` (the board plus one square of margin). Square (a, b) (a along x, from the
    top-left square) is dark when ``a + b`` is even. Inner corner ``(i, j)`` (id ``j * nx + i``) is
    the corner shared by squares (i, j) and (i + 1, j + 1).
    """

    def __init__(self, screen=MONITOR_RESOLUTION_PX, pixel_pitch: float = MONITOR_PIXEL_PITCH_MM, corners=(9, 6), square: float = 100, *,
                 centre=None, dark: float = 0.0, light: float = 255.0):
        self.corners = _pair(corners, "corners", integer=True, minimum=2)
        self.square = positive_float(square, "square")
        self.pixel_pitch = positive_float(pixel_pitch, "pixel_pitch")
        nsq = np.array(self.corners) + 1
        if screen is None:
            screen = tuple(int(math.ceil(v)) for v in (nsq + 2) * self.square)
        self.screen = _screen(screen)
        w, h = self.screen
        self.centre = ((w - 1) / 2.0, (h - 1) / 2.0) if centre is None else _pair(centre, "centre", integer=False, minimum=-np.inf)
        self.dark, self.light = _grey(dark, "dark"), _grey(light, "light")
        self._origin = np.array(self.centre) - nsq * self.square / 2  # outer corner of square (0, 0)
        end = self._origin + nsq * self.square
        if np.any(self._origin < -0.5 - 1e-9) or end[0] > w - 0.5 + 1e-9 or end[1] > h - 0.5 + 1e-9:
            raise ValueError(f"a {nsq[0]}x{nsq[1]}-square board of {self.square:g} px squares does not fit on the {w}x{h} screen")

    @property
    def n_images(self) -> int:
        return 1

    @property
    def n_points(self) -> int:
        return self.corners[0] * self.corners[1]

    @property
    def points_px(self) -> np.ndarray:
        """(n, 2) screen px of the inner corners, id order ``j * nx + i``."""
        nx, ny = self.corners
        j, i = np.divmod(np.arange(nx * ny), nx)
        return self._origin + (np.stack([i, j], axis=1) + 1) * self.square

    @property
    def object_points(self) -> np.ndarray:
        """(n, 3) mm inner corners in the target frame, id order."""
        return self.screen_to_target(self.points_px)

    def intensity(self, x, y, index: int = 0) -> np.ndarray:
        x, y = _screen_xy(x, y)
        a = np.floor((x - self._origin[0]) / self.square)
        b = np.floor((y - self._origin[1]) / self.square)
        nsq = np.array(self.corners) + 1
        inside = (a >= 0) & (a < nsq[0]) & (b >= 0) & (b < nsq[1])
        dark = ((a + b) % 2 == 0) & inside
        return np.where(dark, self.dark, self.light)

    def images(self) -> np.ndarray:
        x, y = self._pixel_grid()
        return np.rint(_box_supersample(self.intensity, x, y))[None].astype(np.uint8)

    def to_dict(self) -> dict[str, Any]:
        return {"schema": TARGET_SCHEMA, "schema_version": TARGET_SCHEMA_VERSION, "type": "checkerboard",
                "target_frame": TARGET_FRAME, "screen": list(self.screen), "pixel_pitch": self.pixel_pitch,
                "corners": list(self.corners), "square": self.square, "centre": list(self.centre),
                "dark": self.dark, "light": self.light, "square_mm": self.square * self.pixel_pitch,
                "ids": list(range(self.n_points)), "object_points": self.object_points.tolist()}

    @classmethod
    def from_dict(cls, data):
        _check_schema(data, "checkerboard")
        return cls(data["screen"], data["pixel_pitch"], data["corners"], data["square"], centre=data["centre"],
                   dark=data["dark"], light=data["light"])


class CircleGridTarget(_ScreenTarget):
    """Symmetric grid of dark filled circles on a light background (OpenCV's
    ``findCirclesGrid(..., CALIB_CB_SYMMETRIC_GRID)`` target). ``grid = (nx, ny)`` circles,
    ``pitch`` and ``diameter`` in screen px. Id ``j * nx + i``."""

    def __init__(self, screen=MONITOR_RESOLUTION_PX, pixel_pitch: float = MONITOR_PIXEL_PITCH_MM, grid=(6, 3), pitch: float = 300,
                 diameter: float | None = None, *, centre=None, dark: float = 0.0, light: float = 255.0):
        self.grid = _pair(grid, "grid", integer=True, minimum=2)
        self.pitch = positive_float(pitch, "pitch")
        self.diameter = self.pitch / 2 if diameter is None else positive_float(diameter, "diameter")
        if self.diameter >= self.pitch:
            raise ValueError(f"circle diameter ({self.diameter:g} px) must be smaller than the pitch ({self.pitch:g} px)")
        self.pixel_pitch = positive_float(pixel_pitch, "pixel_pitch")
        if screen is None:
            screen = tuple(int(math.ceil(v)) for v in (np.array(self.grid) + 1) * self.pitch)
        self.screen = _screen(screen)
        w, h = self.screen
        self.centre = ((w - 1) / 2.0, (h - 1) / 2.0) if centre is None else _pair(centre, "centre", integer=False, minimum=-np.inf)
        self.dark, self.light = _grey(dark, "dark"), _grey(light, "light")
        self._first = np.array(self.centre) - (np.array(self.grid) - 1) / 2 * self.pitch
        lo = self._first - self.diameter / 2
        hi = self._first + (np.array(self.grid) - 1) * self.pitch + self.diameter / 2
        if np.any(lo < -0.5) or hi[0] > w - 0.5 or hi[1] > h - 0.5:
            raise ValueError(f"the {self.grid[0]}x{self.grid[1]} circle grid does not fit on the {w}x{h} screen")

    @property
    def n_images(self) -> int:
        return 1

    @property
    def n_points(self) -> int:
        return self.grid[0] * self.grid[1]

    @property
    def points_px(self) -> np.ndarray:
        nx, ny = self.grid
        j, i = np.divmod(np.arange(nx * ny), nx)
        return self._first + np.stack([i, j], axis=1) * self.pitch

    @property
    def object_points(self) -> np.ndarray:
        return self.screen_to_target(self.points_px)

    def intensity(self, x, y, index: int = 0) -> np.ndarray:
        x, y = _screen_xy(x, y)
        i = np.clip(np.rint((x - self._first[0]) / self.pitch), 0, self.grid[0] - 1)
        j = np.clip(np.rint((y - self._first[1]) / self.pitch), 0, self.grid[1] - 1)
        r = np.hypot(x - self._first[0] - i * self.pitch, y - self._first[1] - j * self.pitch)
        return np.where(r <= self.diameter / 2, self.dark, self.light)

    def images(self) -> np.ndarray:
        x, y = self._pixel_grid()
        return np.rint(_box_supersample(self.intensity, x, y))[None].astype(np.uint8)

    def to_dict(self) -> dict[str, Any]:
        return {"schema": TARGET_SCHEMA, "schema_version": TARGET_SCHEMA_VERSION, "type": "circles",
                "target_frame": TARGET_FRAME, "screen": list(self.screen), "pixel_pitch": self.pixel_pitch,
                "grid": list(self.grid), "pitch": self.pitch, "diameter": self.diameter, "centre": list(self.centre),
                "dark": self.dark, "light": self.light, "ids": list(range(self.n_points)),
                "object_points": self.object_points.tolist()}

    @classmethod
    def from_dict(cls, data):
        _check_schema(data, "circles")
        return cls(data["screen"], data["pixel_pitch"], data["grid"], data["pitch"], data["diameter"],
                   centre=data["centre"], dark=data["dark"], light=data["light"])


def _check_schema(data: dict, kind: str) -> None:
    if not isinstance(data, dict) or data.get("schema") != TARGET_SCHEMA:
        raise ValueError(f"not a Specula target file (expected schema {TARGET_SCHEMA!r}, got {data.get('schema') if isinstance(data, dict) else type(data)})")
    if data.get("schema_version") != TARGET_SCHEMA_VERSION:
        raise ValueError(f"target file schema_version {data.get('schema_version')} is not supported (expected {TARGET_SCHEMA_VERSION})")
    if data.get("type") != kind:
        raise ValueError(f"expected a {kind!r} target, the file describes a {data.get('type')!r} target")


def load_target(path):
    """Read a target JSON written by ``save_json`` / ``specula target`` and rebuild the target."""
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, ValueError) as exc:  # json.JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise ValueError(f"cannot read target file {path}: {exc}") from None
    except RecursionError:
        raise ValueError(f"cannot read target file {path}: JSON nested too deeply") from None
    kinds = {"phase": PhaseTarget, "checkerboard": CheckerboardTarget, "circles": CircleGridTarget}
    kind = data.get("type") if isinstance(data, dict) else None
    if not isinstance(kind, str) or kind not in kinds:
        raise ValueError(f"target file {path} has unknown type {kind!r}; expected one of {sorted(kinds)}")
    try:
        target = kinds[kind].from_dict(data)
        with np.errstate(over="ignore", invalid="ignore"):
            finite = bool(np.all(np.isfinite(target.object_points)))
        if not finite:
            raise ValueError("its sizes overflow (the target's points in mm are not finite)")
        return target
    except KeyError as exc:
        raise ValueError(f"target file {path} lacks the key {exc}") from None
    except (ValueError, TypeError, IndexError, OverflowError) as exc:
        raise ValueError(f"target file {path}: {exc}") from None


# ------------------------------------------------------------------------------------------------
# synthetic camera views
# ------------------------------------------------------------------------------------------------
def _gaussian_blur(image: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(image, sigma, mode="nearest", truncate=4.0)


def screen_points_of_pixels(camera, R_cam_target, t_cam_target, pixel_pitch: float, uv) -> np.ndarray:
    """Screen position (px) seen by camera pixels ``uv`` (N, 2): NaN where the ray misses the
    target plane (parallel or behind the camera). ``R_cam_target`` may be improper (det -1) for a
    mirrored (virtual) target."""
    R = np.asarray(R_cam_target, dtype=np.float64)
    t = np.asarray(t_cam_target, dtype=np.float64).reshape(3)
    xy = camera.pixels_to_normalized(uv)
    if np.any(camera.dist):
        xy = camera.undistort_normalized(xy)
    xn, yn = xy[:, 0], xy[:, 1]
    n = R[:, 2]
    denom = n[0] * xn + n[1] * yn + n[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = float(n @ t) / denom
    dx, dy, dz = lam * xn - t[0], lam * yn - t[1], lam - t[2]
    out = np.empty((len(xn), 2))
    out[:, 0] = (R[0, 0] * dx + R[1, 0] * dy + R[2, 0] * dz) / pixel_pitch
    out[:, 1] = (R[0, 1] * dx + R[1, 1] * dy + R[2, 1] * dz) / pixel_pitch
    out[~(lam > 0)] = np.nan
    return out


def render_view(
    target,
    camera,
    R_cam_target,
    t_cam_target,
    *,
    indices=None,
    supersample: int = 3,
    blur_sigma: float = 0.0,
    noise_sigma: float = 0.0,
    gain: float = 0.8,
    black_level: float = 10.0,
    bits: int | None = 8,
    seed: int = 0,
) -> np.ndarray:
    """Render the images a pinhole camera records of a target (exact ground truth, no interpolation).

    Each camera pixel is split into ``supersample**2`` sub-pixel rays (box-filtered pixel area);
    each ray is undistorted through ``camera`` (a :class:`calibration.camera.Camera`), intersected
    with the target plane (pose ``x_cam = R_cam_target @ X + t_cam_target``, mm; ``R`` may be
    improper for a mirrored view) and the target's analytic emitted intensity is evaluated at the
    exact screen point. Off-screen and missed rays see black. Then ``grey = black_level + gain *
    emitted``, a Gaussian blur of ``blur_sigma`` px (a defocus stand-in), Gaussian noise of
    ``noise_sigma`` grey levels, and rounding/clipping to ``bits`` (None: float output).

    Returns (n, H, W) float64 (``bits=None``) or uint8/uint16, for the target images ``indices``
    (default all ``target.n_images``). Ground-truth image points: ``camera.project(
    (R @ target.object_points.T).T + t)``.
    """
    if not hasattr(target, "intensity") or not hasattr(target, "n_images"):
        raise ValueError(f"target must be a Specula target (PhaseTarget, CheckerboardTarget, ...), got {type(target).__name__}")
    w, h = camera.size
    if w <= 0 or h <= 0:
        raise ValueError(f"camera.size must be positive (width, height), got {camera.size}")
    if not isinstance(supersample, (int, np.integer)) or supersample < 1:
        raise ValueError(f"supersample must be an integer >= 1, got {supersample!r}")
    for name, v in (("blur_sigma", blur_sigma), ("noise_sigma", noise_sigma)):
        if not math.isfinite(v) or v < 0:
            raise ValueError(f"{name} must be a finite number >= 0, got {v!r}")
    if bits not in (None, 8, 16):
        raise ValueError(f"bits must be 8, 16 or None, got {bits!r}")
    R = np.asarray(R_cam_target, dtype=np.float64)
    if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-9):
        raise ValueError("R_cam_target must be an orthogonal 3x3 matrix (proper, or improper for a mirrored view)")
    indices = list(range(target.n_images)) if indices is None else list(indices)
    n = supersample
    # render a margin around the sensor so that the blur near the image edge sees the scene
    # beyond it, as a real lens does
    pad = int(math.ceil(4 * blur_sigma)) if blur_sigma > 0 else 0
    ys, xs = np.mgrid[-pad:h + pad, -pad:w + pad].astype(np.float64)
    hp, wp = h + 2 * pad, w + 2 * pad
    acc = np.zeros((len(indices), hp, wp))
    sw, sh = target.screen
    for a in range(n):
        for b in range(n):
            uv = np.stack([xs.ravel() + (a + 0.5) / n - 0.5, ys.ravel() + (b + 0.5) / n - 0.5], axis=1)
            sp = screen_points_of_pixels(camera, R, t_cam_target, target.pixel_pitch, uv)
            sx, sy = sp[:, 0], sp[:, 1]
            on = np.isfinite(sx) & (sx >= -0.5) & (sx <= sw - 0.5) & (sy >= -0.5) & (sy <= sh - 0.5)
            sx = np.where(on, sx, 0.0)
            sy = np.where(on, sy, 0.0)
            for m, val in enumerate(target.intensities(sx, sy, indices)):
                acc[m] += np.where(on, val, 0.0).reshape(hp, wp)
    acc /= n * n
    rng = np.random.default_rng(seed)
    out = []
    for img in acc:
        img = black_level + gain * img
        if blur_sigma > 0:
            img = _gaussian_blur(img, blur_sigma)[pad:pad + h, pad:pad + w]
        if noise_sigma > 0:
            img = img + rng.normal(0.0, noise_sigma, img.shape)
        out.append(img)
    out = np.stack(out)
    if bits is None:
        return out
    top = 2 ** bits - 1
    return np.clip(np.rint(out), 0, top).astype(np.uint8 if bits == 8 else np.uint16)
