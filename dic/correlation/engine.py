"""The correlation engine: IC-GN of one reference image's POIs into current images.

Everything that correlates subsets goes through here: 2-D tracking (:class:`dic.Tracker`),
the stereo match left -> right and the temporal tracks of stereo DIC
(:class:`dic.StereoCorrelation`).

* :class:`Correlator` holds a reference image, its POIs and the per-POI reference quantities
  (B-spline gradients, IC-GN Hessians; :func:`kernels.icgn.prepare_subsets`), computed once, and
  runs IC-GN (:func:`kernels.icgn.icgn`) for all or some POIs from given initial guesses.
* :func:`correlate` runs IC-GN from the guesses of an initial-guess strategy, then spreads
  accepted results to their neighbours (propagation), asks a fallback strategy for guesses of
  isolated POIs, and gives suspicious results a second opinion (:mod:`.acceptance`).
* :func:`reliability_guided` is the reliability-guided propagation of Pan (2009): seeds found by a
  ZNCC search, then neighbours in decreasing-ZNCC order.

Initial guesses come from :mod:`.guesses`; acceptance rules (status, ZNCC, second opinion,
implausible warps) from :mod:`.acceptance`.
"""
from __future__ import annotations

import heapq
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np
import warp as wp

from kernels.conventions import Status
from kernels.frames import FrameTracker
from kernels.icgn import (
    CurrentImage,
    IcgnResult,
    gather_subsets,
    icgn,
    n_params,
    prepare_current,
    prepare_reference,
    prepare_subsets,
    subset_buffers,
    subset_rows,
    subsets_window,
)

from .acceptance import GOOD, accepted_mask, flag_implausible, second_opinion_candidates
from .params import convert_order, extrapolate

__all__ = ["Correlator", "CorrelationResult", "correlate", "reliability_guided", "spread", "check_robust",
           "ADAPTIVE", "SOURCE_NONE", "SOURCE_FEATURES", "SOURCE_NEIGHBOUR", "SOURCE_SEARCH", "SOURCE_PREVIOUS",
           "SOURCE_GLOBAL"]

#: the ``robust`` value that refines only the subsets whose plain residuals show outliers (the 2-D default)
ADAPTIVE = "adaptive"

_HOST_POOL = None


def _host_pool():
    """One background thread for host work started ahead of its use (:meth:`Correlator.prefetch_textured_fraction`)."""
    global _HOST_POOL
    if _HOST_POOL is None:
        from concurrent.futures import ThreadPoolExecutor

        _HOST_POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="specula-host")
    return _HOST_POOL


#: adaptive robust IC-GN leaves alone the subsets of which less than this fraction carries texture
#: (:meth:`Correlator.textured_fraction`; the ``partial_below`` of
#: :func:`dic.correlation.plausibility.implausible_warps`): their residual comes from the featureless part (a
#: background, a hole), which pixel masks handle, not from a texture that changed. Measured on the virtual-lab
#: renders of bench/stereo.py rates: every subset the residual test flagged there (82 of 15 876, order 1) was such
#: a partial subset along the specimen's edge, each refused as IMPLAUSIBLE_WARP with or without the refinement, and
#: their 30 weighted iterations cost a quarter of the frame's plain IC-GN time
ADAPTIVE_MIN_TEXTURED = 0.8


def check_robust(robust, name: str = "robust"):
    """``robust`` checked: ``False`` (plain IC-GN), ``True`` (every accepted POI refined by Tukey-weighted
    IC-GN) or ``"adaptive"`` (only the POIs whose plain residuals show outliers,
    :func:`kernels.icgn_robust.residual_outliers`; the others keep the plain result bit for bit)."""
    if isinstance(robust, (bool, np.bool_)):
        return bool(robust)
    if isinstance(robust, str) and robust == ADAPTIVE:
        return ADAPTIVE
    raise ValueError(f"{name} must be True or False, or 'adaptive' (robust IC-GN only where a subset's residuals "
                     f"show outliers), got {robust!r}")

#: where a POI's accepted initial guess came from (``guess_source`` in stereo results)
SOURCE_NONE, SOURCE_FEATURES, SOURCE_NEIGHBOUR, SOURCE_SEARCH, SOURCE_PREVIOUS, SOURCE_GLOBAL = -1, 0, 1, 2, 3, 4


class Correlator:
    """IC-GN of one reference image's POIs into current images; reference quantities computed once.

    Parameters
    ----------
    reference : (H, W) float32 grey image (validated by the caller).
    points : (N, 2) float64 POIs ``(x, y)`` px.
    subset : odd int (px); order : 1 or 2.
    max_iter : int; tol : float (px) - IC-GN limits (:func:`kernels.icgn.icgn`).
    flat_std : float, optional - grey-level std below which a subset is FLAT_SUBSET.
    device : resolved device string.
    pixel_mask : (N, subset**2) bool, optional - the pixels each subset keeps
        (:func:`dic.correlation.subset_masks.subset_pixel_masks`): IC-GN over those only
        (:mod:`kernels.icgn_masked`); None: every pixel.
    min_kept_fraction : float in (0, 1], optional - with ``pixel_mask``, the fraction of its pixels a subset
        must keep (else TOO_FEW_PIXELS; default :data:`kernels.icgn_masked.DEFAULT_MIN_KEPT_FRACTION`).
    active : (N,) bool, optional - the POIs that may be correlated (e.g. a grid's points in the region); the
        others are not prepared (status NOT_COMPUTED, never ready: :func:`kernels.icgn.prepare_subsets`), the
        prepared ones bit for bit as without it. Without a ``pixel_mask`` only (masked subsets prepare every POI).
    """

    def __init__(self, reference: np.ndarray, points: np.ndarray, *, subset: int, order: int, max_iter: int,
                 tol: float, device: str, flat_std: float | None = None, pixel_mask: np.ndarray | None = None,
                 min_kept_fraction: float | None = None, active: np.ndarray | None = None):
        self.image = reference
        self.points = points
        self.subset, self.order, self.device = subset, order, device
        self.max_iter, self.tol, self.flat_std = max_iter, tol, flat_std
        self.pixel_mask = None if pixel_mask is None else np.asarray(pixel_mask, dtype=bool)
        # with active POIs (a region of a grid over the image), the reference gradients where their subsets lie only
        window = None if active is None or pixel_mask is not None else subsets_window(points, subset, active)
        self.reference = prepare_reference(reference, device=device, window=window)
        if self.pixel_mask is None:
            self.subsets = prepare_subsets(self.reference, points, subset=subset, order=order, flat_std=flat_std,
                                           active=active)
        else:
            from kernels.icgn_masked import DEFAULT_MIN_KEPT_FRACTION, prepare_subsets_masked

            self.subsets = prepare_subsets_masked(
                self.reference, points, subset=subset, order=order, flat_std=flat_std, pixel_mask=self.pixel_mask,
                min_kept_fraction=DEFAULT_MIN_KEPT_FRACTION if min_kept_fraction is None else min_kept_fraction)
        self.reference_status = self.subsets.status.numpy().astype(np.int32)
        self._out = None
        self._frames = {}  # device-resident frame trackers by frame dtype (run_frame)
        self._frame_subsets = None  # run_frame's subsets when limited to some POIs (limit_frames)
        self._frame_active = None  # the POIs run_frame correlates when limited (limit_frames); None: all
        self._frame_index = None  # limited: the POIs its launch covers (ready and active), in order
        self._frame_status = None  # limited: the statuses of the others (reference status, NOT_COMPUTED if not active)
        self._textured = None
        self._textured_future = None  # prefetch_textured_fraction's computation, until it is read
        self._indexed = None  # buffers of run(): allocated once, on first use
        self._spacing = None
        self._rg = None  # device state of the reliability-guided waves (per neighbour radius)
        self._robust = None  # buffers of refine_robust(): guesses, active flags, results
        self._noise = None  # per-subset roughness and std of the reference (adaptive refine_robust)
        #: per-reference work of initial-guess strategies, kept across frames (e.g. the reference
        #: pyramid and its level correlators of the "pyramid" guess)
        self.cache: dict = {}

    @property
    def n_points(self) -> int:
        return int(self.points.shape[0])

    @property
    def ready(self) -> np.ndarray:
        """(N,) bool: the reference subset is trackable (inside the image, textured, regular)."""
        return self.reference_status == int(Status.CONVERGED)

    def textured_fraction(self) -> np.ndarray:
        """(N,) fraction of each reference subset's pixels that carry texture (computed once); with a
        ``pixel_mask``, the fraction of its kept pixels (the pixels it is correlated on)."""
        if self._textured is None:
            future, self._textured_future = self._textured_future, None
            self._textured = future.result() if future is not None else self._compute_textured()
        return self._textured

    def prefetch_textured_fraction(self) -> None:
        """Start :meth:`textured_fraction` on a background thread, to overlap it with the work that comes before it
        is needed (the stereo match, the first state); :meth:`textured_fraction` then waits for it. The same values:
        host work (NumPy, OpenCV) on this correlator's reference image, which nothing changes."""
        if self._textured is None and self._textured_future is None:
            self._textured_future = _host_pool().submit(self._compute_textured)

    def _compute_textured(self) -> np.ndarray:
        if self.pixel_mask is None:
            from .plausibility import textured_fraction

            return textured_fraction(self.image, self.points, self.subset)
        from .subset_masks import kept_textured_fraction

        return kept_textured_fraction(self.image, self.points, self.subset, self.pixel_mask)

    def run_all(self, current, guess: np.ndarray) -> dict:
        """IC-GN of every POI from ``guess`` (N, k); returns host arrays (copies) of the results.

        The result buffers are reused from call to call (no allocation per frame).
        """
        res = icgn(self.subsets, current, guess=guess, max_iter=self.max_iter, tol=self.tol, out=self._out)
        self._out = res
        return res.numpy()

    def run_frame(self, frame, guess: np.ndarray, name: str = "current") -> dict:
        """IC-GN of every POI into a raw frame through the device-resident path (:class:`kernels.frames.FrameTracker`).

        ``frame``: a 2-D uint8, uint16 or float32 array of the reference's shape (NumPy, ``wp.array`` or torch
        tensor on this device), converted and checked (NaN/inf: ``ValueError`` naming ``name``) on the device;
        no buffer is allocated after the first frame of each dtype. Host arrays (copies) as :meth:`run_all`,
        bit for bit those of ``run_all(prepare_current(frame), guess)``.
        """
        dt = np.dtype(frame.dtype) if isinstance(frame, np.ndarray) else None
        if dt is None:
            raise ValueError(f"{name} must be a NumPy array here, got {type(frame).__name__}")
        idx = self._frame_index
        if idx is not None:  # limited (limit_frames): the launch over the POIs it correlates only
            g = np.asarray(guess, dtype=np.float64)
            if g.shape != (self.n_points, n_params(self.order)):
                raise ValueError(f"guess must have shape {(self.n_points, n_params(self.order))} (one row of "
                                 f"parameters per POI), got {g.shape}")
            if not np.all(np.isfinite(g)):
                raise ValueError("guess contains NaN or infinite values; give a finite guess")
            # what a launch over every POI returns at one it skips: the guess (float32), no ZNCC, no iteration
            out = {"params": g.astype(np.float32), "zncc": np.full(self.n_points, np.nan, dtype=np.float32),
                   "iterations": np.zeros(self.n_points, dtype=np.int32), "status": self._frame_status.copy()}
            tracker = self._frames.get(dt)
            if tracker is None:
                tracker = self._frames[dt] = FrameTracker(self._frame_subsets, dt, max_iter=self.max_iter,
                                                          tol=self.tol)
            r = tracker.track(frame, guess=g[idx], name=name)
            for key in out:
                out[key][idx] = r[key]
            return out
        tracker = self._frames.get(dt)
        if tracker is None:
            subsets = self.subsets if self._frame_subsets is None else self._frame_subsets
            tracker = self._frames[dt] = FrameTracker(subsets, dt, max_iter=self.max_iter, tol=self.tol)
        return tracker.track(frame, guess=guess, name=name)

    def limit_frames(self, active: np.ndarray) -> None:
        """Let :meth:`run_frame` correlate the POIs ``active`` (N,) bool only; the others come back
        ``NOT_COMPUTED`` after no iteration (their reference subsets stay ready for :meth:`run`).

        For a caller that uses the first pass at some POIs only (the stereo tracks: the matched POIs): the
        others cost nothing, and each active POI's result is bit for bit the one of the unrestricted launch
        (one thread per POI). The rows of the POIs it correlates (active and ready) are gathered once
        (:func:`kernels.icgn.gather_subsets`) and the launch covers those only, so a region of a grid over the
        whole image spreads its work evenly over the threads; the others come back as the unrestricted launch
        returns them (their guess, no ZNCC, no iteration, NOT_COMPUTED or their reference status). The frame
        trackers are built again on the next :meth:`run_frame` (not when the same POIs are given again)."""
        active = np.asarray(active, dtype=bool)
        if active.shape != (self.n_points,):
            raise ValueError(f"active must be an ({self.n_points},) bool array, got shape {active.shape}")
        same = self._frame_active is None if active.all() else (self._frame_active is not None
                                                                 and np.array_equal(active, self._frame_active))
        if same:  # these POIs already (a sequence: every state): the trackers and their buffers are kept
            return
        self._frames = {}
        self._frame_active = self._frame_subsets = self._frame_index = self._frame_status = None
        if active.all():
            return
        self._frame_active = active.copy()
        status = self.reference_status.copy()
        status[~active & (status == int(Status.CONVERGED))] = int(Status.NOT_COMPUTED)
        idx = np.flatnonzero(status == int(Status.CONVERGED))
        if idx.size:
            # the launch over the correlated POIs only (their rows gathered once: a grid over an image of which a
            # region is correlated would otherwise spread its work unevenly over the threads' chunks)
            self._frame_index, self._frame_status = idx, status
            self._frame_subsets = gather_subsets(self.subsets, wp.array(idx.astype(np.int32), dtype=wp.int32,
                                                                        device=self.device),
                                                 int(idx.size), subset_buffers(self.subsets, int(idx.size)),
                                                 points=self.points[idx])
        else:  # none: a launch that correlates nothing but still prepares the frame (frame_current)
            self._frame_subsets = replace(self.subsets, status=wp.array(status, dtype=wp.int32, device=self.device))

    def frame_current(self, frame_dtype) -> CurrentImage:
        """The prepared last frame of :meth:`run_frame` for ``frame_dtype`` (a view of its tracker's buffers)."""
        tracker = self._frames.get(np.dtype(frame_dtype))
        if tracker is None:
            raise ValueError(f"no frame of dtype {np.dtype(frame_dtype)} was tracked with run_frame()")
        return tracker.current()

    def refine_robust(self, current, r: dict, *, adaptive: bool = False) -> dict:
        """Refine the accepted POIs of a result ``r`` (host arrays as :meth:`run_all`) with Tukey-weighted IC-GN.

        :func:`kernels.icgn_robust.icgn_robust` starts from ``r["params"]`` at the POIs whose status is
        CONVERGED or MAX_ITERATIONS (the others keep their result) and discounts the subset pixels whose
        residual the reference texture cannot explain (speckles that changed). ``current``: the current image
        (a :class:`kernels.icgn.CurrentImage` or a grey image). Returns a new dict: ``params``, ``zncc``
        (unweighted, at the refined warp), ``iterations`` (plain + weighted), ``status`` of the refined POIs
        replaced, ``inliers`` (N,) float32, the weighted fraction of each refined subset, and ``outliers`` (N,) float32, its
        number of pixels given zero weight (both NaN elsewhere), and ``robust_flagged`` (N,) bool, the POIs refined.
        One upload of the guesses, one launch, one copy back; the buffers are allocated once.

        ``adaptive``: refine only the POIs whose residuals at the plain warp show outliers: among those whose
        plain RMS residual (from the ZNCC) exceeds both ``RMS_GATE`` x the subset's grey-level std and
        ``NOISE_GATE`` x sqrt(2) x its fine-scale roughness (:func:`kernels.icgn_robust.reference_noise`, once per
        reference), the ones :func:`kernels.icgn_robust.residual_outliers` flags (kurtosis above ``KURTOSIS_MAX``,
        then a compact blob: the box statistic above ``BOX_MAX``); the others keep every entry of ``r`` bit for bit
        (no refinement is launched when none is flagged).
        """
        from kernels import icgn_robust as robust_module
        from kernels.icgn_robust import icgn_robust, residual_outliers, robust_result

        cur = self._current(current)
        n, k = self.n_points, n_params(self.order)
        status = np.asarray(r["status"])
        active = (status == int(Status.CONVERGED)) | (status == int(Status.MAX_ITERATIONS))
        if self.pixel_mask is not None:  # the robust kernel reads whole subsets: masked ones keep their masked result
            active &= self.pixel_mask.all(axis=1)
        if self._robust is None:
            self._robust = (wp.empty((n, k), dtype=wp.float32, device=self.device),
                            wp.empty(n, dtype=wp.int32, device=self.device), robust_result(n, k, self.device))
        guess, act, out = self._robust
        _upload(guess, np.asarray(r["params"], dtype=np.float32))
        if adaptive and np.any(active):
            # the residual test, on the subsets whose plain RMS residual is a good part of their contrast
            ratio = self._plain_rms_ratio(np.asarray(r["zncc"], np.float64))
            noise, std = self._reference_noise()
            with np.errstate(invalid="ignore"):
                active &= (ratio > robust_module.RMS_GATE) & (ratio * std > robust_module.NOISE_GATE * np.sqrt(2.0) * noise)
            if np.any(active):  # partly featureless subsets: left to the implausible-warp check and pixel masks
                active &= self.textured_fraction() >= ADAPTIVE_MIN_TEXTURED
            if np.any(active):
                _upload(act, active.astype(np.int32))
                active &= residual_outliers(self.subsets, cur, guess, act,
                                            kurtosis_max=robust_module.KURTOSIS_MAX).flagged
        if not np.any(active):
            refined = dict(r)
            refined["inliers"] = np.full(n, np.nan, dtype=np.float32)
            refined["outliers"] = np.full(n, np.nan, dtype=np.float32)
            refined["robust_flagged"] = active
            return refined
        _upload(act, active.astype(np.int32))
        res = icgn_robust(self.subsets, cur, guess, act, max_iter=self.max_iter, tol=self.tol, out=out).numpy()
        refined = dict(r)
        for key in ("params", "zncc", "status"):
            a = np.array(r[key], copy=True)
            a[active] = res[key][active]
            refined[key] = a
        refined["iterations"] = np.where(active, np.asarray(r["iterations"]) + res["iterations"],
                                         np.asarray(r["iterations"])).astype(np.int32)
        refined["inliers"] = np.where(active, res["inliers"], np.float32(np.nan)).astype(np.float32)
        refined["outliers"] = np.where(active, res["outliers"], np.float32(np.nan)).astype(np.float32)
        refined["robust_flagged"] = active
        return refined

    def _reference_noise(self) -> tuple[np.ndarray, np.ndarray]:
        """(N,) fine-scale roughness and grey-level std of each reference subset
        (:func:`kernels.icgn_robust.reference_noise`; computed once per reference)."""
        if self._noise is None:
            from kernels.icgn_robust import reference_noise

            self._noise = reference_noise(self.image, self.subsets.table.centres.numpy(), self.subset)
        return self._noise

    def _plain_rms_ratio(self, zncc: np.ndarray) -> np.ndarray:
        """(N,) RMS residual of the least-squares intensity fit of each subset at a plain IC-GN result of ZNCC
        ``zncc``, over the reference subset's grey-level std: ``sqrt((1 - C^2) n / (n - 2))``."""
        npx = self.subset * self.subset
        with np.errstate(invalid="ignore"):
            return np.sqrt(np.clip(1.0 - zncc * zncc, 0.0, None) * npx / (npx - 2))

    def run_device(self, current, guess) -> IcgnResult:
        """IC-GN of every POI; the results stay on the device (:class:`kernels.icgn.IcgnResult`).

        The result buffers are reused by the next call (copy what you keep).
        """
        res = icgn(self.subsets, current, guess=guess, max_iter=self.max_iter, tol=self.tol, out=self._out)
        self._out = res
        return res

    def median_spacing(self) -> float:
        """Median distance of a POI to its nearest neighbour (px; computed once), 1 for a single POI."""
        if self._spacing is None:
            from scipy.spatial import cKDTree

            p = self.points
            self._spacing = float(np.median(cKDTree(p).query(p, k=2)[0][:, 1])) if p.shape[0] > 1 else 1.0
        return self._spacing

    def check_indices(self, idx) -> np.ndarray:
        """``idx`` as a 1-D int64 array of distinct POI indices in ``[0, N)``; ValueError otherwise."""
        a = np.asarray(idx)
        if a.ndim != 1 or not (a.size == 0 or np.issubdtype(a.dtype, np.integer)):
            raise ValueError(f"idx must be a 1-D array of integer POI indices, got shape {a.shape} dtype {a.dtype}")
        a = a.astype(np.int64)
        n = self.n_points
        if a.size and (a.min() < 0 or a.max() >= n):
            raise ValueError(f"idx must hold POI indices in [0, {n}), got values in [{a.min()}, {a.max()}]")
        if a.size > 1 and np.unique(a).size != a.size:
            raise ValueError("idx must hold distinct POI indices (each POI at most once per run)")
        return a

    def _buffers(self) -> _IndexedBuffers:
        if self._indexed is None:
            n, k, dev = self.n_points, n_params(self.order), self.device
            self._indexed = _IndexedBuffers(wp.empty(n, dtype=wp.int32, device=dev), subset_buffers(self.subsets),
                                            wp.empty((n, k), dtype=wp.float32, device=dev), _result(n, k, dev))
        return self._indexed

    def _current(self, current) -> CurrentImage:
        return current if isinstance(current, CurrentImage) else prepare_current(current, device=self.device)

    def run(self, current, idx: np.ndarray, guess: np.ndarray) -> dict:
        """IC-GN of the POIs ``idx`` (M,) from ``guess`` (M, k); host arrays (copies) of the M results.

        Indexed IC-GN: the POIs' reference quantities, prepared once, are gathered on the device
        (:func:`kernels.icgn.gather_subsets`), not prepared again, and IC-GN runs over them; each POI's
        result is bitwise what :meth:`run_all` gives it from the same guess. The device buffers are
        allocated on the first call; per call the indices and guesses go up (two copies), two launches
        run, and the M results come back.
        """
        idx = self.check_indices(idx)
        k = n_params(self.order)
        g = np.asarray(guess, dtype=np.float64)
        if g.shape != (idx.size, k):
            raise ValueError(f"guess must have shape {(idx.size, k)} (one row per index), got {g.shape}")
        if not np.all(np.isfinite(g)):
            raise ValueError("guess contains NaN or infinite values; give a finite guess or leave those POIs out")
        m = idx.size
        if m == 0:
            return {"params": np.zeros((0, k), np.float32), "zncc": np.zeros(0, np.float32),
                    "iterations": np.zeros(0, np.int32), "status": np.zeros(0, np.int32)}
        cur = self._current(current)
        b = self._buffers()
        _upload(b.guess[:m], g.astype(np.float32))
        if m == self.n_points and np.array_equal(idx, np.arange(m)):
            sub = self.subsets  # every POI in order: nothing to gather
        else:
            _upload(b.idx[:m], idx.astype(np.int32))
            sub = gather_subsets(self.subsets, b.idx, m, b.subsets, points=self.points[idx])
        res = icgn(sub, cur, guess=b.guess[:m], max_iter=self.max_iter, tol=self.tol, out=_rows(b.out, m))
        return res.numpy()  # host copies the caller owns (kernels._device.host_copy)


@dataclass
class _IndexedBuffers:
    """Device buffers of :meth:`Correlator.run` (N rows each, allocated once)."""

    idx: wp.array
    subsets: object  # kernels.icgn.ReferenceSubsets from subset_buffers()
    guess: wp.array
    out: IcgnResult


def _result(n: int, k: int, device: str) -> IcgnResult:
    return IcgnResult(wp.empty((n, k), dtype=wp.float32, device=device), wp.empty(n, dtype=wp.float32, device=device),
                      wp.empty(n, dtype=wp.int32, device=device), wp.empty(n, dtype=wp.int32, device=device))


def _rows(res: IcgnResult, m: int) -> IcgnResult:
    """The first ``m`` rows of ``res`` (views)."""
    return IcgnResult(res.params[:m], res.zncc[:m], res.iterations[:m], res.status[:m])


def _upload(dst: wp.array, host: np.ndarray) -> None:
    """Copy a host array into a device array (a view of a preallocated buffer) without allocating."""
    wp.copy(dst, wp.array(np.ascontiguousarray(host), dtype=dst.dtype, device="cpu", copy=False))


@dataclass
class CorrelationResult:
    """Per-POI outcome of :func:`correlate` (the best attempt per POI).

    params (N, k) float64 (NaN where never run); zncc (N,) float64; iterations (N,) int32;
    icgn_status (N,) int32 :class:`kernels.conventions.Status` (NOT_COMPUTED where never run);
    accepted (N,) bool; source (N,) int8 (``SOURCE_*``); extra_failed (N,) bool (converged with a
    good ZNCC but rejected by the caller's extra check, e.g. the epipolar constraint);
    implausible (N,) bool (converged with a good ZNCC to an implausible warp; not accepted);
    robust_flagged (N,) bool (refined by robust IC-GN: every accepted POI with ``robust=True``, those whose
    residuals showed outliers with ``"adaptive"``).
    """

    params: np.ndarray
    zncc: np.ndarray
    iterations: np.ndarray
    icgn_status: np.ndarray
    accepted: np.ndarray
    source: np.ndarray
    extra_failed: np.ndarray
    implausible: np.ndarray
    robust_flagged: np.ndarray | None = None


def spread(points: np.ndarray, candidates: np.ndarray, max_count: int) -> np.ndarray:
    """Up to ``max_count`` of the candidate indices, spread over the image (one per grid cell)."""
    if candidates.size <= max_count:
        return candidates
    P = points[candidates]
    lo, hi = P.min(axis=0), P.max(axis=0)
    cells = int(np.ceil(np.sqrt(max_count)))
    span = np.maximum(hi - lo, 1e-9)
    cell = np.minimum((cells * (P - lo) / span).astype(int), cells - 1)
    key = cell[:, 1] * cells + cell[:, 0]
    _, first = np.unique(key, return_index=True)
    chosen = candidates[np.sort(first)]
    return chosen[:max_count]


def correlate(corr: Correlator, current, guess: np.ndarray, has_guess: np.ndarray, initial_source: int, *,
              eligible: np.ndarray, zncc_min: float, radius: float, extra: Callable | None = None,
              fallback: Callable | None = None, max_attempts: int = 3, max_seeds: int = 64,
              max_fallback_rounds: int = 8, min_fallback: int = 1, zncc_drop: float = 0.05,
              second_opinion: bool = True, check_warps: bool = True, robust: bool | str = False,
              first: dict | None = None, report: Callable[[str, int, int], None] | None = None,
              max_fruitless_rounds: int | None = None) -> CorrelationResult:
    """IC-GN of every eligible POI from the given guesses, then neighbour propagation and a fallback.

    Parameters
    ----------
    corr : the reference side; current : a prepared current image (:func:`kernels.icgn.prepare_current`).
    guess : (N, k) initial parameters; has_guess : (N,) bool, rows of ``guess`` to start from.
    initial_source : ``SOURCE_*`` code recorded for POIs accepted from ``guess``.
    eligible : (N,) bool - POIs to correlate (further restricted to ``corr.ready``).
    zncc_min : acceptance threshold; radius : px, reach of the neighbour propagation.
    extra : ``extra(idx, params) -> (m,) bool`` - an additional acceptance test (the epipolar check).
    fallback : ``fallback(idx) -> (guess (m, k), ok (m,))`` - guesses for isolated POIs (an
        initial-guess strategy of :mod:`.guesses`); called only while at least ``min_fallback``
        eligible POIs are unresolved and untried.
    second_opinion : retry an accepted POI whose ZNCC is more than ``zncc_drop`` below the median
        of its accepted neighbours from its best neighbour; the better-correlating result is kept.
    check_warps : un-accept POIs whose warp is implausible (:func:`.acceptance.flag_implausible`);
        they are marked in ``CorrelationResult.implausible``.
    robust : False, True or ``"adaptive"`` (:func:`check_robust`): refine the accepted POIs (``"adaptive"``:
        those whose plain residuals show outliers) with outlier-robust IC-GN (:meth:`Correlator.refine_robust`)
        before the warp check; a refined POI stays accepted only if it still converges with a ZNCC of at least
        ``zncc_min`` and passes ``extra``; the others keep their plain result bit for bit.
    first : optional host results of IC-GN over every POI from ``guess`` (``params`` (N, k), ``zncc``,
        ``iterations``, ``status`` (N,); :meth:`Correlator.run_frame` or :meth:`Correlator.run_all`): the
        first pass, taken at the POIs it would run (``has_guess & eligible``) instead of running them again
        (each POI's result is bitwise what :meth:`Correlator.run` gives it from the same guess). The device
        frame path of the stereo tracks; ``current`` is then the frame's prepared image
        (:meth:`Correlator.frame_current`) for the later passes.
    max_fruitless_rounds : stop asking the fallback after this many rounds in a row that accepted no POI (their
        seeds and the propagation from them); None: only ``max_fallback_rounds`` and ``min_fallback`` stop it.
        For a costly fallback (the epipolar search of the stereo match: ~13 ms per POI) where the POIs left
        over are out of the other view, every further round is spent in vain.
    report : optional ``report(stage, accepted, settled)``, called after each pass (``stage``: ``"first pass"``,
        ``"propagation"``, ``"fallback"``, ``"second opinion"``, ``"done"``) with the number of eligible POIs
        accepted so far and of those settled (accepted, out of attempts, or tried by the fallback; all of them
        at ``"done"``): progress of a long correlation (the stereo reference match).
    """
    from scipy.spatial import cKDTree

    n = corr.points.shape[0]
    k = n_params(corr.order)
    params = np.full((n, k), np.nan)
    zncc = np.full(n, np.nan)
    iters = np.zeros(n, dtype=np.int32)
    status = np.full(n, int(Status.NOT_COMPUTED), dtype=np.int32)
    accepted = np.zeros(n, dtype=bool)
    extra_failed = np.zeros(n, dtype=bool)
    source = np.full(n, SOURCE_NONE, dtype=np.int8)
    attempts = np.zeros(n, dtype=np.int32)
    rank = np.full(n, -1, dtype=np.int32)
    eligible = eligible & corr.ready

    def batch(idx: np.ndarray, g: np.ndarray, src: int) -> int:
        if idx.size == 0:
            return 0
        return take(idx, corr.run(current, idx, g), src)

    def take(idx: np.ndarray, r: dict, src: int) -> int:
        p = r["params"].astype(np.float64)
        z = r["zncc"].astype(np.float64)
        st = r["status"].astype(np.int32)
        attempts[idx] += 1
        good = accepted_mask(st, z, zncc_min)
        ext = np.ones(idx.size, dtype=bool)
        if extra is not None and np.any(good):
            ext[good] = extra(idx[good], p[good])
        # keep the best attempt per POI: accepted > rejected by `extra` > low ZNCC > failed, then ZNCC
        new_rank = np.where(good & ext, 3, np.where(good, 2, np.where(np.isin(st, GOOD), 1, 0)))
        take = (new_rank > rank[idx]) | ((new_rank == rank[idx]) & (np.nan_to_num(z, nan=-2.0)
                                                                   >= np.nan_to_num(zncc[idx], nan=-2.0)))
        t = idx[take]
        params[t], zncc[t], status[t], iters[t] = p[take], z[take], st[take], r["iterations"][take]
        source[t] = src
        rank[t] = new_rank[take]
        extra_failed[t] = (good & ~ext)[take]
        accepted[t] = (good & ext)[take]
        return int(np.count_nonzero((good & ext)[take]))

    def tell(stage: str) -> None:
        if report is not None:
            done = accepted | (attempts >= max_attempts) | (fallback_tried & (attempts > 0)) | (stage == "done")
            report(stage, int(np.count_nonzero(accepted & eligible)), int(np.count_nonzero(done & eligible)))

    fallback_tried = np.zeros(n, dtype=bool)
    start = np.flatnonzero(has_guess & eligible)
    if first is None:
        batch(start, guess[start], initial_source)
    elif start.size:
        r0 = {key: np.asarray(first[key]) for key in ("params", "zncc", "iterations", "status")}
        if r0["params"].shape != (n, k) or any(r0[key].shape != (n,) for key in ("zncc", "iterations", "status")):
            raise ValueError(f"first must hold the results of all {n} POIs (params ({n}, {k}), zncc, iterations, "
                             f"status ({n},)), got params of shape {r0['params'].shape}")
        take(start, {key: a[start] for key, a in r0.items()}, initial_source)
    tell("first pass")
    fruitless, before = 0, None
    for _ in range(max_fallback_rounds + 1):
        # reliability-guided propagation: POIs next to accepted ones start from their parameters
        while True:
            acc = np.flatnonzero(accepted)
            open_ = np.flatnonzero(eligible & ~accepted & (attempts < max_attempts))
            if acc.size == 0 or open_.size == 0:
                break
            d, j = cKDTree(corr.points[acc]).query(corr.points[open_], k=1, distance_upper_bound=radius)
            near = np.isfinite(d)
            if not np.any(near):
                break
            idx = open_[near]
            nb = acc[j[near]]
            g = extrapolate(params[nb], corr.points[idx] - corr.points[nb], corr.order)
            batch(idx, g, SOURCE_NEIGHBOUR)
            tell("propagation")
        if before is not None:  # the last fallback round: its seeds and the propagation from them
            fruitless = fruitless + 1 if int(np.count_nonzero(accepted)) == before else 0
        if fallback is None or (max_fruitless_rounds is not None and fruitless >= max_fruitless_rounds):
            break
        cand = np.flatnonzero(eligible & ~accepted & ~fallback_tried)
        if cand.size < max(1, min_fallback):
            break
        seeds = spread(corr.points, cand, max_seeds)
        fallback_tried[seeds] = True
        before = int(np.count_nonzero(accepted))
        g, ok = fallback(seeds)
        if np.any(ok):
            batch(seeds[ok], g[ok], SOURCE_SEARCH)
            attempts[seeds[ok]] = np.minimum(attempts[seeds[ok]], max_attempts - 1)  # neighbours may still retry
        tell("fallback")
    if second_opinion:
        idx, best = second_opinion_candidates(corr.points, zncc, accepted, radius, zncc_drop, cache=corr.cache)
        if idx.size:
            g = extrapolate(params[best], corr.points[idx] - corr.points[best], corr.order)
            batch(idx, g, SOURCE_NEIGHBOUR)  # replaces a result only by an accepted one with a higher ZNCC
            tell("second opinion")
    robust_flagged = np.zeros(n, dtype=bool)
    if robust and np.any(accepted):
        plain = {"params": np.nan_to_num(params).astype(np.float32), "zncc": zncc.astype(np.float32),
                 "iterations": iters, "status": np.where(accepted, status, int(Status.NOT_COMPUTED)).astype(np.int32)}
        r = corr.refine_robust(current, plain, adaptive=robust == ADAPTIVE)
        robust_flagged = r["robust_flagged"] & accepted
        idx = np.flatnonzero(robust_flagged)  # the POIs refined (all accepted ones unless adaptive)
        p = r["params"][idx].astype(np.float64)
        z = r["zncc"][idx].astype(np.float64)
        st = r["status"][idx].astype(np.int32)
        good = accepted_mask(st, z, zncc_min)
        if extra is not None and np.any(good):
            ext = np.ones(idx.size, dtype=bool)
            ext[good] = extra(idx[good], p[good])
            extra_failed[idx] = good & ~ext
            good &= ext
        params[idx], zncc[idx], status[idx], iters[idx] = p, z, st, r["iterations"][idx]
        accepted[idx] = good
    implausible = np.zeros(n, dtype=bool)
    if check_warps:
        implausible = flag_implausible(corr, params, accepted, corr.order)
        accepted &= ~implausible
    tell("done")
    return CorrelationResult(params, zncc, iters, status, accepted, source, extra_failed, implausible, robust_flagged)


def reliability_guided(corr: Correlator, current, base: np.ndarray, seed_guess: Callable, *, zncc_min: float,
                       step: float | None, waves: str = "device") -> dict:
    """Reliability-guided propagation (Pan et al. 2009, doi:10.1364/AO.48.001535) over every POI.

    Seeds (up to 9 trackable POIs spread over the list) get their guess from ``seed_guess(idx) ->
    (m, k)`` (a ZNCC search) and are tracked; then neighbours (within 1.5 grid steps) of tracked
    valid POIs, in decreasing-ZNCC order, in batched waves: each wave tracks, in one launch, every
    untracked POI adjacent to a tracked valid POI, starting from the affine prediction of its
    best-ZNCC tracked neighbour; a wave only releases neighbours of POIs whose ZNCC is within 0.05 of
    the best pending one, which keeps the reliability ordering while launching many POIs at once.

    ``waves``: ``"device"`` (default) runs the waves on the device with no host round trip per wave:
    on CUDA the whole frame's loop is one CUDA graph (``wp.capture_while`` on the pending count;
    :mod:`kernels.propagation`, :mod:`kernels.rg_device`: per wave a bookkeeping launch, an IC-GN
    launch over N rows that reads the candidate count on the device, a scatter and a one-thread
    step), on the CPU the loop reads each wave's counts in place (host memory: no copy) and sizes the
    launches by them; ``"device-sync"`` reads each wave's two counts back on every device (one
    synchronisation per wave on CUDA; the route before); ``"host"`` runs them from a heap on the host
    (the reference implementation). All three give bitwise the same results (same waves, same sources, same guesses); no allocation after
    the first frame on the device routes.

    ``base`` (N, k): parameters where nothing was tracked (the user's guess or zeros).
    Returns host arrays ``params``, ``zncc``, ``iterations``, ``status`` (N rows).
    """
    from scipy.spatial import cKDTree

    if waves not in WAVES:
        raise ValueError(f"waves must be one of {WAVES}, got {waves!r}")
    n, k = corr.n_points, n_params(corr.order)
    base = np.asarray(base, dtype=np.float64)
    if base.shape != (n, k):
        raise ValueError(f"base must have shape {(n, k)} (one row of parameters per POI), got {base.shape}")
    points = corr.points
    ready = corr.ready
    step = step or corr.median_spacing()
    cand = np.flatnonzero(ready)
    n_seeds = min(cand.size, 9)
    seeds = cand[np.unique(np.linspace(0, cand.size - 1, n_seeds).round().astype(int))] if cand.size else cand
    if waves != "host":
        return _rg_device(corr, current, base, seeds, seed_guess, zncc_min, float(step),
                          sync=waves == "device-sync")
    params = base.copy()
    zncc = np.full(n, np.nan)
    iters = np.zeros(n, np.int32)
    status = np.full(n, int(Status.NOT_COMPUTED), np.int32)
    status[~ready] = corr.reference_status[~ready]
    neigh = cKDTree(points).query_ball_point(points, r=1.5 * step)

    def run(idx: np.ndarray, g: np.ndarray):
        res = corr.run(current, idx, g)
        params[idx] = res["params"]
        zncc[idx] = res["zncc"]
        iters[idx] = res["iterations"]
        status[idx] = res["status"]

    result = {"params": params, "zncc": zncc, "iterations": iters, "status": status}
    if cand.size == 0:
        return result
    run(seeds, seed_guess(seeds))
    good = lambda i: status[i] in GOOD and zncc[i] >= zncc_min  # noqa: E731
    heap = [(-zncc[i], i) for i in seeds if good(i)]
    heapq.heapify(heap)
    while heap:
        best = -heap[0][0]
        wave = []
        while heap and -heap[0][0] >= best - RG_BAND:
            wave.append(heapq.heappop(heap)[1])
        todo = {}
        for i in wave:
            for j in neigh[i]:
                if status[j] == int(Status.NOT_COMPUTED) and ready[j]:
                    if j not in todo or zncc[i] > zncc[todo[j]]:
                        todo[j] = i
        if not todo:
            continue
        idx = np.fromiter(todo.keys(), dtype=np.int64)
        src = np.fromiter(todo.values(), dtype=np.int64)
        d = points[idx] - points[src]
        p = convert_order(params[src], 1)
        g = np.zeros((idx.size, 6))
        g[:, 0] = p[:, 0] + p[:, 1] * d[:, 0] + p[:, 2] * d[:, 1]
        g[:, 3] = p[:, 3] + p[:, 4] * d[:, 0] + p[:, 5] * d[:, 1]
        g[:, [1, 2, 4, 5]] = p[:, [1, 2, 4, 5]]
        gk = convert_order(g, corr.order).copy()
        if k == 12:
            gk[:, [3, 4, 5, 9, 10, 11]] = params[src][:, [3, 4, 5, 9, 10, 11]]
        run(idx, gk)
        for j in idx:
            if good(j):
                heapq.heappush(heap, (-zncc[j], j))
    return result


#: the ways of running the reliability-guided waves (:func:`reliability_guided`)
WAVES = ("device", "device-sync", "host")

#: a reliability-guided wave expands every pending POI within this ZNCC of the best pending one
RG_BAND = 0.05


@dataclass
class _RgState:
    """Device state of the reliability-guided waves of one correlator (allocated once, reused per frame)."""

    step: float
    nb_start: wp.array
    nb: wp.array
    points: wp.array
    ready_status: wp.array
    full: IcgnResult  # N rows: the frame's results
    batch: _IndexedBuffers  # the correlator's batch buffers (shared with Correlator.run): a wave's POIs
    pop: wp.array
    best: wp.array
    counts: wp.array
    counts_host: wp.array | None  # pinned 2-int buffer for the per-wave counts (CUDA)
    ctl: wp.array  # int32 (2,): the batch/wave index of the device loop, the "bound reached" flag
    cond: wp.array  # int32 (1,): the device loop's condition (wp.capture_while)
    graph: tuple | None = None  # CUDA: (key, wp.Graph) of the frame loop captured for one current image


def _rg_state(corr: Correlator, step: float) -> _RgState:
    from kernels.propagation import neighbour_lists

    if corr._rg is not None and corr._rg.step == step:
        return corr._rg
    n, k, dev = corr.n_points, n_params(corr.order), corr.device
    start, flat = neighbour_lists(corr.points, 1.5 * step)
    ready_status = np.where(corr.ready, int(Status.NOT_COMPUTED), corr.reference_status).astype(np.int32)
    cuda = not str(dev).startswith("cpu")
    corr._rg = _RgState(
        step, wp.array(start, dtype=wp.int32, device=dev), wp.array(flat, dtype=wp.int32, device=dev),
        wp.array(corr.points, dtype=wp.vec2d, device=dev), wp.array(ready_status, dtype=wp.int32, device=dev),
        _result(n, k, dev), corr._buffers(), wp.zeros(n, dtype=wp.int32, device=dev), wp.empty(n + 3, dtype=wp.float32, device=dev),
        wp.zeros((n + 3, 2), dtype=wp.int32, device=dev),
        wp.empty(2, dtype=wp.int32, device="cpu", pinned=True) if cuda else None,
        wp.zeros(2, dtype=wp.int32, device=dev), wp.zeros(1, dtype=wp.int32, device=dev))
    return corr._rg


def _rg_device(corr: Correlator, current, base: np.ndarray, seeds: np.ndarray, seed_guess: Callable,
               zncc_min: float, step: float, sync: bool = False, max_waves: int | None = None) -> dict:
    """The waves of :func:`reliability_guided` on the device (:mod:`kernels.propagation`).

    ``sync``: read each wave's two counts back (``waves="device-sync"``); else the device loop
    (:func:`_rg_loop_body` under ``wp.capture_while``), stopped after wave ``max_waves`` (default: the
    state arrays' rows, more than any frame needs) with the host loop finishing the frame."""
    from kernels.propagation import init_state, start_loop

    st = _rg_state(corr, step)
    full, b = st.full, st.batch
    init_state(st.ready_status, full.status, full.zncc, full.iterations, st.pop, st.best, st.counts)
    m = seeds.size
    if m:
        cur = corr._current(current)
        k = n_params(corr.order)
        g = np.asarray(seed_guess(seeds), dtype=np.float64)
        if g.shape != (m, k) or not np.all(np.isfinite(g)):
            raise ValueError(f"seed_guess must return finite parameters of shape {(m, k)}, got {g.shape}")
        _upload(b.idx[:m], seeds.astype(np.int32))
        _upload(b.guess[:m], g.astype(np.float32))
        gather_subsets(corr.subsets, b.idx, m, b.subsets, points=corr.points[seeds])
        # masked subsets: the waves' counts read on the host (the counted kernel of kernels.rg_device has no
        # masked variant; the same waves and results)
        kind = "sync" if sync or corr.pixel_mask is not None else _loop_kind(wp.get_device(corr.device))
        if kind == "sync":
            _rg_sync_loop(corr, st, cur, zncc_min, 0, m)
        else:
            last = st.best.shape[0] - 2  # rg_wave's last wave
            last = last if max_waves is None else max(1, min(last, int(max_waves)))
            start_loop(st.ctl, st.cond, st.counts, m)
            _rg_device_loop(corr, st, cur, zncc_min, last, graph=kind == "graph")
            ctl = st.ctl.numpy()  # one copy per frame on CUDA (the frame's results come back anyway)
            if ctl[1]:  # the bound was reached: the host loop finishes the frame
                w = int(ctl[0])
                counts = st.counts.numpy()
                _rg_sync_loop(corr, st, cur, zncc_min, w, int(counts[w, 0]))
    status = np.array(full.status.numpy(), dtype=np.int32, copy=True)
    run = (status != int(Status.NOT_COMPUTED)) & corr.ready
    params = base.copy()
    params[run] = full.params.numpy()[run]
    zncc = full.zncc.numpy().astype(np.float64)
    iters = np.array(full.iterations.numpy(), dtype=np.int32, copy=True)
    return {"params": params, "zncc": zncc, "iterations": iters, "status": status}


def _rg_sync_loop(corr: Correlator, st: _RgState, cur: CurrentImage, zncc_min: float, w: int, m: int) -> None:
    """The waves with their counts read on the host (``waves="device-sync"``), from batch ``w`` whose ``m``
    candidates are gathered in the batch buffers (``w = 0``: the seeds) and not yet tracked (``m = 0``: none,
    but POIs still pending)."""
    from kernels.propagation import rg_wave, scatter_accept

    full, b = st.full, st.batch
    counts = st.counts.numpy() if st.counts_host is None else None
    while True:
        if m:
            sub = subset_rows(b.subsets, m)
            res = icgn(sub, cur, guess=b.guess[:m], max_iter=corr.max_iter, tol=corr.tol, out=_rows(b.out, m))
            scatter_accept(b.idx, res, full, m, float(zncc_min), st.pop, st.best, w + 1)
        w += 1
        rg_wave(w, RG_BAND, st.nb_start, st.nb, st.points, corr.subsets, full, st.pop, st.best, st.counts,
                b.idx, b.subsets, b.guess)
        if counts is not None:  # CPU: the counts are host memory
            m, left = int(counts[w, 0]), int(counts[w, 1])
        else:  # CUDA: two ints back, the only copy per wave
            wp.copy(st.counts_host, st.counts, src_offset=2 * w, count=2)
            wp.synchronize_device(corr.device)
            m, left = (int(x) for x in st.counts_host.numpy())
        if m and corr.subsets.mask is not None:  # the wave gathered the candidates' tables: their masks follow
            from kernels.icgn_masked import launch_gather_masks

            launch_gather_masks(m, b.idx, corr.subsets.mask, b.subsets.mask, corr.device)
        if not m and not left:
            return


def _rg_loop_body(corr: Correlator, st: _RgState, cur: CurrentImage, zncc_min: float, last: int) -> None:
    """One pass of the device loop, no host value read: IC-GN of batch ``ctl[0]``'s candidates (launched over
    N rows, :func:`kernels.rg_device.icgn_counted`), their scatter, the bookkeeping of wave ``ctl[0] + 1``
    and the step that advances ``ctl[0]`` and sets the condition. The same launches as a pass of
    :func:`_rg_sync_loop` (a batch of 0 candidates runs no thread), hence the same bits."""
    from kernels.propagation import advance, rg_wave_counted, scatter_counted
    from kernels.rg_device import icgn_counted

    b = st.batch
    icgn_counted(b.subsets, cur, b.guess, corr.max_iter, corr.tol, b.out, st.ctl, st.counts)
    scatter_counted(st.ctl, st.counts, b.idx, b.out, st.full, float(zncc_min), st.pop, st.best)
    rg_wave_counted(st.ctl, RG_BAND, st.nb_start, st.nb, st.points, corr.subsets, st.full, st.pop, st.best,
                    st.counts, b.idx, b.subsets, b.guess)
    advance(st.ctl, st.cond, st.counts, last)


def _loop_kind(device) -> str:
    """How ``waves="device"`` runs a frame's waves on ``device``: ``"graph"`` on CUDA (the device loop
    captured as a CUDA graph); ``"sync"`` on the CPU, where the counts are host memory read in place (no
    round trip to save) and launches sized by the count are cheaper than the counted ones over N rows
    (measured: docs/dic2d.md). ``"counted"`` (the device loop driven from the host) and ``"graph"`` on the
    CPU (Warp 1.19 captures there too, one launch per kernel: ``SPECULA_THREADS=1``) are what the tests
    run to exercise the CUDA branch here. A CUDA driver or toolkit older than 12.4 (no conditional graph
    nodes) gets ``"sync"``."""
    if not device.is_cuda:
        return "sync"
    return "graph" if wp.is_conditional_graph_supported() else "sync"


def _rg_device_loop(corr: Correlator, st: _RgState, cur: CurrentImage, zncc_min: float, last: int,
                    graph: bool) -> None:
    """The frame's waves: ``wp.capture_while(cond, body)``. ``graph``: captured once per current image
    buffer (and settings) as a graph with a conditional while node and launched (CUDA: no host round trip
    per wave); else ``wp.capture_while`` runs the body from the host while ``cond[0]`` is set (read in
    place on the CPU; on CUDA that would be a read per wave)."""
    body = lambda: _rg_loop_body(corr, st, cur, zncc_min, last)  # noqa: E731
    dev = wp.get_device(corr.device)
    if not graph:
        wp.capture_while(st.cond, body)
        return
    key = ((cur.rows4 if cur.rows4 is not None else cur.plain).ptr, cur.pitch, cur.shape, float(zncc_min), corr.max_iter, corr.tol, last)
    if st.graph is None or st.graph[0] != key:
        import kernels.propagation as prop
        import kernels.rg_device as rgd

        for mod in (prop, rgd):  # compiled and loaded before the capture
            wp.load_module(mod, device=dev)
        with wp.ScopedCapture(device=dev) as capture:
            wp.capture_while(st.cond, body)
        st.graph = (key, capture.graph)
    wp.capture_launch(st.graph[1])
