#!/usr/bin/env python3
"""Function lengths in the C sources (docs/architecture.md, "Function length").

Lists every function longer than the limit (default 150 lines, signature to closing brace) in
the given directories. A long function passes when the comment right above it (or in its first
lines) says why it is one piece: the words "one piece" in that comment.

  funclen.py [--limit N] [--strict DIR ...] [--all] [--self-test] DIR...

--strict DIR  exit 1 when a long function under DIR has no such comment (the other
              directories are only reported)
--all         print every function with its length, longest first
Plain Python 3 (no third-party modules)."""
import argparse
import os
import re
import sys

IDENT = re.compile(r'([A-Za-z_][A-Za-z_0-9]*)\s*\($')
REASON = re.compile(r'one\s+piece', re.I)


def strip(text):
    """The text with comments, strings and character literals blanked (newlines kept), and
    the list of (first line, last line, comment text) of every comment."""
    out, comments = [], []
    i, n, line = 0, len(text), 1
    while i < n:
        c = text[i]
        if text.startswith('/*', i):
            j = text.find('*/', i + 2)
            j = n if j < 0 else j + 2
            body = text[i:j]
            comments.append((line, line + body.count('\n'), body))
            out.append(re.sub(r'[^\n]', ' ', body))
            line += body.count('\n')
            i = j
        elif text.startswith('//', i):
            j = text.find('\n', i)
            j = n if j < 0 else j
            comments.append((line, line, text[i:j]))
            out.append(' ' * (j - i))
            i = j
        elif c in '"\'':
            j = i + 1
            while j < n and text[j] != c:
                j += 2 if text[j] == '\\' else 1
            body = text[i:j + 1]
            out.append(c + re.sub(r'[^\n]', ' ', body[1:-1]) + c)
            line += body.count('\n')
            i = j + 1
        else:
            if c == '\n':
                line += 1
            out.append(c)
            i += 1
    return ''.join(out), comments


def functions(path):
    """(name, first line, last line, has reason) of every function definition in path."""
    with open(path, encoding='utf-8', errors='replace') as f:
        return functions_in(f.read())


def functions_in(text):
    """functions() of a source text."""
    code, comments = strip(text)
    # preprocessor lines out (a macro body must not count as code at depth 0)
    code = re.sub(r'(?m)^[ \t]*#(?:[^\n]*\\\n)*[^\n]*', lambda m: re.sub(r'[^\n]', ' ', m.group(0)), code)
    found = []
    depth, head_start, line = 0, 0, 1
    start = None
    for i, c in enumerate(code):
        if c == '\n':
            line += 1
        elif c == '{':
            if depth == 0:
                head = code[head_start:i]
                paren = head.find('(')
                if paren >= 0 and '=' not in head[:paren] and head.rstrip().endswith(')') or \
                        paren >= 0 and re.search(r'\)\s*(?:[A-Za-z_]\w*\s*)*$', head):
                    m = IDENT.search(head[:paren + 1].rstrip())
                    name = m.group(1) if m else '?'
                    sig_line = line - head[head.find(name):].count('\n') if m else line
                    start = (name, sig_line)
                else:
                    start = None
            depth += 1
        elif c == '}':
            depth -= 1
            if depth == 0:
                if start:
                    name, first = start
                    reason = any(REASON.search(body) for (a, b, body) in comments
                                 if (first - 12 <= b <= first) or first <= a <= first + 8)
                    found.append((name, first, line, reason))
                start = None
                head_start = i + 1
        elif c == ';' and depth == 0:
            head_start = i + 1
    return found


def sources(dirs):
    for d in dirs:
        for root, _, files in os.walk(d):
            for f in sorted(files):
                if f.endswith(('.c', '.cpp', '.h')):
                    yield os.path.join(root, f)


def self_test(limit):
    """functions() on a made-up file: lengths, names, the "one piece" comment, and a
    brace-initialised table that is no function. Returns the number of failed cases."""
    import tempfile
    body = lambda n: ''.join(f'    x += {i};\n' for i in range(n))
    text = ('static const int table[] = {\n    1,\n    2,\n};\n\n'
            '/* A long function. */\nint too_long(int x)\n{\n' + body(limit) + '    return x;\n}\n\n'
            '/* One piece: a made-up reason. */\nint explained(int x)\n{\n' + body(limit) +
            '    return x;\n}\n\nstatic int short_one(int x) { return x; }\n')
    with tempfile.NamedTemporaryFile('w', suffix='.c', delete=False) as f:
        f.write(text)
    try:
        got = {name: (last - first + 1, reason) for name, first, last, reason in functions(f.name)}
    finally:
        os.unlink(f.name)
    want = {'too_long': (limit + 4, False), 'explained': (limit + 4, True), 'short_one': (1, False)}
    failed = 0
    for name, w in want.items():
        ok = got.get(name) == w
        failed += not ok
        print(f'self-test {"ok" if ok else "FAILED"}: {name}: {got.get(name)}, expected {w}')
    if 'table' in got:
        failed += 1
        print('self-test FAILED: the initialised table counted as a function')
    return failed


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('dirs', nargs='+')
    ap.add_argument('--limit', type=int, default=150)
    ap.add_argument('--strict', action='append', default=[])
    ap.add_argument('--all', action='store_true')
    ap.add_argument('--self-test', action='store_true',
                    help='first check the parser on a made-up file')
    a = ap.parse_args()
    if a.self_test and self_test(a.limit):
        return 1
    rows = []
    for path in sources(a.dirs):
        for name, first, last, reason in functions(path):
            rows.append((last - first + 1, path, first, name, reason))
    rows.sort(key=lambda r: (-r[0], r[1]))
    bad = 0
    long_rows = [r for r in rows if r[0] > a.limit]
    for n, path, first, name, reason in (rows if a.all else long_rows):
        strict = any(os.path.normpath(path).startswith(os.path.normpath(s) + os.sep)
                     for s in a.strict)
        if n > a.limit and not reason:
            tag = 'FAIL' if strict else 'long'
            bad += strict
        else:
            tag = 'ok (one piece)' if n > a.limit else ''
        print(f'{n:5d}  {path}:{first}  {name}  {tag}'.rstrip())
    print(f'{len(long_rows)} function(s) over {a.limit} lines, '
          f'{sum(1 for r in long_rows if not r[4])} without a "one piece" comment; '
          f'{bad} of them under a strict directory')
    return 1 if bad else 0


if __name__ == '__main__':
    sys.exit(main())
