#!/usr/bin/env python3
"""Before/after figures of the code's shape: include graph cycles, file sizes, long functions.

  include_graph.py [--root DIR] [--rev REV ...] [--top N] [--limit L] [--self-test]

For the working tree under --root (default: this repository), or for each git revision given
with --rev (read with `git archive`, nothing checked out), over the C/C++ files of src/ and
tools/svpsf:
- the file include graph (a -> b when a has #include "..." naming b: its own folder, the
  root, src/, include/) and its cycles: strongly connected components of more than one file;
- the module include graph (module = folder: src/psf, src/io, tools/svpsf, ...) and its cycles;
- the file use graph (a.c -> b.c when a.c names a function b.c defines without `static`, read
  from the source text: a reference to a name two files define is left out) and its cycles;
  these are the loops a reader follows between files (operator.c -> variant.c -> exact.c and
  back), whichever headers carry the declarations; and the same graph between modules;
- the largest files (lines) and the total;
- the functions longer than --limit lines (default 150; tools/check/funclen.py's parser, which
  here also looks inside C++ `extern "C" {` and `namespace {` blocks).
With several revisions a summary table compares them. Plain Python 3 (no third-party
modules); git only for --rev."""
import argparse
import collections
import io
import os
import re
import subprocess
import sys
import tarfile
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import funclen  # noqa: E402  (the same parser as the function-length check)
from layers import sccs  # noqa: E402  (the same Tarjan as the layer check)

DIRS = ('src', os.path.join('tools', 'svpsf'))
EXT = ('.c', '.cpp', '.h', '.hpp')
INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"', re.M)
WORD = re.compile(r'[A-Za-z_][A-Za-z_0-9]*')


def files_of(root):
    out = []
    for d in DIRS:
        for dirpath, _, names in os.walk(os.path.join(root, d)):
            for f in sorted(names):
                if f.endswith(EXT):
                    out.append(os.path.relpath(os.path.join(dirpath, f), root))
    return sorted(out)


def module_of(path):
    return os.path.dirname(path)


def resolve(root, src, inc):
    for base in (os.path.dirname(src), '.', 'src', 'include'):
        p = os.path.normpath(os.path.join(base, inc))
        if os.path.exists(os.path.join(root, p)):
            return p
    return None


def include_graph(root, files):
    known = set(files)
    graph = collections.defaultdict(set)
    for src in files:
        with open(os.path.join(root, src), encoding='utf-8', errors='replace') as f:
            text = f.read()
        for inc in INCLUDE.findall(text):
            p = resolve(root, src, inc)
            if p in known and p != src:
                graph[src].add(p)
    return graph


def module_graph(file_graph):
    graph = collections.defaultdict(set)
    for a, targets in file_graph.items():
        for b in targets:
            if module_of(a) != module_of(b):
                graph[module_of(a)].add(module_of(b))
    return graph


# C++ wrappers whose braces would hide the functions inside from funclen's parser (it reads
# depth 0 only): `extern "C" {`, `namespace {` and their closing `} // ...` lines.
CXX_WRAPPER = re.compile(r'(?m)^(?:extern "C"|namespace(?:\s+\w+)?)\s*\{\s*$|'
                         r'^\}\s*//\s*(?:namespace|extern).*$')


def read_source(path):
    with open(path, encoding='utf-8', errors='replace') as f:
        text = f.read()
    if path.endswith(('.cpp', '.hpp')):
        text = CXX_WRAPPER.sub('', text)
    return text


def functions(path):
    """funclen's (name, first line, last line, reason) of path's functions."""
    return funclen.functions_in(read_source(path))


def external_functions(path):
    """Names of the functions path defines without `static` (funclen's parser)."""
    lines = funclen.strip(read_source(path))[0].split('\n')
    names = []
    for name, first, _, _ in functions(path):
        head = lines[first - 1]
        if head.lstrip().startswith(name) and first >= 2:  # return type on the line above
            head = lines[first - 2] + ' ' + head
        if name != '?' and not re.search(r'\bstatic\b', head):
            names.append(name)
    return names


def use_graph(root, files):
    units = [f for f in files if f.endswith(('.c', '.cpp'))]
    owner = collections.defaultdict(set)
    defines = {}
    for u in units:
        defines[u] = set(external_functions(os.path.join(root, u)))
        for name in defines[u]:
            owner[name].add(u)
    graph = collections.defaultdict(set)
    for u in units:
        with open(os.path.join(root, u), encoding='utf-8', errors='replace') as f:
            words = set(WORD.findall(funclen.strip(f.read())[0]))
        for w in words - defines[u]:
            if len(owner.get(w, ())) == 1:
                graph[u].add(next(iter(owner[w])))
    return graph


def line_count(path):
    with open(path, encoding='utf-8', errors='replace') as f:
        return sum(1 for _ in f)


def measure(root, limit):
    files = files_of(root)
    fg = include_graph(root, files)
    ug = use_graph(root, files)
    sizes = sorted(((line_count(os.path.join(root, f)), f) for f in files), reverse=True)
    long_fns = []
    for f in files:
        for name, first, last, _ in functions(os.path.join(root, f)):
            if last - first + 1 > limit:
                long_fns.append((last - first + 1, f, name))
    long_fns.sort(key=lambda r: (-r[0], r[1]))
    return {
        'files': len(files),
        'lines': sum(n for n, _ in sizes),
        'sizes': sizes,
        'file_cycles': sccs(fg),
        'module_cycles': sccs(module_graph(fg)),
        'use_cycles': sccs(ug),
        'module_use_cycles': sccs(module_graph(ug)),
        'long': long_fns,
    }


def report(title, m, top, limit):
    print(f'== {title}')
    print(f'{m["files"]} files, {m["lines"]} lines under {", ".join(DIRS)}')
    for label, key in (('file include cycles', 'file_cycles'),
                       ('module include cycles', 'module_cycles'),
                       ('file use cycles (function calls between .c files)', 'use_cycles'),
                       ('module use cycles', 'module_use_cycles')):
        print(f'{label}: {len(m[key])}')
        for c in m[key]:
            print(f'  {" <-> ".join(c)}')
    print(f'largest files (of {m["files"]}):')
    for n, f in m['sizes'][:top]:
        print(f'  {n:6d}  {f}')
    print(f'functions over {limit} lines: {len(m["long"])}')
    for n, f, name in m['long']:
        print(f'  {n:6d}  {f}  {name}')
    print()


def summary(results, top, limit):
    cols = [t for t, _ in results]
    rows = [
        ('files / lines', lambda m: f'{m["files"]} / {m["lines"]}'),
        ('largest file', lambda m: f'{m["sizes"][0][1]} ({m["sizes"][0][0]})'),
        (f'files over 1000 lines', lambda m: str(sum(1 for n, _ in m['sizes'] if n > 1000))),
        ('file include cycles', lambda m: str(len(m['file_cycles']))),
        ('module include cycles', lambda m: '; '.join(' <-> '.join(os.path.basename(x)
                                                                for x in c)
                                                      for c in m['module_cycles']) or '0'),
        ('file use cycles (files in each)', lambda m: f'{len(m["use_cycles"])} (' +
         ', '.join(str(len(c)) for c in m['use_cycles']) + ')'),
        ('module use cycles', lambda m: '; '.join(' <-> '.join(os.path.basename(x)
                                                            for x in c)
                                                  for c in m['module_use_cycles']) or '0'),
        (f'functions over {limit} lines (in src/)',
         lambda m: f'{len(m["long"])} ({sum(1 for r in m["long"] if r[1].startswith("src"))})'),
        ('longest function', lambda m: f'{m["long"][0][2]} ({m["long"][0][0]})'
         if m['long'] else '-'),
    ]
    print('| | ' + ' | '.join(cols) + ' |')
    print('|---' * (len(cols) + 1) + '|')
    for label, fn in rows:
        print(f'| {label} | ' + ' | '.join(fn(m) for _, m in results) + ' |')


def extract(root, rev, into):
    """The src/ and tools/svpsf files of revision rev under into (git archive)."""
    paths = subprocess.run(['git', '-C', root, 'ls-tree', '--name-only', rev, '--'] +
                           [d for d in DIRS] + ['include'],
                           capture_output=True, text=True, check=True).stdout.split()
    data = subprocess.run(['git', '-C', root, 'archive', '--format=tar', rev, '--'] + paths,
                          capture_output=True, check=True).stdout
    with tarfile.open(fileobj=io.BytesIO(data)) as t:
        t.extractall(into)


def self_test():
    """A made-up tree: a header cycle, a module cycle and a call cycle must be found, a static
    function of the same name elsewhere must not make an edge. Returns the failures."""
    tree = {
        'src/a/a.h': '#include "b.h"\n',
        'src/a/b.h': '#include "a.h"\n',
        'src/a/x.c': '#include "a.h"\n#include "../b/y.h"\nint fx(void) { return fy(); }\n',
        'src/b/y.h': 'int fy(void);\n',
        'src/b/y.c': '#include "../a/a.h"\nint fy(void) { return fx(); }\n',
        'src/b/z.c': 'static int fz(void) { return 0; }\nint gz(void) { return fz(); }\n',
        'src/a/w.c': 'static int fz(void) { return 1; }\nint gw(void) { return fz(); }\n',
    }
    with tempfile.TemporaryDirectory() as root:
        for p, text in tree.items():
            os.makedirs(os.path.join(root, os.path.dirname(p)), exist_ok=True)
            with open(os.path.join(root, p), 'w') as f:
                f.write(text)
        m = measure(root, 150)
    want = {'file_cycles': [['src/a/a.h', 'src/a/b.h']],
            'module_cycles': [['src/a', 'src/b']],
            'use_cycles': [['src/a/x.c', 'src/b/y.c']],
            'module_use_cycles': [['src/a', 'src/b']]}
    failed = 0
    for k, w in want.items():
        ok = m[k] == w
        failed += not ok
        print(f'self-test {"ok" if ok else "FAILED"}: {k}: {m[k]}, expected {w}')
    return failed


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--root', default=os.path.normpath(os.path.join(here, '..', '..')))
    ap.add_argument('--rev', action='append', default=[],
                    help='a git revision to measure (repeatable); default: the working tree')
    ap.add_argument('--top', type=int, default=10, help='largest files to list')
    ap.add_argument('--limit', type=int, default=150, help='function length limit')
    ap.add_argument('--self-test', action='store_true')
    a = ap.parse_args()
    if a.self_test:
        return 1 if self_test() else 0
    results = []
    if not a.rev:
        results.append(('working tree', measure(a.root, a.limit)))
    for rev in a.rev:
        with tempfile.TemporaryDirectory() as tmp:
            extract(a.root, rev, tmp)
            short = subprocess.run(['git', '-C', a.root, 'rev-parse', '--short', rev],
                                   capture_output=True, text=True, check=True).stdout.strip()
            results.append((f'{rev} ({short})' if short != rev else rev, measure(tmp, a.limit)))
    for title, m in results:
        report(title, m, a.top, a.limit)
    if len(results) > 1:
        summary(results, a.top, a.limit)
    return 0


if __name__ == '__main__':
    sys.exit(main())
