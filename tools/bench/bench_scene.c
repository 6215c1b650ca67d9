/* Benchmarks of the scenes (docs/performance.md, section "scene").
 *
 *   bench_scene cube --size N --points P [--threads T] [--fit 0|1] [--rl 0|1] [--w 0|1]
 *                    [--rl-iterations K] [--balance L]
 *       The closed form (eq. 3 forward, eq. 4 inverse) against the brute-force spectral path
 *       on one N x N scene: the ODMR cube of P frames is simulated, every frame blurred, and
 *       the field estimated per pixel (centroid; Lorentzian fit with --fit 1); for the
 *       correction every blurred frame is deconvolved (with --w 1 Wiener–Hunt with balance L;
 *       with --rl 1 Richardson–Lucy with K iterations) and the centroid taken again; the
 *       closed-form T⁻¹ runs with the same settings (methods W and R). Prints the time
 *       of each path and the difference between the paths, and the error of each against the
 *       true field.
 *   bench_scene fit --size N --points P [--threads T] [--reps R]
 *       per-pixel Lorentzian fits per second (svp_odmr_fit) on the blurred cube of the same
 *       scene at N x N: median over R repetitions.
 *   bench_scene odmr --size N --points P [--threads T] [--reps R] [--noise S] [--out DIR]
 *       the fit of `svpsf fit-odmr` (svp_odmr_fit_maps with every map it writes: field, PL,
 *       contrast, linewidth, their σ, R², converged) against the scene engine's call
 *       (svp_odmr_fit with the field alone, as `svpsf simulate` makes it) on the same blurred
 *       cube, interleaved, median over R repetitions each; also the one-line model (--lines
 *       one: the sweep holds the upper line only). S > 0 adds Gaussian noise of σ = S √(b ·
 *       b_peak) to every frame, b the pixel's off-resonance PL (shot-noise-like; fixed seed). Prints a hash of every map's bits (to compare thread
 *       counts) and whether the two calls' fields are identical. With --out DIR it writes the
 *       cube as DIR/stack.tif (float32, one page per frequency) and DIR/freq.txt (Hz) for
 *       timing the program end to end.
 *   bench_scene recon --size N [--threads T] [--reps R]
 *       the magnetisation from B_z by the Fourier method and by the support method
 *       (svp_reconstruct_magnetisation, docs/model.md §11) on the closed-form field of a thin
 *       square flake (side 0.5 N + 0.5 px, edges a quarter pixel off the pixel grid, 1 mA,
 *       100 nm pixels, standoff 100 nm; written here, not by the library): medians of R runs
 *       each, the transform pairs of the ×2 padded canvas each method needs (Fourier 1, support
 *       6 + 3 per CG step) timed in the same process as the bound, and each method's median
 *       and largest |error| of m_z at least 1 µm inside the flake.
 *
 * The scene: pixel 0.2 µm, a square flake of 0.6 N pixels (M_z t = 0.1 mA, standoff 100 nm,
 * B_z only), emission = Gaussian spot (FWHM 0.8 N px) x chessboard (20 px squares, levels 0.1,
 * 0.8, 1.0), Lorentzian PSF of 1 µm FWHM, zero boundary, no margin; ODMR: D = 2.87 GHz,
 * Γ = 1 MHz, C = 2 % uniform, the bias and the sweep of `svpsf simulate` (bias = max|B| +
 * 12 Γ/γ, sweep over the upper dip ± 6 Γ). No noise. Times are wall-clock seconds of single
 * runs (cube mode) or medians (fit mode); maxrss_mb is the process's peak resident memory.
 * Errors are in µT over the view without a 16-pixel border (the zero boundary darkens it). */
#include "bench_common.h"
#include "core/internal.h" /* svp_fft_cleanup */

#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define GAMMA 28.033e9
#define D_HZ 2.870e9
#define LINEWIDTH 1e6
#define SPAN_LW 6.0
#define BORDER 16

typedef struct args {
    const char *mode;
    int size, points, threads, reps, fit, rl, w, rl_iterations;
    double balance, noise;
    const char *out;
} args;

static int fail(svp_status st, const char *what)
{
    printf("{\"error\": \"%s\", \"message\": \"%s: %s\"}\n", svp_status_string(st), what,
           svp_last_error());
    return st == SVP_ERR_UNSUPPORTED ? 3 : 2;
}

#define TRY(call, what)                                                                            \
    do {                                                                                           \
        svp_status st_ = (call);                                                                   \
        if (st_ != SVP_OK) return fail(st_, what);                                                 \
    } while (0)

typedef struct scene {
    int n;
    svp_image *pl, *bz;
    svp_blur *blur;
    svp_odmr odmr;
    double bias, bmax, *freq;
    int nf;
} scene;

/* the chessboard level of square (a, b): a hash of the square and the seed */
static double level(int a, int b)
{
    static const double levels[3] = {0.1, 0.8, 1.0};
    uint64_t z =
        (uint64_t)(a + 1000) * 0x9E3779B97F4A7C15u ^ (uint64_t)(b + 1000) * 0xBF58476D1CE4E5B9u;
    z ^= z >> 31;
    z *= 0x94D049BB133111EBu;
    z ^= z >> 29;
    return levels[z % 3];
}

static svp_status scene_make(int n, int nf, scene *s)
{
    memset(s, 0, sizeof *s);
    s->n = n;
    s->nf = nf;
    svp_status st;
    svp_image *moment = NULL;
    if ((st = svp_image_new(n, n, &moment)) != SVP_OK) return st;
    if ((st = svp_image_new(n, n, &s->pl)) != SVP_OK) return st;
    if ((st = svp_image_new(n, n, &s->bz)) != SVP_OK) return st;
    const double c = 0.5 * (n - 1);
    if ((st = svp_raster_rectangle(moment, c, c, 0.6 * n, 0.6 * n, 0, 1e-4)) != SVP_OK) return st;
    svp_sensor sensor;
    svp_sensor_defaults(&sensor);
    sensor.pixel_m = 0.2e-6;
    sensor.standoff_m = 100e-9;
    if ((st = svp_flake_field(moment, 0, &sensor, 2, NULL, NULL, s->bz)) != SVP_OK) return st;
    svp_image_free(moment);
    const double sig = 0.8 * n / 2.3548200450309493;
    for (int j = 0; j < n; j++)
        for (int i = 0; i < n; i++) {
            double r2 = (i - c) * (i - c) + (j - c) * (j - c);
            s->pl->data[(size_t)j * n + i] = exp(-0.5 * r2 / (sig * sig)) * level(i / 20, j / 20);
        }
    svp_psf psf;
    svp_psf_defaults(&psf);
    psf.model = SVP_PSF_LORENTZIAN;
    psf.beta = 1;
    psf.fwhm = 5; /* 1 µm in pixels of 0.2 µm */
    if ((st = svp_blur_new(&psf, n, n, SVP_BOUNDARY_ZERO, &s->blur)) != SVP_OK) return st;
    svp_odmr_defaults(&s->odmr);
    s->odmr.linewidth_hz = LINEWIDTH;
    s->odmr.contrast = 0.02;
    double mx = 0;
    for (size_t p = 0; p < (size_t)n * n; p++) mx = fmax(mx, fabs(s->bz->data[p]));
    s->bmax = mx;
    const double span_t = SPAN_LW * LINEWIDTH / GAMMA;
    s->bias = mx + 2 * span_t;
    const double lo = D_HZ + GAMMA * (s->bias - mx) - SPAN_LW * LINEWIDTH;
    const double hi = D_HZ + GAMMA * (s->bias + mx) + SPAN_LW * LINEWIDTH;
    s->freq = malloc((size_t)nf * sizeof(double));
    if (!s->freq) return SVP_ERR_NOMEM;
    for (int f = 0; f < nf; f++) s->freq[f] = lo + (hi - lo) * f / (nf - 1);
    return SVP_OK;
}

static void scene_free(scene *s)
{
    svp_image_free(s->pl);
    svp_image_free(s->bz);
    svp_blur_free(s->blur);
    free(s->freq);
}

/* the blurred cube (frames of the true cube blurred one at a time) */
static svp_status blurred_cube(scene *s, svp_cube **out, double *t_sim, double *t_blur)
{
    const int n = s->n;
    svp_status st;
    svp_cube *cube = NULL, *one = NULL;
    svp_image *bnv = NULL;
    if ((st = svp_cube_new(n, n, s->nf, s->freq, &cube)) != SVP_OK) return st;
    if ((st = svp_cube_new(n, n, 1, s->freq, &one)) != SVP_OK) return st;
    if ((st = svp_image_new(n, n, &bnv)) != SVP_OK) return st;
    for (size_t p = 0; p < (size_t)n * n; p++) bnv->data[p] = s->bz->data[p] + s->bias;
    *t_sim = *t_blur = 0;
    for (int f = 0; f < s->nf && st == SVP_OK; f++) {
        double t0 = bench_now();
        one->freq[0] = s->freq[f];
        st = svp_odmr_simulate(&s->odmr, s->pl, bnv, NULL, NULL, one);
        double t1 = bench_now();
        if (st == SVP_OK) st = svp_blur_apply(s->blur, one->frame[0], cube->frame[f]);
        *t_sim += t1 - t0;
        *t_blur += bench_now() - t1;
    }
    svp_cube_free(one);
    svp_image_free(bnv);
    if (st != SVP_OK) {
        svp_cube_free(cube);
        return st;
    }
    *out = cube;
    return SVP_OK;
}

/* baseline = mean of the 3 end frames at each side (as `svpsf simulate`); centroid − bias */
static svp_status centroid(const scene *s, const svp_cube *cube, svp_image *baseline,
                           svp_image *out)
{
    const size_t np = (size_t)s->n * s->n;
    const int ne = 3;
    for (size_t p = 0; p < np; p++) {
        double b = 0;
        for (int e = 0; e < ne; e++)
            b += cube->frame[e]->data[p] + cube->frame[s->nf - 1 - e]->data[p];
        baseline->data[p] = b / (2 * ne);
    }
    svp_status st = svp_odmr_centroid(&s->odmr, cube, baseline, 0, 0, out, NULL);
    for (size_t p = 0; p < np; p++) out->data[p] -= s->bias;
    return st;
}

/* rms and max |a − b| (µT) over the view without its border (and, when mask is set, only where
 * mask >= 1) */
static const svp_image *g_mask;

static void diff(const scene *s, const svp_image *a, const svp_image *b, double *rms, double *mx)
{
    double s2 = 0, m = 0;
    size_t cnt = 0;
    for (int j = BORDER; j < s->n - BORDER; j++)
        for (int i = BORDER; i < s->n - BORDER; i++) {
            size_t p = (size_t)j * s->n + i;
            if (g_mask && !(g_mask->data[p] >= 1)) continue;
            double d = a->data[p] - b->data[p];
            s2 += d * d;
            m = fmax(m, fabs(d));
            cnt++;
        }
    *rms = cnt ? 1e6 * sqrt(s2 / (double)cnt) : NAN;
    *mx = 1e6 * m;
}

static void print_pair(const char *name, const scene *s, const svp_image *a, const svp_image *b,
                       int last)
{
    double rms, mx;
    diff(s, a, b, &rms, &mx);
    printf("\"%s_rms_uT\": %.6g, \"%s_max_uT\": %.6g%s", name, rms, name, mx, last ? "" : ", ");
}

static int run_cube(const args *a)
{
    scene s;
    TRY(scene_make(a->size, a->points, &s), "scene");
    const int n = a->size;
    const size_t np = (size_t)n * n;
    svp_image *pl_app, *b_cf, *b_cent, *b_fit, *base, *pl_c, *b_cw, *b_cr, *b_bw, *b_br, *val;
    TRY(svp_image_new(n, n, &pl_app), "alloc");
    TRY(svp_image_new(n, n, &b_cf), "alloc");
    TRY(svp_image_new(n, n, &b_cent), "alloc");
    TRY(svp_image_new(n, n, &b_fit), "alloc");
    TRY(svp_image_new(n, n, &base), "alloc");
    TRY(svp_image_new(n, n, &pl_c), "alloc");
    TRY(svp_image_new(n, n, &b_cw), "alloc");
    TRY(svp_image_new(n, n, &b_cr), "alloc");
    TRY(svp_image_new(n, n, &b_bw), "alloc");
    TRY(svp_image_new(n, n, &b_br), "alloc");
    TRY(svp_image_new(n, n, &val), "alloc");
    /* warm the plans (the closed form and the cube share the operator) */
    TRY(svp_blur_apply(s.blur, s.pl, pl_app), "warm-up");

    /* forward: closed form */
    const svp_image *ft[1] = {s.bz};
    svp_image *fa[1] = {b_cf};
    double t0 = bench_now();
    TRY(svp_forward_transform(s.blur, s.pl, ft, 1, pl_app, fa, NULL), "closed form");
    const double t_cf = bench_now() - t0;
    /* forward: the cube */
    svp_cube *cube = NULL;
    double t_sim, t_blur;
    TRY(blurred_cube(&s, &cube, &t_sim, &t_blur), "cube");
    t0 = bench_now();
    TRY(centroid(&s, cube, base, b_cent), "centroid");
    const double t_cent = bench_now() - t0;
    double t_fit = 0;
    size_t failed = 0;
    if (a->fit) {
        t0 = bench_now();
        TRY(svp_odmr_fit(&s.odmr, cube, NULL, b_fit, NULL, NULL, NULL, &failed), "fit");
        t_fit = bench_now() - t0;
        for (size_t p = 0; p < np; p++) b_fit->data[p] -= s.bias;
    }

    /* inverse: closed form (eq. 4) with W and R; one untimed call of each first (plans,
     * operator caches), as the per-frame paths reuse them too */
    svp_correct_options co;
    svp_correct_defaults(&co);
    co.method = SVP_METHOD_W;
    co.deconv.balance = a->balance;
    /* a timing of the study's settings (balance 1), whose W result may be in doubt on this
     * scene: kept (validity 0 there), as the scenes keep it, instead of refused */
    co.keep_doubtful = 1;
    const svp_image *fa2[1] = {b_cf};
    svp_image *fc[1] = {b_cw};
    TRY(svp_inverse_transform(s.blur, pl_app, fa2, 1, &co, pl_c, fc, val, NULL), "warm-up W");
    if (a->rl) {
        co.method = SVP_METHOD_R;
        co.deconv.iterations = 1;
        TRY(svp_inverse_transform(s.blur, pl_app, fa2, 1, &co, pl_c, fc, val, NULL), "warm-up R");
        co.method = SVP_METHOD_W;
    }
    t0 = bench_now();
    TRY(svp_inverse_transform(s.blur, pl_app, fa2, 1, &co, pl_c, fc, val, NULL), "T^-1 W");
    const double t_inv_w = bench_now() - t0;
    /* W's errors are taken where its recovered PL is above the floor (validity 1) */
    svp_image *val_w = NULL;
    TRY(svp_image_copy(val, &val_w), "alloc");
    size_t n_valid_w = 0;
    for (int j = BORDER; j < n - BORDER; j++)
        for (int i = BORDER; i < n - BORDER; i++) n_valid_w += val_w->data[(size_t)j * n + i] >= 1;
    double t_inv_r = 0;
    if (a->rl) {
        co.method = SVP_METHOD_R;
        co.deconv.iterations = a->rl_iterations;
        fc[0] = b_cr;
        t0 = bench_now();
        TRY(svp_inverse_transform(s.blur, pl_app, fa2, 1, &co, pl_c, fc, val, NULL), "T^-1 R");
        t_inv_r = bench_now() - t0;
    }
    /* inverse: deconvolve every frame, then the centroid */
    svp_cube *dec = NULL;
    TRY(svp_cube_new(n, n, s.nf, s.freq, &dec), "alloc");
    svp_deconv_options dopt;
    svp_deconv_defaults(&dopt);
    dopt.balance = a->balance;
    dopt.iterations = a->rl_iterations;
    double t_brute_w = 0;
    if (a->w) {
        t0 = bench_now();
        for (int f = 0; f < s.nf; f++)
            TRY(svp_deconv_wiener(s.blur, cube->frame[f], &dopt, dec->frame[f]),
                "Wiener per frame");
        TRY(centroid(&s, dec, base, b_bw), "centroid");
        t_brute_w = bench_now() - t0;
    }
    double t_brute_r = 0;
    if (a->rl) {
        t0 = bench_now();
        for (int f = 0; f < s.nf; f++)
            TRY(svp_deconv_rl(s.blur, cube->frame[f], &dopt, dec->frame[f]), "RL per frame");
        TRY(centroid(&s, dec, base, b_br), "centroid");
        t_brute_r = bench_now() - t0;
    }
    svp_cube_free(dec);
    svp_cube_free(cube);

    double step = (s.freq[s.nf - 1] - s.freq[0]) / (s.nf - 1);
    printf("{\"mode\": \"cube\", \"size\": %d, \"points\": %d, \"threads\": %d, "
           "\"step_MHz\": %.4g, \"bias_mT\": %.5g, \"bmax_uT\": %.6g, \"balance\": %g, "
           "\"rl_iterations\": %d, ",
           n, s.nf, svp_get_threads(), 1e-6 * step, 1e3 * s.bias, 1e6 * s.bmax, a->balance,
           a->rl ? a->rl_iterations : 0);
    printf("\"t_closed_forward\": %.6g, \"t_cube_simulate\": %.6g, \"t_cube_blur\": %.6g, "
           "\"t_centroid\": %.6g, \"t_fit\": %.6g, \"fits_failed\": %zu, ",
           t_cf, t_sim, t_blur, t_cent, t_fit, failed);
    printf("\"t_closed_inverse_w\": %.6g, \"t_brute_inverse_w\": %.6g, "
           "\"t_closed_inverse_r\": %.6g, \"t_brute_inverse_r\": %.6g, ",
           t_inv_w, t_brute_w, t_inv_r, t_brute_r);
    print_pair("cf_vs_true", &s, b_cf, s.bz, 0);
    print_pair("cf_vs_centroid", &s, b_cf, b_cent, 0);
    print_pair("centroid_vs_true", &s, b_cent, s.bz, 0);
    if (a->fit) {
        print_pair("cf_vs_fit", &s, b_cf, b_fit, 0);
        print_pair("fit_vs_true", &s, b_fit, s.bz, 0);
    }
    g_mask = val_w;
    print_pair("w_cf_vs_true", &s, b_cw, s.bz, 0);
    if (a->w) {
        print_pair("w_cf_vs_brute", &s, b_cw, b_bw, 0);
        print_pair("w_brute_vs_true", &s, b_bw, s.bz, 0);
    }
    g_mask = NULL;
    printf("\"w_valid_fraction\": %.4g, ",
           (double)n_valid_w / ((double)(n - 2 * BORDER) * (n - 2 * BORDER)));
    if (a->rl) {
        print_pair("r_cf_vs_true", &s, b_cr, s.bz, 0);
        print_pair("r_cf_vs_brute", &s, b_cr, b_br, 0);
        print_pair("r_brute_vs_true", &s, b_br, s.bz, 0);
    }
    printf("\"maxrss_mb\": %.1f}\n", bench_maxrss_mb());
    fflush(stdout);
    svp_image_free(val_w);
    svp_image *imgs[] = {pl_app, b_cf, b_cent, b_fit, base, pl_c, b_cw, b_cr, b_bw, b_br, val};
    for (size_t i = 0; i < sizeof imgs / sizeof imgs[0]; i++) svp_image_free(imgs[i]);
    scene_free(&s);
    return 0;
}

static int run_fit(const args *a)
{
    scene s;
    TRY(scene_make(a->size, a->points, &s), "scene");
    const int n = a->size;
    svp_cube *cube = NULL;
    double t_sim, t_blur;
    TRY(blurred_cube(&s, &cube, &t_sim, &t_blur), "cube");
    svp_image *field = NULL;
    TRY(svp_image_new(n, n, &field), "alloc");
    double *t = malloc((size_t)a->reps * sizeof(double));
    if (!t) return fail(SVP_ERR_NOMEM, "alloc");
    size_t failed = 0;
    for (int r = 0; r < a->reps; r++) {
        double t0 = bench_now();
        TRY(svp_odmr_fit(&s.odmr, cube, NULL, field, NULL, NULL, NULL, &failed), "fit");
        t[r] = bench_now() - t0;
    }
    double med = bench_median(t, a->reps);
    double rms = 0;
    for (size_t p = 0; p < (size_t)n * n; p++) {
        double d = field->data[p] - s.bias - s.bz->data[p];
        rms += d * d;
    }
    rms = 1e6 * sqrt(rms / ((double)n * n));
    printf("{\"mode\": \"fit\", \"size\": %d, \"points\": %d, \"threads\": %d, \"reps\": %d, "
           "\"fits\": %zu, \"seconds\": %.6g, \"fits_per_second\": %.6g, \"failed\": %zu, "
           "\"fit_vs_true_rms_uT\": %.4g, \"maxrss_mb\": %.1f}\n",
           n, s.nf, svp_get_threads(), a->reps, (size_t)n * n, med, (double)n * n / med, failed,
           rms, bench_maxrss_mb());
    fflush(stdout);
    free(t);
    svp_image_free(field);
    svp_cube_free(cube);
    scene_free(&s);
    return 0;
}

/* ---- recon: the magnetisation by the Fourier and the support method ------------------------- */

/* B_z of a thin rectangle [x1, x2] × [y1, y2] of areal moment m (A) at (x, y), height z: the
 * dipole sheet's closed form (φ = m Ω / 4π) */
static double rect_bz(double m, double x1, double x2, double y1, double y2, double x, double y,
                      double z)
{
    const double xs[2] = {x1 - x, x2 - x}, ys[2] = {y1 - y, y2 - y};
    double hz = 0;
    for (int i = 0; i < 2; i++)
        for (int j = 0; j < 2; j++) {
            double X = xs[i], Y = ys[j], r = sqrt(X * X + Y * Y + z * z);
            double t = X * Y * (r * r + z * z) / (r * (X * X + z * z) * (Y * Y + z * z));
            hz += i == j ? t : -t;
        }
    return 1.25663706212e-6 * m / (4 * M_PI) * hz;
}

/* median and largest |m_z − 1 mA| / 1 mA at least 10 px inside the flake [lo, hi] (pixels) */
static void recon_error(const svp_image *mz, double lo, double hi, double *med, double *mx)
{
    const int n = mz->width;
    double *e = malloc((size_t)n * n * sizeof(double));
    size_t k = 0;
    *mx = 0;
    for (int j = 0; j < n && e; j++)
        for (int i = 0; i < n; i++)
            if (i > lo + 10 && i < hi - 10 && j > lo + 10 && j < hi - 10) {
                e[k] = fabs(mz->data[(size_t)j * n + i] - 1e-3) / 1e-3;
                *mx = fmax(*mx, e[k++]);
            }
    *med = e && k ? bench_median(e, (int)k) : NAN;
    free(e);
}

static int run_recon(const args *a)
{
    const int n = a->size;
    const double px = 100e-9, h = 100e-9, lo = 0.25 * n - 0.25, hi = 0.75 * n + 0.25;
    svp_image *bz = NULL, *mz = NULL;
    TRY(svp_image_new(n, n, &bz), "alloc");
    TRY(svp_image_new(n, n, &mz), "alloc");
    for (int j = 0; j < n; j++)
        for (int i = 0; i < n; i++)
            bz->data[(size_t)j * n + i] = rect_bz(1e-3, lo * px, hi * px, lo * px, hi * px,
                                                  i * px, j * px, h);
    /* the bound: one r2c + c2r pair of the canvas, median of max(R, 5) */
    const int nc = svp_fft_good_size(2 * n);
    const svp_fft_plan *plan = NULL;
    TRY(svp_fft_plan_get(nc, nc, &plan), "plan");
    double *real = svp_alloc((size_t)nc * nc * sizeof(double));
    fftw_complex *spec = svp_alloc((size_t)nc * (nc / 2 + 1) * sizeof(fftw_complex));
    const int pr = a->reps > 5 ? a->reps : 5;
    double *t = malloc((size_t)(2 * a->reps + pr) * sizeof(double));
    if (!real || !spec || !t) return fail(SVP_ERR_NOMEM, "alloc");
    for (size_t p = 0; p < (size_t)nc * nc; p++) real[p] = bz->data[p % ((size_t)n * n)];
    for (int r = -1; r < pr; r++) { /* r = -1: a warm-up (first touch of the buffers) */
        double t0 = bench_now();
        svp_fft_forward(plan, real, spec);
        svp_fft_inverse(plan, spec, real);
        if (r >= 0) t[2 * a->reps + r] = bench_now() - t0;
    }
    const double pair = bench_median(t + 2 * a->reps, pr);
    svp_recon_options o;
    svp_recon_defaults(&o);
    o.sensor.pixel_m = px;
    o.sensor.standoff_m = h;
    double med[2], mx[2], sec[2];
    svp_recon_report rep = {0};
    for (int m = 0; m < 2; m++) {
        o.method = m ? SVP_RECON_SUPPORT : SVP_RECON_FOURIER;
        TRY(svp_reconstruct_magnetisation_report(bz, &o, mz, &rep), "reconstruct"); /* warm */
        for (int r = 0; r < a->reps; r++) {
            double t0 = bench_now();
            TRY(svp_reconstruct_magnetisation_report(bz, &o, mz, &rep), "reconstruct");
            t[m * a->reps + r] = bench_now() - t0;
        }
        sec[m] = bench_median(t + m * a->reps, a->reps);
        recon_error(mz, lo, hi, &med[m], &mx[m]);
    }
    const int pairs_support = 6 + 3 * rep.iterations;
    printf("{\"mode\": \"recon\", \"size\": %d, \"canvas\": %d, \"threads\": %d, \"reps\": %d, "
           "\"fft_pair_s\": %.6g, \"fourier_s\": %.6g, \"support_s\": %.6g, "
           "\"support_steps\": %d, \"support_residual\": %.3g, \"support_pairs\": %d, "
           "\"fourier_median_err_pct\": %.4g, \"fourier_max_err_pct\": %.4g, "
           "\"support_median_err_pct\": %.4g, \"support_max_err_pct\": %.4g, "
           "\"maxrss_mb\": %.1f}\n",
           n, nc, svp_get_threads(), a->reps, pair, sec[0], sec[1], rep.iterations, rep.residual,
           pairs_support, 100 * med[0], 100 * mx[0], 100 * med[1], 100 * mx[1],
           bench_maxrss_mb());
    fflush(stdout);
    free(t);
    svp_free(real);
    svp_free(spec);
    svp_image_free(bz);
    svp_image_free(mz);
    return 0;
}

/* ---- odmr: svp_odmr_fit_maps (fit-odmr) against svp_odmr_fit (the scene engine) -------------- */

static void le_put(unsigned char *p, uint32_t v, int n)
{
    for (int k = 0; k < n; k++) p[k] = (unsigned char)(v >> (8 * k));
}

/* the cube as a little-endian multi-page float32 TIFF (one strip per page, then its
 * directory), and the frequencies one per line */
static int write_stack(const svp_cube *cube, const char *dir)
{
    const int w = cube->width, h = cube->height, n = cube->n_freq;
    const size_t bytes = (size_t)w * h * 4, page = bytes + 2 + 12 * 10 + 4 + 1;
    char path[4096];
    snprintf(path, sizeof path, "%s/stack.tif", dir);
    FILE *f = fopen(path, "wb");
    if (!f) return 1;
    unsigned char head[8] = {'I', 'I', 42, 0};
    le_put(head + 4, (uint32_t)(8 + bytes + (bytes & 1)), 4); /* page 1's directory */
    int bad = fwrite(head, 1, 8, f) != 8;
    unsigned char *buf = malloc(page);
    if (!buf) bad = 1;
    size_t pos = 8;
    for (int p = 0; p < n && !bad; p++) {
        float *px = (float *)buf; /* little-endian host assumed (x86-64, aarch64) */
        for (size_t k = 0; k < (size_t)w * h; k++) px[k] = (float)cube->frame[p]->data[k];
        const size_t data = pos, ifd = pos + bytes + (bytes & 1);
        unsigned char *d = buf + (ifd - pos);
        memset(buf + bytes, 0, page - bytes);
        const uint32_t e[10][3] = {{256, 3, (uint32_t)w}, {257, 3, (uint32_t)h}, {258, 3, 32},
                                   {259, 3, 1}, {262, 3, 1}, {273, 4, (uint32_t)data},
                                   {277, 3, 1}, {278, 3, (uint32_t)h}, {279, 4, (uint32_t)bytes},
                                   {339, 3, 3}};
        le_put(d, 10, 2);
        for (int k = 0; k < 10; k++) {
            unsigned char *q = d + 2 + 12 * k;
            le_put(q, e[k][0], 2);
            le_put(q + 2, e[k][1], 2);
            le_put(q + 4, 1, 4);
            le_put(q + 8, e[k][2], e[k][1] == 3 ? 2 : 4);
        }
        const size_t end = ifd + 2 + 12 * 10 + 4;
        le_put(d + 2 + 12 * 10, p + 1 < n ? (uint32_t)(end + bytes) : 0, 4); /* next page's */
        bad |= fwrite(buf, 1, end - pos, f) != end - pos;
        pos = end;
    }
    free(buf);
    bad |= fclose(f) != 0;
    snprintf(path, sizeof path, "%s/freq.txt", dir);
    f = fopen(path, "w");
    if (!f) return 1;
    for (int p = 0; p < n; p++) fprintf(f, "%.17g\n", cube->freq[p]);
    bad |= fclose(f) != 0;
    return bad;
}

/* CPU seconds of the process (all its threads) */
static double cpu_now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

/* FNV-1a over the bits of the images */
static uint64_t hash_images(svp_image *const *imgs, int n, uint64_t h)
{
    for (int i = 0; i < n; i++) {
        if (!imgs[i]) continue;
        const unsigned char *b = (const unsigned char *)imgs[i]->data;
        const size_t len = (size_t)imgs[i]->width * imgs[i]->height * sizeof(double);
        for (size_t k = 0; k < len; k++) h = (h ^ b[k]) * 0x100000001b3u;
    }
    return h;
}

static double gauss_noise(uint64_t *s)
{
    double u[2];
    for (int k = 0; k < 2; k++) {
        *s = *s * 6364136223846793005u + 1442695040888963407u;
        u[k] = ((double)(*s >> 11) + 0.5) / 9007199254740992.0;
    }
    return sqrt(-2 * log(u[0])) * cos(2 * M_PI * u[1]);
}

static int run_odmr(const args *a)
{
    scene s;
    TRY(scene_make(a->size, a->points, &s), "scene");
    const int n = a->size;
    const size_t np = (size_t)n * n;
    svp_cube *cube = NULL;
    double t_sim, t_blur;
    TRY(blurred_cube(&s, &cube, &t_sim, &t_blur), "cube");
    if (a->noise > 0) { /* shot-noise-like: σ = S √(b · b_peak), b the off-resonance PL */
        double peak = 0;
        for (size_t p = 0; p < np; p++) peak = fmax(peak, cube->frame[0]->data[p]);
        double *sd = malloc(np * sizeof(double));
        if (!sd) return fail(SVP_ERR_NOMEM, "alloc");
        for (size_t p = 0; p < np; p++)
            sd[p] = a->noise * sqrt(fmax(cube->frame[0]->data[p], 0) * peak);
        uint64_t seed = 12345;
        for (int f = 0; f < s.nf; f++)
            for (size_t p = 0; p < np; p++)
                cube->frame[f]->data[p] += sd[p] * gauss_noise(&seed);
        free(sd);
    }
    if (a->out && write_stack(cube, a->out)) {
        printf("{\"error\": \"io\", \"message\": \"cannot write %s/stack.tif\"}\n", a->out);
        return 2;
    }
    enum { NM = 10 };
    svp_image *old = NULL, *pair[NM] = {NULL}, *one[NM] = {NULL};
    TRY(svp_image_new(n, n, &old), "alloc");
    for (int k = 0; k < NM; k++) {
        TRY(svp_image_new(n, n, &pair[k]), "alloc");
        TRY(svp_image_new(n, n, &one[k]), "alloc");
    }
#define ODMR_MAPS(m)                                                                               \
    {.field = m[0], .field_sigma = m[1], .baseline = m[2], .baseline_sigma = m[3],                 \
     .contrast = m[4], .contrast_sigma = m[5], .linewidth = m[6], .linewidth_sigma = m[7],         \
     .quality = m[8], .converged = m[9]}
    const svp_odmr_maps maps_pair = ODMR_MAPS(pair), maps_one = ODMR_MAPS(one);
    svp_odmr_fit_options o_pair, o_one;
    svp_odmr_fit_defaults(&o_pair);
    svp_odmr_fit_defaults(&o_one);
    o_one.lines = SVP_ODMR_LINES_ONE;
    o_one.line_sign = 1;
    /* wall-clock and process CPU seconds (every thread's; the CPU time is what load changes
     * least: fits per CPU-second x cores is the speed of idle cores) */
    double *t = malloc(6 * (size_t)a->reps * sizeof(double)), *cpu = t + 3 * (size_t)a->reps;
    if (!t) return fail(SVP_ERR_NOMEM, "alloc");
    size_t f_old = 0, f_pair = 0, f_one = 0;
    for (int r = 0; r < a->reps; r++) {
        double t0 = bench_now(), c0 = cpu_now();
        TRY(svp_odmr_fit(&s.odmr, cube, NULL, old, NULL, NULL, NULL, &f_old), "scene fit");
        double t1 = bench_now(), c1 = cpu_now();
        TRY(svp_odmr_fit_maps(&s.odmr, cube, &o_pair, &maps_pair, &f_pair), "fit maps (pair)");
        double t2 = bench_now(), c2 = cpu_now();
        TRY(svp_odmr_fit_maps(&s.odmr, cube, &o_one, &maps_one, &f_one), "fit maps (one)");
        double t3 = bench_now(), c3 = cpu_now();
        t[r] = t1 - t0;
        t[a->reps + r] = t2 - t1;
        t[2 * a->reps + r] = t3 - t2;
        cpu[r] = c1 - c0;
        cpu[a->reps + r] = c2 - c1;
        cpu[2 * a->reps + r] = c3 - c2;
    }
    const double m_old = bench_median(t, a->reps), m_pair = bench_median(t + a->reps, a->reps),
                 m_one = bench_median(t + 2 * a->reps, a->reps);
    const double cpu_old = bench_median(cpu, a->reps), cpu_pair = bench_median(cpu + a->reps, a->reps);
    const int same = memcmp(old->data, pair[0]->data, np * sizeof(double)) == 0;
    /* errors against the true field (the bias removed), converged pixels */
    double r_pair = 0, r_one = 0, sig = 0;
    size_t cnt = 0;
    for (size_t p = 0; p < np; p++) {
        if (pair[9]->data[p] != 1 || one[9]->data[p] != 1) continue;
        const double want = s.bz->data[p] + s.bias;
        r_pair += (pair[0]->data[p] - want) * (pair[0]->data[p] - want);
        r_one += (one[0]->data[p] - want) * (one[0]->data[p] - want);
        if (isfinite(pair[1]->data[p])) sig += pair[1]->data[p] * pair[1]->data[p];
        cnt++;
    }
    const double c = cnt ? (double)cnt : 1;
    const uint64_t hash = hash_images(one, NM, hash_images(pair, NM, 0xcbf29ce484222325u));
    printf("{\"mode\": \"odmr\", \"size\": %d, \"points\": %d, \"threads\": %d, \"reps\": %d, "
           "\"noise\": %.6g, \"fits\": %zu, \"scene_seconds\": %.6g, \"pair_seconds\": %.6g, "
           "\"one_seconds\": %.6g, \"scene_cpu_seconds\": %.6g, \"pair_cpu_seconds\": %.6g, "
           "\"scene_fits_per_second\": %.6g, "
           "\"pair_fits_per_second\": %.6g, \"one_fits_per_second\": %.6g, "
           "\"scene_failed\": %zu, \"pair_failed\": %zu, \"one_failed\": %zu, "
           "\"field_identical\": %s, \"maps_hash\": \"%016llx\", \"pair_rms_uT\": %.4g, "
           "\"one_rms_uT\": %.4g, \"pair_sigma_rms_uT\": %.4g, \"maxrss_mb\": %.1f}\n",
           n, s.nf, svp_get_threads(), a->reps, a->noise, np, m_old, m_pair, m_one, cpu_old,
           cpu_pair,
           (double)np / m_old, (double)np / m_pair, (double)np / m_one, f_old, f_pair, f_one,
           same ? "true" : "false", (unsigned long long)hash, 1e6 * sqrt(r_pair / c),
           1e6 * sqrt(r_one / c), 1e6 * sqrt(sig / c), bench_maxrss_mb());
    fflush(stdout);
    free(t);
    svp_image_free(old);
    for (int k = 0; k < NM; k++) {
        svp_image_free(pair[k]);
        svp_image_free(one[k]);
    }
    svp_cube_free(cube);
    scene_free(&s);
    return 0;
}

static int usage(void)
{
    fprintf(stderr,
            "usage: bench_scene cube --size N --points P [--threads T] [--fit 0|1] [--rl 0|1]\n"
            "                        [--w 0|1] [--rl-iterations K] [--balance L]\n"
            "       bench_scene fit --size N --points P [--threads T] [--reps R]\n"
            "       bench_scene odmr --size N --points P [--threads T] [--reps R] [--noise S]\n"
            "                        [--out DIR]\n"
            "       bench_scene recon --size N [--threads T] [--reps R]\n");
    return 1;
}

int main(int argc, char **argv)
{
    if (argc < 2) return usage();
    args a = {.mode = argv[1],
              .size = 512,
              .points = 100,
              .threads = 2,
              .reps = 3,
              .fit = 1,
              .rl = 1,
              .w = 1,
              .rl_iterations = 15,
              .balance = 1e-3};
    for (int i = 2; i < argc; i++) {
        const char *k = argv[i];
        if (i + 1 >= argc) return usage();
        const char *v = argv[++i];
        if (!strcmp(k, "--size"))
            a.size = atoi(v);
        else if (!strcmp(k, "--points"))
            a.points = atoi(v);
        else if (!strcmp(k, "--threads"))
            a.threads = atoi(v);
        else if (!strcmp(k, "--reps"))
            a.reps = atoi(v);
        else if (!strcmp(k, "--fit"))
            a.fit = atoi(v);
        else if (!strcmp(k, "--rl"))
            a.rl = atoi(v);
        else if (!strcmp(k, "--w"))
            a.w = atoi(v);
        else if (!strcmp(k, "--rl-iterations"))
            a.rl_iterations = atoi(v);
        else if (!strcmp(k, "--balance"))
            a.balance = atof(v);
        else if (!strcmp(k, "--noise"))
            a.noise = atof(v);
        else if (!strcmp(k, "--out"))
            a.out = v;
        else
            return usage();
    }
    if (a.size < 64 || a.points < 12 || a.threads < 1 || a.reps < 1 || a.rl_iterations < 1 ||
        !(a.balance >= 0) || !(a.noise >= 0))
        return usage();
    svp_set_threads(a.threads);
    svp_set_fft_effort(SVP_FFT_ESTIMATE);
    int rc;
    if (!strcmp(a.mode, "cube"))
        rc = run_cube(&a);
    else if (!strcmp(a.mode, "fit"))
        rc = run_fit(&a);
    else if (!strcmp(a.mode, "odmr"))
        rc = run_odmr(&a);
    else if (!strcmp(a.mode, "recon"))
        rc = run_recon(&a);
    else
        rc = usage();
    svp_fft_cleanup();
    return rc;
}
