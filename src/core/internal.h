/* Library-internal helpers shared by the modules. Not installed. */
#ifndef SVP_INTERNAL_H
#define SVP_INTERNAL_H

#include "svpsf.h"

#include <complex.h>
#include <fftw3.h>
#include <stddef.h>

#define SVP_ALIGN 64
/* Loops and FFTs over fewer values than this run on one thread. */
#define SVP_PARALLEL_MIN 65536
/* The smallest Moffat beta accepted (the range fit-psf searches; docs/reliability.md): below it
 * the profile falls slower than 1/r and the FWHM conversion underflows as beta -> 0. */
#define SVP_PSF_BETA_MIN 0.5
/* The smallest pixel size in µm accepted by the readers (1 pm, docs/reliability.md). */
#define SVP_PIXEL_UM_MIN 1e-6

#if defined(__GNUC__)
#define SVP_PRINTF(a, b) __attribute__((format(printf, a, b)))
#else
#define SVP_PRINTF(a, b)
#endif

/* Records a message for svp_last_error() and returns status (so `return svp_fail(...)`). */
svp_status svp_fail(svp_status status, const char *fmt, ...) SVP_PRINTF(2, 3);
/* Prefixes the current error message: "context: previous message". Returns status. */
svp_status svp_fail_context(svp_status status, const char *fmt, ...) SVP_PRINTF(2, 3);
void svp_clear_error(void);

/* 64-byte aligned allocation (fftw_malloc); sizes in bytes. NULL on failure. */
void *svp_alloc(size_t bytes);
void *svp_calloc(size_t count, size_t size);
void svp_free(void *p);

#define SVP_CHECK(expr)                                                                        \
    do {                                                                                       \
        svp_status svp_check_status_ = (expr);                                                 \
        if (svp_check_status_ != SVP_OK) return svp_check_status_;                             \
    } while (0)

/* The longest error message kept (svp_last_error), terminator included. */
#define SVP_ERROR_LEN 1024

/* Deterministic sum (the same for every thread count): fixed blocks summed in parallel, the
 * block sums added in order. */
double svp_sum(const double *restrict x, size_t n);
/* Σ a b with svp_sum's order (prod: n scratch values, overwritten with a ⊙ b). */
double svp_dot(const double *a, const double *b, double *restrict prod, size_t n);
/* out[j] = Σ a[j] b[j] for j < m (at most SVP_DOTS_MAX) in one pass over the data, each with
 * svp_dot's order and so the same bits, without its scratch. */
#define SVP_DOTS_MAX 8
void svp_dots(const double *const *a, const double *const *b, int m, size_t n, double *out);
double svp_max(const double *restrict x, size_t n); /* of finite values; -inf when none */
double svp_max_abs(const double *restrict x, size_t n); /* largest finite |value|; 0 when none */
/* k with 2^k · max|x| in [1, 2) when the largest finite |value| lies outside [2^-bits, 2^bits],
 * else 0 (also for none): the power of two that brings data of extreme magnitude to unit size
 * and back exactly (linear steps commute with it bit for bit, barring overflow). */
int svp_unit_exponent(const double *restrict x, size_t n, int bits);
/* Fills the NaN pixels of v (w x h) with the mean of their non-NaN 3 x 3 neighbours, growing
 * inwards one ring per pass for clusters; what is left after max_passes passes (large holes)
 * gets `fallback`. A local fill adds far less spurious texture than a constant. */
svp_status svp_fill_nan(double *restrict v, int w, int h, int max_passes, double fallback);
/* Median of v[0..n), n >= 1 (sorts v in place; the mean of the middle two for even n). */
double svp_median(double *v, size_t n);
/* The k-th smallest of a[0..n) (0-based, n > 0, k < n) by quickselect; reorders a. */
double svp_select_kth(double *a, size_t n, size_t k);
double svp_min(const double *restrict x, size_t n);

/* ---- FFT engine ---------------------------------------------------------------------------
 * Plans for real 2-D transforms of ny x nx real values (nx/2+1 complex columns), made once
 * per (ny, nx, threads) and cached (guarded by a mutex). Execution uses FFTW's new-array API
 * on svp_alloc'd buffers and is thread-safe. */
typedef struct svp_fft_plan {
    int ny, nx;       /* real size */
    int ncx;          /* nx / 2 + 1 */
    fftw_plan r2c;    /* real (ny x nx) → complex (ny x ncx) */
    fftw_plan c2r;    /* complex → real (unnormalised, destroys its input) */
} svp_fft_plan;

svp_status svp_fft_plan_get(int ny, int nx, const svp_fft_plan **out);
/* Plans the calling thread gets from now on (svp_fft_plan_get, svp_fft_pruned_get,
 * svp_fftf_rows_get) use n threads instead of svp_get_threads() (n < 1: back to it). For work
 * split between concurrent threads, each transforming with fewer FFTW threads. */
void svp_fft_local_threads(int n);
/* The planning effort last set by svp_set_fft_effort (for summaries). */
svp_fft_effort svp_get_fft_effort(void);
void svp_fft_forward(const svp_fft_plan *plan, double *in, fftw_complex *out);
/* Inverse real FFT, scaled by 1/(ny nx) so forward followed by inverse is the identity.
 * Destroys `in`. */
void svp_fft_inverse(const svp_fft_plan *plan, fftw_complex *in, double *out);
/* The same without the 1/(ny nx) scaling (fold it into a spectral product instead). */
void svp_fft_inverse_unscaled(const svp_fft_plan *plan, fftw_complex *in, double *out);
/* Pruned real 2-D transforms for zero-padded frames whose input is non-zero only in its first
 * `rows` rows and whose output is needed only there: the r2c transforms those rows then every
 * column, the c2r every column then those rows (the other rows are skipped, not computed:
 * (ny − rows) / (2 ny) of the work, a quarter when rows = ny / 2). Cached like svp_fft_plan. */
typedef struct svp_fft_pruned {
    int ny, nx, ncx, rows;
    fftw_plan rows_r2c; /* rows x nx real → rows x ncx complex (row-major, dist nx / ncx) */
    fftw_plan cols_fwd; /* in place on ny x ncx complex, along y */
    fftw_plan cols_bwd;
    fftw_plan rows_c2r; /* rows x ncx complex → rows x nx real (destroys its input) */
} svp_fft_pruned;

/* rows = 0: the column plans only (rows_r2c and rows_c2r NULL), for callers that transform
 * the rows themselves (svp_fft_block); svp_fft_forward_pruned / _inverse need rows >= 1. */
svp_status svp_fft_pruned_get(int ny, int nx, int rows, const svp_fft_pruned **out);
/* out (ny x ncx) = r2c of in (ny x nx, only rows 0 .. rows − 1 are read: the rest is taken
 * as zero). */
void svp_fft_forward_pruned(const svp_fft_pruned *p, double *in, fftw_complex *out);
/* Rows 0 .. rows − 1 of the unnormalised c2r of in (destroyed) into out; out's other rows are
 * left as they were. */
void svp_fft_inverse_pruned_unscaled(const svp_fft_pruned *p, fftw_complex *in, double *out);
/* Row blocks: single-threaded r2c / c2r plans for SVP_FFT_BLOCK rows (and for 1 row, the
 * tail) of an nx-wide frame, to be run from the caller's own parallel loop over blocks so
 * that each block can be made (a weighted copy, an extension) or used (a crop, a weighted
 * sum) while it is in cache; with a frame's column plans (svp_fft_pruned.cols_*) they make
 * the same 2-D transform as svp_fft_forward without a frame-sized input or output buffer.
 * Real rows are bx = nx rounded up to even apart (so every row is 16-byte aligned when the
 * block is), complex rows ncx; the plans assume 16-byte alignment only, so any row of an
 * svp_alloc'd frame may be passed. Cached like svp_fft_plan. */
#define SVP_FFT_BLOCK 8
typedef struct svp_fft_block {
    int nx, ncx, bx;
    fftw_plan r2c, c2r;   /* SVP_FFT_BLOCK rows; c2r destroys its input */
    fftw_plan r2c1, c2r1; /* one row */
} svp_fft_block;

svp_status svp_fft_block_get(int nx, const svp_fft_block **out);
/* rows (1 .. SVP_FFT_BLOCK) packed rows: in → out. */
void svp_fft_block_forward(const svp_fft_block *p, int rows, double *in, fftw_complex *out);
void svp_fft_block_inverse(const svp_fft_block *p, int rows, fftw_complex *in, double *out);
/* Single precision (fftw3f), for the optional float transforms of Richardson–Lucy: the same
 * row-then-column decomposition for every frame (rows = ny for a full transform, fewer for a
 * zero-padded one), cached like the double plans. */
typedef struct svp_fftf_rows {
    int ny, nx, ncx, rows;
    fftwf_plan rows_r2c, cols_fwd, cols_bwd, rows_c2r;
} svp_fftf_rows;

svp_status svp_fftf_rows_get(int ny, int nx, int rows, const svp_fftf_rows **out);
/* out (ny x ncx) = r2c of in (only rows 0 .. rows − 1 read, the rest taken as zero). */
void svp_fftf_forward_rows(const svp_fftf_rows *p, float *in, fftwf_complex *out);
/* Rows 0 .. rows − 1 of the unnormalised c2r of in (destroyed) into out. */
void svp_fftf_inverse_rows_unscaled(const svp_fftf_rows *p, fftwf_complex *in, float *out);
/* Frees every cached plan (tests and tools at exit). */
void svp_fft_cleanup(void);

/* Progress helper: calls the callback if any; returns SVP_ERR_CANCELLED when it asks to stop. */
svp_status svp_report_progress(svp_progress_fn fn, void *user, double fraction);
/* One part of a longer job: a progress callback for the part (svp_progress_share_fn, user =
 * the share) forwards fraction f of the part as base + span · f of the whole to fn / user. */
typedef struct svp_progress_share {
    svp_progress_fn fn;
    void *user;
    double base, span;
} svp_progress_share;
int svp_progress_share_fn(void *share, double fraction);

/* Independent items 0 .. n − 1 (the frames of a cube) over `workers` threads (dynamic, one at
 * a time): fn(ctx, worker, item) on worker 0 .. workers − 1, each worker's FFT plans made
 * with one thread (svp_fft_local_threads(1)), so an item's result does not depend on the
 * thread count; after the first failure the items not begun are skipped. Progress base +
 * span · done / n from the calling thread only (a nonzero answer stops the items not begun:
 * SVP_ERR_CANCELLED), and base + span at the end. The failure of the lowest failing item, its
 * message included, is the call's. */
svp_status svp_items_parallel(int n, int workers, svp_status (*fn)(void *ctx, int worker, int item),
                              void *ctx, svp_progress_fn progress, void *progress_user, double base,
                              double span);

#endif
