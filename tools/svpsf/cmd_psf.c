/* svpsf psf: render a PSF file's kernel to an image and describe it (widths, encircled
 * energy). */
#include "cli.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

enum { OPT_SIZE = CLI_OPTION_FIRST };

#define DEFAULT_MAX_SIZE 2049

static void print_help(const cli_run *run, FILE *out)
{
    fputs("usage: svpsf psf PSF.yaml -o KERNEL [--size N] [options]\n"
          "\n"
          "Renders the core kernel of a YAML PSF file (docs/cli.md) to an image, normalised to\n"
          "unit sum over the rendered N x N pixels with the centre at the middle pixel, and\n"
          "prints the model, FWHM (um and px), r0, beta, halo and the radii holding 50, 80, 90\n"
          "and 95 % of the core's light. The halo is never part of the kernel image (it is\n"
          "spread evenly over the field of view).\n"
          "\n"
          "  PSF.yaml              the PSF file\n"
          "  -o, --output KERNEL   the kernel image; .tif, .npy, .txt or .mat[:VAR] (required)\n"
          "  --size N              odd kernel side in pixels, 1..16385 (default: 2 ceil(support)\n"
          "                        + 1 when the file sets a support; else the diameter holding\n"
          "                        99 % of the light, 2 ceil(r99) + 1; for beta <= 1, whose\n"
          "                        light over the plane diverges, 2 ceil(10 FWHM) + 1; the\n"
          "                        default is at most 2049, a larger kernel needs --size)\n",
          out);
    cli_print_common_help(run, out);
}

static const char *model_title(svp_psf_model m)
{
    switch (m) {
    case SVP_PSF_GAUSSIAN: return "Gaussian";
    case SVP_PSF_LORENTZIAN: return "Lorentzian (Moffat beta = 1)";
    case SVP_PSF_MOFFAT: return "Moffat";
    }
    return "?";
}

struct psf_args {
    const char *psf_path; /* PSF.yaml */
    int size;             /* --size; 0 = chosen from the PSF */
};

/* The default kernel side (2 r + 1) and the rule that chose it. */
static int default_size(const svp_psf *p, const char **size_rule)
{
    const double beta = p->model == SVP_PSF_LORENTZIAN ? 1.0 : p->beta;
    const int converges = p->model == SVP_PSF_GAUSSIAN || beta > 1;
    const double fwhm_max = p->fwhm_minor > p->fwhm ? p->fwhm_minor : p->fwhm;
    double r;
    if (p->support > 0) {
        r = ceil(p->support);
        *size_rule = "the support";
    } else if (converges) {
        svp_psf circ = *p;
        circ.fwhm = fwhm_max;
        circ.fwhm_minor = 0;
        if (svp_psf_encircled_radius(&circ, 0.99, 0, &r) != SVP_OK) r = 10 * fwhm_max;
        r = ceil(r);
        *size_rule = "99 % of the light";
    } else {
        r = ceil(10 * fwhm_max);
        *size_rule = "10 x FWHM (beta <= 1)";
    }
    if (2 * r + 1 > DEFAULT_MAX_SIZE) {
        r = (DEFAULT_MAX_SIZE - 1) / 2;
        *size_rule = "the default maximum";
    }
    return 2 * (int)r + 1;
}

static int parse_psf_args(cli_run *run, struct psf_args *a)
{
    static const struct option own[] = {
        {"size", required_argument, NULL, OPT_SIZE},
        {NULL, 0, NULL, 0},
    };
    memset(a, 0, sizeof *a);
    int c;
    while ((c = cli_next_option(run, own)) != CLI_OPTIONS_DONE) {
        switch (c) {
        case CLI_OPTION_HELP: print_help(run, stdout); return CLI_OPTION_HELP;
        case CLI_OPTION_ERROR: return CLI_EXIT_USAGE;
        case OPT_SIZE:
            if (cli_parse_int(run, "--size", optarg, 1, 16385, &a->size)) return CLI_EXIT_USAGE;
            if (a->size % 2 == 0)
                return cli_error(run,
                                 "--size %d: the size must be odd so that the centre is the "
                                 "middle pixel",
                                 a->size);
            break;
        default: return cli_error(run, "internal: option %d", c);
        }
    }
    a->psf_path = cli_one_argument(run, "the PSF file is required (see --help)", "");
    if (!a->psf_path) return CLI_EXIT_USAGE;
    if (!run->output) return cli_error(run, "-o KERNEL is required");
    svp_file_format format = cli_format_of_path(run->output);
    if (format == SVP_FORMAT_AUTO || format == SVP_FORMAT_PNG16)
        return cli_error(run, "-o %s: use a .tif, .npy, .txt or .mat name", run->output);
    return 0;
}

/* The PSF's description on stdout: model, widths, beta, halo, support. */
static void describe_psf(const char *psf_path, const svp_psf *p, double um)
{
    const double beta = p->model == SVP_PSF_LORENTZIAN ? 1.0 : p->beta;
    printf("PSF %s (pixel %g um)\n", psf_path, um);
    printf("  model      %s\n", model_title(p->model));
    if (p->fwhm_minor > 0) {
        printf("  FWHM       %.4g um = %.4g px (major axis), %.4g um = %.4g px (minor axis),\n"
               "             major axis at %.4g deg from +x towards +y\n",
               p->fwhm * um, p->fwhm, p->fwhm_minor * um, p->fwhm_minor, p->angle * 180 / M_PI);
    } else {
        printf("  FWHM       %.4g um = %.4g px\n", p->fwhm * um, p->fwhm);
    }
    if (p->model == SVP_PSF_GAUSSIAN) {
        double sigma = svp_psf_fwhm_to_r0(p->fwhm, 0);
        printf("  sigma      %.4g um = %.4g px (beta does not apply)\n", sigma * um, sigma);
    } else {
        double r0 = svp_psf_fwhm_to_r0(p->fwhm, beta);
        printf("  r0         %.4g um = %.4g px (FWHM = 2 r0 sqrt(2^(1/beta) - 1))\n", r0 * um, r0);
        printf("  beta       %g%s\n", beta,
               beta <= 1 ? " (<= 1: the light over the plane diverges; the support matters)" : "");
    }
    printf("  halo       %g%s\n", p->halo,
           p->halo > 0 ? " of the light spread evenly over the field of view (not in the "
                         "kernel image)"
                       : "");
    if (p->support > 0)
        printf("  support    radius %.4g um = %.4g px\n", p->support * um, p->support);
    else
        printf("  support    the whole field of view (the kernel reaches every pixel)\n");
}

/* Encircled energy of the core over a disc of radius R: the radii holding 50 to 95 %. */
static int print_encircled(cli_run *run, const char *psf_path, const svp_psf *p, double um,
                           int radius)
{
    const double beta = p->model == SVP_PSF_LORENTZIAN ? 1.0 : p->beta;
    const int converges = p->model == SVP_PSF_GAUSSIAN || beta > 1;
    double R = 0;
    const char *R_note;
    char R_buf[160];
    if (p->support > 0) {
        R = p->support;
        snprintf(R_buf, sizeof R_buf, "over the support disc R = %.4g px", R);
        R_note = R_buf;
    } else if (converges) {
        R_note = "over the infinite plane";
    } else {
        R = radius;
        snprintf(R_buf, sizeof R_buf,
                 "over a disc of R = %d px, the rendered half-size (beta <= 1: the radii grow "
                 "with R; set support_um in the file to fix it)",
                 radius);
        R_note = R_buf;
    }
    printf("  encircled energy of the core %s%s:\n", R_note,
           p->fwhm_minor > 0 && p->fwhm_minor != p->fwhm ? " (elliptical: radius of the disc)"
                                                          : "");
    static const double fractions[] = {0.50, 0.80, 0.90, 0.95};
    for (int i = 0; i < 4; i++) {
        double r = 0;
        svp_status st = svp_psf_encircled_radius(p, fractions[i], R, &r);
        if (st != SVP_OK) return cli_fail(run, st, psf_path);
        printf("    %2.0f %%     r = %.4g um = %.4g px\n", 100 * fractions[i], r * um, r);
    }
    return 0;
}

static int run_psf(cli_run *run, const struct psf_args *a)
{
    cli_psf psf;
    memset(&psf, 0, sizeof psf);
    svp_image *kernel = NULL;
    int code = cli_psf_load(run, a->psf_path, &psf);
    if (!code && !psf.is_model)
        code = cli_error(run, "%s: expected a YAML PSF file (.yaml or .yml)", a->psf_path);
    if (!code) {
        cli_output_file(run, "kernel", run->output);
        code = cli_outputs_check(run);
    }
    const svp_psf *p = &psf.model;
    const char *size_rule = "--size";
    const int size = code ? 0 : a->size ? a->size : default_size(p, &size_rule);
    const int radius = (size - 1) / 2;
    if (!code) {
        svp_status st = svp_psf_render(p, radius, radius, &kernel);
        code = st == SVP_OK ? cli_write_image(run, run->output, kernel)
                            : cli_fail(run, st, a->psf_path);
    }
    if (!code) {
        describe_psf(a->psf_path, p, psf.pixel_um);
        code = print_encircled(run, a->psf_path, p, psf.pixel_um, radius);
    }
    if (!code) {
        const double beta = p->model == SVP_PSF_LORENTZIAN ? 1.0 : p->beta;
        const int converges = p->model == SVP_PSF_GAUSSIAN || beta > 1;
        double held = converges || p->support > 0
                          ? svp_psf_encircled_energy(p, radius, p->support > 0 ? p->support : 0)
                          : NAN;
        printf("kernel %d x %d px (size from %s) written to %s, normalised to unit sum", size, size,
               size_rule, run->output);
        if (isfinite(held))
            printf("; the square holds at least %.4g %% of the core's light", 100 * held);
        printf("\n");
    }
    svp_image_free(kernel);
    cli_psf_release(&psf);
    return code;
}

int cmd_psf(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "psf", argc, argv, CLI_COMMON_OUTPUT);
    struct psf_args args;
    int code = parse_psf_args(&run, &args);
    if (code == 0) code = run_psf(&run, &args);
    return cli_run_finish(&run, cli_parsed_status(code));
}
