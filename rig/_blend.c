/* facecast.rig._kernel.blend_rows: eq. 3.14's blend weights (B, M) @ basis (M, C) in float32
 * for small batches, reading each basis row that some frame uses once per batch (see
 * rig/blend.py). The basis is ~18 MB (ICT) and a blend only streams it, so what it costs is
 * how often a row is read: BLAS copies ("packs") the whole basis per call, scipy's CSR
 * product reads a row once per frame that uses it. Here the columns go in tiles of 2 kB of
 * a row: for each tile, the rows some frame weighs are taken GROUP at a time (their tiles,
 * 32 kB, stay in L1 once the first frame has read them from memory), and each frame whose
 * weights for the group are not all 0 adds its terms to its output tile in registers, 64
 * columns at a time, loading and storing the output tile once per group. Nothing is copied,
 * a zero weight costs nothing. It must not keep state: it reads its arguments only. Runs
 * (basis column, out column, count) let a product over some columns land in a wider output
 * (a full blend from the moving columns) without a scatter.
 *
 * Each output column is a sum over the used rows in increasing order, the first term a
 * product, each next one fused (AVX2+FMA: vector lanes and tail alike) or as the compiler
 * rounds a*b+c (generic): a column's value depends only on that column of the basis and the
 * weights, never on the column count, the tile or the run.
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <stdint.h>
#include <string.h>

#if defined(__x86_64__) && defined(__GNUC__)
#define HAVE_AVX2_BUILD 1
#include <immintrin.h>
#endif

/* Columns a tile holds when the caller does not say: 2 kB of a row, so a group's row tiles
 * (GROUP x 2 kB) stay in L1; with MAX_BATCH (32) frames the output tiles take 64 kB (L2).
 * Measured on ICT (B = 1..16, groups of 2 to 32 rows, tiles of 256 to 8192 columns): 16
 * rows and 512 columns were best or within noise of it everywhere. */
#define DEFAULT_TILE 512

/* What the loops read. The rows some frame weighs go in groups of up to GROUP, in increasing
 * order; for group g and frame b, the terms (basis row, weight not 0) of that frame among the
 * group's rows are [start[g B + b], start[g B + b + 1]). */
typedef struct {
    const float *basis;      /* (M, C) */
    float *out;              /* (B, C) */
    Py_ssize_t frames;       /* B */
    Py_ssize_t cols;         /* C */
    Py_ssize_t out_cols;     /* out's row length: C, or more when runs place the columns */
    Py_ssize_t groups;
    const Py_ssize_t *start; /* (groups B + 1,) */
    const Py_ssize_t *row;   /* (terms,) */
    const float *coef;       /* (terms,) */
    unsigned char *touched;  /* (B,) scratch: the frame's output tile holds a partial sum */
} Plan;

/* A tile: basis columns [c0, c0 + n) into out's columns [d0, d0 + n). */
typedef void (*tile_fn)(const Plan *, Py_ssize_t, Py_ssize_t, Py_ssize_t);

/* A frame's partial sums for a group's rows stay in registers (CHUNK columns at a time) and
 * go to its output tile once per group, not once per row; the group's row tiles stay in L1
 * for the frames after the first. */
#define GROUP 16
#define CHUNK 64

/* One tile, plain C (the compiler vectorises with what it has). */
static void tile_generic(const Plan *p, Py_ssize_t c0, Py_ssize_t d0, Py_ssize_t n) {
    memset(p->touched, 0, (size_t)p->frames);
    for (Py_ssize_t g = 0; g < p->groups; g++) {
        for (Py_ssize_t b = 0; b < p->frames; b++) {
            const Py_ssize_t first = p->start[g * p->frames + b];
            const Py_ssize_t last = p->start[g * p->frames + b + 1];
            if (first == last) continue;
            float *restrict dst = p->out + b * p->out_cols + d0;
            for (Py_ssize_t j = 0; j < n; j += CHUNK) {
                const Py_ssize_t width = n - j < CHUNK ? n - j : CHUNK;
                float acc[CHUNK];
                Py_ssize_t t = first;
                const float *restrict src;
                if (p->touched[b]) {
                    memcpy(acc, dst + j, sizeof(float) * (size_t)width);
                } else {
                    src = p->basis + p->row[t] * p->cols + c0 + j;
                    for (Py_ssize_t c = 0; c < width; c++) acc[c] = p->coef[t] * src[c];
                    t++;
                }
                for (; t < last; t++) {
                    const float w = p->coef[t];
                    src = p->basis + p->row[t] * p->cols + c0 + j;
                    for (Py_ssize_t c = 0; c < width; c++) acc[c] += w * src[c];
                }
                memcpy(dst + j, acc, sizeof(float) * (size_t)width);
            }
            p->touched[b] = 1;
        }
    }
    for (Py_ssize_t b = 0; b < p->frames; b++)
        if (!p->touched[b]) memset(p->out + b * p->out_cols + d0, 0, sizeof(float) * (size_t)n);
}

#ifdef HAVE_AVX2_BUILD
/* The same tile with 8-float FMAs, 64 columns of partial sums in 8 registers (each column a
 * chain of dependent FMAs, one a row): twice the loads in flight of 32 columns in 4, which
 * is what a basis streamed from memory needs (ICT's moving columns, B = 1 to 8, basis
 * evicted from the cache first, as in the server: 8-17 % less time; in the cache, a few %).
 * The tail's columns take 8-wide and scalar FMAs (the same rounding). */
__attribute__((target("avx2,fma"))) static void tile_avx2(const Plan *p, Py_ssize_t c0,
                                                          Py_ssize_t d0, Py_ssize_t n) {
    const Py_ssize_t whole = n & ~(Py_ssize_t)(CHUNK - 1), eights = n & ~(Py_ssize_t)7;
    memset(p->touched, 0, (size_t)p->frames);
    for (Py_ssize_t g = 0; g < p->groups; g++) {
        for (Py_ssize_t b = 0; b < p->frames; b++) {
            const Py_ssize_t first = p->start[g * p->frames + b];
            const Py_ssize_t last = p->start[g * p->frames + b + 1];
            if (first == last) continue;
            const int touched = p->touched[b];
            p->touched[b] = 1;
            float *dst = p->out + b * p->out_cols + d0;
            const float *base = p->basis + c0;
            const Py_ssize_t begin = touched ? first : first + 1;
            const float *src0 = base + p->row[first] * p->cols;
            const __m256 w0 = _mm256_set1_ps(p->coef[first]);
            Py_ssize_t j = 0;
            for (; j < whole; j += CHUNK) {
                __m256 a[CHUNK / 8]; /* unrolled by the compiler: CHUNK / 8 registers */
                if (touched) {
                    for (int k = 0; k < CHUNK / 8; k++) a[k] = _mm256_loadu_ps(dst + j + 8 * k);
                } else {
                    for (int k = 0; k < CHUNK / 8; k++)
                        a[k] = _mm256_mul_ps(w0, _mm256_loadu_ps(src0 + j + 8 * k));
                }
                for (Py_ssize_t t = begin; t < last; t++) {
                    const float *src = base + p->row[t] * p->cols + j;
                    const __m256 w = _mm256_set1_ps(p->coef[t]);
                    for (int k = 0; k < CHUNK / 8; k++)
                        a[k] = _mm256_fmadd_ps(w, _mm256_loadu_ps(src + 8 * k), a[k]);
                }
                for (int k = 0; k < CHUNK / 8; k++) _mm256_storeu_ps(dst + j + 8 * k, a[k]);
            }
            for (; j < eights; j += 8) {
                __m256 a = touched ? _mm256_loadu_ps(dst + j)
                                   : _mm256_mul_ps(w0, _mm256_loadu_ps(src0 + j));
                for (Py_ssize_t t = begin; t < last; t++)
                    a = _mm256_fmadd_ps(_mm256_set1_ps(p->coef[t]),
                                        _mm256_loadu_ps(base + p->row[t] * p->cols + j), a);
                _mm256_storeu_ps(dst + j, a);
            }
            for (; j < n; j++) {
                __m128 a = touched ? _mm_set_ss(dst[j])
                                   : _mm_mul_ss(_mm_set_ss(p->coef[first]), _mm_set_ss(src0[j]));
                for (Py_ssize_t t = begin; t < last; t++)
                    a = _mm_fmadd_ss(_mm_set_ss(p->coef[t]),
                                     _mm_set_ss(base[p->row[t] * p->cols + j]), a);
                dst[j] = _mm_cvtss_f32(a);
            }
        }
    }
    for (Py_ssize_t b = 0; b < p->frames; b++)
        if (!p->touched[b]) memset(p->out + b * p->out_cols + d0, 0, sizeof(float) * (size_t)n);
}
#endif

static tile_fn blend_tile = tile_generic;
static const char *blend_isa = "generic";

/* Called from PyInit__kernel: the AVX2+FMA tile where the CPU has both. */
const char *facecast_blend_init(void) {
#ifdef HAVE_AVX2_BUILD
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma")) {
        blend_tile = tile_avx2;
        blend_isa = "avx2+fma";
    }
#endif
    return blend_isa;
}

/* Runs [runs, runs + n) whose basis columns follow one another, [c0, end): the span is tiled
 * as one run would be, each tile into scratch ((B, tile), a tile's columns a row), then each
 * run's part of it copied to its out columns. Cutting tiles at the runs instead would give
 * short tiles where runs are short (ICT's moving vertices: 270 runs, most under 32 columns),
 * each a jump of every row's stream and scalar tails (a full ICT blend from the moving
 * columns, B = 1 to 8, cold cache: 15-35 % less time); the values are the same either way. */
static void blend_span(const Plan *p, tile_fn run, float *scratch, Py_ssize_t tile,
                       const int64_t *runs, Py_ssize_t n, Py_ssize_t c0, Py_ssize_t end) {
    Plan tiled = *p;
    tiled.out = scratch;
    Py_ssize_t r = 0;
    for (Py_ssize_t j = c0; j < end; j += tile) {
        const Py_ssize_t width = end - j < tile ? end - j : tile;
        tiled.out_cols = width;
        run(&tiled, j, 0, width);
        /* The runs this tile overlaps: from r on (in order), the last may go on. */
        for (; r < n; r++) {
            const Py_ssize_t from = runs[3 * r], to = from + runs[3 * r + 2];
            const Py_ssize_t lo = from > j ? from : j, hi = to < j + width ? to : j + width;
            if (hi > lo) {
                for (Py_ssize_t b = 0; b < p->frames; b++)
                    memcpy(p->out + b * p->out_cols + runs[3 * r + 1] + (lo - from),
                           scratch + b * width + (lo - j), sizeof(float) * (size_t)(hi - lo));
            }
            if (to > j + width) break; /* goes on into the next tile */
        }
    }
}

/* -- the Python function --------------------------------------------------------------------- */

static int is_float32(const Py_buffer *view) {
    const char *f = view->format;
    if (f == NULL || view->itemsize != 4) return 0;
    if (f[0] == '@' || f[0] == '=') f++;
#if PY_LITTLE_ENDIAN
    else if (f[0] == '<') f++;
#endif
    return f[0] == 'f' && f[1] == '\0';
}

static int overlap(const Py_buffer *a, const Py_buffer *b) {
    const char *x = a->buf, *y = b->buf;
    return a->len > 0 && b->len > 0 && x < y + b->len && y < x + a->len;
}

/* A 2-D C-contiguous float32 view of obj, or -1 with TypeError (dtype) or ValueError. */
static int get_matrix(PyObject *obj, Py_buffer *view, int writable, const char *name) {
    if (PyObject_GetBuffer(obj, view, PyBUF_STRIDES | PyBUF_FORMAT |
                                          (writable ? PyBUF_WRITABLE : 0)) < 0)
        return -1;
    if (!is_float32(view)) {
        PyErr_Format(PyExc_TypeError, "%s: expected float32 items", name);
    } else if (view->ndim != 2) {
        PyErr_Format(PyExc_ValueError, "%s: expected a 2-D array, got %d dimensions", name,
                     view->ndim);
    } else if (!PyBuffer_IsContiguous(view, 'C')) {
        PyErr_Format(PyExc_ValueError, "%s must be C-contiguous", name);
    } else {
        return 0;
    }
    PyBuffer_Release(view);
    return -1;
}

/* runs: an (R, 3) C-contiguous int64 array of (source column, out column, count), each
 * inside both arrays (source: "basis" or "src", for the message). Returns R, *view then held
 * for the caller to release, or -1 with an exception set and nothing held. */
static Py_ssize_t get_runs(PyObject *obj, Py_buffer *view, Py_ssize_t cols, Py_ssize_t out_cols,
                           const char *source) {
    if (PyObject_GetBuffer(obj, view, PyBUF_STRIDES | PyBUF_FORMAT) < 0) return -1;
    const char *f = view->format;
    if (f != NULL && (f[0] == '@' || f[0] == '=' || f[0] == '<')) f++;
    if (f == NULL || view->itemsize != 8 || (f[0] != 'q' && f[0] != 'l') || f[1] != '\0') {
        PyErr_SetString(PyExc_TypeError, "runs: expected int64 items");
    } else if (view->ndim != 2 || view->shape[1] != 3 || !PyBuffer_IsContiguous(view, 'C')) {
        PyErr_SetString(PyExc_ValueError, "runs: expected a C-contiguous (R, 3) array");
    } else {
        const int64_t *run = view->buf;
        Py_ssize_t r = 0;
        for (; r < view->shape[0]; r++, run += 3) {
            if (run[0] < 0 || run[1] < 0 || run[2] < 0 || run[0] > cols - run[2] ||
                run[1] > out_cols - run[2])
                break;
        }
        if (r == view->shape[0]) return r;
        PyErr_Format(PyExc_ValueError,
                     "runs[%zd]: (%s column, out column, count) must lie inside %s "
                     "(%zd columns) and out (%zd)",
                     r, source, source, cols, out_cols);
    }
    PyBuffer_Release(view);
    return -1;
}

PyObject *facecast_blend_rows(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    (void)module;
    if (nargs < 3 || nargs > 6) {
        PyErr_SetString(PyExc_TypeError,
                        "blend_rows(weights, basis, out, runs=None, generic=False, tile=0) takes "
                        "3 to 6 positional arguments");
        return NULL;
    }
    int generic = 0;
    Py_ssize_t tile = DEFAULT_TILE;
    if (nargs >= 5 && (generic = PyObject_IsTrue(args[4])) < 0) return NULL;
    if (nargs == 6) {
        tile = PyNumber_AsSsize_t(args[5], PyExc_OverflowError);
        if (tile == -1 && PyErr_Occurred()) return NULL;
        if (tile < 0) {
            PyErr_SetString(PyExc_ValueError, "tile must be >= 0 (0: the default)");
            return NULL;
        }
        if (tile == 0) tile = DEFAULT_TILE;
    }
    Py_buffer wv, bv, ov, rv;
    if (get_matrix(args[0], &wv, 0, "weights") < 0) return NULL;
    if (get_matrix(args[1], &bv, 0, "basis") < 0) {
        PyBuffer_Release(&wv);
        return NULL;
    }
    if (get_matrix(args[2], &ov, 1, "out") < 0) {
        PyBuffer_Release(&wv);
        PyBuffer_Release(&bv);
        return NULL;
    }
    const Py_ssize_t frames = wv.shape[0], m = wv.shape[1], cols = bv.shape[1];
    const Py_ssize_t out_cols = ov.shape[1];
    const int placed = nargs >= 4 && args[3] != Py_None;
    PyObject *error_type = PyExc_ValueError;
    const char *error = NULL;
    if (bv.shape[0] != m) {
        error = "basis: expected one row per weight (weights (B, M), basis (M, C))";
    } else if (ov.shape[0] != frames || (!placed && out_cols != cols)) {
        error = "out: expected shape (B, C) for weights (B, M) and basis (M, C)";
    } else if (overlap(&ov, &wv) || overlap(&ov, &bv)) {
        error = "out must not overlap weights or basis";
    }
    Py_ssize_t nruns = 1;
    const int64_t whole[3] = {0, 0, cols};
    const int64_t *runs = whole;
    if (error == NULL && placed) {
        nruns = get_runs(args[3], &rv, cols, out_cols, "basis");
        if (nruns < 0) {
            PyBuffer_Release(&wv);
            PyBuffer_Release(&bv);
            PyBuffer_Release(&ov);
            return NULL;
        }
        runs = rv.buf;
    }
    Py_ssize_t *index = NULL;
    float *coef = NULL, *scratch = NULL;
    unsigned char *touched = NULL;
    /* used rows (M), starts (B ceil(M / GROUP) + 1), rows (B M); coefficients (B M);
     * touched (B). */
    const Py_ssize_t most = (m + GROUP - 1) / GROUP * frames + 1;
    if (error == NULL) {
        index = PyMem_Malloc(sizeof(Py_ssize_t) * (size_t)(m + most + frames * m));
        coef = PyMem_Malloc(sizeof(float) * (size_t)(frames * m + 1));
        touched = PyMem_Malloc((size_t)frames + 1);
        /* A span's tile of every frame (blend_span), when some run is not a span alone. */
        const Py_ssize_t width = tile < cols ? tile : cols;
        if (nruns > 1) scratch = PyMem_Malloc(sizeof(float) * (size_t)(frames * width + 1));
        if (index == NULL || coef == NULL || touched == NULL || (nruns > 1 && scratch == NULL)) {
            error_type = PyExc_MemoryError;
            error = "blend_rows: out of memory";
        }
    }
    if (error == NULL) {
        Py_BEGIN_ALLOW_THREADS
        const float *weights = wv.buf;
        Py_ssize_t *used = index, *start = index + m, *row = start + most;
        Py_ssize_t nused = 0, terms = 0, groups = 0;
        for (Py_ssize_t r = 0; r < m; r++) {
            for (Py_ssize_t b = 0; b < frames; b++) {
                if (weights[b * m + r] != 0.0f) { /* NaN is not 0: it reaches the output */
                    used[nused++] = r;
                    break;
                }
            }
        }
        for (Py_ssize_t u = 0; u < nused; u += GROUP, groups++) {
            const Py_ssize_t end = nused - u < GROUP ? nused : u + GROUP;
            for (Py_ssize_t b = 0; b < frames; b++) {
                start[groups * frames + b] = terms;
                for (Py_ssize_t k = u; k < end; k++) {
                    const float w = weights[b * m + used[k]];
                    if (w != 0.0f) {
                        row[terms] = used[k];
                        coef[terms++] = w;
                    }
                }
            }
        }
        start[groups * frames] = terms;
        const Plan plan = {bv.buf, ov.buf, frames, cols, out_cols, groups,
                           start,  row,    coef,   touched};
        const tile_fn run = generic ? tile_generic : blend_tile;
        for (Py_ssize_t r = 0; r < nruns;) {
            /* A span: the runs from r on whose basis columns follow one another. */
            const Py_ssize_t c0 = runs[3 * r];
            Py_ssize_t last = r, end = c0 + runs[3 * r + 2];
            while (last + 1 < nruns && runs[3 * (last + 1)] == end)
                end += runs[3 * ++last + 2];
            if (last == r) {
                const Py_ssize_t d0 = runs[3 * r + 1];
                for (Py_ssize_t j = c0; j < end; j += tile)
                    run(&plan, j, d0 + j - c0, end - j < tile ? end - j : tile);
            } else {
                blend_span(&plan, run, scratch, tile, runs + 3 * r, last - r + 1, c0, end);
            }
            r = last + 1;
        }
        Py_END_ALLOW_THREADS
    }
    PyMem_Free(scratch);
    PyMem_Free(touched);
    PyMem_Free(index);
    PyMem_Free(coef);
    if (placed && runs != whole) PyBuffer_Release(&rv);
    PyBuffer_Release(&wv);
    PyBuffer_Release(&bv);
    PyBuffer_Release(&ov);
    if (error != NULL) {
        PyErr_SetString(error_type, error);
        return NULL;
    }
    Py_RETURN_NONE;
}

/* place_columns(src, out, runs): each run's columns of src (B, C) copied to its columns of out
 * (B, W); out's other columns are left as they are. Where a product other than blend_rows
 * (BLAS's, for one frame of dense weights) lands in a wider output: one copy per run and
 * frame, where numpy's scatter of ICT's 62k moving columns indexes each one. */
PyObject *facecast_place_columns(PyObject *module, PyObject *const *args, Py_ssize_t nargs) {
    (void)module;
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "place_columns(src, out, runs) takes 3 arguments");
        return NULL;
    }
    Py_buffer sv, ov, rv;
    if (get_matrix(args[0], &sv, 0, "src") < 0) return NULL;
    if (get_matrix(args[1], &ov, 1, "out") < 0) {
        PyBuffer_Release(&sv);
        return NULL;
    }
    const char *error = NULL;
    if (ov.shape[0] != sv.shape[0]) {
        error = "out: expected as many rows as src";
    } else if (overlap(&ov, &sv)) {
        error = "out must not overlap src";
    }
    Py_ssize_t nruns = 0;
    if (error == NULL) {
        nruns = get_runs(args[2], &rv, sv.shape[1], ov.shape[1], "src");
        if (nruns < 0) {
            PyBuffer_Release(&sv);
            PyBuffer_Release(&ov);
            return NULL;
        }
        const int64_t *runs = rv.buf;
        const float *src = sv.buf;
        float *out = ov.buf;
        const Py_ssize_t frames = sv.shape[0], cols = sv.shape[1], width = ov.shape[1];
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t b = 0; b < frames; b++)
            for (Py_ssize_t r = 0; r < nruns; r++)
                memcpy(out + b * width + runs[3 * r + 1], src + b * cols + runs[3 * r],
                       sizeof(float) * (size_t)runs[3 * r + 2]);
        Py_END_ALLOW_THREADS
        PyBuffer_Release(&rv);
    }
    PyBuffer_Release(&sv);
    PyBuffer_Release(&ov);
    if (error != NULL) {
        PyErr_SetString(PyExc_ValueError, error);
        return NULL;
    }
    Py_RETURN_NONE;
}
