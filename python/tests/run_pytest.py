"""Runs pytest for meson (python/meson.build): exit 77 (skip) when pytest is missing.

The guard matters: Dask's worker processes are started by multiprocessing's spawn, which
imports the parent's main module again."""
import sys


def main():
    try:
        import pytest
    except ImportError:
        print("SKIP: pytest is not installed (Debian: python3-pytest): the svpsf package is not "
              "tested")
        return 77
    return pytest.main(sys.argv[1:])


if __name__ == "__main__":
    sys.exit(main())
