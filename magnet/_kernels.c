/* The per-sample loops of the filters, compiled (docs/cost.md says why C and not numba).
 *
 * Each function takes numpy arrays (any float64 buffer: C-contiguous or a strided view such as a table's columns)
 * and writes its results into the arrays it is given, or returns a few floats. They are the maths of the Python
 * modules that call them (magnet.attitude: aided_fusion, aiding, gyro_bias, mag_delay, field_watch), written once
 * here; tests/test_kernels.py compares each with the same maths written plainly in numpy on random inputs.
 * Quaternions are w, x, y, z; vectors x, y, z; no allocation, no Python objects inside the loops. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <float.h>
#include <math.h>
#include <stdio.h>
#include <string.h>

typedef struct {
    Py_buffer view;
    Py_ssize_t rows, cols;
    Py_ssize_t st[2]; /* the strides of an Array over memory of our own (``raw_array``) */
} Array;

#define AT(a, i, j) (*(double *)((char *)(a).view.buf + (i) * (a).view.strides[0] + (j) * (a).view.strides[1]))
#define AT1(a, i) (*(double *)((char *)(a).view.buf + (i) * (a).view.strides[0]))

/* A float64 array of ``ndim`` dimensions (1 or 2) with ``cols`` columns (2-D; -1: any); ``rows`` -1: any. */
static int get_array(PyObject *obj, Array *a, int ndim, Py_ssize_t rows, Py_ssize_t cols, int writable,
                     const char *name) {
    int flags = PyBUF_STRIDES | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, &a->view, flags) < 0) {
        return -1;
    }
    const char *format = a->view.format;
    if (a->view.itemsize != 8 || format == NULL || !(format[0] == 'd' || (format[0] == '<' && format[1] == 'd')) ||
        a->view.ndim != ndim) {
        PyErr_Format(PyExc_ValueError, "%s must be a %d-D float64 array", name, ndim);
        PyBuffer_Release(&a->view);
        return -1;
    }
    a->rows = a->view.shape[0];
    a->cols = ndim == 2 ? a->view.shape[1] : 1;
    if ((rows >= 0 && a->rows != rows) || (ndim == 2 && cols >= 0 && a->cols != cols)) {
        PyErr_Format(PyExc_ValueError, "%s has shape (%zd, %zd), expected (%zd, %zd) (-1: any)", name, a->rows,
                     a->cols, rows, cols);
        PyBuffer_Release(&a->view);
        return -1;
    }
    return 0;
}

/* An Array over ``rows`` x ``cols`` doubles at ``buf``, ``row_items`` doubles from one row to the next. */
static void raw_array(Array *a, double *buf, Py_ssize_t rows, Py_ssize_t cols, Py_ssize_t row_items) {
    memset(a, 0, sizeof(*a));
    a->st[0] = row_items * (Py_ssize_t)sizeof(double);
    a->st[1] = sizeof(double);
    a->view.buf = buf;
    a->view.strides = a->st;
    a->rows = rows;
    a->cols = cols;
}

static void release(Array *arrays, int count) {
    for (int i = 0; i < count; i++) {
        PyBuffer_Release(&arrays[i].view);
    }
}

/* p q, Hamilton product. */
static void quat_mul(const double p[4], const double q[4], double out[4]) {
    out[0] = p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3];
    out[1] = p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2];
    out[2] = p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1];
    out[3] = p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0];
}

/* The rotation matrix of a quaternion (normalised here), row-major. */
static void quat_matrix(const double q_in[4], double r[9]) {
    double n = sqrt(q_in[0] * q_in[0] + q_in[1] * q_in[1] + q_in[2] * q_in[2] + q_in[3] * q_in[3]);
    double w = q_in[0] / n, x = q_in[1] / n, y = q_in[2] / n, z = q_in[3] / n;
    r[0] = 1 - 2 * (y * y + z * z);
    r[1] = 2 * (x * y - w * z);
    r[2] = 2 * (x * z + w * y);
    r[3] = 2 * (x * y + w * z);
    r[4] = 1 - 2 * (x * x + z * z);
    r[5] = 2 * (y * z - w * x);
    r[6] = 2 * (x * z - w * y);
    r[7] = 2 * (y * z + w * x);
    r[8] = 1 - 2 * (x * x + y * y);
}

PyDoc_STRVAR(carry_forward_doc,
             "carry_forward(start, gyr, bias, period_s, out)\n\n"
             "out (N, 4): quaternion ``start`` (4,) turned by each body rate gyr (N, 3) rad/s less ``bias`` (3,) over "
             "one period in turn (right products), as vqf integrates them.");

static void carry_forward_core(const double start[4], const Array *gyr, const double bias[3], double period,
                               Array *out) {
    double q[4] = {start[0], start[1], start[2], start[3]};
    for (Py_ssize_t i = 0; i < gyr->rows; i++) {
        double r0 = AT(*gyr, i, 0) - bias[0], r1 = AT(*gyr, i, 1) - bias[1], r2 = AT(*gyr, i, 2) - bias[2];
        double norm = sqrt(r0 * r0 + r1 * r1 + r2 * r2);
        double angle = norm * period / 2.0;
        double c = cos(angle), s = norm > 0 ? sin(angle) / norm : 0.0;
        double turn[4] = {c, r0 * s, r1 * s, r2 * s}, next[4];
        quat_mul(q, turn, next);
        for (int k = 0; k < 4; k++) {
            q[k] = next[k];
            AT(*out, i, k) = next[k];
        }
    }
}

static PyObject *carry_forward(PyObject *self, PyObject *args) {
    PyObject *o_start, *o_gyr, *o_bias, *o_out;
    double period;
    if (!PyArg_ParseTuple(args, "OOOdO", &o_start, &o_gyr, &o_bias, &period, &o_out)) {
        return NULL;
    }
    Array a[4];
    if (get_array(o_start, &a[0], 1, 4, -1, 0, "start") < 0) return NULL;
    if (get_array(o_gyr, &a[1], 2, -1, 3, 0, "gyr") < 0) { release(a, 1); return NULL; }
    if (get_array(o_bias, &a[2], 1, 3, -1, 0, "bias") < 0) { release(a, 2); return NULL; }
    if (get_array(o_out, &a[3], 2, a[1].rows, 4, 1, "out") < 0) { release(a, 3); return NULL; }
    double start[4] = {AT1(a[0], 0), AT1(a[0], 1), AT1(a[0], 2), AT1(a[0], 3)};
    double bias[3] = {AT1(a[2], 0), AT1(a[2], 1), AT1(a[2], 2)};
    carry_forward_core(start, &a[1], bias, period, &a[3]);
    release(a, 4);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(quaternion_product_doc,
             "quaternion_product(p, q, out, conjugate_p=False, normalise=False)\n\n"
             "out (N, 4) = p q row by row: p (1, 4) one quaternion for every row, or (N, 4); q (N, 4). "
             "``conjugate_p``: p's conjugate; ``normalise``: each product to unit length. ``out`` may be ``q``.");

/* out = p q row by row (p one row or one a row), p conjugated and each product normalised on request. */
static void quaternion_product_core(const Array *pa, const Array *qa, Array *out, int conjugate, int normalise) {
    int p_each = pa->rows != 1;
    double sign = conjugate ? -1.0 : 1.0;
    for (Py_ssize_t i = 0; i < qa->rows; i++) {
        double p[4], q[4], r[4];
        for (int k = 0; k < 4; k++) {
            p[k] = AT(*pa, p_each ? i : 0, k) * (k ? sign : 1.0);
            q[k] = AT(*qa, i, k);
        }
        quat_mul(p, q, r);
        double n = normalise ? sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3]) : 1.0;
        for (int k = 0; k < 4; k++) {
            AT(*out, i, k) = r[k] / n;
        }
    }
}

static PyObject *quaternion_product(PyObject *self, PyObject *args) {
    PyObject *o_p, *o_q, *o_out;
    int conjugate = 0, normalise = 0;
    if (!PyArg_ParseTuple(args, "OOO|pp", &o_p, &o_q, &o_out, &conjugate, &normalise)) {
        return NULL;
    }
    Array a[3];
    if (get_array(o_q, &a[1], 2, -1, 4, 0, "q") < 0) return NULL;
    if (get_array(o_p, &a[0], 2, -1, 4, 0, "p") < 0) { PyBuffer_Release(&a[1].view); return NULL; }
    if (a[0].rows != 1 && a[0].rows != a[1].rows) {
        release(a, 2);
        PyErr_SetString(PyExc_ValueError, "p must have one row or as many as q");
        return NULL;
    }
    if (get_array(o_out, &a[2], 2, a[1].rows, 4, 1, "out") < 0) { release(a, 2); return NULL; }
    quaternion_product_core(&a[0], &a[1], &a[2], conjugate, normalise);
    release(a, 3);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(into_body_doc,
             "into_body(quat_vqf, a_ned, out)\n\n"
             "out (N, 3) = R^T a: accelerations a_ned (N, 3) magnetic NED turned into vqf's body frame by vqf's "
             "quaternions (N, 4) body -> ENU (normalised here).");

static void into_body_core(const Array *qa, const Array *aa, Array *out) {
    for (Py_ssize_t i = 0; i < qa->rows; i++) {
        double q[4] = {AT(*qa, i, 0), AT(*qa, i, 1), AT(*qa, i, 2), AT(*qa, i, 3)}, r[9];
        quat_matrix(q, r);
        double e = AT(*aa, i, 1), n = AT(*aa, i, 0), u = -AT(*aa, i, 2); /* NED -> ENU */
        for (int k = 0; k < 3; k++) {
            AT(*out, i, k) = r[k] * e + r[3 + k] * n + r[6 + k] * u;
        }
    }
}

static PyObject *into_body(PyObject *self, PyObject *args) {
    PyObject *o_q, *o_a, *o_out;
    if (!PyArg_ParseTuple(args, "OOO", &o_q, &o_a, &o_out)) {
        return NULL;
    }
    Array a[3];
    if (get_array(o_q, &a[0], 2, -1, 4, 0, "quat_vqf") < 0) return NULL;
    if (get_array(o_a, &a[1], 2, a[0].rows, 3, 0, "a_ned") < 0) { release(a, 1); return NULL; }
    if (get_array(o_out, &a[2], 2, a[0].rows, 3, 1, "out") < 0) { release(a, 2); return NULL; }
    into_body_core(&a[0], &a[1], &a[2]);
    release(a, 3);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(piece_figures_doc,
             "piece_figures(quat6d, field, acc, gravity) -> (up_x, up_y, up_z, heading_rad, horizontal, vertical, "
             "left_ms2)\n\n"
             "What one piece fed to vqf says, from its 6D quaternions (n, 4) body -> ENU, the field (n, 3) and the "
             "accelerometer fed (n, 3) in vqf's body frame: the earth's up axis in body axes at the piece's end; the "
             "field in the 6D earth frame E = R b: the circular mean of its heading atan2(E_east, E_north), the mean "
             "of its horizontal norm and of E_up; and |mean(acc - gravity up)| (m/s^2).");

/* out: up (3), heading (rad), horizontal, vertical, left (m/s^2) of n >= 1 samples (see piece_figures_doc). */
static void piece_figures_core(const Array *qa, const Array *fa, const Array *aa, double gravity, double out[7]) {
    Py_ssize_t n = qa->rows;
    double sin_sum = 0, cos_sum = 0, horizontal = 0, vertical = 0, left[3] = {0, 0, 0}, up[3] = {0, 0, 1};
    for (Py_ssize_t i = 0; i < n; i++) {
        double q[4] = {AT(*qa, i, 0), AT(*qa, i, 1), AT(*qa, i, 2), AT(*qa, i, 3)}, r[9];
        quat_matrix(q, r);
        double b[3] = {AT(*fa, i, 0), AT(*fa, i, 1), AT(*fa, i, 2)}, e[3];
        for (int k = 0; k < 3; k++) {
            e[k] = r[3 * k] * b[0] + r[3 * k + 1] * b[1] + r[3 * k + 2] * b[2];
            up[k] = r[6 + k];
            left[k] += AT(*aa, i, k) - gravity * up[k];
        }
        double phi = atan2(e[0], e[1]);
        sin_sum += sin(phi);
        cos_sum += cos(phi);
        horizontal += hypot(e[0], e[1]);
        vertical += e[2];
    }
    double mean_left = sqrt(left[0] * left[0] + left[1] * left[1] + left[2] * left[2]) / (double)n;
    double figures[7] = {up[0], up[1], up[2], atan2(sin_sum / n, cos_sum / n), horizontal / n, vertical / n,
                         mean_left};
    memcpy(out, figures, sizeof(figures));
}

static PyObject *piece_figures(PyObject *self, PyObject *args) {
    PyObject *o_q, *o_field, *o_acc;
    double gravity;
    if (!PyArg_ParseTuple(args, "OOOd", &o_q, &o_field, &o_acc, &gravity)) {
        return NULL;
    }
    Array a[3];
    if (get_array(o_q, &a[0], 2, -1, 4, 0, "quat6d") < 0) return NULL;
    if (get_array(o_field, &a[1], 2, a[0].rows, 3, 0, "field") < 0) { release(a, 1); return NULL; }
    if (get_array(o_acc, &a[2], 2, a[0].rows, 3, 0, "acc") < 0) { release(a, 2); return NULL; }
    Py_ssize_t n = a[0].rows;
    if (n == 0) {
        release(a, 3);
        PyErr_SetString(PyExc_ValueError, "piece_figures needs at least one sample");
        return NULL;
    }
    double f[7];
    piece_figures_core(&a[0], &a[1], &a[2], gravity, f);
    PyObject *out = Py_BuildValue("ddddddd", f[0], f[1], f[2], f[3], f[4], f[5], f[6]);
    release(a, 3);
    return out;
}

/* np.interp(x, xp, fp) for increasing xp (F >= 1): the ends held. */
static double interp(double x, const Array *xp, const Array *fp, Py_ssize_t column) {
    Py_ssize_t count = xp->rows;
    if (x <= AT1(*xp, 0)) return AT(*fp, 0, column);
    if (x >= AT1(*xp, count - 1)) return AT(*fp, count - 1, column);
    Py_ssize_t lo = 0, hi = count - 1; /* xp[lo] <= x < xp[hi] */
    while (hi - lo > 1) {
        Py_ssize_t mid = (lo + hi) / 2;
        if (AT1(*xp, mid) <= x) lo = mid; else hi = mid;
    }
    double slope = (AT(*fp, hi, column) - AT(*fp, lo, column)) / (AT1(*xp, hi) - AT1(*xp, lo));
    return slope * (x - AT1(*xp, lo)) + AT(*fp, lo, column);
}

PyDoc_STRVAR(centred_difference_doc,
             "centred_difference(times, values, t, half_window, out)\n\n"
             "out (n, 3) = (v(t + h) - v(t - h)) / 2h of the fixes (times (F,) increasing, F >= 2, values (F, 3)) "
             "joined by straight lines (held beyond the ends); 0 where t - h is before the first fix or t + h after "
             "the last (+1e-9 s).");

/* times (F >= 2,), values (F, 3), t (n,) -> out (n, 3): see centred_difference_doc. */
static void centred_difference_core(const Array *times, const Array *values, const Array *ta, double h, Array *out) {
    double first = AT1(*times, 0), last = AT1(*times, times->rows - 1);
    for (Py_ssize_t i = 0; i < ta->rows; i++) {
        double t = AT1(*ta, i);
        int covered = (t - h >= first) && (t + h <= last + 1e-9);
        for (int k = 0; k < 3; k++) {
            AT(*out, i, k) =
                covered ? (interp(t + h, times, values, k) - interp(t - h, times, values, k)) / (2.0 * h) : 0.0;
        }
    }
}

static PyObject *centred_difference(PyObject *self, PyObject *args) {
    PyObject *o_times, *o_values, *o_t, *o_out;
    double h;
    if (!PyArg_ParseTuple(args, "OOOdO", &o_times, &o_values, &o_t, &h, &o_out)) {
        return NULL;
    }
    Array a[4];
    if (get_array(o_times, &a[0], 1, -1, -1, 0, "times") < 0) return NULL;
    if (get_array(o_values, &a[1], 2, a[0].rows, 3, 0, "values") < 0) { release(a, 1); return NULL; }
    if (get_array(o_t, &a[2], 1, -1, -1, 0, "t") < 0) { release(a, 2); return NULL; }
    if (get_array(o_out, &a[3], 2, a[2].rows, 3, 1, "out") < 0) { release(a, 3); return NULL; }
    if (a[0].rows < 2) {
        release(a, 4);
        PyErr_SetString(PyExc_ValueError, "centred_difference needs at least two fixes");
        return NULL;
    }
    centred_difference_core(&a[0], &a[1], &a[2], h, &a[3]);
    release(a, 4);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(drift_step_doc,
             "drift_step(x, p, dt, tau_s, up, q_diag, z, noise, update) -> None\n\n"
             "The heading-drift Kalman filter's step, in place on x (5,) and p (5, 5): the prediction over dt (s, "
             "0 if negative) with F = I, F[0, 1:4] = -dt up (3,), F[4, 4] = exp(-dt / tau_s) and the process noise "
             "diag(q_diag (5,)) (already for dt); then, when ``update``, the measurement z (rad) of x[0] + x[4] with "
             "variance ``noise``, the innovation and x[0] wrapped to [-pi, pi].");

static void drift_step_core(double *x_io, double *p_io, double dt, double tau, const double up[3], const double q[5],
                            double z, double noise, int update);

static PyObject *drift_step(PyObject *self, PyObject *args) {
    PyObject *o_x, *o_p, *o_up, *o_q;
    double dt, tau, z, noise;
    int update;
    if (!PyArg_ParseTuple(args, "OOddOOddp", &o_x, &o_p, &dt, &tau, &o_up, &o_q, &z, &noise, &update)) {
        return NULL;
    }
    Array a[4];
    if (get_array(o_x, &a[0], 1, 5, -1, 1, "x") < 0) return NULL;
    if (get_array(o_p, &a[1], 2, 5, 5, 1, "p") < 0) { release(a, 1); return NULL; }
    if (get_array(o_up, &a[2], 1, 3, -1, 0, "up") < 0) { release(a, 2); return NULL; }
    if (get_array(o_q, &a[3], 1, 5, -1, 0, "q_diag") < 0) { release(a, 3); return NULL; }
    double x0[5], p0[25], up[3], q[5];
    for (int i = 0; i < 5; i++) {
        x0[i] = AT1(a[0], i);
        q[i] = AT1(a[3], i);
        for (int j = 0; j < 5; j++) p0[5 * i + j] = AT(a[1], i, j);
    }
    for (int k = 0; k < 3; k++) up[k] = AT1(a[2], k);
    drift_step_core(x0, p0, dt, tau, up, q, z, noise, update);
    for (int i = 0; i < 5; i++) {
        AT1(a[0], i) = x0[i];
        for (int j = 0; j < 5; j++) AT(a[1], i, j) = p0[5 * i + j];
    }
    release(a, 4);
    Py_RETURN_NONE;
}

/* The step of drift_step_doc on x (5,) and p (25,, row-major) in place. */
static void drift_step_core(double *x_io, double *p_io, double dt, double tau, const double up[3], const double q[5],
                            double z, double noise, int update) {
    double f[5][5] = {{0}}, x[5], p[5][5], fp[5][5];
    dt = dt > 0.0 ? dt : 0.0;
    for (int i = 0; i < 5; i++) f[i][i] = 1.0;
    for (int k = 0; k < 3; k++) f[0][1 + k] = -dt * up[k];
    f[4][4] = exp(-dt / tau);
    for (int i = 0; i < 5; i++) {
        x[i] = 0.0;
        for (int j = 0; j < 5; j++) x[i] += f[i][j] * x_io[j];
    }
    for (int i = 0; i < 5; i++) {
        for (int j = 0; j < 5; j++) {
            fp[i][j] = 0.0;
            for (int k = 0; k < 5; k++) fp[i][j] += f[i][k] * p_io[5 * k + j];
        }
    }
    for (int i = 0; i < 5; i++) {
        for (int j = 0; j < 5; j++) {
            p[i][j] = 0.0;
            for (int k = 0; k < 5; k++) p[i][j] += fp[i][k] * f[j][k];
        }
        p[i][i] += q[i];
    }
    if (update) {
        double innovation = remainder(z - (x[0] + x[4]), 2.0 * M_PI);
        double s = p[0][0] + p[0][4] + p[4][0] + p[4][4] + noise, gain[5], hp[5];
        for (int i = 0; i < 5; i++) {
            gain[i] = (p[i][0] + p[i][4]) / s;
            hp[i] = p[0][i] + p[4][i];
        }
        for (int i = 0; i < 5; i++) x[i] += gain[i] * innovation;
        x[0] = remainder(x[0], 2.0 * M_PI);
        for (int i = 0; i < 5; i++) {
            for (int j = 0; j < 5; j++) p[i][j] -= gain[i] * hp[j];
        }
    }
    for (int i = 0; i < 5; i++) {
        x_io[i] = x[i];
        for (int j = 0; j < 5; j++) p_io[5 * i + j] = p[i][j];
    }
}

PyDoc_STRVAR(advance_field_doc,
             "advance_field(field, gyr, lags, out)\n\n"
             "out (N, 3): each field (N, 3) turned by exp(-[w]x lag), w the body rate gyr (N, 3) rad/s and lag "
             "lags (N,) s; rows whose lag is 0 or whose rate or field is not finite are copied as they are.");

static PyObject *advance_field(PyObject *self, PyObject *args) {
    PyObject *o_field, *o_gyr, *o_lags, *o_out;
    if (!PyArg_ParseTuple(args, "OOOO", &o_field, &o_gyr, &o_lags, &o_out)) {
        return NULL;
    }
    Array a[4];
    if (get_array(o_field, &a[0], 2, -1, 3, 0, "field") < 0) return NULL;
    if (get_array(o_gyr, &a[1], 2, a[0].rows, 3, 0, "gyr") < 0) { release(a, 1); return NULL; }
    if (get_array(o_lags, &a[2], 1, a[0].rows, -1, 0, "lags") < 0) { release(a, 2); return NULL; }
    if (get_array(o_out, &a[3], 2, a[0].rows, 3, 1, "out") < 0) { release(a, 3); return NULL; }
    for (Py_ssize_t i = 0; i < a[0].rows; i++) {
        double b[3] = {AT(a[0], i, 0), AT(a[0], i, 1), AT(a[0], i, 2)}, lag = AT1(a[2], i);
        double w[3] = {-AT(a[1], i, 0) * lag, -AT(a[1], i, 1) * lag, -AT(a[1], i, 2) * lag};
        int finite = isfinite(b[0]) && isfinite(b[1]) && isfinite(b[2]) && isfinite(AT(a[1], i, 0)) &&
                     isfinite(AT(a[1], i, 1)) && isfinite(AT(a[1], i, 2));
        double angle = sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]);
        if (lag != 0.0 && finite && angle > 0.0) {
            double k[3] = {w[0] / angle, w[1] / angle, w[2] / angle};
            double kb[3] = {k[1] * b[2] - k[2] * b[1], k[2] * b[0] - k[0] * b[2], k[0] * b[1] - k[1] * b[0]};
            double kkb[3] = {k[1] * kb[2] - k[2] * kb[1], k[2] * kb[0] - k[0] * kb[2], k[0] * kb[1] - k[1] * kb[0]};
            double s = sin(angle), c = 1.0 - cos(angle);
            for (int j = 0; j < 3; j++) b[j] = b[j] + s * kb[j] + c * kkb[j];
        }
        for (int j = 0; j < 3; j++) AT(a[3], i, j) = b[j];
    }
    release(a, 4);
    Py_RETURN_NONE;
}


/* One 1-D array of bools (numpy's '?', one byte), writable, with ``rows`` items. */
static int get_flags(PyObject *obj, Py_buffer *view, Py_ssize_t rows, const char *name) {
    if (PyObject_GetBuffer(obj, view, PyBUF_STRIDES | PyBUF_FORMAT | PyBUF_WRITABLE) < 0) {
        return -1;
    }
    if (view->itemsize != 1 || view->format == NULL || view->format[0] != '?' || view->ndim != 1 ||
        view->shape[0] != rows) {
        PyErr_Format(PyExc_ValueError, "%s must be a writable 1-D bool array of %zd items", name, rows);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

static int compare_doubles(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* The k-th smallest of v[0 .. n - 1] (0-based), the values reordered so that those after k are not smaller. */
static double select_kth(double *v, Py_ssize_t n, Py_ssize_t k) {
    Py_ssize_t lo = 0, hi = n - 1;
    while (lo < hi) {
        double pivot = v[(lo + hi) / 2];
        Py_ssize_t i = lo, j = hi;
        while (i <= j) {
            while (v[i] < pivot) i++;
            while (v[j] > pivot) j--;
            if (i <= j) {
                double swap = v[i];
                v[i++] = v[j];
                v[j--] = swap;
            }
        }
        if (k <= j) hi = j;
        else if (k >= i) lo = i;
        else break;
    }
    return v[k];
}

/* numpy's percentile (linear) of the first n values of v (reordered here), n >= 1. */
static double percentile(double *v, Py_ssize_t n, double percent) {
    double index = percent / 100.0 * (double)(n - 1);
    Py_ssize_t lo = (Py_ssize_t)floor(index);
    if (lo >= n - 1) return select_kth(v, n, n - 1);
    double low = select_kth(v, n, lo), high = v[lo + 1];
    for (Py_ssize_t i = lo + 2; i < n; i++) high = v[i] < high ? v[i] : high;
    return low + (high - low) * (index - (double)lo);
}

/* The indices of the watch's state vector (magnet.attitude.field_watch.FieldWatch). */
enum { W_QUAT = 0, W_TURNED = 4, W_SAMPLES, W_REFERENCE, W_HOLD_LEFT, W_RUN, W_PENDING, W_CALM, W_SUM, W_SIZE = W_SUM + 3 };
#define MAX_STEPS 8

/* At a block's end (FieldWatch._learn): the reference |B| towards the block's calm samples' mean (their median
 * first), the usual levels towards the 90th percentile of each statistic; a field flagged for longer than
 * max_reject_s is the new normal, learnt again. */
static void watch_learn(double *state, Array *levels, Array *pending, Array *calm, double period, double tau_s,
                        double max_reject_s, int steps, double *scratch) {
    if (state[W_RUN] * period > max_reject_s) {
        state[W_REFERENCE] = 0.0, state[W_HOLD_LEFT] = 0.0, state[W_RUN] = 0.0;
        for (int j = 0; j <= steps; j++) AT1(*levels, j) = 0.0;
    }
    Py_ssize_t count = (Py_ssize_t)state[W_PENDING], calm_count = (Py_ssize_t)state[W_CALM];
    state[W_PENDING] = 0.0, state[W_CALM] = 0.0;
    if (count == 0) return;
    double seconds = (double)count * period, seen_s = state[W_SAMPLES] * period;
    double share = seconds / (seen_s > seconds ? seen_s : seconds);
    double alpha = -expm1(-seconds / tau_s);
    alpha = alpha > (share < 1.0 ? share : 1.0) ? alpha : (share < 1.0 ? share : 1.0);
    if (calm_count > 0) {
        double mean = 0.0;
        for (Py_ssize_t i = 0; i < calm_count; i++) {
            scratch[i] = AT1(*calm, i);
            mean += scratch[i];
        }
        mean /= (double)calm_count;
        if (state[W_REFERENCE] == 0.0) {
            qsort(scratch, (size_t)calm_count, sizeof(double), compare_doubles);
            Py_ssize_t half = calm_count / 2;
            state[W_REFERENCE] = calm_count % 2 ? scratch[half] : (scratch[half - 1] + scratch[half]) / 2.0;
            alpha = 1.0;
        }
        state[W_REFERENCE] += alpha * (mean - state[W_REFERENCE]);
    }
    for (int j = 0; j <= steps; j++) {
        Py_ssize_t finite = 0;
        for (Py_ssize_t i = 0; i < count; i++) {
            double value = AT(*pending, i, j);
            if (isfinite(value)) scratch[finite++] = value;
        }
        if (finite > 0) {
            double level = AT1(*levels, j);
            AT1(*levels, j) = level + alpha * (percentile(scratch, finite, 90.0) - level);
        }
    }
}

PyDoc_STRVAR(watch_update_doc,
             "watch_update(field, gyr, flagged, state, levels, ring, pending, calm, widths, floors, period_s, smooth, "
             "hold, block, relative, field_tol_pct, learn_s, level_tau_s, max_reject_s, turn_floor_rad)\n\n"
             "FieldWatch.update's per-sample loop (magnet.attitude.field_watch), in place: flagged (n,) bool, the "
             "samples of field (n, 3) and gyr (n, 3) rad/s that are disturbed. State: ``state`` (14,) the integrated "
             "attitude wxyz, the radians turned, the samples seen, the reference |B|, the hold left, the flagged run, "
             "the block's pending and calm counts, the running sum (3,) of the last ``smooth`` samples' field in the "
             "integrated frame; ``levels`` (S + 1,) the usual levels; ``ring`` (K, 7) the last K = max(widths) + smooth samples' field in the integrated frame, its mean over ``smooth`` samples and the "
             "radians turned (row = sample index mod K); ``pending`` (block, S + 1) the block's statistics per radian, "
             "``calm`` (block,) its calm samples' |B|. widths (S,) and floors (S,): the step windows in samples and "
             "their floors.");

/* FieldWatch's numbers (``watch_update``'s float and int arguments). */
typedef struct {
    double period, relative, tol_pct, learn_s, tau_s, max_reject_s, turn_floor;
    Py_ssize_t smooth, hold, block;
} WatchNumbers;

/* The watch's own arrays a[2] .. a[8] (widths, floors, state, levels, ring, pending, calm) from their objects; on
 * failure -1, an exception set and nothing held. a[0] and a[1] (field and gyr, n rows) are the caller's. */
static int watch_arrays(Array a[9], PyObject *o_widths, PyObject *o_floors, PyObject *o_state, PyObject *o_levels,
                        PyObject *o_ring, PyObject *o_pending, PyObject *o_calm, Py_ssize_t block) {
    if (get_array(o_widths, &a[2], 1, -1, -1, 0, "widths") < 0) return -1;
    int steps = (int)a[2].rows;
    if (get_array(o_floors, &a[3], 1, steps, -1, 0, "floors") < 0) { release(a + 2, 1); return -1; }
    if (get_array(o_state, &a[4], 1, W_SIZE, -1, 1, "state") < 0) { release(a + 2, 2); return -1; }
    if (get_array(o_levels, &a[5], 1, steps + 1, -1, 1, "levels") < 0) { release(a + 2, 3); return -1; }
    if (get_array(o_ring, &a[6], 2, -1, 7, 1, "ring") < 0) { release(a + 2, 4); return -1; }
    if (get_array(o_pending, &a[7], 2, block, steps + 1, 1, "pending") < 0) { release(a + 2, 5); return -1; }
    if (get_array(o_calm, &a[8], 1, block, -1, 1, "calm") < 0) { release(a + 2, 6); return -1; }
    return 0;
}

/* FieldWatch.update's loop over the a[0].rows samples of field a[0] and gyr a[1] (the rest as ``watch_arrays``):
 * out[i * stride] set where sample i is disturbed, the state updated in place. -1 and an exception on bad sizes. */
static int watch_run(Array *a, const WatchNumbers *nums, char *out, Py_ssize_t stride) {
    const double period = nums->period, relative = nums->relative, tol_pct = nums->tol_pct,
                 learn_s = nums->learn_s, tau_s = nums->tau_s, max_reject_s = nums->max_reject_s,
                 turn_floor = nums->turn_floor;
    const Py_ssize_t smooth = nums->smooth, hold = nums->hold, block = nums->block;
    int steps = (int)a[2].rows;
    Py_ssize_t widths[MAX_STEPS], keep = a[6].rows, longest = 0;
    double *scratch = steps <= MAX_STEPS && smooth >= 1 && block >= 1 ? PyMem_Malloc(block * sizeof(double)) : NULL;
    for (int j = 0; j < steps && j < MAX_STEPS; j++) {
        widths[j] = (Py_ssize_t)AT1(a[2], j);
        longest = widths[j] > longest ? widths[j] : longest;
    }
    if (scratch == NULL || keep != longest + smooth) {
        PyMem_Free(scratch);
        PyErr_Format(PyExc_ValueError, "watch_update needs at most %d steps, smooth and block >= 1 and a ring of "
                     "max(widths) + smooth rows", MAX_STEPS);
        return -1;
    }
    double state[W_SIZE];
    for (int k = 0; k < W_SIZE; k++) state[k] = AT1(a[4], k);
    for (Py_ssize_t i = 0; i < a[0].rows; i++) {
        /* the attitude integrated from the start, and the field in its frame */
        double r[3] = {AT(a[1], i, 0) * period, AT(a[1], i, 1) * period, AT(a[1], i, 2) * period};
        double angle = sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]);
        double s = angle > 1e-12 ? sin(0.5 * angle) / angle : 0.5;
        double turn[4] = {cos(0.5 * angle), r[0] * s, r[1] * s, r[2] * s}, q[4];
        quat_mul(&state[W_QUAT], turn, q);
        double norm_q = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
        for (int k = 0; k < 4; k++) state[W_QUAT + k] = q[k] / norm_q;
        const double *u = &state[W_QUAT + 1], w = state[W_QUAT];
        double v[3] = {AT(a[0], i, 0), AT(a[0], i, 1), AT(a[0], i, 2)};
        double t[3] = {2.0 * (u[1] * v[2] - u[2] * v[1]), 2.0 * (u[2] * v[0] - u[0] * v[2]),
                       2.0 * (u[0] * v[1] - u[1] * v[0])};
        double world[3] = {v[0] + w * t[0] + (u[1] * t[2] - u[2] * t[1]),
                           v[1] + w * t[1] + (u[2] * t[0] - u[0] * t[2]),
                           v[2] + w * t[2] + (u[0] * t[1] - u[1] * t[0])};
        Py_ssize_t g = (Py_ssize_t)state[W_SAMPLES], row = g % keep;
        state[W_TURNED] += sqrt(AT(a[1], i, 0) * AT(a[1], i, 0) + AT(a[1], i, 1) * AT(a[1], i, 1) +
                                AT(a[1], i, 2) * AT(a[1], i, 2)) * period;
        for (int k = 0; k < 3; k++) AT(a[6], row, k) = world[k];
        AT(a[6], row, 6) = state[W_TURNED];
        /* the mean of the last ``smooth`` (fewer at first): a running sum (the newest in, the one ``smooth``
         * before out), summed afresh once every ``keep`` samples so that its rounding cannot build up */
        Py_ssize_t count = g + 1 < smooth ? g + 1 : smooth;
        double *sum = &state[W_SUM];
        if (row == 0) {
            for (int k = 0; k < 3; k++) sum[k] = 0.0;
            for (Py_ssize_t m = 0, at = row; m < count; m++, at = at ? at - 1 : keep - 1) {
                for (int k = 0; k < 3; k++) sum[k] += AT(a[6], at, k);
            }
        } else {
            Py_ssize_t out_row = (g - smooth) % keep; /* meaningful only when g >= smooth */
            for (int k = 0; k < 3; k++) sum[k] += world[k] - (g >= smooth ? AT(a[6], out_row, k) : 0.0);
        }
        for (int k = 0; k < 3; k++) AT(a[6], row, 3 + k) = sum[k] / (double)count;
        /* the statistics against their limits (references as at the block's start) */
        double field_norm = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
        int ready = state[W_SAMPLES] * period >= learn_s && state[W_REFERENCE] > 0.0, raw = 0;
        Py_ssize_t slot = (Py_ssize_t)state[W_PENDING];
        for (int j = 0; j < steps; j++) {
            double statistic = NAN, turned = 1.0;
            if (g - widths[j] >= smooth - 1) {
                Py_ssize_t then = (g - widths[j]) % keep;
                double d[3];
                for (int k = 0; k < 3; k++) d[k] = AT(a[6], row, 3 + k) - AT(a[6], then, 3 + k);
                statistic = sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
                turned = AT(a[6], row, 6) - AT(a[6], then, 6) + turn_floor;
            }
            double limit = relative * AT1(a[5], j) * turned;
            limit = limit > AT1(a[3], j) ? limit : AT1(a[3], j);
            raw |= statistic > limit;
            AT(a[7], slot, j) = statistic / turned;
        }
        double deviation = fabs(field_norm - state[W_REFERENCE]);
        double limit = relative * AT1(a[5], steps), floor_ut = tol_pct / 100.0 * state[W_REFERENCE];
        raw |= deviation > (limit > floor_ut ? limit : floor_ut);
        AT(a[7], slot, steps) = deviation;
        raw &= ready;
        /* held for ``hold`` samples after, and the block's calm samples */
        int flagged = raw || state[W_HOLD_LEFT] > 0.0;
        state[W_HOLD_LEFT] = raw ? (double)hold : (state[W_HOLD_LEFT] > 0.0 ? state[W_HOLD_LEFT] - 1.0 : 0.0);
        state[W_RUN] = flagged ? state[W_RUN] + 1.0 : 0.0;
        if (!flagged) {
            AT1(a[8], (Py_ssize_t)state[W_CALM]) = field_norm;
            state[W_CALM] += 1.0;
        }
        state[W_PENDING] += 1.0;
        out[i * stride] = (char)flagged;
        state[W_SAMPLES] += 1.0;
        if ((Py_ssize_t)state[W_SAMPLES] % block == 0) {
            watch_learn(state, &a[5], &a[7], &a[8], period, tau_s, max_reject_s, steps, scratch);
        }
    }
    for (int k = 0; k < W_SIZE; k++) AT1(a[4], k) = state[k];
    PyMem_Free(scratch);
    return 0;
}

static PyObject *watch_update(PyObject *self, PyObject *args) {
    PyObject *o_field, *o_gyr, *o_flagged, *o_state, *o_levels, *o_ring, *o_pending, *o_calm, *o_widths, *o_floors;
    WatchNumbers w;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOdnnndddddd", &o_field, &o_gyr, &o_flagged, &o_state, &o_levels, &o_ring,
                          &o_pending, &o_calm, &o_widths, &o_floors, &w.period, &w.smooth, &w.hold, &w.block,
                          &w.relative, &w.tol_pct, &w.learn_s, &w.tau_s, &w.max_reject_s, &w.turn_floor)) {
        return NULL;
    }
    Array a[9];
    Py_buffer flags;
    if (get_array(o_field, &a[0], 2, -1, 3, 0, "field") < 0) return NULL;
    if (get_array(o_gyr, &a[1], 2, a[0].rows, 3, 0, "gyr") < 0) { release(a, 1); return NULL; }
    if (watch_arrays(a, o_widths, o_floors, o_state, o_levels, o_ring, o_pending, o_calm, w.block) < 0) {
        release(a, 2);
        return NULL;
    }
    if (get_flags(o_flagged, &flags, a[0].rows, "flagged") < 0) { release(a, 9); return NULL; }
    int failed = watch_run(a, &w, (char *)flags.buf, flags.strides[0]);
    PyBuffer_Release(&flags);
    release(a, 9);
    if (failed) return NULL;
    Py_RETURN_NONE;
}

/* numpy's mod (the sign of the divisor; a zero result is +0): np.mod(a, 360.0) as numpy computes it. */
static double mod_360(double a) {
    double m = fmod(a, 360.0);
    if (m != 0.0) {
        if (m < 0.0) m += 360.0;
    } else {
        m = copysign(0.0, 360.0);
    }
    return m;
}

PyDoc_STRVAR(vqf_attitudes_doc,
             "vqf_attitudes(raw, fused, quat, rotation, down, heading, pitch, roll)\n\n"
             "vqf's quaternions raw (S, 4) (body FLU -> ENU, NaN rows where nothing was fused) as the compass uses "
             "them, in one pass (magnet.compass.filters.FusedColumns.from_vqf): fused (S,) bool, the rows that are "
             "finite; quat (S, 4) body FRD -> NED (frames.ned_enu_attitude: w >= 0); rotation (S, 9) its matrix (None: not kept) "
             "(frames.quaternion_to_matrix, row-major; the identity where not fused); down (S, 3) NED down in body "
             "axes (the matrix's last row); heading [0, 360), pitch, roll (S,) deg (frames.matrix_to_euler). Rows "
             "not fused: NaN everywhere but the identity rotation.");

static PyObject *vqf_attitudes(PyObject *self, PyObject *args) {
    PyObject *o_raw, *o_fused, *o_quat, *o_rotation, *o_down, *o_heading, *o_pitch, *o_roll;
    if (!PyArg_ParseTuple(args, "OOOOOOOO", &o_raw, &o_fused, &o_quat, &o_rotation, &o_down, &o_heading, &o_pitch,
                          &o_roll)) {
        return NULL;
    }
    Array a[7];
    Py_buffer fused;
    if (get_array(o_raw, &a[0], 2, -1, 4, 0, "raw") < 0) return NULL;
    Py_ssize_t n = a[0].rows;
    if (get_array(o_quat, &a[1], 2, n, 4, 1, "quat") < 0) { release(a, 1); return NULL; }
    double unkept[9]; /* rotation None: the matrices not kept (every row written here) */
    if (o_rotation == Py_None) {
        raw_array(&a[2], unkept, n, 9, 0);
    } else if (get_array(o_rotation, &a[2], 2, n, 9, 1, "rotation") < 0) {
        release(a, 2);
        return NULL;
    }
    if (get_array(o_down, &a[3], 2, n, 3, 1, "down") < 0) { release(a, 3); return NULL; }
    if (get_array(o_heading, &a[4], 1, n, -1, 1, "heading") < 0) { release(a, 4); return NULL; }
    if (get_array(o_pitch, &a[5], 1, n, -1, 1, "pitch") < 0) { release(a, 5); return NULL; }
    if (get_array(o_roll, &a[6], 1, n, -1, 1, "roll") < 0) { release(a, 6); return NULL; }
    if (get_flags(o_fused, &fused, n, "fused") < 0) { release(a, 7); return NULL; }
    const double h = sqrt(0.5), deg = 180.0 / M_PI;
    char *out = (char *)fused.buf;
    for (Py_ssize_t i = 0; i < n; i++) {
        double r[4] = {AT(a[0], i, 0), AT(a[0], i, 1), AT(a[0], i, 2), AT(a[0], i, 3)};
        int ok = isfinite(r[0]) && isfinite(r[1]) && isfinite(r[2]) && isfinite(r[3]);
        out[i * fused.strides[0]] = (char)ok;
        if (!ok) {
            for (int k = 0; k < 4; k++) AT(a[1], i, k) = NAN;
            for (int k = 0; k < 9; k++) AT(a[2], i, k) = k % 4 == 0 ? 1.0 : 0.0;
            for (int k = 0; k < 3; k++) AT(a[3], i, k) = NAN;
            AT1(a[4], i) = NAN, AT1(a[5], i) = NAN, AT1(a[6], i) = NAN;
            continue;
        }
        /* q_NED_ENU q q_FRD_FLU (frames._NED_ENU_ATTITUDE), then w >= 0 */
        double q[4] = {-h * r[0] - h * r[3], -h * r[1] - h * r[2], -h * r[1] + h * r[2], -h * r[0] + h * r[3]};
        if (q[0] < 0) {
            for (int k = 0; k < 4; k++) q[k] = -q[k];
        }
        double m[9];
        quat_matrix(q, m);
        for (int k = 0; k < 4; k++) AT(a[1], i, k) = q[k];
        for (int k = 0; k < 9; k++) AT(a[2], i, k) = m[k];
        for (int k = 0; k < 3; k++) AT(a[3], i, k) = m[6 + k];
        double sine = -m[6] < -1.0 ? -1.0 : (-m[6] > 1.0 ? 1.0 : -m[6]);
        AT1(a[4], i) = mod_360(atan2(m[3], m[0]) * deg);
        AT1(a[5], i) = asin(sine) * deg;
        AT1(a[6], i) = atan2(m[7], m[8]) * deg;
    }
    PyBuffer_Release(&fused);
    release(a, 7);
    Py_RETURN_NONE;
}

/* One 1-D int64 array (numpy's int64: 'l' or 'q', 8 bytes) of ``rows`` items, read only. */
static int get_int64(PyObject *obj, Py_buffer *view, Py_ssize_t rows, const char *name) {
    if (PyObject_GetBuffer(obj, view, PyBUF_STRIDES | PyBUF_FORMAT) < 0) {
        return -1;
    }
    const char *f = view->format;
    char kind = f == NULL ? 0 : (f[0] == '<' || f[0] == '=' ? f[1] : f[0]);
    if (view->itemsize != 8 || !(kind == 'l' || kind == 'q') || view->ndim != 1 || view->shape[0] != rows) {
        PyErr_Format(PyExc_ValueError, "%s must be a 1-D int64 array of %zd items", name, rows);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

PyDoc_STRVAR(sigma_direct_doc,
             "sigma_direct(field, acc, down_fused, fused, flags, expected, residual, disturbed_bits, max_dip_rad, "
             "uncalibrated_fraction, unlevel_rad, gravity, tan_dip, field_rad, tilt, variance)\n\n"
             "The per-sample part of magnet.attitude.uncertainty.HeadingUncertainty.step, in one pass: field (S, 3) "
             "uT, acc (S, 3) (NaN rows: none), down_fused (S, 3) the fused attitude's down in body axes, used where "
             "fused (S,) bool is set, flags (S,) int64, expected (S,) uT, residual (S,) uT (NaN: no calibration: "
             "uncalibrated_fraction of |B|). Writes tan_dip (S,) |tan(dip)| (dip held at max_dip_rad), field_rad "
             "(S,) the residual over |B_h|, tilt (S,) rad the accelerometer's own tilt error (| |acc| - g | / g, "
             "unlevel_rad without one) and variance (S,) rad^2: field_rad^2 + (tilt tan_dip)^2, plus the flagged "
             "disturbance's (| |B| - expected | / |B_h|)^2 where a flag of disturbed_bits is set.");

static PyObject *sigma_direct(PyObject *self, PyObject *args) {
    PyObject *o_field, *o_acc, *o_down, *o_fused, *o_flags, *o_expected, *o_residual, *o_tan, *o_rad, *o_tilt,
        *o_var;
    long long bits;
    double max_dip, fraction, unlevel, gravity;
    if (!PyArg_ParseTuple(args, "OOOOOOOLddddOOOO", &o_field, &o_acc, &o_down, &o_fused, &o_flags, &o_expected,
                          &o_residual, &bits, &max_dip, &fraction, &unlevel, &gravity, &o_tan, &o_rad, &o_tilt,
                          &o_var)) {
        return NULL;
    }
    Array a[9];
    Py_buffer fused, flags;
    if (get_array(o_field, &a[0], 2, -1, 3, 0, "field") < 0) return NULL;
    Py_ssize_t n = a[0].rows;
    if (get_array(o_acc, &a[1], 2, n, 3, 0, "acc") < 0) { release(a, 1); return NULL; }
    if (get_array(o_down, &a[2], 2, n, 3, 0, "down_fused") < 0) { release(a, 2); return NULL; }
    if (get_array(o_expected, &a[3], 1, n, -1, 0, "expected") < 0) { release(a, 3); return NULL; }
    if (get_array(o_residual, &a[4], 1, n, -1, 0, "residual") < 0) { release(a, 4); return NULL; }
    if (get_array(o_tan, &a[5], 1, n, -1, 1, "tan_dip") < 0) { release(a, 5); return NULL; }
    if (get_array(o_rad, &a[6], 1, n, -1, 1, "field_rad") < 0) { release(a, 6); return NULL; }
    if (get_array(o_tilt, &a[7], 1, n, -1, 1, "tilt") < 0) { release(a, 7); return NULL; }
    if (get_array(o_var, &a[8], 1, n, -1, 1, "variance") < 0) { release(a, 8); return NULL; }
    if (PyObject_GetBuffer(o_fused, &fused, PyBUF_STRIDES | PyBUF_FORMAT) < 0) { release(a, 9); return NULL; }
    if (fused.itemsize != 1 || fused.format == NULL || fused.format[0] != '?' || fused.ndim != 1 ||
        fused.shape[0] != n) {
        PyErr_Format(PyExc_ValueError, "fused must be a 1-D bool array of %zd items", n);
        PyBuffer_Release(&fused);
        release(a, 9);
        return NULL;
    }
    if (get_int64(o_flags, &flags, n, "flags") < 0) { PyBuffer_Release(&fused); release(a, 9); return NULL; }
    for (Py_ssize_t i = 0; i < n; i++) {
        double f[3] = {AT(a[0], i, 0), AT(a[0], i, 1), AT(a[0], i, 2)};
        double g[3] = {AT(a[1], i, 0), AT(a[1], i, 1), AT(a[1], i, 2)};
        double norm_acc = sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2]);
        double d[3];
        if (((char *)fused.buf)[i * fused.strides[0]]) {
            for (int k = 0; k < 3; k++) d[k] = AT(a[2], i, k);
        } else {
            for (int k = 0; k < 3; k++) d[k] = -g[k] / norm_acc;
        }
        if (!(isfinite(d[0]) && isfinite(d[1]) && isfinite(d[2]))) { /* no tilt known: level */
            d[0] = 0.0, d[1] = 0.0, d[2] = 1.0;
        }
        double norm = sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]);
        double sine = (f[0] * d[0] + f[1] * d[1] + f[2] * d[2]) / norm;
        sine = sine < -1.0 ? -1.0 : (sine > 1.0 ? 1.0 : sine);
        double dip = asin(sine);
        dip = isnan(dip) ? 0.0 : dip;
        dip = dip < -max_dip ? -max_dip : (dip > max_dip ? max_dip : dip);
        double horizontal = norm * cos(dip), tan_dip = fabs(tan(dip));
        double residual = AT1(a[4], i);
        residual = isfinite(residual) ? residual : fraction * norm;
        double field_rad = residual / horizontal;
        double tilt = isfinite(norm_acc) ? fabs(norm_acc - gravity) / gravity : unlevel;
        double tilt_share = tilt * tan_dip;
        double variance = field_rad * field_rad + tilt_share * tilt_share;
        long long flag = *(long long *)((char *)flags.buf + i * flags.strides[0]);
        if (flag & bits) {
            double turn = fabs(norm - AT1(a[3], i)) / horizontal;
            if (isfinite(turn)) variance += turn * turn;
        }
        AT1(a[5], i) = tan_dip, AT1(a[6], i) = field_rad, AT1(a[7], i) = tilt, AT1(a[8], i) = variance;
    }
    PyBuffer_Release(&flags);
    PyBuffer_Release(&fused);
    release(a, 9);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(gyro_rows_doc,
             "gyro_rows(gyr, acc, field, limit, present, finite, saturated, usable)\n\n"
             "The compass filters' per-sample checks (magnet.compass.filters.DeviceFilters.update) in one pass over "
             "gyr, acc, field (S, 3): present (S,) bool, a gyroscope row not all NaN; finite, every value of the row "
             "finite; saturated, finite and a value at or beyond +-limit (rad/s); usable, finite, not saturated and "
             "acc's and field's rows finite.");

static PyObject *gyro_rows(PyObject *self, PyObject *args) {
    PyObject *o_gyr, *o_acc, *o_field, *o_out[4];
    double limit;
    if (!PyArg_ParseTuple(args, "OOOdOOOO", &o_gyr, &o_acc, &o_field, &limit, &o_out[0], &o_out[1], &o_out[2],
                          &o_out[3])) {
        return NULL;
    }
    const char *names[4] = {"present", "finite", "saturated", "usable"};
    Array a[3];
    Py_buffer out[4];
    int arrays = 0, got = 0;
    PyObject *result = NULL;
    if (get_array(o_gyr, &a[0], 2, -1, 3, 0, "gyr") < 0) return NULL;
    arrays++;
    Py_ssize_t n = a[0].rows;
    if (get_array(o_acc, &a[1], 2, n, 3, 0, "acc") < 0) goto done;
    arrays++;
    if (get_array(o_field, &a[2], 2, n, 3, 0, "field") < 0) goto done;
    arrays++;
    for (; got < 4; got++) {
        if (get_flags(o_out[got], &out[got], n, names[got]) < 0) goto done;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        double g[3] = {AT(a[0], i, 0), AT(a[0], i, 1), AT(a[0], i, 2)};
        int finite = isfinite(g[0]) && isfinite(g[1]) && isfinite(g[2]);
        int saturated = finite && (fabs(g[0]) >= limit || fabs(g[1]) >= limit || fabs(g[2]) >= limit);
        int others = isfinite(AT(a[1], i, 0)) && isfinite(AT(a[1], i, 1)) && isfinite(AT(a[1], i, 2)) &&
                     isfinite(AT(a[2], i, 0)) && isfinite(AT(a[2], i, 1)) && isfinite(AT(a[2], i, 2));
        ((char *)out[0].buf)[i * out[0].strides[0]] = !(isnan(g[0]) && isnan(g[1]) && isnan(g[2]));
        ((char *)out[1].buf)[i * out[1].strides[0]] = (char)finite;
        ((char *)out[2].buf)[i * out[2].strides[0]] = (char)saturated;
        ((char *)out[3].buf)[i * out[3].strides[0]] = (char)(finite && !saturated && others);
    }
    result = Py_None;
    Py_INCREF(result);
done:
    for (int k = 0; k < got; k++) PyBuffer_Release(&out[k]);
    release(a, arrays);
    return result;
}

PyDoc_STRVAR(disturbance_bits_doc,
             "disturbance_bits(field, acc, expected, dip, expected_dip, field_tol_pct, dip_tol_deg, tiny, flags)\n\n"
             "magnet.attitude.heading.disturbance_flags per sample, in one pass: field (S, 3) uT, acc (S, 3) or "
             "None (no accelerometer: NO_TILT everywhere), expected (S,) uT or None, dip and expected_dip (S,) deg "
             "or None (no dip check). Writes flags (S,) int64: FIELD_DISTURBED where | |B| - expected | > expected "
             "field_tol_pct / 100 and expected > 0; NO_TILT where |acc| is not finite or not above tiny; "
             "DIP_DISTURBED where |dip - expected_dip| > dip_tol_deg and there is a tilt.");

static PyObject *disturbance_bits(PyObject *self, PyObject *args) {
    PyObject *o_field, *o_acc, *o_expected, *o_dip, *o_expected_dip, *o_flags;
    double tol_pct, dip_tol, tiny;
    if (!PyArg_ParseTuple(args, "OOOOOdddO", &o_field, &o_acc, &o_expected, &o_dip, &o_expected_dip, &tol_pct,
                          &dip_tol, &tiny, &o_flags)) {
        return NULL;
    }
    Array a[5];
    PyObject *objs[4] = {o_acc, o_expected, o_dip, o_expected_dip};
    const char *names[4] = {"acc", "expected", "dip", "expected_dip"};
    int have[4] = {0, 0, 0, 0}, arrays = 0;
    Py_buffer flags;
    int got_flags = 0;
    PyObject *result = NULL;
    if (get_array(o_field, &a[0], 2, -1, 3, 0, "field") < 0) return NULL;
    arrays = 1;
    Py_ssize_t n = a[0].rows;
    for (int k = 0; k < 4; k++) {
        if (objs[k] == Py_None) {
            memset(&a[1 + k], 0, sizeof(Array));
            continue;
        }
        if (get_array(objs[k], &a[1 + k], k == 0 ? 2 : 1, n, k == 0 ? 3 : -1, 0, names[k]) < 0) goto done;
        have[k] = 1;
    }
    if (get_int64(o_flags, &flags, n, "flags") < 0) goto done;
    got_flags = 1;
    if (flags.readonly) {
        PyErr_SetString(PyExc_ValueError, "flags must be writable");
        goto done;
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        long long bits = 0;
        if (have[1]) {
            double e = AT1(a[2], i);
            double norm = sqrt(AT(a[0], i, 0) * AT(a[0], i, 0) + AT(a[0], i, 1) * AT(a[0], i, 1) +
                               AT(a[0], i, 2) * AT(a[0], i, 2));
            if (fabs(norm - e) > e * tol_pct / 100.0 && e > 0) bits |= 4; /* FIELD_DISTURBED */
        }
        if (!have[0]) {
            bits |= 2; /* NO_TILT */
        } else {
            double g = sqrt(AT(a[1], i, 0) * AT(a[1], i, 0) + AT(a[1], i, 1) * AT(a[1], i, 1) +
                            AT(a[1], i, 2) * AT(a[1], i, 2));
            int no_tilt = !(isfinite(g) && g > tiny);
            if (no_tilt) bits |= 2;
            if (have[2] && have[3] && !no_tilt && fabs(AT1(a[3], i) - AT1(a[4], i)) > dip_tol) bits |= 8;
        }
        *(long long *)((char *)flags.buf + i * flags.strides[0]) = bits;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    if (got_flags) PyBuffer_Release(&flags);
    for (int k = 0; k < 4; k++) {
        if (have[k]) PyBuffer_Release(&a[1 + k].view);
    }
    release(a, arrays);
    return result;
}

PyDoc_STRVAR(bias_drift_doc,
             "bias_drift(t_ns, trusted, bounds, slot, untrusted, bias, slots, drift)\n\n"
             "The gyroscope's bias drift of magnet.attitude.uncertainty (HeadingUncertainty._drift), batch by batch "
             "in order: t_ns (S,) int64, trusted (S,) bool, bounds (B + 1,) int64; per batch slot (B,) int64, its "
             "device's entry in slots (D,) int64 (the device's last trusted time, ns; updated in place) or -1 (not "
             "fused: skipped), untrusted (B,) bool, bias (B,) rad/s. A batch not untrusted sets its slot to its last "
             "time; in an untrusted one each sample's since is the running maximum of its time where trusted and of "
             "the slot's time (at the batch's start) where not, drift (S,) = bias (t - since) 1e-9 rad, and the slot "
             "takes the last since. Samples of other batches keep their drift.");

static PyObject *bias_drift(PyObject *self, PyObject *args) {
    PyObject *o_t, *o_trusted, *o_bounds, *o_slot, *o_untrusted, *o_bias, *o_slots, *o_drift;
    if (!PyArg_ParseTuple(args, "OOOOOOOO", &o_t, &o_trusted, &o_bounds, &o_slot, &o_untrusted, &o_bias, &o_slots,
                          &o_drift)) {
        return NULL;
    }
    Py_buffer t, trusted, bounds, slot, untrusted, slots;
    Array a[2];
    int got = 0, arrays = 0;
    PyObject *result = NULL;
    if (get_array(o_drift, &a[0], 1, -1, -1, 1, "drift") < 0) return NULL;
    arrays++;
    Py_ssize_t n = a[0].rows;
    if (get_int64(o_t, &t, n, "t_ns") < 0) goto done;
    got = 1;
    if (get_flags(o_trusted, &trusted, n, "trusted") < 0) goto done;
    got = 2;
    if (PyObject_GetBuffer(o_bounds, &bounds, PyBUF_STRIDES | PyBUF_FORMAT) < 0) goto done;
    got = 3;
    Py_ssize_t count = bounds.ndim == 1 ? bounds.shape[0] - 1 : -1;
    PyBuffer_Release(&bounds);
    got = 2;
    if (count < 0) {
        PyErr_SetString(PyExc_ValueError, "bounds must be a 1-D int64 array of B + 1 items");
        goto done;
    }
    if (get_int64(o_bounds, &bounds, count + 1, "bounds") < 0) goto done;
    got = 3;
    if (get_int64(o_slot, &slot, count, "slot") < 0) goto done;
    got = 4;
    if (get_flags(o_untrusted, &untrusted, count, "untrusted") < 0) goto done;
    got = 5;
    if (get_array(o_bias, &a[1], 1, count, -1, 0, "bias") < 0) goto done;
    arrays++;
    if (PyObject_GetBuffer(o_slots, &slots, PyBUF_STRIDES | PyBUF_FORMAT | PyBUF_WRITABLE) < 0) goto done;
    got = 6;
    const char *f = slots.format;
    char kind = f == NULL ? 0 : (f[0] == '<' || f[0] == '=' ? f[1] : f[0]);
    if (slots.itemsize != 8 || !(kind == 'l' || kind == 'q') || slots.ndim != 1) {
        PyErr_SetString(PyExc_ValueError, "slots must be a writable 1-D int64 array");
        goto done;
    }
#define I64(view, i) (*(long long *)((char *)(view).buf + (i) * (view).strides[0]))
#define B8(view, i) (((char *)(view).buf)[(i) * (view).strides[0]])
    for (Py_ssize_t b = 0; b < count; b++) {
        long long lo = I64(bounds, b), hi = I64(bounds, b + 1), k = I64(slot, b);
        if (lo < 0 || hi > n || lo > hi || k >= slots.shape[0]) {
            PyErr_Format(PyExc_ValueError, "batch %zd: samples %lld .. %lld or slot %lld out of range", b, lo, hi, k);
            goto done;
        }
        if (k < 0 || hi == lo) continue;
        if (!B8(untrusted, b)) {
            I64(slots, k) = I64(t, hi - 1);
            continue;
        }
        long long init = I64(slots, k), since = 0;
        double bias = AT1(a[1], b);
        for (long long i = lo; i < hi; i++) {
            long long value = B8(trusted, i) ? I64(t, i) : init;
            since = i == lo || value > since ? value : since;
            AT1(a[0], i) = bias * (double)(I64(t, i) - since) * 1e-9;
        }
        I64(slots, k) = since;
    }
#undef I64
#undef B8
    result = Py_None;
    Py_INCREF(result);
done:
    if (got >= 6) PyBuffer_Release(&slots);
    if (got >= 5) PyBuffer_Release(&untrusted);
    if (got >= 4) PyBuffer_Release(&slot);
    if (got >= 3) PyBuffer_Release(&bounds);
    if (got >= 2) PyBuffer_Release(&trusted);
    if (got >= 1) PyBuffer_Release(&t);
    release(a, arrays);
    return result;
}

PyDoc_STRVAR(sigma_degrees_doc,
             "sigma_degrees(variance, tilt, max_sigma_deg, unlevel_deg, min_tilt_deg, heading_deg, tilt_deg)\n\n"
             "The sigmas in degrees (magnet.attitude.uncertainty): heading_deg (S,) sqrt(variance) (S,) rad^2 at "
             "most max_sigma_deg (that where not finite); tilt_deg (S,) the tilt (S,) rad between min_tilt_deg and "
             "90 (unlevel_deg where NaN).");

static PyObject *sigma_degrees(PyObject *self, PyObject *args) {
    PyObject *o_var, *o_tilt, *o_heading, *o_tilt_deg;
    double max_sigma, unlevel, min_tilt;
    if (!PyArg_ParseTuple(args, "OOdddOO", &o_var, &o_tilt, &max_sigma, &unlevel, &min_tilt, &o_heading,
                          &o_tilt_deg)) {
        return NULL;
    }
    Array a[4];
    if (get_array(o_var, &a[0], 1, -1, -1, 0, "variance") < 0) return NULL;
    Py_ssize_t n = a[0].rows;
    if (get_array(o_tilt, &a[1], 1, n, -1, 0, "tilt") < 0) { release(a, 1); return NULL; }
    if (get_array(o_heading, &a[2], 1, n, -1, 1, "heading_deg") < 0) { release(a, 2); return NULL; }
    if (get_array(o_tilt_deg, &a[3], 1, n, -1, 1, "tilt_deg") < 0) { release(a, 3); return NULL; }
    const double deg = 180.0 / M_PI;
    for (Py_ssize_t i = 0; i < n; i++) {
        double sigma = sqrt(AT1(a[0], i)) * deg;
        AT1(a[2], i) = isfinite(sigma) ? (sigma < max_sigma ? sigma : max_sigma) : max_sigma;
        double tilt = AT1(a[1], i) * deg;
        AT1(a[3], i) = isnan(tilt) ? unlevel : (tilt < min_tilt ? min_tilt : (tilt > 90.0 ? 90.0 : tilt));
    }
    release(a, 4);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(turn_about_down_doc,
             "turn_about_down(quat, angle_deg, out)\n\n"
             "out (S, 4): the attitudes quat (S, 4) wxyz body -> NED turned by angle_deg (S,) about NED down "
             "(frames.rotate_heading: the product (cos h, 0, 0, sin h) q, h half the angle, then w >= 0); NaN rows "
             "stay NaN.");

static PyObject *turn_about_down(PyObject *self, PyObject *args) {
    PyObject *o_quat, *o_angle, *o_out;
    if (!PyArg_ParseTuple(args, "OOO", &o_quat, &o_angle, &o_out)) {
        return NULL;
    }
    Array a[3];
    if (get_array(o_quat, &a[0], 2, -1, 4, 0, "quat") < 0) return NULL;
    Py_ssize_t n = a[0].rows;
    if (get_array(o_angle, &a[1], 1, n, -1, 0, "angle_deg") < 0) { release(a, 1); return NULL; }
    if (get_array(o_out, &a[2], 2, n, 4, 1, "out") < 0) { release(a, 2); return NULL; }
    for (Py_ssize_t i = 0; i < n; i++) {
        double half = AT1(a[1], i) * (M_PI / 180.0) / 2.0;
        double p[4] = {cos(half), 0.0, 0.0, sin(half)};
        double q[4] = {AT(a[0], i, 0), AT(a[0], i, 1), AT(a[0], i, 2), AT(a[0], i, 3)}, r[4];
        quat_mul(p, q, r);
        double sign = r[0] < 0 ? -1.0 : 1.0;
        for (int k = 0; k < 4; k++) AT(a[2], i, k) = r[k] * sign;
    }
    release(a, 3);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(row_faults_doc,
             "row_faults(arr, limit, absent_rows, nonfinite, beyond)\n\n"
             "The raw decoder's value checks (magnet.wire.arrays.value_faults) in one pass over arr (N, k): "
             "nonfinite (N,) bool, a value of the row is not finite (with absent_rows, unless every one is NaN: a "
             "value not known at that sample); beyond (N,) bool, a value of the row is beyond +-limit.");

static PyObject *row_faults(PyObject *self, PyObject *args) {
    PyObject *o_arr, *o_nonfinite, *o_beyond;
    double limit;
    int absent_rows;
    if (!PyArg_ParseTuple(args, "OdpOO", &o_arr, &limit, &absent_rows, &o_nonfinite, &o_beyond)) {
        return NULL;
    }
    Array a;
    Py_buffer nonfinite, beyond;
    if (get_array(o_arr, &a, 2, -1, -1, 0, "arr") < 0) return NULL;
    if (get_flags(o_nonfinite, &nonfinite, a.rows, "nonfinite") < 0) { release(&a, 1); return NULL; }
    if (get_flags(o_beyond, &beyond, a.rows, "beyond") < 0) {
        PyBuffer_Release(&nonfinite);
        release(&a, 1);
        return NULL;
    }
    char *out_nonfinite = nonfinite.buf, *out_beyond = beyond.buf;
    if (a.cols == 3 && a.view.strides[1] == 8 && a.view.strides[0] == 24 && nonfinite.strides[0] == 1 &&
        beyond.strides[0] == 1) { /* the usual (S, 3) C-contiguous rows: the same tests without the strides' sums */
        const double *row = a.view.buf;
        for (Py_ssize_t i = 0; i < a.rows; i++, row += 3) {
            double x = row[0], y = row[1], z = row[2];
            int finite = isfinite(x) && isfinite(y) && isfinite(z);
            int all_nan = isnan(x) && isnan(y) && isnan(z);
            out_nonfinite[i] = (char)!(finite || (absent_rows && all_nan));
            out_beyond[i] = (char)(fabs(x) > limit || fabs(y) > limit || fabs(z) > limit);
        }
        PyBuffer_Release(&beyond);
        PyBuffer_Release(&nonfinite);
        release(&a, 1);
        Py_RETURN_NONE;
    }
    for (Py_ssize_t i = 0; i < a.rows; i++) {
        int finite = 1, all_nan = 1, over = 0;
        for (Py_ssize_t k = 0; k < a.cols; k++) {
            double v = AT(a, i, k);
            finite &= isfinite(v) != 0;
            all_nan &= isnan(v) != 0;
            over |= fabs(v) > limit;
        }
        ((char *)nonfinite.buf)[i * nonfinite.strides[0]] = (char)!(finite || (absent_rows && all_nan));
        ((char *)beyond.buf)[i * beyond.strides[0]] = (char)over;
    }
    PyBuffer_Release(&beyond);
    PyBuffer_Release(&nonfinite);
    release(&a, 1);
    Py_RETURN_NONE;
}

/* -acc / |acc| as heading.py's _down computes it (acc times -1 / |acc|; NaN where |acc| <= 1e-12 or not finite). */
static void down_of(const double f[3], double d[3]) {
    double norm = sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2]);
    double scale = norm > 1e-12 ? -1.0 / norm : NAN;
    d[0] = f[0] * scale, d[1] = f[1] * scale, d[2] = f[2] * scale;
}

PyDoc_STRVAR(tilt_heading_doc,
             "tilt_heading(field, acc, heading, dip)\n\n"
             "magnet.attitude.heading's per-sample maths over field (N, 3) and acc (N, 3), body frame: heading (N,) "
             "the tilt-compensated heading in [0, 360) (atan2(e_x, n_x), e = d x B, n = e x d, d = -acc / |acc|; "
             "NaN without a usable acc), and dip (N,) deg asin(B . d / |B|), unless dip is None.");

static PyObject *tilt_heading(PyObject *self, PyObject *args) {
    PyObject *o_field, *o_acc, *o_heading, *o_dip;
    if (!PyArg_ParseTuple(args, "OOOO", &o_field, &o_acc, &o_heading, &o_dip)) {
        return NULL;
    }
    Array a[4];
    int with_heading = o_heading != Py_None, with_dip = o_dip != Py_None, count = 2;
    if (get_array(o_field, &a[0], 2, -1, 3, 0, "field") < 0) return NULL;
    Py_ssize_t n = a[0].rows;
    if (get_array(o_acc, &a[1], 2, n, 3, 0, "acc") < 0) { release(a, 1); return NULL; }
    if (with_heading) {
        if (get_array(o_heading, &a[count], 1, n, -1, 1, "heading") < 0) { release(a, count); return NULL; }
        count++;
    }
    if (with_dip) {
        if (get_array(o_dip, &a[count], 1, n, -1, 1, "dip") < 0) { release(a, count); return NULL; }
        count++;
    }
    const double deg = 180.0 / M_PI;
    for (Py_ssize_t i = 0; i < n; i++) {
        double b[3] = {AT(a[0], i, 0), AT(a[0], i, 1), AT(a[0], i, 2)};
        double g[3] = {AT(a[1], i, 0), AT(a[1], i, 1), AT(a[1], i, 2)}, d[3];
        down_of(g, d);
        if (with_heading) {
            double ex = d[1] * b[2] - d[2] * b[1], ey = d[2] * b[0] - d[0] * b[2], ez = d[0] * b[1] - d[1] * b[0];
            double h = mod_360(atan2(ex, ey * d[2] - ez * d[1]) * deg);
            AT1(a[2], i) = h >= 360.0 ? 0.0 : h;
        }
        if (with_dip) {
            double sine = (b[0] * d[0] + b[1] * d[1] + b[2] * d[2]) / sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2]);
            sine = sine < -1.0 ? -1.0 : (sine > 1.0 ? 1.0 : sine);
            AT1(a[count - 1], i) = asin(sine) * deg;
        }
    }
    release(a, count);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(column_checks_doc,
             "column_checks(matrix, out)\n\n"
             "Per column j of matrix (N, K) float64, in one pass over its rows: out[j, 0] the largest |x| of its finite "
             "values (0 with none), out[j, 1] how many are NaN, out[j, 2] how many are infinite (out (K, 3) float64). "
             "What a CSV reader checks of a table of numbers (services.common.inputs.csvio), without three numpy "
             "reductions along the table's short axis.");

static PyObject *column_checks(PyObject *self, PyObject *args) {
    PyObject *o_matrix, *o_out;
    if (!PyArg_ParseTuple(args, "OO", &o_matrix, &o_out)) {
        return NULL;
    }
    Array a[2];
    if (get_array(o_matrix, &a[0], 2, -1, -1, 0, "matrix") < 0) return NULL;
    if (get_array(o_out, &a[1], 2, a[0].cols, 3, 1, "out") < 0) { release(a, 1); return NULL; }
    for (Py_ssize_t j = 0; j < a[0].cols; j++) AT(a[1], j, 0) = AT(a[1], j, 1) = AT(a[1], j, 2) = 0.0;
    for (Py_ssize_t i = 0; i < a[0].rows; i++) { /* row by row: the table's own order in memory */
        for (Py_ssize_t j = 0; j < a[0].cols; j++) {
            double x = fabs(AT(a[0], i, j));
            if (x <= DBL_MAX) {
                if (x > AT(a[1], j, 0)) AT(a[1], j, 0) = x;
            } else {
                AT(a[1], j, isnan(x) ? 1 : 2) += 1.0;
            }
        }
    }
    release(a, 2);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(format_rows_doc,
             "format_rows(matrix, decimals) -> bytes\n\n"
             "The CSV lines of matrix (N, K) float64: column j printed as Python's '%.{d}f' % x for d = decimals[j] "
             ">= 0 (correctly rounded, as Python and printf: the exact binary value, ties to even), as '%d' % x for "
             "d = -1; 'nan', 'inf', '-inf' as Python writes them; values joined by ',', each row ended by '\\n'.");

/* Room for ``more`` bytes at ``*pos`` in ``*buf`` of ``*size`` bytes (doubled as needed); -1 on no memory. */
static int room(char **buf, Py_ssize_t *size, Py_ssize_t pos, Py_ssize_t more) {
    if (pos + more <= *size) return 0;
    Py_ssize_t grown = *size;
    while (pos + more > grown) grown *= 2;
    char *bigger = PyMem_Realloc(*buf, grown);
    if (bigger == NULL) { PyErr_NoMemory(); return -1; }
    *buf = bigger;
    *size = grown;
    return 0;
}

/* The number of decimal digits of ``v`` (1 for 0). */
static int digit_count(unsigned long long v) {
    int n = 1;
    while (v >= 10000) { v /= 10000; n += 4; }
    return v < 10 ? n : v < 100 ? n + 1 : v < 1000 ? n + 2 : n + 3;
}

/* "0000" .. "9999": four digits a step (made at import, ``PyInit__kernels``), and 4 bytes of slack after the last so
 * that a copy of 4 bytes starting inside the last quad stays inside the table */
static char digit_quads[40004];

static void make_digit_quads(void) {
    for (int v = 0; v < 10000; v++) {
        digit_quads[4 * v] = (char)('0' + v / 1000);
        digit_quads[4 * v + 1] = (char)('0' + v / 100 % 10);
        digit_quads[4 * v + 2] = (char)('0' + v / 10 % 10);
        digit_quads[4 * v + 3] = (char)('0' + v % 10);
    }
}

/* The last ``n`` (1 to 4) digits of the quad of ``q`` (q < 10^n) at ``out``: one copy of 4 bytes, of which the
 * 4 - n past the digits are scratch that the caller writes over next (``format_rows`` keeps room for them). */
static inline char *put_quad_tail(unsigned q, int n, char *out) {
    memcpy(out, digit_quads + 4 * q + 4 - n, 4);
    return out + n;
}

/* The digits of ``v`` at ``out`` (no zeros in front); returns the end. The usual values (below 10^4) in one copy;
 * larger ones four digits a division, from the last backwards. */
static inline char *put_digits(unsigned long long v, char *out) {
    if (v < 10000) {
        int k = v < 10 ? 1 : v < 100 ? 2 : v < 1000 ? 3 : 4;
        return put_quad_tail((unsigned)v, k, out);
    }
    int n = digit_count(v);
    char *p = out + n;
    while (v >= 10000) {
        unsigned q = (unsigned)(v % 10000);
        v /= 10000;
        p -= 4;
        memcpy(p, digit_quads + 4 * q, 4);
    }
    int k = v < 10 ? 1 : v < 100 ? 2 : v < 1000 ? 3 : 4;
    memcpy(p - k, digit_quads + 4 * v + 4 - k, (size_t)k);
    return out + n;
}

/* ``v`` (v < 10^d, d <= 9) as exactly ``d`` digits (zeros in front) at ``out``; returns the end. */
static inline char *put_fraction(unsigned long long v, int d, char *out) {
    switch (d) { /* constant divisors: a multiplication, not a division (tens of cycles) a value */
        case 0: return out;
        case 1: case 2: case 3: case 4: return put_quad_tail((unsigned)v, d, out);
        case 5: case 6: case 7: case 8:
            out = put_quad_tail((unsigned)(v / 10000), d - 4, out);
            return put_quad_tail((unsigned)(v % 10000), 4, out);
        default:
            out = put_quad_tail((unsigned)(v / 100000000), 1, out);
            out = put_quad_tail((unsigned)(v / 10000 % 10000), 4, out);
            return put_quad_tail((unsigned)(v % 10000), 4, out);
    }
}

/* x with ``d`` decimals (d <= 9) at ``out`` where the rounding of x * 10^d cannot differ from that of the exact value
 * (an integer path); returns the bytes written (at most 26, and 4 of scratch past them), or -1 where it can differ or
 * x is not finite (``fixed`` then asks printf). Inlined with a constant ``d`` by ``format_column``. */
static inline __attribute__((always_inline)) int fast_fixed(double x, int d, char *out) {
    static const double tens[] = {1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9};
    static const unsigned long long powers[] = {1ULL, 10ULL, 100ULL, 1000ULL, 10000ULL, 100000ULL, 1000000ULL,
                                                10000000ULL, 100000000ULL, 1000000000ULL};
    double scaled = fabs(x) * tens[d];
    if (!(scaled < 1e15)) return -1; /* NaN fails this too */
    /* below 2^53 the conversion truncates to floor(scaled) exactly, without a call to floor */
    unsigned long long whole = (unsigned long long)scaled;
    double frac = scaled - (double)whole;
    if (!(fabs(frac - 0.5) > scaled * 1e-15 + 1e-12)) return -1;
    unsigned long long r = whole + (frac > 0.5);
    unsigned long long units = r / powers[d]; /* a constant divisor once inlined: a multiplication */
    char *p = out;
    *p = '-';
    p += signbit(x) != 0;
    p = put_digits(units, p);
    if (d > 0) {
        *p++ = '.';
        p = put_fraction(r - units * powers[d], d, p);
    }
    return (int)(p - out);
}

/* '%d' % x (Python's: x truncated) at ``out`` for |x| < 9e18; returns the bytes written (at most 20, and 4 of
 * scratch past them), or -1 for any other x (``fixed`` with 0 decimals then writes it, as Python's '%d' would not:
 * format_rows' doc). */
static inline __attribute__((always_inline)) int fast_integer(double x, char *out) {
    if (!(fabs(x) < 9e18)) return -1;
    long long v = (long long)x;
    char *p = out;
    *p = '-';
    p += v < 0;
    return (int)(put_digits(v < 0 ? (unsigned long long)(-(v + 1)) + 1 : (unsigned long long)v, p) - out);
}

/* x with ``d`` decimals (0 .. 20) at ``out`` (room for 400 bytes and 4 of scratch past them); returns the bytes
 * written: ``fast_fixed`` where it can, printf (correctly rounded, as Python) elsewhere. */
static int fixed(double x, int d, char *out) {
    int n = d <= 9 ? fast_fixed(x, d, out) : -1;
    if (n >= 0) return n;
    if (isnan(x)) { memcpy(out, "nan", 3); return 3; }
    if (isinf(x)) { if (x < 0) { memcpy(out, "-inf", 4); return 4; } memcpy(out, "inf", 3); return 3; }
    return snprintf(out, 400, "%.*f", d, x);
}

/* ``format_rows`` a block at a time: each value in a slot of its own, column by column (so that each loop has one
 * constant number of decimals), then the slots' bytes joined row by row */
#define FORMAT_SLOT 32
#define FORMAT_BLOCK 256

/* Rows lo .. hi of column j of ``a`` into their slots (row r - lo at ``slots + (r - lo) * stride``), their lengths
 * into ``lengths`` (same steps); -1 where ``format_rows`` must write the value itself (``fixed``). */
static void format_column(const Array *a, Py_ssize_t j, Py_ssize_t lo, Py_ssize_t hi, int d, char *slots,
                          int *lengths, Py_ssize_t step) {
#define FORMAT_LOOP(CALL)                                                           \
    for (Py_ssize_t i = lo; i < hi; i++) {                                          \
        double x = AT(*a, i, j);                                                    \
        lengths[(i - lo) * step] = CALL(x, slots + (i - lo) * step * FORMAT_SLOT); \
    }
#define FORMAT_D(D) \
    case D: { FORMAT_LOOP(FORMAT_FIXED_##D) break; }
#define FORMAT_FIXED_0(x, out) fast_fixed(x, 0, out)
#define FORMAT_FIXED_1(x, out) fast_fixed(x, 1, out)
#define FORMAT_FIXED_2(x, out) fast_fixed(x, 2, out)
#define FORMAT_FIXED_3(x, out) fast_fixed(x, 3, out)
#define FORMAT_FIXED_4(x, out) fast_fixed(x, 4, out)
#define FORMAT_FIXED_5(x, out) fast_fixed(x, 5, out)
#define FORMAT_FIXED_6(x, out) fast_fixed(x, 6, out)
#define FORMAT_FIXED_7(x, out) fast_fixed(x, 7, out)
#define FORMAT_FIXED_8(x, out) fast_fixed(x, 8, out)
#define FORMAT_FIXED_9(x, out) fast_fixed(x, 9, out)
#define FORMAT_NONE(x, out) ((void)(x), (void)(out), -1)
    switch (d) {
        case -1: { FORMAT_LOOP(fast_integer) break; }
        FORMAT_D(0) FORMAT_D(1) FORMAT_D(2) FORMAT_D(3) FORMAT_D(4)
        FORMAT_D(5) FORMAT_D(6) FORMAT_D(7) FORMAT_D(8) FORMAT_D(9)
        default: { FORMAT_LOOP(FORMAT_NONE) break; }
    }
}

static PyObject *format_rows(PyObject *self, PyObject *args) {
    PyObject *o_matrix;
    Py_buffer decimals;
    if (!PyArg_ParseTuple(args, "Oy*", &o_matrix, &decimals)) {
        return NULL;
    }
    Array a;
    if (get_array(o_matrix, &a, 2, -1, decimals.len, 0, "matrix") < 0) { PyBuffer_Release(&decimals); return NULL; }
    const signed char *dec = (const signed char *)decimals.buf;
    for (Py_ssize_t j = 0; j < decimals.len; j++) {
        if (dec[j] < -1 || dec[j] > 20) {
            PyErr_SetString(PyExc_ValueError, "decimals must be -1 (an integer) or 0 .. 20");
            release(&a, 1);
            PyBuffer_Release(&decimals);
            return NULL;
        }
    }
    Py_ssize_t size = 64 + a.rows * a.cols * 12, pos = 0, cols = a.cols;
    char *buf = PyMem_Malloc(size);
    char *slots = PyMem_Malloc((size_t)(FORMAT_BLOCK * (cols ? cols : 1) * FORMAT_SLOT));
    int *lengths = PyMem_Malloc((size_t)(FORMAT_BLOCK * (cols ? cols : 1)) * sizeof(int));
    if (buf == NULL || slots == NULL || lengths == NULL) {
        PyMem_Free(buf), PyMem_Free(slots), PyMem_Free(lengths);
        release(&a, 1);
        PyBuffer_Release(&decimals);
        return PyErr_NoMemory();
    }
    for (Py_ssize_t lo = 0; lo < a.rows; lo += FORMAT_BLOCK) {
        Py_ssize_t hi = lo + FORMAT_BLOCK < a.rows ? lo + FORMAT_BLOCK : a.rows;
        for (Py_ssize_t j = 0; j < cols; j++) format_column(&a, j, lo, hi, dec[j], slots + j * FORMAT_SLOT, lengths + j, cols);
        for (Py_ssize_t i = lo; i < hi; i++) {
            if (room(&buf, &size, pos, 420 * cols) < 0) {
                PyMem_Free(buf), PyMem_Free(slots), PyMem_Free(lengths);
                release(&a, 1);
                PyBuffer_Release(&decimals);
                return NULL;
            }
            const char *slot = slots + (i - lo) * cols * FORMAT_SLOT;
            const int *length = lengths + (i - lo) * cols;
            for (Py_ssize_t j = 0; j < cols; j++, slot += FORMAT_SLOT) {
                if (length[j] >= 0) {
                    memcpy(buf + pos, slot, FORMAT_SLOT); /* the bytes past its length are written over next */
                    pos += length[j];
                } else {
                    pos += fixed(AT(a, i, j), dec[j] < 0 ? 0 : dec[j], buf + pos);
                }
                buf[pos++] = j + 1 < cols ? ',' : '\n';
            }
        }
    }
    PyMem_Free(slots);
    PyMem_Free(lengths);
    PyObject *out = PyBytes_FromStringAndSize(buf, pos);
    PyMem_Free(buf);
    release(&a, 1);
    PyBuffer_Release(&decimals);
    return out;
}

/* ------------------------------------------------------------------------------------------------------------
 * The velocity-aided filter (magnet.attitude.aided_fusion), whole batches at a time, driving vqf's own compiled
 * filter: the C++ VQF object inside the Python ``vqf.VQF`` it is given, through the functions vqf's wheel exports
 * (``vqf_bind``). No copy of vqf: the same object, the same machine code as ``VQF.updateBatch``; the Python side
 * keeps using that object as it did. The aided filter's own state lives in float64 arrays its Python objects hold
 * (views: ``AidedFilter.state``), laid out by the A_* and S_* indices below, mirrored in aided_fusion.py. */
#include <dlfcn.h>
#include <stdbool.h>
#include <stddef.h>
#include <stdlib.h>

/* vqf's VQFParams and VQFState (vqf/cpp/vqf.hpp, double precision, motion bias estimation on: the wheel's build).
 * ``vqf_bind`` checks their sizes against the object's own layout, the tests compare the fields with VQF.state. */
typedef struct {
    double tauAcc, tauMag;
    bool motionBiasEstEnabled, restBiasEstEnabled, magDistRejectionEnabled;
    double biasSigmaInit, biasForgettingTime, biasClip, biasSigmaMotion, biasVerticalForgettingFactor, biasSigmaRest,
        restMinT, restFilterTau, restThGyr, restThAcc, magCurrentTau, magRefTau, magNormTh, magDipTh, magNewTime,
        magNewFirstTime, magNewMinGyr, magMinUndisturbedTime, magMaxRejectionTime, magRejectionFactor;
} VqfParams;

typedef struct {
    double gyrQuat[4], accQuat[4], delta;
    bool restDetected, magDistDetected;
    double lastAccLp[3], accLpState[6], lastAccCorrAngularRate, kMagInit, lastMagDisAngle, lastMagCorrAngularRate,
        bias[3], biasP[9], motionBiasEstRLpState[18], motionBiasEstBiasLpState[4], restLastSquaredDeviations[2],
        restT, restLastGyrLp[3], restGyrLpState[6], restLastAccLp[3], restAccLpState[6], magRefNorm, magRefDip,
        magUndisturbedT, magRejectT, magCandidateNorm, magCandidateDip, magCandidateT, magNormDip[2],
        magNormDipLpState[4];
} VqfState;

static struct {
    int ready;
    void (*update_batch)(void *, const double *, const double *, const double *, size_t, double *, double *,
                         double *, double *, double *, bool *, bool *);
    void (*get_quat9d)(const void *, double *);
    void (*get_quat6d)(const void *, double *);
    double (*get_bias)(const void *, double *);
    void (*set_bias)(void *, double *, double);
    double (*get_delta)(const void *);
    void (*set_tau_acc)(void *, double);
    void (*set_rest)(void *, bool);
    const VqfParams *(*get_params)(const void *);
    const VqfState *(*get_state)(const void *);
    const void *(*get_coeffs)(const void *);
} vqf_api;

static const char *vqf_symbols[] = {
    "_ZN3VQF11updateBatchEPKdS1_S1_mPdS2_S2_S2_S2_PbS3_", "_ZNK3VQF9getQuat9DEPd", "_ZNK3VQF15getBiasEstimateEPd",
    "_ZN3VQF15setBiasEstimateEPdd", "_ZNK3VQF8getDeltaEv", "_ZN3VQF9setTauAccEd", "_ZN3VQF21setRestBiasEstEnabledEb",
    "_ZNK3VQF9getParamsEv", "_ZNK3VQF8getStateEv", "_ZNK3VQF9getCoeffsEv", "_ZNK3VQF9getQuat6DEPd",
};

PyDoc_STRVAR(vqf_bind_doc,
             "vqf_bind(path)\n\n"
             "Find vqf's compiled filter in its extension module at ``path`` (``vqf.vqf.__file__``, loaded already): "
             "the functions of its C++ class VQF that the aided filter calls. RuntimeError when one is missing.");

static PyObject *vqf_bind(PyObject *self, PyObject *args) {
    const char *path;
    if (!PyArg_ParseTuple(args, "s", &path)) return NULL;
    if (vqf_api.ready) Py_RETURN_NONE;
    void *lib = dlopen(path, RTLD_NOW | RTLD_NOLOAD);
    if (lib == NULL) lib = dlopen(path, RTLD_NOW | RTLD_LOCAL);
    if (lib == NULL) return PyErr_Format(PyExc_RuntimeError, "cannot open vqf's module %s: %s", path, dlerror());
    void **slots[] = {
        (void **)&vqf_api.update_batch, (void **)&vqf_api.get_quat9d, (void **)&vqf_api.get_bias,
        (void **)&vqf_api.set_bias,     (void **)&vqf_api.get_delta,  (void **)&vqf_api.set_tau_acc,
        (void **)&vqf_api.set_rest,     (void **)&vqf_api.get_params, (void **)&vqf_api.get_state,
        (void **)&vqf_api.get_coeffs,   (void **)&vqf_api.get_quat6d,
    };
    for (size_t i = 0; i < sizeof(slots) / sizeof(slots[0]); i++) {
        *slots[i] = dlsym(lib, vqf_symbols[i]);
        if (*slots[i] == NULL) {
            return PyErr_Format(PyExc_RuntimeError,
                                "vqf's module %s lacks %s: magnet's aided filter needs vqf 2.1 (pip install "
                                "'vqf>=2.1,<2.2')", path, vqf_symbols[i]);
        }
    }
    vqf_api.ready = 1;
    Py_RETURN_NONE;
}

/* The C++ VQF inside a Python vqf.VQF (Cython: the object's one field, ``c_obj``), its layout checked. */
static void *vqf_object(PyObject *obj) {
    PyTypeObject *type = Py_TYPE(obj);
    if (!vqf_api.ready) {
        PyErr_SetString(PyExc_RuntimeError, "vqf_bind was not called");
        return NULL;
    }
    if (strcmp(type->tp_name, "vqf.vqf.VQF") != 0 || type->tp_basicsize != sizeof(PyObject) + sizeof(void *)) {
        PyErr_Format(PyExc_TypeError, "expected a vqf.VQF, got %s", type->tp_name);
        return NULL;
    }
    void *vqf = *(void **)((char *)obj + sizeof(PyObject));
    const char *params = (const char *)vqf_api.get_params(vqf), *state = (const char *)vqf_api.get_state(vqf);
    const char *coeffs = (const char *)vqf_api.get_coeffs(vqf);
    if (vqf == NULL || state - params != (ptrdiff_t)sizeof(VqfParams) ||
        coeffs - state != (ptrdiff_t)sizeof(VqfState)) {
        PyErr_SetString(PyExc_RuntimeError, "vqf's VQF object is not laid out as magnet was built for (vqf 2.1)");
        return NULL;
    }
    return vqf;
}

PyDoc_STRVAR(vqf_probe_doc,
             "vqf_probe(filter) -> dict\n\n"
             "The fields of a vqf.VQF's state and parameters this module reads or writes, read through its C++ "
             "object (for tests: they must equal VQF.state and VQF.params).");

static PyObject *vqf_probe(PyObject *self, PyObject *args) {
    PyObject *obj;
    if (!PyArg_ParseTuple(args, "O", &obj)) return NULL;
    void *vqf = vqf_object(obj);
    if (vqf == NULL) return NULL;
    const VqfState *s = vqf_api.get_state(vqf);
    const VqfParams *p = vqf_api.get_params(vqf);
    PyObject *bias_p = PyList_New(9);
    if (bias_p == NULL) return NULL;
    for (int i = 0; i < 9; i++) PyList_SET_ITEM(bias_p, i, PyFloat_FromDouble(s->biasP[i]));
    return Py_BuildValue("{s:d,s:(ddd),s:N,s:O,s:d,s:d,s:d,s:(dd),s:d,s:d,s:d,s:O}", "delta", s->delta, "bias",
                         s->bias[0], s->bias[1], s->bias[2], "biasP", bias_p, "magDistDetected",
                         s->magDistDetected ? Py_True : Py_False, "magCandidateNorm", s->magCandidateNorm,
                         "magCandidateDip", s->magCandidateDip, "magCandidateT", s->magCandidateT, "magNormDip",
                         s->magNormDip[0], s->magNormDip[1], "magNormTh", p->magNormTh, "magDipTh", p->magDipTh,
                         "tauAcc", p->tauAcc, "restBiasEstEnabled", p->restBiasEstEnabled ? Py_True : Py_False);
}

static double radians(double deg) { return deg * (M_PI / 180.0); }

/* numpy's sum of n doubles ``stride`` apart (its pairwise summation: the same rounding as np.mean). */
static double pairwise_sum(const double *a, Py_ssize_t n, Py_ssize_t stride) {
    if (n < 8) {
        double res = 0.0;
        for (Py_ssize_t i = 0; i < n; i++) res += a[i * stride];
        return res;
    }
    if (n <= 128) {
        double r[8], res;
        Py_ssize_t i;
        for (int k = 0; k < 8; k++) r[k] = a[k * stride];
        for (i = 8; i < n - (n % 8); i += 8) {
            for (int k = 0; k < 8; k++) r[k] += a[(i + k) * stride];
        }
        res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        for (; i < n; i++) res += a[i * stride];
        return res;
    }
    Py_ssize_t n2 = n / 2;
    n2 -= n2 % 8;
    return pairwise_sum(a, n2, stride) + pairwise_sum(a + n2 * stride, n - n2, stride);
}

PyDoc_STRVAR(batch_figures_doc,
             "batch_figures(bounds, t_ns, fused, trusted, tan_dip, horizontal, out)\n\n"
             "The per-batch figures of magnet.attitude.uncertainty (_Batches.of) in one pass: batches b of samples "
             "bounds[b] .. bounds[b + 1] (bounds (B + 1,) int64), t_ns (S,) int64, fused and trusted (S,) bool, "
             "tan_dip (S,), horizontal (S, 2) (north, east; g). Writes out (B, 7): the fused samples, their mean "
             "tan_dip, the fused samples whose horizontal force is finite (known), their mean time (s since the "
             "epoch: the mean of (t - t_ns[0]) 1e-9, plus t_ns[0] 1e-9), mean north and east force, and the fused "
             "samples not trusted; each sum as numpy's add.reduceat along a row gives it (the first value plus the "
             "pairwise sum of the rest); an empty batch 0 (its means NaN).");

static PyObject *batch_figures(PyObject *self, PyObject *args) {
    PyObject *o_bounds, *o_t, *o_fused, *o_trusted, *o_tan, *o_horizontal, *o_out;
    if (!PyArg_ParseTuple(args, "OOOOOOO", &o_bounds, &o_t, &o_fused, &o_trusted, &o_tan, &o_horizontal, &o_out)) {
        return NULL;
    }
    Py_buffer bounds, t, fused, trusted;
    Array a[3];
    int got = 0, arrays = 0;
    PyObject *result = NULL;
    double *scratch = NULL;
    if (get_array(o_tan, &a[0], 1, -1, -1, 0, "tan_dip") < 0) return NULL;
    arrays++;
    Py_ssize_t n = a[0].rows;
    if (get_array(o_horizontal, &a[1], 2, n, 2, 0, "horizontal") < 0) goto done;
    arrays++;
    if (get_array(o_out, &a[2], 2, -1, 7, 1, "out") < 0) goto done;
    arrays++;
    Py_ssize_t count = a[2].rows;
    if (get_int64(o_bounds, &bounds, count + 1, "bounds") < 0) goto done;
    got = 1;
    if (get_int64(o_t, &t, n, "t_ns") < 0) goto done;
    got = 2;
    if (get_flags(o_fused, &fused, n, "fused") < 0) goto done;
    got = 3;
    if (get_flags(o_trusted, &trusted, n, "trusted") < 0) goto done;
    got = 4;
#define I64(view, i) (*(long long *)((char *)(view).buf + (i) * (view).strides[0]))
#define B8(view, i) (((char *)(view).buf)[(i) * (view).strides[0]])
    Py_ssize_t longest = 0;
    for (Py_ssize_t b = 0; b < count; b++) {
        long long lo = I64(bounds, b), hi = I64(bounds, b + 1);
        if (lo < 0 || hi > n || lo > hi) {
            PyErr_Format(PyExc_ValueError, "batch %zd: samples %lld .. %lld out of range", b, lo, hi);
            goto done;
        }
        longest = hi - lo > longest ? hi - lo : longest;
    }
    scratch = PyMem_Malloc(sizeof(double) * (size_t)(7 * longest + 1));
    if (scratch == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    long long t0 = n ? I64(t, 0) : 0;
    for (Py_ssize_t b = 0; b < count; b++) {
        long long lo = I64(bounds, b), hi = I64(bounds, b + 1);
        Py_ssize_t m = (Py_ssize_t)(hi - lo);
        double sums[7] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
        if (m > 0) {
            for (Py_ssize_t j = 0; j < m; j++) { /* the rows of _Batches.of, row r at scratch + r * m */
                Py_ssize_t i = (Py_ssize_t)lo + j;
                int f = B8(fused, i) != 0;
                double north = AT(a[1], i, 0), east = AT(a[1], i, 1);
                int known = f && isfinite(north) && isfinite(east);
                scratch[j] = f;
                scratch[m + j] = f ? AT1(a[0], i) : 0.0;
                scratch[2 * m + j] = known;
                scratch[3 * m + j] = known ? (double)(I64(t, i) - t0) * 1e-9 : 0.0;
                scratch[4 * m + j] = known ? north : 0.0;
                scratch[5 * m + j] = known ? east : 0.0;
                scratch[6 * m + j] = f && !B8(trusted, i);
            }
            for (int r = 0; r < 7; r++) sums[r] = scratch[r * m] + pairwise_sum(scratch + r * m + 1, m - 1, 1);
        }
        AT(a[2], b, 0) = sums[0];
        AT(a[2], b, 1) = sums[1] / sums[0];
        AT(a[2], b, 2) = sums[2];
        AT(a[2], b, 3) = sums[3] / sums[2] + (double)t0 * 1e-9;
        AT(a[2], b, 4) = sums[4] / sums[2];
        AT(a[2], b, 5) = sums[5] / sums[2];
        AT(a[2], b, 6) = sums[6];
    }
#undef I64
#undef B8
    result = Py_None;
    Py_INCREF(result);
done:
    PyMem_Free(scratch);
    if (got >= 4) PyBuffer_Release(&trusted);
    if (got >= 3) PyBuffer_Release(&fused);
    if (got >= 2) PyBuffer_Release(&t);
    if (got >= 1) PyBuffer_Release(&bounds);
    release(a, arrays);
    return result;
}

/* ---- the velocity fixes (aiding.VelocityFixes): times (cap,) and values (cap, 3) buffers, the visible fixes
 * [start, start + count); meta (6,): start, count, whether a value is held, the held value (3). */
enum { F_START, F_COUNT, F_HELD_VALID, F_HELD, F_SIZE = 6 };

typedef struct {
    double *meta, *times, *values;
    Py_ssize_t cap;
} Fixes;

/* Whether the held velocity row v is a new fix: finite and unlike the row before (prev; NULL: the held one). */
static int fix_arrives(const double *meta, const double *v, const double *prev) {
    if (!(isfinite(v[0]) && isfinite(v[1]) && isfinite(v[2]))) return 0;
    if (prev == NULL) {
        if (meta[F_HELD_VALID] == 0.0) return 1;
        prev = meta + F_HELD;
    }
    return v[0] != prev[0] || v[1] != prev[1] || v[2] != prev[2];
}

static void fix_append(Fixes *f, double t, const double *v, Py_ssize_t max_fixes) {
    Py_ssize_t start = (Py_ssize_t)f->meta[F_START], count = (Py_ssize_t)f->meta[F_COUNT];
    if (start + count >= f->cap) {
        memmove(f->times, f->times + start, count * sizeof(double));
        memmove(f->values, f->values + 3 * start, 3 * count * sizeof(double));
        start = 0;
    }
    f->times[start + count] = t;
    memcpy(f->values + 3 * (start + count), v, 3 * sizeof(double));
    count++;
    if (count > max_fixes) {
        start += count - max_fixes;
        count = max_fixes;
    }
    f->meta[F_START] = (double)start;
    f->meta[F_COUNT] = (double)count;
}

/* observe: n samples' times (t_stride doubles apart) and held velocities (rows v_stride apart). */
static void fixes_observe_core(Fixes *f, const double *t, Py_ssize_t t_stride, const double *vel,
                               Py_ssize_t v_stride, Py_ssize_t n, double delay, Py_ssize_t max_fixes) {
    if (n == 0) return;
    int first = fix_arrives(f->meta, vel, NULL); /* against the value held before this call */
    for (Py_ssize_t i = 0; i < n; i++) {
        const double *v = vel + i * v_stride;
        if (i == 0 ? first : fix_arrives(f->meta, v, v - v_stride)) fix_append(f, t[i * t_stride] - delay, v, max_fixes);
    }
    const double *last = vel + (n - 1) * v_stride;
    if (isfinite(last[0]) && isfinite(last[1]) && isfinite(last[2])) {
        f->meta[F_HELD_VALID] = 1.0;
        memcpy(f->meta + F_HELD, last, 3 * sizeof(double));
    }
}

static double fixes_known_until(const Fixes *f, double h) {
    Py_ssize_t start = (Py_ssize_t)f->meta[F_START], count = (Py_ssize_t)f->meta[F_COUNT];
    return count >= 2 ? f->times[start + count - 1] - h : -INFINITY;
}

/* 1 standing (every fix within h of [start_s, end_s] under max_speed), 0 not, -1 no such fix. */
static int fixes_standing_core(const Fixes *f, double start_s, double end_s, double h, double max_speed) {
    Py_ssize_t start = (Py_ssize_t)f->meta[F_START], count = (Py_ssize_t)f->meta[F_COUNT];
    int any = 0, all = 1;
    for (Py_ssize_t i = start; i < start + count; i++) {
        if (f->times[i] >= start_s - h && f->times[i] <= end_s + h) {
            const double *v = f->values + 3 * i;
            any = 1;
            if (!(sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]) < max_speed)) all = 0;
        }
    }
    return any ? all : -1;
}

/* dv/dt at n times (t_stride apart) into out (n, 3) contiguous: zero before two fixes. */
static void fixes_acceleration(const Fixes *f, const double *t, Py_ssize_t t_stride, Py_ssize_t n, double h,
                               double *out) {
    Py_ssize_t start = (Py_ssize_t)f->meta[F_START], count = (Py_ssize_t)f->meta[F_COUNT];
    if (count < 2) {
        memset(out, 0, 3 * n * sizeof(double));
        return;
    }
    Array times, values, ta, oa;
    raw_array(&times, f->times + start, count, 1, 1);
    raw_array(&values, f->values + 3 * start, count, 3, 3);
    raw_array(&ta, (double *)t, n, 1, t_stride);
    raw_array(&oa, out, n, 3, 3);
    centred_difference_core(&times, &values, &ta, h, &oa);
}

/* ---- the filters of a piece (gyro_bias.Explained, gyro_bias.HeadingDrift, aided_fusion.VerticalBias) */
enum { E_VALID, E_MEAN_SQUARE, E_SIZE };
enum { V_FED_S, V_DELTA_VALID, V_DELTA, V_INTEGRAL_S, V_SETTLE_S, V_SIZE };
enum { D_STARTED, D_T_S, D_UP, D_TAU_S = 5, D_BIAS_SIGMA, D_X, D_P = 12, D_SIZE = 37 };
/* the drift filter's noise figures: heading noise (deg), tilt error (deg), angle and bias random walks, max dip */
enum { K_HEADING_NOISE_DEG, K_TILT_ERROR_DEG, K_ANGLE_WALK, K_BIAS_WALK, K_MAX_DIP_DEG, K_SIZE };

static double explained_core(double *e, double left_ms2, double seconds, double time_s) {
    double left = pow(left_ms2, 2.0), weight = -expm1(-seconds / time_s);
    e[E_MEAN_SQUARE] = e[E_VALID] == 0.0 ? left : e[E_MEAN_SQUARE] + weight * (left - e[E_MEAN_SQUARE]);
    e[E_VALID] = 1.0;
    return sqrt(e[E_MEAN_SQUARE]);
}

static void vertical_core(double *v, double delta, const double up[3], double seconds, int disturbed,
                          double more[3]) {
    double step = 0.0;
    v[V_FED_S] += seconds;
    if (v[V_DELTA_VALID] != 0.0 && !disturbed && v[V_FED_S] >= v[V_SETTLE_S]) {
        step = remainder(delta - v[V_DELTA], 2.0 * M_PI);
    }
    v[V_DELTA] = delta;
    v[V_DELTA_VALID] = 1.0;
    double gain = -step / v[V_INTEGRAL_S];
    for (int k = 0; k < 3; k++) more[k] = gain * up[k];
}

/* d: the drift filter's D_SIZE numbers; piece: mean time, count, heading, horizontal, vertical. */
static void drift_core(double *d, const double *k, const double piece[5], int disturbed, const double up[3],
                       double tilt_rad, double learnt[3]) {
    double t = piece[0], z = piece[2];
    double dip = atan2(fabs(piece[4]), piece[3]), max_dip = radians(k[K_MAX_DIP_DEG]);
    if (max_dip < dip) dip = max_dip;
    double sigma_c = hypot(radians(k[K_TILT_ERROR_DEG]), tilt_rad) * tan(dip);
    learnt[0] = learnt[1] = learnt[2] = 0.0;
    if (d[D_STARTED] == 0.0) {
        if (disturbed) return;
        double *p = d + D_P;
        memset(d + D_X, 0, 5 * sizeof(double));
        d[D_X] = z;
        d[D_T_S] = t;
        memcpy(d + D_UP, up, 3 * sizeof(double));
        memset(p, 0, 25 * sizeof(double));
        p[0] = pow(radians(k[K_HEADING_NOISE_DEG]), 2.0);
        for (int i = 1; i < 4; i++) p[6 * i] = pow(d[D_BIAS_SIGMA], 2.0);
        p[24] = pow(sigma_c, 2.0);
        d[D_STARTED] = 1.0;
        return;
    }
    double dt = t - d[D_T_S];
    if (0.0 > dt) dt = 0.0;
    double decay = exp(-dt / d[D_TAU_S]);
    double walk = pow(k[K_BIAS_WALK], 2.0) * dt;
    double noise[5] = {pow(k[K_ANGLE_WALK], 2.0) * dt, walk, walk, walk,
                       pow(sigma_c, 2.0) * (1.0 - pow(decay, 2.0))};
    double measured = pow(radians(k[K_HEADING_NOISE_DEG]), 2.0) / piece[1];
    double mid[3] = {(up[0] + d[D_UP]) / 2.0, (up[1] + d[D_UP + 1]) / 2.0, (up[2] + d[D_UP + 2]) / 2.0};
    drift_step_core(d + D_X, d + D_P, dt, d[D_TAU_S], mid, noise, z, measured, !disturbed);
    d[D_T_S] = t;
    memcpy(d + D_UP, up, 3 * sizeof(double));
    if (disturbed) return;
    for (int i = 0; i < 3; i++) {
        learnt[i] = d[D_X + 1 + i];
        d[D_X + 1 + i] = 0.0;
    }
}

static void drift_reset(double *d) {
    double tau = d[D_TAU_S], sigma = d[D_BIAS_SIGMA];
    memset(d, 0, D_SIZE * sizeof(double));
    d[D_UP + 2] = 1.0;
    d[D_TAU_S] = tau;
    d[D_BIAS_SIGMA] = sigma;
}

static double vehicle_tau_core(double residual_ms2, double bias_sigma, double half_window_s, double gravity) {
    double window = 2.0 * half_window_s, sigma = residual_ms2 / gravity;
    return pow(pow(sigma, 2.0) * window / (4.0 * pow(bias_sigma, 2.0)), 1.0 / 3.0);
}

/* vqf's bias uncertainty about the horizontal axes (rad/s) from its biasP (9,) and the up axis (3,). */
static double horizontal_sigma_core(const double *cov, const double up[3]) {
    double trace = cov[0] + cov[4] + cov[8], row[3], quad = 0.0;
    for (int j = 0; j < 3; j++) row[j] = up[0] * cov[j] + up[1] * cov[3 + j] + up[2] * cov[6 + j];
    for (int j = 0; j < 3; j++) quad += row[j] * up[j];
    double variance = trace - quad;
    if (0.0 > variance) variance = 0.0;
    return radians(sqrt(variance / 2.0) / 100.0);
}

static void travelled_core(void *vqf, double seconds) {
    VqfState *s = (VqfState *)vqf_api.get_state(vqf);
    const VqfParams *p = vqf_api.get_params(vqf);
    if (!s->magDistDetected || s->magCandidateNorm <= 0.0) return;
    double norm = s->magNormDip[0], dip = s->magNormDip[1];
    int agrees = fabs(norm - s->magCandidateNorm) < p->magNormTh * s->magCandidateNorm;
    if (agrees && fabs(dip - s->magCandidateDip) < radians(p->magDipTh)) s->magCandidateT += seconds;
}

/* ---- the aided filter: settings (S_*) and state (A_*), float64 arrays aided_fusion.AidedFilter keeps */
enum {
    S_PERIOD, S_MAX_LAG, S_DELAY, S_HALF_WINDOW, S_MAX_FIXES, S_REST_ENABLED, S_TAU_ACC, S_VEHICLE_TAU, S_GRAVITY,
    S_STANDING_SPEED, S_CHUNK, S_EXPLAINED_TIME, S_DRIFT_ON, S_DRIFT_FIGURES, S_SIZE = S_DRIFT_FIGURES + K_SIZE
};
enum {
    A_FED, A_DISTURBED, A_PENDING, A_FIXES, A_EXPLAINED = A_FIXES + F_SIZE, A_VERTICAL = A_EXPLAINED + E_SIZE,
    A_DRIFT = A_VERTICAL + V_SIZE, A_SIZE = A_DRIFT + D_SIZE
};
/* a pending row: time, gyroscope, accelerometer, field, the attitude given, the turn since the filter's state */
enum { R_T = 0, R_GYR = 1, R_ACC = 4, R_FIELD = 7, R_GIVEN = 10, R_TURN = 14, R_SIZE = 18 };

typedef struct {
    void *vqf;
    const double *s;
    double *a;
    Fixes fixes;
    double *pending; /* (cap, R_SIZE) */
    double *scratch; /* 24 doubles a row of ``rows`` (the pending table's rows in this call at most) */
    Py_ssize_t rows;
    bool *flags;
} Aided;

/* The attitude of the pending samples [from, to): the filter's, turned by each sample's turn. Given when it is
 * used (fed: the rows fed; answered: the piece's rows), as the filter's state then makes it. */
static void aided_give(Aided *e, Py_ssize_t from, Py_ssize_t to) {
    double q9[4];
    Array p, q, out;
    vqf_api.get_quat9d(e->vqf, q9);
    raw_array(&p, q9, 1, 4, 4);
    raw_array(&q, e->pending + from * R_SIZE + R_TURN, to - from, 4, R_SIZE);
    raw_array(&out, e->pending + from * R_SIZE + R_GIVEN, to - from, 4, R_SIZE);
    quaternion_product_core(&p, &q, &out, 0, 0);
}

/* After a piece was fed (aided_fusion.AidedFilter._heading_loop): times t (n, R_SIZE apart), accelerometer fed,
 * field, vqf's 6D quaternions, its disturbance flags. */
static void aided_heading_loop(Aided *e, const double *t, Py_ssize_t n, double *acc, double *field, double *q6,
                               const bool *dist) {
    const double *s = e->s;
    double *drift = e->a + A_DRIFT, f[7], bias[3], up[3];
    Array qa, fa, aa;
    raw_array(&qa, q6, n, 4, 4);
    raw_array(&fa, field, n, 3, 3);
    raw_array(&aa, acc, n, 3, 3);
    piece_figures_core(&qa, &fa, &aa, s[S_GRAVITY], f);
    memcpy(up, f, sizeof(up));
    int disturbed = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        /* vqf's flag, or the field watch's: its samples reach vqf as a zero field, which vqf skips without raising
         * its flag, and whose heading atan2(0, 0) would read as north in the piece's mean */
        const double *b = field + 3 * i;
        disturbed |= dist[i] || (b[0] == 0.0 && b[1] == 0.0 && b[2] == 0.0);
    }
    double seconds = (double)n * s[S_PERIOD];
    vqf_api.get_bias(e->vqf, bias);
    double residual = explained_core(e->a + A_EXPLAINED, f[6], seconds, s[S_EXPLAINED_TIME]);
    int vehicle = vehicle_tau_core(residual, drift[D_BIAS_SIGMA], s[S_HALF_WINDOW], s[S_GRAVITY]) < s[S_TAU_ACC];
    double tau = vehicle ? s[S_VEHICLE_TAU] : s[S_TAU_ACC];
    vqf_api.set_tau_acc(e->vqf, tau);
    drift[D_TAU_S] = tau;
    if (!vehicle) {
        double more[3];
        if (drift[D_STARTED] != 0.0) drift_reset(drift); /* starts afresh when it is needed again */
        vertical_core(e->a + A_VERTICAL, vqf_api.get_delta(e->vqf), up, seconds, disturbed, more);
        for (int k = 0; k < 3; k++) bias[k] = bias[k] + more[k];
        vqf_api.set_bias(e->vqf, bias, -1.0);
        return;
    }
    e->a[A_VERTICAL + V_DELTA_VALID] = 0.0; /* vqf's delta is set here: not a drift for the integral term */
    double piece[5] = {pairwise_sum(t, n, R_SIZE) / (double)n, (double)n, f[3], f[4], f[5]}, learnt[3];
    VqfState *state = (VqfState *)vqf_api.get_state(e->vqf);
    double tilt = horizontal_sigma_core(state->biasP, up) * drift[D_TAU_S];
    if (s[S_DRIFT_ON] != 0.0) {
        drift_core(drift, s + S_DRIFT_FIGURES, piece, disturbed, up, tilt, learnt);
    } else { /* the drift filter switched off (a comparison): vqf's own bias and delta */
        learnt[0] = learnt[1] = learnt[2] = 0.0;
    }
    for (int k = 0; k < 3; k++) bias[k] = bias[k] + learnt[k];
    if (drift[D_STARTED] != 0.0 && !disturbed) { /* the bias (as setBiasEstimate sets it) and the delta */
        memcpy(state->bias, bias, sizeof(bias));
        state->delta = drift[D_X];
    } else {
        vqf_api.set_bias(e->vqf, bias, -1.0);
    }
}

/* Feed the leading pending samples whose acceleration is known (aided_fusion.AidedFilter._feed); vqf's 9D
 * quaternions of those fed into q9_out when not NULL. Returns how many were fed. */
static Py_ssize_t aided_feed(Aided *e, double now_s, Py_ssize_t keep, int at_once, double *q9_out) {
    const double *s = e->s;
    Py_ssize_t total = (Py_ssize_t)e->a[A_PENDING], count = 0;
    double known = fixes_known_until(&e->fixes, s[S_HALF_WINDOW]), *rows = e->pending;
    while (count < total && (at_once || rows[count * R_SIZE] <= known || rows[count * R_SIZE] < now_s - s[S_MAX_LAG]))
        count++;
    if (count > total - keep) count = total - keep;
    if (count <= 0) return 0;
    aided_give(e, 0, count); /* the attitudes the rows fed are given before the feed */
    e->a[A_FED] = 1.0;
    double *gyr = e->scratch, *acc = gyr + 3 * count, *field = acc + 3 * count, *accel = field + 3 * count;
    double *q6 = accel + 3 * count, *q9 = q6 + 4 * count;
    fixes_acceleration(&e->fixes, rows + R_T, R_SIZE, count, s[S_HALF_WINDOW], accel);
    Array given, ned, body;
    raw_array(&given, rows + R_GIVEN, count, 4, R_SIZE);
    raw_array(&ned, accel, count, 3, 3);
    raw_array(&body, accel, count, 3, 3); /* in place: each row read before it is written */
    into_body_core(&given, &ned, &body);
    for (Py_ssize_t i = 0; i < count; i++) {
        const double *row = rows + i * R_SIZE;
        for (int k = 0; k < 3; k++) {
            gyr[3 * i + k] = row[R_GYR + k];
            acc[3 * i + k] = row[R_ACC + k] - accel[3 * i + k];
            field[3 * i + k] = row[R_FIELD + k];
        }
    }
    int standing = fixes_standing_core(&e->fixes, rows[R_T], rows[(count - 1) * R_SIZE + R_T], s[S_HALF_WINDOW],
                                       s[S_STANDING_SPEED]);
    vqf_api.set_rest(e->vqf, s[S_REST_ENABLED] != 0.0 && standing != 0);
    vqf_api.update_batch(e->vqf, gyr, acc, field, (size_t)count, q6, q9, NULL, NULL, NULL, NULL, e->flags);
    if (standing == 0) travelled_core(e->vqf, (double)count * s[S_PERIOD]);
    e->a[A_DISTURBED] = e->flags[count - 1] ? 1.0 : 0.0;
    aided_heading_loop(e, rows + R_T, count, acc, field, q6, e->flags);
    if (q9_out != NULL) memcpy(q9_out, q9, 4 * count * sizeof(double));
    Py_ssize_t left = total - count;
    if (left > 0) { /* the turns from the new state: conj(last fed) turn, normalised (rounding would compound) */
        Array last, turns;
        raw_array(&last, rows + (count - 1) * R_SIZE + R_TURN, 1, 4, 4);
        raw_array(&turns, rows + count * R_SIZE + R_TURN, left, 4, R_SIZE);
        quaternion_product_core(&last, &turns, &turns, 1, 1);
        memmove(rows, rows + count * R_SIZE, left * R_SIZE * sizeof(double));
    }
    e->a[A_PENDING] = (double)left;
    return count;
}

/* One piece of a batch (aided_fusion.AidedFilter._chunk): n samples; answers into quat (rows 4 apart), flags. */
static void aided_chunk(Aided *e, const double *t, Py_ssize_t t_stride, const Array *gyr, const Array *acc,
                        const Array *field, Py_ssize_t first, const double *vel, Py_ssize_t v_stride, Py_ssize_t n,
                        double *quat, bool *out_dist) {
    const double *s = e->s;
    double bias[3], start[4] = {1.0, 0.0, 0.0, 0.0};
    fixes_observe_core(&e->fixes, t, t_stride, vel, v_stride, n, s[S_DELAY], (Py_ssize_t)s[S_MAX_FIXES]);
    vqf_api.get_bias(e->vqf, bias);
    Py_ssize_t before = (Py_ssize_t)e->a[A_PENDING];
    double *rows = e->pending + before * R_SIZE;
    if (before > 0) memcpy(start, rows - R_SIZE + R_TURN, sizeof(start));
    for (Py_ssize_t i = 0; i < n; i++) {
        double *row = rows + i * R_SIZE;
        row[R_T] = t[i * t_stride];
        for (int k = 0; k < 3; k++) {
            row[R_GYR + k] = AT(*gyr, first + i, k);
            row[R_ACC + k] = AT(*acc, first + i, k);
            row[R_FIELD + k] = AT(*field, first + i, k);
        }
        memset(row + R_GIVEN, 0, 8 * sizeof(double));
    }
    Array g, turn;
    raw_array(&g, rows + R_GYR, n, 3, R_SIZE);
    raw_array(&turn, rows + R_TURN, n, 4, R_SIZE);
    carry_forward_core(start, &g, bias, s[S_PERIOD], &turn);
    e->a[A_PENDING] = (double)(before + n);
    if (e->a[A_FED] == 0.0) { /* no attitude yet to carry forward: fed at once */
        Py_ssize_t total = (Py_ssize_t)e->a[A_PENDING];
        double *q9 = e->scratch + 20 * e->rows; /* past what aided_feed uses of the scratch (20 a row) */
        aided_feed(e, t[0], 0, 1, q9);
        memcpy(quat, q9 + 4 * (total - n), 4 * n * sizeof(double));
    } else {
        aided_feed(e, t[0], n, 0, NULL);
        Py_ssize_t total = (Py_ssize_t)e->a[A_PENDING];
        aided_give(e, total - n, total);
        for (Py_ssize_t i = 0; i < n; i++) memcpy(quat + 4 * i, e->pending + (total - n + i) * R_SIZE + R_GIVEN, 32);
    }
    memset(out_dist, e->a[A_DISTURBED] != 0.0, n);
}

static int get_state_array(PyObject *obj, Py_buffer *view, Py_ssize_t min_items, const char *name) {
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0) return -1;
    if (view->itemsize != 8 || view->format == NULL || strcmp(view->format, "d") != 0 ||
        view->len / 8 < min_items) {
        PyErr_Format(PyExc_ValueError, "%s must be a C-contiguous float64 array of at least %zd items", name,
                     min_items);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

PyDoc_STRVAR(aided_update_doc,
             "aided_update(filter, settings, state, fix_times, fix_values, pending, t, gyr, acc, field, vel, quat, "
             "disturbed)\n\n"
             "One batch of N samples through the velocity-aided filter (magnet.attitude.aided_fusion.AidedFilter."
             "update, whose docstrings are its specification): ``filter`` the vqf.VQF driven; ``settings`` (S_SIZE,) "
             "and ``state`` (A_SIZE,) float64 (aided_fusion's layout), ``fix_times`` (C,) and ``fix_values`` "
             "(C, 3) the fixes' buffers, ``pending`` (P, 18) the pending table with room for N more rows, all "
             "C-contiguous and updated in place; t (N,) s, gyr, acc, field (N, 3) vqf's frame, vel (N, 3) held "
             "magnetic NED m/s. Writes vqf's quaternions quat (N, 4) and the flags disturbed (N,) bool.");

static PyObject *aided_update(PyObject *self, PyObject *args) {
    PyObject *o_filter, *o_settings, *o_state, *o_times, *o_values, *o_pending, *o_t, *o_gyr, *o_acc, *o_field,
        *o_vel, *o_quat, *o_dist;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOO", &o_filter, &o_settings, &o_state, &o_times, &o_values, &o_pending,
                          &o_t, &o_gyr, &o_acc, &o_field, &o_vel, &o_quat, &o_dist)) {
        return NULL;
    }
    Aided e;
    e.vqf = vqf_object(o_filter);
    if (e.vqf == NULL) return NULL;
    Py_buffer b[6];
    int got = 0;
    Array a[6];
    int arrays = 0;
    Py_buffer dist;
    int have_dist = 0;
    PyObject *result = NULL;
    e.scratch = NULL;
    e.flags = NULL;
    if (get_state_array(o_settings, &b[got], S_SIZE, "settings") < 0) goto done;
    got++;
    if (get_state_array(o_state, &b[got], A_SIZE, "state") < 0) goto done;
    got++;
    if (get_state_array(o_times, &b[got], 1, "fix_times") < 0) goto done;
    got++;
    if (get_state_array(o_values, &b[got], 3 * (b[2].len / 8), "fix_values") < 0) goto done;
    got++;
    if (get_state_array(o_pending, &b[got], 0, "pending") < 0) goto done;
    got++;
    if (get_array(o_t, &a[arrays], 1, -1, -1, 0, "t") < 0) goto done;
    arrays++;
    Py_ssize_t n = a[0].rows;
    const char *names[] = {"gyr", "acc", "field", "vel"};
    PyObject *objs[] = {o_gyr, o_acc, o_field, o_vel};
    for (int i = 0; i < 4; i++) {
        if (get_array(objs[i], &a[arrays], 2, n, 3, 0, names[i]) < 0) goto done;
        arrays++;
    }
    if (get_array(o_quat, &a[arrays], 2, n, 4, 1, "quat") < 0) goto done;
    arrays++;
    if (get_flags(o_dist, &dist, n, "disturbed") < 0) goto done;
    have_dist = 1;
    e.s = b[0].buf;
    e.a = b[1].buf;
    e.fixes.meta = e.a + A_FIXES;
    e.fixes.times = b[2].buf;
    e.fixes.values = b[3].buf;
    e.fixes.cap = b[2].len / 8;
    e.pending = b[4].buf;
    Py_ssize_t cap = b[4].len / (8 * R_SIZE), held = (Py_ssize_t)e.a[A_PENDING];
    if (cap < held + n || e.fixes.cap <= (Py_ssize_t)e.s[S_MAX_FIXES]) {
        PyErr_Format(PyExc_ValueError, "pending has room for %zd rows, %zd needed (or the fixes' buffers are "
                     "not larger than max_fixes)", cap, held + n);
        goto done;
    }
    e.rows = held + n;
    e.scratch = PyMem_Malloc((size_t)(held + n) * 24 * sizeof(double) + 1);
    e.flags = PyMem_Malloc((size_t)(held + n) * sizeof(bool) + 1);
    if (e.scratch == NULL || e.flags == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    /* pieces start where a fix arrives or a chunk's tick of time begins */
    const double *t = a[0].view.buf, *vel = a[4].view.buf;
    Py_ssize_t ts = a[0].view.strides[0] / 8, vs = a[4].view.strides[0] / 8;
    if (a[4].view.strides[1] != 8) {
        PyErr_SetString(PyExc_ValueError, "vel's rows must be contiguous");
        goto done;
    }
    if (a[5].view.strides[1] != 8 || a[5].view.strides[0] != 32) {
        PyErr_SetString(PyExc_ValueError, "quat must be C-contiguous");
        goto done;
    }
    Py_ssize_t lo = 0;
    for (Py_ssize_t i = 1; i <= n; i++) {
        if (i < n) {
            int tick_changes = floor(t[i * ts] / e.s[S_CHUNK]) != floor(t[(i - 1) * ts] / e.s[S_CHUNK]);
            if (!tick_changes && !fix_arrives(e.fixes.meta, vel + i * vs, vel + (i - 1) * vs)) continue;
        }
        double *quat = (double *)a[5].view.buf + 4 * lo;
        aided_chunk(&e, t + lo * ts, ts, &a[1], &a[2], &a[3], lo, vel + lo * vs, vs, i - lo, quat,
                    (bool *)dist.buf + lo);
        lo = i;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyMem_Free(e.scratch);
    PyMem_Free(e.flags);
    if (have_dist) PyBuffer_Release(&dist);
    release(a, arrays);
    for (int i = 0; i < got; i++) PyBuffer_Release(&b[i]);
    return result;
}

/* ---- the same maths for the Python classes that hold one of these filters alone (and their tests) */
PyDoc_STRVAR(fixes_observe_doc,
             "fixes_observe(meta, times, values, t, vel, delay_s, max_fixes)\n\n"
             "aiding.VelocityFixes.observe: meta (6,) start, count, held?, held (3); times (C,) and values (C, 3) the "
             "buffers (C > max_fixes); t (n,) s, vel (n, 3) held velocities. In place.");

static PyObject *fixes_observe(PyObject *self, PyObject *args) {
    PyObject *o_meta, *o_times, *o_values, *o_t, *o_vel;
    double delay;
    Py_ssize_t max_fixes;
    if (!PyArg_ParseTuple(args, "OOOOOdn", &o_meta, &o_times, &o_values, &o_t, &o_vel, &delay, &max_fixes)) return NULL;
    Py_buffer b[3];
    Array a[2];
    if (get_state_array(o_meta, &b[0], F_SIZE, "meta") < 0) return NULL;
    if (get_state_array(o_times, &b[1], max_fixes + 1, "times") < 0) { PyBuffer_Release(&b[0]); return NULL; }
    if (get_state_array(o_values, &b[2], 3 * (b[1].len / 8), "values") < 0) {
        PyBuffer_Release(&b[0]);
        PyBuffer_Release(&b[1]);
        return NULL;
    }
    PyObject *result = NULL;
    int arrays = 0;
    if (get_array(o_t, &a[0], 1, -1, -1, 0, "t") < 0) goto done;
    arrays++;
    if (get_array(o_vel, &a[1], 2, a[0].rows, 3, 0, "vel") < 0) goto done;
    arrays++;
    if (a[1].view.strides[1] != 8) {
        PyErr_SetString(PyExc_ValueError, "vel's rows must be contiguous");
        goto done;
    }
    Fixes f = {b[0].buf, b[1].buf, b[2].buf, b[1].len / 8};
    fixes_observe_core(&f, a[0].view.buf, a[0].view.strides[0] / 8, a[1].view.buf, a[1].view.strides[0] / 8,
                       a[0].rows, delay, max_fixes);
    result = Py_None;
    Py_INCREF(result);
done:
    release(a, arrays);
    for (int i = 0; i < 3; i++) PyBuffer_Release(&b[i]);
    return result;
}

PyDoc_STRVAR(fixes_arrivals_doc,
             "fixes_arrivals(meta, vel, out)\n\n"
             "aiding.VelocityFixes.arrivals: out (n,) bool, the rows of held velocities vel (n, 3) where a new fix "
             "appears (finite, unlike the row before; the first row against the value held in meta).");

static PyObject *fixes_arrivals(PyObject *self, PyObject *args) {
    PyObject *o_meta, *o_vel, *o_out;
    if (!PyArg_ParseTuple(args, "OOO", &o_meta, &o_vel, &o_out)) return NULL;
    Py_buffer meta, out;
    Array vel;
    if (get_state_array(o_meta, &meta, F_SIZE, "meta") < 0) return NULL;
    if (get_array(o_vel, &vel, 2, -1, 3, 0, "vel") < 0) { PyBuffer_Release(&meta); return NULL; }
    if (get_flags(o_out, &out, vel.rows, "out") < 0 || vel.view.strides[1] != 8) {
        if (!PyErr_Occurred()) {
            PyBuffer_Release(&out);
            PyErr_SetString(PyExc_ValueError, "vel's rows must be contiguous");
        }
        PyBuffer_Release(&meta);
        release(&vel, 1);
        return NULL;
    }
    const double *v = vel.view.buf;
    Py_ssize_t vs = vel.view.strides[0] / 8;
    for (Py_ssize_t i = 0; i < vel.rows; i++) {
        ((bool *)out.buf)[i * out.strides[0]] = fix_arrives(meta.buf, v + i * vs, i ? v + (i - 1) * vs : NULL);
    }
    PyBuffer_Release(&meta);
    PyBuffer_Release(&out);
    release(&vel, 1);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(fixes_standing_doc,
             "fixes_standing(meta, times, values, start_s, end_s, half_window_s, max_speed) -> int\n\n"
             "aiding.VelocityFixes.standing: 1 when every fix measured within h of [start_s, end_s] is under "
             "max_speed (m/s), 0 when one is not, -1 when there is none.");

static PyObject *fixes_standing(PyObject *self, PyObject *args) {
    PyObject *o_meta, *o_times, *o_values;
    double start_s, end_s, h, max_speed;
    if (!PyArg_ParseTuple(args, "OOOdddd", &o_meta, &o_times, &o_values, &start_s, &end_s, &h, &max_speed))
        return NULL;
    Py_buffer b[3];
    if (get_state_array(o_meta, &b[0], F_SIZE, "meta") < 0) return NULL;
    if (get_state_array(o_times, &b[1], 1, "times") < 0) { PyBuffer_Release(&b[0]); return NULL; }
    if (get_state_array(o_values, &b[2], 3 * (b[1].len / 8), "values") < 0) {
        PyBuffer_Release(&b[0]);
        PyBuffer_Release(&b[1]);
        return NULL;
    }
    Fixes f = {b[0].buf, b[1].buf, b[2].buf, b[1].len / 8};
    int standing = fixes_standing_core(&f, start_s, end_s, h, max_speed);
    for (int i = 0; i < 3; i++) PyBuffer_Release(&b[i]);
    return PyLong_FromLong(standing);
}

PyDoc_STRVAR(drift_update_doc,
             "drift_update(drift, figures, t_s, count, heading_rad, horizontal, vertical, disturbed, up, tilt_rad) "
             "-> (bx, by, bz)\n\n"
             "gyro_bias.HeadingDrift.update on its numbers drift (37,): started, t_s, up (3), tau_s, bias_sigma, "
             "x (5), p (25); figures (5,): heading noise (deg), tilt error (deg), angle and bias random walks, the "
             "steepest dip (deg). Returns the bias learnt (rad/s, body axes).");

static PyObject *drift_update(PyObject *self, PyObject *args) {
    PyObject *o_drift, *o_figures, *o_up;
    double piece[5], tilt;
    int disturbed;
    if (!PyArg_ParseTuple(args, "OOdddddpOd", &o_drift, &o_figures, &piece[0], &piece[1], &piece[2], &piece[3],
                          &piece[4], &disturbed, &o_up, &tilt)) {
        return NULL;
    }
    Py_buffer b[2];
    Array up;
    if (get_state_array(o_drift, &b[0], D_SIZE, "drift") < 0) return NULL;
    if (get_state_array(o_figures, &b[1], K_SIZE, "figures") < 0) { PyBuffer_Release(&b[0]); return NULL; }
    if (get_array(o_up, &up, 1, 3, -1, 0, "up") < 0) {
        PyBuffer_Release(&b[0]);
        PyBuffer_Release(&b[1]);
        return NULL;
    }
    double u[3] = {AT1(up, 0), AT1(up, 1), AT1(up, 2)}, learnt[3];
    drift_core(b[0].buf, b[1].buf, piece, disturbed, u, tilt, learnt);
    release(&up, 1);
    PyBuffer_Release(&b[0]);
    PyBuffer_Release(&b[1]);
    return Py_BuildValue("ddd", learnt[0], learnt[1], learnt[2]);
}

PyDoc_STRVAR(explained_update_doc,
             "explained_update(store, left_ms2, seconds, time_s) -> float\n\n"
             "gyro_bias.Explained.update on store (2,): whether a mean is held, the mean square; returns the RMS.");

static PyObject *explained_update(PyObject *self, PyObject *args) {
    PyObject *o_store;
    double left, seconds, time_s;
    if (!PyArg_ParseTuple(args, "Oddd", &o_store, &left, &seconds, &time_s)) return NULL;
    Py_buffer b;
    if (get_state_array(o_store, &b, E_SIZE, "store") < 0) return NULL;
    double rms = explained_core(b.buf, left, seconds, time_s);
    PyBuffer_Release(&b);
    return PyFloat_FromDouble(rms);
}

PyDoc_STRVAR(vertical_correction_doc,
             "vertical_correction(store, delta, up, seconds, disturbed) -> (bx, by, bz)\n\n"
             "aided_fusion.VerticalBias.correction on store (5,): seconds fed, whether a delta is held, that delta, "
             "the integral time and the settling time (s).");

static PyObject *vertical_correction(PyObject *self, PyObject *args) {
    PyObject *o_store, *o_up;
    double delta, seconds;
    int disturbed;
    if (!PyArg_ParseTuple(args, "OdOdp", &o_store, &delta, &o_up, &seconds, &disturbed)) return NULL;
    Py_buffer b;
    Array up;
    if (get_state_array(o_store, &b, V_SIZE, "store") < 0) return NULL;
    if (get_array(o_up, &up, 1, 3, -1, 0, "up") < 0) { PyBuffer_Release(&b); return NULL; }
    double u[3] = {AT1(up, 0), AT1(up, 1), AT1(up, 2)}, more[3];
    vertical_core(b.buf, delta, u, seconds, disturbed, more);
    release(&up, 1);
    PyBuffer_Release(&b);
    return Py_BuildValue("ddd", more[0], more[1], more[2]);
}

PyDoc_STRVAR(vehicle_tau_acc_doc,
             "vehicle_tau_acc(residual_ms2, bias_sigma_rads, half_window_s, gravity) -> float\n\n"
             "aiding.vehicle_tau_acc_s: (sigma^2 2h / (4 b^2))^(1/3), sigma = residual / gravity.");

static PyObject *vehicle_tau_acc(PyObject *self, PyObject *args) {
    double residual, sigma, h, g;
    if (!PyArg_ParseTuple(args, "dddd", &residual, &sigma, &h, &g)) return NULL;
    return PyFloat_FromDouble(vehicle_tau_core(residual, sigma, h, g));
}

PyDoc_STRVAR(horizontal_bias_sigma_doc,
             "horizontal_bias_sigma(bias_p, up) -> float\n\n"
             "aided_fusion.horizontal_bias_sigma: vqf's bias covariance bias_p (9,) (body axes, (0.01 deg/s)^2) and "
             "the up axis (3,) -> one sigma about the horizontal axes, rad/s.");

static PyObject *horizontal_bias_sigma(PyObject *self, PyObject *args) {
    PyObject *o_cov, *o_up;
    if (!PyArg_ParseTuple(args, "OO", &o_cov, &o_up)) return NULL;
    Array a[2];
    if (get_array(o_cov, &a[0], 1, 9, -1, 0, "bias_p") < 0) return NULL;
    if (get_array(o_up, &a[1], 1, 3, -1, 0, "up") < 0) { release(a, 1); return NULL; }
    double cov[9], up[3];
    for (int i = 0; i < 9; i++) cov[i] = AT1(a[0], i);
    for (int i = 0; i < 3; i++) up[i] = AT1(a[1], i);
    release(a, 2);
    return PyFloat_FromDouble(horizontal_sigma_core(cov, up));
}

PyDoc_STRVAR(vqf_travelled_doc,
             "vqf_travelled(filter, seconds)\n\n"
             "aided_fusion.travelled on a vqf.VQF's own state.");

static PyObject *vqf_travelled(PyObject *self, PyObject *args) {
    PyObject *obj;
    double seconds;
    if (!PyArg_ParseTuple(args, "Od", &obj, &seconds)) return NULL;
    void *vqf = vqf_object(obj);
    if (vqf == NULL) return NULL;
    travelled_core(vqf, seconds);
    Py_RETURN_NONE;
}

/* ------------------------------------------------------------------------------------------------------------
 * The turn gate (magnet.attitude.turn_gate.TurnGate, whose docstrings are its specification): the accelerometer
 * fed a window late in a gait and left out where the course turned; in a swing (a limb's periodic rotation outside a
 * gait) the specific force's stride mean made level where the course turned. ``gate_update`` runs one piece of a block
 * (TurnGate.update); ``gated_run`` a whole batch through the gate and vqf's own compiled filter (the Python
 * ``vqf.VQF`` given, as aided_update drives it), its attitude and bias read at each block's start: one call a batch
 * instead of a Python loop over 0.5 s blocks. The settings and the state are float64 arrays laid out by the T_* and
 * G_* indices below, mirrored in turn_gate.py; the state's tail holds the last 2 (width - 1) rotations about the
 * vertical, the last width - 1 specific forces in the integrated frame, the last gait_width magnitudes and the last
 * gait_width body rates (3 each), each a ring whose oldest entry is at G_SAMPLES modulo its length (``ring_head``): a
 * piece writes its own samples only, instead of shifting 60 kB of windows (at 500 Hz) through the cache. */
enum {
    T_PERIOD, T_WIDTH, T_GAIT_WIDTH, T_LAG_LO, T_LAG_HI, T_STRIDE_LO, T_STRIDE_HI, T_MAX_HOLD, T_BLOCK, T_TURN_DEG,
    T_GAIT_SD, T_GAIT_CORR, T_SWING_SD, T_SWING_MAX, T_SWING_CORR, T_SWING_GAIT, T_SIZE
};
enum { G_SAMPLES, G_STRIDE, G_RUN, G_IN_GAIT, G_ATTITUDE, G_BIAS = 8, G_HELD = 11, G_IN_SWING = 15, G_RECENT = 16 };

typedef struct {
    const double *s;
    double *g;
    Py_ssize_t width, gait_width, block;
    double *recent, *earth, *mags, *rates; /* views into g */
    double *seen, *all_earth, *held, *centred, *up, *spin; /* scratch for pieces of up to ``block`` samples (centred:
                                                            * gait_width + block; spin: 3 (gait_width + block)) */
    double *turns; /* each sample's turn (4 doubles), for the heading gate of the same piece (gated_core) */
} Gate;

/* The scratch of the gate's pieces, kept from call to call (the GIL held: one user at a time): no allocation of
 * ~90 kB (at 500 Hz) per call, which glibc's heap, trimmed at 128 kB in the services, faulted in afresh. */
static double *gate_scratch = NULL;
static size_t gate_scratch_doubles = 0;

/* Where the oldest of a ring of ``length`` entries is after ``samples`` samples (the next entry's place). */
static Py_ssize_t ring_head(double samples, Py_ssize_t length) {
    return length > 0 ? (Py_ssize_t)samples % length : 0;
}

/* A ring of ``length`` rows of ``k`` doubles, oldest at ``head``, into ``out`` oldest first. */
static void ring_read(const double *ring, Py_ssize_t length, Py_ssize_t k, Py_ssize_t head, double *out) {
    memcpy(out, ring + k * head, sizeof(double) * (size_t)(k * (length - head)));
    memcpy(out + k * (length - head), ring, sizeof(double) * (size_t)(k * head));
}

/* ``n`` new rows of ``k`` doubles appended to a ring of ``length`` rows whose oldest was at ``head`` (the last
 * ``length`` of them where n is more). */
static void ring_write(double *ring, Py_ssize_t length, Py_ssize_t k, Py_ssize_t head, const double *rows,
                       Py_ssize_t n) {
    if (length <= 0) return;
    Py_ssize_t skip = n > length ? n - length : 0, at = (head + skip) % length, left = n - skip;
    while (left > 0) {
        Py_ssize_t part = length - at < left ? length - at : left;
        memcpy(ring + k * at, rows + k * skip, sizeof(double) * (size_t)(k * part));
        skip += part;
        left -= part;
        at = 0;
    }
}

static Py_ssize_t gate_state_size(const double *s) {
    Py_ssize_t w = (Py_ssize_t)s[T_WIDTH];
    return G_RECENT + 2 * (w - 1) + 3 * (w - 1) + 4 * (Py_ssize_t)s[T_GAIT_WIDTH];
}

/* The views and the scratch (NULL and an exception on failure); ``gate_free`` releases the scratch. */
static int gate_open(Gate *e, const double *s, double *g) {
    e->s = s;
    e->g = g;
    e->width = (Py_ssize_t)s[T_WIDTH];
    e->gait_width = (Py_ssize_t)s[T_GAIT_WIDTH];
    e->block = (Py_ssize_t)s[T_BLOCK];
    e->recent = g + G_RECENT;
    e->earth = e->recent + 2 * (e->width - 1);
    e->mags = e->earth + 3 * (e->width - 1);
    e->rates = e->mags + e->gait_width;
    Py_ssize_t w = e->width, b = e->block, gw = e->gait_width;
    size_t need = (size_t)(2 * (w - 1) + b + 3 * (w - 1 + b) + 4 * b + gw + b + 3 * b + 3 * (gw + b) + 4 * b);
    if (need > gate_scratch_doubles) {
        double *grown = PyMem_Realloc(gate_scratch, sizeof(double) * need);
        if (grown == NULL) {
            PyErr_NoMemory();
            return -1;
        }
        gate_scratch = grown;
        gate_scratch_doubles = need;
    }
    e->seen = gate_scratch;
    e->all_earth = e->seen + 2 * (w - 1) + b;
    e->held = e->all_earth + 3 * (w - 1 + b);
    e->centred = e->held + 4 * b;
    e->up = e->centred + gw + b;
    e->spin = e->up + 3 * b;
    e->turns = e->spin + 3 * (gw + b);
    return 0;
}

static void gate_free(Gate *e) { e->seen = NULL; } /* the scratch is kept (gate_scratch) */

/* v + w t + u x t, t = 2 u x v: a body vector in the frame a quaternion q (w, u) integrates (field_watch.to_frame). */
static void to_frame3(const double q[4], const double v[3], double out[3]) {
    double t0 = 2.0 * (q[2] * v[2] - q[3] * v[1]), t1 = 2.0 * (q[3] * v[0] - q[1] * v[2]),
           t2 = 2.0 * (q[1] * v[1] - q[2] * v[0]);
    out[0] = v[0] + q[0] * t0 + (q[2] * t2 - q[3] * t1);
    out[1] = v[1] + q[0] * t1 + (q[3] * t0 - q[1] * t2);
    out[2] = v[2] + q[0] * t2 + (q[1] * t1 - q[2] * t0);
}

/* TurnGate._gait: whether the last gait_width magnitudes are a gait (the stride set where they are). */
static int gate_gait(Gate *e) {
    const double *s = e->s, *m = e->centred; /* the magnitudes oldest first (gate_piece), centred in place */
    Py_ssize_t n = e->gait_width;
    if (isnan(m[0])) return 0;
    double mean = pairwise_sum(m, n, 1) / (double)n, power = 0.0;
    for (Py_ssize_t i = 0; i < n; i++) {
        e->centred[i] = m[i] - mean;
        power += e->centred[i] * e->centred[i];
    }
    if (power <= (double)n * (s[T_GAIT_SD] * s[T_GAIT_SD])) return 0;
    double best = -INFINITY, best_stride = -INFINITY;
    Py_ssize_t stride = -1;
    for (Py_ssize_t lag = (Py_ssize_t)s[T_LAG_LO]; lag <= (Py_ssize_t)s[T_LAG_HI] && lag < n; lag++) {
        double c = 0.0;
        for (Py_ssize_t i = 0; i + lag < n; i++) c += e->centred[i] * e->centred[i + lag];
        if (c > best) best = c;
    }
    for (Py_ssize_t lag = (Py_ssize_t)s[T_STRIDE_LO]; lag <= (Py_ssize_t)s[T_STRIDE_HI] && lag < n; lag++) {
        double c = 0.0;
        for (Py_ssize_t i = 0; i + lag < n; i++) c += e->centred[i] * e->centred[i + lag];
        if (c > best_stride) {
            best_stride = c;
            stride = lag;
        }
    }
    if ((best > best_stride ? best : best_stride) <= s[T_GAIT_CORR] * power) return 0;
    e->g[G_STRIDE] = (double)(stride < e->width ? stride : e->width);
    return 1;
}

/* TurnGate._swing: whether the last gait_width body rates are a swing (the stride set where they are): their spread
 * about their mean (RMS of the vector) between swing_sd and swing_max, repeating at a stride's lag (the summed
 * products of the centred rates over swing_corr times their power). 2 where the spread is swing_gait or more (a
 * runner's arm, or a device turned fast by hand: a swing only where the magnitudes are a gait too), else 1. */
static int gate_swing(Gate *e) {
    const double *s = e->s, *r = e->spin; /* the rates oldest first (gate_piece), centred in place */
    Py_ssize_t n = e->gait_width;
    if (isnan(r[0])) return 0;
    double *x = e->spin, power = 0.0;
    for (int k = 0; k < 3; k++) {
        double mean = pairwise_sum(r + k, n, 3) / (double)n;
        for (Py_ssize_t i = 0; i < n; i++) {
            x[3 * i + k] = r[3 * i + k] - mean;
            power += x[3 * i + k] * x[3 * i + k];
        }
    }
    if (power <= (double)n * (s[T_SWING_SD] * s[T_SWING_SD]) || power >= (double)n * (s[T_SWING_MAX] * s[T_SWING_MAX]))
        return 0;
    double best = -INFINITY;
    Py_ssize_t stride = -1;
    for (Py_ssize_t lag = (Py_ssize_t)s[T_STRIDE_LO]; lag <= (Py_ssize_t)s[T_STRIDE_HI] && lag < n; lag++) {
        double c = 0.0;
        for (Py_ssize_t i = 0; i < 3 * (n - lag); i++) c += x[i] * x[i + 3 * lag];
        if (c > best) {
            best = c;
            stride = lag;
        }
    }
    if (best <= s[T_SWING_CORR] * power) return 0;
    e->g[G_STRIDE] = (double)(stride < e->width ? stride : e->width);
    return power >= (double)n * (s[T_SWING_GAIT] * s[T_SWING_GAIT]) ? 2 : 1;
}

/* TurnGate._level: in a swing, where the rotation about the vertical over the last two strides (the triangle of
 * 2 stride - 1 weights ending at each sample) exceeds turn_deg, each sample's specific force less the horizontal
 * part (square to vqf's vertical) of the mean over the last stride, both in the held frame: the course's own
 * acceleration taken out, the swing's kept. ``fed`` holds acc on entry. */
static void gate_level(Gate *e, const double *acc, Py_ssize_t n, double *fed) {
    const double *s = e->s;
    double *g = e->g, run = g[G_RUN], max_hold = s[T_MAX_HOLD], to_deg = 180.0 / M_PI;
    Py_ssize_t w1 = e->width - 1, ns = (Py_ssize_t)g[G_STRIDE];
    for (Py_ssize_t j = 0; j < n; j++) {
        double turned = 0.0;
        const double *x = e->seen + 2 * w1 + j - (2 * ns - 2);
        for (Py_ssize_t m = 0; m < 2 * ns - 1; m++) {
            double weight = (double)(m < ns ? m + 1 : 2 * ns - 1 - m) / (double)ns;
            turned += x[m] * weight;
        }
        int over = fabs(turned * to_deg) > s[T_TURN_DEG];
        run = over ? run + 1.0 : 0.0;
        if (!(over && run <= max_hold)) continue;
        double mean[3] = {0.0, 0.0, 0.0};
        const double *rows = e->all_earth + 3 * (w1 + j - ns + 1);
        for (Py_ssize_t m = 0; m < ns; m++)
            for (int k = 0; k < 3; k++) mean[k] += rows[3 * m + k];
        if (isnan(mean[0] + mean[1] + mean[2])) continue;
        const double *u = e->up + 3 * j;
        double uu = u[0] * u[0] + u[1] * u[1] + u[2] * u[2], along = 0.0;
        for (int k = 0; k < 3; k++) {
            mean[k] /= (double)ns;
            along += mean[k] * u[k];
        }
        double level[3], out[3];
        for (int k = 0; k < 3; k++) level[k] = mean[k] - along * u[k] / uu;
        const double *q = e->held + 4 * j;
        double inverse[4] = {q[0], -q[1], -q[2], -q[3]};
        to_frame3(inverse, level, out);
        for (int k = 0; k < 3; k++) fed[3 * j + k] = acc[3 * j + k] - out[k];
    }
    g[G_RUN] = run;
}

/* TurnGate.update on n samples (n within the block): gyr, acc rows 3 doubles apart; writes the accelerometer to feed
 * into ``fed`` (n, 3) and the samples left out into ``gated`` (n,). Returns whether the block is in a gait (else fed
 * is acc; in a swing fed is acc made level where the course turned, ``gate_level``, and 1 is returned, gated all
 * false). ``start`` and ``bias`` are read at a block's start only. */
static int gate_piece(Gate *e, const double *gyr, const double *acc, Py_ssize_t n, const double start[4],
                      const double bias_in[3], double *fed, bool *gated) {
    const double *s = e->s;
    double *g = e->g, period = s[T_PERIOD];
    Py_ssize_t w1 = e->width - 1, gw = e->gait_width;
    double samples = g[G_SAMPLES]; /* before this piece: where each ring's oldest entry is */
    Py_ssize_t at_recent = ring_head(samples, 2 * w1), at_earth = ring_head(samples, w1), at_gw = ring_head(samples, gw);
    if ((Py_ssize_t)samples % e->block == 0) {
        memcpy(g + G_ATTITUDE, start, 4 * sizeof(double));
        memcpy(g + G_BIAS, bias_in, 3 * sizeof(double));
        ring_read(e->rates, gw, 3, at_gw, e->spin);
        double before = g[G_STRIDE];
        int swing = gate_swing(e);
        if (swing != 1) ring_read(e->mags, gw, 1, at_gw, e->centred);
        if (swing == 2) { /* a fast swing: a swing where the magnitudes are a gait (a runner's arm), else neither */
            double stride = g[G_STRIDE];
            swing = gate_gait(e) ? 1 : 0;
            g[G_STRIDE] = swing ? stride : before;
            g[G_IN_GAIT] = 0.0;
        } else {
            g[G_IN_GAIT] = swing == 0 && gate_gait(e);
        }
        g[G_IN_SWING] = (double)swing;
    }
    g[G_SAMPLES] += (double)n;
    const double *bias = g + G_BIAS;
    double att[4], held[4];
    memcpy(att, g + G_ATTITUDE, sizeof(att));
    memcpy(held, g + G_HELD, sizeof(held));
    int in_gait = g[G_IN_GAIT] != 0.0, in_swing = g[G_IN_SWING] != 0.0;
    if (in_gait || in_swing) { /* the windows before the piece, oldest first, ahead of its own samples */
        ring_read(e->recent, 2 * w1, 1, at_recent, e->seen);
        ring_read(e->earth, w1, 3, at_earth, e->all_earth);
    }
    for (Py_ssize_t i = 0; i < n; i++) {
        const double *a = acc + 3 * i;
        double r[3] = {gyr[3 * i] - bias[0], gyr[3 * i + 1] - bias[1], gyr[3 * i + 2] - bias[2]};
        double norm = sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]);
        double angle = norm * period / 2.0;
        double c = cos(angle), sn = norm > 0 ? sin(angle) / norm : 0.0;
        double *turn = e->turns + 4 * i, next[4], v[3];
        turn[0] = c, turn[1] = r[0] * sn, turn[2] = r[1] * sn, turn[3] = r[2] * sn;
        quat_mul(att, turn, next);
        memcpy(att, next, sizeof(att));
        quat_mul(held, turn, next);
        memcpy(held, next, sizeof(held));
        memcpy(e->held + 4 * i, held, sizeof(held));
        to_frame3(att, r, v);
        e->seen[2 * w1 + i] = v[2] * period;
        to_frame3(held, a, e->all_earth + 3 * (w1 + i));
        e->centred[i] = sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]); /* the magnitudes, for a moment */
        /* vqf's vertical (z up in its Earth frame) in the body, then in the held frame */
        double inverse[4] = {att[0], -att[1], -att[2], -att[3]}, z[3] = {0.0, 0.0, 1.0}, body[3];
        to_frame3(inverse, z, body);
        to_frame3(held, body, e->up + 3 * i);
    }
    if (n > 0) {
        memcpy(g + G_ATTITUDE, att, sizeof(att));
        double hn = sqrt(held[0] * held[0] + held[1] * held[1] + held[2] * held[2] + held[3] * held[3]);
        for (int k = 0; k < 4; k++) g[G_HELD + k] = held[k] / hn;
    }
    /* the piece's own samples into the rings */
    ring_write(e->mags, gw, 1, at_gw, e->centred, n);
    ring_write(e->rates, gw, 3, at_gw, gyr, n);
    ring_write(e->recent, 2 * w1, 1, at_recent, e->seen + 2 * w1, n);
    ring_write(e->earth, w1, 3, at_earth, e->all_earth + 3 * w1, n);
    if (!in_gait) {
        memset(gated, 0, (size_t)n);
        if (fed != acc) memcpy(fed, acc, sizeof(double) * (size_t)(3 * n));
        if (!in_swing) {
            if (n > 0) g[G_RUN] = 0.0;
            return 0;
        }
        gate_level(e, acc, n, fed);
        return 1;
    }
    /* _turned: the triangle of 2 stride - 1 weights centred on each delayed sample's rotation */
    Py_ssize_t ns = (Py_ssize_t)g[G_STRIDE], first = (w1 + 1) - ns;
    double run = g[G_RUN], max_hold = s[T_MAX_HOLD], to_deg = 180.0 / M_PI;
    for (Py_ssize_t j = 0; j < n; j++) {
        double turned = 0.0;
        const double *x = e->seen + first + j;
        for (Py_ssize_t m = 0; m < 2 * ns - 1; m++) {
            double weight = (double)(m < ns ? m + 1 : 2 * ns - 1 - m) / (double)ns;
            turned += x[m] * weight;
        }
        int over = fabs(turned * to_deg) > s[T_TURN_DEG];
        run = over ? run + 1.0 : 0.0;
        gated[j] = over && run <= max_hold;
        const double *q = e->held + 4 * j;
        double inverse[4] = {q[0], -q[1], -q[2], -q[3]}, out[3];
        to_frame3(inverse, e->all_earth + 3 * j, out);
        if (isnan(out[0])) memcpy(out, acc + 3 * j, sizeof(out));
        if (gated[j]) out[0] = out[1] = out[2] = 0.0;
        memcpy(fed + 3 * j, out, sizeof(out));
    }
    g[G_RUN] = run;
    return 1;
}

/* A C-contiguous (rows, cols) float64 array (read-only unless ``writable``). */
static int get_rows(PyObject *obj, Py_buffer *view, Py_ssize_t rows, Py_ssize_t cols, int writable,
                    const char *name) {
    int flags = PyBUF_STRIDES | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) < 0) return -1;
    if (!PyBuffer_IsContiguous(view, 'C') || view->itemsize != 8 || view->format == NULL ||
        strcmp(view->format, "d") != 0 ||
        (view->ndim != 2 && !(view->ndim == 1 && cols == 1)) || (rows >= 0 && view->shape[0] != rows) ||
        (view->ndim == 2 && view->shape[1] != cols)) {
        PyErr_Format(PyExc_ValueError, "%s must be a C-contiguous float64 array of shape (%zd, %zd) (-1: any)", name,
                     rows, cols);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

/* The gate's settings (T_SIZE,) and state (its size for them), C-contiguous float64. */
static int get_gate(PyObject *o_settings, PyObject *o_state, Py_buffer b[2]) {
    if (get_state_array(o_settings, &b[0], T_SIZE, "settings") < 0) return -1;
    const double *s = b[0].buf;
    if (!(s[T_WIDTH] >= 1 && s[T_GAIT_WIDTH] >= 3 && s[T_BLOCK] >= 1)) {
        PyErr_SetString(PyExc_ValueError, "settings: width, gait_width and block must be positive");
        PyBuffer_Release(&b[0]);
        return -1;
    }
    if (get_state_array(o_state, &b[1], gate_state_size(s), "state") < 0) {
        PyBuffer_Release(&b[0]);
        return -1;
    }
    return 0;
}

PyDoc_STRVAR(gate_update_doc,
             "gate_update(settings, state, gyr, acc, start, bias, fed, gated) -> bool\n\n"
             "TurnGate.update on one piece of n samples within a block: settings (T_SIZE,) and state float64 "
             "(turn_gate.py's layout, updated in place), gyr and acc (n, 3) C-contiguous, vqf's frame, ``start`` (4,) "
             "vqf's 6D attitude and ``bias`` (3,) rad/s (read at a block's start); writes the accelerometer to feed "
             "into fed (n, 3) and the samples left out into gated (n,) bool. Returns whether the block is in a gait or a "
             "swing (else fed is acc).");

static PyObject *gate_update(PyObject *self, PyObject *args) {
    PyObject *o_settings, *o_state, *o_gyr, *o_acc, *o_start, *o_bias, *o_fed, *o_gated;
    if (!PyArg_ParseTuple(args, "OOOOOOOO", &o_settings, &o_state, &o_gyr, &o_acc, &o_start, &o_bias, &o_fed,
                          &o_gated)) {
        return NULL;
    }
    Py_buffer b[2], v[6];
    int got = 0;
    PyObject *result = NULL;
    Gate e;
    e.seen = NULL;
    if (get_gate(o_settings, o_state, b) < 0) return NULL;
    if (get_rows(o_gyr, &v[got], -1, 3, 0, "gyr") < 0) goto done;
    Py_ssize_t n = v[0].shape[0];
    got++;
    if (get_rows(o_acc, &v[got], n, 3, 0, "acc") < 0) goto done;
    got++;
    if (get_rows(o_start, &v[got], 4, 1, 0, "start") < 0) goto done;
    got++;
    if (get_rows(o_bias, &v[got], 3, 1, 0, "bias") < 0) goto done;
    got++;
    if (get_rows(o_fed, &v[got], n, 3, 1, "fed") < 0) goto done;
    got++;
    if (PyObject_GetBuffer(o_gated, &v[got], PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0) goto done;
    got++;
    if (v[5].itemsize != 1 || v[5].format == NULL || v[5].format[0] != '?' || v[5].len != n) {
        PyErr_Format(PyExc_ValueError, "gated must be a C-contiguous bool array of %zd items", n);
        goto done;
    }
    if (gate_open(&e, b[0].buf, b[1].buf) < 0) goto done;
    Py_ssize_t left = e.block - (Py_ssize_t)e.g[G_SAMPLES] % e.block;
    if (n > left) {
        PyErr_Format(PyExc_ValueError, "a batch for the turn gate must end within its block: %zd samples", left);
        goto done;
    }
    int in_gait = gate_piece(&e, v[0].buf, v[1].buf, n, v[2].buf, v[3].buf, v[4].buf, v[5].buf);
    result = PyBool_FromLong(in_gait);
done:
    if (e.seen != NULL) gate_free(&e);
    for (int i = 0; i < got; i++) PyBuffer_Release(&v[i]);
    PyBuffer_Release(&b[0]);
    PyBuffer_Release(&b[1]);
    return result;
}

/* ------------------------------------------------------------------------------------------------------------
 * The heading gate (magnet.attitude.heading_gate.HeadingGate, whose docstrings are its specification): each field
 * sample turned into vqf's 6D Earth frame (its attitude and bias read at a block's start, carried forward with the
 * gyroscope), its heading there against vqf's magnetic heading offset delta (the innovation vqf would correct by),
 * the sample left out where that disagreement is unusual for this device and the device has not turned about the
 * vertical lately. Settings H_* and state HS_* float64 arrays; the state's tail: the last turn_width cumulative
 * rotations about the vertical (a ring), then the block's disagreements (rad, NaN where left out). */
enum {
    H_PERIOD, H_BLOCK, H_TURN_WIDTH, H_FLOOR, H_RELATIVE, H_PERCENT, H_TAU, H_LEARN, H_HOLD, H_MAX_RUN, H_TURN,
    H_SMOOTH, H_SIZE
};
enum {
    HS_SAMPLES, HS_ATTITUDE, HS_BIAS = 5, HS_DELTA = 8, HS_INIT, HS_LEVEL, HS_SEEN, HS_HOLD_LEFT, HS_RUN,
    HS_ACCEPTING, HS_OVER, HS_TURNED, HS_SMOOTHED, HS_RING
};

static Py_ssize_t heading_gate_state_size(const double *s) {
    return HS_RING + (Py_ssize_t)s[H_TURN_WIDTH] + (Py_ssize_t)s[H_BLOCK];
}

/* remainder(x, 2 pi), to the bit, without libm's call where |x| < 9 (all the heading gate sees but NaN): 2 pi is
 * a double y and pi y / 2 exactly, so within [-pi, pi] the quotient rounds to 0 (a half to even) and the result is
 * x; for pi < |x| < 9 < 3 pi it rounds to +-1 and x -+ y is exact (Sterbenz: y / 2 <= |x| <= 2 y). */
static double wrap_pi(double x) {
    double a = fabs(x);
    if (a <= M_PI) return x;
    if (a < 9.0) return x - copysign(2.0 * M_PI, x);
    return remainder(x, 2.0 * M_PI);
}

/* At a block's end: the usual disagreement towards the block's 90th percentile (``percent``), an acceptance that
 * saw no unusual sample in the block ended. */
static void heading_gate_learn(const double *s, double *h, double *scratch) {
    Py_ssize_t block = (Py_ssize_t)s[H_BLOCK], finite = 0;
    double *pending = h + HS_RING + (Py_ssize_t)s[H_TURN_WIDTH];
    for (Py_ssize_t i = 0; i < block; i++) {
        if (isfinite(pending[i])) scratch[finite++] = pending[i];
        pending[i] = NAN;
    }
    if (h[HS_ACCEPTING] != 0.0 && h[HS_OVER] == 0.0) h[HS_ACCEPTING] = 0.0;
    h[HS_OVER] = 0.0;
    if (finite == 0 || h[HS_INIT] != 0.0 || h[HS_ACCEPTING] != 0.0) return;
    h[HS_SEEN] += (double)finite;
    double alpha = -expm1(-(double)block * s[H_PERIOD] / s[H_TAU]), share = (double)block / h[HS_SEEN];
    alpha = alpha > share ? alpha : share;
    alpha = alpha < 1.0 ? alpha : 1.0;
    h[HS_LEVEL] += alpha * (percentile(scratch, finite, s[H_PERCENT]) - h[HS_LEVEL]);
}

/* HeadingGate.update on n samples within a block: field rows 3 doubles apart (a zero row: left out already);
 * ``start`` (4,), ``bias`` (3,), ``delta`` and ``init`` (vqf's kMagInit) read at a block's start only. Writes the
 * field to feed into ``fed`` (n, 3) (may be ``field``) and the samples left out into ``flags`` (n,). Returns
 * whether any was left out; -1 and an exception on no memory. */
static int heading_gate_piece(const double *s, double *h, const double *gyr, const double *field, Py_ssize_t n,
                              const double start[4], const double bias_in[3], double delta, double init,
                              double *fed, bool *flags, const Gate *shared) {
    Py_ssize_t block = (Py_ssize_t)s[H_BLOCK], width = (Py_ssize_t)s[H_TURN_WIDTH];
    double period = s[H_PERIOD], *ring = h + HS_RING, *pending = ring + width;
    double *scratch = PyMem_Malloc(sizeof(double) * (size_t)block + 1);
    if (scratch == NULL) {
        PyErr_NoMemory();
        return -1;
    }
    int any = 0, share = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        Py_ssize_t g = (Py_ssize_t)h[HS_SAMPLES];
        if (g % block == 0) {
            memcpy(h + HS_ATTITUDE, start, 4 * sizeof(double));
            memcpy(h + HS_BIAS, bias_in, 3 * sizeof(double));
            h[HS_DELTA] = delta;
            h[HS_INIT] = init;
            if (init != 0.0) { /* the magnetic side (re)starting: nothing usual known yet */
                h[HS_LEVEL] = 0.0, h[HS_SEEN] = 0.0, h[HS_RUN] = 0.0, h[HS_HOLD_LEFT] = 0.0;
                h[HS_ACCEPTING] = 0.0, h[HS_OVER] = 0.0, h[HS_SMOOTHED] = NAN;
            }
        }
        static const double none[3] = {0.0, 0.0, 0.0};
        const double *bias = h + HS_BIAS, *v = field != NULL ? field + 3 * i : none;
        /* the turn gate's turns of the same piece where they are this gate's (the same bias and period: one
         * sqrt, cos and sin a sample, not two; the bias changes at a block's start only) */
        if (i == 0 || g % block == 0)
            share = shared != NULL && shared->s[T_PERIOD] == period &&
                    memcmp(shared->g + G_BIAS, bias, 3 * sizeof(double)) == 0;
        double r[3] = {gyr[3 * i] - bias[0], gyr[3 * i + 1] - bias[1], gyr[3 * i + 2] - bias[2]};
        double turn[4], att[4], up[3], earth[3];
        if (share) {
            memcpy(turn, shared->turns + 4 * i, sizeof(turn));
        } else {
            double norm = sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]);
            double angle = norm * period / 2.0, c = cos(angle), sn = norm > 0 ? sin(angle) / norm : 0.0;
            turn[0] = c, turn[1] = r[0] * sn, turn[2] = r[1] * sn, turn[3] = r[2] * sn;
        }
        quat_mul(h + HS_ATTITUDE, turn, att);
        double an = sqrt(att[0] * att[0] + att[1] * att[1] + att[2] * att[2] + att[3] * att[3]);
        for (int k = 0; k < 4; k++) h[HS_ATTITUDE + k] = att[k] / an;
        /* the rotation about the vertical over the last turn_width samples: the largest |now - then| */
        to_frame3(h + HS_ATTITUDE, r, up);
        h[HS_TURNED] += up[2] * period;
        /* the disagreement: the field's heading in vqf's 6D frame less delta, within -pi .. pi, smoothed (the
         * weight ``smooth`` a sample: a moment's spike of the magnetometer's lag in a fast turn is no disturbance) */
        double innovation = NAN;
        if (v[0] != 0.0 || v[1] != 0.0 || v[2] != 0.0) {
            to_frame3(h + HS_ATTITUDE, v, earth);
            double now = wrap_pi(atan2(earth[0], earth[1]) - h[HS_DELTA]), was = h[HS_SMOOTHED];
            innovation = isnan(was) ? now : wrap_pi(was + s[H_SMOOTH] * wrap_pi(now - was));
            h[HS_SMOOTHED] = innovation;
        }
        double limit = s[H_RELATIVE] * h[HS_LEVEL];
        limit = limit > s[H_FLOOR] ? limit : s[H_FLOOR];
        int ready = h[HS_INIT] == 0.0 && h[HS_SEEN] * period >= s[H_LEARN] && h[HS_LEVEL] > 0.0;
        int over = isfinite(innovation) && fabs(innovation) > limit;
        if (over) h[HS_OVER] = 1.0;
        int raw = ready && over && h[HS_ACCEPTING] == 0.0;
        if (raw) { /* only then (a scan of the ring a sample was most of the command line's cost): the rotation about
                    * the vertical over the last turn_width samples, the largest |now - then| */
            double turned = 0.0;
            Py_ssize_t back = g < width ? g : width;
            for (Py_ssize_t m = 1; m <= back; m++) {
                double d = fabs(h[HS_TURNED] - ring[(g - m) % width]);
                turned = d > turned ? d : turned;
            }
            raw = turned <= s[H_TURN];
        }
        ring[g % width] = h[HS_TURNED];
        int flagged = raw || (isfinite(innovation) && h[HS_HOLD_LEFT] > 0.0);
        if (raw) {
            h[HS_HOLD_LEFT] = s[H_HOLD];
        } else if (flagged) {
            h[HS_HOLD_LEFT] -= 1.0;
        }
        h[HS_RUN] = flagged ? h[HS_RUN] + 1.0 : 0.0;
        if (h[HS_RUN] > s[H_MAX_RUN]) { /* unusual for too long: the field is right, the heading is not */
            flagged = 0;
            h[HS_RUN] = 0.0, h[HS_HOLD_LEFT] = 0.0, h[HS_ACCEPTING] = 1.0;
        }
        pending[g % block] = flagged ? NAN : fabs(innovation);
        flags[i] = (bool)flagged;
        any |= flagged;
        if (fed != NULL) {
            for (int k = 0; k < 3; k++) fed[3 * i + k] = flagged ? 0.0 : v[k];
        }
        h[HS_SAMPLES] += 1.0;
        if ((Py_ssize_t)h[HS_SAMPLES] % block == 0) heading_gate_learn(s, h, scratch);
    }
    PyMem_Free(scratch);
    return any;
}

/* The heading gate's settings (H_SIZE,) and state (its size for them), C-contiguous float64. */
static int get_heading_gate(PyObject *o_settings, PyObject *o_state, Py_buffer b[2]) {
    if (get_state_array(o_settings, &b[0], H_SIZE, "heading gate settings") < 0) return -1;
    const double *s = b[0].buf;
    if (!(s[H_BLOCK] >= 1 && s[H_TURN_WIDTH] >= 1 && s[H_PERIOD] > 0 && s[H_TAU] > 0)) {
        PyErr_SetString(PyExc_ValueError, "heading gate settings: block, turn_width, period and tau must be positive");
        PyBuffer_Release(&b[0]);
        return -1;
    }
    if (get_state_array(o_state, &b[1], heading_gate_state_size(s), "heading gate state") < 0) {
        PyBuffer_Release(&b[0]);
        return -1;
    }
    return 0;
}

PyDoc_STRVAR(heading_gate_update_doc,
             "heading_gate_update(settings, state, gyr, field, start, bias, delta, k_mag_init, fed, flags) -> bool\n\n"
             "HeadingGate.update on one piece of n samples within a block: settings (H_SIZE,) and state float64 "
             "(heading_gate.py's layout, updated in place), gyr and field (n, 3) C-contiguous, vqf's frame, ``start`` "
             "(4,) vqf's 6D attitude, ``bias`` (3,) rad/s, vqf's ``delta`` (rad) and ``kMagInit`` (read at a block's "
             "start); writes the field to feed into fed (n, 3) and the samples left out into flags (n,) bool. Returns "
             "whether any was left out.");

static PyObject *heading_gate_update(PyObject *self, PyObject *args) {
    PyObject *o_settings, *o_state, *o_gyr, *o_field, *o_start, *o_bias, *o_fed, *o_flags;
    double delta, init;
    if (!PyArg_ParseTuple(args, "OOOOOOddOO", &o_settings, &o_state, &o_gyr, &o_field, &o_start, &o_bias, &delta,
                          &init, &o_fed, &o_flags)) {
        return NULL;
    }
    Py_buffer b[2], v[6];
    int got = 0;
    PyObject *result = NULL;
    if (get_heading_gate(o_settings, o_state, b) < 0) return NULL;
    if (get_rows(o_gyr, &v[got], -1, 3, 0, "gyr") < 0) goto done;
    Py_ssize_t n = v[0].shape[0];
    got++;
    if (get_rows(o_field, &v[got], n, 3, 0, "field") < 0) goto done;
    got++;
    if (get_rows(o_start, &v[got], 4, 1, 0, "start") < 0) goto done;
    got++;
    if (get_rows(o_bias, &v[got], 3, 1, 0, "bias") < 0) goto done;
    got++;
    if (get_rows(o_fed, &v[got], n, 3, 1, "fed") < 0) goto done;
    got++;
    if (PyObject_GetBuffer(o_flags, &v[got], PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0) goto done;
    got++;
    if (v[5].itemsize != 1 || v[5].format == NULL || v[5].format[0] != '?' || v[5].len != n) {
        PyErr_Format(PyExc_ValueError, "flags must be a C-contiguous bool array of %zd items", n);
        goto done;
    }
    Py_ssize_t block = (Py_ssize_t)((double *)b[0].buf)[H_BLOCK];
    if (n > block - (Py_ssize_t)((double *)b[1].buf)[HS_SAMPLES] % block) {
        PyErr_SetString(PyExc_ValueError, "a piece for the heading gate must end within its block");
        goto done;
    }
    int any = heading_gate_piece(b[0].buf, b[1].buf, v[0].buf, v[1].buf, n, v[2].buf, v[3].buf, delta, init,
                                 v[4].buf, v[5].buf, NULL);
    if (any < 0) goto done;
    result = PyBool_FromLong(any);
done:
    for (int i = 0; i < got; i++) PyBuffer_Release(&v[i]);
    PyBuffer_Release(&b[0]);
    PyBuffer_Release(&b[1]);
    return result;
}

/* gated_run's work on n samples (rows 3 doubles apart; field NULL: without the magnetometer; quat6 NULL: not
 * wanted), the gate's settings and state already checked (``get_gate``): -1 and an exception on no memory. */
static int gated_core(void *vqf, const double *settings, double *state, const double *gyr, const double *acc,
                      const double *field, Py_ssize_t n, double *quat6, double *quat9, bool *rest, bool *dist,
                      const double *heading_settings, double *heading_state) {
    Gate e;
    int failed = -1;
    double *fed = NULL, *field_fed = NULL;
    bool *gated = NULL, *left_out = NULL;
    if (gate_open(&e, settings, state) < 0) return -1;
    fed = PyMem_Malloc(sizeof(double) * (size_t)(3 * e.block) + 1);
    gated = PyMem_Malloc((size_t)e.block + 1);
    field_fed = PyMem_Malloc(sizeof(double) * (size_t)(3 * e.block) + 1);
    left_out = PyMem_Malloc((size_t)e.block + 1);
    if (fed == NULL || gated == NULL || field_fed == NULL || left_out == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    if (heading_settings != NULL &&
        ((Py_ssize_t)heading_state[HS_SAMPLES] - (Py_ssize_t)e.g[G_SAMPLES]) % e.block != 0) {
        PyErr_SetString(PyExc_ValueError, "the heading gate's blocks must be the turn gate's (reset them together)");
        goto done;
    }
    double start[4], bias[3], delta = 0.0, init = 0.0;
    for (Py_ssize_t pos = 0; pos < n;) {
        Py_ssize_t left = e.block - (Py_ssize_t)e.g[G_SAMPLES] % e.block, k = n - pos < left ? n - pos : left;
        if (left == e.block) {
            vqf_api.get_quat6d(vqf, start);
            vqf_api.get_bias(vqf, bias);
            delta = vqf_api.get_delta(vqf);
            init = vqf_api.get_state(vqf)->kMagInit;
        }
        const double *a = acc + 3 * pos, *f = field ? field + 3 * pos : NULL;
        if (gate_piece(&e, gyr + 3 * pos, a, k, start, bias, fed, gated)) a = fed;
        int any = 0;
        if (heading_settings != NULL) {
            any = heading_gate_piece(heading_settings, heading_state, gyr + 3 * pos, f, k, start, bias, delta, init,
                                     f ? field_fed : NULL, left_out, &e);
            if (any < 0) goto done;
            if (any) f = field_fed;
        }
        vqf_api.update_batch(vqf, gyr + 3 * pos, a, f, (size_t)k, quat6 ? quat6 + 4 * pos : NULL, quat9 + 4 * pos,
                             NULL, NULL, NULL, rest + pos, dist + pos);
        if (any) {
            for (Py_ssize_t i = 0; i < k; i++) dist[pos + i] = dist[pos + i] || left_out[i];
        }
        pos += k;
    }
    failed = 0;
done:
    PyMem_Free(fed);
    PyMem_Free(gated);
    PyMem_Free(field_fed);
    PyMem_Free(left_out);
    gate_free(&e);
    return failed;
}

PyDoc_STRVAR(gated_run_doc,
             "gated_run(filter, settings, state, gyr, acc, field, quat6, quat9, rest, disturbed, heading_settings, "
             "heading_state)\n\n"
             "One batch of N samples through the turn gate and the vqf.VQF ``filter`` (turn_gate.run_gated without "
             "a bias loop): the batch cut at the gate's blocks, vqf's 6D attitude and bias read at each block's "
             "start, each piece fed the accelerometer the gate gives (``gate_update``). gyr, acc, field (N, 3) "
             "C-contiguous, vqf's frame (field None: without the magnetometer); writes vqf's outputs quat6 (None: "
             "not wanted), quat9 (N, 4), rest and disturbed (N,) bool. heading_settings and heading_state: the "
             "heading gate's (HeadingGate; None, None: none), the field samples it leaves out fed as zero rows and "
             "flagged disturbed.");

static PyObject *gated_run(PyObject *self, PyObject *args) {
    PyObject *o_filter, *o_settings, *o_state, *o_gyr, *o_acc, *o_field, *o_q6, *o_q9, *o_rest, *o_dist, *o_hs, *o_hg;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOO", &o_filter, &o_settings, &o_state, &o_gyr, &o_acc, &o_field, &o_q6,
                          &o_q9, &o_rest, &o_dist, &o_hs, &o_hg)) {
        return NULL;
    }
    void *vqf = vqf_object(o_filter);
    if (vqf == NULL) return NULL;
    Py_buffer b[2], v[7], hb[2];
    int got = 0, heading = o_hs != Py_None;
    PyObject *result = NULL;
    if (heading && get_heading_gate(o_hs, o_hg, hb) < 0) return NULL;
    if (get_gate(o_settings, o_state, b) < 0) {
        if (heading) {
            PyBuffer_Release(&hb[0]);
            PyBuffer_Release(&hb[1]);
        }
        return NULL;
    }
    if (get_rows(o_gyr, &v[got], -1, 3, 0, "gyr") < 0) goto done;
    Py_ssize_t n = v[0].shape[0];
    got++;
    if (get_rows(o_acc, &v[got], n, 3, 0, "acc") < 0) goto done;
    got++;
    if (o_field != Py_None) {
        if (get_rows(o_field, &v[got], n, 3, 0, "field") < 0) goto done;
        got++;
    }
    const double *field = o_field != Py_None ? v[2].buf : NULL;
    double *quat6 = NULL;
    if (o_q6 != Py_None) {
        if (get_rows(o_q6, &v[got], n, 4, 1, "quat6") < 0) goto done;
        quat6 = v[got++].buf;
    }
    if (get_rows(o_q9, &v[got], n, 4, 1, "quat9") < 0) goto done;
    double *quat9 = v[got++].buf;
    int flags_at = got;
    PyObject *flags[2] = {o_rest, o_dist};
    for (int i = 0; i < 2; i++) {
        if (PyObject_GetBuffer(flags[i], &v[got], PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0) goto done;
        got++;
        if (v[got - 1].itemsize != 1 || v[got - 1].format == NULL || v[got - 1].format[0] != '?' ||
            v[got - 1].len != n) {
            PyErr_Format(PyExc_ValueError, "%s must be a C-contiguous bool array of %zd items",
                         i ? "disturbed" : "rest", n);
            goto done;
        }
    }
    if (gated_core(vqf, b[0].buf, b[1].buf, v[0].buf, v[1].buf, field, n, quat6, quat9, v[flags_at].buf,
                   v[flags_at + 1].buf, heading ? hb[0].buf : NULL, heading ? hb[1].buf : NULL) < 0) {
        goto done;
    }
    result = Py_None;
    Py_INCREF(result);
done:
    for (int i = 0; i < got; i++) PyBuffer_Release(&v[i]);
    PyBuffer_Release(&b[0]);
    PyBuffer_Release(&b[1]);
    if (heading) {
        PyBuffer_Release(&hb[0]);
        PyBuffer_Release(&hb[1]);
    }
    return result;
}

PyDoc_STRVAR(fuse_rows_doc,
             "fuse_rows(filter, settings, state, watch, gyr, acc, field, lo, hi, quat9, disturbed, heading_settings, "
             "heading_state)\n\n"
             "Fusion.update_vqf_frame on rows lo .. hi of a drain, in one call (the compass's path, "
             "magnet.attitude.fusion.Fusion.update_rows): the field's watch (``watch``: None, or FieldWatch's "
             "kernel_args, the tail of watch_update's arguments from widths on) on those rows' field and gyr, the "
             "samples it flags fed to vqf without their field (zero rows), then the turn gate and the vqf.VQF "
             "``filter`` as gated_run (settings and state the gate's). gyr, acc, field (S, 3) C-contiguous, vqf's "
             "frame; writes vqf's quaternions into quat9 (S, 4) rows lo .. hi and its disturbance flags, or-ed with "
             "the watch's, into disturbed (S,) bool; heading_settings and heading_state: the heading gate's, as "
             "gated_run's.");

static PyObject *fuse_rows(PyObject *self, PyObject *args) {
    PyObject *o_filter, *o_settings, *o_state, *o_watch, *o_gyr, *o_acc, *o_field, *o_q9, *o_dist, *o_hs, *o_hg;
    Py_ssize_t lo, hi;
    if (!PyArg_ParseTuple(args, "OOOOOOOnnOOOO", &o_filter, &o_settings, &o_state, &o_watch, &o_gyr, &o_acc,
                          &o_field, &lo, &hi, &o_q9, &o_dist, &o_hs, &o_hg)) {
        return NULL;
    }
    void *vqf = vqf_object(o_filter);
    if (vqf == NULL) return NULL;
    Py_buffer b[2], v[5], hb[2];
    int got = 0, watching = 0, heading = o_hs != Py_None;
    PyObject *result = NULL;
    char *watched = NULL, *rest = NULL;
    double *zeroed = NULL;
    Array wa[9];
    if (heading && get_heading_gate(o_hs, o_hg, hb) < 0) return NULL;
    if (get_gate(o_settings, o_state, b) < 0) {
        if (heading) {
            PyBuffer_Release(&hb[0]);
            PyBuffer_Release(&hb[1]);
        }
        return NULL;
    }
    if (get_rows(o_gyr, &v[got], -1, 3, 0, "gyr") < 0) goto done;
    Py_ssize_t count = v[0].shape[0];
    got++;
    if (get_rows(o_acc, &v[got], count, 3, 0, "acc") < 0) goto done;
    got++;
    if (get_rows(o_field, &v[got], count, 3, 0, "field") < 0) goto done;
    got++;
    if (get_rows(o_q9, &v[got], count, 4, 1, "quat9") < 0) goto done;
    got++;
    if (PyObject_GetBuffer(o_dist, &v[got], PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0) goto done;
    got++;
    if (v[4].itemsize != 1 || v[4].format == NULL || v[4].format[0] != '?' || v[4].len != count) {
        PyErr_Format(PyExc_ValueError, "disturbed must be a C-contiguous bool array of %zd items", count);
        goto done;
    }
    if (!(0 <= lo && lo <= hi && hi <= count)) {
        PyErr_Format(PyExc_ValueError, "rows %zd .. %zd are not within the %zd samples", lo, hi, count);
        goto done;
    }
    Py_ssize_t n = hi - lo;
    const double *gyr = (const double *)v[0].buf + 3 * lo, *acc = (const double *)v[1].buf + 3 * lo;
    const double *field = (const double *)v[2].buf + 3 * lo;
    watched = PyMem_Calloc((size_t)n + 1, 1);
    rest = PyMem_Malloc((size_t)n + 1);
    if (watched == NULL || rest == NULL) {
        PyErr_NoMemory();
        goto done;
    }
    if (o_watch != Py_None) {
        PyObject *o_widths, *o_floors, *o_wstate, *o_levels, *o_ring, *o_pending, *o_calm;
        WatchNumbers w;
        if (!PyTuple_Check(o_watch)) {
            PyErr_SetString(PyExc_TypeError, "watch must be None or FieldWatch.kernel_args (a tuple)");
            goto done;
        }
        if (!PyArg_ParseTuple(o_watch, "OOOOOOOdnnndddddd", &o_widths, &o_floors, &o_wstate, &o_levels, &o_ring,
                              &o_pending, &o_calm, &w.period, &w.smooth, &w.hold, &w.block, &w.relative, &w.tol_pct,
                              &w.learn_s, &w.tau_s, &w.max_reject_s, &w.turn_floor)) {
            goto done;
        }
        raw_array(&wa[0], (double *)field, n, 3, 3);
        raw_array(&wa[1], (double *)gyr, n, 3, 3);
        if (watch_arrays(wa, o_widths, o_floors, o_wstate, o_levels, o_ring, o_pending, o_calm, w.block) < 0) {
            goto done;
        }
        watching = 1;
        if (watch_run(wa, &w, watched, 1) < 0) goto done;
        Py_ssize_t first = 0;
        while (first < n && !watched[first]) first++;
        if (first < n) { /* the flagged samples reach vqf without their field */
            zeroed = PyMem_Malloc(sizeof(double) * (size_t)(3 * n) + 1);
            if (zeroed == NULL) {
                PyErr_NoMemory();
                goto done;
            }
            for (Py_ssize_t i = 0; i < 3 * n; i++) zeroed[i] = watched[i / 3] ? 0.0 : field[i];
            field = zeroed;
        }
    }
    bool *dist = (bool *)v[4].buf + lo;
    if (gated_core(vqf, b[0].buf, b[1].buf, gyr, acc, field, n, NULL, (double *)v[3].buf + 4 * lo, (bool *)rest,
                   dist, heading ? hb[0].buf : NULL, heading ? hb[1].buf : NULL) < 0) {
        goto done;
    }
    for (Py_ssize_t i = 0; i < n; i++) dist[i] = dist[i] || watched[i];
    result = Py_None;
    Py_INCREF(result);
done:
    if (watching) release(wa + 2, 7);
    PyMem_Free(zeroed);
    PyMem_Free(watched);
    PyMem_Free(rest);
    for (int i = 0; i < got; i++) PyBuffer_Release(&v[i]);
    PyBuffer_Release(&b[0]);
    PyBuffer_Release(&b[1]);
    if (heading) {
        PyBuffer_Release(&hb[0]);
        PyBuffer_Release(&hb[1]);
    }
    return result;
}

static PyObject *gate_layout(PyObject *self, PyObject *args) {
    return Py_BuildValue("{s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i}",
                         "period", T_PERIOD, "width", T_WIDTH, "gait_width", T_GAIT_WIDTH, "lag_lo", T_LAG_LO,
                         "lag_hi", T_LAG_HI, "stride_lo", T_STRIDE_LO, "stride_hi", T_STRIDE_HI, "max_hold",
                         T_MAX_HOLD, "block", T_BLOCK, "turn_deg", T_TURN_DEG, "gait_sd", T_GAIT_SD, "gait_corr",
                         T_GAIT_CORR, "swing_sd", T_SWING_SD, "swing_max", T_SWING_MAX, "swing_corr", T_SWING_CORR, "swing_gait", T_SWING_GAIT, "settings", T_SIZE,
                         "samples", G_SAMPLES, "stride", G_STRIDE, "run", G_RUN, "in_gait", G_IN_GAIT, "attitude",
                         G_ATTITUDE, "bias", G_BIAS, "held", G_HELD, "in_swing", G_IN_SWING, "recent", G_RECENT);
}

static PyObject *heading_gate_layout(PyObject *self, PyObject *args) {
    return Py_BuildValue("{s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,"
                         "s:i,s:i,s:i,s:i,s:i}",
                         "period", H_PERIOD, "block", H_BLOCK, "turn_width", H_TURN_WIDTH, "floor", H_FLOOR,
                         "relative", H_RELATIVE, "percent", H_PERCENT, "tau", H_TAU, "learn", H_LEARN, "hold", H_HOLD,
                         "max_run", H_MAX_RUN, "turn", H_TURN, "smooth", H_SMOOTH, "settings", H_SIZE, "samples", HS_SAMPLES, "attitude",
                         HS_ATTITUDE, "bias", HS_BIAS, "delta", HS_DELTA, "init", HS_INIT, "level", HS_LEVEL, "seen",
                         HS_SEEN, "hold_left", HS_HOLD_LEFT, "run", HS_RUN, "accepting", HS_ACCEPTING, "over",
                         HS_OVER, "turned", HS_TURNED, "smoothed", HS_SMOOTHED, "ring", HS_RING);
}

PyDoc_STRVAR(aided_layout_doc, "aided_layout() -> dict: the sizes and indices of the settings and state arrays.");

static PyObject *aided_layout(PyObject *self, PyObject *args) {
    return Py_BuildValue("{s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i,s:i}", "settings", S_SIZE, "state", A_SIZE,
                         "fixes", A_FIXES, "explained", A_EXPLAINED, "vertical", A_VERTICAL, "drift", A_DRIFT,
                         "fixes_size", F_SIZE, "explained_size", E_SIZE, "vertical_size", V_SIZE, "drift_size", D_SIZE,
                         "figures", S_DRIFT_FIGURES, "row", R_SIZE);
}

/* numpy's einsum "sij,sj->si" for one output (s, i): its sum of products over j = 0..2 as numpy 2 computes it on its
 * baseline (X86_V2: lanes of two, a product then an add, the remainder loaded with zeros, a horizontal add, then
 * added to the output's zero), the instructions' operands in the order numpy's own build puts them, which decides
 * the sign of a NaN where two NaNs meet (tests/magnet/attitude/test_kernels.py compares the numbers bit by bit with
 * numpy's, NaN's sign included). x86-64 only; elsewhere the same sums in plain C. */
#if defined(__x86_64__) && defined(__GNUC__)
#include <emmintrin.h>
/* a * b, a + b and the horizontal sum, each as one instruction whose first operand is a (its NaN wins) */
static inline __m128d mul_first(__m128d a, __m128d b) {
    __asm__("mulpd %1, %0" : "+x"(a) : "x"(b));
    return a;
}
static inline __m128d add_first(__m128d a, __m128d b) {
    __asm__("addpd %1, %0" : "+x"(a) : "x"(b));
    return a;
}
static inline double lanes_sum(__m128d a) {
    __asm__("haddpd %0, %0" : "+x"(a));
    double zero = 0.0;
    __asm__("addsd %1, %0" : "+x"(zero) : "x"(_mm_cvtsd_f64(a)));
    return zero;
}
static double einsum_row3(const double *m, const double *v) {
    __m128d acc = _mm_setzero_pd();
    acc = add_first(acc, mul_first(_mm_loadu_pd(v), _mm_loadu_pd(m)));
    acc = add_first(acc, mul_first(_mm_set_pd(0.0, m[2]), _mm_set_pd(0.0, v[2])));
    return lanes_sum(acc);
}
#else
static double einsum_row3(const double *m, const double *v) {
    double lane0 = 0.0 + v[0] * m[0], lane1 = 0.0 + v[1] * m[1];
    lane0 = lane0 + m[2] * v[2];
    lane1 = lane1 + 0.0 * 0.0;
    return 0.0 + (lane0 + lane1);
}
#endif

PyDoc_STRVAR(correct_field_doc,
             "correct_field(mag, offsets, matrices, bounds, out)\n\n"
             "Each batch's calibration on its samples (magnet.compass.calibrations.Correction.apply): out (S, 3) = "
             "A_b (mag - b_b) for the samples bounds[b] .. bounds[b + 1] of batch b, mag (S, 3), offsets (B, 3), "
             "matrices (B, 9) row-major, bounds (B + 1,) int64: numpy's einsum('sij,sj->si') to the bit, without "
             "the per-sample copies of the offsets and matrices.");

static PyObject *correct_field(PyObject *self, PyObject *args) {
    PyObject *o_mag, *o_offsets, *o_matrices, *o_bounds, *o_out;
    if (!PyArg_ParseTuple(args, "OOOOO", &o_mag, &o_offsets, &o_matrices, &o_bounds, &o_out)) return NULL;
    Array a[4];
    Py_buffer bounds;
    if (get_array(o_mag, &a[0], 2, -1, 3, 0, "mag") < 0) return NULL;
    Py_ssize_t n = a[0].rows;
    if (get_array(o_offsets, &a[1], 2, -1, 3, 0, "offsets") < 0) { release(a, 1); return NULL; }
    Py_ssize_t count = a[1].rows;
    if (get_array(o_matrices, &a[2], 2, count, 9, 0, "matrices") < 0) { release(a, 2); return NULL; }
    if (get_array(o_out, &a[3], 2, n, 3, 1, "out") < 0) { release(a, 3); return NULL; }
    if (get_int64(o_bounds, &bounds, count + 1, "bounds") < 0) { release(a, 4); return NULL; }
    PyObject *result = NULL;
    for (Py_ssize_t b = 0; b < count; b++) {
        long long lo = *(long long *)((char *)bounds.buf + b * bounds.strides[0]);
        long long hi = *(long long *)((char *)bounds.buf + (b + 1) * bounds.strides[0]);
        if (lo < 0 || hi > n || lo > hi) {
            PyErr_Format(PyExc_ValueError, "batch %zd: samples %lld .. %lld out of range", b, lo, hi);
            goto done;
        }
        double m[9], off[3] = {AT(a[1], b, 0), AT(a[1], b, 1), AT(a[1], b, 2)};
        for (int k = 0; k < 9; k++) m[k] = AT(a[2], b, k);
        for (long long i = lo; i < hi; i++) {
            double d[3] = {AT(a[0], i, 0) - off[0], AT(a[0], i, 1) - off[1], AT(a[0], i, 2) - off[2]};
            for (int k = 0; k < 3; k++) AT(a[3], i, k) = einsum_row3(m + 3 * k, d);
        }
    }
    result = Py_None;
    Py_INCREF(result);
done:
    PyBuffer_Release(&bounds);
    release(a, 4);
    return result;
}

PyDoc_STRVAR(horizontal_force_doc,
             "horizontal_force(rotation, acc, scale, out)\n\n"
             "out (S, 2) = the first two rows of each rotation (S, 9) row-major times acc (S, 3), divided by "
             "``scale`` (magnet.attitude.uncertainty: the horizontal specific force in g): numpy's "
             "einsum('sij,sj->si', rotation[:, :2], acc) / scale to the bit.");

static PyObject *horizontal_force(PyObject *self, PyObject *args) {
    PyObject *o_rotation, *o_acc, *o_out;
    double scale;
    if (!PyArg_ParseTuple(args, "OOdO", &o_rotation, &o_acc, &scale, &o_out)) return NULL;
    Array a[3];
    if (get_array(o_rotation, &a[0], 2, -1, 9, 0, "rotation") < 0) return NULL;
    Py_ssize_t n = a[0].rows;
    if (get_array(o_acc, &a[1], 2, n, 3, 0, "acc") < 0) { release(a, 1); return NULL; }
    if (get_array(o_out, &a[2], 2, n, 2, 1, "out") < 0) { release(a, 2); return NULL; }
    for (Py_ssize_t i = 0; i < n; i++) {
        double m[6], v[3] = {AT(a[1], i, 0), AT(a[1], i, 1), AT(a[1], i, 2)};
        for (int k = 0; k < 6; k++) m[k] = AT(a[0], i, k);
        AT(a[2], i, 0) = einsum_row3(m, v) / scale;
        AT(a[2], i, 1) = einsum_row3(m + 3, v) / scale;
    }
    release(a, 3);
    Py_RETURN_NONE;
}

/* The first heading's take (magnet.compass.first_heading.FirstHeading.judge): its state's items. */
enum {
    FT_LEFT, FT_SIZE, FT_JUDGED, FT_AWAY, FT_CALM, FT_SEEN_AWAY, FT_SEEN_STRENGTH, FT_CALM_NEEDED, FT_EARLY, FT_PERIOD,
    FT_SIZE_ALL
};

PyDoc_STRVAR(first_take_doc,
             "first_take(field, low2, high2, min_judged_s, max_share, state, out) -> (restart, left_out)\n\n"
             "One step of a filter's first-heading take over field (n, 3) uT, C-contiguous float64, written in place "
             "(the rows left out zeroed): |B|^2 outside [low2, high2] uT^2 is away from the record's strength; state "
             "(FT_SIZE_ALL,) float64 as FirstHeading.state (left, size, judged, away, calm, seen_away, seen_strength, "
             "calm_needed, early, period_s), updated; out (n,) bool: the samples left out. restart: the index where the "
             "take starts again, -1: none; left_out: how many were left out (0: out is not written). The maths of "
             "FirstHeading's docstring; tests compare it with the same written plainly in numpy.");

static PyObject *first_take(PyObject *self, PyObject *args) {
    PyObject *o_field, *o_state, *o_out;
    double low2, high2, min_judged_s, max_share;
    if (!PyArg_ParseTuple(args, "OddddOO", &o_field, &low2, &high2, &min_judged_s, &max_share, &o_state, &o_out)) {
        return NULL;
    }
    Py_buffer v[3];
    if (get_rows(o_field, &v[0], -1, 3, 1, "field") < 0) return NULL;
    Py_ssize_t n = v[0].shape[0];
    if (get_state_array(o_state, &v[1], FT_SIZE_ALL, "state") < 0) {
        PyBuffer_Release(&v[0]);
        return NULL;
    }
    if (PyObject_GetBuffer(o_out, &v[2], PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0) {
        PyBuffer_Release(&v[0]);
        PyBuffer_Release(&v[1]);
        return NULL;
    }
    if (v[2].itemsize != 1 || v[2].format == NULL || v[2].format[0] != '?' || v[2].len != n) {
        PyErr_Format(PyExc_ValueError, "out must be a C-contiguous bool array of %zd items", n);
        for (int i = 0; i < 3; i++) PyBuffer_Release(&v[i]);
        return NULL;
    }
    double *field = v[0].buf, *s = v[1].buf;
    char *flag = v[2].buf; /* 1: known, 2: away; then the samples left out */
    Py_ssize_t take = (Py_ssize_t)s[FT_LEFT] < n ? (Py_ssize_t)s[FT_LEFT] : n, restart = -1, end, left_out = 0;
    int any_away = 0;
    for (Py_ssize_t i = 0; i < take; i++) {
        const double *b = field + 3 * i;
        double norm2 = b[0] * b[0] + b[1] * b[1] + b[2] * b[2];
        int known = norm2 > 0.0, away = known && (norm2 < low2 || norm2 > high2);
        flag[i] = (char)(known | (away << 1));
        any_away |= away;
    }
    double begun = s[FT_SIZE] - s[FT_LEFT]; /* samples of the take before this step */
    if (s[FT_SEEN_AWAY] != 0.0 || (any_away && begun < s[FT_EARLY])) { /* an early away, now or before: calm again */
        double calm = s[FT_CALM];
        int seen = s[FT_SEEN_AWAY] != 0.0, any_known = 0;
        for (Py_ssize_t i = 0; i < take && restart < 0; i++) {
            if (!(flag[i] & 1)) continue;
            any_known = 1;
            int away = flag[i] >> 1;
            calm = away ? 0.0 : calm + 1.0;
            seen |= away && (double)i + begun < s[FT_EARLY];
            if (seen && calm >= s[FT_CALM_NEEDED]) restart = i;
        }
        if (restart < 0 && any_known) {
            s[FT_CALM] = calm;
            s[FT_SEEN_AWAY] = seen;
        }
    }
    end = restart < 0 ? take : restart;
    s[FT_LEFT] -= (double)end;
    Py_ssize_t judged = 0, away_count = 0;
    for (Py_ssize_t i = 0; i < end; i++) {
        judged += flag[i] & 1;
        away_count += flag[i] >> 1;
    }
    s[FT_JUDGED] += (double)judged;
    if (any_away) {
        s[FT_AWAY] += (double)away_count;
        if (s[FT_JUDGED] * s[FT_PERIOD] >= min_judged_s && s[FT_AWAY] > max_share * s[FT_JUDGED]) {
            s[FT_LEFT] = 0.0; /* the strength is in question: nothing more left out until the next start */
            restart = -1;
        } else { /* left out once the field has shown the strength */
            int seen = s[FT_SEEN_STRENGTH] != 0.0;
            for (Py_ssize_t i = 0; i < n; i++) {
                int away = i < end && (flag[i] >> 1);
                seen |= i < end && flag[i] == 1;
                flag[i] = (char)(away && seen);
                left_out += flag[i];
                if (flag[i]) field[3 * i] = field[3 * i + 1] = field[3 * i + 2] = 0.0;
            }
            s[FT_SEEN_STRENGTH] = seen;
        }
    } else {
        for (Py_ssize_t i = 0; i < end && s[FT_SEEN_STRENGTH] == 0.0; i++) s[FT_SEEN_STRENGTH] = flag[i] & 1;
    }
    for (int i = 0; i < 3; i++) PyBuffer_Release(&v[i]);
    return Py_BuildValue("nn", restart, left_out);
}

static PyMethodDef methods[] = {
    {"carry_forward", carry_forward, METH_VARARGS, carry_forward_doc},
    {"quaternion_product", quaternion_product, METH_VARARGS, quaternion_product_doc},
    {"into_body", into_body, METH_VARARGS, into_body_doc},
    {"piece_figures", piece_figures, METH_VARARGS, piece_figures_doc},
    {"centred_difference", centred_difference, METH_VARARGS, centred_difference_doc},
    {"drift_step", drift_step, METH_VARARGS, drift_step_doc},
    {"advance_field", advance_field, METH_VARARGS, advance_field_doc},
    {"watch_update", watch_update, METH_VARARGS, watch_update_doc},
    {"vqf_attitudes", vqf_attitudes, METH_VARARGS, vqf_attitudes_doc},
    {"sigma_direct", sigma_direct, METH_VARARGS, sigma_direct_doc},
    {"batch_figures", batch_figures, METH_VARARGS, batch_figures_doc},
    {"gyro_rows", gyro_rows, METH_VARARGS, gyro_rows_doc},
    {"disturbance_bits", disturbance_bits, METH_VARARGS, disturbance_bits_doc},
    {"bias_drift", bias_drift, METH_VARARGS, bias_drift_doc},
    {"sigma_degrees", sigma_degrees, METH_VARARGS, sigma_degrees_doc},
    {"turn_about_down", turn_about_down, METH_VARARGS, turn_about_down_doc},
    {"row_faults", row_faults, METH_VARARGS, row_faults_doc},
    {"tilt_heading", tilt_heading, METH_VARARGS, tilt_heading_doc},
    {"correct_field", correct_field, METH_VARARGS, correct_field_doc},
    {"horizontal_force", horizontal_force, METH_VARARGS, horizontal_force_doc},
    {"column_checks", column_checks, METH_VARARGS, column_checks_doc},
    {"format_rows", format_rows, METH_VARARGS, format_rows_doc},
    {"vqf_bind", vqf_bind, METH_VARARGS, vqf_bind_doc},
    {"vqf_probe", vqf_probe, METH_VARARGS, vqf_probe_doc},
    {"vqf_travelled", vqf_travelled, METH_VARARGS, vqf_travelled_doc},
    {"aided_update", aided_update, METH_VARARGS, aided_update_doc},
    {"aided_layout", aided_layout, METH_NOARGS, aided_layout_doc},
    {"fixes_observe", fixes_observe, METH_VARARGS, fixes_observe_doc},
    {"fixes_arrivals", fixes_arrivals, METH_VARARGS, fixes_arrivals_doc},
    {"fixes_standing", fixes_standing, METH_VARARGS, fixes_standing_doc},
    {"drift_update", drift_update, METH_VARARGS, drift_update_doc},
    {"explained_update", explained_update, METH_VARARGS, explained_update_doc},
    {"vertical_correction", vertical_correction, METH_VARARGS, vertical_correction_doc},
    {"vehicle_tau_acc", vehicle_tau_acc, METH_VARARGS, vehicle_tau_acc_doc},
    {"horizontal_bias_sigma", horizontal_bias_sigma, METH_VARARGS, horizontal_bias_sigma_doc},
    {"gate_update", gate_update, METH_VARARGS, gate_update_doc},
    {"fuse_rows", fuse_rows, METH_VARARGS, fuse_rows_doc},
    {"first_take", first_take, METH_VARARGS, first_take_doc},
    {"gated_run", gated_run, METH_VARARGS, gated_run_doc},
    {"gate_layout", gate_layout, METH_NOARGS, "gate_layout() -> dict: the T_* and G_* indices (turn_gate.py)."},
    {"heading_gate_update", heading_gate_update, METH_VARARGS, heading_gate_update_doc},
    {"heading_gate_layout", heading_gate_layout, METH_NOARGS,
     "heading_gate_layout() -> dict: the H_* and HS_* indices (heading_gate.py)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "magnet._kernels",
    "The filters' per-sample loops, compiled (see magnet/_kernels.c).", -1, methods,
};

PyMODINIT_FUNC PyInit__kernels(void) {
    make_digit_quads();
    return PyModule_Create(&module);
}
