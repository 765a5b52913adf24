"""Figures like the paper's: contours per level with OA squares and US crosses (Figs. 3-4),
the rig's response (Fig. 2) and confusion matrices (Fig. 5).

A contour panel has equal scales on both axes and a square window around the points and the
table axis (the object frame's origin, which every scan turns about), so a flat face shows
as a row of points across the panel, not as a collapsed strip; lines join only neighbouring
points (a contour is closed only where the points go all the way round); the legend sits
below the panel, never over the data."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

STYLE = {"oa": ("s", "tab:red", "OA"), "us": ("x", "tab:blue", "US")}
JOIN = 2.5  # neighbouring points closer than JOIN x their median spacing are joined


def _outline(size_xy: tuple[float, float], pose: dict) -> np.ndarray:
    w, h = np.asarray(size_xy) / 2
    c = np.array([[-w, -h], [w, -h], [w, h], [-w, h], [-w, -h]])
    a = np.radians(pose["yaw_deg"])
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return c @ R.T + [pose["x_mm"], pose["y_mm"]]


def neighbour_segments(P: np.ndarray) -> list[np.ndarray]:
    """Runs of points (xy) to draw as lines: the points in order of their angle about the
    table axis (the origin), split where two neighbours lie more than JOIN x the median
    spacing apart; the last point joins the first only if that gap is as small (the points
    go all the way round). A single sweep from one side is thus an open line."""
    P = np.asarray(P, float)[:, :2]
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) < 2:
        return []
    P = P[np.argsort(np.arctan2(P[:, 1], P[:, 0]), kind="stable")]
    gaps = np.linalg.norm(np.diff(P, axis=0), axis=1)
    close = float(np.linalg.norm(P[0] - P[-1]))
    limit = JOIN * max(float(np.median(gaps)), 1e-9)
    runs, start = [], 0
    for i, g in enumerate(gaps):
        if g > limit:
            runs.append(P[start:i + 1])
            start = i + 1
    runs.append(P[start:])
    if len(P) >= 3 and close <= limit:  # closed: the last run continues into the first
        if len(runs) == 1:
            runs = [np.vstack([P, P[:1]])]
        else:
            runs = [np.vstack([runs[-1], runs[0]])] + runs[1:-1]
    return [r for r in runs if len(r) >= 2]


def square_window(xy: np.ndarray, pad: float = 0.08, least: float = 0.5) -> tuple:
    """((x0, x1), (y0, y1)): a square around the points (the larger extent plus `pad` of
    it on each side, at least `least` wide), so equal scales never collapse a panel."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if not len(xy):
        return (-least, least), (-least, least)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    c = (lo + hi) / 2
    half = max(float((hi - lo).max()) * (0.5 + pad), least / 2)
    return (c[0] - half, c[0] + half), (c[1] - half, c[1] + half)


def contour_axes(pts: dict, size_xy: tuple[float, float] | None = None,
                 fits: dict | None = None, title: str = "") -> Figure:
    """The matplotlib Figure of contour_figure (object-frame points in cm, one panel per
    level; fitted block outlines per modality when given, else lines between neighbours)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    levels = sorted(set(np.concatenate([pts[m]["level"] for m in STYLE]).tolist())) or [0]
    fig, axes = plt.subplots(1, len(levels), figsize=(4.4 * len(levels), 5.0), squeeze=False)
    for ax, lvl in zip(axes[0], levels):
        shown = [np.zeros((1, 2))]  # the table axis, which every scan turns about
        for m, (marker, color, label) in STYLE.items():
            sel = pts[m]["level"] == lvl
            P = pts[m]["P"][sel] / 10.0
            if not len(P):
                continue
            shown.append(P[:, :2])
            ax.scatter(P[:, 0], P[:, 1], marker=marker, s=16, color=color, label=label,
                       facecolors="none" if marker == "s" else None, linewidths=0.9,
                       zorder=3)
            if fits and m in fits and size_xy:
                o = _outline(size_xy, fits[m]["pose"]) / 10.0  # a rectangle: really closed
                shown.append(o)
                ax.plot(o[:, 0], o[:, 1], color=color, lw=1.0,
                        label=f"{label} fit, e={fits[m]['e_mean_mm']:.3f} mm")
            else:
                for run in neighbour_segments(P):
                    ax.plot(run[:, 0], run[:, 1], color=color, lw=0.6)
        ax.plot([0], [0], "+", color="0.45", ms=9, label="table axis")
        xl, yl = square_window(np.vstack(shown))
        ax.set_xlim(*xl)
        ax.set_ylim(*yl)
        ax.set_aspect("equal", adjustable="box")
        z = np.concatenate([pts[m]["P"][pts[m]["level"] == lvl][:, 2] for m in STYLE])
        ax.set_title(f"{title} level {lvl}" + (f" (z {np.median(z):.0f} mm)" if len(z) else ""),
                     fontsize=10)
        ax.set_xlabel("x (cm)")
        ax.set_ylabel("y (cm)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=3,
                  frameon=False)  # below the panel: never over the data
    fig.tight_layout()
    return fig


def contour_figure(pts: dict, path: Path, size_xy: tuple[float, float] | None = None,
                   fits: dict | None = None, title: str = "") -> None:
    """PNG of object-frame points (cm, like the paper), one panel per level; fitted block
    outlines per modality when given, else lines between neighbouring points."""
    import matplotlib.pyplot as plt

    fig = contour_axes(pts, size_xy, fits, title)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def rig_figure(raw: dict[str, np.ndarray], path: Path, modality: str = "oa") -> None:
    """PNG like the paper's Fig. 2: response amplitude over each tip frame's X-Z raster and
    over each edge frame's X sweeps (one row per Z level)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    sel = raw["modality"] == modality
    tips = sorted(set(raw["frame"][sel & (raw["step"] == "tip")].astype(int).tolist()))
    edges = sorted(set(raw["frame"][sel & (raw["step"] == "edge")].astype(int).tolist()))
    panels = [("tip", f) for f in tips] + [("edge", f) for f in edges]
    fig, axes = plt.subplots(1, max(len(panels), 1), figsize=(3.0 * max(len(panels), 1), 3.2),
                             squeeze=False)
    for ax, (step, f) in zip(axes[0], panels):
        m = sel & (raw["step"] == step) & (raw["frame"] == f)
        amp = np.nan_to_num(raw["amplitude"][m])
        if step == "tip":
            x, y = raw["sx_mm"][m] - raw["sx_mm"][m].mean(), raw["sz_mm"][m]
            ax.tricontourf(x, y - y.mean(), amp, levels=12, cmap="viridis")
            ax.set_title(f"tip frame {f}: Y {raw['sy_mm'][m].mean():.1f} mm", fontsize=8)
            ax.set_xlabel("X - centre (mm)", fontsize=8)
            ax.set_ylabel("Z - centre (mm)", fontsize=8)
        else:
            lines = raw["line"][m].astype(int)
            x = raw["sx_mm"][m] - raw["sx_mm"][m].mean()
            ax.scatter(x, raw["sz_mm"][m], c=amp, s=12, marker="s", cmap="viridis")
            ax.set_title(f"edge frame {f}: {raw['theta_deg'][m][0]:.0f} deg, "
                         f"{len(set(lines.tolist()))} lines", fontsize=8)
            ax.set_xlabel("X - centre (mm)", fontsize=8)
            ax.set_ylabel("Z (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def confusion_figure(cm: np.ndarray, classes: np.ndarray, path: Path, title: str) -> None:
    """PNG like the paper's Fig. 5: row-normalised confusion matrix in percent."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pct = 100 * cm / np.maximum(cm.sum(axis=1, keepdims=True), 1)
    fig, ax = plt.subplots(figsize=(5.2, 4.6))
    ax.imshow(pct, cmap="Blues", vmin=0, vmax=100)
    for i in range(len(classes)):
        for j in range(len(classes)):
            ax.text(j, i, f"{pct[i, j]:.1f}", ha="center", va="center", fontsize=7,
                    color="white" if pct[i, j] > 60 else "black")
    ax.set_xticks(range(len(classes)), classes, rotation=45, ha="right", fontsize=8)
    ax.set_yticks(range(len(classes)), classes, fontsize=8)
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
