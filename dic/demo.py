"""End-to-end demo on generated data: ``python -m dic.demo --out DIR`` (what ``make demo`` runs).

Steps (each a function, so later demos can add stages such as the stereo chain):

1. :func:`generate` - a Boolean-model speckle pair (Sur, Blaysat & Grédiac 2018) deformed by a
   known, non-uniform displacement: a uniform stretch plus a sinusoidal shear;
2. :func:`track_step` - 2-D DIC of the pair (IC-GN, 21 px subsets, 2nd-order shape function);
3. :func:`strain_step` - pointwise least-squares strain;
4. :func:`write_step` - the HDF5 result file, a figure (PNG) and a summary (Markdown and JSON)
   with the errors against the exact ground truth.

Everything is written into ``--out``; a short summary is printed.
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import sys
import time
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np


@dataclass
class DemoConfig:
    """Parameters of the demo (image size in px, displacement amplitudes in px, DIC settings)."""

    size: int = 512
    stretch: float = 0.004          #: uniform strain exx (and -0.4 x in eyy)
    amplitude_u: float = 1.5        #: amplitude of u = A sin(2 pi y / period), px
    amplitude_v: float = 0.8        #: amplitude of v = B sin(2 pi x / period), px
    period: float = 192.0           #: px
    offset: tuple[float, float] = (2.3, -1.7)  #: rigid translation, px
    subset: int = 21
    step: int = 4
    order: int = 2
    search: str | None = "pyramid"  #: initial-guess strategy (the motion reaches ~5 px)
    search_radius: int = 8          #: px
    strain_window: int = 7
    noise_sigma: float = 1.0        #: grey levels (8-bit)
    seed: int = 2019
    device: str | None = None


@dataclass
class DemoState:
    """What the steps pass along."""

    config: DemoConfig
    out: Path
    reference: np.ndarray | None = None
    current: np.ndarray | None = None
    field: object = None
    strain: object = None
    timings: dict = dataclasses.field(default_factory=dict)
    summary: dict = dataclasses.field(default_factory=dict)


# -- the known displacement and its derivatives (reference coordinates, px)
def displacement(cfg: DemoConfig):
    c = cfg.size / 2.0
    k = 2 * math.pi / cfg.period

    def u_v(x, y):
        u = cfg.offset[0] + cfg.stretch * (x - c) + cfg.amplitude_u * np.sin(k * (y - c))
        v = cfg.offset[1] - 0.4 * cfg.stretch * (y - c) + cfg.amplitude_v * np.sin(k * (x - c))
        return u, v

    def gradients(x, y):
        dudx = np.full_like(x, cfg.stretch)
        dudy = cfg.amplitude_u * k * np.cos(k * (y - c))
        dvdx = cfg.amplitude_v * k * np.cos(k * (x - c))
        dvdy = np.full_like(x, -0.4 * cfg.stretch)
        return dudx, dudy, dvdx, dvdy

    return u_v, gradients


def generate(state: DemoState) -> None:
    """Step 1: render the reference and the deformed image (8-bit, Gaussian noise)."""
    from dic.synth import speckle_pair

    cfg = state.config
    t0 = time.perf_counter()
    u_v, _ = displacement(cfg)
    state.reference, state.current = speckle_pair((cfg.size, cfg.size), u_v, noise_sigma=cfg.noise_sigma, bits=8,
                                                  seed=cfg.seed, device=cfg.device)
    state.timings["generate_s"] = time.perf_counter() - t0


def track_step(state: DemoState) -> None:
    """Step 2: 2-D DIC."""
    from dic.track import track

    cfg = state.config
    t0 = time.perf_counter()
    state.field = track(state.reference, state.current, step=cfg.step, subset=cfg.subset, order=cfg.order,
                        search=cfg.search, search_radius=cfg.search_radius, device=cfg.device)
    state.timings["track_s"] = time.perf_counter() - t0


def strain_step(state: DemoState) -> None:
    """Step 3: strain."""
    from dic.strain import strain

    t0 = time.perf_counter()
    state.strain = strain(state.field, window=state.config.strain_window)
    state.timings["strain_s"] = time.perf_counter() - t0


def _rms(a):
    a = np.asarray(a, dtype=np.float64)
    return float(np.sqrt(np.mean(a * a))) if a.size else float("nan")


def evaluate(state: DemoState) -> dict:
    """Errors against the ground truth at the valid points."""
    cfg = state.config
    u_v, grads = displacement(cfg)
    f, s = state.field, state.strain
    pts = np.asarray(f.points, dtype=np.float64)
    valid = np.asarray(f.valid, bool)
    u_true, v_true = u_v(pts[:, 0], pts[:, 1])
    eu = np.asarray(f.u, np.float64)[valid] - u_true[valid]
    ev = np.asarray(f.v, np.float64)[valid] - v_true[valid]
    g = grads(pts[:, 0], pts[:, 1])
    sv = s.valid
    exx_t, eyy_t, exy_t = g[0], g[3], 0.5 * (g[1] + g[2])
    return {
        "points": int(valid.size),
        "valid_points": int(valid.sum()),
        "u_rms_error_px": _rms(eu), "v_rms_error_px": _rms(ev),
        "u_mean_error_px": float(eu.mean()) if eu.size else float("nan"),
        "v_mean_error_px": float(ev.mean()) if ev.size else float("nan"),
        "max_displacement_px": float(np.max(np.hypot(u_true, v_true))),
        "strain_points": int(sv.sum()),
        "exx_rms_error": _rms(s.exx[sv] - exx_t[sv]),
        "eyy_rms_error": _rms(s.eyy[sv] - eyy_t[sv]),
        "exy_rms_error": _rms(s.exy[sv] - exy_t[sv]),
        "max_true_strain": float(np.max(np.abs(np.stack([exx_t, eyy_t, exy_t])))),
    }


def write_step(state: DemoState) -> None:
    """Step 4: images, HDF5 results, figure and summary."""
    from dic.figures import write_field_figure
    from dic.io import write_image
    from dic.store import ResultWriter, image_digest

    cfg, out = state.config, state.out
    out.mkdir(parents=True, exist_ok=True)
    write_image(out / "reference.tif", state.reference, bits=8)
    write_image(out / "current.tif", state.current, bits=8)
    settings = {"subset": cfg.subset, "step": cfg.step, "order": cfg.order, "strain_window": cfg.strain_window}
    with ResultWriter(out / "results.h5", reference_path="reference.tif", reference_shape=state.reference.shape,
                      reference_sha256=image_digest(state.reference), settings=settings, mode="overwrite") as w:
        w.write_frame(1, state.field, strain=state.strain, path="current.tif")
    write_field_figure(out / "displacement_strain.png", state.reference, state.field, state.strain,
                       title="Specula demo: synthetic speckle, stretch + sinusoidal shear")
    u_v, _ = displacement(cfg)
    pts = np.asarray(state.field.points, np.float64)
    u_true, v_true = u_v(pts[:, 0], pts[:, 1])
    error_field = SimpleNamespace(points=pts, u=np.asarray(state.field.u) - u_true,
                                  v=np.asarray(state.field.v) - v_true, valid=state.field.valid)
    write_field_figure(out / "displacement_error.png", state.reference, error_field, components=("u", "v"),
                       title="Measured minus true displacement (px)")
    errors = evaluate(state)
    state.summary = {
        "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in cfg.__dict__.items()},
        "errors": errors,
        "timings_s": {k: round(v, 3) for k, v in state.timings.items()},
        "python": platform.python_version(),
        "files": ["reference.tif", "current.tif", "results.h5", "displacement_strain.png", "displacement_error.png",
                  "summary.json", "summary.md"],
    }
    (out / "summary.json").write_text(json.dumps(state.summary, indent=2))
    e = errors
    lines = [
        "# Specula demo",
        "",
        f"A {cfg.size}x{cfg.size} px Boolean-model speckle pair (8-bit, {cfg.noise_sigma} grey level noise) deformed by "
        f"u = {cfg.offset[0]} + {cfg.stretch} (x - c) + {cfg.amplitude_u} sin(2 pi (y - c) / {cfg.period}), "
        f"v = {cfg.offset[1]} - {0.4 * cfg.stretch:g} (y - c) + {cfg.amplitude_v} sin(2 pi (x - c) / {cfg.period}) px, "
        f"tracked with {cfg.subset} px subsets every {cfg.step} px, shape function order {cfg.order}; strain from "
        f"{cfg.strain_window}x{cfg.strain_window}-point plane fits.",
        "",
        "| quantity | value |",
        "|---|---|",
        f"| valid points | {e['valid_points']} / {e['points']} |",
        f"| u RMS error (px) | {e['u_rms_error_px']:.4f} |",
        f"| v RMS error (px) | {e['v_rms_error_px']:.4f} |",
        f"| exx RMS error | {e['exx_rms_error']:.2e} |",
        f"| eyy RMS error | {e['eyy_rms_error']:.2e} |",
        f"| exy RMS error | {e['exy_rms_error']:.2e} |",
        f"| largest true strain | {e['max_true_strain']:.2e} |",
        "",
        "Timings (s): " + ", ".join(f"{k[:-2]} {v:.2f}" for k, v in state.timings.items()),
        "",
    ]
    (out / "summary.md").write_text("\n".join(lines))


STEPS = (generate, track_step, strain_step, write_step)


def run_demo(out, config: DemoConfig | None = None, *, echo=print) -> dict:
    """Run every step into folder ``out``; return the summary dictionary."""
    state = DemoState(config=config or DemoConfig(), out=Path(out))
    for step in STEPS:
        echo(f"[demo] {step.__doc__.splitlines()[0]}")
        step(state)
    e = state.summary["errors"]
    echo(f"[demo] {e['valid_points']}/{e['points']} points valid; RMS error u {e['u_rms_error_px']:.4f} px, "
         f"v {e['v_rms_error_px']:.4f} px; strain RMS error exx {e['exx_rms_error']:.1e}, "
         f"eyy {e['eyy_rms_error']:.1e}, exy {e['exy_rms_error']:.1e}")
    echo(f"[demo] wrote {', '.join(state.summary['files'])} to {state.out}")
    return state.summary


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m dic.demo", description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="demo_output", help="output folder (default: demo_output)")
    parser.add_argument("--size", type=int, default=DemoConfig.size, help="image side in px (default 512)")
    parser.add_argument("--step", type=int, default=DemoConfig.step, help="grid step in px (default 4)")
    parser.add_argument("--order", type=int, choices=(1, 2), default=DemoConfig.order)
    parser.add_argument("--device", default=None, help="Warp device (default: CUDA when present, else CPU)")
    args = parser.parse_args(argv)
    if args.size < 96:
        parser.error("--size must be at least 96 px")
    cfg = DemoConfig(size=args.size, step=args.step, order=args.order, device=args.device)
    run_demo(args.out, cfg)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
