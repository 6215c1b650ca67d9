/* Growable text buffer, shortest round-trip number formatting and a streaming JSON writer. */
#include "json.h"

#include "../core/internal.h"
#include "image_io.h"
#include "yaml.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/resource.h>
#include <time.h>
#include <unistd.h>

/* ---- growable text ------------------------------------------------------------------------ */

void svp_strbuf_init(svp_strbuf *b)
{
    b->data = NULL;
    b->len = 0;
    b->cap = 0;
    b->failed = 0;
    svp_strbuf_append(b, "", 0); /* so data is "" from the start */
}

void svp_strbuf_free(svp_strbuf *b)
{
    free(b->data);
    b->data = NULL;
    b->len = b->cap = 0;
}

static int strbuf_reserve(svp_strbuf *b, size_t extra)
{
    if (b->failed) return -1;
    if (b->len + extra + 1 <= b->cap) return 0;
    size_t cap = b->cap ? b->cap : 256;
    while (cap < b->len + extra + 1) {
        if (cap > ((size_t)-1) / 2) {
            b->failed = 1;
            return -1;
        }
        cap *= 2;
    }
    char *p = realloc(b->data, cap);
    if (!p) {
        b->failed = 1;
        return -1;
    }
    b->data = p;
    b->cap = cap;
    return 0;
}

int svp_strbuf_append(svp_strbuf *b, const char *text, size_t len)
{
    if (strbuf_reserve(b, len) != 0) return -1;
    if (len) memcpy(b->data + b->len, text, len);
    b->len += len;
    b->data[b->len] = '\0';
    return 0;
}

int svp_strbuf_puts(svp_strbuf *b, const char *text)
{
    return svp_strbuf_append(b, text, strlen(text));
}

int svp_strbuf_printf(svp_strbuf *b, const char *fmt, ...)
{
    if (b->failed) return -1;
    va_list ap;
    va_start(ap, fmt);
    int n = vsnprintf(NULL, 0, fmt, ap);
    va_end(ap);
    if (n < 0) {
        b->failed = 1;
        return -1;
    }
    if (strbuf_reserve(b, (size_t)n) != 0) return -1;
    va_start(ap, fmt);
    vsnprintf(b->data + b->len, (size_t)n + 1, fmt, ap);
    va_end(ap);
    b->len += (size_t)n;
    return 0;
}

char *svp_format_double(char buf[32], double v)
{
    if (isnan(v)) {
        strcpy(buf, "nan");
        return buf;
    }
    if (isinf(v)) {
        strcpy(buf, v > 0 ? "inf" : "-inf");
        return buf;
    }
    /* the shortest precision that reads back exactly: 0.1 stays "0.1", not 0.10000000000000001 */
    for (int precision = 15; precision <= 17; precision++) {
        snprintf(buf, 32, "%.*g", precision, v);
        if (strtod(buf, NULL) == v) break;
    }
    return buf;
}

/* ---- JSON writer --------------------------------------------------------------------------- */

#define JSON_MAX_DEPTH 64

typedef struct json_frame {
    int is_object;
    size_t count;      /* members (object: keys written) or elements (array) */
    int has_container; /* array: a nested object/array was written → multi-line */
} json_frame;

struct svp_json {
    svp_strbuf text;
    json_frame stack[JSON_MAX_DEPTH];
    int depth;
    int key_pending; /* a key was written in the innermost object, its value has not */
    int root_done;
    int finished;
    svp_status status;
    char error[160];
};

svp_status svp_json_new(svp_json **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_json_new: out is NULL");
    svp_json *j = calloc(1, sizeof *j);
    if (!j) return svp_fail(SVP_ERR_NOMEM, "out of memory for a JSON writer");
    svp_strbuf_init(&j->text);
    if (j->text.failed) {
        free(j);
        return svp_fail(SVP_ERR_NOMEM, "out of memory for a JSON writer");
    }
    *out = j;
    return SVP_OK;
}

void svp_json_free(svp_json *j)
{
    if (!j) return;
    svp_strbuf_free(&j->text);
    free(j);
}

static svp_status json_misuse(svp_json *j, const char *what)
{
    if (j->status == SVP_OK) {
        j->status = SVP_ERR_INTERNAL;
        snprintf(j->error, sizeof j->error, "JSON writer: %s", what);
    }
    return j->status;
}

static void json_indent(svp_json *j, int level)
{
    svp_strbuf_append(&j->text, "\n", 1);
    for (int i = 0; i < level; i++) svp_strbuf_append(&j->text, "  ", 2);
}

/* Everything written before a value: separators, the check that a key precedes it. */
static svp_status json_before_value(svp_json *j, int is_container)
{
    if (j->status != SVP_OK) return j->status;
    if (j->finished) return json_misuse(j, "value after svp_json_finish");
    if (j->depth == 0) {
        if (j->root_done) return json_misuse(j, "a second top-level value");
        return SVP_OK;
    }
    json_frame *f = &j->stack[j->depth - 1];
    if (f->is_object) {
        if (!j->key_pending) return json_misuse(j, "a value inside an object without a key");
        j->key_pending = 0;
        return SVP_OK;
    }
    if (is_container) {
        if (f->count) svp_strbuf_append(&j->text, ",", 1);
        json_indent(j, j->depth);
        f->has_container = 1;
    } else if (f->count) {
        svp_strbuf_append(&j->text, ", ", 2);
    }
    f->count++;
    return SVP_OK;
}

static void json_after_value(svp_json *j)
{
    if (j->depth == 0) j->root_done = 1;
}

static void json_escape(svp_strbuf *b, const char *s)
{
    const unsigned char *p = (const unsigned char *)s;
    svp_strbuf_append(b, "\"", 1);
    while (*p) {
        unsigned char c = *p;
        if (c == '"' || c == '\\') {
            char esc[2] = {'\\', (char)c};
            svp_strbuf_append(b, esc, 2);
            p++;
        } else if (c < 0x20) {
            switch (c) {
            case '\n': svp_strbuf_append(b, "\\n", 2); break;
            case '\t': svp_strbuf_append(b, "\\t", 2); break;
            case '\r': svp_strbuf_append(b, "\\r", 2); break;
            case '\b': svp_strbuf_append(b, "\\b", 2); break;
            case '\f': svp_strbuf_append(b, "\\f", 2); break;
            default: svp_strbuf_printf(b, "\\u%04x", c); break;
            }
            p++;
        } else if (c < 0x80) {
            svp_strbuf_append(b, (const char *)p, 1);
            p++;
        } else {
            /* a well-formed UTF-8 sequence is copied; anything else becomes U+FFFD */
            int n = c >= 0xF0 && c <= 0xF4   ? 4
                    : c >= 0xE0 && c <= 0xEF ? 3
                    : c >= 0xC2 && c <= 0xDF ? 2
                                             : 0;
            int ok = n > 0;
            for (int k = 1; ok && k < n; k++) ok = (p[k] & 0xC0) == 0x80;
            if (ok && n == 3) { /* no overlongs, no surrogates */
                unsigned cp = ((c & 0x0Fu) << 12) | ((p[1] & 0x3Fu) << 6) | (p[2] & 0x3Fu);
                ok = cp >= 0x800 && (cp < 0xD800 || cp > 0xDFFF);
            }
            if (ok && n == 4) {
                unsigned cp = ((c & 0x07u) << 18) | ((p[1] & 0x3Fu) << 12) | ((p[2] & 0x3Fu) << 6) |
                              (p[3] & 0x3Fu);
                ok = cp >= 0x10000 && cp <= 0x10FFFF;
            }
            if (ok) {
                svp_strbuf_append(b, (const char *)p, (size_t)n);
                p += n;
            } else {
                svp_strbuf_append(b, "\\ufffd", 6);
                p++;
            }
        }
    }
    svp_strbuf_append(b, "\"", 1);
}

static svp_status json_begin(svp_json *j, int is_object)
{
    SVP_CHECK(json_before_value(j, 1));
    if (j->depth >= JSON_MAX_DEPTH) return json_misuse(j, "nesting deeper than 64 levels");
    svp_strbuf_append(&j->text, is_object ? "{" : "[", 1);
    j->stack[j->depth].is_object = is_object;
    j->stack[j->depth].count = 0;
    j->stack[j->depth].has_container = 0;
    j->depth++;
    return SVP_OK;
}

static svp_status json_end(svp_json *j, int is_object)
{
    if (j->status != SVP_OK) return j->status;
    if (j->depth == 0 || j->stack[j->depth - 1].is_object != is_object)
        return json_misuse(j, is_object ? "end_object without a matching begin_object"
                                        : "end_array without a matching begin_array");
    if (is_object && j->key_pending) return json_misuse(j, "a key without a value");
    json_frame *f = &j->stack[j->depth - 1];
    int multiline = is_object ? f->count > 0 : f->has_container;
    j->depth--;
    if (multiline) json_indent(j, j->depth);
    svp_strbuf_append(&j->text, is_object ? "}" : "]", 1);
    json_after_value(j);
    return SVP_OK;
}

svp_status svp_json_begin_object(svp_json *j) { return json_begin(j, 1); }
svp_status svp_json_end_object(svp_json *j) { return json_end(j, 1); }
svp_status svp_json_begin_array(svp_json *j) { return json_begin(j, 0); }
svp_status svp_json_end_array(svp_json *j) { return json_end(j, 0); }

svp_status svp_json_key(svp_json *j, const char *key)
{
    if (j->status != SVP_OK) return j->status;
    if (j->depth == 0 || !j->stack[j->depth - 1].is_object)
        return json_misuse(j, "a key outside an object");
    if (j->key_pending) return json_misuse(j, "two keys in a row");
    if (!key) return json_misuse(j, "a NULL key");
    json_frame *f = &j->stack[j->depth - 1];
    if (f->count) svp_strbuf_append(&j->text, ",", 1);
    json_indent(j, j->depth);
    json_escape(&j->text, key);
    svp_strbuf_append(&j->text, ": ", 2);
    f->count++;
    j->key_pending = 1;
    return SVP_OK;
}

static svp_status json_raw_value(svp_json *j, const char *text)
{
    SVP_CHECK(json_before_value(j, 0));
    svp_strbuf_puts(&j->text, text);
    json_after_value(j);
    return SVP_OK;
}

svp_status svp_json_string(svp_json *j, const char *s)
{
    if (!s) return svp_json_null(j);
    SVP_CHECK(json_before_value(j, 0));
    json_escape(&j->text, s);
    json_after_value(j);
    return SVP_OK;
}

svp_status svp_json_number(svp_json *j, double v)
{
    char buf[32];
    return json_raw_value(j, isfinite(v) ? svp_format_double(buf, v) : "null");
}

svp_status svp_json_int(svp_json *j, long long v)
{
    char buf[32];
    snprintf(buf, sizeof buf, "%lld", v);
    return json_raw_value(j, buf);
}

svp_status svp_json_bool(svp_json *j, int v) { return json_raw_value(j, v ? "true" : "false"); }
svp_status svp_json_null(svp_json *j) { return json_raw_value(j, "null"); }

svp_status svp_json_key_string(svp_json *j, const char *key, const char *s)
{
    SVP_CHECK(svp_json_key(j, key));
    return svp_json_string(j, s);
}

svp_status svp_json_key_number(svp_json *j, const char *key, double v)
{
    SVP_CHECK(svp_json_key(j, key));
    return svp_json_number(j, v);
}

svp_status svp_json_key_int(svp_json *j, const char *key, long long v)
{
    SVP_CHECK(svp_json_key(j, key));
    return svp_json_int(j, v);
}

svp_status svp_json_key_bool(svp_json *j, const char *key, int v)
{
    SVP_CHECK(svp_json_key(j, key));
    return svp_json_bool(j, v);
}

svp_status svp_json_number_array(svp_json *j, const double *v, size_t n)
{
    SVP_CHECK(svp_json_begin_array(j));
    for (size_t i = 0; i < n; i++) SVP_CHECK(svp_json_number(j, v[i]));
    return svp_json_end_array(j);
}

svp_status svp_json_finish(svp_json *j, const char **text)
{
    if (!j) return svp_fail(SVP_ERR_INVALID, "svp_json_finish: writer is NULL");
    if (j->status == SVP_OK && !j->finished) {
        if (j->depth > 0)
            json_misuse(j, j->stack[j->depth - 1].is_object ? "an object was not closed"
                                                            : "an array was not closed");
        else if (!j->root_done)
            json_misuse(j, "nothing was written");
        else
            svp_strbuf_append(&j->text, "\n", 1);
        j->finished = j->status == SVP_OK;
    }
    if (j->status != SVP_OK) return svp_fail(j->status, "%s", j->error);
    if (j->text.failed) return svp_fail(SVP_ERR_NOMEM, "out of memory while writing JSON");
    if (text) *text = j->text.data;
    return SVP_OK;
}

svp_status svp_json_write_file(svp_json *j, const char *path, int overwrite)
{
    const char *text = NULL;
    svp_status st = svp_json_finish(j, &text);
    if (st != SVP_OK) return svp_fail_context(st, "%s", path ? path : "(null)");
    return svp_io_atomic_write_text(path, text, overwrite);
}

/* ---- a run's context -------------------------------------------------------------------------- */

svp_status svp_json_key_working_directory(svp_json *j)
{
    char cwd[4096];
    if (!getcwd(cwd, sizeof cwd)) snprintf(cwd, sizeof cwd, "?");
    return svp_json_key_string(j, "working_directory", cwd);
}

svp_status svp_json_key_started_utc(svp_json *j, double elapsed_s)
{
    char started[64] = "";
    time_t t = time(NULL) - (time_t)elapsed_s;
    struct tm tm;
    if (gmtime_r(&t, &tm)) strftime(started, sizeof started, "%Y-%m-%dT%H:%M:%SZ", &tm);
    return svp_json_key_string(j, "started_utc", started);
}

svp_status svp_json_key_versions(svp_json *j)
{
    SVP_CHECK(svp_json_key(j, "versions"));
    SVP_CHECK(svp_json_begin_object(j));
    SVP_CHECK(svp_json_key_string(j, "svpsf", svp_version()));
    SVP_CHECK(svp_json_key_string(j, "fftw", svp_fftw_version()));
    SVP_CHECK(svp_json_key_string(j, "opencv", svp_io_opencv_version()));
    SVP_CHECK(svp_json_key_string(j, "libyaml", svp_yaml_library_version()));
    return svp_json_end_object(j);
}

svp_status svp_json_key_peak_memory(svp_json *j)
{
    struct rusage ru;
    /* Linux reports KiB */
    const double bytes = getrusage(RUSAGE_SELF, &ru) == 0 ? (double)ru.ru_maxrss * 1024.0 : 0.0;
    return svp_json_key_number(j, "peak_memory_bytes", bytes);
}
