"""The tactile heat map (matplotlib, Agg backend, imported on use)."""

from __future__ import annotations

import numpy as np

from .sensor import TactileFrame

__all__ = ["plot_frame"]


def plot_frame(frame: TactileFrame, path, title: str | None = None, truth=None) -> None:
    """Write a PNG heat map of the normal displacement (mm) over the lattice, contacts outlined
    (region boundary), centre marked, principal axes drawn as an ellipse, id and force written.

    ``truth``: optional sequence of ``(i, j)`` fractional lattice indices of true centres (drawn
    as crosses). matplotlib is imported here, with the Agg backend.
    """
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse
    from pathlib import Path

    d = frame.displacement * 1e3
    rows, cols = d.shape
    fig, ax = plt.subplots(figsize=(6.4, 5.4), dpi=110)
    vmax = max(float(np.max(np.abs(d))), 0.2)
    im = ax.imshow(d, origin="lower", cmap="magma", vmin=min(0.0, float(d.min())), vmax=vmax,
                   extent=(-0.5, cols - 0.5, -0.5, rows - 0.5), interpolation="bicubic")
    fig.colorbar(im, ax=ax, label="normal displacement into the foam (mm)")
    L = frame.estimate.link_length
    for c in frame.contacts:
        ax.contour(np.arange(cols), np.arange(rows), c.region.astype(float), levels=[0.5],
                   colors="cyan", linewidths=1.5)
        ax.plot(c.index[1], c.index[0], "o", color="cyan", ms=4)
        ax.add_patch(Ellipse((c.index[1], c.index[0]), 2 * c.axes_m[0] / L, 2 * c.axes_m[1] / L,
                             angle=90 - np.degrees(c.angle_rad), fill=False, color="white",
                             ls="--", lw=1))
        ax.annotate(f"#{c.id} {c.force_n:.2f} N", (c.index[1], c.index[0]),
                    xytext=(6, 6), textcoords="offset points", color="white", fontsize=8)
    for t in truth or ():
        ax.plot(t[1], t[0], "x", color="lime", ms=7, mew=2)
    ax.set_xlabel("j (link lengths)")
    ax.set_ylabel("i (link lengths)")
    ax.set_title(title or f"{len(frame.contacts)} contact(s), total "
                          f"{frame.total_force_n:.2f} N")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)
