"""cffi build of the estimator's compiled kernel as ``host.analysis._yaw_kernel`` (API mode).

Built at install time through ``setup.py``'s ``cffi_modules`` (``pip install -e .``), or by hand::

    .venv/bin/python host/analysis/_kernel/build.py     # writes host/analysis/_yaw_kernel*.so

Optional at run time: without it (no compiler, not built, or ``CAPSHEET_NO_KERNEL=1``) the
estimator runs its numpy code, which gives the same numbers (tests/host/analysis/
test_estimator_kernel.py compares them).
"""

from __future__ import annotations

import os
from pathlib import Path

from cffi import FFI

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]

CDEF = r"""
typedef struct {
    int64_t n_units; int64_t n_roll; int64_t n_pairs; int64_t n_var;
    const int64_t *units; const int64_t *unit_var; const double *c_loop;
    const double *Az, *Cz;
    const int64_t *roll_links, *roll_c0, *roll_c1, *roll_var0;
    const double *roll_ws1; const double *y_c; const double *y_z, *w;
    const int64_t *pairs, *pair_var; const double *pair_t, *lam_b;
    const int64_t *var_links; const double *target, *lam;
    int32_t abs_prior;
} capsheet_yaw_t;
double capsheet_yaw_eval(const capsheet_yaw_t *p, const double *gamma, double *grad,
                         double *work);
void capsheet_ldl_solve(int64_t n, int64_t n_super, const int32_t *sn_col, const int64_t *sn_row,
                        const int32_t *rows, const int64_t *sn_diag, const int64_t *sn_below,
                        const float *val, const double *diag, double *x, double *work);
void capsheet_ldl_fill(int64_t n_super, const int32_t *l_ptr, const int32_t *l_idx,
                       const double *l_val, const int32_t *sn_col, const int64_t *sn_row,
                       const int32_t *rows, const int64_t *sn_diag, const int64_t *sn_below,
                       int32_t *map, float *val);
typedef struct {
    int64_t n_links; int64_t max_iter; double tol, refactor_ratio, anderson_cos;
    const int64_t *perm_inv, *perm_of_var;
    int64_t n_super; const int32_t *sn_col; const int64_t *sn_row; const int32_t *rows;
    const int64_t *sn_diag, *sn_below; const float *val; const double *diag;
    int64_t ldl_work_size;
} capsheet_chord_t;
int32_t capsheet_chord(const capsheet_yaw_t *p, double *gamma, double *cost, double *grad,
                       const capsheet_chord_t *c, int64_t *iterations, double *prev_smax,
                       double *work);
void capsheet_directions(int64_t n, const double *alpha, const double *beta, const double *gamma,
                         double *d, double *nrm);
double capsheet_eq8(int64_t n_units, const int64_t *units, const double *d, const double *nrm);
void capsheet_solvability(int64_t n_units, const int64_t *units, const double *alpha,
                          const double *beta, double *ratio);
void capsheet_flatness(int64_t rows_u, int64_t cols_u, const int64_t *units, const double *r,
                       const double *norm_g, double g0, int64_t radius, double th0, double *th2,
                       double *tmp, double *h);
void capsheet_yaw_coeffs(int64_t n_units, const int64_t *units, int64_t n_roll,
                         const int64_t *roll_links, const double *alpha, const double *beta,
                         double *c_loop, double *Az, double *Cz, double *y_c, double *y_z);
"""


def _rel(path: Path) -> str:
    # setuptools wants sources relative to the project root (the cwd of a build).
    try:
        return os.path.relpath(path, os.getcwd())
    except ValueError:  # another drive (Windows)
        return str(path)


ffibuilder = FFI()
ffibuilder.cdef(CDEF)
ffibuilder.set_source(
    "host.analysis._yaw_kernel",
    '#include "yaw_eval.h"\n',
    sources=[_rel(HERE / "yaw_eval.c")],
    include_dirs=[_rel(HERE)],
    # no -ffast-math: the numbers must be the numpy fallback's (IEEE order of operations)
    extra_compile_args=["-O3", "-fno-fast-math", "-ffp-contract=off"] if os.name != "nt" else [],
)

if __name__ == "__main__":
    os.chdir(ROOT)
    ffibuilder.compile(tmpdir=str(ROOT), verbose=False)
