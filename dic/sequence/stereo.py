"""Stereo-DIC sequences: match the reference pair once, track every later pair, write as you go.

Reference strategies (``reference=``, :mod:`dic.sequence.reference`): the temporal tracks of
:class:`dic.StereoCorrelation` follow the reference pair ("fixed") or move to a later state's
pair (:meth:`~dic.StereoCorrelation.move_reference`: "incremental", "every:N", "auto"); the
left -> right match of the reference pair is done once, and every state is reported relative to the
reference state (Lagrangian), with the state its tracks used in ``reference_index``.

On the sequence engine's pipeline (:mod:`dic.sequence.pipeline`): the next pairs are read on a
thread ahead of the correlation, the finished states written on a thread behind it.

:func:`stereo_sequence` runs :class:`dic.StereoCorrelation` over a list of image pairs
(arrays or image files; the first pair is the reference) and writes each state through the
results store (:class:`dic.store.ResultWriter`, kind ``stereo``) as soon as it is finished, so
that an interrupted run keeps every finished state and a rerun with the same output, images and
settings resumes after the last one (the reference match is read back, not recomputed).
:func:`read_stereo` and :func:`read_field` (from :mod:`dic.store`) read a file back into
:class:`~dic.field3d.Field3D` objects. File layout: docs/results_format.md (format
``specula-stereo``), docs/stereo.md ("Sequences and the result file").
"""
from __future__ import annotations

import os
import threading
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .._stereo import StereoCorrelation, as_rig
from ..field3d import Field3D, StereoStatus
from ..store import SCHEMA_VERSION, ResultReader, ResultWriter, StereoResults, image_digest, read_field, read_stereo
from ..store import STEREO_FORMAT_NAME as FORMAT_NAME
from .engine import CannotServe, SequenceSummary, run_on_dask, run_sequence
from .options import StereoOptions
from .pipeline import Loaded, WriteBehind, load_image, read_ahead, trim_memory
from .reference import AUTO_VALID, AUTO_ZNCC, parse_reference
from .stereo_checks import composed_mismatch_attrs, composed_mismatches

__all__ = ["stereo_sequence", "read_stereo", "read_field", "StereoResults", "FORMAT_NAME", "SCHEMA_VERSION"]


_load = load_image


def stereo_sequence(rig, pairs: Sequence, out, *, reference: str = "fixed", mode: str = "resume",
                    progress: bool = False, callback: Callable[[int, Field3D, None], None] | None = None, vtk_dir=None,
                    vtk_stem: str = "stereo", figure_dir=None, figure_every: int = 1, auto_valid: float = AUTO_VALID,
                    auto_zncc: float = AUTO_ZNCC, guess: str | None = None, client=None, compression=None,
                    **options) -> SequenceSummary:
    """Stereo DIC of an image-pair sequence, written state by state to an HDF5 file.

    Parameters
    ----------
    rig : calibration.stereo.StereoRig, or a rig file in any format Specula reads (Specula JSON,
        OpenCV YAML/XML/JSON, VIC-3D XML, DICe XML; :func:`dic._stereo.as_rig`)
    pairs : sequence of (left, right)
        Images (arrays or file paths: TIFF, PNG, BMP). ``pairs[0]`` is the reference state;
        state ``k`` is ``pairs[k]``. Each state is tracked with the previous state's parameters
        as initial guess (the reference match left -> right is done once).
    out : str or Path
        The ``.h5`` file (layout: docs/results_format.md). An existing file with the same rig,
        reference images and settings is resumed (finished states are skipped) unless
        ``mode="overwrite"`` (``"new"`` refuses an existing file); an incompatible one, or one
        whose finished states were computed from other image pairs than those given now, raises
        ``ValueError``; a file another process is writing raises
        :class:`dic.store.ResultFileInUse`, a full disk :class:`dic.store.ResultWriteError`
        (both ``ValueError``; finished states stay in the file).
    reference : "fixed" | "incremental" | "every:N" | "auto"
        Which pair the left and right temporal tracks of state ``k`` start from
        (:mod:`dic.sequence.reference`): the reference pair (fixed), pair ``k - 1`` (incremental),
        pair ``N * floor((k - 1) / N)`` (every:N), or the previous state's until its valid fraction
        (among the points that reference can track) falls below ``auto_valid`` or the median track
        ZNCC (the lower of left and right) below ``auto_zncc``, then pair ``k - 1`` (auto). Results
        are always relative to the reference state at the original points (Lagrangian); each
        state's ``reference_index`` (in the file and on the :class:`Field3D`) says which pair its
        tracks used. A point not valid in the state a moved reference starts from, but whose place
        there is interpolated from a close triangle of valid neighbours (left and right track each,
        :func:`dic.correlation.lagrangian.fill_reference`), is tracked again from that place and
        comes back once both tracks are accepted; each such state's ``reference_interpolated``
        attribute counts these points. Other points lost on the way stay invalid with the status
        they had then.
    auto_valid, auto_zncc : float in [0, 1]
        The thresholds of ``reference="auto"`` (defaults 0.95 and 0.95).
    mode : "resume" | "overwrite" | "new"
    progress : bool
        Show a tqdm progress bar.
    callback : callable(index, field, strain), optional
        The callback of :func:`dic.sequence.track_sequence`: called with each state's index and
        :class:`Field3D` (``strain`` is None: a state's surface strain is in its ``Field3D``) once
        it is in the file and its VTK and figure files are written (not for skipped states; later
        states are called on the writer thread, in order).
    vtk_dir : folder, optional
        Write ``<vtk_stem>_<index>.vtu`` per state as it finishes (every point with a position, NaN
        where invalid: the same point set at every state) and keep ``<vtk_stem>.pvd`` (the ParaView
        collection of the states written so far) up to date. Resuming, the finished states that
        have no file there yet get theirs first.
    figure_dir : folder, optional
        Write the PNG maps of :func:`dic.plots.fields.write_figures`
        (``state_<index>_<quantity>.png``) of every ``figure_every``-th state as it finishes.
    guess : "previous" | "none", optional
        ``"previous"`` (default without ``client``): each state starts from the previous state's
        parameters; ``"none"`` (default, and the only choice, with ``client``): from zero and the
        global shift, so states are independent (stored in the settings).
    client : distributed.Client or scheduler address, optional
        Measure the states on a Dask cluster (docs/dic2d.md, "Sequences on several machines"): the
        reference match is done here once, each worker prepares the reference pair once and keeps it,
        the states are written here in order; results identical to ``guess="none"`` on one process.
        Only ``reference="fixed"`` can be distributed (every other strategy waits for earlier states).
    compression : "none" | "lzf" | "gzip" | "gzip:N", optional
        How the file's datasets are compressed (default ``"none"``: the fastest; docs/results_format.md). A resumed
        file keeps the setting it was written with.
    options
        :class:`dic.StereoCorrelation` keywords (``step``, ``subset``, ``order``,
        ``frame``, ``roi``, ``points``, ``epipolar_tol_px``, ``zncc_min``, ``strain_window``,
        ``max_iter``, ``tol``, ``triangulation``, ``device``, ``strain_type``: "green-lagrange" (default),
        "small" or "euler-almansi", recorded in the run record), and ``verify_composed`` (default None: on
        with a moved reference) / ``verify_zncc`` (default 0.95): each state tracked from a moved reference has
        its composed left and right tracks checked against the reference pair
        (:mod:`dic.correlation.stereo_verify`); points below ``verify_zncc`` in either camera get the status
        ``COMPOSED_MISMATCH``, counted per state in the file (``composed_mismatch``, and per camera) and in
        :attr:`SequenceSummary.n_mismatch`. False: no check (a file written before the option resumes only so).
        ``verify_spread`` (default 4; "off": ``verify_zncc`` alone): each camera's threshold of a state lowered to
        its median ZNCC less that many robust standard deviations, with the peak test, as 2-D
        (:func:`kernels.verify.composed_failures`).
        ``right_track_mask`` (default True: the right track's subsets masked by the region mapped through the
        match, :mod:`dic.correlation.right_masks`) and ``cracks`` (declared cracks in left reference px,
        :mod:`dic.stereo_cracks`: no subset or strain window across them; stored in the file's settings).
        ``motion_prediction`` ("velocity" or "none"; default: "velocity" for a new file, a resumed file's own, "none"
        for files written before the option): how each state's temporal tracks start, with ``guess="previous"``:
        "velocity" extrapolates the two states before (the first: the reference pair, zero) at constant velocity (a
        start that accepts under 95 % of the points the state before had runs again from the previous state + the
        global shift;
        :class:`dic.StereoCorrelation`), "none" starts from the previous state + that shift.

    Returns
    -------
    SequenceSummary
        The same summary as :func:`dic.sequence.track_sequence`'s: per state computed in this call
        (the reference state 0 included when it was written now) its index, valid and total point
        counts, seconds and reference index; the finished states skipped; the file. No state is
        held in memory once written: read them back with :func:`read_stereo` / :func:`read_field`.
    """
    if isinstance(client, str):  # a scheduler address: connected here, closed when the run ends
        from .distributed import call_connected

        return call_connected(stereo_sequence, locals())
    from tqdm import tqdm

    from kernels.checks import positive_int

    t_start = time.perf_counter()
    _import_ahead()
    policy = parse_reference(reference, auto_valid=auto_valid, auto_zncc=auto_zncc)
    figure_every = positive_int(figure_every, "figure_every")
    if callback is not None and not callable(callback):
        raise ValueError(f"callback must be callable, got {type(callback).__name__}")
    vtk_stem = str(vtk_stem)
    if not vtk_stem or os.sep in vtk_stem or "/" in vtk_stem:
        raise ValueError(f"vtk_stem must be a plain file name prefix, got {vtk_stem!r}")
    pairs = list(pairs)
    if not pairs:
        raise ValueError("pairs is empty: give at least the reference (left, right) pair")
    for k, p in enumerate(pairs):
        if not isinstance(p, (tuple, list)) or len(p) != 2:
            raise ValueError(f"pairs[{k}] must be a (left, right) pair, got {type(p).__name__}")
    out = Path(os.fspath(out))
    for d, what in ((vtk_dir, "vtk_dir"), (figure_dir, "figure_dir")):
        if d is not None and Path(os.fspath(d)).exists() and not Path(os.fspath(d)).is_dir():
            raise ValueError(f"{what} must be a folder, but {d} is a file")
    left_ref, lp = _load(pairs[0][0], "reference left image")
    right_ref, rp = _load(pairs[0][1], "reference right image")
    device = options.pop("device", None)
    rig = as_rig(rig, image_size=(np.shape(left_ref)[1], np.shape(left_ref)[0]))
    if out.suffix.lower() not in (".h5", ".hdf5"):
        raise ValueError(f"the output must be an HDF5 file ending in .h5, got {out.name}")
    if guess is None:
        guess = "previous" if client is None else "none"
    if guess not in ("previous", "none"):
        raise ValueError(f"guess must be 'previous' or 'none', got {guess!r}")
    if client is not None and policy.kind != "fixed":
        raise ValueError(f"reference={policy.text!r} cannot be distributed: each state may wait for the ones before "
                         "it; use reference='fixed' with client=, or run without client")
    if client is not None:
        if guess != "none":
            raise ValueError("guess='previous' chains each state to the one before it and cannot be distributed: "
                             "with client= every state starts from guess='none' (leave guess out)")
        from .distributed import connect

        client = connect(client)
    if options.get("motion_prediction") is None:  # not chosen: a resumed file keeps its own, a new one "velocity"
        options["motion_prediction"] = _stored_motion_prediction(out, mode) or "velocity"
    # the run record (dic.sequence.options): every option that affects the results, validated once (a mask file is
    # read once), stored with its defaults and compared on resume whichever writer (library or CLI) made the file
    record = StereoOptions.from_keywords({**options, "reference": policy.text, "auto_valid": policy.auto_valid,
                                          "auto_zncc": policy.auto_zncc, "guess": guess}, shape=np.shape(left_ref))
    settings, options = record.to_settings(), record.correlation_kwargs()
    ref_digests = (image_digest(left_ref), image_digest(right_ref))
    writer = ResultWriter(out, kind="stereo", reference_path=(lp, rp), reference_shape=np.shape(left_ref),
                          reference_sha256=ref_digests, settings=settings, rig=rig, mode=mode,
                          compression=compression, settings_check=record.resume_check)
    writer.hold_outputs(vtk_dir, figure_dir)  # their locks, released with the writer's (dic.store.files)
    summary = SequenceSummary(path=out)
    with writer:
        done = set(writer.done_frames())
        # resuming: every finished state must have been computed from the pair given for it now (the later
        # states are checked as they are read, below)
        if 0 in done:
            writer.check_frame(0, (lp, rp), ref_digests)
        match = writer.read_match()
        t0 = time.perf_counter()
        sc = StereoCorrelation(rig, left_ref, right_ref, match=match, device=device, progress=progress, **options)
        if match is None:
            writer.write_match(sc.match)
        vtk_written: set[int] = set()  # states with a VTK file of this run or of the run before (resuming)
        if vtk_dir is not None and done:  # the VTK files of finished states: whole, or rewritten now
            from ..export import restore_vtk_files, write_pvd

            restore_vtk_files(writer, vtk_dir, vtk_stem, done)
            vtk_written = set(done)
            write_pvd(vtk_dir, [(i, f"{vtk_stem}_{i:06d}.vtu") for i in sorted(vtk_written)], stem=vtk_stem)

        def finish(k, f, paths, digests, seconds):
            attrs = {"seconds": seconds, "reference_index": int(f.reference_index)}
            if f.reference_interpolated is not None:  # the valid points whose place in the tracks' reference was interpolated
                attrs["reference_interpolated"] = int(np.count_nonzero(f.reference_interpolated))
            if record.verify_composed and f.reference_index != 0:  # checked against the reference pair
                attrs.update(composed_mismatch_attrs(f, record.verify_zncc))
            writer.write_frame(k, f, path=paths, sha256=digests, attrs=attrs)
            if vtk_dir is not None:
                from ..export import write_pvd, write_vtk

                name = f"{vtk_stem}_{k:06d}.vtu"
                write_vtk(f, Path(vtk_dir) / name, invalid="nan")
                vtk_written.add(k)
                write_pvd(vtk_dir, [(i, f"{vtk_stem}_{i:06d}.vtu") for i in sorted(vtk_written)], stem=vtk_stem)
            if figure_dir is not None and k % figure_every == 0:
                from ..plots import fields as plots

                plots.write_figures(f, left_ref, figure_dir, prefix=f"state_{k:06d}_", region=record.region,
                                    cracks=record.cracks)
            if callback:
                callback(k, f, None)

        seconds0 = float(time.perf_counter() - t0)

        def load(k, pair) -> Loaded:
            (L, lpath), (R, rpath) = _load(pair[0], f"left image of pair {k}"), _load(pair[1], f"right image of pair {k}")
            return Loaded(k, (L, R), (lpath, rpath), (image_digest(L), image_digest(R)))

        # the later states: the next pairs are read on a thread ahead, the finished ones written on one behind
        wb = WriteBehind(depth=2)
        reader = read_ahead(pairs[1:], load, first=1)
        with tqdm(total=len(pairs), initial=1, unit="pair", desc="stereo", disable=not progress) as bar:
            try:
                if 0 not in done:  # written on the writer thread, its strain and uncertainty computed there first
                    state0 = sc.reference_field(complete=False)
                    wb.submit(lambda: finish(0, sc.complete(state0), (lp, rp), ref_digests, seconds0))
                    summary.add(0, *_counts(state0), seconds0, 0)
                else:
                    summary.skipped += 1
                if client is not None:
                    _stereo_on_dask(client, reader, writer, wb, done, summary, bar, finish,
                                    _StereoBuilder(rig, left_ref, right_ref, sc.match, device, options))
                else:
                    kind = _Stereo(sc, writer, finish, use_previous=guess == "previous")
                    kind.verified = bool(record.verify_composed)
                    run_sequence(kind, reader, policy, done=done, wb=wb, summary=summary, bar=bar, out=out,
                                 lock=wb.lock)
                wb.close(raise_error=True)  # (state 0 when no later pair was given)
            finally:
                reader.close()
                wb.close(raise_error=False)
        trim_memory()
    summary.seconds = time.perf_counter() - t_start
    return summary


def _import_ahead() -> None:
    """Import the SciPy parts a stereo run needs later (k-d trees of the match and the acceptance, the strain's box
    filters; 0.2-0.45 s on first import) on a background thread, while this one reads the reference pair and runs
    the kernels and SIFT, which release the GIL. Python's import locks make an import the run reaches first wait
    for this one."""
    import sys

    if "scipy.spatial" in sys.modules and "scipy.ndimage" in sys.modules:
        return

    def work():
        try:
            import scipy.ndimage  # noqa: F401
            import scipy.spatial  # noqa: F401
        except Exception:  # noqa: BLE001 - the run imports them itself and reports what fails
            pass

    threading.Thread(target=work, name="specula-imports", daemon=True).start()


def _counts(field: Field3D) -> tuple[int, int]:
    """(valid points, points computed) of a state: the computed ones are those inside the region of interest
    whose reference subset could be correlated (status not NOT_COMPUTED), not the whole grid, which keeps the
    points outside the region."""
    computed = np.asarray(field.status) != StereoStatus.NOT_COMPUTED
    return int(np.count_nonzero(np.asarray(field.valid, bool) & computed)), int(np.count_nonzero(computed))


def _stored_motion_prediction(out: Path, mode: str) -> str | None:
    """The ``motion_prediction`` of the stereo run in an existing result file that this call would resume ("none" for
    a file written before the option), or None (no such file, ``mode="overwrite"``, or not a readable stereo file:
    the writer says what is wrong with it)."""
    if mode == "overwrite" or not out.is_file():
        return None
    try:
        with ResultReader(out, kind="stereo") as reader:
            settings = reader.settings
    except Exception:  # noqa: BLE001 - not ours to judge here: ResultWriter refuses it with its own message
        return None
    if not isinstance(settings, dict) or not settings:
        return None
    return settings.get("motion_prediction") or StereoOptions.ADDED_OPTIONS["motion_prediction"]


class _Stereo:
    """The stereo kind of :func:`dic.sequence.engine.run_sequence`: a :class:`dic.StereoCorrelation`
    whose temporal tracks follow the reference pair or a later state's (its public sequence protocol:
    ``measure``, ``move_reference``, ``trackable``, ``set_previous``, ``saved_previous``)."""

    noun, images_noun, inputs_noun = "state", "the images", "pairs"

    def __init__(self, sc: StereoCorrelation, writer, finish, *, use_previous: bool):
        self.sc, self.writer, self._finish, self.use_previous = sc, writer, finish, use_previous
        self._saved = None  # the previous state a state measured twice (auto) starts from both times
        self._tried = None  # the first result of a state measured twice (auto), until it is kept or measured again

    @property
    def reference_index(self) -> int:
        return self.sc.reference_index

    def move_reference(self, r: int, image, state) -> None:
        if r == 0:
            self.sc.move_reference()
        elif not np.any(state.valid):
            raise CannotServe(f"state {r} has no valid point")
        else:
            self.sc.move_reference(image[0], image[1], state)

    def measure(self, k: int, image, *, final: bool = True) -> Field3D:
        if self._saved is not None:  # measured once already, from another reference: from the same previous state
            self.sc.restore_previous(self._saved)
            self._saved = None
            if self._tried is not None:  # that result is not kept
                self.sc.discard(self._tried)
        if not final:
            self._saved = self.sc.saved_previous()
        L, R = image
        # the state's strain and uncertainty are computed on the writer thread (write), while the next state tracks
        result = self.sc.measure(L, R, index=k, warn=final, use_previous=self.use_previous, complete=False)
        self._tried = result if not final else None
        return result

    def kept(self, result: Field3D) -> None:
        self._saved = self._tried = None
        self.sc.warn_if_mostly_invalid(result)

    def quality(self, result: Field3D) -> tuple[float, float]:
        return _quality(result, self.sc.trackable)

    def accept(self, k: int, result: Field3D, image) -> Field3D:
        self._saved = self._tried = None
        return result

    def stored_state(self, r: int) -> Field3D:
        return self.writer.read_frame(r)

    def check_done(self, k: int, item: Loaded) -> int:
        self.writer.check_frame(k, item.path, item.digest)
        return int(self.writer.frame_attrs(k).get("reference_index", 0))

    def resume(self, k: int, image, *, next_done: bool) -> None:
        if not next_done:  # the next state starts from this one's parameters (and its images' global shift)
            names = ("params_left", "params_right")
            params_left, params_right = self.writer.frame_arrays(k, names)
            # motion_prediction="velocity": and the state's before it, as in one run (state k started from state
            # k - 1's parameters; state 1 from the reference pair's, state 0's zero)
            before = self.writer.frame_arrays(k - 1, names) if k >= 1 and self.use_previous else None
            self.sc.set_previous(params_left, params_right, images=image, before=before)

    def counts(self, result: Field3D) -> tuple[int, int]:
        return _counts(result)

    verified = False  # composed tracks checked against the reference pair (verify_composed)

    def mismatches(self, result: Field3D) -> int:
        return composed_mismatches(result) if self.verified else 0

    def write(self, k: int, result: Field3D, item: Loaded, seconds: float) -> None:
        # (writer thread) the strain and uncertainty measure() left, then the file, side outputs and callback
        self._finish(k, self.sc.complete(result), item.path, item.digest, float(seconds))

    def failed(self, item: Loaded, exc: BaseException) -> BaseException:
        if exc is item.error:  # a pair that could not be read: its message names it
            return exc
        lpath, rpath = item.path
        return ValueError(f"pair {item.index} ({lpath or 'array'}, {rpath or 'array'}): {exc}")


def _quality(f: Field3D, reference_valid: np.ndarray) -> tuple[float, float]:
    """Valid fraction (among the points the tracks' reference can track: valid in it, or placed there by
    local interpolation) and median track ZNCC (the lower of left and right) of the valid points."""
    valid = np.asarray(f.valid, bool) & reference_valid
    n_ref = int(np.count_nonzero(reference_valid))
    frac = np.count_nonzero(valid) / n_ref if n_ref else 0.0
    z = np.fmin(np.asarray(f.zncc_left, np.float64), np.asarray(f.zncc_right, np.float64))[valid]
    return float(frac), float(np.median(z)) if z.size else 0.0


class _StereoBuilder:
    """A worker's :class:`dic.StereoCorrelation` of the reference pair with the client's match
    (the builder interface of :func:`dic.sequence.distributed.track_on_worker`)."""

    def __init__(self, rig, left, right, match, device, options):
        self.rig, self.left, self.right, self.match, self.device, self.options = rig, left, right, match, device, options

    def __call__(self, _image, _points):
        return _StereoMeasure(StereoCorrelation(self.rig, self.left, self.right, match=self.match, device=self.device,
                                                **self.options))


class _StereoMeasure:
    def __init__(self, sc):
        self.sc = sc

    def track(self, item, guess=None):
        k, L, R = item
        return self.sc.measure(L, R, index=k, use_previous=False)


def _stereo_on_dask(client, reader, writer, wb, done, summary, bar, finish, builder):
    """The later states of :func:`stereo_sequence` measured on a Dask cluster, written here in order
    (:func:`dic.sequence.engine.run_on_dask`)."""
    import uuid

    import cloudpickle

    from .distributed import held, track_on_worker

    token = uuid.uuid4().hex[:16]
    try:
        cloudpickle.dumps(builder)
    except Exception as exc:
        raise ValueError(f"the stereo settings cannot be sent to the Dask workers ({type(exc).__name__}: {exc})") from None
    build = client.submit(held, builder, key=f"specula-{token}-stereo-builder", pure=False)

    def failed(item, exc):
        if exc is item.error:  # a pair that could not be read: its message names it
            return exc
        lpath, rpath = item.path if item.path else (None, None)
        return ValueError(f"pair {item.index} ({lpath or 'array'}, {rpath or 'array'}): {exc}")

    def collect(k, item, _context, f, seconds):
        wb.submit(lambda k=k, f=f, p=item.path, d=item.digest, s=float(seconds): finish(k, f, p, d, s))
        return (*_counts(f), 0)

    def check_done(k, item):
        writer.check_frame(k, item.path, item.digest)

    def submit(k, item):
        L, R = item.image
        return client.submit(track_on_worker, f"{token}:stereo", build, None, None, (k, L, R),
                             key=f"specula-{token}-pair-{k}", pure=False), None

    run_on_dask(client, reader, done=done, wb=wb, summary=summary, bar=bar, token=token, submit=submit,
                collect=collect, check_done=check_done, failed=failed)
