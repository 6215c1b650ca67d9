/* libFuzzer target: svp_psf_file_read (a YAML PSF file, docs/cli.md). An input gives a PSF or
 * an error with a message; a PSF read must render to a kernel or be refused with a message. */
#include "fuzz_common.h"
#include "svpsf.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    const char *path = fuzz_write("psf.yaml", data, size);
    svp_psf psf;
    double px = 0;
    svp_boundary boundary;
    svp_status st = svp_psf_file_read(path, &psf, &px, &boundary);
    if (st != SVP_OK) {
        const char *msg = svp_last_error();
        if (!msg || !*msg) abort();
        return 0;
    }
    if (!(px > 0)) abort();
    return 0;
}
