/* What the spot fits (fit.c) offer the layers above them beyond svpsf.h: the pair method
 * (src/restore/pair.c) fits the emission spot keeping the mask of pixels it used, and turns
 * the fitted excitation spot into a kernel. */
#ifndef SVP_SPOT_INTERNAL_H
#define SVP_SPOT_INTERNAL_H

#include "../core/internal.h"

/* svp_spot_fit without model or residual images; used (width * height bytes, may be NULL)
 * receives 1 for every pixel the final fit used and 0 for those it excluded (saturated, hot,
 * clipped, non-finite, outside the fit window). */
svp_status svp_spot_fit_used(const svp_image *spot, const svp_spot_options *options,
                             svp_spot_result *res, unsigned char *used);

/* The kernel of a fitted spot: a (2R+1)² image centred on the rounded fitted centre, inside a
 * disc of radius R; from_fit = 0: the measured image ex with the fitted background removed
 * (negatives and non-finite pixels 0), from_fit = 1: the fitted profile without background
 * (pixel-integrated when so->pixel_integration). *out is new on success. */
svp_status svp_spot_kernel(const svp_image *ex, const svp_spot_result *fit,
                           const svp_spot_options *so, int R, int from_fit, svp_image **out);

#endif
