/* svpsf reconstruct: source reconstruction from measured field maps (docs/model.md §11, the physics
 * section of svpsf.h): areal magnetisation from B_z, sheet current density from B_z or from
 * B_x, B_y. */
#include "cli.h"

#include "io/mat.h"
#include "figure/figure.h"

#include <limits.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

enum {
    OPT_BX = CLI_OPTION_FIRST,
    OPT_BY,
    OPT_BZ,
    OPT_QUANTITY,
    OPT_PIXEL,
    OPT_STANDOFF,
    OPT_UNIT,
    OPT_NV,
    OPT_SIDE,
    OPT_CUTOFF,
    OPT_NO_WINDOW,
    OPT_PAD,
    OPT_THICKNESS,
    OPT_METHOD,
    OPT_MAX_IT
};

static const char *const quantity_names[] = {"magnetisation", "current_from_bz", "current_from_bxy",
                                             NULL};
static const char *const unit_names[] = {"T", "mT", "uT", "nT", NULL};
static const double unit_scale[] = {1, 1e-3, 1e-6, 1e-9};
static const char *const pad_names[] = {"taper", "mean", "none", NULL};
static const char *const method_names[] = {"fourier", "support", NULL};

static void print_help(const cli_run *run, FILE *out)
{
    fputs("usage: svpsf reconstruct --quantity magnetisation --bz Bz.tif --pixel-um P\n"
          "                         --standoff-nm H -o DIR [options]\n"
          "       svpsf reconstruct --quantity current_from_bz --bz Bz.tif ...\n"
          "       svpsf reconstruct --quantity current_from_bxy --bx Bx.tif [--by By.tif] ...\n"
          "\n"
          "Source reconstruction (docs/model.md §11): the areal magnetisation\n"
          "m_z = M_z t (A) from B_z, or the sheet current density J (A/m) from B_z or from the\n"
          "in-plane field. A radial Hann window W = (1 + cos(pi k / k_c)) / 2 (k_c = 2 pi /\n"
          "standoff by default) tames the e^(kh) gain; the maps are padded (x2, tapered) against\n"
          "wrap-around. k = 0 is set to 0: by the Fourier method the mean of m_z is lost\n"
          "(restored by setting the outermost pixel ring to zero; --method support determines\n"
          "it) and a uniform current makes no B_z. Frame: x along the\n"
          "columns, y along the rows (down), z = x cross y, sensor above the sources unless\n"
          "--side below (docs/model.md).\n"
          "\n"
          "inputs (TIFF float32/16-bit, 16-bit PNG, .npy, .txt as numpy.savetxt writes them):\n"
          "  --bz FILE / --bx FILE / --by FILE   field component maps (same size)\n"
          "  --unit T|mT|uT|nT     unit of the field maps (default T)\n"
          "  --quantity magnetisation|current_from_bz|current_from_bxy   (required)\n"
          "  --pixel-um P          pixel size in the sample plane, um (required unless the\n"
          "                        map is a QDMlab .mat file holding `step`)\n"
          "  --standoff-nm H       source plane to the centre of the NV layer, nm (required\n"
          "                        unless the map is a QDMlab .mat file holding `h`)\n"
          "options:\n"
          "  -o, --output DIR      output folder, created when missing (required)\n"
          "  --nv-thickness-nm T   NV layer thickness, averaged over (default 0)\n"
          "  --side above|below    sensor side of the sources (default above)\n"
          "  --thickness-nm T      flake thickness for the magnetisation (default 0: thin film)\n"
          "  --cutoff-per-um K     window cut-off k_c, rad/um (default 2 pi / standoff)\n"
          "  --no-window           no Hann window (the gain is capped at e^700)\n"
          "  --pad taper|mean|none padding of the maps before the FFT (default taper)\n"
          "  --method fourier|support   magnetisation: fourier divides the padded map's\n"
          "                        spectrum (default); support finds the m_z on the view\n"
          "                        (zero outside it) whose field fits B_z on the view in least\n"
          "                        squares (conjugate gradients, then the window): an edge\n"
          "                        pixel's error stays local and the mean is determined, no\n"
          "                        border shift; about 15-40x the Fourier method's time\n"
          "  --max-iterations N    support: conjugate-gradient cap (default 200); a solve that\n"
          "                        does not converge exits 3 and writes nothing\n",
          out);
    cli_print_common_help(run, out);
    fputs("\n"
          "outputs in DIR: m_z.EXT (A) or J_x.EXT, J_y.EXT, J_norm.EXT (A/m), a figure of each\n"
          "(.png, diverging colour map centred on zero, colour bar in mA or A/m, scale bar),\n"
          "summary.json (inputs, settings, mean/peak values, timings).\n",
          out);
}

static int figure(cli_run *run, const char *dir, const char *name, const svp_image *img,
                  double scale, const char *label, double pixel_um, int diverging)
{
    char path[4096], title[256];
    snprintf(path, sizeof path, "%s/%s.png", dir, name);
    size_t n = (size_t)img->width * img->height;
    double m = 0, lo = 0;
    for (size_t i = 0; i < n; i++)
        if (isfinite(img->data[i])) m = fmax(m, fabs(img->data[i]) * scale);
    if (diverging) lo = -m;
    snprintf(title, sizeof title, "%s (svpsf reconstruct)", label);
    char bar[128];
    snprintf(bar, sizeof bar, "%s", label);
    svp_status st =
        svp_figure_map(path, img, scale, lo, m, diverging, title, bar, pixel_um, run->force);
    return st == SVP_OK ? 0 : cli_fail(run, st, path);
}

struct reconstruct_args {
    const char *paths[3]; /* --bx, --by, --bz */
    int quantity;         /* index in quantity_names, -1 when not given */
    int unit, side, pad, window, method, max_iterations;
    double pixel_um, standoff_nm, nv_nm, cutoff, thickness_nm;
};

/* What a run holds (released by run_reconstruct). */
struct reconstruct_job {
    svp_image *b[3], *out[3];
    const char *out_path[3], *names[3], *summary;
    int n_out, w, h;
    svp_recon_options o;
};

static int reconstruct_option(cli_run *run, struct reconstruct_args *a, int c)
{
    switch (c) {
    case OPT_BX: a->paths[0] = optarg; return 0;
    case OPT_BY: a->paths[1] = optarg; return 0;
    case OPT_BZ: a->paths[2] = optarg; return 0;
    case OPT_QUANTITY:
        return cli_parse_choice(run, "--quantity", optarg, quantity_names, &a->quantity);
    case OPT_UNIT: return cli_parse_choice(run, "--unit", optarg, unit_names, &a->unit);
    case OPT_SIDE: {
        static const char *const sides[] = {"above", "below", NULL};
        return cli_parse_choice(run, "--side", optarg, sides, &a->side);
    }
    case OPT_PAD: return cli_parse_choice(run, "--pad", optarg, pad_names, &a->pad);
    case OPT_NO_WINDOW: a->window = 0; return 0;
    case OPT_METHOD: return cli_parse_choice(run, "--method", optarg, method_names, &a->method);
    case OPT_MAX_IT:
        return cli_parse_int(run, "--max-iterations", optarg, 1, 100000, &a->max_iterations);
    case OPT_PIXEL:
    case OPT_STANDOFF:
    case OPT_NV:
    case OPT_CUTOFF:
    case OPT_THICKNESS: {
        const char *names[] = {"--pixel-um", "--standoff-nm", "--nv-thickness-nm",
                               "--cutoff-per-um", "--thickness-nm"};
        double *targets[] = {&a->pixel_um, &a->standoff_nm, &a->nv_nm, &a->cutoff,
                             &a->thickness_nm};
        int k = c == OPT_PIXEL      ? 0
                : c == OPT_STANDOFF ? 1
                : c == OPT_NV       ? 2
                : c == OPT_CUTOFF   ? 3
                                    : 4;
        /* pixel, standoff and cutoff > 0; the thicknesses >= 0 */
        return cli_parse_double_in(run, names[k], optarg, 0, k == 2 || k == 4, INFINITY, 0,
                                   targets[k]);
    }
    default: return cli_error(run, "internal: option %d", c);
    }
}

/* Which maps the quantity takes. */
static int reconstruct_check_maps(const cli_run *run, const struct reconstruct_args *a)
{
    const char *const *paths = a->paths;
    const int quantity = a->quantity;
    if (quantity < 0)
        return cli_error(run, "--quantity is required: magnetisation, current_from_bz or "
                              "current_from_bxy");
    if (quantity < 2 && !paths[2])
        return cli_error(run, "--quantity %s needs --bz", quantity_names[quantity]);
    if (quantity < 2 && (paths[0] || paths[1]))
        return cli_error(run, "--quantity %s uses --bz only (drop --bx, --by)",
                         quantity_names[quantity]);
    if (quantity == 2 && !paths[0] && !paths[1])
        return cli_error(run, "--quantity current_from_bxy needs --bx and/or --by");
    if (quantity > 0 && a->method != 0)
        return cli_error(run, "--method support finds magnetisation only (drop --method for "
                              "--quantity %s: the current uses the Fourier method)",
                         quantity_names[quantity]);
    if (a->max_iterations && a->method == 0)
        return cli_error(run, "--max-iterations applies to --method support only");
    if (quantity == 2 && paths[2])
        return cli_error(run, "--quantity current_from_bxy uses --bx, --by (drop --bz, or use "
                              "current_from_bz)");
    return 0;
}

/* The pixel size and the stand-off: the options, else what a QDMlab Bz file (.mat) holds
 * (`step`, `h`; docs/cli.md, MATLAB / QDMlab files), else an error naming the option. info[k]:
 * what reading map k found beside it (zeros for other formats), so that each file is read
 * once. */
static int reconstruct_geometry(cli_run *run, struct reconstruct_args *a,
                                    const svp_mat_info info[3])
{
    const char *odd_step = NULL; /* a file whose `step` is not one pixel size */
    int odd_n = 0;
    for (int k = 0; k < 3 && !(a->pixel_um > 0 && a->standoff_nm > 0); k++) {
        if (!a->paths[k]) continue;
        if (!(a->pixel_um > 0) && info[k].pixel_um > 0) a->pixel_um = info[k].pixel_um;
        if (info[k].step_elements > 0 && !(info[k].pixel_um > 0) && !odd_step) {
            odd_step = a->paths[k];
            odd_n = info[k].step_elements;
        }
        if (!(a->standoff_nm > 0) && info[k].standoff_um > 0)
            a->standoff_nm = info[k].standoff_um * 1e3;
    }
    if (!(a->pixel_um > 0) && odd_step && odd_n == 1)
        return cli_error(run, "--pixel-um is required: %s holds `step`, but not as a real number",
                         odd_step);
    if (!(a->pixel_um > 0) && odd_step)
        return cli_error(run,
                         "--pixel-um is required: %s holds `step` with %d elements, not one "
                         "pixel size (one number, or [dx dy] of square pixels)",
                         odd_step, odd_n);
    if (!(a->pixel_um > 0))
        return cli_error(run, "--pixel-um is required (the map file holds no pixel size)");
    if (!(a->standoff_nm > 0))
        return cli_error(run, "--standoff-nm is required (the map file holds no stand-off)");
    return 0;
}

static int parse_reconstruct_args(cli_run *run, struct reconstruct_args *a)
{
    static const struct option own[] = {
        {"bx", required_argument, NULL, OPT_BX},
        {"by", required_argument, NULL, OPT_BY},
        {"bz", required_argument, NULL, OPT_BZ},
        {"quantity", required_argument, NULL, OPT_QUANTITY},
        {"pixel-um", required_argument, NULL, OPT_PIXEL},
        {"standoff-nm", required_argument, NULL, OPT_STANDOFF},
        {"unit", required_argument, NULL, OPT_UNIT},
        {"nv-thickness-nm", required_argument, NULL, OPT_NV},
        {"side", required_argument, NULL, OPT_SIDE},
        {"cutoff-per-um", required_argument, NULL, OPT_CUTOFF},
        {"no-window", no_argument, NULL, OPT_NO_WINDOW},
        {"pad", required_argument, NULL, OPT_PAD},
        {"thickness-nm", required_argument, NULL, OPT_THICKNESS},
        {"method", required_argument, NULL, OPT_METHOD},
        {"max-iterations", required_argument, NULL, OPT_MAX_IT},
        {NULL, 0, NULL, 0},
    };
    memset(a, 0, sizeof *a);
    a->quantity = -1;
    a->window = 1;
    int c;
    while ((c = cli_next_option(run, own)) != CLI_OPTIONS_DONE) {
        if (c == CLI_OPTION_HELP) {
            print_help(run, stdout);
            return CLI_OPTION_HELP;
        }
        if (c == CLI_OPTION_ERROR || reconstruct_option(run, a, c)) return CLI_EXIT_USAGE;
    }
    if (optind < run->argc)
        return cli_error(run, "unexpected argument '%s' (maps are given with --bx, --by, --bz)",
                         run->argv[optind]);
    int code;
    if ((code = reconstruct_check_maps(run, a))) return code;
    if (!run->output) return cli_error(run, "-o DIR is required");
    return 0;
}

/* The maps (in tesla, all one size), the outputs planned, the sensor checked, the settings. */
static int reconstruct_read(cli_run *run, struct reconstruct_args *a,
                            struct reconstruct_job *job)
{
    svp_mat_info info[3];
    memset(info, 0, sizeof info);
    static const char *const roles[3] = {"bx", "by", "bz"};
    const svp_image *first = NULL;
    const char *first_path = NULL, *first_role = NULL;
    int code;
    cli_stage_begin(run, "read");
    for (int k = 0; k < 3; k++) {
        svp_image **b = &job->b[k];
        if (!a->paths[k]) continue;
        if ((code = cli_read_image_info(run, roles[k], a->paths[k], b, &info[k]))) return code;
        /* the Fourier method needs every pixel: named here, with what to do */
        const size_t n_bad = svp_image_count_nonfinite(*b);
        if (n_bad) {
            size_t first_bad = 0;
            while (isfinite((*b)->data[first_bad])) first_bad++;
            return cli_error(run,
                             "%s: %zu NaN or Inf pixel%s (the first at x %zu, y %zu): the Fourier "
                             "reconstruction needs a complete map; svpsf correct treats them as "
                             "missing data and writes none, or fill them first",
                             a->paths[k], n_bad, n_bad == 1 ? "" : "s",
                             first_bad % (size_t)(*b)->width, first_bad / (size_t)(*b)->width);
        }
        for (size_t i = 0; i < (size_t)(*b)->width * (*b)->height; i++)
            (*b)->data[i] *= unit_scale[a->unit];
        if (first && (code = cli_check_same_size(run, first, first_role, first_path, *b, roles[k],
                                                 a->paths[k])))
            return code;
        if (!first) first = *b, first_path = a->paths[k], first_role = roles[k];
    }
    if ((code = reconstruct_geometry(run, a, info))) return code;
    job->w = first->width;
    job->h = first->height;
    if (a->quantity == 0) {
        job->names[0] = "m_z";
        job->n_out = 1;
    } else {
        job->names[0] = "J_x", job->names[1] = "J_y", job->names[2] = "J_norm";
        job->n_out = 3;
    }
    for (int k = 0; k < job->n_out; k++)
        job->out_path[k] = cli_output_in_dir(run, job->names[k], job->names[k], 1);
    char fig[3][64];
    for (int k = 0; k < job->n_out; k++) {
        snprintf(fig[k], sizeof fig[k], "%s.png", job->names[k]);
        cli_output_in_dir(run, fig[k], fig[k], 0);
    }
    job->summary = cli_output_in_dir(run, "summary", "summary.json", 0);
    return cli_outputs_check(run);
}

/* The sensor and the reconstruction's options from the arguments; the settings recorded. */
static int reconstruct_options(cli_run *run, const struct reconstruct_args *a,
                               struct reconstruct_job *job)
{
    svp_recon_options *o = &job->o;
    svp_recon_defaults(o);
    o->sensor.pixel_m = a->pixel_um * 1e-6;
    o->sensor.standoff_m = a->standoff_nm * 1e-9;
    o->sensor.nv_thickness_m = a->nv_nm * 1e-9;
    o->sensor.side = a->side ? -1 : 1;
    o->cutoff = a->cutoff * 1e6;
    o->window = a->window;
    o->pad = (svp_pad_mode)a->pad;
    o->source_thickness_m = a->thickness_nm * 1e-9;
    o->method = a->method ? SVP_RECON_SUPPORT : SVP_RECON_FOURIER;
    if (a->max_iterations) o->max_iterations = a->max_iterations;
    svp_status st = svp_sensor_validate(&o->sensor);
    if (st != SVP_OK) return cli_fail(run, st, NULL);
    cli_setting_str(run, "quantity", quantity_names[a->quantity]);
    cli_setting_str(run, "unit", unit_names[a->unit]);
    cli_setting_num(run, "pixel_um", a->pixel_um);
    cli_setting_num(run, "standoff_nm", a->standoff_nm);
    cli_setting_num(run, "nv_thickness_nm", a->nv_nm);
    cli_setting_str(run, "side", a->side ? "below" : "above");
    cli_setting_num(run, "cutoff_per_um",
                    a->cutoff > 0 ? a->cutoff : 2 * M_PI / (a->standoff_nm * 1e-3));
    cli_setting_int(run, "window", a->window);
    cli_setting_str(run, "pad", pad_names[a->pad]);
    cli_setting_str(run, "method", method_names[a->method]);
    if (a->method) cli_setting_int(run, "max_iterations", o->max_iterations);
    return 0;
}

/* The source maps, |J|, and each map's mean and peak. */
static int reconstruct_compute(cli_run *run, const struct reconstruct_args *a,
                               struct reconstruct_job *job)
{
    const int w = job->w, h = job->h;
    svp_image **b = job->b, **out = job->out;
    svp_status st = SVP_OK;
    cli_stage_begin(run, "reconstruct");
    for (int k = 0; k < job->n_out && st == SVP_OK; k++) st = svp_image_new(w, h, &out[k]);
    if (st == SVP_OK) {
        if (a->quantity == 0) {
            svp_recon_report rep;
            st = svp_reconstruct_magnetisation_report(b[2], &job->o, out[0], &rep);
            if (a->method) {
                cli_result_int(run, "cg_iterations", rep.iterations);
                cli_result_num(run, "cg_residual", rep.residual);
            }
        }
        else if (a->quantity == 1)
            st = svp_reconstruct_current_from_bz(b[2], &job->o, out[0], out[1]);
        else
            st = svp_reconstruct_current_from_bxy(b[0], b[1], &job->o, b[1] ? out[0] : NULL,
                                                  b[0] ? out[1] : NULL);
    }
    if (st != SVP_OK) /* the library names the map's role (bz, bx, by); this, its file */
        return cli_fail(run, st, a->paths[2] ? a->paths[2] : a->paths[0] ? a->paths[0]
                                                                           : a->paths[1]);
    if (a->quantity > 0)
        for (size_t i = 0; i < (size_t)w * h; i++)
            out[2]->data[i] = hypot(out[0]->data[i], out[1]->data[i]);
    for (int k = 0; k < job->n_out; k++) {
        double mean = 0, peak = 0;
        for (size_t i = 0; i < (size_t)w * h; i++) {
            mean += out[k]->data[i];
            peak = fmax(peak, fabs(out[k]->data[i]));
        }
        char key[64];
        snprintf(key, sizeof key, "%s_mean", job->names[k]);
        cli_result_num(run, key, mean / ((double)w * h));
        snprintf(key, sizeof key, "%s_peak_abs", job->names[k]);
        cli_result_num(run, key, peak);
    }
    return 0;
}

/* Each map and its figure, summary.json, the line on stdout. */
static int reconstruct_write(cli_run *run, const struct reconstruct_args *a,
                             struct reconstruct_job *job)
{
    int code;
    cli_stage_begin(run, "write");
    for (int k = 0; k < job->n_out; k++) {
        if ((code = cli_write_image(run, job->out_path[k], job->out[k]))) return code;
        int is_norm = k == 2;
        char label[64];
        snprintf(label, sizeof label, "%s (%s)", job->names[k], a->quantity == 0 ? "mA" : "A/m");
        if ((code = figure(run, run->output, job->names[k], job->out[k], a->quantity == 0 ? 1e3 : 1,
                           label, a->pixel_um, !is_norm)))
            return code;
    }
    cli_stage_end(run);
    if ((code = cli_summary_write(run, job->summary))) return code;
    printf("svpsf reconstruct: %s from %d x %d map%s (pixel %g um, standoff %g nm) written to %s\n",
           quantity_names[a->quantity], job->w, job->h,
           a->quantity == 2 && job->b[0] && job->b[1] ? "s" : "", a->pixel_um, a->standoff_nm,
           run->output);
    return 0;
}

static int run_reconstruct(cli_run *run, struct reconstruct_args *a)
{
    struct reconstruct_job job;
    memset(&job, 0, sizeof job);
    int code = reconstruct_read(run, a, &job);
    if (!code) code = reconstruct_options(run, a, &job);
    if (!code) code = reconstruct_compute(run, a, &job);
    if (!code) code = reconstruct_write(run, a, &job);
    for (int k = 0; k < 3; k++) {
        svp_image_free(job.b[k]);
        svp_image_free(job.out[k]);
    }
    svp_figure_cleanup(); /* cairo's font caches: a clean exit for leak checkers */
    return code;
}

int cmd_reconstruct(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "reconstruct", argc, argv, CLI_COMMON_OUTPUT_DIR);
    run.fft_measure = 0;
    struct reconstruct_args args;
    int code = parse_reconstruct_args(&run, &args);
    if (code == 0) code = run_reconstruct(&run, &args);
    return cli_run_finish(&run, cli_parsed_status(code));
}
