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
    OPT_MODEL,
    OPT_ITERATIONS,
    OPT_CIRCULAR,
    OPT_FIX_BETA,
    OPT_GAIN,
    OPT_SIGMA_BG,
    OPT_SATURATION,
    OPT_REFUSE_BORDER,
    OPT_FIGURES,
    OPT_NO_FIGURES,
    OPT_USE,
    OPT_MAX_ITER
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
          "  --excitation SPOT_G   the excitation spot of the pair (same size as SPOT)\n"
          "  --model M             moffat (default), gaussian or lorentzian\n"
          "  --iterations N        Richardson-Lucy iterations of the pair method (default 75)\n"
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
          "does not converge (the last parameters are printed, nothing is written).\n",
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

int cmd_fit_psf(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "fit-psf", argc, argv, CLI_COMMON_OUTPUT);
    static const struct option own[] = {
        {"excitation", required_argument, NULL, OPT_EXCITATION},
        {"pixel-um", required_argument, NULL, OPT_PIXEL_UM},
        {"model", required_argument, NULL, OPT_MODEL},
        {"iterations", required_argument, NULL, OPT_ITERATIONS},
        {"circular", no_argument, NULL, OPT_CIRCULAR},
        {"fix-beta", required_argument, NULL, OPT_FIX_BETA},
        {"gain", required_argument, NULL, OPT_GAIN},
        {"sigma-bg", required_argument, NULL, OPT_SIGMA_BG},
        {"saturation", required_argument, NULL, OPT_SATURATION},
        {"refuse-border", no_argument, NULL, OPT_REFUSE_BORDER},
        {"figures", required_argument, NULL, OPT_FIGURES},
        {"no-figures", no_argument, NULL, OPT_NO_FIGURES},
        {"use", required_argument, NULL, OPT_USE},
        {"max-iterations", required_argument, NULL, OPT_MAX_ITER},
        {NULL, 0, NULL, 0},
    };
    svp_pair_options po;
    svp_pair_defaults(&po);
    svp_spot_options *so = &po.spot;
    const char *exc_path = NULL, *figures = NULL;
    double pixel_um = 0;
    int no_figures = 0, model = SVP_PSF_MOFFAT, use_direct = 0;
    svp_image *spot = NULL, *exc = NULL, *dec = NULL, *m1 = NULL, *r1 = NULL, *m2 = NULL,
              *r2 = NULL, *m3 = NULL, *r3 = NULL;
    char *text = NULL;
    int code = 0;
    svp_status st;

    int c;
    while ((c = cli_next_option(&run, own)) != CLI_OPTIONS_DONE) {
        int bad = 0;
        switch (c) {
        case CLI_OPTION_HELP: print_help(&run, stdout); return cli_run_finish(&run, 0);
        case CLI_OPTION_ERROR: return cli_run_finish(&run, CLI_EXIT_USAGE);
        case OPT_EXCITATION: exc_path = optarg; break;
        case OPT_PIXEL_UM:
            bad = cli_parse_double_in(&run, "--pixel-um", optarg, SVP_PIXEL_UM_MIN, 1, INFINITY,
                                      0, &pixel_um);
            break;
        case OPT_MODEL:
            bad = cli_parse_choice(&run, "--model", optarg, cli_psf_model_names, &model);
            break;
        case OPT_ITERATIONS:
            bad = cli_parse_int(&run, "--iterations", optarg, 1, 100000, &po.iterations);
            break;
        case OPT_CIRCULAR: so->elliptical = 0; break;
        case OPT_FIX_BETA:
            if (cli_parse_double_in(&run, "--fix-beta", optarg, 0, 0, INFINITY, 0, &so->beta))
                return cli_run_finish(&run, CLI_EXIT_USAGE);
            so->fix_beta = 1;
            break;
        case OPT_GAIN:
            bad = cli_parse_double_in(&run, "--gain", optarg, 0, 1, INFINITY, 0, &so->noise.gain);
            break;
        case OPT_SIGMA_BG:
            bad = cli_parse_double_in(&run, "--sigma-bg", optarg, 0, 1, INFINITY, 0,
                                      &so->noise.sigma_bg);
            break;
        case OPT_SATURATION:
            bad = cli_parse_double_in(&run, "--saturation", optarg, 0, 0, INFINITY, 0,
                                      &so->saturation);
            break;
        case OPT_REFUSE_BORDER: so->refuse_near_border = 1; break;
        case OPT_MAX_ITER:
            bad =
                cli_parse_int(&run, "--max-iterations", optarg, 1, 100000, &so->lm.max_iterations);
            break;
        case OPT_FIGURES: figures = optarg; break;
        case OPT_NO_FIGURES: no_figures = 1; break;
        case OPT_USE: {
            static const char *const uses[] = {"deconvolved", "direct", NULL};
            bad = cli_parse_choice(&run, "--use", optarg, uses, &use_direct);
            break;
        }
        default: return cli_run_finish(&run, cli_error(&run, "internal: option %d", c));
        }
        if (bad) return cli_run_finish(&run, CLI_EXIT_USAGE);
    }
    if (optind >= argc)
        return cli_run_finish(&run,
                              cli_error(&run, "the spot image SPOT is required (see --help)"));
    if (optind + 1 < argc)
        return cli_run_finish(&run, cli_error(&run, "unexpected argument '%s'", argv[optind + 1]));
    const char *spot_path = argv[optind];
    if (!(pixel_um > 0)) return cli_run_finish(&run, cli_error(&run, "--pixel-um P is required"));
    if (!run.output) return cli_run_finish(&run, cli_error(&run, "-o PSF.yaml is required"));
    if (!cli_yaml_extension(run.output))
        return cli_run_finish(&run, cli_error(&run, "-o %s: the PSF file must end in .yaml or .yml",
                                              run.output));
    if (figures && no_figures)
        return cli_run_finish(&run, cli_error(&run, "--figures and --no-figures contradict"));
    if (!exc_path && use_direct)
        return cli_run_finish(&run, cli_error(&run, "--use needs --excitation (a pair)"));
    so->model = (svp_psf_model)model;
    if (model != SVP_PSF_MOFFAT && so->fix_beta)
        return cli_run_finish(&run, cli_error(&run, "--fix-beta applies to --model moffat only"));

    /* inputs, then every output planned and checked before any work */
    cli_stage_begin(&run, "read");
    if ((code = cli_read_image(&run, exc_path ? "emission" : "spot", spot_path, &spot)))
        goto cleanup;
    if (exc_path) {
        if ((code = cli_read_image(&run, "excitation", exc_path, &exc))) goto cleanup;
        if ((code = cli_check_same_size(&run, spot, "emission", spot_path, exc, "excitation",
                                        exc_path)))
            goto cleanup;
    }
    char summary_path[4096], fig_dir[4096], buf[8448];
    cli_path_sibling(run.output, ".summary.json", summary_path, sizeof summary_path);
    if (figures)
        snprintf(fig_dir, sizeof fig_dir, "%s", figures);
    else
        cli_path_sibling(run.output, ".figures", fig_dir, sizeof fig_dir);
    cli_output_file(&run, "psf", run.output);
    cli_output_file(&run, "summary", summary_path);
    if (!no_figures) {
        static const char *const names[] = {"spot", "model", "residual", "profile"};
        static const char *const prefixes[] = {"", "excitation_", "direct_", "deconvolved_"};
        for (int p = exc_path ? 1 : 0; p < (exc_path ? 4 : 1); p++)
            for (int k = 0; k < 4; k++) {
                snprintf(buf, sizeof buf, "%s/%s%s.png", fig_dir, prefixes[p], names[k]);
                cli_output_file(&run, "figure", buf);
            }
    }
    if ((code = cli_outputs_check(&run))) goto cleanup;
    cli_setting_num(&run, "pixel_um", pixel_um);
    cli_setting_str(&run, "model", cli_psf_model_names[model]);
    cli_setting_int(&run, "elliptical", so->elliptical);
    if (so->fix_beta) cli_setting_num(&run, "fixed_beta", so->beta);
    cli_setting_num(&run, "gain", so->noise.gain);
    cli_setting_num(&run, "sigma_bg", so->noise.sigma_bg);
    if (exc_path) cli_setting_int(&run, "rl_iterations", po.iterations);

    const double um = pixel_um;
    const svp_spot_result *chosen = NULL;
    svp_spot_result single, dfit;
    svp_pair_result pr;
    memset(&pr, 0, sizeof pr);
    char source[512];
    cli_stage_begin(&run, "fit");
    if (!exc_path) {
        st = svp_image_new(spot->width, spot->height, &m1);
        if (st == SVP_OK) st = svp_image_new(spot->width, spot->height, &r1);
        if (st == SVP_OK) st = svp_spot_fit(spot, so, &single, m1, r1);
        if (st == SVP_ERR_NUMERIC && (single.flags & SVP_SPOT_NOT_CONVERGED)) {
            print_fit("last parameters (NOT CONVERGED)", &single, um,
                      so->noise.gain == 0 && so->noise.sigma_bg == 0);
            code = cli_fail(&run, st, spot_path);
            goto cleanup;
        }
        if (st != SVP_OK) {
            code = cli_fail(&run, st, spot_path);
            goto cleanup;
        }
        record_fit(&run, "", &single, um);
        print_fit(spot_path, &single, um, so->noise.gain == 0 && so->noise.sigma_bg == 0);
        chosen = &single;
        snprintf(source, sizeof source, "%s fit of %s", cli_psf_model_names[model], spot_path);
    } else {
        /* offset by phase correlation (a cross-check of the fitted centres, which the pair
         * method uses to centre the kernel) */
        svp_register_options ro;
        svp_register_defaults(&ro);
        ro.contrast = SVP_CONTRAST_SAME; /* two bright spots: never a negative */
        svp_register_result rr;
        svp_status rst = svp_register(exc, spot, &ro, &rr);
        st = svp_image_new(spot->width, spot->height, &dec);
        if (st == SVP_OK) st = svp_psf_from_pair(exc, spot, &po, &pr, dec);
        if (st != SVP_OK && !(pr.excitation.fwhm > 0 && pr.direct.fwhm > 0)) {
            code =
                cli_fail(&run, st,
                         st == SVP_ERR_NUMERIC || strstr(svp_last_error(), "emission") ? spot_path
                                                                                       : exc_path);
            goto cleanup;
        }
        record_fit(&run, "excitation_", &pr.excitation, um);
        record_fit(&run, "direct_", &pr.direct, um);
        print_fit("excitation spot I_G (direct fit)", &pr.excitation, um,
                  so->noise.gain == 0 && so->noise.sigma_bg == 0);
        print_fit("emission spot I_PL (direct fit: upper bound on the PSF width)", &pr.direct, um,
                  so->noise.gain == 0 && so->noise.sigma_bg == 0);
        printf("offset emission - excitation: fitted centres (%.3f, %.3f) px", pr.offset_x,
               pr.offset_y);
        cli_result_num(&run, "offset_x_px", pr.offset_x);
        cli_result_num(&run, "offset_y_px", pr.offset_y);
        if (rst == SVP_OK) {
            printf(", phase correlation (%.3f, %.3f) px (significance %.1f)\n", rr.shift_x,
                   rr.shift_y, rr.significance);
            cli_result_num(&run, "phase_offset_x_px", rr.shift_x);
            cli_result_num(&run, "phase_offset_y_px", rr.shift_y);
            cli_result_num(&run, "phase_significance", rr.significance);
        } else {
            printf(", phase correlation failed: %s\n", svp_last_error());
        }
        if (!pr.deconvolved_ok) {
            cli_note(&run, "%s: the deconvolution failed (%s)", spot_path, svp_last_error());
            if (!use_direct) {
                code = cli_error(&run,
                                 "%s: no deconvolved PSF; use --use direct to write the "
                                 "direct fit (upper bound) instead",
                                 spot_path);
                goto cleanup;
            }
        } else {
            record_fit(&run, "deconvolved_", &pr.deconvolved, um);
            char what[160];
            snprintf(what, sizeof what,
                     "PSF p = I_PL deconvolved by I_G (%d RL iterations: "
                     "lower bound on the width)",
                     po.iterations);
            print_fit(what, &pr.deconvolved, um, 1);
        }
        chosen = use_direct ? &pr.direct : &pr.deconvolved;
        snprintf(source, sizeof source, "%s fit of %s (%s), excitation %s, %d RL iterations",
                 cli_psf_model_names[model], spot_path, use_direct ? "direct" : "deconvolved",
                 exc_path, po.iterations);
    }
    cli_result_str(&run, "written_fit", !exc_path ? "spot" : use_direct ? "direct" : "deconvolved");
    if (chosen->flags)
        cli_note(&run, "%s: the written fit is flagged: %s", spot_path,
                 (svp_spot_flags_describe(chosen->flags, buf, sizeof buf), buf));

    if (!no_figures) {
        cli_stage_begin(&run, "figures");
        if (!exc_path) {
            if ((code = write_figures(&run, fig_dir, "", "spot", spot, m1, r1, &single, so, um)))
                goto cleanup;
        } else {
            svp_spot_result tmp;
            if ((code = fit_with_images(&run, exc, so, &tmp, &m1, &r1, exc_path))) goto cleanup;
            if ((code = write_figures(&run, fig_dir, "excitation_", "excitation", exc, m1, r1, &tmp,
                                      so, um)))
                goto cleanup;
            if ((code = fit_with_images(&run, spot, so, &tmp, &m2, &r2, spot_path))) goto cleanup;
            if ((code = write_figures(&run, fig_dir, "direct_", "emission", spot, m2, r2, &tmp, so,
                                      um)))
                goto cleanup;
            if (pr.deconvolved_ok) {
                svp_spot_options ds = *so; /* as svp_psf_from_pair fits the deconvolved spot */
                ds.noise.sigma_bg = ds.noise.gain = ds.noise.excess = 0.0;
                ds.saturation = -1.0;
                ds.hot_pixels = 0;
                if ((code = fit_with_images(&run, dec, &ds, &dfit, &m3, &r3, spot_path)))
                    goto cleanup;
                if ((code = write_figures(&run, fig_dir, "deconvolved_", "deconvolved", dec, m3, r3,
                                          &dfit, &ds, um)))
                    goto cleanup;
            }
        }
    }

    cli_stage_begin(&run, "write");
    text = psf_file_text(chosen, um, source);
    if (!text) {
        cli_error(&run, "out of memory");
        code = CLI_EXIT_RUNTIME;
        goto cleanup;
    }
    if ((code = cli_write_text(&run, run.output, text))) goto cleanup;
    cli_stage_end(&run);
    if ((code = cli_summary_write(&run, summary_path))) goto cleanup;
    printf("svpsf fit-psf: wrote %s (FWHM %.4f um%s), %s%s%s\n", run.output, chosen->fwhm * um,
           chosen->model == SVP_PSF_MOFFAT
               ? (snprintf(buf, sizeof buf, ", beta %.3f", chosen->beta), buf)
               : "",
           summary_path, no_figures ? "" : ", figures in ", no_figures ? "" : fig_dir);

cleanup:
    free(text);
    svp_image_free(spot);
    svp_image_free(exc);
    svp_image_free(dec);
    svp_image_free(m1);
    svp_image_free(r1);
    svp_image_free(m2);
    svp_image_free(r2);
    svp_image_free(m3);
    svp_image_free(r3);
    svp_figure_cleanup();
    return cli_run_finish(&run, code);
}
