"""Time and size of ``specula report`` (issue 25, "A run report"): ``dic.write_report`` of a 2-D result file of 11
frames on a grid of 240 x 307 points (73 680 points, step 4 px, like the 11-frame CFRP file of issue 25; the file of
:mod:`bench.animate`), quantity ``u``, default map width (640 px) and frame limit.

    python -m bench.report                  # writes bench/results/report_cpu.json

Reported per case: wall time (one run after a warm-up report that loads the imports and Matplotlib's font cache),
HTML size, and the load average (the machine is shared). Cases: maps without the reference image; with a
980 x 1250 uniform noise reference image; with the image, two point histories and one extensometer.
"""
from __future__ import annotations

import json
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.animate import build


def main() -> None:
    from dic.report import write_report

    image = np.random.default_rng(0).random((980, 1250))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        build(tmp / "run.h5")
        write_report(tmp / "run.h5", tmp / "warm.html", quantity="u")
        cases = [("maps", {}), ("maps over the image", {"image": image}),
                 ("image, 2 histories, 1 extensometer", {"image": image, "history": [(300, 300), (900, 600)],
                                                         "extensometer": [(100, 500, 1100, 500)]})]
        for name, kwargs in cases:
            t = time.perf_counter()
            out = write_report(tmp / "run.h5", tmp / "report.html", quantity="u", **kwargs)
            seconds = time.perf_counter() - t
            rows.append({"case": name, "seconds": round(seconds, 3), "html_bytes": out.stat().st_size,
                         "load_average_1min": os.getloadavg()[0]})
            print(f"{name:40s} {seconds:6.2f} s  {out.stat().st_size / 1e6:6.2f} MB  load {os.getloadavg()[0]:.2f}")
    result = {"frames": 11, "points": 73680, "quantity": "u", "machine": platform.processor() or platform.machine(),
              "cpus": os.cpu_count(), "rows": rows}
    dest = Path(__file__).parent / "results" / "report_cpu.json"
    dest.parent.mkdir(exist_ok=True)
    dest.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {dest}")


if __name__ == "__main__":
    main()
