/* rotlearn.geometry.eigen4's fused CPU kernels: the Jacobi eigensolver of symmetric 4x4 matrices
 * (all four eigenpairs, sorted, canonical sign) and its analytic backward, float32 and float64.
 *
 * Plain C11 with no dependency but libm and pthreads: it includes no torch header, so one build
 * serves every torch version; rotlearn.geometry.eigen4.cpu compiles it on first use (cached per
 * source, compiler and flags) and calls it through ctypes on the tensors' memory. The algorithm,
 * round counts and accuracy are those of the eager solver (rotlearn.geometry.eigen4.eager); the
 * exported functions take a range of the batch, and split it over `threads` POSIX threads.
 */

#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <string.h>

#define LANES 16 /* matrices per block: two AVX-512 / four AVX2 registers of float32 */
#define INLINE inline __attribute__((always_inline))

#if defined(ROTLEARN_TARGET_CLONES)
#define HOT __attribute__((target_clones("avx512f", "avx2", "default")))
#else
#define HOT
#endif

#define REAL float
#define UINT uint32_t
#define INT int32_t
#define MANT 23
#define BIAS 127
#define TINY 1.17549435e-38f
#define SQRT sqrtf
#define NAME(x) x##_f32
#include "sym4_body.h"
#undef REAL
#undef UINT
#undef INT
#undef MANT
#undef BIAS
#undef TINY
#undef SQRT
#undef NAME

#define REAL double
#define UINT uint64_t
#define INT int64_t
#define MANT 52
#define BIAS 1023
#define TINY 2.2250738585072014e-308
#define SQRT sqrt
#define NAME(x) x##_f64
#include "sym4_body.h"

/* One job per thread: a contiguous range of the batch. */
typedef struct {
    int dtype64, backward, rounds;
    const void *A, *gl, *gq, *L_in, *V_in;
    void *L, *q, *V, *G;
    int64_t begin, end, sb, sr, sc;
    double gap_eps;
} job_t;

static void run(const job_t *j) {
    if (j->backward) {
        if (j->dtype64)
            backward_range_f64(j->gl, j->gq, j->L_in, j->V_in, j->gap_eps, j->begin, j->end,
                               j->G);
        else
            backward_range_f32(j->gl, j->gq, j->L_in, j->V_in, (float)j->gap_eps, j->begin,
                               j->end, j->G);
    } else if (j->dtype64) {
        forward_range_f64(j->A, j->begin, j->end, j->sb, j->sr, j->sc, j->rounds, j->L, j->q,
                          j->V);
    } else {
        forward_range_f32(j->A, j->begin, j->end, j->sb, j->sr, j->sc, j->rounds, j->L, j->q,
                          j->V);
    }
}

static void *run_thread(void *arg) {
    run((const job_t *)arg);
    return NULL;
}

#define MAX_THREADS 256

/* Split [0, n) into `threads` ranges (multiples of LANES) and run them; this thread runs the
 * first. A thread that cannot be started leaves its range to this thread. */
static void run_parallel(job_t base, int64_t n, int threads) {
    if (threads < 1) threads = 1;
    if (threads > MAX_THREADS) threads = MAX_THREADS;
    int64_t per = (n + threads - 1) / threads;
    per = (per + LANES - 1) / LANES * LANES;
    job_t jobs[MAX_THREADS];
    pthread_t ids[MAX_THREADS];
    int started[MAX_THREADS];
    int count = 0;
    for (int64_t begin = 0; begin < n; begin += per) {
        jobs[count] = base;
        jobs[count].begin = begin;
        jobs[count].end = begin + per < n ? begin + per : n;
        ++count;
    }
    for (int t = 1; t < count; ++t)
        started[t] = pthread_create(&ids[t], NULL, run_thread, &jobs[t]) == 0;
    if (count > 0) run(&jobs[0]);
    for (int t = 1; t < count; ++t) {
        if (started[t])
            pthread_join(ids[t], NULL);
        else
            run(&jobs[t]);
    }
}

/* Forward: A (strides sb, sr, sc in elements) -> L (n, 4) ascending, q (n, 4) = column 0 of V
 * with canonical sign, V (n, 4, 4) row-major with the eigenvectors as columns. */
int rotlearn_sym4_forward(int dtype64, const void *A, int64_t n, int64_t sb, int64_t sr,
                          int64_t sc, int rounds, void *L, void *q, void *V, int threads) {
    job_t base = {dtype64, 0, rounds, A, NULL, NULL, NULL, NULL, L, q, V, NULL, 0, 0,
                  sb, sr, sc, 0.0};
    run_parallel(base, n, threads);
    return 0;
}

/* Backward: grad_A (n, 4, 4) from the gradients of L and q (either may be NULL) and the saved
 * L (n, 4), V (n, 4, 4) (all contiguous). */
int rotlearn_sym4_backward(int dtype64, const void *gl, const void *gq, const void *L,
                           const void *V, double gap_eps, int64_t n, void *G, int threads) {
    job_t base = {dtype64, 1, 0, NULL, gl, gq, L, V, NULL, NULL, NULL, G, 0, 0,
                  0, 0, 0, gap_eps};
    run_parallel(base, n, threads);
    return 0;
}

/* The version of this file's interface, checked by the loader. */
int rotlearn_sym4_abi(void) { return 1; }
