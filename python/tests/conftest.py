"""pytest set-up for the svpsf package tests (meson suite `python`: see python/meson.build).

The tests import svpsf from python/ (PYTHONPATH) over the built library (SVPSF_LIBRARY) and
compare it with the built `svpsf` program (SVPSF_CLI). FFT plans are made with FFTW_ESTIMATE on
both sides so that both use the same plans and the results can be compared bit for bit."""
import os
import subprocess

import numpy as np
import pytest

import svpsf


@pytest.fixture(scope="session")
def cli():
    path = os.environ.get("SVPSF_CLI")
    if not path or not os.access(path, os.X_OK):
        pytest.skip("SVPSF_CLI does not name the svpsf program: no comparison with the CLI")

    def run(*args, ok=True):
        p = subprocess.run([path, *map(str, args)], capture_output=True, text=True)
        if ok and p.returncode != 0:
            raise AssertionError("svpsf %s failed (%d): %s" % (" ".join(map(str, args)),
                                                               p.returncode, p.stderr))
        return p

    return run


@pytest.fixture(autouse=True)
def deterministic_plans():
    svpsf.set_fft_effort("estimate")
    svpsf.set_threads(2)
    yield


def smooth_maps(h, w, seed=1):
    """A PL map with a quenched stripe and a dark corner, and a signed field map (tesla)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(float)
    pl = 1.0 - 0.85 * np.exp(-0.5 * ((x - 0.55 * w) / (0.06 * w)) ** 2)
    pl *= 0.6 + 0.4 * np.cos(2 * np.pi * y / h) ** 2
    pl += 0.01 * rng.random((h, w))
    field = 1e-4 * (np.tanh((x - 0.4 * w) / 4.0) - 0.5 * np.exp(-((y - 0.3 * h) / 6.0) ** 2))
    return pl, field


@pytest.fixture
def maps():
    return smooth_maps(96, 80)
