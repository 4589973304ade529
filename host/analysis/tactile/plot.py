"""Tactile figures (matplotlib, Agg backend, imported on use): one frame's heat map
(`frame_figure`), and estimated against true footprints and forces over bodies and indenters
(`footprint_figure`).

Every mark has a legend entry; the colour scale is fixed (a diverging map centred on zero, at least
``±min_scale_mm``), so an untouched sheet's noise is not stretched into apparent contacts; the
true contacts the virtual sheet knows are drawn over the detected ones; footprints are ellipses
of their principal half-axes (a round punch is a circle). Numbers (forces with their standard
deviations, footprints) go in a table beside the map, not onto it: labels on a map overlap each
other and vanish on dark cells.
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass

import numpy as np

from .sensor import TactileFrame

__all__ = ["plot_frame", "frame_figure", "TrueMark", "footprint_figure"]


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
        Footprint half-axes (major, minor), link lengths: the true dent's half-depth
        footprint (`virtual_sheet.foam.TrueFootprint.dent_axes_m`), the definition the
        detected contacts' ``axes_m`` follow.
    angle_rad : float
        Major axis from the lattice's i direction, towards j.
    """

    index: tuple[float, float]
    force_n: float
    axes_l: tuple[float, float] | None = None
    angle_rad: float = 0.0


def _ellipse(centre_ij, axes_l, angle_rad, **kw):
    """An `Ellipse` in the maps' coordinates (x = j, y = i): half-axes in link lengths, the
    major axis ``angle_rad`` from i towards j."""
    from matplotlib.patches import Ellipse
    return Ellipse((centre_ij[1], centre_ij[0]), 2 * axes_l[0], 2 * axes_l[1],
                   angle=90 - np.degrees(angle_rad), fill=False, **kw)


def _clear_corner(ax, n_lines: int) -> tuple[float, float]:
    """The corner of a footprint panel (axes fraction) for a box of ``n_lines`` lines that
    covers the fewest points of the panel's ellipses: lower left unless something is there
    (a pair's lower finger reached into it). The box's size is a generous estimate (7.5 pt
    text, 3-inch panels); the test measures the drawn one."""
    xlim, ylim = ax.get_xlim(), ax.get_ylim()
    pts = [p.get_path().transformed(p.get_patch_transform()).vertices for p in ax.patches]
    if not pts:
        return 0.03, 0.03
    xy = np.vstack(pts)
    fx = (xy[:, 0] - xlim[0]) / (xlim[1] - xlim[0])
    fy = (xy[:, 1] - ylim[0]) / (ylim[1] - ylim[0])
    w, h = 0.5, 0.06 * n_lines + 0.04
    best, where = None, (0.03, 0.03)
    for cx, cy in ((0.03, 0.03), (0.97, 0.03), (0.03, 0.97), (0.97, 0.97)):
        x0 = cx if cx < 0.5 else cx - w
        y0 = cy if cy < 0.5 else cy - h
        hits = int(np.sum((fx >= x0) & (fx <= x0 + w) & (fy >= y0) & (fy <= y0 + h)))
        if best is None or hits < best:
            best, where = hits, (cx, cy)
    return where


def _wrap_items(part: str, width: int) -> list[str]:
    """``part`` in lines of at most ``width`` characters, broken after its commas (a value and
    its unit stay together: "noise 0.3 %" / "g" was one such cut); an item longer than
    ``width`` alone is wrapped at its spaces."""
    lines: list[str] = []
    for item in part.split(", "):
        if lines and len(lines[-1]) + 2 + len(item) <= width:
            lines[-1] += ", " + item
        elif lines:
            lines[-1] += ","
            lines.extend(textwrap.wrap(item, width) or [""])
        else:
            lines.extend(textwrap.wrap(item, width) or [""])
    return lines


def _contact_line(c, L: float) -> str:
    ax = 2e3 * np.asarray(c.axes_m)
    line = (f"#{c.id}: {c.force_n:.2f} ± {c.force_std_n:.2f} N, footprint "
            f"{ax[0]:.0f} × {ax[1]:.0f} mm")
    if np.isfinite(c.angle_std_rad) and c.angle_std_rad < np.pi / 6:
        line += f" at {np.degrees(c.angle_rad):+.0f}°"
    return line + ("  (count uncertain)" if c.ambiguous else "")


def frame_figure(frame: TactileFrame, title: str | None = None, truth=None,
                 min_scale_mm: float = 1.0):
    """The heat map of one frame as a matplotlib Figure (not saved, not closed).

    Parameters
    ----------
    frame : TactileFrame
    title : str, optional
        The run's parameters (body, noise, lattice, foam, time); the frame's count and total force
        are appended. Wrapped to the figure's width.
    truth : sequence of TrueMark or (i, j), optional
        True contacts (drawn as lime crosses, their footprints dotted).
    min_scale_mm : float
        The colour scale spans at least ``±min_scale_mm`` (default 1 mm), more if the frame's
        largest displacement is larger.
    """
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    d = frame.displacement * 1e3
    rows, cols = d.shape
    n_lines = len(frame.contacts) + (1 if truth else 0)
    fig = Figure(figsize=(7.6, 6.9 + 0.16 * n_lines), dpi=110, layout="constrained")
    gs = fig.add_gridspec(2, 1, height_ratios=[6.0, 0.25 + 0.16 * max(n_lines, 1)])
    ax = fig.add_subplot(gs[0])
    vmax = max(float(np.max(np.abs(d))), float(min_scale_mm))
    im = ax.imshow(d, origin="lower", cmap="RdBu_r", vmin=-vmax, vmax=vmax,
                   extent=(-0.5, cols - 0.5, -0.5, rows - 0.5), interpolation="nearest")
    fig.colorbar(im, ax=ax, label="normal displacement into the foam (mm)", shrink=0.9)
    L = frame.estimate.link_length
    handles = []
    for c in frame.contacts:
        if c.region.any():
            ax.contour(np.arange(cols), np.arange(rows), c.region.astype(float), levels=[0.5],
                       colors="black", linewidths=1.0)
        # a ring, above the true cross: a centre on its true contact stays visible around the cross
        ax.plot(c.index[1], c.index[0], "o", mfc="none", mec="black", ms=7, mew=1.6, zorder=4)
        ax.add_patch(_ellipse(c.index, np.asarray(c.axes_m) / L, c.angle_rad, color="black",
                              ls="--", lw=1.2))
        # the id beside the footprint, on a white box (readable on any cell)
        r = float(np.max(c.axes_m)) / L
        ax.annotate(f"#{c.id}", (c.index[1] + 0.7 * r, c.index[0] + 0.7 * r), fontsize=8,
                    ha="left", va="bottom", color="black",
                    bbox=dict(boxstyle="round,pad=0.15", fc="white", ec="none", alpha=0.85))
    if frame.contacts:
        handles += [Line2D([], [], color="black", lw=1.0, label="contact region"),
                    Line2D([], [], marker="o", mfc="none", mec="black", ls="", ms=7, mew=1.6,
                           label="contact centre (#id)"),
                    Line2D([], [], color="black", ls="--", lw=1.2,
                           label="half-depth footprint")]
    marks = [t if isinstance(t, TrueMark) else TrueMark((float(t[0]), float(t[1])), float("nan"))
             for t in (truth or ())]
    for t in marks:
        ax.plot(t.index[1], t.index[0], "x", color="limegreen", ms=8, mew=2, zorder=3)
        if t.axes_l is not None:
            ax.add_patch(_ellipse(t.index, t.axes_l, t.angle_rad, color="limegreen", ls=":",
                                  lw=1.8))
    if marks:
        handles.append(Line2D([], [], color="limegreen", marker="x", ls="", ms=8, mew=2,
                              label="true contact"))
        if any(t.axes_l is not None for t in marks):
            handles.append(Line2D([], [], color="limegreen", ls=":", lw=1.8,
                                  label="true half-depth footprint"))
    if handles:
        ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.09), ncol=3,
                  fontsize=7, frameon=False)
    ax.set_xlim(-0.5, cols - 0.5)
    ax.set_ylim(-0.5, rows - 0.5)
    ax.set_xticks(range(0, cols, 2))
    ax.set_yticks(range(0, rows, 2))
    ax.set_xlabel("joint j (link lengths)")
    ax.set_ylabel("joint i (link lengths)")
    summary = f"{len(frame.contacts)} contact(s), total {frame.total_force_n:.2f} N"
    # the title's parts on lines of their own (never cut inside one), wrapped if still long
    head = "".join("\n".join(_wrap_items(part, 70)) + "\n"
                   for part in title.split("; ")) if title else ""
    ax.set_title(head + summary, fontsize=9)
    # the numbers: one line per contact, and the truth's forces
    tx = fig.add_subplot(gs[1])
    tx.axis("off")
    lines = [_contact_line(c, L) for c in frame.contacts] or ["no contact"]
    forces = [f"{t.force_n:.2f} N" for t in marks if np.isfinite(t.force_n)]
    if forces:
        lines.append("true: " + ", ".join(forces))
    tx.text(0.1, 1.0, "\n".join(lines), va="top", ha="left", fontsize=8, family="monospace",
            transform=tx.transAxes)
    return fig


def plot_frame(frame: TactileFrame, path, title: str | None = None, truth=None,
               min_scale_mm: float = 1.0) -> None:
    """Write `frame_figure` as a PNG to ``path`` (parent folders created)."""
    from pathlib import Path

    fig = frame_figure(frame, title=title, truth=truth, min_scale_mm=min_scale_mm)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


#: Indenters in `footprint_figure`'s columns, and how their column is headed.
_KIND_TITLE = {"sphere": "sphere R 15 mm, 2 N", "punch": "flat punch a 7.5 mm, 2 N",
               "capsule": "finger (capsule R 10 mm, 4 cm), 3 N"}
_KIND_MARK = {"sphere": "o", "punch": "s", "capsule": "D"}


def _column_title(kind: str, sep) -> str:
    if sep is None:
        return _KIND_TITLE[kind]
    name = "two fingers" if kind == "capsule" else f"two {kind}s"
    return f"{name} {sep:g} L apart"


def footprint_figure(cases, path, link_length: float, zoom_l: float = 3.5):
    """Estimated against true footprints and forces, every body and indenter: a grid of panels
    (rows: bodies; columns: indenters, single and in pairs) showing one placement's half-depth
    footprint and contact patch, estimated (black) and true (green), over the lattice; and per
    body the force error of every placement with its ±1 standard deviation. Saved to ``path``
    (PNG); returns the Figure.

    Parameters
    ----------
    cases : sequence of tuple
        ``(body, indenter, separation, placement, frame, truth, truth_index, footprints)``:
        `TactileFrame` of the placement's last snapshot, the scene's `TrueContact` s, their
        lattice indices, its `TrueFootprint` s (``benchmarks/bench_tactile.py --figure``).
    link_length : float
        ``L``, metres.
    zoom_l : float
        Half-width of a footprint panel, link lengths (one more for a pair).
    """
    import matplotlib
    matplotlib.use("Agg")
    from pathlib import Path

    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from scipy.optimize import linear_sum_assignment

    L = float(link_length)
    bodies = list(dict.fromkeys(c[0] for c in cases))
    columns = list(dict.fromkeys((c[1], c[2]) for c in cases))
    columns.sort(key=lambda kc: (kc[1] is not None, list(_KIND_TITLE).index(kc[0])))
    fig = Figure(figsize=(3.0 * (len(columns) + 1), 3.0 * len(bodies) + 1.0), dpi=110,
                 layout="constrained")
    axes = fig.subplots(len(bodies), len(columns) + 1, squeeze=False)
    for r, body in enumerate(bodies):
        errors = []
        for col, (kind, sep) in enumerate(columns):
            ax = axes[r, col]
            mine = [c for c in cases if c[0] == body and c[1] == kind and c[2] == sep]
            if not mine:
                ax.axis("off")
                continue
            _, _, _, _, fr, truth, idx, fps = mine[0]
            rows, cols = fr.displacement.shape
            jj, ii = np.meshgrid(np.arange(cols), np.arange(rows))
            ax.plot(jj.ravel(), ii.ravel(), ".", color="0.75", ms=2.5, zorder=0)
            for t, ti, fp in zip(truth, idx, fps):
                ax.add_patch(_ellipse(ti, np.array(fp.dent_axes_m) / L, fp.dent_angle_rad,
                                      color="tab:green", lw=2.0))
                ax.add_patch(_ellipse(ti, np.array(fp.pressure_axes_m) / L,
                                      fp.pressure_angle_rad, color="tab:green", lw=1.2,
                                      ls=":"))
                ax.plot(ti[1], ti[0], "+", color="tab:green", ms=9, mew=1.5)
            lines = []
            for c in fr.contacts:
                ax.add_patch(_ellipse(c.index, np.asarray(c.axes_m) / L, c.angle_rad,
                                      color="black", lw=1.4, ls="--"))
                ax.add_patch(_ellipse(c.index, np.asarray(c.contact_axes_m) / L, c.angle_rad,
                                      color="black", lw=1.0, ls=":"))
                ax.plot(c.index[1], c.index[0], "x", color="black", ms=6)
                lines.append(f"{c.force_n:.2f} ± {c.force_std_n:.2f} N")
            lines.append("true " + ", ".join(f"{t.force_n:.2f} N" for t in truth))
            ci = np.mean(idx, axis=0)
            z = zoom_l + (0.0 if sep is None else 1.0)     # a pair: room for the box
            ax.set_xlim(ci[1] - z, ci[1] + z)
            ax.set_ylim(ci[0] - z, ci[0] + z)
            fx, fy = _clear_corner(ax, len(lines))
            ax.text(fx, fy, "\n".join(lines), transform=ax.transAxes, fontsize=7.5,
                    va="bottom" if fy < 0.5 else "top", ha="left" if fx < 0.5 else "right",
                    bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="0.8", alpha=0.9))
            ax.set_aspect("equal")
            if r == 0:
                ax.set_title(_column_title(kind, sep), fontsize=9)
            if col == 0:
                ax.set_ylabel(f"{body}\njoint i (link lengths)", fontsize=9)
            if r == len(bodies) - 1:
                ax.set_xlabel("joint j (link lengths)", fontsize=9)
            # every placement's force errors, with the stated standard deviation
            for c in mine:
                fr, truth = c[4], c[5]
                if len(fr.contacts) != len(truth):
                    continue
                D = np.linalg.norm(np.array([x.index for x in fr.contacts])[:, None]
                                   - np.array(c[6])[None], axis=2)
                for a, b in zip(*linear_sum_assignment(D)):
                    e = fr.contacts[a]
                    errors.append((col, 100 * (e.force_n / truth[b].force_n - 1),
                                   100 * e.force_std_n / truth[b].force_n, kind))
        ax = axes[r, -1]
        ax.axhspan(-15, 15, color="tab:green", alpha=0.12, lw=0)
        ax.axhline(0, color="tab:green", lw=1)
        for n, (col, err, std, kind) in enumerate(errors):
            x = col + 0.12 * ((n % 5) - 2)
            ax.errorbar(x, err, yerr=std, marker=_KIND_MARK[kind], color="black", ms=4,
                        capsize=2, lw=0.8, ls="none", mfc="white")
        lim = max(20.0, 1.15 * max((abs(e) + s for _, e, s, _ in errors), default=0.0))
        ax.set_ylim(-lim, lim)
        ax.set_xlim(-0.6, len(columns) - 0.4)
        ax.set_xticks(range(len(columns)))
        ax.set_xticklabels([("finger" if k == "capsule" else k) + ("" if s is None else
                                                                  f"\n{s:g} L")
                            for k, s in columns], fontsize=8)
        ax.set_ylabel("force error (% of true)", fontsize=9)
        if r == 0:
            ax.set_title("force, every placement (±1 std)", fontsize=9)
    handles = [Line2D([], [], color="tab:green", lw=2.0, label="true half-depth footprint"),
               Line2D([], [], color="tab:green", lw=1.2, ls=":", label="true contact patch"),
               Line2D([], [], color="black", lw=1.4, ls="--",
                      label="estimated half-depth footprint"),
               Line2D([], [], color="black", lw=1.0, ls=":", label="estimated contact patch"),
               Line2D([], [], color="0.75", marker=".", ls="", label="joints"),
               Line2D([], [], color="tab:green", lw=6, alpha=0.25, label="±15 % (the target)")]
    fig.legend(handles=handles, loc="outside lower center", ncol=6, fontsize=8, frameon=False)
    fig.suptitle("Estimated against true footprints and forces (14x14, L = 1 cm, foam h 20 mm, "
                 "E 20 kPa, 1 % g; the last snapshot of each placement)", fontsize=10)
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return fig
