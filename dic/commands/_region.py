"""The region-of-interest options shared by ``specula track``, ``specula stereo`` and ``specula speckle``.

``--roi X0 Y0 X1 Y1`` (inclusive box, px), ``--roi-polygon "x,y;x,y;..."`` or ``--roi-polygon FILE``
(JSON: ``[[x, y], ...]`` or ``{"polygon": [[x, y], ...]}``; CSV/text: one ``x,y`` per line, an
optional header line) and ``--mask FILE`` (an image, non-zero inside, of the images' size). At most
one of them; the rule that selects POIs is :mod:`dic.correlation.points` (the same for 2-D and stereo).
``--exclude SHAPE`` (repeatable) takes a shape out of that region (or out of the whole image):
``circle:CX,CY,R``, ``box:X0,Y0,X1,Y1`` or ``polygon:X1,Y1,X2,Y2,X3,Y3,...`` (px), or
``polygon:FILE`` (the vertices as for ``--roi-polygon``).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import click
import numpy as np

_POLYGON_HELP = ('Region of interest as a polygon of >= 3 vertices in px: "x,y;x,y;..." or a JSON/CSV file of the '
                 "vertices; POIs inside or on its edge are used.")


_EXCLUDE_HELP = ("Leave a shape out of the region (a hole, a notch, a clamp), px in the (left) reference image: "
                 "circle:CX,CY,R, box:X0,Y0,X1,Y1 (inclusive) or polygon:X1,Y1,X2,Y2,X3,Y3,... (or polygon:FILE); "
                 "repeatable. Without --roi/--roi-polygon/--mask: the whole image less the shapes.")


def region_options(f):
    """Add ``--roi``, ``--roi-polygon``, ``--mask`` and ``--exclude`` to a command (keywords ``roi``,
    ``roi_polygon``, ``mask``, ``exclude``: a tuple of texts)."""
    f = click.option("--exclude", "exclude", multiple=True, metavar="SHAPE", help=_EXCLUDE_HELP)(f)
    f = click.option("--mask", "mask", default=None, type=click.Path(dir_okay=False, path_type=Path),
                     help="Region of interest as a mask image (TIFF/PNG/BMP) of the images' size: non-zero = inside.")(f)
    f = click.option("--roi-polygon", "roi_polygon", default=None, metavar="VERTICES|FILE", help=_POLYGON_HELP)(f)
    f = click.option("--roi", "roi", nargs=4, type=float, default=None, metavar="X0 Y0 X1 Y1",
                     help="Region of interest as a box in px (bounds inclusive).")(f)
    return f


def _pairs(rows, where: str) -> np.ndarray:
    try:
        v = np.array([[float(a), float(b)] for a, b in rows], dtype=np.float64)
    except (TypeError, ValueError):
        raise click.BadParameter(f"{where}: every vertex must be two numbers x,y (px)", param_hint="--roi-polygon") from None
    return v.reshape(-1, 2)


def _polygon_file(path: str) -> np.ndarray:
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise click.BadParameter(f"cannot read {path}: {exc}", param_hint="--roi-polygon") from None
    if text.lstrip().startswith(("[", "{")):
        try:
            data = json.loads(text)
        except json.JSONDecodeError as exc:
            raise click.BadParameter(f"{path} is not valid JSON ({exc})", param_hint="--roi-polygon") from None
        if isinstance(data, dict):
            data = data.get("polygon", data.get("vertices"))
        if not isinstance(data, list) or not all(isinstance(p, (list, tuple)) and len(p) == 2 for p in data):
            raise click.BadParameter(f"{path}: expected a JSON list of [x, y] vertices (or {{\"polygon\": [...]}})",
                                     param_hint="--roi-polygon")
        return _pairs(data, path)
    rows = []
    for k, line in enumerate(text.splitlines()):
        parts = [p for p in line.replace(";", ",").replace("\t", ",").replace(" ", ",").split(",") if p]
        if not parts or parts[0].startswith("#"):
            continue
        if len(parts) != 2:
            raise click.BadParameter(f"{path} line {k + 1}: expected x,y, got {line!r}", param_hint="--roi-polygon")
        try:
            rows.append((float(parts[0]), float(parts[1])))
        except ValueError:
            if rows:  # only the first line may be a header
                raise click.BadParameter(f"{path} line {k + 1}: expected two numbers x,y, got {line!r}",
                                         param_hint="--roi-polygon") from None
    return _pairs(rows, path)


def parse_polygon(value: str) -> np.ndarray:
    """(N, 2) vertices from ``"x,y;x,y;..."`` or from a JSON/CSV file (see the module docstring)."""
    if os.path.isfile(value):
        return _polygon_file(value)
    rows = [p.split(",") for p in value.replace(" ", "").split(";") if p]
    if not rows or any(len(r) != 2 for r in rows):
        raise click.BadParameter(f'give the vertices as "x,y;x,y;..." (px) or a JSON/CSV file of them; got {value!r} '
                                 "(no such file either)", param_hint="--roi-polygon")
    return _pairs(rows, repr(value))


def parse_exclusion(text: str):
    """One ``--exclude`` shape (:func:`dic.correlation.points.exclusion`; ``polygon:FILE`` read as
    ``--roi-polygon`` reads a file); a bad shape is a ``click.BadParameter`` naming ``--exclude``."""
    from dic.correlation.points import exclusion

    kind, sep, rest = text.partition(":")
    try:
        if sep and kind.strip().lower() == "polygon" and os.path.isfile(rest.strip()):
            try:
                vertices = _polygon_file(rest.strip())
            except click.BadParameter as exc:
                raise ValueError(exc.message) from None
            return exclusion({"polygon": vertices.tolist()})
        return exclusion(text)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--exclude") from None


def parse_region(roi, roi_polygon, mask, exclude=()):
    """The library's ``roi`` from the options: a box tuple, (N, 2) vertices, a mask path, or None; with
    ``--exclude`` shapes, the dict form ``{"box" | "polygon" | "mask": ..., "exclude": [...]}``
    (:mod:`dic.correlation.points`)."""
    given = [n for n, v in (("--roi", roi), ("--roi-polygon", roi_polygon), ("--mask", mask)) if v]
    if len(given) > 1:
        raise click.UsageError(f"give one region of interest, not {' and '.join(given)}")
    if roi:
        base = tuple(float(c) for c in roi)
    elif roi_polygon:
        base = parse_polygon(roi_polygon)
    elif mask:
        base = os.fspath(mask)
    else:
        base = None
    if not exclude:
        return base
    shapes = [parse_exclusion(t).settings() for t in exclude]
    if base is None:
        return {"exclude": shapes}
    if roi:
        return {"box": list(base), "exclude": shapes}
    if roi_polygon:
        return {"polygon": base.tolist(), "exclude": shapes}
    return {"mask": base, "exclude": shapes}
