"""Shared helpers of the benchmark scripts (tools/bench/run and tools/bench/section_*.py).

Imported by the section scripts with `sys.path.insert(0, os.path.dirname(__file__))`; it is not
an installed module and has no third-party dependencies.
"""
import datetime
import json
import os
import platform
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def log(msg):
    print(f"[bench] {msg}", file=sys.stderr, flush=True)


def run_json(cmd, timeout=3600):
    """Runs one benchmark process; returns its last JSON line (or an error dict)."""
    log(" ".join(os.path.relpath(c, ROOT) if c.startswith(ROOT) else c for c in cmd))
    try:
        p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": "timeout"}
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    result = json.loads(lines[-1]) if lines else {"error": "no output"}
    if p.returncode != 0:
        result.setdefault("error", f"exit {p.returncode}")
        result["returncode"] = p.returncode
        result["stderr"] = p.stderr.strip()[-400:]
        log(f"  failed ({p.returncode}): {result.get('message', '')} {result['stderr']}")
    return result


def sh(cmd):
    try:
        return subprocess.run(cmd, capture_output=True, text=True, shell=True).stdout.strip()
    except OSError:
        return ""


def machine_info():
    lscpu = {}
    for line in sh("LC_ALL=C lscpu").splitlines():
        k, _, v = line.partition(":")
        lscpu[k.strip()] = v.strip()
    mem = ""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemTotal"):
                    mem = f"{int(line.split()[1]) / 1048576:.1f} GiB"
    except OSError:
        pass
    return {
        "cpu": lscpu.get("Model name", platform.processor() or "unknown"),
        "cpus": lscpu.get("CPU(s)", str(os.cpu_count())),
        "cores": lscpu.get("Core(s) per socket", "?"),
        "threads_per_core": lscpu.get("Thread(s) per core", "?"),
        "mhz": lscpu.get("CPU max MHz", lscpu.get("CPU MHz", "")),
        "memory": mem,
        "kernel": platform.release(),
        "os": sh(". /etc/os-release && echo $PRETTY_NAME"),
        "gcc": sh("gcc -dumpfullversion"),
        "fftw": sh("dpkg-query -W -f='${Version}' libfftw3-dev"),
        "skimage": sh("dpkg-query -W -f='${Version}' python3-skimage"),
        "commit": sh(f"git -C {ROOT} rev-parse --short HEAD 2>/dev/null"),
        "dirty": bool(sh(f"git -C {ROOT} status --porcelain -uno 2>/dev/null")),
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
    }


def loadavg():
    try:
        with open("/proc/loadavg") as f:
            return f.read().split()[0]
    except OSError:
        return "?"


def ms(s):
    return "–" if s is None else f"{1e3 * s:.1f}"


def sig(v, nd=3):
    """v to nd significant digits; – for None or NaN."""
    if v is None or (isinstance(v, float) and v != v):
        return "–"
    return f"{v:.{nd}g}"


def built(build, *parts):
    """The path of a built program under the build folder (os.path.join(build, *parts)); exits
    with a message when it is missing."""
    path = os.path.join(build, *parts)
    if not os.access(path, os.X_OK):
        sys.exit(f"{path} is missing: build first (tools/run bench, or ninja -C {build})")
    return path


def ok(r):
    return r is not None and "error" not in r


def verdict(ratio, target, smaller_is_better=True):
    if ratio is None:
        return "–"
    met = ratio <= target if smaller_is_better else ratio >= target
    return "met" if met else "**missed**"


def describe_error(r):
    if r is None:
        return "not run"
    if r.get("returncode") == 3:
        return "not implemented yet"
    return f"failed ({r.get('error')})"


def built_library(build):
    """The shared libsvpsf.so.MAJOR... file of a build tree (meson's libsvpsf.so.p/ is a
    folder, not the library), or None."""
    import glob
    libs = sorted((p for p in glob.glob(os.path.join(build, "libsvpsf.so.*"))
                   if os.path.isfile(p)), key=len)
    return libs[0] if libs else None


def interleaved(wrapped, raw, reps):
    """Times wrapped() and raw() (which must return 0) one after the other, reps times: the two
    lists of seconds, each pair taken moments apart."""
    import time
    tw, tr = [], []
    for _ in range(reps):
        t0 = time.perf_counter()
        wrapped()
        t1 = time.perf_counter()
        assert raw() == 0
        t2 = time.perf_counter()
        tw.append(t1 - t0)
        tr.append(t2 - t1)
    return tw, tr
