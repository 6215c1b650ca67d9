/* Richardson–Lucy deconvolution (docs/model.md §Deconvolution) for any operator H, through
 * svp_blur_apply / svp_blur_adjoint only:
 *     x ← x · Hᵀ(m y / max(Hx, floor)) / Hᵀm
 * m the finite-data mask (NaN/Inf pixels of y are missing data), Hᵀm the Bertero–Boccacci
 * boundary weights (with options->boundary_weights = 0 the scalar mean of Hᵀm instead: plain
 * RL, exact for a periodic unit-flux operator without missing data), floor = options->floor ·
 * max(y). Started flat at the mean of the finite data (RL forgets the start's scale after one
 * iteration). */
#include "restore_internal.h"

#include <float.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

/* Pointwise loops run in parallel only above this many pixels (below, threads cost more). */
#define PAR_MIN 32768
/* auto_stop: stalled when χ² fell by less than STALL_FALL of itself over STALL_SPAN iterations */
#define STALL_SPAN 10
#define STALL_FALL 0.001
/* Biggs–Andrews: the extrapolation weight's cap (α → 1 can overshoot without bound) */
#define ALPHA_MAX 0.95
/* an extrapolated pixel keeps at least this fraction of its value */
#define KEEP_FRACTION 0.5

/* Biggs–Andrews: x ← z = x_k + α (x_k − x_{k−1}) in place, x_prev ← x_k; α = <g_{k−1}, g_{k−2}> /
 * <g_{k−2}, g_{k−2}> in [0, ALPHA_MAX] from the last two RL steps (0 for the first two), or
 * alpha_in[k] when given; alpha_out[k] records it. A pixel the extrapolation would push below
 * KEEP_FRACTION of its value keeps that fraction (RL cannot bring a zero back). scratch: n
 * values for the dot products. */
static void extrapolate(double *restrict x, double *restrict x_prev, const double *step_1,
                        const double *step_2, double *scratch, size_t n, int k,
                        const double *alpha_in, double *alpha_out)
{
    double alpha = 0;
    if (alpha_in) {
        alpha = alpha_in[k];
    } else if (k >= 2) {
        const double num = svp_dot(step_1, step_2, scratch, n);
        const double den = svp_dot(step_2, step_2, scratch, n);
        alpha = den > 0 ? num / den : 0.0;
        alpha = alpha > 0 ? (alpha < ALPHA_MAX ? alpha : ALPHA_MAX) : 0.0;
    }
    if (alpha_out) alpha_out[k] = alpha;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) {
        const double xk = x[i], z = xk + alpha * (xk - x_prev[i]);
        x_prev[i] = xk;
        x[i] = z > KEEP_FRACTION * xk ? z : KEEP_FRACTION * xk;
    }
}

/* Σ over finite data of (Hx − y)² / var (var_map, at least var_const; or var_const), in
 * svp_sum's fixed order (scratch: n values). */
static double residual_chi2(const double *y, const double *hx, const double *var_map,
                            double var_const, double *scratch, size_t n)
{
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) {
        const double r = isfinite(y[i]) ? hx[i] - y[i] : 0.0;
        const double v = var_map ? fmax(var_map[i], var_const) : var_const;
        scratch[i] = isfinite(y[i]) ? r * r / v : 0.0;
    }
    return svp_sum(scratch, n);
}

/* The stopping rule after iteration k's χ² per datum (history: the last STALL_SPAN + 1 values,
 * shifted here): SVP_RL_STOP_DISCREPANCY at χ² <= 1, SVP_RL_STOP_STALLED when χ² fell by less
 * than STALL_FALL of itself over STALL_SPAN iterations, else SVP_RL_STOP_CAP (go on). */
static int stopping_rule(double *history, double chi2, int k)
{
    for (int j = 0; j < STALL_SPAN; j++) history[j] = history[j + 1];
    history[STALL_SPAN] = chi2;
    if (chi2 <= 1.0) return SVP_RL_STOP_DISCREPANCY;
    if (k >= STALL_SPAN && history[0] - chi2 < STALL_FALL * chi2) return SVP_RL_STOP_STALLED;
    return SVP_RL_STOP_CAP;
}

static svp_status check_args(const svp_blur *blur, const svp_image *y, const svp_deconv_options *o,
                             const svp_image *x)
{
    const char *what = "Richardson–Lucy";
    SVP_CHECK(svp_deconv_check_images(blur, y, x, what));
    if (o->iterations < 1)
        return svp_fail(SVP_ERR_INVALID, "%s: iterations = %d: at least 1 is needed", what,
                        o->iterations);
    if (o->acceleration != SVP_RL_PLAIN && o->acceleration != SVP_RL_BIGGS_ANDREWS)
        return svp_fail(SVP_ERR_INVALID, "%s: unknown acceleration %d", what, (int)o->acceleration);
    if (!(o->floor >= 0) || !isfinite(o->floor))
        return svp_fail(SVP_ERR_INVALID, "%s: floor %g is invalid: it must be finite and >= 0",
                        what, o->floor);
    return SVP_OK;
}

svp_status svp_deconv_rl(svp_blur *blur, const svp_image *y, const svp_deconv_options *options,
                         svp_image *x)
{
    return svp_deconv_rl_path(blur, y, options, x, NULL, NULL);
}

/* One Richardson–Lucy run (svp_deconv_rl_path): its data, buffers and constants. */
typedef struct rl_run {
    svp_blur *blur;
    const svp_deconv_options *o;
    int w, h;
    size_t n, n_finite;
    const double *yd;                                    /* the data y */
    double *y_masked, *blurred, *correction, *inv_norm; /* n values each */
    double *x_prev, *step_1, *step_2;                    /* Biggs–Andrews, else NULL */
    double y_max;
    const double *var_map; /* the stopping rule's noise variance: a map, or */
    double var_const;      /* one σ² (and the floor under the map) */
} rl_run;

/* One pass: the finite mask folded into y (missing → 0), the range and the count; the data
 * RL cannot take (no finite pixel, a negative one) as an error. */
static svp_status rl_scan(rl_run *r)
{
    const size_t n = r->n;
    const double *restrict yd = r->yd;
    double *y_masked = r->y_masked;
    double y_min = INFINITY, y_max = -INFINITY;
    size_t n_finite = 0;
#pragma omp parallel for schedule(static) if (n > PAR_MIN) reduction(min : y_min)              \
    reduction(max : y_max) reduction(+ : n_finite)
    for (size_t i = 0; i < n; i++) {
        double v = yd[i];
        if (isfinite(v)) {
            y_masked[i] = v;
            y_min = v < y_min ? v : y_min;
            y_max = v > y_max ? v : y_max;
            n_finite++;
        } else {
            y_masked[i] = 0.0;
        }
    }
    r->y_max = y_max;
    r->n_finite = n_finite;
    if (n_finite == 0)
        return svp_fail(SVP_ERR_INVALID,
                        "Richardson–Lucy: all %zu pixels of the data y are NaN "
                        "or Inf",
                        n);
    if (y_min < 0) {
        size_t at = 0;
        while (at < n && !(yd[at] == y_min)) at++;
        return svp_fail(SVP_ERR_INVALID,
                        "Richardson–Lucy needs data >= 0 but y has minimum %.17g at pixel (%d, "
                        "%d); for signed data use the signed shift (method rl-signed)",
                        y_min, (int)(at % (size_t)r->w), (int)(at / (size_t)r->w));
    }
    return SVP_OK;
}

/* The normalisation 1 / Hᵀm (m = 1 without missing data) into inv_norm, computed once: per
 * pixel with boundary weights (0 where no finite datum sees the pixel), else its mean. */
static svp_status rl_normalisation(rl_run *r)
{
    const size_t n = r->n;
    const double *yd = r->yd;
    double *blurred = r->blurred, *inv_norm = r->inv_norm;
    svp_image img_blurred = {r->w, r->h, blurred}, img_norm = {r->w, r->h, inv_norm};
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) blurred[i] = isfinite(yd[i]) ? 1.0 : 0.0;
    SVP_CHECK(svp_blur_adjoint(r->blur, &img_blurred, &img_norm));
    if (r->o->boundary_weights) {
        /* Pixels no finite datum sees (Hᵀm ~ 0) keep their value: 0 marks them. */
        const double tiny = 1e-12 * svp_max(inv_norm, n);
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) inv_norm[i] = inv_norm[i] > tiny ? 1.0 / inv_norm[i] : 0.0;
    } else {
        const double mean_norm = svp_sum(inv_norm, n) / (double)n;
        const double inv = mean_norm > 0 ? 1.0 / mean_norm : 1.0;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
        for (size_t i = 0; i < n; i++) inv_norm[i] = inv;
    }
    return SVP_OK;
}

/* The stopping rule's noise variance (auto_stop): the caller's map, or one σ² estimated from
 * y; at least round-off of y_max², so noiseless data never reach χ² = 1 and the stall decides. */
static svp_status rl_variance(rl_run *r, const svp_image *y)
{
    const svp_deconv_options *o = r->o;
    r->var_map = NULL;
    r->var_const = 0;
    if (!o->auto_stop) return SVP_OK;
    if (o->variance) {
        SVP_CHECK(svp_image_same_size(y, o->variance, "y", "variance"));
        r->var_map = o->variance->data;
    } else {
        double sigma = 0;
        SVP_CHECK(svp_noise_sigma_estimate(y, &sigma));
        r->var_const = sigma * sigma;
    }
    r->var_const = fmax(r->var_const, 1e-24 * r->y_max * r->y_max);
    return SVP_OK;
}

/* One multiplicative step x ← x · Hᵀ(m y / max(Hx, floor)) / Hᵀm, with Hx in `blurred`;
 * g (or NULL) receives the step x_new − x. */
static svp_status rl_step(rl_run *r, double *restrict xd, double *restrict g, double floor_abs)
{
    const size_t n = r->n;
    double *blurred = r->blurred;
    const double *y_masked = r->y_masked, *inv_norm = r->inv_norm, *correction = r->correction;
    svp_image img_blurred = {r->w, r->h, blurred}, img_correction = {r->w, r->h, r->correction};
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) {
        double hx = blurred[i];
        blurred[i] = y_masked[i] / (hx > floor_abs ? hx : floor_abs);
    }
    SVP_CHECK(svp_blur_adjoint(r->blur, &img_blurred, &img_correction));
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) {
        if (inv_norm[i] == 0) {
            if (g) g[i] = 0.0;
            continue;
        }
        const double old = xd[i];
        double v = old * correction[i] * inv_norm[i];
        /* round-off can make Hᵀ(...) slightly negative; NaN/Inf never leave */
        v = (v > 0 && v <= DBL_MAX) ? v : 0.0;
        xd[i] = v;
        if (g) g[i] = v - old;
    }
    return SVP_OK;
}

/* The flat start: x = the mean of the finite data. */
static void rl_start(const rl_run *r, svp_image *x)
{
    const size_t n = r->n;
    const double start = svp_sum(r->y_masked, n) / (double)r->n_finite;
    double *restrict xd = x->data;
#pragma omp parallel for schedule(static) if (n > PAR_MIN)
    for (size_t i = 0; i < n; i++) xd[i] = start;
}

/* Acceleration (Biggs–Andrews): the previous iterate and the last two RL steps. */
static svp_status rl_alloc_acceleration(rl_run *r)
{
    if (r->o->acceleration != SVP_RL_BIGGS_ANDREWS) return SVP_OK;
    r->x_prev = svp_alloc(r->n * sizeof(double));
    r->step_1 = svp_alloc(r->n * sizeof(double));
    r->step_2 = svp_alloc(r->n * sizeof(double));
    if (!r->x_prev || !r->step_1 || !r->step_2)
        return svp_fail(SVP_ERR_NOMEM, "Richardson–Lucy: out of memory for the acceleration");
    return SVP_OK;
}

/* The iterations from the start in x, until the count or (auto_stop) the stopping rule; the
 * report filled. */
static svp_status rl_iterate(rl_run *r, svp_image *x, const double *alpha_in, double *alpha_out)
{
    const svp_deconv_options *o = r->o;
    const size_t n = r->n;
    /* floor > 0 keeps y / Hx finite; 1e-300 y_max guards floor = 0 without overflowing */
    const double floor_abs = fmax(o->floor * r->y_max, 1e-300 * r->y_max);
    double *restrict xd = x->data;
    svp_image img_x = {r->w, r->h, x->data}, img_blurred = {r->w, r->h, r->blurred};
    const int auto_stop = o->auto_stop, accel = r->x_prev != NULL;
    double chi2_history[STALL_SPAN + 1] = {0};
    int done = 0, stop = auto_stop ? SVP_RL_STOP_CAP : SVP_RL_STOP_COUNT;
    double chi2 = 0;
    for (int k = 0; k < o->iterations; k++) {
        if (accel)
            extrapolate(xd, r->x_prev, r->step_1, r->step_2, r->correction, n, k, alpha_in,
                        alpha_out);
        SVP_CHECK(svp_blur_apply(r->blur, &img_x, &img_blurred));
        if (auto_stop) {
            chi2 = residual_chi2(r->yd, r->blurred, r->var_map, r->var_const, r->correction, n) /
                   (double)r->n_finite;
            const int why = stopping_rule(chi2_history, chi2, k);
            if (why != SVP_RL_STOP_CAP) {
                stop = why;
                done = k;
                break;
            }
        }
        double *g = r->step_2; /* becomes the newest step */
        SVP_CHECK(rl_step(r, xd, g, floor_abs));
        if (accel) {
            r->step_2 = r->step_1;
            r->step_1 = g;
        }
        done = k + 1;
        SVP_CHECK(svp_report_progress(o->progress, o->progress_user,
                                      (double)(k + 1) / o->iterations));
    }
    svp_status st = SVP_OK;
    if (stop == SVP_RL_STOP_DISCREPANCY || stop == SVP_RL_STOP_STALLED)
        st = svp_report_progress(o->progress, o->progress_user, 1.0);
    if (o->report) {
        o->report->iterations = done;
        o->report->chi2 = chi2;
        o->report->stop = stop;
    }
    return st;
}

svp_status svp_deconv_rl_path(svp_blur *blur, const svp_image *y,
                              const svp_deconv_options *options, svp_image *x,
                              const double *alpha_in, double *alpha_out)
{
    svp_deconv_options defaults;
    if (!options) {
        svp_deconv_defaults(&defaults);
        options = &defaults;
    }
    SVP_CHECK(check_args(blur, y, options, x));
    /* single precision: the operator's float transforms for this call only */
    const int was_single = blur->single;
    if (options->single_precision) SVP_CHECK(svp_blur_set_single(blur, 1));
    const size_t n = (size_t)y->width * y->height;
    rl_run r = {.blur = blur, .o = options, .w = y->width, .h = y->height, .n = n,
                .yd = y->data};
    svp_status st = SVP_OK;
    if (options->report) memset(options->report, 0, sizeof *options->report);

    /* y with its missing pixels at 0, Hx (and the ratio y / Hx), Hᵀ(...), 1 / Hᵀm */
    r.y_masked = svp_alloc(n * sizeof(double));
    r.blurred = svp_alloc(n * sizeof(double));
    r.correction = svp_alloc(n * sizeof(double));
    r.inv_norm = svp_alloc(n * sizeof(double));
    if (!r.y_masked || !r.blurred || !r.correction || !r.inv_norm) {
        st = svp_fail(SVP_ERR_NOMEM, "Richardson–Lucy: out of memory for %d x %d buffers", r.w,
                      r.h);
        goto cleanup;
    }
    if ((st = rl_scan(&r)) != SVP_OK) goto cleanup;
    if (r.y_max == 0) {
        /* all-zero data: the only non-negative solution with zero flux */
        memset(x->data, 0, n * sizeof(double));
        for (int k = 1; k <= options->iterations && st == SVP_OK; k++)
            st = svp_report_progress(options->progress, options->progress_user,
                                     (double)k / options->iterations);
        goto cleanup;
    }
    if ((st = rl_normalisation(&r)) != SVP_OK) goto cleanup;
    rl_start(&r, x);
    if ((st = rl_variance(&r, y)) != SVP_OK || (st = rl_alloc_acceleration(&r)) != SVP_OK)
        goto cleanup;
    st = rl_iterate(&r, x, alpha_in, alpha_out);
cleanup:
    if (options->single_precision && !was_single) svp_blur_set_single(blur, 0);
    svp_free(r.y_masked);
    svp_free(r.blurred);
    svp_free(r.correction);
    svp_free(r.inv_norm);
    svp_free(r.x_prev);
    svp_free(r.step_1); /* rl_iterate swaps the two steps: both are freed either way */
    svp_free(r.step_2);
    return st;
}
