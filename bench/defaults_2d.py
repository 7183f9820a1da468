"""2-D defaults by measurement: shape-function order and subset size against exact truth.

Run from the repository root::

    .venv/bin/python -m bench.defaults_2d [--size 512] [--noise 2] [--out FILE]

Images: dic.synth.speckle_pair (Boolean speckle, 2 px disk radius, 8-bit, ``--noise`` grey levels of
Gaussian noise on each image, 4 samples per pixel), ``--size`` px square. Fields (px, at reference
coordinates, c = the image centre):

* ``uniform``: u = 0.005 (x - c) + 0.3, v = -0.002 (y - c) - 0.2 (a homogeneous stretch);
* ``waves``: u = 1.0 sin(2 pi y / 128), v = 0.5 sin(2 pi x / 200) (shear waves of 128 and 200 px);
* ``bump``: u = v = 0.8 exp(-r^2 / (2 40^2)) with r the distance to c (a local strain
  concentration of about 1.2 %, what a hole or notch gives).

For each (order, subset) at step 8 px: RMS of the displacement error (px) and of the exx = du/dx
error (from dic.strain, window 5, against the analytic gradient) over the valid points, the valid
fraction, and the tracking CPU time per 1000 POIs. Writes bench/results/defaults_2d.json.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import time
from datetime import datetime, timezone

import numpy as np

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
SETTINGS = ((1, 21), (1, 31), (2, 21), (2, 31), (2, 41))


def _fields(c):
    two_pi = 2.0 * np.pi
    return {
        "uniform": (lambda x, y: (0.005 * (x - c) + 0.3, -0.002 * (y - c) - 0.2),
                    lambda x, y: 0.005 + 0.0 * x),
        "waves": (lambda x, y: (1.0 * np.sin(two_pi * y / 128.0), 0.5 * np.sin(two_pi * x / 200.0)),
                  lambda x, y: 0.0 * x),
        "bump": (lambda x, y: (0.8 * np.exp(-((x - c) ** 2 + (y - c) ** 2) / (2 * 40.0 ** 2)),) * 2,
                 lambda x, y: -0.8 * (x - c) / 40.0 ** 2 * np.exp(-((x - c) ** 2 + (y - c) ** 2) / (2 * 40.0 ** 2))),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--noise", type=float, default=2.0, help="grey levels")
    parser.add_argument("--step", type=int, default=8)
    parser.add_argument("--out", default=os.path.join(RESULTS, "defaults_2d.json"))
    args = parser.parse_args(argv)

    from dic import strain, track
    from dic.synth import speckle_pair

    c = args.size / 2.0
    rows = []
    for name, (disp, dudx) in _fields(c).items():
        ref, cur = speckle_pair((args.size, args.size), disp, noise_sigma=args.noise, seed=7)
        for order, subset in SETTINGS:
            t0 = time.process_time()
            f = track(ref, cur, step=args.step, subset=subset, order=order, device="cpu")
            cpu = time.process_time() - t0
            ok = f.valid
            x, y = f.points[ok, 0], f.points[ok, 1]
            u_true, v_true = disp(x, y)
            err = np.hypot(f.u[ok] - u_true, f.v[ok] - v_true)
            s = strain(f, window=5)
            good = ok & np.isfinite(s.exx)
            e_err = s.exx[good] - dudx(f.points[good, 0], f.points[good, 1])
            row = {"field": name, "order": order, "subset": subset, "points": len(f.u), "valid": int(ok.sum()),
                   "rms_disp_px": float(np.sqrt(np.mean(err ** 2))),
                   "rms_exx": float(np.sqrt(np.mean(e_err ** 2))),
                   "cpu_s_per_kpoi": 1e3 * cpu / len(f.u)}
            rows.append(row)
            print(f"{name:8s} order {order} subset {subset}: valid {row['valid']:5d}/{row['points']:5d}  "
                  f"disp {row['rms_disp_px']:.4f} px  exx {row['rms_exx'] * 1e6:7.0f} ue  "
                  f"CPU {row['cpu_s_per_kpoi']:.3f} s/kPOI", flush=True)
    out = {"benchmark": "defaults_2d", "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
           "machine": platform.processor() or platform.machine(), "size_px": args.size, "noise_grey": args.noise,
           "step": args.step, "rows": rows}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(out, fh, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
