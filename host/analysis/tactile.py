"""Tactile sensing: contacts and forces from the sheet wrapped on foam (docs/tactile.md).

The paper's application: "The number, shapes, and positions of contact objects are obtained
because the whole surface profile of the material is observed by the sheet. The contact forces
are also estimated from the surface deformation and Young's modulus of the material."

Pipeline for one snapshot (`TactileSensor.process`):

1. Shape: `host.estimator.estimate` with the **rest shape as the prior** (``rest=``), every
   snapshot (not the previous snapshot: a flat level sheet is the paper's unsolvable Case 1 for
   yaw, and chaining priors would let its horizontal layout drift; heights need no yaw).
2. Deformation (`deformation`): the estimate overlaid on the rest shape by a trimmed rigid fit
   (rotation + translation over the joints that did not move, so contacts do not tilt the fit;
   when contacts are found, the fit is redone without their regions grown by one joint, and the
   contacts found again), then the displacement of every joint along the rest normal, **positive into
   the foam**, metres.
3. Contacts (`find_contacts`): joints above a threshold ``τ_i = max(k_detect σ_i, floor)`` (``σ_i``
   the joint's displacement noise, learned from an untouched period or, failing that, a robust
   spread of the current frame), grown from local maxima in descending order (a watershed):
   where two regions meet, the lower one is merged into the higher if its prominence above the
   meeting point is below ``max(k_prominence σ, prominence_fraction · its peak)`` or the peaks
   are closer than ``min_separation`` link lengths. Each region (plus a skirt of ``skirt``
   joints, for the shallow tail of the dent) is one contact.
4. Per contact: depth (largest displacement), position (the displacement-weighted centroid of
   the joints above half the depth, in fractional lattice indices, mapped onto the rest surface),
   shape (area of the joints above half the depth; principal half-axes ``2 sqrt(eigenvalues)`` of
   the weighted second moments in the rest tangent plane, so a uniform disc of radius ``a`` gives
   ``a``; orientation of the major axis from the lattice's i direction), and force by the
   foam model (`Foam`): ``F = k Σ w_i A_i`` over the region and skirt, ``A_i`` the joint's rest
   area. The total force is the sum over contacts.
5. Tracking (`ContactTracker`): contacts matched to the previous snapshot's by minimum total
   distance (Hungarian) within a gate; unmatched contacts get new ids; a track survives
   ``max_missed`` snapshots without a match.

The force model is the virtual foam's (`virtual_sheet.foam`): a thin layer as a Vlasov
two-parameter foundation, ``p = k w − G_p ∇²w`` with ``k = E_oed / h``; the shear term integrates
to zero, so ``F = k ∫ w dA`` exactly — the integral, sampled at the joints, is what is read here.

This module needs numpy and scipy only; it does not import `virtual_sheet`.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from protocol.lattice import joint_normals

from .estimator import ShapeEstimate, estimate
from .metrics import rigid_fit

__all__ = ["Foam", "RestShape", "Contact", "DetectorSettings", "TactileFrame", "deformation",
           "find_contacts", "ContactTracker", "TactileSensor", "plot_frame", "rigid_fit",
           "lattice_index"]


# ---------------------------------------------------------------------------------------------
# Foam
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class Foam:
    """The foam under the sheet, as the host knows it (docs/tactile.md, "Foam model").

    Attributes
    ----------
    thickness_m : float
        ``h``, metres.
    youngs_modulus_pa : float
        ``E``, Pa.
    poisson : float
        ``ν``, in [0, 0.45].
    """

    thickness_m: float = 0.02
    youngs_modulus_pa: float = 20e3
    poisson: float = 0.25

    def __post_init__(self) -> None:
        for name in ("thickness_m", "youngs_modulus_pa"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"Invalid {name}: {v!r} (need a finite value > 0)")
        if not (0.0 <= self.poisson <= 0.45):
            raise ValueError(f"Invalid poisson: {self.poisson!r} (need 0 <= nu <= 0.45)")

    @property
    def k_pa_per_m(self) -> float:
        """``k = E_oed / h``, Pa/m, with ``E_oed = E (1 − ν) / ((1 + ν)(1 − 2ν))``."""
        nu = self.poisson
        e_oed = self.youngs_modulus_pa * (1 - nu) / ((1 + nu) * (1 - 2 * nu))
        return e_oed / self.thickness_m

    @property
    def shear_length_m(self) -> float:
        """Spreading length ``λ = h sqrt((1 − 2ν) / (6 (1 − ν)))`` of the layer, metres: a dent's
        tail decays about as ``exp(−r / λ)``."""
        nu = self.poisson
        return self.thickness_m * np.sqrt((1 - 2 * nu) / (6 * (1 - nu)))


# ---------------------------------------------------------------------------------------------
# Rest shape
# ---------------------------------------------------------------------------------------------



def _joint_areas(P: np.ndarray) -> np.ndarray:
    """Rest area of every joint: a quarter of each adjacent cell (trapezoid rule), m²."""
    d1 = P[1:, 1:] - P[:-1, :-1]
    d2 = P[:-1, 1:] - P[1:, :-1]
    cell = 0.5 * np.linalg.norm(np.cross(d1, d2), axis=-1)
    out = np.zeros(P.shape[:2])
    out[:-1, :-1] += cell / 4
    out[1:, 1:] += cell / 4
    out[:-1, 1:] += cell / 4
    out[1:, :-1] += cell / 4
    return out


def _yaws_of(P: np.ndarray) -> np.ndarray:
    """Yaw of every link (DESIGN.md link order) from joints: sensor x is ``Rz(γ) Ry(β) e_x``, so
    ``γ = atan2(d_y, d_x)`` of the link vector."""
    di = (P[1:, :] - P[:-1, :]).reshape(-1, 3)
    dj = (P[:, 1:] - P[:, :-1]).reshape(-1, 3)
    d = np.concatenate([di, dj])
    return np.arctan2(d[:, 1], d[:, 0])


@dataclass(frozen=True, eq=False)
class _Prior:
    """What `estimate` reads from ``previous``: joints and yaws."""

    joints: np.ndarray
    yaws: np.ndarray


@dataclass(frozen=True, eq=False)
class RestShape:
    """The sheet untouched: joints, normals, joint areas and displacement noise.

    Attributes
    ----------
    joints : ndarray, shape (rows, cols, 3)
        Metres, the frame the deformation is reported in.
    link_length : float
        ``L``, metres.
    noise_m : ndarray, shape (rows, cols), optional
        Standard deviation of every joint's normal displacement while untouched, metres (None:
        unknown; `find_contacts` then uses a robust spread of each frame).
    yaws : ndarray, shape (n_links,), optional
        Link yaws for the estimator's prior (default: from the joints).
    """

    joints: np.ndarray
    link_length: float
    noise_m: np.ndarray | None = None
    yaws: np.ndarray | None = None

    def __post_init__(self) -> None:
        P = np.array(self.joints, dtype=float)
        if P.ndim != 3 or P.shape[2] != 3 or min(P.shape[:2]) < 2:
            raise ValueError(f"Expected `joints` to have shape (rows, cols, 3), got {P.shape}.")
        object.__setattr__(self, "joints", P)
        if self.noise_m is not None and np.shape(self.noise_m) != P.shape[:2]:
            raise ValueError(f"Expected `noise_m` to have shape {P.shape[:2]}, got "
                             f"{np.shape(self.noise_m)}.")
        yaws = _yaws_of(P) if self.yaws is None else np.asarray(self.yaws, float)
        object.__setattr__(self, "yaws", yaws)
        object.__setattr__(self, "normals", joint_normals(P))
        object.__setattr__(self, "areas", _joint_areas(P))

    @property
    def rows(self) -> int:
        return self.joints.shape[0]

    @property
    def cols(self) -> int:
        return self.joints.shape[1]

    @property
    def prior(self) -> _Prior:
        """The estimator's ``previous=``: the rest joints and yaws."""
        return _Prior(self.joints, self.yaws)

    @classmethod
    def from_joints(cls, joints: np.ndarray, link_length: float,
                    noise_m: np.ndarray | None = None) -> "RestShape":
        """A known rest shape (e.g. the body's design), joints ``(rows, cols, 3)`` in metres."""
        return cls(joints=joints, link_length=float(link_length), noise_m=noise_m)

    @classmethod
    def learn(cls, snapshots: Sequence[ShapeEstimate | np.ndarray],
              link_length: float | None = None, noise_floor_fraction: float = 1.0
              ) -> "RestShape":
        """Learn the rest shape from an untouched period.

        Every snapshot's joints are overlaid on the first (rigid least squares), averaged; the
        noise of every joint is the standard deviation of its normal displacement from the mean,
        floored at ``noise_floor_fraction`` × the median over joints (few snapshots make single
        joints look quieter than they are).

        Parameters
        ----------
        snapshots : sequence of ShapeEstimate or ndarray, shape (rows, cols, 3)
            At least 2 (better 20+) shapes of the untouched sheet.
        link_length : float, optional
            ``L``, metres (default: from the estimates).
        """
        snaps = list(snapshots)
        if len(snaps) < 2:
            raise ValueError(f"RestShape.learn needs at least 2 snapshots, got {len(snaps)}.")
        if link_length is None:
            if not isinstance(snaps[0], ShapeEstimate):
                raise ValueError("RestShape.learn: give link_length with plain joint arrays.")
            link_length = snaps[0].link_length
        P = [np.asarray(s.joints if isinstance(s, ShapeEstimate) else s, float) for s in snaps]
        shape = P[0].shape
        if any(p.shape != shape for p in P):
            raise ValueError(f"RestShape.learn: snapshots of different shapes "
                             f"{sorted({p.shape for p in P})}.")
        ref = P[0].reshape(-1, 3)
        al = np.array([rigid_fit(p.reshape(-1, 3), ref) for p in P])
        mean = al.mean(axis=0)
        al = np.array([rigid_fit(a, mean) for a in al])
        mean = al.mean(axis=0).reshape(shape)
        n = joint_normals(mean)
        d = np.einsum("sjk,jk->sj", al - mean.reshape(-1, 3), n.reshape(-1, 3))
        noise = d.std(axis=0, ddof=1).reshape(shape[:2])
        noise = np.maximum(noise, noise_floor_fraction * np.median(noise))
        yaws = None
        if all(isinstance(s, ShapeEstimate) for s in snaps):
            y = np.array([s.yaws for s in snaps])
            yaws = np.angle(np.exp(1j * y).mean(axis=0))
        return cls(joints=mean, link_length=float(link_length), noise_m=noise, yaws=yaws)


# ---------------------------------------------------------------------------------------------
# Deformation
# ---------------------------------------------------------------------------------------------

def deformation(joints: np.ndarray, rest: RestShape, *, exclude: np.ndarray | None = None,
                trim_sigma: float = 3.0, trim_floor_m: float | None = None, iterations: int = 4
                ) -> tuple[np.ndarray, np.ndarray]:
    """Normal displacement of every joint against the rest shape.

    The joints are overlaid on the rest joints by a rigid fit that ignores moved joints
    (iterated: weight 0 for ``|d| > max(trim_sigma · σ, trim_floor_m)``, ``σ`` a robust spread
    of ``d``), then ``d_i = (rest_i − joints_i) · n_i`` with ``n_i`` the rest normal (top face,
    pointing out of the foam).

    Parameters
    ----------
    joints : ndarray, shape (rows, cols, 3)
        Estimated joints, metres, any rigid placement (the estimator's gauge).
    rest : RestShape
    exclude : ndarray of bool, shape (rows, cols), optional
        Joints known to be moved (e.g. contacts found in a first pass with their skirts): left
        out of the fit, so the dents' shallow tails do not bias it.

    Returns
    -------
    displacement : ndarray, shape (rows, cols)
        Metres, positive into the foam.
    aligned : ndarray, shape (rows, cols, 3)
        The joints overlaid on the rest shape, metres, rest frame.
    """
    P = np.asarray(joints, float)
    if P.shape != rest.joints.shape:
        raise ValueError(f"Expected `joints` to have shape {rest.joints.shape}, got {P.shape}.")
    src, dst = P.reshape(-1, 3), rest.joints.reshape(-1, 3)
    n = rest.normals.reshape(-1, 3)
    floor = 0.01 * rest.link_length if trim_floor_m is None else float(trim_floor_m)
    allowed = np.ones(len(src), bool) if exclude is None else ~np.asarray(exclude, bool).ravel()
    if allowed.sum() < 4:
        allowed = np.ones(len(src), bool)
    moved = src - np.median((src - dst)[allowed], axis=0)  # robust start: translation only
    for _ in range(iterations):
        d = np.sum((dst - moved) * n, axis=1)
        r = d - np.median(d[allowed])
        s = 1.4826 * np.median(np.abs(r[allowed]))
        keep = allowed & (np.abs(r) <= max(trim_sigma * s, floor))
        if keep.sum() < 4:
            keep = allowed
        moved = rigid_fit(src, dst, keep.astype(float))
    d = np.sum((dst - moved) * n, axis=1)
    return d.reshape(P.shape[:2]), moved.reshape(P.shape)


# ---------------------------------------------------------------------------------------------
# Contacts
# ---------------------------------------------------------------------------------------------

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
    """

    k_detect: float = 5.0
    k_region: float = 3.0
    floor_m: float = 1e-4
    k_prominence: float = 4.0
    prominence_fraction: float = 0.3
    min_separation: float = 1.5
    skirt: int = 2


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
        ``k Σ w_i A_i`` over the region and skirt, N.
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


def _noise_map(displacement: np.ndarray, rest: RestShape) -> np.ndarray:
    if rest.noise_m is not None:
        return np.asarray(rest.noise_m, float)
    d = displacement.ravel()
    s = 1.4826 * np.median(np.abs(d - np.median(d)))
    return np.full(displacement.shape, s)


def _segment(d: np.ndarray, sigma: np.ndarray, s: DetectorSettings) -> np.ndarray:
    """Watershed with merging by prominence and separation; labels ``(rows, cols)``, -1 none."""
    rows, cols = d.shape
    region_thr = np.maximum(s.k_region * sigma, s.floor_m)
    inside = d > region_thr
    label = -np.ones(d.shape, int)
    parent: list[int] = []
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
        label[i, j] = top
    out = -np.ones(d.shape, int)
    m = label >= 0
    out[m] = [find(int(x)) for x in label[m]]
    return out


def find_contacts(displacement: np.ndarray, rest: RestShape, foam: Foam,
                  settings: DetectorSettings = DetectorSettings()) -> list[Contact]:
    """Contacts in a displacement field (module docstring, steps 3-4).

    Parameters
    ----------
    displacement : ndarray, shape (rows, cols)
        Normal displacement into the foam, metres (`deformation`).
    rest : RestShape
    foam : Foam
    settings : DetectorSettings

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
    labels = _segment(d, sigma, settings)
    detect_thr = np.maximum(settings.k_detect * sigma, settings.floor_m)
    ids = [int(x) for x in np.unique(labels) if x >= 0]
    ids = [r for r in ids if np.any((labels == r) & (d > detect_thr))]
    # skirts: grow every region by dilation into unlabelled joints, deepest neighbour wins
    grown = np.where(np.isin(labels, ids), labels, -1)
    for _ in range(settings.skirt):
        new = grown.copy()
        for i, j in zip(*np.nonzero(grown < 0)):
            best, best_d = -1, -np.inf
            for di, dj in _NB8:
                a, b = i + di, j + dj
                if 0 <= a < d.shape[0] and 0 <= b < d.shape[1] and grown[a, b] >= 0:
                    if d[a, b] > best_d:
                        best, best_d = grown[a, b], d[a, b]
            new[i, j] = best
        grown = new
    k = foam.k_pa_per_m
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
        X = rest.joints[core] - pos
        xy = np.stack([X @ e1, X @ e2], axis=1)
        mu = w @ xy / w.sum()
        C = ((xy - mu) * w[:, None]).T @ (xy - mu) / w.sum()
        ev, evec = np.linalg.eigh(C)
        axes = 2.0 * np.sqrt(np.maximum(ev[::-1], 0.0))
        major = evec[:, 1]
        ang = float(np.arctan2(major[1], major[0]))
        if ang <= -np.pi / 2:
            ang += np.pi
        elif ang > np.pi / 2:
            ang -= np.pi
        geo.append((pos, float(np.sqrt(rest.areas[core].sum() / np.pi))))
        out.append(Contact(id=-1, index=np.array([fi, fj]), position=pos, normal=nrm,
                           depth_m=depth, force_n=0.0, area_m2=float(rest.areas[core].sum()),
                           axes_m=axes, angle_rad=ang, peak=(int(pk[0]), int(pk[1])),
                           region=region))
    share = _force_shares(d, rest, grown, ids, geo, foam.shear_length_m)
    out = [replace(c, force_n=float(k * np.sum(d * rest.areas * f)))
           for c, f in zip(out, share)]
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


# ---------------------------------------------------------------------------------------------
# Tracking
# ---------------------------------------------------------------------------------------------

class ContactTracker:
    """Stable ids for contacts over snapshots.

    Association: minimum total distance between the previous snapshot's tracks and the new
    contacts (Hungarian, `scipy.optimize.linear_sum_assignment`), pairs farther than
    ``gate_m`` not matched; unmatched contacts start new tracks (ids count up from 0, never
    reused); a track not matched for more than ``max_missed`` snapshots ends.

    Parameters
    ----------
    gate_m : float
        Largest distance a contact moves between snapshots and keeps its id, metres.
    max_missed : int
        Snapshots a track may go unmatched (a contact blinking below threshold keeps its id).
    """

    def __init__(self, gate_m: float, max_missed: int = 2):
        if not (gate_m > 0):
            raise ValueError(f"Invalid gate_m: {gate_m!r} (need > 0)")
        self.gate_m = float(gate_m)
        self.max_missed = int(max_missed)
        self._tracks: dict[int, tuple[np.ndarray, int]] = {}  # id -> (position, missed)
        self._next = 0

    def update(self, contacts: Sequence[Contact]) -> list[Contact]:
        """The contacts with their track ids, same order."""
        from scipy.optimize import linear_sum_assignment

        ids = list(self._tracks)
        assigned = [-1] * len(contacts)
        if ids and contacts:
            A = np.array([self._tracks[t][0] for t in ids])
            B = np.array([c.position for c in contacts])
            D = np.linalg.norm(A[:, None, :] - B[None, :, :], axis=2)
            cost = np.where(D <= self.gate_m, D, 1e6 * self.gate_m)
            r, c = linear_sum_assignment(cost)
            for a, b in zip(r, c):
                if D[a, b] <= self.gate_m:
                    assigned[b] = ids[a]
        matched = set(x for x in assigned if x >= 0)
        for t in ids:
            if t not in matched:
                pos, missed = self._tracks[t]
                if missed + 1 > self.max_missed:
                    del self._tracks[t]
                else:
                    self._tracks[t] = (pos, missed + 1)
        out = []
        for c, t in zip(contacts, assigned):
            if t < 0:
                t = self._next
                self._next += 1
            self._tracks[t] = (np.asarray(c.position, float), 0)
            out.append(replace(c, id=t))
        return out


# ---------------------------------------------------------------------------------------------
# Streaming sensor
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class TactileFrame:
    """What one snapshot tells.

    Attributes
    ----------
    t_s : float or None
        Snapshot time, seconds.
    estimate : ShapeEstimate
    displacement : ndarray, shape (rows, cols)
        Normal displacement into the foam, metres.
    contacts : list of Contact
        With track ids.
    total_force_n : float
        Sum of the contacts' forces, N.
    """

    t_s: float | None
    estimate: ShapeEstimate
    displacement: np.ndarray
    contacts: list[Contact]
    total_force_n: float


class TactileSensor:
    """Readings in, tracked contacts out (module docstring).

    Parameters
    ----------
    rest : RestShape
        Known (`RestShape.from_joints`) or learned (`TactileSensor.learn_rest`).
    foam : Foam
    settings : DetectorSettings, optional
    gate : float, optional
        Tracking gate, link lengths (default 2).
    """

    def __init__(self, rest: RestShape, foam: Foam, settings: DetectorSettings | None = None,
                 gate: float = 2.0, max_missed: int = 2):
        self.rest = rest
        self.foam = foam
        self.settings = settings or DetectorSettings()
        self.tracker = ContactTracker(gate * rest.link_length, max_missed)

    @staticmethod
    def learn_rest(readings: Sequence[np.ndarray], rows: int, cols: int, link_length: float,
                   valid: np.ndarray | None = None, prior: RestShape | None = None
                   ) -> RestShape:
        """Learn the rest shape from snapshots of an untouched sheet, shape ``(n_links, 3)``
        each, m/s² (the estimator with ``prior`` or its own rest layout as prior)."""
        rest = None if prior is None else prior.yaws
        ests = [estimate(r, rows, cols, link_length, valid=valid, rest=rest)
                for r in readings]
        return RestShape.learn(ests)

    def process(self, readings: np.ndarray, valid: np.ndarray | None = None,
                t_s: float | None = None) -> TactileFrame:
        """One snapshot: readings ``(n_links, 3)`` m/s², sensor frames, DESIGN.md link order."""
        est = estimate(readings, self.rest.rows, self.rest.cols, self.rest.link_length,
                       valid=valid, rest=self.rest.yaws)
        d, _ = deformation(est.joints, self.rest)
        found = find_contacts(d, self.rest, self.foam, self.settings)
        if found:  # second pass: fit the rigid overlay without the dents and their tails
            moved = np.zeros(d.shape, bool)
            for c in found:
                moved |= c.region
            moved = _dilate(moved)
            d, _ = deformation(est.joints, self.rest, exclude=moved)
            found = find_contacts(d, self.rest, self.foam, self.settings)
        contacts = self.tracker.update(found)
        return TactileFrame(t_s=t_s, estimate=est, displacement=d, contacts=contacts,
                            total_force_n=float(sum(c.force_n for c in contacts)))


# ---------------------------------------------------------------------------------------------
# Plot
# ---------------------------------------------------------------------------------------------

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
