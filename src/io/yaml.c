/* YAML reading (a marked node tree built from libyaml's events), typed getters with
 * file:line:col messages, and a small block-style writer. See yaml.h. */
#include "yaml.h"

#include "../core/internal.h"
#include "image_io.h"
#include "json.h"

#include <ctype.h>
#include <errno.h>
#include <limits.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <strings.h>
#include <yaml.h>
#include <sys/stat.h>

/* ---- the tree -------------------------------------------------------------------------------- */

struct svp_yaml_node {
    svp_yaml_type type;
    int line, column; /* 1-based */
    int quoted;
    const char *file; /* the document's name */
    char *text;       /* scalars: the text ("" for null); collections: NULL */
    size_t nitems;    /* list: items; mapping: 2 × pairs (key, value, key, value, ...) */
    size_t cap;
    svp_yaml_node **items;
    char *anchor;
    svp_yaml_node *next_alloc; /* every node of a document, newest first, for freeing */
};

struct svp_yaml_doc {
    char *file;
    svp_yaml_node *root;
    svp_yaml_node *all;
};

#define YAML_MAX_DEPTH 256
/* bounds that keep the quadratic checks (duplicate keys, alias look-up) quick on any input
 * (docs/reliability.md): svpsf's files have tens of keys per mapping and few aliases */
#define YAML_MAX_PAIRS 4096
#define YAML_MAX_ALIASES 1024

typedef struct builder {
    svp_yaml_doc *doc;
    svp_yaml_node *stack[YAML_MAX_DEPTH];
    int depth;
    int documents;
    int aliases;
    int last_line, last_column; /* end of the previous event (1-based), for empty values */
} builder;

const char *svp_yaml_library_version(void) { return yaml_get_version_string(); }

static svp_yaml_node *node_new(builder *b, svp_yaml_type type, const yaml_mark_t *mark)
{
    svp_yaml_node *n = calloc(1, sizeof *n);
    if (!n) return NULL;
    n->type = type;
    n->file = b->doc->file;
    if (mark) { /* libyaml's marks are 0-based */
        n->line = mark->line + 1 > INT_MAX ? INT_MAX : (int)mark->line + 1;
        n->column = mark->column + 1 > INT_MAX ? INT_MAX : (int)mark->column + 1;
    } else {
        n->line = b->last_line;
        n->column = b->last_column;
    }
    n->next_alloc = b->doc->all;
    b->doc->all = n;
    return n;
}

static char *text_copy(const unsigned char *s, size_t len)
{
    char *copy = malloc(len + 1);
    if (!copy) return NULL;
    if (len) memcpy(copy, s, len);
    copy[len] = '\0';
    return copy;
}

static svp_status set_anchor(svp_yaml_node *n, const yaml_char_t *anchor)
{
    if (!anchor) return SVP_OK;
    n->anchor = text_copy(anchor, strlen((const char *)anchor));
    return n->anchor ? SVP_OK : svp_fail(SVP_ERR_NOMEM, "out of memory reading YAML");
}

/* Appends a finished or opened node to the innermost open collection (or makes it the root). */
static svp_status attach(builder *b, svp_yaml_node *n)
{
    if (b->depth == 0) {
        b->doc->root = n;
        return SVP_OK;
    }
    svp_yaml_node *parent = b->stack[b->depth - 1];
    if (parent->type == SVP_YAML_MAPPING && parent->nitems % 2 == 0) {
        /* n is a key: it must be text, and new */
        if (n->type != SVP_YAML_SCALAR)
            return svp_yaml_fail(n, SVP_ERR_FORMAT, "mapping keys must be plain names, got %s",
                                 n->type == SVP_YAML_NULL      ? "an empty key"
                                 : n->type == SVP_YAML_MAPPING ? "a mapping"
                                                               : "a list");
        for (size_t i = 0; i < parent->nitems; i += 2)
            if (strcmp(parent->items[i]->text, n->text) == 0)
                return svp_yaml_fail(n, SVP_ERR_FORMAT, "duplicate key '%s' (first at line %d)",
                                     n->text, parent->items[i]->line);
    }
    if (parent->type == SVP_YAML_MAPPING && parent->nitems >= 2 * YAML_MAX_PAIRS)
        return svp_yaml_fail(n, SVP_ERR_FORMAT, "a mapping of more than %d keys", YAML_MAX_PAIRS);
    if (parent->nitems == parent->cap) {
        size_t cap = parent->cap ? 2 * parent->cap : 8;
        svp_yaml_node **items = realloc(parent->items, cap * sizeof *items);
        if (!items) return svp_fail(SVP_ERR_NOMEM, "out of memory reading YAML");
        parent->items = items;
        parent->cap = cap;
    }
    parent->items[parent->nitems++] = n;
    return SVP_OK;
}

static int is_null_text(const char *s)
{
    return !*s || !strcmp(s, "~") || !strcmp(s, "null") || !strcmp(s, "Null") || !strcmp(s, "NULL");
}

static svp_status handle_event(builder *b, yaml_event_t *ev)
{
    const yaml_mark_t *mark = &ev->start_mark;
    svp_yaml_node *n = NULL;
    switch (ev->type) {
    case YAML_DOCUMENT_START_EVENT:
        if (++b->documents > 1) {
            svp_yaml_node where = {.file = b->doc->file,
                                   .line = (int)mark->line + 1,
                                   .column = (int)mark->column + 1};
            return svp_yaml_fail(&where, SVP_ERR_FORMAT,
                                 "a second YAML document ('---'): one document per file");
        }
        return SVP_OK;
    case YAML_MAPPING_START_EVENT:
    case YAML_SEQUENCE_START_EVENT: {
        const int is_map = ev->type == YAML_MAPPING_START_EVENT;
        n = node_new(b, is_map ? SVP_YAML_MAPPING : SVP_YAML_SEQUENCE, mark);
        if (!n) return svp_fail(SVP_ERR_NOMEM, "out of memory reading YAML");
        SVP_CHECK(set_anchor(n, is_map ? ev->data.mapping_start.anchor
                                       : ev->data.sequence_start.anchor));
        SVP_CHECK(attach(b, n));
        if (b->depth == YAML_MAX_DEPTH)
            return svp_yaml_fail(n, SVP_ERR_FORMAT, "nesting deeper than %d levels",
                                 YAML_MAX_DEPTH);
        b->stack[b->depth++] = n;
        return SVP_OK;
    }
    case YAML_MAPPING_END_EVENT:
    case YAML_SEQUENCE_END_EVENT:
        if (b->depth > 0) b->depth--;
        return SVP_OK;
    case YAML_SCALAR_EVENT: {
        /* the empty value of "key:" is reported just after its key (the previous event) */
        const int empty = ev->data.scalar.length == 0 &&
                          ev->data.scalar.style == YAML_PLAIN_SCALAR_STYLE &&
                          ev->start_mark.index == ev->end_mark.index;
        n = node_new(b, SVP_YAML_SCALAR, empty ? NULL : mark);
        if (!n) return svp_fail(SVP_ERR_NOMEM, "out of memory reading YAML");
        n->text = text_copy(ev->data.scalar.value, ev->data.scalar.length);
        if (!n->text) return svp_fail(SVP_ERR_NOMEM, "out of memory reading YAML");
        if (strlen(n->text) != ev->data.scalar.length) /* "\0" escapes in a quoted string */
            return svp_yaml_fail(n, SVP_ERR_FORMAT, "a text value holds a NUL character");
        n->quoted = ev->data.scalar.style == YAML_SINGLE_QUOTED_SCALAR_STYLE ||
                    ev->data.scalar.style == YAML_DOUBLE_QUOTED_SCALAR_STYLE;
        if (!n->quoted && !ev->data.scalar.tag && is_null_text(n->text)) n->type = SVP_YAML_NULL;
        SVP_CHECK(set_anchor(n, ev->data.scalar.anchor));
        return attach(b, n);
    }
    case YAML_ALIAS_EVENT: {
        const char *name = (const char *)ev->data.alias.anchor;
        svp_yaml_node where = {.file = b->doc->file,
                               .line = (int)mark->line + 1,
                               .column = (int)mark->column + 1};
        if (++b->aliases > YAML_MAX_ALIASES)
            return svp_yaml_fail(&where, SVP_ERR_FORMAT, "more than %d aliases", YAML_MAX_ALIASES);
        svp_yaml_node *target = NULL;
        for (svp_yaml_node *m = b->doc->all; m && !target; m = m->next_alloc)
            if (m->anchor && !strcmp(m->anchor, name)) target = m; /* newest definition */
        if (!target) return svp_yaml_fail(&where, SVP_ERR_FORMAT, "unknown alias '*%s'", name);
        for (int d = 0; d < b->depth; d++)
            if (b->stack[d] == target)
                return svp_yaml_fail(&where, SVP_ERR_FORMAT, "alias '*%s' refers to itself", name);
        return attach(b, target);
    }
    default: return SVP_OK;
    }
}

static svp_status parse_text(svp_yaml_doc *doc, const char *text, size_t len)
{
    svp_status st = SVP_OK;
    builder *b = calloc(1, sizeof *b);
    if (!b) return svp_fail(SVP_ERR_NOMEM, "out of memory reading YAML");
    b->doc = doc;
    b->last_line = b->last_column = 1;
    yaml_parser_t parser;
    if (!yaml_parser_initialize(&parser)) {
        free(b);
        return svp_fail(SVP_ERR_NOMEM, "%s: cannot create a YAML parser", doc->file);
    }
    yaml_parser_set_input_string(&parser, (const unsigned char *)text, len);
    yaml_parser_set_encoding(&parser, YAML_UTF8_ENCODING);
    for (;;) {
        yaml_event_t ev;
        if (!yaml_parser_parse(&parser, &ev)) {
            if (parser.error == YAML_MEMORY_ERROR) {
                st = svp_fail(SVP_ERR_NOMEM, "out of memory reading YAML");
            } else if (parser.error == YAML_READER_ERROR) {
                st = svp_fail(SVP_ERR_FORMAT, "%s: %s at byte offset %zu", doc->file,
                              parser.problem ? parser.problem : "unreadable text",
                              parser.problem_offset);
            } else {
                const yaml_mark_t *m = &parser.problem_mark;
                char context[160] = "";
                if (parser.context)
                    snprintf(context, sizeof context, " (%s at line %zu)", parser.context,
                             parser.context_mark.line + 1);
                st = svp_fail(SVP_ERR_FORMAT, "%s:%zu:%zu: %s%s", doc->file, m->line + 1,
                              m->column + 1, parser.problem ? parser.problem : "malformed YAML",
                              context);
            }
            break;
        }
        const int end = ev.type == YAML_STREAM_END_EVENT;
        st = handle_event(b, &ev);
        b->last_line = (int)ev.end_mark.line + 1;
        b->last_column = (int)ev.end_mark.column + 1;
        yaml_event_delete(&ev);
        if (st != SVP_OK || end) break;
    }
    yaml_parser_delete(&parser);
    if (st == SVP_OK && !doc->root) { /* an empty file: a null root at 1:1 */
        doc->root = node_new(b, SVP_YAML_NULL, NULL);
        if (!doc->root) {
            st = svp_fail(SVP_ERR_NOMEM, "out of memory reading YAML");
        } else {
            doc->root->line = doc->root->column = 1;
            doc->root->text = calloc(1, 1);
            if (!doc->root->text) st = svp_fail(SVP_ERR_NOMEM, "out of memory reading YAML");
        }
    }
    free(b);
    return st;
}

/* YAML admits only printable Unicode in UTF-8 (YAML 1.2 §5.1: tab, LF, CR, U+0020..U+007E,
 * U+0085, U+00A0..U+D7FF, U+E000..U+FFFD, U+10000..U+10FFFF). Checking this before parsing
 * gives one clear message for binary files (a PDF, an image) and is what kept Debian 12's
 * libfyaml 0.7.12, the parser before libyaml, from looping forever on some invalid bytes (for
 * example "%\xe8"; docs/reliability.md).
 * Returns the offset of the first byte that starts an invalid or unprintable character, or len
 * when the whole text is fine. */
static size_t first_non_text(const unsigned char *s, size_t len)
{
    size_t i = 0;
    while (i < len) {
        unsigned c = s[i];
        if (c < 0x80) {
            if (c == '\t' || c == '\n' || c == '\r' || (c >= 0x20 && c <= 0x7e)) {
                i++;
                continue;
            }
            return i;
        }
        size_t n;
        unsigned long cp, min;
        if ((c & 0xe0) == 0xc0) n = 2, cp = c & 0x1f, min = 0x80;
        else if ((c & 0xf0) == 0xe0) n = 3, cp = c & 0x0f, min = 0x800;
        else if ((c & 0xf8) == 0xf0) n = 4, cp = c & 0x07, min = 0x10000;
        else return i;
        if (len - i < n) return i;
        for (size_t k = 1; k < n; k++) {
            if ((s[i + k] & 0xc0) != 0x80) return i;
            cp = (cp << 6) | (s[i + k] & 0x3f);
        }
        if (cp < min || cp > 0x10ffff) return i; /* overlong or beyond Unicode */
        int printable = cp == 0x85 || (cp >= 0xa0 && cp <= 0xd7ff) ||
                        (cp >= 0xe000 && cp <= 0xfffd) || cp >= 0x10000;
        if (!printable) return i;
        i += n;
    }
    return len;
}

/* Refuses what is not YAML text before the parser sees it: larger than SVP_YAML_MAX_BYTES, or
 * a byte that is not printable UTF-8 (a PDF, an image or a binary given by mistake). */
static svp_status check_text(const char *name, const char *text, size_t len)
{
    if (len > SVP_YAML_MAX_BYTES)
        return svp_fail(SVP_ERR_FORMAT, "%s: %zu bytes, larger than the %d MiB a YAML file may have",
                        name, len, SVP_YAML_MAX_BYTES >> 20);
    size_t bad = first_non_text((const unsigned char *)text, len);
    if (bad < len)
        return svp_fail(SVP_ERR_FORMAT,
                        "%s: not a text file (byte offset %zu: 0x%02x is not printable UTF-8 text)",
                        name, bad, (unsigned)(unsigned char)text[bad]);
    return SVP_OK;
}

static svp_status doc_new(const char *name, svp_yaml_doc **out)
{
    *out = NULL;
    svp_yaml_doc *doc = calloc(1, sizeof *doc);
    if (!doc) return svp_fail(SVP_ERR_NOMEM, "out of memory reading YAML");
    doc->file = strdup(name ? name : "(yaml)");
    if (!doc->file) {
        free(doc);
        return svp_fail(SVP_ERR_NOMEM, "out of memory reading YAML");
    }
    *out = doc;
    return SVP_OK;
}

svp_status svp_yaml_load_string(const char *name, const char *text, size_t len, svp_yaml_doc **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_yaml_load_string: out is NULL");
    *out = NULL;
    if (!text) return svp_fail(SVP_ERR_INVALID, "svp_yaml_load_string: text is NULL");
    SVP_CHECK(check_text(name ? name : "(yaml)", text, len));
    svp_yaml_doc *doc = NULL;
    SVP_CHECK(doc_new(name, &doc));
    svp_status st = parse_text(doc, text, len);
    if (st != SVP_OK) {
        svp_yaml_free(doc);
        return st;
    }
    *out = doc;
    return SVP_OK;
}

svp_status svp_yaml_load_file(const char *path, svp_yaml_doc **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_yaml_load_file: out is NULL");
    *out = NULL;
    if (!path) return svp_fail(SVP_ERR_INVALID, "svp_yaml_load_file: path is NULL");
    struct stat sb;
    if (stat(path, &sb) != 0) {
        if (errno == ENOENT) return svp_fail(SVP_ERR_IO, "%s: no such file", path);
        return svp_fail(SVP_ERR_IO, "%s: cannot open (%s)", path, strerror(errno));
    }
    if (S_ISDIR(sb.st_mode)) return svp_fail(SVP_ERR_IO, "%s: is a directory", path);
    if (S_ISREG(sb.st_mode) && (unsigned long long)sb.st_size > SVP_YAML_MAX_BYTES)
        return svp_fail(SVP_ERR_FORMAT, "%s: %lld bytes, larger than the %d MiB a YAML file may have",
                        path, (long long)sb.st_size, SVP_YAML_MAX_BYTES >> 20);
    FILE *f = fopen(path, "rb");
    if (!f) return svp_fail(SVP_ERR_IO, "%s: cannot open (%s)", path, strerror(errno));
    svp_strbuf text;
    svp_strbuf_init(&text);
    char chunk[8192];
    size_t got;
    while ((got = fread(chunk, 1, sizeof chunk, f)) > 0 && text.len <= SVP_YAML_MAX_BYTES)
        svp_strbuf_append(&text, chunk, got);
    int read_error = ferror(f);
    fclose(f);
    svp_status st = SVP_OK;
    if (read_error)
        st = svp_fail(SVP_ERR_IO, "%s: read error", path);
    else if (text.failed)
        st = svp_fail(SVP_ERR_NOMEM, "%s: out of memory reading the file", path);
    else
        st = svp_yaml_load_string(path, text.data, text.len, out);
    svp_strbuf_free(&text);
    return st;
}

void svp_yaml_free(svp_yaml_doc *doc)
{
    if (!doc) return;
    svp_yaml_node *n = doc->all;
    while (n) {
        svp_yaml_node *next = n->next_alloc;
        free(n->text);
        free(n->items);
        free(n->anchor);
        free(n);
        n = next;
    }
    free(doc->file);
    free(doc);
}

const svp_yaml_node *svp_yaml_root(const svp_yaml_doc *doc) { return doc ? doc->root : NULL; }

/* ---- node access ----------------------------------------------------------------------------- */

svp_yaml_type svp_yaml_type_of(const svp_yaml_node *n) { return n ? n->type : SVP_YAML_NULL; }
const char *svp_yaml_file(const svp_yaml_node *n) { return n ? n->file : NULL; }
int svp_yaml_line(const svp_yaml_node *n) { return n ? n->line : 0; }
int svp_yaml_column(const svp_yaml_node *n) { return n ? n->column : 0; }
int svp_yaml_quoted(const svp_yaml_node *n) { return n ? n->quoted : 0; }

const char *svp_yaml_text(const svp_yaml_node *n)
{
    if (!n) return NULL;
    if (n->type == SVP_YAML_SEQUENCE || n->type == SVP_YAML_MAPPING) return NULL;
    if (n->type == SVP_YAML_NULL || !n->text) return "";
    return n->text;
}

size_t svp_yaml_size(const svp_yaml_node *n)
{
    if (!n) return 0;
    if (n->type == SVP_YAML_SEQUENCE) return n->nitems;
    if (n->type == SVP_YAML_MAPPING) return n->nitems / 2;
    return 0;
}

const svp_yaml_node *svp_yaml_item(const svp_yaml_node *list, size_t i)
{
    if (!list || list->type != SVP_YAML_SEQUENCE || i >= list->nitems) return NULL;
    return list->items[i];
}

const svp_yaml_node *svp_yaml_key_at(const svp_yaml_node *map, size_t i)
{
    if (!map || map->type != SVP_YAML_MAPPING || 2 * i + 1 >= map->nitems) return NULL;
    return map->items[2 * i];
}

const svp_yaml_node *svp_yaml_value_at(const svp_yaml_node *map, size_t i)
{
    if (!map || map->type != SVP_YAML_MAPPING || 2 * i + 1 >= map->nitems) return NULL;
    return map->items[2 * i + 1];
}

const svp_yaml_node *svp_yaml_get(const svp_yaml_node *map, const char *key)
{
    if (!map || !key || map->type != SVP_YAML_MAPPING) return NULL;
    for (size_t i = 0; i + 1 < map->nitems; i += 2)
        if (!strcmp(map->items[i]->text, key)) return map->items[i + 1];
    return NULL;
}

/* ---- errors ---------------------------------------------------------------------------------- */

const char *svp_yaml_where(const svp_yaml_node *n, char *buf, size_t size)
{
    if (!n)
        snprintf(buf, size, "(unknown position)");
    else
        snprintf(buf, size, "%s:%d:%d", n->file ? n->file : "(yaml)", n->line, n->column);
    return buf;
}

svp_status svp_yaml_fail(const svp_yaml_node *n, svp_status status, const char *fmt, ...)
{
    char message[900];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(message, sizeof message, fmt, ap);
    va_end(ap);
    if (!n) return svp_fail(status, "%s", message);
    char where[300];
    return svp_fail(status, "%s: %s", svp_yaml_where(n, where, sizeof where), message);
}

/* "'text'", "a mapping", "a list", "no value": what a node holds, for "got ..." */
static const char *describe(const svp_yaml_node *n, char *buf, size_t size)
{
    if (!n || n->type == SVP_YAML_NULL) return "no value";
    if (n->type == SVP_YAML_MAPPING) return "a mapping";
    if (n->type == SVP_YAML_SEQUENCE) return "a list";
    size_t len = strlen(n->text);
    if (len > 40)
        snprintf(buf, size, "'%.37s...'", n->text);
    else
        snprintf(buf, size, "'%s'", n->text);
    return buf;
}

svp_status svp_yaml_expect_mapping(const svp_yaml_node *n, const char *what)
{
    if (n && n->type == SVP_YAML_MAPPING) return SVP_OK;
    char got[64];
    if (!what)
        return svp_yaml_fail(n, SVP_ERR_FORMAT,
                             "the file must be a mapping of keys to values, got %s",
                             describe(n, got, sizeof got));
    return svp_yaml_fail(n, SVP_ERR_FORMAT, "%s must be a mapping of keys to values, got %s", what,
                         describe(n, got, sizeof got));
}

/* Levenshtein distance, for "did you mean". Keys are short; longer ones count as far. */
static int edit_distance(const char *a, const char *b)
{
    size_t la = strlen(a), lb = strlen(b);
    if (la > 63 || lb > 63) return 99;
    int row[64];
    for (size_t j = 0; j <= lb; j++) row[j] = (int)j;
    for (size_t i = 1; i <= la; i++) {
        int diag = row[0];
        row[0] = (int)i;
        for (size_t j = 1; j <= lb; j++) {
            int up = row[j];
            int best = diag + (a[i - 1] != b[j - 1]);
            if (up + 1 < best) best = up + 1;
            if (row[j - 1] + 1 < best) best = row[j - 1] + 1;
            row[j] = best;
            diag = up;
        }
    }
    return row[lb];
}

svp_status svp_yaml_check_keys(const svp_yaml_node *map, const char *what,
                               const char *const *allowed)
{
    SVP_CHECK(svp_yaml_expect_mapping(map, what));
    for (size_t i = 0; i + 1 < map->nitems; i += 2) {
        const svp_yaml_node *key = map->items[i];
        int known = 0;
        for (const char *const *a = allowed; *a && !known; a++) known = !strcmp(*a, key->text);
        if (known) continue;
        svp_strbuf list;
        svp_strbuf_init(&list);
        const char *suggestion = NULL;
        int best = 3; /* suggest only near misses: at most 2 edits */
        for (const char *const *a = allowed; *a; a++) {
            svp_strbuf_printf(&list, "%s%s", a == allowed ? "" : ", ", *a);
            int d = edit_distance(key->text, *a);
            if (d < best && d < (int)strlen(*a)) {
                best = d;
                suggestion = *a;
            }
        }
        char hint[128] = "";
        if (suggestion) snprintf(hint, sizeof hint, "; did you mean '%s'?", suggestion);
        svp_status st = svp_yaml_fail(
            key, SVP_ERR_FORMAT, "unknown key '%s'%s%s (expected one of: %s%s)", key->text,
            what ? " in " : "", what ? what : "", list.failed ? "..." : list.data, hint);
        svp_strbuf_free(&list);
        return st;
    }
    return SVP_OK;
}

svp_status svp_yaml_require(const svp_yaml_node *map, const char *key, const char *what,
                            const svp_yaml_node **child)
{
    SVP_CHECK(svp_yaml_expect_mapping(map, what));
    const svp_yaml_node *v = svp_yaml_get(map, key);
    if (!v)
        return svp_yaml_fail(map, SVP_ERR_FORMAT, "missing required key '%s'%s%s", key,
                             what ? " in " : "", what ? what : "");
    if (child) *child = v;
    return SVP_OK;
}

/* ---- typed values ---------------------------------------------------------------------------- */

/* 0 when text is a number (YAML's .inf/.nan spelled any way, or decimal text strtod reads in
 * full), -1 otherwise. */
static int parse_number(const char *text, double *value)
{
    const char *s = text;
    int negative = 0;
    if (*s == '+' || *s == '-') negative = *s++ == '-';
    if (!strcasecmp(s, ".inf") || !strcasecmp(s, "inf")) {
        *value = negative ? -INFINITY : INFINITY;
        return 0;
    }
    if (!strcasecmp(s, ".nan") || !strcasecmp(s, "nan")) {
        *value = NAN;
        return 0;
    }
    int digits = 0;
    for (const char *p = text; *p; p++) {
        if (isdigit((unsigned char)*p))
            digits = 1;
        else if (!strchr("+-.eE", *p))
            return -1; /* no hex, no words, no spaces */
    }
    if (!digits) return -1;
    char *end = NULL;
    errno = 0;
    double v = strtod(text, &end);
    if (end == text || *end) return -1;
    *value = v; /* an overflow (1e999) gives ±inf and is caught as non-finite */
    return 0;
}

static svp_status expect_scalar(const svp_yaml_node *n, const char *name, const char *kind)
{
    if (n && n->type == SVP_YAML_SCALAR) return SVP_OK;
    char got[64];
    return svp_yaml_fail(n, SVP_ERR_FORMAT, "%s must be %s, got %s", name, kind,
                         describe(n, got, sizeof got));
}

svp_status svp_yaml_number(const svp_yaml_node *n, const char *name, double *value)
{
    return svp_yaml_number_in(n, name, -INFINITY, INFINITY, 0, value);
}

static void format_range(char *buf, size_t size, double lo, double hi, int flags)
{
    const char *lo_op = (flags & SVP_YAML_OPEN_LO) ? ">" : ">=";
    const char *hi_op = (flags & SVP_YAML_OPEN_HI) ? "<" : "<=";
    if (isfinite(lo) && !isfinite(hi))
        snprintf(buf, size, "%s %g", lo_op, lo);
    else if (!isfinite(lo) && isfinite(hi))
        snprintf(buf, size, "%s %g", hi_op, hi);
    else
        snprintf(buf, size, "in %c%g, %g%c", (flags & SVP_YAML_OPEN_LO) ? '(' : '[', lo, hi,
                 (flags & SVP_YAML_OPEN_HI) ? ')' : ']');
}

svp_status svp_yaml_number_in(const svp_yaml_node *n, const char *name, double lo, double hi,
                              int flags, double *value)
{
    SVP_CHECK(expect_scalar(n, name, "a number"));
    double v;
    char got[64];
    if (parse_number(n->text, &v) != 0)
        return svp_yaml_fail(n, SVP_ERR_FORMAT, "%s must be a number, got %s", name,
                             describe(n, got, sizeof got));
    if (!isfinite(v)) {
        if (flags & SVP_YAML_NONFINITE) {
            *value = v;
            return SVP_OK;
        }
        return svp_yaml_fail(n, SVP_ERR_INVALID, "%s must be a finite number, got %s", name,
                             describe(n, got, sizeof got));
    }
    int below = (flags & SVP_YAML_OPEN_LO) ? !(v > lo) : !(v >= lo);
    int above = (flags & SVP_YAML_OPEN_HI) ? !(v < hi) : !(v <= hi);
    if ((isfinite(lo) && below) || (isfinite(hi) && above)) {
        char range[96];
        format_range(range, sizeof range, lo, hi, flags);
        return svp_yaml_fail(n, SVP_ERR_INVALID, "%s must be %s, got %s", name, range, n->text);
    }
    *value = v;
    return SVP_OK;
}

svp_status svp_yaml_int(const svp_yaml_node *n, const char *name, long long lo, long long hi,
                        long long *value)
{
    SVP_CHECK(expect_scalar(n, name, "an integer"));
    const char *s = n->text;
    char *end = NULL;
    char got[64];
    errno = 0;
    long long v = strtoll(s, &end, 10);
    int ok = end != s && !*end && !isspace((unsigned char)*s);
    if (!ok)
        return svp_yaml_fail(n, SVP_ERR_FORMAT, "%s must be an integer, got %s", name,
                             describe(n, got, sizeof got));
    if (errno == ERANGE || v < lo || v > hi)
        return svp_yaml_fail(n, SVP_ERR_INVALID, "%s must be an integer in %lld..%lld, got %s",
                             name, lo, hi, n->text);
    *value = v;
    return SVP_OK;
}

svp_status svp_yaml_bool(const svp_yaml_node *n, const char *name, int *value)
{
    SVP_CHECK(expect_scalar(n, name, "true or false"));
    static const char *const yes[] = {"true", "yes", "on"}, *const no[] = {"false", "no", "off"};
    for (int i = 0; i < 3; i++) {
        if (!strcasecmp(n->text, yes[i])) {
            *value = 1;
            return SVP_OK;
        }
        if (!strcasecmp(n->text, no[i])) {
            *value = 0;
            return SVP_OK;
        }
    }
    char got[64];
    return svp_yaml_fail(n, SVP_ERR_FORMAT, "%s must be true or false, got %s", name,
                         describe(n, got, sizeof got));
}

svp_status svp_yaml_string(const svp_yaml_node *n, const char *name, const char **value)
{
    SVP_CHECK(expect_scalar(n, name, "a string"));
    *value = n->text;
    return SVP_OK;
}

svp_status svp_yaml_choice(const svp_yaml_node *n, const char *name, const char *const *choices,
                           int *index)
{
    const char *s = NULL;
    SVP_CHECK(svp_yaml_string(n, name, &s));
    for (int i = 0; choices[i]; i++)
        if (!strcasecmp(s, choices[i])) {
            *index = i;
            return SVP_OK;
        }
    svp_strbuf list;
    svp_strbuf_init(&list);
    for (int i = 0; choices[i]; i++) svp_strbuf_printf(&list, "%s%s", i ? ", " : "", choices[i]);
    char got[64];
    svp_status st = svp_yaml_fail(n, SVP_ERR_INVALID, "%s must be one of %s; got %s", name,
                                  list.failed ? "..." : list.data, describe(n, got, sizeof got));
    svp_strbuf_free(&list);
    return st;
}

svp_status svp_yaml_number_list(const svp_yaml_node *n, const char *name, size_t min_count,
                                size_t max_count, double *values, size_t *count)
{
    char expected[96];
    if (min_count == max_count)
        snprintf(expected, sizeof expected, "a list of %zu number%s", min_count,
                 min_count == 1 ? "" : "s");
    else if (max_count == (size_t)-1)
        snprintf(expected, sizeof expected, "a list of at least %zu number%s", min_count,
                 min_count == 1 ? "" : "s");
    else
        snprintf(expected, sizeof expected, "a list of %zu to %zu numbers", min_count, max_count);
    char got[64];
    if (!n || n->type != SVP_YAML_SEQUENCE)
        return svp_yaml_fail(n, SVP_ERR_FORMAT, "%s must be %s, got %s", name, expected,
                             describe(n, got, sizeof got));
    if (n->nitems < min_count || n->nitems > max_count)
        return svp_yaml_fail(n, SVP_ERR_FORMAT, "%s must be %s, got %zu", name, expected,
                             n->nitems);
    for (size_t i = 0; i < n->nitems; i++) {
        char item_name[128];
        snprintf(item_name, sizeof item_name, "%s[%zu]", name, i);
        SVP_CHECK(svp_yaml_number(n->items[i], item_name, &values[i]));
    }
    if (count) *count = n->nitems;
    return SVP_OK;
}

svp_status svp_yaml_get_number(const svp_yaml_node *map, const char *key, double lo, double hi,
                               int flags, double *value, int *found)
{
    const svp_yaml_node *v = svp_yaml_get(map, key);
    if (found) *found = v != NULL;
    return v ? svp_yaml_number_in(v, key, lo, hi, flags, value) : SVP_OK;
}

svp_status svp_yaml_get_int(const svp_yaml_node *map, const char *key, long long lo, long long hi,
                            long long *value, int *found)
{
    const svp_yaml_node *v = svp_yaml_get(map, key);
    if (found) *found = v != NULL;
    return v ? svp_yaml_int(v, key, lo, hi, value) : SVP_OK;
}

svp_status svp_yaml_get_bool(const svp_yaml_node *map, const char *key, int *value, int *found)
{
    const svp_yaml_node *v = svp_yaml_get(map, key);
    if (found) *found = v != NULL;
    return v ? svp_yaml_bool(v, key, value) : SVP_OK;
}

svp_status svp_yaml_get_string(const svp_yaml_node *map, const char *key, const char **value,
                               int *found)
{
    const svp_yaml_node *v = svp_yaml_get(map, key);
    if (found) *found = v != NULL;
    return v ? svp_yaml_string(v, key, value) : SVP_OK;
}

svp_status svp_yaml_get_choice(const svp_yaml_node *map, const char *key,
                               const char *const *choices, int *index, int *found)
{
    const svp_yaml_node *v = svp_yaml_get(map, key);
    if (found) *found = v != NULL;
    return v ? svp_yaml_choice(v, key, choices, index) : SVP_OK;
}

/* ---- writer ---------------------------------------------------------------------------------- */

typedef struct writer_frame {
    int is_map;
    int indent;       /* column of this collection's entries */
    size_t count;     /* entries written */
    int header_open;  /* the parent's "key:" or "-" line is still open (no entry yet) */
    int first_inline; /* a mapping that is a list item: its first key follows the "- " */
} writer_frame;

struct svp_yaml_writer {
    svp_strbuf out;
    writer_frame stack[YAML_MAX_DEPTH];
    int depth;
    int line_open; /* after "key:" or "-": the value goes on this line */
    int root_done;
    svp_status status;
    char error[160];
};

svp_status svp_yaml_writer_new(svp_yaml_writer **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_yaml_writer_new: out is NULL");
    svp_yaml_writer *w = calloc(1, sizeof *w);
    if (!w) return svp_fail(SVP_ERR_NOMEM, "out of memory for a YAML writer");
    svp_strbuf_init(&w->out);
    *out = w;
    return SVP_OK;
}

void svp_yaml_writer_free(svp_yaml_writer *w)
{
    if (!w) return;
    svp_strbuf_free(&w->out);
    free(w);
}

static svp_status writer_misuse(svp_yaml_writer *w, const char *what)
{
    if (w->status == SVP_OK) {
        w->status = SVP_ERR_INTERNAL;
        snprintf(w->error, sizeof w->error, "YAML writer: %s", what);
    }
    return w->status;
}

static void spaces(svp_yaml_writer *w, int n)
{
    for (int i = 0; i < n; i++) svp_strbuf_append(&w->out, " ", 1);
}

/* Starts an entry (a key of a mapping, or the "-" of a list item) of the innermost frame. */
static void entry_start(svp_yaml_writer *w, writer_frame *f)
{
    if (f->count == 0 && f->header_open) {
        if (f->first_inline) {
            svp_strbuf_append(&w->out, " ", 1);
        } else {
            svp_strbuf_append(&w->out, "\n", 1);
            spaces(w, f->indent);
        }
        f->header_open = 0;
    } else {
        spaces(w, f->indent);
    }
    f->count++;
}

/* Where a value may go: after a key, after a list's "-", or (collections only) at the top. */
static svp_status before_value(svp_yaml_writer *w, int is_collection)
{
    if (w->status != SVP_OK) return w->status;
    if (w->depth == 0) {
        if (!is_collection) return writer_misuse(w, "a scalar at the top level");
        if (w->root_done) return writer_misuse(w, "a second top-level collection");
        return SVP_OK;
    }
    writer_frame *f = &w->stack[w->depth - 1];
    if (f->is_map) {
        if (!w->line_open) return writer_misuse(w, "a value inside a mapping without a key");
    } else {
        entry_start(w, f);
        svp_strbuf_append(&w->out, "-", 1);
        w->line_open = 1;
    }
    return SVP_OK;
}

/* Plain text reads back as the same string only when it is a simple word that is not a number,
 * a boolean or null. */
static int plain_safe(const char *s)
{
    if (!*s || !(isalpha((unsigned char)*s) || *s == '_' || *s == '/')) return 0;
    for (const char *p = s; *p; p++)
        if (!isalnum((unsigned char)*p) && !strchr("_-./+", *p)) return 0;
    static const char *const reserved[] = {"true", "false", "yes", "no",  "on",  "off",
                                           "null", "y",     "n",   "inf", "nan", NULL};
    for (int i = 0; reserved[i]; i++)
        if (!strcasecmp(s, reserved[i])) return 0;
    return 1;
}

static void write_string_text(svp_yaml_writer *w, const char *s)
{
    if (plain_safe(s)) {
        svp_strbuf_puts(&w->out, s);
        return;
    }
    svp_strbuf_append(&w->out, "\"", 1);
    for (const unsigned char *p = (const unsigned char *)s; *p; p++) {
        switch (*p) {
        case '"': svp_strbuf_append(&w->out, "\\\"", 2); break;
        case '\\': svp_strbuf_append(&w->out, "\\\\", 2); break;
        case '\n': svp_strbuf_append(&w->out, "\\n", 2); break;
        case '\t': svp_strbuf_append(&w->out, "\\t", 2); break;
        case '\r': svp_strbuf_append(&w->out, "\\r", 2); break;
        default:
            if (*p < 0x20 || *p == 0x7f)
                svp_strbuf_printf(&w->out, "\\x%02x", *p);
            else
                svp_strbuf_append(&w->out, (const char *)p, 1);
        }
    }
    svp_strbuf_append(&w->out, "\"", 1);
}

static void number_text(char buf[32], double v)
{
    if (isnan(v))
        strcpy(buf, ".nan");
    else if (isinf(v))
        strcpy(buf, v > 0 ? ".inf" : "-.inf");
    else {
        svp_format_double(buf, v);
        /* "1e-300" → "1.0e-300": YAML 1.1 readers (PyYAML) need the dot to see a float */
        char *e = strchr(buf, 'e');
        if (e && !strchr(buf, '.')) {
            memmove(e + 2, e, strlen(e) + 1);
            e[0] = '.';
            e[1] = '0';
        }
    }
}

static svp_status write_scalar_raw(svp_yaml_writer *w, const char *text, int is_string)
{
    SVP_CHECK(before_value(w, 0));
    svp_strbuf_append(&w->out, " ", 1);
    if (is_string)
        write_string_text(w, text);
    else
        svp_strbuf_puts(&w->out, text);
    svp_strbuf_append(&w->out, "\n", 1);
    w->line_open = 0;
    return SVP_OK;
}

svp_status svp_yaml_write_comment(svp_yaml_writer *w, const char *text)
{
    if (w->status != SVP_OK) return w->status;
    if (w->line_open && w->depth > 0 && w->stack[w->depth - 1].is_map)
        return writer_misuse(w, "a comment between a key and its value");
    int indent = 0;
    if (w->depth > 0) {
        writer_frame *f = &w->stack[w->depth - 1];
        indent = f->indent;
        if (f->count == 0 && f->header_open) { /* close the parent's "key:" line first */
            svp_strbuf_append(&w->out, "\n", 1);
            f->header_open = 0;
            f->first_inline = 0;
        }
    }
    /* one "# ..." line per line of text */
    const char *p = text ? text : "";
    do {
        const char *nl = strchr(p, '\n');
        size_t len = nl ? (size_t)(nl - p) : strlen(p);
        spaces(w, indent);
        svp_strbuf_append(&w->out, len ? "# " : "#", len ? 2 : 1);
        svp_strbuf_append(&w->out, p, len);
        svp_strbuf_append(&w->out, "\n", 1);
        p = nl ? nl + 1 : NULL;
    } while (p);
    return SVP_OK;
}

static svp_status writer_begin(svp_yaml_writer *w, int is_map)
{
    SVP_CHECK(before_value(w, 1));
    if (w->depth == YAML_MAX_DEPTH) return writer_misuse(w, "nesting too deep");
    writer_frame f = {
        .is_map = is_map, .indent = 0, .count = 0, .header_open = 0, .first_inline = 0};
    if (w->depth > 0) {
        writer_frame *parent = &w->stack[w->depth - 1];
        f.indent = parent->indent + 2;
        f.header_open = 1;
        f.first_inline = is_map && !parent->is_map;
    }
    w->stack[w->depth++] = f;
    w->line_open = 0;
    return SVP_OK;
}

static svp_status writer_end(svp_yaml_writer *w, int is_map)
{
    if (w->status != SVP_OK) return w->status;
    if (w->depth == 0 || w->stack[w->depth - 1].is_map != is_map)
        return writer_misuse(w, is_map ? "end_mapping without begin_mapping"
                                       : "end_sequence without begin_sequence");
    if (is_map && w->line_open) return writer_misuse(w, "a key without a value");
    writer_frame *f = &w->stack[w->depth - 1];
    if (f->count == 0) { /* empty: flow style on the open line, or on its own line */
        const char *empty = is_map ? "{}\n" : "[]\n";
        if (f->header_open)
            svp_strbuf_append(&w->out, " ", 1);
        else
            spaces(w, f->indent);
        svp_strbuf_puts(&w->out, empty);
    }
    w->depth--;
    w->line_open = 0;
    if (w->depth == 0) w->root_done = 1;
    return SVP_OK;
}

svp_status svp_yaml_begin_mapping(svp_yaml_writer *w) { return writer_begin(w, 1); }
svp_status svp_yaml_end_mapping(svp_yaml_writer *w) { return writer_end(w, 1); }
svp_status svp_yaml_begin_sequence(svp_yaml_writer *w) { return writer_begin(w, 0); }
svp_status svp_yaml_end_sequence(svp_yaml_writer *w) { return writer_end(w, 0); }

svp_status svp_yaml_write_key(svp_yaml_writer *w, const char *key)
{
    if (w->status != SVP_OK) return w->status;
    if (w->depth == 0 || !w->stack[w->depth - 1].is_map)
        return writer_misuse(w, "a key outside a mapping");
    if (w->line_open) return writer_misuse(w, "two keys in a row");
    if (!key || !*key) return writer_misuse(w, "an empty key");
    entry_start(w, &w->stack[w->depth - 1]);
    write_string_text(w, key);
    svp_strbuf_append(&w->out, ":", 1);
    w->line_open = 1;
    return SVP_OK;
}

svp_status svp_yaml_write_number(svp_yaml_writer *w, double v)
{
    char buf[32];
    number_text(buf, v);
    return write_scalar_raw(w, buf, 0);
}

svp_status svp_yaml_write_int(svp_yaml_writer *w, long long v)
{
    char buf[32];
    snprintf(buf, sizeof buf, "%lld", v);
    return write_scalar_raw(w, buf, 0);
}

svp_status svp_yaml_write_bool(svp_yaml_writer *w, int v)
{
    return write_scalar_raw(w, v ? "true" : "false", 0);
}

svp_status svp_yaml_write_string(svp_yaml_writer *w, const char *s)
{
    return s ? write_scalar_raw(w, s, 1) : svp_yaml_write_null(w);
}

svp_status svp_yaml_write_null(svp_yaml_writer *w) { return write_scalar_raw(w, "null", 0); }

svp_status svp_yaml_write_number_list(svp_yaml_writer *w, const double *v, size_t n)
{
    SVP_CHECK(before_value(w, 0));
    svp_strbuf_append(&w->out, " [", 2);
    for (size_t i = 0; i < n; i++) {
        char buf[32];
        number_text(buf, v[i]);
        if (i) svp_strbuf_append(&w->out, ", ", 2);
        svp_strbuf_puts(&w->out, buf);
    }
    svp_strbuf_append(&w->out, "]\n", 2);
    w->line_open = 0;
    return SVP_OK;
}

svp_status svp_yaml_write_key_number(svp_yaml_writer *w, const char *key, double v)
{
    SVP_CHECK(svp_yaml_write_key(w, key));
    return svp_yaml_write_number(w, v);
}

svp_status svp_yaml_write_key_int(svp_yaml_writer *w, const char *key, long long v)
{
    SVP_CHECK(svp_yaml_write_key(w, key));
    return svp_yaml_write_int(w, v);
}

svp_status svp_yaml_write_key_bool(svp_yaml_writer *w, const char *key, int v)
{
    SVP_CHECK(svp_yaml_write_key(w, key));
    return svp_yaml_write_bool(w, v);
}

svp_status svp_yaml_write_key_string(svp_yaml_writer *w, const char *key, const char *s)
{
    SVP_CHECK(svp_yaml_write_key(w, key));
    return svp_yaml_write_string(w, s);
}

svp_status svp_yaml_write_key_number_list(svp_yaml_writer *w, const char *key, const double *v,
                                          size_t n)
{
    SVP_CHECK(svp_yaml_write_key(w, key));
    return svp_yaml_write_number_list(w, v, n);
}

svp_status svp_yaml_writer_finish(svp_yaml_writer *w, const char **text)
{
    if (!w) return svp_fail(SVP_ERR_INVALID, "svp_yaml_writer_finish: writer is NULL");
    if (w->status == SVP_OK) {
        if (w->depth > 0)
            writer_misuse(w, w->stack[w->depth - 1].is_map ? "a mapping was not closed"
                                                           : "a list was not closed");
        else if (!w->root_done)
            writer_misuse(w, "nothing was written");
    }
    if (w->status != SVP_OK) return svp_fail(w->status, "%s", w->error);
    if (w->out.failed) return svp_fail(SVP_ERR_NOMEM, "out of memory while writing YAML");
    if (text) *text = w->out.data;
    return SVP_OK;
}

svp_status svp_yaml_writer_write_file(svp_yaml_writer *w, const char *path, int overwrite)
{
    const char *text = NULL;
    svp_status st = svp_yaml_writer_finish(w, &text);
    if (st != SVP_OK) return svp_fail_context(st, "%s", path ? path : "(null)");
    return svp_io_atomic_write_text(path, text, overwrite);
}
