"""Fuzz pass over the calibration importers and the image reader (issue 15: nothing silently wrong).

Run from the repository root::

    .venv/bin/python -m bench.fuzz_inputs                  # full: 500 mutants per seed file (9500 files)
    .venv/bin/python -m bench.fuzz_inputs --per-seed 30    # reduced (tests/project/test_fuzz_inputs.py)
    .venv/bin/python -m bench.fuzz_inputs --seed 7 --keep failures/   # other mutants; keep failing files

Seed files (written fresh into a temporary folder each run): OpenCV FileStorage rigs (YAML, XML,
JSON) and a camera (YAML), DICe camera systems (world extrinsics with a rotation matrix; camera-to-
camera extrinsics with Euler angles), VIC-3D calibrations (the project layout with its
``<polygonmask>`` size and the bare ``<calibration>`` layout with the size given), Specula camera
and rig JSON (with covariances), Specula target JSON (phase, checkerboard, circle grid), and images
(PNG 8/16 bit, TIFF 8/16 bit, float32 and LZW-compressed 16 bit, BMP 8 bit): 20 seed files.

Each mutant applies 1-3 random edits to one seed: for text files byte flips, truncation, deleted /
duplicated / swapped lines, a number replaced by an "interesting" token (0, -1, nan, inf, 1e308,
2**63, text, a bracket...), deleted spans, inserted bytes, and structural edits (a JSON value
replaced by another type or deleted, an XML element or attribute deleted or changed, deep nesting);
for images truncation, byte flips (biased to the header) and header-field edits (PNG IHDR with a
valid CRC, TIFF tags, BMP header fields).

Every load must either return a valid object or raise ``ValueError``:

* cameras: finite ``K`` with ``fx, fy > 0``, last row ``[0, 0, 1]``, 0/4/5/8 finite distortion
  terms, a positive image size (a file with ``(0, 0)``, size unknown, is refused) and, for the
  foreign formats, the principal point inside the image;
* rigs: two valid cameras, ``R_right_left`` a proper rotation (``|R Rᵀ − I| < 1e-9``, det +1), a
  finite non-zero ``t_right_left``, a finite 6x6 covariance if any;
* images: a non-empty 2-D array of a real numeric dtype (float images may hold non-finite pixels:
  counted and reported, since they are data, and refused by the DIC launchers).

Any other exception type, a hang (``--timeout`` s per file), or an invalid object returned is a
failure: printed with the file kind and the edits, the file kept under ``--keep``. Exit status 1
when there is a failure. Writes ``bench/results/fuzz_inputs.json`` (counts, time, failures) unless
``--no-save``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import random
import re
import shutil
import signal
import struct
import sys
import tempfile
import time
import traceback
import xml.etree.ElementTree as ET
import zlib
from datetime import datetime, timezone

import numpy as np

from calibration.camera import Camera, rotation_from_vector
from calibration.formats import load_dice_xml, load_opencv, load_vic3d_xml, save_dice_xml, save_opencv, save_vic3d_xml
from calibration.stereo import StereoRig
from calibration.targets import CheckerboardTarget, CircleGridTarget, PhaseTarget, load_target
from kernels.images import read_image

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")

INTERESTING = [b"0", b"-1", b"nan", b"inf", b"-inf", b"1e308", b"-1e308", b"1e400", b"1e-320", b"", b"abc",
               b"9223372036854775808", b"2147483648", b"0.5", b"-0", b"{", b"}", b"[", b"]", b",", b"<", b">",
               b'"', b"'", b"&", b"\x00", b"\xff\xfe", b"1280.5", b"  ", b"1,2", b"0x10", b"True"]
NUMBER = re.compile(rb"-?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?")
JSON_VALUES = [None, True, False, 0, -1, 1.5, 1e308, float("nan"), float("inf"), "x", "", [], {}, [1, 2], [[1]],
               {"a": 1}, 2 ** 63, [0, 0], [1e9, 1e9], [5], [[1, 0, 0], [0, 1, 0], [0, 0, -1]]]


class Hang(Exception):
    pass


# -- seeds -----------------------------------------------------------------------------------------
def _rig():
    left = Camera(K=[[2400.0, 0.3, 640.5], [0, 2399.0, 400.25], [0, 0, 1]], dist=[-0.05, 0.02, 1e-4, -2e-4, 0.001],
                  size=(1280, 800), name="left",
                  covariance=np.diag([4.0, 4.0, 1.0, 1.0]), covariance_names=("fx", "fy", "cx", "cy"))
    right = Camera(K=[[2380.0, 0, 630.0], [0, 2381.0, 395.0], [0, 0, 1]], dist=[-0.04, 0.01, 0, 0, 0.0],
                   size=(1280, 800), name="right")
    return StereoRig(left, right, rotation_from_vector(np.radians([0.5, -18.0, 0.3])), [130.5, -0.6, 17.0],
                     covariance=np.eye(6) * 1e-6, metadata={"note": "fuzz seed"})


DICE_RELATIVE = """<ParameterList>
<Parameter name="xml_file_format" type="string" value="DICe_xml_camera_system_file" />
<Parameter name="extrinsics_relative_camera_to_camera" type="bool" value="true" />
<ParameterList name="CAMERA 0">
<Parameter name="CX" type="double" value="640.5" /><Parameter name="CY" type="double" value="400.25" />
<Parameter name="FX" type="double" value="2400.0" /><Parameter name="FY" type="double" value="2399.0" />
<Parameter name="K1" type="double" value="0.05" />
<Parameter name="LENS_DISTORTION_MODEL" type="string" value="OPENCV_LENS_DISTORTION" />
<Parameter name="IMAGE_HEIGHT_WIDTH" type="string" value="{ 800, 1280 }" />
</ParameterList>
<ParameterList name="CAMERA 1">
<Parameter name="CX" type="double" value="630.0" /><Parameter name="CY" type="double" value="395.0" />
<Parameter name="FX" type="double" value="2380.0" /><Parameter name="FY" type="double" value="2381.0" />
<Parameter name="P2" type="double" value="0.001" />
<Parameter name="LENS_DISTORTION_MODEL" type="string" value="OPENCV_LENS_DISTORTION" />
<Parameter name="TX" type="double" value="130.5" /><Parameter name="TY" type="double" value="-0.6" />
<Parameter name="TZ" type="double" value="17.0" />
<Parameter name="ALPHA" type="double" value="0.09" /><Parameter name="BETA" type="double" value="-18.0" />
<Parameter name="GAMMA" type="double" value="-0.08" />
<Parameter name="IMAGE_HEIGHT_WIDTH" type="string" value="{ 800, 1280 }" />
</ParameterList>
</ParameterList>
"""


def make_seeds(folder) -> list[dict]:
    """Write the seed files; each entry: name, path, kind ("text"/"json"/"xml"/"image"), loader, check."""
    import cv2
    import tifffile

    rig = _rig()
    seeds = []

    def add(name, kind, loader, check):
        seeds.append({"name": name, "path": os.path.join(folder, name), "kind": kind, "loader": loader,
                      "check": check})
        return seeds[-1]["path"]

    for ext in ("yml", "xml", "json"):
        save_opencv(add(f"opencv_rig.{ext}", "text", load_opencv, check_rig), rig)
    save_opencv(add("opencv_camera.yml", "text", load_opencv, check_camera), rig.left)
    save_dice_xml(add("dice_world.xml", "xml", load_dice_xml, check_rig), rig)
    with open(add("dice_relative.xml", "xml", load_dice_xml, check_rig), "w") as f:
        f.write(DICE_RELATIVE)
    save_vic3d_xml(add("vic3d_project.xml", "xml", load_vic3d_xml, check_rig), rig, allow_lossy=True)
    text = open(os.path.join(folder, "vic3d_project.xml"), encoding="iso-8859-1").read()
    cal = text[text.index("<calibration"):text.index("</calibration>") + len("</calibration>")]
    with open(add("vic3d_calibration.xml", "xml", lambda p: load_vic3d_xml(p, image_size=(1280, 800)), check_rig),
              "w", encoding="iso-8859-1") as f:
        f.write(cal)
    rig.left.save(add("camera.json", "json", Camera.load, lambda c: check_camera(c, foreign=False)))
    rig.save(add("rig.json", "json", StereoRig.load, lambda r: check_rig(r, foreign=False)))

    for t in (PhaseTarget(grid=(6, 3), pitch=300, steps=3), CheckerboardTarget(corners=(9, 6), square=100),
              CircleGridTarget(grid=(6, 4), pitch=150)):
        t.save_json(add(f"target_{type(t).__name__}.json", "json", load_target, check_target))
    rng = np.random.default_rng(5)
    img8 = rng.integers(0, 256, (30, 40), dtype=np.uint8)
    img16 = rng.integers(0, 65536, (30, 40), dtype=np.uint16)
    cv2.imwrite(add("image8.png", "image", read_image, check_image), img8)
    cv2.imwrite(add("image16.png", "image", read_image, check_image), img16)
    cv2.imwrite(add("image8.bmp", "image", read_image, check_image), img8)
    tifffile.imwrite(add("image8.tif", "image", read_image, check_image), img8)
    tifffile.imwrite(add("image16.tif", "image", read_image, check_image), img16)
    tifffile.imwrite(add("imagef.tiff", "image", read_image, check_image), img16.astype(np.float32) / 65535)
    cv2.imwrite(add("image16_lzw.tif", "image", read_image, check_image), img16)  # OpenCV's TIFFs are LZW
    for s in seeds:  # every seed must load as it is
        s["check"](s["loader"](s["path"]))
    return seeds


# -- validity of what a load returns ---------------------------------------------------------------
def check_camera(cam, foreign=True):
    assert isinstance(cam, Camera), f"a {type(cam).__name__}, not a Camera"
    K = cam.K
    assert K.shape == (3, 3) and np.all(np.isfinite(K)), "K not finite 3x3"
    assert K[0, 0] > 0 and K[1, 1] > 0, f"focal lengths {K[0, 0]}, {K[1, 1]}"
    assert np.array_equal(K[2], [0, 0, 1]) and K[1, 0] == 0, "K not upper triangular with [0, 0, 1]"
    assert cam.dist.size in (0, 4, 5, 8) and np.all(np.isfinite(cam.dist)), f"distortion {cam.dist}"
    w, h = cam.size
    assert isinstance(w, int) and isinstance(h, int), f"size {cam.size}"
    assert w > 0 and h > 0, f"size {cam.size}"  # a file must give the size (Specula's JSON too, issue 24)
    if foreign:
        assert -0.5 <= K[0, 2] <= w - 0.5 and -0.5 <= K[1, 2] <= h - 0.5, f"principal point {K[:2, 2]} outside"
    if cam.covariance is not None:
        assert np.all(np.isfinite(cam.covariance)), "covariance not finite"


def check_rig(rig, foreign=True):
    assert isinstance(rig, StereoRig), f"a {type(rig).__name__}, not a StereoRig"
    check_camera(rig.left, foreign)
    check_camera(rig.right, foreign)
    R = rig.R_right_left
    assert R.shape == (3, 3) and np.all(np.isfinite(R)), "R not finite"
    assert np.max(np.abs(R @ R.T - np.eye(3))) < 1e-9 and np.linalg.det(R) > 0, "R not a proper rotation"
    t = rig.t_right_left
    assert t.shape == (3,) and np.all(np.isfinite(t)) and np.linalg.norm(t) > 0, f"t {t}"
    if rig.covariance is not None:
        assert rig.covariance.shape == (6, 6) and np.all(np.isfinite(rig.covariance)), "covariance"


def check_target(t):
    assert isinstance(t, (PhaseTarget, CheckerboardTarget, CircleGridTarget)), type(t).__name__
    assert len(t.screen) == 2 and min(t.screen) > 0 and t.pixel_pitch > 0 and np.isfinite(t.pixel_pitch), \
        f"screen {t.screen}, pixel pitch {t.pixel_pitch}"
    X = t.object_points
    assert X.ndim == 2 and X.shape[1] == 3 and len(X) > 0 and np.all(np.isfinite(X)), "object points"


def check_image(arr):
    assert isinstance(arr, np.ndarray), type(arr).__name__
    assert arr.ndim == 2 and arr.size > 0, f"shape {arr.shape}"
    assert np.issubdtype(arr.dtype, np.number) and not np.iscomplexobj(arr), f"dtype {arr.dtype}"


# -- mutations -------------------------------------------------------------------------------------
def _lines(data):
    return data.split(b"\n")


def mutate_bytes(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    ops = ["flip", "truncate", "del_line", "dup_line", "swap_lines", "number", "number", "number", "del_span",
           "insert"]
    op = rng.choice(ops)
    if not data:
        return b"{", "insert into empty"
    if op == "flip":
        i = rng.randrange(len(data))
        return data[:i] + bytes([rng.randrange(256)]) + data[i + 1:], f"byte {i} changed"
    if op == "truncate":
        i = rng.randrange(len(data))
        return data[:i], f"truncated at {i}"
    lines = _lines(data)
    if op in ("del_line", "dup_line", "swap_lines") and len(lines) > 1:
        i, j = rng.randrange(len(lines)), rng.randrange(len(lines))
        if op == "del_line":
            del lines[i]
        elif op == "dup_line":
            lines.insert(j, lines[i])
        else:
            lines[i], lines[j] = lines[j], lines[i]
        return b"\n".join(lines), f"{op} {i} {j}"
    if op == "number":
        nums = list(NUMBER.finditer(data))
        if nums:
            m = rng.choice(nums)
            tok = rng.choice(INTERESTING) if rng.random() < 0.7 else repr(float(m.group()) * rng.choice(
                [-1, 0.5, 2, 10, 1e6, 1.05])).encode() if _is_float(m.group()) else b"0"
            return data[:m.start()] + tok + data[m.end():], f"number {m.group()!r} -> {tok!r}"
    if op == "del_span":
        i = rng.randrange(len(data))
        n = rng.randint(1, 40)
        return data[:i] + data[i + n:], f"deleted {n} bytes at {i}"
    i = rng.randrange(len(data) + 1)
    tok = rng.choice(INTERESTING)
    return data[:i] + tok + data[i:], f"inserted {tok!r} at {i}"


def _is_float(b):
    try:
        float(b)
        return True
    except ValueError:
        return False


def _json_nodes(node, path=()):
    yield path, node
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _json_nodes(v, path + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _json_nodes(v, path + (i,))


def mutate_json(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    if rng.random() < 0.35:
        return mutate_bytes(data, rng)
    doc = json.loads(data)
    if rng.random() < 0.03:
        depth = rng.choice([100, 5000, 200_000])
        return b"[" * depth + b"]" * depth, f"nesting {depth} deep"
    nodes = [(p, n) for p, n in _json_nodes(doc) if p]
    path, _ = rng.choice(nodes)
    parent = doc
    for k in path[:-1]:
        parent = parent[k]
    if isinstance(parent, dict) and rng.random() < 0.3:
        del parent[path[-1]]
        what = f"deleted {path}"
    else:
        v = rng.choice(JSON_VALUES)
        parent[path[-1]] = v
        what = f"{path} = {v!r:.40}"
    return json.dumps(doc).encode(), what


def mutate_xml(data: bytes, rng: random.Random) -> tuple[bytes, str]:
    if rng.random() < 0.4:
        return mutate_bytes(data, rng)
    try:
        root = ET.fromstring(data)
    except (ET.ParseError, LookupError, ValueError):  # already broken by an earlier edit
        return mutate_bytes(data, rng)
    elems = list(root.iter())
    parents = {c: p for p in elems for c in p}
    el = rng.choice(elems)
    op = rng.choice(["delete", "attr_delete", "attr_set", "text", "duplicate"])
    if op == "delete" and el in parents:
        parents[el].remove(el)
        what = f"deleted <{el.tag} {el.attrib}>"
    elif op == "duplicate" and el in parents:
        parents[el].append(ET.fromstring(ET.tostring(el)))
        what = f"duplicated <{el.tag} {el.attrib}>"
    elif op == "attr_delete" and el.attrib:
        k = rng.choice(sorted(el.attrib))
        del el.attrib[k]
        what = f"deleted attribute {k} of <{el.tag}>"
    elif op == "attr_set" and el.attrib:
        k = rng.choice(sorted(el.attrib))
        v = rng.choice(INTERESTING).decode("latin-1")
        v = v if rng.random() < 0.6 else re.sub(r"-?\d+(\.\d*)?(e[-+]?\d+)?", lambda m: v or "0", el.attrib[k], count=1)
        el.set(k, "".join(ch for ch in v if ch.isprintable()))
        what = f"<{el.tag}> {k} = {el.get(k)!r}"
    else:
        nums = (el.text or "").split()
        if nums:
            i = rng.randrange(len(nums))
            nums[i] = rng.choice(INTERESTING).decode("latin-1")
            el.text = " ".join("".join(ch for ch in n if ch.isprintable()) for n in nums)
        else:
            el.text = rng.choice(["1 2 3", "nan", "x"])
        what = f"text of <{el.tag}> = {el.text!r:.60}"
    return ET.tostring(root), what


def mutate_image(data: bytes, rng: random.Random, name: str) -> tuple[bytes, str]:
    if len(data) < 2:
        return mutate_bytes(data, rng)
    op = rng.choice(["truncate", "flip", "flip", "header", "header", "header"])
    if op == "truncate":
        i = rng.randrange(len(data))
        return data[:i], f"truncated at {i}"
    if op == "flip":
        out = bytearray(data)
        notes = []
        for _ in range(rng.randint(1, 4)):
            i = rng.randrange(min(len(out), 128)) if rng.random() < 0.6 else rng.randrange(len(out))
            out[i] = rng.randrange(256)
            notes.append(i)
        return bytes(out), f"bytes {notes} changed"
    value = rng.choice([0, 1, 2, 3, 7, 8, 16, 17, 32, 255, 256, 65535, 65536, 2 ** 31 - 1, 2 ** 31, 2 ** 32 - 1,
                        rng.randrange(2 ** 32)])
    out = bytearray(data)
    if name.endswith(".png"):  # IHDR: width, height, bit depth, colour type, compression, filter, interlace
        field = rng.choice(["width", "height", "depth", "colour", "compression", "filter", "interlace"])
        off, size = {"width": (16, 4), "height": (20, 4), "depth": (24, 1), "colour": (25, 1),
                     "compression": (26, 1), "filter": (27, 1), "interlace": (28, 1)}[field]
        out[off:off + size] = (value % (256 ** size)).to_bytes(size, "big")
        out[29:33] = struct.pack(">I", zlib.crc32(bytes(out[12:29])) & 0xFFFFFFFF)  # keep the CRC valid
        return bytes(out), f"IHDR {field} = {value % (256 ** size)}"
    if name.endswith(".bmp"):
        field = rng.choice(["offset", "width", "height", "bpp", "compression", "colours"])
        off, fmt = {"offset": (10, "<I"), "width": (18, "<i"), "height": (22, "<i"), "bpp": (28, "<H"),
                    "compression": (30, "<I"), "colours": (46, "<I")}[field]
        v = value % (2 ** (8 * struct.calcsize(fmt)))
        if fmt == "<i" and v >= 2 ** 31:
            v -= 2 ** 32
        out[off:off + struct.calcsize(fmt)] = struct.pack(fmt, v)
        return bytes(out), f"BMP {field} = {v}"
    import io

    import tifffile

    try:
        with tifffile.TiffFile(io.BytesIO(data)) as tif:
            tags = [t for t in tif.pages[0].tags.values() if t.count == 1 and t.dtype in (3, 4)]  # SHORT, LONG
            tag = rng.choice(tags)
            fmt = "<H" if tag.dtype == 3 else "<I"
            v = value % (2 ** (8 * struct.calcsize(fmt)))
            off = tag.valueoffset
    except Exception:  # noqa: BLE001 - an earlier edit broke the header: edit bytes instead
        return mutate_bytes(data, rng)
    out[off:off + struct.calcsize(fmt)] = struct.pack(fmt, v)
    return bytes(out), f"TIFF tag {tag.name} = {v}"


def mutate(seed: dict, data: bytes, rng: random.Random) -> tuple[bytes, list[str]]:
    notes = []
    for _ in range(rng.choice([1, 1, 1, 2, 3])):
        if seed["kind"] == "image":
            data, what = mutate_image(data, rng, seed["name"]) if notes == [] or rng.random() < 0.5 else \
                mutate_bytes(data, rng)
        elif seed["kind"] == "json":
            try:
                data, what = mutate_json(data, rng)
            except (ValueError, RecursionError):  # already broken by an earlier edit
                data, what = mutate_bytes(data, rng)
        elif seed["kind"] == "xml":
            data, what = mutate_xml(data, rng)
        else:
            data, what = mutate_bytes(data, rng)
        notes.append(what)
    return data, notes


# -- the pass --------------------------------------------------------------------------------------
def _alarm(signum, frame):
    raise Hang()


def run(per_seed: int, seed: int = 0, keep: str | None = None, timeout: float = 20.0, verbose: bool = True) -> dict:
    import logging

    logging.getLogger("tifffile").setLevel(logging.CRITICAL)  # its warnings about the broken files it reads
    rng = random.Random(seed)
    work = tempfile.mkdtemp(prefix="specula_fuzz_")
    counts: dict[str, dict[str, int]] = {}
    failures = []
    t0 = time.perf_counter()
    old = signal.signal(signal.SIGALRM, _alarm)
    try:
        seeds = make_seeds(work)
        for s in seeds:
            base = open(s["path"], "rb").read()
            c = counts.setdefault(s["name"], {"files": 0, "loaded": 0, "value_error": 0, "nonfinite_pixels": 0,
                                              "failures": 0})
            ext = os.path.splitext(s["name"])[1]
            for k in range(per_seed):
                data, notes = mutate(s, base, rng)
                path = os.path.join(work, f"mutant{ext}")
                with open(path, "wb") as f:
                    f.write(data)
                c["files"] += 1
                problem = None
                signal.setitimer(signal.ITIMER_REAL, timeout)
                try:
                    obj = s["loader"](path)
                except ValueError:
                    c["value_error"] += 1
                except Hang:
                    problem = f"no answer within {timeout} s"
                except Exception as exc:  # noqa: BLE001 - the point of the pass
                    problem = f"{type(exc).__name__}: {exc}"[:300] + " | " + traceback.format_exc(limit=-2)[-400:]
                else:
                    try:
                        s["check"](obj)
                        c["loaded"] += 1
                        if isinstance(obj, np.ndarray) and obj.dtype.kind == "f" and not np.all(np.isfinite(obj)):
                            c["nonfinite_pixels"] += 1
                    except AssertionError as exc:
                        problem = f"accepted an invalid value: {exc}"
                finally:
                    signal.setitimer(signal.ITIMER_REAL, 0)
                if problem:
                    c["failures"] += 1
                    failures.append({"seed_file": s["name"], "mutant": k, "edits": notes, "problem": problem})
                    if verbose:
                        print(f"FAIL {s['name']} #{k} {notes}: {problem}", file=sys.stderr)
                    if keep:
                        os.makedirs(keep, exist_ok=True)
                        shutil.copy(path, os.path.join(keep, f"{os.path.splitext(s['name'])[0]}_{k}{ext}"))
    finally:
        signal.signal(signal.SIGALRM, old)
        shutil.rmtree(work, ignore_errors=True)
    total = {k: sum(c[k] for c in counts.values()) for k in ("files", "loaded", "value_error", "nonfinite_pixels",
                                                            "failures")}
    return {"per_seed": per_seed, "seed": seed, "seconds": time.perf_counter() - t0, "total": total,
            "by_seed_file": counts, "failures": failures}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--per-seed", type=int, default=500, help="mutants per seed file (default 500)")
    ap.add_argument("--seed", type=int, default=0, help="random seed of the mutations")
    ap.add_argument("--timeout", type=float, default=20.0, help="seconds one load may take")
    ap.add_argument("--keep", default=None, help="folder to copy failing mutants into")
    ap.add_argument("--max-memory-gb", type=float, default=8.0,
                    help="address-space limit of this process (a header claiming a huge image then fails to "
                         "allocate instead of exhausting the machine); 0: none")
    ap.add_argument("--no-save", action="store_true", help="do not write bench/results/fuzz_inputs.json")
    args = ap.parse_args(argv)
    if args.per_seed < 1:
        ap.error("--per-seed must be >= 1")
    if args.max_memory_gb > 0:
        import resource

        lim = int(args.max_memory_gb * 2 ** 30)
        resource.setrlimit(resource.RLIMIT_AS, (lim, resource.getrlimit(resource.RLIMIT_AS)[1]))
    res = run(args.per_seed, args.seed, args.keep, args.timeout)
    print(f"{'seed file':30s} {'files':>6s} {'loaded':>7s} {'ValueError':>10s} {'non-finite px':>13s} {'FAIL':>5s}")
    for name, c in res["by_seed_file"].items():
        print(f"{name:30s} {c['files']:6d} {c['loaded']:7d} {c['value_error']:10d} {c['nonfinite_pixels']:13d} "
              f"{c['failures']:5d}")
    t = res["total"]
    print(f"{'total':30s} {t['files']:6d} {t['loaded']:7d} {t['value_error']:10d} {t['nonfinite_pixels']:13d} "
          f"{t['failures']:5d}   in {res['seconds']:.1f} s")
    if not args.no_save:
        os.makedirs(RESULTS, exist_ok=True)
        import cv2
        import PIL
        import tifffile

        res["environment"] = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                              "python": platform.python_version(), "numpy": np.__version__, "opencv": cv2.__version__,
                              "pillow": PIL.__version__, "tifffile": tifffile.__version__,
                              "machine": platform.machine(), "cpus": os.cpu_count()}
        with open(os.path.join(RESULTS, "fuzz_inputs.json"), "w") as f:
            json.dump(res, f, indent=1)
            f.write("\n")
    return 1 if t["failures"] else 0


if __name__ == "__main__":
    sys.exit(main())
