/* Benchmarks of the foundation issue (docs/performance.md, written by tools/bench/run).
 *
 *   svpsf_bench rl       --size N [--threads T] [--reps R] [--wisdom FILE]
 *       time per Richardson–Lucy iteration (svp_deconv_rl) with a full-frame Moffat PSF
 *       (support 0 = whole field of view, zero boundary), and the FFT bound measured in the
 *       same process with the operator's own cached plans: 2 × (one r2c + one c2r).
 *   svpsf_bench rl32     --size N ...  the same with single-precision transforms
 *       (svp_deconv_options.single_precision) against the float FFT bound (fftw3f, the same
 *       frame), plus the relative max difference to the double result after k2 iterations
 *   svpsf_bench skimage  --size N ...  the same for the scikit-image compatibility mode
 *       (svp_skimage_richardson_lucy with the (2N−1)² kernel)
 *   svpsf_bench inverse  --size N ...  T⁻¹ (R&W, 75 RL iterations) on an N² map vs the FFT
 *       bound of the transforms it needs, all at the operator's padded frame: 1 + 75 × 2 pairs
 *       for RL on Ĩ (Hᵀ1, then H and Hᵀ per iteration) plus the pairs the zero-boundary Wiener
 *       on B̃Ĩ used (1 + 3 per CG step: H, Hᵀ and the preconditioner, counted by the library)
 *   svpsf_bench export   --size N --out DIR   writes DIR/image.npy and DIR/psf.npy (float64),
 *       the very input and kernel of `rl`, for tools/bench/skimage_rl.py
 *
 * Each case prints one JSON line on stdout; times are medians over the repetitions, in
 * seconds; maxrss_mb is the process's peak resident memory (getrusage). Exit 3 when the
 * library reports the feature as not available yet (SVP_ERR_UNSUPPORTED). */
#include "bench_common.h"
#include "restore/restore_internal.h"

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

typedef struct bench_args {
    const char *mode;
    int size, threads, reps;
    const char *wisdom, *out;
    int kernel_full; /* export: 1 = the operator's (2N−1)² kernel, 0 = the compat (N−1)² one */
    int single;      /* rl32: single-precision transforms */
} bench_args;

static int fail(const char *what, svp_status st)
{
    printf("{\"error\": \"%s\", \"status\": %d, \"message\": \"%s\"}\n", what, (int)st,
           svp_last_error());
    fprintf(stderr, "svpsf_bench: %s: %s\n", what, svp_last_error());
    return st == SVP_ERR_UNSUPPORTED ? 3 : 1;
}

/* ---- inputs -------------------------------------------------------------------------------- */

/* The PSF of the benchmarks: a real set-up's PL PSF (Moffat β = 1.1, FWHM 610 nm at 100 nm per
 * pixel) whose tail reaches across the whole field of view. */
static svp_psf bench_psf(void)
{
    svp_psf p;
    svp_psf_defaults(&p);
    p.model = SVP_PSF_MOFFAT;
    p.fwhm = 6.1;
    p.beta = 1.1;
    p.support = 0; /* the whole field of view */
    return p;
}

static uint64_t rng_state = 0x9E3779B97F4A7C15ULL;
static double rng(void)
{
    rng_state ^= rng_state >> 12;
    rng_state ^= rng_state << 25;
    rng_state ^= rng_state >> 27;
    return (double)((rng_state * 0x2545F4914F6CDD1DULL) >> 11) * (1.0 / 9007199254740992.0);
}

/* The reference study's emission pattern: a Gaussian illumination spot (FWHM 60 % of the
 * frame) times a random chessboard of relative levels {0.1, 0.8, 1.0}. */
static svp_image *bench_pl(int n)
{
    svp_image *img = NULL;
    if (svp_image_new(n, n, &img) != SVP_OK) return NULL;
    const int squares = 16, side = (n + squares - 1) / squares;
    double levels[16 * 16];
    const double choice[3] = {0.1, 0.8, 1.0};
    for (int i = 0; i < squares * squares; i++) levels[i] = choice[(int)(3.0 * rng()) % 3];
    const double c = 0.5 * (n - 1), sigma = 0.6 * n / 2.3548200450309493;
    for (int y = 0; y < n; y++)
        for (int x = 0; x < n; x++) {
            double r2 = (x - c) * (x - c) + (y - c) * (y - c);
            img->data[(size_t)y * n + x] =
                exp(-0.5 * r2 / (sigma * sigma)) * levels[(y / side) * squares + x / side];
        }
    return img;
}

/* A signed field map (tesla): a strip-like step and a dipole-like bump. */
static svp_image *bench_field(int n)
{
    svp_image *img = NULL;
    if (svp_image_new(n, n, &img) != SVP_OK) return NULL;
    for (int y = 0; y < n; y++)
        for (int x = 0; x < n; x++) {
            double u = (x - 0.5 * n) / (0.05 * n), v = (y - 0.3 * n) / (0.04 * n);
            img->data[(size_t)y * n + x] =
                1e-4 * (atan(u + 4) - atan(u - 4)) + 3e-5 * v * exp(-0.5 * (u * u + v * v));
        }
    return img;
}

/* ---- the FFT bound ------------------------------------------------------------------------- */

typedef struct fft_times {
    double r2c, c2r; /* medians, seconds */
} fft_times;

/* One r2c and one c2r of the full ny x nx frame, timed separately; the input is refilled
 * (untimed) before each run so the unnormalised round trips never grow. The library's cached
 * plans: double the operator's own 2-D plan, single its float row-then-column plans (those of
 * svp_blur_set_single) over every row. */
static svp_status time_fft_precision(int ny, int nx, int reps, int single, fft_times *out)
{
    const svp_fft_plan *plan = NULL;
    const svp_fftf_rows *plan_f = NULL;
    if (single)
        SVP_CHECK(svp_fftf_rows_get(ny, nx, ny, &plan_f));
    else
        SVP_CHECK(svp_fft_plan_get(ny, nx, &plan));
    const size_t nr = (size_t)ny * nx, nc = (size_t)ny * (nx / 2 + 1);
    const size_t real = single ? sizeof(float) : sizeof(double);
    void *src = svp_alloc(nr * real), *re = svp_alloc(nr * real), *cx = svp_alloc(nc * 2 * real);
    double *t_r2c = malloc((size_t)reps * sizeof(double));
    double *t_c2r = malloc((size_t)reps * sizeof(double));
    svp_status st = SVP_OK;
    if (!src || !re || !cx || !t_r2c || !t_c2r) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d FFT benchmark", nx, ny);
        goto cleanup;
    }
    for (size_t i = 0; i < nr; i++) {
        if (single)
            ((float *)src)[i] = (float)rng();
        else
            ((double *)src)[i] = rng();
    }
    for (int r = 0; r < reps; r++) {
        memcpy(re, src, nr * real);
        double t0 = bench_now();
        if (single)
            svp_fftf_forward_rows(plan_f, re, cx);
        else
            svp_fft_forward(plan, re, cx);
        double t1 = bench_now();
        if (single)
            svp_fftf_inverse_rows_unscaled(plan_f, cx, re);
        else
            svp_fft_inverse_unscaled(plan, cx, re);
        double t2 = bench_now();
        t_r2c[r] = t1 - t0;
        t_c2r[r] = t2 - t1;
    }
    out->r2c = bench_median(t_r2c, reps);
    out->c2r = bench_median(t_c2r, reps);
cleanup:
    svp_free(src);
    svp_free(re);
    svp_free(cx);
    free(t_r2c);
    free(t_c2r);
    return st;
}

static svp_status time_fft(int ny, int nx, int reps, fft_times *out)
{
    return time_fft_precision(ny, nx, reps, 0, out);
}

/* ---- cases --------------------------------------------------------------------------------- */

static void setup_library(const bench_args *a)
{
    svp_set_threads(a->threads);
    svp_set_fft_effort(SVP_FFT_MEASURE);
    if (a->wisdom) (void)svp_fft_wisdom_load(a->wisdom); /* absent the first time */
}

static void finish_library(const bench_args *a)
{
    if (a->wisdom && svp_fft_wisdom_save(a->wisdom) != SVP_OK)
        fprintf(stderr, "svpsf_bench: %s\n", svp_last_error());
    svp_fft_cleanup();
}

/* Iteration counts for the per-iteration difference t(k2) − t(k1): setup (buffers, Hᵀ1, the
 * start) cancels. */
static void iteration_pair(int size, int *k1, int *k2)
{
    *k1 = 2;
    *k2 = size >= 2048 ? 6 : size >= 1024 ? 10 : 22;
}

/* The zero-padded frame of the scikit-image mode for a k x k kernel: size + reach, smoothed
 * (as svp_frame_init in zero mode). */
static int compat_frame(int n, int k)
{
    int reach = k - 1 < n - 1 ? k - 1 : n - 1;
    return svp_fft_good_size(n + reach);
}

typedef svp_status (*rl_runner)(void *ctx, int iterations, svp_image *out);

typedef struct rl_ctx {
    svp_blur *blur;
    const svp_image *data, *kernel;
    int single;
} rl_ctx;

static svp_status run_library_rl(void *p, int iterations, svp_image *out)
{
    rl_ctx *c = p;
    svp_deconv_options o;
    svp_deconv_defaults(&o);
    o.iterations = iterations;
    o.single_precision = c->single;
    return svp_deconv_rl(c->blur, c->data, &o, out);
}

static svp_status run_skimage_rl(void *p, int iterations, svp_image *out)
{
    rl_ctx *c = p;
    return svp_skimage_richardson_lucy(c->data, c->kernel, iterations, NULL, NULL, out);
}

static int bench_rl(const bench_args *a, int compat)
{
    const int n = a->size;
    setup_library(a);
    svp_psf psf = bench_psf();
    svp_blur *blur = NULL;
    svp_image *pl = bench_pl(n), *data = NULL, *out = NULL, *kernel = NULL;
    int rc = 0;
    svp_status st;
    double *per_iter = malloc((size_t)a->reps * sizeof(double));
    double *ratio = malloc((size_t)a->reps * sizeof(double));
    double *t_r2c = malloc((size_t)a->reps * sizeof(double));
    double *t_c2r = malloc((size_t)a->reps * sizeof(double));
    if (!pl || !per_iter || !ratio || !t_r2c || !t_c2r) return fail("allocation", SVP_ERR_NOMEM);
    double t0 = bench_now();
    if ((st = svp_blur_new(&psf, n, n, SVP_BOUNDARY_ZERO, &blur)) != SVP_OK) {
        rc = fail("svp_blur_new", st);
        goto cleanup;
    }
    double setup_s = bench_now() - t0;
    if ((st = svp_image_new(n, n, &data)) != SVP_OK || (st = svp_image_new(n, n, &out)) != SVP_OK ||
        (st = svp_blur_apply(blur, pl, data)) != SVP_OK) {
        rc = fail("blurring the input", st);
        goto cleanup;
    }
    /* the scikit-image mode takes the kernel itself: the same Moffat on the largest odd square
     * it accepts (the image's size at most), (N−1)² for even N */
    if (compat && (st = svp_psf_render(&psf, (n - 1) / 2, (n - 1) / 2, &kernel)) != SVP_OK) {
        rc = fail("svp_psf_render", st);
        goto cleanup;
    }
    rl_ctx ctx = {blur, data, kernel, a->single};
    rl_runner run = compat ? run_skimage_rl : run_library_rl;
    int k1, k2;
    iteration_pair(n, &k1, &k2);
    /* one untimed warm-up run (plans of the compat frame, page faults) */
    if ((st = run(&ctx, 1, out)) != SVP_OK) {
        rc = fail(compat ? "svp_skimage_richardson_lucy" : "svp_deconv_rl", st);
        goto cleanup;
    }
    int nx = blur->frame.nx, ny = blur->frame.ny;
    if (compat) nx = ny = compat_frame(n, kernel->width);
    /* Each repetition times the solver and then, right after, the FFT bound on the same plans,
     * so a change of machine load between repetitions moves both. */
    for (int r = 0; r < a->reps; r++) {
        double ta = bench_now();
        st = run(&ctx, k1, out);
        double tb = bench_now();
        if (st == SVP_OK) st = run(&ctx, k2, out);
        double tc = bench_now();
        if (st != SVP_OK) {
            rc = fail("Richardson–Lucy", st);
            goto cleanup;
        }
        per_iter[r] = ((tc - tb) - (tb - ta)) / (k2 - k1);
        fft_times ft;
        if ((st = time_fft_precision(ny, nx, 5, a->single, &ft)) != SVP_OK) {
            rc = fail("FFT timing", st);
            goto cleanup;
        }
        t_r2c[r] = ft.r2c;
        t_c2r[r] = ft.c2r;
        ratio[r] = per_iter[r] / (2.0 * (ft.r2c + ft.c2r));
    }
    size_t nonfinite = svp_image_count_nonfinite(out);
    /* single precision: what it costs in accuracy, the k2-iteration result against double's */
    double single_diff = 0;
    if (a->single) {
        svp_image *ref = NULL;
        rl_ctx dctx = ctx;
        dctx.single = 0;
        if ((st = svp_image_new(n, n, &ref)) != SVP_OK || (st = run(&dctx, k2, ref)) != SVP_OK) {
            svp_image_free(ref);
            rc = fail("double reference", st);
            goto cleanup;
        }
        double dmax = 0, rmax = 0;
        for (size_t i = 0; i < (size_t)n * n; i++) {
            dmax = fmax(dmax, fabs(out->data[i] - ref->data[i]));
            rmax = fmax(rmax, fabs(ref->data[i]));
        }
        single_diff = dmax / rmax;
        svp_image_free(ref);
    }
    fft_times ft = {bench_median(t_r2c, a->reps), bench_median(t_c2r, a->reps)};
    double iter_s = bench_median(per_iter, a->reps);
    double bound_s = 2.0 * (ft.r2c + ft.c2r);
    double ratio_s = bench_median(ratio, a->reps);
    printf("{\"case\": \"%s\", \"size\": %d, \"threads\": %d, \"reps\": %d, \"frame\": [%d, %d], "
           "\"kernel\": %d, "
           "\"k1\": %d, \"k2\": %d, \"iter_s\": %.6g, \"r2c_s\": %.6g, \"c2r_s\": %.6g, "
           "\"bound_s\": %.6g, \"ratio\": %.4g, \"setup_s\": %.4g, \"operator_mb\": %.1f, "
           "\"nonfinite\": %zu, \"single_rel_diff\": %.3g, \"maxrss_mb\": %.1f}\n",
           compat      ? "skimage_compat"
           : a->single ? "rl_single"
                       : "rl",
           n, svp_get_threads(), a->reps, nx, ny, kernel ? kernel->width : 2 * n - 1, k1, k2,
           iter_s, ft.r2c, ft.c2r, bound_s, ratio_s, setup_s, svp_blur_memory(blur) / 1048576.0,
           nonfinite, single_diff, bench_maxrss_mb());
cleanup:
    svp_blur_free(blur);
    svp_image_free(pl);
    svp_image_free(data);
    svp_image_free(out);
    svp_image_free(kernel);
    free(per_iter);
    free(ratio);
    free(t_r2c);
    free(t_c2r);
    finish_library(a);
    return rc;
}

static int bench_inverse(const bench_args *a)
{
    const int n = a->size, iterations = 75;
    setup_library(a);
    svp_psf psf = bench_psf();
    svp_blur *blur = NULL;
    svp_image *pl = bench_pl(n), *field = bench_field(n);
    svp_image *pl_app = NULL, *field_app = NULL, *pl_rec = NULL, *field_rec = NULL, *valid = NULL,
              *product = NULL;
    double *total = malloc((size_t)a->reps * sizeof(double));
    double *t_rl = malloc((size_t)a->reps * sizeof(double));
    double *t_wiener = malloc((size_t)a->reps * sizeof(double));
    double *t_bound = malloc((size_t)a->reps * sizeof(double));
    double *ratio = malloc((size_t)a->reps * sizeof(double));
    int rc = 0;
    svp_status st;
    if (!pl || !field || !total || !t_rl || !t_wiener || !t_bound || !ratio)
        return fail("allocation", SVP_ERR_NOMEM);
    if ((st = svp_blur_new(&psf, n, n, SVP_BOUNDARY_ZERO, &blur)) != SVP_OK) {
        rc = fail("svp_blur_new", st);
        goto cleanup;
    }
    if ((st = svp_image_new(n, n, &pl_app)) != SVP_OK ||
        (st = svp_image_new(n, n, &field_app)) != SVP_OK ||
        (st = svp_image_new(n, n, &pl_rec)) != SVP_OK ||
        (st = svp_image_new(n, n, &field_rec)) != SVP_OK ||
        (st = svp_image_new(n, n, &valid)) != SVP_OK ||
        (st = svp_image_new(n, n, &product)) != SVP_OK) {
        rc = fail("allocation", st);
        goto cleanup;
    }
    const svp_image *fields_in[1] = {field};
    svp_image *fields_app[1] = {field_app};
    if ((st = svp_forward_transform(blur, pl, fields_in, 1, pl_app, fields_app, NULL)) != SVP_OK) {
        rc = fail("svp_forward_transform", st);
        goto cleanup;
    }
    svp_correct_options o;
    svp_correct_defaults(&o);
    o.method = SVP_METHOD_RW;
    o.deconv.iterations = iterations;
    const svp_image *apparent[1] = {field_app};
    svp_image *recovered[1] = {field_rec};
    size_t n_missing = 0;
    /* untimed warm-up (pruned plans, page faults) */
    if ((st = svp_inverse_transform(blur, pl_app, apparent, 1, &o, pl_rec, recovered, valid,
                                    &n_missing)) != SVP_OK) {
        rc = fail("svp_inverse_transform", st);
        goto cleanup;
    }
    /* a sanity figure, not a test: the recovered field against the truth where the PL is lit
     * (above 10 % of its peak) */
    double err = 0, peak = 0, pl_max = svp_max(pl->data, (size_t)n * n);
    for (size_t i = 0; i < (size_t)n * n; i++) {
        if (fabs(field->data[i]) > peak) peak = fabs(field->data[i]);
        if (pl->data[i] > 0.1 * pl_max && fabs(field_rec->data[i] - field->data[i]) > err)
            err = fabs(field_rec->data[i] - field->data[i]);
    }
    /* the same with W on both deconvolutions, for its accuracy (untimed) */
    double err_w = 0;
    {
        svp_correct_options ow = o;
        ow.method = SVP_METHOD_W;
        if ((st = svp_inverse_transform(blur, pl_app, apparent, 1, &ow, pl_rec, recovered, valid,
                                        &n_missing)) != SVP_OK) {
            rc = fail("svp_inverse_transform (W)", st);
            goto cleanup;
        }
        for (size_t i = 0; i < (size_t)n * n; i++)
            if (pl->data[i] > 0.1 * pl_max && fabs(field_rec->data[i] - field->data[i]) > err_w)
                err_w = fabs(field_rec->data[i] - field->data[i]);
    }
    for (size_t i = 0; i < (size_t)n * n; i++)
        product->data[i] = field_app->data[i] * pl_app->data[i];
    fft_times last_ft = {0, 0};
    int wiener_pairs = 0, wiener_steps = 0;
    for (int r = 0; r < a->reps; r++) {
        double t0 = bench_now();
        st = svp_inverse_transform(blur, pl_app, apparent, 1, &o, pl_rec, recovered, valid,
                                   &n_missing);
        double t1 = bench_now();
        if (st != SVP_OK) {
            rc = fail("svp_inverse_transform", st);
            goto cleanup;
        }
        total[r] = t1 - t0;
        svp_restore_wiener_counts(blur, &wiener_steps, &wiener_pairs); /* of the Wiener in T⁻¹ */
        /* the two deconvolutions alone, for the breakdown (the Wiener on B̃Ĩ, as in T⁻¹) */
        if ((st = svp_deconv_rl(blur, pl_app, &o.deconv, pl_rec)) != SVP_OK) {
            rc = fail("svp_deconv_rl", st);
            goto cleanup;
        }
        double t2 = bench_now();
        if ((st = svp_deconv_wiener(blur, product, &o.deconv, field_rec)) != SVP_OK) {
            rc = fail("svp_deconv_wiener", st);
            goto cleanup;
        }
        double t3 = bench_now();
        t_rl[r] = t2 - t1;
        t_wiener[r] = t3 - t2;
        /* the bound right after, on the same cached plans: full (unpruned) r2c + c2r pairs at
         * the operator's frame, 1 + 2 per RL iteration plus the Wiener's count */
        fft_times ft;
        if ((st = time_fft(blur->frame.ny, blur->frame.nx, 5, &ft)) != SVP_OK) {
            rc = fail("FFT timing", st);
            goto cleanup;
        }
        t_bound[r] = (1.0 + iterations * 2.0 + wiener_pairs) * (ft.r2c + ft.c2r);
        ratio[r] = total[r] / t_bound[r];
        last_ft = ft;
    }
    fft_times ft = last_ft;
    double bound_rl = (1.0 + iterations * 2.0) * (ft.r2c + ft.c2r);
    double bound_w = wiener_pairs * (ft.r2c + ft.c2r);
    double total_s = bench_median(total, a->reps);
    printf("{\"case\": \"inverse_rw\", \"size\": %d, \"threads\": %d, \"reps\": %d, "
           "\"iterations\": %d, \"frame\": [%d, %d], \"total_s\": %.6g, \"rl_s\": %.6g, "
           "\"wiener_s\": %.6g, \"bound_s\": %.6g, \"bound_rl_s\": %.6g, \"bound_wiener_s\": "
           "%.6g, \"ratio\": %.4g, \"r2c_s\": %.6g, \"c2r_s\": %.6g, \"field_err_rel\": %.3g, "
           "\"field_err_rel_w\": %.3g, \"wiener_steps\": %d, \"wiener_pairs\": %d, "
           "\"maxrss_mb\": %.1f}\n",
           n, svp_get_threads(), a->reps, iterations, blur->frame.nx, blur->frame.ny, total_s,
           bench_median(t_rl, a->reps), bench_median(t_wiener, a->reps),
           bench_median(t_bound, a->reps), bound_rl, bound_w, bench_median(ratio, a->reps), ft.r2c,
           ft.c2r, peak > 0 ? err / peak : 0, peak > 0 ? err_w / peak : 0, wiener_steps,
           wiener_pairs, bench_maxrss_mb());
cleanup:
    svp_blur_free(blur);
    svp_image_free(pl);
    svp_image_free(field);
    svp_image_free(pl_app);
    svp_image_free(field_app);
    svp_image_free(pl_rec);
    svp_image_free(field_rec);
    svp_image_free(valid);
    svp_image_free(product);
    free(total);
    free(t_rl);
    free(t_wiener);
    free(t_bound);
    free(ratio);
    finish_library(a);
    return rc;
}

/* A float64 C-order .npy (format 1.0), written here so the export does not depend on io/. */
static int write_npy(const char *path, const svp_image *img)
{
    char header[128];
    int len = snprintf(header, sizeof header,
                       "{'descr': '<f8', 'fortran_order': False, 'shape': (%d, %d), }", img->height,
                       img->width);
    int total = 10 + len + 1, pad = (64 - total % 64) % 64;
    FILE *f = fopen(path, "wb");
    if (!f) return -1;
    unsigned short hlen = (unsigned short)(len + pad + 1);
    unsigned char pre[10] = {0x93,
                             'N',
                             'U',
                             'M',
                             'P',
                             'Y',
                             1,
                             0,
                             (unsigned char)(hlen & 0xff),
                             (unsigned char)(hlen >> 8)};
    int ok = fwrite(pre, 1, 10, f) == 10 && fwrite(header, 1, (size_t)len, f) == (size_t)len;
    for (int i = 0; i < pad && ok; i++) ok = fputc(' ', f) != EOF;
    ok = ok && fputc('\n', f) != EOF;
    size_t n = (size_t)img->width * img->height;
    ok = ok && fwrite(img->data, sizeof(double), n, f) == n; /* little-endian x86-64 */
    ok = (fclose(f) == 0) && ok;
    return ok ? 0 : -1;
}

static int bench_export(const bench_args *a)
{
    const int n = a->size;
    svp_set_fft_effort(SVP_FFT_ESTIMATE);
    svp_psf psf = bench_psf();
    svp_blur *blur = NULL;
    svp_image *pl = bench_pl(n), *data = NULL, *kernel = NULL;
    svp_status st;
    int rc = 0;
    char path[4096];
    if (!pl) return fail("allocation", SVP_ERR_NOMEM);
    if ((st = svp_blur_new(&psf, n, n, SVP_BOUNDARY_ZERO, &blur)) != SVP_OK ||
        (st = svp_image_new(n, n, &data)) != SVP_OK ||
        (st = svp_blur_apply(blur, pl, data)) != SVP_OK ||
        (st = svp_psf_render(&psf, a->kernel_full ? n - 1 : (n - 1) / 2,
                             a->kernel_full ? n - 1 : (n - 1) / 2, &kernel)) != SVP_OK) {
        rc = fail("export", st);
        goto cleanup;
    }
    snprintf(path, sizeof path, "%s/image.npy", a->out);
    if (write_npy(path, data) != 0) {
        fprintf(stderr, "svpsf_bench: cannot write %s\n", path);
        rc = 1;
        goto cleanup;
    }
    snprintf(path, sizeof path, "%s/psf.npy", a->out);
    if (write_npy(path, kernel) != 0) {
        fprintf(stderr, "svpsf_bench: cannot write %s\n", path);
        rc = 1;
        goto cleanup;
    }
    printf("{\"case\": \"export\", \"size\": %d, \"kernel\": [%d, %d]}\n", n, kernel->width,
           kernel->height);
cleanup:
    svp_blur_free(blur);
    svp_image_free(pl);
    svp_image_free(data);
    svp_image_free(kernel);
    svp_fft_cleanup();
    return rc;
}

/* ---- accelerated Richardson–Lucy: time to plain RL's error ---------------------------------- */

/* Noiseless data (the benchmark PL blurred by the benchmark PSF, zero boundary): plain RL's
 * relative L2 error after 100 iterations, then the fewest Biggs–Andrews iterations that reach it
 * (bisection on the count), and the median time of each. */
static double rel_l2(const svp_image *a, const svp_image *b)
{
    double e = 0, t = 0;
    for (size_t i = 0; i < (size_t)a->width * a->height; i++) {
        e += (a->data[i] - b->data[i]) * (a->data[i] - b->data[i]);
        t += b->data[i] * b->data[i];
    }
    return sqrt(e / t);
}

static int bench_rlaccel(const bench_args *a)
{
    const int n = a->size;
    svp_set_threads(a->threads);
    if (a->wisdom) (void)svp_fft_wisdom_load(a->wisdom);
    svp_psf psf = bench_psf();
    svp_blur *op = NULL;
    svp_image *truth = bench_pl(n), *y = NULL, *x = NULL;
    svp_status st = svp_blur_new(&psf, n, n, SVP_BOUNDARY_ZERO, &op);
    if (st != SVP_OK || !truth) return fail("operator", st);
    if ((st = svp_image_new(n, n, &y)) || (st = svp_image_new(n, n, &x))) return fail("image", st);
    if ((st = svp_blur_apply(op, truth, y))) return fail("apply", st);
    svp_deconv_options o;
    svp_deconv_defaults(&o);
    /* plain RL's error after 100 iterations, then the fewest accelerated iterations that reach
     * it (bisection); then the two timed in turn, repetition by repetition, so that a change of
     * the machine's load between them lands on both: the ratio is the median of the
     * per-repetition ratios (as for the RL iteration against its bound) */
    double *times = malloc((size_t)a->reps * 3 * sizeof(double));
    if (!times) return fail("times", SVP_ERR_NOMEM);
    double *times_acc = times + a->reps, *ratios = times + 2 * a->reps;
    const int plain_its = 100;
    o.iterations = plain_its;
    if ((st = svp_deconv_rl(op, y, &o, x))) return fail("rl", st);
    const double e_plain = rel_l2(x, truth);
    svp_deconv_options acc = o;
    acc.acceleration = SVP_RL_BIGGS_ANDREWS;
    int lo = 1, hi = plain_its; /* e(hi) <= e_plain is assumed, checked below */
    while (lo < hi) {
        const int mid = (lo + hi) / 2;
        acc.iterations = mid;
        if ((st = svp_deconv_rl(op, y, &acc, x))) return fail("rl accelerated", st);
        if (rel_l2(x, truth) <= e_plain)
            hi = mid;
        else
            lo = mid + 1;
    }
    acc.iterations = hi;
    for (int r = 0; r < a->reps; r++) {
        double t0 = bench_now();
        if ((st = svp_deconv_rl(op, y, &o, x))) return fail("rl", st);
        times[r] = bench_now() - t0;
        t0 = bench_now();
        if ((st = svp_deconv_rl(op, y, &acc, x))) return fail("rl accelerated", st);
        times_acc[r] = bench_now() - t0;
        ratios[r] = times_acc[r] / times[r];
    }
    const double e_acc = rel_l2(x, truth);
    const double t_plain = bench_median(times, a->reps), t_acc = bench_median(times_acc, a->reps);
    const double ratio = bench_median(ratios, a->reps);
    printf("{\"case\": \"rlaccel\", \"size\": %d, \"threads\": %d, \"reps\": %d, "
           "\"plain_iterations\": %d, \"plain_seconds\": %.6g, \"plain_error\": %.6g, "
           "\"accel_iterations\": %d, \"accel_seconds\": %.6g, \"accel_error\": %.6g, "
           "\"ratio\": %.6g, \"reached\": %d, \"maxrss_mb\": %.1f}\n",
           n, a->threads, a->reps, plain_its, t_plain, e_plain, hi, t_acc, e_acc, ratio,
           e_acc <= e_plain, bench_maxrss_mb());
    if (a->wisdom) (void)svp_fft_wisdom_save(a->wisdom);
    free(times);
    svp_image_free(truth);
    svp_image_free(y);
    svp_image_free(x);
    svp_blur_free(op);
    return 0;
}

static int usage(void)
{
    fprintf(stderr, "usage: svpsf_bench rl|rl32|skimage|inverse|export|rlaccel --size N [--threads T] "
                    "[--reps R] [--wisdom FILE] [--out DIR] [--kernel full|image]\n");
    return 2;
}

int main(int argc, char **argv)
{
    bench_args a = {NULL, 512, 1, 5, NULL, ".", 1, 0};
    if (argc < 2) return usage();
    a.mode = argv[1];
    for (int i = 2; i < argc; i++) {
        const char *opt = argv[i];
        if (i + 1 >= argc) return usage();
        const char *val = argv[++i];
        if (!strcmp(opt, "--size"))
            a.size = atoi(val);
        else if (!strcmp(opt, "--threads"))
            a.threads = atoi(val);
        else if (!strcmp(opt, "--reps"))
            a.reps = atoi(val);
        else if (!strcmp(opt, "--wisdom"))
            a.wisdom = val;
        else if (!strcmp(opt, "--out"))
            a.out = val;
        else if (!strcmp(opt, "--kernel") && (!strcmp(val, "full") || !strcmp(val, "image")))
            a.kernel_full = !strcmp(val, "full");
        else
            return usage();
    }
    if (a.size < 8 || a.threads < 1 || a.reps < 1) return usage();
    if (!strcmp(a.mode, "rl")) return bench_rl(&a, 0);
    if (!strcmp(a.mode, "rl32")) {
        a.single = 1;
        return bench_rl(&a, 0);
    }
    if (!strcmp(a.mode, "skimage")) return bench_rl(&a, 1);
    if (!strcmp(a.mode, "inverse")) return bench_inverse(&a);
    if (!strcmp(a.mode, "export")) return bench_export(&a);
    if (!strcmp(a.mode, "rlaccel")) return bench_rlaccel(&a);
    return usage();
}
