"""Contacts in a displacement field: watershed segmentation, per-contact depth, position, shape
and force (module docstring of `host.analysis.tactile`, steps 3-4)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .foam import Foam
from .rest import RestShape

__all__ = ["DetectorSettings", "Contact", "find_contacts", "lattice_index"]


@dataclass(frozen=True)
class DetectorSettings:
    """Detection thresholds (docs/tactile.md, "Detection").

    Attributes
    ----------
    k_detect : float
        A contact's deepest joint must exceed ``k_detect σ_i`` (default 5: on an untouched sheet
        Gaussian noise passes it with probability 3e-7 per joint).
    k_region : float
        Joints above ``k_region σ_i`` belong to a contact's region (default 3).
    floor_m : float
        Thresholds are at least this, metres (default 0.1 mm: model errors the noise does not
        show, e.g. the normal assumption).
    k_prominence, prominence_fraction : float
        A local maximum is a contact of its own only if it rises above the point where it meets
        a higher one by ``max(k_prominence σ, prominence_fraction · its depth)`` (defaults 4, 0.3).
    min_separation : float
        Maxima closer than this, in link lengths, are one contact (default 1.5: adjacent and
        diagonal joints never make two contacts).
    skirt : int
        Joints beyond the region (dilation steps, 8-neighbours) added to each contact's force
        integral for the dent's shallow tail (default 2).
    force_model : {"fit", "sum"}
        How a contact's force is read (docs/tactile.md, "Force"): ``"fit"`` (default) fits the
        layer's dent template (`dent_template`: amplitude, contact radius, cap shape, centre, a
        local offset) to the region and skirt at the joints' surface positions and integrates
        the template, ``F = k α ∫ t dA``; ``"sum"`` is the sampled Winkler integral
        ``Σ k_i w_i A_i`` over the region and skirt. A contact flagged ``merged`` (two contacts
        or an elongated one: no round template fits it) always uses the sum, and so does a
        contact whose fit fails.
    merge_flag_ratio : float
        A contact whose half-depth footprint is this elongated (major / minor half-axis) is
        flagged ``merged`` (default 1.6: a round contact reads 1.0-1.5, two 2 N contacts 2 L
        apart that merged 1.8-2.8; a finger, 3.7-5, is flagged too: one elongated contact and two
        merged round ones look alike at one joint per link length).
    """

    k_detect: float = 5.0
    k_region: float = 3.0
    floor_m: float = 1e-4
    k_prominence: float = 4.0
    prominence_fraction: float = 0.3
    min_separation: float = 1.5
    skirt: int = 2
    merge_flag_ratio: float = 1.6
    force_model: str = "fit"

    def __post_init__(self) -> None:
        if self.force_model not in ("fit", "sum"):
            raise ValueError(f"Invalid force_model: {self.force_model!r} (need 'fit' or 'sum')")


@dataclass(frozen=True, eq=False)
class Contact:
    """One contact.

    Attributes
    ----------
    id : int
        Track id (`ContactTracker`); -1 when untracked.
    index : ndarray, shape (2,)
        Centre in fractional lattice indices ``(i, j)``.
    position : ndarray, shape (3,)
        Centre on the rest surface, metres, rest frame.
    normal : ndarray, shape (3,)
        Rest surface normal there (out of the foam).
    depth_m : float
        Largest displacement into the foam, metres.
    force_n : float
        N: the fitted dent template's integral ``k α ∫ t dA`` (`DetectorSettings.force_model`
        ``"fit"``, the default, for a contact not flagged ``merged``), else ``k Σ w_i A_i`` over
        the region and skirt.
    area_m2 : float
        Rest area of the joints displaced by at least half the depth, m².
    axes_m : ndarray, shape (2,)
        Principal half-axes (major, minor), metres: ``2 sqrt(eigenvalue)`` of the weighted second
        moment over those joints (a uniform disc of radius ``a`` gives ``a``).
    angle_rad : float
        Major axis from the lattice's i direction at the contact, towards j, in (−π/2, π/2].
    peak : tuple of int
        Joint ``(i, j)`` of the largest displacement.
    region : ndarray of bool, shape (rows, cols)
        The joints of the contact (without the skirt).
    force_n_held : float or None
        Mean force of its track over the last few snapshots, N (`ContactTracker`'s
        ``force_window``; None untracked): for a held contact, about half the noise.
    merged : bool
        The region may hold more than one contact: a second maximum above the detection
        threshold was merged into it (closer than ``min_separation`` or not prominent enough),
        or its footprint is elongated (``merge_flag_ratio``). Its force is then the sum.
    """

    id: int
    index: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    depth_m: float
    force_n: float
    area_m2: float
    axes_m: np.ndarray
    angle_rad: float
    peak: tuple[int, int]
    region: np.ndarray = field(repr=False)
    merged: bool = False
    force_n_held: float | None = None


_NB8 = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


def _dilate(mask: np.ndarray) -> np.ndarray:
    out = mask.copy()
    out[1:] |= mask[:-1]
    out[:-1] |= mask[1:]
    out[:, 1:] |= out[:, :-1].copy()
    out[:, :-1] |= out[:, 1:].copy()
    return out


def _bilinear(P: np.ndarray, fi: float, fj: float) -> np.ndarray:
    rows, cols = P.shape[:2]
    i0 = int(np.clip(np.floor(fi), 0, rows - 2))
    j0 = int(np.clip(np.floor(fj), 0, cols - 2))
    a, b = fi - i0, fj - j0
    return ((1 - a) * (1 - b) * P[i0, j0] + a * (1 - b) * P[i0 + 1, j0]
            + (1 - a) * b * P[i0, j0 + 1] + a * b * P[i0 + 1, j0 + 1])


def lattice_index(joints: np.ndarray, point: np.ndarray, iterations: int = 20) -> np.ndarray:
    """Fractional lattice indices ``(i, j)`` of the sheet point nearest ``point``: the inverse of
    bilinear interpolation of ``joints`` (Gauss-Newton from the nearest joint).

    Parameters
    ----------
    joints : ndarray, shape (rows, cols, 3)
        Metres.
    point : ndarray, shape (3,)
        Metres, the same frame.

    Returns
    -------
    ndarray, shape (2,)
        ``(i, j)``, clipped to the lattice.
    """
    P = np.asarray(joints, float)
    x = np.asarray(point, float)
    rows, cols = P.shape[:2]
    i0, j0 = np.unravel_index(np.argmin(np.linalg.norm(P - x, axis=-1)), (rows, cols))
    f = np.array([float(i0), float(j0)])
    for _ in range(iterations):
        h = 1e-4
        r = _bilinear(P, *f) - x
        J = np.stack([(_bilinear(P, f[0] + h, f[1]) - _bilinear(P, f[0] - h, f[1])) / (2 * h),
                      (_bilinear(P, f[0], f[1] + h) - _bilinear(P, f[0], f[1] - h)) / (2 * h)],
                     axis=1)
        step = np.linalg.lstsq(J, r, rcond=None)[0]
        f = np.clip(f - step, [0, 0], [rows - 1, cols - 1])
        if np.max(np.abs(step)) < 1e-9:
            break
    return f


#: Subsamples per link length for the footprint (bilinear interpolation of the displacement).
FOOTPRINT_SUBSAMPLES = 4


def _footprint(d, region, rest, level, pos, e1, e2):
    """The contact's footprint above ``level``: points ``(n, 2)`` in the tangent frame ``(e1,
    e2)`` at ``pos`` (metres) and its area (m²), from the displacement interpolated bilinearly
    at `FOOTPRINT_SUBSAMPLES` per link inside the region (a punch's round flat bottom spans a few
    joints only: their moments alone would make it a line)."""
    rows, cols = d.shape
    ii, jj = np.nonzero(region)
    f = FOOTPRINT_SUBSAMPLES
    si = np.arange(max(ii.min() - 1, 0) * f, min(ii.max() + 1, rows - 1) * f + 1) / f
    sj = np.arange(max(jj.min() - 1, 0) * f, min(jj.max() + 1, cols - 1) * f + 1) / f
    SI, SJ = (a.ravel() for a in np.meshgrid(si, sj, indexing="ij"))
    dv = _bilinear_many(d[..., None], SI, SJ)[:, 0]
    inr = region[np.floor(SI + 0.5).astype(int), np.floor(SJ + 0.5).astype(int)]  # nearest joint
    keep = inr & (dv >= level)
    if keep.sum() < 1:
        keep = np.zeros(len(SI), bool)
        keep[np.argmax(np.where(inr, dv, -np.inf))] = True
    X = _bilinear_many(rest.joints, SI[keep], SJ[keep]) - pos
    cell = _bilinear_many(rest.areas[..., None], SI[keep], SJ[keep])[:, 0] / (f * f)
    return np.stack([X @ e1, X @ e2], axis=1), float(cell.sum())


def _bilinear_many(P: np.ndarray, fi: np.ndarray, fj: np.ndarray) -> np.ndarray:
    """`_bilinear` at many fractional indices: ``P (rows, cols, m)`` -> ``(n, m)``."""
    rows, cols = P.shape[:2]
    i0 = np.clip(np.floor(fi).astype(int), 0, rows - 2)
    j0 = np.clip(np.floor(fj).astype(int), 0, cols - 2)
    a, b = (fi - i0)[:, None], (fj - j0)[:, None]
    return ((1 - a) * (1 - b) * P[i0, j0] + a * (1 - b) * P[i0 + 1, j0]
            + (1 - a) * b * P[i0, j0 + 1] + a * b * P[i0 + 1, j0 + 1])


def _noise_map(displacement: np.ndarray, rest: RestShape) -> np.ndarray:
    if rest.noise_m is not None:
        return np.asarray(rest.noise_m, float)
    d = displacement.ravel()
    s = 1.4826 * np.median(np.abs(d - np.median(d)))
    return np.full(displacement.shape, s)


def _segment(d: np.ndarray, sigma: np.ndarray, s: DetectorSettings
             ) -> tuple[np.ndarray, set[int]]:
    """Watershed with merging by prominence and separation: labels ``(rows, cols)`` (-1 none)
    and the labels that absorbed a second maximum above the detection threshold."""
    rows, cols = d.shape
    region_thr = np.maximum(s.k_region * sigma, s.floor_m)
    inside = d > region_thr
    label = -np.ones(d.shape, int)
    parent: list[int] = []
    absorbed: list[int] = []
    peak_of: list[tuple[int, int]] = []

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    order = np.argsort(-d, axis=None)
    for flat in order:
        i, j = divmod(int(flat), cols)
        if not inside[i, j]:
            continue
        roots = {find(label[i + di, j + dj]) for di, dj in _NB8
                 if 0 <= i + di < rows and 0 <= j + dj < cols and label[i + di, j + dj] >= 0}
        if not roots:
            parent.append(len(parent))
            peak_of.append((i, j))
            label[i, j] = len(parent) - 1
            continue
        # the joint joins its steepest-ascent neighbour's region (a saddle joint next to one peak
        # and the flank of another goes to the peak it is next to)
        nbrs = [(d[i + di, j + dj], i + di, j + dj) for di, dj in _NB8
                if 0 <= i + di < rows and 0 <= j + dj < cols and label[i + di, j + dj] >= 0]
        _, si_, sj_ = max(nbrs)
        steep = find(label[si_, sj_])
        roots = sorted(roots, key=lambda r: -d[peak_of[r]])
        top = roots[0]
        for r in roots[1:]:
            pi, pj = peak_of[r]
            ti, tj = peak_of[top]
            prom = d[pi, pj] - d[i, j]
            need = max(s.k_prominence * sigma[pi, pj], s.prominence_fraction * d[pi, pj])
            sep = np.hypot(pi - ti, pj - tj)
            if prom < need or sep < s.min_separation:
                parent[r] = top
                if sep >= s.min_separation and prom >= s.k_prominence * sigma[pi, pj]:
                    absorbed.append(top)  # a real second maximum, merged as not prominent enough
        label[i, j] = find(steep)
    out = -np.ones(d.shape, int)
    m = label >= 0
    out[m] = [find(int(x)) for x in label[m]]
    return out, {find(a) for a in absorbed}


def find_contacts(displacement: np.ndarray, rest: RestShape, foam: Foam,
                  settings: DetectorSettings = DetectorSettings(),
                  aligned: np.ndarray | None = None) -> list[Contact]:
    """Contacts in a displacement field (module docstring, steps 3-4).

    Parameters
    ----------
    displacement : ndarray, shape (rows, cols)
        Normal displacement into the foam, metres (`deformation`).
    rest : RestShape
    foam : Foam
    settings : DetectorSettings
    aligned : ndarray, shape (rows, cols, 3), optional
        The joints overlaid on the rest shape (`deformation`'s second result), metres: the
        force fit samples the dent where the joints are (the sheet slides towards a dent), at
        their foot points on the rest surface (``aligned + d n``). Default: the rest joints.

    Returns
    -------
    list of Contact
        Untracked (``id = -1``), deepest first.
    """
    d = np.asarray(displacement, float)
    if d.shape != rest.joints.shape[:2]:
        raise ValueError(f"Expected `displacement` to have shape {rest.joints.shape[:2]}, "
                         f"got {d.shape}.")
    sigma = _noise_map(d, rest)
    labels, absorbed = _segment(d, sigma, settings)
    detect_thr = np.maximum(settings.k_detect * sigma, settings.floor_m)
    ids = [int(x) for x in np.unique(labels) if x >= 0]
    ids = [r for r in ids if np.any((labels == r) & (d > detect_thr))]
    # skirts: grow every region by dilation into unlabelled joints, deepest neighbour wins
    grown = np.where(np.isin(labels, ids), labels, -1)
    rows, cols = d.shape
    for _ in range(settings.skirt):
        lab = np.pad(grown, 1, constant_values=-1)
        dep = np.pad(d, 1, constant_values=-np.inf)
        best, best_d = np.full(d.shape, -1), np.full(d.shape, -np.inf)
        for di, dj in _NB8:
            nl = lab[1 + di:1 + di + rows, 1 + dj:1 + dj + cols]
            nd = np.where(nl >= 0, dep[1 + di:1 + di + rows, 1 + dj:1 + dj + cols], -np.inf)
            better = nd > best_d
            best = np.where(better, nl, best)
            best_d = np.where(better, nd, best_d)
        grown = np.where(grown >= 0, grown, best)
    k = rest.k_map(foam)  # per joint: the layer is softer where the core is convex
    out = []
    geo = []
    for r in ids:
        region = labels == r
        depth = float(d[region].max())
        pk = np.unravel_index(np.argmax(np.where(region, d, -np.inf)), d.shape)
        core = region & (d >= 0.5 * depth)
        w = d[core]
        ii, jj = np.nonzero(core)
        fi, fj = float(w @ ii / w.sum()), float(w @ jj / w.sum())
        pos = _bilinear(rest.joints, fi, fj)
        nrm = _bilinear(rest.normals, fi, fj)
        nrm /= np.linalg.norm(nrm)
        e1 = _bilinear(rest.joints, min(fi + 0.5, rest.rows - 1), fj) - _bilinear(
            rest.joints, max(fi - 0.5, 0), fj)
        e1 -= (e1 @ nrm) * nrm
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(nrm, e1)
        xy, sub_area = _footprint(d, region, rest, 0.5 * depth, pos, e1, e2)
        mu = xy.mean(axis=0)
        C = (xy - mu).T @ (xy - mu) / len(xy)
        ev, evec = np.linalg.eigh(C)
        axes = 2.0 * np.sqrt(np.maximum(ev[::-1], 0.0))
        major = evec[:, 1]
        ang = float(np.arctan2(major[1], major[0]))
        if ang <= -np.pi / 2:
            ang += np.pi
        elif ang > np.pi / 2:
            ang -= np.pi
        geo.append((pos, float(np.sqrt(sub_area / np.pi))))
        merged = r in absorbed or axes[0] >= settings.merge_flag_ratio * max(axes[1], 1e-12)
        out.append(Contact(id=-1, index=np.array([fi, fj]), position=pos, normal=nrm,
                           depth_m=depth, force_n=0.0, area_m2=sub_area, axes_m=axes,
                           angle_rad=ang, peak=(int(pk[0]), int(pk[1])), region=region,
                           merged=bool(merged)))
    share = _force_shares(d, rest, grown, ids, geo, foam.shear_length_m)
    forces = [float(np.sum(k * d * rest.areas * f)) for f in share]
    if settings.force_model == "fit" and out:
        surf = rest.joints if aligned is None else (
            np.asarray(aligned, float) + d[..., None] * rest.normals)
        fitted = _fit_forces(d, rest, k, surf, out, [grown == r for r in ids],
                             foam.shear_length_m)
        forces = [f if (ft is None or c.merged) else ft
                  for f, ft, c in zip(forces, fitted, out)]
    out = [replace(c, force_n=f) for c, f in zip(out, forces)]
    out.sort(key=lambda c: -c.depth_m)
    return out


def _force_shares(d, rest, grown, ids, geo, lam):
    """Each contact's share of every joint's displacement, shape ``(n_contacts, rows, cols)``.

    A joint in one contact's region or skirt belongs to it; where the skirts of several
    contacts cover the same neighbourhood, the joints of all their regions and skirts are
    shared in proportion to fitted templates: contact ``c`` has ``t_c(r) = exp(−max(r − a_c, 0)
    / λ)`` (flat over its half-depth radius ``a_c``, the foam's tail beyond), amplitudes by
    non-negative least squares on those joints. The shares add up to 1 on the support, so the
    total force is the plain Winkler integral; only its split is modelled.
    """
    from scipy.optimize import nnls

    n = len(ids)
    share = np.zeros((n,) + d.shape)
    for c, r in enumerate(ids):
        share[c] = grown == r
    if n < 2 or lam <= 0:
        return share
    support = grown >= 0
    P = rest.joints[support]
    T = np.empty((P.shape[0], n))
    for c, (pos, a) in enumerate(geo):
        rr = np.linalg.norm(P - pos, axis=1)
        T[:, c] = np.exp(-np.maximum(rr - a, 0.0) / lam)
    amp, _ = nnls(T, np.maximum(d[support], 0.0))
    fit = T * amp[None, :]
    tot = fit.sum(axis=1)
    ok = tot > 1e-12
    frac = np.where(ok[:, None], fit / np.where(ok, tot, 1.0)[:, None], 0.0)
    # keep hard ownership where only one contact's template is non-negligible or fit failed
    for c in range(n):
        s = share[c][support]
        share_c = np.where(ok, frac[:, c], s)
        out = np.zeros(d.shape)
        out[support] = share_c
        share[c] = out
    return share


def _k0_ratio(x: np.ndarray, a: float) -> np.ndarray:
    """``K0(x) / K0(a)`` for ``x >= a > 0`` (scaled Bessel functions: no underflow)."""
    from scipy.special import k0e
    return k0e(x) / k0e(a) * np.exp(a - x)


def dent_template(r: np.ndarray, a: float, s: float, lam: float) -> np.ndarray:
    """The layer's dent around a round contact of radius ``a``, normalised to 1 at ``r = a``.

    Outside the contact the Vlasov layer carries no load, ``k w − G_p ∇²w = 0``, whose decaying
    axisymmetric solution is ``K0(r / λ)`` (modified Bessel function; ``λ`` the spreading length,
    `Foam.shear_length_m`): ``t = K0(r/λ) / K0(a/λ)``. Inside, a cap
    ``1 + s (a² − r²) / (2 a λ) · K1(a/λ) / K0(a/λ)``: ``s = 0`` a flat punch's bottom (slope
    discontinuous at the rim), ``s = 1`` the paraboloid that meets the tail with a continuous
    slope (a sphere's). ``r``, ``a``, ``λ`` in metres.

    >>> from scipy.special import k0
    >>> t = float(dent_template(np.array(0.01), 0.005, 0.0, 0.0067))
    >>> round(t, 6) == round(float(k0(0.01 / 0.0067) / k0(0.005 / 0.0067)), 6)
    True
    """
    from scipy.special import k0e, k1e
    r = np.asarray(r, float)
    x, xa = r / lam, a / lam
    q = k1e(xa) / k0e(xa)
    cap = 1.0 + s * (a * a - r * r) / (2.0 * a * lam) * q
    return np.where(r < a, cap, _k0_ratio(np.maximum(x, xa), xa))


def dent_template_integral(a: float, s: float, lam: float) -> float:
    """``∫ t dA`` over the plane of `dent_template`, m²: ``π a²`` (the cap's base)
    ``+ s π a³ K1 / (4 λ K0)`` (the cap above it) ``+ 2 π λ a K1 / K0`` (the tail,
    ``∫_a^∞ 2π r K0(r/λ) dr = 2π λ a K1(a/λ)``), Bessel functions at ``a / λ``.

    >>> round(dent_template_integral(0.005, 0.0, 1e-9) / (np.pi * 0.005 ** 2), 6)   # no spreading
    1.0
    """
    from scipy.special import k0e, k1e
    xa = a / lam
    q = k1e(xa) / k0e(xa)
    return float(np.pi * a * a + s * np.pi * a ** 3 * q / (4.0 * lam) + 2.0 * np.pi * lam * a * q)


#: Weight of the cap-shape prior in `_fit_forces` (residuals in units of the contact's depth).
CAP_SHAPE_PULL = 0.05


def _fit_forces(d, rest, k, surf, contacts, supports, lam):
    """Every contact's force from a fit of `dent_template` to the displacement (docs/tactile.md,
    "Force"): one joint least-squares fit over the union of the contacts' supports (region and
    skirt), per contact an amplitude ``α``, radius ``a``, cap shape ``s`` in [0, 1], centre (in its
    rest tangent plane) and an offset over its own support (the noise's local level: the joints'
    heights come from integrated slopes, their error is smooth). The joints are placed at
    ``surf`` (their foot points on the rest surface). ``F = k α ∫ t dA``, ``k`` at the centre.
    A contact's entry is None where the fit failed."""
    from scipy.optimize import least_squares

    n = len(contacts)
    if n == 0 or lam <= 0:
        return [None] * n
    union = np.zeros(d.shape, bool)
    for sup in supports:
        union |= sup
    if union.sum() < 6 * n + 1:
        return [None] * n
    owner = np.full(d.shape, -1)
    for c, sup in enumerate(supports):
        owner[sup] = c
    own = owner[union]
    dv = d[union]
    P = surf[union]
    frames, x0, lo, hi, scale = [], [], [], [], []
    L = rest.link_length
    for c in contacts:
        nrm = c.normal
        e1 = np.cross([0.0, 1.0, 0.0] if abs(nrm[0]) > 0.9 else [1.0, 0.0, 0.0], nrm)
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(nrm, e1)
        X = P - c.position
        frames.append(np.stack([X @ e1, X @ e2], axis=1))
        rh = max(float(np.sqrt(c.area_m2 / np.pi)), 0.25 * L)
        dep = max(c.depth_m, 1e-4)
        # parameters in units of the depth and the link length (the fit's tolerances are
        # relative: in metres the residuals, ~1e-4, stopped it at the start)
        scale += [dep, L, 1.0, L, L, dep]
        x0 += [1.0, 0.6 * rh / L, 0.5, 0.0, 0.0, 0.0]
        lo += [0.0, 0.02, 0.0, -1.0, -1.0, -0.5]
        hi += [10.0, (2.0 * rh + L) / L, 1.0, 1.0, 1.0, 0.5]
    scale = np.array(scale)
    dscale = max(max(c.depth_m for c in contacts), 1e-4)

    def model(q):
        p = q * scale
        m = np.zeros(len(dv))
        for c in range(n):
            al, a, s, u0, v0, off = p[6 * c:6 * c + 6]
            xy = frames[c]
            m += al * dent_template(np.hypot(xy[:, 0] - u0, xy[:, 1] - v0), a, s, lam)
            m[own == c] += off
        return m

    def residual(q):
        # a weak pull of the cap shape towards 1/2: at one joint per link the data barely tell
        # a flat bottom from a paraboloid (a valley of near-equal cost along which the force
        # changes by several per cent); the pull makes the minimum unique and continuous
        return np.concatenate([(model(q) - dv) / dscale, CAP_SHAPE_PULL * (q[2::6] - 0.5)])

    try:
        best = least_squares(residual, np.array(x0), bounds=(np.array(lo), np.array(hi)),
                             ftol=1e-12, xtol=1e-10, gtol=1e-12, max_nfev=400)
    except (ValueError, np.linalg.LinAlgError):
        return [None] * n
    if not best.success or not np.all(np.isfinite(best.x)):
        return [None] * n
    sol_x = best.x * scale
    out = []
    for c, con in enumerate(contacts):
        al, a, s = sol_x[6 * c:6 * c + 3]
        kc = float(_bilinear(k[..., None], *con.index)[0])
        out.append(kc * al * dent_template_integral(a, s, lam))
    return out
