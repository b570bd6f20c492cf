/* rcotorch's native engine: the one definition of its op codes and record layouts.
 *
 * Each list below is an X-macro: the C code expands it into an enum, and the extension module exports the
 * names in order (rcotorch._engine.OPS, BIND_FIELDS, ...), from which rcotorch.kernels builds its
 * constants. Adding a field or an op here is the whole change of the layout on both sides.
 */
#ifndef RCOTORCH_ENGINE_H
#define RCOTORCH_ENGINE_H

#include <stdint.h>

/* Instructions: code[pc] = op, code[pc + 1] = the instruction's length in int64 (header included), then its
 * arguments. Slot s of a chunk holds one scalar for each of its VL lanes: S[s * VL + lane]. A parameter that
 * all members share ("shared" = 1) holds the same value in every lane, and operations read it once. */
#define RCO_OPS(X)                                                                                           \
    X(PLAYBACK)  /* ptr, member stride, time stride, offset, width, counter, out                          */ \
    X(NOISE)     /* width, counter, stream key, std, mean, out, buffer: mean + std N(seed, member, k, c)  */ \
    X(LTI_OUT)   /* n, rows, C, x, out, total inputs, D, shared, nft, [column, in] * nft (feedthrough)      */ \
    X(LTI_UPD)   /* n, total inputs mt, A, B, x, scratch, shared, in * mt (the slot of each input column)  */ \
    X(GAIN)      /* rows, cols, K, in, out, shared                                                         */ \
    X(SUM)       /* width, nin, out, [in, sign] * nin                                                      */ \
    X(COPY)      /* width, in, out                                                                         */ \
    X(FEATURE)   /* out, nterms, then per term: width, coefficient, nfactors, [FACTOR_FIELDS] * nfactors   */ \
    X(RCO_OUT)   /* RCO_FIELDS, then the variable tables (see below)                                       */ \
    X(RCO_UPD)                                                                                               \
    X(CALL)      /* nin, in, nout, out, fn: out = fn(in) for the chunk's lanes, fn a compiled function's     \
                  * address in the pointer table, void fn(const double *in, double *out, int64_t lanes)    \
                  * with in (nin, lanes) and out (nout, lanes) (a user function, compiled.py)             */

/* One factor of a basis feature: f(x), x = slot src + stride * channel. */
#define RCO_FACTOR_FIELDS(X) X(KIND) X(SRC) X(STRIDE) X(POWER) X(PARAM)
#define RCO_FACTORS(X) X(POW) X(SIGN) X(ABS) X(SAT) X(DEADZONE) X(TANH) X(AFFINE)

/* The estimator's instruction: these fields, then phi_src[NPHI] (the slot of each entry of phi),
 * param_of[NENT] (the parameter of each entry of theta, -1: pinned) and rep[NTHETA] (an entry holding each
 * parameter). Slots: state (THETA .. PASTU), parameters (BETA: the weights of the ring's rows, twice over;
 * LAM, RINV, bounds), inputs (Z, VALID, CUR), the output (UOUT) and scratch (SCRATCH, RCO_SCRATCH slots, see
 * rco_scratch in lanes.h). The robustness options (estimator.py): NL rows in the update (n_z, plus n_theta
 * with the penalty on the parameters' change), parameter slots RDQ (sqrt(r_delta)), NORM (1 / s^2 of
 * normalized regressors, with RW: the cost's weight R, n_z x n_z) and PMAX (the trace bound on P), each -1
 * when off. IDENT: 1 when each entry of theta is its own parameter, in order (param_of[i] = i). */
#define RCO_FIELDS(X)                                                                                        \
    X(NU) X(NZ) X(NPHI) X(NTHETA) X(NENT) X(W) X(NC) X(NC1) X(NSIG) X(LAM_ONE) X(COUNTER) X(SHARED) \
    X(THETA) X(P) X(WIN) X(PHI) X(UNOW) X(ZR) X(ALIVE) X(DIV) X(PAST) X(PASTU)                             \
    X(BETA) X(LAM) X(RINV) X(TLO) X(THI) X(ULO) X(UHI) X(Z) X(VALID) X(CUR) X(UOUT) X(SCRATCH)                 \
    X(NL) X(RDQ) X(NORM) X(RW) X(PMAX) X(IDENT)

/* A tensor copied into slots before the steps (mode 1), back after them (mode 2), or both (3).
 * Element c of member b lives at ptr + (b * MSTRIDE + (c / INNER) * OSTRIDE + c % INNER) elements. */
#define RCO_BIND_FIELDS(X) X(PTR) X(KIND) X(MSTRIDE) X(INNER) X(OSTRIDE) X(COUNT) X(SLOT) X(MODE)
#define RCO_KINDS(X) X(F64) X(BOOL) X(I64)

/* Observers, run after every step: SUMSQ adds sum_c x_c^2 to acc[b]; RECORD writes x into a time-major
 * buffer (steps, B, width) at every EVERY-th step (t + PHASE + 1 divisible by EVERY). */
#define RCO_OBS_FIELDS(X) X(KIND) X(SLOT) X(WIDTH) X(PTR) X(EVERY) X(PHASE)
#define RCO_OBSERVERS(X) X(SUMSQ) X(RECORD)

#define X_OP(name) OP_##name,
#define X_FAC(name) FAC_##name,
#define X_FF(name) FF_##name,
#define X_E(name) E_##name,
#define X_BF(name) BF_##name,
#define X_KIND(name) KIND_##name,
#define X_OF(name) OF_##name,
#define X_OBS(name) OBS_##name,

enum { OP_NONE = 0, RCO_OPS(X_OP) OP_N };
enum { RCO_FACTORS(X_FAC) FAC_N };
enum { RCO_FACTOR_FIELDS(X_FF) FF_N };
enum { RCO_FIELDS(X_E) E_N };
enum { RCO_BIND_FIELDS(X_BF) BF_N };
enum { RCO_KINDS(X_KIND) KIND_N };
enum { RCO_OBS_FIELDS(X_OF) OF_N };
enum { RCO_OBSERVERS(X_OBS) OBS_N };

/* Instruction header: op and length. */
#define HDR 2

/* Noise is drawn for NOISE_AHEAD steps at a time (vectorized over steps and lanes) into a buffer of
 * NOISE_AHEAD * width slots. */
#define NOISE_AHEAD 32

#endif
