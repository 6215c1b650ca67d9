/* svpsf register: the transform between two images of the same scene (phase correlation or
 * ECC), printed and optionally written to a JSON/YAML file; optionally a third image (a label
 * mask from a layout drawing, or any image in the moving image's frame) warped onto the
 * reference grid. */
#include "cli.h"

#include "io/json.h"
#include "io/yaml.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>

enum {
    OPT_METHOD = CLI_OPTION_FIRST,
    OPT_MOTION,
    OPT_WARP,
    OPT_TRANSFORM_OUT,
    OPT_INTERP,
    OPT_BORDER,
    OPT_SMOOTH,
    OPT_NO_WINDOW,
    OPT_ITERATIONS,
    OPT_EPSILON,
    OPT_INVERT,
    OPT_NO_INVERT,
    OPT_KEEP_DOUBTFUL
};

static void print_help(const cli_run *run, FILE *out)
{
    fputs("usage: svpsf register REFERENCE MOVING [--method phase|ecc]\n"
          "                      [--motion translation|euclidean|affine]\n"
          "                      [--warp IMAGE -o OUT] [--transform-out FILE] [options]\n"
          "\n"
          "Finds the transform that maps REFERENCE pixel coordinates to MOVING pixel\n"
          "coordinates (pixel centres at integers; x = column, y = row):\n"
          "    x_moving = a0 x_ref + a1 y_ref + a2,   y_moving = a3 x_ref + a4 y_ref + a5\n"
          "and prints it with its quality: the correlation and the RMS difference of the two\n"
          "images (each scaled to zero mean and unit variance) over their overlap after\n"
          "warping. Both images must have the same size.\n"
          "\n"
          "  REFERENCE, MOVING        images (.tif, .png, .npy, .txt); NaN pixels are filled\n"
          "                           from their neighbours for the estimate\n"
          "  --method phase|ecc       phase: phase correlation, translation only, sub-pixel\n"
          "                           (default); ecc: OpenCV's enhanced correlation\n"
          "                           coefficient, started from the phase-correlation shift\n"
          "  --motion M               translation | euclidean (rotation + shift) | affine;\n"
          "                           default translation for phase, affine for ecc\n"
          "  --warp IMAGE             warp IMAGE (in MOVING's frame, any size) onto REFERENCE's\n"
          "                           grid and write it to -o OUT\n"
          "  -o, --output OUT         with --warp: the warped image (.tif, .npy, .txt, .mat);\n"
          "                           without --warp: the transform file (.json, .yaml, .yml)\n"
          "  --transform-out FILE     the transform file (.json, .yaml or .yml)\n"
          "  --interp auto|nearest|linear\n"
          "                           warp interpolation; auto (default): nearest when every\n"
          "                           finite pixel of IMAGE is an integer (a label mask), else\n"
          "                           linear\n"
          "  --border V               value where the warped image has no data (outside\n"
          "                           MOVING's frame); a number or nan; default 0 for nearest,\n"
          "                           nan for linear\n"
          "  --smooth SIGMA           Gaussian pre-smoothing of both images, pixels (default 1;\n"
          "                           0 = none)\n"
          "  --no-window              phase correlation without the Hann window (isolated\n"
          "                           spots on a flat background, periodic images)\n"
          "  --iterations N           most ECC iterations (default 100)\n"
          "  --epsilon E              ECC stops when the correlation changes by less than E\n"
          "                           between iterations (default 1e-6); not reached within N\n"
          "                           iterations: exit 2\n"
          "  --invert                 MOVING's contrast is inverted: its bright regions are\n"
          "                           dark in REFERENCE (a label mask of a metal wire on a PL\n"
          "                           image); default: detected from the sign of the\n"
          "                           correlation peak\n"
          "  --no-invert              MOVING's contrast is the same as REFERENCE's (no\n"
          "                           detection)\n"
          "  --keep-doubtful          write a result whose peak is not significant (exit 0,\n"
          "                           with a warning)\n",
          out);
    cli_print_common_help(run, out);
    fputs("\nA result whose phase-correlation peak is not significant (peak-to-sidelobe ratio\n"
          "below 10: the images may not overlap or lack common texture) is a result in doubt:\n"
          "it is printed, nothing is written and the exit status is 3; with --keep-doubtful it\n"
          "is written with a warning and the transform file says \"low_significance\": true.\n"
          "Exit status: 0 ok, 1 bad usage or input, 2 ECC did not converge, 3 not significant.\n",
          out);
}

static int is_transform_path(const char *path)
{
    const char *dot = strrchr(path, '.');
    const char *slash = strrchr(path, '/');
    if (!dot || (slash && dot < slash)) return 0;
    if (strcasecmp(dot, ".json") == 0) return 1;
    if (strcasecmp(dot, ".yaml") == 0 || strcasecmp(dot, ".yml") == 0) return 2;
    return 0;
}

static const char *const method_names[] = {"phase", "ecc", NULL};
static const char *const motion_names[] = {"translation", "euclidean", "affine", NULL};
static const char *const interp_names[] = {"auto", "nearest", "linear", NULL};
static const char *const contrast_names[] = {"auto", "same", "inverted", NULL};

/* A label mask: every finite pixel an integer. */
static int looks_like_labels(const svp_image *img)
{
    const size_t n = (size_t)img->width * img->height;
    for (size_t i = 0; i < n; i++)
        if (isfinite(img->data[i]) && img->data[i] != floor(img->data[i])) return 0;
    return 1;
}

typedef struct transform_doc {
    const char *reference, *moving;
    int width, height;
    const svp_register_options *options;
    const svp_register_result *result;
} transform_doc;

static const char *convention =
    "x_moving = a[0][0] x_ref + a[0][1] y_ref + a[0][2]; y_moving = a[1][0] x_ref + a[1][1] "
    "y_ref + a[1][2]; pixel centres at integer coordinates, x = column, y = row";

static svp_status transform_json(const transform_doc *d, svp_json *j)
{
    const svp_register_result *r = d->result;
    const svp_register_options *o = d->options;
    svp_json_begin_object(j);
    svp_json_key_int(j, "svpsf_register", 1);
    svp_json_key_string(j, "reference", d->reference);
    svp_json_key_string(j, "moving", d->moving);
    svp_json_key_int(j, "width", d->width);
    svp_json_key_int(j, "height", d->height);
    svp_json_key_string(j, "method", method_names[o->method]);
    svp_json_key_string(j, "motion", motion_names[o->motion]);
    svp_json_key_string(j, "convention", convention);
    svp_json_key(j, "affine");
    svp_json_begin_array(j);
    svp_json_number_array(j, r->affine, 3);
    svp_json_number_array(j, r->affine + 3, 3);
    svp_json_end_array(j);
    const double shift[2] = {r->shift_x, r->shift_y};
    svp_json_key(j, "shift_px");
    svp_json_number_array(j, shift, 2);
    svp_json_key_number(j, "rotation_deg", r->rotation * 180 / M_PI);
    svp_json_key_number(j, "scale", r->scale);
    svp_json_key_number(j, "correlation", r->correlation);
    svp_json_key_number(j, "residual_rms", r->residual_rms);
    svp_json_key_number(j, "overlap", r->overlap);
    svp_json_key_number(j, "response", r->response);
    svp_json_key_number(j, "significance", r->significance);
    svp_json_key_bool(j, "low_significance", r->low_significance);
    svp_json_key_string(j, "contrast", r->inverted ? "inverted" : "same");
    svp_json_key_number(j, "significance_other", r->significance_other);
    svp_json_key_int(j, "iterations", r->iterations);
    svp_json_key_int(j, "nonfinite_reference", (long long)r->nonfinite_reference);
    svp_json_key_int(j, "nonfinite_moving", (long long)r->nonfinite_moving);
    svp_json_key(j, "settings");
    svp_json_begin_object(j);
    svp_json_key_number(j, "smooth_sigma", o->smooth_sigma);
    svp_json_key_bool(j, "window", o->window);
    svp_json_key_number(j, "whitening", o->whitening);
    svp_json_key_int(j, "iterations", o->iterations);
    svp_json_key_number(j, "epsilon", o->epsilon);
    svp_json_key_string(j, "contrast", contrast_names[o->contrast]);
    svp_json_end_object(j);
    svp_json_key_string(j, "svpsf_version", svp_version());
    return svp_json_end_object(j);
}

/* The same keys as YAML (svp_yaml_writer: lossless numbers that YAML 1.1 readers see as floats,
 * .nan/.inf, strings quoted when needed). */
static void transform_yaml(const transform_doc *d, svp_yaml_writer *w)
{
    const svp_register_result *r = d->result;
    const svp_register_options *o = d->options;
    svp_yaml_begin_mapping(w);
    svp_yaml_write_key_int(w, "svpsf_register", 1);
    svp_yaml_write_key_string(w, "reference", d->reference);
    svp_yaml_write_key_string(w, "moving", d->moving);
    svp_yaml_write_key_int(w, "width", d->width);
    svp_yaml_write_key_int(w, "height", d->height);
    svp_yaml_write_key_string(w, "method", method_names[o->method]);
    svp_yaml_write_key_string(w, "motion", motion_names[o->motion]);
    svp_yaml_write_key_string(w, "convention", convention);
    svp_yaml_write_key(w, "affine");
    svp_yaml_begin_sequence(w);
    svp_yaml_write_number_list(w, r->affine, 3);
    svp_yaml_write_number_list(w, r->affine + 3, 3);
    svp_yaml_end_sequence(w);
    const double shift[2] = {r->shift_x, r->shift_y};
    svp_yaml_write_key_number_list(w, "shift_px", shift, 2);
    svp_yaml_write_key_number(w, "rotation_deg", r->rotation * 180 / M_PI);
    svp_yaml_write_key_number(w, "scale", r->scale);
    svp_yaml_write_key_number(w, "correlation", r->correlation);
    svp_yaml_write_key_number(w, "residual_rms", r->residual_rms);
    svp_yaml_write_key_number(w, "overlap", r->overlap);
    svp_yaml_write_key_number(w, "response", r->response);
    svp_yaml_write_key_number(w, "significance", r->significance);
    svp_yaml_write_key_bool(w, "low_significance", r->low_significance);
    svp_yaml_write_key_string(w, "contrast", r->inverted ? "inverted" : "same");
    svp_yaml_write_key_number(w, "significance_other", r->significance_other);
    svp_yaml_write_key_int(w, "iterations", r->iterations);
    svp_yaml_write_key_int(w, "nonfinite_reference", (long long)r->nonfinite_reference);
    svp_yaml_write_key_int(w, "nonfinite_moving", (long long)r->nonfinite_moving);
    svp_yaml_write_key(w, "settings");
    svp_yaml_begin_mapping(w);
    svp_yaml_write_key_number(w, "smooth_sigma", o->smooth_sigma);
    svp_yaml_write_key_bool(w, "window", o->window);
    svp_yaml_write_key_number(w, "whitening", o->whitening);
    svp_yaml_write_key_int(w, "iterations", o->iterations);
    svp_yaml_write_key_number(w, "epsilon", o->epsilon);
    svp_yaml_write_key_string(w, "contrast", contrast_names[o->contrast]);
    svp_yaml_end_mapping(w);
    svp_yaml_write_key_string(w, "svpsf_version", svp_version());
    svp_yaml_end_mapping(w);
}

static int write_transform(cli_run *run, const char *path, const transform_doc *d)
{
    svp_json *j = NULL;
    svp_yaml_writer *w = NULL;
    const char *text = NULL;
    svp_status st;
    if (is_transform_path(path) == 1) {
        st = svp_json_new(&j);
        if (st == SVP_OK) st = transform_json(d, j);
        if (st == SVP_OK) st = svp_json_finish(j, &text);
    } else {
        st = svp_yaml_writer_new(&w);
        if (st == SVP_OK) {
            transform_yaml(d, w);
            st = svp_yaml_writer_finish(w, &text);
        }
    }
    int code = st == SVP_OK ? cli_write_text(run, path, text) : cli_fail(run, st, path);
    svp_json_free(j);
    svp_yaml_writer_free(w);
    return code;
}

struct register_args {
    const char *reference_path, *moving_path; /* REFERENCE, MOVING */
    const char *warp_path;                    /* --warp */
    const char *warp_out;                     /* -o with --warp: the warped image */
    const char *transform_path;               /* --transform-out, or -o without --warp */
    const char *contrast_option;              /* "--invert" / "--no-invert" as given */
    int method, motion, interp;               /* indices in the name tables */
    int border_given, keep_doubtful;
    double border;            /* --border (NaN for "nan") */
    svp_register_options opt; /* the library's options, filled from the above */
};

/* What a run holds (released by run_register). */
struct register_job {
    svp_image *reference, *moving, *to_warp, *warped;
    svp_register_options opt;
    svp_register_result r;
};

static int register_option(cli_run *run, struct register_args *a, int c)
{
    svp_register_options *opt = &a->opt;
    switch (c) {
    case OPT_METHOD: return cli_parse_choice(run, "--method", optarg, method_names, &a->method);
    case OPT_MOTION: return cli_parse_choice(run, "--motion", optarg, motion_names, &a->motion);
    case OPT_WARP: a->warp_path = optarg; return 0;
    case OPT_TRANSFORM_OUT: a->transform_path = optarg; return 0;
    case OPT_INTERP: return cli_parse_choice(run, "--interp", optarg, interp_names, &a->interp);
    case OPT_BORDER:
        a->border_given = 1;
        if (strcasecmp(optarg, "nan") == 0) {
            a->border = NAN;
            return 0;
        }
        return cli_parse_double(run, "--border", optarg, &a->border);
    case OPT_SMOOTH:
        return cli_parse_double_in(run, "--smooth", optarg, 0, 1, INFINITY, 0, &opt->smooth_sigma);
    case OPT_NO_WINDOW: opt->window = 0; return 0;
    case OPT_ITERATIONS:
        return cli_parse_int(run, "--iterations", optarg, 2, 1000000, &opt->iterations);
    case OPT_EPSILON:
        return cli_parse_double_in(run, "--epsilon", optarg, 0, 0, INFINITY, 0, &opt->epsilon);
    case OPT_INVERT:
    case OPT_NO_INVERT: {
        const char *name = c == OPT_INVERT ? "--invert" : "--no-invert";
        if (a->contrast_option && strcmp(a->contrast_option, name) != 0)
            return cli_error(run, "%s and %s: give one", a->contrast_option, name);
        a->contrast_option = name;
        opt->contrast = c == OPT_INVERT ? SVP_CONTRAST_INVERTED : SVP_CONTRAST_SAME;
        return 0;
    }
    case OPT_KEEP_DOUBTFUL: a->keep_doubtful = 1; return 0;
    default: return cli_error(run, "internal: option %d", c);
    }
}

/* The method and motion, then the outputs: -o is the warped image with --warp, else the
 * transform file. */
static int register_check(cli_run *run, struct register_args *a)
{
    svp_register_options *opt = &a->opt;
    opt->method = a->method == 1 ? SVP_REGISTER_ECC : SVP_REGISTER_PHASE;
    if (a->motion < 0) a->motion = opt->method == SVP_REGISTER_ECC ? 2 : 0;
    opt->motion = (svp_register_motion)a->motion;
    if (opt->method == SVP_REGISTER_PHASE && opt->motion != SVP_MOTION_TRANSLATION)
        return cli_error(run,
                         "--motion %s needs --method ecc (phase correlation finds a translation "
                         "only)",
                         motion_names[a->motion]);
    if (a->warp_path) {
        if (!run->output)
            return cli_error(run, "--warp %s needs -o OUT for the warped image", a->warp_path);
        svp_file_format f = cli_format_of_path(run->output);
        if (f == SVP_FORMAT_AUTO || f == SVP_FORMAT_PNG16)
            return cli_error(run, "-o %s: the warped image needs a .tif, .npy, .txt or .mat name",
                             run->output);
        a->warp_out = run->output;
    } else if (run->output) {
        if (a->transform_path)
            return cli_error(run,
                             "-o %s and --transform-out %s: without --warp both name the "
                             "transform file; give one",
                             run->output, a->transform_path);
        a->transform_path = run->output;
    }
    if (a->transform_path && !is_transform_path(a->transform_path))
        return cli_error(run, "%s: the transform file needs a .json, .yaml or .yml name",
                         a->transform_path);
    return 0;
}

static int parse_register_args(cli_run *run, struct register_args *a)
{
    static const struct option own[] = {
        {"method", required_argument, NULL, OPT_METHOD},
        {"motion", required_argument, NULL, OPT_MOTION},
        {"warp", required_argument, NULL, OPT_WARP},
        {"transform-out", required_argument, NULL, OPT_TRANSFORM_OUT},
        {"interp", required_argument, NULL, OPT_INTERP},
        {"border", required_argument, NULL, OPT_BORDER},
        {"smooth", required_argument, NULL, OPT_SMOOTH},
        {"no-window", no_argument, NULL, OPT_NO_WINDOW},
        {"iterations", required_argument, NULL, OPT_ITERATIONS},
        {"epsilon", required_argument, NULL, OPT_EPSILON},
        {"invert", no_argument, NULL, OPT_INVERT},
        {"no-invert", no_argument, NULL, OPT_NO_INVERT},
        {"keep-doubtful", no_argument, NULL, OPT_KEEP_DOUBTFUL},
        {NULL, 0, NULL, 0},
    };
    memset(a, 0, sizeof *a);
    svp_register_defaults(&a->opt);
    a->motion = -1;
    int c;
    while ((c = cli_next_option(run, own)) != CLI_OPTIONS_DONE) {
        if (c == CLI_OPTION_HELP) {
            print_help(run, stdout);
            return CLI_OPTION_HELP;
        }
        if (c == CLI_OPTION_ERROR || register_option(run, a, c)) return CLI_EXIT_USAGE;
    }
    if (run->argc - optind < 2)
        return cli_error(run, "REFERENCE and MOVING images are required (see --help)");
    if (run->argc - optind > 2)
        return cli_error(run, "unexpected argument '%s'", run->argv[optind + 2]);
    a->reference_path = run->argv[optind];
    a->moving_path = run->argv[optind + 1];
    /* a handful of transforms of one size: measuring plans would cost more than it saves */
    svp_set_fft_effort(SVP_FFT_ESTIMATE);
    return register_check(run, a);
}

/* The pair (same size), the image to warp; the outputs planned and checked. */
static int register_read(cli_run *run, const struct register_args *a, struct register_job *job)
{
    int code;
    cli_stage_begin(run, "read");
    if ((code = cli_read_image(run, "reference", a->reference_path, &job->reference))) return code;
    if ((code = cli_read_image(run, "moving", a->moving_path, &job->moving))) return code;
    if ((code = cli_check_same_size(run, job->reference, "reference", a->reference_path,
                                    job->moving, "moving", a->moving_path)))
        return code;
    if (a->warp_path && (code = cli_read_image(run, "warp", a->warp_path, &job->to_warp)))
        return code;
    if (a->warp_out) cli_output_file(run, "warped", a->warp_out);
    if (a->transform_path) cli_output_file(run, "transform", a->transform_path);
    return cli_outputs_check(run);
}

/* The transform as found, on stdout. */
static void register_print(const struct register_args *a, const struct register_job *job)
{
    const svp_register_result *r = &job->r;
    const double *m = r->affine;
    const int ecc = job->opt.method == SVP_REGISTER_ECC;
    printf("registration of %s onto %s (%d x %d), %s, %s\n", a->moving_path, a->reference_path,
           job->reference->width, job->reference->height, ecc ? "ECC" : "phase correlation",
           motion_names[a->motion]);
    printf("  affine      x_moving = %.8g x_ref %+.8g y_ref %+.6f\n", m[0], m[1], m[2]);
    printf("              y_moving = %.8g x_ref %+.8g y_ref %+.6f\n", m[3], m[4], m[5]);
    printf("              (reference -> moving pixel coordinates, pixel centres at integers)\n");
    printf("  shift       %+.4f %+.4f px (where the reference centre lies in the moving image, "
           "minus the centre)\n",
           r->shift_x, r->shift_y);
    printf("  rotation    %+.5f deg   scale %.6f\n", r->rotation * 180 / M_PI, r->scale);
    printf("  residual    RMS %.4g (in standard deviations) over %.1f %% of the reference; "
           "correlation %.5f\n",
           r->residual_rms, 100 * r->overlap, r->correlation);
    if (isfinite(r->response))
        printf("  phase peak  response %.3f, significance %.1f\n", r->response, r->significance);
    if (job->opt.contrast != SVP_CONTRAST_AUTO)
        printf("  contrast    %s (%s)\n", r->inverted ? "inverted" : "same", a->contrast_option);
    else if (isfinite(r->significance_other))
        printf("  contrast    %s (detected: the correlation's %s, significance %.1f, against "
               "%.1f for its %s)\n",
               r->inverted ? "inverted" : "same", r->inverted ? "trough" : "peak", r->significance,
               r->significance_other, r->inverted ? "peak" : "trough");
    if (ecc) printf("  ECC         %d iterations\n", r->iterations);
    if (r->nonfinite_reference || r->nonfinite_moving)
        printf("  NaN/Inf     %zu reference and %zu moving pixels, filled from their neighbours "
               "for the estimate and left out of the residual\n",
               r->nonfinite_reference, r->nonfinite_moving);
}

/* The registration; a peak that is not significant is a result in doubt (docs/cli.md, exit
 * status): printed, nothing written, unless --keep-doubtful. */
static int register_compute(cli_run *run, const struct register_args *a, struct register_job *job)
{
    svp_register_options *opt = &job->opt;
    cli_stage_begin(run, "register");
    if (opt->method == SVP_REGISTER_ECC) {
        cli_progress_start(run, "ECC");
        opt->progress = cli_progress;
        opt->progress_user = run;
    }
    opt->reference_name = a->reference_path;
    opt->moving_name = a->moving_path;
    svp_status st = svp_register(job->reference, job->moving, opt, &job->r);
    if (opt->method == SVP_REGISTER_ECC) cli_progress_done(run);
    if (st != SVP_OK) {
        /* the library names an image by its file (options above); the fault is the pair's */
        char pair[8192];
        snprintf(pair, sizeof pair, "%s onto %s", a->moving_path, a->reference_path);
        return cli_fail(run, st, pair);
    }
    register_print(a, job);
    const svp_register_result *r = &job->r;
    if (r->low_significance && !a->keep_doubtful) {
        cli_error(run,
                  "%s onto %s: the phase-correlation peak is not significant (%.1f < %g): the "
                  "images may not overlap or share no texture, so the transform cannot be "
                  "vouched for; nothing written (check the pair%s; --keep-doubtful writes it)",
                  a->moving_path, a->reference_path, r->significance, opt->min_significance,
                  opt->contrast == SVP_CONTRAST_SAME ? "; without --no-invert the contrast is "
                                                       "detected"
                                                     : "");
        return CLI_EXIT_DOUBTFUL;
    }
    if (r->low_significance)
        cli_warn(run,
                 "the phase-correlation peak is not significant (%.1f < %g): the images may not "
                 "overlap or share no texture; the transform is unreliable (--keep-doubtful: "
                 "written)",
                 r->significance, opt->min_significance);
    return 0;
}

/* --warp: the third image on the reference grid (nearest for a label mask, else linear). */
static int register_warp(cli_run *run, const struct register_args *a, struct register_job *job)
{
    const svp_image *to_warp = job->to_warp;
    int code;
    cli_stage_begin(run, "warp");
    const int labels = looks_like_labels(to_warp);
    const svp_interpolation how =
        a->interp == 1 || (a->interp == 0 && labels) ? SVP_INTERP_NEAREST : SVP_INTERP_LINEAR;
    double border = a->border;
    if (!a->border_given) border = how == SVP_INTERP_NEAREST ? 0 : NAN;
    svp_status st;
    if ((st = svp_image_new(job->reference->width, job->reference->height, &job->warped)) !=
            SVP_OK ||
        (st = svp_warp(to_warp, job->r.affine, how, border, job->warped)) != SVP_OK)
        return cli_fail(run, st, a->warp_path);
    cli_stage_begin(run, "write");
    if ((code = cli_write_image(run, a->warp_out, job->warped))) return code;
    printf("  warped      %s (%d x %d) -> %s (%d x %d), %s interpolation%s, border %g\n",
           a->warp_path, to_warp->width, to_warp->height, a->warp_out, job->warped->width,
           job->warped->height, how == SVP_INTERP_NEAREST ? "nearest" : "linear",
           a->interp == 0
               ? (labels ? " (integer pixels: a label mask)" : " (non-integer pixels: an image)")
               : "",
           border);
    return 0;
}

static int run_register(cli_run *run, const struct register_args *a)
{
    struct register_job job;
    memset(&job, 0, sizeof job);
    job.opt = a->opt;
    int code = register_read(run, a, &job);
    if (!code) code = register_compute(run, a, &job);
    if (!code && a->warp_path) code = register_warp(run, a, &job);
    if (!code && a->transform_path) {
        cli_stage_begin(run, "write");
        const transform_doc doc = {a->reference_path,     a->moving_path, job.reference->width,
                                   job.reference->height, &job.opt,       &job.r};
        code = write_transform(run, a->transform_path, &doc);
        if (!code) printf("  transform   written to %s\n", a->transform_path);
    }
    if (!code) cli_stage_end(run);
    svp_image_free(job.reference);
    svp_image_free(job.moving);
    svp_image_free(job.to_warp);
    svp_image_free(job.warped);
    return code;
}

int cmd_register(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "register", argc, argv, CLI_COMMON_OUTPUT);
    struct register_args args;
    int code = parse_register_args(&run, &args);
    if (code == 0) code = run_register(&run, &args);
    return cli_run_finish(&run, cli_parsed_status(code));
}
