/* Scene files: parsing and checking (every error names file:line:col and the key) into a
 * struct svp_scene, whose plan plan.c then compiles. The keys are documented in
 * docs/scenes.md; the runner is run.c, the result result.c, the metrics metrics.c, the
 * figures report.c. */
#include "scene_internal.h"

#include "../io/yaml.h"

#include <ctype.h>
#include <stdarg.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* The largest canvas side: memory and time stay reasonable (a 8192² double map is 512 MB). */
#define SCENE_MAX_SIDE 8192
#define SCENE_MIN_SIDE 8

/* ---- small helpers ------------------------------------------------------------------------- */

static char *dup_text(const char *s)
{
    if (!s) return NULL;
    size_t n = strlen(s);
    char *c = malloc(n + 1);
    if (c) memcpy(c, s, n + 1);
    return c;
}

static void where_of(const svp_yaml_node *n, char *buf) { svp_yaml_where(n, buf, SCENE_WHERE); }

/* Unit suffixes a length/quantity key may carry. A key that is not allowed but whose stem
 * matches an allowed key with another suffix is a wrong unit, reported as such. */
static const char *const unit_suffixes[] = {"_um", "_nm",  "_mm",  "_m",   "_A_per_m", "_mA",
                                            "_A",  "_deg", "_rad", "_MHz", "_GHz",     "_Hz",
                                            "_mT", "_uT",  "_T",   "_pct", "_per_um",  NULL};

static size_t stem_length(const char *key)
{
    size_t n = strlen(key);
    for (int i = 0; unit_suffixes[i]; i++) {
        size_t k = strlen(unit_suffixes[i]);
        if (n > k && strcmp(key + n - k, unit_suffixes[i]) == 0) return n - k;
    }
    return n;
}

/* svp_yaml_check_keys, preceded by the unit check: "standoff_um: wrong unit: standoff is
 * given as standoff_nm (nanometres)". Also a bare stem ("standoff") names its unit. */
static svp_status check_keys(const svp_yaml_node *map, const char *what, const char *const *allowed)
{
    SVP_CHECK(svp_yaml_expect_mapping(map, what));
    for (size_t i = 0; i < svp_yaml_size(map); i++) {
        const svp_yaml_node *key = svp_yaml_key_at(map, i);
        const char *k = svp_yaml_text(key);
        int ok = 0;
        for (int a = 0; allowed[a] && !ok; a++) ok = strcmp(allowed[a], k) == 0;
        if (ok) continue;
        size_t ks = stem_length(k);
        for (int a = 0; allowed[a]; a++) {
            size_t as = stem_length(allowed[a]);
            if (as == strlen(allowed[a])) continue; /* the allowed key has no unit */
            if (ks == as && strncmp(k, allowed[a], as) == 0)
                return svp_yaml_fail(key, SVP_ERR_FORMAT,
                                     "%s%s%s: wrong or missing unit: this value is given as "
                                     "'%s' (unit %s)",
                                     what ? what : "", what ? "." : "", k, allowed[a],
                                     allowed[a] + as + 1);
        }
    }
    return svp_yaml_check_keys(map, what, allowed);
}

/* name buffer: "what.key" */
static const char *qname(char *buf, size_t size, const char *what, const char *key)
{
    if (what && *what)
        snprintf(buf, size, "%s.%s", what, key);
    else
        snprintf(buf, size, "%s", key);
    return buf;
}

static svp_status get_num(const svp_yaml_node *map, const char *what, const char *key, double lo,
                          double hi, int flags, double *value, int required)
{
    char name[160];
    const svp_yaml_node *n = svp_yaml_get(map, key);
    if (!n) {
        if (required)
            return svp_yaml_fail(map, SVP_ERR_FORMAT, "missing required key '%s'%s%s", key,
                                 what ? " in " : "", what ? what : "");
        return SVP_OK;
    }
    return svp_yaml_number_in(n, qname(name, sizeof name, what, key), lo, hi, flags, value);
}

static svp_status get_pair(const svp_yaml_node *map, const char *what, const char *key,
                           double out[2], int required)
{
    char name[160];
    const svp_yaml_node *n = svp_yaml_get(map, key);
    if (!n) {
        if (required)
            return svp_yaml_fail(map, SVP_ERR_FORMAT, "missing required key '%s'%s%s", key,
                                 what ? " in " : "", what ? what : "");
        return SVP_OK;
    }
    return svp_yaml_number_list(n, qname(name, sizeof name, what, key), 2, 2, out, NULL);
}

static svp_status get_choice(const svp_yaml_node *map, const char *what, const char *key,
                             const char *const *choices, int *index, int required)
{
    char name[160];
    const svp_yaml_node *n = svp_yaml_get(map, key);
    if (!n) {
        if (required)
            return svp_yaml_fail(map, SVP_ERR_FORMAT, "missing required key '%s'%s%s", key,
                                 what ? " in " : "", what ? what : "");
        return SVP_OK;
    }
    return svp_yaml_choice(n, qname(name, sizeof name, what, key), choices, index);
}

static svp_status get_bool(const svp_yaml_node *map, const char *what, const char *key, int *value)
{
    char name[160];
    const svp_yaml_node *n = svp_yaml_get(map, key);
    if (!n) return SVP_OK;
    return svp_yaml_bool(n, qname(name, sizeof name, what, key), value);
}

/* A name used in output file names: letters, digits, '_' and '-', 1..31 characters. */
static svp_status get_name(const svp_yaml_node *map, const char *what, char out[32])
{
    const svp_yaml_node *n = svp_yaml_get(map, "name");
    if (!n) return SVP_OK;
    char qn[160];
    const char *s = NULL;
    SVP_CHECK(svp_yaml_string(n, qname(qn, sizeof qn, what, "name"), &s));
    size_t len = strlen(s);
    int ok = len >= 1 && len <= 31;
    for (size_t i = 0; ok && i < len; i++)
        ok = isalnum((unsigned char)s[i]) || s[i] == '_' || s[i] == '-';
    if (!ok)
        return svp_yaml_fail(n, SVP_ERR_INVALID,
                             "%s must be 1 to 31 letters, digits, '_' or '-' (it names output "
                             "files), got '%s'",
                             qn, s);
    memcpy(out, s, len + 1);
    return SVP_OK;
}

/* Joins a path relative to the scene's folder (absolute paths are kept). */
static char *resolve_path(const struct svp_scene *s, const char *p)
{
    if (p[0] == '/' || !s->dir || !*s->dir) return dup_text(p);
    size_t n = strlen(s->dir) + strlen(p) + 2;
    char *out = malloc(n);
    if (out) snprintf(out, n, "%s/%s", s->dir, p);
    return out;
}

/* Reads an image named by key `key` of map (path relative to the scene file) and checks its
 * size: the canvas, or the view when there is no margin. */
static svp_status get_image(struct svp_scene *s, const svp_yaml_node *map, const char *what,
                            const char *key, char **path_out, svp_image **image_out)
{
    char qn[160];
    const svp_yaml_node *n = NULL;
    SVP_CHECK(svp_yaml_require(map, key, what, &n));
    const char *p = NULL;
    SVP_CHECK(svp_yaml_string(n, qname(qn, sizeof qn, what, key), &p));
    char *path = resolve_path(s, p);
    if (!path) return svp_fail(SVP_ERR_NOMEM, "out of memory");
    svp_image *img = NULL;
    svp_status st = svp_image_read(path, &img);
    if (st != SVP_OK) {
        st = svp_yaml_fail(n, st, "%s: %s", qn, svp_last_error());
        free(path);
        return st;
    }
    if (img->width != s->canvas_w || img->height != s->canvas_h) {
        if (s->margin_px > 0)
            st = svp_yaml_fail(n, SVP_ERR_SIZE,
                               "%s: '%s' is %d x %d pixels but the canvas (view %d x %d plus "
                               "margin_um on each side) is %d x %d",
                               qn, p, img->width, img->height, s->view_w, s->view_h, s->canvas_w,
                               s->canvas_h);
        else
            st = svp_yaml_fail(n, SVP_ERR_SIZE,
                               "%s: '%s' is %d x %d pixels but the view (grid.size_um / "
                               "grid.pixel_um) is %d x %d",
                               qn, p, img->width, img->height, s->view_w, s->view_h);
        svp_image_free(img);
        free(path);
        return st;
    }
    if (svp_image_count_nonfinite(img)) {
        st = svp_yaml_fail(n, SVP_ERR_INVALID, "%s: '%s' holds %zu NaN or Inf pixels", qn, p,
                           svp_image_count_nonfinite(img));
        svp_image_free(img);
        free(path);
        return st;
    }
    *path_out = path;
    *image_out = img;
    return SVP_OK;
}

/* ---- grid and sensor ----------------------------------------------------------------------- */

static svp_status parse_grid(struct svp_scene *s, const svp_yaml_node *root)
{
    static const char *const keys[] = {"pixel_um", "size_um", "margin_um", NULL};
    const svp_yaml_node *g = NULL;
    SVP_CHECK(svp_yaml_require(root, "grid", NULL, &g));
    SVP_CHECK(check_keys(g, "grid", keys));
    SVP_CHECK(get_num(g, "grid", "pixel_um", SVP_PIXEL_UM_MIN, INFINITY, 0, &s->pixel_um, 1));
    SVP_CHECK(get_pair(g, "grid", "size_um", s->size_um, 1));
    const svp_yaml_node *sz = svp_yaml_get(g, "size_um");
    for (int a = 0; a < 2; a++) {
        if (!(s->size_um[a] > 0))
            return svp_yaml_fail(svp_yaml_item(sz, (size_t)a), SVP_ERR_INVALID,
                                 "grid.size_um[%d] must be > 0, got %g", a, s->size_um[a]);
        double px = s->size_um[a] / s->pixel_um;
        if (!(px >= SCENE_MIN_SIDE - 0.5) || !(px <= SCENE_MAX_SIDE))
            return svp_yaml_fail(svp_yaml_item(sz, (size_t)a), SVP_ERR_INVALID,
                                 "grid.size_um[%d] = %g um is %.4g pixels of %g um: the view "
                                 "must be %d to %d pixels across",
                                 a, s->size_um[a], px, s->pixel_um, SCENE_MIN_SIDE, SCENE_MAX_SIDE);
    }
    s->view_w = (int)lround(s->size_um[0] / s->pixel_um);
    s->view_h = (int)lround(s->size_um[1] / s->pixel_um);
    SVP_CHECK(get_num(g, "grid", "margin_um", 0, INFINITY, 0, &s->margin_um, 0));
    /* checked in pixels before any integer conversion (a huge margin overflowed an int) */
    const double margin_px = s->margin_um / s->pixel_um;
    if (!(margin_px <= SCENE_MAX_SIDE))
        return svp_yaml_fail(svp_yaml_get(g, "margin_um"), SVP_ERR_INVALID,
                             "grid.margin_um = %g um is %.4g pixels: the canvas may be at most %d "
                             "pixels across",
                             s->margin_um, margin_px, SCENE_MAX_SIDE);
    s->margin_px = (int)lround(margin_px);
    s->canvas_w = s->view_w + 2 * s->margin_px;
    s->canvas_h = s->view_h + 2 * s->margin_px;
    if (s->canvas_w > SCENE_MAX_SIDE || s->canvas_h > SCENE_MAX_SIDE)
        return svp_yaml_fail(svp_yaml_get(g, "margin_um"), SVP_ERR_INVALID,
                             "grid.margin_um = %g um makes a canvas of %d x %d pixels, more "
                             "than %d across",
                             s->margin_um, s->canvas_w, s->canvas_h, SCENE_MAX_SIDE);
    return SVP_OK;
}

static svp_status parse_sensor(struct svp_scene *s, const svp_yaml_node *root)
{
    static const char *const keys[] = {"nv_thickness_nm", "side", NULL};
    static const char *const sides[] = {"above", "below", NULL};
    s->side = 1;
    const svp_yaml_node *n = svp_yaml_get(root, "sensor");
    if (!n) return SVP_OK;
    SVP_CHECK(check_keys(n, "sensor", keys));
    SVP_CHECK(get_num(n, "sensor", "nv_thickness_nm", 0, INFINITY, 0, &s->nv_thickness_nm, 0));
    int side = 0;
    SVP_CHECK(get_choice(n, "sensor", "side", sides, &side, 0));
    s->side = side == 0 ? 1 : -1;
    return SVP_OK;
}

/* ---- sources ------------------------------------------------------------------------------- */

/* The single key of a one-key mapping list item ("- flake: {...}"). */
static svp_status single_key(const svp_yaml_node *item, const char *what, const char *const *kinds,
                             int *kind, const svp_yaml_node **body)
{
    if (svp_yaml_type_of(item) != SVP_YAML_MAPPING || svp_yaml_size(item) != 1) {
        char list[200] = "";
        for (int i = 0; kinds[i]; i++) {
            strncat(list, i ? ", " : "", sizeof list - strlen(list) - 1);
            strncat(list, kinds[i], sizeof list - strlen(list) - 1);
        }
        return svp_yaml_fail(item, SVP_ERR_FORMAT,
                             "each item of %s must be a mapping with one key (one of: %s)", what,
                             list);
    }
    const svp_yaml_node *key = svp_yaml_key_at(item, 0);
    char qn[160];
    snprintf(qn, sizeof qn, "%s item", what);
    SVP_CHECK(svp_yaml_choice(key, qn, kinds, kind));
    *body = svp_yaml_value_at(item, 0);
    return SVP_OK;
}

/* Does a polygon/rectangle/disk (canvas pixels) reach beyond the canvas? */
static svp_status check_inside_canvas(const struct svp_scene *s, const svp_yaml_node *n,
                                      const char *what, double x0, double x1, double y0, double y1)
{
    double tol = 0.5;
    if (x0 < -0.5 - tol || y0 < -0.5 - tol || x1 > s->canvas_w - 0.5 + tol ||
        y1 > s->canvas_h - 0.5 + tol)
        return svp_yaml_fail(n, SVP_ERR_INVALID,
                             "%s reaches beyond the canvas (x %.4g..%.4g um, y %.4g..%.4g um; "
                             "the canvas spans +-%.4g um by +-%.4g um): its field would be that "
                             "of a cut flake; enlarge grid.size_um or grid.margin_um",
                             what, scene_x_um(s, x0), scene_x_um(s, x1), scene_y_um(s, y0),
                             scene_y_um(s, y1), 0.5 * s->canvas_w * s->pixel_um,
                             0.5 * s->canvas_h * s->pixel_um);
    return SVP_OK;
}

static svp_status parse_flake(struct svp_scene *s, scene_source *src, const svp_yaml_node *b,
                              const char *what)
{
    static const char *const keys[] = {"shape",        "size_um",     "diameter_um",
                                       "vertices_um",  "mask",        "threshold",
                                       "centre_um",    "angle_deg",   "magnetisation_A_per_m",
                                       "thickness_nm", "standoff_nm", NULL};
    static const char *const shapes[] = {"rectangle", "disk", "polygon", "mask", NULL};
    SVP_CHECK(check_keys(b, what, keys));
    int shape = 0;
    SVP_CHECK(get_choice(b, what, "shape", shapes, &shape, 1));
    src->shape = (scene_shape)shape;
    char qn[160];
    SVP_CHECK(get_pair(b, what, "centre_um", src->centre_um, 0));
    SVP_CHECK(get_num(b, what, "angle_deg", -INFINITY, INFINITY, 0, &src->angle_deg, 0));
    SVP_CHECK(get_num(b, what, "magnetisation_A_per_m", -INFINITY, INFINITY, 0,
                      &src->magnetisation_A_per_m, 1));
    SVP_CHECK(
        get_num(b, what, "thickness_nm", 0, INFINITY, SVP_YAML_OPEN_LO, &src->thickness_nm, 1));
    SVP_CHECK(get_num(b, what, "standoff_nm", 0, INFINITY, SVP_YAML_OPEN_LO, &src->standoff_nm, 1));
    const char *shape_keys[] = {"size_um", "diameter_um", "vertices_um", "mask"};
    for (int k = 0; k < 4; k++) {
        const svp_yaml_node *n = svp_yaml_get(b, shape_keys[k]);
        if (n && k != shape)
            return svp_yaml_fail(n, SVP_ERR_FORMAT,
                                 "%s: '%s' does not apply to shape %s (it "
                                 "takes '%s')",
                                 what, shape_keys[k], shapes[shape], shape_keys[shape]);
    }
    if (svp_yaml_get(b, "threshold") && shape != SHAPE_MASK)
        return svp_yaml_fail(svp_yaml_get(b, "threshold"), SVP_ERR_FORMAT,
                             "%s: 'threshold' applies to shape mask only", what);
    if (svp_yaml_get(b, "angle_deg") && shape != SHAPE_RECTANGLE)
        return svp_yaml_fail(svp_yaml_get(b, "angle_deg"), SVP_ERR_FORMAT,
                             "%s: 'angle_deg' applies to shape rectangle only", what);
    double ci = scene_i_px(s, src->centre_um[0]), cj = scene_j_px(s, src->centre_um[1]);
    switch (src->shape) {
    case SHAPE_RECTANGLE: {
        SVP_CHECK(get_pair(b, what, "size_um", src->size_um, 1));
        for (int a = 0; a < 2; a++)
            if (!(src->size_um[a] > 0))
                return svp_yaml_fail(svp_yaml_item(svp_yaml_get(b, "size_um"), (size_t)a),
                                     SVP_ERR_INVALID, "%s.size_um[%d] must be > 0, got %g", what, a,
                                     src->size_um[a]);
        double c = cos(src->angle_deg * M_PI / 180), sn = sin(src->angle_deg * M_PI / 180);
        double hx = 0.5 * (fabs(c) * src->size_um[0] + fabs(sn) * src->size_um[1]) / s->pixel_um;
        double hy = 0.5 * (fabs(sn) * src->size_um[0] + fabs(c) * src->size_um[1]) / s->pixel_um;
        SVP_CHECK(check_inside_canvas(s, b, what, ci - hx, ci + hx, cj - hy, cj + hy));
        break;
    }
    case SHAPE_DISK: {
        SVP_CHECK(
            get_num(b, what, "diameter_um", 0, INFINITY, SVP_YAML_OPEN_LO, &src->diameter_um, 1));
        double r = 0.5 * src->diameter_um / s->pixel_um;
        SVP_CHECK(check_inside_canvas(s, b, what, ci - r, ci + r, cj - r, cj + r));
        break;
    }
    case SHAPE_POLYGON: {
        const svp_yaml_node *v = NULL;
        SVP_CHECK(svp_yaml_require(b, "vertices_um", what, &v));
        size_t n = svp_yaml_size(v);
        if (svp_yaml_type_of(v) != SVP_YAML_SEQUENCE || n < 3)
            return svp_yaml_fail(v, SVP_ERR_FORMAT,
                                 "%s.vertices_um must be a list of at least 3 points [x, y]", what);
        src->vertices_um = malloc(2 * n * sizeof(double));
        if (!src->vertices_um) return svp_fail(SVP_ERR_NOMEM, "out of memory");
        src->n_vertices = (int)n;
        double x0 = INFINITY, x1 = -INFINITY, y0 = INFINITY, y1 = -INFINITY;
        for (size_t i = 0; i < n; i++) {
            snprintf(qn, sizeof qn, "%s.vertices_um[%zu]", what, i);
            SVP_CHECK(svp_yaml_number_list(svp_yaml_item(v, i), qn, 2, 2, src->vertices_um + 2 * i,
                                           NULL));
            double pi = scene_i_px(s, src->vertices_um[2 * i] + src->centre_um[0]);
            double pj = scene_j_px(s, src->vertices_um[2 * i + 1] + src->centre_um[1]);
            x0 = fmin(x0, pi), x1 = fmax(x1, pi), y0 = fmin(y0, pj), y1 = fmax(y1, pj);
        }
        if (!(x1 - x0 > 0) || !(y1 - y0 > 0))
            return svp_yaml_fail(v, SVP_ERR_INVALID, "%s.vertices_um: the polygon has no area",
                                 what);
        SVP_CHECK(check_inside_canvas(s, b, what, x0, x1, y0, y1));
        break;
    }
    case SHAPE_MASK: {
        svp_image *mask = NULL;
        SVP_CHECK(get_image(s, b, what, "mask", &src->mask_path, &mask));
        src->mask_threshold = NAN;
        svp_status st =
            get_num(b, what, "threshold", -INFINITY, INFINITY, 0, &src->mask_threshold, 0);
        svp_image_free(mask); /* read again at run time; checked here */
        if (st != SVP_OK) return st;
        if (svp_yaml_get(b, "centre_um"))
            return svp_yaml_fail(svp_yaml_get(b, "centre_um"), SVP_ERR_FORMAT,
                                 "%s: 'centre_um' does not apply to a mask (the mask covers the "
                                 "canvas pixel for pixel)",
                                 what);
        break;
    }
    }
    return SVP_OK;
}

static svp_status parse_strip(struct svp_scene *s, scene_source *src, const svp_yaml_node *b,
                              const char *what)
{
    (void)s;
    static const char *const keys[] = {
        "width_um", "sheet_current_A_per_m", "current_mA", "standoff_nm", "angle_deg", "centre_um",
        NULL};
    SVP_CHECK(check_keys(b, what, keys));
    SVP_CHECK(get_num(b, what, "width_um", 0, INFINITY, SVP_YAML_OPEN_LO, &src->width_um, 1));
    SVP_CHECK(get_num(b, what, "standoff_nm", 0, INFINITY, SVP_YAML_OPEN_LO, &src->standoff_nm, 1));
    src->angle_deg = 90;
    SVP_CHECK(get_num(b, what, "angle_deg", -INFINITY, INFINITY, 0, &src->angle_deg, 0));
    SVP_CHECK(get_pair(b, what, "centre_um", src->centre_um, 0));
    const svp_yaml_node *j = svp_yaml_get(b, "sheet_current_A_per_m");
    const svp_yaml_node *i = svp_yaml_get(b, "current_mA");
    if (j && i)
        return svp_yaml_fail(i, SVP_ERR_FORMAT,
                             "%s: give either sheet_current_A_per_m or current_mA, not both", what);
    if (!j && !i)
        return svp_yaml_fail(b, SVP_ERR_FORMAT,
                             "missing required key 'sheet_current_A_per_m' (or 'current_mA') "
                             "in %s",
                             what);
    if (j) {
        SVP_CHECK(get_num(b, what, "sheet_current_A_per_m", -INFINITY, INFINITY, 0,
                          &src->sheet_current_A_per_m, 1));
    } else {
        double ma = 0;
        SVP_CHECK(get_num(b, what, "current_mA", -INFINITY, INFINITY, 0, &ma, 1));
        src->sheet_current_A_per_m = ma * 1e-3 / (src->width_um * 1e-6);
    }
    return SVP_OK;
}

static svp_status parse_field_file(struct svp_scene *s, scene_source *src, const svp_yaml_node *b,
                                   const char *what)
{
    static const char *const keys[] = {"path", "component", "unit", NULL};
    static const char *const comps[] = {"x", "y", "z", NULL};
    static const char *const units[] = {"T", "mT", "uT", "nT", NULL};
    static const double scale[] = {1, 1e-3, 1e-6, 1e-9};
    SVP_CHECK(check_keys(b, what, keys));
    SVP_CHECK(get_choice(b, what, "component", comps, &src->component, 1));
    int unit = 0;
    SVP_CHECK(get_choice(b, what, "unit", units, &unit, 1));
    src->to_tesla = scale[unit];
    svp_image *img = NULL;
    SVP_CHECK(get_image(s, b, what, "path", &src->path, &img));
    svp_image_free(img);
    return SVP_OK;
}

static svp_status parse_sources(struct svp_scene *s, const svp_yaml_node *root)
{
    static const char *const kinds[] = {"flake", "strip", "field_file", NULL};
    const svp_yaml_node *list = NULL;
    SVP_CHECK(svp_yaml_require(root, "sources", NULL, &list));
    size_t n = svp_yaml_size(list);
    if (svp_yaml_type_of(list) != SVP_YAML_SEQUENCE || n == 0)
        return svp_yaml_fail(list, SVP_ERR_FORMAT,
                             "sources must be a list of at least one source (- flake: {...}, "
                             "- strip: {...}, - field_file: {...})");
    s->sources = calloc(n, sizeof *s->sources);
    if (!s->sources) return svp_fail(SVP_ERR_NOMEM, "out of memory");
    s->n_sources = (int)n;
    for (size_t i = 0; i < n; i++) {
        const svp_yaml_node *item = svp_yaml_item(list, i), *body = NULL;
        int kind = 0;
        SVP_CHECK(single_key(item, "sources", kinds, &kind, &body));
        scene_source *src = &s->sources[i];
        src->kind = (scene_source_kind)kind;
        where_of(body, src->where);
        char what[64];
        snprintf(what, sizeof what, "sources[%zu].%s", i, kinds[kind]);
        switch (src->kind) {
        case SRC_FLAKE:
            SVP_CHECK(parse_flake(s, src, body, what));
            s->n_flakes++;
            break;
        case SRC_STRIP:
            SVP_CHECK(parse_strip(s, src, body, what));
            s->n_strips++;
            break;
        case SRC_FIELD_FILE:
            SVP_CHECK(parse_field_file(s, src, body, what));
            s->n_files++;
            break;
        }
        if (src->kind != SRC_FIELD_FILE && s->nv_thickness_nm >= 2 * src->standoff_nm)
            return svp_yaml_fail(svp_yaml_get(body, "standoff_nm"), SVP_ERR_INVALID,
                                 "%s.standoff_nm = %g must exceed half of "
                                 "sensor.nv_thickness_nm (%g nm): the NV layer would reach "
                                 "into the source",
                                 what, src->standoff_nm, s->nv_thickness_nm);
        /* a flake's field is made on the canvas padded twice (periodic): its images, two
         * canvas sides away, must stay far beyond the standoff (else, at a standoff of a metre,
         * the field came out 0 and the metrics NaN with exit 0) */
        const double side_um = fmin(s->canvas_w, s->canvas_h) * s->pixel_um;
        if (src->kind == SRC_FLAKE && src->standoff_nm * 1e-3 > 0.1 * side_um)
            return svp_yaml_fail(svp_yaml_get(body, "standoff_nm"), SVP_ERR_INVALID,
                                 "%s.standoff_nm = %g is more than a tenth of the canvas's "
                                 "smaller side (%g um): the flake's field is made on a periodic "
                                 "canvas, whose images of it would no longer be negligible; "
                                 "enlarge grid.size_um or grid.margin_um",
                                 what, src->standoff_nm, side_um);
    }
    return SVP_OK;
}

/* ---- field components ---------------------------------------------------------------------- */

static svp_status parse_field(struct svp_scene *s, const svp_yaml_node *root)
{
    static const char *const keys[] = {"components", "nv_axis", NULL};
    static const char *const comps[] = {"x", "y", "z", NULL};
    const svp_yaml_node *f = svp_yaml_get(root, "field");
    if (!f) {
        s->n_fields = 1;
        s->field_comp[0] = 2;
        return SVP_OK;
    }
    SVP_CHECK(check_keys(f, "field", keys));
    const svp_yaml_node *c = svp_yaml_get(f, "components");
    if (c) {
        size_t n = svp_yaml_size(c);
        if (svp_yaml_type_of(c) != SVP_YAML_SEQUENCE || n < 1 || n > 3)
            return svp_yaml_fail(c, SVP_ERR_FORMAT,
                                 "field.components must be a list of 1 to 3 of x, y, z");
        for (size_t i = 0; i < n; i++) {
            int comp = 0;
            char qn[64];
            snprintf(qn, sizeof qn, "field.components[%zu]", i);
            SVP_CHECK(svp_yaml_choice(svp_yaml_item(c, i), qn, comps, &comp));
            for (int k = 0; k < s->n_fields; k++)
                if (s->field_comp[k] == comp)
                    return svp_yaml_fail(svp_yaml_item(c, i), SVP_ERR_INVALID,
                                         "field.components lists '%s' twice", comps[comp]);
            s->field_comp[s->n_fields++] = comp;
        }
    }
    const svp_yaml_node *a = svp_yaml_get(f, "nv_axis");
    if (a) {
        SVP_CHECK(svp_yaml_number_list(a, "field.nv_axis", 3, 3, s->nv_axis, NULL));
        double norm = sqrt(s->nv_axis[0] * s->nv_axis[0] + s->nv_axis[1] * s->nv_axis[1] +
                           s->nv_axis[2] * s->nv_axis[2]);
        if (!(norm > 0))
            return svp_yaml_fail(a, SVP_ERR_INVALID,
                                 "field.nv_axis must be a non-zero vector [x, y, z]");
        for (int k = 0; k < 3; k++) s->nv_axis[k] /= norm;
        s->field_comp[s->n_fields++] = 3;
    }
    if (s->n_fields == 0)
        return svp_yaml_fail(f, SVP_ERR_FORMAT,
                             "field needs 'components' (a list of x, y, z) and/or 'nv_axis'");
    return SVP_OK;
}

/* ---- emission factors ---------------------------------------------------------------------- */

static svp_status parse_factors(struct svp_scene *s, const svp_yaml_node *list, const char *what,
                                scene_factor **out, int *n_out)
{
    static const char *const kinds[] = {"uniform", "gaussian", "chessboard", "quench",
                                        "image",   "fringes",  NULL};
    size_t n = svp_yaml_size(list);
    if (svp_yaml_type_of(list) != SVP_YAML_SEQUENCE || n == 0)
        return svp_yaml_fail(list, SVP_ERR_FORMAT,
                             "%s must be a list of factors (- uniform: {...}, - gaussian: "
                             "{...}, - chessboard: {...}, - quench: {...}, - fringes: {...}, "
                             "- image: {...}); the PL is their product",
                             what);
    scene_factor *f = calloc(n, sizeof *f);
    if (!f) return svp_fail(SVP_ERR_NOMEM, "out of memory");
    *out = f;
    *n_out = (int)n;
    for (size_t i = 0; i < n; i++) {
        const svp_yaml_node *body = NULL;
        int kind = 0;
        SVP_CHECK(single_key(svp_yaml_item(list, i), what, kinds, &kind, &body));
        scene_factor *e = &f[i];
        e->kind = (scene_emission_kind)kind;
        where_of(body, e->where);
        char w[96];
        snprintf(w, sizeof w, "%s[%zu].%s", what, i, kinds[kind]);
        if (svp_yaml_type_of(body) == SVP_YAML_NULL && kind == EM_UNIFORM) {
            e->level = 1;
            continue;
        }
        switch (e->kind) {
        case EM_UNIFORM: {
            static const char *const keys[] = {"level", NULL};
            SVP_CHECK(check_keys(body, w, keys));
            e->level = 1;
            SVP_CHECK(get_num(body, w, "level", 0, INFINITY, SVP_YAML_OPEN_LO, &e->level, 0));
            break;
        }
        case EM_GAUSSIAN: {
            static const char *const keys[] = {"fwhm_um", "centre_um", NULL};
            SVP_CHECK(check_keys(body, w, keys));
            SVP_CHECK(get_num(body, w, "fwhm_um", 0, INFINITY, SVP_YAML_OPEN_LO, &e->fwhm_um, 1));
            SVP_CHECK(get_pair(body, w, "centre_um", e->centre_um, 0));
            break;
        }
        case EM_CHESSBOARD: {
            static const char *const keys[] = {"square_um", "levels", "seed", "offset_um", NULL};
            SVP_CHECK(check_keys(body, w, keys));
            SVP_CHECK(
                get_num(body, w, "square_um", 0, INFINITY, SVP_YAML_OPEN_LO, &e->square_um, 1));
            const svp_yaml_node *lv = NULL;
            SVP_CHECK(svp_yaml_require(body, "levels", w, &lv));
            char qn[128];
            size_t nl = 0;
            SVP_CHECK(svp_yaml_number_list(lv, qname(qn, sizeof qn, w, "levels"), 1,
                                           SCENE_MAX_LEVELS, e->levels, &nl));
            e->n_levels = (int)nl;
            for (int k = 0; k < e->n_levels; k++)
                if (!(e->levels[k] >= 0))
                    return svp_yaml_fail(svp_yaml_item(lv, (size_t)k), SVP_ERR_INVALID,
                                         "%s.levels[%d] must be >= 0 (a relative emission), "
                                         "got %g",
                                         w, k, e->levels[k]);
            long long seed = 1;
            const svp_yaml_node *sn = svp_yaml_get(body, "seed");
            if (sn)
                SVP_CHECK(svp_yaml_int(sn, qname(qn, sizeof qn, w, "seed"), 0, INT64_MAX, &seed));
            e->seed = (uint64_t)seed;
            SVP_CHECK(get_pair(body, w, "offset_um", e->offset_um, 0));
            break;
        }
        case EM_QUENCH: {
            static const char *const keys[] = {"under", "mask", "factor", NULL};
            static const char *const unders[] = {"sources", "flakes", "strips", NULL};
            SVP_CHECK(check_keys(body, w, keys));
            SVP_CHECK(get_num(body, w, "factor", 0, 1, 0, &e->factor, 1));
            const svp_yaml_node *u = svp_yaml_get(body, "under"), *m = svp_yaml_get(body, "mask");
            if ((u != NULL) == (m != NULL))
                return svp_yaml_fail(body, SVP_ERR_FORMAT,
                                     "%s needs exactly one of 'under' (sources, flakes, strips) "
                                     "and 'mask' (an image file)",
                                     w);
            if (u) {
                int under = 0;
                SVP_CHECK(get_choice(body, w, "under", unders, &under, 1));
                e->under = (scene_under)under;
                if ((e->under == UNDER_FLAKES && s->n_flakes == 0) ||
                    (e->under == UNDER_STRIPS && s->n_strips == 0) ||
                    (e->under == UNDER_SOURCES && s->n_flakes + s->n_strips == 0))
                    return svp_yaml_fail(u, SVP_ERR_INVALID,
                                         "%s.under: the scene has no %s to quench under", w,
                                         unders[under]);
            } else {
                e->under = UNDER_MASK;
                svp_image *img = NULL;
                SVP_CHECK(get_image(s, body, w, "mask", &e->path, &img));
                svp_image_free(img);
            }
            break;
        }
        case EM_IMAGE: {
            static const char *const keys[] = {"path", NULL};
            SVP_CHECK(check_keys(body, w, keys));
            svp_image *img = NULL;
            SVP_CHECK(get_image(s, body, w, "path", &e->path, &img));
            int negative = 0;
            for (size_t k = 0; k < (size_t)img->width * img->height; k++)
                negative |= img->data[k] < 0;
            svp_image_free(img);
            if (negative)
                return svp_yaml_fail(svp_yaml_get(body, "path"), SVP_ERR_INVALID,
                                     "%s.path: an emission image must be >= 0 everywhere", w);
            break;
        }
        case EM_FRINGES: {
            static const char *const keys[] = {"period_um", "visibility", "angle_deg", "phase_deg",
                                               "from_um",   "to_um",      NULL};
            SVP_CHECK(check_keys(body, w, keys));
            SVP_CHECK(
                get_num(body, w, "period_um", 0, INFINITY, SVP_YAML_OPEN_LO, &e->period_um, 1));
            SVP_CHECK(get_num(body, w, "visibility", 0, 1, 0, &e->visibility, 1));
            SVP_CHECK(get_num(body, w, "angle_deg", -INFINITY, INFINITY, 0, &e->angle_deg, 0));
            SVP_CHECK(get_num(body, w, "phase_deg", -INFINITY, INFINITY, 0, &e->phase_deg, 0));
            e->from_um = -INFINITY;
            e->to_um = INFINITY;
            SVP_CHECK(get_num(body, w, "from_um", -INFINITY, INFINITY, 0, &e->from_um, 0));
            SVP_CHECK(get_num(body, w, "to_um", -INFINITY, INFINITY, 0, &e->to_um, 0));
            if (!(e->to_um > e->from_um))
                return svp_yaml_fail(svp_yaml_get(body, "to_um"), SVP_ERR_INVALID,
                                     "%s.to_um (%g) must be greater than from_um (%g)", w, e->to_um,
                                     e->from_um);
            break;
        }
        }
    }
    return SVP_OK;
}

/* ---- PSF ------------------------------------------------------------------------------------ */

static const char *const model_names[] = SCENE_PSF_MODEL_NAMES;
static const char *const boundary_names[] = SCENE_BOUNDARY_NAMES;

/* psf.regions (docs/model.md §9): PSFs under shapes, the rest of `psf` being the PSF elsewhere:
 *   regions: [{under: strips|flakes|sources, fwhm_um: .., beta: .., halo: ..}, ...]  (<= 4)
 *   transition_um: blend width across region boundaries (default 0: sharp)
 *   nodes: N or [NX, NY]: tent node grid of the space-variant operator (default 8)
 * Each region takes the model, support and subsample of `psf`; fwhm_um is required, beta for
 * moffat, halo defaults to 0. */
static svp_status parse_psf_regions(struct svp_scene *s, const svp_yaml_node *p, const char *what,
                                    const svp_psf *base, scene_psf *out, int n)
{
    static const char *const rkeys[] = {"under", "fwhm_um", "beta", "halo", NULL};
    static const char *const unders[] = {"sources", "flakes", "strips", NULL};
    const svp_yaml_node *r = svp_yaml_get(p, "regions");
    char qn[128], rw[96];
    out->nodes_x = out->nodes_y = 8;
    if (!r) {
        if (svp_yaml_get(p, "transition_um") || svp_yaml_get(p, "nodes"))
            return svp_yaml_fail(p, SVP_ERR_FORMAT,
                                 "%s: 'transition_um' and 'nodes' apply only with 'regions'", what);
        return SVP_OK;
    }
    const size_t nr = svp_yaml_size(r);
    if (svp_yaml_type_of(r) != SVP_YAML_SEQUENCE || nr < 1 || nr > 4)
        return svp_yaml_fail(r, SVP_ERR_FORMAT, "%s: a list of 1 to 4 regions",
                             qname(qn, sizeof qn, what, "regions"));
    for (size_t k = 0; k < nr; k++) {
        const svp_yaml_node *e = svp_yaml_item(r, k);
        snprintf(rw, sizeof rw, "%s.regions[%zu]", what, k);
        SVP_CHECK(check_keys(e, rw, rkeys));
        int under = 0;
        SVP_CHECK(get_choice(e, rw, "under", unders, &under, 1));
        out->region_under[k] = (scene_under)under;
        svp_psf q = *base;
        double fwhm_um = 0;
        SVP_CHECK(get_num(e, rw, "fwhm_um", 0, INFINITY, SVP_YAML_OPEN_LO, &fwhm_um, 1));
        q.fwhm = fwhm_um / s->pixel_um;
        q.halo = 0;
        SVP_CHECK(get_num(e, rw, "halo", 0, 1, SVP_YAML_OPEN_HI, &q.halo, 0));
        if (base->model == SVP_PSF_MOFFAT)
            SVP_CHECK(get_num(e, rw, "beta", 0, INFINITY, SVP_YAML_OPEN_LO, &q.beta, 1));
        else if (svp_yaml_get(e, "beta"))
            return svp_yaml_fail(svp_yaml_get(e, "beta"), SVP_ERR_INVALID,
                                 "%s.beta: only a moffat PSF takes beta", rw);
        svp_status st = svp_psf_validate(&q);
        if (st != SVP_OK) return svp_yaml_fail(e, st, "%s: %s", rw, svp_last_error());
        out->region_psf[k] = q;
        if (n > 0 && (size_t)n < sizeof out->describe)
            n += snprintf(out->describe + n, sizeof out->describe - (size_t)n,
                          "; under %s FWHM %g um", unders[under], fwhm_um);
        if (base->model == SVP_PSF_MOFFAT && n > 0 && (size_t)n < sizeof out->describe)
            n += snprintf(out->describe + n, sizeof out->describe - (size_t)n, " beta %g", q.beta);
    }
    out->n_regions = (int)nr;
    double t_um = 0;
    SVP_CHECK(get_num(p, what, "transition_um", 0, INFINITY, 0, &t_um, 0));
    out->transition_px = t_um / s->pixel_um;
    const svp_yaml_node *nn = svp_yaml_get(p, "nodes");
    if (nn) {
        double g[2];
        size_t got = 0;
        if (svp_yaml_type_of(nn) == SVP_YAML_SEQUENCE)
            SVP_CHECK(svp_yaml_number_list(nn, qname(qn, sizeof qn, what, "nodes"), 2, 2, g, &got));
        else {
            SVP_CHECK(svp_yaml_number(nn, qname(qn, sizeof qn, what, "nodes"), &g[0]));
            g[1] = g[0];
        }
        for (int a = 0; a < 2; a++)
            if (!(g[a] >= 1 && g[a] <= 64 && g[a] == floor(g[a])))
                return svp_yaml_fail(nn, SVP_ERR_INVALID, "%s: node counts are integers in 1..64",
                                     qn);
        out->nodes_x = (int)g[0];
        out->nodes_y = (int)g[1];
    }
    if (n > 0 && (size_t)n < sizeof out->describe)
        snprintf(out->describe + n, sizeof out->describe - (size_t)n, "; %d x %d nodes",
                 out->nodes_x, out->nodes_y);
    return SVP_OK;
}

/* want_w x want_h: the size a PSF map must have (the canvas for the simulation, the view for
 * a correction). */
static svp_status parse_psf(struct svp_scene *s, const svp_yaml_node *p, const char *what,
                            int want_w, int want_h, scene_psf *out)
{
    static const char *const keys[] = {
        "model",     "fwhm_um",  "beta", "halo",    "fwhm_minor_um", "angle_deg", "support_um",
        "subsample", "boundary", "file", "regions", "transition_um", "nodes",     NULL};
    SVP_CHECK(check_keys(p, what, keys));
    where_of(p, out->where);
    int boundary = 0;
    SVP_CHECK(get_choice(p, what, "boundary", boundary_names, &boundary, 0));
    out->boundary = (svp_boundary)boundary;
    const svp_yaml_node *file = svp_yaml_get(p, "file");
    if (file) {
        for (int k = 0; keys[k]; k++)
            if (strcmp(keys[k], "file") && strcmp(keys[k], "boundary") && svp_yaml_get(p, keys[k]))
                return svp_yaml_fail(svp_yaml_get(p, keys[k]), SVP_ERR_FORMAT,
                                     "%s: '%s' cannot be combined with 'file' (the file holds "
                                     "the whole PSF)",
                                     what, keys[k]);
        const char *rel = NULL;
        char qn[128];
        SVP_CHECK(svp_yaml_string(file, qname(qn, sizeof qn, what, "file"), &rel));
        out->from_file = 1;
        out->path = resolve_path(s, rel);
        if (!out->path) return svp_fail(SVP_ERR_NOMEM, "out of memory");
        svp_psf_field *field = NULL;
        double px = 0;
        svp_status st = svp_psf_field_read(out->path, &field, &px);
        if (st != SVP_OK) return svp_yaml_fail(file, st, "%s: %s", qn, svp_last_error());
        int fw = svp_psf_field_width(field), fh = svp_psf_field_height(field);
        svp_psf_field_free(field);
        if (fabs(px - s->pixel_um) > 1e-6 * s->pixel_um)
            return svp_yaml_fail(file, SVP_ERR_INVALID,
                                 "%s: '%s' is for pixels of %g um but grid.pixel_um is %g", qn, rel,
                                 px, s->pixel_um);
        if (fw != 0 && (fw != want_w || fh != want_h))
            return svp_yaml_fail(file, SVP_ERR_SIZE,
                                 "%s: the PSF map '%s' is for %d x %d pixels but the %s is "
                                 "%d x %d",
                                 qn, rel, fw, fh,
                                 want_w == s->canvas_w && want_h == s->canvas_h ? "canvas" : "view",
                                 want_w, want_h);
        snprintf(out->describe, sizeof out->describe, "%s PSF from %s",
                 fw ? "space-variant" : "invariant", rel);
        return SVP_OK;
    }
    int model = 0;
    SVP_CHECK(get_choice(p, what, "model", model_names, &model, 1));
    double fwhm_um = 0;
    SVP_CHECK(get_num(p, what, "fwhm_um", 0, INFINITY, SVP_YAML_OPEN_LO, &fwhm_um, 1));
    svp_psf q;
    svp_psf_defaults(&q);
    q.model = (svp_psf_model)model;
    q.fwhm = fwhm_um / s->pixel_um;
    const svp_yaml_node *bn = svp_yaml_get(p, "beta");
    char qn[128];
    if (bn) {
        SVP_CHECK(svp_yaml_number_in(bn, qname(qn, sizeof qn, what, "beta"), 0, INFINITY,
                                     SVP_YAML_OPEN_LO, &q.beta));
        if (q.model == SVP_PSF_GAUSSIAN)
            return svp_yaml_fail(bn, SVP_ERR_INVALID,
                                 "%s.beta does not apply to a gaussian PSF (use model: moffat)",
                                 what);
        if (q.model == SVP_PSF_LORENTZIAN && q.beta != 1.0)
            return svp_yaml_fail(bn, SVP_ERR_INVALID,
                                 "%s.beta must be 1 for a lorentzian PSF (use model: moffat)",
                                 what);
    } else if (q.model == SVP_PSF_MOFFAT) {
        return svp_yaml_fail(p, SVP_ERR_FORMAT,
                             "missing required key 'beta' in %s (a moffat "
                             "PSF needs its beta)",
                             what);
    }
    if (q.model == SVP_PSF_LORENTZIAN) q.beta = 1.0;
    SVP_CHECK(get_num(p, what, "halo", 0, 1, SVP_YAML_OPEN_HI, &q.halo, 0));
    double minor_um = 0, angle_deg = 0, support_um = 0;
    const svp_yaml_node *mn = svp_yaml_get(p, "fwhm_minor_um");
    if (mn) {
        SVP_CHECK(get_num(p, what, "fwhm_minor_um", 0, fwhm_um, SVP_YAML_OPEN_LO, &minor_um, 1));
        q.fwhm_minor = minor_um / s->pixel_um;
    }
    SVP_CHECK(get_num(p, what, "angle_deg", -INFINITY, INFINITY, 0, &angle_deg, 0));
    q.angle = angle_deg * M_PI / 180;
    SVP_CHECK(get_num(p, what, "support_um", 0, INFINITY, 0, &support_um, 0));
    q.support = support_um / s->pixel_um;
    const svp_yaml_node *ss = svp_yaml_get(p, "subsample");
    if (ss) {
        long long sub = 0;
        SVP_CHECK(svp_yaml_int(ss, qname(qn, sizeof qn, what, "subsample"), 0, 64, &sub));
        q.subsample = (int)sub;
    }
    svp_status st = svp_psf_validate(&q);
    if (st != SVP_OK) return svp_yaml_fail(p, st, "%s: %s", what, svp_last_error());
    out->psf = q;
    int n =
        snprintf(out->describe, sizeof out->describe, "%s FWHM %g um", model_names[model], fwhm_um);
    if (q.model == SVP_PSF_MOFFAT && n > 0)
        n += snprintf(out->describe + n, sizeof out->describe - (size_t)n, " beta %g", q.beta);
    if (q.halo > 0 && n > 0 && (size_t)n < sizeof out->describe)
        n += snprintf(out->describe + n, sizeof out->describe - (size_t)n, " halo %g", q.halo);
    if (q.fwhm_minor > 0 && n > 0 && (size_t)n < sizeof out->describe)
        n += snprintf(out->describe + n, sizeof out->describe - (size_t)n, " minor %g um %g deg",
                      minor_um, angle_deg);
    return parse_psf_regions(s, p, what, &q, out, n);
}

/* ---- effects -------------------------------------------------------------------------------- */

static svp_status parse_effects(struct svp_scene *s, const svp_yaml_node *root)
{
    static const char *const keys[] = {"noise", "spectrum", "drift", NULL};
    const svp_yaml_node *e = svp_yaml_get(root, "effects");
    s->linewidth_hz = 1e6;
    s->contrast = 0.02;
    s->zero_field_hz = 2.87e9;
    s->span_linewidths = 6;
    s->spectrum_points = 100;
    s->noise_linewidth_hz = 1e6;
    s->noise_contrast = 0.02;
    if (!e || svp_yaml_type_of(e) == SVP_YAML_NULL) return SVP_OK;
    SVP_CHECK(check_keys(e, "effects", keys));

    const svp_yaml_node *sp = svp_yaml_get(e, "spectrum");
    if (sp) {
        static const char *const skeys[] = {"points",           "linewidth_MHz",  "contrast",
                                            "contrast_pattern", "estimator",      "bias_mT",
                                            "span_linewidths",  "zero_field_GHz", NULL};
        static const char *const estimators[] = {"centroid", "lorentzian_fit", NULL};
        const char *w = "effects.spectrum";
        s->spectrum = 1;
        if (svp_yaml_type_of(sp) != SVP_YAML_NULL) {
            SVP_CHECK(check_keys(sp, w, skeys));
            const svp_yaml_node *pn = svp_yaml_get(sp, "points");
            if (pn) {
                long long pts = 0;
                SVP_CHECK(svp_yaml_int(pn, "effects.spectrum.points", 5, 4000, &pts));
                s->spectrum_points = (int)pts;
            }
            double mhz = 1;
            SVP_CHECK(get_num(sp, w, "linewidth_MHz", 0, INFINITY, SVP_YAML_OPEN_LO, &mhz, 0));
            s->linewidth_hz = mhz * 1e6;
            SVP_CHECK(get_num(sp, w, "contrast", 0, 0.5, SVP_YAML_OPEN_LO, &s->contrast, 0));
            SVP_CHECK(get_choice(sp, w, "estimator", estimators, &s->estimator, 0));
            double bias_mt = 0;
            SVP_CHECK(get_num(sp, w, "bias_mT", 0, INFINITY, 0, &bias_mt, 0));
            s->bias_t = bias_mt * 1e-3;
            SVP_CHECK(get_num(sp, w, "span_linewidths", 0.5, 1000, 0, &s->span_linewidths, 0));
            double ghz = 2.87;
            SVP_CHECK(get_num(sp, w, "zero_field_GHz", 0, INFINITY, SVP_YAML_OPEN_LO, &ghz, 0));
            s->zero_field_hz = ghz * 1e9;
            const svp_yaml_node *cp = svp_yaml_get(sp, "contrast_pattern");
            if (cp)
                SVP_CHECK(parse_factors(s, cp, "effects.spectrum.contrast_pattern",
                                        &s->contrast_pattern, &s->n_contrast_pattern));
        }
        s->noise_linewidth_hz = s->linewidth_hz;
        s->noise_contrast = s->contrast;
    }

    const svp_yaml_node *nz = svp_yaml_get(e, "noise");
    if (nz) {
        static const char *const nkeys[] = {"photons_per_pixel", "seed", "linewidth_MHz",
                                            "contrast", NULL};
        const char *w = "effects.noise";
        s->noise = 1;
        SVP_CHECK(check_keys(nz, w, nkeys));
        /* at least one photon at the brightest pixel, a dip of at least 1 ppm and a line
         * narrower than 10 GHz: beyond those the noise amplitudes overflowed the correction,
         * whose line was then blamed (a noise of 1e-300 photons gave a PL of 3e150) */
        SVP_CHECK(get_num(nz, w, "photons_per_pixel", 1, INFINITY, 0, &s->photons, 1));
        long long seed = 1;
        const svp_yaml_node *sn = svp_yaml_get(nz, "seed");
        if (sn) SVP_CHECK(svp_yaml_int(sn, "effects.noise.seed", 0, INT64_MAX, &seed));
        s->noise_seed = (uint64_t)seed;
        const char *odmr_keys[] = {"linewidth_MHz", "contrast"};
        for (int k = 0; k < 2; k++) {
            const svp_yaml_node *kn = svp_yaml_get(nz, odmr_keys[k]);
            if (kn && s->spectrum)
                return svp_yaml_fail(kn, SVP_ERR_FORMAT,
                                     "effects.noise.%s: with the spectrum effect the ODMR line "
                                     "is set in effects.spectrum (the noise then falls on the "
                                     "frames)",
                                     odmr_keys[k]);
        }
        if (!s->spectrum) {
            double mhz = 1;
            SVP_CHECK(get_num(nz, w, "linewidth_MHz", 0, 1e4, SVP_YAML_OPEN_LO, &mhz, 0));
            s->noise_linewidth_hz = mhz * 1e6;
            SVP_CHECK(get_num(nz, w, "contrast", 1e-6, 0.5, 0, &s->noise_contrast, 0));
        }
    }

    const svp_yaml_node *dr = svp_yaml_get(e, "drift");
    if (dr) {
        static const char *const dkeys[] = {"total_um", "register", NULL};
        if (!s->spectrum)
            return svp_yaml_fail(dr, SVP_ERR_INVALID,
                                 "effects.drift needs effects.spectrum: drift shifts the "
                                 "spectral frames, which exist only in the simulated cube");
        SVP_CHECK(check_keys(dr, "effects.drift", dkeys));
        SVP_CHECK(get_pair(dr, "effects.drift", "total_um", s->drift_um, 1));
        SVP_CHECK(get_bool(dr, "effects.drift", "register", &s->drift_register));
        s->drift = 1;
    }
    return SVP_OK;
}

/* ---- corrections and reconstructions ----------------------------------------------------- */

static svp_status parse_one_correct(struct svp_scene *s, const svp_yaml_node *c, const char *what,
                                    scene_correct *out)
{
    static const char *const keys[] = {"method",    "iterations",   "balance",  "pl_floor",
                                       "psf",       "name",         "margin",   "precision",
                                       "acceleration", "tail_tol", NULL};
    static const char *const precisions[] = {"double", "single", NULL};
    static const char *const accelerations[] = {"none", "biggs-andrews", NULL};
    static const char *const methods[] = {"rw", "r", "w", "rl_signed", "cube", NULL};
    SVP_CHECK(check_keys(c, what, keys));
    where_of(c, out->where);
    int m = 0;
    SVP_CHECK(get_choice(c, what, "method", methods, &m, 1));
    out->method = m == 0   ? SVP_METHOD_RW
                  : m == 2 ? SVP_METHOD_W
                  : m == 3 ? SVP_METHOD_RL_SIGNED
                           : SVP_METHOD_R;
    out->cube = m == 4;
    if (out->cube && !s->spectrum)
        return svp_yaml_fail(c, SVP_ERR_INVALID,
                             "%s: method cube deconvolves the frames of the ODMR cube, which "
                             "needs effects.spectrum",
                             what);
    snprintf(out->name, sizeof out->name, "%s", methods[m]);
    SVP_CHECK(get_name(c, what, out->name));
    /* the reference study's simulation settings (docs/model.md §12) */
    out->iterations = 15;
    out->balance = 1;
    out->pl_floor = 1e-3;
    const svp_yaml_node *it = svp_yaml_get(c, "iterations");
    char qn[128];
    if (it) {
        long long v = 0;
        SVP_CHECK(svp_yaml_int(it, qname(qn, sizeof qn, what, "iterations"), 1, 100000, &v));
        out->iterations = (int)v;
    }
    SVP_CHECK(get_num(c, what, "balance", 0, INFINITY, 0, &out->balance, 0));
    SVP_CHECK(get_num(c, what, "pl_floor", 0, 1, SVP_YAML_OPEN_HI, &out->pl_floor, 0));
    int prec = 0;
    SVP_CHECK(get_choice(c, what, "precision", precisions, &prec, 0));
    out->single = prec == 1;
    int acc = 0;
    SVP_CHECK(get_choice(c, what, "acceleration", accelerations, &acc, 0));
    out->accelerated = acc == 1;
    out->tail_tol = SVP_TAIL_TOL_DEFAULT;
    SVP_CHECK(get_num(c, what, "tail_tol", 0, 1, SVP_YAML_OPEN_HI, &out->tail_tol, 0));
    const svp_yaml_node *mg = svp_yaml_get(c, "margin");
    const char *mtext = NULL;
    if (mg && svp_yaml_type_of(mg) == SVP_YAML_SCALAR &&
        svp_yaml_string(mg, "margin", &mtext) == SVP_OK && strcmp(mtext, "auto") == 0) {
        out->margin_px = -1;
    } else if (mg) {
        double um = 0;
        SVP_CHECK(svp_yaml_number_in(mg, qname(qn, sizeof qn, what, "margin"), 0, 1e4, 0, &um));
        out->margin_px = (int)lround(um / s->pixel_um);
    }
    const svp_yaml_node *p = svp_yaml_get(c, "psf");
    if (p) {
        char w[96];
        snprintf(w, sizeof w, "%s.psf", what);
        out->has_psf = 1;
        SVP_CHECK(parse_psf(s, p, w, s->view_w, s->view_h, &out->psf));
    }
    return SVP_OK;
}

static svp_status parse_correct(struct svp_scene *s, const svp_yaml_node *root)
{
    const svp_yaml_node *c = svp_yaml_get(root, "correct");
    if (!c || svp_yaml_type_of(c) == SVP_YAML_NULL) return SVP_OK;
    if (svp_yaml_type_of(c) == SVP_YAML_MAPPING) {
        s->n_correct = 1;
        return parse_one_correct(s, c, "correct", &s->correct[0]);
    }
    size_t n = svp_yaml_size(c);
    if (svp_yaml_type_of(c) != SVP_YAML_SEQUENCE || n < 1 || n > SCENE_MAX_CORRECT)
        return svp_yaml_fail(c, SVP_ERR_FORMAT,
                             "correct must be a mapping {method: ...} or a list of 1 to %d of "
                             "them",
                             SCENE_MAX_CORRECT);
    for (size_t i = 0; i < n; i++) {
        char w[32];
        snprintf(w, sizeof w, "correct[%zu]", i);
        SVP_CHECK(parse_one_correct(s, svp_yaml_item(c, i), w, &s->correct[i]));
        for (size_t k = 0; k < i; k++)
            if (strcmp(s->correct[k].name, s->correct[i].name) == 0)
                return svp_yaml_fail(svp_yaml_item(c, i), SVP_ERR_INVALID,
                                     "%s: a second correction named '%s' (give each a distinct "
                                     "'name': it names the outputs)",
                                     w, s->correct[i].name);
        s->n_correct = (int)i + 1;
    }
    return SVP_OK;
}

static svp_status parse_one_recon(struct svp_scene *s, const svp_yaml_node *r, const char *what,
                                  scene_recon *out)
{
    static const char *const quantities[] = {"magnetisation", "current_from_bz", "current_from_bxy",
                                             NULL};
    static const char *const keys[] = {"quantity", "standoff_nm", "cutoff_per_um",
                                       "window",   "pad",         "method", NULL};
    static const char *const pads[] = {"taper", "mean", "none", NULL};
    static const char *const methods[] = {"fourier", "support", NULL};
    where_of(r, out->where);
    const svp_yaml_node *qnode = r;
    int q = 0;
    out->window = 1;
    out->pad = SVP_PAD_TAPER;
    out->method = SVP_RECON_FOURIER;
    if (svp_yaml_type_of(r) == SVP_YAML_MAPPING) {
        SVP_CHECK(check_keys(r, what, keys));
        SVP_CHECK(get_choice(r, what, "quantity", quantities, &q, 1));
        qnode = svp_yaml_get(r, "quantity");
        SVP_CHECK(
            get_num(r, what, "standoff_nm", 0, INFINITY, SVP_YAML_OPEN_LO, &out->standoff_nm, 0));
        SVP_CHECK(get_num(r, what, "cutoff_per_um", 0, INFINITY, SVP_YAML_OPEN_LO,
                          &out->cutoff_per_um, 0));
        SVP_CHECK(get_bool(r, what, "window", &out->window));
        int pad = 0;
        SVP_CHECK(get_choice(r, what, "pad", pads, &pad, 0));
        out->pad = (svp_pad_mode)pad;
        int method = 0;
        SVP_CHECK(get_choice(r, what, "method", methods, &method, 0));
        out->method = (svp_recon_method)method;
        if (method && q != 0)
            return svp_yaml_fail(svp_yaml_get(r, "method"), SVP_ERR_INVALID,
                                 "%s: method support finds magnetisation only (the current "
                                 "uses the Fourier method)",
                                 what);
        if (method && pad == SVP_PAD_NONE)
            return svp_yaml_fail(svp_yaml_get(r, "method"), SVP_ERR_INVALID,
                                 "%s: method support needs a padded canvas (pad taper or mean)",
                                 what);
    } else {
        SVP_CHECK(svp_yaml_choice(r, what, quantities, &q));
    }
    out->kind = (scene_recon_kind)q;
    static const char *const names[] = {"m_z", "J_bz", "J_bxy"};
    snprintf(out->name, sizeof out->name, "%s", names[q]);
    if (out->kind != RECON_CURRENT_BXY && !scene_has_component(s, 2))
        return svp_yaml_fail(qnode, SVP_ERR_INVALID, "%s: %s needs B_z: add z to field.components",
                             what, quantities[q]);
    if (out->kind == RECON_CURRENT_BXY && !scene_has_component(s, 0) && !scene_has_component(s, 1))
        return svp_yaml_fail(qnode, SVP_ERR_INVALID,
                             "%s: current_from_bxy needs B_x and/or B_y: add x (and y) to "
                             "field.components",
                             what);
    if (out->standoff_nm == 0) {
        /* the standoff of the first source of the matching kind, else of any source */
        scene_source_kind want = out->kind == RECON_MAGNETISATION ? SRC_FLAKE : SRC_STRIP;
        for (int i = 0; i < s->n_sources && out->standoff_nm == 0; i++)
            if (s->sources[i].kind == want) out->standoff_nm = s->sources[i].standoff_nm;
        for (int i = 0; i < s->n_sources && out->standoff_nm == 0; i++)
            out->standoff_nm = s->sources[i].standoff_nm;
        if (out->standoff_nm == 0)
            return svp_yaml_fail(r, SVP_ERR_FORMAT,
                                 "%s: no source gives a standoff: add standoff_nm (as a mapping "
                                 "{quantity: %s, standoff_nm: ...})",
                                 what, quantities[q]);
    }
    return SVP_OK;
}

static svp_status parse_recon(struct svp_scene *s, const svp_yaml_node *root)
{
    const svp_yaml_node *r = svp_yaml_get(root, "reconstruct");
    if (!r || svp_yaml_type_of(r) == SVP_YAML_NULL) return SVP_OK;
    if (svp_yaml_type_of(r) != SVP_YAML_SEQUENCE) {
        s->n_recon = 1;
        return parse_one_recon(s, r, "reconstruct", &s->recon[0]);
    }
    size_t n = svp_yaml_size(r);
    if (n < 1 || n > SCENE_MAX_RECON)
        return svp_yaml_fail(r, SVP_ERR_FORMAT,
                             "reconstruct must be one of magnetisation, current_from_bz, "
                             "current_from_bxy (or a mapping with 'quantity'), or a list of up "
                             "to %d",
                             SCENE_MAX_RECON);
    for (size_t i = 0; i < n; i++) {
        char w[32];
        snprintf(w, sizeof w, "reconstruct[%zu]", i);
        SVP_CHECK(parse_one_recon(s, svp_yaml_item(r, i), w, &s->recon[i]));
        for (size_t k = 0; k < i; k++)
            if (s->recon[k].kind == s->recon[i].kind)
                return svp_yaml_fail(svp_yaml_item(r, i), SVP_ERR_INVALID, "%s: %s is listed twice",
                                     w, s->recon[i].name);
        s->n_recon = (int)i + 1;
    }
    return SVP_OK;
}

/* ---- metrics and outputs ------------------------------------------------------------------- */

static svp_status add_mask(struct svp_scene *s, const char *name, scene_mask_region inside,
                           double erode_um, double lit_above)
{
    if (s->n_masks >= SCENE_MAX_MASKS) return SVP_OK;
    scene_mask *m = &s->masks[s->n_masks++];
    memset(m, 0, sizeof *m);
    snprintf(m->name, sizeof m->name, "%s", name);
    m->inside = inside;
    m->erode_um = erode_um;
    m->lit_above = lit_above;
    return SVP_OK;
}

static int emission_is_uniform(const struct svp_scene *s)
{
    for (int i = 0; i < s->n_emission; i++)
        if (s->emission[i].kind != EM_UNIFORM) return 0;
    return 1;
}

static svp_status parse_metrics(struct svp_scene *s, const svp_yaml_node *root)
{
    static const char *const keys[] = {
        "masks", "line_cuts", "histogram_bins", "histogram_range_pct", "local_floor", NULL};
    static const char *const mkeys[] = {"name", "inside", "outside", "erode_um", "lit_above", NULL};
    static const char *const regions[] = {"all", "sources", "flakes", "strips", NULL};
    s->hist_bins = 101;
    s->local_floor = 0.05;
    const svp_yaml_node *m = svp_yaml_get(root, "metrics");
    const svp_yaml_node *masks = NULL, *cuts = NULL;
    if (m && svp_yaml_type_of(m) != SVP_YAML_NULL) {
        SVP_CHECK(check_keys(m, "metrics", keys));
        const svp_yaml_node *hb = svp_yaml_get(m, "histogram_bins");
        if (hb) {
            long long v = 0;
            SVP_CHECK(svp_yaml_int(hb, "metrics.histogram_bins", 5, 10000, &v));
            s->hist_bins = (int)v;
        }
        SVP_CHECK(get_num(m, "metrics", "histogram_range_pct", 0, INFINITY, SVP_YAML_OPEN_LO,
                          &s->hist_range_pct, 0));
        SVP_CHECK(get_num(m, "metrics", "local_floor", 0, 1, SVP_YAML_OPEN_HI, &s->local_floor, 0));
        masks = svp_yaml_get(m, "masks");
        cuts = svp_yaml_get(m, "line_cuts");
    }
    if (masks) {
        size_t n = svp_yaml_size(masks);
        if (svp_yaml_type_of(masks) != SVP_YAML_SEQUENCE || n < 1 || n > SCENE_MAX_MASKS)
            return svp_yaml_fail(masks, SVP_ERR_FORMAT,
                                 "metrics.masks must be a list of 1 to %d masks {name, inside | "
                                 "outside, erode_um, lit_above}",
                                 SCENE_MAX_MASKS);
        for (size_t i = 0; i < n; i++) {
            const svp_yaml_node *mk = svp_yaml_item(masks, i);
            char w[48];
            snprintf(w, sizeof w, "metrics.masks[%zu]", i);
            SVP_CHECK(check_keys(mk, w, mkeys));
            scene_mask *q = &s->masks[s->n_masks];
            memset(q, 0, sizeof *q);
            where_of(mk, q->where);
            if (!svp_yaml_get(mk, "name"))
                return svp_yaml_fail(mk, SVP_ERR_FORMAT, "missing required key 'name' in %s", w);
            SVP_CHECK(get_name(mk, w, q->name));
            for (int k = 0; k < s->n_masks; k++)
                if (strcmp(s->masks[k].name, q->name) == 0)
                    return svp_yaml_fail(svp_yaml_get(mk, "name"), SVP_ERR_INVALID,
                                         "%s: a second mask named '%s'", w, q->name);
            const svp_yaml_node *in = svp_yaml_get(mk, "inside"),
                                *out = svp_yaml_get(mk, "outside");
            if (in && out)
                return svp_yaml_fail(out, SVP_ERR_FORMAT,
                                     "%s: give 'inside' or 'outside', not "
                                     "both",
                                     w);
            const svp_yaml_node *rn = in ? in : out;
            q->inside = MASK_ALL;
            if (rn) {
                q->outside = out != NULL;
                if (svp_yaml_type_of(rn) == SVP_YAML_MAPPING) {
                    static const char *const fkeys[] = {"file", NULL};
                    char fw[64];
                    snprintf(fw, sizeof fw, "%s.%s", w, in ? "inside" : "outside");
                    SVP_CHECK(check_keys(rn, fw, fkeys));
                    svp_image *img = NULL;
                    SVP_CHECK(get_image(s, rn, fw, "file", &q->path, &img));
                    svp_image_free(img);
                    q->inside = MASK_FILE;
                } else {
                    int r = 0;
                    char rw[64];
                    snprintf(rw, sizeof rw, "%s.%s", w, in ? "inside" : "outside");
                    SVP_CHECK(svp_yaml_choice(rn, rw, regions, &r));
                    q->inside = (scene_mask_region)r;
                    if ((q->inside == MASK_FLAKES && s->n_flakes == 0) ||
                        (q->inside == MASK_STRIPS && s->n_strips == 0) ||
                        (q->inside == MASK_SOURCES && s->n_flakes + s->n_strips == 0))
                        return svp_yaml_fail(rn, SVP_ERR_INVALID,
                                             "%s: the scene has no %s (sources from files have "
                                             "no outline)",
                                             rw, regions[r]);
                    if (q->inside == MASK_ALL && q->outside)
                        return svp_yaml_fail(rn, SVP_ERR_INVALID,
                                             "%s: outside all would leave no pixel", rw);
                }
            }
            SVP_CHECK(get_num(mk, w, "erode_um", 0, INFINITY, 0, &q->erode_um, 0));
            SVP_CHECK(get_num(mk, w, "lit_above", 0, 1, SVP_YAML_OPEN_HI, &q->lit_above, 0));
            s->n_masks++;
        }
    } else {
        add_mask(s, "view", MASK_ALL, 0, 0);
        if (s->n_flakes) add_mask(s, "flake", MASK_FLAKES, 0, 0);
        if (s->n_strips) add_mask(s, "strip", MASK_STRIPS, 0, 0);
        if (!emission_is_uniform(s)) add_mask(s, "lit", MASK_ALL, 0, 0.3);
    }
    if (cuts) {
        static const char *const ckeys[] = {"name", "from_um", "to_um", NULL};
        size_t n = svp_yaml_size(cuts);
        if (svp_yaml_type_of(cuts) != SVP_YAML_SEQUENCE || n < 1 || n > SCENE_MAX_CUTS)
            return svp_yaml_fail(cuts, SVP_ERR_FORMAT,
                                 "metrics.line_cuts must be a list of 1 to %d cuts {name, "
                                 "from_um: [x, y], to_um: [x, y]}",
                                 SCENE_MAX_CUTS);
        double hx = 0.5 * (s->view_w - 1) * s->pixel_um, hy = 0.5 * (s->view_h - 1) * s->pixel_um;
        for (size_t i = 0; i < n; i++) {
            const svp_yaml_node *c = svp_yaml_item(cuts, i);
            char w[48];
            snprintf(w, sizeof w, "metrics.line_cuts[%zu]", i);
            SVP_CHECK(check_keys(c, w, ckeys));
            scene_cut *q = &s->cuts[s->n_cuts];
            memset(q, 0, sizeof *q);
            where_of(c, q->where);
            snprintf(q->name, sizeof q->name, "cut%zu", i);
            SVP_CHECK(get_name(c, w, q->name));
            for (int k = 0; k < s->n_cuts; k++)
                if (strcmp(s->cuts[k].name, q->name) == 0)
                    return svp_yaml_fail(c, SVP_ERR_INVALID, "%s: a second line cut named '%s'", w,
                                         q->name);
            SVP_CHECK(get_pair(c, w, "from_um", q->from_um, 1));
            SVP_CHECK(get_pair(c, w, "to_um", q->to_um, 1));
            const char *ends[] = {"from_um", "to_um"};
            const double *pts[] = {q->from_um, q->to_um};
            for (int e = 0; e < 2; e++)
                if (fabs(pts[e][0]) > hx + 1e-9 || fabs(pts[e][1]) > hy + 1e-9)
                    return svp_yaml_fail(svp_yaml_get(c, ends[e]), SVP_ERR_INVALID,
                                         "%s.%s = [%g, %g] lies outside the view (pixel centres "
                                         "span x +-%g um, y +-%g um from its centre)",
                                         w, ends[e], pts[e][0], pts[e][1], hx, hy);
            if (hypot(q->to_um[0] - q->from_um[0], q->to_um[1] - q->from_um[1]) < s->pixel_um)
                return svp_yaml_fail(c, SVP_ERR_INVALID, "%s is shorter than one pixel", w);
            s->n_cuts++;
        }
    } else {
        scene_cut *q = &s->cuts[s->n_cuts++];
        memset(q, 0, sizeof *q);
        snprintf(q->name, sizeof q->name, "horizontal");
        double hx = 0.5 * (s->view_w - 1) * s->pixel_um;
        /* through the pixel row nearest the centre */
        double yc = s->view_h % 2 ? 0 : -0.5 * s->pixel_um;
        q->from_um[0] = -hx;
        q->to_um[0] = hx;
        q->from_um[1] = q->to_um[1] = yc;
    }
    return SVP_OK;
}

static svp_status parse_outputs(struct svp_scene *s, const svp_yaml_node *root)
{
    static const char *const keys[] = {"maps", "figures", "format", "canvas", NULL};
    static const char *const formats[] = {"tif", "npy", "txt", NULL};
    s->write_maps = 1;
    s->write_figures = 1;
    s->format = SVP_FORMAT_TIFF;
    const svp_yaml_node *o = svp_yaml_get(root, "outputs");
    if (!o || svp_yaml_type_of(o) == SVP_YAML_NULL) return SVP_OK;
    SVP_CHECK(check_keys(o, "outputs", keys));
    SVP_CHECK(get_bool(o, "outputs", "maps", &s->write_maps));
    SVP_CHECK(get_bool(o, "outputs", "figures", &s->write_figures));
    SVP_CHECK(get_bool(o, "outputs", "canvas", &s->write_canvas));
    int f = 0;
    SVP_CHECK(get_choice(o, "outputs", "format", formats, &f, 0));
    s->format = f == 0 ? SVP_FORMAT_TIFF : f == 1 ? SVP_FORMAT_NPY : SVP_FORMAT_TXT;
    return SVP_OK;
}

/* ---- the whole file ------------------------------------------------------------------------ */

static svp_status parse_scene(struct svp_scene *s, const svp_yaml_node *root)
{
    static const char *const keys[] = {
        "name", "description", "grid",    "sensor",      "sources", "field",   "emission",
        "psf",  "effects",     "correct", "reconstruct", "metrics", "outputs", NULL};
    if (svp_yaml_type_of(root) != SVP_YAML_MAPPING)
        return svp_yaml_fail(root, SVP_ERR_FORMAT,
                             "a scene file is a mapping with grid, sources, psf, ... "
                             "(docs/scenes.md)");
    SVP_CHECK(check_keys(root, NULL, keys));
    const svp_yaml_node *nn = svp_yaml_get(root, "name");
    if (nn) {
        const char *name = NULL;
        SVP_CHECK(svp_yaml_string(nn, "name", &name));
        if (strlen(name) > 100)
            return svp_yaml_fail(nn, SVP_ERR_INVALID, "name is longer than 100 characters");
        free(s->name);
        s->name = dup_text(name);
    }
    const char *desc = NULL;
    const svp_yaml_node *dn = svp_yaml_get(root, "description");
    if (dn) {
        SVP_CHECK(svp_yaml_string(dn, "description", &desc));
        s->description = dup_text(desc);
    }
    SVP_CHECK(parse_grid(s, root));
    SVP_CHECK(parse_sensor(s, root));
    SVP_CHECK(parse_sources(s, root));
    SVP_CHECK(parse_field(s, root));
    const svp_yaml_node *em = svp_yaml_get(root, "emission");
    if (em) SVP_CHECK(parse_factors(s, em, "emission", &s->emission, &s->n_emission));
    const svp_yaml_node *p = NULL;
    SVP_CHECK(svp_yaml_require(root, "psf", NULL, &p));
    SVP_CHECK(parse_psf(s, p, "psf", s->canvas_w, s->canvas_h, &s->psf));
    SVP_CHECK(parse_effects(s, root));
    SVP_CHECK(parse_correct(s, root));
    SVP_CHECK(parse_recon(s, root));
    SVP_CHECK(parse_metrics(s, root));
    SVP_CHECK(parse_outputs(s, root));
    /* a correction that assumes a PSF map needs one for the view (the correction works on the
     * cropped measurement) */
    for (int k = 0; k < s->n_correct; k++) {
        const scene_psf *cp = s->correct[k].has_psf ? &s->correct[k].psf : &s->psf;
        if (!cp->from_file) continue;
        svp_psf_field *f = NULL;
        if (svp_psf_field_read(cp->path, &f, NULL) != SVP_OK) continue;
        int fw = svp_psf_field_width(f), fh = svp_psf_field_height(f);
        svp_psf_field_free(f);
        if (fw != 0 && s->margin_px > 0 && !s->correct[k].has_psf)
            return svp_yaml_fail(svp_yaml_get(root, "correct"), SVP_ERR_INVALID,
                                 "correct: the scene's PSF map is for the canvas (%d x %d) but "
                                 "the correction works on the view (%d x %d): give the "
                                 "correction its own psf",
                                 fw, fh, s->view_w, s->view_h);
    }
    return SVP_OK;
}

/* ---- public API: load, free, accessors ----------------------------------------------------- */

static void free_factors(scene_factor *f, int n)
{
    for (int i = 0; i < n; i++) free(f[i].path);
    free(f);
}

void svp_scene_free(svp_scene *s)
{
    if (!s) return;
    for (int i = 0; i < s->n_sources; i++) {
        free(s->sources[i].vertices_um);
        free(s->sources[i].mask_path);
        free(s->sources[i].path);
    }
    free(s->sources);
    free_factors(s->emission, s->n_emission);
    free_factors(s->contrast_pattern, s->n_contrast_pattern);
    free(s->psf.path);
    for (int k = 0; k < SCENE_MAX_CORRECT; k++) free(s->correct[k].psf.path);
    for (int m = 0; m < SCENE_MAX_MASKS; m++) free(s->masks[m].path);
    for (int i = 0; i < s->n_outputs; i++) free(s->outputs[i]);
    free(s->outputs);
    free(s->plan);
    free(s->stages);
    free(s->path);
    free(s->dir);
    free(s->name);
    free(s->description);
    free(s);
}

static svp_status scene_from_doc(const char *name, svp_yaml_doc *doc, svp_scene **out)
{
    svp_scene *s = calloc(1, sizeof *s);
    if (!s) return svp_fail(SVP_ERR_NOMEM, "out of memory");
    s->path = dup_text(name);
    /* folder and stem of the file name */
    const char *slash = strrchr(name, '/');
    s->dir = slash ? malloc((size_t)(slash - name) + 1) : dup_text("");
    if (slash && s->dir) {
        memcpy(s->dir, name, (size_t)(slash - name));
        s->dir[slash - name] = '\0';
    }
    const char *base = slash ? slash + 1 : name;
    s->name = dup_text(base);
    if (!s->path || !s->dir || !s->name) {
        svp_scene_free(s);
        return svp_fail(SVP_ERR_NOMEM, "out of memory");
    }
    char *dot = strrchr(s->name, '.');
    if (dot && dot != s->name) *dot = '\0';
    svp_status st = parse_scene(s, svp_yaml_root(doc));
    if (st == SVP_OK) st = scene_compile_plan(s);
    if (st != SVP_OK) {
        svp_scene_free(s);
        return st;
    }
    *out = s;
    return SVP_OK;
}

svp_status svp_scene_load(const char *path, svp_scene **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_scene_load: out is NULL");
    *out = NULL;
    if (!path) return svp_fail(SVP_ERR_INVALID, "svp_scene_load: path is NULL");
    svp_yaml_doc *doc = NULL;
    SVP_CHECK(svp_yaml_load_file(path, &doc));
    svp_status st = scene_from_doc(path, doc, out);
    svp_yaml_free(doc);
    return st;
}

svp_status svp_scene_load_string(const char *name, const char *text, size_t len, svp_scene **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_scene_load_string: out is NULL");
    *out = NULL;
    if (!name || !text)
        return svp_fail(SVP_ERR_INVALID, "svp_scene_load_string: name or text is NULL");
    svp_yaml_doc *doc = NULL;
    SVP_CHECK(svp_yaml_load_string(name, text, len, &doc));
    svp_status st = scene_from_doc(name, doc, out);
    svp_yaml_free(doc);
    return st;
}

const char *svp_scene_name(const svp_scene *s) { return s ? s->name : NULL; }

double svp_scene_memory(const svp_scene *s) { return s ? scene_memory_estimate(s) : 0; }

void svp_scene_geometry(const svp_scene *s, double *pixel_um, int *view_w, int *view_h,
                        int *canvas_w, int *canvas_h)
{
    if (!s) return;
    if (pixel_um) *pixel_um = s->pixel_um;
    if (view_w) *view_w = s->view_w;
    if (view_h) *view_h = s->view_h;
    if (canvas_w) *canvas_w = s->canvas_w;
    if (canvas_h) *canvas_h = s->canvas_h;
}

int svp_scene_n_outputs(const svp_scene *s) { return s ? s->n_outputs : 0; }

const char *svp_scene_output(const svp_scene *s, int index)
{
    return s && index >= 0 && index < s->n_outputs ? s->outputs[index] : NULL;
}

/* ---- random numbers ------------------------------------------------------------------------ */

static uint64_t splitmix64(uint64_t x)
{
    x += 0x9E3779B97F4A7C15ULL;
    x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ULL;
    x = (x ^ (x >> 27)) * 0x94D049BB133111EBULL;
    return x ^ (x >> 31);
}

double scene_gauss(uint64_t seed, uint64_t stream, uint64_t index)
{
    uint64_t h = splitmix64(splitmix64(seed ^ 0x5CE7E5EEDULL) ^
                            splitmix64(stream * 0x632BE59BD9B4E019ULL) ^ index);
    uint64_t a = splitmix64(h), b = splitmix64(h ^ 0xD1B54A32D192ED03ULL);
    double u1 = ((double)(a >> 11) + 0.5) * (1.0 / 9007199254740992.0); /* (0, 1) */
    double u2 = (double)(b >> 11) * (1.0 / 9007199254740992.0);
    return sqrt(-2 * log(u1)) * cos(2 * M_PI * u2); /* Box–Muller */
}
