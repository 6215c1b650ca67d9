/* svpsf forward: the forward transform T (eq. 3): what a blurred measurement reports. */
#include "cli.h"

#include <stdlib.h>
#include <string.h>

enum { OPT_FIELD = CLI_OPTION_FIRST, OPT_PL, OPT_PSF, OPT_BOUNDARY };

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
          "                        PSF file's boundary, else zero)\n",
          out);
    cli_print_variant_help(out);
    cli_print_common_help(run, out);
    fputs("\n"
          "outputs in DIR: pl.EXT (apparent PL), field.EXT (apparent field; field_<stem>.EXT\n"
          "per input when several), validity.EXT (1 where the apparent PL is > 0, else 0; the\n"
          "apparent field is 0 there), summary.json.\n",
          out);
}

int cmd_forward(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "forward", argc, argv, CLI_COMMON_OUTPUT_DIR);
    static const struct option own[] = {
        {"field", required_argument, NULL, OPT_FIELD},
        {"pl", required_argument, NULL, OPT_PL},
        {"psf", required_argument, NULL, OPT_PSF},
        CLI_VARIANT_LONGOPTS,
        {"boundary", required_argument, NULL, OPT_BOUNDARY},
        {NULL, 0, NULL, 0},
    };
    cli_maps maps;
    memset(&maps, 0, sizeof maps);
    cli_psf psf;
    memset(&psf, 0, sizeof psf);
    const char *psf_path = NULL;
    svp_boundary boundary = SVP_BOUNDARY_ZERO;
    svp_variant_options variant;
    cli_variant_defaults(&variant);
    int variant_given = 0;
    int boundary_given = 0;
    svp_blur *blur = NULL;
    svp_image *pl_apparent = NULL, *validity = NULL;
    svp_image *field_apparent[CLI_MAX_FIELDS] = {NULL};
    int code = 0;

    int c;
    while ((c = cli_next_option(&run, own)) != CLI_OPTIONS_DONE) {
        switch (c) {
        case CLI_OPTION_HELP: print_help(&run, stdout); return cli_run_finish(&run, 0);
        case CLI_OPTION_ERROR: return cli_run_finish(&run, CLI_EXIT_USAGE);
        case OPT_FIELD:
            if (cli_maps_add_field(&run, &maps, optarg))
                return cli_run_finish(&run, CLI_EXIT_USAGE);
            break;
        case OPT_PL: maps.pl_path = optarg; break;
        case OPT_PSF: psf_path = optarg; break;
        case CLI_OPT_NODES:
        case CLI_OPT_RANK:
            if (cli_variant_option(&run, &variant, c, optarg))
                return cli_run_finish(&run, CLI_EXIT_USAGE);
            variant_given = 1;
            break;
        case OPT_BOUNDARY:
            if (cli_parse_boundary(&run, "--boundary", optarg, &boundary))
                return cli_run_finish(&run, CLI_EXIT_USAGE);
            boundary_given = 1;
            break;
        default: return cli_run_finish(&run, cli_error(&run, "internal: option %d", c));
        }
    }
    if (optind < argc)
        return cli_run_finish(&run, cli_error(&run,
                                              "unexpected argument '%s' (inputs are "
                                              "given with --field, --pl and --psf)",
                                              argv[optind]));
    if (maps.n_fields == 0)
        return cli_run_finish(&run, cli_error(&run, "--field is required (see --help)"));
    if (!maps.pl_path) return cli_run_finish(&run, cli_error(&run, "--pl is required"));
    if (!psf_path) return cli_run_finish(&run, cli_error(&run, "--psf is required"));
    if (!run.output) return cli_run_finish(&run, cli_error(&run, "-o DIR is required"));

    /* Everything that can be wrong with the inputs or outputs is found before any work. */
    cli_stage_begin(&run, "read");
    if ((code = cli_psf_load_map(&run, psf_path, &variant, &psf))) goto cleanup;
    if (variant_given && !psf.field)
        cli_note(&run, "--nodes / --rank ignored: %s is a single PSF, not a space-variant map",
                 psf_path);
    if ((code = cli_maps_read(&run, &maps))) goto cleanup;
    if (!boundary_given && psf.has_boundary) boundary = psf.boundary;
    if ((code = cli_maps_plan(&run, &maps))) goto cleanup;
    if ((code = cli_psf_check(&run, &psf, maps.pl->width, maps.pl->height))) goto cleanup;
    if ((code = cli_outputs_check(&run))) goto cleanup;

    const int w = maps.pl->width, h = maps.pl->height;
    cli_psf_describe(&run, &psf);
    cli_setting_str(&run, "boundary", cli_boundary_name(boundary));
    cli_setting_int(&run, "n_fields", maps.n_fields);
    cli_setting_str(&run, "format", cli_format_extension(run.format));

    cli_stage_begin(&run, "plan");
    if ((code = cli_psf_blur(&run, &psf, w, h, boundary, &blur))) goto cleanup;

    cli_stage_begin(&run, "transform");
    svp_status st = svp_image_new(w, h, &pl_apparent);
    if (st == SVP_OK) st = svp_image_new(w, h, &validity);
    for (int i = 0; i < maps.n_fields && st == SVP_OK; i++)
        st = svp_image_new(w, h, &field_apparent[i]);
    if (st == SVP_OK)
        st = svp_forward_transform(blur, maps.pl, (const svp_image *const *)maps.fields,
                                   maps.n_fields, pl_apparent, field_apparent, validity);
    if (st != SVP_OK) {
        code = cli_fail(&run, st, NULL);
        goto cleanup;
    }
    size_t n = (size_t)w * h, n_dark = 0;
    for (size_t i = 0; i < n; i++) n_dark += validity->data[i] < 1;
    cli_result_int(&run, "n_dark", (long long)n_dark);
    cli_result_num(&run, "dark_fraction", (double)n_dark / (double)n);

    cli_stage_begin(&run, "write");
    if ((code = cli_write_image(&run, maps.pl_out, pl_apparent))) goto cleanup;
    for (int i = 0; i < maps.n_fields; i++)
        if ((code = cli_write_image(&run, maps.field_out[i], field_apparent[i]))) goto cleanup;
    if ((code = cli_write_image(&run, maps.validity_out, validity))) goto cleanup;
    cli_stage_end(&run);
    if ((code = cli_summary_write(&run, maps.summary_out))) goto cleanup;

    printf("svpsf forward: %d x %d, %d field map%s: apparent maps written to %s "
           "(%zu dark pixel%s with zero apparent PL) in %.2f s\n",
           w, h, maps.n_fields, maps.n_fields > 1 ? "s" : "", run.output, n_dark,
           n_dark == 1 ? "" : "s", cli_now() - run.t_start);

cleanup:
    svp_blur_free(blur);
    svp_image_free(pl_apparent);
    svp_image_free(validity);
    for (int i = 0; i < CLI_MAX_FIELDS; i++) svp_image_free(field_apparent[i]);
    cli_maps_release(&maps);
    cli_psf_release(&psf);
    return cli_run_finish(&run, code);
}
