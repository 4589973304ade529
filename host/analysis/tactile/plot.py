"""The tactile heat map (matplotlib, Agg backend, imported on use).

Every mark has a legend entry; the colour scale is fixed (a diverging map centred on zero, at least
``±min_scale_mm``), so an untouched sheet's noise stays pale instead of being stretched into
apparent contacts; the true contacts the virtual sheet knows are drawn over the detected ones;
footprints are ellipses of the principal half-axes (a round punch is a circle).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .sensor import TactileFrame

__all__ = ["plot_frame", "frame_figure", "TrueMark"]


@dataclass(frozen=True)
class TrueMark:
    """A true contact to overlay (from a virtual scene).

    Attributes
    ----------
    index : tuple of float
        Centre in fractional lattice indices ``(i, j)``.
    force_n : float
        N.
    axes_l : tuple of float, optional
        Footprint half-axes (major, minor), link lengths.
    angle_rad : float
        Major axis from the lattice's i direction, towards j.
    """

    index: tuple[float, float]
    force_n: float
    axes_l: tuple[float, float] | None = None
    angle_rad: float = 0.0


def frame_figure(frame: TactileFrame, title: str | None = None, truth=None,
                 min_scale_mm: float = 1.0):
    """The heat map of one frame as a matplotlib Figure (not saved, not closed).

    Parameters
    ----------
    frame : TactileFrame
    title : str, optional
        The run's parameters (body, noise, lattice, foam, time); the frame's count and total force
        are appended.
    truth : sequence of TrueMark or (i, j), optional
        True contacts (drawn as lime crosses, their footprints dashed).
    min_scale_mm : float
        The colour scale spans at least ``±min_scale_mm`` (default 1 mm), more if the frame's
        largest displacement is larger.
    """
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Ellipse

    d = frame.displacement * 1e3
    rows, cols = d.shape
    fig = Figure(figsize=(6.8, 5.8), dpi=110)
    ax = fig.add_subplot()
    vmax = max(float(np.max(np.abs(d))), float(min_scale_mm))
    im = ax.imshow(d, origin="lower", cmap="RdBu_r", vmin=-vmax, vmax=vmax,
                   extent=(-0.5, cols - 0.5, -0.5, rows - 0.5), interpolation="nearest")
    fig.colorbar(im, ax=ax, label="normal displacement into the foam (mm)")
    L = frame.estimate.link_length
    handles = []
    for c in frame.contacts:
        if c.region.any():
            ax.contour(np.arange(cols), np.arange(rows), c.region.astype(float), levels=[0.5],
                       colors="black", linewidths=1.2)
        ax.plot(c.index[1], c.index[0], "o", color="black", ms=4)
        ax.add_patch(Ellipse((c.index[1], c.index[0]), 2 * c.axes_m[0] / L, 2 * c.axes_m[1] / L,
                             angle=90 - np.degrees(c.angle_rad), fill=False, color="black",
                             ls="--", lw=1))
        ax.annotate(f"#{c.id} {c.force_n:.2f} N" + (" count?" if c.ambiguous else ""),
                    (c.index[1], c.index[0]), xytext=(6, 6), textcoords="offset points",
                    color="black", fontsize=8)
    if frame.contacts:
        handles += [Line2D([], [], color="black", lw=1.2, label="contact region"),
                    Line2D([], [], color="black", marker="o", ls="", ms=4,
                           label="contact centre (id, force)"),
                    Line2D([], [], color="black", ls="--", lw=1,
                           label="half-depth footprint (principal half-axes)")]
    marks = [t if isinstance(t, TrueMark) else TrueMark((float(t[0]), float(t[1])), float("nan"))
             for t in (truth or ())]
    for t in marks:
        ax.plot(t.index[1], t.index[0], "x", color="limegreen", ms=8, mew=2)
        if t.axes_l is not None:
            ax.add_patch(Ellipse((t.index[1], t.index[0]), 2 * t.axes_l[0], 2 * t.axes_l[1],
                                 angle=90 - np.degrees(t.angle_rad), fill=False,
                                 color="limegreen", ls=":", lw=1.5))
        if np.isfinite(t.force_n):
            ax.annotate(f"{t.force_n:.2f} N", (t.index[1], t.index[0]), xytext=(-6, -14),
                        textcoords="offset points", color="darkgreen", fontsize=8, ha="right")
    if marks:
        handles.append(Line2D([], [], color="limegreen", marker="x", ls="", ms=8, mew=2,
                              label="true contact (force)"))
        if any(t.axes_l is not None for t in marks):
            handles.append(Line2D([], [], color="limegreen", ls=":", lw=1.5,
                                  label="true footprint (Winkler contact)"))
    if handles:
        ax.legend(handles=handles, loc="upper left", fontsize=7, framealpha=0.85)
    ax.set_xlim(-0.5, cols - 0.5)
    ax.set_ylim(-0.5, rows - 0.5)
    ax.set_xticks(range(0, cols, 2))
    ax.set_yticks(range(0, rows, 2))
    ax.set_xlabel("joint j (link lengths)")
    ax.set_ylabel("joint i (link lengths)")
    summary = f"{len(frame.contacts)} contact(s), total {frame.total_force_n:.2f} N"
    ax.set_title(f"{title}\n{summary}" if title else summary, fontsize=9)
    fig.tight_layout()
    return fig


def plot_frame(frame: TactileFrame, path, title: str | None = None, truth=None,
               min_scale_mm: float = 1.0) -> None:
    """Write `frame_figure` as a PNG to ``path`` (parent folders created)."""
    from pathlib import Path

    fig = frame_figure(frame, title=title, truth=truth, min_scale_mm=min_scale_mm)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
