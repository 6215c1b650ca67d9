/* MATLAB .mat files (src/io/mat.c): files written here with libmatio in the layouts QDMlab
 * writes (B111dataToPlot.mat: B111ferro, B111para, negDiff, posDiff, ledImg, laser,
 * pixelAlerts; Bz_uc0.mat: Bz, Bt, h, step, corners, newLED; the raw run_0000N.mat: imgStack1/2
 * of numFreqs x (imgNumRows * imgNumCols), imgNumRows, imgNumCols, numFreqs, freqList), read
 * back value for value with MATLAB's column-major order checked on non-symmetric arrays;
 * svpsf's own .mat output read back with libmatio; every refusal's message. Everything is
 * written in a mkdtemp folder that is removed afterwards. */
#include "test_helpers.h"

#include "io/mat.h"

#include <dirent.h>
#include <matio.h>
#include <stdio.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zlib.h>

static char tmpdir[64];

static int make_tmpdir(void **state)
{
    (void)state;
    strcpy(tmpdir, "/tmp/svpsf-test-mat-XXXXXX");
    return mkdtemp(tmpdir) ? 0 : -1;
}

/* With SVP_TEST_MAT_KEEP=DIR the files written here are copied into DIR first (the seeds of
 * the fuzz target tests/fuzz/fuzz_mat.c come from there). */
static void keep_copy(const char *path, const char *name)
{
    const char *keep = getenv("SVP_TEST_MAT_KEEP");
    if (!keep || !*keep) return;
    char dest[600];
    snprintf(dest, sizeof dest, "%s/%s", keep, name);
    FILE *in = fopen(path, "rb"), *out = in ? fopen(dest, "wb") : NULL;
    char buf[4096];
    size_t n;
    while (in && out && (n = fread(buf, 1, sizeof buf, in)) > 0) fwrite(buf, 1, n, out);
    if (in) fclose(in);
    if (out) fclose(out);
}

static int remove_tmpdir(void **state)
{
    (void)state;
    DIR *d = opendir(tmpdir);
    if (!d) return -1;
    struct dirent *e;
    char path[600];
    while ((e = readdir(d)) != NULL) {
        if (!strcmp(e->d_name, ".") || !strcmp(e->d_name, "..")) continue;
        snprintf(path, sizeof path, "%s/%s", tmpdir, e->d_name);
        keep_copy(path, e->d_name);
        remove(path);
    }
    closedir(d);
    return rmdir(tmpdir);
}

static const char *tpath(const char *name)
{
    static char p[8][512];
    static int k;
    k = (k + 1) % 8;
    snprintf(p[k], sizeof p[k], "%s/%s", tmpdir, name);
    return p[k];
}

/* The value MATLAB's element (r, c, k) gets in these tests: distinct for every index, so a
 * transposed or frame-swapped read cannot pass. */
static double value_at(size_t r, size_t c, size_t k) { return 1000.0 * k + 10.0 * r + 0.5 * c - 3; }

/* A column-major rows x cols (x frames) array of class cls, values value_at (+ offset). */
static void *make_data(enum matio_classes cls, size_t rows, size_t cols, size_t frames,
                       double offset)
{
    size_t n = rows * cols * frames, esize = 8;
    if (cls == MAT_C_SINGLE || cls == MAT_C_INT32) esize = 4;
    if (cls == MAT_C_INT16 || cls == MAT_C_UINT16) esize = 2;
    if (cls == MAT_C_UINT8 || cls == MAT_C_INT8) esize = 1;
    unsigned char *buf = malloc(n * esize);
    assert_non_null(buf);
    for (size_t k = 0; k < frames; k++)
        for (size_t c = 0; c < cols; c++)
            for (size_t r = 0; r < rows; r++) {
                size_t i = r + rows * c + rows * cols * k;
                double v = value_at(r, c, k) + offset;
                switch (cls) {
                case MAT_C_DOUBLE: ((double *)buf)[i] = v; break;
                case MAT_C_SINGLE: ((float *)buf)[i] = (float)v; break;
                case MAT_C_INT32: ((int32_t *)buf)[i] = (int32_t)(v * 2); break;
                case MAT_C_INT16: ((int16_t *)buf)[i] = (int16_t)(v * 2); break;
                case MAT_C_UINT16: ((uint16_t *)buf)[i] = (uint16_t)(r + 7 * c + 3 * k); break;
                case MAT_C_UINT8: ((uint8_t *)buf)[i] = (uint8_t)((r + c + k) % 2); break;
                default: fail_msg("class %d", (int)cls);
                }
            }
    return buf;
}

static enum matio_types type_of(enum matio_classes cls)
{
    switch (cls) {
    case MAT_C_DOUBLE: return MAT_T_DOUBLE;
    case MAT_C_SINGLE: return MAT_T_SINGLE;
    case MAT_C_INT32: return MAT_T_INT32;
    case MAT_C_INT16: return MAT_T_INT16;
    case MAT_C_UINT16: return MAT_T_UINT16;
    case MAT_C_UINT8: return MAT_T_UINT8;
    default: return MAT_T_UNKNOWN;
    }
}

/* Adds a variable (data as make_data writes it) to an open file. */
static void add_var(mat_t *mat, const char *name, enum matio_classes cls, int rank,
                    size_t rows, size_t cols, size_t frames, double offset, int logical,
                    enum matio_compression z)
{
    size_t dims[3] = {rows, cols, frames};
    void *data = make_data(cls, rows, cols, rank == 3 ? frames : 1, offset);
    matvar_t *v = Mat_VarCreate(name, cls, type_of(cls), rank, dims, data,
                                logical ? MAT_F_LOGICAL : 0);
    assert_non_null(v);
    assert_int_equal(Mat_VarWrite(mat, v, z), 0);
    Mat_VarFree(v);
    free(data);
}

static void add_scalar(mat_t *mat, const char *name, double value)
{
    size_t dims[2] = {1, 1};
    matvar_t *v = Mat_VarCreate(name, MAT_C_DOUBLE, MAT_T_DOUBLE, 2, dims, &value, 0);
    assert_non_null(v);
    assert_int_equal(Mat_VarWrite(mat, v, MAT_COMPRESSION_NONE), 0);
    Mat_VarFree(v);
}

static mat_t *create(const char *path)
{
    mat_t *mat = Mat_CreateVer(path, NULL, MAT_FT_MAT5);
    assert_non_null(mat);
    return mat;
}

/* Pixel (x = c, y = r) of frame image == value_at(r, c, k) + offset, exactly. */
static void assert_frame(const svp_image *img, size_t rows, size_t cols, size_t k, double offset,
                         double scale)
{
    assert_int_equal(img->width, (int)cols);
    assert_int_equal(img->height, (int)rows);
    for (size_t r = 0; r < rows; r++)
        for (size_t c = 0; c < cols; c++) {
            double want = (value_at(r, c, k) + offset) * scale;
            if (img->data[r * cols + c] != want)
                fail_msg("pixel (x %zu, y %zu) of frame %zu: %.17g, want %.17g", c, r, k,
                         img->data[r * cols + c], want);
        }
}

static void assert_error(svp_status st, svp_status want, const char *message)
{
    if (st != want)
        fail_msg("status %d, want %d (%s); message: %s", (int)st, (int)want, message,
                 svp_last_error());
    if (strcmp(svp_last_error(), message) != 0)
        fail_msg("message\n  %s\nwant\n  %s", svp_last_error(), message);
}

/* ---- QDMlab's layouts ---------------------------------------------------------------------- */

/* Bz_uc0.mat as QDMlab's QDMdataprocessing saves it: Bz, Bt, h, step, corners, newLED; both
 * stored plainly (MATLAB -v6) and compressed (MATLAB's default -v7). */
static void test_bz_file(void **state)
{
    (void)state;
    for (int z = 0; z < 2; z++) {
        enum matio_compression comp = z ? MAT_COMPRESSION_ZLIB : MAT_COMPRESSION_NONE;
        const char *path = tpath(z ? "Bz_uc0_v7.mat" : "Bz_uc0_v6.mat");
        mat_t *mat = create(path);
        add_scalar(mat, "h", 5e-6);
        add_var(mat, "Bz", MAT_C_DOUBLE, 2, 5, 7, 1, 0, 0, comp);
        add_var(mat, "Bt", MAT_C_DOUBLE, 2, 5, 7, 1, 100, 0, comp);
        add_scalar(mat, "step", 4.7e-6);
        add_var(mat, "corners", MAT_C_DOUBLE, 2, 2, 2, 1, 0, 0, comp);
        add_var(mat, "newLED", MAT_C_UINT16, 2, 20, 28, 1, 0, 0, comp);
        Mat_Close(mat);

        svp_image *img = NULL;
        svp_mat_info info;
        ASSERT_OK(svp_mat_read(path, NULL, &img, &info)); /* the default: Bz */
        assert_string_equal(info.variable, "Bz");
        assert_int_equal(info.n_variables, 6);
        assert_frame(img, 5, 7, 0, 0, 1);
        ASSERT_CLOSE(info.pixel_um, 4.7, 1e-12);
        ASSERT_CLOSE(info.standoff_um, 5.0, 1e-12);
        svp_image_free(img);

        /* "FILE.mat:VAR" through the generic reader: the LED image (uint16) */
        char spec[600];
        snprintf(spec, sizeof spec, "%s:newLED", path);
        ASSERT_OK(svp_image_read(spec, &img));
        assert_int_equal(img->width, 28);
        assert_int_equal(img->height, 20);
        for (int y = 0; y < 20; y++)
            for (int x = 0; x < 28; x++)
                assert_true(img->data[y * 28 + x] == (double)(y + 7 * x));
        svp_image_free(img);
        ASSERT_OK(svp_mat_read(path, "Bt", &img, &info));
        assert_frame(img, 5, 7, 0, 100, 1);
        svp_image_free(img);
    }

    /* a step stored in micrometres (as some of QDMlab's files hold it: 4.68) */
    const char *um = tpath("Bz_step_um.mat");
    mat_t *mat = create(um);
    add_var(mat, "Bz", MAT_C_DOUBLE, 2, 3, 4, 1, 0, 0, MAT_COMPRESSION_NONE);
    add_scalar(mat, "step", 4.68);
    Mat_Close(mat);
    svp_image *img = NULL;
    svp_mat_info info;
    ASSERT_OK(svp_mat_read(um, NULL, &img, &info));
    assert_true(info.pixel_um == 4.68);
    assert_true(info.standoff_um == 0);
    assert_int_equal(info.step_elements, 1);
    svp_image_free(img);

    /* `step` as [dx dy]: square pixels give the size, others none, and step_elements says why;
     * the map is read either way */
    const double pairs[3][3] = {{4.7e-6, 4.7e-6, 1}, {4.7e-6, 5.2e-6, 2}, {4.7e-6, 4.7e-6, 3}};
    for (int k = 0; k < 3; k++) {
        const char *pp = tpath("Bz_step_pair.mat");
        remove(pp);
        mat = create(pp);
        add_var(mat, "Bz", MAT_C_DOUBLE, 2, 3, 4, 1, 0, 0, MAT_COMPRESSION_NONE);
        double values[3] = {pairs[k][0], pairs[k][1], pairs[k][1]};
        size_t dims[2] = {1, k == 2 ? 3 : 2};
        matvar_t *v = Mat_VarCreate("step", MAT_C_DOUBLE, MAT_T_DOUBLE, 2, dims, values, 0);
        assert_int_equal(Mat_VarWrite(mat, v, MAT_COMPRESSION_NONE), 0);
        Mat_VarFree(v);
        Mat_Close(mat);
        ASSERT_OK(svp_mat_read(pp, NULL, &img, &info));
        assert_frame(img, 3, 4, 0, 0, 1);
        assert_int_equal(info.step_elements, k == 2 ? 3 : 2);
        if (k == 0)
            ASSERT_CLOSE(info.pixel_um, 4.7, 1e-12);
        else
            assert_true(info.pixel_um == 0);
        svp_image_free(img);
    }
}

/* B111dataToPlot.mat as QDMlab's get_B111 saves it ('-struct': one variable per field). */
static void test_b111_file(void **state)
{
    (void)state;
    const char *path = tpath("B111dataToPlot.mat");
    mat_t *mat = create(path);
    add_var(mat, "negDiff", MAT_C_DOUBLE, 2, 6, 9, 1, 1, 0, MAT_COMPRESSION_ZLIB);
    add_var(mat, "posDiff", MAT_C_DOUBLE, 2, 6, 9, 1, 2, 0, MAT_COMPRESSION_ZLIB);
    add_var(mat, "B111ferro", MAT_C_DOUBLE, 2, 6, 9, 1, 0.25, 0, MAT_COMPRESSION_ZLIB);
    add_var(mat, "B111para", MAT_C_SINGLE, 2, 6, 9, 1, -0.5, 0, MAT_COMPRESSION_ZLIB);
    add_var(mat, "chi2Pos1", MAT_C_DOUBLE, 2, 6, 9, 1, 3, 0, MAT_COMPRESSION_ZLIB);
    add_var(mat, "ledImg", MAT_C_DOUBLE, 2, 24, 36, 1, 0, 0, MAT_COMPRESSION_ZLIB);
    add_var(mat, "laser", MAT_C_INT16, 2, 24, 36, 1, 0, 0, MAT_COMPRESSION_ZLIB);
    add_var(mat, "pixelAlerts", MAT_C_UINT8, 2, 6, 9, 1, 0, 1, MAT_COMPRESSION_ZLIB);
    Mat_Close(mat);

    svp_image *img = NULL;
    svp_mat_info info;
    ASSERT_OK(svp_mat_read(path, NULL, &img, &info)); /* the default: B111ferro */
    assert_string_equal(info.variable, "B111ferro");
    assert_true(info.pixel_um == 0);
    assert_frame(img, 6, 9, 0, 0.25, 1);
    svp_image_free(img);
    ASSERT_OK(svp_mat_read(path, "B111para", &img, &info)); /* single: exact in float */
    assert_frame(img, 6, 9, 0, -0.5, 1);
    svp_image_free(img);
    ASSERT_OK(svp_mat_read(path, "ledImg", &img, NULL));
    assert_frame(img, 24, 36, 0, 0, 1);
    svp_image_free(img);
    ASSERT_OK(svp_mat_read(path, "laser", &img, NULL)); /* int16: 2 * value */
    assert_frame(img, 24, 36, 0, 0, 2);
    svp_image_free(img);
    ASSERT_OK(svp_mat_read(path, "pixelAlerts", &img, NULL)); /* logical */
    for (int y = 0; y < 6; y++)
        for (int x = 0; x < 9; x++) assert_true(img->data[y * 9 + x] == (double)((x + y) % 2));
    svp_image_free(img);
}

/* Stacks: a 3-D array rows x cols x frames, and the raw run_0000N.mat layout. */
static void test_stacks(void **state)
{
    (void)state;
    const char *path = tpath("stack3d.mat");
    mat_t *mat = create(path);
    add_var(mat, "odmr", MAT_C_SINGLE, 3, 4, 5, 3, 0, 0, MAT_COMPRESSION_ZLIB);
    add_var(mat, "ledImg", MAT_C_DOUBLE, 2, 4, 5, 1, 0, 0, MAT_COMPRESSION_ZLIB);
    Mat_Close(mat);
    svp_stack *s = NULL;
    svp_mat_info info;
    ASSERT_OK(svp_mat_read_stack(path, NULL, &s, &info));
    assert_string_equal(info.variable, "odmr");
    assert_int_equal(s->n_frames, 3);
    assert_int_equal(s->width, 5);
    assert_int_equal(s->height, 4);
    for (int k = 0; k < 3; k++) assert_frame(s->frame[k], 4, 5, (size_t)k, 0, 1);
    svp_stack_free(s);
    /* through svp_stack_read, and a 2-D variable as a stack of one */
    char spec[600];
    snprintf(spec, sizeof spec, "%s:ledImg", path);
    ASSERT_OK(svp_stack_read(spec, &s));
    assert_int_equal(s->n_frames, 1);
    assert_frame(s->frame[0], 4, 5, 0, 0, 1);
    svp_stack_free(s);
    /* a stack where one image is expected */
    svp_image *img = NULL;
    char want[900];
    snprintf(want, sizeof want,
             "%s: variable odmr is a stack of 3 frames (3-D array of 4 x 5 x 3): expected one "
             "image (a stack is read as an ODMR stack by svp_stack_read / svpsf fit-odmr)",
             path);
    snprintf(spec, sizeof spec, "%s:odmr", path);
    assert_error(svp_image_read(spec, &img), SVP_ERR_FORMAT, want);
    assert_null(img);

    /* the raw layout: imgStackN is numFreqs x (rows * cols), frame k = row k, the pixels of a
     * frame row after row: pixel (r, c) at column r * imgNumCols + c */
    const size_t rows = 3, cols = 4, nf = 5;
    const char *raw = tpath("run_00000.mat");
    mat = create(raw);
    add_scalar(mat, "numFreqs", (double)nf);
    add_scalar(mat, "imgNumRows", (double)rows);
    add_scalar(mat, "imgNumCols", (double)cols);
    for (int stack = 1; stack <= 2; stack++) {
        double *d = malloc(nf * rows * cols * sizeof *d);
        for (size_t k = 0; k < nf; k++)
            for (size_t r = 0; r < rows; r++)
                for (size_t c = 0; c < cols; c++)
                    d[k + nf * (r * cols + c)] = value_at(r, c, k) + 10000.0 * stack;
        size_t dims[2] = {nf, rows * cols};
        matvar_t *v = Mat_VarCreate(stack == 1 ? "imgStack1" : "imgStack2", MAT_C_DOUBLE,
                                    MAT_T_DOUBLE, 2, dims, d, 0);
        assert_int_equal(Mat_VarWrite(mat, v, MAT_COMPRESSION_ZLIB), 0);
        Mat_VarFree(v);
        free(d);
    }
    add_var(mat, "freqList", MAT_C_DOUBLE, 2, 1, 2 * nf, 1, 0, 0, MAT_COMPRESSION_NONE);
    Mat_Close(mat);
    ASSERT_OK(svp_mat_read_stack(raw, NULL, &s, &info)); /* the default: imgStack1 */
    assert_string_equal(info.variable, "imgStack1");
    assert_int_equal(s->n_frames, (int)nf);
    for (size_t k = 0; k < nf; k++) assert_frame(s->frame[k], rows, cols, k, 10000.0, 1);
    svp_stack_free(s);
    ASSERT_OK(svp_mat_read_stack(raw, "imgStack2", &s, &info));
    for (size_t k = 0; k < nf; k++) assert_frame(s->frame[k], rows, cols, k, 20000.0, 1);
    svp_stack_free(s);
    snprintf(want, sizeof want,
             "%s: variable imgStack1 is a stack of 5 frames (QDMlab's raw layout, 3 x 4 "
             "pixels): expected one image (a stack is read as an ODMR stack by svp_stack_read "
             "/ svpsf fit-odmr)",
             raw);
    assert_error(svp_mat_read(raw, "imgStack1", &img, NULL), SVP_ERR_FORMAT, want);

    /* imgNumRows x imgNumCols not matching the stack */
    const char *bad = tpath("run_bad.mat");
    mat = create(bad);
    add_scalar(mat, "imgNumRows", 3);
    add_scalar(mat, "imgNumCols", 5);
    add_var(mat, "imgStack1", MAT_C_DOUBLE, 2, 5, 12, 1, 0, 0, MAT_COMPRESSION_NONE);
    Mat_Close(mat);
    snprintf(want, sizeof want,
             "%s: imgStack1 is 5 x 12 but imgNumRows x imgNumCols = 3 x 5 = 15 pixels per frame",
             bad);
    assert_error(svp_mat_read_stack(bad, NULL, &s, NULL), SVP_ERR_FORMAT, want);
    assert_null(s);
    /* the raw layout without its sizes: refused naming what is missing (it was read as one
     * frame of 5 x 12, and fit-odmr said "1 frame") */
    const char *nosize = tpath("run_nosize.mat");
    mat = create(nosize);
    add_scalar(mat, "imgNumRows", 3);
    add_var(mat, "imgStack1", MAT_C_DOUBLE, 2, 5, 12, 1, 0, 0, MAT_COMPRESSION_NONE);
    Mat_Close(mat);
    snprintf(want, sizeof want,
             "%s: variable imgStack1 (5 x 12) is QDMlab's raw stack, one frame per row, but the "
             "file holds no imgNumCols: the frames' size is unknown (add imgNumRows and "
             "imgNumCols, or save the stack as a 3-D array)",
             nosize);
    assert_error(svp_mat_read_stack(nosize, "imgStack1", &s, NULL), SVP_ERR_FORMAT, want);
    assert_null(s);
}

/* svpsf's own output: read back with libmatio (column-major, name, step in metres) and with
 * svp_mat_read; no overwrite without leave; variable names. */
static void test_write(void **state)
{
    (void)state;
    svp_image *a = test_random_image(7, 5, 11), *b = test_random_image(3, 4, 12);
    a->data[3] = NAN;
    a->data[4] = -INFINITY;
    const char *path = tpath("maps.mat");
    const char *names[2] = {"Bz", "ledImg"};
    const svp_image *images[2] = {a, b};
    ASSERT_OK(svp_mat_write(path, 2, names, images, 2.5, 0));

    mat_t *mat = Mat_Open(path, MAT_ACC_RDONLY);
    assert_non_null(mat);
    assert_int_equal(Mat_GetVersion(mat), MAT_FT_MAT5);
    matvar_t *v = Mat_VarRead(mat, "Bz");
    assert_non_null(v);
    assert_int_equal(v->class_type, MAT_C_DOUBLE);
    assert_int_equal(v->rank, 2);
    assert_int_equal(v->dims[0], 5); /* rows */
    assert_int_equal(v->dims[1], 7); /* columns */
    assert_int_equal(v->compression, MAT_COMPRESSION_ZLIB);
    const double *d = v->data;
    for (int y = 0; y < 5; y++)
        for (int x = 0; x < 7; x++) {
            double want = a->data[y * 7 + x], got = d[y + 5 * x];
            assert_true(got == want || (isnan(got) && isnan(want)));
        }
    Mat_VarFree(v);
    v = Mat_VarRead(mat, "step");
    assert_non_null(v);
    assert_true(((const double *)v->data)[0] == 2.5e-6);
    Mat_VarFree(v);
    Mat_Close(mat);

    svp_image *back = NULL;
    svp_mat_info info;
    ASSERT_OK(svp_mat_read(path, "ledImg", &back, &info));
    assert_memory_equal(back->data, b->data, sizeof(double) * 12);
    ASSERT_CLOSE(info.pixel_um, 2.5, 1e-12);
    svp_image_free(back);

    /* no overwrite without leave; the earlier file intact */
    char want[900];
    snprintf(want, sizeof want, "%s exists (use --force to overwrite)", path);
    assert_error(svp_mat_write(path, 1, names, images, 0, 0), SVP_ERR_EXISTS, want);
    ASSERT_OK(svp_mat_read(path, "Bz", &back, NULL));
    svp_image_free(back);
    ASSERT_OK(svp_mat_write(path, 1, names + 1, images + 1, 0, 1));
    ASSERT_OK(svp_mat_read(path, NULL, &back, &info)); /* only ledImg now */
    assert_string_equal(info.variable, "ledImg");
    assert_int_equal(info.n_variables, 1);
    svp_image_free(back);

    /* svp_image_write: the variable named after the file, or OUT.mat:VAR */
    ASSERT_OK(svp_image_write(tpath("field-corrected.mat"), a, SVP_FORMAT_AUTO, 0));
    ASSERT_OK(svp_mat_read(tpath("field-corrected.mat"), NULL, &back, &info));
    assert_string_equal(info.variable, "field_corrected");
    svp_image_free(back);
    char spec[600];
    snprintf(spec, sizeof spec, "%s:Bz", tpath("named.mat"));
    ASSERT_OK(svp_image_write(spec, b, SVP_FORMAT_AUTO, 0));
    ASSERT_OK(svp_image_read(tpath("named.mat"), &back));
    assert_memory_equal(back->data, b->data, sizeof(double) * 12);
    svp_image_free(back);

    /* bad names */
    const char *bad_names[2] = {"1x", "Bz"};
    snprintf(want, sizeof want,
             "%s: '1x' is not a MATLAB variable name (a letter, then letters, digits or '_', at "
             "most 63)",
             tpath("x.mat"));
    assert_error(svp_mat_write(tpath("x.mat"), 1, bad_names, images, 0, 0), SVP_ERR_INVALID,
                 want);
    const char *twice[2] = {"Bz", "Bz"};
    snprintf(want, sizeof want, "%s: variable 'Bz' given twice", tpath("x.mat"));
    assert_error(svp_mat_write(tpath("x.mat"), 2, twice, images, 0, 0), SVP_ERR_INVALID, want);
    assert_int_equal(access(tpath("x.mat"), F_OK), -1); /* nothing written */
    svp_image_free(a);
    svp_image_free(b);
}

/* ---- refusals ------------------------------------------------------------------------------ */

static void test_refusals(void **state)
{
    (void)state;
    const char *path = tpath("kinds.mat");
    mat_t *mat = create(path);
    add_var(mat, "map", MAT_C_DOUBLE, 2, 2, 3, 1, 0, 0, MAT_COMPRESSION_NONE);
    add_var(mat, "other", MAT_C_DOUBLE, 2, 2, 3, 1, 0, 0, MAT_COMPRESSION_NONE);
    {
        double re[2] = {1, 2}, im[2] = {3, 4};
        mat_complex_split_t z = {re, im};
        size_t dims[2] = {1, 2};
        matvar_t *v = Mat_VarCreate("Z", MAT_C_DOUBLE, MAT_T_DOUBLE, 2, dims, &z, MAT_F_COMPLEX);
        assert_int_equal(Mat_VarWrite(mat, v, MAT_COMPRESSION_NONE), 0);
        Mat_VarFree(v);
    }
    {
        double data[2] = {5, 6};
        mat_uint32_t ir[2] = {0, 1}, jc[3] = {0, 1, 2};
        mat_sparse_t sp = {2, ir, 2, jc, 3, 2, data};
        size_t dims[2] = {2, 2};
        matvar_t *v = Mat_VarCreate("S", MAT_C_SPARSE, MAT_T_DOUBLE, 2, dims, &sp,
                                    MAT_F_DONT_COPY_DATA);
        assert_int_equal(Mat_VarWrite(mat, v, MAT_COMPRESSION_NONE), 0);
        Mat_VarFree(v);
    }
    {
        size_t dims[2] = {1, 1};
        const char *fields[1] = {"a"};
        matvar_t *st = Mat_VarCreateStruct("St", 2, dims, fields, 1);
        double one = 1;
        size_t d1[2] = {1, 1};
        Mat_VarSetStructFieldByName(st, "a", 0,
                                    Mat_VarCreate("a", MAT_C_DOUBLE, MAT_T_DOUBLE, 2, d1, &one, 0));
        assert_int_equal(Mat_VarWrite(mat, st, MAT_COMPRESSION_NONE), 0);
        Mat_VarFree(st);
        matvar_t *cells[2] = {
            Mat_VarCreate(NULL, MAT_C_DOUBLE, MAT_T_DOUBLE, 2, d1, &one, 0), NULL};
        size_t cd[2] = {1, 1};
        matvar_t *cell = Mat_VarCreate("C", MAT_C_CELL, MAT_T_CELL, 2, cd, cells, 0);
        assert_int_equal(Mat_VarWrite(mat, cell, MAT_COMPRESSION_NONE), 0);
        Mat_VarFree(cell);
        char text[3] = "abc";
        size_t td[2] = {1, 3};
        matvar_t *t = Mat_VarCreate("T", MAT_C_CHAR, MAT_T_UINT8, 2, td, text, 0);
        assert_int_equal(Mat_VarWrite(mat, t, MAT_COMPRESSION_NONE), 0);
        Mat_VarFree(t);
    }
    {
        size_t dims[4] = {2, 2, 2, 2};
        double d[16] = {0};
        matvar_t *v = Mat_VarCreate("F", MAT_C_DOUBLE, MAT_T_DOUBLE, 4, dims, d, 0);
        assert_int_equal(Mat_VarWrite(mat, v, MAT_COMPRESSION_NONE), 0);
        Mat_VarFree(v);
        size_t ed[2] = {0, 3};
        v = Mat_VarCreate("E", MAT_C_DOUBLE, MAT_T_DOUBLE, 2, ed, NULL, 0);
        assert_int_equal(Mat_VarWrite(mat, v, MAT_COMPRESSION_NONE), 0);
        Mat_VarFree(v);
    }
    Mat_Close(mat);

    svp_image *img = NULL;
    char want[1200];
    snprintf(want, sizeof want,
             "%s: no variable 'nope' (the file holds: map (2 x 3 double), other (2 x 3 double), "
             "Z (1 x 2 complex double), S (2 x 2 sparse), St (1 x 1 struct), C (1 x 1 cell "
             "array), T (1 x 3 char), F (2 x 2 x 2 x ... double), E (0 x 3 double))",
             path);
    assert_error(svp_mat_read(path, "nope", &img, NULL), SVP_ERR_FORMAT, want);
    snprintf(want, sizeof want,
             "%s: no variable to read by default (Bz, B111ferro, B111para, or the only 2-D "
             "numeric array); name one as %s:VAR (the file holds: map (2 x 3 double), other "
             "(2 x 3 double), Z (1 x 2 complex double), S (2 x 2 sparse), St (1 x 1 struct), C "
             "(1 x 1 cell array), T (1 x 3 char), F (2 x 2 x 2 x ... double), E (0 x 3 double))",
             path, path);
    assert_error(svp_mat_read(path, NULL, &img, NULL), SVP_ERR_FORMAT, want);
    static const struct {
        const char *var, *fault;
    } bad[] = {
        {"Z", "variable Z is complex: expected a real numeric array"},
        {"S", "variable S is a sparse matrix (save it with full(...)): expected a real numeric "
              "array"},
        {"St", "variable St is a struct: expected a real numeric array"},
        {"C", "variable C is a cell array: expected a real numeric array"},
        {"T", "variable T is text (char): expected a real numeric array"},
        {"F", "variable F has 4 dimensions: expected a 2-D image"},
        {"E", "variable E is empty (0 x 3)"},
    };
    for (size_t i = 0; i < sizeof bad / sizeof *bad; i++) {
        snprintf(want, sizeof want, "%s: %s", path, bad[i].fault);
        assert_error(svp_mat_read(path, bad[i].var, &img, NULL), SVP_ERR_FORMAT, want);
        assert_null(img);
    }
    snprintf(want, sizeof want,
             "%s:1x: '1x' is not a MATLAB variable name (a letter, then letters, digits or '_', "
             "at most 63)",
             path);
    char spec[600];
    snprintf(spec, sizeof spec, "%s:1x", path);
    assert_error(svp_image_read(spec, &img), SVP_ERR_INVALID, want);

    /* not a MAT-file, short, v7.3 (HDF5), missing */
    const char *text = tpath("text.mat");
    FILE *f = fopen(text, "w");
    for (int i = 0; i < 20; i++) fputs("0.5 0.25 0.125\n", f);
    fclose(f);
    snprintf(want, sizeof want,
             "%s: not a MATLAB v5/v7 .mat file (no MAT-file header; v4 files are not read)",
             text);
    assert_error(svp_image_read(text, &img), SVP_ERR_FORMAT, want);
    const char *shortf = tpath("short.mat");
    f = fopen(shortf, "w");
    fputs("MATLAB 5.0 MAT-file", f);
    fclose(f);
    snprintf(want, sizeof want,
             "%s: not a MATLAB .mat file (shorter than the 128-byte MAT-file header)", shortf);
    assert_error(svp_image_read(shortf, &img), SVP_ERR_FORMAT, want);
    const char *v73 = tpath("v73.mat");
    mat = Mat_CreateVer(v73, NULL, MAT_FT_MAT73);
    if (mat) { /* Debian's libmatio is built with HDF5: a real v7.3 file */
        add_var(mat, "Bz", MAT_C_DOUBLE, 2, 2, 3, 1, 0, 0, MAT_COMPRESSION_NONE);
        Mat_Close(mat);
        snprintf(want, sizeof want,
                 "%s: a MATLAB v7.3 (HDF5) file: not read; svpsf reads the v5/v7 files MATLAB's "
                 "save writes by default (in MATLAB: save(FILE, ..., '-v7'))",
                 v73);
        assert_error(svp_image_read(v73, &img), SVP_ERR_FORMAT, want);
    } else {
        print_message("libmatio without HDF5: no v7.3 file to refuse\n");
    }
    snprintf(want, sizeof want, "%s: no such file", tpath("absent.mat"));
    assert_error(svp_image_read(tpath("absent.mat"), &img), SVP_ERR_IO, want);

    /* a bad step */
    const char *badstep = tpath("badstep.mat");
    mat = create(badstep);
    add_var(mat, "Bz", MAT_C_DOUBLE, 2, 2, 3, 1, 0, 0, MAT_COMPRESSION_NONE);
    add_scalar(mat, "step", -1);
    Mat_Close(mat);
    snprintf(want, sizeof want, "%s: step = -1 is not a pixel size (expected > 0)", badstep);
    assert_error(svp_image_read(badstep, &img), SVP_ERR_FORMAT, want);
}

/* Sizes claimed beyond the file, and truncation. */
static void test_too_large_and_truncated(void **state)
{
    (void)state;
    const char *path = tpath("big.mat");
    mat_t *mat = create(path);
    add_var(mat, "Bz", MAT_C_DOUBLE, 2, 2, 3, 1, 0, 0, MAT_COMPRESSION_NONE);
    Mat_Close(mat);
    /* the plain v5 layout: header (128), miMATRIX tag (8), array flags (16), dimensions tag (8)
     * then the two int32 dimensions at bytes 160 and 164 */
    FILE *f = fopen(path, "r+b");
    assert_non_null(f);
    unsigned char dims[8];
    fseek(f, 160, SEEK_SET);
    assert_int_equal(fread(dims, 1, 8, f), 8);
    assert_int_equal(dims[0], 2); /* little-endian 2, then 3 */
    assert_int_equal(dims[4], 3);
    const int32_t big = 100000;
    fseek(f, 160, SEEK_SET);
    fwrite(&big, 4, 1, f);
    fwrite(&big, 4, 1, f);
    fclose(f);
    struct stat sb;
    stat(path, &sb);
    svp_image *img = NULL;
    char want[900];
    snprintf(want, sizeof want,
             "%s: data element 1 (at byte 128): variable Bz: 48 bytes of data for 10000000000 "
             "values of 8 bytes",
             path);
    assert_error(svp_image_read(path, &img), SVP_ERR_FORMAT, want);
    (void)sb;

    /* a compressed variable claiming 20000 x 20000 uint8 values whose stream holds only the
     * variable's head: refused by deflate's largest ratio (1032:1) before any allocation */
    uint32_t inner[] = {MAT_T_MATRIX, 0,      MAT_T_UINT32, 8, MAT_C_UINT8, 0, MAT_T_INT32, 8,
                        20000,        20000,  0x00020001,   0, MAT_T_UINT8, 400000000};
    memcpy(&inner[11], "Bz\0\0", 4);
    inner[1] = 48 + 400000000;
    unsigned char packed[256];
    uLongf packed_n = sizeof packed;
    assert_int_equal(compress2(packed, &packed_n, (const Bytef *)inner, sizeof inner, 6), Z_OK);
    const char *zbig = tpath("zbig.mat");
    mat = create(zbig);
    Mat_Close(mat); /* the header only */
    f = fopen(zbig, "ab");
    uint32_t tag[2] = {MAT_T_COMPRESSED, (uint32_t)packed_n};
    fwrite(tag, 4, 2, f);
    fwrite(packed, 1, packed_n, f);
    fclose(f);
    snprintf(want, sizeof want,
             "%s: variable Bz claims 400000000 elements, more than its %lld compressed bytes "
             "can hold (corrupt)",
             zbig, (long long)packed_n + 8);
    assert_error(svp_image_read(zbig, &img), SVP_ERR_FORMAT, want);

    /* truncated files: every cut of a compressed and of a plain file ends in an error naming
     * the file (or, cut after the last variable's data, in the same values) */
    for (int z = 0; z < 2; z++) {
        const char *whole = tpath("whole.mat");
        remove(whole);
        mat = create(whole);
        add_var(mat, "Bz", MAT_C_DOUBLE, 2, 9, 11, 1, 0, 0,
                z ? MAT_COMPRESSION_ZLIB : MAT_COMPRESSION_NONE);
        Mat_Close(mat);
        stat(whole, &sb);
        unsigned char *bytes = malloc((size_t)sb.st_size);
        f = fopen(whole, "rb");
        assert_int_equal(fread(bytes, 1, (size_t)sb.st_size, f), (size_t)sb.st_size);
        fclose(f);
        const char *cut = tpath("cut.mat");
        for (long n = 0; n < (long)sb.st_size; n += 7) {
            f = fopen(cut, "wb");
            fwrite(bytes, 1, (size_t)n, f);
            fclose(f);
            svp_status st = svp_image_read(cut, &img);
            if (st == SVP_OK) fail_msg("a file cut to %ld of %lld bytes was read", n, (long long)sb.st_size);
            assert_null(img);
            assert_int_equal(strncmp(svp_last_error(), cut, strlen(cut)), 0);
        }
        free(bytes);
    }
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_bz_file),
        cmocka_unit_test(test_b111_file),
        cmocka_unit_test(test_stacks),
        cmocka_unit_test(test_write),
        cmocka_unit_test(test_refusals),
        cmocka_unit_test(test_too_large_and_truncated),
    };
    return cmocka_run_group_tests(tests, make_tmpdir, remove_tmpdir);
}
