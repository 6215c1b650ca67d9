/* ODMR spectral cubes (PHYSICS.md §1–2): the two-Lorentzian model and per-pixel estimators. The
 * cube is frame-major (one svp_image per frequency) so each frame can be blurred by the blur
 * operators; an estimator streams the frames and keeps per-pixel sums, which is also what
 * makes the centroid exactly linear-fractional (eq. 3). */
#include "physics_internal.h"

#include <math.h>
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
}

typedef struct odmr_pixel {
    const double *freq;
    double D, gamma;
} odmr_pixel;

/* θ = (b, C, B, Γ): f = b [1 − C (L(u₊) + L(u₋))], u± = ω − D ∓ γB, L = g² / (u² + g²), g = Γ/2 */
static int odmr_model(void *user, const double *th, int n_params, int n_points, double *model,
                      double *jac)
{
    (void)n_params;
    const odmr_pixel *px = user;
    const double b = th[0], C = th[1], split = px->gamma * th[2], g = 0.5 * th[3];
    if (!(g > 0)) return 1;
    const double g2 = g * g;
    for (int i = 0; i < n_points; i++) {
        double up = px->freq[i] - px->D - split, um = px->freq[i] - px->D + split;
        double ep = up * up + g2, em = um * um + g2;
        double lp = g2 / ep, lm = g2 / em, S = lp + lm;
        model[i] = b * (1 - C * S);
        if (jac) {
            double *row = jac + (size_t)i * 4;
            double dlp = -2 * up * g2 / (ep * ep), dlm = -2 * um * g2 / (em * em); /* ∂L/∂u */
            double glp = 2 * g * up * up / (ep * ep), glm = 2 * g * um * um / (em * em); /* ∂L/∂g */
            row[0] = 1 - C * S;
            row[1] = -b * S;
            row[2] = b * C * px->gamma * (dlp - dlm);
            row[3] = -0.5 * b * C * (glp + glm);
        }
    }
    return 0;
}

svp_status svp_odmr_fit(const svp_odmr *odmr, const svp_cube *cube,
                        const svp_odmr_fit_options *options, svp_image *field,
                        svp_image *contrast, svp_image *baseline, svp_image *linewidth,
                        size_t *n_failed)
{
    SVP_CHECK(odmr_validate(odmr));
    SVP_CHECK(cube_check(cube));
    SVP_CHECK(map_check(cube, field, "field"));
    if (contrast) SVP_CHECK(map_check(cube, contrast, "contrast"));
    if (baseline) SVP_CHECK(map_check(cube, baseline, "baseline"));
    if (linewidth) SVP_CHECK(map_check(cube, linewidth, "linewidth"));
    svp_odmr_fit_options defaults;
    if (!options) {
        svp_odmr_fit_defaults(&defaults);
        options = &defaults;
    }
    const int nf = cube->n_freq;
    if (nf < 5) return svp_fail(SVP_ERR_INVALID, "Lorentzian fit: %d frequencies, >= 5 needed", nf);
    if (options->baseline_frames < 1 || 2 * options->baseline_frames > nf)
        return svp_fail(SVP_ERR_INVALID, "Lorentzian fit: baseline_frames %d must be in [1, %d]",
                        options->baseline_frames, nf / 2);
    const size_t n = (size_t)cube->width * cube->height;
    const double D = odmr->zero_field_hz, gamma = odmr->gamma_hz_per_t;
    const int nb = options->baseline_frames;
    /* trapezoid weights for the starting point (the centroid of the depth) */
    double *q = malloc((size_t)nf * sizeof(double));
    if (!q) return svp_fail(SVP_ERR_NOMEM, "out of memory for the fit");
    for (int f = 0; f < nf; f++)
        q[f] = nf == 1 ? 1.0
                       : 0.5 * (cube->freq[f < nf - 1 ? f + 1 : f] - cube->freq[f > 0 ? f - 1 : f]);
    /* smoothing half-width for the starting point: about half a linewidth of frames */
    const double spacing = (cube->freq[nf - 1] - cube->freq[0]) / (nf - 1);
    const int half_box = (int)fmin(nf / 4, floor(0.5 * odmr->linewidth_hz / spacing));
    size_t failed = 0;
    int alloc_failed = 0;
    svp_status first_error = SVP_OK;
    const double lower[4] = {-INFINITY, 0, -INFINITY, 0};
    const double upper[4] = {INFINITY, 1, INFINITY, INFINITY};
#pragma omp parallel reduction(+ : failed)
    {
        svp_lm_workspace *ws = NULL;
        double *y = malloc((size_t)nf * sizeof(double));
        if (svp_lm_workspace_new(4, nf, &ws) != SVP_OK || !y) {
#pragma omp atomic write
            alloc_failed = 1;
        }
        odmr_pixel px = {.freq = cube->freq, .D = D, .gamma = gamma};
        svp_lm_problem prob = {.n_params = 4, .n_points = nf, .model = odmr_model, .user = &px,
                               .analytic_jacobian = 1, .data = y, .lower = lower,
                               .upper = upper};
#pragma omp for schedule(dynamic, 64)
        for (size_t p = 0; p < n; p++) {
            if (!ws || !y) continue;
            double b0 = 0, den = 0;
            for (int f = 0; f < nf; f++) y[f] = cube->frame[f]->data[p];
            for (int f = 0; f < nb; f++) b0 += (y[f] + y[nf - 1 - f]) / (2.0 * nb);
            for (int f = 0; f < nf; f++) den += q[f] * (b0 - y[f]);
            /* start at the deepest point of the spectrum smoothed over about one linewidth (the
             * centroid is too noisy a start: far-off frames enter it weighted by |ω − D|) */
            int best = 0;
            double best_v = INFINITY;
            for (int f = 0; f < nf; f++) {
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
            double th[4] = {b0, 0, fabs(cube->freq[best] - D) / gamma, odmr->linewidth_hz};
            /* at B = 0 exactly the model is flat in B (the dips are symmetric): start off it */
            th[2] = fmax(th[2], 0.25 * odmr->linewidth_hz / gamma);
            th[1] = (den > 0 && b0 > 0) ? fmin(0.9, den / (b0 * M_PI * th[3])) : 0.01;
            if (!(th[1] > 1e-6)) th[1] = 1e-6;
            svp_lm_result res;
            svp_status st = svp_lm_solve(ws, &prob, &options->lm, th, &res, NULL);
            if (st != SVP_OK) {
                failed++;
                if (st != SVP_ERR_NUMERIC) {
#pragma omp critical(svp_odmr_fit_error)
                    if (first_error == SVP_OK) first_error = st;
                }
            }
            field->data[p] = fabs(th[2]);
            if (contrast) contrast->data[p] = th[1];
            if (baseline) baseline->data[p] = th[0];
            if (linewidth) linewidth->data[p] = th[3];
        }
        svp_lm_workspace_free(ws);
        free(y);
    }
    free(q);
    if (alloc_failed) return svp_fail(SVP_ERR_NOMEM, "out of memory for the fit workspaces");
    if (first_error != SVP_OK)
        return svp_fail(first_error, "Lorentzian fit: a pixel fit failed (%s)",
                        svp_status_string(first_error));
    if (n_failed) *n_failed = failed;
    return SVP_OK;
}
