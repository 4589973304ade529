"""The checks every entry point makes (`estimate`, `estimate_batch`, `ShapeEstimator`): the
options, the lattice's size, the link length, one snapshot's readings and mask, ``previous`` and
``rest``; each raises a ValueError that names what is wrong (the shape expected and got, the links)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .angles import G0
from .priors import DEFAULT_PRIOR, PRIORS
from .result import ShapeEstimate
from .structure import lattice_of

__all__ = ["METHODS", "MODELS", "READING_NORM_RANGE", "Options", "Snapshot", "check_int",
           "check_link_length", "check_noise_pct_g", "check_options", "check_previous",
           "check_readings", "rest_yaws"]

#: `estimate`'s methods (module docstring)
METHODS = ("global", "paper")
#: `estimate`'s normal models (module docstring)
MODELS = ("cells", "eq6")
#: Plausible |reading| range, in g: outside it a link is a dead, stuck or saturated chip.
READING_NORM_RANGE = (0.5, 1.5)


def check_int(name: str, v, lo: int) -> int:
    """``v`` as an int >= ``lo`` (ValueError naming ``name`` otherwise; a bool is no integer)."""
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or v < lo:
        raise ValueError(f"Invalid {name}: {v!r} (need an integer >= {lo})")
    return int(v)


def rest_yaws(rest, n: int, rows: int, cols: int) -> np.ndarray:
    """The rest yaws (n,) of ``rest`` (a `ShapeEstimate` of this lattice, or its yaws), checked."""
    if isinstance(rest, ShapeEstimate):
        if rest.joints.shape != (rows, cols, 3):
            raise ValueError(f"Expected `rest` of a {rows}x{cols} lattice, joints shape "
                             f"({rows}, {cols}, 3), got {rest.joints.shape}.")
        y = np.asarray(rest.yaws, float)
    else:
        y = np.asarray(rest)
        if y.dtype.kind not in "iuf":
            raise ValueError(f"Invalid rest: {type(rest).__name__} of dtype {y.dtype} (need a "
                             f"ShapeEstimate or rest yaws, shape ({n},), radians)")
        y = y.astype(float)
        if y.shape != (n,):
            raise ValueError(f"Expected `rest` yaws to have shape ({n},) for a {rows}x{cols} "
                             f"lattice, got {y.shape}.")
    if not np.all(np.isfinite(y)):
        raise ValueError("Invalid rest: its yaws contain NaN or inf.")
    return y


def check_previous(previous, n: int, rows: int, cols: int) -> None:
    """ValueError unless ``previous`` is a finite `ShapeEstimate` of this lattice."""
    if not isinstance(previous, ShapeEstimate):
        raise ValueError(f"Invalid previous: {type(previous).__name__} (need a ShapeEstimate from "
                         "an earlier estimate() of the same lattice, or None)")
    pj = np.shape(previous.joints)
    if pj != (rows, cols, 3):
        raise ValueError(f"Expected `previous` of a {rows}x{cols} lattice, joints shape "
                         f"({rows}, {cols}, 3), got {pj}.")
    if np.shape(previous.yaws) != (n,):
        raise ValueError(f"Expected `previous.yaws` to have shape ({n},), got "
                         f"{np.shape(previous.yaws)}.")
    if not (np.all(np.isfinite(previous.yaws)) and np.all(np.isfinite(previous.joints))):
        raise ValueError("Invalid previous: its yaws or joints contain NaN or inf (a failed "
                         "estimate cannot seed the next one; pass previous=None)")


class Options(NamedTuple):
    """The checked options of `estimate` that do not depend on the lattice."""

    method: str
    model: str
    prior: str
    noise_pct_g: float
    bad_readings: str
    paper_options: object


def check_options(method="global", model="cells", prior=DEFAULT_PRIOR, noise_pct_g=1.0,
                  bad_readings="raise", paper_options=None) -> Options:
    """`estimate`'s options checked (ValueError naming what is wrong), as an `Options`
    (``noise_pct_g`` is checked by `check_noise_pct_g`)."""
    if method not in METHODS:
        raise ValueError(f"Invalid method: {method!r} (expected one of {METHODS})")
    if model not in MODELS:
        raise ValueError(f"Invalid model: {model!r} (expected one of {MODELS})")
    if prior not in PRIORS:
        raise ValueError(f"Invalid prior: {prior!r} (expected one of {PRIORS})")
    if bad_readings not in ("raise", "mask"):
        raise ValueError(f"Invalid bad_readings: {bad_readings!r} (expected 'raise' or 'mask')")
    if paper_options is not None:  # method="paper" only (host.analysis.paper_method)
        from ..paper_method import PaperOptions
        if method != "paper" or not isinstance(paper_options, PaperOptions):
            raise ValueError(f"Invalid paper_options: {paper_options!r} (a PaperOptions, with "
                             "method='paper' only)")
    return Options(method, model, prior, noise_pct_g, bad_readings, paper_options)


def check_noise_pct_g(noise_pct_g) -> float:
    """``noise_pct_g`` as a finite float >= 0 (ValueError otherwise)."""
    if isinstance(noise_pct_g, (bool, np.bool_)) or not isinstance(noise_pct_g,
                                                                    (int, float, np.number)) \
            or not (np.isfinite(noise_pct_g) and noise_pct_g >= 0):
        raise ValueError(f"Invalid noise_pct_g: {noise_pct_g!r} (need a finite value >= 0)")
    return float(noise_pct_g)


def check_link_length(link_length) -> float:
    """``link_length`` as a finite float > 0, metres (ValueError otherwise)."""
    if isinstance(link_length, (bool, np.bool_)) or not isinstance(link_length,
                                                                    (int, float, np.number)):
        raise ValueError(f"Invalid link_length: {link_length!r} (need a number of metres > 0)")
    L = float(link_length)
    if not (np.isfinite(L) and L > 0):
        raise ValueError(f"Invalid link_length: {link_length!r} (need a finite value > 0 m)")
    return L


class Snapshot(NamedTuple):
    """One snapshot's readings, checked (`check_readings`)."""

    #: readings, (n_links, 3), m/s², float
    readings: np.ndarray
    #: the links used, (n_links,) bool: ``valid`` less the implausible readings masked out
    valid: np.ndarray
    #: ``valid``, or None when every link is used
    mask: np.ndarray | None
    #: ``|s| / G0`` per link, (n_links,)
    norm_g: np.ndarray


def check_readings(readings, rows: int, cols: int, valid=None, bad_readings: str = "raise"
                   ) -> Snapshot:
    """One snapshot's readings and mask checked as `estimate` checks them (ValueError naming the
    shape expected and got, the non-finite or implausible links), as a `Snapshot`."""
    n = lattice_of(rows, cols).n_links
    r = np.asarray(readings)
    if r.dtype.kind not in "iuf":
        raise ValueError(f"Invalid readings: dtype {r.dtype} (need real numbers, m/s²)")
    r = r.astype(float, copy=False)
    if r.shape != (n, 3):
        raise ValueError(f"Expected `readings` to have shape ({n}, 3) for a {rows}x{cols} "
                         f"lattice, got {r.shape}.")
    if valid is None:
        vmask = np.ones(n, bool)
    else:
        vmask = np.asarray(valid)
        if vmask.dtype != bool:
            raise ValueError(f"Invalid valid: dtype {vmask.dtype} (need a boolean mask, True = "
                             "link present)")
        if vmask.shape != (n,):
            raise ValueError(f"Expected `valid` to have shape ({n},) for a {rows}x{cols} lattice, "
                             f"got {vmask.shape}.")
        if not vmask.any():
            raise ValueError(f"No valid link: all {n} links are masked out by `valid`; "
                             "cannot estimate a shape.")
    bad = ~finite_rows(r) & vmask
    if bad.any():
        raise ValueError(f"Non-finite readings on valid links {_few(np.flatnonzero(bad))}; mask "
                         "them out with `valid`.")
    norm = np.sqrt(np.einsum("ij,ij->i", r, r)) / G0
    lo, hi = READING_NORM_RANGE
    far = vmask & ~((norm >= lo) & (norm <= hi))
    if far.any():
        if bad_readings == "raise":
            k = np.flatnonzero(far)
            raise ValueError(f"Implausible readings on links {_few(k)}: |s| = "
                             f"{_few(np.round(norm[k], 3))} g, outside [{lo}, {hi}] g (dead or "
                             "stuck chips?); mask them with `valid` or bad_readings='mask'.")
        vmask = vmask & ~far
        if not vmask.any():
            raise ValueError("No valid link left after masking the implausible readings.")
    return Snapshot(r, vmask, None if vmask.all() else vmask, norm)


def finite_rows(r: np.ndarray) -> np.ndarray:
    """Per row of ``r`` (n, 3), whether all three entries are finite: ``np.isfinite(r).all(
    axis=1)``, column by column (numpy's reduction over an axis of three took ~0.3 ms of a 64x64
    snapshot, twenty times this)."""
    return np.isfinite(r[:, 0]) & np.isfinite(r[:, 1]) & np.isfinite(r[:, 2])


def _few(idx, limit: int = 8) -> str:
    """A short list for error messages: the first ``limit`` items and how many more."""
    items = [str(v) for v in np.asarray(idx).tolist()[:limit]]
    more = len(idx) - len(items)
    return "[" + ", ".join(items) + (f", … {more} more" if more > 0 else "") + "]"
