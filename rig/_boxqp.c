/* facecast.rig._kernel.project_box: bounded blend weights, compiled (see rig/bounds.py).
 * For each frame, argmin_x (x - w) H (x - w) + 2 half 1^T x subject to 0 <= x (<= upper),
 * by the same block principal pivoting as the numpy reference (Judice & Pires 1994, with
 * Murty's single exchange after BACKUP_CHANCES steps without progress), but solving only
 * the free variables' system (Cholesky) instead of a masked full one: with sparse weights
 * few are free, so a frame costs microseconds, not the numpy path's hundreds. It must not
 * keep state between calls; it agrees with the reference to rounding, not bit for bit.
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <string.h>

#define BACKUP_CHANCES 3 /* bounds._BACKUP_CHANCES */
enum { FREE = 0, LOW = 1, HIGH = 2 };

/* Solve a x = b in place (b becomes x) for the f x f SPD matrix a (row-major; its lower
 * triangle is overwritten by the Cholesky factor). Returns -1 if a is not positive definite. */
static int cholesky_solve(double *a, double *b, Py_ssize_t f) {
    for (Py_ssize_t j = 0; j < f; j++) {
        double d = a[j * f + j];
        for (Py_ssize_t k = 0; k < j; k++) d -= a[j * f + k] * a[j * f + k];
        if (!(d > 0.0)) return -1;
        d = sqrt(d);
        a[j * f + j] = d;
        for (Py_ssize_t i = j + 1; i < f; i++) {
            double s = a[i * f + j];
            for (Py_ssize_t k = 0; k < j; k++) s -= a[i * f + k] * a[j * f + k];
            a[i * f + j] = s / d;
        }
    }
    for (Py_ssize_t i = 0; i < f; i++) {
        double s = b[i];
        for (Py_ssize_t k = 0; k < i; k++) s -= a[i * f + k] * b[k];
        b[i] = s / a[i * f + i];
    }
    for (Py_ssize_t i = f - 1; i >= 0; i--) {
        double s = b[i];
        for (Py_ssize_t k = i + 1; k < f; k++) s -= a[k * f + i] * b[k];
        b[i] = s / a[i * f + i];
    }
    return 0;
}

typedef struct {
    Py_ssize_t n;
    const double *h;     /* (n, n) symmetric positive definite metric */
    const double *shift; /* (n,) (lambda / 2) H^-1 1, or NULL without a penalty */
    double half;         /* lambda / 2 */
    int bounded;
    double upper;
    int max_iter;
    /* scratch */
    double *a, *rhs, *target;
    Py_ssize_t *idx;
    signed char *state, *infeasible;
} Problem;

/* One frame w; writes x. -1: the metric is not positive definite. Everything is computed
 * here from w alone, so a frame gives the same bits alone or in any batch. */
static int project_one(const Problem *p, const double *w, double *x) {
    const Py_ssize_t n = p->n;
    const double *h = p->h;
    const double upper = p->upper;
    double *target = p->target;
    signed char *state = p->state, *infeasible = p->infeasible;
    for (Py_ssize_t i = 0; i < n; i++) {
        const double *row = h + i * n;
        double s = 0.0;
        for (Py_ssize_t j = 0; j < n; j++) s += row[j] * w[j];
        target[i] = s - p->half; /* H w - lambda / 2 */
        /* Start from the signs of the unbounded minimiser w - (lambda / 2) H^-1 1. */
        const double start = p->shift != NULL ? w[i] - p->shift[i] : w[i];
        state[i] = start < 0.0 ? LOW : (p->bounded && start > upper ? HIGH : FREE);
    }
    Py_ssize_t best = n + 1;
    int chances = BACKUP_CHANCES;
    for (int iter = 0; iter < p->max_iter; iter++) {
        Py_ssize_t f = 0;
        for (Py_ssize_t i = 0; i < n; i++) {
            x[i] = state[i] == HIGH ? upper : 0.0;
            if (state[i] == FREE) p->idx[f++] = i;
        }
        for (Py_ssize_t r = 0; r < f; r++) {
            const Py_ssize_t i = p->idx[r];
            const double *row = h + i * n;
            double s = target[i];
            if (p->bounded) {
                for (Py_ssize_t j = 0; j < n; j++) {
                    if (state[j] == HIGH) s -= row[j] * upper;
                }
            }
            p->rhs[r] = s;
            for (Py_ssize_t c = 0; c < f; c++) p->a[r * f + c] = row[p->idx[c]];
        }
        if (cholesky_solve(p->a, p->rhs, f) < 0) return -1;
        for (Py_ssize_t r = 0; r < f; r++) x[p->idx[r]] = p->rhs[r];
        /* Half the objective's gradient: H x - target = H (x - w) + half (KKT: >= 0 at 0,
         * <= 0 at the upper bound, 0 where free). */
        Py_ssize_t count = 0, last = -1;
        for (Py_ssize_t i = 0; i < n; i++) {
            const double *row = h + i * n;
            double s = -target[i];
            for (Py_ssize_t j = 0; j < n; j++) s += row[j] * x[j];
            const double tol = 1e-12 * (1.0 + fabs(target[i]));
            const signed char st = state[i];
            const int bad = (st == FREE && (x[i] < 0.0 || (p->bounded && x[i] > upper))) ||
                            (st == LOW && s < -tol) || (st == HIGH && s > tol);
            infeasible[i] = (signed char)bad;
            if (bad) {
                count++;
                last = i;
            }
        }
        if (count == 0) break;
        if (count < best) {
            best = count;
            chances = BACKUP_CHANCES;
        } else {
            chances--;
        }
        for (Py_ssize_t i = 0; i < n; i++) {
            if (!infeasible[i] || (chances <= 0 && i != last)) continue;
            /* A free variable goes to the bound it crosses; a bound one goes free. */
            if (state[i] == FREE) {
                state[i] = x[i] < 0.0 ? LOW : HIGH;
            } else {
                state[i] = FREE;
            }
        }
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        double v = x[i] < 0.0 ? 0.0 : x[i];
        x[i] = p->bounded && v > upper ? upper : v;
    }
    return 0;
}

static int get_matrix(PyObject *obj, Py_buffer *view, Py_ssize_t rows, Py_ssize_t cols,
                      int writable, const char *name) {
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) < 0) return -1;
    const char *f = view->format;
    if (f != NULL && (f[0] == '@' || f[0] == '=' || f[0] == '<')) f++;
    if (view->itemsize != 8 || f == NULL || f[0] != 'd' || f[1] != '\0' ||
        view->len != rows * cols * 8) {
        PyErr_Format(PyExc_ValueError, "%s must be a C-contiguous float64 (%zd, %zd) array",
                     name, rows, cols);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

/* project_box(metric, weights, shift, half, out, upper, max_iter): see _kernel.c's doc. */
PyObject *facecast_project_box(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    (void)module;
    if (nargs != 7) {
        PyErr_SetString(PyExc_TypeError,
                        "project_box(metric, weights, shift, half, out, upper, max_iter) takes "
                        "7 positional arguments");
        return NULL;
    }
    double half = PyFloat_AsDouble(args[3]);
    if (half == -1.0 && PyErr_Occurred()) return NULL;
    if (!(half >= 0.0) || !isfinite(half)) {
        PyErr_SetString(PyExc_ValueError, "half must be a finite number >= 0");
        return NULL;
    }
    double upper = 0.0;
    int bounded = args[5] != Py_None;
    if (bounded) {
        upper = PyFloat_AsDouble(args[5]);
        if (upper == -1.0 && PyErr_Occurred()) return NULL;
        if (!(upper > 0.0)) {
            PyErr_SetString(PyExc_ValueError, "upper must be None or a positive number");
            return NULL;
        }
    }
    long max_iter = PyLong_AsLong(args[6]);
    if (max_iter == -1 && PyErr_Occurred()) return NULL;
    if (max_iter < 1 || max_iter > 1000000) {
        PyErr_SetString(PyExc_ValueError, "max_iter must be in 1..1000000");
        return NULL;
    }
    Py_buffer hv, wv, sv, ov;
    if (PyObject_GetBuffer(args[0], &hv, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_ND) < 0) {
        return NULL;
    }
    Py_ssize_t n = hv.ndim == 2 && hv.shape[0] == hv.shape[1] ? hv.shape[0] : -1;
    PyBuffer_Release(&hv);
    if (n < 1) {
        PyErr_SetString(PyExc_ValueError, "metric must be a square 2-d array");
        return NULL;
    }
    if (PyObject_GetBuffer(args[1], &wv, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) return NULL;
    Py_ssize_t frames = wv.itemsize == 8 ? wv.len / 8 / n : 0;
    PyBuffer_Release(&wv);
    int have_shift = args[2] != Py_None;
    if (get_matrix(args[0], &hv, n, n, 0, "metric") < 0) return NULL;
    if (get_matrix(args[1], &wv, frames, n, 0, "weights") < 0) {
        PyBuffer_Release(&hv);
        return NULL;
    }
    if (have_shift && get_matrix(args[2], &sv, 1, n, 0, "shift") < 0) {
        PyBuffer_Release(&hv);
        PyBuffer_Release(&wv);
        return NULL;
    }
    if (get_matrix(args[4], &ov, frames, n, 1, "out") < 0) {
        PyBuffer_Release(&hv);
        PyBuffer_Release(&wv);
        if (have_shift) PyBuffer_Release(&sv);
        return NULL;
    }
    int failed = 0;
    void *scratch = PyMem_RawMalloc((size_t)(n * n + 2 * n) * sizeof(double) +
                                    (size_t)n * sizeof(Py_ssize_t) + 2 * (size_t)n);
    if (scratch == NULL) {
        failed = 2;
    } else {
        Problem p = {.n = n, .h = hv.buf, .shift = have_shift ? sv.buf : NULL, .half = half,
                     .bounded = bounded, .upper = upper, .max_iter = (int)max_iter};
        p.a = scratch;
        p.rhs = p.a + n * n;
        p.target = p.rhs + n;
        p.idx = (Py_ssize_t *)(p.target + n);
        p.state = (signed char *)(p.idx + n);
        p.infeasible = p.state + n;
        const double *weights = wv.buf;
        double *out = ov.buf;
        /* Pure C on buffers the caller keeps alive: other threads may run meanwhile. */
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t b = 0; b < frames && !failed; b++) {
            failed = project_one(&p, weights + b * n, out + b * n) < 0;
        }
        Py_END_ALLOW_THREADS
        PyMem_RawFree(scratch);
    }
    PyBuffer_Release(&hv);
    PyBuffer_Release(&wv);
    if (have_shift) PyBuffer_Release(&sv);
    PyBuffer_Release(&ov);
    if (failed == 2) return PyErr_NoMemory();
    if (failed) {
        PyErr_SetString(PyExc_ValueError, "metric is not positive definite");
        return NULL;
    }
    Py_RETURN_NONE;
}
