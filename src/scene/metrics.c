/* Scene metrics as a physicist reads them (docs/scenes.md §Metrics): masks, relative-error maps,
 * statistics over each mask (means, peaks, reductions, medians and percentiles of the relative
 * error), histograms of the relative error, line cuts; CSV tables and result values. */
#include "scene_internal.h"

#include "../io/json.h"

#include <math.h>
#include <stddef.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* ---- masks ------------------------------------------------------------------------------ */

/* 1-D squared Euclidean distance transform (Felzenszwalb & Huttenlocher 2012). f: n values
 * (0 or INFINITY), d: output; v, z: work (n and n + 1). */
static void edt_1d(const double *f, int n, double *d, int *v, double *z)
{
    int k = 0;
    v[0] = 0;
    z[0] = -INFINITY;
    z[1] = INFINITY;
    int start = 0;
    while (start < n && isinf(f[start])) start++;
    if (start == n) {
        for (int q = 0; q < n; q++) d[q] = INFINITY;
        return;
    }
    v[0] = start;
    for (int q = start + 1; q < n; q++) {
        if (isinf(f[q])) continue;
        double sq;
        for (;;) {
            sq =
                ((f[q] + (double)q * q) - (f[v[k]] + (double)v[k] * v[k])) / (2.0 * q - 2.0 * v[k]);
            if (sq <= z[k] && k > 0) {
                k--;
                continue;
            }
            break;
        }
        k++;
        v[k] = q;
        z[k] = sq;
        z[k + 1] = INFINITY;
    }
    k = 0;
    for (int q = 0; q < n; q++) {
        while (z[k + 1] < q) k++;
        double dq = (double)q - v[k];
        d[q] = dq * dq + f[v[k]];
    }
}

/* Squared distance (pixels²) of each pixel of `inside` (nonzero) to the nearest pixel outside
 * it; the image border does not count as outside. */
static svp_status distance_to_outside(const svp_image *inside, double *dist)
{
    const int w = inside->width, h = inside->height, n = w > h ? w : h;
    double *f = malloc((size_t)n * sizeof *f), *d = malloc((size_t)n * sizeof *d);
    double *z = malloc((size_t)(n + 1) * sizeof *z);
    int *v = malloc((size_t)n * sizeof *v);
    if (!f || !d || !z || !v) {
        free(f), free(d), free(z), free(v);
        return svp_fail(SVP_ERR_NOMEM, "out of memory");
    }
    for (int i = 0; i < w; i++) {
        for (int j = 0; j < h; j++) f[j] = inside->data[(size_t)j * w + i] != 0 ? INFINITY : 0;
        edt_1d(f, h, d, v, z);
        for (int j = 0; j < h; j++) dist[(size_t)j * w + i] = d[j];
    }
    for (int j = 0; j < h; j++) {
        memcpy(f, dist + (size_t)j * w, (size_t)w * sizeof *f);
        edt_1d(f, w, d, v, z);
        memcpy(dist + (size_t)j * w, d, (size_t)w * sizeof *d);
    }
    free(f), free(d), free(z), free(v);
    return SVP_OK;
}

/* The pixels a mask holds. */
static size_t mask_count(const svp_image *mask)
{
    const size_t n = (size_t)mask->width * mask->height;
    size_t k = 0;
    for (size_t p = 0; p < n; p++) k += mask->data[p] != 0;
    return k;
}

svp_status scene_make_masks(const svp_scene *s, svp_scene_result *r)
{
    const int w = s->view_w, h = s->view_h;
    const size_t n = (size_t)w * h;
    const svp_image *cf = scene_result_get(r, "cover_flakes");
    const svp_image *cs = scene_result_get(r, "cover_strips");
    const svp_image *pl = scene_result_get(r, "pl_true");
    if (!cf || !cs || !pl) return svp_fail(SVP_ERR_INTERNAL, "scene: masks need the cropped maps");
    double pl_max = svp_max(pl->data, n);
    for (int m = 0; m < s->n_masks; m++) {
        const scene_mask *mk = &s->masks[m];
        char name[64];
        snprintf(name, sizeof name, "mask_%s", mk->name);
        if (scene_result_get(r, name)) continue;
        svp_image *mask = scene_result_new_map(r, name, w, h);
        if (!mask) return svp_fail(SVP_ERR_NOMEM, "out of memory");
        svp_image *file = NULL;
        if (mk->inside == MASK_FILE) {
            SVP_CHECK(svp_image_read(mk->path, &file));
            if (file->width != s->canvas_w || file->height != s->canvas_h) {
                svp_image_free(file);
                return svp_fail(SVP_ERR_SIZE, "%s: the mask changed size", mk->where);
            }
        }
        for (int j = 0; j < h; j++)
            for (int i = 0; i < w; i++) {
                size_t p = (size_t)j * w + i;
                int in = 1;
                switch (mk->inside) {
                case MASK_ALL: in = 1; break;
                case MASK_SOURCES: in = fmax(cf->data[p], cs->data[p]) >= 0.5; break;
                case MASK_FLAKES: in = cf->data[p] >= 0.5; break;
                case MASK_STRIPS: in = cs->data[p] >= 0.5; break;
                case MASK_FILE:
                    in = file->data[(size_t)(j + s->margin_px) * s->canvas_w + i + s->margin_px] >
                         0.5;
                    break;
                case MASK_NONE_REGION: in = 0; break;
                }
                if (mk->outside) in = !in;
                mask->data[p] = in;
            }
        svp_image_free(file);
        const size_t n_region = mask_count(mask);
        if (mk->erode_um > 0) {
            double *dist = malloc(n * sizeof *dist);
            if (!dist) return svp_fail(SVP_ERR_NOMEM, "out of memory");
            svp_status st = distance_to_outside(mask, dist);
            /* a pixel next to the outside is 1 px (centre to centre) from it and its centre
             * 0.5 px from the region's edge: drop centres within erode_um of the edge */
            double r2 = pow(mk->erode_um / s->pixel_um + 0.5, 2) * (1 + 1e-12);
            for (size_t p = 0; st == SVP_OK && p < n; p++)
                if (mask->data[p] != 0 && !(dist[p] > r2)) mask->data[p] = 0;
            free(dist);
            SVP_CHECK(st);
        }
        const size_t n_eroded = mask_count(mask);
        if (mk->lit_above > 0)
            for (size_t p = 0; p < n; p++)
                if (!(pl->data[p] >= mk->lit_above * pl_max)) mask->data[p] = 0;
        /* an empty mask has no statistics: every metric over it would be NaN */
        if (mask_count(mask) == 0) {
            const int own = mk->where[0] != 0; /* else one of the scene's defaults */
            return svp_fail(SVP_ERR_INVALID,
                            "%s%s mask '%s' holds no pixel of the %d x %d view (its region %zu, "
                            "after erode_um %g: %zu, after lit_above %g: 0): its statistics "
                            "would be NaN; %s",
                            own ? mk->where : "", own ? ":" : "the default", mk->name, w, h,
                            n_region, mk->erode_um, n_eroded, mk->lit_above,
                            own ? "widen it, erode less, or drop it"
                                : "are the sources inside the view? (metrics: masks: lists the "
                                  "masks to use instead of the defaults)");
        }
    }
    return SVP_OK;
}

/* ---- statistics ------------------------------------------------------------------------- */

/* Quantile q of a[0..n) with linear interpolation between order statistics (numpy's default);
 * reorders a. */
static double quantile(double *a, size_t n, double q)
{
    if (n == 0) return NAN;
    double pos = q * (double)(n - 1);
    size_t i = (size_t)floor(pos);
    double x = svp_select_kth(a, n, i);
    if (i + 1 >= n) return x;
    double y = INFINITY; /* after the selection everything beyond i is >= a[i] */
    for (size_t k = i + 1; k < n; k++) y = fmin(y, a[k]);
    return x + (pos - (double)i) * (y - x);
}

/* 1, 2, 5 × 10^k at or above x. */
static double nice_ceil(double x)
{
    if (!(x > 0) || !isfinite(x)) return 1;
    double e = pow(10, floor(log10(x)));
    double m = x / e;
    double n = m <= 1 + 1e-9 ? 1 : m <= 2 + 1e-9 ? 2 : m <= 5 + 1e-9 ? 5 : 10;
    return n * e;
}

static svp_status setv(svp_scene_result *r, double v, const char *q, const char *m, const char *ver,
                       const char *stat)
{
    char key[200];
    snprintf(key, sizeof key, "%s/%s/%s/%s", q, m, ver, stat);
    return scene_result_set(r, key, v);
}

static const char *ascii_unit(const scene_quantity *q)
{
    if (!strcmp(q->unit, "\xc2\xb5T")) return "uT";
    if (!strcmp(q->unit, "A/m")) return "A_per_m";
    if (!strcmp(q->unit, "a.u.")) return "au";
    return q->unit;
}

static double bilinear(const svp_image *img, double x, double y)
{
    int x0 = (int)floor(x), y0 = (int)floor(y);
    if (x0 < 0) x0 = 0;
    if (y0 < 0) y0 = 0;
    if (x0 > img->width - 2) x0 = img->width - 2;
    if (y0 > img->height - 2) y0 = img->height - 2;
    if (x0 < 0) x0 = 0;
    if (y0 < 0) y0 = 0;
    double fx = fmin(fmax(x - x0, 0), 1), fy = fmin(fmax(y - y0, 0), 1);
    int x1 = x0 + 1 < img->width ? x0 + 1 : x0, y1 = y0 + 1 < img->height ? y0 + 1 : y0;
    const double *d = img->data;
    int w = img->width;
    return (1 - fy) * ((1 - fx) * d[(size_t)y0 * w + x0] + fx * d[(size_t)y0 * w + x1]) +
           fy * ((1 - fx) * d[(size_t)y1 * w + x0] + fx * d[(size_t)y1 * w + x1]);
}

void scene_analysis_free(scene_analysis *a)
{
    if (!a) return;
    for (int i = 0; i < a->n_hists; i++) free(a->hists[i].fraction);
    free(a->hists);
    for (int c = 0; c < SCENE_MAX_CUTS; c++) {
        free(a->cuts[c].s_um);
        free(a->cuts[c].x_um);
        free(a->cuts[c].y_um);
        free(a->cuts[c].values);
        free(a->cut_csv[c]);
    }
    free(a->metrics_csv);
    free(a->hist_csv);
    memset(a, 0, sizeof *a);
}

static char *take(svp_strbuf *b)
{
    if (b->failed) {
        svp_strbuf_free(b);
        return NULL;
    }
    char *t = b->data;
    b->data = NULL;
    return t;
}

/* What the stages of scene_analyse share. */
typedef struct analyse_ctx {
    const svp_scene *s;
    svp_scene_result *r;
    scene_analysis *a;
    int w, h;
    size_t n;          /* pixels of the view */
    double *buf, *abuf; /* n each: signed and absolute errors of the pixels in use */
    svp_strbuf csv, hcsv; /* metrics.csv, histograms.csv */
} analyse_ctx;

/* Quantity qi: the colour range of its maps (display units), and its true map and peak. */
static svp_status analyse_range(analyse_ctx *c, int qi, const svp_image **truth_out,
                                double *peak_out)
{
    scene_analysis *a = c->a;
    const scene_quantity *q = &a->q[qi];
    const size_t n = c->n;
    char name[128];
    snprintf(name, sizeof name, "%s_true", q->name);
    const svp_image *truth = scene_result_get(c->r, name);
    if (!truth) return svp_fail(SVP_ERR_INTERNAL, "scene: no map %s", name);
    double peak = fmax(svp_max(truth->data, n), -svp_min(truth->data, n));
    if (q->diverging) {
        a->map_lo[qi] = -peak * q->display_scale;
        a->map_hi[qi] = peak * q->display_scale;
    } else {
        double mx = svp_max(truth->data, n);
        snprintf(name, sizeof name, "%s_apparent", q->name);
        const svp_image *app = scene_result_get(c->r, name);
        if (q->recon < 0 && app) mx = fmax(mx, svp_max(app->data, n));
        a->map_lo[qi] = 0;
        a->map_hi[qi] = mx * q->display_scale;
    }
    if (!(a->map_hi[qi] > a->map_lo[qi])) {
        a->map_lo[qi] = q->diverging ? -1 : 0;
        a->map_hi[qi] = 1;
    }
    *truth_out = truth;
    *peak_out = peak;
    return SVP_OK;
}

/* Quantity qi: the relative-error map of every version against the truth, and the colour
 * range of the error maps (the 99th percentile of |error| of the apparent map over the view). */
static svp_status analyse_error_maps(analyse_ctx *c, int qi, const svp_image *truth, double peak)
{
    scene_analysis *a = c->a;
    const scene_quantity *q = &a->q[qi];
    const size_t n = c->n;
    const double floor_abs = c->s->local_floor * peak;
    char name[128];
    for (int v = 1; v < a->nv; v++) {
        snprintf(name, sizeof name, "%s_%s", q->name, a->versions[v]);
        const svp_image *est = scene_result_get(c->r, name);
        snprintf(name, sizeof name, "err_%s_%s", q->name, a->versions[v]);
        svp_image *err = scene_result_new_map(c->r, name, c->w, c->h);
        if (!est || !err) return svp_fail(SVP_ERR_INTERNAL, "scene: no map for %s", name);
        for (size_t p = 0; p < n; p++) {
            double t = truth->data[p];
            double ref = q->ref_local ? fabs(t) : peak;
            err->data[p] = (q->ref_local && !(fabs(t) >= floor_abs)) || !(ref > 0)
                               ? NAN
                               : (est->data[p] - t) / ref;
        }
    }
    snprintf(name, sizeof name, "err_%s_apparent", q->name);
    const svp_image *err = scene_result_get(c->r, name);
    size_t k = 0;
    for (size_t p = 0; p < n; p++)
        if (isfinite(err->data[p])) c->abuf[k++] = fabs(err->data[p]);
    a->err_range_pct[qi] = k ? fmax(nice_ceil(100 * quantile(c->abuf, k, 0.99)), 0.1) : 1;
    return SVP_OK;
}

/* Quantity qi, mask m, version v: mean, mean |value| and peak over the mask; for v > 0 also
 * the reductions against the truth (true_mean_abs, true_peak: set when v = 0), the statistics
 * of the relative error and its histogram; one line of metrics.csv. */
static svp_status analyse_version(analyse_ctx *c, int qi, int m, const svp_image *mask,
                                  size_t n_pix, int v, double *true_mean_abs, double *true_peak)
{
    const svp_scene *s = c->s;
    svp_scene_result *r = c->r;
    scene_analysis *a = c->a;
    const scene_quantity *q = &a->q[qi];
    const scene_mask *mk = &s->masks[m];
    scene_hist *hist = &a->hists[qi * s->n_masks + m];
    const size_t n = c->n;
    double *buf = c->buf, *abuf = c->abuf;
    const char *ver = a->versions[v];
    char name[128];
    snprintf(name, sizeof name, "%s_%s", q->name, ver);
    const svp_image *est = scene_result_get(r, name);
    double sum = 0, sum_abs = 0, pk = 0;
    for (size_t p = 0; p < n; p++)
        if (mask->data[p] != 0) {
            sum += est->data[p];
            sum_abs += fabs(est->data[p]);
            pk = fmax(pk, fabs(est->data[p]));
        }
    double mean = n_pix ? sum / n_pix : NAN, mean_abs = n_pix ? sum_abs / n_pix : NAN;
    if (!n_pix) pk = NAN;
    if (v == 0) *true_mean_abs = mean_abs, *true_peak = pk;
    double mean_red = v ? 100 * (1 - mean_abs / *true_mean_abs) : NAN;
    double peak_red = v ? 100 * (1 - pk / *true_peak) : NAN;
    svp_status st = setv(r, n_pix, q->name, mk->name, ver, "n_pixels");
    if (st == SVP_OK) st = setv(r, mean, q->name, mk->name, ver, "mean");
    if (st == SVP_OK) st = setv(r, mean_abs, q->name, mk->name, ver, "mean_abs");
    if (st == SVP_OK) st = setv(r, pk, q->name, mk->name, ver, "peak_abs");
    double e_mean = NAN, e_mean_abs = NAN, e_rms = NAN, e_med = NAN, e_med_abs = NAN,
           e_p95 = NAN, e_max = NAN;
    size_t used = 0;
    if (v > 0) {
        st = st == SVP_OK ? setv(r, mean_red, q->name, mk->name, ver, "mean_reduction_pct") : st;
        st = st == SVP_OK ? setv(r, peak_red, q->name, mk->name, ver, "peak_reduction_pct") : st;
        snprintf(name, sizeof name, "err_%s_%s", q->name, ver);
        const svp_image *err = scene_result_get(r, name);
        double se = 0, sa = 0, s2 = 0;
        for (size_t p = 0; p < n; p++)
            if (mask->data[p] != 0 && isfinite(err->data[p])) {
                double e = 100 * err->data[p];
                buf[used] = e;
                abuf[used] = fabs(e);
                se += e, sa += fabs(e), s2 += e * e;
                used++;
            }
        if (used) {
            e_mean = se / used;
            e_mean_abs = sa / used;
            e_rms = sqrt(s2 / used);
            e_med = quantile(buf, used, 0.5);
            e_med_abs = quantile(abuf, used, 0.5);
            e_p95 = quantile(abuf, used, 0.95);
            e_max = 0;
            for (size_t i = 0; i < used; i++) e_max = fmax(e_max, abuf[i]);
        }
        /* histogram range: from the apparent version (all versions share it) */
        if (v == 1) {
            hist->hi = s->hist_range_pct > 0
                           ? s->hist_range_pct
                           : fmax(nice_ceil(used ? quantile(abuf, used, 0.99) : 1), 0.1);
            hist->lo = -hist->hi;
            hist->n_used = (int)used;
        }
        double *frac = hist->fraction + (size_t)(v - 1) * s->hist_bins;
        for (size_t i = 0; i < used; i++) {
            int b = (int)floor((buf[i] - hist->lo) / (hist->hi - hist->lo) * s->hist_bins);
            if (b < 0) b = 0;
            if (b >= s->hist_bins) b = s->hist_bins - 1;
            frac[b] += 1.0 / used;
        }
        const char *stats[] = {"n_used",
                               "mean_rel_err_pct",
                               "mean_abs_rel_err_pct",
                               "rms_rel_err_pct",
                               "median_rel_err_pct",
                               "median_abs_rel_err_pct",
                               "p95_abs_rel_err_pct",
                               "max_abs_rel_err_pct"};
        double vals[] = {(double)used, e_mean,    e_mean_abs, e_rms,
                         e_med,        e_med_abs, e_p95,      e_max};
        for (int k = 0; k < 8 && st == SVP_OK; k++)
            st = setv(r, vals[k], q->name, mk->name, ver, stats[k]);
    }
    double ds = q->display_scale;
    svp_strbuf_printf(&c->csv, "%s,%s,%s,%s,%zu,", q->name, ascii_unit(q), mk->name, ver, n_pix);
    if (v) svp_strbuf_printf(&c->csv, "%zu", used);
    svp_strbuf_printf(&c->csv, ",%.6g,%.6g,%.6g", mean * ds, mean_abs * ds, pk * ds);
    if (v)
        svp_strbuf_printf(&c->csv, ",%.4g,%.4g,%.4g,%.4g,%.4g,%.4g,%.4g,%.4g,%.4g\n", mean_red,
                          peak_red, e_mean, e_mean_abs, e_rms, e_med, e_med_abs, e_p95, e_max);
    else
        svp_strbuf_puts(&c->csv, ",,,,,,,,,\n");
    return st;
}

/* Quantity qi over mask m: every version's statistics, the ideal source's mean for a
 * reconstruction, and the histogram's lines of histograms.csv. */
static svp_status analyse_mask(analyse_ctx *c, int qi, int m)
{
    const svp_scene *s = c->s;
    scene_analysis *a = c->a;
    const scene_quantity *q = &a->q[qi];
    const scene_mask *mk = &s->masks[m];
    const size_t n = c->n;
    const int nv = a->nv;
    char name[128];
    snprintf(name, sizeof name, "mask_%s", mk->name);
    const svp_image *mask = scene_result_get(c->r, name);
    size_t n_pix = 0;
    for (size_t p = 0; p < n; p++) n_pix += mask->data[p] != 0;
    double true_mean_abs = 0, true_peak = 0;
    scene_hist *hist = &a->hists[qi * s->n_masks + m];
    hist->q = qi;
    hist->m = m;
    hist->bins = s->hist_bins;
    hist->fraction = calloc((size_t)(nv - 1) * s->hist_bins, sizeof(double));
    if (!hist->fraction) return svp_fail(SVP_ERR_NOMEM, "out of memory");
    svp_status st = SVP_OK;
    for (int v = 0; v < nv && st == SVP_OK; v++)
        st = analyse_version(c, qi, m, mask, n_pix, v, &true_mean_abs, &true_peak);
    /* the ideal source of a reconstruction (rasterised moment, strip current) */
    if (st == SVP_OK && q->recon >= 0) {
        const char *src =
            s->recon[q->recon].kind == RECON_MAGNETISATION ? "m_z_source" : "J_source_norm";
        const svp_image *img = scene_result_get(c->r, src);
        double sum = 0;
        for (size_t p = 0; p < n; p++)
            if (mask->data[p] != 0) sum += img->data[p];
        st = setv(c->r, n_pix ? sum / n_pix : NAN, q->name, mk->name, "source", "mean");
    }
    if (st != SVP_OK) return st;
    for (int b = 0; b < s->hist_bins; b++) {
        double lo = hist->lo + (hist->hi - hist->lo) * b / s->hist_bins;
        double hi = hist->lo + (hist->hi - hist->lo) * (b + 1) / s->hist_bins;
        svp_strbuf_printf(&c->hcsv, "%s,%s,%.6g,%.6g", q->name, mk->name, lo, hi);
        for (int v = 1; v < nv; v++)
            svp_strbuf_printf(&c->hcsv, ",%.6g",
                              hist->fraction[(size_t)(v - 1) * s->hist_bins + b]);
        svp_strbuf_puts(&c->hcsv, "\n");
    }
    return SVP_OK;
}

/* Line cut ci: the points along it, every quantity and version sampled there (bilinear,
 * display units), and its CSV. */
static svp_status analyse_cut(analyse_ctx *c, int ci)
{
    const svp_scene *s = c->s;
    scene_analysis *a = c->a;
    const int nq = a->nq, nv = a->nv, w = c->w, h = c->h;
    const scene_cut *cut = &s->cuts[ci];
    scene_cutdata *cd = &a->cuts[ci];
    double dx = cut->to_um[0] - cut->from_um[0], dy = cut->to_um[1] - cut->from_um[1];
    double len = hypot(dx, dy);
    int np = (int)floor(len / s->pixel_um + 1e-9) + 1;
    cd->n = np;
    cd->s_um = malloc((size_t)np * sizeof(double));
    cd->x_um = malloc((size_t)np * sizeof(double));
    cd->y_um = malloc((size_t)np * sizeof(double));
    cd->values = malloc((size_t)np * nq * nv * sizeof(double));
    if (!cd->s_um || !cd->x_um || !cd->y_um || !cd->values)
        return svp_fail(SVP_ERR_NOMEM, "out of memory");
    svp_strbuf cb;
    svp_strbuf_init(&cb);
    svp_strbuf_puts(&cb, "s_um,x_um,y_um");
    for (int qi = 0; qi < nq; qi++)
        for (int v = 0; v < nv; v++)
            svp_strbuf_printf(&cb, ",%s_%s_%s", a->q[qi].name, a->versions[v],
                              ascii_unit(&a->q[qi]));
    svp_strbuf_puts(&cb, "\n");
    for (int i = 0; i < np; i++) {
        double t = np > 1 ? (double)i * s->pixel_um / len : 0;
        cd->s_um[i] = t * len;
        cd->x_um[i] = cut->from_um[0] + t * dx;
        cd->y_um[i] = cut->from_um[1] + t * dy;
    }
    for (int qi = 0; qi < nq; qi++)
        for (int v = 0; v < nv; v++) {
            char name[128];
            snprintf(name, sizeof name, "%s_%s", a->q[qi].name, a->versions[v]);
            const svp_image *img = scene_result_get(c->r, name);
            for (int i = 0; i < np; i++) {
                double px = cd->x_um[i] / s->pixel_um + 0.5 * (w - 1);
                double py = cd->y_um[i] / s->pixel_um + 0.5 * (h - 1);
                cd->values[((size_t)qi * nv + v) * np + i] =
                    bilinear(img, px, py) * a->q[qi].display_scale;
            }
        }
    for (int i = 0; i < np; i++) {
        svp_strbuf_printf(&cb, "%.6g,%.6g,%.6g", cd->s_um[i], cd->x_um[i], cd->y_um[i]);
        for (int k = 0; k < nq * nv; k++)
            svp_strbuf_printf(&cb, ",%.8g", cd->values[(size_t)k * np + i]);
        svp_strbuf_puts(&cb, "\n");
    }
    a->cut_csv[ci] = take(&cb);
    if (!a->cut_csv[ci]) return svp_fail(SVP_ERR_NOMEM, "out of memory");
    return SVP_OK;
}

/* The metrics of a run, stage by stage: per quantity the colour ranges, the error maps and,
 * per mask, the statistics of every version; then the line cuts. */
svp_status scene_analyse(const svp_scene *s, svp_scene_result *r, scene_analysis *a)
{
    memset(a, 0, sizeof *a);
    analyse_ctx c;
    memset(&c, 0, sizeof c);
    c.s = s;
    c.r = r;
    c.a = a;
    c.w = s->view_w;
    c.h = s->view_h;
    c.n = (size_t)c.w * c.h;
    a->nq = scene_quantities(s, a->q);
    a->nv = scene_versions(s, a->versions);
    const int nq = a->nq, nv = a->nv, nm = s->n_masks;
    a->hists = calloc((size_t)nq * nm, sizeof *a->hists);
    c.buf = malloc(c.n * sizeof *c.buf);
    c.abuf = malloc(c.n * sizeof *c.abuf);
    if (!a->hists || !c.buf || !c.abuf) {
        free(c.buf), free(c.abuf);
        return svp_fail(SVP_ERR_NOMEM, "out of memory");
    }
    a->n_hists = nq * nm;
    svp_strbuf_init(&c.csv);
    svp_strbuf_init(&c.hcsv);
    svp_strbuf_puts(&c.csv, "quantity,unit,mask,version,n_pixels,n_used,mean,mean_abs,peak_abs,"
                            "mean_reduction_pct,peak_reduction_pct,mean_rel_err_pct,"
                            "mean_abs_rel_err_pct,rms_rel_err_pct,median_rel_err_pct,"
                            "median_abs_rel_err_pct,p95_abs_rel_err_pct,max_abs_rel_err_pct\n");
    svp_strbuf_puts(&c.hcsv, "quantity,mask,bin_lo_pct,bin_hi_pct");
    for (int v = 1; v < nv; v++) svp_strbuf_printf(&c.hcsv, ",%s", a->versions[v]);
    svp_strbuf_puts(&c.hcsv, "\n");
    svp_status st = SVP_OK;

    for (int qi = 0; qi < nq && st == SVP_OK; qi++) {
        const svp_image *truth = NULL;
        double peak = 0;
        st = analyse_range(&c, qi, &truth, &peak);
        if (st == SVP_OK) st = analyse_error_maps(&c, qi, truth, peak);
        for (int m = 0; m < nm && st == SVP_OK; m++) st = analyse_mask(&c, qi, m);
    }
    for (int ci = 0; ci < s->n_cuts && st == SVP_OK; ci++) st = analyse_cut(&c, ci);
    free(c.buf);
    free(c.abuf);
    a->metrics_csv = take(&c.csv);
    a->hist_csv = take(&c.hcsv);
    if (st == SVP_OK && (!a->metrics_csv || !a->hist_csv))
        st = svp_fail(SVP_ERR_NOMEM, "out of memory");
    return st;
}
