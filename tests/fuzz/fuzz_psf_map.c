/* libFuzzer target: svp_psf_field_read (a PSF-map file or a plain PSF file, docs/cli.md). */
#include "fuzz_common.h"
#include "svpsf.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    const char *path = fuzz_write("map.yaml", data, size);
    svp_psf_field *field = NULL;
    double px = 0;
    svp_status st = svp_psf_field_read(path, &field, &px);
    if (st != SVP_OK) {
        if (field) abort();
        const char *msg = svp_last_error();
        if (!msg || !*msg) abort();
        return 0;
    }
    if (!field || !(px > 0)) abort();
    svp_psf_field_free(field);
    return 0;
}
