/* Fused element-wise kernels of the agent's GRU step, for service.inference.FastPolicy.
 *
 * The GEMMs stay with torch (MKL for float32, oneDNN/AMX for bfloat16); everything
 * between them is done here in one pass over each row, which replaces about ten torch
 * calls per layer (each a full pass over memory) and the dtype conversions around
 * bfloat16 GEMMs. Every function takes raw addresses (from ``Tensor.data_ptr()``) and
 * row strides in elements; the Python side owns shapes, dtypes and lifetimes. The GIL is
 * released while a kernel runs, so two threads step two halves of a batch in parallel.
 *
 * Conventions (PyTorch's nn.GRU, gates ordered r, z, n; gamma: forgetting factor):
 *   pre:      dst = gamma h_prev                                 (the GEMM's h input)
 *   GEMM:     gates = [x, 1, h, 1] W = [a_r | a_z | a_in | a_hn] (biases folded into W)
 *   post:     r = sigmoid(a_r), z = sigmoid(a_z), n = tanh(a_in + r a_hn),
 *             h' = n + z (gamma h_prev - n), written over h_prev in place,
 *             optionally also to the next layer's GEMM input and to a float32 output.
 *   features: [kp, ki, e, int_e] -> [log max(kp, floor), log max(ki, floor),
 *             clip(e, -e_clip, e_clip), sign(int_e) log(1 + |int_e|)].
 *
 * exp is a degree-6 polynomial on a range-reduced argument (relative error below 3e-7,
 * close to float32 rounding), written so that GCC vectorises every inner loop;
 * x86-64 builds carry AVX-512, AVX2 and baseline clones chosen at load time.
 * bfloat16 is converted with round-to-nearest-even (inputs are finite).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#define MULTIVERSION __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define MULTIVERSION
#endif

#define HMAX 512 /* widest hidden layer the row buffers hold */
#define LANES 16 /* the compute loop runs over whole vectors (padding is zero) */

static inline float u2f(uint32_t u) { float f; memcpy(&f, &u, 4); return f; }
static inline uint32_t f2u(float f) { uint32_t u; memcpy(&u, &f, 4); return u; }
static inline float bf2f(uint16_t v) { return u2f((uint32_t)v << 16); }
static inline uint16_t f2bf(float f) {
    uint32_t u = f2u(f);
    return (uint16_t)((u + 0x7fffu + ((u >> 16) & 1u)) >> 16);
}

/* exp(x) for |x| <= 40; callers clamp (a ternary vectorises, fminf needs finite-math) */
static inline float fexp(float x) {
    const float t = x * 1.44269504088896341f; /* exp(x) = 2^t = 2^n 2^f, |f| <= 1/2 */
    const float n = rintf(t);
    const float f = t - n;
    float p = 1.535336188319500e-4f;
    p = p * f + 1.339887440266574e-3f;
    p = p * f + 9.618437357674640e-3f;
    p = p * f + 5.550332471162809e-2f;
    p = p * f + 2.402264791363012e-1f;
    p = p * f + 6.931472028550421e-1f;
    p = p * f + 1.0f;
    return p * u2f((uint32_t)((int32_t)n + 127) << 23);
}
/* sigmoid and tanh saturate to within 4e-18 beyond |40|: clamping there keeps
 * products of two (1 + exp) terms finite, so r and z share one division */
static inline float clamp40(float x) {
    x = x < -40.0f ? -40.0f : x;
    return x > 40.0f ? 40.0f : x;
}
static inline float ftanh(float x) { return 2.0f / (1.0f + fexp(clamp40(-2.0f * x))) - 1.0f; }

static inline void load_row(float *restrict dst, const void *src, int64_t n, int bf16) {
    if (bf16) {
        const uint16_t *restrict s = src;
        for (int64_t j = 0; j < n; j++) dst[j] = bf2f(s[j]);
    } else {
        memcpy(dst, src, (size_t)n * sizeof(float));
    }
}

static inline void store_row(void *dst, const float *restrict src, int64_t n, int bf16) {
    if (bf16) {
        uint16_t *restrict d = dst;
        for (int64_t j = 0; j < n; j++) d[j] = f2bf(src[j]);
    } else {
        memcpy(dst, src, (size_t)n * sizeof(float));
    }
}

static inline char *row(intptr_t base, int64_t i, int64_t stride, int bf16) {
    return (char *)base + i * stride * (bf16 ? 2 : 4);
}

MULTIVERSION
static void gru_pre(int64_t b, int64_t hid, const float *h, int64_t hs, const float *gamma,
                    intptr_t dst, int64_t ds, int bf16) {
    float tmp[HMAX];
    for (int64_t i = 0; i < b; i++) {
        const float g = gamma[i];
        const float *restrict hi = h + i * hs;
        for (int64_t j = 0; j < hid; j++) tmp[j] = g * hi[j];
        store_row(row(dst, i, ds, bf16), tmp, hid, bf16);
    }
}

MULTIVERSION
static void gru_post(int64_t b, int64_t hid, intptr_t gates, int64_t gs, int bf16, float *h,
                     int64_t hs, const float *gamma, intptr_t next, int64_t ns, intptr_t out,
                     int64_t os) {
    /* one row's gates and states, padded to whole vectors (the padding stays zero) */
    float ar[HMAX] = {0}, az[HMAX] = {0}, ain[HMAX] = {0}, ahn[HMAX] = {0};
    float hp[HMAX] = {0}, hn[HMAX];
    const int64_t padded = (hid + LANES - 1) / LANES * LANES;
    for (int64_t i = 0; i < b; i++) {
        const char *gi = row(gates, i, gs, bf16);
        const int64_t width = bf16 ? 2 : 4;
        load_row(ar, gi, hid, bf16);
        load_row(az, gi + hid * width, hid, bf16);
        load_row(ain, gi + 2 * hid * width, hid, bf16);
        load_row(ahn, gi + 3 * hid * width, hid, bf16);
        float *restrict hi = h + i * hs;
        const float g = gamma[i];
        for (int64_t j = 0; j < hid; j++) hp[j] = g * hi[j];
        for (int64_t jb = 0; jb < padded; jb += LANES) {
            for (int l = 0; l < LANES; l++) {
                const int64_t j = jb + l;
                /* r = 1 / dr, z = 1 / dz with a single division */
                const float dr = 1.0f + fexp(clamp40(-ar[j]));
                const float dz = 1.0f + fexp(clamp40(-az[j]));
                const float inv = 1.0f / (dr * dz);
                const float r = dz * inv, z = dr * inv;
                const float n = ftanh(ain[j] + r * ahn[j]);
                hn[j] = n + z * (hp[j] - n);
            }
        }
        memcpy(hi, hn, (size_t)hid * sizeof(float));
        if (next) store_row(row(next, i, ns, bf16), hn, hid, bf16);
        if (out) memcpy((float *)out + i * os, hn, (size_t)hid * sizeof(float));
    }
}

MULTIVERSION
static void gru_features(int64_t b, const float *obs, float *gains, intptr_t x, int64_t xs,
                         int bf16, float floor, float e_clip) {
    for (int64_t i = 0; i < b; i++) {
        const float *o = obs + 4 * i;
        const float kp = o[0] > floor ? o[0] : floor, ki = o[1] > floor ? o[1] : floor;
        const float e = o[2] < -e_clip ? -e_clip : (o[2] > e_clip ? e_clip : o[2]);
        const float ie = o[3];
        const float f[4] = {logf(kp), logf(ki), e, copysignf(log1pf(fabsf(ie)), ie)};
        gains[2 * i] = kp;
        gains[2 * i + 1] = ki;
        store_row(row(x, i, xs, bf16), f, 4, bf16);
    }
}

static int check_width(Py_ssize_t hid) {
    if (hid < 1 || hid > HMAX) {
        PyErr_Format(PyExc_ValueError, "hidden width must be in [1, %d], got %zd", HMAX, hid);
        return 0;
    }
    return 1;
}

static PyObject *py_pre(PyObject *self, PyObject *args) {
    Py_ssize_t b, hid, h, hs, gamma, dst, ds;
    int bf16;
    if (!PyArg_ParseTuple(args, "nnnnnnnp", &b, &hid, &h, &hs, &gamma, &dst, &ds, &bf16))
        return NULL;
    if (!check_width(hid)) return NULL;
    Py_BEGIN_ALLOW_THREADS
    gru_pre(b, hid, (const float *)h, hs, (const float *)gamma, (intptr_t)dst, ds, bf16);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

static PyObject *py_post(PyObject *self, PyObject *args) {
    Py_ssize_t b, hid, gates, gs, h, hs, gamma, next, ns, out, os;
    int bf16;
    if (!PyArg_ParseTuple(args, "nnnnpnnnnnnn", &b, &hid, &gates, &gs, &bf16, &h, &hs, &gamma,
                          &next, &ns, &out, &os))
        return NULL;
    if (!check_width(hid)) return NULL;
    Py_BEGIN_ALLOW_THREADS
    gru_post(b, hid, (intptr_t)gates, gs, bf16, (float *)h, hs, (const float *)gamma,
             (intptr_t)next, ns, (intptr_t)out, os);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

static PyObject *py_features(PyObject *self, PyObject *args) {
    Py_ssize_t b, obs, gains, x, xs;
    int bf16;
    float floor, e_clip;
    if (!PyArg_ParseTuple(args, "nnnnnpff", &b, &obs, &gains, &x, &xs, &bf16, &floor, &e_clip))
        return NULL;
    Py_BEGIN_ALLOW_THREADS
    gru_features(b, (const float *)obs, (float *)gains, (intptr_t)x, xs, bf16, floor, e_clip);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"pre", py_pre, METH_VARARGS,
     "pre(b, hid, h, h_stride, gamma, dst, dst_stride, bf16): dst = gamma h"},
    {"post", py_post, METH_VARARGS,
     "post(b, hid, gates, gates_stride, bf16, h, h_stride, gamma, next, next_stride, out, "
     "out_stride): the GRU update from the gates, in place on h"},
    {"features", py_features, METH_VARARGS,
     "features(b, obs, gains, x, x_stride, bf16, floor, e_clip): the agent's input features"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_gru", "Fused element-wise kernels of the agent's GRU step.", -1,
    methods,
};

PyMODINIT_FUNC PyInit__gru(void) {
    PyObject *m = PyModule_Create(&module);
    if (m && PyModule_AddIntConstant(m, "MAX_HIDDEN", HMAX) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
