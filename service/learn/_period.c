/* One RL period of the training environment's closed loops, for service.learn.env.
 *
 * TuningEnv.step runs 275 controller samples per RL period; in numpy each sample is a
 * dozen calls on arrays of a few hundred episodes, so the interpreter, not the
 * arithmetic, took two thirds of an imitation epoch. This kernel runs the same sample
 * loop over every episode in C: the same operations in the same order on the same
 * doubles, so its results equal the numpy path's bit for bit (built with
 * -ffp-contract=off: a fused multiply-add would round differently; tests compare the two
 * paths exactly). The numpy path (plant_sim's FOPTDBatch.step and PIBatch.step) stays the
 * definition and the fallback where the extension is not built.
 *
 * Per episode i and sample j (arrays row-major, (n,) or (n, inner)):
 *   err = target.x - plant.x;      sq += min(err^2, err_cap)
 *   y = plant.x (+ noise: ns = a_n ns + w_n[j]; y = y + ns);   e[j] = sp[j] - y
 *   int_e += e dt
 *   PI (parallel, clamped; conditional integration: the integral moves at most to the
 *   value that puts the output on a limit, as plant_sim.pi.PIBatch._limited): u
 *   load walk: lw = a_w lw + w_w[j];   plant input u + (load[j] + lw)
 *   FOPTD plant with its dead-time ring buffer (and an optional second lag), then the
 *   target filter (an FOPTD of gain 1) driven by sp[j].
 * The ring buffers' write position is shared by all rows; the caller advances it.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>

typedef struct {
    double *x, *x1, *buf, *a, *b, *a2;
    const int64_t *delay;
    const uint8_t *lag2; /* per row: a second lag follows (NULL: none anywhere) */
    Py_ssize_t width;    /* ring buffer length */
} Lag;

/* FOPTDBatch.step for one row: write u at ptr, read it back delay samples later. */
static inline void lag_step(const Lag *p, Py_ssize_t i, Py_ssize_t ptr, double u) {
    double *row = p->buf + i * p->width;
    row[ptr] = u;
    Py_ssize_t at = (ptr - p->delay[i]) % p->width;
    if (at < 0) at += p->width;
    const double delayed = row[at];
    if (!p->lag2) {
        p->x[i] = p->a[i] * p->x[i] + p->b[i] * delayed;
        if (p->x1 != p->x) p->x1[i] = p->x[i];
        return;
    }
    p->x1[i] = p->a[i] * p->x1[i] + p->b[i] * delayed;
    const double lagged = p->a2[i] * p->x[i] + (1.0 - p->a2[i]) * p->x1[i];
    p->x[i] = p->lag2[i] ? lagged : p->x1[i];
}

static inline double clip(double v, double lo, double hi) {
    v = v < lo ? lo : v; /* np.clip: NaN passes through */
    return v > hi ? hi : v;
}

/* np.minimum / np.maximum: a NaN in either operand is the result; a tie gives the second
 * operand, as numpy's loops do (so signed zeros come out the same) */
static inline double np_min(double a, double b) { return (a < b || a != a) ? a : b; }
static inline double np_max(double a, double b) { return (a > b || a != a) ? a : b; }

#define PTR(T, v) ((T *)(intptr_t)(v))

static PyObject *py_run(PyObject *self, PyObject *args) {
    Py_ssize_t n, inner, ptr_p, ptr_t;
    /* plant, target */
    Py_ssize_t px, px1, pbuf, pa, pb, pa2, pdelay, plag2, pwidth;
    Py_ssize_t tx, tbuf, ta, tb, tdelay, twidth;
    /* PI */
    Py_ssize_t kp, ki, bias, integral, e_last, saturated;
    double dt, u_min, u_max, err_cap;
    /* signals and states */
    Py_ssize_t sp, e_out, sq, int_e, ns, a_n, w_n, load, lw, w_w;
    double a_w;
    if (!PyArg_ParseTuple(args, "nnnnnnnnnnnnnnnnnnnnnnnnnddddnnnnnnnnnnd", &n, &inner, &ptr_p,
                          &ptr_t, &px, &px1, &pbuf, &pa, &pb, &pa2, &pdelay, &plag2, &pwidth,
                          &tx, &tbuf, &ta, &tb, &tdelay, &twidth, &kp, &ki, &bias, &integral,
                          &e_last, &saturated, &dt, &u_min, &u_max, &err_cap, &sp, &e_out, &sq,
                          &int_e, &ns, &a_n, &w_n, &load, &lw, &w_w, &a_w))
        return NULL;
    if (n < 0 || inner < 0 || pwidth < 1 || twidth < 1) {
        PyErr_SetString(PyExc_ValueError, "bad sizes");
        return NULL;
    }
    const Lag plant = {PTR(double, px), PTR(double, px1), PTR(double, pbuf), PTR(double, pa),
                       PTR(double, pb), PTR(double, pa2), PTR(const int64_t, pdelay),
                       PTR(const uint8_t, plag2), pwidth};
    const Lag target = {PTR(double, tx), PTR(double, tx), PTR(double, tbuf), PTR(double, ta),
                        PTR(double, tb), NULL, PTR(const int64_t, tdelay), NULL, twidth};
    double *Kp = PTR(double, kp), *Ki = PTR(double, ki), *Bias = PTR(double, bias);
    double *I = PTR(double, integral), *E_last = PTR(double, e_last);
    uint8_t *Sat = PTR(uint8_t, saturated);
    const double *Sp = PTR(const double, sp), *A_n = PTR(const double, a_n);
    const double *W_n = PTR(const double, w_n), *Load = PTR(const double, load);
    const double *W_w = PTR(const double, w_w);
    double *E = PTR(double, e_out), *Sq = PTR(double, sq), *Int_e = PTR(double, int_e);
    double *Ns = PTR(double, ns), *Lw = PTR(double, lw);
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t j = 0; j < inner; j++) {
        const Py_ssize_t at_p = (ptr_p + j) % pwidth, at_t = (ptr_t + j) % twidth;
        for (Py_ssize_t i = 0; i < n; i++) {
            const Py_ssize_t k = i * inner + j;
            const double err = target.x[i] - plant.x[i];
            const double sq_err = err * err;
            Sq[i] = Sq[i] + (sq_err > err_cap ? err_cap : sq_err);
            double y = plant.x[i];
            if (Ns) {
                Ns[i] = A_n[i] * Ns[i] + W_n[k];
                y = y + Ns[i];
            }
            const double e = Sp[k] - y;
            E[k] = e;
            Int_e[i] = Int_e[i] + e * dt;
            /* PIBatch.step: the integral advanced as far as PIBatch._limited lets it */
            const double on_high = u_max - Bias[i] - Kp[i] * e;
            const double on_low = u_min - Bias[i] - Kp[i] * e;
            const double integ = np_min(I[i] + Ki[i] * e * dt, np_max(I[i], on_high));
            I[i] = np_max(integ, np_min(I[i], on_low));
            const double raw = Bias[i] + Kp[i] * e + I[i];
            Sat[i] = (uint8_t)(raw >= u_max || raw <= u_min);
            E_last[i] = e;
            double u = clip(raw, u_min, u_max);
            if (Load) {
                if (W_w) Lw[i] = a_w * Lw[i] + W_w[k];
                u = u + (Load[k] + Lw[i]);
            }
            lag_step(&plant, i, at_p, u);
            lag_step(&target, i, at_t, Sp[k]);
        }
    }
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"run", py_run, METH_VARARGS,
     "run(...): one RL period of the training environment's loops, in place (see "
     "service.learn.env.TuningEnv._run_kernel for the arguments)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_period", "One RL period of the training environment's loops.",
    -1, methods,
};

PyMODINIT_FUNC PyInit__period(void) { return PyModule_Create(&module); }
