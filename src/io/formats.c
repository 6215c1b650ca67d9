/* Image files: format dispatch by extension, .npy and numpy.savetxt text matrices, and the
 * atomic write used by every output (images, summary.json, YAML). TIFF/PNG decoding and
 * encoding live in image_io.cpp (OpenCV). */
#include "../core/internal.h"
#include "image_io.h"
#include "json.h"
#include "mat.h"

#include <errno.h>
#include <fcntl.h>
#include <limits.h>
#include <float.h>
#include <math.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>
#include <sys/stat.h>
#include <unistd.h>

/* ---- atomic writes ----------------------------------------------------------------------------- */

/* The process umask without changing it (umask() would, briefly, for every thread). */
static mode_t current_umask(void)
{
    mode_t mask = 022;
    FILE *f = fopen("/proc/self/status", "r");
    if (!f) return mask;
    char line[256];
    while (fgets(line, sizeof line, f))
        if (!strncmp(line, "Umask:", 6)) {
            mask = (mode_t)strtol(line + 6, NULL, 8);
            break;
        }
    fclose(f);
    return mask;
}

static svp_status write_all(int fd, const unsigned char *data, size_t size)
{
    while (size > 0) {
        ssize_t n = write(fd, data, size);
        if (n < 0) {
            if (errno == EINTR) continue;
            return SVP_ERR_IO;
        }
        data += n;
        size -= (size_t)n;
    }
    return SVP_OK;
}

static void fsync_folder(const char *path)
{
    /* best effort: makes the new directory entry durable too */
    const char *slash = strrchr(path, '/');
    char folder[PATH_MAX];
    if (!slash)
        strcpy(folder, ".");
    else if (slash == path)
        strcpy(folder, "/");
    else if ((size_t)(slash - path) < sizeof folder)
        snprintf(folder, sizeof folder, "%.*s", (int)(slash - path), path);
    else
        return;
    int fd = open(folder, O_RDONLY | O_DIRECTORY);
    if (fd >= 0) {
        fsync(fd);
        close(fd);
    }
}

/* Creates the temporary file (mkstemp on the template tmp) and registers it for removal by
 * the CLI's signal handler, with SIGTERM, SIGINT, SIGHUP and SIGQUIT held back in between: a
 * signal arriving right after the file appears would otherwise find it not yet registered and
 * leave it behind. A held signal is delivered on return, when the name is registered. */
static int temp_create(char *tmp, int *slot)
{
    sigset_t hold, old;
    sigemptyset(&hold);
    sigaddset(&hold, SIGTERM);
    sigaddset(&hold, SIGINT);
    sigaddset(&hold, SIGHUP);
    sigaddset(&hold, SIGQUIT);
    int masked = pthread_sigmask(SIG_BLOCK, &hold, &old) == 0;
    int fd = mkstemp(tmp);
    int err = errno;
    *slot = fd >= 0 ? svp_io_temp_register(tmp) : -1;
    if (masked) pthread_sigmask(SIG_SETMASK, &old, NULL);
    errno = err;
    return fd;
}

svp_status svp_io_atomic_write_bytes(const char *path, const void *data, size_t size, int overwrite)
{
    if (!path || !*path) return svp_fail(SVP_ERR_INVALID, "output path is empty");
    if (!data && size) return svp_fail(SVP_ERR_INVALID, "%s: no data to write", path);
    struct stat sb;
    if (lstat(path, &sb) == 0) {
        if (S_ISDIR(sb.st_mode)) return svp_fail(SVP_ERR_IO, "%s: is a directory", path);
        if (!overwrite)
            return svp_fail(SVP_ERR_EXISTS, "%s exists (use --force to overwrite)", path);
    }
    const char *slash = strrchr(path, '/');
    size_t folder_len = slash ? (size_t)(slash - path) + 1 : 0;
    const char *base = path + folder_len;
    if (!*base) return svp_fail(SVP_ERR_INVALID, "%s: names a folder, not a file", path);

    /* ".<name>.svpsf-tmp-<pid>-XXXXXX" in the same folder, so rename/link never cross file
     * systems; the PID lets a later run remove what a killed one left (docs/reliability.md) */
    {
        char folder[PATH_MAX];
        if (folder_len < sizeof folder) {
            snprintf(folder, sizeof folder, "%.*s", (int)folder_len, path);
            svp_io_temp_remove_stale(folder, base);
        }
    }
    size_t tmp_size = strlen(path) + sizeof SVP_IO_TEMP_TAG + 32;
    char *tmp = malloc(tmp_size);
    if (!tmp) return svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path);
    snprintf(tmp, tmp_size, "%.*s.%s" SVP_IO_TEMP_TAG "%ld-XXXXXX", (int)folder_len, path, base,
             (long)getpid());
    svp_status st = SVP_OK;
    int slot;
    int fd = temp_create(tmp, &slot);
    int tmp_exists = fd >= 0;
    if (fd < 0) {
        st = svp_fail(SVP_ERR_IO, "%s: cannot write (%s)", path, strerror(errno));
        goto cleanup;
    }
    if (fchmod(fd, 0666 & ~current_umask()) != 0 || write_all(fd, data, size) != SVP_OK ||
        fsync(fd) != 0) {
        st = svp_fail(SVP_ERR_IO, "%s: cannot write (%s)", path, strerror(errno));
        close(fd);
        goto cleanup;
    }
    if (close(fd) != 0) {
        st = svp_fail(SVP_ERR_IO, "%s: cannot write (%s)", path, strerror(errno));
        goto cleanup;
    }
    if (overwrite) {
        if (rename(tmp, path) != 0) {
            st = svp_fail(SVP_ERR_IO, "%s: cannot write (%s)", path, strerror(errno));
            goto cleanup;
        }
        tmp_exists = 0;
    } else if (link(tmp, path) != 0) {
        int err = errno;
        if (err == EEXIST) {
            st = svp_fail(SVP_ERR_EXISTS, "%s exists (use --force to overwrite)", path);
            goto cleanup;
        }
        if (err != EPERM && err != ENOTSUP && err != EOPNOTSUPP && err != ENOSYS) {
            st = svp_fail(SVP_ERR_IO, "%s: cannot write (%s)", path, strerror(err));
            goto cleanup;
        }
        /* no hard links on this file system: claim the name exclusively, then replace it */
        int claim = open(path, O_WRONLY | O_CREAT | O_EXCL, 0666);
        if (claim < 0) {
            if (errno == EEXIST)
                st = svp_fail(SVP_ERR_EXISTS, "%s exists (use --force to overwrite)", path);
            else
                st = svp_fail(SVP_ERR_IO, "%s: cannot write (%s)", path, strerror(errno));
            goto cleanup;
        }
        close(claim);
        if (rename(tmp, path) != 0) {
            st = svp_fail(SVP_ERR_IO, "%s: cannot write (%s)", path, strerror(errno));
            unlink(path);
            goto cleanup;
        }
        tmp_exists = 0;
    }
    fsync_folder(path);
cleanup:
    if (tmp_exists) unlink(tmp);
    svp_io_temp_release(slot);
    free(tmp);
    return st;
}

svp_status svp_io_atomic_write_text(const char *path, const char *text, int overwrite)
{
    if (!text) return svp_fail(SVP_ERR_INVALID, "%s: no text to write", path ? path : "");
    return svp_io_atomic_write_bytes(path, text, strlen(text), overwrite);
}

/* ---- reading whole files ------------------------------------------------------------------------ */

/* Checks the input exists and is a regular file: "<path>: no such file". */
static svp_status check_input(const char *path, struct stat *sb)
{
    if (stat(path, sb) != 0) {
        if (errno == ENOENT || errno == ENOTDIR)
            return svp_fail(SVP_ERR_IO, "%s: no such file", path);
        return svp_fail(SVP_ERR_IO, "%s: cannot open (%s)", path, strerror(errno));
    }
    if (S_ISDIR(sb->st_mode)) return svp_fail(SVP_ERR_IO, "%s: is a directory", path);
    return SVP_OK;
}

/* The whole file, NUL-terminated (text parsers rely on it). */
static svp_status read_file(const char *path, unsigned char **bytes, size_t *size)
{
    *bytes = NULL;
    *size = 0;
    FILE *f = fopen(path, "rb");
    if (!f) return svp_fail(SVP_ERR_IO, "%s: cannot open (%s)", path, strerror(errno));
    svp_status st = SVP_OK;
    size_t cap = 1 << 16, len = 0;
    unsigned char *buf = malloc(cap + 1);
    if (!buf) {
        st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path);
        goto cleanup;
    }
    for (;;) {
        if (len == cap) {
            unsigned char *bigger = cap < SIZE_MAX / 4 ? realloc(buf, 2 * cap + 1) : NULL;
            if (!bigger) {
                st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path);
                goto cleanup;
            }
            buf = bigger;
            cap *= 2;
        }
        size_t got = fread(buf + len, 1, cap - len, f);
        len += got;
        if (got == 0) break;
    }
    if (ferror(f)) {
        st = svp_fail(SVP_ERR_IO, "%s: read error", path);
        goto cleanup;
    }
    buf[len] = '\0';
    *bytes = buf;
    *size = len;
    buf = NULL;
cleanup:
    free(buf);
    fclose(f);
    return st;
}

/* ---- .npy -------------------------------------------------------------------------------------- */

/* The header is a Python dict literal, e.g.
 *   {'descr': '<f8', 'fortran_order': False, 'shape': (480, 640), }
 * Only string, bool and tuple-of-int values occur; other keys are ignored (as numpy does). */
typedef struct npy_header {
    char descr[32];
    int have_descr, descr_is_string;
    int fortran_order, have_order;
    long long shape[8];
    int ndim, have_shape;
} npy_header;

static const char *skip_space(const char *p, const char *end)
{
    while (p < end && (*p == ' ' || *p == '\t' || *p == '\n' || *p == '\r')) p++;
    return p;
}

/* Parses a quoted Python string into out (truncated to size); returns the end or NULL. */
static const char *npy_string(const char *p, const char *end, char *out, size_t size)
{
    if (p >= end || (*p != '\'' && *p != '"')) return NULL;
    char quote = *p++;
    size_t n = 0;
    while (p < end && *p != quote) {
        if (n + 1 < size) out[n++] = *p;
        p++;
    }
    if (p >= end) return NULL;
    out[n] = '\0';
    return p + 1;
}

/* Skips any value (for descr lists and unknown keys): balanced brackets and quotes. */
static const char *npy_skip_value(const char *p, const char *end)
{
    int depth = 0;
    while (p < end) {
        char c = *p;
        if (c == '\'' || c == '"') {
            char tmp[2];
            p = npy_string(p, end, tmp, sizeof tmp);
            if (!p) return NULL;
            continue;
        }
        if (c == '(' || c == '[' || c == '{') depth++;
        if (c == ')' || c == ']' || c == '}') {
            if (depth == 0) return p; /* the dict's closing brace */
            depth--;
        }
        if (c == ',' && depth == 0) return p;
        p++;
    }
    return NULL;
}

static const char *npy_parse_header(const char *p, const char *end, npy_header *h,
                                    const char **fault)
{
    memset(h, 0, sizeof *h);
    p = skip_space(p, end);
    if (p >= end || *p != '{') {
        *fault = "it does not start with '{'";
        return NULL;
    }
    p++;
    for (;;) {
        p = skip_space(p, end);
        if (p < end && *p == '}') return p + 1;
        char key[32];
        p = npy_string(p, end, key, sizeof key);
        if (!p) {
            *fault = "a key is not a quoted string";
            return NULL;
        }
        p = skip_space(p, end);
        if (p >= end || *p != ':') {
            *fault = "a key is not followed by ':'";
            return NULL;
        }
        p = skip_space(p + 1, end);
        if (!strcmp(key, "descr")) {
            h->have_descr = 1;
            const char *q = npy_string(p, end, h->descr, sizeof h->descr);
            if (q) {
                h->descr_is_string = 1;
                p = q;
            } else { /* a structured dtype (a list): unsupported, reported by the caller */
                p = npy_skip_value(p, end);
                snprintf(h->descr, sizeof h->descr, "structured");
            }
        } else if (!strcmp(key, "fortran_order")) {
            h->have_order = 1;
            if (end - p >= 4 && !strncmp(p, "True", 4)) {
                h->fortran_order = 1;
                p += 4;
            } else if (end - p >= 5 && !strncmp(p, "False", 5)) {
                p += 5;
            } else {
                *fault = "fortran_order is not True or False";
                return NULL;
            }
        } else if (!strcmp(key, "shape")) {
            h->have_shape = 1;
            if (p >= end || *p != '(') {
                *fault = "shape is not a tuple";
                return NULL;
            }
            p++;
            for (;;) {
                p = skip_space(p, end);
                if (p < end && *p == ')') {
                    p++;
                    break;
                }
                char *num_end = NULL;
                errno = 0;
                long long v = strtoll(p, &num_end, 10);
                if (num_end == p || errno || v < 0 || h->ndim == 8) {
                    *fault = "shape is not a tuple of sizes";
                    return NULL;
                }
                h->shape[h->ndim++] = v;
                p = num_end;
                if (p < end && *p == 'L') p++; /* Python 2 longs */
                p = skip_space(p, end);
                if (p < end && *p == ',') p++;
            }
        } else {
            p = npy_skip_value(p, end);
        }
        if (!p) {
            *fault = "a value is not terminated";
            return NULL;
        }
        p = skip_space(p, end);
        if (p < end && *p == ',')
            p++;
        else if (p < end && *p == '}')
            return p + 1;
        else {
            *fault = "entries are not separated by ','";
            return NULL;
        }
    }
}

static void shape_text(const npy_header *h, char *buf, size_t size)
{
    size_t n = (size_t)snprintf(buf, size, "(");
    for (int i = 0; i < h->ndim && n < size; i++)
        n += (size_t)snprintf(buf + n, size - n, "%s%lld", i ? ", " : "", h->shape[i]);
    if (n < size) snprintf(buf + n, size - n, h->ndim == 1 ? ",)" : ")");
}

static int host_is_little_endian(void)
{
    const uint16_t one = 1;
    unsigned char b;
    memcpy(&b, &one, 1);
    return b == 1;
}

/* One element of `size` bytes of kind 'f', 'i' or 'u' → double. */
static double npy_element(const unsigned char *p, char kind, int size, int swap)
{
    unsigned char b[8];
    for (int k = 0; k < size; k++) b[k] = swap ? p[size - 1 - k] : p[k];
    union {
        float f4;
        double f8;
        int8_t i1;
        int16_t i2;
        int32_t i4;
        int64_t i8;
        uint8_t u1;
        uint16_t u2;
        uint32_t u4;
        uint64_t u8;
    } u;
    memcpy(&u, b, (size_t)size);
    if (kind == 'f') return size == 4 ? (double)u.f4 : u.f8;
    if (kind == 'i') return size == 1 ? u.i1 : size == 2 ? u.i2 : size == 4 ? u.i4 : (double)u.i8;
    return size == 1 ? u.u1 : size == 2 ? u.u2 : size == 4 ? u.u4 : (double)u.u8;
}

/* What a stack met where one image is expected is pointed to. */
#define STACK_HINT "a stack is read as an ODMR stack by svp_stack_read / svpsf fit-odmr"

/* The frames of a .npy: a 2-D array is one frame; a 3-D array (frames, height, width) is a
 * stack when `stack` is nonzero, else refused naming its frame count. */
static svp_status read_npy_frames(const char *path, const unsigned char *bytes, size_t size,
                                  int stack, svp_image ***out, int *n_frames)
{
    *out = NULL;
    *n_frames = 0;
    static const unsigned char magic[6] = {0x93, 'N', 'U', 'M', 'P', 'Y'};
    if (size < 6 || memcmp(bytes, magic, 6) != 0) {
        if (size < 6 && memcmp(bytes, magic, size) == 0)
            return svp_fail(SVP_ERR_FORMAT, "%s: truncated: the file ends inside the header", path);
        return svp_fail(SVP_ERR_FORMAT, "%s: not a .npy file (bad magic bytes)", path);
    }
    if (size < 10)
        return svp_fail(SVP_ERR_FORMAT, "%s: truncated: the file ends inside the header", path);
    int major = bytes[6], minor = bytes[7];
    size_t header_len, header_start;
    if (major == 1) {
        header_len = (size_t)bytes[8] | (size_t)bytes[9] << 8;
        header_start = 10;
    } else if (major == 2 || major == 3) {
        if (size < 12)
            return svp_fail(SVP_ERR_FORMAT, "%s: truncated: the file ends inside the header", path);
        header_len = (size_t)bytes[8] | (size_t)bytes[9] << 8 | (size_t)bytes[10] << 16 |
                     (size_t)bytes[11] << 24;
        header_start = 12;
    } else {
        return svp_fail(SVP_ERR_FORMAT,
                        "%s: unsupported .npy format version %d.%d (expected 1.0, 2.0 or 3.0)",
                        path, major, minor);
    }
    if (header_len > size - header_start)
        return svp_fail(SVP_ERR_FORMAT, "%s: truncated: the file ends inside the header", path);
    const char *hp = (const char *)bytes + header_start;
    const char *hend = hp + header_len;
    npy_header h;
    const char *fault = "malformed";
    if (!npy_parse_header(hp, hend, &h, &fault))
        return svp_fail(SVP_ERR_FORMAT, "%s: malformed .npy header: %s", path, fault);
    if (!h.have_descr || !h.have_order || !h.have_shape)
        return svp_fail(SVP_ERR_FORMAT, "%s: malformed .npy header: missing '%s'", path,
                        !h.have_descr   ? "descr"
                        : !h.have_order ? "fortran_order"
                                        : "shape");

    /* dtype: byte order, kind, size */
    const char *d = h.descr;
    char order = '=';
    if (h.descr_is_string && (*d == '<' || *d == '>' || *d == '|' || *d == '=')) order = *d++;
    char kind = *d;
    char *size_end = NULL;
    long item = h.descr_is_string && kind ? strtol(d + 1, &size_end, 10) : 0;
    int supported =
        h.descr_is_string && size_end && !*size_end &&
        ((kind == 'f' && (item == 4 || item == 8)) ||
         ((kind == 'i' || kind == 'u') && (item == 1 || item == 2 || item == 4 || item == 8)));
    if (!supported)
        return svp_fail(SVP_ERR_FORMAT,
                        "%s: unsupported dtype '%s' (expected float32, float64 or a signed or "
                        "unsigned integer of 1, 2, 4 or 8 bytes)",
                        path, h.descr);
    int little = host_is_little_endian();
    int swap = item > 1 && ((order == '<' && !little) || (order == '>' && little));

    char shape[128];
    shape_text(&h, shape, sizeof shape);
    if (h.ndim == 3 && h.shape[2] == 1) h.ndim = 2; /* (h, w, 1): one channel */
    long long frames = 1, rows, cols;
    if (h.ndim == 3) {
        if (!stack)
            return svp_fail(SVP_ERR_FORMAT,
                            "%s: a stack of %lld frames (3-D array of shape %s): expected one "
                            "image (" STACK_HINT ")",
                            path, h.shape[0], shape);
        frames = h.shape[0];
        rows = h.shape[1];
        cols = h.shape[2];
    } else if (h.ndim == 2) {
        rows = h.shape[0];
        cols = h.shape[1];
    } else {
        return svp_fail(SVP_ERR_FORMAT,
                        stack ? "%s: %d-D array of shape %s: expected a 2-D image (height, width) "
                                "or a 3-D stack (frames, height, width)"
                              : "%s: %d-D array of shape %s: expected a 2-D image (height, width)",
                        path, h.ndim, shape);
    }
    if (rows == 0 || cols == 0 || frames == 0)
        return svp_fail(SVP_ERR_FORMAT, "%s: empty array of shape %s", path, shape);
    if (rows > INT_MAX || cols > INT_MAX || frames > INT_MAX ||
        (unsigned long long)rows > SIZE_MAX / (size_t)cols / (size_t)item ||
        (unsigned long long)frames > SIZE_MAX / ((size_t)rows * (size_t)cols * (size_t)item))
        return svp_fail(SVP_ERR_FORMAT, "%s: array of shape %s is too large", path, shape);
    SVP_CHECK(svp_io_check_image_size(path, "", cols, rows));
    const size_t plane = (size_t)rows * (size_t)cols, count = plane * (size_t)frames;
    size_t expected = count * (size_t)item;
    size_t data_start = header_start + header_len;
    size_t found = size - data_start;
    if (found < expected)
        return svp_fail(SVP_ERR_FORMAT, "%s: truncated: expected %zu bytes of data, found %zu",
                        path, expected, found);
    /* trailing bytes are ignored, as numpy.load does */
    SVP_CHECK(svp_io_check_memory(path, "reading the array as float64",
                                  (double)size + 8.0 * (double)count));

    svp_image **img = calloc((size_t)frames, sizeof *img);
    if (!img) return svp_fail(SVP_ERR_NOMEM, "%s: out of memory for %lld frames", path, frames);
    svp_status st = SVP_OK;
    for (long long f = 0; f < frames && st == SVP_OK; f++)
        st = svp_image_new((int)cols, (int)rows, &img[f]);
    if (st != SVP_OK) {
        for (long long f = 0; f < frames; f++) svp_image_free(img[f]);
        free(img);
        return st;
    }
    const unsigned char *data = bytes + data_start;
    const size_t w = (size_t)cols, hgt = (size_t)rows, nf = (size_t)frames;
    for (size_t k = 0; k < count; k++) {
        /* file order: C → (frame, y, x) row-major; Fortran → column-major (element (f, y, x)
         * at f + y F + x F h) */
        size_t f, y, x;
        if (h.fortran_order) {
            f = k % nf;
            y = k / nf % hgt;
            x = k / nf / hgt;
        } else {
            f = k / plane;
            y = k % plane / w;
            x = k % w;
        }
        img[f]->data[y * w + x] = npy_element(data + k * (size_t)item, kind, (int)item, swap);
    }
    *out = img;
    *n_frames = (int)frames;
    return SVP_OK;
}

static svp_status read_npy(const char *path, const unsigned char *bytes, size_t size,
                           svp_image **out)
{
    svp_image **frames = NULL;
    int n = 0;
    SVP_CHECK(read_npy_frames(path, bytes, size, 0, &frames, &n));
    *out = frames[0];
    free(frames);
    return SVP_OK;
}

/* float64 little-endian .npy of n frames of one size: shape (height, width) for one image
 * (stack 0), (n, height, width) for a stack. */
static svp_status write_npy_frames(const char *path, const svp_image *const *frames, int n,
                                   int stack, int overwrite)
{
    const svp_image *img = frames[0];
    char header[192];
    int hn = stack ? snprintf(header, sizeof header,
                              "{'descr': '<f8', 'fortran_order': False, 'shape': (%d, %d, %d), }",
                              n, img->height, img->width)
                   : snprintf(header, sizeof header,
                              "{'descr': '<f8', 'fortran_order': False, 'shape': (%d, %d), }",
                              img->height, img->width);
    /* pad with spaces and a final newline so the data starts at a multiple of 64 bytes */
    size_t header_len = (size_t)hn + 1;
    size_t total_header = (10 + header_len + 63) / 64 * 64;
    header_len = total_header - 10;
    const size_t count = (size_t)img->width * img->height;
    const size_t size = total_header + (size_t)n * count * 8;
    unsigned char *buf = malloc(size);
    if (!buf) return svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path);
    memcpy(buf, "\x93NUMPY\x01\x00", 8);
    buf[8] = (unsigned char)(header_len & 0xff);
    buf[9] = (unsigned char)(header_len >> 8);
    memcpy(buf + 10, header, (size_t)hn);
    memset(buf + 10 + hn, ' ', header_len - (size_t)hn - 1);
    buf[total_header - 1] = '\n';
    const int little = host_is_little_endian();
    unsigned char *out = buf + total_header;
    for (int f = 0; f < n; f++)
        for (size_t k = 0; k < count; k++, out += 8) {
            unsigned char b[8];
            memcpy(b, &frames[f]->data[k], 8);
            for (int i = 0; i < 8; i++) out[i] = little ? b[i] : b[7 - i];
        }
    svp_status st = svp_io_atomic_write_bytes(path, buf, size, overwrite);
    free(buf);
    return st;
}

static svp_status write_npy(const char *path, const svp_image *img, int overwrite)
{
    return write_npy_frames(path, &img, 1, 0, overwrite);
}

svp_status svp_stack_write(const char *path, const svp_image *const *frames, int n_frames,
                           int overwrite)
{
    if (!path || !*path) return svp_fail(SVP_ERR_INVALID, "svp_stack_write: no path given");
    if (!frames || n_frames < 1)
        return svp_fail(SVP_ERR_INVALID, "%s: no frames to write", path);
    const char *dot = strrchr(path, '.');
    if (!dot || strcmp(dot, ".npy") != 0)
        return svp_fail(SVP_ERR_INVALID, "%s: a stack is written as a 3-D .npy (the name must "
                        "end in .npy)", path);
    for (int f = 0; f < n_frames; f++)
        if (!frames[f] || !frames[f]->data || frames[f]->width != frames[0]->width ||
            frames[f]->height != frames[0]->height)
            return svp_fail(SVP_ERR_SIZE, "%s: frame %d is missing or not the first frame's size",
                            path, f);
    return write_npy_frames(path, frames, n_frames, 1, overwrite);
}

/* ---- numpy.savetxt text ------------------------------------------------------------------------ */

static int is_blank(char c) { return c == ' ' || c == '\t' || c == '\r' || c == '\v' || c == '\f'; }

static svp_status read_text(const char *path, char *text, size_t size, svp_image **out)
{
    svp_status st = SVP_OK;
    double *values = NULL;
    size_t nvalues = 0, cap = 0;
    long long columns = -1;
    long first_line = 0;
    int rows = 0, comma = -1;
    char *p = text, *end = text + size;
    if (size >= 3 && (unsigned char)p[0] == 0xEF && (unsigned char)p[1] == 0xBB &&
        (unsigned char)p[2] == 0xBF)
        p += 3; /* UTF-8 byte-order mark */
    for (long line = 1; p < end; line++) {
        char *eol = memchr(p, '\n', (size_t)(end - p));
        if (!eol) eol = end;
        *eol = '\0';
        char *hash = strchr(p, '#');
        if (hash) *hash = '\0';
        char *s = p;
        while (is_blank(*s)) s++;
        if (*s) {
            if (comma < 0) comma = strchr(s, ',') != NULL; /* decided by the first data row */
            long long ncols = 0;
            while (*s) {
                char *tok = s, *tok_end;
                int before_comma = 0;
                if (comma) {
                    tok_end = strchr(s, ',');
                    before_comma = tok_end != NULL;
                    if (!tok_end) tok_end = s + strlen(s);
                    s = *tok_end ? tok_end + 1 : tok_end;
                    while (tok < tok_end && is_blank(*tok)) tok++;
                    while (tok_end > tok && is_blank(tok_end[-1])) tok_end--;
                } else {
                    tok_end = tok;
                    while (*tok_end && !is_blank(*tok_end)) tok_end++;
                    s = tok_end;
                    while (is_blank(*s)) s++;
                }
                char saved = *tok_end;
                *tok_end = '\0';
                char *num_end = NULL;
                double v = strtod(tok, &num_end);
                if (num_end == tok || *num_end) {
                    st = svp_fail(SVP_ERR_FORMAT, "%s:%ld: '%.40s' is not a number (column %lld)",
                                  path, line, tok, ncols + 1);
                    goto cleanup;
                }
                *tok_end = saved;
                if (nvalues == cap) {
                    size_t new_cap = cap ? 2 * cap : 1024;
                    /* the file, the buffer while it moves, and the image made from it */
                    if (new_cap >= ((size_t)1 << 21) &&
                        (st = svp_io_check_memory(path, "reading its numbers",
                                                  (double)size +
                                                      8.0 * (double)(cap + 2 * new_cap))) != SVP_OK)
                        goto cleanup;
                    double *bigger = realloc(values, new_cap * sizeof *values);
                    if (!bigger) {
                        st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path);
                        goto cleanup;
                    }
                    values = bigger;
                    cap = new_cap;
                }
                values[nvalues++] = v;
                ncols++;
                /* "1,2," leaves an empty last column: a missing value */
                if (before_comma && !*s) {
                    st = svp_fail(SVP_ERR_FORMAT, "%s:%ld: '' is not a number (column %lld)", path,
                                  line, ncols + 1);
                    goto cleanup;
                }
            }
            if (columns < 0) {
                columns = ncols;
                first_line = line;
            } else if (ncols != columns) {
                st =
                    svp_fail(SVP_ERR_FORMAT, "%s:%ld: %lld columns, expected %lld (as on line %ld)",
                             path, line, ncols, columns, first_line);
                goto cleanup;
            }
            if (rows == INT_MAX || columns > INT_MAX) {
                st = svp_fail(SVP_ERR_FORMAT, "%s: too many rows or columns", path);
                goto cleanup;
            }
            if ((st = svp_io_check_image_size(path, "", columns, rows + 1LL)) != SVP_OK)
                goto cleanup;
            rows++;
        }
        p = eol + 1;
    }
    if (rows == 0) {
        st = svp_fail(SVP_ERR_FORMAT, "%s: no numbers found", path);
        goto cleanup;
    }
    svp_image *img = NULL;
    st = svp_image_new((int)columns, rows, &img);
    if (st != SVP_OK) goto cleanup;
    memcpy(img->data, values, nvalues * sizeof *values);
    *out = img;
cleanup:
    free(values);
    return st;
}

static svp_status write_text(const char *path, const svp_image *img, int comma, int overwrite)
{
    svp_strbuf b;
    svp_strbuf_init(&b);
    for (int y = 0; y < img->height && !b.failed; y++) {
        for (int x = 0; x < img->width; x++) {
            double v = img->data[(size_t)y * img->width + x];
            if (x) svp_strbuf_append(&b, comma ? "," : " ", 1);
            if (isnan(v))
                svp_strbuf_append(&b, "nan", 3); /* never "-nan" */
            else
                svp_strbuf_printf(&b, "%.17g", v); /* lossless; inf and -inf as numpy writes */
        }
        svp_strbuf_append(&b, "\n", 1);
    }
    svp_status st = b.failed ? svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path)
                             : svp_io_atomic_write_bytes(path, b.data, b.len, overwrite);
    svp_strbuf_free(&b);
    return st;
}

/* ---- PNG pre-check ---------------------------------------------------------------------------
 * libpng reports truncation, CRC errors and ancillary-chunk warnings (e.g. "iCCP: known incorrect
 * sRGB profile") by printing to stderr, and the library must not print. So the chunk structure
 * and every CRC are checked here first, and only the critical chunks (IHDR, PLTE, IDAT, IEND)
 * are handed to the decoder: a malformed file is refused before libpng sees it, and the
 * ancillary chunks (colour profiles, transparency, text) that do not change pixel values of a
 * single-channel image never reach it. */

static uint32_t crc32_png(const unsigned char *p, size_t n)
{
    uint32_t table[256]; /* 2k operations per call: cheaper than any sharing between threads */
    for (uint32_t i = 0; i < 256; i++) {
        uint32_t c = i;
        for (int k = 0; k < 8; k++) c = c & 1 ? 0xEDB88320u ^ (c >> 1) : c >> 1;
        table[i] = c;
    }
    uint32_t c = 0xFFFFFFFFu;
    for (size_t i = 0; i < n; i++) c = table[(c ^ p[i]) & 0xFF] ^ (c >> 8);
    return c ^ 0xFFFFFFFFu;
}

static uint32_t be32(const unsigned char *p)
{
    return (uint32_t)p[0] << 24 | (uint32_t)p[1] << 16 | (uint32_t)p[2] << 8 | p[3];
}

/* Validates the PNG in bytes[0..size) and writes its critical chunks to `critical` (at most
 * size bytes), returning their length in *critical_size. */
static svp_status png_critical_chunks(const char *path, const unsigned char *bytes, size_t size,
                                      unsigned char *critical, size_t *critical_size)
{
    size_t pos = 8, out = 8;
    memcpy(critical, bytes, 8);
    int seen_iend = 0;
    while (!seen_iend) {
        if (size - pos < 12)
            return svp_fail(SVP_ERR_FORMAT, "%s: cannot decode PNG (truncated or corrupt)", path);
        uint32_t len = be32(bytes + pos);
        const unsigned char *type = bytes + pos + 4;
        if (len > size - pos - 12)
            return svp_fail(SVP_ERR_FORMAT, "%s: cannot decode PNG (truncated or corrupt)", path);
        if (crc32_png(type, 4 + (size_t)len) != be32(type + 4 + len))
            return svp_fail(SVP_ERR_FORMAT,
                            "%s: cannot decode PNG (truncated or corrupt: CRC error in chunk "
                            "'%.4s')",
                            path, (const char *)type);
        if (!memcmp(type, "IHDR", 4) && len >= 13) { /* the size, before libpng allocates it */
            const unsigned char *d = type + 4;
            const long long w = be32(d), h = be32(d + 4);
            SVP_CHECK(svp_io_check_image_size(path, "", w, h));
            /* OpenCV decodes gray + alpha and colour to up to 4 channels */
            const double channels = d[9] == 0 ? 1 : 4, sample = d[8] == 16 ? 2 : 1;
            SVP_CHECK(svp_io_check_memory(path, "decoding the PNG",
                                          2.0 * (double)size +
                                              (double)w * (double)h * (channels * sample + 8.0)));
        }
        /* critical chunks have an upper-case first letter (bit 5 clear) */
        if (!(type[0] & 0x20)) {
            memcpy(critical + out, bytes + pos, 12 + (size_t)len);
            out += 12 + (size_t)len;
        }
        seen_iend = !memcmp(type, "IEND", 4);
        pos += 12 + (size_t)len;
    }
    *critical_size = out;
    return SVP_OK;
}

/* ---- TIFF directory chain ------------------------------------------------------------------------ */

static uint64_t tiff_get(const unsigned char *p, int bytes, int little)
{
    uint64_t v = 0;
    for (int k = 0; k < bytes; k++) v |= (uint64_t)p[little ? k : bytes - 1 - k] << (8 * k);
    return v;
}

/* The first value of a directory entry of an integer type, (S)BYTE, (S)SHORT, (S)LONG or
 * (S)LONG8, as libtiff reads it (0 for any other type, a negative value, or a value beyond the
 * end of the file). */
static uint64_t tiff_entry_value(const unsigned char *b, size_t size, const unsigned char *entry,
                                 int little, int big)
{
    const int type = (int)tiff_get(entry + 2, 2, little);
    const int tsize = type == 1 || type == 6     ? 1
                      : type == 3 || type == 8   ? 2
                      : type == 4 || type == 9   ? 4
                      : type == 16 || type == 17 ? 8
                                                 : 0;
    if (!tsize) return 0;
    const int is_signed = type == 6 || type == 8 || type == 9 || type == 17;
    const int count_bytes = big ? 8 : 4, inline_bytes = big ? 8 : 4;
    const uint64_t count = tiff_get(entry + 4, count_bytes, little);
    const unsigned char *value = entry + 4 + count_bytes;
    if (count > (uint64_t)inline_bytes / (uint64_t)tsize) { /* stored elsewhere */
        uint64_t at = tiff_get(value, inline_bytes, little);
        if (at > size || size - at < (uint64_t)tsize) return 0;
        value = b + at;
    }
    const uint64_t v = tiff_get(value, tsize, little);
    return is_signed && (v >> (8 * tsize - 1)) & 1 ? 0 : v;
}

/* What a TIFF's directories claim: pages, and the memory OpenCV and svpsf need to decode them
 * (every page as OpenCV's Mat and as float64, plus OpenCV's largest strip or tile buffer). */
typedef struct tiff_scan {
    long long pages;
    double decoded;  /* bytes of all pages: OpenCV's Mat + svpsf's float64 image */
    double tile_max; /* bytes of the largest strip or tile buffer */
    long long big_page, big_width, big_height; /* a page beyond the size limit (0: none) */
} tiff_scan;

static void tiff_scan_page(const unsigned char *b, size_t size, uint64_t ifd, uint64_t n,
                           int little, int big, tiff_scan *scan)
{
    const int count_bytes = big ? 8 : 2, entry_bytes = big ? 20 : 12;
    uint64_t width = 0, height = 0, bits = 1, spp = 1, photometric = 1, rows_per_strip = 0;
    uint64_t tile_w = 0, tile_h = 0;
    unsigned seen = 0; /* a tag given twice: libtiff reads the first entry */
    for (uint64_t k = 0; k < n; k++) {
        const unsigned char *e = b + ifd + (uint64_t)count_bytes + k * (uint64_t)entry_bytes;
        const unsigned tag = (unsigned)tiff_get(e, 2, little);
        const unsigned bit = tag >= 256 && tag <= 278   ? 1u << (tag - 256)
                             : tag == 322 || tag == 323 ? 1u << (tag - 322 + 23)
                                                        : 0;
        if (!bit || (seen & bit)) continue;
        seen |= bit;
        const uint64_t v = tiff_entry_value(b, size, e, little, big);
        switch (tag) {
        case 256: width = v; break;
        case 257: height = v; break;
        case 258: bits = v; break;
        case 262: photometric = v; break;
        case 277: spp = v; break;
        case 278: rows_per_strip = v; break;
        case 322: tile_w = v; break;
        case 323: tile_h = v; break;
        default: break;
        }
    }
    if (!scan->big_page && (width > SVP_IO_MAX_SIDE || height > SVP_IO_MAX_SIDE ||
                            (width && height > (uint64_t)SVP_IO_MAX_PIXELS / width))) {
        scan->big_page = scan->pages;
        scan->big_width = (long long)(width < INT64_MAX ? width : INT64_MAX);
        scan->big_height = (long long)(height < INT64_MAX ? height : INT64_MAX);
    }
    /* OpenCV keeps one channel of a plain grayscale page; others it decodes to up to 4 */
    const double channels = spp == 1 && photometric <= 1 ? 1 : 4;
    const double sample = bits > 8 ? (double)((bits + 7) / 8) : 1;
    const double pixels = (double)width * (double)height;
    scan->decoded += pixels * (channels * sample + (double)sizeof(double));
    double tile =
        tile_w && tile_h
            ? (double)tile_w * (double)tile_h
            : (double)width *
                  (double)(rows_per_strip && rows_per_strip < height ? rows_per_strip : height);
    tile *= channels * sample;
    if (tile > scan->tile_max) scan->tile_max = tile;
}

/* Walks the directory chain of a TIFF held in memory, classic or BigTIFF; pages = 0 when the
 * chain is broken (a directory beyond the end of the file, or a loop). The magic bytes were
 * checked by the caller. */
static void tiff_walk(const unsigned char *b, size_t size, tiff_scan *scan)
{
    memset(scan, 0, sizeof *scan);
    const int little = b[0] == 'I', big = tiff_get(b + 2, 2, little) == 43;
    const int off_bytes = big ? 8 : 4, count_bytes = big ? 8 : 2, entry_bytes = big ? 20 : 12;
    if (size < (size_t)(big ? 16 : 8)) return;
    uint64_t ifd = tiff_get(b + (big ? 8 : 4), off_bytes, little);
    /* every directory takes at least count + next-offset bytes: more pages than fit means a loop */
    const long long max_pages = (long long)(size / (size_t)(count_bytes + off_bytes)) + 1;
    while (ifd != 0) {
        if (ifd > size - (size_t)count_bytes || ++scan->pages > max_pages) {
            scan->pages = 0;
            return;
        }
        uint64_t n = tiff_get(b + ifd, count_bytes, little);
        uint64_t next_at = ifd + (uint64_t)count_bytes + n * (uint64_t)entry_bytes;
        if (n > size || next_at > size - (size_t)off_bytes) {
            scan->pages = 0;
            return;
        }
        tiff_scan_page(b, size, ifd, n, little, big, scan);
        ifd = tiff_get(b + next_at, off_bytes, little);
    }
}

/* Checks a TIFF's magic bytes, counts its pages (>= 1), and checks every page's size against
 * the image limit and the memory decoding all of them needs against the budget (before
 * OpenCV allocates it), else an error. */
static svp_status tiff_check(const char *path, const unsigned char *bytes, size_t size,
                             long long *pages)
{
    static const unsigned char le[4] = {'I', 'I', 42, 0}, be[4] = {'M', 'M', 0, 42},
                               le_big[4] = {'I', 'I', 43, 0}, be_big[4] = {'M', 'M', 0, 43};
    if (size < 8)
        return svp_fail(SVP_ERR_FORMAT, "%s: cannot decode TIFF (truncated or corrupt)", path);
    if (memcmp(bytes, le, 4) && memcmp(bytes, be, 4) && memcmp(bytes, le_big, 4) &&
        memcmp(bytes, be_big, 4))
        return svp_fail(SVP_ERR_FORMAT, "%s: not a TIFF file (bad magic bytes)", path);
    tiff_scan scan;
    tiff_walk(bytes, size, &scan);
    *pages = scan.pages;
    if (*pages < 1)
        return svp_fail(SVP_ERR_FORMAT, "%s: cannot decode TIFF (truncated or corrupt)", path);
    if (*pages > INT_MAX)
        return svp_fail(SVP_ERR_FORMAT, "%s: a TIFF of %lld pages is too large", path, *pages);
    if (scan.big_page) {
        char where[64] = "";
        if (*pages > 1) snprintf(where, sizeof where, "page %lld of %lld: ", scan.big_page, *pages);
        return svp_io_check_image_size(path, where, scan.big_width, scan.big_height);
    }
    char what[96];
    snprintf(what, sizeof what, "decoding %lld TIFF page%s", *pages, *pages > 1 ? "s" : "");
    return svp_io_check_memory(path, what, (double)size + scan.decoded + scan.tile_max);
}

/* ---- dispatch ------------------------------------------------------------------------------------ */

typedef enum file_kind { KIND_UNKNOWN, KIND_TIFF, KIND_PNG, KIND_NPY, KIND_TXT, KIND_MAT } file_kind;

/* The extension after the last '.' of the file name (not of a folder), lower-cased. */
static const char *extension(const char *path, char *buf, size_t size)
{
    const char *slash = strrchr(path, '/');
    const char *base = slash ? slash + 1 : path;
    const char *dot = strrchr(base, '.');
    if (!dot || dot == base) {
        buf[0] = '\0';
        return buf;
    }
    size_t n = 0;
    for (const char *p = dot + 1; *p && n + 1 < size; p++)
        buf[n++] = (char)((*p >= 'A' && *p <= 'Z') ? *p - 'A' + 'a' : *p);
    buf[n] = '\0';
    return buf;
}

static file_kind kind_of(const char *ext)
{
    if (!strcmp(ext, "tif") || !strcmp(ext, "tiff")) return KIND_TIFF;
    if (!strcmp(ext, "png")) return KIND_PNG;
    if (!strcmp(ext, "npy")) return KIND_NPY;
    if (!strcmp(ext, "txt") || !strcmp(ext, "csv") || !strcmp(ext, "dat")) return KIND_TXT;
    if (!strcmp(ext, "mat")) return KIND_MAT;
    return KIND_UNKNOWN;
}

static svp_status unknown_extension(const char *path, const char *ext)
{
    if (!*ext)
        return svp_fail(SVP_ERR_INVALID,
                        "%s: no file extension to tell the format (expected .tif, .tiff, .png, "
                        ".npy, .txt, .csv, .dat or .mat)",
                        path);
    return svp_fail(SVP_ERR_INVALID,
                    "%s: unknown image format '.%s' (expected .tif, .tiff, .png, .npy, .txt, "
                    ".csv, .dat or .mat)",
                    path, ext);
}

svp_status svp_image_read(const char *path, svp_image **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_image_read: out is NULL");
    *out = NULL;
    if (!path || !*path) return svp_fail(SVP_ERR_INVALID, "svp_image_read: no path given");
    {
        char mfile[PATH_MAX], mvar[64];
        int bad = 0;
        if (svp_io_mat_path(path, mfile, sizeof mfile, mvar, sizeof mvar, &bad))
            return svp_mat_read(path, NULL, out, NULL);
    }
    char ext[16];
    extension(path, ext, sizeof ext);
    file_kind kind = kind_of(ext);
    struct stat sb;
    SVP_CHECK(check_input(path, &sb));
    if (kind == KIND_UNKNOWN) return unknown_extension(path, ext);
    unsigned char *bytes = NULL;
    size_t size = 0;
    SVP_CHECK(read_file(path, &bytes, &size));
    svp_status st = SVP_OK;
    switch (kind) {
    case KIND_NPY: st = read_npy(path, bytes, size, out); break;
    case KIND_TXT: st = read_text(path, (char *)bytes, size, out); break;
    case KIND_TIFF: {
        long long pages = 0;
        st = tiff_check(path, bytes, size, &pages);
        if (st == SVP_OK && pages > 1)
            st = svp_fail(SVP_ERR_FORMAT,
                          "%s: multi-page TIFF of %lld pages: expected one image (" STACK_HINT ")",
                          path, pages);
        if (st == SVP_OK) st = svp_io_decode_cv(path, bytes, size, 1, out);
        break;
    }
    case KIND_PNG: {
        static const unsigned char sig[8] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
        if (size < 8 && !memcmp(bytes, sig, size))
            st = svp_fail(SVP_ERR_FORMAT, "%s: cannot decode PNG (truncated or corrupt)", path);
        else if (size < 8 || memcmp(bytes, sig, 8))
            st = svp_fail(SVP_ERR_FORMAT, "%s: not a PNG file (bad signature)", path);
        else {
            unsigned char *critical = malloc(size);
            size_t critical_size = 0;
            if (!critical)
                st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path);
            else
                st = png_critical_chunks(path, bytes, size, critical, &critical_size);
            if (st == SVP_OK) st = svp_io_decode_cv(path, critical, critical_size, 0, out);
            free(critical);
        }
        break;
    }
    case KIND_MAT: /* handled above */
    case KIND_UNKNOWN: break;
    }
    free(bytes);
    return st;
}

void svp_stack_free(svp_stack *stack)
{
    if (!stack) return;
    if (stack->frame)
        for (int i = 0; i < stack->n_frames; i++) svp_image_free(stack->frame[i]);
    free(stack->frame);
    free(stack);
}

svp_status svp_stack_read(const char *path, svp_stack **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_stack_read: out is NULL");
    *out = NULL;
    if (!path || !*path) return svp_fail(SVP_ERR_INVALID, "svp_stack_read: no path given");
    {
        char mfile[PATH_MAX], mvar[64];
        int bad = 0;
        if (svp_io_mat_path(path, mfile, sizeof mfile, mvar, sizeof mvar, &bad))
            return svp_mat_read_stack(path, NULL, out, NULL);
    }
    char ext[16];
    extension(path, ext, sizeof ext);
    file_kind kind = kind_of(ext);
    struct stat sb;
    SVP_CHECK(check_input(path, &sb));
    if (kind == KIND_UNKNOWN) return unknown_extension(path, ext);
    svp_stack *s = calloc(1, sizeof *s);
    if (!s) return svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path);
    svp_status st = SVP_OK;
    if (kind == KIND_TIFF || kind == KIND_NPY) {
        unsigned char *bytes = NULL;
        size_t size = 0;
        st = read_file(path, &bytes, &size);
        long long pages = 1;
        if (st == SVP_OK && kind == KIND_NPY)
            st = read_npy_frames(path, bytes, size, 1, &s->frame, &s->n_frames);
        else if (st == SVP_OK && (st = tiff_check(path, bytes, size, &pages)) == SVP_OK) {
            if (pages == 1) { /* the in-memory decoder of one image */
                s->frame = calloc(1, sizeof *s->frame);
                if (!s->frame)
                    st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path);
                else if ((st = svp_io_decode_cv(path, bytes, size, 1, &s->frame[0])) == SVP_OK)
                    s->n_frames = 1;
            } else {
                free(bytes); /* imreadmulti reads the file itself */
                bytes = NULL;
                if ((st = svp_io_read_tiff_pages(path, (int)pages, &s->frame)) == SVP_OK)
                    s->n_frames = (int)pages;
            }
        }
        free(bytes);
    } else {
        s->frame = calloc(1, sizeof *s->frame);
        if (!s->frame)
            st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path);
        else if ((st = svp_image_read(path, &s->frame[0])) == SVP_OK)
            s->n_frames = 1;
    }
    if (st != SVP_OK) {
        svp_stack_free(s);
        return st;
    }
    s->width = s->frame[0]->width;
    s->height = s->frame[0]->height;
    *out = s;
    return SVP_OK;
}

svp_status svp_image_write(const char *path, const svp_image *image, svp_file_format format,
                           int overwrite)
{
    if (!path || !*path) return svp_fail(SVP_ERR_INVALID, "svp_image_write: no path given");
    if (!image || !image->data || image->width < 1 || image->height < 1)
        return svp_fail(SVP_ERR_INVALID, "%s: no image to write", path);
    char ext[16];
    extension(path, ext, sizeof ext);
    {
        char mfile[PATH_MAX], mvar[64];
        int bad = 0;
        if (format == SVP_FORMAT_AUTO && svp_io_mat_path(path, mfile, sizeof mfile, mvar,
                                                         sizeof mvar, &bad))
            format = SVP_FORMAT_MAT;
    }
    if (format == SVP_FORMAT_AUTO) {
        switch (kind_of(ext)) {
        case KIND_TIFF: format = SVP_FORMAT_TIFF; break;
        case KIND_PNG: format = SVP_FORMAT_PNG16; break;
        case KIND_NPY: format = SVP_FORMAT_NPY; break;
        case KIND_TXT: format = SVP_FORMAT_TXT; break;
        case KIND_MAT: format = SVP_FORMAT_MAT; break;
        case KIND_UNKNOWN: return unknown_extension(path, ext);
        }
    }
    if (format == SVP_FORMAT_TIFF) { /* float32: beyond its range a value would become Inf */
        const double top = svp_max_abs(image->data, (size_t)image->width * image->height);
        if (top > FLT_MAX)
            return svp_fail(SVP_ERR_INVALID,
                            "%s: values up to %g exceed a float32 TIFF's range (3.4e38): they "
                            "would be written as Inf; write .npy (float64) or rescale",
                            path, top);
        /* below float32's normal range the whole map would lose its digits or become 0 */
        if (top > 0 && top < FLT_MIN)
            return svp_fail(SVP_ERR_INVALID,
                            "%s: values of at most %g are below a float32 TIFF's normal range "
                            "(1.2e-38): they would be written with fewer digits or as 0; write "
                            ".npy (float64) or rescale",
                            path, top);
    }
    switch (format) {
    case SVP_FORMAT_TIFF: return svp_io_write_tiff(path, image, overwrite);
    case SVP_FORMAT_PNG16: return svp_io_write_png16(path, image, overwrite);
    case SVP_FORMAT_NPY: return write_npy(path, image, overwrite);
    case SVP_FORMAT_TXT: return write_text(path, image, !strcmp(ext, "csv"), overwrite);
    case SVP_FORMAT_MAT: return svp_io_mat_write_image(path, image, overwrite);
    case SVP_FORMAT_AUTO: break;
    }
    return svp_fail(SVP_ERR_INVALID, "%s: unknown output format %d", path, (int)format);
}
