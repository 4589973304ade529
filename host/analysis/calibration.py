"""Calibration of every chip in place: bias, scale and mounting misalignment, from a few static
poses of the sheet clamped flat on a rigid board (docs/calibration.md).

The model of chip ``k`` (link ``k``), in every static pose ``p``::

    r[p, k] = s[k] ⊙ (R(m[k])ᵀ v[p, k]) + b[k] + noise,     v[p, k] = R0[k]ᵀ g[p]

* ``r`` — the reading as the host converted it (m/s², the chip's sensor frame, with whatever
  chip calibration CAL_DATA reported at capture: the *reference* conversion);
* ``b`` — bias, m/s² per axis; ``s`` — scale, 1 per axis;
* ``R(m)`` — the chip's mounting misalignment, a rotation whose columns are the chip's axes in its
  link's sensor frame, ``m`` its rotation vector (radians);
* ``R0[k]`` — the link's sensor frame on the flat board (docs/design.md): identity for an i-link
  (x along the board's x), a quarter turn about z for a j-link (x along the board's y);
* ``g[p] = G0 · u[p]`` — the specific force of gravity in the board's frame: one unknown unit
  vector per pose (2 parameters), shared by every chip. Its length is standard gravity, which fixes
  the common scale (a local g differing by δ shows up as a common scale error δ/g).

All chips and poses are fitted jointly by a sparse trust-region Levenberg-Marquardt-type
least-squares solve (`scipy.optimize.least_squares`, ``method="trf"`` with the Jacobian's sparsity:
each residual touches one chip's 9 parameters and one pose's 2), from the start ``b = 0, s = 1,
m = 0``, ``u[p]`` the board-frame mean of the readings' directions.

**What cannot be identified**: a rotation ``Q`` common to every chip (in the board frame) together
with the inverse rotation of every pose's gravity leaves every reading unchanged. The solve fixes it
while it runs by holding pose 0's direction and one component of the pose most orthogonal to it,
and afterwards re-expresses the solution so that the chips' mean board-frame misalignment is zero
(``mean_k R0 R(m) R0ᵀ`` projected on SO(3) is the identity): the board's frame is *defined* as the
mean of the chips' frames. Recovered misalignments are the true ones minus that common part.

>>> import numpy as np
>>> u = np.array([[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0.]])
>>> R0 = link_frames_on_board(2, 2)
>>> truth_b = np.zeros((4, 3)); truth_b[2] = [0.2, -0.1, 0.3]
>>> r = np.einsum("kji,pj->pki", R0, u * G0) * 1.01 + truth_b
>>> cal = fit_board_poses(r, 2, 2)
>>> np.round(cal.bias[2], 6).tolist(), np.round(cal.scale[0], 6).tolist()
([0.2, -0.1, 0.3], [1.01, 1.01, 1.01])
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from protocol.constants import G0
from protocol.files import MAX_LINKS, loads_json, read_file
from protocol.frames import BOARD_POSES
from protocol.lattice import Lattice
from protocol.rotations import matrix_rotvecs, rotvec_matrices

__all__ = ["Calibration", "fit_board_poses", "link_frames_on_board", "board_frame_readings",
           "pose_directions", "StaticDetector", "BOARD_POSES", "MIN_POSES", "G0",
           "NOMINAL_SENSITIVITY", "FORMAT", "VERSION"]

#: Counts per g at ±2 g (`protocol.constants.nominal_sensitivity`): what a chip without calibration reports.
NOMINAL_SENSITIVITY = 1024.0
#: Fewest poses `fit_board_poses` accepts (9 unknowns per chip need 3 independent poses; 6 make
#: every axis see +g and -g so bias and scale separate with margin).
MIN_POSES = 6
#: cal.json format name and version
FORMAT = "capsheet-calibration"
VERSION = 1
#: a calibration file larger than this is refused unread (`MAX_LINKS` chips of ~700 bytes, with room)
MAX_FILE_BYTES = 64 << 20
#: what a file may say of a chip, each field's plausible range (the fit's own limits where it has
#: them: scale 0.5 .. 2, `fit_board_poses`); beyond is a broken or hostile file, refused naming the
#: field. bias: m/s², at most a ±16 g part's range; misalignment: a rotation vector of at most π rad
#: (any rotation has one); non_orthogonality: rad; reference offset: ±2 g counts of a 16-bit word;
#: reference sensitivity: counts per g; rms: m/s².
FILE_LIMITS = {"bias": (-16 * G0, 16 * G0), "scale": (0.5, 2.0), "misalignment": (-np.pi, np.pi),
               "non_orthogonality": (-0.5, 0.5), "reference_offset_counts": (-32768.0, 32767.0),
               "reference_sensitivity": (1.0, 1e6), "rms_mps2": (0.0, 1e3)}
#: held poses a file may list (`pose_directions`)
MAX_FILE_POSES = 10_000
# G0 (`protocol.constants`) and the suggested poses BOARD_POSES (`protocol.frames`) are re-exported.


def link_frames_on_board(rows: int, cols: int) -> np.ndarray:
    """Every link's sensor frame on the flat board (i-links along x, j-links along y).

    Returns
    -------
    ndarray, shape (n_links, 3, 3)
        ``R0`` with columns the sensor axes in the board's frame: identity for an i-link, the
        quarter turn ``[[0, -1, 0], [1, 0, 0], [0, 0, 1]]`` for a j-link (x along +y, y = z × x = -x).
    """
    lat = Lattice(int(rows), int(cols))
    R0 = np.tile(np.eye(3), (lat.n_links, 1, 1))
    R0[lat.n_i_links:] = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    return R0


def board_frame_readings(readings: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Readings ``(..., n_links, 3)`` of a sheet flat on the board, turned into the board's frame."""
    return np.einsum("kij,...kj->...ki", link_frames_on_board(rows, cols), readings)


def pose_directions(pose_readings: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Each pose's gravity direction in the board's frame, ``(n_poses, 3)`` unit vectors: the mean
    of every chip's reading turned into the board's frame (the fit's starting point)."""
    m = board_frame_readings(np.asarray(pose_readings, dtype=float), rows, cols).mean(axis=-2)
    n = np.linalg.norm(m, axis=-1, keepdims=True)
    return m / np.where(n > 0, n, 1.0)


def _lower(t: np.ndarray) -> np.ndarray:
    """``(..., 3)`` non-orthogonality ``(yx, zx, zy)`` -> ``(..., 3, 3)`` unit lower-triangular T."""
    t = np.asarray(t, dtype=float)
    T = np.zeros(t.shape[:-1] + (3, 3))
    T[..., 0, 0] = T[..., 1, 1] = T[..., 2, 2] = 1.0
    T[..., 1, 0], T[..., 2, 0], T[..., 2, 1] = t[..., 0], t[..., 1], t[..., 2]
    return T


def project_so3(A: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(A)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _tangent_basis(u: np.ndarray, first: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    if first is None:
        a = np.eye(3)[int(np.argmin(np.abs(u)))]
        first = np.cross(u, a)
    t1 = first / np.linalg.norm(first)
    return t1, np.cross(u, t1)


def _check_array(name: str, a, shape: tuple[int, ...]) -> np.ndarray:
    a = np.asarray(a, dtype=float)
    if a.shape != shape:
        raise ValueError(f"Invalid {name}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"Invalid {name}: contains NaN or inf")
    return a


@dataclass(frozen=True)
class Calibration:
    """Per-chip bias, scale and misalignment of a ``rows x cols`` sheet (`fit_board_poses`).

    Attributes
    ----------
    rows, cols : int
        Joints of the lattice; ``n_links`` chips in lattice order.
    bias : ndarray, shape (n_links, 3)
        m/s², chip axes, relative to the reference conversion.
    scale : ndarray, shape (n_links, 3)
        Dimensionless (1 = the reference conversion's sensitivity is right), > 0.
    misalignment : ndarray, shape (n_links, 3)
        Rotation vector, radians, of each chip's axes in its link's sensor frame (mean over the
        chips fixed to zero: module docstring).
    residual_rms : float
        m/s², RMS of every residual of the fit (0 if the calibration was not fitted).
    chip_rms : ndarray, shape (n_links,)
        m/s², each chip's residual RMS over its poses and axes.
    outliers : tuple of int
        Links whose ``chip_rms`` exceeds the outlier threshold (`fit_board_poses`).
    reference_offset_counts, reference_sensitivity : ndarray, shape (n_links, 3)
        The chip calibration (±2 g counts: offset counts, counts per g; CAL_DATA) the fitted
        readings were converted with. ``bias`` and ``scale`` are relative to it; `rebased`
        re-expresses them for another one (e.g. after CAL_WRITE).
    pose_directions : ndarray, shape (n_poses, 3)
        Fitted gravity direction of each pose, board frame (unit vectors).
    non_orthogonality : ndarray, shape (n_links, 3)
        Radians ``(yx, zx, zy)``: the chip's y axis leaning towards x, z towards x, z towards y
        (``T = [[1, 0, 0], [yx, 1, 0], [zx, zy, 1]]``, the chip reads ``s ⊙ T R(m)ᵀ f + b``);
        zeros unless fitted (``fit_board_poses(..., non_orthogonality=True)``).
    """

    rows: int
    cols: int
    bias: np.ndarray
    scale: np.ndarray
    misalignment: np.ndarray
    residual_rms: float = 0.0
    chip_rms: np.ndarray | None = None
    outliers: tuple[int, ...] = ()
    reference_offset_counts: np.ndarray | None = None
    reference_sensitivity: np.ndarray | None = None
    pose_directions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    non_orthogonality: np.ndarray | None = None

    def __post_init__(self) -> None:
        lat = Lattice(int(self.rows), int(self.cols))
        object.__setattr__(self, "rows", lat.rows)
        object.__setattr__(self, "cols", lat.cols)
        n = lat.n_links
        for name in ("bias", "scale", "misalignment"):
            object.__setattr__(self, name, _check_array(name, getattr(self, name), (n, 3)))
        if np.any(self.scale <= 0):
            raise ValueError("Invalid scale: every value must be > 0")
        if self.reference_offset_counts is None:
            object.__setattr__(self, "reference_offset_counts", np.zeros((n, 3)))
        if self.reference_sensitivity is None:
            object.__setattr__(self, "reference_sensitivity", np.full((n, 3), NOMINAL_SENSITIVITY))
        for name in ("reference_offset_counts", "reference_sensitivity"):
            object.__setattr__(self, name, _check_array(name, getattr(self, name), (n, 3)))
        if np.any(self.reference_sensitivity <= 0):
            raise ValueError("Invalid reference_sensitivity: every value must be > 0")
        chip_rms = np.zeros(n) if self.chip_rms is None else self.chip_rms
        object.__setattr__(self, "chip_rms", _check_array("chip_rms", chip_rms, (n,)))
        if not (np.isfinite(self.residual_rms) and self.residual_rms >= 0):
            raise ValueError(f"Invalid residual_rms: {self.residual_rms!r} (need a finite value >= 0)")
        object.__setattr__(self, "residual_rms", float(self.residual_rms))
        out = tuple(int(k) for k in self.outliers)
        if any(not 0 <= k < n for k in out):
            raise ValueError(f"Invalid outliers: {out!r} (links are 0..{n - 1})")
        object.__setattr__(self, "outliers", out)
        pd = np.asarray(self.pose_directions, dtype=float).reshape(-1, 3)
        object.__setattr__(self, "pose_directions", pd)
        no = np.zeros((n, 3)) if self.non_orthogonality is None else self.non_orthogonality
        object.__setattr__(self, "non_orthogonality", _check_array("non_orthogonality", no, (n, 3)))
        # the correction R(m) T⁻¹, one matrix per chip
        A = rotvec_matrices(self.misalignment) @ np.linalg.inv(_lower(self.non_orthogonality))
        object.__setattr__(self, "_M", rotvec_matrices(self.misalignment))
        object.__setattr__(self, "_A", A)

    @property
    def n_links(self) -> int:
        return self.bias.shape[0]

    @property
    def rotations(self) -> np.ndarray:
        """``R(misalignment)``, shape (n_links, 3, 3): columns are the chip's axes in the link frame."""
        return self._M.copy()

    @classmethod
    def identity(cls, rows: int, cols: int) -> "Calibration":
        """No correction (bias 0, scale 1, no misalignment)."""
        n = Lattice(rows, cols).n_links
        return cls(rows, cols, np.zeros((n, 3)), np.ones((n, 3)), np.zeros((n, 3)))

    def apply(self, readings: np.ndarray) -> np.ndarray:
        """Corrected readings: ``R(m) T⁻¹ ((r − b) / s)`` per chip (``T = I`` without non-orthogonality).

        Parameters
        ----------
        readings : ndarray, shape (..., n_links, 3)
            m/s², chip frames, converted with the reference chip calibration (see `rebased`).

        Returns
        -------
        ndarray, same shape
            m/s², each link's sensor frame. NaN entries (invalid links) stay NaN.
        """
        r = np.asarray(readings, dtype=float)
        if r.ndim < 2 or r.shape[-2:] != (self.n_links, 3):
            raise ValueError(f"Expected `readings` to have shape (..., {self.n_links}, 3), got {r.shape}.")
        return np.einsum("kij,...kj->...ki", self._A, (r - self.bias) / self.scale)

    def chip_calibration(self) -> tuple[np.ndarray, np.ndarray]:
        """The absolute chip calibration this fit found, ±2 g counts (what CAL_WRITE carries).

        Returns
        -------
        offset_counts : ndarray, shape (n_links, 3)
            Counts at zero specific force (``offset_q4 = round(16 · offset_counts)``).
        sensitivity : ndarray, shape (n_links, 3)
            Counts per g.
        """
        sens = self.reference_sensitivity * self.scale
        off = self.reference_offset_counts + self.bias * self.reference_sensitivity / G0
        return off, sens

    def rebased(self, offset_counts: np.ndarray, sensitivity: np.ndarray) -> "Calibration":
        """The same chips, for readings converted with another chip calibration (±2 g counts).

        After CAL_WRITE of `chip_calibration` the chips report it; ``rebased`` to it, the bias is
        (nearly) 0 and the scale 1, and only the misalignment (which a chip cannot hold) is left.
        """
        n = self.n_links
        off = _check_array("offset_counts", offset_counts, (n, 3))
        sens = _check_array("sensitivity", sensitivity, (n, 3))
        if np.any(sens <= 0):
            raise ValueError("Invalid sensitivity: every value must be > 0")
        true_off, true_sens = self.chip_calibration()
        return Calibration(self.rows, self.cols, bias=(true_off - off) * G0 / sens, scale=true_sens / sens,
                           misalignment=self.misalignment, residual_rms=self.residual_rms,
                           chip_rms=self.chip_rms, outliers=self.outliers, reference_offset_counts=off,
                           reference_sensitivity=sens, pose_directions=self.pose_directions,
                           non_orthogonality=self.non_orthogonality)

    # -- files ------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {"format": FORMAT, "version": VERSION, "rows": self.rows, "cols": self.cols,
                "units": {"bias": "m/s^2", "scale": "1", "misalignment": "rad (rotation vector)",
                          "reference": "±2 g counts (offset, counts per g)"},
                "residual_rms_mps2": self.residual_rms, "outliers": list(self.outliers),
                "pose_directions": self.pose_directions.tolist(),
                "chips": [{"link": k, "bias": self.bias[k].tolist(), "scale": self.scale[k].tolist(),
                           "misalignment": self.misalignment[k].tolist(),
                           "non_orthogonality": self.non_orthogonality[k].tolist(),
                           "rms_mps2": float(self.chip_rms[k]),
                           "reference_offset_counts": self.reference_offset_counts[k].tolist(),
                           "reference_sensitivity": self.reference_sensitivity[k].tolist()}
                          for k in range(self.n_links)]}

    def save(self, path) -> Path:
        """Write the calibration as JSON (docs/calibration.md, "cal.json")."""
        path = Path(path)
        path.write_text(json.dumps(self.to_dict(), indent=1) + "\n")
        return path

    @classmethod
    def from_dict(cls, doc: dict, source: str = "calibration") -> "Calibration":
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise ValueError(f"{source}: not a capsheet calibration (format must be {FORMAT!r})")
        if doc.get("version") != VERSION:
            raise ValueError(f"{source}: unsupported version {doc.get('version')!r} (this reader knows {VERSION})")
        try:
            rows, cols = doc["rows"], doc["cols"]
            if any(isinstance(v, bool) or not isinstance(v, int) for v in (rows, cols)):
                raise ValueError(f"rows {rows!r}, cols {cols!r}: need integers")
            n = Lattice(rows, cols).n_links
            if n > MAX_LINKS:  # before anything is sized by it
                raise ValueError(f"a {rows}x{cols} lattice has {n:,} links, more than a sheet's {MAX_LINKS:,}")
            if not isinstance(doc["chips"], list) or len(doc["chips"]) != n:
                raise ValueError(f"chips must list links 0..{n - 1} once each")
            chips = sorted(doc["chips"], key=lambda c: int(c["link"]))
            if [int(c["link"]) for c in chips] != list(range(n)):
                raise ValueError(f"chips must list links 0..{n - 1} once each")
            poses = doc.get("pose_directions", [])
            if not isinstance(poses, list) or len(poses) > MAX_FILE_POSES:
                raise ValueError(f"pose_directions: a list of at most {MAX_FILE_POSES} directions")
            pose_dirs = np.array(poses, dtype=float).reshape(-1, 3)
            if not np.all(np.abs(pose_dirs) <= 1.0 + 1e-6):  # unit vectors; NaN fails too
                raise ValueError("pose_directions: need unit vectors (each value in [-1, 1])")

            def col(key, default=None):
                if default is not None and not all(key in c for c in chips):
                    return default
                a = np.array([c[key] for c in chips], dtype=float)
                lo, hi = FILE_LIMITS[key]
                bad = np.argwhere(~((a >= lo) & (a <= hi)))  # NaN and inf fail too
                if bad.size:
                    k = int(chips[int(bad[0][0])]["link"])
                    v = float(a[tuple(bad[0])])
                    raise ValueError(f"chip {k}: {key} {v!r} is outside [{lo:g}, {hi:g}]")
                if key == "misalignment" and np.any(np.linalg.norm(a, axis=-1) > np.pi):
                    k = int(np.argmax(np.linalg.norm(a, axis=-1)))
                    raise ValueError(f"chip {k}: misalignment of {np.linalg.norm(a[k]):.4g} rad, more than π")
                return a

            rms = float(doc.get("residual_rms_mps2", 0.0))
            if not 0.0 <= rms <= FILE_LIMITS["rms_mps2"][1]:
                raise ValueError(f"residual_rms_mps2 {rms!r} is outside [0, {FILE_LIMITS['rms_mps2'][1]:g}]")
            return cls(rows, cols, bias=col("bias"), scale=col("scale"), misalignment=col("misalignment"),
                       residual_rms=rms, chip_rms=col("rms_mps2"),
                       outliers=tuple(doc.get("outliers", ())),
                       reference_offset_counts=col("reference_offset_counts"),
                       reference_sensitivity=col("reference_sensitivity"),
                       pose_directions=pose_dirs,
                       non_orthogonality=col("non_orthogonality", np.zeros((n, 3))))
        except (KeyError, TypeError, IndexError, AttributeError, OverflowError) as exc:
            raise ValueError(f"{source}: missing or malformed field: {exc}") from None
        except ValueError as exc:
            raise ValueError(f"{source}: {exc}") from None

    @classmethod
    def load(cls, path) -> "Calibration":
        """Read a file written by `save`; a ValueError names what is wrong with it (one line: the
        file, the field and the value): not a regular file, larger than `MAX_FILE_BYTES`, not JSON or
        nested too deep, a lattice beyond a sheet's `MAX_LINKS`, a value outside `FILE_LIMITS`."""
        path = Path(path)
        # a regular file of a calibration's size (not a FIFO, not /dev/zero), nesting bounded
        doc = loads_json(read_file(path, MAX_FILE_BYTES, "a calibration file"), str(path))
        return cls.from_dict(doc, str(path))


# --------------------------------------------------------------------------------------------
# The fit
# --------------------------------------------------------------------------------------------

def _check_poses(pose_readings, rows: int, cols: int) -> tuple[np.ndarray, Lattice]:
    lat = Lattice(int(rows), int(cols))
    r = np.asarray(pose_readings, dtype=float)
    if r.ndim != 3 or r.shape[1:] != (lat.n_links, 3):
        raise ValueError(f"Expected `pose_readings` to have shape (n_poses, {lat.n_links}, 3) for a "
                         f"{lat.rows}x{lat.cols} lattice, got {r.shape}.")
    bad = np.argwhere(~np.isfinite(r))
    if bad.size:
        p, k, _ = bad[0]
        raise ValueError(f"`pose_readings` has NaN or inf ({len(bad)} values; first at pose {p}, link {k})")
    if r.shape[0] < MIN_POSES:
        raise ValueError(f"Too few poses: {r.shape[0]} (need at least {MIN_POSES}: docs/calibration.md)")
    return r, lat


def _per_chip_jacobian(v: np.ndarray, non_orthogonality: bool = False) -> np.ndarray:
    """d r / d (b, s, m[, t]) at b = 0, s = 1, m = 0, t = 0 for one chip seeing ``v (K, 3)``:
    ``(3K, 9)`` (``(3K, 12)`` with the non-orthogonality terms)."""
    K = v.shape[0]
    J = np.zeros((K, 3, 12 if non_orthogonality else 9))
    J[:, :, 0:3] = np.eye(3)
    J[:, np.arange(3), 3 + np.arange(3)] = v
    # R(m)ᵀ v ≈ v − m × v = v + [v]× m
    vx = np.zeros((K, 3, 3))
    vx[:, 0, 1], vx[:, 0, 2], vx[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    vx[:, 1, 0], vx[:, 2, 0], vx[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    J[:, :, 6:9] = vx
    if non_orthogonality:
        J[:, 1, 9], J[:, 2, 10], J[:, 2, 11] = v[:, 0], v[:, 0], v[:, 1]
    return J.reshape(3 * K, J.shape[2])


def _check_separable(u: np.ndarray, non_orthogonality: bool = False) -> None:
    """Poses too alike: bias and scale of an axis, or a misalignment, cannot be told apart."""
    names = "xyz"
    spans = u.max(axis=0) - u.min(axis=0)
    a = int(np.argmin(spans))  # name the weakest axis
    if spans[a] < 1.0:
        raise ValueError(
            f"Poses too alike to separate bias from scale on the board's {names[a]} axis: gravity's "
            f"{names[a]} component spans only {spans[a]:.2f} g over the poses (need >= 1 g; turn the board "
            f"so its {names[a]} axis points up in some poses and down in others)")
    sv = np.linalg.svd(_per_chip_jacobian(u * G0, non_orthogonality), compute_uv=False) / G0
    if sv[-1] < 1e-2 * sv[0]:
        raise ValueError(f"Poses too alike: the per-chip problem is near-singular (singular values "
                         f"{sv[-1]:.2g} vs {sv[0]:.2g}); use poses with gravity along each of "
                         "±x, ±y, ±z of the board")


def fit_board_poses(pose_readings: np.ndarray, rows: int, cols: int, *,
                    reference_offset_counts: np.ndarray | None = None,
                    reference_sensitivity: np.ndarray | None = None,
                    outlier_factor: float = 4.0, outlier_floor_mps2: float = 0.005,
                    gravity_mps2: float = G0, non_orthogonality: bool = False,
                    max_nfev: int = 50) -> Calibration:
    """Fit every chip's bias, scale and misalignment from static poses of the sheet on a flat board.

    Parameters
    ----------
    pose_readings : ndarray, shape (n_poses, n_links, 3)
        Specific force, m/s², each chip's sensor frame, each pose averaged over its static
        interval; links in lattice order; the sheet clamped flat on a rigid board (i-links along
        the board's x, j-links along its y). ``n_poses >= MIN_POSES``.
    rows, cols : int
        Joints of the lattice.
    reference_offset_counts, reference_sensitivity : ndarray, shape (n_links, 3), optional
        The chip calibration (±2 g counts) the readings were converted with; default the nominal
        one (offset 0, 1024 counts/g). Kept in the result so it can be rebased and written to chips.
    outlier_factor, outlier_floor_mps2 : float
        A link is an outlier when its residual RMS exceeds both ``outlier_factor`` times the median
        chip's and ``outlier_floor_mps2`` (docs/calibration.md).
    gravity_mps2 : float
        Local gravity, m/s² (default standard gravity). It sets the common scale: across the Earth
        g varies by ±0.27 %, a common scale error that leaves shapes unchanged but counts against
        |reading| = g checks.
    non_orthogonality : bool
        Also fit 3 non-orthogonality terms per chip (`Calibration.non_orthogonality`; 12 unknowns
        per chip instead of 9).
    max_nfev : int
        Iteration cap of the solver.

    Returns
    -------
    Calibration

    Raises
    ------
    ValueError
        Wrong shapes, NaN or inf, fewer than `MIN_POSES` poses, or poses too alike (an axis never
        sees gravity's component change by 1 g, or the per-chip problem is near-singular).
    """
    from scipy.optimize import least_squares
    from scipy.sparse import lil_matrix

    r, lat = _check_poses(pose_readings, rows, cols)
    if not (np.isfinite(outlier_factor) and outlier_factor > 1):
        raise ValueError(f"Invalid outlier_factor: {outlier_factor!r} (need > 1)")
    if not (np.isfinite(outlier_floor_mps2) and outlier_floor_mps2 >= 0):
        raise ValueError(f"Invalid outlier_floor_mps2: {outlier_floor_mps2!r} (need >= 0)")
    if not (np.isfinite(gravity_mps2) and 9.7 < gravity_mps2 < 9.9):
        raise ValueError(f"Invalid gravity_mps2: {gravity_mps2!r} (need Earth's, 9.7 .. 9.9 m/s²)")
    P, n = r.shape[0], lat.n_links
    R0 = link_frames_on_board(lat.rows, lat.cols)
    u0 = pose_directions(r, lat.rows, lat.cols)
    _check_separable(u0, bool(non_orthogonality))
    dots = np.abs(u0 @ u0[0])
    # gauge: pose 0 fixed; pose j1 (most orthogonal to pose 0) keeps its component about u0[0]
    j1 = int(np.argmin(dots))
    bases = []
    for p in range(P):
        first = np.cross(u0[0], u0[p]) if p == j1 else None
        bases.append(np.stack(_tangent_basis(u0[p], first)))
    bases = np.array(bases)  # (P, 2, 3)
    # pose p's parameters are a rotation vector a0 t1 + a1 t2 applied to u0[p]; the rotation about
    # t2 = u × t1 moves u along t1 = u0[0] × u0[j1], which is what a rotation about u0[0] does:
    # holding (j1, 1) removes the last gauge freedom
    free = [(p, c) for p in range(P) for c in range(2) if p != 0 and not (p == j1 and c == 1)]
    npc = 12 if non_orthogonality else 9  # parameters per chip
    n_chip = npc * n
    n_par = n_chip + len(free)

    def unpack(x):
        c = x[:n_chip].reshape(n, npc)
        a = np.zeros((P, 2))
        for i, (p, ci) in enumerate(free):
            a[p, ci] = x[n_chip + i]
        w = np.einsum("pc,pci->pi", a, bases)
        u = np.einsum("pij,pj->pi", rotvec_matrices(w), u0)
        t = c[:, 9:12] if non_orthogonality else np.zeros((n, 3))
        return c[:, 0:3], c[:, 3:6], c[:, 6:9], t, u

    def model(b, s, m, t, u):
        M = rotvec_matrices(m)
        v = np.einsum("kji,pj->pki", R0, u * gravity_mps2)  # R0ᵀ g
        w = np.einsum("kji,pkj->pki", M, v)  # Mᵀ v
        if non_orthogonality:
            w = np.einsum("kij,pkj->pki", _lower(t), w)  # T Mᵀ v
        return s * w + b

    def residual(x):
        return (model(*unpack(x)) - r).ravel()

    sparsity = lil_matrix((P * n * 3, n_par), dtype=np.int8)
    rows_idx = np.arange(P * n * 3).reshape(P, n, 3)
    for k in range(n):
        sparsity[rows_idx[:, k, :].ravel()[:, None], np.arange(npc * k, npc * k + npc)[None, :]] = 1
    for i, (p, _c) in enumerate(free):
        sparsity[rows_idx[p].ravel(), n_chip + i] = 1
    x0 = np.zeros(n_par)
    x0[:n_chip].reshape(n, npc)[:, 3:6] = 1.0
    sol = least_squares(residual, x0, jac_sparsity=sparsity.tocsr(), method="trf", x_scale=1.0,
                        tr_solver="lsmr", max_nfev=max_nfev, xtol=1e-10, ftol=1e-8, gtol=1e-10)
    b, s, m, t, u = unpack(sol.x)
    if np.any(s <= 0.5) or np.any(s >= 2.0):
        raise ValueError("The fit did not converge to plausible scales (0.5 .. 2); are the readings "
                         "in m/s² and the sheet flat on the board in every pose?")
    res = (model(b, s, m, t, u) - r)
    # fix the common rotation: the chips' mean board-frame misalignment becomes the identity
    B = np.einsum("kij,kjl,kml->kim", R0, rotvec_matrices(m), R0)  # R0 M R0ᵀ
    Q = project_so3(B.mean(axis=0))
    m = matrix_rotvecs(np.einsum("kji,jl,klm,kmn->kin", R0, Q.T, B, R0))  # R0ᵀ Qᵀ B R0
    u = u @ Q  # Qᵀ u for each row
    chip_rms = np.sqrt(np.mean(res ** 2, axis=(0, 2)))
    limit = max(outlier_factor * float(np.median(chip_rms)), outlier_floor_mps2)
    outliers = tuple(np.flatnonzero(chip_rms > limit).tolist())
    return Calibration(lat.rows, lat.cols, bias=b, scale=s, misalignment=m,
                       residual_rms=float(np.sqrt(np.mean(res ** 2))), chip_rms=chip_rms, outliers=outliers,
                       reference_offset_counts=reference_offset_counts,
                       reference_sensitivity=reference_sensitivity, pose_directions=u,
                       non_orthogonality=t if non_orthogonality else None)


# --------------------------------------------------------------------------------------------
# Static intervals
# --------------------------------------------------------------------------------------------

class StaticDetector:
    """Is the sheet holding still? A variance threshold over a sliding window of snapshots.

    The sheet is static when, over the last ``window`` snapshots, the per-chip standard deviation
    (RMS over the three axes) of the readings is below ``threshold_mps2`` for at least
    ``quantile`` of the valid chips. Turning a board changes readings by metres per second squared;
    chip noise (0.3 % g ≈ 0.03 m/s²) stays well below the default 1 % g.

    Parameters
    ----------
    n_links : int
    window : int
        Snapshots in the window (default 25: 0.25 s at 100 Hz).
    threshold_mps2 : float
        Standard deviation threshold, m/s² (default 0.098, 1 % g).
    quantile : float
        Fraction of valid chips that must be below it (default 0.9: a few noisy chips do not
        prevent capture).

    >>> det = StaticDetector(2, window=3)
    >>> [det.update(np.full((2, 3), 9.8 if t < 4 else 1.0)) for t in range(6)]
    [False, False, True, True, False, False]
    """

    def __init__(self, n_links: int, *, window: int = 25, threshold_mps2: float = 0.098,
                 quantile: float = 0.9) -> None:
        if not (isinstance(window, (int, np.integer)) and window >= 2):
            raise ValueError(f"Invalid window: {window!r} (need an integer >= 2)")
        if not (np.isfinite(threshold_mps2) and threshold_mps2 > 0):
            raise ValueError(f"Invalid threshold_mps2: {threshold_mps2!r} (need > 0)")
        if not 0 < quantile <= 1:
            raise ValueError(f"Invalid quantile: {quantile!r} (need 0 < quantile <= 1)")
        self.n_links = int(n_links)
        self.window = int(window)
        self.threshold_mps2 = float(threshold_mps2)
        self.quantile = float(quantile)
        self._buf = np.full((self.window, self.n_links, 3), np.nan)
        self._count = 0
        self.last_std = np.full(self.n_links, np.nan)  #: per-chip std over the window, m/s²

    def reset(self) -> None:
        self._buf[:] = np.nan
        self._count = 0

    def update(self, readings: np.ndarray, valid: np.ndarray | None = None) -> bool:
        """Add one snapshot ``(n_links, 3)`` (m/s²; invalid links NaN or masked); True when static."""
        r = np.asarray(readings, dtype=float)
        if r.shape != (self.n_links, 3):
            raise ValueError(f"Expected `readings` to have shape ({self.n_links}, 3), got {r.shape}.")
        if valid is not None:
            r = np.where(np.asarray(valid, dtype=bool)[:, None], r, np.nan)
        self._buf[self._count % self.window] = r
        self._count += 1
        if self._count < self.window:
            return False
        seen = np.isfinite(self._buf).all(axis=(0, 2))  # a chip missing in the window is not judged
        std = np.full(self.n_links, np.nan)
        std[seen] = np.sqrt(np.mean(np.var(self._buf[:, seen], axis=0), axis=1))
        self.last_std = std
        ok = np.isfinite(std)
        if not ok.any():
            return False
        return bool(np.mean(std[ok] < self.threshold_mps2) >= self.quantile)
