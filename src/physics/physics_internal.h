/* Shared by the physics module: the padded Fourier canvas of the Fourier-method fields. */
#ifndef SVP_PHYSICS_INTERNAL_H
#define SVP_PHYSICS_INTERNAL_H

#include "../core/internal.h"

#define SVP_MU0 1.25663706212e-6 /* vacuum permeability, T m / A (CODATA 2018) */

/* How the image is continued into the padding (see svp_pad_mode; ZERO for sources, whose
 * magnetisation is zero outside the image). */
typedef enum svp_canvas_fill { SVP_FILL_ZERO, SVP_FILL_MEAN, SVP_FILL_TAPER } svp_canvas_fill;

/* An image of w x h pixels placed at the origin of an ny x nx periodic canvas; spec holds its
 * spectrum (r2c, ny x ncx), work receives one output spectrum at a time. */
typedef struct svp_canvas {
    int w, h;
    int nx, ny, ncx;
    double dkx, dky; /* rad/m per frequency index */
    const svp_fft_plan *plan;
    double *real;
    fftw_complex *spec;
    fftw_complex *work;
} svp_canvas;

/* pad_factor 1: no padding (periodic at the image size); >= 2: the smallest 2,3,5,7-smooth
 * size >= pad_factor times the image per axis. */
svp_status svp_canvas_init(svp_canvas *c, int w, int h, int pad_factor, double pixel_m);
void svp_canvas_release(svp_canvas *c);
/* Fills the canvas from the image and transforms it into c->spec. */
svp_status svp_canvas_load(svp_canvas *c, const svp_image *image, svp_canvas_fill fill);
/* Inverse transform of c->work (destroyed) cropped to out (w x h). */
void svp_canvas_emit(svp_canvas *c, svp_image *out);

/* Signed wavenumbers (rad/m) of spectrum column i and row j; *odd_ok is 0 at the Nyquist
 * frequency of an even axis, where odd (derivative-like) multipliers must vanish. */
static inline double svp_canvas_kx(const svp_canvas *c, int i, int *odd_ok)
{
    *odd_ok = !(c->nx % 2 == 0 && i == c->nx / 2);
    return i * c->dkx;
}
static inline double svp_canvas_ky(const svp_canvas *c, int j, int *odd_ok)
{
    *odd_ok = !(c->ny % 2 == 0 && j == c->ny / 2);
    return (j <= (c->ny - 1) / 2 ? j : j - c->ny) * c->dky;
}

/* e^(−kh) averaged over an NV layer of thickness t_nv centred at h (h > t_nv / 2):
 * e^(−kh) sinh(a)/a, a = k t_nv / 2, without overflow. */
double svp_layer_decay(double k, double h, double t_nv);

#endif
