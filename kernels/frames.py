"""The device-resident frame path of IC-GN: a sequence of frames tracked against one reference with
every buffer allocated once, and IC-GN launches over (frames x POIs).

:class:`FrameTracker` is the per-frame loop of :func:`kernels.icgn.icgn` with the host work taken out:

* frames are uploaded as they come (8/16-bit or float32, :data:`kernels.interp.FRAME_DTYPES`) and
  converted to float in the B-spline prefilter kernel (:func:`kernels.interp.bspline_frames`), which
  also flags a non-finite pixel: that is the frame's only validity check (no host pass over it);
* the raw frame, the coefficients, the row-expanded layout, the guess, the results and the packed
  host copy are allocated once, in the constructor: tracking a frame allocates no Warp memory
  (``tests/kernels/test_frames.py`` counts the allocations);
* the guess of frame k is frame k-1's result, taken on the device (:func:`_propagate_guess`): a POI
  whose IC-GN status is CONVERGED or MAX_ITERATIONS with ``zncc >= zncc_min`` passes its parameters
  on, any other POI keeps its previous guess;
* the results come back in one packed copy per frame (params, zncc, iterations, status in one float32
  buffer, to pinned host memory on CUDA), or stay on the device (:meth:`FrameTracker.track_device`,
  :meth:`FrameTracker.track_torch`: ``wp.array`` / torch tensors in and out, no host copy).

On the CPU the frame's memory is read in place (a C-contiguous NumPy array of the frame dtype is
wrapped, not copied) and the results are copied out of the output buffers directly (the packing
pays only for a device-to-host transfer; ``packed=True`` forces it, for tests).

:func:`icgn_batch` and :meth:`FrameTracker.track_batch` run one IC-GN launch over (frames x POIs)
(thread ``t`` tracks POI ``t % N`` of frame ``t // N``), for frames with too few POIs to fill a GPU.
Both kernels call the per-POI bodies of :mod:`kernels.icgn` (``icgn_point_1st``/``icgn_point_2nd``),
so every frame's results equal a per-frame :func:`kernels.icgn.icgn` launch bit for bit.
"""
from __future__ import annotations

import numpy as np
import warp as wp

from ._common import ST_CONVERGED, ST_MAX_ITERATIONS, icgn_module_options, struct_of
from ._device import host_copy
from ._launch import cuda_launch_bounds, launch_1d
from .checks import in_range, positive_float, positive_int
from .icgn import (
    MASKED_PATH,
    CurrentCoefficients,
    CurrentImage,
    IcgnOutputs,
    IcgnResult,
    ReferenceSubsets,
    SubsetTable,
    check_layout,
    check_max_iter,
    icgn_point_1st,
    icgn_point_2nd,
    n_params,
)
from .images import is_torch_tensor
from .interp import FRAME_DTYPES, PAD, bspline_frames

#: the coefficient layout of :class:`FrameTracker` per device kind (``layout=None``): on the CPU the coefficients are
#: read in place (``"plain"``: no expansion pass, a quarter of the memory; the kernels' time is the same, docs/dic2d.md,
#: "Two coefficient layouts"); on CUDA the row-expanded copy until ``bench/gpu.py`` has measured both
FRAME_LAYOUT = {"cpu": "plain", "cuda": "rows4"}

# the IC-GN modules' options: the per-POI bodies compile here too and must give the same bits
wp.set_module_options(icgn_module_options("_icgn_frames_2nd"))


@wp.struct
class FrameArrays:
    """The per-frame arrays of a frames x POIs launch (F frames of N POIs, K parameters)."""

    #: (F, (H + 4) * (W + 4)) the frames' row-expanded B-spline coefficients
    coef: wp.array2d(dtype=wp.vec4)
    #: W + 4, the padded row length
    pitch: int
    #: (F, N, K), (F, N), (F, N), (F, N): the IC-GN results per frame
    params: wp.array3d(dtype=float)
    zncc: wp.array2d(dtype=float)
    iterations: wp.array2d(dtype=wp.int32)
    status: wp.array2d(dtype=wp.int32)


# ----------------------------------------------------------------------------------------------
# kernels
# ----------------------------------------------------------------------------------------------


@wp.func
def frame_current(frames: FrameArrays, f: int):
    """Frame ``f``'s coefficients as the :class:`kernels.icgn.CurrentCoefficients` of the per-POI bodies."""
    cur = CurrentCoefficients()
    cur.coef = frames.coef[f]
    cur.pitch = frames.pitch
    return cur


@wp.func
def frame_outputs(frames: FrameArrays, f: int):
    """Frame ``f``'s result rows as the :class:`kernels.icgn.IcgnOutputs` of the per-POI bodies."""
    out = IcgnOutputs()
    out.params = frames.params[f]
    out.zncc = frames.zncc[f]
    out.iterations = frames.iterations[f]
    out.status = frames.status[f]
    return out


def _make_icgn_frames(order: int):
    """The frames x POIs IC-GN kernel of one order: thread ``t`` tracks POI ``t % N`` of frame ``t // N``
    with the per-POI body of :mod:`kernels.icgn`, from guess row ``f * guess_stride``."""
    icgn_point = icgn_point_1st if order == 1 else icgn_point_2nd

    def icgn_frames(offset: int, n_points: int, sub: SubsetTable, frames: FrameArrays,
                    guess: wp.array3d(dtype=float), guess_stride: int, max_iter: int, tol: float):
        t = wp.tid() + offset
        f = t // n_points
        icgn_point(t - f * n_points, sub, frame_current(frames, f), guess[f * guess_stride], max_iter, tol,
                   frame_outputs(frames, f))

    name = "_icgn_frames_1st" if order == 1 else "_icgn_frames_2nd"
    icgn_frames.__name__ = icgn_frames.__qualname__ = name
    return wp.kernel(icgn_frames, launch_bounds=cuda_launch_bounds(name))


_icgn_frames_1st = _make_icgn_frames(1)
_icgn_frames_2nd = _make_icgn_frames(2)


@wp.kernel
def _propagate_guess(offset: int, n_frames: int, frames: FrameArrays, bad: wp.array(dtype=wp.int32), zncc_min: float,
                     guess: wp.array2d(dtype=float)):
    """The next frame's guess: POI n takes the parameters of the last of the ``n_frames`` frames where they
    are valid (status CONVERGED or MAX_ITERATIONS, ``zncc >= zncc_min``) and keeps its guess otherwise; a
    launch with a non-finite pixel in any frame passes nothing on (it is refused as a whole)."""
    n = wp.tid() + offset
    refused = int(0)
    for f in range(n_frames):
        refused += bad[f]
    if refused == 0:
        for f in range(n_frames):
            st = frames.status[f, n]
            if (st == ST_CONVERGED or st == ST_MAX_ITERATIONS) and frames.zncc[f, n] >= zncc_min:
                for i in range(guess.shape[1]):
                    guess[n, i] = frames.params[f, n, i]


@wp.kernel
def _pack_results(offset: int, n_points: int, frames: FrameArrays, packed: wp.array3d(dtype=float)):
    """One float32 row per POI: ``params, zncc, iterations, status`` (integers below 2**24: exact)."""
    t = wp.tid() + offset
    f = t // n_points
    n = t - f * n_points
    k = frames.params.shape[2]
    for i in range(k):
        packed[f, n, i] = frames.params[f, n, i]
    packed[f, n, k] = frames.zncc[f, n]
    packed[f, n, k + 1] = float(frames.iterations[f, n])
    packed[f, n, k + 2] = float(frames.status[f, n])


# ----------------------------------------------------------------------------------------------
# launchers
# ----------------------------------------------------------------------------------------------


def _launch_icgn_frames(subsets: ReferenceSubsets, frames: FrameArrays, n_frames: int, guess: wp.array,
                        guess_stride: int, max_iter: int, tol: float) -> None:
    n = subsets.n_points
    if subsets.mask is not None:  # per-POI pixel masks: the masked body (kernels.icgn_masked)
        MASKED_PATH["frames"](subsets.order, n, n_frames, subsets.table, subsets.mask, frames, guess, guess_stride,
                              max_iter, tol, subsets.device)
        return
    kernel = _icgn_frames_1st if subsets.order == 1 else _icgn_frames_2nd
    launch_1d(kernel, n_frames * n, [0, n, subsets.table, frames, guess, guess_stride, int(max_iter), float(tol)],
              subsets.device, offset_index=0, min_chunk=64)


def zncc_threshold32(zncc_min: float) -> float:
    """The smallest float32 ``t >= zncc_min``: ``z >= t`` in float32 is ``float64(z) >= zncc_min`` for every
    float32 ``z`` (the host's acceptance test, :func:`dic.correlation.acceptance.accepted_mask`)."""
    t = np.float32(zncc_min)
    if float(t) < zncc_min:
        t = np.nextafter(t, np.float32(np.inf))
    return float(t)


def _check_subsets(subsets) -> None:
    if not isinstance(subsets, ReferenceSubsets):
        raise ValueError(f"subsets must be a ReferenceSubsets from prepare_subsets(), got {type(subsets).__name__}")


def _guess_array(guess, n: int, k: int, name: str = "guess") -> np.ndarray:
    g = np.asarray(guess, dtype=np.float64)
    if g.shape != (n, k):
        raise ValueError(f"{name} must have shape {(n, k)} (one row of parameters per POI), got {g.shape}")
    if not np.all(np.isfinite(g)):
        raise ValueError(f"{name} contains NaN or infinite values; give a finite guess")
    return g.astype(np.float32)


def icgn_batch(subsets: ReferenceSubsets, currents, guesses=None, max_iter: int = 30,
               tol: float = 1e-3) -> list[IcgnResult]:
    """IC-GN of every POI into several current images in one launch over (frames x POIs).

    For sequences whose frames hold too few POIs to fill a GPU. Each frame's result equals
    ``icgn(subsets, currents[f], guesses[f], max_iter, tol)`` bit for bit (tested).

    Parameters
    ----------
    subsets : ReferenceSubsets from :func:`kernels.icgn.prepare_subsets`.
    currents : sequence of :class:`kernels.icgn.CurrentImage` (from :func:`kernels.icgn.prepare_current`, on
        the subsets' device, of the reference's shape).
    guesses : None (zeros), one (N, 6|12) guess shared by every frame, or (F, N, 6|12), one per frame.
    max_iter, tol : as :func:`kernels.icgn.icgn`.

    Returns
    -------
    list of F :class:`kernels.icgn.IcgnResult`, views of one (F, N, ...) set of device arrays.
    """
    _check_subsets(subsets)
    currents = list(currents) if not isinstance(currents, CurrentImage) else [currents]
    if not currents:
        raise ValueError("currents must hold at least one CurrentImage")
    device = subsets.device
    h, w = subsets.reference.shape
    for i, c in enumerate(currents):
        if not isinstance(c, CurrentImage):
            raise ValueError(f"currents[{i}] must be a CurrentImage from prepare_current(), got {type(c).__name__}")
        if c.device != device or c.shape != (h, w):
            raise ValueError(f"currents[{i}] is {c.shape[0]}x{c.shape[1]} on {c.device}; the subsets need {h}x{w} on {device}")
        if c.rows4 is None:
            raise ValueError(f'currents[{i}] was prepared with layout="plain"; the frames launch reads "rows4"')
    max_iter = check_max_iter(max_iter)
    tol = positive_float(tol, "tol", detail=" of pixels")
    f, n, k = len(currents), subsets.n_points, n_params(subsets.order)
    if guesses is None:
        g = np.zeros((1, n, k), np.float32)
    else:
        ga = np.asarray(guesses, dtype=np.float64)
        if ga.ndim == 2:
            g = _guess_array(ga, n, k, "guesses")[None]
        elif ga.ndim == 3 and ga.shape[0] == f:
            g = np.stack([_guess_array(gi, n, k, f"guesses[{i}]") for i, gi in enumerate(ga)])
        else:
            raise ValueError(f"guesses must be None, ({n}, {k}) or ({f}, {n}, {k}), got shape {ga.shape}")
    guess = wp.array(g, dtype=wp.float32, device=device)
    length = (h + 2 * PAD) * (w + 2 * PAD)
    rows4 = wp.empty((f, length), dtype=wp.vec4, device=device)
    for i, c in enumerate(currents):
        wp.copy(rows4, c.rows4, dest_offset=i * length, src_offset=0, count=length)
    params = wp.empty((f, n, k), dtype=wp.float32, device=device)
    zncc = wp.empty((f, n), dtype=wp.float32, device=device)
    iterations = wp.empty((f, n), dtype=wp.int32, device=device)
    status = wp.empty((f, n), dtype=wp.int32, device=device)
    frames = struct_of(FrameArrays, coef=rows4, pitch=w + 2 * PAD, params=params, zncc=zncc, iterations=iterations,
                       status=status)
    _launch_icgn_frames(subsets, frames, f, guess, int(g.shape[0] > 1), max_iter, tol)
    return [IcgnResult(params[i], zncc[i], iterations[i], status[i]) for i in range(f)]


class FrameTracker:
    """Track the POIs of one reference into a sequence of frames, device-resident (see the module doc).

    Parameters
    ----------
    subsets : ReferenceSubsets from :func:`kernels.icgn.prepare_subsets` (fixes the device, the frame
        shape ``subsets.reference.shape``, the subset size and the order).
    frame_dtype : numpy dtype of the frames: uint8, uint16 or float32 (grey levels keep their scale;
        the conversion to float happens in the prefilter kernel). Every frame must have exactly it.
    max_iter, tol : IC-GN limits (:func:`kernels.icgn.icgn`).
    zncc_min : float in [-1, 1]
        A POI passes its parameters to the next frame's guess only with a ZNCC at least this.
    batch : int >= 1
        Most frames per :meth:`track_batch` launch (the buffers hold this many frames).
    guess : (N, 6|12), optional
        The first frame's guess (default zeros); :meth:`reset` sets it again.
    packed : None or bool
        Results through one packed buffer (default: on CUDA, where it saves transfers).
    layout : None, "rows4" or "plain"
        How IC-GN reads the coefficients (:data:`kernels.icgn.LAYOUTS`): ``"rows4"`` the row-expanded copy (an
        expansion pass per frame, 4x the memory), ``"plain"`` the coefficients in place through a ``wp.vec4`` view
        with a 4-byte stride (:func:`kernels.interp.rows4_view`'s layout). The same compiled kernels read either,
        so the results are the same bits. Default :data:`FRAME_LAYOUT` of the device.

    Every buffer is allocated here; :meth:`track`, :meth:`track_device`, :meth:`track_torch` and
    :meth:`track_batch` allocate no Warp memory. Frames: NumPy arrays, ``wp.array`` or torch tensors
    (CPU or CUDA, on this tracker's device, read in place) of shape ``frame_shape`` and dtype
    ``frame_dtype``; anything else is a ``ValueError``, as is a frame holding a NaN or infinity
    (found on the device; that frame passes nothing on to the next guess).
    """

    def __init__(self, subsets: ReferenceSubsets, frame_dtype=np.float32, *, max_iter: int = 30, tol: float = 1e-3,
                 zncc_min: float = 0.8, batch: int = 1, guess=None, packed: bool | None = None,
                 layout: str | None = None):
        _check_subsets(subsets)
        try:
            dt = np.dtype(frame_dtype)
        except TypeError:
            dt = None
        if dt not in FRAME_DTYPES:
            raise ValueError(f"frame_dtype must be uint8, uint16 or float32, got {frame_dtype!r}")
        self.subsets = subsets
        self.device = subsets.device
        self.frame_dtype = dt
        self.frame_shape = tuple(subsets.reference.shape)
        self.max_iter = check_max_iter(max_iter)
        self.tol = positive_float(tol, "tol", detail=" of pixels")
        self.zncc_min = in_range(zncc_min, -1.0, 1.0, "zncc_min")
        self.batch = positive_int(batch, "batch", detail=" (frames per launch)")
        self._cuda = not self.device.startswith("cpu")
        self.packed = self._cuda if packed is None else bool(packed)
        h, w = self.frame_shape
        n, k = subsets.n_points, n_params(subsets.order)
        self.n_points, self.n_params = n, k
        dev, b = self.device, self.batch
        wdt = FRAME_DTYPES[dt]
        self._wdt = wdt
        self._length = (h + 2 * PAD) * (w + 2 * PAD)
        # raw frames on the device, and (CUDA) their pinned host staging buffer
        self._raw = wp.empty((b, h, w), dtype=wdt, device=dev)
        self._stage = wp.empty((b, h, w), dtype=wdt, device="cpu", pinned=True) if self._cuda else self._raw
        self._stage_np = self._stage.numpy()
        self.layout = check_layout(FRAME_LAYOUT["cpu" if dev.startswith("cpu") else "cuda"] if layout is None else layout)
        # the coefficients one float into a buffer of 4 more: the "plain" view below starts one float before them
        self._coef_buffer = wp.empty(b * self._length + 4, dtype=wp.float32, device=dev)
        self._coef = wp.array(ptr=self._coef_buffer.ptr + 4, shape=(b, h + 2 * PAD, w + 2 * PAD), dtype=wp.float32,
                              device=dev, copy=False)
        if self.layout == "rows4":
            self._rows4 = wp.empty((b, self._length), dtype=wp.vec4, device=dev)
        else:  # entry [f, k] = coefficients k - 1 .. k + 2 of frame f (rows4_view's layout), inside the buffer
            self._rows4 = wp.array(ptr=self._coef_buffer.ptr, shape=(b, self._length), strides=(4 * self._length, 4),
                                   dtype=wp.vec4, device=dev, copy=False)
        self._bad = wp.zeros(b, dtype=wp.int32, device=dev)
        self._guess = wp.zeros((1, n, k), dtype=wp.float32, device=dev)
        self._guess2d = self._guess[0]
        self._params = wp.empty((b, n, k), dtype=wp.float32, device=dev)
        self._zncc = wp.empty((b, n), dtype=wp.float32, device=dev)
        self._iterations = wp.empty((b, n), dtype=wp.int32, device=dev)
        self._status = wp.empty((b, n), dtype=wp.int32, device=dev)
        self._results = [IcgnResult(self._params[i], self._zncc[i], self._iterations[i], self._status[i])
                         for i in range(b)]
        self._frames = struct_of(FrameArrays, coef=self._rows4, pitch=w + 2 * PAD, params=self._params, zncc=self._zncc,
                                 iterations=self._iterations, status=self._status)
        if self.packed:
            self._packed = wp.empty((b, n, k + 3), dtype=wp.float32, device=dev)
            self._packed_host = (wp.empty((b, n, k + 3), dtype=wp.float32, device="cpu", pinned=True)
                                 if self._cuda else self._packed)
            self._packed_np = self._packed_host.numpy()
        self._bad_host = wp.empty(b, dtype=wp.int32, device="cpu", pinned=True) if self._cuda else self._bad
        self._bad_np = self._bad_host.numpy()
        self._guess_stage = (wp.empty((n, k), dtype=wp.float32, device="cpu", pinned=True)
                             if self._cuda else self._guess2d)
        self._guess_stage_np = self._guess_stage.numpy()
        self._zncc_min32 = zncc_threshold32(self.zncc_min)
        self._held = []  # frames read in place, kept alive until the next call (CUDA reads them asynchronously)
        self.frames_tracked = 0
        if guess is not None:
            self.reset(guess)

    # -- guesses ---------------------------------------------------------------------------------

    def reset(self, guess=None) -> None:
        """Set the next frame's guess: ``guess`` (N, 6|12) or zeros."""
        if guess is None:
            self._guess.zero_()
            return
        g = _guess_array(guess, self.n_points, self.n_params)
        if self._cuda:
            wp.synchronize_stream(wp.get_stream(self.device))  # the stage may still feed the previous upload
        np.copyto(self._guess_stage_np, g)
        if self._cuda:
            wp.copy(self._guess2d, self._guess_stage)

    @property
    def guess(self) -> np.ndarray:
        """The next frame's guess (a host copy)."""
        return host_copy(self._guess2d)

    # -- frames ----------------------------------------------------------------------------------

    def _check_frame(self, frame, i: int, name: str) -> wp.array | None:
        """A frame -> a (1, H, W) ``wp.array`` read in place, or None after copying it into slot ``i``."""
        h, w = self.frame_shape
        if is_torch_tensor(frame):
            dev = "cpu" if frame.device.type == "cpu" else f"cuda:{frame.device.index or 0}"
            tdt = str(frame.dtype).replace("torch.", "")
            if tdt not in ("uint8", "uint16", "float32") or np.dtype(tdt) != self.frame_dtype:
                raise ValueError(f"{name} has dtype {frame.dtype}; this tracker reads {self.frame_dtype} frames")
            if tuple(frame.shape) != (h, w):
                raise ValueError(f"{name} has shape {tuple(frame.shape)}; this tracker reads {h}x{w} frames")
            if dev != self.device:
                raise ValueError(f"{name} is on {dev} but this tracker runs on {self.device}")
            if not frame.is_contiguous():
                raise ValueError(f"{name} must be contiguous (call .contiguous())")
            if self._cuda:  # Warp's stream waits (on the device) for the work that produced the tensor
                import torch

                wp.get_stream(self.device).wait_stream(wp.stream_from_torch(torch.cuda.current_stream(frame.device)))
            self._held.append(frame)
            return wp.array(ptr=frame.data_ptr(), shape=(1, h, w), dtype=self._wdt, device=self.device)
        if isinstance(frame, wp.array):
            if frame.dtype != self._wdt:
                raise ValueError(f"{name} has dtype {frame.dtype.__name__}; this tracker reads {self.frame_dtype} frames")
            if frame.shape != (h, w):
                raise ValueError(f"{name} has shape {frame.shape}; this tracker reads {h}x{w} frames")
            if str(frame.device) != self.device:
                raise ValueError(f"{name} is on {frame.device} but this tracker runs on {self.device}")
            if not frame.is_contiguous:
                raise ValueError(f"{name} must be a contiguous wp.array")
            self._held.append(frame)
            return wp.array(ptr=frame.ptr, shape=(1, h, w), dtype=self._wdt, device=self.device)
        if not isinstance(frame, np.ndarray):
            raise ValueError(f"{name} must be a NumPy array, a wp.array or a torch tensor, got {type(frame).__name__}")
        if frame.dtype != self.frame_dtype:
            raise ValueError(f"{name} has dtype {frame.dtype}; this tracker reads {self.frame_dtype} frames "
                             f"(convert once, or build the tracker with frame_dtype={frame.dtype.name!r} if supported)")
        if frame.shape != (h, w):
            raise ValueError(f"{name} has shape {frame.shape}; this tracker reads {h}x{w} frames")
        if not self._cuda and frame.flags.c_contiguous:
            self._held.append(frame)
            return wp.array(ptr=frame.ctypes.data, shape=(1, h, w), dtype=self._wdt, device=self.device)
        np.copyto(self._stage_np[i], frame)
        return None

    def _run(self, frames: list, name: str = "frame") -> int:
        f = len(frames)
        if not 1 <= f <= self.batch:
            raise ValueError(f"a launch takes 1 to {self.batch} frames (batch={self.batch}), got {f}")
        self._held.clear()
        if self._cuda:  # the staging buffers may still feed the previous frame's transfers
            wp.synchronize_stream(wp.get_stream(self.device))
        views = [self._check_frame(fr, i, name if len(frames) == 1 else f"frames[{i}]") for i, fr in enumerate(frames)]
        h, w = self.frame_shape
        size = h * w
        if f == 1 and views[0] is not None:
            src = views[0]
        else:
            for i, v in enumerate(views):
                if v is not None:  # read in place: copy on the device into the slot
                    wp.copy(self._raw, v, dest_offset=i * size, src_offset=0, count=size)
                elif self._cuda:
                    wp.copy(self._raw, self._stage, dest_offset=i * size, src_offset=i * size, count=size)
            src = self._raw
        self._bad.zero_()
        bspline_frames(src, f, self._coef, self._expanded, self._bad)
        self._launch_frame(f)
        self.frames_tracked += f
        return f

    def _launch_frame(self, f: int) -> None:
        """IC-GN of the ``f`` prepared frames from the propagated guess, then the guess propagation."""
        _launch_icgn_frames(self.subsets, self._frames, f, self._guess, 0, self.max_iter, self.tol)
        launch_1d(_propagate_guess, self.n_points, [0, f, self._frames, self._bad, self._zncc_min32, self._guess2d],
                  self.device, offset_index=0, min_chunk=1 << 12)

    def _check_bad(self, f: int, copied: bool, name: str = "frame") -> None:
        if self._cuda and not copied:
            wp.copy(self._bad_host, self._bad, count=f)
            wp.synchronize_stream(wp.get_stream(self.device))
        bad = np.flatnonzero(self._bad_np[:f])
        if bad.size:
            which = name if f == 1 else "frames[" + ", ".join(str(int(i)) for i in bad) + "]"
            raise ValueError(f"{which} contains NaN or infinite values; DIC needs finite grey levels "
                             "(the launch is refused: the guess of the next frame is left as it was)")

    def _host_results(self, f: int, name: str = "frame") -> list[dict]:
        k = self.n_params
        if self.packed:
            launch_1d(_pack_results, f * self.n_points, [0, self.n_points, self._frames, self._packed],
                      self.device, offset_index=0, min_chunk=1 << 12)
            if self._cuda:
                wp.copy(self._packed_host, self._packed, count=f * self.n_points * (k + 3))
                wp.copy(self._bad_host, self._bad, count=f)
                wp.synchronize_stream(wp.get_stream(self.device))
            self._check_bad(f, copied=True, name=name)
            out = []
            for i in range(f):
                p = self._packed_np[i]
                out.append({"params": p[:, :k].copy(), "zncc": p[:, k].copy(),
                            "iterations": p[:, k + 1].astype(np.int32), "status": p[:, k + 2].astype(np.int32)})
            return out
        self._check_bad(f, copied=False, name=name)
        return [self._results[i].numpy() for i in range(f)]

    def track(self, frame, guess=None, *, name: str = "frame") -> dict[str, np.ndarray]:
        """Track one frame; host copies (the caller's) of ``params`` (N, 6|12) float32, ``zncc`` (N,) float32,
        ``iterations`` (N,) int32 and ``status`` (N,) int32, as ``kernels.icgn.icgn(...).numpy()``.

        ``guess`` (N, 6|12), optional, replaces the propagated guess for this frame (and onwards); ``name``
        names the frame in error messages."""
        if guess is not None:
            self.reset(guess)
        return self._host_results(self._run([frame], name), name)[0]

    def track_batch(self, frames, guess=None) -> list[dict[str, np.ndarray]]:
        """Track up to ``batch`` frames in one IC-GN launch over (frames x POIs); host results per frame.

        Every frame of the batch starts from the same guess (the propagated one, or ``guess``); afterwards
        the guess takes each POI's last valid result among them. A non-finite pixel in any frame refuses
        the whole launch (``ValueError`` naming the frames; the guess stays as it was)."""
        if guess is not None:
            self.reset(guess)
        frames = list(frames)
        return self._host_results(self._run(frames))

    def track_device(self, frame, guess=None) -> IcgnResult:
        """Track one frame; the results stay on the device (views of this tracker's buffers, overwritten by
        the next call). Float32 frames are checked for non-finite pixels with one 4-byte copy."""
        if guess is not None:
            self.reset(guess)
        self._run([frame])
        if self.frame_dtype == np.float32:
            self._check_bad(1, copied=False)
        return self._results[0]

    @property
    def frame_buffer(self) -> wp.array:
        """The device buffer (H, W) of ``frame_dtype`` that a graph of :meth:`capture_graph` reads its frame from."""
        return self._raw[0]

    @property
    def results(self) -> IcgnResult:
        """The device results of the last single frame (views, overwritten by the next frame)."""
        return self._results[0]

    def current(self, slot: int = 0) -> CurrentImage:
        """The prepared coefficients of frame ``slot`` of the last launch, as a :class:`kernels.icgn.CurrentImage`
        (a view of this tracker's buffers, overwritten by the next frame): for further IC-GN passes over the
        same frame, e.g. :func:`kernels.icgn_robust.icgn_robust`."""
        if isinstance(slot, bool) or not isinstance(slot, (int, np.integer)) or not 0 <= int(slot) < self.batch:
            raise ValueError(f"slot must be a frame slot in [0, {self.batch}), got {slot!r}")
        if self.layout == "rows4":
            return CurrentImage(self._rows4[int(slot)], self.frame_shape, self.device)
        return CurrentImage(None, self.frame_shape, self.device, plain=self._rows4[int(slot)])

    @property
    def _expanded(self) -> wp.array | None:
        """The row-expanded buffer the prefilter fills (None: the "plain" layout reads the coefficients in place)."""
        return self._rows4 if self.layout == "rows4" else None

    def capture_graph(self):
        """Capture one frame's device work as a CUDA graph (``wp.Graph``): the prefilter of :attr:`frame_buffer`
        with its finiteness flag, IC-GN from the propagated guess, and the guess propagation.

        Replay per frame: copy the frame into :attr:`frame_buffer` on the device (``wp.copy``), then
        ``wp.capture_launch(graph)``; the results are in :attr:`results` (on the device). One launch of the
        whole frame instead of about ten kernel launches. Track one frame first (modules loaded, scratch
        allocated). CUDA only: on the CPU this is a ``ValueError``.
        """
        if not self._cuda:
            raise ValueError(f"CUDA graphs need a CUDA device; this tracker runs on {self.device}")
        if self.frames_tracked == 0:
            raise ValueError("track one frame before capturing (kernels loaded, scratch buffers allocated)")
        wp.synchronize_device(self.device)
        with wp.ScopedCapture(device=self.device) as capture:
            self._bad.zero_()
            bspline_frames(self._raw, 1, self._coef, self._expanded, self._bad)
            self._launch_frame(1)
        return capture.graph

    def track_torch(self, frame, guess=None) -> dict:
        """:meth:`track_device` with torch tensors out (``wp.to_torch``: no copy; CUDA tensors stay on the GPU):
        ``params``, ``zncc``, ``iterations``, ``status``. Overwritten by the next call: ``.clone()`` what you keep."""
        res = self.track_device(frame, guess)
        if self._cuda:  # torch's stream waits (on the device) for the results
            import torch

            wp.stream_from_torch(torch.cuda.current_stream(self.device)).wait_stream(wp.get_stream(self.device))
        return {name: wp.to_torch(getattr(res, name)) for name in ("params", "zncc", "iterations", "status")}
