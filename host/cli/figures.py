"""Figures fit for a paper: the demo's, the paper's Fig. 8 (solvability), Fig. 9 (Gaussian) and
Fig. 10 (noise), and an offline run's (``capsheet estimate --png``).

Conventions: lengths in cm (a 1 cm-link sheet; the unit is in every axis label); errors in % of the
side length ``(cols - 1) L`` after the rigid overlay (`host.analysis.metrics`) — Fig. 10 as the
paper draws it, mean and standard deviation on a linear axis with its 5 % failure line; the run's
parameters (shape, lattice, noise, rate, seed) in the title; a legend entry for every mark. Each function draws, saves ``path`` (PNG) and
returns the `matplotlib.figure.Figure` (close it with ``plt.close(fig)``), so a test can check
what is drawn.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["demo_figure", "gaussian_figure", "noise_figure", "solvability_figure", "estimate_run_figure",
           "misfit_pct_of_link", "motion_scenes_figure", "imu_stream_figure", "ERROR_FLOOR_PCT"]

#: errors below this (% of side) are drawn at it on log axes (a noise-free estimate is exact to
#: ~1e-12 %); the caption says so
ERROR_FLOOR_PCT = 1e-6
CM = 100.0


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def _save(fig, path) -> None:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)


def _equal_box(ax, P_cm: np.ndarray) -> None:
    """Equal scales on x, y, z (a flat sheet keeps a visible z range: at least 1/4 of the widest),
    zoomed out so the axis labels stay inside the panel; at most 5 ticks per axis."""
    from matplotlib.ticker import MaxNLocator

    lo, hi = P_cm.reshape(-1, 3).min(0), P_cm.reshape(-1, 3).max(0)
    ext = np.maximum(hi - lo, 1e-9)
    need = 0.25 * ext.max()
    if ext[2] < need:
        mid = 0.5 * (lo[2] + hi[2])
        ax.set_zlim(mid - need / 2, mid + need / 2)
        ext = np.array([ext[0], ext[1], need])
    ax.set_box_aspect(ext, zoom=0.82)
    for axis in (ax.xaxis, ax.yaxis):
        axis.set_major_locator(MaxNLocator(5))
    # the z box is the flattest: fewer ticks, or their labels crowd each other and "z [cm]"
    ax.zaxis.set_major_locator(MaxNLocator(5 if ext[2] >= 0.6 * ext.max() else 3))


def _wire(ax, P_cm, **kw):
    return ax.plot_wireframe(P_cm[..., 0], P_cm[..., 1], P_cm[..., 2], **kw)


def _labels_cm(ax) -> None:
    ax.set_xlabel("x [cm]", labelpad=7)
    ax.set_ylabel("y [cm]", labelpad=7)
    ax.set_zlabel("z [cm]", labelpad=2)


def demo_figure(path, truth: np.ndarray, est: np.ndarray, err_pct: np.ndarray, *, shape: str, noise_pct_g: float,
                rate_hz: float, run_mean_error_pct: float, counter: int, link_length: float,
                sensors: str = "accel", failed: str | None = None, compared: int | None = None):
    """The demo's figure: truth; estimate (overlaid) drawn over the truth; per-joint error map.

    Parameters
    ----------
    truth, est : ndarray, shape (rows, cols, 3), metres
        The virtual truth and the estimate (not yet overlaid) of snapshot ``counter``.
    err_pct : ndarray, shape (rows, cols)
        That snapshot's joint error, % of side.
    run_mean_error_pct : float
        The run's summary figure (mean over the compared snapshots), shown in the title.
    sensors : str
        The chips' sensors (``--sensors``): 6/9-axis chips are named in the title with the fused
        estimator that used them.
    failed : str, optional
        Why the run failed (the demo's verdict): the figure is marked FAIL with it, in red.
    compared : int, optional
        How many snapshots the run's mean is over (named in the title).
    """
    plt = _plt()
    from host.analysis.metrics import overlay

    rows, cols = truth.shape[:2]
    T, A = truth * CM, overlay(est, truth) * CM
    fig = plt.figure(figsize=(16, 5.4))
    gs = fig.add_gridspec(1, 3, width_ratios=(1.0, 1.0, 0.85), left=0.01, right=0.96, bottom=0.1,
                          top=0.76 if failed else 0.8,
                          wspace=0.28)
    ax = fig.add_subplot(gs[0], projection="3d")
    _wire(ax, T, color="C0", lw=0.8, label="virtual truth")
    ax.set_title("virtual truth")
    _labels_cm(ax)
    _equal_box(ax, T)
    ax.legend(loc="upper left", fontsize=8)
    ax = fig.add_subplot(gs[1], projection="3d")
    _wire(ax, T, color="0.65", lw=0.6, label="virtual truth")
    _wire(ax, A, color="C3", lw=0.9, label="estimate (overlaid)")
    ax.set_title("estimate (overlaid) over the truth")
    _labels_cm(ax)
    _equal_box(ax, T)
    ax.legend(loc="upper left", fontsize=8)
    ax = fig.add_subplot(gs[2])
    im = ax.imshow(err_pct, origin="lower", cmap="viridis", extent=(-0.5, cols - 0.5, -0.5, rows - 0.5))
    step = max(1, int(np.ceil(max(rows, cols) / 7)))
    ax.set_xticks(np.arange(0, cols, step))
    ax.set_yticks(np.arange(0, rows, step))
    ax.set_xlabel("joint j")
    ax.set_ylabel("joint i")
    ax.set_title(f"joint error, this snapshot only\n(counter {counter}): mean {float(np.mean(err_pct)):.2f} %",
                 fontsize=10)
    fig.colorbar(im, ax=ax, shrink=0.85, label="error [% of side]")
    chips = "" if sensors == "accel" else f"{sensors} chips (fused estimator), "
    over = "" if compared is None else f" over {compared} snapshots"
    title = (f"capsheet demo: {rows}x{cols} joints, L = {link_length * CM:g} cm, '{shape}', {chips}"
             f"{noise_pct_g:g} % g noise, {rate_hz:g} Hz\nrun mean error {run_mean_error_pct:.2f} % of side{over}; "
             f"the panels show the last snapshot compared (counter {counter})")
    if failed:
        fig.suptitle(f"FAIL: {failed}\n{title}", color="red", fontsize=11)
    else:
        fig.suptitle(title, fontsize=11)
    _save(fig, path)
    return fig


def gaussian_figure(path, truth: np.ndarray, estimates: dict, errors_pct: dict, *, shape: str,
                    noise_pct_g: float, seed: int, link_length: float, caption: str | None = None):
    """Fig. 9: the model and each method's estimate, overlaid on the model, in cm.

    ``estimates``: method -> joints (rows, cols, 3) m (not yet overlaid); ``errors_pct``: method ->
    mean joint error, % of side; ``caption``: text under the panels (the paper's description of
    its figure beside what is drawn here).
    """
    plt = _plt()
    from host.analysis.metrics import overlay

    rows, cols = truth.shape[:2]
    T = truth * CM
    fig = plt.figure(figsize=(5.2 * (1 + len(estimates)), 5.9 if caption else 5.2))
    fig.subplots_adjust(left=0.01, right=0.97, bottom=0.16 if caption else 0.05, top=0.86,
                        wspace=0.12)
    ax = fig.add_subplot(1, 1 + len(estimates), 1, projection="3d")
    _wire(ax, T, color="C0", lw=0.8, label="model (truth)")
    ax.set_title("model (truth)")
    _labels_cm(ax)
    _equal_box(ax, T)
    ax.legend(loc="upper left", fontsize=8)
    for k, (m, J) in enumerate(estimates.items()):
        ax = fig.add_subplot(1, 1 + len(estimates), k + 2, projection="3d")
        _wire(ax, T, color="0.7", lw=0.5, label="model (truth)")
        _wire(ax, overlay(J, truth) * CM, color=f"C{k + 1}", lw=0.8, label=f"{m} estimate (overlaid)")
        ax.set_title(f"{m}: mean error {errors_pct[m]:.2f} % of side")
        _labels_cm(ax)
        _equal_box(ax, T)
        ax.legend(loc="upper left", fontsize=8)
    fig.suptitle(f"Fig. 9: '{shape}', {rows}x{cols} joints, L = {link_length * CM:g} cm, "
                 f"{noise_pct_g:g} % g noise, seed {seed}")
    if caption:
        import textwrap
        fig.text(0.02, 0.02, "\n".join(textwrap.fill(p, 150) for p in caption.split("\n")),
                 fontsize=8, va="bottom", ha="left")
    _save(fig, path)
    return fig


def _noise_label(method: str) -> str:
    """How Fig. 10's legend names a method of `host.cli.paper.METHODS`: "global" is `estimate`
    with its defaults, so its legend says so and names the default prior."""
    if method == "paper":
        return "paper's method"
    if method == "global":
        from host.analysis.estimator.priors import DEFAULT_PRIOR
        return f"capsheet default (global, prior {DEFAULT_PRIOR!r})"
    return method


def noise_figure(path, results: dict, methods, *, trials: int, seed: int, side_joints: int,
                 noise_dist: str = "normal", failure_line_pct: float = 5.0):
    """Fig. 10, as the paper draws it: per target, the mean joint error (dots) and its standard
    deviation (bars) against the noise, both methods, the paper's failure line; under it the
    target's units' λ3/λ1 (eq. 7, noise-free), the reason a method cannot see some of them.

    ``results``: target name -> ``{"rows": host.cli.paper.noise_study output, "solvability":
    {"map": (R-1, C-1) list, "below_0_1": int, "units": int}, "works_up_to_pct_g": {method:
    level or None}}``.
    """
    plt = _plt()
    names = list(results)
    vmax = max(0.5, *(float(np.max(results[n]["solvability"]["map"])) for n in names))
    fig, axes = plt.subplots(2, len(names), figsize=(6.4 * len(names), 9.2), squeeze=False,
                             height_ratios=(1.25, 1.0), layout="constrained")
    for c, name in enumerate(names):
        res = results[name]
        ax = axes[0, c]
        rows = res["rows"]
        x = np.array([r["noise_pct_g"] for r in rows], dtype=float)
        dx = 0.12 * max(1.0, float(np.ptp(x)) / 10)
        for k, m in enumerate(methods):
            mean = np.array([r[m]["mean_pct"] for r in rows])
            std = np.array([r[m]["std_pct"] for r in rows])
            xs = x + (k - (len(methods) - 1) / 2) * dx
            label = _noise_label(m)
            ax.errorbar(xs, mean, yerr=std, fmt="o", ms=4, capsize=3, color=f"C{k}",
                        label=f"{label}: mean ± std")
        ax.axhline(failure_line_pct, color="C3", linestyle="--", linewidth=1.0,
                   label=f"paper's failure line ({failure_line_pct:g} % of side)")
        top = max(float(r[m]["mean_pct"] + r[m]["std_pct"]) for r in rows for m in methods)
        ax.set_ylim(0, max(1.5 * failure_line_pct, 1.08 * top))  # room for the legend above the line
        ax.set_xlabel(f"noise [% g, {noise_dist}, per component]")
        ax.set_ylabel("joint error [% of side]")
        upto = res.get("works_up_to_pct_g", {}).get("paper")
        ax.set_title(f"'{name}': paper's method under the line up to "
                     + ("no level" if upto is None else f"{upto:g} % g"), fontsize=10)
        ax.legend(fontsize=8, loc="upper left")
        ax = axes[1, c]
        sv = np.asarray(res["solvability"]["map"], dtype=float)
        im = ax.imshow(sv, origin="lower", cmap="viridis", vmin=0.0, vmax=vmax,
                       extent=(-0.5, sv.shape[1] - 0.5, -0.5, sv.shape[0] - 0.5))
        bi, bj = np.nonzero(sv < 0.1)
        ax.plot(bj, bi, "x", color="C3", ms=7, mew=1.5, label="λ3/λ1 < 0.1 (unsolvable, Fig. 8)")
        ax.set_xticks(np.arange(0, sv.shape[1], 2))
        ax.set_yticks(np.arange(0, sv.shape[0], 2))
        ax.set_xlabel("unit j")
        ax.set_ylabel("unit i")
        ax.set_title(f"units' λ3/λ1 of eq. (7), noise-free: {res['solvability']['below_0_1']} of "
                     f"{res['solvability']['units']} below 0.1", fontsize=10)
        ax.legend(fontsize=8, loc="upper right")
        fig.colorbar(im, ax=ax, shrink=0.9, label="λ3/λ1")
    sep = "; " if len(names) > 1 else "\n"  # one column: two lines, or the title is clipped
    fig.suptitle(f"Fig. 10 reproduced: {side_joints}x{side_joints} joints, {side_joints ** 2} joints "
                 f"x {trials} trials per level, seed {seed}{sep}both methods on the same draws")
    _save(fig, path)
    return fig


def solvability_figure(path, res: dict, groups, cases):
    """Fig. 8: the unit states each criterion flags, in (θf, θr, θp), coloured by the paper's
    case; Case 2 is counted, not drawn (θc ∈ {0, π} alone fills the cube once θc is projected
    out); every legend count is a count of grid states, as the table's.

    ``res``: `host.cli.paper.solvability_grid` output; ``groups``: ``CASE_GROUPS``;
    ``cases``: the partition function ``(points, steps) -> masks``.
    """
    plt = _plt()
    steps = res["steps"]
    short = {"case2": "Case 2", "case1": "Case 1", "near_case2": "near Case 2",
             "near_case1": "near Case 1", "vertical": "θp = π/2", "other": "elsewhere"}
    colour = {"case1": "C0", "near_case1": "C9", "near_case2": "C1", "vertical": "C2",
              "other": "C3"}
    fig = plt.figure(figsize=(13, 7.6))
    fig.subplots_adjust(left=0.0, right=0.97, bottom=0.2, top=0.88, wspace=0.06)
    panels = ((res["points"], res["eq7"], "λ3/λ1 < 0.1 (eq. 7, the paper's criterion)"),
              (res["points_yaw"], res["yaw_std"],
               f"yaw std > {res['yaw_gain_limit']:.0f} (10 × the median unit; estimator's "
               "normal matrix)"))
    for k, (pts, counts, title) in enumerate(panels):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        masks = cases(pts, steps) if len(pts) else {}
        for key, _ in groups:
            if key == "case2":
                ax.scatter([], [], [], s=0, label=f"Case 2 ({counts['case2']:,}): not drawn")
                continue
            sel = masks.get(key, np.zeros(0, bool))
            big = key == "case1"  # a handful of states in the corners: drawn larger
            ax.scatter(pts[sel, 1], pts[sel, 2], pts[sel, 3], s=40 if big else 9,
                       marker="*" if big else "o", color=colour[key], depthshade=False,
                       zorder=3 if big else 2, label=f"{short[key]} ({counts[key]:,})")
        ax.set_xlim(0, np.pi)
        ax.set_ylim(0, np.pi)
        ax.set_zlim(0, np.pi / 2)
        for axis, top in ((ax.xaxis, 1.0), (ax.yaxis, 1.0), (ax.zaxis, 0.5)):
            ticks = np.array([0.0, 0.25, 0.5, 0.75, 1.0]) * top
            axis.set_ticks(np.pi * ticks)
            axis.set_ticklabels(["0", "π/4", "π/2", "3π/4", "π"][:len(ticks)] if top == 1.0
                                else ["0", "π/8", "π/4", "3π/8", "π/2"])
        ax.set_xlabel("fold θf [rad]")
        ax.set_ylabel("roll θr [rad]")
        ax.set_zlabel("pitch θp [rad]")
        ax.set_title(f"{title}\n{counts['flagged']:,} of {res['n_total']:,} states flagged",
                     fontsize=10)
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.02), ncol=3, fontsize=8,
                  title="grid states per group (as the table)", title_fontsize=8)
    fig.suptitle("Fig. 8: unsolvable states of one unit (corner θc, fold θf, roll θr, pitch θp)")
    fig.text(0.02, 0.02,
             "θc is projected out: a dot is a (θf, θr, θp) flagged at one or more corner angles "
             f"θc ({steps} values in [0, π]); the counts are grid states. Case 2 (θc = 0 or π, "
             "or θf = π) is counted but not drawn:\nits θc ends would fill the whole cube. "
             "Groups as the table's (a state in the first group it belongs to); 'near': within "
             "one grid step.", fontsize=8, va="bottom")
    _save(fig, path)
    return fig


def misfit_pct_of_link(residual: np.ndarray, valid: np.ndarray, lattice) -> np.ndarray:
    """eq. (8)'s residual per snapshot as a figure a reader can picture: the RMS misfit of one unit
    (its loop closure, in link lengths, and its normal assumption, in unit normals), in % — a
    closure gap of 1 % of L per unit reads 1. ``residual`` sums over the units with four valid links
    (`host.analysis.estimator.ShapeEstimate.residual`); ``valid`` (n, n_links) counts them."""
    units = np.asarray(lattice.units).reshape(-1, 4)
    n_units = np.asarray(valid, dtype=bool)[:, units].all(axis=2).sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return 100.0 * np.sqrt(np.asarray(residual, dtype=float) / np.where(n_units > 0, n_units, np.nan))


def _readable_y(ax, y: np.ndarray) -> None:
    """A linear axis when the values span less than a decade and a half, else a log axis with ticks
    at 1, 2 and 5 of every decade written as plain numbers (a log axis had two labels, 2e-1 and
    4e-1, in mathtext)."""
    from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator

    y = y[np.isfinite(y) & (y > 0)]
    if y.size and y.max() / y.min() > 30:
        ax.set_yscale("log")
        ax.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax.yaxis.set_minor_locator(LogLocator(base=10, subs="auto"))
        ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _pos: f"{v:g}"))
    else:
        ax.set_ylim(0, 1.1 * float(y.max()) if y.size else 1.0)
        ax.yaxis.set_major_locator(MaxNLocator(6))


def estimate_run_figure(path, t_s: np.ndarray, residual: np.ndarray, valid: np.ndarray, joints: np.ndarray,
                        lattice, link_length: float, *, title: str, gyro: np.ndarray | None = None,
                        fused: dict | None = None):
    """An offline run: eq. (8)'s misfit per unit (`misfit_pct_of_link`, %) and the valid links (%)
    over time, and the last estimated shape (cm).

    A recording of 6/9-axis chips adds a row: ``gyro`` (n, n_links, 3) rad/s — the three axes of the
    link that turned most (largest RMS rate) and, per snapshot, the fastest link's rate, °/s — and
    ``fused`` (the fused estimator's own figures per snapshot, `host.cli.estimate.estimate_fused_batch`):
    the RMS of its gyroscope-bias estimate over the links (°/s), the acceleration common to all links
    (m/s², the sheet's translation), and with magnetometers their mean weight and whether the heading
    is absolute."""
    from matplotlib.ticker import MaxNLocator

    plt = _plt()
    imu = gyro is not None
    fig = plt.figure(figsize=(13, 8.6 if imu else 4.6), layout="constrained")
    ax = fig.add_subplot(2 if imu else 1, 2, 1)
    misfit = misfit_pct_of_link(residual, valid, lattice)
    ok = np.isfinite(misfit)
    ax.plot(t_s[ok], misfit[ok], ".", ms=2, color="C0", label="eq. (8) misfit per unit, RMS")
    _readable_y(ax, misfit[ok])
    ax.set_xlabel("time [s]")
    ax.set_ylabel("misfit per unit, RMS [% of a link length]")
    ax2 = ax.twinx()
    ax2.plot(t_s, 100 * np.asarray(valid).mean(axis=1), "-", lw=0.8, color="C1", label="links valid")
    ax2.set_ylabel("links valid [%]")
    ax2.set_ylim(0, 105)
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=8, loc="lower left")
    ax.set_title("per snapshot: loop closure and normal assumption (eq. 8), links valid")
    if imu:
        _gyro_panels(fig, t_s, np.asarray(gyro, dtype=float), np.asarray(valid, dtype=bool), fused)
    ax = fig.add_subplot(2 if imu else 1, 2, 2, projection="3d")
    last = np.flatnonzero(np.isfinite(residual))
    if last.size:
        P = joints[last[-1]] * CM
        _wire(ax, P, color="C3", lw=0.8, label=f"estimate, snapshot {int(last[-1])}")
        _equal_box(ax, P)
        ax.zaxis.set_major_locator(MaxNLocator(3))  # a flat box: 3 z labels do not collide
        ax.legend(loc="upper left", fontsize=8)
    _labels_cm(ax)
    for axis in (ax.xaxis, ax.yaxis):
        axis.labelpad = 8  # clear of the tick labels
    ax.set_title("last estimated shape")
    fig.suptitle(title)
    _save(fig, path)
    return fig


def _gyro_panels(fig, t_s: np.ndarray, gyro: np.ndarray, valid: np.ndarray, fused: dict | None) -> None:
    """`estimate_run_figure`'s second row: the gyroscopes, and the fused estimator's own figures."""
    g = np.where(valid[:, :, None], np.degrees(gyro), np.nan)  # °/s, links not in the snapshot NaN
    rate = np.linalg.norm(g, axis=2)  # (n, n_links)
    with np.errstate(all="ignore"):
        rms = np.sqrt(np.nanmean(rate ** 2, axis=0))
    ax = fig.add_subplot(2, 2, 3)
    if np.isfinite(rms).any():
        k = int(np.nanargmax(rms))
        for a, name in enumerate("xyz"):
            ax.plot(t_s, g[:, k, a], "-", lw=0.8, color=f"C{a}", label=f"link {k}, {name}")
        fastest = np.where(np.isfinite(rate).any(axis=1), np.nanmax(np.where(np.isfinite(rate), rate, -np.inf),
                                                                      axis=1), np.nan)
        ax.plot(t_s, fastest, "-", lw=0.6, color="0.5", label="fastest link's |ω|, per snapshot")
        lo, hi = ax.get_ylim()
        ax.set_ylim(lo - 0.3 * (hi - lo), hi)  # a free band below the curves for the legend
        ax.legend(fontsize=8, loc="lower left", ncol=4)
    ax.axhline(0.0, color="0.8", lw=0.5)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("angular rate [°/s]")
    ax.set_title("gyroscopes: the link that turned most (largest RMS rate), axes; the fastest link", fontsize=10)
    ax = fig.add_subplot(2, 2, 4)
    if fused is None:
        ax.text(0.5, 0.5, "no fused estimate (method global or paper)", ha="center", va="center",
                transform=ax.transAxes)
        ax.set_axis_off()
        return
    ax.plot(t_s, fused["gyro_bias_rms_dps"], "-", lw=0.9, color="C0", label="gyroscope bias estimate, RMS over links")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("bias estimate, RMS [°/s]", color="C0")
    ax2 = ax.twinx()
    ax2.plot(t_s, fused["common_accel_mps2"], "-", lw=0.8, color="C3", label="|common acceleration| (translation)")
    ax2.set_ylabel("common acceleration [m/s²]", color="C3")
    for a, y in ((ax, fused["gyro_bias_rms_dps"]), (ax2, fused["common_accel_mps2"])):
        top = float(np.nanmax(y)) if np.isfinite(y).any() else 0.0
        a.set_ylim(0.0, 1.4 * top if top > 0 else 1.0)  # a free band above the curves for the legend
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=8, loc="upper left", ncol=2)
    w = fused.get("mag_weight_mean")
    if w is not None and np.isfinite(w).any():
        absolute = np.asarray(fused.get("heading_absolute", []), dtype=bool)
        note = (f"magnetometers: mean weight {np.nanmean(w):.2f} (min {np.nanmin(w):.2f}); heading "
                f"{'absolute' if absolute.size and absolute[-1] else 'a gauge'} at the end")
    else:
        note = "no magnetometers: heading is a gauge"
    ax.set_title(f"fused estimator: its bias estimate and the sheet's common acceleration\n{note}", fontsize=10)


def motion_scenes_figure(path, scenes: list[dict], *, lattice: str, link_length: float, rate_hz: float):
    """The moving scenes: per scene (a row) the sheet at a few instants, drawn in one
    box at the same scale, and its links' largest own acceleration and angular rate over time.

    ``scenes``: dicts with ``name``; ``t_s`` (T,); ``snapshots``, a list of ``(t, joints (rows, cols,
    3) m)`` (drawn in one cube per scene, so the sheet's motion shows at its true proportions);
    ``peak_accel_mps2`` (T,), the largest link acceleration at each instant;
    ``peak_rate_dps`` (T,), the largest link rate.
    """
    plt = _plt()
    from matplotlib.ticker import MaxNLocator

    n = len(scenes)
    k = max(len(s["snapshots"]) for s in scenes)
    fig = plt.figure(figsize=(4.0 * k + 5.5, 3.6 * n))
    gs = fig.add_gridspec(n, k + 1, width_ratios=[1.0] * k + [1.5], left=0.02, right=0.95, bottom=0.04,
                          top=0.95, wspace=0.12, hspace=0.3)
    for r, sc in enumerate(scenes):
        allP = np.concatenate([P.reshape(-1, 3) for _t, P in sc["snapshots"]]) * CM
        lo, hi = allP.min(0), allP.max(0)
        mid, half = 0.5 * (lo + hi), 0.5 * max(float(np.max(hi - lo)), 1e-9)
        for c, (t, P) in enumerate(sc["snapshots"]):
            ax = fig.add_subplot(gs[r, c], projection="3d")
            _wire(ax, P * CM, color=f"C{c}", lw=0.7)
            ax.set_title(f"{sc['name']}, t = {t:.2f} s", fontsize=10)
            _labels_cm(ax)
            ax.set_xlim(mid[0] - half, mid[0] + half)  # one cube for every instant: true proportions
            ax.set_ylim(mid[1] - half, mid[1] + half)
            ax.set_zlim(mid[2] - half, mid[2] + half)
            ax.set_box_aspect((1, 1, 1), zoom=0.85)
            for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
                axis.set_major_locator(MaxNLocator(4))
        ax = fig.add_subplot(gs[r, k])
        ax.plot(sc["t_s"], sc["peak_accel_mps2"], color="C3", lw=1.0, label="largest link acceleration")
        for t, _P in sc["snapshots"]:
            ax.axvline(t, color="0.8", lw=0.8)
        ax.set_xlabel("t [s]")
        ax.set_ylabel("acceleration [m/s²]", color="C3")
        ax.axhline(2.0, color="C3", ls=":", lw=0.8, label="2 m/s² (the fused estimator's floor)")
        ax2 = ax.twinx()
        ax2.plot(sc["t_s"], sc["peak_rate_dps"], color="C0", lw=1.0, label="largest link rate")
        ax2.set_ylabel("angular rate [°/s]", color="C0")
        h1, l1 = ax.get_legend_handles_labels()
        h2, l2 = ax2.get_legend_handles_labels()
        ax.legend(h1 + h2, l1 + l2, loc="upper right", fontsize=7)
        ax.set_title(f"{sc['name']}: peaks {np.max(sc['peak_accel_mps2']):.1f} m/s², "
                     f"{np.max(sc['peak_rate_dps']):.0f} °/s", fontsize=10)
    fig.suptitle(f"capsheet moving scenes: {lattice} joints, L = {link_length * CM:g} cm, exact nets at every "
                 f"instant, sampled at {rate_hz:g} Hz")
    _save(fig, path)
    return fig


def imu_stream_figure(path, t_s: np.ndarray, series: list[tuple[str, str, np.ndarray, np.ndarray]], *,
                      title: str):
    """One chip's readings against the truth, one panel per sensor.

    ``series``: ``(name, unit, truth (T, 3), reading (T, 3))``, already in ``unit``.
    """
    plt = _plt()
    fig, axes = plt.subplots(len(series), 1, figsize=(11, 3.0 * len(series)), sharex=True, squeeze=False)
    for ax, (name, unit, truth, reading) in zip(axes[:, 0], series):
        for a, axis in enumerate("xyz"):
            ax.plot(t_s, truth[:, a], color=f"C{a}", lw=1.2, label=f"truth {axis}")
            ax.plot(t_s, reading[:, a], ".", color=f"C{a}", ms=1.5, alpha=0.6, label=f"reading {axis}")
        ax.set_ylabel(f"{name} [{unit}]")
        ax.legend(loc="upper right", fontsize=7, ncol=6, markerscale=4)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("t [s]")
    fig.suptitle(title)
    fig.tight_layout()
    _save(fig, path)
    return fig
