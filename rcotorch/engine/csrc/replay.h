/* The replay's kernels (verdict/intervals.py, estimator/rco.py), included by engine.c once per instruction set
 * (ISA: base, avx2, avx512), their names suffixed by it (RFN); engine.c calls the copy the processor runs. */
#ifndef REPLAY_SIZES
#define REPLAY_SIZES
#define WS_LANES 64      /* window_sums: members side by side in a group ... */
#define WS_LANES_SMALL 8 /* ... or in a batch smaller than that */
#define WS_AHEAD 2       /* window_sums: the records this many steps ahead are prefetched */
#define WS_LANE _Pragma("omp simd") for (int64_t l = 0; l < NB; l++) /* a loop over a group's lanes */
#define MF_BLOCK 64 /* markov_filter: members a block */
#define MF_AHEAD 2  /* ... and its rows this many steps ahead prefetched */
#define RS_BLOCK 256 /* residual_sums: members a block */
#define RS_LANES 8  /* ... members side by side in its lagged sums */
#define RS_LAGS 6   /* ... and lags at a time (the six sums written out below) */
/* residual_sums' scratch, in doubles: (L + C) steps of nz + nw channels per member, blocks padded (as it lays them) */
/* residual_sums' members a block: RS_BLOCK, or where the batch is smaller, the batch rounded up to RS_LANES */
static inline int64_t rs_block(int64_t B) {
    return B >= RS_BLOCK ? RS_BLOCK : (B + RS_LANES - 1) / RS_LANES * RS_LANES;
}
static inline int64_t rs_scratch(int64_t B, int64_t nz, int64_t nw, int64_t L, int64_t C) {
    const int64_t NB = rs_block(B);
    return (B + NB - 1) / NB * (L + C) * ((nz + nw) * NB + RS_LANES);
}
/* RS_LANES doubles, loaded from anywhere a double may lie */
typedef double rs_vec __attribute__((vector_size(RS_LANES * sizeof(double)), aligned(sizeof(double))));
#endif

/* The replay's sums over a stretch of C steps (verdict/intervals.py, _WindowSums), per member b, from time-major
 * records: z (C, B, nz), the moved copies' z (C, B, nz, n), the regressors psi (C, B, nz, n) and d (C, B, nz) or
 * none. At a step t0 + t inside the member's measured steps [own_b, own_b + measured), with J = (moved - z) / eps_b
 * and, where norm is given (normalized regressors, norm_b = 1 / s^2 per member),
 * m = sqrt(1 + norm_b sum_{r,i} psi[r,i] (W psi)[r,i]) (else m = 1),
 * the row g = [J, z, d, psi / m, J / m, z / m] (K = 3 nz n + 3 nz) adds g g^T to gram[b] (K x K) in the blocks the
 * covariance reads (upper triangle: [J, z, d] x [J, z, d], psi / m x [psi / m, J / m], z / m x z / m), and the
 * score s = (psi / m)^T W (z / m) (n) enters the scores' long-run sums (_ScoreSums): sgram[b] += s s^T and, with
 * S the sum of the last L + 1 scores (ring[b], (L, n), the L before this step, oldest first, carried from stretch
 * to stretch), moving[b] += S S^T at every step; outside the member's measured steps g and s are 0.
 * Members in lanes of WS_LANES, each pair's sum a vector over the lanes,
 * loaded from gram before the stretch and stored after it: every member's sums are added in the order of its
 * steps, as one member at a time would add them. */
static int RFN(window_sums)(int64_t C, int64_t B, int64_t nz, int64_t n, int64_t t0, int64_t measured,
                             const double *z, const double *moved, const double *psi, const double *d,
                             const double *eps, const int64_t *own, const double *W, const double *norm, double *gram,
                             int64_t L, double *ring, double *sgram, double *moving, int nthreads) {
    const int64_t nj = nz * n, K = 3 * nj + 3 * nz;
    /* the pairs (a, c) of the blocks the covariance reads */
    int64_t *pa = malloc(sizeof(int64_t) * K * K * 2), np = 0;
    int fail = 0;
    if (!pa) return 1;
    int64_t *pc = pa + K * K;
    const int64_t top[3] = {nj + 2 * nz, 3 * nj + 2 * nz, K};
    for (int64_t a = 0; a < K; a++) {
        if (a >= 2 * nj + 2 * nz && a < 3 * nj + 2 * nz) continue; /* J / m: only beside psi */
        const int64_t end = a < top[0] ? top[0] : a < 2 * nj + 2 * nz ? top[1] : top[2];
        for (int64_t c = a; c < end; c++) {
            pa[np] = a;
            pc[np] = c;
            np++;
        }
    }
    /* lanes: WS_LANES, or in a smaller batch WS_LANES_SMALL, so that one member does not pay for a wide group */
    const int64_t NB = B >= WS_LANES ? WS_LANES : WS_LANES_SMALL;
    const int64_t nblocks = (B + NB - 1) / NB;
#ifdef _OPENMP
#pragma omp parallel num_threads(nthreads) if (nthreads > 1 && B >= 256) reduction(| : fail)
#endif
    {
        /* per lane l, each an array over the lanes: acc the pairs' sums, g the row, the scores' ring (L, n), this
         * step's scores sv, their moving sum Sv, the ring's sum Sr, the score sums sg and mv2; the step's records
         * as lanes (zl, mvl, psl, dl), eps (el), norm (nl), m, W z / m (wz), whether the step counts (in) and each
         * lane's first measured step (ol) */
        const int64_t nd = NB * (np + K + (L + 3) * n + 2 * n * n + 2 * nz + 2 * nj + nz + n + 2) + NB;
        double *acc = malloc(sizeof(double) * nd);
        int64_t *ol = malloc(sizeof(int64_t) * NB);
        fail |= !acc || !ol;
        if (acc && ol) {
            double *g = acc + np * NB, *rl = g + K * NB, *sv = rl + L * n * NB, *Sv = sv + n * NB, *Sr = Sv + n * NB;
            double *sg = Sr + n * NB, *mv2 = sg + n * n * NB, *wz = mv2 + n * n * NB, *zl = wz + nz * NB;
            double *mvl = zl + nz * NB, *psl = mvl + nj * NB, *dl = psl + nj * NB, *el = dl + nz * NB;
            double *nl = el + n * NB, *m = nl + NB, *in = m + NB;
#ifdef _OPENMP
#pragma omp for schedule(static)
#endif
            for (int64_t blk = 0; blk < nblocks; blk++) {
                const int64_t b0 = blk * NB, nb = b0 + NB < B ? NB : B - b0;
                for (int64_t p = 0; p < np; p++)
                    for (int64_t l = 0; l < NB; l++)
                        acc[p * NB + l] = l < nb ? gram[(b0 + l) * K * K + pa[p] * K + pc[p]] : 0.0;
                for (int64_t l = 0; l < NB; l++) {
                    const int64_t b = b0 + (l < nb ? l : nb - 1);
                    ol[l] = l < nb ? own[b] : INT64_MAX / 2; /* a lane past the batch never measures */
                    nl[l] = norm ? norm[b] : 0.0;
                    for (int64_t i = 0; i < n; i++) {
                        el[i * NB + l] = eps[b * n + i];
                        for (int64_t j = 0; j < L; j++)
                            rl[(j * n + i) * NB + l] = l < nb ? ring[((b0 + l) * L + j) * n + i] : 0.0;
                        for (int64_t j = 0; j < n; j++) {
                            sg[(i * n + j) * NB + l] = l < nb ? sgram[((b0 + l) * n + i) * n + j] : 0.0;
                            mv2[(i * n + j) * NB + l] = l < nb ? moving[((b0 + l) * n + i) * n + j] : 0.0;
                        }
                    }
                }
                int64_t head = 0; /* the ring's oldest entry */
                for (int64_t t = 0; t < C; t++) {
                    /* the ring's sum, oldest first, at the stretch's start and each time the ring comes round;
                     * between, carried on: less the entry that leaves, plus the one that enters */
                    if (head == 0)
                        for (int64_t i = 0; i < n; i++) {
                            double *restrict S = Sr + i * NB;
                            WS_LANE S[l] = 0.0;
                            for (int64_t j = 0; j < L; j++) {
                                const double *restrict r = rl + (j * n + i) * NB;
                                WS_LANE S[l] += r[l];
                            }
                        }
                    /* the step's records as lanes (a lane past the batch reads the last member's); the records
                     * of a later step asked for meanwhile (a step's rows lie far apart: no stride to guess) */
                    const int64_t row = t * B + b0;
                    if (t + WS_AHEAD < C) {
                        const int64_t ahead = row + WS_AHEAD * B;
                        for (int64_t c = 0; c < nb * nj; c += 8) {
                            __builtin_prefetch(moved + ahead * nj + c);
                            __builtin_prefetch(psi + ahead * nj + c);
                        }
                        for (int64_t c = 0; c < nb * nz; c += 8) {
                            __builtin_prefetch(z + ahead * nz + c);
                            if (d) __builtin_prefetch(d + ahead * nz + c);
                        }
                    }
                    WS_LANE {
                        const int64_t k = row + (l < nb ? l : nb - 1);
                        for (int64_t r = 0; r < nz; r++) {
                            zl[r * NB + l] = z[k * nz + r];
                            dl[r * NB + l] = d ? d[k * nz + r] : 0.0;
                        }
                        for (int64_t c = 0; c < nj; c++) {
                            mvl[c * NB + l] = moved[k * nj + c];
                            psl[c * NB + l] = psi[k * nj + c];
                        }
                    }
                    const int64_t now = t0 + t;
                    WS_LANE in[l] = (now - ol[l] >= 0) & (now - ol[l] < measured);
                    WS_LANE m[l] = 1.0;
                    if (norm) {
                        double q[NB];
                        WS_LANE q[l] = 0.0;
                        for (int64_t r = 0; r < nz; r++)
                            for (int64_t s2 = 0; s2 < nz; s2++)
                                for (int64_t i = 0; i < n; i++) {
                                    const double w = W[r * nz + s2];
                                    const double *restrict pr = psl + (r * n + i) * NB, *restrict ps2 = psl + (s2 * n + i) * NB;
                                    WS_LANE q[l] += pr[l] * w * ps2[l];
                                }
                        WS_LANE m[l] = sqrt(1.0 + q[l] * nl[l]);
                    }
                    /* x / m, written x where m is 1 (the same number, without a division); 0 where the step does
                     * not count */
#define WS_BY_M(x) (norm ? (x) / m[l] : (x))
#define WS_IN(x) (in[l] != 0.0 ? (x) : 0.0)
                    for (int64_t r = 0; r < nz; r++) {
                        for (int64_t i = 0; i < n; i++) {
                            const int64_t c = r * n + i;
                            double *restrict gj = g + c * NB, *restrict gp = g + (nj + 2 * nz + c) * NB;
                            double *restrict gm = g + (2 * nj + 2 * nz + c) * NB;
                            const double *restrict mv = mvl + c * NB, *restrict ps = psl + c * NB;
                            const double *restrict zr = zl + r * NB, *restrict e = el + i * NB;
                            WS_LANE {
                                const double j = (mv[l] - zr[l]) / e[l];
                                gj[l] = WS_IN(j);
                                gp[l] = WS_IN(WS_BY_M(ps[l]));
                                gm[l] = WS_IN(WS_BY_M(j));
                            }
                        }
                        double *restrict gz = g + (nj + r) * NB, *restrict gd = g + (nj + nz + r) * NB;
                        double *restrict gzm = g + (3 * nj + 2 * nz + r) * NB;
                        const double *restrict zr = zl + r * NB, *restrict dr = dl + r * NB;
                        WS_LANE {
                            gz[l] = WS_IN(zr[l]);
                            gd[l] = WS_IN(dr[l]);
                            gzm[l] = WS_IN(WS_BY_M(zr[l]));
                        }
                    }
                    for (int64_t r = 0; r < nz; r++) {
                        double *restrict o = wz + r * NB;
                        WS_LANE o[l] = 0.0;
                        for (int64_t s2 = 0; s2 < nz; s2++) {
                            const double w = W[r * nz + s2];
                            const double *restrict zs = zl + s2 * NB;
                            WS_LANE o[l] += w * WS_BY_M(zs[l]);
                        }
                    }
                    for (int64_t i = 0; i < n; i++) {
                        double *restrict o = sv + i * NB;
                        WS_LANE o[l] = 0.0;
                        for (int64_t r = 0; r < nz; r++) {
                            const double *restrict ps = psl + (r * n + i) * NB, *restrict w = wz + r * NB;
                            WS_LANE o[l] += WS_BY_M(ps[l]) * w[l];
                        }
                        WS_LANE o[l] = WS_IN(o[l]);
                    }
#undef WS_BY_M
#undef WS_IN
                    for (int64_t p = 0; p < np; p++) {
                        double *restrict o = acc + p * NB;
                        const double *restrict x = g + pa[p] * NB, *restrict y = g + pc[p] * NB;
                        WS_LANE o[l] += x[l] * y[l];
                    }
                    /* the scores: S the sum of the ring's L and this one; this one replaces the ring's oldest */
                    for (int64_t i = 0; i < n; i++) {
                        const double *restrict S = Sr + i * NB, *restrict s = sv + i * NB;
                        double *restrict o = Sv + i * NB;
                        WS_LANE o[l] = S[l] + s[l];
                    }
                    for (int64_t i = 0; i < n; i++)
                        for (int64_t j = 0; j < n; j++) {
                            double *restrict a1 = sg + (i * n + j) * NB, *restrict a2 = mv2 + (i * n + j) * NB;
                            const double *restrict si = sv + i * NB, *restrict sj = sv + j * NB;
                            const double *restrict Si = Sv + i * NB, *restrict Sj = Sv + j * NB;
                            WS_LANE {
                                a1[l] += si[l] * sj[l];
                                a2[l] += Si[l] * Sj[l];
                            }
                        }
                    if (L > 0) {
                        for (int64_t i = 0; i < n; i++) {
                            double *restrict r = rl + (head * n + i) * NB, *restrict S = Sr + i * NB;
                            const double *restrict s = sv + i * NB;
                            WS_LANE {
                                S[l] = S[l] - r[l] + s[l];
                                r[l] = s[l];
                            }
                        }
                        head = (head + 1) % L;
                    }
                }
                for (int64_t p = 0; p < np; p++)
                    for (int64_t l = 0; l < nb; l++) gram[(b0 + l) * K * K + pa[p] * K + pc[p]] = acc[p * NB + l];
                for (int64_t l = 0; l < nb; l++)
                    for (int64_t i = 0; i < n; i++) {
                        for (int64_t j = 0; j < L; j++)
                            ring[((b0 + l) * L + j) * n + i] = rl[((((head + j) % L) * n) + i) * NB + l];
                        for (int64_t j = 0; j < n; j++) {
                            sgram[((b0 + l) * n + i) * n + j] = sg[(i * n + j) * NB + l];
                            moving[((b0 + l) * n + i) * n + j] = mv2[(i * n + j) * NB + l];
                        }
                    }
            }
        }
        free(acc);
        free(ol);
    }
    free(pa);
    return fail;
}

/* The regressors of a stretch of steps filtered by the Markov parameters (estimator/rco.py, regressors_over):
 * psi[t, b, o, j] = sum_{i=0}^{nu-1} beta[b, i, o] phi[t + s0 - i, b, j] for t = 0 .. T - 1, from phi time-major
 * (rows, B, n_phi) with rows >= T + s0 and s0 >= nu - 1, beta (B, nu, n_out) or, shared (bshared), (1, nu, n_out);
 * psi (T, B, n_out, n_phi). The sum over i in increasing order, each term a product then a sum (not fused).
 * Members in blocks of MF_BLOCK: a step reads nu rows of the block's phi, each contiguous. The kernels here return 1
 * where memory for their scratch was refused (their results are then not valid), else 0. */
static int RFN(markov_filter)(int64_t T, int64_t B, int64_t n_phi, int64_t n_out, int64_t nu, int64_t s0,
                               const double *phi, const double *beta, int bshared, double *psi, int nthreads) {
    const int64_t nblocks = (B + MF_BLOCK - 1) / MF_BLOCK, row = B * n_phi;
    int fail = 0;
#ifdef _OPENMP
#pragma omp parallel num_threads(nthreads) if (nthreads > 1 && B >= 256) reduction(| : fail)
#endif
    {
        /* per block: the Markov parameters spread over the block's (member, regressor) pairs, and the sums */
        double *bx = malloc(sizeof(double) * (nu * n_out + 1) * MF_BLOCK * n_phi);
        fail |= !bx;
        if (bx) {
            double *acc = bx + nu * n_out * MF_BLOCK * n_phi;
#ifdef _OPENMP
#pragma omp for schedule(static)
#endif
            for (int64_t blk = 0; blk < nblocks; blk++) {
                const int64_t b0 = blk * MF_BLOCK, nb = b0 + MF_BLOCK < B ? MF_BLOCK : B - b0, nq = nb * n_phi;
                for (int64_t i = 0; i < nu; i++)
                    for (int64_t o = 0; o < n_out; o++)
                        for (int64_t l = 0; l < nb; l++)
                            for (int64_t j = 0; j < n_phi; j++)
                                bx[(i * n_out + o) * nq + l * n_phi + j] =
                                    beta[((bshared ? 0 : b0 + l) * nu + i) * n_out + o];
                for (int64_t t = 0; t < T; t++) {
                    /* the row a later step adds, asked for meanwhile (a step's rows lie far apart) */
                    if (t + MF_AHEAD < T)
                        for (int64_t q = 0; q < nq; q += 8) __builtin_prefetch(phi + (t + MF_AHEAD + s0) * row + b0 * n_phi + q);
                    for (int64_t o = 0; o < n_out; o++) {
                        double *restrict a = acc;
                        for (int64_t q = 0; q < nq; q++) a[q] = 0.0;
                        for (int64_t i = 0; i < nu; i++) {
                            const double *restrict x = phi + (t + s0 - i) * row + b0 * n_phi;
                            const double *restrict w = bx + (i * n_out + o) * nq;
                            for (int64_t q = 0; q < nq; q++) a[q] += w[q] * x[q];
                        }
                        double *out = psi + ((t * B + b0) * n_out + o) * n_phi;
                        if (n_out == 1)
                            memcpy(out, a, sizeof(double) * nq);
                        else
                            for (int64_t l = 0; l < nb; l++)
                                for (int64_t j = 0; j < n_phi; j++) out[l * n_out * n_phi + j] = a[l * n_phi + j];
                    }
                }
            }
            free(bx);
        }
    }
    return fail;
}


/* The residual checks' sums over a stretch of C steps (verdict/intervals.py, _ResidualSums), per member b, from
 * time-major records z and zi (the initial model's z) (C, B, nz), y (C, B, ny) and w (C, B, nw) or none. Each value
 * is multiplied by 1 inside the member's measured steps [own_b, own_b + measured) and by 0 outside them (v below),
 * and adds: to zlag (L + 1, B, nz) z_v(t) z_v(t - lag) per channel and to wlag (L + 1, B, nz, nw) z_v(t) w_v(t - lag)
 * per pair, for lag = 0 .. L, the L values before the stretch read from zring (B, L, nz) and wring (B, L, nw)
 * (oldest first), which the stretch's last L replace; and to sums (B, nz + 2 nw + ny + 3) the member's
 * [sum z_v, sum w_v, sum w_v^2, sum |z_v|^2, sum |zi_v|^2, sum y_v, sum |y_v|^2], step by step. The lagged sums
 * of a stretch are summed from 0 in the order of its steps, then added to zlag and wlag, as one member at a time
 * would. The records are read once, in the order they lie, into blocks of RS_BLOCK members (each block's steps
 * together); each group of RS_LAGS lags of RS_LANES members is then summed over the block's steps in registers.
 * Scratch: (L + C) (nz + nw) values per member (padded to a block). */
static int RFN(residual_sums)(int64_t C, int64_t B, int64_t nz, int64_t nw, int64_t ny, int64_t t0, int64_t measured,
                               const int64_t *own, int64_t L, const double *z, const double *zi, const double *y,
                               const double *w, double *zlag, double *wlag, double *zring, double *wring,
                               double *sums, double *scratch, int64_t scratch_len, int nthreads) {
    const int64_t NB = rs_block(B);
    const int64_t nblocks = (B + NB - 1) / NB, rows = L + C, ch = nz + nw, S = nz + 2 * nw + ny + 3;
    /* from one step of a channel to the next in a block, a cache line more than the channels take: rows a power of
     * two apart would share the cache's sets */
    const int64_t row = ch * NB + RS_LANES;
    /* (block, step, channel, lane): the caller's scratch where it is large enough (zero in the lanes past the
     * last member, which are read and never written), else one of its own */
    const int64_t need = rs_scratch(B, nz, nw, L, C);
    double *own_buf = scratch_len >= need ? NULL : calloc((size_t)need, sizeof(double));
    double *buf = own_buf ? own_buf : scratch;
    double *fl = malloc(sizeof(double) * B);
    if (!buf || !fl) {
        free(own_buf);
        free(fl);
        return 1;
    }
#define RS_AT(blk, r, c) (buf + ((blk) * rows + (r)) * row + (c) * NB)
    for (int64_t b = 0; b < B; b++)
        for (int64_t l = 0; l < L; l++) {
            for (int64_t i = 0; i < nz; i++) RS_AT(b / NB, l, i)[b % NB] = zring[(b * L + l) * nz + i];
            for (int64_t j = 0; j < nw; j++) RS_AT(b / NB, l, nz + j)[b % NB] = wring[(b * L + l) * nw + j];
        }
    for (int64_t t = 0; t < C; t++) {
        for (int64_t b = 0; b < B; b++) {
            const int64_t at = t0 + t - own[b];
            fl[b] = at >= 0 && at < measured ? 1.0 : 0.0;
        }
#ifdef _OPENMP
#pragma omp parallel for schedule(static) num_threads(nthreads) if (nthreads > 1 && B >= 1024)
#endif
        for (int64_t blk = 0; blk < nblocks; blk++) {
            const int64_t b0 = blk * NB, nb = b0 + NB < B ? NB : B - b0, e0 = t * B + b0;
            const double *f = fl + b0;
            double *sm = sums + b0 * S;
            for (int64_t i = 0; i < nz; i++) {
                double *restrict o = RS_AT(blk, L + t, i);
                for (int64_t q = 0; q < nb; q++) {
                    const double v = z[(e0 + q) * nz + i] * f[q], vi = zi[(e0 + q) * nz + i] * f[q];
                    o[q] = v;
                    sm[q * S + i] += v;
                    sm[q * S + nz + 2 * nw] += v * v;
                    sm[q * S + nz + 2 * nw + 1] += vi * vi;
                }
            }
            for (int64_t j = 0; j < nw; j++) {
                double *restrict o = RS_AT(blk, L + t, nz + j);
                for (int64_t q = 0; q < nb; q++) {
                    const double v = w[(e0 + q) * nw + j] * f[q];
                    o[q] = v;
                    sm[q * S + nz + j] += v;
                    sm[q * S + nz + nw + j] += v * v;
                }
            }
            for (int64_t k = 0; k < ny; k++)
                for (int64_t q = 0; q < nb; q++) {
                    const double v = y[(e0 + q) * ny + k] * f[q];
                    sm[q * S + nz + 2 * nw + 2 + k] += v;
                    sm[q * S + nz + 2 * nw + 2 + ny] += v * v;
                }
        }
    }
#ifdef _OPENMP
#pragma omp parallel for schedule(static) num_threads(nthreads) if (nthreads > 1 && B >= 256)
#endif
    for (int64_t blk = 0; blk < nblocks; blk++) {
        const int64_t b0 = blk * NB, nb = b0 + NB < B ? NB : B - b0;
        for (int64_t i = 0; i < nz; i++)
            for (int64_t j = -1; j < nw; j++) /* j = -1: z with itself, else z with w's channel j */
                for (int64_t g0 = 0; g0 <= L; g0 += RS_LAGS)
                    for (int64_t l0 = 0; l0 < nb; l0 += RS_LANES) {
                        const int64_t ng = g0 + RS_LAGS <= L + 1 ? RS_LAGS : L + 1 - g0;
                        double sum[RS_LAGS][RS_LANES] = {{0.0}};
                        const double *x = RS_AT(blk, L, i) + l0;
                        const double *p = RS_AT(blk, L - g0, j < 0 ? i : nz + j) + l0;
                        if (ng == RS_LAGS) { /* a whole group: the sums stay in registers, a vector each */
                            rs_vec s0 = {0.0}, s1 = {0.0}, s2 = {0.0}, s3 = {0.0}, s4 = {0.0}, s5 = {0.0};
                            for (int64_t t = 0; t < C; t++, x += row, p += row) {
                                const rs_vec xv = *(const rs_vec *)x;
                                s0 += xv * *(const rs_vec *)p;
                                s1 += xv * *(const rs_vec *)(p - row);
                                s2 += xv * *(const rs_vec *)(p - 2 * row);
                                s3 += xv * *(const rs_vec *)(p - 3 * row);
                                s4 += xv * *(const rs_vec *)(p - 4 * row);
                                s5 += xv * *(const rs_vec *)(p - 5 * row);
                            }
                            const rs_vec all[RS_LAGS] = {s0, s1, s2, s3, s4, s5};
                            for (int64_t g = 0; g < RS_LAGS; g++)
                                for (int64_t v = 0; v < RS_LANES; v++) sum[g][v] = all[g][v];
                        } else {
                            rs_vec part[RS_LAGS] = {{0.0}};
                            for (int64_t t = 0; t < C; t++, x += row, p += row) {
                                const rs_vec xv = *(const rs_vec *)x;
                                for (int64_t g = 0; g < ng; g++) part[g] += xv * *(const rs_vec *)(p - g * row);
                            }
                            for (int64_t g = 0; g < ng; g++)
                                for (int64_t v = 0; v < RS_LANES; v++) sum[g][v] = part[g][v];
                        }
                        for (int64_t g = 0; g < ng; g++)
                            for (int64_t v = 0; v < RS_LANES && l0 + v < nb; v++) {
                                const int64_t b = b0 + l0 + v;
                                if (j < 0)
                                    zlag[((g0 + g) * B + b) * nz + i] += sum[g][v];
                                else
                                    wlag[(((g0 + g) * B + b) * nz + i) * nw + j] += sum[g][v];
                            }
                    }
        for (int64_t q = 0; q < nb; q++)
            for (int64_t l = 0; l < L; l++) {
                const int64_t b = b0 + q;
                for (int64_t i = 0; i < nz; i++) zring[(b * L + l) * nz + i] = RS_AT(blk, C + l, i)[q];
                for (int64_t j = 0; j < nw; j++) wring[(b * L + l) * nw + j] = RS_AT(blk, C + l, nz + j)[q];
            }
    }
#undef RS_AT
    free(own_buf);
    free(fl);
    return 0;
}
