/* YAML for svpsf's own files (PSF files, PSF-map files, scenes). Library-internal.
 *
 * Reading: libyaml's event parser builds a small read-only tree in which EVERY node (scalar,
 * list, mapping, and the empty value of "key:") knows its file, line and column, so callers can
 * report "file:line:col: ..." for any fault. Lines and columns are 1-based, as editors show
 * them (libyaml's marks are 0-based; the conversion happens here once).
 *
 *     svp_yaml_doc *doc = NULL;
 *     SVP_CHECK(svp_yaml_load_file(path, &doc));
 *     const svp_yaml_node *root = svp_yaml_root(doc), *psf = NULL;
 *     static const char *const top_keys[] = {"pixel_um", "psf", NULL};
 *     if ((st = svp_yaml_expect_mapping(root, "the file")) ||
 *         (st = svp_yaml_check_keys(root, NULL, top_keys)) ||
 *         (st = svp_yaml_require(root, "pixel_um", NULL, &node)) ||
 *         (st = svp_yaml_number_in(node, "pixel_um", 0, INFINITY, SVP_YAML_OPEN_LO, &px)))
 *         goto cleanup;
 *     svp_yaml_free(doc);
 *
 * Status codes and messages (all start with "file:line:col: "):
 *   SVP_ERR_IO      "x.yaml: no such file", "x.yaml: cannot open (Permission denied)"
 *   SVP_ERR_FORMAT  not text:         "x.yaml: not a text file (byte offset 1: 0xe8 is not
 *                                      printable UTF-8 text)" (checked before parsing)
 *                   too large:        "x.yaml: ... bytes, larger than the 16 MiB a YAML file ..."
 *                   malformed YAML:   "x.yaml:3:4: <libyaml's message>"
 *                   duplicate key:    "x.yaml:5:1: duplicate key 'halo' (first at line 2)"
 *                   unknown key:      "x.yaml:4:3: unknown key 'fwhm_nm' in psf (expected one
 *                                      of: model, fwhm_um, ...; did you mean 'fwhm_um'?)"
 *                   missing key:      "x.yaml:1:1: missing required key 'pixel_um'" / "... in psf"
 *                   wrong type:       "x.yaml:3:12: fwhm_um must be a number, got 'abc'"
 *                                     (got 'text' | got a mapping | got a list | got no value)
 *                   list length:      "x.yaml:2:9: size_um must be a list of 2 numbers, got 3"
 *   SVP_ERR_INVALID a value out of its range or not among the choices:
 *                                     "x.yaml:3:12: fwhm_um must be > 0, got -0.5"
 *                                     "x.yaml:4:9: halo must be in [0, 1), got 1.5"
 *                                     "x.yaml:2:10: model must be one of gaussian, lorentzian,
 *                                      moffat; got 'gauss'"
 *
 * Numbers: plain or quoted decimal text as strtod reads it ("1", "-2.5e-3"), YAML's .inf,
 * -.inf, .nan (only with SVP_YAML_NONFINITE). Integers: decimal without a fraction. Booleans:
 * true/false/yes/no/on/off in any case. Null: "~", "null" or nothing.
 *
 * Writing: svp_yaml_writer emits block-style YAML that svp_yaml_load_* reads back exactly
 * (numbers are written lossless, strings quoted when they would read as something else). */
#ifndef SVP_YAML_H
#define SVP_YAML_H

#include "svpsf.h"

#include <stddef.h>

#if defined(__GNUC__)
#define SVP_YAML_PRINTF(a, b) __attribute__((format(printf, a, b)))
#else
#define SVP_YAML_PRINTF(a, b)
#endif

typedef enum svp_yaml_type {
    SVP_YAML_NULL = 0,     /* "~", "null" or an empty value */
    SVP_YAML_SCALAR = 1,   /* any other scalar (text) */
    SVP_YAML_SEQUENCE = 2, /* a list */
    SVP_YAML_MAPPING = 3
} svp_yaml_type;

typedef struct svp_yaml_doc svp_yaml_doc;
typedef struct svp_yaml_node svp_yaml_node;

/* The largest YAML file read (docs/reliability.md). */
#define SVP_YAML_MAX_BYTES (16 << 20)

/* Parses one YAML document (a second "---" document is an error). An empty file gives a NULL
 * root node at 1:1. Aliases (*name) point at their anchored node. */
svp_status svp_yaml_load_file(const char *path, svp_yaml_doc **out);
/* The same from memory; `name` stands for the file in messages. */
svp_status svp_yaml_load_string(const char *name, const char *text, size_t len, svp_yaml_doc **out);
void svp_yaml_free(svp_yaml_doc *doc);
const svp_yaml_node *svp_yaml_root(const svp_yaml_doc *doc);
/* libyaml's version string (for --version and summary.json). */
const char *svp_yaml_library_version(void);

/* ---- nodes (all accept NULL and then return 0 / NULL / SVP_YAML_NULL) ---------------------- */
svp_yaml_type svp_yaml_type_of(const svp_yaml_node *n);
const char *svp_yaml_file(const svp_yaml_node *n);
int svp_yaml_line(const svp_yaml_node *n);   /* 1-based */
int svp_yaml_column(const svp_yaml_node *n); /* 1-based */
/* Scalar text ("" for a NULL node; NULL for lists and mappings). Valid while the doc lives. */
const char *svp_yaml_text(const svp_yaml_node *n);
/* Nonzero for '...' and "..." scalars. */
int svp_yaml_quoted(const svp_yaml_node *n);
/* Number of list items or mapping pairs (0 for scalars). */
size_t svp_yaml_size(const svp_yaml_node *n);
const svp_yaml_node *svp_yaml_item(const svp_yaml_node *list, size_t i);
const svp_yaml_node *svp_yaml_key_at(const svp_yaml_node *map, size_t i);
const svp_yaml_node *svp_yaml_value_at(const svp_yaml_node *map, size_t i);
/* The value of `key` in a mapping, or NULL when absent (or when map is not a mapping). Note: a
 * present key with no value gives a node of type SVP_YAML_NULL, not NULL. */
const svp_yaml_node *svp_yaml_get(const svp_yaml_node *map, const char *key);

/* ---- errors --------------------------------------------------------------------------------- */
/* Sets svp_last_error to "file:line:col: <message>" and returns status. n may be NULL (then
 * the message has no prefix). */
svp_status svp_yaml_fail(const svp_yaml_node *n, svp_status status, const char *fmt, ...)
    SVP_YAML_PRINTF(3, 4);
/* "file:line:col" of a node into buf. */
const char *svp_yaml_where(const svp_yaml_node *n, char *buf, size_t size);

/* ---- structure checks (SVP_ERR_FORMAT) ------------------------------------------------------
 * `what` names the mapping in messages ("psf"); NULL for the top level. */
svp_status svp_yaml_expect_mapping(const svp_yaml_node *n, const char *what);
/* Every key of map must be in `allowed` (a NULL-terminated list). */
svp_status svp_yaml_check_keys(const svp_yaml_node *map, const char *what,
                               const char *const *allowed);
/* *child = the value of a key that must be present. */
svp_status svp_yaml_require(const svp_yaml_node *map, const char *key, const char *what,
                            const svp_yaml_node **child);

/* ---- typed values; `name` (usually the key) names the value in messages ------------------- */
enum {
    SVP_YAML_OPEN_LO = 1,  /* lo is excluded: value > lo (else value >= lo) */
    SVP_YAML_OPEN_HI = 2,  /* hi is excluded: value < hi (else value <= hi) */
    SVP_YAML_NONFINITE = 4 /* .inf / .nan are accepted (and the range is not checked) */
};
/* A finite number (SVP_ERR_FORMAT when not a number). */
svp_status svp_yaml_number(const svp_yaml_node *n, const char *name, double *value);
/* A number in [lo, hi] (flags make either end open; ±INFINITY for no bound). */
svp_status svp_yaml_number_in(const svp_yaml_node *n, const char *name, double lo, double hi,
                              int flags, double *value);
/* An integer in lo..hi (inclusive). */
svp_status svp_yaml_int(const svp_yaml_node *n, const char *name, long long lo, long long hi,
                        long long *value);
svp_status svp_yaml_bool(const svp_yaml_node *n, const char *name, int *value);
/* Any non-null scalar's text. */
svp_status svp_yaml_string(const svp_yaml_node *n, const char *name, const char **value);
/* A string that must be one of `choices` (NULL-terminated); *index = its position. */
svp_status svp_yaml_choice(const svp_yaml_node *n, const char *name, const char *const *choices,
                           int *index);
/* A list of min_count..max_count finite numbers into values[max_count]; *count = how many. */
svp_status svp_yaml_number_list(const svp_yaml_node *n, const char *name, size_t min_count,
                                size_t max_count, double *values, size_t *count);

/* Optional keys of a mapping: when the key is absent nothing is written, *found (may be NULL)
 * = 0 and SVP_OK is returned; when present the value is checked as above, *found = 1. */
svp_status svp_yaml_get_number(const svp_yaml_node *map, const char *key, double lo, double hi,
                               int flags, double *value, int *found);
svp_status svp_yaml_get_int(const svp_yaml_node *map, const char *key, long long lo, long long hi,
                            long long *value, int *found);
svp_status svp_yaml_get_bool(const svp_yaml_node *map, const char *key, int *value, int *found);
svp_status svp_yaml_get_string(const svp_yaml_node *map, const char *key, const char **value,
                               int *found);
svp_status svp_yaml_get_choice(const svp_yaml_node *map, const char *key,
                               const char *const *choices, int *index, int *found);

/* ---- writing ----------------------------------------------------------------------------------
 *     svp_yaml_writer *w = NULL;
 *     svp_yaml_writer_new(&w);
 *     svp_yaml_write_comment(w, "PSF map written by svpsf 0.1.0");
 *     svp_yaml_begin_mapping(w);                 // the top level
 *     svp_yaml_write_key_number(w, "pixel_um", 0.1);
 *     svp_yaml_write_key(w, "psf");
 *     svp_yaml_begin_mapping(w);
 *     svp_yaml_write_key_string(w, "model", "moffat");
 *     svp_yaml_end_mapping(w);
 *     svp_yaml_write_key(w, "fwhm_um");
 *     svp_yaml_begin_sequence(w);                // a grid: one flow list per row
 *     svp_yaml_write_number_list(w, row0, nx);
 *     svp_yaml_write_number_list(w, row1, nx);
 *     svp_yaml_end_sequence(w);
 *     svp_yaml_end_mapping(w);
 *     st = svp_yaml_writer_write_file(w, "map.yaml", overwrite);   // atomic
 *     svp_yaml_writer_free(w);
 * Misuse (a value without a key in a mapping, unbalanced ends, ...) is sticky and reported by
 * finish/write_file as SVP_ERR_INTERNAL "YAML writer: ...". Numbers are lossless (shortest
 * round-trip text; .nan, .inf, -.inf). Strings are plain when that reads back as the same string,
 * else double-quoted with escapes. Comments may appear between entries. */
typedef struct svp_yaml_writer svp_yaml_writer;

svp_status svp_yaml_writer_new(svp_yaml_writer **out);
void svp_yaml_writer_free(svp_yaml_writer *w);
svp_status svp_yaml_write_comment(svp_yaml_writer *w, const char *text);
svp_status svp_yaml_begin_mapping(svp_yaml_writer *w);
svp_status svp_yaml_end_mapping(svp_yaml_writer *w);
svp_status svp_yaml_begin_sequence(svp_yaml_writer *w);
svp_status svp_yaml_end_sequence(svp_yaml_writer *w);
svp_status svp_yaml_write_key(svp_yaml_writer *w, const char *key);
svp_status svp_yaml_write_number(svp_yaml_writer *w, double v);
svp_status svp_yaml_write_int(svp_yaml_writer *w, long long v);
svp_status svp_yaml_write_bool(svp_yaml_writer *w, int v);
svp_status svp_yaml_write_string(svp_yaml_writer *w, const char *s); /* NULL → null */
svp_status svp_yaml_write_null(svp_yaml_writer *w);
/* A flow list on one line: [1, 2.5, 3]. */
svp_status svp_yaml_write_number_list(svp_yaml_writer *w, const double *v, size_t n);
svp_status svp_yaml_write_key_number(svp_yaml_writer *w, const char *key, double v);
svp_status svp_yaml_write_key_int(svp_yaml_writer *w, const char *key, long long v);
svp_status svp_yaml_write_key_bool(svp_yaml_writer *w, const char *key, int v);
svp_status svp_yaml_write_key_string(svp_yaml_writer *w, const char *key, const char *s);
svp_status svp_yaml_write_key_number_list(svp_yaml_writer *w, const char *key, const double *v,
                                          size_t n);
/* Checks the document is complete and returns its text (owned by w). */
svp_status svp_yaml_writer_finish(svp_yaml_writer *w, const char **text);
/* finish, then svp_io_atomic_write_text(path, text, overwrite). */
svp_status svp_yaml_writer_write_file(svp_yaml_writer *w, const char *path, int overwrite);

#endif
