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
    /* zero mode: 0, or the margin of svp_blur_set_view (the frame is exact for data on the
     * view `margin` pixels in from every side only) */
    int margin;
    int *src_x, *src_y;
    const svp_fft_plan *plan;
    fftw_complex *otf; /* ny x ncx, NULL until a kernel is set or when otf_re holds it */
    /* The OTF of a point-symmetric kernel is real: svp_frame_keep_real keeps only its real
     * part here (ny x ncx; otf NULL), which halves what a spectral product reads. */
    double *otf_re;
} svp_frame;

/* A kernel's reach along an axis: the largest offset from its centre. */
static inline int svp_kernel_reach(int size, int centre)
{
    return size - 1 - centre > centre ? size - 1 - centre : centre;
}

/* The frame size svp_frame_init would choose, without planning or tables. */
svp_status svp_frame_size(int width, int height, int rx, int ry, svp_boundary boundary, int *nx,
                          int *ny);
/* The same for a zero-boundary operator whose data lie on the view `margin` pixels in from each
 * side (svp_blur_set_view's frame; margin 0: svp_frame_size's). */
svp_status svp_frame_size_view(int width, int height, int rx, int ry, int margin, int *nx,
                               int *ny);
/* Frame geometry for an image of width x height, kernel radii rx, ry (offsets that reach). */
svp_status svp_frame_init(svp_frame *f, int width, int height, int rx, int ry,
                          svp_boundary boundary);
/* OTF of a kernel centred at (cx, cy): every offset is placed modulo the frame (aliasing adds,
 * which is exact for periodic and full-period mirror frames). In zero mode offsets beyond the
 * image size never connect two pixels and are dropped. */
svp_status svp_frame_set_kernel(svp_frame *f, const svp_image *kernel, int cx, int cy,
                                svp_boundary boundary);
/* When every |Im otf| is at most 1e-12 max |otf| — a kernel point-symmetric about its centre
 * up to round-off, whose imaginary parts are only the FFT's round-off — replaces otf by its
 * real part in otf_re (the operator then uses the kernel's point-symmetric part, which differs
 * from the kernel by that round-off). Returns 1 when it did, 0 when the OTF stays complex. */
int svp_frame_keep_real(svp_frame *f);
/* The OTF at spectral index k, whichever form the frame holds. */
static inline double complex svp_frame_otf(const svp_frame *f, size_t k)
{
    return f->otf_re ? f->otf_re[k] : f->otf[k];
}
/* max |Im z| <= 1e-12 max |z| over n values (a real spectrum up to round-off). */
int svp_spectrum_is_real(const fftw_complex *z, size_t n);
/* A new svp_alloc'd array of the n real parts of z; NULL when out of memory. */
double *svp_spectrum_real_part(const fftw_complex *z, size_t n);
/* s *= scale · o on n interleaved complex values, o real, in place. */
void svp_spectrum_scale(const double *restrict o, double *restrict s, size_t n, double scale);
void svp_spectrum_scale_f(const float *restrict o, float *restrict s, size_t n);
void svp_frame_release(svp_frame *f);
size_t svp_frame_memory(const svp_frame *f);

/* E: image → frame (frame must hold ny * nx); C: frame → image. */
void svp_frame_extend(const svp_frame *f, const double *restrict image, double *restrict frame);
void svp_frame_crop(const svp_frame *f, const double *restrict frame, double *restrict image);
/* Cᵀ: image → frame (zeros elsewhere); Eᵀ: frame → image (sums every copy of a pixel). */
void svp_frame_embed(const svp_frame *f, const double *restrict image, double *restrict frame);
void svp_frame_fold(const svp_frame *f, const double *restrict frame, double *restrict image);
/* The same four between a double image and a float frame (the single-precision transforms). */
void svp_frame_extend_f(const svp_frame *f, const double *restrict image, float *restrict frame);
void svp_frame_crop_f(const svp_frame *f, const float *restrict frame, double *restrict image);
void svp_frame_embed_f(const svp_frame *f, const double *restrict image, float *restrict frame);
void svp_frame_fold_f(const svp_frame *f, const float *restrict frame, double *restrict image);
/* Zero mode's load (E = Cᵀ there): frame rows 0 .. height − 1 = the image rows zero-padded to
 * nx, rows height .. rows − 1 zero, rows beyond `rows` untouched. */
void svp_frame_zero_load(const svp_frame *f, int rows, const double *restrict image,
                         double *restrict frame);
void svp_frame_zero_load_f(const svp_frame *f, int rows, const double *restrict image,
                           float *restrict frame);
/* s *= scale · otf (conjugate: scale · conj(otf)) on n interleaved complex values, in place. */
void svp_spectrum_product(const double *restrict otf, double *restrict s, size_t n, int conjugate,
                          double scale);
void svp_spectrum_product_f(const float *restrict otf, float *restrict s, size_t n, int conjugate,
                            float scale);
/* frame = C K E of what the frame holds, in place, without the load and crop: the forward
 * transform (pruned to the image's rows when `pruned` is given), the product with the OTF / (nx ny)
 * (adjoint: its conjugate), the inverse (pruned alike); spectrum is the work spectrum. */
void svp_frame_filter(const svp_frame *f, const svp_fft_pruned *pruned, double *frame,
                      fftw_complex *spectrum, int adjoint);
/* spectrum *= otf (conj != 0: *= conj(otf)), scaled by `scale`. */
void svp_frame_multiply(const svp_frame *f, fftw_complex *restrict spectrum, int conjugate,
                        double scale);

typedef enum svp_blur_kind {
    SVP_BLUR_INVARIANT = 0,
    SVP_BLUR_TENT = 1,    /* space-variant: tent-weighted overlap-add (variant.c) */
    SVP_BLUR_LOWRANK = 2, /* space-variant: eigen-PSFs and coefficient maps (variant.c); also
                             the region representation (regions.c) */
    SVP_BLUR_EXACT = 3    /* space-variant: the per-source reference sum (exact.c) */
} svp_blur_kind;

/* One operator interface: every representation fills a table of its application, adjoint,
 * memory and release; svp_blur_apply / _adjoint / _memory / _free (operator.c) check the
 * arguments and call through it. The tables: svp_invariant_ops (operator.c), svp_tent_ops and
 * svp_lowrank_ops (variant.c), svp_exact_ops (exact.c). Image sizes are checked by the
 * caller. memory counts what the representation holds besides the svp_blur's common part
 * (counted by svp_blur_memory); release frees it. */
typedef struct svp_blur_ops {
    const char *name;
    svp_status (*apply)(svp_blur *b, const double *restrict x, double *restrict y);
    svp_status (*adjoint)(svp_blur *b, const double *restrict y, double *restrict x);
    size_t (*memory)(const svp_blur *b);
    void (*release)(svp_blur *b);
    const double *(*halo_map)(const svp_blur *b); /* per-pixel halo (svp_blur_halo_map) */
} svp_blur_ops;
extern const svp_blur_ops svp_invariant_ops, svp_tent_ops, svp_lowrank_ops, svp_exact_ops;
/* The region representation (kind SVP_BLUR_LOWRANK: the low-rank apply and adjoint with one
 * term per used label and per-pixel coefficient maps; variant.c, regions.c). */
extern const svp_blur_ops svp_regions_ops;
/* The common part only (what svp_variant_begin made), until a constructor sets its table. */
extern const svp_blur_ops svp_variant_common_ops;

/* A cache that a higher layer keeps with an operator (the solvers' workspace, restore/): the
 * operator frees and counts it through the functions stored with it and never names them. */
typedef struct svp_blur_cache {
    void *data;
    void (*release)(void *data);
    size_t (*memory)(const void *data);
} svp_blur_cache;

/* The PSF's far tail on a coarse grid (tail.c, docs/model.md §5 "The tail on a coarse grid"):
 * the kernel's core k (1 − w) (w a smooth step from r0 to 2 r0) convolved on a frame sized for
 * radius 2 r0, its tail k w as P K_c Pᵀ on nodes every s pixels (Pᵀ: bilinear gather, K_c the
 * tail sampled every s pixels, P: bilinear spread). */
typedef struct svp_tail svp_tail;
/* The estimated ‖tail − P K_c Pᵀ‖₁ / ‖k‖₁ (an ℓ1 operator-norm bound per unit of the kernel's
 * flux) for a kernel centred at (cx, cy) on a width x height zero-boundary grid whose data lie
 * `margin` pixels in from each side (0: the whole grid): the bilinear interpolation bound
 * (s² / 4) Σ (|Δxx| + |Δyy|) of the tail over the offsets the operator uses, with a kernel that
 * stops inside them counted with its edge. */
double svp_tail_estimate(const svp_image *k, int cx, int cy, int width, int height, int margin,
                         int s, int r0);
/* The cheapest (s, r0) whose estimate is at most tol and whose core frame, node frame and
 * passes cost less than 0.8 of the plain frame pnx x pny: *s 0 when none does. */
svp_status svp_tail_choose(const svp_image *k, int cx, int cy, int width, int height, int margin,
                           double tol, int pnx, int pny, int *s, int *r0, double *error);
/* The core kernel k (1 − w), radius 2 r0 (less where the kernel is smaller), centre (*ocx, *ocy). */
svp_status svp_tail_core(const svp_image *k, int cx, int cy, int r0, svp_image **out, int *ocx,
                         int *ocy);
/* The tail for (s, r0) (svp_tail_choose's), `error` its estimate (kept for svp_tail_error). */
svp_status svp_tail_new(const svp_image *k, int cx, int cy, int width, int height, int margin,
                        int s, int r0, double error, svp_tail **out);
/* The splits r0 svp_tail_choose tries (svp_tail_n_splits of them, ascending), and per split the
 * kernel's Σ |Δxx| + |Δyy| of its tail over the used offsets per unit of its ℓ1 norm (HUGE_VAL
 * for a split it cannot hold): the estimate for spacing s is 0.25 s² times it. */
int svp_tail_n_splits(void);
svp_status svp_tail_split_sums(const svp_image *k, int cx, int cy, int width, int height,
                               int margin, double *sums);
/* The cheapest (s, r0) whose estimate 0.25 s² sums[r0's index] is within tol, when cheaper than
 * 0.8 of the plain frame pnx x pny (k: the kernel whose reach sizes the nodes); *s 0: none. */
svp_status svp_tail_pick(const svp_image *k, int cx, int cy, int width, int height, int margin,
                         const double *sums, double tol, int pnx, int pny, int *s_out, int *r0_out,
                         double *error);
/* A copy with its own buffers and plans (another thread's), the same operator. */
svp_status svp_tail_copy(const svp_tail *t, svp_tail **out);
void svp_tail_free(svp_tail *t);
size_t svp_tail_memory(const svp_tail *t);
int svp_tail_step(const svp_tail *t);
int svp_tail_split(const svp_tail *t);
double svp_tail_error(const svp_tail *t);
/* The tail's part of H (adjoint 0) or Hᵀ (1): gather reads the width x height input (rows
 * `stride` values apart) and convolves the nodes; spread then adds the result to the output
 * (rows `stride` apart). In double or from / into float frames. */
void svp_tail_gather(svp_tail *t, const double *in, size_t stride, int adjoint);
void svp_tail_gather_f(svp_tail *t, const float *in, size_t stride, int adjoint);
void svp_tail_spread(svp_tail *t, double *out, size_t stride);
void svp_tail_spread_f(svp_tail *t, float *out, size_t stride);

typedef struct svp_variant_data svp_variant_data; /* variant.c */
typedef struct svp_exact_data svp_exact_data;     /* exact.c */

struct svp_blur {
    const svp_blur_ops *ops;
    svp_blur_kind kind;
    int width, height;
    svp_boundary boundary;
    double halo;          /* alpha_b */
    svp_image *kernel;    /* the normalised core kernel (kept for solvers that need another
                             frame, e.g. Wiener in a mirror frame) */
    int kcx, kcy;         /* its centre */
    int kernel_borrowed;  /* kernel is another operator's (svp_blur_clone) */
    int has_model;
    svp_psf psf;          /* when built from a model */
    /* Invariant operators make their frame (plans, OTF, work buffers) on first use
     * (svp_blur_ready): the full grid's, or with view_margin > 0 the view's (svp_blur_set_view);
     * frame.plan is NULL until then. frames_built counts the frames made (tests). */
    svp_frame frame;
    int view_margin;
    int frames_built;
    double *work_r;       /* ny * nx */
    fftw_complex *work_c; /* ny * ncx */
    /* Invariant zero-boundary operators whose frame has more rows than the image: transforms
     * pruned to the image's rows (NULL otherwise: full transforms of frame.plan). */
    const svp_fft_pruned *pruned;
    /* Space-variant kinds only (NULL otherwise). For them kernel / psf / halo / has_model
     * describe the PSF at the image centre (for solvers that need one invariant stand-in,
     * e.g. the CG preconditioner), and frame holds the shared geometry without an OTF. */
    svp_psf_field *field;
    svp_variant_info info; /* space-variant kinds: what was built and why */
    svp_variant_data *variant;
    svp_exact_data *exact;
    double *work_r_image; /* width x height work image */
    /* the solvers' workspace (restore/: Wiener filters, gains, frames; CG counts) */
    svp_blur_cache restore;
    /* Single precision (svp_blur_set_single; tent and low rank: svp_variant_set_single): H and Hᵀ transform
     * in float on the same frame (row-pruned like `pruned` in zero mode); the buffers and the
     * OTF / (nx ny) in float are made on first use and kept: otf_f holds ny x ncx complex
     * values interleaved, or when otf_f_real (the frame's OTF is real, otf_re) their real parts
     * only, which halves what the spectral product reads. */
    int single;
    const svp_fftf_rows *rows_f;
    float *work_rf;
    fftwf_complex *work_cf;
    float *otf_f;
    int otf_f_real;
    /* The tail on a coarse grid (svp_blur_set_tail): tail_tol > 0 lets an invariant
     * zero-boundary operator's frame (svp_blur_ready) be the core's, with `tail` for the rest,
     * when svp_tail_choose finds it cheaper; core is then the core kernel (centre core_cx,
     * core_cy). Made and freed with the frame. */
    double tail_tol;
    svp_tail *tail;
    /* svp_tail_choose's answer for tail_tol and the view margin tail_for − 1 (0: none yet), kept
     * so that copies (svp_blur_clone) and later frames do not choose again */
    int tail_for, tail_s, tail_r0;
    double tail_err;
    svp_image *core;
    int core_cx, core_cy;
    /* 1 while the work frame holds the output of the last svp_blur_rows (rows 0 .. height − 1,
     * in the precision then in use); any other use of the frame clears it */
    int rows_held;
};

/* Invariant operators: makes the frame in use (the full grid's, or the view's after
 * svp_blur_set_view) with its OTF, plans, work buffers and, when single precision is on, the
 * float state, if not made yet; other kinds are always ready. Every user of b->frame,
 * b->work_r / work_c or svp_blur_spectrum_in / _out on an invariant operator calls it first. */
svp_status svp_blur_ready(svp_blur *b);

/* A copy of b that can be applied at the same time as b from another thread (T⁻¹'s runs side by
 * side): what the build made (kernel; a PSF map's term spectra, weight tables and maps) is b's,
 * read only, so b must outlive the copy; the copy has its own frame and buffers. Invariant
 * operators (svp_blur_clone_invariant: its view, precision and halo; the frame made on first
 * use) and tent, low-rank and region operators in double precision (svp_variant_clone: the
 * frame's plans for the calling thread's plan thread count, svp_fft_local_threads).
 * SVP_ERR_UNSUPPORTED for the others: svp_blur_clonable says which. */
svp_status svp_blur_clone(const svp_blur *b, svp_blur **out);
int svp_blur_clonable(const svp_blur *b);
svp_status svp_blur_clone_invariant(const svp_blur *b, svp_blur **out);
svp_status svp_variant_clone(const svp_blur *b, svp_blur **out);
/* A space-variant operator's far tail on a coarse grid (svp_variant_options.tail_tol): node
 * spacing, split radius and estimated error; 0 when it has none. */
svp_status svp_variant_tail_info(const svp_blur *b, int *step, int *split, double *error);
/* The copies' common part: a zeroed operator with b's kind, operations, size, boundary, halo,
 * PSF and kernel (b's, borrowed); NULL when out of memory. */
svp_blur *svp_blur_copy_header(const svp_blur *b);

/* Invariant operators: b->work_c = the spectrum of an image placed in b->frame, by E
 * (adjoint_side 0) or Cᵀ (1) — the same plain copy with zero padding in zero mode — with the
 * pruned transform when b->pruned is set; and back: image = C (0) or Eᵀ (1) of the inverse
 * transform of b->work_c (destroyed), unscaled. H x = C K E x is spectrum_in(x, 0), multiply by
 * the OTF / (nx ny), spectrum_out(.., 0) (plus the halo). */
void svp_blur_spectrum_in(svp_blur *b, const double *restrict image, int adjoint_side);
/* Single-precision H and Hᵀ for invariant operators: on (1) makes the float plans, buffers and
 * OTF if needed; off (0) returns to double (buffers kept). Space-variant operators: see
 * svp_variant_set_single. Results agree with double to about 1e-6 of the largest value. */
svp_status svp_blur_set_single(svp_blur *b, int on);
/* The same for tent and low rank (variant.c): float term spectra (made from the double ones on
 * first use and kept; an operator built with svp_variant_options.single_precision holds only
 * the float ones and cannot return to double: SVP_ERR_UNSUPPORTED), float transforms on the
 * same frames. SVP_ERR_UNSUPPORTED for the exact operator. */
svp_status svp_variant_set_single(svp_blur *b, int on);
/* 1 when the operator can transform in double (everything but a tent / low-rank operator built
 * with svp_variant_options.single_precision, which keeps only float spectra). */
int svp_blur_has_double(const svp_blur *b);
void svp_blur_spectrum_out(svp_blur *b, double *restrict image, int adjoint_side);
/* A row stage of svp_blur_rows: row y (0 .. height − 1) of an image, `width` values. Called
 * in parallel over rows, each row once by one thread; it must not start OpenMP regions. */
typedef void (*svp_blur_row_fn)(void *user, int y, double *restrict row);
/* 1 when svp_blur_rows serves b: an invariant zero-boundary operator without halo. */
int svp_blur_rows_ok(const svp_blur *b);
/* H (adjoint 0) or Hᵀ (1) of an operator svp_blur_rows_ok accepts with its input and output
 * passed a row at a time, so a solver's pointwise work before and after runs in the same pass
 * over the frame as its copy in and out, with no image-sized intermediate: load(user, y, row)
 * writes row y of the input into `row` (with `chained` it arrives holding row y of the last
 * svp_blur_rows' output, which the frame still holds, and is rewritten in place; the frame must
 * not have been used since: SVP_ERR_INTERNAL); store (NULL: none) receives row y of the output
 * for every y with y % store_every == 0. Bit-identical to svp_blur_apply / _adjoint of the
 * images load writes and store takes, in either precision. */
svp_status svp_blur_rows(svp_blur *b, int adjoint, int chained, svp_blur_row_fn load,
                         svp_blur_row_fn store, int store_every, void *user);
/* Invariant zero-boundary operators, for solvers whose data lie on the view `margin` pixels in
 * from every side of the operator's grid (T⁻¹ with a margin, docs/model.md §3): margin > 0 puts
 * the smallest frame that is exact for such data in use — H x exact on the view (not beyond),
 * Hᵀ y exact on the whole grid for y zero outside the view: offsets that join no grid pixel to
 * the view are dropped and only the view is kept free of wrap-around, a frame of
 * good(2 (w − m) − 1) instead of good(2 w − 1) for a whole-grid kernel — and margin 0 returns
 * to the full frame. Only the frame in use is held: the one left is freed, and the one put in
 * use is made on first use (svp_blur_ready), so an operator used only on a view never makes
 * the full frame. The single-precision state follows the frame. *applied:
 * 1 when a view's frame is in use, 0 when none is (margin 0; other kinds or boundaries; a
 * view frame no smaller than the full one). Only H x on the view and Hᵀ of data on the view
 * may be used meanwhile (Richardson–Lucy with the margin missing). */
svp_status svp_blur_set_view(svp_blur *b, int margin, int *applied);

/* The parts of tent / low rank / exact operators that other files of blur/ share. */
/* Tent / low rank: 1 when the term spectra are stored real (every term's kernel point-symmetric
 * and no row-pruning phase), 0 when complex. */
int svp_variant_real_spectra(const svp_blur *b);
/* The common part of the space-variant kinds (variant.c): its memory, and its release (the
 * field's copy and the work image). */
size_t svp_variant_common_memory(const svp_blur *b);
void svp_variant_common_release(svp_blur *b);
/* Shared set-up of the variant kinds (variant.c): checks, the field's copy, kernel radii
 * (rx, ry) and support as svp_blur_new would choose them, the central PSF as stand-in. */
svp_status svp_variant_begin(const svp_psf_field *field, int width, int height,
                             svp_boundary boundary, double support, svp_blur_kind kind,
                             svp_blur **out, int *rx, int *ry, double *support_used);
/* svp_blur_new_field with the low-rank terms from the dense SVD of the whole sampled-kernel
 * matrix (build 1, LAPACKE_dgesdd; at most 2^27 values) or from its Gram matrix (0, the
 * default build, on the fold the kernels' symmetry allows, variant.c; 2, the same on the
 * point-symmetric half whatever the symmetry). Tests compare them. */
svp_status svp_blur_new_field_build(const svp_psf_field *field, int width, int height,
                                    svp_boundary boundary, const svp_variant_options *options,
                                    int build, svp_blur **out);
/* Term r of a tent / low-rank operator: its spectrum (ny x ncx, scaled by 1 / (nx ny)) in *re
 * when stored real, else in *c, and for low rank its coefficients at the samples; returns the
 * number of terms (0 when r is out of range or the operator is not tent / low rank). */
int svp_variant_term(const svp_blur *b, int r, const double **re, const fftw_complex **c,
                     const double **coef);
/* The chooser's cost model of the representation options force (tent, low rank, regions), in
 * real FFTs of the operator's frame: *build once, *pair per H + Hᵀ pair (half: the low-rank
 * build on the point symmetry only, svp_blur_new_field_build's build 2). */
svp_status svp_variant_cost(const svp_psf_field *field, int width, int height,
                            svp_boundary boundary, const svp_variant_options *options, int half,
                            double *build, double *pair);
/* options->max_memory, or the physical memory when 0. */
double svp_variant_memory_limit(const svp_variant_options *options);
/* Bytes a tent (lowrank 0: K nodes) or low-rank (1: K terms from S samples) operator holds at
 * its peak while built, kernel radii rx, ry, halo map included (an upper estimate). */
size_t svp_variant_peak_bytes(int width, int height, svp_boundary boundary, int lowrank, int K,
                              int S, int rx, int ry);
/* Bytes the Gram low-rank build holds while it runs (besides the operator itself). */
size_t svp_lowrank_build_memory(int samples, int rank, int rx, int ry, int threads);
/* Region maps (regions.c, docs/model.md §9 "Region maps"). The terms of the region
 * representation: K used labels (those with a pixel), label[k] their label, psf[k] their PSF
 * (svp_psf_field_region_psf) and weight + k N their blend weight maps (N = width x height;
 * one-hot for a sharp map), all malloc'd. */
typedef struct svp_region_terms {
    int K;
    int *label;
    svp_psf *psf;
    double *weight;
} svp_region_terms;
/* SVP_ERR_INVALID unless the field is of kind regions. */
svp_status svp_region_check(const svp_psf_field *field);
/* Labels with at least one pixel (0 for other kinds). */
int svp_region_count(const svp_psf_field *field);
svp_status svp_region_terms_make(const svp_psf_field *field, svp_region_terms *t);
void svp_region_terms_free(svp_region_terms *t);
/* Representation choice by error budget (choose.c, docs/model.md §9): *chosen = options with
 * the cheapest tent / low rank / regions whose estimated error is within options->tolerance
 * (else the cheapest near the most accurate), info filled with the estimate. terms (may be
 * NULL): on a region map, the region terms the estimate made (K = 0 when none), the caller's
 * to free or to hand to the build (their weight maps smoothed once). */
svp_status svp_variant_choose(const svp_psf_field *field, int width, int height,
                              svp_boundary boundary, const svp_variant_options *options,
                              svp_variant_options *chosen, svp_variant_info *info,
                              svp_region_terms *terms);
/* Bytes the region operator of K terms holds at its peak while built (an upper estimate, as
 * svp_variant_peak_bytes). */
size_t svp_region_peak_bytes(int width, int height, svp_boundary boundary, int K, int rx, int ry);
/* svp_blur_new_exact with the kernel table forced on (1), off (0) or automatic (-1: on when
 * N · kernel area <= 2^23 values). Tests compare both paths. */
svp_status svp_blur_new_exact_tab(const svp_psf_field *field, int width, int height,
                                  svp_boundary boundary, double support, int tabulate,
                                  svp_blur **out);
/* The operator's per-pixel halo fraction α (width x height, owned by the operator), or NULL
 * when it has none (invariant operators, or no halo anywhere): then b->halo holds it. Space-variant operators with a varying halo
 * have Hᵀ1 = 1 and H applies (1 − α_s) per source: code that inverts the halo term pointwise
 * (e.g. coverage of missing pixels) should use this map, not b->halo. */
const double *svp_blur_halo_map(const svp_blur *b);
/* Per-pixel halo fraction of a field (NULL when zero everywhere). */
svp_status svp_variant_halo_map(const svp_psf_field *field, int width, int height,
                                double **alpha);
/* The halo term of H for a per-pixel halo α (n pixels): out += <α ⊙ in> everywhere (scatter,
 * tmp: n scratch values), and its adjoint out += α <in> (gather). */
void svp_halo_scatter(const double *restrict alpha, size_t n, const double *restrict in,
                      double *restrict out, double *restrict tmp);
void svp_halo_gather(const double *restrict alpha, size_t n, const double *restrict in,
                     double *restrict out);
/* Image size >= 1 x 1 and a known boundary mode (operator.c; every operator constructor). */
svp_status svp_blur_check_geometry(int width, int height, svp_boundary boundary);

#endif
