/* Fitting: Levenberg–Marquardt against analytic answers, Moffat spot fits on Poisson data
 * (accuracy, coverage of the reported uncertainties, robustness), the PSF from an
 * excitation/emission pair, and PSF maps over a field. */
#include "test_helpers.h"

#include "core/internal.h"

#include <stdio.h>
#include <unistd.h>

#ifdef _OPENMP
#include <omp.h>
#endif

/* ---- random numbers ---------------------------------------------------------------------- */

static double test_normal(uint64_t *s)
{
    double u1 = test_rand(s), u2 = test_rand(s);
    if (u1 < 1e-300) u1 = 1e-300;
    return sqrt(-2.0 * log(u1)) * cos(2.0 * M_PI * u2);
}

/* Poisson deviates: multiplication method below 10, Hörmann's transformed rejection (PTRS,
 * 1993) above. */
static double test_poisson(uint64_t *s, double lambda)
{
    if (lambda <= 0) return 0;
    if (lambda < 10) {
        double L = exp(-lambda), p = 1;
        int k = 0;
        do {
            k++;
            p *= test_rand(s);
        } while (p > L);
        return k - 1;
    }
    double slam = sqrt(lambda), loglam = log(lambda);
    double b = 0.931 + 2.53 * slam, a = -0.059 + 0.02483 * b;
    double invalpha = 1.1239 + 1.1328 / (b - 3.4), vr = 0.9277 - 3.6224 / (b - 2);
    for (;;) {
        double U = test_rand(s) - 0.5, V = test_rand(s);
        double us = 0.5 - fabs(U);
        double k = floor((2 * a / us + b) * U + lambda + 0.43);
        if (us >= 0.07 && V <= vr) return k;
        if (k < 0 || (us < 0.013 && V > us)) continue;
        if (log(V) + log(invalpha) - log(a / (us * us) + b) <= -lambda + k * loglam - lgamma(k + 1))
            return k;
    }
}

/* ---- LM on analytic problems ------------------------------------------------------------- */

static int rosenbrock(void *user, const double *p, int np, int m, double *f, double *J)
{
    (void)user;
    (void)np;
    (void)m;
    f[0] = 10.0 * (p[1] - p[0] * p[0]);
    f[1] = 1.0 - p[0];
    if (J) {
        J[0] = -20.0 * p[0];
        J[1] = 10.0;
        J[2] = -1.0;
        J[3] = 0.0;
    }
    return 0;
}

static void test_lm_rosenbrock(void **state)
{
    (void)state;
    svp_lm_workspace *ws = NULL;
    ASSERT_OK(svp_lm_workspace_new(2, 2, &ws));
    for (int analytic = 0; analytic < 2; analytic++) {
        svp_lm_problem pr;
        memset(&pr, 0, sizeof pr);
        pr.n_params = 2;
        pr.n_points = 2;
        pr.model = rosenbrock;
        pr.analytic_jacobian = analytic;
        double p[2] = {-1.2, 1.0};
        svp_lm_result r;
        double cov[4];
        ASSERT_OK(svp_lm_solve(ws, &pr, NULL, p, &r, cov));
        ASSERT_CLOSE(p[0], 1.0, 1e-7);
        ASSERT_CLOSE(p[1], 1.0, 1e-7);
        assert_true(r.chi2 < 1e-14);
        assert_int_equal(r.dof, 0);
        assert_true(r.stop != SVP_LM_MAX_ITER && r.stop != SVP_LM_STUCK);
        assert_true(r.iterations > 3 && r.iterations < 100);
    }
    svp_lm_workspace_free(ws);
}

/* y = A exp(-t / tau) + c */
static int exp_decay(void *user, const double *p, int np, int m, double *f, double *J)
{
    const double *t = user;
    (void)np;
    for (int i = 0; i < m; i++) {
        double e = exp(-t[i] / p[1]);
        f[i] = p[0] * e + p[2];
        if (J) {
            J[i * 3 + 0] = e;
            J[i * 3 + 1] = p[0] * e * t[i] / (p[1] * p[1]);
            J[i * 3 + 2] = 1.0;
        }
    }
    return 0;
}

static void test_lm_exponential_decay(void **state)
{
    (void)state;
    enum { M = 40 };
    double t[M], y[M];
    for (int i = 0; i < M; i++) {
        t[i] = 0.25 * i;
        y[i] = 5.0 * exp(-t[i] / 2.0) + 1.0;
    }
    svp_lm_workspace *ws = NULL;
    ASSERT_OK(svp_lm_workspace_new(3, M, &ws));
    for (int analytic = 0; analytic < 2; analytic++) {
        svp_lm_problem pr;
        memset(&pr, 0, sizeof pr);
        pr.n_params = 3;
        pr.n_points = M;
        pr.model = exp_decay;
        pr.user = t;
        pr.data = y;
        pr.analytic_jacobian = analytic;
        double p[3] = {1.0, 0.5, 0.0};
        svp_lm_result r;
        ASSERT_OK(svp_lm_solve(ws, &pr, NULL, p, &r, NULL));
        /* exact data: the minimum is the truth with chi2 = 0 */
        ASSERT_CLOSE(p[0], 5.0, 1e-7);
        ASSERT_CLOSE(p[1], 2.0, 1e-7);
        ASSERT_CLOSE(p[2], 1.0, 1e-7);
        assert_true(r.chi2 < 1e-16);
        assert_int_equal(r.dof, M - 3);
        /* the same by hand: init / iterate / finish */
        double p0[3] = {1.0, 0.5, 0.0}, p1[3];
        svp_lm_stop stop = SVP_LM_RUNNING;
        ASSERT_OK(svp_lm_init(ws, &pr, NULL, p0));
        int iters = 0;
        while (stop == SVP_LM_RUNNING && iters < 200) {
            ASSERT_OK(svp_lm_iterate(ws, &stop));
            iters++;
        }
        svp_lm_result r1;
        ASSERT_OK(svp_lm_finish(ws, p1, &r1, NULL));
        for (int j = 0; j < 3; j++) assert_true(p1[j] == p[j]);
        assert_int_equal(r1.iterations, r.iterations);
        assert_non_null(svp_lm_stop_string(r1.stop));

        /* bounds: an inactive bound changes nothing; an active one stops at the bound */
        double lo[3] = {0, 0.1, -INFINITY}, hi[3] = {100, 10, INFINITY};
        pr.lower = lo;
        pr.upper = hi;
        double q[3] = {1.0, 0.5, 0.0};
        ASSERT_OK(svp_lm_solve(ws, &pr, NULL, q, &r, NULL));
        ASSERT_CLOSE(q[1], 2.0, 1e-6);
        assert_true(r.at_bound == 0);
        hi[1] = 1.5; /* tau cannot reach 2 */
        double cov[9];
        q[0] = 1.0;
        q[1] = 0.5;
        q[2] = 0.0;
        ASSERT_OK(svp_lm_solve(ws, &pr, NULL, q, &r, cov));
        assert_true(q[1] <= 1.5 && q[1] > 1.5 - 1e-3);
        assert_true(r.at_bound == 2u);
        assert_true(isinf(cov[4]));
        assert_true(isfinite(cov[0]) && cov[0] > 0);
        /* a fixed parameter (lower == upper) stays put and has no variance */
        lo[1] = hi[1] = 2.0;
        q[0] = 1.0;
        q[1] = 7.0;
        q[2] = 0.0;
        ASSERT_OK(svp_lm_solve(ws, &pr, NULL, q, &r, cov));
        assert_true(q[1] == 2.0);
        ASSERT_CLOSE(q[0], 5.0, 1e-7);
        assert_true(cov[4] == 0 && cov[1] == 0 && cov[3] == 0);
        assert_int_equal(r.dof, M - 2);
    }
    svp_lm_workspace_free(ws);
}

/* A linear model a + b t + c t²: the LM solution and covariance must be the weighted
 * least-squares ones, computed here from the normal equations. */
static int quadratic(void *user, const double *p, int np, int m, double *f, double *J)
{
    const double *t = user;
    (void)np;
    for (int i = 0; i < m; i++) {
        f[i] = p[0] + p[1] * t[i] + p[2] * t[i] * t[i];
        if (J) {
            J[i * 3 + 0] = 1;
            J[i * 3 + 1] = t[i];
            J[i * 3 + 2] = t[i] * t[i];
        }
    }
    return 0;
}

static void invert3(const long double a[9], long double inv[9])
{
    long double det = a[0] * (a[4] * a[8] - a[5] * a[7]) - a[1] * (a[3] * a[8] - a[5] * a[6]) +
                      a[2] * (a[3] * a[7] - a[4] * a[6]);
    inv[0] = (a[4] * a[8] - a[5] * a[7]) / det;
    inv[1] = (a[2] * a[7] - a[1] * a[8]) / det;
    inv[2] = (a[1] * a[5] - a[2] * a[4]) / det;
    inv[3] = (a[5] * a[6] - a[3] * a[8]) / det;
    inv[4] = (a[0] * a[8] - a[2] * a[6]) / det;
    inv[5] = (a[2] * a[3] - a[0] * a[5]) / det;
    inv[6] = (a[3] * a[7] - a[4] * a[6]) / det;
    inv[7] = (a[1] * a[6] - a[0] * a[7]) / det;
    inv[8] = (a[0] * a[4] - a[1] * a[3]) / det;
}

static void test_lm_linear_covariance(void **state)
{
    (void)state;
    enum { M = 30 };
    double t[M], y[M], sig[M];
    uint64_t s = 12345;
    for (int i = 0; i < M; i++) {
        t[i] = -1.0 + 2.0 * i / (M - 1);
        sig[i] = 0.05 + 0.1 * test_rand(&s);
        y[i] = 1.0 - 2.0 * t[i] + 0.5 * t[i] * t[i] + sig[i] * test_normal(&s);
    }
    long double ata[9] = {0}, aty[3] = {0}, inv[9];
    for (int i = 0; i < M; i++) {
        long double row[3] = {1, t[i], (long double)t[i] * t[i]};
        long double w = 1.0L / ((long double)sig[i] * sig[i]);
        for (int a = 0; a < 3; a++) {
            aty[a] += w * row[a] * y[i];
            for (int b = 0; b < 3; b++) ata[a * 3 + b] += w * row[a] * row[b];
        }
    }
    invert3(ata, inv);
    double sol[3], chi2 = 0;
    for (int a = 0; a < 3; a++)
        sol[a] = (double)(inv[a * 3] * aty[0] + inv[a * 3 + 1] * aty[1] + inv[a * 3 + 2] * aty[2]);
    for (int i = 0; i < M; i++) {
        double d = (y[i] - sol[0] - sol[1] * t[i] - sol[2] * t[i] * t[i]) / sig[i];
        chi2 += d * d;
    }
    svp_lm_workspace *ws = NULL;
    ASSERT_OK(svp_lm_workspace_new(3, M, &ws));
    svp_lm_problem pr;
    memset(&pr, 0, sizeof pr);
    pr.n_params = 3;
    pr.n_points = M;
    pr.model = quadratic;
    pr.user = t;
    pr.data = y;
    pr.sigma = sig;
    pr.analytic_jacobian = 1;
    double p[3] = {0, 0, 0}, cov[9];
    svp_lm_result r;
    ASSERT_OK(svp_lm_solve(ws, &pr, NULL, p, &r, cov));
    /* χ² is flat to round-off within ~sqrt(eps) of the minimum: that limits the accuracy */
    for (int a = 0; a < 3; a++) ASSERT_CLOSE(p[a], sol[a], 1e-8 * (1 + fabs(sol[a])));
    ASSERT_CLOSE(r.chi2, chi2, 1e-9 * chi2);
    ASSERT_CLOSE(r.chi2_red, chi2 / (M - 3), 1e-9);
    for (int k = 0; k < 9; k++) ASSERT_CLOSE(cov[k], (double)inv[k], 1e-9 * fabs((double)inv[4]));
    /* scaled covariance = unscaled × χ²_red; unit weights scale automatically */
    svp_lm_options opt;
    svp_lm_defaults(&opt);
    opt.covariance = SVP_LM_COV_SCALED;
    double p2[3] = {0, 0, 0}, cov2[9];
    ASSERT_OK(svp_lm_solve(ws, &pr, &opt, p2, &r, cov2));
    for (int k = 0; k < 9; k++)
        ASSERT_CLOSE(cov2[k], cov[k] * r.chi2_red, 1e-9 * fabs(cov[4] * r.chi2_red));
    svp_lm_workspace_free(ws);
}

/* Constant model with shot-noise weights taken from the model: iteratively reweighted LM
 * solves the Poisson score equation, whose root is the sample mean (data-weighted χ² would
 * be biased low, model-weighted Pearson χ² high). */
static int constant_model(void *user, const double *p, int np, int m, double *f, double *J)
{
    (void)user;
    (void)np;
    for (int i = 0; i < m; i++) {
        f[i] = p[0];
        if (J) J[i] = 1.0;
    }
    return 0;
}

static void test_lm_noise_model_weights(void **state)
{
    (void)state;
    enum { M = 200 };
    double y[M], mean = 0;
    uint64_t s = 99;
    for (int i = 0; i < M; i++) {
        y[i] = test_poisson(&s, 20.0);
        mean += y[i] / M;
    }
    svp_noise_model nm = {0.0, 1.0, 0.0};
    ASSERT_CLOSE(svp_noise_variance(&nm, 20.0), 20.0, 1e-15);
    svp_noise_model nm2 = {3.0, 2.0, 0.1};
    ASSERT_CLOSE(svp_noise_variance(&nm2, 50.0), 9.0 + 25.0 + 25.0, 1e-12);
    ASSERT_CLOSE(svp_noise_variance(&nm2, 0.0), 9.0 + 0.25, 1e-12); /* one-electron floor */
    svp_lm_workspace *ws = NULL;
    ASSERT_OK(svp_lm_workspace_new(1, M, &ws));
    svp_lm_problem pr;
    memset(&pr, 0, sizeof pr);
    pr.n_params = 1;
    pr.n_points = M;
    pr.model = constant_model;
    pr.data = y;
    pr.noise = nm;
    pr.analytic_jacobian = 1;
    double p[1] = {5.0}, cov[1];
    svp_lm_result r;
    ASSERT_OK(svp_lm_solve(ws, &pr, NULL, p, &r, cov));
    ASSERT_CLOSE(p[0], mean, 1e-8 * mean);
    /* unscaled covariance with known noise: σ²/M = mean/M */
    ASSERT_CLOSE(cov[0], mean / M, 1e-6 * mean / M);
    svp_lm_workspace_free(ws);
}

static void test_lm_not_converged_and_bad_input(void **state)
{
    (void)state;
    svp_lm_workspace *ws = NULL;
    ASSERT_OK(svp_lm_workspace_new(2, 2, &ws));
    svp_lm_problem pr;
    memset(&pr, 0, sizeof pr);
    pr.n_params = 2;
    pr.n_points = 2;
    pr.model = rosenbrock;
    pr.analytic_jacobian = 1;
    svp_lm_options opt;
    svp_lm_defaults(&opt);
    opt.max_iterations = 3;
    double p[2] = {-1.2, 1.0};
    svp_lm_result r;
    assert_int_equal(svp_lm_solve(ws, &pr, &opt, p, &r, NULL), SVP_ERR_NUMERIC);
    assert_non_null(strstr(svp_last_error(), "did not converge after 3 iterations"));
    assert_int_equal(r.stop, SVP_LM_MAX_ITER);
    assert_int_equal(r.iterations, 3);
    assert_true(p[0] != -1.2); /* the last parameters are returned */

    double q[2] = {0, 0};
    pr.model = NULL;
    assert_int_equal(svp_lm_solve(ws, &pr, NULL, q, &r, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "no model"));
    pr.model = rosenbrock;
    pr.n_points = 3;
    assert_int_equal(svp_lm_solve(ws, &pr, NULL, q, &r, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "n_points = 3"));
    pr.n_points = 2;
    double lo[2] = {1, 0}, hi[2] = {0, 1};
    pr.lower = lo;
    pr.upper = hi;
    assert_int_equal(svp_lm_solve(ws, &pr, NULL, q, &r, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "bounds of parameter 0"));
    pr.lower = pr.upper = NULL;
    q[1] = NAN;
    assert_int_equal(svp_lm_solve(ws, &pr, NULL, q, &r, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "initial parameter 1"));
    q[1] = 0;
    double sig[2] = {1, 0};
    pr.sigma = sig;
    assert_int_equal(svp_lm_solve(ws, &pr, NULL, q, &r, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "sigma[1]"));
    svp_lm_workspace_free(ws);
    assert_int_equal(svp_lm_workspace_new(SVP_LM_MAX_PARAMS + 1, 5, &ws), SVP_ERR_INVALID);
    assert_null(ws);
}

/* ---- synthetic spots --------------------------------------------------------------------- */

/* Expected counts: bg + amp × pixel mean of the profile (ns × ns midpoint samples of
 * svp_psf_profile, the model module's definition of the PSF shape). */
static svp_image *spot_expected(int w, int h, const svp_psf *psf, double x0, double y0,
                                double amp, double bg, int ns)
{
    svp_image *img = test_image(w, h);
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double acc = 0;
            for (int j = 0; j < ns; j++)
                for (int i = 0; i < ns; i++)
                    acc += svp_psf_profile(psf, x - x0 - 0.5 + (i + 0.5) / ns,
                                           y - y0 - 0.5 + (j + 0.5) / ns);
            img->data[(size_t)y * w + x] = bg + amp * acc / (ns * ns);
        }
    return img;
}

static void poisson_draw(const svp_image *expected, svp_image *out, uint64_t *s)
{
    for (size_t i = 0; i < (size_t)expected->width * expected->height; i++)
        out->data[i] = test_poisson(s, expected->data[i]);
}

static svp_psf moffat(double fa, double fb, double angle, double beta)
{
    svp_psf p;
    svp_psf_defaults(&p);
    p.model = SVP_PSF_MOFFAT;
    p.fwhm = fa;
    p.fwhm_minor = fb;
    p.angle = angle;
    p.beta = beta;
    return p;
}

/* Noise-free spots: the fitted model reproduces an independent pixel integration of
 * svp_psf_profile, for a wide and an undersampled (sub-pixel integrated) spot. */
static void test_spot_exact_data(void **state)
{
    (void)state;
    const double cases[][4] = {{5.0, 4.0, 0.5, 2.5}, {1.6, 1.3, -0.4, 3.0}, {3.0, 3.0, 0, 1.5}};
    for (int c = 0; c < 3; c++) {
        svp_psf truth = moffat(cases[c][0], cases[c][1], cases[c][2], cases[c][3]);
        svp_image *img = spot_expected(25, 25, &truth, 12.3, 11.6, 1000.0, 10.0, 24);
        svp_spot_options o;
        svp_spot_defaults(&o);
        o.noise.gain = 0; /* exact data: unit weights, nothing to clip */
        o.hot_pixels = 0;
        o.clip_kappa = 0;
        svp_spot_result r;
        ASSERT_OK(svp_spot_fit(img, &o, &r, NULL, NULL));
        /* 24² midpoint samples vs 2×2 (4×4 below 2 px) Gauss–Legendre: both approximate the
         * pixel integral; they agree to ~1e-4 */
        ASSERT_CLOSE(r.fwhm_major, cases[c][0], 2e-3 * cases[c][0]);
        ASSERT_CLOSE(r.fwhm_minor, cases[c][1], 2e-3 * cases[c][1]);
        ASSERT_CLOSE(r.beta, cases[c][3], 5e-3 * cases[c][3]);
        ASSERT_CLOSE(r.x0, 12.3, 1e-3);
        ASSERT_CLOSE(r.y0, 11.6, 1e-3);
        ASSERT_CLOSE(r.amplitude, 1000.0, 2.0);
        ASSERT_CLOSE(r.background, 10.0, 0.05);
        if (cases[c][0] != cases[c][1]) ASSERT_CLOSE(r.angle, cases[c][2], 2e-3);
        /* field convention: (e1, e2) = e (cos 2θ, sin 2θ), fwhm = (major + minor) / 2 */
        double e = (cases[c][0] - cases[c][1]) / (cases[c][0] + cases[c][1]);
        ASSERT_CLOSE(r.e1, e * cos(2 * cases[c][2]), 2e-3);
        ASSERT_CLOSE(r.e2, e * sin(2 * cases[c][2]), 2e-3);
        ASSERT_CLOSE(r.fwhm, 0.5 * (cases[c][0] + cases[c][1]), 2e-3 * cases[c][0]);
        assert_true((r.flags & ~(unsigned)SVP_SPOT_POOR_FIT) == 0);
        svp_image_free(img);
    }
}

typedef struct spot_case {
    const char *name;
    svp_psf_model model;
    double fa, fb, angle, beta;
} spot_case;

/* One Poisson draw of a 31×31 spot (peak 5000 photons above 100 background): FWHM within
 * 2 %, β within 5 % (the requirement); Gaussian and Lorentzian special cases. */
static void test_spot_poisson_accuracy(void **state)
{
    (void)state;
    const spot_case cases[] = {
        {"moffat", SVP_PSF_MOFFAT, 5.0, 4.0, M_PI / 6, 2.5},
        {"moffat-round", SVP_PSF_MOFFAT, 4.0, 4.0, 0.0, 1.5},
        {"gaussian", SVP_PSF_GAUSSIAN, 4.5, 3.5, -0.6, 0},
        {"lorentzian", SVP_PSF_LORENTZIAN, 3.0, 3.0, 0, 1.0},
    };
    for (size_t c = 0; c < sizeof cases / sizeof cases[0]; c++) {
        svp_psf truth = moffat(cases[c].fa, cases[c].fb, cases[c].angle, cases[c].beta);
        truth.model = cases[c].model;
        svp_image *ex = spot_expected(31, 31, &truth, 15.2, 14.7, 5000.0, 100.0, 8);
        svp_image *img = test_image(31, 31);
        uint64_t s = 1000 + c;
        poisson_draw(ex, img, &s);
        svp_spot_options o;
        svp_spot_defaults(&o);
        o.model = cases[c].model;
        svp_spot_result r;
        ASSERT_OK(svp_spot_fit(img, &o, &r, NULL, NULL));
        double fmean = 0.5 * (cases[c].fa + cases[c].fb);
        printf("# %-12s FWHM major %.4f (true %.2f, %+.2f%%), minor %.4f (%.2f, %+.2f%%), mean "
               "%.4f (%+.2f%%), beta %.4f (%.2f, %+.2f%%), chi2_red %.3f\n",
               cases[c].name, r.fwhm_major, cases[c].fa,
               100 * (r.fwhm_major / cases[c].fa - 1), r.fwhm_minor, cases[c].fb,
               100 * (r.fwhm_minor / cases[c].fb - 1), r.fwhm, 100 * (r.fwhm / fmean - 1), r.beta,
               cases[c].beta, cases[c].beta > 0 ? 100 * (r.beta / cases[c].beta - 1) : 0.0,
               r.chi2_red);
        ASSERT_CLOSE(r.fwhm, fmean, 0.02 * fmean);
        if (cases[c].fa != cases[c].fb) {
            ASSERT_CLOSE(r.fwhm_major, cases[c].fa, 0.02 * cases[c].fa);
            ASSERT_CLOSE(r.fwhm_minor, cases[c].fb, 0.02 * cases[c].fb);
            ASSERT_CLOSE(r.angle, cases[c].angle, 0.05);
        }
        if (cases[c].model == SVP_PSF_MOFFAT) ASSERT_CLOSE(r.beta, cases[c].beta, 0.05 * cases[c].beta);
        if (cases[c].model == SVP_PSF_LORENTZIAN) assert_true(r.beta == 1.0);
        ASSERT_CLOSE(r.x0, 15.2, 0.05);
        ASSERT_CLOSE(r.y0, 14.7, 0.05);
        ASSERT_CLOSE(r.background, 100.0, 3.0);
        assert_true(r.chi2_red > 0.8 && r.chi2_red < 1.25);
        assert_true(r.flags == 0);
        /* encircled-energy radii are ordered and refer to the half-width disc */
        assert_true(r.ee50 > 0 && r.ee50 < r.ee80 && r.ee80 < r.ee95 && r.ee95 <= 15.5);
        ASSERT_CLOSE(r.ee_radius, 15.5, 1e-12);
        if (cases[c].fa == cases[c].fb) {
            /* circular fit: no ellipticity at all */
            o.elliptical = 0;
            ASSERT_OK(svp_spot_fit(img, &o, &r, NULL, NULL));
            assert_true(r.e1 == 0 && r.e2 == 0 && r.fwhm_major == r.fwhm_minor);
            ASSERT_CLOSE(r.fwhm, fmean, 0.02 * fmean);
            assert_true(r.flags == 0);
        }
        svp_image_free(ex);
        svp_image_free(img);
    }
}

/* Coverage: over many noise draws the 1σ intervals contain the truth about 68 % of the time. */
static void test_spot_coverage(void **state)
{
    (void)state;
    enum { DRAWS = 200, W = 21 };
    svp_psf truth = moffat(4.4, 3.6, 0.4, 2.5);
    svp_image *ex = spot_expected(W, W, &truth, 10.3, 9.8, 5000.0, 100.0, 8);
    svp_image *img = test_image(W, W);
    svp_spot_options o;
    svp_spot_defaults(&o);
    const char *names[6] = {"fwhm", "fwhm_major", "fwhm_minor", "beta", "x0", "angle"};
    const double tv[6] = {4.0, 4.4, 3.6, 2.5, 10.3, 0.4};
    int inside[6] = {0}, n_ok = 0;
    double mean_err[6] = {0}, bias[6] = {0};
    uint64_t s = 777;
    for (int d = 0; d < DRAWS; d++) {
        poisson_draw(ex, img, &s);
        svp_spot_result r;
        ASSERT_OK(svp_spot_fit(img, &o, &r, NULL, NULL));
        const double v[6] = {r.fwhm, r.fwhm_major, r.fwhm_minor, r.beta, r.x0, r.angle};
        const double e[6] = {r.fwhm_err, r.fwhm_major_err, r.fwhm_minor_err, r.beta_err,
                             r.x0_err, r.angle_err};
        for (int k = 0; k < 6; k++) {
            inside[k] += fabs(v[k] - tv[k]) <= e[k];
            mean_err[k] += e[k] / DRAWS;
            bias[k] += (v[k] - tv[k]) / DRAWS;
        }
        n_ok++;
    }
    /* binomial σ of the rate at 200 draws: 0.033; tolerance ±0.10 (3σ) */
    for (int k = 0; k < 6; k++) {
        double rate = (double)inside[k] / n_ok;
        printf("# coverage %-10s %.3f (1 sigma %.4f, bias %+.4f)\n", names[k], rate,
               mean_err[k], bias[k]);
        if (fabs(rate - 0.683) > 0.10)
            fail_msg("%s: 1-sigma coverage %.3f over %d draws (expected 0.683 +- 0.10)",
                     names[k], rate, n_ok);
    }
    svp_image_free(ex);
    svp_image_free(img);
}

static void test_spot_hot_pixel(void **state)
{
    (void)state;
    svp_psf truth = moffat(4.0, 3.5, 0.3, 2.5);
    svp_image *ex = spot_expected(31, 31, &truth, 15.0, 15.4, 5000.0, 100.0, 8);
    svp_image *img = test_image(31, 31);
    uint64_t s = 4242;
    poisson_draw(ex, img, &s);
    svp_spot_options o;
    svp_spot_defaults(&o);
    svp_spot_result clean, hot;
    ASSERT_OK(svp_spot_fit(img, &o, &clean, NULL, NULL));
    assert_true(clean.flags == 0);
    /* two hot pixels: one in the wing, one two pixels from the peak, far brighter than it */
    img->data[5 * 31 + 22] = 30000;
    img->data[17 * 31 + 15] = 40000;
    ASSERT_OK(svp_spot_fit(img, &o, &hot, NULL, NULL));
    assert_true(hot.flags & SVP_SPOT_HOT_PIXELS);
    assert_int_equal(hot.n_hot, 2);
    printf("# hot pixels: FWHM %.4f -> %.4f, beta %.4f -> %.4f\n", clean.fwhm, hot.fwhm,
           clean.beta, hot.beta);
    ASSERT_CLOSE(hot.fwhm, clean.fwhm, 0.3 * clean.fwhm_err);
    ASSERT_CLOSE(hot.beta, clean.beta, 0.3 * clean.beta_err);
    /* without spike detection, κ-σ clipping still removes the wing spike */
    o.hot_pixels = 0;
    img->data[17 * 31 + 15] = ex->data[17 * 31 + 15];
    ASSERT_OK(svp_spot_fit(img, &o, &hot, NULL, NULL));
    printf("# hot pixel without spike detection: %d pixels clipped\n", hot.n_clipped);
    assert_true(hot.flags & SVP_SPOT_CLIPPED);
    assert_true(hot.n_clipped >= 1 && hot.n_clipped <= 3);
    ASSERT_CLOSE(hot.fwhm, clean.fwhm, 0.3 * clean.fwhm_err);
    svp_image_free(ex);
    svp_image_free(img);
}

static void test_spot_border_saturation_empty(void **state)
{
    (void)state;
    svp_psf truth = moffat(4.0, 4.0, 0, 2.5);
    uint64_t s = 31337;
    svp_spot_options o;
    svp_spot_defaults(&o);
    svp_spot_result r;
    /* near the border: flagged, or refused on request */
    svp_image *ex = spot_expected(31, 31, &truth, 3.0, 15.0, 5000.0, 100.0, 8);
    svp_image *img = test_image(31, 31);
    poisson_draw(ex, img, &s);
    ASSERT_OK(svp_spot_fit(img, &o, &r, NULL, NULL));
    assert_true(r.flags & SVP_SPOT_NEAR_BORDER);
    ASSERT_CLOSE(r.border_distance, 3.5, 0.1);
    o.refuse_near_border = 1;
    assert_int_equal(svp_spot_fit(img, &o, &r, NULL, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "from the edge"));
    o.refuse_near_border = 0;
    svp_image_free(ex);

    /* saturated: detected as a plateau of equal maxima, and from a given level */
    ex = spot_expected(31, 31, &truth, 15.0, 15.0, 5000.0, 100.0, 8);
    poisson_draw(ex, img, &s);
    svp_spot_result ref;
    ASSERT_OK(svp_spot_fit(img, &o, &ref, NULL, NULL));
    /* a level above every pixel cuts nothing and must change nothing (it once set the
     * start's amplitude, and a level 10-1e5 times the peak moved the fit) */
    for (int k = 0; k < 3; k++) {
        const double level[3] = {6000.0, 6.0e5, 1.0e9};
        o.saturation = level[k];
        ASSERT_OK(svp_spot_fit(img, &o, &r, NULL, NULL));
        assert_int_equal(r.n_saturated, 0);
        assert_false(r.flags & SVP_SPOT_SATURATED);
        ASSERT_CLOSE(r.fwhm, ref.fwhm, 1e-6 * ref.fwhm);
        ASSERT_CLOSE(r.beta, ref.beta, 1e-6 * ref.beta);
        assert_int_equal(r.n_clipped, ref.n_clipped);
    }
    o.saturation = 0;
    for (size_t i = 0; i < 31 * 31; i++) img->data[i] = fmin(img->data[i], 3000.0);
    ASSERT_OK(svp_spot_fit(img, &o, &r, NULL, NULL));
    assert_true(r.flags & SVP_SPOT_SATURATED);
    assert_true(r.n_saturated >= 3);
    printf("# saturated at 3000 (peak 5100): %d pixels excluded, FWHM %.4f vs %.4f unsaturated, "
           "amplitude %.0f\n", r.n_saturated, r.fwhm, ref.fwhm, r.amplitude);
    ASSERT_CLOSE(r.fwhm, ref.fwhm, 0.03 * ref.fwhm); /* the wings still hold the shape */
    o.saturation = 2500;
    ASSERT_OK(svp_spot_fit(img, &o, &r, NULL, NULL));
    assert_true(r.flags & SVP_SPOT_SATURATED);
    o.saturation = 0;

    /* a centred spot in other units than photon counts (normalised: × 1e-4): at the default
     * gain 1 its Poisson σ (1) swamps the spot, and the refusal says why and what to give; at
     * gain 0 (unknown noise) it fits as in counts */
    {
        svp_image *c = spot_expected(31, 31, &truth, 15.2, 14.7, 5000.0, 100.0, 8);
        poisson_draw(c, img, &s);
        ASSERT_OK(svp_spot_fit(img, &o, &r, NULL, NULL));
        const double fwhm_counts = r.fwhm;
        for (size_t i = 0; i < 31 * 31; i++) img->data[i] *= 1e-4;
        assert_int_equal(svp_spot_fit(img, &o, &r, NULL, NULL), SVP_ERR_INVALID);
        assert_non_null(strstr(svp_last_error(), "holds no spot"));
        assert_non_null(strstr(svp_last_error(), "if the data are not photon counts at gain 1, "
                                                 "give their gain, or gain 0"));
        o.noise.gain = 0;
        ASSERT_OK(svp_spot_fit(img, &o, &r, NULL, NULL));
        ASSERT_CLOSE(r.fwhm, fwhm_counts, 0.02 * fwhm_counts);
        /* beyond [1e-150, 1e150]: refused for its magnitude (at 1e160 it was written, flagged
         * "poor fit" with infinite uncertainties) */
        for (size_t i = 0; i < 31 * 31; i++) img->data[i] *= 1e164;
        assert_int_equal(svp_spot_fit(img, &o, &r, NULL, NULL), SVP_ERR_INVALID);
        assert_non_null(strstr(svp_last_error(), "spot fit: the spot image: its largest |value|"));
        o.noise.gain = 1;
        svp_image_free(c);
    }

    /* an empty image: background only (no gain hint: the model's σ is the scatter) */
    for (size_t i = 0; i < 31 * 31; i++) img->data[i] = test_poisson(&s, 100.0);
    assert_int_equal(svp_spot_fit(img, &o, &r, NULL, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "holds no spot"));
    assert_null(strstr(svp_last_error(), "give their gain"));
    for (size_t i = 0; i < 31 * 31; i++) img->data[i] = 0;
    assert_int_equal(svp_spot_fit(img, &o, &r, NULL, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "holds no spot"));
    for (size_t i = 0; i < 31 * 31; i++) img->data[i] = NAN;
    assert_int_equal(svp_spot_fit(img, &o, &r, NULL, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "finite pixels"));
    svp_image *tiny = test_image(4, 9);
    assert_int_equal(svp_spot_fit(tiny, &o, &r, NULL, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "too small"));
    o.beta_min = 3;
    o.beta_max = 2;
    assert_int_equal(svp_spot_fit(ex, &o, &r, NULL, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "beta bounds"));
    svp_image_free(tiny);
    svp_image_free(ex);
    svp_image_free(img);
}

static void test_spot_beta_bound_and_no_convergence(void **state)
{
    (void)state;
    /* a Gaussian spot fitted as a Moffat: β runs to beta_max */
    svp_psf truth = moffat(4.0, 4.0, 0, 0);
    truth.model = SVP_PSF_GAUSSIAN;
    svp_image *ex = spot_expected(31, 31, &truth, 15.0, 15.0, 5000.0, 100.0, 8);
    svp_image *img = test_image(31, 31);
    uint64_t s = 555;
    poisson_draw(ex, img, &s);
    svp_spot_options o;
    svp_spot_defaults(&o);
    o.beta_max = 6.0;
    svp_spot_result r;
    ASSERT_OK(svp_spot_fit(img, &o, &r, NULL, NULL));
    printf("# Gaussian spot as Moffat with beta_max 6: beta %.4f, flags 0x%x\n", r.beta, r.flags);
    assert_true(r.flags & SVP_SPOT_BETA_AT_BOUND);
    char buf[256];
    svp_spot_flags_describe(r.flags, buf, sizeof buf);
    assert_non_null(strstr(buf, "beta at bound"));
    /* the same spot fitted as a Gaussian is fine */
    o.model = SVP_PSF_GAUSSIAN;
    ASSERT_OK(svp_spot_fit(img, &o, &r, NULL, NULL));
    assert_true(r.flags == 0);
    ASSERT_CLOSE(r.fwhm, 4.0, 0.08);

    /* β creeping along its bound when the iterations run out: held at the bound for a last
     * fit, flagged, its uncertainty unknown */
    o.model = SVP_PSF_MOFFAT;
    o.lm.max_iterations = 5;
    ASSERT_OK(svp_spot_fit(img, &o, &r, NULL, NULL));
    assert_true(r.beta == 6.0);
    assert_true(isinf(r.beta_err));
    assert_true(r.flags & SVP_SPOT_BETA_AT_BOUND);
    assert_true(isfinite(r.fwhm_err) && r.fwhm_err > 0);
    o.lm.max_iterations = 200;

    /* too few iterations: SVP_ERR_NUMERIC, the result filled and flagged */
    o.model = SVP_PSF_MOFFAT;
    o.beta_max = 20;
    o.lm.max_iterations = 2;
    memset(&r, 0, sizeof r);
    assert_int_equal(svp_spot_fit(img, &o, &r, NULL, NULL), SVP_ERR_NUMERIC);
    assert_non_null(strstr(svp_last_error(), "did not converge"));
    assert_true(r.flags & SVP_SPOT_NOT_CONVERGED);
    assert_true(r.fwhm > 0 && r.iterations == 2);
    svp_spot_flags_describe(r.flags, buf, sizeof buf);
    assert_non_null(strstr(buf, "not converged"));
    svp_spot_flags_describe(0, buf, sizeof buf);
    assert_string_equal(buf, "ok");
    assert_string_equal(svp_spot_flag_string(0), "");
    assert_non_null(strstr(svp_spot_flag_string(SVP_SPOT_SATURATED), "saturated"));
    svp_image_free(ex);
    svp_image_free(img);
}

/* Model and residual images: model + residual = data; Σ residual²/σ² = χ² over used pixels. */
static void test_spot_model_residual(void **state)
{
    (void)state;
    svp_psf truth = moffat(3.5, 3.0, 1.0, 2.0);
    svp_image *ex = spot_expected(21, 21, &truth, 10.0, 10.0, 3000.0, 50.0, 8);
    svp_image *img = test_image(21, 21), *model = test_image(21, 21), *res = test_image(21, 21);
    uint64_t s = 8;
    poisson_draw(ex, img, &s);
    svp_spot_options o;
    svp_spot_defaults(&o);
    svp_spot_result r;
    ASSERT_OK(svp_spot_fit(img, &o, &r, model, res));
    double chi2 = 0;
    for (size_t i = 0; i < 21 * 21; i++) {
        ASSERT_CLOSE(model->data[i] + res->data[i], img->data[i], 1e-9 * img->data[i]);
        chi2 += res->data[i] * res->data[i] / svp_noise_variance(&o.noise, model->data[i]);
    }
    assert_int_equal(r.n_used, 21 * 21);
    ASSERT_CLOSE(chi2, r.chi2, 1e-6 * r.chi2);
    /* non-finite pixels are left out (and get residual 0) */
    img->data[3] = NAN;
    img->data[200] = INFINITY;
    ASSERT_OK(svp_spot_fit(img, &o, &r, model, res));
    assert_int_equal(r.n_used, 21 * 21 - 2);
    assert_true(res->data[3] == 0 && res->data[200] == 0 && test_all_finite(res));
    svp_image *wrong = test_image(20, 21);
    assert_int_equal(svp_spot_fit(img, &o, &r, wrong, NULL), SVP_ERR_SIZE);
    svp_image_free(wrong);
    svp_image_free(ex);
    svp_image_free(img);
    svp_image_free(model);
    svp_image_free(res);
}

/* Workspaces are independent: fits in parallel threads equal the serial ones bit for bit. */
static void test_lm_thread_safety(void **state)
{
    (void)state;
    enum { M = 60, FITS = 32 };
    static double t[M], y[FITS][M], serial[FITS][3], parallel[FITS][3];
    for (int i = 0; i < M; i++) t[i] = 0.1 * i;
    uint64_t s = 5;
    for (int k = 0; k < FITS; k++)
        for (int i = 0; i < M; i++)
            y[k][i] = (2.0 + 0.1 * k) * exp(-t[i] / (1.0 + 0.05 * k)) + 0.3 +
                      0.01 * test_normal(&s);
    for (int pass = 0; pass < 2; pass++) {
        int failures = 0;
#pragma omp parallel if (pass == 1) reduction(+ : failures)
        {
            svp_lm_workspace *ws = NULL;
            if (svp_lm_workspace_new(3, M, &ws) != SVP_OK) failures++;
#pragma omp for schedule(static)
            for (int k = 0; k < FITS; k++) {
                svp_lm_problem pr;
                memset(&pr, 0, sizeof pr);
                pr.n_params = 3;
                pr.n_points = M;
                pr.model = exp_decay;
                pr.user = t;
                pr.data = y[k];
                pr.analytic_jacobian = 1;
                double *p = pass ? parallel[k] : serial[k];
                p[0] = 1;
                p[1] = 0.5;
                p[2] = 0;
                if (!ws || svp_lm_solve(ws, &pr, NULL, p, NULL, NULL) != SVP_OK) failures++;
            }
            svp_lm_workspace_free(ws);
        }
        assert_int_equal(failures, 0);
    }
    for (int k = 0; k < FITS; k++)
        for (int j = 0; j < 3; j++) assert_true(serial[k][j] == parallel[k][j]);
}

/* ---- PSF from an excitation/emission pair --------------------------------------------- */

/* I_G: Moffat β 3.3, FWHM 480 nm; p: Moffat β 1.1, FWHM 610 nm; 50 nm pixels; I_PL = I_G ⊛ p
 * (direct sum over every pixel pair, p untruncated over the image), the emission centre
 * shifted by (shift_x, shift_y) px; both Poisson at peak ~5000 photons over 100. */
static void make_pair(int W, double shift_x, double shift_y, uint64_t seed, svp_image **ig,
                      svp_image **ipl)
{
    const double px_nm = 50.0;
    svp_psf pg = moffat(480.0 / px_nm, 480.0 / px_nm, 0, 3.3);
    svp_psf pp = moffat(610.0 / px_nm, 610.0 / px_nm, 0, 1.1);
    const double cx = 0.5 * W - 0.7, cy = 0.5 * W + 0.2;
    svp_image *g = spot_expected(W, W, &pg, cx, cy, 1.0, 0.0, 4);
    int K = 2 * W - 1;
    double *kern = malloc((size_t)K * K * sizeof(double));
    for (int j = 0; j < K; j++)
        for (int i = 0; i < K; i++)
            kern[(size_t)j * K + i] = svp_psf_profile(&pp, i - (W - 1) - shift_x, j - (W - 1) - shift_y);
    svp_image *pl = test_image(W, W);
    for (int y = 0; y < W; y++)
        for (int x = 0; x < W; x++) {
            double acc = 0;
            for (int sy = 0; sy < W; sy++) {
                const double *krow = kern + (size_t)(y - sy + W - 1) * K + (W - 1) + x;
                const double *grow = g->data + (size_t)sy * W;
                for (int sx = 0; sx < W; sx++) acc += grow[sx] * krow[-sx];
            }
            pl->data[(size_t)y * W + x] = acc;
        }
    double gmax = 0, plmax = 0;
    for (size_t i = 0; i < (size_t)W * W; i++) {
        gmax = fmax(gmax, g->data[i]);
        plmax = fmax(plmax, pl->data[i]);
    }
    uint64_t s = seed;
    for (size_t i = 0; i < (size_t)W * W; i++) {
        g->data[i] = test_poisson(&s, 100.0 + 5000.0 * g->data[i] / gmax);
        pl->data[i] = test_poisson(&s, 100.0 + 5000.0 * pl->data[i] / plmax);
    }
    free(kern);
    *ig = g;
    *ipl = pl;
}

static void test_pair_recovers_psf(void **state)
{
    (void)state;
    enum { W = 96 };
    svp_image *ig = NULL, *ipl = NULL;
    make_pair(W, 2.4, -1.3, 2024, &ig, &ipl);
    svp_pair_options o;
    svp_pair_defaults(&o);
    assert_int_equal(o.iterations, 75);
    svp_pair_result r;
    svp_image *dec = test_image(W, W);
    svp_status st = svp_psf_from_pair(ig, ipl, &o, &r, dec);
    if (st == SVP_ERR_UNSUPPORTED) {
        /* Richardson–Lucy not built yet: the direct fits must still be there */
        assert_true(r.deconvolved_ok == 0 && r.direct.fwhm > 0);
        svp_image_free(ig);
        svp_image_free(ipl);
        svp_image_free(dec);
        skip();
    }
    ASSERT_OK(st);
    const double nm = 50.0;
    printf("# pair: excitation FWHM %.1f nm beta %.3f (480, 3.3); direct PL %.1f nm beta %.3f; "
           "deconvolved (75 RL) %.1f nm beta %.3f (true 610, 1.1); offset (%.2f, %.2f) px\n",
           r.excitation.fwhm * nm, r.excitation.beta, r.direct.fwhm * nm, r.direct.beta,
           r.deconvolved.fwhm * nm, r.deconvolved.beta, r.offset_x, r.offset_y);
    ASSERT_CLOSE(r.excitation.fwhm * nm, 480.0, 0.02 * 480);
    ASSERT_CLOSE(r.excitation.beta, 3.3, 0.05 * 3.3);
    assert_true(r.deconvolved_ok);
    ASSERT_CLOSE(r.offset_x, 2.4, 0.1);
    ASSERT_CLOSE(r.offset_y, -1.3, 0.1);
    /* the direct fit is the upper bound; 75 RL iterations leave p a few % wide */
    assert_true(r.direct.fwhm > r.deconvolved.fwhm);
    assert_true(r.direct.fwhm * nm > 900.0);
    ASSERT_CLOSE(r.deconvolved.fwhm * nm, 610.0, 0.08 * 610);
    ASSERT_CLOSE(r.deconvolved.beta, 1.1, 0.15 * 1.1);
    /* more iterations approach p */
    o.iterations = 300;
    svp_pair_result r2;
    ASSERT_OK(svp_psf_from_pair(ig, ipl, &o, &r2, NULL));
    printf("# pair: deconvolved (300 RL) %.1f nm beta %.3f\n", r2.deconvolved.fwhm * nm,
           r2.deconvolved.beta);
    assert_true(fabs(r2.deconvolved.fwhm * nm - 610) < fabs(r.deconvolved.fwhm * nm - 610));
    ASSERT_CLOSE(r2.deconvolved.fwhm * nm, 610.0, 0.04 * 610);
    ASSERT_CLOSE(r2.deconvolved.beta, 1.1, 0.10 * 1.1);
    /* the fitted (noise-free) excitation model as kernel gives the same p */
    o.iterations = 75;
    o.kernel_from_fit = 1;
    ASSERT_OK(svp_psf_from_pair(ig, ipl, &o, &r2, NULL));
    printf("# pair: deconvolved with the fitted kernel (75 RL) %.1f nm beta %.3f\n",
           r2.deconvolved.fwhm * nm, r2.deconvolved.beta);
    ASSERT_CLOSE(r2.deconvolved.fwhm, r.deconvolved.fwhm, 0.02 * r.deconvolved.fwhm);
    ASSERT_CLOSE(r2.deconvolved.beta, r.deconvolved.beta, 0.05 * r.deconvolved.beta);
    /* bad input */
    svp_image *small = test_image(40, 40);
    assert_int_equal(svp_psf_from_pair(ig, small, &o, &r2, NULL), SVP_ERR_SIZE);
    o.iterations = 0;
    assert_int_equal(svp_psf_from_pair(ig, ipl, &o, &r2, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "iterations"));
    svp_image_free(small);
    svp_image_free(ig);
    svp_image_free(ipl);
    svp_image_free(dec);
}

/* ---- PSF maps ----------------------------------------------------------------------------- */

/* The truth of the mapped field: FWHM linear, β quadratic in the normalised position. */
static void field_truth(double x, double y, int W, int H, double *fwhm, double *beta)
{
    double u = (2 * x - (W - 1)) / (W - 1), v = (2 * y - (H - 1)) / (H - 1);
    *fwhm = 4.0 + 1.0 * u + 0.4 * v;
    *beta = 2.2 + 0.8 * u * u + 0.3 * v;
}

/* The surface's standard error (svp_map_report.surface_se_max) against the closed form: four
 * spots of equal value and error σ at u, v = ±a (a = 1/2) make the degree-1 design orthogonal,
 * so at a corner (u, v = ±1) se² = σ² (1/4 + 1/(4a²) + 1/(4a²)) = (3σ/2)²; degree 0 gives σ/2.
 * Spots along one row leave the v term to their ±1 px scatter: a ratio in the thousands. */
static void test_map_poly_surface_error(void **state)
{
    (void)state;
    enum { W = 401, H = 401 };
    svp_psf_sample sp[4];
    memset(sp, 0, sizeof sp);
    const double sigma = 0.1;
    for (int k = 0; k < 4; k++) {
        sp[k].x = k % 2 ? 300 : 100;
        sp[k].y = k / 2 ? 300 : 100;
        sp[k].fit.model = SVP_PSF_MOFFAT;
        sp[k].fit.fwhm = 4.0;
        sp[k].fit.fwhm_err = sigma;
        sp[k].fit.e1_err = sp[k].fit.e2_err = 0.01;
        sp[k].fit.beta = 2.5;
        sp[k].fit.beta_err = 0.05;
    }
    svp_map_options mo;
    svp_map_defaults(&mo);
    mo.clip_kappa = 0;
    for (int deg = 0; deg <= 1; deg++) {
        mo.degree = deg;
        svp_map_report *rep = NULL;
        ASSERT_OK(svp_psf_map_poly(sp, 4, W, H, &mo, NULL, &rep));
        assert_int_equal(rep->degree[SVP_FIELD_FWHM], deg);
        ASSERT_CLOSE(rep->spot_se_median[SVP_FIELD_FWHM], sigma, 1e-15);
        ASSERT_CLOSE(rep->surface_se_max[SVP_FIELD_FWHM], deg ? 1.5 * sigma : 0.5 * sigma, 1e-12);
        if (deg) /* at a corner */
            assert_true((rep->surface_se_x[SVP_FIELD_FWHM] == 0 ||
                         rep->surface_se_x[SVP_FIELD_FWHM] == W - 1) &&
                        (rep->surface_se_y[SVP_FIELD_FWHM] == 0 ||
                         rep->surface_se_y[SVP_FIELD_FWHM] == H - 1));
        svp_map_report_free(rep);
    }
    /* a row: y 199, 200, 201, 200 */
    for (int k = 0; k < 4; k++) {
        sp[k].x = 50 + 100 * k;
        sp[k].y = 199 + (k % 3);
    }
    svp_map_report *rep = NULL;
    ASSERT_OK(svp_psf_map_poly(sp, 4, W, H, &mo, NULL, &rep));
    const double ratio = rep->surface_se_max[SVP_FIELD_FWHM] / rep->spot_se_median[SVP_FIELD_FWHM];
    printf("# map of a row of spots, degree 1: surface error %.3g = %.3g x a spot's\n",
           rep->surface_se_max[SVP_FIELD_FWHM], ratio);
    assert_true(ratio > 100);
    svp_map_report_free(rep);
}

static void test_map_poly_recovers_field(void **state)
{
    (void)state;
    enum { W = 400, H = 400, CUT = 25, N = 25 };
    svp_psf_sample samples[N + 2];
    uint64_t s = 2718;
    svp_spot_options so;
    svp_spot_defaults(&so);
    svp_image *img = test_image(CUT, CUT);
    for (int k = 0; k < N; k++) {
        double cx = 40 + 80 * (k % 5) + 10 * (test_rand(&s) - 0.5);
        double cy = 40 + 80 * (k / 5) + 10 * (test_rand(&s) - 0.5);
        double F, B;
        field_truth(cx, cy, W, H, &F, &B);
        svp_psf truth = moffat(F, F, 0, B);
        int ox = (int)floor(cx) - CUT / 2, oy = (int)floor(cy) - CUT / 2;
        svp_image *ex = spot_expected(CUT, CUT, &truth, cx - ox, cy - oy, 5000.0, 100.0, 6);
        poisson_draw(ex, img, &s);
        ASSERT_OK(svp_spot_fit(img, &so, &samples[k].fit, NULL, NULL));
        samples[k].x = ox + samples[k].fit.x0;
        samples[k].y = oy + samples[k].fit.y0;
        svp_image_free(ex);
    }
    /* two bad spots: one flagged near the border, one with a wrong width */
    samples[N] = samples[3];
    samples[N].fit.flags |= SVP_SPOT_NEAR_BORDER;
    samples[N + 1] = samples[12];
    samples[N + 1].fit.fwhm *= 1.3;
    svp_psf_field *field = NULL;
    svp_map_report *rep = NULL;
    ASSERT_OK(svp_psf_map_poly(samples, N + 2, W, H, NULL, &field, &rep));
    printf("# map: degrees fwhm %d, beta %d, e1 %d, e2 %d; chi2_red fwhm %.2f beta %.2f; used "
           "%d, %d\n", rep->degree[SVP_FIELD_FWHM], rep->degree[SVP_FIELD_BETA],
           rep->degree[SVP_FIELD_E1], rep->degree[SVP_FIELD_E2], rep->chi2_red[SVP_FIELD_FWHM],
           rep->chi2_red[SVP_FIELD_BETA], rep->n_used[SVP_FIELD_FWHM],
           rep->n_used[SVP_FIELD_BETA]);
    assert_true(rep->degree[SVP_FIELD_FWHM] >= 1 && rep->degree[SVP_FIELD_FWHM] <= 2);
    assert_true(rep->degree[SVP_FIELD_BETA] >= 2);
    assert_int_equal(svp_psf_field_get_kind(field), SVP_FIELD_POLY);
    /* reasons */
    char buf[512];
    svp_map_describe_sample(rep, samples, N, buf, sizeof buf);
    printf("# %s\n", buf);
    assert_non_null(strstr(buf, "rejected: spot fit flagged (near border)"));
    svp_map_describe_sample(rep, samples, N + 1, buf, sizeof buf);
    printf("# %s\n", buf);
    assert_non_null(strstr(buf, "fwhm outlier (z = "));
    assert_int_equal(rep->reject[(size_t)(N + 1) * SVP_FIELD_NPARAM + SVP_FIELD_BETA],
                     SVP_MAP_KEPT);
    svp_map_describe_sample(rep, samples, 0, buf, sizeof buf);
    assert_non_null(strstr(buf, ": kept"));
    assert_int_equal(rep->n_used[SVP_FIELD_FWHM], N);
    /* the surfaces over the spots' area */
    double worst_f = 0, worst_b = 0, worst_e = 0;
    for (int j = 0; j <= 8; j++)
        for (int i = 0; i <= 8; i++) {
            double x = 40 + 40 * i, y = 40 + 40 * j, F, B, p[SVP_FIELD_NPARAM];
            field_truth(x, y, W, H, &F, &B);
            ASSERT_OK(svp_psf_field_params_at(field, x, y, p));
            worst_f = fmax(worst_f, fabs(p[SVP_FIELD_FWHM] / F - 1));
            worst_b = fmax(worst_b, fabs(p[SVP_FIELD_BETA] / B - 1));
            worst_e = fmax(worst_e, hypot(p[SVP_FIELD_E1], p[SVP_FIELD_E2]));
        }
    printf("# map: worst relative error over the view: FWHM %.2f%%, beta %.2f%%; |e| <= %.4f\n",
           100 * worst_f, 100 * worst_b, worst_e);
    assert_true(worst_f < 0.02);
    assert_true(worst_b < 0.05);
    assert_true(worst_e < 0.02);
    /* the map survives the PSF-map file (what `svpsf correct` reads) */
    char path[128];
    snprintf(path, sizeof path, "/tmp/svpsf_test_fit_map_%ld.yaml", (long)getpid());
    ASSERT_OK(svp_psf_field_write(path, field, 0.05, "test_fit", 1));
    svp_psf_field *back = NULL;
    double pixel_um = 0;
    ASSERT_OK(svp_psf_field_read(path, &back, &pixel_um));
    remove(path);
    ASSERT_CLOSE(pixel_um, 0.05, 1e-12);
    for (int k = 0; k < 5; k++) {
        double x = 17 + 91 * k, y = 380 - 83 * k, pa[SVP_FIELD_NPARAM], pb[SVP_FIELD_NPARAM];
        ASSERT_OK(svp_psf_field_params_at(field, x, y, pa));
        ASSERT_OK(svp_psf_field_params_at(back, x, y, pb));
        for (int q = 0; q < SVP_FIELD_NPARAM; q++) ASSERT_CLOSE(pa[q], pb[q], 1e-9);
    }
    svp_psf_field_free(back);
    svp_psf_field_free(field);
    svp_map_report_free(rep);

    /* a fixed degree; and everything flagged is an error naming the counts */
    svp_map_options mo;
    svp_map_defaults(&mo);
    mo.degree = 2;
    ASSERT_OK(svp_psf_map_poly(samples, N, W, H, &mo, NULL, &rep));
    assert_int_equal(rep->degree[SVP_FIELD_FWHM], 2);
    svp_map_report_free(rep);
    for (int k = 0; k < N; k++) samples[k].fit.flags |= SVP_SPOT_NOT_CONVERGED;
    assert_int_equal(svp_psf_map_poly(samples, N, W, H, NULL, &field, &rep), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "only 0 of 25 spots usable for fwhm (rejected: 25 "
                                             "flagged"));
    assert_null(field);
    assert_null(rep);
    mo.folds = 1;
    assert_int_equal(svp_psf_map_poly(samples, N, W, H, &mo, NULL, NULL), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "folds"));
    svp_image_free(img);
}

/* Two-sided p of Welch's test by numerical integration of the t density (Simpson). */
static double ref_welch_p(const double *a, int na, const double *b, int nb)
{
    double ma = 0, mb = 0, va = 0, vb = 0;
    for (int i = 0; i < na; i++) ma += a[i] / na;
    for (int i = 0; i < nb; i++) mb += b[i] / nb;
    for (int i = 0; i < na; i++) va += (a[i] - ma) * (a[i] - ma) / (na - 1);
    for (int i = 0; i < nb; i++) vb += (b[i] - mb) * (b[i] - mb) / (nb - 1);
    double se2 = va / na + vb / nb, t = fabs(ma - mb) / sqrt(se2);
    double nu = se2 * se2 / ((va / na) * (va / na) / (na - 1) + (vb / nb) * (vb / nb) / (nb - 1));
    double c = exp(lgamma(0.5 * (nu + 1)) - lgamma(0.5 * nu)) / sqrt(nu * M_PI);
    const int M = 20000;
    double h = t / M, acc = 0;
    for (int i = 0; i <= M; i++) {
        double x = i * h, f = c * pow(1 + x * x / nu, -0.5 * (nu + 1));
        acc += (i == 0 || i == M ? 1 : i % 2 ? 4 : 2) * f;
    }
    return 1.0 - 2.0 * acc * h / 3.0;
}

static void region_samples(svp_psf_sample *smp, int n, double x_lo, double x_hi, double fwhm,
                           double beta, double scatter, uint64_t *s, double *vf, double *vb)
{
    for (int i = 0; i < n; i++) {
        memset(&smp[i], 0, sizeof smp[i]);
        smp[i].x = x_lo + (x_hi - x_lo) * test_rand(s);
        smp[i].y = 63 * test_rand(s);
        smp[i].fit.model = SVP_PSF_MOFFAT;
        smp[i].fit.fwhm = vf[i] = fwhm + scatter * test_normal(s);
        smp[i].fit.fwhm_err = scatter;
        smp[i].fit.beta = vb[i] = beta + scatter * test_normal(s);
        smp[i].fit.beta_err = scatter;
    }
}

static void test_map_regions_separate_or_merge(void **state)
{
    (void)state;
    enum { W = 64, H = 64, NR = 12 };
    int *labels = malloc(W * H * sizeof(int));
    for (int y = 0; y < H; y++)
        for (int x = 0; x < W; x++) labels[y * W + x] = x < W / 2 ? 0 : 1; /* oxide | metal */
    svp_psf_sample smp[3 * NR];
    double f0[NR], b0[NR], f1[NR], b1[NR];
    uint64_t s = 161803;
    for (int differ = 1; differ >= 0; differ--) {
        region_samples(smp, NR, 0, 31, 5.0, 2.0, 0.08, &s, f0, b0);
        region_samples(smp + NR, NR, 33, 63, differ ? 5.6 : 5.0, differ ? 1.6 : 2.0, 0.08, &s,
                       f1, b1);
        svp_psf_field *field = NULL;
        svp_map_report *rep = NULL;
        ASSERT_OK(svp_psf_map_regions(smp, 2 * NR, labels, W, H, 2, NULL, &field, &rep));
        double pf = ref_welch_p(f0, NR, f1, NR), pb = ref_welch_p(b0, NR, b1, NR);
        double pref = fmin(1.0, 2 * fmin(pf, pb)); /* Bonferroni over fwhm and beta */
        printf("# regions (%s): oxide fwhm %.3f +- %.3f beta %.3f, metal fwhm %.3f +- %.3f beta "
               "%.3f; Welch p %.3g (reference %.3g); %d group(s)\n",
               differ ? "different" : "same", rep->regions[0].mean[0], rep->regions[0].sem[0],
               rep->regions[0].mean[3], rep->regions[1].mean[0], rep->regions[1].sem[0],
               rep->regions[1].mean[3], rep->p_value[1], pref, rep->n_groups);
        ASSERT_CLOSE(rep->p_value[1], pref, 1e-7 + 1e-6 * pref);
        assert_int_equal(rep->regions[0].count, NR);
        assert_int_equal(rep->regions[1].count, NR);
        double p0[SVP_FIELD_NPARAM], p1[SVP_FIELD_NPARAM];
        ASSERT_OK(svp_psf_field_params_at(field, 10, 30, p0));
        ASSERT_OK(svp_psf_field_params_at(field, 50, 30, p1));
        if (differ) {
            assert_int_equal(rep->n_groups, 2);
            assert_true(rep->p_value[1] < 1e-6);
            ASSERT_CLOSE(p0[SVP_FIELD_FWHM], 5.0, 0.1);
            ASSERT_CLOSE(p1[SVP_FIELD_FWHM], 5.6, 0.1);
            ASSERT_CLOSE(p1[SVP_FIELD_BETA], 1.6, 0.1);
        } else {
            assert_int_equal(rep->n_groups, 1);
            assert_true(rep->p_value[1] > 0.01);
            assert_int_equal(rep->groups[0].count, 2 * NR);
            ASSERT_CLOSE(p0[SVP_FIELD_FWHM], p1[SVP_FIELD_FWHM], 1e-12);
            ASSERT_CLOSE(p0[SVP_FIELD_FWHM], rep->groups[0].mean[SVP_FIELD_FWHM], 1e-12);
        }
        svp_psf_field_free(field);
        svp_map_report_free(rep);
    }
    /* three regions: two alike, one different → two groups */
    for (int y = 0; y < H; y++)
        for (int x = 0; x < W; x++) labels[y * W + x] = x < 21 ? 0 : x < 42 ? 1 : 2;
    region_samples(smp, NR, 0, 20, 5.0, 2.0, 0.08, &s, f0, b0);
    region_samples(smp + NR, NR, 21.5, 41, 5.0, 2.0, 0.08, &s, f0, b0);
    region_samples(smp + 2 * NR, NR, 42.5, 63, 6.0, 1.5, 0.08, &s, f1, b1);
    svp_map_report *rep = NULL;
    ASSERT_OK(svp_psf_map_regions(smp, 3 * NR, labels, W, H, 3, NULL, NULL, &rep));
    assert_int_equal(rep->n_groups, 2);
    assert_int_equal(rep->regions[0].group, rep->regions[1].group);
    assert_true(rep->regions[2].group != rep->regions[0].group);
    svp_map_report_free(rep);
    /* a label outside 0..n_labels-1 under a spot rejects it with a reason */
    labels[30 * W + 10] = 7;
    smp[0].x = 10;
    smp[0].y = 30;
    ASSERT_OK(svp_psf_map_regions(smp, 3 * NR, labels, W, H, 3, NULL, NULL, &rep));
    assert_int_equal(rep->reject[0], SVP_MAP_REJECT_OUTSIDE);
    assert_int_equal(rep->regions[0].count, NR - 1);
    svp_map_report_free(rep);
    free(labels);
}

int main(void)
{
    svp_set_fft_effort(SVP_FFT_ESTIMATE);
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_lm_rosenbrock),
        cmocka_unit_test(test_lm_exponential_decay),
        cmocka_unit_test(test_lm_linear_covariance),
        cmocka_unit_test(test_lm_noise_model_weights),
        cmocka_unit_test(test_lm_not_converged_and_bad_input),
        cmocka_unit_test(test_lm_thread_safety),
        cmocka_unit_test(test_spot_exact_data),
        cmocka_unit_test(test_spot_poisson_accuracy),
        cmocka_unit_test(test_spot_coverage),
        cmocka_unit_test(test_spot_hot_pixel),
        cmocka_unit_test(test_spot_border_saturation_empty),
        cmocka_unit_test(test_spot_beta_bound_and_no_convergence),
        cmocka_unit_test(test_spot_model_residual),
        cmocka_unit_test(test_pair_recovers_psf),
        cmocka_unit_test(test_map_poly_recovers_field),
        cmocka_unit_test(test_map_poly_surface_error),
        cmocka_unit_test(test_map_regions_separate_or_merge),
    };
    if (getenv("SVP_TEST_FILTER")) cmocka_set_test_filter(getenv("SVP_TEST_FILTER"));
    int rc = cmocka_run_group_tests_name("fit", tests, NULL, NULL);
    svp_fft_cleanup();
    return rc;
}
