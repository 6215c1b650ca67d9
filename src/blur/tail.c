/* The PSF's far tail on a coarse grid (docs/model.md §5, "The tail on a coarse grid").
 *
 * A kernel k splits into a core k (1 − w) of radius r1 and a tail k w, w(r) a quintic step from
 * 0 at r0 to 1 at r1 = 2 r0. The core is convolved exactly on a frame sized for r1; the tail,
 * smooth where it lives, as P K_c Pᵀ: Pᵀ gathers the fine image onto nodes every s pixels with
 * bilinear (tent) weights, K_c convolves the nodes with the tail sampled every s pixels, P
 * spreads the nodes back with the same weights. P K_c Pᵀ is its own adjoint's transpose with K_c
 * transposed (a real OTF for a point-symmetric kernel: the same operator), non-negative for a
 * non-negative kernel, and exact for a constant tail; its error is that of interpolating the
 * tail bilinearly at both ends, at most (s² / 8) (|∂xx| + |∂yy|) of it per end. */
#include "blur_internal.h"

#include <math.h>
#include <omp.h>
#include <stdlib.h>
#include <string.h>

struct svp_tail {
    int s, r0;                    /* node spacing, split (the core reaches 2 r0) */
    int w, h;                     /* fine grid */
    int cw, ch;                   /* nodes: node ni at fine x = ni s, ni = 0 .. cw − 1 */
    svp_frame frame;              /* the nodes' frame (zero mode) with the OTF of K_c */
    const svp_fft_pruned *pruned; /* its transforms pruned to the node rows (NULL: full) */
    double *frame_r;
    fftw_complex *frame_c;
    double *nodes; /* ch x cw */
    double *tmp;   /* h x cw: the fine rows gathered, or the nodes spread over the fine rows */
    double error;
    svp_image *kc; /* the tail sampled every s pixels (centre rcx, rcy): what svp_tail_copy needs */
    int rcx, rcy;
};

/* The step w(r): 0 up to r0, 1 from r1, 10t³ − 15t⁴ + 6t⁵ between (continuous slope and
 * curvature at both ends). */
static double step(double r, int r0, int r1)
{
    if (r <= r0) return 0.0;
    if (r >= r1) return 1.0;
    const double t = (r - r0) / (double)(r1 - r0);
    return t * t * t * (10.0 + t * (-15.0 + 6.0 * t));
}

/* The kernel at offset (dx, dy); beyond its rectangle the value at the nearest offset inside it
 * when `extend` (a kernel that covers every offset the operator uses: what lies beyond is never
 * used, and the continuation keeps the tail smooth there), else 0. */
static inline double kernel_at(const svp_image *k, int cx, int cy, int dx, int dy, int extend)
{
    int x = cx + dx, y = cy + dy;
    if (x < 0 || y < 0 || x >= k->width || y >= k->height) {
        if (!extend) return 0.0;
        x = x < 0 ? 0 : (x >= k->width ? k->width - 1 : x);
        y = y < 0 ? 0 : (y >= k->height ? k->height - 1 : y);
    }
    return k->data[(size_t)y * k->width + x];
}

/* The tail's value at offset (dx, dy): the kernel (kernel_at) times w. */
static double tail_at(const svp_image *k, int cx, int cy, int dx, int dy, int r0, int r1,
                      int extend)
{
    return kernel_at(k, cx, cy, dx, dy, extend) * step(hypot(dx, dy), r0, r1);
}

/* Whether the kernel reaches every offset an operator on this grid uses (view: `margin` pixels
 * in from each side). */
static int covers(const svp_image *k, int cx, int cy, int width, int height, int margin)
{
    const int ux = width - margin - 1, uy = height - margin - 1;
    return cx >= ux && k->width - 1 - cx >= ux && cy >= uy && k->height - 1 - cy >= uy;
}

/* What the estimate needs of a kernel on a grid, computed once: the kernel's flux, the offsets
 * the operator uses (one beyond: a truncated tail's edge) and, per whole radius, the sum of
 * |Δxx k| + |Δyy k| there (where w = 1 on a whole stencil the tail's second differences are
 * the kernel's). */
typedef struct profile {
    const svp_image *k;
    int cx, cy, extend;
    int x0, x1, y0, y1; /* the offsets summed */
    int n_bins;
    double *outer; /* outer[b] = the sum over offsets with radius >= b */
    double flux;
} profile;

static void profile_free(profile *p) { free(p->outer); }

static svp_status profile_make(const svp_image *k, int cx, int cy, int width, int height,
                               int margin, profile *p)
{
    memset(p, 0, sizeof *p);
    p->k = k;
    p->cx = cx;
    p->cy = cy;
    p->extend = covers(k, cx, cy, width, height, margin);
    const int ux = width - margin - 1, uy = height - margin - 1;
    const int rx = k->width - 1 - cx, ry = k->height - 1 - cy;
    p->x0 = -(cx < ux ? cx : ux) - 1;
    p->x1 = (rx < ux ? rx : ux) + 1;
    p->y0 = -(cy < uy ? cy : uy) - 1;
    p->y1 = (ry < uy ? ry : uy) + 1;
    const size_t n = (size_t)k->width * k->height;
    for (size_t i = 0; i < n; i++) p->flux += fabs(k->data[i]);
    const int mx = -p->x0 > p->x1 ? -p->x0 : p->x1, my = -p->y0 > p->y1 ? -p->y0 : p->y1;
    p->n_bins = (int)ceil(hypot(mx, my)) + 2;
    p->outer = calloc((size_t)p->n_bins + 1, sizeof *p->outer);
    if (!p->outer) return svp_fail(SVP_ERR_NOMEM, "out of memory for the tail's profile");
    /* w = 1: the kernel's own second differences, binned by whole radius (serial: the sums do
     * not depend on the threads). Only bins beyond the smallest r1 + 2 are read. */
    for (int dy = p->y0; dy <= p->y1; dy++)
        for (int dx = p->x0; dx <= p->x1; dx++) {
            const double c = kernel_at(k, cx, cy, dx, dy, p->extend);
            const double xx = kernel_at(k, cx, cy, dx - 1, dy, p->extend) - 2 * c +
                              kernel_at(k, cx, cy, dx + 1, dy, p->extend);
            const double yy = kernel_at(k, cx, cy, dx, dy - 1, p->extend) - 2 * c +
                              kernel_at(k, cx, cy, dx, dy + 1, p->extend);
            p->outer[(int)sqrt((double)dx * dx + (double)dy * dy)] += fabs(xx) + fabs(yy);
        }
    for (int b = p->n_bins - 1; b >= 0; b--) p->outer[b] += p->outer[b + 1];
    return SVP_OK;
}

/* *out = Σ |Δxx| + |Δyy| of the tail for split r0 over the used offsets, relative to the flux:
 * exact inside radius r1 + 2 (from a table of the tail there), the profile beyond (there w = 1
 * on every stencil point). */
static svp_status profile_sum(const profile *p, int r0, double *out)
{
    *out = 0.0;
    if (!(p->flux > 0)) return SVP_OK;
    const int r1 = 2 * r0, rb = r1 + 2, side = 2 * rb + 3;
    double *t = malloc((size_t)side * side * sizeof *t);
    if (!t) return svp_fail(SVP_ERR_NOMEM, "out of memory for the tail's estimate");
    for (int j = 0; j < side; j++)
        for (int i = 0; i < side; i++)
            t[(size_t)j * side + i] =
                tail_at(p->k, p->cx, p->cy, i - rb - 1, j - rb - 1, r0, r1, p->extend);
    double sum = rb < p->n_bins ? p->outer[rb] : 0.0;
    for (int dy = -rb; dy <= rb; dy++) {
        if (dy < p->y0 || dy > p->y1) continue;
        for (int dx = -rb; dx <= rb; dx++) {
            if (dx < p->x0 || dx > p->x1) continue;
            const double r = sqrt((double)dx * dx + (double)dy * dy);
            if (r >= rb || r + 1.5 < r0) continue; /* beyond: the profile; within: 0 */
            const double *c = t + (size_t)(dy + rb + 1) * side + dx + rb + 1;
            const double xx = c[-1] - 2 * c[0] + c[1], yy = c[-side] - 2 * c[0] + c[side];
            sum += fabs(xx) + fabs(yy);
        }
    }
    free(t);
    *out = sum / p->flux;
    return SVP_OK;
}

double svp_tail_estimate(const svp_image *k, int cx, int cy, int width, int height, int margin,
                         int s, int r0)
{
    profile p;
    if (profile_make(k, cx, cy, width, height, margin, &p) != SVP_OK) {
        profile_free(&p);
        return HUGE_VAL; /* no memory: no tail is chosen */
    }
    double sum = 0.0;
    const svp_status st = profile_sum(&p, r0, &sum);
    profile_free(&p);
    return st == SVP_OK ? 0.25 * s * s * sum : HUGE_VAL;
}

svp_status svp_tail_core(const svp_image *k, int cx, int cy, int r0, svp_image **out, int *ocx,
                         int *ocy)
{
    const int r1 = 2 * r0;
    const int lx = cx < r1 ? cx : r1, hx = k->width - 1 - cx < r1 ? k->width - 1 - cx : r1;
    const int ly = cy < r1 ? cy : r1, hy = k->height - 1 - cy < r1 ? k->height - 1 - cy : r1;
    SVP_CHECK(svp_image_new(lx + hx + 1, ly + hy + 1, out));
    svp_image *c = *out;
    for (int dy = -ly; dy <= hy; dy++)
        for (int dx = -lx; dx <= hx; dx++)
            c->data[(size_t)(dy + ly) * c->width + dx + lx] =
                k->data[(size_t)(cy + dy) * k->width + cx + dx] *
                (1.0 - step(hypot(dx, dy), r0, r1));
    *ocx = lx;
    *ocy = ly;
    return SVP_OK;
}

void svp_tail_free(svp_tail *t)
{
    if (!t) return;
    svp_frame_release(&t->frame);
    svp_free(t->frame_r);
    svp_free(t->frame_c);
    svp_free(t->nodes);
    svp_free(t->tmp);
    svp_image_free(t->kc);
    free(t);
}

size_t svp_tail_memory(const svp_tail *t)
{
    if (!t) return 0;
    const svp_frame *f = &t->frame;
    return sizeof *t + svp_frame_memory(f) + (size_t)f->ny * f->nx * sizeof(double) +
           (size_t)f->ny * f->ncx * sizeof(fftw_complex) +
           ((size_t)t->ch + t->h) * t->cw * sizeof(double) +
           (t->kc ? (size_t)t->kc->width * t->kc->height * sizeof(double) : 0);
}

int svp_tail_step(const svp_tail *t) { return t->s; }
int svp_tail_split(const svp_tail *t) { return t->r0; }
double svp_tail_error(const svp_tail *t) { return t->error; }

/* The reach of K_c in nodes: the node offsets whose tail value some used fine offset
 * interpolates, up to the largest used offset (the kernel's, when it stops short of it) plus a
 * node spacing at each end. */
static void node_reach(const svp_image *k, int cx, int cy, int width, int height, int margin,
                       int s, int *rcx, int *rcy)
{
    const int ux = width - margin - 1, uy = height - margin - 1;
    const int extend = covers(k, cx, cy, width, height, margin);
    int rkx = extend ? ux : svp_kernel_reach(k->width, cx);
    int rky = extend ? uy : svp_kernel_reach(k->height, cy);
    *rcx = (rkx < ux ? rkx : ux) / s + 2;
    *rcy = (rky < uy ? rky : uy) / s + 2;
}

/* t's node frame with the OTF of t->kc, its plans and buffers. */
static svp_status tail_setup(svp_tail *t)
{
    svp_status st = svp_frame_init(&t->frame, t->cw, t->ch, t->rcx, t->rcy, SVP_BOUNDARY_ZERO);
    if (st == SVP_OK)
        st = svp_frame_set_kernel(&t->frame, t->kc, t->rcx, t->rcy, SVP_BOUNDARY_ZERO);
    if (st == SVP_OK && t->frame.ny > t->ch)
        st = svp_fft_pruned_get(t->frame.ny, t->frame.nx, t->ch, &t->pruned);
    if (st != SVP_OK) return st;
    svp_frame_keep_real(&t->frame);
    const svp_frame *f = &t->frame;
    t->frame_r = svp_alloc((size_t)f->ny * f->nx * sizeof(double));
    t->frame_c = svp_alloc((size_t)f->ny * f->ncx * sizeof(fftw_complex));
    t->nodes = svp_alloc((size_t)t->ch * t->cw * sizeof(double));
    t->tmp = svp_alloc((size_t)t->h * t->cw * sizeof(double));
    if (!t->frame_r || !t->frame_c || !t->nodes || !t->tmp)
        return svp_fail(SVP_ERR_NOMEM, "out of memory for the coarse tail's %d x %d nodes", t->cw,
                        t->ch);
    return SVP_OK;
}

svp_status svp_tail_new(const svp_image *k, int cx, int cy, int width, int height, int margin,
                        int s, int r0, double error, svp_tail **out)
{
    *out = NULL;
    svp_tail *t = calloc(1, sizeof *t);
    if (!t) return svp_fail(SVP_ERR_NOMEM, "out of memory for the coarse tail");
    t->s = s;
    t->r0 = r0;
    t->w = width;
    t->h = height;
    t->cw = (width - 1) / s + 2;
    t->ch = (height - 1) / s + 2;
    t->error = error;
    const int extend = covers(k, cx, cy, width, height, margin);
    node_reach(k, cx, cy, width, height, margin, s, &t->rcx, &t->rcy);
    const int rcx = t->rcx, rcy = t->rcy;
    svp_status st = svp_image_new(2 * rcx + 1, 2 * rcy + 1, &t->kc);
    if (st == SVP_OK) {
        svp_image *kc = t->kc;
        for (int j = -rcy; j <= rcy; j++)
            for (int i = -rcx; i <= rcx; i++)
                kc->data[(size_t)(j + rcy) * kc->width + i + rcx] =
                    tail_at(k, cx, cy, i * s, j * s, r0, 2 * r0, extend);
        st = tail_setup(t);
    }
    if (st != SVP_OK) {
        svp_tail_free(t);
        return st;
    }
    *out = t;
    return SVP_OK;
}

svp_status svp_tail_copy(const svp_tail *src, svp_tail **out)
{
    *out = NULL;
    svp_tail *t = calloc(1, sizeof *t);
    if (!t) return svp_fail(SVP_ERR_NOMEM, "out of memory for the coarse tail");
    t->s = src->s, t->r0 = src->r0, t->w = src->w, t->h = src->h;
    t->cw = src->cw, t->ch = src->ch, t->error = src->error;
    t->rcx = src->rcx, t->rcy = src->rcy;
    svp_status st = svp_image_new(src->kc->width, src->kc->height, &t->kc);
    if (st == SVP_OK) {
        memcpy(t->kc->data, src->kc->data,
               (size_t)src->kc->width * src->kc->height * sizeof(double));
        st = tail_setup(t);
    }
    if (st != SVP_OK) {
        svp_tail_free(t);
        return st;
    }
    *out = t;
    return SVP_OK;
}

/* The nodes convolved with K_c (adjoint: correlated), in place. */
static void nodes_convolve(svp_tail *t, int adjoint)
{
    const svp_frame *f = &t->frame;
    /* pruned: only the node rows are read in and kept out */
    svp_frame_zero_load(f, t->pruned ? t->ch : f->ny, t->nodes, t->frame_r);
    svp_frame_filter(f, t->pruned, t->frame_r, t->frame_c, adjoint);
    svp_frame_crop(f, t->frame_r, t->nodes);
}

/* The gather and spread run on several threads from this many pixels: a pass costs about a
 * millisecond per million pixels, and each parallel region's barriers cost far more than that on
 * a machine with more runnable threads than cores (measured: on 600² with a load of 2 extra
 * jobs, 40 accelerated iterations took 6.2 s with the passes parallel from 65536 pixels against
 * 3.8 s for the plain frame). */
#define SVP_TAIL_PARALLEL_MIN ((size_t)1 << 20)

/* _Pragma inside a macro is beyond clang-format: this block is laid out by hand */
/* clang-format off */
/* Pᵀ (GATHER: the fine image, rows `stride` apart, onto the nodes) and P added (SPREAD: the
 * nodes onto the fine image, added), for fine values of type FT. Every node row and every fine
 * row is one thread's, summed in a fixed order: the result does not depend on the threads. */
#define SVP_TAIL_PASSES(GATHER, SPREAD, FT)                                                        \
    static void GATHER(svp_tail *t, const FT *restrict in, size_t stride)                          \
    {                                                                                              \
        const int s = t->s, w = t->w, h = t->h, cw = t->cw;                                        \
        const double inv = 1.0 / s;                                                                \
        double *restrict tmp = t->tmp, *restrict nodes = t->nodes;                                 \
        _Pragma("omp parallel if ((size_t)w * h > SVP_TAIL_PARALLEL_MIN)")                         \
        {                                                                                          \
            _Pragma("omp for schedule(static)")                                                    \
            for (int y = 0; y < h; y++) {                                                          \
                const FT *row = in + (size_t)y * stride;                                           \
                double *o = tmp + (size_t)y * cw;                                                  \
                memset(o, 0, (size_t)cw * sizeof(double));                                         \
                for (int x0 = 0, ni = 0; x0 < w; x0 += s, ni++) {                                  \
                    double a = 0.0, b = 0.0;                                                       \
                    for (int q = 0; q < s && x0 + q < w; q++) {                                    \
                        const double v = (double)row[x0 + q], u = q * inv;                         \
                        a += (1.0 - u) * v;                                                        \
                        b += u * v;                                                                \
                    }                                                                              \
                    o[ni] += a;                                                                    \
                    o[ni + 1] += b;                                                                \
                }                                                                                  \
            }                                                                                      \
            _Pragma("omp for schedule(static)")                                                    \
            for (int nj = 0; nj < t->ch; nj++) {                                                   \
                double *o = nodes + (size_t)nj * cw;                                               \
                memset(o, 0, (size_t)cw * sizeof(double));                                         \
                const int lo = nj > 0 ? (nj - 1) * s + 1 : 0;                                      \
                const int hi = (nj + 1) * s - 1 < h - 1 ? (nj + 1) * s - 1 : h - 1;                \
                for (int y = lo; y <= hi; y++) {                                                   \
                    const double u = (y - nj * s) * inv, g = u < 0 ? 1.0 + u : 1.0 - u;            \
                    const double *r = tmp + (size_t)y * cw;                                        \
                    for (int ni = 0; ni < cw; ni++) o[ni] += g * r[ni];                            \
                }                                                                                  \
            }                                                                                      \
        }                                                                                          \
    }                                                                                              \
    static void SPREAD(svp_tail *t, FT *restrict out, size_t stride)                               \
    {                                                                                              \
        const int s = t->s, w = t->w, h = t->h, cw = t->cw;                                        \
        const double inv = 1.0 / s;                                                                \
        const double *restrict nodes = t->nodes;                                                   \
        double *restrict tmp = t->tmp;                                                             \
        _Pragma("omp parallel for schedule(static) if ((size_t)w * h > SVP_TAIL_PARALLEL_MIN)")    \
        for (int y = 0; y < h; y++) {                                                              \
            const int nj = y / s;                                                                  \
            const double u = (y - nj * s) * inv;                                                   \
            const double *a = nodes + (size_t)nj * cw, *b = a + cw;                                \
            double *r = tmp + (size_t)y * cw;                                                      \
            for (int ni = 0; ni < cw; ni++) r[ni] = (1.0 - u) * a[ni] + u * b[ni];                 \
            FT *o = out + (size_t)y * stride;                                                      \
            for (int x0 = 0, ni = 0; x0 < w; x0 += s, ni++)                                        \
                for (int q = 0; q < s && x0 + q < w; q++) {                                        \
                    const double v = q * inv;                                                      \
                    o[x0 + q] = (FT)((double)o[x0 + q] + (1.0 - v) * r[ni] + v * r[ni + 1]);       \
                }                                                                                  \
        }                                                                                          \
    }

SVP_TAIL_PASSES(gather_d, spread_d, double)
SVP_TAIL_PASSES(gather_f, spread_f, float)
/* clang-format on */

void svp_tail_gather(svp_tail *t, const double *in, size_t stride, int adjoint)
{
    gather_d(t, in, stride);
    nodes_convolve(t, adjoint);
}

void svp_tail_gather_f(svp_tail *t, const float *in, size_t stride, int adjoint)
{
    gather_f(t, in, stride);
    nodes_convolve(t, adjoint);
}

void svp_tail_spread(svp_tail *t, double *out, size_t stride) { spread_d(t, out, stride); }
void svp_tail_spread_f(svp_tail *t, float *out, size_t stride) { spread_f(t, out, stride); }

/* A transform's cost in arbitrary units: n log2 n over its points. */
static double fft_cost(int nx, int ny)
{
    const double n = (double)nx * ny;
    return n * log2(n > 2 ? n : 2);
}

static const int tail_steps[] = {2, 3, 4, 6, 8};
static const int tail_splits[] = {4, 6, 8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256};
#define N_TAIL_SPLITS ((int)(sizeof tail_splits / sizeof *tail_splits))

int svp_tail_n_splits(void) { return N_TAIL_SPLITS; }

svp_status svp_tail_split_sums(const svp_image *k, int cx, int cy, int width, int height,
                               int margin, double *sums)
{
    const int ux = width - margin - 1, uy = height - margin - 1;
    int rx = svp_kernel_reach(k->width, cx), ry = svp_kernel_reach(k->height, cy);
    if (rx > ux) rx = ux;
    if (ry > uy) ry = uy;
    profile p;
    svp_status st = profile_make(k, cx, cy, width, height, margin, &p);
    for (int i = 0; i < N_TAIL_SPLITS && st == SVP_OK; i++) {
        sums[i] = HUGE_VAL; /* a split the kernel cannot hold */
        if (2 * tail_splits[i] < (rx < ry ? rx : ry))
            st = profile_sum(&p, tail_splits[i], &sums[i]);
    }
    profile_free(&p);
    return st;
}

svp_status svp_tail_pick(const svp_image *k, int cx, int cy, int width, int height, int margin,
                         const double *sums, double tol, int pnx, int pny, int *s_out, int *r0_out,
                         double *error)
{
    *s_out = 0;
    *r0_out = 0;
    *error = 0;
    const double plain = fft_cost(pnx, pny);
    double best = 0.8 * plain; /* a tail must save at least a fifth */
    for (size_t a = 0; a < sizeof tail_steps / sizeof *tail_steps; a++) {
        const int s = tail_steps[a];
        for (int i = 0; i < N_TAIL_SPLITS; i++) {
            const int r0 = tail_splits[i], r1 = 2 * r0;
            const double e = 0.25 * s * s * sums[i];
            if (r0 < 2 * s || !(e <= tol)) continue;
            /* the frames svp_blur_ready and svp_tail_new would make: the core's, the nodes' */
            int cnx, cny, tnx, tny, rcx, rcy;
            SVP_CHECK(svp_frame_size_view(width, height, r1, r1, margin, &cnx, &cny));
            node_reach(k, cx, cy, width, height, margin, s, &rcx, &rcy);
            SVP_CHECK(svp_frame_size((width - 1) / s + 2, (height - 1) / s + 2, rcx, rcy,
                                     SVP_BOUNDARY_ZERO, &tnx, &tny));
            /* the gather and spread: about half a transform's work over the fine grid */
            const double cost =
                fft_cost(cnx, cny) + fft_cost(tnx, tny) + 0.5 * fft_cost(width, height);
            if (cost < best) {
                best = cost;
                *s_out = s;
                *r0_out = r0;
                *error = e;
            }
        }
    }
    return SVP_OK;
}

svp_status svp_tail_choose(const svp_image *k, int cx, int cy, int width, int height, int margin,
                           double tol, int pnx, int pny, int *s_out, int *r0_out, double *error)
{
    *s_out = 0;
    *r0_out = 0;
    *error = 0;
    double sums[N_TAIL_SPLITS];
    SVP_CHECK(svp_tail_split_sums(k, cx, cy, width, height, margin, sums));
    return svp_tail_pick(k, cx, cy, width, height, margin, sums, tol, pnx, pny, s_out, r0_out,
                         error);
}
