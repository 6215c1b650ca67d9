"""The svpsf package against the svpsf program on the same inputs, its errors and its memory.

Equality with the CLI is bit for bit (np.array_equal on float64 .npy outputs): the same library
calls on the same data with the same (FFTW_ESTIMATE) plans and thread count."""
import json
import os
import tracemalloc

import numpy as np
import pytest

import svpsf
from conftest import smooth_maps
from svpsf._lib import ffi

MOFFAT = "pixel_um: 0.1\npsf: {model: moffat, fwhm_um: 0.61, beta: 1.5, halo: 0.02}\n"
GRID = ("pixel_um: 0.1\nimage: {width: 80, height: 96}\nmodel: moffat\nkind: grid\n"
        "nodes: {nx: 2, ny: 2}\nnode_psfs:\n  - {fwhm_um: 0.5, beta: 3.0}\n"
        "  - {fwhm_um: 0.8, beta: 1.5}\n  - {fwhm_um: 0.6, beta: 2.5}\n"
        "  - {fwhm_um: 1.0, beta: 1.2, halo: 0.1}\n")

COMMON = ["--fft", "estimate", "--threads", "2", "--format", "npy", "--quiet"]


def write(tmp_path, name, content):
    p = tmp_path / name
    if isinstance(content, str):
        p.write_text(content)
    else:
        np.save(p, content)
    return str(p)


def test_version_is_the_programs(cli):
    first = cli("--version").stdout.splitlines()[0]
    assert first == "svpsf " + svpsf.version()


def test_psf_model_matches_cli_render(cli, tmp_path):
    f = write(tmp_path, "psf.yaml", MOFFAT)
    cli("psf", f, "--size", "41", "-o", tmp_path / "k.npy", "--quiet")
    read = svpsf.read_psf(f)
    assert isinstance(read.psf, svpsf.PSF) and read.pixel_um == 0.1 and read.boundary == "zero"
    assert read.psf.model == "moffat" and read.psf.fwhm == pytest.approx(6.1)
    assert np.array_equal(read.psf.render(20), np.load(tmp_path / "k.npy"))
    # FWHM: the profile is half its peak at r = FWHM / 2
    assert read.psf.profile(read.psf.fwhm / 2, 0) == pytest.approx(0.5, rel=1e-12)


@pytest.mark.parametrize("psf_text, extra", [(MOFFAT, []), (GRID, ["--nodes", "2x2"]),
                                             (MOFFAT + "boundary: mirror\n", [])])
def test_forward_equals_cli(cli, tmp_path, maps, psf_text, extra):
    pl, field = maps
    pf = write(tmp_path, "psf.yaml", psf_text)
    cli("forward", "--pl", write(tmp_path, "pl.npy", pl), "--field",
        write(tmp_path, "B.npy", field), "--psf", pf, "-o", tmp_path / "out", *COMMON, *extra)
    r = svpsf.forward(pl, field, pf, nodes=(2, 2))
    assert np.array_equal(r.pl, np.load(tmp_path / "out" / "pl.npy"))
    assert np.array_equal(r.fields, np.load(tmp_path / "out" / "field.npy"))
    assert np.array_equal(r.validity, np.load(tmp_path / "out" / "validity.npy"))


@pytest.mark.parametrize("args, kwargs", [
    ([], {}),
    (["--method", "w", "--balance", "1e-4"], dict(method="w", balance=1e-4)),
    (["--method", "r", "--iterations", "40"], dict(method="r", iterations=40)),
    (["--iterations", "auto", "--acceleration", "biggs-andrews", "--keep-doubtful"],
     dict(iterations="auto", acceleration="biggs-andrews", keep_doubtful=True)),
    (["--side-by-side", "off"], dict(side_by_side=False)),
    (["--tail-tol", "0"], dict(tail_tol=0)),
    (["--tail-tol", "0.05"], dict(tail_tol=0.05)),
])
def test_correct_equals_cli(cli, tmp_path, maps, args, kwargs):
    pl, field = maps
    pf = write(tmp_path, "psf.yaml", MOFFAT)
    apparent = svpsf.forward(pl, [field, -0.5 * field], pf)
    plf = write(tmp_path, "pl_app.npy", apparent.pl)
    b1 = write(tmp_path, "Bx.npy", apparent.fields[0])
    b2 = write(tmp_path, "Bz.npy", apparent.fields[1])
    # the CLI's default margin for r is auto and its precision single, the library's (and so
    # Python's) 0 and double
    cli("correct", "--pl", plf, "--field", b1, "--field", b2, "--psf", pf, "-o",
        tmp_path / "out", "--margin", "0", "--precision", "double", *COMMON, *args)
    r = svpsf.correct(apparent.pl, apparent.fields, pf, **kwargs)
    out = tmp_path / "out"
    assert np.array_equal(r.pl, np.load(out / "pl.npy"))
    assert np.array_equal(r.fields[0], np.load(out / "field_Bx.npy"))
    assert np.array_equal(r.fields[1], np.load(out / "field_Bz.npy"))
    assert np.array_equal(r.validity, np.load(out / "validity.npy"))
    results = json.load(open(out / "summary.json"))["results"]
    assert r.n_missing == results["n_missing"] == 0
    assert int(np.count_nonzero(r.validity < 1)) == results["n_flagged"]
    assert r.summary["side_by_side"] == results["side_by_side"]
    assert r.summary["tail_step"] == results["tail_step_px"]
    assert r.summary["doubt_names"] == [d for d in results["doubts"].split(",") if d]


def test_doubtful_correction_kept_and_named(cli, tmp_path, maps):
    """Wiener at a vanishing balance blows up: refused (DoubtfulError) as the program exits 3, and
    kept on request with its doubts named as the program's summary.json names them."""
    pl, field = maps
    pf = write(tmp_path, "psf.yaml", MOFFAT)
    a = svpsf.forward(pl, field, pf)
    noisy = a.fields + 0.05 * np.abs(a.fields).max() * np.random.default_rng(3).standard_normal(
        a.fields.shape)
    with pytest.raises(svpsf.DoubtfulError, match="result in doubt"):
        svpsf.correct(a.pl, noisy, pf, method="w", balance=1e-12)
    r = svpsf.correct(a.pl, noisy, pf, method="w", balance=1e-12, keep_doubtful=True)
    cli("correct", "--pl", write(tmp_path, "pl.npy", a.pl), "--field",
        write(tmp_path, "B.npy", noisy), "--psf", pf, "--method", "w", "--balance", "1e-12",
        "--keep-doubtful", "-o", tmp_path / "out", *COMMON)
    results = json.load(open(tmp_path / "out" / "summary.json"))["results"]
    assert r.summary["doubts"] != 0 and r.summary["doubt_names"]
    assert ",".join(r.summary["doubt_names"]) == results["doubts"]


def test_correct_with_a_psf_map_and_missing_pixels_equals_cli(cli, tmp_path, maps):
    pl, field = maps
    pf = write(tmp_path, "map.yaml", GRID)
    a = svpsf.forward(pl, field, pf, nodes=4)
    measured = a.fields.copy()
    measured[40:43, 10:12] = np.nan  # failed fits: missing data
    cli("correct", "--pl", write(tmp_path, "pl.npy", a.pl), "--field",
        write(tmp_path, "B.npy", measured), "--psf", pf, "--nodes", "4", "--method", "w",
        "-o", tmp_path / "out", *COMMON)
    r = svpsf.correct(a.pl, measured, pf, method="w", nodes=4)
    assert r.n_missing == 6
    assert np.array_equal(r.fields, np.load(tmp_path / "out" / "field.npy"))
    assert np.all(np.isfinite(r.fields))


def test_correct_with_a_map_and_a_margin_equals_cli(cli, tmp_path, maps):
    """A margin with a PSF map (its edge PSFs carried outward, PSFMap.pad): margin='auto' and
    a number give the program's --margin auto / N bit for bit; the map's auto margin is its
    widest PSF's; a halo anywhere gives none."""
    pl, field = maps
    pf = write(tmp_path, "map.yaml", GRID.replace(", halo: 0.1", ""))
    fmap = svpsf.read_psf(pf).psf
    widest = svpsf.PSF("moffat", fwhm=10.0, beta=1.2)
    assert fmap.auto_margin(pl.shape) == widest.auto_margin(pl.shape) > 0
    assert svpsf.read_psf(write(tmp_path, "halo.yaml", GRID)).psf.auto_margin(pl.shape) == 0
    padded = fmap.pad(5)
    assert padded.shape == (96 + 10, 80 + 10)
    assert padded.params_at(0, 0) == fmap.params_at(0, 0)
    assert padded.params_at(5 + 30, 5 + 40) == fmap.params_at(30, 40)
    with pytest.raises(svpsf.Error, match="padded"):
        padded.write(tmp_path / "padded.yaml", 0.1)
    a = svpsf.forward(pl, field, pf, nodes=2)
    pln, fln = write(tmp_path, "pl.npy", a.pl), write(tmp_path, "B.npy", a.fields)
    for margin in ("auto", "5"):
        out = tmp_path / ("out" + margin)
        cli("correct", "--pl", pln, "--field", fln, "--psf", pf, "--nodes", "2", "--iterations",
            "10", "--margin", margin, "-o", out, *COMMON)
        r = svpsf.correct(a.pl, a.fields, pf, nodes=2, iterations=10,
                          margin=margin if margin == "auto" else int(margin))
        assert np.array_equal(r.fields, np.load(out / "field.npy"))
        settings = json.load(open(out / "summary.json"))["settings"]
        assert settings["margin"] == (fmap.auto_margin(pl.shape) if margin == "auto" else 5)


def test_automatic_representation_equals_cli(cli, tmp_path, maps):
    """Without nodes / rank both choose the representation by operator_tol with the same cost
    model (the H + Hᵀ pairs the command runs: 1 for forward, 2 x 10 for r at 10 iterations)."""
    pl, field = maps
    pf = write(tmp_path, "map.yaml", GRID)
    cli("forward", "--pl", write(tmp_path, "pl0.npy", pl), "--field",
        write(tmp_path, "B0.npy", field), "--psf", pf, "--operator-tol", "1e-2", "-o",
        tmp_path / "fwd", *COMMON)
    a = svpsf.forward(pl, field, svpsf.Blur(svpsf.read_psf(pf).psf, pl.shape,
                                            operator_tol=1e-2, applications=1))
    assert np.array_equal(a.pl, np.load(tmp_path / "fwd" / "pl.npy"))
    cli("correct", "--pl", write(tmp_path, "pl.npy", a.pl), "--field",
        write(tmp_path, "B.npy", a.fields), "--psf", pf, "--method", "r", "--iterations", "10",
        "--margin", "0", "-o", tmp_path / "out", *COMMON)
    r = svpsf.correct(a.pl, a.fields, pf, method="r", iterations=10)
    assert np.array_equal(r.fields, np.load(tmp_path / "out" / "field.npy"))
    settings = json.load(open(tmp_path / "out" / "summary.json"))["settings"]
    assert settings["operator_applications"] == 20
    assert settings["operator_apply_s"] > 0 and settings["operator_adjoint_s"] > 0


def test_lowrank_map_tail_equals_cli(cli, tmp_path):
    """A low-rank map's far tail on a coarse grid (tail_tol, docs/model.md §9): correct with
    r equals `svpsf correct --rank 3` bit for bit and both take the tail; a Blur built with the
    same tail_tol reports it in .variant, one without none, and the two apply within the
    tail's estimated ℓ1 error per unit flux of each other."""
    h, w = 200, 180
    pl, field = smooth_maps(h, w)
    pf = write(tmp_path, "map.yaml",
               "pixel_um: 0.1\nimage: {width: %d, height: %d}\nmodel: moffat\nkind: grid\n"
               "nodes: {nx: 2, ny: 2}\nnode_psfs:\n  - {fwhm_um: 0.35, beta: 1.1}\n"
               "  - {fwhm_um: 0.45, beta: 1.2}\n  - {fwhm_um: 0.4, beta: 1.1}\n"
               "  - {fwhm_um: 0.5, beta: 1.3}\n" % (w, h))
    fmap = svpsf.read_psf(pf).psf
    a = svpsf.forward(pl, field, pf, rank=3)
    cli("correct", "--pl", write(tmp_path, "pl.npy", a.pl), "--field",
        write(tmp_path, "B.npy", a.fields), "--psf", pf, "--rank", "3", "--method", "r",
        "--iterations", "10", "--margin", "0", "-o", tmp_path / "out", *COMMON)
    r = svpsf.correct(a.pl, a.fields, pf, rank=3, method="r", iterations=10)
    assert np.array_equal(r.fields, np.load(tmp_path / "out" / "field.npy"))
    results = json.load(open(tmp_path / "out" / "summary.json"))["results"]
    assert results["tail_step_px"] > 0 and 0 < results["tail_error"] <= 1e-3
    assert r.summary["tail_step"] == results["tail_step_px"]
    tail = svpsf.Blur(fmap, (h, w), rank=3, tail_tol=1e-3)
    plain = svpsf.Blur(fmap, (h, w), rank=3)
    v = tail.variant
    assert v["tail_step"] == results["tail_step_px"] and v["tail_split"] > 0
    assert plain.variant["tail_step"] == 0
    for y, x in ((0, 0), (h // 2, w // 3), (h - 1, w - 1)):
        e = np.zeros((h, w))
        e[y, x] = 1.0
        assert 0 < np.abs(tail.apply(e) - plain.apply(e)).sum() <= v["tail_error"]


def test_regions_equals_cli(cli, tmp_path, maps):
    """regions=True is `--regions` (one kernel per region of a region map): forward and correct
    equal the program's bit for bit, the Blur reports the representation and its two kernels;
    with nodes, or on a map that is not of kind regions, it is refused."""
    pl, field = maps
    labels = np.zeros(pl.shape, dtype=np.int32)
    labels[:, 30:52] = 1
    np.save(tmp_path / "map.labels.npy", labels)
    pf = write(tmp_path, "map.yaml",
               "pixel_um: 0.1\nimage: {width: %d, height: %d}\nmodel: moffat\nkind: regions\n"
               "labels_file: map.labels.npy\nregions:\n  - {label: 0, fwhm_um: 0.5, beta: 2.5}\n"
               "  - {label: 1, fwhm_um: 0.9, beta: 1.3, halo: 0.05}\n" % (pl.shape[1], pl.shape[0]))
    cli("forward", "--pl", write(tmp_path, "pl0.npy", pl), "--field",
        write(tmp_path, "B0.npy", field), "--psf", pf, "--regions", "-o", tmp_path / "fwd",
        *COMMON)
    a = svpsf.forward(pl, field, pf, regions=True)
    assert np.array_equal(a.pl, np.load(tmp_path / "fwd" / "pl.npy"))
    assert np.array_equal(a.fields, np.load(tmp_path / "fwd" / "field.npy"))
    cli("correct", "--pl", write(tmp_path, "pl.npy", a.pl), "--field",
        write(tmp_path, "B.npy", a.fields), "--psf", pf, "--regions", "--method", "r",
        "--iterations", "10", "--margin", "0", "--precision", "double", "-o", tmp_path / "out",
        *COMMON)
    r = svpsf.correct(a.pl, a.fields, pf, method="r", iterations=10, regions=True)
    assert np.array_equal(r.fields, np.load(tmp_path / "out" / "field.npy"))
    settings = json.load(open(tmp_path / "out" / "summary.json"))["settings"]
    assert settings["psf_representation"] == "regions" and settings["psf_region_kernels"] == 2
    v = svpsf.Blur(svpsf.read_psf(pf).psf, pl.shape, regions=True).variant
    assert v["representation"] == "regions" and v["rank"] == 2 and v["nodes"] == (0, 0)
    with pytest.raises(ValueError, match="regions cannot be combined"):
        svpsf.Blur(svpsf.read_psf(pf).psf, pl.shape, regions=True, nodes=4)
    with pytest.raises(svpsf.Error, match="kind regions"):
        svpsf.forward(pl, field, write(tmp_path, "grid.yaml", GRID), regions=True)


@pytest.mark.parametrize("args, kwargs", [
    (["--method", "wiener", "--balance", "auto"], dict(method="wiener", balance="auto")),
    (["--method", "rl", "--iterations", "30"], dict(method="rl", iterations=30)),
])
def test_deconvolve_equals_cli(cli, tmp_path, maps, args, kwargs):
    pl, _ = maps
    # mirror boundary (the psf file's): with the zero boundary and this PSF the discrepancy
    # balance ends on its lower bound, which the CLI refuses (exit 3) and Python reports
    pf = write(tmp_path, "psf.yaml", MOFFAT + "boundary: mirror\n")
    rng = np.random.default_rng(3)
    y = svpsf.Blur(pf, pl.shape).apply(pl) + 1e-3 * rng.standard_normal(pl.shape)
    cli("deconvolve", write(tmp_path, "y.npy", y), "--psf", pf, "-o", tmp_path / "x.npy",
        *COMMON, *args)
    x, report = svpsf.deconvolve(y, pf, **kwargs)
    assert np.array_equal(x, np.load(tmp_path / "x.npy"))
    if kwargs.get("balance") == "auto":
        res = json.load(open(tmp_path / "x.summary.json"))["results"]
        assert report["balance"] == res["balance"]
        assert report["noise_sigma"] == res["noise_sigma"]
        assert report["balance_at_bound"] == 0 and "balance_at_bound" not in res


def test_deconvolve_doubts_as_cli(cli, tmp_path, maps):
    # what `svpsf deconvolve` refuses with exit 3 raises DoubtfulError (it was returned: ±10
    # garbage for a constant image), and comes back on request with report["doubts"]; counts
    # beyond the program's range, or not integers, are refused, not truncated (1e9 iterations
    # ran for hours where Ctrl-C does not reach)
    pl, _ = maps
    pf = write(tmp_path, "psf.yaml", MOFFAT)
    flat = np.ones((16, 16))
    p = cli("deconvolve", write(tmp_path, "flat.npy", flat), "--psf", pf, "--method", "wiener",
            "--balance", "auto", "-o", tmp_path / "flat_x.npy", *COMMON, ok=False)
    assert p.returncode == 3
    with pytest.raises(svpsf.DoubtfulError, match="balance auto ended on the lower end"):
        svpsf.deconvolve(flat, pf, balance="auto")
    _, report = svpsf.deconvolve(flat, pf, balance="auto", keep_doubtful=True)
    assert report["doubts"] == ["balance_at_bound"]
    p = cli("deconvolve", write(tmp_path, "pl.npy", pl), "--psf", pf, "--method", "wiener",
            "--cg-max-steps", "1", "-o", tmp_path / "pl_x.npy", *COMMON, ok=False)
    assert p.returncode == 3
    with pytest.raises(svpsf.DoubtfulError, match="did not converge"):
        svpsf.deconvolve(pl, pf, cg_max_steps=1)
    _, report = svpsf.deconvolve(pl, pf, cg_max_steps=1, keep_doubtful=True)
    assert report["doubts"] == ["cg_not_converged"]
    assert svpsf.deconvolve(pl, pf)[1]["doubts"] == []
    # a kernel summing to -0.5 is refused as the program refuses it (it was normalised by -2)
    k = -np.ones((3, 3))
    k[1, 1] = 7.5
    with pytest.raises(svpsf.Error, match="kernel sums to -0.5: it cannot be normalised"):
        svpsf.Blur(k, pl.shape)
    for bad in (0, 100001, 2.5, True, "x"):
        with pytest.raises(ValueError, match="iterations"):
            svpsf.deconvolve(pl, pf, method="rl", iterations=bad)
        with pytest.raises(ValueError, match="iterations"):
            svpsf.correct(pl, pl, pf, iterations=bad)


def test_options_the_program_refuses(tmp_path, maps):
    # options `svpsf correct` refuses (ignored, or out of their range) are refused here too;
    # before, each ran with no effect or with a misleading doubt
    pl, field = maps
    pf = write(tmp_path, "psf.yaml", MOFFAT)
    with pytest.raises(ValueError, match="balance is used only"):
        svpsf.correct(pl, field, pf, method="r", balance=1e-3)
    with pytest.raises(ValueError, match="noise is only used with balance='auto'"):
        svpsf.correct(pl, field, pf, method="rw", noise=1e-3)
    with pytest.raises(ValueError, match="not with method w"):
        svpsf.correct(pl, field, pf, method="w", precision="single")
    with pytest.raises(svpsf.Error, match="noise_sigma must be >= 0"):
        svpsf.correct(pl, field, pf, method="rw", balance="auto", noise=-1)
    with pytest.raises(svpsf.Error, match=r"tail_tol must be in \[0, 1\)"):
        svpsf.correct(pl, field, pf, tail_tol=-1)
    with pytest.raises(svpsf.Error, match="field_sigma.0. is negative"):
        svpsf.correct(pl, field, pf, field_sigma=-np.ones_like(field))
    with pytest.raises(ValueError, match="margin 2.5"):
        svpsf.correct(pl, field, pf, margin=2.5)
    with pytest.raises(ValueError, match="a Blur has its own boundary"):
        svpsf.correct(pl, field, svpsf.Blur(pf, pl.shape), boundary="mirror")
    with pytest.warns(UserWarning, match="ignored for a single PSF"):
        svpsf.Blur(pf, pl.shape, nodes=2)
    # arrays and objects that were taken silently the wrong way
    with pytest.raises(ValueError, match="complex array"):
        svpsf.correct(pl + 0j, field, pf)
    for bad in (None, 2.0, {"fwhm": 2}):  # read as a 0-D "kernel image"
        with pytest.raises(TypeError, match="psf: a PSF, a PSFMap, a PSF file's path or a kernel"):
            svpsf.forward(pl, field, bad)
    q = svpsf.PSF("gaussian", fwhm=2)
    with pytest.raises(AttributeError, match="immutable"):
        q.fwhm = 6  # it showed in repr, and every computation used 2
    assert svpsf.PSF("lorentzian", fwhm=2, beta=2.5).beta == 1.0  # what it renders with
    with pytest.raises(ValueError, match="the extension says otherwise"):
        svpsf.write_image(tmp_path / "y.npy", pl, format="tif")
    r = svpsf.correct(pl.tolist(), field.tolist(), pf, method="r", iterations=5)
    assert np.array_equal(r.fields, svpsf.correct(pl, field, pf, method="r",
                                                  iterations=5).fields)


def test_fit_odmr_refusals():
    # as `svpsf fit-odmr`: a stack without dips has no map to give (NaN maps were returned),
    # frequencies below 1 MHz are not in Hz, counts are counts
    rng = np.random.default_rng(4)
    stack = 1000 + 3 * rng.standard_normal((20, 8, 8))
    freq = np.linspace(2.80e9, 2.94e9, 20)
    with pytest.raises(svpsf.DoubtfulError, match="none of the 64 pixel fits found a dip"):
        svpsf.fit_odmr(stack, freq)
    with pytest.raises(ValueError, match="below 1 MHz where no NV line lies"):
        svpsf.fit_odmr(stack, freq / 1e6)
    with pytest.raises(ValueError, match="max_iterations 2.5"):
        svpsf.fit_odmr(stack, freq, max_iterations=2.5)
    for bad in (0, -1, 10**12):
        with pytest.raises(ValueError, match="threads"):
            svpsf.set_threads(bad)
    # what only psf= or register=True use, given without them (it was ignored), a margin wider
    # than the view (it ran), shapes that are not two whole sizes (4.7 became 4; 2**31 an
    # OverflowError)
    for kwargs in (dict(iterations=30), dict(margin=4), dict(drift_degree=2), dict(align_to=0)):
        with pytest.raises(ValueError, match="used only with"):
            svpsf.fit_odmr(stack, freq, **kwargs)
    with pytest.raises(svpsf.Error, match="margin"):
        svpsf.fit_odmr(stack, freq, psf=svpsf.PSF("gaussian", fwhm=2), margin=100)
    for shape in ((4.7, 5.2), (4, 5, 6), (2**31, 5)):
        with pytest.raises(ValueError, match="shape"):
            svpsf.Blur(svpsf.PSF("gaussian", fwhm=2), shape)
    with pytest.raises(ValueError, match="balance 'x'"):
        svpsf.correct(stack[0], stack[1], svpsf.PSF("gaussian", fwhm=2), method="rw",
                      balance="x")


def spot_image(psf, shape=(48, 52), centre=(25.3, 22.8), amplitude=4000.0, background=20.0,
               seed=0):
    h, w = shape
    y, x = np.mgrid[0:h, 0:w]
    img = np.array([[psf.profile(xx - centre[0], yy - centre[1]) for xx in range(w)]
                    for yy in range(h)]) * amplitude + background
    return np.random.default_rng(seed).poisson(img).astype(float)


def test_fit_psf_equals_cli(cli, tmp_path):
    truth = svpsf.PSF("moffat", fwhm=6.0, beta=2.5, fwhm_minor=5.0, angle=0.4)
    spot = spot_image(truth)
    cli("fit-psf", write(tmp_path, "spot.npy", spot), "--pixel-um", "0.05", "-o",
        tmp_path / "fit.yaml", "--no-figures", "--quiet")
    fit = svpsf.fit_psf(spot)
    res = json.load(open(tmp_path / "fit.summary.json"))["results"]
    assert fit.fwhm * 0.05 == res["fwhm_um"]
    assert fit.beta == res["beta"]
    assert fit.beta_err == res["beta_err"]
    assert fit.fwhm == pytest.approx(5.5, abs=0.3)  # the truth's mean FWHM, 5.5 px
    assert fit.flags_text == "ok"


def test_map_psf_equals_cli(cli, tmp_path):
    lines = ["pixel_um: 0.05", "field: {width: 200, height: 160}", "spots:"]
    samples = []
    k = 0
    for oy in (10, 60, 110):
        for ox in (10, 75, 140):
            fwhm = 4.5 + 0.01 * ox + 0.008 * oy  # the PSF widens across the field
            p = svpsf.PSF("moffat", fwhm=fwhm, beta=2.5)
            spot = spot_image(p, shape=(40, 40), centre=(19.6, 20.2), seed=k)
            name = "s%02d.npy" % k
            np.save(tmp_path / name, spot)
            lines.append("  - {file: %s, origin: [%d, %d]}" % (name, ox, oy))
            fit = svpsf.fit_psf(spot)
            samples.append((ox + fit.x0, oy + fit.y0, fit))
            k += 1
    (tmp_path / "spots.yaml").write_text("\n".join(lines) + "\n")
    cli("map-psf", tmp_path / "spots.yaml", "-o", tmp_path / "map.yaml", "--degree", "1",
        "--quiet")
    fmap, report = svpsf.map_psf(samples, (160, 200), degree=1)
    assert fmap.kind == "poly" and report["degree"]["fwhm"] == 1
    # the same map through the same file writer (lengths in um in the file: both sides read
    # back through the same conversion)
    fmap.write(tmp_path / "map_py.yaml", 0.05, provenance="python")
    cli_map = svpsf.read_psf(tmp_path / "map.yaml").psf
    py_map = svpsf.read_psf(tmp_path / "map_py.yaml").psf
    for x, y in ((0, 0), (100, 80), (199, 159)):
        assert cli_map.params_at(x, y) == py_map.params_at(x, y)
        assert fmap.params_at(x, y) == pytest.approx(py_map.params_at(x, y), rel=1e-14)
    # and the fitted surface follows the truth (fwhm 4.5 + 0.01 x + 0.008 y at the cut-out
    # corner, the spot ~20 px further): within 0.15 px at the centre
    assert fmap.params_at(95, 80)[0] == pytest.approx(4.5 + 0.01 * 75 + 0.008 * 60, abs=0.15)


def test_fit_odmr_recovers_the_field():
    h, w, nf = 12, 10, 61
    D, gamma, lw = 2.870e9, 28.033e9, 6e6
    freq = np.linspace(D - 20e6, D + 20e6, nf)
    y, x = np.mgrid[0:h, 0:w]
    b = 1e-4 + 2e-5 * x / w + 1e-5 * y / h  # tesla
    pl = 1000.0 + 50 * x
    c = 0.03

    def lor(f0):
        return (lw / 2) ** 2 / ((freq[:, None, None] - f0) ** 2 + (lw / 2) ** 2)

    stack = pl * (1 - c * (lor(D + gamma * b) + lor(D - gamma * b)))
    r = svpsf.fit_odmr(stack, freq, linewidth_hz=lw)
    assert r.n_failed == 0 and np.all(r.converged == 1)
    assert np.max(np.abs(r.field - b)) < 1e-9  # noiseless: to the fit's tolerance
    assert np.max(np.abs(r.contrast - c)) < 1e-6
    assert np.max(np.abs(r.pl - pl) / pl) < 1e-6
    assert np.all(r.quality > 1 - 1e-12)  # R² of a perfect fit
    assert "field_lower" not in r  # per resonance with lines="two" only
    # a decreasing sweep is the same sweep (the program reorders it too)
    rd = svpsf.fit_odmr(stack[::-1], freq[::-1], linewidth_hz=lw)
    assert all(np.array_equal(rd[k], r[k]) for k in r)


# ---- ODMR stacks: the package against `svpsf fit-odmr` ------------------------------------------

def write_tiff_stack(path, frames):
    """A little-endian multi-page float32 TIFF written here (one strip per page, then its
    directory), not by the library: what a camera's software saves."""
    import struct
    frames = np.asarray(frames, dtype="<f4")
    n, h, w = frames.shape
    out = bytearray(b"II*\0" + struct.pack("<I", 0))
    link = 4
    for p in range(n):
        data = len(out)
        out += frames[p].tobytes()
        ifd = len(out)
        struct.pack_into("<I", out, link, ifd)
        tags = [(256, 3, w), (257, 3, h), (258, 3, 32), (259, 3, 1), (262, 3, 1),
                (273, 4, data), (277, 3, 1), (278, 3, h), (279, 4, 4 * w * h), (339, 3, 3)]
        out += struct.pack("<H", len(tags))
        for tag, typ, value in tags:
            out += struct.pack("<HHI", tag, typ, 1)
            out += struct.pack("<HH", value, 0) if typ == 3 else struct.pack("<I", value)
        link = len(out)
        out += struct.pack("<I", 0)
    with open(path, "wb") as f:
        f.write(bytes(out))
    return str(path)


def odmr_stack(h=14, w=18, nf=100, seed=3):
    """A noisy two-dip stack (D shifted by 0.4 MHz, B 1..3 mT, FWHM 5 MHz, contrast 3 %,
    PL ~1000 counts, noise 3 counts), its frequencies (Hz) and the true field (T)."""
    rng = np.random.default_rng(seed)
    D, gamma, lw = 2.870e9 + 0.4e6, 28.033e9, 5e6
    freq = 1e6 * (2750.0 + (2990.0 - 2750.0) * np.arange(nf) / float(nf - 1))
    y, x = np.mgrid[0:h, 0:w]
    b = 1e-3 + 2e-3 * (0.5 + 0.5 * np.sin(0.3 * x) * np.cos(0.2 * y))
    pl = 1000 + 200 * np.cos(0.15 * (x + y))

    def lor(f0):
        return (lw / 2) ** 2 / ((freq[:, None, None] - f0) ** 2 + (lw / 2) ** 2)

    stack = pl * (1 - 0.03 * (lor(D - gamma * b) + lor(D + gamma * b)))
    return stack + 3 * rng.standard_normal(stack.shape), freq, b


ODMR_COMMON = ["--threads", "2", "--format", "npy", "--quiet"]  # fit-odmr makes no FFT plans

ODMR_CASES = [
    (["--lines", "two", "--linewidth", "4e6"], dict(lines="two", linewidth_hz=4e6)),
    (["--zero-field", "2.8704e9", "--linewidth", "4e6"], dict(zero_field_hz=2.8704e9,
                                                            linewidth_hz=4e6)),
    (["--lines", "one", "--line", "lower", "--max-iterations", "30"],
     dict(lines="one", line="lower", max_iterations=30)),
]


@pytest.mark.parametrize("args, kwargs", ODMR_CASES)
def test_fit_odmr_equals_cli_on_a_tiff_stack(cli, tmp_path, args, kwargs):
    stack, freq, b = odmr_stack()
    tif = write_tiff_stack(tmp_path / "stack.tif", stack)
    # the stack as the library reads it: the float32 pages exactly
    read = svpsf.read_stack(tif)
    assert read.shape == stack.shape and read.dtype == np.float64
    assert np.array_equal(read, stack.astype(np.float32))
    ffile = tmp_path / "freq.txt"
    ffile.write_text("".join("%r\n" % f for f in freq))
    cli("fit-odmr", tif, "--frequencies", ffile, "-o", tmp_path / "fit", *args, *ODMR_COMMON)
    r = svpsf.fit_odmr(read, freq, **kwargs)
    written = sorted(p.name[:-4] for p in (tmp_path / "fit").glob("*.npy"))
    assert written == sorted(k for k in r if k != "converged")
    for k in written:  # bit for bit, NaN (not converged) where the program has NaN
        assert np.array_equal(r[k], np.load(tmp_path / "fit" / (k + ".npy")), equal_nan=True), k
    summary = json.loads((tmp_path / "fit" / "summary.json").read_text())
    assert summary["results"]["n_failed"] == r.n_failed
    if kwargs.get("lines") != "one":  # (one line cannot fit two dips: not asserted)
        # σ_B ≈ 4 µT: the field within a stated 10 µT mean, 50 µT max; R² > 0.5 (a dip 10 σ
        # deep in 100 frames of which most are off resonance)
        assert r.n_failed == 0 and np.all(r.quality > 0.5)
        assert np.mean(np.abs(r.field - b)) < 10e-6 and np.max(np.abs(r.field - b)) < 50e-6


def test_fit_odmr_equals_cli_on_a_npy_stack_and_a_range(cli, tmp_path):
    # a 3-D .npy read in place by the program; frequencies as START:STOP:N in MHz, decreasing
    stack, freq, _ = odmr_stack(nf=60, seed=4)
    freq = 1e6 * (2990.0 + (2750.0 - 2990.0) * np.arange(60) / 59.0)
    stack = stack[::-1].copy()  # the same spectra, swept downwards
    f = write(tmp_path, "stack.npy", stack)
    cli("fit-odmr", f, "--frequencies", "2990:2750:60", "--frequency-unit", "MHz", "--unit", "T",
        "--failed", "keep", "-o", tmp_path / "fit", *ODMR_COMMON)
    r = svpsf.fit_odmr(stack, freq, failed="keep")
    for k in ("field", "field_sigma", "pl", "contrast", "linewidth", "quality"):
        assert np.array_equal(r[k], np.load(tmp_path / "fit" / (k + ".npy"))), k


def drifting_stack(h=40, w=48, nf=60, total=(0.4, -0.25), seed=8):
    """A sweep rendered by numpy while the sample drifts linearly from 0 to `total` px: 30
    Gaussian blobs (σ 1.5–4 px) squashed by tanh as the PL, field 1..3 mT, two dips of 3 % and
    5 MHz, noise 1 count; returns the stack (descending frequencies: the program reverses
    them), the frequencies, and the field at the mean position."""
    rng = np.random.default_rng(seed)
    D, gamma, lw = 2.870e9, 28.033e9, 5e6
    freq = 1e6 * (2990.0 + (2750.0 - 2990.0) * np.arange(nf) / float(nf - 1))
    bx, by = rng.uniform(-5, w + 5, 30), rng.uniform(-5, h + 5, 30)
    bs, ba = rng.uniform(1.5, 4, 30), rng.uniform(-0.5, 0.5, 30)
    y, x = np.mgrid[0:h, 0:w].astype(float)

    def scene(t):
        sx, sy = x - t * total[0], y - t * total[1]
        u = sum(a * np.exp(-((sx - cx) ** 2 + (sy - cy) ** 2) / (2 * s * s))
                for cx, cy, s, a in zip(bx, by, bs, ba))
        return 1000 + 600 * np.tanh(2 * u), 1e-3 + 1e-3 * (1 + np.sin(0.3 * sx) * np.cos(0.2 * sy))

    stack = np.empty((nf, h, w))
    for f in range(nf):
        pl, b = scene(f / (nf - 1.0))
        lor = sum((lw / 2) ** 2 / ((freq[f] - (D + s * gamma * b)) ** 2 + (lw / 2) ** 2)
                  for s in (-1, 1))
        stack[f] = pl * (1 - 0.03 * lor) + rng.standard_normal((h, w))
    return stack, freq, scene(0.5)[1]


def test_fit_odmr_register_equals_cli(cli, tmp_path):
    # register=True equals `fit-odmr --register` bit for bit (maps and drift.csv), leaves the
    # caller's stack alone, and brings the field back to the fit's noise where the drift ruins
    # it (measured max |error| 26 uT aligned, stated 60 uT; unaligned 2.8 mT, or those pixels'
    # fits fail)
    stack, freq, b = drifting_stack()
    before = stack.copy()
    f = write(tmp_path, "stack.npy", stack)
    ffile = tmp_path / "freq.txt"
    ffile.write_text("".join("%r\n" % v for v in freq))
    cli("fit-odmr", f, "--frequencies", ffile, "--linewidth", "4e6", "--register", "-o",
        tmp_path / "fit", *COMMON)  # --register makes FFT plans: the same (estimate) plans
    r = svpsf.fit_odmr(stack, freq, linewidth_hz=4e6, register=True)
    assert np.array_equal(stack, before)
    for k in ("field", "field_sigma", "pl", "contrast", "linewidth", "quality"):
        assert np.array_equal(r[k], np.load(tmp_path / "fit" / (k + ".npy")), equal_nan=True), k
    csv = np.loadtxt(tmp_path / "fit" / "drift.csv", delimiter=",", skiprows=1)
    assert np.allclose(csv[:, 2:], r.drift, rtol=0, atol=1e-5)  # %.6g in the file
    # the stack's first frame (the highest frequency, drift 0) is at -total / 2 of the mean
    assert np.allclose(r.drift[0], [-0.2, 0.125], atol=0.01)
    assert np.allclose(r.drift[-1], [0.2, -0.125], atol=0.01)
    assert r.register["min_correlation"] > 0.99
    # unaligned, the drift ruins fits: they fail (the fit's rules see no dip the sweep shows) or
    # land far off (before those rules: 2.8 mT)
    plain = svpsf.fit_odmr(stack, freq, linewidth_hz=4e6)
    assert plain.n_failed > 0 or np.nanmax(np.abs(plain.field - b)) > 1e-3
    assert np.max(np.abs(r.field - b)) < 60e-6
    # align_to the stack's frame 0: its shift is 0
    r0 = svpsf.fit_odmr(stack, freq, linewidth_hz=4e6, register=True, align_to=0)
    assert np.array_equal(r0.drift[0], [0.0, 0.0])
    with pytest.raises(ValueError):
        svpsf.fit_odmr(stack, freq, register=True, drift_degree=7)
    with pytest.raises(ValueError):
        svpsf.fit_odmr(stack, freq, register=True, align_to=60)
    # a stack of noise on a uniform PL has nothing to register on: DoubtfulError (exit 3)
    flat = 1000 + np.random.default_rng(1).standard_normal((20, 16, 16))
    with pytest.raises(svpsf.DoubtfulError, match="correlate too weakly"):
        svpsf.fit_odmr(flat, freq[:20], register=True)


def test_fit_odmr_psf_equals_cli(cli, tmp_path):
    # psf= deconvolves every frame before the fit, as `fit-odmr --psf` (bit for bit, margin
    # auto from the same Gaussian), on a copy; on a sweep blurred here by numpy (a Gaussian of
    # σ 1.7 px by FFT on a canvas 10 px beyond the view) over a field step the fit of the
    # deconvolved stack is closer to the truth (measured rms 2.4 uT against 8.4 uT as blurred)
    rng = np.random.default_rng(5)
    D, gamma, lw, nf, h, w, pad = 2.870e9, 28.033e9, 1e6, 50, 40, 48, 10
    freq = D - 12e6 + 24e6 * np.arange(nf) / (nf - 1.0)
    y, x = np.mgrid[-pad:h + pad, -pad:w + pad].astype(float)
    u = sum(a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / 30.0)
            for cx, cy, a in zip(rng.uniform(-5, w + 5, 10), rng.uniform(-5, h + 5, 10),
                                 rng.uniform(-0.5, 0.5, 10)))
    pl = 1000 + 600 * np.tanh(2 * u)
    b = 150e-6 + 120e-6 * np.tanh((x + 0.3 * y - 0.6 * w) / 1.5)
    ky = np.fft.fftfreq(h + 2 * pad)[:, None]
    kx = np.fft.fftfreq(w + 2 * pad)[None, :]
    otf = np.exp(-2 * (np.pi * 1.7) ** 2 * (kx ** 2 + ky ** 2))
    stack = np.empty((nf, h, w))
    for f in range(nf):
        lor = sum((lw / 2) ** 2 / ((freq[f] - (D + s * gamma * b)) ** 2 + (lw / 2) ** 2)
                  for s in (-1, 1))
        blurred = np.real(np.fft.ifft2(np.fft.fft2(pl * (1 - 0.03 * lor)) * otf))
        stack[f] = blurred[pad:pad + h, pad:pad + w] + rng.standard_normal((h, w))
    truth = b[pad:pad + h, pad:pad + w]
    before = stack.copy()
    f = write(tmp_path, "stack.npy", stack)
    ffile = tmp_path / "freq.txt"
    ffile.write_text("".join("%r\n" % v for v in freq))
    (tmp_path / "g.yaml").write_text("pixel_um: 1\npsf: {model: gaussian, fwhm_um: 4.003}\n")
    cli("fit-odmr", f, "--frequencies", ffile, "--psf", tmp_path / "g.yaml", "-o",
        tmp_path / "fit", *COMMON)
    r = svpsf.fit_odmr(stack, freq, psf=svpsf.PSF("gaussian", fwhm=4.003))
    assert np.array_equal(stack, before)
    for k in ("field", "pl", "contrast", "quality"):
        assert np.array_equal(r[k], np.load(tmp_path / "fit" / (k + ".npy")), equal_nan=True), k
    plain = svpsf.fit_odmr(stack, freq, failed="keep")
    e_plain = np.sqrt(np.mean((plain.field - truth) ** 2))
    e_psf = np.sqrt(np.nanmean((r.field - truth) ** 2))
    assert e_psf < 0.8 * e_plain, (e_psf, e_plain)
    with pytest.raises(ValueError):
        svpsf.fit_odmr(stack, freq, psf=svpsf.PSF("gaussian", fwhm=4.0), margin=-1)


def test_fit_odmr_does_not_copy_the_stack():
    stack, freq, _ = odmr_stack(h=16, w=20, nf=100)
    svpsf.fit_odmr(stack, freq)
    tracemalloc.start()
    r = svpsf.fit_odmr(stack, freq)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    maps = sum(a.nbytes for a in r.values())  # 12 output maps: ~31 kB; the stack: 256 kB
    assert maps <= peak < maps + stack.nbytes // 4, (peak, maps, stack.nbytes)


def test_fit_odmr_errors(cli, tmp_path):
    stack, freq, _ = odmr_stack(h=6, w=5, nf=40)
    # a truncated .npy stack: the library's message, as the program prints it
    f = write(tmp_path, "s.npy", stack)
    trunc = tmp_path / "trunc.npy"
    trunc.write_bytes(open(f, "rb").read()[:2000])
    with pytest.raises(svpsf.Error) as e:
        svpsf.read_stack(trunc)
    p = cli("fit-odmr", trunc, "--frequencies", "1:40:40", "-o", tmp_path / "o", ok=False)
    assert p.returncode == 1
    assert p.stderr.strip() == "svpsf fit-odmr: " + e.value.message
    assert "trunc.npy" in e.value.message and "truncated" in e.value.message
    # one frame: the library refuses the fit
    with pytest.raises(svpsf.Error) as e:
        svpsf.fit_odmr(stack[:1], freq[:1])
    assert e.value.status == 1 and e.value.message == "Lorentzian fit: 1 frequencies, >= 5 needed"
    with pytest.raises(svpsf.Error, match="baseline_frames 30 must be in \\[1, 20\\]"):
        svpsf.fit_odmr(stack, freq, baseline_frames=30)
    # arguments the wrapper checks before the library, as the program does
    with pytest.raises(ValueError, match="frequencies: 39 values for a stack of 40 frames"):
        svpsf.fit_odmr(stack, freq[:-1])
    with pytest.raises(ValueError, match=r"one value per frame \(a 1-D sequence\), got an "
                       r"array of shape \(1, 40\)"):
        svpsf.fit_odmr(stack, freq[None, :])
    bad = freq.copy()
    bad[20] = bad[5]
    with pytest.raises(ValueError, match="not monotonic: frame 21"):
        svpsf.fit_odmr(stack, bad)
    with pytest.raises(ValueError, match="lines 'three'"):
        svpsf.fit_odmr(stack, freq, lines="three")
    with pytest.raises(ValueError, match="needs lines='one'"):
        svpsf.fit_odmr(stack, freq, line="lower")
    with pytest.raises(ValueError, match="shape \\(n_freq, height, width\\)"):
        svpsf.fit_odmr(stack[0], freq)


def test_correct_names_the_maps_as_asked(cli, tmp_path, maps):
    # pl_name / field_names: the library's messages name the maps as the program names files
    pl, field = maps
    bad = pl.copy()
    bad[3, 4] = -1.0
    with pytest.raises(svpsf.Error) as e:
        svpsf.correct(bad, field, svpsf.PSF("gaussian", fwhm=2), pl_name="pl_run7.npy")
    p = cli("correct", "--pl", write(tmp_path, "pl_run7.npy", bad), "--field",
            write(tmp_path, "B.npy", field), "--psf", write(tmp_path, "g.yaml", "pixel_um: 0.1\n"
            "psf: {model: gaussian, fwhm_um: 0.2}\n"), "-o", tmp_path / "o", ok=False)
    assert p.returncode == 1
    assert e.value.message.startswith("pl_run7.npy is negative (-1) at pixel (4, 3)")
    assert "is negative (-1) at pixel (4, 3)" in p.stderr


def test_fit_odmr_missing_frames(cli, tmp_path):
    # a frame of NaN: every pixel fitted on the other frames, to the bit as the stack without
    # that frame, and as the program fits it
    stack, freq, truth = odmr_stack(h=6, w=5, nf=60, seed=5)
    st = stack.copy()
    st[7] = np.nan
    r = svpsf.fit_odmr(st, freq, failed="keep")
    k = svpsf.fit_odmr(np.delete(stack, 7, axis=0), np.delete(freq, 7), failed="keep")
    cli("fit-odmr", write(tmp_path, "st.npy", st), "--frequencies", "2750:2990:60",
        "--frequency-unit", "MHz", "--failed", "keep", "-o", tmp_path / "fit", *ODMR_COMMON)
    for name in ("field", "field_sigma", "pl", "contrast", "linewidth", "quality"):
        assert np.array_equal(r[name], k[name]), name
        assert np.array_equal(r[name], np.load(tmp_path / "fit" / (name + ".npy"))), name
    assert np.abs(r["field"] - truth).max() < 50e-6
    # more than half the frames missing everywhere: missing data, said so (the program: exit 1)
    st[:31] = np.nan
    with pytest.raises(svpsf.Error) as e:
        svpsf.fit_odmr(st, freq)
    assert e.value.status == 1 and not isinstance(e.value, svpsf.DoubtfulError)
    assert e.value.message == (
        "ODMR fit: every one of the 30 pixels holds NaN or Inf in more than 30 of its 60 frames "
        "(missing data: a pixel needs 30 finite samples to be fitted) (the frame at 2.75 GHz is "
        "NaN or Inf at every pixel)")
    p = cli("fit-odmr", write(tmp_path, "half.npy", st), "--frequencies", "2750:2990:60",
            "--frequency-unit", "MHz", "-o", tmp_path / "o2", *ODMR_COMMON, ok=False)
    assert p.returncode == 1
    assert p.stderr.strip() == "svpsf fit-odmr: " + str(tmp_path / "half.npy") + ": " + \
        e.value.message


def test_errors_carry_the_library_message(cli, tmp_path, maps):
    pl, field = maps
    bad = write(tmp_path, "typo.yaml", "pixel_um: 0.1\npsf: {model: moffat, fwhm_umm: 0.6, "
                "beta: 1.1}\n")
    with pytest.raises(svpsf.Error) as e:
        svpsf.correct(pl, field, bad)
    assert e.value.status == 3 and e.value.reason == "malformed file"
    p = cli("correct", "--pl", write(tmp_path, "pl.npy", pl), "--field",
            write(tmp_path, "B.npy", field), "--psf", bad, "-o", tmp_path / "o", ok=False)
    assert p.returncode == 1
    assert p.stderr.strip() == "svpsf correct: " + e.value.message
    assert "typo.yaml:2:" in e.value.message and "fwhm_umm" in e.value.message

    trunc = tmp_path / "trunc.npy"
    trunc.write_bytes((tmp_path / "pl.npy").read_bytes()[:300])
    with pytest.raises(svpsf.Error) as e:
        svpsf.read_image(trunc)
    assert "trunc.npy" in e.value.message and "truncated" in e.value.message

    with pytest.raises(svpsf.Error) as e:
        svpsf.PSF("moffat", fwhm=2, beta=-1)
    assert e.value.status == 1 and "beta" in e.value.message.lower()

    with pytest.raises(ValueError, match="size mismatch"):
        svpsf.correct(pl, field[:, :-1], svpsf.PSF())

    # a Blur for the maps while a margin needs the maps plus the margin: said so
    with pytest.raises(ValueError, match=r"with a margin of 4 the correction needs one for "
                       r"\(%d, %d\)" % (pl.shape[0] + 8, pl.shape[1] + 8)):
        svpsf.correct(pl, field, svpsf.Blur(svpsf.PSF(), pl.shape), margin=4)

    # a NUL in a path: C would stop there and write "cut" instead (as open() refuses it)
    with pytest.raises(ValueError, match="embedded null byte"):
        svpsf.write_image(str(tmp_path / "cut\0.npy"), pl)
    assert not (tmp_path / "cut").exists()
    with pytest.raises(ValueError, match="embedded null byte"):
        svpsf.read_psf(str(tmp_path / "typo.yaml\0x.yaml"))


def test_inputs_are_not_copied(maps):
    pl, field = maps
    imgs = svpsf._Images()
    view = imgs.view(svpsf._input(pl, "pl"))
    assert int(ffi.cast("uintptr_t", view.data)) == pl.ctypes.data  # the array's own memory
    assert svpsf._input(pl, "pl") is pl
    # a transposed (Fortran-order) or float32 array is converted once
    assert svpsf._input(pl.T, "pl").flags.c_contiguous
    psf = svpsf.PSF("gaussian", fwhm=3)
    blur = svpsf.Blur(psf, pl.shape)
    svpsf.correct(pl, field, blur)  # plans made
    n = pl.nbytes
    tracemalloc.start()
    r = svpsf.correct(pl, field, blur)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    # numpy's allocations are traced: the three outputs, and no copy of the two inputs
    assert 3 * n <= peak < 3 * n + n // 2, peak
    assert r.pl.flags.owndata and r.fields.flags.c_contiguous


def test_read_image_is_the_librarys_buffer(tmp_path, maps):
    pl, _ = maps
    np.save(tmp_path / "pl.npy", pl)
    a = svpsf.read_image(tmp_path / "pl.npy")
    assert not a.flags.owndata  # a view of the svp_image the library read (freed with it)
    assert np.array_equal(a, pl)
    svpsf.write_image(tmp_path / "back.npy", a)
    assert np.array_equal(np.load(tmp_path / "back.npy"), pl)
    with pytest.raises(svpsf.Error) as e:
        svpsf.write_image(tmp_path / "back.npy", a)
    assert e.value.reason == "output exists"
    # MATLAB files as `--format mat`: read back by the library and by scipy when it is there
    svpsf.write_image(tmp_path / "back.mat", a, format="mat")
    assert np.array_equal(svpsf.read_image(tmp_path / "back.mat"), pl)
    try:
        import scipy.io
        assert np.array_equal(scipy.io.loadmat(tmp_path / "back.mat")["back"], pl)
    except ImportError:
        print("scipy is not installed (Debian python3-scipy): .mat checked by svpsf only")
    with pytest.raises(ValueError, match="the extension says otherwise"):
        svpsf.write_image(tmp_path / "back.tif", a, format="mat")


def test_read_mat(tmp_path, maps):
    """QDMlab-like files written by scipy: the default variable, a named one, the pixel size
    from `step` (metres, a scalar or [dx dy] of square pixels), the stand-off from `h`."""
    try:
        import scipy.io
    except ImportError:
        print("scipy is not installed (Debian python3-scipy): read_mat not checked")
        return
    pl, field = maps
    scipy.io.savemat(tmp_path / "Bz_uc0.mat", {"Bz": field, "newLED": pl, "h": 5e-6,
                                                "step": 4.7e-6})
    a, info = svpsf.read_mat(tmp_path / "Bz_uc0.mat")
    assert np.array_equal(a, field) and np.array_equal(a, svpsf.read_image(tmp_path /
                                                                           "Bz_uc0.mat"))
    assert info == {"variable": "Bz", "n_variables": 4, "pixel_um": pytest.approx(4.7),
                    "step_elements": 1, "standoff_um": pytest.approx(5.0)}
    a, info = svpsf.read_mat(tmp_path / "Bz_uc0.mat", "newLED")
    assert np.array_equal(a, pl) and info["variable"] == "newLED"
    for step, want in (([4.7e-6, 4.7e-6], 4.7), ([4.7e-6, 5.2e-6], 0.0)):
        scipy.io.savemat(tmp_path / "pair.mat", {"B111ferro": field, "step": np.array([step])})
        a, info = svpsf.read_mat(tmp_path / "pair.mat")
        assert info["variable"] == "B111ferro" and info["step_elements"] == 2
        assert info["pixel_um"] == pytest.approx(want) and info["standoff_um"] == 0
    with pytest.raises(svpsf.Error, match=r"no variable 'nope' \(the file holds: Bz"):
        svpsf.read_mat(tmp_path / "Bz_uc0.mat", "nope")
    # write_mat: two maps and the pixel size, read back here and by scipy; no overwrite
    svpsf.write_mat(tmp_path / "out.mat", {"Bz": field, "pl": pl[:, :5]}, pixel_um=4.7)
    a, info = svpsf.read_mat(tmp_path / "out.mat")
    assert np.array_equal(a, field) and info["pixel_um"] == pytest.approx(4.7)
    assert info["n_variables"] == 3 and info["standoff_um"] == 0
    assert np.array_equal(svpsf.read_mat(tmp_path / "out.mat", "pl")[0], pl[:, :5])
    m = scipy.io.loadmat(tmp_path / "out.mat")
    assert np.array_equal(m["Bz"], field) and m["step"][0, 0] == pytest.approx(4.7e-6)
    with pytest.raises(svpsf.Error) as e:
        svpsf.write_mat(tmp_path / "out.mat", {"Bz": field})
    assert e.value.reason == "output exists"
    svpsf.write_mat(tmp_path / "out.mat", {"Bz": pl}, overwrite=True)
    assert np.array_equal(svpsf.read_mat(tmp_path / "out.mat")[0], pl)
    with pytest.raises(svpsf.Error, match="1x"):
        svpsf.write_mat(tmp_path / "bad.mat", {"1x": pl})
    with pytest.raises(ValueError, match="no maps"):
        svpsf.write_mat(tmp_path / "bad.mat", {})
    assert not (tmp_path / "bad.mat").exists()
    with pytest.raises(ValueError, match="null byte"):
        svpsf.read_mat(tmp_path / "Bz_uc0.mat", "B\0z")


def test_blur_adjoint_and_out(maps):
    pl, field = maps
    for psf in (svpsf.PSF("moffat", fwhm=4.0, beta=1.2, halo=0.05),
                svpsf.PSF("gaussian", fwhm=2.5)):
        for boundary in ("zero", "mirror", "periodic"):
            b = svpsf.Blur(psf, pl.shape, boundary=boundary)
            # the exact adjoint: <H x, y> = <x, Hᵀ y>
            lhs = np.vdot(b.apply(pl), field)
            rhs = np.vdot(pl, b.adjoint(field))
            assert lhs == pytest.approx(rhs, rel=1e-12)
            out = np.empty_like(pl)
            assert b.apply(pl, out=out) is out and np.array_equal(out, b.apply(pl))
    with pytest.raises(ValueError, match="out"):
        b.apply(pl, out=np.empty(pl.shape, dtype=np.float32))
    with pytest.raises(ValueError, match="shape"):
        b.apply(pl[:-1])


def test_library_lookup_errors(tmp_path):
    import subprocess
    import sys

    env = dict(os.environ, SVPSF_LIBRARY=str(tmp_path / "nothere.so"))
    p = subprocess.run([sys.executable, "-c", "import svpsf"], env=env, capture_output=True,
                       text=True)
    assert p.returncode != 0
    assert "ImportError: svpsf: SVPSF_LIBRARY=%s cannot be loaded" % (tmp_path / "nothere.so") \
        in p.stderr
    env = dict(os.environ, SVPSF_HEADER=str(tmp_path / "none.h"))
    p = subprocess.run([sys.executable, "-c", "import svpsf"], env=env, capture_output=True,
                       text=True)
    assert p.returncode != 0
    assert "SVPSF_HEADER=%s: no such file" % (tmp_path / "none.h") in p.stderr


def square_flake_bz(n, lo, hi, px=0.1e-6, h=100e-9):
    """B_z (T) of a thin square flake of 1 mA over [lo, hi]² pixels: the dipole sheet's closed
    form, written here (not by the library)."""
    j, i = np.mgrid[:n, :n]
    x, y = i * px, j * px
    hz = 0
    for a, xx in enumerate((lo * px - x, hi * px - x)):
        for b, yy in enumerate((lo * px - y, hi * px - y)):
            r = np.sqrt(xx * xx + yy * yy + h * h)
            hz = hz + (1 if a == b else -1) * xx * yy * (r * r + h * h) / (
                r * (xx * xx + h * h) * (yy * yy + h * h))
    return 4e-7 * np.pi * 1e-3 / (4 * np.pi) * hz


@pytest.mark.parametrize("method", ["fourier", "support"])
def test_reconstruct_magnetisation_equals_cli(cli, tmp_path, method):
    bz = square_flake_bz(96, 23.75, 72.25)
    np.save(tmp_path / "bz.npy", bz)
    cli("reconstruct", "--quantity", "magnetisation", "--bz", tmp_path / "bz.npy", "--pixel-um",
        "0.1", "--standoff-nm", "100", "--method", method, "-o", tmp_path / "out", "--format",
        "npy", "--quiet", "--fft", "estimate")
    mz, report = svpsf.reconstruct_magnetisation(bz, 0.1, 100, method=method)
    assert np.array_equal(mz, np.load(tmp_path / "out" / "m_z.npy"))
    inside = mz[34:62, 34:62]
    if method == "support":
        assert 0 < report["cg_iterations"] < 200 and report["cg_residual"] <= 1e-9
        assert np.abs(inside - 1e-3).max() < 0.01e-3  # within 1 % of 1 mA
    else:
        assert report == {"cg_iterations": 0, "cg_residual": 0.0}


def test_reconstruct_magnetisation_refusals():
    bz = square_flake_bz(48, 11.75, 36.25)
    with pytest.raises(svpsf.DoubtfulError, match="conjugate gradients stopped after 1 steps"):
        svpsf.reconstruct_magnetisation(bz, 0.1, 100, method="support", max_iterations=1)
    with pytest.raises(ValueError, match="fourier or support"):
        svpsf.reconstruct_magnetisation(bz, 0.1, 100, method="wiener")
    bz[3, 4] = np.nan
    with pytest.raises(svpsf.Error, match="NaN or Inf"):
        svpsf.reconstruct_magnetisation(bz, 0.1, 100, method="support")
