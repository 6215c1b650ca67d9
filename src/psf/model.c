/* PSF models: Gaussian, Lorentzian, Moffat (elliptical), sampling and normalisation. */
#include "../core/internal.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

void svp_psf_defaults(svp_psf *psf)
{
    psf->model = SVP_PSF_GAUSSIAN;
    psf->fwhm = 2.0;
    psf->fwhm_minor = 0.0;
    psf->angle = 0.0;
    psf->beta = 2.5;
    psf->halo = 0.0;
    psf->support = 0.0;
    psf->subsample = 0;
}

static const char *model_name(svp_psf_model m)
{
    switch (m) {
    case SVP_PSF_GAUSSIAN: return "gaussian";
    case SVP_PSF_LORENTZIAN: return "lorentzian";
    case SVP_PSF_MOFFAT: return "moffat";
    }
    return "unknown";
}

svp_status svp_psf_validate(const svp_psf *psf)
{
    if (!psf) return svp_fail(SVP_ERR_INVALID, "PSF is NULL");
    if (psf->model != SVP_PSF_GAUSSIAN && psf->model != SVP_PSF_LORENTZIAN &&
        psf->model != SVP_PSF_MOFFAT)
        return svp_fail(SVP_ERR_INVALID, "PSF model %d is not gaussian, lorentzian or moffat",
                        (int)psf->model);
    if (!(psf->fwhm > 0) || !isfinite(psf->fwhm))
        return svp_fail(SVP_ERR_INVALID, "PSF FWHM must be positive and finite, got %g",
                        psf->fwhm);
    if (psf->fwhm_minor < 0 || !isfinite(psf->fwhm_minor))
        return svp_fail(SVP_ERR_INVALID, "PSF minor-axis FWHM must be >= 0, got %g",
                        psf->fwhm_minor);
    if (psf->fwhm_minor > 0 && (psf->fwhm_minor < 1e-6 * psf->fwhm ||
                                psf->fwhm < 1e-6 * psf->fwhm_minor))
        return svp_fail(SVP_ERR_INVALID,
                        "PSF axes %g px and %g px differ by more than 10^6: a line, not a spot (a "
                        "minor-axis FWHM of 0 means a circular PSF)",
                        psf->fwhm, psf->fwhm_minor);
    if (psf->model == SVP_PSF_MOFFAT && (!(psf->beta >= SVP_PSF_BETA_MIN) || !isfinite(psf->beta)))
        return svp_fail(SVP_ERR_INVALID, "Moffat beta must be >= %g and finite, got %g",
                        SVP_PSF_BETA_MIN, psf->beta);
    if (!(psf->halo >= 0 && psf->halo < 1))
        return svp_fail(SVP_ERR_INVALID, "halo fraction must be in [0, 1), got %g", psf->halo);
    if (psf->support < 0 || !isfinite(psf->support))
        return svp_fail(SVP_ERR_INVALID, "PSF support radius must be >= 0, got %g",
                        psf->support);
    if (psf->subsample < 0 || psf->subsample > 64)
        return svp_fail(SVP_ERR_INVALID, "PSF subsample must be in 0..64, got %d",
                        psf->subsample);
    if (!isfinite(psf->angle))
        return svp_fail(SVP_ERR_INVALID, "PSF angle must be finite");
    (void)model_name;
    return SVP_OK;
}

static double effective_beta(const svp_psf *psf)
{
    return psf->model == SVP_PSF_LORENTZIAN ? 1.0 : psf->beta;
}

double svp_psf_fwhm_to_r0(double fwhm, double beta)
{
    if (!(beta > 0)) return fwhm / (2.0 * sqrt(2.0 * log(2.0))); /* Gaussian sigma */
    /* 2^(1/β) − 1 = expm1(ln 2 / β): accurate for large β too. */
    return fwhm / (2.0 * sqrt(expm1(log(2.0) / beta)));
}

/* Scale lengths of the two axes: σ for a Gaussian, r0 for a Moffat. */
static void axis_scales(const svp_psf *psf, double *sa, double *sb)
{
    double fa = psf->fwhm;
    double fb = psf->fwhm_minor > 0 ? psf->fwhm_minor : psf->fwhm;
    double beta = psf->model == SVP_PSF_GAUSSIAN ? 0.0 : effective_beta(psf);
    *sa = svp_psf_fwhm_to_r0(fa, beta);
    *sb = svp_psf_fwhm_to_r0(fb, beta);
}

typedef struct profile_eval {
    svp_psf_model model;
    double beta;
    double c, s;     /* cos, sin of the angle */
    double ia2, ib2; /* 1 / scale² */
} profile_eval;

static void profile_setup(const svp_psf *psf, profile_eval *e)
{
    double sa, sb;
    axis_scales(psf, &sa, &sb);
    e->model = psf->model;
    e->beta = effective_beta(psf);
    e->c = cos(psf->angle);
    e->s = sin(psf->angle);
    e->ia2 = 1.0 / (sa * sa);
    e->ib2 = 1.0 / (sb * sb);
}

static inline double profile_at(const profile_eval *e, double dx, double dy)
{
    double u = dx * e->c + dy * e->s;
    double v = -dx * e->s + dy * e->c;
    double q = u * u * e->ia2 + v * v * e->ib2; /* (ρ / scale)² */
    if (e->model == SVP_PSF_GAUSSIAN) return exp(-0.5 * q);
    if (e->beta == 1.0) return 1.0 / (1.0 + q);
    return exp(-e->beta * log1p(q));
}

double svp_psf_profile(const svp_psf *psf, double dx, double dy)
{
    profile_eval e;
    profile_setup(psf, &e);
    return profile_at(&e, dx, dy);
}

/* Radius along the major axis where the core profile falls to `level` of its peak:
 * Gaussian σ √(2 ln(1/level)), Moffat r0 √(level^(−1/β) − 1); at most the support when one is
 * set. 0 for a level outside (0, 1). */
double svp_psf_reach(const svp_psf *psf, double level)
{
    if (!(level > 0 && level < 1)) return 0.0;
    double r;
    if (psf->model == SVP_PSF_GAUSSIAN) {
        r = svp_psf_fwhm_to_r0(psf->fwhm, 0.0) * sqrt(-2.0 * log(level));
    } else {
        const double beta = effective_beta(psf);
        r = svp_psf_fwhm_to_r0(psf->fwhm, beta) * sqrt(expm1(-log(level) / beta));
    }
    if (psf->support > 0 && psf->support < r) r = psf->support;
    return r;
}

/* `margin auto` (docs/model.md §3): the reach at 1 % of the peak, rounded up, at most a quarter
 * of the larger side; 0 with a halo, whose flux a margin's unknowns could take up. */
int svp_psf_auto_margin(const svp_psf *psf, int width, int height)
{
    if (psf->halo > 0) return 0;
    const int cap = (width > height ? width : height) / 4;
    const int r = (int)ceil(svp_psf_reach(psf, 0.01));
    return r < cap ? r : cap;
}

/* Encircled energy. A profile P(q) of q = u²/a² + v²/b² (axis scales a >= b; the angle does
 * not matter for a disc) holds, inside the disc x² + y² < r², a b ∫∫ P over the unit-scale
 * region ρ² < r² / (a² cos²φ + b² sin²φ), so with the unit-scale radial cumulative
 *     U(s) = ∫_0^√s P(ρ²) ρ dρ:  Gaussian −expm1(−s/2); Moffat expm1((1 − β) log1p(s)) / (1 − β)
 * (log1p(s) at β = 1; over the plane U(∞) = 1 resp. 1 / (β − 1) when β > 1)
 * the flux is 2π a b F(r) with F(r) = (2/π) ∫_0^{π/2} U(r² / (a² cos²φ + b² sin²φ)) dφ, and the
 * encircled energy is F(r) / F(R) (R = 0: / U(∞)). Circular: F(r) = U(r² / a²), closed form;
 * elliptical: the φ integral by adaptive Simpson to about 1e-13 relative. */
typedef struct ee_eval {
    int gaussian;
    double beta;
    double a2, b2; /* axis scales squared */
} ee_eval;

static void ee_setup(const svp_psf *psf, ee_eval *e)
{
    double sa, sb;
    axis_scales(psf, &sa, &sb);
    e->gaussian = psf->model == SVP_PSF_GAUSSIAN;
    e->beta = effective_beta(psf);
    e->a2 = sa * sa;
    e->b2 = sb * sb;
}

static double ee_cumulative(const ee_eval *e, double s)
{
    if (e->gaussian) return -expm1(-0.5 * s);
    const double l = log1p(s);
    return e->beta == 1.0 ? l : expm1((1.0 - e->beta) * l) / (1.0 - e->beta);
}

static double ee_integrand(const ee_eval *e, double r2, double phi)
{
    const double c = cos(phi), sn = sin(phi);
    return ee_cumulative(e, r2 / (e->a2 * c * c + e->b2 * sn * sn));
}

/* tol halves with each split down to `floor` (the round-off of the whole integral), so that
 * round-off never drives the recursion to its depth limit */
static double ee_simpson(const ee_eval *e, double r2, double lo, double hi, double flo, double fmid,
                         double fhi, double whole, double tol, double floor, int depth)
{
    const double mid = 0.5 * (lo + hi), m1 = 0.5 * (lo + mid), m2 = 0.5 * (mid + hi);
    const double f1 = ee_integrand(e, r2, m1), f2 = ee_integrand(e, r2, m2);
    const double left = (mid - lo) / 6.0 * (flo + 4.0 * f1 + fmid);
    const double right = (hi - mid) / 6.0 * (fmid + 4.0 * f2 + fhi);
    const double diff = left + right - whole;
    if (depth <= 0 || fabs(diff) <= 15.0 * fmax(tol, floor)) return left + right + diff / 15.0;
    return ee_simpson(e, r2, lo, mid, flo, f1, fmid, left, 0.5 * tol, floor, depth - 1) +
           ee_simpson(e, r2, mid, hi, fmid, f2, fhi, right, 0.5 * tol, floor, depth - 1);
}

/* F(r) (see above); circular profiles in closed form */
static double ee_flux(const ee_eval *e, double r)
{
    const double r2 = r * r;
    if (e->a2 == e->b2) return ee_cumulative(e, r2 / e->a2);
    /* 16 panels first, so that the peak of U near φ = π/2 (width ~ b / a) is seen */
    const int panels = 16;
    const double h = 0.5 * M_PI / panels;
    double lo_value = ee_integrand(e, r2, 0.0), sum = 0, scale = 0;
    double parts[16], f_lo[16], f_mid[16], f_hi[16];
    for (int k = 0; k < panels; k++) {
        const double lo = k * h, hi = (k + 1) * h;
        f_lo[k] = k ? f_hi[k - 1] : lo_value;
        f_mid[k] = ee_integrand(e, r2, 0.5 * (lo + hi));
        f_hi[k] = ee_integrand(e, r2, hi);
        parts[k] = h / 6.0 * (f_lo[k] + 4.0 * f_mid[k] + f_hi[k]);
        scale += fabs(parts[k]);
    }
    const double tol = 1e-13 * scale / panels, floor = 4.0 * DBL_EPSILON * scale;
    for (int k = 0; k < panels; k++)
        sum += ee_simpson(e, r2, k * h, (k + 1) * h, f_lo[k], f_mid[k], f_hi[k], parts[k], tol,
                          floor, 30);
    return sum / (0.5 * M_PI);
}

/* F over the plane; 0 when it diverges (β <= 1) */
static double ee_total(const ee_eval *e)
{
    if (e->gaussian) return 1.0;
    return e->beta > 1.0 ? 1.0 / (e->beta - 1.0) : 0.0;
}

/* Fraction of flux within radius r of a disc of radius R (R = 0: the plane); exact for
 * elliptical profiles too. */
double svp_psf_encircled_energy(const svp_psf *psf, double r, double R)
{
    if (r <= 0) return 0.0;
    if (R > 0 && r >= R) return 1.0;
    ee_eval e;
    ee_setup(psf, &e);
    if (R <= 0) {
        const double total = ee_total(&e);
        if (!(total > 0)) return NAN; /* the flux over the plane diverges */
        if (e.a2 == e.b2 && !e.gaussian) /* 1 − (1 + s)^(1 − β), accurate near 1 */
            return -expm1((1.0 - e.beta) * log1p(r * r / e.a2));
        return ee_flux(&e, r) / total;
    }
    return ee_flux(&e, r) / ee_flux(&e, R);
}

svp_status svp_psf_encircled_radius(const svp_psf *psf, double fraction, double R,
                                    double *radius)
{
    SVP_CHECK(svp_psf_validate(psf));
    if (!(fraction > 0 && fraction < 1))
        return svp_fail(SVP_ERR_INVALID, "encircled-energy fraction must be in (0, 1), got %g",
                        fraction);
    ee_eval e;
    ee_setup(psf, &e);
    if (R <= 0 && !e.gaussian && e.beta <= 1.0)
        return svp_fail(SVP_ERR_INVALID,
                        "encircled energy of a Moffat with beta = %g <= 1 needs a finite "
                        "support radius (its flux over the plane diverges)",
                        e.beta);
    /* the circular radius of scale s (closed-form inversion of U(r² / s²) = fraction · F(R)) */
    double radius_a = 0, radius_b = 0;
    for (int axis = 0; axis < 2; axis++) {
        const double s2 = axis ? e.b2 : e.a2;
        double u;
        if (e.gaussian) {
            const double den = R > 0 ? -expm1(-0.5 * R * R / s2) : 1.0;
            u = -2.0 * log1p(-fraction * den);
        } else if (R <= 0) {
            u = expm1(log1p(-fraction) / (1.0 - e.beta));
        } else {
            const double lU = log1p(R * R / s2);
            if (e.beta == 1.0) {
                u = expm1(fraction * lU);
            } else {
                const double D = -expm1((1.0 - e.beta) * lU);
                u = expm1(log1p(-fraction * D) / (1.0 - e.beta));
            }
        }
        *(axis ? &radius_b : &radius_a) = sqrt(s2 * u);
    }
    if (e.a2 == e.b2) {
        *radius = radius_a;
        return SVP_OK;
    }
    /* elliptical: bisection on the exact encircled energy. Over the plane the radius lies
     * between the circular ones of the minor and the major scale; within a disc in (0, R). */
    double lo = R > 0 ? 0.0 : fmin(radius_a, radius_b), hi = R > 0 ? R : fmax(radius_a, radius_b);
    for (int it = 0; it < 200 && hi - lo > 1e-15 * hi; it++) {
        const double mid = 0.5 * (lo + hi);
        if (svp_psf_encircled_energy(psf, mid, R) < fraction)
            lo = mid;
        else
            hi = mid;
    }
    *radius = 0.5 * (lo + hi);
    return SVP_OK;
}

static int auto_subsample(const svp_psf *psf)
{
    if (psf->subsample > 0) return psf->subsample;
    double fmin = psf->fwhm_minor > 0 && psf->fwhm_minor < psf->fwhm ? psf->fwhm_minor
                                                                     : psf->fwhm;
    return fmin < 2.0 ? 9 : 1;
}

/* Pixel (dx, dy) of the unnormalised kernel where the profile curves within a pixel: its mean
 * over ns x ns sub-pixels. */
static double render_subsampled(const profile_eval *e, int ns, double dx, double dy)
{
    double acc = 0;
    for (int j = 0; j < ns; j++) {
        double sy = dy - 0.5 + (j + 0.5) / ns;
        for (int i = 0; i < ns; i++) acc += profile_at(e, dx - 0.5 + (i + 0.5) / ns, sy);
    }
    return acc / (ns * ns);
}

/* q = (ρ / scale)² → the profile, n values in place (the pixel-centre values of render_row).
 * With glibc's vector math (libmvec) exp and log1p run four (AVX2) or two at a time; every
 * value goes through the vector functions, padded lanes included, so a pixel's value does not
 * depend on where the batch starts (each lane is computed on its own). */
#if defined(SVP_HAVE_MVEC) && defined(__x86_64__)
typedef double svp_m2d __attribute__((vector_size(16)));
typedef double svp_m4d __attribute__((vector_size(32)));
svp_m2d _ZGVbN2v_exp(svp_m2d);
svp_m2d _ZGVbN2v_log1p(svp_m2d);
__attribute__((target("avx2"))) svp_m4d _ZGVdN4v_exp(svp_m4d);
__attribute__((target("avx2"))) svp_m4d _ZGVdN4v_log1p(svp_m4d);

__attribute__((target("avx2"))) static void profile_values_avx2(const profile_eval *e,
                                                                double *q, int n)
{
    const int gauss = e->model == SVP_PSF_GAUSSIAN, n4 = n & ~3;
    for (int i = 0; i < n4; i += 4) {
        svp_m4d x;
        memcpy(&x, q + i, sizeof x);
        x = gauss ? _ZGVdN4v_exp(-0.5 * x) : _ZGVdN4v_exp(-e->beta * _ZGVdN4v_log1p(x));
        memcpy(q + i, &x, sizeof x);
    }
    for (int i = n4; i < n; i += 4) {
        svp_m4d x = {0, 0, 0, 0};
        const int k = n - i < 4 ? n - i : 4;
        for (int t = 0; t < k; t++) x[t] = q[i + t];
        const svp_m4d y = gauss ? _ZGVdN4v_exp(-0.5 * x) : _ZGVdN4v_exp(-e->beta * _ZGVdN4v_log1p(x));
        for (int t = 0; t < k; t++) q[i + t] = y[t];
    }
}

static void profile_values_sse2(const profile_eval *e, double *q, int n)
{
    const int gauss = e->model == SVP_PSF_GAUSSIAN;
    for (int i = 0; i < n; i += 2) {
        svp_m2d x = {q[i], i + 1 < n ? q[i + 1] : 0};
        const svp_m2d y = gauss ? _ZGVbN2v_exp(-0.5 * x) : _ZGVbN2v_exp(-e->beta * _ZGVbN2v_log1p(x));
        q[i] = y[0];
        if (i + 1 < n) q[i + 1] = y[1];
    }
}
#endif

static void profile_values(const profile_eval *e, double *q, int n)
{
    if (e->model != SVP_PSF_GAUSSIAN && e->beta == 1.0) {
        for (int i = 0; i < n; i++) q[i] = 1.0 / (1.0 + q[i]);
        return;
    }
#if defined(SVP_HAVE_MVEC) && defined(__x86_64__)
    if (__builtin_cpu_supports("avx2"))
        profile_values_avx2(e, q, n);
    else
        profile_values_sse2(e, q, n);
#else
    for (int i = 0; i < n; i++)
        q[i] = e->model == SVP_PSF_GAUSSIAN ? exp(-0.5 * q[i]) : exp(-e->beta * log1p(q[i]));
#endif
}

/* n values of the unnormalised kernel at offsets (dx0 + i, dy), i = 0 .. n − 1: the profile at
 * the pixel centres (profile_values, a batch at a time), the sub-pixel mean where it curves
 * within a pixel, 0 beyond the support. A span all of whose pixels are centre-sampled (most
 * of them) takes its q values in place and the profile over all of them at once: the same
 * values, without the batches' gathers and scatters, which cost more than the vector maths. */
static void render_offsets(const svp_psf *psf, const profile_eval *e, int dy, int dx0, int n,
                           double *restrict out)
{
    const int ns = auto_subsample(psf);
    /* Pixel integration only where the profile curves within a pixel. */
    const double fwhm_max = psf->fwhm_minor > psf->fwhm ? psf->fwhm_minor : psf->fwhm;
    const double sub_radius2 = pow(fmax(3.0, 4.0 * fwhm_max), 2);
    const double support2 = psf->support > 0 ? psf->support * psf->support : INFINITY;
    const double ddy = dy;
    /* every pixel at its centre (none beyond the support or in the sub-sampled disc, which a
     * row crosses at most once each): q in place, then the profile */
    const double dxa = fabs((double)dx0), dxb = fabs((double)dx0 + n - 1);
    const double near = dx0 <= 0 && dx0 + n - 1 >= 0 ? 0 : fmin(dxa, dxb), far = fmax(dxa, dxb);
    if (n > 0 && far * far + ddy * ddy <= support2 &&
        (ns == 1 || near * near + ddy * ddy > sub_radius2)) {
        for (int x = 0; x < n; x++) {
            const double dx = dx0 + x;
            const double u = dx * e->c + ddy * e->s, v = -dx * e->s + ddy * e->c;
            out[x] = u * u * e->ia2 + v * v * e->ib2;
        }
        profile_values(e, out, n);
        return;
    }
    enum { BATCH = 256 };
    double qb[BATCH];
    int xb[BATCH], nb = 0;
    for (int x = 0; x <= n; x++) {
        if (nb == BATCH || (x == n && nb > 0)) {
            profile_values(e, qb, nb);
            for (int t = 0; t < nb; t++) out[xb[t]] = qb[t];
            nb = 0;
        }
        if (x == n) break;
        const double dx = dx0 + x, r2 = dx * dx + ddy * ddy;
        if (!(r2 <= support2))
            out[x] = 0;
        else if (ns > 1 && r2 <= sub_radius2)
            out[x] = render_subsampled(e, ns, dx, ddy);
        else {
            const double u = dx * e->c + ddy * e->s, v = -dx * e->s + ddy * e->c;
            qb[nb] = u * u * e->ia2 + v * v * e->ib2; /* as profile_at */
            xb[nb++] = x;
        }
    }
}

/* Row y (0 .. 2 ry) of the unnormalised kernel of radius rx (2 rx + 1 values into out)
 * (render_offsets). An unrotated profile (sin θ = 0: u = ±dx, v = dy exactly) has
 * k(−dx) = k(dx) bit for bit at the pixel centres: the right half of the row copies the left
 * one there (the sub-pixel means are summed in another order, so they are computed). */
static void render_row(const svp_psf *psf, const profile_eval *e, int rx, int ry, int y,
                       double *restrict out)
{
    const int w = 2 * rx + 1, mirror = e->s == 0.0, xend = mirror ? rx + 1 : w;
    const double dy = y - ry;
    render_offsets(psf, e, y - ry, -rx, xend, out);
    if (!mirror) return;
    const int ns = auto_subsample(psf);
    const double fwhm_max = psf->fwhm_minor > psf->fwhm ? psf->fwhm_minor : psf->fwhm;
    const double sub_radius2 = pow(fmax(3.0, 4.0 * fwhm_max), 2);
    const double support2 = psf->support > 0 ? psf->support * psf->support : INFINITY;
    for (int x = xend; x < w; x++) {
        const double dx = x - rx, r2 = dx * dx + dy * dy;
        if (!(r2 <= support2))
            out[x] = 0;
        else if (ns > 1 && r2 <= sub_radius2)
            out[x] = render_subsampled(e, ns, dx, dy);
        else
            out[x] = out[2 * rx - x];
    }
}

int svp_psf_symmetry(const svp_psf *psf)
{
    if (psf->fwhm_minor == 0 || psf->fwhm_minor == psf->fwhm) return 2;
    return remainder(psf->angle, 0.5 * 3.14159265358979323846) == 0 ? 1 : 0;
}

void svp_psf_render_fold(const svp_psf *psf, int rx, int octant, int y0, int rows,
                         double *out)
{
    profile_eval e;
    profile_setup(psf, &e);
    for (int dy = y0; dy < y0 + rows; dy++) {
        const int x0 = octant ? dy : 0;
        render_offsets(psf, &e, dy, x0, rx + 1 - x0, out);
        out += rx + 1 - x0;
    }
}

svp_status svp_psf_render_rows(const svp_psf *psf, int rx, int ry, int y0, int rows,
                               double *out)
{
    profile_eval e;
    profile_setup(psf, &e);
    for (int t = 0; t < rows; t++)
        render_row(psf, &e, rx, ry, y0 + t, out + (size_t)t * (2 * rx + 1));
    return SVP_OK;
}

svp_status svp_psf_render(const svp_psf *psf, int rx, int ry, svp_image **kernel)
{
    if (!kernel) return svp_fail(SVP_ERR_INVALID, "svp_psf_render: kernel is NULL");
    *kernel = NULL;
    SVP_CHECK(svp_psf_validate(psf));
    if (rx < 0 || ry < 0)
        return svp_fail(SVP_ERR_INVALID, "kernel radii must be >= 0, got %d, %d", rx, ry);
    svp_image *k = NULL;
    SVP_CHECK(svp_image_new(2 * rx + 1, 2 * ry + 1, &k));
    profile_eval e;
    profile_setup(psf, &e);
    const int w = k->width;
#pragma omp parallel for schedule(static)
    for (int y = 0; y < k->height; y++) render_row(psf, &e, rx, ry, y, k->data + (size_t)y * w);
    size_t n = (size_t)k->width * k->height;
    double sum = svp_sum(k->data, n);
    if (!(sum > 0 && isfinite(sum)) && fmax(psf->fwhm, psf->fwhm_minor) < 1e-3) {
        /* a PSF far narrower than a pixel: its width squared underflows (FWHM ~1e-155 px),
         * and the limit it tends to is all of the light in the centre pixel */
        memset(k->data, 0, n * sizeof(double));
        k->data[(size_t)ry * w + rx] = sum = 1.0;
    }
    if (!(sum > 0) || !isfinite(sum)) {
        svp_image_free(k);
        return svp_fail(SVP_ERR_NUMERIC, "PSF kernel has no flux on its %d x %d support",
                        2 * rx + 1, 2 * ry + 1);
    }
    double inv = 1.0 / sum;
#pragma omp parallel for schedule(static)
    for (size_t i = 0; i < n; i++) k->data[i] *= inv;
    *kernel = k;
    return SVP_OK;
}
