/* svpsf correct: the inverse transform T⁻¹ (eq. 4): the true maps from measured ones. */
#include "cli.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

enum {
    OPT_METHOD = CLI_OPTION_FIRST,
    OPT_ITERATIONS,
    OPT_BALANCE,
    OPT_PL_FLOOR,
    OPT_SHIFT,
    OPT_NOISE,
    OPT_CG_MAX_STEPS,
    OPT_PRECISION,
    OPT_ACCELERATION,
    OPT_MARGIN,
    OPT_GAIN,
    OPT_OFFSET,
    OPT_FIELD_SIGMA,
    OPT_KEEP_DOUBTFUL,
    OPT_PLAUSIBLE,
};

static const char *const acceleration_names[] = {"none", "biggs-andrews", NULL};
static const char *const stop_names[] = {"count", "discrepancy", "stalled", "cap"};
static const char *const doubt_names[] = {"cg_not_converged", "balance_at_bound",
                                          "iterations_at_cap", "implausible_values",
                                          "regularised_away"};

/* --margin auto: the PSF's significant reach, the radius where the profile falls to 1 % of its
 * peak along the major axis (Gaussian 1.29 FWHM; Moffat r0 √(100^(1/β) − 1): 4.3 FWHM at β 1.1;
 * a kernel image: its half-width), at most a quarter of the view's larger side. */
static int auto_margin(const cli_psf *psf, int w, int h)
{
    const int cap = (w > h ? w : h) / 4;
    double r = 0;
    if (psf->is_model) {
        const svp_psf *p = &psf->model;
        if (p->model == SVP_PSF_GAUSSIAN) {
            r = p->fwhm / (2 * sqrt(2 * log(2))) * sqrt(2 * log(100.0));
        } else {
            const double beta = p->model == SVP_PSF_LORENTZIAN ? 1.0 : p->beta;
            const double r0 = p->fwhm / (2 * sqrt(expm1(log(2) / beta)));
            r = r0 * sqrt(expm1(log(100.0) / beta));
        }
        if (p->support > 0 && p->support < r) r = p->support;
    } else if (psf->kernel_raw) {
        const int kw = psf->kernel_raw->width, kh = psf->kernel_raw->height;
        r = 0.5 * (kw > kh ? kw : kh);
    }
    int m = (int)ceil(r);
    return m < cap ? m : cap;
}

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
            "                        the numerators run the same count (docs/model.md §6)\n"
            "  --acceleration none|biggs-andrews  Richardson-Lucy vector extrapolation\n"
            "                        (default none); biggs-andrews reaches plain RL's error in\n"
            "                        fewer iterations (docs/accuracy.md)\n"
            "  --margin auto|PX      estimate the object on the view plus PX pixels per side, the\n"
            "                        data term over the view only: light from outside the view\n"
            "                        (zero boundary, one PSF; default auto for r and rl-signed,\n"
            "                        0 for rw and w; auto: where the PSF falls to 1 %% of its\n"
            "                        peak, at most a quarter of the view, 0 where it does not\n"
            "                        apply; --margin 0 turns it off)\n"
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
            "                        rl-signed in double (default) or single precision (float\n"
            "                        FFTs: 1.4-2.4x faster, within about 1e-5 of the peak at\n"
            "                        100 iterations); one PSF only, not a space-variant map\n"
            "  --balance L|auto      Wiener-Hunt regularisation lambda, Laplacian regulariser\n"
            "                        (default %g); auto: each Wiener deconvolution (of the PL\n"
            "                        for w, of field x PL for rw and w) picks its own by the\n"
            "                        discrepancy principle (residual = noise)\n"
            "  --noise SIGMA         with --balance auto: the noise standard deviation of the\n"
            "                        deconvolved images (PL, field x PL); default: estimated\n"
            "                        from each image\n"
            "  --cg-max-steps N      step cap of the zero-boundary Wiener solve (conjugate\n"
            "                        gradients; default %d); a solve that stops there above\n"
            "                        its tolerance is warned about and recorded\n"
            "  --pl-floor F          the recovered PL is floored at F x max(PL) before dividing;\n"
            "                        pixels below it get validity < 1 (default %g)\n"
            "  --shift C             the constant c of the signed shift for r/rl-signed\n"
            "                        (default: automatic, 2 max|Bt| per map)\n"
            "  --boundary zero|mirror|periodic  the scene beyond the image edges (default: the\n"
            "                        PSF file's boundary, else zero)\n",
            d.deconv.iterations, d.plausible_factor, d.deconv.balance, d.deconv.cg_max_steps,
            d.pl_floor);
    cli_print_variant_help(out);
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

int cmd_correct(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "correct", argc, argv, CLI_COMMON_OUTPUT_DIR);
    static const struct option own[] = {
        CLI_MAPS_LONGOPTS,
        {"method", required_argument, NULL, OPT_METHOD},
        {"iterations", required_argument, NULL, OPT_ITERATIONS},
        {"balance", required_argument, NULL, OPT_BALANCE},
        {"pl-floor", required_argument, NULL, OPT_PL_FLOOR},
        {"shift", required_argument, NULL, OPT_SHIFT},
        {"noise", required_argument, NULL, OPT_NOISE},
        {"cg-max-steps", required_argument, NULL, OPT_CG_MAX_STEPS},
        {"precision", required_argument, NULL, OPT_PRECISION},
        {"acceleration", required_argument, NULL, OPT_ACCELERATION},
        {"margin", required_argument, NULL, OPT_MARGIN},
        {"gain", required_argument, NULL, OPT_GAIN},
        {"offset", required_argument, NULL, OPT_OFFSET},
        {"field-sigma", required_argument, NULL, OPT_FIELD_SIGMA},
        {"keep-doubtful", no_argument, NULL, OPT_KEEP_DOUBTFUL},
        {"plausible-factor", required_argument, NULL, OPT_PLAUSIBLE},
        {NULL, 0, NULL, 0},
    };
    cli_maps maps;
    cli_maps_init(&maps);
    cli_psf psf;
    memset(&psf, 0, sizeof psf);
    int method = 0, precision = 0, acceleration = 0, margin_auto = -1, n_sigma = 0;
    int balance_given = 0;
    const char *sigma_paths[CLI_MAX_FIELDS] = {NULL};
    svp_image *field_sigma[CLI_MAX_FIELDS] = {NULL};
    svp_correct_summary summary;
    svp_correct_options opt;
    svp_correct_defaults(&opt);
    while (method_values[method] != opt.method) method++; /* the library's default */
    svp_blur *blur = NULL;
    svp_image *pl_true = NULL, *validity = NULL;
    svp_image *field_true[CLI_MAX_FIELDS] = {NULL};
    int code = 0;
    memset(&summary, 0, sizeof summary);

    int c;
    while ((c = cli_next_option(&run, own)) != CLI_OPTIONS_DONE) {
        int bad = 0;
        switch (c) {
        case CLI_OPTION_HELP: print_help(&run, stdout); return cli_run_finish(&run, 0);
        case CLI_OPTION_ERROR: return cli_run_finish(&run, CLI_EXIT_USAGE);
        case OPT_METHOD:
            bad = cli_parse_choice(&run, "--method", optarg, method_names, &method);
            opt.method = method_values[method];
            break;
        case OPT_ITERATIONS:
            if (strcmp(optarg, "auto") == 0)
                opt.auto_iterations = 1;
            else
                bad = cli_parse_int(&run, "--iterations", optarg, 1, 100000,
                                    &opt.deconv.iterations);
            break;
        case OPT_ACCELERATION:
            bad = cli_parse_choice(&run, "--acceleration", optarg, acceleration_names,
                                   &acceleration);
            opt.deconv.acceleration = (svp_rl_acceleration)acceleration;
            break;
        case OPT_MARGIN:
            margin_auto = strcmp(optarg, "auto") == 0;
            if (!margin_auto)
                bad = cli_parse_int(&run, "--margin", optarg, 0, 100000, &opt.margin);
            break;
        case OPT_GAIN:
            bad = cli_parse_double_in(&run, "--gain", optarg, 0, 0, INFINITY, 0, &opt.pl_gain);
            break;
        case OPT_OFFSET: bad = cli_parse_double(&run, "--offset", optarg, &opt.pl_offset); break;
        case OPT_FIELD_SIGMA:
            if (n_sigma >= CLI_MAX_FIELDS)
                bad = cli_error(&run, "--field-sigma: at most %d maps", CLI_MAX_FIELDS);
            else
                sigma_paths[n_sigma++] = optarg;
            break;
        case OPT_KEEP_DOUBTFUL: opt.keep_doubtful = 1; break;
        case OPT_PLAUSIBLE:
            bad = cli_parse_double_in(&run, "--plausible-factor", optarg, 1, 0, INFINITY, 0,
                                      &opt.plausible_factor);
            break;
        case OPT_BALANCE:
            bad = cli_parse_balance(&run, optarg, &opt.deconv.balance, &opt.balance_auto);
            balance_given = 1;
            break;
        case OPT_NOISE:
            bad = cli_parse_double_in(&run, "--noise", optarg, 0, 0, INFINITY, 0, &opt.noise_sigma);
            break;
        case OPT_CG_MAX_STEPS:
            bad =
                cli_parse_int(&run, "--cg-max-steps", optarg, 1, 100000, &opt.deconv.cg_max_steps);
            break;
        case OPT_PL_FLOOR:
            bad = cli_parse_double_in(&run, "--pl-floor", optarg, 0, 0, 1, 0, &opt.pl_floor);
            break;
        case OPT_SHIFT: bad = cli_parse_double(&run, "--shift", optarg, &opt.shift); break;
        case OPT_PRECISION:
            bad = cli_parse_choice(&run, "--precision", optarg, cli_precision_names, &precision);
            break;
        default:
            bad = cli_maps_option(&run, &maps, c, optarg);
            if (bad < 0) bad = cli_error(&run, "internal: option %d", c);
        }
        if (bad) return cli_run_finish(&run, CLI_EXIT_USAGE);
    }
    const int has_wiener = opt.method == SVP_METHOD_RW || opt.method == SVP_METHOD_W;
    if (balance_given && !opt.balance_auto && !has_wiener)
        return cli_run_finish(&run, cli_error(&run, "--balance is used only by the methods with a "
                                                    "Wiener deconvolution (--method rw or w), "
                                                    "not --method %s", method_names[method]));
    if (opt.balance_auto && !has_wiener)
        return cli_run_finish(&run, cli_error(&run, "--balance auto needs a method with a Wiener "
                                                    "deconvolution (--method rw or w)"));
    if (opt.noise_sigma > 0 && !opt.balance_auto)
        return cli_run_finish(&run, cli_error(&run, "--noise is only used with --balance auto"));
    if ((opt.auto_iterations || acceleration) && opt.method == SVP_METHOD_W)
        return cli_run_finish(&run, cli_error(&run, "--iterations auto and --acceleration apply "
                                                    "to Richardson-Lucy: not with --method w"));
    if (precision == 1 && opt.method == SVP_METHOD_W)
        return cli_run_finish(&run, cli_error(&run, "--precision single applies to Richardson-"
                                                    "Lucy: not with --method w"));
    opt.deconv.single_precision = precision == 1;
    if ((code = cli_maps_open(&run, &maps, &psf))) goto cleanup;
    if (precision == 1 && psf.field) { /* refused before the map's operator is built */
        code = cli_error(&run,
                         "%s: --precision single needs one PSF; this is a space-variant PSF "
                         "map",
                         psf.path);
        goto cleanup;
    }

    const int w = maps.pl->width, h = maps.pl->height;
    const size_t n = (size_t)w * h;
    if (n_sigma && n_sigma != maps.n_fields) {
        code = cli_error(&run, "--field-sigma: %d map%s for %d --field map%s: give one per field, in "
                         "the same order",
                         n_sigma, n_sigma == 1 ? "" : "s", maps.n_fields,
                         maps.n_fields == 1 ? "" : "s");
        goto cleanup;
    }
    for (int i = 0; i < n_sigma; i++) {
        if ((code = cli_read_image(&run, "field_sigma", sigma_paths[i], &field_sigma[i])))
            goto cleanup;
        if (field_sigma[i]->width != w || field_sigma[i]->height != h) {
            code = cli_error(&run,
                             "size mismatch: field sigma %s is %d x %d (width x height) but PL %s "
                             "is %d x %d",
                             sigma_paths[i], field_sigma[i]->width, field_sigma[i]->height,
                             maps.pl_path, w, h);
            goto cleanup;
        }
        for (size_t k = 0; k < n; k++)
            if (field_sigma[i]->data[k] < 0) {
                code = cli_error(&run, "%s: field sigma is negative (%g) at pixel (%zu, %zu)",
                                 sigma_paths[i], field_sigma[i]->data[k], k % (size_t)w,
                                 k / (size_t)w);
                goto cleanup;
            }
    }
    if (n_sigma) opt.field_sigma = (const svp_image *const *)field_sigma;
    /* default: auto for the RL methods (measured: docs/accuracy.md), 0 for the Wiener ones */
    if (margin_auto < 0)
        margin_auto = opt.method == SVP_METHOD_R || opt.method == SVP_METHOD_RL_SIGNED;
    if ((margin_auto || opt.margin > 0) && (psf.field || maps.boundary != SVP_BOUNDARY_ZERO)) {
        if (!margin_auto) {
            code = cli_error(&run, "--margin needs one PSF and the zero boundary%s",
                             psf.field ? " (this is a space-variant PSF map)" : "");
            goto cleanup;
        }
        opt.margin = 0; /* auto: only where it applies */
    } else if (margin_auto) {
        opt.margin = auto_margin(&psf, w, h);
    }
    opt.summary = &summary;
    /* the library's messages name the field maps by their files */
    opt.field_names = maps.field_paths;
    cli_setting_str(&run, "method", method_names[method]);
    if (opt.auto_iterations)
        cli_setting_str(&run, "iterations", "auto");
    cli_setting_int(&run, opt.auto_iterations ? "iteration_cap" : "iterations",
                    opt.deconv.iterations);
    cli_setting_str(&run, "acceleration", acceleration_names[acceleration]);
    cli_setting_int(&run, "margin", opt.margin);
    if (opt.pl_gain > 0) cli_setting_num(&run, "gain", opt.pl_gain);
    cli_setting_num(&run, "offset", opt.pl_offset);
    cli_setting_num(&run, "plausible_factor", opt.plausible_factor);
    cli_setting_int(&run, "keep_doubtful", opt.keep_doubtful);
    cli_setting_str(&run, "precision", cli_precision_names[precision]);
    if (opt.balance_auto)
        cli_setting_str(&run, "balance", "auto (discrepancy principle)");
    else
        cli_setting_num(&run, "balance", opt.deconv.balance);
    if (opt.noise_sigma > 0) cli_setting_num(&run, "noise_sigma", opt.noise_sigma);
    cli_setting_int(&run, "cg_max_steps", opt.deconv.cg_max_steps);
    cli_setting_num(&run, "pl_floor", opt.pl_floor);
    cli_setting_num(&run, "shift", opt.shift);

    cli_stage_begin(&run, "plan");
    psf.variant.applications = cli_correct_applications(&opt, maps.n_fields); /* cost model */
    if ((code = cli_psf_blur(&run, &psf, w + 2 * opt.margin, h + 2 * opt.margin, maps.boundary,
                             &blur)))
        goto cleanup;

    cli_stage_begin(&run, "transform");
    svp_status st = svp_image_new(w, h, &pl_true);
    if (st == SVP_OK) st = svp_image_new(w, h, &validity);
    for (int i = 0; i < maps.n_fields && st == SVP_OK; i++)
        st = svp_image_new(w, h, &field_true[i]);
    size_t n_missing = 0;
    svp_deconv_report reports[CLI_MAX_FIELDS + 1];
    opt.reports = reports;
    if (st == SVP_OK) {
        opt.deconv.progress = cli_progress;
        opt.deconv.progress_user = &run;
        cli_progress_start(&run, "correcting");
        st = svp_inverse_transform(blur, maps.pl, (const svp_image *const *)maps.fields,
                                   maps.n_fields, &opt, pl_true, field_true, validity, &n_missing);
        cli_progress_done(&run);
    }
    if (st != SVP_OK) {
        code = cli_fail(&run, st, NULL);
        goto cleanup;
    }
    size_t n_flagged = 0, n_invalid = 0;
    for (size_t i = 0; i < n; i++) {
        n_flagged += validity->data[i] < 1;
        n_invalid += validity->data[i] <= 0;
    }
    cli_result_int(&run, "n_missing", (long long)n_missing);
    cli_result_int(&run, "n_flagged", (long long)n_flagged);
    cli_result_num(&run, "flagged_fraction", (double)n_flagged / (double)n);
    cli_result_int(&run, "n_invalid", (long long)n_invalid);
    /* What each Wiener deconvolution did: [0] the PL's (method W), [1 + c] field c's numerator:
     * the chosen balance and noise, and whether its CG stopped at the step cap. */
    char bal[1024] = "";
    size_t at = 0;
    int n_capped = 0;
    for (int k = 0; k <= maps.n_fields; k++) {
        const svp_deconv_report *r = &reports[k];
        if (!r->wiener) continue;
        char name[300], key[340];
        if (k == 0)
            snprintf(name, sizeof name, "pl");
        else if (maps.n_fields == 1)
            snprintf(name, sizeof name, "field");
        else {
            char stem[256];
            cli_path_stem(maps.field_paths[k - 1], stem, sizeof stem);
            snprintf(name, sizeof name, "field_%s", stem);
        }
        if (opt.balance_auto) {
            snprintf(key, sizeof key, "balance_%s", name);
            cli_result_num(&run, key, r->balance);
            snprintf(key, sizeof key, "noise_sigma_%s", name);
            cli_result_num(&run, key, r->noise_sigma);
            snprintf(key, sizeof key, "balance_rule_%s", name);
            cli_result_str(&run, key, r->balance_lcurve ? "lcurve" : "discrepancy");
            char what[600];
            if (k == 0)
                snprintf(what, sizeof what, "the PL %s", maps.pl_path);
            else
                snprintf(what, sizeof what, "field x PL of %s", maps.field_paths[k - 1]);
            const char *bound = cli_balance_bound_check(&run, what, r->balance, r->noise_sigma);
            if (bound) {
                snprintf(key, sizeof key, "balance_at_bound_%s", name);
                cli_result_str(&run, key, bound);
            }
            if (at < sizeof bal)
                at += (size_t)snprintf(bal + at, sizeof bal - at, "%s %s %g (%s, noise sigma %g)",
                                       at ? "," : ", automatic balance:", k == 0 ? "PL" : name,
                                       r->balance,
                                       r->balance_lcurve ? "L-curve corner: the noise level is "
                                                           "out of reach"
                                                         : "discrepancy principle",
                                       r->noise_sigma);
        }
        if (r->cg_steps > 0) {
            snprintf(key, sizeof key, "cg_steps_%s", name);
            cli_result_int(&run, key, r->cg_steps);
        }
        if (r->cg_capped) {
            n_capped++;
            snprintf(key, sizeof key, "cg_capped_%s", name);
            cli_result_int(&run, key, 1);
            snprintf(key, sizeof key, "cg_residual_%s", name);
            cli_result_num(&run, key, r->cg_residual);
            cli_warn(&run,
                     "the Wiener deconvolution of %s%s stopped at the step cap (%d conjugate-"
                     "gradient steps) with relative residual %.3g above the tolerance 1e-8: "
                     "not converged (kept by --keep-doubtful; its validity is 0)",
                     k == 0 ? "the PL" : name, k == 0 ? "" : " x PL", r->cg_steps, r->cg_residual);
        }
    }
    if (opt.balance_auto)
        cli_result_str(&run, "noise_sigma_from", opt.noise_sigma > 0 ? "--noise" : "estimated");
    cli_result_int(&run, "n_cg_capped", n_capped);
    if (opt.method != SVP_METHOD_W) {
        cli_result_int(&run, "rl_iterations", summary.rl_iterations);
        cli_result_str(&run, "rl_stop", stop_names[summary.rl_stop]);
        if (opt.auto_iterations) cli_result_num(&run, "rl_chi2", summary.rl_chi2);
    }
    if (opt.method == SVP_METHOD_R || opt.method == SVP_METHOD_RL_SIGNED)
        for (int k = 0; k < maps.n_fields && k < 16; k++) {
            char key[64];
            snprintf(key, sizeof key, maps.n_fields == 1 ? "shift" : "shift_%d", k);
            cli_result_num(&run, key, summary.shift[k]);
        }
    if (summary.pl_gain > 0) {
        cli_result_num(&run, "pl_gain", summary.pl_gain);
        cli_result_str(&run, "pl_gain_from", opt.pl_gain > 0 ? "--gain" : "estimated");
        if (!(opt.pl_gain > 0))
            cli_result_num(&run, "pl_gain_offset_estimate", summary.pl_gain_offset);
    }
    cli_result_num(&run, "spread_ratio", summary.spread_ratio);
    cli_result_int(&run, "n_implausible", (long long)summary.n_implausible);
    {
        char list[256] = "";
        size_t at_l = 0;
        for (int b = 0; b < 5; b++)
            if (summary.doubts & (1u << b) && at_l < sizeof list)
                at_l += (size_t)snprintf(list + at_l, sizeof list - at_l, "%s%s", at_l ? "," : "",
                                         doubt_names[b]);
        cli_result_str(&run, "doubts", list);
        if (summary.doubts)
            cli_warn(&run,
                     "result in doubt (%s), kept by --keep-doubtful: the affected pixels have "
                     "validity 0",
                     list);
    }

    if ((code = cli_maps_write(&run, &maps, pl_true, field_true, validity))) goto cleanup;

    {
        char iters[96] = "", op[256];
        cli_variant_sentence(blur, op, sizeof op);
        if (opt.method != SVP_METHOD_W)
            snprintf(iters, sizeof iters, ", %d RL iterations", opt.deconv.iterations);
        if (has_wiener && !opt.balance_auto)
            snprintf(bal, sizeof bal, ", balance %g", opt.deconv.balance);
        if (opt.auto_iterations)
            snprintf(iters, sizeof iters, ", %d RL iterations (auto: %s)", summary.rl_iterations,
                     stop_names[summary.rl_stop]);
        printf("svpsf correct: %d field map%s of %d x %d corrected with %s%s%s. "
               "%zu input pixel%s were missing (NaN/Inf) and treated as missing data; "
               "%zu pixels (%.2f %%) are flagged (validity < 1), %zu of them with no "
               "information (validity 0). Time %.2f s (deconvolutions %.2f s).%s "
               "Outputs in %s.\n",
               maps.n_fields, maps.n_fields > 1 ? "s" : "", w, h, method_long_name(opt.method),
               iters, bal, n_missing, n_missing == 1 ? "" : "s", n_flagged,
               100.0 * (double)n_flagged / (double)n, n_invalid, cli_now() - run.t_start,
               cli_stage_seconds(&run, "transform"), op, run.output);
    }

cleanup:
    svp_blur_free(blur);
    svp_image_free(pl_true);
    svp_image_free(validity);
    for (int i = 0; i < CLI_MAX_FIELDS; i++) {
        svp_image_free(field_true[i]);
        svp_image_free(field_sigma[i]);
    }
    cli_maps_release(&maps);
    cli_psf_release(&psf);
    return cli_run_finish(&run, code);
}
