/* PSF files (YAML), the uniform case of the PSF description:
 *
 *   pixel_um: 0.1                 # required, >= 1e-6: the camera pixel in the sample plane
 *   psf:                          # required
 *     model: moffat               # required: gaussian | lorentzian | moffat
 *     fwhm_um: 0.61               # required, > 0 (major axis when elliptical)
 *     beta: 1.1                   # >= 0.5; required for moffat, 1 (or absent) for lorentzian,
 *                                 #   absent for gaussian
 *     halo: 0.0                   # alpha_b in [0, 1), default 0
 *     fwhm_minor_um: 0.5          # > 0 and <= fwhm_um; absent = circular
 *     angle_deg: 30               # major-axis angle from +x towards +y; default 0
 *     support_um: 20              # >= 0; 0 (default) = the whole field of view
 *     subsample: 0                # 0..64; 0 (default) = automatic
 *   boundary: zero                # optional: zero | mirror | periodic (default zero)
 *   provenance: "fit of spot 3"   # optional free text (also: comment); not interpreted
 *
 * Unknown keys, wrong types and impossible values are errors naming file:line:column. */
#include "../core/internal.h"
#include "yaml.h"

#include <math.h>
#include <stdio.h>
#include <string.h>

static const char *const top_keys[] = {"pixel_um",   "psf",     "boundary",
                                       "provenance", "comment", NULL};
static const char *const psf_keys[] = {"model",      "fwhm_um",       "beta",
                                       "halo",       "fwhm_minor_um", "angle_deg",
                                       "support_um", "subsample",     NULL};
static const char *const model_names[] = {"gaussian", "lorentzian", "moffat", NULL};
static const char *const boundary_names[] = {"zero", "mirror", "periodic", NULL};

static svp_status read_psf(const svp_yaml_doc *doc, svp_psf *psf, double *pixel_um_out,
                           svp_boundary *boundary_out)
{
    const svp_yaml_node *root = svp_yaml_root(doc), *node = NULL, *psf_node = NULL;
    double pixel_um = 0;
    SVP_CHECK(svp_yaml_expect_mapping(root, NULL));
    /* `kind` marks a PSF-map file (svp_psf_field_read): say that, not "unknown key 'version'" */
    const svp_yaml_node *kind = svp_yaml_get(root, "kind");
    if (kind)
        return svp_yaml_fail(kind, SVP_ERR_FORMAT,
                             "a PSF-map file (kind: %s), not a single PSF file (pixel_um and psf)",
                             svp_yaml_text(kind));
    SVP_CHECK(svp_yaml_check_keys(root, NULL, top_keys));
    SVP_CHECK(svp_yaml_require(root, "pixel_um", NULL, &node));
    SVP_CHECK(svp_yaml_number_in(node, "pixel_um", SVP_PIXEL_UM_MIN, INFINITY, 0, &pixel_um));
    int boundary = SVP_BOUNDARY_ZERO;
    SVP_CHECK(svp_yaml_get_choice(root, "boundary", boundary_names, &boundary, NULL));

    SVP_CHECK(svp_yaml_require(root, "psf", NULL, &psf_node));
    SVP_CHECK(svp_yaml_check_keys(psf_node, "psf", psf_keys));
    int model = 0;
    SVP_CHECK(svp_yaml_require(psf_node, "model", "psf", &node));
    SVP_CHECK(svp_yaml_choice(node, "model", model_names, &model));
    double fwhm_um = 0;
    SVP_CHECK(svp_yaml_require(psf_node, "fwhm_um", "psf", &node));
    SVP_CHECK(svp_yaml_number_in(node, "fwhm_um", 0, INFINITY, SVP_YAML_OPEN_LO, &fwhm_um));

    svp_psf p;
    svp_psf_defaults(&p);
    p.model = (svp_psf_model)model;
    p.fwhm = fwhm_um / pixel_um;
    if (!(p.fwhm > 0) || !isfinite(p.fwhm)) /* the ratio under- or overflows */
        return svp_yaml_fail(node, SVP_ERR_INVALID,
                             "fwhm_um %g over pixel_um %g is %g pixels: out of the range a PSF "
                             "can be rendered in (check both lengths' units)",
                             fwhm_um, pixel_um, p.fwhm);

    const svp_yaml_node *beta_node = svp_yaml_get(psf_node, "beta");
    if (beta_node) {
        SVP_CHECK(svp_yaml_number_in(beta_node, "beta", p.model == SVP_PSF_MOFFAT ? SVP_PSF_BETA_MIN : 0,
                                     INFINITY, p.model == SVP_PSF_MOFFAT ? 0 : SVP_YAML_OPEN_LO,
                                     &p.beta));
        if (p.model == SVP_PSF_GAUSSIAN)
            return svp_yaml_fail(beta_node, SVP_ERR_INVALID,
                                 "beta does not apply to a gaussian PSF (use model: moffat for "
                                 "a Moffat profile)");
        if (p.model == SVP_PSF_LORENTZIAN && p.beta != 1.0)
            return svp_yaml_fail(beta_node, SVP_ERR_INVALID,
                                 "beta must be 1 for a lorentzian PSF, got %s (use model: moffat "
                                 "for other values)",
                                 svp_yaml_text(beta_node));
    } else if (p.model == SVP_PSF_MOFFAT) {
        return svp_yaml_fail(psf_node, SVP_ERR_FORMAT,
                             "missing required key 'beta' in psf (a moffat PSF needs its beta)");
    }
    if (p.model == SVP_PSF_LORENTZIAN) p.beta = 1.0;

    SVP_CHECK(svp_yaml_get_number(psf_node, "halo", 0, 1, SVP_YAML_OPEN_HI, &p.halo, NULL));
    double minor_um = 0;
    int found = 0;
    SVP_CHECK(svp_yaml_get_number(psf_node, "fwhm_minor_um", 0, fwhm_um, SVP_YAML_OPEN_LO,
                                  &minor_um, &found));
    if (found) p.fwhm_minor = minor_um / pixel_um;
    double angle_deg = 0;
    SVP_CHECK(svp_yaml_get_number(psf_node, "angle_deg", -INFINITY, INFINITY, 0, &angle_deg, NULL));
    p.angle = angle_deg * (M_PI / 180.0);
    double support_um = 0;
    SVP_CHECK(svp_yaml_get_number(psf_node, "support_um", 0, INFINITY, 0, &support_um, NULL));
    p.support = support_um / pixel_um;
    long long subsample = 0;
    SVP_CHECK(svp_yaml_get_int(psf_node, "subsample", 0, 64, &subsample, NULL));
    p.subsample = (int)subsample;

    /* anything the model itself rejects (e.g. a FWHM that underflows in pixels) */
    svp_status st = svp_psf_validate(&p);
    if (st != SVP_OK) return svp_yaml_fail(psf_node, st, "%s", svp_last_error());

    *psf = p;
    if (pixel_um_out) *pixel_um_out = pixel_um;
    if (boundary_out) *boundary_out = (svp_boundary)boundary;
    return SVP_OK;
}

svp_status svp_psf_file_read(const char *path, svp_psf *psf, double *pixel_um,
                             svp_boundary *boundary)
{
    if (!path) return svp_fail(SVP_ERR_INVALID, "svp_psf_file_read: path is NULL");
    if (!psf) return svp_fail(SVP_ERR_INVALID, "svp_psf_file_read: psf is NULL");
    svp_yaml_doc *doc = NULL;
    SVP_CHECK(svp_yaml_load_file(path, &doc));
    svp_status st = read_psf(doc, psf, pixel_um, boundary);
    svp_yaml_free(doc);
    return st;
}
