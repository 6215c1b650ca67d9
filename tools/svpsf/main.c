/* svpsf: the command-line program. `svpsf <command> [options]`, `svpsf --help`,
 * `svpsf --version`. Commands live in cmd_*.c; this file only dispatches. */
#include "cli.h"
#include "svpsf_version.h"

#include <stdio.h>
#include <string.h>

/* The commands, in the order `svpsf --help` lists them. A command exists for the user once it
 * has a line here (see cli.h: "Adding a command"). */
static const cli_command commands[] = {
    {"forward", "predict the apparent PL and field maps of a blurred measurement (T, eq. 3)",
     cmd_forward},
    {"correct", "recover the true field and PL maps from measured ones (T^-1, eq. 4)", cmd_correct},
    {"deconvolve", "deconvolve one image by a PSF (Wiener-Hunt or Richardson-Lucy)",
     cmd_deconvolve},
    {"psf", "render a PSF file to a kernel image; print its width and encircled energy", cmd_psf},
    {"demo", "a built-in example: blur and correct a synthetic field map", cmd_demo},
    {"register", "align two images (phase correlation or ECC); warp a mask onto the reference",
     cmd_register},
    {"simulate", "run a scene file: simulate, correct, reconstruct, report", cmd_simulate},
    {"reconstruct", "magnetisation or current density from field maps", cmd_reconstruct},
    {"fit-psf", "fit a Moffat PSF to a spot image, or derive it from an excitation/emission pair",
     cmd_fit_psf},
    {"map-psf", "map PSF parameters over the field (or per region) from many spot fits",
     cmd_map_psf},
    {"psf-compare", "compare two PSF maps: parameter differences, effect on a corrected field",
     cmd_psf_compare},
    {"fit-odmr", "fit an ODMR stack per pixel: field, its sigma, PL, contrast, width maps",
     cmd_fit_odmr},
};

static const int n_commands = (int)(sizeof commands / sizeof commands[0]);

static void print_usage(FILE *out)
{
    fputs("usage: svpsf <command> [options]\n"
          "       svpsf <command> --help\n"
          "       svpsf --version\n"
          "\n"
          "svpsf corrects optical-aberration artefacts in widefield spectral imaging (NV-diamond\n"
          "field maps): the forward transform T predicts what a blurred, non-uniformly lit\n"
          "measurement reports, and its inverse T^-1 recovers the true field map.\n"
          "\n"
          "commands:\n",
          out);
    for (int i = 0; i < n_commands; i++)
        fprintf(out, "  %-12s %s\n", commands[i].name, commands[i].summary);
    fputs("\n"
          "exit status: 0 ok, 1 bad usage or bad input (the message names the file and the\n"
          "problem), 2 runtime failure, 3 a result the program cannot vouch for.\n"
          "Reference: docs/cli.md, and `man svpsf`; an installed copy keeps docs/ in\n"
          "  " SVPSF_DOCDIR "\n",
          out);
}

static void print_version(void)
{
    cli_versions v;
    cli_get_versions(&v);
    printf("svpsf %s\n", v.svpsf);
    printf("FFTW %s\n", v.fftw);
    printf("OpenCV %s\n", v.opencv);
    printf("libyaml %s\n", v.libyaml);
}

int main(int argc, char **argv)
{
    cli_openmp_passive(argv); /* may run the program again with OMP_WAIT_POLICY=passive */
    cli_set_program_args(argc, argv);
    if (argc < 2) {
        print_usage(stderr);
        return CLI_EXIT_USAGE;
    }
    const char *name = argv[1];
    if (strcmp(name, "--help") == 0 || strcmp(name, "-h") == 0) {
        print_usage(stdout);
        return CLI_EXIT_OK;
    }
    if (strcmp(name, "--version") == 0 || strcmp(name, "-V") == 0) {
        print_version();
        return CLI_EXIT_OK;
    }
    /* `svpsf help CMD` is `svpsf CMD --help` */
    char *help_argv[4] = {argv[0], NULL, "--help", NULL};
    if (strcmp(name, "help") == 0) {
        if (argc < 3) {
            print_usage(stdout);
            return CLI_EXIT_OK;
        }
        name = help_argv[1] = argv[2];
        argv = help_argv;
        argc = 3;
    }
    for (int i = 0; i < n_commands; i++)
        if (strcmp(name, commands[i].name) == 0) {
            int code = commands[i].run(argc - 1, argv + 1);
            if (code != CLI_EXIT_OK) cli_remove_created_dirs(); /* a failed run writes nothing */
            return code;
        }
    if (name[0] == '-')
        fprintf(stderr, "svpsf: unknown option %s before the command (see svpsf --help)\n", name);
    else
        fprintf(stderr, "svpsf: unknown command '%s' (see svpsf --help)\n", name);
    return CLI_EXIT_USAGE;
}
