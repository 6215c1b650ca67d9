/* PSF-map files (YAML): a PSF field of any kind (uniform, grid, poly, regions with its label
 * image beside the file) read into and written from svp_psf_field (docs/cli.md §PSF-map files,
 * docs/model.md §9). The uniform PSF files are src/io/psf_file.c. */
#include "../psf/field_internal.h"
#include "yaml.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static const char *const model_names[] = {"gaussian", "lorentzian", "moffat", NULL};
#define RAD_PER_DEG (3.14159265358979323846 / 180.0)

/* One PSF entry {fwhm_um, fwhm_minor_um, angle_deg, beta, halo} (plus `extra` keys the caller
 * reads) into psf (model, support, subsample from base). */
static svp_status read_psf_entry(const svp_yaml_node *n, const char *what, const svp_psf *base,
                                 double pixel_um, const char *const *extra, svp_psf *psf)
{
    const char *keys[16] = {"fwhm_um", "fwhm_minor_um", "angle_deg", "beta", "halo"};
    int nk = 5;
    for (int i = 0; extra && extra[i] && nk < 15; i++) keys[nk++] = extra[i];
    keys[nk] = NULL;
    SVP_CHECK(svp_yaml_expect_mapping(n, what));
    SVP_CHECK(svp_yaml_check_keys(n, what, keys));
    const svp_yaml_node *v = NULL;
    double fwhm, minor = 0, angle = 0, beta = base->beta, halo = 0;
    SVP_CHECK(svp_yaml_require(n, "fwhm_um", what, &v));
    SVP_CHECK(svp_yaml_number_in(v, "fwhm_um", 0, INFINITY, SVP_YAML_OPEN_LO, &fwhm));
    SVP_CHECK(svp_yaml_get_number(n, "fwhm_minor_um", 0, INFINITY, 0, &minor, NULL));
    SVP_CHECK(svp_yaml_get_number(n, "angle_deg", -INFINITY, INFINITY, 0, &angle, NULL));
    int has_beta = 0;
    SVP_CHECK(svp_yaml_get_number(n, "beta", SVP_PSF_BETA_MIN, INFINITY, 0, &beta, &has_beta));
    if (!has_beta && base->model == SVP_PSF_MOFFAT)
        return svp_yaml_fail(n, SVP_ERR_FORMAT,
                             "missing required key 'beta' in %s (a Moffat "
                             "field)",
                             what);
    /* as the plain PSF file: beta belongs to Moffat fields (1 for Lorentzian) */
    if (has_beta && base->model == SVP_PSF_GAUSSIAN)
        return svp_yaml_fail(svp_yaml_get(n, "beta"), SVP_ERR_INVALID,
                             "beta does not apply to a gaussian field (use model: moffat)");
    if (has_beta && base->model == SVP_PSF_LORENTZIAN && beta != 1.0)
        return svp_yaml_fail(svp_yaml_get(n, "beta"), SVP_ERR_INVALID,
                             "beta must be 1 in a lorentzian field, got %g (use model: moffat)",
                             beta);
    SVP_CHECK(svp_yaml_get_number(n, "halo", 0, 1, SVP_YAML_OPEN_HI, &halo, NULL));
    *psf = *base;
    psf->fwhm = fwhm / pixel_um;
    psf->fwhm_minor = minor / pixel_um;
    psf->angle = angle * RAD_PER_DEG;
    psf->beta = base->model == SVP_PSF_LORENTZIAN ? 1.0 : beta;
    psf->halo = halo;
    svp_status st = svp_psf_validate(psf);
    if (st != SVP_OK) return svp_yaml_fail(n, st, "%s: %s", what, svp_last_error());
    return SVP_OK;
}

static svp_status write_psf_entry(svp_yaml_writer *w, const svp_psf *psf, double pixel_um)
{
    SVP_CHECK(svp_yaml_begin_mapping(w));
    SVP_CHECK(svp_yaml_write_key_number(w, "fwhm_um", psf->fwhm * pixel_um));
    if (psf->fwhm_minor > 0) {
        SVP_CHECK(svp_yaml_write_key_number(w, "fwhm_minor_um", psf->fwhm_minor * pixel_um));
        SVP_CHECK(svp_yaml_write_key_number(w, "angle_deg", psf->angle / RAD_PER_DEG));
    }
    if (psf->model == SVP_PSF_MOFFAT) SVP_CHECK(svp_yaml_write_key_number(w, "beta", psf->beta));
    SVP_CHECK(svp_yaml_write_key_number(w, "halo", psf->halo));
    return svp_yaml_end_mapping(w);
}

/* "dir/map.yaml" + "x.npy" → "dir/x.npy" (absolute names are kept). Caller frees. */
static char *sibling_path(const char *yaml_path, const char *name)
{
    if (name[0] == '/') return strdup(name);
    const char *slash = strrchr(yaml_path, '/');
    size_t dir = slash ? (size_t)(slash - yaml_path + 1) : 0;
    char *out = malloc(dir + strlen(name) + 1);
    if (!out) return NULL;
    memcpy(out, yaml_path, dir);
    strcpy(out + dir, name);
    return out;
}

/* The labels file written beside a map: "<path without .yaml/.yml>.labels.npy". */
static char *labels_path_for(const char *path)
{
    size_t n = strlen(path);
    if (n > 5 && strcmp(path + n - 5, ".yaml") == 0)
        n -= 5;
    else if (n > 4 && strcmp(path + n - 4, ".yml") == 0)
        n -= 4;
    char *out = malloc(n + sizeof ".labels.npy");
    if (!out) return NULL;
    memcpy(out, path, n);
    strcpy(out + n, ".labels.npy");
    return out;
}

static const char *const map_keys[] = {
    "version",     "pixel_um",      "image",   "model",      "support_um", "subsample",
    "kind",        "psf",           "nodes",   "node_psfs",  "degree",     "coefficients",
    "labels_file", "transition_um", "regions", "provenance", "comment",    NULL};
static const char *const kind_names[] = {"uniform", "grid", "poly", "regions", NULL};
static const char *const coef_names[] = {"fwhm_um", "e1", "e2", "beta", "halo", NULL};

/* What every kind of map gives: the pixel, the image size, the kind and the common model. */
typedef struct map_head {
    const char *path;
    double pixel_um;
    long long width, height; /* 0 x 0: a uniform map without `image` */
    int kind;
    svp_psf base; /* model, support, subsample; beta the model's default */
} map_head;

/* The keys every map has (version, pixel_um, kind, model, support_um, subsample, image), and
 * no key of another kind. */
static svp_status read_map_head(const char *path, const svp_yaml_node *root, map_head *m)
{
    const svp_yaml_node *v = NULL;
    double support_um = 0;
    long long subsample = 0, version = 1;
    int model = 0;
    memset(m, 0, sizeof *m);
    m->path = path;
    SVP_CHECK(svp_yaml_check_keys(root, NULL, map_keys));
    SVP_CHECK(svp_yaml_get_int(root, "version", 1, 1, &version, NULL));
    SVP_CHECK(svp_yaml_require(root, "pixel_um", NULL, &v));
    SVP_CHECK(svp_yaml_number_in(v, "pixel_um", SVP_PIXEL_UM_MIN, INFINITY, 0, &m->pixel_um));
    SVP_CHECK(svp_yaml_require(root, "kind", NULL, &v));
    SVP_CHECK(svp_yaml_choice(v, "kind", kind_names, &m->kind));
    SVP_CHECK(svp_yaml_require(root, "model", NULL, &v));
    SVP_CHECK(svp_yaml_choice(v, "model", model_names, &model));
    SVP_CHECK(svp_yaml_get_number(root, "support_um", 0, INFINITY, 0, &support_um, NULL));
    SVP_CHECK(svp_yaml_get_int(root, "subsample", 0, 64, &subsample, NULL));
    const int kind = m->kind;
    const svp_yaml_node *image = svp_yaml_get(root, "image");
    if (image) {
        static const char *const image_keys[] = {"width", "height", NULL};
        SVP_CHECK(svp_yaml_expect_mapping(image, "image"));
        SVP_CHECK(svp_yaml_check_keys(image, "image", image_keys));
        SVP_CHECK(svp_yaml_require(image, "width", "image", &v));
        SVP_CHECK(svp_yaml_int(v, "width", 1, 1 << 20, &m->width));
        SVP_CHECK(svp_yaml_require(image, "height", "image", &v));
        SVP_CHECK(svp_yaml_int(v, "height", 1, 1 << 20, &m->height));
    } else if (kind != SVP_FIELD_UNIFORM) {
        return svp_yaml_fail(root, SVP_ERR_FORMAT,
                             "missing required key 'image' (a %s map "
                             "needs the image size)",
                             kind_names[kind]);
    }
    /* keys that belong to another kind are mistakes worth naming */
    static const char *const kind_keys[4][4] = {{"psf", NULL},
                                                {"nodes", "node_psfs", NULL},
                                                {"degree", "coefficients", NULL},
                                                {"labels_file", "transition_um", "regions", NULL}};
    for (int k = 0; k < 4; k++)
        for (int i = 0; k != kind && kind_keys[k][i]; i++)
            if ((v = svp_yaml_get(root, kind_keys[k][i])))
                return svp_yaml_fail(v, SVP_ERR_FORMAT, "key '%s' does not belong to a %s map",
                                     kind_keys[k][i], kind_names[kind]);
    svp_psf_defaults(&m->base);
    m->base.model = (svp_psf_model)model;
    m->base.beta = model == SVP_PSF_LORENTZIAN ? 1.0 : 2.5;
    m->base.support = support_um / m->pixel_um;
    m->base.subsample = (int)subsample;
    return SVP_OK;
}

/* kind: uniform — one `psf`. */
static svp_status read_map_uniform(const map_head *m, const svp_yaml_node *root,
                                   svp_psf_field **out)
{
    const svp_yaml_node *v = NULL;
    svp_psf psf;
    SVP_CHECK(svp_yaml_require(root, "psf", NULL, &v));
    SVP_CHECK(read_psf_entry(v, "psf", &m->base, m->pixel_um, NULL, &psf));
    return svp_psf_field_new_uniform(&psf, (int)m->width, (int)m->height, out);
}

/* The node grid of a grid map: x_px / y_px (positions) or nx / ny (cell centres); nx, ny
 * hold 4096 values each. */
static svp_status read_map_nodes(const svp_yaml_node *root, const svp_yaml_node *nodes,
                                 double *nx, double *ny, size_t *cx_out, size_t *cy_out,
                                 int *has_positions)
{
    const svp_yaml_node *v = NULL;
    size_t cx = 0, cy = 0;
    int found = 0;
    if (!nodes)
        return svp_yaml_fail(root, SVP_ERR_FORMAT,
                             "missing required key 'nodes' (give "
                             "{nx: .., ny: ..} or {x_px: [..], y_px: [..]})");
    static const char *const node_keys[] = {"nx", "ny", "x_px", "y_px", NULL};
    SVP_CHECK(svp_yaml_expect_mapping(nodes, "nodes"));
    SVP_CHECK(svp_yaml_check_keys(nodes, "nodes", node_keys));
    int has_x = 0, has_y = 0;
    long long lnx = 0, lny = 0;
    if ((v = svp_yaml_get(nodes, "x_px"))) {
        SVP_CHECK(svp_yaml_number_list(v, "x_px", 1, 4096, nx, &cx));
        has_x = 1;
    }
    if ((v = svp_yaml_get(nodes, "y_px"))) {
        SVP_CHECK(svp_yaml_number_list(v, "y_px", 1, 4096, ny, &cy));
        has_y = 1;
    }
    SVP_CHECK(svp_yaml_get_int(nodes, "nx", 1, 4096, &lnx, &found));
    if (found) {
        if (has_x && (size_t)lnx != cx)
            return svp_yaml_fail(nodes, SVP_ERR_FORMAT,
                                 "nodes: nx = %lld but x_px has %zu "
                                 "values",
                                 lnx, cx);
        cx = (size_t)lnx;
    }
    SVP_CHECK(svp_yaml_get_int(nodes, "ny", 1, 4096, &lny, &found));
    if (found) {
        if (has_y && (size_t)lny != cy)
            return svp_yaml_fail(nodes, SVP_ERR_FORMAT,
                                 "nodes: ny = %lld but y_px has %zu "
                                 "values",
                                 lny, cy);
        cy = (size_t)lny;
    }
    if (!cx || !cy || has_x != has_y)
        return svp_yaml_fail(nodes, SVP_ERR_FORMAT,
                             "nodes needs both x_px and y_px, or nx and ny (then the nodes "
                             "sit at cell centres)");
    *cx_out = cx;
    *cy_out = cy;
    *has_positions = has_x;
    return SVP_OK;
}

/* kind: grid — `nodes` and one PSF per node (`node_psfs`, row by row). */
static svp_status read_map_grid(const map_head *m, const svp_yaml_node *root,
                                svp_psf_field **out)
{
    const svp_yaml_node *list = NULL, *nodes = svp_yaml_get(root, "nodes");
    size_t cx = 0, cy = 0;
    int has_positions = 0;
    SVP_CHECK(svp_yaml_require(root, "node_psfs", NULL, &list));
    if (svp_yaml_type_of(list) != SVP_YAML_SEQUENCE || svp_yaml_size(list) == 0)
        return svp_yaml_fail(list, SVP_ERR_FORMAT, "node_psfs must be a non-empty list");
    const size_t nk = svp_yaml_size(list);
    svp_status st = SVP_OK;
    double *nx = malloc(4096 * sizeof(double));
    double *ny = malloc(4096 * sizeof(double));
    svp_psf *psfs = malloc(nk * sizeof(svp_psf));
    if (!nx || !ny || !psfs) {
        st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory", m->path);
        goto cleanup;
    }
    if ((st = read_map_nodes(root, nodes, nx, ny, &cx, &cy, &has_positions))) goto cleanup;
    if (cx * cy != nk) {
        st = svp_yaml_fail(list, SVP_ERR_FORMAT,
                           "node_psfs has %zu entries but the node grid is %zu x %zu = %zu", nk,
                           cx, cy, cx * cy);
        goto cleanup;
    }
    for (size_t k = 0; k < nk; k++) {
        char what[48];
        snprintf(what, sizeof what, "node_psfs[%zu]", k);
        if ((st = read_psf_entry(svp_yaml_item(list, k), what, &m->base, m->pixel_um, NULL,
                                 &psfs[k])))
            goto cleanup;
    }
    st = svp_psf_field_new_grid((int)m->width, (int)m->height, (int)cx, (int)cy,
                                has_positions ? nx : NULL, has_positions ? ny : NULL, psfs, out);
    if (st != SVP_OK) st = svp_yaml_fail(nodes, st, "%s", svp_last_error());
cleanup:
    free(psfs);
    free(nx);
    free(ny);
    return st;
}

/* kind: poly — `degree` and per parameter the coefficients of its polynomial surface. */
static svp_status read_map_poly(const map_head *m, const svp_yaml_node *root,
                                svp_psf_field **out)
{
    const svp_yaml_node *v = NULL;
    long long degree = 0;
    const svp_yaml_node *coefs = NULL;
    SVP_CHECK(svp_yaml_require(root, "degree", NULL, &v));
    SVP_CHECK(svp_yaml_int(v, "degree", 0, SVP_FIELD_POLY_MAX_DEGREE, &degree));
    const int nt = svp_psf_field_poly_terms((int)degree);
    SVP_CHECK(svp_yaml_require(root, "coefficients", NULL, &coefs));
    SVP_CHECK(svp_yaml_expect_mapping(coefs, "coefficients"));
    SVP_CHECK(svp_yaml_check_keys(coefs, "coefficients", coef_names));
    double *values = calloc((size_t)nt * SVP_FIELD_NPARAM, sizeof(double));
    if (!values) return svp_fail(SVP_ERR_NOMEM, "%s: out of memory", m->path);
    svp_status st = SVP_OK;
    for (int q = 0; q < SVP_FIELD_NPARAM; q++) {
        size_t count = 0;
        v = svp_yaml_get(coefs, coef_names[q]);
        if (!v) {
            /* absent: constant — beta defaults to the model's, others to 0 */
            if (q == SVP_FIELD_FWHM) {
                st = svp_yaml_fail(coefs, SVP_ERR_FORMAT,
                                   "missing required key 'fwhm_um' in coefficients");
                goto cleanup;
            }
            if (q == SVP_FIELD_BETA) values[q * nt] = m->base.beta;
            continue;
        }
        if ((st = svp_yaml_number_list(v, coef_names[q], (size_t)nt, (size_t)nt,
                                       values + (size_t)q * nt, &count)))
            goto cleanup;
    }
    for (int t = 0; t < nt; t++) values[SVP_FIELD_FWHM * nt + t] /= m->pixel_um;
    st = svp_psf_field_new_poly(&m->base, (int)m->width, (int)m->height, (int)degree, values,
                                out);
    if (st != SVP_OK) st = svp_yaml_fail(coefs, st, "%s", svp_last_error());
cleanup:
    free(values);
    return st;
}

/* The `regions` list of a regions map: one PSF per label 0 .. nl − 1, each label once. */
static svp_status read_map_region_psfs(const map_head *m, const svp_yaml_node *list, size_t nl,
                                       svp_psf *psfs)
{
    const svp_yaml_node *v = NULL;
    svp_status st = SVP_OK;
    int *seen = calloc(nl, sizeof(int));
    if (!seen) return svp_fail(SVP_ERR_NOMEM, "%s: out of memory", m->path);
    static const char *const region_extra[] = {"label", "name", NULL};
    for (size_t k = 0; k < nl && st == SVP_OK; k++) {
        const svp_yaml_node *item = svp_yaml_item(list, k);
        char what[48];
        long long label = 0;
        snprintf(what, sizeof what, "regions[%zu]", k);
        svp_psf psf;
        if ((st = read_psf_entry(item, what, &m->base, m->pixel_um, region_extra, &psf))) break;
        if ((st = svp_yaml_require(item, "label", what, &v))) break;
        if ((st = svp_yaml_int(v, "label", 0, (long long)nl - 1, &label))) break;
        if (seen[label]) {
            st = svp_yaml_fail(v, SVP_ERR_FORMAT, "label %lld is given twice in regions", label);
            break;
        }
        const char *name = NULL;
        if ((st = svp_yaml_get_string(item, "name", &name, NULL))) break;
        seen[label] = 1;
        psfs[label] = psf;
    }
    free(seen);
    return st;
}

/* The label image beside the file: the image's size, integer labels 0 .. nl − 1. */
static svp_status read_map_labels(const map_head *m, const svp_yaml_node *labels_node,
                                  const char *labels_file, size_t nl, int **labels_out)
{
    svp_status st = SVP_OK;
    svp_image *label_image = NULL;
    int *labels = NULL;
    char *labels_path = sibling_path(m->path, labels_file);
    if (!labels_path) return svp_fail(SVP_ERR_NOMEM, "%s: out of memory", m->path);
    const long long width = m->width, height = m->height;
    if ((st = svp_image_read(labels_path, &label_image)) != SVP_OK) {
        st = svp_yaml_fail(labels_node, st, "labels_file: %s", svp_last_error());
        goto cleanup;
    }
    if (label_image->width != width || label_image->height != height) {
        st = svp_yaml_fail(labels_node, SVP_ERR_SIZE,
                           "labels_file %s is %d x %d but the image is %lld x %lld",
                           labels_path, label_image->width, label_image->height, width, height);
        goto cleanup;
    }
    const size_t n = (size_t)width * height;
    labels = malloc(n * sizeof(int));
    if (!labels) {
        st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory", m->path);
        goto cleanup;
    }
    for (size_t i = 0; i < n; i++) {
        double l = label_image->data[i];
        if (!(l >= 0 && l < (double)nl && l == floor(l))) {
            st = svp_yaml_fail(labels_node, SVP_ERR_FORMAT,
                               "%s: pixel (%zu, %zu) has label %g; labels must be integers "
                               "0..%zu (one per entry of regions)",
                               labels_path, i % (size_t)width, i / (size_t)width, l, nl - 1);
            goto cleanup;
        }
        labels[i] = (int)l;
    }
    *labels_out = labels;
    labels = NULL;
cleanup:
    free(labels);
    free(labels_path);
    svp_image_free(label_image);
    return st;
}

/* kind: regions — `labels_file`, `transition_um` and one PSF per label (`regions`). */
static svp_status read_map_regions(const map_head *m, const svp_yaml_node *root,
                                   svp_psf_field **out)
{
    const svp_yaml_node *v = NULL, *list = NULL;
    const char *labels_file = NULL;
    double transition_um = 0;
    SVP_CHECK(svp_yaml_require(root, "labels_file", NULL, &v));
    SVP_CHECK(svp_yaml_string(v, "labels_file", &labels_file));
    const svp_yaml_node *labels_node = v;
    SVP_CHECK(svp_yaml_get_number(root, "transition_um", 0, INFINITY, 0, &transition_um, NULL));
    SVP_CHECK(svp_yaml_require(root, "regions", NULL, &list));
    if (svp_yaml_type_of(list) != SVP_YAML_SEQUENCE || svp_yaml_size(list) == 0)
        return svp_yaml_fail(list, SVP_ERR_FORMAT, "regions must be a non-empty list");
    const size_t nl = svp_yaml_size(list);
    int *labels = NULL;
    svp_psf *psfs = calloc(nl, sizeof(svp_psf));
    if (!psfs) return svp_fail(SVP_ERR_NOMEM, "%s: out of memory", m->path);
    svp_status st = read_map_region_psfs(m, list, nl, psfs);
    if (st == SVP_OK) st = read_map_labels(m, labels_node, labels_file, nl, &labels);
    if (st == SVP_OK)
        st = svp_psf_field_new_regions((int)m->width, (int)m->height, labels, (int)nl, psfs,
                                       transition_um / m->pixel_um, out);
    free(labels);
    free(psfs);
    return st;
}

/* A PSF-map document: the common keys, then the kind's own. */
static svp_status read_map(const char *path, const svp_yaml_node *root, svp_psf_field **out,
                           double *pixel_um_out)
{
    map_head m;
    SVP_CHECK(read_map_head(path, root, &m));
    svp_status st = SVP_OK;
    switch (m.kind) {
    case SVP_FIELD_UNIFORM: st = read_map_uniform(&m, root, out); break;
    case SVP_FIELD_GRID: st = read_map_grid(&m, root, out); break;
    case SVP_FIELD_POLY: st = read_map_poly(&m, root, out); break;
    case SVP_FIELD_REGIONS: st = read_map_regions(&m, root, out); break;
    }
    if (st == SVP_OK && pixel_um_out) *pixel_um_out = m.pixel_um;
    return st;
}

svp_status svp_psf_field_read(const char *path, svp_psf_field **out, double *pixel_um)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_psf_field_read: out is NULL");
    *out = NULL;
    if (!path) return svp_fail(SVP_ERR_INVALID, "svp_psf_field_read: path is NULL");
    svp_yaml_doc *doc = NULL;
    SVP_CHECK(svp_yaml_load_file(path, &doc));
    const svp_yaml_node *root = svp_yaml_root(doc);
    svp_status st = svp_yaml_expect_mapping(root, NULL);
    if (st == SVP_OK && !svp_yaml_get(root, "kind")) {
        /* no `kind`: the plain PSF file of the foundation issue, a uniform field for any size */
        svp_yaml_free(doc);
        doc = NULL;
        svp_psf psf;
        double px = 0;
        st = svp_psf_file_read(path, &psf, &px, NULL);
        if (st == SVP_OK) st = svp_psf_field_new_uniform(&psf, 0, 0, out);
        if (st == SVP_OK && pixel_um) *pixel_um = px;
    } else if (st == SVP_OK) {
        st = read_map(path, root, out, pixel_um);
    }
    svp_yaml_free(doc);
    return st;
}

static svp_status write_map(svp_yaml_writer *w, const svp_psf_field *f, double pixel_um,
                            const char *provenance, const char *labels_name)
{
    char comment[128];
    snprintf(comment, sizeof comment, "PSF map written by svpsf %s (lengths in micrometres)",
             svp_version());
    SVP_CHECK(svp_yaml_write_comment(w, comment));
    SVP_CHECK(svp_yaml_begin_mapping(w));
    SVP_CHECK(svp_yaml_write_key_int(w, "version", 1));
    SVP_CHECK(svp_yaml_write_key_number(w, "pixel_um", pixel_um));
    if (f->width > 0) {
        SVP_CHECK(svp_yaml_write_key(w, "image"));
        SVP_CHECK(svp_yaml_begin_mapping(w));
        SVP_CHECK(svp_yaml_write_key_int(w, "width", f->width));
        SVP_CHECK(svp_yaml_write_key_int(w, "height", f->height));
        SVP_CHECK(svp_yaml_end_mapping(w));
    }
    SVP_CHECK(svp_yaml_write_key_string(w, "model", model_names[f->base.model]));
    SVP_CHECK(svp_yaml_write_key_number(w, "support_um", f->base.support * pixel_um));
    SVP_CHECK(svp_yaml_write_key_int(w, "subsample", f->base.subsample));
    SVP_CHECK(svp_yaml_write_key_string(w, "kind", kind_names[f->kind]));
    switch (f->kind) {
    case SVP_FIELD_UNIFORM:
        SVP_CHECK(svp_yaml_write_key(w, "psf"));
        SVP_CHECK(write_psf_entry(w, &f->uniform, pixel_um));
        break;
    case SVP_FIELD_GRID:
        SVP_CHECK(svp_yaml_write_key(w, "nodes"));
        SVP_CHECK(svp_yaml_begin_mapping(w));
        if (f->grid_default_nodes) {
            SVP_CHECK(svp_yaml_write_key_int(w, "nx", f->nx));
            SVP_CHECK(svp_yaml_write_key_int(w, "ny", f->ny));
        } else {
            SVP_CHECK(svp_yaml_write_key_number_list(w, "x_px", f->node_x, (size_t)f->nx));
            SVP_CHECK(svp_yaml_write_key_number_list(w, "y_px", f->node_y, (size_t)f->ny));
        }
        SVP_CHECK(svp_yaml_end_mapping(w));
        SVP_CHECK(svp_yaml_write_comment(w, "one entry per node, x fastest"));
        SVP_CHECK(svp_yaml_write_key(w, "node_psfs"));
        SVP_CHECK(svp_yaml_begin_sequence(w));
        for (size_t k = 0; k < (size_t)f->nx * f->ny; k++) {
            svp_psf psf;
            svp_psf_from_params(&f->base, f->node_p + k * SVP_FIELD_NPARAM, &psf);
            SVP_CHECK(write_psf_entry(w, &psf, pixel_um));
        }
        SVP_CHECK(svp_yaml_end_sequence(w));
        break;
    case SVP_FIELD_POLY: {
        const int nt = svp_psf_field_poly_terms(f->degree);
        double scaled[(SVP_FIELD_POLY_MAX_DEGREE + 1) * (SVP_FIELD_POLY_MAX_DEGREE + 2) / 2];
        SVP_CHECK(svp_yaml_write_key_int(w, "degree", f->degree));
        SVP_CHECK(svp_yaml_write_comment(w, "terms 1, u, v, u^2, u v, v^2, ...; u, v in [-1, 1] "
                                            "across the image"));
        SVP_CHECK(svp_yaml_write_key(w, "coefficients"));
        SVP_CHECK(svp_yaml_begin_mapping(w));
        for (int q = 0; q < SVP_FIELD_NPARAM; q++) {
            for (int t = 0; t < nt; t++)
                scaled[t] = f->coeffs[q * nt + t] * (q == SVP_FIELD_FWHM ? pixel_um : 1.0);
            SVP_CHECK(svp_yaml_write_key_number_list(w, coef_names[q], scaled, (size_t)nt));
        }
        SVP_CHECK(svp_yaml_end_mapping(w));
        break;
    }
    case SVP_FIELD_REGIONS:
        SVP_CHECK(svp_yaml_write_key_string(w, "labels_file", labels_name));
        SVP_CHECK(svp_yaml_write_key_number(w, "transition_um", f->transition * pixel_um));
        SVP_CHECK(svp_yaml_write_key(w, "regions"));
        SVP_CHECK(svp_yaml_begin_sequence(w));
        for (int l = 0; l < f->n_labels; l++) {
            /* write_psf_entry's mapping, with the label first */
            const svp_psf *psf = &f->region_psfs[l];
            SVP_CHECK(svp_yaml_begin_mapping(w));
            SVP_CHECK(svp_yaml_write_key_int(w, "label", l));
            SVP_CHECK(svp_yaml_write_key_number(w, "fwhm_um", psf->fwhm * pixel_um));
            if (psf->fwhm_minor > 0) {
                SVP_CHECK(
                    svp_yaml_write_key_number(w, "fwhm_minor_um", psf->fwhm_minor * pixel_um));
                SVP_CHECK(svp_yaml_write_key_number(w, "angle_deg", psf->angle / RAD_PER_DEG));
            }
            if (psf->model == SVP_PSF_MOFFAT)
                SVP_CHECK(svp_yaml_write_key_number(w, "beta", psf->beta));
            SVP_CHECK(svp_yaml_write_key_number(w, "halo", psf->halo));
            SVP_CHECK(svp_yaml_end_mapping(w));
        }
        SVP_CHECK(svp_yaml_end_sequence(w));
        break;
    }
    if (provenance) SVP_CHECK(svp_yaml_write_key_string(w, "provenance", provenance));
    return svp_yaml_end_mapping(w);
}

svp_status svp_psf_field_write(const char *path, const svp_psf_field *field, double pixel_um,
                               const char *provenance, int overwrite)
{
    if (!path || !field) return svp_fail(SVP_ERR_INVALID, "svp_psf_field_write: NULL argument");
    if (!(pixel_um > 0) || !isfinite(pixel_um))
        return svp_fail(SVP_ERR_INVALID, "%s: pixel size must be > 0 micrometres, got %g", path,
                        pixel_um);
    if (field->margin > 0)
        return svp_fail(SVP_ERR_UNSUPPORTED,
                        "%s: a PSF map padded for an operator's margin (svp_psf_field_pad) is not "
                        "written: write the map it was padded from",
                        path);
    svp_status st = SVP_OK;
    svp_yaml_writer *w = NULL;
    char *labels_path = NULL;
    svp_image *label_image = NULL;
    const char *labels_name = NULL;
    if (field->kind == SVP_FIELD_REGIONS) {
        labels_path = labels_path_for(path);
        if (!labels_path) return svp_fail(SVP_ERR_NOMEM, "out of memory");
        const char *slash = strrchr(labels_path, '/');
        labels_name = slash ? slash + 1 : labels_path;
        const size_t n = (size_t)field->width * field->height;
        if ((st = svp_image_new(field->width, field->height, &label_image)) != SVP_OK) goto cleanup;
        for (size_t i = 0; i < n; i++) label_image->data[i] = field->labels[i];
    }
    if ((st = svp_yaml_writer_new(&w)) != SVP_OK) goto cleanup;
    if ((st = write_map(w, field, pixel_um, provenance, labels_name)) != SVP_OK) goto cleanup;
    const char *text = NULL;
    if ((st = svp_yaml_writer_finish(w, &text)) != SVP_OK) goto cleanup;
    /* labels first: a map never names a labels file that was not written */
    if (label_image &&
        (st = svp_image_write(labels_path, label_image, SVP_FORMAT_NPY, overwrite)) != SVP_OK)
        goto cleanup;
    st = svp_yaml_writer_write_file(w, path, overwrite);
cleanup:
    svp_yaml_writer_free(w);
    svp_image_free(label_image);
    free(labels_path);
    return st;
}
