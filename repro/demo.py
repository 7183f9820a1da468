"""End-to-end demo on generated data: ``python -m repro.demo --out DIR`` (what ``make demo`` runs).

Steps (each a function, so later demos can add stages such as the stereo chain):

1. :func:`generate` - a Boolean-model speckle pair (Sur, Blaysat & Grédiac 2018) deformed by a
   known, non-uniform displacement: a uniform stretch plus a sinusoidal shear;
2. :func:`track_step` - 2-D DIC of the pair (IC-GN, 21 px subsets, 2nd-order shape function);
3. :func:`strain_step` - pointwise least-squares strain;
4. :func:`write_step` - the HDF5 result file, a figure (PNG) and a summary (Markdown and JSON)
   with the errors against the exact ground truth.

Then the stereo chain on the virtual paper rig (``--only stereo``; both by default), at reduced
resolution (:mod:`repro.experiments`):

5. :func:`stereo_calibration_step` - render the phase-target calibration images (mirrored at three
   tilts, direct at several depths, one far view), calibrate intrinsics and mirror extrinsics (joint
   adjustment with the far view), write the rig file;
6. :func:`stereo_measure_step` - render a reference and a deformed speckle state on the monitor at
   the crossing point (x_d = x + A sin(2 pi f y), the paper's deformation test) and measure them in 3-D;
7. :func:`stereo_report_step` - figures, the reference images and a short Markdown report (``stereo/report.md``).

Everything is written into ``--out``; a short summary is printed.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from dic.lab.paper import BASELINE_MM, WORKING_DISTANCE_MM
from repro.experiments import DOT_SPACING_MM


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
    stereo_config: object = None
    experiment: object = None
    calibration: object = None
    dots: object = None
    deformation: object = None


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
    from dic._track import track

    cfg = state.config
    t0 = time.perf_counter()
    state.field = track(state.reference, state.current, step=cfg.step, subset=cfg.subset, order=cfg.order,
                        search=cfg.search, search_radius=cfg.search_radius, device=cfg.device)
    state.timings["track_s"] = time.perf_counter() - t0


def strain_step(state: DemoState) -> None:
    """Step 3: strain."""
    from dic._strain import strain

    t0 = time.perf_counter()
    # the small strain: what the demo's truth (exx = du/dx ...) and its report compare against (issue 25: named)
    state.strain = strain(state.field, window=state.config.strain_window, strain_type="small")
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
    from dic.io import write_image
    from dic.plots.fields import write_field_figure
    from dic.sequence.options import TrackOptions
    from dic.store import ResultWriter, image_digest

    cfg, out = state.config, state.out
    out.mkdir(parents=True, exist_ok=True)
    write_image(out / "reference.tif", state.reference, bits=8)
    write_image(out / "current.tif", state.current, bits=8)
    # the run record of the options track_step used (docs/results_format.md, "The run record")
    settings = TrackOptions(subset=cfg.subset, step=cfg.step, order=cfg.order, search=cfg.search,
                            search_radius=cfg.search_radius, strain_window=cfg.strain_window,
                            strain_type="small").to_settings()
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
    checks = _checks_2d(e)
    lines = [
        "# Specula demo",
        "",
        f"A {cfg.size}x{cfg.size} px Boolean-model speckle pair (8-bit, {cfg.noise_sigma} grey level noise) deformed by "
        f"u = {cfg.offset[0]} + {cfg.stretch} (x - c) + {cfg.amplitude_u} sin(2 pi (y - c) / {cfg.period}), "
        f"v = {cfg.offset[1]} - {0.4 * cfg.stretch:g} (y - c) + {cfg.amplitude_v} sin(2 pi (x - c) / {cfg.period}) px, "
        f"tracked with {cfg.subset} px subsets every {cfg.step} px, shape function order {cfg.order}; strain from "
        f"{cfg.strain_window}x{cfg.strain_window}-point plane fits.",
        "",
        "## Accuracy against the exact displacement",
        "",
        "Errors are measured minus exact at the valid points. The bounds are those of `tests/project/test_demo.py`: the noise "
        "floor of 21 px subsets at 1 grey level is about 0.002-0.003 px, so 0.015 px RMS leaves room for the sine's "
        "curvature and still catches a convention error (a sign or half-pixel slip gives >= 0.5 px); a 7-point plane "
        "fit over 36 px of the 192 px sine stays well below 5e-3 strain RMS (largest true strain "
        f"{e['max_true_strain']:.1e}).",
        "",
        "| quantity | measured | bound | |",
        "|---|---|---|---|",
        *(f"| {name} | {value} | {bound} | {'pass' if ok else '**FAIL**'} |" for name, value, bound, ok in checks),
        "",
        "## Figures",
        "",
        "Maps over the grey reference image (the map drawn with 75 % opacity), axes in image px. A quantity whose "
        "colour range spans zero is on a diverging map centred on zero (white = 0), a one-signed one on a sequential "
        "map over its own range; the limits are the 1st-99th percentiles of the drawn values.",
        "",
        "- `displacement_strain.png`: the measured u and v (px) and the small strains εxx, εyy, εxy. Expected: u "
        f"rising by {cfg.stretch * cfg.size:.1f} px from left to right plus a {cfg.amplitude_u} px sine along y about "
        f"{cfg.offset[0]} px; v a {cfg.amplitude_v} px sine along x about {cfg.offset[1]} px, falling by "
        f"{0.4 * cfg.stretch * cfg.size:.1f} px from top to bottom; εxx = {cfg.stretch} and εyy = {-0.4 * cfg.stretch:g} "
        "uniform, so their maps show only the noise about these values (read the colourbars: a narrow one-signed "
        "range, on the sequential map); εxy a checkerboard of the two sines (±0.02-0.04, diverging map).",
        "- `displacement_error.png`: measured minus true u and v (px), the error maps of the table above: noise "
        "without structure when the tracking is right (a pattern that follows the sine would be the subsets' "
        "smoothing of its curvature).",
        "",
        "Timings (s): " + ", ".join(f"{k[:-2]} {v:.2f}" for k, v in state.timings.items()),
        "",
    ]
    (out / "summary.md").write_text("\n".join(lines))


def _checks_2d(e: dict) -> list[tuple[str, str, str, bool]]:
    """(quantity, measured, bound, within the bound) of the 2-D demo's errors; the bounds of tests/project/test_demo.py."""
    rows = [("valid points", f"{e['valid_points']} / {e['points']}", "> 90 %", e["valid_points"] > 0.9 * e["points"])]
    for q in ("u", "v"):
        v = e[f"{q}_rms_error_px"]
        rows.append((f"{q} RMS error (px)", f"{v:.4f} (mean {e[f'{q}_mean_error_px']:+.4f})", "< 0.015", v < 0.015))
    for q in ("exx", "eyy", "exy"):
        v = e[f"{q}_rms_error"]
        rows.append((f"{q} RMS error", f"{v:.2e}", "< 5e-3", v < 5e-3))
    return rows


STEPS = (generate, track_step, strain_step, write_step)


# -- the stereo chain on the virtual paper rig ---------------------------------------------------
@dataclass
class StereoDemoConfig:
    """Reduced-resolution settings of the stereo demo (see repro.experiments.ExperimentConfig)."""

    scale: float = 0.25
    samples: int = 4
    direct_distances_mm: tuple = (1100.0, 1400.0, 1700.0, 2000.0, 2400.0, 2700.0)
    step: int = 3
    amplitude_px: float = 24.0           #: monitor px (the paper's A)
    frequency: float = 1.0 / 600.0       #: 1/monitor px (the paper's f)
    cache: str | None = None             #: render cache folder (None: no cache)
    device: str | None = None


def _resolution_note(exp, deformation: dict) -> str:
    """Why the demo's amplitude is below the imposed one: its quarter resolution, in numbers."""
    from dic.lab.paper import MONITOR_PITCH_MM, WORKING_DISTANCE_MM

    scale, subset, period_px = exp.cfg.scale, exp.cfg.subset, 1.0 / exp.cfg.deform_frequency
    focal_px = float(exp.lab.cameras[0].camera.fx)  # the lab camera at this scale
    monitor_px_per_camera_px = WORKING_DISTANCE_MM / focal_px / MONITOR_PITCH_MM
    span = subset * monitor_px_per_camera_px
    smoothing = 1.0 - deformation["fitted_amplitude_px"] / deformation["imposed_amplitude_px"]
    return (f"**Why the amplitude is {100 * smoothing:.1f} % low here:** the demo runs at {scale:g} of the paper's "
            f"resolution, where one camera pixel sees {monitor_px_per_camera_px:.1f} monitor pixels at "
            f"{WORKING_DISTANCE_MM / 1000:g} m, so a {subset} px subset spans about {span:.0f} of the {period_px:g} monitor "
            f"px period and averages the sine (the subset's warp cannot follow a curve that tight). At full resolution the "
            f"subset spans about {span * scale:.0f} monitor px and the same chain smooths the peak by 0.02 % "
            "(docs/paper_reproduction.md); at half resolution 0.4 %.")


def stereo_calibration_step(state: DemoState) -> None:
    """Step 5: render the calibration images of the paper rig and calibrate it (intrinsics, mirror extrinsics)."""
    from repro.experiments import Experiment, ExperimentConfig

    sc = state.stereo_config
    t0 = time.perf_counter()
    cfg = ExperimentConfig(scale=sc.scale, samples=sc.samples, direct_distances_mm=sc.direct_distances_mm,
                           far_view=True, checkerboard=False, positions=(13,), step=sc.step,
                           deform_amplitude_px=sc.amplitude_px, deform_frequency=sc.frequency, device=sc.device)
    state.experiment = Experiment(cfg, cache=sc.cache, log=lambda m: None)
    state.calibration = state.experiment.calibrate()
    out = state.out / "stereo"
    out.mkdir(parents=True, exist_ok=True)
    state.calibration.rig.save(out / "rig.json")
    state.timings["stereo_calibration_s"] = time.perf_counter() - t0


def stereo_measure_step(state: DemoState) -> None:
    """Step 6: render a reference and a sinusoidally deformed speckle state and measure them in 3-D."""
    from repro.experiments import _central_position, run_deformation_test

    t0 = time.perf_counter()
    exp = state.experiment
    p = _central_position(exp)
    state.dots = exp.dot_views(p)
    state.deformation = run_deformation_test(exp, state.calibration.rig, state.dots, log=lambda m: None)
    state.timings["stereo_measure_s"] = time.perf_counter() - t0


def stereo_report_step(state: DemoState) -> None:
    """Step 7: figures, the reference images and the stereo report (Markdown, JSON)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt
    from mpl_toolkits.axes_grid1 import make_axes_locatable

    from dic.io import write_image
    from dic.lab.paper import MONITOR_PITCH_MM
    from dic.plots._common import colour_scale
    from repro.experiments import dot_test

    exp, cal, de = state.experiment, state.calibration, state.deformation
    out = state.out / "stereo"
    out.mkdir(parents=True, exist_ok=True)
    p = de["position"]
    L0, R0 = exp.speckle_pair(p)
    write_image(out / "left_reference.tif", L0, bits=8)
    write_image(out / "right_reference.tif", R0, bits=8)
    dots = dot_test(cal.rig, *state.dots, exp.dot_target)
    m = de.pop("_map")
    fig, axs = plt.subplots(1, 3, figsize=(14, 4.0))
    for ax, key, title, bar in ((axs[0], "u_px", "measured u (monitor px)", "u (monitor px)"),
                                (axs[2], "residual_px", "u residual: measured - imposed (monitor px)",
                                 "u residual (monitor px)")):
        cmap, lo, hi = colour_scale(m[key], signed=True)  # diverging centred on 0 when the range spans zero
        s = ax.scatter(m["x_px"], m["y_px"], c=m[key], s=4, cmap=cmap, vmin=lo, vmax=hi)
        ax.invert_yaxis(); ax.set_aspect("equal", adjustable="box"); ax.set_title(title, fontsize=10)
        ax.set_xlabel("monitor x (px)"); ax.set_ylabel("monitor y (px)")
        cax = make_axes_locatable(ax).append_axes("right", size="4%", pad=0.08)  # as tall as the panel
        fig.colorbar(s, cax=cax, label=bar)
    y = np.linspace(m["y_px"].min(), m["y_px"].max(), 300)
    axs[1].plot(de["profile_y_px"], de["profile_u_px"], "o", ms=3, label="measured (row bins)")
    axs[1].plot(y, de["imposed_amplitude_px"] * np.sin(2 * np.pi * exp.cfg.deform_frequency * y), label="imposed")
    axs[1].set_title("u profile along the monitor rows (monitor px)", fontsize=10)
    axs[1].set_xlabel("monitor y (px)"); axs[1].set_ylabel("u (monitor px)"); axs[1].legend(fontsize=8)
    fig.tight_layout(); fig.savefig(out / "deformation.png", dpi=80); plt.close(fig)
    fig, axs = plt.subplots(1, 2, figsize=(9, 3.6))
    for ax, img, side in ((axs[0], L0, "left"), (axs[1], R0, "right")):
        ax.imshow(img, cmap="gray"); ax.set_title(f"{side} camera, reference state", fontsize=10)
        ax.set_xlabel(f"x, {side} image (px)"); ax.set_ylabel(f"y, {side} image (px)")
    fig.tight_layout(); fig.savefig(out / "views.png", dpi=80); plt.close(fig)
    f = cal.figures
    summary = {"calibration": f, "dot_check": {"mean_distance_mm": float(dots["distances_mm"].mean()),
                                                "std_mm": float(dots["distances_mm"].std(ddof=1)),
                                                "true_mm": DOT_SPACING_MM},
               "deformation": {k: v for k, v in de.items() if not k.startswith("profile")},
               "config": {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(exp.cfg).items()},
               "image_size": list(exp.size), "renders": exp.cache.renders, "render_s": round(exp.cache.render_s, 1),
               "files": ["rig.json", "left_reference.tif", "right_reference.tif", "deformation.png", "views.png",
                         "report.md", "summary.json"]}
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
    rp = f["reprojection_rms_px"]
    checks = _checks_stereo(f, summary["dot_check"], de, MONITOR_PITCH_MM)
    lines = [
        "# Specula demo: stereo DIC on the virtual paper rig",
        "",
        f"The paper's rig (docs/lab.md) at scale {exp.cfg.scale} ({exp.size[0]} x {exp.size[1]} px cameras, 8 bit, read "
        f"and shot noise, f/2.8 defocus), {exp.cfg.samples} samples per pixel. Calibrated from rendered images only: "
        f"a coded {exp.cfg.calib_grid[0]}x{exp.cfg.calib_grid[1]} phase-dot target seen through each camera's mirror at "
        f"3 tilts and directly at {len(exp.cfg.direct_distances_mm)} depths; intrinsics (Zhang, direct + mirrored views), "
        "mirror extrinsics (the paper's method + bundle adjustment), then a joint adjustment of both cameras' mirror "
        f"views with one far view of the target that both cameras see (at 4.6 m, not the test position). Then the monitor at the axes' crossing ({WORKING_DISTANCE_MM / 1000:g} m) "
        f"shows a speckle, then the same speckle deformed by x_d = x + {de['imposed_amplitude_px']:g} sin(2 pi y / "
        f"{1 / exp.cfg.deform_frequency:g}) (monitor px), measured by stereo DIC (subset {exp.cfg.subset} px, step "
        f"{exp.cfg.step} px, order {exp.cfg.order}). See docs/paper_reproduction.md for the full reproduction.",
        "",
        "## What was measured, and is it good?",
        "",
        "Each row says what the number is, what a correct chain gives (the truth the demo knows) and the bound it "
        "is checked against; the bounds are those of `tests/project/test_experiments.py` at this quarter resolution "
        "(1 monitor px = " f"{MONITOR_PITCH_MM:g} mm).",
        "",
        "| quantity | measured | expected | bound | |",
        "|---|---|---|---|---|",
        *(f"| {q} | {v} | {x} | {b} | {'' if ok is None else 'pass' if ok else '**FAIL**'} |" for q, v, x, b, ok in checks),
        "",
        "- **Spurious v and w** are the in-plane (v, along the monitor columns) and out-of-plane (w, normal to the "
        "monitor) displacements measured where only u was imposed: truth 0 at every point. Their mean is a "
        "systematic error (bound: 1 and 2 monitor px, which a calibration or convention error exceeds); their "
        f"scatter (± one standard deviation over the {de['valid']} points) is the per-point noise, which at this "
        "resolution is about 0.5 (v) and 2.8 (w) monitor px, 4x less at half resolution (docs/paper_reproduction.md).",
        "",
        _resolution_note(exp, de),
        "",
        "## Figures",
        "",
        "![views](views.png)",
        "",
        "`views.png`: the speckle on the monitor as each camera sees it in the reference state (through its mirror), "
        "axes in image px.",
        "",
        "![deformation](deformation.png)",
        "",
        "`deformation.png`, axes in monitor px (x along the rows, y down the columns): left, the measured u at each "
        f"valid point, which should be a sine along y of amplitude {de['imposed_amplitude_px']:g} px (bands of constant "
        "colour across x); middle, u averaged over rows of points (dots) against the imposed sine (line): the dots "
        "should sit on the line, with peaks a few % low at this resolution (see above); right, measured minus imposed "
        "u: noise centred on zero, with the subset's smoothing showing as bands at the sine's peaks.",
        "",
        "Timings (s): " + ", ".join(f"{k[:-2]} {v:.1f}" for k, v in state.timings.items() if k.startswith("stereo")),
        "",
    ]
    (out / "report.md").write_text("\n".join(lines))
    state.summary.setdefault("stereo", {})
    state.summary["stereo"] = {"deformation": summary["deformation"], "reprojection_rms_px": rp,
                               "dot_check": summary["dot_check"]}


def _checks_stereo(f: dict, dots: dict, de: dict, pitch_mm: float) -> list[tuple[str, str, str, str, bool | None]]:
    """(quantity, measured, expected, bound, within the bound or None where only reported) of the stereo demo;
    the bounds of tests/project/test_experiments.py."""
    rp, A = f["reprojection_rms_px"], de["imposed_amplitude_px"]
    scale_err = dots["mean_distance_mm"] / dots["true_mm"] - 1.0
    return [
        ("calibration reprojection RMS left / right (px): fit of the calibration model to the rendered dots",
         f"{rp['left']:.4f} / {rp['right']:.4f}", "~0.04 (rendering noise; the paper 0.115)", "< 0.25",
         max(rp["left"], rp["right"]) < 0.25),
        ("calibrated baseline, mirror only / joint with the far view (mm)",
         f"{f['baseline_mm_mirror']:.2f} / {f.get('baseline_mm_joint', float('nan')):.2f}", f"{BASELINE_MM:g} (the lab's)",
         "(reported; the dots below check the scale)", None),
        (f"neighbour distance of the 4x2 dots at {WORKING_DISTANCE_MM / 1000:g} m (mm): the 3-D scale",
         f"{dots['mean_distance_mm']:.3f} ± {dots['std_mm']:.3f} ({100 * scale_err:+.2f} %)", f"{dots['true_mm']:g}",
         "within 2 %", abs(scale_err) < 0.02),
        ("valid 3-D points", f"{de['valid']} / {de['points']}", "all", "> 80 %", de["valid"] > 0.8 * de["points"]),
        ("u amplitude (monitor px): fitted sine of the measured u", f"{de['fitted_amplitude_px']:.3f}",
         f"{A:g} imposed; ~6 % lower at this resolution", "within 15 %",
         abs(de["fitted_amplitude_px"] - A) < 0.15 * A),
        ("u residual RMS (monitor px): measured minus imposed u", f"{de['u_residual_rms_px']:.4f}",
         "noise + the sine's smoothing", "(reported)", None),
        ("spurious v, mean ± std (monitor px)", f"{de['v_mean_px']:+.4f} ± {de['v_std_px']:.4f} "
         f"({de['v_mean_px'] * pitch_mm:+.3f} mm)", "0", "abs(mean) < 1", abs(de["v_mean_px"]) < 1.0),
        ("spurious w, mean ± std (monitor px)", f"{de['w_mean_px']:+.4f} ± {de['w_std_px']:.4f} "
         f"({de['w_mean_px'] * pitch_mm:+.3f} mm)", "0", "abs(mean) < 2", abs(de["w_mean_px"]) < 2.0),
    ]


STEREO_STEPS = (stereo_calibration_step, stereo_measure_step, stereo_report_step)


def run_demo(out, config: DemoConfig | None = None, *, echo=print, only: str = "all",
             stereo_config: StereoDemoConfig | None = None) -> dict:
    """Run the steps into folder ``out`` (``only``: "2d", "stereo" or "all"); return the summary dictionary."""
    if only not in ("2d", "stereo", "all"):
        raise ValueError(f"only must be '2d', 'stereo' or 'all', got {only!r}")
    state = DemoState(config=config or DemoConfig(), out=Path(out), stereo_config=stereo_config or StereoDemoConfig())
    state.out.mkdir(parents=True, exist_ok=True)
    if only in ("2d", "all"):
        for step in STEPS:
            echo(f"[demo] {step.__doc__.splitlines()[0]}")
            step(state)
        e = state.summary["errors"]
        echo(f"[demo] {e['valid_points']}/{e['points']} points valid; RMS error u {e['u_rms_error_px']:.4f} px, "
             f"v {e['v_rms_error_px']:.4f} px; strain RMS error exx {e['exx_rms_error']:.1e}, "
             f"eyy {e['eyy_rms_error']:.1e}, exy {e['exy_rms_error']:.1e}")
        echo(f"[demo] wrote {', '.join(state.summary['files'])} to {state.out}")
    if only in ("stereo", "all"):
        for step in STEREO_STEPS:
            echo(f"[demo] {step.__doc__.splitlines()[0]}")
            t0 = time.perf_counter()
            step(state)
            echo(f"[demo]   ({time.perf_counter() - t0:.0f} s)")
        d = state.summary["stereo"]["deformation"]
        rp = state.summary["stereo"]["reprojection_rms_px"]
        echo(f"[demo] stereo: calibration RMS {rp['left']:.3f} / {rp['right']:.3f} px; u amplitude "
             f"{d['fitted_amplitude_px']:.2f} of {d['imposed_amplitude_px']:g} monitor px (low because of the demo's "
             f"quarter resolution: a subset spans most of the sine's period; full resolution: 0.02 % low); spurious "
             f"out-of-plane w (truth 0) mean {d['w_mean_px']:+.3f} monitor px (bound |mean| < 2), per-point scatter "
             f"{d['w_std_px']:.2f} px; wrote {state.out / 'stereo'}")
        if only == "stereo":
            (state.out / "summary.json").write_text(json.dumps(state.summary, indent=2, default=float))
    return state.summary


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m repro.demo", description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="demo_output", help="output folder (default: demo_output)")
    parser.add_argument("--size", type=int, default=DemoConfig.size, help="image side in px (default 512)")
    parser.add_argument("--step", type=int, default=DemoConfig.step, help="grid step in px (default 4)")
    parser.add_argument("--order", type=int, choices=(1, 2), default=DemoConfig.order)
    parser.add_argument("--device", default=None, help="Warp device (default: CUDA when present, else CPU)")
    parser.add_argument("--only", choices=("2d", "stereo", "all"), default="all",
                        help="2d: the synthetic 2-D demo; stereo: the paper-rig chain; all (default): both")
    parser.add_argument("--scale", type=float, default=StereoDemoConfig.scale,
                        help="stereo: camera resolution factor of the paper rig (default 0.25)")
    parser.add_argument("--cache", default=None, help="stereo: folder to cache rendered images in (default: none)")
    args = parser.parse_args(argv)
    if args.size < 96:
        parser.error("--size must be at least 96 px")
    cfg = DemoConfig(size=args.size, step=args.step, order=args.order, device=args.device)
    if not 0.05 <= args.scale <= 1.0:
        parser.error("--scale must be in [0.05, 1]")
    run_demo(args.out, cfg, only=args.only,
             stereo_config=StereoDemoConfig(scale=args.scale, cache=args.cache, device=args.device))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
