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

int cmd_forward(int argc, char **argv)
{
    cli_run run;
    cli_run_init(&run, "forward", argc, argv, CLI_COMMON_OUTPUT_DIR);
    enum { OPT_PRECISION = 1 };
    static const struct option own[] = {CLI_MAPS_LONGOPTS,
                                        {"precision", required_argument, NULL, OPT_PRECISION},
                                        {NULL, 0, NULL, 0}};
    int precision = 0;
    cli_maps maps;
    cli_maps_init(&maps);
    cli_psf psf;
    memset(&psf, 0, sizeof psf);
    svp_blur *blur = NULL;
    svp_image *pl_apparent = NULL, *validity = NULL;
    svp_image *field_apparent[CLI_MAX_FIELDS] = {NULL};
    int code = 0;

    int c;
    while ((c = cli_next_option(&run, own)) != CLI_OPTIONS_DONE) {
        switch (c) {
        case CLI_OPTION_HELP: print_help(&run, stdout); return cli_run_finish(&run, 0);
        case CLI_OPTION_ERROR: return cli_run_finish(&run, CLI_EXIT_USAGE);
        case OPT_PRECISION:
            if (cli_parse_choice(&run, "--precision", optarg, cli_precision_names, &precision))
                return cli_run_finish(&run, CLI_EXIT_USAGE);
            break;
        default:
            code = cli_maps_option(&run, &maps, c, optarg);
            if (code < 0) code = cli_error(&run, "internal: option %d", c);
            if (code) return cli_run_finish(&run, code);
        }
    }
    if ((code = cli_maps_open(&run, &maps, &psf))) goto cleanup;
    psf.variant.single_precision = precision == 1; /* a map's spectra in float only */
    cli_setting_str(&run, "precision", cli_precision_names[precision]);

    const int w = maps.pl->width, h = maps.pl->height;

    cli_stage_begin(&run, "plan");
    psf.variant.applications = 1; /* the cost model: one application each, no adjoint */
    if ((code = cli_psf_blur(&run, &psf, w, h, maps.boundary, &blur))) goto cleanup;
    if (precision == 1) {
        svp_status pst = svp_blur_set_precision(blur, 1);
        if (pst != SVP_OK) {
            code = cli_fail(&run, pst, NULL);
            goto cleanup;
        }
    }

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

    if ((code = cli_maps_write(&run, &maps, pl_apparent, field_apparent, validity))) goto cleanup;

    char op[256];
    cli_variant_sentence(blur, op, sizeof op);
    printf("svpsf forward: %d x %d, %d field map%s: apparent maps written to %s "
           "(%zu dark pixel%s with zero apparent PL) in %.2f s.%s\n",
           w, h, maps.n_fields, maps.n_fields > 1 ? "s" : "", run.output, n_dark,
           n_dark == 1 ? "" : "s", cli_now() - run.t_start, op);

cleanup:
    svp_blur_free(blur);
    svp_image_free(pl_apparent);
    svp_image_free(validity);
    for (int i = 0; i < CLI_MAX_FIELDS; i++) svp_image_free(field_apparent[i]);
    cli_maps_release(&maps);
    cli_psf_release(&psf);
    return cli_run_finish(&run, code);
}
