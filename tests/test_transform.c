/* The transforms T (eq. 3) and T⁻¹ (eq. 4; signed shift eq. 5, validity eq. 6) and the halo
 * correction (eq. 7) of docs/model.md: limit cases, noiseless round trips, hard cases, bad
 * input, threads, progress. Measured numbers are printed and quoted in the comments (release
 * build; SVP_TEST_FILTER=test_name runs one test). */
#include "test_helpers.h"

#include "blur/blur_internal.h"
#include "core/internal.h"

#include <omp.h>
#include <stdio.h>

/* internal (restore/transform.c): T⁻¹ that also counts its last-resort NaN/Inf repairs */
svp_status svp_inverse_transform_counted(svp_blur *blur, const svp_image *pl_apparent,
                                         const svp_image *const *field_apparent, int n_fields,
                                         const svp_correct_options *options, svp_image *pl_true,
                                         svp_image *const *field_true, svp_image *validity,
                                         size_t *n_missing, size_t *n_repaired);

#define NF 2 /* field components in the scenes */

/* A stated bound: fails the test, or (built with -DTRANSFORM_MEASURE) only reports. */
#ifdef TRANSFORM_MEASURE
#define CHECK_BOUND(cond, ...)                                                                     \
    do {                                                                                           \
        if (!(cond)) print_message("BOUND EXCEEDED: " __VA_ARGS__);                                \
    } while (0)
#else
#define CHECK_BOUND(cond, ...)                                                                     \
    do {                                                                                           \
        if (!(cond)) fail_msg(__VA_ARGS__);                                                        \
    } while (0)
#endif

static const char *method_names[] = {"RW", "R", "W", "RL_SIGNED"};

/* ---- operators and scenes ---------------------------------------------------------------- */

static svp_blur *blur_model(svp_psf_model model, double fwhm, double beta, double halo, int w,
                            int h, svp_boundary boundary)
{
    svp_psf psf;
    svp_psf_defaults(&psf);
    psf.model = model;
    psf.fwhm = fwhm;
    psf.beta = beta;
    psf.halo = halo;
    svp_blur *op = NULL;
    ASSERT_OK(svp_blur_new(&psf, w, h, boundary, &op));
    return op;
}

/* p = δ: a 1 x 1 kernel */
static svp_blur *blur_delta(int w, int h, svp_boundary boundary)
{
    svp_image *k = test_image(1, 1);
    k->data[0] = 1;
    svp_blur *op = NULL;
    ASSERT_OK(svp_blur_new_kernel(k, 0, 0, 1, w, h, boundary, &op));
    svp_image_free(k);
    return op;
}

/* p = (1 − α) δ + α / A: a Gaussian of FWHM 0.01 px sampled at pixel centres is exactly δ
 * (its neighbours underflow to 0), plus the halo term of the operator. */
static svp_blur *blur_halo_only(double alpha, int w, int h)
{
    svp_psf psf;
    svp_psf_defaults(&psf);
    psf.fwhm = 0.01;
    psf.subsample = 1;
    psf.halo = alpha;
    svp_blur *op = NULL;
    ASSERT_OK(svp_blur_new(&psf, w, h, SVP_BOUNDARY_PERIODIC, &op));
    return op;
}

/* The reference study's emission pattern: a Gaussian spot (FWHM = the larger side) times a
 * random chessboard of `square`-pixel squares with levels {0.1, 0.8, 1.0}. */
static svp_image *pl_spot_chessboard(int w, int h, int square, uint64_t seed)
{
    static const double levels[3] = {0.1, 0.8, 1.0};
    svp_image *pl = test_image(w, h);
    int nsx = (w + square - 1) / square, nsy = (h + square - 1) / square;
    double *level = malloc((size_t)nsx * nsy * sizeof *level);
    uint64_t s = seed * 2654435761ULL + 1442695040888963407ULL;
    for (int i = 0; i < nsx * nsy; i++) {
        int k = (int)(3 * test_rand(&s));
        level[i] = levels[k > 2 ? 2 : k];
    }
    double fwhm = w > h ? w : h, sigma = fwhm / 2.3548200450309493;
    double cx = 0.5 * (w - 1), cy = 0.5 * (h - 1);
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double r2 = (x - cx) * (x - cx) + (y - cy) * (y - cy);
            pl->data[(size_t)y * w + x] =
                exp(-0.5 * r2 / (sigma * sigma)) * level[(y / square) * nsx + x / square];
        }
    free(level);
    return pl;
}

/* Smooth signed field components (zero slope at the edges, so mirror extension is smooth). */
static svp_image *field_smooth(int w, int h, int component)
{
    svp_image *b = test_image(w, h);
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double u = (x + 0.5) / w, v = (y + 0.5) / h;
            b->data[(size_t)y * w + x] =
                component == 0 ? cos(M_PI * u) * (1 + 0.5 * cos(M_PI * v)) - 0.2
                               : 0.7 * cos(2 * M_PI * v) + 0.3 * cos(M_PI * u) * cos(M_PI * v);
        }
    return b;
}

static void free_images(svp_image **images, int n)
{
    for (int i = 0; i < n; i++) svp_image_free(images[i]);
}

/* Seeded Poisson sampler (Knuth's product of uniforms; fine for means up to a few hundred). */
static double poisson(uint64_t *s, double mean)
{
    if (!(mean > 0)) return 0;
    double limit = exp(-mean), p = 1;
    int k = -1;
    do {
        k++;
        p *= test_rand(s);
    } while (p > limit);
    return k;
}

static svp_correct_options options_for(svp_method method, int iterations, double balance)
{
    svp_correct_options o;
    svp_correct_defaults(&o);
    o.method = method;
    o.deconv.iterations = iterations;
    o.deconv.balance = balance;
    return o;
}

/* ---- defaults ---------------------------------------------------------------------------- */

static void test_defaults(void **state)
{
    (void)state;
    svp_correct_options o;
    memset(&o, 0xff, sizeof o);
    svp_correct_defaults(&o);
    assert_int_equal(o.method, SVP_METHOD_R);
    assert_int_equal(o.deconv.iterations, 75);
    ASSERT_CLOSE(o.pl_floor, 1e-3, 0);
    ASSERT_CLOSE(o.shift, 0, 0);
    assert_null(o.deconv.progress);
    assert_int_equal(o.side_by_side, 1);
}

/* ---- limit cases (docs/model.md §2 and §4) ---------------------------------------------------------- */

/* p = δ → B̃ = B and Ĩ = I; and T⁻¹ with Wiener at balance 0 is then the identity too. */
static void test_delta_psf_is_identity(void **state)
{
    (void)state;
    const int w = 40, h = 33;
    for (int m = 0; m < 3; m++) {
        svp_blur *op = blur_delta(w, h, (svp_boundary)m);
        svp_image *pl = pl_spot_chessboard(w, h, 6, 1), *pl_app = test_image(w, h);
        for (size_t i = 0; i < (size_t)w * h; i++) pl->data[i] += 0.05; /* corners stay lit */
        svp_image *b[NF] = {field_smooth(w, h, 0), field_smooth(w, h, 1)};
        svp_image *b_app[NF] = {test_image(w, h), test_image(w, h)};
        svp_image *valid = test_image(w, h);
        ASSERT_OK(
            svp_forward_transform(op, pl, (const svp_image *const *)b, NF, pl_app, b_app, valid));
        assert_true(test_max_abs_diff(pl_app, pl) < 1e-14);
        for (int c = 0; c < NF; c++) assert_true(test_max_abs_diff(b_app[c], b[c]) < 1e-14);
        for (size_t i = 0; i < (size_t)w * h; i++) assert_true(valid->data[i] == 1.0);

        svp_correct_options o = options_for(SVP_METHOD_W, 1, 0.0);
        svp_image *b_rec[NF] = {test_image(w, h), test_image(w, h)}, *pl_rec = test_image(w, h);
        size_t repaired = 1;
        ASSERT_OK(svp_inverse_transform_counted(op, pl_app, (const svp_image *const *)b_app, NF, &o,
                                                pl_rec, b_rec, valid, NULL, &repaired));
        assert_int_equal(repaired, 0);
        assert_true(test_max_abs_diff(pl_rec, pl) < 1e-12);
        for (int c = 0; c < NF; c++) assert_true(test_max_abs_diff(b_rec[c], b[c]) < 1e-12);
        svp_blur_free(op);
        svp_image_free(pl);
        svp_image_free(pl_app);
        svp_image_free(valid);
        svp_image_free(pl_rec);
        free_images(b, NF);
        free_images(b_app, NF);
        free_images(b_rec, NF);
    }
}

/* Uniform I → B̃ = H B for the periodic and mirror boundaries (H 1 = 1), and the normalised
 * convolution B̃ = H B / H 1 for the zero boundary, where light leaves the image. */
static void test_uniform_pl_is_blur(void **state)
{
    (void)state;
    const int w = 48, h = 36;
    for (int m = 0; m < 3; m++) {
        svp_blur *op = blur_model(SVP_PSF_MOFFAT, 3.0, 2.5, 0.0, w, h, (svp_boundary)m);
        svp_image *pl = test_image(w, h), *pl_app = test_image(w, h), *one = test_image(w, h);
        svp_image *h_one = test_image(w, h), *h_b = test_image(w, h);
        for (size_t i = 0; i < (size_t)w * h; i++) {
            pl->data[i] = 3.7;
            one->data[i] = 1.0;
        }
        svp_image *b[1] = {test_random_image(w, h, 5)};
        for (size_t i = 0; i < (size_t)w * h; i++) b[0]->data[i] -= 0.5; /* signed */
        svp_image *b_app[1] = {test_image(w, h)};
        ASSERT_OK(
            svp_forward_transform(op, pl, (const svp_image *const *)b, 1, pl_app, b_app, NULL));
        ASSERT_OK(svp_blur_apply(op, b[0], h_b));
        ASSERT_OK(svp_blur_apply(op, one, h_one));
        double err = 0;
        for (size_t i = 0; i < (size_t)w * h; i++) {
            double expect = m == SVP_BOUNDARY_ZERO ? h_b->data[i] / h_one->data[i] : h_b->data[i];
            err = fmax(err, fabs(b_app[0]->data[i] - expect));
        }
        if (err > 1e-12) fail_msg("boundary %d: B̃ differs from H B by %.3g", m, err);
        svp_blur_free(op);
        svp_image_free(pl);
        svp_image_free(pl_app);
        svp_image_free(one);
        svp_image_free(h_one);
        svp_image_free(h_b);
        free_images(b, 1);
        free_images(b_app, 1);
    }
}

/* Halo-only PSF: uniform PL → B̃ − <B̃> = (1 − α)(B − <B>); svp_halo_correct inverts it, and it
 * inverts T exactly for a non-uniform PL too (where there is light). */
static void test_halo_only(void **state)
{
    (void)state;
    const int w = 36, h = 32;
    const size_t n = (size_t)w * h;
    const double alpha = 0.5;
    svp_blur *op = blur_halo_only(alpha, w, h);
    ASSERT_CLOSE(svp_blur_halo(op), alpha, 0);
    svp_image *b[1] = {field_smooth(w, h, 0)};
    svp_image *b_app[1] = {test_image(w, h)};
    svp_image *pl = test_image(w, h), *pl_app = test_image(w, h), *b_rec = test_image(w, h);
    for (size_t i = 0; i < n; i++) pl->data[i] = 2.0;
    ASSERT_OK(svp_forward_transform(op, pl, (const svp_image *const *)b, 1, pl_app, b_app, NULL));
    double mean_b = test_sum(b[0]) / n, mean_app = test_sum(b_app[0]) / n;
    for (size_t i = 0; i < n; i++)
        ASSERT_CLOSE(b_app[0]->data[i] - mean_app, (1 - alpha) * (b[0]->data[i] - mean_b), 1e-12);
    ASSERT_OK(svp_halo_correct(alpha, pl_app, b_app[0], b_rec));
    assert_true(test_max_abs_diff(b_rec, b[0]) < 1e-12);

    /* non-uniform PL with a dark region (I = 0: no information there, the correction gives 0) */
    svp_image_free(pl);
    pl = pl_spot_chessboard(w, h, 5, 3);
    for (int y = 10; y < 20; y++)
        for (int x = 4; x < 14; x++) pl->data[(size_t)y * w + x] = 0;
    ASSERT_OK(svp_forward_transform(op, pl, (const svp_image *const *)b, 1, pl_app, b_app, NULL));
    ASSERT_OK(svp_halo_correct(alpha, pl_app, b_app[0], b_rec));
    double err = 0;
    for (size_t i = 0; i < n; i++) {
        if (pl->data[i] > 0)
            err = fmax(err, fabs(b_rec->data[i] - b[0]->data[i]));
        else
            assert_true(b_rec->data[i] == 0.0);
    }
    if (err > 1e-12) fail_msg("halo correction with non-uniform PL: error %.3g", err);
    /* Wiener at balance 0 inverts the halo exactly as well: the same answer through eq. (4) */
    svp_correct_options o = options_for(SVP_METHOD_W, 1, 0.0);
    svp_image *b_rec_w[1] = {test_image(w, h)}, *pl_rec = test_image(w, h);
    ASSERT_OK(svp_inverse_transform(op, pl_app, (const svp_image *const *)b_app, 1, &o, pl_rec,
                                    b_rec_w, NULL, NULL));
    double err_w = 0, pl_max = test_max_abs(pl);
    for (size_t i = 0; i < n; i++)
        if (pl->data[i] > o.pl_floor * pl_max)
            err_w = fmax(err_w, fabs(b_rec_w[0]->data[i] - b[0]->data[i]));
    if (err_w > 1e-10) fail_msg("T⁻¹ (W, balance 0) of a halo-only PSF: error %.3g", err_w);
    print_message("halo-only PSF: closed form error %.2g, T⁻¹ (W) error %.2g\n", err, err_w);
    /* in place: field_true may be field_apparent */
    ASSERT_OK(svp_halo_correct(alpha, pl_app, b_app[0], b_app[0]));
    assert_true(test_max_abs_diff(b_app[0], b_rec) < 1e-15);
    svp_blur_free(op);
    svp_image_free(pl);
    svp_image_free(pl_app);
    svp_image_free(b_rec);
    svp_image_free(pl_rec);
    free_images(b, 1);
    free_images(b_app, 1);
    free_images(b_rec_w, 1);
}

/* ---- helpers for the inverse ------------------------------------------------------------- */

typedef struct apparent {
    svp_image *pl, *field[NF], *valid;
} apparent;

static apparent forward_run(svp_blur *op, const svp_image *pl, svp_image *const *fields, int nf)
{
    apparent a = {0};
    a.pl = test_image(pl->width, pl->height);
    a.valid = test_image(pl->width, pl->height);
    for (int c = 0; c < nf; c++) a.field[c] = test_image(pl->width, pl->height);
    ASSERT_OK(svp_forward_transform(op, pl, (const svp_image *const *)fields, nf, a.pl, a.field,
                                    a.valid));
    return a;
}

static void apparent_free(apparent *a, int nf)
{
    svp_image_free(a->pl);
    svp_image_free(a->valid);
    free_images(a->field, nf);
}

typedef struct restored {
    svp_image *pl, *field[NF], *valid;
    size_t n_missing;
} restored;

/* T⁻¹ with the invariants every call must keep: finite outputs, validity in [0, 1], and the
 * last-resort repair never used. */
static restored inverse_run(svp_blur *op, const svp_image *pl_app, svp_image *const *b_app, int nf,
                            const svp_correct_options *o)
{
    const int w = pl_app->width, h = pl_app->height;
    restored r = {0};
    r.pl = test_image(w, h);
    r.valid = test_image(w, h);
    for (int c = 0; c < nf; c++) r.field[c] = test_image(w, h);
    size_t repaired = 99;
    ASSERT_OK(svp_inverse_transform_counted(op, pl_app, (const svp_image *const *)b_app, nf, o,
                                            r.pl, r.field, r.valid, &r.n_missing, &repaired));
    assert_int_equal(repaired, 0);
    assert_true(test_all_finite(r.pl) && test_all_finite(r.valid));
    for (int c = 0; c < nf; c++) assert_true(test_all_finite(r.field[c]));
    for (size_t i = 0; i < (size_t)w * h; i++)
        assert_true(r.valid->data[i] >= 0 && r.valid->data[i] <= 1);
    return r;
}

static void restored_free(restored *r, int nf)
{
    svp_image_free(r->pl);
    svp_image_free(r->valid);
    free_images(r->field, nf);
}

/* max |rec − truth| over pixels with pl > lit · max(pl) and skip[i] == 0 (skip may be NULL),
 * relative to max |truth| over all components */
static double lit_error(const svp_image *pl, svp_image *const *truth, svp_image *const *rec, int nf,
                        double lit, const unsigned char *skip)
{
    const size_t n = (size_t)pl->width * pl->height;
    double pl_max = test_max_abs(pl), b_max = 0, err = 0;
    for (int c = 0; c < nf; c++) b_max = fmax(b_max, test_max_abs(truth[c]));
    for (size_t i = 0; i < n; i++) {
        if (!(pl->data[i] > lit * pl_max) || (skip && skip[i])) continue;
        for (int c = 0; c < nf; c++) err = fmax(err, fabs(rec[c]->data[i] - truth[c]->data[i]));
    }
    return err / b_max;
}

static double gaussian(uint64_t *s)
{
    double u1 = test_rand(s), u2 = test_rand(s);
    return sqrt(-2.0 * log(1.0 - u1)) * cos(2 * M_PI * u2);
}

/* ---- round trip T⁻¹(T(B)), noiseless ------------------------------------------------------ */

/* Moffat β = 2.5, FWHM 3 px, mirror boundary, 64 x 64, PL = spot × chessboard (8 px squares,
 * levels 0.1 / 0.8 / 1.0), two signed smooth components. Max error in lit pixels (PL > 0.2 max)
 * relative to max |B|, measured:
 *   W  (balance 1e-6)              0.52 %
 *   R  (RL, 1000 iterations)       0.68 %  (RL_SIGNED: the same computation, identical output;
 *                                           200 it: 0.95 %, so 1000 is "converged" here)
 *   RW (1000 it, balance 1e-6)     18.9 %: RL and Wiener resolve the pixel-sharp chessboard
 *      edges differently, and the ratio (4) of two differently resolved maps is biased beside
 *      them (asserted < 30 %); on the resolvable spot-only PL RW gives 0.36 % (< 1 %).
 * Periodic boundary, periodic fields: W 0.77 % (R measured 0.96 % at 1000 it: too close to
 * the 1 % line to assert without more iterations). */
#define RT_RL_ITERATIONS 1000
static void test_round_trip(void **state)
{
    (void)state;
    const int w = 64, h = 64;
    svp_image *pl = pl_spot_chessboard(w, h, 8, 7);
    svp_image *b[NF] = {field_smooth(w, h, 0), field_smooth(w, h, 1)};
    svp_blur *op = blur_model(SVP_PSF_MOFFAT, 3.0, 2.5, 0.0, w, h, SVP_BOUNDARY_MIRROR);
    apparent a = forward_run(op, pl, b, NF);
    double err[4];
    restored r_prev = {0};
    for (int method = 0; method < 4; method++) {
        svp_correct_options o = options_for((svp_method)method, RT_RL_ITERATIONS, 1e-6);
        restored r = inverse_run(op, a.pl, a.field, NF, &o);
        err[method] = lit_error(pl, b, r.field, NF, 0.2, NULL);
        print_message("round trip mirror %-9s (RL %d it, balance 1e-6): lit error %.3g %% of "
                      "max|B|\n",
                      method_names[method], RT_RL_ITERATIONS, 100 * err[method]);
        for (size_t i = 0; i < (size_t)w * h; i++)
            if (pl->data[i] > 0.2 * test_max_abs(pl)) assert_true(r.valid->data[i] == 1.0);
        if (method == SVP_METHOD_RL_SIGNED) /* R is RL_SIGNED under another name */
            for (int c = 0; c < NF; c++)
                assert_true(test_max_abs_diff(r.field[c], r_prev.field[c]) == 0);
        if (method == SVP_METHOD_R)
            r_prev = r;
        else
            restored_free(&r, NF);
    }
    restored_free(&r_prev, NF);
    CHECK_BOUND(err[SVP_METHOD_W] < 0.01, "W: %.3g %% >= 1 %%", 100 * err[SVP_METHOD_W]);
    CHECK_BOUND(err[SVP_METHOD_R] < 0.01, "R: %.3g %% >= 1 %%", 100 * err[SVP_METHOD_R]);
    CHECK_BOUND(err[SVP_METHOD_RL_SIGNED] < 0.01, "RL_SIGNED: %.3g %% >= 1 %%",
                100 * err[SVP_METHOD_RL_SIGNED]);
    CHECK_BOUND(err[SVP_METHOD_RW] < 0.30, "RW: %.3g %% >= 30 %%", 100 * err[SVP_METHOD_RW]);
    apparent_free(&a, NF);

    /* RW on a PL the deconvolutions can resolve (the spot alone) */
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double r2 = (x - 31.5) * (x - 31.5) + (y - 31.5) * (y - 31.5), s = w / 2.35482;
            pl->data[(size_t)y * w + x] = exp(-0.5 * r2 / (s * s));
        }
    a = forward_run(op, pl, b, NF);
    svp_correct_options o = options_for(SVP_METHOD_RW, RT_RL_ITERATIONS, 1e-6);
    restored r = inverse_run(op, a.pl, a.field, NF, &o);
    double err_rw = lit_error(pl, b, r.field, NF, 0.2, NULL);
    print_message("round trip mirror RW on the spot-only PL: lit error %.3g %%\n", 100 * err_rw);
    CHECK_BOUND(err_rw < 0.01, "RW, spot-only PL: %.3g %% >= 1 %%", 100 * err_rw);
    restored_free(&r, NF);
    apparent_free(&a, NF);
    svp_blur_free(op);

    /* periodic boundary (periodic fields so the scene itself has no seam) */
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double u = (x + 0.5) / w, v = (y + 0.5) / h;
            b[0]->data[(size_t)y * w + x] = cos(2 * M_PI * u) * (1 + 0.5 * cos(2 * M_PI * v)) - 0.2;
            b[1]->data[(size_t)y * w + x] = 0.7 * sin(2 * M_PI * v) + 0.3 * cos(2 * M_PI * (u + v));
        }
    svp_image_free(pl);
    pl = pl_spot_chessboard(w, h, 8, 7);
    op = blur_model(SVP_PSF_MOFFAT, 3.0, 2.5, 0.0, w, h, SVP_BOUNDARY_PERIODIC);
    a = forward_run(op, pl, b, NF);
    o = options_for(SVP_METHOD_W, 1, 1e-6);
    r = inverse_run(op, a.pl, a.field, NF, &o);
    double err_periodic = lit_error(pl, b, r.field, NF, 0.2, NULL);
    print_message("round trip periodic W: lit error %.3g %%\n", 100 * err_periodic);
    CHECK_BOUND(err_periodic < 0.01, "periodic W: %.3g %% >= 1 %%", 100 * err_periodic);
    restored_free(&r, NF);
    apparent_free(&a, NF);
    svp_blur_free(op);
    svp_image_free(pl);
    free_images(b, NF);
}

/* The same round trip with the ZERO boundary (the default: light leaving the field is lost),
 * 64 x 64, PL = spot × chessboard, the two smooth signed components; Moffat FWHM 3 px with
 * β = 2.5 and with the long β = 1.1 tail (which, before W solved the zero-boundary problem
 * itself, put W's error above the field's peak). Max error in lit pixels (PL > 0.2 max)
 * relative to max |B|, measured:
 *   β = 2.5: W (balance 1e-6) 0.52 %, R (1000 it) 0.69 %, RW on the spot-only PL 0.15 %
 *   β = 1.1: W 0.65 %, R 2.3 %, RW on the spot-only PL 1.7 %
 * Asserted: < 1 % for the moderate β = 2.5 (the issue's case) and for W with β = 1.1; RL with
 * the β = 1.1 tail is < 3 %: with the zero boundary its corners converge slowly (RL alone on
 * the spot PL, corner error 0.48 % of the peak at 1000 it, 0.18 % at 4000, 0.05 % at 16000, so
 * it is convergence, not bias), and the field divides by the PL there. RW on the chessboard is
 * biased beside the edges as with the mirror boundary (test_round_trip): not asserted here. */
static void test_round_trip_zero(void **state)
{
    (void)state;
    const int w = 64, h = 64;
    const double betas[2] = {2.5, 1.1};
    svp_image *b[NF] = {field_smooth(w, h, 0), field_smooth(w, h, 1)};
    svp_image *chess = pl_spot_chessboard(w, h, 8, 7), *spot = test_image(w, h);
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double r2 = (x - 31.5) * (x - 31.5) + (y - 31.5) * (y - 31.5), s = w / 2.35482;
            spot->data[(size_t)y * w + x] = exp(-0.5 * r2 / (s * s));
        }
    for (int k = 0; k < 2; k++) {
        svp_blur *op = blur_model(SVP_PSF_MOFFAT, 3.0, betas[k], 0.0, w, h, SVP_BOUNDARY_ZERO);
        apparent a = forward_run(op, chess, b, NF);
        const svp_method methods[2] = {SVP_METHOD_W, SVP_METHOD_R};
        for (int m = 0; m < 2; m++) {
            svp_correct_options o = options_for(methods[m], RT_RL_ITERATIONS, 1e-6);
            restored r = inverse_run(op, a.pl, a.field, NF, &o);
            double err = lit_error(chess, b, r.field, NF, 0.2, NULL);
            print_message("round trip zero β %.1f %-2s (RL %d it, balance 1e-6): lit error %.3g "
                          "%% of max|B|\n",
                          betas[k], method_names[methods[m]], RT_RL_ITERATIONS, 100 * err);
            const double bound = methods[m] == SVP_METHOD_R && k == 1 ? 0.03 : 0.01;
            CHECK_BOUND(err < bound, "zero boundary β %.1f %s: %.3g %% >= %g %%", betas[k],
                        method_names[methods[m]], 100 * err, 100 * bound);
            restored_free(&r, NF);
        }
        apparent_free(&a, NF);
        a = forward_run(op, spot, b, NF);
        svp_correct_options o = options_for(SVP_METHOD_RW, RT_RL_ITERATIONS, 1e-6);
        restored r = inverse_run(op, a.pl, a.field, NF, &o);
        double err = lit_error(spot, b, r.field, NF, 0.2, NULL);
        print_message("round trip zero β %.1f RW on the spot-only PL: lit error %.3g %%\n",
                      betas[k], 100 * err);
        const double bound = k == 1 ? 0.03 : 0.01;
        CHECK_BOUND(err < bound, "zero boundary β %.1f RW, spot-only PL: %.3g %% >= %g %%",
                    betas[k], 100 * err, 100 * bound);
        restored_free(&r, NF);
        apparent_free(&a, NF);
        svp_blur_free(op);
    }
    svp_image_free(chess);
    svp_image_free(spot);
    free_images(b, NF);
}

/* Every component shares the one deconvolution of Ĩ: a component restored alongside another
 * is bit-identical to the same component restored alone. */
static void test_components_share_pl(void **state)
{
    (void)state;
    const int w = 40, h = 36;
    svp_blur *op = blur_model(SVP_PSF_MOFFAT, 2.5, 2.5, 0.0, w, h, SVP_BOUNDARY_MIRROR);
    svp_image *pl = pl_spot_chessboard(w, h, 6, 2);
    svp_image *b[NF] = {field_smooth(w, h, 0), field_smooth(w, h, 1)};
    apparent a = forward_run(op, pl, b, NF);
    for (int method = 0; method < 4; method++) {
        svp_correct_options o = options_for((svp_method)method, 30, 1e-3);
        restored both = inverse_run(op, a.pl, a.field, NF, &o);
        restored alone = inverse_run(op, a.pl, &a.field[1], 1, &o);
        assert_true(test_max_abs_diff(both.field[1], alone.field[0]) == 0);
        assert_true(test_max_abs_diff(both.pl, alone.pl) == 0);
        restored_free(&both, NF);
        restored_free(&alone, 1);
    }
    apparent_free(&a, NF);
    svp_blur_free(op);
    svp_image_free(pl);
    free_images(b, NF);
}

/* ---- hard cases: finite and flagged ------------------------------------------------------- */

/* PL exactly 0 over a 20 x 20 region, and PL at 1e-6 of its peak there (64 x 64, Moffat
 * β = 2.5, FWHM 3 px, mirror). Measured (validity deep inside the region: max / mean; lit
 * error away from it, % of max |B|):
 *   R, RW (RL on Ĩ, 300 it):   validity 0.0035 / 0.0013 (dark and faint alike)
 *   W (balance 1e-6):          validity 1 / 0.39 with the default pl_floor 1e-3: Wiener's
 *                              ringing lifts the recovered PL above that floor; with
 *                              pl_floor = 0.05 the region is flagged: 0.18 / 0.023.
 *   lit error away from the region: W 0.52 %, R 0.79 %, RW 26 % (see test_round_trip). */
static void test_dark_and_faint_regions(void **state)
{
    (void)state;
    const int w = 64, h = 64, x0 = 8, x1 = 28, y0 = 36, y1 = 56;
    svp_image *b[NF] = {field_smooth(w, h, 0), field_smooth(w, h, 1)};
    unsigned char *near = calloc((size_t)w * h, 1); /* within 4 px of the region */
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++)
            near[(size_t)y * w + x] = x >= x0 - 4 && x < x1 + 4 && y >= y0 - 4 && y < y1 + 4;
    for (int faint = 0; faint < 2; faint++) {
        svp_image *pl = pl_spot_chessboard(w, h, 8, 7);
        double peak = test_max_abs(pl);
        for (int y = y0; y < y1; y++)
            for (int x = x0; x < x1; x++) pl->data[(size_t)y * w + x] = faint ? 1e-6 * peak : 0.0;

        /* T with a Gaussian (FWHM 2 px): its tails underflow, so deep inside the dark region
         * Ĩ is round-off and T flags it (B̃ = 0, validity 0); the faint region is lit: there
         * B̃ = H B, the PL being uniform within reach. */
        svp_blur *op = blur_model(SVP_PSF_GAUSSIAN, 2.0, 0, 0.0, w, h, SVP_BOUNDARY_MIRROR);
        apparent a = forward_run(op, pl, b, NF);
        const size_t centre = (size_t)((y0 + y1) / 2) * w + (x0 + x1) / 2;
        if (!faint) {
            assert_true(a.valid->data[centre] == 0.0 && a.field[0]->data[centre] == 0.0);
        } else {
            svp_image *hb = test_image(w, h);
            ASSERT_OK(svp_blur_apply(op, b[0], hb));
            assert_true(a.valid->data[centre] == 1.0);
            ASSERT_CLOSE(a.field[0]->data[centre], hb->data[centre], 1e-8);
            svp_image_free(hb);
        }
        apparent_free(&a, NF);
        svp_blur_free(op);

        op = blur_model(SVP_PSF_MOFFAT, 3.0, 2.5, 0.0, w, h, SVP_BOUNDARY_MIRROR);
        a = forward_run(op, pl, b, NF);
        const svp_method methods[4] = {SVP_METHOD_R, SVP_METHOD_RW, SVP_METHOD_W, SVP_METHOD_W};
        for (int k = 0; k < 4; k++) {
            svp_correct_options o = options_for(methods[k], 300, 1e-6);
            if (k == 3) o.pl_floor = 0.05;
            /* the numerics of the hard case, not its verdict: W's ringing next to the region
             * is implausible (test_doubt_checks); kept, it loses its validity */
            o.keep_doubtful = 1;
            restored r = inverse_run(op, a.pl, a.field, NF, &o);
            double vmax = 0, vmean = 0;
            int count = 0;
            for (int y = y0 + 4; y < y1 - 4; y++)
                for (int x = x0 + 4; x < x1 - 4; x++) {
                    double v = r.valid->data[(size_t)y * w + x];
                    vmax = fmax(vmax, v);
                    vmean += v;
                    count++;
                }
            vmean /= count;
            double e = lit_error(pl, b, r.field, NF, 0.2, near);
            print_message("%s region, %-2s pl_floor %g: validity inside max %.3g mean %.3g; lit "
                          "error away from it %.3g %%\n",
                          faint ? "faint (1e-6)" : "dark (0)", method_names[methods[k]], o.pl_floor,
                          vmax, vmean, 100 * e);
            if (methods[k] != SVP_METHOD_W)
                CHECK_BOUND(vmax < 0.01, "%s: validity inside %.3g", method_names[methods[k]],
                            vmax);
            if (k == 3) CHECK_BOUND(vmean < 0.1, "W, pl_floor 0.05: validity inside %.3g", vmean);
            CHECK_BOUND(e < (methods[k] == SVP_METHOD_RW ? 0.4 : 0.015), "%s: lit error %.3g %%",
                        method_names[methods[k]], 100 * e);
            restored_free(&r, NF);
        }
        apparent_free(&a, NF);
        svp_blur_free(op);
        svp_image_free(pl);
    }
    free(near);
    free_images(b, NF);
}

/* Lorentzian and Moffat β = 0.9, FWHM 3 px, with the default full-field support: the kernels
 * are (2w − 1) x (2h − 1), wider than the 48 x 40 image; zero boundary. Outputs stay finite
 * with validity in [0, 1]. Max error in lit pixels, % of max |B|, measured (Lorentzian /
 * Moffat β 0.9):
 *                      interior (>= 10 px from the border)   all lit pixels
 *   R  (300 it)        7.6 / 14.1                           11.8 / 25.2
 *   W  (balance 1e-6)  0.63 / 0.59                          1.06 / 1.14
 *   RW                 31 / 33                              34 / 35
 * W solves the zero-boundary problem itself (restore/wiener.c: CG on the linear operator's
 * normal equations), so it is as good as with the mirror boundary (1.5 % / 2.0 % there). Before
 * that it filtered in a mirror frame that does not model the light these tails carry out of the
 * image and was off by 5e4 % at the border. R converges slowly with these tails (300 it) and
 * RW's two deconvolutions resolve the chessboard differently: both carry that bias.
 * Asserted: R interior < 25 %, all < 40 %; W all < 3 %; mirror W < 5 %. */
static void test_wide_kernels(void **state)
{
    (void)state;
    const int w = 48, h = 40;
    svp_image *pl = pl_spot_chessboard(w, h, 8, 11);
    svp_image *b[NF] = {field_smooth(w, h, 0), field_smooth(w, h, 1)};
    unsigned char *border = calloc((size_t)w * h, 1);
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++)
            border[(size_t)y * w + x] = x < 10 || y < 10 || x >= w - 10 || y >= h - 10;
    const svp_psf_model models[2] = {SVP_PSF_LORENTZIAN, SVP_PSF_MOFFAT};
    for (int k = 0; k < 2; k++) {
        svp_blur *op = blur_model(models[k], 3.0, 0.9, 0.0, w, h, SVP_BOUNDARY_ZERO);
        apparent a = forward_run(op, pl, b, NF);
        const svp_method methods[3] = {SVP_METHOD_R, SVP_METHOD_W, SVP_METHOD_RW};
        for (int m = 0; m < 3; m++) {
            svp_correct_options o = options_for(methods[m], 300, 1e-6);
            restored r = inverse_run(op, a.pl, a.field, NF, &o);
            double e_in = lit_error(pl, b, r.field, NF, 0.2, border);
            double e_all = lit_error(pl, b, r.field, NF, 0.2, NULL);
            print_message("%s, zero boundary, %-2s: lit error interior %.3g %%, all %.3g %%\n",
                          k == 0 ? "Lorentzian  " : "Moffat β 0.9", method_names[methods[m]],
                          100 * e_in, 100 * e_all);
            if (methods[m] == SVP_METHOD_R)
                CHECK_BOUND(e_in < 0.25 && e_all < 0.4, "R: lit error %.3g %% / %.3g %%",
                            100 * e_in, 100 * e_all);
            if (methods[m] == SVP_METHOD_W)
                CHECK_BOUND(e_all < 0.03, "W: lit error %.3g %%", 100 * e_all);
            restored_free(&r, NF);
        }
        apparent_free(&a, NF);
        svp_blur_free(op);
        /* the same kernel with the mirror boundary: W everywhere */
        op = blur_model(models[k], 3.0, 0.9, 0.0, w, h, SVP_BOUNDARY_MIRROR);
        a = forward_run(op, pl, b, NF);
        svp_correct_options o = options_for(SVP_METHOD_W, 1, 1e-6);
        restored r = inverse_run(op, a.pl, a.field, NF, &o);
        double e = lit_error(pl, b, r.field, NF, 0.2, NULL);
        print_message("%s, mirror boundary, W : lit error %.3g %%\n",
                      k == 0 ? "Lorentzian  " : "Moffat β 0.9", 100 * e);
        CHECK_BOUND(e < 0.05, "mirror W: lit error %.3g %%", 100 * e);
        restored_free(&r, NF);
        apparent_free(&a, NF);
        svp_blur_free(op);
    }
    free(border);
    svp_image_free(pl);
    free_images(b, NF);
}

/* 1 x 1 (the kernel is one pixel: T and T⁻¹ are the identity), 2 x 3, 509 x 311 (W only). */
static void test_sizes(void **state)
{
    (void)state;
    /* 1 x 1 */
    svp_blur *op = blur_model(SVP_PSF_MOFFAT, 3.0, 2.5, 0.0, 1, 1, SVP_BOUNDARY_ZERO);
    svp_image *pl = test_image(1, 1), *b[NF] = {test_image(1, 1), test_image(1, 1)};
    pl->data[0] = 2.0;
    b[0]->data[0] = -0.75;
    b[1]->data[0] = 1e-3;
    apparent a = forward_run(op, pl, b, NF);
    for (int method = 0; method < 4; method++) {
        svp_correct_options o = options_for((svp_method)method, 10, 1e-3);
        restored r = inverse_run(op, a.pl, a.field, NF, &o);
        for (int c = 0; c < NF; c++) ASSERT_CLOSE(r.field[c]->data[0], b[c]->data[0], 1e-12);
        ASSERT_CLOSE(r.valid->data[0], 1.0, 0);
        restored_free(&r, NF);
    }
    apparent_free(&a, NF);
    svp_blur_free(op);
    svp_image_free(pl);
    free_images(b, NF);

    /* 2 x 3: W at balance 0 is the exact inverse with the periodic and with the zero boundary
     * (measured 1.2e-15 both); every method stays finite (errors printed: RL on the 6-pixel
     * problem is badly conditioned) */
    for (int m = 0; m < 2; m++) {
        svp_boundary boundary = m == 0 ? SVP_BOUNDARY_PERIODIC : SVP_BOUNDARY_ZERO;
        op = blur_model(SVP_PSF_GAUSSIAN, 1.5, 0, 0.0, 2, 3, boundary);
        pl = test_random_image(2, 3, 4);
        for (int i = 0; i < 6; i++) pl->data[i] += 0.5;
        b[0] = test_random_image(2, 3, 5);
        b[1] = test_random_image(2, 3, 6);
        for (int i = 0; i < 6; i++) b[1]->data[i] -= 0.5;
        a = forward_run(op, pl, b, NF);
        for (int method = 0; method < 4; method++) {
            svp_correct_options o = options_for((svp_method)method, 500, 0.0);
            restored r = inverse_run(op, a.pl, a.field, NF, &o);
            double e = lit_error(pl, b, r.field, NF, 0.0, NULL);
            print_message("2 x 3 %s, %-9s: error %.3g %%\n", m == 0 ? "periodic" : "zero    ",
                          method_names[method], 100 * e);
            if (method == SVP_METHOD_W)
                CHECK_BOUND(e < 1e-9, "2 x 3 %s W: error %.3g", m == 0 ? "periodic" : "zero", e);
            restored_free(&r, NF);
        }
        apparent_free(&a, NF);
        svp_blur_free(op);
        svp_image_free(pl);
        free_images(b, NF);
    }

    /* 509 x 311, W */
    const int w = 509, h = 311;
    op = blur_model(SVP_PSF_MOFFAT, 3.0, 2.5, 0.0, w, h, SVP_BOUNDARY_MIRROR);
    pl = pl_spot_chessboard(w, h, 16, 9);
    b[0] = field_smooth(w, h, 0);
    b[1] = field_smooth(w, h, 1);
    a = forward_run(op, pl, b, NF);
    svp_correct_options o = options_for(SVP_METHOD_W, 1, 1e-6);
    restored r = inverse_run(op, a.pl, a.field, NF, &o);
    double e = lit_error(pl, b, r.field, NF, 0.2, NULL);
    print_message("509 x 311, W: lit error %.3g %%\n", 100 * e);
    CHECK_BOUND(e < 0.01, "509 x 311 W: lit error %.3g %%", 100 * e);
    restored_free(&r, NF);
    apparent_free(&a, NF);
    svp_blur_free(op);
    svp_image_free(pl);
    free_images(b, NF);
}

/* Poisson noise on the PL at peak SNR 10 (100 counts at the brightest pixel) and Gaussian
 * field noise ∝ 1/√PL, SNR 10 at that pixel (64 x 64, Moffat β 2.5, FWHM 3, mirror; seeded).
 * Measured in lit pixels, % of max |B| (the apparent map B̃ itself: RMS 13.7 %):
 *   RW (15 it, balance 1)   RMS 6.7   max 58
 *   W  (balance 1)          RMS 3.9   max 21
 *   R  (15 it)              RMS 12.4  max 69: the automatic shift c is set by the noisiest
 *       dim pixels (c ≈ 5 max |B|) and RL of (B̃ + c)Ĩ carries c times the PL noise.
 * Bounds asserted: RW, W RMS < 10 %, max < 80 %; R RMS < 20 %, max < 100 %. */
static void test_poisson_noise(void **state)
{
    (void)state;
    const int w = 64, h = 64;
    const size_t n = (size_t)w * h;
    const double peak_counts = 100;
    svp_image *pl = pl_spot_chessboard(w, h, 8, 7);
    svp_image *b[NF] = {field_smooth(w, h, 0), field_smooth(w, h, 1)};
    svp_blur *op = blur_model(SVP_PSF_MOFFAT, 3.0, 2.5, 0.0, w, h, SVP_BOUNDARY_MIRROR);
    apparent a = forward_run(op, pl, b, NF);
    double pl_max = test_max_abs(a.pl), b_max = fmax(test_max_abs(b[0]), test_max_abs(b[1]));
    uint64_t s = 12345;
    for (size_t i = 0; i < n; i++) {
        double counts = poisson(&s, peak_counts * a.pl->data[i] / pl_max);
        double sigma_b = 0.1 * b_max * sqrt(pl_max / fmax(a.pl->data[i], 1e-3 * pl_max));
        for (int c = 0; c < NF; c++) a.field[c]->data[i] += sigma_b * gaussian(&s);
        a.pl->data[i] = counts * pl_max / peak_counts;
    }
    const svp_method methods[3] = {SVP_METHOD_RW, SVP_METHOD_W, SVP_METHOD_R};
    const int iterations[3] = {15, 1, 15};
    const double bound_rms[3] = {0.10, 0.10, 0.20}, bound_max[3] = {0.8, 0.8, 1.0};
    const double pmax = test_max_abs(pl);
    for (int k = 0; k < 3; k++) {
        svp_correct_options o = options_for(methods[k], iterations[k], 1.0);
        restored r = inverse_run(op, a.pl, a.field, NF, &o);
        double rms = 0, rms_app = 0;
        int count = 0;
        for (size_t i = 0; i < n; i++) {
            if (!(pl->data[i] > 0.2 * pmax)) continue;
            for (int c = 0; c < NF; c++) {
                double d = r.field[c]->data[i] - b[c]->data[i];
                double d_app = a.field[c]->data[i] - b[c]->data[i];
                rms += d * d;
                rms_app += d_app * d_app;
                count++;
            }
        }
        rms = sqrt(rms / count) / b_max;
        rms_app = sqrt(rms_app / count) / b_max;
        double e = lit_error(pl, b, r.field, NF, 0.2, NULL);
        print_message("Poisson PL (peak SNR 10) + field noise, %-2s (%d it, balance 1): lit RMS "
                      "error %.3g %% (apparent map %.3g %%), max %.3g %%\n",
                      method_names[methods[k]], iterations[k], 100 * rms, 100 * rms_app, 100 * e);
        CHECK_BOUND(rms < bound_rms[k] && e < bound_max[k],
                    "%s: RMS %.3g %%, max %.3g %% above the stated bounds",
                    method_names[methods[k]], 100 * rms, 100 * e);
        restored_free(&r, NF);
    }
    apparent_free(&a, NF);
    svp_blur_free(op);
    svp_image_free(pl);
    free_images(b, NF);
}

/* Constant inputs give the constant back: W and R exactly (linearity; scale invariance of RL),
 * RW too where its two deconvolutions agree on the boundary (mirror, periodic: measured
 * <= 3.3e-15); an all-zero PL gives zeros and validity 0. */
static void test_constant_images(void **state)
{
    (void)state;
    const int w = 32, h = 32;
    const size_t n = (size_t)w * h;
    svp_image *pl = test_image(w, h), *b[NF] = {test_image(w, h), test_image(w, h)};
    for (size_t i = 0; i < n; i++) {
        pl->data[i] = 5.0;
        b[0]->data[i] = 2.5;
        b[1]->data[i] = -1.5;
    }
    for (int m = 0; m < 3; m++) {
        svp_blur *op = blur_model(SVP_PSF_MOFFAT, 3.0, 2.5, 0.0, w, h, (svp_boundary)m);
        for (int method = 0; method < 4; method++) {
            svp_correct_options o = options_for((svp_method)method, 50, 1e-3);
            restored r = inverse_run(op, pl, b, NF, &o);
            double err = 0;
            for (int c = 0; c < NF; c++)
                for (size_t i = 0; i < n; i++)
                    err = fmax(err, fabs(r.field[c]->data[i] - b[c]->data[0]));
            print_message("constant maps, boundary %d, %-9s: error %.3g\n", m, method_names[method],
                          err);
            /* RW with the zero boundary: not asserted. A constant apparent map is not T of a
             * constant when light leaves the image (the true PL is brighter at the border): W
             * solves that problem, 50 RL iterations have not yet reached the corners, and the
             * ratio of the two is off there (measured 1.72 for b = 2.5). */
            if (!(method == SVP_METHOD_RW && m == SVP_BOUNDARY_ZERO))
                CHECK_BOUND(err < 1e-9, "constant maps %s boundary %d: error %.3g",
                            method_names[method], m, err);
            restored_free(&r, NF);
        }
        svp_blur_free(op);
    }
    /* no light at all: nothing to restore, refused by every method (it returned a field of 0
     * with validity 0 everywhere, exit 0, as does an offset above every value) */
    memset(pl->data, 0, n * sizeof(double));
    svp_blur *op = blur_model(SVP_PSF_MOFFAT, 3.0, 2.5, 0.0, w, h, SVP_BOUNDARY_ZERO);
    svp_image *out_pl = test_image(w, h), *out_b[NF] = {test_image(w, h), test_image(w, h)};
    for (int method = 0; method < 4; method++) {
        svp_correct_options o = options_for((svp_method)method, 20, 1e-3);
        assert_int_equal(svp_inverse_transform(op, pl, (const svp_image *const *)b, NF, &o,
                                               out_pl, out_b, NULL, NULL),
                         SVP_ERR_INVALID);
        assert_non_null(strstr(svp_last_error(), "pl_apparent holds no light: its largest "
                                                 "measured value is 0: nothing to restore"));
    }
    svp_image_free(out_pl);
    free_images(out_b, NF);
    /* T of an all-dark PL is refused as T⁻¹'s is: the apparent field would be undefined (0 with
     * validity 0) at every pixel; one faint pixel is light */
    {
        svp_image *pa = test_image(w, h), *fa[NF] = {test_image(w, h), test_image(w, h)};
        assert_int_equal(svp_forward_transform(op, pl, (const svp_image *const *)b, NF, pa, fa,
                                               NULL),
                         SVP_ERR_INVALID);
        assert_non_null(strstr(svp_last_error(), "pl_true holds no light (0 at every pixel)"));
        pl->data[w + 1] = 1e-300;
        apparent a = forward_run(op, pl, b, NF);
        assert_true(a.valid->data[w + 1] == 1);
        apparent_free(&a, NF);
        svp_image_free(pa);
        free_images(fa, NF);
    }
    svp_blur_free(op);
    svp_image_free(pl);
    free_images(b, NF);
}

/* NaN and Inf input pixels are missing data: counted, never smeared, outputs finite; validity
 * 0 only where no measured pixel sees the missing one (64 x 64, Gaussian FWHM 2, mirror; 5
 * isolated pixels and a 14 x 14 hole). Measured (% of max |B|): at the isolated pixels W 0.091,
 * R 0.074, RW 2.5 (validity >= 0.78 there); >= 5 px from any missing pixel W 0.37, R 0.33,
 * RW 7.8; the hole centre has validity 0. Asserted: 2 % / 1 % (RW 6 % / 15 %). */
static void test_missing_pixels(void **state)
{
    (void)state;
    const int w = 64, h = 64;
    const size_t n = (size_t)w * h;
    svp_image *pl = pl_spot_chessboard(w, h, 8, 7);
    for (size_t i = 0; i < n; i++) pl->data[i] = 0.3 + 0.7 * pl->data[i]; /* lit everywhere */
    svp_image *b[NF] = {field_smooth(w, h, 0), field_smooth(w, h, 1)};
    svp_blur *op = blur_model(SVP_PSF_GAUSSIAN, 2.0, 0, 0.0, w, h, SVP_BOUNDARY_MIRROR);
    apparent a = forward_run(op, pl, b, NF);
    /* isolated pixels: NaN and Inf in the fields, NaN and −Inf in the PL */
    const int iso[5][2] = {{10, 10}, {40, 20}, {30, 45}, {50, 8}, {20, 30}};
    a.field[0]->data[10 * w + 10] = NAN;
    a.field[0]->data[20 * w + 40] = NAN;
    a.field[1]->data[45 * w + 30] = INFINITY;
    a.pl->data[8 * w + 50] = NAN;
    a.pl->data[30 * w + 20] = -INFINITY;
    /* a 14 x 14 hole of failed fits (all components) */
    unsigned char *skip = calloc(n, 1);
    for (int y = 36; y < 50; y++)
        for (int x = 40; x < 54; x++) {
            a.field[0]->data[(size_t)y * w + x] = NAN;
            a.field[1]->data[(size_t)y * w + x] = NAN;
        }
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            int near = x >= 40 - 4 && x < 54 + 4 && y >= 36 - 4 && y < 50 + 4;
            for (int k = 0; k < 5; k++) near |= abs(x - iso[k][0]) <= 4 && abs(y - iso[k][1]) <= 4;
            skip[(size_t)y * w + x] = (unsigned char)near;
        }
    const size_t hole_centre = 43 * w + 47;
    const svp_method methods[3] = {SVP_METHOD_W, SVP_METHOD_R, SVP_METHOD_RW};
    for (int k = 0; k < 3; k++) {
        svp_correct_options o = options_for(methods[k], 300, 1e-6);
        restored r = inverse_run(op, a.pl, a.field, NF, &o);
        assert_int_equal(r.n_missing, 5 + 14 * 14);
        assert_true(r.valid->data[hole_centre] == 0.0);
        double err_iso = 0, v_iso = 1;
        for (int i = 0; i < 5; i++) {
            size_t at = (size_t)iso[i][1] * w + iso[i][0];
            v_iso = fmin(v_iso, r.valid->data[at]);
            for (int c = 0; c < NF; c++)
                err_iso = fmax(err_iso, fabs(r.field[c]->data[at] - b[c]->data[at]));
        }
        double b_max = fmax(test_max_abs(b[0]), test_max_abs(b[1]));
        double e = lit_error(pl, b, r.field, NF, 0.0, skip);
        print_message("missing pixels, %-2s: n_missing %zu; isolated: validity >= %.3g, error "
                      "%.3g %%; hole centre validity %g; error away from them %.3g %%\n",
                      method_names[methods[k]], r.n_missing, v_iso, 100 * err_iso / b_max,
                      r.valid->data[hole_centre], 100 * e);
        CHECK_BOUND(v_iso > 0.3, "isolated validity %.3g", v_iso);
        const double bound_iso = methods[k] == SVP_METHOD_RW ? 0.06 : 0.02;
        const double bound_rest = methods[k] == SVP_METHOD_RW ? 0.15 : 0.01;
        CHECK_BOUND(err_iso / b_max < bound_iso && e < bound_rest,
                    "%s: isolated %.3g %%, elsewhere %.3g %%", method_names[methods[k]],
                    100 * err_iso / b_max, 100 * e);
        restored_free(&r, NF);
    }
    /* A constant field with holes and a non-uniform PL: numerator and denominator see the
     * same measurements, so W and R return the constant, holes included, wherever validity
     * is > 0 (measured relative error W 8.5e-9, R 5.1e-8: round-off through the iterations;
     * R reaches 7e-5 at the uncovered hole centre, where validity is 0). */
    for (size_t i = 0; i < n; i++) {
        a.field[0]->data[i] = isfinite(a.field[0]->data[i]) ? 0.625 : NAN;
        a.field[1]->data[i] = isfinite(a.field[1]->data[i]) ? -3.0 : INFINITY;
    }
    for (int k = 0; k < 2; k++) {
        svp_correct_options o = options_for(methods[k], 100, 1e-4);
        restored r = inverse_run(op, a.pl, a.field, NF, &o);
        double err = 0, err_flagged = 0;
        for (size_t i = 0; i < n; i++) {
            double e =
                fmax(fabs(r.field[0]->data[i] / 0.625 - 1), fabs(r.field[1]->data[i] / -3.0 - 1));
            /* hole pixels whose coverage is ~1e-8 (validity) carry no information: the
             * automatic shift's round-off reaches 1e-6 there */
            if (r.valid->data[i] > 1e-6)
                err = fmax(err, e);
            else
                err_flagged = fmax(err_flagged, e);
        }
        print_message("constant field with holes, %-2s: max relative error %.3g (%.3g where "
                      "validity is 0)\n",
                      method_names[methods[k]], err, err_flagged);
        CHECK_BOUND(err < 1e-6, "constant field with holes, %s: relative error %.3g",
                    method_names[methods[k]], err);
        restored_free(&r, NF);
    }
    apparent_free(&a, NF);
    svp_blur_free(op);

    /* δ PSF: nothing covers a missing pixel, so its validity is exactly 0 */
    op = blur_delta(w, h, SVP_BOUNDARY_ZERO);
    a = forward_run(op, pl, b, NF);
    a.field[1]->data[5 * w + 7] = NAN;
    svp_correct_options o = options_for(SVP_METHOD_W, 1, 0.0);
    restored r = inverse_run(op, a.pl, a.field, NF, &o);
    assert_int_equal(r.n_missing, 1);
    assert_true(r.valid->data[5 * w + 7] == 0.0 && r.valid->data[5 * w + 8] == 1.0);
    restored_free(&r, NF);
    apparent_free(&a, NF);
    svp_blur_free(op);
    free(skip);
    svp_image_free(pl);
    free_images(b, NF);
}

/* A field spanning 1e-6 .. 1e6 (dynamic range 1e12; 64 x 64, Moffat β 2.5, FWHM 3, mirror):
 * finite output, bounded relative error on the large values (lit pixels with B > 1e3).
 * Measured: W (balance 1e-6) 7.4 %, R (1000 it) 9.3 %, RW 25 %; asserted 15 % (RW 50 %). The
 * field changes by a factor ~1.6 per pixel on its slopes, which no deconvolution resolves. */
static void test_dynamic_range(void **state)
{
    (void)state;
    const int w = 64, h = 64;
    const size_t n = (size_t)w * h;
    svp_image *pl = pl_spot_chessboard(w, h, 8, 7);
    svp_image *b[1] = {test_image(w, h)};
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double u = (x + 0.5) / w, v = (y + 0.5) / h;
            double s = 0.5 * (1 - cos(M_PI * u)) * (0.75 + 0.25 * cos(M_PI * v)); /* 0 .. 1 */
            b[0]->data[(size_t)y * w + x] = pow(10.0, -6 + 12 * s / 1.0);
        }
    double lo = INFINITY, hi = 0;
    for (size_t i = 0; i < n; i++) {
        lo = fmin(lo, b[0]->data[i]);
        hi = fmax(hi, b[0]->data[i]);
    }
    assert_true(hi / lo > 1e11);
    svp_blur *op = blur_model(SVP_PSF_MOFFAT, 3.0, 2.5, 0.0, w, h, SVP_BOUNDARY_MIRROR);
    apparent a = forward_run(op, pl, b, 1);
    const svp_method methods[3] = {SVP_METHOD_W, SVP_METHOD_R, SVP_METHOD_RW};
    for (int k = 0; k < 3; k++) {
        svp_correct_options o = options_for(methods[k], 1000, 1e-6);
        restored r = inverse_run(op, a.pl, a.field, 1, &o);
        double rel = 0, pmax = test_max_abs(pl);
        for (size_t i = 0; i < n; i++)
            if (b[0]->data[i] > 1e3 && pl->data[i] > 0.2 * pmax)
                rel = fmax(rel, fabs(r.field[0]->data[i] / b[0]->data[i] - 1));
        print_message("dynamic range 1e12, %-2s: max relative error on lit values > 1e3: "
                      "%.3g\n",
                      method_names[methods[k]], rel);
        CHECK_BOUND(rel < (methods[k] == SVP_METHOD_RW ? 0.5 : 0.15), "%s: relative error %.3g",
                    method_names[methods[k]], rel);
        restored_free(&r, 1);
    }
    apparent_free(&a, 1);
    svp_blur_free(op);
    svp_image_free(pl);
    free_images(b, 1);
}

/* The maps' units do not matter: PL and field times 2^±520 (double) or 2^±100 (single
 * precision, beyond float's range) give the same apparent maps times the same powers, bit for
 * bit, and finite (a PL and a field of 1e160, or of 1e20 in single precision, gave NaN fields
 * of validity 1; a PL of 1e36 in single precision a PL of 0) */
static void test_forward_scale(void **state)
{
    (void)state;
    const int w = 48, h = 40;
    const size_t n = (size_t)w * h;
    svp_image *pl = pl_spot_chessboard(w, h, 8, 7), *b[1] = {test_image(w, h)};
    for (size_t i = 0; i < n; i++) b[0]->data[i] = sin(0.37 * (double)i) - 0.2;
    svp_image *ps = test_image(w, h), *bs[1] = {test_image(w, h)};
    for (int single = 0; single <= 1; single++) {
        svp_blur *op = blur_model(SVP_PSF_MOFFAT, 3.0, 1.5, 0.0, w, h, SVP_BOUNDARY_ZERO);
        ASSERT_OK(svp_blur_set_precision(op, single));
        apparent ref = forward_run(op, pl, b, 1);
        const int e = single ? 100 : 520; /* 2^1040: B I overflows double */
        for (int ei = -e; ei <= e; ei += e)
            for (int eb = -e; eb <= e; eb += 2 * e) {
                for (size_t i = 0; i < n; i++) {
                    ps->data[i] = ldexp(pl->data[i], ei);
                    bs[0]->data[i] = ldexp(b[0]->data[i], eb);
                }
                apparent a = forward_run(op, ps, bs, 1);
                for (size_t i = 0; i < n; i++) {
                    assert_true(a.pl->data[i] == ldexp(ref.pl->data[i], ei));
                    assert_true(a.field[0]->data[i] == ldexp(ref.field[0]->data[i], eb));
                    assert_true(a.valid->data[i] == ref.valid->data[i]);
                }
                apparent_free(&a, 1);
            }
        apparent_free(&ref, 1);
        svp_blur_free(op);
    }
    svp_image_free(ps);
    free_images(bs, 1);
    svp_image_free(pl);
    free_images(b, 1);
}

/* ---- bad input ---------------------------------------------------------------------------- */

static void expect_error(svp_status got, svp_status want, const char *needle)
{
    if (got != want)
        fail_msg("status %d (%s), expected %d; message: %s", got, svp_status_string(got), want,
                 svp_last_error());
    if (needle && !strstr(svp_last_error(), needle))
        fail_msg("message \"%s\" does not name \"%s\"", svp_last_error(), needle);
}

static void test_bad_input(void **state)
{
    (void)state;
    const int w = 16, h = 12;
    svp_blur *op = blur_model(SVP_PSF_GAUSSIAN, 2.0, 0, 0.0, w, h, SVP_BOUNDARY_ZERO);
    svp_image *pl = pl_spot_chessboard(w, h, 4, 1), *pl_out = test_image(w, h);
    svp_image *b[NF] = {field_smooth(w, h, 0), field_smooth(w, h, 1)};
    svp_image *out[NF] = {test_image(w, h), test_image(w, h)};
    svp_image *wrong = test_image(w + 1, h), *valid = test_image(w, h);
    svp_correct_options o;
    svp_correct_defaults(&o);
    const svp_image *const *bc = (const svp_image *const *)b;

    /* size mismatch between a field and the PL: both named */
    svp_image *b_bad[NF] = {b[0], wrong};
    svp_status st = svp_inverse_transform(op, pl, (const svp_image *const *)b_bad, NF, &o, pl_out,
                                          out, valid, NULL);
    expect_error(st, SVP_ERR_SIZE, "field_apparent[1]");
    expect_error(st, SVP_ERR_SIZE, "pl_apparent");
    st = svp_forward_transform(op, pl, (const svp_image *const *)b_bad, NF, pl_out, out, NULL);
    expect_error(st, SVP_ERR_SIZE, "field_true[1]");
    expect_error(st, SVP_ERR_SIZE, "pl_true");
    /* PL of the wrong size for the operator */
    expect_error(svp_inverse_transform(op, wrong, bc, NF, &o, pl_out, out, valid, NULL),
                 SVP_ERR_SIZE, "blur operator");
    /* an output of the wrong size */
    svp_image *out_bad[NF] = {out[0], wrong};
    expect_error(svp_inverse_transform(op, pl, bc, NF, &o, pl_out, out_bad, valid, NULL),
                 SVP_ERR_SIZE, "field_true[1]");
    /* n_fields < 1, NULL */
    expect_error(svp_inverse_transform(op, pl, bc, 0, &o, pl_out, out, valid, NULL),
                 SVP_ERR_INVALID, "n_fields");
    expect_error(svp_forward_transform(op, pl, bc, -1, pl_out, out, NULL), SVP_ERR_INVALID,
                 "n_fields");
    expect_error(svp_inverse_transform(NULL, pl, bc, NF, &o, pl_out, out, valid, NULL),
                 SVP_ERR_INVALID, "blur operator");
    expect_error(svp_inverse_transform(op, NULL, bc, NF, &o, pl_out, out, valid, NULL),
                 SVP_ERR_INVALID, "pl_apparent");
    expect_error(svp_inverse_transform(op, pl, NULL, NF, &o, pl_out, out, valid, NULL),
                 SVP_ERR_INVALID, "field_apparent");
    svp_image *b_null[NF] = {b[0], NULL};
    expect_error(svp_inverse_transform(op, pl, (const svp_image *const *)b_null, NF, &o, pl_out,
                                       out, valid, NULL),
                 SVP_ERR_INVALID, "field_apparent[1]");
    expect_error(svp_forward_transform(op, pl, bc, NF, NULL, out, NULL), SVP_ERR_INVALID,
                 "pl_apparent");
    /* options */
    o.pl_floor = -1e-3;
    expect_error(svp_inverse_transform(op, pl, bc, NF, &o, pl_out, out, valid, NULL),
                 SVP_ERR_INVALID, "pl_floor");
    o.pl_floor = 0;
    expect_error(svp_inverse_transform(op, pl, bc, NF, &o, pl_out, out, valid, NULL),
                 SVP_ERR_INVALID, "pl_floor");
    svp_correct_defaults(&o);
    o.method = (svp_method)7;
    expect_error(svp_inverse_transform(op, pl, bc, NF, &o, pl_out, out, valid, NULL),
                 SVP_ERR_INVALID, "method");
    svp_correct_defaults(&o);
    o.deconv.iterations = 0;
    expect_error(svp_inverse_transform(op, pl, bc, NF, &o, pl_out, out, valid, NULL),
                 SVP_ERR_INVALID, "iterations");
    svp_correct_defaults(&o);
    o.method = SVP_METHOD_W;
    o.deconv.balance = -1;
    expect_error(svp_inverse_transform(op, pl, bc, NF, &o, pl_out, out, valid, NULL),
                 SVP_ERR_INVALID, "balance");
    /* a shift that leaves B̃ + c <= 0 */
    svp_correct_defaults(&o);
    o.method = SVP_METHOD_RL_SIGNED;
    o.shift = 0.1; /* field_smooth(0) reaches −0.2 − ... < −0.1 */
    expect_error(svp_inverse_transform(op, pl, bc, NF, &o, pl_out, out, valid, NULL),
                 SVP_ERR_INVALID, "field_apparent[0]");
    assert_non_null(strstr(svp_last_error(), "at pixel (x "));
    /* the caller's names for the maps (the CLI passes the files) */
    const char *names[NF];
    for (int c = 0; c < NF; c++) names[c] = c == 0 ? "Bz.tif" : "other.tif";
    o.field_names = names;
    expect_error(svp_inverse_transform(op, pl, bc, NF, &o, pl_out, out, valid, NULL),
                 SVP_ERR_INVALID, "Bz.tif: the shift c = 0.1");
    /* negative PL: T needs intensities; RL methods in T⁻¹ too (W accepts it) */
    svp_correct_defaults(&o);
    pl->data[5] = -0.25;
    expect_error(svp_forward_transform(op, pl, bc, NF, pl_out, out, NULL), SVP_ERR_INVALID,
                 "pl_true is negative");
    expect_error(svp_inverse_transform(op, pl, bc, NF, &o, pl_out, out, valid, NULL),
                 SVP_ERR_INVALID, "pl_apparent is negative");
    o.method = SVP_METHOD_W;
    ASSERT_OK(svp_inverse_transform(op, pl, bc, NF, &o, pl_out, out, valid, NULL));
    pl->data[5] = 0.25;
    /* NaN in the true maps of T: the input is named */
    b[1]->data[3] = NAN;
    expect_error(svp_forward_transform(op, pl, bc, NF, pl_out, out, NULL), SVP_ERR_INVALID,
                 "field_true[1]");
    b[1]->data[3] = 0.5;
    pl->data[7] = INFINITY;
    expect_error(svp_forward_transform(op, pl, bc, NF, pl_out, out, NULL), SVP_ERR_INVALID,
                 "pl_true");
    pl->data[7] = 0.5;
    /* everything missing */
    svp_image *all_nan = test_image(w, h);
    for (size_t i = 0; i < (size_t)w * h; i++) all_nan->data[i] = NAN;
    expect_error(svp_inverse_transform(op, all_nan, bc, NF, &o, pl_out, out, valid, NULL),
                 SVP_ERR_INVALID, "every pixel of pl_apparent is NaN");
    o.pl_name = "pl.tif"; /* the caller's name for the PL, as field_names for the fields */
    expect_error(svp_inverse_transform(op, all_nan, bc, NF, &o, pl_out, out, valid, NULL),
                 SVP_ERR_INVALID, "every pixel of pl.tif is NaN");
    o.pl_name = NULL;
    const svp_image *one_nan[NF] = {b[0], all_nan};
    expect_error(svp_inverse_transform(op, pl, one_nan, NF, &o, pl_out, out, valid, NULL),
                 SVP_ERR_INVALID, "every pixel of field_apparent[1] is NaN");
    {
        /* PL and field measured on disjoint halves: no pixel has both */
        svp_image *half_pl = test_image(w, h), *half_b = test_image(w, h);
        for (size_t i = 0; i < (size_t)w * h; i++) {
            half_pl->data[i] = i % 2 ? NAN : 0.5;
            half_b->data[i] = i % 2 ? 0.1 : NAN;
        }
        const svp_image *hb[NF] = {half_b, b[1]};
        expect_error(svp_inverse_transform(op, half_pl, hb, NF, &o, pl_out, out, valid, NULL),
                     SVP_ERR_INVALID, "no pixel is measured in pl_apparent and every field map");
        svp_image_free(half_pl);
        svp_image_free(half_b);
    }
    {
        /* a margin wider than the view's larger side (16): refused, however the operator fits */
        const int m = 17;
        svp_blur *big = blur_model(SVP_PSF_GAUSSIAN, 2.0, 0, 0.0, w + 2 * m, h + 2 * m,
                                   SVP_BOUNDARY_ZERO);
        svp_correct_options om;
        svp_correct_defaults(&om);
        om.method = SVP_METHOD_R;
        om.margin = m;
        expect_error(svp_inverse_transform(big, pl, bc, NF, &om, pl_out, out, valid, NULL),
                     SVP_ERR_INVALID, "a margin of 17 pixels is wider than the view's larger side");
        om.margin = 16; /* the largest allowed: runs */
        svp_blur *edge = blur_model(SVP_PSF_GAUSSIAN, 2.0, 0, 0.0, w + 32, h + 32,
                                    SVP_BOUNDARY_ZERO);
        om.deconv.iterations = 5;
        ASSERT_OK(svp_inverse_transform(edge, pl, bc, NF, &om, pl_out, out, valid, NULL));
        svp_blur_free(big);
        svp_blur_free(edge);
    }
    /* outputs that alias inputs */
    svp_image *out_alias[NF] = {out[0], b[1]};
    expect_error(svp_inverse_transform(op, pl, bc, NF, &o, pl_out, out_alias, valid, NULL),
                 SVP_ERR_INVALID, "field_true[1]");
    expect_error(svp_forward_transform(op, pl, bc, NF, pl, out, NULL), SVP_ERR_INVALID,
                 "pl_apparent");
    /* halo correction */
    expect_error(svp_halo_correct(1.0, pl, b[0], out[0]), SVP_ERR_INVALID, "halo");
    expect_error(svp_halo_correct(-0.1, pl, b[0], out[0]), SVP_ERR_INVALID, "halo");
    expect_error(svp_halo_correct(NAN, pl, b[0], out[0]), SVP_ERR_INVALID, "halo");
    expect_error(svp_halo_correct(0.5, pl, wrong, out[0]), SVP_ERR_SIZE, "field_apparent");
    expect_error(svp_halo_correct(0.5, NULL, b[0], out[0]), SVP_ERR_INVALID, "pl_apparent");
    b[0]->data[0] = NAN;
    expect_error(svp_halo_correct(0.5, pl, b[0], out[0]), SVP_ERR_INVALID, "field_apparent");

    svp_image_free(all_nan);
    svp_image_free(wrong);
    svp_image_free(valid);
    svp_image_free(pl);
    svp_image_free(pl_out);
    free_images(b, NF);
    free_images(out, NF);
    svp_blur_free(op);
}

/* ---- threads and progress ----------------------------------------------------------------- */

/* The same T⁻¹ with 1 and 2 threads (192 x 176, zero boundary, 20 RL iterations; the image is
 * above the pointwise loops' 32768-pixel threshold and its 384 x 352 frame above
 * SVP_PARALLEL_MIN, so the FFTs and the loops do run on two threads — at 40 x 32 nothing did):
 * max difference relative to max |B|, measured 0 (bit-identical) for every method, the
 * zero-boundary Wiener's CG included; asserted <= 1e-12. */
static void test_threads(void **state)
{
    (void)state;
    const int w = 192, h = 176;
    const int saved = svp_get_threads();
    svp_image *pl = pl_spot_chessboard(w, h, 16, 3);
    svp_image *b[NF] = {field_smooth(w, h, 0), field_smooth(w, h, 1)};
    restored r[2];
    for (int method = 0; method < 4; method++) {
        for (int t = 0; t < 2; t++) {
            svp_set_threads(t + 1);
            svp_blur *op = blur_model(SVP_PSF_MOFFAT, 3.0, 2.5, 0.0, w, h, SVP_BOUNDARY_ZERO);
            apparent a = forward_run(op, pl, b, NF);
            svp_correct_options o = options_for((svp_method)method, 20, 1e-3);
            r[t] = inverse_run(op, a.pl, a.field, NF, &o);
            apparent_free(&a, NF);
            svp_blur_free(op);
        }
        double diff = 0, scale = fmax(test_max_abs(r[0].field[0]), test_max_abs(r[0].field[1]));
        for (int c = 0; c < NF; c++)
            diff = fmax(diff, test_max_abs_diff(r[0].field[c], r[1].field[c]));
        diff /= scale;
        double diff_v = test_max_abs_diff(r[0].valid, r[1].valid);
        print_message("1 vs 2 threads, %-9s: max field difference %.3g of max |B|, validity "
                      "%.3g\n",
                      method_names[method], diff, diff_v);
        CHECK_BOUND(diff <= 1e-12 && diff_v <= 1e-12, "%s: 1 vs 2 threads differ by %.3g",
                    method_names[method], diff);
        restored_free(&r[0], NF);
        restored_free(&r[1], NF);
    }
    svp_set_threads(saved);
    svp_image_free(pl);
    free_images(b, NF);
}

/* With a margin, R and RL_SIGNED run on the operator's frame for the view (svp_blur_set_view:
 * 343² instead of 384² here) — against the plain formulation, the same T⁻¹ of the inputs padded
 * with a missing (NaN) margin and margin 0 on the grid's full frame, cropped. 150 x 134 view,
 * margin 20, Moffat FWHM 4 px β 1.1 with whole-grid support (a heavy tail: offsets the view
 * frame drops or wraps would show), light beyond the view, up to 40 missing pixels, plain RL
 * (30 iterations) and accelerated (10). Max differences relative to max |B| / max Ĩ, measured
 * 5.0e-13 / 1.7e-12 (field: the shift of eq. 5 costs two digits), 1.6e-14 (PL), validity
 * 4.4e-16; asserted ≤ 1e-11 (keeping the offsets the view frame drops: 1.2e-2 / 2.3e-3). The
 * same margin T⁻¹ with 1 and 2 threads: measured bit-identical, asserted ≤ 1e-12. */
static void test_margin_view_frame(void **state)
{
    (void)state;
    const int w = 150, h = 134, m = 20, gw = w + 2 * m, gh = h + 2 * m;
    svp_image *pl = pl_spot_chessboard(gw, gh, 12, 7);
    svp_image *b[NF] = {field_smooth(gw, gh, 0), field_smooth(gw, gh, 1)};
    svp_blur *op = blur_model(SVP_PSF_MOFFAT, 4.0, 1.1, 0.0, gw, gh, SVP_BOUNDARY_ZERO);
    apparent a = forward_run(op, pl, b, NF);
    /* the view's data, and the same padded with a missing margin */
    svp_image *view_pl = test_image(w, h), *pad_pl = test_image(gw, gh);
    svp_image *view_b[NF], *pad_b[NF];
    for (int c = 0; c < NF; c++) {
        view_b[c] = test_image(w, h);
        pad_b[c] = test_image(gw, gh);
    }
    uint64_t seed = 11;
    for (int y = 0; y < gh; y++)
        for (int x = 0; x < gw; x++) {
            const size_t g = (size_t)y * gw + x;
            const int in = x >= m && x < m + w && y >= m && y < m + h;
            pad_pl->data[g] = in ? a.pl->data[g] : NAN;
            for (int c = 0; c < NF; c++) pad_b[c]->data[g] = in ? a.field[c]->data[g] : NAN;
            if (!in) continue;
            const size_t v = (size_t)(y - m) * w + (x - m);
            view_pl->data[v] = a.pl->data[g];
            for (int c = 0; c < NF; c++) view_b[c]->data[v] = a.field[c]->data[g];
        }
    for (int k = 0; k < 40; k++) { /* missing pixels inside the view */
        const int x = (int)(w * test_rand(&seed)), y = (int)(h * test_rand(&seed));
        view_pl->data[(size_t)y * w + x] = NAN;
        pad_pl->data[(size_t)(y + m) * gw + x + m] = NAN;
    }
    const svp_method methods[2] = {SVP_METHOD_R, SVP_METHOD_RL_SIGNED};
    const int saved = svp_get_threads();
    for (int k = 0; k < 4; k++) {
        svp_correct_options o = options_for(methods[k % 2], k >= 2 ? 10 : 30, 1e-3);
        if (k >= 2) o.deconv.acceleration = SVP_RL_BIGGS_ANDREWS;
        o.margin = m;
        /* the view's frame against the plain one, exactly: no tail on a coarse grid here (the
         * two grids would choose different ones; test_tail_transform) */
        o.tail_tol = 0;
        restored r = inverse_run(op, view_pl, view_b, NF, &o);
        svp_set_threads(2);
        restored r2 = inverse_run(op, view_pl, view_b, NF, &o);
        svp_set_threads(saved);
        o.margin = 0;
        restored plain = inverse_run(op, pad_pl, pad_b, NF, &o);
        double d_b = 0, d_t = 0, scale = 0, d_pl = 0, d_v = 0;
        for (int y = 0; y < h; y++)
            for (int x = 0; x < w; x++) {
                const size_t v = (size_t)y * w + x, g = (size_t)(y + m) * gw + x + m;
                for (int c = 0; c < NF; c++) {
                    d_b = fmax(d_b, fabs(r.field[c]->data[v] - plain.field[c]->data[g]));
                    d_t = fmax(d_t, fabs(r.field[c]->data[v] - r2.field[c]->data[v]));
                    scale = fmax(scale, fabs(plain.field[c]->data[g]));
                }
                d_pl = fmax(d_pl, fabs(r.pl->data[v] - plain.pl->data[g]));
                d_v = fmax(d_v, fabs(r.valid->data[v] - plain.valid->data[g]));
                d_t = fmax(d_t, fabs(r.valid->data[v] - r2.valid->data[v]));
            }
        d_b /= scale;
        d_pl /= test_max_abs(plain.pl);
        d_t /= scale;
        print_message("margin %d, %s%s: view frame vs plain: field %.3g, PL %.3g, validity "
                      "%.3g; 1 vs 2 threads %.3g\n",
                      m, method_names[methods[k % 2]], k >= 2 ? " accelerated" : "", d_b, d_pl, d_v,
                      d_t);
        assert_true(d_b <= 1e-11 && d_pl <= 1e-11 && d_v <= 1e-11);
        assert_true(d_t <= 1e-12);
        assert_int_equal(r.n_missing, plain.n_missing - ((size_t)gw * gh - (size_t)w * h));
        assert_true(r.n_missing > 30 && r.n_missing <= 40);
        restored_free(&r, NF);
        restored_free(&r2, NF);
        restored_free(&plain, NF);
    }
    apparent_free(&a, NF);
    svp_blur_free(op);
    svp_image_free(pl);
    svp_image_free(view_pl);
    svp_image_free(pad_pl);
    free_images(b, NF);
    free_images(view_b, NF);
    free_images(pad_b, NF);
}

/* T⁻¹ with the PSF's tail on a coarse grid (svp_correct_options.tail_tol; docs/model.md §5)
 * against the plain frame, with and without a margin: the summary reports the tail taken (node
 * spacing, split, estimated error within the tolerance), the field and PL agree to a small
 * fraction of their peaks, and the caller's operator comes back with its own tolerance (0). */
static void test_tail_transform(void **state)
{
    (void)state;
    const int w = 300, h = 260, m = 20;
    for (int margin = 0; margin <= m; margin += m) {
        const int gw = w + 2 * margin, gh = h + 2 * margin;
        svp_image *pl = pl_spot_chessboard(gw, gh, 12, 7);
        svp_image *b[NF] = {field_smooth(gw, gh, 0), field_smooth(gw, gh, 1)};
        svp_blur *op = blur_model(SVP_PSF_MOFFAT, 4.0, 1.1, 0.0, gw, gh, SVP_BOUNDARY_ZERO);
        apparent a = forward_run(op, pl, b, NF);
        svp_image *view_pl = test_image(w, h), *view_b[NF];
        for (int c = 0; c < NF; c++) view_b[c] = test_image(w, h);
        for (int y = 0; y < h; y++)
            for (int x = 0; x < w; x++) {
                const size_t v = (size_t)y * w + x, g = (size_t)(y + margin) * gw + x + margin;
                view_pl->data[v] = a.pl->data[g];
                for (int c = 0; c < NF; c++) view_b[c]->data[v] = a.field[c]->data[g];
            }
        svp_correct_options o = options_for(SVP_METHOD_R, 30, 1e-3);
        o.margin = margin;
        svp_correct_summary sum;
        o.summary = &sum;
        o.tail_tol = 0;
        restored plain = inverse_run(op, view_pl, view_b, NF, &o);
        assert_int_equal(sum.tail_step, 0);
        o.tail_tol = 3e-3;
        restored tail = inverse_run(op, view_pl, view_b, NF, &o);
        assert_true(sum.tail_step >= 2 && sum.tail_split >= 4);
        assert_true(sum.tail_error > 0 && sum.tail_error <= 3e-3);
        assert_true(svp_blur_tail_tol(op) == 0);
        double d_b = 0, scale = 0;
        for (int c = 0; c < NF; c++) {
            d_b = fmax(d_b, test_max_abs_diff(tail.field[c], plain.field[c]));
            scale = fmax(scale, test_max_abs(plain.field[c]));
        }
        const double d_pl = test_max_abs_diff(tail.pl, plain.pl) / test_max_abs(plain.pl);
        print_message("margin %d: tail s %d, r0 %d, estimate %.3g: field %.3g, PL %.3g of the "
                      "peak from the plain frame's\n",
                      margin, sum.tail_step, sum.tail_split, sum.tail_error, d_b / scale, d_pl);
        assert_true(d_b / scale <= 5e-3 && d_pl <= 5e-3);
        restored_free(&plain, NF);
        restored_free(&tail, NF);
        apparent_free(&a, NF);
        svp_blur_free(op);
        svp_image_free(pl);
        svp_image_free(view_pl);
        free_images(b, NF);
        free_images(view_b, NF);
    }
}

typedef struct progress_log {
    double last;
    int calls, monotone, in_range;
    double cancel_at;
    int thread_max; /* the largest OpenMP thread number that called */
    int inside, overlap; /* calls under way; 1 once two were at the same time */
} progress_log;

static int log_progress(void *user, double fraction)
{
    progress_log *p = user;
    int inside;
#pragma omp atomic capture
    inside = ++p->inside;
    if (inside > 1) p->overlap = 1;
    if (omp_get_thread_num() > p->thread_max) p->thread_max = omp_get_thread_num();
#pragma omp atomic
    p->inside--;
    if (fraction < p->last) p->monotone = 0;
    if (!(fraction >= 0 && fraction <= 1)) p->in_range = 0;
    p->last = fraction;
    p->calls++;
    return fraction >= p->cancel_at;
}

static void test_progress(void **state)
{
    (void)state;
    const int w = 32, h = 32;
    svp_blur *op = blur_model(SVP_PSF_GAUSSIAN, 2.0, 0, 0.0, w, h, SVP_BOUNDARY_ZERO);
    svp_image *pl = pl_spot_chessboard(w, h, 4, 1);
    svp_image *b[NF] = {field_smooth(w, h, 0), field_smooth(w, h, 1)};
    apparent a = forward_run(op, pl, b, NF);
    for (int method = 0; method < 4; method++) {
        progress_log log = {0, 0, 1, 1, 2.0, 0, 0, 0};
        svp_correct_options o = options_for((svp_method)method, 20, 1e-3);
        o.deconv.progress = log_progress;
        o.deconv.progress_user = &log;
        restored r = inverse_run(op, a.pl, a.field, NF, &o);
        assert_true(log.monotone && log.in_range && log.calls >= 3);
        ASSERT_CLOSE(log.last, 1.0, 1e-12);
        restored_free(&r, NF);
        /* cancel half way */
        progress_log cancel = {0, 0, 1, 1, 0.5, 0, 0, 0};
        o.deconv.progress_user = &cancel;
        svp_image *pl_out = test_image(w, h), *out[NF] = {test_image(w, h), test_image(w, h)};
        expect_error(svp_inverse_transform(op, a.pl, (const svp_image *const *)a.field, NF, &o,
                                           pl_out, out, NULL, NULL),
                     SVP_ERR_CANCELLED, NULL);
        assert_true(cancel.last >= 0.5 && cancel.last < 1.0);
        svp_image_free(pl_out);
        free_images(out, NF);
    }
    apparent_free(&a, NF);
    svp_blur_free(op);
    svp_image_free(pl);
    free_images(b, NF);
}

/* Side by side (transform.c, deconvolve_side_by_side): with two threads, R's PL and its two
 * numerators (three plain RL runs, 160 x 144 > the 128² threshold) run on two copies of the
 * operator at once; with four (more threads than runs) only where OpenMP allows nesting. The caller still sees one progress, monotone from 0 to 1, one call at a
 * time; a cancel half way stops every run with SVP_ERR_CANCELLED and its message, and reports
 * no fraction after it. The result equals the one-thread (sequential) run's: measured
 * bit-identical (both transform with one-thread plans), asserted <= 1e-12. */
static void test_side_by_side(void **state)
{
    (void)state;
    const int w = 160, h = 144;
    const int saved = svp_get_threads();
    svp_blur *op = blur_model(SVP_PSF_MOFFAT, 3.0, 1.5, 0.0, w, h, SVP_BOUNDARY_ZERO);
    svp_image *pl = pl_spot_chessboard(w, h, 16, 5);
    svp_image *b[NF] = {field_smooth(w, h, 0), field_smooth(w, h, 1)};
    apparent a = forward_run(op, pl, b, NF);
    svp_correct_options o = options_for(SVP_METHOD_R, 25, 1e-3);
    svp_correct_summary sum;
    o.summary = &sum;
    restored seq = inverse_run(op, a.pl, a.field, NF, &o);
    assert_int_equal(sum.side_by_side, 1); /* one thread: in order */
    svp_set_threads(2);
    progress_log log = {0, 0, 1, 1, 2.0, 0, 0, 0};
    o.deconv.progress = log_progress;
    o.deconv.progress_user = &log;
    restored par = inverse_run(op, a.pl, a.field, NF, &o);
    assert_int_equal(sum.side_by_side, 2); /* the summary says so */
    assert_int_equal(sum.side_by_side_fallback, 0);
    assert_true(log.monotone && log.in_range && log.calls >= 3);
    ASSERT_CLOSE(log.last, 1.0, 1e-12);
    /* the runs did go side by side: the second worker reported too, never at the same time */
    assert_true(log.thread_max == 1 && !log.overlap);
    double diff = 0, scale = 0;
    for (int c = 0; c < NF; c++) {
        diff = fmax(diff, test_max_abs_diff(seq.field[c], par.field[c]));
        scale = fmax(scale, test_max_abs(seq.field[c]));
    }
    diff = fmax(diff / scale, test_max_abs_diff(seq.pl, par.pl) / test_max_abs(seq.pl));
    diff = fmax(diff, test_max_abs_diff(seq.valid, par.valid));
    print_message("side by side (2 threads) vs sequential (1): max difference %.3g, %d progress "
                  "calls\n",
                  diff, log.calls);
    CHECK_BOUND(diff <= 1e-12, "side by side differs from sequential by %.3g", diff);
    progress_log cancel = {0, 0, 1, 1, 0.5, 0, 0, 0};
    o.deconv.progress_user = &cancel;
    svp_image *pl_out = test_image(w, h), *out[NF] = {test_image(w, h), test_image(w, h)};
    expect_error(svp_inverse_transform(op, a.pl, (const svp_image *const *)a.field, NF, &o, pl_out,
                                       out, NULL, NULL),
                 SVP_ERR_CANCELLED, "cancelled");
    assert_true(cancel.monotone && cancel.last >= 0.5 && cancel.last < 1.0);
    /* the caller's OpenMP thread count is its own again */
    assert_int_equal(omp_get_max_threads(), 2);
    /* More threads (4) than runs (3): a worker's FFTs and loops would be nested regions, which
     * OpenMP runs on one thread by default (max active levels 1), so the runs stay in order,
     * every transform on all four threads; with nesting allowed they go side by side, a
     * worker per run (4 / 3 threads: one-thread plans each; asserted <= 1e-10 of the one-thread
     * run, as plans of another thread count would be). */
    const int levels = omp_get_max_active_levels();
    for (int nest = 0; nest < 2; nest++) {
        omp_set_max_active_levels(nest ? 2 : 1);
        svp_set_threads(4);
        progress_log four = {0, 0, 1, 1, 2.0, 0, 0, 0};
        o.deconv.progress_user = &four;
        restored r4 = inverse_run(op, a.pl, a.field, NF, &o);
        double d4 = 0;
        for (int c = 0; c < NF; c++) d4 = fmax(d4, test_max_abs_diff(seq.field[c], r4.field[c]));
        d4 /= scale;
        print_message("4 threads, nesting %s: %s, max difference %.3g\n", nest ? "allowed" : "off",
                      four.thread_max ? "side by side" : "in order", d4);
        assert_true(nest ? four.thread_max >= 1 : four.thread_max == 0);
        assert_int_equal(sum.side_by_side, nest ? 3 : 1);
        assert_true(!four.overlap && four.monotone);
        CHECK_BOUND(d4 <= 1e-10, "4 threads differ from 1 by %.3g", d4);
        restored_free(&r4, NF);
    }
    omp_set_max_active_levels(levels);
    /* side_by_side 0: in order with 2 threads (two-thread plans: the 1-thread result to
     * round-off), and a value other than 0 or 1 is refused */
    svp_set_threads(2);
    o.side_by_side = 0;
    progress_log off = {0, 0, 1, 1, 2.0, 0, 0, 0};
    o.deconv.progress_user = &off;
    restored ord = inverse_run(op, a.pl, a.field, NF, &o);
    assert_true(off.thread_max == 0 && sum.side_by_side == 1 && !sum.side_by_side_fallback);
    double d_off = 0;
    for (int c = 0; c < NF; c++) d_off = fmax(d_off, test_max_abs_diff(seq.field[c], ord.field[c]));
    CHECK_BOUND(d_off / scale <= 1e-10, "side_by_side 0 differs from 1 thread by %.3g", d_off);
    restored_free(&ord, NF);
    o.side_by_side = 2;
    expect_error(svp_inverse_transform(op, a.pl, (const svp_image *const *)a.field, NF, &o, pl_out,
                                       out, NULL, NULL),
                 SVP_ERR_INVALID, "side_by_side");
    svp_set_threads(saved);
    svp_image_free(pl_out);
    free_images(out, NF);
    restored_free(&seq, NF);
    restored_free(&par, NF);
    apparent_free(&a, NF);
    svp_blur_free(op);
    svp_image_free(pl);
    free_images(b, NF);
}

/* The same with PSF maps in double precision (low rank, tent, a row-pruned tent whose nodes
 * transform only their window's rows): each worker on a copy of the
 * operator that shares its term spectra and weight tables (svp_blur_clone). Asserted: the copy
 * applies exactly the original's H and Hᵀ; 2 threads (side by side: the second worker reports)
 * give the 1-thread result bit for bit (one-thread plans both ways; bound 1e-12); an operator
 * switched to single precision is not copied, and its runs stay in order. */
static void test_side_by_side_map(void **state)
{
    (void)state;
    const int w = 128, h = 128;
    const int saved = svp_get_threads();
    svp_psf base;
    svp_psf_defaults(&base);
    base.model = SVP_PSF_MOFFAT;
    base.fwhm = 3.0;
    base.beta = 1.5;
    svp_psf corner = base;
    corner.fwhm = 4.5;
    corner.beta = 2.5;
    const svp_psf nodes[4] = {base, corner, corner, base};
    const double nx[2] = {0, w - 1}, ny[2] = {0, h - 1};
    svp_psf_field *field = NULL;
    ASSERT_OK(svp_psf_field_new_grid(w, h, 2, 2, nx, ny, nodes, &field));
    svp_image *pl = pl_spot_chessboard(w, h, 16, 9);
    svp_image *b[NF] = {field_smooth(w, h, 0), field_smooth(w, h, 1)};
    svp_image *x = test_random_image(w, h, 21), *y0 = test_image(w, h), *y1 = test_image(w, h);
    static const char *const names[3] = {"low-rank", "tent", "tent, 12 px support (row-pruned)"};
    for (int rep = 0; rep < 3; rep++) {
        svp_variant_options vo;
        svp_variant_defaults(&vo);
        vo.representation = rep ? SVP_VARIANT_TENT : SVP_VARIANT_LOWRANK;
        vo.rank = 3;
        vo.samples_x = vo.samples_y = 4;
        vo.grid_x = vo.grid_y = rep == 2 ? 5 : 3;
        vo.support = rep == 2 ? 12 : 0;
        svp_blur *op = NULL, *copy = NULL;
        ASSERT_OK(svp_blur_new_field(field, w, h, SVP_BOUNDARY_ZERO, &vo, &op));
        assert_true(svp_blur_clonable(op));
        ASSERT_OK(svp_blur_clone(op, &copy));
        ASSERT_OK(svp_blur_apply(op, x, y0));
        ASSERT_OK(svp_blur_apply(copy, x, y1));
        assert_true(test_max_abs_diff(y0, y1) == 0.0);
        ASSERT_OK(svp_blur_adjoint(op, x, y0));
        ASSERT_OK(svp_blur_adjoint(copy, x, y1));
        assert_true(test_max_abs_diff(y0, y1) == 0.0);
        svp_blur_free(copy);
        apparent a = forward_run(op, pl, b, NF);
        svp_correct_options o = options_for(SVP_METHOD_R, 12, 1e-3);
        svp_set_threads(1);
        restored seq = inverse_run(op, a.pl, a.field, NF, &o);
        svp_set_threads(2);
        progress_log log = {0, 0, 1, 1, 2.0, 0, 0, 0};
        o.deconv.progress = log_progress;
        o.deconv.progress_user = &log;
        restored par = inverse_run(op, a.pl, a.field, NF, &o);
        assert_true(log.thread_max == 1 && !log.overlap && log.monotone);
        double diff = test_max_abs_diff(seq.pl, par.pl) / test_max_abs(seq.pl);
        for (int c = 0; c < NF; c++)
            diff = fmax(diff,
                        test_max_abs_diff(seq.field[c], par.field[c]) / test_max_abs(seq.field[c]));
        print_message("%s map: side by side (2 threads) vs 1 thread: max difference %.3g\n",
                      names[rep], diff);
        CHECK_BOUND(diff <= 1e-12, "side by side differs from sequential by %.3g", diff);
        restored_free(&par, NF);
        /* single precision: no copy, the runs in order */
        ASSERT_OK(svp_blur_set_precision(op, 1));
        assert_false(svp_blur_clonable(op));
        expect_error(svp_blur_clone(op, &copy), SVP_ERR_UNSUPPORTED, "double precision");
        progress_log one = {0, 0, 1, 1, 2.0, 0, 0, 0};
        o.deconv.progress_user = &one;
        restored single = inverse_run(op, a.pl, a.field, NF, &o);
        assert_true(one.thread_max == 0);
        restored_free(&single, NF);
        restored_free(&seq, NF);
        apparent_free(&a, NF);
        svp_blur_free(op);
    }
    svp_set_threads(saved);
    svp_image_free(x);
    svp_image_free(y0);
    svp_image_free(y1);
    svp_image_free(pl);
    free_images(b, NF);
    svp_psf_field_free(field);
}

int main(void)
{
    svp_set_fft_effort(SVP_FFT_ESTIMATE);
    /* One thread except in test_threads (1 and 2): on a loaded shared machine the many small
     * parallel regions of these 32²..96² problems cost far more than they save (test_progress
     * took 59 s with 2 threads at load 14, 0.5 s with 1). */
    svp_set_threads(1);
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_defaults),
        cmocka_unit_test(test_delta_psf_is_identity),
        cmocka_unit_test(test_uniform_pl_is_blur),
        cmocka_unit_test(test_halo_only),
        cmocka_unit_test(test_round_trip),
        cmocka_unit_test(test_round_trip_zero),
        cmocka_unit_test(test_components_share_pl),
        cmocka_unit_test(test_dark_and_faint_regions),
        cmocka_unit_test(test_wide_kernels),
        cmocka_unit_test(test_sizes),
        cmocka_unit_test(test_poisson_noise),
        cmocka_unit_test(test_constant_images),
        cmocka_unit_test(test_missing_pixels),
        cmocka_unit_test(test_dynamic_range),
        cmocka_unit_test(test_forward_scale),
        cmocka_unit_test(test_bad_input),
        cmocka_unit_test(test_threads),
        cmocka_unit_test(test_margin_view_frame), cmocka_unit_test(test_tail_transform),
        cmocka_unit_test(test_progress),
        cmocka_unit_test(test_side_by_side),
        cmocka_unit_test(test_side_by_side_map),
    };
    if (getenv("SVP_TEST_FILTER")) cmocka_set_test_filter(getenv("SVP_TEST_FILTER"));
    int rc = cmocka_run_group_tests_name("transform", tests, NULL, NULL);
    svp_fft_cleanup();
    return rc;
}
