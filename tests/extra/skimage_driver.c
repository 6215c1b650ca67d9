/* Runs the deconvolution functions on raw images for tests/extra/skimage_check.py.
 *
 * File format (all little-endian): the 4 bytes "SVPD", int32 height, int32 width, then
 * height * width float64 values, row-major.
 *
 *   skimage_driver wiener          IMAGE PSF BALANCE OUT   svp_skimage_wiener
 *   skimage_driver rl              IMAGE PSF NUM_ITER OUT  svp_skimage_richardson_lucy
 *   skimage_driver rl-periodic     IMAGE PSF NUM_ITER OUT  svp_deconv_rl, periodic operator of
 *                                                          the normalised PSF centred at
 *                                                          (kw/2, kh/2), default options
 *   skimage_driver wiener-periodic IMAGE PSF BALANCE OUT   svp_deconv_wiener, same operator
 *
 * Exit 0 on success, 1 with a message on stderr otherwise. */
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "core/internal.h"

static uint32_t get_u32(const unsigned char *b)
{
    return (uint32_t)b[0] | (uint32_t)b[1] << 8 | (uint32_t)b[2] << 16 | (uint32_t)b[3] << 24;
}

static svp_image *read_raw(const char *path)
{
    FILE *fp = fopen(path, "rb");
    if (!fp) {
        fprintf(stderr, "%s: cannot open\n", path);
        return NULL;
    }
    unsigned char head[12];
    svp_image *img = NULL;
    if (fread(head, 1, 12, fp) != 12 || memcmp(head, "SVPD", 4) != 0) {
        fprintf(stderr, "%s: not an SVPD file\n", path);
        goto done;
    }
    int h = (int)get_u32(head + 4), w = (int)get_u32(head + 8);
    if (svp_image_new(w, h, &img) != SVP_OK) {
        fprintf(stderr, "%s: %s\n", path, svp_last_error());
        goto done;
    }
    for (size_t i = 0; i < (size_t)w * h; i++) {
        unsigned char b[8];
        if (fread(b, 1, 8, fp) != 8) {
            fprintf(stderr, "%s: truncated after %zu values\n", path, i);
            svp_image_free(img);
            img = NULL;
            goto done;
        }
        uint64_t u = (uint64_t)get_u32(b) | (uint64_t)get_u32(b + 4) << 32;
        memcpy(&img->data[i], &u, 8);
    }
done:
    fclose(fp);
    return img;
}

static int write_raw(const char *path, const svp_image *img)
{
    FILE *fp = fopen(path, "wb");
    if (!fp) {
        fprintf(stderr, "%s: cannot create\n", path);
        return 1;
    }
    unsigned char head[12] = {'S', 'V', 'P', 'D'};
    uint32_t dims[2] = {(uint32_t)img->height, (uint32_t)img->width};
    for (int k = 0; k < 2; k++)
        for (int b = 0; b < 4; b++) head[4 + 4 * k + b] = (unsigned char)(dims[k] >> (8 * b));
    int bad = fwrite(head, 1, 12, fp) != 12;
    for (size_t i = 0; !bad && i < (size_t)img->width * img->height; i++) {
        uint64_t u;
        memcpy(&u, &img->data[i], 8);
        unsigned char b[8];
        for (int k = 0; k < 8; k++) b[k] = (unsigned char)(u >> (8 * k));
        bad = fwrite(b, 1, 8, fp) != 8;
    }
    if (fclose(fp) != 0) bad = 1;
    if (bad) fprintf(stderr, "%s: write failed\n", path);
    return bad;
}

int main(int argc, char **argv)
{
    if (argc != 6) {
        fprintf(stderr, "usage: %s wiener|rl|rl-periodic|wiener-periodic IMAGE PSF PARAM OUT\n",
                argv[0]);
        return 1;
    }
    svp_set_fft_effort(SVP_FFT_ESTIMATE);
    const char *mode = argv[1];
    const double param = strtod(argv[4], NULL);
    svp_image *image = read_raw(argv[2]), *psf = read_raw(argv[3]), *out = NULL;
    svp_blur *op = NULL;
    int rc = 1;
    if (!image || !psf) goto done;
    if (svp_image_new(image->width, image->height, &out) != SVP_OK) goto fail;
    svp_status st;
    if (strcmp(mode, "wiener") == 0) {
        st = svp_skimage_wiener(image, psf, param, out);
    } else if (strcmp(mode, "rl") == 0) {
        st = svp_skimage_richardson_lucy(image, psf, (int)param, NULL, NULL, out);
    } else if (strcmp(mode, "rl-periodic") == 0 || strcmp(mode, "wiener-periodic") == 0) {
        st = svp_blur_new_kernel(psf, -1, -1, 1, image->width, image->height,
                                 SVP_BOUNDARY_PERIODIC, &op);
        if (st != SVP_OK) goto fail;
        svp_deconv_options opt;
        svp_deconv_defaults(&opt);
        if (mode[0] == 'r') {
            opt.iterations = (int)param;
            st = svp_deconv_rl(op, image, &opt, out);
        } else {
            opt.balance = param;
            st = svp_deconv_wiener(op, image, &opt, out);
        }
    } else {
        fprintf(stderr, "unknown mode '%s'\n", mode);
        goto done;
    }
    if (st != SVP_OK) goto fail;
    rc = write_raw(argv[5], out);
    goto done;
fail:
    fprintf(stderr, "%s: %s\n", mode, svp_last_error());
done:
    svp_blur_free(op);
    svp_image_free(image);
    svp_image_free(psf);
    svp_image_free(out);
    svp_fft_cleanup();
    return rc;
}
