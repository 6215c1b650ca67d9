/* The solvers' internals shared within restore/ (and with tests and benchmarks). */
#ifndef SVP_RESTORE_INTERNAL_H
#define SVP_RESTORE_INTERNAL_H

#include "../blur/blur_internal.h"

/* The solvers' workspace kept with an operator (svp_blur.restore), made on first use: the
 * zero-boundary Wiener preconditioner's filter for wiener_balance; the periodic / mirror
 * Wiener gain conj(P) / (|P|² + λ|L|²) (valid when wiener_gain_ok), and for mirror its
 * full-period frame with OTF and buffers; the CG steps and FFT pairs of the last
 * zero-boundary Wiener solve (benchmarks, tests). Freed with the operator. */
typedef struct svp_restore_cache {
    double *wiener_filter; /* ny x ncx on the operator's frame */
    double wiener_balance;
    int wiener_steps, wiener_pairs;
    fftw_complex *wiener_gain;
    int wiener_gain_ok;
    svp_frame *wiener_frame;
    double *wiener_work_r;
    fftw_complex *wiener_work_c;
    size_t filter_bytes, gain_bytes; /* what the filter and the gain hold */
} svp_restore_cache;

/* The operator's workspace, made on first use (NULL: out of memory, the error set). */
svp_restore_cache *svp_restore_cache_of(svp_blur *blur);
/* CG steps and FFT pairs of the operator's last zero-boundary Wiener solve (0 when none). */
void svp_restore_wiener_counts(const svp_blur *blur, int *steps, int *pairs);

/* Tikhonov inverse filter in place (wiener.c): filt (ny x ncx, holding |Ĥ|²) becomes
 * 1 / (nx ny max(|Ĥ|² + λ |L̂|², 1e-12 max |Ĥ|²)), L̂ the 5-point Laplacian's transfer
 * function on the nx x ny frame. */
void svp_tikhonov_invert(double *restrict filt, int nx, int ny, int ncx, double balance);
/* The arguments every deconvolution shares (wiener.c): operator, data y and output x present,
 * both of the operator's size, x not y; `what` names the method in the message. */
typedef struct svp_rl_levels svp_rl_levels;
/* svp_deconv_rl that follows a given extrapolation path: with acceleration, alpha_in (may be
 * NULL: computed) gives the weight α of every iteration and alpha_out (may be NULL) receives the
 * ones used (options->iterations entries each). T⁻¹ runs its numerators on the PL's path, so
 * the two halves of (4) extrapolate alike and their errors cancel as without acceleration. */
svp_status svp_deconv_rl_path(svp_blur *blur, const svp_image *y,
                              const svp_deconv_options *options, svp_image *x,
                              const double *alpha_in, double *alpha_out,
                              svp_rl_levels **levels);
/* The levels of single-precision RL with an operator built in single precision (rl.c,
 * docs/model.md §6 (11b)): the data's shape s and H1, Hs, Hᵀm, Hᵀs, transformed once in float.
 * levels (may be NULL: the run makes its own) passed to svp_deconv_rl_path with *levels NULL
 * receives the run's, and with *levels set the run uses those instead of its own: T⁻¹ gives
 * its numerators the PL's, so the levels' float round-off is the same bits in both halves of
 * (4), scales with their fits and cancels. Same size and missing pixels required. Nothing is
 * made or used for other operators. */
void svp_rl_levels_free(svp_rl_levels *levels);
/* k² of the field noise model σ_B² = k² / Ĩ (noise.c); 0 when nothing is usable. */
svp_status svp_field_noise_k2(const svp_image *field, const svp_image *pl, double *k2);
/* The discrepancy principle with a per-pixel noise variance (NULL: sigma², sigma <= 0
 * estimated): Σ M (H x_λ − y)² / var = n_finite. *at_bound: −1 / +1 when the choice is the
 * lower / upper end of the search, else 0. *sigma_used: the σ used; with a variance map the
 * rms of its σ over the measured pixels. lcurve (may be NULL: no fallback): when no λ the
 * search can solve meets the noise, the L-curve's corner is taken instead and *lcurve = 1
 * (wiener.c; docs/model.md §6). */
svp_status svp_wiener_balance_discrepancy_var(svp_blur *blur, const svp_image *y,
                                              const svp_image *variance, double sigma,
                                              int cg_max_steps, double *balance,
                                              double *sigma_used, int *at_bound, int *lcurve);
svp_status svp_deconv_check_images(const svp_blur *blur, const svp_image *y, const svp_image *x,
                                   const char *what);

#endif
