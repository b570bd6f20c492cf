/* The engine's operations on VL lanes (members) at once. engine.c includes this file once for each lane
 * width (VL = 1, 4, 8, 16) and instruction set; FN(name) names this copy's functions.
 *
 * Every value lives in slots: slot s holds one double for each lane, S[s * VL + lane], so each operation is
 * a loop over the lanes that the compiler vectorizes. A lane's arithmetic is the same sequence of IEEE
 * operations whatever VL is (no reassociation, no contraction: -ffp-contract=off, no fast-math), so a member's
 * result does not depend on the lane width, the batch or the threads.
 *
 * The equations follow the PyTorch blocks, the reference semantics: blocks/base.py (Gain, Sum), blocks/lti.py,
 * blocks/sources.py (WhiteNoise, Recorded), blocks/features.py, estimator/rco.py (RCOEstimator.output, .update)
 * and engine/rls.py (rls_update).
 *
 * One member alone (VL = 1) is bound by the instructions it executes, not by arithmetic: a loop over sizes
 * known only at run time costs more than its few multiply-adds. At VL = 1 these operations therefore also
 * exist as copies compiled with their sizes as constants, which the compiler unrolls (the arithmetic, and so
 * every result, is the same in every copy):
 *
 *   copy                  compiled for                                    chosen
 *   LTI_OUT               n = 1..LTI_SMALL_N states, 1..LTI_SMALL_W       when the program is decoded
 *                         output rows, no feedthrough                     (lti_out_sized)
 *   LTI_UPD               n = 1..LTI_SMALL_N states, 1..LTI_SMALL_W       when the program is decoded
 *                         input columns; the new state in registers       (lti_upd_sized)
 *   SUM                   two inputs of width 1                           when the program is decoded (sum_1_2)
 *   RCO_OUT               one u, n_phi = 1..SMALL regressors              when the program is decoded
 *                                                                         (rco_out_sized)
 *   RCO_UPD               one u, z and row, n = n_phi = 1..SMALL          on each step (FN(rco_upd))
 *                         parameters, one per regressor
 *   RCO_UPD stages:
 *     own_scratch         one member whose scratch fits OWN slots: the    on each step (FN(rco_upd_n))
 *                         scratch in an array of its own, in registers
 *     theta_is_eta        one u, z and row, each entry its own            on each step
 *                         parameter: eta is theta, Psi the filter's sums
 *     row_after_filter    own_scratch and theta_is_eta, the current row   on each step
 *                         weighed by 0: the filter sums before the row
 *                         is stored
 *   Markov filter         one member: 4, then 2 columns at a time in      always at VL = 1 (FN(markov))
 *                         vectors
 */

/* The SISO estimator's sizes compiled as constants at one lane: 1 .. SMALL. */
#define SMALL_LIST(X) X(1) X(2) X(3) X(4) X(5) X(6)
#define X_COUNT(c) +1
#define SMALL (0 SMALL_LIST(X_COUNT))
/* The LTI sizes compiled as constants at one lane: n = 1 .. LTI_SMALL_N states, w = 1 .. LTI_SMALL_W output rows
 * (LTI_OUT) or input columns (LTI_UPD); each (n, w) as X(op, n, w). */
#define LTI_STATES(X, op) X(op, 1) X(op, 2) X(op, 3) X(op, 4)
#define LTI_WIDTHS(X, op, n) X(op, n, 1) X(op, n, 2)
#define X_COUNT2(op, c) +1
#define X_COUNT3(op, n, c) +1
#define LTI_SMALL_N (0 LTI_STATES(X_COUNT2, _))
#define LTI_SMALL_W (0 LTI_WIDTHS(X_COUNT3, _, _))
/* The scratch of one member's estimator update held in an array of its own (rco_upd_n): room for the SISO
 * estimator of SMALL parameters, rounded up to whole cache lines. */
#define OWN ((RCO_UPD_SCRATCH_SIZE(1, 1, SMALL, SMALL, 1) + 7) / 8 * 8)

#define LANES _Pragma("omp simd") for (int l = 0; l < VL; l++)
#define SL(s) (S + (int64_t)(s) * VL)
#define AT(p, i) ((p) + (int64_t)(i) * VL) /* element i of a lane array */
/* acc += p x for a parameter slot p (read once when every lane holds the same value) and a lane slot x */
#define PMAC(acc, p, x, shared)                                                                              \
    do {                                                                                                     \
        const double *p_ = (p), *x_ = (x);                                                                   \
        if (VL == 1 || (shared)) {                                                                           \
            double v_ = p_[0];                                                                               \
            LANES(acc)[l] += v_ * x_[l];                                                                     \
        } else {                                                                                             \
            LANES(acc)[l] += p_[l] * x_[l];                                                                  \
        }                                                                                                    \
    } while (0)

/* ------------------------------------------------------------------------------------------------------ */
/* RLS (engine/rls.py, rls_update): theta (n), P (n x n), psi (n x nl), zr (nl), lam (1), rinv (nl x nl), active (1)  */
/* in lane arrays; ok (1) out: 0 where S is not positive definite and finite or the step is not finite.     */
/* ------------------------------------------------------------------------------------------------------ */
/* a = P Psi (n x nl) */
static inline ALWAYS void FN(rls_p_psi)(int64_t n, int64_t nl, const double *restrict P,
                                        const double *restrict psi, double *restrict a) {
    for (int64_t i = 0; i < n; i++)
        for (int64_t c = 0; c < nl; c++) {
            double acc[VL];
            LANES acc[l] = 0.0;
            for (int64_t j = 0; j < n; j++) {
                const double *p = AT(P, i * n + j), *q = AT(psi, j * nl + c);
                LANES acc[l] += p[l] * q[l];
            }
            double *ai = AT(a, i * nl + c);
            LANES ai[l] = acc[l];
        }
}

/* One row (nl = 1): S = lam R^-1 + psi^T P psi, a scalar; the step P psi S^-1 z_R and si = S^-1, a = P psi and
 * both 0 where the member does not go (go: active, S > 0 and finite, the step finite). */
static inline ALWAYS void FN(rls_gain_row)(int64_t n, double *restrict a, double *restrict step,
        const double *restrict psi, const double *restrict zr, const double *restrict lam, int lam_one,
        const double *restrict rinv, const double *restrict active, double *restrict ok, double *restrict go,
        double *restrict si) {
    double s[VL], g[VL], sum[VL];
    LANES s[l] = 0.0;
    for (int64_t i = 0; i < n; i++) {
        const double *q = AT(psi, i), *ai = AT(a, i);
        LANES s[l] += q[l] * ai[l];
    }
    LANES {
        double sv = (lam_one ? rinv[l] : lam[l] * rinv[l]) + s[l]; /* S = lam R^-1 + psi^T P psi */
        int ok0 = (sv > 0.0) & (sv < INFINITY), gg = ok0 & (active[l] != 0.0);
        ok[l] = ok0;
        s[l] = gg ? sv : 1.0;
        go[l] = gg;
        double q = zr[l] / s[l]; /* every lane loads (no masked loads) */
        g[l] = gg ? q : 0.0;
        sum[l] = 0.0;
    }
    for (int64_t i = 0; i < n; i++) {
        double *ai = AT(a, i), *st = AT(step, i);
        LANES {
            ai[l] = go[l] != 0.0 ? ai[l] : 0.0;
            st[l] = ai[l] * g[l]; /* P psi S^-1 z_R */
            sum[l] += st[l];
        }
    }
    LANES {
        int fin = fabs(sum[l]) < INFINITY;
        ok[l] = (ok[l] != 0.0) & fin;
        go[l] = (go[l] != 0.0) & fin;
        si[l] = go[l] != 0.0 ? 1.0 / s[l] : 0.0;
    }
    for (int64_t i = 0; i < n; i++) {
        double *st = AT(step, i);
        LANES st[l] = go[l] != 0.0 ? st[l] : 0.0;
    }
}

/* S = L L^T (nl x nl) in place, the lower triangle; ok cleared where a pivot is not positive (the pivot is
 * then taken as 1, so that every lane goes on). */
static inline ALWAYS void FN(cholesky)(int64_t nl, double *restrict Lm, double *restrict ok) {
    for (int64_t j = 0; j < nl; j++) {
        double *ljj = AT(Lm, j * nl + j), d[VL];
        LANES d[l] = 0.0;
        for (int64_t k = 0; k < j; k++) {
            const double *ljk = AT(Lm, j * nl + k);
            LANES d[l] += ljk[l] * ljk[l];
        }
        LANES {
            double piv = ljj[l] - d[l];
            ok[l] = (ok[l] != 0.0) & (piv > 0.0);
            ljj[l] = sqrt(piv > 0.0 ? piv : 1.0);
        }
        for (int64_t i = j + 1; i < nl; i++) {
            double *lij = AT(Lm, i * nl + j);
            LANES d[l] = 0.0;
            for (int64_t k = 0; k < j; k++) {
                const double *lik = AT(Lm, i * nl + k), *ljk = AT(Lm, j * nl + k);
                LANES d[l] += lik[l] * ljk[l];
            }
            LANES lij[l] = (lij[l] - d[l]) / ljj[l];
        }
    }
}

/* nl rows: S = lam R^-1 + Psi^T P Psi and its Cholesky factor L (in Lm), W = a L^-T, v = L^-1 z_R and the step
 * W v, each 0 where the member does not go (go: active, S positive definite and finite, the step finite). */
static inline ALWAYS void FN(rls_gain_rows)(int64_t n, int64_t nl, const double *restrict a, double *restrict step,
        double *restrict Lm, double *restrict Wm, double *restrict v, const double *restrict psi,
        const double *restrict zr, const double *restrict lam, int lam_one, const double *restrict rinv,
        const double *restrict active, double *restrict ok, double *restrict go) {
    double sum[VL];
    for (int64_t c1 = 0; c1 < nl; c1++) /* S = lam R^-1 + Psi^T P Psi, into Lm */
        for (int64_t c2 = 0; c2 < nl; c2++) {
            double *sc = AT(Lm, c1 * nl + c2), acc[VL];
            const double *r = AT(rinv, c1 * nl + c2);
            LANES acc[l] = 0.0;
            for (int64_t i = 0; i < n; i++) {
                const double *q = AT(psi, i * nl + c1), *ai = AT(a, i * nl + c2);
                LANES acc[l] += q[l] * ai[l];
            }
            LANES sc[l] = (lam_one ? r[l] : lam[l] * r[l]) + acc[l];
        }
    LANES ok[l] = 1.0;
    for (int64_t e = 0; e < nl * nl; e++) {
        const double *sc = AT(Lm, e);
        LANES ok[l] = (ok[l] != 0.0) & (fabs(sc[l]) < INFINITY);
    }
    FN(cholesky)(nl, Lm, ok);
    LANES go[l] = (ok[l] != 0.0) & (active[l] != 0.0);
    for (int64_t i = 0; i < nl; i++) /* L where go, else I */
        for (int64_t j = 0; j <= i; j++) {
            double *lij = AT(Lm, i * nl + j), e = i == j ? 1.0 : 0.0;
            LANES lij[l] = go[l] != 0.0 ? lij[l] : e;
        }
    for (int64_t r = -1; r < n; r++) { /* W = a L^-T (rows r of a), v = L^-1 z_R (r = -1) */
        for (int64_t c = 0; c < nl; c++) {
            double *x = r < 0 ? AT(v, c) : AT(Wm, r * nl + c);
            const double *b = r < 0 ? AT(zr, c) : AT(a, r * nl + c), *lcc = AT(Lm, c * nl + c);
            LANES {
                double bv = b[l];
                x[l] = go[l] != 0.0 ? bv : 0.0;
            }
            for (int64_t k = 0; k < c; k++) {
                const double *lck = AT(Lm, c * nl + k), *xk = r < 0 ? AT(v, k) : AT(Wm, r * nl + k);
                LANES x[l] -= lck[l] * xk[l];
            }
            LANES x[l] /= lcc[l];
        }
    }
    LANES sum[l] = 0.0;
    for (int64_t i = 0; i < n; i++) { /* step = W v */
        double *st = AT(step, i), acc[VL];
        LANES acc[l] = 0.0;
        for (int64_t c = 0; c < nl; c++) {
            const double *w = AT(Wm, i * nl + c), *vc = AT(v, c);
            LANES acc[l] += w[l] * vc[l];
        }
        LANES st[l] = acc[l];
        LANES sum[l] += st[l];
    }
    LANES {
        int fin = fabs(sum[l]) < INFINITY;
        ok[l] = (ok[l] != 0.0) & fin;
        go[l] = (go[l] != 0.0) & fin;
    }
    for (int64_t i = 0; i < n; i++) {
        double *st = AT(step, i);
        LANES st[l] = go[l] != 0.0 ? st[l] : 0.0;
        for (int64_t c = 0; c < nl; c++) {
            double *w = AT(Wm, i * nl + c);
            LANES w[l] = go[l] != 0.0 ? w[l] : 0.0;
        }
    }
}

/* P <- (P - W W^T) / lam where the member goes, W W^T = (a a^T) S^-1 for one row (Wm = a, si = S^-1: (a_i a_j)
 * si, exactly symmetric); theta <- theta - step. */
static inline ALWAYS void FN(rls_apply)(int64_t n, int64_t nl, double *restrict th, double *restrict P,
        const double *restrict Wm, const double *restrict si, const double *restrict step,
        const double *restrict lam, int lam_one, const double *restrict go) {
    for (int64_t i = 0; i < n; i++)
        for (int64_t j = 0; j < n; j++) {
            double *p = AT(P, i * n + j);
            if (nl == 1) {
                const double *ai = AT(Wm, i), *aj = AT(Wm, j);
                LANES p[l] -= (ai[l] * aj[l]) * si[l];
            } else {
                double d[VL];
                LANES d[l] = 0.0;
                for (int64_t c = 0; c < nl; c++) {
                    const double *wi = AT(Wm, i * nl + c), *wj = AT(Wm, j * nl + c);
                    LANES d[l] += wi[l] * wj[l];
                }
                LANES p[l] -= d[l];
            }
            if (!lam_one) LANES {
                double lv = lam[l];
                p[l] /= go[l] != 0.0 ? lv : 1.0;
            }
        }
    for (int64_t i = 0; i < n; i++) {
        double *t = AT(th, i);
        const double *st = AT(step, i);
        LANES t[l] -= st[l];
    }
}

/* The RLS step: a = P Psi, the gain (one row with S^-1, or nl rows through S's Cholesky factor), then P and
 * theta. */
static inline ALWAYS void FN(rls)(int64_t n, int64_t nl, double *restrict th,
        double *restrict P, const double *restrict psi, const double *restrict zr, const double *restrict lam,
        int lam_one, const double *restrict rinv, const double *restrict active, double *restrict ok,
        double *restrict scr) {
    const rls_scratch_t at = rls_scratch_at(n, nl);
    double *a = AT(scr, at.a), *step = AT(scr, at.step), *Lm = AT(scr, at.L), *Wm = AT(scr, at.W), *v = AT(scr, at.v);
    double go[VL], si[VL] = {0}; /* si: S^-1 of one row (nl = 1) */
    FN(rls_p_psi)(n, nl, P, psi, a);
    if (VL == 1 && nl == 1) {
        /* One member, one row: the step the member takes when it goes, with the checks as predicted branches
         * (a selection would put them on the path from one step's theta and P to the next). The same
         * operations as below; a member that does not go takes the general path. */
        double s = 0.0;
        for (int64_t i = 0; i < n; i++) s += psi[i] * a[i];
        const double sv = (lam_one ? rinv[0] : lam[0] * rinv[0]) + s;
        if (__builtin_expect((sv > 0.0) & (sv < INFINITY) & (active[0] != 0.0), 1)) {
            const double q = zr[0] / sv;
            double sum = 0.0;
            for (int64_t i = 0; i < n; i++) {
                step[i] = a[i] * q;
                sum += step[i];
            }
            if (__builtin_expect(fabs(sum) < INFINITY, 1)) {
                const double inv = 1.0 / sv;
                for (int64_t i = 0; i < n; i++)
                    for (int64_t j = 0; j < n; j++) {
                        double p = P[i * n + j] - (a[i] * a[j]) * inv;
                        P[i * n + j] = lam_one ? p : p / lam[0];
                    }
                for (int64_t i = 0; i < n; i++) th[i] -= step[i];
                ok[0] = 1.0;
                return;
            }
        }
    }
    if (nl == 1) {
        FN(rls_gain_row)(n, a, step, psi, zr, lam, lam_one, rinv, active, ok, go, si);
        Wm = a;
    } else {
        FN(rls_gain_rows)(n, nl, a, step, Lm, Wm, v, psi, zr, lam, lam_one, rinv, active, ok, go);
    }
    FN(rls_apply)(n, nl, th, P, Wm, si, step, lam, lam_one, go);
}

/* ------------------------------------------------------------------------------------------------------ */
/* Sources, LTI, static blocks                                                                             */
/* ------------------------------------------------------------------------------------------------------ */
static inline void FN(playback)(const int64_t *restrict a, double *restrict S, const int64_t *restrict ptrs,
                                const int64_t *restrict ctr, int64_t t,
                                int64_t b0, int64_t nb) {
    const double *src = (const double *)(intptr_t)ptrs[a[PLAYBACK_TABLE]];
    int64_t ms = a[PLAYBACK_MSTRIDE], ts = a[PLAYBACK_TSTRIDE], off = a[PLAYBACK_OFFSET], w = a[PLAYBACK_WIDTH];
    int64_t k = ctr[a[PLAYBACK_COUNTER]] + t;
    for (int64_t c = 0; c < w; c++) {
        double *o = SL(a[PLAYBACK_OUT] + c);
        LANES o[l] = src[(b0 + (l < nb ? l : nb - 1)) * ms + k * ts + off + c];
    }
}

/* The buffer of a channel holds the normals of pairs of steps, from the even step at or before the step of its
 * fill: [parity][pair][lane], NOISE_PAIRS pairs, so that one log, one square root, a cosine and a sine make two
 * steps' normals. */
static inline void FN(noise)(const int64_t *restrict a, double *restrict S, const int64_t *restrict ctr,
                             int64_t t, int64_t T) {
    int64_t w = a[NOISE_WIDTH], k = ctr[a[NOISE_COUNTER]] + t, ahead = t % NOISE_AHEAD;
    int64_t odd = (k - ahead) & 1; /* the filling step was odd: the buffer starts one step before it */
    const double *key = SL(a[NOISE_KEY]), *sd = SL(a[NOISE_STD]), *mean = SL(a[NOISE_MEAN]);
    double *buf = SL(a[NOISE_BUFFER]);
    if (ahead == 0) { /* the pairs of the next steps (at most NOISE_AHEAD, no further than the call's last step) */
        uint32_t k1 = mix32_key(1u), k2 = mix32_key(2u);
        int64_t p0 = (k - odd) >> 1, n = ((T - t < NOISE_AHEAD ? T - t : NOISE_AHEAD) + odd + 1) / 2 * VL;
        for (int64_t c = 0; c < w; c++) {
            uint32_t kc = mix32_key((uint32_t)c);
            double *even = buf + c * 2 * NOISE_PAIRS * VL, *next = even + NOISE_PAIRS * VL;
            _Pragma("omp simd") for (int64_t j = 0; j < n; j++) {
                uint32_t h = mix32(mix32(key_u32(key[j % VL]) ^ mix32_key((uint32_t)(p0 + j / VL))) ^ kc);
                normal_pair(uniform53(mix32(h ^ k1)), uniform53(mix32(h ^ k2)), even + j, next + j);
            }
        }
    }
    int64_t s = ahead + odd; /* the step in the buffer */
    for (int64_t c = 0; c < w; c++) {
        const double *n = buf + (c * 2 * NOISE_PAIRS + (s & 1) * NOISE_PAIRS + (s >> 1)) * VL;
        double *o = SL(a[NOISE_OUT] + c);
        LANES o[l] = n[l] * sd[l] + mean[l];
    }
}

/* out = C[rows] x + sum_f D[rows, column_f] u_f over the feedthrough columns f (a column and its input slot) */
static inline ALWAYS void FN(lti_out_n)(const int64_t *restrict a, double *restrict S, int64_t n, int64_t w,
                                        int64_t nft) {
    int64_t cs = a[LTI_OUT_C], xs = a[LTI_OUT_STATE], os = a[LTI_OUT_OUT], mt = a[LTI_OUT_MT], ds = a[LTI_OUT_D];
    int64_t sh = a[LTI_OUT_SHARED];
    const int64_t *restrict ft = a + LTI_OUT_N; /* the table FEEDTHROUGH */
    for (int64_t r = 0; r < w; r++) {
        double acc[VL];
        LANES acc[l] = 0.0;
        for (int64_t j = 0; j < n; j++) PMAC(acc, SL(cs + r * n + j), SL(xs + j), sh);
        for (int64_t f = 0; f < nft; f++) {
            const int64_t *col = ft + f * LTI_FT_N;
            PMAC(acc, SL(ds + r * mt + col[LTI_FT_COLUMN]), SL(col[LTI_FT_IN]), sh);
        }
        double *o = SL(os + r);
        LANES o[l] = acc[l];
    }
}

/* x = A x + B u, u the mt input columns (the slot of each): the new state into the lane array xn, from which
 * the caller then stores x */
static inline ALWAYS void FN(lti_upd_to)(const int64_t *restrict a, double *restrict S, int64_t n, int64_t mt,
                                         double *restrict xn) {
    int64_t as = a[LTI_UPD_A], bs = a[LTI_UPD_B], xs = a[LTI_UPD_STATE], sh = a[LTI_UPD_SHARED];
    const int64_t *restrict in = a + LTI_UPD_N; /* the table INPUTS, one slot per entry */
    for (int64_t r = 0; r < n; r++) {
        double acc[VL];
        LANES acc[l] = 0.0;
        for (int64_t j = 0; j < n; j++) PMAC(acc, SL(as + r * n + j), SL(xs + j), sh);
        for (int64_t c = 0; c < mt; c++) PMAC(acc, SL(bs + r * mt + c), SL(in[c]), sh);
        double *o = AT(xn, r);
        LANES o[l] = acc[l];
    }
}
static inline ALWAYS void FN(lti_upd_n)(const int64_t *restrict a, double *restrict S, int64_t n, int64_t mt) {
    double *xn = SL(a[LTI_UPD_SCRATCH]); /* through the scratch slots */
    FN(lti_upd_to)(a, S, n, mt, xn);
    for (int64_t r = 0; r < n; r++) {
        double *x = SL(a[LTI_UPD_STATE] + r);
        const double *v = AT(xn, r);
        LANES x[l] = v[l];
    }
}

/* The copies compiled for their sizes, used at one lane only: an output without feedthrough, and an update
 * (n <= 4) that holds the new state in an array of its own, in registers, rather than in the scratch slots */
static inline ALWAYS void FN(lti_out_c)(const int64_t *restrict a, double *restrict S, int64_t n, int64_t w) {
    FN(lti_out_n)(a, S, n, w, 0);
}
static inline ALWAYS void FN(lti_upd_c)(const int64_t *restrict a, double *restrict S, int64_t n, int64_t mt) {
    double xn[LTI_SMALL_N * VL];
    FN(lti_upd_to)(a, S, n, mt, xn);
    for (int64_t r = 0; r < n; r++) SL(a[LTI_UPD_STATE] + r)[0] = xn[r];
}

/* A compiled user function, called once per chunk: its inputs are consecutive slots (n_in x VL lane values,
 * slot by slot) and so are its outputs; spare lanes compute on their copy of the last member's values, as
 * everywhere. */
typedef void (*rco_fn_t)(const double *, double *, int64_t);
static inline void FN(call)(const int64_t *restrict a, double *restrict S, const int64_t *restrict ptrs) {
    ((rco_fn_t)(intptr_t)ptrs[a[CALL_FUNCTION]])(SL(a[CALL_IN]), SL(a[CALL_OUT]), VL);
}

static inline void FN(gain)(const int64_t *restrict a, double *restrict S) {
    int64_t m = a[GAIN_ROWS], n = a[GAIN_COLS], ks = a[GAIN_K], is = a[GAIN_IN], os = a[GAIN_OUT];
    int64_t sh = a[GAIN_SHARED];
    for (int64_t r = 0; r < m; r++) {
        double acc[VL];
        LANES acc[l] = 0.0;
        for (int64_t j = 0; j < n; j++) PMAC(acc, SL(ks + r * n + j), SL(is + j), sh);
        double *o = SL(os + r);
        LANES o[l] = acc[l];
    }
}

static inline ALWAYS void FN(sum_n)(const int64_t *restrict a, double *restrict S, int64_t w, int64_t nin) {
    int64_t os = a[SUM_OUT];
    const int64_t *terms = a + SUM_N; /* the table TERMS */
    for (int64_t c = 0; c < w; c++) {
        double acc[VL];
        LANES acc[l] = 0.0;
        for (int64_t q = 0; q < nin; q++) {
            const int64_t *term = terms + q * SUM_TERM_N;
            const double *v = SL(term[SUM_TERM_IN] + c);
            int pos = term[SUM_TERM_SIGN] > 0;
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

static inline void FN(sum)(const int64_t *restrict a, double *restrict S) {
    FN(sum_n)(a, S, a[SUM_WIDTH], a[SUM_NIN]);
}

static inline void FN(copy)(const int64_t *restrict a, double *restrict S) {
    for (int64_t c = 0; c < a[COPY_WIDTH]; c++) {
        const double *v = SL(a[COPY_IN] + c);
        double *o = SL(a[COPY_OUT] + c);
        LANES o[l] = v[l];
    }
}

/* Basis features (blocks/features.py): each output channel is coefficient * f_1(x_1) * f_2(x_2) * ... */
static inline void FN(feature)(const int64_t *restrict a, double *restrict S, const double *restrict consts) {
    int64_t out = a[FEATURE_OUT], nterms = a[FEATURE_NTERMS];
    const int64_t *q = a + FEATURE_N; /* the table TERMS: each term's fields, then its table FACTORS */
    for (int64_t term = 0; term < nterms; term++) {
        int64_t w = q[TERM_WIDTH], nf = q[TERM_NFACTORS];
        double coef = consts[q[TERM_COEF]];
        for (int64_t c = 0; c < w; c++) {
            double v[VL];
            LANES v[l] = coef;
            for (int64_t f = 0; f < nf; f++) {
                const int64_t *fa = q + TERM_N + f * FF_N;
                const double *x = SL(fa[FF_SRC] + fa[FF_STRIDE] * c), *p = consts + fa[FF_PARAM];
                switch (fa[FF_KIND]) {
                case FAC_POW:
                    LANES {
                        double r = x[l];
                        for (int64_t e = 1; e < fa[FF_POWER]; e++) r *= x[l];
                        v[l] *= r;
                    }
                    break;
                case FAC_SIGN: LANES v[l] *= (double)(x[l] > 0.0) - (double)(x[l] < 0.0); break;
                case FAC_ABS: LANES v[l] *= fabs(x[l]); break;
                case FAC_SAT: LANES v[l] *= clampd(x[l], p[FP_LO], p[FP_HI]); break;
                case FAC_DEADZONE: LANES v[l] *= x[l] - clampd(x[l], p[FP_LO], p[FP_HI]); break;
                case FAC_TANH: LANES v[l] *= tanh(x[l] / p[FP_SCALE]); break;
                case FAC_AFFINE: LANES v[l] *= p[FP_GAIN] * x[l] + p[FP_OFFSET]; break;
                default: break;
                }
            }
            double *o = SL(out + c);
            LANES o[l] = v[l];
        }
        out += w;
        q += TERM_N + nf * FF_N;
    }
}

/* ------------------------------------------------------------------------------------------------------ */
/* The RCO estimator (estimator/rco.py)                                                                    */
/* ------------------------------------------------------------------------------------------------------ */

/* output: phi = [s(k) | past s | past u] gathered, u = theta phi (0 for a frozen member), saturated. */
static inline ALWAYS void FN(rco_out_n)(const int64_t *restrict e, double *restrict S, int64_t n_u,
                                        int64_t n_phi) {
    const int64_t *phi_src = e + E_N; /* the table PHI_SRC */
    const double *alive = SL(e[E_ALIVE]);
    for (int64_t j = 0; j < n_phi; j++) {
        const double *v = SL(phi_src[j]);
        double *phi = SL(e[E_PHI] + j);
        LANES phi[l] = v[l];
    }
    for (int64_t a = 0; a < n_u; a++) { /* phi read from its sources: the same values, not waiting for the copy */
        double acc[VL];
        LANES acc[l] = 0.0;
        for (int64_t j = 0; j < n_phi; j++) {
            const double *th = SL(e[E_THETA] + a * n_phi + j), *phi = SL(phi_src[j]);
            LANES acc[l] += th[l] * phi[l];
        }
        LANES acc[l] = alive[l] != 0.0 ? acc[l] : 0.0;
        if (e[E_ULO] >= 0) {
            const double *lo = SL(e[E_ULO] + a), *hi = SL(e[E_UHI] + a);
            LANES acc[l] = clampd(acc[l], lo[l], hi[l]);
        }
        double *u = SL(e[E_UNOW] + a), *uo = SL(e[E_UOUT] + a);
        LANES u[l] = uo[l] = acc[l];
    }
}

static inline void FN(rco_out)(const int64_t *restrict e, double *restrict S) {
    FN(rco_out_n)(e, S, e[E_NU], e[E_NPHI]);
}

/* The rows of the RLS step (estimator/rco.py, _rows): z_R into zrx, the rows of z divided by
 * m = sqrt(1 + |Psi|_R^2 / s^2) when normalized (NORM; R in RW), then sqrt(r_delta) I with residual 0 (RDQ). */
static inline void FN(rco_rows)(const int64_t *restrict e, double *restrict S, int64_t n, int64_t n_z, int64_t nl,
                                double *restrict psi, const double *restrict zr, double *restrict zrx) {
    for (int64_t z = 0; z < n_z; z++) {
        const double *a = AT(zr, z);
        double *x = AT(zrx, z);
        LANES x[l] = a[l];
    }
    if (e[E_NORM] >= 0) {
        const double *is2 = SL(e[E_NORM]), *rw = SL(e[E_RW]);
        double ss[VL], mm[VL];
        LANES ss[l] = 0.0;
        for (int64_t z = 0; z < n_z; z++) /* |Psi|_R^2 = sum Psi^T * (R Psi^T), in the order of Psi^T (z, p) */
            for (int64_t p = 0; p < n; p++) {
                const double *ps = AT(psi, p * nl + z);
                double rp[VL];
                LANES rp[l] = 0.0;
                for (int64_t y = 0; y < n_z; y++) {
                    const double *r = AT(rw, z * n_z + y), *py = AT(psi, p * nl + y);
                    LANES rp[l] += r[l] * py[l];
                }
                LANES ss[l] += ps[l] * rp[l];
            }
        LANES mm[l] = sqrt(1.0 + ss[l] * is2[l]);
        for (int64_t z = 0; z < n_z; z++) {
            double *x = AT(zrx, z);
            LANES x[l] /= mm[l];
            for (int64_t p = 0; p < n; p++) {
                double *ps = AT(psi, p * nl + z);
                LANES ps[l] /= mm[l];
            }
        }
    }
    if (e[E_RDQ] >= 0) {
        const double *rq = SL(e[E_RDQ]);
        for (int64_t q = 0; q < n; q++) {
            double *x = AT(zrx, n_z + q);
            LANES x[l] = 0.0;
            for (int64_t p = 0; p < n; p++) {
                double *ps = AT(psi, p * nl + n_z + q);
                LANES ps[l] = p == q ? rq[l] : 0.0;
            }
        }
    }
}

/* [phi(k), u(k)] into row pr of the window ring. At one lane, 4 and 2 entries at a time with one
 * store, as the Markov filter reads them (a load of values just stored then gets them from that store, not
 * from the cache). */
static inline ALWAYS void FN(win_row)(const int64_t *restrict e, double *restrict S, int64_t pr, int64_t n_phi,
                                      int64_t m) {
#define WIN_SRC(j) SL((j) < n_phi ? e[E_PHI] + (j) : e[E_UNOW] + (j) - n_phi)
    int64_t j0 = 0;
    if (VL == 1) {
        double *row = SL(e[E_WIN] + pr * m);
        for (; j0 + 3 < m; j0 += 4)
            *(v4d_t *)(row + j0) = (v4d_t){WIN_SRC(j0)[0], WIN_SRC(j0 + 1)[0], WIN_SRC(j0 + 2)[0],
                                           WIN_SRC(j0 + 3)[0]};
        for (; j0 + 1 < m; j0 += 2) *(v2d_t *)(row + j0) = (v2d_t){WIN_SRC(j0)[0], WIN_SRC(j0 + 1)[0]};
    }
    for (int64_t j = j0; j < m; j++) {
        const double *v = WIN_SRC(j);
        double *r1 = SL(e[E_WIN] + pr * m + j);
        LANES r1[l] = v[l];
    }
#undef WIN_SRC
}

/* The Markov filter of the nq = n_z n_u weights: prod[z, a, j] = sum_i beta_i[z, a] [phi, u](k - i) over
 * every row of the ring: row r holds delay (pr - r) mod W, weighed by beta_rev[(r - pr - 1) mod W] and by 0
 * below the first delay as on the PyTorch engine. The weights hold that ring twice ([beta_rev, 0 *
 * first_delay] twice, 2W entries), so this step's weights of rows 0 .. W - 1 are the W entries from W - pr - 1
 * on. Rows in memory order, in four chains. With lanes (VL > 1) and a parameter map (param_of, weights
 * q = z n_u + a), only the sums that the update reads are made: phi column j of weight (z, a) where Theta's
 * entry (a, j) is a parameter, and u column a; a masked static gain on n signals skips most of them. */
static inline ALWAYS void FN(markov)(const int64_t *restrict e, double *restrict S, double *restrict prod,
                                     int64_t nq, int64_t m, int64_t W, int64_t pr, int64_t n_u,
                                     const int64_t *restrict param_of) {
    const double *restrict win = SL(e[E_WIN]);
    const int64_t sh = e[E_SHARED];
    for (int64_t q = 0; q < nq; q++) {
        const double *restrict wr = SL(e[E_BETA] + q * 2 * W + W - pr - 1);
        if (VL == 1) { /* one member: the same four chains, with a row's m columns side by side */
            /* 4, then 2 columns at a time in vectors, then one (the same operations for each column) */
#define COLUMNS(T, K)                                                                                        \
    for (; j + K - 1 < m; j += K) {                                                                          \
        T a0 = {0.0}, a1 = a0, a2 = a0, a3 = a0;                                                             \
        const double *x = win + j;                                                                           \
        int64_t r = 0;                                                                                       \
        for (; r + 3 < W; r += 4, x += 4 * m) {                                                              \
            a0 += wr[r] * *(const T *)x;                                                                     \
            a1 += wr[r + 1] * *(const T *)(x + m);                                                           \
            a2 += wr[r + 2] * *(const T *)(x + 2 * m);                                                       \
            a3 += wr[r + 3] * *(const T *)(x + 3 * m);                                                       \
        }                                                                                                    \
        for (; r < W; r++, x += m) a0 += wr[r] * *(const T *)x;                                              \
        *(T *)(prod + q * m + j) = (a0 + a1) + (a2 + a3);                                                    \
    }
            int64_t j = 0;
            COLUMNS(v4d_t, 4)
            COLUMNS(v2d_t, 2)
            COLUMNS(double, 1)
#undef COLUMNS
            continue;
        }
        const int64_t a = q % n_u, n_phi = m - n_u;
        for (int64_t j = 0; j < m; j++) {
            if (param_of && (j < n_phi ? param_of[a * n_phi + j] < 0 : j - n_phi != a)) continue; /* not read */
            double a0[VL], a1[VL], a2[VL], a3[VL];
            LANES a0[l] = a1[l] = a2[l] = a3[l] = 0.0;
            int64_t r = 0;
            for (; r + 3 < W; r += 4) {
                PMAC(a0, AT(wr, r), AT(win, r * m + j), sh);
                PMAC(a1, AT(wr, r + 1), AT(win, (r + 1) * m + j), sh);
                PMAC(a2, AT(wr, r + 2), AT(win, (r + 2) * m + j), sh);
                PMAC(a3, AT(wr, r + 3), AT(win, (r + 3) * m + j), sh);
            }
            for (; r < W; r++) PMAC(a0, AT(wr, r), AT(win, r * m + j), sh);
            double *p = AT(prod, q * m + j);
            LANES p[l] = (a0[l] + a1[l]) + (a2[l] + a3[l]);
        }
    }
}

/* The stages of the estimator's update (FN(rco_upd_n)), in its order. prod holds the Markov filter's sums
 * prod[z, a, j] = sum_i beta_i[z, a] [phi, u](k - i)[j] (m = n_phi + n_u columns). */

/* zeta(k) = z(k) - sum_i beta_i u(k - i), into zr */
static inline ALWAYS void FN(upd_zeta)(const int64_t *restrict e, double *restrict S, const double *restrict prod,
                                       double *restrict zr, int64_t n_u, int64_t n_z, int64_t n_phi) {
    const int64_t m = n_phi + n_u;
    for (int64_t z = 0; z < n_z; z++) {
        double *o = AT(zr, z), d[VL];
        const double *zi = SL(e[E_Z] + z);
        LANES d[l] = 0.0;
        for (int64_t a = 0; a < n_u; a++) {
            const double *p = AT(prod, (z * n_u + a) * m + n_phi + a);
            if (a == 0) { LANES d[l] = p[l]; } else { LANES d[l] += p[l]; }
        }
        LANES o[l] = zi[l] - d[l];
    }
}

/* eta (each parameter's value, read at its representative entry) and its regressor T^T Psi (the entries of one
 * parameter summed), psi[p, z] */
static inline ALWAYS void FN(upd_over_parameters)(const int64_t *restrict e, double *restrict S,
                                                  const double *restrict prod, double *restrict psi,
                                                  double *restrict eta, const int64_t *restrict param_of,
                                                  const int64_t *restrict rep, int64_t n_u, int64_t n_z,
                                                  int64_t n_phi, int64_t n, int64_t nent, int64_t nl) {
    const int64_t m = n_phi + n_u;
    for (int64_t p = 0; p < n; p++) {
        const double *th = SL(e[E_THETA] + rep[p]);
        double *et = AT(eta, p);
        LANES et[l] = th[l];
        for (int64_t z = 0; z < n_z; z++) {
            double *ps = AT(psi, p * nl + z);
            int first = 1;
            for (int64_t en = 0; en < nent; en++) {
                if (param_of[en] != p) continue;
                const double *v = AT(prod, (z * n_u + en / n_phi) * m + en % n_phi);
                if (first) { LANES ps[l] = v[l]; } else { LANES ps[l] += v[l]; }
                first = 0;
            }
        }
    }
}

/* z_R = zeta + Psi_eta^T eta, in place in zr */
static inline ALWAYS void FN(upd_retrospective)(const double *restrict psi, const double *restrict eta,
                                                double *restrict zr, int64_t n_z, int64_t n, int64_t nl) {
    for (int64_t z = 0; z < n_z; z++) {
        double *o = AT(zr, z), d[VL];
        LANES d[l] = 0.0;
        for (int64_t p = 0; p < n; p++) {
            const double *ps = AT(psi, p * nl + z), *et = AT(eta, p);
            LANES d[l] += ps[l] * et[l];
        }
        LANES o[l] += d[l];
    }
}

/* the members that update: alive, and valid > 0.5 where the estimator has a valid input */
static inline ALWAYS void FN(upd_active)(const int64_t *restrict e, double *restrict S, const double *restrict alive,
                                         double *restrict act) {
    const double *valid = e[E_VALID] >= 0 ? SL(e[E_VALID]) : 0;
    if (valid) { /* & and |, not && and ||, in lane loops: no conditional (masked) loads */
        LANES act[l] = (alive[l] != 0.0) & (valid[l] > 0.5);
    } else {
        LANES act[l] = alive[l] != 0.0;
    }
}

/* Theta = T eta: each parameter's value into every entry it holds (pinned entries stay 0) */
static inline ALWAYS void FN(upd_write_theta)(const int64_t *restrict e, double *restrict S,
                                              const double *restrict eta, const int64_t *restrict param_of,
                                              int64_t nent) {
    for (int64_t en = 0; en < nent; en++) {
        if (param_of[en] < 0) continue;
        double *th = SL(e[E_THETA] + en);
        const double *et = AT(eta, param_of[en]);
        LANES th[l] = et[l];
    }
}

/* theta projected onto its box (P unchanged) */
static inline ALWAYS void FN(upd_project_theta)(const int64_t *restrict e, double *restrict S, int64_t nent) {
    for (int64_t en = 0; en < nent; en++) {
        double *th = SL(e[E_THETA] + en);
        const double *lo = SL(e[E_TLO] + en), *hi = SL(e[E_THI] + en);
        LANES th[l] = clampd(th[l], lo[l], hi[l]);
    }
}

/* the trace bound: P scaled by p_max / trace(P) where a living member whose step succeeded exceeds it */
static inline ALWAYS void FN(upd_bound_covariance)(const int64_t *restrict e, double *restrict S,
                                                   const double *restrict okv, const double *restrict act,
                                                   const double *restrict alive, int64_t n) {
    double *P = SL(e[E_P]), tr[VL], c[VL];
    const double *pm = SL(e[E_PMAX]);
    LANES tr[l] = 0.0;
    for (int64_t i = 0; i < n; i++) {
        const double *pii = AT(P, i * n + i);
        LANES tr[l] += pii[l];
    }
    LANES {
        int fine = (okv[l] != 0.0) | (act[l] == 0.0);
        c[l] = (alive[l] != 0.0) & fine & (tr[l] > pm[l]) ? pm[l] / tr[l] : 1.0;
    }
    for (int64_t i = 0; i < n * n; i++) {
        double *pij = AT(P, i);
        LANES pij[l] *= c[l];
    }
}

/* a member whose step failed while it was active is frozen, the step recorded */
static inline ALWAYS void FN(upd_freeze_failed)(const int64_t *restrict e, double *restrict S,
                                                const double *restrict okv, const double *restrict act,
                                                double *restrict alive, int64_t k) {
    double *dv = SL(e[E_DIV]);
    LANES {
        int fine = (okv[l] != 0.0) | (act[l] == 0.0), dies = (alive[l] != 0.0) & !fine;
        dv[l] = dies ? (double)k : dv[l];
        alive[l] = dies ? 0.0 : alive[l];
    }
}

/* one history moves one step into the past: slots past .. past + nc1 * width hold x(k - 1) .. x(k - nc1) of a
 * signal of ``width`` entries, and x(k) (at cur) becomes x(k - 1) */
static inline ALWAYS void FN(shift_history)(double *restrict S, int64_t past, int64_t cur, int64_t width,
                                            int64_t nc1) {
    for (int64_t c = (nc1 - 1) * width - 1; c >= 0; c--) {
        double *d = SL(past + width + c);
        const double *v = SL(past + c);
        LANES d[l] = v[l];
    }
    for (int64_t c = 0; c < width; c++) {
        double *d = SL(past + c);
        const double *v = SL(cur + c);
        LANES d[l] = v[l];
    }
}

/* the regressor signals and u move one step into the past: s(k) and u(k) become s(k - 1) and u(k - 1) */
static inline ALWAYS void FN(upd_shift_histories)(const int64_t *restrict e, double *restrict S, int64_t n_u) {
    FN(shift_history)(S, e[E_PAST], e[E_CUR], e[E_NSIG], e[E_NC1]);
    FN(shift_history)(S, e[E_PASTU], e[E_UNOW], n_u, e[E_NC1]);
}

/* update: the [phi, u] window, the retrospective error z_R = zeta + Psi_eta^T eta, RLS on eta, theta = T eta,
 * the theta box, the member's health and the regressor histories (a held estimator: the window and the
 * histories only). */
static inline ALWAYS void FN(rco_upd_n)(const int64_t *restrict e, double *restrict S, const int64_t *restrict ctr,
                                        int64_t t, int64_t n_u, int64_t n_z, int64_t n_phi, int64_t n, int64_t nent,
                                        int64_t nl) {
    int64_t W = e[E_W], m = n_phi + n_u, k = ctr[e[E_COUNTER]] + t, pr = ring_row(k, W, (uint64_t)e[E_WMOD]);
    if (e[E_HELD]) { /* held: theta, P and z_r stay; the window and the histories move on */
        FN(win_row)(e, S, pr, n_phi, m);
        if (e[E_NC]) FN(upd_shift_histories)(e, S, n_u);
        return;
    }
    const int64_t *param_of = e + E_N + n_phi, *rep = param_of + nent; /* the tables PARAM_OF and REP */
    /* own_scratch: one member keeps its scratch and z_R (stored to its slot once computed) in an array of its
     * own when they fit: the compiler then holds them in registers where the sizes are constants, where slots in
     * S put a store and a load between one stage of the update and the next. */
    const rco_upd_scratch_t at = rco_upd_scratch_at(n_u, n_z, n_phi, n, nl);
    double own[VL == 1 ? OWN : 1];
    const int own_scratch = VL == 1 && at.end <= OWN;
    double *scr = own_scratch ? own : SL(e[E_SCRATCH]);
    double *prod = AT(scr, at.prod), *psi = AT(scr, at.psi), *eta = AT(scr, at.eta), *act = AT(scr, at.act);
    /* theta_is_eta: one z, one u, one row, each entry its own parameter: Psi is prod's phi part and eta is
     * theta, updated in place */
    const int theta_is_eta = n_z == 1 && n_u == 1 && nl == 1 && e[E_IDENT];
    if (theta_is_eta) {
        psi = prod;
        eta = SL(e[E_THETA]);
    }
    double *okv = AT(scr, at.ok), *zrx = AT(scr, at.zrx), *rls_scr = AT(scr, at.rls);
    double *zr = own_scratch ? AT(scr, at.zr) : SL(e[E_ZR]), *alive = SL(e[E_ALIVE]);
    /* row_after_filter: one member (own_scratch) with one z, u and row (theta_is_eta) whose current row (this
     * step's phi and u, delay 0) is weighed by 0 (below the first delay): the row's products are 0 where its
     * entries are finite and add nothing to the sums. The filter below then sums the ring before the row is
     * stored, so that it does not wait for this step's u: row pr still holds the oldest sample, whose products
     * are 0 as well where it is finite. Where a product is NaN or the current row is not finite, the sums are
     * made again with the row stored, as in the general case. */
    const int row_after_filter = own_scratch && theta_is_eta && SL(e[E_BETA])[W - 1] == 0.0;
    if (!row_after_filter) FN(win_row)(e, S, pr, n_phi, m);
    FN(markov)(e, S, prod, n_z * n_u, m, W, pr, n_u, e[E_IDENT] ? 0 : param_of);
    if (row_after_filter) {
        FN(win_row)(e, S, pr, n_phi, m);
        /* t is finite where the m sums and the row are (or else overflows): then the sums are those of the
         * general order; otherwise they are made again with the row stored (one z and u: m sums) */
        const double *row = SL(e[E_WIN] + pr * m);
        double t = 0.0;
        for (int64_t j = 0; j < m; j++) t += prod[j] + row[j];
        if (__builtin_expect(!(t - t == 0.0), 0)) FN(markov)(e, S, prod, 1, m, W, pr, n_u, 0);
    }
    FN(upd_zeta)(e, S, prod, zr, n_u, n_z, n_phi);
    if (!theta_is_eta) FN(upd_over_parameters)(e, S, prod, psi, eta, param_of, rep, n_u, n_z, n_phi, n, nent, nl);
    FN(upd_retrospective)(psi, eta, zr, n_z, n, nl);
    FN(rco_rows)(e, S, n, n_z, nl, psi, zr, zrx);
    if (own_scratch)
        for (int64_t z = 0; z < n_z; z++) SL(e[E_ZR])[z] = zr[z];
    FN(upd_active)(e, S, alive, act);
    FN(rls)(n, nl, eta, SL(e[E_P]), psi, zrx, SL(e[E_LAM]), (int)e[E_LAM_ONE], SL(e[E_RINV]), act, okv, rls_scr);
    if (!theta_is_eta) FN(upd_write_theta)(e, S, eta, param_of, nent);
    if (e[E_TLO] >= 0) FN(upd_project_theta)(e, S, nent);
    if (e[E_PMAX] >= 0) FN(upd_bound_covariance)(e, S, okv, act, alive, n);
    FN(upd_freeze_failed)(e, S, okv, act, alive, k);
    if (e[E_NC]) FN(upd_shift_histories)(e, S, n_u);
}

static inline void FN(rco_upd)(const int64_t *restrict e, double *restrict S, const int64_t *restrict ctr,
                               int64_t t) {
    int64_t n_u = e[E_NU], n_z = e[E_NZ], n_phi = e[E_NPHI], n = e[E_NTHETA], nent = e[E_NENT], nl = e[E_NL];
    if (VL == 1 && n_u == 1 && n_z == 1 && nl == 1 && n == n_phi) /* SISO, one parameter per regressor */
        switch (n) {
#define SISO_CASE(c) case c: FN(rco_upd_n)(e, S, ctr, t, 1, 1, c, c, c, 1); return;
            SMALL_LIST(SISO_CASE)
#undef SISO_CASE
        default: break;
        }
    FN(rco_upd_n)(e, S, ctr, t, n_u, n_z, n_phi, n, nent, nl);
}

/* ------------------------------------------------------------------------------------------------------ */
/* Running a program                                                                                       */
/* ------------------------------------------------------------------------------------------------------ */
/* Load and store walk each binding's elements in order (c = o * INNER + i: row o, entry i) with each lane's
 * member offset computed once per binding, the element type chosen once per row of entries. */
static inline void FN(load)(const int64_t *bd, int64_t nbind, double *S, int64_t b0, int64_t nb) {
    for (int64_t q = 0; q < nbind; q++) {
        const int64_t *x = bd + q * BF_N;
        if (!(x[BF_MODE] & BIND_LOAD)) continue;
        const int64_t inner = x[BF_INNER], count = x[BF_COUNT], kind = x[BF_KIND];
        /* shared, and read in the first lane only: loaded into that lane */
        if ((x[BF_MODE] & BIND_FIRST_LANE) && x[BF_MSTRIDE] == 0 && kind == KIND_F64) {
            const double *p = (const double *)(intptr_t)x[BF_PTR];
            double *d = SL(x[BF_SLOT]);
            for (int64_t c = 0; c < count; c++) d[c * VL] = p[c];
            continue;
        }
        int64_t m[VL];
        LANES m[l] = (b0 + (l < nb ? l : nb - 1)) * x[BF_MSTRIDE]; /* spare lanes repeat the last member */
        double *d = SL(x[BF_SLOT]);
        for (int64_t c = 0, o = 0; c < count; o += x[BF_OSTRIDE]) {
            int64_t n = count - c < inner ? count - c : inner;
            if (kind == KIND_F64) {
                const double *p = (const double *)(intptr_t)x[BF_PTR] + o;
                for (int64_t i = 0; i < n; i++, d += VL) LANES d[l] = p[m[l] + i];
            } else if (kind == KIND_BOOL) {
                const uint8_t *p = (const uint8_t *)(intptr_t)x[BF_PTR] + o;
                for (int64_t i = 0; i < n; i++, d += VL) LANES d[l] = p[m[l] + i] ? 1.0 : 0.0;
            } else {
                const int64_t *p = (const int64_t *)(intptr_t)x[BF_PTR] + o;
                for (int64_t i = 0; i < n; i++, d += VL) LANES d[l] = (double)p[m[l] + i];
            }
            c += n;
        }
    }
}

static inline void FN(store)(const int64_t *bd, int64_t nbind, const double *S, int64_t b0, int64_t nb) {
    for (int64_t q = 0; q < nbind; q++) {
        const int64_t *x = bd + q * BF_N;
        if (!(x[BF_MODE] & BIND_STORE)) continue;
        const int64_t inner = x[BF_INNER], count = x[BF_COUNT], kind = x[BF_KIND], ms = x[BF_MSTRIDE];
        const double *d = SL(x[BF_SLOT]);
        for (int64_t c = 0, o = b0 * ms; c < count; o += x[BF_OSTRIDE]) {
            int64_t n = count - c < inner ? count - c : inner;
            if (kind == KIND_F64) {
                double *p = (double *)(intptr_t)x[BF_PTR] + o;
                for (int64_t i = 0; i < n; i++, d += VL)
                    for (int64_t l = 0; l < nb; l++) p[l * ms + i] = d[l];
            } else if (kind == KIND_BOOL) {
                uint8_t *p = (uint8_t *)(intptr_t)x[BF_PTR] + o;
                for (int64_t i = 0; i < n; i++, d += VL)
                    for (int64_t l = 0; l < nb; l++) p[l * ms + i] = d[l] != 0.0;
            } else {
                int64_t *p = (int64_t *)(intptr_t)x[BF_PTR] + o;
                for (int64_t i = 0; i < n; i++, d += VL)
                    for (int64_t l = 0; l < nb; l++) p[l * ms + i] = (int64_t)d[l];
            }
            c += n;
        }
    }
}

static inline void FN(observe)(const int64_t *obs, int64_t nobs, double *S, double *acc, int64_t t, int64_t b0,
                               int64_t nb, int64_t B) {
    for (int64_t q = 0; q < nobs; q++) {
        const int64_t *o = obs + q * OF_N;
        int64_t w = o[OF_WIDTH];
        if (o[OF_KIND] == OBS_SUMSQ) {
            double v[VL], *a = AT(acc, q);
            LANES v[l] = 0.0;
            for (int64_t c = 0; c < w; c++) {
                const double *x = SL(o[OF_SLOT] + c);
                LANES v[l] += x[l] * x[l];
            }
            LANES a[l] += v[l];
        } else if ((t + o[OF_PHASE] + 1) % o[OF_EVERY] == 0) {
            double *buf = (double *)(intptr_t)o[OF_PTR] + ((t + o[OF_PHASE] + 1) / o[OF_EVERY] - 1) * B * w;
            for (int64_t c = 0; c < w; c++) {
                const double *x = SL(o[OF_SLOT] + c);
                for (int64_t l = 0; l < nb; l++) buf[(b0 + l) * w + c] = x[l];
            }
        }
    }
}

/* The SUMSQ observers' sums, one lane array each in acc: from the caller's accumulators before the steps
 * (load), back after them (store). */
static inline void FN(sums_load)(const int64_t *obs, int64_t nobs, double *acc, int64_t b0, int64_t nb) {
    for (int64_t q = 0; q < nobs; q++) {
        const int64_t *o = obs + q * OF_N;
        double *a = AT(acc, q);
        if (o[OF_KIND] == OBS_SUMSQ) LANES a[l] = ((const double *)(intptr_t)o[OF_PTR])[b0 + (l < nb ? l : nb - 1)];
    }
}

static inline void FN(sums_store)(const int64_t *obs, int64_t nobs, const double *acc, int64_t b0, int64_t nb) {
    for (int64_t q = 0; q < nobs; q++) {
        const int64_t *o = obs + q * OF_N;
        const double *a = AT(acc, q);
        if (o[OF_KIND] == OBS_SUMSQ)
            for (int64_t l = 0; l < nb; l++) ((double *)(intptr_t)o[OF_PTR])[b0 + l] = a[l];
    }
}

#ifndef SIZED_COPY_DECLARED
#define SIZED_COPY_DECLARED
/* The copy compiled for its sizes that an instruction runs at one lane (the table at the top of this file):
 * its kind and the indices of its sizes in lti_out_sized / lti_upd_sized [n - 1][w - 1] or rco_out_sized
 * [n_phi - 1]; SIZED_NONE for the general copy. */
enum { SIZED_NONE, SIZED_LTI_OUT, SIZED_LTI_UPD, SIZED_SUM_1_2, SIZED_RCO_OUT };
typedef struct {
    int kind;
    int64_t i, j;
} sized_t;

static inline int in_range(int64_t v, int64_t hi) { return v >= 1 && v <= hi; }

static inline sized_t sized_copy(int64_t op, const int64_t *x) {
    if (op == OP_LTI_OUT && x[LTI_OUT_NFT] == 0 && in_range(x[LTI_OUT_NX], LTI_SMALL_N) &&
        in_range(x[LTI_OUT_ROWS], LTI_SMALL_W))
        return (sized_t){SIZED_LTI_OUT, x[LTI_OUT_NX] - 1, x[LTI_OUT_ROWS] - 1};
    if (op == OP_LTI_UPD && in_range(x[LTI_UPD_NX], LTI_SMALL_N) && in_range(x[LTI_UPD_MT], LTI_SMALL_W))
        return (sized_t){SIZED_LTI_UPD, x[LTI_UPD_NX] - 1, x[LTI_UPD_MT] - 1};
    if (op == OP_SUM && x[SUM_WIDTH] == 1 && x[SUM_NIN] == 2) return (sized_t){SIZED_SUM_1_2, 0, 0};
    if (op == OP_RCO_OUT && x[E_NU] == 1 && in_range(x[E_NPHI], SMALL))
        return (sized_t){SIZED_RCO_OUT, x[E_NPHI] - 1, 0};
    return (sized_t){SIZED_NONE, 0, 0};
}
#endif

/* One chunk of members [b0, b0 + nb) for T steps: load, step, store. */
static void FN(chunk)(const run_t *r, double *S, int64_t b0, int64_t nb) {
    double *acc = SL(r->nslots);
    FN(load)(r->binds, r->nbind, S, b0, nb);
    FN(sums_load)(r->obs, r->nobs, acc, b0, nb);
    const int64_t *restrict code = r->code, *restrict ptrs = r->ptrs, *restrict ctr = r->counters;
    const double *restrict consts = r->consts;
    const int64_t ncode = r->ncode, T = r->T;
    /* Direct threading: each operation jumps to the next one's code (one indirect jump per instruction,
     * at a site of its own, which the branch predictor learns per operation). The program is decoded once
     * per call into (code, arguments) pairs, the last one the end of a step; at one lane, small LTI, sum and
     * estimator output operations go to the copy compiled for their sizes. */
    static const void *const labels[OP_N] = {
        [OP_NONE] = &&next, [OP_PLAYBACK] = &&playback, [OP_NOISE] = &&noise, [OP_LTI_OUT] = &&lti_out,
        [OP_LTI_UPD] = &&lti_upd, [OP_GAIN] = &&gain, [OP_SUM] = &&sum, [OP_COPY] = &&copy,
        [OP_FEATURE] = &&feature, [OP_RCO_OUT] = &&rco_out, [OP_RCO_UPD] = &&rco_upd, [OP_CALL] = &&call};
#if VL == 1 /* [n - 1][w - 1]: LTI_OUT (no feedthrough) and LTI_UPD of n states and w rows or input columns;
             * [n_phi - 1]: RCO_OUT of one u and n_phi regressors */
#define LTI_LABEL(op, n, w) &&op##_##n##_##w,
#define LTI_LABELS(op, n) {LTI_WIDTHS(LTI_LABEL, op, n)},
    static const void *const lti_out_sized[LTI_SMALL_N][LTI_SMALL_W] = {LTI_STATES(LTI_LABELS, lti_out)};
    static const void *const lti_upd_sized[LTI_SMALL_N][LTI_SMALL_W] = {LTI_STATES(LTI_LABELS, lti_upd)};
#define RCO_OUT_LABEL(c) &&rco_out_##c,
    static const void *const rco_out_sized[SMALL] = {SMALL_LIST(RCO_OUT_LABEL)};
#undef RCO_OUT_LABEL
#undef LTI_LABELS
#undef LTI_LABEL
#endif
    int64_t nops = 0;
    for (int64_t pc = 0; pc < ncode; pc += code[pc + 1]) nops++;
    struct {
        const void *to;
        const int64_t *args;
    } prog[nops + 1], *ip;
    for (int64_t pc = 0, i = 0; pc < ncode; pc += code[pc + 1], i++) {
        const int64_t op = code[pc], *x = code + pc + HDR;
        prog[i].to = labels[op];
        prog[i].args = x;
#if VL == 1
        sized_t z = sized_copy(op, x);
        if (z.kind == SIZED_LTI_OUT) prog[i].to = lti_out_sized[z.i][z.j];
        if (z.kind == SIZED_LTI_UPD) prog[i].to = lti_upd_sized[z.i][z.j];
        if (z.kind == SIZED_SUM_1_2) prog[i].to = &&sum_1_2;
        if (z.kind == SIZED_RCO_OUT) prog[i].to = rco_out_sized[z.i];
#endif
    }
    prog[nops].to = &&step_done;
    prog[nops].args = code;
    const int64_t *a;
    int64_t t;
#define NEXT()                                                                                               \
    do {                                                                                                     \
        const void *to_ = ip->to;                                                                            \
        a = ip->args;                                                                                        \
        ip++;                                                                                                \
        goto *to_;                                                                                           \
    } while (0)
    for (t = 0; t < T; t++) {
        ip = prog;
        NEXT();
    playback: FN(playback)(a, S, ptrs, ctr, t, b0, nb); NEXT();
    noise: FN(noise)(a, S, ctr, t, T); NEXT();
    lti_out: FN(lti_out_n)(a, S, a[LTI_OUT_NX], a[LTI_OUT_ROWS], a[LTI_OUT_NFT]); NEXT();
    lti_upd: FN(lti_upd_n)(a, S, a[LTI_UPD_NX], a[LTI_UPD_MT]); NEXT();
    gain: FN(gain)(a, S); NEXT();
    sum: FN(sum)(a, S); NEXT();
    copy: FN(copy)(a, S); NEXT();
    feature: FN(feature)(a, S, consts); NEXT();
    rco_out: FN(rco_out)(a, S); NEXT();
    rco_upd: FN(rco_upd)(a, S, ctr, t); NEXT();
    call: FN(call)(a, S, ptrs); NEXT();
#if VL == 1
#define LTI_CASE(op, n, w) op##_##n##_##w: FN(op##_c)(a, S, n, w); NEXT();
#define LTI_CASES(op, n) LTI_WIDTHS(LTI_CASE, op, n)
    LTI_STATES(LTI_CASES, lti_out)
    LTI_STATES(LTI_CASES, lti_upd)
#undef LTI_CASES
#undef LTI_CASE
    sum_1_2: FN(sum_n)(a, S, 1, 2); NEXT();
#define RCO_OUT1(c) rco_out_##c: FN(rco_out_n)(a, S, 1, c); NEXT();
    SMALL_LIST(RCO_OUT1)
#undef RCO_OUT1
#endif
    next: NEXT();
    step_done:
        if (r->nobs) FN(observe)(r->obs, r->nobs, S, acc, t, b0, nb, r->B);
    }
#undef NEXT
    FN(store)(r->binds, r->nbind, S, b0, nb);
    FN(sums_store)(r->obs, r->nobs, acc, b0, nb);
}

/* Lane arrays from the members' own rows and back: dst[i * VL + l] = src[l][i] for i < cnt (to_lanes), and
 * the reverse for the first nb members (from_lanes). Blocks of 4 members x 4 entries are transposed in
 * registers, so that both sides are read and written 4 entries at a time. */
static inline ALWAYS void FN(tr4)(v4d_t *a, v4d_t *b, v4d_t *c, v4d_t *d) {
    v4d_t t0 = SHUF4(*a, *b, 0, 4, 2, 6), t1 = SHUF4(*a, *b, 1, 5, 3, 7);
    v4d_t t2 = SHUF4(*c, *d, 0, 4, 2, 6), t3 = SHUF4(*c, *d, 1, 5, 3, 7);
    *a = SHUF4(t0, t2, 0, 1, 4, 5);
    *b = SHUF4(t1, t3, 0, 1, 4, 5);
    *c = SHUF4(t0, t2, 2, 3, 6, 7);
    *d = SHUF4(t1, t3, 2, 3, 6, 7);
}

static inline ALWAYS void FN(to_lanes)(double *restrict dst, double *const *src, int64_t cnt) {
    int64_t i = 0;
    if (VL % 4 == 0)
        for (; i + 3 < cnt; i += 4)
            for (int64_t l = 0; l + 3 < VL; l += 4) {
                v4d_t a = *(const v4d_t *)(src[l] + i), b = *(const v4d_t *)(src[l + 1] + i);
                v4d_t c = *(const v4d_t *)(src[l + 2] + i), d = *(const v4d_t *)(src[l + 3] + i);
                FN(tr4)(&a, &b, &c, &d);
                *(v4d_t *)(dst + i * VL + l) = a;
                *(v4d_t *)(dst + (i + 1) * VL + l) = b;
                *(v4d_t *)(dst + (i + 2) * VL + l) = c;
                *(v4d_t *)(dst + (i + 3) * VL + l) = d;
            }
    for (; i < cnt; i++)
        for (int64_t l = 0; l < VL; l++) dst[i * VL + l] = src[l][i];
}

static inline ALWAYS void FN(from_lanes)(double *const *dst, const double *restrict src, int64_t cnt, int64_t nb) {
    int64_t i = 0, full = VL % 4 == 0 ? nb / 4 * 4 : 0; /* members in whole blocks of 4 */
    if (full)
        for (; i + 3 < cnt; i += 4)
            for (int64_t l = 0; l < full; l += 4) {
                v4d_t a = *(const v4d_t *)(src + i * VL + l), b = *(const v4d_t *)(src + (i + 1) * VL + l);
                v4d_t c = *(const v4d_t *)(src + (i + 2) * VL + l), d = *(const v4d_t *)(src + (i + 3) * VL + l);
                FN(tr4)(&a, &b, &c, &d);
                *(v4d_t *)(dst[l] + i) = a;
                *(v4d_t *)(dst[l + 1] + i) = b;
                *(v4d_t *)(dst[l + 2] + i) = c;
                *(v4d_t *)(dst[l + 3] + i) = d;
            }
    for (int64_t l = 0; l < nb; l++) /* the entries after the blocks, and the members after the last block */
        for (int64_t j = l < full ? i : 0; j < cnt; j++) dst[l][j] = src[j * VL + l];
}

/* rls_update on (B, n) theta, (B, n, n) P, (B, n, nl) psi, (B, nl) z_r: VL members at a time through the same
 * FN(rls) as the estimator, each chunk copied into lane arrays and back (one pass over P, in 4 x 4 blocks). */
static void FN(rls_chunk)(const rls_t *q, double *S, int64_t b0, int64_t nb) {
    int64_t n = q->n, nl = q->nl;
    double *th = S, *P = AT(th, n), *psi = AT(P, n * n), *zr = AT(psi, n * nl), *lam = AT(zr, nl);
    double *rinv = AT(lam, 1), *act = AT(rinv, nl * nl), *ok = AT(act, 1), *scr = AT(ok, 1);
    double *rows[VL]; /* each lane's member's P (spare lanes: the last member's) */
    for (int64_t l = 0; l < VL; l++) rows[l] = q->P + (b0 + (l < nb ? l : nb - 1)) * n * n;
    FN(to_lanes)(P, rows, n * n);
    LANES {
        int64_t b = b0 + (l < nb ? l : nb - 1);
        for (int64_t i = 0; i < n; i++) th[i * VL + l] = q->theta[b * n + i];
        for (int64_t i = 0; i < n * nl; i++) psi[i * VL + l] = q->psi[b * n * nl + i];
        for (int64_t i = 0; i < nl; i++) zr[i * VL + l] = q->zr[b * nl + i];
        for (int64_t i = 0; i < nl * nl; i++) rinv[i * VL + l] = q->rinv[i];
        lam[l] = q->lam[b * q->lam_stride];
        act[l] = q->active ? q->active[b] != 0 : 1.0;
    }
    FN(rls)(n, nl, th, P, psi, zr, lam, q->lam_one, rinv, act, ok, scr);
    FN(from_lanes)(rows, P, n * n, nb);
    for (int64_t l = 0; l < nb; l++) {
        int64_t b = b0 + l;
        for (int64_t i = 0; i < n; i++) q->theta[b * n + i] = th[i * VL + l];
        q->ok[b] = ok[l] != 0.0;
    }
}

/* dst = P Q in lane arrays, P rows x inner, Q inner x cols, each entry summed over j in order */
static inline ALWAYS void FN(lane_matmul)(double *restrict dst, const double *P, const double *Q, int64_t rows,
                                          int64_t inner, int64_t cols, double *restrict acc) {
    for (int64_t r = 0; r < rows; r++)
        for (int64_t k = 0; k < cols; k++) {
            LANES acc[l] = 0.0;
            for (int64_t j = 0; j < inner; j++)
                LANES acc[l] += P[(r * inner + j) * VL + l] * Q[(j * cols + k) * VL + l];
            LANES dst[(r * cols + k) * VL + l] = acc[l];
        }
}

/* The Markov parameters of one linear system per member, VL members at a time (engine.c, lti_markov): beta_t =
 * -H_(d+t), t = 0..nu-1, H_0 = D0, H_i = C A^(i-1) B, X = A^(i-1) B carried N x m. All nu of the chunk are made
 * in the arena first, turned into one array per member, then written member by member into every target at the
 * member's row, each target in the order of its memory. With q->stable, a member's are written only where
 * ||A^(2^s)||_inf < 1 for some s <= 16 (so its spectral radius is below 1), and stable[b] says whether they
 * were. */
static void FN(markov_chunk)(const markov_t *q, double *S, int64_t b0, int64_t nb) {
    int64_t N = q->N, m = q->m, p = q->p, d = q->d, nu = q->nu, pm = p * m;
    double *a = S, *c = AT(a, N * N), *x = AT(c, p * N), *y = AT(x, N * m), *sq = AT(y, N * m);
    double *sq2 = AT(sq, N * N), *ok = AT(sq2, N * N), *acc = AT(ok, 1), *h = AT(acc, 1); /* h: nu x pm lanes */
    double *hm = AT(h, nu * pm);                                                             /* and by member */
    LANES {
        int64_t b = b0 + (l < nb ? l : nb - 1);
        for (int64_t i = 0; i < N * N; i++) a[i * VL + l] = q->A[b * N * N + i];
        for (int64_t i = 0; i < p * N; i++) c[i * VL + l] = q->C[b * p * N + i];
        for (int64_t i = 0; i < N * m; i++) x[i * VL + l] = q->Bm[b * N * m + i];
        ok[l] = q->stable ? 0.0 : 1.0;
    }
    if (q->stable) {
        memcpy(sq, a, sizeof(double) * (size_t)(N * N * VL));
        for (int s = 1; s <= 16; s++) {
            double *src = s & 1 ? sq : sq2, *dst = s & 1 ? sq2 : sq;
            FN(lane_matmul)(dst, src, src, N, N, N, acc);
            int all = 1;
            LANES {
                int below = 1; /* every row's absolute sum below 1; NaN and inf fail */
                for (int64_t r = 0; r < N; r++) {
                    double row = 0.0;
                    for (int64_t k = 0; k < N; k++) row += fabs(dst[(r * N + k) * VL + l]);
                    below &= row < 1.0;
                }
                ok[l] = ok[l] != 0.0 || below ? 1.0 : 0.0;
            }
            for (int64_t l = 0; l < nb; l++) all &= ok[l] != 0.0;
            if (all) break;
        }
        for (int64_t l = 0; l < nb; l++) q->stable[b0 + l] = ok[l] != 0.0;
    }
    for (int64_t i = d == 0 ? 0 : 1; i < d + nu; i++) {
        double *hi = h + (i - d) * pm * VL;
        if (i == 0) {
            LANES for (int64_t e = 0; e < pm; e++)
                hi[e * VL + l] = -q->D0[(b0 + (l < nb ? l : nb - 1)) * pm + e];
        } else if (i >= d) { /* beta = -H_i = -C X */
            FN(lane_matmul)(hi, c, x, p, N, m, acc);
            for (int64_t e = 0; e < pm; e++) LANES hi[e * VL + l] = -hi[e * VL + l];
        }
        if (i >= 1 && i + 1 < d + nu) { /* X <- A X */
            FN(lane_matmul)(y, a, x, N, N, m, acc);
            double *t = x;
            x = y;
            y = t;
        }
    }
    double *own[VL]; /* each member's nu x pm, one after the other */
    for (int64_t l = 0; l < VL; l++) own[l] = hm + l * nu * pm;
    FN(from_lanes)(own, h, nu * pm, nb);
    for (int64_t l = 0; l < nb; l++) {
        if (ok[l] == 0.0) continue;
        int64_t row = q->rows ? q->rows[b0 + l] : b0 + l;
        const double *restrict v = own[l];
        for (int64_t g = 0; g < q->ntargets; g++) {
            const int64_t st = q->t[g].st, se = q->t[g].se, copies = q->t[g].copies, coff = q->t[g].coff;
            double *restrict base = q->t[g].base + row * q->t[g].srow;
            if (st == pm && se == 1 && copies == 1) { /* as made: (nu, p, m) */
                memcpy(base, v, sizeof(double) * (size_t)(nu * pm));
            } else if (st == -1) { /* reversed in time, as the native program reads them: t = nu - 1 - j */
                for (int64_t e = 0; e < pm; e++)
                    for (int64_t cp = 0; cp < copies; cp++) {
                        double *restrict at = base - (nu - 1) + e * se + cp * coff;
                        for (int64_t j = 0; j < nu; j++) at[j] = v[(nu - 1 - j) * pm + e];
                    }
            } else if ((st < 0 ? -st : st) < (se < 0 ? -se : se)) { /* along t */
                for (int64_t e = 0; e < pm; e++)
                    for (int64_t cp = 0; cp < copies; cp++) {
                        double *restrict at = base + e * se + cp * coff;
                        for (int64_t t = 0; t < nu; t++) at[t * st] = v[t * pm + e];
                    }
            } else { /* along the entries */
                for (int64_t t = 0; t < nu; t++)
                    for (int64_t e = 0; e < pm; e++)
                        for (int64_t cp = 0; cp < copies; cp++) base[t * st + e * se + cp * coff] = v[t * pm + e];
            }
        }
    }
}

#undef LANES
#undef SL
#undef AT
