"""svpsf: space-variant PSF restoration for widefield spectral imaging, from Python.

A thin layer over the C library libsvpsf (include/svpsf.h; docs/api.md), loaded with cffi in
ABI mode. Images are 2-D numpy arrays of float64, row y = image row y (shape (height, width)),
exactly the library's layout: a C-contiguous float64 array is handed to the library as it is
(no copy); any other array is converted once (np.ascontiguousarray(..., float64)). Outputs are
new numpy arrays the library writes into. Every failure raises svpsf.Error (DoubtfulError for
a result the library cannot vouch for) carrying the library's own message (svp_last_error()).
The calls release the GIL. The tutorial is docs/python.md.
"""
import os
import warnings
from collections import namedtuple

import numpy as np

from ._lib import HEADER, LIBRARY, ffi, lib

__all__ = [
    "Error", "DoubtfulError", "version", "fftw_version", "set_threads", "get_threads",
    "set_fft_effort", "wisdom_load", "wisdom_save", "read_image", "write_image", "PSF", "PSFMap",
    "read_psf", "Blur", "forward", "correct", "deconvolve", "fit_psf", "map_psf", "fit_odmr",
    "read_stack", "read_mat", "write_mat", "OdmrFit", "reconstruct_magnetisation",
    "SpotFit", "LIBRARY", "HEADER",
]

# ---- errors ---------------------------------------------------------------------------------


class Error(Exception):
    """A libsvpsf failure: .status (the svp_status code), .reason (its short text), .message
    (svp_last_error(): names the input at fault)."""

    def __init__(self, status, message):
        self.status = int(status)
        self.reason = ffi.string(lib.svp_status_string(status)).decode()
        self.message = message
        super().__init__(message or self.reason)


class DoubtfulError(Error):
    """SVP_ERR_DOUBTFUL: the computation ran but its result cannot be vouched for; the message
    says what to change (docs/cli.md, exit status 3)."""


def _check(status):
    if status != lib.SVP_OK:
        message = ffi.string(lib.svp_last_error()).decode("utf-8", "replace")
        cls = DoubtfulError if status == lib.SVP_ERR_DOUBTFUL else Error
        raise cls(status, message)


def _text(p):
    return ffi.string(p).decode("utf-8", "replace") if p != ffi.NULL else ""


def _path(p):
    """A path for the library: bytes without NUL (C would stop there and write another file,
    as open() refuses it)."""
    b = os.fsencode(os.fspath(p))
    if b"\0" in b:
        raise ValueError("path %r: embedded null byte" % (os.fspath(p),))
    return b


# ---- versions, threads, FFT planning ----------------------------------------------------------


def version():
    """The library's version ("0.1.0")."""
    return _text(lib.svp_version())


def fftw_version():
    return _text(lib.svp_fftw_version())


def set_threads(n):
    """Threads of the library's FFTs and loops (default: all cores OpenMP reports); 1..4096, as
    `--threads` (0 and -1 became 1 silently)."""
    lib.svp_set_threads(_count(n, "threads", 1, 4096))


def get_threads():
    return lib.svp_get_threads()


def set_fft_effort(effort):
    """'measure' (the default: slower first plan per size, faster FFTs) or 'estimate' (no
    timing: the same plan in every process, so results repeat bit for bit across runs)."""
    values = {"estimate": lib.SVP_FFT_ESTIMATE, "measure": lib.SVP_FFT_MEASURE}
    if effort not in values:
        raise ValueError("fft effort %r: 'estimate' or 'measure'" % (effort,))
    lib.svp_set_fft_effort(values[effort])


def wisdom_load(path):
    _check(lib.svp_fft_wisdom_load(_path(path)))


def wisdom_save(path):
    _check(lib.svp_fft_wisdom_save(_path(path)))


# ---- images -----------------------------------------------------------------------------------


def _input(array, name):
    """A C-contiguous float64 2-D array: the array itself when it already is one."""
    if np.iscomplexobj(array):
        raise ValueError("%s: a complex array; the maps are real (pass .real or abs() on "
                         "purpose)" % name)
    a = np.asarray(array, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError("%s: a 2-D image is needed, got an array of shape %s" % (name, a.shape))
    if a.shape[0] < 1 or a.shape[1] < 1:
        raise ValueError("%s: the image is empty (shape %s)" % (name, a.shape))
    if not a.flags.c_contiguous:
        a = np.ascontiguousarray(a)
    return a


class _Images:
    """svp_image structs viewing numpy arrays (no copy); keeps the arrays alive."""

    def __init__(self):
        self._keep = []

    def view(self, a):
        img = ffi.new("svp_image *")
        img.height, img.width = a.shape
        buf = ffi.from_buffer("double[]", a, require_writable=False)
        img.data = buf
        self._keep.append((a, buf, img))
        return img

    def out(self, shape):
        a = np.empty(shape, dtype=np.float64)
        return a, self.view(a)

    def array(self, imgs):
        arr = ffi.new("svp_image *[]", len(imgs))
        for i, img in enumerate(imgs):
            arr[i] = img
        self._keep.append(arr)
        return arr


def _owned_array(img):
    """A numpy array over an image the library allocated, freed with the array (no copy)."""
    h, w = img.height, img.width
    data = ffi.gc(ffi.cast("double *", img.data), lambda _p, img=img: lib.svp_image_free(img))
    return np.frombuffer(ffi.buffer(data, 8 * w * h), dtype=np.float64).reshape(h, w)


def read_image(path):
    """Reads an image file as svpsf reads it (TIFF, PNG, .npy, numpy.savetxt text: the
    extension decides; docs/cli.md §Input files)."""
    out = ffi.new("svp_image **")
    _check(lib.svp_image_read(_path(path), out))
    return _owned_array(out[0])


def read_mat(path, variable=None):
    """Reads one 2-D variable of a MATLAB v5/v7 .mat file as svpsf reads it (svp_mat_read;
    docs/cli.md, MATLAB / QDMlab files): by default the first of Bz, B111ferro, B111para, else
    the only 2-D numeric array. MATLAB's element (r, c) is the array's [r, c]. Returns (array,
    info), info a dict: `variable` (the one read), `n_variables`, `pixel_um` (from the file's
    `step`: one number or [dx dy] of square pixels, QDMlab's metres converted; 0 without one),
    `step_elements` (how many values `step` holds, 0 without one) and `standoff_um` (from `h`,
    0 without one)."""
    out = ffi.new("svp_image **")
    info = ffi.new("svp_mat_info *")
    name = ffi.NULL
    if variable is not None:
        name = str(variable).encode("utf-8")
        if b"\0" in name:
            raise ValueError("variable %r: embedded null byte" % (variable,))
    _check(lib.svp_mat_read(_path(path), name, out, info))
    return _owned_array(out[0]), {
        "variable": ffi.string(info.variable).decode("utf-8", "replace"),
        "n_variables": int(info.n_variables), "pixel_um": float(info.pixel_um),
        "step_elements": int(info.step_elements), "standoff_um": float(info.standoff_um)}


def write_mat(path, maps, pixel_um=0.0, overwrite=False):
    """Writes maps, a dict {MATLAB name: 2-D array}, as double variables of one MATLAB v7 .mat
    file (svp_mat_write; the array's [r, c] is MATLAB's element (r, c)), with pixel_um > 0 also
    the scalar `step` in metres as QDMlab writes it, so that read_mat and `svpsf reconstruct`
    take the pixel size from the file. Atomic; an existing file is an error unless overwrite.
    Names: a letter, then letters, digits or '_', at most 63, distinct (the library checks)."""
    if not maps:
        raise ValueError("write_mat: no maps to write")
    imgs = _Images()
    names, views = [], []
    for name, image in maps.items():
        b = str(name).encode("utf-8")
        if b"\0" in b:
            raise ValueError("variable %r: embedded null byte" % (name,))
        names.append(ffi.new("char[]", b))
        views.append(imgs.view(_input(image, str(name))))
    c_names = ffi.new("const char *[]", names)
    _check(lib.svp_mat_write(_path(path), len(names), c_names, imgs.array(views),
                             float(pixel_um), int(bool(overwrite))))


_FORMATS = {"auto": 0, "tif": 1, "tiff": 1, "npy": 2, "txt": 3, "png": 4, "mat": 5}


def write_image(path, image, format="auto", overwrite=False):
    """Writes atomically; an existing file is an error unless overwrite. format: 'auto' (from
    the extension), 'tif' (float32), 'npy' (float64), 'txt' (%.17g), 'png' (16-bit figure),
    'mat' (MATLAB v7, one double variable named after the file, as `--format mat`)."""
    if format not in _FORMATS:
        raise ValueError("format %r: one of %s" % (format, ", ".join(_FORMATS)))
    ext = os.path.splitext(os.fspath(path))[1].lower().lstrip(".")
    same = {"tif": ("tif", "tiff"), "tiff": ("tif", "tiff"), "npy": ("npy",),
            "txt": ("txt", "csv", "dat"),
            "png": ("png",), "mat": ("mat",)}
    if format != "auto" and ext not in same.get(format, (format,)):
        raise ValueError("format %r for %s: the extension says otherwise (a file is read by its "
                         "extension)" % (format, os.fspath(path)))
    imgs = _Images()
    img = imgs.view(_input(image, "image"))
    _check(lib.svp_image_write(_path(path), img, _FORMATS[format], int(bool(overwrite))))


# ---- PSF models and files ---------------------------------------------------------------------

_MODELS = {"gaussian": 0, "lorentzian": 1, "moffat": 2}
_MODEL_NAMES = {v: k for k, v in _MODELS.items()}
_BOUNDARIES = {"zero": 0, "mirror": 1, "periodic": 2}
_BOUNDARY_NAMES = {v: k for k, v in _BOUNDARIES.items()}


class PSF:
    """A PSF model (lengths in pixels; docs/model.md §5): Gaussian, Lorentzian or Moffat, with
    an optional ellipticity, halo fraction and support radius."""

    _FIELDS = ("fwhm", "fwhm_minor", "angle", "beta", "halo", "support", "subsample")

    def __init__(self, model="gaussian", fwhm=2.0, beta=None, fwhm_minor=0.0, angle=0.0,
                 halo=0.0, support=0.0, subsample=0):
        if model not in _MODELS:
            raise ValueError("PSF model %r: one of %s" % (model, ", ".join(_MODELS)))
        c = ffi.new("svp_psf *")
        lib.svp_psf_defaults(c)
        c.model = _MODELS[model]
        c.fwhm, c.fwhm_minor, c.angle = fwhm, fwhm_minor, angle
        if beta is not None:
            c.beta = beta
        elif model == "lorentzian":
            c.beta = 1.0
        c.halo, c.support, c.subsample = halo, support, subsample
        _check(lib.svp_psf_validate(c))
        self._c = c

    @classmethod
    def _wrap(cls, c):
        self = cls.__new__(cls)
        self._c = ffi.new("svp_psf *", c[0])  # c: an svp_psf * (copied)
        return self

    @property
    def model(self):
        return _MODEL_NAMES[self._c.model]

    def __getattr__(self, name):
        if name in PSF._FIELDS:
            if name == "beta" and self._c.model == _MODELS["lorentzian"]:
                return 1.0  # what the library uses, whatever was given
            return getattr(self._c, name)
        raise AttributeError(name)

    def __setattr__(self, name, value):
        if name != "_c":  # a changed attribute would show in repr but not be used
            raise AttributeError("PSF is immutable: make a new one, e.g. PSF(%r, fwhm=...)"
                                 % (self.model,))
        object.__setattr__(self, name, value)

    def __repr__(self):
        parts = ["model=%r" % self.model, "fwhm=%g" % self.fwhm]
        if self.model == "moffat":
            parts.append("beta=%g" % self.beta)
        for k in ("fwhm_minor", "angle", "halo", "support", "subsample"):
            if getattr(self, k):
                parts.append("%s=%g" % (k, getattr(self, k)))
        return "PSF(" + ", ".join(parts) + ")"

    def render(self, rx, ry=None):
        """The core kernel on a (2 ry + 1, 2 rx + 1) grid centred on its middle pixel,
        normalised to unit sum (no halo): svp_psf_render."""
        out = ffi.new("svp_image **")
        _check(lib.svp_psf_render(self._c, int(rx), int(rx if ry is None else ry), out))
        return _owned_array(out[0])

    def profile(self, dx, dy):
        """Un-normalised profile (peak 1) at offset (dx, dy) pixels."""
        return lib.svp_psf_profile(self._c, dx, dy)

    def encircled_energy(self, r, R=0.0):
        return lib.svp_psf_encircled_energy(self._c, r, R)

    def auto_margin(self, shape):
        """`--margin auto` over images of shape (height, width): the reach at 1 % of the peak,
        at most a quarter of the larger side, 0 with a halo (svp_psf_auto_margin)."""
        h, w = shape
        return lib.svp_psf_auto_margin(self._c, int(w), int(h))

    def encircled_radius(self, fraction, R=0.0):
        out = ffi.new("double *")
        _check(lib.svp_psf_encircled_radius(self._c, fraction, R, out))
        return out[0]


class PSFMap:
    """A space-variant PSF field (docs/cli.md §PSF-map files): read_psf() of a map file,
    map_psf(), or PSFMap.uniform()."""

    _KINDS = {0: "uniform", 1: "grid", 2: "poly", 3: "regions"}

    def __init__(self, ptr):
        self._ptr = ffi.gc(ptr, lib.svp_psf_field_free)

    @classmethod
    def uniform(cls, psf, width=0, height=0):
        out = ffi.new("svp_psf_field **")
        _check(lib.svp_psf_field_new_uniform(psf._c, width, height, out))
        return cls(out[0])

    @property
    def kind(self):
        return self._KINDS[lib.svp_psf_field_get_kind(self._ptr)]

    @property
    def shape(self):
        """(height, width) of the image the map is for ((0, 0): any size)."""
        return (lib.svp_psf_field_height(self._ptr), lib.svp_psf_field_width(self._ptr))

    def at(self, x, y):
        """The local PSF at pixel position (x, y)."""
        c = ffi.new("svp_psf *")
        _check(lib.svp_psf_field_at(self._ptr, x, y, c))
        return PSF._wrap(c)

    def params_at(self, x, y):
        """The parameter vector (fwhm, e1, e2, beta, halo) at (x, y)."""
        p = ffi.new("double[5]")
        _check(lib.svp_psf_field_params_at(self._ptr, x, y, p))
        return tuple(p)

    def pad(self, margin):
        """The map on its image plus `margin` pixels per side, its edge PSFs carried outward
        (svp_psf_field_pad): for a Blur on the grid of correct(margin=...)."""
        out = ffi.new("svp_psf_field **")
        _check(lib.svp_psf_field_pad(self._ptr, _count(margin, "margin", 0, 100000), out))
        return PSFMap(out[0])

    def auto_margin(self, shape):
        """`--margin auto` for this map over images of shape (height, width): its widest PSF's
        reach at 1 % of the peak, at most a quarter of the larger side, 0 with a halo
        (svp_psf_field_auto_margin)."""
        h, w = shape
        return lib.svp_psf_field_auto_margin(self._ptr, int(w), int(h))

    def write(self, path, pixel_um, provenance=None, overwrite=False):
        """Writes the map file (atomically; svp_psf_field_write)."""
        prov = provenance.encode() if provenance is not None else ffi.NULL
        _check(lib.svp_psf_field_write(_path(path), self._ptr, pixel_um, prov,
                                       int(bool(overwrite))))

    def __repr__(self):
        return "PSFMap(kind=%r, shape=%s)" % (self.kind, self.shape)


PSFFile = namedtuple("PSFFile", "psf pixel_um boundary")
PSFFile.__doc__ = """read_psf()'s result: psf is a PSF, a PSFMap or a kernel image (ndarray);
pixel_um the file's pixel size (None for a kernel image); boundary the file's boundary or
None."""


def read_psf(path):
    """Reads what `svpsf forward/correct --psf FILE` reads, with the same rules: a YAML PSF
    file (-> PSF, its pixel size and boundary), a PSF-map file (kind uniform -> PSF; grid,
    poly, regions -> PSFMap) or a kernel image (-> ndarray, normalised by Blur)."""
    p = os.fspath(path)
    if not p.lower().endswith((".yaml", ".yml")):
        return PSFFile(read_image(p), None, None)
    field = ffi.new("svp_psf_field **")
    pixel = ffi.new("double *")
    _check(lib.svp_psf_field_read(_path(p), field, pixel))
    fmap = PSFMap(field[0])
    if fmap.kind != "uniform":
        return PSFFile(fmap, pixel[0], None)
    # one PSF: a plain PSF file (which may name a boundary) or a map of kind uniform
    c = ffi.new("svp_psf *")
    lib.svp_psf_defaults(c)
    boundary = ffi.new("int *", -1)  # stays -1 when the file names no boundary
    if lib.svp_psf_file_read(_path(p), c, pixel, ffi.cast("svp_boundary *", boundary)) == 0:
        b = _BOUNDARY_NAMES.get(boundary[0])
        return PSFFile(PSF._wrap(c), pixel[0], b)
    return PSFFile(fmap.at(0, 0), pixel[0], None)


# ---- blur operators ---------------------------------------------------------------------------


def _boundary(name):
    if name not in _BOUNDARIES:
        raise ValueError("boundary %r: one of zero, mirror, periodic" % (name,))
    return _BOUNDARIES[name]


class Blur:
    """The blur operator H for an image shape (height, width): svp_blur_new (a PSF),
    svp_blur_new_kernel (a kernel image, normalised, centre at (w // 2, h // 2)) or
    svp_blur_new_field (a PSFMap: tent nodes, or rank R eigen-PSFs on the nodes grid, as
    `--nodes`/`--rank`; regions=True: one kernel per region of a map of kind regions, as
    `--regions`; none: the representation chosen by operator_tol, default 1e-3, as
    `--operator-tol`; applications: the H + Hᵀ pairs its cost model counts, default 50;
    forward() and correct() pass what they run, as the program does; tail_tol: a low-rank or
    region map's far tail on a coarse grid within this error, default 0 = never, correct()
    passes its own for the RL methods as `--tail-tol`). psf may also be a file
    name (read_psf); boundary None = the file's,
    else 'zero'. Building it plans the FFTs once: reuse it for many images of one size. One
    Blur must not be used from two threads at once."""

    def __init__(self, psf, shape, boundary=None, nodes=None, rank=None, operator_tol=None,
                 applications=None, regions=False, tail_tol=None):
        if isinstance(psf, (str, bytes, os.PathLike)):
            f = read_psf(psf)
            psf = f.psf
            if boundary is None:
                boundary = f.boundary
        boundary = boundary or "zero"
        if len(shape) != 2:
            raise ValueError("shape %r: (height, width) of the images" % (tuple(shape),))
        h, w = (_count(shape[0], "shape[0]", 1, 1 << 20), _count(shape[1], "shape[1]", 1, 1 << 20))
        out = ffi.new("svp_blur **")
        if not isinstance(psf, PSFMap) and (nodes is not None or rank is not None or regions):
            # as `svpsf forward / correct` note it: ignored for a single PSF
            warnings.warn("nodes, rank and regions apply to a PSF map (PSFMap); ignored for a "
                          "single PSF", stacklevel=3)
        if isinstance(psf, PSF):
            _check(lib.svp_blur_new(psf._c, w, h, _boundary(boundary), out))
        elif isinstance(psf, PSFMap):
            if regions and (nodes is not None or rank is not None):
                raise ValueError("regions cannot be combined with nodes or rank")
            v = ffi.new("svp_variant_options *")
            lib.svp_variant_defaults(v)
            if nodes is not None:
                nx, ny = (nodes, nodes) if np.isscalar(nodes) else nodes
                v.grid_x = v.samples_x = int(nx)
                v.grid_y = v.samples_y = int(ny)
                v.representation = lib.SVP_VARIANT_TENT
            if operator_tol is not None:
                v.tolerance = float(operator_tol)
            if applications is not None:
                v.applications = int(applications)
            if rank is not None:
                v.representation = lib.SVP_VARIANT_LOWRANK
                v.rank = int(rank)
            if regions:
                v.representation = lib.SVP_VARIANT_REGIONS
            if tail_tol is not None:
                v.tail_tol = float(tail_tol)
            _check(lib.svp_blur_new_field(psf._ptr, w, h, _boundary(boundary), v, out))
        else:
            if psf is None or np.isscalar(psf) or isinstance(psf, dict):
                raise TypeError("psf: a PSF, a PSFMap, a PSF file's path or a kernel image (2-D "
                                "array) is needed, got %s" % type(psf).__name__)
            imgs = _Images()
            k = imgs.view(_input(psf, "psf kernel"))
            _check(lib.svp_blur_new_kernel(k, -1, -1, 1, w, h, _boundary(boundary), out))
        self._ptr = ffi.gc(out[0], lib.svp_blur_free)
        self.shape = (h, w)
        self.boundary = boundary

    @property
    def memory(self):
        return lib.svp_blur_memory(self._ptr)

    _REPRESENTATIONS = {0: "tent", 1: "low rank", 3: "regions"}

    @property
    def variant(self):
        """A space-variant operator's representation (svp_blur_variant_info): a dict with
        representation ('tent', 'low rank' or 'regions'), nodes (tent nodes or low-rank samples
        (x, y); regions (0, 0)), rank (low-rank terms or region kernels; tent 0),
        estimated_error (NaN when not estimated) and tail_step, tail_split, tail_error (a
        low-rank or region map's far tail on a coarse grid, tail_tol; step 0: the plain
        frame); None for other operators."""
        if not self.is_variant:
            return None
        info = ffi.new("svp_variant_info *")
        if lib.svp_blur_variant_info(self._ptr, info) != lib.SVP_OK:
            return None
        return {"representation": self._REPRESENTATIONS.get(info.representation),
                "nodes": (info.grid_x, info.grid_y), "rank": info.rank,
                "estimated_error": info.estimated_error, "tail_step": info.tail_step,
                "tail_split": info.tail_split, "tail_error": info.tail_error}

    @property
    def is_variant(self):
        return bool(lib.svp_blur_is_variant(self._ptr))

    def _apply(self, fn, x, out):
        imgs = _Images()
        x = _input(x, "image")
        if x.shape != self.shape:
            raise ValueError("the Blur is for images of shape %s, the image is %s"
                             % (self.shape, x.shape))
        if out is None:
            out, oi = imgs.out(self.shape)
        else:
            if not (isinstance(out, np.ndarray) and out.dtype == np.float64 and
                    out.flags.c_contiguous and out.flags.writeable and out.shape == self.shape):
                raise ValueError("out: a writable C-contiguous float64 array of shape %s is "
                                 "needed" % (self.shape,))
            if np.shares_memory(out, x):
                raise ValueError("out must not share memory with the input")
            oi = imgs.view(out)
        _check(fn(self._ptr, imgs.view(x), oi))
        return out

    def apply(self, x, out=None):
        """H x."""
        return self._apply(lib.svp_blur_apply, x, out)

    def adjoint(self, y, out=None):
        """Hᵀ y."""
        return self._apply(lib.svp_blur_adjoint, y, out)


def _blur_for(psf, shape, boundary, nodes, rank, applications=None, operator_tol=None,
              regions=False, margin=0, tail_tol=None):
    if isinstance(psf, Blur):
        given = [k for k, v in (("boundary", boundary), ("nodes", nodes), ("rank", rank),
                                ("regions", regions)) if v not in (None, False)]
        if given:
            raise ValueError("%s: a Blur has its own boundary and representation (drop them, "
                             "or give the PSF instead)" % ", ".join(given))
        if psf.shape != tuple(shape):
            if margin:
                raise ValueError("the Blur is for images of shape %s; with a margin of %d the "
                                 "correction needs one for %s (the maps' shape %s plus the "
                                 "margin on every side)" % (psf.shape, margin, tuple(shape),
                                 (shape[0] - 2 * margin, shape[1] - 2 * margin)))
            raise ValueError("the Blur is for images of shape %s, the inputs are %s"
                             % (psf.shape, tuple(shape)))
        return psf
    return Blur(psf, shape, boundary=boundary, nodes=nodes, rank=rank,
                operator_tol=operator_tol, applications=applications, regions=regions,
                tail_tol=tail_tol if isinstance(psf, PSFMap) else None)


def _auto_margin(psf, h, w):
    """`--margin auto` (cli_auto_margin): a PSF's reach, a map's widest, a kernel image's
    half-width, each at most a quarter of the larger side."""
    if isinstance(psf, (PSF, PSFMap)):
        return psf.auto_margin((h, w))
    if isinstance(psf, Blur):
        raise ValueError("margin 'auto' needs a PSF, a PSFMap or a kernel (a Blur is built for "
                         "one margin: give it in pixels)")
    k = np.shape(psf)
    return min(int(np.ceil(0.5 * max(k))), max(h, w) // 4) if len(k) == 2 else 0


def _padded(psf, margin):
    """A PSF map carried `margin` pixels beyond the view (PSFMap.pad); anything else as is."""
    return psf.pad(margin) if isinstance(psf, PSFMap) and margin > 0 else psf


def _correct_applications(opt, n_fields):
    """The H + Hᵀ pairs a correction runs, as `svpsf correct` counts them (docs/cli.md): RL
    iterations per Richardson-Lucy deconvolution, about 40 CG steps per Wiener one of a
    space-variant operator (17 solves with balance 'auto')."""
    cg = 40 * (17 if opt.balance_auto else 1)
    rl = opt.deconv.iterations
    if opt.method == _METHODS["rw"]:
        pairs = rl + n_fields * cg
    elif opt.method == _METHODS["w"]:
        pairs = (1 + n_fields) * cg
    else:
        pairs = (1 + n_fields) * rl
    return max(1, min(pairs, 1000000))


def _fields(fields, name):
    """A single 2-D map or a sequence of them -> (list of arrays, was a single map)."""
    if isinstance(fields, np.ndarray) and fields.ndim == 2:
        return [_input(fields, name)], True
    if (isinstance(fields, (list, tuple)) and fields and isinstance(fields[0], (list, tuple))
            and fields[0] and np.isscalar(fields[0][0])):
        return [_input(fields, name)], True  # a nested list of numbers is one map
    out = [_input(f, "%s[%d]" % (name, i)) for i, f in enumerate(fields)]
    if not out:
        raise ValueError("%s: at least one field map is needed" % name)
    return out, False


def _same_shape(arrays, names):
    shape = arrays[0].shape
    for a, n in zip(arrays[1:], names[1:]):
        if a.shape != shape:
            raise ValueError("size mismatch: %s is %d x %d (width x height) but %s is %d x %d"
                             % (n, a.shape[1], a.shape[0], names[0], shape[1], shape[0]))


# ---- T and T⁻¹ -------------------------------------------------------------------------------

ForwardResult = namedtuple("ForwardResult", "pl fields validity")


def forward(pl, fields, psf, boundary=None, nodes=None, rank=None, regions=False):
    """The forward transform T (eq. 3 of docs/model.md): what a blurred measurement of the true
    PL and field map(s) reports; `svpsf forward`. fields: one 2-D map or a list. psf: a PSF,
    PSFMap, kernel image, file name or a Blur of the maps' shape. Returns (pl, fields,
    validity), fields shaped as given (one map or a list)."""
    pl = _input(pl, "pl")
    fl, single = _fields(fields, "field")
    _same_shape([pl] + fl, ["pl"] + ["field[%d]" % i for i in range(len(fl))])
    blur = _blur_for(psf, pl.shape, boundary, nodes, rank, applications=1, regions=regions)
    imgs = _Images()
    pl_out, pl_oi = imgs.out(pl.shape)
    outs = [imgs.out(pl.shape) for _ in fl]
    val, val_i = imgs.out(pl.shape)
    _check(lib.svp_forward_transform(blur._ptr, imgs.view(pl), imgs.array([imgs.view(f) for f in fl]),
                                     len(fl), pl_oi, imgs.array([o[1] for o in outs]), val_i))
    f_out = [o[0] for o in outs]
    return ForwardResult(pl_out, f_out[0] if single else f_out, val)


CorrectResult = namedtuple("CorrectResult", "pl fields validity n_missing summary reports")

_METHODS = {"rw": 0, "r": 1, "w": 2, "rl-signed": 3}
_ACCELERATIONS = {"none": 0, "biggs-andrews": 1}
_STOPS = {0: "count", 1: "discrepancy", 2: "stalled", 3: "cap"}


# What `svpsf deconvolve` and `correct` accept (docs/cli.md): counts beyond would run for hours
# in the C loop, where Ctrl-C does not reach.
_MAX_COUNT = 100000
# SVP_CG_DOUBT_RESIDUAL of svpsf.h (a float #define, which cffi does not carry): a Wiener CG
# stopped at its cap above this relative residual is not converged, a result in doubt.
_CG_DOUBT_RESIDUAL = 1e-4


def _count(value, name, lo=1, hi=_MAX_COUNT):
    """An integer argument in [lo, hi]: the int itself, else ValueError naming it (2.5, True and
    "x" are refused, not truncated)."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        if isinstance(value, (float, np.floating)) and float(value).is_integer():
            value = int(value)
        else:
            raise ValueError("%s %r: an integer in %d..%d is needed" % (name, value, lo, hi))
    if not lo <= int(value) <= hi:
        raise ValueError("%s %d: must be in %d..%d" % (name, int(value), lo, hi))
    return int(value)


def _report(r):
    return {"wiener": bool(r.wiener), "balance": r.balance, "noise_sigma": r.noise_sigma,
            "noise_per_pixel": bool(r.noise_per_pixel), "cg_steps": r.cg_steps, "cg_residual": r.cg_residual, "cg_capped": bool(r.cg_capped),
            "balance_at_bound": r.balance_at_bound, "iterations": r.iterations, "chi2": r.chi2,
            "stop": _STOPS.get(r.stop, r.stop)}


def correct(pl, fields, psf, method=None, iterations=None, balance=None, noise=None,
            pl_floor=None, shift=None, cg_max_steps=None, precision="double",
            acceleration=None, margin=None, gain=None, offset=None, field_sigma=None,
            keep_doubtful=False, plausible_factor=None, boundary=None, nodes=None, rank=None,
            field_names=None, operator_tol=1e-2, regions=False, side_by_side=True,
            tail_tol=None, pl_name=None):
    """The inverse transform T⁻¹ (eq. 4 of docs/model.md) on measured maps; `svpsf correct`
    with the same option names (docs/cli.md): method 'r' | 'rw' | 'w' | 'rl-signed';
    iterations N or 'auto'; balance λ or 'auto'; noise σ (with balance 'auto'); precision
    'double' | 'single' (default double, where `svpsf correct` takes single for r and
    rl-signed with one PSF from 1024² pixels); acceleration 'none' | 'biggs-andrews'; margin
    pixels per side or 'auto' (zero boundary; a PSFMap carries its edge PSFs onto it,
    PSFMap.pad; default 0, where `svpsf correct` takes auto for r with one PSF: give it to
    match);
    gain, offset of the PL's camera; field_sigma one σ map per field; operator_tol a PSF map's
    operator error budget (default 1e-2, as `svpsf correct`); regions=True one kernel per region
    of a map of kind regions (`--regions`); side_by_side=False keeps the deconvolutions in
    order, one operator's memory (`--side-by-side off`); tail_tol the error budget of the PSF's
    far tail on a coarse grid (`--tail-tol`, 0 = never); pl_name and field_names: what the
    library's messages call the maps (e.g. their files, as the program does; default pl_apparent,
    field_apparent[k]). None = the library's default (svp_correct_defaults: the program's defaults). psf as for
    forward(). Returns (pl, fields, validity, n_missing, summary, reports): the recovered maps
    (fields shaped as given), what T⁻¹ did (svp_correct_summary as a dict) and one report per
    deconvolution ([0] the PL's, [1 + c] field c's numerator). Raises DoubtfulError (the
    message says why) unless keep_doubtful."""
    pl = _input(pl, "pl")
    fl, single = _fields(fields, "field")
    _same_shape([pl] + fl, ["pl"] + ["field[%d]" % i for i in range(len(fl))])
    if method is not None and method not in _METHODS:
        raise ValueError("method %r: one of %s" % (method, ", ".join(_METHODS)))
    if acceleration is not None and acceleration not in _ACCELERATIONS:
        raise ValueError("acceleration %r: none or biggs-andrews" % (acceleration,))
    if precision not in ("double", "single"):
        raise ValueError("precision %r: double or single" % (precision,))
    opt = ffi.new("svp_correct_options *")
    lib.svp_correct_defaults(opt)
    if method is not None:
        opt.method = _METHODS[method]
    # what `svpsf correct` refuses as options that would be ignored (docs/reliability.md)
    wiener = opt.method in (lib.SVP_METHOD_RW, lib.SVP_METHOD_W)
    if balance is not None and not wiener:
        raise ValueError("balance is used only by the methods with a Wiener deconvolution "
                         "(rw, w), not %s" % (method,))
    if noise is not None and noise != 0 and balance != "auto":  # as --noise (0: estimated)
        raise ValueError("noise is only used with balance='auto'")
    if opt.method == lib.SVP_METHOD_W and (iterations == "auto" or acceleration not in
                                           (None, "none") or precision == "single"):
        raise ValueError("iterations='auto', acceleration and precision='single' apply to "
                         "Richardson-Lucy: not with method w")
    if iterations == "auto":
        opt.auto_iterations = 1
    elif iterations is not None:
        opt.deconv.iterations = _count(iterations, "iterations")
    if balance == "auto":
        opt.balance_auto = 1
    elif balance is not None:
        try:
            opt.deconv.balance = float(balance)
        except (TypeError, ValueError):
            raise ValueError("balance %r: a number >= 0 or 'auto'" % (balance,)) from None
    for name, value in (("noise_sigma", noise), ("pl_floor", pl_floor), ("shift", shift),
                        ("pl_gain", gain), ("pl_offset", offset),
                        ("plausible_factor", plausible_factor)):
        if value is not None:
            setattr(opt, name, float(value))
    if cg_max_steps is not None:
        opt.deconv.cg_max_steps = _count(cg_max_steps, "cg_max_steps")
    opt.deconv.single_precision = int(precision == "single")
    opt.side_by_side = int(bool(side_by_side))
    if tail_tol is not None:
        opt.tail_tol = float(tail_tol)
    if acceleration is not None:
        opt.deconv.acceleration = _ACCELERATIONS[acceleration]
    h, w = pl.shape
    if isinstance(psf, (str, bytes, os.PathLike)):  # as Blur reads it, its boundary included
        f = read_psf(psf)
        psf, boundary = f.psf, boundary if boundary is not None else f.boundary
    if margin == "auto":  # as `--margin auto`: the PSF's (a map's widest) reach
        opt.margin = _auto_margin(psf, h, w) if (boundary or "zero") == "zero" else 0
    elif margin is not None:
        opt.margin = _count(margin, "margin", 0)
    opt.keep_doubtful = int(bool(keep_doubtful))
    imgs = _Images()
    if field_sigma is not None:
        sl, _ = _fields(field_sigma, "field_sigma")
        if len(sl) != len(fl):
            raise ValueError("field_sigma: %d maps for %d field maps" % (len(sl), len(fl)))
        _same_shape([pl] + sl, ["pl"] + ["field_sigma[%d]" % i for i in range(len(sl))])
        opt.field_sigma = imgs.array([imgs.view(s) for s in sl])
    if field_names is not None:
        names = [ffi.new("char[]", os.fsencode(n)) for n in field_names]
        if len(names) != len(fl):
            raise ValueError("field_names: %d names for %d field maps" % (len(names), len(fl)))
        name_array = ffi.new("char *[]", names)
        imgs._keep += [names, name_array]
        opt.field_names = name_array
    if pl_name is not None:
        pl_name_c = ffi.new("char[]", os.fsencode(pl_name))
        imgs._keep.append(pl_name_c)
        opt.pl_name = pl_name_c
    summary = ffi.new("svp_correct_summary *")
    reports = ffi.new("svp_deconv_report[]", len(fl) + 1)
    opt.summary = summary
    opt.reports = reports
    _check(lib.svp_correct_check_margin(opt.margin, w, h))  # as `--margin`
    blur = _blur_for(_padded(psf, opt.margin), (h + 2 * opt.margin, w + 2 * opt.margin),
                     boundary, nodes, rank, applications=_correct_applications(opt, len(fl)),
                     operator_tol=operator_tol, regions=regions, margin=opt.margin,
                     tail_tol=opt.tail_tol if opt.method in (lib.SVP_METHOD_R,
                                                             lib.SVP_METHOD_RL_SIGNED) else 0)
    pl_out, pl_oi = imgs.out(pl.shape)
    outs = [imgs.out(pl.shape) for _ in fl]
    val, val_i = imgs.out(pl.shape)
    n_missing = ffi.new("size_t *")
    _check(lib.svp_inverse_transform(blur._ptr, imgs.view(pl),
                                     imgs.array([imgs.view(f) for f in fl]), len(fl), opt,
                                     pl_oi, imgs.array([o[1] for o in outs]), val_i, n_missing))
    s = summary
    summ = {"doubts": s.doubts, "doubt_names": _doubt_names(s.doubts),
            "n_implausible": s.n_implausible,
            "spread_ratio": s.spread_ratio, "pl_gain": s.pl_gain,
            "pl_gain_offset": s.pl_gain_offset, "shift": [s.shift[i] for i in range(min(16, len(fl)))],
            "rl_iterations": s.rl_iterations, "rl_stop": _STOPS.get(s.rl_stop, s.rl_stop),
            "rl_chi2": s.rl_chi2, "side_by_side": s.side_by_side,
            "side_by_side_fallback": bool(s.side_by_side_fallback),
            "tail_step": s.tail_step, "tail_split": s.tail_split, "tail_error": s.tail_error}
    f_out = [o[0] for o in outs]
    return CorrectResult(pl_out, f_out[0] if single else f_out, val, int(n_missing[0]), summ,
                         [_report(reports[i]) for i in range(len(fl) + 1)])


def _doubt_names(bits):
    """The names of the doubt bits set in `bits` (svp_doubt_name), as summary.json lists them."""
    names, b = [], 0
    while True:
        name = lib.svp_doubt_name(b)
        if name == ffi.NULL:
            return names
        if bits & (1 << b):
            names.append(ffi.string(name).decode())
        b += 1


def deconvolve(image, psf, method="wiener", balance=1e-3, noise=0.0, iterations=50,
               precision="double", cg_max_steps=400, boundary=None, nodes=None, rank=None,
               regions=False, keep_doubtful=False):
    """One image ⊘ one PSF: Wiener–Hunt ('wiener'; balance λ or 'auto' by the discrepancy
    principle, noise σ or 0 = estimated) or Richardson–Lucy ('rl'); `svpsf deconvolve`.
    Returns (x, report): the deconvolved image and a dict of what was done. A result the
    program would refuse (exit 3: an automatic balance on an end of its search, a Wiener CG
    stopped at its cap above a relative residual of 1e-4) raises DoubtfulError unless
    keep_doubtful; report["doubts"] lists them either way."""
    y = _input(image, "image")
    if method not in ("wiener", "rl"):
        raise ValueError("method %r: wiener or rl" % (method,))
    blur = _blur_for(psf, y.shape, boundary, nodes, rank, regions=regions)
    opt = ffi.new("svp_deconv_options *")
    lib.svp_deconv_defaults(opt)
    opt.iterations = _count(iterations, "iterations")
    opt.cg_max_steps = _count(cg_max_steps, "cg_max_steps")
    opt.single_precision = int(precision == "single")
    report = ffi.new("svp_deconv_report *")
    opt.report = report
    imgs = _Images()
    yi = imgs.view(y)
    x, xi = imgs.out(y.shape)
    if method == "wiener":
        if balance == "auto":
            lam = ffi.new("double *")
            used = ffi.new("double *")
            _check(lib.svp_wiener_balance_discrepancy(blur._ptr, yi, noise, lam, used))
            opt.balance = lam[0]
        else:
            opt.balance = float(balance)
        _check(lib.svp_deconv_wiener(blur._ptr, yi, opt, xi))
    else:
        _check(lib.svp_deconv_rl(blur._ptr, yi, opt, xi))
    rep = _report(report[0])
    if method == "wiener":
        rep["balance"] = opt.balance
        if balance == "auto":
            rep["noise_sigma"] = used[0]
            # an automatic choice on an end of its search [1e-12, 1e2] cannot be vouched for
            # (`svpsf deconvolve` exits 3 on it): -1 lower end, +1 upper end, else 0 (the
            # bisection ends within a factor 1.002 of a crossing; 1.01 tells an end from it)
            rep["balance_at_bound"] = -1 if opt.balance <= 1.01e-12 else (
                1 if opt.balance >= 1e2 / 1.01 else 0)
    doubts = {}  # name as summary.json's: why, in the program's words
    if rep.get("balance_at_bound"):
        low = rep["balance_at_bound"] < 0
        doubts["balance_at_bound"] = (
            "balance auto ended on the %s end of its search (%g): the noise sigma %g %s; give "
            "balance or noise" % ("lower" if low else "upper", opt.balance, rep["noise_sigma"],
                                  "is below what any balance leaves (noiseless data?)" if low
                                  else "explains the data at every balance"))
    if method == "wiener" and rep["cg_capped"] and rep["cg_residual"] > _CG_DOUBT_RESIDUAL:
        doubts["cg_not_converged"] = (
            "the Wiener solve did not converge (relative residual %.3g after %d steps); raise "
            "cg_max_steps or balance" % (rep["cg_residual"], rep["cg_steps"]))
    rep["doubts"] = list(doubts)
    if doubts and not keep_doubtful:
        first = next(iter(doubts.values()))
        raise DoubtfulError(lib.SVP_ERR_DOUBTFUL, "result in doubt: " + first)
    return x, rep


# ---- source reconstruction -------------------------------------------------------------------


def reconstruct_magnetisation(bz, pixel_um, standoff_nm, method="fourier", nv_thickness_nm=0.0,
                              thickness_nm=0.0, cutoff_per_um=0.0, window=True, pad="taper",
                              max_iterations=200):
    """The areal magnetisation m_z (A) from B_z (T), as `svpsf reconstruct --quantity
    magnetisation` (docs/model.md §11): `method` "fourier" (the padded map's spectrum divided,
    the outermost pixel ring set to zero) or "support" (the m_z on the view, zero outside it,
    whose field fits B_z on the view in least squares; an edge pixel's error stays local).
    Returns (m_z, report): report["cg_iterations"], report["cg_residual"] for "support" (0
    for "fourier"). A support solve that does not converge within max_iterations raises
    DoubtfulError (the program exits 3)."""
    b = _input(bz, "bz")
    methods = {"fourier": lib.SVP_RECON_FOURIER, "support": lib.SVP_RECON_SUPPORT}
    pads = {"taper": lib.SVP_PAD_TAPER, "mean": lib.SVP_PAD_MEAN, "none": lib.SVP_PAD_NONE}
    if method not in methods:
        raise ValueError("method %r: fourier or support" % (method,))
    if pad not in pads:
        raise ValueError("pad %r: taper, mean or none" % (pad,))
    o = ffi.new("svp_recon_options *")
    lib.svp_recon_defaults(o)
    o.sensor.pixel_m = float(pixel_um) * 1e-6
    o.sensor.standoff_m = float(standoff_nm) * 1e-9
    o.sensor.nv_thickness_m = float(nv_thickness_nm) * 1e-9
    o.source_thickness_m = float(thickness_nm) * 1e-9
    o.cutoff = float(cutoff_per_um) * 1e6
    o.window = int(bool(window))
    o.pad = pads[pad]
    o.method = methods[method]
    o.max_iterations = _count(max_iterations, "max_iterations")
    report = ffi.new("svp_recon_report *")
    imgs = _Images()
    bi = imgs.view(b)
    m, mi = imgs.out(b.shape)
    _check(lib.svp_reconstruct_magnetisation_report(bi, o, mi, report))
    return m, {"cg_iterations": report.iterations, "cg_residual": report.residual}


# ---- PSF fits and maps ------------------------------------------------------------------------


class SpotFit:
    """One spot fit (svp_spot_result): attributes amplitude, x0, y0, fwhm, fwhm_major,
    fwhm_minor, angle, e1, e2, beta, r0, background (each with _err), ee50, ee80, ee95, chi2,
    chi2_red, dof, iterations, n_used, flags; lengths in pixels. .psf() is the fitted PSF;
    .flags_text the flags in words."""

    def __init__(self, c):
        self._c = c

    def __getattr__(self, name):
        if name.startswith("_"):
            raise AttributeError(name)
        try:
            v = getattr(self._c, name)
        except AttributeError:
            raise AttributeError(name) from None
        if name == "model":
            return _MODEL_NAMES[v]
        if isinstance(v, ffi.CData):
            return list(v)
        return v

    @property
    def flags_text(self):
        buf = ffi.new("char[512]")
        lib.svp_spot_flags_describe(self._c.flags, buf, 512)
        return _text(buf)

    def psf(self):
        c = ffi.new("svp_psf *")
        lib.svp_spot_result_psf(self._c, c)
        return PSF._wrap(c)

    def as_dict(self):
        names = [f for f, _ in ffi.typeof("svp_spot_result").fields if f != "covariance"]
        return {n: getattr(self, n) for n in names}

    def __repr__(self):
        return "SpotFit(model=%r, fwhm=%.4g±%.2g px, beta=%.4g, flags=%r)" % (
            self.model, self.fwhm, self.fwhm_err, self.beta, self.flags_text)


PairFit = namedtuple("PairFit", "excitation direct deconvolved offset deconvolved_ok image")


def _spot_options(o, model, elliptical, fix_beta, gain, sigma_bg, saturation, max_iterations,
                  refuse_border):
    if model not in _MODELS:
        raise ValueError("model %r: one of %s" % (model, ", ".join(_MODELS)))
    o.model = _MODELS[model]
    o.elliptical = int(bool(elliptical))
    if fix_beta is not None:
        if model != "moffat":
            raise ValueError("fix_beta applies to the moffat model only")
        o.beta, o.fix_beta = fix_beta, 1
    o.noise.gain = gain
    o.noise.sigma_bg = sigma_bg
    o.saturation = saturation
    o.lm.max_iterations = int(max_iterations)
    o.refuse_near_border = int(bool(refuse_border))


def fit_psf(spot, model="moffat", elliptical=True, fix_beta=None, gain=1.0, sigma_bg=0.0,
            saturation=0.0, max_iterations=200, refuse_border=False, excitation=None,
            iterations=75):
    """Fits a PSF to a spot image (svp_spot_fit; `svpsf fit-psf` with the same defaults:
    photon counts, gain 1). With excitation (an image of the excitation spot, the same size)
    the pair method (svp_psf_from_pair): returns PairFit(excitation, direct, deconvolved,
    offset, deconvolved_ok, image). A fit that does not converge raises Error (status
    numeric) with the library's message."""
    s = _input(spot, "spot")
    imgs = _Images()
    if excitation is None:
        o = ffi.new("svp_spot_options *")
        lib.svp_spot_defaults(o)
        _spot_options(o, model, elliptical, fix_beta, gain, sigma_bg, saturation,
                      max_iterations, refuse_border)
        r = ffi.new("svp_spot_result *")
        _check(lib.svp_spot_fit(imgs.view(s), o, r, ffi.NULL, ffi.NULL))
        return SpotFit(r)
    e = _input(excitation, "excitation")
    _same_shape([s, e], ["spot", "excitation"])
    po = ffi.new("svp_pair_options *")
    lib.svp_pair_defaults(po)
    _spot_options(po.spot, model, elliptical, fix_beta, gain, sigma_bg, saturation,
                  max_iterations, refuse_border)
    po.iterations = int(iterations)
    pr = ffi.new("svp_pair_result *")
    dec, dec_i = imgs.out(s.shape)
    _check(lib.svp_psf_from_pair(imgs.view(e), imgs.view(s), po, pr, dec_i))

    def part(name):
        c = ffi.new("svp_spot_result *")
        c[0] = getattr(pr, name)
        return SpotFit(c)

    return PairFit(part("excitation"), part("direct"), part("deconvolved"),
                   (pr.offset_x, pr.offset_y), bool(pr.deconvolved_ok), dec)


_PARAMS = ("fwhm", "e1", "e2", "beta", "halo")
_REJECT = {0: "kept", 1: "flags", 2: "invalid", 3: "outside", 4: "outlier"}


def map_psf(samples, shape, labels=None, degree="auto", max_degree=3, folds=5,
            clip_kappa=4.0, alpha=0.01, transition=0.0, halo=0.0, support=0.0):
    """A PSF map from spot fits (`svpsf map-psf`): samples is a sequence of (x, y, SpotFit),
    (x, y) the spot's centre in the field (pixels); shape (height, width) of the field.
    Without labels: polynomial surfaces (degree 'auto' = cross-validated up to max_degree);
    with labels (an integer image 0..L-1 of the field's shape): per-region means, regions that
    do not differ merged (Welch tests at alpha), blended over `transition` pixels. Returns
    (PSFMap, report dict)."""
    samples = list(samples)
    n = len(samples)
    h, w = int(shape[0]), int(shape[1])
    cs = ffi.new("svp_psf_sample[]", max(n, 1))
    for i, (x, y, fit) in enumerate(samples):
        cs[i].x, cs[i].y = x, y
        cs[i].fit = fit._c[0]
    mo = ffi.new("svp_map_options *")
    lib.svp_map_defaults(mo)
    mo.degree = -1 if degree == "auto" else int(degree)
    mo.max_degree = int(max_degree)
    mo.folds = int(folds)
    mo.clip_kappa = clip_kappa
    mo.alpha = alpha
    mo.transition = transition
    mo.halo = halo
    mo.support = support
    field = ffi.new("svp_psf_field **")
    rep = ffi.new("svp_map_report **")
    if labels is None:
        _check(lib.svp_psf_map_poly(cs, n, w, h, mo, field, rep))
    else:
        lab = np.ascontiguousarray(labels, dtype=np.intc)
        if lab.shape != (h, w):
            raise ValueError("labels: shape %s, the field is %s" % (lab.shape, (h, w)))
        n_labels = int(lab.max()) + 1 if lab.size else 0
        _check(lib.svp_psf_map_regions(cs, n, ffi.from_buffer("int[]", lab), w, h, n_labels,
                                       mo, field, rep))
    fmap = PSFMap(field[0])
    r = rep[0]
    try:
        report = {"n_samples": r.n_samples,
                  "mapped": {p: bool(r.mapped[q]) for q, p in enumerate(_PARAMS)},
                  "rejections": [{p: _REJECT.get(r.reject[i * 5 + q], r.reject[i * 5 + q])
                                  for q, p in enumerate(_PARAMS)} for i in range(r.n_samples)]}
        if labels is None:
            report["degree"] = {p: r.degree[q] for q, p in enumerate(_PARAMS)}
            report["rms"] = {p: r.rms[q] for q, p in enumerate(_PARAMS)}
            report["n_used"] = {p: r.n_used[q] for q, p in enumerate(_PARAMS)}
        else:
            report["n_regions"] = r.n_regions
            report["n_groups"] = r.n_groups
            report["regions"] = [{"label": g.label, "count": g.count, "group": g.group,
                                  "mean": dict(zip(_PARAMS, list(g.mean)))}
                                 for g in (r.regions[i] for i in range(r.n_regions))]
    finally:
        lib.svp_map_report_free(r)
    return fmap, report


# ---- ODMR stacks ------------------------------------------------------------------------------


def read_stack(path):
    """Reads an image stack as svpsf fit-odmr does (svp_stack_read): a multi-page TIFF (one
    frame per page), a .npy of shape (frames, height, width), or any single image (one frame).
    Returns a (frames, height, width) float64 array (one copy: the library holds every frame
    in its own buffer)."""
    out = ffi.new("svp_stack **")
    _check(lib.svp_stack_read(_path(path), out))
    s = out[0]
    try:
        nf, h, w = s.n_frames, s.height, s.width
        a = np.empty((nf, h, w), dtype=np.float64)
        for i in range(nf):
            a[i] = np.frombuffer(ffi.buffer(s.frame[i].data, 8 * w * h),
                                 dtype=np.float64).reshape(h, w)
    finally:
        lib.svp_stack_free(s)
    return a


class OdmrFit(dict):
    """fit_odmr's maps by name, also as attributes (r.field, r["field"]); .n_failed."""

    def __getattr__(self, name):
        try:
            return self[name]
        except KeyError:
            raise AttributeError(name) from None


_LINES = {"pair": "SVP_ODMR_LINES_PAIR", "two": "SVP_ODMR_LINES_TWO", "one": "SVP_ODMR_LINES_ONE"}
_LINE_SIGN = {"upper": 1, "lower": -1}
# the maps in the order of svp_odmr_maps, named as the files `svpsf fit-odmr` writes
_ODMR_MAPS = (("field", "field"), ("field_sigma", "field_sigma"), ("field_lower", "field_lower"),
              ("field_lower_sigma", "field_lower_sigma"), ("field_upper", "field_upper"),
              ("field_upper_sigma", "field_upper_sigma"), ("pl", "baseline"),
              ("pl_sigma", "baseline_sigma"), ("contrast", "contrast"),
              ("contrast_sigma", "contrast_sigma"), ("linewidth", "linewidth"),
              ("linewidth_sigma", "linewidth_sigma"), ("quality", "quality"),
              ("converged", "converged"))


def _stack_frames(stack):
    """Frames of a stack as C-contiguous float64 2-D arrays: views of a C-contiguous float64
    (n, h, w) array (no copy), else converted once."""
    if isinstance(stack, np.ndarray):
        st = stack if stack.dtype == np.float64 and stack.flags.c_contiguous else \
            np.ascontiguousarray(stack, dtype=np.float64)
        if st.ndim != 3:
            raise ValueError("stack: shape (n_freq, height, width) needed, got %s" % (st.shape,))
        if st.shape[1] < 1 or st.shape[2] < 1:
            raise ValueError("stack: the frames are empty (shape %s)" % (st.shape,))
        return [st[i] for i in range(st.shape[0])]
    frames = [_input(f, "stack[%d]" % i) for i, f in enumerate(stack)]
    if frames:
        _same_shape(frames, ["stack[%d]" % i for i in range(len(frames))])
    return frames


def fit_odmr(stack, frequencies, lines="pair", line=None, zero_field_hz=2.870e9,
             gamma_hz_per_t=28.033e9, linewidth_hz=1e6, baseline_frames=3, max_iterations=None,
             failed="nan", register=False, drift_degree=1, align_to="mean", psf=None,
             iterations=75, margin="auto", tail_tol=1e-3):
    """Per-pixel Lorentzian fits of an ODMR stack (svp_odmr_fit_maps; `svpsf fit-odmr`,
    docs/model.md §10): stack of shape (n_freq, height, width) (or a sequence of 2-D frames),
    one frame per frequency (Hz; a decreasing sweep is put in increasing order, as the program
    does). A C-contiguous float64 stack is handed to the library in place.

    lines: 'pair' (both lines at D ± γB about zero_field_hz: field = |B|), 'two' (two free
    dips f₋ < f₊: field = (f₊ − f₋) / 2γ, and field_lower / field_upper per resonance) or
    'one' (one dip; line='upper' (default) or 'lower' gives its sign). linewidth_hz: the
    starting FWHM; baseline_frames: frames at each end for the starting baseline;
    max_iterations: Levenberg–Marquardt steps per pixel (default 200). failed: 'nan' (as the
    program: the field maps are NaN where the fit did not converge) or 'keep'.

    register=True aligns the frames first (svp_cube_align; `svpsf fit-odmr --register`,
    docs/model.md §10 "Drift"), on a copy: the caller's stack is left as it is. drift_degree:
    the degree of the drift polynomial in the frame index (-1: each frame its own shift);
    align_to: 'mean' (the sweep's mean position) or the index of the stack's frame whose
    position the maps take. The result then has .drift, an (n_freq, 2) array of each stack
    frame's (shift_x, shift_y) in pixels (what drift.csv holds), and .register, a dict of
    max_shift, median_deviation, max_deviation, min_correlation (px, px, px, 1). A frame whose
    correlation with the mean frame is below 0.5 raises DoubtfulError (the program's exit 3).

    psf (a PSF, or a Blur built for the frames plus `margin` pixels per side) deconvolves every
    frame (Richardson–Lucy, `iterations` each; svp_cube_deconvolve, `svpsf fit-odmr --psf`,
    docs/model.md §10 "Blur before the estimate") on a copy before the fit; margin: pixels per
    side whose light comes from outside the view, or 'auto' (a PSF's reach, 0 with a halo;
    0 for anything else); tail_tol: one PSF's far tail on a coarse grid within this error
    (`--tail-tol`, 0 = never). Values below 0 are taken as 0 (RL needs data >= 0), counted in
    .negative_values.

    Returns an OdmrFit (a dict, keys also attributes) with the maps `svpsf fit-odmr` writes,
    in SI units (field in T, linewidth in Hz): field, field_sigma (with lines='two' also
    field_lower, field_lower_sigma, field_upper, field_upper_sigma), pl, pl_sigma, contrast,
    contrast_sigma, linewidth, linewidth_sigma, quality (R²), converged (1 or 0); and
    .n_failed, the pixels not converged or missing. σ: 1σ from (JᵀJ)⁻¹ χ²/dof."""
    if lines not in _LINES:
        raise ValueError("lines %r: one of %s" % (lines, ", ".join(_LINES)))
    if line is not None and lines != "one":
        raise ValueError("line=%r needs lines='one'" % (line,))
    if (line or "upper") not in _LINE_SIGN:
        raise ValueError("line %r: 'upper' or 'lower'" % (line,))
    if failed not in ("nan", "keep"):
        raise ValueError("failed %r: 'nan' or 'keep'" % (failed,))
    frames = _stack_frames(stack)
    nf = len(frames)
    fr = np.array(frequencies, dtype=np.float64)
    if fr.ndim != 1:
        raise ValueError("frequencies: one value per frame (a 1-D sequence), got an array of "
                         "shape %s" % (fr.shape,))
    if fr.size != nf:
        raise ValueError("frequencies: %d values for a stack of %d frames" % (fr.size, nf))
    for f in range(nf):
        if not np.isfinite(fr[f]):
            raise ValueError("frequencies: frequency %d is not a finite number" % (f + 1))
    decreasing = nf > 1 and fr[-1] < fr[0]
    if decreasing:
        frames, fr = frames[::-1], np.ascontiguousarray(fr[::-1])
    for f in range(1, nf):
        if not fr[f] > fr[f - 1]:
            raise ValueError("frequencies: not monotonic: frame %d at %.9g Hz after %.9g Hz"
                             % (nf - f if decreasing else f + 1, fr[f], fr[f - 1]))
    if nf and fr[0] > 0 and not fr[-1] >= 1e6:  # as `svpsf fit-odmr` (<= 0: the library's)
        raise ValueError("frequencies: the sweep ends at %.6g Hz, below 1 MHz where no NV line "
                         "lies: give them in Hz" % fr[-1])
    if register and not (isinstance(drift_degree, (int, np.integer)) and -1 <= drift_degree <= 5):
        raise ValueError("drift_degree %r: an integer in -1 .. 5" % (drift_degree,))
    if register and not (align_to == "mean" or (isinstance(align_to, (int, np.integer))
                                                and 0 <= align_to < nf)):
        raise ValueError("align_to %r: 'mean' or a frame index 0 .. %d" % (align_to, nf - 1))
    if register or psf is not None:  # aligned / deconvolved in place: on a copy
        frames = [np.array(f, dtype=np.float64, order="C") for f in frames]
    h, w = frames[0].shape if nf else (0, 0)
    imgs = _Images()
    cube = ffi.new("svp_cube *")
    cube.width, cube.height, cube.n_freq = w, h, nf
    fbuf = ffi.from_buffer("double[]", fr)
    cube.freq = fbuf
    cube.frame = imgs.array([imgs.view(f) for f in frames])
    if psf is not None:
        if not (isinstance(iterations, (int, np.integer)) and iterations >= 1):
            raise ValueError("iterations %r: an integer >= 1" % (iterations,))
        if margin == "auto":  # a map: 0 unless given, as `fit-odmr --psf MAP`
            margin = lib.svp_psf_auto_margin(psf._c, w, h) if isinstance(psf, PSF) else 0
        if not (isinstance(margin, (int, np.integer)) and margin >= 0):
            raise ValueError("margin %r: 'auto' or an integer >= 0" % (margin,))
        _check(lib.svp_correct_check_margin(int(margin), w, h))  # as `--margin`
        if not 0 <= float(tail_tol) < 1:
            raise ValueError("tail_tol %r: in [0, 1)" % (tail_tol,))
    else:  # what only --psf uses, given without it: refused as the program refuses it
        given = [k for k, v, d in (("iterations", iterations, 75), ("margin", margin, "auto"),
                                   ("tail_tol", tail_tol, 1e-3)) if v != d]
        if given:
            raise ValueError("%s: used only with psf" % ", ".join(given))
    if not register and (drift_degree != 1 or align_to != "mean"):
        raise ValueError("drift_degree, align_to: used only with register=True")
    drift = info = None
    if register:
        ao = ffi.new("svp_align_options *")
        lib.svp_align_defaults(ao)
        ao.degree = int(drift_degree)
        if align_to != "mean":  # the stack's frame k is nf − 1 − k of a decreasing sweep
            ao.reference_frame = nf - 1 - int(align_to) if decreasing else int(align_to)
        sx, sy = ffi.new("double[]", nf), ffi.new("double[]", nf)
        info = ffi.new("svp_align_info *")
        _check(lib.svp_cube_align(cube, ao, sx, sy, info, ffi.NULL, ffi.NULL))
        if info.n_low_correlation:
            worst = info.worst_frame
            raise DoubtfulError(lib.SVP_ERR_DOUBTFUL,
                "register: %d of %d frames correlate too weakly with the mean frame to be "
                "aligned (weakest: frame %d of the stack, correlation %.2f < 0.5)"
                % (info.n_low_correlation, nf, nf - 1 - worst if decreasing else worst,
                   info.min_correlation))
        drift = np.array([[sx[f], sy[f]] for f in range(nf)])
        if decreasing:
            drift = drift[::-1].copy()
    if psf is not None:
        blur = _blur_for(_padded(psf, margin), (h + 2 * margin, w + 2 * margin), "zero", None,
                         None, margin=margin, tail_tol=float(tail_tol))
        tol_before = lib.svp_blur_tail_tol(blur._ptr)  # a caller's Blur gets it back
        _check(lib.svp_blur_set_tail(blur._ptr, float(tail_tol)))
        dopt = ffi.new("svp_deconv_options *")
        lib.svp_deconv_defaults(dopt)
        dopt.iterations = _count(iterations, "iterations")
        negative = ffi.new("size_t *")
        try:
            _check(lib.svp_cube_deconvolve(blur._ptr, cube, int(margin), dopt, negative,
                                           ffi.NULL, ffi.NULL))
        finally:
            lib.svp_blur_set_tail(blur._ptr, tol_before)
    odmr = ffi.new("svp_odmr *")
    lib.svp_odmr_defaults(odmr)
    odmr.zero_field_hz, odmr.gamma_hz_per_t, odmr.linewidth_hz = (zero_field_hz, gamma_hz_per_t,
                                                                    linewidth_hz)
    opt = ffi.new("svp_odmr_fit_options *")
    lib.svp_odmr_fit_defaults(opt)
    opt.lines = getattr(lib, _LINES[lines])
    opt.line_sign = _LINE_SIGN[line or "upper"]
    opt.baseline_frames = _count(baseline_frames, "baseline_frames", 1, 1000000)
    if max_iterations is not None:
        opt.lm.max_iterations = _count(max_iterations, "max_iterations")
    maps = ffi.new("svp_odmr_maps *")
    result = OdmrFit()
    for name, member in _ODMR_MAPS:
        if lines != "two" and name in ("field_lower", "field_lower_sigma", "field_upper",
                                       "field_upper_sigma"):
            continue
        a, img = imgs.out((h, w))
        setattr(maps, member, img)
        result[name] = a
    n_failed = ffi.new("size_t *")
    _check(lib.svp_odmr_fit_maps(odmr, cube, opt, maps, n_failed))
    if failed == "nan":
        bad = result["converged"] != 1
        for name in ("field", "field_sigma", "field_lower", "field_lower_sigma", "field_upper",
                     "field_upper_sigma"):
            if name in result:
                result[name][bad] = np.nan
    result.n_failed = int(n_failed[0])
    if nf and result.n_failed == w * h:  # maps of NaN only: `svpsf fit-odmr` exits 3
        raise DoubtfulError(lib.SVP_ERR_DOUBTFUL,
                            "none of the %d pixel fits found a dip in the sweep (%.6g to %.6g "
                            "GHz): no light, no dip above the noise, lines outside the sweep, "
                            "or frequencies in another unit than Hz" % (w * h, fr[0] * 1e-9,
                                                                        fr[-1] * 1e-9))
    if psf is not None:
        result.negative_values = int(negative[0])
    if register:
        result.drift = drift
        result.register = dict(max_shift=info.max_shift, median_deviation=info.median_deviation,
                               max_deviation=info.max_deviation,
                               min_correlation=info.min_correlation)
    return result
