/* svpsf deconvolve: one image ⊘ one PSF (Wiener–Hunt or Richardson–Lucy), optionally with
 * scikit-image 0.19's exact conventions. */
#include "cli.h"

#include <limits.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

enum {
    OPT_PSF = CLI_OPTION_FIRST,
    OPT_METHOD,
    OPT_ITERATIONS,
    OPT_BALANCE,
    OPT_NOISE,
    OPT_BOUNDARY,
    OPT_COMPAT,
    OPT_CG_MAX_STEPS,
    OPT_PRECISION,
    OPT_ACCELERATION,
    OPT_KEEP_DOUBTFUL,
};

static const char *const acceleration_names[] = {"none", "biggs-andrews", NULL};
static const char *const stop_names[] = {"count", "discrepancy", "stalled", "cap"};

static void print_help(const cli_run *run, FILE *out)
{
    svp_deconv_options d;
    svp_deconv_defaults(&d);
    fputs("usage: svpsf deconvolve IN --psf PSF -o OUT --method wiener|rl [options]\n"
          "\n"
          "Deconvolves one image IN by the PSF and writes OUT (its extension .tif, .npy or .txt\n"
          "picks the format; without one, --format does and the extension is added).\n"
          "NaN/Inf pixels of IN are missing data. A run summary OUT_STEM.summary.json is\n"
          "written next to OUT.\n"
          "\n"
          "  IN                    the image (TIFF float32/16-bit, 16-bit PNG, .npy, .txt)\n"
          "  --psf FILE            a YAML PSF file (docs/cli.md) or a kernel image (.npy, .tif,\n"
          "                        .txt; normalised to unit sum, centre at the middle pixel;\n"
          "                        with --compat skimage used as given)\n"
          "  -o, --output OUT      the output file (required)\n"
          "  --method wiener|rl    Wiener-Hunt (Laplacian regulariser) or Richardson-Lucy\n"
          "                        (required)\n",
          out);
    fprintf(out,
            "  --balance L|auto      Wiener-Hunt regularisation lambda (default %g); auto:\n"
            "                        chosen by the discrepancy principle (the lambda whose\n"
            "                        residual |H x - IN|^2 is what the noise explains, n sigma^2)\n"
            "  --noise SIGMA         with --balance auto or --iterations auto: the noise's\n"
            "                        standard deviation in IN's units (default: estimated)\n"
            "  --iterations N|auto   Richardson-Lucy iterations (default %d); auto: that many\n"
            "                        at most, stopping when the residual reaches the noise\n"
            "                        (chi2 per pixel 1) or stops falling (docs/model.md §6)\n"
            "  --acceleration none|biggs-andrews  Richardson-Lucy vector extrapolation\n"
            "                        (default none)\n"
            "  --keep-doubtful       write a result in doubt (an automatic choice on its\n"
            "                        bound, a CG solve not converged), exit 0, recorded in the\n"
            "                        summary; without it such a run exits 3, writing nothing\n"
            "  --precision double|single  Richardson-Lucy's convolutions in double (default)\n"
            "                        or single precision (float FFTs: 1.4-2.4x faster, the\n"
            "                        result within about 1e-5 of the peak at 100 iterations)\n"
            "  --cg-max-steps N      step cap of the zero-boundary Wiener solve (conjugate\n"
            "                        gradients; default %d); a solve that stops there above\n"
            "                        its tolerance is warned about and recorded\n"
            "  --boundary zero|mirror|periodic  the scene beyond the image edges (default: the\n"
            "                        PSF file's boundary, else zero; not with --compat)\n"
            "  --compat skimage      reproduce scikit-image 0.19: restoration.wiener(IN, psf,\n"
            "                        balance) (circular, clipped to [-1, 1]) or\n"
            "                        restoration.richardson_lucy(IN, psf, num_iter) (start 0.5,\n"
            "                        zero-padded 'same', clipped to [-1, 1]); a kernel image is\n"
            "                        used as given, a YAML PSF is rendered at the image size\n"
            "                        (default: off, the library's own methods: Richardson-Lucy\n"
            "                        started at the data mean with a floored denominator and\n"
            "                        boundary weights)\n",
            d.balance, d.iterations, d.cg_max_steps);
    cli_print_common_help(run, out);
}

/* The summary's name: OUT without its extension + ".summary.json". */
static void summary_path(const char *out, char *buf, size_t size)
{
    const char *slash = strrchr(out, '/');
    const char *dot = strrchr(out, '.');
    size_t n = dot && (!slash || dot > slash + 1) ? (size_t)(dot - out) : strlen(out);
    snprintf(buf, size, "%.*s.summary.json", (int)n, out);
}

int cmd_deconvolve(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "deconvolve", argc, argv, CLI_COMMON_OUTPUT_DIR);
    static const struct option own[] = {
        {"psf", required_argument, NULL, OPT_PSF},
        {"method", required_argument, NULL, OPT_METHOD},
        {"iterations", required_argument, NULL, OPT_ITERATIONS},
        {"balance", required_argument, NULL, OPT_BALANCE},
        {"noise", required_argument, NULL, OPT_NOISE},
        {"cg-max-steps", required_argument, NULL, OPT_CG_MAX_STEPS},
        {"boundary", required_argument, NULL, OPT_BOUNDARY},
        {"compat", required_argument, NULL, OPT_COMPAT},
        {"precision", required_argument, NULL, OPT_PRECISION},
        {"acceleration", required_argument, NULL, OPT_ACCELERATION},
        {"keep-doubtful", no_argument, NULL, OPT_KEEP_DOUBTFUL},
        {NULL, 0, NULL, 0},
    };
    static const char *const methods[] = {"wiener", "rl", NULL};
    static const char *const compats[] = {"skimage", NULL};
    int precision = 0;
    cli_psf psf;
    memset(&psf, 0, sizeof psf);
    const char *psf_path = NULL;
    int method = -1, compat = -1, boundary_given = 0, balance_auto = 0, acceleration = 0;
    int balance_given = 0;
    int keep_doubtful = 0;
    char doubt[600] = "";
    svp_deconv_report report;
    memset(&report, 0, sizeof report);
    double noise = 0; /* 0: estimated */
    svp_boundary boundary = SVP_BOUNDARY_ZERO;
    svp_deconv_options opt;
    svp_deconv_defaults(&opt);
    svp_image *in = NULL, *out = NULL, *kernel = NULL;
    svp_blur *blur = NULL;
    char out_path[PATH_MAX], sum_path[PATH_MAX + 16];
    int code = 0;

    int c;
    while ((c = cli_next_option(&run, own)) != CLI_OPTIONS_DONE) {
        int bad = 0;
        switch (c) {
        case CLI_OPTION_HELP: print_help(&run, stdout); return cli_run_finish(&run, 0);
        case CLI_OPTION_ERROR: return cli_run_finish(&run, CLI_EXIT_USAGE);
        case OPT_PSF: psf_path = optarg; break;
        case OPT_METHOD: bad = cli_parse_choice(&run, "--method", optarg, methods, &method); break;
        case OPT_COMPAT: bad = cli_parse_choice(&run, "--compat", optarg, compats, &compat); break;
        case OPT_PRECISION:
            bad = cli_parse_choice(&run, "--precision", optarg, cli_precision_names, &precision);
            break;
        case OPT_ITERATIONS:
            if (strcmp(optarg, "auto") == 0)
                opt.auto_stop = 1;
            else
                bad = cli_parse_int(&run, "--iterations", optarg, 1, 100000, &opt.iterations);
            break;
        case OPT_ACCELERATION:
            bad = cli_parse_choice(&run, "--acceleration", optarg, acceleration_names,
                                   &acceleration);
            opt.acceleration = (svp_rl_acceleration)acceleration;
            break;
        case OPT_KEEP_DOUBTFUL: keep_doubtful = 1; break;
        case OPT_BALANCE:
            bad = cli_parse_balance(&run, optarg, &opt.balance, &balance_auto);
            balance_given = 1;
            break;
        case OPT_CG_MAX_STEPS:
            bad = cli_parse_int(&run, "--cg-max-steps", optarg, 1, 100000, &opt.cg_max_steps);
            break;
        case OPT_NOISE:
            bad = cli_parse_double_in(&run, "--noise", optarg, 0, 0, INFINITY, 0, &noise);
            break;
        case OPT_BOUNDARY:
            bad = cli_parse_boundary(&run, "--boundary", optarg, &boundary);
            boundary_given = 1;
            break;
        default: bad = cli_error(&run, "internal: option %d", c);
        }
        if (bad) return cli_run_finish(&run, CLI_EXIT_USAGE);
    }
    if (optind >= argc)
        return cli_run_finish(&run, cli_error(&run, "the input image IN is required (see "
                                                    "--help)"));
    if (optind + 1 < argc)
        return cli_run_finish(&run, cli_error(&run,
                                              "unexpected argument '%s': one input "
                                              "image per run",
                                              argv[optind + 1]));
    const char *in_path = argv[optind];
    if (!psf_path) return cli_run_finish(&run, cli_error(&run, "--psf is required"));
    if (!run.output) return cli_run_finish(&run, cli_error(&run, "-o OUT is required"));
    if (method < 0) return cli_run_finish(&run, cli_error(&run, "--method wiener|rl is required"));
    if (balance_given && !balance_auto && method == 1)
        return cli_run_finish(&run, cli_error(&run, "--balance is used only by --method wiener, "
                                                    "not --method rl"));
    if (balance_auto && (method != 0 || compat >= 0))
        return cli_run_finish(&run, cli_error(&run, "--balance auto needs --method wiener "
                                                    "without --compat"));
    if ((opt.auto_stop || acceleration) && (method != 1 || compat >= 0))
        return cli_run_finish(&run, cli_error(&run, "--iterations auto and --acceleration are for "
                                                    "--method rl without --compat"));
    if (noise > 0 && !balance_auto && !opt.auto_stop)
        return cli_run_finish(&run, cli_error(&run, "--noise is only used with --balance "
                                                    "auto or --iterations auto"));
    if (precision == 1 && (method != 1 || compat >= 0))
        return cli_run_finish(&run, cli_error(&run, "--precision single is for --method rl "
                                                    "without --compat"));
    opt.single_precision = precision == 1;
    if (compat >= 0 && boundary_given)
        return cli_run_finish(&run, cli_error(&run, "--boundary cannot be used with --compat "
                                                    "skimage (it fixes the boundary handling)"));

    /* OUT's extension picks the format; --format must agree or supply one. */
    svp_file_format ext_format = cli_format_of_path(run.output);
    if (ext_format == SVP_FORMAT_PNG16)
        return cli_run_finish(&run, cli_error(&run,
                                              "%s: PNG output would lose the values; "
                                              "use .tif, .npy, .txt or .mat",
                                              run.output));
    if (ext_format == SVP_FORMAT_AUTO)
        snprintf(out_path, sizeof out_path, "%s.%s", run.output, cli_format_extension(run.format));
    else if (run.format_given && ext_format != run.format)
        return cli_run_finish(&run, cli_error(&run,
                                              "-o %s: the extension contradicts --format "
                                              "%s",
                                              run.output, cli_format_extension(run.format)));
    else
        snprintf(out_path, sizeof out_path, "%s", run.output);
    summary_path(out_path, sum_path, sizeof sum_path);

    cli_stage_begin(&run, "read");
    if ((code = cli_psf_load(&run, psf_path, &psf))) goto cleanup;
    if ((code = cli_read_image(&run, "image", in_path, &in))) goto cleanup;
    if (!boundary_given && psf.has_boundary) boundary = psf.boundary;
    cli_output_file(&run, "image", out_path);
    cli_output_file(&run, "summary", sum_path);
    if ((code = cli_outputs_check(&run))) goto cleanup;

    const int w = in->width, h = in->height;
    cli_psf_describe(&run, &psf);
    cli_setting_str(&run, "method", methods[method]);
    if (method == 0 && balance_auto)
        cli_setting_str(&run, "balance", "auto (discrepancy principle)");
    else if (method == 0)
        cli_setting_num(&run, "balance", opt.balance);
    else {
        if (opt.auto_stop) cli_setting_str(&run, "iterations", "auto");
        cli_setting_int(&run, opt.auto_stop ? "iteration_cap" : "iterations", opt.iterations);
        cli_setting_str(&run, "acceleration", acceleration_names[acceleration]);
    }
    if (method == 1 && compat < 0)
        cli_setting_str(&run, "precision", cli_precision_names[precision]);
    cli_setting_str(&run, "compat", compat >= 0 ? compats[compat] : "none");
    if (compat < 0) cli_setting_str(&run, "boundary", cli_boundary_name(boundary));
    long long n_missing = (long long)svp_image_count_nonfinite(in);
    cli_result_int(&run, "n_missing", n_missing);

    svp_status st = svp_image_new(w, h, &out);
    if (st != SVP_OK) {
        code = cli_fail(&run, st, NULL);
        goto cleanup;
    }
    cli_progress_start(&run, method == 0 ? "Wiener-Hunt" : "Richardson-Lucy");
    if (compat >= 0) {
        /* scikit-image takes the kernel as it is given; a model is rendered as large as the
         * image allows (its shape must not exceed the image's). */
        const svp_image *k = psf.kernel_raw;
        if (!psf.is_model && (k->width > w || k->height > h)) {
            code = cli_error(&run,
                             "%s: the %d x %d kernel is larger than the %d x %d image %s "
                             "(scikit-image needs a PSF no larger than the image)",
                             psf.path, k->width, k->height, w, h, in_path);
            goto cleanup;
        }
        if (psf.is_model) {
            int rx = (w - 1) / 2, ry = (h - 1) / 2;
            if (psf.model.support > 0) {
                int rs = (int)ceil(psf.model.support);
                if (rs < rx) rx = rs;
                if (rs < ry) ry = rs;
            }
            cli_stage_begin(&run, "plan");
            st = svp_psf_render(&psf.model, rx, ry, &kernel);
            if (st != SVP_OK) {
                code = cli_fail(&run, st, psf.path);
                goto cleanup;
            }
            k = kernel;
            if (psf.model.halo > 0)
                cli_note(&run,
                         "%s: the halo (%g) is not part of a scikit-image kernel; it is "
                         "ignored with --compat skimage",
                         psf.path, psf.model.halo);
        }
        cli_stage_begin(&run, "deconvolve");
        if (method == 0)
            st = svp_skimage_wiener(in, k, opt.balance, out);
        else
            st = svp_skimage_richardson_lucy(in, k, opt.iterations, cli_progress, &run, out);
    } else {
        cli_stage_begin(&run, "plan");
        if ((code = cli_psf_blur(&run, &psf, w, h, boundary, &blur))) goto cleanup;
        if (balance_auto) {
            cli_stage_begin(&run, "balance");
            double sigma_used = 0;
            st = svp_wiener_balance_discrepancy(blur, in, noise, &opt.balance, &sigma_used);
            if (st != SVP_OK) {
                code = cli_fail(&run, st, in_path);
                goto cleanup;
            }
            cli_result_num(&run, "noise_sigma", sigma_used);
            cli_result_str(&run, "noise_sigma_from", noise > 0 ? "--noise" : "estimated");
            cli_result_num(&run, "balance", opt.balance);
            const char *bound = cli_balance_bound_check(&run, in_path, opt.balance, sigma_used);
            if (bound) {
                cli_result_str(&run, "balance_at_bound", bound);
                snprintf(doubt, sizeof doubt,
                         "--balance auto ended on the %s end of its search (%g): the noise sigma "
                         "%g %s; give --balance or --noise",
                         bound, opt.balance, sigma_used,
                         bound[0] == 'l' ? "is below what any balance leaves (noiseless data?)"
                                         : "explains the data at every balance (the signal "
                                           "would be smoothed away)");
            }
        }
        svp_image *var = NULL;
        if (opt.auto_stop && noise > 0) { /* the given σ as the stopping rule's variance */
            if ((st = svp_image_new(w, h, &var)) != SVP_OK) {
                code = cli_fail(&run, st, NULL);
                goto cleanup;
            }
            for (size_t i = 0; i < (size_t)w * h; i++) var->data[i] = noise * noise;
            opt.variance = var;
        }
        cli_stage_begin(&run, "deconvolve");
        opt.progress = cli_progress;
        opt.progress_user = &run;
        opt.report = &report;
        if (method == 0)
            st = svp_deconv_wiener(blur, in, &opt, out);
        else
            st = svp_deconv_rl(blur, in, &opt, out);
        svp_image_free(var);
        opt.variance = NULL;
        if (st == SVP_OK && method == 1) {
            cli_result_int(&run, "rl_iterations", report.iterations);
            cli_result_str(&run, "rl_stop", stop_names[report.stop]);
            if (opt.auto_stop) cli_result_num(&run, "rl_chi2", report.chi2);
            if (report.stop == SVP_RL_STOP_CAP && !doubt[0])
                snprintf(doubt, sizeof doubt,
                         "--iterations auto: the stopping rule was not met within the cap of %d "
                         "iterations (chi2 per pixel %.3g, still falling); raise --iterations "
                         "(the cap) or use --acceleration biggs-andrews",
                         report.iterations, report.chi2);
        }
        if (st == SVP_OK && method == 0) {
            if (report.cg_steps > 0) cli_result_int(&run, "cg_steps", report.cg_steps);
            cli_result_int(&run, "cg_capped", report.cg_capped);
            if (report.cg_capped) {
                cli_result_num(&run, "cg_residual", report.cg_residual);
                cli_warn(&run,
                         "the Wiener deconvolution of %s stopped at the step cap (%d conjugate-"
                         "gradient steps) with relative residual %.3g above the tolerance 1e-8",
                         in_path, report.cg_steps, report.cg_residual);
                if (report.cg_residual > 1e-4 && !doubt[0])
                    snprintf(doubt, sizeof doubt,
                             "the Wiener solve did not converge (relative residual %.3g after %d "
                             "steps); raise --cg-max-steps or --balance",
                             report.cg_residual, report.cg_steps);
            }
        }
    }
    cli_progress_done(&run);
    if (st != SVP_OK) {
        code = cli_fail(&run, st, in_path);
        goto cleanup;
    }

    cli_result_str(&run, "doubt", doubt);
    if (doubt[0]) {
        if (!keep_doubtful) {
            cli_error(&run, "%s: result in doubt: %s (--keep-doubtful writes it anyway)", in_path,
                      doubt);
            code = CLI_EXIT_DOUBTFUL;
            goto cleanup;
        }
        cli_warn(&run, "%s: result in doubt, kept by --keep-doubtful: %s", in_path, doubt);
    }
    cli_stage_begin(&run, "write");
    if ((code = cli_write_image(&run, out_path, out))) goto cleanup;
    cli_stage_end(&run);
    if ((code = cli_summary_write(&run, sum_path))) goto cleanup;
    if (method == 0)
        printf("svpsf deconvolve: %s (%d x %d) deconvolved with Wiener-Hunt, balance %g%s%s "
               "-> %s in %.2f s",
               in_path, w, h, opt.balance, balance_auto ? " (discrepancy principle)" : "",
               compat >= 0 ? " (scikit-image compatible)" : "", out_path, cli_now() - run.t_start);
    else
        printf("svpsf deconvolve: %s (%d x %d) deconvolved with %d Richardson-Lucy "
               "iterations%s -> %s in %.2f s",
               in_path, w, h, opt.report ? report.iterations : opt.iterations, compat >= 0 ? " (scikit-image compatible)" : "",
               out_path, cli_now() - run.t_start);
    if (n_missing) printf("; %lld missing (NaN/Inf) input pixels", n_missing);
    printf("\n");

cleanup:
    svp_blur_free(blur);
    svp_image_free(in);
    svp_image_free(out);
    svp_image_free(kernel);
    cli_psf_release(&psf);
    return cli_run_finish(&run, code);
}
