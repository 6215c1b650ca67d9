"""Batch correction of many datasets, serially or on a Dask cluster (docs/python.md §Batch).

    python3 -m svpsf.batch DATASET... -o OUT [--psf PSF] [correct options]
                           [--dask local:N | --dask SCHEDULER] [--threads-per-task T]

A DATASET is a folder holding the measured PL map `pl.EXT` and one or more field maps
`field.EXT` / `field_<name>.EXT` (EXT any image format svpsf reads), and optionally its own PSF
file `psf.yaml` (else --psf). A folder without `pl.*` stands for the dataset folders inside it;
a `.txt` file lists dataset folders, one per line (relative to the list's folder, `#`
comments). Each dataset is corrected with svpsf.correct (T⁻¹, eq. 4 of docs/model.md) — the
same numbers as `svpsf correct` with the same options, and with its defaults where none is given
(the margin auto and, from 1024², single precision for r and rl-signed with one PSF, where the
library's default is neither) — into OUT/<name>/ (pl.npy, field*.npy,
validity.npy, summary.json), written into a temporary folder and renamed into place, so a
dataset's folder is complete or absent. OUT/summary.csv and OUT/summary.json (one row per
dataset: status, message, counts, seconds, worker) are written atomically at the end; a dataset
that fails (a bad file, a doubtful result) is a row with status `failed` and the library's
message, and the others go on. Exit status 0 when every dataset succeeded, 1 otherwise (bad
usage, existing outputs without --force, or any failed dataset).

With --dask, one task per dataset runs on the Dask cluster (dask.distributed): `local:N` starts a
LocalCluster of N single-threaded worker processes on this machine; anything else is a scheduler
address (tcp://host:8786) of a running cluster whose workers see the same file system and can
import svpsf. Each task runs the library with --threads-per-task threads (default 1: one core
per worker; OMP_NUM_THREADS of the workers should match). FFT plans are made with FFTW_ESTIMATE
by default (--fft), so a dataset gives the same bits whichever worker runs it.
"""
import argparse
import csv
import io
import json
import os
import platform
import shutil
import socket
import sys
import tempfile
import time

import numpy as np

IMAGE_EXTENSIONS = (".tif", ".tiff", ".npy", ".txt", ".csv", ".dat", ".png", ".mat")
SUMMARY_COLUMNS = ("dataset", "status", "message", "n_fields", "width", "height", "n_missing",
                   "n_flagged", "n_invalid", "doubts", "seconds", "worker", "path")


def _image_files(folder, stem_prefix):
    out = []
    for name in sorted(os.listdir(folder)):
        stem, ext = os.path.splitext(name)
        if ext.lower() in IMAGE_EXTENSIONS and (stem == stem_prefix or
                                                stem.startswith(stem_prefix + "_")):
            out.append(os.path.join(folder, name))
    return out


def _check_mat_pixels(files, psf_path):
    """As `svpsf correct`: a MATLAB input whose `step` (its pixel size) differs from the PSF
    file's pixel size by more than 1 % is refused, naming both (the PSF would act at the wrong
    scale); nothing to compare for a kernel image."""
    import svpsf  # as correct_dataset: imported where it runs (a Dask worker)
    psf_pixel = svpsf.read_psf(psf_path).pixel_um
    if not psf_pixel or not psf_pixel > 0:
        return
    for f in files:
        if os.path.splitext(f)[1].lower() != ".mat":
            continue
        step = svpsf.read_mat(f)[1]["pixel_um"]
        if step > 0 and abs(step / psf_pixel - 1) > 0.01:
            raise ValueError("%s holds `step` = %g um (its pixel size), but the PSF file %s is "
                             "for pixels of %g um: the PSF would be applied at the wrong scale "
                             "(give a PSF file for the map's pixels)"
                             % (f, step, psf_path, psf_pixel))


def _is_dataset(folder):
    return os.path.isdir(folder) and bool(_image_files(folder, "pl"))


def find_datasets(paths):
    """Dataset folders from folders, parent folders and list files, in the order given
    (a parent's datasets sorted by name). Raises ValueError naming a path that is none."""
    found = []
    for p in paths:
        p = os.fspath(p)
        if os.path.isfile(p) and p.lower().endswith(".txt"):
            base = os.path.dirname(os.path.abspath(p))
            with open(p, encoding="utf-8") as f:
                for n, line in enumerate(f, 1):
                    line = line.split("#", 1)[0].strip()
                    if not line:
                        continue
                    d = line if os.path.isabs(line) else os.path.join(base, line)
                    if not _is_dataset(d):
                        raise ValueError("%s:%d: %s is not a dataset folder (no pl.* image in it)"
                                         % (p, n, line))
                    found.append(d)
        elif _is_dataset(p):
            found.append(p)
        elif os.path.isdir(p):
            subs = [os.path.join(p, d) for d in sorted(os.listdir(p))]
            subs = [d for d in subs if _is_dataset(d)]
            if not subs:
                raise ValueError("%s: neither a dataset folder (pl.* and field*.*) nor a folder "
                                 "of them" % p)
            found.extend(subs)
        else:
            raise ValueError("%s: no such dataset folder or list file" % p)
    names = {}
    for d in found:
        name = os.path.basename(os.path.normpath(d))
        if name in names:
            raise ValueError("datasets %s and %s have the same name '%s': their outputs would "
                             "collide" % (names[name], d, name))
        names[name] = d
    return found


def _atomic_write_text(path, text):
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", dir=folder)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def correct_dataset(folder, out_root, psf=None, options=None, threads=1, fft="estimate",
                    overwrite=False):
    """Corrects one dataset folder into out_root/<name>/. Never raises for the dataset's own
    faults: returns a summary row (status 'ok' or 'failed' with the message). The unit of
    work of a batch: a Dask task runs exactly this."""
    import svpsf

    t0 = time.perf_counter()
    name = os.path.basename(os.path.normpath(folder))
    row = dict.fromkeys(SUMMARY_COLUMNS, "")
    row.update(dataset=name, worker="%s:%d" % (socket.gethostname(), os.getpid()),
               path=os.path.join(out_root, name))
    tmp = None
    try:
        svpsf.set_threads(threads)
        svpsf.set_fft_effort(fft)
        pl_files = _image_files(folder, "pl")
        if len(pl_files) != 1:
            raise ValueError("%s: %d PL maps (pl.*): one is needed" % (folder, len(pl_files)))
        field_files = _image_files(folder, "field")
        if not field_files:
            raise ValueError("%s: no field map (field.* or field_<name>.*)" % folder)
        seen = {}
        for f in field_files:  # field_x.npy and field_x.txt would write one field_x.npy
            stem = os.path.splitext(os.path.basename(f))[0]
            if stem in seen:
                raise ValueError("%s: %s and %s are two field maps of one name (their corrected "
                                 "maps would be one file, %s.npy): keep one"
                                 % (folder, os.path.basename(seen[stem]), os.path.basename(f),
                                    stem))
            seen[stem] = f
        own_psf = [os.path.join(folder, n) for n in ("psf.yaml", "psf.yml")
                   if os.path.isfile(os.path.join(folder, n))]
        psf_path = own_psf[0] if own_psf else psf
        if psf_path is None:
            raise ValueError("%s: no psf.yaml in the dataset and no --psf" % folder)
        pl = svpsf.read_image(pl_files[0])
        fields = [svpsf.read_image(f) for f in field_files]
        for f, a in zip(field_files, fields):
            if a.shape != pl.shape:
                raise ValueError("size mismatch: field %s is %d x %d (width x height) but PL %s "
                                 "is %d x %d" % (f, a.shape[1], a.shape[0], pl_files[0],
                                                 pl.shape[1], pl.shape[0]))
        _check_mat_pixels([pl_files[0]] + field_files, psf_path)
        opts = _program_defaults(dict(options or {}), psf_path, pl.shape)
        res = svpsf.correct(pl, fields, psf_path, field_names=field_files, pl_name=pl_files[0],
                            **opts)
        final = os.path.join(out_root, name)
        if os.path.exists(final) and not overwrite:
            raise FileExistsError("%s exists (use --force to replace it)" % final)
        tmp = tempfile.mkdtemp(prefix="." + name + ".", dir=out_root)
        svpsf.write_image(os.path.join(tmp, "pl.npy"), res.pl)
        stems = [os.path.splitext(os.path.basename(f))[0] for f in field_files]
        out_names = ["field.npy"] if len(fields) == 1 else [s + ".npy" for s in stems]
        for n, f in zip(out_names, res.fields):
            svpsf.write_image(os.path.join(tmp, n), f)
        svpsf.write_image(os.path.join(tmp, "validity.npy"), res.validity)
        valid = res.validity
        # a result kept in doubt (keep_doubtful) says so in its row, not only in its folder
        doubts = ",".join(res.summary.get("doubt_names", []))
        row.update(status="ok", n_fields=len(fields), width=pl.shape[1], height=pl.shape[0],
                   n_missing=res.n_missing, n_flagged=int(np.count_nonzero(valid < 1)),
                   n_invalid=int(np.count_nonzero(valid <= 0)), doubts=doubts,
                   message="kept in doubt: " + doubts if doubts else "")
        summary = {"dataset": name, "inputs": {"pl": pl_files[0], "fields": field_files,
                                               "psf": psf_path},
                   "options": opts, "threads": threads, "fft": fft,
                   "results": {k: row[k] for k in ("n_missing", "n_flagged", "n_invalid")},
                   "correct_summary": res.summary, "reports": res.reports,
                   "versions": {"svpsf": svpsf.version(), "fftw": svpsf.fftw_version(),
                                "python": platform.python_version()}}
        _atomic_write_text(os.path.join(tmp, "summary.json"),
                           json.dumps(summary, indent=1, default=str) + "\n")
        if os.path.exists(final):  # overwrite: the old folder goes only once the new is whole
            old = final + ".old-%d" % os.getpid()
            os.replace(final, old)
            os.replace(tmp, final)
            shutil.rmtree(old)
        else:
            os.replace(tmp, final)
        tmp = None
    except Exception as e:  # the dataset fails alone, with its message
        msg = getattr(e, "message", None) or str(e)
        row.update(status="failed", message="%s: %s" % (type(e).__name__, msg), path="")
        final = os.path.join(out_root, name)
        if overwrite and os.path.isdir(final) and not isinstance(e, FileExistsError):
            # --force replaces this batch's outputs: an earlier run's results must not stand
            # beside a row that says this one failed
            shutil.rmtree(final, ignore_errors=True)
            row["message"] += " (the earlier outputs in %s were removed: --force)" % final
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    row["seconds"] = round(time.perf_counter() - t0, 4)
    return row


def _make_client(dask):
    from dask.distributed import Client, LocalCluster

    if dask.startswith("local:"):
        n = int(dask.split(":", 1)[1])
        if n < 1:
            raise ValueError("--dask local:N: N >= 1")
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                               dashboard_address=":0",
                               env={"OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "passive"})
        return Client(cluster), cluster
    return Client(dask), None


def run(datasets, out, psf=None, options=None, dask=None, client=None, threads=1,
        fft="estimate", overwrite=False):
    """Corrects every dataset (see find_datasets) into out/. dask: None (serial, in this
    process), 'local:N' or a scheduler address; or pass a dask.distributed Client. Returns the
    summary rows in the order of the datasets; writes out/summary.csv and out/summary.json."""
    folders = find_datasets(datasets)
    if not folders:  # an empty or comment-only list: nothing was asked, nothing done
        raise ValueError("no dataset in %s" % ", ".join(map(str, datasets)))
    if psf is not None and not os.path.exists(psf):  # once, not per dataset
        raise ValueError("--psf %s: no such file" % psf)
    if isinstance(threads, bool) or not isinstance(threads, int) or not 1 <= threads <= 4096:
        raise ValueError("--threads-per-task %r: 1 .. 4096" % (threads,))
    os.makedirs(out, exist_ok=True)
    if not overwrite:
        existing = [os.path.join(out, os.path.basename(os.path.normpath(d))) for d in folders]
        existing += [os.path.join(out, n) for n in ("summary.csv", "summary.json")]
        existing = [p for p in existing if os.path.exists(p)]
        if existing:
            raise FileExistsError("%s exists (use --force to replace the outputs); nothing was "
                                  "written" % existing[0])
    t0 = time.perf_counter()
    args = dict(psf=os.path.abspath(psf) if psf else None, options=options or {},
                threads=threads, fft=fft, overwrite=overwrite)
    out_abs = os.path.abspath(out)
    own = None
    mode = "serial"
    if client is None and dask:
        client, own = _make_client(dask)
        mode = "dask " + dask
    elif client is not None:
        mode = "dask client"
    rows = [None] * len(folders)
    interrupted = False
    try:
        if client is None:  # in this process: its library thread count is restored after
            import svpsf

            before = svpsf.get_threads()
            try:
                for i, d in enumerate(folders):
                    rows[i] = correct_dataset(os.path.abspath(d), out_abs, **args)
            finally:
                svpsf.set_threads(before)
        else:
            from dask.distributed import as_completed

            futures = {}
            for i, d in enumerate(folders):
                fut = client.submit(correct_dataset, os.path.abspath(d), out_abs, pure=False,
                                    key="svpsf-correct-%d-%s" % (i, os.path.basename(d)),
                                    **args)
                futures[fut] = i
            for fut in as_completed(list(futures)):
                i = futures[fut]
                try:
                    rows[i] = fut.result()
                except Exception as e:  # the worker died (a crash, out of memory): not lost
                    row = dict.fromkeys(SUMMARY_COLUMNS, "")
                    row.update(dataset=os.path.basename(os.path.normpath(folders[i])),
                               status="failed", message="%s: %s" % (type(e).__name__, e))
                    rows[i] = row
    except KeyboardInterrupt:  # Ctrl-C: the datasets done so far keep their rows
        interrupted = True
    finally:
        if own is not None:
            client.close()
            own.close()
    for i, r in enumerate(rows):
        if r is None:
            rows[i] = dict.fromkeys(SUMMARY_COLUMNS, "")
            rows[i].update(dataset=os.path.basename(os.path.normpath(folders[i])),
                           status="interrupted", message="not run: the batch was interrupted")
    elapsed = time.perf_counter() - t0
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=SUMMARY_COLUMNS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow(r)
    _atomic_write_text(os.path.join(out, "summary.csv"), buf.getvalue())
    summary = {"mode": mode, "threads_per_task": threads, "fft": fft, "psf": args["psf"],
               "options": options or {}, "seconds": round(elapsed, 4),
               "n_datasets": len(rows), "n_ok": sum(r["status"] == "ok" for r in rows),
               "n_failed": sum(r["status"] != "ok" for r in rows), "datasets": rows}
    _atomic_write_text(os.path.join(out, "summary.json"),
                       json.dumps(summary, indent=1, default=str) + "\n")
    if interrupted:
        raise KeyboardInterrupt("%d of %d datasets done; summary written" % (
            sum(r["status"] != "interrupted" for r in rows), len(rows)))
    return rows


def _number(text, option, kind):
    """An option's number, or ValueError naming the option (not int()'s own message)."""
    try:
        return kind(text)
    except ValueError:
        raise ValueError("%s %s: %s" % (option, text, "an integer or auto" if kind is int
                                        else "a number or auto")) from None


# `svpsf correct` takes single precision for r and rl-signed with one PSF from this many pixels
SINGLE_FROM_PIXELS = 1024 * 1024


def _program_defaults(opts, psf_path, shape):
    """What `svpsf correct` takes where an option is not given and svpsf.correct's (the
    library's) default differs (docs/cli.md): for r and rl-signed with one PSF (not a map) the
    margin 'auto' (0 for a boundary other than zero) and, from 1024² pixels, single precision;
    else margin 0 and double precision. So a batch gives `svpsf correct`'s numbers."""
    import svpsf  # in the worker, as correct_dataset

    rl = opts.get("method") in (None, "r", "rl-signed")
    one = not isinstance(svpsf.read_psf(psf_path).psf, svpsf.PSFMap)
    if "margin" not in opts:
        opts["margin"] = "auto" if rl and one else 0
    if "precision" not in opts:
        big = shape[0] * shape[1] >= SINGLE_FROM_PIXELS
        opts["precision"] = "single" if rl and one and big else "double"
    return opts


def _options_from_args(a):
    opts = {}
    if a.method:
        opts["method"] = a.method
    if a.iterations is not None:
        opts["iterations"] = a.iterations if a.iterations == "auto" else _number(
            a.iterations, "--iterations", int)
    if a.balance is not None:
        opts["balance"] = a.balance if a.balance == "auto" else _number(
            a.balance, "--balance", float)
    if a.boundary:
        opts["boundary"] = a.boundary
    if a.pl_floor is not None:
        opts["pl_floor"] = a.pl_floor
    if a.keep_doubtful:
        opts["keep_doubtful"] = True
    if a.precision:
        opts["precision"] = a.precision
    if a.margin is not None:
        opts["margin"] = a.margin if a.margin == "auto" else _number(a.margin, "--margin", int)
    return opts


def main(argv=None):
    p = argparse.ArgumentParser(
        prog="python3 -m svpsf.batch",
        description="Correct many datasets (T^-1 of docs/model.md, as `svpsf correct`), "
        "serially or one Dask task per dataset. A dataset is a folder with pl.EXT and "
        "field.EXT / field_<name>.EXT (and optionally psf.yaml); see docs/python.md.")
    p.add_argument("datasets", nargs="+", help="dataset folders, folders of them, or .txt lists")
    p.add_argument("-o", "--output", required=True, help="output folder")
    p.add_argument("--psf", help="PSF file, PSF-map file or kernel image for datasets without "
                   "their own psf.yaml")
    p.add_argument("--method", choices=("r", "rw", "w", "rl-signed"),
                   help="as svpsf correct --method (default: the library's, r)")
    p.add_argument("--iterations", help="Richardson-Lucy iterations or auto (default 75)")
    p.add_argument("--balance", help="Wiener-Hunt lambda or auto (default 0.001)")
    p.add_argument("--pl-floor", type=float)
    p.add_argument("--precision", choices=("double", "single"),
                   help="default as svpsf correct: single for r and rl-signed with one PSF "
                   "from 1024x1024 pixels, else double")
    p.add_argument("--margin", help="pixels per side or auto (default as svpsf correct: auto "
                   "for r and rl-signed with one PSF, else 0)")
    p.add_argument("--boundary", choices=("zero", "mirror", "periodic"))
    p.add_argument("--keep-doubtful", action="store_true")
    p.add_argument("--dask", metavar="local:N|ADDRESS",
                   help="run one task per dataset on Dask: local:N = a LocalCluster of N "
                   "single-threaded workers; else a scheduler address")
    p.add_argument("--threads-per-task", type=int, default=1,
                   help="library threads per dataset (default 1)")
    p.add_argument("--fft", choices=("estimate", "measure"), default="estimate",
                   help="FFT planning (default estimate: the same result on every worker)")
    p.add_argument("--force", action="store_true", help="replace existing outputs")
    a = p.parse_args(argv)
    try:
        rows = run(a.datasets, a.output, psf=a.psf, options=_options_from_args(a), dask=a.dask,
                   threads=a.threads_per_task, fft=a.fft, overwrite=a.force)
    except (ValueError, FileExistsError, OSError) as e:
        print("svpsf batch: %s" % e, file=sys.stderr)
        return 1
    except KeyboardInterrupt as e:  # no traceback: what was done is in the summary
        print("svpsf batch: interrupted%s" % (": %s" % e if str(e) else ""), file=sys.stderr)
        return 130
    failed = [r for r in rows if r["status"] != "ok"]
    for r in rows:
        print("%-24s %-6s %8ss  %s" % (r["dataset"], r["status"], r["seconds"], r["message"]))
    print("%d datasets: %d ok, %d failed; summary: %s" % (
        len(rows), len(rows) - len(failed), len(failed), os.path.join(a.output, "summary.csv")))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
