/* libFuzzer target: svp_fft_wisdom_load (an FFTW wisdom file, docs/cli.md --wisdom). FFTW's
 * own parser reads the text; svpsf splits the double and single precision parts first. */
#include "fuzz_common.h"
#include "svpsf.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    const char *path = fuzz_write("input.wisdom", data, size);
    svp_status st = svp_fft_wisdom_load(path);
    if (st != SVP_OK) {
        const char *msg = svp_last_error();
        if (!msg || !*msg) abort();
    }
    return 0;
}
