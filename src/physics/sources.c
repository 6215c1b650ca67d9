/* Source fields: shapes, the flake's stray field (Fourier method), the strip's Oersted field
 * (closed form), NV-axis projection; and the padded Fourier canvas shared with
 * reconstruct.c. Frame and signs: include/svpsf.h, section physics. */
#include "physics_internal.h"

#include <math.h>
#include <stdlib.h>
#include <string.h>

/* ---- the padded Fourier canvas ------------------------------------------------------------ */

svp_status svp_canvas_init(svp_canvas *c, int w, int h, int pad_factor, double pixel_m)
{
    memset(c, 0, sizeof *c);
    if (pad_factor < 1)
        return svp_fail(SVP_ERR_INVALID, "pad_factor %d: must be at least 1", pad_factor);
    if (pad_factor > 16)
        return svp_fail(SVP_ERR_INVALID, "pad_factor %d: at most 16 is supported", pad_factor);
    c->w = w;
    c->h = h;
    c->nx = pad_factor == 1 ? w : svp_fft_good_size(pad_factor * w);
    c->ny = pad_factor == 1 ? h : svp_fft_good_size(pad_factor * h);
    c->ncx = c->nx / 2 + 1;
    c->dkx = 2 * M_PI / (c->nx * pixel_m);
    c->dky = 2 * M_PI / (c->ny * pixel_m);
    SVP_CHECK(svp_fft_plan_get(c->ny, c->nx, &c->plan));
    size_t nreal = (size_t)c->ny * c->nx, ncomplex = (size_t)c->ny * c->ncx;
    c->real = svp_alloc(nreal * sizeof(double));
    c->spec = svp_alloc(ncomplex * sizeof(fftw_complex));
    c->work = svp_alloc(ncomplex * sizeof(fftw_complex));
    if (!c->real || !c->spec || !c->work) {
        svp_canvas_release(c);
        return svp_fail(SVP_ERR_NOMEM, "out of memory for a %d x %d Fourier canvas", c->nx,
                        c->ny);
    }
    return SVP_OK;
}

void svp_canvas_release(svp_canvas *c)
{
    svp_free(c->real);
    svp_free(c->spec);
    svp_free(c->work);
    memset(c, 0, sizeof *c);
}

/* Source index and weight of canvas index t along an axis of n image pixels in a canvas of
 * size m: inside, (t, 1); in the padding the nearer edge pixel (the last one on the first half,
 * the first one — reached by wrap-around — on the second half) with a cosine taper that is 1
 * at the edge and 0 half-way across. */
static void axis_fill(int n, int m, int taper, int *src, double *weight)
{
    int mid = n + (m - n) / 2;
    for (int t = 0; t < m; t++) {
        if (t < n) {
            src[t] = t;
            weight[t] = 1;
        } else if (!taper) {
            src[t] = 0;
            weight[t] = 0;
        } else if (t < mid) {
            src[t] = n - 1;
            weight[t] = 0.5 * (1 + cos(M_PI * (t - (n - 1)) / (double)(mid - (n - 1))));
        } else {
            src[t] = 0;
            weight[t] = 0.5 * (1 + cos(M_PI * (m - t) / (double)(m - mid)));
        }
    }
}

svp_status svp_canvas_load(svp_canvas *c, const svp_image *image, svp_canvas_fill fill)
{
    const int w = c->w, nx = c->nx, ny = c->ny;
    const double *restrict in = image->data;
    double *restrict out = c->real;
    const double mean =
        fill == SVP_FILL_ZERO ? 0.0 : svp_sum(in, (size_t)w * c->h) / ((double)w * c->h);
    int *sx = malloc((size_t)(nx + ny) * sizeof(int));
    double *tx = malloc((size_t)(nx + ny) * sizeof(double));
    if (!sx || !tx) {
        free(sx);
        free(tx);
        return svp_fail(SVP_ERR_NOMEM, "out of memory for the padding tables");
    }
    int *sy = sx + nx;
    double *ty = tx + nx;
    axis_fill(w, nx, fill == SVP_FILL_TAPER, sx, tx);
    axis_fill(c->h, ny, fill == SVP_FILL_TAPER, sy, ty);
#pragma omp parallel for schedule(static)
    for (int j = 0; j < ny; j++) {
        double *row = out + (size_t)j * nx;
        const double *src = in + (size_t)sy[j] * w;
        for (int i = 0; i < nx; i++) row[i] = mean + ty[j] * tx[i] * (src[sx[i]] - mean);
    }
    free(sx);
    free(tx);
    svp_fft_forward(c->plan, c->real, c->spec);
    return SVP_OK;
}

void svp_canvas_emit(svp_canvas *c, svp_image *out)
{
    svp_fft_inverse(c->plan, c->work, c->real);
    const int w = c->w, nx = c->nx;
#pragma omp parallel for schedule(static)
    for (int j = 0; j < c->h; j++)
        memcpy(out->data + (size_t)j * w, c->real + (size_t)j * nx, (size_t)w * sizeof(double));
}

double svp_layer_decay(double k, double h, double t_nv)
{
    double a = 0.5 * k * t_nv;
    if (a < 1e-4) return exp(-k * h) * (1 + a * a / 6);
    return (exp(a - k * h) - exp(-a - k * h)) / (2 * a);
}

/* ---- sensor ------------------------------------------------------------------------------- */

void svp_sensor_defaults(svp_sensor *sensor)
{
    sensor->pixel_m = 100e-9;
    sensor->standoff_m = 100e-9;
    sensor->nv_thickness_m = 0;
    sensor->side = 1;
}

svp_status svp_sensor_validate(const svp_sensor *s)
{
    if (!s) return svp_fail(SVP_ERR_INVALID, "sensor geometry is NULL");
    if (!(s->pixel_m > 0) || !isfinite(s->pixel_m))
        return svp_fail(SVP_ERR_INVALID, "sensor pixel_m %g: must be a finite length > 0 m",
                        s->pixel_m);
    if (!(s->standoff_m > 0) || !isfinite(s->standoff_m))
        return svp_fail(SVP_ERR_INVALID, "sensor standoff_m %g: must be a finite length > 0 m",
                        s->standoff_m);
    if (!(s->nv_thickness_m >= 0) || !(s->nv_thickness_m < 2 * s->standoff_m))
        return svp_fail(SVP_ERR_INVALID,
                        "sensor nv_thickness_m %g: must be in [0, 2 standoff_m = %g) m",
                        s->nv_thickness_m, 2 * s->standoff_m);
    if (s->side != 1 && s->side != -1)
        return svp_fail(SVP_ERR_INVALID, "sensor side %d: must be +1 (above) or -1 (below)",
                        s->side);
    return SVP_OK;
}

/* ---- shapes ------------------------------------------------------------------------------- */

/* Sutherland–Hodgman: clips the polygon (n vertices in p) against x·sign <= bound (axis 0 = x,
 * 1 = y), writing to q; returns the new vertex count. Exact area for any simple polygon
 * clipped by a convex window (degenerate edges add no area). */
static int clip_half(const double *p, int n, int axis, double sign, double bound, double *q)
{
    int m = 0;
    for (int a = 0; a < n; a++) {
        const double *s = p + 2 * a, *e = p + 2 * ((a + 1) % n);
        double ds = sign * s[axis] - bound, de = sign * e[axis] - bound;
        if (ds <= 0) {
            q[2 * m] = s[0];
            q[2 * m + 1] = s[1];
            m++;
        }
        if ((ds < 0 && de > 0) || (ds > 0 && de < 0)) {
            double t = ds / (ds - de);
            q[2 * m] = s[0] + t * (e[0] - s[0]);
            q[2 * m + 1] = s[1] + t * (e[1] - s[1]);
            m++;
        }
    }
    return m;
}

static double shoelace(const double *p, int n)
{
    double a = 0;
    for (int i = 0; i < n; i++) {
        const double *s = p + 2 * i, *e = p + 2 * ((i + 1) % n);
        a += s[0] * e[1] - e[0] * s[1];
    }
    return 0.5 * a;
}

svp_status svp_raster_polygon(svp_image *image, const double *xy, int n, double value)
{
    if (!image || !xy) return svp_fail(SVP_ERR_INVALID, "polygon: image or vertices NULL");
    if (n < 3) return svp_fail(SVP_ERR_INVALID, "polygon: %d vertices, at least 3 needed", n);
    double x0 = INFINITY, x1 = -INFINITY, y0 = INFINITY, y1 = -INFINITY;
    for (int i = 0; i < n; i++) {
        if (!isfinite(xy[2 * i]) || !isfinite(xy[2 * i + 1]))
            return svp_fail(SVP_ERR_INVALID, "polygon vertex %d is not finite", i);
        x0 = fmin(x0, xy[2 * i]);
        x1 = fmax(x1, xy[2 * i]);
        y0 = fmin(y0, xy[2 * i + 1]);
        y1 = fmax(y1, xy[2 * i + 1]);
    }
    if (!isfinite(value)) return svp_fail(SVP_ERR_INVALID, "polygon value is not finite");
    const int w = image->width, h = image->height;
    int i0 = (int)fmax(0, floor(x0 + 0.5)), i1 = (int)fmin(w - 1, ceil(x1 - 0.5));
    int j0 = (int)fmax(0, floor(y0 + 0.5)), j1 = (int)fmin(h - 1, ceil(y1 - 0.5));
    if (i0 > i1 || j0 > j1) return SVP_OK;
    /* a half-plane clip emits at most two vertices per edge, so four clips stay below 16 n */
    const size_t cap = 2 * 16 * ((size_t)n + 4);
    int failed = 0;
#pragma omp parallel
    {
        double *a = malloc(cap * sizeof(double)), *b = malloc(cap * sizeof(double));
        if (!a || !b) {
#pragma omp atomic write
            failed = 1;
        }
#pragma omp for schedule(static)
        for (int j = j0; j <= j1; j++) {
            if (!a || !b) continue;
            double *row = image->data + (size_t)j * w;
            /* clip to the pixel row once, then to each pixel's columns */
            double *rowpoly = malloc(cap * sizeof(double));
            if (!rowpoly) {
#pragma omp atomic write
                failed = 1;
                continue;
            }
            int m = clip_half(xy, n, 1, 1, j + 0.5, a);
            m = clip_half(a, m, 1, -1, -(j - 0.5), rowpoly);
            for (int i = i0; i <= i1 && m >= 3; i++) {
                int k = clip_half(rowpoly, m, 0, 1, i + 0.5, a);
                k = clip_half(a, k, 0, -1, -(i - 0.5), b);
                if (k >= 3) row[i] += value * fabs(shoelace(b, k));
            }
            free(rowpoly);
        }
        free(a);
        free(b);
    }
    if (failed) return svp_fail(SVP_ERR_NOMEM, "out of memory rasterising a polygon");
    return SVP_OK;
}

svp_status svp_raster_rectangle(svp_image *image, double cx, double cy, double width,
                                double height, double angle, double value)
{
    if (!(width > 0) || !(height > 0) || !isfinite(width) || !isfinite(height))
        return svp_fail(SVP_ERR_INVALID, "rectangle size %g x %g px: both must be finite > 0",
                        width, height);
    double c = cos(angle), s = sin(angle), hw = 0.5 * width, hh = 0.5 * height;
    double xy[8];
    const double corner[4][2] = {{-1, -1}, {1, -1}, {1, 1}, {-1, 1}};
    for (int k = 0; k < 4; k++) {
        double u = corner[k][0] * hw, v = corner[k][1] * hh;
        xy[2 * k] = cx + c * u - s * v;
        xy[2 * k + 1] = cy + s * u + c * v;
    }
    return svp_raster_polygon(image, xy, 4, value);
}

svp_status svp_raster_disk(svp_image *image, double cx, double cy, double radius, double value)
{
    if (!image) return svp_fail(SVP_ERR_INVALID, "disk: image is NULL");
    if (!(radius > 0) || !isfinite(radius) || !isfinite(cx) || !isfinite(cy))
        return svp_fail(SVP_ERR_INVALID, "disk radius %g px at (%g, %g): must be finite, > 0",
                        radius, cx, cy);
    const int w = image->width, h = image->height, sub = 16;
    int i0 = (int)fmax(0, floor(cx - radius)), i1 = (int)fmin(w - 1, ceil(cx + radius));
    int j0 = (int)fmax(0, floor(cy - radius)), j1 = (int)fmin(h - 1, ceil(cy + radius));
    const double r2 = radius * radius;
#pragma omp parallel for schedule(static)
    for (int j = j0; j <= j1; j++) {
        for (int i = i0; i <= i1; i++) {
            double dx = fabs(i - cx), dy = fabs(j - cy);
            double nx = fmax(0, dx - 0.5), ny = fmax(0, dy - 0.5); /* nearest point */
            double fx = dx + 0.5, fy = dy + 0.5;                   /* farthest corner */
            double cover;
            if (nx * nx + ny * ny >= r2) continue;
            if (fx * fx + fy * fy <= r2) {
                cover = 1;
            } else {
                int inside = 0;
                for (int v = 0; v < sub; v++) {
                    double y = j - 0.5 + (v + 0.5) / sub - cy;
                    for (int u = 0; u < sub; u++) {
                        double x = i - 0.5 + (u + 0.5) / sub - cx;
                        inside += x * x + y * y < r2;
                    }
                }
                cover = inside / (double)(sub * sub);
            }
            image->data[(size_t)j * w + i] += value * cover;
        }
    }
    return SVP_OK;
}

/* ---- flake -------------------------------------------------------------------------------- */

static svp_status outputs_match(const svp_image *ref, const char *ref_name, svp_image *a,
                                const char *an, svp_image *b, const char *bn, svp_image *c,
                                const char *cn)
{
    if (a) SVP_CHECK(svp_image_same_size(ref, a, ref_name, an));
    if (b) SVP_CHECK(svp_image_same_size(ref, b, ref_name, bn));
    if (c) SVP_CHECK(svp_image_same_size(ref, c, ref_name, cn));
    return SVP_OK;
}

svp_status svp_flake_field(const svp_image *moment, double thickness_m, const svp_sensor *sensor,
                           int pad_factor, svp_image *bx, svp_image *by, svp_image *bz)
{
    if (!moment) return svp_fail(SVP_ERR_INVALID, "flake field: moment map is NULL");
    SVP_CHECK(svp_sensor_validate(sensor));
    if (!(thickness_m >= 0) || !isfinite(thickness_m))
        return svp_fail(SVP_ERR_INVALID, "flake thickness_m %g: must be finite and >= 0",
                        thickness_m);
    if (!bx && !by && !bz) return svp_fail(SVP_ERR_INVALID, "flake field: no output requested");
    SVP_CHECK(outputs_match(moment, "moment", bx, "bx", by, "by", bz, "bz"));
    if (svp_image_count_nonfinite(moment))
        return svp_fail(SVP_ERR_INVALID, "flake field: the moment map has NaN or Inf pixels");
    if (pad_factor == 0) pad_factor = 2;
    svp_canvas c;
    SVP_CHECK(svp_canvas_init(&c, moment->width, moment->height, pad_factor, sensor->pixel_m));
    svp_status st = svp_canvas_load(&c, moment, SVP_FILL_ZERO);
    if (st != SVP_OK) {
        svp_canvas_release(&c);
        return st;
    }
    const double h = sensor->standoff_m, tnv = sensor->nv_thickness_m, t = thickness_m;
    const double s = sensor->side;
    svp_image *outs[3] = {bx, by, bz};
    for (int comp = 0; comp < 3; comp++) {
        if (!outs[comp]) continue;
#pragma omp parallel for schedule(static)
        for (int j = 0; j < c.ny; j++) {
            int oky, okx;
            double ky = svp_canvas_ky(&c, j, &oky);
            for (int i = 0; i < c.ncx; i++) {
                double kx = svp_canvas_kx(&c, i, &okx), k = hypot(kx, ky);
                double thick = (t > 0 && k > 0) ? -expm1(-k * t) / (k * t) : 1.0;
                /* (μ0/2) e^(−kh) (sinh a / a) (thickness factor): B_z = g k m, B_x = −i s g kx m */
                double g = 0.5 * SVP_MU0 * svp_layer_decay(k, h, tnv) * thick;
                double complex mult;
                if (comp == 2) mult = g * k;
                else if (comp == 0) mult = okx ? -I * s * g * kx : 0;
                else mult = oky ? -I * s * g * ky : 0;
                size_t idx = (size_t)j * c.ncx + i;
                c.work[idx] = c.spec[idx] * mult;
            }
        }
        svp_canvas_emit(&c, outs[comp]);
    }
    svp_canvas_release(&c);
    return SVP_OK;
}

/* ---- strip -------------------------------------------------------------------------------- */

void svp_strip_defaults(svp_strip *strip)
{
    strip->width_m = 40e-6;
    strip->sheet_current = 200;
    strip->centre_x = 0;
    strip->centre_y = 0;
    strip->angle = M_PI / 2;
}

static svp_status strip_validate(const svp_strip *st)
{
    if (!st) return svp_fail(SVP_ERR_INVALID, "strip is NULL");
    if (!(st->width_m > 0) || !isfinite(st->width_m))
        return svp_fail(SVP_ERR_INVALID, "strip width_m %g: must be a finite length > 0 m",
                        st->width_m);
    if (!isfinite(st->sheet_current) || !isfinite(st->centre_x) || !isfinite(st->centre_y) ||
        !isfinite(st->angle))
        return svp_fail(SVP_ERR_INVALID, "strip sheet_current, centre or angle not finite");
    return SVP_OK;
}

/* Layer averages over z in [z1, z2] of atan(c / z) and ln(x² + z²), from their antiderivatives
 * F(z) = z atan(c/z) + (c/2) ln(z² + c²) and G(z) = z ln(x² + z²) − 2z + 2|x| atan(z/|x|). */
static double avg_atan(double c, double z1, double z2)
{
    double f2 = z2 * atan(c / z2) + 0.5 * c * log(z2 * z2 + c * c);
    double f1 = z1 * atan(c / z1) + 0.5 * c * log(z1 * z1 + c * c);
    return (f2 - f1) / (z2 - z1);
}

static double avg_log(double x, double z1, double z2)
{
    double ax = fabs(x);
    double g2 = z2 * log(x * x + z2 * z2) - 2 * z2 + (ax > 0 ? 2 * ax * atan(z2 / ax) : 0);
    double g1 = z1 * log(x * x + z1 * z1) - 2 * z1 + (ax > 0 ? 2 * ax * atan(z1 / ax) : 0);
    return (g2 - g1) / (z2 - z1);
}

svp_status svp_strip_field(const svp_strip *strip, const svp_sensor *sensor, svp_image *bx,
                           svp_image *by, svp_image *bz)
{
    SVP_CHECK(strip_validate(strip));
    SVP_CHECK(svp_sensor_validate(sensor));
    svp_image *ref = bx ? bx : by ? by : bz;
    if (!ref) return svp_fail(SVP_ERR_INVALID, "strip field: no output requested");
    SVP_CHECK(outputs_match(ref, "first output", bx, "bx", by, "by", bz, "bz"));
    const double ux = cos(strip->angle), uy = sin(strip->angle);
    const double nx = uy, ny = -ux; /* n = u × z */
    const double a = 0.5 * strip->width_m, h = sensor->standoff_m;
    const double dx = sensor->pixel_m, s = sensor->side, J = strip->sheet_current;
    const double tnv = sensor->nv_thickness_m;
    /* below ~1e-4 h the layer average equals the plane value to ~1e-9 and the difference of
     * antiderivatives would only lose digits */
    const int layer = tnv > 1e-4 * h;
    const double z1 = h - 0.5 * tnv, z2 = h + 0.5 * tnv;
    const double cn = s * SVP_MU0 * J / (2 * M_PI), cz = SVP_MU0 * J / (4 * M_PI);
    const int w = ref->width, hh = ref->height;
#pragma omp parallel for schedule(static) if ((size_t)w * hh > 4096)
    for (int j = 0; j < hh; j++) {
        for (int i = 0; i < w; i++) {
            double xi = ((i - strip->centre_x) * nx + (j - strip->centre_y) * ny) * dx;
            double bn, bzv;
            if (layer) {
                bn = cn * (avg_atan(a + xi, z1, z2) + avg_atan(a - xi, z1, z2));
                bzv = cz * (avg_log(xi - a, z1, z2) - avg_log(xi + a, z1, z2));
            } else {
                bn = cn * (atan((a + xi) / h) + atan((a - xi) / h));
                bzv = cz * log(((xi - a) * (xi - a) + h * h) / ((xi + a) * (xi + a) + h * h));
            }
            size_t p = (size_t)j * w + i;
            if (bx) bx->data[p] = bn * nx;
            if (by) by->data[p] = bn * ny;
            if (bz) bz->data[p] = bzv;
        }
    }
    return SVP_OK;
}

svp_status svp_strip_current(const svp_strip *strip, double pixel_m, svp_image *jx,
                             svp_image *jy)
{
    SVP_CHECK(strip_validate(strip));
    if (!(pixel_m > 0) || !isfinite(pixel_m))
        return svp_fail(SVP_ERR_INVALID, "strip current: pixel_m %g must be finite > 0",
                        pixel_m);
    svp_image *ref = jx ? jx : jy;
    if (!ref) return svp_fail(SVP_ERR_INVALID, "strip current: no output requested");
    if (jx && jy) SVP_CHECK(svp_image_same_size(jx, jy, "jx", "jy"));
    svp_image *cover = NULL;
    SVP_CHECK(svp_image_new(ref->width, ref->height, &cover));
    /* the band as a rectangle long enough to cross the whole image */
    double length = 4.0 * (ref->width + ref->height + fabs(strip->centre_x) +
                           fabs(strip->centre_y)) + 16;
    svp_status st = svp_raster_rectangle(cover, strip->centre_x, strip->centre_y, length,
                                         strip->width_m / pixel_m, strip->angle, 1.0);
    if (st == SVP_OK) {
        const double jux = strip->sheet_current * cos(strip->angle);
        const double juy = strip->sheet_current * sin(strip->angle);
        const size_t n = (size_t)ref->width * ref->height;
        for (size_t p = 0; p < n; p++) {
            if (jx) jx->data[p] = jux * cover->data[p];
            if (jy) jy->data[p] = juy * cover->data[p];
        }
    }
    svp_image_free(cover);
    return st;
}

/* ---- NV-axis projection ------------------------------------------------------------------- */

svp_status svp_field_project(const svp_image *bx, const svp_image *by, const svp_image *bz,
                             const double axis[3], svp_image *out)
{
    if (!axis || !out) return svp_fail(SVP_ERR_INVALID, "field projection: axis or out NULL");
    double norm = sqrt(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]);
    if (!(norm > 0) || !isfinite(norm))
        return svp_fail(SVP_ERR_INVALID, "NV axis (%g, %g, %g): must be finite and non-zero",
                        axis[0], axis[1], axis[2]);
    const svp_image *comp[3] = {bx, by, bz};
    const char *names[3] = {"bx", "by", "bz"};
    for (int c = 0; c < 3; c++) {
        if (!comp[c] && axis[c] != 0)
            return svp_fail(SVP_ERR_INVALID,
                            "NV axis component %d is %g but %s is NULL (pass the map or a 0)",
                            c, axis[c], names[c]);
        if (comp[c]) SVP_CHECK(svp_image_same_size(out, comp[c], "out", names[c]));
    }
    const double a[3] = {axis[0] / norm, axis[1] / norm, axis[2] / norm};
    const size_t n = (size_t)out->width * out->height;
    const double *restrict px = bx ? bx->data : NULL, *restrict py = by ? by->data : NULL;
    const double *restrict pz = bz ? bz->data : NULL;
    double *restrict o = out->data;
#pragma omp parallel for schedule(static) if (n > 32768)
    for (size_t p = 0; p < n; p++)
        o[p] = (px ? a[0] * px[p] : 0) + (py ? a[1] * py[p] : 0) + (pz ? a[2] * pz[p] : 0);
    return SVP_OK;
}
