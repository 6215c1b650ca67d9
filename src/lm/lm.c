/* Levenberg–Marquardt for small dense problems (docs/model.md §8): Marquardt scaling, each
 * damped step solved by QR of the augmented system, bounds through smooth transforms, weights
 * from the model (iteratively reweighted). Used by the spot fits (src/psf/fit.c) and the
 * per-pixel ODMR fits (src/physics/spectrum.c). */
#include "lm_internal.h"

#include <float.h>
#include <lapacke.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>


enum { BOUND_NONE = 0, BOUND_BOTH = 1, BOUND_LOWER = 2, BOUND_UPPER = 3 };

struct svp_lm_workspace {
    int cap_params, cap_points;
    svp_lm_problem prob;
    svp_lm_options opt;
    int n, m, nf; /* parameters, points, free parameters */
    int weights_from_model;
    int free_idx[SVP_LM_MAX_PARAMS];
    int kind[SVP_LM_MAX_PARAMS]; /* per free parameter */
    double lo[SVP_LM_MAX_PARAMS], hi[SVP_LM_MAX_PARAMS];
    double x[SVP_LM_MAX_PARAMS], x_trial[SVP_LM_MAX_PARAMS];
    double x_start[SVP_LM_MAX_PARAMS];
    double u[SVP_LM_MAX_PARAMS], u_trial[SVP_LM_MAX_PARAMS], dxdu[SVP_LM_MAX_PARAMS];
    double D[SVP_LM_MAX_PARAMS], tau[SVP_LM_MAX_PARAMS], delta[SVP_LM_MAX_PARAMS];
    double *f, *f_trial, *sw, *r; /* m each: model, trial model, √w, √w (f − y) */
    double *jac;                  /* m × n row-major, from the model (or differences) */
    double *J;                    /* m × nf column-major: √w ∂f/∂u */
    double *QR;                   /* m × nf column-major: J's QR factors */
    double *qtr;                  /* m: Qᵀ r */
    double *A, *b;                /* (2 nf) × nf and 2 nf: the damped subproblem */
    double *cov;                  /* n × n */
    double *work;
    int lwork;
    double chi2, lambda, nu, last_step;
    int iter, nev, initialized;
    svp_lm_stop stop;
};

void svp_lm_defaults(svp_lm_options *o)
{
    o->max_iterations = 200;
    o->xtol = 1e-8;
    o->gtol = 1e-10;
    o->ftol = 1e-8;
    o->lambda_init = 1e-3;
    o->fd_step = sqrt(DBL_EPSILON);
    o->covariance = SVP_LM_COV_AUTO;
}

double svp_noise_variance(const svp_noise_model *noise, double p)
{
    double v = noise->sigma_bg * noise->sigma_bg;
    if (noise->gain > 0) v += fmax(p, 1.0 / noise->gain) / noise->gain;
    if (noise->excess > 0) v += (noise->excess * p) * (noise->excess * p);
    return v > 0 ? v : 1.0;
}

const char *svp_lm_stop_string(svp_lm_stop stop)
{
    switch (stop) {
    case SVP_LM_RUNNING: return "running";
    case SVP_LM_XTOL: return "small step";
    case SVP_LM_GTOL: return "small gradient";
    case SVP_LM_FTOL: return "small chi-square change";
    case SVP_LM_ROUNDOFF: return "no further decrease at machine precision";
    case SVP_LM_MAX_ITER: return "maximum number of iterations reached";
    case SVP_LM_STUCK: return "no decreasing step although the gradient is not small";
    }
    return "unknown";
}

void svp_lm_workspace_free(svp_lm_workspace *ws)
{
    if (!ws) return;
    free(ws->f);
    free(ws->f_trial);
    free(ws->sw);
    free(ws->r);
    free(ws->jac);
    free(ws->J);
    free(ws->QR);
    free(ws->qtr);
    free(ws->A);
    free(ws->b);
    free(ws->cov);
    free(ws->work);
    free(ws);
}

svp_status svp_lm_workspace_new(int max_params, int max_points, svp_lm_workspace **out)
{
    if (!out) return svp_fail(SVP_ERR_INVALID, "svp_lm_workspace_new: out is NULL");
    *out = NULL;
    if (max_params < 1 || max_params > SVP_LM_MAX_PARAMS)
        return svp_fail(SVP_ERR_INVALID, "LM workspace: max_params must be in 1..%d, got %d",
                        SVP_LM_MAX_PARAMS, max_params);
    if (max_points < 1)
        return svp_fail(SVP_ERR_INVALID, "LM workspace: max_points must be >= 1, got %d",
                        max_points);
    svp_lm_workspace *ws = calloc(1, sizeof *ws);
    if (!ws) return svp_fail(SVP_ERR_NOMEM, "LM workspace: out of memory");
    const size_t m = (size_t)max_points, n = (size_t)max_params;
    ws->cap_params = max_params;
    ws->cap_points = max_points;
    ws->f = malloc(m * sizeof(double));
    ws->f_trial = malloc(m * sizeof(double));
    ws->sw = malloc(m * sizeof(double));
    ws->r = malloc(m * sizeof(double));
    ws->qtr = malloc(m * sizeof(double));
    ws->jac = malloc(m * n * sizeof(double));
    ws->J = malloc(m * n * sizeof(double));
    ws->QR = malloc(m * n * sizeof(double));
    ws->A = malloc(2 * n * n * sizeof(double));
    ws->b = malloc(2 * n * sizeof(double));
    ws->cov = malloc(n * n * sizeof(double));
    if (!ws->f || !ws->f_trial || !ws->sw || !ws->r || !ws->qtr || !ws->jac || !ws->J ||
        !ws->QR || !ws->A || !ws->b || !ws->cov) {
        svp_lm_workspace_free(ws);
        return svp_fail(SVP_ERR_NOMEM, "LM workspace for %d parameters x %d points: out of "
                        "memory", max_params, max_points);
    }
    /* LAPACK work sizes for the largest problem, queried once: iterate never allocates. The
     * column-major _work interfaces call LAPACK directly (no transposed copies). */
    double q1 = 0, q2 = 0, q3 = 0;
    lapack_int mm = max_points, nn = max_params, m2 = 2 * max_params;
    if (mm < nn) mm = nn;
    LAPACKE_dgeqrf_work(LAPACK_COL_MAJOR, mm, nn, ws->QR, mm, ws->tau, &q1, -1);
    LAPACKE_dormqr_work(LAPACK_COL_MAJOR, 'L', 'T', mm, 1, nn, ws->QR, mm, ws->tau, ws->qtr, mm,
                        &q2, -1);
    LAPACKE_dgels_work(LAPACK_COL_MAJOR, 'N', m2, nn, 1, ws->A, m2, ws->b, m2, &q3, -1);
    double q = fmax(fmax(q1, q2), fmax(q3, (double)(4 * max_params)));
    ws->lwork = (int)q + 64;
    ws->work = malloc((size_t)ws->lwork * sizeof(double));
    if (!ws->work) {
        svp_lm_workspace_free(ws);
        return svp_fail(SVP_ERR_NOMEM, "LM workspace: out of memory");
    }
    *out = ws;
    return SVP_OK;
}

static double softplus(double u) { return u > 30 ? u + log1p(exp(-u)) : log1p(exp(u)); }
static double softplus_inv(double s) { return s > 30 ? s + log(-expm1(-s)) : log(expm1(s)); }
static double sigmoid(double u) { return 1.0 / (1.0 + exp(-u)); }

/* x from u for free parameter k; also dx/du. */
static double to_external(const svp_lm_workspace *ws, int k, double u, double *dxdu)
{
    int j = ws->free_idx[k];
    double lo = ws->lo[j], hi = ws->hi[j];
    switch (ws->kind[k]) {
    case BOUND_BOTH:
        if (dxdu) *dxdu = 0.5 * (hi - lo) * cos(u);
        return lo + 0.5 * (hi - lo) * (1.0 + sin(u));
    case BOUND_LOWER:
        if (dxdu) *dxdu = sigmoid(u);
        return lo + softplus(u);
    case BOUND_UPPER:
        if (dxdu) *dxdu = -sigmoid(u);
        return hi - softplus(u);
    default:
        if (dxdu) *dxdu = 1.0;
        return u;
    }
}

/* u from x (x strictly inside the bounds: init nudges it there). */
static double to_internal(const svp_lm_workspace *ws, int k, double x)
{
    int j = ws->free_idx[k];
    double lo = ws->lo[j], hi = ws->hi[j];
    switch (ws->kind[k]) {
    case BOUND_BOTH: {
        double s = 2.0 * (x - lo) / (hi - lo) - 1.0;
        return asin(fmax(-1.0, fmin(1.0, s)));
    }
    case BOUND_LOWER: return softplus_inv(x - lo);
    case BOUND_UPPER: return softplus_inv(hi - x);
    default: return x;
    }
}

static void set_external(svp_lm_workspace *ws, const double *u, double *x, double *dxdu)
{
    for (int k = 0; k < ws->nf; k++) x[ws->free_idx[k]] = to_external(ws, k, u[k], &dxdu[k]);
}

static int all_finite(const double *v, size_t n)
{
    for (size_t i = 0; i < n; i++)
        if (!isfinite(v[i])) return 0;
    return 1;
}

/* Model values (and the Jacobian when jac != NULL): 0 on success. */
static int evaluate(svp_lm_workspace *ws, const double *x, double *f, double *jac)
{
    ws->nev++;
    const svp_lm_problem *p = &ws->prob;
    if (p->model(p->user, x, ws->n, ws->m, f, jac) != 0) return -1;
    if (!all_finite(f, (size_t)ws->m)) return -1;
    if (jac) {
        for (int i = 0; i < ws->m; i++)
            for (int k = 0; k < ws->nf; k++)
                if (!isfinite(jac[(size_t)i * ws->n + ws->free_idx[k]])) return -1;
    }
    return 0;
}

/* Forward differences in θ (backward at an upper bound), columns of free parameters only;
 * ws->f must hold f(x). Uses f_trial as scratch. */
static int finite_differences(svp_lm_workspace *ws)
{
    const int n = ws->n, m = ws->m;
    double xt[SVP_LM_MAX_PARAMS];
    memcpy(xt, ws->x, (size_t)n * sizeof(double));
    for (int k = 0; k < ws->nf; k++) {
        int j = ws->free_idx[k];
        double scale = fmax(fmax(fabs(ws->x[j]), fabs(ws->x_start[j])), 1e-3);
        double h = ws->opt.fd_step * scale;
        if (ws->x[j] + h > ws->hi[j]) h = -h;
        volatile double xh = ws->x[j] + h; /* the step actually taken, exactly representable */
        h = xh - ws->x[j];
        xt[j] = xh;
        if (evaluate(ws, xt, ws->f_trial, NULL) != 0) return -1;
        xt[j] = ws->x[j];
        for (int i = 0; i < m; i++) ws->jac[(size_t)i * n + j] = (ws->f_trial[i] - ws->f[i]) / h;
    }
    return 0;
}

/* From f (and jac) at the current x: weights, residuals, χ², the scaled Jacobian J, D. */
static void update_linearisation(svp_lm_workspace *ws)
{
    const svp_lm_problem *p = &ws->prob;
    const int m = ws->m, n = ws->n;
    double chi2 = 0;
    for (int i = 0; i < m; i++) {
        if (p->sigma)
            ws->sw[i] = 1.0 / p->sigma[i];
        else if (ws->weights_from_model)
            ws->sw[i] = 1.0 / sqrt(svp_noise_variance(&p->noise, ws->f[i]));
        else
            ws->sw[i] = 1.0;
        double y = p->data ? p->data[i] : 0.0;
        ws->r[i] = ws->sw[i] * (ws->f[i] - y);
        chi2 += ws->r[i] * ws->r[i];
    }
    ws->chi2 = chi2;
    for (int k = 0; k < ws->nf; k++) {
        int j = ws->free_idx[k];
        double *col = ws->J + (size_t)k * m, norm2 = 0;
        for (int i = 0; i < m; i++) {
            col[i] = ws->sw[i] * ws->jac[(size_t)i * n + j] * ws->dxdu[k];
            norm2 += col[i] * col[i];
        }
        /* Marquardt scaling, monotone as in MINPACK so the trust region cannot collapse on a
         * column that vanishes temporarily (a sin-bounded parameter passing its bound). */
        double d = sqrt(norm2);
        if (d > ws->D[k]) ws->D[k] = d;
        if (!(ws->D[k] > 0)) ws->D[k] = 1.0;
    }
}

/* Model and Jacobian at ws->x into f and jac. */
static int linearise(svp_lm_workspace *ws)
{
    if (ws->prob.analytic_jacobian) {
        if (evaluate(ws, ws->x, ws->f, ws->jac) != 0) return -1;
    } else {
        if (finite_differences(ws) != 0) return -1;
    }
    return 0;
}

svp_status svp_lm_init(svp_lm_workspace *ws, const svp_lm_problem *problem,
                       const svp_lm_options *options, const double *params0)
{
    if (!ws || !problem || !params0)
        return svp_fail(SVP_ERR_INVALID, "svp_lm_init: workspace, problem and params0 are "
                        "required");
    ws->initialized = 0;
    const svp_lm_problem *p = problem;
    if (p->n_params < 1 || p->n_params > ws->cap_params)
        return svp_fail(SVP_ERR_INVALID, "LM: n_params = %d outside the workspace's 1..%d",
                        p->n_params, ws->cap_params);
    if (p->n_points < 1 || p->n_points > ws->cap_points)
        return svp_fail(SVP_ERR_INVALID, "LM: n_points = %d outside the workspace's 1..%d",
                        p->n_points, ws->cap_points);
    if (!p->model) return svp_fail(SVP_ERR_INVALID, "LM: the problem has no model function");
    if (options) {
        ws->opt = *options;
        if (ws->opt.max_iterations < 0 || !(ws->opt.xtol >= 0) || !(ws->opt.gtol >= 0) ||
            !(ws->opt.ftol >= 0) || !(ws->opt.lambda_init > 0) || !(ws->opt.fd_step > 0))
            return svp_fail(SVP_ERR_INVALID, "LM options out of range: max_iterations %d, xtol "
                            "%g, gtol %g, ftol %g, lambda_init %g, fd_step %g (need >= 0, "
                            "lambda_init and fd_step > 0)", ws->opt.max_iterations,
                            ws->opt.xtol, ws->opt.gtol, ws->opt.ftol, ws->opt.lambda_init,
                            ws->opt.fd_step);
    } else {
        svp_lm_defaults(&ws->opt);
    }
    const svp_noise_model *nm = &p->noise;
    if (!(nm->sigma_bg >= 0) || !(nm->gain >= 0) || !(nm->excess >= 0) ||
        !isfinite(nm->sigma_bg + nm->gain + nm->excess))
        return svp_fail(SVP_ERR_INVALID, "LM noise model: sigma_bg %g, gain %g, excess %g "
                        "must be finite and >= 0", nm->sigma_bg, nm->gain, nm->excess);
    ws->prob = *p;
    ws->n = p->n_params;
    ws->m = p->n_points;
    ws->weights_from_model = !p->sigma && (nm->sigma_bg > 0 || nm->gain > 0 || nm->excess > 0);
    if (p->sigma) {
        for (int i = 0; i < ws->m; i++)
            if (!(p->sigma[i] > 0) || !isfinite(p->sigma[i]))
                return svp_fail(SVP_ERR_INVALID, "LM: sigma[%d] = %g must be positive and "
                                "finite", i, p->sigma[i]);
    }
    if (p->data) {
        for (int i = 0; i < ws->m; i++)
            if (!isfinite(p->data[i]))
                return svp_fail(SVP_ERR_INVALID, "LM: data[%d] is not finite", i);
    }
    ws->nf = 0;
    for (int j = 0; j < ws->n; j++) {
        double lo = p->lower ? p->lower[j] : -INFINITY;
        double hi = p->upper ? p->upper[j] : INFINITY;
        if (isnan(lo) || isnan(hi) || lo > hi || lo == INFINITY || hi == -INFINITY)
            return svp_fail(SVP_ERR_INVALID, "LM: bounds of parameter %d are [%g, %g]", j, lo,
                            hi);
        if (!isfinite(params0[j]))
            return svp_fail(SVP_ERR_INVALID, "LM: initial parameter %d is not finite", j);
        ws->lo[j] = lo;
        ws->hi[j] = hi;
        double x = fmin(fmax(params0[j], lo), hi);
        if (lo == hi) {
            ws->x[j] = lo;
            continue;
        }
        int k = ws->nf++;
        ws->free_idx[k] = j;
        ws->kind[k] = isfinite(lo) && isfinite(hi) ? BOUND_BOTH
                      : isfinite(lo)               ? BOUND_LOWER
                      : isfinite(hi)               ? BOUND_UPPER
                                                   : BOUND_NONE;
        /* Start strictly inside: at a bound the transform's derivative is 0 and the
         * parameter could never move. */
        if (ws->kind[k] == BOUND_BOTH) {
            double margin = 1e-3 * (hi - lo);
            x = fmin(fmax(x, lo + margin), hi - margin);
        } else if (ws->kind[k] == BOUND_LOWER) {
            x = fmax(x, lo + 1e-6 * fmax(1.0, fabs(lo)));
        } else if (ws->kind[k] == BOUND_UPPER) {
            x = fmin(x, hi - 1e-6 * fmax(1.0, fabs(hi)));
        }
        ws->x[j] = x;
    }
    if (ws->m < ws->nf)
        return svp_fail(SVP_ERR_INVALID, "LM: %d points cannot determine %d free parameters",
                        ws->m, ws->nf);
    memcpy(ws->x_start, ws->x, (size_t)ws->n * sizeof(double));
    memcpy(ws->x_trial, ws->x, (size_t)ws->n * sizeof(double));
    for (int k = 0; k < ws->nf; k++) {
        ws->u[k] = to_internal(ws, k, ws->x[ws->free_idx[k]]);
        to_external(ws, k, ws->u[k], &ws->dxdu[k]);
        ws->D[k] = 0;
    }
    ws->nev = 0;
    ws->iter = 0;
    ws->stop = SVP_LM_RUNNING;
    ws->lambda = ws->opt.lambda_init;
    ws->nu = 2.0;
    ws->last_step = 0;
    if (evaluate(ws, ws->x, ws->f, ws->prob.analytic_jacobian ? ws->jac : NULL) != 0)
        return svp_fail(SVP_ERR_INVALID, "LM: the model cannot be evaluated (or is not finite)"
                        " at the initial parameters");
    if (!ws->prob.analytic_jacobian && finite_differences(ws) != 0)
        return svp_fail(SVP_ERR_INVALID, "LM: the model cannot be evaluated near the initial "
                        "parameters (finite differences)");
    update_linearisation(ws);
    if (ws->nf == 0) ws->stop = SVP_LM_XTOL;
    ws->initialized = 1;
    return SVP_OK;
}

void svp_lm_params(const svp_lm_workspace *ws, double *params)
{
    memcpy(params, ws->x, (size_t)ws->n * sizeof(double));
}

static double norm2_scaled(const double *D, const double *v, int n)
{
    double s = 0;
    for (int k = 0; k < n; k++) s += (D[k] * v[k]) * (D[k] * v[k]);
    return sqrt(s);
}

svp_status svp_lm_iterate(svp_lm_workspace *ws, svp_lm_stop *stop)
{
    if (!ws || !ws->initialized)
        return svp_fail(SVP_ERR_INVALID, "svp_lm_iterate: workspace not initialised");
    if (stop) *stop = ws->stop;
    if (ws->stop != SVP_LM_RUNNING) return SVP_OK;
    const int m = ws->m, nf = ws->nf, n2 = 2 * nf;
    const double *y = ws->prob.data;
    if (ws->chi2 == 0) {
        ws->stop = SVP_LM_GTOL;
        if (stop) *stop = ws->stop;
        return SVP_OK;
    }

    /* QR of J once per iteration; every trial λ then costs a (2 nf × nf) QR only. */
    memcpy(ws->QR, ws->J, (size_t)m * nf * sizeof(double));
    memcpy(ws->qtr, ws->r, (size_t)m * sizeof(double));
    lapack_int info = LAPACKE_dgeqrf_work(LAPACK_COL_MAJOR, m, nf, ws->QR, m, ws->tau, ws->work,
                                          ws->lwork);
    if (info == 0)
        info = LAPACKE_dormqr_work(LAPACK_COL_MAJOR, 'L', 'T', m, 1, nf, ws->QR, m, ws->tau,
                                   ws->qtr, m, ws->work, ws->lwork);
    if (info != 0)
        return svp_fail(SVP_ERR_INTERNAL, "LM: LAPACK QR failed (info %d)", (int)info);

    /* Gradient test: the cosine between each column of J and the residual vector. */
    double rnorm = sqrt(ws->chi2), gmax = 0;
    for (int k = 0; k < nf; k++) {
        const double *col = ws->J + (size_t)k * m;
        double g = 0, cn = 0;
        for (int i = 0; i < m; i++) {
            g += col[i] * ws->r[i];
            cn += col[i] * col[i];
        }
        if (cn > 0) gmax = fmax(gmax, fabs(g) / (sqrt(cn) * rnorm));
    }
    if (gmax <= ws->opt.gtol) {
        ws->stop = SVP_LM_GTOL;
        if (stop) *stop = ws->stop;
        return SVP_OK;
    }

    for (int attempt = 0; attempt < 100; attempt++) {
        /* min ‖J δ + r‖² + λ ‖D δ‖²  ⇔  [R; √λ D] δ = [−Qᵀr; 0] in the least-squares sense. */
        double sl = sqrt(ws->lambda);
        for (int k = 0; k < nf; k++) {
            double *col = ws->A + (size_t)k * n2;
            for (int i = 0; i < nf; i++) col[i] = i <= k ? ws->QR[(size_t)k * m + i] : 0.0;
            for (int i = 0; i < nf; i++) col[nf + i] = i == k ? sl * ws->D[k] : 0.0;
            ws->b[k] = -ws->qtr[k];
            ws->b[nf + k] = 0.0;
        }
        info = LAPACKE_dgels_work(LAPACK_COL_MAJOR, 'N', n2, nf, 1, ws->A, n2, ws->b, n2,
                                  ws->work, ws->lwork);
        if (info < 0)
            return svp_fail(SVP_ERR_INTERNAL, "LM: LAPACK dgels failed (info %d)", (int)info);
        double pred = -1;
        int ok = info == 0;
        if (ok) {
            memcpy(ws->delta, ws->b, (size_t)nf * sizeof(double));
            /* predicted decrease of the linear model: ‖Qᵀr‖² − ‖Qᵀr + R δ‖² (first nf rows) */
            double a0 = 0, a1 = 0;
            for (int i = 0; i < nf; i++) {
                double t = ws->qtr[i];
                for (int k = i; k < nf; k++) t += ws->QR[(size_t)k * m + i] * ws->delta[k];
                a0 += ws->qtr[i] * ws->qtr[i];
                a1 += t * t;
            }
            pred = a0 - a1;
            for (int k = 0; k < nf; k++) ws->u_trial[k] = ws->u[k] + ws->delta[k];
            double dxdu_trial[SVP_LM_MAX_PARAMS];
            set_external(ws, ws->u_trial, ws->x_trial, dxdu_trial);
            ok = evaluate(ws, ws->x_trial, ws->f_trial, NULL) == 0;
        }
        double chi2_trial = INFINITY;
        if (ok) {
            chi2_trial = 0;
            for (int i = 0; i < m; i++) {
                double t = ws->sw[i] * (ws->f_trial[i] - (y ? y[i] : 0.0));
                chi2_trial += t * t;
            }
        }
        double step = ok ? norm2_scaled(ws->D, ws->delta, nf) : INFINITY;
        double unorm = norm2_scaled(ws->D, ws->u, nf);
        if (ok && chi2_trial < ws->chi2) {
            double chi2_old = ws->chi2;
            double rho = pred > 0 ? (chi2_old - chi2_trial) / pred : 0;
            /* Nielsen's update of the damping */
            double t = 2 * rho - 1;
            ws->lambda *= fmax(1.0 / 3.0, 1.0 - t * t * t);
            ws->nu = 2.0;
            memcpy(ws->u, ws->u_trial, (size_t)nf * sizeof(double));
            set_external(ws, ws->u, ws->x, ws->dxdu);
            memcpy(ws->f, ws->f_trial, (size_t)m * sizeof(double));
            if (linearise(ws) != 0)
                return svp_fail(SVP_ERR_NUMERIC, "LM: the Jacobian is not finite at an "
                                "accepted point (iteration %d)", ws->iter + 1);
            update_linearisation(ws);
            ws->iter++;
            ws->last_step = step;
            if (step <= ws->opt.xtol * (unorm + ws->opt.xtol))
                ws->stop = SVP_LM_XTOL;
            else if (chi2_old - chi2_trial <= ws->opt.ftol * chi2_old &&
                     pred <= ws->opt.ftol * chi2_old)
                ws->stop = SVP_LM_FTOL;
            if (stop) *stop = ws->stop;
            return SVP_OK;
        }
        /* Rejected. At machine precision the model can no longer tell the points apart. */
        if (ok && (pred <= 4 * DBL_EPSILON * ws->chi2 || step <= 4 * DBL_EPSILON * unorm)) {
            ws->stop = SVP_LM_ROUNDOFF;
            if (stop) *stop = ws->stop;
            return SVP_OK;
        }
        ws->lambda *= ws->nu;
        ws->nu *= 2.0;
        if (ws->lambda > 1e300) break;
    }
    ws->stop = SVP_LM_STUCK;
    if (stop) *stop = ws->stop;
    return svp_fail(SVP_ERR_NUMERIC, "LM: no step decreases chi-square %.6g at iteration %d "
                    "(the largest gradient cosine is %.3g): the model is not smooth or its "
                    "Jacobian is wrong", ws->chi2, ws->iter, gmax);
}

svp_status svp_lm_finish(svp_lm_workspace *ws, double *params, svp_lm_result *result,
                         double *covariance)
{
    if (!ws || !ws->initialized)
        return svp_fail(SVP_ERR_INVALID, "svp_lm_finish: workspace not initialised");
    const int n = ws->n, m = ws->m;
    if (params) svp_lm_params(ws, params);
    svp_lm_result res;
    memset(&res, 0, sizeof res);
    res.chi2 = ws->chi2;
    res.dof = m - ws->nf;
    res.chi2_red = res.dof > 0 ? ws->chi2 / res.dof : 0.0;
    res.iterations = ws->iter;
    res.evaluations = ws->nev;
    res.stop = ws->stop;

    /* Covariance from the Jacobian in θ (not u): at a bound the transform's derivative
     * vanishes, so such parameters are held fixed and reported with infinite variance. */
    int cols[SVP_LM_MAX_PARAMS], nc = 0;
    for (int k = 0; k < ws->nf; k++) {
        int j = ws->free_idx[k];
        double range = ws->hi[j] - ws->lo[j];
        double x = ws->x[j];
        int at = 0;
        if (ws->kind[k] == BOUND_BOTH)
            at = x - ws->lo[j] <= 1e-4 * range || ws->hi[j] - x <= 1e-4 * range;
        else if (ws->kind[k] == BOUND_LOWER)
            at = x - ws->lo[j] <= 1e-6 * fmax(1.0, fabs(ws->lo[j]));
        else if (ws->kind[k] == BOUND_UPPER)
            at = ws->hi[j] - x <= 1e-6 * fmax(1.0, fabs(ws->hi[j]));
        if (at)
            res.at_bound |= 1ull << j;
        else
            cols[nc++] = j;
    }
    double *C = ws->cov;
    memset(C, 0, (size_t)n * n * sizeof(double));
    res.covariance_ok = 1;
    if (nc > 0) {
        for (int c = 0; c < nc; c++) {
            double *col = ws->QR + (size_t)c * m;
            for (int i = 0; i < m; i++)
                col[i] = ws->sw[i] * ws->jac[(size_t)i * n + cols[c]];
        }
        lapack_int info = LAPACKE_dgeqrf_work(LAPACK_COL_MAJOR, m, nc, ws->QR, m, ws->tau,
                                              ws->work, ws->lwork);
        double dmax = 0, dmin = INFINITY;
        for (int c = 0; c < nc; c++) {
            double d = fabs(ws->QR[(size_t)c * m + c]);
            dmax = fmax(dmax, d);
            dmin = fmin(dmin, d);
        }
        /* (JᵀWJ)⁻¹ = (RᵀR)⁻¹: dpotri on the triangular factor R. */
        double *Rinv = ws->A; /* nc × nc, lda nc */
        for (int c = 0; c < nc; c++)
            for (int i = 0; i < nc; i++)
                Rinv[(size_t)c * nc + i] = i <= c ? ws->QR[(size_t)c * m + i] : 0.0;
        if (info != 0 || !(dmin > 1e-13 * dmax) ||
            LAPACKE_dpotri_work(LAPACK_COL_MAJOR, 'U', nc, Rinv, nc) != 0) {
            res.covariance_ok = 0;
        } else {
            double scale = 1.0;
            int unit = !ws->prob.sigma && !ws->weights_from_model;
            if (ws->opt.covariance == SVP_LM_COV_SCALED ||
                (ws->opt.covariance == SVP_LM_COV_AUTO && unit))
                scale = res.dof > 0 ? res.chi2_red : 1.0;
            for (int a = 0; a < nc; a++)
                for (int b2 = 0; b2 < nc; b2++) {
                    int lo = a < b2 ? a : b2, hi = a < b2 ? b2 : a;
                    double v = Rinv[(size_t)hi * nc + lo] * scale;
                    C[(size_t)cols[a] * n + cols[b2]] = v;
                }
        }
    }
    for (int k = 0; k < ws->nf; k++) {
        int j = ws->free_idx[k];
        if (!res.covariance_ok || (res.at_bound >> j & 1)) C[(size_t)j * n + j] = INFINITY;
    }
    if (!res.covariance_ok)
        for (int a = 0; a < n; a++)
            for (int b2 = 0; b2 < n; b2++)
                if (a != b2) C[(size_t)a * n + b2] = 0.0;
    if (covariance) memcpy(covariance, C, (size_t)n * n * sizeof(double));
    if (result) *result = res;
    return SVP_OK;
}

svp_status svp_lm_solve(svp_lm_workspace *ws, const svp_lm_problem *problem,
                        const svp_lm_options *options, double *params, svp_lm_result *result,
                        double *covariance)
{
    SVP_CHECK(svp_lm_init(ws, problem, options, params));
    svp_status st = SVP_OK;
    svp_lm_stop stop = ws->stop;
    while (stop == SVP_LM_RUNNING && ws->iter < ws->opt.max_iterations) {
        st = svp_lm_iterate(ws, &stop);
        if (st != SVP_OK) break;
    }
    if (st == SVP_OK && stop == SVP_LM_RUNNING) {
        ws->stop = stop = SVP_LM_MAX_ITER;
        st = SVP_ERR_NUMERIC;
        svp_lm_finish(ws, params, result, covariance);
        return svp_fail(SVP_ERR_NUMERIC, "LM did not converge after %d iterations (chi-square "
                        "%.6g, last scaled step %.3g, xtol %g)", ws->iter, ws->chi2,
                        ws->last_step, ws->opt.xtol);
    }
    svp_status fst = svp_lm_finish(ws, params, result, covariance);
    return st != SVP_OK ? st : fst;
}

int svp_lm_n_points(const svp_lm_workspace *ws) { return ws->m; }

const double *svp_lm_residuals(const svp_lm_workspace *ws) { return ws->r; }
