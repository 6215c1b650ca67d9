#!/usr/bin/env python3
"""The layers of svpsf (docs/architecture.md) checked against the code.

  layers.py [--root DIR] [--doc docs/architecture.md] [--objects BUILDDIR]
            [--core-lib LIB] [--report] [--self-test]

Reads the layer list (the ```layers block of docs/architecture.md: rank, module, directory,
library), then
- every #include "..." of a C/C++ file under a listed directory: a module may include its own
  headers, include/ and generated headers, and the headers of modules of strictly lower rank;
  anything else (a lower layer including a higher one, or two modules of one rank including
  each other) is a violation;
- prints the module include graph and its cycles;
- with --objects: the symbol graph (which module's object files call which module's
  functions, from `nm` on the object files under BUILDDIR; a call to a module of equal or
  higher rank is a violation, even through the public header), its module cycles and the
  file-level cycles inside src/ (files that call each other round a loop, reported only);
- with --core-lib: the dynamic dependencies (readelf -d NEEDED) of the numerics library must
  not name OpenCV, cairo, fontconfig or a YAML library, and its undefined symbols
  (nm -D --undefined-only) none of theirs.
Exit 1 on any violation (unless --report). Plain Python 3 (no third-party modules)."""
import argparse
import collections
import os
import re
import subprocess
import sys

INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"', re.M)
FORBIDDEN_LIBS = re.compile(r'opencv|cairo|fontconfig|yaml|stdc\+\+', re.I)
FORBIDDEN_SYMS = re.compile(r'^(_ZN2cv|cv[A-Z]|cairo_|Fc[A-Z]|yaml_|fy_)')


def read_layers(doc):
    with open(doc, encoding='utf-8') as f:
        text = f.read()
    m = re.search(r'```layers\n(.*?)```', text, re.S)
    if not m:
        sys.exit(f'{doc}: no ```layers block')
    layers = []
    for ln in m.group(1).splitlines():
        ln = ln.split('#')[0].strip()
        if ln:
            rank, name, directory, *lib = ln.split()
            layers.append((int(rank), name, directory.rstrip('/'), lib[0] if lib else '-'))
    return layers


def module_of(path, layers):
    path = os.path.normpath(path)
    best = None
    for rank, name, d, _ in layers:
        if path == d or path.startswith(d + os.sep):
            if not best or len(d) > len(best[2]):
                best = (rank, name, d)
    return best


def sources(root, layers):
    for _, _, d, _ in layers:
        top = os.path.join(root, d)
        for dirpath, _, files in os.walk(top):
            for f in sorted(files):
                if f.endswith(('.c', '.cpp', '.h', '.hpp')):
                    yield os.path.relpath(os.path.join(dirpath, f), root)


def resolve(root, src, inc):
    """The repository path an #include "inc" in src names (its own directory, then the
    include directories of the build: the root, src/, include/), or None."""
    for base in (os.path.dirname(src), '.', 'src', 'include'):
        p = os.path.normpath(os.path.join(base, inc))
        if os.path.exists(os.path.join(root, p)):
            return p
    return None


def sccs(graph):
    """Strongly connected components with more than one node (Tarjan, iterative)."""
    index, low, on, stack, out, counter = {}, {}, set(), [], [], [0]
    nodes = sorted(set(graph) | {w for v in graph.values() for w in v})

    def visit(v0):
        work = [(v0, iter(sorted(graph.get(v0, ()))))]
        index[v0] = low[v0] = counter[0]
        counter[0] += 1
        stack.append(v0)
        on.add(v0)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))

    for v in nodes:
        if v not in index:
            visit(v)
    return sorted(out)


def print_graph(title, graph):
    print(title)
    for a in sorted(graph):
        if graph[a]:
            print(f'  {a:10s} -> {", ".join(sorted(graph[a]))}')


def symbol_graph(builddir, root, layers):
    """(module graph, file graph) from the object files of the build: an edge a -> b when an
    object of a has an undefined symbol an object of b defines."""
    objs = {}
    for dirpath, _, files in os.walk(builddir):
        if 'svpsf_internal' in dirpath or 'fuzz' in dirpath:
            continue
        for f in files:
            if f.endswith('.o'):
                name = f[:-2]
                # meson names objects after the source path with '/' turned into '_'
                for src in sources(root, layers):
                    if src.replace('/', '_') == name and src not in objs:
                        objs[src] = os.path.join(dirpath, f)
    defined, undefined = {}, {}
    for src, obj in objs.items():
        out = subprocess.run(['nm', obj], capture_output=True, text=True).stdout
        und = set()
        for ln in out.splitlines():
            parts = ln.split()
            if len(parts) == 2 and parts[0] == 'U':
                und.add(parts[1])
            elif len(parts) == 3 and parts[1] in 'TDBRVW' and parts[1].isupper():
                defined.setdefault(parts[2], src)
        undefined[src] = und
    files = collections.defaultdict(set)
    mods = collections.defaultdict(set)
    for src, und in undefined.items():
        for s in und:
            d = defined.get(s)
            if d and d != src:
                files[src].add(d)
                ma, mb = module_of(src, layers)[1], module_of(d, layers)[1]
                if ma != mb:
                    mods[ma].add(mb)
    return mods, files


def check_core_lib(lib):
    bad = []
    dyn = subprocess.run(['readelf', '-d', lib], capture_output=True, text=True)
    if dyn.returncode:
        return [f'readelf -d {lib} failed: {dyn.stderr.strip()}']
    needed = re.findall(r'\(NEEDED\).*\[(.*)\]', dyn.stdout)
    print(f'{lib}: NEEDED {", ".join(needed)}')
    bad += [f'{lib} needs {n}' for n in needed if FORBIDDEN_LIBS.search(n)]
    und = subprocess.run(['nm', '-D', '--undefined-only', lib], capture_output=True, text=True)
    syms = [ln.split()[-1] for ln in und.stdout.splitlines() if ln.strip()]
    bad += [f'{lib} calls {s}' for s in syms if FORBIDDEN_SYMS.search(s)]
    return bad


def check_includes(root, layers):
    """(module include graph, violations) of every #include "..." under the listed
    directories."""
    rank = {name: r for r, name, _, _ in layers}
    violations = []
    graph = collections.defaultdict(set)
    for src in sources(root, layers):
        with open(os.path.join(root, src), encoding='utf-8', errors='replace') as f:
            text = f.read()
        me = module_of(src, layers)
        for inc in INCLUDE.findall(text):
            p = resolve(root, src, inc)
            if p is None or p.startswith('include' + os.sep):
                continue  # generated (svpsf_version.h) or the public header
            other = module_of(p, layers)
            if other is None or other[1] == me[1]:
                continue
            graph[me[1]].add(other[1])
            if rank[other[1]] >= rank[me[1]]:
                violations.append(f'{src}: includes "{inc}" ({other[1]}, rank {rank[other[1]]}) '
                                  f'from {me[1]} (rank {me[0]})')
    return graph, violations


def self_test():
    """The include check on small made-up trees: it must flag a lower layer including a
    higher one and two modules of one rank including each other, and pass the allowed
    direction. Returns the number of failed cases."""
    import tempfile
    doc = ('```layers\n0 low src/low\n1 mid src/mid\n1 side src/side\n2 high src/high\n```\n')
    cases = [  # (file, include, expected violations)
        ('src/high/a.c', '../low/low.h', 0),
        ('src/high/a.c', '../mid/mid.h', 0),
        ('src/low/a.c', '../high/high.h', 1),
        ('src/low/a.c', '../mid/mid.h', 1),
        ('src/mid/a.c', '../side/side.h', 1),
        ('src/mid/a.c', 'mid.h', 0),
    ]
    failed = 0
    for path, inc, want in cases:
        with tempfile.TemporaryDirectory() as root:
            os.makedirs(os.path.join(root, 'docs'))
            with open(os.path.join(root, 'docs', 'architecture.md'), 'w') as f:
                f.write(doc)
            for m in ('low', 'mid', 'side', 'high'):
                os.makedirs(os.path.join(root, 'src', m))
                open(os.path.join(root, 'src', m, m + '.h'), 'w').close()
            with open(os.path.join(root, path), 'w') as f:
                f.write(f'#include "{inc}"\nint f(void) {{ return 0; }}\n')
            layers = read_layers(os.path.join(root, 'docs', 'architecture.md'))
            _, v = check_includes(root, layers)
            ok = len(v) == want
            failed += not ok
            print(f'self-test {"ok" if ok else "FAILED"}: {path} includes "{inc}": '
                  f'{len(v)} violation(s), expected {want}')
    return failed


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--root', default=os.path.normpath(os.path.join(here, '..', '..')))
    ap.add_argument('--doc', default=None)
    ap.add_argument('--objects')
    ap.add_argument('--core-lib')
    ap.add_argument('--report', action='store_true', help='never exit 1')
    ap.add_argument('--self-test', action='store_true',
                    help='first check the include check itself on made-up trees')
    a = ap.parse_args()
    if a.self_test and self_test():
        return 1
    root = a.root
    layers = read_layers(a.doc or os.path.join(root, 'docs', 'architecture.md'))
    rank = {name: r for r, name, _, _ in layers}

    graph, violations = check_includes(root, layers)
    print_graph('include graph (module -> modules whose headers it includes):', graph)
    cyc = sccs(graph)
    print(f'include cycles between modules: {len(cyc)}' +
          ''.join(f'\n  {" <-> ".join(c)}' for c in cyc))

    if a.objects:
        mods, files = symbol_graph(a.objects, root, layers)
        print_graph('symbol graph (module -> modules whose functions it calls):', mods)
        cyc = sccs(mods)
        print(f'call cycles between modules: {len(cyc)}' +
              ''.join(f'\n  {" <-> ".join(c)}' for c in cyc))
        for m, targets in sorted(mods.items()):
            for t in sorted(targets):
                if rank[t] >= rank[m]:
                    violations.append(f'{m} (rank {rank[m]}) calls functions of {t} '
                                      f'(rank {rank[t]})')
        cyc = [c for c in sccs(files) if all(f.startswith('src' + os.sep) for f in c)]
        print(f'call cycles between files in src/: {len(cyc)}' +
              ''.join(f'\n  {" <-> ".join(c)}' for c in cyc))

    if a.core_lib:
        violations += check_core_lib(a.core_lib)

    for v in violations:
        print('VIOLATION:', v)
    print(f'{len(violations)} violation(s)')
    return 1 if violations and not a.report else 0


if __name__ == '__main__':
    sys.exit(main())
