/* PSF models (docs/model.md §PSF): FWHM ↔ r0, Lorentzian = Moffat β = 1, encircled energy
 * against a numerical radial integral written here, kernel normalisation, pixel integration,
 * elliptical orientation, validation messages. */
#include "test_helpers.h"

#include "core/internal.h"
#include "psf/field_internal.h"

#include <stdio.h>

static svp_psf make_psf(svp_psf_model model, double fwhm, double beta)
{
    svp_psf p;
    svp_psf_defaults(&p);
    p.model = model;
    p.fwhm = fwhm;
    p.beta = beta;
    return p;
}

static svp_image *render(const svp_psf *p, int rx, int ry)
{
    svp_image *k = NULL;
    ASSERT_OK(svp_psf_render(p, rx, ry, &k));
    return k;
}

static double kernel_sum(const svp_image *k) { return test_sum(k); }

/* ---- independent reference: the radial profiles and a numerical integral ----------------- */

typedef struct radial_ref {
    int gaussian;
    double scale; /* σ or r0, computed here from the FWHM without the library */
    double beta;
} radial_ref;

static radial_ref radial_ref_make(int gaussian, double fwhm, double beta)
{
    radial_ref f = {gaussian, 0, beta};
    if (gaussian)
        f.scale = fwhm / (2.0 * sqrt(2.0 * log(2.0)));
    else
        f.scale = 0.5 * fwhm / sqrt(pow(2.0, 1.0 / beta) - 1.0);
    return f;
}

/* ρ · profile(ρ): the integrand of the flux inside radius r (the 2π cancels in ratios). */
static double radial_integrand(const radial_ref *f, double rho)
{
    double q = (rho / f->scale) * (rho / f->scale);
    double v = f->gaussian ? exp(-0.5 * q) : pow(1.0 + q, -f->beta);
    return rho * v;
}

static double simpson_step(const radial_ref *f, double a, double b, double fa, double fm, double fb,
                           double whole, double tol, int depth)
{
    double m = 0.5 * (a + b), lm = 0.5 * (a + m), rm = 0.5 * (m + b);
    double flm = radial_integrand(f, lm), frm = radial_integrand(f, rm);
    double left = (m - a) / 6.0 * (fa + 4.0 * flm + fm);
    double right = (b - m) / 6.0 * (fm + 4.0 * frm + fb);
    double delta = left + right - whole;
    if (depth <= 0 || fabs(delta) <= 15.0 * tol) return left + right + delta / 15.0;
    return simpson_step(f, a, m, fa, flm, fm, left, 0.5 * tol, depth - 1) +
           simpson_step(f, m, b, fm, frm, fb, right, 0.5 * tol, depth - 1);
}

/* ∫_0^r ρ p(ρ) dρ by adaptive Simpson on panels growing geometrically from the centre, so the
 * core and the long tail both get resolved. */
static double radial_flux(const radial_ref *f, double r)
{
    double total = 0, a = 0, b = fmin(r, 0.125 * f->scale);
    while (a < r) {
        double fa = radial_integrand(f, a), fb = radial_integrand(f, b);
        double fm = radial_integrand(f, 0.5 * (a + b));
        double whole = (b - a) / 6.0 * (fa + 4.0 * fm + fb);
        total += simpson_step(f, a, b, fa, fm, fb, whole, 1e-16 * (b - a) / f->scale, 40);
        a = b;
        b = fmin(r, 2.0 * b);
    }
    return total;
}

/* ---- FWHM and r0 ------------------------------------------------------------------------ */

static void test_fwhm_r0(void **state)
{
    (void)state;
    const double betas[] = {0.5, 0.9, 1.0, 1.1, 1.4, 2.5, 3.3, 10.0, 1e3};
    const double fwhms[] = {0.3, 2.0, 6.1, 47.0};
    for (size_t i = 0; i < sizeof betas / sizeof betas[0]; i++)
        for (size_t j = 0; j < sizeof fwhms / sizeof fwhms[0]; j++) {
            svp_psf p = make_psf(SVP_PSF_MOFFAT, fwhms[j], betas[i]);
            double h = 0.5 * fwhms[j];
            /* half maximum at FWHM/2 along x, y and a diagonal */
            ASSERT_CLOSE(svp_psf_profile(&p, h, 0), 0.5, 1e-12);
            ASSERT_CLOSE(svp_psf_profile(&p, 0, -h), 0.5, 1e-12);
            ASSERT_CLOSE(svp_psf_profile(&p, h / sqrt(2.0), h / sqrt(2.0)), 0.5, 1e-12);
            ASSERT_CLOSE(svp_psf_profile(&p, 0, 0), 1.0, 0);
            /* r0 against the closed form with pow (the library uses expm1) */
            double r0 = 0.5 * fwhms[j] / sqrt(pow(2.0, 1.0 / betas[i]) - 1.0);
            ASSERT_CLOSE(svp_psf_fwhm_to_r0(fwhms[j], betas[i]), r0, 1e-12 * r0);
            /* at r0 the Moffat profile is 2^-β */
            ASSERT_CLOSE(svp_psf_profile(&p, r0, 0), pow(2.0, -betas[i]), 1e-12);
        }
    for (size_t j = 0; j < sizeof fwhms / sizeof fwhms[0]; j++) {
        svp_psf g = make_psf(SVP_PSF_GAUSSIAN, fwhms[j], 0);
        ASSERT_CLOSE(svp_psf_profile(&g, 0.5 * fwhms[j], 0), 0.5, 1e-12);
        ASSERT_CLOSE(svp_psf_fwhm_to_r0(fwhms[j], 0), fwhms[j] / 2.3548200450309493, 1e-12);
    }
    /* large β tends to the Gaussian of the same FWHM (difference O(1/β)) */
    svp_psf m = make_psf(SVP_PSF_MOFFAT, 3.0, 1e6), g = make_psf(SVP_PSF_GAUSSIAN, 3.0, 0);
    for (double r = 0; r < 6; r += 0.25)
        ASSERT_CLOSE(svp_psf_profile(&m, r, 0), svp_psf_profile(&g, r, 0), 1e-5);
    /* elliptical: half maximum at the two FWHMs along the rotated axes */
    svp_psf e = make_psf(SVP_PSF_MOFFAT, 6.0, 2.5);
    e.fwhm_minor = 3.0;
    e.angle = 0.4;
    double c = cos(e.angle), s = sin(e.angle);
    ASSERT_CLOSE(svp_psf_profile(&e, 3.0 * c, 3.0 * s), 0.5, 1e-12);
    ASSERT_CLOSE(svp_psf_profile(&e, -1.5 * s, 1.5 * c), 0.5, 1e-12);
}

static void test_lorentzian_is_moffat_1(void **state)
{
    (void)state;
    svp_psf lor = make_psf(SVP_PSF_LORENTZIAN, 4.2, 7.0); /* beta is ignored: forced to 1 */
    svp_psf mof = make_psf(SVP_PSF_MOFFAT, 4.2, 1.0);
    for (double r = 0; r < 200; r = r * 1.3 + 0.1)
        ASSERT_CLOSE(svp_psf_profile(&lor, r, 0.3 * r), svp_psf_profile(&mof, r, 0.3 * r), 1e-15);
    ASSERT_CLOSE(svp_psf_encircled_energy(&lor, 5.0, 80.0),
                 svp_psf_encircled_energy(&mof, 5.0, 80.0), 1e-15);
    svp_image *kl = render(&lor, 40, 25), *km = render(&mof, 40, 25);
    double d = test_max_abs_diff(kl, km);
    if (d > 1e-16) fail_msg("Lorentzian and Moffat beta = 1 kernels differ by %.3g", d);
    svp_image_free(kl);
    svp_image_free(km);
}

/* ---- encircled energy -------------------------------------------------------------------- */

static void test_encircled_energy_vs_quadrature(void **state)
{
    (void)state;
    struct {
        svp_psf_model model;
        double beta;
    } cases[] = {{SVP_PSF_GAUSSIAN, 0}, {SVP_PSF_MOFFAT, 3.3}, {SVP_PSF_MOFFAT, 1.1},
                 {SVP_PSF_MOFFAT, 1.0}, {SVP_PSF_MOFFAT, 0.9}, {SVP_PSF_LORENTZIAN, 1.0}};
    const double fwhm = 3.0, discs[] = {12.0, 60.0, 400.0};
    const double radii[] = {0.2, 1.0, 1.5, 3.0, 7.5, 11.9};
    double worst = 0;
    for (size_t c = 0; c < sizeof cases / sizeof cases[0]; c++) {
        svp_psf p = make_psf(cases[c].model, fwhm, cases[c].beta);
        radial_ref f = radial_ref_make(cases[c].model == SVP_PSF_GAUSSIAN, fwhm,
                                       cases[c].beta > 0 ? cases[c].beta : 1.0);
        for (size_t d = 0; d < sizeof discs / sizeof discs[0]; d++) {
            double R = discs[d], total = radial_flux(&f, R);
            for (size_t k = 0; k < sizeof radii / sizeof radii[0]; k++) {
                double r = radii[k] * R / 12.0;
                double ref = radial_flux(&f, r) / total;
                double got = svp_psf_encircled_energy(&p, r, R);
                double err = fabs(got - ref);
                if (err > worst) worst = err;
                if (err > 1e-10)
                    fail_msg("model %d beta %g: EE(r = %g, R = %g) = %.15g, quadrature %.15g",
                             (int)cases[c].model, cases[c].beta, r, R, got, ref);
            }
            ASSERT_CLOSE(svp_psf_encircled_energy(&p, R, R), 1.0, 0);
            ASSERT_CLOSE(svp_psf_encircled_energy(&p, 0.0, R), 0.0, 0);
        }
    }
    /* infinite plane where the flux converges: Gaussian and β = 3.3 (tails beyond 1e4 px hold
     * < 1e-17 of the flux) */
    for (int c = 0; c < 2; c++) {
        svp_psf p = make_psf(c ? SVP_PSF_MOFFAT : SVP_PSF_GAUSSIAN, fwhm, 3.3);
        radial_ref f = radial_ref_make(!c, fwhm, 3.3);
        double total = radial_flux(&f, 1e4);
        for (double r = 0.5; r < 20; r *= 2)
            ASSERT_CLOSE(svp_psf_encircled_energy(&p, r, 0), radial_flux(&f, r) / total, 1e-10);
    }
    /* β <= 1 over the infinite plane diverges: NaN, and the radius inversion refuses */
    svp_psf lor = make_psf(SVP_PSF_MOFFAT, fwhm, 0.9);
    assert_true(isnan(svp_psf_encircled_energy(&lor, 2.0, 0)));
    double rad = 0;
    assert_int_equal(svp_psf_encircled_radius(&lor, 0.5, 0, &rad), SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "support"));
    print_message("encircled energy vs quadrature: worst |diff| %.3g\n", worst);
}

/* Elliptical profiles: the encircled energy against a quadrature over the disc in the image
 * plane, in polar coordinates about the centre (the trapezoid rule over the direction θ, exact
 * to round-off for this periodic integrand; along each direction the profile is radial with
 * the scale 1 / √(cos²(θ − angle) / a² + sin²(θ − angle) / b²)): a quadrature in other
 * coordinates than the library's. Before, the library took a circular profile of the
 * geometric-mean FWHM: 6 % (EE50) and 10 % (EE90) too small a radius at axes 2 : 1. */
static double ellipse_flux(int gaussian, double fwhm, double fwhm_minor, double beta, double angle,
                           double r)
{
    const radial_ref fa = radial_ref_make(gaussian, fwhm, beta);
    const radial_ref fb = radial_ref_make(gaussian, fwhm_minor, beta);
    const int n = 512;
    double sum = 0;
    for (int k = 0; k < n; k++) {
        const double t = 2.0 * M_PI * k / n - angle;
        const double kk = cos(t) * cos(t) / (fa.scale * fa.scale) +
                          sin(t) * sin(t) / (fb.scale * fb.scale);
        radial_ref f = fa;
        f.scale = 1.0 / sqrt(kk);
        sum += radial_flux(&f, r);
    }
    return sum / n;
}

static void test_encircled_energy_elliptical(void **state)
{
    (void)state;
    struct {
        svp_psf_model model;
        double beta, ratio;
    } cases[] = {{SVP_PSF_GAUSSIAN, 0, 0.5}, {SVP_PSF_MOFFAT, 3.3, 0.8}, {SVP_PSF_MOFFAT, 1.5, 0.5},
                 {SVP_PSF_MOFFAT, 2.0, 0.25}, {SVP_PSF_MOFFAT, 1.0, 0.5}};
    const double fwhm = 4.0, angle = 0.4;
    double worst = 0;
    for (size_t c = 0; c < sizeof cases / sizeof cases[0]; c++) {
        svp_psf p = make_psf(cases[c].model, fwhm, cases[c].beta);
        p.fwhm_minor = cases[c].ratio * fwhm;
        p.angle = angle;
        const int gaussian = cases[c].model == SVP_PSF_GAUSSIAN;
        const double beta = gaussian ? 1.0 : cases[c].beta;
        const int converges = gaussian || beta > 1.0;
        const double discs[] = {30.0, 0.0};
        for (int d = 0; d < 2; d++) {
            const double R = discs[d];
            if (R == 0 && !converges) continue;
            /* beyond 1e4 px a β 1.5 Moffat still holds 1e-4 of its flux: its plane total
             * is the closed form 2π a b / (2 (β − 1)) / (2π) here */
            double total;
            if (R > 0)
                total = ellipse_flux(gaussian, fwhm, p.fwhm_minor, beta, angle, R);
            else {
                const radial_ref fa = radial_ref_make(gaussian, fwhm, beta);
                const radial_ref fb = radial_ref_make(gaussian, p.fwhm_minor, beta);
                total = fa.scale * fb.scale / (gaussian ? 1.0 : 2.0 * (beta - 1.0));
            }
            for (double r = 0.5; r < 29; r *= 1.9) {
                const double ref = ellipse_flux(gaussian, fwhm, p.fwhm_minor, beta, angle, r) / total;
                const double got = svp_psf_encircled_energy(&p, r, R);
                worst = fmax(worst, fabs(got - ref));
                if (!(fabs(got - ref) <= 1e-9))
                    fail_msg("model %d beta %g axes 1 : %g: EE(r = %g, R = %g) = %.15g, "
                             "quadrature %.15g",
                             (int)cases[c].model, cases[c].beta, cases[c].ratio, r, R, got, ref);
                if (1.0 - got < 1e-4) continue; /* EE is flat there: no radius to invert */
                double back = 0;
                ASSERT_OK(svp_psf_encircled_radius(&p, got, R, &back));
                ASSERT_CLOSE(back, r, 1e-9 * r);
            }
        }
    }
    /* an extreme ellipse (axes 1 : 1e-6) ends, and lies between the circular ones */
    svp_psf thin = make_psf(SVP_PSF_MOFFAT, 6.0, 2.0), wide = thin, narrow = thin;
    thin.fwhm_minor = 6e-6;
    narrow.fwhm = 6e-6;
    double r50 = 0, r50_wide = 0, r50_narrow = 0;
    ASSERT_OK(svp_psf_encircled_radius(&thin, 0.5, 0, &r50));
    ASSERT_OK(svp_psf_encircled_radius(&wide, 0.5, 0, &r50_wide));
    ASSERT_OK(svp_psf_encircled_radius(&narrow, 0.5, 0, &r50_narrow));
    assert_true(r50 > r50_narrow && r50 < r50_wide);
    print_message("elliptical encircled energy vs quadrature: worst |diff| %.3g; axes 1 : 1e-6 "
                  "EE50 at %.4g px (circular %.4g / %.4g)\n",
                  worst, r50, r50_narrow, r50_wide);
}

static void test_encircled_energy_near_beta_1(void **state)
{
    (void)state;
    const double R = 150.0, fwhm = 2.5;
    svp_psf one = make_psf(SVP_PSF_MOFFAT, fwhm, 1.0);
    double worst = 0;
    for (int sign = -1; sign <= 1; sign += 2)
        for (int e = 15; e >= 6; e--) {
            double db = sign * pow(10.0, -e);
            svp_psf near = make_psf(SVP_PSF_MOFFAT, fwhm, 1.0 + db);
            for (double r = 0.25; r < R; r *= 1.7) {
                double a = svp_psf_encircled_energy(&near, r, R);
                double b = svp_psf_encircled_energy(&one, r, R);
                assert_true(isfinite(a));
                /* dEE/dβ is O(ln² R) ≈ 25 here: allow 100 |Δβ| plus round-off */
                double tol = 100.0 * fabs(db) + 1e-13;
                if (fabs(a - b) > tol)
                    fail_msg("beta = 1 %+g: EE(%g) = %.17g vs %.17g at beta = 1", db, r, a, b);
                if (fabs(db) == 1e-12 && fabs(a - b) > worst) worst = fabs(a - b);
                double rr = 0;
                ASSERT_OK(svp_psf_encircled_radius(&near, a, R, &rr));
                ASSERT_CLOSE(rr, r, 1e-9 * r);
            }
        }
    if (worst > 1e-9) fail_msg("beta = 1 ± 1e-12 differs from beta = 1 by %.3g", worst);
    /* the rendered kernels are continuous in β too */
    svp_psf near = make_psf(SVP_PSF_MOFFAT, fwhm, 1.0 + 1e-12);
    svp_image *ka = render(&near, 30, 30), *kb = render(&one, 30, 30);
    ASSERT_CLOSE(test_max_abs_diff(ka, kb), 0.0, 1e-12);
    svp_image_free(ka);
    svp_image_free(kb);
    print_message("beta = 1 ± 1e-12: max |EE - EE(beta = 1)| = %.3g\n", worst);
}

static void test_encircled_radius_inverts(void **state)
{
    (void)state;
    const double fractions[] = {1e-4, 0.1, 0.5, 0.8, 0.95, 0.999};
    const double betas[] = {0.9, 1.0, 1.1, 1.4, 3.3};
    const double discs[] = {0.0, 25.0, 1e3};
    for (int model = 0; model < 3; model++)
        for (size_t b = 0; b < sizeof betas / sizeof betas[0]; b++)
            for (size_t d = 0; d < sizeof discs / sizeof discs[0]; d++) {
                svp_psf p = make_psf((svp_psf_model)model, 2.7, betas[b]);
                double R = discs[d];
                int diverges = model != SVP_PSF_GAUSSIAN && R == 0 &&
                               (model == SVP_PSF_LORENTZIAN || betas[b] <= 1.0);
                for (size_t f = 0; f < sizeof fractions / sizeof fractions[0]; f++) {
                    double r = -1;
                    svp_status st = svp_psf_encircled_radius(&p, fractions[f], R, &r);
                    if (diverges) {
                        assert_int_equal(st, SVP_ERR_INVALID);
                        continue;
                    }
                    ASSERT_OK(st);
                    assert_true(r > 0 && (R == 0 || r <= R * (1 + 1e-12)));
                    ASSERT_CLOSE(svp_psf_encircled_energy(&p, r, R), fractions[f], 1e-12);
                }
            }
    /* bad fractions name the parameter */
    svp_psf g = make_psf(SVP_PSF_GAUSSIAN, 2.0, 0);
    double r;
    const double bad[] = {0.0, 1.0, -0.2, 1.5, NAN};
    for (size_t i = 0; i < sizeof bad / sizeof bad[0]; i++) {
        assert_int_equal(svp_psf_encircled_radius(&g, bad[i], 10.0, &r), SVP_ERR_INVALID);
        assert_non_null(strstr(svp_last_error(), "fraction"));
    }
}

/* ---- rendered kernels -------------------------------------------------------------------- */

static void test_kernels_unit_sum(void **state)
{
    (void)state;
    struct {
        svp_psf_model model;
        double fwhm, fwhm_minor, angle, beta, support;
        int rx, ry;
    } cases[] = {
        {SVP_PSF_GAUSSIAN, 3.0, 0, 0, 0, 0, 12, 12},
        {SVP_PSF_GAUSSIAN, 0.8, 0, 0, 0, 0, 5, 5},   /* sub-pixel integration */
        {SVP_PSF_GAUSSIAN, 40.0, 0, 0, 0, 0, 10, 6}, /* cut far inside the core */
        {SVP_PSF_MOFFAT, 2.5, 0, 0, 2.5, 0, 30, 30},
        {SVP_PSF_MOFFAT, 6.1, 0, 0, 1.1, 0, 255, 127}, /* heavy tail, whole frame */
        {SVP_PSF_MOFFAT, 4.0, 0, 0, 0.9, 0, 100, 100}, /* β < 1: exists only truncated */
        {SVP_PSF_LORENTZIAN, 3.0, 0, 0, 1, 0, 200, 50},
        {SVP_PSF_MOFFAT, 6.0, 2.0, 0.7, 3.3, 0, 25, 25}, /* elliptical */
        {SVP_PSF_GAUSSIAN, 1.5, 0.6, -1.1, 0, 0, 6, 6},  /* elliptical, sub-pixel */
        {SVP_PSF_MOFFAT, 3.0, 0, 0, 1.4, 7.5, 20, 20},   /* truncated support */
        {SVP_PSF_LORENTZIAN, 3.0, 0, 0, 1, 0.4, 3, 3},   /* support below one pixel */
        {SVP_PSF_MOFFAT, 3.0, 0, 0, 2.0, 0, 0, 0},       /* 1 x 1 */
    };
    for (size_t c = 0; c < sizeof cases / sizeof cases[0]; c++) {
        svp_psf p = make_psf(cases[c].model, cases[c].fwhm, cases[c].beta);
        p.fwhm_minor = cases[c].fwhm_minor;
        p.angle = cases[c].angle;
        p.support = cases[c].support;
        svp_image *k = render(&p, cases[c].rx, cases[c].ry);
        assert_int_equal(k->width, 2 * cases[c].rx + 1);
        assert_int_equal(k->height, 2 * cases[c].ry + 1);
        double sum = kernel_sum(k);
        if (fabs(sum - 1.0) > 1e-12) fail_msg("case %zu: kernel sums to 1 %+.3g", c, sum - 1.0);
        double peak = k->data[(size_t)cases[c].ry * k->width + cases[c].rx];
        for (int y = 0; y < k->height; y++)
            for (int x = 0; x < k->width; x++) {
                double v = k->data[(size_t)y * k->width + x];
                double dx = x - cases[c].rx, dy = y - cases[c].ry;
                assert_true(v >= 0 && v <= peak);
                /* nothing outside the support radius */
                if (p.support > 0 && dx * dx + dy * dy > p.support * p.support) assert_true(v == 0);
            }
        svp_image_free(k);
    }
    /* the halo is a separate term: the rendered core does not depend on it */
    svp_psf a = make_psf(SVP_PSF_MOFFAT, 3.0, 1.1), b = a;
    b.halo = 0.5;
    svp_image *ka = render(&a, 20, 20), *kb = render(&b, 20, 20);
    ASSERT_CLOSE(test_max_abs_diff(ka, kb), 0.0, 0);
    svp_image_free(ka);
    svp_image_free(kb);
}

static double second_moment_x(const svp_image *k, int rx)
{
    long double m = 0, s = 0;
    for (int y = 0; y < k->height; y++)
        for (int x = 0; x < k->width; x++) {
            double v = k->data[(size_t)y * k->width + x];
            m += (long double)v * (x - rx) * (x - rx);
            s += v;
        }
    return (double)(m / s);
}

/* Exact pixel integral of a 1-D Gaussian over [x − ½, x + ½] (erf), for the reference. */
static double gauss_pixel(double x, double sigma)
{
    return 0.5 * (erf((x + 0.5) / (sqrt(2.0) * sigma)) - erf((x - 0.5) / (sqrt(2.0) * sigma)));
}

static void test_subpixel_integration(void **state)
{
    (void)state;
    const int r = 10;
    /* FWHM 0.8 px: the auto mode integrates over each pixel */
    svp_psf p = make_psf(SVP_PSF_GAUSSIAN, 0.8, 0);
    svp_psf centre = p;
    centre.subsample = 1;
    svp_image *ki = render(&p, r, r), *kc = render(&centre, r, r);
    double peak_i = ki->data[(size_t)r * ki->width + r],
           peak_c = kc->data[(size_t)r * kc->width + r];
    if (!(peak_i < peak_c))
        fail_msg("integrated peak %.6f is not below the centre-sampled %.6f", peak_i, peak_c);
    /* against the exact (erf) pixel integrals of the separable Gaussian */
    double sigma = 0.8 / (2.0 * sqrt(2.0 * log(2.0)));
    double norm = 0;
    for (int x = -r; x <= r; x++) norm += gauss_pixel(x, sigma);
    double worst = 0, m2_exact = 0;
    for (int y = -r; y <= r; y++)
        for (int x = -r; x <= r; x++) {
            double ref = gauss_pixel(x, sigma) * gauss_pixel(y, sigma) / (norm * norm);
            double d = fabs(ki->data[(size_t)(y + r) * ki->width + x + r] - ref);
            if (d > worst) worst = d;
            m2_exact += ref * x * x;
        }
    double m2 = second_moment_x(ki, r);
    /* 9 x 9 midpoint samples per pixel: measured 0.41 % of the peak and 1.3 % in the second
     * moment at FWHM 0.8 px. (σ² + 1/12 does not hold here: a 0.34 px σ aliases on the pixel
     * grid, the exact pixel-integrated kernel has second moment 0.141, not 0.199.) */
    if (worst > 0.005 * peak_i) fail_msg("FWHM 0.8: max |k - erf reference| = %.3g", worst);
    if (fabs(m2 / m2_exact - 1) > 0.02)
        fail_msg("FWHM 0.8: second moment %.5f vs exact pixel integral %.5f", m2, m2_exact);
    print_message("FWHM 0.8 px: peak integrated %.4f vs centre %.4f; max |k - erf| %.2e; "
                  "<x^2> %.5f vs exact %.5f\n",
                  peak_i, peak_c, worst, m2, m2_exact);
    svp_image_free(ki);
    svp_image_free(kc);

    /* FWHM 1.9 px (still integrated): no aliasing, <x²> = σ² + 1/12 of the continuous
     * Gaussian convolved with the pixel box, while centre sampling gives σ² */
    p = make_psf(SVP_PSF_GAUSSIAN, 1.9, 0);
    centre = p;
    centre.subsample = 1;
    ki = render(&p, r, r);
    kc = render(&centre, r, r);
    sigma = 1.9 / (2.0 * sqrt(2.0 * log(2.0)));
    double want = sigma * sigma + 1.0 / 12.0;
    m2 = second_moment_x(ki, r);
    double m2c = second_moment_x(kc, r);
    if (fabs(m2 / want - 1) > 0.01)
        fail_msg("FWHM 1.9: integrated <x^2> %.5f vs sigma^2 + 1/12 = %.5f", m2, want);
    ASSERT_CLOSE(m2c, sigma * sigma, 1e-3 * sigma * sigma); /* aliasing: 1.3e-4 relative */
    print_message("FWHM 1.9 px: <x^2> integrated %.5f (sigma^2 + 1/12 = %.5f), centre %.5f\n", m2,
                  want, m2c);
    svp_image_free(ki);
    svp_image_free(kc);
}

static void test_elliptical_orientation(void **state)
{
    (void)state;
    const double angles[] = {0.0, 0.5236, 1.2, 2.0944, -0.3};
    const int r = 30;
    for (size_t a = 0; a < sizeof angles / sizeof angles[0]; a++) {
        svp_psf p = make_psf(SVP_PSF_GAUSSIAN, 8.0, 0);
        p.fwhm_minor = 4.0;
        p.angle = angles[a];
        svp_image *k = render(&p, r, r);
        long double mxx = 0, myy = 0, mxy = 0;
        for (int y = 0; y < k->height; y++)
            for (int x = 0; x < k->width; x++) {
                long double v = k->data[(size_t)y * k->width + x];
                mxx += v * (x - r) * (x - r);
                myy += v * (y - r) * (y - r);
                mxy += v * (x - r) * (y - r);
            }
        /* major axis angle of the second-moment ellipse, from +x towards +y (row index) */
        double theta = 0.5 * atan2(2.0 * (double)mxy, (double)(mxx - myy));
        double want = remainder(angles[a], M_PI); /* an axis: defined modulo π */
        ASSERT_CLOSE(remainder(theta - want, M_PI), 0.0, 1e-9);
        /* the eigenvalues are the two σ² */
        double tr = (double)(mxx + myy), det = (double)(mxx * myy - mxy * mxy);
        double l1 = 0.5 * tr + sqrt(0.25 * tr * tr - det), l2 = tr - l1;
        double sa = 8.0 / 2.3548200450309493, sb = 4.0 / 2.3548200450309493;
        ASSERT_CLOSE(l1, sa * sa, 1e-7);
        ASSERT_CLOSE(l2, sb * sb, 1e-7);
        svp_image_free(k);
    }
    /* a Moffat ellipse is rotated the same way: the profile is largest along the major axis */
    svp_psf m = make_psf(SVP_PSF_MOFFAT, 8.0, 1.1);
    m.fwhm_minor = 2.0;
    m.angle = 0.6;
    svp_image *k = render(&m, r, r);
    double best = -1, best_angle = 0;
    for (int i = 0; i < 360; i++) {
        double t = i * M_PI / 360;
        int x = (int)lround(r + 10 * cos(t)), y = (int)lround(r + 10 * sin(t));
        double v = k->data[(size_t)y * k->width + x];
        if (v > best) best = v, best_angle = t;
    }
    ASSERT_CLOSE(best_angle, 0.6, 0.06);
    svp_image_free(k);
}

/* ---- validation ---------------------------------------------------------------------------- */

static void expect_invalid(const svp_psf *p, const char *word)
{
    svp_image *k = (svp_image *)1;
    svp_blur *b = NULL;
    assert_int_equal(svp_psf_validate(p), SVP_ERR_INVALID);
    if (!strstr(svp_last_error(), word))
        fail_msg("message '%s' does not name '%s'", svp_last_error(), word);
    assert_int_equal(svp_psf_render(p, 4, 4, &k), SVP_ERR_INVALID);
    assert_null(k);
    assert_non_null(strstr(svp_last_error(), word));
    assert_int_equal(svp_blur_new(p, 16, 16, SVP_BOUNDARY_ZERO, &b), SVP_ERR_INVALID);
    assert_null(b);
    assert_non_null(strstr(svp_last_error(), word));
}

/* The renderer's pixel-centre values (vector exp / log1p where glibc's libmvec is there, a batch
 * at a time; an unrotated profile's right half copied from its left) agree with the scalar
 * profile (svp_psf_profile) to 1e-14 relative, for Moffat (β 1.6 and 1), Gaussian, rotated and
 * not; unrotated kernels are mirror-symmetric bit for bit at the pixel centres; a kernel of
 * another radius has the same shape to 1e-14 (values do not depend on the batches). */
static void test_render_matches_profile(void **state)
{
    (void)state;
    const int rx = 300, ry = 7;
    for (int c = 0; c < 5; c++) {
        svp_psf p;
        svp_psf_defaults(&p);
        p.model = c == 2 ? SVP_PSF_GAUSSIAN : SVP_PSF_MOFFAT;
        p.fwhm = c == 4 ? 1.5 : 6.0; /* 1.5: sub-sampled centre */
        p.beta = c == 1 ? 1.0 : 1.6;
        if (c == 3) {
            p.fwhm_minor = 4.0;
            p.angle = 0.4;
        }
        svp_image *k = NULL, *k2 = NULL;
        ASSERT_OK(svp_psf_render(&p, rx, ry, &k));
        ASSERT_OK(svp_psf_render(&p, rx - 37, ry, &k2));
        /* unnormalise by the centre's ratio to the profile: compare shapes at the pixel centres */
        const double scale = svp_psf_profile(&p, 150, 3) / k->data[(size_t)(ry + 3) * k->width + rx + 150];
        const double scale2 = k->data[(size_t)ry * k->width + rx + 40] /
                              k2->data[(size_t)ry * k2->width + rx - 37 + 40];
        double worst = 0;
        for (int y = 0; y < k->height; y++)
            for (int x = 0; x < k->width; x++) {
                const double dx = x - rx, dy = y - ry, r2 = dx * dx + dy * dy;
                const double kv = k->data[(size_t)y * k->width + x];
                if (r2 > 36 * 4 * 36) { /* outside any sub-sampled disc */
                    const double ref = svp_psf_profile(&p, dx, dy);
                    worst = fmax(worst, fabs(kv * scale - ref) / ref);
                }
                if (c != 3 && r2 > 36 * 4 * 36) /* the sub-pixel means are summed in another order */
                    assert_true(kv == k->data[(size_t)y * k->width + 2 * rx - x]);
                if (abs(x - rx) <= rx - 37 && r2 > 36 * 4 * 36) {
                    const double kv2 = k2->data[(size_t)y * k2->width + x - 37];
                    assert_true(fabs(kv2 * scale2 - kv) <= 1e-14 * kv);
                }
            }
        print_message("profile %d: rendered vs scalar profile %.2g relative\n", c, worst);
        assert_true(worst < 1e-14);
        svp_image_free(k);
        svp_image_free(k2);
    }
}


/* The symmetry classes (svp_psf_symmetry) and the fold the low-rank build renders
 * (svp_psf_render_fold) against svp_psf_render_rows's whole kernel: a circular PSF's octant, an
 * axis-aligned ellipse's quadrant (angle 0 and π / 2). At angle 0 the fold's pixel-centre values
 * are the kernel's bit for bit at (dx, dy) and at every mirror (x, y, and x ↔ y for an octant);
 * at π / 2 (cos ≠ 0 in floating point) and in the sub-sampled centre to round-off. */
static void test_render_fold(void **state)
{
    (void)state;
    const int r = 40;
    for (int c = 0; c < 6; c++) {
        svp_psf p;
        svp_psf_defaults(&p);
        p.model = c == 1 ? SVP_PSF_GAUSSIAN : SVP_PSF_MOFFAT;
        p.fwhm = c == 2 ? 1.5 : 5.0; /* 1.5: sub-sampled centre */
        p.beta = 1.7;
        p.support = c == 3 ? 30.5 : 0;
        if (c == 3) p.fwhm_minor = 5.0; /* circular too */
        if (c >= 4) p.fwhm_minor = 3.0;
        if (c == 5) p.angle = 0.5 * 3.14159265358979323846;
        const int sym = svp_psf_symmetry(&p), want = c <= 3 ? 2 : 1, octant = sym == 2;
        assert_int_equal(sym, want);
        const int w = 2 * r + 1;
        double *k = malloc((size_t)w * w * sizeof(double));
        double *f = malloc((size_t)w * w * sizeof(double));
        assert_non_null(k);
        assert_non_null(f);
        ASSERT_OK(svp_psf_render_rows(&p, r, r, 0, w, k));
        const double peak = k[(size_t)r * w + r];
        svp_psf_render_fold(&p, r, octant, 0, 7, f); /* rows in two calls */
        size_t n7 = 0;
        for (int dy = 0; dy < 7; dy++) n7 += (size_t)(r + 1 - (octant ? dy : 0));
        svp_psf_render_fold(&p, r, octant, 7, r + 1 - 7, f + n7);
        double worst = 0;
        size_t i = 0;
        for (int dy = 0; dy <= r; dy++)
            for (int dx = octant ? dy : 0; dx <= r; dx++, i++) {
                const int sub = dx * dx + dy * dy <= 400; /* inside the sub-sampled disc */
                for (int m = 0; m < (octant ? 8 : 4); m++) {
                    const int sx = m & 1 ? -1 : 1, sy = m & 2 ? -1 : 1, swap = m & 4;
                    const int x = r + sx * (swap ? dy : dx), y = r + sy * (swap ? dx : dy);
                    const double kv = k[(size_t)y * w + x];
                    if (c != 5 && !(c == 2 && sub)) assert_true(f[i] == kv);
                    worst = fmax(worst, fabs(f[i] - kv) / peak);
                }
            }
        print_message("fold %d (symmetry %d): %zu pixels, max difference %.1e of the peak\n", c,
                      sym, i, worst);
        assert_true(worst <= 1e-15);
        free(k);
        free(f);
    }
    svp_psf rot;
    svp_psf_defaults(&rot);
    rot.fwhm_minor = 1.0;
    rot.angle = 0.3;
    assert_int_equal(svp_psf_symmetry(&rot), 0);
}

static void test_validation(void **state)
{
    (void)state;
    const double bad_fwhm[] = {0.0, -1.0, NAN, INFINITY};
    for (size_t i = 0; i < 4; i++)
        for (int model = 0; model < 3; model++) {
            svp_psf p = make_psf((svp_psf_model)model, bad_fwhm[i], 2.0);
            expect_invalid(&p, "FWHM");
        }
    const double bad_beta[] = {0.0, -0.5, NAN};
    for (size_t i = 0; i < 3; i++) {
        svp_psf p = make_psf(SVP_PSF_MOFFAT, 3.0, bad_beta[i]);
        expect_invalid(&p, "beta");
    }
    const double bad_halo[] = {1.0, 1.5, -0.1, NAN};
    for (size_t i = 0; i < 4; i++) {
        svp_psf p = make_psf(SVP_PSF_MOFFAT, 3.0, 2.0);
        p.halo = bad_halo[i];
        expect_invalid(&p, "halo");
    }
    svp_psf p = make_psf(SVP_PSF_GAUSSIAN, 3.0, 0);
    p.support = -2.0;
    expect_invalid(&p, "support");
    p = make_psf(SVP_PSF_GAUSSIAN, 3.0, 0);
    p.fwhm_minor = -1.0;
    expect_invalid(&p, "minor");
    p = make_psf(SVP_PSF_GAUSSIAN, 3.0, 0);
    p.model = (svp_psf_model)7;
    expect_invalid(&p, "model");
    /* the defaults are valid and what the header says */
    svp_psf d;
    svp_psf_defaults(&d);
    ASSERT_OK(svp_psf_validate(&d));
    assert_int_equal(d.model, SVP_PSF_GAUSSIAN);
    ASSERT_CLOSE(d.fwhm, 2.0, 0);
    ASSERT_CLOSE(d.beta, 2.5, 0);
    ASSERT_CLOSE(d.halo + d.support + d.fwhm_minor + d.angle + d.subsample, 0.0, 0);
    /* β is ignored for the Lorentzian (forced to 1), so a zero β there is fine */
    p = make_psf(SVP_PSF_LORENTZIAN, 3.0, 0.0);
    ASSERT_OK(svp_psf_validate(&p));
    /* negative kernel radii */
    svp_image *k = NULL;
    assert_int_equal(svp_psf_render(&d, -1, 3, &k), SVP_ERR_INVALID);
    assert_null(k);
    /* axes 10^6 apart are a line, not a spot (a minor axis of 1e-300 gave "no flux", exit 2) */
    p = make_psf(SVP_PSF_GAUSSIAN, 1.0, 0);
    p.fwhm_minor = 1e-300;
    expect_invalid(&p, "differ by more than 10^6");
    /* a PSF far narrower than a pixel renders as its limit, all light in the centre pixel, in
     * every model, also where its width squared underflows (FWHM 1e-200 px: 0/0 before) */
    for (int model = 0; model < 3; model++)
        for (double fw = 1e-6; fw > 1e-250; fw *= 1e-97) {
            p = make_psf((svp_psf_model)model, fw, 1.5);
            ASSERT_OK(svp_psf_render(&p, 2, 1, &k));
            for (int i = 0; i < 15; i++) ASSERT_CLOSE(k->data[i], i == 7 ? 1.0 : 0.0, 1e-6);
            svp_image_free(k);
        }
}

int main(void)
{
    svp_set_fft_effort(SVP_FFT_ESTIMATE);
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_fwhm_r0),
        cmocka_unit_test(test_lorentzian_is_moffat_1),
        cmocka_unit_test(test_encircled_energy_vs_quadrature),
        cmocka_unit_test(test_encircled_energy_elliptical),
        cmocka_unit_test(test_encircled_energy_near_beta_1),
        cmocka_unit_test(test_encircled_radius_inverts),
        cmocka_unit_test(test_kernels_unit_sum),
        cmocka_unit_test(test_subpixel_integration),
        cmocka_unit_test(test_elliptical_orientation),
        cmocka_unit_test(test_render_matches_profile),
        cmocka_unit_test(test_render_fold),
        cmocka_unit_test(test_validation),
    };
    int failed = cmocka_run_group_tests_name("psf", tests, NULL, NULL);
    svp_fft_cleanup();
    return failed;
}
