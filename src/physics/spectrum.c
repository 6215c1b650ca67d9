/* ODMR spectral cubes (docs/model.md §10): the two-Lorentzian model and per-pixel estimators. The
 * cube is frame-major (one svp_image per frequency) so each frame can be blurred by the blur
 * operators; an estimator streams the frames and keeps per-pixel sums, which is also what
 * makes the centroid exactly linear-fractional (eq. 3). */
#include "physics_internal.h"

#include <math.h>
#include <omp.h>
#include <stdlib.h>
#include <string.h>

svp_status svp_cube_new(int width, int height, int n_freq, const double *freq, svp_cube **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_cube_new: out is NULL");
    *out = NULL;
    if (n_freq < 1) return svp_fail(SVP_ERR_INVALID, "cube n_freq %d: must be >= 1", n_freq);
    if (!freq) return svp_fail(SVP_ERR_INVALID, "cube frequencies are NULL");
    for (int f = 0; f < n_freq; f++) {
        if (!isfinite(freq[f]))
            return svp_fail(SVP_ERR_INVALID, "cube frequency %d is not finite", f);
        if (f > 0 && !(freq[f] > freq[f - 1]))
            return svp_fail(SVP_ERR_INVALID,
                            "cube frequencies must increase strictly: freq[%d] = %.9g Hz after "
                            "%.9g Hz",
                            f, freq[f], freq[f - 1]);
    }
    svp_status st = SVP_OK;
    svp_cube *c = calloc(1, sizeof *c);
    if (!c) return svp_fail(SVP_ERR_NOMEM, "out of memory for a cube");
    c->width = width;
    c->height = height;
    c->n_freq = n_freq;
    c->freq = malloc((size_t)n_freq * sizeof(double));
    c->frame = calloc((size_t)n_freq, sizeof(svp_image *));
    if (!c->freq || !c->frame) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory for a cube of %d frames", n_freq);
        goto cleanup;
    }
    memcpy(c->freq, freq, (size_t)n_freq * sizeof(double));
    for (int f = 0; f < n_freq && st == SVP_OK; f++) st = svp_image_new(width, height, &c->frame[f]);
cleanup:
    if (st != SVP_OK) {
        svp_cube_free(c);
        return st;
    }
    *out = c;
    return SVP_OK;
}

void svp_cube_free(svp_cube *cube)
{
    if (!cube) return;
    if (cube->frame)
        for (int f = 0; f < cube->n_freq; f++) svp_image_free(cube->frame[f]);
    free(cube->frame);
    free(cube->freq);
    free(cube);
}

void svp_odmr_defaults(svp_odmr *odmr)
{
    odmr->zero_field_hz = 2.870e9;
    odmr->gamma_hz_per_t = 28.033e9;
    odmr->linewidth_hz = 1e6;
    odmr->contrast = 0.02;
}

static svp_status odmr_validate(const svp_odmr *m)
{
    if (!m) return svp_fail(SVP_ERR_INVALID, "ODMR model is NULL");
    if (!(m->zero_field_hz > 0) || !isfinite(m->zero_field_hz))
        return svp_fail(SVP_ERR_INVALID, "ODMR zero_field_hz %g: must be finite > 0",
                        m->zero_field_hz);
    if (!(m->gamma_hz_per_t > 0) || !isfinite(m->gamma_hz_per_t))
        return svp_fail(SVP_ERR_INVALID, "ODMR gamma_hz_per_t %g: must be finite > 0",
                        m->gamma_hz_per_t);
    if (!(m->linewidth_hz > 0) || !isfinite(m->linewidth_hz))
        return svp_fail(SVP_ERR_INVALID, "ODMR linewidth_hz %g: must be finite > 0",
                        m->linewidth_hz);
    if (!(m->contrast >= 0 && m->contrast <= 0.5))
        return svp_fail(SVP_ERR_INVALID, "ODMR contrast %g: must be in [0, 0.5]", m->contrast);
    return SVP_OK;
}

svp_status svp_odmr_sweep(const svp_odmr *odmr, double field_max_t, double half_span_linewidths,
                          int n_freq, double *freq)
{
    SVP_CHECK(odmr_validate(odmr));
    if (!freq) return svp_fail(SVP_ERR_INVALID, "sweep: freq is NULL");
    if (n_freq < 2) return svp_fail(SVP_ERR_INVALID, "sweep n_freq %d: must be >= 2", n_freq);
    if (!isfinite(field_max_t) || !(half_span_linewidths >= 0) || !isfinite(half_span_linewidths))
        return svp_fail(SVP_ERR_INVALID, "sweep: field_max_t %g or half_span_linewidths %g "
                        "invalid", field_max_t, half_span_linewidths);
    double half = odmr->gamma_hz_per_t * fabs(field_max_t) + half_span_linewidths *
                                                                 odmr->linewidth_hz;
    if (!(half > 0))
        return svp_fail(SVP_ERR_INVALID, "sweep: zero span (field_max_t and "
                        "half_span_linewidths both 0)");
    for (int f = 0; f < n_freq; f++)
        freq[f] = odmr->zero_field_hz - half + 2 * half * f / (double)(n_freq - 1);
    return SVP_OK;
}

static svp_status cube_check(const svp_cube *cube)
{
    if (!cube || !cube->frame || !cube->freq)
        return svp_fail(SVP_ERR_INVALID, "cube is NULL or incomplete");
    return SVP_OK;
}

static svp_status map_check(const svp_cube *cube, const svp_image *map, const char *name)
{
    if (!map) return svp_fail(SVP_ERR_INVALID, "%s map is NULL", name);
    if (map->width != cube->width || map->height != cube->height)
        return svp_fail(SVP_ERR_SIZE, "%s is %d x %d but the cube's frames are %d x %d", name,
                        map->width, map->height, cube->width, cube->height);
    return SVP_OK;
}

svp_status svp_odmr_simulate(const svp_odmr *odmr, const svp_image *pl,
                             const svp_image *field_nv, const svp_image *contrast,
                             const double *drift_px, svp_cube *cube)
{
    SVP_CHECK(odmr_validate(odmr));
    SVP_CHECK(cube_check(cube));
    SVP_CHECK(map_check(cube, pl, "pl"));
    SVP_CHECK(map_check(cube, field_nv, "field_nv"));
    if (contrast) SVP_CHECK(map_check(cube, contrast, "contrast"));
    /* Drift hook: a lateral shift (dx_f, dy_f) per frame would sample pl, field_nv and contrast
     * at (x − dx_f, y − dy_f) here. */
    if (drift_px)
        return svp_fail(SVP_ERR_UNSUPPORTED, "ODMR simulation: frame drift is not implemented "
                        "yet (drift_px must be NULL)");
    const size_t n = (size_t)cube->width * cube->height;
    for (size_t p = 0; p < n; p++) {
        if (!(pl->data[p] >= 0) || !isfinite(pl->data[p]))
            return svp_fail(SVP_ERR_INVALID, "pl pixel (%zu, %zu) = %g: must be finite >= 0",
                            p % cube->width, p / cube->width, pl->data[p]);
        if (!isfinite(field_nv->data[p]))
            return svp_fail(SVP_ERR_INVALID, "field_nv pixel (%zu, %zu) is not finite",
                            p % cube->width, p / cube->width);
        if (contrast && !(contrast->data[p] >= 0 && contrast->data[p] <= 0.5))
            return svp_fail(SVP_ERR_INVALID, "contrast pixel (%zu, %zu) = %g: must be in "
                            "[0, 0.5]", p % cube->width, p / cube->width, contrast->data[p]);
    }
    const double D = odmr->zero_field_hz, g = odmr->gamma_hz_per_t;
    const double hw2 = 0.25 * odmr->linewidth_hz * odmr->linewidth_hz, c0 = odmr->contrast;
    const double *restrict ppl = pl->data, *restrict pb = field_nv->data;
    const double *restrict pc = contrast ? contrast->data : NULL;
    for (int f = 0; f < cube->n_freq; f++) {
        const double w = cube->freq[f];
        double *restrict out = cube->frame[f]->data;
#pragma omp parallel for schedule(static) if (n > 16384)
        for (size_t p = 0; p < n; p++) {
            double split = g * pb[p];
            double up = w - (D + split), down = w - (D - split);
            double dips = hw2 / (up * up + hw2) + hw2 / (down * down + hw2);
            out[p] = ppl[p] * (1 - (pc ? pc[p] : c0) * dips);
        }
    }
    return SVP_OK;
}

svp_status svp_odmr_centroid(const svp_odmr *odmr, const svp_cube *cube,
                             const svp_image *baseline, double window_lo_hz,
                             double window_hi_hz, svp_image *field, svp_image *weight)
{
    SVP_CHECK(odmr_validate(odmr));
    SVP_CHECK(cube_check(cube));
    SVP_CHECK(map_check(cube, baseline, "baseline"));
    SVP_CHECK(map_check(cube, field, "field"));
    if (weight) SVP_CHECK(map_check(cube, weight, "weight"));
    if (!isfinite(window_lo_hz) || !isfinite(window_hi_hz) || window_hi_hz < window_lo_hz)
        return svp_fail(SVP_ERR_INVALID, "centroid window [%g, %g] Hz is not an interval",
                        window_lo_hz, window_hi_hz);
    const int all = window_lo_hz == 0 && window_hi_hz == 0;
    const int nf = cube->n_freq;
    const size_t n = (size_t)cube->width * cube->height;
    double *num = field->data;
    double *den = weight ? weight->data : svp_alloc(n * sizeof(double));
    if (!den) return svp_fail(SVP_ERR_NOMEM, "out of memory for the centroid weights");
    memset(num, 0, n * sizeof(double));
    memset(den, 0, n * sizeof(double));
    const double D = odmr->zero_field_hz;
    const double *restrict b = baseline->data;
    int used = 0;
    for (int f = 0; f < nf; f++) {
        const double w = cube->freq[f];
        if (!all && (w < window_lo_hz || w > window_hi_hz)) continue;
        used++;
        /* trapezoid weight of the frequency grid */
        double q = nf == 1 ? 1.0
                           : 0.5 * (cube->freq[f < nf - 1 ? f + 1 : f] -
                                    cube->freq[f > 0 ? f - 1 : f]);
        const double qs = q * fabs(w - D);
        const double *restrict in = cube->frame[f]->data;
        double *restrict pn = num, *restrict pd = den;
#pragma omp parallel for schedule(static) if (n > 16384)
        for (size_t p = 0; p < n; p++) {
            double depth = b[p] - in[p];
            pn[p] += qs * depth;
            pd[p] += q * depth;
        }
    }
    svp_status st = SVP_OK;
    if (!used) {
        st = svp_fail(SVP_ERR_INVALID, "centroid window [%.9g, %.9g] Hz holds no frame",
                      window_lo_hz, window_hi_hz);
        memset(num, 0, n * sizeof(double));
    } else {
        const double g = odmr->gamma_hz_per_t;
#pragma omp parallel for schedule(static) if (n > 16384)
        for (size_t p = 0; p < n; p++) num[p] = den[p] > 0 ? num[p] / (g * den[p]) : 0.0;
    }
    if (!weight) svp_free(den);
    return st;
}

/* ---- per-pixel Lorentzian fit -------------------------------------------------------------- */

void svp_odmr_fit_defaults(svp_odmr_fit_options *options)
{
    memset(options, 0, sizeof *options);
    svp_lm_defaults(&options->lm);
    options->baseline_frames = 3;
    options->lines = SVP_ODMR_LINES_PAIR;
    options->line_sign = 1;
}

typedef struct odmr_pixel {
    const double *freq;
    double D, gamma;
} odmr_pixel;

/* θ = (b, C, B, Γ): f = b [1 − C (L(u₊) + L(u₋))], u± = ω − D ∓ γB, L = g² / (u² + g²), g = Γ/2.
 * One frequency: returns f at u0 = ω − D and stores in d its derivatives with respect to
 * (b, C, split = γB, g), which odmr_model and odmr_fast_eval scale to their parameters. */
static inline double odmr_point(double u0, double b, double C, double split, double g, double d[4])
{
    const double g2 = g * g;
    const double up = u0 - split, um = u0 + split;
    const double ip = 1 / (up * up + g2), im = 1 / (um * um + g2);
    const double lp = g2 * ip, lm = g2 * im, S = lp + lm;
    /* ∂L/∂u = −2 u g² / (u² + g²)², ∂L/∂g = 2 g u² / (u² + g²)² */
    const double dlp = -2 * up * lp * ip, dlm = -2 * um * lm * im;
    const double glp = 2 * g * up * up * ip * ip, glm = 2 * g * um * um * im * im;
    d[0] = 1 - C * S;
    d[1] = -b * S;
    d[2] = b * C * (dlp - dlm);
    d[3] = -b * C * (glp + glm);
    return b * d[0];
}

static int odmr_model(void *user, const double *th, int n_params, int n_points, double *model,
                      double *jac)
{
    (void)n_params;
    const odmr_pixel *px = user;
    const double b = th[0], C = th[1], split = px->gamma * th[2], g = 0.5 * th[3];
    if (!(g > 0)) return 1;
    for (int i = 0; i < n_points; i++) {
        double d[4];
        model[i] = odmr_point(px->freq[i] - px->D, b, C, split, g, d);
        if (jac) {
            double *row = jac + (size_t)i * 4;
            row[0] = d[0];
            row[1] = d[1];
            row[2] = px->gamma * d[2];
            row[3] = 0.5 * d[3];
        }
    }
    return 0;
}

/* A dedicated Levenberg–Marquardt for the 4-parameter model above (the generic svp_lm_solve
 * pays per pixel for what a 4 x 4 problem does not need: QR factorisations through LAPACKE,
 * a covariance, function pointers). Internal parameters are scaled to order one:
 * q = (b / b0, C, γB / Γ0, Γ / Γ0) with b0 the starting baseline and Γ0 the nominal linewidth.
 * Each trial point is evaluated once, with its Jacobian, JᵀJ and Jᵀr accumulated in the same
 * pass, so an accepted step needs no second evaluation. The damped normal equations
 * (A + λ diag A) δ = Jᵀr are solved in Jacobi-scaled form by a 4 x 4 Cholesky. Steps keep
 * C in [0, 1]; a step to Γ <= 0 is rejected (λ grows). Stops on an accepted step when
 * max_j |δ_j| / (|q_j| + 1e-3) <= xtol, or when the actual and predicted relative decreases of
 * χ² are both <= ftol, or χ² reaches round-off; returns 0 then, 1 when it ran out of iterations
 * or damping (the caller falls back to svp_lm_solve). */
typedef struct odmr_fast {
    const double *freq, *y;
    int n;
    double D, gamma, b0, g0;
} odmr_fast;

/* index of (i, j) in the 10-value upper triangle of a symmetric 4 x 4 */
static const int sym4[4][4] = {{0, 1, 2, 3}, {1, 4, 5, 6}, {2, 5, 7, 8}, {3, 6, 8, 9}};

/* χ², A = JᵀJ (upper triangle, 10 values), v = Jᵀr at q; 1 when q is outside the model */
static int odmr_fast_eval(const odmr_fast *o, const double q[4], double *chi2, double A[10],
                          double v[4])
{
    const double b = q[0] * o->b0, C = q[1], split = q[2] * o->g0, g = 0.5 * q[3] * o->g0;
    if (!(g > 0)) return 1;
    /* derivatives with respect to the scaled parameters: ∂/∂q0 = b0 ∂/∂b, ∂/∂q2 = Γ0 ∂/∂split,
     * ∂/∂q3 = (Γ0 / 2) ∂/∂g */
    const double s0 = o->b0, s2 = o->g0, s3 = 0.5 * o->g0;
    double c2 = 0, a00 = 0, a01 = 0, a02 = 0, a03 = 0, a11 = 0, a12 = 0, a13 = 0, a22 = 0, a23 = 0,
           a33 = 0, v0 = 0, v1 = 0, v2 = 0, v3 = 0;
    for (int i = 0; i < o->n; i++) {
        double d[4];
        const double r = o->y[i] - odmr_point(o->freq[i] - o->D, b, C, split, g, d);
        const double j0 = s0 * d[0], j1 = d[1], j2 = s2 * d[2], j3 = s3 * d[3];
        c2 += r * r;
        a00 += j0 * j0;
        a01 += j0 * j1;
        a02 += j0 * j2;
        a03 += j0 * j3;
        a11 += j1 * j1;
        a12 += j1 * j2;
        a13 += j1 * j3;
        a22 += j2 * j2;
        a23 += j2 * j3;
        a33 += j3 * j3;
        v0 += j0 * r;
        v1 += j1 * r;
        v2 += j2 * r;
        v3 += j3 * r;
    }
    *chi2 = c2;
    A[0] = a00, A[1] = a01, A[2] = a02, A[3] = a03, A[4] = a11, A[5] = a12, A[6] = a13, A[7] = a22,
    A[8] = a23, A[9] = a33;
    v[0] = v0, v[1] = v1, v[2] = v2, v[3] = v3;
    return !isfinite(c2);
}

/* Solves (A + λ diag A) δ = v in Jacobi-scaled form; 1 when not positive definite */
static int odmr_fast_solve(const double A[10], const double v[4], double lambda, double d[4])
{
    double sc[4], M[4][4], z[4];
    for (int i = 0; i < 4; i++) {
        double a = A[sym4[i][i]];
        sc[i] = a > 0 ? 1 / sqrt(a) : 0;
    }
    for (int i = 0; i < 4; i++)
        for (int j = 0; j < 4; j++) M[i][j] = A[sym4[i][j]] * sc[i] * sc[j];
    for (int i = 0; i < 4; i++) M[i][i] = (sc[i] > 0 ? 1 : 0) * (1 + lambda) + (sc[i] > 0 ? 0 : 1);
    /* Cholesky M = L Lᵀ in place (lower) */
    for (int j = 0; j < 4; j++) {
        double dsum = M[j][j];
        for (int k = 0; k < j; k++) dsum -= M[j][k] * M[j][k];
        if (!(dsum > 1e-300)) return 1;
        M[j][j] = sqrt(dsum);
        for (int i = j + 1; i < 4; i++) {
            double t = M[i][j];
            for (int k = 0; k < j; k++) t -= M[i][k] * M[j][k];
            M[i][j] = t / M[j][j];
        }
    }
    for (int i = 0; i < 4; i++) {
        double t = v[i] * sc[i];
        for (int k = 0; k < i; k++) t -= M[i][k] * z[k];
        z[i] = t / M[i][i];
    }
    for (int i = 3; i >= 0; i--) {
        double t = z[i];
        for (int k = i + 1; k < 4; k++) t -= M[k][i] * z[k];
        z[i] = t / M[i][i];
    }
    for (int i = 0; i < 4; i++) d[i] = z[i] * sc[i];
    return 0;
}

/* th (b, C, B, Γ) in/out; 0 on convergence. A_out (JᵀJ in the scaled parameters, 10 values)
 * and chi2_out: at the final point. */
static int odmr_fast_fit(const odmr_fast *o, const svp_lm_options *opt, double th[4],
                         double A_out[10], double *chi2_out)
{
    double q[4] = {th[0] / o->b0, th[1], o->gamma * th[2] / o->g0, th[3] / o->g0};
    double chi2, A[10], v[4];
    if (odmr_fast_eval(o, q, &chi2, A, v)) return 1;
    double sy = 0;
    for (int i = 0; i < o->n; i++) sy += o->y[i] * o->y[i];
    double lambda = opt->lambda_init > 0 ? opt->lambda_init : 1e-3;
    int accepted = 0, converged = 0;
    while (accepted < opt->max_iterations && !converged) {
        if (chi2 <= 1e-28 * sy) {
            converged = 1;
            break;
        }
        double d[4], qt[4], chi2t, At[10], vt[4];
        if (odmr_fast_solve(A, v, lambda, d)) {
            lambda *= 10;
            if (lambda > 1e16) break;
            continue;
        }
        for (int j = 0; j < 4; j++) qt[j] = q[j] + d[j];
        qt[1] = fmin(fmax(qt[1], 0), 1);
        if (odmr_fast_eval(o, qt, &chi2t, At, vt) || !(chi2t < chi2)) {
            lambda *= 10;
            if (lambda > 1e16) {
                /* no decrease at any damping: the minimum to round-off when the gradient
                 * vanishes there (as svp_lm_solve's gtol) */
                double gmax = 0;
                for (int j = 0; j < 4; j++)
                    if (A[sym4[j][j]] > 0 && chi2 > 0)
                        gmax = fmax(gmax, fabs(v[j]) / sqrt(A[sym4[j][j]] * chi2));
                converged = gmax <= opt->gtol;
                break;
            }
            continue;
        }
        /* predicted decrease of the linear model: 2 δᵀv − δᵀAδ (actual δ after clamping) */
        double dd[4], Ad[4];
        for (int j = 0; j < 4; j++) dd[j] = qt[j] - q[j];
        double pred = 0, step = 0;
        for (int i = 0; i < 4; i++) {
            Ad[i] = 0;
            for (int j = 0; j < 4; j++) Ad[i] += A[sym4[i][j]] * dd[j];
            pred += 2 * dd[i] * v[i] - dd[i] * Ad[i];
            step = fmax(step, fabs(dd[i]) / (fabs(qt[i]) + 1e-3));
        }
        double actual = (chi2 - chi2t) / chi2;
        pred /= chi2;
        memcpy(q, qt, sizeof q);
        memcpy(A, At, sizeof A);
        memcpy(v, vt, sizeof v);
        chi2 = chi2t;
        accepted++;
        lambda = fmax(lambda * 0.1, 1e-12);
        if (step <= opt->xtol || (actual <= opt->ftol && fabs(pred) <= opt->ftol)) converged = 1;
    }
    th[0] = q[0] * o->b0;
    th[1] = q[1];
    th[2] = q[2] * o->g0 / o->gamma;
    th[3] = q[3] * o->g0;
    memcpy(A_out, A, sizeof A);
    *chi2_out = chi2;
    return !converged;
}


/* ---- free lines: one dip, or two dips at independent frequencies ----------------------------
 * Parameters scaled to order one, frequencies measured from D in units of the nominal Γ0:
 *   ONE: q = (b / b0, C, u₀, w),      TWO: q = (b / b0, C, u₋, u₊, w),
 * with u = (f − D) / Γ0 and w = Γ / Γ0, at the points x_f = (ω_f − D) / Γ0. The same
 * Levenberg–Marquardt as odmr_fast_fit on an n x n (n = 4 or 5) system. */
#define GEN_MAX 5

typedef struct odmr_gen {
    const double *x, *y; /* n points */
    int n, np, two;      /* np = 4 (ONE) or 5 (TWO) */
    double b0;
} odmr_gen;

/* the model at x and its derivatives with respect to q */
static inline double gen_point(const odmr_gen *o, const double *q, double x, double *j)
{
    const double b = q[0] * o->b0, C = q[1], h = 0.5 * q[o->np - 1], h2 = h * h;
    const int nl = o->two ? 2 : 1;
    double S = 0, dw = 0;
    for (int l = 0; l < nl; l++) {
        const double u = x - q[2 + l], ip = 1 / (u * u + h2), L = h2 * ip;
        S += L;
        /* ∂L/∂u₀ = 2 u h² ip², ∂L/∂w = (1/2) ∂L/∂h = h u² ip² */
        j[2 + l] = -b * C * (2 * u * L * ip);
        dw += h * u * u * ip * ip;
    }
    j[0] = o->b0 * (1 - C * S);
    j[1] = -b * S;
    j[o->np - 1] = -b * C * dw;
    return b * (1 - C * S);
}

static int gen_eval(const odmr_gen *o, const double *q, double *chi2, double A[GEN_MAX][GEN_MAX],
                    double *v)
{
    const int np = o->np;
    if (!(q[np - 1] > 0)) return 1;
    double c2 = 0;
    memset(A, 0, GEN_MAX * sizeof A[0]);
    for (int a = 0; a < np; a++) v[a] = 0;
    for (int i = 0; i < o->n; i++) {
        double j[GEN_MAX];
        const double r = o->y[i] - gen_point(o, q, o->x[i], j);
        c2 += r * r;
        for (int a = 0; a < np; a++) {
            v[a] += j[a] * r;
            for (int b = a; b < np; b++) A[a][b] += j[a] * j[b];
        }
    }
    for (int a = 0; a < np; a++)
        for (int b = 0; b < a; b++) A[a][b] = A[b][a];
    *chi2 = c2;
    return !isfinite(c2);
}

/* Cholesky of the n x n symmetric M in place (lower); 1 when not positive definite */
static int chol(int n, double M[GEN_MAX][GEN_MAX])
{
    for (int j = 0; j < n; j++) {
        double dsum = M[j][j];
        for (int k = 0; k < j; k++) dsum -= M[j][k] * M[j][k];
        if (!(dsum > 1e-300)) return 1;
        M[j][j] = sqrt(dsum);
        for (int i = j + 1; i < n; i++) {
            double t = M[i][j];
            for (int k = 0; k < j; k++) t -= M[i][k] * M[j][k];
            M[i][j] = t / M[j][j];
        }
    }
    return 0;
}

static void chol_solve(int n, double L[GEN_MAX][GEN_MAX], const double *b, double *x)
{
    double z[GEN_MAX];
    for (int i = 0; i < n; i++) {
        double t = b[i];
        for (int k = 0; k < i; k++) t -= L[i][k] * z[k];
        z[i] = t / L[i][i];
    }
    for (int i = n - 1; i >= 0; i--) {
        double t = z[i];
        for (int k = i + 1; k < n; k++) t -= L[k][i] * x[k];
        x[i] = t / L[i][i];
    }
}

/* (A + λ diag A) d = v in Jacobi-scaled form; 1 when not positive definite */
static int gen_solve(int n, double A[GEN_MAX][GEN_MAX], const double *v, double lambda, double *d)
{
    double sc[GEN_MAX], M[GEN_MAX][GEN_MAX], rhs[GEN_MAX], z[GEN_MAX];
    for (int i = 0; i < n; i++) sc[i] = A[i][i] > 0 ? 1 / sqrt(A[i][i]) : 0;
    for (int i = 0; i < n; i++)
        for (int j = 0; j < n; j++) M[i][j] = A[i][j] * sc[i] * sc[j];
    for (int i = 0; i < n; i++) M[i][i] = sc[i] > 0 ? 1 + lambda : 1;
    if (chol(n, M)) return 1;
    for (int i = 0; i < n; i++) rhs[i] = v[i] * sc[i];
    chol_solve(n, M, rhs, z);
    for (int i = 0; i < n; i++) d[i] = z[i] * sc[i];
    return 0;
}

/* q in/out; 0 on convergence; A and chi2 at the final point */
static int gen_fit(const odmr_gen *o, const svp_lm_options *opt, double *q,
                   double A[GEN_MAX][GEN_MAX], double *chi2_out)
{
    const int np = o->np;
    double chi2, v[GEN_MAX];
    if (gen_eval(o, q, &chi2, A, v)) return 1;
    double sy = 0;
    for (int i = 0; i < o->n; i++) sy += o->y[i] * o->y[i];
    double lambda = opt->lambda_init > 0 ? opt->lambda_init : 1e-3;
    int accepted = 0, converged = 0;
    while (accepted < opt->max_iterations && !converged) {
        if (chi2 <= 1e-28 * sy) {
            converged = 1;
            break;
        }
        double d[GEN_MAX], qt[GEN_MAX], chi2t, At[GEN_MAX][GEN_MAX], vt[GEN_MAX];
        if (gen_solve(np, A, v, lambda, d)) {
            lambda *= 10;
            if (lambda > 1e16) break;
            continue;
        }
        for (int j = 0; j < np; j++) qt[j] = q[j] + d[j];
        qt[1] = fmin(fmax(qt[1], 0), 1);
        if (gen_eval(o, qt, &chi2t, At, vt) || !(chi2t < chi2)) {
            lambda *= 10;
            if (lambda > 1e16) {
                double gmax = 0;
                for (int j = 0; j < np; j++)
                    if (A[j][j] > 0 && chi2 > 0) gmax = fmax(gmax, fabs(v[j]) / sqrt(A[j][j] * chi2));
                converged = gmax <= opt->gtol;
                break;
            }
            continue;
        }
        double pred = 0, step = 0;
        for (int i = 0; i < np; i++) {
            double di = qt[i] - q[i], Ad = 0;
            for (int j = 0; j < np; j++) Ad += A[i][j] * (qt[j] - q[j]);
            pred += 2 * di * v[i] - di * Ad;
            step = fmax(step, fabs(di) / (fabs(qt[i]) + 1e-3));
        }
        const double actual = (chi2 - chi2t) / chi2;
        pred /= chi2;
        memcpy(q, qt, (size_t)np * sizeof(double));
        memcpy(A, At, sizeof At);
        memcpy(v, vt, (size_t)np * sizeof(double));
        chi2 = chi2t;
        accepted++;
        lambda = fmax(lambda * 0.1, 1e-12);
        if (step <= opt->xtol || (actual <= opt->ftol && fabs(pred) <= opt->ftol)) converged = 1;
    }
    *chi2_out = chi2;
    return !converged;
}

/* svp_lm_solve's model over the same q (the fallback) */
static int gen_model(void *user, const double *q, int n_params, int n_points, double *model,
                     double *jac)
{
    const odmr_gen *o = user;
    if (!(q[n_params - 1] > 0)) return 1;
    for (int i = 0; i < n_points; i++) {
        double j[GEN_MAX];
        model[i] = gen_point(o, q, o->x[i], j);
        if (jac) memcpy(jac + (size_t)i * n_params, j, (size_t)n_params * sizeof(double));
    }
    return 0;
}

/* Covariance of q from A = JᵀJ at the solution: A⁻¹ χ² / dof (INFINITY diagonal when singular) */
static void covariance_from(int n, double A[GEN_MAX][GEN_MAX], double chi2, int dof,
                            double cov[GEN_MAX][GEN_MAX])
{
    double L[GEN_MAX][GEN_MAX], sc[GEN_MAX];
    for (int i = 0; i < n; i++) sc[i] = A[i][i] > 0 ? 1 / sqrt(A[i][i]) : 0;
    for (int i = 0; i < n; i++)
        for (int j = 0; j < n; j++) L[i][j] = A[i][j] * sc[i] * sc[j];
    int singular = 0;
    for (int i = 0; i < n; i++) singular |= !(sc[i] > 0);
    if (!singular) singular = chol(n, L);
    const double s2 = dof > 0 ? chi2 / dof : 0;
    for (int c = 0; c < n; c++) {
        double e[GEN_MAX] = {0}, x[GEN_MAX];
        e[c] = 1;
        if (!singular) chol_solve(n, L, e, x);
        for (int r = 0; r < n; r++)
            cov[r][c] = singular ? (r == c ? INFINITY : 0) : x[r] * sc[r] * sc[c] * s2;
    }
}

/* The deepest point of y smoothed over [f − half_box, f + half_box], excluding frames within
 * `exclude` of frame `avoid` (avoid < 0: none); -1 when none is left. *value: its smoothed value */
static int deepest(const double *y, int nf, int half_box, int avoid, int exclude, double *value)
{
    int best = -1;
    double best_v = INFINITY;
    for (int f = 0; f < nf; f++) {
        if (avoid >= 0 && abs(f - avoid) < exclude) continue;
        double v = 0;
        int cnt = 0;
        for (int g = f - half_box; g <= f + half_box; g++) {
            if (g < 0 || g >= nf) continue;
            v += y[g];
            cnt++;
        }
        v /= cnt;
        if (v < best_v) {
            best_v = v;
            best = f;
        }
    }
    *value = best_v;
    return best;
}

static svp_status maps_check(const svp_cube *cube, const svp_odmr_maps *m, svp_odmr_lines lines)
{
    if (!m) return svp_fail(SVP_ERR_INVALID, "ODMR fit: maps is NULL");
    SVP_CHECK(map_check(cube, m->field, "field"));
    const svp_image *opt[] = {m->field_sigma,     m->field_lower,    m->field_lower_sigma,
                              m->field_upper,     m->field_upper_sigma, m->baseline,
                              m->baseline_sigma,  m->contrast,       m->contrast_sigma,
                              m->linewidth,       m->linewidth_sigma, m->quality,
                              m->converged};
    static const char *const names[] = {
        "field_sigma", "field_lower",     "field_lower_sigma", "field_upper",     "field_upper_sigma",
        "baseline",    "baseline_sigma",  "contrast",          "contrast_sigma",  "linewidth",
        "linewidth_sigma", "quality",     "converged"};
    for (size_t i = 0; i < sizeof opt / sizeof opt[0]; i++)
        if (opt[i]) SVP_CHECK(map_check(cube, opt[i], names[i]));
    if (lines != SVP_ODMR_LINES_TWO &&
        (m->field_lower || m->field_lower_sigma || m->field_upper || m->field_upper_sigma))
        return svp_fail(SVP_ERR_INVALID, "ODMR fit: field_lower / field_upper are given by two "
                                         "free resonances only (SVP_ODMR_LINES_TWO)");
    return SVP_OK;
}

static void put(svp_image *img, size_t p, double v)
{
    if (img) img->data[p] = v;
}

/* The options of svp_odmr_fit_maps and its maps against the cube. */
static svp_status fit_check(const svp_cube *cube, const svp_odmr_fit_options *options,
                            const svp_odmr_maps *maps)
{
    const svp_odmr_lines lines = options->lines;
    if (lines != SVP_ODMR_LINES_PAIR && lines != SVP_ODMR_LINES_TWO && lines != SVP_ODMR_LINES_ONE)
        return svp_fail(SVP_ERR_INVALID, "ODMR fit: lines %d is not PAIR (0), TWO (1) or ONE (2)",
                        (int)lines);
    if (lines == SVP_ODMR_LINES_ONE && options->line_sign != 1 && options->line_sign != -1)
        return svp_fail(SVP_ERR_INVALID, "ODMR fit: line_sign %d must be +1 or -1",
                        options->line_sign);
    SVP_CHECK(maps_check(cube, maps, lines));
    const int nf = cube->n_freq, np = lines == SVP_ODMR_LINES_TWO ? 5 : 4;
    if (nf < 5 || nf <= np)
        return svp_fail(SVP_ERR_INVALID, "Lorentzian fit: %d frequencies, >= %d needed", nf,
                        np + 1 > 5 ? np + 1 : 5);
    if (options->baseline_frames < 1 || 2 * options->baseline_frames > nf)
        return svp_fail(SVP_ERR_INVALID, "Lorentzian fit: baseline_frames %d must be in [1, %d]",
                        options->baseline_frames, nf / 2);
    if (options->lm.max_iterations < 1)
        return svp_fail(SVP_ERR_INVALID, "Lorentzian fit: lm.max_iterations %d must be >= 1",
                        options->lm.max_iterations);
    return SVP_OK;
}

/* What every pixel's fit shares (svp_odmr_fit_maps). */
typedef struct fit_shared {
    const svp_cube *cube;
    const svp_odmr_fit_options *options;
    const svp_odmr_maps *maps;
    svp_odmr_lines lines;
    int nf, np, nb;        /* frequencies, parameters, baseline frames at each end */
    double D, gamma, G0;   /* zero-field splitting, gyromagnetic ratio, nominal linewidth */
    double sweep_lo, sweep_hi; /* the swept range (fit_in_sweep) */
    const double *q, *xs;  /* trapezoid weights; frequencies (ω − D) / Γ0 */
    int half_box, exclude; /* the starting point's smoothing and second-dip exclusion */
} fit_shared;

/* One thread's solvers: the generic LM (fallback) for the pair model and for ONE / TWO. */
typedef struct fit_thread {
    svp_lm_workspace *ws;
    odmr_pixel px;
    svp_lm_problem prob, gprob;
    odmr_gen go;
    double *sub; /* 4 nf: a pixel's finite samples, their frequencies, q and xs (fit_pixel) */
} fit_thread;

/* One pixel's start values from its spectrum y: baseline b0 (mean of the end frames), dip area
 * den (trapezoid), mean, the deepest smoothed frame (best, its smoothed value v_best). */
typedef struct fit_start {
    double b0, den, mean, v_best;
    int best;
} fit_start;

/* PAIR: θ = (b, C, B, Γ) by odmr_fast_fit, or svp_lm_solve when it does not converge.
 * Returns 1 when the fit failed (*st its status). */
static int fit_pair(const fit_shared *c, fit_thread *t, const double *y, const fit_start *s,
                    double th[GEN_MAX], double cov[GEN_MAX][GEN_MAX], double *chi2,
                    svp_status *st)
{
    const int nf = c->nf;
    const double b0 = s->b0, den = s->den, D = c->D, gamma = c->gamma, G0 = c->G0;
    const double bs = b0 > 0 ? b0 : 1;
    double A[GEN_MAX][GEN_MAX];
    th[0] = b0;
    th[2] = fabs(c->cube->freq[s->best] - D) / gamma;
    th[3] = G0;
    /* at B = 0 exactly the model is flat in B (the dips are symmetric) */
    th[2] = fmax(th[2], 0.25 * G0 / gamma);
    th[1] = (den > 0 && b0 > 0) ? fmin(0.9, den / (b0 * M_PI * th[3])) : 0.01;
    if (!(th[1] > 1e-6)) th[1] = 1e-6;
    double th0[4] = {th[0], th[1], th[2], th[3]}, Ap[10];
    const odmr_fast fo = {.freq = c->cube->freq, .y = y, .n = nf, .D = D, .gamma = gamma,
                          .b0 = bs, .g0 = G0};
    if (b0 > 0 && !odmr_fast_fit(&fo, &c->options->lm, th, Ap, chi2)) {
        for (int a = 0; a < 4; a++)
            for (int k = 0; k < 4; k++) A[a][k] = Ap[sym4[a][k]];
        covariance_from(4, A, *chi2, nf - 4, cov);
        /* q = (b / b0, C, γB / Γ0, Γ / Γ0) → θ */
        const double sc[4] = {bs, 1, G0 / gamma, G0};
        for (int a = 0; a < 4; a++)
            for (int k = 0; k < 4; k++) cov[a][k] *= sc[a] * sc[k];
        return 0;
    }
    svp_lm_result res;
    double covl[16];
    memcpy(th, th0, sizeof th0);
    *st = svp_lm_solve(t->ws, &t->prob, &c->options->lm, th, &res, covl);
    *chi2 = res.chi2;
    for (int a = 0; a < 4; a++)
        for (int k = 0; k < 4; k++) cov[a][k] = covl[a * 4 + k];
    return *st != SVP_OK;
}

/* ONE and TWO: the scaled start q = (b / b0, C, u..., w) of a pixel (TWO: the two deepest dips
 * apart by `exclude` frames, else the deepest one's mirror about D, else a split about it). */
static void fit_lines_start(const fit_shared *c, const double *y, const fit_start *s,
                            double qs[GEN_MAX])
{
    const double b0 = s->b0, den = s->den, bs = b0 > 0 ? b0 : 1;
    const double *xs = c->xs;
    const double area_lines = c->lines == SVP_ODMR_LINES_TWO ? 1.0 : 0.5;
    qs[0] = b0 / bs;
    qs[1] = (den > 0 && b0 > 0) ? fmin(0.9, den / (b0 * M_PI * c->G0 * area_lines)) : 0.01;
    if (!(qs[1] > 1e-6)) qs[1] = 1e-6;
    if (c->lines == SVP_ODMR_LINES_ONE) {
        qs[2] = xs[s->best];
        qs[3] = 1;
        return;
    }
    double v2;
    int second = deepest(y, c->nf, c->half_box, s->best, c->exclude, &v2);
    double u1 = xs[s->best], u2;
    if (second >= 0 && b0 - v2 >= 0.3 * (b0 - s->v_best))
        u2 = xs[second];
    else if (fabs(u1) > 0.25)
        u2 = -u1; /* its mirror about D */
    else {
        u1 = -0.25; /* overlapping lines: split about the dip */
        u2 = 0.25;
        u1 += xs[s->best];
        u2 += xs[s->best];
    }
    qs[2] = fmin(u1, u2);
    qs[3] = fmax(u1, u2);
    qs[4] = 1;
}

/* ONE: θ = (b, C, f₀, Γ); TWO: θ = (b, C, f₋, f₊, Γ) with f₋ < f₊; by gen_fit, or svp_lm_solve
 * when it does not converge. Returns 1 when the fit failed (*st its status). */
static int fit_lines(const fit_shared *c, fit_thread *t, const double *y, const fit_start *s,
                     double th[GEN_MAX], double cov[GEN_MAX][GEN_MAX], double *chi2,
                     svp_status *st)
{
    const int np = c->np, nf = c->nf;
    const double b0 = s->b0, bs = b0 > 0 ? b0 : 1, D = c->D, G0 = c->G0;
    double qs[GEN_MAX], q0[GEN_MAX], A[GEN_MAX][GEN_MAX];
    int fail = 0;
    fit_lines_start(c, y, s, qs);
    memcpy(q0, qs, sizeof qs);
    t->go.b0 = bs;
    if (!(b0 > 0) || gen_fit(&t->go, &c->options->lm, qs, A, chi2)) {
        svp_lm_result res;
        double covl[GEN_MAX * GEN_MAX];
        memcpy(qs, q0, sizeof q0);
        *st = svp_lm_solve(t->ws, &t->gprob, &c->options->lm, qs, &res, covl);
        fail = *st != SVP_OK;
        *chi2 = res.chi2;
        for (int a = 0; a < np; a++)
            for (int k = 0; k < np; k++) cov[a][k] = covl[a * np + k];
    } else {
        covariance_from(np, A, *chi2, nf - np, cov);
    }
    /* q → θ: b = b0 q0, C, f = D + Γ0 u, Γ = Γ0 w */
    double sc[GEN_MAX];
    sc[0] = bs;
    sc[1] = 1;
    for (int a = 2; a < np; a++) sc[a] = G0;
    th[0] = qs[0] * bs;
    th[1] = qs[1];
    for (int a = 2; a < np - 1; a++) th[a] = D + G0 * qs[a];
    th[np - 1] = G0 * qs[np - 1];
    for (int a = 0; a < np; a++)
        for (int k = 0; k < np; k++) cov[a][k] *= sc[a] * sc[k];
    if (c->lines == SVP_ODMR_LINES_TWO && th[2] > th[3]) { /* f₋ < f₊ */
        double tmp = th[2];
        th[2] = th[3];
        th[3] = tmp;
        for (int a = 0; a < np; a++) {
            tmp = cov[a][2], cov[a][2] = cov[a][3], cov[a][3] = tmp;
        }
        for (int k = 0; k < np; k++) {
            tmp = cov[2][k], cov[2][k] = cov[3][k], cov[3][k] = tmp;
        }
    }
    return fail;
}

/* Pixel p's maps from its fit θ, covariance and χ² (the field B and its σ per line model). */
static void fit_put(const fit_shared *c, size_t p, const double *y, double mean,
                    const double th[GEN_MAX], double cov[GEN_MAX][GEN_MAX], double chi2, int fail)
{
    const svp_odmr_maps *maps = c->maps;
    const int np = c->np, nf = c->nf;
    const double D = c->D, gamma = c->gamma;
    if (!(th[1] > 0 && th[1] < 1)) /* C on its bound: no σ from the curvature */
        for (int a = 0; a < np; a++)
            for (int k = 0; k < np; k++) cov[a][k] = a == k ? INFINITY : 0;
    const double sd_b = sqrt(cov[0][0]), sd_c = sqrt(cov[1][1]);
    const double sd_w = sqrt(cov[np - 1][np - 1]);
    double B, sd_B;
    if (c->lines == SVP_ODMR_LINES_PAIR) {
        B = fabs(th[2]);
        sd_B = sqrt(cov[2][2]);
    } else if (c->lines == SVP_ODMR_LINES_ONE) {
        B = c->options->line_sign * (th[2] - D) / gamma;
        sd_B = sqrt(cov[2][2]) / gamma;
    } else {
        B = (th[3] - th[2]) / (2 * gamma);
        double var = cov[2][2] + cov[3][3] - 2 * cov[2][3];
        sd_B = isfinite(var) ? sqrt(fmax(var, 0)) / (2 * gamma) : INFINITY;
        put(maps->field_lower, p, (D - th[2]) / gamma);
        put(maps->field_lower_sigma, p, sqrt(cov[2][2]) / gamma);
        put(maps->field_upper, p, (th[3] - D) / gamma);
        put(maps->field_upper_sigma, p, sqrt(cov[3][3]) / gamma);
    }
    maps->field->data[p] = B;
    put(maps->field_sigma, p, sd_B);
    put(maps->baseline, p, th[0]);
    put(maps->baseline_sigma, p, sd_b);
    put(maps->contrast, p, th[1]);
    put(maps->contrast_sigma, p, sd_c);
    put(maps->linewidth, p, th[np - 1]);
    put(maps->linewidth_sigma, p, sd_w);
    put(maps->converged, p, fail ? 0.0 : 1.0);
    if (maps->quality) {
        double ss = 0;
        for (int f = 0; f < nf; f++) ss += (y[f] - mean) * (y[f] - mean);
        maps->quality->data[p] = ss > 0 ? 1 - chi2 / ss : 0.0;
    }
}

/* A missing pixel (NaN/Inf in some frame): NaN maps, not converged. */
static void fit_put_missing(const svp_odmr_maps *maps, size_t p)
{
    svp_image *const all[] = {
        maps->field,          maps->field_sigma,    maps->field_lower, maps->field_lower_sigma,
        maps->field_upper,    maps->field_upper_sigma, maps->baseline, maps->baseline_sigma,
        maps->contrast,       maps->contrast_sigma, maps->linewidth,   maps->linewidth_sigma,
        maps->quality};
    for (size_t k = 0; k < sizeof all / sizeof all[0]; k++) put(all[k], p, NAN);
    put(maps->converged, p, 0.0);
}

/* Whether fit θ describes a dip the sweep has seen: its line inside the swept range by more
 * than one step (PAIR: one of D ± γB at least; ONE: f₀; TWO: f₋ and f₊; a line at the end of
 * the sweep cannot be told from one beyond it), its width at most the range and at least half
 * a step (narrower, at most one sample lies in it: noise; noisy fits of a dip one step wide
 * scatter down to 0.98 step), and a positive baseline (no light, no dip). Fits to spectra
 * without a dip (noise alone) converged to lines far outside (B of 10⁹ T), to single samples
 * (widths of kHz at a 2.4 MHz step) and to the sweep's ends; an all-zero pixel (a masked one)
 * converged to a made-up field. */
static int fit_in_sweep(const fit_shared *c, const double th[GEN_MAX])
{
    const double step = (c->sweep_hi - c->sweep_lo) / (c->nf - 1);
    const double lo = c->sweep_lo + step, hi = c->sweep_hi - step;
    const double width = th[c->np - 1];
    if (!(th[0] > 0) || !(width >= 0.5 * step) || !(width <= c->sweep_hi - c->sweep_lo)) return 0;
#define IN_SWEEP(f) ((f) > lo && (f) < hi)
    int ok;
    if (c->lines == SVP_ODMR_LINES_PAIR) {
        const double s = c->gamma * fabs(th[2]);
        ok = IN_SWEEP(c->D - s) || IN_SWEEP(c->D + s);
    } else if (c->lines == SVP_ODMR_LINES_ONE) {
        ok = IN_SWEEP(th[2]);
    } else {
        ok = IN_SWEEP(th[2]) && IN_SWEEP(th[3]);
    }
#undef IN_SWEEP
    return ok;
}

/* A fitted dip must be this many of its own σ deep (C / σ_C) or this many of its σ in area
 * (C Γ, with the fit's covariance of C and Γ): a dip about one step wide determines C Γ but not
 * C and Γ apart (real dips with C / σ_C down to 1.4 and fields within a few σ), one wide against
 * a short sweep C but not C Γ (C / σ_C 10, area about 4). Fits to noise alone (400 pixels of
 * 1000 counts ± 30, no dip) stay below both (C / σ_C at most 3.2), and below both fits latched
 * onto noise (a field 3 mT off with a σ of 20 µT). */
#define FIT_MIN_SIGNIFICANCE 5.0

static int fit_significant(const fit_shared *c, const double th[GEN_MAX],
                           double cov[GEN_MAX][GEN_MAX])
{
    const int w = c->np - 1;
    const double area = th[1] * th[w];
    const double var = th[w] * th[w] * cov[1][1] + th[1] * th[1] * cov[w][w] +
                       2 * th[1] * th[w] * cov[1][w];
    const int area_ok = isfinite(var) && area >= FIT_MIN_SIGNIFICANCE * sqrt(fmax(var, 0.0));
    const int depth_ok = isfinite(cov[1][1]) && th[1] >= FIT_MIN_SIGNIFICANCE * sqrt(cov[1][1]);
    return area_ok || depth_ok;
}

static const double fit_lower4[4] = {-INFINITY, 0, -INFINITY, 0};
static const double fit_upper4[4] = {INFINITY, 1, INFINITY, INFINITY};
static const double fit_lowerg[GEN_MAX] = {-INFINITY, 0, -INFINITY, -INFINITY, 0};
static const double fit_upperg[GEN_MAX] = {INFINITY, 1, INFINITY, INFINITY, INFINITY};

/* The settings every pixel's fit shares, for the frequencies of cube (the stack's, or a
 * pixel's finite samples): q (trapezoid weights) and xs ((ω − D) / Γ0) filled, nf of each. */
static void fit_shared_fill(const svp_cube *cube, const svp_odmr_fit_options *options,
                            const svp_odmr_maps *maps, double D, double gamma, double G0,
                            double *q, double *xs, fit_shared *c)
{
    const int nf = cube->n_freq;
    for (int f = 0; f < nf; f++) {
        q[f] = 0.5 * (cube->freq[f < nf - 1 ? f + 1 : f] - cube->freq[f > 0 ? f - 1 : f]);
        xs[f] = (cube->freq[f] - D) / G0;
    }
    /* smoothing half-width for the starting point: about half a linewidth of frames */
    const double spacing = (cube->freq[nf - 1] - cube->freq[0]) / (nf - 1);
    const double f_first = cube->freq[0], f_last = cube->freq[nf - 1];
    *c = (fit_shared){.cube = cube, .options = options, .maps = maps,
                      .lines = options->lines, .nf = nf,
                      .np = options->lines == SVP_ODMR_LINES_TWO ? 5 : 4,
                      .nb = options->baseline_frames, .D = D, .gamma = gamma, .G0 = G0,
                      .q = q, .xs = xs, .half_box = (int)fmin(nf / 4, floor(0.5 * G0 / spacing)),
                      .exclude = (int)ceil(1.5 * G0 / spacing),
                      .sweep_lo = fmin(f_first, f_last), .sweep_hi = fmax(f_first, f_last)};
}

/* A thread's solvers for spectra at y (pointers moved per pixel by fit_pixel). */
static void fit_thread_init(const fit_shared *c, fit_thread *t, double *y)
{
    t->px = (odmr_pixel){.freq = c->cube->freq, .D = c->D, .gamma = c->gamma};
    t->prob = (svp_lm_problem){.n_params = 4, .n_points = c->nf, .model = odmr_model,
                               .user = &t->px, .analytic_jacobian = 1, .data = y,
                               .lower = fit_lower4, .upper = fit_upper4};
    t->go = (odmr_gen){.x = c->xs, .y = y, .n = c->nf, .np = c->np,
                       .two = c->lines == SVP_ODMR_LINES_TWO};
    t->gprob = (svp_lm_problem){.n_params = c->np, .n_points = c->nf, .model = gen_model,
                                .user = &t->go, .analytic_jacobian = 1, .data = y,
                                .lower = c->np == 5 ? fit_lowerg : fit_lower4,
                                .upper = fit_upperg};
}

/* The fit of spectrum y at pixel p, every sample finite; returns as fit_pixel. */
static int fit_spectrum(const fit_shared *c, fit_thread *t, double *y, size_t p,
                        svp_status *st)
{
    const int nf = c->nf, nb = c->nb;
    fit_start s = {0, 0, 0, 0, 0};
    *st = SVP_OK;
    t->prob.data = t->gprob.data = t->go.y = y;
    for (int f = 0; f < nb; f++) s.b0 += (y[f] + y[nf - 1 - f]) / (2.0 * nb);
    for (int f = 0; f < nf; f++) {
        s.den += c->q[f] * (s.b0 - y[f]);
        s.mean += y[f];
    }
    s.mean /= nf;
    s.best = deepest(y, nf, c->half_box, -1, 0, &s.v_best);
    /* θ in physical units: PAIR (b, C, B, Γ); ONE (b, C, f₀, Γ); TWO (b, C, f₋, f₊, Γ) */
    double th[GEN_MAX], cov[GEN_MAX][GEN_MAX], chi2 = NAN;
    int fail = c->lines == SVP_ODMR_LINES_PAIR ? fit_pair(c, t, y, &s, th, cov, &chi2, st)
                                               : fit_lines(c, t, y, &s, th, cov, &chi2, st);
    if (!fail && (!fit_in_sweep(c, th) || !fit_significant(c, th, cov))) {
        fail = 1;
        *st = SVP_ERR_NUMERIC;
    }
    fit_put(c, p, y, s.mean, th, cov, chi2, fail);
    return fail;
}

/* The finite samples a pixel needs to be fitted (the rule is documented in svpsf.h). */
int svp_odmr_fit_min_finite(int n_freq, const svp_odmr_fit_options *options)
{
    svp_odmr_fit_options d;
    if (!options) {
        svp_odmr_fit_defaults(&d);
        options = &d;
    }
    const int np = options->lines == SVP_ODMR_LINES_TWO ? 5 : 4;
    int need = (n_freq + 1) / 2;
    if (need < np + 1) need = np + 1;
    if (need < 5) need = 5;
    if (need < 2 * options->baseline_frames) need = 2 * options->baseline_frames;
    return need;
}

/* A pixel with NaN/Inf samples (failed frames, masked values): fitted on its finite samples
 * alone, exactly as a stack without the other frames would fit it, when at most half are
 * missing and enough remain for the model and the baseline frames; else missing. */
static int fit_pixel_finite(const fit_shared *c, fit_thread *t, double *y, size_t p, int n_ok,
                            svp_status *st)
{
    const int nf = c->nf;
    if (n_ok < svp_odmr_fit_min_finite(nf, c->options)) {
        fit_put_missing(c->maps, p);
        return 2;
    }
    double *ys = t->sub, *fs = ys + nf, *qs = fs + nf, *xs = qs + nf;
    int k = 0;
    for (int f = 0; f < nf; f++)
        if (isfinite(y[f])) {
            ys[k] = y[f];
            fs[k++] = c->cube->freq[f];
        }
    const svp_cube sub = {.width = c->cube->width, .height = c->cube->height, .n_freq = n_ok,
                          .freq = fs, .frame = NULL};
    fit_shared cs;
    fit_shared_fill(&sub, c->options, c->maps, c->D, c->gamma, c->G0, qs, xs, &cs);
    fit_thread_init(&cs, t, ys);
    const int fail = fit_spectrum(&cs, t, ys, p, st);
    fit_thread_init(c, t, y); /* the next pixel's full set */
    return fail;
}

/* Pixel p of spectrum y: its start, fit and maps. Returns 0 when it converged, 1 when its fit
 * failed (*st the status; SVP_ERR_NUMERIC for a fit that converged to no dip the sweep shows —
 * outside it, too narrow, without light, or not significant — which is counted like one that
 * did not converge) and 2 for a missing pixel. */
static int fit_pixel(const fit_shared *c, fit_thread *t, double *y, size_t p, svp_status *st)
{
    int n_ok = 0;
    *st = SVP_OK;
    for (int f = 0; f < c->nf; f++) n_ok += isfinite(y[f]) != 0;
    if (n_ok < c->nf) return fit_pixel_finite(c, t, y, p, n_ok, st);
    return fit_spectrum(c, t, y, p, st);
}

svp_status svp_odmr_fit_maps(const svp_odmr *odmr, const svp_cube *cube,
                             const svp_odmr_fit_options *options, const svp_odmr_maps *maps,
                             size_t *n_failed)
{
    SVP_CHECK(odmr_validate(odmr));
    SVP_CHECK(cube_check(cube));
    svp_odmr_fit_options defaults;
    if (!options) {
        svp_odmr_fit_defaults(&defaults);
        options = &defaults;
    }
    SVP_CHECK(fit_check(cube, options, maps));
    if (!(cube->freq[0] > 0))
        return svp_fail(SVP_ERR_INVALID,
                        "ODMR fit: the frequencies must be > 0 Hz (the lowest is %g): an ODMR "
                        "line lies at D ± γB > 0",
                        cube->freq[0]);
    for (int f = 0; f < cube->n_freq; f++) { /* the fits square the data */
        char what[48];
        snprintf(what, sizeof what, "ODMR fit: frame %d", f);
        SVP_CHECK(svp_image_check_scale(cube->frame[f], what));
    }
    const int nf = cube->n_freq, np = options->lines == SVP_ODMR_LINES_TWO ? 5 : 4;
    const size_t n = (size_t)cube->width * cube->height;
    const double D = odmr->zero_field_hz, G0 = odmr->linewidth_hz;
    /* trapezoid weights (the dip area for the starting contrast) and scaled frequencies */
    double *q = malloc((size_t)nf * sizeof(double)), *xs = malloc((size_t)nf * sizeof(double));
    if (!q || !xs) {
        free(q);
        free(xs);
        return svp_fail(SVP_ERR_NOMEM, "out of memory for the fit");
    }
    fit_shared c;
    fit_shared_fill(cube, options, maps, D, odmr->gamma_hz_per_t, G0, q, xs, &c);
    size_t failed = 0, missing = 0;
    int alloc_failed = 0, cancelled = 0;
    svp_status first_error = SVP_OK;
    /* Pixels go to the threads in chunks (dynamic: fits differ in cost), with no barrier
     * between them; the calling thread (OpenMP's thread 0) reports the fraction done from a
     * shared count whenever it passes another 1 %, between its own chunks, and a cancel stops
     * every thread at its next chunk. Each pixel's fit is independent, so neither the chunks
     * nor the threads change a result. */
    const size_t per_thread = n / ((size_t)omp_get_max_threads() * 32);
    const size_t chunk = per_thread < 1 ? 1 : per_thread > 64 ? 64 : per_thread;
    const size_t n_chunks = (n + chunk - 1) / chunk, step = n / 100 > 0 ? n / 100 : 1;
    size_t done = 0;
#pragma omp parallel reduction(+ : failed, missing)
    {
        size_t next_report = step; /* thread 0's */
        fit_thread t = {0};
        /* the chunk's spectra, pixel-major: read frame by frame (a run of contiguous pixels
         * from each), not pixel by pixel across all frames */
        double *spectra = malloc((size_t)nf * chunk * sizeof(double));
        t.sub = malloc(4 * (size_t)nf * sizeof(double));
        if (svp_lm_workspace_new(np, nf, &t.ws) != SVP_OK || !spectra || !t.sub) {
#pragma omp atomic write
            alloc_failed = 1;
        }
        fit_thread_init(&c, &t, spectra);
#pragma omp for schedule(dynamic, 1)
        for (size_t ck = 0; ck < n_chunks; ck++) {
            int stop;
#pragma omp atomic read
            stop = cancelled;
            if (stop || !t.ws || !spectra || !t.sub) continue;
            const size_t p0 = ck * chunk, p1 = p0 + chunk < n ? p0 + chunk : n;
            for (int f = 0; f < nf; f++) {
                const double *src = cube->frame[f]->data + p0;
                for (size_t k = 0; k < p1 - p0; k++) spectra[k * (size_t)nf + f] = src[k];
            }
            for (size_t p = p0; p < p1; p++) {
                svp_status st;
                const int fail = fit_pixel(&c, &t, spectra + (p - p0) * (size_t)nf, p, &st);
                if (fail) failed++;
                if (fail == 2) missing++;
                if (fail == 1 && st != SVP_ERR_NUMERIC) {
#pragma omp critical(svp_odmr_fit_error)
                    if (first_error == SVP_OK) first_error = st;
                }
            }
            size_t now;
#pragma omp atomic capture
            {
                done += p1 - p0;
                now = done;
            }
            if (options->progress && omp_get_thread_num() == 0 && now >= next_report && now < n) {
                next_report = (now / step + 1) * step;
                if (options->progress(options->progress_user, (double)now / (double)n)) {
#pragma omp atomic write
                    cancelled = 1;
                }
            }
        }
        svp_lm_workspace_free(t.ws);
        free(spectra);
        free(t.sub);
    }
    free(q);
    free(xs);
    if (alloc_failed) return svp_fail(SVP_ERR_NOMEM, "out of memory for the fit workspaces");
    /* the last report, 1, from the calling thread once every pixel is done */
    if (!cancelled && options->progress && options->progress(options->progress_user, 1.0))
        cancelled = 1;
    if (cancelled) return svp_fail(SVP_ERR_CANCELLED, "Lorentzian fit cancelled");
    if (first_error != SVP_OK)
        return svp_fail(first_error, "Lorentzian fit: a pixel fit failed (%s)",
                        svp_status_string(first_error));
    if (missing == n) { /* nothing to fit (as svp_inverse_transform: nothing to restore) */
        const int need = svp_odmr_fit_min_finite(nf, options);
        int whole = -1;
        for (int f = 0; f < nf && whole < 0; f++)
            if (svp_image_count_nonfinite(cube->frame[f]) == n) whole = f;
        char frame[96] = "";
        if (whole >= 0)
            snprintf(frame, sizeof frame, " (the frame at %.6g GHz is NaN or Inf at every pixel)",
                     cube->freq[whole] * 1e-9);
        return svp_fail(SVP_ERR_INVALID,
                        "ODMR fit: every one of the %zu pixels holds NaN or Inf in more than %d "
                        "of its %d frames (missing data: a pixel needs %d finite samples to be "
                        "fitted)%s",
                        n, nf - need, nf, need, frame);
    }
    if (n_failed) *n_failed = failed;
    return SVP_OK;
}

svp_status svp_odmr_fit(const svp_odmr *odmr, const svp_cube *cube,
                        const svp_odmr_fit_options *options, svp_image *field,
                        svp_image *contrast, svp_image *baseline, svp_image *linewidth,
                        size_t *n_failed)
{
    svp_odmr_maps maps = {.field = field, .contrast = contrast, .baseline = baseline,
                          .linewidth = linewidth};
    return svp_odmr_fit_maps(odmr, cube, options, &maps, n_failed);
}
