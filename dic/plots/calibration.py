"""Figures of the calibration from images (``specula calibrate ... --figures DIR``).

Each function takes a result of :mod:`calibration.pipeline` and a folder (or a file path) and
writes PNGs; it returns the paths written. Image coordinates are px with y down (docs/conventions.md);
residual vectors are drawn magnified, with a key arrow of a round length in px.

* :func:`write_intrinsics_figures` — ``intrinsics_views.png`` (wrapped phase and detected centres per
  view), ``intrinsics_detail.png`` (close-up with dot ids), ``intrinsics_residuals.png`` (residual
  vectors, their distribution, RMS per view with dropped views in grey, the median and the rejection
  limit in red).
* :func:`write_mirror_figures` — ``mirror_views.png`` and ``mirror_residuals.png`` (per mirror tilt).
* :func:`write_rig_figures` — ``stereo_residuals.png`` (joint adjustment, both cameras),
  ``stereo_view_rms.png`` (:func:`view_rms_bars`: RMS per view and camera, the limit drawn) and
  ``stereo_check.png`` (:func:`write_check_figures`: dot-distance errors and reprojection residuals
  of the check views).
* :func:`view_mosaic`, :func:`view_detail` — the view panels, for any list of
  :class:`~calibration.pipeline.ViewResult`.
"""
from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import numpy as np

from calibration.pipeline import IntrinsicsCalibration, MirrorCalibration, RigCalibration, read_stack

from ._common import new_figure, save_figure

__all__ = ["write_intrinsics_figures", "write_mirror_figures", "write_rig_figures", "write_check_figures",
           "view_mosaic", "view_detail", "view_rms_bars", "FigureSkipped"]

#: resolution of every calibration figure (dots per inch)
DPI = 110
#: the limit drawn in ``stereo_view_rms.png``: this multiple of a camera's median view RMS, the default
#: view-rejection rule of the intrinsics (``calibrate_intrinsics(reject=3)``); the rig stage drops no view
STEREO_VIEW_LIMIT = 3.0


class FigureSkipped(UserWarning):
    """A figure was not drawn; the message says which and why (the others are still written)."""


def _check(obj, cls, name: str):
    if not isinstance(obj, cls):
        raise ValueError(f"{name} must be a calibration.pipeline.{cls.__name__}, got {type(obj).__name__}")
    return obj


def _folder(folder) -> Path:
    if folder is None:
        raise ValueError("folder must be a path to write the figures into, got None")
    p = Path(os.fspath(folder))
    if p.exists() and not p.is_dir():
        raise ValueError(f"{p} exists and is not a folder")
    p.mkdir(parents=True, exist_ok=True)
    return p


def _view_label(name: str) -> str:
    """Short label of a view: its folder name (``pose03``), or the last two parts when that is ambiguous (``left``)."""
    parts = [p for p in str(name).replace("\\", "/").rstrip("/").split("/") if p and p != "*" and "*" not in p]
    if not parts:
        return str(name)
    if len(parts) >= 2 and parts[-1] in ("left", "right", "L", "R"):
        return "/".join(parts[-2:])
    return parts[-1]


def _nice_step(x: float) -> float:
    """A round number (1, 2 or 5 × 10^k) close to ``x`` (for arrow keys)."""
    if not x > 0:
        return 1.0
    e = math.floor(math.log10(x))
    m = x / 10 ** e
    return (1 if m < 1.5 else 2 if m < 3.5 else 5 if m < 7.5 else 10) * 10 ** e


def _residual_arrows(ax, points, residuals, colors, labels, size, title):
    """Residual vectors (px) drawn at their points (px), magnified so that the 95th percentile is ~5 % of
    the image width, with a key arrow of a round length in px. Returns the magnification."""
    w, h = size
    # points not seen in a view are NaN rows: leave them out
    pairs = []
    for pts, r in zip(points, residuals):
        pts, r = np.asarray(pts, dtype=float).reshape(-1, 2), np.asarray(r, dtype=float).reshape(-1, 2)
        ok = np.all(np.isfinite(pts), axis=1) & np.all(np.isfinite(r), axis=1)
        pairs.append((pts[ok], r[ok]))
    allr = np.concatenate([r for _, r in pairs]) if pairs else np.zeros((0, 2))
    p95 = float(np.percentile(np.linalg.norm(allr, axis=1), 95)) if len(allr) else 0.0
    key = _nice_step(p95) if p95 > 0 else 1.0
    scale = 0.05 * w / key
    q = None
    for (pts, r), c, lab in zip(pairs, colors, labels):
        ax.plot(pts[:, 0], pts[:, 1], ".", ms=2, color=c, label=lab)
        q = ax.quiver(pts[:, 0], pts[:, 1], r[:, 0] * scale, r[:, 1] * scale, color=c, angles="xy", scale_units="xy",
                      scale=1, width=0.0025)
    if q is not None:
        ax.quiverkey(q, 0.04, 0.04, key * scale, f"{key:g} px", labelpos="E", coordinates="axes", color="k",
                     fontproperties={"size": 7})
    ax.set_xlim(0, w)
    ax.set_ylim(h, 0)
    ax.set_aspect("equal")
    ax.tick_params(labelsize=7)
    ax.set_title(title, fontsize=8, loc="left")
    return scale


# -- views -----------------------------------------------------------------------------------------------
def view_mosaic(views, path, max_views: int = 16, title: str = "") -> Path | None:
    """Wrapped phase of each view (subsampled) with the detected dot centres; up to ``max_views`` panels.

    ``views`` are :class:`~calibration.pipeline.ViewResult`; those without a phase preview are left out.
    Returns the path written, or None when no view has a preview.
    """
    from matplotlib.patches import Rectangle

    if isinstance(max_views, bool) or not isinstance(max_views, (int, np.integer)) or max_views < 1:
        raise ValueError(f"max_views must be a positive integer, got {max_views!r}")
    shown = [v for v in views if v.preview is not None][:max_views]
    if not shown:
        return None
    n = len(shown)
    cols = min(4, n)
    rows = math.ceil(n / cols)
    h, w = shown[0].preview.shape
    fig = new_figure((2.6 * cols, (2.6 * h / w + 0.3) * rows))
    axes = fig.subplots(rows, cols, squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, v in zip(axes.ravel(), shown):
        ax.imshow(v.preview, cmap="twilight", interpolation="nearest", vmin=-np.pi, vmax=np.pi)
        ax.add_patch(Rectangle((-0.5, -0.5), w, h, fill=False, lw=0.5, color="0.6"))
        if v.detection is not None:
            q = v.detection.image_points / v.preview_step
            ax.plot(q[:, 0], q[:, 1], "+", color="red", ms=4, mew=0.8)
        state = ("mirrored" if v.mirrored else "direct") if v.ok else "dropped"
        blur = f", blur {v.detection.blur_sigma:.1f} px" if v.detection is not None else ""
        ax.set_title(f"{_view_label(v.name)} ({state}, {v.n_points} pts{blur})", fontsize=6)
    if title:
        fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    return save_figure(fig, path, dpi=DPI)


def _first_image(view):
    """The first recorded image of a view given as a folder or glob (None when it cannot be read)."""
    try:
        return read_stack(view.name)[0]
    except (ValueError, OSError, IndexError):
        return None


def view_detail(views, path, title: str = "") -> Path | None:
    """Close-up of the most blurred direct view and of the first mirrored view: the recorded image
    and the wrapped phase with the detected centres and their ids (the mirrored view's ids follow the
    reflected target). Dots removed for a poor phase fit are listed in the panel title.

    ``views`` are :class:`~calibration.pipeline.ViewResult`. Returns the path written, or None when no
    usable view has a detection and a phase preview.
    """
    ok = [v for v in views if v.ok and v.detection is not None and v.preview is not None]
    direct = [v for v in ok if not v.mirrored]
    mirrored = [v for v in ok if v.mirrored]
    picks = []
    if direct:
        picks.append(max(direct, key=lambda v: v.detection.blur_sigma))
    if mirrored:  # the one with the most dots removed (it shows why), else the first
        picks.append(max(mirrored, key=lambda v: (len(v.removed) + len(v.vignetted), -mirrored.index(v))))
    if not picks:
        return None
    fig = new_figure((10, 2.9 * len(picks) + 0.4))
    axes = fig.subplots(len(picks), 2, squeeze=False)
    for (ax_img, ax_ph), v in zip(axes, picks):
        d = v.detection
        q = d.image_points
        # crop: the lit target area (robust bounds of the valid phase, so that dots removed near an edge show too)
        s = v.preview_step
        yy, xx = np.nonzero(np.isfinite(v.preview))
        if len(xx) > 100:
            lo = np.array([np.percentile(xx, 0.5), np.percentile(yy, 0.5)]) * s
            hi = np.array([np.percentile(xx, 99.5), np.percentile(yy, 99.5)]) * s
            pad = 0.03 * (hi - lo)
            (x0, y0), (x1, y1) = np.minimum(lo, q.min(axis=0)) - pad, np.maximum(hi, q.max(axis=0)) + pad
        else:
            (x0, y0), (x1, y1) = q.min(axis=0) - 50, q.max(axis=0) + 50
        W, H = v.image_size
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, W - 1), min(y1, H - 1)
        img = _first_image(v)
        if img is not None:
            ax_img.imshow(img, cmap="gray", interpolation="antialiased")
            ax_img.set_title(f"{_view_label(v.name)}: first recorded image (of the N phase steps)", fontsize=8, loc="left")
        else:
            ax_img.set_title(f"{_view_label(v.name)}: (image not readable)", fontsize=8, loc="left")
        hp, wp = v.preview.shape
        ax_ph.imshow(v.preview, cmap="twilight", interpolation="nearest", vmin=-np.pi, vmax=np.pi,
                     extent=(-0.5 * s, (wp - 0.5) * s, (hp - 0.5) * s, -0.5 * s))
        ax_ph.plot(q[:, 0], q[:, 1], "+", color="red", ms=7, mew=1.2)
        if len(q) <= 80:
            for (x, y), i in zip(q, d.ids):
                ax_ph.annotate(str(int(i)), (x, y), xytext=(4, 4), textcoords="offset points", fontsize=7,
                               color="k", bbox=dict(boxstyle="round,pad=0.1", fc="white", ec="none", alpha=0.8))
        kind = "mirrored: ids follow the reflected target" if v.mirrored else "direct"
        extra = []
        if v.removed:
            extra.append(f"poor phase fit: {', '.join(str(i) for i, _ in v.removed)}")
        if v.vignetted:
            extra.append(f"vignetted: {', '.join(str(i) for i, _ in v.vignetted)}")
        extra = f"; removed ids ({'; '.join(extra)})" if extra else ""
        ax_ph.set_title(f"wrapped phase, {len(q)} centres ({kind})\nblur σ ≈ {d.blur_sigma:.1f} px{extra}",
                        fontsize=8, loc="left")
        for ax in (ax_img, ax_ph):
            ax.set_xlim(x0, x1)
            ax.set_ylim(y1, y0)
            ax.set_aspect("equal")
            ax.tick_params(labelsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path, dpi=DPI)


# -- intrinsics ------------------------------------------------------------------------------------------
def _rms_bars(ax, names, values, colors, hatches, limits, median) -> None:
    """Bars of per-view RMS (px) with the median (dashed) and each view's rejection limit (red ticks;
    one red line when all are equal), labelled for the legend."""
    bars = ax.bar(range(len(names)), values, color=colors)
    for b, hh in zip(bars, hatches):
        b.set_hatch(hh)
    ax.axhline(median, color="k", ls="--", lw=0.7, label=f"median {median:.4f} px")
    lim = np.asarray(limits, dtype=np.float64)
    finite = np.isfinite(lim)
    if finite.any():
        if np.allclose(lim[finite], lim[finite][0], rtol=1e-9):
            ax.axhline(lim[finite][0], color="tab:red", lw=1.0, label=f"rejection limit {lim[finite][0]:.4f} px")
        else:
            xs = np.flatnonzero(finite)
            ax.hlines(lim[finite], xs - 0.4, xs + 0.4, color="tab:red", lw=1.2, label="rejection limit per view")
    ax.set_xticks(range(len(names)))
    ax.set_xticklabels(names, rotation=90, fontsize=6)
    ax.tick_params(axis="y", labelsize=7)
    ax.set_ylabel("RMS reprojection error (px)", fontsize=7)
    ax.set_ylim(0, 1.15 * max([*values, *lim[finite], median, 1e-12]))
    ax.legend(fontsize=6, loc="upper left")


def view_rms_bars(per_camera, path, limits=None, title: str = "") -> Path:
    """Bars of the RMS reprojection error per view, one panel per camera, with each camera's median
    and rejection limit drawn; returns the path written.

    ``per_camera``: ``{camera name: [(view label, RMS px), ...]}``; ``limits``: ``{camera name: px}``
    (a horizontal line; missing or None: none drawn)."""
    if not isinstance(per_camera, dict) or not per_camera:
        raise ValueError("per_camera must be a non-empty dict {camera name: [(view label, RMS px), ...]}")
    limits = {} if limits is None else dict(limits)
    n = len(per_camera)
    width = max(4.0, 0.35 * max(len(v) for v in per_camera.values()) + 1.5)
    fig = new_figure((width * n, 3.6))
    axes = np.atleast_1d(fig.subplots(1, n, squeeze=False)[0])
    for ax, (cam, items) in zip(axes, per_camera.items()):
        items = list(items)
        if not items:
            raise ValueError(f"camera {cam!r} has no views")
        names = [str(nm) for nm, _ in items]
        vals = [float(v) for _, v in items]
        lim = limits.get(cam)
        _rms_bars(ax, names, vals, [f"C{k % 10}" for k in range(len(vals))], [""] * len(vals),
                  [np.nan if lim is None else float(lim)] * len(vals), float(np.median(vals)))
        ax.set_title(f"{cam} camera: RMS per view (all {np.sqrt(np.mean(np.square(vals))):.4f} px)", fontsize=8,
                     loc="left")
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return save_figure(fig, path, dpi=DPI)


def write_intrinsics_figures(calibration: IntrinsicsCalibration, folder) -> list[Path]:
    """Figures of an intrinsic calibration into ``folder`` (created); returns the paths written.

    Detected centres on the phase maps (all views, and a close-up with ids), residual vectors of
    every kept view in the image, their distribution, and the RMS per view (dropped views in grey).
    """
    from matplotlib.patches import Circle

    ic = _check(calibration, IntrinsicsCalibration, "calibration")
    folder = _folder(folder)
    out = []
    mosaic = view_mosaic(ic.views, folder / "intrinsics_views.png", title="wrapped phase and detected dot centres")
    if mosaic is not None:
        out.append(mosaic)
    detail = view_detail(ic.views, folder / "intrinsics_detail.png",
                         title="dot centres found in the wrapped phase (defocus-insensitive), with their ids")
    if detail is not None:
        out.append(detail)
    res = ic.result
    size = res.camera.size
    fig = new_figure((12, 3.8))
    ax, cx, bx = fig.subplots(1, 3, gridspec_kw={"width_ratios": [1.45, 0.75, 1.1]})
    colors = ["tab:orange" if ic.views[ic.used[u]].mirrored else "tab:blue" for u in res.view_indices]
    _residual_arrows(ax, [ic.image_points[u] for u in res.view_indices], res.residuals, colors,
                     [None] * len(colors), size, "residual vectors, magnified (blue: direct, orange: mirrored)")
    allr = np.concatenate(res.residuals)
    for r, c in zip(res.residuals, colors):
        cx.plot(r[:, 0], r[:, 1], ".", ms=2.5, color=c)
    lim = 1.15 * float(np.max(np.abs(allr))) if len(allr) else 1.0
    rms1 = float(np.sqrt(np.mean(allr ** 2)))  # per axis
    cx.add_patch(Circle((0, 0), rms1, fill=False, ls="--", color="k", lw=0.8))
    cx.axhline(0, color="0.7", lw=0.5)
    cx.axvline(0, color="0.7", lw=0.5)
    cx.set_xlim(-lim, lim)
    cx.set_ylim(lim, -lim)
    cx.set_aspect("equal")
    cx.tick_params(labelsize=7)
    cx.set_xlabel("residual x (px)", fontsize=7)
    cx.set_ylabel("residual y (px)", fontsize=7)
    cx.set_title(f"residuals; circle: RMS per axis {rms1:.4f} px", fontsize=8, loc="left")
    # RMS per view in input order; views dropped by the outlier rejection in grey
    rms_of = {int(u): float(r) for u, r in zip(res.view_indices, res.per_view_rms)}
    drop_of = {int(d.index): d for d in res.dropped}
    names, vals, cols, hatches = [], [], [], []
    for u, vi in enumerate(ic.used):
        v = ic.views[vi]
        names.append(_view_label(v.name))
        if u in rms_of:
            vals.append(rms_of[u])
            cols.append("tab:orange" if v.mirrored else "tab:blue")
            hatches.append("")
        else:
            vals.append(drop_of[u].rms if u in drop_of else 0.0)
            cols.append("0.75")
            hatches.append("//")
    limit_of = {}
    if res.view_rms_limit is not None:
        limit_of = {int(u): float(v) for u, v in zip(res.view_indices, res.view_rms_limit) if np.isfinite(v)}
    limits = [limit_of.get(u, np.nan) for u in range(len(ic.used))]
    _rms_bars(bx, names, vals, cols, hatches, limits, float(np.median(res.per_view_rms)))
    nd = len(drop_of)
    title = f"RMS per view (all {res.rms:.4f} px"
    if nd:
        title += f"; {nd} dropped, grey; {res.rms_all_views:.4f} px with them"
    bx.set_title(title + ")", fontsize=8, loc="left")
    fig.tight_layout()
    return out + [save_figure(fig, folder / "intrinsics_residuals.png", dpi=DPI)]


# -- mirror extrinsics -----------------------------------------------------------------------------------
def write_mirror_figures(calibration: MirrorCalibration, folder) -> list[Path]:
    """Figures of a mirror calibration into ``folder`` (created); returns the paths written.

    Mirrored views with their centres, and the residuals of the bundle adjustment per mirror tilt.
    """
    mc = _check(calibration, MirrorCalibration, "calibration")
    folder = _folder(folder)
    out = []
    mosaic = view_mosaic(mc.views, folder / "mirror_views.png", title="mirrored views: wrapped phase and dot centres")
    if mosaic is not None:
        out.append(mosaic)
    r = mc.result
    fig = new_figure((6.4, 4.9))
    ax = fig.subplots()
    labels = [f"{_view_label(mc.names[j])}: RMS {r.per_mirror_rms[j]:.4f} px" for j in range(len(mc.names))]
    _residual_arrows(ax, mc.mirrored_points, r.residuals, [f"C{j}" for j in range(len(mc.names))], labels,
                     r.camera.size, f"{r.camera.name or 'camera'}: mirrored dots and residuals (magnified) after the "
                                    f"bundle adjustment;\nRMS {r.rms:.4f} px (closed form alone {r.closed_form_rms:.4f} px)")
    ax.legend(fontsize=7, loc="lower right", markerscale=3)
    fig.tight_layout()
    return out + [save_figure(fig, folder / "mirror_residuals.png", dpi=DPI)]


# -- stereo rig ------------------------------------------------------------------------------------------
def _joint_residuals(rc):
    """Per-point residuals (px) of the joint adjustment, recomputed from its solution:
    ``{"left": [(label, points, residuals)...], "right": [...]}`` (mirror tilts, then far views)."""
    j = rc.joint
    rig = j.rig
    out = {"left": [], "right": []}
    common = np.intersect1d(rc.left.point_ids, rc.right.point_ids)
    for side, mc, mirrors in (("left", rc.left, j.mirrors_left), ("right", rc.right, j.mirrors_right)):
        pos = {int(d): n for n, d in enumerate(mc.point_ids)}
        idx = [pos[int(i)] for i in common]
        X = mc.object_points[idx]
        P = X @ j.R_left_target.T + j.t_left_target
        if side == "right":
            P = P @ rig.R_right_left.T + rig.t_right_left
        for nm, q, m in zip(mc.names, mc.mirrored_points, mirrors):
            qo = q[idx]
            out[side].append((_view_label(nm), qo, mc.camera.project(m.reflect(P)) - qo))
    for fv, (R, t) in zip(rc.far_views, j.far_poses_left):
        P = fv.object_points @ np.asarray(R).T + t
        out["left"].append((fv.name or "far", fv.left_points, rig.left.project(P) - fv.left_points))
        Pr = P @ rig.R_right_left.T + rig.t_right_left
        out["right"].append((fv.name or "far", fv.right_points, rig.right.project(Pr) - fv.right_points))
    return out


def write_rig_figures(calibration: RigCalibration, folder) -> list[Path]:
    """Figures of a stereo rig calibrated from mirrors into ``folder`` (created); returns the paths written.

    ``stereo_residuals.png``: residuals of the joint adjustment in both cameras (mirror tilts and far
    views), when there was one. They are recomputed here, so the figure is drawn only when they
    reproduce the adjustment's RMS (within 0.1 %); otherwise a :class:`FigureSkipped` warning says why it is missing.
    ``stereo_check.png`` (:func:`write_check_figures`) when there are check views.
    """
    rc = _check(calibration, RigCalibration, "calibration")
    folder = _folder(folder)
    out = []
    groups = _joint_residuals(rc) if rc.joint is not None else None
    if groups is not None:
        for side in ("left", "right"):
            r = np.concatenate([r for _, _, r in groups[side][:len(rc.left.names if side == "left" else rc.right.names)]])
            want = rc.joint.rms_groups.get(f"{side}_mirrored")
            got = float(np.sqrt(np.nanmean(np.sum(r ** 2, axis=1))))
            if want is None or not abs(got - want) <= 1e-3 * want + 1e-9:
                warnings.warn(f"no stereo_residuals.png (recomputed {side} RMS {got:.4g} px differs from the "
                              f"adjustment's {want})", FigureSkipped, stacklevel=2)
                groups = None
                break
    if groups is not None:
        fig = new_figure((11, 4.3))
        axes = fig.subplots(1, 2)
        for ax, side in zip(axes, ("left", "right")):
            items = groups[side]
            labels = [f"{nm}: {np.sqrt(np.nanmean(np.sum(r ** 2, axis=1))):.4f} px" for nm, _, r in items]
            cols = [f"C{k}" for k in range(len(items))]
            cam = rc.rig.left if side == "left" else rc.rig.right
            _residual_arrows(ax, [p for _, p, _ in items], [r for _, _, r in items], cols, labels, cam.size,
                             f"{side} camera: residuals (magnified) of the joint adjustment")
            ax.legend(fontsize=6.5, loc="lower right", markerscale=3)
        fig.tight_layout()
        out.append(save_figure(fig, folder / "stereo_residuals.png", dpi=DPI))
        per_camera = {side: [(nm, float(np.sqrt(np.nanmean(np.sum(r ** 2, axis=1))))) for nm, _, r in groups[side]]
                      for side in ("left", "right")}
        limits = {side: STEREO_VIEW_LIMIT * float(np.median([v for _, v in items])) for side, items in per_camera.items()}
        out.append(view_rms_bars(per_camera, folder / "stereo_view_rms.png", limits=limits,
                                 title=f"joint adjustment: RMS per view and camera; red: {STEREO_VIEW_LIMIT:g} × the "
                                       "camera's median (the intrinsics' default rejection rule)"))
    if rc.checks:
        out.extend(write_check_figures(list(zip(rc.check_views, rc.checks)), folder, rig=rc.rig))
    return out


def write_check_figures(checks, folder, rig=None) -> list[Path]:
    """``stereo_check.png`` in ``folder`` (created): errors of the distances between adjacent dots of each
    check view (mm) and, with ``rig`` (a :class:`~calibration.stereo.StereoRig`), the reprojection residuals
    (px) of the triangulated dots in both cameras. Returns ``[path]``.

    ``checks`` is a sequence of ``(view, reconstruction)`` pairs: a
    :class:`~calibration.pipeline.StereoView` and its :class:`~calibration.stereo.TargetReconstruction`.
    """
    checks = list(checks)
    if not checks:
        raise ValueError("checks is empty; give at least one (StereoView, TargetReconstruction) pair")
    if any(not isinstance(c, (tuple, list)) or len(c) != 2 for c in checks):
        raise ValueError("checks must be (StereoView, TargetReconstruction) pairs")
    folder = _folder(folder)
    ncol = 3 if rig is not None else 1
    fig = new_figure((4.2 * ncol, 3.4))
    axes = fig.subplots(1, ncol, squeeze=False, gridspec_kw={"width_ratios": [1.0] + [1.2] * (ncol - 1)})
    ax = axes[0, 0]
    for k, (view, rec) in enumerate(checks):
        e = np.asarray(rec.neighbour_errors)
        ax.plot(np.full(len(e), k) + np.linspace(-0.2, 0.2, len(e)), e, "o", ms=3)
        ax.annotate(f"RMS {np.sqrt(np.mean(e ** 2)):.3f} mm\nscale {rec.mean_relative_error * 100:+.3f} %", (k, 0.97),
                    xycoords=("data", "axes fraction"), fontsize=6, va="top", ha="center")
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xticks(range(len(checks)))
    ax.set_xticklabels([v.name for v, _ in checks], fontsize=7)
    ax.tick_params(axis="y", labelsize=7)
    ax.set_xlim(-0.7, len(checks) - 0.3)
    lo, hi = ax.get_ylim()
    ax.set_ylim(lo, hi + 0.35 * (hi - lo))
    ax.set_ylabel("measured − true distance (mm)", fontsize=7)
    ax.set_title("check views: distance between adjacent dots", fontsize=8, loc="left")
    if rig is not None:
        for ax, side in zip(axes[0, 1:], ("left", "right")):
            pts, res, labels = [], [], []
            for view, rec in checks:
                pl, pr = rig.project(rec.points)
                q = view.left_points if side == "left" else view.right_points
                r = (pl if side == "left" else pr) - q
                pts.append(q)
                res.append(r)
                labels.append(f"{view.name}: {np.sqrt(np.nanmean(np.sum(r ** 2, axis=1))):.4f} px")
            cam = rig.left if side == "left" else rig.right
            _residual_arrows(ax, pts, res, [f"C{k}" for k in range(len(pts))], labels, cam.size,
                             f"{side}: reprojection of the triangulated dots")
            ax.legend(fontsize=6.5, loc="best", markerscale=3)
    fig.tight_layout()
    return [save_figure(fig, folder / "stereo_check.png", dpi=DPI)]
