/* Scene figures and report: every figure of a scene's plan (maps, error maps, histograms, line
 * cuts; drawn by src/figure) and report.md. Every file is written atomically. */
#include "scene_internal.h"

#include "../figure/figure.h"
#include "../io/json.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* ---- all figures of a scene ------------------------------------------------------------- */

static void version_label(const char *v, char *buf, size_t size)
{
    if (!strncmp(v, "corrected_", 10))
        snprintf(buf, size, "corrected (%s)", v + 10);
    else
        snprintf(buf, size, "%s", v);
}

svp_status scene_figures(const svp_scene *s, const svp_scene_result *r, const scene_analysis *a,
                         const char *out_dir, int overwrite, svp_progress_fn progress,
                         void *progress_user)
{
    char path[4096], title[256], bar[128], name[128], vl[64];
    const int nq = a->nq, nv = a->nv;
    const int total = nq * nv * 2 + nq * s->n_masks + s->n_cuts * nq;
    int done = 0;
    for (int qi = 0; qi < nq; qi++) {
        const scene_quantity *q = &a->q[qi];
        for (int v = 0; v < nv; v++) {
            version_label(a->versions[v], vl, sizeof vl);
            snprintf(name, sizeof name, "%s_%s", q->name, a->versions[v]);
            snprintf(path, sizeof path, "%s/figures/%s.png", out_dir, name);
            snprintf(title, sizeof title, "%s, %s  (%s)", q->label, vl, s->name);
            snprintf(bar, sizeof bar, "%s (%s)", q->label, q->unit);
            SVP_CHECK(svp_figure_map(path, scene_result_get(r, name), q->display_scale,
                                       a->map_lo[qi], a->map_hi[qi], q->diverging, title, bar,
                                       s->pixel_um, overwrite));
            if (v > 0) {
                snprintf(name, sizeof name, "err_%s_%s", q->name, a->versions[v]);
                snprintf(path, sizeof path, "%s/figures/%s.png", out_dir, name);
                snprintf(title, sizeof title, "relative error of %s, %s", q->label, vl);
                snprintf(bar, sizeof bar, "(%s \xe2\x88\x92 true) / %s (%%)", q->name,
                         q->ref_local ? "|true|" : "peak |true|");
                SVP_CHECK(svp_figure_map(path, scene_result_get(r, name), 100,
                                           -a->err_range_pct[qi], a->err_range_pct[qi], 1, title,
                                           bar, s->pixel_um, overwrite));
            }
            if (progress && progress(progress_user, (double)(done += 2) / total))
                return svp_fail(SVP_ERR_CANCELLED, "cancelled");
        }
        /* histograms */
        for (int m = 0; m < s->n_masks; m++) {
            const scene_hist *hst = &a->hists[qi * s->n_masks + m];
            double *edges = malloc((size_t)(hst->bins + 1) * sizeof *edges);
            double *pct = malloc((size_t)(nv - 1) * hst->bins * sizeof *pct);
            char labels[SCENE_MAX_VERSIONS][64];
            svp_figure_series ser[SCENE_MAX_VERSIONS];
            if (!edges || !pct) {
                free(edges), free(pct);
                return svp_fail(SVP_ERR_NOMEM, "out of memory");
            }
            for (int b = 0; b <= hst->bins; b++)
                edges[b] = hst->lo + (hst->hi - hst->lo) * b / hst->bins;
            for (int v = 1; v < nv; v++) {
                for (int b = 0; b < hst->bins; b++)
                    pct[(size_t)(v - 1) * hst->bins + b] =
                        100 * hst->fraction[(size_t)(v - 1) * hst->bins + b];
                version_label(a->versions[v], labels[v], sizeof labels[v]);
                ser[v - 1] = (svp_figure_series){.x = edges,
                                                 .y = pct + (size_t)(v - 1) * hst->bins,
                                                 .n = hst->bins,
                                                 .label = labels[v],
                                                 .step = 1,
                                                 .width = 1.6};
                svp_figure_palette(v, ser[v - 1].rgb);
            }
            snprintf(path, sizeof path, "%s/figures/hist_%s_%s.png", out_dir, q->name,
                     s->masks[m].name);
            snprintf(title, sizeof title,
                     "relative error of %s over mask '%s' (%d px; end bins "
                     "hold all beyond)",
                     q->label, s->masks[m].name, hst->n_used);
            snprintf(bar, sizeof bar, "(%s \xe2\x88\x92 true) / %s (%%)", q->name,
                     q->ref_local ? "|true|" : "peak |true|");
            svp_status st =
                svp_figure_plot(path, title, bar, "pixels (%)", ser, nv - 1, overwrite);
            free(edges);
            free(pct);
            SVP_CHECK(st);
            if (progress && progress(progress_user, (double)(++done) / total))
                return svp_fail(SVP_ERR_CANCELLED, "cancelled");
        }
    }
    /* line cuts */
    for (int c = 0; c < s->n_cuts; c++) {
        const scene_cutdata *cd = &a->cuts[c];
        for (int qi = 0; qi < nq; qi++) {
            const scene_quantity *q = &a->q[qi];
            char labels[SCENE_MAX_VERSIONS][64];
            svp_figure_series ser[SCENE_MAX_VERSIONS];
            for (int v = 0; v < nv; v++) {
                version_label(a->versions[v], labels[v], sizeof labels[v]);
                ser[v] = (svp_figure_series){.x = cd->s_um,
                                             .y = cd->values + ((size_t)qi * nv + v) * cd->n,
                                             .n = cd->n,
                                             .label = labels[v],
                                             .width = v == 0 ? 2.2 : 1.5};
                svp_figure_palette(v, ser[v].rgb);
            }
            snprintf(path, sizeof path, "%s/figures/cut_%s_%s.png", out_dir, s->cuts[c].name,
                     q->name);
            snprintf(title, sizeof title, "%s along '%s' from (%g, %g) to (%g, %g) \xc2\xb5m",
                     q->label, s->cuts[c].name, s->cuts[c].from_um[0], s->cuts[c].from_um[1],
                     s->cuts[c].to_um[0], s->cuts[c].to_um[1]);
            snprintf(bar, sizeof bar, "%s (%s)", q->label, q->unit);
            SVP_CHECK(svp_figure_plot(path, title, "position along the cut (\xc2\xb5m)", bar, ser,
                                      nv, overwrite));
            if (progress && progress(progress_user, (double)(++done) / total))
                return svp_fail(SVP_ERR_CANCELLED, "cancelled");
        }
    }
    return SVP_OK;
}

/* ---- report.md ----------------------------------------------------------------------------- */

static double val(const svp_scene_result *r, const char *q, const char *m, const char *v,
                  const char *stat)
{
    char key[200];
    snprintf(key, sizeof key, "%s/%s/%s/%s", q, m, v, stat);
    double x = NAN;
    svp_scene_result_value(r, key, &x);
    return x;
}

static void num(svp_strbuf *b, double x, const char *fmt)
{
    if (isfinite(x))
        svp_strbuf_printf(b, fmt, x);
    else
        svp_strbuf_puts(b, "–");
}

/* A line for each correction in doubt (kept for the comparison, its doubtful pixels at
 * validity 0; its SVP_DOUBT_* bits in correct/<name>/doubts). */
static void report_doubts(svp_strbuf *b, const svp_scene_result *r)
{
    for (int i = 0; i < r->n_values; i++) {
        const char *k = r->keys[i];
        const size_t kl = strlen(k);
        if (strncmp(k, "correct/", 8) || kl < 16 || strcmp(k + kl - 7, "/doubts") ||
            !(r->values[i] > 0))
            continue;
        char list[256];
        svp_doubt_list((unsigned)r->values[i], list, sizeof list);
        svp_strbuf_printf(b,
                          "**In doubt:** correction `%.*s` (%s): a result the program cannot "
                          "vouch for, kept here for the comparison with its doubtful pixels at "
                          "validity 0 (docs/model.md §3, \"Results in doubt\").\n\n",
                          (int)(kl - 15), k + 8, list);
    }
}

svp_status scene_report_text(const svp_scene *s, const svp_scene_result *r, const scene_analysis *a,
                             char **text)
{
    svp_strbuf b;
    svp_strbuf_init(&b);
    svp_strbuf_printf(&b, "# Scene `%s`\n\n", s->name);
    if (s->description) svp_strbuf_printf(&b, "%s\n\n", s->description);
    svp_strbuf_printf(&b,
                      "Scene file `%s`. View %d x %d px of %g µm (%g x %g µm), simulated on a "
                      "%d x %d canvas (margin %g µm). PSF: %s. svpsf %s.\n\n",
                      s->path, s->view_w, s->view_h, s->pixel_um, s->view_w * s->pixel_um,
                      s->view_h * s->pixel_um, s->canvas_w, s->canvas_h, s->margin_px * s->pixel_um,
                      s->psf.describe, svp_version());
    svp_strbuf_puts(&b, "## Plan\n\n| # | stage | what it did | time (s) |\n|---|---|---|---|\n");
    double total = 0;
    for (int i = 0; i < s->n_stages; i++) {
        svp_strbuf_printf(&b, "| %d | %s | %s | %.3f |\n", i + 1, s->plan[i].name,
                          s->plan[i].detail, r->seconds[i]);
        total += r->seconds[i];
    }
    svp_strbuf_printf(&b, "\nTotal %.2f s on %d thread%s.\n\n", total, svp_get_threads(),
                      svp_get_threads() == 1 ? "" : "s");
    report_doubts(&b, r);
    /* headline table */
    svp_strbuf_puts(&b,
                    "## Errors\n\nRelative error = (map − true) / reference, the reference being "
                    "|true| pixel by pixel for the PL and reconstructions (pixels below "
                    "`local_floor` of the peak left out) and the peak |true| over the view for "
                    "field components. Reductions compare mean |·| and peak |·| over the mask "
                    "with the true map's (positive: the map is weaker than the truth).\n\n");
    for (int qi = 0; qi < a->nq; qi++) {
        const scene_quantity *q = &a->q[qi];
        svp_strbuf_printf(&b, "### %s (%s)\n\n", q->label, q->unit);
        svp_strbuf_puts(&b, "| mask | version | mean | peak abs | mean reduction % | peak "
                            "reduction % | median rel. err. % | median abs rel. err. % | p95 abs "
                            "rel. err. % |\n|---|---|---|---|---|---|---|---|---|\n");
        for (int m = 0; m < s->n_masks; m++) {
            const char *mn = s->masks[m].name;
            for (int v = 0; v < a->nv; v++) {
                const char *vn = a->versions[v];
                svp_strbuf_printf(&b, "| %s | %s | ", mn, vn);
                num(&b, val(r, q->name, mn, vn, "mean") * q->display_scale, "%.4g");
                svp_strbuf_puts(&b, " | ");
                num(&b, val(r, q->name, mn, vn, "peak_abs") * q->display_scale, "%.4g");
                const char *stats[] = {"mean_reduction_pct", "peak_reduction_pct",
                                       "median_rel_err_pct", "median_abs_rel_err_pct",
                                       "p95_abs_rel_err_pct"};
                for (int k = 0; k < 5; k++) {
                    svp_strbuf_puts(&b, " | ");
                    num(&b, v ? val(r, q->name, mn, vn, stats[k]) : NAN, "%.3g");
                }
                svp_strbuf_puts(&b, " |\n");
            }
            if (q->recon >= 0) {
                svp_strbuf_printf(&b, "| %s | ideal source | ", mn);
                num(&b, val(r, q->name, mn, "source", "mean") * q->display_scale, "%.4g");
                svp_strbuf_puts(&b, " | | | | | | |\n");
            }
        }
        svp_strbuf_puts(&b, "\n");
    }
    /* the cube's estimate against the closed form on the same maps */
    if (s->spectrum) {
        svp_strbuf_printf(&b,
                          "## The cube against the closed form\n\nThe apparent field above is "
                          "the %s of the blurred ODMR cube; the closed form (eq. 3, PL as I_m) "
                          "on the same maps differs from it by:\n\n",
                          s->estimator == 0 ? "spectral centroid" : "per-pixel Lorentzian fit");
        static const char *const cls[3] = {"contrast_uniform", "contrast_mixed_2_10pct",
                                           "contrast_varies"};
        static const char *const cls_text[3] = {"where blurring mixes contrasts by < 2 %",
                                                "where it mixes them by 2–10 %",
                                                "where it mixes them by > 10 %"};
        for (int k = 0; k < s->n_fields; k++) {
            const char *cn = scene_component_name(s->field_comp[k]);
            char key[160];
            double mean = NAN, mx = NAN;
            snprintf(key, sizeof key, "cube_vs_closed_form/B_%s/mean_abs_T", cn);
            svp_scene_result_value(r, key, &mean);
            snprintf(key, sizeof key, "cube_vs_closed_form/B_%s/max_abs_T", cn);
            svp_scene_result_value(r, key, &mx);
            svp_strbuf_printf(&b, "- B_%s: mean |difference| %.3g µT, max %.3g µT over the view",
                              cn, 1e6 * mean, 1e6 * mx);
            if (s->n_contrast_pattern) {
                for (int c = 0; c < 3; c++) {
                    double cm = NAN, frac = NAN;
                    snprintf(key, sizeof key, "cube_vs_closed_form/B_%s/%s/mean_abs_T", cn, cls[c]);
                    svp_scene_result_value(r, key, &cm);
                    snprintf(key, sizeof key, "cube_vs_closed_form/%s_fraction", cls[c]);
                    svp_scene_result_value(r, key, &frac);
                    if (isfinite(cm) && frac > 0)
                        svp_strbuf_printf(&b, "; %.3g µT %s (%.0f %% of the view)", 1e6 * cm,
                                          cls_text[c], 100 * frac);
                }
            }
            svp_strbuf_puts(&b, ".\n");
        }
        svp_strbuf_puts(&b, "\n");
    }
    /* other values */
    svp_strbuf_puts(&b, "## Other results\n\n");
    for (int i = 0; i < r->n_values; i++) {
        const char *k = r->keys[i];
        if (strchr(k, '/') && strncmp(k, "noise/", 6) && strncmp(k, "cube", 4) &&
            strncmp(k, "correct/", 8) && strncmp(k, "sources/", 8) && strncmp(k, "emission/", 9) &&
            strncmp(k, "operator/", 9))
            continue;
        svp_strbuf_printf(&b, "- `%s` = %.6g\n", k, r->values[i]);
    }
    if (s->write_figures) {
        svp_strbuf_puts(&b, "\n## Figures\n\n");
        for (int qi = 0; qi < a->nq; qi++) {
            const scene_quantity *q = &a->q[qi];
            svp_strbuf_printf(&b, "### %s\n\n", q->label);
            for (int v = 0; v < a->nv; v++)
                svp_strbuf_printf(&b, "![%s %s](figures/%s_%s.png)\n", q->name, a->versions[v],
                                  q->name, a->versions[v]);
            svp_strbuf_puts(&b, "\n");
            for (int v = 1; v < a->nv; v++)
                svp_strbuf_printf(&b, "![error %s %s](figures/err_%s_%s.png)\n", q->name,
                                  a->versions[v], q->name, a->versions[v]);
            svp_strbuf_puts(&b, "\n");
            for (int m = 0; m < s->n_masks; m++)
                svp_strbuf_printf(&b, "![histogram %s %s](figures/hist_%s_%s.png)\n", q->name,
                                  s->masks[m].name, q->name, s->masks[m].name);
            for (int c = 0; c < s->n_cuts; c++)
                svp_strbuf_printf(&b, "![cut %s %s](figures/cut_%s_%s.png)\n", s->cuts[c].name,
                                  q->name, s->cuts[c].name, q->name);
            svp_strbuf_puts(&b, "\n");
        }
    }
    svp_strbuf_puts(&b, "Tables: `tables/metrics.csv` (every statistic), `tables/histograms.csv`, "
                        "`tables/cut_*.csv`; machine-readable summary: `summary.json`.\n");
    if (b.failed) {
        svp_strbuf_free(&b);
        return svp_fail(SVP_ERR_NOMEM, "out of memory (report)");
    }
    *text = b.data;
    return SVP_OK;
}
