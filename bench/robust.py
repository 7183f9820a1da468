"""Adaptive robust IC-GN (issue 26, item 3): where it engages, what it costs, what it gains.

Run from the repository root::

    .venv/bin/python -m bench.robust                      # every part (about 10 min on 2 shared cores)
    .venv/bin/python -m bench.robust --parts clean --size 256
    .venv/bin/python -m bench.robust --parts evolving --frames 60 --size 512

Three ``robust`` values of :class:`dic.Tracker` / :func:`dic.sequence.track_sequence` are compared:
``False`` (plain IC-GN), ``"adaptive"`` (the 2-D default: Tukey-weighted IC-GN only for the subsets whose
plain residuals show a compact blob of outliers, :meth:`dic.correlation.engine.Correlator.refine_robust`) and ``True`` (every accepted
subset refined). Conditions: 8-bit Boolean speckle from :mod:`dic.synth` (mean radius 2 px, density
0.5, blur 0.7 px) with exact ground truth, 21 px subsets, step ``--step`` (default 10 px), CPU.

* **clean**: :func:`dic.synth.speckle_pair` of ``--size`` px under a smooth field
  (``u = 0.3 + 0.005 (x - c) + 2e-5 (y - c)^2``, ``v = -0.2 + 0.004 (y - c)`` px), Gaussian noise
  0.5, 1, 2 and 4 grey levels (its own noise stream per image), orders 1 and 2. Per case: the std of
  the error of u and v of the valid points (pooled), for each robust value, the ratio to plain, the
  fraction of the subsets the adaptive test flags, and, for the comparison of the statistics, the
  fraction flagged by the MAD rule (more than 2 % of the pixels beyond 3 MAD-scales).
* **evolving**: :func:`dic.synth.evolving_sequence` of ``--size`` px, ``--frames`` (60) frames, a stretch
  along x growing to ``--stretch`` (30 %), ``--fade`` (2 %) of the speckles replaced every frame, 1
  grey level of noise, ``reference="auto"`` (the POIs whose subsets stay in the image to the last
  frame). Per robust value: the final and worst RMS error of the valid points against the exact
  Lagrangian displacement, the final valid fraction, the refined points per frame, the wall time;
  also adaptive without the neighbour-outlier check (``check_outliers=False``; on by default unless
  ``robust`` is False).
* **renders**: stereo (``StereoCorrelation``, orders 2 and 1) on the virtual-lab renders of
  tests/dic/test_stereo_dic.py (no added noise, a rigid translation): the std of the 3-D displacement error
  per robust value (why stereo stays plain by default).
* **renders2d**: 2-D ``Tracker.track`` of the 1024^2 left renders of ``python -m bench.stereo rates`` (states 0 and
  1, 2 samples per pixel, 8-bit, no sensor noise; rendered into ``--cache`` once), step 8, orders 1 and 2: the
  subsets the default (adaptive) refines, the POIs whose result differs from plain, the process CPU time per frame
  (plain, default, default without the neighbour check).
* **candidates**: the per-subset statistics of the adaptive test (RMS gate, noise ratio, kurtosis, box statistic)
  on evolving pairs (frame k against k - 1 .. k - 3), the rate renders and the clean pairs, and per rule of
  ``CANDIDATE_RULES`` the flagged fraction and, on the evolving pairs, the RMS error with robust IC-GN's result
  where flagged (docs/dic2d.md, "Which statistic").
* **speed**: ``Tracker.track`` of one clean frame (noise 1 GL, ``--size`` px, previous result as the
  guess), median of ``--repeats`` calls, plain against adaptive (the cost of the residual test).

Writes bench/results/robust_<device>.json (``--out`` to write elsewhere); the machine's load
(``os.getloadavg``) is recorded before and after each part.
"""
from __future__ import annotations

import argparse
import os
import time
from datetime import datetime, timezone

import numpy as np

from bench._host import cpu_model, write_json

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
SEED = 2026
ROBUST_VALUES = {"plain": False, "adaptive": "adaptive", "on": True}
#: the evolving part's variants: the robust values (with their default ``check_outliers``: on unless robust is
#: False), and adaptive without the neighbour-outlier check
EVOLVING_VARIANTS = {"plain": {"robust": False}, "adaptive": {"robust": "adaptive"}, "on": {"robust": True},
                     "adaptive-no-check": {"robust": "adaptive", "check_outliers": False}}
#: the rules of the candidates part: name -> flagged from the per-subset statistics (``gate``: plain RMS residual over
#: the subset's std, ``noise``: over sqrt(2) x the reference's roughness, ``kurt``: kurtosis, ``box``: box statistic)
CANDIDATE_RULES = {
    "kurtosis > 4 (before)": lambda s: (s["gate"] > 0.05) & (s["kurt"] > 4),
    "kurtosis > 6": lambda s: (s["gate"] > 0.05) & (s["kurt"] > 6),
    "kurtosis > 8": lambda s: (s["gate"] > 0.05) & (s["kurt"] > 8),
    "kurtosis > 10": lambda s: (s["gate"] > 0.05) & (s["kurt"] > 10),
    "box > 5": lambda s: (s["gate"] > 0.05) & (s["kurt"] > 4) & (s["box"] > 5),
    "box > 6": lambda s: (s["gate"] > 0.05) & (s["kurt"] > 4) & (s["box"] > 6),
    "box > 7": lambda s: (s["gate"] > 0.05) & (s["kurt"] > 4) & (s["box"] > 7),
    "noise gate 0.8 (pass)": lambda s: (s["gate"] > 0.05) & (s["noise"] > 0.8),
    "noise gate 0.8 + kurtosis > 4": lambda s: (s["gate"] > 0.05) & (s["noise"] > 0.8) & (s["kurt"] > 4),
    "noise gate 0.8 + box > 6 (default)": lambda s: (s["gate"] > 0.05) & (s["noise"] > 0.8) & (s["kurt"] > 4)
    & (s["box"] > 6),
    "noise gate 1.0 + box > 6": lambda s: (s["gate"] > 0.05) & (s["noise"] > 1.0) & (s["kurt"] > 4) & (s["box"] > 6),
}
#: the MAD rule of the comparison: a subset is flagged when more than this fraction of its pixels lies
#: beyond CORE_A (3) MAD-scales
BEYOND_MAX = 0.02


def clean_field(size: int):
    c = (size - 1) / 2.0

    def field(x, y):
        return 0.3 + 0.005 * (x - c) + 2e-5 * (y - c) ** 2, -0.2 + 0.004 * (y - c) + 0.0 * x

    return field


def part_clean(args) -> dict:
    import dic
    from dic.synth import speckle_pair
    from kernels.icgn import prepare_current
    from kernels.icgn_robust import residual_outliers

    field = clean_field(args.size)
    rows = []
    for noise in args.noise:
        ref, cur = speckle_pair((args.size, args.size), field, noise_sigma=noise, seed=SEED)
        for order in (1, 2):
            row = {"noise_sigma": noise, "order": order}
            for name, robust in ROBUST_VALUES.items():
                tr = dic.Tracker(ref, step=args.step, subset=21, order=order, robust=robust, device=args.device)
                f = tr.track(cur, guess=(0.3, -0.2))
                u_true, v_true = field(f.points[:, 0], f.points[:, 1])
                ok = f.valid
                err = np.concatenate([(f.u - u_true)[ok], (f.v - v_true)[ok]])
                row[name] = {"std_px": float(np.std(err)), "rms_px": float(np.sqrt(np.mean(err ** 2))),
                             "valid": int(ok.sum()), "n_points": f.n_points,
                             "refined": f.extra.get("robust_refined")}
                if name == "plain":  # the two statistics on the plain result
                    stats = residual_outliers(tr.correlator.subsets, prepare_current(cur, device=args.device),
                                              f.params.astype(np.float32), ok, beyond_max=BEYOND_MAX, box_max=None)
                    kurt = residual_outliers(tr.correlator.subsets, prepare_current(cur, device=args.device),
                                             f.params.astype(np.float32), ok, box_max=None)
                    row["flagged_kurtosis"] = float(kurt.flagged[ok].mean())
                    row["flagged_kurtosis_or_mad"] = float(stats.flagged[ok].mean())
                    row["flagged_mad_only"] = float((stats.beyond[ok] > BEYOND_MAX).mean())
                    row["kurtosis_percentiles_50_90_99"] = np.percentile(kurt.kurtosis[ok], [50, 90, 99]).tolist()
            row["adaptive_std_ratio"] = row["adaptive"]["std_px"] / row["plain"]["std_px"]
            row["on_std_ratio"] = row["on"]["std_px"] / row["plain"]["std_px"]
            rows.append(row)
            print(f"clean noise {noise} order {order}: std plain {row['plain']['std_px']:.5f} adaptive "
                  f"{row['adaptive']['std_px']:.5f} ({row['adaptive_std_ratio']:.3f}) on {row['on']['std_px']:.5f} "
                  f"({row['on_std_ratio']:.3f}); flagged kurtosis {row['flagged_kurtosis']:.3f} "
                  f"MAD {row['flagged_mad_only']:.3f}", flush=True)
    return {"size": args.size, "step": args.step, "subset": 21, "guess": [0.3, -0.2],
            "target": "adaptive std within 5 % of plain", "cases": rows}


def part_evolving(args) -> dict:
    from dic.sequence import track_sequence
    from dic.store import ResultReader
    from dic.synth import evolving_sequence

    size = args.size
    seq = evolving_sequence((size, size), args.frames, stretch_final=args.stretch, fade_fraction=args.fade,
                            noise_sigma=1.0, seed=SEED + 1, device=args.device)
    frames = [seq[k] for k in range(args.frames)]
    half = 21 // 2 + 2
    cx, _ = seq.centre
    hx = ((size - 1) / 2 - half) / (1.0 + args.stretch)
    roi = (int(np.ceil(cx - hx)), half, int(np.floor(cx + hx)), size - 1 - half)
    out_dir = args.tmp
    modes = {}
    for name, options in EVOLVING_VARIANTS.items():
        if name not in args.robust:
            continue
        out = os.path.join(out_dir, f"robust_bench_{name}.h5")
        t0 = time.perf_counter()
        # verify_composed off: against frame 0 the replaced speckles fail the composed-result check by design
        # (with it on, the valid fraction falls to nothing within 20 frames, robust or not)
        track_sequence(frames[0], frames[1:], out, reference="auto", subset=21, step=args.step, roi=roi,
                       device=args.device, mode="overwrite", verify_composed=False, **options)
        wall = time.perf_counter() - t0
        per_frame = []
        with ResultReader(out) as reader:
            for index in reader.done_frames():
                fr = reader.read_frame(index)
                k = index  # track_sequence numbers the frames 1, 2, ... (the reference is 0)
                truth = seq.displacement(np.asarray(fr.points, np.float64), k)
                valid = np.asarray(fr.valid, bool)
                err = np.hypot(np.asarray(fr.u) - truth[:, 0], np.asarray(fr.v) - truth[:, 1])[valid]
                per_frame.append({"frame": int(k), "valid_fraction": float(valid.mean()),
                                  "rms_error_px": float(np.sqrt(np.mean(err ** 2))) if err.size else None,
                                  "robust_refined": fr.attrs.get("robust_refined"),
                                  "reference_index": fr.attrs.get("reference_index")})
        os.remove(out)
        last = per_frame[-1]
        modes[name] = {"seconds": wall, "final_rms_error_px": last["rms_error_px"],
                       "final_valid_fraction": last["valid_fraction"],
                       "max_rms_error_px": max(f["rms_error_px"] for f in per_frame if f["rms_error_px"] is not None),
                       "mean_refined_per_frame": float(np.mean([f["robust_refined"] or 0 for f in per_frame])),
                       "reference_updates": len({f["reference_index"] for f in per_frame}) - 1,
                       "per_frame": per_frame}
        print(f"evolving {name}: final rms {last['rms_error_px']:.4f} px valid {last['valid_fraction']:.3f} "
              f"max rms {modes[name]['max_rms_error_px']:.4f} refined/frame {modes[name]['mean_refined_per_frame']:.0f}"
              f" ({wall:.0f} s)", flush=True)
    return {"size": size, "frames": args.frames, "stretch_final": args.stretch, "fade_fraction": args.fade,
            "noise_sigma": 1.0, "reference": "auto", "verify_composed": False, "step": args.step, "subset": 21,
            "roi": list(roi),
            "target": {"adaptive final_rms_error_px": 0.05}, "modes": modes}


def part_speed(args) -> dict:
    import dic
    from dic.synth import speckle_pair

    field = clean_field(args.size)
    ref, cur = speckle_pair((args.size, args.size), field, noise_sigma=1.0, seed=SEED)
    cur = cur.astype(np.float32)
    out = {}
    trackers = {name: dic.Tracker(ref, step=args.step, subset=21, robust=ROBUST_VALUES[name], device=args.device)
                for name in ("plain", "adaptive")}
    first = {name: tr.track(cur, guess=(0.3, -0.2)) for name, tr in trackers.items()}  # compiles, and the guess
    times = {name: [] for name in trackers}
    for _ in range(args.repeats):  # interleaved: the machine's load moves both alike
        for name, tr in trackers.items():
            t0 = time.perf_counter()
            tr.track(cur, guess=first[name])
            times[name].append(time.perf_counter() - t0)
    for name in trackers:
        out[name] = {"median_s": float(np.median(times[name])), "min_s": float(np.min(times[name])),
                     "n_points": trackers[name].n_points}
    out["adaptive_over_plain_median"] = out["adaptive"]["median_s"] / out["plain"]["median_s"]
    out["adaptive_over_plain_min"] = out["adaptive"]["min_s"] / out["plain"]["min_s"]
    print(f"speed: plain {out['plain']['median_s'] * 1e3:.1f} ms adaptive {out['adaptive']['median_s'] * 1e3:.1f} ms "
          f"(x{out['adaptive_over_plain_median']:.3f} median, x{out['adaptive_over_plain_min']:.3f} min; "
          f"{out['plain']['n_points']} POIs)", flush=True)
    return {"size": args.size, "step": args.step, "subset": 21, "order": 1, "noise_sigma": 1.0,
            "repeats": args.repeats, **out}


def part_renders(args) -> dict:
    """Stereo on the virtual-lab renders of tests/dic/test_stereo_dic.py (its ``lab`` fixture: 320 x 240, 16
    samples per pixel, no added noise, a rigid translation): std of the 3-D displacement error per robust value."""
    import sys

    sys.path.insert(0, os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "tests", "dic"))
    import test_stereo_dic as rig_test

    from dic._stereo import StereoCorrelation

    lab = rig_test.lab.__wrapped__()
    (l0, r0), (l1, r1), _ = lab["states"]
    true = lab["R_left_world"] @ rig_test.TRANSLATION_WORLD
    rows = []
    for order in (2, 1):
        row = {"order": order}
        for name, robust in ROBUST_VALUES.items():
            sc = StereoCorrelation(lab["rig"], l0, r0, step=10, subset=21, order=order, robust=robust,
                                   device=args.device)
            f = sc.measure(l1, r1, index=1)
            row[name] = {"std_xyz_mm": (f.uvw[f.valid] - true).std(axis=0).tolist(), "valid": int(f.valid.sum())}
        row["adaptive_std_ratio"] = (np.array(row["adaptive"]["std_xyz_mm"]) / row["plain"]["std_xyz_mm"]).tolist()
        print(f"renders order {order}: std plain {np.round(row['plain']['std_xyz_mm'], 4)} adaptive "
              f"{np.round(row['adaptive']['std_xyz_mm'], 4)} on {np.round(row['on']['std_xyz_mm'], 4)}", flush=True)
        rows.append(row)
    return {"scene": "tests/dic/test_stereo_dic.py lab: 320 x 240 px, 16 samples per pixel, translation (1, -0.5, 2) mm",
            "step": 10, "subset": 21, "cases": rows}


def _rate_renders(cache: str):
    """The 1024^2 virtual-lab left images of state 0 and 1 of ``python -m bench.stereo rates`` (2 samples per pixel,
    8-bit, no sensor noise; rendered into ``cache`` once) and the specimen box."""
    from bench.stereo import RATE_SIZE, _lab_pairs

    _, pairs, _, box = _lab_pairs(RATE_SIZE, 2, (500.0, 450.0), cache, 2, "rate")
    return pairs[0][0], pairs[1][0], box


def part_renders2d(args) -> dict:
    """2-D ``Tracker.track`` of the rate renders (state 1 against state 0, step 8), plain against the default
    (adaptive): the subsets refined, the POIs whose result differs from plain, and the process CPU time per frame
    (median of ``--repeats`` calls, interleaved, the previous result as the guess)."""
    import dic

    ref, cur, box = _rate_renders(args.cache)
    rows = []
    for order in (1, 2):
        trackers = {"plain": dic.Tracker(ref, step=8, subset=21, order=order, robust=False, roi=box, device=args.device),
                    "default": dic.Tracker(ref, step=8, subset=21, order=order, roi=box, device=args.device),
                    # the adaptive refinement alone, without the neighbour check that comes with it by default
                    "default-no-check": dic.Tracker(ref, step=8, subset=21, order=order, roi=box, check_outliers=False,
                                                    device=args.device)}
        first = {name: tr.track(cur) for name, tr in trackers.items()}
        cpu = {name: [] for name in trackers}
        for _ in range(args.repeats):
            for name, tr in trackers.items():
                t0 = time.process_time()
                tr.track(cur, guess=first[name])
                cpu[name].append(time.process_time() - t0)
        p, d = first["plain"], first["default"]
        same = np.all((p.params == d.params) | (np.isnan(p.params) & np.isnan(d.params)), axis=1)
        row = {"order": order, "n_points": p.n_points, "valid_plain": int(p.valid.sum()),
               "valid_default": int(d.valid.sum()), "refined": d.extra.get("robust_refined"),
               "params_differ": int(np.count_nonzero(~same)),
               "neighbour_outliers": int(np.count_nonzero(d.status == 8)),
               "cpu_s_plain": float(np.median(cpu["plain"])), "cpu_s_default": float(np.median(cpu["default"])),
               "cpu_s_default_no_check": float(np.median(cpu["default-no-check"]))}
        row["cpu_ratio"] = row["cpu_s_default"] / row["cpu_s_plain"]
        row["cpu_ratio_no_check"] = row["cpu_s_default_no_check"] / row["cpu_s_plain"]
        both = p.valid & d.valid
        row["std_ratio_u_v"] = [float(np.std(d.u[both]) / np.std(p.u[both])), float(np.std(d.v[both]) / np.std(p.v[both]))]
        print(f"renders2d order {order}: refined {row['refined']} of {row['n_points']}, differ {row['params_differ']}, "
              f"cpu {row['cpu_s_plain']:.3f} -> {row['cpu_s_default']:.3f} s (x{row['cpu_ratio']:.3f}; without the neighbour "
              f"check x{row['cpu_ratio_no_check']:.3f})", flush=True)
        rows.append(row)
    return {"images": "bench.stereo rates: 1024^2 left images of states 0 and 1, 2 samples per pixel, 8-bit",
            "step": 8, "subset": 21, "repeats": args.repeats, "box": list(box), "cases": rows}


def _candidate_stats(ref, cur, order, step, roi, guess, device, truth=None):
    """Per-subset statistics of the plain result (every rule of CANDIDATE_RULES evaluated from them) and, with
    ``truth`` ((N, 2) px), the errors of plain and robust=True."""
    import dic
    from kernels.icgn import prepare_current
    from kernels.icgn_robust import reference_noise, residual_outliers

    out = {}
    for robust in (False, True):
        tr = dic.Tracker(ref, step=step, subset=21, order=order, robust=robust, roi=roi, check_outliers=False,
                         device=device)
        f = tr.track(cur, guess=guess) if guess is not None else tr.track(cur)
        out[robust] = f
        if robust is False:
            ok = f.valid
            # the box pass on every subset with a kurtosis above 1e-6 (all): the statistic itself, not the rule
            st = residual_outliers(tr.correlator.subsets, prepare_current(cur, device=device),
                                   f.params.astype(np.float32), ok, kurtosis_max=1e-6)
            sigma, std = reference_noise(ref, tr.correlator.subsets.table.centres.numpy(), 21)
            n = 21 * 21
            with np.errstate(invalid="ignore"):
                gate = np.sqrt(np.clip(1 - f.zncc ** 2, 0, None) * n / (n - 2))
                stats = {"gate": gate, "noise": gate * std / (np.sqrt(2) * sigma), "kurt": st.kurtosis, "box": st.box}
    p, r = out[False], out[True]
    res = {"ok": p.valid, "stats": stats}
    if truth is not None:
        t = truth(p.points)
        res["err_plain"] = np.hypot(p.u - t[:, 0], p.v - t[:, 1])
        res["err_robust"] = np.hypot(r.u - t[:, 0], r.v - t[:, 1])
        res["both"] = p.valid & r.valid
    return res


def part_candidates(args) -> dict:
    """The candidate statistics of the adaptive test, per subset, on the three kinds of images: pairs of the evolving
    texture (512^2, 2 % per frame, frame k against k - 1, k - 2 or k - 3: what reference="auto" correlates), the
    1024^2 rate renders (orders 1 and 2) and clean speckle pairs (0.5-4 GL, both orders). Per rule: the fraction of
    the valid subsets flagged and, on the evolving pairs, the RMS error when the flagged subsets take robust IC-GN's
    result and the others plain's."""
    from dic.synth import evolving_sequence, speckle_pair

    cases = {}
    seq = evolving_sequence((512, 512), 60, stretch_final=0.3, fade_fraction=0.02, noise_sigma=1.0, seed=SEED + 1,
                            device=args.device)
    for k0, k1 in ((0, 1), (0, 2), (20, 22), (40, 42), (56, 59)):
        s1, s0 = 0.3 * k1 / 59, 0.3 * k0 / 59
        hx = (255.5 - 12) / (1 + s1) * (1 + s0)
        roi = (int(np.ceil(255.5 - hx)), 12, int(np.floor(255.5 + hx)), 499)
        cases[f"evolving {k0}->{k1}"] = _candidate_stats(
            seq[k0], seq[k1], 1, 10, roi, None, args.device,
            truth=lambda pts, k0=k0, k1=k1: seq.displacement(np.asarray(pts, np.float64), k1, since=k0))
    ref, cur, box = _rate_renders(args.cache)
    for order in (1, 2):
        cases[f"render order {order}"] = _candidate_stats(ref, cur, order, 8, box, None, args.device)
    field = clean_field(512)
    for noise in args.noise:
        a, b = speckle_pair((512, 512), field, noise_sigma=noise, seed=SEED)
        for order in (1, 2):
            cases[f"clean {noise:g} GL order {order}"] = _candidate_stats(a, b, order, 10, None, (0.3, -0.2), args.device)
    table = {}
    for rule, fn in CANDIDATE_RULES.items():
        row = {}
        for name, c in cases.items():
            ok = c["ok"]
            with np.errstate(invalid="ignore"):
                flagged = fn(c["stats"]) & ok
            entry = {"flagged_fraction": float(flagged[ok].mean())}
            if "err_plain" in c:
                both = c["both"]
                err = np.where(flagged, c["err_robust"], c["err_plain"])[both]
                entry["rms_error_px"] = float(np.sqrt(np.mean(err ** 2)))
            row[name] = entry
        table[rule] = row
        print(f"{rule:38s} " + " ".join(f"{v['flagged_fraction']:.3f}" + (f"/{v['rms_error_px']:.4f}" if "rms_error_px" in v
                                                                            else "") for v in row.values()), flush=True)
    refs = {name: {"plain_rms_px": float(np.sqrt(np.mean(c["err_plain"][c["both"]] ** 2))),
                   "robust_rms_px": float(np.sqrt(np.mean(c["err_robust"][c["both"]] ** 2)))}
            for name, c in cases.items() if "err_plain" in c}
    pct = {name: {k: np.nanpercentile(v[c["ok"]], [10, 50, 90, 99]).tolist() for k, v in c["stats"].items()}
           for name, c in cases.items()}
    return {"cases": list(cases), "rules": table, "evolving_plain_and_robust": refs, "percentiles_10_50_90_99": pct}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--parts", default="clean,evolving,speed,renders,renders2d,candidates",
                        help="comma-separated: clean, evolving, speed, renders, renders2d, candidates")
    parser.add_argument("--size", type=int, default=512, help="image size (px, square)")
    parser.add_argument("--step", type=int, default=10, help="POI grid step (px)")
    parser.add_argument("--noise", default="0.5,1,2,4", help="noise levels of the clean part (grey levels)")
    parser.add_argument("--frames", type=int, default=60, help="evolving frames (reference included)")
    parser.add_argument("--stretch", type=float, default=0.30, help="stretch at the last evolving frame")
    parser.add_argument("--fade", type=float, default=0.02, help="fraction of the speckles replaced per frame")
    parser.add_argument("--robust", default=",".join(EVOLVING_VARIANTS),
                        help=f"variants of the evolving part ({', '.join(EVOLVING_VARIANTS)})")
    parser.add_argument("--repeats", type=int, default=15, help="timed calls per value (speed)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--tmp", default="/tmp", help="folder of the evolving part's result files")
    parser.add_argument("--cache", default=os.path.join(RESULTS, "..", ".cache"), help="rendered images (renders2d)")
    parser.add_argument("--out", default=None, help="JSON output (default bench/results/robust_<device>.json)")
    args = parser.parse_args(argv)
    args.parts = [p for p in args.parts.split(",") if p]
    args.noise = [float(x) for x in args.noise.split(",") if x]
    args.robust = [x for x in args.robust.split(",") if x]
    parts = {"clean": part_clean, "evolving": part_evolving, "speed": part_speed, "renders": part_renders,
             "renders2d": part_renders2d, "candidates": part_candidates}
    bad = [p for p in args.parts if p not in parts]
    if bad:
        parser.error(f"unknown part(s) {bad}; choose from {', '.join(parts)}")
    result = {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "device": args.device,
              "cpu": cpu_model(), "parts": {}}
    for part in args.parts:
        load_before = os.getloadavg()
        t0 = time.perf_counter()
        res = parts[part](args)
        res["load_before_after"] = [list(load_before), list(os.getloadavg())]
        res["seconds"] = time.perf_counter() - t0
        result["parts"][part] = res
    out = args.out or os.path.join(RESULTS, f"robust_{args.device.split(':')[0]}.json")
    write_json(result, out)
    return result


if __name__ == "__main__":
    main()
