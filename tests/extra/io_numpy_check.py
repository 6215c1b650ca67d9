#!/usr/bin/python3
"""Cross-check of svpsf's image readers/writers against numpy, tifffile and Pillow.

numpy writes .npy files of every supported dtype (both byte orders, C and Fortran order, shape
(h, w, 1)) and numpy.savetxt text; tifffile writes float32 / uint16 / int16 TIFFs; Pillow writes
8- and 16-bit PNGs. io_numpy_check reads them all and compares with the same formula. Then it
writes .npy / .txt / .csv / float32 TIFF / 16-bit PNG, which numpy, tifffile and Pillow read
back here. Exits 77 (skip) when numpy, tifffile or Pillow is missing.
usage: io_numpy_check.py PATH_TO_io_numpy_check
"""
import os
import subprocess
import sys
import tempfile

try:
    import numpy as np
    import tifffile
    from PIL import Image
except ImportError as e:
    print(f"SKIP: {e}: the numpy/tifffile/Pillow cross-check of svpsf's I/O needs "
          "python3-numpy, python3-skimage (tifffile) and python3-pil")
    sys.exit(77)

W, H = 13, 7


def formula(kind):
    y, x = np.mgrid[0:H, 0:W]
    v = ((y * 37 + x * 11) % 200).astype(np.float64)
    if kind != "unsigned":
        v -= 100
    if kind == "float":
        v += 0.25 * (x % 4)
    return v


def main():
    exe = sys.argv[1]
    failures = 0
    with tempfile.TemporaryDirectory(prefix="svpsf-io-check-") as d:
        manifest = []

        def add(name, kind):
            manifest.append(f"{name} {kind}\n")

        for dt in ["<f8", ">f8", "<f4", ">f4"]:
            for order in "CF":
                name = f"py_{'le' if dt[0] == '<' else 'be'}{dt[1:]}_{order}.npy"
                np.save(os.path.join(d, name), np.asarray(formula("float"), dtype=dt, order=order))
                add(name, "float")
        for dt in ["i1", "u1", "<i2", ">i2", "<u2", ">u2", "<i4", ">u4", "<i8", "<u8"]:
            kind = "unsigned" if "u" in dt else "signed"
            name = f"py_{dt.replace('<', 'le').replace('>', 'be')}.npy"
            np.save(os.path.join(d, name), formula(kind).astype(dt))
            add(name, kind)
        np.save(os.path.join(d, "py_i2_F.npy"), np.asfortranarray(formula("signed").astype("<i2")))
        add("py_i2_F.npy", "signed")
        np.save(os.path.join(d, "py_hw1.npy"), formula("float")[:, :, None])
        add("py_hw1.npy", "float")
        np.savetxt(os.path.join(d, "py_default.txt"), formula("float"), header="numpy.savetxt")
        add("py_default.txt", "float")
        np.savetxt(os.path.join(d, "py_comma.csv"), formula("float"), delimiter=",", fmt="%.6f")
        add("py_comma.csv", "float")
        tifffile.imwrite(os.path.join(d, "py_f32.tif"), formula("float").astype(np.float32))
        add("py_f32.tif", "float")
        tifffile.imwrite(os.path.join(d, "py_u16.tif"), formula("unsigned").astype(np.uint16))
        add("py_u16.tif", "unsigned")
        tifffile.imwrite(os.path.join(d, "py_i16.tif"), formula("signed").astype(np.int16))
        add("py_i16.tif", "signed")
        Image.fromarray(formula("unsigned").astype(np.uint8)).save(os.path.join(d, "py_u8.png"))
        add("py_u8.png", "unsigned")
        Image.fromarray(formula("unsigned").astype(np.uint16)).save(os.path.join(d, "py_u16.png"))
        add("py_u16.png", "unsigned")
        with open(os.path.join(d, "manifest.txt"), "w") as f:
            f.writelines(manifest)
        r = subprocess.run([exe, "read", d])
        failures += r.returncode != 0

        r = subprocess.run([exe, "write", d])
        if r.returncode != 0:
            print("FAIL: io_numpy_check write")
            return 1
        want = formula("float")
        checks = [
            ("out.npy", np.load(os.path.join(d, "out.npy")), want, np.float64),
            ("out.txt", np.loadtxt(os.path.join(d, "out.txt")), want, np.float64),
            ("out.csv", np.loadtxt(os.path.join(d, "out.csv"), delimiter=","), want, np.float64),
            ("out.tif", tifffile.imread(os.path.join(d, "out.tif")), want.astype(np.float32),
             np.float32),
            ("out.png", np.asarray(Image.open(os.path.join(d, "out.png"))),
             np.round(formula("unsigned") / 199.0 * 65535.0), None),
        ]
        for name, got, expected, dtype in checks:
            ok = got.shape == expected.shape and np.array_equal(got.astype(np.float64),
                                                               expected.astype(np.float64))
            if dtype is not None:
                ok = ok and got.dtype == dtype
            print(f"{'ok  ' if ok else 'FAIL'} {name} read by Python: dtype {got.dtype}, "
                  f"shape {got.shape}")
            failures += not ok
        # colour maps (RGB as Pillow reads them): diverging blue-white-red centred on zero over
        # [-2, 2], sequential viridis over [-2, 2], NaN grey
        div = np.asarray(Image.open(os.path.join(d, "out_div.png")).convert("RGB")).astype(int)
        seq = np.asarray(Image.open(os.path.join(d, "out_seq.png")).convert("RGB")).astype(int)
        colour_checks = [
            ("diverging -2 is dark blue", div[0, 0], (5, 48, 97), 0),
            ("diverging 0 is white", div[0, 2], (247, 247, 247), 3),
            ("diverging +2 is dark red", div[0, 4], (103, 0, 31), 0),
            ("diverging NaN is grey", div[0, 5], (128, 128, 128), 0),
            ("viridis -2 is dark purple", seq[0, 0], (68, 1, 84), 3),
            ("viridis +2 is yellow", seq[0, 4], (253, 231, 37), 3),
            ("viridis NaN is grey", seq[0, 5], (128, 128, 128), 0),
        ]
        for what, got, want, tol in colour_checks:
            ok = bool(np.all(np.abs(got - np.array(want)) <= tol))
            print(f"{'ok  ' if ok else 'FAIL'} {what}: RGB {tuple(got)} (expected {want} ± {tol})")
            failures += not ok
        # YAML (PyYAML is a YAML 1.1 reader: floats need a dot, "yes" is a boolean) and JSON
        import json
        with open(os.path.join(d, "out.json")) as f:
            js = json.load(f)
        grid = [0.1, -2e-300, 1.0 / 3.0]
        ok = js == {"text": 'a "b" \\ \n \x01 \u00b5m', "nan": None, "grid": grid}
        print(f"{'ok  ' if ok else 'FAIL'} out.json read by json.load: {js}")
        failures += not ok
        try:
            import yaml
        except ImportError:
            print("SKIP out.yaml: python3-yaml is not installed")
        else:
            with open(os.path.join(d, "out.yaml")) as f:
                y = yaml.safe_load(f)
            want = {"pixel_um": 0.1, "text": 'a: "b" # c\n\\ yes', "word": "yes", "grid": grid,
                    "regions": [{"label": 2, "metal": True}]}
            ok = y == want
            print(f"{'ok  ' if ok else 'FAIL'} out.yaml read by yaml.safe_load: {y}")
            failures += not ok
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
