/* The per-sample loops of the filters, compiled (docs/cost.md says why C and not numba).
 *
 * Each function takes numpy arrays (any float64 buffer: C-contiguous or a strided view such as a table's columns)
 * and writes its results into the arrays it is given, or returns a few floats. They are the maths of the Python
 * modules that call them (magnet.attitude: aided_fusion, aiding, gyro_bias, mag_delay, field_watch), written once
 * here; tests/test_kernels.py compares each with the same maths written plainly in numpy on random inputs.
 * Quaternions are w, x, y, z; vectors x, y, z; no allocation, no Python objects inside the loops. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdio.h>
#include <string.h>

typedef struct {
    Py_buffer view;
    Py_ssize_t rows, cols;
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
    double q[4] = {AT1(a[0], 0), AT1(a[0], 1), AT1(a[0], 2), AT1(a[0], 3)};
    double bias[3] = {AT1(a[2], 0), AT1(a[2], 1), AT1(a[2], 2)};
    for (Py_ssize_t i = 0; i < a[1].rows; i++) {
        double r0 = AT(a[1], i, 0) - bias[0], r1 = AT(a[1], i, 1) - bias[1], r2 = AT(a[1], i, 2) - bias[2];
        double norm = sqrt(r0 * r0 + r1 * r1 + r2 * r2);
        double angle = norm * period / 2.0;
        double c = cos(angle), s = norm > 0 ? sin(angle) / norm : 0.0;
        double turn[4] = {c, r0 * s, r1 * s, r2 * s}, next[4];
        quat_mul(q, turn, next);
        for (int k = 0; k < 4; k++) {
            q[k] = next[k];
            AT(a[3], i, k) = next[k];
        }
    }
    release(a, 4);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(quaternion_product_doc,
             "quaternion_product(p, q, out, conjugate_p=False, normalise=False)\n\n"
             "out (N, 4) = p q row by row: p (1, 4) one quaternion for every row, or (N, 4); q (N, 4). "
             "``conjugate_p``: p's conjugate; ``normalise``: each product to unit length. ``out`` may be ``q``.");

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
    int p_each = a[0].rows != 1;
    if (get_array(o_out, &a[2], 2, a[1].rows, 4, 1, "out") < 0) { release(a, 2); return NULL; }
    double sign = conjugate ? -1.0 : 1.0;
    for (Py_ssize_t i = 0; i < a[1].rows; i++) {
        double p[4], q[4], r[4];
        for (int k = 0; k < 4; k++) {
            p[k] = AT(a[0], p_each ? i : 0, k) * (k ? sign : 1.0);
            q[k] = AT(a[1], i, k);
        }
        quat_mul(p, q, r);
        double n = normalise ? sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3]) : 1.0;
        for (int k = 0; k < 4; k++) {
            AT(a[2], i, k) = r[k] / n;
        }
    }
    release(a, 3);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(into_body_doc,
             "into_body(quat_vqf, a_ned, out)\n\n"
             "out (N, 3) = R^T a: accelerations a_ned (N, 3) magnetic NED turned into vqf's body frame by vqf's "
             "quaternions (N, 4) body -> ENU (normalised here).");

static PyObject *into_body(PyObject *self, PyObject *args) {
    PyObject *o_q, *o_a, *o_out;
    if (!PyArg_ParseTuple(args, "OOO", &o_q, &o_a, &o_out)) {
        return NULL;
    }
    Array a[3];
    if (get_array(o_q, &a[0], 2, -1, 4, 0, "quat_vqf") < 0) return NULL;
    if (get_array(o_a, &a[1], 2, a[0].rows, 3, 0, "a_ned") < 0) { release(a, 1); return NULL; }
    if (get_array(o_out, &a[2], 2, a[0].rows, 3, 1, "out") < 0) { release(a, 2); return NULL; }
    for (Py_ssize_t i = 0; i < a[0].rows; i++) {
        double q[4] = {AT(a[0], i, 0), AT(a[0], i, 1), AT(a[0], i, 2), AT(a[0], i, 3)}, r[9];
        quat_matrix(q, r);
        double e = AT(a[1], i, 1), n = AT(a[1], i, 0), u = -AT(a[1], i, 2); /* NED -> ENU */
        for (int k = 0; k < 3; k++) {
            AT(a[2], i, k) = r[k] * e + r[3 + k] * n + r[6 + k] * u;
        }
    }
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
    double sin_sum = 0, cos_sum = 0, horizontal = 0, vertical = 0, left[3] = {0, 0, 0}, up[3] = {0, 0, 1};
    for (Py_ssize_t i = 0; i < n; i++) {
        double q[4] = {AT(a[0], i, 0), AT(a[0], i, 1), AT(a[0], i, 2), AT(a[0], i, 3)}, r[9];
        quat_matrix(q, r);
        double b[3] = {AT(a[1], i, 0), AT(a[1], i, 1), AT(a[1], i, 2)}, e[3];
        for (int k = 0; k < 3; k++) {
            e[k] = r[3 * k] * b[0] + r[3 * k + 1] * b[1] + r[3 * k + 2] * b[2];
            up[k] = r[6 + k];
            left[k] += AT(a[2], i, k) - gravity * up[k];
        }
        double phi = atan2(e[0], e[1]);
        sin_sum += sin(phi);
        cos_sum += cos(phi);
        horizontal += hypot(e[0], e[1]);
        vertical += e[2];
    }
    double mean_left = sqrt(left[0] * left[0] + left[1] * left[1] + left[2] * left[2]) / (double)n;
    PyObject *out = Py_BuildValue("ddddddd", up[0], up[1], up[2], atan2(sin_sum / n, cos_sum / n), horizontal / n,
                                  vertical / n, mean_left);
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
    double first = AT1(a[0], 0), last = AT1(a[0], a[0].rows - 1);
    for (Py_ssize_t i = 0; i < a[2].rows; i++) {
        double t = AT1(a[2], i);
        int covered = (t - h >= first) && (t + h <= last + 1e-9);
        for (int k = 0; k < 3; k++) {
            AT(a[3], i, k) =
                covered ? (interp(t + h, &a[0], &a[1], k) - interp(t - h, &a[0], &a[1], k)) / (2.0 * h) : 0.0;
        }
    }
    release(a, 4);
    Py_RETURN_NONE;
}

PyDoc_STRVAR(drift_step_doc,
             "drift_step(x, p, dt, tau_s, up, q_diag, z, noise, update) -> None\n\n"
             "The heading-drift Kalman filter's step, in place on x (5,) and p (5, 5): the prediction over dt (s, "
             "0 if negative) with F = I, F[0, 1:4] = -dt up (3,), F[4, 4] = exp(-dt / tau_s) and the process noise "
             "diag(q_diag (5,)) (already for dt); then, when ``update``, the measurement z (rad) of x[0] + x[4] with "
             "variance ``noise``, the innovation and x[0] wrapped to [-pi, pi].");

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
    double f[5][5] = {{0}}, x[5], p[5][5], fp[5][5];
    dt = dt > 0.0 ? dt : 0.0;
    for (int i = 0; i < 5; i++) f[i][i] = 1.0;
    for (int k = 0; k < 3; k++) f[0][1 + k] = -dt * AT1(a[2], k);
    f[4][4] = exp(-dt / tau);
    for (int i = 0; i < 5; i++) {
        x[i] = 0.0;
        for (int j = 0; j < 5; j++) x[i] += f[i][j] * AT1(a[0], j);
    }
    for (int i = 0; i < 5; i++) {
        for (int j = 0; j < 5; j++) {
            fp[i][j] = 0.0;
            for (int k = 0; k < 5; k++) fp[i][j] += f[i][k] * AT(a[1], k, j);
        }
    }
    for (int i = 0; i < 5; i++) {
        for (int j = 0; j < 5; j++) {
            p[i][j] = 0.0;
            for (int k = 0; k < 5; k++) p[i][j] += fp[i][k] * f[j][k];
        }
        p[i][i] += AT1(a[3], i);
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
        AT1(a[0], i) = x[i];
        for (int j = 0; j < 5; j++) AT(a[1], i, j) = p[i][j];
    }
    release(a, 4);
    Py_RETURN_NONE;
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
enum { W_QUAT = 0, W_TURNED = 4, W_SAMPLES, W_REFERENCE, W_HOLD_LEFT, W_RUN, W_PENDING, W_CALM, W_SIZE };
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
             "samples of field (n, 3) and gyr (n, 3) rad/s that are disturbed. State: ``state`` (11,) the integrated "
             "attitude wxyz, the radians turned, the samples seen, the reference |B|, the hold left, the flagged run, "
             "the block's pending and calm counts; ``levels`` (S + 1,) the usual levels; ``ring`` (K, 7) the last K = "
             "max(widths) + smooth samples' field in the integrated frame, its mean over ``smooth`` samples and the "
             "radians turned (row = sample index mod K); ``pending`` (block, S + 1) the block's statistics per radian, "
             "``calm`` (block,) its calm samples' |B|. widths (S,) and floors (S,): the step windows in samples and "
             "their floors.");

static PyObject *watch_update(PyObject *self, PyObject *args) {
    PyObject *o_field, *o_gyr, *o_flagged, *o_state, *o_levels, *o_ring, *o_pending, *o_calm, *o_widths, *o_floors;
    double period, relative, tol_pct, learn_s, tau_s, max_reject_s, turn_floor;
    Py_ssize_t smooth, hold, block;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOdnnndddddd", &o_field, &o_gyr, &o_flagged, &o_state, &o_levels, &o_ring,
                          &o_pending, &o_calm, &o_widths, &o_floors, &period, &smooth, &hold, &block, &relative,
                          &tol_pct, &learn_s, &tau_s, &max_reject_s, &turn_floor)) {
        return NULL;
    }
    Array a[9];
    Py_buffer flags;
    if (get_array(o_field, &a[0], 2, -1, 3, 0, "field") < 0) return NULL;
    if (get_array(o_gyr, &a[1], 2, a[0].rows, 3, 0, "gyr") < 0) { release(a, 1); return NULL; }
    if (get_array(o_widths, &a[2], 1, -1, -1, 0, "widths") < 0) { release(a, 2); return NULL; }
    int steps = (int)a[2].rows;
    if (get_array(o_floors, &a[3], 1, steps, -1, 0, "floors") < 0) { release(a, 3); return NULL; }
    if (get_array(o_state, &a[4], 1, W_SIZE, -1, 1, "state") < 0) { release(a, 4); return NULL; }
    if (get_array(o_levels, &a[5], 1, steps + 1, -1, 1, "levels") < 0) { release(a, 5); return NULL; }
    if (get_array(o_ring, &a[6], 2, -1, 7, 1, "ring") < 0) { release(a, 6); return NULL; }
    if (get_array(o_pending, &a[7], 2, block, steps + 1, 1, "pending") < 0) { release(a, 7); return NULL; }
    if (get_array(o_calm, &a[8], 1, block, -1, 1, "calm") < 0) { release(a, 8); return NULL; }
    if (get_flags(o_flagged, &flags, a[0].rows, "flagged") < 0) { release(a, 9); return NULL; }
    Py_ssize_t widths[MAX_STEPS], keep = a[6].rows, longest = 0;
    double *scratch = steps <= MAX_STEPS && smooth >= 1 && block >= 1 ? PyMem_Malloc(block * sizeof(double)) : NULL;
    for (int j = 0; j < steps && j < MAX_STEPS; j++) {
        widths[j] = (Py_ssize_t)AT1(a[2], j);
        longest = widths[j] > longest ? widths[j] : longest;
    }
    if (scratch == NULL || keep != longest + smooth) {
        PyMem_Free(scratch);
        PyBuffer_Release(&flags);
        release(a, 9);
        PyErr_Format(PyExc_ValueError, "watch_update needs at most %d steps, smooth and block >= 1 and a ring of "
                     "max(widths) + smooth rows", MAX_STEPS);
        return NULL;
    }
    double state[W_SIZE];
    for (int k = 0; k < W_SIZE; k++) state[k] = AT1(a[4], k);
    char *out = (char *)flags.buf;
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
        Py_ssize_t count = g + 1 < smooth ? g + 1 : smooth; /* the mean of the last ``smooth`` (fewer at first) */
        double sum[3] = {0.0, 0.0, 0.0};
        for (Py_ssize_t m = 0, at = row; m < count; m++, at = at ? at - 1 : keep - 1) {
            for (int k = 0; k < 3; k++) sum[k] += AT(a[6], at, k);
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
        out[i * flags.strides[0]] = (char)flagged;
        state[W_SAMPLES] += 1.0;
        if ((Py_ssize_t)state[W_SAMPLES] % block == 0) {
            watch_learn(state, &a[5], &a[7], &a[8], period, tau_s, max_reject_s, steps, scratch);
        }
    }
    for (int k = 0; k < W_SIZE; k++) AT1(a[4], k) = state[k];
    PyMem_Free(scratch);
    PyBuffer_Release(&flags);
    release(a, 9);
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

/* The digits of ``v`` (v >= 0) at ``out``, at least ``width`` of them (zeros in front); returns how many. */
static int digits(unsigned long long v, int width, char *out) {
    char tmp[24];
    int n = 0;
    do { tmp[n++] = (char)('0' + v % 10); v /= 10; } while (v);
    while (n < width) tmp[n++] = '0';
    for (int i = 0; i < n; i++) out[i] = tmp[n - 1 - i];
    return n;
}

/* x with ``d`` decimals at ``out`` (room for 400 bytes); returns the bytes written. Fast integer path where the
 * rounding of x * 10^d cannot differ from that of the exact value; printf (correctly rounded, as Python) elsewhere. */
static int fixed(double x, int d, char *out) {
    static const double tens[] = {1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9};
    if (isnan(x)) { memcpy(out, "nan", 3); return 3; }
    if (isinf(x)) { if (x < 0) { memcpy(out, "-inf", 4); return 4; } memcpy(out, "inf", 3); return 3; }
    if (d <= 9) {
        double scaled = fabs(x) * tens[d];
        double whole = floor(scaled), frac = scaled - whole;
        if (scaled < 1e15 && fabs(frac - 0.5) > scaled * 1e-15 + 1e-12) {
            unsigned long long r = (unsigned long long)whole + (frac > 0.5);
            unsigned long long unit = (unsigned long long)tens[d];
            int n = 0;
            if (signbit(x)) out[n++] = '-';
            n += digits(r / unit, 1, out + n);
            if (d > 0) { out[n++] = '.'; n += digits(r % unit, d, out + n); }
            return n;
        }
    }
    return snprintf(out, 400, "%.*f", d, x);
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
    Py_ssize_t size = 64 + a.rows * a.cols * 12, pos = 0;
    char *buf = PyMem_Malloc(size);
    if (buf == NULL) { release(&a, 1); PyBuffer_Release(&decimals); return PyErr_NoMemory(); }
    for (Py_ssize_t i = 0; i < a.rows; i++) {
        for (Py_ssize_t j = 0; j < a.cols; j++) {
            if (room(&buf, &size, pos, 420) < 0) { PyMem_Free(buf); release(&a, 1); PyBuffer_Release(&decimals); return NULL; }
            double x = AT(a, i, j);
            if (dec[j] < 0 && isfinite(x) && fabs(x) < 9e18) {
                long long v = (long long)x;
                if (v < 0) { buf[pos++] = '-'; }
                pos += digits(v < 0 ? (unsigned long long)(-(v + 1)) + 1 : (unsigned long long)v, 1, buf + pos);
            } else {
                pos += fixed(x, dec[j] < 0 ? 0 : dec[j], buf + pos);
            }
            buf[pos++] = j + 1 < a.cols ? ',' : '\n';
        }
    }
    PyObject *out = PyBytes_FromStringAndSize(buf, pos);
    PyMem_Free(buf);
    release(&a, 1);
    PyBuffer_Release(&decimals);
    return out;
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
    {"format_rows", format_rows, METH_VARARGS, format_rows_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "magnet._kernels",
    "The filters' per-sample loops, compiled (see magnet/_kernels.c).", -1, methods,
};

PyMODINIT_FUNC PyInit__kernels(void) { return PyModule_Create(&module); }
