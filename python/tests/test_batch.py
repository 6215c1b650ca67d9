"""svpsf.batch: serial and on a Dask LocalCluster of 2 workers, the same outputs; a dataset with
a bad file fails alone, with the library's message in the summary; outputs are never
overwritten without force."""
import csv
import json
import os

import numpy as np
import pytest

import svpsf
from svpsf import batch
from conftest import smooth_maps

PSF = "pixel_um: 0.1\npsf: {model: moffat, fwhm_um: 0.5, beta: 2.0}\nboundary: mirror\n"
OPTIONS = {"method": "rw", "iterations": 20}


def make_datasets(root, n=5):
    """n datasets of measured maps (T of smooth truths); dataset 'd2' has a truncated field."""
    root.mkdir()
    psf = svpsf.PSF("moffat", fwhm=5.0, beta=2.0)
    for i in range(n):
        d = root / ("d%d" % i)
        d.mkdir()
        pl, field = smooth_maps(48, 40, seed=i)
        a = svpsf.forward(pl, [field, 0.3 * field + 1e-5], psf, boundary="mirror")
        np.save(d / "pl.npy", a.pl)
        np.save(d / "field_x.npy", a.fields[0])
        np.save(d / "field_z.npy", a.fields[1])
    bad = root / "d2" / "field_z.npy"
    bad.write_bytes(bad.read_bytes()[:200])
    (root / "psf.yaml").write_text(PSF)
    return root


def read_summary(out):
    with open(out / "summary.csv") as f:
        return {r["dataset"]: r for r in csv.DictReader(f)}


def check_outputs(out, root):
    rows = read_summary(out)
    assert [rows[k]["status"] for k in sorted(rows)] == ["ok", "ok", "failed", "ok", "ok"]
    msg = rows["d2"]["message"]
    assert "field_z.npy" in msg and "truncated" in msg, msg
    assert not (out / "d2").exists()  # a failed dataset leaves no folder
    assert not [p for p in os.listdir(out) if p.startswith(".")]  # no temporary left
    summary = json.load(open(out / "summary.json"))
    assert summary["n_ok"] == 4 and summary["n_failed"] == 1
    # each dataset's outputs are svpsf.correct's on its files
    pl = svpsf.read_image(root / "d0" / "pl.npy")
    fields = [svpsf.read_image(root / "d0" / n) for n in ("field_x.npy", "field_z.npy")]
    ref = svpsf.correct(pl, fields, str(root / "psf.yaml"), **OPTIONS)
    assert np.array_equal(np.load(out / "d0" / "field_z.npy"), ref.fields[1])
    return rows


def test_serial_and_dask_give_the_same_outputs(tmp_path):
    root = make_datasets(tmp_path / "data")
    serial = tmp_path / "serial"
    rows = batch.run([root], serial, psf=root / "psf.yaml", options=OPTIONS)
    assert [r["dataset"] for r in rows] == ["d0", "d1", "d2", "d3", "d4"]
    srows = check_outputs(serial, root)

    pytest.importorskip("dask.distributed", reason="python3-distributed is not installed")
    dist = tmp_path / "dask"
    rows = batch.run([root], dist, psf=root / "psf.yaml", options=OPTIONS, dask="local:2")
    drows = check_outputs(dist, root)
    assert drows["d2"]["message"] == srows["d2"]["message"]
    # the tasks ran on two worker processes, none in this one
    workers = {r["worker"] for r in rows if r["status"] == "ok"}
    assert len(workers) == 2 and all(not w.endswith(":%d" % os.getpid()) for w in workers)
    for d in ("d0", "d1", "d3", "d4"):
        for n in ("pl.npy", "field_x.npy", "field_z.npy", "validity.npy"):
            assert np.array_equal(np.load(serial / d / n), np.load(dist / d / n)), (d, n)


def test_command_line_and_no_overwrite(tmp_path, capsys):
    root = make_datasets(tmp_path / "data")
    lst = tmp_path / "list.txt"
    lst.write_text("# two of them\ndata/d0\ndata/d1\n")
    out = tmp_path / "out"
    args = [str(lst), "-o", str(out), "--psf", str(root / "psf.yaml"), "--iterations", "20"]
    assert batch.main(args) == 0
    assert sorted(read_summary(out)) == ["d0", "d1"]
    before = (out / "d0" / "pl.npy").read_bytes()
    assert batch.main(args) == 1  # outputs exist: refused, nothing written
    assert "exists" in capsys.readouterr().err
    assert (out / "d0" / "pl.npy").read_bytes() == before
    assert batch.main(args + ["--force"]) == 0
    assert batch.main([str(root), "-o", str(tmp_path / "o2"), "--psf",
                       str(root / "psf.yaml"), "--iterations", "20"]) == 1  # d2 fails
    assert batch.main([str(tmp_path / "nothere"), "-o", str(tmp_path / "o3")]) == 1
    assert "no such dataset" in capsys.readouterr().err
    # refused up front, once: an empty list (exit 0 with 0 datasets before), a PSF file that
    # does not exist (each dataset failed on it), a count that is not one (int()'s message)
    empty = tmp_path / "empty.txt"
    empty.write_text("# nothing yet\n")
    assert batch.main([str(empty), "-o", str(tmp_path / "o4")]) == 1
    assert "no dataset in" in capsys.readouterr().err
    assert batch.main([str(root / "d0"), "-o", str(tmp_path / "o5"), "--psf", "nope.yaml"]) == 1
    assert "--psf nope.yaml: no such file" in capsys.readouterr().err
    assert batch.main(args[:-1] + ["2.5", "-o", str(tmp_path / "o6")]) == 1
    assert "--iterations 2.5: an integer or auto" in capsys.readouterr().err
    assert batch.main(args[:-2] + ["--threads-per-task", "-3", "-o", str(tmp_path / "o7")]) == 1
    assert "--threads-per-task -3: 1 .. 4096" in capsys.readouterr().err
    assert not (tmp_path / "o4").exists() and not (tmp_path / "o5").exists()
    # --force over a dataset that now fails: its earlier outputs go, and its row says so (they
    # stood beside a 'failed' row before); a failed row names no output folder
    np.save(root / "d1" / "field_x.npy", np.full((40, 48), np.nan))
    assert batch.main(args + ["--force"]) == 1
    rows = read_summary(out)
    assert rows["d1"]["status"] == "failed" and "earlier outputs" in rows["d1"]["message"]
    assert rows["d1"]["path"] == "" and not (out / "d1").exists()
    assert rows["d0"]["status"] == "ok" and rows["d0"]["doubts"] == ""


def test_kept_doubt_is_in_the_row(tmp_path):
    # a result kept in doubt is an 'ok' row that names its doubts (before: only its folder's
    # summary.json did)
    root = make_datasets(tmp_path / "data")
    rows = batch.run([root / "d0"], tmp_path / "out", psf=root / "psf.yaml",
                     options={"iterations": "auto", "keep_doubtful": True})
    assert rows[0]["status"] == "ok" and rows[0]["doubts"], rows[0]
    assert rows[0]["message"].startswith("kept in doubt: ")
    assert read_summary(tmp_path / "out")["d0"]["doubts"] == rows[0]["doubts"]


def test_interrupt_keeps_what_was_done(tmp_path, monkeypatch, capsys):
    # Ctrl-C: the datasets done keep their rows, the others are 'interrupted', the summary is
    # written and no traceback is printed (exit 130; before: a traceback and no summary)
    root = make_datasets(tmp_path / "data")
    real, calls = batch.correct_dataset, []

    def interrupted_third(folder, *args, **kwargs):
        calls.append(folder)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(folder, *args, **kwargs)

    monkeypatch.setattr(batch, "correct_dataset", interrupted_third)
    out = tmp_path / "out"
    assert batch.main([str(root), "-o", str(out), "--psf", str(root / "psf.yaml"),
                       "--iterations", "5"]) == 130
    rows = read_summary(out)
    assert [rows[k]["status"] for k in sorted(rows)] == ["ok", "ok"] + ["interrupted"] * 3
    err = capsys.readouterr().err
    assert "interrupted: 2 of 5 datasets done; summary written" in err and "Traceback" not in err
    assert (out / "d1" / "field_x.npy").exists() and not (out / "d2").exists()


def test_two_field_files_of_one_name_fail_the_dataset(tmp_path):
    # field_x.npy and field_x.txt would both write field_x.npy: the second overwrote the first
    # and the row said ok with 3 fields; now the dataset fails, naming both files
    root = make_datasets(tmp_path / "data", n=3)
    np.savetxt(root / "d0" / "field_x.txt", np.load(root / "d0" / "field_x.npy"))
    rows = batch.run([root / "d0"], tmp_path / "out", psf=root / "psf.yaml", options=OPTIONS)
    assert rows[0]["status"] == "failed", rows[0]
    assert "field_x.npy and field_x.txt are two field maps of one name" in rows[0]["message"]
    assert not (tmp_path / "out" / "d0").exists()


def test_library_errors_name_the_dataset_files(tmp_path):
    # a PL without light: the row names the PL file, as `svpsf correct` does (it said
    # "pl_apparent holds no light", which names no file of the batch)
    root = make_datasets(tmp_path / "data", n=3)
    np.save(root / "d0" / "pl.npy", np.zeros_like(np.load(root / "d0" / "pl.npy")))
    rows = batch.run([root / "d0"], tmp_path / "out", psf=root / "psf.yaml", options=OPTIONS)
    assert rows[0]["status"] == "failed", rows[0]
    assert str(root / "d0" / "pl.npy") + " holds no light" in rows[0]["message"], rows[0]


def test_mat_datasets(tmp_path):
    # MATLAB files are datasets too: the same numbers as the .npy files, and a file whose
    # `step` says other pixels than the PSF file fails the dataset, naming both
    root = make_datasets(tmp_path / "data", n=3)
    for k, px in (("m0", 0.1), ("m1", 0.3)):
        d = root / k
        d.mkdir()
        svpsf.write_mat(d / "pl.mat", {"pl": np.load(root / "d0" / "pl.npy")}, pixel_um=px)
        svpsf.write_mat(d / "field_x.mat", {"Bz": np.load(root / "d0" / "field_x.npy")},
                        pixel_um=px)
    out = tmp_path / "out"
    rows = {r["dataset"]: r for r in batch.run([root / "d0", root / "m0", root / "m1"], out,
                                               psf=root / "psf.yaml", options=OPTIONS)}
    assert rows["m0"]["status"] == "ok", rows["m0"]
    ref = svpsf.correct(np.load(root / "d0" / "pl.npy"), [np.load(root / "d0" / "field_x.npy")],
                        str(root / "psf.yaml"), **OPTIONS)
    assert np.array_equal(np.load(out / "m0" / "field.npy"), ref.fields[0])
    assert rows["m1"]["status"] == "failed"
    assert "holds `step` = 0.3 um (its pixel size), but the PSF file" in rows["m1"]["message"]
    assert "is for pixels of 0.1 um" in rows["m1"]["message"]
    assert not (out / "m1").exists()


def test_defaults_are_the_programs(cli, tmp_path):
    # without options a dataset gets `svpsf correct`'s numbers: R with the margin auto (the
    # library's default is none, which the batch took before), bit for bit with the same plans
    # and thread count; --margin 0 gives the library's
    root = tmp_path / "data"
    d = root / "d0"
    d.mkdir(parents=True)
    pl, field = smooth_maps(48, 40, seed=3)
    psf = svpsf.PSF("moffat", fwhm=5.0, beta=1.5)
    a = svpsf.forward(pl, field, psf)
    np.save(d / "pl.npy", a.pl)
    np.save(d / "field.npy", a.fields)
    (root / "psf.yaml").write_text("pixel_um: 0.1\npsf: {model: moffat, fwhm_um: 0.5, "
                                   "beta: 1.5}\n")
    out = tmp_path / "out"
    assert batch.main([str(d), "-o", str(out), "--psf", str(root / "psf.yaml")]) == 0
    cli("correct", "--pl", d / "pl.npy", "--field", d / "field.npy", "--psf",
        root / "psf.yaml", "-o", tmp_path / "prog", "--fft", "estimate", "--threads", "1",
        "--format", "npy", "--quiet")
    prog = json.load(open(tmp_path / "prog" / "summary.json"))["settings"]
    assert prog["margin"] > 0
    assert np.array_equal(np.load(out / "d0" / "field.npy"),
                          np.load(tmp_path / "prog" / "field.npy"))
    assert json.load(open(out / "d0" / "summary.json"))["options"]["margin"] == "auto"
    assert batch.main([str(d), "-o", str(tmp_path / "out0"), "--psf", str(root / "psf.yaml"),
                       "--margin", "0"]) == 0
    ref = svpsf.correct(a.pl, a.fields, str(root / "psf.yaml"))  # the library's defaults
    assert np.array_equal(np.load(tmp_path / "out0" / "d0" / "field.npy"), ref.fields)
    assert not np.array_equal(ref.fields, np.load(out / "d0" / "field.npy"))
