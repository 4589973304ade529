"""Contacts in a displacement field: segmentation, how many contacts a region holds, and per
contact its force, footprint and their uncertainties (module docstring of
`host.analysis.tactile`, steps 3-4; docs/tactile.md, "Contacts")."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .fit import ContactGeometry, FitResult, fit_contacts
from .foam import Foam
from .response import half_depth_footprint, line_response
from .rest import RestShape

__all__ = ["DetectorSettings", "Contact", "ContactModel", "find_contacts", "lattice_index"]

#: The standard deviation given to an orientation the data do not determine (a round footprint):
#: that of an angle uniform over π, radians.
ANGLE_STD_UNKNOWN = float(np.pi / np.sqrt(12.0))

#: A footprint less elongated than this (major / minor half-axis) states no orientation
#: (`ANGLE_STD_UNKNOWN`): a round punch between joints reads up to ~1.3 (its rim-heavy pressure
#: is not the model's uniform disc), a finger 3-4.
ORIENTATION_MIN_RATIO = 1.4


@dataclass(frozen=True)
class DetectorSettings:
    """Detection thresholds and the contact model's settings (docs/tactile.md, "Contacts").

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
        In the watershed that proposes the contacts, a local maximum starts a region of its own
        only if it rises above the point where it meets a higher one by ``max(k_prominence σ,
        prominence_fraction · its depth)`` (defaults 4, 0.3).
    min_separation : float
        Two contacts whose centres are closer than this (link lengths) are never reported: the
        lattice cannot sample the dip between them (default 1.5).
    skirt : int
        Joints beyond a region (8-neighbour dilation steps) that take part in its fit: the
        dent's shallow tail and the offset's level (default 2).
    force_model : {"fit", "sum"}
        ``"fit"`` (default): the force is the amplitude of the fitted contact model
        (`fit.fit_contacts`, unit-force templates of the layer's response); ``"sum"``: the
        sampled Winkler integral ``Σ k_i w_i A_i`` over each contact's region and skirt, a
        joint shared between contacts in proportion to their fitted dents (for comparison).
    contact_radius_m, contact_radius_std_m : float
        The prior on a contact's half-width ``a`` (default 8 ± 2 mm: a fingertip's, a 15 mm
        ball's at 2 N). Between joints the data cannot tell a sharp contact from a blunt one
        (no joint inside it sees its cap), and the force read from the dent's tail changes by
        up to 16 % along that valley; the prior holds ``a`` where the data do not decide
        (docs/tactile.md, "The contact model").
    contact_length_std_m : float
        The prior on a contact's half-length ``ℓ``: about 0 with this standard deviation
        (default 6 mm), as much as one joint's noise. A round punch's rim-heavy pressure fits
        a short line of discs about as well as a disc, and without it half its snapshots read
        it 25 % elongated in a direction the sampling picked; a finger's 2.5 cm are decided by
        its data.
    split_gain : float
        Two contacts are reported instead of one when they lower the fit's residual by at
        least this, in units of the joints' noise variance (default 40: a single finger's
        two-contact alternatives lowered it by at most 20 at 0.3-2 % g where the thresholds
        were chosen, two contacts 2 L apart by 60 and more at 1 % g, 15 and more at 2 % g).
    ambiguous_gain : float
        Below `split_gain` but at least this (default 12): one contact is reported, flagged
        ``ambiguous``.
    split_try : float
        Two contacts are tried in a region whose one-contact fit leaves a residual above this
        per joint, in units of the noise variance (default 1.5: single contacts left 0.2-0.9 at
        1 % g, two merged ones 1.1-11), or whose contact is long enough to hold two
        (`min_separation`).
    """

    k_detect: float = 5.0
    k_region: float = 3.0
    floor_m: float = 1e-4
    k_prominence: float = 4.0
    prominence_fraction: float = 0.3
    min_separation: float = 1.5
    skirt: int = 2
    force_model: str = "fit"
    contact_radius_m: float = 0.008
    contact_radius_std_m: float = 0.002
    contact_length_std_m: float = 0.006
    split_gain: float = 40.0
    ambiguous_gain: float = 12.0
    split_try: float = 1.5

    def __post_init__(self) -> None:
        if self.force_model not in ("fit", "sum"):
            raise ValueError(f"Invalid force_model: {self.force_model!r} (need 'fit' or 'sum')")
        for name in ("k_detect", "k_region", "contact_radius_m", "contact_radius_std_m",
                     "contact_length_std_m", "split_gain", "min_separation"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"Invalid {name}: {v!r} (need a finite value > 0)")
        if not (isinstance(self.skirt, (int, np.integer)) and self.skirt >= 0):
            raise ValueError(f"Invalid skirt: {self.skirt!r} (need an integer >= 0)")


@dataclass(frozen=True, eq=False)
class ContactModel:
    """A contact's fitted pressure, in the rest frame: a line of uniform discs (`response`).

    Attributes
    ----------
    centre : ndarray, shape (3,)
        The line's middle, metres (in the rest tangent plane at the contact).
    direction : ndarray, shape (3,)
        Unit vector along the line.
    half_width_m, half_length_m : float
        ``a`` and ``ℓ``, metres.
    """

    centre: np.ndarray
    direction: np.ndarray
    half_width_m: float
    half_length_m: float


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
        Largest displacement into the foam among its joints, metres.
    force_n : float
        N: the fitted model's amplitude (`DetectorSettings.force_model` ``"fit"``), else the
        sampled Winkler sum over its region and skirt.
    area_m2 : float
        Area of its half-depth footprint (below), m².
    axes_m : ndarray, shape (2,)
        The **half-depth footprint** (the region the dent is deeper than half its depth: what
        the sheet sees of the contact), of the fitted dent: principal half-axes (major, minor)
        ``2 sqrt(eigenvalue)`` of its second moments (a disc of radius ``R`` gives ``R``);
        length and width are twice these. Metres.
    angle_rad : float
        Major axis from the lattice's i direction at the contact, towards j, in (−π/2, π/2].
    peak : tuple of int
        Joint ``(i, j)`` of the largest displacement.
    region : ndarray of bool, shape (rows, cols)
        The joints of the contact (without the skirt).
    ambiguous : bool
        The count here is uncertain: this contact may be two that the lattice cannot
        separate (an elongated dent whose two-contact alternative the data cannot exclude), or
        one of two reported where the evidence for two was close to the threshold.
    force_n_held : float or None
        Mean force of its track over the last few snapshots, N (`ContactTracker`); None
        untracked.
    force_std_n : float
        Standard deviation of ``force_n`` (the fit's covariance), N.
    position_std_m : float
        Standard deviation of the centre along its worst direction, metres.
    axes_std_m : ndarray, shape (2,)
        Standard deviations of ``axes_m``, metres.
    angle_std_rad : float
        Standard deviation of ``angle_rad``; `ANGLE_STD_UNKNOWN` where the footprint is too
        round for an orientation.
    contact_axes_m, contact_axes_std_m : ndarray, shape (2,)
        Half-axes ``2 sqrt(moment)`` of the fitted **pressure** (the contact patch itself,
        `response.pressure_half_axes`) and their standard deviations, metres. The patch's
        length is resolved; its width only where it exceeds the layer's spreading (docs).
    model : ContactModel or None
        The fitted pressure (warm start of the next snapshot's fit).
    onset_s : float or None
        Time its track began (`ContactTracker`), seconds.
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
    ambiguous: bool = False
    force_n_held: float | None = None
    force_std_n: float = float("nan")
    position_std_m: float = float("nan")
    axes_std_m: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    angle_std_rad: float = float("nan")
    contact_axes_m: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    contact_axes_std_m: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    model: ContactModel | None = field(default=None, repr=False)
    onset_s: float | None = None


_NB8 = [(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)]


def dilate(mask: np.ndarray) -> np.ndarray:
    """8-neighbour dilation by one joint."""
    out = mask.copy()
    out[1:] |= mask[:-1]
    out[:-1] |= mask[1:]
    out[:, 1:] |= out[:, :-1].copy()
    out[:, :-1] |= out[:, 1:].copy()
    return out


def _bilinear(P: np.ndarray, fi: float, fj: float) -> np.ndarray:
    rows, cols = P.shape[:2]
    i0 = min(max(int(np.floor(fi)), 0), rows - 2)
    j0 = min(max(int(np.floor(fj)), 0), cols - 2)
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


def _noise_map(displacement: np.ndarray, rest: RestShape) -> np.ndarray:
    if rest.noise_m is not None:
        return np.asarray(rest.noise_m, float)
    d = displacement.ravel()
    s = 1.4826 * np.median(np.abs(d - np.median(d)))
    return np.full(displacement.shape, s)


def _segment(d: np.ndarray, sigma: np.ndarray, s: DetectorSettings) -> np.ndarray:
    """Watershed with merging by prominence and separation: labels ``(rows, cols)`` (-1 none).
    The connected components of the joints above the region threshold are labelled at once
    (`scipy.ndimage.label`); only a component with more than one local maximum is cut by the
    watershed, joint by joint."""
    from scipy.ndimage import label as nd_label, maximum_filter

    region_thr = np.maximum(s.k_region * sigma, s.floor_m)
    inside = d > region_thr
    comp, n = nd_label(inside, structure=np.ones((3, 3), int))
    peaks = inside & (d >= maximum_filter(np.where(inside, d, -np.inf), size=3))
    per = np.bincount(comp[peaks], minlength=n + 1)
    out = comp - 1
    for c in np.flatnonzero(per[1:] > 1) + 1:
        sub = _watershed(np.where(comp == c, d, -np.inf), sigma, region_thr, s)
        m = sub >= 0
        out[m] = sub[m] + out.max() + 1
    return out


def _watershed(d: np.ndarray, sigma: np.ndarray, region_thr: np.ndarray, s: DetectorSettings
               ) -> np.ndarray:
    """`_segment`'s cut of one component (``d`` is -inf outside it)."""
    rows, cols = d.shape
    label = -np.ones(d.shape, int)
    parent: list[int] = []
    peak_of: list[tuple[int, int]] = []

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    cand = np.flatnonzero(d > region_thr)
    for flat in cand[np.argsort(-d.ravel()[cand])]:
        i, j = divmod(int(flat), cols)
        nbrs = [(d[i + di, j + dj], i + di, j + dj) for di, dj in _NB8
                if 0 <= i + di < rows and 0 <= j + dj < cols and label[i + di, j + dj] >= 0]
        if not nbrs:
            parent.append(len(parent))
            peak_of.append((i, j))
            label[i, j] = len(parent) - 1
            continue
        roots = sorted({find(label[a, b]) for _, a, b in nbrs}, key=lambda r: -d[peak_of[r]])
        # the joint joins its steepest-ascent neighbour's region (a saddle joint next to one peak
        # and the flank of another goes to the peak it is next to)
        _, si_, sj_ = max(nbrs)
        steep = find(label[si_, sj_])
        top = roots[0]
        for r in roots[1:]:
            pi, pj = peak_of[r]
            ti, tj = peak_of[top]
            prom = d[pi, pj] - d[i, j]
            need = max(s.k_prominence * sigma[pi, pj], s.prominence_fraction * d[pi, pj])
            if prom < need or np.hypot(pi - ti, pj - tj) < s.min_separation:
                parent[r] = top
        label[i, j] = find(steep)
    out = -np.ones(d.shape, int)
    m = label >= 0
    out[m] = [find(int(x)) for x in label[m]]
    return out


@dataclass
class _Frame:
    """A component's tangent frame: origin on the rest surface, ``e1`` along the lattice's i
    direction, and the map from frame coordinates to lattice indices."""

    index: np.ndarray
    origin: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    normal: np.ndarray
    to_index: np.ndarray      # (2, 2): frame (u, v) metres -> lattice index offsets


#: A part's frame is anchored at its centroid rounded to this many link lengths: frames are then
#: cached per rest shape (its tangent plane barely turns within it; the fitted geometry is
#: relative to the anchor wherever it is).
FRAME_GRID = 0.1


def _frame(rest: RestShape, fi: float, fj: float) -> _Frame:
    """The tangent frame at ``(fi, fj)`` rounded to `FRAME_GRID`, cached on the rest shape."""
    key = (round(fi / FRAME_GRID), round(fj / FRAME_GRID))
    cache = rest.__dict__.setdefault("_frames", {})
    if key not in cache:
        if len(cache) > 4096:
            cache.clear()
        cache[key] = _make_frame(rest, key[0] * FRAME_GRID, key[1] * FRAME_GRID)
    return cache[key]


def _make_frame(rest: RestShape, fi: float, fj: float) -> _Frame:
    nrm = _bilinear(rest.normals, fi, fj)
    nrm /= np.linalg.norm(nrm)
    hi_i, lo_i = min(fi + 0.5, rest.rows - 1), max(fi - 0.5, 0)
    hi_j, lo_j = min(fj + 0.5, rest.cols - 1), max(fj - 0.5, 0)
    di = (_bilinear(rest.joints, hi_i, fj) - _bilinear(rest.joints, lo_i, fj)) / (hi_i - lo_i)
    dj = (_bilinear(rest.joints, fi, hi_j) - _bilinear(rest.joints, fi, lo_j)) / (hi_j - lo_j)
    e1 = di - (di @ nrm) * nrm
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(nrm, e1)
    M = np.array([[di @ e1, dj @ e1], [di @ e2, dj @ e2]])   # index offsets -> (u, v)
    return _Frame(np.array([fi, fj]), _bilinear(rest.joints, fi, fj), e1, e2, nrm,
                  np.linalg.inv(M))


def _moments_start(XY: np.ndarray, dv: np.ndarray, sel: np.ndarray, a0: float
                   ) -> ContactGeometry:
    """A contact's first geometry from the joints ``sel`` above half their depth: the
    displacement-weighted centroid and the difference of the principal second moments (the
    dent's spreading adds the same moment in every direction, a line of length ``2ℓ`` adds
    ``ℓ² / 3`` along itself)."""
    w = np.where(sel, dv, 0.0)
    top = w.max()
    w = np.where(w >= 0.5 * top, w, 0.0)
    mu = w @ XY / w.sum()
    X = XY - mu
    C = X.T @ (X * w[:, None]) / w.sum()
    ev, evec = np.linalg.eigh(C)
    th = float(np.arctan2(evec[1, 1], evec[0, 1]))
    hl = float(np.sqrt(max(3.0 * (ev[1] - ev[0]), 0.0)))
    return ContactGeometry(float(mu[0]), float(mu[1]), a0, hl, th)


class _Context:
    """What every component's fit shares in one snapshot."""

    def __init__(self, d, sigma, rest, foam, settings, surf):
        self.d, self.sigma, self.rest, self.settings, self.surf = d, sigma, rest, settings, surf
        self.lam = foam.shear_length_m
        self.kmap = rest.k_map(foam)
        self.noise = float(np.median(sigma))
        self.L = rest.link_length
        L = self.L
        self.samples = rest.noise_samples_m
        self.lo = np.array([-3 * L, -3 * L, 0.1 * L, 0.0, -np.inf])
        self.hi = np.array([3 * L, 3 * L, 2.5 * L, 5 * L, np.inf])

    def fit(self, dv, XY, owner, starts, ks, max_iter=10, mask=None) -> FitResult:
        """`fit.fit_contacts` with the settings' prior; ``mask`` the joints of ``dv`` (their
        noise samples give the covariance, `RestShape.noise_samples_m`)."""
        s = self.settings
        ns = None if mask is None or self.samples is None else self.samples[:, mask]
        return fit_contacts(dv, XY, owner, starts, self.lam, ks, [(self.lo, self.hi)] * len(starts),
                            max_iter=max_iter, prior_a=s.contact_radius_m,
                            prior_a_std=s.contact_radius_std_m,
                            prior_length_std=s.contact_length_std_m, noise_m=self.noise,
                            noise_samples=ns)

    def valid(self, fit: FitResult) -> bool:
        """Every contact pushes (a clear force, a dent that would have been detected on its
        own), no two centres are closer than the lattice can separate
        (`DetectorSettings.min_separation`) and no two pressure lines come closer than half that
        (two pieces of one line that abut are one contact)."""
        F, sF = fit.force_n, fit.force_std()
        if np.any(F <= 0) or np.any(F < 2.0 * sF):
            return False
        if fit.responses is not None and len(F) > 1:
            # every contact's own dent reaches the detection threshold somewhere: a faint
            # second "contact" soaking up a lump of noise would never have been detected
            deep = np.max(fit.responses * F[None, :], axis=0)
            if np.any(deep < self.settings.k_detect * self.noise):
                return False
        g = fit.geometry
        sep = self.settings.min_separation * self.L
        return all(np.hypot(g[i].u - g[j].u, g[i].v - g[j].v) >= sep
                   and _segment_distance(g[i], g[j]) >= 0.5 * sep
                   for i in range(len(g)) for j in range(i + 1, len(g)))

    def detectable(self, dv, XY, owner, one: FitResult, k: float) -> float:
        """How clearly the data would have shown two contacts instead of ``one``'s line: the
        pair with the line's moment (two round contacts at ``± ℓ / √3`` along it, half the force
        each, the prior's radius), noise-free, refitted as one line; the residual left, in noise
        variances. Below `DetectorSettings.split_gain` the split test could not have seen such
        a pair."""
        g = one.geometry[0]
        e = np.array([np.cos(g.angle), np.sin(g.angle)])
        a0 = self.settings.contact_radius_m
        pair = np.zeros(dv.size)
        for s in (-1.0, 1.0):
            c = np.array([g.u, g.v]) + s * g.half_length / np.sqrt(3.0) * e
            pair += 0.5 * one.force_n[0] * line_response(XY, c, a0, 0.0, 0.0, self.lam, k)
        refit = self.fit(pair, [XY], owner, [g], [k], 6)
        return refit.rss / self.noise ** 2


def _segment_distance(g1: ContactGeometry, g2: ContactGeometry) -> float:
    """Smallest distance between two contacts' pressure lines, metres."""
    t = np.linspace(-1.0, 1.0, 9)[:, None]
    p1 = np.array([g1.u, g1.v]) + t * g1.half_length * np.array([np.cos(g1.angle),
                                                                 np.sin(g1.angle)])
    p2 = np.array([g2.u, g2.v]) + t * g2.half_length * np.array([np.cos(g2.angle),
                                                                 np.sin(g2.angle)])
    return float(np.min(np.linalg.norm(p1[:, None] - p2[None], axis=2)))


def _split_starts(g: ContactGeometry, L: float, a0: float) -> list[list[ContactGeometry]]:
    """Two-contact starts from one contact: the pair with the line's moment (round, at
    ``± ℓ / √3``), the line cut in two along itself, and two lines side by side across it."""
    e = np.array([np.cos(g.angle), np.sin(g.angle)])
    p = np.array([-e[1], e[0]])
    out = []
    if g.half_length > 0.5 * L:
        s = g.half_length / np.sqrt(3.0) * e
        out.append([ContactGeometry(g.u + s[0], g.v + s[1], a0, 0.1 * L, g.angle),
                    ContactGeometry(g.u - s[0], g.v - s[1], a0, 0.1 * L, g.angle)])
        s = 0.55 * g.half_length * e
        hl = 0.35 * g.half_length
        out.append([ContactGeometry(g.u + s[0], g.v + s[1], a0, hl, g.angle),
                    ContactGeometry(g.u - s[0], g.v - s[1], a0, hl, g.angle)])
    s = 0.9 * L * p
    out.append([ContactGeometry(g.u + s[0], g.v + s[1], a0, g.half_length, g.angle),
                ContactGeometry(g.u - s[0], g.v - s[1], a0, g.half_length, g.angle)])
    return out


@dataclass
class _Part:
    """One connected component of detected joints: its mask, the watershed's proposals, the
    previous snapshot's contacts in it, its support (mask and skirt), frame and stiffness."""

    mask: np.ndarray
    regions: list
    warm: list
    support: np.ndarray
    frame: _Frame
    k: float
    geometry: list | None = None     # in the part's frame
    ambiguous: bool = False


def _part(ctx: _Context, cm: np.ndarray, regions: list, warm: list) -> _Part:
    d = ctx.d
    support = cm.copy()
    for _ in range(ctx.settings.skirt):
        support = dilate(support)
    w = np.where(cm, d, 0.0)
    w = np.where(w >= 0.5 * w.max(), w, 0.0)
    ii, jj = np.nonzero(w)
    fi = float(w[ii, jj] @ ii / w[ii, jj].sum())
    fj = float(w[ii, jj] @ jj / w[ii, jj].sum())
    fr = _frame(ctx.rest, fi, fj)
    k = float(_bilinear(ctx.kmap[..., None], fi, fj)[0])
    p = _Part(cm, regions, warm, support, fr, k)
    if warm:
        p.geometry = [_in_frame(m, fr) for m in warm]
    return p


def _in_frame(m: ContactModel, fr: _Frame) -> ContactGeometry:
    c = m.centre - fr.origin
    t = m.direction
    return ContactGeometry(float(c @ fr.e1), float(c @ fr.e2), m.half_width_m, m.half_length_m,
                           float(np.arctan2(t @ fr.e2, t @ fr.e1)))


def _local(ctx: _Context, p: _Part, mask: np.ndarray) -> np.ndarray:
    """Joints of ``mask`` in the part's frame, shape (n, 2), metres."""
    P = ctx.surf[mask] - p.frame.origin
    return np.stack([P @ p.frame.e1, P @ p.frame.e2], axis=1)


def _select(ctx: _Context, p: _Part) -> None:
    """How many contacts the part holds, and their geometry: the watershed's proposals (or
    the previous snapshot's contacts), one fewer (proposals merged into one line: a finger the
    watershed cut in two), one more (one line split along or across: two contacts too close
    for the watershed). More contacts are kept when they lower the residual by
    `DetectorSettings.split_gain` noise variances; by `DetectorSettings.ambiguous_gain` or
    more, or where a pair would not have shown at this noise (`_Context.detectable`), the one
    contact is flagged ambiguous."""
    s = ctx.settings
    d = ctx.d
    XY = _local(ctx, p, p.support)
    dv = d[p.support]
    owner = np.zeros(dv.size, int)
    a0 = s.contact_radius_m
    noise2 = ctx.noise ** 2
    k = p.k
    if p.geometry is not None:
        starts = p.geometry
    else:
        starts = [_moments_start(XY, dv, r[p.support], a0) for r in p.regions]
    best = ctx.fit(dv, [XY] * len(starts), owner, starts, [k] * len(starts), mask=p.support)
    ambiguous = False
    if len(starts) >= 2:
        one = _moments_start(XY, dv, p.mask[p.support], a0)
        h1 = ctx.fit(dv, [XY], owner, [one], [k], mask=p.support)
        gain = (h1.rss - best.rss) / noise2
        if not ctx.valid(best) or gain < s.split_gain:
            ambiguous = ctx.valid(best) and gain >= s.ambiguous_gain
            best = h1
    if len(best.geometry) == 1:
        g = best.geometry[0]
        # a line of half-length ℓ has the moment of two points at ± ℓ / √3
        long_enough = 2.0 * g.half_length / np.sqrt(3.0) >= s.min_separation * ctx.L
        if best.rss / (dv.size * noise2) > s.split_try or long_enough:
            alt = None
            for st in _split_starts(g, ctx.L, a0):
                h2 = ctx.fit(dv, [XY, XY], owner, st, [k, k], mask=p.support)
                if ctx.valid(h2) and (alt is None or h2.rss < alt.rss):
                    alt = h2
            if alt is not None:
                gain = (best.rss - alt.rss) / noise2
                if gain >= s.split_gain:
                    best = alt
                elif gain >= s.ambiguous_gain:
                    ambiguous = True
            if len(best.geometry) == 1 and long_enough and not ambiguous:
                # no evidence for two; but would two at its ends have shown at this noise?
                ambiguous = ctx.detectable(dv, XY, owner, best, k) < s.split_gain
    p.geometry = best.geometry
    p.ambiguous = ambiguous


def find_contacts(displacement: np.ndarray, rest: RestShape, foam: Foam,
                  settings: DetectorSettings = DetectorSettings(),
                  aligned: np.ndarray | None = None, previous=()) -> list[Contact]:
    """Contacts in a displacement field (module docstring, steps 3-4).

    Parameters
    ----------
    displacement : ndarray, shape (rows, cols)
        Normal displacement into the foam, metres (`deformation`).
    rest : RestShape
    foam : Foam
    settings : DetectorSettings
    aligned : ndarray, shape (rows, cols, 3), optional
        The joints overlaid on the rest shape (`deformation`'s second result), metres: the fit
        samples the dent where the joints are (the sheet slides towards a dent), at their foot
        points on the rest surface (``aligned + d n``). Default: the rest joints.
    previous : sequence of Contact, optional
        The previous snapshot's contacts (with their `ContactModel`): a component holding some
        of their centres starts from their geometry and count, and is only re-counted when the
        fit leaves a residual above `DetectorSettings.split_try` or a contact loses its force
        or comes closer than `DetectorSettings.min_separation` to another.

    Returns
    -------
    list of Contact
        Untracked (``id = -1``), deepest first.
    """
    from scipy.ndimage import label as nd_label

    d = np.asarray(displacement, float)
    if d.shape != rest.joints.shape[:2]:
        raise ValueError(f"Expected `displacement` to have shape {rest.joints.shape[:2]}, "
                         f"got {d.shape}.")
    s = settings
    sigma = _noise_map(d, rest)
    labels = _segment(d, sigma, s)
    detect_thr = np.maximum(s.k_detect * sigma, s.floor_m)
    ids = [int(x) for x in np.unique(labels) if x >= 0]
    ids = [r for r in ids if np.any((labels == r) & (d > detect_thr))]
    if not ids:
        return []
    surf = rest.joints if aligned is None else (np.asarray(aligned, float)
                                                + d[..., None] * rest.normals)
    ctx = _Context(d, sigma, rest, foam, s, surf)
    comp, nc = nd_label(np.isin(labels, ids), structure=np.ones((3, 3), int))
    prev = [(p.model, p.index, p.ambiguous) for p in previous if p.model is not None]
    parts = []
    for ci in range(1, nc + 1):
        cm = comp == ci
        regions = [labels == r for r in ids if np.any((labels == r) & cm)]
        near = dilate(cm)
        inside = [near[min(max(int(round(idx[0])), 0), d.shape[0] - 1),
                       min(max(int(round(idx[1])), 0), d.shape[1] - 1)] for _, idx, _ in prev]
        warm = [m for (m, _, _), y in zip(prev, inside) if y]
        parts.append(_part(ctx, cm, regions, warm))
        parts[-1].ambiguous = any(a for (_, _, a), y in zip(prev, inside) if y)
    # clusters: parts whose supports overlap are fitted together (their tails add up)
    group = list(range(len(parts)))
    for a in range(len(parts)):
        for b in range(a + 1, len(parts)):
            if group[a] != group[b] and np.any(parts[a].support & parts[b].support):
                ga, gb = group[a], group[b]
                group = [ga if g == gb else g for g in group]
    out = []
    for gid in sorted(set(group)):
        members = [p for p, g in zip(parts, group) if g == gid]
        out += _cluster(ctx, members)
    out.sort(key=lambda c: -c.depth_m)
    return out


def _cluster(ctx: _Context, members: list) -> list[Contact]:
    """Fit a cluster of parts jointly (per part an offset over its support); parts without a
    warm start, or whose warm fit is poor, are counted first (`_select`)."""
    d = ctx.d
    union = np.zeros(d.shape, bool)
    for p in members:
        union |= p.support
    # a joint's offset is that of the part it is nearest to (dilation order)
    own = -np.ones(d.shape, int)
    grow = [p.mask for p in members]
    for c, g in enumerate(grow):
        own[g] = c
    for _ in range(ctx.settings.skirt):
        grow = [dilate(g) for g in grow]
        for c, g in enumerate(grow):
            own[g & (own < 0)] = c
    owner = own[union]
    dv = d[union]
    XY = [_local(ctx, p, union) for p in members]
    noise2 = ctx.noise ** 2

    def joint(max_iter):
        starts, xys, ks, idx = [], [], [], []
        for c, p in enumerate(members):
            for g in p.geometry:
                starts.append(g)
                xys.append(XY[c])
                ks.append(p.k)
                idx.append(c)
        return ctx.fit(dv, xys, owner, starts, ks, max_iter, mask=union), idx

    fit = None
    if all(p.geometry is not None for p in members):   # warm: one joint fit, then a check
        fit, idx = joint(2)
        res = fit.residual
        redo = False
        for c, p in enumerate(members):
            mine = [i for i, x in enumerate(idx) if x == c]
            sub = fit.geometry[mine[0]:mine[-1] + 1]
            rc = res[owner == c]
            poor = rc @ rc / (rc.size * noise2) > ctx.settings.split_try
            lost = not ctx.valid(_sub_fit(fit, mine))
            if poor or lost or p.ambiguous:   # an uncertain count is looked at every time
                p.geometry = None
                redo = True
            else:
                p.geometry = sub
        if not redo:
            return _contacts_of(ctx, fit, idx, members, union)
    for p in members:
        if p.geometry is None:
            _select(ctx, p)
    fit, idx = joint(6)
    return _contacts_of(ctx, fit, idx, members, union)


def _sub_fit(fit: FitResult, which: list) -> FitResult:
    """The part of a joint fit that concerns the contacts ``which`` (forces, their
    covariance, geometry): enough for `_Context.valid`."""
    m = len(fit.geometry)
    keep = list(which)
    cov = fit.cov[np.ix_(keep, keep)] if fit.cov.shape[0] >= m else fit.cov
    return FitResult([fit.geometry[i] for i in which], fit.force_n[which], fit.offset_m, cov,
                     fit.rss, fit.n, fit.iterations, fit.residual,
                     None if fit.responses is None else fit.responses[:, which])


def _footprint_spread(g: ContactGeometry, Cp: np.ndarray, lam: float
                      ) -> tuple[np.ndarray, float, np.ndarray, float]:
    """The half-depth footprint's half-axes and area, and the standard deviations of its
    half-axes and of its angle, from the covariance ``Cp`` of the fitted ``(u, v, a, q_x,
    q_y)`` by sigma points (the unscented transform: ``mean ± √3 ·`` the covariance's
    square-root columns over ``(a, q)``): smooth where the footprint is round (a linearisation
    there says nothing about the angle). An angle that spreads by more than a uniform one would
    is `ANGLE_STD_UNKNOWN`."""
    x0 = np.array([g.a, g.half_length * np.cos(g.angle), g.half_length * np.sin(g.angle)])
    C3 = Cp[2:5, 2:5]
    ok = bool(np.all(np.isfinite(C3)))
    if ok:
        ev, V = np.linalg.eigh(0.5 * (C3 + C3.T))
        S = V * np.sqrt(np.maximum(ev, 0.0) * 3.0)        # columns: √3 × the square root
        pts = np.concatenate([x0[None, :], x0 + S.T, x0 - S.T])   # (7, 3)
    else:
        pts = x0[None, :]
    axes, area = half_depth_footprint(np.maximum(pts[:, 0], 1e-4),
                                      np.hypot(pts[:, 1], pts[:, 2]), lam)
    if not ok:
        return axes[0], float(area[0]), np.full(2, np.nan), ANGLE_STD_UNKNOWN
    ax_std = np.sqrt(np.mean((axes[1:] - axes[0]) ** 2, axis=0))
    dth = np.arctan2(pts[1:, 2], pts[1:, 1]) - g.angle
    dth = (dth + np.pi / 2) % np.pi - np.pi / 2
    th_std = float(np.sqrt(np.mean(dth ** 2)))
    return axes[0], float(area[0]), ax_std, min(th_std, ANGLE_STD_UNKNOWN)


def _contacts_of(ctx: _Context, fit: FitResult, idx: list, members: list, union: np.ndarray
                 ) -> list[Contact]:
    """Every contact's figures from the cluster's fit (`Contact`)."""
    d, rest, s, lam = ctx.d, ctx.rest, ctx.settings, ctx.lam
    m = len(fit.geometry)
    # every joint of the union goes to the contact whose fitted dent is deepest there
    dents = fit.responses * fit.force_n[None, :]
    best = np.argmax(dents, axis=1)
    region_thr = np.maximum(s.k_region * ctx.sigma, s.floor_m)
    inside = (d > region_thr)[union]
    if s.force_model == "sum":
        tot = dents.sum(axis=1)
        share = np.where(tot[:, None] > 0, dents / np.where(tot > 0, tot, 1.0)[:, None],
                         1.0 / m)
        sums = share.T @ (ctx.kmap * d * rest.areas)[union]
    out = []
    fstd = fit.force_std()
    for c, (g, i) in enumerate(zip(fit.geometry, idx)):
        fr = members[i].frame
        reg = np.zeros(d.shape, bool)
        reg[union] = inside & (best == c)
        if not reg.any():
            reg[union] = best == c
        pk = np.unravel_index(np.argmax(np.where(reg, d, -np.inf)), d.shape)
        index = np.clip(fr.index + fr.to_index @ np.array([g.u, g.v]), 0,
                        [rest.rows - 1, rest.cols - 1])
        nrm = _bilinear(rest.normals, *index)
        Cp = fit.parameter_cov(c)
        axes, area, ax_std, th_std = _footprint_spread(g, Cp, lam)
        if axes[0] < ORIENTATION_MIN_RATIO * axes[1]:
            th_std = ANGLE_STD_UNKNOWN
        cax, cax_std = fit.half_axes(c)
        ang = float(np.arctan2(np.sin(2 * g.angle), np.cos(2 * g.angle)) / 2.0)
        if ang <= -np.pi / 2:
            ang += np.pi
        e = np.cos(g.angle) * fr.e1 + np.sin(g.angle) * fr.e2
        out.append(Contact(
            id=-1, index=index, position=_bilinear(rest.joints, *index),
            normal=nrm / np.linalg.norm(nrm), depth_m=float(d[pk]),
            force_n=float(sums[c] if s.force_model == "sum" else fit.force_n[c]),
            area_m2=area, axes_m=axes, angle_rad=ang, peak=(int(pk[0]), int(pk[1])),
            region=reg, ambiguous=bool(members[i].ambiguous), force_std_n=float(fstd[c]),
            position_std_m=float(np.sqrt(max(np.linalg.eigvalsh(Cp[:2, :2]).max(), 0.0))),
            axes_std_m=ax_std, angle_std_rad=th_std,
            contact_axes_m=cax, contact_axes_std_m=cax_std,
            model=ContactModel(fr.origin + g.u * fr.e1 + g.v * fr.e2, e, float(g.a),
                               float(g.half_length))))
    return out
