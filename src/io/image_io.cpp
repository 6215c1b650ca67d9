// OpenCV codecs and colour maps: the only C++ file of the library. Every OpenCV call sits inside
// try/catch; nothing is thrown across the C boundary (image_io.h is plain C).
#include "image_io.h"

#include <opencv2/core.hpp>
#include <opencv2/core/utils/logger.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <mutex>
#include <iostream>
#include <new>
#include <sstream>
#include <vector>

// internal.h pulls in <complex.h> and FFTW, which do not belong in C++; the one internal helper
// this file needs is declared here with C linkage (it is defined in core/status.c).
extern "C" svp_status svp_fail(svp_status status, const char *fmt, ...)
    __attribute__((format(printf, 2, 3)));

namespace {

// The library never prints: OpenCV's log goes quiet unless the user asked for it explicitly.
void quiet_opencv_log()
{
    static std::once_flag once;
    std::call_once(once, [] {
        if (!std::getenv("OPENCV_LOG_LEVEL"))
            cv::utils::logging::setLogLevel(cv::utils::logging::LOG_LEVEL_SILENT);
    });
}

// imdecode/imencode catch decoder exceptions themselves and print them on std::cerr, outside
// OpenCV's log levels. While a codec runs, std::cerr writes into a string instead (serialised
// by a mutex: the stream buffer is process-wide; nothing else in this C program uses std::cerr).
class SilenceCerr {
  public:
    SilenceCerr() : lock_(mutex()), saved_(std::cerr.rdbuf(sink_.rdbuf())) {}
    ~SilenceCerr() { std::cerr.rdbuf(saved_); }
    SilenceCerr(const SilenceCerr &) = delete;
    SilenceCerr &operator=(const SilenceCerr &) = delete;

  private:
    static std::mutex &mutex()
    {
        static std::mutex m;
        return m;
    }
    std::lock_guard<std::mutex> lock_;
    std::ostringstream sink_;
    std::streambuf *saved_;
};

const char *depth_name(int depth)
{
    switch (depth) {
    case CV_8U: return "8-bit unsigned";
    case CV_8S: return "8-bit signed";
    case CV_16U: return "16-bit unsigned";
    case CV_16S: return "16-bit signed";
    case CV_32S: return "32-bit signed";
    case CV_32F: return "32-bit float";
    case CV_64F: return "64-bit float";
    case CV_16F: return "16-bit float";
    default: return "unknown";
    }
}

template <typename T> void copy_rows(const cv::Mat &m, svp_image *img)
{
    for (int y = 0; y < m.rows; y++) {
        const T *row = m.ptr<T>(y);
        double *dst = img->data + (size_t)y * img->width;
        for (int x = 0; x < m.cols; x++) dst[x] = (double)row[x];
    }
}

// One decoded page → a new image; `where` prefixes the fault ("page 3 of 5: " or "").
svp_status mat_to_image(const char *path, const char *where, const cv::Mat &m, svp_image **out)
{
    if (m.channels() != 1)
        return svp_fail(SVP_ERR_FORMAT,
                        "%s: %s%d-channel image: expected a single-channel (grayscale) image",
                        path, where, m.channels());
    if (m.dims != 2)
        return svp_fail(SVP_ERR_FORMAT, "%s: %s%d-dimensional image: expected 2-D", path, where,
                        m.dims);
    svp_image *img = nullptr;
    svp_status st = svp_image_new(m.cols, m.rows, &img);
    if (st != SVP_OK) return st;
    switch (m.depth()) {
    case CV_8U: copy_rows<uint8_t>(m, img); break;
    case CV_8S: copy_rows<int8_t>(m, img); break;
    case CV_16U: copy_rows<uint16_t>(m, img); break;
    case CV_16S: copy_rows<int16_t>(m, img); break;
    case CV_32S: copy_rows<int32_t>(m, img); break;
    case CV_32F: copy_rows<float>(m, img); break;
    case CV_64F: copy_rows<double>(m, img); break;
    default:
        svp_image_free(img);
        return svp_fail(SVP_ERR_FORMAT,
                        "%s: %sunsupported pixel type %s (expected 8/16-bit integer, 32-bit "
                        "integer, float32 or float64)",
                        path, where, depth_name(m.depth()));
    }
    *out = img;
    return SVP_OK;
}

// Writes an encoded image atomically; ext is ".tiff" or ".png".
svp_status encode_and_write(const char *path, const cv::Mat &m, const char *ext,
                            const std::vector<int> &params, int overwrite)
{
    std::vector<uchar> bytes;
    try {
        quiet_opencv_log();
        SilenceCerr quiet;
        if (!cv::imencode(ext, m, bytes, params))
            return svp_fail(SVP_ERR_IO, "%s: OpenCV could not encode the image as %s", path,
                            ext + 1);
    } catch (const cv::Exception &e) {
        return svp_fail(SVP_ERR_IO, "%s: OpenCV could not encode the image as %s (%s)", path,
                        ext + 1, e.what());
    } catch (const std::bad_alloc &) {
        return svp_fail(SVP_ERR_NOMEM, "%s: out of memory while encoding", path);
    } catch (const std::exception &e) {
        return svp_fail(SVP_ERR_INTERNAL, "%s: encoding failed (%s)", path, e.what());
    }
    return svp_io_atomic_write_bytes(path, bytes.data(), bytes.size(), overwrite);
}

svp_status check_image(const char *path, const svp_image *img)
{
    if (!path) return svp_fail(SVP_ERR_INVALID, "image write: path is NULL");
    if (!img || !img->data || img->width < 1 || img->height < 1)
        return svp_fail(SVP_ERR_INVALID, "%s: no image to write", path);
    return SVP_OK;
}

// Diverging blue–white–red anchors (ColorBrewer RdBu, 7 classes), from −m to +m, as RGB.
const unsigned char diverging_anchors[7][3] = {{5, 48, 97},     {33, 102, 172},  {146, 197, 222},
                                               {247, 247, 247}, {244, 165, 130}, {178, 24, 43},
                                               {103, 0, 31}};

cv::Mat diverging_lut()
{
    cv::Mat lut(256, 1, CV_8UC3);
    for (int i = 0; i < 256; i++) {
        double t = i / 255.0 * 6.0;
        int k = t >= 6.0 ? 5 : (int)t;
        double f = t - k;
        cv::Vec3b &bgr = lut.at<cv::Vec3b>(i, 0);
        for (int c = 0; c < 3; c++) {
            double v = (1 - f) * diverging_anchors[k][c] + f * diverging_anchors[k + 1][c];
            bgr[2 - c] = (uchar)std::lround(v);
        }
    }
    return lut;
}

} // namespace

extern "C" {

const char *svp_io_opencv_version(void) { return CV_VERSION; }

svp_status svp_io_decode_cv(const char *path, const unsigned char *bytes, size_t size, int is_tiff,
                            svp_image **out)
{
    *out = nullptr;
    const char *kind = is_tiff ? "TIFF" : "PNG";
    cv::Mat m;
    try {
        quiet_opencv_log();
        if (size > (size_t)INT32_MAX)
            return svp_fail(SVP_ERR_FORMAT, "%s: file too large for the %s decoder", path, kind);
        cv::Mat raw(1, (int)size, CV_8U, const_cast<unsigned char *>(bytes));
        SilenceCerr quiet;
        m = cv::imdecode(raw, cv::IMREAD_UNCHANGED | cv::IMREAD_ANYDEPTH);
    } catch (const cv::Exception &e) {
        return svp_fail(SVP_ERR_FORMAT, "%s: cannot decode %s (%s)", path, kind, e.what());
    } catch (const std::bad_alloc &) {
        return svp_fail(SVP_ERR_NOMEM, "%s: out of memory while decoding", path);
    } catch (const std::exception &e) {
        return svp_fail(SVP_ERR_FORMAT, "%s: cannot decode %s (%s)", path, kind, e.what());
    }
    if (m.empty())
        return svp_fail(SVP_ERR_FORMAT, "%s: cannot decode %s (truncated or corrupt)", path, kind);
    return mat_to_image(path, "", m, out);
}

svp_status svp_io_read_tiff_pages(const char *path, int n_pages, svp_image ***pages)
{
    *pages = nullptr;
    if (n_pages < 1) return svp_fail(SVP_ERR_INVALID, "%s: no page to read", path);
    std::vector<cv::Mat> mats;
    try {
        quiet_opencv_log();
        SilenceCerr quiet;
        if (!cv::imreadmulti(path, mats, cv::IMREAD_UNCHANGED | cv::IMREAD_ANYDEPTH))
            mats.clear();
    } catch (const cv::Exception &e) {
        return svp_fail(SVP_ERR_FORMAT, "%s: cannot decode TIFF stack (%s)", path, e.what());
    } catch (const std::bad_alloc &) {
        return svp_fail(SVP_ERR_NOMEM, "%s: out of memory while decoding %d pages", path,
                        n_pages);
    } catch (const std::exception &e) {
        return svp_fail(SVP_ERR_FORMAT, "%s: cannot decode TIFF stack (%s)", path, e.what());
    }
    if (mats.size() != (size_t)n_pages)
        return svp_fail(SVP_ERR_FORMAT,
                        "%s: cannot decode TIFF stack (truncated or corrupt: %zu of %d pages "
                        "decoded)",
                        path, mats.size(), n_pages);
    svp_image **out = (svp_image **)calloc((size_t)n_pages, sizeof(svp_image *));
    if (!out) return svp_fail(SVP_ERR_NOMEM, "%s: out of memory for %d pages", path, n_pages);
    svp_status st = SVP_OK;
    const int cols0 = mats[0].cols, rows0 = mats[0].rows;
    for (int i = 0; i < n_pages && st == SVP_OK; i++) {
        char where[64];
        snprintf(where, sizeof where, "page %d of %d: ", i + 1, n_pages);
        const cv::Mat &m = mats[(size_t)i];
        if (m.empty())
            st = svp_fail(SVP_ERR_FORMAT, "%s: %scannot decode TIFF (truncated or corrupt)", path,
                          where);
        else if (i > 0 && (m.cols != cols0 || m.rows != rows0))
            st = svp_fail(SVP_ERR_FORMAT, "%s: page %d of %d is %d x %d but page 1 is %d x %d",
                          path, i + 1, n_pages, m.cols, m.rows, cols0, rows0);
        else
            st = mat_to_image(path, where, m, &out[i]);
        mats[(size_t)i].release(); // peak memory: the decoded pages go as they are copied
    }
    if (st != SVP_OK) {
        for (int i = 0; i < n_pages; i++) svp_image_free(out[i]);
        free(out);
        return st;
    }
    *pages = out;
    return SVP_OK;
}

svp_status svp_io_write_tiff(const char *path, const svp_image *img, int overwrite)
{
    svp_status st = check_image(path, img);
    if (st != SVP_OK) return st;
    try {
        cv::Mat m(img->height, img->width, CV_32F);
        for (int y = 0; y < img->height; y++) {
            float *row = m.ptr<float>(y);
            const double *src = img->data + (size_t)y * img->width;
            for (int x = 0; x < img->width; x++) row[x] = (float)src[x];
        }
        // uncompressed: every reader understands it, and float data barely compresses
        std::vector<int> params = {cv::IMWRITE_TIFF_COMPRESSION, 1};
        return encode_and_write(path, m, ".tiff", params, overwrite);
    } catch (const cv::Exception &e) {
        return svp_fail(SVP_ERR_IO, "%s: %s", path, e.what());
    } catch (const std::bad_alloc &) {
        return svp_fail(SVP_ERR_NOMEM, "%s: out of memory for a %d x %d float32 image", path,
                        img->width, img->height);
    } catch (const std::exception &e) {
        return svp_fail(SVP_ERR_INTERNAL, "%s: %s", path, e.what());
    }
}

svp_status svp_io_write_png16(const char *path, const svp_image *img, int overwrite)
{
    svp_status st = check_image(path, img);
    if (st != SVP_OK) return st;
    size_t n = (size_t)img->width * img->height;
    double lo = INFINITY, hi = -INFINITY;
    for (size_t i = 0; i < n; i++) {
        double v = img->data[i];
        if (std::isfinite(v)) {
            if (v < lo) lo = v;
            if (v > hi) hi = v;
        }
    }
    double scale = hi > lo ? 65535.0 / (hi - lo) : 0.0;
    try {
        cv::Mat m(img->height, img->width, CV_16U);
        for (int y = 0; y < img->height; y++) {
            uint16_t *row = m.ptr<uint16_t>(y);
            const double *src = img->data + (size_t)y * img->width;
            for (int x = 0; x < img->width; x++) {
                double v = src[x];
                double s = std::isfinite(v) ? (v - lo) * scale : 0.0;
                row[x] = (uint16_t)(s <= 0 ? 0 : s >= 65535 ? 65535 : std::lround(s));
            }
        }
        return encode_and_write(path, m, ".png", {}, overwrite);
    } catch (const cv::Exception &e) {
        return svp_fail(SVP_ERR_IO, "%s: %s", path, e.what());
    } catch (const std::bad_alloc &) {
        return svp_fail(SVP_ERR_NOMEM, "%s: out of memory for a %d x %d 16-bit image", path,
                        img->width, img->height);
    } catch (const std::exception &e) {
        return svp_fail(SVP_ERR_INTERNAL, "%s: %s", path, e.what());
    }
}

svp_status svp_io_write_colormap_png(const char *path, const svp_image *img, double lo, double hi,
                                     int diverging, int overwrite)
{
    svp_status st = check_image(path, img);
    if (st != SVP_OK) return st;
    size_t n = (size_t)img->width * img->height;
    if (!(lo < hi) || !std::isfinite(lo) || !std::isfinite(hi)) {
        lo = INFINITY;
        hi = -INFINITY;
        for (size_t i = 0; i < n; i++) {
            double v = img->data[i];
            if (std::isfinite(v)) {
                if (v < lo) lo = v;
                if (v > hi) hi = v;
            }
        }
        if (!(lo <= hi)) lo = hi = 0; // no finite pixel
    }
    if (diverging) { // centred on zero: white is exactly 0
        double m = std::fmax(std::fabs(lo), std::fabs(hi));
        lo = -m;
        hi = m;
    }
    double scale = hi > lo ? 255.0 / (hi - lo) : 0.0;
    try {
        quiet_opencv_log();
        cv::Mat index(img->height, img->width, CV_8U);
        for (int y = 0; y < img->height; y++) {
            uint8_t *row = index.ptr<uint8_t>(y);
            const double *src = img->data + (size_t)y * img->width;
            for (int x = 0; x < img->width; x++) {
                double v = src[x];
                // a constant or all-zero image maps to the middle of the scale
                double s = hi > lo ? (v - lo) * scale : 127.5;
                row[x] = (uint8_t)(!(s > 0) ? 0 : s >= 255 ? 255 : std::lround(s));
            }
        }
        cv::Mat colour;
        if (diverging)
            cv::applyColorMap(index, colour, diverging_lut());
        else
            cv::applyColorMap(index, colour, cv::COLORMAP_VIRIDIS);
        for (int y = 0; y < img->height; y++) {
            cv::Vec3b *row = colour.ptr<cv::Vec3b>(y);
            const double *src = img->data + (size_t)y * img->width;
            for (int x = 0; x < img->width; x++)
                if (!std::isfinite(src[x])) row[x] = cv::Vec3b(128, 128, 128);
        }
        return encode_and_write(path, colour, ".png", {}, overwrite);
    } catch (const cv::Exception &e) {
        return svp_fail(SVP_ERR_IO, "%s: colour map failed (%s)", path, e.what());
    } catch (const std::bad_alloc &) {
        return svp_fail(SVP_ERR_NOMEM, "%s: out of memory for a colour map", path);
    } catch (const std::exception &e) {
        return svp_fail(SVP_ERR_INTERNAL, "%s: %s", path, e.what());
    }
}

} // extern "C"

// For figures (src/figure): the colour map of svp_io_write_colormap_png into an RGB buffer, so a
// figure can be composed around it (colour bar, scale bar, labels).
// values[n] → rgb[3 n] over exactly [lo, hi] (clamped; no symmetric widening), NaN/Inf grey.
extern "C" svp_status svp_io_colormap_rgb(const double *values, size_t n, double lo, double hi,
                                          int diverging, unsigned char *rgb)
{
    if (!values || !rgb || n == 0 || n > (size_t)2147483647)
        return svp_fail(SVP_ERR_INVALID, "colour map: no values");
    double scale = hi > lo ? 255.0 / (hi - lo) : 0.0;
    try {
        quiet_opencv_log();
        cv::Mat index(1, (int)n, CV_8U);
        uint8_t *row = index.ptr<uint8_t>(0);
        for (size_t i = 0; i < n; i++) {
            double s = hi > lo ? (values[i] - lo) * scale : 127.5;
            row[i] = (uint8_t)(!(s > 0) ? 0 : s >= 255 ? 255 : std::lround(s));
        }
        cv::Mat colour;
        if (diverging)
            cv::applyColorMap(index, colour, diverging_lut());
        else
            cv::applyColorMap(index, colour, cv::COLORMAP_VIRIDIS);
        const cv::Vec3b *bgr = colour.ptr<cv::Vec3b>(0);
        for (size_t i = 0; i < n; i++) {
            int grey = !std::isfinite(values[i]);
            for (int c = 0; c < 3; c++) rgb[3 * i + c] = grey ? 128 : bgr[i][2 - c];
        }
        return SVP_OK;
    } catch (const cv::Exception &e) {
        return svp_fail(SVP_ERR_INTERNAL, "colour map failed (%s)", e.what());
    } catch (const std::bad_alloc &) {
        return svp_fail(SVP_ERR_NOMEM, "out of memory for a colour map");
    } catch (const std::exception &e) {
        return svp_fail(SVP_ERR_INTERNAL, "colour map: %s", e.what());
    }
}

// ---- registration: ECC -----------------------------------------------------------------------
// svp_io_register_ecc (image_io.h). Phase correlation, warping and the residual are plain C in
// io/register.c; only the OpenCV part lives here.
#include <opencv2/video/tracking.hpp>

namespace {

cv::Mat float_image(const double *data, int width, int height, double smooth_sigma)
{
    cv::Mat m(height, width, CV_32F);
    for (int y = 0; y < height; y++) {
        float *row = m.ptr<float>(y);
        const double *src = data + (size_t)y * width;
        for (int x = 0; x < width; x++) row[x] = (float)src[x];
    }
    // smoothed once here; findTransformECC's own filter is switched off (size 1)
    if (smooth_sigma > 0)
        cv::GaussianBlur(m, m, cv::Size(0, 0), smooth_sigma, smooth_sigma, cv::BORDER_REFLECT);
    return m;
}

const char *motion_name(int motion)
{
    switch (motion) {
    case 0: return "translation";
    case 1: return "euclidean";
    case 2: return "affine";
    default: return "?";
    }
}

} // namespace

extern "C" svp_status svp_io_register_ecc(const double *reference, const double *moving,
                                          int width, int height, int motion,
                                          double smooth_sigma, int iterations, double epsilon,
                                          double warp[6], int *iterations_done,
                                          double *correlation, svp_progress_fn progress,
                                          void *progress_user)
{
    *iterations_done = 0;
    *correlation = NAN;
    static const int cv_motion[] = {cv::MOTION_TRANSLATION, cv::MOTION_EUCLIDEAN,
                                    cv::MOTION_AFFINE};
    if (motion < 0 || motion > 2)
        return svp_fail(SVP_ERR_INVALID, "ECC registration: motion %d is not translation (0), "
                                         "euclidean (1) or affine (2)",
                        motion);
    if (iterations < 1)
        return svp_fail(SVP_ERR_INVALID, "ECC registration: iterations %d (must be >= 1)",
                        iterations);
    int done = 0;
    double rho = NAN, last_rho = NAN, change = NAN;
    bool converged = false;
    try {
        quiet_opencv_log();
        const cv::Mat templ = float_image(reference, width, height, smooth_sigma);
        const cv::Mat input = float_image(moving, width, height, smooth_sigma);
        cv::Mat map(2, 3, CV_32F);
        for (int i = 0; i < 6; i++) map.at<float>(i / 3, i % 3) = (float)warp[i];
        // One iteration per call: OpenCV does not say whether it stopped on epsilon or on the
        // count, and a stall must be reported, not returned as a result.
        const cv::TermCriteria one_step(cv::TermCriteria::COUNT, 1, 0);
        while (done < iterations) {
            rho = cv::findTransformECC(templ, input, map, cv_motion[motion], one_step,
                                       cv::noArray(), 1);
            done++;
            *iterations_done = done;
            *correlation = rho;
            for (int i = 0; i < 6; i++) warp[i] = map.at<float>(i / 3, i % 3);
            if (progress && progress(progress_user, (double)done / iterations))
                return svp_fail(SVP_ERR_CANCELLED, "registration cancelled at ECC iteration %d",
                                done);
            change = std::fabs(rho - last_rho);
            if (change < epsilon) { // false while last_rho is NaN (first iteration)
                converged = true;
                break;
            }
            last_rho = rho;
        }
    } catch (const cv::Exception &e) {
        return svp_fail(SVP_ERR_NUMERIC,
                        "ECC registration (%s) failed at iteration %d: %s (the images may not "
                        "overlap or share no texture; try method phase, or a better start)",
                        motion_name(motion), done + 1, e.err.c_str());
    } catch (const std::bad_alloc &) {
        return svp_fail(SVP_ERR_NOMEM, "ECC registration: out of memory for %d x %d images",
                        width, height);
    } catch (const std::exception &e) {
        return svp_fail(SVP_ERR_INTERNAL, "ECC registration: %s", e.what());
    }
    if (!converged)
        return svp_fail(SVP_ERR_NUMERIC,
                        "registration did not converge after %d iterations (correlation %.4g; "
                        "last change %.3g > epsilon %.3g)",
                        done, rho, change, epsilon);
    return SVP_OK;
}
