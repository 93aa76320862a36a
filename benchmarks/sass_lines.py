"""Which Python lines a kernel's instructions and stall samples come from: ncu's SASS page against nvdisasm's lines.

ncu's source page for a Warp kernel lists the SASS instructions with their samples and counts, but its Python view
names one file without figures (Warp inlines every ``@wp.func`` into the kernel, so the line tables hold chains of
inlined calls). nvdisasm ``-gi`` prints, above each instruction of the cubin, the chain of (file, line) it was
inlined through. This script reads both and sums, for each instruction's innermost Python line (or its outermost:
the kernel's own line, ``--level outer``) and for each ``def`` around that line, the share of the warp-state
samples and of the executed warp instructions. The SASS page and the disassembly must come from the same cubin:
the script checks each instruction's opcode against the page and says how many differ.

The cubin: Warp's kernel cache on the GPU machine (``pair_stalls.py`` disassembles it there where nvdisasm is
present), or compiled here for the same architecture with Warp's NVRTC and ``wp.config.lineinfo`` (the same
Warp version gives the same cubin; the kernel's name in both, e.g. ``..._8ca9ec3e_cuda_kernel_forward``, says so).
nvdisasm ships with the CUDA toolkit and in PyPI's ``nvidia-cuda-nvdisasm`` wheel. The lines' text and the ``def``
around them are read from ``--roots``: give the tree that was compiled (``git archive REV kernels | tar x``), as a
later edit moves the lines.

    python benchmarks/sass_lines.py --page cube_one_source_sass.csv --sass overlap.sass [--level inner] [--top 30]
    python benchmarks/sass_lines.py --page ... --cubin kernel.sm90.cubin --nvdisasm /path/to/nvdisasm
"""

import argparse
import collections
import csv
import functools
import io
import json
import os
import re
import shutil
import subprocess
import sys

LINE_INFO = re.compile(r'//## File "([^"]+)", line (\d+)(?: inlined at "([^"]+)", line (\d+))?')
INSTRUCTION = re.compile(r"\s*/\*([0-9a-f]{4,})\*/\s+(.*?)\s*;")
FUNCTION = re.compile(r"\.text\.(\S+):")


def read_disassembly(text):
    """{function: {offset: (chain, instruction)}} of nvdisasm -gi's output: each instruction's chain of (file, line),
    innermost first (the chain above it, or the previous instruction's where none is printed)."""
    functions = {}
    where, chain, pending = None, [], []
    for line in text.splitlines():
        found = FUNCTION.match(line.strip())
        if found:
            where = functions.setdefault(found.group(1), {})
            chain, pending = [], []
            continue
        found = LINE_INFO.search(line)
        if found:
            pending.append((found.group(1), int(found.group(2))))
            if found.group(3):
                pending.append((found.group(3), int(found.group(4))))
            continue
        found = INSTRUCTION.match(line)
        if found and where is not None:
            if pending:
                chain, pending = pending, []
            where[int(found.group(1), 16)] = (tuple(chain), found.group(2))
    return functions


def read_page(text):
    """(kernel name, rows as dicts) of ncu's source page printed with --print-source sass (CSV)."""
    start = text.find('"')
    table = [r for r in csv.reader(io.StringIO(text[start:] if start >= 0 else "")) if r]
    kernel = next((r[1] for r in table if r[0] == "Kernel Name" and len(r) > 1), None)
    table = [r for r in table if r[0] != "Kernel Name"]
    if not table:
        return kernel, []
    return kernel, [dict(zip(table[0], r, strict=False)) for r in table[1:] if len(r) >= len(table[0])]


def number(value):
    try:
        return float(str(value).replace(",", ""))
    except ValueError:
        return 0.0


def opcode(instruction):
    """The opcode of a SASS instruction, without its predicate (``@P2  BRA x`` -> ``BRA``)."""
    words = instruction.strip().rstrip(";").split()
    if words and words[0].startswith("@"):
        words = words[1:]
    return words[0] if words else ""


def pick(chain, level):
    """The (file, line) a chain is counted at: its innermost or outermost Python line (else its innermost)."""
    python = [c for c in chain if c[0].endswith(".py")]
    if not python:
        return chain[0] if chain else ("?", 0)
    return python[0] if level == "inner" else python[-1]


@functools.cache
def file_lines(path):
    try:
        with open(path) as f:
            return f.read().splitlines()
    except OSError:
        return []


def source_line(path, line):
    lines = file_lines(path)
    return lines[line - 1] if 0 < line <= len(lines) else ""


def enclosing_def(path, line):
    """The name of the ``def`` a Python line is in (the nearest one above it), or "?"."""
    for k in range(line, 0, -1):
        found = re.match(r"\s*def (\w+)\(", source_line(path, k))
        if found:
            return found.group(1)
    return "?"


def attribute(functions, kernel, rows, level="inner", roots=()):
    """Samples and warp instructions summed by line and by function; the count of opcodes that differ.
    ``roots``: folders to look for the source files in when the paths of the disassembly are not here."""
    name = kernel if kernel in functions else next(iter(functions), None)
    if name is None:
        raise SystemExit("sass_lines: the disassembly holds no function")
    where = functions[name]
    sample_key = next((k for k in rows[0] if k.startswith("Warp Stall Sampling (All")), None) if rows else None
    if sample_key is None:
        raise SystemExit(
            "sass_lines: the page has no 'Warp Stall Sampling (All Samples)' column: ncu's source page printed "
            "with --page source --print-source sass --csv, from a report with SourceCounters"
        )
    base = int(rows[0]["Address"], 16)
    by_line, by_def = collections.defaultdict(lambda: [0.0, 0.0]), collections.defaultdict(lambda: [0.0, 0.0])
    differ = 0
    for row in rows:
        chain, instruction = where.get(int(row["Address"], 16) - base, ((), ""))
        if opcode(instruction) != opcode(row.get("Source", "")):
            differ += 1
        path, line = pick(chain, level)
        local = resolve(path, roots)
        figures = (number(row.get(sample_key)), number(row.get("Instructions Executed")))
        for table, key in ((by_line, (path, line)), (by_def, (os.path.basename(path), enclosing_def(local, line)))):
            table[key][0] += figures[0]
            table[key][1] += figures[1]
    return name, by_line, by_def, differ


def resolve(path, roots):
    if os.path.exists(path):
        return path
    for root in roots:
        for tail in (os.path.basename(path), os.path.join(*path.split(os.sep)[-2:])):
            candidate = os.path.join(root, tail)
            if os.path.exists(candidate):
                return candidate
    return path


def table(entries, top):
    samples = sum(s for s, _ in entries.values()) or 1.0
    instructions = sum(i for _, i in entries.values()) or 1.0
    ranked = sorted(entries.items(), key=lambda kv: -kv[1][0])[:top]
    return [{"at": key, "samples": s / samples, "instructions": i / instructions} for key, (s, i) in ranked]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--page", required=True, help="ncu's SASS source page (CSV)")
    ap.add_argument("--sass", help="nvdisasm -gi's output for the kernel's cubin")
    ap.add_argument("--cubin", help="the cubin (disassembled here with --nvdisasm)")
    ap.add_argument("--nvdisasm", default=None, help="nvdisasm's path (default: on the PATH or in the CUDA toolkit)")
    ap.add_argument("--level", choices=("inner", "outer"), default="inner")
    ap.add_argument("--top", type=int, default=30)
    ap.add_argument("--roots", default="kernels,src/polydem", help="where to find the source files (comma list)")
    ap.add_argument("--json", help="write the tables here")
    args = ap.parse_args(argv)
    if (args.sass is None) == (args.cubin is None):
        ap.error("give one of --sass (a disassembly) and --cubin (disassembled here)")
    if args.cubin:
        tool = args.nvdisasm or shutil.which("nvdisasm") or "/usr/local/cuda/bin/nvdisasm"
        if not os.path.exists(tool) and shutil.which(tool) is None:
            sys.exit(f"sass_lines: nvdisasm not found ({tool}); give --nvdisasm, or --sass with its output")
        text = subprocess.run([tool, "-gi", "-c", args.cubin], capture_output=True, text=True, check=True).stdout
    else:
        with open(args.sass) as f:
            text = f.read()
    with open(args.page) as f:
        kernel, rows = read_page(f.read())
    if not rows:
        sys.exit(f"sass_lines: {args.page} holds no rows of ncu's source page")
    roots = [r for r in args.roots.split(",") if r]
    name, by_line, by_def, differ = attribute(read_disassembly(text), kernel, rows, args.level, roots)
    print(f"{name}: {len(rows)} instructions, {differ} of them with another opcode in the disassembly"
          + ("  (NOT the same cubin: the figures below mean nothing)" if differ else ""))  # fmt: skip
    lines, defs = table(by_line, args.top), table(by_def, args.top)
    print("samples  instr.  line")
    for e in lines:
        path, line = e["at"]
        text_line = source_line(resolve(path, roots), line).strip()[:80]
        print(f"{e['samples']:6.1%} {e['instructions']:6.1%}  {os.path.basename(path)}:{line:<5} {text_line}")
    print("samples  instr.  function")
    for e in defs:
        print(f"{e['samples']:6.1%} {e['instructions']:6.1%}  {e['at'][0]}:{e['at'][1]}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"kernel": name, "differ": differ, "level": args.level, "lines": lines, "functions": defs}, f,
                      indent=1)  # fmt: skip


if __name__ == "__main__":
    main()
