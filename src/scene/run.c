/* Running a scene: the plan's stages in order, each only when the plan has it (scene.c compiles
 * the plan; docs/scenes.md describes each stage). Maps live in the result under their names. */
#include "scene_internal.h"

#include "../io/image_io.h"
#include "../io/json.h"
#include "../io/yaml.h"

#include <errno.h>
#include <stdarg.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <time.h>
#include <unistd.h>

#define GAMMA_NV_HZ_PER_T 28.033e9
/* Shot-noise-limited CW-ODMR field noise of a Lorentzian dip at its steepest slope:
 * σ_B = (4 / (3√3)) Γ / (γ C √N)  (Barry et al., Rev. Mod. Phys. 92, 015004 (2020), eq. 34). */
#define ODMR_NOISE_FACTOR 0.7698003589195010

void svp_scene_defaults(svp_scene_options *o)
{
    memset(o, 0, sizeof *o);
    o->write = 1;
    o->keep_maps = 1;
}

/* ---- the run context ----------------------------------------------------------------------- */

typedef struct run_ctx {
    const svp_scene *s;
    const svp_scene_options *o;
    svp_scene_result *r;
    const char *out_dir;
    int stage; /* index of the current plan stage */
    double t0; /* start of the current stage */
    double t_run;
    svp_blur *blur;                            /* canvas operator */
    svp_blur *blur_view;                       /* view operator of the scene's PSF (corrections) */
    svp_image *canvas_field[SCENE_MAX_FIELDS]; /* measured components, true, canvas */
    int cropped;
    int drift_stage, noise_stage; /* plan indices (cube path: timed inside the cube loop) */
    double drift_seconds, noise_seconds;
    double cube_seconds[SCENE_MAX_CORRECT]; /* method cube: its deconvolutions and estimates */
    int cube_margin[SCENE_MAX_CORRECT];
    scene_analysis analysis;
    int have_analysis;
} run_ctx;

static double now_s(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (double)ts.tv_sec + 1e-9 * (double)ts.tv_nsec;
}

static svp_status progress(run_ctx *c, double inner)
{
    if (!c->o->progress) return SVP_OK;
    double f = (c->stage + fmin(fmax(inner, 0), 1)) / c->s->n_stages;
    return svp_report_progress(c->o->progress, c->o->progress_user, f);
}

static int inner_progress(void *user, double fraction)
{
    run_ctx *c = user;
    return progress(c, fraction) != SVP_OK;
}

static svp_image *new_map(run_ctx *c, const char *name, int w, int h)
{
    return scene_result_new_map(c->r, name, w, h);
}

#define NEW_MAP(var, ctx, name, w, h)                                                              \
    do {                                                                                           \
        if (!((var) = new_map((ctx), (name), (w), (h))))                                           \
            return svp_fail_context(SVP_ERR_NOMEM, "scene map %s", (name));                        \
    } while (0)

static svp_image *get(run_ctx *c, const char *fmt, ...) SVP_PRINTF(2, 3);
static svp_image *get(run_ctx *c, const char *fmt, ...)
{
    char name[128];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(name, sizeof name, fmt, ap);
    va_end(ap);
    return scene_result_get(c->r, name);
}

static svp_status value(run_ctx *c, double v, const char *fmt, ...) SVP_PRINTF(3, 4);
static svp_status value(run_ctx *c, double v, const char *fmt, ...)
{
    char key[160];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(key, sizeof key, fmt, ap);
    va_end(ap);
    return scene_result_set(c->r, key, v);
}

static void add_into(svp_image *dst, const svp_image *src, double scale)
{
    size_t n = (size_t)dst->width * dst->height;
    double *restrict d = dst->data;
    const double *restrict x = src->data;
#pragma omp parallel for schedule(static)
    for (size_t i = 0; i < n; i++) d[i] += scale * x[i];
}

static svp_sensor sensor_for(const svp_scene *s, double standoff_nm)
{
    svp_sensor sn;
    svp_sensor_defaults(&sn);
    sn.pixel_m = s->pixel_um * 1e-6;
    sn.standoff_m = standoff_nm * 1e-9;
    sn.nv_thickness_m = s->nv_thickness_nm * 1e-9;
    sn.side = s->side;
    return sn;
}

/* The view cut out of a canvas map. */
static svp_status crop_into(const svp_scene *s, const svp_image *canvas, svp_image *view)
{
    for (int j = 0; j < s->view_h; j++)
        memcpy(view->data + (size_t)j * s->view_w,
               canvas->data + (size_t)(j + s->margin_px) * s->canvas_w + s->margin_px,
               (size_t)s->view_w * sizeof(double));
    return SVP_OK;
}

static svp_status crop_map(run_ctx *c, const char *canvas_name, const char *view_name)
{
    const svp_scene *s = c->s;
    svp_image *src = scene_result_get(c->r, canvas_name), *dst = NULL;
    if (!src) return svp_fail(SVP_ERR_INTERNAL, "scene: map %s missing", canvas_name);
    NEW_MAP(dst, c, view_name, s->view_w, s->view_h);
    return crop_into(s, src, dst);
}

/* ---- sources ------------------------------------------------------------------------------- */

static svp_status raster_flake(const svp_scene *s, const scene_source *src, svp_image *cover)
{
    double cx = scene_i_px(s, src->centre_um[0]), cy = scene_j_px(s, src->centre_um[1]);
    switch (src->shape) {
    case SHAPE_RECTANGLE:
        return svp_raster_rectangle(cover, cx, cy, src->size_um[0] / s->pixel_um,
                                    src->size_um[1] / s->pixel_um, src->angle_deg * M_PI / 180,
                                    1.0);
    case SHAPE_DISK:
        return svp_raster_disk(cover, cx, cy, 0.5 * src->diameter_um / s->pixel_um, 1.0);
    case SHAPE_POLYGON: {
        double *xy = malloc(2 * (size_t)src->n_vertices * sizeof *xy);
        if (!xy) return svp_fail(SVP_ERR_NOMEM, "out of memory");
        for (int i = 0; i < src->n_vertices; i++) {
            xy[2 * i] = scene_i_px(s, src->vertices_um[2 * i] + src->centre_um[0]);
            xy[2 * i + 1] = scene_j_px(s, src->vertices_um[2 * i + 1] + src->centre_um[1]);
        }
        svp_status st = svp_raster_polygon(cover, xy, src->n_vertices, 1.0);
        free(xy);
        return st;
    }
    case SHAPE_MASK: {
        svp_image *m = NULL;
        svp_status st = svp_image_read(src->mask_path, &m);
        if (st != SVP_OK) return svp_fail_context(st, "%s", src->where);
        if (m->width != cover->width || m->height != cover->height) {
            svp_image_free(m);
            return svp_fail(SVP_ERR_SIZE, "%s: the mask changed size since the scene was loaded",
                            src->where);
        }
        size_t n = (size_t)m->width * m->height;
        for (size_t i = 0; i < n; i++) {
            double v = m->data[i];
            double cov = isnan(src->mask_threshold) ? fmin(fmax(v, 0), 1)
                                                    : (v > src->mask_threshold ? 1.0 : 0.0);
            cover->data[i] += cov;
        }
        svp_image_free(m);
        return SVP_OK;
    }
    }
    return SVP_OK;
}

static svp_status stage_sources(run_ctx *c)
{
    const svp_scene *s = c->s;
    const int w = s->canvas_w, h = s->canvas_h;
    svp_image *b[3], *cover_f = NULL, *cover_s = NULL, *mz = NULL, *jx = NULL, *jy = NULL;
    NEW_MAP(b[0], c, "canvas_B_x_true", w, h);
    NEW_MAP(b[1], c, "canvas_B_y_true", w, h);
    NEW_MAP(b[2], c, "canvas_B_z_true", w, h);
    NEW_MAP(cover_f, c, "canvas_cover_flakes", w, h);
    NEW_MAP(cover_s, c, "canvas_cover_strips", w, h);
    NEW_MAP(mz, c, "canvas_m_z_source", w, h);
    NEW_MAP(jx, c, "canvas_J_x_source", w, h);
    NEW_MAP(jy, c, "canvas_J_y_source", w, h);
    svp_image *tmp[3] = {NULL, NULL, NULL}, *cover = NULL, *tj[2] = {NULL, NULL};
    svp_status st = SVP_OK;
    for (int k = 0; k < 3 && st == SVP_OK; k++) st = svp_image_new(w, h, &tmp[k]);
    if (st == SVP_OK) st = svp_image_new(w, h, &cover);
    for (int k = 0; k < 2 && st == SVP_OK; k++) st = svp_image_new(w, h, &tj[k]);
    for (int i = 0; i < s->n_sources && st == SVP_OK; i++) {
        const scene_source *src = &s->sources[i];
        svp_sensor sn = sensor_for(s, src->standoff_nm);
        if (src->kind == SRC_FLAKE) {
            memset(cover->data, 0, (size_t)w * h * sizeof(double));
            st = raster_flake(s, src, cover);
            if (st != SVP_OK) break;
            double moment = src->magnetisation_A_per_m * src->thickness_nm * 1e-9; /* A */
            size_t n = (size_t)w * h;
            for (size_t p = 0; p < n; p++) {
                cover_f->data[p] = fmin(1.0, cover_f->data[p] + cover->data[p]);
                mz->data[p] += moment * cover->data[p];
                cover->data[p] *= moment;
            }
            st = svp_flake_field(cover, src->thickness_nm * 1e-9, &sn, 2, tmp[0], tmp[1], tmp[2]);
        } else if (src->kind == SRC_STRIP) {
            svp_strip strip;
            svp_strip_defaults(&strip);
            strip.width_m = src->width_um * 1e-6;
            strip.sheet_current = src->sheet_current_A_per_m;
            strip.centre_x = scene_i_px(s, src->centre_um[0]);
            strip.centre_y = scene_j_px(s, src->centre_um[1]);
            strip.angle = src->angle_deg * M_PI / 180;
            st = svp_strip_field(&strip, &sn, tmp[0], tmp[1], tmp[2]);
            if (st == SVP_OK) st = svp_strip_current(&strip, sn.pixel_m, tj[0], tj[1]);
            if (st == SVP_OK) {
                add_into(jx, tj[0], 1);
                add_into(jy, tj[1], 1);
                size_t n = (size_t)w * h;
                double j = fabs(strip.sheet_current);
                if (!(j > 0)) {
                    /* a wire without current is still metal: it quenches the emission under
                     * it and makes the 'strips' masks (its cover, from a unit current) */
                    svp_strip unit = strip;
                    unit.sheet_current = 1;
                    j = 1;
                    st = svp_strip_current(&unit, sn.pixel_m, tj[0], tj[1]);
                }
                for (size_t p = 0; st == SVP_OK && p < n; p++)
                    cover_s->data[p] =
                        fmin(1.0, cover_s->data[p] + hypot(tj[0]->data[p], tj[1]->data[p]) / j);
            }
        } else {
            svp_image *f = NULL;
            st = svp_image_read(src->path, &f);
            if (st != SVP_OK) {
                st = svp_fail_context(st, "%s", src->where);
                break;
            }
            if (f->width == w && f->height == h) {
                for (int k = 0; k < 3; k++) memset(tmp[k]->data, 0, (size_t)w * h * sizeof(double));
                add_into(tmp[src->component], f, src->to_tesla);
            } else {
                st = svp_fail(SVP_ERR_SIZE, "%s: the field file changed size", src->where);
            }
            svp_image_free(f);
        }
        if (st != SVP_OK) {
            st = svp_fail_context(st, "%s", src->where);
            break;
        }
        for (int k = 0; k < 3; k++) add_into(b[k], tmp[k], 1);
    }
    for (int k = 0; k < 3; k++) svp_image_free(tmp[k]);
    svp_image_free(cover);
    svp_image_free(tj[0]);
    svp_image_free(tj[1]);
    if (st != SVP_OK) return st;
    /* the measured components (projection is its own stage) */
    for (int k = 0; k < s->n_fields; k++)
        if (s->field_comp[k] < 3) c->canvas_field[k] = b[s->field_comp[k]];
    double peak = 0;
    for (int k = 0; k < 3; k++)
        peak = fmax(peak,
                    fmax(svp_max(b[k]->data, (size_t)w * h), -svp_min(b[k]->data, (size_t)w * h)));
    return value(c, peak, "sources/peak_abs_B_T");
}

static svp_status stage_projection(run_ctx *c)
{
    const svp_scene *s = c->s;
    svp_image *nv = NULL;
    NEW_MAP(nv, c, "canvas_B_nv_true", s->canvas_w, s->canvas_h);
    SVP_CHECK(svp_field_project(get(c, "canvas_B_x_true"), get(c, "canvas_B_y_true"),
                                get(c, "canvas_B_z_true"), s->nv_axis, nv));
    for (int k = 0; k < s->n_fields; k++)
        if (s->field_comp[k] == 3) c->canvas_field[k] = nv;
    return SVP_OK;
}

/* ---- emission ------------------------------------------------------------------------------ */

static double square_level(const scene_factor *f, long long i, long long j)
{
    uint64_t x = f->seed * 0x9E3779B97F4A7C15ULL ^ ((uint64_t)i * 0xBF58476D1CE4E5B9ULL) ^
                 ((uint64_t)j * 0x94D049BB133111EBULL);
    x ^= x >> 31;
    x *= 0xD6E8FEB86659FD93ULL;
    x ^= x >> 32;
    x *= 0xD6E8FEB86659FD93ULL;
    x ^= x >> 32;
    return f->levels[x % (uint64_t)f->n_levels];
}

/* Multiplies map by the factors (canvas). */
static svp_status apply_factors(run_ctx *c, const scene_factor *f, int n, svp_image *map)
{
    const svp_scene *s = c->s;
    const int w = map->width, h = map->height;
    for (int i = 0; i < n; i++) {
        const scene_factor *e = &f[i];
        svp_image *img = NULL;
        if (e->kind == EM_IMAGE || (e->kind == EM_QUENCH && e->under == UNDER_MASK)) {
            svp_status st = svp_image_read(e->path, &img);
            if (st != SVP_OK) return svp_fail_context(st, "%s", e->where);
            if (img->width != w || img->height != h) {
                svp_image_free(img);
                return svp_fail(SVP_ERR_SIZE, "%s: the image changed size", e->where);
            }
        }
        const svp_image *cf = get(c, "canvas_cover_flakes"), *cs = get(c, "canvas_cover_strips");
        double ct = cos(e->angle_deg * M_PI / 180), sn = sin(e->angle_deg * M_PI / 180);
#pragma omp parallel for schedule(static)
        for (int j = 0; j < h; j++) {
            double y = scene_y_um(s, j);
            for (int ii = 0; ii < w; ii++) {
                size_t p = (size_t)j * w + ii;
                double x = scene_x_um(s, ii), v = 1;
                switch (e->kind) {
                case EM_UNIFORM: v = e->level; break;
                case EM_GAUSSIAN: {
                    double dx = x - e->centre_um[0], dy = y - e->centre_um[1];
                    v = exp(-4 * M_LN2 * (dx * dx + dy * dy) / (e->fwhm_um * e->fwhm_um));
                    break;
                }
                case EM_CHESSBOARD:
                    v = square_level(e, (long long)floor((x - e->offset_um[0]) / e->square_um),
                                     (long long)floor((y - e->offset_um[1]) / e->square_um));
                    break;
                case EM_QUENCH: {
                    double cov = e->under == UNDER_FLAKES   ? cf->data[p]
                                 : e->under == UNDER_STRIPS ? cs->data[p]
                                 : e->under == UNDER_MASK   ? fmin(fmax(img->data[p], 0), 1)
                                                            : fmin(1, cf->data[p] + cs->data[p]);
                    v = 1 - (1 - e->factor) * cov;
                    break;
                }
                case EM_IMAGE: v = img->data[p]; break;
                case EM_FRINGES: {
                    double xi = fmin(fmax(x * ct + y * sn, e->from_um), e->to_um);
                    v = 1 + e->visibility *
                                cos(2 * M_PI * xi / e->period_um + e->phase_deg * M_PI / 180);
                    break;
                }
                }
                map->data[p] *= v;
            }
        }
        svp_image_free(img);
    }
    return SVP_OK;
}

static svp_status stage_emission(run_ctx *c)
{
    const svp_scene *s = c->s;
    const int w = s->canvas_w, h = s->canvas_h;
    svp_image *pl = NULL;
    NEW_MAP(pl, c, "canvas_pl_true", w, h);
    for (size_t p = 0; p < (size_t)w * h; p++) pl->data[p] = 1;
    SVP_CHECK(apply_factors(c, s->emission, s->n_emission, pl));
    double mx = svp_max(pl->data, (size_t)w * h);
    if (!(mx > 0))
        return svp_fail(SVP_ERR_INVALID, "%s: emission: the PL is zero everywhere on the canvas",
                        s->path);
    if (s->spectrum) {
        svp_image *con = NULL;
        NEW_MAP(con, c, "canvas_contrast", w, h);
        for (size_t p = 0; p < (size_t)w * h; p++) con->data[p] = s->contrast;
        SVP_CHECK(apply_factors(c, s->contrast_pattern, s->n_contrast_pattern, con));
        double cmax = svp_max(con->data, (size_t)w * h);
        if (cmax > 0.5)
            return svp_fail(SVP_ERR_INVALID,
                            "%s: effects.spectrum: contrast x contrast_pattern reaches %g; a dip "
                            "contrast must stay in [0, 0.5]",
                            s->path, cmax);
    }
    return value(c, mx, "emission/pl_max");
}

/* ---- operator ------------------------------------------------------------------------------ */

/* Region-dependent PSF (psf.regions): labels from the shapes' coverage on the canvas or in the
 * view (w x h tells which), a regions field. */
static svp_status region_field(run_ctx *c, const scene_psf *p, int w, int h, svp_psf_field **out)
{
    const svp_scene *s = c->s;
    const int canvas = w == s->canvas_w && h == s->canvas_h;
    const svp_image *cf = get(c, canvas ? "canvas_cover_flakes" : "cover_flakes");
    const svp_image *cs = get(c, canvas ? "canvas_cover_strips" : "cover_strips");
    if (!cf || !cs || cf->width != w || cf->height != h)
        return svp_fail(SVP_ERR_INTERNAL, "%s: the shapes' coverage maps are missing", p->where);
    const size_t n = (size_t)w * h;
    int *labels = malloc(n * sizeof(int));
    if (!labels) return svp_fail(SVP_ERR_NOMEM, "out of memory for a label image");
    svp_psf psfs[5];
    psfs[0] = p->psf;
    for (int k = 0; k < p->n_regions; k++) psfs[k + 1] = p->region_psf[k];
    for (size_t i = 0; i < n; i++) {
        labels[i] = 0;
        for (int k = 0; k < p->n_regions; k++) {
            const double cov = p->region_under[k] == UNDER_FLAKES   ? cf->data[i]
                               : p->region_under[k] == UNDER_STRIPS ? cs->data[i]
                                                                    : cf->data[i] + cs->data[i];
            if (cov >= 0.5) labels[i] = k + 1;
        }
    }
    svp_status st =
        svp_psf_field_new_regions(w, h, labels, p->n_regions + 1, psfs, p->transition_px, out);
    free(labels);
    return st;
}

/* The PSF map of `p` for a w x h image (the canvas or the view): its regions, or a map file
 * with an image size; for one PSF (the model, or a map file of kind uniform) *out = NULL and
 * *one that PSF. */
static svp_status scene_field(run_ctx *c, const scene_psf *p, int w, int h, svp_psf_field **out,
                              svp_psf *one)
{
    *out = NULL;
    *one = p->psf;
    if (p->n_regions > 0) return region_field(c, p, w, h, out);
    if (!p->from_file) return SVP_OK;
    svp_status st = svp_psf_field_read(p->path, out, NULL);
    if (st == SVP_OK && svp_psf_field_width(*out) == 0) {
        st = svp_psf_field_at(*out, 0, 0, one);
        svp_psf_field_free(*out);
        *out = NULL;
    }
    return st;
}

/* The operator of `p` for a w x h image plus `margin` pixels per side (a map carried onto the
 * margin from its edge, svp_psf_field_pad): region PSFs as a tent operator on the scene's node
 * grid, a map file with the library's choice, one PSF invariant. */
static svp_status make_blur(run_ctx *c, const scene_psf *p, int w, int h, int margin,
                            svp_blur **out)
{
    svp_psf_field *field = NULL, *padded = NULL;
    svp_psf one;
    svp_status st = scene_field(c, p, w, h, &field, &one);
    if (st == SVP_OK && !field) {
        st = svp_blur_new(&one, w + 2 * margin, h + 2 * margin, p->boundary, out);
    } else if (st == SVP_OK) {
        /* the view's map as it is without a margin (no copy, no second blend) */
        if (margin > 0) st = svp_psf_field_pad(field, margin, &padded);
        svp_variant_options o;
        svp_variant_defaults(&o);
        if (p->n_regions > 0) {
            o.representation = SVP_VARIANT_TENT; /* the scene's node grid, as before */
            o.grid_x = p->nodes_x;
            o.grid_y = p->nodes_y;
        }
        if (st == SVP_OK)
            st = svp_blur_new_field(padded ? padded : field, w + 2 * margin, h + 2 * margin,
                                    p->boundary, p->n_regions > 0 ? &o : NULL, out);
    }
    svp_psf_field_free(field);
    svp_psf_field_free(padded);
    if (st != SVP_OK) return svp_fail_context(st, "%s", p->where);
    return SVP_OK;
}

static svp_status stage_operator(run_ctx *c)
{
    SVP_CHECK(make_blur(c, &c->s->psf, c->s->canvas_w, c->s->canvas_h, 0, &c->blur));
    return value(c, svp_blur_is_variant(c->blur), "operator/variant");
}

/* ---- forward (closed form) ------------------------------------------------------------------ */

static svp_status stage_forward(run_ctx *c)
{
    const svp_scene *s = c->s;
    const int w = s->canvas_w, h = s->canvas_h;
    svp_image *pl_app = NULL, *fa[SCENE_MAX_FIELDS];
    NEW_MAP(pl_app, c, "canvas_pl_apparent", w, h);
    for (int k = 0; k < s->n_fields; k++) {
        char name[64];
        snprintf(name, sizeof name, "canvas_B_%s_apparent", scene_component_name(s->field_comp[k]));
        NEW_MAP(fa[k], c, name, w, h);
    }
    return svp_forward_transform(c->blur, get(c, "canvas_pl_true"),
                                 (const svp_image *const *)c->canvas_field, s->n_fields, pl_app, fa,
                                 NULL);
}

/* ---- crop ---------------------------------------------------------------------------------- */

static svp_status stage_crop(run_ctx *c)
{
    const svp_scene *s = c->s;
    if (c->cropped) return SVP_OK;
    c->cropped = 1;
    SVP_CHECK(crop_map(c, "canvas_pl_true", "pl_true"));
    if (!s->spectrum) SVP_CHECK(crop_map(c, "canvas_pl_apparent", "pl_apparent"));
    for (int k = 0; k < s->n_fields; k++) {
        const char *cn = scene_component_name(s->field_comp[k]);
        char a[64], b[64];
        snprintf(a, sizeof a, "canvas_B_%s_true", cn);
        snprintf(b, sizeof b, "B_%s_true", cn);
        SVP_CHECK(crop_map(c, a, b));
        if (!s->spectrum) {
            snprintf(a, sizeof a, "canvas_B_%s_apparent", cn);
            snprintf(b, sizeof b, "B_%s_apparent", cn);
            SVP_CHECK(crop_map(c, a, b));
        }
    }
    SVP_CHECK(crop_map(c, "canvas_m_z_source", "m_z_source"));
    SVP_CHECK(crop_map(c, "canvas_J_x_source", "J_x_source"));
    SVP_CHECK(crop_map(c, "canvas_J_y_source", "J_y_source"));
    SVP_CHECK(crop_map(c, "canvas_cover_flakes", "cover_flakes"));
    SVP_CHECK(crop_map(c, "canvas_cover_strips", "cover_strips"));
    if (s->spectrum && s->n_contrast_pattern) SVP_CHECK(crop_map(c, "canvas_contrast", "contrast"));
    /* the masks as soon as their maps exist: an empty one stops the run before the corrections */
    return scene_make_masks(s, c->r);
}

/* ---- noise on the closed-form maps --------------------------------------------------------- */

static svp_status stage_noise(run_ctx *c)
{
    const svp_scene *s = c->s;
    if (s->spectrum) return SVP_OK; /* fell on the frames inside the cube loop */
    svp_image *pl = get(c, "pl_apparent");
    size_t n = (size_t)s->view_w * s->view_h;
    double mx = svp_max(pl->data, n);
    double scale = s->photons / mx; /* photons per PL unit */
    double sigma_b0 = ODMR_NOISE_FACTOR * s->noise_linewidth_hz /
                      (GAMMA_NV_HZ_PER_T * s->noise_contrast); /* T √photon */
    svp_image *fields[SCENE_MAX_FIELDS];
    for (int k = 0; k < s->n_fields; k++)
        fields[k] = get(c, "B_%s_apparent", scene_component_name(s->field_comp[k]));
    double *restrict pd = pl->data;
    const int nf = s->n_fields;
    const uint64_t seed = s->noise_seed;
#pragma omp parallel for schedule(static)
    for (size_t i = 0; i < n; i++) {
        double photons = fmax(pd[i] * scale, 0);
        /* the field noise follows the photons the pixel collected (at least one) */
        double sigma_b = sigma_b0 / sqrt(fmax(photons, 1));
        for (int k = 0; k < nf; k++)
            fields[k]->data[i] += sigma_b * scene_gauss(seed, 1 + (uint64_t)k, i);
        /* Gaussian shot noise, clipped at 0 as a count is: below ~30 photons its tail went
         * negative, which the RL-based corrections rightly refuse in a measured PL */
        pd[i] = fmax(pd[i] + sqrt(photons) / scale * scene_gauss(seed, 0, i), 0.0);
    }
    SVP_CHECK(value(c, s->photons, "noise/photons_per_pixel"));
    SVP_CHECK(value(c, sigma_b0 / sqrt(s->photons), "noise/sigma_B_at_brightest_T"));
    double peak = 0;
    for (int k = 0; k < s->n_fields; k++) {
        svp_image *t = get(c, "B_%s_true", scene_component_name(s->field_comp[k]));
        peak = fmax(peak, fmax(svp_max(t->data, n), -svp_min(t->data, n)));
    }
    SVP_CHECK(value(c, peak / (sigma_b0 / sqrt(s->photons)), "noise/field_snr"));
    return value(c, sqrt(s->photons), "noise/pl_snr");
}

/* ---- the cube ------------------------------------------------------------------------------- */

/* Frame f of n is displaced by f / (n − 1) × effects.drift.total_um, in pixels. */
static void drift_of(const svp_scene *s, int f, int n, double d[2])
{
    const double a = n > 1 ? (double)f / (n - 1) : 0;
    d[0] = a * s->drift_um[0] / s->pixel_um;
    d[1] = a * s->drift_um[1] / s->pixel_um;
}

/* The sample moves: frame f of n, blurred, translates by its drift (Fourier interpolation,
 * exact for the band-limited blurred frame); its time goes to the drift stage. */
static svp_status drift_frame(run_ctx *c, int f, int n, const svp_image *blurred,
                              svp_image *shifted)
{
    const double t = now_s();
    double d[2];
    drift_of(c->s, f, n, d);
    svp_status st = svp_shift(blurred, d[0], d[1], shifted);
    c->drift_seconds += now_s() - t;
    return st;
}

/* effects.drift.register: as a user would, the view's frames aligned before the estimate,
 * to frame 0's position (the drift's start, where the true maps are); its time goes to the
 * drift stage; how far each applied shift is from the drift simulated is recorded. */
static svp_status cube_register(run_ctx *c, svp_cube *view_cube, const char *cn)
{
    const svp_scene *s = c->s;
    const int nfreq = view_cube->n_freq;
    const double t = now_s();
    svp_align_options ao;
    svp_align_defaults(&ao);
    ao.reference_frame = 0;
    svp_align_info info;
    double *sx = malloc(2 * (size_t)nfreq * sizeof(double));
    if (!sx) return svp_fail(SVP_ERR_NOMEM, "out of memory");
    svp_status st = svp_cube_align(view_cube, &ao, sx, sx + nfreq, &info, NULL, NULL);
    double worst = 0;
    for (int f = 0; f < nfreq && st == SVP_OK; f++) {
        double d[2];
        drift_of(s, f, nfreq, d);
        worst = fmax(worst, hypot(sx[f] - d[0], sx[nfreq + f] - d[1]));
    }
    free(sx);
    c->drift_seconds += now_s() - t;
    if (st == SVP_OK && info.n_low_correlation)
        st = svp_fail(SVP_ERR_DOUBTFUL,
                      "%s: effects.drift.register: %d frames of B_%s correlate too weakly with "
                      "the mean frame to be aligned (lowest %.3g)",
                      s->path, info.n_low_correlation, cn, info.min_correlation);
    if (st == SVP_OK) st = value(c, info.max_shift, "cube/%s/register_max_shift_px", cn);
    if (st == SVP_OK) st = value(c, worst, "cube/%s/register_shift_error_px", cn);
    return st;
}

/* The per-pixel estimate of a cube (centroid with the baseline, or the Lorentzian fit), the
 * bias removed. A fit that did not converge (or found no dip the sweep shows) is NaN, missing
 * data, as `svpsf fit-odmr` writes it by default (--failed nan): its last parameters reached
 * 1e95 T on a noisy cube, and a correction of them blew up. */
static svp_status cube_estimate(const svp_scene *s, const svp_odmr *odmr, const svp_cube *cube,
                                const svp_image *baseline, double bias, svp_image *est,
                                size_t *failed)
{
    const size_t n = (size_t)cube->width * cube->height;
    *failed = 0;
    svp_status st;
    if (s->estimator == 0) {
        st = svp_odmr_centroid(odmr, cube, baseline, 0, 0, est, NULL);
    } else {
        svp_image *ok = NULL;
        st = svp_image_new(cube->width, cube->height, &ok);
        svp_odmr_maps maps = {.field = est, .converged = ok};
        if (st == SVP_OK) st = svp_odmr_fit_maps(odmr, cube, NULL, &maps, failed);
        for (size_t p = 0; p < n && st == SVP_OK; p++)
            if (!(ok->data[p] > 0)) est->data[p] = NAN;
        svp_image_free(ok);
    }
    for (size_t p = 0; p < n && st == SVP_OK; p++) est->data[p] -= bias;
    return st;
}

/* The baseline of a cube (the measured PL map): the mean of the 3 frames at each end of the
 * sweep (1 below 12 frames). */
static void cube_baseline(const svp_cube *cube, svp_image *baseline)
{
    const int nf = cube->n_freq, nend = nf >= 12 ? 3 : 1;
    for (size_t p = 0; p < (size_t)cube->width * cube->height; p++) {
        double b = 0;
        for (int e = 0; e < nend; e++)
            b += cube->frame[e]->data[p] + cube->frame[nf - 1 - e]->data[p];
        baseline->data[p] = b / (2 * nend);
    }
}

/* A measurement whose fits mostly fail has no apparent map to compare or correct: refused. */
static svp_status fits_mostly_failed(const svp_scene *s, size_t failed, int n, int nfreq,
                                     const char *cn)
{
    if (2 * failed <= (size_t)n) return SVP_OK;
    char why[160] = "";
    if (s->noise)
        snprintf(why, sizeof why, " (effects.noise: %g photons at the brightest pixel over %d "
                 "frames)", s->photons, nfreq);
    return svp_fail(SVP_ERR_INVALID,
                    "%s: %zu of the %d pixel fits of B_%s did not converge or found no dip in "
                    "the noise%s: the apparent map would be mostly missing; raise "
                    "effects.noise.photons_per_pixel or effects.spectrum.contrast, or use the "
                    "centroid estimator",
                    s->path, failed, n, cn, why);
}

static svp_status correct_margin(run_ctx *c, const scene_correct *cr, const scene_psf *psf,
                                 int w, int h, int *m);
/* Correction j of method cube, component k: a copy of the view's cube deconvolved frame by
 * frame (svp_cube_deconvolve, RL with the correction's iterations, on the view plus its
 * margin, the assumed PSF if it has one), then estimated as the apparent map was: the maps
 * B_<c>_corrected_<name> and, for the first component, pl_corrected_<name> (the deconvolved
 * cube's baseline) and validity_<name> (1; 0 where the estimate is not finite). */
static svp_status cube_correct(run_ctx *c, int j, int k, const svp_odmr *odmr,
                               const svp_cube *view_cube, double bias)
{
    const svp_scene *s = c->s;
    const scene_correct *cr = &s->correct[j];
    const scene_psf *psf = cr->has_psf ? &cr->psf : &s->psf;
    const int w = view_cube->width, h = view_cube->height, nf = view_cube->n_freq;
    const size_t n = (size_t)w * h;
    const char *cn = scene_component_name(s->field_comp[k]);
    const double t0 = now_s();
    int m = 0;
    SVP_CHECK(correct_margin(c, cr, psf, w, h, &m));
    c->cube_margin[j] = m;
    svp_cube *copy = NULL;
    svp_blur *op = NULL;
    svp_image *base = NULL;
    svp_status st = svp_cube_new(w, h, nf, view_cube->freq, &copy);
    for (int f = 0; f < nf && st == SVP_OK; f++)
        memcpy(copy->frame[f]->data, view_cube->frame[f]->data, n * sizeof(double));
    if (st == SVP_OK) st = make_blur(c, psf, w, h, m, &op);
    /* as `fit-odmr --psf`: one PSF's far tail on a coarse grid when cheaper */
    if (st == SVP_OK) st = svp_blur_set_tail(op, cr->tail_tol);
    svp_deconv_options o;
    svp_deconv_defaults(&o);
    o.iterations = cr->iterations;
    o.single_precision = cr->single;
    o.acceleration = cr->accelerated ? SVP_RL_BIGGS_ANDREWS : SVP_RL_PLAIN;
    if (st == SVP_OK) st = svp_cube_deconvolve(op, copy, m, &o, NULL, NULL, NULL);
    if (st == SVP_OK) st = svp_image_new(w, h, &base);
    char name[96];
    snprintf(name, sizeof name, "B_%s_corrected_%s", cn, cr->name);
    svp_image *est = st == SVP_OK ? new_map(c, name, w, h) : NULL;
    if (st == SVP_OK && !est) st = svp_fail(SVP_ERR_NOMEM, "out of memory");
    size_t failed = 0;
    if (st == SVP_OK) {
        cube_baseline(copy, base);
        st = cube_estimate(s, odmr, copy, base, bias, est, &failed);
    }
    if (st == SVP_OK && k == 0) {
        snprintf(name, sizeof name, "pl_corrected_%s", cr->name);
        svp_image *pl = new_map(c, name, w, h);
        snprintf(name, sizeof name, "validity_%s", cr->name);
        svp_image *valid = new_map(c, name, w, h);
        if (!pl || !valid) st = svp_fail(SVP_ERR_NOMEM, "out of memory");
        for (size_t p = 0; p < n && st == SVP_OK; p++) {
            pl->data[p] = base->data[p];
            valid->data[p] = isfinite(est->data[p]) ? 1 : 0;
        }
    }
    /* outputs are never NaN: a failed fit's pixel gets 0 with validity 0 */
    for (size_t p = 0; p < n && st == SVP_OK; p++)
        if (!isfinite(est->data[p])) est->data[p] = 0;
    svp_image_free(base);
    svp_blur_free(op);
    svp_cube_free(copy);
    c->cube_seconds[j] += now_s() - t0;
    if (st != SVP_OK) return svp_fail_context(st, "correction '%s' (%s)", cr->name, cr->where);
    return value(c, (double)failed, "correct/%s/fits_not_converged_%s", cr->name, cn);
}

static svp_status stage_cube(run_ctx *c)
{
    const svp_scene *s = c->s;
    const int cw = s->canvas_w, ch = s->canvas_h, vw = s->view_w, vh = s->view_h;
    const int nfreq = s->spectrum_points;
    const size_t ncanvas = (size_t)cw * ch, nview = (size_t)vw * vh;
    svp_odmr odmr;
    svp_odmr_defaults(&odmr);
    odmr.zero_field_hz = s->zero_field_hz;
    odmr.gamma_hz_per_t = GAMMA_NV_HZ_PER_T;
    odmr.linewidth_hz = s->linewidth_hz;
    odmr.contrast = s->contrast;
    svp_status st = SVP_OK;
    double *freq = malloc((size_t)nfreq * sizeof *freq);
    svp_cube *one = NULL, *view_cube = NULL;
    svp_image *field_nv = NULL, *blurred = NULL, *shifted = NULL, *baseline = NULL;
    svp_image *pl_blur = NULL, *pl_app = NULL;
    if (!freq) return svp_fail(SVP_ERR_NOMEM, "out of memory");
    NEW_MAP(pl_app, c, "pl_apparent", vw, vh);
    st = svp_image_new(cw, ch, &field_nv);
    if (st == SVP_OK) st = svp_image_new(cw, ch, &blurred);
    if (st == SVP_OK && s->drift) st = svp_image_new(cw, ch, &shifted);
    if (st == SVP_OK) st = svp_image_new(vw, vh, &baseline);
    if (st == SVP_OK) st = svp_image_new(cw, ch, &pl_blur);
    /* the blurred PL sets the photon scale of the noise */
    if (st == SVP_OK) st = svp_blur_apply(c->blur, get(c, "canvas_pl_true"), pl_blur);
    double pl_blur_max = 1;
    if (st == SVP_OK) {
        svp_image *tmp = NULL;
        st = svp_image_new(vw, vh, &tmp);
        if (st == SVP_OK) {
            crop_into(s, pl_blur, tmp);
            pl_blur_max = svp_max(tmp->data, nview);
        }
        svp_image_free(tmp);
    }
    const svp_image *contrast = s->n_contrast_pattern ? get(c, "canvas_contrast") : NULL;
    double total_failed = 0;
    for (int k = 0; k < s->n_fields && st == SVP_OK; k++) {
        const char *cn = scene_component_name(s->field_comp[k]);
        const svp_image *bk = c->canvas_field[k];
        double bmax = fmax(svp_max(bk->data, ncanvas), -svp_min(bk->data, ncanvas));
        double span_t = s->span_linewidths * s->linewidth_hz / GAMMA_NV_HZ_PER_T;
        /* bias along the measured axis: the upper dip alone lies inside the sweep, at least
         * span linewidths above D */
        double bias = s->bias_t > 0 ? s->bias_t : bmax + 2 * span_t;
        if (s->bias_t > 0 && !(bias - bmax > span_t)) {
            st = svp_fail(SVP_ERR_INVALID,
                          "%s: effects.spectrum.bias_mT = %g mT is too small for B_%s (|B| up to "
                          "%g mT): the dips must stay %g linewidths apart from D; use at least "
                          "%g mT",
                          s->path, 1e3 * s->bias_t, cn, 1e3 * bmax, s->span_linewidths,
                          1e3 * (bmax + span_t) * 1.01);
            break;
        }
        double lo = s->zero_field_hz + GAMMA_NV_HZ_PER_T * (bias - bmax) -
                    s->span_linewidths * s->linewidth_hz;
        double hi = s->zero_field_hz + GAMMA_NV_HZ_PER_T * (bias + bmax) +
                    s->span_linewidths * s->linewidth_hz;
        if ((hi - lo) / (nfreq - 1) > s->linewidth_hz) {
            st = svp_fail(SVP_ERR_INVALID,
                          "%s: effects.spectrum.points = %d samples the sweep of %.4g MHz (B_%s "
                          "up to %.4g mT) every %.3g MHz, coarser than the linewidth %g MHz: the "
                          "dips would fall between frames; use at least %d points",
                          s->path, nfreq, 1e-6 * (hi - lo), cn, 1e3 * bmax,
                          1e-6 * (hi - lo) / (nfreq - 1), 1e-6 * s->linewidth_hz,
                          (int)ceil((hi - lo) / s->linewidth_hz) + 1);
            break;
        }
        for (int f = 0; f < nfreq; f++) freq[f] = lo + (hi - lo) * f / (nfreq - 1);
        SVP_CHECK(value(c, bias, "cube/%s/bias_T", cn));
        SVP_CHECK(value(c, (hi - lo) / (nfreq - 1), "cube/%s/frequency_step_Hz", cn));
        for (size_t p = 0; p < ncanvas; p++) field_nv->data[p] = bk->data[p] + bias;
        svp_cube_free(one);
        svp_cube_free(view_cube);
        one = view_cube = NULL;
        st = svp_cube_new(cw, ch, 1, &freq[0], &one);
        if (st == SVP_OK) st = svp_cube_new(vw, vh, nfreq, freq, &view_cube);
        for (int f = 0; f < nfreq && st == SVP_OK; f++) {
            one->freq[0] = freq[f];
            st = svp_odmr_simulate(&odmr, get(c, "canvas_pl_true"), field_nv, contrast, NULL, one);
            if (st == SVP_OK) st = svp_blur_apply(c->blur, one->frame[0], blurred);
            if (st != SVP_OK) break;
            svp_image *frame = blurred;
            if (s->drift && (st = drift_frame(c, f, nfreq, blurred, shifted)) != SVP_OK) break;
            if (s->drift) frame = shifted;
            svp_image *vf = view_cube->frame[f];
            crop_into(s, frame, vf);
            if (s->noise) {
                double t = now_s();
                /* photons at the brightest pixel over the whole sweep: s->photons */
                double scale = s->photons / (nfreq * pl_blur_max);
                uint64_t stream = 100 + (uint64_t)k * 100000 + (uint64_t)f;
                double *restrict d = vf->data;
                const uint64_t seed = s->noise_seed;
#pragma omp parallel for schedule(static)
                for (size_t p = 0; p < nview; p++) {
                    double photons = fmax(d[p] * scale, 0);
                    d[p] = fmax(d[p] + sqrt(photons) / scale * scene_gauss(seed, stream, p),
                                0.0); /* a count: clipped at 0, as on the closed-form path */
                }
                c->noise_seconds += now_s() - t;
            }
            SVP_CHECK(progress(c, (k + (f + 1.0) / nfreq) / s->n_fields));
        }
        if (st != SVP_OK) break;
        if (s->drift_register) st = cube_register(c, view_cube, cn);
        if (st != SVP_OK) break;
        cube_baseline(view_cube, baseline);
        if (k == 0) memcpy(pl_app->data, baseline->data, nview * sizeof(double));
        char name[64];
        snprintf(name, sizeof name, "B_%s_apparent", cn);
        svp_image *est = new_map(c, name, vw, vh);
        if (!est) {
            st = svp_fail(SVP_ERR_NOMEM, "out of memory");
            break;
        }
        double t_est = now_s();
        size_t failed = 0;
        st = cube_estimate(s, &odmr, view_cube, baseline, bias, est, &failed);
        total_failed += (double)failed;
        if (st == SVP_OK && s->estimator)
            st = value(c, (double)failed, "cube/%s/fits_not_converged", cn);
        if (st == SVP_OK && s->estimator) st = fits_mostly_failed(s, failed, vw * vh, nfreq, cn);
        if (st == SVP_OK) st = value(c, now_s() - t_est, "cube/%s/estimate_seconds", cn);
        for (int j = 0; j < s->n_correct && st == SVP_OK; j++)
            if (s->correct[j].cube) st = cube_correct(c, j, k, &odmr, view_cube, bias);
    }
    svp_cube_free(one);
    svp_cube_free(view_cube);
    svp_image_free(field_nv);
    svp_image_free(blurred);
    svp_image_free(shifted);
    svp_image_free(baseline);
    svp_image_free(pl_blur);
    free(freq);
    (void)total_failed;
    return st;
}

/* The estimate runs inside the cube loop (one component's cube at a time); its time is in
 * cube/<c>/estimate_seconds and is moved to this stage. */
static svp_status stage_estimate(run_ctx *c)
{
    (void)c;
    return SVP_OK;
}

/* Closed form on the same maps, for comparison with the cube estimate. */
static svp_status stage_compare(run_ctx *c)
{
    const svp_scene *s = c->s;
    const int w = s->canvas_w, h = s->canvas_h;
    const size_t nview = (size_t)s->view_w * s->view_h;
    svp_image *pl_app = NULL, *fa[SCENE_MAX_FIELDS] = {NULL}, *ca = NULL, *cpl = NULL;
    svp_status st = svp_image_new(w, h, &pl_app);
    for (int k = 0; k < s->n_fields && st == SVP_OK; k++) st = svp_image_new(w, h, &fa[k]);
    if (st == SVP_OK)
        st = svp_forward_transform(c->blur, get(c, "canvas_pl_true"),
                                   (const svp_image *const *)c->canvas_field, s->n_fields, pl_app,
                                   fa, NULL);
    /* how much blurring mixes different contrasts: the relative contrast mixing
     * |H(C PL) / H(PL) − C| / C (0 where the contrast around a pixel is uniform) */
    svp_image *mixing = NULL;
    if (st == SVP_OK && s->n_contrast_pattern) {
        const svp_image *con = get(c, "canvas_contrast"), *pl = get(c, "canvas_pl_true");
        st = svp_image_new(w, h, &ca);
        if (st == SVP_OK) st = svp_image_new(w, h, &cpl);
        if (st == SVP_OK) {
            for (size_t p = 0; p < (size_t)w * h; p++) cpl->data[p] = con->data[p] * pl->data[p];
            st = svp_blur_apply(c->blur, cpl, ca);
        }
        if (st == SVP_OK) {
            for (size_t p = 0; p < (size_t)w * h; p++) {
                double m = pl_app->data[p] > 0 ? ca->data[p] / pl_app->data[p] : con->data[p];
                cpl->data[p] = fabs(m - con->data[p]) / fmax(con->data[p], 1e-12);
            }
            mixing = new_map(c, "contrast_mixing", s->view_w, s->view_h);
            if (!mixing)
                st = svp_fail(SVP_ERR_NOMEM, "out of memory");
            else
                crop_into(s, cpl, mixing);
        }
    }
    /* classes of mixing: below 2 % ("uniform"), 2–10 %, above 10 % ("varies") */
    static const char *const class_names[3] = {"contrast_uniform", "contrast_mixed_2_10pct",
                                               "contrast_varies"};
    for (int k = 0; k < s->n_fields && st == SVP_OK; k++) {
        const char *cn = scene_component_name(s->field_comp[k]);
        char name[64];
        snprintf(name, sizeof name, "B_%s_closed_form", cn);
        svp_image *cf = new_map(c, name, s->view_w, s->view_h);
        if (!cf) {
            st = svp_fail(SVP_ERR_NOMEM, "out of memory");
            break;
        }
        crop_into(s, fa[k], cf);
        const svp_image *cube = get(c, "B_%s_apparent", cn);
        double sum = 0, mx = 0, csum[3] = {0, 0, 0}, cmax[3] = {0, 0, 0};
        size_t cn_pix[3] = {0, 0, 0};
        for (size_t p = 0; p < nview; p++) {
            double d = fabs(cube->data[p] - cf->data[p]);
            sum += d;
            mx = fmax(mx, d);
            if (mixing) {
                double m = mixing->data[p];
                int cl = m < 0.02 ? 0 : m <= 0.1 ? 1 : 2;
                csum[cl] += d;
                cmax[cl] = fmax(cmax[cl], d);
                cn_pix[cl]++;
            }
        }
        st = value(c, sum / nview, "cube_vs_closed_form/B_%s/mean_abs_T", cn);
        if (st == SVP_OK) st = value(c, mx, "cube_vs_closed_form/B_%s/max_abs_T", cn);
        for (int cl = 0; cl < 3 && mixing && st == SVP_OK; cl++) {
            st = value(c, cn_pix[cl] ? csum[cl] / cn_pix[cl] : NAN,
                       "cube_vs_closed_form/B_%s/%s/mean_abs_T", cn, class_names[cl]);
            if (st == SVP_OK)
                st = value(c, cn_pix[cl] ? cmax[cl] : NAN, "cube_vs_closed_form/B_%s/%s/max_abs_T",
                           cn, class_names[cl]);
            if (st == SVP_OK)
                st = value(c, (double)cn_pix[cl] / nview, "cube_vs_closed_form/%s_fraction",
                           class_names[cl]);
        }
    }
    svp_image_free(pl_app);
    for (int k = 0; k < SCENE_MAX_FIELDS; k++) svp_image_free(fa[k]);
    svp_image_free(ca);
    svp_image_free(cpl);
    return st;
}

/* ---- corrections ---------------------------------------------------------------------------- */

/* The margin of correction `cr` in pixels: its own, or for `auto` the PSF's significant reach
 * (svp_psf_reach at 1 % of the peak, at most a quarter of the view's larger side, as `svpsf
 * correct --margin auto`; a PSF map's widest, svp_psf_field_auto_margin) with the zero
 * boundary, else 0; a map is carried onto the margin from its edge (make_blur). */
static svp_status correct_margin(run_ctx *c, const scene_correct *cr, const scene_psf *psf,
                                 int w, int h, int *m)
{
    if (cr->margin_px >= 0) {
        if (cr->margin_px > 0 && psf->boundary != SVP_BOUNDARY_ZERO)
            return svp_fail(SVP_ERR_INVALID, "%s: a margin needs the zero boundary", cr->where);
        *m = cr->margin_px;
        return SVP_OK;
    }
    *m = 0;
    if (psf->boundary != SVP_BOUNDARY_ZERO) return SVP_OK;
    svp_psf_field *field = NULL;
    svp_psf one;
    SVP_CHECK(scene_field(c, psf, w, h, &field, &one));
    *m = field ? svp_psf_field_auto_margin(field, w, h) : svp_psf_auto_margin(&one, w, h);
    svp_psf_field_free(field);
    return SVP_OK;
}

static svp_status stage_correct(run_ctx *c)
{
    const int k = c->s->plan[c->stage].index;
    const svp_scene *s = c->s;
    const scene_correct *cr = &s->correct[k];
    const int w = s->view_w, h = s->view_h;
    const scene_psf *psf = cr->has_psf ? &cr->psf : &s->psf;
    if (cr->cube) { /* done in the cube loop (stage_cube): its time and margin */
        SVP_CHECK(value(c, (double)c->cube_margin[k], "correct/%s/margin_px", cr->name));
        SVP_CHECK(value(c, 0, "correct/%s/doubts", cr->name));
        return value(c, c->cube_seconds[k], "correct/%s/seconds", cr->name);
    }
    int m = 0;
    SVP_CHECK(correct_margin(c, cr, psf, w, h, &m));
    const double t0 = now_s(); /* the correction's time, its operator's build included */
    svp_blur *own = NULL, *blur = NULL;
    if (cr->has_psf || m > 0) {
        SVP_CHECK(make_blur(c, psf, w, h, m, &own));
        blur = own;
    } else {
        if (!c->blur_view) SVP_CHECK(make_blur(c, &s->psf, w, h, 0, &c->blur_view));
        blur = c->blur_view;
    }
    svp_correct_options o;
    svp_correct_defaults(&o);
    o.method = cr->method;
    o.deconv.iterations = cr->iterations;
    o.deconv.balance = cr->balance;
    o.deconv.progress = inner_progress;
    o.deconv.progress_user = c;
    o.pl_floor = cr->pl_floor;
    o.margin = m;
    o.deconv.single_precision = cr->single;
    o.deconv.acceleration = cr->accelerated ? SVP_RL_BIGGS_ANDREWS : SVP_RL_PLAIN;
    o.tail_tol = cr->tail_tol;
    /* a study compares corrections, doubtful ones included: kept (validity 0 where in doubt)
     * and their doubts recorded */
    svp_correct_summary summary;
    o.keep_doubtful = 1;
    o.summary = &summary;
    const svp_image *fa[SCENE_MAX_FIELDS];
    svp_image *fc[SCENE_MAX_FIELDS];
    svp_image *pl_c = NULL, *valid = NULL;
    char name[96];
    svp_status st = SVP_OK;
    snprintf(name, sizeof name, "pl_corrected_%s", cr->name);
    if (!(pl_c = new_map(c, name, w, h))) st = svp_fail(SVP_ERR_NOMEM, "out of memory");
    snprintf(name, sizeof name, "validity_%s", cr->name);
    if (st == SVP_OK && !(valid = new_map(c, name, w, h)))
        st = svp_fail(SVP_ERR_NOMEM, "out of memory");
    for (int i = 0; i < s->n_fields && st == SVP_OK; i++) {
        const char *cn = scene_component_name(s->field_comp[i]);
        fa[i] = get(c, "B_%s_apparent", cn);
        snprintf(name, sizeof name, "B_%s_corrected_%s", cn, cr->name);
        if (!(fc[i] = new_map(c, name, w, h))) st = svp_fail(SVP_ERR_NOMEM, "out of memory");
    }
    size_t n_missing = 0;
    if (st == SVP_OK)
        st = svp_inverse_transform(blur, get(c, "pl_apparent"), fa, s->n_fields, &o, pl_c, fc,
                                   valid, &n_missing);
    const double seconds = now_s() - t0;
    if (st != SVP_OK) st = svp_fail_context(st, "correction '%s' (%s)", cr->name, cr->where);
    svp_blur_free(own);
    if (st != SVP_OK) return st;
    double low = 0;
    for (size_t p = 0; p < (size_t)w * h; p++) low += valid->data[p] < 1;
    SVP_CHECK(value(c, (double)m, "correct/%s/margin_px", cr->name));
    SVP_CHECK(value(c, (double)summary.doubts, "correct/%s/doubts", cr->name));
    SVP_CHECK(value(c, (double)summary.n_implausible, "correct/%s/n_implausible", cr->name));
    SVP_CHECK(value(c, seconds, "correct/%s/seconds", cr->name));
    /* the PSF's far tail on a coarse grid: node spacing (0: the plain frame) */
    SVP_CHECK(value(c, (double)summary.tail_step, "correct/%s/tail_step_px", cr->name));
    return value(c, low / ((double)w * h), "correct/%s/low_validity_fraction", cr->name);
}

/* ---- reconstruction ------------------------------------------------------------------------ */

/* A field map with missing pixels (NaN: fits that failed) for the reconstruction, which needs a
 * complete map: a copy (*filled, to free) with each missing pixel the mean of its measured
 * 3 x 3 neighbours, ring by ring inwards (svp_fill_nan); *n_missing counts them. The map
 * itself when complete (*filled NULL). */
static svp_status recon_source(const svp_image *map, svp_image **filled, size_t *n_missing)
{
    *filled = NULL;
    *n_missing = map ? svp_image_count_nonfinite(map) : 0;
    if (!*n_missing) return SVP_OK;
    const int w = map->width, h = map->height;
    const size_t n = (size_t)w * h;
    if (*n_missing == n)
        return svp_fail(SVP_ERR_INVALID, "every pixel of the field map is missing (NaN)");
    SVP_CHECK(svp_image_new(w, h, filled));
    for (size_t p = 0; p < n; p++)
        (*filled)->data[p] = isfinite(map->data[p]) ? map->data[p] : NAN;
    /* w + h rings reach every pixel from any measured one */
    svp_status st = svp_fill_nan((*filled)->data, w, h, w + h, 0.0);
    if (st != SVP_OK) {
        svp_image_free(*filled);
        *filled = NULL;
    }
    return st;
}

/* NaN where the field maps the reconstruction came from were missing (filled only for it) */
static void recon_mark_missing(svp_image *out, const svp_image *a, const svp_image *b)
{
    if (!out) return;
    for (size_t p = 0; p < (size_t)out->width * out->height; p++)
        if ((a && !isfinite(a->data[p])) || (b && !isfinite(b->data[p]))) out->data[p] = NAN;
}

static svp_status stage_reconstruct(run_ctx *c)
{
    const int r = c->s->plan[c->stage].index;
    const svp_scene *s = c->s;
    const scene_recon *rc = &s->recon[r];
    const int w = s->view_w, h = s->view_h;
    svp_recon_options o;
    svp_recon_defaults(&o);
    o.sensor = sensor_for(s, rc->standoff_nm);
    o.cutoff = rc->cutoff_per_um * 1e6;
    o.window = rc->window;
    o.pad = rc->pad;
    o.method = rc->method;
    char versions[SCENE_MAX_VERSIONS][48];
    int nv = scene_versions(s, versions);
    /* the component maps of one version by name suffix */
    for (int v = 0; v < nv; v++) {
        char vn[48], name[96];
        memcpy(vn, versions[v], sizeof vn); /* bounded: keeps the names' lengths visible */
        SVP_CHECK(progress(c, (double)v / nv));
        /* the maps it reads (B_z, or B_x and B_y) and writes (m_z, or J_x, J_y and |J|). A
         * version's field maps may miss pixels (failed fits of a spectrum, NaN): filled for the
         * reconstruction, NaN again in its results, counted */
        const int bxy = rc->kind == RECON_CURRENT_BXY;
        const svp_image *src[2] = {get(c, bxy ? "B_x_%s" : "B_z_%s", vn),
                                   bxy ? get(c, "B_y_%s", vn) : NULL};
        svp_image *out[3] = {NULL, NULL, NULL};
        if (rc->kind == RECON_MAGNETISATION) {
            snprintf(name, sizeof name, "m_z_%s", vn);
            NEW_MAP(out[0], c, name, w, h);
        } else {
            static const char *const parts[3] = {"_x", "_y", ""};
            for (int k = 0; k < 3; k++) {
                snprintf(name, sizeof name, "%s%s_%s", rc->name, parts[k], vn);
                NEW_MAP(out[k], c, name, w, h);
            }
        }
        svp_image *filled[2] = {NULL, NULL};
        size_t n_filled = 0;
        svp_status st = SVP_OK;
        for (int k = 0; k < 2 && st == SVP_OK; k++) {
            size_t m = 0;
            st = recon_source(src[k], &filled[k], &m);
            n_filled += m;
        }
        const svp_image *in[2] = {filled[0] ? filled[0] : src[0], filled[1] ? filled[1] : src[1]};
        if (st == SVP_OK)
            st = value(c, (double)n_filled, "reconstruct/%s/%s/filled_pixels", rc->name, vn);
        if (st == SVP_OK && rc->kind == RECON_MAGNETISATION)
            st = svp_reconstruct_magnetisation(in[0], &o, out[0]);
        else if (st == SVP_OK && rc->kind == RECON_CURRENT_BZ)
            st = svp_reconstruct_current_from_bz(in[0], &o, out[0], out[1]);
        else if (st == SVP_OK)
            st = svp_reconstruct_current_from_bxy(in[0], in[1], &o, in[1] ? out[0] : NULL,
                                                  in[0] ? out[1] : NULL);
        svp_image_free(filled[0]);
        svp_image_free(filled[1]);
        if (st != SVP_OK) return svp_fail_context(st, "reconstruction of %s", vn);
        if (out[2])
            for (size_t p = 0; p < (size_t)w * h; p++)
                out[2]->data[p] = hypot(out[0]->data[p], out[1]->data[p]);
        for (int k = 0; k < 3; k++) recon_mark_missing(out[k], src[0], src[1]);
    }
    if (rc->kind != RECON_MAGNETISATION && !get(c, "J_source_norm")) {
        svp_image *jn = NULL;
        NEW_MAP(jn, c, "J_source_norm", w, h);
        const svp_image *jx = get(c, "J_x_source"), *jy = get(c, "J_y_source");
        for (size_t p = 0; p < (size_t)w * h; p++) jn->data[p] = hypot(jx->data[p], jy->data[p]);
    }
    return SVP_OK;
}

/* ---- outputs -------------------------------------------------------------------------------- */

static svp_status make_dir(const char *path)
{
    if (mkdir(path, 0777) == 0 || errno == EEXIST) {
        struct stat stt;
        if (stat(path, &stt) == 0 && S_ISDIR(stt.st_mode)) return SVP_OK;
        return svp_fail(SVP_ERR_IO, "%s exists and is not a folder", path);
    }
    return svp_fail(SVP_ERR_IO, "%s: cannot create the folder (%s)", path, strerror(errno));
}

static svp_status make_dirs(const char *path)
{
    char buf[4096];
    snprintf(buf, sizeof buf, "%s", path);
    for (char *p = buf + 1; *p; p++)
        if (*p == '/') {
            *p = '\0';
            struct stat stt;
            if (stat(buf, &stt) != 0) SVP_CHECK(make_dir(buf));
            *p = '/';
        }
    return make_dir(buf);
}

/* `absent[i]` (when not NULL) is set to whether output i did not exist: what a failed run removes
 * again (remove_new_outputs). */
static svp_status check_outputs(const svp_scene *s, const char *out_dir, int overwrite,
                                unsigned char *absent)
{
    int existing = 0;
    char first[4096] = "";
    for (int i = 0; i < s->n_outputs; i++) {
        char path[4096];
        snprintf(path, sizeof path, "%s/%s", out_dir, s->outputs[i]);
        struct stat stt;
        int exists = stat(path, &stt) == 0;
        if (absent) absent[i] = !exists;
        if (!exists) continue;
        if (S_ISDIR(stt.st_mode))
            return svp_fail(SVP_ERR_EXISTS, "%s exists and is a folder", path);
        if (!overwrite && existing++ == 0) snprintf(first, sizeof first, "%s", path);
    }
    if (existing)
        return svp_fail(SVP_ERR_EXISTS,
                        "%s exists (use --force to overwrite)%s; nothing was written", first,
                        existing > 1 ? " and other outputs too" : "");
    return SVP_OK;
}

/* A run that fails after writing some outputs (a map a float32 TIFF cannot hold, a full disk)
 * removes those it created, so the folder holds all of a run's outputs or none (files that
 * existed before, overwritten, stay). */
static void remove_new_outputs(const svp_scene *s, const char *out_dir, const unsigned char *absent)
{
    for (int i = 0; i < s->n_outputs; i++) {
        if (!absent[i]) continue;
        char path[4096];
        snprintf(path, sizeof path, "%s/%s", out_dir, s->outputs[i]);
        unlink(path);
    }
}

static svp_status write_maps(run_ctx *c)
{
    const svp_scene *s = c->s;
    const char *ext = s->format == SVP_FORMAT_TIFF  ? ".tif"
                      : s->format == SVP_FORMAT_NPY ? ".npy"
                                                    : ".txt";
    for (int i = 0; i < s->n_outputs; i++) {
        const char *o = s->outputs[i];
        if (strncmp(o, "maps/", 5) != 0) continue;
        char name[256];
        snprintf(name, sizeof name, "%s", o + 5);
        char *dot = strrchr(name, '.');
        if (dot && strcmp(dot, ext) == 0) *dot = '\0';
        const svp_image *img = scene_result_get(c->r, name);
        if (!img) return svp_fail(SVP_ERR_INTERNAL, "scene: no map '%s' for %s", name, o);
        char path[4096];
        snprintf(path, sizeof path, "%s/%s", c->out_dir, o);
        SVP_CHECK(svp_image_write(path, img, s->format, c->o->overwrite));
    }
    return SVP_OK;
}

static svp_status write_text(run_ctx *c, const char *rel, const char *text)
{
    char path[4096];
    snprintf(path, sizeof path, "%s/%s", c->out_dir, rel);
    return svp_io_atomic_write_text(path, text, c->o->overwrite);
}

static svp_status write_summary(run_ctx *c, double total)
{
    const svp_scene *s = c->s;
    svp_json *j = NULL;
    SVP_CHECK(svp_json_new(&j));
    svp_json_begin_object(j);
    svp_json_key_int(j, "svpsf_summary", 1);
    svp_json_key_string(j, "command", "simulate");
    svp_json_key(j, "command_line");
    svp_json_begin_array(j);
    for (int i = 0; i < c->o->argc && c->o->argv; i++) svp_json_string(j, c->o->argv[i]);
    svp_json_end_array(j);
    /* the run's context, as every command's summary.json has it */
    svp_json_key_working_directory(j);
    svp_json_key_started_utc(j, total);
    svp_json_key(j, "inputs");
    svp_json_begin_array(j);
    if (s->path) {
        struct stat sb;
        svp_json_begin_object(j);
        svp_json_key_string(j, "role", "scene");
        svp_json_key_string(j, "path", s->path);
        if (stat(s->path, &sb) == 0) svp_json_key_int(j, "bytes", (long long)sb.st_size);
        svp_json_end_object(j);
    }
    svp_json_end_array(j);
    svp_json_key(j, "scene");
    svp_json_begin_object(j);
    svp_json_key_string(j, "path", s->path);
    svp_json_key_string(j, "name", s->name);
    svp_json_key_string(j, "description", s->description);
    svp_json_end_object(j);
    svp_json_key(j, "geometry");
    svp_json_begin_object(j);
    svp_json_key_number(j, "pixel_um", s->pixel_um);
    svp_json_key_int(j, "view_width", s->view_w);
    svp_json_key_int(j, "view_height", s->view_h);
    svp_json_key_int(j, "margin_px", s->margin_px);
    svp_json_key_int(j, "canvas_width", s->canvas_w);
    svp_json_key_int(j, "canvas_height", s->canvas_h);
    svp_json_end_object(j);
    svp_json_key(j, "plan");
    svp_json_begin_array(j);
    for (int i = 0; i < s->n_stages; i++) {
        svp_json_begin_object(j);
        svp_json_key_string(j, "stage", s->plan[i].name);
        svp_json_key_string(j, "detail", s->plan[i].detail);
        svp_json_key_number(j, "seconds", c->r->seconds[i]);
        svp_json_end_object(j);
    }
    svp_json_end_array(j);
    svp_json_key(j, "timings_s");
    svp_json_begin_object(j);
    for (int i = 0; i < s->n_stages; i++) {
        int first = 1;
        for (int k = 0; k < i; k++) first &= s->plan[k].stage != s->plan[i].stage;
        if (!first) continue;
        double sum = 0;
        for (int k = i; k < s->n_stages; k++)
            if (s->plan[k].stage == s->plan[i].stage) sum += c->r->seconds[k];
        svp_json_key_number(j, s->plan[i].name, sum);
    }
    svp_json_key_number(j, "total", total);
    svp_json_end_object(j);
    svp_json_key(j, "settings");
    svp_json_begin_object(j);
    svp_json_key_string(j, "psf", s->psf.describe);
    svp_json_key_string(j, "boundary",
                        s->psf.boundary == SVP_BOUNDARY_ZERO     ? "zero"
                        : s->psf.boundary == SVP_BOUNDARY_MIRROR ? "mirror"
                                                                 : "periodic");
    svp_json_key_bool(j, "noise", s->noise);
    svp_json_key_bool(j, "spectrum", s->spectrum);
    svp_json_key_bool(j, "drift", s->drift);
    svp_json_key(j, "corrections");
    svp_json_begin_array(j);
    for (int k = 0; k < s->n_correct; k++) {
        const scene_correct *cr = &s->correct[k];
        svp_json_begin_object(j);
        svp_json_key_string(j, "name", cr->name);
        svp_json_key_string(j, "method",
                            cr->method == SVP_METHOD_RW  ? "rw"
                            : cr->method == SVP_METHOD_R ? "r"
                            : cr->method == SVP_METHOD_W ? "w"
                                                         : "rl_signed");
        svp_json_key_int(j, "iterations", cr->iterations);
        svp_json_key_number(j, "balance", cr->balance);
        svp_json_key_number(j, "pl_floor", cr->pl_floor);
        if (cr->margin_px < 0)
            svp_json_key_string(j, "margin", "auto");
        else
            svp_json_key_int(j, "margin_px", cr->margin_px);
        svp_json_key_string(j, "precision", cr->single ? "single" : "double");
        svp_json_key_string(j, "acceleration", cr->accelerated ? "biggs-andrews" : "none");
        svp_json_key_number(j, "tail_tol", cr->tail_tol);
        if (cr->has_psf) svp_json_key_string(j, "psf", cr->psf.describe);
        svp_json_end_object(j);
    }
    svp_json_end_array(j);
    svp_json_end_object(j);
    svp_json_key(j, "results");
    svp_json_begin_object(j);
    for (int i = 0; i < c->r->n_values; i++) svp_json_key_number(j, c->r->keys[i], c->r->values[i]);
    svp_json_end_object(j);
    svp_json_key(j, "outputs");
    svp_json_begin_array(j);
    for (int i = 0; i < s->n_outputs; i++) svp_json_string(j, s->outputs[i]);
    svp_json_end_array(j);
    svp_json_key_versions(j);
    svp_json_key_int(j, "threads", svp_get_threads());
    svp_json_key_string(j, "fft_planning",
                        svp_get_fft_effort() == SVP_FFT_MEASURE ? "measure" : "estimate");
    svp_json_key_peak_memory(j);
    svp_json_end_object(j);
    char path[4096];
    snprintf(path, sizeof path, "%s/summary.json", c->out_dir);
    svp_status st = svp_json_write_file(j, path, c->o->overwrite);
    svp_json_free(j);
    return st;
}

static svp_status stage_write(run_ctx *c)
{
    const svp_scene *s = c->s;
    if (!c->o->write) return SVP_OK;
    if (s->write_maps) SVP_CHECK(write_maps(c));
    SVP_CHECK(write_text(c, "tables/metrics.csv", c->analysis.metrics_csv));
    SVP_CHECK(write_text(c, "tables/histograms.csv", c->analysis.hist_csv));
    for (int k = 0; k < s->n_cuts; k++) {
        char rel[96];
        snprintf(rel, sizeof rel, "tables/cut_%s.csv", s->cuts[k].name);
        SVP_CHECK(write_text(c, rel, c->analysis.cut_csv[k]));
    }
    return SVP_OK;
}

/* ---- the driver ----------------------------------------------------------------------------- */

/* The geometry was fixed at load; the drift runs inside the cube loop (timed there). */
static svp_status stage_grid(run_ctx *c)
{
    (void)c;
    return SVP_OK;
}

static svp_status stage_drift(run_ctx *c)
{
    (void)c;
    return SVP_OK;
}

static svp_status stage_metrics(run_ctx *c)
{
    SVP_CHECK(scene_make_masks(c->s, c->r));
    c->have_analysis = 1;
    return scene_analyse(c->s, c->r, &c->analysis);
}

static svp_status stage_figures(run_ctx *c)
{
    return c->o->write ? scene_figures(c->s, c->r, &c->analysis, c->out_dir, c->o->overwrite,
                                       inner_progress, c)
                       : SVP_OK;
}

/* The stage table: the function of every scene_stage (names and order: SCENE_STAGES in
 * scene_internal.h). */
typedef svp_status (*stage_fn)(run_ctx *c);
static const stage_fn stage_table[SCENE_STAGE_COUNT] = {
#define SCENE_STAGE_FN(e, name, fn) [SCENE_STAGE_##e] = fn,
    SCENE_STAGES(SCENE_STAGE_FN)
#undef SCENE_STAGE_FN
};

static svp_status run_stage(run_ctx *c, int i)
{
    scene_stage st = c->s->plan[i].stage;
    if ((unsigned)st >= SCENE_STAGE_COUNT || !stage_table[st])
        return svp_fail(SVP_ERR_INTERNAL, "scene: unknown stage %d", (int)st);
    return stage_table[st](c);
}

/* The peak memory of a run, from measured peaks (release build, 2 threads): a strip under a
 * Lorentzian PSF with one R correction peaked at 0.19 / 0.55 / 1.96 / 7.5 GB on 512² / 1024² /
 * 2048² / 4096² canvases (85 MB + 446 B per canvas pixel); the reference study's 700² scenes
 * with three or four corrections and their figures at 0.35 - 0.50 GB; a cube holds its frames
 * about three times over. An 8192² canvas (30 GB) was killed by the kernel. */
double scene_memory_estimate(const svp_scene *s)
{
    const double canvas = (double)s->canvas_w * s->canvas_h, view = (double)s->view_w * s->view_h;
    double b = 100e6 + canvas * (450.0 + 40.0 * s->n_correct);
    if (s->spectrum) b += 24.0 * s->spectrum_points * view;
    return b;
}

svp_status svp_scene_run(const svp_scene *s, const char *out_dir, const svp_scene_options *options,
                         svp_scene_result **result)
{
    if (result) *result = NULL;
    if (!s) return svp_fail(SVP_ERR_INVALID, "svp_scene_run: scene is NULL");
    svp_scene_options defaults;
    svp_scene_defaults(&defaults);
    const svp_scene_options *o = options ? options : &defaults;
    if (o->write && (!out_dir || !*out_dir))
        return svp_fail(SVP_ERR_INVALID, "svp_scene_run: no output folder (out_dir is NULL)");
    /* before anything is written or allocated: the run must fit the memory budget */
    char what[96];
    snprintf(what, sizeof what, "the scene's run (%d x %d canvas, %d correction%s)", s->canvas_w,
             s->canvas_h, s->n_correct, s->n_correct == 1 ? "" : "s");
    SVP_CHECK(svp_io_check_memory(s->path, what, scene_memory_estimate(s)));
    unsigned char *absent = NULL;
    if (o->write) {
        absent = calloc((size_t)s->n_outputs + 1, 1);
        if (!absent) return svp_fail(SVP_ERR_NOMEM, "out of memory");
        svp_status cs = check_outputs(s, out_dir, o->overwrite, absent);
        if (cs == SVP_OK) cs = make_dirs(out_dir);
        const char *sub[] = {"maps", "figures", "tables"};
        for (int i = 0; i < 3 && cs == SVP_OK; i++) {
            char p[4096];
            snprintf(p, sizeof p, "%s/%s", out_dir, sub[i]);
            if ((i == 0 && !s->write_maps) || (i == 1 && !s->write_figures)) continue;
            cs = make_dir(p);
        }
        if (cs != SVP_OK) {
            free(absent);
            return cs;
        }
    }
    svp_scene_result *r = calloc(1, sizeof *r);
    if (!r) {
        free(absent);
        return svp_fail(SVP_ERR_NOMEM, "out of memory");
    }
    r->n_stages = s->n_stages;
    r->seconds = calloc((size_t)s->n_stages, sizeof *r->seconds);
    run_ctx c;
    memset(&c, 0, sizeof c);
    c.s = s;
    c.o = o;
    c.r = r;
    c.out_dir = out_dir;
    c.drift_stage = c.noise_stage = -1;
    c.t_run = now_s();
    svp_status st = r->seconds ? SVP_OK : svp_fail(SVP_ERR_NOMEM, "out of memory");
    int cube_stage = -1, estimate_stage = -1;
    for (int i = 0; i < s->n_stages; i++) {
        if (s->plan[i].stage == SCENE_STAGE_DRIFT) c.drift_stage = i;
        if (s->plan[i].stage == SCENE_STAGE_NOISE) c.noise_stage = i;
        if (s->plan[i].stage == SCENE_STAGE_CUBE) cube_stage = i;
        if (s->plan[i].stage == SCENE_STAGE_ESTIMATE) estimate_stage = i;
    }
    int memory_noted = 0;
    /* without a margin the view is the canvas: the crop is a copy, not a stage */
    for (int i = 0; i < s->n_stages && st == SVP_OK; i++) {
        c.stage = i;
        if (o->on_stage && o->on_stage(o->stage_user, i, s->n_stages, &s->stages[i])) {
            st =
                svp_fail(SVP_ERR_CANCELLED, "scene run cancelled before stage %s", s->plan[i].name);
            break;
        }
        if ((st = progress(&c, 0)) != SVP_OK) break;
        double t0 = now_s();
        st = run_stage(&c, i);
        r->seconds[i] += now_s() - t0;
        /* an invariant operator makes its frame on first use: its bytes once the forward
         * model (closed form or cube) has used it */
        if (st == SVP_OK && c.blur && !memory_noted &&
            (s->plan[i].stage == SCENE_STAGE_FORWARD || s->plan[i].stage == SCENE_STAGE_CUBE)) {
            st = value(&c, (double)svp_blur_memory(c.blur), "operator/memory_bytes");
            memory_noted = 1;
        }
        if (st == SVP_OK && s->margin_px == 0 && !c.cropped &&
            (s->plan[i].stage == SCENE_STAGE_FORWARD || s->plan[i].stage == SCENE_STAGE_ESTIMATE ||
             (s->plan[i].stage == SCENE_STAGE_CUBE && estimate_stage < 0)))
            st = stage_crop(&c);
        if (st == SVP_OK && i == s->n_stages - 1) {
            /* the cube loop's inner parts, moved to their own stages */
            if (cube_stage >= 0) {
                double est = 0, v;
                for (int k = 0; k < s->n_fields; k++) {
                    char key[96];
                    snprintf(key, sizeof key, "cube/%s/estimate_seconds",
                             scene_component_name(s->field_comp[k]));
                    if (svp_scene_result_value(r, key, &v)) est += v;
                }
                double moved = est + c.drift_seconds + c.noise_seconds;
                /* a cube correction's deconvolutions and estimates: its correct stage's */
                for (int k = 0; k < s->n_stages; k++)
                    if (s->plan[k].stage == SCENE_STAGE_CORRECT &&
                        s->correct[s->plan[k].index].cube) {
                        r->seconds[k] += c.cube_seconds[s->plan[k].index];
                        moved += c.cube_seconds[s->plan[k].index];
                    }
                r->seconds[cube_stage] = fmax(0, r->seconds[cube_stage] - moved);
                if (estimate_stage >= 0) r->seconds[estimate_stage] += est;
                if (c.drift_stage >= 0) r->seconds[c.drift_stage] += c.drift_seconds;
                if (c.noise_stage >= 0) r->seconds[c.noise_stage] += c.noise_seconds;
            }
        }
    }
    if (st == SVP_OK && o->write) {
        char *report = NULL;
        st = scene_report_text(s, r, &c.analysis, &report);
        if (st == SVP_OK) st = write_text(&c, "report.md", report);
        free(report);
        if (st == SVP_OK) st = write_summary(&c, now_s() - c.t_run);
    }
    if (st == SVP_OK) st = progress(&c, 1);
    svp_blur_free(c.blur);
    svp_blur_free(c.blur_view);
    if (c.have_analysis) scene_analysis_free(&c.analysis);
    if (st != SVP_OK && absent) remove_new_outputs(s, out_dir, absent);
    free(absent);
    if (st != SVP_OK || !result) {
        svp_scene_result_free(r);
        return st;
    }
    if (!o->keep_maps) {
        for (int i = 0; i < r->n_maps; i++) {
            free(r->map_names[i]);
            svp_image_free(r->maps[i]);
        }
        r->n_maps = 0;
    }
    *result = r;
    return SVP_OK;
}
