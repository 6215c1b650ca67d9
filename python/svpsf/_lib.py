"""Loading libsvpsf through cffi in ABI mode (no compiler needed at install or import).

The declarations come from the library's own header, svpsf.h, cleaned of what cffi's parser
does not take (preprocessor conditionals, the visibility macro); the shared library is
dlopen()ed. Where they are found, first match wins:

  header:  $SVPSF_HEADER (that file or an error); svpsf.h installed beside this file;
           ../../include/svpsf.h (a source tree)
  library: $SVPSF_LIBRARY (that library or an error); the path `meson install` wrote into _config.py; the system's search
           (libsvpsf.so.MAJOR, then libsvpsf.so)
"""
import os
import re

import cffi

_HERE = os.path.dirname(os.path.abspath(__file__))


def _header_path():
    env = os.environ.get("SVPSF_HEADER")
    if env:  # an explicit choice: that header or an error
        if not os.path.isfile(env):
            raise ImportError("svpsf: SVPSF_HEADER=%s: no such file" % env)
        return env
    candidates = [os.path.join(_HERE, "svpsf.h"),
                  os.path.join(_HERE, "..", "..", "include", "svpsf.h")]
    for path in candidates:
        if path and os.path.isfile(path):
            return path
    raise ImportError("svpsf: the header svpsf.h was not found (set SVPSF_HEADER to its path); "
                      "looked in: " + ", ".join(p for p in candidates if p))


def _cdef_text(header):
    with open(header, encoding="utf-8") as f:
        text = f.read()
    text = re.sub(r"/\*.*?\*/", " ", text, flags=re.S)  # comments (with their UTF-8)
    text = re.sub(r"^\s*#\s*ifdef\s+__cplusplus.*?^\s*#\s*endif", "", text, flags=re.S | re.M)
    text = re.sub(r"^\s*#\s*if\s+defined\(_WIN32\).*?^\s*#\s*endif", "", text,
                  flags=re.S | re.M)
    lines = []
    for line in text.split("\n"):
        s = line.strip()
        if s.startswith("#"):
            # integer constants stay (cffi takes `#define NAME 64`), the rest goes
            if re.match(r"^#\s*define\s+\w+\s+\d+\s*$", s):
                lines.append(s)
            continue
        lines.append(line)
    text = "\n".join(lines)
    text = re.sub(r"\bSVP_API\b", "", text)
    # cffi wants array lengths as constants: fold products such as [8 * 8]
    text = re.sub(r"\[\s*(\d+)\s*\*\s*(\d+)\s*\]",
                  lambda m: "[%d]" % (int(m.group(1)) * int(m.group(2))), text)
    return text


def _config_library():
    try:
        from . import _config  # written by meson install
    except ImportError:
        return None
    return getattr(_config, "LIBRARY", None)


def _open(ffi):
    tried = []
    env = os.environ.get("SVPSF_LIBRARY")
    if env:  # an explicit choice: that library or an error
        try:
            return ffi.dlopen(env), env
        except OSError as e:
            raise ImportError("svpsf: SVPSF_LIBRARY=%s cannot be loaded: %s" % (env, e)) from e
    candidates = []
    configured = _config_library()
    if configured:
        candidates.append(configured)
    soname = None
    try:
        from . import _config
        soname = getattr(_config, "SONAME", None)
    except ImportError:
        pass
    candidates += [c for c in (soname, "libsvpsf.so") if c]
    for path in candidates:
        try:
            return ffi.dlopen(path), path
        except OSError as e:
            tried.append("%s (%s)" % (path, e))
    raise ImportError("svpsf: libsvpsf could not be loaded; set SVPSF_LIBRARY to the shared "
                      "library's path. Tried: " + "; ".join(tried))


HEADER = _header_path()
ffi = cffi.FFI()
ffi.cdef(_cdef_text(HEADER))
lib, LIBRARY = _open(ffi)
