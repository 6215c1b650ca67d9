/* Inputs and checks for tests/extra/mat_cli_test.sh:
 *   mat_cli_make qdm DIR W H      QDMlab's files written with libmatio: DIR/Bz_uc0.mat (Bz in
 *                                 tesla, Bt, h, step, corners, newLED; compressed as MATLAB's
 *                                 save), DIR/B111dataToPlot.mat (B111ferro, B111para in gauss,
 *                                 negDiff, posDiff, ledImg), and the same Bz and LED image as
 *                                 DIR/Bz.npy, DIR/led.npy
 *   mat_cli_make odmr DIR W H N   an ODMR stack of N frames (both lines of one NV axis) as
 *                                 DIR/stack.npy, QDMlab's raw DIR/run_00000.mat (imgStack1) and
 *                                 a 3-D variable DIR/stack3.mat:odmr
 *   mat_cli_make compare A B      exit 0 when images A and B (any format svpsf reads) are
 *                                 equal value for value (NaN equal to NaN)
 *   mat_cli_make info FILE[:VAR]  prints "variable W H pixel_um standoff_um" (svp_mat_read) */
#include "svpsf.h"

#include <math.h>
#include <matio.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int put(mat_t *mat, const char *name, const double *rowmajor, size_t rows, size_t cols)
{
    double *col = malloc(rows * cols * sizeof *col);
    if (!col) return 1;
    for (size_t r = 0; r < rows; r++)
        for (size_t c = 0; c < cols; c++) col[r + rows * c] = rowmajor[r * cols + c];
    size_t dims[2] = {rows, cols};
    matvar_t *v = Mat_VarCreate(name, MAT_C_DOUBLE, MAT_T_DOUBLE, 2, dims, col, 0);
    int rc = !v || Mat_VarWrite(mat, v, MAT_COMPRESSION_ZLIB) != 0;
    Mat_VarFree(v);
    free(col);
    return rc;
}

static int qdm(const char *dir, int w, int h)
{
    svp_image *bz, *led, *other;
    if (svp_image_new(w, h, &bz) || svp_image_new(w, h, &led) || svp_image_new(w, h, &other))
        return 1;
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double dx = x - 0.6 * w, dy = y - 0.4 * h;
            bz->data[y * w + x] = 2e-6 * exp(-(dx * dx + dy * dy) / 18.0) * (1 + 0.01 * x) +
                                  1e-8 * y;
            led->data[y * w + x] = 150 + 40 * sin(x / 5.0) * cos(y / 7.0) + 0.5 * y;
            other->data[y * w + x] = 1e4 * bz->data[y * w + x]; /* gauss */
        }
    char path[1024];
    snprintf(path, sizeof path, "%s/Bz_uc0.mat", dir);
    mat_t *mat = Mat_CreateVer(path, NULL, MAT_FT_MAT5);
    if (!mat) return 1;
    double h_m = 5e-6, step_m = 4.7e-6, corners[4] = {1, 1, (double)h, (double)w};
    int rc = put(mat, "Bz", bz->data, (size_t)h, (size_t)w) ||
             put(mat, "Bt", other->data, (size_t)h, (size_t)w) ||
             put(mat, "h", &h_m, 1, 1) || put(mat, "step", &step_m, 1, 1) ||
             put(mat, "corners", corners, 2, 2) ||
             put(mat, "newLED", led->data, (size_t)h, (size_t)w);
    Mat_Close(mat);
    /* `step` as [dx dy] of pixels that are not square: no pixel size for svpsf */
    snprintf(path, sizeof path, "%s/Bz_steps.mat", dir);
    mat = Mat_CreateVer(path, NULL, MAT_FT_MAT5);
    if (!mat) return 1;
    double steps[2] = {4.7e-6, 5.1e-6};
    rc = rc || put(mat, "Bz", bz->data, (size_t)h, (size_t)w) || put(mat, "h", &h_m, 1, 1) ||
         put(mat, "step", steps, 1, 2);
    Mat_Close(mat);
    /* `step` as text: no pixel size either */
    snprintf(path, sizeof path, "%s/Bz_stepchar.mat", dir);
    mat = Mat_CreateVer(path, NULL, MAT_FT_MAT5);
    if (!mat) return 1;
    rc = rc || put(mat, "Bz", bz->data, (size_t)h, (size_t)w);
    {
        char text[1] = {'x'};
        size_t dims[2] = {1, 1};
        matvar_t *v = Mat_VarCreate("step", MAT_C_CHAR, MAT_T_UINT8, 2, dims, text, 0);
        rc = rc || !v || Mat_VarWrite(mat, v, MAT_COMPRESSION_NONE) != 0;
        if (v) Mat_VarFree(v);
    }
    Mat_Close(mat);
    snprintf(path, sizeof path, "%s/B111dataToPlot.mat", dir);
    mat = Mat_CreateVer(path, NULL, MAT_FT_MAT5);
    if (!mat) return 1;
    rc = rc || put(mat, "negDiff", other->data, (size_t)h, (size_t)w) ||
         put(mat, "posDiff", other->data, (size_t)h, (size_t)w) ||
         put(mat, "B111ferro", other->data, (size_t)h, (size_t)w) ||
         put(mat, "B111para", bz->data, (size_t)h, (size_t)w) ||
         put(mat, "ledImg", led->data, (size_t)h, (size_t)w);
    Mat_Close(mat);
    snprintf(path, sizeof path, "%s/Bz.npy", dir);
    rc = rc || svp_image_write(path, bz, SVP_FORMAT_NPY, 1);
    snprintf(path, sizeof path, "%s/led.npy", dir);
    rc = rc || svp_image_write(path, led, SVP_FORMAT_NPY, 1);
    svp_image_free(bz);
    svp_image_free(led);
    svp_image_free(other);
    return rc;
}

/* A 3-D .npy (frames, height, width), C order, float64. */
static int write_npy3(const char *path, const double *d, int n, int h, int w)
{
    FILE *f = fopen(path, "wb");
    if (!f) return 1;
    char header[128];
    int len = snprintf(header, sizeof header,
                       "{'descr': '<f8', 'fortran_order': False, 'shape': (%d, %d, %d), }", n, h,
                       w);
    int total = 10 + len + 1, pad = (64 - total % 64) % 64;
    unsigned short hl = (unsigned short)(len + pad + 1);
    fwrite("\x93NUMPY\x01\x00", 1, 8, f);
    fputc(hl & 0xff, f);
    fputc(hl >> 8, f);
    fwrite(header, 1, (size_t)len, f);
    for (int i = 0; i < pad; i++) fputc(' ', f);
    fputc('\n', f);
    size_t count = (size_t)n * h * w;
    int rc = fwrite(d, sizeof *d, count, f) != count;
    return fclose(f) != 0 || rc;
}

/* An ODMR stack of n frames over 2.84..2.90 GHz (n points): both lines of one NV axis at
 * D +/- gamma B with B varying over the image, as DIR/stack.npy (frames, h, w), as QDMlab's raw
 * DIR/run_00000.mat (imgStack1: n x (h * w), frame k = row k, pixels row after row; imgNumRows,
 * imgNumCols, numFreqs, freqList) and as a 3-D variable DIR/stack3.mat:odmr (h x w x n). */
static int odmr(const char *dir, int w, int h, int n)
{
    size_t np = (size_t)w * h;
    double *frames = malloc(np * n * sizeof *frames), *raw = malloc(np * n * sizeof *raw),
           *cube = malloc(np * n * sizeof *cube), *freq = malloc(2 * (size_t)n * sizeof *freq);
    if (!frames || !raw || !cube || !freq) return 1;
    for (int k = 0; k < n; k++) freq[k] = freq[n + k] = 2.84e9 + 0.06e9 * k / (n - 1);
    for (int y = 0; y < h; y++)
        for (int x = 0; x < w; x++) {
            double b = 4e-4 * (x - 0.3 * w) / w + 2e-4 * y / h, pl = 1000 + 10 * x + 3 * y;
            for (int k = 0; k < n; k++) {
                double s = 0;
                for (int sign = -1; sign <= 1; sign += 2) {
                    double u = (freq[k] - (2.87e9 + sign * 28.033e9 * b)) / 2e6; /* HWHM 2 MHz */
                    s += 0.02 / (1 + u * u);
                }
                double v = pl * (1 - s);
                frames[(size_t)k * np + (size_t)y * w + x] = v;
                raw[(size_t)k + (size_t)n * ((size_t)y * w + x)] = v;
                cube[(size_t)y + (size_t)h * x + np * k] = v;
            }
        }
    char path[1024];
    snprintf(path, sizeof path, "%s/stack.npy", dir);
    int rc = write_npy3(path, frames, n, h, w);
    snprintf(path, sizeof path, "%s/run_00000.mat", dir);
    mat_t *mat = Mat_CreateVer(path, NULL, MAT_FT_MAT5);
    if (!mat) return 1;
    double rows = h, cols = w, nf = n;
    size_t dims[2] = {(size_t)n, np}, fd[2] = {1, 2 * (size_t)n}, one[2] = {1, 1};
    matvar_t *v = Mat_VarCreate("imgStack1", MAT_C_DOUBLE, MAT_T_DOUBLE, 2, dims, raw, 0);
    rc = rc || !v || Mat_VarWrite(mat, v, MAT_COMPRESSION_ZLIB);
    Mat_VarFree(v);
    v = Mat_VarCreate("freqList", MAT_C_DOUBLE, MAT_T_DOUBLE, 2, fd, freq, 0);
    rc = rc || !v || Mat_VarWrite(mat, v, MAT_COMPRESSION_NONE);
    Mat_VarFree(v);
    const char *names[3] = {"imgNumRows", "imgNumCols", "numFreqs"};
    double *vals[3] = {&rows, &cols, &nf};
    for (int i = 0; i < 3; i++) {
        v = Mat_VarCreate(names[i], MAT_C_DOUBLE, MAT_T_DOUBLE, 2, one, vals[i], 0);
        rc = rc || !v || Mat_VarWrite(mat, v, MAT_COMPRESSION_NONE);
        Mat_VarFree(v);
    }
    Mat_Close(mat);
    snprintf(path, sizeof path, "%s/stack3.mat", dir);
    mat = Mat_CreateVer(path, NULL, MAT_FT_MAT5);
    if (!mat) return 1;
    size_t d3[3] = {(size_t)h, (size_t)w, (size_t)n};
    v = Mat_VarCreate("odmr", MAT_C_DOUBLE, MAT_T_DOUBLE, 3, d3, cube, 0);
    rc = rc || !v || Mat_VarWrite(mat, v, MAT_COMPRESSION_ZLIB);
    Mat_VarFree(v);
    double step_m = 4.7e-6; /* the pixel size, as QDMlab's Bz files hold it */
    v = Mat_VarCreate("step", MAT_C_DOUBLE, MAT_T_DOUBLE, 2, one, &step_m, 0);
    rc = rc || !v || Mat_VarWrite(mat, v, MAT_COMPRESSION_NONE);
    Mat_VarFree(v);
    Mat_Close(mat);
    free(frames);
    free(raw);
    free(cube);
    free(freq);
    return rc;
}

static int compare(const char *a_path, const char *b_path)
{
    svp_image *a = NULL, *b = NULL;
    if (svp_image_read(a_path, &a) || svp_image_read(b_path, &b)) {
        fprintf(stderr, "%s\n", svp_last_error());
        return 2;
    }
    if (a->width != b->width || a->height != b->height) {
        fprintf(stderr, "%s is %d x %d, %s is %d x %d\n", a_path, a->width, a->height, b_path,
                b->width, b->height);
        return 1;
    }
    size_t n = (size_t)a->width * a->height, diff = 0;
    for (size_t i = 0; i < n; i++)
        if (!(a->data[i] == b->data[i] || (isnan(a->data[i]) && isnan(b->data[i])))) diff++;
    if (diff) fprintf(stderr, "%s and %s differ at %zu of %zu pixels\n", a_path, b_path, diff, n);
    else printf("%s == %s (%d x %d, every value)\n", a_path, b_path, a->width, a->height);
    svp_image_free(a);
    svp_image_free(b);
    return diff != 0;
}

int main(int argc, char **argv)
{
    if (argc == 5 && !strcmp(argv[1], "qdm")) return qdm(argv[2], atoi(argv[3]), atoi(argv[4]));
    if (argc == 4 && !strcmp(argv[1], "compare")) return compare(argv[2], argv[3]);
    if (argc == 6 && !strcmp(argv[1], "odmr"))
        return odmr(argv[2], atoi(argv[3]), atoi(argv[4]), atoi(argv[5]));
    if (argc == 3 && !strcmp(argv[1], "info")) {
        svp_image *img = NULL;
        svp_mat_info info;
        if (svp_mat_read(argv[2], NULL, &img, &info)) {
            fprintf(stderr, "%s\n", svp_last_error());
            return 1;
        }
        printf("%s %d %d %.17g %.17g\n", info.variable, img->width, img->height, info.pixel_um,
               info.standoff_um);
        svp_image_free(img);
        return 0;
    }
    fprintf(stderr, "usage: see the comment at the top of mat_cli_make.c\n");
    return 2;
}
