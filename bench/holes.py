"""Holes and free edges: subsets correlated on all their pixels (``subset_mask="none"``) or on the specimen's
pixels only (``"region"``, :mod:`kernels.icgn_masked`), against exact truth.

``python -m bench.holes [--json PATH]`` prints, for each case, order and mode: the RMS error of the
interior points (subset entirely on the specimen), the RMS error of the kept edge points (subset
overlapping the hole or the background), their ratio, and the share of the edge points kept (valid).

Cases (:func:`case`; dic.synth renders, exact truth ``u = 0.008 x``, ``v = 0``: a 0.8 % stretch about
the image's left edge, 1.3-2.5 px of motion where the holes and edges are; 1 GL noise, 8 bits):

* ``hole``: a 30 px hole (radius 15 px) in a speckled plate, the dark featureless background seen through it;
* ``edges``: a speckled band with two slanted free edges on the dark featureless background;
* ``hole-textured``, ``edges-textured``: the same, with a *textured* stationary background (a speckled
  fixture seen through the hole / behind the edges: :func:`dic.synth.specimen_on_background` ``behind=``),
  where correlating the background pixels pulls the warp towards zero motion.

The region is given as the mask of the specimen (the hole / the band: ``roi=``); the POIs are the
grid points (subset 21, step 4) inside it; :class:`dic.Tracker` with the "zncc" start search.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

SHAPE = (200, 320)
SUBSET = 21
STEP = 4
STRETCH = 0.008
NOISE = 1.0
HOLE_CENTRE = (240.0, 100.0)
HOLE_RADIUS = 15.0
#: the band of the "edges" cases (reference px): two slanted straight edges
BAND = np.array([[-50.0, 55.0], [400.0, 70.0], [400.0, 150.0], [-50.0, 135.0]])
CASES = ("hole", "edges", "hole-textured", "edges-textured")


def displacement(x, y):
    """The exact displacement (px) of a material point (x, y) of the reference."""
    return STRETCH * np.asarray(x, dtype=np.float64), 0.0 * np.asarray(y, dtype=np.float64)


def case(name: str, seed: int = 3):
    """``(reference, current, region)``: the images (float32) and the specimen's pixels (H, W) bool."""
    from dic.correlation.points import _inside_polygon
    from dic.synth import specimen_on_background, speckle_image

    if name not in CASES:
        raise ValueError(f"case must be one of {CASES}, got {name!r}")
    h, w = SHAPE
    yy, xx = np.mgrid[0:h, 0:w]
    if name.startswith("hole"):
        cx, cy = HOLE_CENTRE

        def specimen(x, y):
            return (x - cx) ** 2 + (y - cy) ** 2 > HOLE_RADIUS ** 2

        region = specimen(xx, yy)
    else:
        specimen = BAND
        region = _inside_polygon(np.stack([xx.ravel(), yy.ravel()], 1).astype(np.float64), BAND).reshape(h, w)
    behind = None
    if name.endswith("textured"):
        # a stationary speckled fixture behind the specimen (coarser speckle, darker)
        behind = 0.5 * speckle_image(SHAPE, radius=3.0, seed=seed + 100, bits=None)
    reference, current, _ = specimen_on_background(SHAPE, displacement, specimen=specimen, noise_sigma=NOISE,
                                                   seed=seed, behind=behind)
    return reference, current, region


def measure(name: str, order: int, subset_mask: str, *, device: str = "cpu", robust=False) -> dict:
    """Interior and edge errors of one case, order and ``subset_mask`` mode (see the module docstring).
    ``robust``: the Tracker's option; False (plain IC-GN, as these figures were first measured) isolates what
    the masks do; the 2-D default, ``"adaptive"``, also refines subsets whose residuals show outliers, which
    pulls part of the unmasked error back (docs/dic2d.md, Holes, edges and masks)."""
    from dic import Tracker
    from dic.correlation.subset_masks import subset_pixel_masks

    reference, current, region = case(name)
    t0 = time.perf_counter()
    tracker = Tracker(reference, step=STEP, roi=region, subset=SUBSET, order=order, search="zncc", search_radius=4,
                      subset_mask=subset_mask, robust=robust, device=device)
    field = tracker.track(current)
    seconds = time.perf_counter() - t0
    pts = field.points
    u, v = displacement(pts[:, 0], pts[:, 1])
    error = np.hypot(field.u - u, field.v - v)
    inside_image = ((pts[:, 0] >= SUBSET // 2) & (pts[:, 0] <= SHAPE[1] - 1 - SUBSET // 2)
                    & (pts[:, 1] >= SUBSET // 2) & (pts[:, 1] <= SHAPE[0] - 1 - SUBSET // 2))
    edge = ~subset_pixel_masks(pts, SUBSET, region).all(axis=1) & inside_image
    interior = ~edge & inside_image
    ok = field.valid
    interior_rms = float(np.sqrt(np.mean(error[ok & interior] ** 2)))
    edge_rms = float(np.sqrt(np.mean(error[ok & edge] ** 2))) if np.any(ok & edge) else float("nan")
    return {"case": name, "order": order, "subset_mask": subset_mask, "robust": robust, "interior_rms_px": interior_rms,
            "edge_rms_px": edge_rms, "edge_over_interior": edge_rms / interior_rms,
            "edge_kept": float(np.count_nonzero(ok & edge) / max(1, np.count_nonzero(edge))),
            "edge_points": int(np.count_nonzero(edge)), "interior_points": int(np.count_nonzero(interior)),
            "edge_max_px": float(error[ok & edge].max()) if np.any(ok & edge) else float("nan"),
            "seconds": seconds}


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", help="write the rows to this JSON file")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    rows = []
    print(f"{'case':16s} {'order':>5s} {'subset_mask':>11s} {'interior RMS':>12s} {'edge RMS':>9s} {'ratio':>6s} "
          f"{'edge kept':>9s} {'edge max':>8s}")
    for name in CASES:
        for order in (1, 2):
            for mode in ("none", "region"):
                r = measure(name, order, mode, device=args.device)
                rows.append(r)
                print(f"{name:16s} {order:5d} {mode:>11s} {r['interior_rms_px']:12.4f} {r['edge_rms_px']:9.4f} "
                      f"{r['edge_over_interior']:6.2f} {100 * r['edge_kept']:8.1f}% {r['edge_max_px']:8.3f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"shape": SHAPE, "subset": SUBSET, "step": STEP, "stretch": STRETCH, "noise_sigma": NOISE,
                       "rows": rows}, f, indent=1)
    return rows


if __name__ == "__main__":
    main()
