/* libFuzzer target: svp_stack_read (multi-page TIFF through OpenCV's imreadmulti, 3-D .npy, a
 * single image as one frame). The input is written as .tif when it starts with TIFF's byte-order
 * mark ("II"/"MM"), else as .npy, so one corpus covers both readers. Any input must give SVP_OK
 * with frames of one size, or an error with a message; never a crash, a hang or a leak. */
#include "fuzz_common.h"
#include "svpsf.h"

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    const int tiff =
        size >= 2 && ((data[0] == 'I' && data[1] == 'I') || (data[0] == 'M' && data[1] == 'M'));
    const char *path = fuzz_write(tiff ? "stack.tif" : "stack.npy", data, size);
    svp_stack *s = NULL;
    svp_status st = svp_stack_read(path, &s);
    if (st != SVP_OK) {
        if (s) abort();
        const char *msg = svp_last_error();
        if (!msg || !*msg) abort();
        return 0;
    }
    if (!s || s->n_frames < 1 || !s->frame || s->width < 1 || s->height < 1) abort();
    volatile double sum = 0; /* touch every pixel of every frame: each holds width x height */
    for (int f = 0; f < s->n_frames; f++) {
        const svp_image *img = s->frame[f];
        if (!img || img->width != s->width || img->height != s->height || !img->data) abort();
        for (size_t i = 0; i < (size_t)img->width * (size_t)img->height; i++) sum += img->data[i];
    }
    (void)sum;
    svp_stack_free(s);
    return 0;
}
