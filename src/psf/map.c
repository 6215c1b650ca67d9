/* PSF maps from many spot fits: polynomial surfaces of the PSF-field parameters over the field
 * (weighted least squares, degree by k-fold cross-validation), or per-region statistics with
 * Welch tests deciding which regions share a PSF. Output: an svp_psf_field (field.c). */
#include "../core/internal.h"

#include <lapacke.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define NP SVP_FIELD_NPARAM
#define MAX_DEGREE 8
#define MAX_TERMS 45 /* (8 + 1)(8 + 2) / 2 */

static const char *const param_names[NP] = {"fwhm", "e1", "e2", "beta", "halo"};

void svp_map_defaults(svp_map_options *o)
{
    o->degree = -1;
    o->max_degree = 3;
    o->folds = 5;
    o->reject_flags = SVP_SPOT_NOT_CONVERGED | SVP_SPOT_NEAR_BORDER | SVP_SPOT_SATURATED |
                      SVP_SPOT_BETA_AT_BOUND | SVP_SPOT_NO_ERRORS | SVP_SPOT_WIDTH_AT_BOUND;
    o->clip_kappa = 4.0;
    o->clip_iterations = 5;
    o->alpha = 0.01;
    o->transition = 0.0;
    o->halo = 0.0;
    o->support = 0.0;
    o->subsample = 0;
}

const char *svp_map_reject_string(svp_map_reject code)
{
    switch (code) {
    case SVP_MAP_KEPT: return "kept";
    case SVP_MAP_REJECT_FLAGS: return "spot fit flagged";
    case SVP_MAP_REJECT_INVALID: return "value or uncertainty invalid";
    case SVP_MAP_REJECT_OUTSIDE: return "outside the field";
    case SVP_MAP_REJECT_OUTLIER: return "outlier";
    }
    return "unknown";
}

void svp_map_report_free(svp_map_report *r)
{
    if (!r) return;
    free(r->reject);
    free(r->reject_z);
    free(r->regions);
    free(r->groups);
    free(r->p_value);
    free(r);
}

size_t svp_map_describe_sample(const svp_map_report *r, const svp_psf_sample *samples,
                               int index, char *buf, size_t size)
{
    char tmp[1024];
    size_t len = 0;
    if (!r || index < 0 || index >= r->n_samples) {
        len = (size_t)snprintf(tmp, sizeof tmp, "spot %d: no such spot", index);
    } else {
        int k = snprintf(tmp, sizeof tmp, "spot %d", index);
        if (k > 0) len = (size_t)k;
        if (samples) {
            k = snprintf(tmp + len, sizeof tmp - len, " (x %.1f, y %.1f)", samples[index].x,
                         samples[index].y);
            if (k > 0) len += (size_t)k;
        }
        const int *code = r->reject + (size_t)index * NP;
        int any = 0, whole = 1;
        for (int q = 0; q < NP; q++) {
            if (!r->mapped[q]) continue;
            if (code[q] != SVP_MAP_KEPT) any = 1;
            if (code[q] == SVP_MAP_KEPT || code[q] == SVP_MAP_REJECT_OUTLIER) whole = 0;
        }
        if (!any) {
            k = snprintf(tmp + len, sizeof tmp - len, ": kept");
            if (k > 0) len += (size_t)k;
        } else if (whole) {
            int c = code[SVP_FIELD_FWHM];
            k = snprintf(tmp + len, sizeof tmp - len, ": rejected: %s",
                         svp_map_reject_string((svp_map_reject)c));
            if (k > 0) len += (size_t)k;
            if (c == SVP_MAP_REJECT_FLAGS && samples) {
                char fl[512];
                svp_spot_flags_describe(samples[index].fit.flags, fl, sizeof fl);
                k = snprintf(tmp + len, sizeof tmp - len, " (%s)", fl);
                if (k > 0 && len + (size_t)k < sizeof tmp) len += (size_t)k;
            }
        } else {
            k = snprintf(tmp + len, sizeof tmp - len, ": rejected for");
            if (k > 0) len += (size_t)k;
            int first = 1;
            for (int q = 0; q < NP; q++) {
                if (!r->mapped[q] || code[q] == SVP_MAP_KEPT) continue;
                if (code[q] == SVP_MAP_REJECT_OUTLIER)
                    k = snprintf(tmp + len, sizeof tmp - len, "%s %s outlier (z = %.1f)",
                                 first ? "" : ",", param_names[q],
                                 r->reject_z[(size_t)index * NP + q]);
                else
                    k = snprintf(tmp + len, sizeof tmp - len, "%s %s (%s)", first ? "" : ",",
                                 param_names[q], svp_map_reject_string((svp_map_reject)code[q]));
                if (k > 0 && len + (size_t)k < sizeof tmp) len += (size_t)k;
                first = 0;
            }
        }
    }
    if (len >= sizeof tmp) len = sizeof tmp - 1;
    if (buf && size > 0) {
        size_t c = len < size - 1 ? len : size - 1;
        memcpy(buf, tmp, c);
        buf[c] = '\0';
    }
    return len;
}

/* The field parameter vector of a fit and its 1σ errors. */
/* The mapped field's common PSF: the report's model, the options' support and subsample; and
 * the value given to β when it is not mapped (the model's own, as a field file reads it). */
static svp_psf map_base(const svp_map_report *rep, const svp_map_options *o)
{
    svp_psf base;
    svp_psf_defaults(&base);
    base.model = rep->model;
    base.support = o->support;
    base.subsample = o->subsample;
    return base;
}

static double unmapped_beta(const svp_map_report *rep)
{
    return rep->model == SVP_PSF_LORENTZIAN ? 1.0 : 2.5;
}

static void sample_values(const svp_spot_result *f, double v[NP], double e[NP])
{
    v[SVP_FIELD_FWHM] = f->fwhm;
    v[SVP_FIELD_E1] = f->e1;
    v[SVP_FIELD_E2] = f->e2;
    v[SVP_FIELD_BETA] = f->model == SVP_PSF_LORENTZIAN ? 1.0 : f->beta;
    v[SVP_FIELD_HALO] = 0.0;
    e[SVP_FIELD_FWHM] = f->fwhm_err;
    e[SVP_FIELD_E1] = f->e1_err;
    e[SVP_FIELD_E2] = f->e2_err;
    e[SVP_FIELD_BETA] = f->beta_err;
    e[SVP_FIELD_HALO] = 0.0;
}

static svp_status check_options(const svp_map_options *o)
{
    if (o->degree < -1 || o->degree > MAX_DEGREE)
        return svp_fail(SVP_ERR_INVALID, "PSF map: degree %d must be -1 (cross-validation) or "
                        "0..%d", o->degree, MAX_DEGREE);
    if (o->max_degree < 0 || o->max_degree > MAX_DEGREE)
        return svp_fail(SVP_ERR_INVALID, "PSF map: max_degree %d must be in 0..%d",
                        o->max_degree, MAX_DEGREE);
    if (o->folds < 2)
        return svp_fail(SVP_ERR_INVALID, "PSF map: folds %d must be >= 2", o->folds);
    if (!(o->clip_kappa >= 0) || o->clip_iterations < 0)
        return svp_fail(SVP_ERR_INVALID, "PSF map: clip_kappa %g and clip_iterations %d must "
                        "be >= 0", o->clip_kappa, o->clip_iterations);
    if (!(o->alpha > 0 && o->alpha < 1))
        return svp_fail(SVP_ERR_INVALID, "PSF map: alpha %g must be in (0, 1)", o->alpha);
    if (!(o->halo >= 0 && o->halo < 1))
        return svp_fail(SVP_ERR_INVALID, "PSF map: halo %g must be in [0, 1)", o->halo);
    if (!(o->transition >= 0) || !(o->support >= 0) || o->subsample < 0)
        return svp_fail(SVP_ERR_INVALID, "PSF map: transition %g, support %g and subsample %d "
                        "must be >= 0", o->transition, o->support, o->subsample);
    return SVP_OK;
}

/* Screening shared by both map kinds: flags, model, finite values, position. Fills the report
 * header (model, mapped parameters) and the reject codes. */
static svp_status screen_samples(const svp_psf_sample *samples, int n, int width, int height,
                                 const svp_map_options *o, svp_map_report *rep)
{
    if (!samples || n < 1)
        return svp_fail(SVP_ERR_INVALID, "PSF map: no spots given (n = %d)", n);
    if (width < 1 || height < 1)
        return svp_fail(SVP_ERR_INVALID, "PSF map: field size %d x %d must be positive", width,
                        height);
    rep->n_samples = n;
    rep->reject = calloc((size_t)n * NP, sizeof(int));
    rep->reject_z = calloc((size_t)n * NP, sizeof(double));
    if (!rep->reject || !rep->reject_z)
        return svp_fail(SVP_ERR_NOMEM, "PSF map: out of memory for %d spots", n);
    /* The model: that of the first spot without rejecting flags. */
    int first = -1;
    for (int i = 0; i < n && first < 0; i++)
        if (!(samples[i].fit.flags & o->reject_flags)) first = i;
    rep->model = first >= 0 ? samples[first].fit.model : samples[0].fit.model;
    for (int q = 0; q < NP; q++) {
        rep->mapped[q] = 0;
        rep->degree[q] = -1;
    }
    rep->mapped[SVP_FIELD_FWHM] = 1;
    rep->mapped[SVP_FIELD_BETA] = rep->model == SVP_PSF_MOFFAT;
    /* orientation only when some fit measured it (circular fits report e = 0 exactly) */
    for (int i = 0; i < n; i++)
        if (samples[i].fit.e1_err > 0 || samples[i].fit.e2_err > 0)
            rep->mapped[SVP_FIELD_E1] = rep->mapped[SVP_FIELD_E2] = 1;
    for (int i = 0; i < n; i++) {
        const svp_psf_sample *s = &samples[i];
        int *code = rep->reject + (size_t)i * NP;
        int whole = SVP_MAP_KEPT;
        if (s->fit.flags & o->reject_flags)
            whole = SVP_MAP_REJECT_FLAGS;
        else if (s->fit.model != rep->model)
            whole = SVP_MAP_REJECT_INVALID;
        else if (!(s->x >= -0.5 && s->x < width - 0.5 && s->y >= -0.5 && s->y < height - 0.5))
            whole = SVP_MAP_REJECT_OUTSIDE;
        double v[NP], e[NP];
        sample_values(&s->fit, v, e);
        if (whole == SVP_MAP_KEPT && !(isfinite(v[SVP_FIELD_FWHM]) && v[SVP_FIELD_FWHM] > 0))
            whole = SVP_MAP_REJECT_INVALID;
        for (int q = 0; q < NP; q++) {
            code[q] = whole;
            if (whole != SVP_MAP_KEPT || !rep->mapped[q]) continue;
            if (!isfinite(v[q]) || !isfinite(e[q]) || !(e[q] > 0))
                code[q] = SVP_MAP_REJECT_INVALID;
        }
    }
    return SVP_OK;
}

/* ---- polynomial surfaces ---------------------------------------------------------------- */

typedef struct poly_data {
    int n;          /* points in use */
    const double *basis; /* per sample: MAX_TERMS values (all degrees up to MAX_DEGREE) */
    const int *idx; /* sample indices */
    const double *y, *sw; /* per sample: value, 1/σ */
    double *A, *b;  /* scratch: n × MAX_TERMS, max(n, MAX_TERMS) */
} poly_data;

/* Weighted LS on the points whose mask (over the idx list) is nonzero: nt terms. −1 when the
 * points cannot determine them (fewer than nt, or a design of lower rank). */
#define RANK_TOL 1e-8
static int wls_fit(const poly_data *d, const unsigned char *mask, int nt, double *coef)
{
    int m = 0;
    for (int k = 0; k < d->n; k++)
        if (mask[k]) m++;
    if (m < nt) return -1;
    int lda = m, ldb = m > nt ? m : nt;
    int r = 0;
    for (int k = 0; k < d->n; k++) {
        if (!mask[k]) continue;
        int i = d->idx[k];
        for (int t = 0; t < nt; t++) d->A[(size_t)t * lda + r] = d->sw[i] * d->basis[(size_t)i * MAX_TERMS + t];
        d->b[r] = d->sw[i] * d->y[i];
        r++;
    }
    lapack_int info = LAPACKE_dgels(LAPACK_COL_MAJOR, 'N', m, nt, 1, d->A, lda, d->b, ldb);
    if (info != 0) return -1;
    /* the spots must determine every term: a diagonal of R below 1e-8 of its largest means a
     * term that is (nearly) a combination of the others on these positions (e.g. u⁴ on four
     * distinct u), whose coefficient is then round-off amplified (FWHM surfaces of −0.3 µm
     * between spots at 0.3 µm were the result) */
    double rmax = 0, rmin = INFINITY;
    for (int t = 0; t < nt; t++) {
        const double r = fabs(d->A[(size_t)t * lda + t]);
        rmax = fmax(rmax, r);
        rmin = fmin(rmin, r);
    }
    if (!(rmin > RANK_TOL * rmax)) return -1;
    memcpy(coef, d->b, (size_t)nt * sizeof(double));
    return 0;
}

static double poly_eval(const double *basis, const double *coef, int nt)
{
    double s = 0;
    for (int t = 0; t < nt; t++) s += basis[t] * coef[t];
    return s;
}

/* Degree by k-fold cross-validation (one-standard-error rule). Returns -1 if no degree fits. */
static int choose_degree(const poly_data *d, const svp_map_options *o, double *scores,
                         unsigned char *mask)
{
    const int folds = o->folds < d->n ? o->folds : d->n;
    double mean[MAX_DEGREE + 1], se[MAX_DEGREE + 1];
    int best = -1;
    for (int deg = 0; deg <= o->max_degree; deg++) {
        int nt = svp_psf_field_poly_terms(deg);
        double fs[64], sum = 0, sum2 = 0;
        int ok = folds >= 2;
        for (int f = 0; f < folds && ok; f++) {
            for (int k = 0; k < d->n; k++) mask[k] = k % folds != f;
            double coef[MAX_TERMS];
            int ntrain = 0;
            for (int k = 0; k < d->n; k++) ntrain += mask[k];
            if (ntrain <= nt || wls_fit(d, mask, nt, coef) != 0) {
                ok = 0;
                break;
            }
            double sc = 0;
            int c = 0;
            for (int k = 0; k < d->n; k++) {
                if (mask[k]) continue;
                int i = d->idx[k];
                double res = (d->y[i] - poly_eval(d->basis + (size_t)i * MAX_TERMS, coef, nt)) *
                             d->sw[i];
                sc += res * res;
                c++;
            }
            fs[f] = c ? sc / c : 0;
            sum += fs[f];
            sum2 += fs[f] * fs[f];
        }
        if (!ok) break; /* higher degrees have even more terms */
        mean[deg] = sum / folds;
        se[deg] = sqrt(fmax(sum2 / folds - mean[deg] * mean[deg], 0.0) / (folds - 1));
        scores[deg] = mean[deg];
        if (best < 0 || mean[deg] < mean[best]) best = deg;
    }
    if (best < 0) return -1;
    for (int deg = 0; deg <= best; deg++)
        if (mean[deg] <= mean[best] + se[best]) return deg;
    return best;
}

/* The buffers of a polynomial map (n spots). */
typedef struct poly_work {
    double *basis, *y, *sw, *A, *b, *zs;
    int *idx;
    unsigned char *mask;
} poly_work;

/* The surface's standard error over the field (svp_map_report.surface_se_max): the final
 * fit's R factor (A = Q R, rows weighted by 1/σ) gives bᵀ (AᵀA)⁻¹ b = |R⁻ᵀ b|², scaled by
 * √χ²_red when the scatter exceeds the spots' errors; the worst of a 33 x 33 grid over the
 * field. The R factor is refitted here: the outlier rounds use A as scratch. */
#define SURFACE_GRID 33
static svp_status surface_error(const poly_data *d, int nt, svp_map_report *rep, int q, int width,
                                int height)
{
    unsigned char *mask = malloc((size_t)d->n);
    double coef[MAX_TERMS], *spot_se = malloc((size_t)d->n * sizeof(double));
    if (!mask || !spot_se) {
        free(mask);
        free(spot_se);
        return svp_fail(SVP_ERR_NOMEM, "PSF map: out of memory");
    }
    memset(mask, 1, (size_t)d->n);
    for (int k = 0; k < d->n; k++) spot_se[k] = 1.0 / d->sw[d->idx[k]];
    rep->spot_se_median[q] = svp_median(spot_se, (size_t)d->n);
    rep->surface_se_max[q] = NAN;
    rep->surface_se_x[q] = rep->surface_se_y[q] = NAN;
    if (wls_fit(d, mask, nt, coef) == 0) {
        const int lda = d->n;
        const double scale = sqrt(fmax(1.0, rep->chi2_red[q]));
        double worst = -1, b[MAX_TERMS], z[MAX_TERMS];
        for (int gy = 0; gy < SURFACE_GRID; gy++)
            for (int gx = 0; gx < SURFACE_GRID; gx++) {
                const double x = (width - 1) * (double)gx / (SURFACE_GRID - 1);
                const double yy = (height - 1) * (double)gy / (SURFACE_GRID - 1);
                svp_psf_field_poly_basis(MAX_DEGREE, width, height, x, yy, b);
                /* Rᵀ z = b, forward substitution (R upper triangular in A's first nt rows) */
                double s2 = 0;
                for (int t = 0; t < nt; t++) {
                    double acc = b[t];
                    for (int u = 0; u < t; u++) acc -= d->A[(size_t)t * lda + u] * z[u];
                    z[t] = acc / d->A[(size_t)t * lda + t];
                    s2 += z[t] * z[t];
                }
                const double se = scale * sqrt(s2);
                if (se > worst) {
                    worst = se;
                    rep->surface_se_max[q] = se;
                    rep->surface_se_x[q] = x;
                    rep->surface_se_y[q] = yy;
                }
            }
    }
    free(mask);
    free(spot_se);
    return SVP_OK;
}

/* The polynomial surface of parameter q: its values and 1/σ per spot, the degree (given, or
 * by cross-validation) and the weighted fit, repeated while outliers are clipped; then the
 * report's degree, n_used, chi2_red, rms and surface error. */
static svp_status poly_fit_param(const svp_psf_sample *samples, int n, const svp_map_options *op,
                                 svp_map_report *rep, int q, poly_work *pw, double *coeffs,
                                 int width, int height)
{
    const svp_map_options o = *op;
    const double *basis = pw->basis;
    double *y = pw->y, *sw = pw->sw, *zs = pw->zs;
    int *idx = pw->idx;
    unsigned char *mask = pw->mask;
    for (int i = 0; i < n; i++) {
        double v[NP], e[NP];
        sample_values(&samples[i].fit, v, e);
        y[i] = v[q];
        /* a floor on σ keeps one over-precise spot from owning the surface */
        sw[i] = 1.0 / fmax(e[q], 1e-9 * fmax(fabs(v[q]), 1.0));
    }
    poly_data d = {0, basis, idx, y, sw, pw->A, pw->b};
    int deg = -1;
    for (int round = 0; round <= o.clip_iterations; round++) {
        d.n = 0;
        for (int i = 0; i < n; i++)
            if (rep->reject[(size_t)i * NP + q] == SVP_MAP_KEPT) idx[d.n++] = i;
        if (d.n < 2) {
            int counts[5] = {0};
            for (int i = 0; i < n; i++) counts[rep->reject[(size_t)i * NP + q]]++;
            return svp_fail(SVP_ERR_INVALID, "PSF map: only %d of %d spots usable for %s "
                            "(rejected: %d flagged, %d invalid, %d outside, %d outliers); at "
                            "least 2 needed", d.n, n, param_names[q], counts[1], counts[2],
                            counts[3], counts[4]);
        }
        if (o.degree >= 0) {
            deg = o.degree;
            while (deg > 0 && svp_psf_field_poly_terms(deg) > d.n) deg--;
        } else {
            deg = choose_degree(&d, &o, rep->cv_score[q], mask);
            if (deg < 0) deg = 0;
        }
        memset(mask, 1, (size_t)d.n);
        /* a degree the spots' positions cannot determine falls to the highest that they can
         * (the report's degree says so) */
        int nt;
        for (;; deg--) {
            nt = svp_psf_field_poly_terms(deg);
            if (wls_fit(&d, mask, nt, coeffs) == 0) break;
            if (deg == 0)
                return svp_fail(SVP_ERR_NUMERIC, "PSF map: the least-squares surface of degree "
                                "0 for %s failed (%d spots)", param_names[q], d.n);
        }
        if (o.clip_kappa <= 0 || round == o.clip_iterations || d.n <= nt + 1) break;
        /* outliers: z beyond κ times the robust scale (never below 1 σ) */
        for (int k = 0; k < d.n; k++) {
            int i = idx[k];
            zs[k] = fabs((y[i] - poly_eval(basis + (size_t)i * MAX_TERMS, coeffs, nt)) * sw[i]);
        }
        double *tmp = pw->A; /* free while not fitting */
        memcpy(tmp, zs, (size_t)d.n * sizeof(double));
        double scale = fmax(1.0, 1.4826 * svp_median(tmp, (size_t)d.n));
        int removed = 0;
        for (int k = 0; k < d.n; k++) {
            if (zs[k] > o.clip_kappa * scale) {
                int i = idx[k];
                rep->reject[(size_t)i * NP + q] = SVP_MAP_REJECT_OUTLIER;
                double res = y[i] - poly_eval(basis + (size_t)i * MAX_TERMS, coeffs, nt);
                rep->reject_z[(size_t)i * NP + q] = res * sw[i];
                removed++;
            }
        }
        if (!removed) break;
    }
    rep->degree[q] = deg;
    int nt = svp_psf_field_poly_terms(deg);
    double chi2 = 0, ss = 0;
    for (int k = 0; k < d.n; k++) {
        int i = idx[k];
        double res = y[i] - poly_eval(basis + (size_t)i * MAX_TERMS, coeffs, nt);
        chi2 += res * res * sw[i] * sw[i];
        ss += res * res;
    }
    rep->n_used[q] = d.n;
    rep->chi2_red[q] = d.n > nt ? chi2 / (d.n - nt) : 0.0;
    rep->rms[q] = sqrt(ss / d.n);
    return surface_error(&d, nt, rep, q, width, height);
}

/* The poly field of the fitted surfaces (every parameter at the largest degree; lower
 * degrees are a prefix, the unmapped parameters constant). */
static svp_status poly_field(const svp_map_report *rep, const svp_map_options *o, int width,
                             int height, double coeffs[NP][MAX_TERMS], svp_psf_field **field)
{
    int dmax = 0;
    for (int q = 0; q < NP; q++)
        if (rep->degree[q] > dmax) dmax = rep->degree[q];
    const int nt = svp_psf_field_poly_terms(dmax);
    double *c = calloc((size_t)NP * nt, sizeof(double));
    if (!c) return svp_fail(SVP_ERR_NOMEM, "PSF map: out of memory");
    for (int q = 0; q < NP; q++) {
        if (rep->mapped[q]) {
            /* terms are ordered by total degree: a lower degree is a prefix */
            memcpy(c + (size_t)q * nt, coeffs[q],
                   (size_t)svp_psf_field_poly_terms(rep->degree[q]) * sizeof(double));
        }
    }
    c[(size_t)SVP_FIELD_HALO * nt] = o->halo;
    if (!rep->mapped[SVP_FIELD_BETA]) c[(size_t)SVP_FIELD_BETA * nt] = unmapped_beta(rep);
    const svp_psf base = map_base(rep, o);
    svp_status st = svp_psf_field_new_poly(&base, width, height, dmax, c, field);
    free(c);
    return st != SVP_OK ? svp_fail_context(st, "PSF map") : SVP_OK;
}

svp_status svp_psf_map_poly(const svp_psf_sample *samples, int n, int width, int height,
                            const svp_map_options *options, svp_psf_field **field,
                            svp_map_report **report)
{
    if (field) *field = NULL;
    if (report) *report = NULL;
    svp_map_options o;
    if (options)
        o = *options;
    else
        svp_map_defaults(&o);
    SVP_CHECK(check_options(&o));
    svp_status st = SVP_OK;
    svp_map_report *rep = calloc(1, sizeof *rep);
    poly_work pw;
    memset(&pw, 0, sizeof pw);
    if (!rep) return svp_fail(SVP_ERR_NOMEM, "PSF map: out of memory");
    st = screen_samples(samples, n, width, height, &o, rep);
    if (st != SVP_OK) goto cleanup;

    pw.basis = malloc((size_t)n * MAX_TERMS * sizeof(double));
    pw.y = malloc((size_t)n * sizeof(double));
    pw.sw = malloc((size_t)n * sizeof(double));
    pw.A = malloc((size_t)(n > MAX_TERMS ? n : MAX_TERMS) * MAX_TERMS * sizeof(double));
    pw.b = malloc((size_t)(n > MAX_TERMS ? n : MAX_TERMS) * sizeof(double));
    pw.zs = malloc((size_t)n * sizeof(double));
    pw.idx = malloc((size_t)n * sizeof(int));
    pw.mask = malloc((size_t)n);
    if (!pw.basis || !pw.y || !pw.sw || !pw.A || !pw.b || !pw.zs || !pw.idx || !pw.mask) {
        st = svp_fail(SVP_ERR_NOMEM, "PSF map: out of memory for %d spots", n);
        goto cleanup;
    }
    for (int i = 0; i < n; i++)
        svp_psf_field_poly_basis(MAX_DEGREE, width, height, samples[i].x, samples[i].y,
                                 pw.basis + (size_t)i * MAX_TERMS);

    double coeffs[NP][MAX_TERMS];
    memset(coeffs, 0, sizeof coeffs);
    for (int q = 0; q < NP && st == SVP_OK; q++)
        if (rep->mapped[q])
            st = poly_fit_param(samples, n, &o, rep, q, &pw, coeffs[q], width, height);
    if (st == SVP_OK && field) st = poly_field(rep, &o, width, height, coeffs, field);
cleanup:
    free(pw.basis);
    free(pw.y);
    free(pw.sw);
    free(pw.A);
    free(pw.b);
    free(pw.zs);
    free(pw.idx);
    free(pw.mask);
    if (st == SVP_OK && report)
        *report = rep;
    else
        svp_map_report_free(rep);
    return st;
}

/* ---- regions ----------------------------------------------------------------------------- */

/* Regularised incomplete beta I_x(a, b) by its continued fraction (modified Lentz). */
static double incomplete_beta(double a, double b, double x)
{
    if (x <= 0) return 0.0;
    if (x >= 1) return 1.0;
    if (x > (a + 1) / (a + b + 2)) return 1.0 - incomplete_beta(b, a, 1.0 - x);
    double lnfront = a * log(x) + b * log1p(-x) - log(a) + lgamma(a + b) - lgamma(a) - lgamma(b);
    const double tiny = 1e-300;
    double f = 1.0, C = 1.0, D = 0.0;
    for (int i = 0; i <= 400; i++) {
        int m = i / 2;
        double num;
        if (i == 0)
            num = 1.0;
        else if (i % 2 == 0)
            num = m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m));
        else
            num = -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1));
        D = 1.0 + num * D;
        if (fabs(D) < tiny) D = tiny;
        D = 1.0 / D;
        C = 1.0 + num / C;
        if (fabs(C) < tiny) C = tiny;
        double cd = C * D;
        f *= cd;
        if (fabs(1.0 - cd) < 1e-15) break;
    }
    return exp(lnfront) * (f - 1.0);
}

/* Two-sided p value of Welch's t test between two groups (mean, sample std, count >= 2). */
static double welch_p(double m1, double s1, int n1, double m2, double s2, int n2)
{
    double v1 = s1 * s1 / n1, v2 = s2 * s2 / n2, v = v1 + v2;
    if (!(v > 0)) return m1 == m2 ? 1.0 : 0.0;
    double t = (m1 - m2) / sqrt(v);
    double nu = v * v / (v1 * v1 / (n1 - 1) + v2 * v2 / (n2 - 1));
    return incomplete_beta(0.5 * nu, 0.5, nu / (nu + t * t));
}

/* Statistics of the samples whose membership[i] == which, per mapped parameter (over the
 * samples kept for that parameter). */
static void group_stats(const svp_psf_sample *samples, int n, const int *member, int which,
                        const svp_map_report *rep, svp_region_stats *st)
{
    int count_any = 0;
    for (int q = 0; q < NP; q++) {
        double s = 0, s2 = 0;
        int c = 0;
        for (int i = 0; i < n; i++) {
            if (member[i] != which || rep->reject[(size_t)i * NP + q] != SVP_MAP_KEPT) continue;
            double v[NP], e[NP];
            sample_values(&samples[i].fit, v, e);
            s += v[q];
            c++;
        }
        double mean = c ? s / c : 0.0;
        for (int i = 0; i < n; i++) {
            if (member[i] != which || rep->reject[(size_t)i * NP + q] != SVP_MAP_KEPT) continue;
            double v[NP], e[NP];
            sample_values(&samples[i].fit, v, e);
            s2 += (v[q] - mean) * (v[q] - mean);
        }
        st->mean[q] = mean;
        st->std[q] = c > 1 ? sqrt(s2 / (c - 1)) : 0.0;
        st->sem[q] = c > 1 ? st->std[q] / sqrt((double)c) : 0.0;
        if (q == SVP_FIELD_FWHM) count_any = c;
    }
    st->count = count_any;
}

/* Bonferroni-corrected minimum p over the mapped parameters; -1 when untestable. */
static double pair_p(const svp_region_stats *a, const svp_region_stats *b,
                     const svp_map_report *rep)
{
    if (a->count < 2 || b->count < 2) return -1.0;
    int nq = 0;
    double pmin = 1.0;
    for (int q = 0; q < NP; q++) {
        if (!rep->mapped[q]) continue;
        nq++;
        double p = welch_p(a->mean[q], a->std[q], a->count, b->mean[q], b->std[q], b->count);
        if (p < pmin) pmin = p;
    }
    return fmin(1.0, pmin * nq);
}

/* Each spot's label (−1: none; a spot on a pixel whose label is out of range is rejected). */
static void regions_label_spots(const svp_psf_sample *samples, int n, const int *labels,
                                int width, int height, int n_labels, svp_map_report *rep,
                                int *label_of)
{
    for (int i = 0; i < n; i++) {
        label_of[i] = -1;
        int *code = rep->reject + (size_t)i * NP;
        if (code[SVP_FIELD_FWHM] == SVP_MAP_REJECT_OUTSIDE ||
            code[SVP_FIELD_FWHM] == SVP_MAP_REJECT_FLAGS)
            continue;
        long xi = lround(samples[i].x), yi = lround(samples[i].y);
        if (xi < 0 || yi < 0 || xi >= width || yi >= height) continue;
        int l = labels[(size_t)yi * width + xi];
        if (l < 0 || l >= n_labels) {
            for (int q = 0; q < NP; q++) code[q] = SVP_MAP_REJECT_OUTSIDE;
            continue;
        }
        label_of[i] = l;
    }
}

/* Outliers within each region: beyond κ robust σ of the region's median (>= 5 spots). */
static void regions_clip(const svp_psf_sample *samples, int n, int n_labels, double kappa,
                         const int *label_of, double *tmp, svp_map_report *rep)
{
    for (int l = 0; l < n_labels; l++)
        for (int q = 0; q < NP; q++) {
            if (!rep->mapped[q]) continue;
            int c = 0;
            for (int i = 0; i < n; i++)
                if (label_of[i] == l && rep->reject[(size_t)i * NP + q] == SVP_MAP_KEPT) {
                    double v[NP], e[NP];
                    sample_values(&samples[i].fit, v, e);
                    tmp[c++] = v[q];
                }
            if (c < 5) continue;
            double med = svp_median(tmp, (size_t)c);
            for (int k = 0; k < c; k++) tmp[k] = fabs(tmp[k] - med);
            double mad = 1.4826 * svp_median(tmp, (size_t)c);
            if (!(mad > 0)) continue;
            for (int i = 0; i < n; i++) {
                if (label_of[i] != l || rep->reject[(size_t)i * NP + q] != SVP_MAP_KEPT)
                    continue;
                double v[NP], e[NP];
                sample_values(&samples[i].fit, v, e);
                double z = (v[q] - med) / mad;
                if (fabs(z) > kappa) {
                    rep->reject[(size_t)i * NP + q] = SVP_MAP_REJECT_OUTLIER;
                    rep->reject_z[(size_t)i * NP + q] = z;
                }
            }
        }
}

/* Greedy merging of the regions' groups: the most similar pair first, while not
 * significantly different (p > alpha); then the groups compacted and renumbered.
 * regions[l].group holds each label's group. */
static svp_status regions_merge(const svp_psf_sample *samples, int n, int n_labels, double alpha,
                                const int *label_of, int *member, svp_map_report *rep)
{
    for (int l = 0; l < n_labels; l++) rep->regions[l].group = l;
    svp_region_stats *g = rep->groups; /* indexed by group id (= a label) during merging */
    for (int l = 0; l < n_labels; l++) g[l] = rep->regions[l];
    unsigned char *alive = malloc((size_t)n_labels);
    int *newid = malloc((size_t)n_labels * sizeof(int));
    if (!alive || !newid) {
        free(alive);
        free(newid);
        return svp_fail(SVP_ERR_NOMEM, "PSF map: out of memory");
    }
    memset(alive, 1, (size_t)n_labels);
    for (;;) {
        int ba = -1, bb = -1;
        double bp = -1;
        for (int a = 0; a < n_labels; a++) {
            if (!alive[a]) continue;
            for (int b2 = a + 1; b2 < n_labels; b2++) {
                if (!alive[b2]) continue;
                double p = pair_p(&g[a], &g[b2], rep);
                if (p > bp) {
                    bp = p;
                    ba = a;
                    bb = b2;
                }
            }
        }
        if (ba < 0 || !(bp > alpha)) break;
        for (int l = 0; l < n_labels; l++)
            if (rep->regions[l].group == bb) rep->regions[l].group = ba;
        alive[bb] = 0;
        for (int i = 0; i < n; i++)
            member[i] = label_of[i] >= 0 ? rep->regions[label_of[i]].group : -1;
        group_stats(samples, n, member, ba, rep, &g[ba]);
        g[ba].label = ba;
    }
    int k = 0;
    for (int l = 0; l < n_labels; l++) {
        newid[l] = -1;
        if (alive[l]) {
            newid[l] = k;
            g[k] = g[l];
            g[k].group = k;
            k++;
        }
    }
    for (int l = 0; l < n_labels; l++) rep->regions[l].group = newid[rep->regions[l].group];
    rep->n_groups = k;
    free(newid);
    free(alive);
    return SVP_OK;
}

/* Each label's PSF: its group's mean; the mean of all spots where a group has none. */
static svp_status regions_psfs(const svp_psf_sample *samples, int n, int n_labels,
                               const svp_map_options *o, const int *label_of, int *member,
                               const svp_map_report *rep, svp_psf *psfs)
{
    svp_region_stats all;
    for (int i = 0; i < n; i++) member[i] = label_of[i] >= 0 ? 0 : -1;
    group_stats(samples, n, member, 0, rep, &all);
    if (all.count < 1)
        return svp_fail(SVP_ERR_INVALID, "PSF map: none of the %d spots is usable (all "
                        "flagged, invalid or outside the labelled field)", n);
    const svp_psf base = map_base(rep, o);
    for (int l = 0; l < n_labels; l++) {
        const svp_region_stats *gs = &rep->groups[rep->regions[l].group];
        const svp_region_stats *src = gs->count > 0 ? gs : &all;
        double p[NP];
        for (int q = 0; q < NP; q++) p[q] = rep->mapped[q] ? src->mean[q] : 0.0;
        if (!rep->mapped[SVP_FIELD_BETA]) p[SVP_FIELD_BETA] = unmapped_beta(rep);
        p[SVP_FIELD_HALO] = o->halo;
        svp_psf_from_params(&base, p, &psfs[l]);
    }
    return SVP_OK;
}

svp_status svp_psf_map_regions(const svp_psf_sample *samples, int n, const int *labels,
                               int width, int height, int n_labels,
                               const svp_map_options *options, svp_psf_field **field,
                               svp_map_report **report)
{
    if (field) *field = NULL;
    if (report) *report = NULL;
    if (!labels) return svp_fail(SVP_ERR_INVALID, "PSF map: the label image is missing");
    if (n_labels < 1 || n_labels > 65536)
        return svp_fail(SVP_ERR_INVALID, "PSF map: n_labels %d must be in 1..65536", n_labels);
    svp_map_options o;
    if (options)
        o = *options;
    else
        svp_map_defaults(&o);
    SVP_CHECK(check_options(&o));
    svp_status st = SVP_OK;
    svp_map_report *rep = calloc(1, sizeof *rep);
    int *label_of = NULL, *member = NULL;
    double *tmp = NULL;
    svp_psf *psfs = NULL;
    if (!rep) return svp_fail(SVP_ERR_NOMEM, "PSF map: out of memory");
    st = screen_samples(samples, n, width, height, &o, rep);
    if (st != SVP_OK) goto cleanup;
    label_of = malloc((size_t)n * sizeof(int));
    member = malloc((size_t)n * sizeof(int));
    tmp = malloc((size_t)n * sizeof(double));
    rep->n_regions = n_labels;
    rep->regions = calloc((size_t)n_labels, sizeof(svp_region_stats));
    rep->groups = calloc((size_t)n_labels, sizeof(svp_region_stats));
    rep->p_value = malloc((size_t)n_labels * n_labels * sizeof(double));
    psfs = malloc((size_t)n_labels * sizeof(svp_psf));
    if (!label_of || !member || !tmp || !rep->regions || !rep->groups || !rep->p_value ||
        !psfs) {
        st = svp_fail(SVP_ERR_NOMEM, "PSF map: out of memory for %d regions", n_labels);
        goto cleanup;
    }
    regions_label_spots(samples, n, labels, width, height, n_labels, rep, label_of);
    if (o.clip_kappa > 0) regions_clip(samples, n, n_labels, o.clip_kappa, label_of, tmp, rep);
    for (int l = 0; l < n_labels; l++) {
        group_stats(samples, n, label_of, l, rep, &rep->regions[l]);
        rep->regions[l].label = l;
    }
    for (int a = 0; a < n_labels; a++)
        for (int b2 = 0; b2 < n_labels; b2++)
            rep->p_value[(size_t)a * n_labels + b2] =
                a == b2 ? 1.0 : pair_p(&rep->regions[a], &rep->regions[b2], rep);
    st = regions_merge(samples, n, n_labels, o.alpha, label_of, member, rep);
    if (st == SVP_OK) st = regions_psfs(samples, n, n_labels, &o, label_of, member, rep, psfs);
    if (st == SVP_OK && field) {
        st = svp_psf_field_new_regions(width, height, labels, n_labels, psfs, o.transition,
                                       field);
        if (st != SVP_OK) st = svp_fail_context(st, "PSF map");
    }
cleanup:
    free(label_of);
    free(member);
    free(tmp);
    free(psfs);
    if (st == SVP_OK && report)
        *report = rep;
    else
        svp_map_report_free(rep);
    return st;
}
