"""Movies of a result file: one map per finished frame (2-D) or state (stereo), one colour range for all.

* :func:`write_animation` — an MP4 (H.264 through imageio-ffmpeg, encoded frame by frame) or an animated
  GIF (Pillow) of one quantity over the frames of a 2-D or stereo result file (``specula animate``).
* :func:`animation_frames` — the same frames as RGB arrays, one at a time (what is encoded).
* :func:`animation_limits` — the one colour range of a movie.
* :func:`animation_quantities` — the quantities a result file can be animated with.

Each frame is the figure of :mod:`dic.plots.fields` (:func:`~dic.plots.fields.field_figure` for a 2-D
frame, :func:`~dic.plots.fields.field3d_figure` for a stereo state; drawn by :mod:`dic.plots.animate`)
with the colour limits of the whole selection: the 1st-99th percentiles of every selected frame's valid
values together (symmetric about zero for a signed quantity whose range spans zero), so a colour means the
same value in every frame. The file is read through :class:`dic.store.ResultFrames` one frame at a time,
twice (the colour range, then the pictures); besides one frame, the first pass keeps the selected
quantity's valid values (8 bytes per valid point and frame).
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .store import ResultFrames

__all__ = ["write_animation", "animation_frames", "animation_limits", "animation_quantities", "ANIMATION_SUFFIXES",
           "MAX_FPS"]

#: movie formats by file suffix
ANIMATION_SUFFIXES = (".mp4", ".gif")
#: the highest frame rate accepted (frames per second)
MAX_FPS = 60.0
#: frames are padded (white) to a multiple of this many pixels: H.264 in yuv420p needs even sizes, and
#: ffmpeg's encoders work in 16-pixel macro blocks (imageio-ffmpeg would otherwise rescale, with a warning)
_MACRO_BLOCK = 16


def animation_quantities(results) -> list[str]:
    """The quantities a result can be animated with (:func:`dic.plots.animate.frame_quantities` of its first
    finished frame): 2-D ``u``, ``v``, ``magnitude`` and the stored strains; stereo ``Z``, ``U``, ``V``,
    ``W``, ``exx``, ``eyy``, ``exy``, ``zncc_stereo``. ``results``: a result file (path), results object
    or an open :class:`dic.store.ResultFrames`."""
    if isinstance(results, ResultFrames):
        return _quantities(results)
    with ResultFrames(results) as src:
        return _quantities(src)


def _quantities(src: ResultFrames) -> list[str]:
    from .plots.animate import frame_quantities

    if not src.indices:
        raise ValueError("the result file has no finished frame to animate")
    return frame_quantities(src.read(src.indices[0]))


def _list(indices, most: int = 10) -> str:
    shown = ", ".join(str(i) for i in indices[:most])
    return shown + (f", ... ({len(indices)} in all)" if len(indices) > most else "")


def _select(src: ResultFrames, wanted) -> list[int]:
    if not src.indices:
        raise ValueError("the result file has no finished frame to animate")
    if wanted is None:
        return list(src.indices)
    try:
        wanted = [int(i) for i in wanted]
    except (TypeError, ValueError):
        raise ValueError(f"frames must be frame indices, got {wanted!r}") from None
    if not wanted:
        raise ValueError("frames is empty: name at least one frame")
    missing = sorted(set(wanted) - set(src.indices))
    if missing:
        raise ValueError(f"no finished frame {_list(missing)} in the result file; finished: {_list(src.indices)}")
    return sorted(set(wanted))


def _check_quantity(src: ResultFrames, quantity) -> None:
    known = _quantities(src)
    if quantity not in known:
        raise ValueError(f"unknown quantity {quantity!r} for this {'stereo' if src.kind == 'stereo' else '2-D'} "
                         f"result file; choose from {', '.join(known)}")


def _limits(src: ResultFrames, indices, quantity) -> tuple[float, float]:
    from .plots.animate import frame_values, movie_limits

    chunks = []
    for index in indices:  # one frame at a time; only the quantity's valid values are kept
        vals = frame_values(src.read(index), quantity)
        chunks.append(vals[np.isfinite(vals)])
    return movie_limits(np.concatenate(chunks), quantity)


def animation_limits(results, quantity: str, *, frames=None) -> tuple[float, float]:
    """The colour range ``(vmin, vmax)`` of a movie of ``quantity`` over the selected frames: the 1st-99th
    percentiles of every selected frame's valid values together, symmetric about zero for a signed
    quantity whose range spans zero (:func:`dic.plots.animate.movie_limits`). Arguments as in
    :func:`animation_frames`."""
    with ResultFrames(results) as src:
        indices = _select(src, frames)
        _check_quantity(src, quantity)
        return _limits(src, indices, quantity)


def _check_image(image):
    if image is None:
        return None
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"image must be the (H, W) grey reference image, got shape {img.shape}")
    return img


def _fit(rgb: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``rgb`` padded with white (or cropped) to ``shape`` (H, W), so every frame of a movie has one size."""
    if rgb.shape[:2] == shape:
        return rgb
    out = np.full((*shape, 3), 255, dtype=np.uint8)
    h, w = min(shape[0], rgb.shape[0]), min(shape[1], rgb.shape[1])
    out[:h, :w] = rgb[:h, :w]
    return out


def animation_frames(results, quantity: str, *, frames=None, image=None, dpi: float = 80, alpha: float = 0.75):
    """Yield ``(index, rgb)`` for every selected frame of a result: ``rgb`` (H, W, 3) uint8, the same
    size for every frame (padded to a multiple of 16 px), drawn with one colour range for all.

    Parameters
    ----------
    results : a result file (path), :class:`~dic.store.TrackResults` or :class:`~dic.store.StereoResults`
    quantity : one of :func:`animation_quantities` (e.g. ``"exx"``, ``"W"``)
    frames : iterable of frame indices (default: every finished frame); each must be finished
    image : (H, W) grey reference image drawn beneath the maps (the left one for stereo), or None
    dpi : resolution of the frames (a 5-inch map at 80 dpi is 400 px wide), 10 to 600
    alpha : opacity of the map over the reference image
    """
    from .plots.animate import frame_rgb

    if not (isinstance(dpi, (int, float)) and np.isfinite(dpi) and 10 <= dpi <= 600):
        raise ValueError(f"dpi must be a number from 10 to 600, got {dpi!r}")
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must be in [0, 1], got {alpha!r}")
    img = _check_image(image)
    with ResultFrames(results) as src:
        indices = _select(src, frames)
        _check_quantity(src, quantity)
        limits = _limits(src, indices, quantity)
        shape = None
        for index in indices:  # one figure at a time
            rgb = frame_rgb(src.read(index), quantity, limits, index=index, image=img, dpi=dpi, alpha=alpha)
            if shape is None:
                shape = tuple(-(-n // _MACRO_BLOCK) * _MACRO_BLOCK for n in rgb.shape[:2])
            yield index, _fit(rgb, shape)


def _check_fps(fps) -> float:
    try:
        value = float(fps)
    except (TypeError, ValueError):
        raise ValueError(f"fps must be a number of frames per second, got {fps!r}") from None
    if not (np.isfinite(value) and 0 < value <= MAX_FPS):
        raise ValueError(f"fps must be above 0 and at most {MAX_FPS:g} frames per second, got {fps!r}")
    return value


def write_animation(results, path, *, quantity: str, fps: float = 5.0, frames=None, image=None,
                    dpi: float = 80, alpha: float = 0.75) -> Path:
    """Write a movie of one quantity over the frames of a result; returns the path.

    ``path`` ends in ``.mp4`` (H.264, yuv420p, through imageio-ffmpeg; frames are encoded as they are
    drawn) or ``.gif`` (Pillow, looping; Pillow holds the frames until the file is closed). ``fps``:
    frames per second (above 0, at most :data:`MAX_FPS`). The other arguments are those of
    :func:`animation_frames`. The movie is written to a hidden temporary file in the same folder and
    renamed into place when complete: a failed or interrupted run leaves no file under ``path``.
    """
    p = Path(os.fspath(path))
    suffix = p.suffix.lower()
    if suffix not in ANIMATION_SUFFIXES:
        raise ValueError(f"the movie file must end in {' or '.join(ANIMATION_SUFFIXES)}, got {p.name!r}")
    rate = _check_fps(fps)
    if p.is_dir():
        raise ValueError(f"{p} is a folder; give the movie's file name")
    stream = animation_frames(results, quantity, frames=frames, image=image, dpi=dpi, alpha=alpha)
    tmp = p.with_name(f".{p.stem}.partial-{os.getpid()}{p.suffix}")
    try:
        first = next(stream)  # input errors are raised before any file is created
        p.parent.mkdir(parents=True, exist_ok=True)
        if suffix == ".mp4":
            import imageio.v2 as iio2

            writer = iio2.get_writer(tmp, format="FFMPEG", mode="I", fps=rate, codec="libx264", quality=8,
                                     pixelformat="yuv420p", macro_block_size=_MACRO_BLOCK, ffmpeg_log_level="error")
            try:
                for _, rgb in _chain(first, stream):
                    writer.append_data(rgb)
            finally:
                writer.close()
        else:
            import imageio.v3 as iio

            with iio.imopen(tmp, "w", plugin="pillow", extension=".gif") as writer:
                for _, rgb in _chain(first, stream):
                    writer.write(rgb, is_batch=False, duration=1000.0 / rate, loop=0)
        os.replace(tmp, p)
    except BaseException:
        stream.close()
        tmp.unlink(missing_ok=True)
        raise
    return p


def _chain(first, rest):
    yield first
    yield from rest
