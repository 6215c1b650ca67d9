/* svpsf demo: a built-in example that needs no input files. A synthetic field map under a
 * chequered, spot-lit PL map is blurred by a Lorentzian PSF (T, eq. 3) and corrected with
 * `svpsf correct`'s defaults (T⁻¹, eq. 4: R, margin auto); the errors in the lit regions before
 * and after are printed.
 * (`svpsf simulate` runs full scenes; this quick example is kept in its own file on purpose.) */
#include "cli.h"

#include "io/image_io.h"

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define DEMO_SIZE 256
#define DEMO_PIXEL_UM 0.1
#define DEMO_FWHM_UM 1.0
#define DEMO_SQUARE_PX 20       /* chessboard squares of 2 µm */
#define DEMO_SPOT_FWHM_PX 180.0 /* the illumination spot, 18 µm */
#define DEMO_LIT 0.3            /* "lit": true PL above 30 % of its maximum */

static void print_help(const cli_run *run, FILE *out)
{
    svp_correct_options d;
    svp_correct_defaults(&d);
    fprintf(out,
            "usage: svpsf demo [-o DIR] [options]\n"
            "\n"
            "A built-in example that needs no input files, finished in a few seconds:\n"
            "  - a %d x %d true field map (signed Gaussian bumps, in uT) at %g um pixels;\n"
            "  - a true PL map: a Gaussian illumination spot (FWHM %g um) times a chessboard of\n"
            "    %g um squares with levels 0.1, 0.8 and 1.0;\n"
            "  - a Lorentzian PSF of %g um FWHM reaching over the whole field of view.\n"
            "It runs T (the apparent maps a microscope would record), then T^-1 with the\n"
            "defaults of svpsf correct (R: %d Richardson-Lucy iterations on the PL and on the\n"
            "shifted field x PL, the object estimated on the view plus the PSF's reach), and\n"
            "prints the errors in the lit regions (true PL above %g %% of its maximum).\n"
            "\n"
            "  -o, --output DIR      output folder (default ./svpsf-demo)\n",
            DEMO_SIZE, DEMO_SIZE, DEMO_PIXEL_UM, DEMO_SPOT_FWHM_PX * DEMO_PIXEL_UM,
            DEMO_SQUARE_PX * DEMO_PIXEL_UM, DEMO_FWHM_UM, d.deconv.iterations, 100 * DEMO_LIT);
    cli_print_common_help(run, out);
    fputs("\n"
          "outputs in DIR: field_true, pl_true, field_apparent, pl_apparent, field_corrected,\n"
          "pl_corrected, validity (.EXT per --format), psf.yaml (the demo's PSF file, to try\n"
          "`svpsf correct` yourself), colour figures *.png, summary.json.\n",
          out);
}

/* Deterministic levels for the chessboard (the same picture on every machine). */
static double square_level(int i, int j)
{
    uint64_t x = (uint64_t)(i * 7919 + j * 104729 + 12345);
    x ^= x >> 33;
    x *= 0xff51afd7ed558ccdULL;
    x ^= x >> 33;
    x *= 0xc4ceb9fe1a85ec53ULL;
    x ^= x >> 33;
    static const double levels[3] = {0.1, 0.8, 1.0};
    return levels[x % 3];
}

static void make_scene(svp_image *field_true, svp_image *pl_true)
{
    /* signed bumps: centre x, y (px), sigma (px), amplitude (µT) */
    static const double bumps[][4] = {
        {80, 90, 14, 40}, {170, 120, 20, -25}, {120, 185, 10, 15}, {190, 200, 8, -12}};
    const int n = DEMO_SIZE;
    const double c = (n - 1) / 2.0;
    const double spot_sigma = DEMO_SPOT_FWHM_PX / (2 * sqrt(2 * log(2)));
    for (int y = 0; y < n; y++)
        for (int x = 0; x < n; x++) {
            double b = 0;
            for (size_t k = 0; k < sizeof bumps / sizeof bumps[0]; k++) {
                double dx = x - bumps[k][0], dy = y - bumps[k][1];
                b += bumps[k][3] * exp(-(dx * dx + dy * dy) / (2 * bumps[k][2] * bumps[k][2]));
            }
            field_true->data[(size_t)y * n + x] = b;
            double r2 = (x - c) * (x - c) + (y - c) * (y - c);
            double spot = exp(-r2 / (2 * spot_sigma * spot_sigma));
            pl_true->data[(size_t)y * n + x] =
                spot * square_level(x / DEMO_SQUARE_PX, y / DEMO_SQUARE_PX);
        }
}

typedef struct lit_error {
    double max, mean;
} lit_error;

static lit_error error_in_lit(const svp_image *estimate, const svp_image *truth,
                              const svp_image *pl_true, double pl_max)
{
    lit_error e = {0, 0};
    size_t count = 0, n = (size_t)truth->width * truth->height;
    for (size_t i = 0; i < n; i++) {
        if (!(pl_true->data[i] > DEMO_LIT * pl_max)) continue;
        double d = fabs(estimate->data[i] - truth->data[i]);
        if (d > e.max) e.max = d;
        e.mean += d;
        count++;
    }
    if (count) e.mean /= (double)count;
    return e;
}

static svp_image *difference(const svp_image *a, const svp_image *b)
{
    svp_image *d = NULL;
    if (svp_image_new(a->width, a->height, &d) != SVP_OK) return NULL;
    size_t n = (size_t)a->width * a->height;
    for (size_t i = 0; i < n; i++) d->data[i] = a->data[i] - b->data[i];
    return d;
}

enum { N_IMAGES = 7, N_FIGURES = 7 };
enum { FIELD_TRUE, PL_TRUE, FIELD_APPARENT, PL_APPARENT, FIELD_CORRECTED, PL_CORRECTED, VALIDITY };

/* The demo takes no options of its own: its arguments are the output folder. */
struct demo_args {
    const char *output; /* -o, default svpsf-demo */
};

/* What a run holds (released by run_demo). */
struct demo_job {
    svp_image *images[N_IMAGES]; /* indexed by the enum above */
    const char *image_paths[N_IMAGES], *figure_paths[N_FIGURES], *psf_path, *summary_path;
    svp_image *err_apparent, *err_corrected;
    svp_blur *blur, *blur_margin; /* the view's (T); the view plus the margin's (T⁻¹) */
    svp_correct_options opt;
    size_t n_missing;
    double pl_max, peak; /* of the true PL and |field| */
    lit_error ea, ec;    /* apparent and corrected errors in the lit regions */
};

static int parse_demo_args(cli_run *run, struct demo_args *a)
{
    static const struct option own[] = {{NULL, 0, NULL, 0}};
    a->output = NULL;
    int c;
    while ((c = cli_next_option(run, own)) != CLI_OPTIONS_DONE) {
        switch (c) {
        case CLI_OPTION_HELP: print_help(run, stdout); return CLI_OPTION_HELP;
        case CLI_OPTION_ERROR: return CLI_EXIT_USAGE;
        default: return cli_error(run, "internal: option %d", c);
        }
    }
    if (optind < run->argc)
        return cli_error(run, "unexpected argument '%s' (the demo needs no input)",
                         run->argv[optind]);
    if (!run->output) run->output = "svpsf-demo";
    a->output = run->output;
    return 0;
}

/* Every output planned and checked; the images allocated. */
static int demo_plan(cli_run *run, struct demo_job *job)
{
    static const char *const image_names[N_IMAGES] = {
        "field_true",      "pl_true",      "field_apparent", "pl_apparent",
        "field_corrected", "pl_corrected", "validity"};
    static const char *const figure_names[N_FIGURES] = {
        "field_true.png",  "field_apparent.png", "field_corrected.png", "pl_true.png",
        "pl_apparent.png", "error_apparent.png", "error_corrected.png"};
    int code;
    for (int i = 0; i < N_IMAGES; i++)
        job->image_paths[i] = cli_output_in_dir(run, image_names[i], image_names[i], 1);
    for (int i = 0; i < N_FIGURES; i++)
        job->figure_paths[i] = cli_output_in_dir(run, figure_names[i], figure_names[i], 0);
    job->psf_path = cli_output_in_dir(run, "psf", "psf.yaml", 0);
    job->summary_path = cli_output_in_dir(run, "summary", "summary.json", 0);
    if ((code = cli_outputs_check(run))) return code;
    svp_status st = SVP_OK;
    for (int i = 0; i < N_IMAGES && st == SVP_OK; i++)
        st = svp_image_new(DEMO_SIZE, DEMO_SIZE, &job->images[i]);
    return st == SVP_OK ? 0 : cli_fail(run, st, NULL);
}

/* The scene, its PSF and operator, the forward transform T and the correction T^-1. */
static int demo_compute(cli_run *run, struct demo_job *job)
{
    svp_image **im = job->images;
    svp_correct_options *opt = &job->opt;
    cli_stage_begin(run, "scene");
    make_scene(im[FIELD_TRUE], im[PL_TRUE]);
    svp_psf psf;
    svp_psf_defaults(&psf);
    psf.model = SVP_PSF_LORENTZIAN;
    psf.fwhm = DEMO_FWHM_UM / DEMO_PIXEL_UM;
    psf.beta = 1.0;
    /* svpsf correct's defaults for one PSF at this size: R, margin auto, double precision */
    svp_correct_defaults(opt);
    opt->margin = svp_psf_auto_margin(&psf, DEMO_SIZE, DEMO_SIZE);
    cli_setting_int(run, "size", DEMO_SIZE);
    cli_setting_num(run, "pixel_um", DEMO_PIXEL_UM);
    cli_setting_str(run, "psf_model", "lorentzian");
    cli_setting_num(run, "psf_fwhm_um", DEMO_FWHM_UM);
    cli_setting_str(run, "boundary", "zero");
    cli_setting_str(run, "method", "r");
    cli_setting_int(run, "iterations", opt->deconv.iterations);
    cli_setting_int(run, "margin", opt->margin);
    cli_setting_num(run, "pl_floor", opt->pl_floor);
    cli_setting_num(run, "lit_threshold", DEMO_LIT);

    cli_stage_begin(run, "plan");
    svp_status st = svp_blur_new(&psf, DEMO_SIZE, DEMO_SIZE, SVP_BOUNDARY_ZERO, &job->blur);
    if (st == SVP_OK)
        st = svp_blur_new(&psf, DEMO_SIZE + 2 * opt->margin, DEMO_SIZE + 2 * opt->margin,
                          SVP_BOUNDARY_ZERO, &job->blur_margin);
    if (st != SVP_OK) return cli_fail(run, st, "PSF");

    cli_stage_begin(run, "forward");
    const svp_image *fields_in[1] = {im[FIELD_TRUE]};
    st = svp_forward_transform(job->blur, im[PL_TRUE], fields_in, 1, im[PL_APPARENT],
                               &im[FIELD_APPARENT], NULL);
    if (st != SVP_OK) return cli_fail(run, st, "forward transform");

    cli_stage_begin(run, "correct");
    opt->deconv.progress = cli_progress;
    opt->deconv.progress_user = run;
    cli_progress_start(run, "correcting");
    const svp_image *fields_app[1] = {im[FIELD_APPARENT]};
    st = svp_inverse_transform(job->blur_margin, im[PL_APPARENT], fields_app, 1, opt,
                               im[PL_CORRECTED],
                               &im[FIELD_CORRECTED], im[VALIDITY], &job->n_missing);
    cli_progress_done(run);
    return st == SVP_OK ? 0 : cli_fail(run, st, "inverse transform");
}

/* Errors in the lit regions. */
static void demo_errors(cli_run *run, struct demo_job *job)
{
    svp_image **im = job->images;
    const size_t n = (size_t)DEMO_SIZE * DEMO_SIZE;
    double pl_max = 0, peak = 0;
    for (size_t i = 0; i < n; i++) {
        if (im[PL_TRUE]->data[i] > pl_max) pl_max = im[PL_TRUE]->data[i];
        if (fabs(im[FIELD_TRUE]->data[i]) > peak) peak = fabs(im[FIELD_TRUE]->data[i]);
    }
    job->pl_max = pl_max;
    job->peak = peak;
    job->ea = error_in_lit(im[FIELD_APPARENT], im[FIELD_TRUE], im[PL_TRUE], pl_max);
    job->ec = error_in_lit(im[FIELD_CORRECTED], im[FIELD_TRUE], im[PL_TRUE], pl_max);
    cli_result_num(run, "field_peak_uT", peak);
    cli_result_num(run, "apparent_error_max_uT", job->ea.max);
    cli_result_num(run, "apparent_error_mean_uT", job->ea.mean);
    cli_result_num(run, "corrected_error_max_uT", job->ec.max);
    cli_result_num(run, "corrected_error_mean_uT", job->ec.mean);
    cli_result_int(run, "n_missing", (long long)job->n_missing);
}

/* Colour figures: fields on one diverging scale, PL on viridis, errors on their own. */
static int demo_figures(cli_run *run, struct demo_job *job)
{
    svp_image **im = job->images;
    const double peak = job->peak, pl_max = job->pl_max, e = job->ea.max;
    job->err_apparent = difference(im[FIELD_APPARENT], im[FIELD_TRUE]);
    job->err_corrected = difference(im[FIELD_CORRECTED], im[FIELD_TRUE]);
    if (!job->err_apparent || !job->err_corrected) return cli_fail(run, SVP_ERR_NOMEM, NULL);
    struct {
        const svp_image *img;
        double lo, hi;
        int diverging;
    } figures[N_FIGURES] = {
        {im[FIELD_TRUE], -peak, peak, 1},      {im[FIELD_APPARENT], -peak, peak, 1},
        {im[FIELD_CORRECTED], -peak, peak, 1}, {im[PL_TRUE], 0, pl_max, 0},
        {im[PL_APPARENT], 0, pl_max, 0},       {job->err_apparent, -e, e, 1},
        {job->err_corrected, -e, e, 1},
    };
    for (int i = 0; i < N_FIGURES; i++) {
        svp_status st =
            svp_io_write_colormap_png(job->figure_paths[i], figures[i].img, figures[i].lo,
                                      figures[i].hi, figures[i].diverging, run->force);
        if (st != SVP_OK) return cli_fail(run, st, job->figure_paths[i]);
    }
    return 0;
}

/* The maps, psf.yaml, the figures and summary.json. */
static int demo_write(cli_run *run, struct demo_job *job)
{
    int code;
    cli_stage_begin(run, "write");
    for (int i = 0; i < N_IMAGES; i++)
        if ((code = cli_write_image(run, job->image_paths[i], job->images[i]))) return code;
    char yaml[512];
    snprintf(yaml, sizeof yaml,
             "# The svpsf demo's PSF: a Lorentzian of %g um FWHM at %g um pixels, reaching\n"
             "# over the whole field of view. Try:\n"
             "#   svpsf correct --field field_apparent.%s --pl pl_apparent.%s \\\n"
             "#       --psf psf.yaml -o corrected\n"
             "pixel_um: %g\n"
             "psf:\n"
             "  model: lorentzian\n"
             "  fwhm_um: %g\n"
             "  halo: 0\n"
             "boundary: zero\n",
             DEMO_FWHM_UM, DEMO_PIXEL_UM, cli_format_extension(run->format),
             cli_format_extension(run->format), DEMO_PIXEL_UM, DEMO_FWHM_UM);
    if ((code = cli_write_text(run, job->psf_path, yaml))) return code;
    if ((code = demo_figures(run, job))) return code;
    cli_stage_end(run);
    return cli_summary_write(run, job->summary_path);
}

static int run_demo(cli_run *run, const struct demo_args *a)
{
    struct demo_job job;
    memset(&job, 0, sizeof job);
    int code = demo_plan(run, &job);
    if (!code) code = demo_compute(run, &job);
    if (!code) {
        demo_errors(run, &job);
        code = demo_write(run, &job);
    }
    if (!code) {
        const lit_error ea = job.ea, ec = job.ec;
        const double peak = job.peak;
        printf(
            "svpsf demo: a %d x %d field map (peak %.3g uT) under a chequered, spot-lit PL map,\n"
            "blurred by a Lorentzian PSF of %g um FWHM (%g um pixels), then corrected with the\n"
            "defaults of svpsf correct (R, %d Richardson-Lucy iterations, margin %d px).\n"
            "Errors in the lit regions (true PL > %g %% of max):\n"
            "  apparent  (T):     max %7.3f uT (%5.2f %% of peak), mean %7.3f uT (%5.2f %%)\n"
            "  corrected (T^-1):  max %7.3f uT (%5.2f %% of peak), mean %7.3f uT (%5.2f %%)\n"
            "Time %.2f s. Outputs (maps, psf.yaml, figures *.png, summary.json) are in %s/\n",
            DEMO_SIZE, DEMO_SIZE, peak, DEMO_FWHM_UM, DEMO_PIXEL_UM, job.opt.deconv.iterations,
            job.opt.margin, 100 * DEMO_LIT, ea.max, 100 * ea.max / peak, ea.mean,
            100 * ea.mean / peak, ec.max, 100 * ec.max / peak, ec.mean, 100 * ec.mean / peak,
            cli_now() - run->t_start, a->output);
    }
    for (int i = 0; i < N_IMAGES; i++) svp_image_free(job.images[i]);
    svp_image_free(job.err_apparent);
    svp_image_free(job.err_corrected);
    svp_blur_free(job.blur);
    svp_blur_free(job.blur_margin);
    return code;
}

int cmd_demo(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "demo", argc, argv, CLI_COMMON_OUTPUT_DIR);
    run.fft_measure = 0; /* a short job: planning by measurement would dominate it */
    struct demo_args args;
    int code = parse_demo_args(&run, &args);
    if (code == 0) code = run_demo(&run, &args);
    return cli_run_finish(&run, cli_parsed_status(code));
}
