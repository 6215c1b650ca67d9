/* libFuzzer target: svp_image_read on one image format, chosen at build time by
 * FUZZ_IMAGE_EXT ("npy", "txt", "tif", "png"; TIFF and PNG go through OpenCV). Any input must
 * give SVP_OK with a well-formed image or an error status with a message, never a crash, a
 * hang or a leak. */
#include "fuzz_common.h"
#include "svpsf.h"


#ifndef FUZZ_IMAGE_EXT
#error "define FUZZ_IMAGE_EXT"
#endif

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    const char *path = fuzz_write("input." FUZZ_IMAGE_EXT, data, size);
    svp_image *img = NULL;
    svp_status st = svp_image_read(path, &img);
    if (st == SVP_OK) {
        if (!img || img->width <= 0 || img->height <= 0 || !img->data) abort();
        volatile double sum = 0; /* touch every pixel: the buffer must hold width x height */
        for (size_t i = 0; i < (size_t)img->width * (size_t)img->height; i++) sum += img->data[i];
        (void)sum;
    } else {
        if (img) abort();
        const char *msg = svp_last_error();
        if (!msg || !*msg) abort();
    }
    svp_image_free(img);
    return 0;
}
