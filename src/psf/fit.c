/* Spot fits: the elliptical Moffat, Gaussian and Lorentzian spot models fitted by the
 * Levenberg–Marquardt of src/lm/lm.c, and the kernel a fitted spot makes (docs/model.md §8). */
#include "spot_internal.h"
#include "../lm/lm_internal.h"

#include <float.h>
#include <lapacke.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* "holds no spot": the message suggests the data's gain when the noise model's σ at the
 * background and the background's MAD scatter differ by more than this factor */
#define NOISE_MISMATCH 10.0

/* ========================================================================================= */
/* Spot fits                                                                                 */

enum { P_AMP = 0, P_X0, P_Y0, P_FWHM, P_E1, P_E2, P_BETA, P_BG, N_SPOT_PARAMS };

static const char *const spot_flag_text[SVP_SPOT_N_FLAGS] = {
    "not converged: the fit stopped before meeting its tolerances",
    "near border: the centre is within border_fwhm FWHM of an image edge",
    "saturated: pixels at the saturation level were excluded",
    "beta at bound: the Moffat index ran to beta_min or beta_max",
    "hot pixels: single-pixel spikes were excluded",
    "clipped: pixels with large normalised residuals were excluded",
    "no errors: the covariance is singular, uncertainties are unknown",
    "width at bound: a FWHM or the axis ratio ran to its bound",
    "poor fit: reduced chi-square above chi2_red_max",
};

const char *svp_spot_flag_string(unsigned flag)
{
    for (int i = 0; i < SVP_SPOT_N_FLAGS; i++)
        if (flag == 1u << i) return spot_flag_text[i];
    return "";
}

size_t svp_spot_flags_describe(unsigned flags, char *buf, size_t size)
{
    size_t len = 0;
    char tmp[1024];
    tmp[0] = '\0';
    if (flags == 0) {
        len = (size_t)snprintf(tmp, sizeof tmp, "ok");
    } else {
        for (int i = 0; i < SVP_SPOT_N_FLAGS; i++) {
            if (!(flags & (1u << i))) continue;
            const char *t = spot_flag_text[i];
            size_t short_len = strcspn(t, ":");
            int k = snprintf(tmp + len, sizeof tmp - len, "%s%.*s", len ? "; " : "",
                             (int)short_len, t);
            if (k > 0) len += (size_t)k;
        }
        unsigned unknown = flags & ~((1u << SVP_SPOT_N_FLAGS) - 1);
        if (unknown) {
            int k = snprintf(tmp + len, sizeof tmp - len, "%sunknown flags 0x%x", len ? "; " : "",
                             unknown);
            if (k > 0) len += (size_t)k;
        }
    }
    if (buf && size > 0) {
        size_t c = len < size - 1 ? len : size - 1;
        memcpy(buf, tmp, c);
        buf[c] = '\0';
    }
    return len;
}

void svp_spot_defaults(svp_spot_options *o)
{
    o->model = SVP_PSF_MOFFAT;
    o->beta = 2.5;
    o->fix_beta = 0;
    o->beta_min = 0.5;
    o->beta_max = 20.0;
    o->elliptical = 1;
    o->noise.sigma_bg = 0.0;
    o->noise.gain = 1.0;
    o->noise.excess = 0.0;
    o->saturation = 0.0;
    o->hot_pixels = 1;
    o->hot_ratio = 4.0;
    o->hot_sigma = 8.0;
    o->clip_kappa = 5.0;
    o->clip_iterations = 5;
    o->border_fwhm = 2.0;
    o->refuse_near_border = 0;
    o->min_snr = 5.0;
    o->chi2_red_max = 3.0;
    o->pixel_integration = 1;
    o->ee_radius = 0.0;
    o->x0 = NAN;
    o->y0 = NAN;
    svp_lm_defaults(&o->lm);
}

/* The spot model over a list of pixels. Nodes: Gauss–Legendre offsets within a pixel. */
typedef struct spot_model {
    svp_psf_model model;
    int width;          /* of the image the indices refer to */
    double origin_x;    /* coordinates of pixel index 0 (kernel rendering shifts them) */
    double origin_y;
    const int *index;   /* pixel indices of the points */
    const unsigned char *integrate; /* per pixel (image-sized), 1 = integrate over the pixel */
    int nq;             /* nodes per integrated pixel */
    double qx[16], qy[16], qw[16];
} spot_model;

static void set_quadrature(spot_model *sm, int order)
{
    static const double n2[2] = {-0.28867513459481287, 0.28867513459481287};
    static const double w2[2] = {0.5, 0.5};
    static const double n4[4] = {-0.43056815579702629, -0.16999052179242813,
                                 0.16999052179242813, 0.43056815579702629};
    static const double w4[4] = {0.17392742256872693, 0.32607257743127307,
                                 0.32607257743127307, 0.17392742256872693};
    const double *nd = order == 4 ? n4 : n2, *wt = order == 4 ? w4 : w2;
    sm->nq = 0;
    for (int j = 0; j < order; j++)
        for (int i = 0; i < order; i++) {
            sm->qx[sm->nq] = nd[i];
            sm->qy[sm->nq] = nd[j];
            sm->qw[sm->nq] = wt[i] * wt[j];
            sm->nq++;
        }
}

/* Shape constants of a parameter vector. */
typedef struct spot_shape {
    double C, S, T;      /* cosh g, sinh g / g, (g cosh g − sinh g) / g³ */
    double inv_s2;       /* 1 / r0² (Moffat) or 1 / σ² (Gaussian) */
    double beta, kbeta;  /* β and −∂ln q/∂β */
    int gaussian;
} spot_shape;

static void spot_shape_setup(svp_psf_model model, const double *t, spot_shape *sh)
{
    double g = hypot(t[P_E1], t[P_E2]);
    sh->C = cosh(g);
    if (g < 1e-2) {
        double g2 = g * g;
        sh->S = 1.0 + g2 / 6.0 + g2 * g2 / 120.0;
        sh->T = 1.0 / 3.0 + g2 / 30.0 + g2 * g2 / 840.0;
    } else {
        sh->S = sinh(g) / g;
        sh->T = (g * cosh(g) - sinh(g)) / (g * g * g);
    }
    double F = t[P_FWHM];
    sh->gaussian = model == SVP_PSF_GAUSSIAN;
    if (sh->gaussian) {
        sh->beta = 0;
        sh->kbeta = 0;
        sh->inv_s2 = 8.0 * log(2.0) / (F * F);
    } else {
        double beta = model == SVP_PSF_LORENTZIAN ? 1.0 : t[P_BETA];
        double E = expm1(log(2.0) / beta); /* 2^(1/β) − 1, accurate for large β */
        sh->beta = beta;
        sh->inv_s2 = 4.0 * E / (F * F);
        sh->kbeta = log(2.0) * (E + 1.0) / (beta * beta * E);
    }
}

/* Profile value at offset (dx, dy) and, when d is not NULL, its derivatives with respect to
 * (x0, y0, F, e1, e2, β) in d[0..5]. */
static inline double spot_profile(const spot_shape *sh, const double *t, double dx, double dy,
                                  double *d)
{
    const double g1 = t[P_E1], g2 = t[P_E2];
    double rho2 = dx * dx + dy * dy, a = dx * dx - dy * dy, b = 2 * dx * dy;
    double hmix = g1 * a + g2 * b;
    double Q = sh->C * rho2 - sh->S * hmix;
    double q = Q * sh->inv_s2;
    double P, dPdq, lq = 0;
    if (sh->gaussian) {
        P = exp(-0.5 * q);
        dPdq = -0.5 * P;
    } else {
        lq = log1p(q);
        P = sh->beta == 1.0 ? 1.0 / (1.0 + q) : exp(-sh->beta * lq);
        dPdq = -sh->beta * P / (1.0 + q);
    }
    if (d) {
        double k = dPdq * sh->inv_s2;
        double dQdx = 2 * (sh->C * dx - sh->S * (g1 * dx + g2 * dy));
        double dQdy = 2 * (sh->C * dy - sh->S * (g2 * dx - g1 * dy));
        d[0] = -k * dQdx;
        d[1] = -k * dQdy;
        d[2] = dPdq * (-2.0 * q / t[P_FWHM]);
        d[3] = k * (sh->S * g1 * rho2 - sh->T * g1 * hmix - sh->S * a);
        d[4] = k * (sh->S * g2 * rho2 - sh->T * g2 * hmix - sh->S * b);
        d[5] = sh->gaussian ? 0.0 : -lq * P - dPdq * q * sh->kbeta;
    }
    return P;
}

static int spot_model_eval(void *user, const double *t, int n_params, int n_points,
                           double *model, double *jac)
{
    const spot_model *sm = user;
    (void)n_params;
    spot_shape sh;
    spot_shape_setup(sm->model, t, &sh);
    const double amp = t[P_AMP], bg = t[P_BG];
    for (int i = 0; i < n_points; i++) {
        int pix = sm->index[i];
        double px = sm->origin_x + pix % sm->width - t[P_X0];
        double py = sm->origin_y + pix / sm->width - t[P_Y0];
        double P = 0, dP[6] = {0, 0, 0, 0, 0, 0}, d[6];
        if (sm->integrate && sm->integrate[pix]) {
            for (int k = 0; k < sm->nq; k++) {
                double v = spot_profile(&sh, t, px + sm->qx[k], py + sm->qy[k], jac ? d : NULL);
                P += sm->qw[k] * v;
                if (jac)
                    for (int c = 0; c < 6; c++) dP[c] += sm->qw[k] * d[c];
            }
        } else {
            P = spot_profile(&sh, t, px, py, jac ? dP : NULL);
        }
        model[i] = bg + amp * P;
        if (jac) {
            double *row = jac + (size_t)i * N_SPOT_PARAMS;
            row[P_AMP] = P;
            row[P_X0] = amp * dP[0];
            row[P_Y0] = amp * dP[1];
            row[P_FWHM] = amp * dP[2];
            row[P_E1] = amp * dP[3];
            row[P_E2] = amp * dP[4];
            row[P_BETA] = amp * dP[5];
            row[P_BG] = 1.0;
        }
    }
    return 0;
}

/* Pixels to integrate: within max(3, 3 F_major) of the centre (elsewhere the profile is flat
 * on the pixel scale and its centre value is within ~0.1 % of the pixel mean). */
static void mark_integration(unsigned char *integrate, int w, int h, const double *t, int on)
{
    double fmaj = t[P_FWHM] * exp(0.5 * hypot(t[P_E1], t[P_E2]));
    double R = fmax(3.0, 3.0 * fmaj);
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double dx = x - t[P_X0], dy = y - t[P_Y0];
            integrate[(size_t)y * w + x] = on && dx * dx + dy * dy <= R * R;
        }
}

/* Variance of a derived quantity with gradient grad (zeros skipped, so an infinite variance
 * only spreads to what depends on it). */
static double propagate(const double *C, const double *grad)
{
    double v = 0;
    for (int a = 0; a < N_SPOT_PARAMS; a++) {
        if (grad[a] == 0) continue;
        for (int b = 0; b < N_SPOT_PARAMS; b++) {
            if (grad[b] == 0) continue;
            double c = C[a * N_SPOT_PARAMS + b];
            if (c == 0) continue;
            v += grad[a] * c * grad[b];
        }
    }
    return v;
}

static double sqrt_or_inf(double v) { return isfinite(v) ? sqrt(fmax(v, 0.0)) : INFINITY; }

void svp_spot_result_psf(const svp_spot_result *r, svp_psf *psf)
{
    svp_psf_defaults(psf);
    psf->model = r->model;
    psf->fwhm = r->fwhm_major;
    psf->fwhm_minor = r->fwhm_minor;
    psf->angle = r->angle;
    psf->beta = r->model == SVP_PSF_MOFFAT ? r->beta : 2.5;
    psf->subsample = 3;
}

static svp_status check_spot_options(const svp_spot_options *o)
{
    if (o->model != SVP_PSF_GAUSSIAN && o->model != SVP_PSF_LORENTZIAN &&
        o->model != SVP_PSF_MOFFAT)
        return svp_fail(SVP_ERR_INVALID, "spot fit: model %d is not gaussian, lorentzian or "
                        "moffat", (int)o->model);
    if (o->model == SVP_PSF_MOFFAT) {
        if (!(o->beta_min >= SVP_PSF_BETA_MIN) || !(o->beta_max > o->beta_min) ||
            !isfinite(o->beta_max))
            return svp_fail(SVP_ERR_INVALID, "spot fit: beta bounds [%g, %g] must satisfy %g <= "
                            "beta_min < beta_max < inf", o->beta_min, o->beta_max,
                            SVP_PSF_BETA_MIN);
        if (!(o->beta >= SVP_PSF_BETA_MIN) || !isfinite(o->beta) ||
            (!o->fix_beta && (o->beta < o->beta_min || o->beta > o->beta_max)))
            return svp_fail(SVP_ERR_INVALID, "spot fit: beta %g must be >= %g%s", o->beta,
                            SVP_PSF_BETA_MIN,
                            o->fix_beta ? "" : " and within [beta_min, beta_max]");
    }
    if (!(o->hot_ratio > 1) || !(o->hot_sigma > 0) || !(o->clip_kappa >= 0) ||
        o->clip_iterations < 0 || !(o->border_fwhm >= 0) || !(o->min_snr >= 0) ||
        !(o->chi2_red_max > 0) || !(o->ee_radius >= 0) || isnan(o->saturation))
        return svp_fail(SVP_ERR_INVALID, "spot fit: options out of range (hot_ratio %g > 1, "
                        "hot_sigma %g > 0, clip_kappa %g >= 0, clip_iterations %d >= 0, "
                        "border_fwhm %g >= 0, min_snr %g >= 0, chi2_red_max %g > 0, ee_radius "
                        "%g >= 0)", o->hot_ratio, o->hot_sigma, o->clip_kappa,
                        o->clip_iterations, o->border_fwhm, o->min_snr, o->chi2_red_max,
                        o->ee_radius);
    const svp_noise_model *nm = &o->noise;
    if (!(nm->sigma_bg >= 0) || !(nm->gain >= 0) || !(nm->excess >= 0) ||
        !isfinite(nm->sigma_bg + nm->gain + nm->excess))
        return svp_fail(SVP_ERR_INVALID, "spot fit: noise model sigma_bg %g, gain %g, excess "
                        "%g must be finite and >= 0", nm->sigma_bg, nm->gain, nm->excess);
    return SVP_OK;
}

/* Everything one spot fit allocates, and what its stages pass on. */
typedef struct spot_work {
    int w, h;
    size_t N;
    const double *data;       /* the spot image */
    unsigned char *use;       /* 1 = in the fit */
    unsigned char *integrate; /* per pixel */
    int *index;               /* used pixels */
    double *y;                /* their values */
    double *scratch;
    svp_lm_workspace *ws;
    /* from the stages before the fit */
    double bg0, sigma_mad, var_bg; /* background, its MAD noise, the variance used */
    int known_noise;               /* a noise model is given (else the MAD) */
    double sat_level;              /* saturation level (INFINITY: none) */
} spot_work;

static void spot_work_free(spot_work *sw)
{
    free(sw->use);
    free(sw->integrate);
    free(sw->index);
    free(sw->y);
    free(sw->scratch);
    svp_lm_workspace_free(sw->ws);
}

static int collect_points(spot_work *sw, const double *data)
{
    int n = 0;
    for (size_t i = 0; i < sw->N; i++)
        if (sw->use[i]) {
            sw->index[n] = (int)i;
            sw->y[n] = data[i];
            n++;
        }
    return n;
}

/* One LM fit over the used pixels. Returns the LM status (OK or NUMERIC, else a hard error). */
static svp_status spot_solve(spot_work *sw, spot_model *sm, const svp_spot_options *o,
                             const double *lo, const double *hi, int known_noise, double *t,
                             svp_lm_result *lmr, double *cov, const double *data)
{
    int n = collect_points(sw, data);
    svp_lm_problem prob;
    memset(&prob, 0, sizeof prob);
    prob.n_params = N_SPOT_PARAMS;
    prob.n_points = n;
    prob.model = spot_model_eval;
    prob.user = sm;
    prob.analytic_jacobian = 1;
    prob.data = sw->y;
    if (known_noise) prob.noise = o->noise;
    prob.lower = lo;
    prob.upper = hi;
    sm->index = sw->index;
    return svp_lm_solve(sw->ws, &prob, &o->lm, t, lmr, cov);
}

/* axis ratio up to e^2.5 ≈ 12 */
#define SPOT_E_MAX 2.5

/* Stage 1: the work arrays, and the finite pixels as the first mask. */
static svp_status spot_prepare(spot_work *sw, const svp_image *spot)
{
    const int w = spot->width, h = spot->height;
    sw->w = w;
    sw->h = h;
    sw->N = (size_t)w * h;
    sw->data = spot->data;
    const size_t N = sw->N;
    sw->use = calloc(N, 1);
    sw->integrate = calloc(N, 1);
    sw->index = malloc(N * sizeof(int));
    sw->y = malloc(N * sizeof(double));
    sw->scratch = malloc(N * sizeof(double));
    if (!sw->use || !sw->integrate || !sw->index || !sw->y || !sw->scratch)
        return svp_fail(SVP_ERR_NOMEM, "spot fit: out of memory for a %d x %d image", w, h);
    size_t n_finite = 0;
    for (size_t i = 0; i < N; i++) {
        sw->use[i] = isfinite(sw->data[i]) != 0;
        n_finite += sw->use[i];
    }
    if (n_finite < 25)
        return svp_fail(SVP_ERR_INVALID, "spot fit: the %d x %d spot image has %zu finite "
                        "pixels (at least 25 needed)", w, h, n_finite);
    return SVP_OK;
}

/* Stage 2: background and its noise from the border ring (median, MAD). */
static void spot_background(spot_work *sw, const svp_spot_options *o)
{
    const int w = sw->w, h = sw->h;
    const double *data = sw->data;
    int ring = (w < h ? w : h) / 10;
    if (ring < 1) ring = 1;
    size_t nb = 0;
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            if (x >= ring && x < w - ring && y >= ring && y < h - ring) continue;
            double v = data[(size_t)y * w + x];
            if (isfinite(v)) sw->scratch[nb++] = v;
        }
    if (nb < 4) {
        for (size_t i = 0; i < sw->N; i++)
            if (sw->use[i]) sw->scratch[nb++] = data[i];
    }
    double bg0 = svp_median(sw->scratch, nb);
    for (size_t i = 0; i < nb; i++) sw->scratch[i] = fabs(sw->scratch[i] - bg0);
    double sigma_mad = 1.4826 * svp_median(sw->scratch, nb);
    sw->bg0 = bg0;
    sw->sigma_mad = sigma_mad;
    sw->known_noise = o->noise.gain > 0 || o->noise.sigma_bg > 0 || o->noise.excess > 0;
    sw->var_bg = sw->known_noise ? svp_noise_variance(&o->noise, bg0) : sigma_mad * sigma_mad;
}

/* Stage 3: saturation: a given level, or a plateau of >= 3 pixels equal to the maximum. */
static void spot_exclude_saturated(spot_work *sw, const svp_spot_options *o, svp_spot_result *res)
{
    const size_t N = sw->N;
    const double *data = sw->data;
    double vmax = -INFINITY;
    for (size_t i = 0; i < N; i++)
        if (sw->use[i] && data[i] > vmax) vmax = data[i];
    double sat_level = INFINITY;
    if (o->saturation > 0) {
        sat_level = o->saturation;
    } else if (o->saturation == 0) {
        int n_max = 0;
        for (size_t i = 0; i < N; i++)
            if (sw->use[i] && data[i] == vmax) n_max++;
        if (n_max >= 3 && vmax > sw->bg0 + o->min_snr * sqrt(sw->var_bg)) sat_level = vmax;
    }
    for (size_t i = 0; i < N; i++)
        if (sw->use[i] && data[i] >= sat_level) {
            sw->use[i] = 0;
            res->n_saturated++;
        }
    sw->sat_level = sat_level;
}

/* Stage 4: hot pixels: far above the brightest of their 8 neighbours, by ratio and
 * significance. */
static void spot_exclude_hot(spot_work *sw, const svp_spot_options *o, svp_spot_result *res)
{
    const int w = sw->w, h = sw->h;
    const double *data = sw->data;
    const double bg0 = sw->bg0;
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            size_t i = (size_t)y * w + x;
            if (!sw->use[i]) continue;
            double nbmax = -INFINITY;
            int count = 0;
            for (int dy = -1; dy <= 1; dy++)
                for (int dx = -1; dx <= 1; dx++) {
                    int xx = x + dx, yy = y + dy;
                    if ((dx == 0 && dy == 0) || xx < 0 || yy < 0 || xx >= w || yy >= h)
                        continue;
                    double v = data[(size_t)yy * w + xx];
                    if (!isfinite(v)) continue;
                    if (v > nbmax) nbmax = v;
                    count++;
                }
            if (count < 3) continue;
            double v = data[i];
            double sig = sw->known_noise ? sqrt(svp_noise_variance(&o->noise, nbmax))
                                         : sw->sigma_mad;
            if (v - bg0 > o->hot_ratio * fmax(nbmax - bg0, 0.0) &&
                v - nbmax > o->hot_sigma * sig) {
                sw->scratch[res->n_hot] = (double)i; /* mark after the scan */
                res->n_hot++;
            }
        }
    for (int k = 0; k < res->n_hot; k++) sw->use[(size_t)sw->scratch[k]] = 0;
}

/* Stage 5: the peak, the brightest 3×3 mean of used pixels; an error when it does not stand
 * min_snr above the background. */
static svp_status spot_find_peak(const spot_work *sw, const svp_spot_options *o, int *px_out,
                                 int *py_out)
{
    const int w = sw->w, h = sw->h;
    const double *data = sw->data;
    double peak3 = -INFINITY;
    int px = -1, py = -1;
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double s = 0;
            int c = 0;
            for (int dy = -1; dy <= 1; dy++)
                for (int dx = -1; dx <= 1; dx++) {
                    int xx = x + dx, yy = y + dy;
                    if (xx < 0 || yy < 0 || xx >= w || yy >= h) continue;
                    size_t j = (size_t)yy * w + xx;
                    if (!sw->use[j]) continue;
                    s += data[j];
                    c++;
                }
            if (c >= 3 && s / c > peak3) {
                peak3 = s / c;
                px = x;
                py = y;
            }
        }
    const double bg0 = sw->bg0;
    double snr = (peak3 - bg0) / sqrt(sw->var_bg / 9.0);
    if (px < 0 || !(peak3 - bg0 > 0) || !(snr >= o->min_snr)) {
        /* a noise model whose σ is far from the background's own scatter: data that are not
         * photon counts at the given gain (a spot image normalised to 1 has a Poisson σ of
         * about 0.1 at gain 1, its scatter perhaps 1e-3) */
        char hint[300] = "";
        const double model_sigma = sqrt(sw->var_bg), mad = sw->sigma_mad;
        if (sw->known_noise && mad > 0 && (model_sigma > NOISE_MISMATCH * mad ||
                                           mad > NOISE_MISMATCH * model_sigma))
            snprintf(hint, sizeof hint,
                     "; the noise model's sigma there is %.3g but the background scatters by "
                     "%.3g (MAD): if the data are not photon counts at gain %g, give their gain, "
                     "or gain 0 for unknown noise (unit weights)",
                     model_sigma, mad, o->noise.gain);
        return svp_fail(SVP_ERR_INVALID, "spot fit: the %d x %d image holds no spot: its "
                        "brightest 3x3 mean stands %.2g sigma above the background %.6g (at "
                        "least min_snr = %g needed)%s", w, h, isfinite(snr) ? snr : 0.0, bg0,
                        o->min_snr, hint);
    }
    *px_out = px;
    *py_out = py;
    return SVP_OK;
}

/* Stage 6: the starting parameters from moments around the peak (px, py). */
static void spot_start(const spot_work *sw, const svp_spot_options *o, int px, int py,
                       int n_saturated, double t[N_SPOT_PARAMS])
{
    const int w = sw->w, h = sw->h;
    const size_t N = sw->N;
    const double *data = sw->data;
    const double bg0 = sw->bg0;
    double amp0 = -INFINITY;
    for (int dy = -1; dy <= 1; dy++)
        for (int dx = -1; dx <= 1; dx++) {
            int xx = px + dx, yy = py + dy;
            if (xx < 0 || yy < 0 || xx >= w || yy >= h) continue;
            size_t j = (size_t)yy * w + xx;
            if (sw->use[j] && data[j] > amp0) amp0 = data[j];
        }
    amp0 -= bg0;
    /* a saturated peak is at least the saturation level (only when pixels were cut: a level
     * above every pixel says nothing about the peak and must not move the start) */
    if (isfinite(sw->sat_level) && n_saturated > 0) amp0 = fmax(amp0, sw->sat_level - bg0);
    int n_half = 0;
    for (size_t i = 0; i < N; i++)
        if (isfinite(data[i]) && data[i] - bg0 >= 0.5 * amp0) n_half++;
    double F0 = sqrt(4.0 * n_half / M_PI);
    F0 = fmin(fmax(F0, 1.0), 0.5 * (w < h ? w : h));
    double cx = isfinite(o->x0) ? o->x0 : px, cy = isfinite(o->y0) ? o->y0 : py;
    {
        double R = fmax(2.0, 1.5 * F0), s0 = 0, sx = 0, sy = 0;
        for (int pass = 0; pass < 2; pass++) {
            double sxx = 0, syy = 0, sxy = 0;
            s0 = sx = sy = 0;
            for (int y = 0; y < h; y++)
                for (int x = 0; x < w; x++) {
                    size_t i = (size_t)y * w + x;
                    double dx = x - cx, dy = y - cy;
                    if (!sw->use[i] || dx * dx + dy * dy > R * R) continue;
                    double v = data[i] - bg0;
                    if (v <= 0) continue;
                    s0 += v;
                    sx += v * dx;
                    sy += v * dy;
                    sxx += v * dx * dx;
                    syy += v * dy * dy;
                    sxy += v * dx * dy;
                }
            if (!(s0 > 0)) break;
            double mx = sx / s0, my = sy / s0;
            double mxx = sxx / s0 - mx * mx, myy = syy / s0 - my * my, mxy = sxy / s0 - mx * my;
            if (pass == 0 && !isfinite(o->x0)) {
                cx += mx;
                cy += my;
                continue;
            }
            double tr = mxx + myy, det = mxx * myy - mxy * mxy;
            double disc = sqrt(fmax(0.25 * tr * tr - det, 0.0));
            double l1 = 0.5 * tr + disc, l2 = 0.5 * tr - disc;
            double g = l2 > 0 ? fmin(0.5 * log(l1 / l2), 1.0) : 0.0;
            double th2 = atan2(2 * mxy, mxx - myy);
            t[P_E1] = g * cos(th2);
            t[P_E2] = g * sin(th2);
            break;
        }
        if (!(s0 > 0)) t[P_E1] = t[P_E2] = 0;
    }
    t[P_AMP] = amp0;
    t[P_X0] = fmin(fmax(cx, 0.0), w - 1.0);
    t[P_Y0] = fmin(fmax(cy, 0.0), h - 1.0);
    t[P_FWHM] = F0;
    t[P_BETA] = o->model == SVP_PSF_MOFFAT ? o->beta : o->model == SVP_PSF_LORENTZIAN ? 1.0 : 0.0;
    t[P_BG] = bg0;
    if (!o->elliptical) t[P_E1] = t[P_E2] = 0;
}

/* Stage 7: the parameters' bounds (β fixed at its start unless a free Moffat). */
static void spot_bounds(const svp_spot_options *o, int w, int h, const double *t, double *lo,
                        double *hi)
{
    lo[P_AMP] = 0;
    hi[P_AMP] = INFINITY;
    lo[P_X0] = -0.5;
    hi[P_X0] = w - 0.5;
    lo[P_Y0] = -0.5;
    hi[P_Y0] = h - 0.5;
    lo[P_FWHM] = 0.3;
    hi[P_FWHM] = 2.0 * (w > h ? w : h);
    lo[P_E1] = lo[P_E2] = o->elliptical ? -SPOT_E_MAX : 0.0;
    hi[P_E1] = hi[P_E2] = o->elliptical ? SPOT_E_MAX : 0.0;
    if (o->model == SVP_PSF_MOFFAT && !o->fix_beta) {
        lo[P_BETA] = o->beta_min;
        hi[P_BETA] = o->beta_max;
    } else {
        lo[P_BETA] = hi[P_BETA] = t[P_BETA];
    }
    lo[P_BG] = -INFINITY;
    hi[P_BG] = INFINITY;
}

/* Stage 8b: κ-σ clipping of the normalised residuals z of the last fit, worst first: only
 * pixels above max(κ, max|z| / 2) go in one round, so one spike cannot drag good pixels out
 * with it. Many moderate outliers mean the model does not fit (POOR_FIT), not that pixels are
 * bad: then nothing is clipped. Returns 1 when pixels were removed (fit again). */
static int spot_clip(spot_work *sw, const svp_spot_options *o, const svp_lm_result *lmr,
                     svp_spot_result *res)
{
    const int m = svp_lm_n_points(sw->ws);
    const double *r = svp_lm_residuals(sw->ws); /* √w (f − y) */
    double scale = sw->known_noise ? 1.0 : sqrt(fmax(lmr->chi2_red, 1e-300));
    double zmax = 0;
    int n_out = 0;
    for (int k = 0; k < m; k++) {
        double z = fabs(r[k]) / scale;
        zmax = fmax(zmax, z);
        n_out += z > o->clip_kappa;
    }
    int systematic = n_out > 5 && n_out > m / 50 && zmax < 4 * o->clip_kappa;
    if (n_out == 0 || systematic) return 0;
    double thr = fmax(o->clip_kappa, 0.5 * zmax);
    int removed = 0;
    for (int k = 0; k < m; k++) removed += fabs(r[k]) / scale > thr;
    if (m - removed < 2 * N_SPOT_PARAMS) return 0;
    for (int k = 0; k < m; k++)
        if (fabs(r[k]) / scale > thr) sw->use[sw->index[k]] = 0;
    res->n_clipped += removed;
    return 1;
}

/* Stage 8: the fit, repeated while the quadrature is refined or pixels are clipped; then,
 * when β crawled along its bound (the sin transform flattens there) until the iterations ran
 * out, once more with β held at the bound. Returns the LM status (OK or NUMERIC) in *fit_st,
 * a hard error as the result. */
static svp_status spot_fit_loop(spot_work *sw, spot_model *sm, const svp_spot_options *o,
                                double *t, double *lo, double *hi, svp_lm_result *lmr,
                                double *cov, svp_spot_result *res, svp_status *fit_st_out,
                                int *beta_pinned)
{
    const int w = sw->w, h = sw->h;
    int order = 2;
    if (o->pixel_integration && t[P_FWHM] * exp(-0.5 * hypot(t[P_E1], t[P_E2])) < 2.0)
        order = 4;
    set_quadrature(sm, order);
    mark_integration(sw->integrate, w, h, t, o->pixel_integration);

    svp_status fit_st = SVP_OK;
    int clip_rounds = 0;
    for (;;) {
        fit_st = spot_solve(sw, sm, o, lo, hi, sw->known_noise, t, lmr, cov, sw->data);
        if (fit_st != SVP_OK && fit_st != SVP_ERR_NUMERIC)
            return svp_fail_context(fit_st, "spot fit");
        int refit = 0;
        /* A narrow result needs the finer quadrature (switched once, never back). */
        double fmin_fit = t[P_FWHM] * exp(-0.5 * hypot(t[P_E1], t[P_E2]));
        if (o->pixel_integration && order == 2 && fmin_fit < 2.0) {
            order = 4;
            set_quadrature(sm, order);
            refit = 1;
        }
        if (o->clip_kappa > 0 && clip_rounds < o->clip_iterations && fit_st == SVP_OK &&
            spot_clip(sw, o, lmr, res)) {
            clip_rounds++;
            refit = 1;
        }
        if (!refit) break;
        mark_integration(sw->integrate, w, h, t, o->pixel_integration);
    }

    *beta_pinned = 0;
    if (fit_st == SVP_ERR_NUMERIC && o->model == SVP_PSF_MOFFAT && !o->fix_beta &&
        (t[P_BETA] <= 1.02 * o->beta_min || t[P_BETA] >= 0.98 * o->beta_max)) {
        double bound = t[P_BETA] <= 1.02 * o->beta_min ? o->beta_min : o->beta_max;
        lo[P_BETA] = hi[P_BETA] = t[P_BETA] = bound;
        fit_st = spot_solve(sw, sm, o, lo, hi, sw->known_noise, t, lmr, cov, sw->data);
        if (fit_st != SVP_OK && fit_st != SVP_ERR_NUMERIC)
            return svp_fail_context(fit_st, "spot fit");
        *beta_pinned = 1;
        cov[P_BETA * 9] = INFINITY;
    }
    *fit_st_out = fit_st;
    return SVP_OK;
}

/* Stage 9: the reported parameters and their 1σ errors from the fit's (t, cov). */
static void spot_results(const svp_spot_options *o, const double *t, const double *cov,
                         svp_spot_result *res)
{
    const double F = t[P_FWHM], g1 = t[P_E1], g2 = t[P_E2], g = hypot(g1, g2);
    res->amplitude = t[P_AMP];
    res->x0 = t[P_X0];
    res->y0 = t[P_Y0];
    res->fwhm_major = F * exp(0.5 * g);
    res->fwhm_minor = F * exp(-0.5 * g);
    res->fwhm = F * cosh(0.5 * g); /* (major + minor) / 2 */
    res->angle = g > 0 ? 0.5 * atan2(g2, g1) : 0.0;
    if (res->angle <= -M_PI / 2) res->angle += M_PI;
    /* field ellipticity e = tanh(g / 2) along (g1, g2) / g; tau = tanh(g / 2) / g */
    double tau, dtau_g; /* τ and τ'(g) / g */
    if (g < 1e-3) {
        tau = 0.5 - g * g / 24.0;
        dtau_g = -1.0 / 12.0;
    } else {
        double th = tanh(0.5 * g);
        tau = th / g;
        dtau_g = (0.5 * g * (1.0 - th * th) - th) / (g * g * g);
    }
    res->e1 = tau * g1;
    res->e2 = tau * g2;
    res->beta = o->model == SVP_PSF_GAUSSIAN ? 0.0 : t[P_BETA];
    res->background = t[P_BG];
    memcpy(res->covariance, cov, sizeof res->covariance);
    const double *C = cov;
    double grad[N_SPOT_PARAMS];
    res->amplitude_err = sqrt_or_inf(C[P_AMP * 9]);
    res->x0_err = sqrt_or_inf(C[P_X0 * 9]);
    res->y0_err = sqrt_or_inf(C[P_Y0 * 9]);
    memset(grad, 0, sizeof grad);
    grad[P_FWHM] = cosh(0.5 * g);
    if (g > 0) {
        grad[P_E1] = 0.5 * F * sinh(0.5 * g) * g1 / g;
        grad[P_E2] = 0.5 * F * sinh(0.5 * g) * g2 / g;
    }
    res->fwhm_err = sqrt_or_inf(propagate(C, grad));
    memset(grad, 0, sizeof grad);
    grad[P_E1] = tau + g1 * g1 * dtau_g;
    grad[P_E2] = g1 * g2 * dtau_g;
    res->e1_err = sqrt_or_inf(propagate(C, grad));
    memset(grad, 0, sizeof grad);
    grad[P_E1] = g1 * g2 * dtau_g;
    grad[P_E2] = tau + g2 * g2 * dtau_g;
    res->e2_err = sqrt_or_inf(propagate(C, grad));
    res->beta_err = sqrt_or_inf(C[P_BETA * 9]);
    res->background_err = sqrt_or_inf(C[P_BG * 9]);
    double ux = g > 0 ? g1 / g : M_SQRT1_2, uy = g > 0 ? g2 / g : M_SQRT1_2;
    for (int s = 0; s < 2; s++) {
        double sign = s == 0 ? 1.0 : -1.0;
        double fa = s == 0 ? res->fwhm_major : res->fwhm_minor;
        memset(grad, 0, sizeof grad);
        grad[P_FWHM] = fa / F;
        grad[P_E1] = sign * 0.5 * fa * ux;
        grad[P_E2] = sign * 0.5 * fa * uy;
        double e = sqrt_or_inf(propagate(C, grad));
        if (s == 0)
            res->fwhm_major_err = e;
        else
            res->fwhm_minor_err = e;
    }
    memset(grad, 0, sizeof grad);
    if (g > 0) {
        grad[P_E1] = -0.5 * g2 / (g * g);
        grad[P_E2] = 0.5 * g1 / (g * g);
        res->angle_err = sqrt_or_inf(propagate(C, grad));
    } else {
        res->angle_err = INFINITY;
    }
    if (!o->elliptical) res->angle_err = 0;
    /* r0 (σ for a Gaussian) and ∂r0/∂β = r0 kβ / 2 from the fitted shape (kβ = 0 Gaussian) */
    spot_shape sh;
    spot_shape_setup(o->model, t, &sh);
    memset(grad, 0, sizeof grad);
    res->r0 = svp_psf_fwhm_to_r0(F, sh.beta);
    grad[P_FWHM] = res->r0 / F;
    grad[P_BETA] = 0.5 * res->r0 * sh.kbeta;
    res->r0_err = sqrt_or_inf(propagate(C, grad));
}

/* Stage 10: fit statistics and the flags. */
static void spot_flags(const spot_work *sw, const svp_spot_options *o, const double *t,
                       const double *lo, const double *hi, const svp_lm_result *lmr,
                       svp_status fit_st, int beta_pinned, svp_spot_result *res)
{
    const int w = sw->w, h = sw->h;
    const double F = t[P_FWHM], g = hypot(t[P_E1], t[P_E2]);
    res->chi2 = lmr->chi2;
    res->chi2_red = lmr->chi2_red;
    res->dof = lmr->dof;
    res->iterations = lmr->iterations;
    res->n_used = svp_lm_n_points(sw->ws);
    double bd = fmin(fmin(res->x0 + 0.5, w - 0.5 - res->x0), fmin(res->y0 + 0.5, h - 0.5 - res->y0));
    res->border_distance = bd;
    if (fit_st == SVP_ERR_NUMERIC) res->flags |= SVP_SPOT_NOT_CONVERGED;
    if (bd < o->border_fwhm * res->fwhm_major) res->flags |= SVP_SPOT_NEAR_BORDER;
    if (res->n_saturated) res->flags |= SVP_SPOT_SATURATED;
    if (res->n_hot) res->flags |= SVP_SPOT_HOT_PIXELS;
    if (res->n_clipped) res->flags |= SVP_SPOT_CLIPPED;
    if (!lmr->covariance_ok) res->flags |= SVP_SPOT_NO_ERRORS;
    if (o->model == SVP_PSF_MOFFAT && !o->fix_beta &&
        (beta_pinned || (lmr->at_bound >> P_BETA & 1) || t[P_BETA] <= 1.02 * o->beta_min ||
         t[P_BETA] >= 0.98 * o->beta_max))
        res->flags |= SVP_SPOT_BETA_AT_BOUND;
    if ((lmr->at_bound >> P_FWHM & 1) || F <= 1.02 * lo[P_FWHM] || F >= 0.98 * hi[P_FWHM] ||
        g >= 0.98 * SPOT_E_MAX)
        res->flags |= SVP_SPOT_WIDTH_AT_BOUND;
    if (sw->known_noise && res->chi2_red > o->chi2_red_max) res->flags |= SVP_SPOT_POOR_FIT;
}

/* Stage 11: encircled energy within a disc (the flux of β ≤ 1 diverges over the plane). */
static void spot_encircled(const svp_spot_options *o, int w, int h, svp_spot_result *res)
{
    res->ee_radius = o->ee_radius > 0 ? o->ee_radius : 0.5 * (w < h ? w : h);
    svp_psf psf;
    svp_spot_result_psf(res, &psf);
    const double fr[3] = {0.5, 0.8, 0.95};
    double *dst[3] = {&res->ee50, &res->ee80, &res->ee95};
    for (int k = 0; k < 3; k++)
        if (svp_psf_encircled_radius(&psf, fr[k], res->ee_radius, dst[k]) != SVP_OK) *dst[k] = 0;
}

/* The fit, stage by stage; used_out (may be NULL, else w·h bytes) receives 1 for the pixels
 * of the final fit, 0 for the excluded ones (non-finite, saturated, hot, clipped). */
static svp_status spot_fit_impl(const svp_image *spot, const svp_spot_options *options,
                                svp_spot_result *res, svp_image *model_image,
                                svp_image *residual, unsigned char *used_out)
{
    if (!spot || !spot->data || !res)
        return svp_fail(SVP_ERR_INVALID, "spot fit: spot image and result are required");
    svp_spot_options o;
    if (options)
        o = *options;
    else
        svp_spot_defaults(&o);
    SVP_CHECK(check_spot_options(&o));
    const int w = spot->width, h = spot->height;
    if (w < 5 || h < 5)
        return svp_fail(SVP_ERR_INVALID, "spot fit: the %d x %d spot image is too small (at "
                        "least 5 x 5 pixels)", w, h);
    SVP_CHECK(svp_image_check_scale(spot, "spot fit: the spot image"));
    if (model_image) SVP_CHECK(svp_image_same_size(spot, model_image, "spot", "model image"));
    if (residual) SVP_CHECK(svp_image_same_size(spot, residual, "spot", "residual image"));
    memset(res, 0, sizeof *res);
    res->model = o.model;

    spot_work sw;
    memset(&sw, 0, sizeof sw);
    const size_t N = (size_t)w * h;
    const double *data = spot->data;
    double t[N_SPOT_PARAMS], lo[N_SPOT_PARAMS], hi[N_SPOT_PARAMS];
    double cov[N_SPOT_PARAMS * N_SPOT_PARAMS];
    svp_lm_result lmr;
    spot_model sm;
    memset(&sm, 0, sizeof sm);
    svp_status fit_st = SVP_OK;
    int px = -1, py = -1, beta_pinned = 0;
    svp_status st = spot_prepare(&sw, spot);
    if (st != SVP_OK) goto cleanup;
    spot_background(&sw, &o);
    spot_exclude_saturated(&sw, &o, res);
    if (o.hot_pixels) spot_exclude_hot(&sw, &o, res);
    st = spot_find_peak(&sw, &o, &px, &py);
    if (st != SVP_OK) goto cleanup;
    spot_start(&sw, &o, px, py, res->n_saturated, t);
    spot_bounds(&o, w, h, t, lo, hi);

    st = svp_lm_workspace_new(N_SPOT_PARAMS, (int)N, &sw.ws);
    if (st != SVP_OK) goto cleanup;
    sm.model = o.model;
    sm.width = w;
    sm.integrate = sw.integrate;
    st = spot_fit_loop(&sw, &sm, &o, t, lo, hi, &lmr, cov, res, &fit_st, &beta_pinned);
    if (st != SVP_OK) goto cleanup;

    spot_results(&o, t, cov, res);
    spot_flags(&sw, &o, t, lo, hi, &lmr, fit_st, beta_pinned, res);
    spot_encircled(&o, w, h, res);

    if (model_image || residual) {
        for (size_t i = 0; i < N; i++) sw.index[i] = (int)i; /* the fit's integration map */
        sm.index = sw.index;
        spot_model_eval(&sm, t, N_SPOT_PARAMS, (int)N, sw.scratch, NULL);
        for (size_t i = 0; i < N; i++) {
            if (model_image) model_image->data[i] = sw.scratch[i];
            if (residual) residual->data[i] = isfinite(data[i]) ? data[i] - sw.scratch[i] : 0.0;
        }
    }

    if (used_out) memcpy(used_out, sw.use, N);
    if ((res->flags & SVP_SPOT_NEAR_BORDER) && o.refuse_near_border) {
        st = svp_fail(SVP_ERR_INVALID, "spot fit: the spot centre (%.2f, %.2f) lies %.2f px "
                      "from the edge of the %d x %d image, closer than %g FWHM (%.2f px): too "
                      "little of its profile is inside the image", res->x0, res->y0,
                      res->border_distance, w, h, o.border_fwhm,
                      o.border_fwhm * res->fwhm_major);
        goto cleanup;
    }
    if (fit_st == SVP_ERR_NUMERIC) {
        st = svp_fail_context(SVP_ERR_NUMERIC, "spot fit (%d x %d, result flagged 'not "
                              "converged')", w, h);
        goto cleanup;
    }
    st = SVP_OK;
cleanup:
    spot_work_free(&sw);
    return st;
}

svp_status svp_spot_fit(const svp_image *spot, const svp_spot_options *options,
                        svp_spot_result *res, svp_image *model_image, svp_image *residual)
{
    return spot_fit_impl(spot, options, res, model_image, residual, NULL);
}

svp_status svp_spot_fit_used(const svp_image *spot, const svp_spot_options *options,
                             svp_spot_result *res, unsigned char *used)
{
    return spot_fit_impl(spot, options, res, NULL, NULL, used);
}

svp_status svp_spot_kernel(const svp_image *ex, const svp_spot_result *fit,
                           const svp_spot_options *so, int R, int from_fit, svp_image **out)
{
    *out = NULL;
    svp_image *k = NULL;
    SVP_CHECK(svp_image_new(2 * R + 1, 2 * R + 1, &k));
    const int cx = (int)lround(fit->x0), cy = (int)lround(fit->y0);
    double t[N_SPOT_PARAMS] = {0};
    double g = log(fit->fwhm_major / fit->fwhm_minor);
    t[P_AMP] = fit->amplitude;
    t[P_X0] = fit->x0;
    t[P_Y0] = fit->y0;
    t[P_FWHM] = sqrt(fit->fwhm_major * fit->fwhm_minor);
    t[P_E1] = g * cos(2.0 * fit->angle);
    t[P_E2] = g * sin(2.0 * fit->angle);
    t[P_BETA] = fit->beta;
    t[P_BG] = 0.0;
    spot_shape sh;
    spot_shape_setup(fit->model, t, &sh);
    spot_model sm;
    memset(&sm, 0, sizeof sm);
    set_quadrature(&sm, fit->fwhm_minor < 2.0 ? 4 : 2);
    for (int j = -R; j <= R; j++)
        for (int i = -R; i <= R; i++) {
            double v = 0;
            int x = cx + i, y = cy + j;
            if (i * i + j * j <= R * R) {
                if (from_fit) {
                    double dx = x - fit->x0, dy = y - fit->y0;
                    if (so->pixel_integration) {
                        for (int q = 0; q < sm.nq; q++)
                            v += sm.qw[q] * spot_profile(&sh, t, dx + sm.qx[q], dy + sm.qy[q],
                                                         NULL);
                    } else {
                        v = spot_profile(&sh, t, dx, dy, NULL);
                    }
                    v *= fit->amplitude;
                } else if (x >= 0 && y >= 0 && x < ex->width && y < ex->height) {
                    double d = ex->data[(size_t)y * ex->width + x];
                    v = isfinite(d) ? fmax(d - fit->background, 0.0) : 0.0;
                }
            }
            k->data[(size_t)(j + R) * k->width + (i + R)] = v;
        }
    *out = k;
    return SVP_OK;
}
