/* The space-variant blur operator (docs/model.md §9, eq. 12): tent-weighted overlap-add and low rank.
 *
 * Both are H x = Σ_k P_k ⊛ (c_k ⊙ s ⊙ x) + <α x>_FOV with one shared FFT frame:
 *   tent:     P_k the normalised core kernel of the field at node k, c_k the bilinear hat of
 *             node k (c_k >= 0, Σ_k c_k = 1 at every pixel);
 *   low rank: P_k the k-th eigen-PSF of the sampled kernels, c_k its coefficient map
 *             (bilinear between the samples);
 *   s = 1 − α per pixel (the halo keeps (1 − α) of each source's light in the core), divided
 *   by the expansion's flux for a renormalised low-rank operator.
 * The node spectra are accumulated in the Fourier domain: one application is K forward FFTs
 * and one inverse; the adjoint Hᵀ y = Σ_k s c_k ⊙ (P̃_k ⋆ y) + α <y> is one forward and K
 * inverse FFTs. Each term's weighted rows are made a block at a time and transformed along x
 * while in cache (svp_fft_block), the frame's column plans finish the transform; only the
 * image's rows are transformed (a margin row copies its source row's spectrum), and only the
 * image's rows come back. For tent grids whose node windows cover at most 70 % of the frame's
 * rows (about 5 x 5 nodes and finer) the K transforms are row-pruned instead (only the
 * window's rows, see svp_variant_data.pruned). The adjoint uses the same row x column weight
 * tables on the frame: each term's inverse transform is weighted into one frame accumulator
 * block by block, folded back onto the image (Eᵀ) and scaled by s once. Point-symmetric
 * kernels have real spectra, stored as such (svp_variant_data.otf_re). */
#include "blur_internal.h"
#include "../psf/field_internal.h"

#include <lapacke.h>
#include <math.h>
#include <omp.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

struct svp_variant_data {
    int n_terms;        /* K nodes or R eigen-PSFs */
    fftw_complex **otf; /* n_terms spectra (ny x ncx), each scaled by 1 / (nx ny) */
    /* The same, real, when every term's kernel is point-symmetric (its OTF real up to
     * round-off, see svp_frame_keep_real) and the terms are not row-pruned (whose phase makes
     * them complex); otf is NULL then. Halves the spectra's memory and what the products read. */
    double **otf_re;
    fftw_complex *acc; /* ny x ncx accumulator */
    double *scale;     /* s per pixel, NULL = 1 */
    double *alpha;     /* halo fraction per pixel, NULL = no halo anywhere */
    /* node / sample grid: per column x the lower node ix0[x] and the fraction fx[x] towards
     * node ix0[x] + 1 (likewise rows) */
    int gx, gy;
    int *ix0, *iy0;
    double *fx, *fy;
    double *coef; /* low rank: coef[(r gy + j) gx + i], the coefficient of e_r at sample (i, j) */
    /* low rank: the eigenvalues σ² of the (deviations') Gram matrix, descending (n_eig of them),
     * and the sum of the sampled kernels' squared norms, for the error estimate */
    double *eig;
    int n_eig;
    double kernel_norm2;
    /* Row-pruned tent path: node k's weighted input is non-zero only in the frame rows
     * start[k] .. start[k] + rows − 1 (cyclically); its spectrum is that of the same rows moved
     * to the top times e^{−2πi ky start / ny}, a phase folded into otf[k] at build time, so
     * the forward transform needs only `rows` row transforms and the adjoint's inverse only
     * those rows back. pruned 0: the image's rows (term_spectra). */
    int pruned;
    int rows;
    int *start;
    /* Apply: term k's weighted rows are a row weight times a column weight times the rows of
     * E(s ⊙ x) (fill_rows), made a block at a time into a per-thread block as the block is
     * filled (extend_rows; unscaled, only the margins: the image's part is read from x), once
     * per pair of terms. (Making E(s ⊙ x) once per application in a frame buffer instead gave
     * bit-identical results, 0-10 % slower at 256² and 512², the same at 1024².)
     *   tent:     wy[j ny + fy] (hat of node row j at frame row fy) · wx[i nx + q];
     *   low rank: the coefficient rows of term r interpolated along x on the frame columns,
     *             wx[(r gy + j) nx + q], blended between sample rows ly0[fy] and ly0[fy] + 1
     *             with weight lty[fy] (ly0 −1: a zero row).
     * unit[k]: term k's weight is 1 on every frame pixel (tent 1 x 1, the low-rank mean): its
     * rows are E(s ⊙ x)'s.
     * ext (ny x nx): the adjoint's frame accumulator. */
    double *ext;
    double *wx, *wy;
    int *ly0;
    double *lty;
    char *unit;
    char *row_on; /* adjoint: per frame row, ext's row holds a term (see accumulate_rows) */
    /* The fused transforms (term_spectra, the apply's way back, the adjoint): row plans, the
     * frame's column plans, and per-thread row blocks. */
    const svp_fft_block *block;
    const svp_fft_pruned *cols;
    double *blk;
    int blk_threads;
    fftw_complex *spec2; /* ny x ncx: the second spectrum of a pair (K > 1) */
    /* Single precision (svp_variant_set_single): the term spectra in float (otf_f[k]: ny x ncx
     * floats when f_real, else ny x ncx complex floats), made on first use and kept; the float
     * frame rows (rows_max x nx), a term's spectrum and the accumulator; the float plans of
     * the image's rows (h rows) and of a pruned tent's window (v->rows rows). double_gone: built
     * in single precision, the double spectra and buffers were freed. */
    float **otf_f;
    int f_real, double_gone, rows_max;
    /* A copy for another thread (svp_variant_clone): everything above that the build made is
     * the original's, read only; the copy owns only its buffers (acc, ext, row_on, spec2, blk)
     * and whatever single precision makes on it (otf_f, fr_f, spec_f, acc_f). */
    int borrowed;
    float *fr_f;
    fftwf_complex *spec_f, *acc_f;
    const svp_fftf_rows *rows_img, *rows_win;
    /* The far tail on a coarse grid (svp_variant_options.tail_tol; low rank and regions): the
     * frame holds each term's core (radius 2 tail_r0, tail.c's split), tails[r] its tail as
     * P K_c Pᵀ on nodes every tail_s pixels (tail.c), tail_err the estimated ℓ1 error per unit
     * flux of all of them; tail_in (w x h) a term's weighted input (apply) or its tail's output
     * (adjoint). A copy makes its own (svp_tail_copy). tails NULL: the plain frame. */
    svp_tail **tails;
    int tail_s, tail_r0;
    double tail_err;
    double *tail_in;
    int tail_pixel; /* regions: coef holds a weight per pixel (term r's at coef + r w h) */
};

void svp_variant_defaults(svp_variant_options *o)
{
    memset(o, 0, sizeof *o);
    o->representation = SVP_VARIANT_AUTO;
    o->tolerance = 1e-3;
    o->applications = 50;
    o->max_memory = 0;
    o->grid_x = 8;
    o->grid_y = 8;
    o->rank = 6;
    o->samples_x = 8;
    o->samples_y = 8;
    o->renormalise = 1;
    o->lowrank_mean = 1;
    o->support = 0;
}

/* ---- node grids -------------------------------------------------------------------------- */

/* Node i of g along an axis of `size` pixels sits at i (size − 1) / (g − 1) (the centre when
 * g = 1): the hats then cover the image exactly and sum to one everywhere. */
static double node_pos(int i, int g, int size)
{
    return g == 1 ? 0.5 * (size - 1) : (double)i * (size - 1) / (g - 1);
}

static svp_status axis_hats(int g, int size, int **i0, double **frac)
{
    *i0 = malloc((size_t)size * sizeof(int));
    *frac = malloc((size_t)size * sizeof(double));
    if (!*i0 || !*frac) return svp_fail(SVP_ERR_NOMEM, "out of memory for node weights");
    for (int x = 0; x < size; x++) {
        if (g == 1) {
            (*i0)[x] = 0;
            (*frac)[x] = 0;
            continue;
        }
        double t = (double)x * (g - 1) / (size - 1);
        int i = (int)floor(t);
        if (i > g - 2) i = g - 2;
        (*i0)[x] = i;
        (*frac)[x] = t - i;
    }
    return SVP_OK;
}

static inline double hat(const int *i0, const double *frac, int node, int x)
{
    if (node == i0[x]) return 1.0 - frac[x];
    if (node == i0[x] + 1) return frac[x];
    return 0.0;
}

/* ---- apply / adjoint --------------------------------------------------------------------- */

/* <α x>_FOV added to every output pixel (scatter), or α(s) <y> (its adjoint, gather). */
void svp_halo_scatter(const double *restrict alpha, size_t n, const double *restrict in,
                      double *restrict out, double *restrict tmp)
{
    const double add = svp_dot(alpha, in, tmp, n) / (double)n;
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
    for (size_t i = 0; i < n; i++) out[i] += add;
}

void svp_halo_gather(const double *restrict alpha, size_t n, const double *restrict in,
                     double *restrict out)
{
    const double mean = svp_sum(in, n) / (double)n;
#pragma omp parallel for schedule(static) if (n > SVP_PARALLEL_MIN)
    for (size_t i = 0; i < n; i++) out[i] += alpha[i] * mean;
}

/* Window rows t0 .. t0 + nb − 1 of E(s ⊙ x) into e, rows `stride` apart: window row t is frame
 * row (start + t) mod ny. The image row is contiguous in the frame; only the margins look up
 * src. Without a scale only the margins are written: fill_rows reads the image's part of the
 * row from x itself. */
static void extend_rows(const svp_blur *b, const double *restrict x, int start, int t0, int nb,
                        double *restrict e, int stride)
{
    const svp_frame *f = &b->frame;
    const int w = b->width, nx = f->nx, ny = f->ny, lo = f->off_x, hi = f->off_x + w;
    const int *sx = f->src_x, *sy = f->src_y;
    const double *restrict scale = b->variant->scale;
    for (int t = t0; t < t0 + nb; t++) {
        const int y = sy[(start + t) % ny];
        double *restrict out = e + (size_t)(t - t0) * stride;
        if (y < 0) {
            memset(out, 0, (size_t)nx * sizeof(double));
            continue;
        }
        const double *restrict in = x + (size_t)y * w;
        if (scale) {
            const double *restrict sr = scale + (size_t)y * w;
            for (int q = 0; q < lo; q++) out[q] = sx[q] >= 0 ? sr[sx[q]] * in[sx[q]] : 0.0;
            for (int q = 0; q < w; q++) out[lo + q] = sr[q] * in[q];
            for (int q = hi; q < nx; q++) out[q] = sx[q] >= 0 ? sr[sx[q]] * in[sx[q]] : 0.0;
        } else {
            for (int q = 0; q < lo; q++) out[q] = sx[q] >= 0 ? in[sx[q]] : 0.0;
            for (int q = hi; q < nx; q++) out[q] = sx[q] >= 0 ? in[sx[q]] : 0.0;
        }
    }
}

/* out[q] = (s0 c0[q] + s1 c1[q]) e[q] for q below n; c0 NULL: out = e. */
static inline void weight_span(double *restrict out, const double *restrict e, int n,
                               const double *restrict c0, const double *restrict c1, double s0,
                               double s1)
{
    if (!c0)
        memcpy(out, e, (size_t)n * sizeof(double));
    else if (s1 == 0)
        for (int q = 0; q < n; q++) out[q] = s0 * c0[q] * e[q];
    else
        for (int q = 0; q < n; q++) out[q] = (s0 * c0[q] + s1 * c1[q]) * e[q];
}

/* Window rows t0 .. t0 + nb − 1 of term k's extended weighted input c_k ⊙ E(s ⊙ x) (= E(c_k ⊙
 * s ⊙ x): the weights are functions of the source pixel) into fr, from the same rows of
 * E(s ⊙ x) as extend_rows made them in ex (without a scale only their margins: the image's
 * part is read from x), both `stride` apart: window row t is frame row (start + t) mod ny. */
static void fill_rows(const svp_blur *b, const double *x, int k, int start, int t0, int nb,
                      const double *restrict ex, double *restrict fr, int stride)
{
    const svp_variant_data *v = b->variant;
    const svp_frame *f = &b->frame;
    const int nx = f->nx, ny = f->ny, gy = v->gy, lo = f->off_x, hi = f->off_x + b->width;
    const int tent = b->kind == SVP_BLUR_TENT;
    const double *restrict cw = tent ? v->wx + (size_t)(k % v->gx) * nx : NULL;
    const double *restrict rw = tent ? v->wy + (size_t)(k / v->gx) * ny : NULL;
    const double *restrict lr = tent ? NULL : v->wx + (size_t)k * gy * nx;
    for (int t = t0; t < t0 + nb; t++) {
        const int fy = (start + t) % ny, y = f->src_y[fy];
        double *restrict out = fr + (size_t)(t - t0) * stride;
        const double *e = ex + (size_t)(t - t0) * stride;
        const double *c0 = NULL, *c1 = NULL;
        double s0 = 1, s1 = 0;
        if (y < 0) {
            memset(out, 0, (size_t)nx * sizeof(double));
            continue;
        }
        if (v->unit[k]) {
            /* out = E(s ⊙ x) */
        } else if (tent) {
            s0 = rw[fy];
            c0 = c1 = cw;
        } else {
            const int j0 = v->ly0[fy], j1 = j0 + 1 < gy ? j0 + 1 : j0;
            s1 = v->lty[fy];
            s0 = 1 - s1;
            c0 = lr + (size_t)j0 * nx;
            c1 = lr + (size_t)j1 * nx;
        }
        if (c0 && s0 == 0 && s1 == 0) {
            memset(out, 0, (size_t)nx * sizeof(double));
            continue;
        }
        const double *mid = v->scale ? e + lo : x + (size_t)y * b->width;
        weight_span(out, e, lo, c0, c1, s0, s1);
        weight_span(out + lo, mid, hi - lo, c0 ? c0 + lo : NULL, c1 ? c1 + lo : NULL, s0, s1);
        weight_span(out + hi, e + hi, nx - hi, c0 ? c0 + hi : NULL, c1 ? c1 + hi : NULL, s0, s1);
    }
}

/* Adjoint: acc (+)= c_k ⊙ z (+ c_k+1 ⊙ z1 when z1) on window rows t0 .. t0 + nb − 1 (z's rows
 * `stride` apart, window row t = frame row (start + t) mod ny), acc = v->ext, with the apply's
 * row x column weight tables (the weights are functions of the source pixel, so c_k ⊙ E(u) =
 * E(c_k ⊙ u) and the transpose Eᵀ(c_k ⊙ z) = c_k ⊙ Eᵀ z). on[fy]: acc's row fy already holds
 * a term this application, so the first term to reach a row assigns it (rows of zero weight
 * are not touched). A pair is two non-unit terms over the same rows. */
static void accumulate_rows(const svp_blur *b, int k, int start, int t0, int nb,
                            const double *restrict z, const double *restrict z1, int stride)
{
    const svp_variant_data *v = b->variant;
    const int nx = b->frame.nx, ny = b->frame.ny, gy = v->gy;
    const int tent = b->kind == SVP_BLUR_TENT, unit = v->unit[k];
    double *restrict acc = v->ext;
    char *restrict on = v->row_on;
    const int k1 = z1 ? k + 1 : k;
    const double *restrict cw0 = tent ? v->wx + (size_t)(k % v->gx) * nx : NULL;
    const double *restrict cw1 = tent ? v->wx + (size_t)(k1 % v->gx) * nx : NULL;
    const double *restrict rw0 = tent ? v->wy + (size_t)(k / v->gx) * ny : NULL;
    const double *restrict rw1 = tent ? v->wy + (size_t)(k1 / v->gx) * ny : NULL;
    const double *restrict lr0 = tent ? NULL : v->wx + (size_t)k * gy * nx;
    const double *restrict lr1 = tent ? NULL : v->wx + (size_t)k1 * gy * nx;
    for (int t = t0; t < t0 + nb; t++) {
        const int fy = (start + t) % ny;
        double *restrict out = acc + (size_t)fy * nx;
        const double *restrict i0 = z + (size_t)(t - t0) * stride;
        const double *restrict i1 = z1 ? z1 + (size_t)(t - t0) * stride : NULL;
        const int first = !on[fy];
        if (unit) { /* never in a pair */
            if (first)
                memcpy(out, i0, (size_t)nx * sizeof(double));
            else
                for (int q = 0; q < nx; q++) out[q] += i0[q];
        } else if (tent) {
            const double h0 = rw0[fy], h1 = i1 ? rw1[fy] : 0.0;
            if (h0 == 0 && h1 == 0) continue;
            if (!i1 && first)
                for (int q = 0; q < nx; q++) out[q] = h0 * cw0[q] * i0[q];
            else if (!i1)
                for (int q = 0; q < nx; q++) out[q] += h0 * cw0[q] * i0[q];
            else if (first)
                for (int q = 0; q < nx; q++) out[q] = h0 * cw0[q] * i0[q] + h1 * cw1[q] * i1[q];
            else
                for (int q = 0; q < nx; q++) out[q] += h0 * cw0[q] * i0[q] + h1 * cw1[q] * i1[q];
        } else {
            const int j0 = v->ly0[fy];
            if (j0 < 0) continue;
            const int j1 = j0 + 1 < gy ? j0 + 1 : j0;
            const double ty = v->lty[fy], sy = 1 - ty;
            const double *restrict a0 = lr0 + (size_t)j0 * nx, *restrict a1 = lr0 + (size_t)j1 * nx;
            const double *restrict b0 = lr1 + (size_t)j0 * nx, *restrict b1 = lr1 + (size_t)j1 * nx;
            if (!i1 && first)
                for (int q = 0; q < nx; q++) out[q] = (sy * a0[q] + ty * a1[q]) * i0[q];
            else if (!i1)
                for (int q = 0; q < nx; q++) out[q] += (sy * a0[q] + ty * a1[q]) * i0[q];
            else if (first)
                for (int q = 0; q < nx; q++)
                    out[q] = (sy * a0[q] + ty * a1[q]) * i0[q] + (sy * b0[q] + ty * b1[q]) * i1[q];
            else
                for (int q = 0; q < nx; q++)
                    out[q] += (sy * a0[q] + ty * a1[q]) * i0[q] + (sy * b0[q] + ty * b1[q]) * i1[q];
        }
        on[fy] = 1;
    }
}

/* x = s ⊙ Eᵀ fr: each image row gathers the frame rows that copy it (those marked in on;
 * NULL = all), in frame-row order (deterministic), then takes the per-pixel scale. */
static void fold_scaled(const svp_blur *b, const double *restrict fr, const char *on,
                        double *restrict x)
{
    const svp_variant_data *v = b->variant;
    const svp_frame *f = &b->frame;
    const int w = b->width, h = b->height, nx = f->nx, ny = f->ny;
    const int *sx = f->src_x, *sy = f->src_y;
    const double *restrict scale = v->scale;
#pragma omp parallel for schedule(static) if ((size_t)nx * ny > SVP_PARALLEL_MIN)
    for (int y = 0; y < h; y++) {
        double *restrict out = x + (size_t)y * w;
        memset(out, 0, (size_t)w * sizeof(double));
        for (int j = 0; j < ny; j++) {
            if (sy[j] != y || (on && !on[j])) continue;
            const double *restrict in = fr + (size_t)j * nx;
            /* the image row is contiguous in the frame; only the margins look up src */
            const int lo = f->off_x, hi = f->off_x + w;
            for (int q = 0; q < w; q++) out[q] += in[lo + q];
            for (int q = 0; q < lo; q++)
                if (sx[q] >= 0) out[sx[q]] += in[q];
            for (int q = hi; q < nx; q++)
                if (sx[q] >= 0) out[sx[q]] += in[q];
        }
        if (scale) {
            const double *restrict sr = scale + (size_t)y * w;
            for (int q = 0; q < w; q++) out[q] *= sr[q];
        }
    }
}

/* The per-thread row blocks of the fused transforms (three per thread: a pair's terms and the
 * extended rows they are made from), made for at least `threads` threads. */
static svp_status ensure_blocks(svp_variant_data *v, int threads)
{
    if (threads <= v->blk_threads) return SVP_OK;
    svp_free(v->blk);
    v->blk_threads = 0;
    v->blk = svp_alloc((size_t)threads * 3 * SVP_FFT_BLOCK * v->block->bx * sizeof(double));
    if (!v->blk) return svp_fail(SVP_ERR_NOMEM, "out of memory for %d row blocks", threads);
    v->blk_threads = threads;
    return SVP_OK;
}

static inline double *thread_block(const svp_variant_data *v, int which)
{
    return v->blk + ((size_t)omp_get_thread_num() * 3 + which) * SVP_FFT_BLOCK * v->block->bx;
}

/* out[q] = the spectrum of term k + q's weighted frame c_k+q ⊙ E(s ⊙ x), for q below n (1 or
 * 2: two terms over the same rows): the rows are made a block at a time (E(s ⊙ x)'s rows
 * extended from x once for both terms of a pair) and transformed along x while in cache, then
 * the columns. Every frame row is a copy of an image row (or zero) and the weights are
 * functions of the source pixel, so only the image's own rows are made and transformed: the
 * margin rows copy their source row's transform. Pruned tents transform only their window's
 * rows (moved to the top: the phase is in otf[k]). */
static void term_spectra(svp_blur *b, const double *x, int k, int n, fftw_complex *const *out)
{
    svp_variant_data *v = b->variant;
    const svp_frame *f = &b->frame;
    const svp_fft_block *p = v->block;
    const int ncx = f->ncx, ny = f->ny, B = SVP_FFT_BLOCK;
    const int rows = v->pruned ? v->rows : b->height;
    const int start = v->pruned ? v->start[k] : f->off_y; /* window row 0's frame row */
    const int nblk = (rows + B - 1) / B;
    const size_t row_bytes = (size_t)ncx * sizeof(fftw_complex);
#pragma omp parallel for schedule(static) if ((size_t)rows * f->nx > SVP_PARALLEL_MIN)
    for (int ib = 0; ib < nblk; ib++) {
        const int t0 = ib * B, nb = rows - t0 < B ? rows - t0 : B;
        const int r0 = v->pruned ? t0 : start + t0; /* where the block's transforms go */
        double *ex = thread_block(v, 2);
        extend_rows(b, x, start, t0, nb, ex, p->bx);
        for (int q = 0; q < n; q++) {
            double *blk = thread_block(v, q);
            fill_rows(b, x, k + q, start, t0, nb, ex, blk, p->bx);
            svp_fft_block_forward(p, nb, blk, out[q] + (size_t)r0 * ncx);
        }
    }
    for (int q = 0; q < n; q++) {
        fftw_complex *o = out[q];
        if (v->pruned) {
            if (rows < ny) memset(o + (size_t)rows * ncx, 0, (size_t)(ny - rows) * row_bytes);
        } else {
            for (int fy = 0; fy < ny; fy++) {
                const int y = f->src_y[fy];
                if (y >= 0 && fy == f->off_y + y) continue; /* an image row itself */
                if (y < 0)
                    memset(o + (size_t)fy * ncx, 0, row_bytes);
                else
                    memcpy(o + (size_t)fy * ncx, o + (size_t)(f->off_y + y) * ncx, row_bytes);
            }
        }
        fftw_execute_dft(v->cols->cols_fwd, o, o);
    }
}

/* acc (assign: =, else +=) otf_k · s0 (+ otf_k+1 · s1 when pair), ns complex values each,
 * written out in real arithmetic (no C99 complex NaN fix-ups, so it vectorises); real
 * spectra (otf_re) read half as much. The loop body is one of six: (real, complex) x (pair,
 * pair assigning, single). */
/* _Pragma inside a macro is beyond clang-format: laid out by hand */
/* clang-format off */
#define SVP_ACCUMULATE(RE, IM)                                                                     \
    do {                                                                                           \
        if (assign) {                                                                              \
            _Pragma("omp parallel for schedule(static) if (ns > SVP_PARALLEL_MIN / 2)")            \
            for (size_t i = 0; i < ns; i++) {                                                      \
                a[2 * i] = (RE);                                                                   \
                a[2 * i + 1] = (IM);                                                               \
            }                                                                                      \
        } else {                                                                                   \
            _Pragma("omp parallel for schedule(static) if (ns > SVP_PARALLEL_MIN / 2)")            \
            for (size_t i = 0; i < ns; i++) {                                                      \
                a[2 * i] += (RE);                                                                  \
                a[2 * i + 1] += (IM);                                                              \
            }                                                                                      \
        }                                                                                          \
    } while (0)
/* clang-format on */

static void accumulate_spectra(svp_variant_data *v, int k, int pair, int assign,
                               const double *restrict s0, const double *restrict s1, size_t ns)
{
    double *restrict a = (double *)v->acc;
    if (v->otf_re) {
        const double *restrict p0 = v->otf_re[k], *restrict p1 = pair ? v->otf_re[k + 1] : p0;
        if (pair)
            SVP_ACCUMULATE(p0[i] * s0[2 * i] + p1[i] * s1[2 * i],
                           p0[i] * s0[2 * i + 1] + p1[i] * s1[2 * i + 1]);
        else
            SVP_ACCUMULATE(p0[i] * s0[2 * i], p0[i] * s0[2 * i + 1]);
        return;
    }
    const double *restrict o0 = (const double *)v->otf[k];
    const double *restrict o1 = pair ? (const double *)v->otf[k + 1] : o0;
    if (pair)
        SVP_ACCUMULATE((o0[2 * i] * s0[2 * i] - o0[2 * i + 1] * s0[2 * i + 1]) +
                           (o1[2 * i] * s1[2 * i] - o1[2 * i + 1] * s1[2 * i + 1]),
                       (o0[2 * i] * s0[2 * i + 1] + o0[2 * i + 1] * s0[2 * i]) +
                           (o1[2 * i] * s1[2 * i + 1] + o1[2 * i + 1] * s1[2 * i]));
    else
        SVP_ACCUMULATE(o0[2 * i] * s0[2 * i] - o0[2 * i + 1] * s0[2 * i + 1],
                       o0[2 * i] * s0[2 * i + 1] + o0[2 * i + 1] * s0[2 * i]);
}
#undef SVP_ACCUMULATE

/* ---- single precision -------------------------------------------------------------------- */

/* Float H and Hᵀ of tent / low rank (docs/model.md §9): the same frames, weights, row copies
 * and pruning as the double path, with fftw3f transforms of whole row sets instead of the fused
 * blocks: each term's weighted rows are made in double a block at a time (extend_rows,
 * fill_rows), stored as float, transformed (rows, then the row copies of the margins, then
 * the columns) and multiplied into a float accumulator; back the same way. The adjoint turns
 * each term's float rows into double a block at a time and weights them into the double frame
 * accumulator (accumulate_rows, fold_scaled): only the transforms and spectral products are in
 * float. */

/* Window rows 0 .. rows − 1 of term k's weighted frame (window row t = frame row
 * (start + t) mod ny) into v->fr_f. */
static void single_load(svp_blur *b, const double *x, int k, int start, int rows)
{
    svp_variant_data *v = b->variant;
    const int nx = b->frame.nx, B = SVP_FFT_BLOCK, bx = v->block->bx;
    const int nblk = (rows + B - 1) / B;
#pragma omp parallel for schedule(static) if ((size_t)rows * nx > SVP_PARALLEL_MIN)
    for (int ib = 0; ib < nblk; ib++) {
        const int t0 = ib * B, nb = rows - t0 < B ? rows - t0 : B;
        double *ex = thread_block(v, 2), *blk = thread_block(v, 0);
        extend_rows(b, x, start, t0, nb, ex, bx);
        fill_rows(b, x, k, start, t0, nb, ex, blk, bx);
        for (int t = 0; t < nb; t++) {
            float *restrict o = v->fr_f + (size_t)(t0 + t) * nx;
            const double *restrict in = blk + (size_t)t * bx;
            for (int q = 0; q < nx; q++) o[q] = (float)in[q];
        }
    }
}

/* v->spec_f = the spectrum of term k's weighted frame. */
static void single_term_spectrum(svp_blur *b, const double *x, int k)
{
    svp_variant_data *v = b->variant;
    const svp_frame *f = &b->frame;
    const int ny = f->ny, ncx = f->ncx, h = b->height;
    const svp_fftf_rows *p = v->pruned ? v->rows_win : v->rows_img;
    fftwf_complex *s = v->spec_f;
    const size_t row_bytes = (size_t)ncx * sizeof(fftwf_complex);
    single_load(b, x, k, v->pruned ? v->start[k] : f->off_y, p->rows);
    fftwf_execute_dft_r2c(p->rows_r2c, v->fr_f, s);
    if (v->pruned) {
        if (p->rows < ny) memset(s + (size_t)p->rows * ncx, 0, (size_t)(ny - p->rows) * row_bytes);
    } else {
        /* the image's rows to their frame rows; a margin row copies its source row */
        if (f->off_y) memmove(s + (size_t)f->off_y * ncx, s, (size_t)h * row_bytes);
        for (int fy = 0; fy < ny; fy++) {
            const int y = f->src_y[fy];
            if (y >= 0 && fy == f->off_y + y) continue;
            if (y < 0)
                memset(s + (size_t)fy * ncx, 0, row_bytes);
            else
                memcpy(s + (size_t)fy * ncx, s + (size_t)(f->off_y + y) * ncx, row_bytes);
        }
    }
    fftwf_execute_dft(p->cols_fwd, s, s);
}

/* out (assign: =, else +=) otf_f[k] · in (conjugate: conj(otf_f[k]) · in), ns values; one
 * loop per case so that each vectorises. */
static void single_product(const svp_variant_data *v, int k, const float *restrict in,
                           float *restrict out, size_t ns, int assign, int conjugate)
{
    const float *restrict o = v->otf_f[k];
    const int big = ns > SVP_PARALLEL_MIN / 2;
    if (v->f_real && assign) {
#pragma omp parallel for schedule(static) if (big)
        for (size_t i = 0; i < ns; i++) {
            out[2 * i] = o[i] * in[2 * i];
            out[2 * i + 1] = o[i] * in[2 * i + 1];
        }
    } else if (v->f_real) {
#pragma omp parallel for schedule(static) if (big)
        for (size_t i = 0; i < ns; i++) {
            out[2 * i] += o[i] * in[2 * i];
            out[2 * i + 1] += o[i] * in[2 * i + 1];
        }
    } else {
        const float sg = conjugate ? -1.0f : 1.0f;
        if (assign) {
#pragma omp parallel for schedule(static) if (big)
            for (size_t i = 0; i < ns; i++) {
                const float pr = o[2 * i], pi = sg * o[2 * i + 1];
                out[2 * i] = pr * in[2 * i] - pi * in[2 * i + 1];
                out[2 * i + 1] = pr * in[2 * i + 1] + pi * in[2 * i];
            }
        } else {
#pragma omp parallel for schedule(static) if (big)
            for (size_t i = 0; i < ns; i++) {
                const float pr = o[2 * i], pi = sg * o[2 * i + 1];
                out[2 * i] += pr * in[2 * i] - pi * in[2 * i + 1];
                out[2 * i + 1] += pr * in[2 * i + 1] + pi * in[2 * i];
            }
        }
    }
}

/* ---- the far tail on a coarse grid (low rank, regions) ------------------------------------ */

/* Low-rank term r's coefficients along image row y at the sample columns (a[i], i < gx):
 * blended between the sample rows as the weight tables are. */
static void coef_samples_row(const svp_variant_data *v, int r, int y, double *restrict a)
{
    const int gx = v->gx, j = v->iy0[y];
    const double t = v->fy[y], *c0 = v->coef + ((size_t)r * v->gy + j) * gx;
    for (int i = 0; i < gx; i++) a[i] = (1.0 - t) * c0[i] + (t > 0 ? t * c0[i + gx] : 0.0);
}

/* The coefficient at column x from a row of coef_samples_row. */
static inline double coef_at(const svp_variant_data *v, const double *a, int x)
{
    const int i = v->ix0[x];
    const double t = v->fx[x];
    return (1.0 - t) * a[i] + (t > 0 ? t * a[i + 1] : 0.0);
}

/* Term r's weights along image row y: low rank, its coefficients at the sample columns in a
 * (coef_at interpolates them); regions, the row of its weight map (returned, a unused). */
static const double *weight_row(const svp_blur *b, int r, int y, double *restrict a)
{
    const svp_variant_data *v = b->variant;
    if (v->tail_pixel) return v->coef + ((size_t)r * b->height + y) * b->width;
    coef_samples_row(v, r, y, a);
    return NULL;
}

/* y += Σ_r P K_r Pᵀ (c_r ⊙ s ⊙ x): every term's tail, each on its own nodes. Rows are
 * independent and each tail's passes sum in a fixed order: the same bits for any threads. */
static void tails_apply(svp_blur *b, const double *restrict x, double *restrict y)
{
    svp_variant_data *v = b->variant;
    const int w = b->width, h = b->height;
    double *restrict in = v->tail_in;
    for (int r = 0; r < v->n_terms; r++) {
#pragma omp parallel for schedule(static) if ((size_t)w * h > SVP_PARALLEL_MIN)
        for (int yy = 0; yy < h; yy++) {
            double a[64]; /* low rank: gx <= 64 (check_options) */
            const double *pix = weight_row(b, r, yy, a);
            const size_t o = (size_t)yy * w;
            for (int q = 0; q < w; q++)
                in[o + q] = (pix ? pix[q] : coef_at(v, a, q)) *
                            (v->scale ? v->scale[o + q] * x[o + q] : x[o + q]);
        }
        svp_tail_gather(v->tails[r], in, (size_t)w, 0);
        svp_tail_spread(v->tails[r], y, (size_t)w);
    }
}

/* x += s ⊙ Σ_r c_r ⊙ P K_rᵀ Pᵀ y: tails_apply's adjoint. */
static void tails_adjoint(svp_blur *b, const double *restrict y, double *restrict x)
{
    svp_variant_data *v = b->variant;
    const int w = b->width, h = b->height;
    double *restrict out = v->tail_in;
    for (int r = 0; r < v->n_terms; r++) {
        svp_tail_gather(v->tails[r], y, (size_t)w, 1);
        memset(out, 0, (size_t)w * h * sizeof(double));
        svp_tail_spread(v->tails[r], out, (size_t)w);
#pragma omp parallel for schedule(static) if ((size_t)w * h > SVP_PARALLEL_MIN)
        for (int yy = 0; yy < h; yy++) {
            double a[64];
            const double *pix = weight_row(b, r, yy, a);
            const size_t o = (size_t)yy * w;
            for (int q = 0; q < w; q++) {
                const double t = (pix ? pix[q] : coef_at(v, a, q)) * out[o + q];
                x[o + q] += v->scale ? v->scale[o + q] * t : t;
            }
        }
    }
}

static void tails_free(svp_variant_data *v)
{
    if (v->tails)
        for (int r = 0; r < v->n_terms; r++) svp_tail_free(v->tails[r]);
    free(v->tails);
    v->tails = NULL;
    svp_free(v->tail_in);
    v->tail_in = NULL;
}

static size_t tails_memory(const svp_blur *b, const svp_variant_data *v)
{
    if (!v->tails) return 0;
    size_t bytes = (size_t)b->width * b->height * sizeof(double);
    for (int r = 0; r < v->n_terms; r++) bytes += svp_tail_memory(v->tails[r]);
    return bytes;
}

/* A copy's own tails (svp_variant_clone): the same coarse kernels, new buffers and plans. */
static svp_status tails_copy(const svp_blur *b, const svp_variant_data *v, svp_variant_data *u)
{
    u->tails = NULL;
    u->tail_in = NULL;
    if (!v->tails) return SVP_OK;
    u->tails = calloc((size_t)v->n_terms, sizeof *u->tails);
    u->tail_in = svp_alloc((size_t)b->width * b->height * sizeof(double));
    if (!u->tails || !u->tail_in)
        return svp_fail(SVP_ERR_NOMEM, "out of memory for a copy of the operator's tails");
    for (int r = 0; r < v->n_terms; r++) SVP_CHECK(svp_tail_copy(v->tails[r], &u->tails[r]));
    return SVP_OK;
}

svp_status svp_variant_tail_info(const svp_blur *b, int *step, int *split, double *error)
{
    const svp_variant_data *v = b->variant;
    *step = *split = 0;
    *error = 0;
    if (v && v->tails) {
        *step = v->tail_s;
        *split = v->tail_r0;
        *error = v->tail_err;
    }
    return SVP_OK;
}

static svp_status variant_apply_single(svp_blur *b, const double *restrict x, double *restrict y)
{
    svp_variant_data *v = b->variant;
    const svp_frame *f = &b->frame;
    const size_t ns = (size_t)f->ny * f->ncx;
    const int w = b->width, h = b->height, nx = f->nx;
    SVP_CHECK(ensure_blocks(v, omp_get_max_threads()));
    for (int k = 0; k < v->n_terms; k++) {
        single_term_spectrum(b, x, k);
        single_product(v, k, (const float *)v->spec_f, (float *)v->acc_f, ns, k == 0, 0);
    }
    /* back: the columns, the image's rows moved to the top, their rows, cropped into y */
    const svp_fftf_rows *p = v->rows_img;
    fftwf_execute_dft(p->cols_bwd, v->acc_f, v->acc_f);
    if (f->off_y)
        memmove(v->acc_f, v->acc_f + (size_t)f->off_y * f->ncx,
                (size_t)h * f->ncx * sizeof(fftwf_complex));
    fftwf_execute_dft_c2r(p->rows_c2r, v->acc_f, v->fr_f);
#pragma omp parallel for schedule(static) if ((size_t)h * nx > SVP_PARALLEL_MIN)
    for (int t = 0; t < h; t++) {
        const float *restrict in = v->fr_f + (size_t)t * nx + f->off_x;
        double *restrict out = y + (size_t)t * w;
        for (int q = 0; q < w; q++) out[q] = (double)in[q];
    }
    if (v->tails) tails_apply(b, x, y);
    if (v->alpha) svp_halo_scatter(v->alpha, (size_t)w * h, x, y, b->work_r_image);
    return SVP_OK;
}

/* v->acc_f = the spectrum of C y (the image embedded in the frame). */
static void single_embed_spectrum(svp_blur *b, const double *restrict y)
{
    svp_variant_data *v = b->variant;
    const svp_frame *f = &b->frame;
    const int w = b->width, h = b->height, nx = f->nx, ncx = f->ncx, ny = f->ny;
    const svp_fftf_rows *p = v->rows_img;
    fftwf_complex *s = v->acc_f;
#pragma omp parallel for schedule(static) if ((size_t)h * nx > SVP_PARALLEL_MIN)
    for (int t = 0; t < h; t++) {
        float *restrict o = v->fr_f + (size_t)t * nx;
        const double *restrict in = y + (size_t)t * w;
        memset(o, 0, (size_t)nx * sizeof(float));
        for (int q = 0; q < w; q++) o[f->off_x + q] = (float)in[q];
    }
    fftwf_execute_dft_r2c(p->rows_r2c, v->fr_f, s);
    const size_t row_bytes = (size_t)ncx * sizeof(fftwf_complex);
    if (f->off_y) {
        memmove(s + (size_t)f->off_y * ncx, s, (size_t)h * row_bytes);
        memset(s, 0, (size_t)f->off_y * row_bytes);
    }
    memset(s + (size_t)(f->off_y + h) * ncx, 0, (size_t)(ny - f->off_y - h) * row_bytes);
    fftwf_execute_dft(p->cols_fwd, s, s);
}

static svp_status variant_adjoint_single(svp_blur *b, const double *restrict y,
                                         double *restrict x)
{
    svp_variant_data *v = b->variant;
    const svp_frame *f = &b->frame;
    const size_t ns = (size_t)f->ny * f->ncx;
    const int ny = f->ny, ncx = f->ncx, nx = f->nx, h = b->height, B = SVP_FFT_BLOCK;
    const int bx = v->block->bx;
    SVP_CHECK(ensure_blocks(v, omp_get_max_threads()));
    single_embed_spectrum(b, y);
    memset(v->row_on, 0, (size_t)ny);
    const svp_fftf_rows *p = v->pruned ? v->rows_win : v->rows_img;
    fftwf_complex *s = v->spec_f;
    for (int k = 0; k < v->n_terms; k++) {
        single_product(v, k, (const float *)v->acc_f, (float *)s, ns, 1, 1);
        fftwf_execute_dft(p->cols_bwd, s, s);
        if (!v->pruned) {
            /* margin rows onto their source rows (fold_spectrum_rows), the image's rows up */
            for (int fy = 0; fy < ny; fy++) {
                const int yy = f->src_y[fy];
                if (yy < 0 || fy == f->off_y + yy) continue;
                float *restrict to = (float *)(s + (size_t)(f->off_y + yy) * ncx);
                const float *restrict from = (const float *)(s + (size_t)fy * ncx);
                for (int i = 0; i < 2 * ncx; i++) to[i] += from[i];
            }
            if (f->off_y)
                memmove(s, s + (size_t)f->off_y * ncx, (size_t)h * ncx * sizeof(fftwf_complex));
        }
        fftwf_execute_dft_c2r(p->rows_c2r, s, v->fr_f);
        const int rows = p->rows, start = v->pruned ? v->start[k] : f->off_y;
        const int nblk = (rows + B - 1) / B;
#pragma omp parallel for schedule(static) if ((size_t)rows * nx > SVP_PARALLEL_MIN)
        for (int ib = 0; ib < nblk; ib++) {
            const int t0 = ib * B, nb = rows - t0 < B ? rows - t0 : B;
            double *z = thread_block(v, 0);
            for (int t = 0; t < nb; t++) {
                const float *restrict in = v->fr_f + (size_t)(t0 + t) * nx;
                double *restrict o = z + (size_t)t * bx;
                for (int q = 0; q < nx; q++) o[q] = (double)in[q];
            }
            accumulate_rows(b, k, start, t0, nb, z, NULL, bx);
        }
    }
    fold_scaled(b, v->ext, v->row_on, x);
    if (v->tails) tails_adjoint(b, y, x);
    if (v->alpha) svp_halo_gather(v->alpha, (size_t)b->width * b->height, y, x);
    return SVP_OK;
}

/* The K float spectra from the double ones (ns complex values a term; real parts only when the
 * spectra are real). drop: each term's double spectrum is freed once converted, so the peak
 * does not grow, and the double arrays go. */
static svp_status float_spectra(svp_variant_data *v, size_t ns, int drop)
{
    const int K = v->n_terms;
    v->f_real = v->otf_re != NULL;
    v->otf_f = calloc((size_t)K, sizeof *v->otf_f);
    if (!v->otf_f) return svp_fail(SVP_ERR_NOMEM, "out of memory for %d float spectra", K);
    const size_t nv = v->f_real ? ns : 2 * ns;
    for (int k = 0; k < K; k++) {
        float *o = v->otf_f[k] = svp_alloc(nv * sizeof(float));
        if (!o) return svp_fail(SVP_ERR_NOMEM, "out of memory for %d float spectra", K);
        const double *d = v->f_real ? v->otf_re[k] : (const double *)v->otf[k];
        for (size_t i = 0; i < nv; i++) o[i] = (float)d[i];
        if (!drop) continue;
        if (v->otf) {
            svp_free(v->otf[k]);
            v->otf[k] = NULL;
        }
        if (v->otf_re) {
            svp_free(v->otf_re[k]);
            v->otf_re[k] = NULL;
        }
    }
    if (drop) {
        free(v->otf);
        free(v->otf_re);
        v->otf = NULL;
        v->otf_re = NULL;
    }
    return SVP_OK;
}

/* The float spectra (from the double ones), buffers and plans, once. */
static svp_status single_setup(svp_blur *b)
{
    svp_variant_data *v = b->variant;
    const svp_frame *f = &b->frame;
    const size_t ns = (size_t)f->ny * f->ncx;
    if (!v->otf_f) SVP_CHECK(float_spectra(v, ns, 0));
    if (!v->fr_f) {
        SVP_CHECK(svp_fftf_rows_get(f->ny, f->nx, b->height, &v->rows_img));
        v->rows_win = v->rows_img;
        if (v->pruned) SVP_CHECK(svp_fftf_rows_get(f->ny, f->nx, v->rows, &v->rows_win));
        v->rows_max = v->rows_win->rows > b->height ? v->rows_win->rows : b->height;
        v->fr_f = svp_alloc((size_t)v->rows_max * f->nx * sizeof(float));
        v->spec_f = svp_alloc(ns * sizeof(fftwf_complex));
        v->acc_f = svp_alloc(ns * sizeof(fftwf_complex));
        if (!v->fr_f || !v->spec_f || !v->acc_f)
            return svp_fail(SVP_ERR_NOMEM, "out of memory for the %d x %d float frame", f->nx,
                            f->ny);
    }
    return SVP_OK;
}

svp_status svp_variant_set_single(svp_blur *b, int on)
{
    if (b->kind != SVP_BLUR_TENT && b->kind != SVP_BLUR_LOWRANK)
        return svp_fail(SVP_ERR_UNSUPPORTED, "single precision is available for the invariant, "
                                             "tent and low-rank operators");
    svp_variant_data *v = b->variant;
    if (!on) {
        if (v->double_gone)
            return svp_fail(SVP_ERR_UNSUPPORTED, "the operator was built in single precision: "
                                                 "its double spectra were not kept");
        b->single = 0;
        return SVP_OK;
    }
    SVP_CHECK(single_setup(b));
    b->single = 1;
    return SVP_OK;
}

int svp_blur_has_double(const svp_blur *b)
{
    if (b->kind != SVP_BLUR_TENT && b->kind != SVP_BLUR_LOWRANK) return 1;
    return !b->variant->double_gone;
}

/* Built in single precision: the float spectra replace the double ones (a term at a time, so
 * the build's peak does not grow), and the double path's spectral buffers go. */
static svp_status drop_double(svp_blur *b)
{
    svp_variant_data *v = b->variant;
    svp_free(v->acc);
    svp_free(v->spec2);
    v->acc = NULL;
    v->spec2 = NULL;
    SVP_CHECK(float_spectra(v, (size_t)b->frame.ny * b->frame.ncx, 1));
    v->double_gone = 1;
    return svp_variant_set_single(b, 1);
}

static svp_status variant_apply(svp_blur *b, const double *restrict x, double *restrict y)
{
    if (b->single) return variant_apply_single(b, x, y);
    svp_variant_data *v = b->variant;
    svp_frame *f = &b->frame;
    const size_t ns = (size_t)f->ny * f->ncx;
    const int K = v->n_terms;
    SVP_CHECK(ensure_blocks(v, omp_get_max_threads()));
    /* One term: multiply in place and invert work_c (no accumulator). Otherwise the terms go
     * in pairs (spectra in work_c and spec2), so each pass over the accumulator adds two
     * products: acc (+)= otf_k · spec_k + otf_k+1 · spec_k+1. */
    fftw_complex *acc = K == 1 ? b->work_c : v->acc;
    for (int k = 0; k < K; k += 2) {
        const int pair = k + 1 < K;
        fftw_complex *const out[2] = {b->work_c, v->spec2};
        if (pair && (!v->pruned || v->start[k] == v->start[k + 1])) {
            term_spectra(b, x, k, 2, out);
        } else {
            term_spectra(b, x, k, 1, out);
            if (pair) term_spectra(b, x, k + 1, 1, out + 1);
        }
        if (K == 1) {
            if (v->otf_re)
                svp_spectrum_scale(v->otf_re[0], (double *)b->work_c, ns, 1.0);
            else
                svp_spectrum_product((const double *)v->otf[0], (double *)b->work_c, ns, 0, 1.0);
            break;
        }
        accumulate_spectra(v, k, pair, k == 0, (const double *)b->work_c,
                           pair ? (const double *)v->spec2 : NULL, ns);
    }
    /* back: the columns, then only the image's rows, a block at a time, cropped into y */
    fftw_execute_dft(v->cols->cols_bwd, acc, acc);
    const svp_fft_block *p = v->block;
    const int w = b->width, h = b->height, B = SVP_FFT_BLOCK, nblk = (h + B - 1) / B;
#pragma omp parallel for schedule(static) if ((size_t)h * f->nx > SVP_PARALLEL_MIN)
    for (int ib = 0; ib < nblk; ib++) {
        const int t0 = ib * B, nb = h - t0 < B ? h - t0 : B;
        double *blk = thread_block(v, 0);
        svp_fft_block_inverse(p, nb, acc + (size_t)(f->off_y + t0) * f->ncx, blk);
        for (int t = 0; t < nb; t++)
            memcpy(y + (size_t)(t0 + t) * w, blk + (size_t)t * p->bx + f->off_x,
                   (size_t)w * sizeof(double));
    }
    if (v->tails) tails_apply(b, x, y);
    if (v->alpha) svp_halo_scatter(v->alpha, (size_t)b->width * b->height, x, y, b->work_r_image);
    return SVP_OK;
}

/* The adjoint's transpose of term_spectra's row copies: every frame row that copies an image
 * row (a margin row) is added onto that row's own frame row in the half spectrum after the
 * column transforms (the row transforms are linear and the weights of a copy are its source
 * row's), so only the image's rows need transforming back; in frame-row order. */
static void fold_spectrum_rows(const svp_frame *f, fftw_complex *restrict s)
{
    const int ncx = f->ncx;
    for (int fy = 0; fy < f->ny; fy++) {
        const int y = f->src_y[fy];
        if (y < 0 || fy == f->off_y + y) continue;
        double *restrict to = (double *)(s + (size_t)(f->off_y + y) * ncx);
        const double *restrict from = (const double *)(s + (size_t)fy * ncx);
        for (int i = 0; i < 2 * ncx; i++) to[i] += from[i];
    }
}

static svp_status variant_adjoint(svp_blur *b, const double *restrict y, double *restrict x)
{
    if (b->single) return variant_adjoint_single(b, y, x);
    svp_variant_data *v = b->variant;
    svp_frame *f = &b->frame;
    const svp_fft_block *p = v->block;
    const size_t ns = (size_t)f->ny * f->ncx;
    const int K = v->n_terms, ny = f->ny, ncx = f->ncx, B = SVP_FFT_BLOCK;
    SVP_CHECK(ensure_blocks(v, omp_get_max_threads()));
    /* Hᵀ y = s ⊙ Eᵀ(Σ_k c_k ⊙ (P̃_k ⋆ C y)), C y the image embedded in the frame: one forward
     * transform of C y (only the image's rows along x); per term a conjugate product, the
     * columns back, then its rows (a pruned tent's window only) back a block at a time,
     * weighted into the frame accumulator v->ext while in cache; one fold at the end. */
    fftw_complex *restrict spec_y = v->acc;
    const int h = b->height, w = b->width;
    const int hb = (h + B - 1) / B;
    /* rows outside the image are zero (its rows' transforms are written below) */
    memset(spec_y, 0, (size_t)f->off_y * ncx * sizeof *spec_y);
    memset(spec_y + (size_t)(f->off_y + h) * ncx, 0,
           (size_t)(ny - f->off_y - h) * ncx * sizeof *spec_y);
#pragma omp parallel for schedule(static) if ((size_t)h * f->nx > SVP_PARALLEL_MIN)
    for (int ib = 0; ib < hb; ib++) {
        const int t0 = ib * B, nb = h - t0 < B ? h - t0 : B;
        double *blk = thread_block(v, 0);
        for (int t = 0; t < nb; t++) {
            double *row = blk + (size_t)t * p->bx;
            memset(row, 0, (size_t)f->nx * sizeof(double));
            memcpy(row + f->off_x, y + (size_t)(t0 + t) * w, (size_t)w * sizeof(double));
        }
        svp_fft_block_forward(p, nb, blk, spec_y + (size_t)(f->off_y + t0) * ncx);
    }
    fftw_execute_dft(v->cols->cols_fwd, spec_y, spec_y);
    memset(v->row_on, 0, (size_t)ny);
    fftw_complex *specs[2] = {b->work_c, v->spec2};
    for (int k = 0; k < K;) {
        /* two non-unit terms over the same rows go in a pair: one accumulator pass adds both */
        const int pair = k + 1 < K && !v->unit[k] && !v->unit[k + 1] &&
                         (!v->pruned || v->start[k] == v->start[k + 1]);
        for (int q = 0; q <= pair; q++) {
            const double *restrict yy = (const double *)spec_y;
            double *restrict sp = (double *)specs[q];
            if (v->otf_re) { /* sp = otf_k · spec_y (real: its own conjugate) */
                const double *restrict o = v->otf_re[k + q];
#pragma omp parallel for schedule(static) if (ns > SVP_PARALLEL_MIN / 2)
                for (size_t i = 0; i < ns; i++) {
                    sp[2 * i] = o[i] * yy[2 * i];
                    sp[2 * i + 1] = o[i] * yy[2 * i + 1];
                }
            } else { /* sp = conj(otf_k) · spec_y, in real arithmetic */
                const double *restrict o = (const double *)v->otf[k + q];
#pragma omp parallel for schedule(static) if (ns > SVP_PARALLEL_MIN / 2)
                for (size_t i = 0; i < ns; i++) {
                    const double pr = o[2 * i], pi = o[2 * i + 1];
                    const double yr = yy[2 * i], yi = yy[2 * i + 1];
                    sp[2 * i] = pr * yr + pi * yi;
                    sp[2 * i + 1] = pr * yi - pi * yr;
                }
            }
            fftw_execute_dft(v->cols->cols_bwd, specs[q], specs[q]);
            if (!v->pruned) fold_spectrum_rows(f, specs[q]);
        }
        /* the rows back: a pruned tent's window, else the image's rows (margins folded in) */
        const int start = v->pruned ? v->start[k] : f->off_y;
        const int rows = v->pruned ? v->rows : h, first = v->pruned ? 0 : f->off_y;
        const int nblk = (rows + B - 1) / B;
#pragma omp parallel for schedule(static) if ((size_t)rows * f->nx > SVP_PARALLEL_MIN)
        for (int ib = 0; ib < nblk; ib++) {
            const int t0 = ib * B, nb = rows - t0 < B ? rows - t0 : B;
            double *z0 = thread_block(v, 0), *z1 = pair ? thread_block(v, 1) : NULL;
            svp_fft_block_inverse(p, nb, specs[0] + (size_t)(first + t0) * ncx, z0);
            if (pair) svp_fft_block_inverse(p, nb, specs[1] + (size_t)(first + t0) * ncx, z1);
            accumulate_rows(b, k, start, t0, nb, z0, z1, p->bx);
        }
        k += 1 + pair;
    }
    fold_scaled(b, v->ext, v->row_on, x);
    if (v->tails) tails_adjoint(b, y, x);
    if (v->alpha) svp_halo_gather(v->alpha, (size_t)b->width * b->height, y, x);
    return SVP_OK;
}

/* What a copy (svp_variant_clone) owns, or the original's share of the same buffers. */
static void release_buffers(svp_variant_data *v)
{
    if (v->otf_f)
        for (int k = 0; k < v->n_terms; k++) svp_free(v->otf_f[k]);
    free(v->otf_f);
    svp_free(v->fr_f);
    svp_free(v->spec_f);
    svp_free(v->acc_f);
    svp_free(v->acc);
    svp_free(v->ext);
    svp_free(v->spec2);
    svp_free(v->blk);
    free(v->row_on);
    tails_free(v);
}

static void variant_release(svp_blur *b)
{
    svp_variant_data *v = b->variant;
    if (v) {
        release_buffers(v);
        if (v->borrowed) {
            free(v);
            b->variant = NULL;
            svp_variant_common_release(b);
            return;
        }
        if (v->otf)
            for (int k = 0; k < v->n_terms; k++) svp_free(v->otf[k]);
        free(v->otf);
        if (v->otf_re)
            for (int k = 0; k < v->n_terms; k++) svp_free(v->otf_re[k]);
        free(v->otf_re);
        svp_free(v->scale);
        svp_free(v->alpha);
        free(v->ix0);
        free(v->iy0);
        free(v->fx);
        free(v->fy);
        free(v->coef);
        free(v->eig);
        free(v->start);
        free(v->wx);
        free(v->wy);
        free(v->ly0);
        free(v->lty);
        free(v->unit);
        free(v);
        b->variant = NULL;
    }
    svp_variant_common_release(b);
}

void svp_variant_common_release(svp_blur *b)
{
    svp_free(b->work_r_image);
    b->work_r_image = NULL;
    svp_psf_field_free(b->field);
    b->field = NULL;
}

size_t svp_variant_common_memory(const svp_blur *b)
{
    size_t bytes = sizeof *b;
    const size_t n = (size_t)b->width * b->height;
    if (b->kernel) bytes += (size_t)b->kernel->width * b->kernel->height * sizeof(double);
    if (b->work_r_image) bytes += n * sizeof(double);
    return bytes;
}

/* What release_buffers frees: the accumulators, the adjoint's frame, the row blocks and the
 * float state (a copy's whole own memory). */
static size_t buffers_memory(const svp_blur *b, const svp_variant_data *v, size_t spectrum)
{
    const svp_frame *f = &b->frame;
    size_t bytes = 0;
    if (v->acc) bytes += spectrum;
    if (v->spec2) bytes += spectrum;
    if (v->ext) bytes += (size_t)f->ny * f->nx * sizeof(double);
    if (v->row_on) bytes += (size_t)f->ny;
    if (v->blk) bytes += (size_t)v->blk_threads * 3 * SVP_FFT_BLOCK * v->block->bx * sizeof(double);
    if (v->otf_f) /* float spectra */
        bytes += (size_t)v->n_terms * (v->f_real ? spectrum / 4 : spectrum / 2);
    if (v->fr_f) /* float frame rows, a term's spectrum and the accumulator */
        bytes += (size_t)v->rows_max * f->nx * sizeof(float) + spectrum;
    return bytes + tails_memory(b, v);
}

static size_t variant_memory(const svp_blur *b)
{
    size_t bytes = svp_variant_common_memory(b);
    const size_t n = (size_t)b->width * b->height;
    const svp_variant_data *v = b->variant;
    const size_t spectrum = (size_t)b->frame.ny * b->frame.ncx * sizeof(fftw_complex);
    bytes += svp_frame_memory(&b->frame) /* geometry; counts one spectrum (work_c) */;
    if (!v) return bytes;
    bytes += buffers_memory(b, v, spectrum);
    if (v->borrowed) return bytes; /* the rest is the original's */
    if (!v->double_gone)
        bytes += (size_t)v->n_terms * (v->otf_re ? spectrum / 2 : spectrum); /* spectra */
    bytes += n * sizeof(double) * ((v->scale != NULL) + (v->alpha != NULL));
    bytes += (size_t)(b->width + b->height) * (sizeof(int) + sizeof(double));
    if (v->coef) bytes += (size_t)v->n_terms * v->gx * v->gy * sizeof(double);
    if (v->start) bytes += (size_t)v->n_terms * sizeof(int);
    if (v->wx)
        bytes += (size_t)(b->kind == SVP_BLUR_TENT ? v->gx : v->n_terms * v->gy) * b->frame.nx *
                 sizeof(double);
    if (v->wy) bytes += (size_t)v->gy * b->frame.ny * sizeof(double);
    if (v->ly0) bytes += (size_t)b->frame.ny * (sizeof(int) + sizeof(double));
    bytes += (size_t)v->n_terms;
    return bytes;
}

const svp_blur_ops svp_variant_common_ops = {"space-variant (being built)", NULL, NULL,
                                             svp_variant_common_memory,
                                             svp_variant_common_release, NULL};

static const double *variant_halo_map(const svp_blur *b)
{
    return b->variant ? b->variant->alpha : NULL;
}

const svp_blur_ops svp_tent_ops = {"tent",         variant_apply,   variant_adjoint,
                                   variant_memory, variant_release, variant_halo_map};
const svp_blur_ops svp_lowrank_ops = {"low rank",     variant_apply,   variant_adjoint,
                                      variant_memory, variant_release, variant_halo_map};
const svp_blur_ops svp_regions_ops = {"regions",      variant_apply,   variant_adjoint,
                                      variant_memory, variant_release, variant_halo_map};

int svp_variant_term(const svp_blur *b, int r, const double **re, const fftw_complex **c,
                     const double **coef)
{
    *re = NULL;
    *c = NULL;
    *coef = NULL;
    if (!b || !b->variant || r < 0 || r >= b->variant->n_terms) return 0;
    const svp_variant_data *v = b->variant;
    if (v->otf_re) *re = v->otf_re[r];
    if (v->otf) *c = v->otf[r];
    if (v->coef) *coef = v->coef + (size_t)r * v->gx * v->gy;
    return v->n_terms;
}

int svp_variant_real_spectra(const svp_blur *b)
{
    return b && b->variant && b->variant->otf_re != NULL;
}

int svp_blur_is_variant(const svp_blur *b) { return b && b->kind != SVP_BLUR_INVARIANT; }

const double *svp_blur_halo_map(const svp_blur *b)
{
    if (!b) return NULL;
    return b->ops->halo_map ? b->ops->halo_map(b) : NULL;
}

svp_status svp_blur_psf_at(const svp_blur *b, double x, double y, svp_psf *out)
{
    if (!b || !out) return svp_fail(SVP_ERR_INVALID, "svp_blur_psf_at: NULL argument");
    if (b->field) return svp_psf_field_at(b->field, x, y, out);
    if (!b->has_model)
        return svp_fail(SVP_ERR_UNSUPPORTED,
                        "the operator was built from a sampled kernel: it has no PSF model");
    *out = b->psf;
    return SVP_OK;
}

/* ---- construction ------------------------------------------------------------------------ */

static svp_status check_options(const svp_variant_options *o)
{
    if (o->representation != SVP_VARIANT_TENT && o->representation != SVP_VARIANT_LOWRANK &&
        o->representation != SVP_VARIANT_AUTO && o->representation != SVP_VARIANT_REGIONS)
        return svp_fail(SVP_ERR_INVALID,
                        "variant representation %d is not tent (0), low rank (1), automatic "
                        "(2) or regions (3)",
                        (int)o->representation);
    if (o->representation == SVP_VARIANT_AUTO && (!(o->tolerance > 0) || !isfinite(o->tolerance)))
        return svp_fail(SVP_ERR_INVALID, "operator tolerance must be > 0, got %g", o->tolerance);
    if (!(o->max_memory >= 0) || !isfinite(o->max_memory))
        return svp_fail(SVP_ERR_INVALID, "memory limit must be >= 0 bytes, got %g",
                        o->max_memory);
    if (o->grid_x < 1 || o->grid_y < 1 || o->grid_x > 64 || o->grid_y > 64)
        return svp_fail(SVP_ERR_INVALID, "tent node grid %d x %d: each side must be in 1..64",
                        o->grid_x, o->grid_y);
    if (o->samples_x < 1 || o->samples_y < 1 || o->samples_x > 64 || o->samples_y > 64)
        return svp_fail(SVP_ERR_INVALID, "low-rank sample grid %d x %d: each side must be in 1..64",
                        o->samples_x, o->samples_y);
    if (o->representation == SVP_VARIANT_LOWRANK &&
        (o->rank < 1 || o->rank > o->samples_x * o->samples_y))
        return svp_fail(SVP_ERR_INVALID,
                        "low rank %d: must be in 1..%d (the number of sampled PSFs, %d x %d)",
                        o->rank, o->samples_x * o->samples_y, o->samples_x, o->samples_y);
    if (!(o->support >= 0) || !isfinite(o->support))
        return svp_fail(SVP_ERR_INVALID, "variant kernel support must be >= 0 pixels, got %g",
                        o->support);
    if (!(o->tail_tol >= 0 && o->tail_tol < 1))
        return svp_fail(SVP_ERR_INVALID, "tail tolerance must be in [0, 1), got %g", o->tail_tol);
    return SVP_OK;
}

/* The common part of every space-variant kind: geometry checks, the field's copy, the kernel
 * radius, the central PSF as the invariant stand-in, per-pixel halo. */
svp_status svp_variant_begin(const svp_psf_field *field, int width, int height,
                             svp_boundary boundary, double support, svp_blur_kind kind,
                             svp_blur **out, int *rx, int *ry, double *support_used)
{
    *out = NULL;
    if (!field) return svp_fail(SVP_ERR_INVALID, "PSF field is NULL");
    SVP_CHECK(svp_blur_check_geometry(width, height, boundary));
    if (field->width != 0 && (field->width != width || field->height != height))
        return svp_fail(SVP_ERR_SIZE,
                        "the PSF field is for a %d x %d image, the operator for "
                        "%d x %d",
                        field->width, field->height, width, height);
    if (!(support >= 0) || !isfinite(support))
        return svp_fail(SVP_ERR_INVALID, "kernel support must be >= 0 pixels, got %g", support);
    double sup = support > 0 ? support : svp_psf_field_base(field)->support;
    /* as svp_blur_new: every offset that joins two pixels, or the support radius */
    *rx = width - 1;
    *ry = height - 1;
    if (sup > 0) *rx = *ry = (int)ceil(sup);
    *support_used = sup;

    svp_blur *b = calloc(1, sizeof *b);
    if (!b) return svp_fail(SVP_ERR_NOMEM, "out of memory for a blur operator");
    b->kind = kind;
    /* the exact operator's constructor (exact.c) puts its own table in place */
    b->ops = kind == SVP_BLUR_TENT      ? &svp_tent_ops
             : kind == SVP_BLUR_LOWRANK ? &svp_lowrank_ops
                                        : &svp_variant_common_ops;
    b->width = width;
    b->height = height;
    b->boundary = boundary;
    svp_status st = svp_psf_field_copy(field, &b->field);
    if (st == SVP_OK) st = svp_psf_field_at(field, 0.5 * (width - 1), 0.5 * (height - 1), &b->psf);
    if (st == SVP_OK) {
        b->psf.support = sup;
        b->has_model = 1;
        b->halo = b->psf.halo;
        b->kcx = *rx;
        b->kcy = *ry;
        st = svp_psf_render(&b->psf, *rx, *ry, &b->kernel);
    }
    if (st == SVP_OK) {
        b->work_r_image = svp_alloc((size_t)width * height * sizeof(double));
        if (!b->work_r_image) st = svp_fail(SVP_ERR_NOMEM, "out of memory for blur buffers");
    }
    if (st != SVP_OK) {
        svp_blur_free(b);
        return st;
    }
    *out = b;
    return SVP_OK;
}

/* Per-pixel halo fraction; NULL when it is zero everywhere. */
svp_status svp_variant_halo_map(const svp_psf_field *field, int width, int height, double **alpha)
{
    *alpha = NULL;
    const size_t n = (size_t)width * height;
    double *a = svp_alloc(n * sizeof(double));
    if (!a) return svp_fail(SVP_ERR_NOMEM, "out of memory for a halo map");
    int any = 0;
    svp_status st = SVP_OK;
    for (int y = 0; y < height && st == SVP_OK; y++)
        for (int x = 0; x < width; x++) {
            double p[SVP_FIELD_NPARAM];
            st = svp_psf_field_params_at(field, x, y, p);
            if (st != SVP_OK) break;
            a[(size_t)y * width + x] = p[SVP_FIELD_HALO];
            any |= p[SVP_FIELD_HALO] != 0;
        }
    if (st != SVP_OK || !any) {
        svp_free(a);
        return st;
    }
    *alpha = a;
    return SVP_OK;
}

/* Renders the field's PSF at (x, y) with the operator's support. */
static svp_status render_at(const svp_blur *b, double x, double y, double support, int rx, int ry,
                            svp_image **kernel)
{
    svp_psf psf;
    SVP_CHECK(svp_psf_field_at(b->field, x, y, &psf));
    psf.support = support;
    svp_status st = svp_psf_render(&psf, rx, ry, kernel);
    if (st != SVP_OK)
        return svp_fail_context(st, "PSF of the field at (%g, %g) (fwhm %g, beta %g)", x, y,
                                psf.fwhm, psf.beta);
    return SVP_OK;
}

/* OTF of a kernel on the shared frame, scaled by 1 / (nx ny) (the inverse FFT is unscaled). */
static svp_status term_otf(svp_blur *b, const svp_image *kernel, int rx, int ry, fftw_complex **otf)
{
    svp_frame *f = &b->frame;
    *otf = svp_alloc((size_t)f->ny * f->ncx * sizeof(fftw_complex));
    if (!*otf) return svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d spectrum", f->nx, f->ny);
    f->otf = *otf; /* svp_frame_set_kernel writes into the frame's OTF slot */
    svp_status st = svp_frame_set_kernel(f, kernel, rx, ry, b->boundary);
    f->otf = NULL;
    if (st != SVP_OK) return st;
    const size_t ns = (size_t)f->ny * f->ncx;
    const double inv = 1.0 / ((double)f->nx * f->ny);
    for (size_t i = 0; i < ns; i++) (*otf)[i] *= inv;
    return SVP_OK;
}

/* Row windows of the tent nodes (see svp_variant_data.pruned): node row j's weighted input is
 * non-zero in the frame rows whose source image row has hat_j > 0, a cyclic interval; all
 * nodes use the longest one's length. Pruning is kept when it skips at least 30 % of the row
 * transforms. */
static svp_status setup_pruning(svp_blur *b)
{
    svp_variant_data *v = b->variant;
    const svp_frame *f = &b->frame;
    const int ny = f->ny, K = v->gx * v->gy;
    int *first = malloc((size_t)v->gy * sizeof(int));
    char *on = malloc((size_t)ny);
    if (!first || !on) {
        free(first);
        free(on);
        return svp_fail(SVP_ERR_NOMEM, "out of memory for node windows");
    }
    int rows = 0;
    for (int j = 0; j < v->gy; j++) {
        int any = 0;
        for (int fy = 0; fy < ny; fy++) {
            const int y = f->src_y[fy];
            on[fy] = y >= 0 && hat(v->iy0, v->fy, j, y) != 0;
            any |= on[fy];
        }
        /* the longest cyclic run of rows that are off; the window starts right after it */
        int best = 0, best_end = 0, run = 0;
        for (int t = 0; t < 2 * ny; t++) {
            if (!on[t % ny]) {
                run++;
                if (run > best && run <= ny) {
                    best = run;
                    best_end = t % ny;
                }
            } else {
                run = 0;
            }
        }
        first[j] = any ? (best_end + 1) % ny : 0;
        const int len = any ? ny - best : 1;
        if (len > rows) rows = len;
    }
    free(on);
    svp_status st = SVP_OK;
    if (rows <= 0.7 * ny) {
        v->start = malloc((size_t)K * sizeof(int));
        if (!v->start) st = svp_fail(SVP_ERR_NOMEM, "out of memory for node windows");
        for (int k = 0; st == SVP_OK && k < K; k++) v->start[k] = first[k / v->gx];
        v->pruned = st == SVP_OK;
        v->rows = rows;
    }
    free(first);
    return st;
}

/* The weight tables of the apply and the adjoint (see svp_variant_data.wx), their buffers
 * (the adjoint's frame accumulator ext, a pair's second spectrum) and the transforms' plans,
 * after the terms are built. */
static svp_status setup_fill(svp_blur *b)
{
    svp_variant_data *v = b->variant;
    const svp_frame *f = &b->frame;
    const int nx = f->nx, ny = f->ny, gx = v->gx, gy = v->gy, K = v->n_terms;
    const int tent = b->kind == SVP_BLUR_TENT;
    const size_t nwx = tent ? (size_t)gx * nx : (size_t)K * gy * nx;
    v->ext = svp_alloc((size_t)ny * nx * sizeof(double));
    SVP_CHECK(svp_fft_block_get(nx, &v->block));
    SVP_CHECK(svp_fft_pruned_get(ny, nx, 0, &v->cols)); /* the column plans only */
    if (K > 1) {
        v->spec2 = svp_alloc((size_t)ny * f->ncx * sizeof(fftw_complex));
        if (!v->spec2) return svp_fail(SVP_ERR_NOMEM, "out of memory for the operator's buffers");
    }
    v->wx = malloc(nwx * sizeof(double));
    v->unit = calloc((size_t)K, 1);
    v->row_on = calloc((size_t)ny, 1);
    if (tent)
        v->wy = malloc((size_t)gy * ny * sizeof(double));
    else {
        v->ly0 = malloc((size_t)ny * sizeof(int));
        v->lty = malloc((size_t)ny * sizeof(double));
    }
    if (!v->ext || !v->wx || !v->unit || !v->row_on || (tent ? !v->wy : !v->ly0 || !v->lty))
        return svp_fail(SVP_ERR_NOMEM, "out of memory for the operator's weight tables");
    if (tent) {
        for (int i = 0; i < gx; i++)
            for (int q = 0; q < nx; q++) {
                const int x = f->src_x[q];
                v->wx[(size_t)i * nx + q] = x >= 0 ? hat(v->ix0, v->fx, i, x) : 0.0;
            }
        for (int j = 0; j < gy; j++)
            for (int fy = 0; fy < ny; fy++) {
                const int y = f->src_y[fy];
                v->wy[(size_t)j * ny + fy] = y >= 0 ? hat(v->iy0, v->fy, j, y) : 0.0;
            }
        v->unit[0] = K == 1;
        return SVP_OK;
    }
    for (int fy = 0; fy < ny; fy++) {
        const int y = f->src_y[fy];
        v->ly0[fy] = y >= 0 ? v->iy0[y] : -1;
        v->lty[fy] = y >= 0 ? v->fy[y] : 0.0;
    }
    const size_t S = (size_t)gx * gy;
    for (int r = 0; r < K; r++) {
        const double *cr = v->coef + (size_t)r * S;
        int unit = 1;
        for (size_t j = 0; j < S; j++) unit &= cr[j] == 1.0;
        v->unit[r] = (char)unit;
        for (int j = 0; j < gy; j++)
            for (int q = 0; q < nx; q++) {
                const int x = f->src_x[q];
                double c = 0;
                if (x >= 0) {
                    const int i0 = v->ix0[x], i1 = i0 + 1 < gx ? i0 + 1 : i0;
                    const double tx = v->fx[x];
                    c = (1 - tx) * cr[(size_t)j * gx + i0] + tx * cr[(size_t)j * gx + i1];
                }
                v->wx[((size_t)r * gy + j) * nx + q] = c;
            }
    }
    return SVP_OK;
}

static svp_status build_tent(svp_blur *b, const svp_variant_options *o, double support, int rx,
                             int ry)
{
    svp_variant_data *v = b->variant;
    const int K = v->gx * v->gy;
    v->otf = calloc((size_t)K, sizeof *v->otf);
    if (!v->otf) return svp_fail(SVP_ERR_NOMEM, "out of memory for %d node spectra", K);
    v->n_terms = K;
    SVP_CHECK(setup_pruning(b));
    for (int k = 0; k < K; k++) {
        const int i = k % v->gx, j = k / v->gx;
        svp_image *kernel = NULL;
        SVP_CHECK(render_at(b, node_pos(i, v->gx, b->width), node_pos(j, v->gy, b->height), support,
                            rx, ry, &kernel));
        svp_status st = term_otf(b, kernel, rx, ry, &v->otf[k]);
        svp_image_free(kernel);
        SVP_CHECK(st);
        if (v->pruned && v->start[k] != 0) {
            /* the rows start[k] .. moved to the top: multiply by e^{−2πi ky start / ny} */
            const svp_frame *f = &b->frame;
            for (int ky = 0; ky < f->ny; ky++) {
                const double a = -2.0 * M_PI * (double)((long)ky * v->start[k] % f->ny) / f->ny;
                const double complex ph = cos(a) + I * sin(a);
                fftw_complex *row = v->otf[k] + (size_t)ky * f->ncx;
                for (int kx = 0; kx < f->ncx; kx++) row[kx] *= ph;
            }
        }
        SVP_CHECK(svp_report_progress(o->progress, o->progress_user, (k + 1.0) / K));
    }
    return SVP_OK;
}

/* Renormalised low rank: the expansion's flux for a point source at each pixel, Σ_r c_r(x)
 * sum(e_r) (flux[r]), bilinear in the samples like c_r; dividing by it gives every source unit
 * flux. */
static svp_status lowrank_renormalise(svp_blur *b, int R, const double *flux)
{
    svp_variant_data *v = b->variant;
    const int S = v->gx * v->gy;
    svp_status st = SVP_OK;
        /* flux of the expansion for a point source at each pixel: Σ_r c_r(x) sum(e_r), bilinear
         * in the samples like c_r; dividing by it gives every source unit flux. */
        const size_t n = (size_t)b->width * b->height;
        double *fs = malloc((size_t)S * sizeof(double));
        if (!v->scale) v->scale = svp_alloc(n * sizeof(double));
        if (!fs || !v->scale) {
            free(fs);
            st = svp_fail(SVP_ERR_NOMEM, "out of memory for the flux map");
            return st;
        }
        for (int j = 0; j < S; j++) {
            double acc = 0;
            for (int r = 0; r < R; r++) acc += v->coef[(size_t)r * S + j] * flux[r];
            fs[j] = acc;
        }
        for (int y = 0; y < b->height && st == SVP_OK; y++) {
            const int j0 = v->iy0[y], j1 = j0 + 1 < v->gy ? j0 + 1 : j0;
            const double ty = v->fy[y];
            for (int x = 0; x < b->width; x++) {
                const int i0 = v->ix0[x], i1 = i0 + 1 < v->gx ? i0 + 1 : i0;
                const double tx = v->fx[x];
                double F = (1 - ty) * ((1 - tx) * fs[j0 * v->gx + i0] + tx * fs[j0 * v->gx + i1]) +
                           ty * ((1 - tx) * fs[j1 * v->gx + i0] + tx * fs[j1 * v->gx + i1]);
                if (!(F > 1e-3)) {
                    st = svp_fail(SVP_ERR_NUMERIC,
                                  "low rank %d: the expansion's flux at pixel (%d, %d) is %g; "
                                  "raise the rank",
                                  R, x, y, F);
                    break;
                }
                const size_t i = (size_t)y * b->width + x;
                v->scale[i] = (v->alpha ? 1.0 - v->alpha[i] : 1.0) / F;
            }
        }
        free(fs);
        /* Mean-centred: the eigen-PSFs after the mean sum to zero, so the flux is 1 up to
         * round-off; without a halo the scale is then 1 to round-off and is dropped (it would
         * cost a pass over the image in every application and adjoint). */
        if (st == SVP_OK && !v->alpha) {
            double dev = 0;
            for (size_t i = 0; i < n; i++) dev = fmax(dev, fabs(v->scale[i] - 1.0));
            if (dev <= 1e-13) {
                svp_free(v->scale);
                v->scale = NULL;
            }
        }
    return st;
}

/* Low rank. Plain: a = [K_1 .. K_S] = U Σ Vᵀ, e_r = u_r, c_r(j) = σ_r v_jr. Mean-centred (the
 * default): e_0 = K̄ (the mean kernel, c_0 = 1) and the SVD of the deviations K_j − K̄ gives
 * e_1 .. e_{R−1}; the deviations sum to zero, so every e_r (r >= 1) does too and each source
 * keeps unit flux at every rank. */
static svp_status build_lowrank(svp_blur *b, const svp_variant_options *o, double support, int rx,
                                int ry)
{
    svp_variant_data *v = b->variant;
    const int S = v->gx * v->gy, R = o->rank, centred = o->lowrank_mean != 0;
    const int kw = 2 * rx + 1, kh = 2 * ry + 1;
    const size_t m = (size_t)kw * kh;
    if (m > (size_t)INT32_MAX / 2 || m * (size_t)S > ((size_t)1 << 27))
        return svp_fail(SVP_ERR_NOMEM,
                        "low rank: %d sampled %d x %d kernels are too large for the SVD; set a "
                        "smaller support or fewer samples",
                        S, kw, kh);
    const int mn = (int)m < S ? (int)m : S;
    if (R > mn + centred)
        return svp_fail(SVP_ERR_INVALID, "low rank %d exceeds min(kernel size %zu, samples %d)", R,
                        m, S);
    svp_status st = SVP_OK;
    double *a = malloc(m * (size_t)S * sizeof(double)); /* column j: kernel of sample j */
    double *mean = centred ? calloc(m, sizeof(double)) : NULL;
    double *u = NULL, *sv = malloc((size_t)mn * sizeof(double));
    double *vt = malloc((size_t)mn * S * sizeof(double));
    double *flux = calloc((size_t)R, sizeof(double));
    if (!a || !sv || !vt || !flux || (centred && !mean)) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory for %d sampled %d x %d kernels", S, kw, kh);
        goto cleanup;
    }
    for (int j = 0; j < S && st == SVP_OK; j++) {
        svp_image *kernel = NULL;
        st = render_at(b, node_pos(j % v->gx, v->gx, b->width),
                       node_pos(j / v->gx, v->gy, b->height), support, rx, ry, &kernel);
        if (st != SVP_OK) break;
        memcpy(a + m * (size_t)j, kernel->data, m * sizeof(double));
        svp_image_free(kernel);
        st = svp_report_progress(o->progress, o->progress_user, 0.5 * (j + 1.0) / S);
    }
    if (st != SVP_OK) goto cleanup;
    /* Point-symmetric samples (every Moffat and Gaussian PSF): k(d) = k(−d) is k[i] = k[m − 1 − i]
     * on the (2 rx + 1) x (2 ry + 1) grid. Their eigen-PSFs of non-zero singular value are
     * point-symmetric too; those of (numerically) zero singular value are arbitrary directions,
     * and are projected onto the symmetric ones below: then every term's OTF is real
     * (svp_variant_data.otf_re), a change of the operator within round-off of σ_r. */
    int symmetric = 1;
    for (int j = 0; j < S && symmetric; j++) {
        const double *k = a + m * (size_t)j, peak = svp_max(k, m); /* kernels are >= 0 */
        for (size_t i = 0; i < m / 2 && symmetric; i++)
            symmetric = fabs(k[i] - k[m - 1 - i]) <= 1e-13 * peak;
    }
    if (centred) {
        for (int j = 0; j < S; j++)
            for (size_t i = 0; i < m; i++) mean[i] += a[m * (size_t)j + i];
        for (size_t i = 0; i < m; i++) mean[i] /= S;
        for (int j = 0; j < S; j++)
            for (size_t i = 0; i < m; i++) a[m * (size_t)j + i] -= mean[i];
    }
    /* a = U Σ Vᵀ; with m >= S the left vectors overwrite a ('O'), else they go to u. */
    lapack_int info;
    const double *uvec;
    if ((int)m >= S) {
        double dummy = 0;
        info = LAPACKE_dgesdd(LAPACK_COL_MAJOR, 'O', (lapack_int)m, S, a, (lapack_int)m, sv, &dummy,
                              1, vt, mn);
        uvec = a;
    } else {
        u = malloc(m * (size_t)mn * sizeof(double));
        if (!u) {
            st = svp_fail(SVP_ERR_NOMEM, "out of memory for the SVD");
            goto cleanup;
        }
        info = LAPACKE_dgesdd(LAPACK_COL_MAJOR, 'S', (lapack_int)m, S, a, (lapack_int)m, sv, u,
                              (lapack_int)m, vt, mn);
        uvec = u;
    }
    if (info != 0) {
        st = svp_fail(SVP_ERR_NUMERIC,
                      "low rank: the SVD of the sampled PSFs failed (LAPACK "
                      "dgesdd info %d)",
                      (int)info);
        goto cleanup;
    }
    v->coef = malloc((size_t)R * S * sizeof(double));
    v->otf = calloc((size_t)R, sizeof *v->otf);
    if (!v->coef || !v->otf) {
        st = svp_fail(SVP_ERR_NOMEM, "out of memory for %d eigen-PSFs", R);
        goto cleanup;
    }
    v->n_terms = R;
    for (int r = 0; r < R && st == SVP_OK; r++) {
        const int q = r - centred; /* singular triplet of term r (−1: the mean) */
        for (int j = 0; j < S; j++)
            v->coef[(size_t)r * S + j] = q < 0 ? 1.0 : sv[q] * vt[q + (size_t)j * mn];
        double *e = q < 0 ? mean : (double *)(uvec + m * (size_t)q);
        if (symmetric)
            for (size_t i = 0; i < m / 2; i++) e[i] = e[m - 1 - i] = 0.5 * (e[i] + e[m - 1 - i]);
        const svp_image eigen = {kw, kh, e};
        flux[r] = svp_sum(eigen.data, m);
        st = term_otf(b, &eigen, rx, ry, &v->otf[r]);
        if (st == SVP_OK)
            st = svp_report_progress(o->progress, o->progress_user, 0.5 + 0.5 * (r + 1.0) / R);
    }
    if (st != SVP_OK) goto cleanup;
    if (o->renormalise) st = lowrank_renormalise(b, R, flux);
cleanup:
    free(a);
    free(mean);
    free(u);
    free(sv);
    free(vt);
    free(flux);
    return st;
}

/* The operator's frame for kernel radii rx, ry, and the buffers sized by it. */
static svp_status frame_buffers(svp_blur *b, int rx, int ry)
{
    svp_variant_data *v = b->variant;
    SVP_CHECK(svp_frame_init(&b->frame, b->width, b->height, rx, ry, b->boundary));
    const size_t ns = (size_t)b->frame.ny * b->frame.ncx;
    b->work_c = svp_alloc(ns * sizeof(fftw_complex));
    v->acc = svp_alloc(ns * sizeof(fftw_complex));
    if (!b->work_c || !v->acc) return svp_fail(SVP_ERR_NOMEM, "out of memory for blur buffers");
    return SVP_OK;
}

/* Term r's whole kernel into k (kw x kh, centre rx, ry) and *scale, its ℓ1 norm times its
 * largest |weight|: what one source's light through that term can weigh. */
typedef svp_status (*term_kernel_fn)(void *ctx, int r, svp_image *k, double *scale);

/* The far tail on a coarse grid (svp_variant_options.tail_tol) for the R terms `make` gives:
 * the split (s, r0) whose estimated error, summed over the terms, is within tol at the least
 * cost (svp_tail_pick; a term's estimate per unit of its ℓ1 norm, times its scale: the light
 * one pixel's source sends to the wrong place) and the frame for the cores (radius 2 r0; the
 * builders then give each term its tail and core with term_tail); none cheaper within tol:
 * the plain frame. */
static svp_status tails_frame(svp_blur *b, int R, int rx, int ry, double tol, term_kernel_fn make,
                              void *ctx)
{
    svp_variant_data *v = b->variant;
    const int w = b->width, h = b->height, n = svp_tail_n_splits();
    double *sums = calloc((size_t)2 * n, sizeof *sums), *one = sums + n, scale;
    svp_image *k = NULL;
    svp_status st = sums ? svp_image_new(2 * rx + 1, 2 * ry + 1, &k)
                         : svp_fail(SVP_ERR_NOMEM, "out of memory for the tail's estimate");
    for (int r = 0; r < R && st == SVP_OK; r++) {
        st = make(ctx, r, k, &scale);
        if (st == SVP_OK) st = svp_tail_split_sums(k, rx, ry, w, h, 0, one);
        for (int i = 0; i < n && st == SVP_OK; i++) sums[i] += one[i] * scale;
    }
    int nx, ny, s = 0, r0 = 0;
    if (st == SVP_OK) st = svp_frame_size(w, h, rx, ry, b->boundary, &nx, &ny);
    if (st == SVP_OK)
        st = svp_tail_pick(k, rx, ry, w, h, 0, sums, tol, nx, ny, &s, &r0, &v->tail_err);
    if (st == SVP_OK && s > 0) {
        v->tails = calloc((size_t)R, sizeof *v->tails);
        v->tail_in = svp_alloc((size_t)w * h * sizeof(double));
        if (!v->tails || !v->tail_in)
            st = svp_fail(SVP_ERR_NOMEM, "out of memory for the operator's tails");
    }
    svp_image_free(k);
    free(sums);
    if (st != SVP_OK) return st;
    v->tail_s = s;
    v->tail_r0 = r0;
    const int r1 = 2 * r0;
    return frame_buffers(b, s > 0 && r1 < rx ? r1 : rx, s > 0 && r1 < ry ? r1 : ry);
}

/* A region term's kernel for tails_frame: its PSF rendered whole, scaled by its largest
 * weight. */
typedef struct region_term_ctx {
    const svp_region_terms *t;
    const svp_variant_data *v;
    double support;
    int rx, ry;
    size_t n; /* pixels of a weight map */
} region_term_ctx;

static svp_status region_term_kernel(void *ctx, int r, svp_image *k, double *scale)
{
    const region_term_ctx *c = ctx;
    svp_psf psf = c->t->psf[r];
    psf.support = c->support;
    svp_image *kernel = NULL;
    SVP_CHECK(svp_psf_render(&psf, c->rx, c->ry, &kernel));
    memcpy(k->data, kernel->data, (size_t)k->width * k->height * sizeof(double));
    svp_image_free(kernel);
    double l1 = 0, cmax = 0;
    for (size_t i = 0; i < (size_t)k->width * k->height; i++) l1 += fabs(k->data[i]);
    const double *wr = c->v->coef + (size_t)r * c->n;
    for (size_t i = 0; i < c->n; i++) cmax = fmax(cmax, fabs(wr[i]));
    *scale = l1 * cmax;
    return SVP_OK;
}

/* Term r's spectrum from its whole kernel (centre rx, ry): the kernel's, or with the far tail
 * on a coarse grid (tails_frame chose it) its tail on nodes (svp_tail_new) and its core's. */
static svp_status term_tail(svp_blur *b, const svp_image *kernel, int rx, int ry, int r,
                            fftw_complex **otf)
{
    svp_variant_data *v = b->variant;
    if (!v->tails) return term_otf(b, kernel, rx, ry, otf);
    SVP_CHECK(svp_tail_new(kernel, rx, ry, b->width, b->height, 0, v->tail_s, v->tail_r0,
                           v->tail_err, &v->tails[r]));
    svp_image *core = NULL;
    int cx, cy;
    SVP_CHECK(svp_tail_core(kernel, rx, ry, v->tail_r0, &core, &cx, &cy));
    const svp_status st = term_otf(b, core, cx, cy, otf);
    svp_image_free(core);
    return st;
}

/* Regions (regions.c): term k is used label k's normalised kernel with its weight map as the
 * coefficients at "samples" on every pixel (gx = width, gy = height: the bilinear weights
 * between samples are then 1 and 0, exact), so setup_fill makes the per-pixel tables. The
 * weights sum to 1 and every kernel to 1: unit flux per source, no renormalisation. given: the
 * terms the automatic choice made (K = 0: none), taken over. */
static svp_status build_regions(svp_blur *b, const svp_variant_options *o, double support,
                                int rx, int ry, svp_region_terms *given)
{
    svp_variant_data *v = b->variant;
    svp_region_terms t = *given; /* the chooser's (its weight maps smoothed once), or made here */
    memset(given, 0, sizeof *given);
    if (t.K == 0) SVP_CHECK(svp_region_terms_make(b->field, &t));
    svp_status st = SVP_OK;
    v->otf = calloc((size_t)t.K, sizeof *v->otf);
    if (!v->otf) st = svp_fail(SVP_ERR_NOMEM, "out of memory for %d region spectra", t.K);
    if (st == SVP_OK) {
        v->n_terms = t.K;
        v->coef = t.weight; /* coef[(r gy + y) gx + x] = weight[r N + y w + x] */
        t.weight = NULL;
        v->tail_pixel = 1;
    }
    if (st == SVP_OK && !b->frame.plan) { /* the far tail on a coarse grid, or the plain frame */
        region_term_ctx c = {&t, v, support, rx, ry, (size_t)b->width * b->height};
        st = tails_frame(b, t.K, rx, ry, o->tail_tol, region_term_kernel, &c);
    }
    for (int k = 0; k < t.K && st == SVP_OK; k++) {
        svp_psf psf = t.psf[k];
        svp_image *kernel = NULL;
        psf.support = support;
        st = svp_psf_render(&psf, rx, ry, &kernel);
        if (st != SVP_OK) {
            st = svp_fail_context(st, "PSF of region %d (fwhm %g, beta %g)", t.label[k], psf.fwhm,
                                  psf.beta);
            break;
        }
        st = term_tail(b, kernel, rx, ry, k, &v->otf[k]);
        svp_image_free(kernel);
        if (st == SVP_OK)
            st = svp_report_progress(o->progress, o->progress_user, (k + 1.0) / t.K);
    }
    svp_region_terms_free(&t);
    return st;
}

/* The sampled PSFs of the low-rank build: sample j at node (j mod gx, j / gx), support set. */
static svp_status sample_psfs(const svp_blur *b, double support, svp_psf *psf)
{
    const svp_variant_data *v = b->variant;
    for (int j = 0; j < v->gx * v->gy; j++) {
        const double x = node_pos(j % v->gx, v->gx, b->width);
        const double y = node_pos(j / v->gx, v->gy, b->height);
        SVP_CHECK(svp_psf_field_at(b->field, x, y, &psf[j]));
        psf[j].support = support;
        svp_status st = svp_psf_validate(&psf[j]);
        if (st != SVP_OK)
            return svp_fail_context(st, "PSF of the field at (%g, %g) (fwhm %g, beta %g)", x, y,
                                    psf[j].fwhm, psf[j].beta);
    }
    return SVP_OK;
}

/* Rows of the Gram build's row blocks, and at most this many bytes of per-chunk partial Gram
 * matrices. */
enum { GRAM_ROWS = 8 };
#define GRAM_PARTIAL_BYTES ((size_t)1 << 26)

size_t svp_lowrank_build_memory(int samples, int rank, int rx, int ry, int threads)
{
    const size_t kw = 2 * (size_t)rx + 1, kh = 2 * (size_t)ry + 1;
    const size_t half = ((size_t)ry + 1) * kw, S = (size_t)samples;
    size_t chunks = GRAM_PARTIAL_BYTES / (S * S * sizeof(double) + 1);
    if (chunks < 1) chunks = 1;
    if (chunks > 16) chunks = 16;
    return (size_t)threads * S * GRAM_ROWS * kw * sizeof(double) /* row blocks */
           + (chunks + 2) * S * S * sizeof(double)                /* Gram, partials, vectors */
           + (size_t)rank * half * sizeof(double) /* eigen-PSF folds (a half at most) */
           + ((size_t)threads * kw + kh) * sizeof(double); /* kernel rows, row sums */
}

/* g (S x S, column-major, lower triangle and diagonal) += Σ_p a_i[p] a_j[p] over the n pixels
 * of the S rows a_i (a[i] points at sample i's pixels; S a multiple of 4, rows beyond the
 * samples point at zeros). Tiles of 4 x 2 rows, pixels in chunks that stay in cache, four
 * pixels per vector lane set; the lanes are summed in a fixed order (deterministic). The tile's
 * eight accumulators are named one by one: held in an array, GCC keeps them in memory, which
 * made the loop three times slower. On x86-64 with GCC an AVX2 clone is chosen at run time
 * when the CPU has it (no FMA: C11 mode keeps products and sums apart). */
typedef double svp_v4d __attribute__((vector_size(32)));
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
__attribute__((target_clones("avx2", "default")))
#endif
static void gram_accumulate(const double *const *a, int S, size_t n, double *restrict g)
{
    enum { CHUNK = 512 };
    for (size_t p0 = 0; p0 < n; p0 += CHUNK) {
        const size_t pn = n - p0 < CHUNK ? n - p0 : CHUNK, pv = pn & ~(size_t)3;
        for (int i = 0; i < S; i += 4)
            for (int j = 0; j <= i + 2; j += 2) {
                const double *ai[4] = {a[i] + p0, a[i + 1] + p0, a[i + 2] + p0, a[i + 3] + p0};
                const double *aj[2] = {a[j] + p0, a[j + 1] + p0};
                svp_v4d c00 = {0}, c01 = {0}, c10 = {0}, c11 = {0}, c20 = {0}, c21 = {0},
                        c30 = {0}, c31 = {0};
                for (size_t p = 0; p < pv; p += 4) {
                    svp_v4d x0, x1, x2, x3, y0, y1;
                    memcpy(&x0, ai[0] + p, sizeof x0);
                    memcpy(&x1, ai[1] + p, sizeof x1);
                    memcpy(&x2, ai[2] + p, sizeof x2);
                    memcpy(&x3, ai[3] + p, sizeof x3);
                    memcpy(&y0, aj[0] + p, sizeof y0);
                    memcpy(&y1, aj[1] + p, sizeof y1);
                    c00 += x0 * y0;
                    c01 += x0 * y1;
                    c10 += x1 * y0;
                    c11 += x1 * y1;
                    c20 += x2 * y0;
                    c21 += x2 * y1;
                    c30 += x3 * y0;
                    c31 += x3 * y1;
                }
                const svp_v4d acc[4][2] = {{c00, c01}, {c10, c11}, {c20, c21}, {c30, c31}};
                for (int u = 0; u < 4; u++)
                    for (int w = 0; w < 2; w++) {
                        if (j + w > i + u) continue; /* above the diagonal */
                        double t = (acc[u][w][0] + acc[u][w][1]) + (acc[u][w][2] + acc[u][w][3]);
                        for (size_t p = pv; p < pn; p++) t += ai[u][p] * aj[w][p];
                        g[(size_t)(j + w) * S + (i + u)] += t;
                    }
            }
    }
}

/* The Gram build's state (build_lowrank_gram's stages): S samples, R terms (Q of them from
 * eigenvectors), kernels of radius rx, ry, of which a fold is rendered (gram_layout): sym 0
 * the rows 0 .. ry (point symmetry), sym 1 the quadrant dx, dy >= 0, sym 2 the octant
 * dx >= dy >= 0 (svp_psf_render_fold); hr = ry + 1 rows in each case, row t's pixels at
 * rowoff[t] .. rowoff[t + 1] − 1 of the n rendered; nblk blocks of GRAM_ROWS rows (at most bp
 * pixels), the pass-1 partial Gram matrices of `chunks` chunks (Sp x Sp each), and the arrays
 * named at gram_alloc and gram_layout (krow: a kernel row per thread, wx: its columns' frame
 * columns, rsum: the rows' sums, placed: the frame gram_otf places a kernel on). */
typedef struct gram_build {
    int S, Sp, R, Q, centred, rx, ry, kw, kh, hr, nblk, chunks, threads, sym;
    size_t m, n, bp;
    size_t *rowoff;
    int *wx;
    svp_psf *psf;
    double *blk, *part, *zeros, *cval, *psum, *g, *z, *lam, *sum, *zx, *eh, *flux, *krow, *rsum;
    double *placed;
    const double **rowp;
    lapack_int *isuppz;
} gram_build;

static void gram_free(gram_build *gb)
{
    free(gb->psf);
    free(gb->blk);
    free(gb->part);
    free(gb->rowp);
    free(gb->zeros);
    free(gb->cval);
    free(gb->psum);
    free(gb->g);
    free(gb->z);
    free(gb->lam);
    free(gb->sum);
    free(gb->zx);
    free(gb->eh);
    free(gb->flux);
    free(gb->krow);
    free(gb->rsum);
    svp_free(gb->placed);
    free(gb->wx);
    free(gb->rowoff);
    free(gb->isuppz);
}

static svp_status gram_alloc(gram_build *gb, const svp_variant_data *v,
                             const svp_variant_options *o, int rx, int ry)
{
    memset(gb, 0, sizeof *gb);
    const int S = gb->S = v->gx * v->gy, R = gb->R = o->rank;
    gb->centred = o->lowrank_mean != 0;
    gb->Q = R - gb->centred;
    gb->rx = rx;
    gb->ry = ry;
    gb->kw = 2 * rx + 1;
    gb->kh = 2 * ry + 1;
    gb->hr = ry + 1; /* rows rendered */
    gb->m = (size_t)gb->kw * gb->kh;
    gb->nblk = (gb->hr + GRAM_ROWS - 1) / GRAM_ROWS;
    gb->threads = omp_get_max_threads();
    int chunks = (int)(GRAM_PARTIAL_BYTES / ((size_t)S * S * sizeof(double) + 1));
    if (chunks < 1) chunks = 1;
    if (chunks > 16) chunks = 16;
    if (chunks > gb->nblk) chunks = gb->nblk;
    gb->chunks = chunks;
    if (gb->Q > S) return svp_fail(SVP_ERR_INVALID, "low rank %d exceeds the %d samples", R, S);
    const int Sp = gb->Sp = (S + 3) & ~3; /* padded to the Gram kernel's tiles */
    gb->psf = malloc((size_t)S * sizeof *gb->psf);
    gb->part = calloc((size_t)chunks * Sp * Sp, sizeof(double));
    gb->rowp = malloc((size_t)gb->threads * Sp * sizeof *gb->rowp);
    gb->cval = calloc((size_t)S, sizeof(double));
    gb->psum = calloc((size_t)gb->nblk * S, sizeof(double));
    gb->g = malloc((size_t)S * S * sizeof(double));
    gb->z = malloc((size_t)S * S * sizeof(double));
    gb->lam = malloc((size_t)S * sizeof(double));
    gb->sum = calloc((size_t)S, sizeof(double));
    gb->zx = malloc((size_t)S * (R + 1) * sizeof(double));
    gb->flux = calloc((size_t)R, sizeof(double));
    gb->isuppz = malloc(2 * (size_t)S * sizeof(lapack_int));
    gb->rowoff = malloc((size_t)(gb->hr + 1) * sizeof *gb->rowoff);
    gb->krow = malloc((size_t)gb->threads * gb->kw * sizeof(double));
    gb->rsum = malloc((size_t)gb->kh * sizeof(double));
    gb->wx = malloc((size_t)gb->kw * sizeof(int));
    if (!gb->psf || !gb->part || !gb->rowp || !gb->cval || !gb->psum || !gb->g || !gb->z ||
        !gb->lam || !gb->sum || !gb->zx || !gb->flux || !gb->isuppz || !gb->rowoff || !gb->krow ||
        !gb->rsum || !gb->wx)
        return svp_fail(SVP_ERR_NOMEM,
                        "out of memory for the low-rank build (%d samples of %d x %d pixels)", S,
                        gb->kw, gb->kh);
    return SVP_OK;
}

/* The fold the samples share (the lowest svp_psf_symmetry; the octant needs rx = ry; half = 1:
 * point symmetry only, the tests' reference), its rows' offsets and the arrays sized by it: the
 * row blocks, the eigen-PSFs' folds (eh, term r at eh + r n). */
static svp_status gram_layout(gram_build *gb, int half)
{
    int sym = half ? 0 : 2;
    for (int j = 0; j < gb->S; j++) {
        const int s = svp_psf_symmetry(&gb->psf[j]);
        if (s < sym) sym = s;
    }
    if (sym == 2 && gb->rx != gb->ry) sym = 1;
    gb->sym = sym;
    gb->rowoff[0] = 0;
    for (int t = 0; t < gb->hr; t++)
        gb->rowoff[t + 1] = gb->rowoff[t] + (size_t)(sym == 0   ? gb->kw
                                                     : sym == 1 ? gb->rx + 1
                                                                : gb->rx + 1 - t);
    gb->n = gb->rowoff[gb->hr];
    gb->bp = 0;
    for (int y0 = 0; y0 < gb->hr; y0 += GRAM_ROWS) {
        const int y1 = y0 + GRAM_ROWS < gb->hr ? y0 + GRAM_ROWS : gb->hr;
        const size_t np = gb->rowoff[y1] - gb->rowoff[y0];
        if (np > gb->bp) gb->bp = np;
    }
    const int R = gb->R;
    gb->blk = malloc((size_t)gb->threads * gb->S * gb->bp * sizeof(double));
    gb->zeros = calloc(gb->bp, sizeof(double));
    gb->eh = malloc((size_t)(R > 0 ? R : 1) * gb->n * sizeof(double));
    if (!gb->blk || !gb->zeros || !gb->eh)
        return svp_fail(SVP_ERR_NOMEM,
                        "out of memory for the low-rank build (%d samples of %d x %d pixels)",
                        gb->S, gb->kw, gb->kh);
    return SVP_OK;
}

/* Rows y0 .. y0 + nr − 1 of sample j's fold, unnormalised, packed into out. */
static void gram_render(const gram_build *gb, int j, int y0, int nr, double *out)
{
    if (gb->sym)
        svp_psf_render_fold(&gb->psf[j], gb->rx, gb->sym == 2, y0, nr, out);
    else
        svp_psf_render_rows(&gb->psf[j], gb->rx, gb->ry, y0, nr, out);
}

/* A quadrant's or octant's rows y0 .. y0 + nr − 1 (packed in a): returns Σ w a over them, w the
 * number of kernel pixels each stands for, and scales a by √w (Σ_p w a_i a_j is then the plain
 * product). A row's first pixel is the centre (w 1) on row 0, else on the axis dx = 0 (quadrant,
 * w 2) or the diagonal (octant, w 4); the others lie on the axis dy = 0 on row 0 (w 2, 4), else
 * inside (w 4, 8). */
static double fold_weigh(const gram_build *gb, int y0, int nr, double *restrict a)
{
    const double oct = gb->sym == 2 ? 2 : 1;
    double acc = 0;
    for (int t = y0; t < y0 + nr; t++) {
        const size_t len = gb->rowoff[t + 1] - gb->rowoff[t];
        const double wf = t == 0 ? 1 : 2 * oct, wr = (t == 0 ? 2 : 4) * oct;
        double rest = 0;
        for (size_t i = 1; i < len; i++) rest += a[i];
        acc += wf * a[0] + wr * rest;
        const double sf = sqrt(wf), sr = sqrt(wr);
        a[0] *= sf;
        for (size_t i = 1; i < len; i++) a[i] *= sr;
        a += len;
    }
    return acc;
}

/* Pass 1: the raw Gram matrix (lower triangle, into g) and the kernels' sums. A fold's pixels
 * are weighted by fold_weigh. The rows 0 .. ry (sym 0): weight 2 on rows < ry and on row ry
 * left of the centre (a contiguous prefix of the rendered pixels), 1 at the centre, 0 right of
 * it: the chunks' partials hold the prefix's unweighted sums, the centre is added at the end.
 * Chunks and blocks are summed in a fixed order. */
static void gram_raw(gram_build *gb)
{
    const int S = gb->S, Sp = gb->Sp, rx = gb->rx, ry = gb->ry, kw = gb->kw, hr = gb->hr;
    const int nblk = gb->nblk, chunks = gb->chunks, sym = gb->sym;
    const size_t p2 = (size_t)ry * kw + rx; /* sym 0: pixels of weight 2 */
#pragma omp parallel for schedule(static, 1)
    for (int c = 0; c < chunks; c++) {
        double *a = gb->blk + (size_t)omp_get_thread_num() * S * gb->bp;
        const double **rows = gb->rowp + (size_t)omp_get_thread_num() * Sp;
        double *gc = gb->part + (size_t)c * Sp * Sp;
        for (int ib = c; ib < nblk; ib += chunks) {
            const int y0 = ib * GRAM_ROWS, nr = hr - y0 < GRAM_ROWS ? hr - y0 : GRAM_ROWS;
            const size_t p0 = gb->rowoff[y0], np = gb->rowoff[y0 + nr] - p0;
            size_t n2 = np;
            int centre = 0;
            if (!sym) {
                n2 = p2 > p0 ? (p2 - p0 < np ? p2 - p0 : np) : 0;
                centre = n2 < np && p0 + n2 == p2;
            }
            for (int j = 0; j < Sp; j++) rows[j] = j < S ? a + (size_t)j * np : gb->zeros;
            for (int j = 0; j < S; j++) {
                double *aj = a + (size_t)j * np;
                gram_render(gb, j, y0, nr, aj);
                double acc = 0;
                if (sym)
                    acc = fold_weigh(gb, y0, nr, aj);
                else {
                    for (size_t i = 0; i < n2; i++) acc += aj[i];
                    acc *= 2;
                    if (centre) {
                        acc += aj[n2];
                        gb->cval[j] = aj[n2];
                    }
                }
                gb->psum[(size_t)ib * S + j] = acc;
            }
            if (n2 > 0) gram_accumulate(rows, Sp, n2, gc);
        }
    }
    double *g = gb->g;
    memset(g, 0, (size_t)S * S * sizeof(double));
    for (int c = 0; c < chunks; c++)
        for (int j = 0; j < S; j++)
            for (int i = j; i < S; i++)
                g[(size_t)j * S + i] += gb->part[((size_t)c * Sp + j) * Sp + i];
    if (!sym)
        for (int j = 0; j < S; j++)
            for (int i = j; i < S; i++)
                g[(size_t)j * S + i] = 2 * g[(size_t)j * S + i] + gb->cval[i] * gb->cval[j];
    for (int ib = 0; ib < nblk; ib++)
        for (int j = 0; j < S; j++) gb->sum[j] += gb->psum[(size_t)ib * S + j];
}

/* The Gram matrix of the normalised (and, centred, mean-free) kernels, D G D then C G C, and
 * its eigen-decomposition (eigenvalues ascending in lam, vectors in z); v->kernel_norm2. */
static svp_status gram_eigen(gram_build *gb, svp_variant_data *v)
{
    const int S = gb->S;
    double *g = gb->g, *sum = gb->sum, *lam = gb->lam;
    for (int j = 0; j < S; j++)
        if (!(sum[j] > 0) || !isfinite(sum[j]))
            return svp_fail(SVP_ERR_NUMERIC, "PSF kernel has no flux on its %d x %d support",
                            gb->kw, gb->kh);
    /* normalise (D G D) and fill the upper triangle */
    for (int j = 0; j < S; j++)
        for (int i = j; i < S; i++) {
            const double x = g[(size_t)j * S + i] / (sum[i] * sum[j]);
            g[(size_t)j * S + i] = g[(size_t)i * S + j] = x;
        }
    v->kernel_norm2 = 0;
    for (int j = 0; j < S; j++) v->kernel_norm2 += g[(size_t)j * S + j];
    if (gb->centred) { /* C G C */
        double tot = 0;
        for (int i = 0; i < S; i++) {
            double r = 0;
            for (int j = 0; j < S; j++) r += g[(size_t)j * S + i];
            lam[i] = r / S; /* row means (scratch) */
            tot += r;
        }
        tot /= (double)S * S;
        for (int j = 0; j < S; j++)
            for (int i = 0; i < S; i++) g[(size_t)j * S + i] += tot - lam[i] - lam[j];
    }
    lapack_int found = 0;
    lapack_int info = LAPACKE_dsyevr(LAPACK_COL_MAJOR, 'V', 'A', 'L', S, g, S, 0, 0, 0, 0, 0.0,
                                     &found, lam, gb->z, S, gb->isuppz);
    if (info != 0 || found != S)
        return svp_fail(SVP_ERR_NUMERIC,
                        "low rank: the eigen-decomposition of the sampled PSFs' Gram matrix "
                        "failed (LAPACK dsyevr info %d)",
                        (int)info);
    return SVP_OK;
}

/* The eigenvalues (descending, v->eig), the coefficients (v->coef) and the combination weights
 * zx of pass 2: column 0 gives the mean (1 / (S s_j)), column 1 + q the q-th vector / (s_j σ_q);
 * lam then holds Σ_j z_jq / σ_q per term (the mean's share of a centred term). */
static svp_status gram_terms(gram_build *gb, svp_variant_data *v)
{
    const int S = gb->S, R = gb->R, Q = gb->Q, centred = gb->centred;
    v->eig = malloc((size_t)S * sizeof(double));
    v->coef = malloc((size_t)R * S * sizeof(double));
    v->otf = calloc((size_t)R, sizeof *v->otf);
    if (!v->eig || !v->coef || !v->otf)
        return svp_fail(SVP_ERR_NOMEM, "out of memory for %d eigen-PSFs", R);
    v->n_eig = S;
    for (int q = 0; q < S; q++) v->eig[q] = gb->lam[S - 1 - q];
    double *zsum = gb->lam, *zx = gb->zx;
    for (int j = 0; j < S; j++) zx[j] = 1.0 / ((double)S * gb->sum[j]);
    for (int q = 0; q < Q; q++) {
        const double *zq = gb->z + (size_t)(S - 1 - q) * S;
        const double l = v->eig[q], sg = l > 0 ? sqrt(l) : 1.0;
        double zs = 0;
        for (int j = 0; j < S; j++) {
            zx[(size_t)(1 + q) * S + j] = zq[j] / (gb->sum[j] * sg);
            v->coef[(size_t)(q + centred) * S + j] = l > 0 ? sg * zq[j] : zq[j];
            zs += zq[j] / sg;
        }
        zsum[q] = zs;
    }
    if (centred)
        for (int j = 0; j < S; j++) v->coef[j] = 1.0;
    v->n_terms = R;
    return SVP_OK;
}

/* Pass 2: the eigen-PSFs' folds E = A_raw zx (minus the mean times Σ z for centred terms) into
 * eh, term r's at eh + r n (the mean, centred, is term 0). */
static void gram_halves(gram_build *gb)
{
    const int S = gb->S, hr = gb->hr;
    const int cols = gb->Q + 1, centred = gb->centred;
    const int skip = centred ? 0 : 1; /* plain: the mean column is not stored */
#pragma omp parallel for schedule(static)
    for (int ib = 0; ib < gb->nblk; ib++) {
        double *a = gb->blk + (size_t)omp_get_thread_num() * S * gb->bp;
        const int y0 = ib * GRAM_ROWS, nr = hr - y0 < GRAM_ROWS ? hr - y0 : GRAM_ROWS;
        const size_t p0 = gb->rowoff[y0], np = gb->rowoff[y0 + nr] - p0;
        for (int j = 0; j < S; j++) gram_render(gb, j, y0, nr, a + (size_t)j * np);
        /* e_q = Σ_j zx_jq a_j over pixel chunks that stay in cache */
        enum { CH = 512 };
        for (size_t c0 = 0; c0 < np; c0 += CH) {
            const size_t cn = np - c0 < CH ? np - c0 : CH;
            for (int q = skip; q < cols; q++) {
                double *restrict e = gb->eh + (size_t)(q - skip) * gb->n + p0 + c0;
                const double *zq = gb->zx + (size_t)q * S;
                memset(e, 0, cn * sizeof(double));
                for (int j = 0; j < S; j++) {
                    const double zj = zq[j];
                    const double *restrict aj = a + (size_t)j * np + c0;
                    for (size_t i = 0; i < cn; i++) e[i] += zj * aj[i];
                }
                if (centred && q > 0) {
                    const double *restrict mean = gb->eh + p0 + c0;
                    const double zs = gb->lam[q - 1];
                    for (size_t i = 0; i < cn; i++) e[i] -= zs * mean[i];
                }
            }
        }
    }
}

/* Row y (0 .. kh − 1) of the whole kernel whose fold (gram_layout) is e, into k (kw values):
 * sym 0 mirrors the rows below ry and the centre row's right half through the centre; a
 * quadrant is mirrored in x and y, an octant also through the diagonal. */
static void kernel_row(const gram_build *gb, const double *e, int y, double *restrict k)
{
    const int rx = gb->rx, ry = gb->ry, kw = gb->kw;
    if (gb->sym == 0) {
        const double *s = e + (size_t)(y <= ry ? y : 2 * ry - y) * kw;
        if (y < ry)
            memcpy(k, s, (size_t)kw * sizeof(double));
        else
            for (int x = 0; x < kw; x++)
                k[x] = y > ry || x <= rx ? s[y > ry ? kw - 1 - x : x] : s[2 * rx - x];
        return;
    }
    const int dy = abs(y - ry);
    double *right = k + rx; /* right[dx], dx = 0 .. rx */
    if (gb->sym == 1)
        memcpy(right, e + gb->rowoff[dy], ((size_t)rx + 1) * sizeof(double));
    else {
        for (int dx = 0; dx < dy; dx++) right[dx] = e[gb->rowoff[dx] + (size_t)(dy - dx)];
        memcpy(right + dy, e + gb->rowoff[dy], ((size_t)rx + 1 - dy) * sizeof(double));
    }
    for (int dx = 1; dx <= rx; dx++) k[rx - dx] = right[dx];
}

static int wrap_index(int d, int n)
{
    d %= n;
    return d < 0 ? d + n : d;
}

/* Term r's spectrum as term_otf's (the whole kernel placed on the frame as
 * svp_frame_set_kernel places it, scaled by 1 / (nx ny), transformed), placed row by row from
 * its fold (kernel_row) into gb->placed, with no whole-kernel image; *flux = the whole kernel's
 * sum (row sums added in order). The rows are placed in parallel when no two of them alias
 * (then each frame row is written by one thread). */
static svp_status gram_otf(svp_blur *b, gram_build *gb, int r, fftw_complex **otf, double *flux)
{
    const svp_frame *f = &b->frame;
    const int zero = b->boundary == SVP_BOUNDARY_ZERO, rx = gb->rx, ry = gb->ry, kw = gb->kw;
    *otf = svp_alloc((size_t)f->ny * f->ncx * sizeof(fftw_complex));
    if (!*otf) return svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d spectrum", f->nx, f->ny);
    for (int x = 0; x < kw; x++) /* offsets beyond the image join no pixels (zero) */
        gb->wx[x] = zero && abs(x - rx) > f->width - 1 ? -1 : wrap_index(x - rx, f->nx);
    const int reach = zero && ry > f->height - 1 ? f->height - 1 : ry; /* rows placed: ±reach */
    const double inv = 1.0 / ((double)f->nx * f->ny), *e = gb->eh + (size_t)r * gb->n;
    double *placed = gb->placed;
    memset(placed, 0, (size_t)f->ny * f->nx * sizeof(double));
#pragma omp parallel for schedule(static) if (2 * reach + 1 <= f->ny)
    for (int y = 0; y < gb->kh; y++) {
        double *k = gb->krow + (size_t)omp_get_thread_num() * kw, rs = 0;
        kernel_row(gb, e, y, k);
        for (int x = 0; x < kw; x++) rs += k[x];
        gb->rsum[y] = rs;
        if (abs(y - ry) > reach) continue;
        double *row = placed + (size_t)wrap_index(y - ry, f->ny) * f->nx;
        for (int x = 0; x < kw; x++)
            if (gb->wx[x] >= 0) row[gb->wx[x]] += inv * k[x];
    }
    double total = 0;
    for (int y = 0; y < gb->kh; y++) total += gb->rsum[y];
    *flux = total;
    svp_fft_forward(f->plan, placed, *otf);
    return SVP_OK;
}

/* Term r's whole kernel (kw x kh, centre rx, ry) from its fold; *l1 its ℓ1 norm, *cmax its
 * largest |coefficient| over the samples. */
static void term_kernel(const gram_build *gb, const svp_variant_data *v, int r, svp_image *k,
                        double *l1, double *cmax)
{
    const double *e = gb->eh + (size_t)r * gb->n;
#pragma omp parallel for schedule(static)
    for (int y = 0; y < gb->kh; y++) kernel_row(gb, e, y, k->data + (size_t)y * gb->kw);
    *l1 = 0;
    *cmax = 0;
    for (size_t i = 0; i < gb->m; i++) *l1 += fabs(k->data[i]);
    for (int j = 0; j < gb->S; j++) *cmax = fmax(*cmax, fabs(v->coef[(size_t)r * gb->S + j]));
}

typedef struct gram_term_ctx {
    const gram_build *gb;
    const svp_variant_data *v;
} gram_term_ctx;

static svp_status gram_term_kernel(void *ctx, int r, svp_image *k, double *scale)
{
    const gram_term_ctx *c = ctx;
    double l1, cmax;
    term_kernel(c->gb, c->v, r, k, &l1, &cmax);
    *scale = l1 * cmax;
    return SVP_OK;
}

/* With the far tail: term r's whole kernel made from its fold, its tail and core (term_tail)
 * and its flux (gram_otf's otherwise). */
static svp_status gram_tail(svp_blur *b, gram_build *gb, int r)
{
    svp_image *k = NULL;
    SVP_CHECK(svp_image_new(gb->kw, gb->kh, &k));
    double l1, cmax, flux = 0;
    term_kernel(gb, b->variant, r, k, &l1, &cmax);
    for (size_t i = 0; i < gb->m; i++) flux += k->data[i];
    gb->flux[r] = flux;
    const svp_status st = term_tail(b, k, gb->rx, gb->ry, r, &b->variant->otf[r]);
    svp_image_free(k);
    return st;
}

/* Low rank through the S x S Gram matrix (S samples) instead of the SVD of the whole m x S
 * kernel matrix A: G = Aᵀ A = V Λ Vᵀ (LAPACKE_dsyevr), then the left singular vectors
 * u_r = A v_r / σ_r, σ_r = √λ_r (the same eigen-PSFs and coefficients σ_r v_r as the SVD, up to
 * sign). Only a fold of the kernels is rendered (gram_layout): every PSF model is
 * point-symmetric (rows 0 .. ry, row ry's centre counted once, every other pixel twice), a
 * circular one also in x, y and x ↔ y (an octant, an eighth of the pixels, each weighted by the
 * number it stands for), an ellipse on the grid's axes in x and y (a quadrant). Both passes
 * stream the fold in blocks of GRAM_ROWS rows for all samples at once (gram_raw:
 * gram_accumulate into the Gram matrix; gram_halves: the eigen-PSFs' folds as combinations of
 * the samples): no kernel matrix is held whole, and the cost is O(S² · fold pixels) in
 * cache-blocked vector loops. The fold is unfolded only when placed on the frame for the FFT
 * (gram_otf). The first pass renders the kernels unnormalised (their sums are not known yet): G
 * of the normalised, mean-centred kernels K_j / s_j − K̄ follows from the raw Gram and the sums
 * exactly, C D G D C (D = diag(1/s), C = I − 11ᵀ/S), which costs about log10(|K|² / |K − K̄|²)
 * digits (gram_eigen). The blocks' partial Gram matrices are summed in a fixed order
 * (deterministic for any thread count). A term with λ <= 0 keeps e = A v, coefficient v (its
 * product, the one that matters, is the same). half = 1: the point symmetry only (tests). */
static svp_status build_lowrank_gram(svp_blur *b, const svp_variant_options *o, double support,
                                     int rx, int ry, int half)
{
    svp_variant_data *v = b->variant;
    gram_build gb;
    svp_status st = gram_alloc(&gb, v, o, rx, ry);
    if (st == SVP_OK) st = sample_psfs(b, support, gb.psf);
    if (st == SVP_OK) st = gram_layout(&gb, half);
    if (st == SVP_OK) {
        gram_raw(&gb);
        st = gram_eigen(&gb, v);
    }
    if (st == SVP_OK) st = gram_terms(&gb, v);
    if (st == SVP_OK) gram_halves(&gb);
    if (st == SVP_OK && !b->frame.plan) {
        gram_term_ctx c = {&gb, v};
        st = tails_frame(b, gb.R, rx, ry, o->tail_tol, gram_term_kernel, &c);
    }
    if (st == SVP_OK) {
        free(gb.blk); /* the row blocks are done with */
        gb.blk = NULL;
        const size_t frame = (size_t)b->frame.ny * b->frame.nx; /* gram_otf's, not gram_tail's */
        gb.placed = v->tails ? NULL : svp_alloc(frame * sizeof(double));
        if (!v->tails && !gb.placed)
            st = svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d frame", b->frame.nx,
                          b->frame.ny);
    }
    for (int r = 0; r < gb.R && st == SVP_OK; r++) {
        st = v->tails ? gram_tail(b, &gb, r) : gram_otf(b, &gb, r, &v->otf[r], &gb.flux[r]);
        if (st == SVP_OK)
            st = svp_report_progress(o->progress, o->progress_user, 0.5 + 0.5 * (r + 1.0) / gb.R);
    }
    if (st == SVP_OK && o->renormalise) st = lowrank_renormalise(b, gb.R, gb.flux);
    gram_free(&gb);
    return st;
}

/* Real term spectra (svp_variant_data.otf_re) when every term's is real up to round-off and
 * none carries a row-pruning phase. */
static svp_status keep_real_spectra(svp_variant_data *v, size_t ns)
{
    if (v->pruned) return SVP_OK;
    for (int k = 0; k < v->n_terms; k++)
        if (!svp_spectrum_is_real(v->otf[k], ns)) return SVP_OK;
    v->otf_re = calloc((size_t)v->n_terms, sizeof *v->otf_re);
    if (!v->otf_re) return svp_fail(SVP_ERR_NOMEM, "out of memory for %d spectra", v->n_terms);
    for (int k = 0; k < v->n_terms; k++) {
        v->otf_re[k] = svp_spectrum_real_part(v->otf[k], ns);
        if (!v->otf_re[k])
            return svp_fail(SVP_ERR_NOMEM, "out of memory for %d spectra", v->n_terms);
        svp_free(v->otf[k]);
        v->otf[k] = NULL;
    }
    free(v->otf);
    v->otf = NULL;
    return SVP_OK;
}

/* The memory the operator needs (info->peak_bytes), checked against the limit before anything
 * large is allocated. */
static svp_status check_peak(const svp_psf_field *field, int width, int height,
                             svp_boundary boundary, const svp_variant_options *o,
                             svp_variant_info *info)
{
    const int lowrank = o->representation == SVP_VARIANT_LOWRANK;
    const int regions = o->representation == SVP_VARIANT_REGIONS;
    const double sup = o->support > 0 ? o->support : svp_psf_field_base(field)->support;
    const int krx = sup > 0 ? (int)ceil(sup) : width - 1, kry = sup > 0 ? (int)ceil(sup)
                                                                       : height - 1;
    const int gx = lowrank ? o->samples_x : o->grid_x, gy = lowrank ? o->samples_y : o->grid_y;
    const int S = (gx < width ? gx : width) * (gy < height ? gy : height);
    const int K = regions ? svp_region_count(field) : lowrank ? o->rank : S;
    const size_t need =
        regions ? svp_region_peak_bytes(width, height, boundary, K, krx, kry)
                : svp_variant_peak_bytes(width, height, boundary, lowrank, K, lowrank ? S : 0, krx,
                                         kry);
    const double limit = svp_variant_memory_limit(o);
    info->peak_bytes = need;
    if ((double)need <= limit) return SVP_OK;
    char what[64];
    if (regions)
        snprintf(what, sizeof what, "regions, %d region kernels", K);
    else
        snprintf(what, sizeof what, "%s, %d x %d %s", lowrank ? "low rank" : "tent", gx, gy,
                 lowrank ? "samples" : "nodes");
    return svp_fail(SVP_ERR_INVALID,
                    "the space-variant operator (%s) for %d x %d with kernels of %d x %d pixels "
                    "needs about %.0f MB, more than the memory limit of %.0f MB; set a smaller "
                    "support, fewer terms or a larger limit",
                    what, width, height, 2 * krx + 1, 2 * kry + 1, need / 1e6, limit / 1e6);
}

/* The representation to build: the automatic choice when asked (*terms: the region terms its
 * estimate made, kept only when it chooses regions; K = 0 otherwise), then the region check and
 * the memory check; *terms freed on failure. */
static svp_status settle_representation(const svp_psf_field *field, int width, int height,
                                        svp_boundary boundary, svp_variant_options *o,
                                        svp_variant_info *info, svp_region_terms *terms)
{
    memset(terms, 0, sizeof *terms);
    if (o->representation == SVP_VARIANT_AUTO) {
        svp_variant_options chosen;
        SVP_CHECK(svp_variant_choose(field, width, height, boundary, o, &chosen, info, terms));
        *o = chosen;
    }
    svp_status st = SVP_OK;
    if (o->representation == SVP_VARIANT_REGIONS)
        st = svp_region_check(field);
    else
        svp_region_terms_free(terms);
    if (st == SVP_OK) st = check_peak(field, width, height, boundary, o, info);
    if (st != SVP_OK) svp_region_terms_free(terms);
    return st;
}

svp_status svp_blur_new_field(const svp_psf_field *field, int width, int height,
                              svp_boundary boundary, const svp_variant_options *options,
                              svp_blur **out)
{
    return svp_blur_new_field_build(field, width, height, boundary, options, 0, out);
}

svp_status svp_blur_new_field_build(const svp_psf_field *field, int width, int height,
                                    svp_boundary boundary, const svp_variant_options *options,
                                    int build, svp_blur **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_blur_new_field: out is NULL");
    *out = NULL;
    svp_variant_options o;
    if (options)
        o = *options;
    else
        svp_variant_defaults(&o);
    SVP_CHECK(check_options(&o));
    if (!field) return svp_fail(SVP_ERR_INVALID, "PSF field is NULL");
    SVP_CHECK(svp_blur_check_geometry(width, height, boundary));
    if (field->width != 0 && (field->width != width || field->height != height))
        return svp_fail(SVP_ERR_SIZE, "the PSF field is for a %d x %d image, the operator for %d x %d",
                        field->width, field->height, width, height);
    svp_variant_info info;
    memset(&info, 0, sizeof info);
    info.estimated_error = NAN;
    svp_region_terms terms; /* the automatic choice's region terms, for build_regions */
    SVP_CHECK(settle_representation(field, width, height, boundary, &o, &info, &terms));
    const int lowrank = o.representation == SVP_VARIANT_LOWRANK;
    const int regions = o.representation == SVP_VARIANT_REGIONS;
    const double t_build = omp_get_wtime();
    svp_blur *b = NULL;
    int rx, ry;
    double support;
    svp_status st = svp_variant_begin(field, width, height, boundary, o.support,
                                      lowrank || regions ? SVP_BLUR_LOWRANK : SVP_BLUR_TENT, &b,
                                      &rx, &ry, &support);
    if (st != SVP_OK) {
        svp_region_terms_free(&terms);
        return st;
    }
    if (regions) b->ops = &svp_regions_ops;
    svp_variant_data *v = b->variant = calloc(1, sizeof *v);
    if (!v) st = svp_fail(SVP_ERR_NOMEM, "out of memory for blur buffers");
    /* the frame now, or with the far tail on a coarse grid once the terms are known (tails_frame:
     * it holds the cores only) */
    const int tail =
        (regions || (lowrank && build != 1)) && o.tail_tol > 0 && boundary == SVP_BOUNDARY_ZERO;
    if (st == SVP_OK && !tail) st = frame_buffers(b, rx, ry);
    if (st == SVP_OK) {
        /* no more nodes than pixels along an axis */
        v->gx = regions ? width : lowrank ? o.samples_x : o.grid_x;
        v->gy = regions ? height : lowrank ? o.samples_y : o.grid_y;
        if (v->gx > width) v->gx = width;
        if (v->gy > height) v->gy = height;
        st = axis_hats(v->gx, width, &v->ix0, &v->fx);
        if (st == SVP_OK) st = axis_hats(v->gy, height, &v->iy0, &v->fy);
    }
    if (st == SVP_OK) st = svp_variant_halo_map(b->field, width, height, &v->alpha);
    if (st == SVP_OK && v->alpha) {
        const size_t n = (size_t)width * height;
        v->scale = svp_alloc(n * sizeof(double));
        if (!v->scale)
            st = svp_fail(SVP_ERR_NOMEM, "out of memory for a halo map");
        else
            for (size_t i = 0; i < n; i++) v->scale[i] = 1.0 - v->alpha[i];
    }
    if (st == SVP_OK)
        st = regions      ? build_regions(b, &o, support, rx, ry, &terms)
             : !lowrank   ? build_tent(b, &o, support, rx, ry)
             : build == 1 ? build_lowrank(b, &o, support, rx, ry)
                          : build_lowrank_gram(b, &o, support, rx, ry, build == 2);
    svp_region_terms_free(&terms); /* unless build_regions took them over */
    if (st == SVP_OK) st = keep_real_spectra(v, (size_t)b->frame.ny * b->frame.ncx);
    if (st == SVP_OK) st = setup_fill(b);
    if (st == SVP_OK && regions && !v->tails) {
        /* the per-pixel maps are in the weight tables now (the tails read them) */
        free(v->coef);
        v->coef = NULL;
    }
    if (st == SVP_OK && o.single_precision) st = drop_double(b);
    if (st != SVP_OK) {
        svp_blur_free(b);
        return st;
    }
    info.representation = o.representation;
    info.grid_x = regions ? 0 : v->gx;
    info.grid_y = regions ? 0 : v->gy;
    info.rank = lowrank ? o.rank : regions ? v->n_terms : 0;
    svp_variant_tail_info(b, &info.tail_step, &info.tail_split, &info.tail_error);
    info.build_seconds = omp_get_wtime() - t_build;
    info.memory_bytes = svp_blur_memory(b);
    b->info = info;
    *out = b;
    return SVP_OK;
}

svp_status svp_variant_clone(const svp_blur *b, svp_blur **out)
{
    *out = NULL;
    if (!b || b->kind == SVP_BLUR_INVARIANT || !svp_blur_clonable(b))
        return svp_fail(SVP_ERR_UNSUPPORTED, "only a tent, low-rank or region operator in double "
                                             "precision can be copied");
    const svp_variant_data *v = b->variant;
    svp_blur *c = svp_blur_copy_header(b);
    svp_variant_data *u = c ? malloc(sizeof *u) : NULL;
    if (!u) {
        free(c);
        return svp_fail(SVP_ERR_NOMEM, "out of memory for a copy of the operator");
    }
    *u = *v; /* the spectra, weight tables, maps and grid: b's, read only */
    u->borrowed = 1;
    u->acc = NULL, u->spec2 = NULL, u->ext = NULL, u->blk = NULL, u->blk_threads = 0;
    u->row_on = NULL;
    u->otf_f = NULL, u->fr_f = NULL, u->spec_f = NULL, u->acc_f = NULL;
    u->rows_img = u->rows_win = NULL;
    u->tails = NULL;
    u->tail_in = NULL;
    c->variant = u;
    c->info = b->info;
    const size_t ns = (size_t)b->frame.ny * b->frame.ncx;
    /* the frame's geometry and the plans anew, for this thread's plan thread count */
    /* the same frame: the whole kernel's, or with a far tail the cores' (radius 2 r0) */
    const int r1 = 2 * v->tail_r0, tails = v->tails != NULL;
    svp_status st =
        svp_frame_init(&c->frame, b->width, b->height, tails && r1 < b->kcx ? r1 : b->kcx,
                       tails && r1 < b->kcy ? r1 : b->kcy, b->boundary);
    if (st == SVP_OK) st = svp_psf_field_copy(b->field, &c->field);
    if (st == SVP_OK) st = svp_fft_block_get(c->frame.nx, &u->block);
    if (st == SVP_OK) st = svp_fft_pruned_get(c->frame.ny, c->frame.nx, 0, &u->cols);
    if (st == SVP_OK) st = tails_copy(b, v, u);
    if (st == SVP_OK) {
        c->work_c = svp_alloc(ns * sizeof(fftw_complex));
        c->work_r_image = svp_alloc((size_t)b->width * b->height * sizeof(double));
        u->acc = svp_alloc(ns * sizeof(fftw_complex));
        u->ext = svp_alloc((size_t)c->frame.ny * c->frame.nx * sizeof(double));
        u->row_on = calloc((size_t)c->frame.ny, 1);
        if (v->spec2) u->spec2 = svp_alloc(ns * sizeof(fftw_complex));
        if (!c->work_c || !c->work_r_image || !u->acc || !u->ext || !u->row_on ||
            (v->spec2 && !u->spec2))
            st = svp_fail(SVP_ERR_NOMEM, "out of memory for a copy of the operator");
    }
    if (st != SVP_OK) {
        svp_blur_free(c);
        return st;
    }
    *out = c;
    return SVP_OK;
}

svp_status svp_blur_variant_info(const svp_blur *b, svp_variant_info *info)
{
    if (!b || !info) return svp_fail(SVP_ERR_INVALID, "svp_blur_variant_info: NULL argument");
    if (b->kind != SVP_BLUR_TENT && b->kind != SVP_BLUR_LOWRANK)
        return svp_fail(SVP_ERR_UNSUPPORTED,
                        "the operator is not a tent, low-rank or region space-variant operator");
    *info = b->info;
    return SVP_OK;
}

size_t svp_variant_peak_bytes(int width, int height, svp_boundary boundary, int lowrank, int K,
                              int S, int rx, int ry)
{
    int nx = 0, ny = 0;
    if (svp_frame_size(width, height, rx, ry, boundary, &nx, &ny) != SVP_OK) return SIZE_MAX;
    const size_t spectrum = (size_t)ny * (nx / 2 + 1) * sizeof(fftw_complex);
    const size_t frame = (size_t)nx * ny * sizeof(double);
    const size_t image = (size_t)width * height * sizeof(double);
    const size_t kernel = (size_t)(2 * rx + 1) * (2 * ry + 1) * sizeof(double);
    const int threads = omp_get_max_threads();
    size_t bytes = (size_t)K * spectrum  /* the terms' spectra, complex until made real */
                   + 3 * spectrum         /* work_c, accumulator, second spectrum */
                   + 2 * frame            /* adjoint accumulator, the FFT's real frame */
                   + kernel               /* the central kernel kept as stand-in */
                   + 3 * image            /* work image, scale, halo map */
                   + (size_t)threads * 3 * SVP_FFT_BLOCK * (size_t)nx * sizeof(double) +
                   (size_t)(lowrank ? K * (S > 0 ? S : 1) : K) * nx * sizeof(double);
    if (lowrank)
        bytes += svp_lowrank_build_memory(S, K, rx, ry, threads);
    else
        bytes += kernel; /* a node's kernel while its spectrum is made */
    return bytes;
}
