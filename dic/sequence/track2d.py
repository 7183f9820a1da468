"""2-D DIC of an image sequence: :func:`track_sequence` (docs/dic2d.md, "Sequences").

One engine for every 2-D sequence, used by the library and by ``specula track``: the reference's
per-POI data are prepared once per reference (a :class:`dic.Tracker`), the next frames are
read on a thread ahead of the correlation and the finished ones are written (strain, result file,
VTK, figures, callback) on a thread behind it (:mod:`dic.sequence.pipeline`), with bounded queues,
so memory does not grow with the sequence. Reference strategies and the Lagrangian composition of
the results: :mod:`dic.sequence.reference`.
"""
from __future__ import annotations

import copy
import functools
import os
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ..correlation.lagrangian import MovedReference, reference_anchors
from ..field2d import Field2D, as_field2d
from .chunks import (
    STRAIN_BAND_POINTS,
    ChunkedTracker,
    bytes_per_poi,
    check_budget,
    default_max_memory,
    strain_in_bands,
    write_depth,
)
from .engine import CannotServe, SequenceSummary, run_sequence
from .options import TrackOptions
from .pipeline import Loaded, WriteBehind, load_image, read_ahead, trim_memory
from .reference import AUTO_VALID, AUTO_ZNCC, parse_reference
from .verification import VERIFY_SPREAD, VERIFY_ZNCC, ComposedVerifier, check_verify_spread, composed_mismatches

__all__ = ["track_sequence", "SequenceSummary"]

@dataclass
class _Ref:
    """The reference a frame is tracked against: the reference image (``moved`` None) or frame ``index``."""

    index: int
    image: Any
    tracker: Any
    ok: np.ndarray  # (N,) bool: the points that can be tracked against it (valid in it, or placed by local interpolation)
    state: Field2D | None = None  # frame ``index``'s field (None: the reference image)
    moved: MovedReference | None = None  # frame ``index`` as a reference (dic.correlation.lagrangian)


def _moved(points0, state: Field2D, index: int, image, order: int) -> _Ref:
    """Frame ``index`` (its Lagrangian field ``state``, computed or read back) as a reference, its tracker not
    built yet (:class:`dic.correlation.lagrangian.MovedReference`). ValueError: no valid point."""
    params = _params(state)
    anchors = reference_anchors(points0, params, state.valid)
    moved = MovedReference(index, points0, params, anchors, order)
    return _Ref(index, image, None, moved.usable, state, moved)


def _params(f: Field2D) -> np.ndarray:
    """(N, 6|12) float64 parameters of a frame (one of another writer's files may have none: translation only)."""
    if f.params is not None:
        return np.asarray(f.params, np.float64)
    params = np.zeros((len(f.u), 6))
    params[:, 0], params[:, 3] = f.u, f.v
    return params


def _guess(previous):
    """Initial parameters from the previous frame: its valid points as they are, the others at
    the mean displacement of the valid ones (None for the first frame or when none is valid)."""
    if previous is None:
        return None
    params, valid = previous
    if not np.any(valid) or params.ndim != 2:
        return None
    guess = params.copy()
    k = params.shape[1]
    guess[~valid] = 0.0
    guess[~valid, 0] = params[valid, 0].mean()
    guess[~valid, k // 2] = params[valid, k // 2].mean()
    return guess


def _quality(raw, ref_valid) -> tuple[float, float]:
    """Valid fraction (among the points the reference can track: ``_Ref.ok``) and median ZNCC of the valid points."""
    valid = np.asarray(raw.valid, bool) & ref_valid
    n_ref = int(np.count_nonzero(ref_valid))
    frac = np.count_nonzero(valid) / n_ref if n_ref else 0.0
    z = np.asarray(raw.zncc, np.float64)[valid]
    return float(frac), float(np.median(z)) if z.size else 0.0


def _lagrangian(ref: _Ref, raw, points0, index: int) -> Field2D:
    """A tracker's result of frame ``index`` against ``ref`` as the frame's :class:`Field2D` against the reference image."""
    raw = as_field2d(raw)
    if ref.index != 0:
        return _compose(ref, raw, points0, index)
    raw.index = int(index)
    return raw


def _compose(ref: _Ref, raw: Field2D, points0, index: int) -> Field2D:
    """Frame ``index``'s result against a moved reference, in the original configuration (Lagrangian)."""
    out = copy.copy(raw)
    s, moved = ref.state, ref.moved  # s: the field of the frame the reference moved to
    params = moved.compose(raw.params)  # tracked at whole pixels: carried to the moved POI, then composed
    ok = moved.usable
    valid = np.asarray(raw.valid, bool) & ok
    status = np.where(ok, np.asarray(raw.status, np.int32), s.status).astype(np.int32)
    out.points = np.array(points0, dtype=np.float64)
    out.params = params
    out.u = params[:, 0].copy()
    out.v = params[:, params.shape[1] // 2].copy()
    out.valid = valid
    out.status = status
    out.index = int(index)
    out.reference_index = int(ref.index)
    out.reference_interpolated = valid & ~moved.anchors  # valid here, placed in the reference by interpolation
    if raw.sigma_u is not None and s.sigma_u is not None:
        out.sigma_u = np.hypot(np.asarray(raw.sigma_u, np.float64), np.asarray(s.sigma_u, np.float64))
    if raw.sigma_v is not None and s.sigma_v is not None:
        out.sigma_v = np.hypot(np.asarray(raw.sigma_v, np.float64), np.asarray(s.sigma_v, np.float64))
    return out


def _digest(image) -> str:
    """A frame's digest for the resume check: SHA-256 of a host image; of a torch tensor (kept on its
    device) the device-computed checksum, so that no frame is copied to the host just to be hashed."""
    from kernels.images import is_torch_tensor

    from ..store import device_checksum, image_digest

    return device_checksum(image) if is_torch_tensor(image) else image_digest(image)


def _digest_like(stored: str, image, given: str) -> str:
    """The digest of ``image`` of the kind the file holds for it (resuming a run whose frames were given
    as tensors with arrays, or the other way round); ``given`` when the kinds already agree."""
    from ..store import DEVICE_CHECKSUM_PREFIX, device_checksum, image_digest

    if not stored or stored.startswith(DEVICE_CHECKSUM_PREFIX) == given.startswith(DEVICE_CHECKSUM_PREFIX):
        return given
    if stored.startswith(DEVICE_CHECKSUM_PREFIX):
        return device_checksum(image)
    # the file holds a SHA-256: a tensor frame goes to the host once, for this check only
    return image_digest(image.detach().cpu().numpy() if hasattr(image, "detach") else image)


def _host(image):
    """A frame image on the host (a torch tensor copied there once, as float32 like every tracker input)."""
    from kernels.images import as_float32_image, is_torch_tensor

    return as_float32_image(image, "a new reference") if is_torch_tensor(image) else image


def _frame_loader(shape, reference_name: str):
    def load(index: int, item) -> Loaded:
        img, path = load_image(item, f"frame {index}", keep_tensors=True)
        if img.ndim != 2 or tuple(img.shape) != tuple(shape):
            got = f"{img.shape[1]}x{img.shape[0]} px" if img.ndim == 2 else f"of shape {tuple(img.shape)}"
            raise ValueError(f"{path or f'frame {index}'} is {got} but the reference {reference_name} is "
                             f"{shape[1]}x{shape[0]} px; all images must have the same size")
        return Loaded(index, img, path, _digest(img))

    return load


def track_sequence(reference_image, frames, out, *, reference: str = "fixed", mode: str = "resume",
                   progress: bool = False, callback: Callable | None = None, strain_window: int = 5,
                   vtk_dir=None, figure_dir=None, figure_every: int = 1, auto_valid: float = AUTO_VALID,
                   auto_zncc: float = AUTO_ZNCC, settings: dict | None = None,
                   make_tracker: Callable | None = None, max_memory: int | None = None, guess: str | None = None,
                   client=None, compression=None, verify_composed: bool | None = None, verify_zncc: float | None = None,
                   strain_type: str = "green-lagrange", verify_spread: float | str | None = None,
                   **options) -> SequenceSummary:
    """2-D DIC of an image sequence against a reference image, written frame by frame to an HDF5 file.

    Parameters
    ----------
    reference_image : path or array (H, W)
        The reference image (frame 0).
    frames : list of paths/arrays, any iterable of arrays (a generator, a (T, H, W) array, a
        :class:`dic.sources.FrameSource`), or one path of a folder, glob pattern, multi-page TIFF or
        video (read with :func:`dic.sources.open_frames`)
        Frame ``k`` (from 1) is the k-th item. Read lazily, a couple of frames ahead of the correlation.
    out : str or Path
        The ``.h5`` result file (docs/results_format.md); an existing compatible file is resumed
        (finished frames are skipped; they must come from the same images) unless ``mode="overwrite"``
        (``"new"`` refuses an existing file).
    reference : "fixed" | "incremental" | "every:N" | "auto"
        Which image each frame is correlated against (:mod:`dic.sequence.reference`). Results are
        always reported at the original POIs in the original reference (Lagrangian); each frame's
        ``reference_index`` attribute says which frame served as its reference (0: the reference image).
    auto_valid, auto_zncc : float in [0, 1]
        ``reference="auto"``: the valid fraction and the median ZNCC below which the reference moves to
        the previous frame (defaults 0.95 and 0.95).
    mode : "resume" | "overwrite" | "new"
    progress : bool
        A tqdm progress bar (frames/s and time left when the length is known).
    callback : callable(index, field, strain), optional
        Called with each computed frame's Lagrangian field (a :class:`dic.field2d.Field2D`) and strain
        (or None) once the frame is in the file (on the writer thread, in frame order).
    strain_window : int
        Strain fit window in grid points (odd >= 3), 0 for no strain.
    strain_type : "green-lagrange" | "small" | "euler-almansi"
        What the strain ``exx``, ``eyy``, ``exy`` is (:func:`dic.strain`); recorded in the settings.
    vtk_dir : folder, optional
        Write ``frame_<index>.vtu`` per frame as it finishes (every POI at its reference position, NaN
        where invalid: the same point set at every step).
    figure_dir : folder, optional
        Write ``frame_<index>.png`` (u, v and strain maps) every ``figure_every`` frames as they finish.
    settings : TrackOptions or dict, optional
        What the file records of the run and a resume compares. Default: the run record
        (:class:`dic.sequence.options.TrackOptions`) of ``options`` and the sequence keywords, stored
        with every default written out and compared option by option (a file written by ``specula
        track`` resumes here and the other way round; docs/results_format.md, "The run record"). A
        ``TrackOptions`` (the command line's): its tracker options, with this call's ``strain_window``,
        ``reference``, ``auto_valid``, ``auto_zncc`` and ``guess``. A dict (with a custom
        ``make_tracker``): stored as given and compared as it is.
    max_memory : int, optional
        Budget in bytes for the per-POI working data of the correlation (default: a twelfth of the
        machine's memory); beyond it the POIs are prepared and tracked in chunks for every frame
        (:mod:`dic.sequence.chunks`), with results identical to an unchunked run.
    make_tracker : callable(image, points) -> tracker, optional
        Builds the tracker of a reference image (``points`` None: the default grid of ``options``;
        otherwise the moved POIs or a chunk of them). Default: :class:`dic.Tracker` with
        ``options``. One that takes a ``carried`` keyword gets, for a moved reference with a mask or polygon
        region or cracks, a dict of :class:`dic.Tracker` keywords (``pixel_region``, ``blocked_pixels``,
        ``cracks``) that mask its subsets by the region and cracks carried into that frame (docs/dic2d.md,
        "Masks and cracks carried to a moved reference"); the default and ``specula track``'s do. With a
        custom one, ``options`` are only used to plan chunks: give ``points`` and ``order`` (the POIs it
        would use) so that an over-budget run is chunked from the start.
    guess : "previous" | "none", optional
        Where each frame's correlation starts: ``"previous"`` (default without ``client``) from the
        previous frame's result (a chain: frame k waits for frame k-1); ``"none"`` (default, and the
        only choice, with ``client``) from the tracker's own start, its ``search`` or zero against the
        reference (for ``every:N`` the block's key frame, moved to where the points are), so frames
        are independent. ``"none"`` is stored in the file's settings.
    client : distributed.Client or scheduler address, optional
        Distribute the frames over a Dask cluster (:mod:`dic.sequence.distributed`): each worker
        prepares the reference once and keeps it, the frames go to the workers, the results come
        back to this process, which writes them in frame order (resume as without a client). Results
        are identical to a single-process run with ``guess="none"`` (a moved reference's carried region and
        cracks, worked out here and shipped with it, and the check of composed frames included). ``"fixed"`` and ``"every:N"``
        only (every:N waits for each key frame before its block); an address is connected within 5 s.
    compression : "none" | "lzf" | "gzip" | "gzip:N", optional
        How the result file's datasets are compressed (:func:`dic.store.layout.parse_compression`;
        default ``"none"``: the fastest, docs/results_format.md). A resumed file keeps the setting it was written with.
    verify_composed : bool
        Check every frame correlated against a moved reference (its result a composition of several
        correlations) against the reference image itself: each valid point's ZNCC between its reference
        subset and the frame at the composed warp (:mod:`dic.sequence.verification`). Points below
        ``verify_zncc`` are not valid and get the status ``COMPOSED_MISMATCH``; the frame's
        ``composed_mismatch`` attribute and :attr:`SequenceSummary.n_mismatch` count them. Default None:
        on wherever it can act (a moved reference; with ``client`` too, the check run in this process as the
        frames come back: the same results as one process); False: no check (the results of runs before the option; a file written
        before it resumes only with False, its record holding no check).
    verify_zncc : float in [-1, 1], optional
        The ZNCC below which a composed point fails (default 0.95,
        :data:`dic.sequence.verification.VERIFY_ZNCC`: a whole-pixel wrong match scores at most 0.92 on a
        2 px speckle, a correct composed warp at least 0.994 at 4 grey levels of noise; docs/dic2d.md).
    verify_spread : float >= 0 or "off", optional
        Each composed frame's threshold is ``min(verify_zncc, median - verify_spread * 1.4826 * MAD)`` of its
        checked points' ZNCCs (:func:`kernels.verify.composed_threshold`): ``verify_zncc`` where the texture still
        matches the reference image, lower where it has changed since (an evolving speckle, whose correct points
        all lose correlation with the reference image); there a point between that and ``verify_zncc`` also
        fails when its composed warp is off the ZNCC's peak by the probes 1 px away
        (:func:`kernels.verify.composed_failures`). Default None: 4
        (:data:`kernels.verify.VERIFY_SPREAD`, by measurement, docs/dic2d.md); ``"off"``: ``verify_zncc`` alone
        (the rule before the option, that a file written before it resumes with).
    options
        :class:`dic.Tracker` keywords (``step``, ``subset``, ``order``, ``roi``, ``points``,
        ``search``, ``search_radius``, ``max_iter``, ``tol``, ``zncc_min``, ``flat_std``, ``check_warps``,
        ``noise_sigma``, ``robust``, ``check_outliers``, ``cracks``, ``device``), and ``scale_mm_per_px``
        (recorded in the file for post-processing). ``cracks`` (:mod:`dic.cracks`, reference px) also keeps
        the strain windows and figure cells from reaching across them, and is stored in the file's settings
        for post-processing (``specula crack``). Validated once (:class:`dic.sequence.options.OptionError`, a
        ValueError naming the option).

    Returns
    -------
    SequenceSummary

    Raises
    ------
    ValueError
        Bad options or images, a frame that cannot be read (``"frame k (path): ..."``; the frames
        before it are in the file), an incompatible result file; :class:`dic.store.ResultWriteError`
        (a ValueError) when the file cannot be written.
    """
    if isinstance(client, str):  # a scheduler address: connected here, closed when the run ends
        from .distributed import call_connected

        return call_connected(track_sequence, locals())
    from tqdm import tqdm

    from kernels.checks import non_negative_int, positive_int

    from ..store import ResultWriter

    t_start = time.perf_counter()
    policy = parse_reference(reference, auto_valid=auto_valid, auto_zncc=auto_zncc)
    if guess is None:
        guess = "previous" if client is None else "none"
    if guess not in ("previous", "none"):
        raise ValueError(f"guess must be 'previous' or 'none', got {guess!r}")
    if verify_composed is None:  # the default: on wherever it can act (a moved reference)
        verify_composed = policy.kind != "fixed"
    if not isinstance(verify_composed, (bool, np.bool_)):
        raise ValueError(f"verify_composed must be None, True or False, got {verify_composed!r}")
    if verify_zncc is not None:
        from kernels.checks import in_range

        verify_zncc = in_range(verify_zncc, -1.0, 1.0, "verify_zncc")
    if verify_spread is not None:
        verify_spread = "off" if check_verify_spread(verify_spread) is None else check_verify_spread(verify_spread)
    if client is not None:
        if guess != "none":
            raise ValueError("guess='previous' chains each frame to the one before it and cannot be distributed: "
                             "with client= every frame starts from guess='none' (leave guess out)")
        if policy.kind not in ("fixed", "every"):
            raise ValueError(f"reference={policy.text!r} cannot be distributed: each frame waits for the one before it; "
                             "use 'fixed' or 'every:N' (the chain split every N frames) with client=, or run "
                             "without client")
        from .distributed import connect

        client = connect(client)
    mode = str(mode)
    strain_window = non_negative_int(strain_window, "strain_window")
    from .._strain import check_strain_type

    strain_type = check_strain_type(strain_type)
    figure_every = positive_int(figure_every, "figure_every")
    if callback is not None and not callable(callback):
        raise ValueError(f"callback must be callable, got {type(callback).__name__}")
    out = Path(os.fspath(out))
    if out.suffix.lower() not in (".h5", ".hdf5"):
        raise ValueError(f"the output must be an HDF5 file ending in .h5, got {out.name}")
    if isinstance(frames, (str, os.PathLike)):
        # a folder, a glob pattern, a multi-page TIFF or a video: every frame it holds (dic.sources)
        from ..sources import open_frames

        frames = open_frames(frames)
    if hasattr(frames, "__len__") and len(frames) == 0:
        raise ValueError("frames is empty: give at least one image to track")
    ref_img, ref_path = load_image(reference_image, "the reference image")
    if ref_img.ndim != 2:
        raise ValueError(f"the reference image must be a grey (H, W) image, got shape {ref_img.shape}")
    custom_tracker = make_tracker
    # the run record (dic.sequence.options): every option that affects the results, validated once, stored
    # with its defaults and compared on resume whichever writer (library or command line) made the file
    record = settings if isinstance(settings, TrackOptions) else \
        TrackOptions.from_keywords(options, shape=ref_img.shape) if settings is None else None
    if record is not None:
        record = replace(record, strain_window=strain_window, reference=policy.text, auto_valid=policy.auto_valid,
                         auto_zncc=policy.auto_zncc, guess=guess, verify_composed=bool(verify_composed),
                         verify_zncc=verify_zncc, strain_type=strain_type, verify_spread=verify_spread)
        settings = record.to_settings()
        if make_tracker is None:
            options = {**record.tracker_kwargs(), "device": options.get("device")}
    if make_tracker is None:
        def make_tracker(image, points, _opts=dict(options), carried=None):
            from .._track import Tracker

            kw = dict(_opts)
            if points is not None:
                region = kw.pop("roi", None)
                kw["points"] = points
                if carried is not None:  # a moved reference: the region and cracks carried into its frame
                    kw.pop("cracks", None)
                    kw.update(carried)
                elif region is not None and _same_image(image, ref_img):  # a chunk of the reference's grid:
                    kw["pixel_region"] = region  # its subsets masked alike
            return Tracker(image, **kw)
    if record is None:  # settings given as a dict (a custom tracker's): stored as given, compared as they are
        settings = dict(settings)
        if policy.kind != "fixed":
            settings["reference"] = policy.text
        if guess == "none":
            settings["guess"] = "none"
            if policy.kind == "auto":
                settings["auto_valid"], settings["auto_zncc"] = policy.auto_valid, policy.auto_zncc
        if verify_composed:
            settings["verify_composed"] = True
            settings["verify_zncc"] = verify_zncc if verify_zncc is not None else VERIFY_ZNCC
            settings["verify_spread"] = verify_spread if verify_spread is not None else VERIFY_SPREAD
    # the ZNCC below which a composed point fails (None: no check; dic.sequence.verification), and the robust
    # standard deviations below each frame's median ZNCC that can lower it (None: the threshold alone)
    verify_threshold = verify_rule = None
    if verify_composed:
        verify_threshold = record.verify_zncc if record is not None else settings["verify_zncc"]
        verify_rule = check_verify_spread(record.verify_spread if record is not None else settings["verify_spread"])

    budget = default_max_memory() if max_memory is None else positive_int(max_memory, "max_memory", detail=" (bytes)")
    # the POIs, known without preparing them (a custom tracker's only when options give points and order)
    planned = _planned_points(ref_img.shape, options) if custom_tracker is None or \
        (options.get("points") is not None and options.get("order") is not None) else None
    if max_memory is not None and planned is not None:  # a budget below the working set crawls: say so
        slow = check_budget(budget, len(planned[0]), planned[1], ref_img.shape)
        if slow:
            warnings.warn(slow, stacklevel=2)
    if planned is not None and len(planned[0]) * bytes_per_poi(planned[1]) > budget:  # chunked from the start
        tracker0 = ChunkedTracker(make_tracker, ref_img, planned[0], order=planned[1],
                                  chunk=budget // bytes_per_poi(planned[1]), search=options.get("search"))
    else:
        tracker0 = make_tracker(ref_img, None)
        if len(tracker0.points) * bytes_per_poi(int(tracker0.order)) > budget:
            tracker0 = ChunkedTracker(make_tracker, ref_img, tracker0.points, order=int(tracker0.order),
                                      chunk=budget // bytes_per_poi(int(tracker0.order)),
                                      search=getattr(tracker0, "search", None))
    points0 = np.array(tracker0.points, dtype=np.float64)
    order = int(tracker0.order)
    search_name = options.get("search") if custom_tracker is None else getattr(tracker0, "search", None)

    def tracker_for(image, points, carried=None):
        """A tracker of ``image`` at ``points`` (the moved POIs), in chunks when over the memory budget;
        ``carried``: the tracker keywords of the region and cracks carried into the image (:func:`_carry_for`)."""
        build = make_tracker if carried is None else functools.partial(make_tracker, carried=carried)
        if len(points) * bytes_per_poi(order) > budget:
            return ChunkedTracker(build, image, points, order=order, chunk=budget // bytes_per_poi(order),
                                  search=search_name)
        return build(image, points)

    tracker0_holder = [tracker0]  # the reference image's tracker, freed once the reference has moved on
    del tracker0

    def reference_tracker():
        if tracker0_holder[0] is None:
            over = len(points0) * bytes_per_poi(order) > budget
            tracker0_holder[0] = tracker_for(ref_img, points0) if over else make_tracker(ref_img, None)
        return tracker0_holder[0]

    n = len(points0)
    cracks = record.cracks if record is not None else options.get("cracks")  # declared cracks (dic.cracks): no strain window or figure cell across one
    strain_plan = None  # the strain's grid and fits worked out once for the POIs (every frame has the same)
    if strain_window:
        from .._strain import StrainPlan, check_strain_window, grid_layout

        try:
            if n <= STRAIN_BAND_POINTS:
                strain_plan = StrainPlan(points0, window=strain_window, cracks=cracks, strain_type=strain_type)
            else:  # huge grids: strain in bands of rows (bounded memory), the grid checked here
                check_strain_window(strain_window, grid_layout(points0)[1])
        except ValueError as exc:
            raise ValueError(f"{exc} (strain_window=0 skips strain)") from None
    everywhere = np.ones(n, bool)  # the reference image: every point can be tracked
    ref_name = ref_path or "(array)"
    writer = ResultWriter(out, reference_path=ref_path, reference_shape=ref_img.shape,
                          reference_sha256=_digest(ref_img), settings=settings, mode=mode,
                          compression=compression, settings_check=record.resume_check if record is not None else None)
    summary = SequenceSummary(path=out)
    total = len(frames) if hasattr(frames, "__len__") else None
    writer.hold_outputs(vtk_dir, figure_dir)  # their locks, released with the writer's (dic.store.files)

    with writer:
        done = set(writer.done_frames())
        if vtk_dir is not None and done:  # the VTK files of finished frames: whole, or rewritten now
            from ..export import restore_vtk_files

            restore_vtk_files(writer, vtk_dir, "frame", done)
        wb = WriteBehind(depth=write_depth(n, order, budget))  # huge frames: none waits (memory)

        def finish(k: int, lag, raw_seconds: float, item: Loaded):
            strain = None
            if strain_window:
                try:
                    if strain_plan is not None and strain_plan.matches(lag.points):
                        strain = strain_plan.strain(lag)  # bit for bit dic.strain
                    else:  # a band of grid rows at a time: bounded memory, the same strain (dic.sequence.chunks)
                        strain = strain_in_bands(lag, strain_window, cracks=cracks, strain_type=strain_type)
                except ValueError as exc:
                    raise ValueError(f"frame {k} ({item.path or 'array'}): {exc}") from None
            lag.strain = strain  # the frame's field carries its strain (callback, later use)
            attrs = {"seconds": raw_seconds, "reference_index": int(lag.reference_index)}
            if lag.reference_interpolated is not None:  # the valid points whose place in the reference was interpolated
                attrs["reference_interpolated"] = int(np.count_nonzero(lag.reference_interpolated))
            if verify_threshold is not None and lag.reference_index != 0:  # checked against the reference image
                attrs["composed_mismatch"] = composed_mismatches(lag)
            refined = (getattr(lag, "extra", None) or {}).get("robust_refined")
            if refined is not None:  # the points refined by robust IC-GN in this frame
                attrs["robust_refined"] = int(refined)
            writer.write_frame(k, lag, strain=strain, path=item.path, sha256=item.digest, attrs=attrs)
            if vtk_dir is not None:
                from ..export import write_vtk

                write_vtk(lag, Path(vtk_dir) / f"frame_{k:06d}.vtu", invalid="nan", strain=strain)
            if figure_dir is not None and k % figure_every == 0:
                from ..plots.fields import write_field_figure

                write_field_figure(Path(figure_dir) / f"frame_{k:06d}.png", ref_img, lag, strain, cracks=cracks,
                                   title=f"frame {k}" + (f": {Path(item.path).name}" if item.path else ""),
                                   region=record.region if record is not None else None)
            if callback is not None:
                callback(k, lag, strain)

        def stored_state(index: int) -> Field2D:
            with wb.lock:
                return writer.read_frame(index)

        bar = tqdm(total=total, unit="frame", desc="track", disable=not progress)
        carry, reference_masks = None, None
        if custom_tracker is None or _takes_carried(custom_tracker):  # a moved reference's region and cracks
            described = options  # the run's region and cracks: the record's with a custom tracker (the command line's)
            if custom_tracker is not None and record is not None:
                described = record.tracker_kwargs()
            carry = _carry_for(described, ref_img.shape)
            if carry is not None:
                reference_masks = lambda: _reference_masks(described, ref_img.shape, points0)  # noqa: E731
        reader = read_ahead(frames, _frame_loader(ref_img.shape, ref_name))
        if client is not None:
            tracker0_holder[0] = None  # the workers prepare the reference
            try:
                _run_on_dask(client, reader, policy, writer, wb, summary, bar, finish, stored_state,
                             builder=_builder(make_tracker, budget, order, search_name), ref_img=ref_img,
                             everywhere=everywhere, points0=points0, order=order, settings=settings, out=out,
                             verify=_verify_here(ref_img, points0, verify_threshold, options.get("device"),
                                                 reference_masks=reference_masks, spread=verify_rule),
                             carry=carry)
            finally:
                reader.close()
                wb.close(raise_error=False)
                bar.close()
            trim_memory()
            summary.seconds = time.perf_counter() - t_start
            return summary
        kind = _Track2D(ref_img=ref_img, everywhere=everywhere, points0=points0, order=order, guess=guess,
                        reference_tracker=reference_tracker, tracker_for=tracker_for,
                        release_reference=lambda: tracker0_holder.__setitem__(0, None), writer=writer,
                        stored_state=stored_state, finish=finish, out=out, verify_threshold=verify_threshold,
                        device=options.get("device"), carry=carry, reference_masks=reference_masks,
                        verify_spread=verify_rule)
        try:
            run_sequence(kind, reader, policy, done=done, wb=wb, summary=summary, bar=bar, out=out, lock=wb.lock)
        finally:
            reader.close()
            wb.close(raise_error=False)
            bar.close()
            del kind
    trim_memory()
    summary.seconds = time.perf_counter() - t_start
    return summary


class _Track2D:
    """The 2-D kind of :func:`dic.sequence.engine.run_sequence`: a :class:`dic.Tracker` per reference
    (the reference image's, or a moved one's), results composed back to the reference image (Lagrangian)."""

    noun, images_noun, inputs_noun = "frame", "the image", "frames"

    def __init__(self, *, ref_img, everywhere, points0, order, guess, reference_tracker, tracker_for, release_reference,
                 writer, stored_state, finish, out, verify_threshold=None, device=None, carry=None,
                 reference_masks=None, verify_spread=None):
        self.ref_img, self.everywhere, self.points0, self.order, self.guess = ref_img, everywhere, points0, order, guess
        self._reference_tracker, self._tracker_for, self._release = reference_tracker, tracker_for, release_reference
        self.writer, self.stored_state, self._finish, self.out = writer, stored_state, finish, out
        self.verify_threshold, self.device = verify_threshold, device
        self.verify_spread = verify_spread  # robust standard deviations that can lower the threshold (None: fixed)
        self._verifier = None  # the check of composed frames (dic.sequence.verification), built at its first frame
        self._carry = carry  # a moved reference's -> its tracker's keywords of the carried region and cracks (or None)
        self._reference_masks = reference_masks  # () -> the reference subsets' pixel masks, for the check (or None)
        self.current = _Ref(0, ref_img, reference_tracker(), everywhere)
        self.prev: Field2D | None = None  # the last frame's field (computed or read back)

    @property
    def reference_index(self) -> int:
        return self.current.index

    def move_reference(self, r: int, image, state) -> None:
        if r == 0:
            self.current = _Ref(0, self.ref_img, self._reference_tracker(), self.everywhere)
            return
        try:
            moved = _moved(self.points0, state, r, None, self.order)
        except ValueError as exc:  # no valid point
            raise CannotServe(str(exc)) from None
        self._release()  # free the previous reference's data before preparing the new one
        self.current = None
        moved.image = _host(image)  # a reference is prepared on the host (once per reference)
        carried = self._carry(moved.moved) if self._carry is not None else None
        moved.tracker = self._tracker_for(moved.image, moved.moved.points, carried)
        self.current = moved

    def measure(self, k: int, image, *, final: bool = True):
        ref = self.current
        start = _guess_for(ref, self.prev, k, self.order) if self.guess == "previous" else None
        return _lagrangian(ref, ref.tracker.track(image, guess=start), self.points0, k)

    def kept(self, result) -> None:
        pass

    def quality(self, result) -> tuple[float, float]:
        return _quality(result, self.current.ok)

    def accept(self, k: int, result: Field2D, image) -> Field2D:
        if self.verify_threshold is not None and result.reference_index != 0:
            if self._verifier is None:
                masks = self._reference_masks() if self._reference_masks is not None else None
                self._verifier = ComposedVerifier(self.ref_img, self.points0, int(result.subset), self.verify_threshold,
                                                  device=self.device, pixel_mask=masks, spread=self.verify_spread)
            self._verifier.apply(result, image)  # before it can anchor a reference or guess the next frame
        self.prev = result
        return result

    def mismatches(self, result: Field2D) -> int:
        return composed_mismatches(result) if self.verify_threshold is not None else 0

    def check_done(self, k: int, item: Loaded) -> int:
        attrs = self.writer.frame_attrs(k)
        self.writer.check_frame(k, item.path, _digest_like(str(attrs.get("sha256", "")), item.image, item.digest))
        return int(attrs.get("reference_index", 0))

    def resume(self, k: int, image, *, next_done: bool) -> None:
        self.prev = None if next_done else self.stored_state(k)

    def counts(self, result) -> tuple[int, int]:
        valid = np.asarray(result.valid, bool)
        return int(valid.sum()), int(valid.size)

    def write(self, k: int, result, item: Loaded, seconds: float) -> None:
        self._finish(k, result, seconds, item)

    def failed(self, item: Loaded, exc: BaseException) -> BaseException:
        if not isinstance(exc, (ValueError, OSError)):
            return exc
        saved = f"; frames before it are saved in {self.out}" if item.index > 1 else ""
        return ValueError(f"frame {item.index} ({os.fspath(item.path) or 'array'}): {exc}{saved}")


def _carry_for(options: dict, shape):
    """What a moved reference's tracker is cut by, from the run's tracker ``options`` (None: nothing to carry):
    ``carry(moved)`` -> its :class:`dic.Tracker` keywords (``pixel_region``, ``blocked_pixels``, ``cracks``): the
    run's region (a mask or polygon ROI, or excluded shapes, with ``subset_mask="region"``) and declared cracks
    carried into the moved reference's frame by its measured field
    (:meth:`dic.correlation.lagrangian.MovedReference.carry_region`, :meth:`~.MovedReference.carry_cracks`), so
    that its subsets are masked as the reference image's are (docs/dic2d.md, "Masks and cracks carried to a
    moved reference")."""
    from ..correlation.subset_masks import region_pixel_mask
    from ..cracks import as_cracks

    region_px = None
    if options.get("roi") is not None and options.get("subset_mask", "region") == "region":
        region_px = region_pixel_mask(options["roi"], shape)
    cracks = as_cracks(options.get("cracks"))
    if region_px is None and not cracks:
        return None
    subset = int(options.get("subset", 21))

    def carry(moved: MovedReference) -> dict:
        pixel_region, blocked = moved.carry_cut(region_px, cracks, subset)
        kw = {"cracks": None}
        if pixel_region is not None:
            kw["pixel_region"] = pixel_region
        if blocked is not None:
            kw["blocked_pixels"] = blocked
        return kw

    return carry


def _takes_carried(make_tracker) -> bool:
    """Whether a custom ``make_tracker`` takes the ``carried`` keyword (the Tracker keywords of a moved reference's
    carried region and cracks, :func:`_carry_for`), as the default one and ``specula track``'s do."""
    import inspect

    try:
        return "carried" in inspect.signature(make_tracker).parameters
    except (TypeError, ValueError):
        return False


def _reference_masks(options: dict, shape, points0):
    """(N, subset²) bool: the pixels the default tracker's reference subsets keep (region and cracks, as
    :class:`dic.Tracker` masks them), or None where every pixel is kept; the check of composed frames compares
    those pixels only (:class:`dic.sequence.verification.ComposedVerifier` ``pixel_mask``)."""
    from ..correlation.subset_masks import tracking_pixel_masks
    from ..cracks import as_cracks, blocked_pixels

    cracks = as_cracks(options.get("cracks"))
    blocked = (lambda pts, size: blocked_pixels(pts, size, cracks)) if cracks else None
    return tracking_pixel_masks(points0, int(options.get("subset", 21)), shape, options.get("roi"),
                                options.get("subset_mask", "region"), blocked)


def _same_image(image, reference) -> bool:
    """Whether ``image`` is the reference image (the same array, or equal values: a copy on a Dask worker)."""
    if image is reference:
        return True
    a, b = np.asarray(image), np.asarray(reference)
    return a.shape == b.shape and bool(np.array_equal(a, b))


def _builder(make_tracker, budget, order, search):
    from .distributed import ReferenceBuilder

    return ReferenceBuilder(make_tracker, budget, order, search)


def _run_on_dask(client, reader, policy, writer, wb, summary, bar, finish, stored_state, *, builder, ref_img, everywhere,
                 points0, order, settings, out, verify=None, carry=None):
    """The frames of :func:`track_sequence` correlated on a Dask cluster, written here in frame order.

    A window of frames is in flight at once (two per worker thread, plus one); the oldest is written
    first. ``every:N``: the frames of a block go out once the block's key frame (its reference) is known.
    ``verify(field, image) -> int``, optional: the check of a composed frame against the reference image
    (:func:`_verify_here`), run here as each frame comes back, before it is written or anchors a reference
    (as the single-process loop does: identical results). ``carry(moved) -> dict``, optional
    (:func:`_carry_for`): a moved reference's tracker keywords of the region and cracks carried into its
    frame, worked out here once per reference as one process does and shipped with the reference
    (:class:`dic.sequence.distributed.CarriedMasks`: the region packed 8 px a byte), so that the workers mask
    its subsets alike (identical results).
    """
    import json
    import uuid

    from .distributed import CarriedMasks, held, track_on_worker
    from .engine import run_on_dask

    token = _sha256_text(json.dumps(settings, sort_keys=True, default=str) + _digest(ref_img))[:16] + "-" + \
        uuid.uuid4().hex[:8]
    # the reference data go to the cluster as the results of tasks that hold them (not scattered): if
    # every worker holding them dies, the scheduler computes them again instead of cancelling the frames
    import cloudpickle

    try:
        cloudpickle.dumps(builder)
    except Exception as exc:  # a make_tracker that cannot be pickled (it holds a lock, an open file, ...)
        raise ValueError(f"make_tracker cannot be sent to the Dask workers ({type(exc).__name__}: {exc}); with client= "
                         "it must be picklable by cloudpickle (create what it holds inside it)") from None
    build = client.submit(held, builder, key=f"specula-{token}-builder", pure=False)
    key_states: dict[int, Field2D] = {}  # every:N: the key frames computed in this call
    images: dict[int, Any] = {}  # images of key frames (the next block's reference): bounded
    done = set(writer.done_frames())

    def scattered(index: int, image, points, digest: str, carried: CarriedMasks | None = None) -> dict:
        return {"key": f"{token}:{index}:{digest}",
                "image": client.submit(held, image, key=f"specula-{token}-reference-{index}", pure=False),
                "points": None if points is None else client.submit(held, points, key=f"specula-{token}-points-{index}",
                                                                   pure=False),
                "carried": None if carried is None else client.submit(held, carried, key=f"specula-{token}-carried-{index}",
                                                                     pure=False)}

    over = builder.over_budget(len(points0))
    cur = _Ref(0, ref_img, None, everywhere)
    skipped_for = None  # every:N: a key frame that could not serve as a reference (no valid point)
    cur_data = scattered(0, ref_img, points0 if over else None, "")

    def failed(item, exc):
        if not isinstance(exc, (ValueError, OSError)):
            return exc
        saved = f"; frames before it are saved in {out}" if item.index > 1 else ""
        return ValueError(f"frame {item.index} ({item.path or 'array'}): {exc}{saved}")

    def collect(k, item, ref, raw, seconds):
        lag = _lagrangian(ref, raw, points0, k)
        n_mismatch = verify(lag, item.image) if verify is not None else 0
        wb.submit(lambda k=k, lag=lag, s=seconds, it=item: finish(k, lag, s, it))
        if policy.kind == "every" and k % policy.every == 0:
            key_states[k] = lag
        valid = np.asarray(lag.valid, bool)
        return int(valid.sum()), int(valid.size), int(ref.index), n_mismatch

    def reference(r: int, wait):
        """The reference frame r of the next block (its key frame's result known: waited for)."""
        nonlocal cur, cur_data
        if r not in key_states:
            wait(r)
        state = key_states.get(r) or stored_state(r)
        if r not in images:
            raise ValueError(f"cannot resume {out}: the image of frame {r}, the reference of the next frame, "
                             "was not given again; give the same frames as the run that wrote the file")
        try:
            cur_new = _moved(points0, state, r, images[r], order)
        except ValueError:  # no valid point: the key frame's own reference stays (as on one machine)
            if state.reference_index != cur.index or r == cur.index:
                raise ValueError(f"frame {r} has no valid point and cannot serve as a reference") from None
            return
        carried = CarriedMasks(carry(cur_new.moved)) if carry is not None else None  # as _Track2D.move_reference
        cur = cur_new
        cur_data = scattered(r, images[r], cur.moved.points, _digest(images[r]), carried)
        for i in [i for i in key_states if i < r]:  # key frames before the reference: not needed again
            del key_states[i]

    def before(k, item, wait):
        nonlocal skipped_for
        if policy.kind != "every":
            return
        r = policy.start(k, 0)
        if r != cur.index and r != skipped_for:
            was = cur.index
            reference(r, wait)
            if cur.index == was:  # the key frame could not serve: remember not to try again
                skipped_for = r
        if k % policy.every == 0:
            images[k] = item.image
        for i in [i for i in images if i not in (k, cur.index)]:
            del images[i]

    def check_done(k, item):
        writer.check_frame(k, item.path, item.digest)

    def submit(k, item):
        return client.submit(track_on_worker, cur_data["key"], build, cur_data["image"], cur_data["points"],
                             item.image, cur_data["carried"], key=f"specula-{token}-frame-{k}", pure=False), cur

    run_on_dask(client, reader, done=done, wb=wb, summary=summary, bar=bar, token=token, submit=submit,
                collect=collect, check_done=check_done, failed=failed, before=before)


def _verify_here(ref_img, points0, threshold, device, reference_masks=None, spread=None):
    """The check of composed frames of a Dask run, run in this process (the one that writes): a callable
    ``(field, image) -> points that failed`` that changes ``field`` in place as :meth:`_Track2D.accept` does (a
    :class:`dic.sequence.verification.ComposedVerifier` built at the first composed frame, given the reference
    subsets' pixel masks ``reference_masks()`` as one process gives them: masked points checked on their kept
    pixels, and the threshold lowered per frame by ``spread`` as there); None without a check (``threshold`` None)."""
    if threshold is None:
        return None
    holder = []

    def verify(field, image) -> int:
        if int(field.reference_index) == 0:  # correlated against the reference image: nothing composed
            return 0
        if not holder:
            masks = reference_masks() if reference_masks is not None else None
            holder.append(ComposedVerifier(ref_img, points0, int(field.subset), threshold, device=device,
                                           pixel_mask=masks, spread=spread))
        holder[0].apply(field, image)
        return composed_mismatches(field)

    return verify


def _sha256_text(text: str) -> str:
    import hashlib

    return hashlib.sha256(text.encode()).hexdigest()


def _planned_points(shape, options: dict):
    """(POIs, order) the default tracker would use, without preparing anything (None if options are bad:
    the tracker then says why)."""
    from kernels.checks import as_points
    from kernels.icgn import check_subset_order

    from ..correlation.points import check_step, grid

    try:
        subset, order = check_subset_order(options.get("subset", 21), options.get("order", 1))
        if options.get("points") is not None:
            return as_points(options["points"]), order
        step = options.get("step")
        step = check_step(step) if step is not None else max(1, subset // 2)
        return grid(shape, step, margin=subset // 2, roi=options.get("roi")), order
    except ValueError:
        return None


def _guess_for(ref: _Ref, prev: Field2D | None, k: int, order: int):
    """The initial guess of frame k against ``ref``, from the previous frame's (Lagrangian) result."""
    if prev is None or prev.index != k - 1 or prev.index == ref.index:
        return None
    if ref.index == 0:
        return _guess((_params(prev), np.asarray(prev.valid, bool)))
    valid = np.asarray(prev.valid, bool) & ref.ok
    return _guess((ref.moved.relative(_params(prev)), valid))
