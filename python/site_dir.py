"""Prints the folder under PREFIX where this interpreter looks for packages (for meson: the
Python package's install folder; python/meson.build), or nothing when it looks in none.

usage: site_dir.py PREFIX
"""
import os
import sys

prefix = os.path.normpath(sys.argv[1]) + os.sep
for entry in sys.path:
    # PREFIX/lib.../{dist,site}-packages (for /usr not /usr/local/lib/...)
    if entry.startswith(prefix) and entry[len(prefix):].startswith("lib") and \
            os.path.basename(entry) in ("dist-packages", "site-packages"):
        print(entry)
        break
