/* The plan of a scene: the quantities and versions it compares, the stages a run goes through
 * (scene_stage, the table in scene_internal.h) with what each does here, and the files it
 * writes (docs/scenes.md §The plan). The parsed scene comes from scene.c. */
#include "scene_internal.h"

#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *const model_names[] = SCENE_PSF_MODEL_NAMES;
static const char *const boundary_names[] = SCENE_BOUNDARY_NAMES;

static char *dup_text(const char *s)
{
    size_t n = strlen(s);
    char *c = malloc(n + 1);
    if (c) memcpy(c, s, n + 1);
    return c;
}

const char *scene_component_name(int comp)
{
    static const char *const names[] = {"x", "y", "z", "nv"};
    return comp >= 0 && comp < 4 ? names[comp] : "?";
}

/* ---- quantities, versions ------------------------------------------------------------------ */

int scene_quantities(const struct svp_scene *s, scene_quantity *q)
{
    int n = 0;
    memset(q, 0, sizeof *q * SCENE_MAX_QUANTITIES);
    snprintf(q[n].name, sizeof q[n].name, "pl");
    snprintf(q[n].label, sizeof q[n].label, "PL");
    snprintf(q[n].unit, sizeof q[n].unit, "a.u.");
    q[n].display_scale = 1;
    q[n].ref_local = 1;
    q[n].field = q[n].recon = -1;
    n++;
    for (int k = 0; k < s->n_fields; k++) {
        const char *c = scene_component_name(s->field_comp[k]);
        snprintf(q[n].name, sizeof q[n].name, "B_%s", c);
        snprintf(q[n].label, sizeof q[n].label, "B_%s", c);
        snprintf(q[n].unit, sizeof q[n].unit, "\xc2\xb5T");
        q[n].display_scale = 1e6;
        q[n].diverging = 1;
        q[n].field = k;
        q[n].recon = -1;
        n++;
    }
    for (int r = 0; r < s->n_recon; r++) {
        snprintf(q[n].name, sizeof q[n].name, "%s", s->recon[r].name);
        if (s->recon[r].kind == RECON_MAGNETISATION) {
            snprintf(q[n].label, sizeof q[n].label, "m_z = M_z t");
            snprintf(q[n].unit, sizeof q[n].unit, "mA");
            q[n].display_scale = 1e3;
            q[n].diverging = 1;
        } else {
            snprintf(q[n].label, sizeof q[n].label, "|J| (from %s)",
                     s->recon[r].kind == RECON_CURRENT_BZ ? "B_z" : "B_x, B_y");
            snprintf(q[n].unit, sizeof q[n].unit, "A/m");
            q[n].display_scale = 1;
        }
        q[n].ref_local = 1;
        q[n].field = -1;
        q[n].recon = r;
        n++;
    }
    return n;
}

int scene_versions(const struct svp_scene *s, char names[][48])
{
    int n = 0;
    snprintf(names[n++], 48, "true");
    snprintf(names[n++], 48, "apparent");
    for (int k = 0; k < s->n_correct; k++)
        snprintf(names[n++], 48, "corrected_%s", s->correct[k].name);
    return n;
}

/* ---- the plan ------------------------------------------------------------------------------ */

static svp_status add_stage(struct svp_scene *s, scene_stage stage, int index, const char *fmt,
                            ...) SVP_PRINTF(4, 5);

static svp_status add_stage(struct svp_scene *s, scene_stage stage, int index, const char *fmt,
                            ...)
{
    scene_stage_entry *p = realloc(s->plan, (size_t)(s->n_stages + 1) * sizeof *p);
    if (!p) return svp_fail(SVP_ERR_NOMEM, "out of memory");
    s->plan = p;
    scene_stage_entry *e = &p[s->n_stages++];
    e->stage = stage;
    e->index = index;
    snprintf(e->name, sizeof e->name, "%s", scene_stage_name(stage));
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(e->detail, sizeof e->detail, fmt, ap);
    va_end(ap);
    return SVP_OK;
}

static svp_status add_output(struct svp_scene *s, const char *fmt, ...) SVP_PRINTF(2, 3);

static svp_status add_output(struct svp_scene *s, const char *fmt, ...)
{
    char buf[256];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(buf, sizeof buf, fmt, ap);
    va_end(ap);
    char **o = realloc(s->outputs, (size_t)(s->n_outputs + 1) * sizeof *o);
    if (!o) return svp_fail(SVP_ERR_NOMEM, "out of memory");
    s->outputs = o;
    if (!(o[s->n_outputs] = dup_text(buf))) return svp_fail(SVP_ERR_NOMEM, "out of memory");
    s->n_outputs++;
    return SVP_OK;
}

static const char *factor_text(const scene_factor *f, char *buf, size_t size)
{
    switch (f->kind) {
    case EM_UNIFORM: snprintf(buf, size, "uniform %g", f->level); break;
    case EM_GAUSSIAN: snprintf(buf, size, "gaussian spot FWHM %g um", f->fwhm_um); break;
    case EM_CHESSBOARD:
        snprintf(buf, size, "chessboard %g um, %d levels", f->square_um, f->n_levels);
        break;
    case EM_QUENCH:
        snprintf(buf, size, "quench x%g under %s", f->factor,
                 f->under == UNDER_SOURCES  ? "sources"
                 : f->under == UNDER_FLAKES ? "flakes"
                 : f->under == UNDER_STRIPS ? "strips"
                                            : "a mask");
        break;
    case EM_IMAGE: snprintf(buf, size, "image"); break;
    case EM_FRINGES:
        snprintf(buf, size, "fringes period %g um, visibility %g", f->period_um, f->visibility);
        break;
    }
    return buf;
}

static const char *method_name(svp_method m)
{
    switch (m) {
    case SVP_METHOD_RW: return "R&W (RL on PL, Wiener on field x PL)";
    case SVP_METHOD_R: return "R (RL on both, signed shift)";
    case SVP_METHOD_W: return "W (Wiener on both)";
    case SVP_METHOD_RL_SIGNED: return "RL-signed";
    }
    return "?";
}

/* The stages, in the order they run, with what each does in this scene. */
static svp_status plan_stages(struct svp_scene *s)
{
    char buf[200];
    SVP_CHECK(add_stage(s, SCENE_STAGE_GRID, 0, "canvas %d x %d px of %g um (view %d x %d + margin %d px)",
                        s->canvas_w, s->canvas_h, s->pixel_um, s->view_w, s->view_h, s->margin_px));
    size_t len = 0;
    buf[0] = '\0';
    for (int i = 0; i < s->n_sources; i++) {
        const scene_source *src = &s->sources[i];
        const char *t = src->kind == SRC_FLAKE   ? "flake (Fourier method)"
                        : src->kind == SRC_STRIP ? "strip (analytic)"
                                                 : "field file";
        if (len < sizeof buf)
            len += (size_t)snprintf(buf + len, sizeof buf - len, "%s%s", i ? ", " : "", t);
    }
    SVP_CHECK(add_stage(s, SCENE_STAGE_SOURCES, 0, "true B_x, B_y, B_z on the canvas: %s", buf));
    if (scene_has_component(s, 3))
        SVP_CHECK(add_stage(s, SCENE_STAGE_PROJECTION, 0, "B_nv = B . [%.3g, %.3g, %.3g]", s->nv_axis[0],
                            s->nv_axis[1], s->nv_axis[2]));
    len = 0;
    buf[0] = '\0';
    for (int i = 0; i < s->n_emission; i++) {
        char t[96];
        if (len < sizeof buf)
            len += (size_t)snprintf(buf + len, sizeof buf - len, "%s%s", i ? " x " : "",
                                    factor_text(&s->emission[i], t, sizeof t));
    }
    SVP_CHECK(add_stage(s, SCENE_STAGE_EMISSION, 0, "true PL = %s", s->n_emission ? buf : "uniform 1"));
    if (s->psf.from_file)
        SVP_CHECK(add_stage(s, SCENE_STAGE_OPERATOR, 0, "%s, %s boundary", s->psf.describe,
                            boundary_names[s->psf.boundary]));
    else if (s->psf.n_regions > 0)
        SVP_CHECK(add_stage(s, SCENE_STAGE_OPERATOR, 0,
                            "space-variant: region PSFs (%s) blended over %g px, tent "
                            "overlap-add on %d x %d, %s boundary",
                            s->psf.describe, s->psf.transition_px, s->canvas_w, s->canvas_h,
                            boundary_names[s->psf.boundary]));
    else
        SVP_CHECK(add_stage(s, SCENE_STAGE_OPERATOR, 0,
                            "invariant: one OTF of the %s PSF (%s) on %d x %d, %s "
                            "boundary",
                            model_names[s->psf.psf.model], s->psf.describe, s->canvas_w,
                            s->canvas_h, boundary_names[s->psf.boundary]));
    if (!s->spectrum) {
        SVP_CHECK(add_stage(s, SCENE_STAGE_FORWARD, 0,
                            "closed form, eq. (3): PL~ = H PL, B~ = H(B PL) / PL~ "
                            "for %d component%s (no spectral cube)",
                            s->n_fields, s->n_fields > 1 ? "s" : ""));
        if (s->margin_px > 0)
            SVP_CHECK(
                add_stage(s, SCENE_STAGE_CROP, 0, "view %d x %d cut from the canvas", s->view_w, s->view_h));
        if (s->noise)
            SVP_CHECK(add_stage(s, SCENE_STAGE_NOISE, 0,
                                "shot noise, %g photons at the brightest pixel: PL "
                                "sigma sqrt(N), field sigma 0.77 Gamma / (gamma C sqrt(N)), "
                                "Gamma %g MHz, C %g, seed %llu",
                                s->photons, s->noise_linewidth_hz * 1e-6, s->noise_contrast,
                                (unsigned long long)s->noise_seed));
    } else {
        SVP_CHECK(add_stage(s, SCENE_STAGE_CUBE, 0,
                            "%d ODMR frames per component (linewidth %g MHz, contrast "
                            "%g%s): simulated, blurred by H frame by frame, cropped to the view",
                            s->spectrum_points, s->linewidth_hz * 1e-6, s->contrast,
                            s->n_contrast_pattern ? " x pattern" : ""));
        if (s->drift)
            SVP_CHECK(add_stage(s, SCENE_STAGE_DRIFT, 0,
                                "frames shifted linearly from 0 to [%g, %g] um over "
                                "the sweep",
                                s->drift_um[0], s->drift_um[1]));
        if (s->noise)
            SVP_CHECK(add_stage(s, SCENE_STAGE_NOISE, 0,
                                "shot noise on every frame, %g photons at the "
                                "brightest pixel over the sweep, seed %llu",
                                s->photons, (unsigned long long)s->noise_seed));
        SVP_CHECK(
            add_stage(s, SCENE_STAGE_ESTIMATE, 0, "%s per pixel of the blurred cube",
                      s->estimator ? "Lorentzian fit (Levenberg-Marquardt)" : "spectral centroid"));
        if (s->margin_px > 0)
            SVP_CHECK(
                add_stage(s, SCENE_STAGE_CROP, 0, "view %d x %d cut from the canvas", s->view_w, s->view_h));
        SVP_CHECK(add_stage(s, SCENE_STAGE_COMPARE, 0,
                            "closed form, eq. (3) on the same maps: how far the "
                            "cube estimate is from the fast path"));
    }
    for (int k = 0; k < s->n_correct; k++) {
        const scene_correct *c = &s->correct[k];
        char params[64];
        if (c->method == SVP_METHOD_W)
            snprintf(params, sizeof params, "balance %g", c->balance);
        else if (c->method == SVP_METHOD_RW)
            snprintf(params, sizeof params, "%d RL iterations, balance %g", c->iterations,
                     c->balance);
        else
            snprintf(params, sizeof params, "%d RL iterations", c->iterations);
        SVP_CHECK(add_stage(s, SCENE_STAGE_CORRECT, k, "'%s': T^-1 (eq. 4) by %s, %s%s%s", c->name,
                            method_name(c->method), params, c->has_psf ? ", assumed PSF " : "",
                            c->has_psf ? c->psf.describe : ""));
    }
    for (int r = 0; r < s->n_recon; r++) {
        const scene_recon *rc = &s->recon[r];
        SVP_CHECK(
            add_stage(s, SCENE_STAGE_RECONSTRUCT, r,
                      "%s from %s, standoff %g nm, %s window, on the true, "
                      "apparent%s maps",
                      rc->kind == RECON_MAGNETISATION ? "magnetisation m_z" : "current density J",
                      rc->kind == RECON_CURRENT_BXY ? "B_x, B_y" : "B_z", rc->standoff_nm,
                      rc->window ? "Hann" : "no", s->n_correct ? " and corrected" : ""));
    }
    SVP_CHECK(add_stage(s, SCENE_STAGE_METRICS, 0,
                        "relative errors over %d mask%s, histograms (%d bins), %d "
                        "line cut%s, peak and mean reductions",
                        s->n_masks, s->n_masks == 1 ? "" : "s", s->hist_bins, s->n_cuts,
                        s->n_cuts == 1 ? "" : "s"));
    if (s->write_figures)
        SVP_CHECK(add_stage(s, SCENE_STAGE_FIGURES, 0,
                            "PNG maps (colour bar, scale bar), histograms and line "
                            "cuts"));
    SVP_CHECK(add_stage(s, SCENE_STAGE_WRITE, 0, "%s%sCSV tables, report.md, summary.json",
                        s->write_maps ? "maps (" : "",
                        s->write_maps ? (s->format == SVP_FORMAT_TIFF  ? "tif), "
                                         : s->format == SVP_FORMAT_NPY ? "npy), "
                                                                       : "txt), ")
                                      : ""));

    s->stages = calloc((size_t)s->n_stages, sizeof *s->stages);
    if (!s->stages) return svp_fail(SVP_ERR_NOMEM, "out of memory");
    for (int i = 0; i < s->n_stages; i++) {
        s->stages[i].name = s->plan[i].name;
        s->stages[i].detail = s->plan[i].detail;
    }
    return SVP_OK;
}

/* The files a run writes, relative to the output folder. */
static svp_status plan_outputs(struct svp_scene *s)
{
    const char *ext = s->format == SVP_FORMAT_TIFF  ? "tif"
                      : s->format == SVP_FORMAT_NPY ? "npy"
                                                    : "txt";
    scene_quantity q[SCENE_MAX_QUANTITIES];
    char versions[SCENE_MAX_VERSIONS][48];
    int nq = scene_quantities(s, q), nv = scene_versions(s, versions);
    for (int i = 0; i < nq; i++)
        for (int v = 0; v < nv; v++) {
            if (s->write_maps) {
                SVP_CHECK(add_output(s, "maps/%s_%s.%s", q[i].name, versions[v], ext));
                if (q[i].recon >= 0 && s->recon[q[i].recon].kind != RECON_MAGNETISATION) {
                    SVP_CHECK(add_output(s, "maps/%s_x_%s.%s", q[i].name, versions[v], ext));
                    SVP_CHECK(add_output(s, "maps/%s_y_%s.%s", q[i].name, versions[v], ext));
                }
                if (v > 0)
                    SVP_CHECK(add_output(s, "maps/err_%s_%s.%s", q[i].name, versions[v], ext));
            }
            if (s->write_figures) {
                SVP_CHECK(add_output(s, "figures/%s_%s.png", q[i].name, versions[v]));
                if (v > 0)
                    SVP_CHECK(add_output(s, "figures/err_%s_%s.png", q[i].name, versions[v]));
            }
        }
    if (s->write_maps) {
        for (int k = 0; k < s->n_correct; k++)
            SVP_CHECK(add_output(s, "maps/validity_%s.%s", s->correct[k].name, ext));
        for (int m = 0; m < s->n_masks; m++)
            SVP_CHECK(add_output(s, "maps/mask_%s.%s", s->masks[m].name, ext));
        if (s->spectrum) {
            for (int k = 0; k < s->n_fields; k++)
                SVP_CHECK(add_output(s, "maps/B_%s_closed_form.%s",
                                     scene_component_name(s->field_comp[k]), ext));
            if (s->n_contrast_pattern) {
                SVP_CHECK(add_output(s, "maps/contrast.%s", ext));
                SVP_CHECK(add_output(s, "maps/contrast_mixing.%s", ext));
            }
        }
        if (s->write_canvas) {
            SVP_CHECK(add_output(s, "maps/canvas_pl_true.%s", ext));
            for (int k = 0; k < s->n_fields; k++)
                SVP_CHECK(add_output(s, "maps/canvas_B_%s_true.%s",
                                     scene_component_name(s->field_comp[k]), ext));
        }
    }
    if (s->write_figures) {
        for (int i = 0; i < nq; i++)
            for (int m = 0; m < s->n_masks; m++)
                SVP_CHECK(add_output(s, "figures/hist_%s_%s.png", q[i].name, s->masks[m].name));
        for (int c = 0; c < s->n_cuts; c++)
            for (int i = 0; i < nq; i++)
                SVP_CHECK(add_output(s, "figures/cut_%s_%s.png", s->cuts[c].name, q[i].name));
    }
    SVP_CHECK(add_output(s, "tables/metrics.csv"));
    SVP_CHECK(add_output(s, "tables/histograms.csv"));
    for (int c = 0; c < s->n_cuts; c++)
        SVP_CHECK(add_output(s, "tables/cut_%s.csv", s->cuts[c].name));
    SVP_CHECK(add_output(s, "report.md"));
    SVP_CHECK(add_output(s, "summary.json"));
    return SVP_OK;
}

svp_status scene_compile_plan(struct svp_scene *s)
{
    SVP_CHECK(plan_stages(s));
    return plan_outputs(s);
}

int svp_scene_plan(const svp_scene *s, const svp_scene_stage **stages)
{
    if (stages) *stages = s ? s->stages : NULL;
    return s ? s->n_stages : 0;
}

int svp_scene_has_stage(const svp_scene *s, const char *name)
{
    if (!s || !name) return 0;
    for (int i = 0; i < s->n_stages; i++)
        if (strcmp(scene_stage_name(s->plan[i].stage), name) == 0) return 1;
    return 0;
}
