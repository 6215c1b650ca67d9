/* svpsf correct: the inverse transform T⁻¹ (eq. 4): the true maps from measured ones. */
#include "cli.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

enum {
    OPT_METHOD = CLI_OPTION_FIRST,
    OPT_PL_FLOOR,
    OPT_SHIFT,
    OPT_MARGIN,
    OPT_GAIN,
    OPT_OFFSET,
    OPT_FIELD_SIGMA,
    OPT_PLAUSIBLE,
    OPT_SIDE_BY_SIDE,
    OPT_TAIL_TOL,
};

static const char *const on_off[] = {"off", "on", NULL};

/* correct's --operator-tol default: the field error of a correction is dominated by the
 * deconvolution's own (iterations, noise), not by an operator error of 1e-2; measured on the
 * smooth-map benchmark (docs/performance.md, space-variant correction) the field error is within
 * 1.5 % of 1e-3's, at about half the time (docs/cli.md). */
#define CORRECT_OPERATOR_TOL 1e-2
/* the default precision is single from this many pixels (r, rl-signed, one PSF) */
#define SINGLE_FROM_PIXELS ((size_t)1024 * 1024)

static const char *const method_names[] = {"rw", "r", "w", "rl-signed", NULL};
static const svp_method method_values[] = {SVP_METHOD_RW, SVP_METHOD_R, SVP_METHOD_W,
                                           SVP_METHOD_RL_SIGNED};

static const char *method_long_name(svp_method m)
{
    switch (m) {
    case SVP_METHOD_RW: return "R&W (Richardson-Lucy on the PL, Wiener-Hunt on field x PL)";
    case SVP_METHOD_R: return "R (Richardson-Lucy on both, signed numerator by a shift)";
    case SVP_METHOD_W: return "W (Wiener-Hunt on both)";
    case SVP_METHOD_RL_SIGNED:
        return "RL-signed (Richardson-Lucy on the PL and on the shifted "
               "numerator)";
    }
    return "?";
}

static void print_help(const cli_run *run, FILE *out)
{
    svp_correct_options d;
    svp_correct_defaults(&d);
    fputs("usage: svpsf correct --field Bt.npy [--field ...] --pl It.npy --psf PSF -o DIR\n"
          "                     [--method rw|r|w|rl-signed] [options]\n"
          "\n"
          "The inverse transform T^-1 (eq. 4 of docs/model.md): from the measured (apparent)\n"
          "field map(s) Bt and PL map It, recovers\n"
          "    pl = It (/) p,   field = ((Bt It) (/) p) / max(pl, floor)\n"
          "with two deconvolutions (/) instead of one per spectral frame. Several --field maps\n"
          "share the one deconvolution of the PL. NaN/Inf input pixels (failed fits) are\n"
          "missing data: they are not smeared over the image, and they are counted.\n"
          "\n"
          "inputs (TIFF float32/16-bit, 16-bit PNG, .npy, .txt as numpy.savetxt writes them):\n"
          "  --field FILE          a measured field map (repeat for several components)\n"
          "  --pl FILE             the measured PL map (same size)\n"
          "  --psf FILE            a YAML PSF file or PSF-map file (docs/cli.md) or a kernel\n"
          "                        image (.npy, .tif, .txt; normalised to unit sum, centre at\n"
          "                        the middle pixel)\n"
          "options:\n"
          "  -o, --output DIR      output folder, created when missing (required)\n",
          out);
    fprintf(out,
            "  --method rw|r|w|rl-signed  the deconvolutions (default r: the most accurate on\n"
            "                        measured-like data, docs/accuracy.md):\n"
            "                        r: Richardson-Lucy on both (signed data through a shift)\n"
            "                        rw: Richardson-Lucy on the PL, Wiener-Hunt on field x PL\n"
            "                        w: Wiener-Hunt on both\n"
            "                        rl-signed: as r, named for what it does\n"
            "  --iterations N|auto   Richardson-Lucy iterations (default %d); auto: that many at\n"
            "                        most, stopping when the PL's residual reaches its noise\n"
            "                        (chi2 per pixel 1) or stops falling (the model's floor);\n"
            "                        the numerators run the same count (docs/model.md §6).\n"
            "                        A magnetisation reconstructed from the field was best at\n"
            "                        30-50 on the reference study's scenes and a current kept\n"
            "                        improving to 150 on foreign data: compare on your own\n"
            "                        (docs/reference-study.md §2)\n"
            "  --acceleration none|biggs-andrews  Richardson-Lucy vector extrapolation\n"
            "                        (default none); biggs-andrews reaches plain RL's error in\n"
            "                        fewer iterations (docs/accuracy.md)\n"
            "  --margin auto|PX      estimate the object on the view plus PX pixels per side, the\n"
            "                        data term over the view only: light from outside the view\n"
            "                        (zero boundary; a PSF map carries its edge's PSFs onto the\n"
            "                        margin; default auto for r and rl-signed with one PSF, 0\n"
            "                        for rw, w and maps; auto: where the PSF (a map's widest)\n"
            "                        falls to 1 %% of its peak, at most a quarter of the view, 0\n"
            "                        where it does not apply; --margin 0 turns it off)\n"
            "  --gain G              camera gain of the PL (counts per detected photon): the PL's\n"
            "                        shot noise var = G (PL - offset) for the automatic choices;\n"
            "                        default: estimated from the PL and reported\n"
            "  --offset O            camera offset subtracted from the PL first (default 0)\n"
            "  --field-sigma FILE    per-pixel 1-sigma uncertainty of a --field map (repeat in\n"
            "                        the order of --field); default: sigma^2 = k^2 / PL, k\n"
            "                        estimated from the map\n"
            "  --keep-doubtful       write a result the doubt checks reject (exit 0), its\n"
            "                        affected pixels with validity 0 and the doubts in\n"
            "                        summary.json; without it such a run exits 3, writing nothing\n"
            "  --plausible-factor K  a corrected |field| above K x the measured map's largest\n"
            "                        |value| at a lit pixel is implausible (default %g)\n"
            "  --precision double|single  the Richardson-Lucy convolutions of rw, r and\n"
            "                        rl-signed in double or single precision (float FFTs:\n"
            "                        1.4-2.4x faster; the field within about 2e-4 of its peak\n"
            "                        of the double one at 75 iterations, docs/cli.md); default\n"
            "                        single for r and rl-signed with one PSF from 1024x1024\n"
            "                        pixels, else double (a map's operator too when given)\n"
            "  --balance L|auto      Wiener-Hunt regularisation lambda, Laplacian regulariser\n"
            "                        (default %g); auto: each Wiener deconvolution (of the PL\n"
            "                        for w, of field x PL for rw and w) picks its own by the\n"
            "                        discrepancy principle (residual = noise)\n"
            "  --noise SIGMA         with --balance auto: the noise standard deviation of the\n"
            "                        deconvolved images (PL, field x PL); default: estimated\n"
            "                        from each image\n",
            d.deconv.iterations, d.plausible_factor, d.deconv.balance);
    cli_print_deconv_help(out, &d.deconv);
    fprintf(out,
            "  --pl-floor F          the recovered PL is floored at F x max(PL) before dividing;\n"
            "                        pixels below it get validity < 1 (default %g)\n"
            "  --shift C             the constant c of the signed shift for r/rl-signed\n"
            "                        (default: automatic, 100 max|Bt| per map)\n"
            "  --side-by-side on|off  on (default): with r / rl-signed, a fixed count and no\n"
            "                        acceleration, the PL's and the fields' Richardson-Lucy run\n"
            "                        side by side, each on a copy of the operator (faster on\n"
            "                        several cores; a copy's memory each, docs/model.md); off:\n"
            "                        in order, one operator's memory\n"
            "  --tail-tol TOL        with r / rl-signed, one PSF or a low-rank or region map:\n"
            "                        the PSF's far tail convolved on a coarser grid when that\n"
            "                        is cheaper and its estimated relative error is at most\n"
            "                        TOL (default %g; 0: never; docs/model.md)\n"
            "  --boundary zero|mirror|periodic  the scene beyond the image edges (default: the\n"
            "                        PSF file's boundary, else zero)\n",
            d.pl_floor, d.tail_tol);
    cli_print_variant_help(out, CORRECT_OPERATOR_TOL);
    cli_print_common_help(run, out);
    fputs("\n"
          "outputs in DIR: pl.EXT (recovered PL), field.EXT (recovered field; field_<stem>.EXT\n"
          "per input when several), validity.EXT (in [0, 1]: 1 where the recovered PL is above\n"
          "the floor, 0 at missing pixels nothing covers), summary.json. No NaN or Inf is ever\n"
          "written.\n"
          "\n"
          "exit status: 0 ok; 1 bad usage or input; 2 runtime failure; 3 the result cannot be\n"
          "vouched for (a solve that did not converge, an automatic choice on the bound of its\n"
          "search, implausible values, a field regularised away): nothing is written and the\n"
          "message says what to change (docs/cli.md).\n",
          out);
}

struct correct_args {
    cli_maps maps;           /* --field, --pl, --psf, --boundary, --nodes, ... */
    cli_deconv_args deconv;  /* --iterations, --balance, --noise, ... */
    svp_correct_options opt; /* the command's own options, then the group's */
    int method;              /* index in method_names */
    int margin_auto;         /* --margin auto: 1, a number: 0, not given: -1 */
    int n_sigma;
    const char *sigma_paths[CLI_MAX_FIELDS]; /* --field-sigma */
};

/* What a run holds (released by correct_release). */
struct correct_job {
    cli_psf psf;
    svp_blur *blur;
    svp_image *field_sigma[CLI_MAX_FIELDS];
    svp_image *pl_true, *validity, *field_true[CLI_MAX_FIELDS];
    svp_correct_summary summary;
    svp_deconv_report reports[CLI_MAX_FIELDS + 1];
    size_t n_missing, n_flagged, n_invalid;
    char bal[1024]; /* the automatic balances, for the line on stdout */
};

static int correct_option(cli_run *run, struct correct_args *a, int c)
{
    svp_correct_options *opt = &a->opt;
    switch (c) {
    case OPT_METHOD: {
        int bad = cli_parse_choice(run, "--method", optarg, method_names, &a->method);
        opt->method = method_values[a->method];
        return bad;
    }
    case OPT_MARGIN:
        a->margin_auto = strcmp(optarg, "auto") == 0;
        return a->margin_auto ? 0 : cli_parse_int(run, "--margin", optarg, 0, 100000, &opt->margin);
    case OPT_GAIN:
        return cli_parse_double_in(run, "--gain", optarg, 0, 0, INFINITY, 0, &opt->pl_gain);
    case OPT_OFFSET: return cli_parse_double(run, "--offset", optarg, &opt->pl_offset);
    case OPT_FIELD_SIGMA:
        if (a->n_sigma >= CLI_MAX_FIELDS)
            return cli_error(run, "--field-sigma: at most %d maps", CLI_MAX_FIELDS);
        a->sigma_paths[a->n_sigma++] = optarg;
        return 0;
    case OPT_PLAUSIBLE:
        return cli_parse_double_in(run, "--plausible-factor", optarg, 1, 0, INFINITY, 0,
                                   &opt->plausible_factor);
    case OPT_PL_FLOOR:
        return cli_parse_double_in(run, "--pl-floor", optarg, 0, 0, 1, 0, &opt->pl_floor);
    case OPT_SHIFT: return cli_parse_double(run, "--shift", optarg, &opt->shift);
    case OPT_SIDE_BY_SIDE:
        return cli_parse_choice(run, "--side-by-side", optarg, on_off, &opt->side_by_side);
    case OPT_TAIL_TOL:
        return cli_parse_double_in(run, "--tail-tol", optarg, 0, 1, 1, 0, &opt->tail_tol);
    default: {
        int bad = cli_deconv_option(run, &a->deconv, c, optarg);
        if (bad < 0) bad = cli_maps_option(run, &a->maps, c, optarg);
        return bad < 0 ? cli_error(run, "internal: option %d", c) : bad;
    }
    }
}

/* The deconvolution group into the library's options; the combinations correct refuses. */
static int correct_check(const cli_run *run, struct correct_args *a)
{
    svp_correct_options *opt = &a->opt;
    const cli_deconv_args *d = &a->deconv;
    const int auto_stop = opt->deconv.auto_stop;
    cli_deconv_apply(d, &opt->deconv);
    opt->deconv.auto_stop = auto_stop; /* --iterations auto is the transform's own */
    opt->auto_iterations = d->iterations_auto;
    opt->balance_auto = d->balance_auto;
    opt->noise_sigma = d->noise;
    opt->keep_doubtful = d->keep_doubtful;
    const int has_wiener = opt->method == SVP_METHOD_RW || opt->method == SVP_METHOD_W;
    if (d->balance_given && !d->balance_auto && !has_wiener)
        return cli_error(run,
                         "--balance is used only by the methods with a Wiener deconvolution "
                         "(--method rw or w), not --method %s",
                         method_names[a->method]);
    if (d->balance_auto && !has_wiener)
        return cli_error(run, "--balance auto needs a method with a Wiener deconvolution "
                              "(--method rw or w)");
    if (d->noise > 0 && !d->balance_auto)
        return cli_error(run, "--noise is only used with --balance auto");
    if ((d->iterations_auto || d->acceleration) && opt->method == SVP_METHOD_W)
        return cli_error(run, "--iterations auto and --acceleration apply to Richardson-Lucy: "
                              "not with --method w");
    if (d->precision == 1 && opt->method == SVP_METHOD_W)
        return cli_error(run, "--precision single applies to Richardson-Lucy: not with --method w");
    return 0;
}

static int parse_correct_args(cli_run *run, struct correct_args *a)
{
    static const struct option own[] = {
        CLI_MAPS_LONGOPTS,
        CLI_DECONV_LONGOPTS,
        {"method", required_argument, NULL, OPT_METHOD},
        {"pl-floor", required_argument, NULL, OPT_PL_FLOOR},
        {"shift", required_argument, NULL, OPT_SHIFT},
        {"margin", required_argument, NULL, OPT_MARGIN},
        {"gain", required_argument, NULL, OPT_GAIN},
        {"offset", required_argument, NULL, OPT_OFFSET},
        {"field-sigma", required_argument, NULL, OPT_FIELD_SIGMA},
        {"plausible-factor", required_argument, NULL, OPT_PLAUSIBLE},
        {"side-by-side", required_argument, NULL, OPT_SIDE_BY_SIDE},
        {"tail-tol", required_argument, NULL, OPT_TAIL_TOL},
        {NULL, 0, NULL, 0},
    };
    memset(a, 0, sizeof *a);
    cli_maps_init(&a->maps);
    a->maps.variant.tolerance = CORRECT_OPERATOR_TOL;
    svp_correct_defaults(&a->opt);
    cli_deconv_init(&a->deconv, &a->opt.deconv);
    while (method_values[a->method] != a->opt.method) a->method++; /* the library's default */
    a->margin_auto = -1;
    int c;
    while ((c = cli_next_option(run, own)) != CLI_OPTIONS_DONE) {
        if (c == CLI_OPTION_HELP) {
            print_help(run, stdout);
            return CLI_OPTION_HELP;
        }
        if (c == CLI_OPTION_ERROR || correct_option(run, a, c)) return CLI_EXIT_USAGE;
    }
    return correct_check(run, a);
}

/* --field-sigma: one map per --field, the PL's size, never negative. */
static int correct_read_sigma(cli_run *run, struct correct_args *a, struct correct_job *job)
{
    const cli_maps *maps = &a->maps;
    const int w = maps->pl->width, h = maps->pl->height, n_sigma = a->n_sigma;
    const size_t n = (size_t)w * h;
    int code;
    if (n_sigma && n_sigma != maps->n_fields)
        return cli_error(run,
                         "--field-sigma: %d map%s for %d --field map%s: give one per field, in "
                         "the same order",
                         n_sigma, n_sigma == 1 ? "" : "s", maps->n_fields,
                         maps->n_fields == 1 ? "" : "s");
    for (int i = 0; i < n_sigma; i++) {
        const char *path = a->sigma_paths[i];
        if ((code = cli_read_image(run, "field_sigma", path, &job->field_sigma[i]))) return code;
        const svp_image *s = job->field_sigma[i];
        if (s->width != w || s->height != h)
            return cli_error(run,
                             "size mismatch: field sigma %s is %d x %d (width x height) but PL %s "
                             "is %d x %d",
                             path, s->width, s->height, maps->pl_path, w, h);
        for (size_t k = 0; k < n; k++)
            if (s->data[k] < 0)
                return cli_error(run, "%s: field sigma is negative (%g) at pixel (%zu, %zu)", path,
                                 s->data[k], k % (size_t)w, k / (size_t)w);
    }
    if (n_sigma) a->opt.field_sigma = (const svp_image *const *)job->field_sigma;
    return cli_check_input_pixels(run, job->psf.pixel_um, maps->psf_path);
}

/* The maps, the PSF and the field sigmas; --margin decided; the settings recorded. */
static int correct_read(cli_run *run, struct correct_args *a, struct correct_job *job)
{
    svp_correct_options *opt = &a->opt;
    cli_maps *maps = &a->maps;
    int code;
    if ((code = cli_maps_open(run, maps, &job->psf))) return code;
    /* default: single-precision transforms for r and rl-signed with one PSF from 1024² pixels —
     * their error is ~10⁻⁴ of the peak, far below a measurement's, and they are 1.3x faster
     * there, while at 256²–512² both take the same time (docs/cli.md, --precision) — else
     * double */
    if (!a->deconv.precision_given && !job->psf.field &&
        (size_t)maps->pl->width * (size_t)maps->pl->height >= SINGLE_FROM_PIXELS &&
        (opt->method == SVP_METHOD_R || opt->method == SVP_METHOD_RL_SIGNED)) {
        a->deconv.precision = 1;
        opt->deconv.single_precision = 1;
    }
    /* a map's operator in single precision keeps only float spectra (half their memory) when
     * RL is its only user; rw's Wiener step (CG) keeps the double ones */
    if (a->deconv.precision == 1 && job->psf.field)
        job->psf.variant.single_precision = opt->method != SVP_METHOD_RW;
    if ((code = correct_read_sigma(run, a, job))) return code;
    const int w = maps->pl->width, h = maps->pl->height;
    /* default: auto for the RL methods with one PSF (measured: docs/accuracy.md), 0 for the
     * Wiener ones and for PSF maps (on maps the margin doubled the time for no gain on the
     * measured data: docs/model.md §9, "Light from outside the view") */
    int margin_auto = a->margin_auto;
    if (margin_auto < 0)
        margin_auto = !job->psf.field &&
                      (opt->method == SVP_METHOD_R || opt->method == SVP_METHOD_RL_SIGNED);
    if ((margin_auto || opt->margin > 0) && maps->boundary != SVP_BOUNDARY_ZERO) {
        if (!margin_auto) return cli_error(run, "--margin needs the zero boundary");
        opt->margin = 0; /* auto: only where it applies */
    } else if (margin_auto) {
        opt->margin = cli_auto_margin(&job->psf, w, h);
    }
    /* the library's margin rule, before the operator for that grid is built; a map is carried
     * onto the margin from its edge (svp_psf_field_pad) */
    svp_status st = svp_correct_check_margin(opt->margin, w, h);
    if (st != SVP_OK) return cli_fail(run, st, maps->pl_path);
    if ((code = cli_psf_pad(run, &job->psf, opt->margin))) return code;
    opt->summary = &job->summary;
    /* the library's messages name the field maps by their files */
    opt->field_names = maps->field_paths;
    opt->pl_name = maps->pl_path;
    cli_setting_str(run, "method", method_names[a->method]);
    if (opt->auto_iterations) cli_setting_str(run, "iterations", "auto");
    cli_setting_int(run, opt->auto_iterations ? "iteration_cap" : "iterations",
                    opt->deconv.iterations);
    cli_setting_str(run, "acceleration", cli_acceleration_names[a->deconv.acceleration]);
    cli_setting_int(run, "margin", opt->margin);
    if (opt->pl_gain > 0) cli_setting_num(run, "gain", opt->pl_gain);
    cli_setting_num(run, "offset", opt->pl_offset);
    cli_setting_num(run, "plausible_factor", opt->plausible_factor);
    cli_setting_int(run, "keep_doubtful", opt->keep_doubtful);
    cli_setting_str(run, "precision", cli_precision_names[a->deconv.precision]);
    if (opt->balance_auto)
        cli_setting_str(run, "balance", "auto (discrepancy principle)");
    else
        cli_setting_num(run, "balance", opt->deconv.balance);
    if (opt->noise_sigma > 0) cli_setting_num(run, "noise_sigma", opt->noise_sigma);
    cli_setting_int(run, "cg_max_steps", opt->deconv.cg_max_steps);
    cli_setting_num(run, "pl_floor", opt->pl_floor);
    cli_setting_num(run, "shift", opt->shift);
    cli_setting_str(run, "side_by_side", on_off[opt->side_by_side]);
    cli_setting_num(run, "tail_tol", opt->tail_tol);
    return 0;
}

/* The operator (on the view plus the margin) and the inverse transform. */
static int correct_compute(cli_run *run, struct correct_args *a, struct correct_job *job)
{
    svp_correct_options *opt = &a->opt;
    const cli_maps *maps = &a->maps;
    const int w = maps->pl->width, h = maps->pl->height;
    int code;
    cli_stage_begin(run, "plan");
    job->psf.variant.applications = cli_correct_applications(opt, maps->n_fields); /* cost model */
    /* a low-rank or region map's far tail on a coarse grid, for the RL methods as one PSF's */
    if (opt->method == SVP_METHOD_R || opt->method == SVP_METHOD_RL_SIGNED)
        job->psf.variant.tail_tol = opt->tail_tol;
    if ((code = cli_psf_blur(run, &job->psf, w + 2 * opt->margin, h + 2 * opt->margin,
                             maps->boundary, &job->blur)))
        return code;

    cli_stage_begin(run, "transform");
    svp_status st = svp_image_new(w, h, &job->pl_true);
    if (st == SVP_OK) st = svp_image_new(w, h, &job->validity);
    for (int i = 0; i < maps->n_fields && st == SVP_OK; i++)
        st = svp_image_new(w, h, &job->field_true[i]);
    opt->reports = job->reports;
    if (st == SVP_OK) {
        opt->deconv.progress = cli_progress;
        opt->deconv.progress_user = run;
        cli_progress_start(run, "correcting");
        st = svp_inverse_transform(job->blur, maps->pl, (const svp_image *const *)maps->fields,
                                   maps->n_fields, opt, job->pl_true, job->field_true,
                                   job->validity, &job->n_missing);
        cli_progress_done(run);
    }
    if (st != SVP_OK) return cli_fail(run, st, NULL);
    const size_t n = (size_t)w * h;
    for (size_t i = 0; i < n; i++) {
        job->n_flagged += job->validity->data[i] < 1;
        job->n_invalid += job->validity->data[i] <= 0;
    }
    cli_result_int(run, "n_missing", (long long)job->n_missing);
    cli_result_int(run, "n_flagged", (long long)job->n_flagged);
    cli_result_num(run, "flagged_fraction", (double)job->n_flagged / (double)n);
    cli_result_int(run, "n_invalid", (long long)job->n_invalid);
    return 0;
}

/* One Wiener deconvolution's automatic balance: results, bound check, the stdout note. */
static void correct_report_balance(cli_run *run, const struct correct_args *a,
                                   struct correct_job *job, int k, const char *name, size_t *at)
{
    const svp_deconv_report *r = &job->reports[k];
    const cli_maps *maps = &a->maps;
    char key[340];
    snprintf(key, sizeof key, "balance_%s", name);
    cli_result_num(run, key, r->balance);
    snprintf(key, sizeof key, "noise_sigma_%s", name);
    cli_result_num(run, key, r->noise_sigma);
    snprintf(key, sizeof key, "noise_per_pixel_%s", name);
    cli_result_int(run, key, r->noise_per_pixel);
    snprintf(key, sizeof key, "balance_rule_%s", name);
    cli_result_str(run, key, r->balance_lcurve ? "lcurve" : "discrepancy");
    char what[600];
    if (k == 0)
        snprintf(what, sizeof what, "the PL %s", maps->pl_path);
    else
        snprintf(what, sizeof what, "field x PL of %s", maps->field_paths[k - 1]);
    const char *bound = cli_balance_bound_check(run, what, r->balance, r->noise_sigma);
    if (bound) {
        snprintf(key, sizeof key, "balance_at_bound_%s", name);
        cli_result_str(run, key, bound);
    }
    if (*at < sizeof job->bal)
        *at +=
            (size_t)snprintf(job->bal + *at, sizeof job->bal - *at, "%s %s %g (%s, %s %g)",
                             *at ? "," : ", automatic balance:", k == 0 ? "PL" : name, r->balance,
                             r->balance_lcurve ? "L-curve corner: the noise level is "
                                                 "out of reach"
                                               : "discrepancy principle",
                             r->noise_per_pixel ? "per-pixel noise of rms sigma" : "noise sigma",
                             r->noise_sigma);
}

/* What each Wiener deconvolution did: [0] the PL's (method W), [1 + c] field c's numerator:
 * the chosen balance and noise, and whether its CG stopped at the step cap. */
static void correct_report_wiener(cli_run *run, const struct correct_args *a,
                                  struct correct_job *job)
{
    const cli_maps *maps = &a->maps;
    size_t at = 0;
    int n_capped = 0;
    for (int k = 0; k <= maps->n_fields; k++) {
        const svp_deconv_report *r = &job->reports[k];
        if (!r->wiener) continue;
        char name[300], key[340];
        if (k == 0)
            snprintf(name, sizeof name, "pl");
        else if (maps->n_fields == 1)
            snprintf(name, sizeof name, "field");
        else {
            char stem[256];
            cli_path_stem(maps->field_paths[k - 1], stem, sizeof stem);
            snprintf(name, sizeof name, "field_%s", stem);
        }
        if (a->opt.balance_auto) correct_report_balance(run, a, job, k, name, &at);
        if (r->cg_steps > 0) {
            snprintf(key, sizeof key, "cg_steps_%s", name);
            cli_result_int(run, key, r->cg_steps);
        }
        if (r->cg_capped) {
            n_capped++;
            snprintf(key, sizeof key, "cg_capped_%s", name);
            cli_result_int(run, key, 1);
            snprintf(key, sizeof key, "cg_residual_%s", name);
            cli_result_num(run, key, r->cg_residual);
            /* above SVP_CG_DOUBT_RESIDUAL the solve is in doubt: exit 3 unless --keep-doubtful
             * (the run only gets here with it); below, close enough to converged to keep */
            const int doubt = r->cg_residual > SVP_CG_DOUBT_RESIDUAL;
            cli_warn(run,
                     "the Wiener deconvolution of %s%s stopped at the step cap (%d conjugate-"
                     "gradient steps) with relative residual %.3g above the tolerance 1e-8: %s",
                     k == 0 ? "the PL" : name, k == 0 ? "" : " x PL", r->cg_steps, r->cg_residual,
                     doubt ? "not converged (kept by --keep-doubtful; its validity is 0)"
                           : "below 1e-4, converged well enough to keep (raise --cg-max-steps "
                             "to reach 1e-8)");
        }
    }
    if (a->opt.balance_auto)
        cli_result_str(run, "noise_sigma_from", a->opt.noise_sigma > 0 ? "--noise" : "estimated");
    cli_result_int(run, "n_cg_capped", n_capped);
}

/* The transform's summary: RL's stop, the shifts, the PL gain, spread and doubts. */
static void correct_report(cli_run *run, const struct correct_args *a, struct correct_job *job)
{
    const svp_correct_options *opt = &a->opt;
    const svp_correct_summary *summary = &job->summary;
    const int n_fields = a->maps.n_fields;
    correct_report_wiener(run, a, job);
    if (opt->method != SVP_METHOD_W) {
        cli_result_int(run, "rl_iterations", summary->rl_iterations);
        cli_result_str(run, "rl_stop", cli_rl_stop_names[summary->rl_stop]);
        if (opt->auto_iterations) cli_result_num(run, "rl_chi2", summary->rl_chi2);
    }
    /* how the deconvolutions ran: side by side on copies of the operator, or in order */
    cli_result_int(run, "side_by_side", summary->side_by_side);
    if (summary->side_by_side_fallback) cli_result_int(run, "side_by_side_fallback", 1);
    /* the PSF's far tail on a coarse grid (--tail-tol), or the plain frame (step 0) */
    cli_result_int(run, "tail_step_px", summary->tail_step);
    if (summary->tail_step > 0) {
        cli_result_int(run, "tail_split_px", summary->tail_split);
        cli_result_num(run, "tail_error", summary->tail_error);
    }
    if (opt->method == SVP_METHOD_R || opt->method == SVP_METHOD_RL_SIGNED)
        for (int k = 0; k < n_fields && k < 16; k++) {
            char key[64];
            snprintf(key, sizeof key, n_fields == 1 ? "shift" : "shift_%d", k);
            cli_result_num(run, key, summary->shift[k]);
        }
    if (summary->pl_gain > 0) {
        cli_result_num(run, "pl_gain", summary->pl_gain);
        cli_result_str(run, "pl_gain_from", opt->pl_gain > 0 ? "--gain" : "estimated");
        if (!(opt->pl_gain > 0))
            cli_result_num(run, "pl_gain_offset_estimate", summary->pl_gain_offset);
    }
    cli_result_num(run, "spread_ratio", summary->spread_ratio);
    cli_result_int(run, "n_implausible", (long long)summary->n_implausible);
    char list[256];
    svp_doubt_list(summary->doubts, list, sizeof list);
    cli_result_str(run, "doubts", list);
    if (summary->doubts)
        cli_warn(run,
                 "result in doubt (%s), kept by --keep-doubtful: the affected pixels have "
                 "validity 0",
                 list);
}

/* The maps and summary.json, then the line on stdout. */
static int correct_write(cli_run *run, const struct correct_args *a, struct correct_job *job)
{
    const svp_correct_options *opt = &a->opt;
    const cli_maps *maps = &a->maps;
    const int w = maps->pl->width, h = maps->pl->height;
    const size_t n = (size_t)w * h;
    int code;
    if ((code = cli_maps_write(run, maps, job->pl_true, job->field_true, job->validity)))
        return code;
    const int has_wiener = opt->method == SVP_METHOD_RW || opt->method == SVP_METHOD_W;
    char iters[96] = "", op[256];
    cli_variant_sentence(job->blur, op, sizeof op);
    if (opt->method != SVP_METHOD_W)
        snprintf(iters, sizeof iters, ", %d RL iterations", opt->deconv.iterations);
    if (has_wiener && !opt->balance_auto)
        snprintf(job->bal, sizeof job->bal, ", balance %g", opt->deconv.balance);
    if (opt->auto_iterations)
        snprintf(iters, sizeof iters, ", %d RL iterations (auto: %s)", job->summary.rl_iterations,
                 cli_rl_stop_names[job->summary.rl_stop]);
    printf("svpsf correct: %d field map%s of %d x %d corrected with %s%s%s. "
           "%zu input pixel%s missing (NaN/Inf in a map or its --field-sigma) and treated "
           "as missing data; "
           "%zu pixels (%.2f %%) are flagged (validity < 1), %zu of them with no "
           "information (validity 0). Time %.2f s (deconvolutions %.2f s).%s "
           "Outputs in %s.\n",
           maps->n_fields, maps->n_fields > 1 ? "s" : "", w, h, method_long_name(opt->method),
           iters, job->bal, job->n_missing, job->n_missing == 1 ? " was" : "s were", job->n_flagged,
           100.0 * (double)job->n_flagged / (double)n, job->n_invalid, cli_now() - run->t_start,
           cli_stage_seconds(run, "transform"), op, run->output);
    return 0;
}

static int run_correct(cli_run *run, struct correct_args *a)
{
    struct correct_job job;
    memset(&job, 0, sizeof job);
    int code = correct_read(run, a, &job);
    if (!code) code = correct_compute(run, a, &job);
    if (!code) {
        correct_report(run, a, &job);
        code = correct_write(run, a, &job);
    }
    svp_blur_free(job.blur);
    svp_image_free(job.pl_true);
    svp_image_free(job.validity);
    for (int i = 0; i < CLI_MAX_FIELDS; i++) {
        svp_image_free(job.field_true[i]);
        svp_image_free(job.field_sigma[i]);
    }
    cli_psf_release(&job.psf);
    return code;
}

int cmd_correct(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "correct", argc, argv, CLI_COMMON_OUTPUT_DIR);
    struct correct_args args;
    int code = parse_correct_args(&run, &args);
    if (code == 0) code = run_correct(&run, &args);
    cli_maps_release(&args.maps);
    return cli_run_finish(&run, cli_parsed_status(code));
}
