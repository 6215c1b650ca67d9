/* A growable text buffer and a small streaming JSON writer (summary.json). Library-internal.
 *
 * Usage:
 *     svp_json *j = NULL;
 *     SVP_CHECK(svp_json_new(&j));
 *     svp_json_begin_object(j);
 *     svp_json_key_string(j, "command", "correct");
 *     svp_json_key(j, "timings_s");
 *     svp_json_begin_object(j);
 *     svp_json_key_number(j, "total", 1.25);
 *     svp_json_end_object(j);
 *     svp_json_end_object(j);
 *     status = svp_json_write_file(j, "out/summary.json", force);  // atomic, like images
 *     svp_json_free(j);
 *
 * Misuse (a value without a key inside an object, a key inside an array, unbalanced ends, a
 * second top-level value) is remembered: the first one makes svp_json_finish/write_file return
 * SVP_ERR_INTERNAL "JSON writer: ...". Every call also returns the sticky status, so callers
 * may check each one or only the last. Strings are escaped (", \, control characters as \uXXXX,
 * invalid UTF-8 bytes as U+FFFD). Numbers are written with the shortest %.{15,16,17}g that
 * reads back to the same double (lossless); NaN and ±Inf are written as null. Output is indented
 * by two spaces, arrays of scalars on one line. */
#ifndef SVP_JSON_H
#define SVP_JSON_H

#include "svpsf.h"

#include <stddef.h>

#if defined(__GNUC__)
#define SVP_STRBUF_PRINTF(a, b) __attribute__((format(printf, a, b)))
#else
#define SVP_STRBUF_PRINTF(a, b)
#endif

/* ---- growable text -------------------------------------------------------------------------
 * data is always NUL-terminated (after init, ""). An allocation failure sets failed = 1; later
 * appends do nothing; the owner checks `failed` once at the end. */
typedef struct svp_strbuf {
    char *data;
    size_t len;
    size_t cap;
    int failed;
} svp_strbuf;

void svp_strbuf_init(svp_strbuf *b);
void svp_strbuf_free(svp_strbuf *b);
/* Returns 0 on success, -1 when memory ran out. */
int svp_strbuf_append(svp_strbuf *b, const char *text, size_t len);
int svp_strbuf_puts(svp_strbuf *b, const char *text);
int svp_strbuf_printf(svp_strbuf *b, const char *fmt, ...) SVP_STRBUF_PRINTF(2, 3);

/* The shortest "%.{15,16,17}g" text of a finite v that reads back exactly (buf >= 32 bytes).
 * Non-finite values give "nan", "inf" or "-inf". Returns buf. */
char *svp_format_double(char buf[32], double v);

/* ---- JSON ----------------------------------------------------------------------------------- */
typedef struct svp_json svp_json;

svp_status svp_json_new(svp_json **out);
void svp_json_free(svp_json *j);

svp_status svp_json_begin_object(svp_json *j);
svp_status svp_json_end_object(svp_json *j);
svp_status svp_json_begin_array(svp_json *j);
svp_status svp_json_end_array(svp_json *j);
/* The key of the next value (inside an object only). */
svp_status svp_json_key(svp_json *j, const char *key);
svp_status svp_json_string(svp_json *j, const char *s); /* NULL → null */
svp_status svp_json_number(svp_json *j, double v);      /* NaN/Inf → null */
svp_status svp_json_int(svp_json *j, long long v);
svp_status svp_json_bool(svp_json *j, int v);
svp_status svp_json_null(svp_json *j);
/* key + value in one call */
svp_status svp_json_key_string(svp_json *j, const char *key, const char *s);
svp_status svp_json_key_number(svp_json *j, const char *key, double v);
svp_status svp_json_key_int(svp_json *j, const char *key, long long v);
svp_status svp_json_key_bool(svp_json *j, const char *key, int v);
/* An array of numbers on one line. */
svp_status svp_json_number_array(svp_json *j, const double *v, size_t n);

/* The run's context that every summary.json carries (svpsf simulate's, written by the library,
 * and every other command's, written by the CLI), one key each: "working_directory";
 * "started_utc" (now − elapsed_s, ISO 8601); "versions" {svpsf, fftw, opencv, libyaml};
 * "peak_memory_bytes" (this process's maximum resident set). */
svp_status svp_json_key_working_directory(svp_json *j);
svp_status svp_json_key_started_utc(svp_json *j, double elapsed_s);
svp_status svp_json_key_versions(svp_json *j);
svp_status svp_json_key_peak_memory(svp_json *j);

/* Checks that exactly one complete top-level value was written and returns its text (owned by
 * j, ends with a newline). */
svp_status svp_json_finish(svp_json *j, const char **text);
/* svp_json_finish, then svp_io_atomic_write_text(path, text, overwrite). */
svp_status svp_json_write_file(svp_json *j, const char *path, int overwrite);

#endif
