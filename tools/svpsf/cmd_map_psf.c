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
    OPT_MODEL,
    OPT_CIRCULAR,
    OPT_GAIN,
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
          "  --max-degree N        largest degree auto tries (default 3)\n"
          "  --model M             moffat (default), gaussian or lorentzian\n"
          "  --circular            round spot fits (no ellipticity)\n"
          "  --gain G              photons per data unit (default 1)\n"
          "  --halo A              background-halo fraction alpha_b written into the map\n"
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

int cmd_map_psf(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "map-psf", argc, argv, CLI_COMMON_OUTPUT);
    static const struct option own[] = {
        {"labels", required_argument, NULL, OPT_LABELS},
        {"degree", required_argument, NULL, OPT_DEGREE},
        {"max-degree", required_argument, NULL, OPT_MAX_DEGREE},
        {"model", required_argument, NULL, OPT_MODEL},
        {"circular", no_argument, NULL, OPT_CIRCULAR},
        {"gain", required_argument, NULL, OPT_GAIN},
        {"halo", required_argument, NULL, OPT_HALO},
        {"transition-um", required_argument, NULL, OPT_TRANSITION},
        {"alpha", required_argument, NULL, OPT_ALPHA},
        {"clip-kappa", required_argument, NULL, OPT_CLIP},
        {"window", required_argument, NULL, OPT_WINDOW},
        {"threshold", required_argument, NULL, OPT_THRESHOLD},
        {NULL, 0, NULL, 0},
    };
    svp_spot_options so;
    svp_spot_defaults(&so);
    svp_map_options mo;
    svp_map_defaults(&mo);
    const char *labels_path = NULL;
    int model = SVP_PSF_MOFFAT, window = 0, window_given = 0, threshold_given = 0;
    double threshold = 10, transition_um = 0;
    svp_yaml_doc *doc = NULL;
    svp_image *labels_img = NULL, *field_img = NULL;
    int *labels = NULL;
    spot_entry *spots = NULL;
    int n_spots = 0;
    svp_psf_sample *samples = NULL;
    int *sample_of = NULL;
    svp_psf_field *field = NULL;
    svp_map_report *rep = NULL;
    char *csv = NULL;
    int code = 0;
    svp_status st;

    int c;
    while ((c = cli_next_option(&run, own)) != CLI_OPTIONS_DONE) {
        int bad = 0;
        switch (c) {
        case CLI_OPTION_HELP: print_help(&run, stdout); return cli_run_finish(&run, 0);
        case CLI_OPTION_ERROR: return cli_run_finish(&run, CLI_EXIT_USAGE);
        case OPT_LABELS: labels_path = optarg; break;
        case OPT_DEGREE:
            if (strcmp(optarg, "auto") == 0)
                mo.degree = -1;
            else if (cli_parse_int(&run, "--degree", optarg, 0, 8, &mo.degree))
                return cli_run_finish(&run, CLI_EXIT_USAGE);
            break;
        case OPT_MAX_DEGREE:
            bad = cli_parse_int(&run, "--max-degree", optarg, 0, 8, &mo.max_degree);
            break;
        case OPT_MODEL:
            bad = cli_parse_choice(&run, "--model", optarg, cli_psf_model_names, &model);
            break;
        case OPT_CIRCULAR: so.elliptical = 0; break;
        case OPT_GAIN:
            bad = cli_parse_double_in(&run, "--gain", optarg, 0, 1, INFINITY, 0, &so.noise.gain);
            break;
        case OPT_HALO:
            bad = cli_parse_double_in(&run, "--halo", optarg, 0, 1, 1, 0, &mo.halo);
            break;
        case OPT_TRANSITION:
            bad = cli_parse_double_in(&run, "--transition-um", optarg, 0, 1, INFINITY, 0,
                                      &transition_um);
            break;
        case OPT_ALPHA:
            bad = cli_parse_double_in(&run, "--alpha", optarg, 0, 0, 1, 0, &mo.alpha);
            break;
        case OPT_CLIP:
            bad = cli_parse_double_in(&run, "--clip-kappa", optarg, 0, 1, INFINITY, 0,
                                      &mo.clip_kappa);
            break;
        case OPT_WINDOW:
            if (cli_parse_int(&run, "--window", optarg, 7, 1001, &window))
                return cli_run_finish(&run, CLI_EXIT_USAGE);
            if (window % 2 == 0)
                return cli_run_finish(&run, cli_error(&run, "--window %d: must be odd", window));
            window_given = 1;
            break;
        case OPT_THRESHOLD:
            if (cli_parse_double_in(&run, "--threshold", optarg, 0, 0, INFINITY, 0, &threshold))
                return cli_run_finish(&run, CLI_EXIT_USAGE);
            threshold_given = 1;
            break;
        default: return cli_run_finish(&run, cli_error(&run, "internal: option %d", c));
        }
        if (bad) return cli_run_finish(&run, CLI_EXIT_USAGE);
    }
    if (optind >= argc)
        return cli_run_finish(&run, cli_error(&run, "SPOTS.yaml is required (see --help)"));
    if (optind + 1 < argc)
        return cli_run_finish(&run, cli_error(&run, "unexpected argument '%s'", argv[optind + 1]));
    const char *spots_path = argv[optind];
    if (!run.output) return cli_run_finish(&run, cli_error(&run, "-o MAP.yaml is required"));
    if (!cli_yaml_extension(run.output))
        return cli_run_finish(&run, cli_error(&run, "-o %s: the PSF map must end in .yaml or .yml",
                                              run.output));
    so.model = (svp_psf_model)model;

    /* ---- read SPOTS.yaml, the images, the labels ---- */
    cli_stage_begin(&run, "read");
    double pixel_um = 0;
    int width = 0, height = 0;
    if ((st = svp_yaml_load_file(spots_path, &doc)) != SVP_OK) {
        code = cli_fail(&run, st, spots_path);
        goto cleanup;
    }
    cli_record_input(&run, "spots", spots_path, 0, 0);
    {
        const svp_yaml_node *root = svp_yaml_root(doc), *node;
        static const char *const keys[] = {"pixel_um", "field",     "spots",   "image",
                                           "window",   "threshold", "comment", NULL};
        if ((st = svp_yaml_expect_mapping(root, NULL)) != SVP_OK ||
            (st = svp_yaml_check_keys(root, NULL, keys)) != SVP_OK ||
            (st = svp_yaml_require(root, "pixel_um", NULL, &node)) != SVP_OK ||
            (st = svp_yaml_number_in(node, "pixel_um", SVP_PIXEL_UM_MIN, INFINITY, 0, &pixel_um)) !=
                SVP_OK)
            goto yaml_fail;
        const svp_yaml_node *list = svp_yaml_get(root, "spots"),
                            *image = svp_yaml_get(root, "image");
        if (!list == !image) {
            st = svp_yaml_fail(root, SVP_ERR_FORMAT,
                               "give either 'spots' (a list of spot images) "
                               "or 'image' (one image with many spots)");
            goto yaml_fail;
        }
        if (image) {
            const char *name;
            long long wv = 31;
            if ((st = svp_yaml_string(image, "image", &name)) != SVP_OK) goto yaml_fail;
            if ((st = svp_yaml_get_int(root, "window", 7, 1001, &wv, NULL)) != SVP_OK)
                goto yaml_fail;
            if (wv % 2 == 0) {
                st = svp_yaml_fail(svp_yaml_get(root, "window"), SVP_ERR_FORMAT,
                                   "window: %lld must be odd", wv);
                goto yaml_fail;
            }
            double th = 10;
            if ((st = svp_yaml_get_number(root, "threshold", 0, INFINITY, SVP_YAML_OPEN_LO, &th,
                                          NULL)) != SVP_OK)
                goto yaml_fail;
            if (!window_given) window = (int)wv;
            if (!threshold_given) threshold = th;
            if (svp_yaml_get(root, "field")) {
                st = svp_yaml_fail(svp_yaml_get(root, "field"), SVP_ERR_FORMAT,
                                   "field: not with 'image' (the field is the image)");
                goto yaml_fail;
            }
            char path[4096];
            relative_to(spots_path, name, path, sizeof path);
            if ((code = cli_read_image(&run, "image", path, &field_img))) goto cleanup;
            width = field_img->width;
            height = field_img->height;
            cli_stage_begin(&run, "detect");
            if ((code = detect(&run, field_img, path, window, threshold, &spots, &n_spots)))
                goto cleanup;
            cli_stage_begin(&run, "read");
            cli_setting_int(&run, "window", window);
            cli_setting_num(&run, "threshold", threshold);
        } else {
            const svp_yaml_node *f = svp_yaml_get(root, "field");
            if (f) {
                static const char *const fk[] = {"width", "height", NULL};
                long long wv, hv;
                const svp_yaml_node *a, *b;
                if ((st = svp_yaml_expect_mapping(f, "field")) != SVP_OK ||
                    (st = svp_yaml_check_keys(f, "field", fk)) != SVP_OK ||
                    (st = svp_yaml_require(f, "width", "field", &a)) != SVP_OK ||
                    (st = svp_yaml_int(a, "width", 1, 1 << 20, &wv)) != SVP_OK ||
                    (st = svp_yaml_require(f, "height", "field", &b)) != SVP_OK ||
                    (st = svp_yaml_int(b, "height", 1, 1 << 20, &hv)) != SVP_OK)
                    goto yaml_fail;
                width = (int)wv;
                height = (int)hv;
            }
            if (svp_yaml_type_of(list) != SVP_YAML_SEQUENCE || svp_yaml_size(list) == 0) {
                st = svp_yaml_fail(list, SVP_ERR_FORMAT, "spots: expected a non-empty list");
                goto yaml_fail;
            }
            n_spots = (int)svp_yaml_size(list);
            spots = calloc((size_t)n_spots, sizeof *spots);
            if (!spots) {
                cli_error(&run, "out of memory");
                code = CLI_EXIT_RUNTIME;
                goto cleanup;
            }
            for (int k = 0; k < n_spots; k++) {
                const svp_yaml_node *it = svp_yaml_item(list, (size_t)k), *fn;
                static const char *const sk[] = {"file", "origin", "x", "y", NULL};
                const char *name;
                if ((st = svp_yaml_expect_mapping(it, "spot")) != SVP_OK ||
                    (st = svp_yaml_check_keys(it, "spot", sk)) != SVP_OK ||
                    (st = svp_yaml_require(it, "file", "spot", &fn)) != SVP_OK ||
                    (st = svp_yaml_string(fn, "file", &name)) != SVP_OK)
                    goto yaml_fail;
                const svp_yaml_node *org = svp_yaml_get(it, "origin");
                int has_x = svp_yaml_get(it, "x") != NULL, has_y = svp_yaml_get(it, "y") != NULL;
                if (!org == !(has_x && has_y) || has_x != has_y) {
                    st = svp_yaml_fail(it, SVP_ERR_FORMAT,
                                       "spot: give either origin: [x, y] (the cut-out's corner "
                                       "in the field) or x and y (the spot's centre)");
                    goto yaml_fail;
                }
                spots[k].x = spots[k].y = NAN;
                if (org) {
                    double v[2];
                    size_t cnt;
                    if ((st = svp_yaml_number_list(org, "origin", 2, 2, v, &cnt)) != SVP_OK)
                        goto yaml_fail;
                    spots[k].ox = v[0];
                    spots[k].oy = v[1];
                } else if ((st = svp_yaml_get_number(it, "x", -INFINITY, INFINITY, 0, &spots[k].x,
                                                     NULL)) != SVP_OK ||
                           (st = svp_yaml_get_number(it, "y", -INFINITY, INFINITY, 0, &spots[k].y,
                                                     NULL)) != SVP_OK)
                    goto yaml_fail;
                relative_to(spots_path, name, spots[k].path, sizeof spots[k].path);
                if ((code = cli_read_image(&run, "spot", spots[k].path, &spots[k].image)))
                    goto cleanup;
            }
        }
        goto yaml_ok;
    yaml_fail:
        code = cli_fail(&run, st, spots_path);
        goto cleanup;
    }
yaml_ok:
    if (labels_path) {
        if ((code = cli_read_image(&run, "labels", labels_path, &labels_img))) goto cleanup;
        if (width == 0) {
            width = labels_img->width;
            height = labels_img->height;
        } else if (labels_img->width != width || labels_img->height != height) {
            code = cli_error(&run,
                             "size mismatch: --labels %s is %d x %d but the field of %s is "
                             "%d x %d",
                             labels_path, labels_img->width, labels_img->height, spots_path, width,
                             height);
            goto cleanup;
        }
    }
    if (width == 0) {
        code = cli_error(&run,
                         "%s: the field size is unknown: add field: {width: W, height: H} "
                         "(or give --labels)",
                         spots_path);
        goto cleanup;
    }
    int n_labels = 0;
    if (labels_img) {
        size_t N = (size_t)width * height;
        labels = malloc(N * sizeof *labels);
        if (!labels) {
            cli_error(&run, "out of memory");
            code = CLI_EXIT_RUNTIME;
            goto cleanup;
        }
        for (size_t i = 0; i < N; i++) {
            double v = labels_img->data[i];
            if (!(v >= 0 && v <= 1000000 && v == floor(v))) {
                code = cli_error(&run,
                                 "%s: pixel (%zu, %zu) is %g: labels must be integers "
                                 "0..L-1",
                                 labels_path, i % (size_t)width, i / (size_t)width, v);
                goto cleanup;
            }
            labels[i] = (int)v;
            if (labels[i] + 1 > n_labels) n_labels = labels[i] + 1;
        }
        if (n_labels > 4096) {
            code = cli_error(&run, "%s: %d labels: at most 4096 regions", labels_path, n_labels);
            goto cleanup;
        }
    }
    if (n_spots == 0) {
        code = cli_error(&run, "%s: no spots to fit", spots_path);
        goto cleanup;
    }

    /* ---- outputs ---- */
    char csv_path[4096], summary_path[4096], labels_out[4096];
    cli_path_sibling(run.output, ".spots.csv", csv_path, sizeof csv_path);
    cli_path_sibling(run.output, ".summary.json", summary_path, sizeof summary_path);
    cli_output_file(&run, "map", run.output);
    if (labels) {
        cli_path_sibling(run.output, ".labels.npy", labels_out, sizeof labels_out);
        cli_output_file(&run, "labels", labels_out);
    }
    cli_output_file(&run, "spots", csv_path);
    cli_output_file(&run, "summary", summary_path);
    if ((code = cli_outputs_check(&run))) goto cleanup;
    cli_setting_num(&run, "pixel_um", pixel_um);
    cli_setting_str(&run, "model", cli_psf_model_names[model]);
    cli_setting_str(&run, "map", labels ? "regions" : "poly");
    if (!labels) {
        if (mo.degree < 0)
            cli_setting_str(&run, "degree", "auto");
        else
            cli_setting_int(&run, "degree", mo.degree);
    }
    cli_setting_num(&run, "halo", mo.halo);
    cli_setting_int(&run, "n_spots", n_spots);

    /* ---- fits (independent: in parallel, each result the same at any thread count) ---- */
    cli_stage_begin(&run, "fit");
    cli_progress_start(&run, "fitting spots");
    int n_done = 0;
#pragma omp parallel for schedule(dynamic)
    for (int k = 0; k < n_spots; k++) {
        spot_entry *e = &spots[k];
        e->status = svp_spot_fit(e->image, &so, &e->fit, NULL, NULL);
        if (e->status != SVP_OK) snprintf(e->error, sizeof e->error, "%s", svp_last_error());
        int done;
#pragma omp atomic capture
        done = ++n_done;
        /* progress is drawn by one thread only (cli_progress is not thread-safe) */
        if (omp_get_thread_num() == 0) cli_progress(&run, (double)done / n_spots);
    }
    cli_progress_done(&run);
    samples = calloc((size_t)n_spots, sizeof *samples);
    sample_of = malloc((size_t)n_spots * sizeof *sample_of);
    if (!samples || !sample_of) {
        cli_error(&run, "out of memory");
        code = CLI_EXIT_RUNTIME;
        goto cleanup;
    }
    int n_samples = 0, n_failed = 0;
    for (int k = 0; k < n_spots; k++) {
        spot_entry *e = &spots[k];
        sample_of[k] = -1;
        /* a fit that did not converge is still a sample (flagged NOT_CONVERGED: the map
         * rejects it with that reason); one that could not be made at all is not */
        if (e->status != SVP_OK &&
            !(e->status == SVP_ERR_NUMERIC && (e->fit.flags & SVP_SPOT_NOT_CONVERGED))) {
            n_failed++;
            continue;
        }
        svp_psf_sample *s = &samples[n_samples];
        s->fit = e->fit;
        s->x = isnan(e->x) ? e->ox + e->fit.x0 : e->x;
        s->y = isnan(e->y) ? e->oy + e->fit.y0 : e->y;
        sample_of[k] = n_samples++;
    }

    /* every fit failed: say so (with each spot's reason), not "no spots given" */
    if (n_samples == 0 && n_spots > 0) {
        for (int k = 0; k < n_spots; k++)
            fprintf(stderr, "svpsf map-psf: spot %d (%s): fit failed: %s\n", k, spots[k].path,
                    spots[k].error);
        if (n_spots == 1)
            code = cli_error(&run, "%s: its only spot failed its fit (%s); no PSF map written",
                             spots_path, spots[0].error);
        else
            code = cli_error(&run,
                             "%s: all %d spots failed their fits (spot 0: %s; each spot's "
                             "reason above); no PSF map written",
                             spots_path, n_spots, spots[0].error);
        goto cleanup;
    }

    /* ---- the map ---- */
    cli_stage_begin(&run, "map");
    if (labels) {
        mo.transition = transition_um / pixel_um;
        st = svp_psf_map_regions(samples, n_samples, labels, width, height, n_labels, &mo, &field,
                                 &rep);
    } else {
        st = svp_psf_map_poly(samples, n_samples, width, height, &mo, &field, &rep);
    }
    if (st != SVP_OK) {
        for (int k = 0; k < n_spots; k++)
            if (sample_of[k] < 0)
                fprintf(stderr, "svpsf map-psf: spot %d (%s): fit failed: %s\n", k, spots[k].path,
                        spots[k].error);
        code = cli_fail(&run, st, spots_path);
        goto cleanup;
    }

    /* per-spot lines: CSV, and the rejections on stdout */
    {
        size_t cap = 256 + (size_t)n_spots * 1400, len = 0;
        csv = malloc(cap);
        if (!csv) {
            cli_error(&run, "out of memory");
            code = CLI_EXIT_RUNTIME;
            goto cleanup;
        }
        len += (size_t)snprintf(csv + len, cap - len,
                                "index,file,x_px,y_px,fwhm_um,fwhm_err_um,beta,beta_err,e1,e2,"
                                "chi2_red,flags,status\n");
        int n_kept = 0, n_rejected = 0;
        for (int k = 0; k < n_spots; k++) {
            char flags[256], desc[1024];
            spot_entry *e = &spots[k];
            int si = sample_of[k];
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
            const svp_spot_result *f = &samples[si].fit;
            svp_spot_flags_describe(f->flags, flags, sizeof flags);
            svp_map_describe_sample(rep, samples, si, desc, sizeof desc);
            const char *status = strstr(desc, "): ");
            status = status ? status + 3 : desc;
            int kept = strcmp(status, "kept") == 0;
            n_kept += kept;
            n_rejected += !kept;
            if (!kept)
                printf("spot %d (%s, x %.1f, y %.1f): %s\n", k, e->path, samples[si].x,
                       samples[si].y, status);
            char st_csv[1024];
            snprintf(st_csv, sizeof st_csv, "%s", status);
            for (char *p = st_csv; *p; p++)
                if (*p == ',') *p = ';';
            len += (size_t)snprintf(csv + len, cap - len,
                                    "%d,%s,%.6f,%.6f,%.8g,%.8g,%.8g,%.8g,%.8g,%.8g,%.6g,%s,%s\n", k,
                                    e->path, samples[si].x, samples[si].y, f->fwhm * pixel_um,
                                    f->fwhm_err * pixel_um, f->beta, f->beta_err, f->e1, f->e2,
                                    f->chi2_red, flags, st_csv);
        }
        cli_result_int(&run, "spots_fitted", n_spots - n_failed);
        cli_result_int(&run, "spots_failed", n_failed);
        cli_result_int(&run, "spots_kept_all_parameters", n_kept);
        cli_result_int(&run, "spots_rejected", n_rejected);
        printf("%d spots: %d kept, %d rejected (%d fits failed)\n", n_spots, n_kept, n_rejected,
               n_failed);
    }
    static const char *const pnames[SVP_FIELD_NPARAM] = {"fwhm", "e1", "e2", "beta", "halo"};
    char key[96];
    if (!labels) {
        for (int q = 0; q < SVP_FIELD_NPARAM; q++) {
            if (!rep->mapped[q]) continue;
            double scale = q == SVP_FIELD_FWHM ? pixel_um : 1;
            printf("  %-5s degree %d, %d spots, rms residual %.4g%s, chi2_red %.3f\n", pnames[q],
                   rep->degree[q], rep->n_used[q], rep->rms[q] * scale,
                   q == SVP_FIELD_FWHM ? " um" : "", rep->chi2_red[q]);
            snprintf(key, sizeof key, "%s_degree", pnames[q]);
            cli_result_int(&run, key, rep->degree[q]);
            snprintf(key, sizeof key, "%s_rms", pnames[q]);
            cli_result_num(&run, key, rep->rms[q] * scale);
            snprintf(key, sizeof key, "%s_chi2_red", pnames[q]);
            cli_result_num(&run, key, rep->chi2_red[q]);
            snprintf(key, sizeof key, "%s_n_used", pnames[q]);
            cli_result_int(&run, key, rep->n_used[q]);
        }
    } else {
        for (int l = 0; l < rep->n_regions; l++) {
            const svp_region_stats *r = &rep->regions[l];
            printf("  region %d: %d spots, FWHM %.4f +- %.4f um, beta %.4f +- %.4f -> group %d\n",
                   r->label, r->count, r->mean[SVP_FIELD_FWHM] * pixel_um,
                   r->sem[SVP_FIELD_FWHM] * pixel_um, r->mean[SVP_FIELD_BETA],
                   r->sem[SVP_FIELD_BETA], r->group);
            snprintf(key, sizeof key, "region%d_count", l);
            cli_result_int(&run, key, r->count);
            snprintf(key, sizeof key, "region%d_fwhm_um", l);
            cli_result_num(&run, key, r->mean[SVP_FIELD_FWHM] * pixel_um);
            snprintf(key, sizeof key, "region%d_beta", l);
            cli_result_num(&run, key, r->mean[SVP_FIELD_BETA]);
            snprintf(key, sizeof key, "region%d_group", l);
            cli_result_int(&run, key, r->group);
        }
        for (int a = 0; a < rep->n_regions; a++)
            for (int b = a + 1; b < rep->n_regions; b++) {
                double p = rep->p_value[a * rep->n_regions + b];
                printf("  regions %d and %d: Welch p = %.3g (%s)\n", a, b, p,
                       p < 0          ? "too few spots"
                       : p > mo.alpha ? "alike"
                                      : "different");
                if (a * rep->n_regions + b < 64) {
                    snprintf(key, sizeof key, "p_value_%d_%d", a, b);
                    cli_result_num(&run, key, p);
                }
            }
        cli_result_int(&run, "n_groups", rep->n_groups);
        printf("  %d region(s) merged into %d group(s) (alpha %g)\n", rep->n_regions, rep->n_groups,
               mo.alpha);
    }

    cli_stage_begin(&run, "write");
    {
        char prov[512];
        snprintf(prov, sizeof prov, "svpsf map-psf %s: %d spots, %s", spots_path, n_spots,
                 labels ? "per-region means" : "polynomial surfaces");
        if ((st = svp_psf_field_write(run.output, field, pixel_um, prov, run.force)) != SVP_OK) {
            code = cli_fail(&run, st, run.output);
            goto cleanup;
        }
    }
    if ((code = cli_write_text(&run, csv_path, csv))) goto cleanup;
    cli_stage_end(&run);
    if ((code = cli_summary_write(&run, summary_path))) goto cleanup;
    printf("svpsf map-psf: wrote %s (%s), %s, %s\n", run.output,
           labels ? "regions" : "polynomial surfaces", csv_path, summary_path);

cleanup:
    if (spots)
        for (int k = 0; k < n_spots; k++) svp_image_free(spots[k].image);
    free(spots);
    free(samples);
    free(sample_of);
    free(labels);
    free(csv);
    svp_image_free(labels_img);
    svp_image_free(field_img);
    svp_psf_field_free(field);
    svp_map_report_free(rep);
    svp_yaml_free(doc);
    return cli_run_finish(&run, code);
}
