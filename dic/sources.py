"""Frame sources: one way to give a sequence of images, for 2-D and stereo, read lazily.

:func:`open_frames` turns any of these into a :class:`FrameSource`:

- a list or tuple of image files and/or arrays (one frame per item, in the given order);
- a folder: its image files (``.tif``, ``.tiff``, ``.png``, ``.bmp``) in natural order
  (``img_2`` before ``img_10``); other files are ignored with a warning that counts them;
- a glob pattern such as ``"run1/*.tif"`` (expanded here, so it works where a shell does not
  expand it; natural order; non-image matches ignored with a warning);
- a multi-page TIFF (one frame per page, read page by page);
- a video file (``.mp4``, ``.avi``, ``.mov``, ...; imageio with its ffmpeg plugin, decoded
  frame by frame);
- a NumPy array ``(T, H, W)`` (or any array-like with ``.shape`` and indexing: a memory map, an
  HDF5 dataset: frames are taken one at a time);
- any other iterable of arrays (a generator is consumed once).

A source is iterable: it yields :class:`Frame` ``(index, image, name)`` with ``index`` 0, 1, ...
in order, ``image`` the (H, W) grey levels (uint8/uint16 kept as they are, other types as
float32; grey stored as RGB is grey; true colour needs ``as_grey=True``, BT.601 luma) and
``name`` saying where it came from (the file path, ``"stack.tif[page 3]"``,
``"film.mp4[frame 12]"``, ``"array[5]"``; pages and video frames are numbered from 0, like the
index). Nothing is read before it is needed and only the frame being yielded is held; ``len()``
works where the length is known without reading the images (everything but generators),
``.shape`` is the (H, W) of the first frame.

Faults raise :class:`FrameError` (a ``ValueError``) naming the frame: a frame whose size differs
from the first frame's (both named), a frame that cannot be read or decoded, a colour frame
without ``as_grey``. Because sources are lazy, the frames before a bad one have already been
yielded (a sequence engine keeps their results). Sources that cannot be opened at all (an empty
folder, a pattern matching nothing, a video the decoder cannot open) raise ``ValueError`` from
:func:`open_frames` itself.

:func:`open_pairs` makes a stereo source of two sources of equal length (or of a sequence of
``(left, right)`` pairs); :func:`open_inputs` joins several inputs (command-line arguments) into
one source.
"""
from __future__ import annotations

import glob
import os
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np

from kernels.checks import boolean
from kernels.images import (
    IMAGE_SUFFIXES,
    as_float32_image,
    check_image_size,
    describe_not_a_file,
    grey_image,
    natural_key,
    read_image,
    read_tiff_page,
)

__all__ = ["Frame", "FrameError", "FrameSource", "PairSource", "VIDEO_SUFFIXES", "is_single_image", "open_frames",
           "open_inputs", "open_pairs"]

#: file name suffixes read as video (imageio's ffmpeg plugin; case-insensitive)
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg", ".wmv", ".mj2")

_COLOUR_HINT = "(open_frames(..., as_grey=True) uses BT.601 luma) or record grey"


class Frame(NamedTuple):
    """One frame of a source: its position, its grey levels (H, W) and where it came from."""

    index: int
    image: np.ndarray
    name: str


class FrameError(ValueError):
    """A frame that cannot be used; ``index`` and ``name`` say which (frames before it were yielded)."""

    def __init__(self, message: str, index: int, name: str):
        super().__init__(message)
        self.index = index
        self.name = name


def _frame_error(index: int, name: str, exc: BaseException | str) -> FrameError:
    msg = str(exc)
    head = f"frame {index}" if name and name in msg else f"frame {index} ({name})"
    return FrameError(f"{head}: {msg}", index, name)


def _validated(image, name: str, as_grey: bool) -> np.ndarray:
    """The checks of :func:`kernels.images.as_float32_image`; uint8/uint16 keep their dtype (the kernels take them)."""
    if isinstance(image, np.ndarray) and not isinstance(image, np.ma.MaskedArray) and image.ndim == 3:
        image = grey_image(image, name, as_grey=as_grey, hint=_COLOUR_HINT)
    if (isinstance(image, np.ndarray) and not isinstance(image, np.ma.MaskedArray) and image.ndim == 2
            and image.size and image.dtype in (np.uint8, np.uint16)):
        return np.ascontiguousarray(image)
    if isinstance(image, np.ndarray) and image.dtype == bool and image.ndim == 2:
        return np.ascontiguousarray(image, dtype=np.uint8)
    return as_float32_image(image, name)


def _size(shape) -> str:
    return f"{shape[1]}x{shape[0]} px"


class FrameSource:
    """A sequence of frames read on demand (see the module's documentation).

    Iterate it for :class:`Frame` objects; ``len(source)`` where the length is known
    (:attr:`length` is None otherwise), :attr:`shape` for the (H, W) of the first frame,
    ``source[k]`` for one frame of a source with random access (files, arrays, TIFF pages,
    video), :meth:`check_shapes` to compare every frame's size with the first's from file headers
    before any work. A source of files, arrays, TIFF pages or video can be iterated any number of
    times; a generator only once.
    """

    #: what the source is, for messages ("folder run1/ (120 images)", "video film.mp4", ...)
    description: str = "frames"

    def __init__(self, *, as_grey: bool = False):
        self.as_grey = boolean(as_grey, "as_grey")
        self._shape: tuple[int, int] | None = None

    # -- to implement -------------------------------------------------------------------------
    def _raw(self) -> Iterator[tuple[int, str, object]]:
        """Yield (index, name, loader) in order; ``loader()`` returns the decoded image (any array)."""
        raise NotImplementedError

    @property
    def length(self) -> int | None:
        """The number of frames, or None when it is not known without reading them (a generator)."""
        return None

    def _item(self, k: int) -> tuple[str, object]:
        raise TypeError(f"{self.description} has no random access; iterate it")

    def _probe_shape(self) -> tuple[int, int]:
        for frame in self:
            return frame.image.shape
        raise ValueError(f"{self.description} holds no frames")

    # -- common ---------------------------------------------------------------------------------
    def __len__(self) -> int:
        n = self.length
        if n is None:
            raise TypeError(f"the length of {self.description} is not known before it is read")
        return n

    def __repr__(self) -> str:
        n = self.length
        return f"<FrameSource {self.description}" + (f", {n} frame(s)>" if n is not None else ">")

    def _load(self, index: int, name: str, loader) -> np.ndarray:
        try:
            return _validated(loader(), name, self.as_grey)
        except FrameError:
            raise
        except Exception as exc:  # decoder errors (OSError, tifffile, ffmpeg, ...) and ValueError
            raise _frame_error(index, name, exc) from None

    def __iter__(self) -> Iterator[Frame]:
        first = None
        for index, name, loader in self._raw():
            image = self._load(index, name, loader)
            if first is None:
                first = (image.shape, name)
                if self._shape is None:
                    self._shape = image.shape
            elif image.shape != first[0]:
                raise FrameError(
                    f"frame {index} ({name}) is {_size(image.shape)} but frame 0 ({first[1]}) is {_size(first[0])}; "
                    "every image must have the same size", index, name)
            yield Frame(index, image, name)

    def __getitem__(self, k) -> Frame:
        n = self.length
        if isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)):
            raise ValueError(f"a frame index must be an integer, got {k!r}")
        k = int(k)
        if n is not None and not -n <= k < n:
            raise IndexError(f"frame {k} is out of range: {self.description} holds {n} frame(s)")
        if k < 0:
            if n is None:
                raise ValueError(f"{self.description} has no known length: count frames from 0")
            k += n
        name, loader = self._item(k)
        image = self._load(k, name, loader)
        if k and image.shape != self.shape:
            raise FrameError(f"frame {k} ({name}) is {_size(image.shape)} but frame 0 is {_size(self.shape)}; "
                             "every image must have the same size", k, name)
        return Frame(k, image, name)

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the first frame (read from a file header where possible, else from the frame)."""
        if self._shape is None:
            self._shape = tuple(int(s) for s in self._probe_shape())
        return self._shape

    @property
    def files(self) -> list[str] | None:
        """The image file of every frame when the frames are image files (a list, folder or glob), else None."""
        return None

    def check_shapes(self) -> None:
        """Raise :class:`FrameError` now for the first frame whose size differs from the first's.

        Reads only file headers (image files, TIFF pages) or array shapes; a video has one size,
        and a generator cannot be checked before it is read (its frames are checked as they come).
        """
        return None


# ------------------------------------------------------------------------------------------------
# the kinds of sources
# ------------------------------------------------------------------------------------------------
def _header_shape(path: str) -> tuple[int, int] | None:
    """(H, W) of an image file from its header, or None when the header does not tell."""
    try:
        if path.lower().endswith((".tif", ".tiff")):
            import tifffile

            with tifffile.TiffFile(path) as tif:
                page = tif.pages[0]
                return int(page.imagelength), int(page.imagewidth)
        from PIL import Image

        with Image.open(path) as im:
            return int(im.size[1]), int(im.size[0])
    except Exception:
        return None


class _ListFrames(FrameSource):
    """One frame per item: an image file (path) or an array."""

    def __init__(self, items, *, label: str = "array", description: str | None = None, as_grey: bool = False):
        super().__init__(as_grey=as_grey)
        self.items = list(items)
        self.label = label
        self.description = description or f"a list of {len(self.items)} image(s)"

    @property
    def length(self) -> int:
        return len(self.items)

    @property
    def files(self) -> list[str] | None:
        if all(isinstance(item, (str, os.PathLike)) for item in self.items):
            return [os.fspath(item) for item in self.items]
        return None

    def _item(self, k: int):
        return _item_loader(self.items[k], k, self.label, self.as_grey)

    def _raw(self):
        for k in range(len(self.items)):
            name, loader = self._item(k)
            yield k, name, loader

    def _probe_shape(self):
        if not self.items:
            raise ValueError(f"{self.description} holds no frames")
        first = self.items[0]
        if isinstance(first, (str, os.PathLike)):
            shape = _header_shape(os.fspath(first))
            if shape is not None:
                return shape
        return self[0].image.shape

    def check_shapes(self) -> None:
        first = None
        for k, item in enumerate(self.items):
            if isinstance(item, (str, os.PathLike)):
                name = os.fspath(item)
                shape = _header_shape(name)
                if shape is None:  # no readable header: the frame says what is wrong when it is read
                    continue
            else:
                name = f"{self.label}[{k}]"
                shape = tuple(np.shape(item))[:2]
            if first is None:
                first = (shape, name)
            elif shape != first[0]:
                raise FrameError(
                    f"frame {k} ({name}) is {_size(shape)} but frame 0 ({first[1]}) is {_size(first[0])}; every "
                    "image must have the same size", k, name)


def _refuse(msg: str):
    raise ValueError(msg)


def _item_loader(item, k: int, label: str, as_grey: bool):
    """(name, loader) of one item of a list or iterable of frames: an image file or an array."""
    if isinstance(item, (str, os.PathLike)):
        path = os.fspath(item)
        return path, lambda: read_image(path, as_grey=as_grey)
    name = f"{label}[{k}]"
    if isinstance(item, (tuple, list)):
        return name, lambda: _refuse(f"item {k} is a {type(item).__name__} of {len(item)}, not an image; pairs of "
                                     "images are for stereo: open_pairs(...)")
    if item is None or isinstance(item, (str, bytes, dict, set)):
        return name, lambda: _refuse(f"item {k} is a {type(item).__name__}, not an image file or array")
    return name, lambda: item


class _StackFrames(FrameSource):
    """An array-like (T, H, W) (or (T, H, W, C)): frame k is ``stack[k]``, taken when needed."""

    def __init__(self, stack, *, label: str = "array", as_grey: bool = False):
        super().__init__(as_grey=as_grey)
        self.stack = stack
        self.label = label
        self.description = f"an array of shape {tuple(stack.shape)}"

    @property
    def length(self) -> int:
        return int(self.stack.shape[0])

    def _item(self, k: int):
        def load():
            frame = self.stack[k]
            return frame if hasattr(frame, "numpy") and not isinstance(frame, np.ndarray) else np.asarray(frame)
        return f"{self.label}[{k}]", load

    def _raw(self):
        for k in range(self.length):
            name, loader = self._item(k)
            yield k, name, loader

    def _probe_shape(self):
        return tuple(int(s) for s in self.stack.shape[1:3])


class _TiffPages(FrameSource):
    """A multi-page TIFF: frame k is page k, read page by page (the file stays open while iterated)."""

    def __init__(self, path: str, n_pages: int, *, as_grey: bool = False):
        super().__init__(as_grey=as_grey)
        self.path = path
        self.n_pages = n_pages
        self.description = f"multi-page TIFF {path} ({n_pages} pages)"

    @property
    def length(self) -> int:
        return self.n_pages

    def _name(self, k: int) -> str:
        return f"{self.path}[page {k}]"

    def _item(self, k: int):
        def load():
            import tifffile

            with tifffile.TiffFile(self.path) as tif:
                return read_tiff_page(tif, k, self._name(k))
        return self._name(k), load

    def _raw(self):
        import tifffile

        try:
            tif = tifffile.TiffFile(self.path)
        except Exception as exc:
            raise _frame_error(0, self._name(0), f"cannot open {self.path}: {exc}") from None
        with tif:
            for k in range(self.n_pages):
                yield k, self._name(k), (lambda k=k: read_tiff_page(tif, k, self._name(k)))

    def _probe_shape(self):
        import tifffile

        with tifffile.TiffFile(self.path) as tif:
            page = tif.pages[0]
            return int(page.imagelength), int(page.imagewidth)

    def check_shapes(self) -> None:
        import tifffile

        with tifffile.TiffFile(self.path) as tif:
            first = None
            for k, page in enumerate(tif.pages):
                shape = (int(page.imagelength), int(page.imagewidth))
                if first is None:
                    first = shape
                elif shape != first:
                    raise FrameError(
                        f"frame {k} ({self._name(k)}) is {_size(shape)} but frame 0 ({self._name(0)}) is "
                        f"{_size(first)}; every image must have the same size", k, self._name(k))


_FFMPEG = "FFMPEG"


class _VideoFrames(FrameSource):
    """A video file decoded frame by frame with imageio's ffmpeg plugin."""

    def __init__(self, path: str, *, as_grey: bool = False):
        super().__init__(as_grey=as_grey)
        self.path = path
        self.description = f"video {path}"
        self._length: int | None = None
        try:
            import imageio.v3 as iio

            meta = iio.immeta(path, plugin=_FFMPEG)
        except ImportError as exc:
            raise ValueError(f"cannot read video {path}: {exc} (install imageio-ffmpeg)") from None
        except Exception as exc:
            raise ValueError(f"cannot decode video {path}: {_first_line(exc)}") from None
        size = meta.get("size")
        if size:
            self._shape = (int(size[1]), int(size[0]))
            check_image_size(self._shape[0], self._shape[1], f"video {path}")

    @property
    def length(self) -> int:
        """Counted once by ffmpeg without decoding the pictures (stream copy)."""
        if self._length is None:
            import imageio_ffmpeg

            try:
                counted = int(imageio_ffmpeg.count_frames_and_secs(self.path)[0])
            except Exception as exc:
                raise ValueError(f"cannot count the frames of video {self.path}: {_first_line(exc)}") from None
            _check_avi_complete(self.path, counted)
            self._length = counted
        return self._length

    def _name(self, k: int) -> str:
        return f"{self.path}[frame {k}]"

    def _item(self, k: int):
        def load():
            import imageio.v3 as iio

            return iio.imread(self.path, plugin=_FFMPEG, index=k)
        return self._name(k), load

    def _raw(self):
        import imageio.v3 as iio

        k = 0
        try:
            frames = iio.imiter(self.path, plugin=_FFMPEG)
            while True:
                try:
                    image = next(frames)
                except StopIteration:
                    return
                yield k, self._name(k), (lambda image=image: image)
                k += 1
        except FrameError:
            raise
        except Exception as exc:
            raise _frame_error(k, self._name(k), f"cannot decode it: {_first_line(exc)}") from None


def _check_avi_complete(path: str, counted: int) -> None:
    """Refuse an AVI file cut short (``ValueError``): its RIFF header declares more bytes than the file holds,
    or its main header (``avih``) more frames than ffmpeg counted. ffmpeg itself reads such a file as a
    shorter video without a word. Other containers are not checked here."""
    import struct

    if Path(path).suffix.lower() != ".avi":
        return
    try:
        with open(path, "rb") as fh:
            head = fh.read(65536)
        actual = os.path.getsize(path)
    except OSError:
        return
    if len(head) < 12 or head[:4] != b"RIFF" or head[8:12] != b"AVI ":
        return
    declared_bytes = struct.unpack("<I", head[4:8])[0] + 8
    at = head.find(b"avih")
    declared_frames = struct.unpack("<I", head[at + 24:at + 28])[0] if 0 <= at and at + 28 <= len(head) else 0
    if declared_bytes > actual or counted < declared_frames:
        raise ValueError(
            f"video {path} is cut short: its header declares {declared_frames} frames in {declared_bytes:,} bytes, "
            f"but the file holds {actual:,} bytes and {counted} readable frames (an interrupted copy or "
            "recording?); copy or export it again")


def _first_line(exc: BaseException) -> str:
    """The first line of an error (ffmpeg appends its whole log)."""
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


class _IterFrames(FrameSource):
    """Any iterable of images (arrays or files); a generator can be iterated once."""

    def __init__(self, iterable, *, label: str = "array", as_grey: bool = False):
        super().__init__(as_grey=as_grey)
        self.iterable = iterable
        self.label = label
        self.description = f"an iterable ({type(iterable).__name__})"
        self._one_shot = iter(iterable) is iterable
        self._started = False
        self._peeked: list = []

    @property
    def length(self) -> int | None:
        try:
            return None if self._one_shot else len(self.iterable)
        except TypeError:
            return None

    def _items(self):
        if self._one_shot:
            if self._started:
                raise ValueError(f"{self.description} has already been read; a generator gives its frames once "
                                 "(open the frames again, or give a list, a folder or an array)")
            self._started = True
            yield from self._peeked
            self._peeked = []
            yield from self.iterable
        else:
            yield from self.iterable

    def _raw(self):
        items = self._items()
        k = 0
        while True:
            try:
                item = next(items)
            except StopIteration:
                return
            except ValueError as exc:
                if self._started and k == 0 and "already been read" in str(exc):
                    raise
                raise _frame_error(k, f"{self.label}[{k}]", f"the iterable failed: {exc}") from None
            except Exception as exc:  # the user's generator failed while making frame k
                raise _frame_error(k, f"{self.label}[{k}]", f"the iterable failed: {type(exc).__name__}: {exc}") \
                    from None
            yield (k,) + _item_loader(item, k, self.label, self.as_grey)
            k += 1

    def _probe_shape(self):
        if self._one_shot:
            if self._started:
                raise ValueError(f"{self.description} has already been read; its shape is not known")
            try:
                item = next(iter(self.iterable))
            except StopIteration:
                raise ValueError(f"{self.description} holds no frames") from None
            self._peeked = [item]
            return self._load(0, *_item_loader(item, 0, self.label, self.as_grey)).shape
        return super()._probe_shape()


class _ChainFrames(FrameSource):
    """Several sources one after the other, numbered on (one size for all)."""

    def __init__(self, sources: list[FrameSource]):
        super().__init__(as_grey=False)
        self.sources = sources
        self.description = " + ".join(s.description for s in sources)

    @property
    def length(self) -> int | None:
        lengths = [s.length for s in self.sources]
        return None if any(n is None for n in lengths) else sum(lengths)

    def _load(self, index, name, loader):
        return loader()  # validated by the source it comes from (with its as_grey), numbered here

    def _raw(self):
        offset = 0
        for src in self.sources:
            n = 0
            raw = src._raw()
            while True:
                try:
                    index, name, loader = next(raw)
                except StopIteration:
                    break
                except FrameError as exc:  # opening or decoding failed: renumber the frame in the joined sequence
                    raise FrameError(str(exc).replace(f"frame {exc.index}", f"frame {offset + exc.index}", 1),
                                     offset + exc.index, exc.name) from None
                k = offset + index
                yield k, name, (lambda src=src, k=k, name=name, loader=loader: src._load(k, name, loader))
                n += 1
            offset += n

    def _item(self, k: int):
        offset = 0
        for src in self.sources:
            n = len(src)
            if k < offset + n:
                try:
                    f = src[k - offset]
                except FrameError as exc:
                    raise FrameError(str(exc).replace(f"frame {exc.index}", f"frame {k}", 1), k, exc.name) from None
                return f.name, (lambda image=f.image: image)
            offset += n
        raise IndexError(k)

    def _probe_shape(self):
        return self.sources[0].shape

    @property
    def files(self) -> list[str] | None:
        parts = [s.files for s in self.sources]
        return None if any(p is None for p in parts) else [f for p in parts for f in p]

    def check_shapes(self) -> None:
        for src in self.sources:
            src.check_shapes()
        shapes = [(s.shape, s.description) for s in self.sources]
        for shape, what in shapes[1:]:
            if shape != shapes[0][0]:
                raise ValueError(f"{what} is {_size(shape)} but {shapes[0][1]} is {_size(shapes[0][0])}; every "
                                 "image must have the same size")


# ------------------------------------------------------------------------------------------------
# opening
# ------------------------------------------------------------------------------------------------
def _image_files(candidates: list[str], where: str) -> list[str]:
    """The image files among ``candidates`` in natural order; the others are ignored with a warning."""
    images = [f for f in candidates if f.lower().endswith(IMAGE_SUFFIXES)]
    others = sorted((f for f in candidates if f not in set(images) and not os.path.basename(f).startswith(".")),
                    key=natural_key)
    if others and images:
        shown = ", ".join(os.path.basename(f) for f in others[:3]) + (", ..." if len(others) > 3 else "")
        warnings.warn(f"{where}: ignored {len(others)} file(s) that are not images ({shown}); frames are the "
                      f"{len(images)} {'/'.join(IMAGE_SUFFIXES)} file(s)", UserWarning, stacklevel=4)
    return sorted(images, key=natural_key)


def _open_path(path: str, as_grey: bool) -> FrameSource:
    if os.path.isdir(path):
        entries = [os.path.join(path, f) for f in os.listdir(path)]
        files = [f for f in entries if os.path.isfile(f)]
        images = _image_files(files, f"folder {path}")
        if not images:
            raise ValueError(f"folder {path} holds no image files ({', '.join(IMAGE_SUFFIXES)})"
                             + (f"; it holds {len(files)} other file(s)" if files else ""))
        return _ListFrames(images, description=f"folder {path} ({len(images)} images)", as_grey=as_grey)
    if os.path.isfile(path):
        suffix = Path(path).suffix.lower()
        if suffix in VIDEO_SUFFIXES:
            return _VideoFrames(path, as_grey=as_grey)
        if suffix in (".tif", ".tiff"):
            n = _tiff_pages(path)
            if n > 1:
                return _TiffPages(path, n, as_grey=as_grey)
        elif suffix not in IMAGE_SUFFIXES:
            raise ValueError(f"{path}: unsupported file type {suffix!r}; a sequence is image files "
                             f"({', '.join(IMAGE_SUFFIXES)}), a multi-page TIFF, a video "
                             f"({', '.join(VIDEO_SUFFIXES)}), a folder or a glob pattern")
        return _ListFrames([path], description=f"image {path}", as_grey=as_grey)
    if glob.has_magic(path):
        matches = glob.glob(path)
        files = [f for f in matches if os.path.isfile(f)]
        if not files:
            raise ValueError(f"the pattern {path!r} matches no files")
        images = _image_files(files, f"pattern {path!r}")
        if not images:
            raise ValueError(f"the pattern {path!r} matches {len(files)} file(s) but no image file "
                             f"({', '.join(IMAGE_SUFFIXES)})")
        return _ListFrames(images, description=f"pattern {path!r} ({len(images)} images)", as_grey=as_grey)
    special = describe_not_a_file(path)  # a symlink loop, a FIFO, a socket: not "not found"
    if special is not None:
        raise ValueError(special)
    suffix = Path(path).suffix.lower()
    what = "image file" if suffix in IMAGE_SUFFIXES else "video file" if suffix in VIDEO_SUFFIXES else "input"
    raise ValueError(f"{what} not found: {path} (a sequence is image files, a folder, a glob pattern (quote it), "
                     "a multi-page TIFF or a video)")


def _tiff_pages(path: str) -> int:
    """Number of pages of a TIFF file (1 for a damaged file: read_image then says what is wrong)."""
    try:
        import tifffile

        with tifffile.TiffFile(path) as tif:
            return len(tif.pages)
    except Exception:
        return 1


def open_frames(source, *, as_grey: bool = False) -> FrameSource:
    """A :class:`FrameSource` over ``source``, read lazily (see the module's documentation).

    Parameters
    ----------
    source : list or tuple of image files / arrays, folder, glob pattern, multi-page TIFF, video
        file, image file (one frame), array (T, H, W), any iterable of arrays, or a FrameSource
        (returned as it is).
    as_grey : bool
        Convert colour frames (files, video, arrays (H, W, 3|4)) to grey with BT.601 luma
        (float32). Without it a colour frame raises :class:`FrameError`; grey stored as RGB is
        grey either way.

    Raises
    ------
    ValueError
        An empty list, folder or pattern, a missing path, an unsupported file type, a video the
        decoder cannot open, a single 2-D image given as an array, an input of another type.
    """
    boolean(as_grey, "as_grey")
    if isinstance(source, FrameSource):
        return source
    if isinstance(source, (str, os.PathLike)):
        path = os.fspath(source)
        if not path:
            raise ValueError("the frame source is an empty path")
        return _open_path(path, as_grey)
    if isinstance(source, (list, tuple)):
        if not source:
            raise ValueError("the list of frames is empty")
        return _ListFrames(source, as_grey=as_grey)
    shape = getattr(source, "shape", None)
    if shape is not None and hasattr(source, "__getitem__") and not isinstance(source, (bytes, dict)):
        ndim = len(shape)
        if ndim == 2:
            raise ValueError(f"an array of shape {tuple(shape)} is one image; a sequence is (T, H, W) (or give "
                             "[image] for a single frame)")
        if ndim == 3 and shape[2] in (3, 4) and shape[0] > 4 and shape[1] > 4:
            raise ValueError(f"an array of shape {tuple(shape)} looks like one colour image (H, W, C); a sequence "
                             "is (T, H, W) (or (T, H, W, C) with as_grey=True)")
        if ndim not in (3, 4) or (ndim == 4 and shape[3] not in (1, 3, 4)):
            raise ValueError(f"a frame array must be (T, H, W) (or (T, H, W, C) colour), got shape {tuple(shape)}")
        if shape[0] == 0:
            raise ValueError(f"the frame array is empty (shape {tuple(shape)})")
        return _StackFrames(source, as_grey=as_grey)
    if isinstance(source, (bytes, dict, set)) or not isinstance(source, Iterable):
        raise ValueError(f"cannot read frames from a {type(source).__name__}: give a list of images, a folder, "
                         "a glob pattern, a multi-page TIFF, a video, an array (T, H, W) or an iterable of arrays")
    return _IterFrames(source, as_grey=as_grey)


def is_single_image(path) -> bool:
    """Whether ``path`` names one image: an image file that is not a multi-page TIFF, or a missing
    image file name (reading it then says it is missing); False for folders, patterns and videos."""
    path = os.fspath(path)
    suffix = Path(path).suffix.lower()
    if os.path.isfile(path):
        return suffix in IMAGE_SUFFIXES and not (suffix in (".tif", ".tiff") and _tiff_pages(path) > 1)
    return not os.path.exists(path) and not glob.has_magic(path) and suffix in IMAGE_SUFFIXES


def open_inputs(inputs, *, as_grey: bool = False) -> FrameSource:
    """One source of several inputs one after the other (e.g. command-line arguments).

    Each input is what :func:`open_frames` takes from a path: an image file (one frame), a
    folder, a glob pattern, a multi-page TIFF or a video; consecutive image files make one list.
    Frames are numbered on through the inputs and must all have the same size.
    """
    if isinstance(inputs, (str, os.PathLike)):
        inputs = [inputs]
    inputs = list(inputs)
    if not inputs:
        raise ValueError("no input given")
    sources: list[FrameSource] = []
    files: list[str] = []
    for item in inputs:
        path = os.fspath(item)
        if os.path.isfile(path) and is_single_image(path):
            files.append(path)
            continue
        if files:
            sources.append(_ListFrames(files, as_grey=as_grey))
            files = []
        sources.append(open_frames(path, as_grey=as_grey))
    if files:
        sources.append(_ListFrames(files, as_grey=as_grey))
    return sources[0] if len(sources) == 1 else _ChainFrames(sources)


# ------------------------------------------------------------------------------------------------
# stereo
# ------------------------------------------------------------------------------------------------
class PairSource:
    """Stereo frames: iterate for ``(left, right)`` :class:`Frame` pairs of the same index.

    ``len()`` where known, :attr:`shape` (H, W) of the first left frame, ``source[k]`` for one pair,
    :meth:`check_shapes`. Left and right frames must have the same size; a side that ends
    before the other raises :class:`FrameError`.
    """

    def __init__(self, left: FrameSource, right: FrameSource):
        self.left = left
        self.right = right
        nl, nr = left.length, right.length
        if nl is not None and nr is not None and nl != nr:
            raise ValueError(f"the left and right sequences differ in length: {nl} left frame(s) "
                             f"({left.description}) but {nr} right frame(s) ({right.description})")

    @property
    def length(self) -> int | None:
        return self.left.length if self.left.length is not None else self.right.length

    def __len__(self) -> int:
        n = self.length
        if n is None:
            raise TypeError("the length of these stereo frames is not known before they are read")
        return n

    @property
    def shape(self) -> tuple[int, int]:
        return self.left.shape

    def _check(self, left: Frame, right: Frame) -> tuple[Frame, Frame]:
        if left.image.shape != right.image.shape:
            raise FrameError(
                f"pair {left.index}: the left frame ({left.name}) is {_size(left.image.shape)} but the right frame "
                f"({right.name}) is {_size(right.image.shape)}; every image must have the same size",
                left.index, right.name)
        return left, right

    def __iter__(self) -> Iterator[tuple[Frame, Frame]]:
        lit, rit = iter(self.left), iter(self.right)
        k = 0
        while True:
            left = next(lit, None)
            right = next(rit, None)
            if left is None and right is None:
                return
            if left is None or right is None:
                side, other = ("left", "right") if left is None else ("right", "left")
                raise FrameError(f"pair {k}: the {side} sequence ended after {k} frame(s) but the {other} one goes "
                                 "on; give as many left as right frames", k, (right or left).name)
            yield self._check(left, right)
            k += 1

    def __getitem__(self, k) -> tuple[Frame, Frame]:
        return self._check(self.left[k], self.right[k])

    def check_shapes(self) -> None:
        self.left.check_shapes()
        self.right.check_shapes()
        if self.left.shape != self.right.shape:
            raise ValueError(f"the left frames ({self.left.description}) are {_size(self.left.shape)} but the right "
                             f"frames ({self.right.description}) are {_size(self.right.shape)}; every image must "
                             "have the same size")


class _IterPairs(PairSource):
    """Stereo frames from an iterable (e.g. a generator) of (left, right) pairs."""

    def __init__(self, iterable, *, as_grey: bool = False):
        self.iterable = iterable
        self.as_grey = as_grey
        self._one_shot = iter(iterable) is iterable
        self._started = False
        self._shape = None

    @property
    def length(self):
        try:
            return None if self._one_shot else len(self.iterable)
        except TypeError:
            return None

    @property
    def shape(self):
        if self._shape is None:
            raise ValueError("the shape of a generator of pairs is not known before it is read")
        return self._shape

    def __iter__(self):
        if self._one_shot:
            if self._started:
                raise ValueError("this generator of pairs has already been read; a generator gives its pairs once")
            self._started = True
        first = None
        for k, pair in enumerate(self.iterable):
            if not isinstance(pair, (tuple, list)) or len(pair) != 2:
                raise FrameError(f"pair {k} must be a (left, right) pair, got {type(pair).__name__}", k, f"pair[{k}]")
            left, right = (self._frame(k, pair[0], "left"), self._frame(k, pair[1], "right"))
            if first is None:
                first = (left.image.shape, left.name)
                self._shape = first[0]
            elif left.image.shape != first[0]:
                raise FrameError(f"frame {k} ({left.name}) is {_size(left.image.shape)} but frame 0 ({first[1]}) is "
                                 f"{_size(first[0])}; every image must have the same size", k, left.name)
            yield self._check(left, right)

    def _frame(self, k: int, item, label: str) -> Frame:
        name, loader = _item_loader(item, k, label, self.as_grey)
        try:
            image = _validated(loader(), name, self.as_grey)
        except Exception as exc:
            raise _frame_error(k, name, exc) from None
        return Frame(k, image, name)

    def __getitem__(self, k):
        raise TypeError("an iterable of pairs has no random access; iterate it")

    def check_shapes(self) -> None:
        return None


def open_pairs(left, right=None, *, as_grey: bool = False) -> PairSource:
    """Stereo frames: two sources of equal length, or ``left`` as a sequence of ``(left, right)`` pairs.

    ``left`` and ``right``: anything :func:`open_frames` takes (folders, globs, lists, videos,
    multi-page TIFFs, arrays (T, H, W), iterables). With ``right=None``, ``left`` is a list of
    ``(left, right)`` pairs (files or arrays), an array (T, 2, H, W) or an iterable of pairs.
    Raises ``ValueError`` when the lengths are known and differ.
    """
    if right is not None:
        return PairSource(_side(left, "left", as_grey), _side(right, "right", as_grey))
    if isinstance(left, (str, os.PathLike)):
        raise ValueError(f"{os.fspath(left)} is one side only; give the right frames too (open_pairs(left, right))")
    shape = getattr(left, "shape", None)
    if shape is not None and hasattr(left, "__getitem__") and not isinstance(left, (list, tuple)):
        if len(shape) != 4 or shape[1] != 2:
            raise ValueError(f"stereo frames as one array must be (T, 2, H, W) (left, right), got shape {tuple(shape)}")
        return PairSource(_StackFrames(_Side(left, 0), label="left", as_grey=as_grey),
                          _StackFrames(_Side(left, 1), label="right", as_grey=as_grey))
    if isinstance(left, (list, tuple)):
        if not left:
            raise ValueError("the list of (left, right) pairs is empty")
        for k, p in enumerate(left):
            if not isinstance(p, (tuple, list)) or len(p) != 2:
                raise ValueError(f"pairs[{k}] must be a (left, right) pair, got {type(p).__name__}")
        return PairSource(_ListFrames([p[0] for p in left], label="left", as_grey=as_grey),
                          _ListFrames([p[1] for p in left], label="right", as_grey=as_grey))
    if isinstance(left, FrameSource) or isinstance(left, (bytes, dict, set)) or not isinstance(left, Iterable):
        raise ValueError(f"cannot read stereo pairs from a {type(left).__name__} alone: give open_pairs(left, right) "
                         "or a list of (left, right) pairs")
    return _IterPairs(left, as_grey=as_grey)


class _Side:
    """View of one side of a (T, 2, H, W) array-like without copying it."""

    def __init__(self, stack, side: int):
        self.stack, self.side = stack, side
        self.shape = (stack.shape[0],) + tuple(stack.shape[2:])

    def __getitem__(self, k):
        return self.stack[k][self.side]


def _side(source, label: str, as_grey: bool) -> FrameSource:
    src = open_frames(source, as_grey=as_grey)
    if isinstance(src, (_StackFrames, _ListFrames, _IterFrames)) and src.label in ("array", "item"):
        src.label = label
    return src
