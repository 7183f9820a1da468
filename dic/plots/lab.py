"""Drawings of a virtual-lab scene (:mod:`dic.lab`): top and side views of the layout.

``plot_layout(scene)`` draws cameras (with their fields of view), optical axes, mirrors (with the
chief ray reflected off each), screens, speckled surfaces and, for a :class:`~dic.lab.PaperRig`, the
27 monitor test positions. Coordinates are world millimetres. ``python -m dic.plots.lab OUT_DIR``
writes the figures of docs/lab.md.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from ..lab.paper import PaperRig
from ..lab.scene import Scene
from ._common import new_figure, save_figure

__all__ = ["plot_layout"]

# view name -> (world axis along the page's x, world axis along the page's y, sign of page y)
_VIEWS = {"top": (0, 2, 1.0), "side": (2, 1, -1.0)}


def _xy(points, view):
    a, b, s = _VIEWS[view]
    p = np.atleast_2d(points)
    return p[:, a], s * p[:, b]


def _draw(ax, scene: Scene, view: str, reach: float, zoom: bool):
    colors = ["tab:blue", "tab:red", "tab:green", "tab:purple"]
    for k, cam in enumerate(scene.cameras):
        c = colors[k % len(colors)]
        C = cam.center_world
        W, H = cam.size
        edge = [[-0.5, (H - 1) / 2], [W - 0.5, (H - 1) / 2]] if view == "top" else [[(W - 1) / 2, -0.5], [(W - 1) / 2, H - 0.5]]
        rays = cam.camera.rays(np.asarray(edge, dtype=float)) @ cam.R_cam_world  # camera -> world directions
        for d in rays:
            P = C + d * reach / d[2 if view == "top" else 2] if abs(d[2]) > 1e-9 else C + d * reach
            ax.plot(*_xy(np.stack([C, P]), view), color=c, lw=0.6, alpha=0.5)
        x, y = _xy(C, view)
        ax.plot(x, y, "^" if view == "top" else ">", color=c, ms=7, label=f"camera {cam.name}" if cam.name else None)
        # chief ray, reflected once by the first mirror it meets
        o, d = C, cam.axis_world
        path = [o]
        for m in scene.mirrors:
            n, dd = m.plane
            den = d @ n
            if den < 0:
                t = -(o @ n + dd) / den
                q = o + t * d
                loc = (q - m.center) @ m.R_world_mirror
                if t > 0 and abs(loc[0]) <= m.size[0] / 2 and abs(loc[1]) <= m.size[1] / 2:
                    path.append(q)
                    o, d = q, d - 2 * den * n
                    break
        end = o + d * (reach if len(path) == 1 else 1.6 * np.linalg.norm(path[-1] - C) + 900.0)
        path.append(end)
        ax.plot(*_xy(np.stack(path), view), color=c, lw=1.0, ls="--")
    for m in scene.mirrors:
        cr = m.corners()
        seg = cr[[0, 1]] if view == "top" else cr[[1, 2]]
        ax.plot(*_xy(seg, view), color="k", lw=2.5, solid_capstyle="butt")
        if zoom and scene.cameras:
            # the cone the nearest camera sees through the mirror: rays to its two edges, reflected
            cam = min(scene.cameras, key=lambda c: np.linalg.norm(c.center_world - m.center))
            C = cam.center_world
            n, dd = m.plane
            for q in (0.5 * (cr[0] + cr[3]), 0.5 * (cr[1] + cr[2])) if view == "top" else (0.5 * (cr[0] + cr[1]), 0.5 * (cr[2] + cr[3])):
                d = (q - C) / np.linalg.norm(q - C)
                d2 = d - 2 * (d @ n) * n
                ax.plot(*_xy(np.stack([C, q, q + d2 * 1.6 * np.linalg.norm(q - C) * 3.0]), view), color="0.3", lw=0.7, alpha=0.8)
    for s in scene.screens:
        cr = s.corners()
        seg = cr[[0, 1]] if view == "top" else cr[[1, 2]]
        ax.plot(*_xy(seg, view), color="darkorange", lw=3, solid_capstyle="butt", label=s.name or "screen")
    for p in scene.planes:
        w, h = p.size
        seg = p.to_world([[0, h / 2], [w, h / 2]] if view == "top" else [[w / 2, 0], [w / 2, h]], deformed=False)
        ax.plot(*_xy(seg, view), color="0.4", lw=2)
    if isinstance(scene, PaperRig) and not zoom:
        mon = scene.monitor
        for pose in scene.monitor_positions:
            moved = mon.placed(pose.R_world_screen, pose.t_world_screen)
            cr = moved.corners()
            seg = cr[[0, 1]] if view == "top" else cr[[1, 2]]
            ax.plot(*_xy(seg, view), color="goldenrod", lw=1.5, alpha=0.7)
        ax.plot(*_xy(scene.crossing_point, view), "k+", ms=8)
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    if view == "top":
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("z (mm, forward)")
    else:
        ax.set_xlabel("z (mm, forward)")
        ax.set_ylabel("height -y (mm)")


def plot_layout(scene: Scene, path=None, *, reach: float | None = None, near: float = 1200.0):
    """Top view, side view and a close-up of the cameras' neighbourhood (top view).

    ``reach`` (mm) is how far fields of view are drawn (default: beyond the farthest object);
    ``near`` (mm) is the half-size of the close-up. Returns the Matplotlib figure (saved to ``path``
    at 90 dpi if given; format from the suffix).
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a dic.lab.Scene, got {type(scene).__name__}")
    if not scene.cameras:
        raise ValueError("the scene has no camera to draw the layout around")
    if reach is not None and not reach > 0:
        raise ValueError(f"reach must be a positive distance in mm, got {reach!r}")
    if not near > 0:
        raise ValueError(f"near must be a positive distance in mm, got {near!r}")
    if reach is None:
        zs = [c.center_world[2] for c in scene.cameras]
        if isinstance(scene, PaperRig):
            zs += [p.t_world_screen[2] for p in scene.monitor_positions]
        zs += [s.center_world[2] for s in scene.screens]
        reach = max(zs) - min(zs) + 500.0
    fig = new_figure((11, 7.2))
    gs = fig.add_gridspec(2, 2, width_ratios=[1.25, 1], height_ratios=[1.5, 1])
    ax_top = fig.add_subplot(gs[0, 0])
    ax_near = fig.add_subplot(gs[0, 1])
    ax_side = fig.add_subplot(gs[1, :])
    _draw(ax_top, scene, "top", reach, zoom=False)
    ax_top.set_title("top view")
    _draw(ax_near, scene, "top", reach, zoom=True)
    centre = np.mean([c.center_world for c in scene.cameras], axis=0)
    ax_near.set_xlim(centre[0] - near, centre[0] + near)
    ax_near.set_ylim(centre[2] - 0.8 * near, centre[2] + 0.8 * near)
    ax_near.set_title("top view, around the cameras")
    _draw(ax_side, scene, "side", reach, zoom=False)
    ax_side.set_title("side view")
    handles, labels = ax_top.get_legend_handles_labels()
    uniq = dict(zip(labels, handles))
    ax_top.legend(uniq.values(), uniq.keys(), loc="upper left", fontsize=8)
    fig.tight_layout()
    if path is not None:
        save_figure(fig, path, dpi=90)
    return fig


def _docs_figures(out_dir: Path) -> None:  # pragma: no cover - run by hand to refresh docs/img
    from ..lab.paper import paper_rig
    from ..lab.rendering import render
    from ..lab.scene import SpecklePlane

    out_dir.mkdir(parents=True, exist_ok=True)
    rig = paper_rig()
    plot_layout(rig.replace(mirrors=list(rig.nominal_mirrors)), out_dir / "lab_layout.png")

    small = paper_rig(scale=0.25)
    # for the picture only: a grey wall 9 m ahead shows where the mirrors are (the rig's lab is dark)
    wall = SpecklePlane.facing(center=(0.0, 0.0, 9000.0), normal=(0.0, 0.0, -1.0), size=(30000.0, 20000.0), albedo=(0.35, 0.35))
    small = small.replace(planes=[wall])
    views = [(small.with_mirror_tilt(k), 0, f"left camera, mirror tilt {k} {small.mirror_tilts_deg[k]}°") for k in range(3)]
    views += [(small.with_mirror_tilt(0), 1, "right camera, mirror tilt 0"),
              (small.with_monitor_at((2, 2, 2)), 0, "left camera, monitor at (2, 2, 2)"),
              (small.with_monitor_at((1, 1, 1)), 1, "right camera, monitor at (1, 1, 1)")]
    fig = new_figure((12, 6.2))
    axes = fig.subplots(2, 3)
    for ax, (scene, cam, title) in zip(axes.ravel(), views):
        img = render(scene, cam, samples=16, seed=0, device="cpu")
        ax.imshow(img, cmap="gray", vmin=0, vmax=255)
        ax.set_title(title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    save_figure(fig, out_dir / "lab_views.png", dpi=72)


if __name__ == "__main__":  # pragma: no cover
    _docs_figures(Path(sys.argv[1] if len(sys.argv) > 1 else "docs/img"))
