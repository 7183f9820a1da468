"""The check of composed results on an evolving texture (docs/dic2d.md, "Re-verification of composed results").

Usage::

    .venv/bin/python -m bench.verify_composed [--size 512] [--frames 60] [--parts defaults,rule,inject]

Conditions: :func:`dic.synth.evolving_sequence` of ``--size`` px, ``--frames`` frames, a stretch along x growing to
30 %, 2 % of the speckles replaced every frame, 1 grey level of noise (the sequence of ``bench.robust``'s evolving
part, its seed), subset 21, step 10, the POIs whose subsets stay in the image to the last frame; exact Lagrangian
truth; CPU.

* **defaults**: ``track_sequence(..., reference="auto")`` with every default (the check on, ``verify_spread`` 4 and
  the peak test), without the check (``verify_composed=False``) and with the threshold alone
  (``verify_spread="off"``): per frame the valid fraction, the RMS error of the valid points, the points refused.
* **rule**: on the run without the check, per composed frame: the median and robust spread (1.4826 MAD) of the
  ZNCC against frame 0 at the composed warps (:class:`kernels.verify.ComposedCheck`), the correct points (within
  0.25 px) below 0.95 and below median - k spreads, the same points moved 1 px along x (a wrong match) below median
  - k spreads, and the peak test's flag rate (a probe 1 px away beats the ZNCC by more than a margin) on both.
* **inject**: a 1 px wrong match on a 4 x 4 block in the result of frame K (``reference="every:K"``, frame K
  against frame 0, so not checked, anchoring frames K+1..2K) with the defaults: per later frame the wrong points
  (> 0.75 px off) reported and flagged, the correct ones (< 0.05 px) reported and flagged.

Writes bench/results/verify_composed_<device>.json (``--out`` to write elsewhere).
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time
from datetime import datetime, timezone

import numpy as np

from bench._host import cpu_model, write_json

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
SEED = 2026 + 1  # bench.robust's evolving sequence
STRETCH = 0.3
MAD_TO_STD = 1.4826


def _sequence(args):
    from dic.synth import evolving_sequence

    seq = evolving_sequence((args.size, args.size), args.frames, stretch_final=STRETCH, fade_fraction=0.02,
                            noise_sigma=1.0, seed=SEED, device=args.device)
    half = 21 // 2 + 2
    cx, _ = seq.centre
    hx = ((args.size - 1) / 2 - half) / (1.0 + STRETCH)
    roi = (int(np.ceil(cx - hx)), half, int(np.floor(cx + hx)), args.size - 1 - half)
    return seq, [seq[k] for k in range(args.frames)], roi


def _errors(seq, field, k):
    truth = seq.displacement(np.asarray(field.points, np.float64), k)
    return np.hypot(np.asarray(field.u) - truth[:, 0], np.asarray(field.v) - truth[:, 1])


def part_defaults(args, seq, frames, roi) -> dict:
    from dic.sequence import track_sequence
    from dic.store import read_results

    out = {}
    for name, options in (("defaults", {}), ("no check", {"verify_composed": False}),
                          ("threshold alone", {"verify_spread": "off"})):
        path = os.path.join(args.tmp, f"verify_{name.replace(' ', '_')}.h5")
        t0 = time.perf_counter()
        s = track_sequence(frames[0], frames[1:], path, reference="auto", roi=roi, subset=21, step=10,
                           device=args.device, mode="overwrite", **options)
        wall = time.perf_counter() - t0
        res = read_results(path)
        per_frame = []
        for k in sorted(res.frames):
            f = res.frames[k]
            valid = np.asarray(f.valid, bool)
            err = _errors(seq, f, k)[valid]
            per_frame.append({"frame": int(k), "reference_index": int(f.attrs["reference_index"]),
                              "valid": float(valid.mean()),
                              "rms_px": float(np.sqrt(np.mean(err ** 2))) if err.size else None,
                              "refused": int(f.attrs.get("composed_mismatch", 0))})
        out[name] = {"options": {k: str(v) for k, v in options.items()}, "wall_s": wall,
                     "refused_total": int(s.n_mismatch.sum()), "last": per_frame[-1],
                     "lowest_valid": min(p["valid"] for p in per_frame), "per_frame": per_frame}
        print(name, out[name]["last"], "lowest valid", out[name]["lowest_valid"], flush=True)
    return out


def part_rule(args, seq, frames, roi) -> dict:
    from dic.store import read_results
    from kernels.verify import CHECKED, PEAK_PROBES, ComposedCheck, shifted_params

    path = os.path.join(args.tmp, "verify_no_check.h5")
    if not os.path.exists(path):
        raise SystemExit("the rule part reads the defaults part's run without the check: run --parts defaults,rule")
    res = read_results(path)
    points = np.asarray(res.frames[1].points, np.float64)
    check = ComposedCheck(frames[0], points, 21, device=args.device)
    rows = []
    for k in sorted(res.frames):
        f = res.frames[k]
        if int(f.attrs["reference_index"]) == 0:
            continue
        params = np.asarray(f.params, np.float64)
        valid = np.asarray(f.valid, bool)
        frame = check.coefficients(frames[k])
        z, outcome = check.zncc(frame, params, valid)
        ok = outcome == CHECKED
        good = ok & (_errors(seq, f, k) < 0.25)
        wrong = shifted_params(params, 1.0, 0.0)
        zw, _ = check.zncc(frame, wrong, valid)
        median = float(np.median(z[ok]))
        spread = MAD_TO_STD * float(np.median(np.abs(z[ok] - median)))

        def best(p):
            return np.nanmax(np.stack([check.zncc(frame, shifted_params(p, du, dv), valid)[0]
                                       for du, dv in PEAK_PROBES]), axis=0)

        gap, gap_wrong = best(params) - z, best(wrong) - zw
        row = {"frame": int(k), "median": median, "spread": spread, "correct": int(good.sum()),
               "correct_below_0.95": float(np.mean(z[good] < 0.95))}
        for n_spreads in (3, 4, 5):
            limit = min(0.95, median - n_spreads * spread)
            row[f"correct_below_median-{n_spreads}"] = int(np.sum(z[good] < limit))
            row[f"wrong_below_median-{n_spreads}"] = float(np.mean(zw[ok] < limit))
        for name, margin in (("0", 0.0), ("0.2(1-median)", 0.2 * (1 - median))):
            row[f"peak_correct_flagged@{name}"] = float(np.mean(gap[good] > margin))
            row[f"peak_wrong_flagged@{name}"] = float(np.mean(gap_wrong[ok] > margin))
        rows.append(row)
        print(row, flush=True)
    return {"per_frame": rows}


def part_inject(args, seq, frames, roi) -> dict:
    from dic._track import Tracker
    from dic.sequence import track_sequence
    from dic.store import read_results
    from kernels.conventions import Status

    mismatch = int(Status.COMPOSED_MISMATCH)
    out = {}
    for k_wrong in args.inject:
        block = {}

        def make_tracker(image, points, k_wrong=k_wrong, block=block):
            tracker = Tracker(image, roi=roi, device=args.device) if points is None else \
                Tracker(image, points=points, device=args.device)
            track = tracker.track

            def corrupted(current, **kw):
                field = track(current, **kw)
                c = np.asarray(current)
                if np.array_equal(c[100:110, 100:110], np.asarray(frames[k_wrong], c.dtype)[100:110, 100:110]):
                    xs, ys = np.unique(field.points[:, 0]), np.unique(field.points[:, 1])
                    cols = xs[len(xs) // 2 - 2:len(xs) // 2 + 2]
                    rows = ys[len(ys) // 2 - 2:len(ys) // 2 + 2]
                    j = np.flatnonzero(np.isin(field.points[:, 0], cols) & np.isin(field.points[:, 1], rows))
                    block["j"] = j
                    field.u[j] += 1.0
                    field.params[j, 0] += 1.0
                return field

            tracker.track = corrupted
            return tracker

        path = os.path.join(args.tmp, f"verify_inject_{k_wrong}.h5")
        end = min(args.frames, 2 * k_wrong + 1)
        track_sequence(frames[0], frames[1:end], path, reference=f"every:{k_wrong}", make_tracker=make_tracker,
                       points=None, order=1, mode="overwrite", roi=roi)
        res = read_results(path)
        rows = []
        for k in range(k_wrong + 1, end):
            f = res.frames[k]
            err = _errors(seq, f, k)
            flagged = f.status == mismatch
            reported = f.valid | flagged
            wrong, good = reported & (err > 0.75), reported & (err < 0.05)
            rows.append({"frame": k, "wrong": int(wrong.sum()), "wrong_flagged": int((wrong & flagged).sum()),
                         "correct": int(good.sum()), "correct_flagged": int((good & flagged).sum()),
                         "valid": float(f.valid.mean())})
            print(k_wrong, rows[-1], flush=True)
        out[str(k_wrong)] = rows
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--parts", default="defaults,rule,inject")
    parser.add_argument("--inject", default="5,10", help="the frames K of the wrong match (every:K)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--tmp", default=None, help="folder of the result files (default: a temporary one)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    args.inject = [int(k) for k in args.inject.split(",") if k]
    parts = [p for p in args.parts.split(",") if p]
    tmp = tempfile.TemporaryDirectory() if args.tmp is None else None
    args.tmp = args.tmp or tmp.name
    seq, frames, roi = _sequence(args)
    result = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "cpu": cpu_model(),
              "device": args.device, "size": args.size, "frames": args.frames, "stretch": STRETCH,
              "fade_fraction": 0.02, "noise_gl": 1.0, "seed": SEED, "roi": roi, "subset": 21, "step": 10,
              "load_before": os.getloadavg()}
    for name, part in (("defaults", part_defaults), ("rule", part_rule), ("inject", part_inject)):
        if name in parts:
            result[name] = part(args, seq, frames, roi)
    result["load_after"] = os.getloadavg()
    out = args.out or os.path.join(RESULTS, f"verify_composed_{args.device}.json")
    write_json(result, out)
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
