/* svpsf forward: the forward transform T (eq. 3): what a blurred measurement reports. */
#include "cli.h"

#include <stdlib.h>
#include <string.h>

static void print_help(const cli_run *run, FILE *out)
{
    fputs("usage: svpsf forward --field B.npy [--field B2.npy ...] --pl I.npy --psf PSF -o DIR\n"
          "                     [options]\n"
          "\n"
          "The forward transform T (eq. 3 of docs/model.md): given the true field map(s) B and\n"
          "the true PL map I, predicts the measured (apparent) maps\n"
          "    pl_apparent = I (*) p,   field_apparent = ((B I) (*) p) / pl_apparent\n"
          "for the PSF p. Several --field maps (vector components) share the one PL map.\n"
          "\n"
          "inputs (TIFF float32/16-bit, 16-bit PNG, .npy, .txt as numpy.savetxt writes them):\n"
          "  --field FILE          a true field map (any unit; repeat for several components)\n"
          "  --pl FILE             the true PL map (same size, >= 0)\n"
          "  --psf FILE            a YAML PSF file or PSF-map file (docs/cli.md) or a kernel\n"
          "                        image (.npy, .tif, .txt; normalised to unit sum, centre at\n"
          "                        the middle pixel)\n"
          "options:\n"
          "  -o, --output DIR      output folder, created when missing (required)\n"
          "  --boundary zero|mirror|periodic  the scene beyond the image edges (default: the\n"
          "                        PSF file's boundary, else zero)\n"
          "  --precision double|single  the blur's FFTs in double (default) or single precision\n"
          "                        (float FFTs on the same frames; a map's operator then keeps\n"
          "                        its spectra in float: half their memory); within 2e-6 of\n"
          "                        the peak of double (docs/cli.md)\n",
          out);
    cli_print_variant_help(out, 1e-3);
    cli_print_common_help(run, out);
    fputs("\n"
          "outputs in DIR: pl.EXT (apparent PL), field.EXT (apparent field; field_<stem>.EXT\n"
          "per input when several), validity.EXT (1 where the apparent PL is > 0, else 0; the\n"
          "apparent field is 0 there), summary.json.\n",
          out);
}

struct forward_args {
    cli_maps maps; /* --field, --pl, --psf, --boundary, --nodes, ... */
    int precision; /* --precision: index in cli_precision_names */
};

enum { OPT_PRECISION = 1 };

static int parse_forward_args(cli_run *run, struct forward_args *a)
{
    static const struct option own[] = {CLI_MAPS_LONGOPTS,
                                        {"precision", required_argument, NULL, OPT_PRECISION},
                                        {NULL, 0, NULL, 0}};
    memset(a, 0, sizeof *a);
    cli_maps_init(&a->maps);
    int c;
    while ((c = cli_next_option(run, own)) != CLI_OPTIONS_DONE) {
        if (c == CLI_OPTION_HELP) {
            print_help(run, stdout);
            return CLI_OPTION_HELP;
        }
        if (c == CLI_OPTION_ERROR) return CLI_EXIT_USAGE;
        if (c == OPT_PRECISION) {
            if (cli_parse_choice(run, "--precision", optarg, cli_precision_names, &a->precision))
                return CLI_EXIT_USAGE;
            continue;
        }
        int code = cli_maps_option(run, &a->maps, c, optarg);
        if (code < 0) code = cli_error(run, "internal: option %d", c);
        if (code) return code;
    }
    return 0;
}

struct forward_job {
    cli_psf psf;
    svp_blur *blur;
    svp_image *pl_apparent, *validity, *field_apparent[CLI_MAX_FIELDS];
};

/* The operator (in float when asked) and T; the dark pixels counted. */
static int forward_compute(cli_run *run, const struct forward_args *a, struct forward_job *job,
                           size_t *n_dark)
{
    const cli_maps *maps = &a->maps;
    const int w = maps->pl->width, h = maps->pl->height;
    int code;
    cli_stage_begin(run, "plan");
    job->psf.variant.applications = 1; /* the cost model: one application each, no adjoint */
    if ((code = cli_psf_blur(run, &job->psf, w, h, maps->boundary, &job->blur))) return code;
    if (a->precision == 1) {
        svp_status pst = svp_blur_set_precision(job->blur, 1);
        if (pst != SVP_OK) return cli_fail(run, pst, NULL);
    }
    cli_stage_begin(run, "transform");
    svp_status st = svp_image_new(w, h, &job->pl_apparent);
    if (st == SVP_OK) st = svp_image_new(w, h, &job->validity);
    for (int i = 0; i < maps->n_fields && st == SVP_OK; i++)
        st = svp_image_new(w, h, &job->field_apparent[i]);
    if (st == SVP_OK)
        st = svp_forward_transform(job->blur, maps->pl, (const svp_image *const *)maps->fields,
                                   maps->n_fields, job->pl_apparent, job->field_apparent,
                                   job->validity);
    if (st != SVP_OK) { /* the library names the map's role (pl_true, field_true[k]): its file */
        const char *msg = svp_last_error(), *file = NULL;
        char role[32];
        if (msg && strstr(msg, "pl_true")) file = maps->pl_path;
        for (int i = 0; i < maps->n_fields && !file && msg; i++) {
            snprintf(role, sizeof role, "field_true[%d]", i);
            if (strstr(msg, role)) file = maps->field_paths[i];
        }
        return cli_fail(run, st, file);
    }
    const size_t n = (size_t)w * h;
    *n_dark = 0;
    for (size_t i = 0; i < n; i++) *n_dark += job->validity->data[i] < 1;
    cli_result_int(run, "n_dark", (long long)*n_dark);
    cli_result_num(run, "dark_fraction", (double)*n_dark / (double)n);
    return 0;
}

static int run_forward(cli_run *run, struct forward_args *a)
{
    struct forward_job job;
    memset(&job, 0, sizeof job);
    cli_maps *maps = &a->maps;
    size_t n_dark = 0;
    int code = cli_maps_open(run, maps, &job.psf);
    if (!code) {
        job.psf.variant.single_precision = a->precision == 1; /* a map's spectra in float only */
        cli_setting_str(run, "precision", cli_precision_names[a->precision]);
        code = forward_compute(run, a, &job, &n_dark);
    }
    if (!code) code = cli_maps_write(run, maps, job.pl_apparent, job.field_apparent, job.validity);
    if (!code) {
        const int w = maps->pl->width, h = maps->pl->height;
        char op[256];
        cli_variant_sentence(job.blur, op, sizeof op);
        printf("svpsf forward: %d x %d, %d field map%s: apparent maps written to %s "
               "(%zu dark pixel%s with zero apparent PL) in %.2f s.%s\n",
               w, h, maps->n_fields, maps->n_fields > 1 ? "s" : "", run->output, n_dark,
               n_dark == 1 ? "" : "s", cli_now() - run->t_start, op);
    }
    svp_blur_free(job.blur);
    svp_image_free(job.pl_apparent);
    svp_image_free(job.validity);
    for (int i = 0; i < CLI_MAX_FIELDS; i++) svp_image_free(job.field_apparent[i]);
    cli_psf_release(&job.psf);
    return code;
}

int cmd_forward(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "forward", argc, argv, CLI_COMMON_OUTPUT_DIR);
    struct forward_args args;
    int code = parse_forward_args(&run, &args);
    if (code == 0) code = run_forward(&run, &args);
    cli_maps_release(&args.maps);
    return cli_run_finish(&run, cli_parsed_status(code));
}
