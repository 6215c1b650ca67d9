/* File I/O: .npy / text / TIFF / PNG round trips, hand-built numpy and TIFF fixtures, truncated
 * and missing files, atomic no-overwrite writes, PSF YAML files with their exact errors, the
 * YAML helpers and writer, and the JSON writer. Everything is written in a mkdtemp folder that
 * the group teardown removes. */
#include "test_helpers.h"

#include "core/internal.h"
#include "io/image_io.h"
#include "io/json.h"
#include "io/yaml.h"

#include <dirent.h>
#include <errno.h>
#include <stdio.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

static char tmpdir[64];

static int make_tmpdir(void **state)
{
    (void)state;
    strcpy(tmpdir, "/tmp/svpsf-test-io-XXXXXX");
    return mkdtemp(tmpdir) ? 0 : -1;
}

static int remove_tmpdir(void **state)
{
    (void)state;
    DIR *d = opendir(tmpdir);
    if (!d) return -1;
    struct dirent *e;
    char path[512];
    while ((e = readdir(d)) != NULL) {
        if (!strcmp(e->d_name, ".") || !strcmp(e->d_name, "..")) continue;
        snprintf(path, sizeof path, "%s/%s", tmpdir, e->d_name);
        unlink(path);
    }
    closedir(d);
    return rmdir(tmpdir);
}

/* A path inside the test folder (static buffers, rotating, so a test can hold a few). */
static const char *tmp_path(const char *name)
{
    static char bufs[8][512];
    static int next = 0;
    char *p = bufs[next++ % 8];
    snprintf(p, 512, "%s/%s", tmpdir, name);
    return p;
}

static void write_bytes(const char *path, const void *data, size_t size)
{
    FILE *f = fopen(path, "wb");
    if (!f) fail_msg("cannot create %s", path);
    if (size && fwrite(data, 1, size, f) != size) fail_msg("cannot write %s", path);
    fclose(f);
}

static void write_string(const char *path, const char *text)
{
    write_bytes(path, text, strlen(text));
}

static unsigned char *slurp(const char *path, size_t *size)
{
    FILE *f = fopen(path, "rb");
    if (!f) fail_msg("cannot open %s", path);
    fseek(f, 0, SEEK_END);
    long n = ftell(f);
    fseek(f, 0, SEEK_SET);
    unsigned char *buf = malloc((size_t)n + 1);
    if (fread(buf, 1, (size_t)n, f) != (size_t)n) fail_msg("cannot read %s", path);
    fclose(f);
    buf[n] = 0;
    *size = (size_t)n;
    return buf;
}

static void assert_contains(const char *haystack, const char *needle)
{
    if (!strstr(haystack, needle)) fail_msg("message \"%s\" lacks \"%s\"", haystack, needle);
}

/* Asserts status and that the message contains `needle`. */
#define ASSERT_FAILS(expr, status, needle)                                                         \
    do {                                                                                           \
        svp_status st_ = (expr);                                                                   \
        if (st_ != (status))                                                                       \
            fail_msg("%s returned %d (%s), expected %d", #expr, (int)st_, svp_last_error(),        \
                     (int)(status));                                                               \
        assert_contains(svp_last_error(), (needle));                                               \
    } while (0)

/* No temporary files of atomic writes (".<name>.svpsf-tmp-<pid>-XXXXXX") left behind. */
static void assert_no_temporaries(void)
{
    DIR *d = opendir(tmpdir);
    struct dirent *e;
    while ((e = readdir(d)) != NULL)
        if (strstr(e->d_name, SVP_IO_TEMP_TAG))
            fail_msg("temporary file left behind: %s", e->d_name);
    closedir(d);
}

/* An image with awkward values: negative, tiny, huge, non-representable decimals. */
static svp_image *awkward_image(int w, int h, int with_nonfinite)
{
    svp_image *img = test_random_image(w, h, 42);
    for (int i = 0; i < w * h; i++) img->data[i] = (img->data[i] - 0.3) * pow(10.0, i % 9 - 4);
    img->data[0] = 0.1;
    img->data[1] = -0.0;
    img->data[2] = 1.0 / 3.0;
    img->data[3] = 5e-324; /* the smallest subnormal */
    if (with_nonfinite) {
        img->data[4] = NAN;
        img->data[5] = INFINITY;
        img->data[6] = -INFINITY;
    }
    return img;
}

static int same_bits(double a, double b) { return memcmp(&a, &b, sizeof a) == 0; }

/* ---- .npy ------------------------------------------------------------------------------------ */

static void test_npy_round_trip_exact(void **state)
{
    (void)state;
    svp_image *img = awkward_image(7, 5, 1), *back = NULL;
    const char *path = tmp_path("round.npy");
    ASSERT_OK(svp_image_write(path, img, SVP_FORMAT_AUTO, 0));
    ASSERT_OK(svp_image_read(path, &back));
    assert_int_equal(back->width, 7);
    assert_int_equal(back->height, 5);
    for (int i = 0; i < 35; i++)
        if (!same_bits(img->data[i], back->data[i]) &&
            !(isnan(img->data[i]) && isnan(back->data[i])))
            fail_msg("pixel %d: wrote %.17g read %.17g", i, img->data[i], back->data[i]);
    /* the header numpy expects: version 1.0, data aligned to 64 bytes, newline-terminated */
    size_t size;
    unsigned char *bytes = slurp(path, &size);
    assert_memory_equal(bytes, "\x93NUMPY\x01\x00", 8);
    size_t header_len = bytes[8] | (size_t)bytes[9] << 8;
    assert_int_equal((10 + header_len) % 64, 0);
    assert_int_equal(bytes[10 + header_len - 1], '\n');
    const char *dict = "{'descr': '<f8', 'fortran_order': False, 'shape': (5, 7), }";
    assert_memory_equal(bytes + 10, dict, strlen(dict));
    assert_int_equal(size, 10 + header_len + 35 * 8);
    free(bytes);
    assert_no_temporaries();
    svp_image_free(img);
    svp_image_free(back);
}

/* Builds a .npy file: magic, version, header dict padded to 64 bytes, then `data`. */
static void write_npy_fixture(const char *path, int major, const char *dict, const void *data,
                              size_t data_size)
{
    size_t prefix = major == 1 ? 10 : 12;
    size_t len = strlen(dict) + 1;
    size_t total = (prefix + len + 63) / 64 * 64;
    size_t header_len = total - prefix;
    unsigned char *buf = calloc(1, total + data_size + 1);
    memcpy(buf, "\x93NUMPY", 6);
    buf[6] = (unsigned char)major;
    buf[7] = 0;
    buf[8] = (unsigned char)(header_len & 0xff);
    buf[9] = (unsigned char)(header_len >> 8);
    memcpy(buf + prefix, dict, strlen(dict));
    memset(buf + prefix + strlen(dict), ' ', header_len - strlen(dict) - 1);
    buf[total - 1] = '\n';
    if (data_size) memcpy(buf + total, data, data_size);
    write_bytes(path, buf, total + data_size);
    free(buf);
}

static void put_be(unsigned char *p, uint64_t v, int size)
{
    for (int k = 0; k < size; k++) p[k] = (unsigned char)(v >> (8 * (size - 1 - k)));
}

static void put_le(unsigned char *p, uint64_t v, int size)
{
    for (int k = 0; k < size; k++) p[k] = (unsigned char)(v >> (8 * k));
}

static void test_npy_numpy_fixtures(void **state)
{
    (void)state;
    svp_image *img = NULL;

    /* float32, Fortran order, little-endian, shape (3, 4): element (y, x) = y - 0.25 x, stored
     * column by column */
    {
        unsigned char data[12 * 4];
        for (int x = 0, k = 0; x < 4; x++)
            for (int y = 0; y < 3; y++, k++) {
                float v = (float)y - 0.25f * (float)x;
                uint32_t bits;
                memcpy(&bits, &v, 4);
                put_le(data + 4 * k, bits, 4);
            }
        const char *path = tmp_path("f4_fortran.npy");
        write_npy_fixture(path, 1, "{'descr': '<f4', 'fortran_order': True, 'shape': (3, 4), }",
                          data, sizeof data);
        ASSERT_OK(svp_image_read(path, &img));
        assert_int_equal(img->width, 4);
        assert_int_equal(img->height, 3);
        for (int y = 0; y < 3; y++)
            for (int x = 0; x < 4; x++) assert_true(img->data[y * 4 + x] == y - 0.25 * x);
        svp_image_free(img);
    }
    /* big-endian float64, C order, version 2.0 header, shape (2, 3) */
    {
        unsigned char data[6 * 8];
        const double values[6] = {1.5, -2.25, 1e300, -1e-300, 0.1, 3.0};
        for (int k = 0; k < 6; k++) {
            uint64_t bits;
            memcpy(&bits, &values[k], 8);
            put_be(data + 8 * k, bits, 8);
        }
        const char *path = tmp_path("f8_big.npy");
        write_npy_fixture(path, 2, "{'descr': '>f8', 'fortran_order': False, 'shape': (2, 3), }",
                          data, sizeof data);
        ASSERT_OK(svp_image_read(path, &img));
        assert_int_equal(img->width, 3);
        assert_int_equal(img->height, 2);
        for (int k = 0; k < 6; k++) assert_true(same_bits(img->data[k], values[k]));
        svp_image_free(img);
    }
    /* integers of every width and sign, both byte orders, converted without scaling */
    struct {
        const char *descr;
        int size, big, is_signed;
    } ints[] = {{"|i1", 1, 0, 1}, {"|u1", 1, 0, 0}, {"<i2", 2, 0, 1}, {">i2", 2, 1, 1},
                {"<u2", 2, 0, 0}, {">u2", 2, 1, 0}, {"<i4", 4, 0, 1}, {">u4", 4, 1, 0},
                {"<i8", 8, 0, 1}, {">i8", 8, 1, 1}, {"<u8", 8, 0, 0}};
    for (size_t t = 0; t < sizeof ints / sizeof ints[0]; t++) {
        int size = ints[t].size;
        int64_t expected[6];
        unsigned char data[6 * 8];
        for (int k = 0; k < 6; k++) {
            /* extremes of the type and small values */
            int64_t maxv = size == 8 ? (ints[t].is_signed ? INT64_MAX >> 11 : (int64_t)1 << 53)
                                     : ((int64_t)1 << (8 * size - ints[t].is_signed)) - 1;
            int64_t minv = ints[t].is_signed ? -maxv - (size < 8) : 0;
            int64_t v = k == 0   ? minv
                        : k == 1 ? maxv
                                 : (k * 37) % 120 - (ints[t].is_signed ? 60 : 0);
            expected[k] = v;
            if (ints[t].big)
                put_be(data + size * k, (uint64_t)v, size);
            else
                put_le(data + size * k, (uint64_t)v, size);
        }
        char dict[128], name[32];
        snprintf(dict, sizeof dict, "{'descr': '%s', 'fortran_order': False, 'shape': (2, 3), }",
                 ints[t].descr);
        snprintf(name, sizeof name, "int%zu.npy", t);
        const char *path = tmp_path(name);
        write_npy_fixture(path, t % 2 ? 3 : 1, dict, data, (size_t)(6 * size));
        ASSERT_OK(svp_image_read(path, &img));
        for (int k = 0; k < 6; k++)
            if (img->data[k] != (double)expected[k])
                fail_msg("%s element %d: read %.17g, expected %lld", ints[t].descr, k, img->data[k],
                         (long long)expected[k]);
        svp_image_free(img);
    }
    /* shape (h, w, 1) is one channel */
    {
        double data[6] = {0, 1, 2, 3, 4, 5};
        const char *path = tmp_path("hw1.npy");
        write_npy_fixture(path, 1, "{'descr': '<f8', 'fortran_order': False, 'shape': (3, 2, 1), }",
                          data, sizeof data);
        ASSERT_OK(svp_image_read(path, &img));
        assert_int_equal(img->width, 2);
        assert_int_equal(img->height, 3);
        assert_true(img->data[5] == 5.0);
        svp_image_free(img);
    }
}

static void test_npy_bad_files(void **state)
{
    (void)state;
    svp_image *img = NULL;
    double data[12] = {0};
    char expect[600];

    const char *path = tmp_path("short.npy");
    /* shape (3, 4) float64 needs 96 bytes; give 50 */
    write_npy_fixture(path, 1, "{'descr': '<f8', 'fortran_order': False, 'shape': (3, 4), }", data,
                      50);
    snprintf(expect, sizeof expect, "%s: truncated: expected 96 bytes of data, found 50", path);
    ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_FORMAT, expect);
    assert_null(img);

    path = tmp_path("header_cut.npy");
    write_bytes(path, "\x93NUMPY\x01\x00\x76\x00{'descr'", 17);
    snprintf(expect, sizeof expect, "%s: truncated: the file ends inside the header", path);
    ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_FORMAT, expect);

    path = tmp_path("magic.npy");
    write_string(path, "PK\x03\x04 this is a zip, not an npy file");
    snprintf(expect, sizeof expect, "%s: not a .npy file (bad magic bytes)", path);
    ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_FORMAT, expect);

    path = tmp_path("complex.npy");
    write_npy_fixture(path, 1, "{'descr': '<c16', 'fortran_order': False, 'shape': (2, 2), }", data,
                      64);
    snprintf(expect, sizeof expect, "%s: unsupported dtype '<c16'", path);
    ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_FORMAT, expect);

    path = tmp_path("rgb.npy");
    write_npy_fixture(path, 1, "{'descr': '<f8', 'fortran_order': False, 'shape': (2, 2, 3), }",
                      data, 96);
    snprintf(expect, sizeof expect,
             "%s: a stack of 2 frames (3-D array of shape (2, 2, 3)): expected one image", path);
    ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_FORMAT, expect);

    path = tmp_path("vector.npy");
    write_npy_fixture(path, 1, "{'descr': '<f8', 'fortran_order': False, 'shape': (5,), }", data,
                      40);
    snprintf(expect, sizeof expect, "%s: 1-D array of shape (5,)", path);
    ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_FORMAT, expect);

    path = tmp_path("version.npy");
    write_npy_fixture(path, 4, "{'descr': '<f8', 'fortran_order': False, 'shape': (1, 1), }", data,
                      8);
    snprintf(expect, sizeof expect, "%s: unsupported .npy format version 4.0", path);
    ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_FORMAT, expect);

    path = tmp_path("empty.npy");
    write_npy_fixture(path, 1, "{'descr': '<f8', 'fortran_order': False, 'shape': (0, 4), }", data,
                      0);
    ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_FORMAT, "empty array of shape (0, 4)");
    assert_null(img);
}

/* ---- text ------------------------------------------------------------------------------------- */

static void test_text_round_trip_and_parsing(void **state)
{
    (void)state;
    svp_image *img = awkward_image(6, 4, 1), *back = NULL;
    const char *names[] = {"round.txt", "round.csv", "round.dat"};
    for (int f = 0; f < 3; f++) {
        const char *path = tmp_path(names[f]);
        ASSERT_OK(svp_image_write(path, img, SVP_FORMAT_AUTO, 0));
        ASSERT_OK(svp_image_read(path, &back));
        assert_int_equal(back->width, 6);
        assert_int_equal(back->height, 4);
        for (int i = 0; i < 24; i++)
            if (!same_bits(img->data[i], back->data[i]) &&
                !(isnan(img->data[i]) && isnan(back->data[i])))
                fail_msg("%s pixel %d: wrote %.17g read %.17g", names[f], i, img->data[i],
                         back->data[i]);
        svp_image_free(back);
        back = NULL;
    }
    /* .csv is comma separated, the others space separated (numpy.savetxt's default) */
    size_t size;
    char *csv = (char *)slurp(tmp_path("round.csv"), &size);
    assert_non_null(strchr(csv, ','));
    free(csv);
    char *txt = (char *)slurp(tmp_path("round.txt"), &size);
    assert_null(strchr(txt, ','));
    assert_non_null(strstr(txt, "nan"));
    assert_null(strstr(txt, "-nan"));
    free(txt);
    svp_image_free(img);

    /* what numpy.savetxt writes: a header comment, %.18e, blank lines, CRLF, nan/inf */
    const char *path = tmp_path("numpy.txt");
    write_string(path, "# header from savetxt\n"
                       "1.000000000000000000e+00 -2.500000000000000000e-01 nan\r\n"
                       "\n"
                       "   3 4 inf   # trailing comment\n"
                       "-inf 5e-324 6\n");
    ASSERT_OK(svp_image_read(path, &back));
    assert_int_equal(back->width, 3);
    assert_int_equal(back->height, 3);
    assert_true(back->data[0] == 1.0 && back->data[1] == -0.25 && isnan(back->data[2]));
    assert_true(back->data[3] == 3 && back->data[5] == INFINITY && back->data[6] == -INFINITY);
    assert_true(back->data[7] == 5e-324 && back->data[8] == 6);
    svp_image_free(back);
    back = NULL;

    path = tmp_path("spaces.csv");
    write_string(path, "1, 2 ,3\n4,5,6\n");
    ASSERT_OK(svp_image_read(path, &back));
    assert_true(back->width == 3 && back->height == 2 && back->data[1] == 2 && back->data[5] == 6);
    svp_image_free(back);
    back = NULL;

    char expect[600];
    path = tmp_path("ragged.txt");
    write_string(path, "1 2 3\n# comment\n4 5\n");
    snprintf(expect, sizeof expect, "%s:3: 2 columns, expected 3 (as on line 1)", path);
    ASSERT_FAILS(svp_image_read(path, &back), SVP_ERR_FORMAT, expect);
    path = tmp_path("word.txt");
    write_string(path, "1 2\n3 abc\n");
    snprintf(expect, sizeof expect, "%s:2: 'abc' is not a number (column 2)", path);
    ASSERT_FAILS(svp_image_read(path, &back), SVP_ERR_FORMAT, expect);
    path = tmp_path("hole.csv");
    write_string(path, "1,2,3\n4,,6\n");
    snprintf(expect, sizeof expect, "%s:2: '' is not a number (column 2)", path);
    ASSERT_FAILS(svp_image_read(path, &back), SVP_ERR_FORMAT, expect);
    path = tmp_path("blank.txt");
    write_string(path, "# only a comment\n\n");
    snprintf(expect, sizeof expect, "%s: no numbers found", path);
    ASSERT_FAILS(svp_image_read(path, &back), SVP_ERR_FORMAT, expect);
    assert_null(back);
}

/* ---- TIFF / PNG --------------------------------------------------------------------------------- */

static void test_tiff_round_trip(void **state)
{
    (void)state;
    svp_image *img = test_random_image(33, 17, 5), *back = NULL;
    for (int i = 0; i < 33 * 17; i++) img->data[i] = (img->data[i] - 0.5) * 1e3;
    img->data[7] = NAN;
    const char *path = tmp_path("round.tif");
    ASSERT_OK(svp_image_write(path, img, SVP_FORMAT_AUTO, 0));
    ASSERT_OK(svp_image_read(path, &back));
    assert_int_equal(back->width, 33);
    assert_int_equal(back->height, 17);
    /* float32 storage: the value read is exactly (float)x, within 1e-7 relative of x (the
     * float32 rounding bound is 2^-24 = 6.0e-8) */
    double worst = 0;
    for (int i = 0; i < 33 * 17; i++) {
        if (i == 7) {
            assert_true(isnan(back->data[i]));
            continue;
        }
        assert_true(back->data[i] == (double)(float)img->data[i]);
        double rel = fabs(back->data[i] - img->data[i]) / fabs(img->data[i]);
        if (rel > worst) worst = rel;
    }
    if (!(worst <= 1e-7)) fail_msg("worst relative error %.3g > 1e-7", worst);
    print_message("float32 TIFF round trip: worst relative error %.3g\n", worst);
    /* .tiff and upper-case extensions select the same format */
    ASSERT_OK(svp_image_write(tmp_path("UPPER.TIFF"), img, SVP_FORMAT_AUTO, 0));
    svp_image_free(back);
    back = NULL;
    ASSERT_OK(svp_image_read(tmp_path("UPPER.TIFF"), &back));
    assert_int_equal(back->width, 33);
    svp_image_free(back);
    /* beyond float32's range a value would be written as Inf: refused, nothing written */
    img->data[3] = 1e300;
    assert_int_equal(svp_image_write(tmp_path("big.tif"), img, SVP_FORMAT_AUTO, 0),
                     SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "values up to 1e+300 exceed a float32 TIFF"));
    assert_int_equal(access(tmp_path("big.tif"), F_OK), -1);
    /* below its normal range the whole map would lose its digits or become 0: refused too;
     * tiny values beside normal ones keep the map's relative precision and are written */
    for (int i = 0; i < 33 * 17; i++) img->data[i] = 1e-42 * (i + 1);
    assert_int_equal(svp_image_write(tmp_path("tiny.tif"), img, SVP_FORMAT_AUTO, 0),
                     SVP_ERR_INVALID);
    assert_non_null(strstr(svp_last_error(), "below a float32 TIFF's normal range"));
    assert_int_equal(access(tmp_path("tiny.tif"), F_OK), -1);
    img->data[0] = 1.0;
    ASSERT_OK(svp_image_write(tmp_path("mixed.tif"), img, SVP_FORMAT_AUTO, 0));
    svp_image_free(img);
    assert_no_temporaries();
}

static void test_png16_round_trip(void **state)
{
    (void)state;
    /* integers spanning 0..65535: the [min, max] → [0, 65535] scaling is the identity */
    svp_image *img = test_image(40, 9), *back = NULL;
    uint64_t s = 99;
    for (int i = 0; i < 40 * 9; i++) img->data[i] = floor(test_rand(&s) * 65536.0);
    img->data[0] = 0;
    img->data[1] = 65535;
    const char *path = tmp_path("ints.png");
    ASSERT_OK(svp_image_write(path, img, SVP_FORMAT_AUTO, 0));
    ASSERT_OK(svp_image_read(path, &back));
    assert_int_equal(back->width, 40);
    assert_int_equal(back->height, 9);
    assert_true(test_max_abs_diff(img, back) == 0);
    svp_image_free(back);
    back = NULL;
    /* an offset, scaled range: v = round(65535 (x - min) / (max - min)) */
    for (int i = 0; i < 40 * 9; i++) img->data[i] = -3.0 + img->data[i] / 65535.0 * 0.5;
    ASSERT_OK(svp_image_write(path, img, SVP_FORMAT_PNG16, 1));
    ASSERT_OK(svp_image_read(path, &back));
    for (int i = 0; i < 40 * 9; i++)
        assert_true(back->data[i] == round((img->data[i] + 3.0) / 0.5 * 65535.0));
    svp_image_free(back);
    back = NULL;
    /* a truncated PNG is refused with the file named */
    size_t size;
    unsigned char *bytes = slurp(path, &size);
    const char *cut = tmp_path("cut.png");
    char expect[600];
    snprintf(expect, sizeof expect, "%s: cannot decode PNG (truncated or corrupt)", cut);
    const size_t cuts[] = {size / 2, size - 13, 20, 4};
    for (size_t c = 0; c < sizeof cuts / sizeof cuts[0]; c++) {
        write_bytes(cut, bytes, cuts[c]);
        ASSERT_FAILS(svp_image_read(cut, &back), SVP_ERR_FORMAT, expect);
        assert_null(back);
    }
    /* one flipped bit inside the image data: the chunk's CRC catches it */
    bytes[size - 20] ^= 0x10;
    write_bytes(cut, bytes, size);
    ASSERT_FAILS(svp_image_read(cut, &back), SVP_ERR_FORMAT, "CRC error in chunk 'IDAT'");
    free(bytes);
    svp_image_free(img);
}

/* A minimal TIFF written by hand with the strip AFTER the directory (as many writers do), so a
 * truncation cuts pixel data rather than the directory. 16-bit, sample format 1 (unsigned) or
 * 2 (signed). */
static size_t hand_tiff(unsigned char *buf, int w, int h, int sample_format, const uint16_t *pixels)
{
    const int nentries = 10;
    size_t ifd = 8, data = ifd + 2 + 12 * (size_t)nentries + 4;
    memset(buf, 0, data);
    memcpy(buf, "II*\0", 4);
    put_le(buf + 4, ifd, 4);
    put_le(buf + ifd, nentries, 2);
    const uint32_t entries[10][3] = {{256, 3, (uint32_t)w},
                                     {257, 3, (uint32_t)h},
                                     {258, 3, 16},
                                     {259, 3, 1},
                                     {262, 3, 1},
                                     {273, 4, (uint32_t)data},
                                     {277, 3, 1},
                                     {278, 3, (uint32_t)h},
                                     {279, 4, (uint32_t)(2 * w * h)},
                                     {339, 3, (uint32_t)sample_format}};
    for (int e = 0; e < nentries; e++) {
        unsigned char *p = buf + ifd + 2 + 12 * e;
        put_le(p, entries[e][0], 2);
        put_le(p + 2, entries[e][1], 2); /* 3 = SHORT, 4 = LONG */
        put_le(p + 4, 1, 4);
        put_le(p + 8, entries[e][2], entries[e][1] == 3 ? 2 : 4);
    }
    for (int i = 0; i < w * h; i++) put_le(buf + data + 2 * i, pixels[i], 2);
    return data + 2 * (size_t)w * h;
}

static void test_tiff_integer_and_truncated(void **state)
{
    (void)state;
    enum { W = 16, H = 12 };
    uint16_t pixels[W * H];
    for (int i = 0; i < W * H; i++) pixels[i] = (uint16_t)(i * 331 + 7);
    unsigned char buf[4096];
    svp_image *img = NULL;
    char expect[600];

    /* 16-bit unsigned and signed TIFFs decode to their integer values */
    for (int sf = 1; sf <= 2; sf++) {
        size_t size = hand_tiff(buf, W, H, sf, pixels);
        const char *path = tmp_path(sf == 1 ? "u16.tif" : "i16.tif");
        write_bytes(path, buf, size);
        ASSERT_OK(svp_image_read(path, &img));
        assert_int_equal(img->width, W);
        assert_int_equal(img->height, H);
        for (int i = 0; i < W * H; i++) {
            double expected = sf == 1 ? (double)pixels[i] : (double)(int16_t)pixels[i];
            if (img->data[i] != expected)
                fail_msg("sample format %d pixel %d: %g, expected %g", sf, i, img->data[i],
                         expected);
        }
        svp_image_free(img);
        img = NULL;
        /* the same file cut inside the pixel data */
        path = tmp_path(sf == 1 ? "u16_cut.tif" : "i16_cut.tif");
        write_bytes(path, buf, size - W * H);
        snprintf(expect, sizeof expect, "%s: cannot decode TIFF (truncated or corrupt)", path);
        ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_FORMAT, expect);
        assert_null(img);
    }

    /* a real float32 TIFF written by the library, then truncated at several lengths */
    svp_image *src = test_random_image(64, 48, 3);
    const char *full = tmp_path("full.tif");
    ASSERT_OK(svp_image_write(full, src, SVP_FORMAT_TIFF, 0));
    size_t size;
    unsigned char *bytes = slurp(full, &size);
    const size_t cuts[] = {size / 2, size - 100, 200, 9, 5, 0};
    for (size_t c = 0; c < sizeof cuts / sizeof cuts[0]; c++) {
        const char *path = tmp_path("cut.tif");
        write_bytes(path, bytes, cuts[c]);
        snprintf(expect, sizeof expect, "%s: cannot decode TIFF (truncated or corrupt)", path);
        ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_FORMAT, expect);
        assert_null(img);
    }
    free(bytes);
    svp_image_free(src);

    const char *path = tmp_path("text.tif");
    write_string(path, "this is not a TIFF at all");
    snprintf(expect, sizeof expect, "%s: not a TIFF file (bad magic bytes)", path);
    ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_FORMAT, expect);
}

/* ---- stacks ---------------------------------------------------------------------------------- */

/* A multi-page 16-bit TIFF written by hand (classic, little-endian, one strip per page, each
 * page's directory after its strip; page p holds pixel(p, i)). big_endian: "MM" byte order.
 * Returns the size; buf must hold n_pages * (2 w h + 200) + 8 bytes. */
static uint16_t stack_pixel(int page, int i) { return (uint16_t)((page * 7919 + i * 31 + 5) & 0xffff); }

static void put_tiff(unsigned char *p, uint64_t v, int size, int big_endian)
{
    if (big_endian)
        put_be(p, v, size);
    else
        put_le(p, v, size);
}

static size_t hand_tiff_stack(unsigned char *buf, int w, int h, int n_pages, int big_endian)
{
    memcpy(buf, big_endian ? "MM\0*" : "II*\0", 4);
    size_t pos = 8, link = 4; /* where the offset of the next directory goes */
    for (int p = 0; p < n_pages; p++) {
        size_t data = pos;
        for (int i = 0; i < w * h; i++) put_tiff(buf + data + 2 * i, stack_pixel(p, i), 2, big_endian);
        size_t ifd = data + 2 * (size_t)w * h;
        ifd += ifd & 1; /* word boundary */
        put_tiff(buf + link, ifd, 4, big_endian);
        const uint32_t entries[10][3] = {{256, 3, (uint32_t)w},   {257, 3, (uint32_t)h},
                                         {258, 3, 16},            {259, 3, 1},
                                         {262, 3, 1},             {273, 4, (uint32_t)data},
                                         {277, 3, 1},             {278, 3, (uint32_t)h},
                                         {279, 4, (uint32_t)(2 * w * h)}, {339, 3, 1}};
        put_tiff(buf + ifd, 10, 2, big_endian);
        for (int e = 0; e < 10; e++) {
            unsigned char *q = buf + ifd + 2 + 12 * e;
            put_tiff(q, entries[e][0], 2, big_endian);
            put_tiff(q + 2, entries[e][1], 2, big_endian);
            put_tiff(q + 4, 1, 4, big_endian);
            memset(q + 8, 0, 4);
            put_tiff(q + 8, entries[e][2], entries[e][1] == 3 ? 2 : 4, big_endian);
        }
        link = ifd + 2 + 12 * 10;
        put_tiff(buf + link, 0, 4, big_endian);
        pos = link + 4;
    }
    return pos;
}

static void test_tiff_stacks(void **state)
{
    (void)state;
    enum { W = 24, H = 10 };
    const int counts[] = {1, 5, 100};
    unsigned char *buf = malloc(100 * (2 * W * H + 200) + 8);
    char expect[600], name[64];
    for (int c = 0; c < 3; c++) {
        const int n = counts[c];
        for (int big = 0; big <= 1; big++) {
            snprintf(name, sizeof name, "stack%d%s.tif", n, big ? "_be" : "");
            const char *path = tmp_path(name);
            write_bytes(path, buf, hand_tiff_stack(buf, W, H, n, big));
            svp_stack *s = NULL;
            ASSERT_OK(svp_stack_read(path, &s));
            assert_int_equal(s->n_frames, n);
            assert_int_equal(s->width, W);
            assert_int_equal(s->height, H);
            for (int p = 0; p < n; p++) {
                assert_int_equal(s->frame[p]->width, W);
                assert_int_equal(s->frame[p]->height, H);
                for (int i = 0; i < W * H; i++)
                    if (s->frame[p]->data[i] != stack_pixel(p, i))
                        fail_msg("%s page %d pixel %d: %g, expected %d", name, p, i,
                                 s->frame[p]->data[i], stack_pixel(p, i));
            }
            svp_stack_free(s);
            /* one image expected: a one-page file is that image, more pages are refused */
            svp_image *img = NULL;
            if (n == 1) {
                ASSERT_OK(svp_image_read(path, &img));
                assert_int_equal(img->data[7], stack_pixel(0, 7));
                svp_image_free(img);
            } else {
                snprintf(expect, sizeof expect,
                         "%s: multi-page TIFF of %d pages: expected one image", path, n);
                ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_FORMAT, expect);
                assert_null(img);
            }
        }
    }
    /* a directory chain that loops back on itself, and one pointing beyond the file */
    size_t size = hand_tiff_stack(buf, W, H, 5, 0);
    size_t last_link = size - 4;
    put_le(buf + last_link, 8 + 2 * W * H, 4); /* the last page links back to the first */
    const char *path = tmp_path("loop.tif");
    write_bytes(path, buf, size);
    svp_stack *s = NULL;
    snprintf(expect, sizeof expect, "%s: cannot decode TIFF (truncated or corrupt)", path);
    ASSERT_FAILS(svp_stack_read(path, &s), SVP_ERR_FORMAT, expect);
    svp_image *img = NULL;
    ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_FORMAT, expect);
    put_le(buf + last_link, (uint64_t)size + 1000, 4);
    path = tmp_path("beyond.tif");
    write_bytes(path, buf, size);
    snprintf(expect, sizeof expect, "%s: cannot decode TIFF (truncated or corrupt)", path);
    ASSERT_FAILS(svp_stack_read(path, &s), SVP_ERR_FORMAT, expect);
    assert_null(s);
    /* pages of different sizes: the second page's directory says 12 rows instead of 10 (its
     * strip is then short, so OpenCV may refuse the page itself: either message names page 2) */
    size = hand_tiff_stack(buf, W, H, 3, 0);
    path = tmp_path("mixed.tif");
    {
        size_t ifd2 = 8 + 2 * W * H + (10 * 12 + 6); /* after page 1's directory */
        ifd2 += 2 * W * H;
        ifd2 += ifd2 & 1;
        assert_int_equal(buf[ifd2 + 2 + 12], 1); /* tag 257 (rows), low byte */
        put_le(buf + ifd2 + 2 + 12 + 8, 5, 2);   /* 5 rows: the strip is long enough */
        put_le(buf + ifd2 + 2 + 7 * 12 + 8, 5, 2); /* rows per strip */
    }
    write_bytes(path, buf, size);
    snprintf(expect, sizeof expect, "%s: page 2 of 3 is 24 x 5 but page 1 is 24 x 10", path);
    ASSERT_FAILS(svp_stack_read(path, &s), SVP_ERR_FORMAT, expect);
    free(buf);
}

/* The readers' limits and memory budget (docs/reliability.md), checked from the TIFF
 * directories before OpenCV decodes anything; the budget's variable; the temporary-file
 * registry and the removal of stale temporary files. */
static void test_limits_and_temporaries(void **state)
{
    (void)state;
    enum { W = 24, H = 10, N = 100 };
    unsigned char *buf = malloc(N * (2 * W * H + 200) + 8);
    const size_t size = hand_tiff_stack(buf, W, H, N, 0);
    const char *path = tmp_path("budget.tif");
    write_bytes(path, buf, size);
    /* the file, every page as OpenCV's 16-bit Mat and as float64, one strip buffer */
    const double need = (double)size + N * W * H * (2.0 + 8.0) + W * H * 2.0;
    char expect[600];
    snprintf(expect, sizeof expect,
             "%s: decoding 100 TIFF pages needs %.0f KiB of memory, more than the 200 KiB "
             "allowed (SVPSF_MAX_MEMORY=200K;",
             path, need / 1024);
    svp_stack *s = NULL;
    setenv("SVPSF_MAX_MEMORY", "200K", 1);
    ASSERT_FAILS(svp_stack_read(path, &s), SVP_ERR_INVALID, expect);
    assert_null(s);
    setenv("SVPSF_MAX_MEMORY", "0.5MiB", 1); /* 512 KiB: enough */
    ASSERT_OK(svp_stack_read(path, &s));
    assert_int_equal(s->n_frames, N);
    svp_stack_free(s);
    s = NULL;
    const char *bad[] = {"0", "-1G", "lots", "4Q", "1e30"};
    for (int i = 0; i < 5; i++) {
        setenv("SVPSF_MAX_MEMORY", bad[i], 1);
        snprintf(expect, sizeof expect, "SVPSF_MAX_MEMORY=%s is not a memory size", bad[i]);
        ASSERT_FAILS(svp_stack_read(path, &s), SVP_ERR_INVALID, expect);
    }
    unsetenv("SVPSF_MAX_MEMORY");
    double budget = 0;
    char source[96];
    ASSERT_OK(svp_io_memory_budget(&budget, source, sizeof source));
    assert_string_equal(source, "available memory");
    assert_true(budget > 0); /* /proc/meminfo on Linux */
    setenv("SVPSF_MAX_MEMORY", "1.5GiB", 1);
    ASSERT_OK(svp_io_memory_budget(&budget, source, sizeof source));
    assert_true(budget == 1.5 * 1073741824.0);
    assert_string_equal(source, "SVPSF_MAX_MEMORY=1.5GiB");
    unsetenv("SVPSF_MAX_MEMORY");

    /* page 3 of 5 claims 20000 x 20000 pixels: refused, naming the page, before decoding */
    size_t size5 = hand_tiff_stack(buf, W, H, 5, 0);
    size_t ifd = 8;
    for (int p = 0; p < 3; p++) {
        size_t data_end = ifd + 2 * W * H;
        ifd = data_end + (data_end & 1);
        if (p < 2) ifd += 2 + 12 * 10 + 4;
    }
    assert_int_equal(buf[ifd + 2], 0x00); /* tag 256 = 0x0100, little-endian: 00 01 */
    assert_int_equal(buf[ifd + 3], 0x01);
    put_le(buf + ifd + 2 + 8, 20000, 2);
    put_le(buf + ifd + 2 + 12 + 8, 20000, 2);
    path = tmp_path("bigpage.tif");
    write_bytes(path, buf, size5);
    snprintf(expect, sizeof expect,
             "%s: page 3 of 5: 20000 x 20000 pixels: larger than an image may be", path);
    ASSERT_FAILS(svp_stack_read(path, &s), SVP_ERR_FORMAT, expect);
    free(buf);

    /* the registry: recorded temporary files go with svp_io_temp_remove_all, released don't */
    const char *t1 = tmp_path(".a.npy.svpsf-tmp-1-aaaaaa"),
               *t2 = tmp_path(".b.npy.svpsf-tmp-1-bbbbbb");
    write_bytes(t1, (const unsigned char *)"x", 1);
    write_bytes(t2, (const unsigned char *)"y", 1);
    int slot1 = svp_io_temp_register(t1), slot2 = svp_io_temp_register(t2);
    assert_true(slot1 >= 0 && slot2 >= 0 && slot1 != slot2);
    svp_io_temp_release(slot2);
    svp_io_temp_remove_all();
    struct stat sb;
    assert_int_equal(stat(t1, &sb), -1);
    assert_int_equal(stat(t2, &sb), 0);
    svp_io_temp_release(slot1);
    /* stale: t2 names PID 1 (alive: init) and stays; this process's own stays; a PID that no
     * longer exists is removed; other names are not touched */
    char dead_name[128], own_name[128];
    pid_t dead = fork();
    if (dead == 0) _exit(0);
    waitpid(dead, NULL, 0);
    snprintf(dead_name, sizeof dead_name, ".b.npy.svpsf-tmp-%ld-cccccc", (long)dead);
    snprintf(own_name, sizeof own_name, ".b.npy.svpsf-tmp-%ld-dddddd", (long)getpid());
    const char *td = tmp_path(dead_name), *to = tmp_path(own_name), *tx = tmp_path(".b.npy.tmpXYZ");
    write_bytes(td, (const unsigned char *)"d", 1);
    write_bytes(to, (const unsigned char *)"o", 1);
    write_bytes(tx, (const unsigned char *)"x", 1);
    svp_io_temp_remove_stale(tmpdir, "b.npy");
    assert_int_equal(stat(td, &sb), -1);
    assert_int_equal(stat(to, &sb), 0);
    assert_int_equal(stat(tx, &sb), 0);
    assert_int_equal(stat(t2, &sb), 0);
    remove(t2);
    remove(to);
    remove(tx);
}

static void test_npy_stacks(void **state)
{
    (void)state;
    enum { F = 5, H = 3, W = 4 };
    double data[F * H * W];
    /* C order: element (f, y, x) at (f H + y) W + x */
    for (int k = 0; k < F * H * W; k++) data[k] = 1000.0 * (k / (H * W)) + 10.0 * (k / W % H) + k % W;
    const char *path = tmp_path("stack_c.npy");
    write_npy_fixture(path, 1, "{'descr': '<f8', 'fortran_order': False, 'shape': (5, 3, 4), }",
                      data, sizeof data);
    svp_stack *s = NULL;
    ASSERT_OK(svp_stack_read(path, &s));
    assert_int_equal(s->n_frames, F);
    assert_int_equal(s->width, W);
    assert_int_equal(s->height, H);
    for (int f = 0; f < F; f++)
        for (int y = 0; y < H; y++)
            for (int x = 0; x < W; x++)
                assert_true(s->frame[f]->data[y * W + x] == 1000.0 * f + 10.0 * y + x);
    svp_stack_free(s);
    svp_image *img = NULL;
    char expect[600];
    snprintf(expect, sizeof expect,
             "%s: a stack of 5 frames (3-D array of shape (5, 3, 4)): expected one image", path);
    ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_FORMAT, expect);
    /* Fortran order: element (f, y, x) at f + y F + x F H */
    float fdata[F * H * W];
    for (int f = 0; f < F; f++)
        for (int y = 0; y < H; y++)
            for (int x = 0; x < W; x++)
                fdata[f + y * F + x * F * H] = (float)(1000.0 * f + 10.0 * y + x);
    path = tmp_path("stack_f.npy");
    write_npy_fixture(path, 1, "{'descr': '<f4', 'fortran_order': True, 'shape': (5, 3, 4), }",
                      fdata, sizeof fdata);
    ASSERT_OK(svp_stack_read(path, &s));
    assert_int_equal(s->n_frames, F);
    for (int f = 0; f < F; f++)
        for (int y = 0; y < H; y++)
            for (int x = 0; x < W; x++)
                assert_true(s->frame[f]->data[y * W + x] == 1000.0 * f + 10.0 * y + x);
    svp_stack_free(s);
    /* a 2-D image is a stack of one frame, in any format */
    path = tmp_path("one.npy");
    write_npy_fixture(path, 1, "{'descr': '<f8', 'fortran_order': False, 'shape': (3, 4), }",
                      data, 12 * 8);
    ASSERT_OK(svp_stack_read(path, &s));
    assert_int_equal(s->n_frames, 1);
    assert_true(s->frame[0]->data[11] == data[11]);
    svp_stack_free(s);
    path = tmp_path("one.txt");
    write_string(path, "1 2 3\n4 5 6\n");
    ASSERT_OK(svp_stack_read(path, &s));
    assert_int_equal(s->n_frames, 1);
    assert_int_equal(s->width, 3);
    assert_true(s->frame[0]->data[5] == 6);
    svp_stack_free(s);
    /* errors: truncated data, 4-D */
    path = tmp_path("stack_cut.npy");
    write_npy_fixture(path, 1, "{'descr': '<f8', 'fortran_order': False, 'shape': (5, 3, 4), }",
                      data, sizeof data - 8);
    snprintf(expect, sizeof expect, "%s: truncated: expected 480 bytes of data, found 472", path);
    ASSERT_FAILS(svp_stack_read(path, &s), SVP_ERR_FORMAT, expect);
    assert_null(s);
    path = tmp_path("stack4.npy");
    write_npy_fixture(path, 1, "{'descr': '<f8', 'fortran_order': False, 'shape': (1, 5, 3, 4), }",
                      data, sizeof data);
    snprintf(expect, sizeof expect,
             "%s: 4-D array of shape (1, 5, 3, 4): expected a 2-D image (height, width) or a 3-D "
             "stack (frames, height, width)", path);
    ASSERT_FAILS(svp_stack_read(path, &s), SVP_ERR_FORMAT, expect);
    /* svp_stack_write: the header numpy writes for (5, 3, 4) float64, C order, and the frames
     * read back bit for bit; no overwrite without asking; only .npy; frames of one size */
    svp_image *fr[F];
    for (int f = 0; f < F; f++) {
        fr[f] = test_image(W, H);
        memcpy(fr[f]->data, data + (size_t)f * H * W, H * W * sizeof(double));
    }
    path = tmp_path("written.npy");
    ASSERT_OK(svp_stack_write(path, (const svp_image *const *)fr, F, 0));
    FILE *fp = fopen(path, "rb");
    char head[128] = {0};
    assert_non_null(fp);
    assert_true(fread(head, 1, 127, fp) == 127);
    fclose(fp);
    assert_non_null(strstr(head + 10, "'shape': (5, 3, 4)"));
    assert_non_null(strstr(head + 10, "'descr': '<f8'"));
    ASSERT_OK(svp_stack_read(path, &s));
    assert_int_equal(s->n_frames, F);
    for (int f = 0; f < F; f++) assert_memory_equal(s->frame[f]->data, fr[f]->data, H * W * 8);
    svp_stack_free(s);
    assert_int_not_equal(svp_stack_write(path, (const svp_image *const *)fr, F, 0), SVP_OK);
    ASSERT_OK(svp_stack_write(path, (const svp_image *const *)fr, F, 1));
    assert_int_equal(svp_stack_write(tmp_path("written.tif"), (const svp_image *const *)fr, F, 0),
                     SVP_ERR_INVALID);
    svp_image *odd = test_image(W + 1, H);
    svp_image *mixed[2] = {fr[0], odd};
    assert_int_equal(svp_stack_write(tmp_path("mixed.npy"), (const svp_image *const *)mixed, 2, 0),
                     SVP_ERR_SIZE);
    svp_image_free(odd);
    for (int f = 0; f < F; f++) svp_image_free(fr[f]);
}

static void test_colour_png_and_channels(void **state)
{
    (void)state;
    svp_image *img = test_image(20, 10), *back = NULL;
    for (int y = 0; y < 10; y++)
        for (int x = 0; x < 20; x++) img->data[y * 20 + x] = x - 7.5;
    img->data[3] = NAN;
    const char *path = tmp_path("map.png");
    ASSERT_OK(svp_io_write_colormap_png(path, img, 0, 0, 1, 0));
    ASSERT_OK(svp_io_write_colormap_png(tmp_path("seq.png"), img, -1, 1, 0, 0));
    ASSERT_FAILS(svp_io_write_colormap_png(path, img, 0, 0, 1, 0), SVP_ERR_EXISTS, path);
    /* a colour PNG is refused as an input image: one channel is required */
    char expect[600];
    snprintf(expect, sizeof expect,
             "%s: 3-channel image: expected a single-channel (grayscale) image", path);
    ASSERT_FAILS(svp_image_read(path, &back), SVP_ERR_FORMAT, expect);
    assert_null(back);
    svp_image_free(img);
    assert_no_temporaries();
}

/* ---- missing files, unknown formats, overwrite -------------------------------------------- */

static void test_missing_and_unknown(void **state)
{
    (void)state;
    svp_image *img = NULL;
    char expect[600];
    const char *names[] = {"nothing.tif", "nothing.png", "nothing.npy", "nothing.txt"};
    for (int i = 0; i < 4; i++) {
        const char *path = tmp_path(names[i]);
        snprintf(expect, sizeof expect, "%s: no such file", path);
        ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_IO, expect);
        assert_null(img);
    }
    ASSERT_FAILS(svp_image_read(tmp_path("no/such/folder/a.npy"), &img), SVP_ERR_IO,
                 "no such file");
    ASSERT_FAILS(svp_image_read(tmpdir, &img), SVP_ERR_IO, "is a directory");
    const char *path = tmp_path("picture.jpg");
    write_string(path, "x");
    snprintf(expect, sizeof expect,
             "%s: unknown image format '.jpg' (expected .tif, .tiff, .png, .npy, .txt, .csv, "
             ".dat or .mat)",
             path);
    ASSERT_FAILS(svp_image_read(path, &img), SVP_ERR_INVALID, expect);
    svp_image *small = test_image(2, 2);
    ASSERT_FAILS(svp_image_write(tmp_path("out.bmp"), small, SVP_FORMAT_AUTO, 0), SVP_ERR_INVALID,
                 "unknown image format '.bmp'");
    /* a folder that does not exist: an I/O error, nothing created */
    path = tmp_path("missing_folder/out.npy");
    snprintf(expect, sizeof expect, "%s: cannot write (No such file or directory)", path);
    ASSERT_FAILS(svp_image_write(path, small, SVP_FORMAT_AUTO, 0), SVP_ERR_IO, expect);
    svp_image_free(small);
}

static void test_no_overwrite(void **state)
{
    (void)state;
    svp_image *a = test_random_image(8, 8, 1), *b = test_random_image(8, 8, 2), *back = NULL;
    const char *formats[] = {"keep.npy", "keep.tif", "keep.txt", "keep.png"};
    char expect[600];
    for (int f = 0; f < 4; f++) {
        const char *path = tmp_path(formats[f]);
        ASSERT_OK(svp_image_write(path, a, SVP_FORMAT_AUTO, 0));
        size_t size0, size1;
        unsigned char *before = slurp(path, &size0);
        snprintf(expect, sizeof expect, "%s exists (use --force to overwrite)", path);
        ASSERT_FAILS(svp_image_write(path, b, SVP_FORMAT_AUTO, 0), SVP_ERR_EXISTS, expect);
        unsigned char *after = slurp(path, &size1);
        assert_int_equal(size0, size1);
        assert_memory_equal(before, after, size0);
        free(before);
        free(after);
        /* with overwrite the new content replaces the old */
        ASSERT_OK(svp_image_write(path, b, SVP_FORMAT_AUTO, 1));
        ASSERT_OK(svp_image_read(path, &back));
        if (f == 0 || f == 2) assert_true(test_max_abs_diff(back, b) == 0);
        svp_image_free(back);
        back = NULL;
    }
    /* the new file gets the usual permissions (0666 & ~umask), not mkstemp's 0600 */
    mode_t mask = umask(022);
    umask(mask);
    struct stat sb;
    assert_int_equal(stat(tmp_path("keep.npy"), &sb), 0);
    assert_int_equal(sb.st_mode & 0777, 0666 & ~mask);
    /* the atomic text helper behaves the same */
    const char *path = tmp_path("note.txt");
    ASSERT_OK(svp_io_atomic_write_text(path, "first\n", 0));
    ASSERT_FAILS(svp_io_atomic_write_text(path, "second\n", 0), SVP_ERR_EXISTS, "exists");
    size_t size;
    char *text = (char *)slurp(path, &size);
    assert_string_equal(text, "first\n");
    free(text);
    ASSERT_OK(svp_io_atomic_write_text(path, "second\n", 1));
    text = (char *)slurp(path, &size);
    assert_string_equal(text, "second\n");
    free(text);
    assert_no_temporaries();
    svp_image_free(a);
    svp_image_free(b);
}

/* ---- PSF files ---------------------------------------------------------------------------------- */

static void test_psf_file_valid(void **state)
{
    (void)state;
    const char *path = tmp_path("psf.yaml");
    write_string(path, "# measured on sample A\n"
                       "pixel_um: 0.1\n"
                       "psf:\n"
                       "  model: moffat\n"
                       "  fwhm_um: 0.61\n"
                       "  beta: 1.1\n"
                       "  halo: 0.05\n"
                       "  fwhm_minor_um: 0.5\n"
                       "  angle_deg: 30\n"
                       "  support_um: 20\n"
                       "  subsample: 3\n"
                       "boundary: mirror\n"
                       "provenance: \"fit of spot 3, 2026-01-12\"\n");
    svp_psf psf;
    double pixel_um = 0;
    svp_boundary boundary = SVP_BOUNDARY_ZERO;
    ASSERT_OK(svp_psf_file_read(path, &psf, &pixel_um, &boundary));
    assert_int_equal(psf.model, SVP_PSF_MOFFAT);
    ASSERT_CLOSE(pixel_um, 0.1, 0);
    ASSERT_CLOSE(psf.fwhm, 6.1, 1e-12);
    ASSERT_CLOSE(psf.fwhm_minor, 5.0, 1e-12);
    ASSERT_CLOSE(psf.beta, 1.1, 0);
    ASSERT_CLOSE(psf.halo, 0.05, 0);
    ASSERT_CLOSE(psf.angle, M_PI / 6, 1e-15);
    ASSERT_CLOSE(psf.support, 200.0, 1e-12);
    assert_int_equal(psf.subsample, 3);
    assert_int_equal(boundary, SVP_BOUNDARY_MIRROR);

    /* the minimal file, flow style; defaults for the rest; lorentzian forces beta = 1 */
    write_string(path, "pixel_um: 0.2\npsf: {model: lorentzian, fwhm_um: 1.0}\n");
    boundary = SVP_BOUNDARY_PERIODIC;
    ASSERT_OK(svp_psf_file_read(path, &psf, &pixel_um, &boundary));
    assert_int_equal(psf.model, SVP_PSF_LORENTZIAN);
    ASSERT_CLOSE(psf.fwhm, 5.0, 1e-12);
    assert_true(psf.beta == 1.0 && psf.halo == 0 && psf.fwhm_minor == 0 && psf.support == 0);
    assert_int_equal(boundary, SVP_BOUNDARY_ZERO);
    write_string(path, "pixel_um: 0.2\npsf: {model: gaussian, fwhm_um: 0.3}\n");
    ASSERT_OK(svp_psf_file_read(path, &psf, NULL, NULL));
    assert_int_equal(psf.model, SVP_PSF_GAUSSIAN);
    ASSERT_CLOSE(psf.fwhm, 1.5, 1e-12);
}

typedef struct bad_psf_case {
    const char *text;
    svp_status status;
    const char *message; /* after "<path>:" */
} bad_psf_case;

static void test_psf_file_errors(void **state)
{
    (void)state;
    const bad_psf_case cases[] = {
        /* unknown key, with line:col of the key and a suggestion */
        {"pixel_um: 0.1\npsf:\n  model: gaussian\n  fwhm_nm: 0.5\n", SVP_ERR_FORMAT,
         "4:3: unknown key 'fwhm_nm' in psf (expected one of: model, fwhm_um, beta, halo, "
         "fwhm_minor_um, angle_deg, support_um, subsample; did you mean 'fwhm_um'?)"},
        {"pixel_size: 0.1\npsf: {model: gaussian, fwhm_um: 0.5}\n", SVP_ERR_FORMAT,
         "1:1: unknown key 'pixel_size' (expected one of: pixel_um, psf, boundary, provenance, "
         "comment)"},
        /* wrong type */
        {"pixel_um: 0.1\npsf:\n  model: gaussian\n  fwhm_um: abc\n", SVP_ERR_FORMAT,
         "4:12: fwhm_um must be a number, got 'abc'"},
        {"pixel_um: [0.1]\npsf: {model: gaussian, fwhm_um: 0.5}\n", SVP_ERR_FORMAT,
         "1:11: pixel_um must be a number, got a list"},
        {"pixel_um: 0.1\npsf: gaussian\n", SVP_ERR_FORMAT,
         "2:6: psf must be a mapping of keys to values, got 'gaussian'"},
        /* an empty value has no position of its own: it is reported just after its key */
        {"pixel_um: 0.1\npsf:\n  model: moffat\n  fwhm_um: 0.5\n  beta:\n", SVP_ERR_FORMAT,
         "5:7: beta must be a number, got no value"},
        {"pixel_um: 0.1\npsf: {model: gaussian, fwhm_um: 0.5, subsample: 2.5}\n", SVP_ERR_FORMAT,
         "2:49: subsample must be an integer, got '2.5'"},
        /* impossible values */
        {"pixel_um: 0.1\npsf:\n  model: gaussian\n  fwhm_um: -0.5\n", SVP_ERR_INVALID,
         "4:12: fwhm_um must be > 0, got -0.5"},
        {"pixel_um: 0.1\npsf:\n  model: gaussian\n  fwhm_um: 0\n", SVP_ERR_INVALID,
         "4:12: fwhm_um must be > 0, got 0"},
        {"pixel_um: 0.1\npsf:\n  model: moffat\n  fwhm_um: 0.5\n  beta: 0\n", SVP_ERR_INVALID,
         "5:9: beta must be >= 0.5, got 0"},
        {"pixel_um: 0.1\npsf:\n  model: moffat\n  fwhm_um: 0.5\n  beta: -1.5\n", SVP_ERR_INVALID,
         "5:9: beta must be >= 0.5, got -1.5"},
        {"pixel_um: 0\npsf: {model: gaussian, fwhm_um: 0.5}\n", SVP_ERR_INVALID,
         "1:11: pixel_um must be >= 1e-06, got 0"},
        {"pixel_um: 0.1\npsf: {model: gaussian, fwhm_um: 0.5, halo: 1}\n", SVP_ERR_INVALID,
         "2:44: halo must be in [0, 1), got 1"},
        {"pixel_um: 0.1\npsf: {model: gaussian, fwhm_um: 0.5, fwhm_minor_um: 0.7}\n",
         SVP_ERR_INVALID, "2:53: fwhm_minor_um must be in (0, 0.5], got 0.7"},
        {"pixel_um: 0.1\npsf: {model: gaussian, fwhm_um: .inf}\n", SVP_ERR_INVALID,
         "2:33: fwhm_um must be a finite number, got '.inf'"},
        {"pixel_um: 0.1\npsf: {model: gaussian, fwhm_um: 0.5, subsample: 65}\n", SVP_ERR_INVALID,
         "2:49: subsample must be an integer in 0..64, got 65"},
        {"pixel_um: 0.1\npsf:\n  model: lorentzian\n  fwhm_um: 0.5\n  beta: 2\n", SVP_ERR_INVALID,
         "5:9: beta must be 1 for a lorentzian PSF, got 2"},
        {"pixel_um: 0.1\npsf:\n  model: gaussian\n  fwhm_um: 0.5\n  beta: 2\n", SVP_ERR_INVALID,
         "5:9: beta does not apply to a gaussian PSF"},
        /* bad names */
        {"pixel_um: 0.1\npsf:\n  model: gauss\n  fwhm_um: 0.5\n", SVP_ERR_INVALID,
         "3:10: model must be one of gaussian, lorentzian, moffat; got 'gauss'"},
        {"pixel_um: 0.1\npsf: {model: gaussian, fwhm_um: 0.5}\nboundary: reflect\n",
         SVP_ERR_INVALID, "3:11: boundary must be one of zero, mirror, periodic; got 'reflect'"},
        /* missing keys */
        {"psf:\n  model: gaussian\n  fwhm_um: 0.5\n", SVP_ERR_FORMAT,
         "1:1: missing required key 'pixel_um'"},
        {"pixel_um: 0.1\npsf:\n  model: gaussian\n", SVP_ERR_FORMAT,
         "3:3: missing required key 'fwhm_um' in psf"},
        {"pixel_um: 0.1\npsf:\n  model: moffat\n  fwhm_um: 0.5\n", SVP_ERR_FORMAT,
         "3:3: missing required key 'beta' in psf (a moffat PSF needs its beta)"},
        /* malformed YAML, duplicate keys, not a mapping, empty file */
        {"pixel_um: 0.1\npsf: {model: gaussian, fwhm_um: 0.5\n", SVP_ERR_FORMAT, "3:1: "},
        {"pixel_um: 0.1\npsf:\n  model: gaussian\n\tfwhm_um: 0.5\n", SVP_ERR_FORMAT, "4:"},
        {"pixel_um: 0.1\npixel_um: 0.2\npsf: {model: gaussian, fwhm_um: 0.5}\n", SVP_ERR_FORMAT,
         "2:1: duplicate key 'pixel_um' (first at line 1)"},
        {"- 1\n- 2\n", SVP_ERR_FORMAT,
         "1:1: the file must be a mapping of keys to values, got a list"},
        {"", SVP_ERR_FORMAT, "1:1: the file must be a mapping of keys to values, got no value"},
        {"pixel_um: 0.1\n---\npixel_um: 0.2\n", SVP_ERR_FORMAT,
         "2:1: a second YAML document ('---'): one document per file"},
    };
    char expect[900];
    const char *path = tmp_path("bad_psf.yaml");
    for (size_t c = 0; c < sizeof cases / sizeof cases[0]; c++) {
        write_string(path, cases[c].text);
        svp_psf psf;
        svp_psf_defaults(&psf);
        psf.fwhm = 123;
        double pixel_um = -7;
        svp_status st = svp_psf_file_read(path, &psf, &pixel_um, NULL);
        if (st != cases[c].status)
            fail_msg("case %zu (%s): status %d (%s), expected %d", c, cases[c].text, (int)st,
                     svp_last_error(), (int)cases[c].status);
        snprintf(expect, sizeof expect, "%s:%s", path, cases[c].message);
        if (strncmp(svp_last_error(), expect, strlen(expect)) != 0)
            fail_msg("case %zu: message\n  \"%s\"\ndoes not start with\n  \"%s\"", c,
                     svp_last_error(), expect);
        /* outputs untouched on failure */
        assert_true(psf.fwhm == 123 && pixel_um == -7);
    }
    char expect_missing[600];
    snprintf(expect_missing, sizeof expect_missing, "%s: no such file", tmp_path("none.yaml"));
    svp_psf psf;
    ASSERT_FAILS(svp_psf_file_read(tmp_path("none.yaml"), &psf, NULL, NULL), SVP_ERR_IO,
                 expect_missing);
}

/* ---- YAML helpers and writer ------------------------------------------------------------------- */

/* What is not YAML text, or too large or deep for the bounds, is refused before or while
 * parsing with the exact message (docs/reliability.md). */
static void expect_yaml_error(const char *text, size_t len, svp_status status, const char *msg)
{
    svp_yaml_doc *doc = NULL;
    svp_status st = svp_yaml_load_string("t.yaml", text, len, &doc);
    if (st != status || !strstr(svp_last_error(), msg))
        fail_msg("status %d (expected %d), message '%s' lacks '%s'", (int)st, (int)status,
                 svp_last_error(), msg);
    assert_null(doc);
}

static void test_yaml_limits(void **state)
{
    (void)state;
    /* the 2-byte files libfyaml 0.7.12 looped on, a PDF's binary line, a control byte, a
     * truncated UTF-8 sequence, an overlong encoding, a UTF-16 surrogate, U+FFFE */
    expect_yaml_error("%\xe8", 2, SVP_ERR_FORMAT,
                      "t.yaml: not a text file (byte offset 1: 0xe8 is not printable UTF-8 text)");
    expect_yaml_error("%\xff\xffm", 4, SVP_ERR_FORMAT, "t.yaml: not a text file (byte offset 1:");
    expect_yaml_error("%PDF-1.4\n%\xe2\xe3\xcf\xd3\n", 15, SVP_ERR_FORMAT, "byte offset 10: 0xe2");
    expect_yaml_error("a: 1\x01\n", 6, SVP_ERR_FORMAT, "byte offset 4: 0x01");
    expect_yaml_error("a: \xc3", 4, SVP_ERR_FORMAT, "byte offset 3: 0xc3");
    expect_yaml_error("a: \xc0\xaf", 5, SVP_ERR_FORMAT, "byte offset 3: 0xc0");
    expect_yaml_error("a: \xed\xa0\x80", 6, SVP_ERR_FORMAT, "byte offset 3: 0xed");
    expect_yaml_error("a: \xef\xbf\xbe", 6, SVP_ERR_FORMAT, "byte offset 3: 0xef");
    expect_yaml_error("a: 1\0", 5, SVP_ERR_FORMAT, "byte offset 4: 0x00");
    /* printable UTF-8 (2, 3 and 4 bytes, NEL, a BOM) reads */
    const char *ok = "\xef\xbb\xbf# caf\xc3\xa9 \xe2\x80\x94 \xf0\x9f\x94\xac\xc2\x85\na: 1\n";
    svp_yaml_doc *doc = NULL;
    assert_int_equal(svp_yaml_load_string("t.yaml", ok, strlen(ok), &doc), SVP_OK);
    assert_string_equal(svp_yaml_text(svp_yaml_get(svp_yaml_root(doc), "a")), "1");
    svp_yaml_free(doc);

    /* bounds: nesting, keys per mapping, aliases */
    char *big = malloc(200000);
    assert_non_null(big);
    size_t n = 0;
    for (int i = 0; i < 300; i++) big[n++] = '[';
    for (int i = 0; i < 300; i++) big[n++] = ']';
    expect_yaml_error(big, n, SVP_ERR_FORMAT, "t.yaml:1:257: nesting deeper than 256 levels");
    n = 0;
    for (int i = 0; i < 4097; i++) n += (size_t)sprintf(big + n, "k%d: 1\n", i);
    expect_yaml_error(big, n, SVP_ERR_FORMAT, "t.yaml:4097:1: a mapping of more than 4096 keys");
    n = (size_t)sprintf(big, "a: &x 1\nb: [");
    for (int i = 0; i < 1025; i++) n += (size_t)sprintf(big + n, "*x, ");
    n += (size_t)sprintf(big + n, "1]\n");
    expect_yaml_error(big, n, SVP_ERR_FORMAT, "more than 1024 aliases");
    free(big);
    /* a NUL written as an escape in a quoted string */
    expect_yaml_error("a: \"x\\0y\"\n", 10, SVP_ERR_FORMAT, "t.yaml:1:4: a text value holds a NUL");
}

static void test_yaml_helpers(void **state)
{
    (void)state;
    const char *text = "size_um: [40, 30.5]\n"
                       "flag: yes\n"
                       "count: 12\n"
                       "name: 'quoted: text'\n"
                       "base: &b {fwhm_um: 1}\n"
                       "copy: *b\n"
                       "levels: [0.1, x]\n"
                       "sources:\n"
                       "  - flake: {size_um: 3}\n"
                       "  - strip: {width_um: 40}\n";
    svp_yaml_doc *doc = NULL;
    ASSERT_OK(svp_yaml_load_string("scene.yaml", text, strlen(text), &doc));
    const svp_yaml_node *root = svp_yaml_root(doc);
    double v[4];
    size_t n = 0;
    ASSERT_OK(svp_yaml_number_list(svp_yaml_get(root, "size_um"), "size_um", 2, 2, v, &n));
    assert_true(n == 2 && v[0] == 40 && v[1] == 30.5);
    ASSERT_FAILS(svp_yaml_number_list(svp_yaml_get(root, "size_um"), "size_um", 3, 3, v, &n),
                 SVP_ERR_FORMAT, "scene.yaml:1:10: size_um must be a list of 3 numbers, got 2");
    ASSERT_FAILS(svp_yaml_number_list(svp_yaml_get(root, "levels"), "levels", 1, 4, v, &n),
                 SVP_ERR_FORMAT, "scene.yaml:7:15: levels[1] must be a number, got 'x'");
    int flag = 0;
    ASSERT_OK(svp_yaml_get_bool(root, "flag", &flag, NULL));
    assert_int_equal(flag, 1);
    long long count = 0;
    int found = -1;
    ASSERT_OK(svp_yaml_get_int(root, "count", 0, 100, &count, &found));
    assert_true(count == 12 && found == 1);
    ASSERT_OK(svp_yaml_get_int(root, "absent", 0, 100, &count, &found));
    assert_true(count == 12 && found == 0);
    const char *name = NULL;
    ASSERT_OK(svp_yaml_get_string(root, "name", &name, NULL));
    assert_string_equal(name, "quoted: text");
    assert_true(svp_yaml_quoted(svp_yaml_get(root, "name")));
    /* an alias is the anchored node itself */
    assert_ptr_equal(svp_yaml_get(root, "copy"), svp_yaml_get(root, "base"));
    const svp_yaml_node *sources = svp_yaml_get(root, "sources");
    assert_int_equal(svp_yaml_type_of(sources), SVP_YAML_SEQUENCE);
    assert_int_equal(svp_yaml_size(sources), 2);
    const svp_yaml_node *strip = svp_yaml_item(sources, 1);
    assert_string_equal(svp_yaml_text(svp_yaml_key_at(strip, 0)), "strip");
    assert_int_equal(svp_yaml_line(strip), 10);
    assert_int_equal(svp_yaml_column(strip), 5);
    ASSERT_FAILS(svp_yaml_bool(svp_yaml_get(root, "count"), "count", &flag), SVP_ERR_FORMAT,
                 "scene.yaml:3:8: count must be true or false, got '12'");
    svp_yaml_free(doc);
}

static void test_yaml_writer_round_trip(void **state)
{
    (void)state;
    svp_yaml_writer *w = NULL;
    ASSERT_OK(svp_yaml_writer_new(&w));
    const double row0[3] = {0.1, 1.0 / 3.0, -2e-300}, row1[3] = {NAN, INFINITY, 5};
    svp_yaml_write_comment(w, "PSF map\nwritten by a test");
    svp_yaml_begin_mapping(w);
    svp_yaml_write_key_number(w, "pixel_um", 0.1);
    svp_yaml_write_key_string(w, "plain", "moffat");
    svp_yaml_write_key_string(w, "tricky", "a: \"b\" # c\n\\");
    svp_yaml_write_key_string(w, "looks_like_number", "1e3");
    svp_yaml_write_key_string(w, "looks_like_bool", "yes");
    svp_yaml_write_key_bool(w, "flag", 0);
    svp_yaml_write_key_int(w, "count", -42);
    svp_yaml_write_key(w, "grid");
    svp_yaml_begin_sequence(w);
    svp_yaml_write_number_list(w, row0, 3);
    svp_yaml_write_number_list(w, row1, 3);
    svp_yaml_end_sequence(w);
    svp_yaml_write_key(w, "regions");
    svp_yaml_begin_sequence(w);
    svp_yaml_begin_mapping(w);
    svp_yaml_write_key_int(w, "label", 1);
    svp_yaml_write_key_number(w, "beta", 1.1);
    svp_yaml_end_mapping(w);
    svp_yaml_begin_mapping(w);
    svp_yaml_end_mapping(w);
    svp_yaml_end_sequence(w);
    svp_yaml_write_key(w, "empty_list");
    svp_yaml_begin_sequence(w);
    svp_yaml_end_sequence(w);
    svp_yaml_write_key(w, "nested");
    svp_yaml_begin_mapping(w);
    svp_yaml_write_comment(w, "inside");
    svp_yaml_write_key_string(w, "x", NULL);
    svp_yaml_end_mapping(w);
    svp_yaml_end_mapping(w);
    const char *path = tmp_path("written.yaml");
    ASSERT_OK(svp_yaml_writer_write_file(w, path, 0));
    svp_yaml_writer_free(w);

    svp_yaml_doc *doc = NULL;
    ASSERT_OK(svp_yaml_load_file(path, &doc));
    const svp_yaml_node *root = svp_yaml_root(doc);
    double v[3];
    ASSERT_OK(svp_yaml_number(svp_yaml_get(root, "pixel_um"), "pixel_um", v));
    assert_true(v[0] == 0.1);
    assert_string_equal(svp_yaml_text(svp_yaml_get(root, "plain")), "moffat");
    assert_string_equal(svp_yaml_text(svp_yaml_get(root, "tricky")), "a: \"b\" # c\n\\");
    assert_string_equal(svp_yaml_text(svp_yaml_get(root, "looks_like_number")), "1e3");
    assert_true(svp_yaml_quoted(svp_yaml_get(root, "looks_like_number")));
    assert_string_equal(svp_yaml_text(svp_yaml_get(root, "looks_like_bool")), "yes");
    int flag = 1;
    ASSERT_OK(svp_yaml_bool(svp_yaml_get(root, "flag"), "flag", &flag));
    assert_int_equal(flag, 0);
    long long count;
    ASSERT_OK(svp_yaml_int(svp_yaml_get(root, "count"), "count", -100, 100, &count));
    assert_true(count == -42);
    const svp_yaml_node *grid = svp_yaml_get(root, "grid");
    assert_int_equal(svp_yaml_size(grid), 2);
    ASSERT_OK(svp_yaml_number_list(svp_yaml_item(grid, 0), "grid[0]", 3, 3, v, NULL));
    for (int i = 0; i < 3; i++) assert_true(same_bits(v[i], row0[i]));
    const svp_yaml_node *row = svp_yaml_item(grid, 1);
    ASSERT_OK(svp_yaml_number_in(svp_yaml_item(row, 0), "g", 0, 0, SVP_YAML_NONFINITE, &v[0]));
    ASSERT_OK(svp_yaml_number_in(svp_yaml_item(row, 1), "g", 0, 0, SVP_YAML_NONFINITE, &v[1]));
    assert_true(isnan(v[0]) && v[1] == INFINITY);
    const svp_yaml_node *regions = svp_yaml_get(root, "regions");
    assert_int_equal(svp_yaml_size(regions), 2);
    ASSERT_OK(svp_yaml_number(svp_yaml_get(svp_yaml_item(regions, 0), "beta"), "beta", v));
    assert_true(v[0] == 1.1);
    assert_int_equal(svp_yaml_type_of(svp_yaml_item(regions, 1)), SVP_YAML_MAPPING);
    assert_int_equal(svp_yaml_size(svp_yaml_item(regions, 1)), 0);
    assert_int_equal(svp_yaml_type_of(svp_yaml_get(root, "empty_list")), SVP_YAML_SEQUENCE);
    assert_int_equal(svp_yaml_type_of(svp_yaml_get(svp_yaml_get(root, "nested"), "x")),
                     SVP_YAML_NULL);
    svp_yaml_free(doc);

    /* misuse is reported, not written */
    ASSERT_OK(svp_yaml_writer_new(&w));
    svp_yaml_begin_mapping(w);
    svp_yaml_write_number(w, 1.0);
    ASSERT_FAILS(svp_yaml_writer_finish(w, NULL), SVP_ERR_INTERNAL,
                 "YAML writer: a value inside a mapping without a key");
    svp_yaml_writer_free(w);
}

/* ---- JSON ---------------------------------------------------------------------------------------- */

static void test_json_writer(void **state)
{
    (void)state;
    svp_json *j = NULL;
    ASSERT_OK(svp_json_new(&j));
    svp_json_begin_object(j);
    svp_json_key_string(j, "text", "quote \" backslash \\ newline \n tab \t bell \a µm");
    svp_json_key_string(j, "bad utf8", "\xff\xc3(");
    svp_json_key_number(j, "nan", NAN);
    svp_json_key_number(j, "inf", -INFINITY);
    svp_json_key_number(j, "tenth", 0.1);
    svp_json_key_number(j, "third", 1.0 / 3.0);
    svp_json_key_int(j, "big", 9007199254740993LL);
    svp_json_key_bool(j, "ok", 1);
    svp_json_key(j, "list");
    const double list[3] = {1, NAN, 2.5};
    svp_json_number_array(j, list, 3);
    svp_json_key(j, "objects");
    svp_json_begin_array(j);
    svp_json_begin_object(j);
    svp_json_end_object(j);
    svp_json_end_array(j);
    svp_json_end_object(j);
    const char *text = NULL;
    ASSERT_OK(svp_json_finish(j, &text));
    const char *expected =
        "{\n"
        "  \"text\": \"quote \\\" backslash \\\\ newline \\n tab \\t bell \\u0007 µm\",\n"
        "  \"bad utf8\": \"\\ufffd\\ufffd(\",\n"
        "  \"nan\": null,\n"
        "  \"inf\": null,\n"
        "  \"tenth\": 0.1,\n"
        "  \"third\": 0.3333333333333333,\n"
        "  \"big\": 9007199254740993,\n"
        "  \"ok\": true,\n"
        "  \"list\": [1, null, 2.5],\n"
        "  \"objects\": [\n"
        "    {}\n"
        "  ]\n"
        "}\n";
    assert_string_equal(text, expected);
    /* numbers are lossless */
    assert_true(strtod("0.3333333333333333", NULL) == 1.0 / 3.0);
    const char *path = tmp_path("summary.json");
    ASSERT_OK(svp_json_write_file(j, path, 0));
    ASSERT_FAILS(svp_json_write_file(j, path, 0), SVP_ERR_EXISTS, "summary.json exists");
    svp_json_free(j);

    /* nesting is checked */
    ASSERT_OK(svp_json_new(&j));
    svp_json_begin_object(j);
    svp_json_string(j, "no key");
    ASSERT_FAILS(svp_json_finish(j, NULL), SVP_ERR_INTERNAL,
                 "JSON writer: a value inside an object without a key");
    svp_json_free(j);
    ASSERT_OK(svp_json_new(&j));
    svp_json_begin_array(j);
    assert_int_equal(svp_json_end_object(j), SVP_ERR_INTERNAL); /* the message comes at finish */
    ASSERT_FAILS(svp_json_finish(j, NULL), SVP_ERR_INTERNAL,
                 "JSON writer: end_object without a matching begin_object");
    svp_json_free(j);
    ASSERT_OK(svp_json_new(&j));
    svp_json_begin_array(j);
    ASSERT_FAILS(svp_json_finish(j, NULL), SVP_ERR_INTERNAL, "an array was not closed");
    svp_json_free(j);
}

int main(void)
{
    svp_set_fft_effort(SVP_FFT_ESTIMATE);
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_npy_round_trip_exact),
        cmocka_unit_test(test_npy_numpy_fixtures),
        cmocka_unit_test(test_npy_bad_files),
        cmocka_unit_test(test_text_round_trip_and_parsing),
        cmocka_unit_test(test_tiff_round_trip),
        cmocka_unit_test(test_png16_round_trip),
        cmocka_unit_test(test_tiff_integer_and_truncated),
        cmocka_unit_test(test_tiff_stacks),
        cmocka_unit_test(test_npy_stacks),
        cmocka_unit_test(test_limits_and_temporaries),
        cmocka_unit_test(test_colour_png_and_channels),
        cmocka_unit_test(test_missing_and_unknown),
        cmocka_unit_test(test_no_overwrite),
        cmocka_unit_test(test_psf_file_valid),
        cmocka_unit_test(test_psf_file_errors),
        cmocka_unit_test(test_yaml_limits),
        cmocka_unit_test(test_yaml_helpers),
        cmocka_unit_test(test_yaml_writer_round_trip),
        cmocka_unit_test(test_json_writer),
    };
    int failed = cmocka_run_group_tests_name("io", tests, make_tmpdir, remove_tmpdir);
    svp_fft_cleanup();
    return failed;
}
