/* rcotorch.engine._engine: the native CPU kernels, built as a Python extension when the package is installed.
 *
 *   run          a graph lowered to instructions (rcotorch/engine/lowering.py), run for T steps
 *   rls          rls_update on batched tensors, through the same RLS code as the estimator's step
 *   uniform_grid the integer part of rcotorch.engine.rng.normal on a (member, pair of steps, component) grid
 *   health_bounds the member health checks' bounds (definiteness, windup, runaway) of every member
 *   window_gram  the sum of the regressors' outer products over the estimator's window, per member
 *   window_sums  the intervals' replay: the Gram sums of a stretch's sensitivities and regressors, per member
 *   residual_sums the intervals' replay: the residual checks' lagged and plain sums of a stretch, per member
 *   markov_filter the intervals' replay: the regressors of a stretch filtered by the Markov parameters
 *   lti_markov   the Markov parameters of one linear system per member, written where the estimator keeps them
 *
 * Members are independent, so a batch is cut into chunks of VL lanes (VL = 1, 4, 8 or 16, chosen by the
 * caller from the batch size); each chunk runs all T steps on its own (a thread per chunk, OpenMP), so
 * nothing is synchronized between steps. The operations are written once, in lanes.h, and compiled for each
 * lane width and, on x86-64 with GCC, for AVX-512, AVX2 and the baseline instruction set (chosen when the
 * module loads). Arithmetic is plain IEEE double without contraction or reassociation (-ffp-contract=off,
 * no fast-math), so a member's result is the same bits whatever the lane width, batch or thread count.
 *
 * The functions take tensors as addresses (int) and sizes; rcotorch.engine.kernels checks shapes, dtypes and
 * contiguity before it calls them.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif

#include "engine.h"

/* Helpers inlined into every variant (a plain static inline function is not inlined across the variants'
 * instruction-set options). */
#define ALWAYS __attribute__((always_inline))

/* ------------------------------------------------------------------------------------------------------ */
/* Helpers shared by every variant                                                                         */
/* ------------------------------------------------------------------------------------------------------ */

/* rng._mix32 on a 32-bit value. */
static inline ALWAYS uint32_t mix32(uint32_t y) {
    y ^= y >> 16;
    y *= 0x7FEB352Du;
    y ^= y >> 15;
    y *= 0x846CA68Bu;
    return y ^ (y >> 16);
}

/* rng._mix32(key + 0x632BE5AB) for a 32-bit key: the sum has 33 bits and the first xor-shift sees the top
 * one (as the int64 code does); the rest is 32-bit arithmetic. */
static inline ALWAYS uint32_t mix32_key(uint32_t key) {
    uint32_t lo = key + 0x632BE5ABu, hi = lo < key; /* carry */
    uint32_t y = lo ^ ((lo >> 16) | (hi << 16));
    y *= 0x7FEB352Du;
    y ^= y >> 15;
    y *= 0x846CA68Bu;
    return y ^ (y >> 16);
}

/* rng.uniform's last two keys and its 53-bit mantissa, from the hash of the keys before them. */
static inline ALWAYS double uniform53(uint32_t h) {
    int32_t a = (int32_t)(mix32(h ^ mix32_key(0x1B873593u)) >> 5);
    int32_t b = (int32_t)(mix32(h ^ mix32_key(0x5BD1E995u)) >> 6);
    return ((double)a * 67108864.0 + (double)b + 0.5) / 9007199254740992.0;
}

/* log, cos and sin for the noise, in plain double arithmetic without branches or calls, so that a loop over
 * lanes vectorizes and every lane width gives the same bits (libm's scalar functions would serialize the
 * lanes). Accurate to about an ulp; the PyTorch engine's samples (torch.log, torch.cos, torch.sin) agree to rounding. */
static inline ALWAYS double as_double(uint64_t b) {
    double d;
    memcpy(&d, &b, sizeof d);
    return d;
}

static inline ALWAYS uint64_t as_bits(double d) {
    uint64_t b;
    memcpy(&b, &d, sizeof b);
    return b;
}

/* log(x) for a normal x > 0: x = 2^e m, m in [sqrt(1/2), sqrt(2)), log m = 2 atanh(f), f = (m - 1) / (m + 1). */
static inline ALWAYS double log_pos(double x) {
    uint64_t b = as_bits(x);
    double e = as_double(0x4330000000000000ull | (b >> 52)) - 4503599627371519.0; /* (b >> 52) - 1023, exact */
    double m = as_double((b & 0x000FFFFFFFFFFFFFull) | 0x3FF0000000000000ull);
    int big = m > 1.4142135623730951;
    m = big ? m * 0.5 : m;
    e = big ? e + 1.0 : e;
    double f = (m - 1.0) / (m + 1.0), s = f * f;
    double p = 1.0 / 23;
    p = p * s + 1.0 / 21;
    p = p * s + 1.0 / 19;
    p = p * s + 1.0 / 17;
    p = p * s + 1.0 / 15;
    p = p * s + 1.0 / 13;
    p = p * s + 1.0 / 11;
    p = p * s + 1.0 / 9;
    p = p * s + 1.0 / 7;
    p = p * s + 1.0 / 5;
    p = p * s + 1.0 / 3;
    double two_f = f + f;
    return e * 6.93147180369123816490e-01 + (e * 1.90821492927058770002e-10 + (two_f + two_f * (p * s)));
}

/* cos(2 pi u) and sin(2 pi u) for u in [0, 1]: d = u - round(u) in [-1/2, 1/2] (exact), |d| reduced exactly to
 * t in [-1/8, 1/8] and a quadrant q, Taylor polynomials of cos t and sin t on [-pi/4, pi/4]; then
 * cos(2 pi |d|) = cos t, -sin t, -cos t and sin(2 pi |d|) = sin t, cos t, -sin t for q = 0, 1, 2, the sine
 * taking the sign of d. */
static inline ALWAYS void sincos_2pi(double u, double *cs, double *sn) {
    const double big = 6755399441055744.0;            /* 1.5 * 2^52: x + big - big rounds x to an integer */
    double d = u - ((u + big) - big);                 /* u - round(u) in [-1/2, 1/2], exact */
    double r = fabs(d);
    double q = (r * 4.0 + big) - big;                 /* quadrant 0, 1 or 2 */
    double t = (r - q * 0.25) * 6.283185307179586, t2 = t * t;
    double c = -1.0 / 20922789888000.0;
    c = c * t2 + 1.0 / 87178291200.0;
    c = c * t2 - 1.0 / 479001600.0;
    c = c * t2 + 1.0 / 3628800.0;
    c = c * t2 - 1.0 / 40320.0;
    c = c * t2 + 1.0 / 720.0;
    c = c * t2 - 1.0 / 24.0;
    c = c * t2 + 0.5;
    c = 1.0 - c * t2;
    double s = 1.0 / 355687428096000.0;
    s = s * t2 - 1.0 / 1307674368000.0;
    s = s * t2 + 1.0 / 6227020800.0;
    s = s * t2 - 1.0 / 39916800.0;
    s = s * t2 + 1.0 / 362880.0;
    s = s * t2 - 1.0 / 5040.0;
    s = s * t2 + 1.0 / 120.0;
    s = s * t2 - 1.0 / 6.0;
    s = t + t * (s * t2);
    *cs = q == 0.0 ? c : q == 1.0 ? -s : -c;
    *sn = copysign(q == 0.0 ? s : q == 1.0 ? c : -s, d);
}

/* A 32-bit key held exactly in a double slot, back as an integer (the low bits of key + 2^52). */
static inline ALWAYS uint32_t key_u32(double key) { return (uint32_t)as_bits(key + 4503599627370496.0); }

/* Box-Muller, in the order of sources._normal_grid: the normals of a pair of steps, r cos(2 pi u2) and
 * r sin(2 pi u2) with r = sqrt(log(u1) * -2). */
static inline ALWAYS void normal_pair(double u1, double u2, double *even, double *odd) {
    double r = sqrt(log_pos(u1) * -2.0), c, s;
    sincos_2pi(u2, &c, &s);
    *even = r * c;
    *odd = r * s;
}

/* k mod W without a division, m = 2^64 / W + 1 rounded down (exact for k and W below 2^32: the multiply-shift
 * remainder of Lemire, Kaser and Kurz, "Faster remainder by direct computation", 2019); a division beyond. */
static inline ALWAYS int64_t ring_row(int64_t k, int64_t W, uint64_t m) {
    if ((uint64_t)k >> 32) return k % W;
    return (int64_t)(((unsigned __int128)(m * (uint64_t)k) * (uint64_t)W) >> 64);
}

/* torch.clamp: NaN stays NaN. */
static inline ALWAYS double clampd(double x, double lo, double hi) {
    double v = x < lo ? lo : x;
    return v > hi ? hi : v;
}

/* Four and two doubles as one value (GNU C vectors), for moving 4 x 4 blocks between members' rows and lane
 * arrays and for one member's Markov filter; read and written in place of doubles at any 8-byte alignment. */
typedef double v4d_t __attribute__((vector_size(32), aligned(8), may_alias));
typedef double v2d_t __attribute__((vector_size(16), aligned(8), may_alias));
#if defined(__clang__)
#define SHUF4(a, b, i, j, k, l) __builtin_shufflevector(a, b, i, j, k, l)
#else
typedef long long v4i_t __attribute__((vector_size(32)));
#define SHUF4(a, b, i, j, k, l) __builtin_shuffle(a, b, (v4i_t){i, j, k, l})
#endif

/* Scratch layouts: lists of regions (lane arrays), each its name and its size in slots, in order. From one
 * list come a struct of the regions' offsets (NAME_at: X_AT) and the total (NAME_SIZE: a constant expression
 * where the sizes are constants). */
#define X_REGION(name, size) int64_t name;
#define X_AT(name, size) o.name = o.end; o.end += (size);
#define X_SIZE(name, size) +(size)

/* One RLS step (lanes.h, rls) with n parameters and nl rows: a = P Psi (n x nl), the step (n), S and its
 * Cholesky factor L (nl x nl), W = P Psi L^-T (n x nl), v = L^-1 z_R (nl). */
#define RLS_SCRATCH(X, n, nl) X(a, (n) * (nl)) X(step, (n)) X(L, (nl) * (nl)) X(W, (n) * (nl)) X(v, (nl))
#define RLS_SCRATCH_SIZE(n, nl) (0 RLS_SCRATCH(X_SIZE, n, nl))
typedef struct { RLS_SCRATCH(X_REGION, 0, 0) int64_t end; } rls_scratch_t;
static inline ALWAYS rls_scratch_t rls_scratch_at(int64_t n, int64_t nl) {
    rls_scratch_t o = {0};
    RLS_SCRATCH(X_AT, n, nl)
    return o;
}

/* One estimator update (lanes.h, rco_upd_n) with n_u outputs, n_z errors, n_phi regressors, n parameters and
 * nl rows: the Markov filter's products (n_z n_u (n_phi + n_u)), Psi (n x nl), eta (n), the member's
 * activity and health (1 each), the rows' residuals (nl), the RLS step's scratch and z_R (n_z; the update
 * keeps it there when it holds its scratch in an array of its own, else in the estimator's state slots). */
#define RCO_UPD_SCRATCH(X, n_u, n_z, n_phi, n, nl)                                                           \
    X(prod, (n_z) * (n_u) * ((n_phi) + (n_u))) X(psi, (n) * (nl)) X(eta, (n)) X(act, 1) X(ok, 1) X(zrx, (nl))  \
    X(rls, RLS_SCRATCH_SIZE(n, nl)) X(zr, (n_z))
#define RCO_UPD_SCRATCH_SIZE(n_u, n_z, n_phi, n, nl) (0 RCO_UPD_SCRATCH(X_SIZE, n_u, n_z, n_phi, n, nl))
typedef struct { RCO_UPD_SCRATCH(X_REGION, 0, 0, 0, 0, 0) int64_t end; } rco_upd_scratch_t;
static inline ALWAYS rco_upd_scratch_t rco_upd_scratch_at(int64_t n_u, int64_t n_z, int64_t n_phi, int64_t n,
                                                          int64_t nl) {
    rco_upd_scratch_t o = {0};
    RCO_UPD_SCRATCH(X_AT, n_u, n_z, n_phi, n, nl)
    return o;
}

/* The arena of one chunk of rls_update (lanes.h, rls_chunk): theta (n), P (n x n), Psi (n x nl), z_R (nl),
 * lambda (1), R^-1 (nl x nl), active and ok (1 each), the RLS step's scratch. */
#define RLS_ARENA(X, n, nl)                                                                                  \
    X(theta, (n)) X(P, (n) * (n)) X(psi, (n) * (nl)) X(zr, (nl)) X(lam, 1) X(rinv, (nl) * (nl)) X(act, 1)       \
    X(ok, 1) X(scratch, RLS_SCRATCH_SIZE(n, nl))
typedef struct { RLS_ARENA(X_REGION, 0, 0) int64_t end; } rls_arena_t;
static inline ALWAYS rls_arena_t rls_arena_at(int64_t n, int64_t nl) {
    rls_arena_t o = {0};
    RLS_ARENA(X_AT, n, nl)
    return o;
}

typedef struct {
    const int64_t *code, *binds, *ptrs, *counters, *obs;
    const double *consts;
    int64_t ncode, nbind, nobs, nslots, T, B;
} run_t;

typedef struct {
    double *theta, *P;
    const double *psi, *zr, *lam, *rinv;
    const uint8_t *active;
    uint8_t *ok;
    int64_t n, nl, lam_stride;
    int lam_one;
} rls_t;

/* Where lti_markov writes (rcotorch.engine.kernels.MarkovTarget): value t of entry e (= r m + k) of the member in
 * row `row` goes to base[row srow + t st + e se + c coff] for each copy c < copies (st may be negative: a layout
 * reversed in time). */
typedef struct {
    double *base;
    int64_t srow, st, se, copies, coff;
} markov_target_t;

#define MARKOV_TARGETS 3
typedef struct {
    const double *A, *Bm, *C, *D0; /* D0 read only where d = 0 */
    const int64_t *rows;           /* the members' rows in the targets; NULL: the member's own index */
    uint8_t *stable;               /* NULL: no stability test, every member written */
    int64_t N, m, p, d, nu, ntargets;
    markov_target_t t[MARKOV_TARGETS];
} markov_t;

/* The arena of one chunk of lti_markov (lanes.h, markov_chunk): A, C, X and A X, two powers of A, the test's
 * verdict, an accumulator and the nu parameters twice (in lanes, and by member). */
static inline int64_t markov_slots(int64_t N, int64_t m, int64_t p, int64_t nu) {
    return 3 * N * N + p * N + 2 * N * m + 2 + 2 * nu * p * m;
}

/* ------------------------------------------------------------------------------------------------------ */
/* The variants: lanes.h for each lane width and instruction set                                          */
/* ------------------------------------------------------------------------------------------------------ */
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#define FN(name) CAT(CAT(name, _), CAT(VL, ISA))

#define RFN(name) CAT(CAT(name, _), ISA)
#define ISA base
#include "widths.h"
#include "replay.h"
#undef ISA

#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#define RCO_MULTI_ISA 1
#pragma GCC push_options
#pragma GCC target("avx2")
#define ISA avx2
#include "widths.h"
#include "replay.h"
#undef ISA
#pragma GCC pop_options
#pragma GCC push_options
#pragma GCC target("avx512f,avx512dq,avx512vl,avx512bw,avx2")
#define ISA avx512
#include "widths.h"
#include "replay.h"
#undef ISA
#pragma GCC pop_options
#endif

typedef void (*chunk_fn)(const run_t *, double *, int64_t, int64_t);
typedef void (*rls_fn)(const rls_t *, double *, int64_t, int64_t);
typedef void (*markov_fn)(const markov_t *, double *, int64_t, int64_t);

static const int LANE_WIDTHS[4] = {1, 4, 8, 16};
static chunk_fn CHUNK[4] = {chunk_1base, chunk_4base, chunk_8base, chunk_16base};
static rls_fn RLS[4] = {rls_chunk_1base, rls_chunk_4base, rls_chunk_8base, rls_chunk_16base};
static markov_fn MARKOV[4] = {markov_chunk_1base, markov_chunk_4base, markov_chunk_8base, markov_chunk_16base};
static const char *ISA_NAME = "baseline";
typedef int (*window_sums_fn)(int64_t, int64_t, int64_t, int64_t, int64_t, int64_t, const double *, const double *,
                               const double *, const double *, const double *, const int64_t *, const double *,
                               const double *, double *, int64_t, double *, double *, double *, int);
typedef int (*markov_filter_fn)(int64_t, int64_t, int64_t, int64_t, int64_t, int64_t, const double *,
                                 const double *, int, double *, int);
typedef int (*residual_sums_fn)(int64_t, int64_t, int64_t, int64_t, int64_t, int64_t, int64_t, const int64_t *,
                                 int64_t, const double *, const double *, const double *, const double *, double *,
                                 double *, double *, double *, double *, double *, int64_t, int);
static window_sums_fn WINDOW_SUMS = window_sums_base;
static residual_sums_fn RESIDUAL_SUMS = residual_sums_base;
static markov_filter_fn MARKOV_FILTER = markov_filter_base;

static void select_isa(void) {
#ifdef RCO_MULTI_ISA
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq") &&
        __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("avx512bw")) {
        chunk_fn c[4] = {chunk_1avx512, chunk_4avx512, chunk_8avx512, chunk_16avx512};
        rls_fn r[4] = {rls_chunk_1avx512, rls_chunk_4avx512, rls_chunk_8avx512, rls_chunk_16avx512};
        markov_fn k[4] = {markov_chunk_1avx512, markov_chunk_4avx512, markov_chunk_8avx512, markov_chunk_16avx512};
        memcpy(CHUNK, c, sizeof c);
        memcpy(RLS, r, sizeof r);
        memcpy(MARKOV, k, sizeof k);
        WINDOW_SUMS = window_sums_avx512;
        RESIDUAL_SUMS = residual_sums_avx512;
        MARKOV_FILTER = markov_filter_avx512;
        ISA_NAME = "avx512";
    } else if (__builtin_cpu_supports("avx2")) {
        chunk_fn c[4] = {chunk_1avx2, chunk_4avx2, chunk_8avx2, chunk_16avx2};
        rls_fn r[4] = {rls_chunk_1avx2, rls_chunk_4avx2, rls_chunk_8avx2, rls_chunk_16avx2};
        markov_fn k[4] = {markov_chunk_1avx2, markov_chunk_4avx2, markov_chunk_8avx2, markov_chunk_16avx2};
        memcpy(CHUNK, c, sizeof c);
        memcpy(RLS, r, sizeof r);
        memcpy(MARKOV, k, sizeof k);
        WINDOW_SUMS = window_sums_avx2;
        RESIDUAL_SUMS = residual_sums_avx2;
        MARKOV_FILTER = markov_filter_avx2;
        ISA_NAME = "avx2";
    }
#endif
}

static int lane_index(int64_t vl) {
    for (int i = 0; i < 4; i++)
        if (LANE_WIDTHS[i] == vl) return i;
    return -1;
}

/* Run fn over ceil(B / VL) chunks on nthreads threads, each with its own arena of nslots slots. */
static int parallel_chunks(void (*fn)(const void *, void *, double *, int64_t, int64_t), const void *ctx,
                           void *f, int64_t nslots, int64_t B, int64_t vl, int nthreads) {
    int64_t nchunks = (B + vl - 1) / vl;
    int fail = 0;
    if (nthreads > nchunks) nthreads = (int)nchunks;
#ifdef _OPENMP
#pragma omp parallel num_threads(nthreads) if (nthreads > 1) reduction(| : fail)
#endif
    {
        size_t bytes = ((size_t)(nslots > 0 ? nslots : 1) * (size_t)vl * sizeof(double) + 63) & ~(size_t)63;
        double *S = (double *)aligned_alloc(64, bytes);
        if (!S) {
            fail = 1;
        } else {
            memset(S, 0, bytes);
#ifdef _OPENMP
#pragma omp for schedule(static)
#endif
            for (int64_t ch = 0; ch < nchunks; ch++) {
                int64_t b0 = ch * vl;
                fn(ctx, f, S, b0, B - b0 < vl ? B - b0 : vl);
            }
            free(S);
        }
    }
    return fail;
}

static void call_chunk(const void *ctx, void *f, double *S, int64_t b0, int64_t nb) {
    ((chunk_fn)f)((const run_t *)ctx, S, b0, nb);
}

static void call_rls(const void *ctx, void *f, double *S, int64_t b0, int64_t nb) {
    ((rls_fn)f)((const rls_t *)ctx, S, b0, nb);
}

static void call_markov(const void *ctx, void *f, double *S, int64_t b0, int64_t nb) {
    ((markov_fn)f)((const markov_t *)ctx, S, b0, nb);
}

/* ------------------------------------------------------------------------------------------------------ */
/* Python functions                                                                                        */
/* ------------------------------------------------------------------------------------------------------ */
#define ADDR(x) ((void *)(intptr_t)(x))

static PyObject *py_run(PyObject *self, PyObject *args) {
    unsigned long long code, consts, binds, ptrs, counters, obs;
    long long ncode, nbind, nobs, nslots, T, B, vl;
    int nthreads;
    if (!PyArg_ParseTuple(args, "KLKKLKKKLLLLLi", &code, &ncode, &consts, &binds, &nbind, &ptrs, &counters, &obs,
                          &nobs, &nslots, &T, &B, &vl, &nthreads))
        return NULL;
    int li = lane_index(vl);
    if (li < 0) return PyErr_Format(PyExc_ValueError, "lane width %lld is not one of 1, 4, 8, 16", vl);
    run_t r = {ADDR(code), ADDR(binds), ADDR(ptrs), ADDR(counters), ADDR(obs), ADDR(consts),
               ncode, nbind, nobs, nslots, T, B};
    int fail;
    Py_BEGIN_ALLOW_THREADS
    fail = parallel_chunks(call_chunk, &r, (void *)CHUNK[li], nslots + nobs, B, vl, nthreads);
    Py_END_ALLOW_THREADS
    if (fail) return PyErr_NoMemory();
    Py_RETURN_NONE;
}

static PyObject *py_rls(PyObject *self, PyObject *args) {
    unsigned long long theta, P, psi, zr, lam, rinv, active, ok;
    long long B, n, nl, lam_stride, vl;
    int lam_one, nthreads;
    if (!PyArg_ParseTuple(args, "KKKKKLiKKKLLLLi", &theta, &P, &psi, &zr, &lam, &lam_stride, &lam_one, &rinv,
                          &active, &ok, &B, &n, &nl, &vl, &nthreads))
        return NULL;
    int li = lane_index(vl);
    if (li < 0) return PyErr_Format(PyExc_ValueError, "lane width %lld is not one of 1, 4, 8, 16", vl);
    rls_t q = {ADDR(theta), ADDR(P), ADDR(psi), ADDR(zr), ADDR(lam), ADDR(rinv), ADDR(active), ADDR(ok),
               n, nl, lam_stride, lam_one};
    int64_t slots = rls_arena_at(n, nl).end;
    int fail;
    Py_BEGIN_ALLOW_THREADS
    fail = parallel_chunks(call_rls, &q, (void *)RLS[li], slots, B, vl, nthreads);
    Py_END_ALLOW_THREADS
    if (fail) return PyErr_NoMemory();
    Py_RETURN_NONE;
}

/* u1, u2 (B, length, width): the two uniforms behind rng.normal(seed_b, member_b, step, c) at the steps
 * 2 (start + t) and 2 (start + t) + 1, the pair start + t. */
static void uniform_grid(int64_t B, const int64_t *seeds, const int64_t *members, int64_t start, int64_t length,
                         int64_t width, double *u1, double *u2, int nthreads) {
#ifdef _OPENMP
#pragma omp parallel for schedule(static) num_threads(nthreads) if (nthreads > 1 && B * length * width >= 65536)
#endif
    for (int64_t b = 0; b < B; b++) {
        uint32_t h0 = mix32((uint32_t)seeds[b] ^ 0x9E3779B9u);
        h0 = mix32(h0 ^ mix32_key((uint32_t)members[b]));
        uint32_t k1 = mix32_key(1u), k2 = mix32_key(2u);
        for (int64_t c = 0; c < width; c++) {
            uint32_t kc = mix32_key((uint32_t)c);
            double *o1 = u1 + b * length * width + c, *o2 = u2 + b * length * width + c;
            for (int64_t t = 0; t < length; t++) {
                uint32_t h = mix32(mix32(h0 ^ mix32_key((uint32_t)(start + t))) ^ kc);
                o1[t * width] = uniform53(mix32(h ^ k1));
                o2[t * width] = uniform53(mix32(h ^ k2));
            }
        }
    }
}

static PyObject *py_uniform_grid(PyObject *self, PyObject *args) {
    unsigned long long seeds, members, u1, u2;
    long long B, start, length, width;
    int nthreads;
    if (!PyArg_ParseTuple(args, "LKKLLLKKi", &B, &seeds, &members, &start, &length, &width, &u1, &u2, &nthreads))
        return NULL;
    Py_BEGIN_ALLOW_THREADS
    uniform_grid(B, ADDR(seeds), ADDR(members), start, length, width, ADDR(u1), ADDR(u2), nthreads);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

/* The health checks' bounds (verdict/health.py, Health._bounds_exceeded) for members [0, B): code[b] = the reason
 * (health.Reason's codes, in the order of HEALTH_REASONS) of an alive member beyond a bound, else 0. Later tests
 * take precedence: P not positive definite or not finite (NOT_PD), trace(P) > windup[b] (WINDUP),
 * max_a |u_now[b, a]| > bound[b] (U_RUNAWAY), max_a sum_j |theta[b, a, j]| phi_rms[b, j] > bound[b]
 * (THETA_RUNAWAY). Comparisons with NaN are false, as in PyTorch. */
#define HEALTH_REASONS(X) X(NOT_PD) X(WINDUP) X(U_RUNAWAY) X(THETA_RUNAWAY)
#define X_REASON(name) REASON_##name,
enum { HEALTH_REASONS(X_REASON) REASON_N };
static int health_bounds(int64_t B, int64_t n, int64_t n_u, int64_t n_phi, const double *P, const double *theta,
                         const double *u_now, const double *phi_rms, const double *bound, const double *windup,
                         const uint8_t *alive, const int64_t *reason, int64_t *code, int nthreads) {
    int fail = 0;
#ifdef _OPENMP
#pragma omp parallel num_threads(nthreads) if (nthreads > 1 && B >= 4096) reduction(| : fail)
#endif
    {
        double *L = (double *)malloc((size_t)(n > 0 ? n * n : 1) * sizeof(double));
        if (!L) {
            fail = 1;
        } else {
#ifdef _OPENMP
#pragma omp for schedule(static)
#endif
            for (int64_t b = 0; b < B; b++) {
                const double *p = P + b * n * n;
                int ok = 1;
                int64_t c = 0;
                double trace = 0.0;
                for (int64_t i = 0; i < n * n; i++) ok = ok && fabs(p[i]) < INFINITY;
                if (ok) { /* positive definite: every pivot of the RLS step's Cholesky factorization is positive */
                    double pivots_ok = 1.0;
                    memcpy(L, p, (size_t)(n * n) * sizeof(double));
                    cholesky_1base(n, L, &pivots_ok);
                    ok = pivots_ok != 0.0;
                }
                for (int64_t i = 0; i < n; i++) trace += p[i * n + i];
                if (!ok) c = reason[REASON_NOT_PD];
                if (trace > windup[b]) c = reason[REASON_WINDUP];
                double u_max = 0.0, pot_max = 0.0;
                for (int64_t a = 0; a < n_u; a++) {
                    double u = fabs(u_now[b * n_u + a]), pot = 0.0;
                    for (int64_t j = 0; j < n_phi; j++)
                        pot += fabs(theta[(b * n_u + a) * n_phi + j]) * phi_rms[b * n_phi + j];
                    u_max = a == 0 || u > u_max || u != u ? u : u_max;          /* amax: NaN wins */
                    pot_max = a == 0 || pot > pot_max || pot != pot ? pot : pot_max;
                }
                if (u_max > bound[b]) c = reason[REASON_U_RUNAWAY];
                if (pot_max > bound[b]) c = reason[REASON_THETA_RUNAWAY];
                code[b] = alive[b] ? c : 0;
            }
            free(L);
        }
    }
    return fail;
}

static PyObject *py_health_bounds(PyObject *self, PyObject *args) {
    long long B, n, n_u, n_phi;
    unsigned long long P, theta, u_now, phi_rms, bound, windup, alive, reason, code;
    int nthreads;
    if (!PyArg_ParseTuple(args, "LLLLKKKKKKKKKi", &B, &n, &n_u, &n_phi, &P, &theta, &u_now, &phi_rms, &bound,
                          &windup, &alive, &reason, &code, &nthreads))
        return NULL;
    int fail;
    Py_BEGIN_ALLOW_THREADS
    fail = health_bounds(B, n, n_u, n_phi, ADDR(P), ADDR(theta), ADDR(u_now), ADDR(phi_rms), ADDR(bound),
                         ADDR(windup), ADDR(alive), ADDR(reason), ADDR(code), nthreads);
    Py_END_ALLOW_THREADS
    if (fail) return PyErr_NoMemory();
    Py_RETURN_NONE;
}

/* out[b] = sum_w x_wb x_wb^T for x_wb = win[w, b, :n] of a time-major (W, B, m) window: the sum of the outer
 * products of the regressors it holds (verdict/health.py, Health._recent_phi). */
static void window_gram(int64_t W, int64_t B, int64_t m, int64_t n, const double *win, double *out, int nthreads) {
#ifdef _OPENMP
#pragma omp parallel for schedule(static) num_threads(nthreads) if (nthreads > 1 && B >= 4096)
#endif
    for (int64_t b0 = 0; b0 < B; b0 += 256) { /* blocks of members, each row of the window read in order */
        int64_t b1 = b0 + 256 < B ? b0 + 256 : B;
        for (int64_t i = b0 * n * n; i < b1 * n * n; i++) out[i] = 0.0;
        for (int64_t w = 0; w < W; w++)
            for (int64_t b = b0; b < b1; b++) {
                const double *x = win + (w * B + b) * m;
                double *o = out + b * n * n;
                for (int64_t i = 0; i < n; i++)
                    for (int64_t j = 0; j < n; j++) o[i * n + j] += x[i] * x[j];
            }
    }
}

static PyObject *py_window_sums(PyObject *self, PyObject *args) {
    long long C, B, nz, n, t0, measured, L;
    unsigned long long z, moved, psi, d, eps, own, W, norm, gram, ring, sgram, moving;
    int nthreads;
    if (!PyArg_ParseTuple(args, "LLLLLLKKKKKKKKKLKKKi", &C, &B, &nz, &n, &t0, &measured, &z, &moved, &psi, &d, &eps,
                          &own, &W, &norm, &gram, &L, &ring, &sgram, &moving, &nthreads))
        return NULL;
    int fail;
    Py_BEGIN_ALLOW_THREADS
    fail = WINDOW_SUMS(C, B, nz, n, t0, measured, ADDR(z), ADDR(moved), ADDR(psi), d ? ADDR(d) : NULL, ADDR(eps),
                       ADDR(own), ADDR(W), norm ? ADDR(norm) : NULL, ADDR(gram), L, L ? ADDR(ring) : NULL,
                       ADDR(sgram), ADDR(moving), nthreads);
    Py_END_ALLOW_THREADS
    if (fail) return PyErr_NoMemory();
    Py_RETURN_NONE;
}

static PyObject *py_residual_sums(PyObject *self, PyObject *args) {
    long long C, B, nz, nw, ny, t0, measured, L, scratch_len;
    unsigned long long own, z, zi, y, w, zlag, wlag, zring, wring, sums, scratch;
    int nthreads;
    if (!PyArg_ParseTuple(args, "LLLLLLLKLKKKKKKKKKKLi", &C, &B, &nz, &nw, &ny, &t0, &measured, &own, &L, &z, &zi,
                          &y, &w, &zlag, &wlag, &zring, &wring, &sums, &scratch, &scratch_len, &nthreads))
        return NULL;
    int fail;
    Py_BEGIN_ALLOW_THREADS
    fail = RESIDUAL_SUMS(C, B, nz, nw, ny, t0, measured, ADDR(own), L, ADDR(z), ADDR(zi), ADDR(y),
                         nw ? ADDR(w) : NULL, ADDR(zlag), nw ? ADDR(wlag) : NULL, L ? ADDR(zring) : NULL,
                         L && nw ? ADDR(wring) : NULL, ADDR(sums), scratch ? ADDR(scratch) : NULL, scratch_len,
                         nthreads);
    Py_END_ALLOW_THREADS
    if (fail) return PyErr_NoMemory();
    Py_RETURN_NONE;
}

static PyObject *py_residual_scratch(PyObject *self, PyObject *args) {
    long long B, nz, nw, L, C;
    if (!PyArg_ParseTuple(args, "LLLLL", &B, &nz, &nw, &L, &C)) return NULL;
    return PyLong_FromLongLong(rs_scratch(B, nz, nw, L, C));
}

static PyObject *py_markov_filter(PyObject *self, PyObject *args) {
    long long T, B, n_phi, n_out, nu, s0;
    unsigned long long phi, beta, psi;
    int bshared, nthreads;
    if (!PyArg_ParseTuple(args, "LLLLLLKKiKi", &T, &B, &n_phi, &n_out, &nu, &s0, &phi, &beta, &bshared, &psi,
                          &nthreads))
        return NULL;
    int fail;
    Py_BEGIN_ALLOW_THREADS
    fail = MARKOV_FILTER(T, B, n_phi, n_out, nu, s0, ADDR(phi), ADDR(beta), bshared, ADDR(psi), nthreads);
    Py_END_ALLOW_THREADS
    if (fail) return PyErr_NoMemory();
    Py_RETURN_NONE;
}

static PyObject *py_window_gram(PyObject *self, PyObject *args) {
    long long W, B, m, n;
    unsigned long long win, out;
    int nthreads;
    if (!PyArg_ParseTuple(args, "LLLLKKi", &W, &B, &m, &n, &win, &out, &nthreads)) return NULL;
    Py_BEGIN_ALLOW_THREADS
    window_gram(W, B, m, n, ADDR(win), ADDR(out), nthreads);
    Py_END_ALLOW_THREADS
    Py_RETURN_NONE;
}

/* From the step map's values at the point and on both sides of it (XN, n x 3 NB lanes, step s): the tangent
 * DX, and along the free motion the next point XI. */
static void step_tangent(const double *XN, double *DX, double *XI, int64_t n, int64_t NB, double s, int trajectory) {
    const int64_t L = 3 * NB;
    for (int64_t i = 0; i < n; i++)
        for (int64_t q = 0; q < NB; q++) {
            DX[i * NB + q] = (XN[i * L + NB + q] - XN[i * L + 2 * NB + q]) / (2 * s);
            if (trajectory) XI[i * NB + q] = XN[i * L + q];
        }
}

/* Markov parameters H_0 .. H_(nh-1) of a compiled discrete map and output function (blocks/nonlinear.py,
 * Nonlinear.markov with method 'fd'; step: [x, u] (n + m) -> x (n), h: x -> (n_out), each called for L lanes,
 * slot-major), of the W input columns from col on to output rows r0 .. r1 - 1, by central differences along the
 * free motion from x (trajectory) or at x, with the inputs held at u: the same operations as that method, whose
 * rows q = j B + b (direction j, member b) are the lanes here, the point and both sides of it in one call of
 * 3 NB lanes. x (B, n) and u (B, m) row-major; H (B, nh, r1 - r0, W), H_0 zero. Returns 1 when out of memory. */
static int markov_fd(rco_fn_t step, rco_fn_t h, int64_t B, int64_t n, int64_t m, int64_t col, int64_t W,
                     int64_t n_out, int64_t r0, int64_t r1, int64_t nh, double eps, int trajectory, const double *x,
                     const double *u, double *H) {
    const int64_t NB = W * B, L = 3 * NB, nr = r1 - r0;
    double *XU = malloc(sizeof(double) * (size_t)((n + m) * L)), *XN = malloc(sizeof(double) * (size_t)(n * L));
    double *HO = malloc(sizeof(double) * (size_t)(n_out * L)), *XI = malloc(sizeof(double) * (size_t)(n * NB));
    double *DX = malloc(sizeof(double) * (size_t)(n * NB));
    int fail = !XU || !XN || !HO || !XI || !DX;
    if (!fail) {
        memset(H, 0, sizeof(double) * (size_t)(B * nh * nr * W));
        for (int64_t c = 0; c < m; c++) /* the held inputs, and the state x, in each copy */
            for (int64_t q = 0; q < L; q++) XU[(n + c) * L + q] = u[(q % B) * m + c];
        for (int64_t i = 0; i < n; i++)
            for (int64_t q = 0; q < NB; q++) {
                XI[i * NB + q] = x[(q % B) * n + i];
                for (int k = 0; k < 3; k++) XU[i * L + k * NB + q] = XI[i * NB + q];
            }
        /* the input's tangent: at = u's columns, v = the unit vector of direction j */
        double big = 1.0;
        for (int64_t b = 0; b < B; b++)
            for (int64_t c = 0; c < W; c++)
                if (fabs(u[b * m + col + c]) > big) big = fabs(u[b * m + col + c]);
        double s = eps * big;
        for (int64_t c = 0; c < W; c++)
            for (int64_t q = 0; q < NB; q++) {
                double at = u[(q % B) * m + col + c], v = q / B == c ? 1.0 : 0.0;
                XU[(n + col + c) * L + NB + q] = at + s * v;
                XU[(n + col + c) * L + 2 * NB + q] = at - s * v;
            }
        step(XU, XN, L);
        for (int64_t c = 0; c < W; c++) /* the inputs held from here on, in every copy */
            for (int64_t q = NB; q < L; q++) XU[(n + col + c) * L + q] = u[(q % B) * m + col + c];
        step_tangent(XN, DX, XI, n, NB, s, trajectory);
        for (int64_t k = 1; k < nh; k++) {
            big = 1.0; /* XI holds the point: the free motion, or x */
            for (int64_t e = 0; e < n * NB; e++)
                if (fabs(XI[e]) > big) big = fabs(XI[e]);
            s = eps * big;
            for (int64_t i = 0; i < n; i++)
                for (int64_t q = 0; q < NB; q++) {
                    double p = XI[i * NB + q], d = DX[i * NB + q];
                    XU[i * L + q] = p;
                    XU[i * L + NB + q] = p + s * d;
                    XU[i * L + 2 * NB + q] = p - s * d;
                }
            h(XU, HO, L); /* h reads the first n slots: the states */
            for (int64_t r = r0; r < r1; r++)
                for (int64_t q = 0; q < NB; q++)
                    H[(((q % B) * nh + k) * nr + r - r0) * W + q / B] =
                        (HO[r * L + NB + q] - HO[r * L + 2 * NB + q]) / (2 * s);
            if (k + 1 < nh) {
                step(XU, XN, L);
                step_tangent(XN, DX, XI, n, NB, s, trajectory);
            }
        }
    }
    free(XU);
    free(XN);
    free(HO);
    free(XI);
    free(DX);
    return fail;
}

static PyObject *py_markov_fd(PyObject *self, PyObject *args) {
    unsigned long long step, h, x, u, H;
    long long B, n, m, col, W, n_out, r0, r1, nh;
    double eps;
    int trajectory, fail;
    if (!PyArg_ParseTuple(args, "KKLLLLLLLLLdiKKK", &step, &h, &B, &n, &m, &col, &W, &n_out, &r0, &r1, &nh, &eps,
                          &trajectory, &x, &u, &H))
        return NULL;
    Py_BEGIN_ALLOW_THREADS
    fail = markov_fd((rco_fn_t)ADDR(step), (rco_fn_t)ADDR(h), B, n, m, col, W, n_out, r0, r1, nh, eps, trajectory,
                     ADDR(x), ADDR(u), ADDR(H));
    Py_END_ALLOW_THREADS
    if (fail) return PyErr_NoMemory();
    Py_RETURN_NONE;
}

/* The Markov parameters beta_t = -H_(d+t), t = 0..nu-1, H_0 = D0, H_i = C A^(i-1) B, of one linear system per
 * member (estimator/tracking.py, the closed loop's): A (B, N, N), Bm (B, N, m), C (B, p, N), D0 (B, p, m)
 * row-major, written into each target (markov_target_t, up to MARKOV_TARGETS, given as flat int64 sextuples
 * base, srow, st, se, copies, coff) at the member's row (rows, or its index where rows is 0); with stable (B
 * bytes) not 0, only the members whose A passes the test of lanes.h's markov_chunk, and stable says which. */
static PyObject *py_lti_markov(PyObject *self, PyObject *args) {
    long long B, N, m, p, d, nu, ntargets, vl;
    unsigned long long A, Bm, C, D0, rows, stable, targets;
    int nthreads, fail;
    if (!PyArg_ParseTuple(args, "LLLLLLKKKKKKKLLi", &B, &N, &m, &p, &d, &nu, &A, &Bm, &C, &D0, &rows, &stable,
                          &targets, &ntargets, &vl, &nthreads))
        return NULL;
    int li = lane_index(vl);
    if (li < 0) return PyErr_Format(PyExc_ValueError, "lane width %lld is not one of 1, 4, 8, 16", vl);
    if (ntargets < 0 || ntargets > MARKOV_TARGETS)
        return PyErr_Format(PyExc_ValueError, "lti_markov writes into 0 to %d targets, got %lld", MARKOV_TARGETS,
                            ntargets);
    markov_t q = {ADDR(A), ADDR(Bm), ADDR(C), ADDR(D0), (const int64_t *)ADDR(rows), (uint8_t *)ADDR(stable),
                  N, m, p, d, nu, ntargets, {{0}}};
    const int64_t *t = (const int64_t *)ADDR(targets);
    for (int64_t g = 0; g < ntargets; g++)
        q.t[g] = (markov_target_t){(double *)(uintptr_t)t[6 * g], t[6 * g + 1], t[6 * g + 2], t[6 * g + 3],
                                   t[6 * g + 4], t[6 * g + 5]};
    Py_BEGIN_ALLOW_THREADS
    fail = parallel_chunks(call_markov, &q, (void *)MARKOV[li], markov_slots(N, m, p, nu), B, vl, nthreads);
    Py_END_ALLOW_THREADS
    if (fail) return PyErr_NoMemory();
    Py_RETURN_NONE;
}

static PyObject *py_rco_scratch(PyObject *self, PyObject *args) {
    long long n_u, n_z, n_phi, n, nl;
    if (!PyArg_ParseTuple(args, "LLLLL", &n_u, &n_z, &n_phi, &n, &nl)) return NULL;
    return PyLong_FromLongLong(rco_upd_scratch_at(n_u, n_z, n_phi, n, nl).end);
}

static PyMethodDef METHODS[] = {
    {"run", py_run, METH_VARARGS, "run(code, ncode, consts, binds, nbind, ptrs, counters, obs, nobs, nslots, T, B, "
                                  "lanes, threads): run a lowered graph for T steps"},
    {"rls", py_rls, METH_VARARGS, "rls(theta, P, psi, z_r, lam, lam_stride, lam_one, r_inv, active, ok, B, n, l, "
                                  "lanes, threads): one RLS step of every member, in place"},
    {"uniform_grid", py_uniform_grid, METH_VARARGS,
     "uniform_grid(B, seeds, members, start, length, width, u1, u2, threads): the uniforms of rng.normal"},
    {"health_bounds", py_health_bounds, METH_VARARGS,
     "health_bounds(B, n, n_u, n_phi, P, theta, u_now, phi_rms, bound, windup, alive, reason, code, threads): "
     "the health checks' bounds"},
    {"window_sums", py_window_sums, METH_VARARGS,
     "window_sums(C, B, nz, n, t0, measured, z, moved, psi, d, eps, own, W, norm, gram, L, ring, sgram, moving, "
     "threads): the replay's Gram sums and its scores' long-run sums over a stretch, per member"},
    {"residual_sums", py_residual_sums, METH_VARARGS,
     "residual_sums(C, B, nz, nw, ny, t0, measured, own, L, z, zi, y, w, zlag, wlag, zring, wring, sums, scratch, "
     "scratch_len, threads): the residual checks' lagged and plain sums over a stretch, per member"},
    {"residual_scratch", py_residual_scratch, METH_VARARGS,
     "residual_scratch(B, nz, nw, L, C): the doubles of residual_sums' scratch for a stretch of C steps"},
    {"markov_filter", py_markov_filter, METH_VARARGS,
     "markov_filter(T, B, n_phi, n_out, nu, s0, phi, beta, bshared, psi, threads): the regressors of a stretch "
     "filtered by the Markov parameters"},
    {"window_gram", py_window_gram, METH_VARARGS,
     "window_gram(W, B, m, n, win, out, threads): sum of x x^T over the window's rows, x = win[w, b, :n]"},
    {"lti_markov", py_lti_markov, METH_VARARGS,
     "lti_markov(B, N, m, p, d, nu, A, Bm, C, D0, rows, stable, targets, ntargets, lanes, threads): beta_t = "
     "-H_(d+t) of one system per member, written into the targets"},
    {"rco_scratch", py_rco_scratch, METH_VARARGS, "rco_scratch(n_u, n_z, n_phi, n_theta, n_rows): scratch slots"},
    {"markov_fd", py_markov_fd, METH_VARARGS,
     "markov_fd(step, h, B, n, m, col, W, n_out, r0, r1, nh, eps, trajectory, x, u, H): Markov parameters of "
     "compiled maps by central differences"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef MODULE = {PyModuleDef_HEAD_INIT, "_engine", "rcotorch's native CPU kernels", -1, METHODS};

#define X_NAME(name) #name,
#define X_OP_NAME(name, layout) #name,
#define X_OP_LAYOUT(name, layout) #layout,
static const char *OP_NAMES[] = {RCO_OPS(X_OP_NAME)};
static const char *OP_LAYOUT_NAMES[] = {RCO_OPS(X_OP_LAYOUT)};
static const char *FACTOR_NAMES[] = {RCO_FACTORS(X_NAME)};
static const char *BIND_FIELD_NAMES[] = {RCO_BIND_FIELDS(X_NAME)};
static const char *KIND_NAMES[] = {RCO_KINDS(X_NAME)};
static const char *OBS_FIELD_NAMES[] = {RCO_OBS_FIELDS(X_NAME)};
static const char *OBSERVER_NAMES[] = {RCO_OBSERVERS(X_NAME)};

static PyObject *name_tuple(const char **names, int count) {
    PyObject *t = PyTuple_New(count);
    if (!t) return NULL;
    for (int i = 0; i < count; i++) {
        PyObject *s = PyUnicode_FromString(names[i]);
        if (!s) {
            Py_DECREF(t);
            return NULL;
        }
        PyTuple_SET_ITEM(t, i, s);
    }
    return t;
}

static int add_names(PyObject *m, const char *attr, const char **names, int count) {
    PyObject *t = name_tuple(names, count);
    return t ? PyModule_AddObject(m, attr, t) : -1;
}

/* LAYOUTS: {layout: (field, ...)}; TABLES: ((layout, table, count field, entry layout), ...). */
#define X_LAYOUT_NAMES(layout) static const char *layout##_FIELD_NAMES[] = {RCO_##layout##_FIELDS(X_NAME)};
RCO_LAYOUTS(X_LAYOUT_NAMES)
#define X_LAYOUT_ADD(layout)                                                                                 \
    if (!fail) {                                                                                             \
        PyObject *t = name_tuple(layout##_FIELD_NAMES, (int)(sizeof layout##_FIELD_NAMES / sizeof(char *)));  \
        fail = !t || PyDict_SetItemString(d, #layout, t) < 0;                                                \
        Py_XDECREF(t);                                                                                       \
    }
#define X_TABLE(layout, table, count, entry) {#layout, #table, #count, #entry},
static const char *TABLE_NAMES[][4] = {RCO_TABLES(X_TABLE)};

static int add_layouts(PyObject *m) {
    PyObject *d = PyDict_New();
    int fail = !d;
    RCO_LAYOUTS(X_LAYOUT_ADD)
    if (fail || PyModule_AddObject(m, "LAYOUTS", d) < 0) {
        Py_XDECREF(d);
        return -1;
    }
    int n = (int)(sizeof TABLE_NAMES / sizeof TABLE_NAMES[0]);
    PyObject *t = PyTuple_New(n);
    if (!t) return -1;
    for (int i = 0; i < n; i++) {
        PyObject *row = name_tuple(TABLE_NAMES[i], 4);
        if (!row) {
            Py_DECREF(t);
            return -1;
        }
        PyTuple_SET_ITEM(t, i, row);
    }
    return PyModule_AddObject(m, "TABLES", t);
}

/* The bits of a binding's MODE, each a constant of the module (BIND_LOAD, ...). */
#define X_BIND_BIT_ADD(name, bit) PyModule_AddIntConstant(m, #name, name) ||

PyMODINIT_FUNC PyInit__engine(void) {
    select_isa();
    PyObject *m = PyModule_Create(&MODULE);
    if (!m) return NULL;
    PyObject *lanes = Py_BuildValue("(iiii)", LANE_WIDTHS[0], LANE_WIDTHS[1], LANE_WIDTHS[2], LANE_WIDTHS[3]);
#ifdef _OPENMP
    int openmp = 1;
#else
    int openmp = 0;
#endif
    if (add_names(m, "OPS", OP_NAMES, OP_N - 1) || add_names(m, "OP_LAYOUTS", OP_LAYOUT_NAMES, OP_N - 1) ||
        add_layouts(m) || add_names(m, "FACTORS", FACTOR_NAMES, FAC_N) ||
        add_names(m, "BIND_FIELDS", BIND_FIELD_NAMES, BF_N) || add_names(m, "KINDS", KIND_NAMES, KIND_N) ||
        add_names(m, "OBS_FIELDS", OBS_FIELD_NAMES, OF_N) ||
        add_names(m, "OBSERVERS", OBSERVER_NAMES, OBS_N) || PyModule_AddObject(m, "LANE_WIDTHS", lanes) ||
        PyModule_AddIntConstant(m, "HEADER", HDR) || PyModule_AddIntConstant(m, "OPENMP", openmp) ||
        PyModule_AddIntConstant(m, "NOISE_AHEAD", NOISE_AHEAD) ||
        PyModule_AddIntConstant(m, "NOISE_SLOTS", NOISE_SLOTS) || RCO_BIND_MODE_BITS(X_BIND_BIT_ADD)
        PyModule_AddStringConstant(m, "ISA", ISA_NAME)) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
