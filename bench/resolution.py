"""Spatial resolution on the DIC Challenge 2.0 star: transfer function, l10, noise floor and MEI.

Run from the repository root::

    .venv/bin/python -m bench.resolution                       # the full star, ~ a few minutes on 2 cores
    .venv/bin/python -m bench.resolution --subsets 15 21 --orders 2 --windows 5
    .venv/bin/python -m bench.resolution --width 700 --period-max 60   # a reduced star (quick look)

**The images.** The displacement law of the challenge's star images as DICe's regression suite uses
them (``tests/regression/bitmap_star`` of github.com/dicengine/dice, 2000 px wide, 8-bit):

    u = 0,   v = A cos(2 pi (Y - yc) / p(X)),   p(X) = p_min + (p_max - p_min) (X + 1) / W

with ``A = 0.5`` px, ``yc = 250``, ``p_min = 10``, ``p_max = 150`` px, ``W = 2000`` px, image
``501 x 2000`` px (rows x columns): a vertical sinusoid whose period grows from 10 to 150 px across
the image. It is rendered with :func:`dic.synth.speckle_pair` (Boolean-model speckle evaluated at the
mapped material points, so the displacement is exact at every point; radius 2 px, density 0.5,
blur 0.7 px, 8 bits) with independent Gaussian noise ``--noise`` grey levels in both images, and a
**noise-only pair** of the same pattern at the same noise (no displacement; the same reference image,
so one :class:`dic.Tracker` serves both pairs).

**The points.** Only what the figures need is tracked: POIs on a lattice of step ``--step`` px (both
axes, through ``(x, yc)``) in the band ``|Y - yc| <= p(X)/4 + h`` of each column, which holds the
centre row (the peak of ``v``), the two rows of the peak of ``eyy`` (``Y = yc -+ p/4``) and ``h`` px
beyond them so that every strain window there is full (``h = (max window // 2 + 1) * step``).

**Transfer function** (Reu et al., "DIC Challenge 2.0: Developing Images and Guidelines for
Evaluating Accuracy and Resolution of 2D Analyses", Exp. Mech. 62 (2022) 639-654,
doi:10.1007/s11340-021-00806-6: the amplitude along the line of the peak, against the true
amplitude): at each POI of the peak rows, the measured value divided by the exact one at that point,

- displacement: ``v(X, yc) / A`` on the centre row (``v = A`` exactly there, whatever the period);
- strain: ``eyy(X, Y*) / eyy_true(X, Y*)`` on the lattice row ``Y*`` nearest to each of ``yc -+ p(X)/4``
  (``eyy = dv/dY = -+ 2 pi A / p`` there: the strain amplitude), ``eyy`` from :func:`dic.strain` with
  window ``w`` grid points, only where the window is full;

then averaged along the row over one local period (the POIs with ``|X - X0| <= p(X0)/2``), which
leaves the transfer unchanged (the true amplitude does not depend on ``X``) and averages down the
noise and the pattern-induced bias. ``l10`` is the first period from which the averaged ratio
stays within 10 % of 1 up to the longest period (``|ratio - 1| < 0.1`` for every longer period: the
challenge's "10 % bias"; a ratio above 1.1 counts as a miss too). Unreached (the ratio within 10 %
down to the shortest tracked period) is reported as that period with ``l10_censored`` True; never
reached (the ratio off by 10 % at the longest period) as None.

A second estimate fits the amplitude by least squares over every POI of the band
(``sum(m t) / sum(t²)`` over one local period, ``t`` the exact value): ``l10_band_px``.

**Noise floor** ``n``: the standard deviation of ``v`` (and of ``eyy``, full windows only) over the
valid POIs of the noise-only pair. **MEI** = ``n_v * l10_v`` (px²) for the displacement and
``n_eyy * l10_eyy²`` (px²) for the strain (Reu et al. 2022; lower is better).

Beside the measurements: :func:`subset_filter_model` (a subset's least-squares shape function as a
linear filter: l10 and noise gain for square and Gaussian-weighted subsets) and :data:`DICE_GOLD`
(a hand-read spot check of DICe's own output on the star in its regression suite).

Writes bench/results/resolution.json (``--out``). See docs/dic2d.md, "Spatial resolution: the DIC
Challenge 2.0 star", for the table and what it says.
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from dataclasses import asdict, dataclass
from datetime import datetime, timezone

import numpy as np

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")

#: the challenge's "10 % bias": l10 is where the amplitude ratio leaves [0.9, 1.1]
TOLERANCE = 0.1


@dataclass(frozen=True)
class Star:
    """The star's law and image: ``v = amplitude cos(2 pi (Y - centre_row) / period(X))``, ``u = 0``.

    ``period(X) = period_min + (period_max - period_min) (X + 1) / width`` px. Defaults: the DIC
    Challenge 2.0 star as DICe's regression suite uses it (2000 x 501 px, 10 -> 150 px, 0.5 px).
    """

    width: int = 2000
    height: int = 501
    centre_row: float = 250.0
    amplitude: float = 0.5
    period_min: float = 10.0
    period_max: float = 150.0
    noise_sigma: float = 2.0
    seed: int = 2022

    def period(self, x):
        """Local period p(X) (px) at reference abscissa ``x`` (px), array-like."""
        return self.period_min + (self.period_max - self.period_min) * (np.asarray(x, dtype=np.float64) + 1.0) / self.width

    def displacement(self, x, y):
        """``(u, v)`` (px) at reference points ``(x, y)`` (NumPy arrays of one shape)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        v = self.amplitude * np.cos(2 * np.pi * (y - self.centre_row) / self.period(x))
        return np.zeros_like(v), v

    def eyy(self, x, y):
        """Exact ``dv/dY`` at reference points ``(x, y)``."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        p = self.period(x)
        return -self.amplitude * 2 * np.pi / p * np.sin(2 * np.pi * (y - self.centre_row) / p)


def render(star: Star, device=None):
    """``(reference, current, second)`` float32 (height, width) 8-bit grey levels: the star pair and the
    noise-only partner of the same reference (same pattern, independent noise, no displacement)."""
    from dic.synth import speckle_pair

    shape = (star.height, star.width)
    ref, cur = speckle_pair(shape, star.displacement, noise_sigma=star.noise_sigma, seed=star.seed, device=device)
    ref0, second = speckle_pair(shape, None, noise_sigma=star.noise_sigma, seed=star.seed, device=device)
    if not np.array_equal(ref, ref0):  # the same seed gives the same reference image and noise: checked
        raise RuntimeError("the star's and the noise pair's reference images differ; dic.synth's seeding changed")
    return ref, cur, second


def star_points(star: Star, subset: int, step: int, band: float) -> np.ndarray:
    """(N, 2) POIs (x, y) px on the lattice of ``step`` through ``(x0, centre_row)``: in each column the
    rows with ``|y - centre_row| <= period(x)/4 + band``, subsets inside the image (1 px spare for
    the 0.5 px motion)."""
    half = subset // 2 + 1
    xs = np.arange(half, star.width - half, step, dtype=np.float64)
    reach = star.period(xs) / 4 + band
    j_lo = -int((star.centre_row - half) // step)
    j_hi = int((star.height - 1 - half - star.centre_row) // step)
    ys = star.centre_row + step * np.arange(j_lo, j_hi + 1, dtype=np.float64)
    X, Y = np.meshgrid(xs, ys)
    keep = np.abs(Y - star.centre_row) <= reach[None, :]
    return np.column_stack([X[keep], Y[keep]])


def amplitude_ratio(x, measured, truth, star: Star):
    """Least-squares amplitude ratio ``sum(m t) / sum(t^2)`` of ``measured`` to ``truth`` over the points with
    ``|x - x0| <= period(x0)/2``, at each distinct ``x0`` of ``x`` (NaNs in ``measured`` skipped).

    Returns ``(x0 ascending, ratio)``. On one peak row (``truth`` constant) it is the mean of
    ``measured / truth`` over one local period along the row."""
    x = np.asarray(x, dtype=np.float64)
    m = np.asarray(measured, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    ok = np.isfinite(m) & np.isfinite(t)
    columns, inverse = np.unique(x, return_inverse=True)
    num = np.bincount(inverse, weights=np.where(ok, m * t, 0.0), minlength=columns.size)
    den = np.bincount(inverse, weights=np.where(ok, t * t, 0.0), minlength=columns.size)
    cnum = np.concatenate([[0.0], np.cumsum(num)])
    cden = np.concatenate([[0.0], np.cumsum(den)])
    half = star.period(columns) / 2
    lo = np.searchsorted(columns, columns - half, side="left")
    hi = np.searchsorted(columns, columns + half, side="right")
    d = cden[hi] - cden[lo]
    with np.errstate(invalid="ignore", divide="ignore"):
        return columns, np.where(d > 0, (cnum[hi] - cnum[lo]) / d, np.nan)


def l10(periods, ratio, tolerance: float = TOLERANCE):
    """``(l10, censored)``: the first period from which ``ratio`` stays within ``tolerance`` of 1 up to
    the longest period. ``periods`` ascending. ``(shortest period, True)`` when it never leaves the
    band; ``(None, False)`` when it is out of the band at the longest period (or all NaN)."""
    periods = np.asarray(periods, dtype=np.float64)
    ratio = np.asarray(ratio, dtype=np.float64)
    ok = np.isfinite(ratio)
    periods, ratio = periods[ok], ratio[ok]
    if periods.size == 0:
        return None, False
    bad = np.flatnonzero(np.abs(ratio - 1.0) >= tolerance)
    if bad.size == 0:
        return float(periods[0]), True
    last = int(bad[-1])
    if last == periods.size - 1:
        return None, False
    return float(periods[last + 1]), False


#: spacing (px) of the period grid on which the JSON gives each transfer curve
CURVE_SPACING = 2.0


def curve_grid(star: Star) -> np.ndarray:
    """The periods (px) at which the JSON gives the transfer curves: ``period_min`` to ``period_max`` by 2 px."""
    return np.arange(star.period_min, star.period_max + 1e-9, CURVE_SPACING)


def _curve_on_grid(periods, ratio, grid) -> dict:
    """The curve interpolated to ``grid`` (the raw curve has one value per POI column); None outside the
    tracked periods."""
    ok = np.isfinite(ratio)
    inside = (grid >= periods[ok].min()) & (grid <= periods[ok].max()) if np.count_nonzero(ok) > 1 else grid < -1
    vals = np.interp(grid, periods[ok], ratio[ok]) if np.count_nonzero(ok) > 1 else np.zeros(grid.shape)
    return {"period_px": [float(p) for p in grid],
            "ratio": [round(float(r), 4) if i else None for r, i in zip(vals, inside)]}


def _transfer(star: Star, x, measured, truth) -> dict:
    columns, ratio = amplitude_ratio(x, measured, truth, star)
    p = star.period(columns)
    level, censored = l10(p, ratio)
    level = None if level is None else round(level, 2)
    return {"x": columns, "period": p, "ratio": ratio, "l10": level, "l10_censored": censored}


def displacement_transfer(star: Star, field) -> dict:
    """Amplitude ratio of ``v`` of ``field`` (a Field2D of the star pair): on the centre row (the
    challenge's line, ``"peak"``) and fitted over the whole band of POIs (``"band"``), each over one
    local period along x; plus ``l10`` of the unaveraged centre-row ratio (``"l10_unaveraged"``)."""
    x, y = field.points[:, 0], field.points[:, 1]
    v = np.where(field.valid, field.v, np.nan)
    truth = star.displacement(x, y)[1]
    on_row = np.abs(y - star.centre_row) < 1e-9
    peak = _transfer(star, x[on_row], v[on_row], truth[on_row])
    band = _transfer(star, x, v, truth)
    order = np.argsort(x[on_row])
    raw = (v[on_row] / truth[on_row])[order]
    level, _ = l10(star.period(x[on_row][order]), raw)
    peak["l10_unaveraged"] = None if level is None else round(level, 2)
    peak["valid_fraction"] = float(np.mean(np.isfinite(raw)))
    return {"peak": peak, "band": band}


def strain_peak_rows(star: Star, points: np.ndarray, step: int) -> np.ndarray:
    """Indices of the POIs on the lattice rows nearest to ``centre_row -+ period(x)/4`` (the peaks of eyy)."""
    x, y = points[:, 0], points[:, 1]
    out = []
    for sign in (-1.0, 1.0):
        target = star.centre_row + sign * star.period(x) / 4
        nearest = star.centre_row + np.round((target - star.centre_row) / step) * step
        out.append(np.flatnonzero(np.abs(y - nearest) < 1e-9))
    return np.concatenate(out)


def strain_transfer(star: Star, field, sfield, step: int) -> dict:
    """Amplitude ratio of ``eyy`` (``sfield``: dic.strain of the star field), full windows only: at its two
    peak rows (``"peak"``) and fitted over the band (``"band"``), each over one local period along x."""
    x, y = field.points[:, 0], field.points[:, 1]
    full = sfield.valid & (sfield.n_fit == sfield.window ** 2)
    e = np.where(full, sfield.eyy, np.nan)
    truth = star.eyy(x, y)
    idx = strain_peak_rows(star, field.points, step)
    peak = _transfer(star, x[idx], e[idx], truth[idx])
    peak["valid_fraction"] = float(np.mean(np.isfinite(e[idx])))
    return {"peak": peak, "band": _transfer(star, x, e, truth)}


def measure(star: Star, images, *, subset: int, order: int, step: int, windows=(5,), device=None,
            keep_curves: bool = False) -> dict:
    """Transfer functions, l10, noise floors and MEI for one subset size and order (one row of the table).

    ``images``: ``render(star)``. Tracks the POIs of :func:`star_points` (step ``step`` px) into the star
    and into the noise-only image with one :class:`dic.Tracker` (defaults: zero start, no search), takes
    :func:`dic.strain` of both with each window of ``windows`` (grid points), and returns a dict:
    ``displacement`` (``l10_px`` from the centre row, ``l10_band_px`` from the band fit,
    ``l10_unaveraged_px``, ``noise_px`` (std of v on the noise pair), ``mei_px2``, the transfer curves on
    :func:`curve_grid`), ``strain[str(w)]`` (the same for eyy; ``noise`` in strain), the POI count, valid
    fractions and the tracking time; with ``keep_curves`` also the per-column curves.
    """
    import dic

    ref, cur, second = images
    reach = (max(windows) // 2 + 1) * step  # beyond the peak rows of eyy: full strain windows there
    points = star_points(star, subset, step, reach)
    t0 = time.perf_counter()
    tracker = dic.Tracker(ref, points=points, subset=subset, order=order, device=device)
    field = tracker.track(cur)
    noise = tracker.track(second)
    seconds = time.perf_counter() - t0
    disp = displacement_transfer(star, field)
    grid = curve_grid(star)
    nv = noise.v[noise.valid]
    n_v = float(np.std(nv)) if nv.size > 1 else float("nan")
    n_u = float(np.std(noise.u[noise.valid])) if nv.size > 1 else float("nan")
    peak, band = disp["peak"], disp["band"]
    out = {
        "subset": subset, "order": order, "step": step, "n_points": int(points.shape[0]),
        "track_seconds": round(seconds, 2),
        "valid_fraction": float(np.mean(field.valid)), "noise_valid_fraction": float(np.mean(noise.valid)),
        "displacement": {
            "l10_px": peak["l10"], "l10_censored": peak["l10_censored"],
            "l10_unaveraged_px": peak["l10_unaveraged"],
            "l10_band_px": band["l10"], "l10_band_censored": band["l10_censored"],
            "noise_px": n_v, "noise_u_px": n_u,
            "mei_px2": _product(n_v, peak["l10"], 1), "mei_band_px2": _product(n_v, band["l10"], 1),
            "transfer": _curve_on_grid(peak["period"], peak["ratio"], grid),
            "transfer_band": _curve_on_grid(band["period"], band["ratio"], grid),
        },
        "strain": {},
    }
    curves = {"displacement": disp}
    for window in windows:
        sf = dic.strain(field, window=window)
        sn = dic.strain(noise, window=window)
        st = strain_transfer(star, field, sf, step)
        full = sn.valid & (sn.n_fit == window ** 2)
        n_e = float(np.std(sn.eyy[full])) if np.count_nonzero(full) > 1 else float("nan")
        peak, band = st["peak"], st["band"]
        out["strain"][str(window)] = {
            "window_points": window, "window_px": (window - 1) * step + subset,
            "l10_px": peak["l10"], "l10_censored": peak["l10_censored"],
            "l10_band_px": band["l10"], "l10_band_censored": band["l10_censored"],
            "noise": n_e, "mei_px2": _product(n_e, peak["l10"], 2), "mei_band_px2": _product(n_e, band["l10"], 2),
            "transfer": _curve_on_grid(peak["period"], peak["ratio"], grid),
            "transfer_band": _curve_on_grid(band["period"], band["ratio"], grid),
        }
        curves[f"strain_{window}"] = st
    if keep_curves:
        out["curves"] = curves
    return out


def _product(noise, level, power):
    """MEI = noise * l10**power, None where l10 is None (never within 10 %)."""
    return None if level is None or not np.isfinite(noise) else float(noise * level ** power)


def subset_filter_model(subset: int, order: int, sigma: float | None = None) -> dict:
    """What a subset's least-squares shape function does to a small displacement field, as a linear filter.

    Near convergence IC-GN solves a linear least-squares problem whose displacement at the subset centre is
    a weighted sum of the displacement over the subset; for a speckle of uniform gradient energy and white
    image noise those weights are those of the least-squares fit of the shape function's polynomial
    (``1, x, y`` for order 1; with ``x², xy, y²`` for order 2), with pixel weights ``w(x) w(y)`` (1: the
    square subset; ``exp(-t² / 2 sigma²)``: a Gaussian-weighted subset). Returns that filter's transfer
    ``l10`` for ``v = cos(2 pi y / p)`` (px, periods 6-400 px by 0.1 px), its noise gain (the std of the
    centre value for unit white noise per pixel) and ``mei`` = gain * l10 (both in the same unit: compare
    the MEI of two settings as a ratio). A model, not a measurement: docs/dic2d.md compares it with
    the measured figures (square subsets).
    """
    h = subset // 2
    t = np.arange(-h, h + 1, dtype=np.float64)
    w1 = np.ones_like(t) if sigma is None else np.exp(-t ** 2 / (2 * sigma ** 2))
    X, Y = np.meshgrid(t, t)
    x, y, w = X.ravel(), Y.ravel(), np.outer(w1, w1).ravel()
    basis = [np.ones_like(x), x, y] + ([x * x, x * y, y * y] if order == 2 else [])
    B = np.stack(basis, axis=1)
    centre = np.linalg.solve(B.T @ (w[:, None] * B), (B * w[:, None]).T)[0]  # centre value = centre @ v
    periods = np.arange(6.0, 400.0, 0.1)
    transfer = np.cos(2 * np.pi * np.outer(1.0 / periods, y)) @ centre
    level, _ = l10(periods, transfer)
    gain = float(np.sqrt(np.sum(centre ** 2)))
    level = None if level is None else round(level, 1)
    return {"subset": subset, "order": order, "gaussian_sigma_px": sigma, "l10_px": level, "noise_gain": gain,
            "mei": None if level is None else gain * level}


#: DICe's own output on the challenge's star, as far as it could be read here: the gold file of DICe's
#: regression test ``tests/regression/bitmap_star`` (github.com/dicengine/dice, commit 1474112879c2,
#: ``gold/DICe_solution_0.txt``: subset 31, step 15, translation only (no strain terms in the shape
#: function), Keys 4th-order interpolation; its reference image is the deformed star, so its ``v`` is the
#: inverse motion). Amplitude ratio = least-squares amplitude of ``-v`` against ``0.5 cos(2 pi (y - 250) / p(x))``
#: over each column's rows y = 30..465 (step 15), pooled over the columns listed; read by hand from the
#: file (7 columns of 129), so a spot check of the transfer, not a full curve. No noise-only pair comes with
#: it: ``fit_residual_std_px`` is the scatter about the fitted cosine (noise and pattern-induced bias
#: together) and ``dice_sigma_px`` the range of DICe's own SIGMA column there (its predicted std).
DICE_GOLD = {
    "source": "github.com/dicengine/dice tests/regression/bitmap_star/gold/DICe_solution_0.txt (commit 1474112879c2)",
    "settings": "subset 31, step 15, translation only (0th order), KEYS_FOURTH, images DIC_Challenge_Wave_*_Noisy.bmp",
    "spot_checks": [
        {"columns_x_px": [1290, 1305, 1320], "mean_period_px": 101.4, "amplitude_ratio": 0.865,
         "per_column": [0.853, 0.869, 0.872]},
        {"columns_x_px": [1635, 1650, 1665, 1680], "mean_period_px": 126.1, "amplitude_ratio": 0.919,
         "per_column": [0.913, 0.919, 0.925, 0.918]},
    ],
    "l10_px_interpolated": 117.0,
    "fit_residual_std_px": [0.0146, 0.0205],
    "dice_sigma_px": [0.0056, 0.0078],
}


#: Gaussian-weighted subsets for the model comparison: (subset, sigma px)
MODEL_GAUSSIAN = ((21, 3.0), (31, 5.0), (41, 6.0), (41, 8.0), (61, 10.0))


def _fmt(value, spec):
    return "—" if value is None or (isinstance(value, float) and not np.isfinite(value)) else format(value, spec)


def _l10_text(level, censored):
    if level is None:
        return "> max"
    return f"<={level:.1f}" if censored else f"{level:.1f}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--subsets", type=int, nargs="+", default=[11, 15, 21, 31, 41])
    ap.add_argument("--orders", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--windows", type=int, nargs="+", default=[3, 5, 7], help="strain windows (grid points)")
    ap.add_argument("--step", type=int, default=2)
    ap.add_argument("--noise", type=float, default=2.0, help="Gaussian noise std in each image (grey levels)")
    ap.add_argument("--width", type=int, default=2000)
    ap.add_argument("--period-max", type=float, default=150.0)
    ap.add_argument("--seed", type=int, default=2022)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=os.path.join(RESULTS, "resolution.json"))
    args = ap.parse_args(argv)

    import warp as wp

    from bench._host import cpu_model, write_json
    from kernels._launch import cpu_threads

    star = Star(width=args.width, period_max=args.period_max, noise_sigma=args.noise, seed=args.seed)
    load_before = os.getloadavg()
    t0 = time.perf_counter()
    images = render(star, device=args.device)
    render_s = time.perf_counter() - t0
    print(f"star {star.height} x {star.width} px, periods {star.period_min:g}-{star.period_max:g} px, "
          f"noise {star.noise_sigma:g} GL: rendered in {render_s:.1f} s")
    rows = []
    print("l10 in px on the centre / peak rows (band fit in brackets), n: noise floor, MEI in px^2")
    print(f"{'order':>5} {'subset':>6} {'l10_v':>15} {'n_v':>8} {'MEI_v':>7} | " +
          " | ".join(f"w{w}: {'l10_e':>15} {'n_e':>8} {'MEI_e':>7}" for w in args.windows) + " | s")
    for order in args.orders:
        for subset in args.subsets:
            r = measure(star, images, subset=subset, order=order, step=args.step, windows=args.windows,
                        device=args.device)
            for block in [r["displacement"]] + list(r["strain"].values()):
                for key in ("transfer", "transfer_band"):  # the periods once, at the top of the file
                    block[key] = block[key]["ratio"]
            rows.append(r)
            d = r["displacement"]
            cells = []
            for w in args.windows:
                s = r["strain"][str(w)]
                lv = f"{_l10_text(s['l10_px'], s['l10_censored'])} ({_l10_text(s['l10_band_px'], s['l10_band_censored'])})"
                cells.append(f"w{w}: {lv:>15} {_fmt(s['noise'], '.2e'):>8} "
                             f"{_fmt(s['mei_px2'], '.3f'):>7}")
            lv = f"{_l10_text(d['l10_px'], d['l10_censored'])} ({_l10_text(d['l10_band_px'], d['l10_band_censored'])})"
            print(f"{order:>5} {subset:>6} {lv:>15} {_fmt(d['noise_px'], '.5f'):>8} "
                  f"{_fmt(d['mei_px2'], '.4f'):>7} | " + " | ".join(cells) + f" | {r['track_seconds']:.0f}")
    model = {"square": [subset_filter_model(s, o) for o in args.orders for s in args.subsets],
             "gaussian": [subset_filter_model(s, o, sigma) for o in args.orders for s, sigma in MODEL_GAUSSIAN]}
    print("model (uniform gradient energy, white noise; MEI in units of the noise gain):")
    for m in model["square"] + model["gaussian"]:
        what = "square" if m["gaussian_sigma_px"] is None else f"gaussian sigma {m['gaussian_sigma_px']:g} px"
        print(f"  order {m['order']} subset {m['subset']:>2} {what:>22}: l10 {_l10_text(m['l10_px'], False):>6} "
              f"noise gain {m['noise_gain']:.4f} MEI {_fmt(m['mei'], '.3f')}")
    result = {
        "benchmark": "resolution",
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "star": asdict(star),
        "speckle": {"radius_px": 2.0, "density": 0.5, "blur_px": 0.7, "bits": 8},
        "step_px": args.step, "tolerance": TOLERANCE,
        "transfer_period_px": [float(p) for p in curve_grid(star)],
        "method": ("amplitude ratio = measured / exact value at the POIs of the peak rows (v: centre row; eyy: rows "
                   "nearest centre -+ p/4), averaged along the row over one local period; l10 = first period from which "
                   "|ratio - 1| < 0.1 up to the longest period; noise = std over the valid POIs of the noise-only pair; "
                   "MEI = n l10 (displacement), n l10^2 (strain)"),
        "render_seconds": round(render_s, 1),
        "rows": rows,
        "model": model,
        "dice_gold_reference": DICE_GOLD,
        "device": args.device, "cpu": cpu_model(), "cpu_threads": cpu_threads(),
        "load_average_before": load_before, "load_average_after": os.getloadavg(),
        "versions": {"python": platform.python_version(), "numpy": np.__version__, "warp": wp.config.version},
    }
    write_json(result, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
