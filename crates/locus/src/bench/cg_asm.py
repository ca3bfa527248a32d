#!/usr/bin/env python3
"""A function's self instructions, instruction by instruction, from callgrind.

`callgrind_annotate` gives a function's cost by source line; where the
compiler has inlined, hoisted and interleaved, a line's count says little
about what runs. Run under `valgrind --tool=callgrind --dump-instr=yes`
(for `forward_cost.py`, through `LOCUS_CALLGRIND_ARGS`), this reads the
callgrind files' per-instruction self costs of the functions whose names
match a regular expression, and prints the binary's disassembly (`objdump
-d -l`) over those functions with each instruction's count beside it. The
count of a function's first instruction is its number of calls, so a
block's count over that is how often it ran per call. The expression
should match one function: the calls are read from the lowest address
matched, and the script says when several functions matched.

    python3 crates/locus/src/bench/cg_asm.py BINARY 'region::trace_local' FILE.cg [FILE.cg ...]
        [--min N]    print only instructions executed at least N times
        [--lines]    print self instructions a call by source line instead,
                     in the order the lines first appear
        [--once]     with --lines, only the instructions run exactly once a
                     call (the call's fixed cost: prologue, setup, epilogue)

It needs valgrind's callgrind output and `objdump` (binutils).
"""

import argparse
import collections
import re
import signal
import subprocess
import sys


def self_costs(paths, pattern):
    """Self instructions by address of the functions matching `pattern`, and
    the names that matched."""
    cost = collections.Counter()
    matched = set()
    for path in paths:
        # Names are compressed: `fn=(7) name` defines 7, `fn=(7)` reuses
        # it, and a definition may first appear on a `cfn=` line.
        names = {}
        in_fn = False
        addr = 0
        skip = False
        with open(path) as f:
            for line in f:
                if line.startswith(("fn=", "cfn=")):
                    key = "cfn=" if line.startswith("cfn=") else "fn="
                    m = re.match(re.escape(key) + r"\((\d+)\)(?: (.*))?", line.rstrip("\n"))
                    if m:
                        if m.group(2):
                            names[m.group(1)] = m.group(2)
                        name = names.get(m.group(1), "")
                    else:
                        name = line[len(key):].strip()
                    if key == "fn=":
                        in_fn = bool(pattern.search(name))
                        if in_fn:
                            matched.add(name)
                    continue
                if line.startswith("calls="):
                    # The next cost line is the call's inclusive cost.
                    skip = True
                    continue
                if not line or not (line[0].isdigit() or line[0] in "+-*"):
                    continue
                parts = line.split()
                pos = parts[0]
                if pos.startswith("0x"):
                    addr = int(pos, 16)
                elif pos[0] in "+-":
                    delta = int(pos[1:], 16) if pos[1:].startswith("0x") else int(pos[1:])
                    addr += delta if pos[0] == "+" else -delta
                if skip:
                    skip = False
                    continue
                # `positions: instr line`: address, line, then the cost.
                if in_fn and len(parts) >= 3:
                    cost[addr] += int(parts[2])
    return cost, matched


def disassembly(binary, lo, hi):
    """objdump's lines for [lo, hi): (address or None, text)."""
    out = subprocess.run(
        ["objdump", "-d", "--no-show-raw-insn", "-C", "-l",
         f"--start-address={lo:#x}", f"--stop-address={hi:#x}", binary],
        capture_output=True, text=True, check=True,
    ).stdout
    for line in out.splitlines():
        m = re.match(r"\s*([0-9a-f]+):\s+(.*)", line)
        if m:
            yield int(m.group(1), 16), m.group(2)
        elif line.startswith("/"):
            yield None, line


def main():
    # Piped into `head`, stop quietly.
    signal.signal(signal.SIGPIPE, signal.SIG_DFL)
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("binary")
    ap.add_argument("function", help="regular expression over function names")
    ap.add_argument("files", nargs="+", help="callgrind files made with --dump-instr=yes")
    ap.add_argument("--min", type=int, default=1)
    ap.add_argument("--lines", action="store_true")
    ap.add_argument("--once", action="store_true")
    a = ap.parse_args()
    if a.once and not a.lines:
        ap.error("--once goes with --lines")
    cost, matched = self_costs(a.files, re.compile(a.function))
    if not cost:
        sys.exit(f"no self cost for /{a.function}/ in {a.files}: no function matches, "
                 "or the files were made without valgrind's --dump-instr=yes")
    if len(matched) > 1:
        print(f"note: {len(matched)} functions match, counted together and their calls "
              f"read from the lowest address: {sorted(matched)}", file=sys.stderr)
    lo, hi = min(cost), max(cost) + 16
    calls = cost[lo]
    print(f"{sum(cost.values())} instructions, {calls} calls (the first instruction's count)")
    if not a.lines:
        # A source line is printed once, before the first instruction of
        # its run that is printed.
        pending = None
        for addr, text in disassembly(a.binary, lo, hi):
            if addr is None:
                pending = text
            elif cost.get(addr, 0) >= a.min:
                if pending:
                    print(f"{'':>12}  # {pending}")
                    pending = None
                print(f"{cost.get(addr, 0):>12}  {addr:x}: {text}")
        return
    by_line = collections.Counter()
    where = None
    for addr, text in disassembly(a.binary, lo, hi):
        if addr is None:
            where = text
            continue
        n = cost.get(addr, 0)
        if n and (not a.once or n == calls):
            by_line[where] += n
    for line, n in by_line.items():
        print(f"{n / max(calls, 1):10.1f} a call  {line}")


if __name__ == "__main__":
    main()
