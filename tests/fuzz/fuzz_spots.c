/* libFuzzer target: the spot list of `svpsf map-psf SPOTS.yaml` (docs/cli.md), read by the CLI
 * command itself (the list is parsed in tools/svpsf/cmd_map_psf.c). Exit codes 0..3 are
 * answers; 4 (internal error) or a crash, hang or leak is a defect. The command's messages go
 * to stderr: run with -close_fd_mask=2 to keep the log short. */
#include "fuzz_common.h"
#include "tools/svpsf/cli.h"

#include <getopt.h>

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    char *spots = strdup(fuzz_write("spots.yaml", data, size));
    char *out = strdup(fuzz_path("out/map.yaml"));
    unlink(out);
    char *argv[] = {"map-psf", spots, "-o", out, "--quiet", "--threads", "1", NULL};
    optind = 0; /* a fresh getopt scan per call (glibc) */
    int rc = cmd_map_psf(7, argv);
    unlink(out);
    free(spots);
    free(out);
    if (rc != 0 && rc != 1 && rc != 3) abort(); /* 2: a runtime failure on bad input */
    return 0;
}
