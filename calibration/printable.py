"""1:1 printable vector files of the conventional targets (checkerboards, circle grids): SVG and PDF.

The file's page is the target's screen area (``target.size_mm``: ``screen × pixel_pitch`` mm), so a
print at 100 % ("actual size", no "fit to page") reproduces the target's object points in mm. The
physical size is written into the file:

* SVG: ``width="…mm" height="…mm"`` and ``viewBox="0 0 W H"`` with one user unit = 1 mm;
* PDF (1.4, one page, written here without a PDF library): ``/MediaBox [0 0 W·72/25.4 H·72/25.4]``
  in points, and the drawing in mm through one ``cm`` transform (scale 72/25.4, y flipped so that
  page y runs down like the target frame).

Geometry: screen pixel ``(x_px, y_px)`` has its centre at ``(x_px, y_px) · pixel_pitch`` mm in the
target frame (:mod:`calibration.targets`); the screen area starts half a pixel before pixel 0, so a
target point ``X`` (mm) lies at page position ``X + pixel_pitch / 2`` (mm from the page's top-left
corner), returned by :func:`page_position`. Squares and circles are exact vector shapes (a circle in
the PDF is four cubic Bézier arcs, radial error 0.027 % of the radius), not the anti-aliased pixels of
the PNG images.

The phase target is not printable (it needs a monitor to show its phase-shifted images): refused.
"""
from __future__ import annotations

import os

import numpy as np

from .targets import CheckerboardTarget, CircleGridTarget

__all__ = ["MM_PER_INCH", "POINTS_PER_INCH", "page_size_mm", "page_position", "write_svg", "write_pdf",
           "write_printable"]

MM_PER_INCH = 25.4
POINTS_PER_INCH = 72.0
#: Bézier handle length of a quarter circle (4/3 (√2 − 1)).
_KAPPA = 4.0 * (np.sqrt(2.0) - 1.0) / 3.0


def _check(target) -> None:
    if not isinstance(target, (CheckerboardTarget, CircleGridTarget)):
        raise ValueError(f"only checkerboards and circle grids can be printed, got {type(target).__name__} "
                         "(a phase target needs a monitor to show its phase-shifted images)")


def page_size_mm(target) -> tuple[float, float]:
    """(width, height) of the printed page in mm: the target's screen area, ``screen × pixel_pitch``."""
    _check(target)
    return float(target.screen[0] * target.pixel_pitch), float(target.screen[1] * target.pixel_pitch)


def page_position(target, points_mm) -> np.ndarray:
    """Target-frame points (N, 2) or (N, 3) mm → (N, 2) mm from the page's top-left corner (x right, y down)."""
    _check(target)
    p = np.asarray(points_mm, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] not in (2, 3):
        raise ValueError(f"points_mm must have shape (N, 2) or (N, 3), got {p.shape}")
    return p[:, :2] + 0.5 * target.pixel_pitch


def _shapes(target):
    """``("rect", x, y, w, h)`` / ``("circle", cx, cy, r)`` in page mm, all in the dark grey."""
    pitch = target.pixel_pitch
    half = 0.5 * pitch
    out = []
    if isinstance(target, CheckerboardTarget):
        nx, ny = np.array(target.corners) + 1
        s = target.square * pitch
        x0, y0 = (target.points_px[0] - target.square) * pitch + half  # outer corner of square (0, 0)
        for b in range(ny):
            for a in range(nx):
                if (a + b) % 2 == 0:
                    out.append(("rect", x0 + a * s, y0 + b * s, s, s))
    else:
        r = 0.5 * target.diameter * pitch
        for cx, cy in target.points_px * pitch + half:
            out.append(("circle", float(cx), float(cy), r))
    return out


def _grey(value: float) -> str:
    v = int(round(float(value)))
    return f"#{v:02x}{v:02x}{v:02x}"


def _fmt(x: float) -> str:
    """A length in mm with 0.1 µm resolution, no trailing zeros."""
    text = f"{x:.4f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def _describe(target) -> str:
    if isinstance(target, CheckerboardTarget):
        return (f"checkerboard {target.corners[0]}x{target.corners[1]} inner corners, "
                f"{_fmt(target.square * target.pixel_pitch)} mm squares")
    return (f"circle grid {target.grid[0]}x{target.grid[1]}, pitch {_fmt(target.pitch * target.pixel_pitch)} mm, "
            f"diameter {_fmt(target.diameter * target.pixel_pitch)} mm")


def write_svg(target, path) -> str:
    """Write ``target`` as a 1:1 SVG: ``width``/``height`` in mm, ``viewBox`` in mm; returns the path."""
    W, H = page_size_mm(target)
    dark = _grey(target.dark)
    lines = ['<?xml version="1.0" encoding="UTF-8"?>',
             f'<svg xmlns="http://www.w3.org/2000/svg" version="1.1" width="{_fmt(W)}mm" height="{_fmt(H)}mm" '
             f'viewBox="0 0 {_fmt(W)} {_fmt(H)}">',
             f"<title>Specula {_describe(target)}; print at 100 % (actual size)</title>",
             f'<rect x="0" y="0" width="{_fmt(W)}" height="{_fmt(H)}" fill="{_grey(target.light)}"/>',
             f'<g fill="{dark}" stroke="none" shape-rendering="crispEdges">']
    for shape in _shapes(target):
        if shape[0] == "rect":
            _, x, y, w, h = shape
            lines.append(f'<rect x="{_fmt(x)}" y="{_fmt(y)}" width="{_fmt(w)}" height="{_fmt(h)}"/>')
        else:
            _, cx, cy, r = shape
            lines.append(f'<circle cx="{_fmt(cx)}" cy="{_fmt(cy)}" r="{_fmt(r)}"/>')
    lines += ["</g>", "</svg>", ""]
    path = os.fspath(path)
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("\n".join(lines))
    return path


def _pdf_content(target) -> bytes:
    W, H = page_size_mm(target)
    k = POINTS_PER_INCH / MM_PER_INCH
    ops = [f"{k:.9f} 0 0 {-k:.9f} 0 {H * k:.6f} cm",  # mm, origin top-left, y down
           f"{target.light / 255:.6f} g", f"0 0 {_fmt(W)} {_fmt(H)} re f",
           f"{target.dark / 255:.6f} g"]
    for shape in _shapes(target):
        if shape[0] == "rect":
            _, x, y, w, h = shape
            ops.append(f"{_fmt(x)} {_fmt(y)} {_fmt(w)} {_fmt(h)} re f")
        else:
            _, cx, cy, r = shape
            c = _KAPPA * r
            f = _fmt
            ops += [f"{f(cx + r)} {f(cy)} m",
                    f"{f(cx + r)} {f(cy + c)} {f(cx + c)} {f(cy + r)} {f(cx)} {f(cy + r)} c",
                    f"{f(cx - c)} {f(cy + r)} {f(cx - r)} {f(cy + c)} {f(cx - r)} {f(cy)} c",
                    f"{f(cx - r)} {f(cy - c)} {f(cx - c)} {f(cy - r)} {f(cx)} {f(cy - r)} c",
                    f"{f(cx + c)} {f(cy - r)} {f(cx + r)} {f(cy - c)} {f(cx + r)} {f(cy)} c", "f"]
    return ("\n".join(ops) + "\n").encode("ascii")


def write_pdf(target, path) -> str:
    """Write ``target`` as a one-page 1:1 PDF whose MediaBox is the physical size in points; returns the path."""
    W, H = page_size_mm(target)
    k = POINTS_PER_INCH / MM_PER_INCH
    content = _pdf_content(target)
    title = f"Specula {_describe(target)}; print at 100 % (actual size)".replace("\\", "").replace("(", "[").replace(")", "]")
    objects = [b"<< /Type /Catalog /Pages 2 0 R >>",
               b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
               (f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {W * k:.6f} {H * k:.6f}] /Contents 4 0 R "
                "/Resources << >> >>").encode("ascii"),
               b"<< /Length " + str(len(content)).encode("ascii") + b" >>\nstream\n" + content + b"endstream",
               f"<< /Title ({title}) /Producer (Specula calibration.printable) >>".encode("ascii", "replace")]
    out = bytearray(b"%PDF-1.4\n%\xe2\xe3\xcf\xd3\n")
    offsets = []
    for i, body in enumerate(objects, start=1):
        offsets.append(len(out))
        out += f"{i} 0 obj\n".encode("ascii") + body + b"\nendobj\n"
    xref = len(out)
    out += f"xref\n0 {len(objects) + 1}\n0000000000 65535 f \n".encode("ascii")
    for off in offsets:
        out += f"{off:010d} 00000 n \n".encode("ascii")
    out += (f"trailer\n<< /Size {len(objects) + 1} /Root 1 0 R /Info {len(objects)} 0 R >>\n"
            f"startxref\n{xref}\n%%EOF\n").encode("ascii")
    path = os.fspath(path)
    with open(path, "wb") as fh:
        fh.write(bytes(out))
    return path


def write_printable(target, path) -> str:
    """Write ``target`` 1:1 as SVG or PDF, chosen by the suffix of ``path`` (``.svg`` / ``.pdf``)."""
    suffix = os.path.splitext(os.fspath(path))[1].lower()
    if suffix == ".svg":
        return write_svg(target, path)
    if suffix == ".pdf":
        return write_pdf(target, path)
    raise ValueError(f"a printable target is written as .svg or .pdf, got {os.fspath(path)!r}")
