/* rcotorch's native CPU kernels (float64).
 *
 * 1. rco_rls1: the RLS update with one z channel (l = 1), one pass over each member's P.
 * 2. rco_uniform_grid: the integer part of rcotorch.rng.normal on a (member, step, component) grid.
 * 3. rco_run: a graph lowered to a list of instructions, run for T steps. Members are independent, so the
 *    batch is cut into chunks of members; each chunk runs all T steps on its own (one thread per chunk),
 *    and inside a chunk every instruction loops over the chunk's members, so the state of a chunk stays in
 *    cache. The arithmetic of a member does not depend on the batch it runs in or on the thread count.
 *
 * Semantics follow the PyTorch blocks (rcotorch/blocks.py, lti.py, sources.py, estimator.py, rls.py) line by
 * line; results agree with them to rounding (the order of sums differs from BLAS). Build flags keep
 * -ffp-contract=off so that results do not depend on the instruction set the compiler targets.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif

#define MAXN 64     /* most states / theta entries / window width a native instruction handles */

/* ------------------------------------------------------------------------------------------------ */
/* RLS, l = 1                                                                                        */
/* ------------------------------------------------------------------------------------------------ */

/* One member. Returns ok (see rls.py). theta (n), P (n x n), psi (n), zr, lam, r, active. */
static inline int rls1_member(int64_t n, double *restrict theta, double *restrict P, const double *restrict psi,
                              double zr, double lam, int lam_one, double r, int active) {
    double a[MAXN];
    double s = 0.0;
    for (int64_t i = 0; i < n; i++) {
        const double *row = P + i * n;
        double acc = 0.0;
        for (int64_t j = 0; j < n; j++) acc += row[j] * psi[j];
        a[i] = acc;
    }
    for (int64_t i = 0; i < n; i++) s += psi[i] * a[i];
    s += lam_one ? r : lam * r;
    int go = (s > 0.0) && (s < INFINITY);
    int ok = go;
    go = go && active;
    if (!go) return ok || !active;
    double g = zr / s, sum = 0.0;
    double step[MAXN];
    for (int64_t i = 0; i < n; i++) {
        step[i] = a[i] * g;
        sum += step[i];
    }
    if (!(fabs(sum) < INFINITY)) return 0; /* the update is not finite: member left as it was */
    double rs = 1.0 / sqrt(s);
    for (int64_t i = 0; i < n; i++) a[i] *= rs; /* w = P psi s^-1/2 */
    for (int64_t i = 0; i < n; i++) {
        double *row = P + i * n;
        double wi = a[i];
        if (lam_one) {
            for (int64_t j = 0; j < n; j++) row[j] -= wi * a[j];
        } else {
            for (int64_t j = 0; j < n; j++) row[j] = (row[j] - wi * a[j]) / lam;
        }
    }
    for (int64_t i = 0; i < n; i++) theta[i] -= step[i];
    return 1;
}

/* theta (B, n), P (B, n, n), psi (B, n), zr (B), lam (B or 1, lam_stride 1 or 0), active (B) or NULL,
 * ok (B) out. Members with n > MAXN are not handled here (the caller checks). */
int rco_rls1(int64_t B, int64_t n, double *theta, double *P, const double *psi, const double *zr,
             const double *lam, int64_t lam_stride, int lam_one, double r, const uint8_t *active, uint8_t *ok,
             int nthreads) {
    if (n > MAXN) return -1;
#ifdef _OPENMP
#pragma omp parallel for schedule(static) num_threads(nthreads) if (nthreads > 1 && B >= 256)
#endif
    for (int64_t b = 0; b < B; b++) {
        ok[b] = (uint8_t)rls1_member(n, theta + b * n, P + b * n * n, psi + b * n, zr[b], lam[b * lam_stride],
                                     lam_one, r, active ? active[b] : 1);
    }
    return 0;
}

/* ------------------------------------------------------------------------------------------------ */
/* Counter-based uniforms (rcotorch/rng.py)                                                          */
/* ------------------------------------------------------------------------------------------------ */

/* rng._mix32 on a 32-bit value. */
static inline uint32_t mix32(uint32_t y) {
    y ^= y >> 16;
    y *= 0x7FEB352Du;
    y ^= y >> 15;
    y *= 0x846CA68Bu;
    return y ^ (y >> 16);
}

/* rng._mix32(key + 0x632BE5AB) for a 32-bit key: the sum has 33 bits, and the first xor-shift sees the top
 * one (as the int64 code does); the rest is 32-bit arithmetic. */
static inline uint32_t mix32_key(uint32_t key) {
    uint32_t lo = key + 0x632BE5ABu, hi = lo < key; /* carry */
    uint32_t y = lo ^ ((lo >> 16) | (hi << 16));
    y *= 0x7FEB352Du;
    y ^= y >> 15;
    y *= 0x846CA68Bu;
    return y ^ (y >> 16);
}

/* One key after the first (rng.hash32). */
static inline uint32_t chain(uint32_t h, uint32_t key) { return mix32(h ^ mix32_key(key)); }

static inline double uniform53(uint32_t h) {
    int32_t a = (int32_t)(chain(h, 0x1B873593u) >> 5), b = (int32_t)(chain(h, 0x5BD1E995u) >> 6);
    return ((double)a * 67108864.0 + (double)b + 0.5) / 9007199254740992.0;
}

/* u1, u2 (B, length, width): the two uniforms behind rng.normal(seed_b, member_b, start + t, c). */
void rco_uniform_grid(int64_t B, const int64_t *seeds, const int64_t *members, int64_t start, int64_t length,
                      int64_t width, double *u1, double *u2, int nthreads) {
#ifdef _OPENMP
#pragma omp parallel for schedule(static) num_threads(nthreads) if (nthreads > 1 && B * length * width >= 65536)
#endif
    for (int64_t b = 0; b < B; b++) {
        uint32_t h0 = mix32((uint32_t)seeds[b] ^ 0x9E3779B9u);
        h0 = chain(h0, (uint32_t)members[b]);
        uint32_t c0 = mix32_key(0u);
        for (int64_t c = 0; c < width; c++) {
            uint32_t kc = c == 0 ? c0 : mix32_key((uint32_t)c), k1 = mix32_key(1u), k2 = mix32_key(2u);
            double *o1 = u1 + b * length * width + c, *o2 = u2 + b * length * width + c;
            if (width == 1) {
                for (int64_t t = 0; t < length; t++) { /* vectorized over steps */
                    uint32_t h = mix32(mix32(h0 ^ mix32_key((uint32_t)(start + t))) ^ kc);
                    o1[t] = uniform53(mix32(h ^ k1));
                    o2[t] = uniform53(mix32(h ^ k2));
                }
            } else {
                for (int64_t t = 0; t < length; t++) {
                    uint32_t h = mix32(mix32(h0 ^ mix32_key((uint32_t)(start + t))) ^ kc);
                    o1[t * width] = uniform53(mix32(h ^ k1));
                    o2[t * width] = uniform53(mix32(h ^ k2));
                }
            }
        }
    }
}

/* ------------------------------------------------------------------------------------------------ */
/* Lowered graphs                                                                                    */
/* ------------------------------------------------------------------------------------------------ */

/* A chunk of VL members is run on a scratch arena of "slots": slot s holds one scalar of every member of
 * the chunk, S[s * VL + lane]. Bindings copy the blocks' batch-first tensors into slots before the steps
 * and back after them, so every operation of a step is a loop over the VL lanes (vectorized). */
#define VL 16

typedef struct {
    void *ptr;       /* the tensor */
    int64_t kind;    /* 0 float64, 1 bool (uint8), 2 int64 */
    int64_t mstride; /* elements between members (0: shared by all members) */
    int64_t inner;   /* element c lives at (c / inner) * ostride + c % inner */
    int64_t ostride;
    int64_t count;   /* elements per member */
    int64_t slot;
    int64_t mode;    /* 1 load, 2 store, 3 both */
} bind_t;

enum {
    OP_SEQ = 1,      /* out[c] = src[b * ms + (t0 + t) * ts + off + c]: noise chunks, recordings */
    OP_LTI_OUT = 2,  /* out = C[rows] x + sum D[rows, cols_j] u_j */
    OP_LTI_UPD = 3,  /* x = A x + sum B[:, cols_j] u_j */
    OP_GAIN = 4,     /* out = K in */
    OP_SUM = 5,      /* out = sum sign_j in_j */
    OP_ACC_SQ = 6,   /* acc += sum_c sig[c]^2 */
    OP_RCO_OUT = 7,  /* u = theta phi (estimator.output) */
    OP_RCO_UPD = 8,  /* window, retrospective error, RLS, histories (estimator.update) */
};

#define NI 200
#define NP 4

typedef struct {
    int64_t op;
    int64_t i[NI];
    double d[4];
    void *p[NP];
} instr_t;

#define LANES for (int l = 0; l < VL; l++)
#define SL(s) (S + (s) * VL)

static void op_seq(const instr_t *in, double *S, int64_t b0, int64_t nb, int64_t t) {
    const double *src = (const double *)in->p[0];
    int64_t ms = in->i[0], ts = in->i[1], off = in->i[2], w = in->i[3], t0 = in->i[4], out = in->i[5];
    for (int64_t c = 0; c < w; c++) {
        double *o = SL(out + c);
        for (int64_t l = 0; l < VL; l++) o[l] = src[(b0 + (l < nb ? l : nb - 1)) * ms + (t0 + t) * ts + off + c];
    }
}

/* i: n, w, c_slot (row 0 of this port), x_slot, out_slot, nft, mt, d_slot (row 0, col 0), [col, wf, u]... */
static void op_lti_out(const instr_t *in, double *S) {
    int64_t n = in->i[0], w = in->i[1], cs = in->i[2], xs = in->i[3], os = in->i[4], nft = in->i[5];
    int64_t mt = in->i[6], ds = in->i[7];
    for (int64_t r = 0; r < w; r++) {
        double acc[VL];
        LANES acc[l] = 0.0;
        for (int64_t j = 0; j < n; j++) {
            const double *c = SL(cs + r * n + j), *x = SL(xs + j);
            LANES acc[l] += c[l] * x[l];
        }
        for (int64_t f = 0; f < nft; f++) {
            int64_t col = in->i[8 + 3 * f], wf = in->i[9 + 3 * f], us = in->i[10 + 3 * f];
            for (int64_t c = 0; c < wf; c++) {
                const double *d = SL(ds + r * mt + col + c), *u = SL(us + c);
                LANES acc[l] += d[l] * u[l];
            }
        }
        double *o = SL(os + r);
        LANES o[l] = acc[l];
    }
}

/* i: n, mt, a_slot, b_slot, x_slot, nin, [u_slot, w]... */
static void op_lti_upd(const instr_t *in, double *S) {
    int64_t n = in->i[0], mt = in->i[1], as = in->i[2], bs = in->i[3], xs = in->i[4], nin = in->i[5];
    double xn[MAXN][VL];
    for (int64_t r = 0; r < n; r++) {
        double *acc = xn[r];
        LANES acc[l] = 0.0;
        for (int64_t j = 0; j < n; j++) {
            const double *a = SL(as + r * n + j), *x = SL(xs + j);
            LANES acc[l] += a[l] * x[l];
        }
        int64_t col = 0;
        for (int64_t q = 0; q < nin; q++) {
            int64_t us = in->i[6 + 2 * q], w = in->i[7 + 2 * q];
            for (int64_t c = 0; c < w; c++) {
                const double *b = SL(bs + r * mt + col + c), *u = SL(us + c);
                LANES acc[l] += b[l] * u[l];
            }
            col += w;
        }
    }
    for (int64_t r = 0; r < n; r++) {
        double *x = SL(xs + r);
        LANES x[l] = xn[r][l];
    }
}

/* i: m, n, k_slot, in_slot, out_slot */
static void op_gain(const instr_t *in, double *S) {
    int64_t m = in->i[0], n = in->i[1], ks = in->i[2], is = in->i[3], os = in->i[4];
    for (int64_t r = 0; r < m; r++) {
        double acc[VL];
        LANES acc[l] = 0.0;
        for (int64_t j = 0; j < n; j++) {
            const double *k = SL(ks + r * n + j), *x = SL(is + j);
            LANES acc[l] += k[l] * x[l];
        }
        double *o = SL(os + r);
        LANES o[l] = acc[l];
    }
}

/* i: w, nin, out_slot, [in_slot, sign]... */
static void op_sum(const instr_t *in, double *S) {
    int64_t w = in->i[0], nin = in->i[1], os = in->i[2];
    for (int64_t c = 0; c < w; c++) {
        double acc[VL];
        LANES acc[l] = 0.0;
        for (int64_t q = 0; q < nin; q++) {
            const double *v = SL(in->i[3 + 2 * q] + c);
            int pos = in->i[4 + 2 * q] > 0;
            if (q == 0) {
                if (pos) { LANES acc[l] = v[l]; } else { LANES acc[l] = -v[l]; }
            } else {
                if (pos) { LANES acc[l] += v[l]; } else { LANES acc[l] -= v[l]; }
            }
        }
        double *o = SL(os + c);
        LANES o[l] = acc[l];
    }
}

/* i: w, sig_slot, acc_slot */
static void op_acc_sq(const instr_t *in, double *S) {
    int64_t w = in->i[0], ss = in->i[1];
    double *acc = SL(in->i[2]);
    double v[VL];
    LANES v[l] = 0.0;
    for (int64_t c = 0; c < w; c++) {
        const double *x = SL(ss + c);
        LANES v[l] += x[l] * x[l];
    }
    LANES acc[l] += v[l];
}

/* Estimator (indices into i[]). */
enum {
    E_NU = 0, E_NPHI, E_NTHETA, E_W, E_NUM, E_NC, E_NC1, E_NSIG, E_LAM_ONE, E_KBASE,
    E_THETA, E_P, E_WIN, E_PHI, E_UNOW, E_BETA, E_Z, E_VALID, E_ALIVE, E_DIV, E_ZR, E_LAM, E_TLO, E_THI,
    E_PAST, E_PASTU, E_UOUT, E_ULO, E_UHI, E_CUR, /* slot of the regressor inputs, n_sig consecutive... */
    E_VAR = 40 /* then phi_src[n_phi], free_theta[n_theta], free_prod[n_theta] */
};

static void op_rco_out(const instr_t *in, double *S) {
    int64_t n_u = in->i[E_NU], n_phi = in->i[E_NPHI];
    const int64_t *src = in->i + E_VAR;
    const double *alive = SL(in->i[E_ALIVE]);
    for (int64_t j = 0; j < n_phi; j++) {
        const double *v = SL(src[j]);
        double *phi = SL(in->i[E_PHI] + j);
        LANES phi[l] = v[l];
    }
    for (int64_t a = 0; a < n_u; a++) {
        double acc[VL];
        LANES acc[l] = 0.0;
        for (int64_t j = 0; j < n_phi; j++) {
            const double *th = SL(in->i[E_THETA] + a * n_phi + j), *phi = SL(in->i[E_PHI] + j);
            LANES acc[l] += th[l] * phi[l];
        }
        LANES acc[l] = alive[l] != 0.0 ? acc[l] : 0.0;
        if (in->i[E_ULO] >= 0) {
            const double *lo = SL(in->i[E_ULO] + a), *hi = SL(in->i[E_UHI] + a);
            LANES {
                double v = acc[l] < lo[l] ? lo[l] : acc[l];
                acc[l] = v > hi[l] ? hi[l] : v;
            }
        }
        double *u = SL(in->i[E_UNOW] + a), *uo = SL(in->i[E_UOUT] + a);
        LANES u[l] = uo[l] = acc[l];
    }
}

static void op_rco_upd(const instr_t *in, double *S, int64_t t) {
    int64_t n_u = in->i[E_NU], n_phi = in->i[E_NPHI], n = in->i[E_NTHETA], W = in->i[E_W], nu = in->i[E_NUM];
    int64_t nc = in->i[E_NC], nc1 = in->i[E_NC1], n_sig = in->i[E_NSIG], lam_one = in->i[E_LAM_ONE];
    int64_t k = in->i[E_KBASE] + t, m = n_phi + n_u, pr = k % W;
    const int64_t *free_theta = in->i + E_VAR + n_phi, *free_prod = free_theta + n;
    int64_t win = in->i[E_WIN];
    double r = in->d[0];
    /* [phi(k), u(k)] into rows pr and pr + W */
    for (int64_t j = 0; j < m; j++) {
        const double *v = SL(j < n_phi ? in->i[E_PHI] + j : in->i[E_UNOW] + j - n_phi);
        double *r1 = SL(win + pr * m + j), *r2 = SL(win + (pr + W) * m + j);
        LANES r1[l] = r2[l] = v[l];
    }
    /* prod[a, j] = sum_i beta_rev[a, i] win[pr + 1 + i][j], oldest first */
    double prod[2 * MAXN][VL];
    for (int64_t a = 0; a < n_u; a++) {
        for (int64_t j = 0; j < m; j++) {
            double *p = prod[a * m + j];
            LANES p[l] = 0.0;
            for (int64_t i = 0; i < nu; i++) {
                const double *c = SL(in->i[E_BETA] + a * nu + i), *w = SL(win + (pr + 1 + i) * m + j);
                LANES p[l] += c[l] * w[l];
            }
        }
    }
    double zr[VL], psi[MAXN][VL], a_[MAXN][VL], s[VL];
    const double *z = SL(in->i[E_Z]);
    LANES zr[l] = z[l];
    for (int64_t a = 0; a < n_u; a++) {
        const double *p = prod[a * m + n_phi + a];
        LANES zr[l] -= p[l];
    }
    for (int64_t f = 0; f < n; f++) {
        const double *p = prod[free_prod[f]], *th = SL(in->i[E_THETA] + free_theta[f]);
        LANES {
            psi[f][l] = p[l];
            zr[l] += p[l] * th[l];
        }
    }
    /* RLS (rls.py, l = 1): a = P psi, s = lam r + psi^T a */
    int64_t Ps = in->i[E_P];
    for (int64_t i = 0; i < n; i++) {
        double *ai = a_[i];
        LANES ai[l] = 0.0;
        for (int64_t j = 0; j < n; j++) {
            const double *P = SL(Ps + i * n + j);
            LANES ai[l] += P[l] * psi[j][l];
        }
    }
    LANES s[l] = 0.0;
    for (int64_t i = 0; i < n; i++) LANES s[l] += psi[i][l] * a_[i][l];
    const double *lam = SL(in->i[E_LAM]), *alive = SL(in->i[E_ALIVE]);
    const double *valid = in->i[E_VALID] >= 0 ? SL(in->i[E_VALID]) : 0;
    double go[VL], okv[VL], g[VL], sum[VL], rs[VL];
    LANES {
        s[l] += lam_one ? r : lam[l] * r;
        double ok0 = (s[l] > 0.0 && s[l] < INFINITY) ? 1.0 : 0.0;
        double active = (alive[l] != 0.0 && (!valid || valid[l] > 0.5)) ? 1.0 : 0.0;
        okv[l] = ok0;
        go[l] = ok0 * active;
        g[l] = go[l] != 0.0 ? zr[l] / (go[l] != 0.0 ? s[l] : 1.0) : 0.0;
        sum[l] = 0.0;
    }
    for (int64_t i = 0; i < n; i++) LANES {
        a_[i][l] = go[l] != 0.0 ? a_[i][l] : 0.0;
        psi[i][l] = a_[i][l] * g[l]; /* psi now holds the step */
        sum[l] += psi[i][l];
    }
    LANES {
        int finite = fabs(sum[l]) < INFINITY;
        if (go[l] != 0.0) okv[l] = finite ? 1.0 : 0.0;
        go[l] = (go[l] != 0.0 && finite) ? 1.0 : 0.0;
        rs[l] = go[l] != 0.0 ? 1.0 / sqrt(s[l]) : 0.0;
    }
    for (int64_t i = 0; i < n; i++) LANES a_[i][l] *= rs[l]; /* w = P psi s^-1/2 */
    for (int64_t i = 0; i < n; i++) {
        for (int64_t j = 0; j < n; j++) {
            double *P = SL(Ps + i * n + j);
            if (lam_one) {
                LANES P[l] -= a_[i][l] * a_[j][l];
            } else {
                LANES P[l] = go[l] != 0.0 ? (P[l] - a_[i][l] * a_[j][l]) / lam[l] : P[l];
            }
        }
    }
    for (int64_t f = 0; f < n; f++) {
        double *th = SL(in->i[E_THETA] + free_theta[f]);
        LANES th[l] -= go[l] != 0.0 ? psi[f][l] : 0.0;
    }
    if (in->i[E_TLO] >= 0) {
        for (int64_t e = 0; e < n_u * n_phi; e++) {
            double *th = SL(in->i[E_THETA] + e);
            const double *lo = SL(in->i[E_TLO] + e), *hi = SL(in->i[E_THI] + e);
            LANES {
                double v = th[l] < lo[l] ? lo[l] : th[l];
                th[l] = v > hi[l] ? hi[l] : v;
            }
        }
    }
    {
        double *al = SL(in->i[E_ALIVE]), *dv = SL(in->i[E_DIV]), *zo = SL(in->i[E_ZR]);
        LANES {
            double active = (alive[l] != 0.0 && (!valid || valid[l] > 0.5)) ? 1.0 : 0.0;
            int okf = okv[l] != 0.0 || active == 0.0;
            if (al[l] != 0.0 && !okf) {
                dv[l] = (double)k;
                al[l] = 0.0;
            }
            zo[l] = zr[l];
        }
    }
    if (nc) { /* shift the regressor histories */
        int64_t ps = in->i[E_PAST], us = in->i[E_PASTU];
        for (int64_t c = (nc1 - 1) * n_sig - 1; c >= 0; c--) {
            double *d = SL(ps + n_sig + c), *v = SL(ps + c);
            LANES d[l] = v[l];
        }
        for (int64_t c = 0; c < n_sig; c++) {
            double *d = SL(ps + c), *v = SL(in->i[E_CUR] + c);
            LANES d[l] = v[l];
        }
        for (int64_t c = (nc1 - 1) * n_u - 1; c >= 0; c--) {
            double *d = SL(us + n_u + c), *v = SL(us + c);
            LANES d[l] = v[l];
        }
        for (int64_t c = 0; c < n_u; c++) {
            double *d = SL(us + c), *v = SL(in->i[E_UNOW] + c);
            LANES d[l] = v[l];
        }
    }
}

static inline double *bind_addr_f(const bind_t *bd, int64_t b, int64_t c, size_t esize) {
    int64_t off = b * bd->mstride + (c / bd->inner) * bd->ostride + c % bd->inner;
    return (double *)((char *)bd->ptr + off * (int64_t)esize);
}

static void load(const bind_t *bd, int64_t nbind, double *S, int64_t b0, int64_t nb) {
    for (int64_t q = 0; q < nbind; q++) {
        const bind_t *x = bd + q;
        if (!(x->mode & 1)) continue;
        for (int64_t c = 0; c < x->count; c++) {
            double *d = SL(x->slot + c);
            for (int64_t l = 0; l < VL; l++) {
                int64_t b = b0 + (l < nb ? l : nb - 1); /* spare lanes repeat the last member */
                if (x->kind == 0) d[l] = *bind_addr_f(x, b, c, 8);
                else if (x->kind == 1) d[l] = *(const uint8_t *)bind_addr_f(x, b, c, 1) ? 1.0 : 0.0;
                else d[l] = (double)*(const int64_t *)bind_addr_f(x, b, c, 8);
            }
        }
    }
}

static void store(const bind_t *bd, int64_t nbind, const double *S, int64_t b0, int64_t nb) {
    for (int64_t q = 0; q < nbind; q++) {
        const bind_t *x = bd + q;
        if (!(x->mode & 2)) continue;
        for (int64_t c = 0; c < x->count; c++) {
            const double *d = SL(x->slot + c);
            for (int64_t l = 0; l < nb; l++) {
                if (x->kind == 0) *bind_addr_f(x, b0 + l, c, 8) = d[l];
                else if (x->kind == 1) *(uint8_t *)bind_addr_f(x, b0 + l, c, 1) = d[l] != 0.0;
                else *(int64_t *)bind_addr_f(x, b0 + l, c, 8) = (int64_t)d[l];
            }
        }
    }
}

int64_t rco_instr_size(void) { return (int64_t)sizeof(instr_t); }
int64_t rco_bind_size(void) { return (int64_t)sizeof(bind_t); }

/* Run the program for T steps over members [0, B), VL members at a time, on nslots slots per chunk. */
int rco_run(const instr_t *prog, int64_t nins, const bind_t *binds, int64_t nbind, int64_t nslots, int64_t T,
            int64_t B, int nthreads) {
    int64_t nchunks = (B + VL - 1) / VL;
    int fail = 0;
#ifdef _OPENMP
#pragma omp parallel num_threads(nthreads) if (nthreads > 1 && nchunks > 1) reduction(| : fail)
#endif
    {
        double *S = (double *)aligned_alloc(64, (size_t)(nslots * VL) * sizeof(double));
        if (!S) {
            fail = 1;
        } else {
            memset(S, 0, (size_t)(nslots * VL) * sizeof(double));
#ifdef _OPENMP
#pragma omp for schedule(static)
#endif
            for (int64_t ch = 0; ch < nchunks; ch++) {
                int64_t b0 = ch * VL, nb = B - b0 < VL ? B - b0 : VL;
                load(binds, nbind, S, b0, nb);
                for (int64_t t = 0; t < T; t++) {
                    for (int64_t q = 0; q < nins; q++) {
                        const instr_t *in = prog + q;
                        switch (in->op) {
                        case OP_SEQ: op_seq(in, S, b0, nb, t); break;
                        case OP_LTI_OUT: op_lti_out(in, S); break;
                        case OP_LTI_UPD: op_lti_upd(in, S); break;
                        case OP_GAIN: op_gain(in, S); break;
                        case OP_SUM: op_sum(in, S); break;
                        case OP_ACC_SQ: op_acc_sq(in, S); break;
                        case OP_RCO_OUT: op_rco_out(in, S); break;
                        case OP_RCO_UPD: op_rco_upd(in, S, t); break;
                        default: break;
                        }
                    }
                }
                store(binds, nbind, S, b0, nb);
            }
            free(S);
        }
    }
    return fail ? -1 : 0;
}
