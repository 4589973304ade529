"""What fills in what the data cannot determine: the priors' weights (`PRIORS`) from the flatness
of the regions around every unit and the readings' noise."""

from __future__ import annotations

import numpy as np

import host.analysis.estimator.kernel as kernel  # the switch, read at call time
from .kernel import ffi as _kffi, lib as _klib
from .angles import G0
from .structure import units_int64

__all__ = ["PRIORS", "DEFAULT_PRIOR", "LEVEL_TILTED_SHARE", "LEVEL_SHARE_NOISE", "tilted_share",
           "FIXED_PRIOR_WEIGHT",
           "ABS_PRIOR_FLOOR", "BEND_STD_RAD", "SHEAR_WEIGHT", "SHEAR_WEIGHT_REST",
           "FLAT_TILT_NOISE", "FLAT_RADIUS", "PRIOR_WEIGHT_MIN", "flatness", "link_flatness",
           "prior_weights", "bridging_pairs"]

#: The priors `estimate` offers (docs/estimator.md §3 compares them): "level" (default) —
#: bending held only where the region is level, plus flat-cell shear, both scaled by the
#: readings' noise: unbiased on a sheet whose lattice lines turn in plan (a drape, the paper's
#: own experiment); "adaptive" (the default before) — the bending held everywhere, biased
#: where lattice lines turn in plan; "off" —
#: only the floors that keep the problem regular (the data alone); "fixed" — the former prior,
#: ``FIXED_PRIOR_WEIGHT`` on every yaw towards the rest; "local" — that yaw prior weighted by
#: the cell's flatness.
PRIORS = ("level", "adaptive", "off", "fixed", "local")
#: The prior `estimate`, `estimate_batch` and `ShapeEstimator` use unless told (``prior=``).
DEFAULT_PRIOR = "level"
#: Weight of the "fixed"/"local" priors on ``wrap(γ − γ_rest)²`` (the estimator's former prior).
FIXED_PRIOR_WEIGHT = 1e-2
#: Least weight of the yaw prior towards the rest yaws (keeps a link without constraints defined).
ABS_PRIOR_FLOOR = 1e-10

#: Prior std of the bending (yaw difference of parallel neighbours beyond the rest's), rad: the
#: bending prior's weight is ``(σ/BEND_STD_RAD)²`` for readings of noise σ (fraction of g).
BEND_STD_RAD = 0.1
#: Weight of the shear prior (a cell's corner angle towards the rest's) on a flat cell; a cell
#: of tilt θ gets ``SHEAR_WEIGHT · exp(−(θ / (FLAT_TILT_NOISE · σ))²)``.
SHEAR_WEIGHT = 1e-3
#: ... when the rest shape is given (``rest=``): then it is known, not guessed, and holds harder.
SHEAR_WEIGHT_REST = 1e-2
#: A cell counts as flat (locally unobservable, Case 1) while its tilt is below ~this many σ.
FLAT_TILT_NOISE = 3.0
#: ... averaged over (2 FLAT_RADIUS + 1)² cells around it.
FLAT_RADIUS = 3
#: "level": the share of the bending weight a pair keeps however tilted its region, for readings
#: of up to `LEVEL_SHARE_NOISE` (`tilted_share`). Small enough not to pull a drape's zigzag
#: (0.01 did: the drape 0.64 -> 1.02 % of side at 5 % g), large enough to hold the smooth modes
#: the data hold weakly on a compass net, which otherwise made the chord steps contract so
#: slowly that a 64x64 stream at 1 % g refactorised every 4-5 snapshots (26 -> 9 ms per
#: snapshot; 0.002 and 0.001 still refactorised; docs/estimator.md §3 has the sweep).
LEVEL_TILTED_SHARE = 0.003
#: ... up to this noise σ (fraction of g); above it the share falls as 1/σ, so that the tilted
#: pairs' weight grows as σ, not σ² (`tilted_share`): the constant share cost the tilted drape
#: 7-9 % of its error at 3-5 % g, on draws of other seeds than `capsheet paper noise`'s too
LEVEL_SHARE_NOISE = 0.01


def tilted_share(noise):
    """The share of the bending weight a tilted pair keeps under "level", for readings of noise
    σ (a float, or per snapshot (B,)): `LEVEL_TILTED_SHARE` up to `LEVEL_SHARE_NOISE`, then
    ``LEVEL_TILTED_SHARE · LEVEL_SHARE_NOISE / σ``. The share is there for the solver: it holds
    the smooth modes that a compass net's data hold weakly, whose curvature is the data's and
    does not grow with the noise, while the pull it exerts on a drape's zigzag does (docs/
    estimator.md §3 measures both)."""
    noise = np.asarray(noise, float)
    share = LEVEL_TILTED_SHARE * np.minimum(1.0, LEVEL_SHARE_NOISE / np.maximum(noise, 1e-300))
    return share[..., None] if share.ndim else float(share)


#: Every prior pair's least weight (noise-free readings): keeps Case 1 regions defined.
PRIOR_WEIGHT_MIN = 1e-8


def flatness(st, r, norm_g, noise):
    """Per unit (all units, row-major), ``h = exp(−(θ/θ0)²)`` in [0, 1]: 1 where the region
    around the unit is level within the noise (Case 1, unobservable), 0 where it is clearly
    tilted. θ² is twice the mean of ``1 − cos`` of the links' sensor-z tilts (cos from the
    reading: ``s_z/|s|``), averaged over the (2 `FLAT_RADIUS` + 1)² units around;
    θ0 = `FLAT_TILT_NOISE` · σ. Noise-free readings (σ = 0) give 0 everywhere."""
    units = st.lattice.units.reshape(-1, 4)
    noise = np.asarray(noise, float)
    if noise.ndim == 0 and noise <= 0.0:
        return np.zeros(units.shape[0])
    lead = noise.shape  # () or (B,): r (..., n_links, 3), norm_g (..., n_links)
    if kernel.USE_KERNEL and not lead and r.ndim == 2 and FLAT_RADIUS >= 0:  # one snapshot
        u = units_int64(st.rows, st.cols)
        rc = np.ascontiguousarray(r, dtype=np.float64)
        ng = np.ascontiguousarray(norm_g, dtype=np.float64)
        work, h = np.empty(2 * u.shape[0]), np.empty(u.shape[0])
        fb = _kffi.from_buffer
        _klib.capsheet_flatness(st.rows - 1, st.cols - 1, fb("int64_t[]", u), fb("double[]", rc),
                                fb("double[]", ng), G0, FLAT_RADIUS,
                                FLAT_TILT_NOISE * max(float(noise), 1e-300),
                                fb("double[]", work[:u.shape[0]]),
                                fb("double[]", work[u.shape[0]:]), fb("double[]", h))
        return h
    cz = r[..., 2] / np.maximum(norm_g * G0, 1e-300)
    th2 = 2.0 * (1.0 - cz[..., units]).mean(axis=-1)
    if FLAT_RADIUS > 0:
        # regional: a level strip between tilted cells (a cylinder's crest) is held by its
        # tilted neighbours through the lattice; only wide level regions need the prior
        from scipy.ndimage import uniform_filter  # here: importing scipy.ndimage costs ~0.2 s

        k = 2 * FLAT_RADIUS + 1
        th2 = uniform_filter(th2.reshape(lead + (st.rows - 1, st.cols - 1)),
                             size=(1,) * len(lead) + (k, k), mode="nearest"
                             ).reshape(lead + (-1,))
    th0 = FLAT_TILT_NOISE * np.maximum(noise, 1e-300)
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):  # noise 0: th0² underflows (0/0 on a level unit); masked below
        h = np.exp(-np.maximum(th2, 0.0) / (th0[..., None] ** 2 if lead else th0 ** 2))
    return np.where((noise > 0.0)[..., None], h, 0.0) if lead else h


def link_flatness(st, h):
    """Per link, the mean flatness `h` (..., n_units) of the units it belongs to (one or two)."""
    units = st.lattice.units.reshape(-1, 4)
    acc = np.zeros(np.shape(h)[:-1] + (st.n_links,))
    for k in range(4):  # a link holds one position k in at most one unit: no repeated index
        acc[..., units[:, k]] += h
    cnt = st.derived.get("link_unit_count")
    if cnt is None:  # per link, the units it belongs to (at least 1): fixed per structure
        cnt = st.derived["link_unit_count"] = np.maximum(
            np.bincount(units.ravel(), minlength=st.n_links).astype(float), 1.0)
    return acc / cnt


def bridging_pairs(st) -> np.ndarray:
    """Per bending pair (n_bend,), 1.0 where its two links are in different islands of the yaw
    problem's data terms, else 0.0 (cached on the structure).

    An island: links joined through active units (those with no missing link); a link in no
    active unit is an island of its own. Loop closure and the cells' normals relate the yaws of
    one island only, so each further island's rotation is free in the data: the "level" prior
    holds the pairs that join islands as "adaptive" does, whatever their tilt. Without missing
    links there is one island and no such pair."""
    got = st.derived.get("bridging_pairs")
    if got is None:
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        u = st.units
        a = np.repeat(u[:, :1], 3, axis=1).ravel()
        b = u[:, 1:].ravel()
        g = coo_matrix((np.ones(a.size), (a, b)), shape=(st.n_links, st.n_links))
        comp = connected_components(g, directed=False)[1]
        pb = st.pairs[:st.n_bend]
        got = st.derived["bridging_pairs"] = (comp[pb[:, 0]] != comp[pb[:, 1]]).astype(float)
    return got


def prior_weights(prior, st, r, norm_g, noise, rest_given=False):
    """(per-variable yaw-prior weights (nv,), per-pair weights (n_pairs,)) for ``prior``.

    "adaptive": bending pairs ``(σ/BEND_STD_RAD)²``, shear pairs ``SHEAR_WEIGHT · h`` (h the
    unit's `flatness`), no yaw prior beyond `ABS_PRIOR_FLOOR`; "level": the same with bending
    pairs at ``(σ/BEND_STD_RAD)² · h``, h the larger of its two links' `link_flatness` (1 for a
    pair that joins islands of the data, `bridging_pairs`; at least `tilted_share`);
    "off": floors only; "fixed":
    `FIXED_PRIOR_WEIGHT` on every yaw; "local": that times the mean flatness of the link's
    units. Pairs never go below `PRIOR_WEIGHT_MIN`.
    """
    lead = np.shape(noise)  # () or (B,): one snapshot, or a batch ("level", "adaptive" only)
    lam = np.full(st.n_var, ABS_PRIOR_FLOOR)
    if prior in ("adaptive", "level") and not lead and kernel.USE_KERNEL and r.ndim == 2:
        return lam, _pair_weights_kernel(prior, st, flatness(st, r, norm_g, noise), float(noise),
                                         rest_given)
    w = np.full(lead + (st.pairs.shape[0],), PRIOR_WEIGHT_MIN)
    if prior in ("adaptive", "level"):
        hu = flatness(st, r, norm_g, noise)
        bend = (np.asarray(noise)[..., None] / BEND_STD_RAD) ** 2
        if prior == "level":  # a pair is held as much as its flatter link's units are level,
            # and wholly where it joins what no unit relates (`bridging_pairs`)
            lf, pb = link_flatness(st, hu), st.pairs[:st.n_bend]
            h = np.maximum(lf[..., pb[:, 0]], lf[..., pb[:, 1]])  # (a fancy max over 2: 20x slower)
            bend = bend * np.maximum(np.maximum(h, bridging_pairs(st)), tilted_share(noise))
        w[..., :st.n_bend] = np.maximum(bend, PRIOR_WEIGHT_MIN)
        sw = SHEAR_WEIGHT_REST if rest_given else SHEAR_WEIGHT
        w[..., st.n_bend:] = np.maximum(sw * hu[..., st.shear_unit], PRIOR_WEIGHT_MIN)
    elif prior == "fixed":
        lam[:] = FIXED_PRIOR_WEIGHT
    elif prior == "local":
        units = st.lattice.units.reshape(-1, 4)
        h = flatness(st, r, norm_g, noise)
        acc = np.bincount(units.ravel(), weights=np.repeat(h, 4), minlength=st.n_links)
        cnt = np.bincount(units.ravel(), minlength=st.n_links)
        hl = acc / np.maximum(cnt, 1)
        lam = np.maximum(FIXED_PRIOR_WEIGHT * hl[st.var_links], ABS_PRIOR_FLOOR)
    return lam, w


def _pair_weights_kernel(prior, st, hu, noise: float, rest_given: bool) -> np.ndarray:
    """`prior_weights`' pair weights for "level" or "adaptive", one snapshot, in the kernel
    (``capsheet_pair_weights``: the same arithmetic as the numpy code, in one pass)."""
    ka = st.derived.get("pair_weight_arrays")
    if ka is None:
        units = units_int64(st.rows, st.cols)
        cnt = np.maximum(np.bincount(units.ravel(), minlength=st.n_links).astype(float), 1.0)
        ka = st.derived["pair_weight_arrays"] = (
            units, cnt, np.ascontiguousarray(st.pairs[:st.n_bend], np.int64),
            np.ascontiguousarray(bridging_pairs(st), np.float64),
            np.ascontiguousarray(st.shear_unit, np.int64))
    units, cnt, pb, bridging, shear_unit = ka
    h = np.ascontiguousarray(hu, np.float64)
    w = np.empty(st.pairs.shape[0])
    lf = np.empty(st.n_links)
    fb = _kffi.from_buffer
    _klib.capsheet_pair_weights(units.shape[0], fb("int64_t[]", units), fb("double[]", h), st.n_links,
                                fb("double[]", cnt), 1 if prior == "level" else 0, st.n_bend,
                                fb("int64_t[]", pb), fb("double[]", bridging),
                                (noise / BEND_STD_RAD) ** 2, tilted_share(noise), shear_unit.size,
                                fb("int64_t[]", shear_unit),
                                SHEAR_WEIGHT_REST if rest_given else SHEAR_WEIGHT,
                                PRIOR_WEIGHT_MIN, fb("double[]", w), fb("double[]", lf))
    return w
