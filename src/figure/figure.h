/* Figures: PNG maps with a colour bar and a scale bar, and line / step plots, drawn with cairo
 * (colour maps from src/io/image_io.cpp). Library-internal, above io and below scenes: scenes
 * (their figure stage), the svpsf commands and the benchmarks draw through it.
 *
 * Every figure is written atomically (svp_io_atomic_write_bytes: never over an existing file
 * unless overwrite); every function returns svp_status with a message naming the file. */
#ifndef SVP_FIGURE_H
#define SVP_FIGURE_H

#include "svpsf.h"

/* One map as a PNG figure: the colour map over [lo, hi] (display units = value × display_scale;
 * diverging: blue–white–red, else viridis), a colour bar with ticks and `bar_label`, a scale bar
 * (pixel_um per pixel) and a title. An empty range (!(hi > lo)) draws over [0, 1] ([-1, 1]
 * diverging). */
svp_status svp_figure_map(const char *path, const svp_image *img, double display_scale, double lo,
                          double hi, int diverging, const char *title, const char *bar_label,
                          double pixel_um, int overwrite);

/* One curve of a plot. */
typedef struct svp_figure_series {
    const double *x, *y; /* y[0..n-1]; x[0..n-1], or the n + 1 bin edges of a step series */
    int n;
    const char *label; /* its legend entry */
    double rgb[3];     /* colour, 0..1 */
    int step;          /* 1: a histogram-like step curve over the edges x */
    double width;      /* line width in pixels; 0: 1.6 */
    int markers;       /* 1: the points as dots (measured data), not joined by a line */
} svp_figure_series;

/* The plot palette: colour k (0..SVP_FIGURE_PALETTE-1: black, red, blue, green, ...). */
#define SVP_FIGURE_PALETTE 10
void svp_figure_palette(int k, double rgb[3]);

/* A plot (PNG, 780 x 500): the series (NaN in y breaks a line) over axes with ticks and grid
 * lines, labelled axes, a title and a legend at the top right. */
svp_status svp_figure_plot(const char *path, const char *title, const char *xlabel,
                           const char *ylabel, const svp_figure_series *series, int n_series,
                           int overwrite);

/* svp_figure_plot over plain arrays: n_series (1..10) curves x[k][0..n[k]-1], y[k][...] in
 * palette colours 0, 1, ...; series k as dots when markers && markers[k], else as a line. */
svp_status svp_figure_line_plot(const char *path, const char *title, const char *xlabel,
                                const char *ylabel, int n_series, const double *const *x,
                                const double *const *y, const int *n, const char *const *labels,
                                const int *markers, int overwrite);

/* Releases cairo's process-wide font caches: call at exit from tools and tests (after every
 * figure is written), never while another thread draws. */
void svp_figure_cleanup(void);

#endif
