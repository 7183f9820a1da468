"""1:1 printable targets (calibration/printable.py): the physical size read back from the SVG and PDF files.

Expected sizes are worked out by hand from the target's definition (a board of (nx + 1) x (ny + 1)
squares plus one square of margin on each side, 1 screen px = 1 mm), not by the code under test:
300 mm = 850.393701 pt (300 / 25.4 * 72)."""
import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from calibration.printable import page_position, write_pdf, write_printable, write_svg
from calibration.targets import CheckerboardTarget, CircleGridTarget, PhaseTarget

SVG_NS = "{http://www.w3.org/2000/svg}"


def _board():
    # 9 x 6 inner corners, 25 mm squares: 10 x 7 squares + 1 square margin = 300 x 225 mm
    return CheckerboardTarget(screen=None, pixel_pitch=1.0, corners=(9, 6), square=25)


def _circles():
    # 7 x 5 circles, 30 mm pitch, 12 mm diameter, on a 0.25 mm "pixel" grid: (7 + 1) x 30 = 240 mm by (5 + 1) x 30 = 180 mm
    return CircleGridTarget(screen=None, pixel_pitch=0.25, grid=(7, 5), pitch=120, diameter=48)


def _pdf_objects(data: bytes) -> dict:
    """Objects of a classic (uncompressed, xref-table) PDF, located through its xref table, which is checked."""
    start = int(re.search(rb"startxref\s+(\d+)\s+%%EOF", data).group(1))
    assert data[start:start + 4] == b"xref"
    m = re.match(rb"xref\s+0 (\d+)\s+", data[start:])
    n = int(m.group(1))
    table = data[start + m.end():].split(b"\n")[:n]
    objs = {}
    for i, row in enumerate(table[1:], start=1):
        off = int(row[:10])
        assert data[off:].startswith(f"{i} 0 obj".encode()), f"xref offset of object {i} is wrong"
        objs[i] = data[off:data.index(b"endobj", off)]
    return objs


def _media_box(data: bytes) -> list:
    return [float(v) for v in re.search(rb"/MediaBox \[([^\]]+)\]", data).group(1).split()]


def test_svg_checkerboard_has_the_physical_size_and_the_corners_in_mm(tmp_path):
    tg = _board()
    root = ET.parse(write_svg(tg, tmp_path / "board.svg")).getroot()
    assert root.get("width") == "300mm" and root.get("height") == "225mm"
    assert [float(v) for v in root.get("viewBox").split()] == [0, 0, 300, 225]
    rects = [r for r in root.iter(SVG_NS + "rect")][1:]  # the first one is the light page
    assert len(rects) == 35  # half of the 10 x 7 squares are dark
    sizes = {(float(r.get("width")), float(r.get("height"))) for r in rects}
    assert sizes == {(25.0, 25.0)}
    corners = {(round(float(r.get("x")) + dx, 6), round(float(r.get("y")) + dy, 6))
               for r in rects for dx in (0, 25) for dy in (0, 25)}
    # every inner corner is a corner of a dark square; the board spans 25..275 x 25..200 mm of the page
    for x, y in page_position(tg, tg.object_points):
        assert (round(x, 6), round(y, 6)) in corners
    xs = [float(r.get("x")) for r in rects]
    ys = [float(r.get("y")) for r in rects]
    assert min(xs) == 25 and max(xs) + 25 == 275 and min(ys) == 25 and max(ys) + 25 == 200
    # the inner corners 25 mm apart on the page, as the target file's object points say
    pos = page_position(tg, tg.object_points)
    assert np.allclose(np.diff(pos[:9, 0]), 25.0) and np.allclose(pos[0], [50.0, 50.0])


def test_svg_circle_grid_centres_and_radius(tmp_path):
    tg = _circles()
    root = ET.parse(write_svg(tg, tmp_path / "circles.svg")).getroot()
    assert root.get("width") == "240mm" and root.get("height") == "180mm"
    circles = list(root.iter(SVG_NS + "circle"))
    assert len(circles) == 35 and {float(c.get("r")) for c in circles} == {6.0}
    centres = np.array([[float(c.get("cx")), float(c.get("cy"))] for c in circles])
    np.testing.assert_allclose(centres, page_position(tg, tg.object_points), atol=1e-4)
    np.testing.assert_allclose(centres[0], [30.0, 30.0], atol=1e-4)  # one pitch from the page corner


@pytest.mark.parametrize("make, size_mm", [(_board, (300.0, 225.0)), (_circles, (240.0, 180.0))])
def test_pdf_media_box_is_the_physical_size_in_points(tmp_path, make, size_mm):
    tg = make()
    data = open(write_pdf(tg, tmp_path / "t.pdf"), "rb").read()
    assert data.startswith(b"%PDF-1.4") and data.rstrip().endswith(b"%%EOF")
    objs = _pdf_objects(data)
    assert b"/Type /Catalog" in objs[1] and b"/Count 1" in objs[2]
    box = _media_box(objs[3])
    assert box[:2] == [0.0, 0.0]
    np.testing.assert_allclose(box[2:], [v / 25.4 * 72 for v in size_mm], rtol=0, atol=1e-5)
    # the content stream: its /Length is right, and the drawing is in mm (scale 72 / 25.4, y flipped)
    stream = objs[4]
    length = int(re.search(rb"/Length (\d+)", stream).group(1))
    body = stream[stream.index(b"stream\n") + 7:]
    assert body[length:].strip() == b"endstream"
    cm = [float(v) for v in body.split(b"\n")[0].split()[:6]]
    np.testing.assert_allclose(cm, [72 / 25.4, 0, 0, -72 / 25.4, 0, size_mm[1] / 25.4 * 72], atol=1e-5)


def test_pdf_checkerboard_squares_in_mm(tmp_path):
    tg = _board()
    data = open(write_pdf(tg, tmp_path / "b.pdf"), "rb").read()
    rects = [tuple(map(float, m)) for m in re.findall(rb"([\d.]+) ([\d.]+) ([\d.]+) ([\d.]+) re f", data)]
    assert rects[0] == (0, 0, 300, 225) and len(rects) == 36
    assert {r[2:] for r in rects[1:]} == {(25.0, 25.0)}
    assert min(r[0] for r in rects[1:]) == 25 and min(r[1] for r in rects[1:]) == 25


def test_write_printable_by_suffix_and_refusals(tmp_path):
    tg = _circles()
    assert write_printable(tg, tmp_path / "c.SVG").endswith("c.SVG")
    assert open(write_printable(tg, tmp_path / "c.pdf"), "rb").read(8) == b"%PDF-1.4"
    with pytest.raises(ValueError, match=r"\.svg or \.pdf"):
        write_printable(tg, tmp_path / "c.png")
    with pytest.raises(ValueError, match="phase target needs a monitor"):
        write_svg(PhaseTarget(grid=(6, 3), pitch=300, steps=4), tmp_path / "p.svg")


def test_monitor_board_prints_at_the_monitor_size(tmp_path):
    """A board made for the paper's monitor (1920 x 1080 px of 0.311 mm) prints at 597.12 x 335.88 mm."""
    tg = CheckerboardTarget(corners=(9, 6), square=100)
    root = ET.parse(write_svg(tg, tmp_path / "m.svg")).getroot()
    assert root.get("width") == "597.12mm" and root.get("height") == "335.88mm"
    box = _media_box(open(write_pdf(tg, tmp_path / "m.pdf"), "rb").read())
    np.testing.assert_allclose(box[2:], [597.12 / 25.4 * 72, 335.88 / 25.4 * 72], atol=1e-5)


def test_cli_writes_printable_files(tmp_path):
    from click.testing import CliRunner

    from dic.cli import main

    res = CliRunner().invoke(main, ["target", "checkerboard", "--screen", "fit", "--pixel-pitch", "1", "--corners", "9x6",
                                    "--square", "25", "--printable", "-o", str(tmp_path / "b")])
    assert res.exit_code == 0, res.output
    assert "300 x 225 mm" in res.output and "print at 100 %" in res.output
    root = ET.parse(tmp_path / "b" / "checkerboard.svg").getroot()
    assert root.get("width") == "300mm" and root.get("height") == "225mm"
    box = _media_box((tmp_path / "b" / "checkerboard.pdf").read_bytes())
    np.testing.assert_allclose(box[2:], [300 / 25.4 * 72, 225 / 25.4 * 72], atol=1e-5)
    assert (tmp_path / "b" / "checkerboard.json").exists()
    res = CliRunner().invoke(main, ["target", "circles", "--screen", "fit", "--pixel-pitch", "0.5", "--grid", "4x3",
                                    "--pitch", "60", "--printable", "-o", str(tmp_path / "c")])
    assert res.exit_code == 0, res.output
    root = ET.parse(tmp_path / "c" / "circles.svg").getroot()
    assert root.get("width") == "150mm" and root.get("height") == "120mm"  # (4 + 1) x 30 mm, (3 + 1) x 30 mm
