/* svpsf deconvolve: one image ⊘ one PSF (Wiener–Hunt or Richardson–Lucy), optionally with
 * scikit-image 0.19's exact conventions. */
#include "cli.h"

#include <limits.h>
#include <math.h>
#include <stdlib.h>
#include <string.h>

enum { OPT_PSF = CLI_OPTION_FIRST, OPT_METHOD, OPT_BOUNDARY, OPT_COMPAT };

static const char *const method_names[] = {"wiener", "rl", NULL};
static const char *const compat_names[] = {"skimage", NULL};

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
            "                        result within about 1e-5 of the peak at 100 iterations)\n",
            d.balance, d.iterations);
    cli_print_deconv_help(out, &d);
    fputs("  --boundary zero|mirror|periodic  the scene beyond the image edges (default: the\n"
          "                        PSF file's boundary, else zero; not with --compat)\n"
          "  --compat skimage      reproduce scikit-image 0.19: restoration.wiener(IN, psf,\n"
          "                        balance) (circular, clipped to [-1, 1]) or\n"
          "                        restoration.richardson_lucy(IN, psf, num_iter) (start 0.5,\n"
          "                        zero-padded 'same', clipped to [-1, 1]); a kernel image is\n"
          "                        used as given, a YAML PSF is rendered at the image size\n"
          "                        (default: off, the library's own methods: Richardson-Lucy\n"
          "                        started at the data mean with a floored denominator and\n"
          "                        boundary weights)\n",
          out);
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

struct deconvolve_args {
    const char *in_path, *psf_path;
    int method; /* index in method_names */
    int compat; /* index in compat_names, -1 off */
    svp_boundary boundary;
    int boundary_given;
    cli_deconv_args deconv;
    char out_path[PATH_MAX], sum_path[PATH_MAX + 16];
};

/* What a run holds (released by deconvolve_release). */
struct deconvolve_job {
    cli_psf psf;
    svp_image *in, *out, *kernel;
    svp_blur *blur;
    svp_boundary boundary;
    svp_deconv_options opt;
    svp_deconv_report report;
    char doubt[600];
    long long n_missing;
};

static int deconvolve_option(cli_run *run, struct deconvolve_args *a, int c)
{
    switch (c) {
    case OPT_PSF: a->psf_path = optarg; return 0;
    case OPT_METHOD: return cli_parse_choice(run, "--method", optarg, method_names, &a->method);
    case OPT_COMPAT: return cli_parse_choice(run, "--compat", optarg, compat_names, &a->compat);
    case OPT_BOUNDARY:
        a->boundary_given = 1;
        return cli_parse_boundary(run, "--boundary", optarg, &a->boundary);
    default: {
        int bad = cli_deconv_option(run, &a->deconv, c, optarg);
        return bad < 0 ? cli_error(run, "internal: option %d", c) : bad;
    }
    }
}

/* The combinations deconvolve refuses, in the order they are checked. */
static int deconvolve_check(const cli_run *run, const struct deconvolve_args *a)
{
    const cli_deconv_args *d = &a->deconv;
    if (!a->psf_path) return cli_error(run, "--psf is required");
    if (!run->output) return cli_error(run, "-o OUT is required");
    if (a->method < 0) return cli_error(run, "--method wiener|rl is required");
    if (d->balance_given && !d->balance_auto && a->method == 1)
        return cli_error(run, "--balance is used only by --method wiener, not --method rl");
    if (d->balance_auto && (a->method != 0 || a->compat >= 0))
        return cli_error(run, "--balance auto needs --method wiener without --compat");
    if ((d->iterations_auto || d->acceleration) && (a->method != 1 || a->compat >= 0))
        return cli_error(run, "--iterations auto and --acceleration are for --method rl without "
                              "--compat");
    if (d->noise > 0 && !d->balance_auto && !d->iterations_auto)
        return cli_error(run, "--noise is only used with --balance auto or --iterations auto");
    if (d->precision == 1 && (a->method != 1 || a->compat >= 0))
        return cli_error(run, "--precision single is for --method rl without --compat");
    if (a->compat >= 0 && a->boundary_given)
        return cli_error(run, "--boundary cannot be used with --compat skimage (it fixes the "
                              "boundary handling)");
    return 0;
}

/* OUT's extension picks the format; --format must agree or supply one. */
static int deconvolve_out_paths(const cli_run *run, struct deconvolve_args *a)
{
    svp_file_format ext_format = cli_format_of_path(run->output);
    if (ext_format == SVP_FORMAT_PNG16)
        return cli_error(run, "%s: PNG output would lose the values; use .tif, .npy, .txt or .mat",
                         run->output);
    if (ext_format == SVP_FORMAT_AUTO)
        snprintf(a->out_path, sizeof a->out_path, "%s.%s", run->output,
                 cli_format_extension(run->format));
    else if (run->format_given && ext_format != run->format)
        return cli_error(run, "-o %s: the extension contradicts --format %s", run->output,
                         cli_format_extension(run->format));
    else
        snprintf(a->out_path, sizeof a->out_path, "%s", run->output);
    summary_path(a->out_path, a->sum_path, sizeof a->sum_path);
    return 0;
}

static int parse_deconvolve_args(cli_run *run, struct deconvolve_args *a)
{
    static const struct option own[] = {
        {"psf", required_argument, NULL, OPT_PSF},
        {"method", required_argument, NULL, OPT_METHOD},
        {"boundary", required_argument, NULL, OPT_BOUNDARY},
        {"compat", required_argument, NULL, OPT_COMPAT},
        CLI_DECONV_LONGOPTS,
        {NULL, 0, NULL, 0},
    };
    memset(a, 0, sizeof *a);
    a->method = a->compat = -1;
    a->boundary = SVP_BOUNDARY_ZERO;
    svp_deconv_options d;
    svp_deconv_defaults(&d);
    cli_deconv_init(&a->deconv, &d);
    int c;
    while ((c = cli_next_option(run, own)) != CLI_OPTIONS_DONE) {
        if (c == CLI_OPTION_HELP) {
            print_help(run, stdout);
            return CLI_OPTION_HELP;
        }
        if (c == CLI_OPTION_ERROR || deconvolve_option(run, a, c)) return CLI_EXIT_USAGE;
    }
    a->in_path = cli_one_argument(run, "the input image IN is required (see --help)",
                                  ": one input image per run");
    if (!a->in_path) return CLI_EXIT_USAGE;
    int code = deconvolve_check(run, a);
    return code ? code : deconvolve_out_paths(run, a);
}

/* Reads the PSF and the image, plans and checks the outputs, records the settings. */
static int deconvolve_read(cli_run *run, const struct deconvolve_args *a,
                           struct deconvolve_job *job)
{
    const cli_deconv_args *d = &a->deconv;
    int code;
    cli_stage_begin(run, "read");
    if ((code = cli_psf_load(run, a->psf_path, &job->psf))) return code;
    if ((code = cli_read_image(run, "image", a->in_path, &job->in))) return code;
    if ((code = cli_check_input_pixels(run, job->psf.pixel_um, a->psf_path))) return code;
    job->boundary = a->boundary;
    if (!a->boundary_given && job->psf.has_boundary) job->boundary = job->psf.boundary;
    cli_output_file(run, "image", a->out_path);
    cli_output_file(run, "summary", a->sum_path);
    if ((code = cli_outputs_check(run))) return code;

    cli_psf_describe(run, &job->psf);
    cli_setting_str(run, "method", method_names[a->method]);
    if (a->method == 0 && d->balance_auto)
        cli_setting_str(run, "balance", "auto (discrepancy principle)");
    else if (a->method == 0)
        cli_setting_num(run, "balance", d->balance);
    else {
        if (d->iterations_auto) cli_setting_str(run, "iterations", "auto");
        cli_setting_int(run, d->iterations_auto ? "iteration_cap" : "iterations", d->iterations);
        cli_setting_str(run, "acceleration", cli_acceleration_names[d->acceleration]);
    }
    if (a->method == 1 && a->compat < 0)
        cli_setting_str(run, "precision", cli_precision_names[d->precision]);
    cli_setting_str(run, "compat", a->compat >= 0 ? compat_names[a->compat] : "none");
    if (a->compat < 0) cli_setting_str(run, "boundary", cli_boundary_name(job->boundary));
    job->n_missing = (long long)svp_image_count_nonfinite(job->in);
    cli_result_int(run, "n_missing", job->n_missing);
    svp_status st = svp_image_new(job->in->width, job->in->height, &job->out);
    return st == SVP_OK ? 0 : cli_fail(run, st, NULL);
}

/* --compat skimage: scikit-image takes the kernel as it is given; a model is rendered as large
 * as the image allows (its shape must not exceed the image's). */
static int deconvolve_compat(cli_run *run, const struct deconvolve_args *a,
                             struct deconvolve_job *job, svp_status *st)
{
    const int w = job->in->width, h = job->in->height;
    const cli_psf *psf = &job->psf;
    const svp_image *k = psf->kernel_raw;
    if (!psf->is_model && (k->width > w || k->height > h))
        return cli_error(run,
                         "%s: the %d x %d kernel is larger than the %d x %d image %s "
                         "(scikit-image needs a PSF no larger than the image)",
                         psf->path, k->width, k->height, w, h, a->in_path);
    if (psf->is_model) {
        int rx = (w - 1) / 2, ry = (h - 1) / 2;
        if (psf->model.support > 0) {
            int rs = (int)ceil(psf->model.support);
            if (rs < rx) rx = rs;
            if (rs < ry) ry = rs;
        }
        cli_stage_begin(run, "plan");
        svp_status rs = svp_psf_render(&psf->model, rx, ry, &job->kernel);
        if (rs != SVP_OK) return cli_fail(run, rs, psf->path);
        k = job->kernel;
        if (psf->model.halo > 0)
            cli_note(run,
                     "%s: the halo (%g) is not part of a scikit-image kernel; it is "
                     "ignored with --compat skimage",
                     psf->path, psf->model.halo);
    }
    cli_stage_begin(run, "deconvolve");
    if (a->method == 0)
        *st = svp_skimage_wiener(job->in, k, job->opt.balance, job->out);
    else
        *st = svp_skimage_richardson_lucy(job->in, k, job->opt.iterations, cli_progress, run,
                                          job->out);
    return 0;
}

/* --balance auto: the discrepancy principle's λ, and a doubt when it ends on a bound. */
static int deconvolve_balance(cli_run *run, const struct deconvolve_args *a,
                              struct deconvolve_job *job)
{
    const double noise = a->deconv.noise;
    cli_stage_begin(run, "balance");
    double sigma_used = 0;
    svp_status st =
        svp_wiener_balance_discrepancy(job->blur, job->in, noise, &job->opt.balance, &sigma_used);
    if (st != SVP_OK) return cli_fail(run, st, a->in_path);
    cli_result_num(run, "noise_sigma", sigma_used);
    cli_result_str(run, "noise_sigma_from", noise > 0 ? "--noise" : "estimated");
    cli_result_num(run, "balance", job->opt.balance);
    const char *bound = cli_balance_bound_check(run, a->in_path, job->opt.balance, sigma_used);
    if (bound) {
        cli_result_str(run, "balance_at_bound", bound);
        snprintf(job->doubt, sizeof job->doubt,
                 "--balance auto ended on the %s end of its search (%g): the noise sigma "
                 "%g %s; give --balance or --noise",
                 bound, job->opt.balance, sigma_used,
                 bound[0] == 'l' ? "is below what any balance leaves (noiseless data?)"
                                 : "explains the data at every balance (the signal "
                                   "would be smoothed away)");
    }
    return 0;
}

/* What the solve reports: RL's stop and the Wiener CG's convergence, doubts among them. */
static void deconvolve_report(cli_run *run, const struct deconvolve_args *a,
                              struct deconvolve_job *job)
{
    const svp_deconv_report *report = &job->report;
    if (a->method == 1) {
        cli_result_int(run, "rl_iterations", report->iterations);
        cli_result_str(run, "rl_stop", cli_rl_stop_names[report->stop]);
        if (job->opt.auto_stop) cli_result_num(run, "rl_chi2", report->chi2);
        if (report->stop == SVP_RL_STOP_CAP && !job->doubt[0])
            snprintf(job->doubt, sizeof job->doubt,
                     "--iterations auto: the stopping rule was not met within the cap of %d "
                     "iterations (chi2 per pixel %.3g, still falling); raise --iterations "
                     "(the cap) or use --acceleration biggs-andrews",
                     report->iterations, report->chi2);
        return;
    }
    if (report->cg_steps > 0) cli_result_int(run, "cg_steps", report->cg_steps);
    cli_result_int(run, "cg_capped", report->cg_capped);
    if (!report->cg_capped) return;
    cli_result_num(run, "cg_residual", report->cg_residual);
    cli_warn(run,
             "the Wiener deconvolution of %s stopped at the step cap (%d conjugate-"
             "gradient steps) with relative residual %.3g above the tolerance 1e-8",
             a->in_path, report->cg_steps, report->cg_residual);
    if (report->cg_residual > SVP_CG_DOUBT_RESIDUAL && !job->doubt[0])
        snprintf(job->doubt, sizeof job->doubt,
                 "the Wiener solve did not converge (relative residual %.3g after %d "
                 "steps); raise --cg-max-steps or --balance",
                 report->cg_residual, report->cg_steps);
}

/* The library's own methods: the operator, the balance, the solve. */
static int deconvolve_library(cli_run *run, const struct deconvolve_args *a,
                              struct deconvolve_job *job, svp_status *st)
{
    const int w = job->in->width, h = job->in->height;
    const double noise = a->deconv.noise;
    int code;
    cli_stage_begin(run, "plan");
    if ((code = cli_psf_blur(run, &job->psf, w, h, job->boundary, &job->blur))) return code;
    if (a->deconv.balance_auto && (code = deconvolve_balance(run, a, job))) return code;
    svp_image *var = NULL;
    if (job->opt.auto_stop && noise > 0) { /* the given σ as the stopping rule's variance */
        if ((*st = svp_image_new(w, h, &var)) != SVP_OK) return cli_fail(run, *st, NULL);
        for (size_t i = 0; i < (size_t)w * h; i++) var->data[i] = noise * noise;
        job->opt.variance = var;
    }
    cli_stage_begin(run, "deconvolve");
    job->opt.progress = cli_progress;
    job->opt.progress_user = run;
    job->opt.report = &job->report;
    if (a->method == 0)
        *st = svp_deconv_wiener(job->blur, job->in, &job->opt, job->out);
    else
        *st = svp_deconv_rl(job->blur, job->in, &job->opt, job->out);
    svp_image_free(var);
    job->opt.variance = NULL;
    if (*st == SVP_OK) deconvolve_report(run, a, job);
    return 0;
}

/* A result in doubt is an error (exit 3) unless --keep-doubtful; then the image, the summary
 * and the line on stdout. */
static int deconvolve_write(cli_run *run, const struct deconvolve_args *a,
                            struct deconvolve_job *job)
{
    int code;
    cli_result_str(run, "doubt", job->doubt);
    if (job->doubt[0]) {
        if (!a->deconv.keep_doubtful) {
            cli_error(run, "%s: result in doubt: %s (--keep-doubtful writes it anyway)", a->in_path,
                      job->doubt);
            return CLI_EXIT_DOUBTFUL;
        }
        cli_warn(run, "%s: result in doubt, kept by --keep-doubtful: %s", a->in_path, job->doubt);
    }
    cli_stage_begin(run, "write");
    if ((code = cli_write_image(run, a->out_path, job->out))) return code;
    cli_stage_end(run);
    if ((code = cli_summary_write(run, a->sum_path))) return code;
    const int w = job->in->width, h = job->in->height;
    const char *compat = a->compat >= 0 ? " (scikit-image compatible)" : "";
    if (a->method == 0)
        printf("svpsf deconvolve: %s (%d x %d) deconvolved with Wiener-Hunt, balance %g%s%s "
               "-> %s in %.2f s",
               a->in_path, w, h, job->opt.balance,
               a->deconv.balance_auto ? " (discrepancy principle)" : "", compat, a->out_path,
               cli_now() - run->t_start);
    else
        printf("svpsf deconvolve: %s (%d x %d) deconvolved with %d Richardson-Lucy "
               "iterations%s -> %s in %.2f s",
               a->in_path, w, h, job->opt.report ? job->report.iterations : job->opt.iterations,
               compat, a->out_path, cli_now() - run->t_start);
    if (job->n_missing) printf("; %lld missing (NaN/Inf) input pixels", job->n_missing);
    printf("\n");
    return 0;
}

static int run_deconvolve(cli_run *run, const struct deconvolve_args *a)
{
    struct deconvolve_job job;
    memset(&job, 0, sizeof job);
    svp_deconv_defaults(&job.opt);
    cli_deconv_apply(&a->deconv, &job.opt);
    int code = deconvolve_read(run, a, &job);
    if (!code) {
        svp_status st = SVP_OK;
        cli_progress_start(run, a->method == 0 ? "Wiener-Hunt" : "Richardson-Lucy");
        code = a->compat >= 0 ? deconvolve_compat(run, a, &job, &st)
                              : deconvolve_library(run, a, &job, &st);
        if (!code) {
            cli_progress_done(run);
            if (st != SVP_OK) code = cli_fail(run, st, a->in_path);
        }
    }
    if (!code) code = deconvolve_write(run, a, &job);
    svp_blur_free(job.blur);
    svp_image_free(job.in);
    svp_image_free(job.out);
    svp_image_free(job.kernel);
    cli_psf_release(&job.psf);
    return code;
}

int cmd_deconvolve(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "deconvolve", argc, argv, CLI_COMMON_OUTPUT_DIR);
    struct deconvolve_args args;
    int code = parse_deconvolve_args(&run, &args);
    if (code == 0) code = run_deconvolve(&run, &args);
    return cli_run_finish(&run, cli_parsed_status(code));
}
