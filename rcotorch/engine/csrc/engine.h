/* rcotorch's native engine: the one definition of its op codes and record layouts.
 *
 * Each list below is an X-macro: the C code expands it into an enum, and the extension module exports the
 * names in order (rcotorch.engine._engine.OPS, LAYOUTS, TABLES, BIND_FIELDS, ...), from which rcotorch.engine.kernels builds
 * its constants and rcotorch.engine.lowering (Builder.emit) encodes an instruction from its fields by name. Adding a
 * field or an op here is the whole change of the layout on both sides.
 */
#ifndef RCOTORCH_ENGINE_H
#define RCOTORCH_ENGINE_H

#include <stdint.h>

/* Instructions: code[pc] = op, code[pc + 1] = the instruction's length in int64 (header included), then its
 * record: the fields of its layout (RCO_<LAYOUT>_FIELDS), then its tables (RCO_TABLES), each a number of
 * entries given by one of the fields, every entry a record of the table's own layout. Slot s of a chunk holds
 * one scalar for each of its VL lanes: S[s * VL + lane]. A parameter that all members share (SHARED = 1)
 * holds the same value in every lane, and operations read it once. Each op and the layout of its record: */
#define RCO_OPS(X)                                                                                           \
    X(PLAYBACK, PLAYBACK) X(NOISE, NOISE) X(LTI_OUT, LTI_OUT) X(LTI_UPD, LTI_UPD) X(GAIN, GAIN) X(SUM, SUM) \
    X(COPY, COPY) X(FEATURE, FEATURE) X(RCO_OUT, ESTIMATOR) X(RCO_UPD, ESTIMATOR) X(CALL, CALL)

/* PLAYBACK: out[c] = table[member * MSTRIDE + k * TSTRIDE + OFFSET + c] for c < WIDTH, k the step counter
 * COUNTER, the table at entry TABLE of the pointer table (a recording read where it is). */
#define RCO_PLAYBACK_FIELDS(X) X(TABLE) X(MSTRIDE) X(TSTRIDE) X(OFFSET) X(WIDTH) X(COUNTER) X(OUT)
/* NOISE: out = MEAN + STD N(KEY, k, c) for c < WIDTH (KEY the member's hashed (seed, member)), drawn in pairs
 * of steps, NOISE_AHEAD steps at a time, into BUFFER (NOISE_SLOTS * WIDTH slots). */
#define RCO_NOISE_FIELDS(X) X(WIDTH) X(COUNTER) X(KEY) X(STD) X(MEAN) X(OUT) X(BUFFER)
/* LTI_OUT: out = C x + sum_f D[:, COLUMN_f] u_f for ROWS rows of C (NX states, at STATE) and of D (MT input
 * columns), over the NFT feedthrough columns of the table FEEDTHROUGH (a column of D and its input slot). */
#define RCO_LTI_OUT_FIELDS(X) X(NX) X(ROWS) X(C) X(STATE) X(OUT) X(MT) X(D) X(SHARED) X(NFT)
#define RCO_LTI_OUT_FEEDTHROUGH_FIELDS(X) X(COLUMN) X(IN)
/* LTI_UPD: x = A x + B u, u the MT input columns of the table INPUTS (the slot of each); the new state goes
 * through SCRATCH (NX slots). */
#define RCO_LTI_UPD_FIELDS(X) X(NX) X(MT) X(A) X(B) X(STATE) X(SCRATCH) X(SHARED)
#define RCO_LTI_UPD_INPUT_FIELDS(X) X(IN)
/* GAIN: out = K in, K (ROWS x COLS). */
#define RCO_GAIN_FIELDS(X) X(ROWS) X(COLS) X(K) X(IN) X(OUT) X(SHARED)
/* SUM: out = sum_i SIGN_i IN_i over the NIN entries of TERMS, each port WIDTH wide. */
#define RCO_SUM_FIELDS(X) X(WIDTH) X(NIN) X(OUT)
#define RCO_SUM_TERM_FIELDS(X) X(IN) X(SIGN)
/* COPY: WIDTH slots from IN to OUT. */
#define RCO_COPY_FIELDS(X) X(WIDTH) X(IN) X(OUT)
/* FEATURE: the NTERMS basis terms (blocks/features.py) into consecutive slots from OUT: a term is WIDTH
 * channels of consts[COEF] * f_1(x_1) * ... over its NFACTORS factors (FACTORS). A factor: f(x) of kind KIND,
 * x = slot SRC + STRIDE * channel, POWER for POW, its parameters at consts[PARAM]. */
#define RCO_FEATURE_FIELDS(X) X(OUT) X(NTERMS)
#define RCO_FEATURE_TERM_FIELDS(X) X(WIDTH) X(COEF) X(NFACTORS)
#define RCO_FACTOR_FIELDS(X) X(KIND) X(SRC) X(STRIDE) X(POWER) X(PARAM)
#define RCO_FACTORS(X) X(POW) X(SIGN) X(ABS) X(SAT) X(DEADZONE) X(TANH) X(AFFINE)
/* A factor's parameters (blocks/features.py): SAT and DEADZONE (lo, hi), TANH (scale), AFFINE (gain, offset). */
enum { FP_LO = 0, FP_HI = 1 };
enum { FP_SCALE = 0 };
enum { FP_GAIN = 0, FP_OFFSET = 1 };
/* CALL: out = fn(in) for the chunk's lanes, fn the compiled function at entry FUNCTION of the pointer table,
 * void fn(const double *in, double *out, int64_t lanes) with in (NIN, lanes) at IN and out (NOUT, lanes) at
 * OUT (a user function, engine/compiled.py). */
#define RCO_CALL_FIELDS(X) X(NIN) X(IN) X(NOUT) X(OUT) X(FUNCTION)

/* The estimator's instructions (RCO_OUT, RCO_UPD): these fields, then the tables PHI_SRC (the slot of each of
 * the NPHI entries of phi), PARAM_OF (the parameter of each of the NENT entries of theta, -1: pinned) and REP
 * (an entry holding each of the NTHETA parameters). Slots: state (THETA .. PASTU), parameters (BETA: the
 * weights of the ring's rows, twice over; LAM, RINV, bounds), inputs (Z, VALID, CUR), the output (UOUT) and
 * scratch (SCRATCH, the estimator update's scratch slots: RCO_UPD_SCRATCH in engine.c). The robustness
 * options (estimator/rco.py): NL rows in the update (n_z, plus n_theta with the penalty on the parameters'
 * change), parameter slots RDQ (sqrt(r_delta)), NORM (1 / s^2 of normalized regressors, with RW: the cost's
 * weight R, n_z x n_z) and PMAX (the trace bound on P), each -1 when off. IDENT: 1 when each entry of theta is
 * its own parameter, in order (param_of[i] = i). HELD: 1 when the estimator is held (``hold``): the update then
 * only stores the window's row and moves the histories on. WMOD: 2^64 / W + 1 (rounded down; the bits of a
 * uint64), the multiplier of the ring's row k mod W (ring_row). */
#define RCO_ESTIMATOR_FIELDS(X)                                                                              \
    X(NU) X(NZ) X(NPHI) X(NTHETA) X(NENT) X(W) X(WMOD) X(NC) X(NC1) X(NSIG) X(LAM_ONE) X(COUNTER) X(SHARED) \
    X(THETA) X(P) X(WIN) X(PHI) X(UNOW) X(ZR) X(ALIVE) X(DIV) X(PAST) X(PASTU)                             \
    X(BETA) X(LAM) X(RINV) X(TLO) X(THI) X(ULO) X(UHI) X(Z) X(VALID) X(CUR) X(UOUT) X(SCRATCH)             \
    X(NL) X(RDQ) X(NORM) X(RW) X(PMAX) X(IDENT) X(HELD)
#define RCO_ESTIMATOR_PHI_FIELDS(X) X(SLOT)
#define RCO_ESTIMATOR_ENTRY_FIELDS(X) X(PARAM)
#define RCO_ESTIMATOR_PARAM_FIELDS(X) X(ENTRY)

/* Every record layout. */
#define RCO_LAYOUTS(X)                                                                                       \
    X(PLAYBACK) X(NOISE) X(LTI_OUT) X(LTI_OUT_FEEDTHROUGH) X(LTI_UPD) X(LTI_UPD_INPUT) X(GAIN) X(SUM)      \
    X(SUM_TERM) X(COPY) X(FEATURE) X(FEATURE_TERM) X(FACTOR) X(CALL) X(ESTIMATOR) X(ESTIMATOR_PHI)          \
    X(ESTIMATOR_ENTRY) X(ESTIMATOR_PARAM)

/* The tables after a record's fields, in order: the record's layout, the table's name, the field holding its
 * number of entries, the entries' layout. */
#define RCO_TABLES(X)                                                                                        \
    X(LTI_OUT, FEEDTHROUGH, NFT, LTI_OUT_FEEDTHROUGH)                                                        \
    X(LTI_UPD, INPUTS, MT, LTI_UPD_INPUT)                                                                    \
    X(SUM, TERMS, NIN, SUM_TERM)                                                                             \
    X(FEATURE, TERMS, NTERMS, FEATURE_TERM)                                                                  \
    X(FEATURE_TERM, FACTORS, NFACTORS, FACTOR)                                                               \
    X(ESTIMATOR, PHI_SRC, NPHI, ESTIMATOR_PHI)                                                               \
    X(ESTIMATOR, PARAM_OF, NENT, ESTIMATOR_ENTRY)                                                            \
    X(ESTIMATOR, REP, NTHETA, ESTIMATOR_PARAM)

/* A tensor bound to COUNT slots from SLOT. Element c of member b lives at ptr + (b * MSTRIDE + (c / INNER) *
 * OSTRIDE + c % INNER) elements. MODE, bits of BIND_MODE_BITS: copied into the slots before the steps
 * (BIND_LOAD), back after them (BIND_STORE), or both; with BIND_FIRST_LANE and MSTRIDE 0 (shared by the
 * members), loaded into the first lane alone (the operations read only that lane of it). Lowering writes four
 * combinations (rcotorch.engine.kernels.BindMode): LOAD 1 (a parameter), STORE 2 (a signal), LOAD_AND_STORE 3
 * (a state buffer) and LOAD_FIRST_LANE 5 (a parameter read in the first lane where shared). */
#define RCO_BIND_FIELDS(X) X(PTR) X(KIND) X(MSTRIDE) X(INNER) X(OSTRIDE) X(COUNT) X(SLOT) X(MODE)
#define RCO_BIND_MODE_BITS(X) X(BIND_LOAD, 1) X(BIND_STORE, 2) X(BIND_FIRST_LANE, 4)
#define RCO_KINDS(X) X(F64) X(BOOL) X(I64)

/* Observers, run after every step: SUMSQ adds sum_c x_c^2 to acc[b]; RECORD writes x into a time-major
 * buffer (steps, B, width) at every EVERY-th step (t + PHASE + 1 divisible by EVERY). */
#define RCO_OBS_FIELDS(X) X(KIND) X(SLOT) X(WIDTH) X(PTR) X(EVERY) X(PHASE)
#define RCO_OBSERVERS(X) X(SUMSQ) X(RECORD)

/* The enums: OP_<op>, and each field's index in its record, <PREFIX>_<FIELD>, <PREFIX>_N fields in all; the
 * prefix is the layout's name, but LTI_FT (LTI_OUT_FEEDTHROUGH), LTI_IN (LTI_UPD_INPUT), TERM (FEATURE_TERM),
 * FF (FACTOR) and E (ESTIMATOR). */
#define X_OP(name, layout) OP_##name,
enum { OP_NONE = 0, RCO_OPS(X_OP) OP_N };
#define X_PLAYBACK(f) PLAYBACK_##f,
enum { RCO_PLAYBACK_FIELDS(X_PLAYBACK) PLAYBACK_N };
#define X_NOISE(f) NOISE_##f,
enum { RCO_NOISE_FIELDS(X_NOISE) NOISE_N };
#define X_LTI_OUT(f) LTI_OUT_##f,
enum { RCO_LTI_OUT_FIELDS(X_LTI_OUT) LTI_OUT_N };
#define X_LTI_FT(f) LTI_FT_##f,
enum { RCO_LTI_OUT_FEEDTHROUGH_FIELDS(X_LTI_FT) LTI_FT_N };
#define X_LTI_UPD(f) LTI_UPD_##f,
enum { RCO_LTI_UPD_FIELDS(X_LTI_UPD) LTI_UPD_N };
#define X_LTI_IN(f) LTI_IN_##f,
enum { RCO_LTI_UPD_INPUT_FIELDS(X_LTI_IN) LTI_IN_N };
#define X_GAIN(f) GAIN_##f,
enum { RCO_GAIN_FIELDS(X_GAIN) GAIN_N };
#define X_SUM(f) SUM_##f,
enum { RCO_SUM_FIELDS(X_SUM) SUM_N };
#define X_SUM_TERM(f) SUM_TERM_##f,
enum { RCO_SUM_TERM_FIELDS(X_SUM_TERM) SUM_TERM_N };
#define X_COPY(f) COPY_##f,
enum { RCO_COPY_FIELDS(X_COPY) COPY_N };
#define X_FEATURE(f) FEATURE_##f,
enum { RCO_FEATURE_FIELDS(X_FEATURE) FEATURE_N };
#define X_TERM(f) TERM_##f,
enum { RCO_FEATURE_TERM_FIELDS(X_TERM) TERM_N };
#define X_FF(f) FF_##f,
enum { RCO_FACTOR_FIELDS(X_FF) FF_N };
#define X_FAC(name) FAC_##name,
enum { RCO_FACTORS(X_FAC) FAC_N };
#define X_CALL(f) CALL_##f,
enum { RCO_CALL_FIELDS(X_CALL) CALL_N };
#define X_E(f) E_##f,
enum { RCO_ESTIMATOR_FIELDS(X_E) E_N };
#define X_BF(name) BF_##name,
enum { RCO_BIND_FIELDS(X_BF) BF_N };
#define X_BIND_BIT(name, bit) name = bit,
enum { RCO_BIND_MODE_BITS(X_BIND_BIT) };
#define X_KIND(name) KIND_##name,
enum { RCO_KINDS(X_KIND) KIND_N };
#define X_OF(name) OF_##name,
enum { RCO_OBS_FIELDS(X_OF) OF_N };
#define X_OBS(name) OBS_##name,
enum { RCO_OBSERVERS(X_OBS) OBS_N };

/* The one-field tables are read as arrays of their field. */
_Static_assert(LTI_IN_N == 1, "LTI_UPD's INPUTS are read as an array of slots");
#define X_ONE_FIELD(f) +1
_Static_assert(0 RCO_ESTIMATOR_PHI_FIELDS(X_ONE_FIELD) == 1 && 0 RCO_ESTIMATOR_ENTRY_FIELDS(X_ONE_FIELD) == 1 &&
               0 RCO_ESTIMATOR_PARAM_FIELDS(X_ONE_FIELD) == 1, "the estimator's tables are read as arrays");

/* Instruction header: op and length. */
#define HDR 2

/* Noise is drawn for NOISE_AHEAD steps at a time (vectorized over pairs of steps and lanes) into a buffer of
 * NOISE_SLOTS slots a channel: NOISE_PAIRS pairs, the first starting at the even step at or before the first
 * step drawn. */
#define NOISE_AHEAD 64
#define NOISE_PAIRS (NOISE_AHEAD / 2 + 1)
#define NOISE_SLOTS (2 * NOISE_PAIRS)
_Static_assert(NOISE_AHEAD % 2 == 0, "the noise buffer holds whole pairs of steps");

#endif
