/* svpsf map-psf: fit many spots (a list of cut-outs, or one image with many spots to detect)
 * and map the PSF parameters over the field (polynomial surfaces) or per region (label image);
 * writes the PSF-map YAML that forward/correct read (svp_psf_field_write). */
#include "cli.h"

#include "core/internal.h"
#include "io/yaml.h"

#include <math.h>
#include <omp.h>
#include <stdlib.h>
#include <string.h>

enum {
    OPT_LABELS = CLI_OPTION_FIRST,
    OPT_DEGREE,
    OPT_MAX_DEGREE,
    OPT_HALO,
    OPT_TRANSITION,
    OPT_ALPHA,
    OPT_CLIP,
    OPT_WINDOW,
    OPT_THRESHOLD
};

static void print_help(const cli_run *run, FILE *out)
{
    fputs("usage: svpsf map-psf SPOTS.yaml -o MAP.yaml [--labels L.tif] [--degree d|auto]\n"
          "                     [options]\n"
          "\n"
          "Fits a PSF (svpsf fit-psf's spot fit) to every spot of SPOTS.yaml, rejects bad fits\n"
          "with a stated reason, and maps the PSF parameters (FWHM, ellipticity e1 e2, beta)\n"
          "over the field: polynomial surfaces in the position (weighted least squares, the\n"
          "degree given or chosen per parameter by 5-fold cross-validation), or with --labels\n"
          "per-region means, regions that do not differ significantly (Welch test, Bonferroni)\n"
          "being merged. Writes the PSF-map file that --psf of forward and correct reads.\n"
          "\n"
          "SPOTS.yaml (paths relative to its folder), either a list of spot images:\n"
          "    pixel_um: 0.05\n"
          "    field: {width: 400, height: 400}     # the field size (or from --labels)\n"
          "    spots:\n"
          "      - {file: s00.tif, origin: [28, 27]}  # field pixel of the cut-out's (0, 0):\n"
          "                                           #   the spot is at origin + fitted centre\n"
          "      - {file: s01.tif, x: 120.5, y: 40.2} # or the spot's centre in the field, px\n"
          "or one image with many spots, detected as local maxima of the 3 x 3 mean that stand\n"
          "`threshold` sigma (robust, from the median absolute deviation) above the median:\n"
          "    pixel_um: 0.05\n"
          "    image: spots.tif\n"
          "    window: 31        # odd cut-out side around each maximum, px (default 31)\n"
          "    threshold: 10     # default 10\n"
          "\n"
          "  -o, --output MAP.yaml the PSF map to write (required)\n"
          "  --labels L.tif        region labels (integers 0..L-1, the field's size): per-region\n"
          "                        map instead of polynomial surfaces\n"
          "  --degree d|auto       polynomial degree 0..8, or auto (default: cross-validation)\n"
          "  --max-degree N        largest degree auto tries (default 3)\n",
          out);
    cli_print_spot_help(out);
    fputs("  --circular            round spot fits (no ellipticity)\n"
          "  --gain G              photons per data unit (default 1)\n"
          "  --halo A              background-halo fraction alpha_b in [0, 0.999] written\n"
          "                        into the map\n"
          "                        (spots do not measure it; default 0)\n"
          "  --transition-um T     regions: blend width across region boundaries (default 0)\n"
          "  --alpha A             regions: significance level for keeping regions apart\n"
          "                        (default 0.01)\n"
          "  --clip-kappa K        reject spots whose parameter lies > K robust sigma from the\n"
          "                        surface or region mean (default 4; 0 = off)\n"
          "  --window N, --threshold K  override the detection settings of SPOTS.yaml\n",
          out);
    cli_print_common_help(run, out);
    fputs("\n"
          "outputs: MAP.yaml (and MAP.labels.npy for a region map), MAP.spots.csv (every spot:\n"
          "position, fitted values, flags and whether it was kept or why it was rejected),\n"
          "MAP.summary.json. Spots near the border, saturated, not converged or with a\n"
          "parameter at its bound are rejected; so are outliers of the surface fit.\n",
          out);
}

/* `name` relative to the folder of `yaml_path` (absolute names unchanged). */
static void relative_to(const char *yaml_path, const char *name, char *buf, size_t size)
{
    const char *slash = strrchr(yaml_path, '/');
    if (name[0] == '/' || !slash)
        snprintf(buf, size, "%s", name);
    else
        snprintf(buf, size, "%.*s/%s", (int)(slash - yaml_path), yaml_path, name);
}

typedef struct spot_entry {
    char path[4096]; /* the image it was fitted in */
    svp_image *image;
    double ox, oy; /* origin of the cut-out in the field */
    double x, y;   /* given centre (NaN: origin + fitted) */
    svp_status status;
    char error[512];
    svp_spot_result fit;
} spot_entry;

static int cmp_peak(const void *a, const void *b)
{
    const double *pa = a, *pb = b;
    if (pa[0] != pb[0]) return pa[0] < pb[0] ? 1 : -1;
    return pa[1] < pb[1] ? -1 : pa[1] > pb[1];
}

/* 1 when no pixel of the (2 r + 1)² window beats sm[y, x] (ties: the first in raster order
 * wins); the 3 x 3 neighbours first, which rejects most pixels at once. */
static int is_local_max(const double *sm, int w, int h, int x, int y, int r)
{
    const double v = sm[(size_t)y * w + x];
    for (int pass = 0; pass < 2; pass++) {
        const int rr = pass == 0 ? 1 : r;
        for (int j = y - rr; j <= y + rr; j++)
            for (int i = x - rr; i <= x + rr; i++) {
                if (i < 0 || j < 0 || i >= w || j >= h || (i == x && j == y)) continue;
                double u = sm[(size_t)j * w + i];
                if (u > v || (u == v && (j < y || (j == y && i < x)))) return 0;
            }
    }
    return 1;
}

/* Local maxima of the 3 x 3 mean above median + threshold sigma / 3, separated by more than
 * window / 2; cut-outs of window x window (clipped to the image). */
static int detect(cli_run *run, const svp_image *img, const char *path, int window,
                  double threshold, spot_entry **out, int *n_out)
{
    const int w = img->width, h = img->height, r = window / 2;
    const size_t N = (size_t)w * h;
    double *tmp = malloc(N * sizeof *tmp), *sm = malloc(N * sizeof *sm);
    double *cand = NULL;
    int code = 0, nc = 0;
    if (!tmp || !sm) goto nomem;
    size_t nf = 0;
    for (size_t i = 0; i < N; i++)
        if (isfinite(img->data[i])) tmp[nf++] = img->data[i];
    if (nf < 9) {
        code = cli_error(run, "%s: fewer than 9 finite pixels: no spots to detect", path);
        goto done;
    }
    const double med = svp_select_kth(tmp, nf, nf / 2);
    for (size_t i = 0; i < nf; i++) tmp[i] = fabs(tmp[i] - med);
    double sigma = 1.4826 * svp_select_kth(tmp, nf, nf / 2);
    if (!(sigma > 0)) sigma = sqrt(fmax(med, 1.0)); /* flat background: shot noise */
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double acc = 0;
            int n = 0;
            for (int j = y - 1; j <= y + 1; j++)
                for (int i = x - 1; i <= x + 1; i++)
                    if (i >= 0 && j >= 0 && i < w && j < h && isfinite(img->data[j * w + i]))
                        acc += img->data[j * w + i], n++;
            sm[(size_t)y * w + x] = n ? acc / n : -INFINITY;
        }
    const double level = med + threshold * sigma / 3;
    cand = malloc(3 * sizeof(double) * 1024);
    int cap = 1024;
    if (!cand) goto nomem;
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double v = sm[(size_t)y * w + x];
            if (!(v > level) || !is_local_max(sm, w, h, x, y, r)) continue;
            if (nc == cap) {
                double *c2 = realloc(cand, 3 * sizeof(double) * (size_t)cap * 2);
                if (!c2) goto nomem;
                cand = c2;
                cap *= 2;
            }
            cand[3 * nc] = v;
            cand[3 * nc + 1] = (double)y * w + x;
            cand[3 * nc + 2] = 0;
            nc++;
        }
    qsort(cand, (size_t)nc, 3 * sizeof(double), cmp_peak);
    spot_entry *e = calloc(nc > 0 ? (size_t)nc : 1, sizeof *e);
    if (!e) goto nomem;
    for (int k = 0; k < nc; k++) {
        size_t idx = (size_t)cand[3 * k + 1];
        int cx = (int)(idx % (size_t)w), cy = (int)(idx / (size_t)w);
        int x0 = cx - r < 0 ? 0 : cx - r, y0 = cy - r < 0 ? 0 : cy - r;
        int x1 = cx + r >= w ? w - 1 : cx + r, y1 = cy + r >= h ? h - 1 : cy + r;
        snprintf(e[k].path, sizeof e[k].path, "%s", path);
        e[k].ox = x0;
        e[k].oy = y0;
        e[k].x = e[k].y = NAN;
        if (svp_image_new(x1 - x0 + 1, y1 - y0 + 1, &e[k].image) != SVP_OK) {
            for (int i = 0; i < k; i++) svp_image_free(e[i].image);
            free(e);
            goto nomem;
        }
        for (int y = y0; y <= y1; y++)
            memcpy(e[k].image->data + (size_t)(y - y0) * (x1 - x0 + 1),
                   img->data + (size_t)y * w + x0, sizeof(double) * (size_t)(x1 - x0 + 1));
    }
    *out = e;
    *n_out = nc;
    cli_note(run, "%s: %d spots detected above %.4g (median %.4g + %g robust sigma / 3)", path, nc,
             level, med, threshold);
    goto done;
nomem:
    cli_error(run, "out of memory");
    code = CLI_EXIT_RUNTIME;
done:
    free(tmp);
    free(sm);
    free(cand);
    return code;
}

struct map_psf_args {
    const char *spots_path;  /* SPOTS.yaml */
    const char *labels_path; /* --labels */
    cli_spot_args spot;      /* --model, --circular, --gain */
    svp_spot_options so;     /* the spot fit (the group applied) */
    svp_map_options mo;      /* --degree, --max-degree, --halo, --alpha, --clip-kappa */
    int window, window_given, threshold_given;
    double threshold, transition_um;
};

/* map-psf warns when a surface's standard error somewhere in the field exceeds this many
 * times the median error of a spot's own fit (svp_map_report.surface_se_max) */
#define MAP_SURFACE_SE_RATIO 5.0

/* What a run holds (released by map_psf_release). */
struct map_psf_job {
    svp_yaml_doc *doc;
    double pixel_um;
    int width, height; /* the field */
    int window;        /* detection settings: SPOTS.yaml's unless overridden */
    double threshold;
    svp_image *labels_img, *field_img;
    int *labels, n_labels;
    spot_entry *spots;
    int n_spots;
    svp_psf_sample *samples;
    int *sample_of, n_samples, n_failed;
    svp_psf_field *field;
    svp_map_report *rep;
    int spots_box[4]; /* x0, y0, x1, y1 of the spots' centres (polynomial maps) */
    char *csv;
    char csv_path[4096], summary_path[4096], labels_out[4096];
};

static int map_psf_option(cli_run *run, struct map_psf_args *a, int c)
{
    svp_map_options *mo = &a->mo;
    switch (c) {
    case OPT_LABELS: a->labels_path = optarg; return 0;
    case OPT_DEGREE:
        if (strcmp(optarg, "auto") == 0) {
            mo->degree = -1;
            return 0;
        }
        return cli_parse_int(run, "--degree", optarg, 0, 8, &mo->degree);
    case OPT_MAX_DEGREE: return cli_parse_int(run, "--max-degree", optarg, 0, 8, &mo->max_degree);
    /* a PSF map holds halos up to 0.999 (svp_psf_field clamps beyond): refused, not clamped */
    case OPT_HALO: return cli_parse_double_in(run, "--halo", optarg, 0, 1, 0.999, 1, &mo->halo);
    case OPT_TRANSITION:
        return cli_parse_double_in(run, "--transition-um", optarg, 0, 1, INFINITY, 0,
                                   &a->transition_um);
    case OPT_ALPHA: return cli_parse_double_in(run, "--alpha", optarg, 0, 0, 1, 0, &mo->alpha);
    case OPT_CLIP:
        return cli_parse_double_in(run, "--clip-kappa", optarg, 0, 1, INFINITY, 0, &mo->clip_kappa);
    case OPT_WINDOW:
        if (cli_parse_int(run, "--window", optarg, 7, 1001, &a->window)) return CLI_EXIT_USAGE;
        if (a->window % 2 == 0) return cli_error(run, "--window %d: must be odd", a->window);
        a->window_given = 1;
        return 0;
    case OPT_THRESHOLD:
        a->threshold_given = 1;
        return cli_parse_double_in(run, "--threshold", optarg, 0, 0, INFINITY, 0, &a->threshold);
    default: {
        int bad = cli_spot_option(run, &a->spot, c, optarg);
        return bad < 0 ? cli_error(run, "internal: option %d", c) : bad;
    }
    }
}

static int parse_map_psf_args(cli_run *run, struct map_psf_args *a)
{
    static const struct option own[] = {
        {"labels", required_argument, NULL, OPT_LABELS},
        {"degree", required_argument, NULL, OPT_DEGREE},
        {"max-degree", required_argument, NULL, OPT_MAX_DEGREE},
        CLI_SPOT_LONGOPTS,
        {"halo", required_argument, NULL, OPT_HALO},
        {"transition-um", required_argument, NULL, OPT_TRANSITION},
        {"alpha", required_argument, NULL, OPT_ALPHA},
        {"clip-kappa", required_argument, NULL, OPT_CLIP},
        {"window", required_argument, NULL, OPT_WINDOW},
        {"threshold", required_argument, NULL, OPT_THRESHOLD},
        {NULL, 0, NULL, 0},
    };
    memset(a, 0, sizeof *a);
    svp_spot_defaults(&a->so);
    svp_map_defaults(&a->mo);
    cli_spot_init(&a->spot, &a->so);
    a->threshold = 10;
    int c;
    while ((c = cli_next_option(run, own)) != CLI_OPTIONS_DONE) {
        if (c == CLI_OPTION_HELP) {
            print_help(run, stdout);
            return CLI_OPTION_HELP;
        }
        if (c == CLI_OPTION_ERROR || map_psf_option(run, a, c)) return CLI_EXIT_USAGE;
    }
    a->spots_path = cli_one_argument(run, "SPOTS.yaml is required (see --help)", "");
    if (!a->spots_path) return CLI_EXIT_USAGE;
    if (!run->output) return cli_error(run, "-o MAP.yaml is required");
    if (!cli_yaml_extension(run->output))
        return cli_error(run, "-o %s: the PSF map must end in .yaml or .yml", run->output);
    cli_spot_apply(&a->spot, &a->so);
    return 0;
}

static int yaml_fail(cli_run *run, const struct map_psf_args *a, svp_status st)
{
    return cli_fail(run, st, a->spots_path);
}

/* SPOTS.yaml with `image`: detect the spots in it (window and threshold from the file unless
 * given as options). */
static int read_spot_image(cli_run *run, const struct map_psf_args *a, struct map_psf_job *job,
                           const svp_yaml_node *root, const svp_yaml_node *image)
{
    const char *name;
    long long wv = 31;
    svp_status st;
    int code;
    if ((st = svp_yaml_string(image, "image", &name)) != SVP_OK) return yaml_fail(run, a, st);
    if ((st = svp_yaml_get_int(root, "window", 7, 1001, &wv, NULL)) != SVP_OK)
        return yaml_fail(run, a, st);
    if (wv % 2 == 0)
        return yaml_fail(run, a,
                         svp_yaml_fail(svp_yaml_get(root, "window"), SVP_ERR_FORMAT,
                                       "window: %lld must be odd", wv));
    double th = 10;
    if ((st = svp_yaml_get_number(root, "threshold", 0, INFINITY, SVP_YAML_OPEN_LO, &th, NULL)) !=
        SVP_OK)
        return yaml_fail(run, a, st);
    job->window = a->window_given ? a->window : (int)wv;
    job->threshold = a->threshold_given ? a->threshold : th;
    if (svp_yaml_get(root, "field"))
        return yaml_fail(run, a,
                         svp_yaml_fail(svp_yaml_get(root, "field"), SVP_ERR_FORMAT,
                                       "field: not with 'image' (the field is the image)"));
    char path[4096];
    relative_to(a->spots_path, name, path, sizeof path);
    if ((code = cli_read_image(run, "image", path, &job->field_img))) return code;
    job->width = job->field_img->width;
    job->height = job->field_img->height;
    cli_stage_begin(run, "detect");
    if ((code = detect(run, job->field_img, path, job->window, job->threshold, &job->spots,
                       &job->n_spots)))
        return code;
    cli_stage_begin(run, "read");
    cli_setting_int(run, "window", job->window);
    cli_setting_num(run, "threshold", job->threshold);
    return 0;
}

/* One entry of SPOTS.yaml's `spots` list: its file, and its origin or centre. */
static int read_spot_entry(cli_run *run, const struct map_psf_args *a, const svp_yaml_node *it,
                           spot_entry *e)
{
    const svp_yaml_node *fn;
    static const char *const sk[] = {"file", "origin", "x", "y", NULL};
    const char *name;
    svp_status st;
    if ((st = svp_yaml_expect_mapping(it, "spot")) != SVP_OK ||
        (st = svp_yaml_check_keys(it, "spot", sk)) != SVP_OK ||
        (st = svp_yaml_require(it, "file", "spot", &fn)) != SVP_OK ||
        (st = svp_yaml_string(fn, "file", &name)) != SVP_OK)
        return yaml_fail(run, a, st);
    const svp_yaml_node *org = svp_yaml_get(it, "origin");
    int has_x = svp_yaml_get(it, "x") != NULL, has_y = svp_yaml_get(it, "y") != NULL;
    if (!org == !(has_x && has_y) || has_x != has_y)
        return yaml_fail(run, a,
                         svp_yaml_fail(it, SVP_ERR_FORMAT,
                                       "spot: give either origin: [x, y] (the cut-out's corner "
                                       "in the field) or x and y (the spot's centre)"));
    e->x = e->y = NAN;
    if (org) {
        double v[2];
        size_t cnt;
        if ((st = svp_yaml_number_list(org, "origin", 2, 2, v, &cnt)) != SVP_OK)
            return yaml_fail(run, a, st);
        e->ox = v[0];
        e->oy = v[1];
    } else if ((st = svp_yaml_get_number(it, "x", -INFINITY, INFINITY, 0, &e->x, NULL)) != SVP_OK ||
               (st = svp_yaml_get_number(it, "y", -INFINITY, INFINITY, 0, &e->y, NULL)) != SVP_OK)
        return yaml_fail(run, a, st);
    relative_to(a->spots_path, name, e->path, sizeof e->path);
    return cli_read_image(run, "spot", e->path, &e->image);
}

/* SPOTS.yaml with `spots`: the optional field size, then each spot image. */
static int read_spot_list(cli_run *run, const struct map_psf_args *a, struct map_psf_job *job,
                          const svp_yaml_node *root, const svp_yaml_node *list)
{
    svp_status st;
    int code;
    const svp_yaml_node *f = svp_yaml_get(root, "field");
    if (f) {
        static const char *const fk[] = {"width", "height", NULL};
        long long wv, hv;
        const svp_yaml_node *x, *y;
        if ((st = svp_yaml_expect_mapping(f, "field")) != SVP_OK ||
            (st = svp_yaml_check_keys(f, "field", fk)) != SVP_OK ||
            (st = svp_yaml_require(f, "width", "field", &x)) != SVP_OK ||
            (st = svp_yaml_int(x, "width", 1, 1 << 20, &wv)) != SVP_OK ||
            (st = svp_yaml_require(f, "height", "field", &y)) != SVP_OK ||
            (st = svp_yaml_int(y, "height", 1, 1 << 20, &hv)) != SVP_OK)
            return yaml_fail(run, a, st);
        job->width = (int)wv;
        job->height = (int)hv;
    }
    if (svp_yaml_type_of(list) != SVP_YAML_SEQUENCE || svp_yaml_size(list) == 0)
        return yaml_fail(run, a,
                         svp_yaml_fail(list, SVP_ERR_FORMAT, "spots: expected a non-empty list"));
    job->n_spots = (int)svp_yaml_size(list);
    job->spots = calloc((size_t)job->n_spots, sizeof *job->spots);
    if (!job->spots) {
        cli_error(run, "out of memory");
        return CLI_EXIT_RUNTIME;
    }
    for (int k = 0; k < job->n_spots; k++)
        if ((code = read_spot_entry(run, a, svp_yaml_item(list, (size_t)k), &job->spots[k])))
            return code;
    return 0;
}

/* SPOTS.yaml: the pixel size and either the spot list or the image to detect spots in. */
static int map_psf_read_spots(cli_run *run, const struct map_psf_args *a, struct map_psf_job *job)
{
    svp_status st;
    cli_stage_begin(run, "read");
    if ((st = svp_yaml_load_file(a->spots_path, &job->doc)) != SVP_OK)
        return cli_fail(run, st, a->spots_path);
    cli_record_input(run, "spots", a->spots_path, 0, 0);
    const svp_yaml_node *root = svp_yaml_root(job->doc), *node;
    static const char *const keys[] = {"pixel_um", "field",     "spots",   "image",
                                       "window",   "threshold", "comment", NULL};
    if ((st = svp_yaml_expect_mapping(root, NULL)) != SVP_OK ||
        (st = svp_yaml_check_keys(root, NULL, keys)) != SVP_OK ||
        (st = svp_yaml_require(root, "pixel_um", NULL, &node)) != SVP_OK ||
        (st = svp_yaml_number_in(node, "pixel_um", SVP_PIXEL_UM_MIN, INFINITY, 0,
                                 &job->pixel_um)) != SVP_OK)
        return yaml_fail(run, a, st);
    const svp_yaml_node *list = svp_yaml_get(root, "spots"), *image = svp_yaml_get(root, "image");
    if (!list == !image)
        return yaml_fail(run, a,
                         svp_yaml_fail(root, SVP_ERR_FORMAT,
                                       "give either 'spots' (a list of spot images) "
                                       "or 'image' (one image with many spots)"));
    return image ? read_spot_image(run, a, job, root, image)
                 : read_spot_list(run, a, job, root, list);
}

/* --labels: the field's size (or checked against it), integers 0..L-1, at most 4096. */
static int map_psf_read_labels(cli_run *run, const struct map_psf_args *a, struct map_psf_job *job)
{
    const char *labels_path = a->labels_path;
    int code;
    if ((code = cli_read_image(run, "labels", labels_path, &job->labels_img))) return code;
    const svp_image *img = job->labels_img;
    if (job->width == 0) {
        job->width = img->width;
        job->height = img->height;
    } else if (img->width != job->width || img->height != job->height) {
        return cli_error(run,
                         "size mismatch: --labels %s is %d x %d but the field of %s is "
                         "%d x %d",
                         labels_path, img->width, img->height, a->spots_path, job->width,
                         job->height);
    }
    const size_t N = (size_t)job->width * job->height;
    job->labels = malloc(N * sizeof *job->labels);
    if (!job->labels) {
        cli_error(run, "out of memory");
        return CLI_EXIT_RUNTIME;
    }
    for (size_t i = 0; i < N; i++) {
        double v = img->data[i];
        if (!(v >= 0 && v <= 1000000 && v == floor(v)))
            return cli_error(run,
                             "%s: pixel (%zu, %zu) is %g: labels must be integers "
                             "0..L-1",
                             labels_path, i % (size_t)job->width, i / (size_t)job->width, v);
        job->labels[i] = (int)v;
        if (job->labels[i] + 1 > job->n_labels) job->n_labels = job->labels[i] + 1;
    }
    if (job->n_labels > 4096)
        return cli_error(run, "%s: %d labels: at most 4096 regions", labels_path, job->n_labels);
    return 0;
}

/* The inputs, then every output planned and checked, the settings recorded. */
static int map_psf_read(cli_run *run, const struct map_psf_args *a, struct map_psf_job *job)
{
    int code;
    if ((code = map_psf_read_spots(run, a, job))) return code;
    if (a->labels_path && (code = map_psf_read_labels(run, a, job))) return code;
    if (job->width == 0)
        return cli_error(run,
                         "%s: the field size is unknown: add field: {width: W, height: H} "
                         "(or give --labels)",
                         a->spots_path);
    if (job->n_spots == 0) return cli_error(run, "%s: no spots to fit", a->spots_path);

    cli_path_sibling(run->output, ".spots.csv", job->csv_path, sizeof job->csv_path);
    cli_path_sibling(run->output, ".summary.json", job->summary_path, sizeof job->summary_path);
    cli_output_file(run, "map", run->output);
    if (job->labels) {
        cli_path_sibling(run->output, ".labels.npy", job->labels_out, sizeof job->labels_out);
        cli_output_file(run, "labels", job->labels_out);
    }
    cli_output_file(run, "spots", job->csv_path);
    cli_output_file(run, "summary", job->summary_path);
    if ((code = cli_outputs_check(run))) return code;
    cli_setting_num(run, "pixel_um", job->pixel_um);
    cli_setting_str(run, "model", cli_psf_model_names[a->spot.model]);
    cli_setting_str(run, "map", job->labels ? "regions" : "poly");
    if (!job->labels) {
        if (a->mo.degree < 0)
            cli_setting_str(run, "degree", "auto");
        else
            cli_setting_int(run, "degree", a->mo.degree);
    }
    cli_setting_num(run, "halo", a->mo.halo);
    cli_setting_int(run, "n_spots", job->n_spots);
    return 0;
}

/* The fits (independent: in parallel, each result the same at any thread count), and the
 * samples the map is made of. */
static int map_psf_fit(cli_run *run, const struct map_psf_args *a, struct map_psf_job *job)
{
    const int n_spots = job->n_spots;
    spot_entry *spots = job->spots;
    cli_stage_begin(run, "fit");
    cli_progress_start(run, "fitting spots");
    int n_done = 0;
#pragma omp parallel for schedule(dynamic)
    for (int k = 0; k < n_spots; k++) {
        spot_entry *e = &spots[k];
        e->status = svp_spot_fit(e->image, &a->so, &e->fit, NULL, NULL);
        if (e->status != SVP_OK) snprintf(e->error, sizeof e->error, "%s", svp_last_error());
        int done;
#pragma omp atomic capture
        done = ++n_done;
        /* progress is drawn by one thread only (cli_progress is not thread-safe) */
        if (omp_get_thread_num() == 0) cli_progress(run, (double)done / n_spots);
    }
    cli_progress_done(run);
    job->samples = calloc((size_t)n_spots, sizeof *job->samples);
    job->sample_of = malloc((size_t)n_spots * sizeof *job->sample_of);
    if (!job->samples || !job->sample_of) {
        cli_error(run, "out of memory");
        return CLI_EXIT_RUNTIME;
    }
    for (int k = 0; k < n_spots; k++) {
        spot_entry *e = &spots[k];
        job->sample_of[k] = -1;
        /* a fit that did not converge is still a sample (flagged NOT_CONVERGED: the map
         * rejects it with that reason); one that could not be made at all is not */
        if (e->status != SVP_OK &&
            !(e->status == SVP_ERR_NUMERIC && (e->fit.flags & SVP_SPOT_NOT_CONVERGED))) {
            job->n_failed++;
            continue;
        }
        svp_psf_sample *s = &job->samples[job->n_samples];
        s->fit = e->fit;
        s->x = isnan(e->x) ? e->ox + e->fit.x0 : e->x;
        s->y = isnan(e->y) ? e->oy + e->fit.y0 : e->y;
        job->sample_of[k] = job->n_samples++;
    }
    if (job->n_samples > 0) return 0;
    /* every fit failed: say so (with each spot's reason), not "no spots given" */
    for (int k = 0; k < n_spots; k++)
        fprintf(stderr, "svpsf map-psf: spot %d (%s): fit failed: %s\n", k, spots[k].path,
                spots[k].error);
    if (n_spots == 1)
        return cli_error(run, "%s: its only spot failed its fit (%s); no PSF map written",
                         a->spots_path, spots[0].error);
    return cli_error(run,
                     "%s: all %d spots failed their fits (spot 0: %s; each spot's "
                     "reason above); no PSF map written",
                     a->spots_path, n_spots, spots[0].error);
}

/* The map: per-region means with --labels, else polynomial surfaces. */
static int map_psf_map(cli_run *run, const struct map_psf_args *a, struct map_psf_job *job)
{
    svp_map_options mo = a->mo;
    svp_status st;
    cli_stage_begin(run, "map");
    if (job->labels) {
        mo.transition = a->transition_um / job->pixel_um;
        st = svp_psf_map_regions(job->samples, job->n_samples, job->labels, job->width, job->height,
                                 job->n_labels, &mo, &job->field, &job->rep);
    } else {
        st = svp_psf_map_poly(job->samples, job->n_samples, job->width, job->height, &mo,
                              &job->field, &job->rep);
    }
    if (st == SVP_OK && !job->labels) { /* surfaces out of range where the spots are */
        int box[4] = {job->width, job->height, -1, -1};
        for (int i = 0; i < job->n_samples; i++) {
            const svp_psf_sample *sp = &job->samples[i];
            box[0] = (int)fmin(box[0], floor(sp->x));
            box[1] = (int)fmin(box[1], floor(sp->y));
            box[2] = (int)fmax(box[2], ceil(sp->x));
            box[3] = (int)fmax(box[3], ceil(sp->y));
        }
        memcpy(job->spots_box, box, sizeof box);
        svp_psf_field_range r;
        st = svp_psf_field_check_range(job->field, box, &r);
        if (st == SVP_OK && r.clamped) {
            char what[700];
            cli_psf_range_text(&r, job->pixel_um, what, sizeof what);
            cli_error(run,
                      "%s: the fitted surfaces leave their valid range inside the spots' extent "
                      "(x %d..%d, y %d..%d) on %.3g %% of it (%s): the spots cannot determine "
                      "them at this degree; use a lower --degree, or --degree auto "
                      "(cross-validation); nothing written",
                      a->spots_path, box[0], box[2], box[1], box[3],
                      100.0 * (double)r.clamped / (double)r.sampled, what);
            return CLI_EXIT_DOUBTFUL;
        }
    }
    if (st == SVP_OK) { /* the surfaces beyond the spots: in range over the whole image? */
        cli_psf_map_range_warning(run, run->output, job->field, job->pixel_um);
        return 0;
    }
    for (int k = 0; k < job->n_spots; k++)
        if (job->sample_of[k] < 0)
            fprintf(stderr, "svpsf map-psf: spot %d (%s): fit failed: %s\n", k, job->spots[k].path,
                    job->spots[k].error);
    return cli_fail(run, st, a->spots_path);
}

/* Per-spot lines: the CSV, and the rejections on stdout. */
static int map_psf_spot_lines(cli_run *run, struct map_psf_job *job)
{
    const double pixel_um = job->pixel_um;
    size_t cap = 256 + (size_t)job->n_spots * 1400, len = 0;
    char *csv = job->csv = malloc(cap);
    if (!csv) {
        cli_error(run, "out of memory");
        return CLI_EXIT_RUNTIME;
    }
    len += (size_t)snprintf(csv + len, cap - len,
                            "index,file,x_px,y_px,fwhm_um,fwhm_err_um,beta,beta_err,e1,e2,"
                            "chi2_red,flags,status\n");
    int n_kept = 0, n_rejected = 0;
    for (int k = 0; k < job->n_spots; k++) {
        char flags[256], desc[1024];
        spot_entry *e = &job->spots[k];
        int si = job->sample_of[k];
        if (si < 0) {
            snprintf(desc, sizeof desc, "fit failed: %s", e->error);
            for (char *p = desc; *p; p++)
                if (*p == ',' || *p == '"') *p = ';';
            printf("spot %d (%s): rejected: %s\n", k, e->path, desc);
            len += (size_t)snprintf(csv + len, cap - len, "%d,%s,,,,,,,,,,,rejected: %s\n", k,
                                    e->path, desc);
            n_rejected++;
            continue;
        }
        const svp_psf_sample *s = &job->samples[si];
        const svp_spot_result *f = &s->fit;
        svp_spot_flags_describe(f->flags, flags, sizeof flags);
        svp_map_describe_sample(job->rep, job->samples, si, desc, sizeof desc);
        const char *status = strstr(desc, "): ");
        status = status ? status + 3 : desc;
        int kept = strcmp(status, "kept") == 0;
        n_kept += kept;
        n_rejected += !kept;
        if (!kept) printf("spot %d (%s, x %.1f, y %.1f): %s\n", k, e->path, s->x, s->y, status);
        char st_csv[1024];
        snprintf(st_csv, sizeof st_csv, "%s", status);
        for (char *p = st_csv; *p; p++)
            if (*p == ',') *p = ';';
        len += (size_t)snprintf(csv + len, cap - len,
                                "%d,%s,%.6f,%.6f,%.8g,%.8g,%.8g,%.8g,%.8g,%.8g,%.6g,%s,%s\n", k,
                                e->path, s->x, s->y, f->fwhm * pixel_um, f->fwhm_err * pixel_um,
                                f->beta, f->beta_err, f->e1, f->e2, f->chi2_red, flags, st_csv);
    }
    cli_result_int(run, "spots_fitted", job->n_spots - job->n_failed);
    cli_result_int(run, "spots_failed", job->n_failed);
    cli_result_int(run, "spots_kept_all_parameters", n_kept);
    cli_result_int(run, "spots_rejected", n_rejected);
    printf("%d spots: %d kept, %d rejected (%d fits failed)\n", job->n_spots, n_kept, n_rejected,
           job->n_failed);
    return 0;
}

/* The polynomial surfaces: degree, spots used, residual per parameter; a note when a given
 * degree fell (too few spots, or positions that cannot determine its terms). */
static void map_psf_report_poly(cli_run *run, const struct map_psf_args *a,
                                const struct map_psf_job *job)
{
    static const char *const pnames[SVP_FIELD_NPARAM] = {"fwhm", "e1", "e2", "beta", "halo"};
    const svp_map_report *rep = job->rep;
    char key[96];
    for (int q = 0; q < SVP_FIELD_NPARAM; q++) {
        if (!rep->mapped[q]) continue;
        double scale = q == SVP_FIELD_FWHM ? job->pixel_um : 1;
        const double ratio = rep->surface_se_max[q] / rep->spot_se_median[q];
        printf("  %-5s degree %d, %d spots, rms residual %.4g%s, chi2_red %.3f, surface error "
               "at worst %.3g (%.2g x a spot's)\n",
               pnames[q], rep->degree[q], rep->n_used[q], rep->rms[q] * scale,
               q == SVP_FIELD_FWHM ? " um" : "", rep->chi2_red[q],
               rep->surface_se_max[q] * scale, ratio);
        if (a->mo.degree >= 0 && rep->degree[q] < a->mo.degree)
            cli_warn(run,
                     "%s: degree %d asked for, %d fitted: the %d spots' positions determine no "
                     "more terms (degree d needs (d + 1)(d + 2) / 2 spots, at d + 1 distinct "
                     "positions along each axis)",
                     pnames[q], a->mo.degree, rep->degree[q], rep->n_used[q]);
        /* a surface far less certain somewhere in the field than one spot's own fit is an
         * extrapolation the spots do not support (measured: 0.2-1.3 x for spots spread over
         * the field, 2.2e3 - 6e3 x for rows of spots at one y) */
        if (ratio > MAP_SURFACE_SE_RATIO)
            cli_warn(run,
                     "%s: the %s surface (degree %d) is uncertain to +-%.3g%s at pixel (%.0f, "
                     "%.0f), %.2g times a spot's own error: the spots' positions do not "
                     "determine it there (they span x %d..%d, y %d..%d); spread the "
                     "spots over the field, or ask for a lower --degree",
                     run->output, pnames[q], rep->degree[q], rep->surface_se_max[q] * scale,
                     q == SVP_FIELD_FWHM ? " um" : "", rep->surface_se_x[q],
                     rep->surface_se_y[q], ratio, job->spots_box[0], job->spots_box[2],
                     job->spots_box[1], job->spots_box[3]);
        snprintf(key, sizeof key, "%s_surface_error_max", pnames[q]);
        cli_result_num(run, key, rep->surface_se_max[q] * scale);
        snprintf(key, sizeof key, "%s_surface_error_ratio", pnames[q]);
        cli_result_num(run, key, ratio);
        snprintf(key, sizeof key, "%s_degree", pnames[q]);
        cli_result_int(run, key, rep->degree[q]);
        snprintf(key, sizeof key, "%s_rms", pnames[q]);
        cli_result_num(run, key, rep->rms[q] * scale);
        snprintf(key, sizeof key, "%s_chi2_red", pnames[q]);
        cli_result_num(run, key, rep->chi2_red[q]);
        snprintf(key, sizeof key, "%s_n_used", pnames[q]);
        cli_result_int(run, key, rep->n_used[q]);
    }
}

/* The regions: their means, the Welch tests between them and the groups they merged into. */
static void map_psf_report_regions(cli_run *run, const struct map_psf_args *a,
                                   const struct map_psf_job *job)
{
    const svp_map_report *rep = job->rep;
    const double pixel_um = job->pixel_um;
    char key[96], empty[256] = "";
    int n_empty = 0;
    for (int l = 0; l < rep->n_regions; l++) {
        const svp_region_stats *r = &rep->regions[l];
        if (r->count == 0) {
            /* the library gives a label without spots the mean of all spots: say so, and what
             * that is (the map's PSF at one of its pixels), not a mean of 0 +- 0 */
            double p[SVP_FIELD_NPARAM] = {0};
            for (size_t i = 0; i < (size_t)job->width * job->height; i++)
                if (job->labels[i] == l) {
                    if (svp_psf_field_params_at(job->field, (double)(i % (size_t)job->width),
                                                (double)(i / (size_t)job->width),
                                                p) != SVP_OK)
                        memset(p, 0, sizeof p);
                    break;
                }
            printf("  region %d: no spot: given the mean of all spots, FWHM %.4f um, beta %.4f "
                   "(not measured there) -> group %d\n",
                   r->label, p[SVP_FIELD_FWHM] * pixel_um, p[SVP_FIELD_BETA], r->group);
            size_t used = strlen(empty);
            if (used + 16 < sizeof empty)
                snprintf(empty + used, sizeof empty - used, "%s%d", n_empty ? ", " : "", l);
            n_empty++;
            snprintf(key, sizeof key, "region%d_count", l);
            cli_result_int(run, key, 0);
            snprintf(key, sizeof key, "region%d_group", l);
            cli_result_int(run, key, r->group);
            continue;
        }
        printf("  region %d: %d spot%s, FWHM %.4f +- %.4f um, beta %.4f +- %.4f -> group %d\n",
               r->label, r->count, r->count == 1 ? "" : "s", r->mean[SVP_FIELD_FWHM] * pixel_um,
               r->sem[SVP_FIELD_FWHM] * pixel_um, r->mean[SVP_FIELD_BETA], r->sem[SVP_FIELD_BETA],
               r->group);
        snprintf(key, sizeof key, "region%d_count", l);
        cli_result_int(run, key, r->count);
        snprintf(key, sizeof key, "region%d_fwhm_um", l);
        cli_result_num(run, key, r->mean[SVP_FIELD_FWHM] * pixel_um);
        snprintf(key, sizeof key, "region%d_beta", l);
        cli_result_num(run, key, r->mean[SVP_FIELD_BETA]);
        snprintf(key, sizeof key, "region%d_group", l);
        cli_result_int(run, key, r->group);
    }
    for (int i = 0; i < rep->n_regions; i++)
        for (int j = i + 1; j < rep->n_regions; j++) {
            double p = rep->p_value[i * rep->n_regions + j];
            if (p < 0) {
                const int k = rep->regions[i].count < 2 ? i : j;
                printf("  regions %d and %d: not compared (region %d has %d spot%s; the Welch "
                       "test needs 2)\n",
                       i, j, k, rep->regions[k].count, rep->regions[k].count == 1 ? "" : "s");
            } else {
                printf("  regions %d and %d: Welch p = %.3g (%s)\n", i, j, p,
                       p > a->mo.alpha ? "alike" : "different");
            }
            if (i * rep->n_regions + j < 64) {
                snprintf(key, sizeof key, "p_value_%d_%d", i, j);
                cli_result_num(run, key, p);
            }
        }
    cli_result_int(run, "n_groups", rep->n_groups);
    cli_result_int(run, "n_regions_without_spots", n_empty);
    printf("  %d region(s) merged into %d group(s) (alpha %g)\n", rep->n_regions, rep->n_groups,
           a->mo.alpha);
    if (n_empty)
        cli_warn(run,
                 "%s: no spot lies in region%s %s: %s PSF in %s is the mean of all spots, not a "
                 "measurement there; add spots in %s, or give %s the label of a measured region",
                 a->labels_path, n_empty == 1 ? "" : "s", empty, n_empty == 1 ? "its" : "their",
                 run->output, n_empty == 1 ? "it" : "them", n_empty == 1 ? "it" : "them");
}

/* MAP.yaml, MAP.spots.csv, MAP.summary.json and the line on stdout. */
static int map_psf_write(cli_run *run, const struct map_psf_args *a, struct map_psf_job *job)
{
    int code;
    cli_stage_begin(run, "write");
    char prov[512];
    snprintf(prov, sizeof prov, "svpsf map-psf %s: %d spots, %s", a->spots_path, job->n_spots,
             job->labels ? "per-region means" : "polynomial surfaces");
    svp_status st = svp_psf_field_write(run->output, job->field, job->pixel_um, prov, run->force);
    if (st != SVP_OK) return cli_fail(run, st, run->output);
    if ((code = cli_write_text(run, job->csv_path, job->csv))) return code;
    cli_stage_end(run);
    if ((code = cli_summary_write(run, job->summary_path))) return code;
    printf("svpsf map-psf: wrote %s (%s), %s, %s\n", run->output,
           job->labels ? "regions" : "polynomial surfaces", job->csv_path, job->summary_path);
    return 0;
}

static int run_map_psf(cli_run *run, const struct map_psf_args *a)
{
    struct map_psf_job job;
    memset(&job, 0, sizeof job);
    int code = map_psf_read(run, a, &job);
    if (!code) code = map_psf_fit(run, a, &job);
    if (!code) code = map_psf_map(run, a, &job);
    if (!code) code = map_psf_spot_lines(run, &job);
    if (!code) {
        if (job.labels)
            map_psf_report_regions(run, a, &job);
        else
            map_psf_report_poly(run, a, &job);
        code = map_psf_write(run, a, &job);
    }
    if (job.spots)
        for (int k = 0; k < job.n_spots; k++) svp_image_free(job.spots[k].image);
    free(job.spots);
    free(job.samples);
    free(job.sample_of);
    free(job.labels);
    free(job.csv);
    svp_image_free(job.labels_img);
    svp_image_free(job.field_img);
    svp_psf_field_free(job.field);
    svp_map_report_free(job.rep);
    svp_yaml_free(job.doc);
    return code;
}

int cmd_map_psf(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "map-psf", argc, argv, CLI_COMMON_OUTPUT);
    struct map_psf_args args;
    int code = parse_map_psf_args(&run, &args);
    if (code == 0) code = run_map_psf(&run, &args);
    return cli_run_finish(&run, cli_parsed_status(code));
}
