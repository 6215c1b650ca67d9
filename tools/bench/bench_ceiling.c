/* What an exact Richardson–Lucy iteration can cost at best on this machine, in double and in
 * single precision (docs/performance.md, the scikit-image comparison). Not part of the
 * library: a probe that bounds what any implementation of the library's scheme could reach.
 *
 *   bench_ceiling --size N [--threads T] [--reps R]
 *
 * One RL iteration of an N² image with a full-frame kernel, zero boundary, on the 2N-smooth
 * frame M², done the way svp_deconv_rl does it but with nothing else around it: per
 * convolution, copy the N image rows into the frame, r2c those N rows, zero the other rows of
 * the half spectrum, transform every column, multiply by a fixed transfer function, transform
 * the columns back, c2r only the N rows kept; then the pointwise RL steps (ratio, update).
 * FFTW_MEASURE plans, the best of R iterations, for double (fftw3) and float (fftw3f) with the
 * same code. Prints one JSON line: frame, threads, double_s, float_s, their ratio, and the
 * relative max difference of the two iterates after the timed iterations (what single
 * precision costs in accuracy on this input). */
#include "bench_common.h"
#include "core/internal.h" /* svp_fft_good_size: the library's own frame sizes */

#include <complex.h>
#include <fftw3.h>
#include <math.h>
#include <omp.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* The same probe for a real type R, its complex type C and FFTW prefix P. The transfer
 * function is a real, positive Moffat-like low-pass (β = 1.1, FWHM 6 px), so iterates stay
 * positive and finite; its exact shape does not change the time. */
/* _Pragma inside a macro is beyond clang-format: this block is laid out by hand */
/* clang-format off */
#define DEFINE_PROBE(NAME, R, C, P)                                                                \
    static int NAME(int n, int reps, const double *y_in, double *x_out, double *best)              \
    {                                                                                              \
        const int m = svp_fft_good_size(2 * n - 1), ncx = m / 2 + 1;                               \
        R *fr = P##alloc_real((size_t)m * m);                                                      \
        C *sp = P##alloc_complex((size_t)m * ncx);                                                 \
        R *otf = P##alloc_real((size_t)m * ncx);                                                   \
        R *x = P##alloc_real((size_t)n * n), *y = P##alloc_real((size_t)n * n);                    \
        R *t = P##alloc_real((size_t)n * n);                                                       \
        if (!fr || !sp || !otf || !x || !y || !t) return 0;                                        \
        P##plan rows_f = P##plan_many_dft_r2c(1, &m, n, fr, NULL, 1, m, sp, NULL, 1, ncx,          \
                                              FFTW_MEASURE);                                       \
        P##plan cols_f = P##plan_many_dft(1, &m, ncx, sp, NULL, ncx, 1, sp, NULL, ncx, 1,          \
                                          FFTW_FORWARD, FFTW_MEASURE);                             \
        P##plan cols_b = P##plan_many_dft(1, &m, ncx, sp, NULL, ncx, 1, sp, NULL, ncx, 1,          \
                                          FFTW_BACKWARD, FFTW_MEASURE);                            \
        P##plan rows_b = P##plan_many_dft_c2r(1, &m, n, sp, NULL, 1, ncx, fr, NULL, 1, m,          \
                                              FFTW_MEASURE);                                       \
        if (!rows_f || !cols_f || !cols_b || !rows_b) return 0;                                    \
        for (int j = 0; j < m; j++)                                                                \
            for (int i = 0; i < ncx; i++) {                                                        \
                const double fy = (j <= m / 2 ? j : m - j) / (double)m, fx = i / (double)m;        \
                const double f2 = fx * fx + fy * fy;                                               \
                otf[(size_t)j * ncx + i] = (R)(exp(-6.0 * sqrt(f2) * 3.0) / ((double)m * m));      \
            }                                                                                      \
        for (size_t i = 0; i < (size_t)n * n; i++) {                                               \
            y[i] = (R)y_in[i];                                                                     \
            x[i] = (R)0.5;                                                                         \
        }                                                                                          \
        *best = INFINITY;                                                                          \
        for (int rep = 0; rep < reps; rep++) {                                                     \
            const double t0 = bench_now();                                                         \
            for (int pass = 0; pass < 2; pass++) {                                                 \
                const R *src = pass == 0 ? x : t;                                                  \
                _Pragma("omp parallel for schedule(static)") for (int j = 0; j < n; j++)           \
                {                                                                                  \
                    memcpy(fr + (size_t)j * m, src + (size_t)j * n, (size_t)n * sizeof(R));        \
                    memset(fr + (size_t)j * m + n, 0, (size_t)(m - n) * sizeof(R));                \
                }                                                                                  \
                P##execute_dft_r2c(rows_f, fr, sp);                                                \
                _Pragma("omp parallel for schedule(static)") for (int j = n; j < m; j++)           \
                    memset(sp + (size_t)j * ncx, 0, (size_t)ncx * sizeof(C));                      \
                P##execute_dft(cols_f, sp, sp);                                                    \
                R *restrict s = (R *)sp;                                                           \
                const size_t ns = (size_t)m * ncx;                                                 \
                _Pragma("omp parallel for schedule(static)") for (size_t i = 0; i < ns; i++)       \
                {                                                                                  \
                    s[2 * i] *= otf[i];                                                            \
                    s[2 * i + 1] *= otf[i];                                                        \
                }                                                                                  \
                P##execute_dft(cols_b, sp, sp);                                                    \
                P##execute_dft_c2r(rows_b, sp, fr);                                                \
                _Pragma("omp parallel for schedule(static)") for (int j = 0; j < n; j++)           \
                {                                                                                  \
                    const R *row = fr + (size_t)j * m;                                             \
                    for (int i = 0; i < n; i++) {                                                  \
                        const size_t k = (size_t)j * n + i;                                        \
                        if (pass == 0) {                                                           \
                            const R h = row[i] > (R)1e-6 ? row[i] : (R)1e-6;                       \
                            t[k] = y[k] / h;                                                       \
                        } else {                                                                   \
                            x[k] *= row[i];                                                        \
                        }                                                                          \
                    }                                                                              \
                }                                                                                  \
            }                                                                                      \
            const double dt = bench_now() - t0;                                                    \
            if (dt < *best) *best = dt;                                                            \
        }                                                                                          \
        for (size_t i = 0; i < (size_t)n * n; i++) x_out[i] = (double)x[i];                        \
        P##destroy_plan(rows_f);                                                                   \
        P##destroy_plan(cols_f);                                                                   \
        P##destroy_plan(cols_b);                                                                   \
        P##destroy_plan(rows_b);                                                                   \
        P##free(fr);                                                                               \
        P##free(sp);                                                                               \
        P##free(otf);                                                                              \
        P##free(x);                                                                                \
        P##free(y);                                                                                \
        P##free(t);                                                                                \
        return m;                                                                                  \
    }

DEFINE_PROBE(probe_double, double, fftw_complex, fftw_)
DEFINE_PROBE(probe_float, float, fftwf_complex, fftwf_)
/* clang-format on */

int main(int argc, char **argv)
{
    int n = 1024, threads = 0, reps = 5;
    for (int i = 1; i + 1 < argc; i += 2) {
        if (!strcmp(argv[i], "--size"))
            n = atoi(argv[i + 1]);
        else if (!strcmp(argv[i], "--threads"))
            threads = atoi(argv[i + 1]);
        else if (!strcmp(argv[i], "--reps"))
            reps = atoi(argv[i + 1]);
        else {
            fprintf(stderr, "bench_ceiling: unknown option '%s'\n", argv[i]);
            return 2;
        }
    }
    if (n < 2 || reps < 1) {
        fprintf(stderr, "bench_ceiling: --size >= 2 and --reps >= 1 are needed\n");
        return 2;
    }
    if (threads < 1) threads = omp_get_max_threads();
    omp_set_num_threads(threads);
    if (!fftw_init_threads() || !fftwf_init_threads()) {
        printf("{\"error\": \"fftw threads\"}\n");
        return 1;
    }
    fftw_plan_with_nthreads(threads);
    fftwf_plan_with_nthreads(threads);
    double *y = malloc((size_t)n * n * sizeof *y), *xd = malloc((size_t)n * n * sizeof *xd);
    double *xf = malloc((size_t)n * n * sizeof *xf);
    if (!y || !xd || !xf) return 1;
    /* a smooth positive scene with a sharp-edged chessboard, like the RL benchmark's input */
    for (int j = 0; j < n; j++)
        for (int i = 0; i < n; i++) {
            const double u = (i - 0.5 * n) / (0.3 * n), v = (j - 0.5 * n) / (0.3 * n);
            const int cell = ((i * 8 / n) + (j * 8 / n)) % 3;
            y[(size_t)j * n + i] = exp(-0.5 * (u * u + v * v)) * (cell == 0   ? 0.1
                                                                  : cell == 1 ? 0.8
                                                                              : 1.0) +
                                   1e-3;
        }
    double t_double, t_float;
    const int m = probe_double(n, reps, y, xd, &t_double);
    if (!m || !probe_float(n, reps, y, xf, &t_float)) {
        printf("{\"error\": \"out of memory or no FFTW plan\"}\n");
        return 1;
    }
    double dmax = 0, xmax = 0;
    for (size_t i = 0; i < (size_t)n * n; i++) {
        dmax = fmax(dmax, fabs(xd[i] - xf[i]));
        xmax = fmax(xmax, fabs(xd[i]));
    }
    printf("{\"case\": \"ceiling\", \"size\": %d, \"frame\": [%d, %d], \"threads\": %d, "
           "\"reps\": %d, \"double_s\": %.6g, \"float_s\": %.6g, \"speedup\": %.4g, "
           "\"float_rel_diff\": %.3g, \"fftw\": \"%s\", \"maxrss_mb\": %.1f}\n",
           n, m, m, threads, reps, t_double, t_float, t_double / t_float, dmax / xmax, fftw_version,
           bench_maxrss_mb());
    free(y);
    free(xd);
    free(xf);
    return 0;
}
