"""Synthetic speckle images with exact ground truth: the Boolean model.

Sur, Blaysat & Grédiac, "Rendering deformed speckle images with a Boolean model", Journal of
Mathematical Imaging and Vision 60 (2018), doi:10.1007/s10851-018-0834-x.

The pattern is the union of disks whose centres form a homogeneous Poisson process of intensity
``λ`` (disks per px²) and whose radii are independent draws with mean ``radius``. The covered
fraction of the plane (the *density*) is ``p = 1 - exp(-λ π E[r²])``, so a requested density
fixes ``λ = -ln(1 - p) / (π E[r²])``. A camera pixel records the pattern integrated over its area
and blurred by a Gaussian point-spread function of standard deviation ``blur`` px; grey levels are
``background + contrast · coverage``, then optionally Poisson (shot) noise, Gaussian noise and
8/16-bit quantisation.

A deformed image is made by evaluating the *same* disk model at the material points that the
displacement maps to each image sample (``x = X + u(X)`` is solved for ``X``), never by
interpolating the reference image, so the displacement is known exactly at every point.

Quick use::

    from dic.synth import speckle_pair
    ref, cur = speckle_pair((256, 256), displacement=(0.3, -0.2), seed=1)
    ref, cur = speckle_pair((256, 256), lambda x, y: (1e-3 * x, 0.0 * y), noise_sigma=2.0)

See docs/synth.md for the model, the rendering quadrature and measured properties.
Conventions (docs/conventions.md): images ``[row, col] = [y, x]``, pixel (0, 0) centred at
(0, 0), displacements ``(u, v)`` in px along x and y, defined on reference coordinates.
"""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from kernels.checks import positive_int

__all__ = [
    "BooleanSpeckle",
    "make_speckle",
    "speckle_image",
    "speckle_pair",
    "deformed_image",
    "add_noise",
    "inverse_displacement",
    "render",
    "specimen_on_background",
    "EvolvingSequence",
    "evolving_sequence",
]

#: tile side in units of the mean radius: disks are drawn tile by tile with per-tile seeds, so a
#: seed gives the same disks wherever two regions overlap
_TILE_RADII = 32.0
_DEFAULT_MARGIN = 2.0  # px beyond the blur support around an image when a model is built for it


def _full_scale(bits) -> float:
    if bits is None:
        return 255.0
    if bits not in (8, 16):
        raise ValueError(f"bits must be 8, 16 or None (no quantisation), got {bits!r}")
    return float(2**bits - 1)


def _seed_entropy(seed, *extra: int) -> list[int]:
    if isinstance(seed, numbers.Integral) and not isinstance(seed, bool):
        base = [int(seed)]
    elif isinstance(seed, (list, tuple)) and all(isinstance(s, numbers.Integral) for s in seed):
        base = [int(s) for s in seed]
    else:
        raise ValueError(f"seed must be a non-negative integer (or a sequence of them), got {seed!r}")
    if any(s < 0 for s in base):
        raise ValueError(f"seed must be non-negative, got {seed!r}")
    return base + [int(e) for e in extra]


# ---------------------------------------------------------------------------------------------
# the model


@dataclass
class BooleanSpeckle:
    """A Boolean-model speckle pattern: disks plus the imaging parameters.

    Attributes
    ----------
    centres : ndarray (M, 2) float64
        Disk centres ``(x, y)`` in px (reference image coordinates).
    radii : ndarray (M,) float64
        Disk radii in px.
    region : tuple (x0, y0, x1, y1)
        Rectangle (px) inside which the pattern is complete: every disk that touches it exists.
        Evaluating outside it shows missing disks; renderers refuse to.
    background, contrast : float
        Grey levels: ``background + contrast · coverage`` (coverage 0 outside disks, 1 inside).
    blur : float
        Standard deviation (px) of the Gaussian point-spread function.
    samples : int
        Sub-cells per pixel side in the rendering quadrature (``samples²`` per pixel).
    bits : int or None
        Default quantisation (8, 16, or None for float grey levels).
    radius, density, radius_spread, seed :
        The generation parameters, for provenance.
    """

    centres: np.ndarray
    radii: np.ndarray
    region: tuple[float, float, float, float]
    background: float
    contrast: float
    blur: float = 0.7
    samples: int = 4
    bits: int | None = 8
    radius: float = float("nan")
    density: float = float("nan")
    radius_spread: float = 0.0
    seed: object = None
    _device_models: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        self.centres = np.asarray(self.centres, dtype=np.float64).reshape(-1, 2)
        self.radii = np.asarray(self.radii, dtype=np.float64).reshape(-1)
        if self.radii.shape[0] != self.centres.shape[0]:
            raise ValueError(f"centres (M, 2) and radii (M,) disagree: {self.centres.shape} vs {self.radii.shape}")
        if len(self.region) != 4 or not (self.region[2] > self.region[0] and self.region[3] > self.region[1]):
            raise ValueError(f"region must be (x0, y0, x1, y1) with x1 > x0 and y1 > y0, got {self.region!r}")
        if not (self.blur >= 0 and math.isfinite(self.blur)):
            raise ValueError(f"blur must be >= 0 px, got {self.blur!r}")
        _full_scale(self.bits)

    # -- device side
    def device_model(self, device=None):
        """The :class:`kernels.speckle.SpeckleModel` of these disks on ``device`` (cached)."""
        from kernels._device import resolve_device
        from kernels.speckle import build_speckle_model

        device = resolve_device(device)
        if device not in self._device_models:
            self._device_models[device] = build_speckle_model(
                self.centres, self.radii, pad=0.5 / self.samples, device=device)
        return self._device_models[device]

    @property
    def max_radius(self) -> float:
        return float(self.radii.max()) if self.radii.size else 0.0

    def covers(self, x0, y0, x1, y1) -> bool:
        """True when the rectangle ``[x0, x1] × [y0, y1]`` (px) lies inside :attr:`region`."""
        r = self.region
        return x0 >= r[0] and y0 >= r[1] and x1 <= r[2] and y1 <= r[3]

    def _check_points(self, x, y):
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        try:
            x, y = np.broadcast_arrays(x, y)
        except ValueError:
            raise ValueError(f"x and y must broadcast together, got shapes {x.shape} and {y.shape}") from None
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            raise ValueError("x and y must be finite")
        return x, y

    def coverage(self, x, y, *, device=None) -> np.ndarray:
        """Binary coverage (1.0 inside a disk, else 0.0) at points ``(x, y)`` px; shape of x."""
        from kernels.speckle import speckle_coverage_points

        x, y = self._check_points(x, y)
        pts = np.stack([x.ravel(), y.ravel()], axis=1)
        if pts.shape[0] == 0:
            return np.zeros(x.shape)
        return speckle_coverage_points(self.device_model(device), pts).reshape(x.shape)

    def evaluate(self, x, y, *, samples: int | None = None, device=None) -> np.ndarray:
        """Noise-free grey level (float64) of pixels centred at ``(x, y)`` px, undeformed pattern.

        Uses the same quadrature as the image renderers (pixel area × Gaussian blur,
        ``samples`` sub-cells per pixel side), so ``evaluate(x - u, y - v)`` equals the pixel
        ``(x, y)`` of an image rigidly shifted by ``(u, v)``.
        """
        from kernels.speckle import speckle_at_points

        x, y = self._check_points(x, y)
        s = self.samples if samples is None else samples
        pts = np.stack([x.ravel(), y.ravel()], axis=1)
        if pts.shape[0] == 0:
            return np.zeros(x.shape)
        reach = 4 * self.blur + 1.0
        if not self.covers(pts[:, 0].min() - reach, pts[:, 1].min() - reach,
                           pts[:, 0].max() + reach, pts[:, 1].max() + reach):
            raise ValueError(
                f"points reach outside the pattern's region {self.region}; build the model with a larger "
                "region or margin (make_speckle(..., margin=...))")
        cov = speckle_at_points(self.device_model(device), pts, samples=s, blur=self.blur)
        return (self.background + self.contrast * cov).reshape(x.shape)

    def expected_density(self) -> float:
        """Covered fraction implied by the Poisson model: ``1 - exp(-λ π E[r²])``."""
        return float(self.density)


def _draw_radii(rng, n, radius, spread):
    if spread == 0:
        return np.full(n, radius)
    half = math.sqrt(3.0) * spread * radius
    return rng.uniform(radius - half, radius + half, size=n)


def make_speckle(
    shape=None,
    *,
    region=None,
    margin: float | None = None,
    radius: float = 2.0,
    density: float = 0.5,
    radius_spread: float = 0.2,
    blur: float = 0.7,
    background: float | None = None,
    contrast: float | None = None,
    bits: int | None = 8,
    samples: int = 4,
    seed=0,
) -> BooleanSpeckle:
    """Draw a Boolean-model speckle pattern (Sur, Blaysat & Grédiac 2018).

    Parameters
    ----------
    shape : (H, W), optional
        Image shape the pattern is for; the region is the image plus ``margin`` px on every side.
    region : (x0, y0, x1, y1), optional
        Rectangle (px) to fill instead of ``shape`` (exactly one of the two is required).
    margin : float, optional
        Extra px around ``shape`` (default ``4 blur + 2``). Deformed images need the region to
        contain every material point they show; :func:`speckle_pair` sizes it for you.
    radius : float
        Mean disk radius, px (> 0). 2 px (4 px speckles) suits 21 px subsets.
    density : float
        Covered fraction of the plane, in (0, 1). 0.5 gives the most contrast.
    radius_spread : float
        Relative standard deviation of the radius (uniform distribution on
        ``radius · (1 ± √3 spread)``), in [0, 0.5].
    blur : float
        Gaussian point-spread function standard deviation, px (>= 0).
    background, contrast : float, optional
        Grey levels ``background + contrast · coverage``; defaults 0.15 and 0.70 of the full scale
        (255 for 8-bit or float, 65535 for 16-bit).
    bits : 8, 16 or None
        Default quantisation of images rendered from this pattern.
    samples : int
        Sub-cells per pixel side in the rendering quadrature.
    seed : int
        Seed of the Poisson process. Disks are drawn per tile of ``32 · radius`` px with seeds
        derived from ``(seed, tile)``, so a seed gives the same disks in any overlapping region.
    """
    if (shape is None) == (region is None):
        raise ValueError("give exactly one of shape=(H, W) or region=(x0, y0, x1, y1)")
    for name, val in (("radius", radius), ("blur", blur)):
        if not isinstance(val, numbers.Real) or not math.isfinite(val):
            raise ValueError(f"{name} must be a finite number, got {val!r}")
    if radius <= 0:
        raise ValueError(f"radius must be > 0 px, got {radius}")
    if not (0 < density < 1):
        raise ValueError(f"density (covered fraction) must be in (0, 1), got {density!r}")
    if not (0 <= radius_spread <= 0.5):
        raise ValueError(f"radius_spread (relative std of the radius) must be in [0, 0.5], got {radius_spread!r}")
    if blur < 0:
        raise ValueError(f"blur must be >= 0 px, got {blur}")
    samples = positive_int(samples, "samples", integral_float=True)
    full = _full_scale(bits)
    background = 0.15 * full if background is None else float(background)
    contrast = 0.70 * full if contrast is None else float(contrast)
    if not (math.isfinite(background) and math.isfinite(contrast)):
        raise ValueError("background and contrast must be finite")
    if shape is not None:
        H, W = _check_shape(shape)
        m = 4 * blur + _DEFAULT_MARGIN if margin is None else float(margin)
        if m < 0:
            raise ValueError(f"margin must be >= 0, got {margin}")
        region = (-0.5 - m, -0.5 - m, W - 0.5 + m, H - 0.5 + m)
    else:
        try:
            region = tuple(float(v) for v in region)
        except (TypeError, ValueError):
            raise ValueError(f"region must be (x0, y0, x1, y1), got {region!r}") from None
        if len(region) != 4 or not all(math.isfinite(v) for v in region) or region[2] <= region[0] or region[3] <= region[1]:
            raise ValueError(f"region must be finite (x0, y0, x1, y1) with x1 > x0 and y1 > y0, got {region!r}")

    mean_r2 = radius**2 * (1.0 + radius_spread**2)
    lam = -math.log1p(-density) / (math.pi * mean_r2)  # disks per px²
    r_max = radius * (1.0 + math.sqrt(3.0) * radius_spread)
    tile = _TILE_RADII * radius
    tx0 = math.floor((region[0] - r_max) / tile)
    tx1 = math.floor((region[2] + r_max) / tile)
    ty0 = math.floor((region[1] - r_max) / tile)
    ty1 = math.floor((region[3] + r_max) / tile)
    n_tiles = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)
    if n_tiles > 2_000_000:
        raise ValueError(f"region {region} needs {n_tiles} tiles of {tile} px; it is too large for radius {radius}")
    off = 1 << 30
    centres, radii = [], []
    for ty in range(ty0, ty1 + 1):
        for tx in range(tx0, tx1 + 1):
            rng = np.random.default_rng(_seed_entropy(seed, tx + off, ty + off))
            n = rng.poisson(lam * tile * tile)
            c = (rng.random((n, 2)) + (tx, ty)) * tile
            centres.append(c)
            radii.append(_draw_radii(rng, n, radius, radius_spread))
    centres = np.concatenate(centres) if centres else np.zeros((0, 2))
    radii = np.concatenate(radii) if radii else np.zeros(0)
    # keep the disks that can touch the region
    keep = ((centres[:, 0] + radii >= region[0]) & (centres[:, 0] - radii <= region[2])
            & (centres[:, 1] + radii >= region[1]) & (centres[:, 1] - radii <= region[3]))
    return BooleanSpeckle(
        centres=centres[keep], radii=radii[keep], region=tuple(region), background=background,
        contrast=contrast, blur=float(blur), samples=int(samples), bits=bits, radius=float(radius),
        density=float(density), radius_spread=float(radius_spread), seed=seed,
    )


# ---------------------------------------------------------------------------------------------
# displacements


def _is_constant(displacement) -> bool:
    if callable(displacement):
        return False
    try:
        arr = np.asarray(displacement, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return arr.shape == (2,)


def _call_displacement(displacement, x, y):
    out = displacement(x, y)
    try:
        u, v = out
    except (TypeError, ValueError):
        raise ValueError("displacement(x, y) must return a pair (u, v) of arrays") from None
    try:
        u = np.broadcast_to(np.asarray(u, dtype=np.float64), x.shape)
        v = np.broadcast_to(np.asarray(v, dtype=np.float64), x.shape)
    except ValueError:
        raise ValueError(f"displacement(x, y) returned arrays that do not match x's shape {x.shape}") from None
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(v))):
        raise ValueError("displacement(x, y) returned NaN or infinite values")
    return u, v


def inverse_displacement(displacement: Callable, x, y, *, tol: float = 1e-9, max_iter: int = 200):
    """Solve ``x = X + u(X)`` for the material points ``X`` seen at current positions ``(x, y)``.

    Fixed-point iteration ``X ← x - u(X)`` (converges when the displacement gradient's norm is
    below 1, i.e. the mapping does not fold), per point until the update is below ``tol`` px.
    Returns ``(X, Y)`` float64 arrays of the shape of ``x``. Raises ``ValueError`` when it does not
    converge.
    """
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    X = x.copy().ravel()
    Y = y.copy().ravel()
    xf, yf = x.ravel(), y.ravel()
    active = np.arange(X.size)
    for _ in range(max_iter):
        u, v = _call_displacement(displacement, X[active], Y[active])
        nx = xf[active] - u
        ny = yf[active] - v
        step = np.maximum(np.abs(nx - X[active]), np.abs(ny - Y[active]))
        X[active] = nx
        Y[active] = ny
        active = active[step > tol]
        if active.size == 0:
            return X.reshape(x.shape), Y.reshape(x.shape)
    raise ValueError(
        f"inverting the displacement x = X + u(X) did not converge at {active.size} points after {max_iter} "
        "iterations; the displacement gradient must stay below 1 (no folding)")


# ---------------------------------------------------------------------------------------------
# images


def add_noise(image, *, noise_sigma: float = 0.0, poisson: bool = False, full_well: float = 20000.0,
              bits: int | None = 8, seed=0) -> np.ndarray:
    """Add shot and read noise to a noise-free grey-level image, then quantise.

    ``poisson``: photo-electrons ``N ~ Poisson(I / full_scale · full_well)``, grey level
    ``N / full_well · full_scale`` (full_scale = 255 for 8-bit/float, 65535 for 16-bit).
    ``noise_sigma``: additive Gaussian noise, std in grey levels. ``bits`` 8/16: round and clip
    to ``[0, 2^bits - 1]``; None: no quantisation. Returns float32.
    """
    img = np.asarray(image, dtype=np.float64)
    full = _full_scale(bits)
    if not (noise_sigma >= 0 and math.isfinite(noise_sigma)):
        raise ValueError(f"noise_sigma must be >= 0 grey levels, got {noise_sigma!r}")
    if poisson and not (full_well > 0 and math.isfinite(full_well)):
        raise ValueError(f"full_well must be > 0 electrons, got {full_well!r}")
    rng = np.random.default_rng(_seed_entropy(seed))
    if poisson:
        electrons = rng.poisson(np.clip(img, 0, None) / full * full_well)
        img = electrons * (full / full_well)
    if noise_sigma > 0:
        img = img + rng.normal(0.0, noise_sigma, size=img.shape)
    if bits is not None:
        img = np.clip(np.rint(img), 0, full)
    return img.astype(np.float32)


def _check_shape(shape):
    try:
        H, W = (int(n) for n in shape)
    except (TypeError, ValueError):
        raise ValueError(f"shape must be (H, W), got {shape!r}") from None
    if H < 1 or W < 1:
        raise ValueError(f"shape must be positive, got {(H, W)}")
    return H, W


def _needed_bounds(model: BooleanSpeckle, shape, displacement):
    """Rectangle of material points a rendered image of ``shape`` shows, and the render plan."""
    H, W = shape
    reach = 4 * model.blur + 1.0  # quadrature support beyond the pixel centres (plus a sub-cell)
    if displacement is None:
        return (-reach, -reach, W - 1 + reach, H - 1 + reach), None
    if _is_constant(displacement):
        u, v = np.asarray(displacement, dtype=np.float64)
        if not (math.isfinite(u) and math.isfinite(v)):
            raise ValueError(f"displacement must be finite, got {displacement!r}")
        return (-reach - u, -reach - v, W - 1 + reach - u, H - 1 + reach - v), ("shift", (u, v))
    if not callable(displacement):
        raise ValueError(
            "displacement must be None, a constant (u, v) pair, or a callable (x, y) -> (u, v) of "
            f"reference coordinates in px; got {type(displacement).__name__}")
    # inverse displacement sampled on the pixel grid with a margin for the quadrature and Keys taps
    m = int(math.ceil(4 * model.blur + 1.0)) + 3
    gx = np.arange(-m, W + m, dtype=np.float64)
    gy = np.arange(-m, H + m, dtype=np.float64)
    xx, yy = np.meshgrid(gx, gy)
    X, Y = inverse_displacement(displacement, xx, yy)
    inner = (xx >= -reach) & (xx <= W - 1 + reach) & (yy >= -reach) & (yy <= H - 1 + reach)
    bounds = (X[inner].min(), Y[inner].min(), X[inner].max(), Y[inner].max())
    plan = ("field", ((xx - X), (yy - Y), (float(-m), float(-m)), 1.0))
    return bounds, plan


def render(model: BooleanSpeckle, shape, displacement=None, *, samples: int | None = None, device=None) -> np.ndarray:
    """Noise-free grey levels (float64, (H, W)) of ``model`` seen through ``displacement``.

    ``displacement``: None (reference), a constant ``(u, v)`` px, or a callable ``(x, y) -> (u, v)``
    of reference coordinates (NumPy arrays in, arrays out). The image at ``x`` shows material
    point ``X`` with ``x = X + u(X)``.
    """
    if not isinstance(model, BooleanSpeckle):
        raise ValueError(f"model must be a BooleanSpeckle (see make_speckle), got {type(model).__name__}")
    H, W = _check_shape(shape)
    bounds, plan = _needed_bounds(model, (H, W), displacement)
    return _render_plan(model, (H, W), bounds, plan, samples=samples, device=device)


def _render_plan(model, shape, bounds, plan, *, samples=None, device=None):
    from kernels.speckle import render_speckle

    H, W = shape
    if not model.covers(*bounds):
        raise ValueError(
            f"the image shows material points in x [{bounds[0]:.1f}, {bounds[2]:.1f}], y [{bounds[1]:.1f}, "
            f"{bounds[3]:.1f}] px but the pattern only covers {tuple(round(v, 1) for v in model.region)}; "
            "build it with a larger region or margin (make_speckle(..., region=... or margin=...)) or use speckle_pair")
    s = model.samples if samples is None else samples
    dev_model = model.device_model(device)
    if plan is None:
        cov = render_speckle(dev_model, (H, W), samples=s, blur=model.blur)
    elif plan[0] == "shift":
        cov = render_speckle(dev_model, (H, W), samples=s, blur=model.blur, shift=plan[1])
    else:
        cov = render_speckle(dev_model, (H, W), samples=s, blur=model.blur, inverse_field=plan[1])
    return model.background + model.contrast * cov.astype(np.float64)


def deformed_image(model: BooleanSpeckle, shape, displacement=None, *, noise_sigma: float = 0.0,
                   poisson: bool = False, full_well: float = 20000.0, bits="model", seed=0,
                   device=None) -> np.ndarray:
    """Image (float32, (H, W)) of ``model`` deformed by ``displacement``, with noise and quantisation.

    ``displacement``: None, a constant ``(u, v)`` px, or a callable ``(x, y) -> (u, v)`` of reference
    coordinates. ``bits`` defaults to the model's. ``seed`` seeds the noise only (give each frame
    its own). See :func:`render` and :func:`add_noise`.
    """
    if not isinstance(model, BooleanSpeckle):
        raise ValueError(f"model must be a BooleanSpeckle (see make_speckle), got {type(model).__name__}")
    H, W = _check_shape(shape)
    bounds, plan = _needed_bounds(model, (H, W), displacement)
    clean = _render_plan(model, (H, W), bounds, plan, device=device)
    bits = model.bits if bits == "model" else bits
    return add_noise(clean, noise_sigma=noise_sigma, poisson=poisson, full_well=full_well, bits=bits, seed=seed)


def speckle_image(shape, *, radius: float = 2.0, density: float = 0.5, radius_spread: float = 0.2,
                  blur: float = 0.7, background: float | None = None, contrast: float | None = None,
                  noise_sigma: float = 0.0, poisson: bool = False, full_well: float = 20000.0,
                  bits: int | None = 8, samples: int = 4, seed=0, device=None) -> np.ndarray:
    """One speckle image (float32 grey levels, (H, W)); see :func:`make_speckle` and :func:`add_noise`."""
    H, W = _check_shape(shape)
    model = make_speckle((H, W), radius=radius, density=density, radius_spread=radius_spread, blur=blur,
                         background=background, contrast=contrast, bits=bits, samples=samples, seed=seed)
    return deformed_image(model, (H, W), None, noise_sigma=noise_sigma, poisson=poisson,
                          full_well=full_well, bits=bits, seed=_seed_entropy(seed, 1), device=device)


def _pair_model(shape, displacement, **pattern):
    """The speckle model covering a reference image and its deformed counterpart, with both render plans.

    ``pattern``: :func:`make_speckle`'s keywords (radius ... seed). Returns ``(model, ref_bounds,
    cur_bounds, cur_plan)``; the model's region holds every disk either image can see, plus 1 px.
    """
    probe = make_speckle(region=(0.0, 0.0, 1.0, 1.0), **pattern)
    ref_bounds, _ = _needed_bounds(probe, shape, None)
    cur_bounds, cur_plan = _needed_bounds(probe, shape, displacement)
    pad = 1.0
    region = (min(ref_bounds[0], cur_bounds[0]) - pad, min(ref_bounds[1], cur_bounds[1]) - pad,
              max(ref_bounds[2], cur_bounds[2]) + pad, max(ref_bounds[3], cur_bounds[3]) + pad)
    return make_speckle(region=region, **pattern), ref_bounds, cur_bounds, cur_plan


def speckle_pair(shape, displacement=None, *, radius: float = 2.0, density: float = 0.5,
                 radius_spread: float = 0.2, blur: float = 0.7, background: float | None = None,
                 contrast: float | None = None, noise_sigma: float = 0.0, poisson: bool = False,
                 full_well: float = 20000.0, bits: int | None = 8, samples: int = 4, seed=0,
                 device=None, return_model: bool = False):
    """A reference image and its deformed counterpart with exact ground truth.

    Parameters
    ----------
    shape : (H, W)
    displacement : None, (u, v) or callable
        None (a second, independently noisy image of the same pattern), a constant shift in px,
        or ``f(x, y) -> (u, v)`` evaluated on NumPy arrays of reference coordinates (px).
    radius, density, radius_spread, blur, background, contrast, samples :
        Pattern and imaging, see :func:`make_speckle`.
    noise_sigma, poisson, full_well, bits :
        Noise and quantisation, see :func:`add_noise`; the two images get independent noise.
    seed : int
        Seeds the disks and the noise (deterministic).
    return_model : bool
        Also return the :class:`BooleanSpeckle` (ground truth for anything else).

    Returns
    -------
    (reference, current) float32 (H, W) grey levels, plus the model when ``return_model``.
    """
    H, W = _check_shape(shape)
    model, ref_bounds, cur_bounds, cur_plan = _pair_model((H, W), displacement, radius=radius, density=density,
                                                          radius_spread=radius_spread, blur=blur, background=background,
                                                          contrast=contrast, bits=bits, samples=samples, seed=seed)
    noise = dict(noise_sigma=noise_sigma, poisson=poisson, full_well=full_well, bits=bits)
    reference = add_noise(_render_plan(model, (H, W), ref_bounds, None, device=device), seed=_seed_entropy(seed, 1), **noise)
    current = add_noise(_render_plan(model, (H, W), cur_bounds, cur_plan, device=device), seed=_seed_entropy(seed, 2), **noise)
    if return_model:
        return reference, current, model
    return reference, current


# ---------------------------------------------------------------------------------------------
# a specimen in front of a featureless background


def _specimen_inside(specimen) -> Callable:
    """``inside(x, y) -> bool array`` from a callable or an (K, 2) polygon of vertices (x, y) px."""
    if callable(specimen):
        def inside(x, y):
            out = np.asarray(specimen(x, y))
            if out.shape != x.shape:
                raise ValueError(f"specimen(x, y) must return a boolean array of x's shape {x.shape}, got {out.shape}")
            return out.astype(bool)
        return inside
    poly = np.asarray(specimen, dtype=np.float64)
    if poly.ndim != 2 or poly.shape[1] != 2 or poly.shape[0] < 3 or not np.all(np.isfinite(poly)):
        raise ValueError("specimen must be a callable inside(x, y) -> bool or an (K >= 3, 2) array of finite "
                         f"polygon vertices (x, y) in px; got {type(specimen).__name__} of shape {poly.shape}")

    def inside(x, y):  # even-odd crossing rule, vectorised over points, looped over the K edges
        result = np.zeros(x.shape, dtype=bool)
        xa, ya = poly[:, 0], poly[:, 1]
        xb, yb = np.roll(xa, -1), np.roll(ya, -1)
        for x0, y0, x1, y1 in zip(xa, ya, xb, yb):
            if y0 == y1:
                continue
            crosses = (y0 > y) != (y1 > y)
            x_cross = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
            result ^= crosses & (x < x_cross)
        return result
    return inside


def _occupancy(inside, shape, displacement, samples: int, blur: float) -> np.ndarray:
    """Fraction (H, W) of each pixel that shows the specimen: ``samples²`` sub-cells per pixel whose
    material points (``x = X + u(X)`` inverted) are tested with ``inside``, then the Gaussian PSF."""
    from scipy.ndimage import gaussian_filter

    H, W = shape
    sub = (np.arange(samples) + 0.5) / samples - 0.5
    xs = (np.arange(W)[:, None] + sub[None, :]).ravel()  # (W * samples,)
    ys = (np.arange(H)[:, None] + sub[None, :]).ravel()
    qx, qy = np.meshgrid(xs, ys)  # (H * samples, W * samples)
    if displacement is not None:
        if _is_constant(displacement):
            u, v = np.asarray(displacement, dtype=np.float64)
            qx, qy = qx - u, qy - v
        else:
            qx, qy = inverse_displacement(displacement, qx, qy)
    cells = inside(qx, qy).astype(np.float64)
    frac = cells.reshape(H, samples, W, samples).mean(axis=(1, 3))
    if blur > 0:
        frac = gaussian_filter(frac, blur, mode="nearest")
    return np.clip(frac, 0.0, 1.0)


def specimen_on_background(shape, displacement=None, *, specimen, background_level: float | None = None,
                           radius: float = 2.0, density: float = 0.5, radius_spread: float = 0.2,
                           blur: float = 0.7, background: float | None = None, contrast: float | None = None,
                           noise_sigma: float = 0.0, poisson: bool = False, full_well: float = 20000.0,
                           bits: int | None = 8, samples: int = 4, seed=0, device=None, behind=None):
    """A speckled specimen in front of a dark featureless background, reference and deformed.

    The specimen is the region ``specimen`` of the reference image (material coordinates); it
    carries the Boolean-model speckle of :func:`speckle_pair` and moves with ``displacement``.
    Everything else is a constant grey level ``background_level`` that does not move (a far,
    featureless background, as behind a specimen's edge in a stereo test). Both images then get
    the same camera noise and quantisation as :func:`add_noise` (independent streams).

    The edge is anti-aliased: each pixel's specimen fraction ``f`` is the share of its
    ``samples²`` sub-cells whose material point lies inside the specimen, blurred by the same
    Gaussian PSF (``blur`` px), and the pixel is ``f · speckle + (1 − f) · background_level``.
    The speckle itself is exact (Boolean model); the edge compositing is this approximation,
    applied identically to both images.

    Parameters
    ----------
    shape : (H, W)
    displacement : None, (u, v) or callable
        As in :func:`speckle_pair`: ``f(x, y) -> (u, v)`` px on reference coordinates; the ground
        truth at a specimen POI ``(x, y)`` is ``f(x, y)``.
    specimen : callable or (K, 2) array
        ``inside(x, y) -> bool array`` on reference coordinates (px), or the vertices ``(x, y)`` px
        of a polygon (even-odd rule; straight and slanted edges).
    background_level : float, optional
        Grey level of the featureless background; default 4 % of the full scale (10.2 in 8 bits).
    radius, density, radius_spread, blur, background, contrast, samples :
        Speckle and imaging of the specimen, see :func:`make_speckle` (``background`` there is the
        specimen's grey level between speckles).
    noise_sigma, poisson, full_well, bits, seed, device :
        As in :func:`speckle_pair`.
    behind : (H, W) array of grey levels, optional
        What is seen where the specimen is not, in both images (it does not move): e.g. a textured
        fixture seen through a hole. Default: the featureless ``background_level``.

    Returns
    -------
    reference, current : float32 (H, W) grey levels.
    specimen_fraction : float64 (H, W)
        The specimen fraction ``f`` of each reference pixel (1 on the specimen, 0 on the
        background).
    """
    H, W = _check_shape(shape)
    full = _full_scale(bits)
    background_level = 0.04 * full if background_level is None else background_level
    if not (isinstance(background_level, numbers.Real) and math.isfinite(background_level)):
        raise ValueError(f"background_level must be a finite grey level, got {background_level!r}")
    if not (isinstance(samples, numbers.Integral) and samples >= 1):
        raise ValueError(f"samples must be a positive integer, got {samples!r}")
    if not (isinstance(blur, numbers.Real) and blur >= 0 and math.isfinite(blur)):
        raise ValueError(f"blur must be >= 0 px, got {blur!r}")
    inside = _specimen_inside(specimen)
    model, ref_bounds, cur_bounds, cur_plan = _pair_model((H, W), displacement, radius=radius, density=density,
                                                          radius_spread=radius_spread, blur=blur, background=background,
                                                          contrast=contrast, bits=bits, samples=samples, seed=seed)
    ref_speckle = _render_plan(model, (H, W), ref_bounds, None, device=device)
    cur_speckle = _render_plan(model, (H, W), cur_bounds, cur_plan, device=device)
    ref_fraction = _occupancy(inside, (H, W), None, int(samples), float(blur))
    cur_fraction = _occupancy(inside, (H, W), displacement, int(samples), float(blur))
    bg = float(background_level)
    if behind is not None:
        bg = np.asarray(behind, dtype=np.float64)
        if bg.shape != (H, W) or not np.all(np.isfinite(bg)):
            raise ValueError(f"behind must be a finite (H, W) = {(H, W)} array of grey levels, got shape {bg.shape}")
    noise = dict(noise_sigma=noise_sigma, poisson=poisson, full_well=full_well, bits=bits)
    reference = add_noise(ref_fraction * ref_speckle + (1.0 - ref_fraction) * bg, seed=_seed_entropy(seed, 1), **noise)
    current = add_noise(cur_fraction * cur_speckle + (1.0 - cur_fraction) * bg, seed=_seed_entropy(seed, 2), **noise)
    return reference, current, ref_fraction


# ---------------------------------------------------------------------------------------------
# long sequences: a growing affine deformation of a speckle pattern whose speckles fade and appear


def _real(value, name: str, *, lo: float | None = None, hi: float | None = None, detail: str = "") -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise ValueError(f"{name} must be a finite number{detail}, got {value!r}")
    value = float(value)
    if lo is not None and not value > lo:
        raise ValueError(f"{name} must be > {lo}{detail}, got {value!r}")
    if hi is not None and not value < hi:
        raise ValueError(f"{name} must be < {hi}{detail}, got {value!r}")
    return value


class FrameIndexError(IndexError, ValueError):
    """A frame index outside a sequence (an ``IndexError`` for the sequence protocol, a ``ValueError`` too)."""


class EvolvingSequence:
    """A synthetic image sequence: a growing stretch of a speckle pattern whose speckles fade and appear.

    Made by :func:`evolving_sequence` (see there for the parameters). Frame ``k`` shows the material
    point ``X`` at ``x = X + u(X, k)``, with the exact affine displacement relative to frame 0

        ``u(X, Y, k) = a_k (X - cx) + tx_k``,  ``v(X, Y, k) = b_k (Y - cy) + ty_k``,

    ``a_k = stretch_final · t``, ``b_k = transverse_final · t``, ``(tx_k, ty_k) =
    translation_final · t``, ``t = k / (n_frames - 1)``, about the image centre ``(cx, cy) =
    ((W - 1) / 2, (H - 1) / 2)``. The pattern is a Boolean model (:func:`make_speckle`) whose disks
    live in material coordinates: from frame 1 on, each frame removes ``round(fade_fraction · M)``
    of its ``M`` alive disks (drawn at random) and adds as many new ones (uniform in the pattern's
    region, radii from the same distribution), so the density stays the same while the texture
    decorrelates from frame 0 (paint cracking, light drift). Frame ``k`` is rendered exactly from
    the disks alive at ``k`` (:meth:`alive`), never by interpolating another frame.

    Frames are rendered on demand (``seq[k]``, ``for image in seq``); nothing is cached but the
    disk pool (births and deaths of every disk that ever lives: about ``M (1 + fade_fraction ·
    n_frames)`` disks), so memory does not grow with the frames rendered. Rendering is
    deterministic: the same arguments give the same frames, in any order.

    Attributes
    ----------
    shape : (H, W)
    n_frames : int
    centre : (cx, cy) px
    pattern : BooleanSpeckle
        Every disk that is ever alive (``centres``, ``radii``) and the imaging parameters.
    born, dies : (P,) int32
        Disk ``i`` is alive in frames ``born[i] <= k < dies[i]`` (``dies = n_frames``: to the end).
    """

    def __init__(self, shape, n_frames, *, stretch_final, transverse_final, translation_final, fade_fraction,
                 pattern_kwargs, noise_sigma, poisson, full_well, seed, device):
        self.shape = _check_shape(shape)
        self.n_frames = positive_int(n_frames, "n_frames")
        self.stretch_final = _real(stretch_final, "stretch_final", lo=-0.5, detail=" (relative stretch along x)")
        self.transverse_final = _real(transverse_final, "transverse_final", lo=-0.5,
                                      detail=" (relative stretch along y)")
        try:
            tr = np.asarray(translation_final, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError):
            tr = np.zeros(0)
        if tr.shape != (2,) or not np.all(np.isfinite(tr)):
            raise ValueError(f"translation_final must be a finite (tx, ty) pair in px, got {translation_final!r}")
        self.translation_final = (float(tr[0]), float(tr[1]))
        self.fade_fraction = _real(fade_fraction, "fade_fraction", lo=None, detail=" (fraction of speckles "
                                   "replaced per frame, in [0, 1))")
        if not 0.0 <= self.fade_fraction < 1.0:
            raise ValueError(f"fade_fraction (fraction of speckles replaced per frame) must be in [0, 1), "
                             f"got {fade_fraction!r}")
        self.noise = dict(noise_sigma=noise_sigma, poisson=poisson, full_well=full_well)
        add_noise(np.zeros((1, 1)), bits=pattern_kwargs.get("bits", 8), **self.noise)  # validates the noise settings
        self.seed = seed
        _seed_entropy(seed)
        self.device = device
        H, W = self.shape
        self.centre = ((W - 1) / 2.0, (H - 1) / 2.0)
        probe = make_speckle(region=(0.0, 0.0, 1.0, 1.0), **pattern_kwargs, seed=seed)
        self._reach = 4 * probe.blur + 1.0
        lo = np.full(2, np.inf)
        hi = np.full(2, -np.inf)
        for k in (0, self.n_frames - 1):  # material points shown: extreme at the first and last frames
            b = self._bounds(k)
            lo = np.minimum(lo, b[:2])
            hi = np.maximum(hi, b[2:])
        margin = 4 * probe.blur + _DEFAULT_MARGIN
        region = (float(min(lo[0] - 1.0, -0.5 - margin)), float(min(lo[1] - 1.0, -0.5 - margin)),
                  float(max(hi[0] + 1.0, W - 0.5 + margin)), float(max(hi[1] + 1.0, H - 0.5 + margin)))
        base = make_speckle(region=region, **pattern_kwargs, seed=seed)
        self._pattern_kwargs = dict(pattern_kwargs)
        self._build_pool(base)

    # -- the disks
    def _build_pool(self, base: BooleanSpeckle) -> None:
        n0 = base.radii.size
        n_change = int(round(self.fade_fraction * n0))
        total = n0 + n_change * (self.n_frames - 1)
        centres = np.empty((total, 2))
        radii = np.empty(total)
        born = np.zeros(total, dtype=np.int32)
        dies = np.full(total, self.n_frames, dtype=np.int32)
        centres[:n0] = base.centres
        radii[:n0] = base.radii
        alive = np.arange(n0)
        rng = np.random.default_rng(_seed_entropy(self.seed, 7, 7))  # the renewal stream (not the tiles' streams)
        x0, y0, x1, y1 = base.region
        nxt = n0
        for k in range(1, self.n_frames):
            if n_change == 0:
                break
            slots = rng.choice(n0, size=n_change, replace=False)
            dies[alive[slots]] = k
            new = np.arange(nxt, nxt + n_change)
            centres[new, 0] = rng.uniform(x0, x1, n_change)
            centres[new, 1] = rng.uniform(y0, y1, n_change)
            radii[new] = _draw_radii(rng, n_change, base.radius, base.radius_spread)
            born[new] = k
            alive[slots] = new
            nxt += n_change
        self.pattern = BooleanSpeckle(
            centres=centres, radii=radii, region=base.region, background=base.background, contrast=base.contrast,
            blur=base.blur, samples=base.samples, bits=base.bits, radius=base.radius, density=base.density,
            radius_spread=base.radius_spread, seed=base.seed)
        self.born = born
        self.dies = dies
        self.n_changed_per_frame = n_change
        self._frame_model: tuple[int, BooleanSpeckle] | None = None

    def _index(self, k) -> int:
        if isinstance(k, bool) or not isinstance(k, (numbers.Integral,)):
            raise ValueError(f"frame index must be an integer, got {k!r}")
        k = int(k)
        if k < 0:
            k += self.n_frames
        if not 0 <= k < self.n_frames:
            raise FrameIndexError(f"frame index {k} out of range for a sequence of {self.n_frames} frames")
        return k

    def alive(self, k) -> np.ndarray:
        """Boolean mask over :attr:`pattern`'s disks: the speckles present in frame ``k``."""
        k = self._index(k)
        return (self.born <= k) & (self.dies > k)

    def model(self, k) -> BooleanSpeckle:
        """The Boolean model of frame ``k``: the disks alive then, in material (frame-0) coordinates."""
        k = self._index(k)
        if self._frame_model is not None and self._frame_model[0] == k:
            return self._frame_model[1]
        keep = self.alive(k)
        p = self.pattern
        m = BooleanSpeckle(centres=p.centres[keep], radii=p.radii[keep], region=p.region, background=p.background,
                           contrast=p.contrast, blur=p.blur, samples=p.samples, bits=p.bits, radius=p.radius,
                           density=p.density, radius_spread=p.radius_spread, seed=p.seed)
        self._frame_model = (k, m)  # one frame's device model at a time
        return m

    # -- the motion
    def parameters(self, k) -> tuple[float, float, float, float]:
        """``(a_k, b_k, tx_k, ty_k)``: stretch along x and y and translation of frame ``k``."""
        k = self._index(k)
        t = k / (self.n_frames - 1) if self.n_frames > 1 else 0.0
        return (self.stretch_final * t, self.transverse_final * t,
                self.translation_final[0] * t, self.translation_final[1] * t)

    def displacement(self, points, k, *, since: int = 0) -> np.ndarray:
        """Exact displacement (N, 2) px from frame ``since`` to frame ``k`` of the material points that
        sit at ``points`` (N, 2) ``(x, y)`` in frame ``since`` (default 0: reference coordinates).

        ``displacement(points, k)`` is the Lagrangian ground truth of a DIC run with frame 0 as
        reference; ``displacement(points_j, k, since=j)`` that of frame ``k`` tracked from frame ``j``.
        """
        from kernels.checks import as_points

        pts = as_points(points)
        X = self.to_reference(pts, since)
        return self.to_frame(X, k) - pts

    def to_reference(self, points, k) -> np.ndarray:
        """Material (frame-0) coordinates (N, 2) of the points ``(x, y)`` seen in frame ``k``."""
        a, b, tx, ty = self.parameters(k)
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        cx, cy = self.centre
        return np.stack([cx + (pts[:, 0] - cx - tx) / (1.0 + a), cy + (pts[:, 1] - cy - ty) / (1.0 + b)], axis=1)

    def to_frame(self, points, k) -> np.ndarray:
        """Positions (N, 2) in frame ``k`` of the material points ``(X, Y)`` (frame-0 coordinates)."""
        a, b, tx, ty = self.parameters(k)
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        cx, cy = self.centre
        return np.stack([cx + (1.0 + a) * (pts[:, 0] - cx) + tx, cy + (1.0 + b) * (pts[:, 1] - cy) + ty], axis=1)

    def field(self, k) -> Callable:
        """``f(x, y) -> (u, v)``: the displacement of frame ``k`` on reference coordinates (for :func:`render`)."""
        a, b, tx, ty = self.parameters(k)
        cx, cy = self.centre

        def u(x, y):
            return a * (np.asarray(x, np.float64) - cx) + tx, b * (np.asarray(y, np.float64) - cy) + ty
        return u

    def _bounds(self, k) -> np.ndarray:
        H, W = self.shape
        r = self._reach
        corners = np.array([[-r, -r], [W - 1 + r, -r], [-r, H - 1 + r], [W - 1 + r, H - 1 + r]])
        X = self.to_reference(corners, k)
        return np.concatenate([X.min(axis=0), X.max(axis=0)])

    def _plan(self, k):
        a, b, tx, ty = self.parameters(k)
        if a == 0.0 and b == 0.0:
            return None if tx == 0.0 and ty == 0.0 else ("shift", (tx, ty))
        H, W = self.shape
        m = int(math.ceil(4 * self.pattern.blur + 1.0)) + 3
        gx = np.arange(-m, W + m, dtype=np.float64)
        gy = np.arange(-m, H + m, dtype=np.float64)
        cx, cy = self.centre
        # the exact inverse: w(x) = x - X(x), separable (X depends on x only, Y on y only)
        wu = np.broadcast_to((gx - (cx + (gx - cx - tx) / (1.0 + a)))[None, :], (gy.size, gx.size))
        wv = np.broadcast_to((gy - (cy + (gy - cy - ty) / (1.0 + b)))[:, None], (gy.size, gx.size))
        return ("field", (wu, wv, (float(-m), float(-m)), 1.0))

    # -- the frames
    def render(self, k) -> np.ndarray:
        """Noise-free grey levels (float64, (H, W)) of frame ``k``."""
        k = self._index(k)
        b = self._bounds(k)
        return _render_plan(self.model(k), self.shape, tuple(b), self._plan(k), device=self.device)

    def frame(self, k) -> np.ndarray:
        """Frame ``k`` (float32 (H, W) grey levels, with the sequence's noise and quantisation).

        Frame ``k``'s noise stream is seeded by ``(seed, 1 + k)``: frame 0 is the image of
        :func:`speckle_image` with the same pattern, noise and seed.
        """
        k = self._index(k)
        return add_noise(self.render(k), bits=self.pattern.bits, seed=_seed_entropy(self.seed, 1 + k), **self.noise)

    def __len__(self) -> int:
        return self.n_frames

    def __getitem__(self, k) -> np.ndarray:
        return self.frame(k)

    def __iter__(self):
        for k in range(self.n_frames):
            yield self.frame(k)

    def changed_fraction(self, k) -> float:
        """Fraction of frame ``k - 1``'s speckles that are gone in frame ``k`` (0 for frame 0)."""
        k = self._index(k)
        if k == 0:
            return 0.0
        before = self.alive(k - 1)
        return float(np.count_nonzero(before & ~self.alive(k)) / max(1, np.count_nonzero(before)))

    def __repr__(self) -> str:
        H, W = self.shape
        return (f"EvolvingSequence({H}x{W} px, {self.n_frames} frames, stretch {self.stretch_final:g} x / "
                f"{self.transverse_final:g} y, translation {self.translation_final}, "
                f"{self.fade_fraction:g} of the speckles replaced per frame, seed {self.seed!r})")


def evolving_sequence(shape, n_frames: int, *, stretch_final: float = 0.30, transverse_final: float = 0.0,
                      translation_final=(0.0, 0.0), fade_fraction: float = 0.002, radius: float = 2.0,
                      density: float = 0.5, radius_spread: float = 0.2, blur: float = 0.7,
                      background: float | None = None, contrast: float | None = None, noise_sigma: float = 0.0,
                      poisson: bool = False, full_well: float = 20000.0, bits: int | None = 8, samples: int = 4,
                      seed=0, device=None) -> EvolvingSequence:
    """A long synthetic sequence with exact ground truth: a growing stretch and an evolving texture.

    Frame ``k`` (``0 <= k < n_frames``) shows the speckle pattern stretched about the image centre by
    ``stretch_final · k / (n_frames - 1)`` along x (and ``transverse_final · ...`` along y) and
    translated by ``translation_final · k / (n_frames - 1)`` px, so the deformation grows linearly
    to its final value at the last frame; and from one frame to the next a fraction
    ``fade_fraction`` of the speckles disappears and as many new ones appear (the texture
    decorrelates from the reference, as when paint cracks and the light drifts). See
    :class:`EvolvingSequence` for the exact displacement and the disk bookkeeping.

    Parameters
    ----------
    shape : (H, W)
    n_frames : int >= 1
    stretch_final, transverse_final : float > -0.5
        Relative stretch along x and y at the last frame (0.30: 30 %).
    translation_final : (tx, ty) px
        Rigid translation at the last frame.
    fade_fraction : float in [0, 1)
        Fraction of the speckles replaced from each frame to the next (0: a fixed texture).
    radius, density, radius_spread, blur, background, contrast, bits, samples :
        The pattern and the imaging, see :func:`make_speckle`.
    noise_sigma, poisson, full_well :
        Camera noise of every frame, see :func:`add_noise`; each frame has its own noise stream.
    seed : int
        Seeds the disks (frame 0 has the disks of ``make_speckle(..., seed=seed)``), their renewal
        and the noise.
    device : Warp device for rendering.

    Returns
    -------
    EvolvingSequence
        A lazy sequence of float32 (H, W) frames (``len``, ``seq[k]``, iteration) with the ground
        truth: ``seq.displacement(points, k, since=0)``, ``seq.alive(k)``, ``seq.changed_fraction(k)``.
        With the same pattern, noise and seed, frame 0 equals :func:`speckle_image`.
    """
    pattern = dict(radius=radius, density=density, radius_spread=radius_spread, blur=blur, background=background,
                   contrast=contrast, bits=bits, samples=samples)
    return EvolvingSequence(shape, n_frames, stretch_final=stretch_final, transverse_final=transverse_final,
                            translation_final=translation_final, fade_fraction=fade_fraction, pattern_kwargs=pattern,
                            noise_sigma=noise_sigma, poisson=poisson, full_well=full_well, seed=seed, device=device)
