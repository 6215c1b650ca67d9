/* Small helpers shared by the test suites. */
#ifndef SVP_TEST_HELPERS_H
#define SVP_TEST_HELPERS_H

#include <math.h>
#include <stdarg.h>
#include <stddef.h>
#include <setjmp.h>
#include <stdint.h>
#include <string.h>
#include <stdlib.h>
#include <cmocka.h>

#include "svpsf.h"

#define ASSERT_OK(expr)                                                                        \
    do {                                                                                       \
        svp_status st_ = (expr);                                                               \
        if (st_ != SVP_OK) fail_msg("%s failed: %s", #expr, svp_last_error());                 \
    } while (0)

#define ASSERT_CLOSE(a, b, tol)                                                                \
    do {                                                                                       \
        double a_ = (a), b_ = (b);                                                             \
        if (!(fabs(a_ - b_) <= (tol)))                                                         \
            fail_msg("%s = %.17g, %s = %.17g, |diff| %.3g > %.3g", #a, a_, #b, b_,             \
                     fabs(a_ - b_), (double)(tol));                                            \
    } while (0)

/* Deterministic pseudo-random numbers in [0, 1) (xorshift64*). */
static inline double test_rand(uint64_t *state)
{
    uint64_t x = *state;
    x ^= x >> 12;
    x ^= x << 25;
    x ^= x >> 27;
    *state = x;
    return (double)((x * 0x2545F4914F6CDD1DULL) >> 11) * (1.0 / 9007199254740992.0);
}

static inline svp_image *test_image(int w, int h)
{
    svp_image *img = NULL;
    if (svp_image_new(w, h, &img) != SVP_OK) fail_msg("image: %s", svp_last_error());
    return img;
}

static inline svp_image *test_random_image(int w, int h, uint64_t seed)
{
    svp_image *img = test_image(w, h);
    uint64_t s = seed * 2654435761ULL + 88172645463325252ULL;
    for (size_t i = 0; i < (size_t)w * h; i++) img->data[i] = test_rand(&s);
    return img;
}

static inline double test_dot(const svp_image *a, const svp_image *b)
{
    long double s = 0;
    for (size_t i = 0; i < (size_t)a->width * a->height; i++) s += (long double)a->data[i] * b->data[i];
    return (double)s;
}

static inline double test_sum(const svp_image *a)
{
    long double s = 0;
    for (size_t i = 0; i < (size_t)a->width * a->height; i++) s += a->data[i];
    return (double)s;
}

static inline double test_max_abs_diff(const svp_image *a, const svp_image *b)
{
    double m = 0;
    for (size_t i = 0; i < (size_t)a->width * a->height; i++) {
        double d = fabs(a->data[i] - b->data[i]);
        if (!(d <= m)) m = d;
    }
    return m;
}

static inline double test_max_abs(const svp_image *a)
{
    double m = 0;
    for (size_t i = 0; i < (size_t)a->width * a->height; i++)
        if (!(fabs(a->data[i]) <= m)) m = fabs(a->data[i]);
    return m;
}

static inline int test_all_finite(const svp_image *a)
{
    return svp_image_count_nonfinite(a) == 0;
}

/* A progress callback's record: calls, the last fraction, whether the fractions never went
 * down (strict: always went up) and stayed <= 1; it cancels at call cancel_at (> 0). */
typedef struct test_progress_rec {
    int calls, cancel_at;
    double last;
    int monotone, strict;
} test_progress_rec;

static inline int test_progress_record(void *user, double fraction)
{
    test_progress_rec *p = user;
    p->calls++;
    if ((p->strict ? !(fraction > p->last) : fraction < p->last) || fraction > 1) p->monotone = 0;
    p->last = fraction;
    return p->cancel_at > 0 && p->calls >= p->cancel_at;
}

#endif
