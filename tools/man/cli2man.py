#!/usr/bin/env python3
"""Makes the man page svpsf.1 from the CLI reference docs/cli.md (run by meson at build time).

usage: cli2man.py CLI.md OUT.1 VERSION DOCDIR

The Markdown of docs/cli.md is small and regular: headings, paragraphs, fenced code blocks,
tables (one row of column names, a separator row, rows), bullet lists, inline `code`,
**bold** and [links](target). Each becomes its roff form (man(7) macros only, no tbl): a
table row becomes a tagged paragraph headed by its first cell, with the other cells after
their column names. Standard library only, so the build needs nothing beyond meson's Python.
"""
import re
import sys


def escape(text):
    """roff-escape plain text (backslashes, hyphens that are minus signs stay hyphens)."""
    return text.replace("\\", "\\e")


def inline(text):
    """Markdown inline markup to roff font changes."""
    out = []
    # split on code spans first: their content is literal
    for i, part in enumerate(re.split(r"(`[^`]*`)", text)):
        if i % 2 == 1:
            out.append("\\fB" + escape(part[1:-1].replace("\\|", "|")) + "\\fR")
            continue
        part = escape(part)
        part = re.sub(r"\[([^\]]+)\]\(([^)]+)\)", lambda m: link(m.group(1), m.group(2)), part)
        part = re.sub(r"\*\*([^*]+)\*\*", r"\\fB\1\\fR", part)
        part = re.sub(r"(?<![\w*])\*([^*\s][^*]*)\*(?![\w*])", r"\\fI\1\\fR", part)
        part = part.replace("\\e|", "|")  # table-escaped pipes
        out.append(part)
    return "".join(out)


def link(label, target):
    """[label](target): the label, with the document it points to when that is another file."""
    if target.startswith("#") or target.startswith("http"):
        return label
    doc = target.split("#")[0]
    return label if label == doc else f"{label} ({doc})"


def line_start(text):
    """A roff text line must not start with a control character."""
    return "\\&" + text if text[:1] in (".", "'") else text


def cells(row):
    row = row.strip()
    if row.startswith("|"):
        row = row[1:]
    if row.endswith("|"):
        row = row[:-1]
    parts = re.split(r"(?<!\\)\|", row)
    return [c.strip() for c in parts]


def convert(md, version, docdir):
    out = [
        '.\\" svpsf.1: made from docs/cli.md by tools/man/cli2man.py; edit docs/cli.md instead.',
        f'.TH SVPSF 1 "" "svpsf {version}" "User Commands"',
        ".SH NAME",
        "svpsf \\- space-variant PSF restoration for widefield spectral imaging",
        ".SH SYNOPSIS",
    ]
    lines = md.split("\n")
    i = 0
    # the title line is the NAME above; the first code block is the SYNOPSIS
    while i < len(lines) and not lines[i].startswith("```"):
        i += 1
    i += 1
    out.append(".nf")
    while i < len(lines) and not lines[i].startswith("```"):
        out.append(line_start(escape(lines[i])))
        i += 1
    out.append(".fi")
    i += 1
    out.append(".SH DESCRIPTION")
    para = []

    def flush():
        if para:
            out.append(".PP")
            out.append(line_start(inline(" ".join(para))))
            para.clear()

    while i < len(lines):
        line = lines[i]
        if line.startswith("```"):
            flush()
            out.append(".PP")
            out.append(".RS 4")
            out.append(".nf")
            i += 1
            while i < len(lines) and not lines[i].startswith("```"):
                out.append(line_start(escape(lines[i])))
                i += 1
            out.append(".fi")
            out.append(".RE")
            i += 1
            continue
        m = re.match(r"^(#{1,4})\s+(.*)$", line)
        if m:
            flush()
            title = re.sub(r"`", "", m.group(2))
            level = len(m.group(1))
            if level <= 2:
                out.append('.SH "' + escape(title).upper() + '"')
            else:
                out.append('.SS "' + escape(title) + '"')
            i += 1
            continue
        if line.startswith("|") and i + 1 < len(lines) and re.match(r"^\|[\s:|-]+\|\s*$",
                                                                     lines[i + 1]):
            flush()
            header = cells(line)
            i += 2
            while i < len(lines) and lines[i].startswith("|"):
                row = cells(lines[i])
                out.append(".TP")
                out.append(line_start(inline(row[0])))
                rest = []
                for name, value in zip(header[1:], row[1:]):
                    if not value:
                        continue
                    if name.lower() in ("meaning", "what it does", "content",
                                        "accepted content", ""):
                        value = inline(value)
                        rest.append(value if value[-1:] in ".:;!?" else value + ".")
                    else:
                        rest.append(f"{escape(name.capitalize())}: {inline(value)}.")
                out.append(line_start(" ".join(rest)))
                i += 1
            continue
        m = re.match(r"^(\s*)[-*]\s+(.*)$", line)
        if m and not line.startswith("**"):
            flush()
            item = [m.group(2)]
            i += 1
            while i < len(lines) and lines[i].startswith("  ") and lines[i].strip() and \
                    not re.match(r"^\s*[-*]\s+", lines[i]):
                item.append(lines[i].strip())
                i += 1
            out.append(".IP \\(bu 2")
            out.append(line_start(inline(" ".join(item))))
            continue
        if not line.strip():
            flush()
        else:
            para.append(line.strip())
        i += 1
    flush()
    out += [
        ".SH FILES",
        ".TP",
        docdir,
        "The documentation this page is made from (cli.md) and the rest of it: model.md (the "
        "model and its equations), api.md (the C library), scenes.md and the scene files in "
        "scenes/, performance.md.",
        ".SH SEE ALSO",
        "The C library: the header svpsf.h and \\fBpkg-config --cflags --libs svpsf\\fR.",
    ]
    return "\n".join(out) + "\n"


def main():
    if len(sys.argv) != 5:
        sys.exit(__doc__.split("\n\n")[1])
    with open(sys.argv[1], encoding="utf-8") as f:
        md = f.read()
    text = convert(md, sys.argv[3], sys.argv[4])
    with open(sys.argv[2], "w", encoding="utf-8") as f:
        f.write(text)


if __name__ == "__main__":
    main()
