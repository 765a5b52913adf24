"""Figures like the paper's: contours per level with OA squares and US crosses (Figs. 3-4)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..scan.reconstruct import contour_order

STYLE = {"oa": ("s", "tab:red", "OA"), "us": ("x", "tab:blue", "US")}


def _outline(size_xy: tuple[float, float], pose: dict) -> np.ndarray:
    w, h = np.asarray(size_xy) / 2
    c = np.array([[-w, -h], [w, -h], [w, h], [-w, h], [-w, -h]])
    a = np.radians(pose["yaw_deg"])
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return c @ R.T + [pose["x_mm"], pose["y_mm"]]


def contour_figure(pts: dict, path: Path, size_xy: tuple[float, float] | None = None,
                   fits: dict | None = None, title: str = "") -> None:
    """PNG of object-frame points (cm, like the paper), one panel per level; fitted block
    outlines per modality when given, else lines between adjacent points."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    levels = sorted(set(np.concatenate([pts[m]["level"] for m in STYLE]).tolist())) or [0]
    fig, axes = plt.subplots(1, len(levels), figsize=(4.2 * len(levels), 4.2), squeeze=False)
    for ax, lvl in zip(axes[0], levels):
        for m, (marker, color, label) in STYLE.items():
            sel = pts[m]["level"] == lvl
            P = pts[m]["P"][sel] / 10.0
            if not len(P):
                continue
            ax.scatter(P[:, 0], P[:, 1], marker=marker, s=14, color=color, label=label,
                       facecolors="none" if marker == "s" else None, linewidths=0.8)
            if fits and m in fits and size_xy:
                o = _outline(size_xy, fits[m]["pose"]) / 10.0
                ax.plot(o[:, 0], o[:, 1], color=color, lw=1.0,
                        label=f"{label} fit, e={fits[m]['e_mean_mm']:.3f} mm")
            else:
                order = contour_order(P)
                ax.plot(P[order, 0], P[order, 1], color=color, lw=0.6)
        z = np.concatenate([pts[m]["P"][pts[m]["level"] == lvl][:, 2] for m in STYLE])
        ax.set_title(f"{title} level {lvl}" + (f" (z {np.median(z):.0f} mm)" if len(z) else ""))
        ax.set_xlabel("x (cm)")
        ax.set_ylabel("y (cm)")
        ax.set_aspect("equal")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
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
