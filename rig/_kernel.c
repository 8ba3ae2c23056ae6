/* facecast.rig._kernel: the cubic B-spline weight functions (thesis eq. 3.7, 3.8, 3.12) for
 * ONE frame, compiled, because at ~1 us a frame numpy's per-call overhead is the whole cost.
 * It must not fit, clamp or keep state between calls: it owns copies of the fitted matrices,
 * allocates nothing shared, and so is safe from any number of threads (the GIL is held).
 *
 * For flattened points x (3K) it computes
 *   p   = x P + p0                        reduced parameters, eq. 3.7 (input map folded in)
 *   lin = a0 + p A                        hyperplanes, eq. 3.10
 *   t_j = |p - p_j| / alpha_j             scaled distances (difference form: no cancellation)
 *   b_j = (2 - t_j)_+^3 - 4 (1 - t_j)_+^3 = 6 B(t_j), eq. 3.12
 *   w   = lin + b (R / 6)                 eq. 3.8
 * Products are sums of scaled rows (axpy), so they vectorise without reassociating a
 * reduction: no -ffast-math, IEEE results, and the same frame gives the same bits on every
 * call. Work that can only add exact zeros is skipped: the rest of |p - p_j|^2 once its
 * leading components put p_j out of the B-spline's reach, and the rows of R with b_j == 0.
 * NaN propagates (a NaN b_j is never skipped). The AVX2+FMA build is chosen at import by CPU
 * features; elsewhere a generic build runs (correct, but its 4-double vectors live in memory
 * without AVX: a few times slower, still faster than numpy for one frame).
 *
 * The module also holds project_box (bounded weights, in _boxqp.c), blend_rows (eq. 3.14's
 * blend of small batches, in _blend.c) and f32_to_f16, the
 * float16 wire copy of vertices results (F16C where the CPU has it), which must give numpy's
 * bits exactly (see its section below).
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <string.h>

#if defined(__GNUC__) && !defined(FACECAST_SCALAR) /* FACECAST_SCALAR: test the plain-C path */
/* GCC/clang vector extensions: four doubles, lowered to AVX2 in the avx2 build and to SSE2
 * pairs (or NEON, ...) elsewhere. Loads and stores go through an unaligned, may_alias
 * variant of the type, and macros, so no 32-byte vector crosses a function boundary. */
typedef double vd __attribute__((vector_size(32)));
typedef double vd_unaligned __attribute__((vector_size(32), aligned(8), may_alias));
#define LANES 4
#define ALWAYS_INLINE inline __attribute__((always_inline))
#define ALIGNED_64 __attribute__((aligned(64)))
#define VLOAD(p) (*(const vd_unaligned *)(p))
#define VSTORE(p, v) (*(vd_unaligned *)(p) = (v))
#define VSPLAT(s) ((vd){(s), (s), (s), (s)})
#define HSUM(v) (((v)[0] + (v)[1]) + ((v)[2] + (v)[3]))
#else
typedef double vd;
#define LANES 1
#define ALWAYS_INLINE inline
#define ALIGNED_64
#define VLOAD(p) (*(p))
#define VSTORE(p, v) (*(p) = (v))
#define VSPLAT(s) (s)
#define HSUM(v) (v)
#endif

/* Panels hold up to MAX_VECS vectors of columns: eight accumulators keep enough FMAs in
 * flight to hide their latency and still leave registers for the operands. */
#define MAX_VECS 8
#define PANEL (MAX_VECS * LANES)
/* The first pass over the distances covers the HEAD leading components for every example;
 * only the examples still within reach (t_j < 2) get the rest, CENTRE_STEP at a time. */
#define HEAD 8
#define CENTRE_STEP (2 * LANES)

#if defined(__x86_64__) && defined(__GNUC__)
#define HAVE_AVX2_BUILD 1
#endif

/* A matrix stored as column panels: panel q holds columns [q*PANEL, q*PANEL + width) of every
 * row, rows contiguous, width a multiple of LANES (zero columns pad the last panel), so the
 * kernel streams it front to back. */
typedef struct {
    const double *data;
    Py_ssize_t rows;
    Py_ssize_t cols; /* padded to a multiple of LANES */
} Packed;

typedef struct KernelObject {
    PyObject_HEAD
    Py_ssize_t num_inputs;     /* 3K */
    Py_ssize_t num_components; /* n */
    Py_ssize_t num_examples;   /* M */
    Packed project;            /* (3K, n) */
    Packed linear;             /* (n, M) */
    Py_ssize_t head;           /* leading components the first distance pass covers */
    int has_radial;            /* 0 when every r_ji is zero: w is the hyperplanes alone */
    Packed folded;             /* (3K, M): project @ linear, used when !has_radial */
    const double *folded_offset; /* (M padded): param_offset @ linear + linear_offset */
    Packed centres_head;       /* (head, M): column j is p_j's leading components */
    const double *centres_tail; /* (M, tail_stride): row j is the rest of p_j, zero-padded */
    Py_ssize_t tail_stride;
    const double *prune;       /* (M): d2 >= prune[j] means t_j > 2, so B(t_j) = 0 */
    Packed radial;             /* (M, M): R / 6 */
    const double *param_offset;  /* (n padded) */
    const double *linear_offset; /* (M padded) */
    const double *inv_alpha;     /* (M) */
    void *memory;
    double (*compute)(const struct KernelObject *, const double *, double *, double *);
    PyObject *empty;            /* numpy.empty */
    PyObject *num_examples_obj; /* M as an int, its argument */
} KernelObject;

static Py_ssize_t round_up(Py_ssize_t value, Py_ssize_t step) {
    return (value + step - 1) / step * step;
}

/* -- the arithmetic -------------------------------------------------------------------------- */

enum { OP_AXPY, OP_SQDIST };

/* y[0:nv*LANES] += sum_r a[r] * panel[r]   (OP_AXPY)
 * y[0:nv*LANES] += sum_r (a[r] - panel[r])^2 (OP_SQDIST)
 * over rows r (all rows, or the rows listed in index). nv and op are constants after
 * inlining, so acc lives in registers. */
static ALWAYS_INLINE void panel_op(const int wide, const int op, const int nv, const double *a,
                                   const Py_ssize_t *index, Py_ssize_t count,
                                   const double *panel, double *y) {
    vd acc[MAX_VECS];
    const Py_ssize_t width = nv * LANES;
    if (!wide) {
        /* Without 4-double registers the vectors above would live in memory; plain doubles
         * let the compiler vectorise with what the target has (SSE2, NEON). */
        double sum[MAX_VECS * LANES];
        for (Py_ssize_t c = 0; c < width; c++) sum[c] = y[c];
        for (Py_ssize_t i = 0; i < count; i++) {
            const double *row = panel + (index ? index[i] : i) * width;
            const double s = a[i];
            for (Py_ssize_t c = 0; c < width; c++) {
                if (op == OP_AXPY) {
                    sum[c] += s * row[c];
                } else {
                    const double d = s - row[c];
                    sum[c] += d * d;
                }
            }
        }
        for (Py_ssize_t c = 0; c < width; c++) y[c] = sum[c];
        return;
    }
    for (int v = 0; v < nv; v++) acc[v] = VLOAD(y + v * LANES);
    for (Py_ssize_t i = 0; i < count; i++) {
        const double *row = panel + (index ? index[i] : i) * width;
        const vd s = VSPLAT(a[i]);
        for (int v = 0; v < nv; v++) {
            if (op == OP_AXPY) {
                acc[v] += s * VLOAD(row + v * LANES);
            } else {
                const vd d = s - VLOAD(row + v * LANES);
                acc[v] += d * d;
            }
        }
    }
    for (int v = 0; v < nv; v++) VSTORE(y + v * LANES, acc[v]);
}

#define PANEL_CASE(N) \
    case N: panel_op(wide, op, N, a, index, count, panel, y + col); break;

/* y (m.cols) += the rows of m (all, or those in index) combined by a (count values). */
static ALWAYS_INLINE void matrix_op(const int wide, const int op, const Packed *m, const double *a,
                                    const Py_ssize_t *index, Py_ssize_t count, double *y) {
    const double *panel = m->data;
    for (Py_ssize_t col = 0; col < m->cols; col += PANEL) {
        const Py_ssize_t width = m->cols - col < PANEL ? m->cols - col : PANEL;
        switch (width / LANES) {
            PANEL_CASE(1)
            PANEL_CASE(2)
            PANEL_CASE(3)
            PANEL_CASE(4)
            PANEL_CASE(5)
            PANEL_CASE(6)
            PANEL_CASE(7)
            PANEL_CASE(8)
            default: break;
        }
        panel += m->rows * width;
    }
}

/* scratch holds n_pad + 2 M_pad doubles and M indices' worth of doubles. Writes M weights to
 * out and returns their sum. */
/* Doubles of per-call scratch compute_body needs. */
static Py_ssize_t scratch_size(const KernelObject *k) {
    const Py_ssize_t used = k->head + k->tail_stride;
    const Py_ssize_t p = used > k->project.cols ? used : k->project.cols;
    return p + k->linear.cols + k->centres_head.cols + 2 * k->num_examples;
}

/* Returns 6 B(t_j) for the squared distance d2_j (NaN stays NaN). */
static ALWAYS_INLINE double bspline6(double d2, double inv_alpha) {
    const double t = sqrt(d2) * inv_alpha;
    double u = 2.0 - t, v = 1.0 - t;
    /* written so that NaN survives: (NaN < 0) is false */
    u = u < 0.0 ? 0.0 : u;
    v = v < 0.0 ? 0.0 : v;
    return u * u * u - 4.0 * (v * v * v);
}

/* scratch: see scratch_size. Writes M weights to out and returns their sum. */
static ALWAYS_INLINE double compute_body(const int wide, const KernelObject *k, const double *x,
                                         double *out, double *scratch) {
    const Py_ssize_t m = k->num_examples, head = k->head, stride = k->tail_stride;
    const Py_ssize_t used = head + stride;
    double *p = scratch;
    double *w = p + (used > k->project.cols ? used : k->project.cols);
    double *d2 = w + k->linear.cols;
    double *coef = d2 + k->centres_head.cols;
    Py_ssize_t *index = (Py_ssize_t *)(coef + m);

    if (!k->has_radial) {
        /* The hyperplanes interpolate (fit zeroed the radial terms): eq. 3.7 and 3.10 folded
         * into one product from the raw points. */
        memcpy(w, k->folded_offset, sizeof(double) * k->folded.cols);
        matrix_op(wide, OP_AXPY, &k->folded, x, NULL, k->num_inputs, w);
        goto finish;
    }
    memcpy(p, k->param_offset, sizeof(double) * k->project.cols);
    matrix_op(wide, OP_AXPY, &k->project, x, NULL, k->num_inputs, p); /* eq. 3.7 */
    for (Py_ssize_t c = k->project.cols; c < used; c++) p[c] = 0.0;
    memcpy(w, k->linear_offset, sizeof(double) * k->linear.cols);
    matrix_op(wide, OP_AXPY, &k->linear, p, NULL, k->num_components, w); /* eq. 3.10 */

    /* |p - p_j|^2 over the leading (largest-variance) components for every j, then the rest
     * only for the j still within reach. The rest only adds to the sum and rounding is
     * monotonic, so a j dropped here would have got B = 0 exactly: dropping changes no bit.
     * No early exits inside the loops: unpredictable branches cost more than the sums. */
    memset(d2, 0, sizeof(double) * k->centres_head.cols);
    matrix_op(wide, OP_SQDIST, &k->centres_head, p, NULL, head, d2);
    Py_ssize_t near = 0;
    for (Py_ssize_t j = 0; j < m; j++) {
        index[near] = j;
        near += !(d2[j] >= k->prune[j]); /* NaN stays */
    }
    Py_ssize_t count = 0;
    for (Py_ssize_t i = 0; i < near; i++) {
        const Py_ssize_t j = index[i];
        const double *rest = k->centres_tail + j * stride;
        double tail = 0.0;
        if (wide) {
            vd even = VSPLAT(0.0), odd = VSPLAT(0.0);
            for (Py_ssize_t c = 0; c < stride; c += CENTRE_STEP) {
                const vd a = VLOAD(p + head + c) - VLOAD(rest + c);
                const vd b = VLOAD(p + head + c + LANES) - VLOAD(rest + c + LANES);
                even += a * a;
                odd += b * b;
            }
            const vd both = even + odd;
            tail = HSUM(both);
        } else {
            for (Py_ssize_t c = 0; c < stride; c++) {
                const double a = p[head + c] - rest[c];
                tail += a * a;
            }
        }
        const double b = bspline6(d2[j] + tail, k->inv_alpha[j]);
        coef[count] = b;
        index[count] = j; /* count <= i: overwrites only entries already read */
        count += b != 0.0; /* true for NaN */
    }
    matrix_op(wide, OP_AXPY, &k->radial, coef, index, count, w); /* eq. 3.8 */

finish:;

    /* The sum only tells the caller whether a NaN or Inf got in; lanes keep it short. */
    double total = 0.0;
    Py_ssize_t whole = 0;
    if (wide) {
        whole = m / LANES * LANES;
        vd lanes = VSPLAT(0.0);
        for (Py_ssize_t i = 0; i < whole; i += LANES) lanes += VLOAD(w + i);
        total = HSUM(lanes);
    }
    for (Py_ssize_t i = whole; i < m; i++) total += w[i];
    memcpy(out, w, sizeof(double) * m);
    return total;
}

typedef double (*compute_fn)(const KernelObject *, const double *, double *, double *);

static double compute_generic(const KernelObject *k, const double *x, double *out,
                              double *scratch) {
    return compute_body(0, k, x, out, scratch);
}

#ifdef HAVE_AVX2_BUILD
/* Chosen at import by CPU features (not by CPU model, which is how target_clones'
 * "arch=haswell" dispatches, and which misses every AMD core). */
__attribute__((target("avx2,fma"))) static double compute_avx2(const KernelObject *k,
                                                               const double *x, double *out,
                                                               double *scratch) {
    return compute_body(1, k, x, out, scratch);
}
#endif

static compute_fn compute = compute_generic;
static const char *compute_isa = "generic";

/* -- buffers --------------------------------------------------------------------------------- */

/* The item type of a buffer format: 'd', 'f' or 'e' in native byte order, else 0. */
static char float_kind(const char *format) {
    if (format == NULL) return 0;
    if (format[0] == '@' || format[0] == '=') format++;
#if PY_LITTLE_ENDIAN
    else if (format[0] == '<') format++;
#else
    else if (format[0] == '>') format++;
#endif
    if (format[0] == '\0' || format[1] != '\0') return 0;
    return format[0] == 'd' || format[0] == 'f' || format[0] == 'e' ? format[0] : 0;
}

static const Py_ssize_t item_size[128] = {['d'] = 8, ['f'] = 4, ['e'] = 2};

enum { SHAPE_FLAT, SHAPE_POINTS, SHAPE_FLAT_OR_POINTS };

/* A C-contiguous buffer of `length` floats: float64 only (accept == 'd') or float16/32/64
 * (accept == 0). Its shape: (length,) and/or (length/3, 3), one frame's points as they come.
 * Stores the item type in *kind. Raises TypeError (not a buffer, not floats) or ValueError
 * (shape, layout, read-only) and returns -1. */
static int get_vector(PyObject *obj, Py_buffer *view, Py_ssize_t length, int writable,
                      int shape, char accept, char *kind, const char *name) {
    if (PyObject_GetBuffer(obj, view, PyBUF_STRIDES | PyBUF_FORMAT) < 0) {
        if (PyErr_ExceptionMatches(PyExc_BufferError)) {
            PyErr_Clear();
            PyErr_Format(PyExc_TypeError, "%s: cannot read %.100s as a buffer", name,
                         Py_TYPE(obj)->tp_name);
        }
        return -1;
    }
    *kind = float_kind(view->format);
    if (*kind == 0 || (accept && *kind != accept) || view->itemsize != item_size[(int)*kind]) {
        PyErr_Format(PyExc_TypeError, "%s: expected %s items, got format '%s'", name,
                     accept ? "float64" : "float16, float32 or float64",
                     view->format ? view->format : "B");
        PyBuffer_Release(view);
        return -1;
    }
    const int flat = view->ndim == 1 && view->shape[0] == length;
    const int points =
        view->ndim == 2 && view->shape[1] == 3 && view->shape[0] * 3 == length;
    const int shaped = shape == SHAPE_FLAT     ? flat
                       : shape == SHAPE_POINTS ? points
                                               : flat || points;
    if (!shaped) {
        if (shape == SHAPE_FLAT)
            PyErr_Format(PyExc_ValueError, "%s: expected shape (%zd,)", name, length);
        else if (shape == SHAPE_POINTS)
            PyErr_Format(PyExc_ValueError, "%s: expected shape (%zd, 3)", name, length / 3);
        else
            PyErr_Format(PyExc_ValueError, "%s: expected shape (%zd,) or (%zd, 3)", name, length,
                         length / 3);
    } else if (!PyBuffer_IsContiguous(view, 'C')) {
        PyErr_Format(PyExc_ValueError, "%s must be C-contiguous", name);
    } else if (writable && view->readonly) {
        PyErr_Format(PyExc_ValueError, "%s must be writable", name);
    } else {
        return 0;
    }
    PyBuffer_Release(view);
    return -1;
}

/* A C-contiguous float64 array of shape (rows, cols), or (rows,) when cols < 0. */
static int get_array(PyObject *obj, Py_buffer *view, Py_ssize_t rows, Py_ssize_t cols,
                     const char *name) {
    if (PyObject_GetBuffer(obj, view, PyBUF_STRIDES | PyBUF_FORMAT) < 0) return -1;
    const int ndim = cols < 0 ? 1 : 2;
    if (float_kind(view->format) != 'd' || view->itemsize != sizeof(double)) {
        PyErr_Format(PyExc_TypeError, "%s: expected float64 items", name);
    } else if (!PyBuffer_IsContiguous(view, 'C')) {
        PyErr_Format(PyExc_ValueError, "%s must be C-contiguous", name);
    } else if (view->ndim != ndim || view->shape[0] != rows ||
               (ndim == 2 && view->shape[1] != cols)) {
        if (ndim == 1)
            PyErr_Format(PyExc_ValueError, "%s: expected shape (%zd,)", name, rows);
        else
            PyErr_Format(PyExc_ValueError, "%s: expected shape (%zd, %zd)", name, rows, cols);
    } else {
        return 0;
    }
    PyBuffer_Release(view);
    return -1;
}

/* Copies a row-major (rows, cols) matrix into column panels at dst; returns the doubles used. */
static Py_ssize_t pack(Packed *m, double *dst, const double *src, Py_ssize_t rows,
                       Py_ssize_t cols) {
    m->data = dst;
    m->rows = rows;
    m->cols = round_up(cols, LANES);
    for (Py_ssize_t col = 0; col < m->cols; col += PANEL) {
        const Py_ssize_t width = m->cols - col < PANEL ? m->cols - col : PANEL;
        for (Py_ssize_t r = 0; r < rows; r++) {
            for (Py_ssize_t c = 0; c < width; c++)
                dst[r * width + c] = col + c < cols ? src[r * cols + col + c] : 0.0;
        }
        dst += rows * width;
    }
    return rows * m->cols;
}

/* -- the type -------------------------------------------------------------------------------- */

static void kernel_dealloc(KernelObject *self) {
    PyMem_Free(self->memory);
    Py_XDECREF(self->empty);
    Py_XDECREF(self->num_examples_obj);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyObject *kernel_new(PyTypeObject *type, PyObject *args, PyObject *kwds) {
    static char *keywords[] = {"project", "param_offset", "linear", "linear_offset", "centres",
                               "alpha",   "radial",       "generic", NULL};
    PyObject *objs[7];
    int generic = 0;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "OOOOOOO|$p:BsplineKernel", keywords, &objs[0],
                                     &objs[1], &objs[2], &objs[3], &objs[4], &objs[5], &objs[6],
                                     &generic))
        return NULL;
    Py_buffer views[7];
    int got = 0;
    KernelObject *self = NULL;

    /* project fixes 3K and n, linear_offset fixes M; the rest must agree. */
    if (PyObject_GetBuffer(objs[0], &views[0], PyBUF_STRIDES | PyBUF_FORMAT) < 0) return NULL;
    got = 1;
    if (views[0].ndim != 2) {
        PyErr_SetString(PyExc_ValueError, "project: expected a 2-D (3K, n) array");
        goto fail;
    }
    const Py_ssize_t k3 = views[0].shape[0], n = views[0].shape[1];
    PyBuffer_Release(&views[0]);
    got = 0;
    if (get_array(objs[0], &views[0], k3, n, "project") < 0) goto fail;
    got = 1;
    if (PyObject_GetBuffer(objs[3], &views[3], PyBUF_STRIDES | PyBUF_FORMAT) < 0) goto fail;
    const Py_ssize_t m = views[3].ndim == 1 ? views[3].shape[0] : -1;
    PyBuffer_Release(&views[3]);
    if (k3 < 1 || n < 1 || m < 1) {
        PyErr_SetString(PyExc_ValueError,
                        "need at least one input, one component and one example "
                        "(linear_offset: expected shape (M,))");
        goto fail;
    }
    const Py_ssize_t rows[7] = {k3, n, n, m, m, m, m};
    const Py_ssize_t cols[7] = {n, -1, m, -1, n, -1, m};
    const char *names[7] = {"project", "param_offset", "linear", "linear_offset",
                            "centres", "alpha",        "radial"};
    for (got = 1; got < 7; got++) {
        if (get_array(objs[got], &views[got], rows[got], cols[got], names[got]) < 0) goto fail;
    }

    self = (KernelObject *)type->tp_alloc(type, 0);
    if (self == NULL) goto fail;
    const Py_ssize_t np_ = round_up(n, LANES), mp = round_up(m, LANES);
    const Py_ssize_t head = n < HEAD ? n : HEAD, ts = round_up(n - head, CENTRE_STEP);
    const Py_ssize_t total =
        k3 * np_ + n * mp + head * mp + m * ts + m * mp + np_ + mp + 2 * m + k3 * mp + mp;
    self->memory = PyMem_Calloc((size_t)total + 8, sizeof(double));
    if (self->memory == NULL) {
        PyErr_NoMemory();
        goto fail;
    }
    /* 64-byte alignment: a row of a panel never straddles more cache lines than it must. */
    double *dst = (double *)(((uintptr_t)self->memory + 63) & ~(uintptr_t)63);
    self->num_inputs = k3;
    self->num_components = n;
    self->num_examples = m;
    self->compute = generic ? compute_generic : compute;
    {
        PyObject *numpy = PyImport_ImportModule("numpy");
        if (numpy == NULL) goto fail;
        self->empty = PyObject_GetAttrString(numpy, "empty");
        Py_DECREF(numpy);
        if (self->empty == NULL) goto fail;
        self->num_examples_obj = PyLong_FromSsize_t(m);
        if (self->num_examples_obj == NULL) goto fail;
    }
    dst += pack(&self->project, dst, views[0].buf, k3, n);
    dst += pack(&self->linear, dst, views[2].buf, n, m);
    {
        /* The leading components as columns for the first pass; the rest as rows, zero-padded
         * (p is zero-padded alike, so the pad adds nothing). */
        const double *params = views[4].buf;
        double *transposed = PyMem_Malloc(sizeof(double) * (size_t)(head * m));
        if (transposed == NULL) {
            PyErr_NoMemory();
            goto fail;
        }
        for (Py_ssize_t c = 0; c < head; c++)
            for (Py_ssize_t j = 0; j < m; j++) transposed[c * m + j] = params[j * n + c];
        self->head = head;
        dst += pack(&self->centres_head, dst, transposed, head, m);
        PyMem_Free(transposed);
        self->tail_stride = ts;
        for (Py_ssize_t j = 0; j < m; j++)
            memcpy(dst + j * ts, params + j * n + head, sizeof(double) * (size_t)(n - head));
        self->centres_tail = dst;
        dst += m * ts;
    }
    {
        const double *radial = views[6].buf;
        double *scaled = PyMem_Malloc(sizeof(double) * (size_t)(m * m));
        if (scaled == NULL) {
            PyErr_NoMemory();
            goto fail;
        }
        self->has_radial = 0;
        for (Py_ssize_t i = 0; i < m * m; i++) {
            scaled[i] = radial[i] / 6.0;
            self->has_radial |= radial[i] != 0.0;
        }
        dst += pack(&self->radial, dst, scaled, m, m);
        PyMem_Free(scaled);
    }
    memcpy(dst, views[1].buf, sizeof(double) * (size_t)n);
    self->param_offset = dst;
    dst += np_;
    memcpy(dst, views[3].buf, sizeof(double) * (size_t)m);
    self->linear_offset = dst;
    dst += mp;
    {
        const double *alpha = views[5].buf;
        double *inv_alpha = dst, *prune = dst + m;
        for (Py_ssize_t j = 0; j < m; j++) {
            if (!(alpha[j] > 0.0) || !isfinite(1.0 / alpha[j])) {
                PyErr_SetString(PyExc_ValueError,
                                "alpha: dilation factors must be finite and > 0");
                goto fail;
            }
            inv_alpha[j] = 1.0 / alpha[j];
            /* A partial |p - p_j|^2 at or past (2 alpha_j)^2 (1 + 1e-12) leaves t_j > 2 after
             * every rounding, fused or not: B(t_j) = 0 exactly. Too small or too large to
             * trust: never stop early. */
            const double reach = 4.0 * alpha[j] * alpha[j] * (1.0 + 1e-12);
            prune[j] = isfinite(reach) && reach > 1e-280 ? reach : INFINITY;
        }
        self->inv_alpha = inv_alpha;
        self->prune = prune;
        dst += 2 * m;
    }
    {
        /* folded = project @ linear and its offset, for rigs without radial terms. */
        const double *project = views[0].buf, *linear = views[2].buf;
        const double *param_offset = views[1].buf, *linear_offset = views[3].buf;
        double *product = PyMem_Calloc((size_t)(k3 * m), sizeof(double));
        if (product == NULL) {
            PyErr_NoMemory();
            goto fail;
        }
        for (Py_ssize_t r = 0; r < k3; r++)
            for (Py_ssize_t c = 0; c < n; c++)
                for (Py_ssize_t j = 0; j < m; j++)
                    product[r * m + j] += project[r * n + c] * linear[c * m + j];
        dst += pack(&self->folded, dst, product, k3, m);
        PyMem_Free(product);
        double *offset = dst;
        for (Py_ssize_t j = 0; j < m; j++) {
            double sum = linear_offset[j];
            for (Py_ssize_t c = 0; c < n; c++) sum += param_offset[c] * linear[c * m + j];
            offset[j] = sum;
        }
        self->folded_offset = offset;
        dst += mp;
    }
    for (int i = 0; i < got; i++) PyBuffer_Release(&views[i]);
    return (PyObject *)self;

fail:
    for (int i = 0; i < got; i++) PyBuffer_Release(&views[i]);
    Py_XDECREF(self);
    return NULL;
}

/* Per-call scratch on the stack up to this many doubles (any rig of up to ~1000 examples);
 * beyond, the heap. Either way nothing is shared between calls. */
#define STACK_SCRATCH 4096

/* Weights of the points in xv (items of type kind) into the float64 buffer ov. Returns their
 * sum; on failure (out of memory) sets an error and *failed. */
static double run(const KernelObject *self, const Py_buffer *xv, char kind, const Py_buffer *ov,
                  int *failed) {
    const Py_ssize_t k3 = self->num_inputs;
    const Py_ssize_t need = scratch_size(self) + (kind == 'd' ? 0 : k3);
    ALIGNED_64 double stack[STACK_SCRATCH];
    double *scratch = stack;
    *failed = 0;
    if (need > STACK_SCRATCH) {
        scratch = PyMem_Malloc(sizeof(double) * (size_t)need);
        if (scratch == NULL) {
            PyErr_NoMemory();
            *failed = 1;
            return -1.0;
        }
    }
    const double *x = xv->buf;
    if (kind != 'd') {
        /* float32 and float16 widen to float64 exactly: as numpy's astype would. */
        double *wide = scratch + scratch_size(self);
        if (kind == 'f') {
            const float *narrow = xv->buf;
            for (Py_ssize_t i = 0; i < k3; i++) wide[i] = narrow[i];
        } else {
            const char *half = xv->buf;
            for (Py_ssize_t i = 0; i < k3; i++) wide[i] = PyFloat_Unpack2(half + 2 * i, PY_LITTLE_ENDIAN);
        }
        x = wide;
    }
    const double total = self->compute(self, x, ov->buf, scratch);
    if (scratch != stack) PyMem_Free(scratch);
    return total;
}

PyDoc_STRVAR(evaluate_doc,
             "evaluate(x, out) -> float\n--\n\n"
             "Weights of one frame into out. x: (3K,) or (K, 3) C-contiguous float64 points;\n"
             "out: (M,) writable C-contiguous float64. Returns the weights' sum: NaN or Inf\n"
             "when the points hold NaN or Inf (the weights then do too).");

static PyObject *kernel_evaluate(KernelObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_Format(PyExc_TypeError, "evaluate() takes 2 arguments (x, out), got %zd", nargs);
        return NULL;
    }
    Py_buffer xv, ov;
    char kind, out_kind;
    if (get_vector(args[0], &xv, self->num_inputs, 0, SHAPE_FLAT_OR_POINTS, 'd', &kind, "x") < 0)
        return NULL;
    if (get_vector(args[1], &ov, self->num_examples, 1, SHAPE_FLAT, 'd', &out_kind, "out") < 0) {
        PyBuffer_Release(&xv);
        return NULL;
    }
    int failed;
    const double total = run(self, &xv, kind, &ov, &failed);
    PyBuffer_Release(&xv);
    PyBuffer_Release(&ov);
    return failed ? NULL : PyFloat_FromDouble(total);
}

PyDoc_STRVAR(evaluate_rows_doc,
             "evaluate_rows(x, out)\n--\n\n"
             "Weights of B frames: row b of out gets evaluate(x[b]), the same bits as one frame\n"
             "alone (so batched and single-frame results agree exactly). x: (B, 3K) C-contiguous\n"
             "float64; out: (B, M) writable C-contiguous float64. Releases the GIL.");

static PyObject *kernel_evaluate_rows(KernelObject *self, PyObject *const *args,
                                      Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_Format(PyExc_TypeError, "evaluate_rows() takes 2 arguments (x, out), got %zd",
                     nargs);
        return NULL;
    }
    Py_buffer xv, ov;
    if (PyObject_GetBuffer(args[0], &xv, PyBUF_STRIDES | PyBUF_FORMAT) < 0) return NULL;
    const Py_ssize_t rows = xv.ndim == 2 ? xv.shape[0] : -1;
    PyBuffer_Release(&xv);
    if (rows < 0) {
        PyErr_SetString(PyExc_ValueError, "x: expected a 2-d (B, 3K) array");
        return NULL;
    }
    if (get_array(args[0], &xv, rows, self->num_inputs, "x") < 0) return NULL;
    if (get_array(args[1], &ov, rows, self->num_examples, "out") < 0) {
        PyBuffer_Release(&xv);
        return NULL;
    }
    if (ov.readonly) {
        PyErr_SetString(PyExc_ValueError, "out must be writable");
        PyBuffer_Release(&xv);
        PyBuffer_Release(&ov);
        return NULL;
    }
    double *scratch = PyMem_Malloc(sizeof(double) * (size_t)scratch_size(self));
    if (scratch == NULL) {
        PyBuffer_Release(&xv);
        PyBuffer_Release(&ov);
        return PyErr_NoMemory();
    }
    const double *x = xv.buf;
    double *out = ov.buf;
    const Py_ssize_t k3 = self->num_inputs, m = self->num_examples;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t b = 0; b < rows; b++) self->compute(self, x + b * k3, out + b * m, scratch);
    Py_END_ALLOW_THREADS
    PyMem_Free(scratch);
    PyBuffer_Release(&xv);
    PyBuffer_Release(&ov);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(weights_doc,
             "weights(points, limit=inf) -> ndarray | None\n--\n\n"
             "Weights of one frame as a new (M,) float64 array, or None when they are not all\n"
             "finite (the points hold NaN or Inf: the caller's checks say so) or when the\n"
             "points' sum of squares (in float64) is not <= limit (the caller's range check\n"
             "decides). points: (K, 3) C-contiguous float16, float32 or float64 (widened\n"
             "exactly).");

/* The sum of squares of a frame's 3K values, in float64 (NaN when one is NaN). */
static double sum_of_squares(const Py_buffer *xv, char kind, Py_ssize_t k3) {
    double total = 0.0;
    if (kind == 'd') {
        const double *x = xv->buf;
        for (Py_ssize_t i = 0; i < k3; i++) total += x[i] * x[i];
    } else if (kind == 'f') {
        const float *x = xv->buf;
        for (Py_ssize_t i = 0; i < k3; i++) total += (double)x[i] * (double)x[i];
    } else {
        const char *half = xv->buf;
        for (Py_ssize_t i = 0; i < k3; i++) {
            const double v = PyFloat_Unpack2(half + 2 * i, PY_LITTLE_ENDIAN);
            total += v * v;
        }
    }
    return total;
}

static PyObject *kernel_weights(KernelObject *self, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 1 && nargs != 2) {
        PyErr_Format(PyExc_TypeError, "weights() takes 1 or 2 arguments (points, limit), got %zd",
                     nargs);
        return NULL;
    }
    double limit = INFINITY;
    if (nargs == 2 && (limit = PyFloat_AsDouble(args[1])) == -1.0 && PyErr_Occurred())
        return NULL;
    Py_buffer xv, ov;
    char kind;
    if (get_vector(args[0], &xv, self->num_inputs, 0, SHAPE_POINTS, 0, &kind, "points") < 0)
        return NULL;
    /* The range check's shortcut, in the pass that reads the points anyway (~20 ns, where
     * numpy's vdot of a frame costs ~0.45 us): a frame past it is not this call's to judge. */
    if (nargs == 2 && !(sum_of_squares(&xv, kind, self->num_inputs) <= limit)) {
        PyBuffer_Release(&xv);
        Py_RETURN_NONE;
    }
    /* numpy.empty through vectorcall: the buffer protocol alone cannot make an array. */
    PyObject *out = PyObject_Vectorcall(self->empty, &self->num_examples_obj, 1, NULL);
    if (out == NULL) {
        PyBuffer_Release(&xv);
        return NULL;
    }
    /* A fresh float64 array of M items: the plainest request is the cheapest (numpy skips
     * building the format string and strides). */
    if (PyObject_GetBuffer(out, &ov, PyBUF_WRITABLE) < 0) {
        PyBuffer_Release(&xv);
        Py_DECREF(out);
        return NULL;
    }
    if (ov.len != self->num_examples * (Py_ssize_t)sizeof(double)) {
        PyErr_SetString(PyExc_SystemError, "numpy.empty returned an unexpected buffer");
        PyBuffer_Release(&ov);
        PyBuffer_Release(&xv);
        Py_DECREF(out);
        return NULL;
    }
    int failed;
    const double total = run(self, &xv, kind, &ov, &failed);
    PyBuffer_Release(&xv);
    PyBuffer_Release(&ov);
    if (failed) {
        Py_DECREF(out);
        return NULL;
    }
    if (!isfinite(total)) {
        Py_DECREF(out);
        Py_RETURN_NONE;
    }
    return out;
}

static PyMethodDef kernel_methods[] = {
    {"evaluate", (PyCFunction)(void (*)(void))kernel_evaluate, METH_FASTCALL, evaluate_doc},
    {"weights", (PyCFunction)(void (*)(void))kernel_weights, METH_FASTCALL, weights_doc},
    {"evaluate_rows", (PyCFunction)(void (*)(void))kernel_evaluate_rows, METH_FASTCALL,
     evaluate_rows_doc},
    {NULL, NULL, 0, NULL},
};

static PyObject *get_num_inputs(KernelObject *self, void *closure) {
    return PyLong_FromSsize_t(self->num_inputs);
}
static PyObject *get_num_components(KernelObject *self, void *closure) {
    return PyLong_FromSsize_t(self->num_components);
}
static PyObject *get_num_examples(KernelObject *self, void *closure) {
    return PyLong_FromSsize_t(self->num_examples);
}

static PyGetSetDef kernel_getset[] = {
    {"num_inputs", (getter)get_num_inputs, NULL, "3K: length of a frame's flattened points", NULL},
    {"num_components", (getter)get_num_components, NULL, "n: kept PCA components", NULL},
    {"num_examples", (getter)get_num_examples, NULL, "M: weights per frame", NULL},
    {NULL, NULL, NULL, NULL, NULL},
};

PyDoc_STRVAR(kernel_doc,
             "BsplineKernel(project, param_offset, linear, linear_offset, centres, alpha, radial)\n"
             "--\n\n"
             "Single-frame B-spline weights w(x) = a0 + p A + B(|p - p_j| / alpha_j) R with\n"
             "p = x P + p0. project (3K, n), param_offset (n,), linear (n, M), linear_offset\n"
             "(M,), centres (M, n) (the examples' p_j), alpha (M,) finite and > 0 and radial\n"
             "(M, M), all C-contiguous float64. The arrays are copied: later changes to them\n"
             "do not reach the kernel. generic=True forces the build for CPUs without AVX2\n"
             "(for tests).");

static PyTypeObject KernelType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "facecast.rig._kernel.BsplineKernel",
    .tp_basicsize = sizeof(KernelObject),
    .tp_dealloc = (destructor)kernel_dealloc,
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_doc = kernel_doc,
    .tp_methods = kernel_methods,
    .tp_getset = kernel_getset,
    .tp_new = kernel_new,
};

/* -- float32 -> float16 --------------------------------------------------------------------- */

/* The wire copy of a vertices result (PROTOCOL.md: f16 results). numpy's cast is a scalar
 * loop on CPUs its build does not assume F16C for (~2.7 ns a value); F16C does 8 at a time.
 * Both round to nearest, ties to even, so they give the same bits; NaN differs (F16C sets
 * the quiet bit, numpy keeps the payload's top bits), so blocks holding a NaN go through
 * f32_bits_to_f16, which follows numpy bit for bit. */

static inline uint16_t f32_bits_to_f16(uint32_t f) {
    uint16_t sign = (uint16_t)((f >> 16) & 0x8000u);
    uint32_t a = f & 0x7fffffffu;
    if (a >= 0x7f800000u) { /* Inf, or NaN: the payload's top 10 bits, kept non-zero */
        uint16_t payload = (uint16_t)(a >> 13) & 0x3ffu;
        return sign | 0x7c00u | (a == 0x7f800000u ? 0 : (payload ? payload : 1));
    }
    if (a >= 0x477ff000u) return sign | 0x7c00u; /* at least 65520: rounds past 65504 */
    uint32_t h, rem, half;
    if (a >= 0x38800000u) { /* normal half: rebias the exponent, round 13 bits away */
        uint32_t r = a - 0x38000000u;
        h = r >> 13;
        rem = r & 0x1fffu;
        half = 0x1000u;
    } else if (a >= 0x33000000u) { /* subnormal half: units of 2^-24 */
        uint32_t shift = 126u - (a >> 23); /* 14 .. 24 */
        uint32_t m = (a & 0x7fffffu) | 0x800000u;
        h = m >> shift;
        rem = m & ((1u << shift) - 1u);
        half = 1u << (shift - 1u);
    } else { /* below 2^-25: rounds to zero */
        return sign;
    }
    /* A carry out of the mantissa bumps the exponent, which is the right answer. */
    if (rem > half || (rem == half && (h & 1u))) h++;
    return sign | (uint16_t)h;
}

static void f32_to_f16_generic(const float *src, uint16_t *dst, Py_ssize_t n) {
    for (Py_ssize_t i = 0; i < n; i++) {
        uint32_t bits;
        memcpy(&bits, src + i, sizeof bits);
        dst[i] = f32_bits_to_f16(bits);
    }
}

#ifdef HAVE_AVX2_BUILD
#include <immintrin.h>

__attribute__((target("f16c,avx2"))) static void f32_to_f16_f16c(const float *src, uint16_t *dst,
                                                                 Py_ssize_t n) {
    Py_ssize_t i = 0;
    for (; i + 8 <= n; i += 8) {
        __m256 v = _mm256_loadu_ps(src + i);
        if (_mm256_movemask_ps(_mm256_cmp_ps(v, v, _CMP_UNORD_Q))) {
            f32_to_f16_generic(src + i, dst + i, 8);
        } else {
            _mm_storeu_si128((__m128i *)(dst + i),
                             _mm256_cvtps_ph(v, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC));
        }
    }
    f32_to_f16_generic(src + i, dst + i, n - i);
}
#endif

typedef void (*convert_fn)(const float *, uint16_t *, Py_ssize_t);
static convert_fn convert_f16 = f32_to_f16_generic;
static const char *convert_isa = "generic";

/* The buffer's format is `code` in native or little-endian order (x86 and ARM: the same). */
static int format_is(const Py_buffer *view, char code) {
    const char *f = view->format;
    if (f == NULL) return 0;
    if (f[0] == '@' || f[0] == '=' || f[0] == '<') f++;
    return f[0] == code && f[1] == '\0';
}

static PyObject *module_f32_to_f16(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    (void)module;
    int generic = 0;
    if (nargs == 3) {
        generic = PyObject_IsTrue(args[2]);
        if (generic < 0) return NULL;
    } else if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "f32_to_f16(src, dst, generic=False) takes 2 or 3 "
                                         "positional arguments");
        return NULL;
    }
    Py_buffer src, dst;
    if (PyObject_GetBuffer(args[0], &src, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) return NULL;
    if (PyObject_GetBuffer(args[1], &dst, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) <
        0) {
        PyBuffer_Release(&src);
        return NULL;
    }
    const char *error = NULL;
    Py_ssize_t n = src.len / 4;
    if (src.itemsize != 4 || !format_is(&src, 'f')) {
        error = "src must be a C-contiguous float32 buffer";
    } else if (dst.itemsize != 2 || !format_is(&dst, 'e')) {
        error = "dst must be a writable C-contiguous float16 buffer";
    } else if (dst.len != 2 * n) {
        error = "src and dst must hold the same number of values";
    } else if ((const char *)dst.buf < (const char *)src.buf + src.len &&
               (const char *)src.buf < (const char *)dst.buf + dst.len) {
        error = "src and dst must not overlap";
    }
    if (error == NULL) {
        convert_fn convert = generic ? f32_to_f16_generic : convert_f16;
        /* Large results (ICT: 80k values, ~20 us) convert in clone pool threads. */
        Py_BEGIN_ALLOW_THREADS
        convert((const float *)src.buf, (uint16_t *)dst.buf, n);
        Py_END_ALLOW_THREADS
    }
    PyBuffer_Release(&src);
    PyBuffer_Release(&dst);
    if (error != NULL) {
        PyErr_SetString(PyExc_ValueError, error);
        return NULL;
    }
    Py_RETURN_NONE;
}

PyDoc_STRVAR(f32_to_f16_doc,
             "f32_to_f16(src, dst, generic=False)\n"
             "--\n\n"
             "Write src (C-contiguous float32) into dst (C-contiguous float16, as many values,\n"
             "not overlapping src), rounding to nearest, ties to even: the same bits as numpy's\n"
             "src.astype(float16), NaN payloads included. generic=True forces the plain-C\n"
             "path (for tests). Releases the GIL while converting.");

/* In _boxqp.c. */
PyObject *facecast_project_box(PyObject *module, PyObject *const *args, Py_ssize_t nargs);

PyDoc_STRVAR(project_box_doc,
             "project_box(metric, weights, shift, half, out, upper, max_iter)\n"
             "--\n\n"
             "For each row w of weights (B, N): out = argmin_x (x - w) H (x - w) + 2 half 1^T x\n"
             "subject to 0 <= x (<= upper unless None), H = metric (N, N) symmetric positive\n"
             "definite, shift (N,) = half H^-1 1 (None when half is 0); float64, C-contiguous.\n"
             "Block principal pivoting on the free variables only (see facecast.rig.bounds);\n"
             "each frame's result depends on that frame alone. Releases the GIL while solving.");

/* In _blend.c. */
PyObject *facecast_blend_rows(PyObject *module, PyObject *const *args, Py_ssize_t nargs);
PyObject *facecast_place_columns(PyObject *module, PyObject *const *args, Py_ssize_t nargs);
const char *facecast_blend_init(void);

PyDoc_STRVAR(blend_rows_doc,
             "blend_rows(weights, basis, out, runs=None, generic=False, tile=0)\n"
             "--\n\n"
             "out = weights (B, M) @ basis (M, C), float32, C-contiguous, out (B, C) writable and\n"
             "not overlapping the others. With runs, an (R, 3) int64 array of (basis column,\n"
             "out column, count), those columns of the product go to those of out (B, any\n"
             "width), whose other columns are left as they are. Columns go in tiles (tile\n"
             "columns; 0: 512): each basis row some frame weighs is read once per tile and\n"
             "added into every frame whose weight for it is not 0, so a batch reads each used\n"
             "row once and zero weights cost nothing. A column's value depends on that column\n"
             "of basis and the weights only. Agrees with a BLAS product to float rounding\n"
             "(another summation order). generic=True forces the plain-C path (for tests).\n"
             "Releases the GIL.");

PyDoc_STRVAR(place_columns_doc,
             "place_columns(src, out, runs)\n"
             "--\n\n"
             "Copy each run's columns of src (B, C) to its columns of out (B, W): runs an (R, 3)\n"
             "int64 array of (src column, out column, count) as blend_rows takes; float32,\n"
             "C-contiguous, out writable and not overlapping src; out's other columns are left\n"
             "as they are. Releases the GIL.");

static PyMethodDef module_methods[] = {
    {"blend_rows", (PyCFunction)(void (*)(void))facecast_blend_rows, METH_FASTCALL,
     blend_rows_doc},
    {"place_columns", (PyCFunction)(void (*)(void))facecast_place_columns, METH_FASTCALL,
     place_columns_doc},
    {"f32_to_f16", (PyCFunction)(void (*)(void))module_f32_to_f16, METH_FASTCALL, f32_to_f16_doc},
    {"project_box", (PyCFunction)(void (*)(void))facecast_project_box, METH_FASTCALL,
     project_box_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef kernel_module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "facecast.rig._kernel",
    .m_doc = "Compiled single-frame B-spline weights, bounded weights, the blend of small "
             "batches and the float32 -> float16 result cast (see facecast.rig.kernel, "
             "facecast.rig.bounds and facecast.rig.blend).",
    .m_size = -1,
    .m_methods = module_methods,
};

PyMODINIT_FUNC PyInit__kernel(void) {
#ifdef HAVE_AVX2_BUILD
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma")) {
        compute = compute_avx2;
        compute_isa = "avx2+fma";
    }
    if (__builtin_cpu_supports("f16c") && __builtin_cpu_supports("avx2")) {
        convert_f16 = f32_to_f16_f16c;
        convert_isa = "f16c";
    }
#endif
    const char *blend_isa = facecast_blend_init();
    if (PyType_Ready(&KernelType) < 0) return NULL;
    PyObject *module = PyModule_Create(&kernel_module);
    if (module == NULL) return NULL;
    if (PyModule_AddObjectRef(module, "BsplineKernel", (PyObject *)&KernelType) < 0 ||
        PyModule_AddStringConstant(module, "ISA", compute_isa) < 0 ||
        PyModule_AddStringConstant(module, "F16_ISA", convert_isa) < 0 ||
        PyModule_AddStringConstant(module, "BLEND_ISA", blend_isa) < 0) {
        Py_DECREF(module);
        return NULL;
    }
    return module;
}
