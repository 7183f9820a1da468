"""Integer-pixel initial guesses for IC-GN: batched ZNCC window search, FFT phase correlation,
and a Gaussian image pyramid for coarse-to-fine tracking.

IC-GN (:mod:`kernels.icgn`) converges from guesses within a few pixels of the solution. For larger
motions, :func:`zncc_search` scans an integer window per POI (one Warp thread per POI, exhaustive,
cost ``(2R + 1)^2 S^2`` per POI), :func:`phase_correlation` finds one global integer shift of the
whole image (SciPy FFT, Kuglin & Hines 1975), and :func:`pyramid` builds the reduced images for
coarse-to-fine tracking (Burt & Adelson, "The Laplacian pyramid as a compact image code", IEEE
Trans. Commun. 31(4), 1983, doi:10.1109/TCOM.1983.1095851). The tracking orchestration (coarse-to-
fine and reliability-guided propagation, Pan et al., Applied Optics 48(8), 2009,
doi:10.1364/AO.48.001535) lives in :mod:`dic.track`.

Conventions (docs/conventions.md): points ``(x, y)`` in pixels; integer displacements ``(u, v)``
move reference pixel ``(x, y)`` to ``(x + u, y + v)`` in the current image.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import scipy.fft
import warp as wp

from ._device import host_copy, resolve_device
from ._launch import cpu_threads, launch_1d
from .checks import as_points, non_negative_int, odd_int
from .conventions import round_half_away
from .images import as_float32_image

wp.set_module_options({"enable_backward": False})

# ----------------------------------------------------------------------------------------------
# @wp.func helpers
# ----------------------------------------------------------------------------------------------


@wp.func
def subset_stats(img: wp.array(dtype=float), width: int, cx: int, cy: int, r: int):
    """(mean, sqrt(sum (f - mean)^2)) of the (2r+1)^2 integer subset centred on (cx, cy)."""
    s = float(0.0)
    for j in range(-r, r + 1):
        row = (cy + j) * width + cx
        for i in range(-r, r + 1):
            s += img[row + i]
    n = float((2 * r + 1) * (2 * r + 1))
    mean = s / n
    ss = float(0.0)
    for j in range(-r, r + 1):
        row = (cy + j) * width + cx
        for i in range(-r, r + 1):
            d = img[row + i] - mean
            ss += d * d
    return mean, wp.sqrt(ss)


@wp.func
def candidate_zncc(ref: wp.array(dtype=float), cur: wp.array(dtype=float), width: int, cx: int, cy: int,
                   du: int, dv: int, r: int, fmean: float, fnorm: float):
    """ZNCC between the reference subset at (cx, cy) and the current subset at (cx + du, cy + dv)."""
    sg = float(0.0)
    sgg = float(0.0)
    sfg = float(0.0)
    for j in range(-r, r + 1):
        rrow = (cy + j) * width + cx
        crow = (cy + j + dv) * width + cx + du
        for i in range(-r, r + 1):
            g = cur[crow + i] - fmean
            sg += g
            sgg += g * g
            sfg += (ref[rrow + i] - fmean) * g
    n = float((2 * r + 1) * (2 * r + 1))
    dg2 = sgg - sg * sg / n
    if not (dg2 > 0.0):
        return -2.0
    return sfg / (fnorm * wp.sqrt(dg2))


# ----------------------------------------------------------------------------------------------
# kernels
# ----------------------------------------------------------------------------------------------


@wp.kernel
def _zncc_search(
    offset: int, ref: wp.array(dtype=float), cur: wp.array(dtype=float), width: int, height: int,
    centres: wp.array(dtype=wp.vec2i), start: wp.array(dtype=wp.vec2i), radius: int, r: int,
    best: wp.array(dtype=wp.vec2i), best_cc: wp.array(dtype=float),
):
    n = wp.tid() + offset
    c = centres[n]
    s0 = start[n]
    best[n] = s0
    best_cc[n] = wp.nan
    if c[0] - r < 0 or c[1] - r < 0 or c[0] + r > width - 1 or c[1] + r > height - 1:
        return
    fmean, fnorm = subset_stats(ref, width, c[0], c[1], r)
    if not (fnorm > 0.0):
        return
    top = float(-3.0)
    arg = s0
    for dv in range(s0[1] - radius, s0[1] + radius + 1):
        if c[1] + dv - r < 0 or c[1] + dv + r > height - 1:
            continue
        for du in range(s0[0] - radius, s0[0] + radius + 1):
            if c[0] + du - r < 0 or c[0] + du + r > width - 1:
                continue
            cc = candidate_zncc(ref, cur, width, c[0], c[1], du, dv, r, fmean, fnorm)
            if cc > top:
                top = cc
                arg = wp.vec2i(du, dv)
    if top > -2.0:
        best[n] = arg
        best_cc[n] = top


@wp.kernel
def _reduce_rows(offset: int, src: wp.array2d(dtype=float), dst: wp.array2d(dtype=float), width: int):
    """Filter rows with [1 4 6 4 1]/16 (mirror) and keep even columns: dst (H, W2)."""
    y = wp.tid() + offset
    for xo in range(dst.shape[1]):
        x = 2 * xo
        acc = 6.0 * src[y, x]
        for k in range(1, 3):
            xl = wp.abs(x - k)
            xr = x + k
            if xr > width - 1:
                xr = 2 * (width - 1) - xr
            w = 4.0
            if k == 2:
                w = 1.0
            acc += w * (src[y, xl] + src[y, xr])
        dst[y, xo] = acc * (1.0 / 16.0)


@wp.kernel
def _reduce_cols(offset: int, src: wp.array2d(dtype=float), dst: wp.array2d(dtype=float), height: int):
    """Filter columns with [1 4 6 4 1]/16 (mirror) and keep even rows."""
    x = wp.tid() + offset
    for yo in range(dst.shape[0]):
        y = 2 * yo
        acc = 6.0 * src[y, x]
        for k in range(1, 3):
            yl = wp.abs(y - k)
            yr = y + k
            if yr > height - 1:
                yr = 2 * (height - 1) - yr
            w = 4.0
            if k == 2:
                w = 1.0
            acc += w * (src[yl, x] + src[yr, x])
        dst[yo, x] = acc * (1.0 / 16.0)


# ----------------------------------------------------------------------------------------------
# launchers
# ----------------------------------------------------------------------------------------------


#: the largest ``|start|`` (px) :func:`zncc_search` accepts: far beyond any image, and small enough
#: that the window's bounds stay within the kernel's 32-bit integers
MAX_START = 2**24


def _int_pairs(a, n: int, name: str) -> np.ndarray:
    arr = np.asarray(a)
    if arr.shape != (n, 2):
        raise ValueError(f"{name} must have shape {(n, 2)}, got {arr.shape}")
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    if arr.size and np.max(np.abs(arr)) > MAX_START:
        raise ValueError(f"{name} must lie within +-{MAX_START} px, got a value of {np.max(np.abs(arr)):.6g}")
    return np.ascontiguousarray(round_half_away(arr), dtype=np.int32)


def useful_radius(shape, points, subset: int, start=None) -> int:
    """The largest search radius that can still change :func:`zncc_search`'s result.

    A candidate shift must keep the current subset on the image, so for a POI at ``(cx, cy)``
    (rounded) with window centre ``start`` only shifts ``du`` in ``[r - cx, W - 1 - r - cx]`` (and
    likewise ``dv``) are ever evaluated, ``r = subset // 2``. The returned radius is the smallest
    one whose window contains all of them for every POI whose reference subset lies on the image
    (at most about the image's larger side plus ``|start|``); a larger radius tries the same
    candidates in the same order, so it gives the same result. 0 when no candidate fits.
    """
    h, w = (int(v) for v in shape)
    r = odd_int(subset, "subset") // 2
    c = round_half_away(as_points(points, allow_empty=True)).astype(np.int64)
    st = np.zeros_like(c) if start is None else _int_pairs(start, c.shape[0], "start").astype(np.int64)
    inside = (c[:, 0] - r >= 0) & (c[:, 1] - r >= 0) & (c[:, 0] + r <= w - 1) & (c[:, 1] + r <= h - 1)
    if not np.any(inside) or w < 2 * r + 1 or h < 2 * r + 1:
        return 0
    c, st = c[inside], st[inside]
    need = 0
    for axis, size in ((0, w), (1, h)):
        lo = r - c[:, axis] - st[:, axis]              # lowest useful shift minus the window centre
        hi = size - 1 - r - c[:, axis] - st[:, axis]   # highest useful shift minus the window centre
        need = max(need, int(np.max(np.maximum(np.abs(lo), np.abs(hi)))))
    return need


@dataclass(frozen=True)
class SearchImage:
    """A grey image uploaded once for :func:`zncc_search` (:func:`search_image`): float32, row-major,
    flat on ``device``. Give it in place of an array to search many times in the same image (e.g. the
    reference of a sequence) without uploading it again."""

    flat: wp.array
    shape: tuple[int, int]
    device: str


def search_image(image, device=None, name: str = "image") -> SearchImage:
    """Validate ``image`` (as every search input, :func:`kernels.images.as_float32_image`) and upload it once."""
    if isinstance(image, SearchImage):
        return image
    device = resolve_device(device)
    arr = as_float32_image(image, name)
    return SearchImage(wp.array(arr.ravel(), dtype=wp.float32, device=device), arr.shape, device)


def _search_input(image, name: str, device: str) -> SearchImage:
    if isinstance(image, SearchImage) and image.device != device:
        raise ValueError(f"{name} was uploaded to {image.device} but the search runs on {device}")
    return search_image(image, device, name)


def zncc_search(reference, current, points, radius: int, subset: int = 21, start=None, device=None):
    """Exhaustive integer ZNCC search of each POI's subset within a window.

    Parameters
    ----------
    reference, current : array-like (H, W) grey images of the same shape, or :class:`SearchImage`
        (:func:`search_image`: uploaded once, used in place).
    points : array-like (N, 2)
        POIs ``(x, y)``; the subset is centred on ``round(x), round(y)``.
    radius : int >= 0
        Half-width R of the search window: shifts ``start + (-R..R)^2`` are tried. Only shifts
        that keep the subset on the image are evaluated, so R is clamped to
        :func:`useful_radius` (about the image's larger side): a larger R gives the same result
        in the same time.
    subset : odd int >= 3
    start : array-like (N, 2), optional
        Integer displacement at the window centre per POI (default zero; rounded).
    device : None or str

    Returns
    -------
    uv : np.ndarray int32 (N, 2)
        Best integer displacement ``(u, v)`` (``start`` where nothing could be evaluated).
    zncc : np.ndarray float32 (N,)
        Its ZNCC; NaN where the reference subset leaves the image or is flat, or no candidate
        subset fits in the current image.
    """
    device = resolve_device(device)
    ref = _search_input(reference, "reference", device)
    cur = _search_input(current, "current", device)
    if ref.shape != cur.shape:
        raise ValueError(f"reference {ref.shape} and current {cur.shape} images must have the same shape")
    subset = odd_int(subset, "subset")
    radius = non_negative_int(radius, "radius", detail=" (pixels)")
    pts = as_points(points)
    n = pts.shape[0]
    st = np.zeros((n, 2), np.int32) if start is None else _int_pairs(start, n, "start")
    h, w = ref.shape
    radius = min(radius, useful_radius((h, w), pts, subset, st))
    centres = wp.array(round_half_away(pts).astype(np.int32), dtype=wp.vec2i, device=device)
    best = wp.empty(n, dtype=wp.vec2i, device=device)
    best_cc = wp.empty(n, dtype=wp.float32, device=device)
    launch_1d(
        _zncc_search, n,
        [0, ref.flat, cur.flat, w, h, centres, wp.array(st, dtype=wp.vec2i, device=device), int(radius), subset // 2,
         best, best_cc],
        device, offset_index=0, min_chunk=1,
    )
    return host_copy(best).astype(np.int32), host_copy(best_cc)


@dataclass(frozen=True)
class PhaseSpectrum:
    """One image's side of :func:`phase_correlation`: ``spectrum`` (H, W // 2 + 1) complex128, the 2-D real
    FFT of the image mean-removed and Hann-windowed, and the image's ``shape`` (H, W)."""

    spectrum: np.ndarray
    shape: tuple


@lru_cache(maxsize=4)
def _hann_window(shape: tuple) -> np.ndarray:
    win = np.outer(np.hanning(shape[0]), np.hanning(shape[1]))
    win.setflags(write=False)
    return win


def phase_spectrum(image, name: str = "image") -> PhaseSpectrum:
    """The spectrum of ``image`` (H, W) for :func:`phase_correlation_spectra` (SciPy's pocketfft, float64).

    Computed once per image, it serves every correlation of that image (in a sequence each image is the
    current image of one state and the base of the next)."""
    img = as_float32_image(image, name).astype(np.float64)
    img -= img.mean()  # in place: the same values as (img - mean) * window, one temporary fewer
    img *= _hann_window(img.shape)
    return PhaseSpectrum(scipy.fft.rfft2(img, workers=fft_workers()), img.shape)


def fft_workers() -> int:
    """Threads of the phase-correlation FFTs: the CPU launches' (:func:`kernels._launch.cpu_threads`). pocketfft
    splits a 2-D transform into whole 1-D transforms per thread, so the result is bit for bit that of one thread
    (tested)."""
    return cpu_threads()


def phase_window(points, shape, margin_px: int, quantum_px: int = 32) -> tuple[slice, slice] | None:
    """The part of an (H, W) image to measure the global shift of ``points`` (N, 2) ``(x, y)`` px on: their
    bounding box grown by ``margin_px`` px on every side (the subsets' half size and the largest shift expected
    beyond it) and out to multiples of ``quantum_px`` (points that move a little give the same window, so a
    kept spectrum serves again), clamped to the image, each side then grown towards a fast FFT length
    (:func:`scipy.fft.next_fast_len`) as far as the image allows. Returns ``(rows, cols)`` slices, or None when
    that is the whole image (or there is no finite point)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    margin = non_negative_int(margin_px, "margin_px")
    quantum = max(1, non_negative_int(quantum_px, "quantum_px"))
    h, w = int(shape[0]), int(shape[1])
    if pts.shape[0] == 0:
        return None
    spans = []
    for lo, hi, size in ((pts[:, 1].min(), pts[:, 1].max(), h), (pts[:, 0].min(), pts[:, 0].max(), w)):
        a = max(0, (int(np.floor(lo)) - margin) // quantum * quantum)
        b = min(size, -(-(int(np.ceil(hi)) + margin + 1) // quantum) * quantum)
        fast = min(size, scipy.fft.next_fast_len(b - a, real=True))
        grow = fast - (b - a)
        b2 = min(size, b + grow)
        a = max(0, a - (grow - (b2 - b)))
        spans.append(slice(a, b2))
    if spans[0] == slice(0, h) and spans[1] == slice(0, w):
        return None
    return spans[0], spans[1]


def phase_correlation_spectra(reference: PhaseSpectrum, current: PhaseSpectrum) -> tuple[int, int, float]:
    """:func:`phase_correlation` from the two images' :func:`phase_spectrum`; the same ``(u, v, peak)``."""
    for name, sp in (("reference", reference), ("current", current)):
        if not isinstance(sp, PhaseSpectrum):
            raise ValueError(f"{name} must be a PhaseSpectrum (phase_spectrum(image)), got {type(sp).__name__}")
    if reference.shape != current.shape:
        raise ValueError(f"reference {reference.shape} and current {current.shape} images must have the same shape")
    cross = current.spectrum * np.conj(reference.spectrum)
    magnitude = np.abs(cross)
    cross /= np.maximum(magnitude, 1e-12 * magnitude.max() + 1e-30)
    corr = scipy.fft.irfft2(cross, s=reference.shape, workers=fft_workers())
    iy, ix = np.unravel_index(int(np.argmax(corr)), corr.shape)
    h, w = reference.shape
    v = iy - h if iy > h // 2 else iy
    u = ix - w if ix > w // 2 else ix
    return int(u), int(v), float(corr[iy, ix])


def phase_correlation(reference, current) -> tuple[int, int, float]:
    """Global integer shift ``(u, v)`` of ``current`` relative to ``reference`` by phase correlation.

    Both images are mean-removed and Hann-windowed; the peak of the normalised cross-power
    spectrum's inverse FFT gives the shift (|u| < W/2, |v| < H/2). SciPy FFT (pocketfft) on the host;
    :func:`phase_spectrum` and :func:`phase_correlation_spectra` keep an image's spectrum for reuse.

    Returns
    -------
    (u, v, peak) : the integer shift in pixels and the peak height (1 for a perfect circular shift,
    close to 0 when the images do not match).
    """
    ref = as_float32_image(reference, "reference")
    cur = as_float32_image(current, "current")
    if ref.shape != cur.shape:
        raise ValueError(f"reference {ref.shape} and current {cur.shape} images must have the same shape")
    return phase_correlation_spectra(phase_spectrum(ref, "reference"), phase_spectrum(cur, "current"))


def reduce(image, device=None) -> np.ndarray:
    """One Gaussian-pyramid reduction: filter with [1 4 6 4 1]/16 (mirror borders), keep even pixels.

    Pixel ``(X, Y)`` of the result sits at ``(2X, 2Y)`` of the input, so coordinates and
    displacements scale by exactly 2 between levels. Returns float32 ``(ceil(H/2), ceil(W/2))``.
    """
    device = resolve_device(device)
    img = as_float32_image(image, "image")
    h, w = img.shape
    if h < 3 or w < 3:
        raise ValueError(f"image must be at least 3x3 to reduce, got shape {img.shape}")
    h2, w2 = (h + 1) // 2, (w + 1) // 2
    src = wp.array(img, dtype=wp.float32, device=device)
    tmp = wp.empty((h, w2), dtype=wp.float32, device=device)
    dst = wp.empty((h2, w2), dtype=wp.float32, device=device)
    launch_1d(_reduce_rows, h, [0, src, tmp, w], device, offset_index=0, min_chunk=64)
    launch_1d(_reduce_cols, w2, [0, tmp, dst, h], device, offset_index=0, min_chunk=64)
    return host_copy(dst)


def pyramid(image, levels: int, device=None) -> list[np.ndarray]:
    """``[image, reduce(image), reduce(reduce(image)), ...]`` with ``levels + 1`` entries (float32).

    ``levels`` may not exceed the reductions the image allows (each needs at least 3x3 pixels).
    """
    levels = non_negative_int(levels, "levels")
    img = as_float32_image(image, "image")
    h, w, most = img.shape[0], img.shape[1], 0
    while min(h, w) >= 3:
        h, w, most = (h + 1) // 2, (w + 1) // 2, most + 1
    if levels > most:
        raise ValueError(f"levels must be <= {most} for a {img.shape[1]}x{img.shape[0]} px image "
                         f"(each level halves it; 3x3 px is the smallest that reduces), got {levels}")
    out = [img]
    for _ in range(levels):
        out.append(reduce(out[-1], device=device))
    return out
