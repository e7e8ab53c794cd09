/*
 * Compiled helpers of the 1 kHz path (pose_node, fk_node, compensation_node). Each does what a
 * Python function of mmd_ros does, and a test checks the two against each other:
 *
 *   solve_stream        ForwardKinematics.solve, sample after sample (core/kinematics.py)
 *   cdf_eval            CdfBank.__call__, the piecewise-linear CDFs of Eq. (10) (calibration.py)
 *   decode_continuing   FrameStream.feed for a transfer that continues the stream
 *                       (hardware/stream.py)
 *
 * On a transfer of 8 samples numpy and scalar Python spend their time in call overhead, not
 * arithmetic; here the same work takes a few microseconds. Buffers are filled in place
 * (C order, checked for format and size); no numpy C API is needed.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

/* ---------------------------------------------------------------------------------------------
 * Streaming forward kinematics. pose_node solves each transfer's samples one after another,
 * warm-started from the previous solutions; a transfer of 8 noisy samples took 340 us in Python
 * and 11-15 us through solve_stream (measured). The algorithm is ForwardKinematics.solve's, step
 * for step:
 *
 *   start: 2 u - v from the last two solutions u, v; else the last solution; else the home
 *          pose plus one step with the home Jacobian inverse;
 *   loop:  rows, res = Jacobian and d - IK(p); residual = max |res|; solve rows s = res
 *          (LU with partial pivoting; an exactly zero pivot ends the loop, not converged);
 *          damp s when its largest angle exceeds max_step; p += s; converged when the
 *          translation step < step_m and the largest angle step < step_rad.
 */
typedef struct {
    double ab[6][6];          /* per bar: a (upper, {U}) x y z, then b (lower, {L}) x y z */
    double home[6];
    double home_lengths[6];
    double home_jinv[36];     /* row major */
    double step_m, step_rad, max_step;
    long max_iter;
} Problem;

/* Jacobian rows (dd/dp, row major 6x6) and residual d - IK(p), as ForwardKinematics._evaluate. */
static void evaluate(const Problem *pb, const double p[6], const double d[6], double rows[36],
                     double res[6])
{
    const double x = p[0], y = p[1], z = p[2];
    const double cf = cos(p[3]), sf = sin(p[3]);
    const double ct = cos(p[4]), st = sin(p[4]);
    const double cp = cos(p[5]), sp = sin(p[5]);
    const double r00 = cp * ct, r01 = -sp * cf + cp * st * sf, r02 = sp * sf + cp * st * cf;
    const double r10 = sp * ct, r11 = cp * cf + sp * st * sf, r12 = -cp * sf + sp * st * cf;
    const double r20 = -st, r21 = ct * sf, r22 = ct * cf;
    const double w0x = cp * ct, w0y = sp * ct;
    for (int i = 0; i < 6; i++) {
        const double *a = pb->ab[i], *b = pb->ab[i] + 3;
        const double rax = r00 * a[0] + r01 * a[1] + r02 * a[2];
        const double ray = r10 * a[0] + r11 * a[1] + r12 * a[2];
        const double raz = r20 * a[0] + r21 * a[1] + r22 * a[2];
        const double lx = rax + x - b[0], ly = ray + y - b[1], lz = raz + z - b[2];
        const double length = sqrt(lx * lx + ly * ly + lz * lz);
        const double nx = lx / length, ny = ly / length, nz = lz / length;
        const double mx = ray * nz - raz * ny, my = raz * nx - rax * nz, mz = rax * ny - ray * nx;
        double *r = rows + 6 * i;
        r[0] = nx;
        r[1] = ny;
        r[2] = nz;
        r[3] = w0x * mx + w0y * my - st * mz;
        r[4] = cp * my - sp * mx;
        r[5] = mz;
        res[i] = d[i] - length;
    }
}

/* Solve A x = b (6x6, row major) by LU with partial pivoting; A and b are overwritten.
 * Returns 0, or the 1-based index of an exactly zero pivot (LAPACK dgesv's info). */
static int solve6(double A[36], double b[6], double x[6])
{
    for (int k = 0; k < 6; k++) {
        int piv = k;
        double big = fabs(A[6 * k + k]);
        for (int i = k + 1; i < 6; i++) {
            if (fabs(A[6 * i + k]) > big) {
                big = fabs(A[6 * i + k]);
                piv = i;
            }
        }
        if (A[6 * piv + k] == 0.0)
            return k + 1;
        if (piv != k) {
            for (int j = 0; j < 6; j++) {
                double t = A[6 * k + j];
                A[6 * k + j] = A[6 * piv + j];
                A[6 * piv + j] = t;
            }
            double t = b[k];
            b[k] = b[piv];
            b[piv] = t;
        }
        for (int i = k + 1; i < 6; i++) {
            double f = A[6 * i + k] / A[6 * k + k];
            A[6 * i + k] = f;
            for (int j = k + 1; j < 6; j++)
                A[6 * i + j] -= f * A[6 * k + j];
            b[i] -= f * b[k];
        }
    }
    for (int i = 5; i >= 0; i--) {
        double s = b[i];
        for (int j = i + 1; j < 6; j++)
            s -= A[6 * i + j] * x[j];
        x[i] = s / A[6 * i + i];
    }
    return 0;
}

static int all_finite(const double *v, int n)
{
    for (int i = 0; i < n; i++)
        if (!isfinite(v[i]))
            return 0;
    return 1;
}

/* One sample. history: up to two previous solutions (oldest first), updated. */
static void solve_one(const Problem *pb, const double d[6], double history[12], long *n_history,
                      double pose[6], unsigned char *converged, long long *iterations,
                      double *residual, double jac[36])
{
    double p[6], rows[36], res[6], A[36], s[6];
    if (*n_history == 2) {
        for (int j = 0; j < 6; j++)
            p[j] = 2.0 * history[6 + j] - history[j];
    } else if (*n_history == 1) {
        memcpy(p, history, sizeof p);
    } else {
        for (int j = 0; j < 6; j++) {
            double acc = 0.0;
            for (int k = 0; k < 6; k++)
                acc += (d[k] - pb->home_lengths[k]) * pb->home_jinv[6 * j + k];
            p[j] = pb->home[j] + acc;
        }
    }
    int ok = 0, evaluated = 0;
    long it = 0;
    double resid = INFINITY;
    for (it = 1; it <= pb->max_iter; it++) {
        evaluate(pb, p, d, rows, res);
        evaluated = 1;
        resid = 0.0;
        for (int i = 0; i < 6; i++)
            resid = fabs(res[i]) > resid ? fabs(res[i]) : resid;
        memcpy(A, rows, sizeof A);
        if (solve6(A, res, s) != 0)
            break;
        double rot = fmax(fabs(s[3]), fmax(fabs(s[4]), fabs(s[5])));
        if (rot > pb->max_step) { /* damp wild steps far from the solution */
            double f = pb->max_step / rot;
            for (int j = 0; j < 6; j++)
                s[j] *= f;
        }
        for (int j = 0; j < 6; j++)
            p[j] += s[j];
        double trans = fmax(fabs(s[0]), fmax(fabs(s[1]), fabs(s[2])));
        if (trans < pb->step_m && rot < pb->step_rad) {
            ok = all_finite(p, 6);
            break;
        }
    }
    if (it > pb->max_iter)
        it = pb->max_iter;
    if (ok) {
        if (*n_history == 2) {
            memcpy(history, history + 6, 6 * sizeof(double));
            memcpy(history + 6, p, 6 * sizeof(double));
        } else {
            memcpy(history + 6 * *n_history, p, 6 * sizeof(double));
            *n_history += 1;
        }
    } else {
        *n_history = 0;
    }
    memcpy(pose, p, sizeof p);
    *converged = (unsigned char)ok;
    *iterations = it;
    *residual = resid;
    if (evaluated)
        memcpy(jac, rows, sizeof rows);
    else
        for (int k = 0; k < 36; k++)
            jac[k] = NAN;
}

static int format_is(const Py_buffer *view, const char *fmt)
{
    const char *f = view->format ? view->format : "B";
    if (*f == '<' || *f == '=' || *f == '@')
        f++;
    return strcmp(f, fmt) == 0;
}

/* A C-contiguous buffer of `count` items of `itemsize` bytes and format `fmt` (count < 0: any
 * number of items). */
static int get_buffer(PyObject *obj, Py_buffer *view, int writable, Py_ssize_t count,
                      Py_ssize_t itemsize, const char *fmt, const char *name)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) < 0)
        return -1;
    /* numpy spells int64 'l' on LP64 platforms */
    int same = format_is(view, fmt) || (strcmp(fmt, "q") == 0 && sizeof(long) == 8
                                          && format_is(view, "l"));
    if (view->itemsize != itemsize || !same || (count >= 0 && view->len != count * itemsize)) {
        PyErr_Format(PyExc_ValueError, "%s: need %zd C-contiguous items of format '%s', "
                     "got %zd of '%s'", name, count, fmt, view->len / view->itemsize,
                     view->format ? view->format : "B");
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

PyDoc_STRVAR(solve_stream_doc,
"solve_stream(constants, home, home_lengths, home_jinv, lengths, history, n_history,\n"
"             poses, converged, iterations, residual, jacobians) -> n_history\n\n"
"Forward kinematics of N consecutive samples, as ForwardKinematics.solve called on each.\n"
"constants: (step_m, step_rad, max_step_rad, max_iter); ab (6, 6) float64 joints [a | b];\n"
"home (6,), home_lengths (6,), home_jinv (6, 6); lengths (N, 6) [m]; history (2, 6) and\n"
"n_history: the warm start, updated in place. Rows with a non-finite length are not solved\n"
"(NaN, not converged, 0 iterations). Outputs: poses (N, 6) float64, converged (N,) bool,\n"
"iterations (N,) int64, residual (N,) float64, jacobians (N, 6, 6) float64.");

static PyObject *solve_stream(PyObject *self, PyObject *args)
{
    (void)self;
    double step_m, step_rad, max_step;
    long max_iter, n_history;
    PyObject *o_ab, *o_home, *o_hl, *o_hj, *o_len, *o_hist, *o_pose, *o_conv, *o_iter, *o_res,
        *o_jac;
    if (!PyArg_ParseTuple(args, "(dddl)OOOOOOlOOOOO", &step_m, &step_rad, &max_step, &max_iter,
                          &o_ab, &o_home, &o_hl, &o_hj, &o_len, &o_hist, &n_history, &o_pose,
                          &o_conv, &o_iter, &o_res, &o_jac))
        return NULL;
    if (max_iter < 1 || n_history < 0 || n_history > 2) {
        PyErr_SetString(PyExc_ValueError, "max_iter must be >= 1 and n_history 0, 1 or 2");
        return NULL;
    }
    Py_buffer b[11];
    int got = 0;
    PyObject *result = NULL;
    Problem pb;
    pb.step_m = step_m;
    pb.step_rad = step_rad;
    pb.max_step = max_step;
    pb.max_iter = max_iter;
    if (get_buffer(o_len, &b[got], 0, -1, 8, "d", "lengths") < 0)
        return NULL;
    got++;
    const Py_ssize_t n = b[0].len / (6 * 8);
    if (b[0].len != n * 6 * 8) {
        PyErr_SetString(PyExc_ValueError, "lengths: need shape (N, 6)");
        goto done;
    }
    struct { PyObject *o; int w; Py_ssize_t count, size; const char *fmt, *name; } spec[] = {
        {o_ab, 0, 36, 8, "d", "ab"},
        {o_home, 0, 6, 8, "d", "home"},
        {o_hl, 0, 6, 8, "d", "home_lengths"},
        {o_hj, 0, 36, 8, "d", "home_jinv"},
        {o_hist, 1, 12, 8, "d", "history"},
        {o_pose, 1, 6 * n, 8, "d", "poses"},
        {o_conv, 1, n, 1, "?", "converged"},
        {o_iter, 1, n, 8, "q", "iterations"},
        {o_res, 1, n, 8, "d", "residual"},
        {o_jac, 1, 36 * n, 8, "d", "jacobians"},
    };
    for (size_t k = 0; k < sizeof spec / sizeof spec[0]; k++) {
        if (get_buffer(spec[k].o, &b[got], spec[k].w, spec[k].count, spec[k].size,
                       spec[k].fmt, spec[k].name) < 0)
            goto done;
        got++;
    }
    memcpy(pb.ab, b[1].buf, sizeof pb.ab);
    memcpy(pb.home, b[2].buf, sizeof pb.home);
    memcpy(pb.home_lengths, b[3].buf, sizeof pb.home_lengths);
    memcpy(pb.home_jinv, b[4].buf, sizeof pb.home_jinv);
    {
        const double *lengths = (const double *)b[0].buf;
        double *history = (double *)b[5].buf;
        double *poses = (double *)b[6].buf;
        unsigned char *conv = (unsigned char *)b[7].buf;
        long long *iters = (long long *)b[8].buf;
        double *resid = (double *)b[9].buf;
        double *jac = (double *)b[10].buf;
        for (Py_ssize_t i = 0; i < n; i++) {
            const double *d = lengths + 6 * i;
            if (!all_finite(d, 6)) { /* not solved */
                for (int j = 0; j < 6; j++)
                    poses[6 * i + j] = NAN;
                for (int j = 0; j < 36; j++)
                    jac[36 * i + j] = NAN;
                conv[i] = 0;
                iters[i] = 0;
                resid[i] = NAN;
                continue;
            }
            solve_one(&pb, d, history, &n_history, poses + 6 * i, conv + i, iters + i,
                      resid + i, jac + 36 * i);
        }
    }
    result = PyLong_FromLong(n_history);
done:
    for (int k = 0; k < got; k++)
        PyBuffer_Release(&b[k]);
    return result;
}

PyDoc_STRVAR(cdf_eval_doc,
"cdf_eval(counts, knots, distances, slopes, lengths, out_of_range) -> None\n\n"
"Piecewise-linear CDFs of k bars (Eq. 10), as CdfBank.__call__: column j of counts (N, k)\n"
"through knots[j] (k, n) -> distances[j] (k, n), extrapolated with the end segments;\n"
"slopes (k, n - 1). Fills lengths (N, k) float64 and out_of_range (N, k) bool.");

static PyObject *cdf_eval(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_c, *o_q, *o_d, *o_s, *o_len, *o_out;
    if (!PyArg_ParseTuple(args, "OOOOOO", &o_c, &o_q, &o_d, &o_s, &o_len, &o_out))
        return NULL;
    Py_buffer b[6];
    int got = 0;
    PyObject *result = NULL;
    if (get_buffer(o_q, &b[got], 0, -1, 8, "d", "knots") < 0)
        return NULL;
    got++;
    if (get_buffer(o_c, &b[got], 0, -1, 8, "d", "counts") < 0)
        goto done;
    got++;
    const Py_ssize_t kn = b[0].len / 8;                /* k * n */
    const Py_ssize_t nk = b[1].len / 8;                /* N * k */
    const Py_ssize_t k = b[0].ndim == 2 ? b[0].shape[0] : 0;
    if (k < 1 || kn % k != 0 || kn / k < 2 || nk % k != 0) {
        PyErr_SetString(PyExc_ValueError, "knots: need shape (k, n >= 2); counts: (N, k)");
        goto done;
    }
    const Py_ssize_t n = kn / k, rows = nk / k;
    struct { PyObject *o; int w; Py_ssize_t count, size; const char *fmt, *name; } spec[] = {
        {o_d, 0, k * n, 8, "d", "distances"},
        {o_s, 0, k * (n - 1), 8, "d", "slopes"},
        {o_len, 1, rows * k, 8, "d", "lengths"},
        {o_out, 1, rows * k, 1, "?", "out_of_range"},
    };
    for (size_t j = 0; j < sizeof spec / sizeof spec[0]; j++) {
        if (get_buffer(spec[j].o, &b[got], spec[j].w, spec[j].count, spec[j].size,
                       spec[j].fmt, spec[j].name) < 0)
            goto done;
        got++;
    }
    {
        const double *q = (const double *)b[0].buf, *c = (const double *)b[1].buf;
        const double *d = (const double *)b[2].buf, *sl = (const double *)b[3].buf;
        double *len = (double *)b[4].buf;
        unsigned char *out = (unsigned char *)b[5].buf;
        for (Py_ssize_t r = 0; r < rows; r++) {
            for (Py_ssize_t j = 0; j < k; j++) {
                const double v = c[r * k + j];
                const double *qj = q + j * n;
                Py_ssize_t idx = -1;          /* knots at or below v, minus one */
                for (Py_ssize_t m = 0; m < n; m++)
                    idx += v >= qj[m];
                if (idx < 0)
                    idx = 0;
                if (idx > n - 2)
                    idx = n - 2;
                len[r * k + j] = d[j * n + idx] + sl[j * (n - 1) + idx] * (v - qj[idx]);
                out[r * k + j] = (unsigned char)(v < qj[0] || v > qj[n - 1]);
            }
        }
    }
    Py_INCREF(Py_None);
    result = Py_None;
done:
    for (int j = 0; j < got; j++)
        PyBuffer_Release(&b[j]);
    return result;
}

/* ---------------------------------------------------------------------------------------------
 * Sample frames of the encoder terminal (msg_docs/usb_protocol.md): the common case of
 * FrameStream.feed, a transfer of valid frames that continue the stream. Anything else (a bad
 * frame, trailing bytes, a sequence step <= 0, a counter reset starting, the first transfer)
 * returns None and FrameStream's numpy path handles the transfer, as it does every transfer
 * without the compiled helpers.
 */
#define FRAME_SIZE 64
#define FRAME_CRC_SPAN 60
#define N_CHANNELS 8
#define MAGIC 0x444D
#define PROTOCOL_VERSION 1
#define TYPE_SAMPLE 0x53
#define FLAG_COUNTER_RESET 0x0001
#define FLAG_FIFO_OVERFLOW 0x0002

static uint32_t crc_table[256];

static void crc_init(void)
{
    for (uint32_t i = 0; i < 256; i++) {
        uint32_t c = i;
        for (int k = 0; k < 8; k++)
            c = c & 1 ? 0xEDB88320u ^ (c >> 1) : c >> 1;
        crc_table[i] = c;
    }
}

/* CRC-32 of IEEE 802.3 (zlib.crc32). */
static uint32_t crc32_of(const unsigned char *p, size_t n)
{
    uint32_t c = 0xFFFFFFFFu;
    for (size_t i = 0; i < n; i++)
        c = crc_table[(c ^ p[i]) & 0xFF] ^ (c >> 8);
    return c ^ 0xFFFFFFFFu;
}

static uint16_t le16(const unsigned char *p) { return (uint16_t)(p[0] | p[1] << 8); }
static uint32_t le32(const unsigned char *p)
{
    return (uint32_t)p[0] | (uint32_t)p[1] << 8 | (uint32_t)p[2] << 16 | (uint32_t)p[3] << 24;
}
static uint64_t le64(const unsigned char *p)
{
    return (uint64_t)le32(p) | (uint64_t)le32(p + 4) << 32;
}

PyDoc_STRVAR(decode_continuing_doc,
"decode_continuing(data, last_seq, reset_seen, last_raw, last_counts,\n"
"                  seq, time_ns, counts, channel_status, flags, missing, raw_last)\n"
"    -> None | (last_seq, reset_seen, gaps, missing_samples, overflows, signal_errors)\n\n"
"Decode a transfer of N = len(data) / 64 sample frames that continue a stream whose last\n"
"accepted frame had the unwrapped sequence number last_seq, raw counters last_raw (8,) int64\n"
"and unwrapped counts last_counts (8,) int64, as FrameStream's fast path does. Fills seq (N,)\n"
"uint32, time_ns (N,) int64, counts (N, 8) int64 (unwrapped), channel_status and flags (N,)\n"
"uint16, missing (N,) int64 (samples missing before each frame) and raw_last (8,) int64 (the\n"
"last frame's raw counters). Returns None, having changed nothing that matters, when the\n"
"transfer needs the general path.");

static PyObject *decode_continuing(PyObject *self, PyObject *args)
{
    (void)self;
    Py_buffer data;
    long long last_seq;
    int reset_seen;
    PyObject *o[9];
    if (!PyArg_ParseTuple(args, "y*LpOOOOOOOOO", &data, &last_seq, &reset_seen, &o[0], &o[1],
                          &o[2], &o[3], &o[4], &o[5], &o[6], &o[7], &o[8]))
        return NULL;
    Py_buffer b[9];
    int got = 0;
    PyObject *result = NULL;
    const Py_ssize_t n = data.len / FRAME_SIZE;
    if (n == 0 || data.len != n * FRAME_SIZE) {
        result = Py_None;
        Py_INCREF(result);
        goto done;
    }
    struct { int w; Py_ssize_t count, size; const char *fmt, *name; } spec[] = {
        {0, N_CHANNELS, 8, "q", "last_raw"},
        {0, N_CHANNELS, 8, "q", "last_counts"},
        {1, n, 4, "I", "seq"},
        {1, n, 8, "q", "time_ns"},
        {1, n * N_CHANNELS, 8, "q", "counts"},
        {1, n, 2, "H", "channel_status"},
        {1, n, 2, "H", "flags"},
        {1, n, 8, "q", "missing"},
        {1, N_CHANNELS, 8, "q", "raw_last"},
    };
    for (int k = 0; k < 9; k++) {
        if (get_buffer(o[k], &b[got], spec[k].w, spec[k].count, spec[k].size, spec[k].fmt,
                       spec[k].name) < 0)
            goto done;
        got++;
    }
    {
        const unsigned char *p = (const unsigned char *)data.buf;
        const int64_t *last_raw = (const int64_t *)b[0].buf;
        const int64_t *last_counts = (const int64_t *)b[1].buf;
        uint32_t *seq = (uint32_t *)b[2].buf;
        int64_t *tns = (int64_t *)b[3].buf, *counts = (int64_t *)b[4].buf;
        uint16_t *status = (uint16_t *)b[5].buf, *flags = (uint16_t *)b[6].buf;
        int64_t *missing = (int64_t *)b[7].buf, *raw_last = (int64_t *)b[8].buf;
        /* check the whole transfer before anything is written that the caller keeps */
        uint32_t prev = (uint32_t)last_seq;
        int any_flagged = 0;
        for (Py_ssize_t i = 0; i < n; i++) {
            const unsigned char *f = p + i * FRAME_SIZE;
            if (le16(f) != MAGIC || f[2] != PROTOCOL_VERSION || f[3] != TYPE_SAMPLE
                    || crc32_of(f, FRAME_CRC_SPAN) != le32(f + 60))
                goto general;
            uint32_t s = le32(f + 4);
            int32_t step = (int32_t)(s - prev);     /* signed step in (-2^31, 2^31) */
            if (step <= 0)
                goto general;
            prev = s;
            any_flagged |= (le16(f + 50) & FLAG_COUNTER_RESET) != 0;
        }
        if (any_flagged && !reset_seen)
            goto general;
        long long gaps = 0, lost = 0, overflows = 0, signal_errors = 0;
        int64_t raw_prev[N_CHANNELS], acc[N_CHANNELS];
        for (int c = 0; c < N_CHANNELS; c++) {
            raw_prev[c] = last_raw[c];
            acc[c] = last_counts[c];
        }
        prev = (uint32_t)last_seq;
        for (Py_ssize_t i = 0; i < n; i++) {
            const unsigned char *f = p + i * FRAME_SIZE;
            const uint32_t s = le32(f + 4);
            const int64_t step = (int32_t)(s - prev);
            prev = s;
            seq[i] = s;
            tns[i] = (int64_t)le64(f + 8);
            missing[i] = step - 1;
            last_seq += step;
            gaps += step > 1;
            lost += step - 1;
            for (int c = 0; c < N_CHANNELS; c++) {
                const int64_t raw = (int32_t)le32(f + 16 + 4 * c);
                acc[c] += (int32_t)(uint32_t)(raw - raw_prev[c]);  /* counter wrap */
                raw_prev[c] = raw;
                counts[i * N_CHANNELS + c] = acc[c];
            }
            status[i] = le16(f + 48);
            flags[i] = le16(f + 50);
            overflows += (flags[i] & FLAG_FIFO_OVERFLOW) != 0;
            signal_errors += status[i] != 0;
        }
        for (int c = 0; c < N_CHANNELS; c++)
            raw_last[c] = raw_prev[c];
        reset_seen = (flags[n - 1] & FLAG_COUNTER_RESET) != 0;
        result = Py_BuildValue("LNLLLL", last_seq, PyBool_FromLong(reset_seen), gaps, lost,
                               overflows, signal_errors);
        goto done;
    }
general:
    result = Py_None;
    Py_INCREF(result);
done:
    for (int k = 0; k < got; k++)
        PyBuffer_Release(&b[k]);
    PyBuffer_Release(&data);
    return result;
}

static PyMethodDef methods[] = {
    {"solve_stream", solve_stream, METH_VARARGS, solve_stream_doc},
    {"cdf_eval", cdf_eval, METH_VARARGS, cdf_eval_doc},
    {"decode_continuing", decode_continuing, METH_VARARGS, decode_continuing_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_fast",
    "Compiled helpers of the 1 kHz path (see mmd_ros.core.compiled).", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__fast(void)
{
    crc_init();
    return PyModule_Create(&module);
}
