/* The learners' fp32 master-weight work, one pass over the weights per call.

   Adam: torch 2.13's fused CPU Adam for float, operation for operation, including where
   its build fuses a multiply-add (m = fma(1 - beta1, g - m, m) as its lerp; v =
   fma((1 - beta2) g, g, beta2 v) in its vector loop, another fma in its scalar loop,
   see `vec`) and where it does not (everything else: this file is built with
   -ffp-contract=off and writes each fma out), reading a weight's gradient in
   bf16 or fp32, then writing the weight's bf16 copy.
   Soft update: torch's lerp for a weight below 0.5 (start + w * (end - start), as one
   fused multiply-add, as torch's vectorized CPU lerp computes it), then the target's
   bf16 copy. The bf16 copies round to nearest even as torch's float -> bfloat16
   conversion does (a NaN becomes the quiet NaN 0x7fc0).

   fp32 learner: Adam and then the soft update of the target in the same pass (the
   weight is in a register when its target reads it), the same arithmetic as torch's
   Adam followed by its lerp, no copies (an fp32 learner's products read the weights).

   tests/test_fused.py checks all three against torch bit for bit; shared/core/learners/fused.py
   compiles this file and says why it is there. */
#include <math.h>
#include <stdint.h>
#include <string.h>
#if defined(__x86_64__) || defined(__i386__)
#include <xmmintrin.h>
#define MACB_MXCSR 1
#endif

/* `vec` below: the width of torch's vector loop in its fused Adam (8 with torch 2.13 on
   the project's machines): the first n - n % vec elements of a tensor go through it, the
   rest through its scalar loop, which its build contracts differently (v = fma(v, beta2,
   (1 - beta2) g g)). fused.py finds it by comparing with torch when it loads this file. */

static inline uint16_t to_bf16(float f) {
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    if (isnan(f)) return 0x7fc0;
    return (uint16_t)((u + 0x7fffu + ((u >> 16) & 1u)) >> 16);
}

static inline float from_bf16(uint16_t h) {
    uint32_t u = (uint32_t)h << 16;
    float f;
    memcpy(&f, &u, sizeof f);
    return f;
}

/* Elements [lo, hi) of one tensor; `n` its size (which element is in torch's tail). */
#define ADAM_LOOP(LOAD)                                                                  \
    const int64_t body = n - n % a.vec;                                                  \
    for (int64_t i = lo; i < hi; i++) {                                                  \
        float gi = LOAD;                                                                 \
        float mi = fmaf(c1, gi - m[i], m[i]);                                            \
        float vi = i < body ? fmaf(c2 * gi, gi, v[i] * beta2) : fmaf(v[i], beta2, c2 * gi * gi); \
        m[i] = mi;                                                                       \
        v[i] = vi;                                                                       \
        float denom = sqrtf(vi) / bc2_sqrt + eps;                                        \
        float pi = p[i] + -step_size * mi / denom;                                       \
        p[i] = pi;                                                                       \
        low[i] = to_bf16(pi);                                                            \
    }

typedef struct {
    float beta1, beta2, c1, c2, step_size, bc2_sqrt, eps;
    int64_t vec;
} adam_args;

static void adam_f32(float *restrict p, const float *restrict g, float *restrict m,
                     float *restrict v, uint16_t *restrict low, int64_t n, int64_t lo,
                     int64_t hi, adam_args a) {
    const float beta2 = a.beta2, c1 = a.c1, c2 = a.c2, step_size = a.step_size;
    const float bc2_sqrt = a.bc2_sqrt, eps = a.eps;
    ADAM_LOOP(g[i])
}

static void adam_bf16(float *restrict p, const uint16_t *restrict g, float *restrict m,
                      float *restrict v, uint16_t *restrict low, int64_t n, int64_t lo,
                      int64_t hi, adam_args a) {
    const float beta2 = a.beta2, c1 = a.c1, c2 = a.c2, step_size = a.step_size;
    const float bc2_sqrt = a.bc2_sqrt, eps = a.eps;
    ADAM_LOOP(from_bf16(g[i]))
}

static void soft(float *restrict t, const float *restrict p, uint16_t *restrict low,
                 int64_t lo, int64_t hi, float tau) {
    for (int64_t i = lo; i < hi; i++) {
        float ti = fmaf(tau, p[i] - t[i], t[i]);
        t[i] = ti;
        low[i] = to_bf16(ti);
    }
}

/* Adam (adam_f32's arithmetic) then t <- fma(tau, p - t, t) (soft's), elements [lo, hi):
   two loops, torch's vector body and its scalar tail, each without a branch inside. */
static void adam_soft_f32(float *restrict p, const float *restrict g, float *restrict m,
                          float *restrict v, float *restrict t, int64_t n, int64_t lo,
                          int64_t hi, adam_args a, float tau) {
    const float beta2 = a.beta2, c1 = a.c1, c2 = a.c2, step_size = a.step_size;
    const float bc2_sqrt = a.bc2_sqrt, eps = a.eps;
    const int64_t body = n - n % a.vec;
    const int64_t mid = hi < body ? hi : body;
    for (int64_t i = lo; i < mid; i++) {
        float gi = g[i];
        float mi = fmaf(c1, gi - m[i], m[i]);
        float vi = fmaf(c2 * gi, gi, v[i] * beta2);
        m[i] = mi;
        v[i] = vi;
        float denom = sqrtf(vi) / bc2_sqrt + eps;
        float pi = p[i] + -step_size * mi / denom;
        p[i] = pi;
        t[i] = fmaf(tau, pi - t[i], t[i]);
    }
    for (int64_t i = lo > body ? lo : body; i < hi; i++) {
        float gi = g[i];
        float mi = fmaf(c1, gi - m[i], m[i]);
        float vi = fmaf(v[i], beta2, c2 * gi * gi);
        m[i] = mi;
        v[i] = vi;
        float denom = sqrtf(vi) / bc2_sqrt + eps;
        float pi = p[i] + -step_size * mi / denom;
        p[i] = pi;
        t[i] = fmaf(tau, pi - t[i], t[i]);
    }
}

/* The share [lo, hi) of a tensor of n elements that thread `part` of `parts` takes: cut
   at multiples of 16 (a cache line of floats; which of torch's loops an element is in
   is decided by its index in the whole tensor, not by the share). */
static void share(int64_t n, int part, int parts, int64_t *lo, int64_t *hi) {
    int64_t lines = (n + 15) / 16;
    *lo = lines * part / parts * 16;
    *hi = lines * (part + 1) / parts * 16;
    if (*lo > n) *lo = n;
    if (*hi > n) *hi = n;
}

/* Tensors smaller than this run in the calling thread alone. */
#define PARALLEL_MIN 4096

/* One call's tensors and scalars (those of Adam or of the soft update). */
typedef struct {
    float **p, **m, **v, **t;
    void **g;
    const int32_t *g_bf16;
    uint16_t **low;
    adam_args a;
    float tau;
} work;

/* Elements [lo, hi) of tensor k, of n elements. */
typedef void (*range_fn)(const work *w, int64_t k, int64_t n, int64_t lo, int64_t hi);

static void adam_range(const work *w, int64_t k, int64_t n, int64_t lo, int64_t hi) {
    if (w->g_bf16[k])
        adam_bf16(w->p[k], (const uint16_t *)w->g[k], w->m[k], w->v[k], w->low[k], n, lo, hi,
                  w->a);
    else
        adam_f32(w->p[k], (const float *)w->g[k], w->m[k], w->v[k], w->low[k], n, lo, hi, w->a);
}

static void soft_range(const work *w, int64_t k, int64_t n, int64_t lo, int64_t hi) {
    (void)n;
    soft(w->t[k], w->p[k], w->low[k], lo, hi, w->tau);
}

static void adam_soft_range(const work *w, int64_t k, int64_t n, int64_t lo, int64_t hi) {
    adam_soft_f32(w->p[k], (const float *)w->g[k], w->m[k], w->v[k], w->t[k], n, lo, hi, w->a,
                  w->tau);
}

/* `fn` over every element of `count` tensors; a large tensor split over `threads` OpenMP
   threads (the process's one OpenMP runtime, torch's: the same pool its ops use). */
static void each_tensor(const work *w, range_fn fn, int64_t count, const int64_t *numel,
                        int32_t threads) {
    for (int64_t k = 0; k < count; k++) {
        int64_t n = numel[k];
        int parts = n >= PARALLEL_MIN && threads > 1 ? threads : 1;
#pragma omp parallel for num_threads(parts) schedule(static, 1) if (parts > 1)
        for (int part = 0; part < parts; part++) {
            int64_t lo, hi;
            share(n, part, parts, &lo, &hi);
            fn(w, k, n, lo, hi);
        }
    }
}

/* One Adam step of `count` tensors: p, m, v fp32; g bf16 where g_bf16[k], else fp32;
   low[k] receives p's bf16 copy. The scalars are torch's, rounded to float as its
   kernel rounds them: beta1, beta2, c1 = 1 - beta1, c2 = 1 - beta2,
   step_size = lr / (1 - beta1^step), bc2_sqrt = sqrt(1 - beta2^step), eps. */
void macb_adam(int64_t count, float **p, void **g, const int32_t *g_bf16, float **m,
               float **v, uint16_t **low, const int64_t *numel, float beta1, float beta2,
               float c1, float c2, float step_size, float bc2_sqrt, float eps,
               int32_t vec, int32_t threads) {
    work w = {0};
    w.p = p;
    w.g = g;
    w.g_bf16 = g_bf16;
    w.m = m;
    w.v = v;
    w.low = low;
    w.a = (adam_args){beta1, beta2, c1, c2, step_size, bc2_sqrt, eps, vec > 0 ? vec : 1};
    each_tensor(&w, adam_range, count, numel, threads);
}

/* One Adam step of `count` fp32 tensors (macb_adam's scalars, fp32 gradients), each
   weight's target then soft-updated from it (tau < 0.5): t <- t + tau (p - t). */
void macb_adam_soft(int64_t count, float **p, void **g, float **m, float **v, float **t,
                    const int64_t *numel, float beta1, float beta2, float c1, float c2,
                    float step_size, float bc2_sqrt, float eps, int32_t vec, float tau,
                    int32_t threads) {
    work w = {0};
    w.p = p;
    w.g = g;
    w.m = m;
    w.v = v;
    w.t = t;
    w.tau = tau;
    w.a = (adam_args){beta1, beta2, c1, c2, step_size, bc2_sqrt, eps, vec > 0 ? vec : 1};
    each_tensor(&w, adam_soft_range, count, numel, threads);
}

/* t <- t + tau (p - t) for `count` tensors (tau < 0.5), then low[k] <- bf16(t). */
void macb_soft_update(int64_t count, float **t, float **p, uint16_t **low,
                      const int64_t *numel, float tau, int32_t threads) {
    work w = {0};
    w.t = t;
    w.p = p;
    w.low = low;
    w.tau = tau;
    each_tensor(&w, soft_range, count, numel, threads);
}

/* Subnormals read and made as zero (x86 DAZ and FTZ: MXCSR bits 6 and 15), or not, in
   every thread of an OpenMP team of `threads`: torch's pool, whose workers keep the mode
   they started with, which torch.set_flush_denormal (the calling thread's) cannot reach.
   Returns 0 where there is no MXCSR. */
int32_t macb_flush_denormals(int32_t on, int32_t threads) {
#ifdef MACB_MXCSR
#pragma omp parallel num_threads(threads)
    {
        unsigned int csr = _mm_getcsr();
        _mm_setcsr(on ? (csr | 0x8040u) : (csr & ~0x8040u));
    }
    return 1;
#else
    (void)on;
    (void)threads;
    return 0;
#endif
}
