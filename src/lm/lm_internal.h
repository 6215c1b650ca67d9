/* What the Levenberg–Marquardt solver (lm.c) offers its users beyond svpsf.h: the weighted
 * residuals of the last evaluation, which the spot fits clip outliers by. */
#ifndef SVP_LM_INTERNAL_H
#define SVP_LM_INTERNAL_H

#include "../core/internal.h"

/* The number of data points m of the problem the workspace was last initialised with. */
int svp_lm_n_points(const svp_lm_workspace *ws);
/* The m weighted residuals √w (f − y) at the current parameters (valid until the next
 * svp_lm_init / svp_lm_iterate on ws). */
const double *svp_lm_residuals(const svp_lm_workspace *ws);

#endif
