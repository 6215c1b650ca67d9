/* libFuzzer target: the MATLAB .mat reader (src/io/mat.c, libmatio underneath) on one input
 * file: svp_mat_read with the default variable and with ledImg (QDMlab's LED image), and
 * svp_mat_read_stack with the default. Any input must give SVP_OK with well-formed images or an
 * error status with a message, never a crash, a hang or a leak. libmatio itself is Debian's
 * build (not instrumented): its crashes, hangs and leaks are caught, its coverage not counted. */
#include "fuzz_common.h"
#include "svpsf.h"

static void touch(const svp_image *img)
{
    if (!img || img->width <= 0 || img->height <= 0 || !img->data) abort();
    volatile double sum = 0; /* the buffer must hold width x height */
    for (size_t i = 0; i < (size_t)img->width * (size_t)img->height; i++) sum += img->data[i];
    (void)sum;
}

static void check_error(void)
{
    const char *msg = svp_last_error();
    if (!msg || !*msg) abort();
}

int LLVMFuzzerTestOneInput(const uint8_t *data, size_t size)
{
    const char *path = fuzz_write("input.mat", data, size);
    static const char *const vars[2] = {NULL, "ledImg"};
    for (int i = 0; i < 2; i++) {
        svp_image *img = NULL;
        svp_mat_info info;
        if (svp_mat_read(path, vars[i], &img, &info) == SVP_OK) {
            touch(img);
            if (!info.variable[0] || !(info.pixel_um >= 0) || !(info.standoff_um >= 0)) abort();
        } else {
            if (img) abort();
            check_error();
        }
        svp_image_free(img);
    }
    svp_stack *s = NULL;
    if (svp_mat_read_stack(path, NULL, &s, NULL) == SVP_OK) {
        if (!s || s->n_frames < 1) abort();
        for (int k = 0; k < s->n_frames; k++) {
            touch(s->frame[k]);
            if (s->frame[k]->width != s->width || s->frame[k]->height != s->height) abort();
        }
    } else {
        if (s) abort();
        check_error();
    }
    svp_stack_free(s);
    return 0;
}
