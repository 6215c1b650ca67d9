/* svpsf fit-psf: fit a Moffat (Gaussian, Lorentzian) PSF to a spot image, or derive the PSF
 * from an excitation/emission spot pair (docs/model.md §8); write a PSF file that --psf of
 * forward/correct/deconvolve accepts, figures and a summary. */
#include "cli.h"

#include "core/internal.h"
#include "figure/figure.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

enum {
    OPT_EXCITATION = CLI_OPTION_FIRST,
    OPT_PIXEL_UM,
    OPT_ITERATIONS,
    OPT_FIX_BETA,
    OPT_SIGMA_BG,
    OPT_SATURATION,
    OPT_REFUSE_BORDER,
    OPT_FIGURES,
    OPT_NO_FIGURES,
    OPT_USE,
    OPT_MAX_ITER,
    OPT_KEEP_DOUBTFUL
};

static void print_help(const cli_run *run, FILE *out)
{
    fputs("usage: svpsf fit-psf SPOT --pixel-um P -o PSF.yaml [--excitation SPOT_G]\n"
          "                     [--model moffat|gaussian|lorentzian] [--iterations N] [options]\n"
          "\n"
          "Fits an elliptical Moffat (or Gaussian, Lorentzian) PSF to the image of one spot by\n"
          "Levenberg-Marquardt with Poisson weights (model integrated over the pixels), and\n"
          "writes it as a PSF file for --psf of forward, correct and deconvolve.\n"
          "With --excitation, SPOT is the emission (PL) image I_PL and SPOT_G the excitation\n"
          "image I_G of the same focused spot: I_PL = I_G (*) p. Both are fitted directly, their\n"
          "offset is measured (phase correlation, and the fitted centres), I_PL is deconvolved by\n"
          "I_G (Richardson-Lucy) and p is fitted: the direct PL fit is an upper bound on the\n"
          "width, the deconvolved fit a lower one (it approaches p from above as RL iterates).\n"
          "\n"
          "  SPOT                  the spot image (photon counts unless --gain says otherwise)\n"
          "  --pixel-um P          pixel size in um (required)\n"
          "  -o, --output PSF.yaml the PSF file to write (required)\n"
          "  --excitation SPOT_G   the excitation spot of the pair (same size as SPOT)\n",
          out);
    cli_print_spot_help(out);
    fputs("  --iterations N        Richardson-Lucy iterations of the pair method (default 75)\n"
          "  --use deconvolved|direct  which fit of a pair goes to PSF.yaml (default\n"
          "                        deconvolved)\n"
          "  --circular            one FWHM (no ellipticity, no angle)\n"
          "  --fix-beta B          keep the Moffat beta at B\n"
          "  --gain G              photons per data unit (default 1: the data are counts);\n"
          "                        0 = unknown noise: unit weights, errors scaled by chi2_red\n"
          "  --sigma-bg S          additive (read) noise in data units (default 0)\n"
          "  --saturation L        pixels >= L are saturated and left out (default: detect a\n"
          "                        plateau of >= 3 equal maxima)\n"
          "  --max-iterations N    Levenberg-Marquardt steps before giving up (default 200)\n"
          "  --refuse-border       a spot within 2 FWHM of an edge is an error (default: fitted\n"
          "                        and flagged)\n"
          "  --keep-doubtful       write a fit the program cannot vouch for (beta or the width\n"
          "                        on its bound, chi2_red above 3 with known noise): exit 0,\n"
          "                        the flags recorded (default: exit 3, nothing written)\n"
          "  --figures DIR         where the figures go (default: PSF.figures/ next to\n"
          "                        PSF.yaml)\n"
          "  --no-figures          no figures\n",
          out);
    cli_print_common_help(run, out);
    fputs("\n"
          "outputs: PSF.yaml; PSF.summary.json (every fitted value, uncertainty and flag);\n"
          "figures (PNG): spot, model (log10 of the counts above the fitted background) and\n"
          "residual ((data - model) / sigma) images, profile.png (azimuthal mean of data and\n"
          "model above background versus radius, log10); for a pair the same with prefixes\n"
          "excitation_, direct_ and deconvolved_.\n"
          "exit status: 1 for bad input (an empty image, a refused border spot), 2 when the fit\n"
          "does not converge (the last parameters are printed, nothing is written), 3 when the\n"
          "fit to be written has beta or the width on its bound or a poor fit (not one Moffat\n"
          "spot, or noise other than counts): printed, nothing written, unless --keep-doubtful.\n",
          out);
}

static void print_fit(const char *what, const svp_spot_result *r, double um, int unit_weights)
{
    char flags[256];
    svp_spot_flags_describe(r->flags, flags, sizeof flags);
    printf("%s:\n", what);
    printf("  FWHM        %.4f +- %.4f um (%.3f +- %.3f px)   major %.4f +- %.4f, minor %.4f "
           "+- %.4f um\n",
           r->fwhm * um, r->fwhm_err * um, r->fwhm, r->fwhm_err, r->fwhm_major * um,
           r->fwhm_major_err * um, r->fwhm_minor * um, r->fwhm_minor_err * um);
    if (r->model == SVP_PSF_MOFFAT)
        printf("  beta        %.4f +- %.4f\n", r->beta, r->beta_err);
    else
        printf("  beta        %s\n",
               r->model == SVP_PSF_LORENTZIAN ? "1 (Lorentzian)" : "- (Gaussian)");
    printf("  angle       %.2f +- %.2f deg   e1 %.4f  e2 %.4f\n", r->angle * 180 / M_PI,
           r->angle_err * 180 / M_PI, r->e1, r->e2);
    printf("  centre      x %.3f +- %.3f, y %.3f +- %.3f px\n", r->x0, r->x0_err, r->y0, r->y0_err);
    printf("  amplitude   %.6g +- %.3g   background %.6g +- %.3g\n", r->amplitude, r->amplitude_err,
           r->background, r->background_err);
    printf("  EE radii    50 %% %.4f um, 80 %% %.4f um, 95 %% %.4f um (of a disc of %.3f um)\n",
           r->ee50 * um, r->ee80 * um, r->ee95 * um, r->ee_radius * um);
    printf("  chi2_red    %.4f%s (dof %d, %d pixels used; %d hot, %d clipped, %d saturated "
           "excluded), %d iterations\n",
           r->chi2_red, unit_weights ? " in squared data units (unit weights)" : "", r->dof,
           r->n_used, r->n_hot, r->n_clipped, r->n_saturated, r->iterations);
    printf("  flags       %s\n", flags);
}

static void record_fit(cli_run *run, const char *prefix, const svp_spot_result *r, double um)
{
    char key[96], flags[256];
#define NUM(name, value)                                                                           \
    do {                                                                                           \
        snprintf(key, sizeof key, "%s%s", prefix, name);                                           \
        cli_result_num(run, key, value);                                                           \
    } while (0)
    NUM("fwhm_um", r->fwhm * um);
    NUM("fwhm_err_um", r->fwhm_err * um);
    NUM("fwhm_major_um", r->fwhm_major * um);
    NUM("fwhm_major_err_um", r->fwhm_major_err * um);
    NUM("fwhm_minor_um", r->fwhm_minor * um);
    NUM("fwhm_minor_err_um", r->fwhm_minor_err * um);
    NUM("angle_deg", r->angle * 180 / M_PI);
    NUM("angle_err_deg", r->angle_err * 180 / M_PI);
    NUM("e1", r->e1);
    NUM("e2", r->e2);
    NUM("beta", r->beta);
    NUM("beta_err", r->beta_err);
    NUM("x0_px", r->x0);
    NUM("x0_err_px", r->x0_err);
    NUM("y0_px", r->y0);
    NUM("y0_err_px", r->y0_err);
    NUM("amplitude", r->amplitude);
    NUM("amplitude_err", r->amplitude_err);
    NUM("background", r->background);
    NUM("background_err", r->background_err);
    NUM("ee50_um", r->ee50 * um);
    NUM("ee80_um", r->ee80 * um);
    NUM("ee95_um", r->ee95 * um);
    NUM("ee_disc_um", r->ee_radius * um);
    NUM("chi2", r->chi2);
    NUM("chi2_red", r->chi2_red);
    NUM("border_distance_px", r->border_distance);
#undef NUM
    snprintf(key, sizeof key, "%siterations", prefix);
    cli_result_int(run, key, r->iterations);
    snprintf(key, sizeof key, "%sn_used", prefix);
    cli_result_int(run, key, r->n_used);
    snprintf(key, sizeof key, "%sn_excluded_hot", prefix);
    cli_result_int(run, key, r->n_hot);
    snprintf(key, sizeof key, "%sn_excluded_clipped", prefix);
    cli_result_int(run, key, r->n_clipped);
    snprintf(key, sizeof key, "%sn_excluded_saturated", prefix);
    cli_result_int(run, key, r->n_saturated);
    snprintf(key, sizeof key, "%sflags", prefix);
    svp_spot_flags_describe(r->flags, flags, sizeof flags);
    cli_result_str(run, key, flags);
}

/* The plain PSF file (svp_psf_file_read) of a fit, the fit's numbers as comments. */
static char *psf_file_text(const svp_spot_result *r, double um, const char *source)
{
    svp_psf p;
    svp_spot_result_psf(r, &p);
    char flags[256];
    svp_spot_flags_describe(r->flags, flags, sizeof flags);
    size_t size = 4096;
    char *t = malloc(size);
    if (!t) return NULL;
    int n = snprintf(t, size,
                     "# svpsf fit-psf: %s\n"
                     "# FWHM %.5f +- %.5f um (major %.5f, minor %.5f), beta %.4f +- %.4f,\n"
                     "# EE radii 50/80/95 %% %.4f/%.4f/%.4f um, chi2_red %.4f, flags: %s\n"
                     "pixel_um: %.17g\n"
                     "psf:\n"
                     "  model: %s\n"
                     "  fwhm_um: %.17g\n",
                     source, r->fwhm * um, r->fwhm_err * um, r->fwhm_major * um, r->fwhm_minor * um,
                     r->beta, r->beta_err, r->ee50 * um, r->ee80 * um, r->ee95 * um, r->chi2_red,
                     flags, um, cli_psf_model_names[p.model], p.fwhm * um);
    if (p.fwhm_minor > 0 && p.fwhm_minor != p.fwhm)
        n += snprintf(t + n, size - (size_t)n, "  fwhm_minor_um: %.17g\n  angle_deg: %.17g\n",
                      p.fwhm_minor * um, p.angle * 180 / M_PI);
    if (p.model == SVP_PSF_MOFFAT)
        n += snprintf(t + n, size - (size_t)n, "  beta: %.17g\n", p.beta);
    n += snprintf(t + n, size - (size_t)n, "  halo: 0\n");
    if (p.subsample > 0) snprintf(t + n, size - (size_t)n, "  subsample: %d\n", p.subsample);
    return t;
}

/* log10 of (v - background) floored at `floor` (> 0). */
static svp_status log_image(const svp_image *v, double background, double floor_, svp_image **out)
{
    svp_status st = svp_image_new(v->width, v->height, out);
    if (st != SVP_OK) return st;
    for (size_t i = 0; i < (size_t)v->width * v->height; i++) {
        double d = v->data[i] - background;
        (*out)->data[i] = isfinite(d) ? log10(fmax(d, floor_)) : NAN;
    }
    return SVP_OK;
}

/* spot/model/residual images and the radial profile of one fit, into DIR/PREFIXname.png. */
static int write_figures(cli_run *run, const char *dir, const char *prefix, const char *title,
                         const svp_image *data, const svp_image *model, const svp_image *resid,
                         const svp_spot_result *r, const svp_spot_options *so, double um)
{
    char path[8448], t[256];
    svp_image *a = NULL, *b = NULL, *z = NULL;
    double *rad = NULL, *pd = NULL, *pm = NULL;
    int code = 0;
    const double amp = r->amplitude > 0 ? r->amplitude : 1;
    const double floor_ = amp * 1e-4;
    const double lo = log10(floor_), hi = log10(amp * 1.05);
    svp_status st = log_image(data, r->background, floor_, &a);
    if (st == SVP_OK) st = log_image(model, r->background, floor_, &b);
    if (st == SVP_OK) st = svp_image_new(data->width, data->height, &z);
    if (st != SVP_OK) goto fail;
    /* unknown noise (unit weights, e.g. a deconvolved spot): sigma from the scatter,
     * sqrt(chi2_red) */
    const int unit = so->noise.gain == 0 && so->noise.sigma_bg == 0 && so->noise.excess == 0;
    for (size_t i = 0; i < (size_t)data->width * data->height; i++) {
        double sigma =
            unit ? sqrt(r->chi2_red) : sqrt(svp_noise_variance(&so->noise, model->data[i]));
        z->data[i] = resid->data[i] / (sigma > 0 ? sigma : 1);
    }
    snprintf(path, sizeof path, "%s/%sspot.png", dir, prefix);
    snprintf(t, sizeof t, "%s: data", title);
    if ((st = svp_figure_map(path, a, 1, lo, hi, 0, t, "log10 (counts above background)", um,
                               run->force)) != SVP_OK)
        goto fail;
    snprintf(path, sizeof path, "%s/%smodel.png", dir, prefix);
    snprintf(t, sizeof t, "%s: fitted %s", title, cli_psf_model_names[r->model]);
    if ((st = svp_figure_map(path, b, 1, lo, hi, 0, t, "log10 (counts above background)", um,
                               run->force)) != SVP_OK)
        goto fail;
    snprintf(path, sizeof path, "%s/%sresidual.png", dir, prefix);
    snprintf(t, sizeof t, "%s: residual (data - model) / sigma%s", title,
             unit ? " (sigma from the scatter)" : "");
    if ((st = svp_figure_map(path, z, 1, -5, 5, 1, t, "residual / sigma", um, run->force)) !=
        SVP_OK)
        goto fail;
    /* azimuthal means in 0.5 px rings around the fitted centre */
    {
        const double dr = 0.5;
        double rmax = fmin(r->ee_radius, 0.5 * fmin(data->width, data->height));
        int nb = (int)ceil(rmax / dr);
        if (nb < 2) nb = 2;
        rad = calloc((size_t)nb, sizeof *rad);
        pd = calloc((size_t)nb, sizeof *pd);
        pm = calloc((size_t)nb, sizeof *pm);
        int *cnt = calloc((size_t)nb, sizeof *cnt);
        if (!rad || !pd || !pm || !cnt) {
            free(cnt);
            cli_error(run, "figures: out of memory");
            code = CLI_EXIT_RUNTIME;
            goto done;
        }
        for (int y = 0; y < data->height; y++)
            for (int x = 0; x < data->width; x++) {
                size_t i = (size_t)y * data->width + x;
                int k = (int)(hypot(x - r->x0, y - r->y0) / dr);
                if (k >= nb || !isfinite(data->data[i])) continue;
                pd[k] += data->data[i] - r->background;
                pm[k] += model->data[i] - r->background;
                cnt[k]++;
            }
        for (int k = 0; k < nb; k++) {
            rad[k] = (k + 0.5) * dr * um;
            pd[k] = cnt[k] && pd[k] / cnt[k] > 0 ? log10(pd[k] / cnt[k]) : NAN;
            pm[k] = cnt[k] && pm[k] / cnt[k] > 0 ? log10(pm[k] / cnt[k]) : NAN;
        }
        free(cnt);
        const double *xs[2] = {rad, rad}, *ys[2] = {pd, pm};
        const int ns[2] = {nb, nb};
        char fitlab[128];
        if (r->model == SVP_PSF_MOFFAT)
            snprintf(fitlab, sizeof fitlab, "Moffat fit: FWHM %.3f um, beta %.2f", r->fwhm * um,
                     r->beta);
        else
            snprintf(fitlab, sizeof fitlab, "%s fit: FWHM %.3f um", cli_psf_model_names[r->model],
                     r->fwhm * um);
        const char *labels[2] = {"data (azimuthal mean)", fitlab};
        snprintf(path, sizeof path, "%s/%sprofile.png", dir, prefix);
        snprintf(t, sizeof t, "%s: radial profile", title);
        const int markers[2] = {1, 0}; /* data as points, the fit as a line */
        if ((st = svp_figure_line_plot(path, t, "radius from the fitted centre (um)",
                                  "log10 (counts above background)", 2, xs, ys, ns, labels,
                                  markers, run->force)) != SVP_OK)
            goto fail;
    }
    goto done;
fail:
    code = cli_fail(run, st, "figures");
done:
    svp_image_free(a);
    svp_image_free(b);
    svp_image_free(z);
    free(rad);
    free(pd);
    free(pm);
    return code;
}

/* model and residual images of a fit by refitting with the same options (deterministic). */
static int fit_with_images(cli_run *run, const svp_image *img, const svp_spot_options *so,
                           svp_spot_result *r, svp_image **model, svp_image **resid,
                           const char *path)
{
    svp_status st = svp_image_new(img->width, img->height, model);
    if (st == SVP_OK) st = svp_image_new(img->width, img->height, resid);
    if (st == SVP_OK) st = svp_spot_fit(img, so, r, *model, *resid);
    if (st != SVP_OK) return cli_fail(run, st, path);
    return 0;
}

struct fit_psf_args {
    const char *spot_path; /* SPOT */
    const char *exc_path;  /* --excitation */
    const char *figures;   /* --figures */
    int no_figures;        /* --no-figures */
    int use_direct;        /* --use direct */
    int keep_doubtful;     /* --keep-doubtful */
    double pixel_um;       /* --pixel-um */
    cli_spot_args spot;    /* --model, --circular, --gain */
    svp_pair_options po;   /* the pair method and its spot fit (the group applied) */
};

/* What a run holds (released by run_fit_psf). */
struct fit_psf_job {
    svp_image *spot, *exc, *dec, *m1, *r1, *m2, *r2, *m3, *r3;
    char *text;
    svp_spot_result single, dfit;
    svp_pair_result pr;
    const svp_spot_result *chosen; /* the fit written to PSF.yaml */
    char source[512];
    char summary_path[4096], fig_dir[4096];
};

static int fit_psf_option(cli_run *run, struct fit_psf_args *a, int c)
{
    svp_spot_options *so = &a->po.spot;
    switch (c) {
    case OPT_EXCITATION: a->exc_path = optarg; return 0;
    case OPT_PIXEL_UM:
        return cli_parse_double_in(run, "--pixel-um", optarg, SVP_PIXEL_UM_MIN, 1, INFINITY, 0,
                                   &a->pixel_um);
    case OPT_ITERATIONS:
        return cli_parse_int(run, "--iterations", optarg, 1, 100000, &a->po.iterations);
    case OPT_FIX_BETA:
        if (cli_parse_double_in(run, "--fix-beta", optarg, 0, 0, INFINITY, 0, &so->beta))
            return CLI_EXIT_USAGE;
        so->fix_beta = 1;
        return 0;
    case OPT_SIGMA_BG:
        return cli_parse_double_in(run, "--sigma-bg", optarg, 0, 1, INFINITY, 0,
                                   &so->noise.sigma_bg);
    case OPT_SATURATION:
        return cli_parse_double_in(run, "--saturation", optarg, 0, 0, INFINITY, 0, &so->saturation);
    case OPT_REFUSE_BORDER: so->refuse_near_border = 1; return 0;
    case OPT_MAX_ITER:
        return cli_parse_int(run, "--max-iterations", optarg, 1, 100000, &so->lm.max_iterations);
    case OPT_FIGURES: a->figures = optarg; return 0;
    case OPT_NO_FIGURES: a->no_figures = 1; return 0;
    case OPT_KEEP_DOUBTFUL: a->keep_doubtful = 1; return 0;
    case OPT_USE: {
        static const char *const uses[] = {"deconvolved", "direct", NULL};
        return cli_parse_choice(run, "--use", optarg, uses, &a->use_direct);
    }
    default: {
        int bad = cli_spot_option(run, &a->spot, c, optarg);
        return bad < 0 ? cli_error(run, "internal: option %d", c) : bad;
    }
    }
}

static int parse_fit_psf_args(cli_run *run, struct fit_psf_args *a)
{
    static const struct option own[] = {
        {"excitation", required_argument, NULL, OPT_EXCITATION},
        {"pixel-um", required_argument, NULL, OPT_PIXEL_UM},
        CLI_SPOT_LONGOPTS,
        {"iterations", required_argument, NULL, OPT_ITERATIONS},
        {"fix-beta", required_argument, NULL, OPT_FIX_BETA},
        {"sigma-bg", required_argument, NULL, OPT_SIGMA_BG},
        {"saturation", required_argument, NULL, OPT_SATURATION},
        {"refuse-border", no_argument, NULL, OPT_REFUSE_BORDER},
        {"figures", required_argument, NULL, OPT_FIGURES},
        {"no-figures", no_argument, NULL, OPT_NO_FIGURES},
        {"use", required_argument, NULL, OPT_USE},
        {"max-iterations", required_argument, NULL, OPT_MAX_ITER},
        {"keep-doubtful", no_argument, NULL, OPT_KEEP_DOUBTFUL},
        {NULL, 0, NULL, 0},
    };
    memset(a, 0, sizeof *a);
    svp_pair_defaults(&a->po);
    cli_spot_init(&a->spot, &a->po.spot);
    int c;
    while ((c = cli_next_option(run, own)) != CLI_OPTIONS_DONE) {
        if (c == CLI_OPTION_HELP) {
            print_help(run, stdout);
            return CLI_OPTION_HELP;
        }
        if (c == CLI_OPTION_ERROR || fit_psf_option(run, a, c)) return CLI_EXIT_USAGE;
    }
    a->spot_path = cli_one_argument(run, "the spot image SPOT is required (see --help)", "");
    if (!a->spot_path) return CLI_EXIT_USAGE;
    if (!(a->pixel_um > 0)) return cli_error(run, "--pixel-um P is required");
    if (!run->output) return cli_error(run, "-o PSF.yaml is required");
    if (!cli_yaml_extension(run->output))
        return cli_error(run, "-o %s: the PSF file must end in .yaml or .yml", run->output);
    if (a->figures && a->no_figures) return cli_error(run, "--figures and --no-figures contradict");
    if (!a->exc_path && a->use_direct) return cli_error(run, "--use needs --excitation (a pair)");
    cli_spot_apply(&a->spot, &a->po.spot);
    if (a->spot.model != SVP_PSF_MOFFAT && a->po.spot.fix_beta)
        return cli_error(run, "--fix-beta applies to --model moffat only");
    return 0;
}

/* The inputs, then every output planned and checked before any work. */
static int fit_psf_read(cli_run *run, const struct fit_psf_args *a, struct fit_psf_job *job)
{
    const svp_spot_options *so = &a->po.spot;
    const char *exc_path = a->exc_path;
    int code;
    cli_stage_begin(run, "read");
    if ((code = cli_read_image(run, exc_path ? "emission" : "spot", a->spot_path, &job->spot)))
        return code;
    if (exc_path) {
        if ((code = cli_read_image(run, "excitation", exc_path, &job->exc))) return code;
        if ((code = cli_check_same_size(run, job->spot, "emission", a->spot_path, job->exc,
                                        "excitation", exc_path)))
            return code;
    }
    cli_path_sibling(run->output, ".summary.json", job->summary_path, sizeof job->summary_path);
    if (a->figures)
        snprintf(job->fig_dir, sizeof job->fig_dir, "%s", a->figures);
    else
        cli_path_sibling(run->output, ".figures", job->fig_dir, sizeof job->fig_dir);
    cli_output_file(run, "psf", run->output);
    cli_output_file(run, "summary", job->summary_path);
    if (!a->no_figures) {
        static const char *const names[] = {"spot", "model", "residual", "profile"};
        static const char *const prefixes[] = {"", "excitation_", "direct_", "deconvolved_"};
        char buf[8448];
        for (int p = exc_path ? 1 : 0; p < (exc_path ? 4 : 1); p++)
            for (int k = 0; k < 4; k++) {
                snprintf(buf, sizeof buf, "%s/%s%s.png", job->fig_dir, prefixes[p], names[k]);
                cli_output_file(run, "figure", buf);
            }
    }
    if ((code = cli_outputs_check(run))) return code;
    cli_setting_num(run, "pixel_um", a->pixel_um);
    cli_setting_str(run, "model", cli_psf_model_names[a->spot.model]);
    cli_setting_int(run, "elliptical", so->elliptical);
    if (so->fix_beta) cli_setting_num(run, "fixed_beta", so->beta);
    cli_setting_num(run, "gain", so->noise.gain);
    cli_setting_num(run, "sigma_bg", so->noise.sigma_bg);
    if (exc_path) cli_setting_int(run, "rl_iterations", a->po.iterations);
    return 0;
}

/* One spot: its fit (the last parameters printed when it does not converge). */
static int fit_psf_single(cli_run *run, const struct fit_psf_args *a, struct fit_psf_job *job)
{
    const svp_spot_options *so = &a->po.spot;
    const int unit_weights = so->noise.gain == 0 && so->noise.sigma_bg == 0;
    const svp_image *spot = job->spot;
    svp_status st = svp_image_new(spot->width, spot->height, &job->m1);
    if (st == SVP_OK) st = svp_image_new(spot->width, spot->height, &job->r1);
    if (st == SVP_OK) st = svp_spot_fit(spot, so, &job->single, job->m1, job->r1);
    if (st == SVP_ERR_NUMERIC && (job->single.flags & SVP_SPOT_NOT_CONVERGED)) {
        print_fit("last parameters (NOT CONVERGED)", &job->single, a->pixel_um, unit_weights);
        return cli_fail(run, st, a->spot_path);
    }
    if (st != SVP_OK) return cli_fail(run, st, a->spot_path);
    record_fit(run, "", &job->single, a->pixel_um);
    print_fit(a->spot_path, &job->single, a->pixel_um, unit_weights);
    job->chosen = &job->single;
    snprintf(job->source, sizeof job->source, "%s fit of %s", cli_psf_model_names[a->spot.model],
             a->spot_path);
    return 0;
}

/* A pair: the offset by phase correlation (a cross-check of the fitted centres, which the
 * pair method uses to centre the kernel), then the pair method's three fits. */
static int fit_psf_pair(cli_run *run, const struct fit_psf_args *a, struct fit_psf_job *job)
{
    const svp_spot_options *so = &a->po.spot;
    const int unit_weights = so->noise.gain == 0 && so->noise.sigma_bg == 0;
    const double um = a->pixel_um;
    const char *spot_path = a->spot_path, *exc_path = a->exc_path;
    svp_pair_result *pr = &job->pr;
    svp_register_options ro;
    svp_register_defaults(&ro);
    ro.contrast = SVP_CONTRAST_SAME; /* two bright spots: never a negative */
    svp_register_result rr;
    svp_status rst = svp_register(job->exc, job->spot, &ro, &rr);
    svp_status st = svp_image_new(job->spot->width, job->spot->height, &job->dec);
    if (st == SVP_OK) st = svp_psf_from_pair(job->exc, job->spot, &a->po, pr, job->dec);
    if (st != SVP_OK && !(pr->excitation.fwhm > 0 && pr->direct.fwhm > 0))
        return cli_fail(run, st,
                        st == SVP_ERR_NUMERIC || strstr(svp_last_error(), "emission") ? spot_path
                                                                                      : exc_path);
    record_fit(run, "excitation_", &pr->excitation, um);
    record_fit(run, "direct_", &pr->direct, um);
    print_fit("excitation spot I_G (direct fit)", &pr->excitation, um, unit_weights);
    print_fit("emission spot I_PL (direct fit: upper bound on the PSF width)", &pr->direct, um,
              unit_weights);
    printf("offset emission - excitation: fitted centres (%.3f, %.3f) px", pr->offset_x,
           pr->offset_y);
    cli_result_num(run, "offset_x_px", pr->offset_x);
    cli_result_num(run, "offset_y_px", pr->offset_y);
    if (rst == SVP_OK) {
        printf(", phase correlation (%.3f, %.3f) px (significance %.1f)\n", rr.shift_x, rr.shift_y,
               rr.significance);
        cli_result_num(run, "phase_offset_x_px", rr.shift_x);
        cli_result_num(run, "phase_offset_y_px", rr.shift_y);
        cli_result_num(run, "phase_significance", rr.significance);
    } else {
        printf(", phase correlation failed: %s\n", svp_last_error());
    }
    if (!pr->deconvolved_ok) {
        cli_note(run, "%s: the deconvolution failed (%s)", spot_path, svp_last_error());
        if (!a->use_direct)
            return cli_error(run,
                             "%s: no deconvolved PSF; use --use direct to write the "
                             "direct fit (upper bound) instead",
                             spot_path);
    } else {
        record_fit(run, "deconvolved_", &pr->deconvolved, um);
        char what[160];
        snprintf(what, sizeof what,
                 "PSF p = I_PL deconvolved by I_G (%d RL iterations: "
                 "lower bound on the width)",
                 a->po.iterations);
        print_fit(what, &pr->deconvolved, um, 1);
    }
    job->chosen = a->use_direct ? &pr->direct : &pr->deconvolved;
    snprintf(job->source, sizeof job->source, "%s fit of %s (%s), excitation %s, %d RL iterations",
             cli_psf_model_names[a->spot.model], spot_path,
             a->use_direct ? "direct" : "deconvolved", exc_path, a->po.iterations);
    return 0;
}

/* The figures of a pair: excitation, direct emission and (when it worked) deconvolved. */
static int fit_psf_pair_figures(cli_run *run, const struct fit_psf_args *a, struct fit_psf_job *job)
{
    const svp_spot_options *so = &a->po.spot;
    const double um = a->pixel_um;
    const char *fig_dir = job->fig_dir;
    svp_spot_result tmp;
    int code;
    if ((code = fit_with_images(run, job->exc, so, &tmp, &job->m1, &job->r1, a->exc_path)))
        return code;
    if ((code = write_figures(run, fig_dir, "excitation_", "excitation", job->exc, job->m1, job->r1,
                              &tmp, so, um)))
        return code;
    if ((code = fit_with_images(run, job->spot, so, &tmp, &job->m2, &job->r2, a->spot_path)))
        return code;
    if ((code = write_figures(run, fig_dir, "direct_", "emission", job->spot, job->m2, job->r2,
                              &tmp, so, um)))
        return code;
    if (!job->pr.deconvolved_ok) return 0;
    svp_spot_options ds = *so; /* as svp_psf_from_pair fits the deconvolved spot */
    ds.noise.sigma_bg = ds.noise.gain = ds.noise.excess = 0.0;
    ds.saturation = -1.0;
    ds.hot_pixels = 0;
    if ((code = fit_with_images(run, job->dec, &ds, &job->dfit, &job->m3, &job->r3, a->spot_path)))
        return code;
    return write_figures(run, fig_dir, "deconvolved_", "deconvolved", job->dec, job->m3, job->r3,
                         &job->dfit, &ds, um);
}

/* PSF.yaml, PSF.summary.json and the line on stdout. */
static int fit_psf_write(cli_run *run, const struct fit_psf_args *a, struct fit_psf_job *job)
{
    const svp_spot_result *chosen = job->chosen;
    char buf[64];
    int code;
    cli_stage_begin(run, "write");
    job->text = psf_file_text(chosen, a->pixel_um, job->source);
    if (!job->text) {
        cli_error(run, "out of memory");
        return CLI_EXIT_RUNTIME;
    }
    if ((code = cli_write_text(run, run->output, job->text))) return code;
    cli_stage_end(run);
    if ((code = cli_summary_write(run, job->summary_path))) return code;
    printf("svpsf fit-psf: wrote %s (FWHM %.4f um%s), %s%s%s\n", run->output,
           chosen->fwhm * a->pixel_um,
           chosen->model == SVP_PSF_MOFFAT
               ? (snprintf(buf, sizeof buf, ", beta %.3f", chosen->beta), buf)
               : "",
           job->summary_path, a->no_figures ? "" : ", figures in ",
           a->no_figures ? "" : job->fig_dir);
    return 0;
}

static void append(char *buf, size_t cap, const char *text)
{
    const size_t len = strlen(buf);
    if (len < cap) snprintf(buf + len, cap - len, "%s", text);
}

/* The fit (one spot or a pair), the flags of the written fit, the figures, the files. */
static int fit_psf_compute(cli_run *run, const struct fit_psf_args *a, struct fit_psf_job *job)
{
    int code;
    cli_stage_begin(run, "fit");
    if ((code = a->exc_path ? fit_psf_pair(run, a, job) : fit_psf_single(run, a, job))) return code;
    cli_result_str(run, "written_fit",
                   !a->exc_path    ? "spot"
                   : a->use_direct ? "direct"
                                   : "deconvolved");
    /* a parameter on its bound (not measured: its uncertainty is unknown) or a fit that does
     * not describe the data is no PSF to hand to a correction */
    const unsigned doubt =
        job->chosen->flags & (SVP_SPOT_BETA_AT_BOUND | SVP_SPOT_WIDTH_AT_BOUND | SVP_SPOT_POOR_FIT);
    cli_result_int(run, "in_doubt", doubt != 0);
    if (job->chosen->flags) {
        char buf[256];
        svp_spot_flags_describe(job->chosen->flags, buf, sizeof buf);
        if (doubt && !a->keep_doubtful) {
            char why[512] = "";
            if (doubt & SVP_SPOT_BETA_AT_BOUND)
                append(why, sizeof why, "; beta ran to its bound (a Gaussian-like spot: "
                                            "--model gaussian; else --fix-beta)");
            if (doubt & SVP_SPOT_WIDTH_AT_BOUND)
                append(why, sizeof why, "; the width ran to its bound (a spot wider than "
                                            "the image shows, or not one spot)");
            if (doubt & SVP_SPOT_POOR_FIT)
                append(why, sizeof why, "; the model does not describe the data (another "
                                            "--model, two spots, a ring, a sloped background, "
                                            "or data not in photon counts: --gain)");
            cli_error(run,
                      "%s: the fit cannot be vouched for (flags: %s)%s; nothing written "
                      "(--keep-doubtful writes it)",
                      a->spot_path, buf, why);
            return CLI_EXIT_DOUBTFUL;
        }
        cli_note(run, "%s: the written fit is flagged: %s", a->spot_path, buf);
    }
    if (a->no_figures) return 0;
    cli_stage_begin(run, "figures");
    if (a->exc_path) return fit_psf_pair_figures(run, a, job);
    return write_figures(run, job->fig_dir, "", "spot", job->spot, job->m1, job->r1, &job->single,
                         &a->po.spot, a->pixel_um);
}

static int run_fit_psf(cli_run *run, const struct fit_psf_args *a)
{
    struct fit_psf_job job;
    memset(&job, 0, sizeof job);
    int code = fit_psf_read(run, a, &job);
    if (!code) code = fit_psf_compute(run, a, &job);
    if (!code) code = fit_psf_write(run, a, &job);
    free(job.text);
    svp_image_free(job.spot);
    svp_image_free(job.exc);
    svp_image_free(job.dec);
    svp_image_free(job.m1);
    svp_image_free(job.r1);
    svp_image_free(job.m2);
    svp_image_free(job.r2);
    svp_image_free(job.m3);
    svp_image_free(job.r3);
    svp_figure_cleanup();
    return code;
}

int cmd_fit_psf(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "fit-psf", argc, argv, CLI_COMMON_OUTPUT);
    struct fit_psf_args args;
    int code = parse_fit_psf_args(&run, &args);
    if (code == 0) code = run_fit_psf(&run, &args);
    return cli_run_finish(&run, cli_parsed_status(code));
}
