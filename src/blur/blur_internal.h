/* The blur operator's internals, shared with the solvers (restore/). */
#ifndef SVP_BLUR_INTERNAL_H
#define SVP_BLUR_INTERNAL_H

#include "../core/internal.h"

/* How an image maps into an FFT frame along both axes, plus the kernel's OTF on that frame.
 * Along each axis src[j] is the image index that frame index j holds (-1: zero), and the
 * image's own pixels sit at frame indices off .. off + size - 1.
 *   zero:     src[j] = j for j < size, else -1; off = 0; n = good(size + r)
 *   periodic: src[j] = j; off = 0; n = size
 *   mirror:   either a single reflection of r pixels each side (off = r, n = good(size + 2r))
 *             or the full symmetric period (off = 0, n = 2 size), whichever is cheaper.
 * The operator is H = C K E: E extends (src), K convolves circularly (OTF), C crops (off);
 * its exact adjoint is Eᵀ K* Cᵀ (embed, correlate, fold). */
typedef struct svp_frame {
    int width, height; /* image size */
    int nx, ny, ncx;   /* frame size (real), ncx = nx / 2 + 1 */
    int off_x, off_y;
    int *src_x, *src_y;
    const svp_fft_plan *plan;
    fftw_complex *otf; /* ny x ncx, NULL until a kernel is set */
} svp_frame;

/* Frame geometry for an image of width x height, kernel radii rx, ry (offsets that reach). */
svp_status svp_frame_init(svp_frame *f, int width, int height, int rx, int ry,
                          svp_boundary boundary);
/* OTF of a kernel centred at (cx, cy): every offset is placed modulo the frame (aliasing adds,
 * which is exact for periodic and full-period mirror frames). In zero mode offsets beyond the
 * image size never connect two pixels and are dropped. */
svp_status svp_frame_set_kernel(svp_frame *f, const svp_image *kernel, int cx, int cy,
                                svp_boundary boundary);
void svp_frame_release(svp_frame *f);
size_t svp_frame_memory(const svp_frame *f);

/* E: image → frame (frame must hold ny * nx); C: frame → image. */
void svp_frame_extend(const svp_frame *f, const double *restrict image, double *restrict frame);
void svp_frame_crop(const svp_frame *f, const double *restrict frame, double *restrict image);
/* Cᵀ: image → frame (zeros elsewhere); Eᵀ: frame → image (sums every copy of a pixel). */
void svp_frame_embed(const svp_frame *f, const double *restrict image, double *restrict frame);
void svp_frame_fold(const svp_frame *f, const double *restrict frame, double *restrict image);
/* spectrum *= otf (conj != 0: *= conj(otf)), scaled by `scale`. */
void svp_frame_multiply(const svp_frame *f, fftw_complex *restrict spectrum, int conjugate,
                        double scale);

typedef enum svp_blur_kind { SVP_BLUR_INVARIANT = 0 } svp_blur_kind;

struct svp_blur {
    svp_blur_kind kind;
    int width, height;
    svp_boundary boundary;
    double halo;          /* alpha_b */
    svp_image *kernel;    /* the normalised core kernel (kept for solvers that need another
                             frame, e.g. Wiener in a mirror frame) */
    int kcx, kcy;         /* its centre */
    int has_model;
    svp_psf psf;          /* when built from a model */
    svp_frame frame;
    double *work_r;       /* ny * nx */
    fftw_complex *work_c; /* ny * ncx */
};

#endif
