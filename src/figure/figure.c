/* Figures (figure.h): PNG maps (OpenCV colour maps, composed with cairo: colour bar with ticks
 * and units, scale bar, title) and line / step plots drawn with cairo (axes with ticks, labels,
 * legend). Every file is written atomically. */
#include "figure.h"

#include "../core/internal.h"
#include "../io/image_io.h"

#include <cairo.h>
#include <fontconfig/fontconfig.h>
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define FONT "DejaVu Sans"

/* ---- PNG into memory, then an atomic write --------------------------------------------- */

typedef struct membuf {
    unsigned char *data;
    size_t len, cap;
    int failed;
} membuf;

static cairo_status_t png_write_fn(void *closure, const unsigned char *data, unsigned int length)
{
    membuf *b = closure;
    if (b->len + length > b->cap) {
        size_t cap = b->cap ? b->cap : 65536;
        while (cap < b->len + length) cap *= 2;
        unsigned char *d = realloc(b->data, cap);
        if (!d) {
            b->failed = 1;
            return CAIRO_STATUS_WRITE_ERROR;
        }
        b->data = d;
        b->cap = cap;
    }
    memcpy(b->data + b->len, data, length);
    b->len += length;
    return CAIRO_STATUS_SUCCESS;
}

static svp_status finish_png(cairo_surface_t *surface, cairo_t *cr, const char *path, int overwrite)
{
    cairo_status_t cs = cairo_status(cr);
    cairo_destroy(cr);
    svp_status st = SVP_OK;
    if (cs != CAIRO_STATUS_SUCCESS) {
        st =
            svp_fail(SVP_ERR_INTERNAL, "%s: drawing failed (%s)", path, cairo_status_to_string(cs));
    } else {
        membuf b = {NULL, 0, 0, 0};
        cs = cairo_surface_write_to_png_stream(surface, png_write_fn, &b);
        if (cs != CAIRO_STATUS_SUCCESS || b.failed)
            st = svp_fail(b.failed ? SVP_ERR_NOMEM : SVP_ERR_INTERNAL,
                          "%s: PNG encoding failed (%s)", path, cairo_status_to_string(cs));
        else
            st = svp_io_atomic_write_bytes(path, b.data, b.len, overwrite);
        free(b.data);
    }
    cairo_surface_destroy(surface);
    return st;
}

/* ---- ticks --------------------------------------------------------------------------------- */

/* Heckbert's nice numbers. */
static double nice_number(double x, int round_it)
{
    if (!(x > 0)) return 1;
    double e = floor(log10(x)), f = x / pow(10, e), nf;
    if (round_it)
        nf = f < 1.5 ? 1 : f < 3 ? 2 : f < 7 ? 5 : 10;
    else
        nf = f <= 1 ? 1 : f <= 2 ? 2 : f <= 5 ? 5 : 10;
    return nf * pow(10, e);
}

static double tick_step(double lo, double hi, int target)
{
    double range = nice_number(hi - lo, 0);
    return nice_number(range / (target - 1), 1);
}

static void format_tick(char *buf, size_t size, double v, double step)
{
    if (fabs(v) < 1e-9 * step) v = 0;
    double a = fabs(v);
    if ((a >= 1e5 || (a > 0 && a < 1e-3)) && step < a)
        snprintf(buf, size, "%.3g", v);
    else {
        int dec = step >= 1 ? 0 : (int)ceil(-log10(step) - 1e-9);
        if (dec > 6) dec = 6;
        snprintf(buf, size, "%.*f", dec, v);
    }
}

static void text_at(cairo_t *cr, double x, double y, const char *s, double ax, double ay)
{
    cairo_text_extents_t e;
    cairo_text_extents(cr, s, &e);
    cairo_move_to(cr, x - ax * e.width - e.x_bearing, y - ay * e.height - e.y_bearing);
    cairo_show_text(cr, s);
}

/* ---- map figures ------------------------------------------------------------------------ */

/* The map in colour (display units over [lo, hi]) as a cairo surface of its own size. */
static svp_status map_surface(const char *path, const svp_image *img, double display_scale,
                              double lo, double hi, int diverging, cairo_surface_t **out)
{
    const int w = img->width, h = img->height;
    const size_t n = (size_t)w * h;
    double *vals = malloc(n * sizeof *vals);
    unsigned char *rgb = malloc(3 * n);
    if (!vals || !rgb) {
        free(vals), free(rgb);
        return svp_fail(SVP_ERR_NOMEM, "%s: out of memory", path);
    }
    for (size_t i = 0; i < n; i++) vals[i] = img->data[i] * display_scale;
    svp_status st = svp_io_colormap_rgb(vals, n, lo, hi, diverging, rgb);
    free(vals);
    if (st != SVP_OK) {
        free(rgb);
        return svp_fail_context(st, "%s", path);
    }
    cairo_surface_t *map = cairo_image_surface_create(CAIRO_FORMAT_RGB24, w, h);
    if (cairo_surface_status(map) != CAIRO_STATUS_SUCCESS) {
        free(rgb);
        cairo_surface_destroy(map);
        return svp_fail(SVP_ERR_NOMEM, "%s: out of memory for the figure", path);
    }
    cairo_surface_flush(map);
    unsigned char *pix = cairo_image_surface_get_data(map);
    int stride = cairo_image_surface_get_stride(map);
    for (int j = 0; j < h; j++) {
        uint32_t *row = (uint32_t *)(void *)(pix + (size_t)j * stride);
        for (int i = 0; i < w; i++) {
            const unsigned char *c = rgb + 3 * ((size_t)j * w + i);
            row[i] = ((uint32_t)c[0] << 16) | ((uint32_t)c[1] << 8) | c[2];
        }
    }
    cairo_surface_mark_dirty(map);
    free(rgb);
    *out = map;
    return SVP_OK;
}

/* The widest tick label of a colour bar over [lo, hi] with ticks every step (12 px font). */
static double tick_label_width(double lo, double hi, double step)
{
    double tick_w = 0;
    cairo_surface_t *probe = cairo_image_surface_create(CAIRO_FORMAT_RGB24, 1, 1);
    cairo_t *pc = cairo_create(probe);
    cairo_select_font_face(pc, FONT, CAIRO_FONT_SLANT_NORMAL, CAIRO_FONT_WEIGHT_NORMAL);
    cairo_set_font_size(pc, 12);
    for (double t = ceil(lo / step - 1e-9) * step; t <= hi + 1e-9 * step; t += step) {
        char tl[32];
        cairo_text_extents_t e;
        format_tick(tl, sizeof tl, t, step);
        cairo_text_extents(pc, tl, &e);
        tick_w = fmax(tick_w, e.x_advance);
    }
    cairo_destroy(pc);
    cairo_surface_destroy(probe);
    return tick_w;
}

/* A scale bar of a 1-2-5 length near a fifth of the view, at the lower left of the map (left,
 * top, map height mh; zoom figure px per image px). */
static void draw_scale_bar(cairo_t *cr, int w, double pixel_um, double zoom, double left,
                           double top, double mh)
{
    double width_um = w * pixel_um;
    double bar_um = nice_number(width_um / 5, 1);
    if (bar_um > width_um / 2) bar_um /= 2;
    double bar_px = bar_um / pixel_um * zoom;
    char label[64];
    if (bar_um >= 1)
        snprintf(label, sizeof label, "%g \xc2\xb5m", bar_um);
    else
        snprintf(label, sizeof label, "%g nm", bar_um * 1e3);
    cairo_set_font_size(cr, 13);
    cairo_text_extents_t te;
    cairo_text_extents(cr, label, &te);
    double bx = left + 12, by = top + mh - 14;
    double box_w = fmax(bar_px, te.width) + 12;
    cairo_set_source_rgba(cr, 1, 1, 1, 0.75);
    cairo_rectangle(cr, bx - 6, by - te.height - 14, box_w, te.height + 22);
    cairo_fill(cr);
    cairo_set_source_rgb(cr, 0, 0, 0);
    cairo_rectangle(cr, bx, by - 4, bar_px, 5);
    cairo_fill(cr);
    text_at(cr, bx + 0.5 * bar_px, by - 8, label, 0.5, 1);
}

/* The colour bar (hi at the top) at x0, from top over mh, its ticks every step and the
 * quantity's label rotated along it (tick_w: the widest tick label). */
static void draw_colour_bar(cairo_t *cr, double x0, double top, double mh, double bar_w,
                            double lo, double hi, int diverging, double step, double tick_w,
                            const char *bar_label)
{
    const int nbar = 256;
    double barv[256];
    unsigned char barc[3 * 256];
    for (int i = 0; i < nbar; i++) barv[i] = hi - (hi - lo) * (i + 0.5) / nbar;
    if (svp_io_colormap_rgb(barv, nbar, lo, hi, diverging, barc) != SVP_OK) return;
    for (int i = 0; i < nbar; i++) {
        cairo_set_source_rgb(cr, barc[3 * i] / 255.0, barc[3 * i + 1] / 255.0,
                             barc[3 * i + 2] / 255.0);
        cairo_rectangle(cr, x0, top + mh * i / nbar, bar_w, mh / nbar + 0.6);
        cairo_fill(cr);
    }
    cairo_set_source_rgb(cr, 0, 0, 0);
    cairo_rectangle(cr, x0 - 0.5, top - 0.5, bar_w + 1, mh + 1);
    cairo_stroke(cr);
    cairo_set_font_size(cr, 12);
    for (double t = ceil(lo / step - 1e-9) * step; t <= hi + 1e-9 * step; t += step) {
        double y = top + mh * (hi - t) / (hi - lo);
        cairo_move_to(cr, x0 + bar_w, y);
        cairo_line_to(cr, x0 + bar_w + 5, y);
        cairo_stroke(cr);
        char tl[32];
        format_tick(tl, sizeof tl, t, step);
        text_at(cr, x0 + bar_w + 8, y, tl, 0, 0.5);
    }
    /* the quantity and unit, rotated along the bar */
    cairo_save(cr);
    cairo_set_font_size(cr, 13);
    cairo_translate(cr, x0 + bar_w + 8 + tick_w + 5 + 12 + 9, top + mh / 2);
    cairo_rotate(cr, -M_PI / 2);
    text_at(cr, 0, 0, bar_label, 0.5, 0.5);
    cairo_restore(cr);
}

svp_status svp_figure_map(const char *path, const svp_image *img, double display_scale, double lo,
                          double hi, int diverging, const char *title, const char *bar_label,
                          double pixel_um, int overwrite)
{
    const int w = img->width, h = img->height;
    if (!(hi > lo)) {
        lo = diverging ? -1 : 0;
        hi = 1;
    }
    cairo_surface_t *map = NULL;
    SVP_CHECK(map_surface(path, img, display_scale, lo, hi, diverging, &map));

    /* layout: the map scaled to 560 px on its long side */
    const double zoom = 560.0 / (w > h ? w : h);
    const double mw = w * zoom, mh = h * zoom;
    const double left = 20, top = 48, bar_gap = 16, bar_w = 18, bottom = 20;
    /* room for the tick labels and the rotated quantity label */
    const double bar_step = tick_step(lo, hi, 6), tick_w = tick_label_width(lo, hi, bar_step);
    const double right = 8 + 5 + tick_w + 12 + 18 + 10;
    const int fw = (int)ceil(left + mw + bar_gap + bar_w + right);
    const int fh = (int)ceil(top + mh + bottom);
    cairo_surface_t *fig = cairo_image_surface_create(CAIRO_FORMAT_RGB24, fw, fh);
    cairo_t *cr = cairo_create(fig);
    cairo_set_source_rgb(cr, 1, 1, 1);
    cairo_paint(cr);
    cairo_select_font_face(cr, FONT, CAIRO_FONT_SLANT_NORMAL, CAIRO_FONT_WEIGHT_NORMAL);

    /* the map */
    cairo_save(cr);
    cairo_translate(cr, left, top);
    cairo_scale(cr, zoom, zoom);
    cairo_set_source_surface(cr, map, 0, 0);
    cairo_pattern_set_filter(cairo_get_source(cr),
                             zoom >= 1 ? CAIRO_FILTER_NEAREST : CAIRO_FILTER_GOOD);
    cairo_rectangle(cr, 0, 0, w, h);
    cairo_fill(cr);
    cairo_restore(cr);
    cairo_surface_destroy(map);
    cairo_set_source_rgb(cr, 0, 0, 0);
    cairo_set_line_width(cr, 1);
    cairo_rectangle(cr, left - 0.5, top - 0.5, mw + 1, mh + 1);
    cairo_stroke(cr);

    /* title */
    cairo_set_font_size(cr, 16);
    text_at(cr, left, 24, title, 0, 0.5);

    draw_scale_bar(cr, w, pixel_um, zoom, left, top, mh);
    draw_colour_bar(cr, left + mw + bar_gap, top, mh, bar_w, lo, hi, diverging, bar_step, tick_w,
                    bar_label);
    return finish_png(fig, cr, path, overwrite);
}

/* ---- plots ------------------------------------------------------------------------------ */

static const double palette[][3] = {{0, 0, 0},          {0.84, 0.15, 0.16}, {0.12, 0.47, 0.71},
                                    {0.17, 0.63, 0.17}, {0.58, 0.40, 0.74}, {1.0, 0.50, 0.05},
                                    {0.55, 0.34, 0.29}, {0.89, 0.47, 0.76}, {0.5, 0.5, 0.5},
                                    {0.74, 0.74, 0.13}};

void svp_figure_palette(int k, double rgb[3])
{
    if (k < 0 || k >= SVP_FIGURE_PALETTE) k = 0;
    memcpy(rgb, palette[k], sizeof palette[k]);
}

/* A plot's area in the figure (left l, top t, size pw × ph) and its data ranges. */
typedef struct plot_frame {
    double l, t, pw, ph;
    double x0, x1, y0, y1;
} plot_frame;

static double plot_px(const plot_frame *f, double v) { return f->l + f->pw * (v - f->x0) / (f->x1 - f->x0); }
static double plot_py(const plot_frame *f, double v) { return f->t + f->ph * (f->y1 - v) / (f->y1 - f->y0); }

/* The data ranges of the series, padded and rounded to ys (the y tick step, returned with xs). */
static void plot_ranges(const svp_figure_series *ser, int ns, plot_frame *f, double *xs_out,
                        double *ys_out)
{
    double x0 = INFINITY, x1 = -INFINITY, y0 = INFINITY, y1 = -INFINITY;
    for (int k = 0; k < ns; k++) {
        int nx = ser[k].step ? ser[k].n + 1 : ser[k].n;
        for (int i = 0; i < nx; i++) x0 = fmin(x0, ser[k].x[i]), x1 = fmax(x1, ser[k].x[i]);
        for (int i = 0; i < ser[k].n; i++)
            if (isfinite(ser[k].y[i])) y0 = fmin(y0, ser[k].y[i]), y1 = fmax(y1, ser[k].y[i]);
    }
    if (!(x1 > x0)) x0 -= 1, x1 += 1;
    if (!(y1 >= y0)) y0 = 0, y1 = 1;
    if (!(y1 > y0)) {
        double d = fabs(y0) > 0 ? 0.1 * fabs(y0) : 1;
        y0 -= d, y1 += d;
    }
    double pad = 0.05 * (y1 - y0);
    y1 += pad;
    if (y0 < 0 || y0 - pad > 0) y0 -= pad;
    double ys = tick_step(y0, y1, 7), xs = tick_step(x0, x1, 9);
    y0 = floor(y0 / ys + 1e-9) * ys;
    y1 = ceil(y1 / ys - 1e-9) * ys;
    f->x0 = x0, f->x1 = x1, f->y0 = y0, f->y1 = y1;
    *xs_out = xs;
    *ys_out = ys;
}

/* Grid lines, ticks and their labels every xs and ys, and the zero line. */
static void plot_grid(cairo_t *cr, const plot_frame *f, double xs, double ys)
{
    const double l = f->l, t = f->t, pw = f->pw, ph = f->ph;
    cairo_set_font_size(cr, 12);
    cairo_set_line_width(cr, 1);
    for (double v = ceil(f->x0 / xs - 1e-9) * xs; v <= f->x1 + 1e-9 * xs; v += xs) {
        cairo_set_source_rgb(cr, 0.9, 0.9, 0.9);
        cairo_move_to(cr, plot_px(f, v), t);
        cairo_line_to(cr, plot_px(f, v), t + ph);
        cairo_stroke(cr);
        cairo_set_source_rgb(cr, 0, 0, 0);
        cairo_move_to(cr, plot_px(f, v), t + ph);
        cairo_line_to(cr, plot_px(f, v), t + ph + 5);
        cairo_stroke(cr);
        char tl[32];
        format_tick(tl, sizeof tl, v, xs);
        text_at(cr, plot_px(f, v), t + ph + 9, tl, 0.5, 0);
    }
    for (double v = f->y0; v <= f->y1 + 1e-9 * ys; v += ys) {
        cairo_set_source_rgb(cr, 0.9, 0.9, 0.9);
        cairo_move_to(cr, l, plot_py(f, v));
        cairo_line_to(cr, l + pw, plot_py(f, v));
        cairo_stroke(cr);
        cairo_set_source_rgb(cr, 0, 0, 0);
        cairo_move_to(cr, l - 5, plot_py(f, v));
        cairo_line_to(cr, l, plot_py(f, v));
        cairo_stroke(cr);
        char tl[32];
        format_tick(tl, sizeof tl, v, ys);
        text_at(cr, l - 8, plot_py(f, v), tl, 1, 0.5);
    }
    if (f->y0 < 0 && f->y1 > 0) { /* the zero line */
        cairo_set_source_rgb(cr, 0.6, 0.6, 0.6);
        cairo_move_to(cr, l, plot_py(f, 0));
        cairo_line_to(cr, l + pw, plot_py(f, 0));
        cairo_stroke(cr);
    }
}

/* The series (dots, lines or steps; NaN breaks a line), clipped to the plot area. */
static void plot_draw_series(cairo_t *cr, const plot_frame *f, const svp_figure_series *ser, int ns)
{
    cairo_save(cr);
    cairo_rectangle(cr, f->l, f->t, f->pw, f->ph);
    cairo_clip(cr);
    cairo_set_line_join(cr, CAIRO_LINE_JOIN_ROUND);
    for (int k = 0; k < ns; k++) {
        const svp_figure_series *s = &ser[k];
        cairo_set_source_rgb(cr, s->rgb[0], s->rgb[1], s->rgb[2]);
        cairo_set_line_width(cr, s->width > 0 ? s->width : 1.6);
        if (s->markers) {
            for (int i = 0; i < s->n; i++) {
                if (!isfinite(s->y[i])) continue;
                cairo_new_sub_path(cr);
                cairo_arc(cr, plot_px(f, s->x[i]), plot_py(f, s->y[i]), 2.8, 0, 2 * M_PI);
            }
            cairo_fill(cr);
            continue;
        }
        int pen = 0;
        for (int i = 0; i < s->n; i++) {
            if (!isfinite(s->y[i])) {
                pen = 0;
                continue;
            }
            if (!pen)
                cairo_move_to(cr, plot_px(f, s->x[i]), plot_py(f, s->y[i]));
            else
                cairo_line_to(cr, plot_px(f, s->x[i]), plot_py(f, s->y[i]));
            if (s->step) cairo_line_to(cr, plot_px(f, s->x[i + 1]), plot_py(f, s->y[i]));
            pen = 1;
        }
        cairo_stroke(cr);
    }
    cairo_restore(cr);
}

/* The legend, top right inside the plot. */
static void plot_legend(cairo_t *cr, const plot_frame *f, const svp_figure_series *ser, int ns)
{
    cairo_set_font_size(cr, 12);
    double lw = 0;
    for (int k = 0; k < ns; k++) {
        cairo_text_extents_t e;
        cairo_text_extents(cr, ser[k].label, &e);
        lw = fmax(lw, e.x_advance);
    }
    double lx = f->l + f->pw - lw - 46, ly = f->t + 8;
    cairo_set_source_rgba(cr, 1, 1, 1, 0.85);
    cairo_rectangle(cr, lx - 6, ly - 4, lw + 46, 18.0 * ns + 6);
    cairo_fill(cr);
    for (int k = 0; k < ns; k++) {
        double yy = ly + 18.0 * k + 7;
        cairo_set_source_rgb(cr, ser[k].rgb[0], ser[k].rgb[1], ser[k].rgb[2]);
        if (ser[k].markers) {
            cairo_arc(cr, lx + 14, yy, 2.8, 0, 2 * M_PI);
            cairo_fill(cr);
        } else {
            cairo_set_line_width(cr, 2);
            cairo_move_to(cr, lx, yy);
            cairo_line_to(cr, lx + 28, yy);
            cairo_stroke(cr);
        }
        cairo_set_source_rgb(cr, 0, 0, 0);
        text_at(cr, lx + 34, yy, ser[k].label, 0, 0.5);
    }
}

svp_status svp_figure_plot(const char *path, const char *title, const char *xlabel,
                           const char *ylabel, const svp_figure_series *ser, int ns, int overwrite)
{
    const int fw = 780, fh = 500;
    plot_frame f;
    f.l = 86, f.t = 46;
    f.pw = fw - f.l - 24, f.ph = fh - f.t - 62; /* right margin 24, bottom 62 */
    double xs, ys;
    plot_ranges(ser, ns, &f, &xs, &ys);
    cairo_surface_t *fig = cairo_image_surface_create(CAIRO_FORMAT_RGB24, fw, fh);
    cairo_t *cr = cairo_create(fig);
    cairo_set_source_rgb(cr, 1, 1, 1);
    cairo_paint(cr);
    cairo_select_font_face(cr, FONT, CAIRO_FONT_SLANT_NORMAL, CAIRO_FONT_WEIGHT_NORMAL);
    plot_grid(cr, &f, xs, ys);
    plot_draw_series(cr, &f, ser, ns);
    /* frame, labels, title */
    cairo_set_source_rgb(cr, 0, 0, 0);
    cairo_set_line_width(cr, 1);
    cairo_rectangle(cr, f.l, f.t, f.pw, f.ph);
    cairo_stroke(cr);
    cairo_set_font_size(cr, 14);
    text_at(cr, f.l + f.pw / 2, fh - 14, xlabel, 0.5, 1);
    cairo_save(cr);
    cairo_translate(cr, 18, f.t + f.ph / 2);
    cairo_rotate(cr, -M_PI / 2);
    text_at(cr, 0, 0, ylabel, 0.5, 0.5);
    cairo_restore(cr);
    cairo_set_font_size(cr, 15);
    text_at(cr, f.l, 24, title, 0, 0.5);
    plot_legend(cr, &f, ser, ns);
    return finish_png(fig, cr, path, overwrite);
}

/* svp_figure_plot over plain arrays, series k in palette colour k. */
svp_status svp_figure_line_plot(const char *path, const char *title, const char *xlabel,
                                const char *ylabel, int n_series, const double *const *x,
                                const double *const *y, const int *n, const char *const *labels,
                                const int *markers, int overwrite)
{
    svp_figure_series ser[10];
    if (n_series < 1 || n_series > 10) return svp_fail(SVP_ERR_INVALID, "%s: 1 to 10 series", path);
    for (int k = 0; k < n_series; k++) {
        memset(&ser[k], 0, sizeof ser[k]);
        ser[k].x = x[k];
        ser[k].y = y[k];
        ser[k].n = n[k];
        ser[k].label = labels[k];
        ser[k].markers = markers ? markers[k] : 0;
        memcpy(ser[k].rgb, palette[k], sizeof ser[k].rgb);
    }
    return svp_figure_plot(path, title, xlabel, ylabel, ser, n_series, overwrite);
}

/* ---- process-wide state ---------------------------------------------------------------- */

void svp_figure_cleanup(void)
{
    /* cairo keeps font caches (through fontconfig) for the life of the process; tools and
     * tests release them at exit so leak checkers see a clean slate. No cairo object may be
     * alive at this point. */
    cairo_debug_reset_static_data();
    FcFini();
}
