/*
 * Compiled helpers of mmd_ros. Each does what a Python function of mmd_ros does, and a test
 * checks the two against each other:
 *
 *   solve_stream        ForwardKinematics.solve, sample after sample (core/kinematics.py)
 *   solve_batch         ForwardKinematics._solve_chunk and solve_series, samples on their own
 *   pose_covariance     propagate_covariance, J^-1 S J^-T per sample (kinematics.py)
 *   cdf_eval            CdfBank.__call__, the piecewise-linear CDFs of Eq. (10) (calibration.py)
 *   play                the play operator: play_positions (terms.py) and
 *                       HysteresisTerm.directions (model.py)
 *   dahl_state          dahl_state, Dahl's friction state along it (terms.py)
 *   friction_travel     the uncertainty budget's friction state and travel (budget.py)
 *   match_rows          rows_match, the fixed bytes of messages read from a log (logs/cdr.py)
 *   decode_continuing   FrameStream.feed for a transfer that continues the stream
 *                       (hardware/stream.py)
 *   fill_rows           _RecordRow.fill, a log's message records from a template (logs/writer.py)
 *   crc32               zlib.crc32, for the chunks of a log being written (logs/mcap_records.py)
 *
 * On a transfer of 8 samples numpy and scalar Python spend their time in call overhead, not
 * arithmetic; here the same work takes a few microseconds. The batch functions release the GIL,
 * so that threads run them on every core. Buffers are filled in place (C order, checked for
 * format and size); no numpy C API is needed.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

/* ---------------------------------------------------------------------------------------------
 * Forward kinematics (core/kinematics.py, ForwardKinematics). One sample:
 *
 *   the lengths must be finite (else OUT_OF_SPAN) and within the bars' range (else BAR_RANGE);
 *   seeds, in turn until one is accepted: the warm start (stream: 2 u - v from the last two
 *          accepted poses, or the last one; batch: the caller's guess), then the home pose plus
 *          one step with the home Jacobian inverse, then the home pose;
 *   Newton from a seed: rows, res = Jacobian and d - IK(p); residual = max |res|; solve rows s =
 *          res (LU with partial pivoting; an exactly zero pivot ends the loop, not converged);
 *          damp s when its largest angle exceeds max_step; p += s; converged when the
 *          translation step < step_m and the largest angle step < step_rad;
 *   acceptance of a converged pose: every bar within the joints' tilt limits at both plates
 *          (else IMPLAUSIBLE), the Jacobian's condition number within max_cond (else
 *          ILL_CONDITIONED), and for the stream's warm start a pose change since the last
 *          accepted pose no faster than max_speed (else DISCONTINUOUS: a jump, re-seeded).
 *
 * A sample no seed solves is not a measurement: NaN pose, and the furthest stage any seed
 * reached as its status. The constants travel in one float64 array laid out as P_* below
 * (ForwardKinematics._packed builds it).
 */
enum {
    ST_OK = 0, ST_RESEEDED = 1, ST_OUT_OF_SPAN = 2, ST_BAR_RANGE = 3, ST_NOT_CONVERGED = 4,
    ST_IMPLAUSIBLE = 5, ST_ILL_CONDITIONED = 6, ST_DISCONTINUOUS = 7,
};
enum {
    P_AB = 0, P_HOME = 36, P_HOME_LENGTHS = 42, P_HOME_JINV = 48, P_STEP_M = 84,
    P_STEP_RAD = 85, P_MAX_STEP = 86, P_MAX_ITER = 87, P_D_LO = 88, P_D_HI = 89,
    P_COS_UPPER = 90, P_COS_LOWER = 91, P_MAX_COND = 92, P_RADIUS = 93, P_MAX_SPEED = 94,
    P_DT = 95, P_SIZE = 96,
};
#define STATE_SIZE 14      /* stream state: history (2, 6), n_history, elapsed [s] */

typedef struct {
    double ab[6][6];          /* per bar: a (upper, {U}) x y z, then b (lower, {L}) x y z */
    double home[6];
    double home_lengths[6];
    double home_jinv[36];     /* row major */
    double step_m, step_rad, max_step;
    long max_iter;
    double d_lo, d_hi;        /* accepted centre distances [m] */
    double cos_upper, cos_lower;  /* cosines of the largest accepted tilts */
    double max_cond;
    double inv_radius;        /* 1 / platform radius: the angle columns' scale */
    double radius;
    double max_speed;         /* [m/s], angles times the platform radius */
    double dt;                /* sample period when the caller gives none [s] */
} Problem;

static int problem_from(const double *v, Problem *pb)
{
    memcpy(pb->ab, v + P_AB, sizeof pb->ab);
    memcpy(pb->home, v + P_HOME, sizeof pb->home);
    memcpy(pb->home_lengths, v + P_HOME_LENGTHS, sizeof pb->home_lengths);
    memcpy(pb->home_jinv, v + P_HOME_JINV, sizeof pb->home_jinv);
    pb->step_m = v[P_STEP_M];
    pb->step_rad = v[P_STEP_RAD];
    pb->max_step = v[P_MAX_STEP];
    pb->max_iter = (long)v[P_MAX_ITER];
    pb->d_lo = v[P_D_LO];
    pb->d_hi = v[P_D_HI];
    pb->cos_upper = v[P_COS_UPPER];
    pb->cos_lower = v[P_COS_LOWER];
    pb->max_cond = v[P_MAX_COND];
    pb->radius = v[P_RADIUS];
    pb->inv_radius = 1.0 / v[P_RADIUS];
    pb->max_speed = v[P_MAX_SPEED];
    pb->dt = v[P_DT];
    if (pb->max_iter < 1 || !(pb->radius > 0.0)) {
        PyErr_SetString(PyExc_ValueError, "problem: max_iter must be >= 1 and radius > 0");
        return -1;
    }
    return 0;
}

/* Jacobian rows (dd/dp, row major 6x6), residual d - IK(p) and the upper plate's normal R e_z,
 * as ForwardKinematics._evaluate. */
static void evaluate(const Problem *pb, const double p[6], const double d[6], double rows[36],
                     double res[6], double normal[3])
{
    /* the operations and their grouping are _evaluate_soa's, so that both round alike */
    const double x = p[0], y = p[1], z = p[2];
    const double cf = cos(p[3]), sf = sin(p[3]);
    const double ct = cos(p[4]), st = sin(p[4]);
    const double cp = cos(p[5]), sp = sin(p[5]);
    const double stsf = st * sf, stcf = st * cf;
    const double r00 = cp * ct, r01 = cp * stsf - sp * cf, r02 = sp * sf + cp * stcf;
    const double r10 = sp * ct, r11 = cp * cf + sp * stsf, r12 = sp * stcf - cp * sf;
    const double r20 = -st, r21 = ct * sf, r22 = ct * cf;
    const double w0x = cp * ct, w0y = sp * ct;
    for (int i = 0; i < 6; i++) {
        const double *a = pb->ab[i], *b = pb->ab[i] + 3;
        const double rax = r00 * a[0] + r01 * a[1] + r02 * a[2];
        const double ray = r10 * a[0] + r11 * a[1] + r12 * a[2];
        const double raz = r20 * a[0] + r21 * a[1] + r22 * a[2];
        const double lx = rax + (x - b[0]), ly = ray + (y - b[1]), lz = raz + (z - b[2]);
        const double length = sqrt(lx * lx + ly * ly + lz * lz);
        const double inv = 1.0 / length;
        const double nx = lx * inv, ny = ly * inv, nz = lz * inv;
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
    normal[0] = r02;
    normal[1] = r12;
    normal[2] = r22;
}

/* LU factorisation with partial pivoting of a 6x6 row-major matrix, in place; ipiv[k] is the
 * row exchanged with row k. Returns 0, or the 1-based index of an exactly zero pivot (LAPACK
 * dgetrf's info). */
static int lu6(double A[36], int ipiv[6])
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
        ipiv[k] = piv;
        if (A[6 * piv + k] == 0.0)
            return k + 1;
        if (piv != k) {
            for (int j = 0; j < 6; j++) {
                double t = A[6 * k + j];
                A[6 * k + j] = A[6 * piv + j];
                A[6 * piv + j] = t;
            }
        }
        for (int i = k + 1; i < 6; i++) {
            double f = A[6 * i + k] / A[6 * k + k];
            A[6 * i + k] = f;
            for (int j = k + 1; j < 6; j++)
                A[6 * i + j] -= f * A[6 * k + j];
        }
    }
    return 0;
}

/* Solve A x = b with the factors of lu6; b is overwritten by x. */
static inline void lu_solve6(const double LU[36], const int ipiv[6], double b[6])
{
    double x[6];
    memcpy(x, b, sizeof x);
    for (int k = 0; k < 6; k++) {
        const int p = ipiv[k];
        const double t = x[k];
        x[k] = x[p];
        x[p] = t;
    }
    for (int k = 0; k < 6; k++)
        for (int i = k + 1; i < 6; i++)
            x[i] -= LU[6 * i + k] * x[k];
    for (int i = 5; i >= 0; i--) {
        double s = x[i];
        for (int j = i + 1; j < 6; j++)
            s -= LU[6 * i + j] * x[j];
        x[i] = s / LU[6 * i + i];
    }
    memcpy(b, x, sizeof x);
}

/* The inverse (row major) from the factors of lu6: lu_solve6 of the six unit vectors, all
 * columns at once (the same operations on each column, in the same order). */
static void lu_inverse6(const double LU[36], const int ipiv[6], double X[36])
{
    for (int i = 0; i < 36; i++)
        X[i] = i % 7 == 0 ? 1.0 : 0.0;
    for (int k = 0; k < 6; k++) {
        const int p = ipiv[k];
        for (int c = 0; c < 6; c++) {
            const double t = X[6 * k + c];
            X[6 * k + c] = X[6 * p + c];
            X[6 * p + c] = t;
        }
    }
    for (int k = 0; k < 6; k++)
        for (int i = k + 1; i < 6; i++) {
            const double f = LU[6 * i + k];
            for (int c = 0; c < 6; c++)
                X[6 * i + c] -= f * X[6 * k + c];
        }
    for (int i = 5; i >= 0; i--) {
        double s[6];
        for (int c = 0; c < 6; c++)
            s[c] = X[6 * i + c];
        for (int j = i + 1; j < 6; j++) {
            const double f = LU[6 * i + j];
            for (int c = 0; c < 6; c++)
                s[c] -= f * X[6 * j + c];
        }
        for (int c = 0; c < 6; c++)
            X[6 * i + c] = s[c] / LU[6 * i + i];
    }
}

static int all_finite(const double *v, int n)
{
    for (int i = 0; i < n; i++)
        if (!isfinite(v[i]))
            return 0;
    return 1;
}

/* Newton from p (updated). Leaves the Jacobian rows, their LU factors and the plate normal of
 * the last evaluation; adds the evaluations to *iters. Returns 1 when converged. */
static int newton(const Problem *pb, const double d[6], double p[6], double rows[36],
                  double LU[36], int ipiv[6], double normal[3], double *residual, long *iters)
{
    double res[6];
    for (long it = 1; it <= pb->max_iter; it++) {
        evaluate(pb, p, d, rows, res, normal);
        (*iters)++;
        double r = 0.0;
        for (int i = 0; i < 6; i++)
            r = fabs(res[i]) > r ? fabs(res[i]) : r;
        *residual = r;
        memcpy(LU, rows, 36 * sizeof(double));
        if (lu6(LU, ipiv) != 0)
            return 0;
        lu_solve6(LU, ipiv, res);               /* res now holds the step */
        double rot = fmax(fabs(res[3]), fmax(fabs(res[4]), fabs(res[5])));
        if (rot > pb->max_step) { /* damp wild steps far from the solution */
            double f = pb->max_step / rot;
            for (int j = 0; j < 6; j++)
                res[j] *= f;
        }
        for (int j = 0; j < 6; j++)
            p[j] += res[j];
        double trans = fmax(fabs(res[0]), fmax(fabs(res[1]), fabs(res[2])));
        if (trans < pb->step_m && rot < pb->step_rad)
            return all_finite(p, 6);
    }
    return 0;
}

/* Acceptance of a converged pose from its last evaluation: tilts, then the condition number
 * (1-norm, angle columns scaled by 1 / radius) with the inverse J^-1 (row major) it needs. */
static int check(const Problem *pb, const double rows[36], const double LU[36],
                 const int ipiv[6], const double normal[3], double *cond, double jinv[36])
{
    for (int i = 0; i < 6; i++) {
        const double *n = rows + 6 * i;
        const double cos_upper = n[0] * normal[0] + n[1] * normal[1] + n[2] * normal[2];
        if (!(n[2] >= pb->cos_lower) || !(cos_upper >= pb->cos_upper))
            return ST_IMPLAUSIBLE;
    }
    lu_inverse6(LU, ipiv, jinv);
    double norm_j = 0.0, norm_inv = 0.0;
    for (int k = 0; k < 6; k++) {
        double sj = 0.0, si = 0.0;
        for (int i = 0; i < 6; i++) {
            sj += fabs(k < 3 ? rows[6 * i + k] : rows[6 * i + k] * pb->inv_radius);
            si += fabs(i < 3 ? jinv[6 * i + k] : jinv[6 * i + k] / pb->inv_radius);
        }
        norm_j = sj > norm_j ? sj : norm_j;
        norm_inv = si > norm_inv ? si : norm_inv;
    }
    *cond = norm_j * norm_inv;
    if (!(*cond <= pb->max_cond))
        return ST_ILL_CONDITIONED;
    return ST_OK;
}

/* Whether p is within max_speed * elapsed of prev (angles times the platform radius). */
static int continuous(const Problem *pb, const double p[6], const double prev[6], double elapsed)
{
    double m = 0.0;
    for (int j = 0; j < 6; j++) {
        double v = fabs(p[j] - prev[j]) * (j < 3 ? 1.0 : pb->radius);
        m = v > m ? v : m;
    }
    return m <= pb->max_speed * elapsed;
}

typedef struct {
    double pose[6];
    int status;
    long iterations;
    double residual;
    double condition;
    double rows[36];
    double jinv[36];
} Result;

static void set_nan(double *v, int n)
{
    for (int i = 0; i < n; i++)
        v[i] = NAN;
}

/* One sample from its seeds. first: the warm start or guess (NULL: none); prev (with first):
 * the last accepted pose it must be continuous with (NULL: no such test). */
static void solve_seeds(const Problem *pb, const double d[6], const double *first,
                        const double *prev, double elapsed, Result *out)
{
    double rows[36], LU[36], normal[3];
    int ipiv[6];
    out->iterations = 0;
    out->residual = NAN;
    out->condition = NAN;
    set_nan(out->pose, 6);
    set_nan(out->rows, 36);
    set_nan(out->jinv, 36);
    if (!all_finite(d, 6)) {
        out->status = ST_OUT_OF_SPAN;
        return;
    }
    for (int i = 0; i < 6; i++) {
        if (!(d[i] >= pb->d_lo && d[i] <= pb->d_hi)) {
            out->status = ST_BAR_RANGE;
            return;
        }
    }
    int worst = ST_NOT_CONVERGED;
    for (int k = first ? 0 : 1; k < 3; k++) {
        double p[6];
        if (k == 0) {
            memcpy(p, first, sizeof p);
        } else if (k == 1) {
            for (int j = 0; j < 6; j++) {
                double acc = 0.0;
                for (int m = 0; m < 6; m++)
                    acc += (d[m] - pb->home_lengths[m]) * pb->home_jinv[6 * j + m];
                p[j] = pb->home[j] + acc;
            }
        } else {
            memcpy(p, pb->home, sizeof p);
        }
        int status = ST_NOT_CONVERGED;
        if (newton(pb, d, p, rows, LU, ipiv, normal, &out->residual, &out->iterations)) {
            status = check(pb, rows, LU, ipiv, normal, &out->condition, out->jinv);
            if (status == ST_OK && k == 0 && prev && !continuous(pb, p, prev, elapsed))
                status = ST_DISCONTINUOUS;
        }
        if (status == ST_OK) {
            out->status = k == (first ? 0 : 1) ? ST_OK : ST_RESEEDED;
            memcpy(out->pose, p, sizeof p);
            memcpy(out->rows, rows, sizeof rows);
            return;
        }
        worst = status > worst ? status : worst;
    }
    out->status = worst;
    set_nan(out->jinv, 36);
}

/* Sample i of a batch's outputs (jinv may be NULL). */
static void store(const Result *r, Py_ssize_t i, double *poses, signed char *status,
                  unsigned char *conv, long long *iters, double *resid, double *cond,
                  double *jinv)
{
    memcpy(poses + 6 * i, r->pose, sizeof r->pose);
    status[i] = (signed char)r->status;
    conv[i] = r->status <= ST_RESEEDED;
    iters[i] = r->iterations;
    resid[i] = r->residual;
    cond[i] = r->condition;
    if (jinv)
        memcpy(jinv + 36 * i, r->jinv, sizeof r->jinv);
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

/* Buffers of one call: acquired in turn, released together. An optional one (None) stays
 * NULL. */
typedef struct {
    Py_buffer views[16];
    int got;
} Buffers;

typedef struct {
    PyObject *obj;
    int writable;
    Py_ssize_t count, itemsize;
    const char *fmt, *name;
    int optional;
} Spec;

static int acquire(Buffers *bufs, const Spec *spec, int n, void **ptrs)
{
    for (int k = 0; k < n; k++) {
        if (spec[k].optional && spec[k].obj == Py_None) {
            ptrs[k] = NULL;
            continue;
        }
        if (get_buffer(spec[k].obj, &bufs->views[bufs->got], spec[k].writable, spec[k].count,
                       spec[k].itemsize, spec[k].fmt, spec[k].name) < 0)
            return -1;
        ptrs[k] = bufs->views[bufs->got].buf;
        bufs->got++;
    }
    return 0;
}

static void release(Buffers *bufs)
{
    for (int k = 0; k < bufs->got; k++)
        PyBuffer_Release(&bufs->views[k]);
    bufs->got = 0;
}

/* Rows of an (N, 6) float64 buffer, or -1 (error set). */
static Py_ssize_t rows_of(PyObject *obj, const char *name)
{
    Py_buffer view;
    if (get_buffer(obj, &view, 0, -1, 8, "d", name) < 0)
        return -1;
    Py_ssize_t n = view.len / (6 * 8);
    int ok = view.len == n * 6 * 8;
    PyBuffer_Release(&view);
    if (!ok) {
        PyErr_Format(PyExc_ValueError, "%s: need shape (N, 6)", name);
        return -1;
    }
    return n;
}

PyDoc_STRVAR(solve_stream_doc,
"solve_stream(problem, lengths, dt, state, poses, status, converged, iterations, residual,\n"
"             condition, jacobians) -> None\n\n"
"Forward kinematics of N consecutive samples, as ForwardKinematics.solve called on each.\n"
"problem: (96,) float64 packed by ForwardKinematics._packed; lengths (N, 6) [m]; dt (N,)\n"
"float64 time since the previous sample [s], or None (the problem's sample period); state\n"
"(14,) float64: the warm start (history (2, 6), n_history, seconds since the last accepted\n"
"sample), updated in place. Outputs: poses (N, 6) float64 (NaN unless accepted), status (N,)\n"
"int8 (FkStatus), converged (N,) bool (accepted), iterations (N,) int64, residual (N,)\n"
"float64, condition (N,) float64, jacobians (N, 6, 6) float64.");

static PyObject *solve_stream(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o[11];
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6],
                          &o[7], &o[8], &o[9], &o[10]))
        return NULL;
    const Py_ssize_t n = rows_of(o[1], "lengths");
    if (n < 0)
        return NULL;
    Spec spec[] = {
        {o[0], 0, P_SIZE, 8, "d", "problem", 0},
        {o[1], 0, 6 * n, 8, "d", "lengths", 0},
        {o[2], 0, n, 8, "d", "dt", 1},
        {o[3], 1, STATE_SIZE, 8, "d", "state", 0},
        {o[4], 1, 6 * n, 8, "d", "poses", 0},
        {o[5], 1, n, 1, "b", "status", 0},
        {o[6], 1, n, 1, "?", "converged", 0},
        {o[7], 1, n, 8, "q", "iterations", 0},
        {o[8], 1, n, 8, "d", "residual", 0},
        {o[9], 1, n, 8, "d", "condition", 0},
        {o[10], 1, 36 * n, 8, "d", "jacobians", 0},
    };
    Buffers bufs = {.got = 0};
    void *ptr[11];
    Problem pb;
    PyObject *result = NULL;
    if (acquire(&bufs, spec, 11, ptr) < 0 || problem_from((const double *)ptr[0], &pb) < 0)
        goto done;
    {
        const double *lengths = ptr[1], *dt = ptr[2];
        double *state = ptr[3], *poses = ptr[4], *resid = ptr[8], *cond = ptr[9], *jac = ptr[10];
        signed char *status = ptr[5];
        unsigned char *conv = ptr[6];
        long long *iters = ptr[7];
        double *history = state;
        long n_history = (long)state[12];
        double elapsed = state[13];
        if (n_history < 0 || n_history > 2) {
            PyErr_SetString(PyExc_ValueError, "state: n_history must be 0, 1 or 2");
            goto done;
        }
        Result r;
        for (Py_ssize_t i = 0; i < n; i++) {
            const double *d = lengths + 6 * i;
            double warm[6];
            elapsed += dt ? dt[i] : pb.dt;
            if (n_history == 2)
                for (int j = 0; j < 6; j++)
                    warm[j] = 2.0 * history[6 + j] - history[j];
            else if (n_history == 1)
                memcpy(warm, history, sizeof warm);
            solve_seeds(&pb, d, n_history ? warm : NULL,
                        n_history ? history + 6 * (n_history - 1) : NULL, elapsed, &r);
            if (r.status <= ST_RESEEDED) {
                if (n_history == 2) {
                    memmove(history, history + 6, 6 * sizeof(double));
                    memcpy(history + 6, r.pose, 6 * sizeof(double));
                } else {
                    memcpy(history + 6 * n_history, r.pose, 6 * sizeof(double));
                    n_history++;
                }
                elapsed = 0.0;
            } else if (r.status != ST_OUT_OF_SPAN) {
                n_history = 0;   /* a failed sample: the next starts from the home seeds */
            }
            memcpy(poses + 6 * i, r.pose, sizeof r.pose);
            status[i] = (signed char)r.status;
            conv[i] = r.status <= ST_RESEEDED;
            iters[i] = r.iterations;
            resid[i] = r.residual;
            cond[i] = r.condition;
            memcpy(jac + 36 * i, r.rows, sizeof r.rows);
        }
        state[12] = (double)n_history;
        state[13] = elapsed;
    }
    Py_INCREF(Py_None);
    result = Py_None;
done:
    release(&bufs);
    return result;
}

PyDoc_STRVAR(solve_batch_doc,
"solve_batch(problem, lengths, guess, stride, start, stop, poses, status, converged,\n"
"            iterations, residual, condition, jacobian_inverse) -> None\n\n"
"Samples start..stop of N independent samples, lengths (N, 6) [m], as the numpy path of\n"
"ForwardKinematics solves them; releases the GIL. stride 0: solve_batch, from guess (N, 6)\n"
"float64 start poses (a row with a non-finite value: none) or None (the home seeds only);\n"
"stride > 0 (guess None): solve_series, every stride-th sample solved from the home seeds and\n"
"the others from the poses interpolated between those (_series_guess). Outputs for the\n"
"stop - start samples, as for solve_stream; jacobian_inverse (M, 6, 6) float64 (dp/dd, NaN\n"
"unless accepted) or None.");

static PyObject *solve_batch(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o[11];
    Py_ssize_t stride, start, stop;
    if (!PyArg_ParseTuple(args, "OOOnnnOOOOOOO", &o[0], &o[1], &o[10], &stride, &start, &stop,
                          &o[2], &o[3], &o[4], &o[5], &o[6], &o[7], &o[8]))
        return NULL;
    const Py_ssize_t n = rows_of(o[1], "lengths");
    if (n < 0)
        return NULL;
    const Py_ssize_t m = stop - start;
    if (stride < 0 || start < 0 || stop > n || m < 0 || (stride > 0 && o[10] != Py_None)) {
        PyErr_SetString(PyExc_ValueError, "need stride >= 0 (no guess with a stride) and "
                        "0 <= start <= stop <= N");
        return NULL;
    }
    Spec spec[] = {
        {o[0], 0, P_SIZE, 8, "d", "problem", 0},
        {o[1], 0, 6 * n, 8, "d", "lengths", 0},
        {o[2], 1, 6 * m, 8, "d", "poses", 0},
        {o[3], 1, m, 1, "b", "status", 0},
        {o[4], 1, m, 1, "?", "converged", 0},
        {o[5], 1, m, 8, "q", "iterations", 0},
        {o[6], 1, m, 8, "d", "residual", 0},
        {o[7], 1, m, 8, "d", "condition", 0},
        {o[8], 1, 36 * m, 8, "d", "jacobian_inverse", 1},
        {o[10], 0, 6 * n, 8, "d", "guess", 1},
    };
    Buffers bufs = {.got = 0};
    void *ptr[10];
    Problem pb;
    PyObject *result = NULL;
    double *seeds = NULL;
    if (acquire(&bufs, spec, 10, ptr) < 0 || problem_from((const double *)ptr[0], &pb) < 0)
        goto done;
    const Py_ssize_t n_seeds = stride ? (n + stride - 1) / stride : 0;
    const Py_ssize_t s0 = m && stride ? start / stride : 0;
    Py_ssize_t s1 = m && stride ? (stop - 1) / stride + 1 : -1;
    if (s1 > n_seeds - 1)
        s1 = n_seeds - 1;
    seeds = PyMem_RawMalloc((size_t)(s1 - s0 + 2) * 6 * sizeof(double));
    if (!seeds) {
        PyErr_NoMemory();
        goto done;
    }
    {
        const double *lengths = ptr[1], *guess = ptr[9];
        double *poses = ptr[2], *resid = ptr[6], *cond = ptr[7], *jinv = ptr[8];
        signed char *status = ptr[3];
        unsigned char *conv = ptr[4];
        long long *iters = ptr[5];
        Py_BEGIN_ALLOW_THREADS
        Result r;
        for (Py_ssize_t s = s0; s <= s1; s++) {
            solve_seeds(&pb, lengths + 6 * s * stride, NULL, NULL, 0.0, &r);
            memcpy(seeds + 6 * (s - s0), r.pose, sizeof r.pose);   /* NaN unless accepted */
        }
        for (Py_ssize_t k = start; k < stop; k++) {
            double g[6];
            const double *first = NULL;
            if (stride) {
                Py_ssize_t i = k / stride;
                if (i > n_seeds - 1)
                    i = n_seeds - 1;
                const Py_ssize_t j = i + 1 < n_seeds ? i + 1 : n_seeds - 1;
                const Py_ssize_t span = (j - i) * stride > 1 ? (j - i) * stride : 1;
                const double frac = (double)(k - i * stride) / (double)span;
                const double *si = seeds + 6 * (i - s0), *sj = seeds + 6 * (j - s0);
                for (int c = 0; c < 6; c++)
                    g[c] = (1.0 - frac) * si[c] + frac * sj[c];
                first = g;
            } else if (guess) {
                first = guess + 6 * k;
            }
            solve_seeds(&pb, lengths + 6 * k, first && all_finite(first, 6) ? first : NULL,
                        NULL, 0.0, &r);
            store(&r, k - start, poses, status, conv, iters, resid, cond, jinv);
        }
        Py_END_ALLOW_THREADS
    }
    Py_INCREF(Py_None);
    result = Py_None;
done:
    PyMem_RawFree(seeds);
    release(&bufs);
    return result;
}

PyDoc_STRVAR(pose_covariance_doc,
"pose_covariance(jinv, length_cov, scale, out) -> None\n\n"
"Pose covariance of N samples, as propagate_covariance: out_n = D_n J_n^-1 S_n J_n^-T D_n;\n"
"releases the GIL. jinv (N, 6, 6) float64; length_cov (N, 6, 6) or (6, 6) float64, S_n\n"
"[m^2]; scale (N,) float64, D_n = diag(s, s, s, 1, 1, 1), or None (D = I); out (N, 6, 6).");

static PyObject *pose_covariance(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o[4];
    if (!PyArg_ParseTuple(args, "OOOO", &o[0], &o[1], &o[2], &o[3]))
        return NULL;
    Py_buffer view;
    if (get_buffer(o[0], &view, 0, -1, 8, "d", "jinv") < 0)
        return NULL;
    const Py_ssize_t n = view.len / (36 * 8);
    const int shaped = view.len == n * 36 * 8;
    PyBuffer_Release(&view);
    if (!shaped) {
        PyErr_SetString(PyExc_ValueError, "jinv: need shape (N, 6, 6)");
        return NULL;
    }
    if (get_buffer(o[1], &view, 0, -1, 8, "d", "length_cov") < 0)
        return NULL;
    const int per_sample = view.len == n * 36 * 8 && n != 1;
    const int shared = view.len == 36 * 8;
    PyBuffer_Release(&view);
    if (!per_sample && !shared) {
        PyErr_SetString(PyExc_ValueError, "length_cov: need shape (N, 6, 6) or (6, 6)");
        return NULL;
    }
    Spec spec[] = {
        {o[0], 0, 36 * n, 8, "d", "jinv", 0},
        {o[1], 0, per_sample ? 36 * n : 36, 8, "d", "length_cov", 0},
        {o[2], 0, n, 8, "d", "scale", 1},
        {o[3], 1, 36 * n, 8, "d", "out", 0},
    };
    Buffers bufs = {.got = 0};
    void *ptr[4];
    if (acquire(&bufs, spec, 4, ptr) < 0) {
        release(&bufs);
        return NULL;
    }
    const double *jinv = ptr[0], *cov = ptr[1], *scale = ptr[2];
    double *out = ptr[3];
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t s = 0; s < n; s++) {
        const double *J = jinv + 36 * s, *S = cov + (per_sample ? 36 * s : 0);
        double T[36], D[6];
        for (int j = 0; j < 6; j++)
            D[j] = scale && j < 3 ? scale[s] : 1.0;
        /* T = J^-1 S, then out = T J^-T, each row and column times D */
        for (int i = 0; i < 6; i++)
            for (int k = 0; k < 6; k++) {
                double acc = 0.0;
                for (int m = 0; m < 6; m++)
                    acc += J[6 * i + m] * S[6 * m + k];
                T[6 * i + k] = acc;
            }
        for (int i = 0; i < 6; i++)
            for (int k = 0; k < 6; k++) {
                double acc = 0.0;
                for (int m = 0; m < 6; m++)
                    acc += T[6 * i + m] * J[6 * k + m];
                out[36 * s + 6 * i + k] = acc * D[i] * D[k];
            }
    }
    Py_END_ALLOW_THREADS
    release(&bufs);
    Py_INCREF(Py_None);
    return Py_None;
}

PyDoc_STRVAR(match_rows_doc,
"match_rows(rows, template, runs) -> bool\n\n"
"Whether every row of rows (N, W) uint8 (rows may be strided, bytes contiguous) holds the\n"
"bytes of template (W,) uint8 in the runs (M, 2) int64 of (start, length): the fixed bytes of\n"
"a message layout (mmd_ros.logs.cdr.rows_match). Releases the GIL.");

static PyObject *match_rows(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_rows, *o_tpl, *o_runs;
    if (!PyArg_ParseTuple(args, "OOO", &o_rows, &o_tpl, &o_runs))
        return NULL;
    Py_buffer rows, tpl, runs;
    if (PyObject_GetBuffer(o_rows, &rows, PyBUF_RECORDS_RO) < 0)
        return NULL;
    if (rows.ndim != 2 || rows.itemsize != 1 || rows.strides[1] != 1 || rows.strides[0] < 0) {
        PyBuffer_Release(&rows);
        PyErr_SetString(PyExc_ValueError, "rows: need a (N, W) uint8 array whose rows are contiguous");
        return NULL;
    }
    const Py_ssize_t n = rows.shape[0], w = rows.shape[1], stride = rows.strides[0];
    if (get_buffer(o_tpl, &tpl, 0, w, 1, "B", "template") < 0) {
        PyBuffer_Release(&rows);
        return NULL;
    }
    if (get_buffer(o_runs, &runs, 0, -1, 8, "q", "runs") < 0) {
        PyBuffer_Release(&rows);
        PyBuffer_Release(&tpl);
        return NULL;
    }
    const Py_ssize_t m = runs.len / 16;
    const long long *r = runs.buf;
    int ok = runs.len % 16 == 0;
    for (Py_ssize_t j = 0; ok && j < m; j++)
        ok = r[2 * j] >= 0 && r[2 * j + 1] >= 0 && r[2 * j] + r[2 * j + 1] <= w;
    if (!ok) {
        PyBuffer_Release(&rows);
        PyBuffer_Release(&tpl);
        PyBuffer_Release(&runs);
        PyErr_SetString(PyExc_ValueError, "runs: need (M, 2) int64 (start, length) within a row");
        return NULL;
    }
    const unsigned char *base = rows.buf, *t = tpl.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; ok && i < n; i++) {
        const unsigned char *row = base + i * stride;
        for (Py_ssize_t j = 0; j < m; j++) {
            if (memcmp(row + r[2 * j], t + r[2 * j], (size_t)r[2 * j + 1]) != 0) {
                ok = 0;
                break;
            }
        }
    }
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&rows);
    PyBuffer_Release(&tpl);
    PyBuffer_Release(&runs);
    return PyBool_FromLong(ok);
}

/* Shape of an (N, k) float64 buffer whose k columns each have ``width`` state entries in a
 * (k, width) float64 buffer: sets n and k, or returns -1 (error set). */
static int columns_of(PyObject *data, PyObject *state, Py_ssize_t width, const char *name,
                      Py_ssize_t *n, Py_ssize_t *k)
{
    Py_buffer view;
    if (get_buffer(state, &view, 0, -1, 8, "d", "state") < 0)
        return -1;
    const Py_ssize_t cells = view.len / 8;
    PyBuffer_Release(&view);
    if (get_buffer(data, &view, 0, -1, 8, "d", name) < 0)
        return -1;
    const Py_ssize_t total = view.len / 8;
    PyBuffer_Release(&view);
    *k = cells / width;
    if (*k < 1 || cells % width || total % *k) {
        PyErr_Format(PyExc_ValueError, "%s: need shape (N, k) with a state of shape (k, %zd)",
                     name, width);
        return -1;
    }
    *n = total / *k;
    return 0;
}

PyDoc_STRVAR(play_doc,
"play(lengths, deadband, play, direction, positions, directions) -> None\n\n"
"The play (backlash) operator of half-width deadband [m] on each column of lengths (N, k)\n"
"float64, from play (k,) float64 (updated in place): its output into positions (N, k), and the\n"
"direction (-1, 0, +1) of its last move into directions (N, k), from direction (k,) (updated\n"
"in place). direction, positions and directions may be None. terms.play_positions and\n"
"HysteresisTerm.directions (model.py). Releases the GIL.");

static PyObject *play(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o[5];
    double w;
    if (!PyArg_ParseTuple(args, "OdOOOO", &o[0], &w, &o[1], &o[2], &o[3], &o[4]))
        return NULL;
    Py_ssize_t n, k;
    if (columns_of(o[0], o[1], 1, "lengths", &n, &k) < 0)
        return NULL;
    Spec spec[] = {
        {o[0], 0, n * k, 8, "d", "lengths", 0},
        {o[1], 1, k, 8, "d", "play", 0},
        {o[2], 1, k, 8, "d", "direction", 1},
        {o[3], 1, n * k, 8, "d", "positions", 1},
        {o[4], 1, n * k, 8, "d", "directions", 1},
    };
    Buffers bufs = {.got = 0};
    void *ptr[5];
    if (acquire(&bufs, spec, 5, ptr) < 0) {
        release(&bufs);
        return NULL;
    }
    const double *x = ptr[0];
    double *play = ptr[1], *dir = ptr[2], *pos = ptr[3], *dirs = ptr[4];
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = 0; j < k; j++) {
        double p = play[j], d = dir ? dir[j] : 0.0;
        for (Py_ssize_t i = 0; i < n; i++) {
            const double v = x[i * k + j];
            if (p < v - w) {        /* the Python expressions, so that rounding agrees */
                p = v - w;
                d = 1.0;
            } else if (p > v + w) {
                p = v + w;
                d = -1.0;
            }
            if (pos)
                pos[i * k + j] = p;
            if (dirs)
                dirs[i * k + j] = d;
        }
        play[j] = p;
        if (dir)
            dir[j] = d;
    }
    Py_END_ALLOW_THREADS
    release(&bufs);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(dahl_state_doc,
"dahl_state(positions, travel, last, direction, anchor_x, anchor_s, out) -> None\n\n"
"terms.dahl_state: Dahl's friction state along each column of positions (N, k) float64 (the\n"
"play's output), turn-over travel [m]; the state (last position, direction, anchor position,\n"
"anchor state), each (k,) float64, is updated in place; out (N, k) float64 gets s in [-1, 1].\n"
"Releases the GIL.");

/* d - (d - a) exp(-y): the Dahl state y travels after an anchor of state a, direction d. Past
 * DAHL_TURNED travels what is left, |d - a| exp(-y) <= 2 exp(-40) < 1e-17, is below half a
 * unit in the last place of d = +-1, and the sum rounds to d: the exp is skipped (a bar moves
 * millimetres between reversals and the state turns within micrometres; the same numbers). */
#define DAHL_TURNED 40.0

static inline double turned(double d, double a, double y)
{
    return y > DAHL_TURNED ? d : d - (d - a) * exp(-y);
}

static PyObject *dahl_state(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o[6];
    double travel;
    if (!PyArg_ParseTuple(args, "OdOOOOO", &o[0], &travel, &o[1], &o[2], &o[3], &o[4], &o[5]))
        return NULL;
    Py_ssize_t n, k;
    if (columns_of(o[0], o[1], 1, "positions", &n, &k) < 0)
        return NULL;
    Spec spec[] = {
        {o[0], 0, n * k, 8, "d", "positions", 0},
        {o[1], 1, k, 8, "d", "last", 0},
        {o[2], 1, k, 8, "d", "direction", 0},
        {o[3], 1, k, 8, "d", "anchor_x", 0},
        {o[4], 1, k, 8, "d", "anchor_s", 0},
        {o[5], 1, n * k, 8, "d", "out", 0},
    };
    Buffers bufs = {.got = 0};
    void *ptr[6];
    if (acquire(&bufs, spec, 6, ptr) < 0) {
        release(&bufs);
        return NULL;
    }
    const double *x = ptr[0];
    double *last = ptr[1], *dir = ptr[2], *anchor_x = ptr[3], *anchor_s = ptr[4], *out = ptr[5];
    Py_BEGIN_ALLOW_THREADS
    /* row by row, each column's state in last/dir/anchor_x/anchor_s: one pass over the rows
     * (column by column, the 10-minute ISO run's (596441, 6) positions took 61 ms a call) */
    for (Py_ssize_t i = 0; i < n; i++) {
        const double *row = x + i * k;
        double *o = out + i * k;
        for (Py_ssize_t j = 0; j < k; j++) {
            const double p = row[j];
            if (i > 0 && p == last[j]) {   /* at rest (the play holds): the same state */
                o[j] = o[j - k];
                continue;
            }
            double d = dir[j];
            const double step = (p > last[j]) - (p < last[j]);
            const double now = step != 0.0 ? step : d;
            if (now != d) {         /* a new direction begins at the last position: its anchor */
                if (d != 0.0)
                    anchor_s[j] = turned(d, anchor_s[j], d * (last[j] - anchor_x[j]) / travel);
                anchor_x[j] = last[j];
                dir[j] = d = now;
            }
            const double s = d == 0.0 ? anchor_s[j]
                                      : turned(d, anchor_s[j], d * (p - anchor_x[j]) / travel);
            o[j] = s < -1.0 ? -1.0 : (s > 1.0 ? 1.0 : s);
            last[j] = p;
        }
    }
    Py_END_ALLOW_THREADS
    release(&bufs);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(friction_travel_doc,
"friction_travel(lengths, deadband, turnover, state, out, settled) -> None\n\n"
"budget._Friction: each column of lengths (N, k) float64 through a play of half-width deadband\n"
"[m]: the friction state as far as the motion tells, d min(1, |p - f| / turnover), into out\n"
"(N, k), and min(1, path / turnover) into settled (N, k); state (k, 4) float64 (play, direction,\n"
"flip position, path since the run began; NaN play: none yet) is updated in place. A NaN\n"
"length leaves the state as it is. Releases the GIL.");

static PyObject *friction_travel(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o[4];
    double w, turn;
    if (!PyArg_ParseTuple(args, "OddOOO", &o[0], &w, &turn, &o[1], &o[2], &o[3]))
        return NULL;
    Py_ssize_t n, k;
    if (columns_of(o[0], o[1], 4, "lengths", &n, &k) < 0)
        return NULL;
    Spec spec[] = {
        {o[0], 0, n * k, 8, "d", "lengths", 0},
        {o[1], 1, 4 * k, 8, "d", "state", 0},
        {o[2], 1, n * k, 8, "d", "out", 0},
        {o[3], 1, n * k, 8, "d", "settled", 0},
    };
    Buffers bufs = {.got = 0};
    void *ptr[4];
    if (acquire(&bufs, spec, 4, ptr) < 0) {
        release(&bufs);
        return NULL;
    }
    const double *x = ptr[0];
    double *st = ptr[1], *out = ptr[2], *settled = ptr[3];
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = 0; j < k; j++) {
        double p = st[4 * j], d = st[4 * j + 1], f = st[4 * j + 2], path = st[4 * j + 3];
        for (Py_ssize_t i = 0; i < n; i++) {
            const double v = x[i * k + j];
            double res = 0.0, a;
            if (v == v) {           /* the Python loop's steps, in its order */
                if (p != p)
                    p = f = v;
                if (p < v - w) {
                    path += v - w - p;
                    p = v - w;
                    if (d != 1.0) {
                        d = 1.0;
                        f = p;
                    }
                } else if (p > v + w) {
                    path += p - v - w;
                    p = v + w;
                    if (d != -1.0) {
                        d = -1.0;
                        f = p;
                    }
                }
            }
            if (d != 0.0) {
                a = fabs(p - f) / turn;
                res = d * (a < 1.0 ? a : 1.0);
            }
            out[i * k + j] = res;
            a = path / turn;
            settled[i * k + j] = a < 1.0 ? a : 1.0;
        }
        st[4 * j] = p;
        st[4 * j + 1] = d;
        st[4 * j + 2] = f;
        st[4 * j + 3] = path;
    }
    Py_END_ALLOW_THREADS
    release(&bufs);
    Py_RETURN_NONE;
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

/* the byte table's CRC, continued from the register value c (pre-inverted) */
static uint32_t crc32_bytes(uint32_t c, const unsigned char *p, size_t n)
{
    for (size_t i = 0; i < n; i++)
        c = crc_table[(c ^ p[i]) & 0xFF] ^ (c >> 8);
    return c;
}

/* CRC-32 of IEEE 802.3 (zlib.crc32). */
static uint32_t crc32_of(const unsigned char *p, size_t n)
{
    return crc32_bytes(0xFFFFFFFFu, p, n) ^ 0xFFFFFFFFu;
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

/* ---------------------------------------------------------------------------------------------
 * Message records of a log being written (logs/writer.py, _RecordRow.fill; logs/mcap_records.py,
 * the chunk's CRC). fill_rows: N rows of W bytes, each the template with per-row columns copied
 * in at their offsets. crc32: zlib.crc32, folded four 128-bit lanes at a time with carry-less
 * multiplication where the CPU has it (Intel's "Fast CRC computation for generic polynomials
 * using PCLMULQDQ", 2009; the constants are x^k mod P for the reflected IEEE 802.3
 * polynomial), else a byte table. Both release the GIL.
 */
PyDoc_STRVAR(fill_rows_doc,
"fill_rows(block, template, columns) -> None\n\n"
"Fill block (N, W) uint8 with N copies of template (W,) uint8, then, for each (offset, column)\n"
"of columns, copy row i of column (a C-contiguous buffer of N rows of B bytes each) to bytes\n"
"offset .. offset + B of row i.");

static PyObject *fill_rows(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_block, *o_tpl, *o_cols;
    if (!PyArg_ParseTuple(args, "OOO", &o_block, &o_tpl, &o_cols))
        return NULL;
    PyObject *cols = PySequence_Fast(o_cols, "columns: need a sequence of (offset, array)");
    if (cols == NULL)
        return NULL;
    const Py_ssize_t m = PySequence_Fast_GET_SIZE(cols);
    Py_buffer block, tpl;
    Py_buffer *views = PyMem_Calloc((size_t)(m > 0 ? m : 1), sizeof(Py_buffer));
    Py_ssize_t *offs = PyMem_Calloc((size_t)(m > 0 ? m : 1), sizeof(Py_ssize_t));
    Py_ssize_t got = 0;
    int have_block = 0, have_tpl = 0;
    PyObject *result = NULL;
    if (views == NULL || offs == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    if (PyObject_GetBuffer(o_block, &block, PyBUF_RECORDS) < 0)
        goto done;
    have_block = 1;
    if (block.ndim != 2 || block.itemsize != 1 || !PyBuffer_IsContiguous(&block, 'C')) {
        PyErr_SetString(PyExc_ValueError, "block: need a writable C-contiguous (N, W) uint8 array");
        goto done;
    }
    const Py_ssize_t n = block.shape[0], w = block.shape[1];
    if (get_buffer(o_tpl, &tpl, 0, w, 1, "B", "template") < 0)
        goto done;
    have_tpl = 1;
    for (Py_ssize_t j = 0; j < m; j++) {
        PyObject *item = PySequence_Fast_GET_ITEM(cols, j);
        PyObject *o_arr;
        if (!PyArg_ParseTuple(item, "nO", &offs[j], &o_arr))
            goto done;
        if (PyObject_GetBuffer(o_arr, &views[got], PyBUF_C_CONTIGUOUS) < 0)
            goto done;
        got++;
        const Py_ssize_t len = views[j].len;
        if (n > 0 && (len % n != 0 || offs[j] < 0 || offs[j] + len / n > w)) {
            PyErr_Format(PyExc_ValueError, "columns[%zd]: %zd bytes are not %zd rows that fit "
                         "at offset %zd of a %zd-byte row", j, len, n, offs[j], w);
            goto done;
        }
        if (n == 0 && len != 0) {
            PyErr_Format(PyExc_ValueError, "columns[%zd]: %zd bytes for no rows", j, len);
            goto done;
        }
    }
    {
        unsigned char *out = block.buf;
        const unsigned char *t = tpl.buf;
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t i = 0; i < n; i++) {
            unsigned char *row = out + i * w;
            memcpy(row, t, (size_t)w);
            for (Py_ssize_t j = 0; j < m; j++) {
                const Py_ssize_t b = views[j].len / n;
                memcpy(row + offs[j], (const unsigned char *)views[j].buf + i * b, (size_t)b);
            }
        }
        Py_END_ALLOW_THREADS
    }
    result = Py_None;
    Py_INCREF(result);
done:
    for (Py_ssize_t j = 0; j < got; j++)
        PyBuffer_Release(&views[j]);
    if (have_tpl)
        PyBuffer_Release(&tpl);
    if (have_block)
        PyBuffer_Release(&block);
    PyMem_Free(views);
    PyMem_Free(offs);
    Py_DECREF(cols);
    return result;
}

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#include <immintrin.h>
#define HAVE_CLMUL_PATH 1

/* The register value c after n >= 64 bytes at p (n a multiple of 16). */
__attribute__((target("pclmul,sse4.1")))
static uint32_t crc32_clmul(uint32_t c, const unsigned char *p, size_t n)
{
    const __m128i k1k2 = _mm_set_epi64x(0x1c6e41596LL, 0x154442bd4LL);
    const __m128i k3k4 = _mm_set_epi64x(0x0ccaa009eLL, 0x1751997d0LL);
    const __m128i k5 = _mm_set_epi64x(0, 0x163cd6124LL);
    const __m128i poly = _mm_set_epi64x(0x1f7011641LL, 0x1db710641LL);
    const __m128i low32 = _mm_setr_epi32(-1, 0, -1, 0);
    __m128i x1 = _mm_loadu_si128((const __m128i *)(p + 0));
    __m128i x2 = _mm_loadu_si128((const __m128i *)(p + 16));
    __m128i x3 = _mm_loadu_si128((const __m128i *)(p + 32));
    __m128i x4 = _mm_loadu_si128((const __m128i *)(p + 48));
    x1 = _mm_xor_si128(x1, _mm_cvtsi32_si128((int)c));
    p += 64;
    n -= 64;
    while (n >= 64) {
        __m128i a1 = _mm_clmulepi64_si128(x1, k1k2, 0x00), b1 = _mm_clmulepi64_si128(x1, k1k2, 0x11);
        __m128i a2 = _mm_clmulepi64_si128(x2, k1k2, 0x00), b2 = _mm_clmulepi64_si128(x2, k1k2, 0x11);
        __m128i a3 = _mm_clmulepi64_si128(x3, k1k2, 0x00), b3 = _mm_clmulepi64_si128(x3, k1k2, 0x11);
        __m128i a4 = _mm_clmulepi64_si128(x4, k1k2, 0x00), b4 = _mm_clmulepi64_si128(x4, k1k2, 0x11);
        x1 = _mm_xor_si128(_mm_xor_si128(a1, b1), _mm_loadu_si128((const __m128i *)(p + 0)));
        x2 = _mm_xor_si128(_mm_xor_si128(a2, b2), _mm_loadu_si128((const __m128i *)(p + 16)));
        x3 = _mm_xor_si128(_mm_xor_si128(a3, b3), _mm_loadu_si128((const __m128i *)(p + 32)));
        x4 = _mm_xor_si128(_mm_xor_si128(a4, b4), _mm_loadu_si128((const __m128i *)(p + 48)));
        p += 64;
        n -= 64;
    }
    /* the four lanes into one */
    __m128i lanes[3] = {x2, x3, x4};
    for (int k = 0; k < 3; k++) {
        __m128i a = _mm_clmulepi64_si128(x1, k3k4, 0x00), b = _mm_clmulepi64_si128(x1, k3k4, 0x11);
        x1 = _mm_xor_si128(_mm_xor_si128(a, b), lanes[k]);
    }
    while (n >= 16) {
        __m128i a = _mm_clmulepi64_si128(x1, k3k4, 0x00), b = _mm_clmulepi64_si128(x1, k3k4, 0x11);
        x1 = _mm_xor_si128(_mm_xor_si128(a, b), _mm_loadu_si128((const __m128i *)p));
        p += 16;
        n -= 16;
    }
    /* 128 bits to 64, then Barrett reduction to 32 */
    __m128i x = _mm_xor_si128(_mm_clmulepi64_si128(x1, k3k4, 0x10), _mm_srli_si128(x1, 8));
    __m128i hi = _mm_srli_si128(x, 4);
    x = _mm_xor_si128(_mm_clmulepi64_si128(_mm_and_si128(x, low32), k5, 0x00), hi);
    __m128i t = _mm_clmulepi64_si128(_mm_and_si128(x, low32), poly, 0x10);
    t = _mm_clmulepi64_si128(_mm_and_si128(t, low32), poly, 0x00);
    x = _mm_xor_si128(x, t);
    return (uint32_t)_mm_extract_epi32(x, 1);
}

static int has_clmul(void)
{
    __builtin_cpu_init();
    return __builtin_cpu_supports("pclmul") && __builtin_cpu_supports("sse4.1");
}
#else
static int has_clmul(void) { return 0; }
#endif

static int clmul_ok = 0;

PyDoc_STRVAR(crc32_doc,
"crc32(data, value=0) -> int\n\n"
"zlib.crc32(data, value): the CRC-32 of IEEE 802.3 of the bytes of data, continued from value.\n"
"Folded with carry-less multiplication when the module's CLMUL is True, else byte by byte\n"
"(slower than zlib: callers use zlib then).");

static PyObject *crc32_fn(PyObject *self, PyObject *args)
{
    (void)self;
    Py_buffer data;
    unsigned int value = 0;
    if (!PyArg_ParseTuple(args, "y*|I", &data, &value))
        return NULL;
    uint32_t c = ~(uint32_t)value;
    const unsigned char *p = data.buf;
    size_t n = (size_t)data.len;
    Py_BEGIN_ALLOW_THREADS
#ifdef HAVE_CLMUL_PATH
    if (clmul_ok && n >= 64) {
        const size_t body = n & ~(size_t)15;
        c = crc32_clmul(c, p, body);
        p += body;
        n -= body;
    }
#endif
    c = crc32_bytes(c, p, n);
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&data);
    return PyLong_FromUnsignedLong(~c);
}

static PyMethodDef methods[] = {
    {"solve_stream", solve_stream, METH_VARARGS, solve_stream_doc},
    {"solve_batch", solve_batch, METH_VARARGS, solve_batch_doc},
    {"pose_covariance", pose_covariance, METH_VARARGS, pose_covariance_doc},
    {"cdf_eval", cdf_eval, METH_VARARGS, cdf_eval_doc},
    {"play", play, METH_VARARGS, play_doc},
    {"friction_travel", friction_travel, METH_VARARGS, friction_travel_doc},
    {"dahl_state", dahl_state, METH_VARARGS, dahl_state_doc},
    {"match_rows", match_rows, METH_VARARGS, match_rows_doc},
    {"decode_continuing", decode_continuing, METH_VARARGS, decode_continuing_doc},
    {"fill_rows", fill_rows, METH_VARARGS, fill_rows_doc},
    {"crc32", crc32_fn, METH_VARARGS, crc32_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_fast",
    "Compiled helpers of mmd_ros (see mmd_ros.core.compiled).", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__fast(void)
{
    crc_init();
    clmul_ok = has_clmul();
    PyObject *m = PyModule_Create(&module);
    if (m != NULL && PyModule_AddObject(m, "CLMUL", PyBool_FromLong(clmul_ok)) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
